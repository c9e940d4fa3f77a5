"""``nmnet replay``: run the front end over a recorded bag and evaluate it.

Reads .bag/.db3/.mcap (topics auto-detected), processes frame by frame, records the outputs
to an .mcap, and prints a summary; with ground truth (in the bag, or ``--gt`` TUM file) also
rotation/translation errors and pose AUC, and writes plots. ``--baseline`` runs the classic
OpenCV pipeline (SIFT + mutual/ratio + MAGSAC++) over the same frames for comparison.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..core.debug_view import draw_matches
from ..core.geometry import Camera
from ..core.model import load_model
from ..core.pipeline import Frontend, selector_name
from ..core.planes import NOTE as PLANE_NOTE
from ..core.settings import for_tool
from ..interface.framecheck import FrameChecks
from ..interface.imgconv import MAX_PIXELS
from ..interface.params import PARAMS, SELECTORS, frontend_config, pose_sigmas, read_params_file
from ..interface.posemsg import SIGMAS
from ..io.bag_truth import bag_ground_truth, tf_ground_truth
from ..io.bags import BagError, BagReader, Frame, choose_topics, image_frame, read_frames
from ..io.datasets import read_camera_yaml
from ..io.mcap_out import McapOutput
from ..io.outputs import not_a_folder, not_an_input, not_someone_elses, output_file, output_folder, write_json
from ..io.trajectory import FrameTruth, Trajectory, read_tum
from . import fleet
from .report import PLOTS, print_scores, print_summary, print_tracks, write_plots
from .scoring import Run, truth_missed, truth_uncovered

BASELINE = {"detector": "sift", "pose_estimator": "classic"}


class Notes:
    """A pass's per-frame warnings, by the kinds the node counts in diagnostics (``warn_<kind>``): each kind is
    said in full the first ``shown`` times, then only counted, and the counts are totalled at the end, so a bag
    from a driver that never stamps does not print a line per frame."""

    def __init__(self, log: Callable[[str], None], shown: int = 3) -> None:
        self.log, self.shown = log, shown
        self.counts: dict[str, int] = {}

    def __call__(self, kind: str, text: str | None) -> None:
        """Count one ``kind``; say ``text`` (None: count only) while the kind is under the limit."""
        n = self.counts[kind] = self.counts.get(kind, 0) + 1
        if text is not None and n <= self.shown:
            self.log(text + (f" (further '{kind}' frames are counted, not named)" if n == self.shown else ""))

    def close(self) -> None:
        """Say each kind's total that was not said frame by frame."""
        for kind, n in self.counts.items():
            if n > self.shown:
                self.log(f"{kind}: {n} frames in all")


class _Gate:
    """The node's checks before a frame enters the front end, offline: a readable image, a calibration, a stamp
    that goes forward, a calibration that fits the frame's size. Each refusal is counted in ``notes`` by the node's
    warning kind; ``camera``, when given, replaces the bag's camera_info."""

    def __init__(self, notes: Notes, camera: Camera | None, time_jump_s: float) -> None:
        self.notes, self.camera, self.time_jump_s = notes, camera, time_jump_s
        self.checks = FrameChecks("--stamp-source arrival")  # the node's
        self.last_note: str | None = None

    def camera_for(self, f: Frame) -> Camera | None:
        """The camera to process frame ``f`` with; None: skip it (said, or counted, in ``notes``)."""
        if f.image is None:
            self.notes("bad_image", f"frame at {f.stamp:.3f}: skipped, {f.error}")
            return None
        calibration = self.camera or f.camera
        if calibration is None:
            if f.camera_error:
                self.notes("bad_camera_info", f"frame at {f.stamp:.3f}: skipped, camera_info refused: {f.camera_error} "
                                              "(give the calibration with --camera)")
            else:
                self.notes("no_camera_info", f"frame at {f.stamp:.3f}: skipped, no camera_info yet (give the calibration "
                                             "with --camera)")
            return None
        go_on, said = self.checks.stamp(f.stamp, self.time_jump_s)
        if said is not None:
            self.notes(said.kind, said.text + " (as the node does)")
        if not go_on:
            return None
        cam, said = self.checks.camera(calibration, (f.image.shape[1], f.image.shape[0]), f.stamp)
        for r in said:
            if r.kind == "camera_size_mismatch":  # said when it changes: a scaled K holds for every frame of the stream
                self.notes(r.kind, f"frame at {f.stamp:.3f}: {r.text}" if r.text != self.last_note else None)
                self.last_note = r.text
            else:
                self.notes(r.kind, f"frame at {f.stamp:.3f}: {r.text}")
        return cam


def process_bag(reader: BagReader, out: McapOutput | None, fe: Frontend, truth: Trajectory | None = None,
                debug_images: bool = False, progress: bool = True, topics: dict | None = None,
                log: Callable[[str], None] = print, camera: Camera | None = None,
                rectified: bool = False, recorded: bool = False,
                window: tuple[float, float] | None = None,
                max_pixels: int = MAX_PIXELS, sigmas: tuple[float, float] = SIGMAS) -> tuple[Run, int, np.ndarray | None]:
    """One pass of the front end ``fe`` over a bag; returns the run, the frame count and the match overlay of the
    first frame with a pose (None when none has one).

    ``reader``: the bag, opened once (opening lists its topics) and read again for each pass.

    ``truth``: the ground truth the frames are scored against (:func:`ground_truth`), by stamp (:class:`FrameTruth`); ``camera``: the
    calibration to use instead of the bag's camera_info; ``rectified``: its images are rectified; ``recorded``: the
    frames are stamped with the time the bag recorded them (``--stamp-source arrival``); ``window``: the part of the
    bag to replay (``--start``, ``--duration``: seconds after its first frame); ``max_pixels``: the node's
    max_image_pixels; ``sigmas``: its pose_sigma_* (the covariance the scores are checked against).
    """
    frames, _ = read_frames(reader, **(topics or {}), rectified=rectified, recorded=recorded, window=window,
                            max_pixels=max_pixels)
    run = Run(selector_name(fe.config["pose_estimator"]), sigmas)
    notes = Notes(log)
    gate = _Gate(notes, camera, fe.config["time_jump_s"])
    n_frames, overlay = 0, None
    look = None if truth is None else FrameTruth(truth)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(desc=f"replay {reader.path.name}", unit="frame", file=sys.stderr,
                   disable=None)  # off when stderr is no terminal (logs, CI)

    def said(*more: str | None) -> None:  # the recording's warnings not said yet (topic choice, 16UC1, damage, ...)
        for w in [*reader.new_warnings(), *more]:
            if w:
                log(f"warning: {w}")
                run.recording_warnings.append(w)

    t0 = time.perf_counter()
    try:
        for f in frames:
            n_frames += 1
            if n_frames == 1:
                said()  # now, not after an hour of a long bag: what was chosen and what the first frame looks like
            if bar is not None:
                bar.update(1)
            T = None if look is None else look.at(f.stamp)  # every frame read: the lookup follows them in order
            if (cam := gate.camera_for(f)) is None:
                continue
            fe.camera = cam
            r = fe.process(f.image, f.stamp)
            if r.plane_ambiguous:
                notes("plane_ambiguous", f"frame at {f.stamp:.3f}: {PLANE_NOTE} (as the node does)")
            run.add(r, T)
            want_overlay = overlay is None and r.status == "ok"
            dbg = draw_matches(f.image, r.k0, r.k1, r.mask) if debug_images or want_overlay else None
            if want_overlay:
                overlay = dbg
            if out is not None:
                out.write_result(r, f.stamp, f.frame_id, debug=dbg if debug_images else None)  # the node's header
    finally:
        run.seconds = time.perf_counter() - t0
        if bar is not None:
            bar.close()
        run.warnings = notes.counts
        notes.close()
    stamps = [s.stamp for s in run.steps]
    uncovered = None if look is None else truth_uncovered(stamps, [s.T is not None for s in run.steps], look.per_frame)
    said(truth_missed(truth, stamps), uncovered)
    return run, n_frames, overlay


NODE_ESTIMATORS = {selector: estimator for estimator, selector in SELECTORS.items()}  # selector -> pose_estimator


def given_options(args: argparse.Namespace) -> dict:
    """The node parameters the command line sets (options given; ``--rectified`` only when present; a --selector the
    node runs as its ``pose_estimator``)."""
    given = {s.name: str(v) if isinstance(v, Path) else v for s in for_tool("replay")
             if (v := getattr(args, s.name)) is not None}
    if given.get("pose_estimator") in NODE_ESTIMATORS:  # a selector the node runs, by eval's name
        given["pose_estimator"] = NODE_ESTIMATORS[given["pose_estimator"]]
    return given


def node_params(args: argparse.Namespace) -> dict:
    """The node parameters a replay runs with: the --params-file's (or the defaults), then the options given."""
    params = (read_params_file(args.params_file, warn=lambda m: print(f"warning: {m}", file=sys.stderr)) if args.params_file
              else {name: default for name, (default, _, _) in PARAMS.items()})
    return {**params, **given_options(args)}


def replay_window(args: argparse.Namespace) -> tuple[float, float] | None:
    """The part of the bag ``--start`` and ``--duration`` ask for, in seconds after its first frame (None: all)."""
    if args.start is None and args.duration is None:
        return None
    start = args.start or 0.0
    return start, start + args.duration if args.duration is not None else float("inf")


def ground_truth(reader: BagReader, args: argparse.Namespace, image_topic: str) -> Trajectory | None:
    """What the replay scores against: the ``--gt`` TUM file, else ``--gt-tf``'s transforms on /tf, else the bag's
    ground-truth topic (each frame looked up by stamp: :class:`FrameTruth`), else nothing; moved to the camera by
    ``--gt-camera`` when it tracks a body. A file or transform that is not there stops the replay, naming it.
    ``image_topic``: the frames', whose frame_id ``--gt-tf`` is checked against."""
    if args.gt is not None:
        truth = read_tum(args.gt)
    elif args.gt_tf is not None:
        camera_frame = image_frame(reader, image_topic) if args.gt_camera is None or not args.gt_tf[1] else ""
        parent, child = args.gt_tf
        if not child and not camera_frame.strip("/"):
            raise BagError(f"--gt-tf {parent}: the images on {image_topic} name no frame (an empty header.frame_id); "
                           f"give the camera's frame: --gt-tf {parent}:CHILD")
        truth = tf_ground_truth(reader, args.gt_topic or "/tf", parent, child or camera_frame, camera_frame=camera_frame)
    else:
        truth = bag_ground_truth(reader, args.gt_topic)
    return truth.moved(args.gt_camera) if truth is not None and args.gt_camera is not None else truth


def check_outputs(args: argparse.Namespace, inputs: list[Path]) -> tuple[Path, str]:
    """Stop before any processing when an output would overwrite an input or cannot be written; the plots' folder
    and file-name prefix.

    The summary and the plots are written last, so a bad ``--json`` or ``--plots`` found only then would lose them
    after the whole replay. Beside ``--out`` the plots carry its name, so replays of several bags into one folder
    (``--out results/a.mcap``, ``--out results/b.mcap``) keep each one's plots.
    """
    not_a_folder(args.out, "--out", "nmnet.mcap")  # the rest of --out's checks come as the output is opened
    not_an_input(args.out, "--out", inputs)
    if args.out.suffix != ".mcap" and not args.out.exists():  # an existing file: McapOutput says whose it is
        raise ValueError(f"--out {args.out}: the output is an MCAP file, which ros2 bag, rosbags and nmnet replay know "
                         f"by its .mcap suffix: give {args.out.with_suffix('.mcap')}")
    folder, prefix = (args.plots, "") if args.plots is not None else (args.out.parent, f"{args.out.stem}_")
    plots = {folder / f"{prefix}{name}.png": f"the {name} plot" for name in PLOTS}
    if args.json is not None:  # one would be written over the other
        for other, what in {args.out: "--out", **plots}.items():
            if args.json.resolve() == other.resolve():
                raise ValueError(f"--json {args.json} is also {what}: give the summary its own file, e.g. summary.json")
    output_file(args.json, "--json", "summary.json", inputs)
    if args.plots is not None:
        output_folder(args.plots, "--plots", "the plots", inputs, [p.name for p in plots])
    else:  # --out's folder: checked as the output is opened
        for path in plots:
            not_someone_elses(path, "the plot")
    return folder, prefix


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet replay``: one recording here, several (a glob, ``--manifest``) on Ray."""
    from .options import file_path

    if fleet.several(args.recordings, args.manifest):
        args.out = Path(args.out)
        return fleet.run(FLEET, args)
    try:
        args.bag, args.out = Path(args.recordings[0]), file_path(str(args.out))
    except argparse.ArgumentTypeError as e:
        raise ValueError(f"--out {e}") from None
    return replay_recording(args)


def _replay_into(args: argparse.Namespace, recording: Path, folder: Path) -> int:
    """One recording of a fleet run: its outputs in ``folder`` (nmnet.mcap, summary.json, the plots)."""
    args.bag, args.out, args.json, args.plots, args.no_progress = (recording, folder / "nmnet.mcap",
                                                                   folder / "summary.json", folder, True)
    return replay_recording(args)


def _refused_for_a_fleet(args: argparse.Namespace) -> None:
    fleet.several_refused({"json": args.json, "plots": args.plots, "gt": args.gt, "live": args.live},
                          {"gt": "each recording's ground truth must be in its bag: --gt-topic or --gt-tf",
                           "live": "a live replay plays at recorded timing and needs the cores to itself; replay them offline, "
                           "or live one at a time"})


FLEET = fleet.Job("replay", _replay_into, "summary.json", (
    fleet.Column("frames", "frames", "{}", "sum"), fleet.Column("processed", "processed", "{}", "sum"),
    fleet.Column("dropped", "dropped", "{}", "sum"), fleet.Column("scored_pairs", "pairs scored", "{}", "sum"),
    fleet.Column("auc5", "AUC@5", total="mean", weight="scored_pairs"),
    fleet.Column("fitted_pose_sigma_rotation_deg", "fitted pose_sigma_rotation_deg", "{:.3g}", "mean", "scored_pairs"),
    fleet.Column("fitted_pose_sigma_direction", "fitted pose_sigma_direction", "{:.3g}", "mean", "scored_pairs"),
    fleet.Column("fps", "frames/s", total="mean")), _refused_for_a_fleet)


def replay_recording(args: argparse.Namespace) -> int:
    """One recording: offline through the front end here, or ``--live`` through the node."""
    reader = BagReader(args.bag)  # a missing or unreadable bag stops here
    plots_dir, plots_prefix = check_outputs(args, [reader.path, *reader.files, args.gt, args.camera, args.params_file,
                                                   args.weights])
    params = node_params(args)  # a bad parameters file stops here, naming it
    topics = {"image_topic": args.image_topic, "info_topic": args.info_topic}
    if args.live:
        from .live import live_topics, require_ros

        require_ros()  # no ROS here, or an environment it cannot run in: stop, naming it, before the output file is made
        chosen = live_topics(reader, **topics)  # likewise a ROS 1 bag, a topic it lacks
        if params["pose_estimator"] not in SELECTORS:
            raise ValueError(f"--pose-estimator {params['pose_estimator']}: the node runs {', '.join(SELECTORS)}; "
                             "replay without --live for the others")
    else:
        chosen = choose_topics(reader, **topics)  # a topic the bag lacks stops before the output file
    camera = read_camera_yaml(args.camera, chosen["image"]) if args.camera else None  # a bad file stops here, naming it
    truth = ground_truth(reader, args, chosen["image"])  # likewise a bad --gt file, --gt-topic or --gt-tf
    if args.live:
        if params["weights"]:
            load_model(params["weights"])  # the node would stop on it; stop before the output file is made
        return main_live(args, reader, McapOutput(args.out, pose_sigmas(params)), camera, params, truth, chosen)
    cfg = frontend_config(params)
    fe = Frontend(None, cfg)  # bad weights stop here, before the output file is made
    base_fe = Frontend(None, {**BASELINE, "max_keypoints": cfg["max_keypoints"],
                              "resize_width": cfg["resize_width"]}) if args.baseline else None
    out = McapOutput(args.out, pose_sigmas(params))  # fails before any processing when not writable
    reading = {"camera": camera, "rectified": params["rectified"], "recorded": params["stamp_source"] == "arrival",
               "window": replay_window(args), "max_pixels": params["max_image_pixels"], "sigmas": out.pose_sigmas}
    runs, interrupted = [], False
    try:
        run, n, overlay = process_bag(reader, out, fe, truth, args.debug_images, not args.no_progress, topics, **reading)
        runs.append(run)
        if base_fe is not None:
            base, _, _ = process_bag(reader, None, base_fe, truth, progress=not args.no_progress, topics=topics,
                                     **reading, log=lambda _: None)  # the same frames: said once, by the first pass
            base.name = "SIFT+ratio+MAGSAC++"
            runs.append(base)
    except KeyboardInterrupt:  # Ctrl-C, or SIGTERM (cli.main raises it as Ctrl-C)
        interrupted = True
        print("interrupted: closing the output file", file=sys.stderr)
    finally:
        out.close()
    if not runs:
        print(f"output: {args.out} ({out.count} messages)")
        return 130
    summary = {**runs[0].summary(n), "parameters": params}  # what it ran with, as the node's parameters
    print_summary(summary, runs[0].name)
    if len(runs) > 1:
        summary["baseline"] = runs[1].summary(n)
        print_summary(summary["baseline"], runs[1].name)
    if args.json:  # before the plots: the summary is what a script reads
        write_json(args.json, summary)
    plots_dir.mkdir(parents=True, exist_ok=True)
    for p in write_plots(runs, overlay, plots_dir, plots_prefix):
        print(f"plot: {p}")
    print(f"output: {args.out} ({out.count} messages)")
    return 130 if interrupted else 0


def live_node_args(params: dict) -> list[str]:
    """The node's ``--ros-args`` for a live replay: ``-p`` for each of ``params`` (:func:`node_params`) that is not
    its default, so the node runs with what the offline replay runs with. Not the --params-file itself: rcl would
    apply its ``/robot/nmnet_node`` section to a node in /robot only, and the replay's node is at the root. Values
    are written as config/nmnet.yaml writes them (JSON is YAML rcl reads): a string quoted, so a path stays one."""
    return [a for name, (default, _, _) in PARAMS.items() if params[name] != default
            for a in ("-p", f"{name}:={json.dumps(params[name])}")]


def live_summary(stats: dict, wall: float, scores: dict, tracks: dict, params: dict, interrupted: bool = False) -> dict:
    """A live replay's summary from the player's ``stats`` (:func:`~.live.play_live`), printed: frames published,
    processed, dropped and why (the node's last /diagnostics; ``None`` where no report came), latency, the recording's
    ``scores`` and ``tracks``. ``interrupted``: the replay was stopped, so the last frames were in flight and the node's
    last report (1 Hz) is older than them: the drops are not explained."""
    lat = np.array(stats["latency_ms"]) if stats["latency_ms"] else np.zeros(1)
    processed = stats["results"]  # one ~/matches per processed frame
    diag = stats["diagnostics"]  # the node's last /diagnostics: why frames were dropped
    warnings = {k.removeprefix("warn_"): int(v) for k, v in diag.items() if k.startswith("warn_")}
    summary = {"frames": stats["published"], "processed": processed, "dropped": stats["published"] - processed,
               "received": int(diag["frames_received"]) if diag else None,  # None: no report came from the node
               "dropped_busy": int(diag["frames_dropped"]) if diag else None,
               "fps": processed / wall, "latency_p50_ms": float(np.percentile(lat, 50)),
               "latency_p90_ms": float(np.percentile(lat, 90)), **scores, "tracks": tracks, "warnings": warnings,
               "parameters": params}
    why = (f" ({summary['dropped_busy']} replaced by a newer frame while the node was busy, "
           f"{summary['frames'] - summary['received']} not received)" if diag and summary["dropped"] else "")
    if interrupted:
        summary["interrupted"] = True
        why = " (interrupted: the last frames were in flight)" if summary["dropped"] else " (interrupted)"
    if stats.get("node_exit") is not None:  # the node died: the drops are its, and the bag was not played to its end
        summary["node_exit_code"] = stats["node_exit"]
        why = f" (the node exited with code {stats['node_exit']} during the replay)"
    print(f"live: {summary['processed']}/{summary['frames']} frames processed, {summary['dropped']} dropped{why}, "
          f"latency p50 {summary['latency_p50_ms']:.0f} ms p90 {summary['latency_p90_ms']:.0f} ms")
    if "node_exit_code" in summary:
        print(f"error: nmnet_node exited with code {summary['node_exit_code']} after {summary['frames']} frames were "
              "played; the rest of the bag was not (a negative code is the signal that ended it: -9, SIGKILL, is what "
              "the kernel's out-of-memory killer sends; otherwise the node's log above says why)", file=sys.stderr)
    if warnings:  # frames the node skipped for bad input are among the dropped ones too
        print("   the node's warnings (its /diagnostics): " + ", ".join(f"{k} {v}" for k, v in sorted(warnings.items())))
    print_tracks(summary["tracks"])
    print_scores(summary)
    return summary


def main_live(args: argparse.Namespace, reader: BagReader, out: McapOutput, camera: Camera | None, params: dict,
              truth: Trajectory | None = None, topics: dict[str, str | None] | None = None) -> int:
    """Live mode: play into the node, record, score like the offline mode."""
    from .live import NodeNotReady, new_stats, play_live, recording_summary

    t0 = time.perf_counter()
    stats, interrupted = new_stats(), False  # filled as it plays: an interrupted replay sums up what it recorded
    try:
        recorded = params["stamp_source"] == "arrival"  # the player stamps frames as the bag recorded them; the node keeps it
        node_args = live_node_args({**params, "stamp_source": "header"})
        play_live(reader, out, args.rate, node_args, camera=camera, topics=topics, recorded=recorded,
                  window=replay_window(args), stats=stats)
    except KeyboardInterrupt:  # Ctrl-C, or SIGTERM (cli.main raises it as Ctrl-C)
        interrupted = True
        print("interrupted: closing the output file", file=sys.stderr)
    except NodeNotReady as e:  # nothing played: the output closes empty, readable
        print(f"nmnet replay: error: {e}", file=sys.stderr)
        return 1
    finally:
        out.close()
        for w in reader.new_warnings():  # a damaged or split bag, pose topics not taken as ground truth
            print(f"warning: {w}")
    wall = time.perf_counter() - t0
    summary = live_summary(stats, wall, *recording_summary(args.out, truth, out.pose_sigmas, stats["stamps"]), params,
                           interrupted)
    print(f"output: {args.out} ({out.count} messages)")
    if args.json:
        write_json(args.json, summary)
    return 130 if interrupted else 1 if "node_exit_code" in summary else 0
