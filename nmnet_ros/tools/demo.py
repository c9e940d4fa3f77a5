"""``nmnet demo``: replay the sample bag shipped inside the package (no ../shared needed).

40 frames of KITTI odometry 07 (frames 120-159, never used for training) as
CompressedImage + CameraInfo + ground-truth PoseStamped. First live: the bag is played onto
ROS 2 topics into ``nmnet_node`` (its own process) and the node's outputs are recorded and
scored; then offline, frame by frame, next to the classic SIFT + ratio + MAGSAC++ pipeline on the
same frames, with the plots. Everything lands in one folder. Without ROS 2 (no rclpy: arm64 with no
ROS installation sourced), or in a ROS environment the node cannot run in (an RMW_IMPLEMENTATION the wheels lack),
the live part is skipped with a note saying what to do.
"""

from __future__ import annotations

import argparse

from ..io.outputs import output_folder, written_here
from ..ros.entry import ros_missing
from . import options, replay


def live_blocked() -> str | None:
    """Why the live part cannot run here, or None: the ROS environment (an RMW_IMPLEMENTATION not installed, whose
    rclpy import would end the demo, a ROS_DOMAIN_ID ROS cannot use, discovery off), rclpy or a message package
    missing. The offline part runs either way."""
    from .live import require_ros

    try:
        require_ros()
    except ValueError as e:
        return str(e)
    except ImportError as e:
        return ros_missing(e)
    return None


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet demo``."""
    out = args.out
    output_folder(out, "--out", "the demo's outputs", [args.bag])
    out.mkdir(parents=True, exist_ok=True)
    parser = argparse.ArgumentParser()
    options.replay(parser)  # the demo is exactly these two replay commands
    live = out / "nmnet_live.mcap"
    if live.is_file() and written_here(live):  # an earlier demo's: not left beside this one's other outputs
        live.unlink()
    if (missing := live_blocked()) is not None:
        print(f"1/2 live: skipped: {missing}")
    else:
        print(f"1/2 live: playing {args.bag} at {args.rate}x into nmnet_node -> {live}")
        rc = replay.main(parser.parse_args([str(args.bag), "--out", str(live), "--json", str(out / "live_summary.json"),
                                            "--live", "--rate", str(args.rate)]))
        if rc:
            return rc
    mcap = out / "nmnet_output.mcap"
    if mcap.is_file() and written_here(mcap):
        mcap.unlink()
    print(f"\n2/2 offline, every frame, with the SIFT + ratio + MAGSAC++ baseline -> {out}/")
    return replay.main(parser.parse_args([str(args.bag), "--out", str(mcap), "--json", str(out / "summary.json"),
                                          "--plots", str(out), "--baseline"]))
