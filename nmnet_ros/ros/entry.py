"""The ``nmnet_node`` console script: the node, its ``--help`` and ``--version`` without starting ROS, and one line
(not a traceback) when a ROS 2 package is missing."""

from __future__ import annotations

import sys

# top-level packages that come from the ROS 2 wheels (x86_64 Linux) or a sourced ROS 2 installation
ROS_PACKAGES = frozenset({"rclpy", "rcl_interfaces", "builtin_interfaces", "sensor_msgs", "geometry_msgs", "std_msgs",
                          "std_srvs", "diagnostic_msgs", "rosidl_runtime_py", "rpyutils", "rosidl_parser"})


def version() -> str:
    """``nmnet_ros X.Y.Z``, the installed package's version (setup.py and package.xml carry the same, tested)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return f"nmnet_ros {installed('nmnet_ros')}"
    except PackageNotFoundError:
        return "nmnet_ros (not installed: run from a source tree)"


def ros_missing(e: ImportError) -> str | None:
    """What to do when ``e`` is a ROS 2 Python package failing to import (None for any other module)."""
    if not e.name or e.name.split(".")[0] not in ROS_PACKAGES:
        return None
    return (f"the ROS 2 Python package {e.name.split('.')[0]!r} is missing. On x86_64 Linux `make setup` (or `pip install -r "
            "requirements.txt`) installs the ROS 2 Kilted wheels; elsewhere (arm64: Jetson, Raspberry Pi) source your ROS 2 "
            "installation first (`source /opt/ros/kilted/setup.bash`), from a Python of the version it was built for")


NODE_USAGE = """usage: nmnet_node [-h] [--ros-args [-p NAME:=VALUE]... [--params-file FILE] [-r FROM:=TO]...]

NM-Net visual-odometry front end: camera frames in, selected matches and relative pose out.

subscribes  image (sensor_msgs/Image), or image/compressed (sensor_msgs/CompressedImage) with use_compressed:=true;
            camera_info (sensor_msgs/CameraInfo)
publishes   ~/matches (sensor_msgs/PointCloud2: u0 v0 u1 v1 score track_id per selected match; a track's id
            follows its point from message to message),
            ~/relative_pose (geometry_msgs/PoseWithCovarianceStamped: the current camera in the previous one's
            frame, unit translation direction), ~/debug_image (sensor_msgs/Image), /diagnostics
service     ~/reset (std_srvs/srv/Trigger): the next frame starts a new chain

example     nmnet_node --ros-args -r image:=/camera/image_raw -r camera_info:=/camera/camera_info \\
                -p max_keypoints:=1000 --params-file config/nmnet.yaml

parameters (default; range or choices; * = set at start-up only):
"""


def node_help(width: int = 100) -> str:
    """``nmnet_node --help``: how to start the node, its topics and service, every parameter with its default and range."""
    import json
    import textwrap

    from ..interface.params import PARAMS, STARTUP_ONLY

    lines = [NODE_USAGE.rstrip("\n")]
    for name, (default, desc, rng) in PARAMS.items():
        limits = "" if rng is None else "; " + (" | ".join(rng) if isinstance(rng[0], str) else f"{rng[0]} .. {rng[1]}")
        lines.append(f"  {name}{' *' if name in STARTUP_ONLY else ''} ({json.dumps(default)}{limits})")
        lines += textwrap.wrap(desc, width, initial_indent=" " * 6, subsequent_indent=" " * 6)
    return "\n".join(lines) + "\n"


def node_main(args: list[str] | None = None) -> int:
    """Entry point of the ``nmnet_node`` console script: the node, its ``--help`` or ``--version``, or one line
    saying which ROS package is missing or that an argument came before ``--ros-args``."""
    argv = sys.argv if args is None else args
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]  # the arguments before ROS's
    if "-h" in own or "--help" in own:
        print(node_help(), end="")
        return 0
    if "--version" in own:
        print(version())
        return 0
    if own:  # rclpy would ignore them and start the node with the defaults
        print(f"nmnet_node: error: unrecognized arguments: {' '.join(own)}; node settings go after --ros-args, e.g. "
              "nmnet_node --ros-args -p max_keypoints:=1000 -r image:=/camera/image_raw (see nmnet_node --help)",
              file=sys.stderr)
        return 2
    from ..interface.dds import rmw_problem

    if (problem := rmw_problem()) is not None:  # rcl would end the process on importing rclpy
        print(f"nmnet_node: error: {problem}", file=sys.stderr)
        return 2
    try:
        from .node import main
    except ImportError as e:
        if (advice := ros_missing(e)) is None:
            raise
        print(f"nmnet_node: error: {advice}", file=sys.stderr)
        return 2
    return main(args)
