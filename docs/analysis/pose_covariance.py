"""How large are the published relative pose's errors? Fits ``~/relative_pose``'s covariance on training pairs.

An analysis behind ``nmnet_ros/posemsg.py``, not part of the package. The node's default pipeline
(NM-Net + mutual NN + ratio 0.8 + MAGSAC++ and the polish, shipped weights, fast frames) runs on
every pair; each pose is written as the node publishes it (T_prev_cur: rotation, unit translation
direction) and compared with the ground truth, per axis: the rotation error as a rotation vector
(radians, the previous camera's axes x right, y down, z forward) and the difference of the unit
translation directions. The published sigma is ``a * sqrt(REF_MATCHES / n)`` for n selected matches,
so ``e * sqrt(n / REF_MATCHES)`` should spread as ``a``: ``a`` per axis is fitted robustly (1.4826 x the
median absolute value) on the training pairs, leaving out failures (> 10 degrees). Then on the
validation pairs: the share of errors within 1 and 2 sigma (a Gaussian has 68 and 95 %), with the
fitted ``a`` and with the constants in posemsg.py.

    python docs/analysis/pose_covariance.py ../shared/data
    python docs/analysis/pose_covariance.py ../shared/data --train my_seq_a --val my_seq_b   # your camera's sigmas

The fitted ``a`` are the node's ``pose_sigma_rotation_deg`` (in degrees) and ``pose_sigma_direction``.
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from nmnet_ros.core.detectors import DEFAULT_DETECTOR, make_detector
from nmnet_ros.core.selectors import build
from nmnet_ros.interface.posemsg import DIR_SIGMA, REF_MATCHES, ROT_SIGMA_RAD
from nmnet_ros.io.cache import FeatureCache
from nmnet_ros.io.pairs import load_pairs, to_correspondences

FAILED_DEG = 10.0
AXES = ("x", "y", "z")


def errors(pairs: list, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Per pair: rotation-vector error (rad), translation-direction error, selected matches; and the failures."""
    cv2.setRNGSeed(seed)
    fit = build("nmnet+ratio+magsac")
    rot, trans, n, failed = [], [], [], 0
    for p in pairs:
        sel = fit(to_correspondences(p, with_labels=False))
        if sel.pose is None:
            failed += 1
            continue
        R_pc, R_gt = sel.pose.R.T, p.R.T  # published: the current camera in the previous one's frame
        t_pc = -sel.pose.R.T @ sel.pose.t
        t_gt = -p.R.T @ p.t
        w = cv2.Rodrigues(R_pc @ R_gt.T)[0].ravel()
        dt = t_pc / np.linalg.norm(t_pc) - t_gt / np.linalg.norm(t_gt)
        if np.degrees(np.linalg.norm(w)) > FAILED_DEG or np.degrees(2 * np.arcsin(min(1.0, np.linalg.norm(dt) / 2))) > FAILED_DEG:
            failed += 1
            continue
        rot.append(w)
        trans.append(dt)
        n.append(int(sel.mask.sum()))
    return np.array(rot), np.array(trans), np.array(n), failed


def spread(e: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Per axis, the robust spread of the errors scaled to REF_MATCHES matches."""
    return 1.4826 * np.median(np.abs(e * np.sqrt(n / REF_MATCHES)[:, None]), axis=0)


def coverage(e: np.ndarray, n: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per axis, the share of errors within 1 and 2 of the sigmas a * sqrt(REF_MATCHES / n)."""
    z = np.abs(e) / (a[None, :] * np.sqrt(REF_MATCHES / n)[:, None])
    return 100 * (z < 1).mean(0), 100 * (z < 2).mean(0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="the ../shared/data folder")
    ap.add_argument("--max-pairs", type=int, default=100, help="training pairs per sequence")
    ap.add_argument("--train", nargs="+", metavar="SEQ[:a-b]", help="fit on these sequence folders instead (your camera's)")
    ap.add_argument("--val", nargs="+", metavar="SEQ[:a-b]", help="check the fit on these instead")
    args = ap.parse_args()
    cache = FeatureCache(make_detector(DEFAULT_DETECTOR))
    d = args.data
    train_specs = args.train or [f"{d}/strecha-fountain-p11", f"{d}/strecha-entry-p10", f"{d}/kitti-07:0-119"]
    val_specs = args.val or [f"{d}/kitti-07:120-159", f"{d}/strecha-herz-jesus-p25"]
    train = load_pairs(train_specs, tuple(range(1, 11)), cache, max_pairs=args.max_pairs)
    val = load_pairs(val_specs, tuple(range(1, 11)), cache)
    rot, trans, n, failed = errors(train)
    a_rot, a_dir = spread(rot, n), spread(trans, n)
    print(f"training: {len(n)} poses ({failed} failures > {FAILED_DEG:g} deg left out), selected matches median {np.median(n):.0f}")
    rot_deg, dirs = " / ".join(f"{np.degrees(v):.3f}" for v in a_rot), " / ".join(f"{v:.4f}" for v in a_dir)
    print(f"fitted a at REF_MATCHES = {REF_MATCHES} (x / y / z): rotation {rot_deg} deg, direction {dirs}")
    q = np.quantile(n, [0, 1 / 3, 2 / 3, 1])
    for lo, hi in zip(q[:-1], q[1:], strict=True):
        m = (n >= lo) & (n <= hi)
        print(f"  n {lo:.0f}-{hi:.0f}: median |rotation error| {np.degrees(np.median(np.linalg.norm(rot[m], axis=1))):.3f} deg, "
              f"|direction error| {np.median(np.linalg.norm(trans[m], axis=1)):.4f}")
    vrot, vtrans, vn, vfailed = errors(val)
    print(f"validation: {len(vn)} poses ({vfailed} failures left out)")
    for label, ar, ad in (("fitted", a_rot, a_dir), ("posemsg.py", np.full(3, ROT_SIGMA_RAD), np.full(3, DIR_SIGMA))):
        (r1, r2), (t1, t2) = coverage(vrot, vn, ar), coverage(vtrans, vn, ad)
        rows = [", ".join(f"{x} {u:.0f} / {v:.0f} %" for x, u, v in zip(AXES, a, b, strict=True)) for a, b in ((r1, r2), (t1, t2))]
        print(f"  {label}: within 1 / 2 sigma, rotation {rows[0]}; direction {rows[1]}")


if __name__ == "__main__":
    main()
