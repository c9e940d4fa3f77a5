"""``nmnet replay`` over many recordings: one Ray task per recording, a merged report.

Without an address Ray starts a local runtime sized to this machine (nothing to install or start by hand);
``--ray-address`` (or ``RAY_ADDRESS``) submits to a running cluster, whose workers read the recordings by path
(shared storage) and write into the run folder. Only paths and per-recording summaries go through Ray.

Each recording's outputs are a single replay's (``RUN/NAME/nmnet.mcap``, ``summary.json``, ``replay.log``, the
plots), built in a hidden folder and renamed into place when complete: a recording's folder is whole or absent, so a
task retried after its worker died starts clean, Ctrl-C leaves every finished recording intact, and a rerun of the
same command skips the recordings that are complete. ``RUN/report.json`` (and ``report.md``, ``report.png``) holds
one row per recording (its summary's numbers, or its error) and the totals; no frame data.
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
from pathlib import Path

from ..io.outputs import not_an_input, not_someone_elses, save_figure, write_json, write_markdown

REPORT = ("report.json", "report.md", "report.png")
PARTIAL = ".partial-"  # prefix of a recording's folder while it is being written
RETRIES = 3  # a task whose worker process dies is run again this many times (Ray's max_retries)
PATH_OPTIONS = ("camera", "params_file", "weights")  # resolved before the tasks run elsewhere
NUMBERS = ("frames", "processed", "dropped", "auc5", "median_rot_deg", "median_trans_deg", "fps")


def recordings(given: list[str], manifest: Path | None) -> list[Path]:
    """The recordings: the paths given (a quoted glob is expanded here, in order), then the manifest's lines (one
    path or glob each, relative to the manifest's folder; blank lines and ``#`` comments skipped). A pattern that
    matches nothing stops the run, naming it; a path that does not exist becomes that recording's error."""
    specs = [(s, Path.cwd()) for s in given]
    if manifest is not None:
        base = manifest.resolve().parent
        specs += [(line.strip(), base) for line in manifest.read_text().splitlines()
                  if line.strip() and not line.lstrip().startswith("#")]
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


def replay_one(replay: Callable[[argparse.Namespace], int], args: argparse.Namespace, recording: Path, run_dir: Path,
               name: str) -> dict:
    """Replay one recording into ``run_dir/name`` with ``replay`` (one recording's replay; this is a Ray task, run in
    a worker): its report row."""
    building = run_dir / f"{PARTIAL}{name}-{uuid.uuid4().hex[:8]}"
    building.mkdir()
    one = copy.copy(args)
    one.bag, one.out, one.json, one.plots = recording, building / "nmnet.mcap", building / "summary.json", building
    one.no_progress = True
    t0 = time.perf_counter()
    with open(building / "replay.log", "w") as log, redirect_stdout(log), redirect_stderr(log):
        try:
            rc = replay(one)
            error = None if rc == 0 else f"replay ended with code {rc}"
        except Exception as e:  # noqa: BLE001 - one recording's failure is its row, not the run's end
            traceback.print_exc()
            error = f"{type(e).__name__}: {e}" if isinstance(e, (ValueError, OSError)) else traceback.format_exc(limit=1)
    row = {"name": name, "recording": str(recording), "seconds": round(time.perf_counter() - t0, 2)}
    if error is not None:
        log_file = run_dir / f"{name}.failed.log"  # kept for the reader; the half-made outputs go
        (building / "replay.log").replace(log_file)
        shutil.rmtree(building, ignore_errors=True)
        return {**row, "status": "failed", "error": error.strip(), "log": str(log_file)}
    import json

    summary = json.loads((building / "summary.json").read_text())
    shutil.rmtree(run_dir / name, ignore_errors=True)  # a complete folder is never there (it would be skipped)
    building.rename(run_dir / name)
    (run_dir / f"{name}.failed.log").unlink(missing_ok=True)
    return {**row, "status": "ok", **_row_numbers(summary)}


def _row_numbers(summary: dict) -> dict:
    """A recording's report numbers from its summary (no frame data)."""
    out = {k: summary.get(k) for k in NUMBERS if k in summary}
    if summary.get("recording_warnings"):
        out["recording_warnings"] = summary["recording_warnings"]
    out["warnings"] = summary.get("warnings", {})
    return out


def complete(run_dir: Path, name: str) -> dict | None:
    """A finished recording's report row from its folder (None: not complete)."""
    import json

    try:
        summary = json.loads((run_dir / name / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    return {"name": name, "status": "ok", "skipped": True, **_row_numbers(summary)}


def check_args(args: argparse.Namespace, inputs: list[Path]) -> None:
    """Refuse what a run over many recordings cannot do, before any work."""
    for flag, value in (("--json", args.json), ("--plots", args.plots), ("--gt", args.gt)):
        if value is not None:
            why = ("each recording's ground truth must be in its bag (--gt-topic, --gt-tf)" if flag == "--gt" else
                   "each recording's outputs go to OUT/NAME/, the merged report to OUT/report.json, .md and .png")
            raise ValueError(f"{flag}: not with several recordings: {why}")
    if args.live:
        raise ValueError("--live: one recording at a time (several would play onto the same topics)")
    if args.out.suffix == ".mcap":
        raise ValueError(f"--out {args.out}: with several recordings --out is the run's folder (e.g. "
                         f"{args.out.with_suffix('')}), each recording's outputs in a folder of its own there")
    if args.out.exists() and not args.out.is_dir():
        raise ValueError(f"--out {args.out} is a file: give a folder for the run")
    not_an_input(args.out, "--out", inputs)
    for name in REPORT:
        not_someone_elses(args.out / name, "--out")


def _init_ray(address: str | None) -> None:
    """Join the cluster at ``address`` (or RAY_ADDRESS); without either start a local runtime for this machine."""
    import logging

    import ray

    address = address or os.environ.get("RAY_ADDRESS") or None
    local = {} if address else {"object_store_memory": 100 * 1024**2}  # summaries only: no large objects
    ray.init(address=address, include_dashboard=False, logging_level=logging.ERROR, log_to_driver=False,
             configure_logging=True, **local)


def run(args: argparse.Namespace, replay: Callable[[argparse.Namespace], int]) -> int:
    """Replay every recording of ``args`` (``recordings``, ``manifest``) in parallel, each with ``replay`` (one
    recording's); 0 when all are complete, 1 when some failed, 130 when interrupted."""
    inputs = recordings(args.recordings, args.manifest)
    check_args(args, inputs)
    for key in PATH_OPTIONS:  # workers may run elsewhere, in another folder
        if getattr(args, key, None):
            setattr(args, key, Path(getattr(args, key)).resolve())
    run_dir = args.out.resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    for stale in run_dir.glob(f"{PARTIAL}*"):  # a run killed before its tasks could clean up
        shutil.rmtree(stale, ignore_errors=True)
    names = names_of(inputs)
    rows: dict[str, dict] = {}
    todo = []
    for name, path in zip(names, inputs, strict=True):
        if (row := complete(run_dir, name)) is not None:
            rows[name] = {**row, "recording": str(path)}
        else:
            todo.append((name, path))
    if rows:
        print(f"{len(rows)} of {len(inputs)} recordings complete in {run_dir} already: skipped (delete a recording's "
              "folder to replay it again)")
    interrupted = False
    if todo:
        interrupted = _run_tasks(args, replay, run_dir, todo, rows)
    ordered = [rows.get(n, {"name": n, "recording": str(p), "status": "interrupted"}) for n, p in zip(names, inputs, strict=True)]
    report = write_report(run_dir, ordered)
    print(report_table(report))
    print(f"report: {run_dir / 'report.json'}, report.md, report.png")
    if interrupted:
        return 130
    return 1 if report["totals"]["failed"] else 0


def _run_tasks(args: argparse.Namespace, replay: Callable[[argparse.Namespace], int], run_dir: Path,
               todo: list[tuple[str, Path]], rows: dict[str, dict]) -> bool:
    """Run the recordings of ``todo`` as Ray tasks, filling ``rows`` as they finish; True when interrupted."""
    import signal

    import ray
    from tqdm import tqdm

    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    _init_ray(args.ray_address)
    for signum, handler in handlers.items():  # Ray's own would abort the process: Ctrl-C and SIGTERM stop as elsewhere
        if handler is not None:
            signal.signal(signum, handler)
    task = ray.remote(num_cpus=1, max_retries=RETRIES)(replay_one)
    shared = ray.put(args)
    pending = {task.remote(replay, shared, path, run_dir, name): (name, path) for name, path in todo}
    bar = tqdm(total=len(todo), desc="recordings", unit="rec", file=sys.stderr, disable=None if not args.no_progress else True)
    interrupted = False
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            name, path = pending.pop(done[0])
            try:
                row = ray.get(done[0])
            except Exception as e:  # noqa: BLE001 - the worker died more often than it is retried, or Ray failed
                row = {"name": name, "recording": str(path), "status": "failed",
                       "error": f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else ''}"}
            rows[name] = row
            if row["status"] != "ok":
                bar.write(f"failed: {name} ({path}): {row['error']}", file=sys.stderr)
            bar.update(1)
    except KeyboardInterrupt:
        interrupted = True
        bar.write(f"interrupted: {len(pending)} recordings not finished; the finished ones are complete in {run_dir}",
                  file=sys.stderr)
        for ref in pending:
            ray.cancel(ref, force=True)
    finally:
        bar.close()
        ray.shutdown()
        for stale in run_dir.glob(f"{PARTIAL}*"):  # the cancelled tasks' half-made folders
            shutil.rmtree(stale, ignore_errors=True)
    return interrupted


def totals(rows: list[dict]) -> dict:
    """The run's totals: recordings by status, frames, the mean AUC@5 over the scored recordings, frames/s."""
    ok = [r for r in rows if r["status"] == "ok"]
    scored = [r["auc5"] for r in ok if r.get("auc5") is not None]
    seconds = sum(r.get("seconds") or 0.0 for r in ok)
    processed = sum(r.get("processed", 0) for r in ok)
    return {"recordings": len(rows), "ok": len(ok), "failed": sum(r["status"] == "failed" for r in rows),
            "interrupted": sum(r["status"] == "interrupted" for r in rows),
            "frames": sum(r.get("frames", 0) for r in ok), "processed": processed,
            "dropped": sum(r.get("dropped", 0) for r in ok),
            "mean_auc5": sum(scored) / len(scored) if scored else None,
            "fps": processed / seconds if seconds else None}


def write_report(run_dir: Path, rows: list[dict]) -> dict:
    """``report.json``, ``report.md`` and ``report.png`` in ``run_dir``; returns the report."""
    report = {"recordings": rows, "totals": totals(rows)}
    write_json(run_dir / "report.json", report)
    write_markdown(run_dir / "report.md", report_table(report))
    _plot(run_dir / "report.png", rows)
    return report


def _cell(v, fmt: str = "{:.1f}") -> str:
    return "-" if v is None else fmt.format(v)


def report_table(report: dict) -> str:
    """The report as a Markdown table: one row per recording, then the totals."""
    lines = ["| recording | status | frames | processed | dropped | AUC@5 | frames/s | note |", "|---|---|---|---|---|---|---|---|"]
    for r in report["recordings"]:
        note = r.get("error") or "; ".join(r.get("recording_warnings", [])) or ("complete before this run" if r.get("skipped") else "")
        lines.append(f"| {r['name']} | {r['status']} | {_cell(r.get('frames'), '{}')} | {_cell(r.get('processed'), '{}')} | "
                     f"{_cell(r.get('dropped'), '{}')} | {_cell(r.get('auc5'))} | {_cell(r.get('fps'))} | "
                     f"{note.replace('|', '/').replace(chr(10), ' ')} |")
    t = report["totals"]
    stopped = f", {t['interrupted']} not run (interrupted)" if t["interrupted"] else ""
    lines.append(f"| **all ({t['recordings']})** | {t['ok']} ok, {t['failed']} failed{stopped} | {t['frames']} | "
                 f"{t['processed']} | {t['dropped']} | {_cell(t['mean_auc5'])} (mean) | {_cell(t['fps'])} (per task) | |")
    return "\n".join(lines)


def _plot(path: Path, rows: list[dict]) -> None:
    """AUC@5 and frames/s per recording, failures marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(2, 1, figsize=(max(6.0, 0.35 * len(rows) + 2), 5), sharex=True)
    x = range(len(rows))
    colours = ["tab:blue" if r["status"] == "ok" else "tab:red" for r in rows]
    a.bar(x, [r.get("auc5") or 0.0 for r in rows], color=colours)
    a.set_ylabel("AUC@5")
    b.bar(x, [r.get("fps") or 0.0 for r in rows], color=colours)
    b.set_ylabel("frames/s")
    b.set_xticks(list(x), [r["name"] for r in rows], rotation=60, ha="right", fontsize=7)
    a.set_title("per recording (red: failed or not run)")
    save_figure(fig, path)
