"""Neighbour mining for NM-Net: compatibility-specific (paper Eq. 2-5) and spatial kNN.

With T = [[A, k], [0, 0, 1]], a correspondence's local transformation H_i = T'_i T_i^-1 is
affine: H_i x = M_i x + b_i with M_i = A'_i A_i^-1 and b_i = k'_i - M_i k_i, so H_i(k_i) = k'_i
and the error e_j(c_i) = |H_j(k_i) - k'_i|_1 (L1, pixels, as the authors' code) is a small
affine expression per pair. Ranking by e_j(c_i) + e_i(c_j) equals ranking by the score
s = exp(-lambda (e_j + e_i)); each correspondence is its own first neighbour. The all-pairs
search runs as one fused numba kernel (errors and top-k per row, rows across cores).
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from .jit import launch

CHUNK = 256  # rows per block of the spatial kNN: keeps the CHUNK x N distance block in cache
_BLOCK = 32  # rows per parallel task of the compatibility kernel (one row buffer per task)


def local_transforms(k0: np.ndarray, a0: np.ndarray, k1: np.ndarray, a1: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """M (N,2,2) and b (N,2) of H_i = T'_i T_i^-1 for each correspondence."""
    a0t = torch.as_tensor(np.asarray(a0, np.float32))
    a1t = torch.as_tensor(np.asarray(a1, np.float32))
    k0t = torch.as_tensor(np.asarray(k0, np.float32))
    k1t = torch.as_tensor(np.asarray(k1, np.float32))
    m = a1t @ torch.linalg.inv(a0t)
    b = k1t - (m @ k0t[..., None])[..., 0]
    return m, b


@numba.njit(parallel=True, fastmath=True, cache=True, boundscheck=False)
def _mine_kernel(x, y, u, v, m00, m01, m10, m11, b0, b1, out):  # pragma: no cover - compiled
    """out[i] = the k smallest e_j(c_i) + e_i(c_j) over j, ascending, with i itself first.

    One fused pass per row (the error row, then an insertion top-k over it) instead of
    writing the N x N error matrix to memory and sorting it: ~3.5x faster than blocked GEMMs.
    """
    n, k = out.shape
    for blk in numba.prange((n + _BLOCK - 1) // _BLOCK):
        row = np.empty(n, np.float32)
        best = np.empty(k, np.float32)
        for i in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            xi, yi, ui, vi = x[i], y[i], u[i], v[i]
            c00, c01, c10, c11, d0, d1 = m00[i], m01[i], m10[i], m11[i], b0[i], b1[i]
            for j in range(n):  # vectorised by LLVM: e_j(c_i) + e_i(c_j), L1 in pixels
                row[j] = (abs(m00[j] * xi + m01[j] * yi + b0[j] - ui) + abs(m10[j] * xi + m11[j] * yi + b1[j] - vi)
                          + abs(c00 * x[j] + c01 * y[j] + d0 - u[j]) + abs(c10 * x[j] + c11 * y[j] + d1 - v[j]))
            row[i] = -1.0  # self first
            for q in range(k):
                best[q] = np.inf
                out[i, q] = i
            for j in range(n):
                e = row[j]
                if e < best[k - 1]:  # strict: among equal errors the lower index stays first (stable)
                    p = k - 1
                    while p > 0 and best[p - 1] > e:
                        best[p] = best[p - 1]
                        out[i, p] = out[i, p - 1]
                        p -= 1
                    best[p] = e
                    out[i, p] = j


def warm_up() -> None:
    """Compile (or load from numba's disk cache) and start the mining kernel's threads now, so the
    first frame pair does not pay for it (compiling takes ~2 s, loading ~0.3 s)."""
    eye = np.tile(np.eye(2, dtype=np.float32), (9, 1, 1))
    pts = np.arange(18, dtype=np.float32).reshape(9, 2)
    compatibility_neighbors(pts, eye, pts + 1, eye)


def _check(n: int, k: int, *arrays: np.ndarray) -> int:
    for a in arrays:
        if len(a) != n:
            raise ValueError(f"correspondence arrays disagree in length: {[len(x) for x in arrays]}")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    return min(k, n)


def compatibility_neighbors(k0: np.ndarray, a0: np.ndarray, k1: np.ndarray, a1: np.ndarray, k: int = 8) -> np.ndarray:
    """Indices (N, k) of each correspondence's k most compatible ones, itself first.

    k0, k1: (N,2) matched keypoints; a0, a1: (N,2,2) their affine frames. When N < k, the
    missing slots repeat the correspondence itself. Runs on torch's thread count (see
    :mod:`nmnet_ros.core.jit`). The first call in a process compiles the kernel (numba caches it on disk afterwards).
    """
    n = len(k0)
    kk = _check(n, k, a0, k1, a1)
    if n == 0:
        return np.zeros((0, k), np.int64)
    m, b = (t.numpy() for t in local_transforms(k0, a0, k1, a1))
    p0 = np.asarray(k0, np.float32)
    p1 = np.asarray(k1, np.float32)
    cols = [p0[:, 0], p0[:, 1], p1[:, 0], p1[:, 1], m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1], b[:, 0], b[:, 1]]
    out = np.empty((n, kk), np.int64)
    launch(_mine_kernel, *(np.ascontiguousarray(c) for c in cols), out)
    return _pad(out, k)


@torch.inference_mode()
def spatial_neighbors(k0: np.ndarray, k1: np.ndarray, k: int = 8) -> np.ndarray:
    """Indices (N, k) of the k nearest correspondences in 4-D (x, y, x', y') pixel space, itself first."""
    n = len(k0)
    kk = _check(n, k, k1)
    if n == 0:
        return np.zeros((0, k), np.int64)
    x = torch.as_tensor(np.concatenate([k0, k1], 1).astype(np.float32))
    out = torch.empty((n, kk), dtype=torch.int64)
    for s in range(0, n, CHUNK):
        e = slice(s, min(s + CHUNK, n))
        d = torch.cdist(x[e], x)
        d[torch.arange(e.stop - e.start), torch.arange(e.start, e.stop)] = -1.0
        out[e] = d.topk(kk, dim=1, largest=False, sorted=True).indices
    return _pad(out.numpy(), k)


def _pad(idx: np.ndarray, k: int) -> np.ndarray:
    if idx.shape[1] == k:
        return idx
    fill = np.repeat(idx[:, :1], k - idx.shape[1], axis=1)
    return np.concatenate([idx, fill], 1)


def compatibility_neighbors_loop(k0: np.ndarray, a0: np.ndarray, k1: np.ndarray, a1: np.ndarray, k: int = 8) -> np.ndarray:
    """Paper Eq. 2-5 written literally, one correspondence at a time (benchmark baseline, tests).

    Builds the 3x3 T and H = T' T^-1 of every correspondence and applies rho (projective
    division); used to check the vectorised :func:`compatibility_neighbors`.
    """
    n = len(k0)
    kk = _check(n, k, a0, k1, a1)
    if n == 0:
        return np.zeros((0, k), np.int64)
    T0 = np.zeros((n, 3, 3))
    T1 = np.zeros((n, 3, 3))
    T0[:, :2, :2], T0[:, :2, 2], T0[:, 2, 2] = a0, k0, 1.0
    T1[:, :2, :2], T1[:, :2, 2], T1[:, 2, 2] = a1, k1, 1.0
    H = T1 @ np.linalg.inv(T0)  # (N,3,3)
    p0 = np.c_[np.asarray(k0, np.float64), np.ones(n)]
    p1 = np.asarray(k1, np.float64)
    out = np.empty((n, kk), np.int64)
    for i in range(n):
        hj_ki = H @ p0[i]  # H_j [k_i; 1] for every j: (N,3)
        e_ji = np.abs(hj_ki[:, :2] / hj_ki[:, 2:] - p1[i]).sum(1)
        hi_kj = p0 @ H[i].T  # H_i [k_j; 1] for every j
        e_ij = np.abs(hi_kj[:, :2] / hi_kj[:, 2:] - p1).sum(1)
        err = e_ji + e_ij
        err[i] = -1.0
        part = np.argpartition(err, kk - 1)[:kk] if kk < n else np.arange(n)
        out[i] = part[np.argsort(err[part], kind="stable")]
    return _pad(out, k)


def mine_neighbors(kind: str, k0: np.ndarray, a0: np.ndarray, k1: np.ndarray, a1: np.ndarray, k: int = 8) -> np.ndarray:
    """Neighbour indices for NM-Net (``compatibility``) or NM-Net-sp (``spatial``)."""
    if kind == "compatibility":
        return compatibility_neighbors(k0, a0, k1, a1, k)
    if kind == "spatial":
        return spatial_neighbors(k0, k1, k)
    raise ValueError(f"unknown neighbour kind {kind!r}; use 'compatibility' or 'spatial'")
