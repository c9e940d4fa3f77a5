"""Other ways to feed NM-Net's scores to MAGSAC++, on the whole validation split or the training pairs (shipped weights).

An analysis behind the README's accuracy section, not part of the package. Each variant picks the
matches MAGSAC++ samples from (and, for some, another set the pose polish runs over); AUC@5 per
sequence, mean over seeds, and the paired difference to ``ratio+magsac``:

    python docs/analysis/robust_variants.py ../shared/data [--detector hessian-affine] [--seeds 3] [--pairs train]

``--pairs train``: the 105 training pairs of the threshold study (docs/accuracy.md), where a variant has to win
before validation is looked at.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable, Iterator

import numpy as np

from nmnet_ros.core.detectors import make_detector
from nmnet_ros.core.geometry import PoseEstimate, pose_error_deg
from nmnet_ros.core.model import load_model
from nmnet_ros.core.model_fast import FastNMNet
from nmnet_ros.core.selectors import DEFAULT_CONFIG, Correspondences, classic_mask, nmnet_scores, robust_fit
from nmnet_ros.io.cache import FeatureCache
from nmnet_ros.io.pairs import PairData, load_pairs, to_correspondences
from nmnet_ros.tools.evaluate import paired_auc_difference, per_sequence_table

CFG = DEFAULT_CONFIG


def magsac(c: Correspondences, fit: np.ndarray, polish: np.ndarray, seed: int, prosac: bool) -> PoseEstimate | None:
    """The package's MAGSAC++ on c[fit] (``prosac``: sampled in that order), its pose polished on c[polish]."""
    return robust_fit(c, fit, "magsac", {**CFG, "seed": seed}, polish, prosac).pose


def by_score(s: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Indices of the masked matches, highest score first (PROSAC's order)."""
    i = np.flatnonzero(mask)
    return i[np.argsort(-s[i], kind="stable")]


def subset(c: Correspondences, idx: np.ndarray) -> Correspondences:
    """The correspondences c[idx]."""
    arrays = ("k0", "k1", "a0", "a1", "x0", "x1", "ratio", "mutual")
    return dataclasses.replace(c, **{f: getattr(c, f)[idx] for f in arrays}, labels=None if c.labels is None else c.labels[idx])


def second_pass(c: Correspondences, s: np.ndarray, t: float, rescore: Callable[[Correspondences], np.ndarray]) -> np.ndarray:
    """Indices the network keeps when run again on its own selection (neighbours mined among the selected matches)."""
    idx = np.flatnonzero(s > t)
    return idx[rescore(subset(c, idx)) > t] if len(idx) >= 16 else idx


U, P = False, True  # uniform / PROSAC sampling


def cut_at(u: float) -> Callable:
    """The variant that hands MAGSAC++ the matches scored above ``u`` instead of the calibrated cut."""
    return lambda c, s, t, _: (np.flatnonzero(s > u),) * 2 + (U,)


# name -> (c, scores, calibrated cut, the network's scores of other correspondences)
#      -> (indices MAGSAC++ samples from, indices the polish runs over, PROSAC?)
Variant = Callable[[Correspondences, np.ndarray, float, Callable], tuple[np.ndarray, np.ndarray, bool]]
VARIANTS: dict[str, Variant] = {
    "ratio+magsac": lambda c, s, t, _: (np.flatnonzero(classic_mask(c)),) * 2 + (U,),
    "nmnet+magsac": lambda c, s, t, _: (np.flatnonzero(s > t),) * 2 + (U,),
    "PROSAC by score": lambda c, s, t, _: (by_score(s, s > t),) * 2 + (P,),
    "PROSAC, cut 0.5": lambda c, s, t, _: (by_score(s, s > 0.5),) * 2 + (P,),
    **{f"cut {u}": cut_at(u) for u in (0.8, 0.9)},
    "fit >0.9, polish >cut": lambda c, s, t, _: (np.flatnonzero(s > 0.9), np.flatnonzero(s > t), U),
    "fit top 150, polish all": lambda c, s, t, _: (by_score(s, s > t)[:150], np.flatnonzero(s > t), U),
    "fit top 300, polish all": lambda c, s, t, _: (by_score(s, s > t)[:300], np.flatnonzero(s > t), U),
    "fit top half, polish all": lambda c, s, t, _: (by_score(s, s > t)[: max(50, int(np.sum(s > t)) // 2)],
                                                  np.flatnonzero(s > t), U),
    "union with mutual+ratio": lambda c, s, t, _: (np.flatnonzero((s > t) | classic_mask(c)),) * 2 + (U,),
    **{f"cut {u}": cut_at(u) for u in (0.2, 0.3, 0.4, 0.5)},
    "second pass on the selection": lambda c, s, t, rescore: (second_pass(c, s, t, rescore),) * 2 + (U,),
    "fit >cut, polish both kept": lambda c, s, t, _: (np.flatnonzero(s > t), np.flatnonzero((s > t) & classic_mask(c)), U),
    "fit >cut, polish mutual+ratio": lambda c, s, t, _: (np.flatnonzero(s > t), np.flatnonzero(classic_mask(c)), U),
    "fit both kept, polish >cut": lambda c, s, t, _: (np.flatnonzero((s > t) & classic_mask(c)), np.flatnonzero(s > t), U),
    "fit mutual+ratio, polish >cut": lambda c, s, t, _: (np.flatnonzero(classic_mask(c)), np.flatnonzero(s > t), U),
}
SPLITS = {"val": (("kitti-07:120-159", None), ("strecha-herz-jesus-p25", None)),
          "train": (("strecha-fountain-p11", 50), ("strecha-entry-p10", 50), ("kitti-07:0-119", 50))}


def arguments(doc: str, detector: str, pairs: str) -> argparse.Namespace:
    """The command line these analyses share: the data folder, the frames, the seeds, the split."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("data", help="the ../shared/data folder")
    ap.add_argument("--detector", default=detector)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--pairs", choices=sorted(SPLITS), default=pairs, help="the validation split or the training pairs")
    return ap.parse_args()


def split_pairs(args: argparse.Namespace, model: FastNMNet) -> Iterator[tuple[str, PairData, Correspondences, np.ndarray]]:
    """Every pair of ``args.pairs``: its sequence's name, the pair, its correspondences and NM-Net's scores."""
    cache = FeatureCache(make_detector(args.detector))
    for name_range, max_pairs in SPLITS[args.pairs]:
        spec = f"{args.data}/{name_range}"
        for p in load_pairs([spec], tuple(range(1, 11)), cache, max_pairs=max_pairs):
            c = to_correspondences(p)
            yield spec.rsplit("/", 1)[-1], p, c, nmnet_scores(model, c, CFG)[1]


def main() -> None:
    args = arguments(__doc__, "hessian-affine", "val")
    model = FastNMNet(load_model(None, "nmnet"))
    errors: dict[str, list] = {v: [] for v in VARIANTS}
    groups = []

    def rescore(c: Correspondences) -> np.ndarray:
        return nmnet_scores(model, c, CFG)[1]

    for group, p, c, scores in split_pairs(args, model):
        for name, variant in VARIANTS.items():
            fit, polish, prosac = variant(c, scores, model.score_threshold, rescore)
            errors[name].append([max(pose_error_deg(magsac(c, fit, polish, s, prosac), p.R, p.t))
                                 for s in range(args.seeds)])
        groups.append(group)
    e = {k: np.array(v) for k, v in errors.items()}
    print(per_sequence_table(e, groups, "ratio+magsac"))
    print(f"\n{args.pairs} pairs ({len(groups)} x {args.seeds} seeds), AUC@5 minus ratio+magsac's:")
    for name in VARIANTS:
        if name != "ratio+magsac":
            d, lo, hi = paired_auc_difference(e[name], e["ratio+magsac"])
            print(f"  {name}: {d:+.2f} [{lo:+.2f}, {hi:+.2f}]")


if __name__ == "__main__":
    main()
