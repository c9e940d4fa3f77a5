"""``nmnet demo``: replay the sample bag shipped inside the package (no ../shared needed).

40 frames of KITTI odometry 07 (frames 120-159, never used for training) as
CompressedImage + CameraInfo + ground-truth PoseStamped. Prints the summary next to the
classic SIFT + ratio + MAGSAC++ pipeline on the same frames and leaves the output .mcap and the
plots in one folder.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from . import replay

SAMPLE_BAG = Path(__file__).parent / "sample" / "kitti07_120-159"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """CLI options of ``nmnet demo``."""
    p.add_argument("--out-dir", type=Path, default=Path("nmnet_demo"), help="folder for the output .mcap, summary and plots")
    p.add_argument("--bag", type=Path, default=SAMPLE_BAG, help="bag to replay (default: the bundled sample)")


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet demo``."""
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    mcap = out / "nmnet_output.mcap"
    mcap.unlink(missing_ok=True)
    print(f"replaying {args.bag} (offline) -> {out}/")
    parser = argparse.ArgumentParser()
    replay.add_arguments(parser)  # the demo is exactly this replay command
    ns = parser.parse_args([str(args.bag), "--out", str(mcap), "--json", str(out / "summary.json"), "--plots", str(out),
                            "--baseline"])
    return replay.main(ns)
