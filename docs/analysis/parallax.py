"""How much parallax do consecutive frames leave once the rotation is taken out? Behind ``no_motion``'s bound.

An analysis behind ``nmnet_ros/pipeline.py``, not part of the package. The front end (the node's defaults)
runs over each sequence folder frame by frame, as the node would; for every related pair it prints the median
flow of the selected matches, the median parallax (the flow the rotation fitted alone does not explain:
``geometry.fit_rotation``), the ground-truth baseline, and the rotation error of that fit and of the identity.
The summary per sequence: the least parallax and how many pairs came out ``no_motion``. A moving camera must
stay above the bound (``static_parallax_px``: 0.25 px); a standing or only turning one sits far below.

    python docs/analysis/parallax.py ../shared/data/kitti-07 ../shared/data/euroc-v101-cam0
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from nmnet_ros.core.geometry import fit_rotation, rotation_error_deg
from nmnet_ros.core.pipeline import Frontend
from nmnet_ros.io.datasets import Sequence


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="+", type=Path, help="sequence folders (../shared/data format)")
    ap.add_argument("--verbose", action="store_true", help="one line per pair")
    args = ap.parse_args()
    for folder in args.sequences:
        seq = Sequence.load(folder)
        fe = Frontend(seq.camera, {})
        rows = []
        for i in range(len(seq)):
            r = fe.process(seq.image(i), float(i))
            if r.mask is None or not r.mask.any():
                continue
            m = r.mask
            _, angles = fit_rotation(seq.camera.normalize(r.k0[m]), seq.camera.normalize(r.k1[m]))
            R_gt, t_gt = seq.relative_pose(i - 1, i)
            row = (i, r.status, np.median(np.linalg.norm(r.k1[m] - r.k0[m], axis=1)),
                   np.median(angles) * seq.camera.focal, np.linalg.norm(t_gt),
                   rotation_error_deg(r.pose.R, R_gt) if r.pose is not None else np.nan,
                   rotation_error_deg(np.eye(3), R_gt))
            rows.append(row)
            if args.verbose:
                print("{} {}: flow {:.2f} px, parallax {:.2f} px, baseline {:.3f}, rotation error {:.4f} deg "
                      "(identity {:.4f})".format(*row))
        parallax = np.array([r[3] for r in rows])
        still = [r for r in rows if r[1] == "no_motion"]
        print(f"{folder.name}: {len(rows)} pairs, parallax least {parallax.min():.2f} / median {np.median(parallax):.2f} px, "
              f"{len(still)} no_motion" + (f" (rotation error mean {np.nanmean([r[5] for r in still]):.4f} deg, the "
                                          f"identity's {np.mean([r[6] for r in still]):.4f})" if still else ""))


if __name__ == "__main__":
    main()
