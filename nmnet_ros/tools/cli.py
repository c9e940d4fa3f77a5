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
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from ..ros.entry import ros_missing, version

# subcommand -> (module, help); each module has add_arguments(parser) and main(args) -> int
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("nmnet_ros.tools.demo", "the bundled sample bag live through the node, then offline beside SIFT; scores and plots"),
    "train": ("nmnet_ros.tools.train", "train NM-Net on sequence folders"),
    "eval": ("nmnet_ros.tools.evaluate", "compare correspondence selectors on sequence folders"),
    "neighbors": ("nmnet_ros.tools.neighbor_study", "inlier ratio of compatibility vs spatial neighbours (paper Fig. 3)"),
    "bench": ("nmnet_ros.tools.bench", "time the pipeline stages on this machine"),
    "make-bag": ("nmnet_ros.tools.make_bag", "convert a sequence folder into a ROS 1 .bag, ROS 2 .db3 or .mcap"),
    "replay": ("nmnet_ros.tools.replay", "run the front end over a bag, record outputs, evaluate against ground truth"),
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


class HelpFormatter(argparse.HelpFormatter):
    """``--help`` that shows each option's default where it has one (not for flags and options without one), unless
    its help already says it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (default is None or default is False or default == argparse.SUPPRESS or not action.option_strings
                or "default" in text or "%(default)" in text):
            return text
        shown = ",".join(str(v) for v in default) if isinstance(default, (list, tuple)) else "%(default)s"
        return f"{text} (default: {shown})"


def build_parser() -> argparse.ArgumentParser:
    """Parser with every subcommand's options (modules imported lazily per subcommand)."""
    parser = argparse.ArgumentParser(prog="nmnet", description="NM-Net visual-odometry front end: tools.")
    parser.add_argument("--version", action="version", version=version())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=HelpFormatter)
        p.set_defaults(_module=module)
        if name in sys.argv[1:2]:  # only import the chosen tool's module
            importlib.import_module(module).add_arguments(p)
    return parser


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


def node_value(name: str) -> Callable[[str], object]:
    """An argparse type for an option that sets node parameter ``name``: the node's own type and range check, so a
    value the node would refuse stops the command there, naming the option (argparse adds it) and the range."""
    from ..interface.params import PARAMS, check_value  # here: the parameters' module loads the detectors

    kind = type(PARAMS[name][0])

    def parse(text: str) -> object:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if (why := check_value(name, value)) is not None:
            raise argparse.ArgumentTypeError(why)
        return value

    return parse
