"""The ``nmnet`` command: one entry point, one subcommand per tool."""

from __future__ import annotations

import argparse
import importlib
import math
import os
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

# top-level packages that come from the ROS 2 wheels (x86_64 Linux) or a sourced ROS 2 installation
ROS_PACKAGES = frozenset({"rclpy", "rcl_interfaces", "builtin_interfaces", "sensor_msgs", "geometry_msgs", "std_msgs",
                          "std_srvs", "diagnostic_msgs", "rosidl_runtime_py", "rpyutils", "rosidl_parser"})

# subcommand -> (module, help); each module has add_arguments(parser) and main(args) -> int
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("nmnet_ros.demo", "the bundled sample bag live through the node, then offline beside SIFT; scores and plots"),
    "train": ("nmnet_ros.train", "train NM-Net on sequence folders"),
    "eval": ("nmnet_ros.evaluate", "compare correspondence selectors on sequence folders"),
    "neighbors": ("nmnet_ros.neighbor_study", "inlier ratio of compatibility vs spatial neighbours (paper Fig. 3)"),
    "bench": ("nmnet_ros.bench", "time the pipeline stages on this machine"),
    "make-bag": ("nmnet_ros.make_bag", "convert a sequence folder into a ROS 1 .bag, ROS 2 .db3 or .mcap"),
    "replay": ("nmnet_ros.replay", "run the front end over a bag, record outputs, evaluate against ground truth"),
}


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised as Ctrl-C is: an interrupt no ``except Exception`` on the way swallows."""


def _raise_terminated(signum, frame):  # noqa: ARG001 - signal handler signature
    raise Terminated()


@contextmanager
def _signals_handled(signums: tuple[int, ...], handler: Callable) -> Iterator[None]:
    """``handler`` for ``signums`` within the block, the previous handlers after it. Outside the main thread (where no
    handler can be set) nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, handler) for s in signums}
    try:
        yield
    finally:
        for s, previous in old.items():
            signal.signal(s, previous)


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM (a service manager, ``timeout``, ``kill``) raises as Ctrl-C does, so the tools that
    close their output on Ctrl-C do so on it too."""
    with _signals_handled((signal.SIGTERM,), _raise_terminated):
        yield


@contextmanager
def interrupts_between_steps() -> Iterator[Callable[[], bool]]:
    """Within the block Ctrl-C and SIGTERM set a flag, read by the function yielded, instead of raising: a loop that
    asks it stops between its steps, never inside one (a bag's frame half written)."""
    signals: list[int] = []
    with _signals_handled((signal.SIGINT, signal.SIGTERM), lambda signum, _frame: signals.append(signum)):
        yield lambda: bool(signals)


def bounded(kind: type, least: float, expected: str, strict: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite number of ``kind`` (int or float) at least ``least``, above it when ``strict``;
    otherwise argparse's error names the option, the value and what was ``expected``."""

    def parse(text: str) -> float:
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not math.isfinite(value) or (value <= least if strict else value < least):
            raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}")
        return value

    return parse


def whole(least: int) -> Callable[[str], int]:
    """An argparse type: a whole number >= ``least`` (a count)."""
    return bounded(int, least, f"a whole number >= {least}")


def file_path(text: str) -> Path:
    """An output file option's value: one ending in '/' names a folder (as ``ros2 bag record -o DIR/``), which
    ``Path`` would quietly turn into a file of the folder's name."""
    if text.endswith(("/", os.sep)):
        raise argparse.ArgumentTypeError(f"'{text}' ends in '/', a folder: give a file name in it")
    return Path(text)


def progress(items: list, desc: str, unit: str) -> Iterable:
    """A progress bar on a terminal (none in a log) for the tools' long loops: features and methods take minutes."""
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit=unit, file=sys.stderr, disable=None, leave=False)


def gaps(text: str) -> tuple[int, ...]:
    """``--gaps``' value, '1-10' or '1,3,5': frame gaps >= 1, as a tuple (argparse names the option when it is not)."""
    try:
        if "-" in text:
            a, b = (int(x) for x in text.split("-"))
            out = tuple(range(a, b + 1))
        else:
            out = tuple(int(x) for x in text.split(","))
    except ValueError:
        out = ()
    if not out or min(out) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected frame gaps >= 1 as a range (1-10) or a list (1,3,5)")
    return out


def version() -> str:
    """``nmnet_ros X.Y.Z``, the installed package's version (setup.py and package.xml carry the same, tested)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return f"nmnet_ros {installed('nmnet_ros')}"
    except PackageNotFoundError:
        return "nmnet_ros (not installed: run from a source tree)"


def build_parser() -> argparse.ArgumentParser:
    """Parser with every subcommand's options (modules imported lazily per subcommand)."""
    parser = argparse.ArgumentParser(prog="nmnet", description="NM-Net visual-odometry front end: tools.")
    parser.add_argument("--version", action="version", version=version())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        if name in sys.argv[1:2]:  # only import the chosen tool's module
            importlib.import_module(module).add_arguments(p)
    return parser


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

    from .params import PARAMS, STARTUP_ONLY

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
    try:
        from .node import main
    except ImportError as e:
        if (advice := ros_missing(e)) is None:
            raise
        print(f"nmnet_node: error: {advice}", file=sys.stderr)
        return 2
    return main(args)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``nmnet`` console script."""
    argv = sys.argv[1:] if argv is None else argv
    sys.argv[1:] = argv
    parser = build_parser()
    args = parser.parse_args(argv)
    warnings.formatwarning = lambda message, *_, **__: f"warning: {message}\n"  # a user's line, not Python's source line
    if not getattr(args, "_module", None):  # a script calling bare `nmnet` must not read success
        parser.print_help(sys.stderr)
        print(f"nmnet: error: name a command: {', '.join(SUBCOMMANDS)} (nmnet COMMAND --help)", file=sys.stderr)
        return 2
    try:
        with sigterm_as_interrupt():  # the tools close their outputs (replay, make-bag) or calibrate (train) on either
            return importlib.import_module(args._module).main(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as e:
        print(f"nmnet {args.command}: error: {e}", file=sys.stderr)
        return 2
    except ImportError as e:  # replay --live and demo run the node and a player over DDS
        if (advice := ros_missing(e)) is None:
            raise
        print(f"nmnet {args.command}: error: {advice}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
