"""Correspondence selectors behind one interface, all starting from the same putative matches.

``nmnet``/``nmnet-sp``: the network's scores, pose by the weighted eight-point on them;
``ratio``, ``gms``, ``lpm``: classic filters, pose by the eight-point on what they keep;
``nn+ransac``/``nn+magsac``: robust essential-matrix fits on every nearest-neighbour match; ``ratio+magsac``: mutual NN +
ratio test then MAGSAC++ (the strongest classic pipeline); ``nmnet+magsac``: MAGSAC++ on the
network's selection; ``nmnet+ratio+magsac``: MAGSAC++ on the matches both NM-Net and mutual NN +
ratio test keep; both NM-Net MAGSAC++ fits take ``ratio+magsac``'s pose where they keep fewer than
``fallback_min_inliers`` matches; ``ratio+poselib``: the classic pre-filter then PoseLib; ``ratio+prosac``: PoseLib
sampling a wider pool in the ratio test's order (PROSAC, no network); ``nmnet+prosac``: the same in NM-Net's order,
the front end's default (level with ``ratio+prosac``, see docs/evaluation.md); ``oracle``: ground-truth inliers +
MAGSAC++ (an upper bound: the labels are chosen by the true pose); ``oracle-pool``: the same on the labelled inliers
of the default's pool only (the ceiling of any cut inside it); ``oracle+prosac``: the default's fit
in the ground truth's order, labelled inliers first (the ceiling of any learned order).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import cv2
import numpy as np
import torch

from .geometry import (
    ROBUST_ESTIMATORS,
    PoseEstimate,
    estimate_pose,
    recover_pose,
    refine_pose,
    robust_threshold,
    weighted_eight_point,
)
from .model import NMNet, load_model, network_input
from .model_fast import FastNMNet, resolve_precision
from .neighbors import mine_neighbors, warm_up
from .settings import FRONTEND_DEFAULTS, METHODS

PROSAC_POOL_RATIO = 0.9  # nmnet+prosac's pool; at 0.8 (the classic pre-filter's) or 0.95 its gain there was gone

DEFAULT_CONFIG: dict = {
    # the settings of core/settings.py that the selectors read, by the same names and defaults
    **{name: FRONTEND_DEFAULTS[name] for name in ("pose_threshold_px", "score_threshold", "pose_refine_iterations",
                                                  "nmnet_precision", "fallback_min_inliers")},
    "ratio": 0.8,
    "max_iters": 10000,  # MAGSAC++/RANSAC iteration cap (they stop earlier once confident)
    "seed": 0,  # MAGSAC++/RANSAC random samples (fixed: the same frames give the same pose)
}


def calibrated_threshold(cfg: dict) -> bool:
    """Whether NM-Net keeps matches above the threshold calibrated with its weights (score_threshold -1 or None)."""
    return cfg["score_threshold"] is None or cfg["score_threshold"] < 0


@dataclass
class Correspondences:
    """Putative matches of one image pair, as every selector sees them."""

    k0: np.ndarray  # (M,2) pixels, image 0
    k1: np.ndarray  # (M,2) pixels, image 1
    a0: np.ndarray  # (M,2,2) affine frames
    a1: np.ndarray
    x0: np.ndarray  # (M,2) normalised (undistorted) coordinates
    x1: np.ndarray
    ratio: np.ndarray  # (M,) nearest/second-nearest descriptor distance ratio
    mutual: np.ndarray  # (M,) bool mutual nearest neighbour
    focal: float  # pixels, converts pixel thresholds to normalised ones
    size0: tuple[int, int]  # (width, height) of image 0
    size1: tuple[int, int]
    labels: np.ndarray | None = None  # ground truth, only the oracles read it

    def __len__(self) -> int:
        return len(self.k0)


@dataclass
class Selection:
    """A selector's output: which matches it keeps, optional scores, and the pose."""

    mask: np.ndarray  # (M,) bool
    scores: np.ndarray | None  # (M,) the order it ranks the matches in, higher first: NM-Net's probabilities, 1 - ratio
    pose: PoseEstimate | None
    candidates: np.ndarray | None = None  # (M,) bool: what a robust fit was given (None: the mask itself)


def _filtered(c: Correspondences, mask: np.ndarray) -> Selection:
    """A filter's selection with the pose from the plain eight-point on what it keeps."""
    E = weighted_eight_point(c.x0, c.x1, mask.astype(np.float64)) if len(c) else None
    return Selection(mask, None, recover_pose(E, c.x0, c.x1, mask) if E is not None else None)


def robust_fit(c: Correspondences, keep: np.ndarray, method: str, cfg: dict, polish: np.ndarray | None = None,
               prosac: bool = False) -> Selection:
    """A robust fit on the kept matches, its pose polished on them (sigma = ``pose_threshold_px``) unless the
    estimator refines its own (PoseLib: ``geometry.ROBUST_ESTIMATORS``).

    ``keep``: a boolean mask or indices (in the order PROSAC samples them, best first, with
    ``prosac``); ``polish``: other matches (mask or indices) to polish the pose over instead.
    """
    keep = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep, np.intp)
    mask = np.zeros(len(c), bool)
    threshold = robust_threshold(method, cfg["pose_threshold_px"], c.focal)
    x0, x1 = c.x0[keep], c.x1[keep]
    est = estimate_pose(x0, x1, method, threshold, max_iters=cfg["max_iters"], seed=cfg["seed"], prosac=prosac)
    if est is None:
        return Selection(mask, None, None)
    pose, inl = est
    if pose is not None and not ROBUST_ESTIMATORS[method].refines_pose:
        p0, p1 = (x0, x1) if polish is None else (c.x0[polish], c.x1[polish])
        pose = refine_pose(pose, p0, p1, cfg["pose_threshold_px"] / c.focal, cfg["pose_refine_iterations"])
    mask[keep[inl]] = True
    candidates = np.zeros(len(c), bool)
    candidates[keep] = True
    return Selection(mask, None, pose, candidates)


def classic_mask(c: Correspondences, cfg: dict = DEFAULT_CONFIG) -> np.ndarray:
    """Mutual nearest neighbour and Lowe's ratio test: the classic pre-filter before MAGSAC++."""
    return c.mutual & (c.ratio < cfg["ratio"])


def prosac_pool(c: Correspondences) -> np.ndarray:
    """The default's pool: the mutual matches of ratio < ``PROSAC_POOL_RATIO`` (a boolean mask)."""
    return c.mutual & (c.ratio < PROSAC_POOL_RATIO)


def prosac_fit(c: Correspondences, order: np.ndarray, cfg: dict) -> Selection:
    """PoseLib with PROSAC over :func:`prosac_pool`, sampled in ``order`` (higher
    first): the samples come from the best-ranked matches first, while the consensus is counted over a pool wider
    than the classic pre-filter's, where the inliers of a hard pair (few, ambiguous) still are."""
    pool = np.flatnonzero(prosac_pool(c))
    return robust_fit(c, pool[np.argsort(-order[pool], kind="stable")], "poselib", cfg, prosac=True)


def ratio_scores(c: Correspondences) -> np.ndarray:
    """The ratio test's order as scores in [0, 1], higher first: 1 - the distance ratio."""
    return 1.0 - c.ratio


def ratio_prosac_select(c: Correspondences, cfg: dict) -> Selection:
    """``prosac_fit`` in the ratio test's order (no network); the order is its scores."""
    scores = ratio_scores(c)
    return replace(prosac_fit(c, scores, cfg), scores=scores)


def nmnet_prosac_select(scored: tuple[np.ndarray, np.ndarray, np.ndarray], c: Correspondences, cfg: dict) -> Selection:
    """``prosac_fit`` in NM-Net's order: the network does not cut, it orders."""
    logits, scores, _ = scored
    sel = prosac_fit(c, logits, cfg)
    return Selection(sel.mask, scores, sel.pose, sel.candidates)


def _true_labels(c: Correspondences) -> np.ndarray:
    """The ground-truth inlier labels (``nmnet eval``'s pairs), or none labelled where the pair has none (frames)."""
    return c.labels if c.labels is not None else np.zeros(len(c), bool)


def nmnet_logits(model: NMNet | FastNMNet, c: Correspondences, neighbors: np.ndarray | None = None) -> np.ndarray:
    """Network logits of every correspondence (neighbours mined as the model was trained, unless given)."""
    if len(c) == 0:
        return np.zeros(0, np.float32)
    nb = neighbors if neighbors is not None else mine_neighbors(model.config["neighbors"], c.k0, c.a0, c.k1, c.a1,
                                                                 model.config["k"])
    x = network_input(c.x0, c.x1, c.ratio, model.config)
    nbt = torch.from_numpy(np.ascontiguousarray(nb, np.int64))
    if isinstance(model, FastNMNet):
        return model(x, nbt).numpy()
    with torch.inference_mode():
        return model(x[None], nbt[None])[0].numpy()


def nmnet_scores(model: NMNet | FastNMNet, c: Correspondences, cfg: dict,
                 neighbors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(logits, probabilities, selection mask at the configured or calibrated threshold)."""
    logits = nmnet_logits(model, c, neighbors)
    scores = 0.5 * (1.0 + np.tanh(0.5 * logits))  # sigmoid without exp overflow
    threshold = model.score_threshold if calibrated_threshold(cfg) else cfg["score_threshold"]
    return logits, scores, scores > threshold


def nmnet_select(model: NMNet | FastNMNet, c: Correspondences, cfg: dict) -> Selection:
    """NM-Net's selection; pose by the eight-point weighted with relu(tanh(logit))."""
    logits, scores, mask = nmnet_scores(model, c, cfg)
    w = np.maximum(np.tanh(logits), 0.0)
    E = weighted_eight_point(c.x0, c.x1, w) if len(c) else None
    pose = recover_pose(E, c.x0, c.x1, mask) if E is not None else None
    return Selection(mask, scores, pose)


def nmnet_magsac_select(scored: tuple[np.ndarray, np.ndarray, np.ndarray], c: Correspondences, cfg: dict,
                        classic: bool = False) -> Selection:
    """MAGSAC++ on NM-Net's selection (``classic``: also mutual NN and ratio test); keeps the network's scores.
    When the fit keeps fewer than ``fallback_min_inliers`` matches, the pose is that of MAGSAC++ on the classic
    pre-filter's matches (where it finds one): on such pairs the network left too little to fit.

    ``scored`` is ``nmnet_scores`` of ``c``. The network scores every nearest-neighbour match, as it
    was trained; the classic test is applied afterwards, so the two filters' rejections add up.
    """
    _, scores, mask = scored
    pre = classic_mask(c, cfg)
    sel = robust_fit(c, mask & pre if classic else mask, "magsac", cfg)
    if sel.mask.sum() < cfg["fallback_min_inliers"]:  # too little of the pair left: the classic pipeline's pose
        fallback = robust_fit(c, pre, "magsac", cfg)
        sel = fallback if fallback.pose is not None else sel
    return Selection(sel.mask, scores, sel.pose, sel.candidates)


# the NM-Net methods that end in a robust fit: the fit, given ``nmnet_scores`` of the pair
SCORED_FITS: dict[str, Callable[[tuple[np.ndarray, np.ndarray, np.ndarray], Correspondences, dict], Selection]] = {
    "nmnet+magsac": nmnet_magsac_select, "nmnet+ratio+magsac": partial(nmnet_magsac_select, classic=True),
    "nmnet+prosac": nmnet_prosac_select}


def _remember_last(f: Callable[[Correspondences], tuple]) -> Callable[[Correspondences], tuple]:
    """``f`` remembering its result for the last correspondences it saw (reruns with other seeds reuse it)."""
    last: list = [None, None]

    def g(c: Correspondences) -> tuple:
        if last[0] is not c:
            last[:] = [c, f(c)]
        return last[1]
    return g


def gms_mask(c: Correspondences) -> np.ndarray:
    """Grid-based motion statistics (cv2.xfeatures2d.matchGMS) on the putative matches."""
    if len(c) == 0:
        return np.zeros(0, bool)
    kp0 = [cv2.KeyPoint(float(x), float(y), 1.0) for x, y in c.k0]
    kp1 = [cv2.KeyPoint(float(x), float(y), 1.0) for x, y in c.k1]
    dm = [cv2.DMatch(i, i, 0.0) for i in range(len(c))]
    kept = cv2.xfeatures2d.matchGMS(c.size0, c.size1, kp0, kp1, dm, withRotation=False, withScale=False,
                                    thresholdFactor=6.0)
    mask = np.zeros(len(c), bool)
    mask[[m.queryIdx for m in kept]] = True
    return mask


def lpm_mask(c: Correspondences, rounds: tuple[tuple[int, float], ...] = ((6, 0.8), (4, 0.5)), tau: float = 0.2) -> np.ndarray:
    """Locality Preserving Matching (Ma et al., IJCV 2019).

    A match is kept when its K spatial neighbours in image 0 are mostly also its neighbours in
    image 1 and move consistently (cosine of motion vectors x length ratio > tau). Two rounds;
    the second searches neighbours among the first round's survivors.
    """
    n = len(c)
    keep = np.ones(n, bool)
    if n < 8:
        return np.zeros(n, bool)
    motion = c.k1 - c.k0
    for K, lam in rounds:
        ref = np.flatnonzero(keep)
        if len(ref) <= K:
            return np.zeros(n, bool)
        k = K + 1
        t0 = torch.cdist(torch.as_tensor(c.k0, dtype=torch.float32), torch.as_tensor(c.k0[ref], dtype=torch.float32))
        t1 = torch.cdist(torch.as_tensor(c.k1, dtype=torch.float32), torch.as_tensor(c.k1[ref], dtype=torch.float32))
        n0 = ref[t0.topk(k, largest=False).indices.numpy()]
        n1 = ref[t1.topk(k, largest=False).indices.numpy()]
        cost = np.zeros(n)
        for i in range(n):
            a = n0[i][n0[i] != i][:K]
            b = n1[i][n1[i] != i][:K]
            common = np.intersect1d(a, b, assume_unique=True)
            cost[i] = K - len(common)
            if len(common):
                vi, vj = motion[i], motion[common]
                ni, nj = np.linalg.norm(vi), np.linalg.norm(vj, axis=1)
                cos = (vj @ vi) / np.maximum(ni * nj, 1e-9)
                ratio = np.minimum(ni, nj) / np.maximum(np.maximum(ni, nj), 1e-9)
                cost[i] += np.sum(cos * ratio <= tau)
        keep = cost / K <= lam
    return keep


def build(name: str, config: dict | None = None, weights: dict[str, str] | None = None) -> Callable[..., Selection]:
    """The selector called ``name``: ``select(c)`` -> Selection.

    The methods in ``ROBUST`` also take ``select(c, seed=s)``: the same pair with other random
    samples (NM-Net runs once per pair, only the robust stage is redone).
    """
    cfg = {**DEFAULT_CONFIG, **(config or {})}
    dtype = resolve_precision(cfg["nmnet_precision"])  # a bad choice is refused by every method
    weights = weights or {}
    nmnet = name in NETWORK
    variant = "nmnet-sp" if name == "nmnet-sp" else "nmnet"
    for other, path in weights.items():
        if path and not (nmnet and other == variant):
            load_model(path, other)  # unused by this method, but a bad file is refused now, not on a later switch

    def at(seed: int | None) -> dict:
        return cfg if seed is None else {**cfg, "seed": seed}

    if nmnet:
        net = load_model(weights.get(variant), variant)
        if calibrated_threshold(cfg) and not net.calibrated:
            warnings.warn(f"{weights.get(variant)}: no calibrated score threshold (a training run stopped before its "
                          "end, or its last.pt), so NM-Net keeps the matches above 0.5: finish the run (nmnet train "
                          "--resume) or set score_threshold", stacklevel=2)
        model = FastNMNet(net, dtype)
        model.config["k"] = cfg.get("k", model.config["k"])
        if model.config["neighbors"] == "compatibility":
            warm_up()  # the mining kernel's compile / cache load happens here, not on the first frame pair
        if name in SCORED_FITS:
            scored, fit = _remember_last(lambda c: nmnet_scores(model, c, cfg)), SCORED_FITS[name]
            return lambda c, seed=None: fit(scored(c), c, at(seed))
        return lambda c: nmnet_select(model, c, cfg)
    table: dict[str, Callable[..., Selection]] = {
        "ratio": lambda c: replace(_filtered(c, c.ratio < cfg["ratio"]), scores=ratio_scores(c)),
        "nn+ransac": lambda c, seed=None: robust_fit(c, np.ones(len(c), bool), "ransac", at(seed)),
        "nn+magsac": lambda c, seed=None: robust_fit(c, np.ones(len(c), bool), "magsac", at(seed)),
        "ratio+magsac": lambda c, seed=None: robust_fit(c, classic_mask(c, cfg), "magsac", at(seed)),
        "ratio+poselib": lambda c, seed=None: robust_fit(c, classic_mask(c, cfg), "poselib", at(seed)),
        "ratio+prosac": lambda c, seed=None: ratio_prosac_select(c, at(seed)),
        "gms": lambda c: _filtered(c, gms_mask(c)),
        "lpm": lambda c: _filtered(c, lpm_mask(c)),
        "oracle": lambda c, seed=None: robust_fit(c, _true_labels(c), "magsac", at(seed)),
        "oracle-pool": lambda c, seed=None: robust_fit(c, _true_labels(c) & prosac_pool(c), "magsac", at(seed)),
        # labelled inliers first, each group in the ratio's order
        "oracle+prosac": lambda c, seed=None: prosac_fit(c, 2.0 * _true_labels(c) - c.ratio, at(seed)),
    }
    if name not in table:
        raise ValueError(f"unknown method {name!r}; choose from {', '.join(METHODS)}")
    return table[name]


ROBUST = ("ratio+magsac", "ratio+poselib", "ratio+prosac", "nn+ransac", "nn+magsac", "nmnet+magsac", "nmnet+ratio+magsac",
          "nmnet+prosac", "oracle", "oracle-pool", "oracle+prosac")  # end in a seeded robust fit
NETWORK = ("nmnet", "nmnet-sp", "nmnet+magsac", "nmnet+ratio+magsac", "nmnet+prosac")  # run NM-Net
GROUND_TRUTH = ("oracle", "oracle-pool", "oracle+prosac")  # read each match's ground-truth label: nmnet eval only
