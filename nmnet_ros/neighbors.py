"""Neighbour mining for NM-Net: compatibility-specific (paper Eq. 2-5) and spatial kNN.

With T = [[A, k], [0, 0, 1]], a correspondence's local transformation H_i = T'_i T_i^-1 is
affine: H_i x = M_i x + b_i with M_i = A'_i A_i^-1 and b_i = k'_i - M_i k_i, so H_i(k_i) = k'_i
and the error e_j(c_i) = |H_j(k_i) - k'_i|_1 (L1, pixels, as the authors' code) is one small
matrix product for all pairs. Ranking by e_j(c_i) + e_i(c_j) equals ranking by the score
s = exp(-lambda (e_j + e_i)); each correspondence is its own first neighbour.
"""

from __future__ import annotations

import threading

import numpy as np
import torch

CHUNK = 256  # rows per block: keeps the two CHUNK x N buffers in cache (2048: 22 ms, 256: 16 ms at N=2000)


def local_transforms(k0: np.ndarray, a0: np.ndarray, k1: np.ndarray, a1: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """M (N,2,2) and b (N,2) of H_i = T'_i T_i^-1 for each correspondence."""
    a0t = torch.as_tensor(np.asarray(a0, np.float32))
    a1t = torch.as_tensor(np.asarray(a1, np.float32))
    k0t = torch.as_tensor(np.asarray(k0, np.float32))
    k1t = torch.as_tensor(np.asarray(k1, np.float32))
    m = a1t @ torch.linalg.inv(a0t)
    b = k1t - (m @ k0t[..., None])[..., 0]
    return m, b


_LOCAL = threading.local()  # one workspace per thread: training mines a batch in parallel threads


def _workspace(size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Two reusable float buffers of at least ``size`` elements, private to the calling thread.

    Freshly allocated multi-MB buffers are page-faulted on first touch, which costs more than
    the arithmetic here; keeping them alive between frames removes that.
    """
    ws = getattr(_LOCAL, "buffers", None)
    if ws is None or ws[0].numel() < size:
        ws = _LOCAL.buffers = (torch.empty(size), torch.empty(size))
    return ws


def _check(n: int, k: int, *arrays: np.ndarray) -> int:
    for a in arrays:
        if len(a) != n:
            raise ValueError(f"correspondence arrays disagree in length: {[len(x) for x in arrays]}")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    return min(k, n)


@torch.inference_mode()
def compatibility_neighbors(k0: np.ndarray, a0: np.ndarray, k1: np.ndarray, a1: np.ndarray, k: int = 8) -> np.ndarray:
    """Indices (N, k) of each correspondence's k most compatible ones, itself first.

    k0, k1: (N,2) matched keypoints; a0, a1: (N,2,2) their affine frames. When N < k, the
    missing slots repeat the correspondence itself.
    """
    n = len(k0)
    kk = _check(n, k, a0, k1, a1)
    if n == 0:
        return np.zeros((0, k), np.int64)
    m, b = local_transforms(k0, a0, k1, a1)
    p0 = torch.as_tensor(np.asarray(k0, np.float32))
    p1 = torch.as_tensor(np.asarray(k1, np.float32))
    ones = torch.ones(n, 1)
    # (H_j k_i - k'_i)_r = [k_i, 1, -k'_ir] . [M_j[r], b_jr, 1]: a rank-4 product per coordinate r
    lhs = [torch.cat([p0, ones, -p1[:, r : r + 1]], 1) for r in range(2)]  # (N,4), indexed by i
    rhs = [torch.cat([m[:, r, :], b[:, r : r + 1], ones], 1) for r in range(2)]  # (N,4), indexed by j
    lhs_t = [x.T.contiguous() for x in lhs]  # contiguous (4,N) operands keep the GEMM on its fast path
    rhs_t = [x.T.contiguous() for x in rhs]
    out = torch.empty((n, kk), dtype=torch.int64)
    err, term = _workspace(min(CHUNK, n) * n)
    for s in range(0, n, CHUNK):
        e = slice(s, min(s + CHUNK, n))
        er, tr = err[: (e.stop - e.start) * n].view(-1, n), term[: (e.stop - e.start) * n].view(-1, n)
        # er[i, j] = e_j(c_i) + e_i(c_j) for i in the chunk, all j
        torch.mm(lhs[0][e], rhs_t[0], out=er).abs_()
        for a, bt in ((lhs[1], rhs_t[1]), (rhs[0], lhs_t[0]), (rhs[1], lhs_t[1])):
            er += torch.mm(a[e], bt, out=tr).abs_()
        er[torch.arange(e.stop - e.start), torch.arange(e.start, e.stop)] = -1.0  # self first
        # non-negative float32 order = int32 order of the bits (self is -1: smallest either way); int topk is faster
        out[e] = er.view(torch.int32).topk(kk, dim=1, largest=False, sorted=True).indices
    return _pad(out.numpy(), k)


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
