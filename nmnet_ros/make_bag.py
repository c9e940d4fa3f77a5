"""``nmnet make-bag SEQ_DIR OUT [--format mcap|sqlite3|ros1] [--compressed]``."""

from __future__ import annotations

import argparse
from pathlib import Path

from .bags import FORMATS, make_bag
from .pairs import parse_seq_spec


def add_arguments(p: argparse.ArgumentParser) -> None:
    """CLI options of ``nmnet make-bag``."""
    p.add_argument("seq", metavar="SEQ_DIR[:a-b]", help="sequence folder (optional frame range)")
    p.add_argument("out", type=Path, help="output: ROS 2 bag directory (mcap, sqlite3) or .bag file (ros1)")
    p.add_argument("--format", choices=FORMATS, default="mcap")
    p.add_argument("--compressed", action="store_true", help="JPEG sensor_msgs/CompressedImage instead of Image")


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet make-bag``."""
    path, frames = parse_seq_spec(args.seq)
    n = make_bag(path, args.out, args.format, args.compressed, frames)
    print(f"wrote {n} frames to {args.out}")
    return 0
