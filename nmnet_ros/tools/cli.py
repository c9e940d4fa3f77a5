"""The ``nmnet`` command: one entry point, one subcommand per tool."""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TextIO

from ..ros.entry import ros_missing, version
from . import options

# subcommand -> (module with main(args) -> int, its options in tools/options.py, help)
SUBCOMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], str]] = {
    "demo": ("nmnet_ros.tools.demo", options.demo,
             "the bundled sample bag live through the node, then offline beside SIFT; scores and plots"),
    "train": ("nmnet_ros.tools.train", options.train, "train NM-Net on sequence folders"),
    "eval": ("nmnet_ros.tools.evaluate", options.evaluate, "compare correspondence selectors on sequence folders"),
    "neighbors": ("nmnet_ros.tools.neighbor_study", options.neighbors,
                  "inlier ratio of compatibility vs spatial neighbours (paper Fig. 3)"),
    "label": ("nmnet_ros.tools.label", options.label,
              "ground-truth poses for an unlabeled recording (COLMAP reconstruction), as a sequence folder to train on"),
    "bench": ("nmnet_ros.tools.bench", options.bench, "time the pipeline stages on this machine"),
    "make-bag": ("nmnet_ros.tools.make_bag", options.make_bag,
                 "convert a sequence folder into a ROS 1 .bag, ROS 2 .db3 or .mcap"),
    "replay": ("nmnet_ros.tools.replay", options.replay,
               "run the front end over a bag, record outputs, evaluate against ground truth"),
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


class ReaderMayLeave:
    """stdout or stderr whose reader may go away (``nmnet eval ... | head``). The first write that finds the pipe
    closed points the stream at the null device, so the tool finishes and writes its files instead of ending there
    with a broken pipe."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._to_null()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._to_null()

    def _to_null(self) -> None:
        null = os.open(os.devnull, os.O_WRONLY)  # the stream's buffer is flushed there, at exit too
        os.dup2(null, self._stream.fileno())
        os.close(null)

    def __getattr__(self, name: str) -> object:
        return getattr(self._stream, name)


@contextmanager
def readers_may_leave() -> Iterator[None]:
    """Within the block stdout and stderr are :class:`ReaderMayLeave` (a stream that is not there stays so)."""
    saved = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = (s if s is None else ReaderMayLeave(s) for s in saved)
    try:
        yield
    finally:
        for stream in (sys.stdout, sys.stderr):  # what is still buffered: a reader gone since is found here, not at exit
            if stream is not None:
                stream.flush()
        sys.stdout, sys.stderr = saved


def _command(p: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    """``p`` as ``nmnet NAME``'s parser: its options from tools/options.py, its module to run."""
    module, add_options, _ = SUBCOMMANDS[name]
    p.set_defaults(_module=module, command=name)
    add_options(p)
    return p


def build_parser() -> argparse.ArgumentParser:
    """Parser with every subcommand's options (a subcommand's module is imported only when it runs)."""
    parser = argparse.ArgumentParser(prog="nmnet", description="NM-Net visual-odometry front end: tools.")
    parser.add_argument("--version", action="version", version=version())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, _, help_text) in SUBCOMMANDS.items():
        _command(sub.add_parser(name, help=help_text, description=help_text, formatter_class=options.HelpFormatter), name)
    return parser


def parse_args(argv: list[str]) -> argparse.Namespace:
    """``argv``'s tool and options. A tool's options may come between its positionals (``nmnet label imgs --camera
    c.yaml out``, ``nmnet eval seq_a --gaps 1-3 seq_b``), which the parser of all tools refuses: it takes a
    subcommand's positionals in one pass, and the error it gives names none of them."""
    if argv and argv[0] in SUBCOMMANDS:
        help_text = SUBCOMMANDS[argv[0]][2]
        p = argparse.ArgumentParser(prog=f"nmnet {argv[0]}", description=help_text, formatter_class=options.HelpFormatter)
        return _command(p, argv[0]).parse_intermixed_args(argv[1:])
    return build_parser().parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``nmnet`` console script."""
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    warnings.formatwarning = lambda message, *_, **__: f"warning: {message}\n"  # a user's line, not Python's source line
    if not getattr(args, "_module", None):  # a script calling bare `nmnet` must not read success
        build_parser().print_help(sys.stderr)
        print(f"nmnet: error: name a command: {', '.join(SUBCOMMANDS)} (nmnet COMMAND --help)", file=sys.stderr)
        return 2
    with readers_may_leave():
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    """``args``' tool, its errors as one line each and an exit code."""
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

