"""``nmnet train``: fit NM-Net on sequence folders with ground-truth poses.

Features are cached per image; putative matches are every keypoint's nearest neighbour (the
paper's setting); labels are the squared symmetric epipolar distance < 1e-4 (normalised; ``--label-threshold``).
Each step samples ``batch`` pairs and ``num_corr`` correspondences per pair, mines the
neighbours on that sample, and minimises balanced BCE (positives weighted by N_neg/N_pos).
The best checkpoint by validation F-measure is kept; ``last.pt`` makes a run resumable.
``--augment`` swaps, mirrors and rolls the training pairs (same labels) against overfitting;
``--thin-inliers`` lowers some samples' inlier ratio to that of wide-baseline pairs;
``--turn-deg`` pans/tilts the second camera (labels recomputed) for the large rotations of turns.
``--balance`` gives small folders (the wide-baseline Strecha scenes) a larger share of the samples.
``--ess-loss`` adds Yi et al.'s essential-matrix regression (not in NM-Net's paper) to the classification loss.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import torch

from ..core.detectors import make_detector
from ..core.geometry import apply_homography, eight_point_rows, essential_from_pose, homography_jacobian
from ..core.metrics import prf
from ..core.model import DEFAULT_CONFIG as NETWORK_CONFIG
from ..core.model import NEIGHBORS, NMNet, WeightsError, load_model, network_input
from ..core.neighbors import mine_neighbors
from ..core.settings import FRONTEND_DEFAULTS
from ..io.cache import FeatureCache
from ..io.datasets import LABEL_THRESHOLD, MAX_VIEW_ANGLE_DEG, Sequence, pose_labels
from ..io.outputs import output_folder, replace_atomically, write_json, written_by
from ..io.pairs import PairData, load_pairs, pair_frames, parse_seq_spec, shared_frames
from . import fleet
from .options import MAX_ROLL_DEG, MIN_THINNED_RATIO, TRAIN_DEFAULTS

DEFAULT_CONFIG: dict = {
    **TRAIN_DEFAULTS,
    "gaps": (1, 2, 3, 4, 5, 6, 7, 8, 9, 10),
    "max_view_angle": MAX_VIEW_ANGLE_DEG,  # pairs whose optical axes are further apart (degrees) are left out
    "min_inliers": 5,
    "detector": FRONTEND_DEFAULTS["detector"],  # local feature frames: the node's (the shipped steps 0-2 used "hessian-affine")
    "max_keypoints": FRONTEND_DEFAULTS["max_keypoints"],  # keypoints per frame: the node's max_keypoints
    "init": None,  # checkpoint to start from (fine-tuning); None = random initialisation
    "augment": False,  # label-preserving pair augmentation (see ``draw_augmentation``)
    "ratio_input": False,  # give the network each match's descriptor distance ratio as a fifth input (see ``_init_model``)
}
MAX_TURN_DEG = 60.0  # --turn-deg above this would turn most views out of the image


def _labelled_pairs(specs: list[str], cache: FeatureCache, c: dict, log: Callable[[str], None],
                    role: str = "train") -> list[PairData]:
    """The pairs of ``specs`` with this run's gaps and labels, those with almost no inliers dropped; a folder without
    pairs is a warning (another may have some). ``role`` (train, val) names the folders' lines in the log."""
    return load_pairs(specs, tuple(c["gaps"]), cache, min_inliers=c["min_inliers"], label_threshold=c["label_threshold"],
                      skip_empty=True, log=lambda line: log(f"  {line}"), tool=role, max_view_angle=c["max_view_angle"])


PARALLEL_FRAMES = 32  # frames to compute before Ray's start (seconds) pays; fewer: the loaders compute them in turn


def _fill(detector: str, max_keypoints: int, root: Path, folder: str, frames: list[int]) -> int:
    """A Ray task: the features of ``folder``'s ``frames`` into the cache at ``root``; how many were computed."""
    return FeatureCache(make_detector(detector, {"max_keypoints": max_keypoints}), root).fill(Sequence.load(folder), frames)


def prepare_features(specs: list[str], cache: FeatureCache, c: dict, log: Callable[[str], None]) -> None:
    """Compute the features that the folders' pairs need and ``cache`` lacks, one Ray task per folder (a local
    runtime, or $RAY_ADDRESS's cluster with the cache on shared storage), when two or more folders lack
    :data:`PARALLEL_FRAMES` or more in all; the loaders then read them. Every folder is read here first: one that
    is none (a fleet's report.json among ``labelled/*``) or lacks a range's frames stops the run before any work."""
    missing: dict[str, tuple[str, list[int]]] = {}  # spec: (its folder, absolute; the frames it lacks)
    for spec in dict.fromkeys(specs):
        seq, frames = pair_frames(spec, tuple(c["gaps"]), c["max_view_angle"])
        if lacking := [k for k in frames if not cache.path(seq, k).is_file()]:
            missing[spec] = (str(seq.root.resolve()), lacking)
    total = sum(len(frames) for _, frames in missing.values())
    if len(missing) < 2 or total < PARALLEL_FRAMES:
        return
    log(f"features: {total} frames of {len(missing)} folders, in parallel (one Ray task per folder)")
    t0 = time.perf_counter()
    common = (c["detector"], c["max_keypoints"], cache.root.resolve())
    done, interrupted = fleet.map_tasks(_fill, missing, common=common, what="train: features", unit="folder")
    if interrupted:
        raise KeyboardInterrupt
    log(f"features: {sum(n for n in done.values() if isinstance(n, int))} computed in {time.perf_counter() - t0:.0f} s")


def pair_weights(group_sizes: list[int], balance: float) -> np.ndarray | None:
    """Sampling probability of each training pair, folder by folder, or None for uniform over pairs.

    A folder with n pairs gets a share proportional to n ** (1 - balance): 0 keeps every pair
    equally likely (a long sequence dominates), 1 gives every folder the same share, values in
    between temper the long ones (the temperature sampling of multi-corpus training).
    """
    if balance == 0:
        return None
    sizes = np.asarray([n for n in group_sizes if n > 0], dtype=float)
    share = sizes ** (1.0 - balance)
    return np.repeat(share / share.sum() / sizes, sizes.astype(int))


def draw_augmentation(rng: np.random.Generator) -> tuple[bool, bool, float, float]:
    """(swap the images, mirror both, roll of image 0, roll of image 1 in radians) for one training sample.

    Each is a valid two-view geometry with the same labels: swapping is the reverse motion, a
    mirror image is the mirrored scene, a roll rotates a camera about its optical axis. All are
    isometries of the normalised image planes, so symmetric epipolar distances (the labels) are
    unchanged; the neighbours are not (a swap or roll changes about half of the compatibility
    neighbour sets, measured), so they are mined on the augmented keypoints and affine frames.
    """
    swap, mirror = rng.random(2) < 0.5
    roll0, roll1 = np.radians(rng.uniform(-MAX_ROLL_DEG, MAX_ROLL_DEG, 2))
    return bool(swap), bool(mirror), float(roll0), float(roll1)


def sample_correspondences(rng: np.random.Generator, labels: np.ndarray, size: int, thin: float = 0.0) -> np.ndarray:
    """Indices of ``size`` correspondences of a pair for one training sample.

    Uniform over the pair's matches; with probability ``thin`` the sample keeps only part of the
    inliers instead, its inlier ratio drawn uniformly between MIN_THINNED_RATIO and the pair's own.
    The outliers stay real nearest-neighbour mismatches: the sample looks like a wider-baseline
    pair, whose inlier ratios (5-13 % on the hardest validation pairs) the training pairs rarely
    reach (mean 36 %). The labels are the pair's, unchanged.
    """
    n = len(labels)
    ratio = float(np.mean(labels)) if n else 0.0
    if thin <= 0 or ratio <= MIN_THINNED_RATIO or rng.random() >= thin:
        return rng.choice(n, size=size, replace=n < size)
    pos, neg = np.flatnonzero(labels), np.flatnonzero(~np.asarray(labels, bool))
    n_pos = max(1, round(rng.uniform(MIN_THINNED_RATIO, ratio) * size))
    # never more negatives than the pair has: a repeated match is its own twin, a perfectly compatible
    # neighbour no real pair has (the ratio is then the lowest the pair allows)
    n_neg = min(size - n_pos, len(neg)) if n >= size else size - n_pos
    n_pos = size - n_neg
    return np.concatenate([rng.choice(pos, size=n_pos, replace=len(pos) < n_pos),
                           rng.choice(neg, size=n_neg, replace=len(neg) < n_neg)])


def draw_turn(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """A rotation turning a camera about its centre: axis in the image plane (pan, tilt or both), up to max_deg."""
    phi = rng.uniform(0.0, 2 * np.pi)
    angle = np.radians(rng.uniform(-max_deg, max_deg))
    return cv2.Rodrigues(angle * np.array([np.cos(phi), np.sin(phi), 0.0]))[0]


def turn_camera(pair: PairData, turn: np.ndarray,
                label_threshold: float = LABEL_THRESHOLD) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pair as if its second camera had been turned by ``turn`` about its centre.

    Returns (k1, a1, x1, labels, inside) for every match: turned pixels, affine frames (mapped by
    the Jacobian of the rotation homography K R K^-1 at each keypoint), normalised coordinates,
    labels recomputed from the turned ground truth (R' = turn R, t' = turn t), and which turned
    keypoints still fall inside the image and in front of the camera. A real turn changes the
    relative rotation, not the scene: this is the large rotation of a vehicle turning (kitti-07
    frames 130-142 rotate 32 degrees in 10 frames), which the training pairs rarely show with few
    inliers. Pinhole only: ``train`` refuses --turn-deg on cameras with lens distortion.
    """
    camera = pair.seq.camera
    H = camera.K @ turn @ np.linalg.inv(camera.K)
    k1, w = apply_homography(H, pair.k1)  # w is the turned ray's depth (K's last row is 0 0 1)
    x1 = camera.normalize(k1)
    labels, _ = pose_labels(turn @ pair.R, turn @ pair.t, pair.normalized()[0], x1, label_threshold)
    front = w > 1e-6
    inside = front.copy()
    if camera.width > 0 and camera.height > 0:
        inside &= (k1[:, 0] >= 0) & (k1[:, 0] < camera.width) & (k1[:, 1] >= 0) & (k1[:, 1] < camera.height)
    return k1, homography_jacobian(H, pair.k1) @ pair.a1, x1, labels & front, inside


def draw_sample(rng: np.random.Generator, pair: PairData, c: dict) -> tuple[np.ndarray, tuple | None, tuple | None, np.ndarray]:
    """One training sample of a pair: (match indices, augmentation, turned (k1, a1, x1, turn) or None, their labels).

    Draws in a fixed order from ``rng`` (turn, matches, augmentation), each only when its option
    is on, so runs without an option draw the same stream as before it existed.
    """
    labels, turned, pool = pair.labels, None, None
    if c["turn_deg"] > 0:
        turn = draw_turn(rng, c["turn_deg"])
        k1, a1, x1, turned_labels, inside = turn_camera(pair, turn, c["label_threshold"])
        # the sample stays as it was when the turn leaves too few inliers, or fewer matches than a sample
        # takes, in view (filling it up would repeat matches: twins, perfectly compatible neighbours)
        if turned_labels[inside].sum() >= c["min_inliers"] and inside.sum() >= c["num_corr"]:
            labels, turned, pool = turned_labels, (k1, a1, x1, turn), np.flatnonzero(inside)
    drawn = sample_correspondences(rng, labels if pool is None else labels[pool], c["num_corr"], c["thin_inliers"])
    sel = drawn if pool is None else pool[drawn]
    return sel, draw_augmentation(rng) if c["augment"] else None, turned, labels[sel]


def _roll(angle: float, mirror: bool) -> np.ndarray:
    """2x2 map of an image plane: mirror in x (if asked), then rotate by ``angle``."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]]) @ np.diag([-1.0 if mirror else 1.0, 1.0])


def pair_input(pair: PairData, config: dict, sel: np.ndarray | None = None,
               augmentation: tuple[bool, bool, float, float] | None = None,
               turned: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(1,N,4|5) network input and (1,N,k) neighbour indices of a pair (optionally turned, a subset, augmented).

    ``config``: the model's (neighbour kind, k, whether the ratio is an input).

    ``turned``: the second view's (k1, a1, x1) from ``turn_camera`` for every match of the pair, and the turn.
    """
    x0, x1 = pair.normalized()
    k0, k1, a0, a1, ratio = pair.k0, pair.k1, pair.a0, pair.a1, pair.matches.ratio
    if turned is not None:
        k1, a1, x1 = turned[:3]
    if sel is not None:
        x0, x1, k0, k1, a0, a1, ratio = (v[sel] for v in (x0, x1, k0, k1, a0, a1, ratio))
    if augmentation is not None:
        swap, mirror, roll0, roll1 = augmentation
        if swap:
            x0, x1, k0, k1, a0, a1 = x1, x0, k1, k0, a1, a0
        M0, M1 = _roll(roll0, mirror), _roll(roll1, mirror)
        c = pair.seq.camera.K[:2, 2]  # rolls turn about the principal point (pixels ~ normalised up to fx/fy)
        x0, x1 = x0 @ M0.T, x1 @ M1.T
        k0, k1 = (k0 - c) @ M0.T + c, (k1 - c) @ M1.T + c
        a0, a1 = M0 @ a0, M1 @ a1
    nb = mine_neighbors(config["neighbors"], k0, a0, k1, a1, config["k"])
    return network_input(x0, x1, ratio, config)[None], torch.from_numpy(nb)[None]


def sample_essential(pair: PairData, augmentation: tuple[bool, bool, float, float] | None = None,
                     turned: tuple | None = None) -> np.ndarray:
    """Unit-norm ground-truth essential matrix of a training sample, in the coordinates ``pair_input`` gives the network.

    A turn rotates the second camera (R' = turn R, t' = turn t); a swap transposes E; the mirror and
    rolls map each normalised image plane by an orthogonal M (x' = M x), so E' = H1 E H0^T with H = diag(M, 1).
    """
    R, t = pair.R, pair.t
    if turned is not None:
        R, t = turned[3] @ R, turned[3] @ t
    E = essential_from_pose(R, t)
    if augmentation is not None:
        swap, mirror, roll0, roll1 = augmentation
        if swap:
            E = E.T
        H0, H1 = np.eye(3), np.eye(3)
        H0[:2, :2], H1[:2, :2] = _roll(roll0, mirror), _roll(roll1, mirror)
        E = H1 @ E @ H0.T
    return E / np.linalg.norm(E)


def essential_loss(logits: torch.Tensor, x: torch.Tensor, E_gt: torch.Tensor) -> torch.Tensor:
    """Yi et al. (CVPR 2018)'s regression loss: min(|e - e_gt|^2, |e + e_gt|^2) per sample, averaged.

    e is the unit-norm essential matrix of the eight-point algorithm weighted by relu(tanh(logit)),
    the weights the ``nmnet`` selector estimates its pose with: the term rewards scores that fit the
    true geometry well, beyond telling inliers from outliers. ``x``: (B, N, >=4) network input
    (normalised x, y, x', y'); ``E_gt``: (B, 3, 3) unit-norm, from ``sample_essential``.
    """
    w = torch.relu(torch.tanh(logits)).double()
    X = eight_point_rows(*(x[..., i].double() for i in range(4)), xp=torch)
    XwX = X.transpose(1, 2) @ (X * w[..., None])
    # a sample with fewer than 8 positive weights has no eight-point solution: left out (identity in its place, so
    # the eigen-decomposition's gradient stays finite)
    posed = (w > 0).sum(1) >= 8
    if not posed.any():
        return logits.sum() * 0.0
    XwX = torch.where(posed[:, None, None], XwX, torch.eye(9, dtype=XwX.dtype, device=XwX.device))
    e = torch.linalg.eigh(XwX)[1][..., 0]  # eigenvector of the smallest eigenvalue, unit norm
    g = E_gt.reshape(-1, 9).double()
    d = torch.minimum(((e - g) ** 2).sum(-1), ((e + g) ** 2).sum(-1))
    return d[posed].float().mean()


def balanced_bce(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """BCE on logits with positives weighted by N_neg / N_pos per pair (rows of the batch)."""
    pos = labels.sum(1, keepdim=True).clamp_min(1.0)
    neg = (1 - labels).sum(1, keepdim=True)
    w = torch.where(labels > 0, neg / pos, torch.ones_like(labels))
    return torch.nn.functional.binary_cross_entropy_with_logits(logits, labels, weight=w)


THRESHOLDS = tuple(float(t) for t in np.round(np.arange(0.05, 1.0, 0.05), 2))


@torch.inference_mode()
def validate(model: NMNet, pairs: list[PairData], threshold: float = 0.5) -> dict:
    """Mean per-pair precision/recall/F (percent) of probability > threshold against the labels.

    Also the F at every threshold of THRESHOLDS (``f1_by_threshold``), to calibrate the
    operating point: the balanced loss centres the scores for recall, not for F.
    """
    model.eval()
    dev = next(model.parameters()).device
    probs = []
    for p in pairs:
        x, nb = pair_input(p, model.config)
        probs.append(torch.sigmoid(model(x.to(dev), nb.to(dev))[0]).cpu().numpy())
    stats = [prf(pr > threshold, p.labels) for pr, p in zip(probs, pairs, strict=True)]
    out = {k: float(np.mean([s[k] for s in stats])) for k in ("precision", "recall", "f1")}
    out["f1_by_threshold"] = {t: float(np.mean([prf(pr > t, p.labels)["f1"] for pr, p in zip(probs, pairs, strict=True)]))
                              for t in THRESHOLDS}
    return out


def _save(path: Path, checkpoint: dict) -> None:
    """torch.save through a temporary file of its own: an interrupt while writing leaves the previous checkpoint
    whole, and a save interrupted half-way cannot write into a later one (it wrote into best.pt.tmp, which the
    calibration's save then renamed to best.pt, and corrupted it)."""
    replace_atomically(path, lambda tmp: torch.save(checkpoint, tmp))


def calibrate(out_dir: Path, val_pairs: list[PairData], log: Callable[[str], None] = print) -> dict:
    """Store in best.pt the score threshold that maximises validation F; returns its metrics."""
    ck = torch.load(out_dir / "best.pt", map_location="cpu", weights_only=False)
    model = NMNet(ck["config"])
    model.load_state_dict(ck["state_dict"])
    f_by_t = validate(model, val_pairs)["f1_by_threshold"]
    best_t = max(f_by_t, key=f_by_t.get)
    val = validate(model, val_pairs, best_t)
    val.pop("f1_by_threshold")
    ck.update(score_threshold=float(best_t), val_calibrated=val)
    _save(out_dir / "best.pt", ck)
    log(f"calibrated score threshold {best_t:.2f}: val P {val['precision']:.1f} R {val['recall']:.1f} F {val['f1']:.1f}")
    return {"score_threshold": float(best_t), **{f"val_{k}": v for k, v in val.items()}}


def _git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent, check=False).stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def _init_model(path: Path, kind: str, ratio_input: bool) -> NMNet:
    """The checkpoint to fine-tune from (``load_model``'s checks), refused when trained for other neighbours.

    ``ratio_input`` on a checkpoint trained without it widens the embedding by a zero column: the
    network starts as the checkpoint's, and training decides how much the ratio counts. The reverse
    (dropping an input the checkpoint was trained with) is refused.
    """
    try:
        model = load_model(path)
    except WeightsError as e:
        raise WeightsError(f"--init {e}") from e
    if model.config["neighbors"] != kind:
        raise WeightsError(f"--init {path}: trained with {model.config['neighbors']} neighbours; it does not fit "
                           f"this --variant ({kind} neighbours)")
    if model.config["ratio_input"] == ratio_input:
        return model
    if not ratio_input:
        raise WeightsError(f"--init {path}: trained with the ratio as an input; add --ratio-input")
    wide = NMNet({**model.config, "ratio_input": True})
    state = model.state_dict()
    w = state["embed.0.weight"]
    state["embed.0.weight"] = torch.cat([w, torch.zeros_like(w[..., :1])], -1)
    wide.load_state_dict(state)
    wide.score_threshold = model.score_threshold
    return wide.eval()


def _checked_neighbors(c: dict, train_specs: list[str]) -> str:
    """The neighbour kind of ``c["variant"]``, after checking every training option (ValueError naming the bad one)."""
    if c["variant"] not in NEIGHBORS:
        raise ValueError(f"unknown variant {c['variant']!r}; use one of {sorted(NEIGHBORS)}")
    if not isinstance(c["workers"], int) or c["workers"] < 1:
        raise ValueError(f"--workers must be a whole number >= 1 (threads mining neighbours), got {c['workers']!r}")
    if str(c["device"]).startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"--device {c['device']}: torch {torch.__version__} sees no CUDA GPU here; use --device cpu")
    try:
        torch.empty(1, device=c["device"])  # a name torch does not know, a GPU index past the last, MPS off macOS
    except (RuntimeError, AssertionError) as e:
        first = (str(e).strip() or type(e).__name__).splitlines()[0].split(". ")[0][:200]  # MPS's runs to 2000 chars
        raise ValueError(f"--device {c['device']}: torch cannot use it ({first}); use cpu or cuda (cuda:N for GPU N)") from e
    if c["num_corr"] < NETWORK_CONFIG["k"]:  # fewer: each match's neighbours padded with itself
        raise ValueError(f"--num-corr must be at least k = {NETWORK_CONFIG['k']} (each correspondence's k neighbours, "
                         f"itself first, are mined among the sample's; default {TRAIN_DEFAULTS['num_corr']}), "
                         f"got {c['num_corr']}")
    if not 0 <= c["lr"] < math.inf:  # Adam refused a negative one only after the features
        raise ValueError(f"--lr is Adam's step size, a number >= 0 (default {DEFAULT_CONFIG['lr']:g}; 0 keeps --init's "
                         f"weights: validation and calibration only), got {c['lr']}")
    if not 0 < c["label_threshold"] < 1:
        raise ValueError(f"--label-threshold must be in (0, 1) (squared normalised distance), got {c['label_threshold']}")
    if not 0 <= c["thin_inliers"] <= 1:
        raise ValueError(f"--thin-inliers is a probability in [0, 1], got {c['thin_inliers']}")
    if not 0 <= c["turn_deg"] <= MAX_TURN_DEG:
        raise ValueError(f"--turn-deg must be in [0, {MAX_TURN_DEG:g}] degrees (0 = off), got {c['turn_deg']}")
    if not c["ess_loss"] >= 0:
        raise ValueError(f"--ess-loss is a weight >= 0 (0 = classification loss only), got {c['ess_loss']}")
    if not 0 <= c["balance"] <= 1:
        raise ValueError(f"--balance must be in [0, 1] (0 = pairs equally often, 1 = folders equally often), got {c['balance']}")
    if not 0 < c["max_view_angle"] <= 180:
        raise ValueError(f"--max-view-angle must be in (0, 180] degrees, got {c['max_view_angle']}")
    if c["turn_deg"] > 0:
        for spec in train_specs:
            path = parse_seq_spec(spec)[0]
            if np.any(Sequence.load(path).camera.dist):
                raise ValueError(f"--turn-deg: {path}/camera.yaml has lens distortion; turning is done with the pinhole "
                                 "model, so train on undistorted (rectified) images or without --turn-deg")
    return NEIGHBORS[c["variant"]]


def _step(model: NMNet, opt: torch.optim.Optimizer, pool: ThreadPoolExecutor, batch: list[tuple], c: dict,
          device: torch.device) -> float:
    """One optimiser step on a batch of (pair, *draw_sample(...)) samples; returns the loss."""
    inputs = list(pool.map(lambda b: pair_input(b[0], model.config, b[1], b[2], b[3]), batch))
    ys = [torch.from_numpy(b[4].astype(np.float32))[None] for b in batch]
    x = torch.cat([x for x, _ in inputs]).to(device)
    logits = model(x, torch.cat([nb for _, nb in inputs]).to(device))
    loss = balanced_bce(logits, torch.cat(ys).to(device))
    if c["ess_loss"] > 0:
        E_gt = torch.from_numpy(np.stack([sample_essential(b[0], b[2], b[3]) for b in batch])).to(device)
        loss = loss + c["ess_loss"] * essential_loss(logits, x, E_gt)
    opt.zero_grad()
    loss.backward()
    opt.step()
    return loss.item()


RESUMABLE_CHANGES = {"epochs", "workers", "device", "init"}  # a resumed run may change these freely


def run_record(config: dict, train_specs: list[str], val_specs: list[str]) -> dict:
    """What the run's checkpoints record of it: its options (tuples as the lists a checkpoint gives back) and folders."""
    return {"train_config": {k: list(v) if isinstance(v, tuple) else v for k, v in config.items()}, "train": train_specs,
            "val": val_specs}


def options_changed(checkpoint: dict, record: dict) -> list[str]:
    """'name: then -> now' for each training option a resumed run (its ``run_record``) changes from the checkpoint's
    (a last.pt written before the record: none known)."""
    if "train_config" not in checkpoint:
        return []
    then, now = ({**r["train_config"], "train": r["train"], "val": r["val"]} for r in (checkpoint, record))
    return [f"{k}: {then.get(k)} -> {now[k]}" for k in now if k not in RESUMABLE_CHANGES and then.get(k) != now[k]]


def train(train_specs: list[str], val_specs: list[str], out_dir: Path, config: dict | None = None,
          resume: bool = False, cache_dir: Path | None = None, log: Callable[[str], None] = print) -> dict:
    """Train; writes ``best.pt`` (by validation F), ``last.pt`` and ``history.json`` to out_dir."""
    c = {**DEFAULT_CONFIG, **(config or {})}
    kind = _checked_neighbors(c, train_specs)
    record = run_record(c, train_specs, val_specs)
    if shared := shared_frames(train_specs, val_specs):  # said before any work (features: minutes)
        log(f"warning: --val takes --train's frames ({'; '.join(shared)}): validation F, which picks best.pt and the "
            "score threshold, then rewards memorising them; validate on other frames or scenes "
            "(--train SEQ:0-119 --val SEQ:120-159)")
    torch.manual_seed(c["seed"])
    rng = np.random.default_rng(c["seed"])
    out_dir = Path(out_dir)
    resuming = resume and (out_dir / "last.pt").is_file()  # --init only seeds a run's first start
    earlier = [name for name in ("best.pt", "last.pt") if (out_dir / name).is_file()]
    if earlier and not resuming:  # a new run would replace them after its first epoch: hours of training lost
        raise ValueError(f"{out_dir} holds a training run already ({', '.join(earlier)}): add --resume to continue it "
                         "(from last.pt), or give a new --out")
    if resume and not resuming:
        log(f"--resume: {out_dir / 'last.pt'} does not exist yet, so this is a new run")
    if c["init"] is not None and not resuming:
        model = _init_model(Path(c["init"]), kind, c["ratio_input"])  # checked before any features are computed
        log(f"initialised from {c['init']}")
    else:
        model = NMNet({"neighbors": kind, "ratio_input": c["ratio_input"]})
    if resuming:  # checked before any features are computed, as --init
        ck = torch.load(out_dir / "last.pt", map_location="cpu", weights_only=False)
        try:
            model.load_state_dict(ck["state_dict"])
        except RuntimeError as e:
            raise WeightsError(f"--resume: {out_dir / 'last.pt'} does not fit this run's network; resume with the options "
                               f"it was started with (--ratio-input or not): {str(e).splitlines()[0]}") from e
    inputs = [parse_seq_spec(s)[0] for s in (*train_specs, *val_specs)] + [c["init"] and Path(c["init"])]
    output_folder(out_dir, "--out", "the checkpoints", inputs, ("history.json", "summary.json"))  # before minutes of features
    cache = FeatureCache(make_detector(c["detector"], {"max_keypoints": c["max_keypoints"]}), cache_dir)
    prepare_features([*train_specs, *val_specs], cache, c, log)
    log("loading training pairs")
    groups = [_labelled_pairs([spec], cache, c, log) for spec in train_specs]
    train_pairs = [p for g in groups for p in g]
    if not train_pairs:  # before the validation folders' features
        raise ValueError("no training pairs: check the sequence folders and frame ranges")
    log("loading validation pairs")
    val_pairs = _labelled_pairs(val_specs, cache, c, log, "val")
    if not val_pairs:  # trained, then failed with '[Errno 2] best.pt' at the end of the first epoch (val F nan)
        raise ValueError("no validation pairs: check the --val folders and frame ranges (validation picks best.pt "
                         "and calibrates the score threshold)")
    weights = pair_weights([len(g) for g in groups], c["balance"])
    if len(val_pairs) > c["max_val_pairs"]:
        val_pairs = [val_pairs[i] for i in np.linspace(0, len(val_pairs) - 1, c["max_val_pairs"]).round().astype(int)]

    device = torch.device(c["device"])
    model = model.to(device)
    opt = torch.optim.Adam(model.parameters(), lr=c["lr"])
    out_dir.mkdir(parents=True, exist_ok=True)
    history: list[dict] = []
    start_epoch, best_f = 0, -1.0
    if resuming:
        opt.load_state_dict(ck["optimizer"])
        rng.bit_generator.state = ck["rng"]
        torch.set_rng_state(ck["torch_rng"])
        start_epoch, best_f, history = ck["epoch"] + 1, ck["best_f"], ck["history"]
        log(f"resumed after epoch {start_epoch}, best val F {best_f:.2f}")  # counted from 1, as the epochs' lines
        if start_epoch >= c["epochs"]:
            log(f"--epochs {c['epochs']}: the run has done them all, so none is trained; give more to go on")
        if changed := options_changed(ck, record):
            log(f"warning: resumed with other options than the run was started with ({'; '.join(changed)}): best.pt "
                "is kept while validation F beats the run's best so far, which other --val, --label-threshold or "
                "--detector values make a different measure; start a new --out to compare them")

    meta = {"config": model.config, **record, "commit": _git_commit(), "written_by": written_by()}  # the same for every epoch's checkpoints
    pool = ThreadPoolExecutor(c["workers"])
    t_start = time.time()
    try:
        for epoch in range(start_epoch, c["epochs"]):
            model.train()
            losses = []
            t0 = time.time()
            for _ in range(c["steps_per_epoch"]):
                batch = []  # drawn in order from the seeded generator, whatever the number of workers
                drawn = (rng.integers(len(train_pairs), size=c["batch"]) if weights is None
                         else rng.choice(len(train_pairs), size=c["batch"], p=weights))
                for pi in drawn:
                    batch.append((train_pairs[pi], *draw_sample(rng, train_pairs[pi], c)))
                losses.append(_step(model, opt, pool, batch, c, device))
            val = validate(model, val_pairs)
            val.pop("f1_by_threshold")
            rec = {"epoch": epoch, "loss": float(np.mean(losses)), **{f"val_{k}": v for k, v in val.items()},
                   "epoch_sec": time.time() - t0}
            history.append(rec)
            log(f"epoch {epoch + 1}/{c['epochs']}  loss {rec['loss']:.4f}  val P {val['precision']:.1f} "
                f"R {val['recall']:.1f} F {val['f1']:.1f}  ({rec['epoch_sec']:.0f}s)")
            state = {k: v.cpu() for k, v in model.state_dict().items()}  # loadable without a GPU
            if val["f1"] > best_f:
                best_f = val["f1"]
                _save(out_dir / "best.pt", {"state_dict": state, **meta, "epoch": epoch, "val": val})
            _save(out_dir / "last.pt", {"state_dict": state, **meta, "optimizer": opt.state_dict(), "epoch": epoch,
                                        "best_f": best_f, "history": history, "rng": rng.bit_generator.state,
                                        "torch_rng": torch.get_rng_state()})
            write_json(out_dir / "history.json", {"epochs": history})
    except KeyboardInterrupt:  # Ctrl-C ends a long run: its best.pt still gets the score threshold the tools read
        pool.shutdown(wait=False, cancel_futures=True)
        if (out_dir / "best.pt").is_file():
            log("interrupted: calibrating best.pt's score threshold (seconds; Ctrl-C again to skip it)")
            calibrate(out_dir, val_pairs, log)
        raise
    pool.shutdown()
    summary = {"best_val_f1_at_0.5": best_f, "train_pairs": len(train_pairs), "val_pairs": len(val_pairs),
               "train_minutes": (time.time() - t_start) / 60, "epochs": c["epochs"], **calibrate(out_dir, val_pairs, log)}
    write_json(out_dir / "summary.json", summary)
    return summary


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet train``."""
    keys = ("variant", "epochs", "steps_per_epoch", "batch", "num_corr", "seed", "max_val_pairs", "lr", "device", "workers",
            "detector", "max_keypoints", "label_threshold", "augment", "thin_inliers", "turn_deg", "balance", "ratio_input", "ess_loss",
            "max_view_angle")
    cfg = {k: getattr(args, k) for k in keys}
    cfg["init"] = str(args.init) if args.init else None
    cfg["gaps"] = args.gaps
    summary = train(args.train, args.val, args.out, cfg, resume=args.resume, cache_dir=args.cache)
    print(json.dumps(summary, indent=1))
    return 0
