"""Matching's bfloat16 screen against the float32 GEMM on every validation pair (docs/speed.md, "Matching").

An analysis, not part of the package. For KITTI-07 frames 120-159 (gaps 1-10) and Strecha
Herz-Jesus, fast Hessian-affine features: counts the matches whose nearest neighbour, mutual flag
or ratio-test decision (0.8) differ between ``gemm: float32`` and ``gemm: bfloat16``, and for each
difference says which of the two float64 agrees with.

    python docs/analysis/matching_screen.py ../shared/data        # about 1 minute
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from nmnet_ros.core.fast_hessaff import FastHessianAffine
from nmnet_ros.core.matching import match_descriptors
from nmnet_ros.io.datasets import Sequence

SPLIT = (("kitti-07", range(120, 160)), ("strecha-herz-jesus-p25", None))


def main(data: Path) -> None:
    det = FastHessianAffine()
    pairs = matches = ratio_flips = 0
    max_distance = 0.0
    agrees = {"float32": 0, "bfloat16": 0, "neither": 0}
    for name, frames in SPLIT:
        seq = Sequence.load(data / name)
        frames = frames if frames is not None else range(len(seq))
        desc = {i: det(seq.image(i)).descriptors for i in frames}
        for i, j in seq.pairs(tuple(range(1, 11)), frames):
            out = {g: match_descriptors(desc[i], desc[j], {"gemm": g}) for g in ("float32", "bfloat16")}
            f, b = out["float32"], out["bfloat16"]
            pairs, matches = pairs + 1, matches + len(f)
            ratio_flips += int(((f.ratio < 0.8) != (b.ratio < 0.8)).sum())
            max_distance = max(max_distance, float(np.abs(f.distance - b.distance).max()))
            differ = np.nonzero((f.idx != b.idx).any(1) | (f.mutual != b.mutual))[0]
            if len(differ) == 0:
                continue
            s = desc[i].astype(np.float64) @ desc[j].astype(np.float64).T
            for k in differ:
                row = f.idx[k, 0]
                truth = (s[row].argmax(), s[:, s[row].argmax()].argmax() == row)  # float64: nearest, mutual
                right = [g for g, m in out.items() if (m.idx[k, 1], bool(m.mutual[k])) == truth]
                agrees[right[0] if len(right) == 1 else "neither"] += 1
                print(f"{name} {i}-{j} row {row}: float32 {f.idx[k, 1]} mutual {f.mutual[k]}, bfloat16 {b.idx[k, 1]} "
                      f"mutual {b.mutual[k]}; float64 {truth[0]} mutual {truth[1]}; "
                      f"gap between the best two (x 1e-7) in the row {1e7 * np.diff(np.sort(s[row])[-2:])[0]:.1f}, "
                      f"in its column {1e7 * np.diff(np.sort(s[:, truth[0]])[-2:])[0]:.1f}")
    print(f"{pairs} pairs, {matches} matches: {sum(agrees.values())} differ in nearest neighbour or mutual flag "
          f"(float64 agrees with float32 {agrees['float32']}, bfloat16 {agrees['bfloat16']}, neither {agrees['neither']}); "
          f"ratio-0.8 decisions differing {ratio_flips}; largest distance difference {max_distance:.1e}")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data"))
