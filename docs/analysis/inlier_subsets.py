"""Which labelled inliers does the pose need? MAGSAC++ (the oracle's fit) on subsets of the ground-truth inliers.

An analysis behind the README's accuracy section, not part of the package. For every validation
pair (shipped weights) the oracle's fit runs on: all labelled inliers; a random 91 % of them (as
many as NM-Net keeps on kitti-07); those NM-Net selects; those mutual NN + ratio 0.8 keep; those
NM-Net scores above 0.1. It prints AUC@5 per sequence (mean over seeds), then how the inliers
NM-Net rejects differ from those it keeps (flow, distance from the image centre, descriptor
ratio, Sampson distance to the ground-truth epipolar geometry).

    python docs/analysis/inlier_subsets.py ../shared/data [--detector hessian-affine] [--seeds 2]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from nmnet_ros.core.detectors import make_detector
from nmnet_ros.core.geometry import pose_auc, pose_error_deg, sampson_px
from nmnet_ros.core.model import load_model
from nmnet_ros.core.model_fast import FastNMNet
from nmnet_ros.core.selectors import DEFAULT_CONFIG, build, classic_mask, nmnet_scores
from nmnet_ros.io.cache import FeatureCache
from nmnet_ros.io.pairs import load_pairs, to_correspondences


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="the ../shared/data folder")
    ap.add_argument("--detector", default="hessian-affine")
    ap.add_argument("--seeds", type=int, default=2)
    args = ap.parse_args()
    specs = [f"{args.data}/kitti-07:120-159", f"{args.data}/strecha-herz-jesus-p25"]
    cache = FeatureCache(make_detector(args.detector))
    model = FastNMNet(load_model(None, "nmnet"))
    fit = build("oracle")  # MAGSAC++ + the pose polish on c.labels, as in nmnet eval
    subsets = ("all inliers", "random 91 %", "NM-Net's", "mutual+ratio's", "NM-Net score > 0.1")
    for spec in specs:
        errors: dict[str, list] = {s: [] for s in subsets}
        stats: dict[str, list] = {k: [] for k in ("flow", "centre", "ratio", "sampson")}
        for p in load_pairs([spec], tuple(range(1, 11)), cache):
            c = to_correspondences(p)
            _, scores, selected = nmnet_scores(model, c, DEFAULT_CONFIG)
            inl = c.labels
            idx = np.flatnonzero(inl)
            for seed in range(args.seeds):
                rng = np.random.default_rng(1000 + seed)
                rand = np.zeros(len(c), bool)
                rand[rng.choice(idx, int(0.91 * len(idx)), replace=False)] = True
                masks = (inl, rand, inl & selected, inl & classic_mask(c), inl & (scores > 0.1))
                for name, m in zip(subsets, masks, strict=True):
                    sel = fit(dataclasses.replace(c, labels=m), seed=seed)
                    errors[name].append(max(pose_error_deg(sel.pose, p.R, p.t)))
            flow = np.linalg.norm(c.k1 - c.k0, axis=1)
            centre = np.abs(c.k0[:, 0] - c.size0[0] / 2) / (c.size0[0] / 2)
            px = sampson_px(p, c.x0, c.x1, c.focal)
            for key, v in zip(stats, (flow, centre, c.ratio, px), strict=True):
                stats[key].append((v[inl & selected], v[inl & ~selected]))
        print(f"\n{spec.rsplit('/', 1)[-1]}: AUC@5 of MAGSAC++ on subsets of the labelled inliers ({args.seeds} seeds)")
        for name in subsets:
            print(f"  {name:20s} {100 * pose_auc(np.array(errors[name]), (5.0,))[0]:.1f}")
        print("  inliers NM-Net keeps vs rejects (median / 90th percentile):")
        for key, parts in stats.items():
            kept = np.concatenate([a for a, _ in parts])
            lost = np.concatenate([b for _, b in parts])
            print(f"    {key:8s} kept {np.median(kept):7.2f} / {np.percentile(kept, 90):7.2f}   "
                  f"rejected {np.median(lost):7.2f} / {np.percentile(lost, 90):7.2f}   ({len(kept)} / {len(lost)} matches)")


if __name__ == "__main__":
    main()
