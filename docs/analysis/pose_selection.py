"""Fit both ``ratio+magsac`` and ``nmnet+magsac`` per pair and keep the pose more of the matches agree with.

An analysis behind docs/accuracy.md, not part of the package. The two pipelines fail on different
pairs, so a rule that picks the better of their two poses could beat both. Each rule scores a pose
over all nearest-neighbour matches by their Sampson distances; the per-pair best of the two (which
needs the ground truth) is the ceiling. AUC@5 and paired differences to both pipelines:

    python docs/analysis/pose_selection.py ../shared/data [--pairs train|val] [--seeds 3]
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from robust_variants import arguments, magsac, split_pairs

from nmnet_ros.core.geometry import pose_error_deg, sampson_px
from nmnet_ros.core.model import load_model
from nmnet_ros.core.model_fast import FastNMNet
from nmnet_ros.core.selectors import classic_mask
from nmnet_ros.tools.evaluate import paired_auc_difference, per_sequence_table

# name -> (Sampson distances in pixels of all matches, NM-Net's scores, the union of both inputs) -> support
Rule = Callable[[np.ndarray, np.ndarray, np.ndarray], float]
RULES: dict[str, Rule] = {
    "matches within 1 px": lambda px, s, u: np.sum(px < 1.0),
    "scores within 1 px": lambda px, s, u: np.sum(s * (px < 1.0)),
    "MSAC 1 px": lambda px, s, u: np.sum(np.maximum(0.0, 1.0 - px ** 2)),
    "MSAC 1 px, both inputs": lambda px, s, u: np.sum(np.maximum(0.0, 1.0 - px ** 2) * u),
    "MSAC 1 px x score": lambda px, s, u: np.sum(s * np.maximum(0.0, 1.0 - px ** 2)),
}


def main() -> None:
    args = arguments(__doc__, "hessian-affine-fast", "train")
    model = FastNMNet(load_model(None, "nmnet"))
    errors: dict[str, list] = {k: [] for k in ("ratio+magsac", "nmnet+magsac", "best of two (ground truth)", *RULES)}
    groups = []
    for group, p, c, s in split_pairs(args, model):
        inputs = {"ratio+magsac": np.flatnonzero(classic_mask(c)), "nmnet+magsac": np.flatnonzero(s > model.score_threshold)}
        union = np.zeros(len(c))
        union[np.concatenate(list(inputs.values()))] = 1.0
        runs: dict[str, list] = {k: [] for k in errors}
        for seed in range(args.seeds):
            poses = {k: magsac(c, idx, idx, seed, False) for k, idx in inputs.items()}
            err = {k: max(pose_error_deg(pose, p.R, p.t)) for k, pose in poses.items()}
            px = {k: None if pose is None else sampson_px(pose, c.x0, c.x1, c.focal)
                  for k, pose in poses.items()}
            for k in inputs:
                runs[k].append(err[k])
            runs["best of two (ground truth)"].append(min(err.values()))
            for rule, support in RULES.items():
                score = {k: -np.inf if d is None else support(d, s, union) for k, d in px.items()}
                runs[rule].append(err[max(score, key=score.get)])
        for k, v in runs.items():
            errors[k].append(v)
        groups.append(group)
    e = {k: np.array(v) for k, v in errors.items()}
    print(per_sequence_table(e, groups, "nmnet+magsac"))
    print(f"\n{args.pairs} pairs ({len(groups)} x {args.seeds} seeds), AUC@5 minus ratio+magsac's / nmnet+magsac's:")
    for name in e:
        if name != "ratio+magsac":
            diffs = [paired_auc_difference(e[name], e[ref]) for ref in ("ratio+magsac", "nmnet+magsac")]
            print(f"  {name}: " + " / ".join(f"{d:+.2f} [{lo:+.2f}, {hi:+.2f}]" for d, lo, hi in diffs))


if __name__ == "__main__":
    main()
