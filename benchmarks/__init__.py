"""The published numbers: each table of the README and the docs is one named experiment here.

``python -m benchmarks run NAME`` runs an experiment (an ``nmnet`` command) and stores its result with its
provenance (command, commit, weights checksum, settings, machine, date) in ``benchmarks/results/NAME.json``;
``python -m benchmarks render`` writes the tables into the pages, between ``<!-- benchmark: NAME -->`` and
``<!-- /benchmark -->``. ``test/test_benchmarks.py`` checks that every published table is the rendering of its
stored result, so a number cannot drift from its source.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from nmnet_ros.core.settings import DEFAULT_METHOD as DEFAULT

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DATA = ROOT.parent / "shared" / "data"  # the maintainers' datasets (not shipped; see docs/data-format.md)
SAMPLE = ROOT / "nmnet_ros" / "sample" / "kitti07_120-159"
WEIGHTS = ROOT / "nmnet_ros" / "weights" / "nmnet.pt"
PAGES = (ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")))
VALIDATION = (f"{DATA}/kitti-07:120-159", f"{DATA}/strecha-herz-jesus-p25")  # never trained on (the model card)


@dataclass(frozen=True)
class Experiment:
    """One published table: what it measures, the ``nmnet`` arguments that measure it ({out}: the JSON it writes,
    {tmp}: a scratch folder), and how its stored result renders."""

    what: str
    args: tuple[str, ...]  # empty: the experiment is ``steps``, its result made by ``combine``
    render: Callable[[dict], str] | None  # None: a part of a COMBINED table
    needs_data: bool = False
    steps: tuple[tuple[str, ...], ...] = ()  # several commands, each timed, one after the other
    combine: Callable[[Path, list[dict]], dict] | None = None  # the result from the steps' outputs in {tmp} and times
    prepare: Callable[[Path], None] | None = None  # makes the steps' inputs in {tmp}


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def render_sample_bag(r: dict) -> str:
    """The default front end beside the classic pipeline on the bundled sample bag."""
    rows = ["| pipeline (sample bag, 39 pairs) | AUC@5 / 10 / 20 | median rotation / direction error (deg) | pose sigmas "
            "that fit the errors: rotation (deg) / direction | frames/s |", "|---|---|---|---|---|"]
    for name, s in ((f"learned: {method_label(DEFAULT)}", r), ("classic: SIFT + ratio + MAGSAC++", r["baseline"])):
        rows.append(f"| {name} | {_pct(s['auc5'])} / {_pct(s['auc10'])} / {_pct(s['auc20'])} | "
                    f"{s['median_rot_deg']:.3f} / {s['median_trans_deg']:.2f} | "
                    f"{s['fitted_pose_sigma_rotation_deg']:.3f} / {s['fitted_pose_sigma_direction']:.3f} | {s['fps']:.1f} |")
    return "\n".join(rows) + ("\n\nThe pose sigmas: pose_sigma_rotation_deg and pose_sigma_direction (per axis, at 200 matches) "
                              "at which the published covariance fits these errors; the defaults are "
                              f"{r['parameters']['pose_sigma_rotation_deg']:g} and {r['parameters']['pose_sigma_direction']:g}.")


METHOD_NAMES = {"nmnet+ratio+magsac": "NM-Net + ratio + MAGSAC++", "ratio+magsac": "classic: ratio + MAGSAC++",
                "nmnet+magsac": "NM-Net + MAGSAC++", "nn+magsac": "MAGSAC++ on all matches", "oracle": "oracle (true inliers + MAGSAC++)",
                "nmnet": "NM-Net alone (weighted eight-point)", "ratio": "ratio test alone",
                "ratio+poselib": "classic with PoseLib: ratio + PoseLib",
                "ratio+prosac": "PoseLib PROSAC on mutual matches of ratio < 0.9 in ratio order",
                "nmnet+prosac": "NM-Net's order + PoseLib PROSAC on mutual matches of ratio < 0.9",
                "oracle+prosac": "the true inliers' order + PoseLib PROSAC on mutual matches of ratio < 0.9",
                "oracle-pool": "the true inliers among mutual matches of ratio < 0.9 + MAGSAC++"}


def method_label(method: str) -> str:
    """A method's name in the tables, the default's marked."""
    return METHOD_NAMES.get(method, method) + (" (default)" if method == DEFAULT else "")


def render_validation(r: dict) -> str:
    """Every method on the validation split: classification (P/F) and pose (AUC, difference to the reference)."""
    from nmnet_ros.tools.evaluate import auc_cell

    ref = r.get("reference")
    rows = [f"| method | P | F | AUC@5 (minus {ref}'s [95 %]) | AUC@10 | AUC@20 | median rot / dir (deg) |",
            "|---|---|---|---|---|---|---|"]
    for name, m in r["methods"].items():
        auc = auc_cell({**m, "vs_reference": r.get("auc5_vs_reference", {}).get(name)})
        rows.append(f"| {method_label(name)} | {m['precision']:.1f} | {m['f1']:.1f} | {auc} | "
                    f"{m['auc10']:.1f} | {m['auc20']:.1f} | {m['median_rot_deg']:.2f} / {m['median_trans_deg']:.2f} |")
    pairs = next(iter(r["methods"].values()))["pairs"]
    return "\n".join(rows) + f"\n\n{pairs} pairs."


def _hard_row(label: str, r: dict, method: str) -> str:
    """One method's row of the hard table: AUC@5 per inlier-ratio bin and over all pairs [difference, 95 %]."""
    from nmnet_ros.tools.evaluate import BIN_ORDER, auc_cell

    bins = sorted(r["bins"]["inlier_ratio"].items(), key=lambda kv: BIN_ORDER[kv[0]])
    overall = {**r["methods"][method], "vs_reference": r.get("auc5_vs_reference", {}).get(method)}
    cells = [auc_cell(b[method]) for _, b in bins] + [auc_cell(overall)]
    return f"| {label} | " + " | ".join(cells) + " |"


def render_hard_pairs() -> str:
    """The hard validation set: AUC@5 per putative-inlier-ratio bin and over all pairs, with the difference to the
    classic pipeline and its 95 % interval; the default also without its classic fallback (a run of its own)."""
    from nmnet_ros.tools.evaluate import BIN_ORDER, ap_cell, prf_cell

    main, plain = _stored("hard-validation"), _stored("hard-validation-no-fallback")
    r = main["result"]
    bins = sorted(r["bins"]["inlier_ratio"].items(), key=lambda kv: BIN_ORDER[kv[0]])
    head = " | ".join(f"{name} ({b['pairs']})" for name, b in bins)
    rows = [f"| AUC@5 by putative inlier ratio (pairs) | {head} | all ({next(iter(r['methods'].values()))['pairs']}) |",
            "|---" * (len(bins) + 2) + "|"]
    for method in r["methods"]:
        if method == "nmnet":  # its pose is the weighted eight-point, no pipeline's: its selection is the next table's
            continue
        rows.append(_hard_row(method_label(method), r, method))
        if method == "nmnet+ratio+magsac":
            rows.append(_hard_row("... the same, fallback_min_inliers 0 (no classic fallback)", plain["result"], method))
    rows += ["", f"| precision / recall (%) by putative inlier ratio | {head} | all |", "|---" * (len(bins) + 2) + "|"]
    for method, label in (("nmnet", "NM-Net's selection"), ("ratio+magsac", "classic: the inliers of ratio + MAGSAC++"),
                          (DEFAULT, "default: the inliers of its fit")):
        cells = [prf_cell(x) for x in [b[method] for _, b in bins] + [r["methods"][method]]]
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    rows += ["", f"| average precision (%) of the order by putative inlier ratio | {head} | all |",
             "|---" * (len(bins) + 2) + "|"]
    for method, label in (("nmnet", "NM-Net's scores (the default's order)"), ("ratio+prosac", "the ratio, lowest first")):
        cells = [ap_cell(x) for x in [b[method] for _, b in bins] + [r["methods"][method]]]
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    m = main["provenance"]["machine"]
    return "\n".join(rows) + (
        f"\n\nIn brackets: the difference to {r.get('reference')} on the same pairs [95 % interval]. Precision and "
        "recall: of the matches each keeps, against the ground-truth labels. Average precision: of all putative matches "
        "ranked in the order, against the labels (the mean precision at each labelled inlier's rank).\n\n<sub>"
        f"{main['what'][0].upper() + main['what'][1:]}. Measured on {m['cpu']} ({m['cores']} cores) by "
        f"`{main['provenance']['command']}`, and the row without the fallback by `{plain['provenance']['command']}`; "
        "stored with their provenance in `benchmarks/results/hard-validation.json` and "
        "`hard-validation-no-fallback.json`, rerun with `python -m benchmarks run hard-validation` and "
        "`... run hard-validation-no-fallback`.</sub>\n")


def render_labels(r: dict) -> str:
    """How the labels of a reconstruction agree with the real ground truth."""
    c = r["truth_check"]
    return ("| keyframes registered | mean reprojection error | consecutive pairs | median rotation error | "
            "median direction error | same epipolar label |\n|---|---|---|---|---|---|\n"
            f"| {r['registered']} of {r['keyframes']} | {r['mean_reprojection_px']:.2f} px | {c['pairs']} | "
            f"{c['median_rot_deg']:.3f} deg | {c['median_trans_deg']:.2f} deg | {c['label_agreement_percent']:.1f} % of "
            f"{c['matches']} matches |")


TRAINING = (f"{DATA}/kitti-07:0-119", f"{DATA}/strecha-fountain-p11", f"{DATA}/strecha-entry-p10")  # the model card's


def _threshold_run(px: str) -> tuple[str, ...]:
    return ("eval", *TRAINING, "--gaps", "1-10", "--stride", "4", "--methods", "ratio+magsac,nmnet+ratio+magsac",
            "--pose-threshold-px", px, "--nmnet-precision", "float32", "--json", "{out}", "--plots", "{tmp}")


def render_threshold() -> str:
    """Why pose_threshold_px is 0.15: both pipelines at 0.15 and at the usual 1 px, on training pairs."""
    rows = ["| MAGSAC++ threshold | classic: ratio + MAGSAC++ AUC@5 | NM-Net + ratio + MAGSAC++ AUC@5 | pairs |", "|---|---|---|---|"]
    for name, px in (("threshold-0.15px", "0.15 px (default)"), ("threshold-1px", "1 px")):
        m = _stored(name)["result"]["methods"]
        rows.append(f"| {px} | {m['ratio+magsac']['auc5']:.1f} | {m['nmnet+ratio+magsac']['auc5']:.1f} | "
                    f"{m['ratio+magsac']['pairs']} |")
    return "\n".join(rows) + ("\n\n<sub>Training pairs (the model card's training scenes, every 4th frame's pairs at "
                              "gaps 1-10); from `benchmarks/results/threshold-0.15px.json` and `threshold-1px.json`, "
                              "each with its command and provenance.</sub>\n")


def render_speed(r: dict) -> str:
    """Per-stage times and rates, and the ratio to the classic pipeline timed in the same process."""
    rows = ["| frames, keypoints | detect | match | neighbours | NM-Net | pose | pipelined Hz | classic (SIFT) Hz | ratio |",
            "|---|---|---|---|---|---|---|---|---|"]
    for size, s in r["pipeline"].items():
        if "detect" not in s:
            continue
        frames, n = size.rsplit("_N", 1)
        rows.append(f"| {frames.replace('native', 'KITTI 1241x376')}, {n} | {s['detect']['median']:.0f} | "
                    f"{s['match']['median']:.0f} | {s['neighbors']['median']:.0f} | {s['nmnet']['median']:.0f} | "
                    f"{s['pose']['median']:.0f} | {s['end_to_end_hz']:.1f} | {s['baseline_hz']:.1f} | "
                    f"{s['end_to_end_hz'] / s['baseline_hz']:.2f}x |")
    return "\n".join(rows) + ("\n\nStage times: median ms, one stage after the other; pipelined: the node's two stages, "
                               "one thread each, side by side.")


def render_neighbors(r: dict) -> str:
    """The paper's Fig. 3: inliers among a true match's neighbours, compatibility against spatial."""
    rows = ["| pair's inlier ratio | pairs | inliers among compatibility neighbours | among spatial neighbours |",
            "|---|---|---|---|"]
    rows += [f"| {b['bucket']} | {b['pairs']} | {b['compatibility']:.1f} % | {b['spatial']:.1f} % |" for b in r["table"]]
    return "\n".join(rows) + (f"\n\nCompatibility neighbours hold more inliers than spatial ones in "
                              f"{r['compat_wins_percent']:.0f} % of the {r['pairs']} pairs.")


ADAPT_TEST = f"{DATA}/kitti-07:120-159"  # evaluated with its real ground truth, never trained on
ADAPT_RUNS = {"before": "Strecha only (before adaptation)", "adapted": "fine-tuned on `nmnet label`'s labels",
              "truth": "fine-tuned on the real ground truth"}


ADAPT_POSE = ("nmnet+prosac", "nmnet+ratio+magsac", "nmnet+magsac", "ratio+magsac", "ratio+prosac")  # the table's columns


def _adaptation_steps() -> tuple[tuple[str, ...], ...]:
    """Weights that never saw KITTI, fine-tuned on KITTI-07 frames 0-119 labelled by ``nmnet label`` and, beside
    them, on the real ground truth of the same frames (frames 0-99 train, 100-119 pick the checkpoint, as a user
    would hold out the end of a recording); all three evaluated on frames 120-159 with the real ground truth."""
    common = ("--epochs", "8", "--augment")
    fine_tune = {"adapted": ("{tmp}/labelled:0-99", "{tmp}/labelled:100-119"),
                 "truth": (f"{DATA}/kitti-07:0-99", f"{DATA}/kitti-07:100-119")}
    steps = [("label", f"{DATA}/kitti-07:0-119", "--out", "{tmp}/labelled", "--json", "{tmp}/label.json"),
             ("train", "--train", f"{DATA}/strecha-fountain-p11", f"{DATA}/strecha-entry-p10", "--val",
              f"{DATA}/strecha-herz-jesus-p25", "--out", "{tmp}/before", "--epochs", "20", "--augment")]
    steps += [("train", "--train", train, "--val", val, "--out", "{tmp}/" + run, "--init", "{tmp}/before/best.pt", *common)
              for run, (train, val) in fine_tune.items()]
    steps += [("eval", ADAPT_TEST, "--methods", f"nmnet,{','.join(ADAPT_POSE)}", "--weights",
               "{tmp}/" + run + "/best.pt", "--nmnet-precision", "float32", "--json", "{tmp}/eval-" + run + ".json",
               "--plots", "{tmp}") for run in ADAPT_RUNS]
    return tuple(steps)


def _adaptation_result(tmp: Path, _steps: list[dict]) -> dict:
    """The three evaluations and the labelling summary."""
    runs = {run: json.loads((tmp / f"eval-{run}.json").read_text()) for run in ADAPT_RUNS}
    for r in runs.values():
        r.pop("written_by", None)
    label = json.loads((tmp / "label.json").read_text())
    return {"runs": runs, "label": {k: label[k] for k in ("keyframes", "registered", "mean_reprojection_px")}}


def _step_name(command: str) -> str:
    """A step of a stored run by its tool, and for ``train`` its output: "label", "train OUT/before"."""
    words = command.split()
    return f"{words[1]} {words[words.index('--out') + 1]}" if words[1] == "train" else words[1]


def render_adaptation(r: dict) -> str:
    """Adaptation: NM-Net's F and the pipelines' AUC@5 on the held-out frames, and what each step cost."""
    rows = ["| weights | NM-Net F | AUC@5: " + " | ".join(method_label(m) for m in ADAPT_POSE) + " |",
            "|---|---|" + "---|" * len(ADAPT_POSE)]
    for run, name in ADAPT_RUNS.items():
        m = r["runs"][run]["methods"]
        rows.append(f"| {name} | {m['nmnet']['f1']:.1f} | " + " | ".join(f"{m[k]['auc5']:.1f}" for k in ADAPT_POSE) + " |")
    pairs = r["runs"]["before"]["methods"]["nmnet"]["pairs"]
    cost = {_step_name(s["command"]): s for s in r["steps"]}
    rows += ["", "| step | minutes | peak memory |", "|---|---|---|"]
    for step, what in (("label", f"`nmnet label`, {r['label']['keyframes']} KITTI frames"),
                       ("train OUT/before", "train from scratch on Strecha (20 epochs)"),
                       ("train OUT/adapted", "fine-tune on the labels (8 epochs)")):
        rows.append(f"| {what} | {cost[step]['seconds'] / 60:.1f} | {cost[step]['peak_memory_mb'] / 1024:.1f} GB |")
    return "\n".join(rows) + f"\n\n{pairs} pairs of KITTI-07 frames 120-159 (gaps 1-10), scored with the real ground truth."


FLEET_COPIES = 8  # recordings of the fleet benchmark: copies of the sample bag


def _fleet_copies(tmp: Path) -> None:
    for i in range(FLEET_COPIES):
        shutil.copytree(SAMPLE, tmp / f"rec{i}")


def _fleet_steps() -> tuple[tuple[str, ...], ...]:
    """A shell loop running ``nmnet replay`` once per recording, then one ``nmnet replay`` of them all (local Ray)."""
    loop = tuple(("replay", f"{{tmp}}/rec{i}", "--out", f"{{tmp}}/loop/rec{i}.mcap", "--no-progress")
                 for i in range(FLEET_COPIES))
    return (*loop, ("replay", *(f"{{tmp}}/rec{i}" for i in range(FLEET_COPIES)), "--out", "{tmp}/fleet", "--no-progress"))


def _fleet_result(tmp: Path, steps: list[dict]) -> dict:
    """Both ways' wall times, their ratio and the fleet run's frames (from its report)."""
    report = json.loads((tmp / "fleet" / "report.json").read_text())
    loop_s, fleet_s = sum(s["seconds"] for s in steps[:-1]), steps[-1]["seconds"]
    return {"recordings": FLEET_COPIES, "loop_seconds": round(loop_s, 1), "fleet_seconds": fleet_s,
            "ratio": loop_s / fleet_s, "frames": report["totals"]["processed"], "cores": os.cpu_count(),
            "driver_peak_memory_mb": steps[-1]["peak_memory_mb"]}  # the command's own (its report: summaries only)


def render_fleet(r: dict) -> str:
    """The fleet run beside a shell loop, and what it means for a fleet's hours of video."""
    per_core = r["frames"] / r["fleet_seconds"] / r["cores"]  # frames a core replays per second, start-up included
    core_hours = 36000 / per_core / 3600  # per hour of 10 Hz video
    return (f"| {r['recordings']} copies of the sample bag ({r['frames']} frames) | wall time | |\n|---|---|---|\n"
            f"| shell loop: `nmnet replay` once per recording | {r['loop_seconds']:.0f} s | 1.00x |\n"
            f"| one `nmnet replay` of all of them (local Ray, {r['cores']} cores) | {r['fleet_seconds']:.0f} s | "
            f"{r['ratio']:.2f}x |\n\nA core replays {per_core:.1f} frames/s here (start-up included): one hour of "
            f"10 Hz video (36,000 frames) takes {core_hours:.1f} core-hours, so N hours of a fleet's video take "
            f"N x {core_hours:.1f} core-hours: 200 one-hour recordings in 8 hours need about "
            f"{200 * core_hours / 8:.0f} such cores.")


EXPERIMENTS: dict[str, Experiment] = {
    "sample-bag": Experiment(
        "the bundled sample bag offline, the default front end beside SIFT + ratio + MAGSAC++ on the same frames",
        ("replay", str(SAMPLE), "--out", "{tmp}/out.mcap", "--json", "{out}", "--baseline", "--no-progress",
         "--nmnet-precision", "float32"), render_sample_bag),
    "validation": Experiment(
        "every selector on the validation split (pairs at gaps 1-10 of two scenes never trained on)",
        ("eval", *VALIDATION, "--gaps", "1-10", "--methods", "nmnet,ratio,nn+magsac,ratio+magsac,nmnet+magsac,"
         "nmnet+ratio+magsac,ratio+poselib,ratio+prosac,nmnet+prosac,oracle+prosac,oracle", "--nmnet-precision", "float32",
         "--json", "{out}",
         "--plots", "{tmp}"),
        render_validation, needs_data=True),
    "hard-validation": Experiment(
        "the hard validation set: the validation scenes at frame gaps up to 30 and views up to 60 degrees apart",
        ("eval", *VALIDATION, "--gaps", "1-30", "--max-view-angle", "60", "--methods",
         "nmnet,ratio+magsac,nmnet+magsac,nmnet+ratio+magsac,ratio+poselib,ratio+prosac,nmnet+prosac,oracle+prosac,"
         "oracle-pool,oracle",
         "--seeds", "3",
         "--nmnet-precision", "float32",
         "--json", "{out}", "--plots", "{tmp}"), None, needs_data=True),
    "hard-validation-no-fallback": Experiment(
        "the hard validation set with fallback_min_inliers 0: the learned fit's pose on every pair",
        ("eval", *VALIDATION, "--gaps", "1-30", "--max-view-angle", "60", "--methods", "ratio+magsac,nmnet+ratio+magsac",
         "--fallback-min-inliers", "0", "--seeds", "3", "--nmnet-precision", "float32", "--json", "{out}", "--plots",
         "{tmp}"), None, needs_data=True),
    "labels": Experiment(
        "`nmnet label` on KITTI-07 frames 0-119 with the ground truth withheld, checked against it afterwards",
        ("label", f"{DATA}/kitti-07:0-119", "--out", "{tmp}/labelled", "--truth", f"{DATA}/kitti-07", "--json", "{out}"),
        render_labels, needs_data=True),
    "adaptation": Experiment(
        "weights that never saw KITTI, adapted to KITTI-07 with nmnet label's labels, beside the same fine-tune on "
        "the real ground truth", (), render_adaptation, needs_data=True, steps=_adaptation_steps(),
        combine=_adaptation_result),
    "fleet": Experiment(
        f"{FLEET_COPIES} recordings replayed by one command on the local Ray runtime, beside a shell loop over them",
        (), render_fleet, steps=_fleet_steps(), combine=_fleet_result, prepare=_fleet_copies),
    "threshold-0.15px": Experiment("pose_threshold_px at its default, on training pairs", _threshold_run("0.15"), None,
                                   needs_data=True),
    "threshold-1px": Experiment("pose_threshold_px at 1 px, on training pairs", _threshold_run("1.0"), None,
                                needs_data=True),
    "speed": Experiment(
        "per-stage times and the pipelined rate on this machine, beside the classic pipeline in the same process",
        ("bench", "--pipeline", "--json", "{out}"), render_speed),
    "neighbors": Experiment(
        "the paper's Fig. 3 on KITTI-07: inlier ratio among a true match's neighbours",
        ("neighbors", f"{DATA}/kitti-07", "--gaps", "1-10", "--stride", "10", "--json", "{out}"), render_neighbors,
        needs_data=True),
}


def render_summary() -> str:
    """The README's table: the learned front end and the classic pipeline, one line each, from the stored results."""
    val = _stored("validation")["result"]["methods"]
    hard = _stored("hard-validation")["result"]["methods"]
    bag = _stored("sample-bag")["result"]
    speed = _stored("speed")["result"]["pipeline"]["native_N2000"]
    rows = ["| front end | AUC@5, validation split | AUC@5, hard validation set | AUC@5, sample bag | frames/s, KITTI "
            "1241x376 |", "|---|---|---|---|---|"]
    rows.append(f"| learned: {method_label(DEFAULT)} | {val[DEFAULT]['auc5']:.1f} | {hard[DEFAULT]['auc5']:.1f} | "
                f"{bag['auc5']:.1f} | {speed['end_to_end_hz']:.1f} (pipelined, the node's schedule) |")
    rows.append(f"| classic: ratio + MAGSAC++ | {val['ratio+magsac']['auc5']:.1f} | {hard['ratio+magsac']['auc5']:.1f} | "
                f"{bag['baseline']['auc5']:.1f} | {speed['baseline_hz']:.1f} (SIFT, serial) |")
    rows.append(f"| classic with the default's fit: {METHOD_NAMES['ratio+prosac']} | {val['ratio+prosac']['auc5']:.1f} | "
                f"{hard['ratio+prosac']['auc5']:.1f} | - | - |")
    p = _stored("speed")["provenance"]["machine"]
    return "\n".join(rows) + (f"\n\n<sub>From `benchmarks/results/` (validation, hard-validation, sample-bag, speed: "
                              f"each with its command and provenance), measured on {p['cpu']} ({p['cores']} cores); the "
                              "full tables are in docs/evaluation.md and docs/speed.md.</sub>\n")


def _stored(name: str) -> dict:
    return json.loads((RESULTS / f"{name}.json").read_text())


def machine() -> dict:
    """The machine a result was measured on."""
    cpu = platform.processor()
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "system": platform.platform(), "python": platform.python_version()}


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=False).stdout.strip()


def provenance() -> dict:
    """Where a result comes from (taken before it runs): enough to rerun it and to judge it."""
    from nmnet_ros.core.settings import FRONTEND_DEFAULTS
    from nmnet_ros.ros.entry import version

    return {"version": version(), "commit": _git("rev-parse", "HEAD"),
            "uncommitted_changes": bool(_git("status", "--porcelain", "--untracked-files=no", "--", ".",
                                             ":!benchmarks/results")),  # the stored results are not the code
            "weights_sha256": hashlib.sha256(WEIGHTS.read_bytes()).hexdigest(), "settings": FRONTEND_DEFAULTS,
            "machine": machine(), "date": datetime.now(UTC).isoformat(timespec="seconds")}


def _timed(args: list[str]) -> dict:
    """Run one ``nmnet`` command; its wall time and peak memory (the child's own, from wait4)."""
    t0 = time.perf_counter()
    child = subprocess.Popen([sys.executable, "-m", "nmnet_ros.tools.cli", *args], cwd=ROOT)
    _, status, usage = os.wait4(child.pid, 0)  # reaped here: Popen's own wait would not see the child's usage
    child.returncode = os.waitstatus_to_exitcode(status)  # told to Popen, which would warn of a child still running
    if child.returncode:
        raise subprocess.CalledProcessError(child.returncode, ["nmnet", *args])
    return {"seconds": round(time.perf_counter() - t0, 1), "peak_memory_mb": round(usage.ru_maxrss / 1024)}


def run(name: str) -> Path:
    """Run experiment ``name`` and store its result with its provenance; returns the stored file."""
    exp = EXPERIMENTS[name]
    if exp.needs_data and not DATA.is_dir():
        raise SystemExit(f"{name}: needs the datasets at {DATA}")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "result.json"

        def shown(args: list[str]) -> str:
            return "nmnet " + " ".join(a.replace(str(ROOT.parent / "shared"), "../shared").replace(str(ROOT) + "/", "")
                                       .replace(str(out), "OUT/result.json").replace(tmp, "OUT") for a in args)

        source, t0 = provenance(), time.perf_counter()
        if exp.steps:
            if exp.prepare is not None:
                exp.prepare(Path(tmp))
            steps = [[a.format(out=out, tmp=tmp) for a in step] for step in exp.steps]
            timed = [{"command": shown(step), **_timed(step)} for step in steps]
            result, command = {**exp.combine(Path(tmp), timed), "steps": timed}, " && ".join(t["command"] for t in timed)
        else:
            args = [a.format(out=out, tmp=tmp) for a in exp.args]
            subprocess.run([sys.executable, "-m", "nmnet_ros.tools.cli", *args], cwd=ROOT, check=True)
            result, command = json.loads(out.read_text()), shown(args)
        source = {"command": command, **source, "seconds": round(time.perf_counter() - t0, 1)}
        stored = {"experiment": name, "what": exp.what, "provenance": source,
                  "result": {k: v for k, v in result.items() if k != "written_by"}}
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(stored, indent=1) + "\n")
    return path


# tables made of several experiments' results: name -> (the experiments, the renderer)
COMBINED: dict[str, tuple[tuple[str, ...], Callable[[], str]]] = {
    "summary": (("validation", "hard-validation", "sample-bag", "speed"), render_summary),
    "threshold": (("threshold-0.15px", "threshold-1px"), render_threshold),
    "hard-pairs": (("hard-validation", "hard-validation-no-fallback"), render_hard_pairs),
}

BLOCK = re.compile(r"(<!-- benchmark: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /benchmark -->)", re.S)


def rendered(name: str) -> str:
    """Experiment ``name``'s table from its stored result, with where it came from ('summary': the README's)."""
    if name in COMBINED:
        return COMBINED[name][1]()
    stored = _stored(name)
    p = stored["provenance"]
    what = stored["what"][0].upper() + stored["what"][1:]  # its names as they are written (KITTI, nmnet)
    return (EXPERIMENTS[name].render(stored["result"]) + f"\n\n<sub>{what}. Measured on "
            f"{p['machine']['cpu']} ({p['machine']['cores']} cores) by `{p['command']}`; stored with its provenance in "
            f"`benchmarks/results/{name}.json`, rerun with `python -m benchmarks run {name}`.</sub>\n")


def render_page(text: str) -> str:
    """``text`` with every benchmark block replaced by its stored result's rendering."""
    return BLOCK.sub(lambda m: m.group(1) + rendered(m.group("name")) + m.group(4), text)


def main(argv: list[str]) -> int:
    """``python -m benchmarks run NAME...|all`` or ``python -m benchmarks render``."""
    if argv[:1] == ["run"] and len(argv) > 1:
        for name in (EXPERIMENTS if argv[1:] == ["all"] else argv[1:]):
            print(f"{name}: {run(name)}")
        return 0
    if argv == ["render"]:
        for page in PAGES:
            text = page.read_text()
            if (new := render_page(text)) != text:
                page.write_text(new)
                print(f"rendered {page.relative_to(ROOT)}")
        return 0
    print(f"usage: python -m benchmarks run NAME...|all  (names: {', '.join(EXPERIMENTS)}) | python -m benchmarks render",
          file=sys.stderr)
    return 2
