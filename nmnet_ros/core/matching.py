"""Descriptor matching: nearest neighbour (the paper's putative set), ratio test, mutual check.

Unit descriptors (RootSIFT) are ranked by their dot products, one (N, M) GEMM. Where the CPU
multiplies bfloat16 natively that GEMM runs in bfloat16 (~6x the float32 rate here) as a screen:
every bfloat16 similarity is within ``SCREEN_DELTA`` of the float32 one, so the two best of a row
(and the best of a column) are among the entries within twice that of the screened ones; only those
are computed again in float32. Same matches, distances and ratios as the float32 GEMM, to float32
rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch

from .bf16 import PAD, bits_from_f32, f32_from_bits, native_bf16, use_bf16

DEFAULT_CONFIG: dict = {
    "ratio": None,  # Lowe ratio threshold (e.g. 0.8); None keeps every nearest neighbour
    "mutual": False,  # keep only mutual nearest neighbours
    "gemm": "auto",  # similarities: auto (bfloat16 screen where native, else float32), float32, bfloat16
}

# bfloat16 keeps 8 significant bits (unit roundoff u = 2^-8). For unit vectors sum |a_i b_i| <= 1, so
# rounding the inputs moves the dot product by at most 2u + u^2, the float32 sum by < 128 * 2^-24 and
# rounding the result by u (1 + 3u): 3u + 6u^2 + 2^-17 = 0.01181 in all; rounded up.
SCREEN_DELTA = 0.0125


@dataclass
class Matches:
    """Putative correspondences between two feature sets."""

    idx: np.ndarray  # (M, 2) int64 indices into (features0, features1)
    distance: np.ndarray  # (M,) float32 descriptor distance to the nearest neighbour
    ratio: np.ndarray  # (M,) float32 distance ratio nearest / second nearest (1 when undefined)
    mutual: np.ndarray  # (M,) bool: image 1's point has image 0's point as its nearest neighbour too

    def __len__(self) -> int:
        return len(self.idx)

    def subset(self, keep: np.ndarray) -> Matches:
        """The matches selected by a boolean mask or index array."""
        return Matches(self.idx[keep], self.distance[keep], self.ratio[keep], self.mutual[keep])


@numba.njit(inline="always")
def _key(u):  # pragma: no cover - compiled
    """bfloat16 bits -> an unsigned key in the values' order (negatives flipped, positives above)."""
    return u ^ (((u >> np.uint16(15)) * np.uint16(0x7FFF)) | np.uint16(0x8000))


@numba.njit(inline="always")
def _cut(key, delta):  # pragma: no cover - compiled
    """A key at or below that of every bfloat16 value >= (the key's value - 2 delta)."""
    u = key ^ np.uint16(0x8000) if key >= np.uint16(0x8000) else key ^ np.uint16(0xFFFF)
    value = f32_from_bits(np.uint32(u) << np.uint32(16))
    k = _key(np.uint16(bits_from_f32(np.float32(value - 2 * delta)) >> np.uint32(16)))  # truncated: toward 0
    return k - np.uint16(1) if k > np.uint16(0) else k


@numba.njit(fastmath=True, cache=True, boundscheck=False)
def _cuts(s, n, m, delta, row_cut, col_key):  # pragma: no cover - compiled
    """Per row of ``s[:n, :m]``: the key at or above which its two best lie (``row_cut``); ``col_key``: the
    columns' largest keys."""
    for i in range(n):
        m1 = np.uint16(0)
        for j in range(m):
            q = _key(s[i, j])
            m1 = max(m1, q)
            col_key[j] = max(col_key[j], q)
        m2 = np.uint16(0)
        ties = 0
        for j in range(m):
            q = _key(s[i, j])
            m2 = max(m2, q if q < m1 else np.uint16(0))
            ties += q == m1
        row_cut[i] = _cut(m1 if ties > 1 else m2, delta)


@numba.njit(fastmath=True, cache=True, boundscheck=False)
def _column_cuts(col_key, delta):  # pragma: no cover - compiled
    """The key at or above which each column's best lies."""
    out = np.empty(len(col_key), np.uint16)
    for j in range(len(col_key)):
        out[j] = _cut(col_key[j], delta)
    return out


@numba.njit(fastmath=True, cache=True, boundscheck=False)
def _recheck(s, a, b, row_cut, col_cut, nn, best, second, col_best):  # pragma: no cover - compiled
    """The float32 dot products of the entries of ``s`` at or above their row's or column's cut: each
    row's two best (``nn``: the best's column) and each column's best."""
    m = len(b)
    flags = np.zeros(8 * ((m + 7) // 8), np.uint8)
    words = flags.view(np.uint64)
    for j in range(m):
        col_best[j] = -4.0  # below any dot product of unit vectors (no infinities under fastmath)
    for i in range(len(a)):
        cut = row_cut[i]
        for j in range(m):  # a vector pass marks the candidates; they are few, so 8 flags at a time are skipped
            q = _key(s[i, j])
            flags[j] = (q >= cut) | (q >= col_cut[j])
        e1 = e2 = np.float32(-4.0)
        j1 = 0
        for w in range(len(words)):
            if words[w] == 0:
                continue
            for j in range(8 * w, min(8 * w + 8, m)):
                if not flags[j]:
                    continue
                q = _key(s[i, j])
                e = np.float32(0.0)
                for c in range(a.shape[1]):
                    e += a[i, c] * b[j, c]
                if q >= cut:
                    if e > e1:
                        e1, e2, j1 = e, e1, j
                    elif e > e2:
                        e2 = e
                if q >= col_cut[j]:
                    col_best[j] = max(col_best[j], e)
        nn[i], best[i], second[i] = j1, e1, e2


def _screened(d0: np.ndarray, d1: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(two best similarities (N, 2), nearest neighbour (N,), mutual (N,)) of unit descriptors: the
    bfloat16 GEMM (on torch's threads), then one serial pass that marks and re-checks the candidates
    (~4 ms for 2000 x 2000 here; serial kernels compile in 2 s, where one parallel kernel took 11 s)."""
    n, m = len(d0), len(d1)
    pa = torch.zeros(-(-n // PAD) * PAD, d0.shape[1], dtype=torch.bfloat16)
    pb = torch.zeros(-(-m // PAD) * PAD, d1.shape[1], dtype=torch.bfloat16)
    pa[:n], pb[:m] = torch.from_numpy(d0), torch.from_numpy(d1)
    s = (pa @ pb.T).view(torch.uint16).numpy()
    delta = np.float32(SCREEN_DELTA)
    row_cut, col_key = np.empty(n, np.uint16), np.zeros(m, np.uint16)
    _cuts(s, n, m, delta, row_cut, col_key)
    nn, best, second, col_best = np.empty(n, np.int64), np.empty(n, np.float32), np.empty(n, np.float32), np.empty(m, np.float32)
    _recheck(s, np.ascontiguousarray(d0), np.ascontiguousarray(d1), row_cut, _column_cuts(col_key, delta), nn, best,
             second, col_best)
    return torch.from_numpy(np.stack([best, second], 1)), torch.from_numpy(nn), torch.from_numpy(best >= col_best[nn])


def warm_up() -> None:
    """Compile (or load from numba's disk cache) the screening kernels now, so that the first frame pair
    does not pay for it (compiling takes seconds: a live camera would drop frames meanwhile)."""
    if native_bf16():
        d = np.eye(3, 128, dtype=np.float32)
        match_descriptors(d, d, {"gemm": "bfloat16"})


def _empty() -> Matches:
    return Matches(np.zeros((0, 2), np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, bool))


@torch.inference_mode()
def match_descriptors(desc0: np.ndarray, desc1: np.ndarray, config: dict | None = None) -> Matches:
    """Match every descriptor of image 0 to its nearest neighbour in image 1 (L2 distance).

    With ``ratio`` set, keeps matches whose nearest/second-nearest distance ratio is below it;
    with ``mutual``, keeps pairs that are each other's nearest neighbour.
    """
    c = {**DEFAULT_CONFIG, **(config or {})}
    screen = use_bf16(c["gemm"], "matching gemm")
    d0 = np.asarray(desc0, np.float32)
    d1 = np.asarray(desc1, np.float32)
    if d0.ndim != 2 or d1.ndim != 2 or (len(d0) and len(d1) and d0.shape[1] != d1.shape[1]):
        raise ValueError(f"descriptor arrays must be (N,D) with equal D, got {d0.shape} and {d1.shape}")
    if len(d0) == 0 or len(d1) == 0:
        return _empty()
    a, b = torch.from_numpy(d0), torch.from_numpy(d1)
    na, nb = (a * a).sum(1), (b * b).sum(1)
    k = min(2, len(d1))
    if bool(((na - 1).abs() < 1e-3).all() and ((nb - 1).abs() < 1e-3).all()):
        # unit descriptors (RootSIFT): |a-b|^2 = 2 - 2 a.b, so rank the GEMM output directly
        if k == 2 and screen:
            svals, nn1, mutual = _screened(d0, d1)
        else:
            sim = a @ b.T
            svals, inds = sim.topk(k, dim=1)
            nn1 = inds[:, 0]
            mutual = svals[:, 0] >= sim.amax(0)[nn1]  # row's best is its column's best (amax: a fast vertical pass)
        vals = (2.0 - 2.0 * svals).clamp_min_(0).sqrt_()
    else:
        dist = (na[:, None] + nb[None] - 2.0 * (a @ b.T)).clamp_min_(0).sqrt_()
        vals, inds = dist.topk(k, dim=1, largest=False)
        nn1 = inds[:, 0]
        mutual = vals[:, 0] <= dist.amin(0)[nn1]
    d_first = vals[:, 0]
    ratio = vals[:, 0] / vals[:, 1].clamp_min(1e-12) if k == 2 else torch.ones_like(d_first)
    keep = torch.ones(len(d0), dtype=torch.bool)
    if c["ratio"] is not None:
        keep &= ratio < c["ratio"]
    if c["mutual"]:
        keep &= mutual
    i0 = torch.nonzero(keep).squeeze(1)
    idx = torch.stack([i0, nn1[i0]], 1).numpy().astype(np.int64)
    return Matches(idx, d_first[i0].numpy(), ratio[i0].numpy().astype(np.float32), mutual[i0].numpy())
