"""Descriptor matching: nearest neighbour (the paper's putative set), ratio test, mutual check."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

DEFAULT_CONFIG: dict = {
    "ratio": None,  # Lowe ratio threshold (e.g. 0.8); None keeps every nearest neighbour
    "mutual": False,  # keep only mutual nearest neighbours
}


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


def _empty() -> Matches:
    return Matches(np.zeros((0, 2), np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, bool))


@torch.inference_mode()
def match_descriptors(desc0: np.ndarray, desc1: np.ndarray, config: dict | None = None) -> Matches:
    """Match every descriptor of image 0 to its nearest neighbour in image 1 (L2 distance).

    With ``ratio`` set, keeps matches whose nearest/second-nearest distance ratio is below it;
    with ``mutual``, keeps pairs that are each other's nearest neighbour.
    """
    c = {**DEFAULT_CONFIG, **(config or {})}
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
        sim = a @ b.T
        svals, inds = sim.topk(k, dim=1)
        vals = (2.0 - 2.0 * svals).clamp_min_(0).sqrt_()
        mutual = svals[:, 0] >= sim.amax(0)[inds[:, 0]]  # row's best is its column's best (amax: a fast vertical pass)
    else:
        dist = (na[:, None] + nb[None] - 2.0 * (a @ b.T)).clamp_min_(0).sqrt_()
        vals, inds = dist.topk(k, dim=1, largest=False)
        mutual = vals[:, 0] <= dist.amin(0)[inds[:, 0]]
    nn1 = inds[:, 0]
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
