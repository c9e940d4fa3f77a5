"""``nmnet neighbors``: the paper's Fig. 3 on our data.

For every pair, the inlier ratio among the neighbours (self excluded) of ground-truth inliers,
for compatibility-specific neighbours vs spatial kNN, grouped by the pair's inlier ratio.
"""

from __future__ import annotations

import argparse

import numpy as np

from ..core.detectors import make_detector
from ..core.neighbors import compatibility_neighbors, spatial_neighbors
from ..io.cache import FeatureCache
from ..io.outputs import output_file, write_json
from ..io.pairs import PairData, load_pairs, parse_seq_spec

BUCKETS = ((0, 20), (20, 35), (35, 50), (50, 101))


def neighbor_inlier_ratios(pair: PairData, k: int = 8) -> tuple[float, float]:
    """(compatibility, spatial) inlier ratio among the k-1 neighbours of the inliers."""
    lab = pair.labels
    if lab.sum() == 0:
        return float("nan"), float("nan")
    comp = compatibility_neighbors(pair.k0, pair.a0, pair.k1, pair.a1, k)
    spat = spatial_neighbors(pair.k0, pair.k1, k)
    return float(lab[comp[lab, 1:]].mean()), float(lab[spat[lab, 1:]].mean())


def study(pairs: list[PairData], k: int = 8) -> dict:
    """Per-pair rows and the bucket table."""
    rows = []
    for p in pairs:
        c, s = neighbor_inlier_ratios(p, k)
        rows.append({"seq": p.seq.name, "i": p.i, "j": p.j, "inlier_ratio": 100 * float(p.labels.mean()),
                     "compatibility": 100 * c, "spatial": 100 * s})
    table = []
    for lo, hi in BUCKETS:
        sel = [r for r in rows if lo <= r["inlier_ratio"] < hi]
        if sel:
            table.append({"bucket": f"{lo}-{min(hi, 100)}%", "pairs": len(sel),
                          "compatibility": float(np.mean([r["compatibility"] for r in sel])),
                          "spatial": float(np.mean([r["spatial"] for r in sel]))})
    wins = [r["compatibility"] > r["spatial"] for r in rows]
    return {"rows": rows, "table": table, "pairs": len(rows),
            "compat_wins_percent": 100 * float(np.mean(wins)) if rows else 0.0,
            "compatibility_mean": float(np.mean([r["compatibility"] for r in rows])) if rows else 0.0,
            "spatial_mean": float(np.mean([r["spatial"] for r in rows])) if rows else 0.0}


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet neighbors``."""
    output_file(args.json, "--json", "neighbors.json", [parse_seq_spec(s)[0] for s in args.seqs])
    cache = FeatureCache(make_detector(args.detector, {"max_keypoints": args.max_keypoints}), args.cache)
    pairs = load_pairs(args.seqs, args.gaps, cache, stride=args.stride, tool="neighbors")  # eval's pairs, notes, reasons
    res = study(pairs, args.k)
    print("| pair inlier ratio | pairs | compatibility nbrs inlier % | spatial kNN inlier % |")
    print("|---|---|---|---|")
    for r in res["table"]:
        print(f"| {r['bucket']} | {r['pairs']} | {r['compatibility']:.1f} | {r['spatial']:.1f} |")
    print(f"\n{res['pairs']} pairs; compatibility higher in {res['compat_wins_percent']:.1f}% of pairs; "
          f"mean {res['compatibility_mean']:.1f}% vs {res['spatial_mean']:.1f}%")
    if args.json:
        write_json(args.json, res)
    return 0
