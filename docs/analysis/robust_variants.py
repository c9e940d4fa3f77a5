"""Other ways to feed NM-Net's scores to MAGSAC++, on the whole validation split (shipped weights).

An analysis behind the README's accuracy section, not part of the package. Each variant picks the
matches MAGSAC++ samples from (and, for some, a larger set the pose polish runs over); AUC@5 per
sequence, mean over seeds, and the paired difference to ``ratio+magsac``:

    python docs/analysis/robust_variants.py ../shared/data [--detector hessian-affine] [--seeds 3]
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

import numpy as np

from nmnet_ros.cache import FeatureCache
from nmnet_ros.detectors import make_detector
from nmnet_ros.evaluate import load_eval_pairs, paired_auc_difference, per_sequence_table
from nmnet_ros.geometry import PoseEstimate, pose_error_deg
from nmnet_ros.model import load_model
from nmnet_ros.model_fast import FastNMNet
from nmnet_ros.pairs import to_correspondences
from nmnet_ros.selectors import DEFAULT_CONFIG, Correspondences, classic_mask, nmnet_scores, robust_fit

CFG = DEFAULT_CONFIG


def magsac(c: Correspondences, fit: np.ndarray, polish: np.ndarray, seed: int, prosac: bool) -> PoseEstimate | None:
    """The package's MAGSAC++ on c[fit] (``prosac``: sampled in that order), its pose polished on c[polish]."""
    return robust_fit(c, fit, "magsac", {**CFG, "seed": seed}, polish, prosac).pose


def by_score(s: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Indices of the masked matches, highest score first (PROSAC's order)."""
    i = np.flatnonzero(mask)
    return i[np.argsort(-s[i], kind="stable")]


U, P = False, True  # uniform / PROSAC sampling
# name -> (c, scores, calibrated cut) -> (indices MAGSAC++ samples from, indices the polish runs over, PROSAC?)
Variant = Callable[[Correspondences, np.ndarray, float], tuple[np.ndarray, np.ndarray, bool]]
VARIANTS: dict[str, Variant] = {
    "ratio+magsac": lambda c, s, t: (np.flatnonzero(classic_mask(c)),) * 2 + (U,),
    "nmnet+magsac": lambda c, s, t: (np.flatnonzero(s > t),) * 2 + (U,),
    "PROSAC by score": lambda c, s, t: (by_score(s, s > t),) * 2 + (P,),
    "PROSAC, cut 0.5": lambda c, s, t: (by_score(s, s > 0.5),) * 2 + (P,),
    "cut 0.8": lambda c, s, t: (np.flatnonzero(s > 0.8),) * 2 + (U,),
    "cut 0.9": lambda c, s, t: (np.flatnonzero(s > 0.9),) * 2 + (U,),
    "fit >0.9, polish >cut": lambda c, s, t: (np.flatnonzero(s > 0.9), np.flatnonzero(s > t), U),
    "fit top 150, polish all": lambda c, s, t: (by_score(s, s > t)[:150], np.flatnonzero(s > t), U),
    "fit top 300, polish all": lambda c, s, t: (by_score(s, s > t)[:300], np.flatnonzero(s > t), U),
    "fit top half, polish all": lambda c, s, t: (by_score(s, s > t)[: max(50, int(np.sum(s > t)) // 2)],
                                                  np.flatnonzero(s > t), U),
    "union with mutual+ratio": lambda c, s, t: (np.flatnonzero((s > t) | classic_mask(c)),) * 2 + (U,),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="the ../shared/data folder")
    ap.add_argument("--detector", default="hessian-affine")
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    model = FastNMNet(load_model(None, "nmnet"))
    cache = FeatureCache(make_detector(args.detector))
    errors: dict[str, list] = {v: [] for v in VARIANTS}
    groups = []
    for spec in (f"{args.data}/kitti-07:120-159", f"{args.data}/strecha-herz-jesus-p25"):
        for p in load_eval_pairs([spec], tuple(range(1, 11)), cache):
            c = to_correspondences(p)
            _, scores, _ = nmnet_scores(model, c, CFG)
            for name, variant in VARIANTS.items():
                fit, polish, prosac = variant(c, scores, model.score_threshold)
                errors[name].append([max(pose_error_deg(magsac(c, fit, polish, s, prosac), p.R, p.t))
                                     for s in range(args.seeds)])
            groups.append(spec.rsplit("/", 1)[-1])
    e = {k: np.array(v) for k, v in errors.items()}
    print(per_sequence_table(e, groups, "ratio+magsac"))
    print(f"\nwhole split ({len(groups)} pairs x {args.seeds} seeds), AUC@5 minus ratio+magsac's:")
    for name in VARIANTS:
        if name != "ratio+magsac":
            d, lo, hi = paired_auc_difference(e[name], e["ratio+magsac"])
            print(f"  {name}: {d:+.2f} [{lo:+.2f}, {hi:+.2f}]")


if __name__ == "__main__":
    main()
