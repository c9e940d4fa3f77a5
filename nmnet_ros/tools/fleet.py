"""A command over many recordings (``nmnet replay``, ``nmnet label``): one Ray task per recording, a merged report.

Without an address Ray starts a local runtime sized to this machine (nothing to install or start by hand);
``--ray-address`` (or ``RAY_ADDRESS``) submits to a running cluster, whose workers read the recordings by path
(shared storage) and write into the run folder. Only paths and per-recording summaries go through Ray.

Each recording's outputs are those of the command run on it alone, in ``RUN/NAME/``, with its log: built in a hidden
folder and renamed into place when complete, so a recording's folder is whole or absent, a task retried after its
worker died starts clean, Ctrl-C leaves every finished recording intact, and a rerun of the same command skips the
recordings that are complete. ``RUN/report.json`` (and ``report.md``, ``report.png``) holds one row per recording
(its summary's numbers, or its error) and the totals; no frame data.
"""

from __future__ import annotations

import argparse
import copy
import glob
import os
import shutil
import sys
import time
import traceback
import uuid
from collections.abc import Callable
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ..io.outputs import not_an_input, not_someone_elses, save_figure, write_json, write_markdown

if TYPE_CHECKING:
    from matplotlib.figure import Figure

REPORT = ("report.json", "report.md", "report.png")
PARTIAL = ".partial-"  # prefix of a recording's folder while it is being written
RETRIES = 3  # a task whose worker process dies is run again this many times (Ray's max_retries)
PATH_OPTIONS = ("camera", "params_file", "weights")  # resolved before the tasks run elsewhere


@dataclass(frozen=True)
class Column:
    """One number of a recording's summary in the report: its key, its table header, its format, how it totals."""

    key: str
    header: str
    fmt: str = "{:.1f}"
    total: str | None = None  # "sum", "mean" (over the recordings that have it) or None
    weight: str | None = None  # the column a mean is weighted by: a recording's pairs, so the total is the fleet's own

    def total_note(self) -> str:
        """What the totals row says after a mean: how it was taken."""
        return "" if self.total != "mean" else " (mean)" if self.weight is None else f" (mean by {self.weight})"


@dataclass(frozen=True)
class Job:
    """What a command does with one recording: ``run_one(args, recording, folder)`` writes its outputs into the
    empty ``folder`` and returns the exit code; a complete folder holds ``summary`` (JSON), whose ``columns`` go
    into the report; ``refuse(args)`` stops options a run over many recordings cannot honour."""

    command: str
    run_one: Callable[[argparse.Namespace, Path, Path], int]
    summary: str
    columns: tuple[Column, ...]
    refuse: Callable[[argparse.Namespace], None]


def recordings(given: list[str], manifest: Path | None) -> list[Path]:
    """The recordings: the paths given (a quoted glob is expanded here, in order), then the manifest's lines (one
    path or glob each, relative to the manifest's folder; blank lines and ``#`` comments skipped). A pattern that
    matches nothing stops the run, naming it; a path that does not exist becomes that recording's error."""
    specs = [(s, Path.cwd()) for s in given]
    if manifest is not None:
        try:
            lines = manifest.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise ValueError(f"--manifest {manifest}: cannot read it ({e}); give a text file, one recording per line") from None
        base = manifest.resolve().parent
        specs += [(line.strip(), base) for line in lines if line.strip() and not line.lstrip().startswith("#")]
    out: list[Path] = []
    for spec, base in specs:
        path = Path(spec).expanduser()
        path = path if path.is_absolute() else base / path
        if glob.has_magic(spec) and not path.exists():
            found = sorted(glob.glob(str(path)))
            if not found:
                raise ValueError(f"{spec}: matches no recording")
            out += [Path(f) for f in found]
        else:
            out.append(path)
    if not out:
        raise ValueError(f"--manifest {manifest}: lists no recording")
    seen: set[Path] = set()
    return [p for p in out if not (p.resolve() in seen or seen.add(p.resolve()))]  # each once, first place kept


def names_of(paths: list[Path]) -> list[str]:
    """Each recording's folder name in the run: its file or folder name without suffix, with ``-2``, ``-3`` ...
    after a name taken before (same inputs in the same order: same names, which a rerun relies on)."""
    names: list[str] = []
    for p in paths:
        base = (p.stem if p.suffix in (".bag", ".mcap", ".db3") else p.name) or "recording"
        name, i = base, 1
        while name in names:
            i += 1
            name = f"{base}-{i}"
        names.append(name)
    return names


def run_one(job: Job, args: argparse.Namespace, recording: Path, run_dir: Path, name: str) -> dict:
    """``job`` on one recording into ``run_dir/name`` (a Ray task, run in a worker): its report row."""
    tag = f"{PARTIAL}{name}-{uuid.uuid4().hex[:8]}"
    building, log_file = run_dir / tag, run_dir / f"{tag}.log"
    building.mkdir()
    t0 = time.perf_counter()
    with open(log_file, "w") as log, redirect_stdout(log), redirect_stderr(log):
        try:
            rc = job.run_one(copy.copy(args), recording, building)
            error = None if rc == 0 else f"{job.command} ended with code {rc}"
        except Exception as e:  # noqa: BLE001 - one recording's failure is its row, not the run's end
            traceback.print_exc()
            error = described(e)
    row = {"name": name, "recording": str(recording), "seconds": round(time.perf_counter() - t0, 2)}
    if error is None and (numbers := _numbers(job, building)) is None:
        error = f"{job.command} wrote no {job.summary}"
    if error is not None:
        failed = run_dir / f"{name}.failed.log"  # kept for the reader; the half-made outputs go
        log_file.replace(failed)
        shutil.rmtree(building, ignore_errors=True)
        return {**row, "status": "failed", "error": error.strip(), "log": str(failed)}
    log_file.replace(building / f"{job.command}.log")
    shutil.rmtree(run_dir / name, ignore_errors=True)  # a complete folder is never there (it would be skipped)
    building.rename(run_dir / name)
    (run_dir / f"{name}.failed.log").unlink(missing_ok=True)
    return {**row, "status": "ok", **numbers}


def _numbers(job: Job, folder: Path) -> dict | None:
    """A complete folder's report numbers from its summary (no frame data); None: not complete."""
    import json

    try:
        summary = json.loads((folder / job.summary).read_text())
    except (OSError, ValueError):
        return None
    out = {c.key: summary.get(c.key) for c in job.columns}
    for key in ("recording_warnings", "warnings"):
        if summary.get(key):
            out[key] = summary[key]
    return out


def check_args(job: Job, args: argparse.Namespace, inputs: list[Path]) -> None:
    """Refuse what a run over many recordings cannot do, before any work."""
    job.refuse(args)
    if args.out.suffix in (".mcap", ".json"):
        raise ValueError(f"{args.out}: with several recordings the output is the run's folder (e.g. "
                         f"{args.out.with_suffix('')}), each recording's outputs in a folder of its own there")
    if args.out.exists() and not args.out.is_dir():
        raise ValueError(f"{args.out} is a file: give a folder for the run")
    not_an_input(args.out, "the output", inputs)
    for name in REPORT:
        not_someone_elses(args.out / name, "the output")


OUTPUTS_WHY = "each recording's outputs go to OUT/NAME/, the merged report to OUT/report.json, .md and .png"


def several_refused(given: dict[str, object], why: dict[str, str] | None = None) -> None:
    """Stop the options (flag: value) that are given: not with several recordings, for ``why[flag]`` (default: the
    outputs' own places)."""
    for flag, value in given.items():
        if value not in (None, False):
            reason = (why or {}).get(flag, OUTPUTS_WHY)
            raise ValueError(f"--{flag.replace('_', '-')}: not with several recordings ({reason})")


def _remove_partial(run_dir: Path) -> None:
    """What unfinished tasks left: their folders and logs, and what a command built beside them (``.NAME.*``)."""
    for stale in [*run_dir.glob(f"{PARTIAL}*"), *run_dir.glob(f".{PARTIAL}*")]:
        if stale.is_dir():
            shutil.rmtree(stale, ignore_errors=True)
        else:
            stale.unlink(missing_ok=True)


def _reachable(address: str, timeout_s: float = 10.0) -> None:
    """Stop at once when nothing answers at a cluster's ``address`` (HOST:PORT or ray://HOST:PORT): Ray itself keeps
    trying to connect for many minutes without a word."""
    import socket

    host, _, port = address.removeprefix("ray://").rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except (OSError, ValueError) as e:
        raise ValueError(f"--ray-address {address}: no Ray cluster answers there ({e}); start one (`ray start --head`) "
                         "or give its head's HOST:PORT, or leave --ray-address out to run on this machine") from None


def several(given: list[str], manifest: Path | None,
            what: str = "a recording (a bag file or folder, a sequence folder)") -> bool:
    """Whether the inputs ``given`` (and ``manifest``) name several: more than one, a glob, or a manifest. None at all
    is refused, naming ``what`` to give."""
    if manifest is not None or len(given) > 1 or any(map(glob.has_magic, given)):
        return True
    if not given:
        raise ValueError(f"name {what}, or give --manifest FILE")
    return False


def _init_ray(address: str | None) -> None:
    """Join the cluster at ``address`` (or RAY_ADDRESS); without either start a local runtime for this machine."""
    import logging

    import ray

    address = address or os.environ.get("RAY_ADDRESS") or None
    if address and address != "auto":
        _reachable(address)
    # "local": a runtime of its own, even beside a cluster started on this machine; summaries only: a small store
    local = {} if address else {"object_store_memory": 100 * 1024**2}
    ray.init(address=address or "local", include_dashboard=False, logging_level=logging.ERROR, log_to_driver=False,
             configure_logging=True, **local)


def run(job: Job, args: argparse.Namespace) -> int:
    """``job`` on every recording of ``args`` (``recordings``, ``manifest``; ``out``: the run's folder) in parallel;
    0 when all are complete, 1 when some failed, 130 when interrupted."""
    inputs = recordings(args.recordings, args.manifest)
    check_args(job, args, inputs)
    for key in PATH_OPTIONS:  # workers may run elsewhere, in another folder
        if getattr(args, key, None):
            setattr(args, key, Path(getattr(args, key)).resolve())
    run_dir = args.out.resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    _remove_partial(run_dir)  # a run killed before its tasks could clean up
    names = names_of(inputs)
    rows: dict[str, dict] = {}
    todo = []
    for name, path in zip(names, inputs, strict=True):
        if (numbers := _numbers(job, run_dir / name)) is not None:
            rows[name] = {"name": name, "recording": str(path), "status": "ok", "skipped": True, **numbers}
        else:
            todo.append((name, path))
    if rows:
        print(f"{len(rows)} of {len(inputs)} recordings complete in {run_dir} already: skipped (delete a recording's "
              "folder to run it again)")
    interrupted = False
    if todo:
        interrupted = _run_tasks(job, args, run_dir, todo, rows)
    ordered = [rows.get(n, {"name": n, "recording": str(p), "status": "interrupted"}) for n, p in zip(names, inputs, strict=True)]
    report = write_report(job, run_dir, ordered)
    print(report_table(job, report))
    print(f"report: {run_dir / 'report.json'}, report.md, report.png")
    if interrupted:
        return 130
    return 1 if report["totals"]["failed"] else 0


def _run_tasks(job: Job, args: argparse.Namespace, run_dir: Path, todo: list[tuple[str, Path]],
               rows: dict[str, dict]) -> bool:
    """Run the recordings of ``todo`` as Ray tasks, filling ``rows`` as they finish; True when interrupted."""
    paths = dict(todo)

    def done(name: str, row: dict | Failed) -> str | None:
        if isinstance(row, Failed):  # the worker died more often than it is retried, or Ray failed
            row = {"name": name, "recording": str(paths[name]), "status": "failed", "error": row.error}
        rows[name] = row
        return None if row["status"] == "ok" else f"{name} ({paths[name]}): {row['error']}"

    try:
        _, interrupted = map_tasks(run_one, {name: (path, run_dir, name) for name, path in todo}, common=(job, args),
                                   address=args.ray_address, what=f"{job.command}: recordings", unit="rec",
                                   quiet=getattr(args, "no_progress", False), done=done)
    finally:
        _remove_partial(run_dir)  # the interrupted or killed tasks' half-made folders
    if interrupted:
        print(f"the finished recordings are complete in {run_dir}", file=sys.stderr)
    return interrupted


@dataclass(frozen=True)
class Failed:
    """A task's error (an exception it raised, or its worker's death after the retries), as one line."""

    error: str


def described(e: Exception) -> str:
    """A task's exception as its report says it: a bad input (ValueError, OSError) plainly, as the command run on that
    input alone says it, anything else with the line of code it came from."""
    if isinstance(e, (ValueError, OSError)):
        return str(e) or type(e).__name__
    return traceback.format_exc(limit=1).strip()


def _guarded(fn: Callable, *args: object) -> object:
    """``fn(*args)``, or its exception as :class:`Failed`: one input's failure is that task's result, not the run's
    end (a Ray task error would come back as the worker's traceback)."""
    try:
        return fn(*args)
    except Exception as e:  # noqa: BLE001 - see above
        return Failed(described(e))


def map_tasks(fn: Callable, calls: dict[str, tuple], *, common: tuple = (), address: str | None = None,
              what: str = "tasks", unit: str = "task", quiet: bool = False,
              done: Callable[[str, object], str | None] | None = None) -> tuple[dict[str, object], bool]:
    """``fn(*common, *calls[name])`` for every name, one Ray task each (one CPU; retried when its worker dies).

    ``common`` goes through Ray's object store once, not once per task: keep it small (options, paths). One progress
    bar over the tasks; ``done(name, result)`` sees each result as it arrives and returns a line to print above the
    bar (a failure, named) or None. An exception in a task, or a worker that died more often than it is retried,
    gives :class:`Failed`. Ctrl-C or SIGTERM ends the tasks not finished (Ray's shutdown). Returns the finished results by
    name and whether the run was interrupted. Ray starts here (see :func:`_init_ray`) and is shut down on return.
    """
    import signal

    import ray
    from tqdm import tqdm

    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    _init_ray(address)
    for signum, handler in handlers.items():  # Ray's own would abort the process: Ctrl-C and SIGTERM stop as elsewhere
        if handler is not None:
            signal.signal(signum, handler)
    results: dict[str, object] = {}
    bar = tqdm(total=len(calls), desc=what, unit=unit, file=sys.stderr, disable=True if quiet else None)
    interrupted, pending = False, {}
    try:
        task = ray.remote(num_cpus=1, max_retries=RETRIES)(_guarded).options(name=fn.__name__)  # ray::NAME processes
        shared = [ray.put(a) for a in common]
        pending = {task.remote(fn, *shared, *a): name for name, a in calls.items()}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            name = pending.pop(ready[0])
            try:
                result = ray.get(ready[0])
            except Exception as e:  # noqa: BLE001 - the worker died more often than it is retried, or Ray failed
                first = str(e).strip().splitlines()[0] if str(e).strip() else ""
                result = Failed(f"{type(e).__name__}: {first}")
            results[name] = result
            line = done(name, result) if done else (f"{name}: {result.error}" if isinstance(result, Failed) else None)
            if line:
                bar.write(f"failed: {line}", file=sys.stderr)
            bar.update(1)
    except KeyboardInterrupt:
        interrupted = True
        bar.write(f"interrupted: {len(pending)} of {len(calls)} not finished", file=sys.stderr)
        # No ray.cancel: it races with a task finishing at that moment and Ray then aborts the driver ("Tried to
        # complete task that was not pending", ray-project/ray#54798), exit 1 instead of 130. The shutdown ends
        # them: a driver's tasks and their workers die with it, on a local runtime and on a cluster alike.
    finally:
        bar.close()
        ray.shutdown()
    return results, interrupted


def totals(job: Job, rows: list[dict]) -> dict:
    """The run's totals: recordings by status, and each column's sum or mean over the complete recordings. A mean
    with a ``weight`` counts each recording by it: AUC@5 weighted by the pairs scored is the AUC@5 of all the fleet's
    pairs together (a mean over pairs), not of an average recording, which a short one would sway as much as an
    hour-long one."""
    ok = [r for r in rows if r["status"] == "ok"]
    out = {"recordings": len(rows), "ok": len(ok), "failed": sum(r["status"] == "failed" for r in rows),
           "interrupted": sum(r["status"] == "interrupted" for r in rows)}
    for c in job.columns:
        have = [r for r in ok if r.get(c.key) is not None and (c.weight is None or (r.get(c.weight) or 0) > 0)]
        weights = [1 if c.weight is None else r[c.weight] for r in have]
        if c.total == "sum":
            out[c.key] = sum(r[c.key] for r in have)
        elif c.total == "mean":
            out[c.key] = sum(r[c.key] * w for r, w in zip(have, weights, strict=True)) / sum(weights) if have else None
    return out


def write_report(job: Job, run_dir: Path, rows: list[dict]) -> dict:
    """``report.json``, ``report.md`` and ``report.png`` in ``run_dir``; returns the report."""
    report = {"command": job.command, "recordings": rows, "totals": totals(job, rows)}
    write_json(run_dir / "report.json", report)
    write_markdown(run_dir / "report.md", report_table(job, report))
    _plot(job, run_dir / "report.png", rows)
    return report


def _cell(v, fmt: str = "{:.1f}") -> str:
    return "-" if v is None else fmt.format(v)


def report_table(job: Job, report: dict) -> str:
    """The report as a Markdown table: one row per recording, then the totals."""
    head = " | ".join(c.header for c in job.columns)
    lines = [f"| recording | status | {head} | note |", "|---" * (len(job.columns) + 3) + "|"]
    for r in report["recordings"]:
        note = (r.get("error") or "; ".join(r.get("recording_warnings", []))
                or ("complete before this run" if r.get("skipped") else ""))
        cells = " | ".join(_cell(r.get(c.key), c.fmt) for c in job.columns)
        lines.append(f"| {r['name']} | {r['status']} | {cells} | {note.replace('|', '/').replace(chr(10), ' ')} |")
    t = report["totals"]
    stopped = f", {t['interrupted']} not run (interrupted)" if t["interrupted"] else ""
    cells = " | ".join(_cell(t.get(c.key), c.fmt) + c.total_note() if c.total else ""
                       for c in job.columns)
    lines.append(f"| **all ({t['recordings']})** | {t['ok']} ok, {t['failed']} failed{stopped} | {cells} | |")
    return "\n".join(lines)


def _plot(job: Job, path: Path, rows: list[dict]) -> Figure:
    """Each averaged column per recording, the names of the failed in red; no bar where a recording has no value
    (no ground truth: no AUC@5, no fitted sigma), as the table's "-". Returns the (closed) figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [c for c in job.columns if c.total == "mean"] or list(job.columns[:1])
    fig, axes = plt.subplots(len(shown), 1, figsize=(max(6.0, 0.35 * len(rows) + 2), 2.5 * len(shown) + 0.5),
                             sharex=True, squeeze=False)
    x = range(len(rows))
    colours = ["tab:blue" if r["status"] == "ok" else "tab:red" for r in rows]
    for ax, c in zip(axes[:, 0], shown, strict=True):
        ax.bar(x, [float("nan") if r.get(c.key) is None else r[c.key] for r in rows], color=colours)
        ax.set_ylabel(c.header)
    axes[-1, 0].set_xticks(list(x), [r["name"] for r in rows], rotation=60, ha="right", fontsize=7)
    for label, colour in zip(axes[-1, 0].get_xticklabels(), colours, strict=True):
        label.set_color(colour)
    axes[0, 0].set_title(f"{job.command}, per recording (red: failed or not run)")
    save_figure(fig, path)
    return fig
