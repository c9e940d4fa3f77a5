"""``nmnet demo``: the front end on the sample shipped inside the package (no ../shared needed).

Runs every frame of the bundled KITTI-07 excerpt through :class:`Frontend` and prints, per
frame, keypoints, putative and selected matches, the relative pose and its error against the
ground truth that ships with the sample.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from .datasets import Sequence
from .geometry import pose_error_deg
from .pipeline import Frontend

SAMPLE = Path(__file__).parent / "sample" / "kitti07"


def run(seq_dir: Path = SAMPLE, selector: str = "nmnet") -> list[dict]:
    """Process the sequence frame by frame; one summary dict per frame after the first."""
    seq = Sequence.load(seq_dir)
    fe = Frontend(seq.camera, {"selector": selector})
    rows = []
    for i in range(len(seq)):
        r = fe.process(seq.image(i), float(seq.stamps[i]))
        if r.status == "first_frame":
            continue
        row = {"frame": i, "status": r.status, "keypoints": r.num_keypoints, "matches": len(r.k0),
               "selected": r.num_selected, "timings_ms": {k: round(v, 1) for k, v in r.timings_ms.items()}}
        if r.pose is not None:
            rvec = cv2.Rodrigues(r.pose.R)[0].ravel()
            row["rotation_deg"] = float(np.degrees(np.linalg.norm(rvec)))
            row["t_dir"] = [round(float(x), 3) for x in r.pose.t]
            if seq.poses is not None:
                R_gt, t_gt = seq.relative_pose(i - 1, i)
                row["rot_err_deg"], row["trans_err_deg"] = pose_error_deg(r.pose, R_gt, t_gt)
        rows.append(row)
    return rows


def add_arguments(p: argparse.ArgumentParser) -> None:
    """CLI options of ``nmnet demo``."""
    p.add_argument("--seq", type=Path, default=SAMPLE, help="sequence folder (default: the bundled sample)")
    p.add_argument("--selector", default="nmnet", help="correspondence selector (see nmnet eval --help)")
    p.add_argument("--json", type=Path, default=None, help="also write the per-frame summary as JSON")


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet demo``."""
    rows = run(args.seq, args.selector)
    for r in rows:
        line = (f"frame {r['frame']}: {r['status']:<8} {r['keypoints']} keypoints, {r['matches']} matches, "
                f"{r['selected']} selected")
        if "rotation_deg" in r:
            line += f", rotation {r['rotation_deg']:.2f} deg, t direction {r['t_dir']}"
        if "rot_err_deg" in r:
            line += f"  (error vs ground truth: rot {r['rot_err_deg']:.2f} deg, trans {r['trans_err_deg']:.2f} deg)"
        print(line)
        print("   stage ms: " + ", ".join(f"{k} {v}" for k, v in r["timings_ms"].items()))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0
