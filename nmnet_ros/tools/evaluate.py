"""``nmnet eval``: every selector on the same putative matches, against ground truth.

Per method: precision / recall / F-measure of the selected matches (mean over pairs, the
paper's P/R/F), the average precision (AP) of the order it ranks the matches in where it has one
(NM-Net's scores, the ratio's), pose AUC@5/10/20 and median rotation/translation errors (a failed
pair counts as 180 degrees), and selection + pose time per pair. With ``--seeds N`` every method with a
MAGSAC++/RANSAC stage runs N times per pair with different random samples and the metrics average
over the runs: on hard pairs one seed's luck moves a method's AUC@5 by a few tenths, about the
size of the differences between the best pipelines.
"""

from __future__ import annotations

import argparse
import bisect
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.detectors import make_detector
from ..core.geometry import pose_auc, pose_error_deg
from ..core.metrics import average_precision, prf
from ..core.model import NEIGHBORS, load_model
from ..core.model_fast import precision_note
from ..core.selectors import METHODS, NETWORK, ROBUST, build
from ..core.settings import POSE_ESTIMATORS, unread
from ..io.cache import FeatureCache, default_cache_dir
from ..io.outputs import output_file, save_figure, write_json
from ..io.pairs import PairData, absolute_spec, load_pairs, parse_seq_spec, shared_frames, spec_label, to_correspondences, to_stderr
from ..io.progress import progress
from . import fleet


@dataclass
class Runs:
    """One method's runs on a list of pairs: what a folder's task returns (no frame data), merged by concatenation."""

    prfs: np.ndarray  # (pairs, seeds, 3): every run's precision, recall, F (%); NaN on a pair without a labelled inlier
    errors: np.ndarray  # (pairs, seeds, 2): every run's rotation and translation error, degrees
    secs: list[float]  # each pair's time of one full run (selection + pose)
    aps: np.ndarray  # (pairs,): the average precision (%) of the method's order; NaN without an order or a labelled inlier


def score(pairs: list[PairData], methods: list[str], weights: dict[str, str] | None = None,
          config: dict | None = None, seeds: int = 1, log: Callable[[str], None] = to_stderr) -> dict[str, Runs]:
    """Run every method on every pair. Methods with a robust estimator run once per seed 0..seeds-1, the others
    (deterministic) once, their one run standing for every seed."""
    if seeds < 1:
        raise ValueError(f"--seeds must be >= 1 (runs of each robust estimator per pair), got {seeds}")
    out = {}
    for name in methods:
        select = build(name, config, weights)
        runs = seeds if name in ROBUST else 1
        prfs, errs, secs, aps, t_method = [], [], [], [], time.perf_counter()
        for p in progress(pairs, name, "pair"):
            c = to_correspondences(p)
            t0 = time.perf_counter()
            sels = [select(c, seed=0) if name in ROBUST else select(c)]
            secs.append(time.perf_counter() - t0)  # one full run; further seeds reuse NM-Net's pass
            sels += [select(c, seed=s) for s in range(1, runs)]
            # P/R/F need a labelled inlier; the pose is scored all the same
            scored = [prf(sel.mask, p.labels) if p.labels.any() else dict.fromkeys(PRF, np.nan) for sel in sels]
            prfs.append([[m[k] for k in PRF] for m in scored] * (seeds // runs))
            errs.append([pose_error_deg(sel.pose, p.R, p.t) for sel in sels] * (seeds // runs))
            order = sels[0].scores  # the method's order (NM-Net's, the ratio's); the seeds share it
            aps.append(np.nan if order is None else average_precision(order, p.labels))
        out[name] = Runs(np.array(prfs, np.float64).reshape(len(pairs), seeds, 3),
                         np.array(errs, np.float64).reshape(len(pairs), seeds, 2), secs, np.array(aps, np.float64))
        log(f"eval: {name}: {len(pairs)} pairs x {runs} run(s) in {time.perf_counter() - t_method:.0f} s")
    return out


PRF = ("precision", "recall", "f1")


def mean_prf(prfs: np.ndarray) -> dict[str, float | None]:
    """Mean precision, recall and F (%) over the runs on pairs with a labelled inlier; None where there are none."""
    defined = prfs[~np.isnan(prfs[..., 0])]
    return {k: float(defined[:, i].mean()) if len(defined) else None for i, k in enumerate(PRF)}


def mean_ap(aps: np.ndarray) -> float | None:
    """Mean average precision (%) over the pairs where it is defined; None where it is nowhere (no order, no inlier)."""
    defined = aps[~np.isnan(aps)]
    return float(defined.mean()) if len(defined) else None


def summarize(runs: dict[str, Runs]) -> dict:
    """{"metrics": {method: metrics}, "errors": {method: (pairs, seeds) errors}, "prfs": {method: (pairs, seeds, 3)},
    "aps": {method: (pairs,)}}:
    each metric is the mean over all runs, except the time, that of one run; a pair's error is the larger of its
    rotation and translation errors."""
    out, errors = {}, {}
    for name, r in runs.items():
        e = r.errors
        aucs = pose_auc(e.max(2).ravel())
        out[name] = {
            **mean_prf(r.prfs), "ap": mean_ap(r.aps),
            "auc5": 100 * aucs[0], "auc10": 100 * aucs[1], "auc20": 100 * aucs[2],
            "median_rot_deg": float(np.median(e[..., 0])), "median_trans_deg": float(np.median(e[..., 1])),
            "pairs": len(e), "sec_per_pair": float(np.mean(r.secs)),
        }
        errors[name] = e.max(2)
    return {"metrics": out, "errors": errors, "prfs": {name: r.prfs for name, r in runs.items()},
            "aps": {name: r.aps for name, r in runs.items()}}


def merge(parts: list[dict[str, Runs]]) -> dict[str, Runs]:
    """Several folders' runs as one list of pairs, in the order given (the bootstrap draws by position)."""
    return {name: Runs(np.concatenate([p[name].prfs for p in parts]), np.concatenate([p[name].errors for p in parts]),
                       [x for p in parts for x in p[name].secs], np.concatenate([p[name].aps for p in parts]))
            for name in parts[0]}


def evaluate(pairs: list[PairData], methods: list[str], weights: dict[str, str] | None = None,
             config: dict | None = None, seeds: int = 1) -> dict:
    """Every method on every pair (:func:`score`), summarized (:func:`summarize`)."""
    return summarize(score(pairs, methods, weights, config, seeds))


def paired_auc_difference(errors: np.ndarray, reference: np.ndarray, threshold: float = 5.0,
                          resamples: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """AUC@threshold of ``errors`` minus that of ``reference`` (same pairs, percent) with a 95 % interval.

    A paired bootstrap over the pairs: each resample draws pairs with replacement and scores both
    methods on the same draw, so a difference decided by one or two hard pairs shows as an
    interval that straddles zero. Errors are (pairs,) or (pairs, seeds): a pair's runs are drawn together.
    """
    errors, reference = np.asarray(errors, np.float64), np.asarray(reference, np.float64)
    if errors.shape != reference.shape or errors.ndim not in (1, 2) or errors.size == 0:
        raise ValueError(f"need the same non-empty set of pairs, got {errors.shape} and {reference.shape}")

    def delta(idx: np.ndarray | slice) -> float:
        return 100 * (pose_auc(errors[idx].ravel(), (threshold,))[0] - pose_auc(reference[idx].ravel(), (threshold,))[0])

    draws = np.random.default_rng(seed).integers(len(errors), size=(resamples, len(errors)))
    lo, hi = np.percentile([delta(d) for d in draws], [2.5, 97.5])
    return delta(slice(None)), float(lo), float(hi)


def difference_lines(errors: dict[str, np.ndarray], reference: str) -> list[str]:
    """One line per method: its AUC@5 minus the reference's, with the paired-bootstrap interval."""
    ref = np.asarray(errors[reference])
    runs = f" x {ref.shape[1]} seeds" if ref.ndim == 2 and ref.shape[1] > 1 else ""
    lines = [f"AUC@5 minus {reference}'s, same {len(ref)} pairs{runs} (paired bootstrap, 95 % interval):"]
    for name, e in errors.items():
        if name != reference:
            d, lo, hi = paired_auc_difference(e, errors[reference])
            lines.append(f"  {name}: {d:+.1f} [{lo:+.1f}, {hi:+.1f}]")
    return lines


def reference_differences(errors: dict[str, np.ndarray], reference: str) -> dict:
    """For the JSON: the ``reference`` and every other method's AUC@5 minus its, with the 95 % interval."""
    if reference not in errors:
        return {}
    diffs = {name: dict(zip(("auc5", "low", "high"), paired_auc_difference(e, errors[reference]), strict=True))
             for name, e in errors.items() if name != reference}
    return {"reference": reference, "auc5_vs_reference": diffs}


RATIO_BINS, RATIO_EDGES = ("< 10 %", "10-20 %", "20-35 %", ">= 35 %"), (10, 20, 35)  # putative inlier ratio, %
GAP_BINS, GAP_EDGES = ("1-2", "3-5", "6-10", "11-30", ">= 31"), (3, 6, 11, 31)  # frames between a pair's images
BIN_ORDER = {name: k for k, name in enumerate((*RATIO_BINS, *GAP_BINS))}  # a table's columns: the hard pairs first


def ratio_bin(ratio_pct: float) -> str:
    """The bin of a pair's putative inlier ratio (%), e.g. '< 10 %', '10-20 %'."""
    return RATIO_BINS[bisect.bisect_right(RATIO_EDGES, ratio_pct)]


def gap_bin(gap: int) -> str:
    """The bin of a pair's frame gap, e.g. '1-2', '>= 31'."""
    return GAP_BINS[bisect.bisect_right(GAP_EDGES, gap)]


def inlier_ratio(p: PairData) -> float:
    """A pair's putative inlier ratio, percent (0 without matches)."""
    return 100 * float(p.labels.mean()) if len(p.labels) else 0.0


def pair_bins(ratios: list[float], gaps: list[int]) -> dict[str, list[str]]:
    """Each pair's bin by putative inlier ratio (%) and by frame gap (pairs.txt pairs: by index distance)."""
    return {"inlier_ratio": [ratio_bin(r) for r in ratios], "gap": [gap_bin(g) for g in gaps]}


def binned(errors: dict[str, np.ndarray], groups: list[str], reference: str | None = None,
           prfs: dict[str, np.ndarray] | None = None, aps: dict[str, np.ndarray] | None = None) -> dict:
    """Per group (``groups[k]`` names pair k's), in first-seen order: its pair count and every method's AUC@5, with the
    paired difference to ``reference`` [95 %] when it is among the methods, with ``prfs`` (:func:`summarize`'s)
    its mean precision, recall and F there, and with ``aps`` its mean average precision. The JSON's ``bins`` and the
    tables'."""
    labels = np.asarray(groups, object)
    n_pairs = len(next(iter(errors.values())))
    if len(labels) != n_pairs:
        raise ValueError(f"{len(labels)} sequence labels for {n_pairs} pairs")
    out = {}
    for g in dict.fromkeys(groups):
        sel = labels == g
        row: dict = {"pairs": int(sel.sum())}
        for name, e in errors.items():
            e_g = np.asarray(e)[sel]
            row[name] = {"auc5": 100 * pose_auc(e_g.ravel(), (5.0,))[0], **(mean_prf(prfs[name][sel]) if prfs else {}),
                         **({"ap": mean_ap(aps[name][sel])} if aps else {})}
            if reference in errors and name != reference:
                d, lo, hi = paired_auc_difference(e_g, np.asarray(errors[reference])[sel])
                row[name]["vs_reference"] = {"auc5": d, "low": lo, "high": hi}
        out[g] = row
    return out


def auc_cell(m: dict) -> str:
    """A method's AUC@5 in a group, with its difference to the reference [95 %] when it has one."""
    d = m.get("vs_reference")
    return f"{m['auc5']:.1f}" + (f" ({d['auc5']:+.1f} [{d['low']:+.1f}, {d['high']:+.1f}])" if d else "")


def prf_cell(m: dict) -> str:
    """A method's precision / recall (%) in a group; '-' where no pair there has a labelled inlier."""
    return f"{m['precision']:.1f} / {m['recall']:.1f}" if m["precision"] is not None else "-"


def ap_cell(m: dict) -> str:
    """A method's mean average precision (%) in a group; '-' where it has no order or no pair a labelled inlier."""
    return "-" if m["ap"] is None else f"{m['ap']:.1f}"


def group_table(rows: dict, title: str = "AUC@5 per sequence (pairs)", cell: Callable[[dict], str] = auc_cell,
                methods: list[str] | None = None) -> str:
    """:func:`binned`'s rows as a markdown table, one column per group, one row per method (``methods``, else every
    one), each cell ``cell``'s."""
    methods = methods or [k for k in next(iter(rows.values())) if k != "pairs"]
    head = " | ".join(f"{g} ({r['pairs']})" for g, r in rows.items())
    lines = [f"| {title} | {head} |", "|---" * (len(rows) + 1) + "|"]
    lines += [f"| {name} | " + " | ".join(cell(r[name]) for r in rows.values()) + " |" for name in methods]
    return "\n".join(lines)


def per_sequence_table(errors: dict[str, np.ndarray], groups: list[str], reference: str | None = None) -> str:
    """AUC@5 of every method on each sequence, as a markdown table.

    A mean over several sequences can hide that the methods differ on one and tie on the other;
    with ``reference`` among the methods, the others' cells also give the paired difference to it.
    """
    return group_table(binned(errors, groups, reference))


def markdown_table(metrics: dict) -> str:
    """The results as a markdown table."""
    lines = ["| method | P | R | F | AP | AUC@5 | AUC@10 | AUC@20 | med. rot ° | med. trans ° | ms/pair |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, m in metrics.items():
        p, r, f, ap = ("-" if m[k] is None else f"{m[k]:.1f}" for k in ("precision", "recall", "f1", "ap"))
        lines.append(f"| {name} | {p} | {r} | {f} | {ap} | {m['auc5']:.1f} | "
                     f"{m['auc10']:.1f} | {m['auc20']:.1f} | {m['median_rot_deg']:.2f} | {m['median_trans_deg']:.2f} | "
                     f"{1000 * m['sec_per_pair']:.1f} |")
    return "\n".join(lines)


def plot_curves(errors: dict[str, np.ndarray], path: Path) -> None:
    """Recall (fraction of pairs) vs pose error threshold, one curve per method, labelled with its
    AUC@5; the right panel zooms into 0-5 degrees, where the robust pipelines differ."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    colors = plt.get_cmap("tab10").colors
    labels = {name: f"{name} (AUC@5 {100 * pose_auc(e, (5.0,))[0]:.1f})" for name, e in errors.items()}
    for ax, top in zip(axes, (20.0, 5.0), strict=True):
        th = np.linspace(0, top, 201)
        for i, (name, e) in enumerate(errors.items()):
            ax.plot(th, [(e <= t).mean() for t in th], label=labels[name], color=colors[i % 10], ls="-" if i < 10 else "--")
        ax.set_xlabel("pose error threshold (deg, max of rotation and translation)")
        ax.set_ylabel("fraction of pairs")
        ax.grid(alpha=0.3)
    axes[1].set_title("0-5 degrees", fontsize=9)
    axes[0].legend(fontsize=7)
    save_figure(fig, path)  # at this very path, also without a .png suffix


SELECTOR_SETTINGS = ("score_threshold", "pose_threshold_px", "pose_refine_iterations", "nmnet_precision",
                     "fallback_min_inliers")


def plot_path(args: argparse.Namespace) -> Path:
    """Where the plot goes: ``--plots DIR``'s eval_curves.png, else beside --json and named after it (evaluations into
    one folder keep each one's plot), else eval_curves.png here; ``--plot FILE``, the former option, as given."""
    if args.plot is not None:
        return args.plot
    if args.plots is not None:
        return args.plots / "eval_curves.png"
    if args.json is None:
        return Path("eval_curves.png")
    if args.json.suffix == ".png":
        raise ValueError(f"--json {args.json}: its .png name is where the plot goes; name it {args.json.stem}.json")
    return args.json.with_suffix(".png")


@dataclass
class Folder:
    """One folder's pairs scored by every method: a Ray task's result, numbers only."""

    ratios: list[float]  # each pair's putative inlier ratio, %
    gaps: list[int]  # each pair's frame gap
    runs: dict[str, Runs]
    notes: list[str]  # its loader's and scorer's lines, when not printed as they came


def score_folder(args: argparse.Namespace, methods: list[str], weights: dict[str, str], config: dict, spec: str,
                 skip_empty: bool, log: Callable[[str], None] | None = None) -> Folder:
    """Load one 'PATH[:a-b]''s pairs and score them; the notes go to ``log``, else into the result (a Ray task's)."""
    notes: list[str] = []
    cache = FeatureCache(make_detector(args.detector, {"max_keypoints": args.max_keypoints}), args.cache)
    pairs = load_pairs([spec], args.gaps, cache, stride=args.stride, max_pairs=args.max_pairs, skip_empty=skip_empty,
                       max_view_angle=args.max_view_angle, log=log or notes.append)
    runs = score(pairs, methods, weights, config, args.seeds, log=log or notes.append)
    return Folder([inlier_ratio(p) for p in pairs], [abs(p.j - p.i) for p in pairs], runs, notes)


def score_folders(args: argparse.Namespace, specs: list[str], labels: list[str], methods: list[str],
                  weights: dict[str, str], config: dict) -> tuple[dict[str, Folder], dict[str, str], bool]:
    """Every folder scored: one alone here, several as Ray tasks, one per folder (see :mod:`.fleet`).
    Returns the folders scored by label, the failed ones' errors, and whether the run was interrupted."""
    if len(specs) == 1:
        return {labels[0]: score_folder(args, methods, weights, config, specs[0], False, log=to_stderr)}, {}, False
    options = argparse.Namespace(**{**vars(args), "cache": (args.cache or default_cache_dir()).resolve()})
    weights = {k: str(Path(v).resolve()) for k, v in weights.items()}

    def done(label: str, result: Folder | fleet.Failed) -> str | None:
        if isinstance(result, fleet.Failed):
            return f"{label}: {result.error}"
        for line in result.notes:
            print(line, file=sys.stderr)
        return None

    calls = {label: (absolute_spec(spec), True) for label, spec in zip(labels, specs, strict=True)}
    results, interrupted = fleet.map_tasks(score_folder, calls, common=(options, methods, weights, config),
                                           address=args.ray_address, what="eval: folders", unit="folder", done=done)
    scored = {k: v for k, v in results.items() if isinstance(v, Folder)}
    return scored, {k: v.error for k, v in results.items() if isinstance(v, fleet.Failed)}, interrupted


# former method names: ``magsac`` was also the node's pose_estimator for MAGSAC++ on NM-Net's selection
FORMER_METHODS = {"magsac": "nn+magsac", "ransac": "nn+ransac"}


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet eval``: 0, 1 when a folder among several failed (the others are scored), 130 when
    interrupted (nothing written)."""
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:  # none: an empty table and an empty plot, exit 0
        hints = [f"{m} is the node's pose_estimator; here it is {POSE_ESTIMATORS[m]}" for m in unknown if m in POSE_ESTIMATORS]
        hints += [f"MAGSAC++/RANSAC on all the matches, formerly {m}, is now {FORMER_METHODS[m]}" for m in unknown
                  if m in FORMER_METHODS]
        raise ValueError(f"{f'unknown method(s) {unknown}' if unknown else '--methods names none'}"
                         f"{''.join(f' ({h})' for h in hints)}; choose from {', '.join(METHODS)}")
    if args.max_iters < 1:
        raise ValueError(f"--max-iters must be >= 1, got {args.max_iters}")
    if args.seeds < 1:
        raise ValueError(f"--seeds must be >= 1 (runs of each robust estimator per pair), got {args.seeds}")
    several = fleet.several(args.seqs, args.manifest, "a sequence folder")
    specs = [str(p) for p in fleet.recordings(args.seqs, args.manifest)] if several else args.seqs
    inputs = [parse_seq_spec(s)[0] for s in specs] + [args.weights, args.weights_sp]
    output_file(args.json, "--json", "eval.json", inputs)
    plot = plot_path(args)
    output_file(plot, "--plot" if args.plot else "--plots" if args.plots else "--json", "eval_curves.png", inputs)
    if args.json is not None and plot.resolve() == args.json.resolve():
        raise ValueError(f"--plot {plot} is also --json: give the plot its own file")  # it was written over the numbers
    weights = {k: str(v) for k, v in (("nmnet", args.weights), ("nmnet-sp", args.weights_sp)) if v}
    for variant, path in weights.items():  # the other variant's network would be scored under this one's name
        if (kind := load_model(path).config["neighbors"]) != NEIGHBORS[variant]:
            flag, other = ("--weights", "--weights-sp") if variant == "nmnet" else ("--weights-sp", "--weights")
            raise ValueError(f"{flag} {path}: trained with {kind} neighbours, the other variant's network; "
                             f"give it as {other}")
    for i, spec in enumerate(specs):  # ranges of one folder that meet: their pairs would weigh double
        if shared := shared_frames([spec], specs[i + 1:], at_least=2):  # one frame shared: no pair in both
            print(f"warning: {spec} and a later folder argument share frames ({'; '.join(shared)}): the pairs within "
                  "them are evaluated twice and count twice in the means", file=sys.stderr)
    labels = [spec_label(spec) for spec in specs]
    if len(set(labels)) < len(labels):  # two folders of the same name (or one given twice): name them in full
        labels = list(specs)
    config = {**{name: getattr(args, name) for name in SELECTOR_SETTINGS}, "max_iters": args.max_iters}
    for s in unread(config, methods):
        print(f"warning: {s.option} {config[s.name]!r} changes nothing: none of --methods reads it (these do: "
              f"{', '.join(s.methods)})", file=sys.stderr)
    scored, failed, interrupted = score_folders(args, specs, labels, methods, weights, config)
    if interrupted:
        print("interrupted: nothing written", file=sys.stderr)
        return 130
    folders = {label: scored[label] for label in labels if label in scored and scored[label].ratios}  # the order given
    if not folders:
        raise ValueError("no pairs to evaluate in any of the folders (the lines above say why)")
    res = summarize(merge([f.runs for f in folders.values()]))
    ratios = [r for f in folders.values() for r in f.ratios]
    groups = [label for label, f in folders.items() for _ in f.ratios]
    runs = f"; MAGSAC++/RANSAC methods: mean of {args.seeds} seeds" if args.seeds > 1 else ""
    net = f"; NM-Net in {precision_note(args.nmnet_precision)}" if set(methods) & set(NETWORK) else ""
    each = "; each folder in a Ray task on one core (ms/pair: one core's)" if len(specs) > 1 else ""
    print(f"{len(ratios)} pairs, mean inlier ratio {np.mean(ratios):.1f}%{runs}{net}{each}\n")
    print(markdown_table(res["metrics"]))
    if args.reference in res["errors"] and len(res["errors"]) > 1:
        print("\n" + "\n".join(difference_lines(res["errors"], args.reference)))
    elif len(res["errors"]) > 1:  # the differences were left out without a word
        print(f"\n(no AUC@5 differences: --reference {args.reference} is not among --methods; add it, or choose one "
              "that is)")
    if len(folders) > 1:
        print("\n" + per_sequence_table(res["errors"], groups, args.reference))
    gaps = [g for f in folders.values() for g in f.gaps]
    bins = {kind: binned(res["errors"], groups_of, args.reference, res["prfs"], res["aps"])
            for kind, groups_of in pair_bins(ratios, gaps).items()}
    for kind, title in (("inlier_ratio", "AUC@5 by putative inlier ratio (pairs)"), ("gap", "AUC@5 by frame gap (pairs)")):
        ordered = dict(sorted(bins[kind].items(), key=lambda kv: BIN_ORDER[kv[0]]))  # the hard pairs first
        print("\n" + group_table(ordered, title))
        if kind == "inlier_ratio":  # how well each selection sorts the hard pairs' matches, and each order ranks them
            print("\n" + group_table(ordered, "precision / recall (%) by putative inlier ratio", prf_cell))
            if ranked := [name for name, m in res["metrics"].items() if m["ap"] is not None]:
                print("\n" + group_table(ordered, "average precision (%) of the order by putative inlier ratio", ap_cell,
                                          ranked))
    if failed:
        print(f"\nnot evaluated, failed: {'; '.join(f'{k}: {v}' for k, v in failed.items())}")
    if args.json:  # before the plot: the numbers are what a script reads
        write_json(args.json, {"methods": res["metrics"], **reference_differences(res["errors"], args.reference),
                               "bins": bins, **({"failed": failed} if failed else {})})
    plot_curves(res["errors"], plot)
    print(f"\nplot: {plot}")
    return 1 if failed else 0
