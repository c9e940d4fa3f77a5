"""Every ``nmnet`` subcommand's command line: its options, their help and defaults.

The options that set a front-end or node setting are made from the settings vocabulary (``core/settings.py``):
the same name as the node's parameter (``--max-keypoints`` is ``max_keypoints``), its help, default and range.
Outputs are named one way: ``--out`` is a tool's main output (a recording, a folder), ``--json FILE`` its numbers,
``--plots DIR`` its figures. Imports nothing heavy, so ``nmnet COMMAND --help`` answers at once.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path

from ..core.settings import BY_NAME, METHODS, POSE_ESTIMATORS, for_tool, problem
from ..io.datasets import FOLDERS_READ, LABEL_THRESHOLD, MAX_VIEW_ANGLE_DEG
from ..io.reconstruction import MIN_REGISTERED

SAMPLE_BAG = Path(__file__).parents[1] / "sample" / "kitti07_120-159"
SHIPPED_WEIGHTS = Path(__file__).parents[1] / "weights" / "nmnet.pt"
BAG_FORMATS = ("mcap", "sqlite3", "ros1")
DEFAULT_FPS = 10.0  # label: a folder of images' frame rate unless --fps says
NEIGHBORS = ("nmnet", "nmnet-sp")  # the network's variants: compatibility (the paper's), spatial neighbours
# former names of setting options, still accepted
ALIASES = {"nmnet_precision": ("--precision",), "pose_estimator": ("--selector",),
           "pose_threshold_px": ("--threshold-px",), "pose_refine_iterations": ("--refine-iterations",)}


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


def view_angle(text: str) -> float:
    """``--max-view-angle``' value: degrees, above 0 and at most 180."""
    value = bounded(float, 0.0, "degrees, above 0 and at most 180", strict=True)(text)
    if value > 180:
        raise argparse.ArgumentTypeError(f"{text!r}: expected degrees, above 0 and at most 180")
    return value


playback_rate = bounded(float, 0.0, "a speed factor > 0 (1 = as recorded, 0.5 = half speed)", strict=True)  # --rate
seconds = bounded(float, 0.0, "seconds, a number >= 0")  # --start, --duration


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


def correspondence_counts(text: str) -> tuple[int, ...]:
    """``--sizes``' value, '1000,2000': counts from 1 to the node's largest ``max_keypoints`` (a count beyond it
    times what the node never runs, and the loop baseline, quadratic, for hours)."""
    most = BY_NAME["max_keypoints"].range[1]
    try:
        counts = tuple(whole(1)(s) for s in text.split(","))
    except argparse.ArgumentTypeError:
        counts = ()
    if not counts or max(counts) > most:
        raise argparse.ArgumentTypeError(f"{text!r}: expected correspondence counts from 1 to {most} (the node's "
                                         "largest max_keypoints), comma-separated (1000,2000)")
    return counts


def gt_frames(text: str) -> tuple[str, str]:
    """``--gt-tf``'s value, PARENT[:CHILD], as two frame names ("" for a CHILD not given: the images' frame)."""
    parent, sep, child = text.partition(":")
    if not parent.strip("/") or sep and not child.strip("/"):
        raise argparse.ArgumentTypeError(f"{text!r}: expected PARENT or PARENT:CHILD, frame names (e.g. world, or "
                                         "world:camera_optical_frame)")
    return parent, child


def gt_camera(text: str) -> object:
    """``--gt-camera``'s value as a 4x4 pose; argparse names the option and the value when it is not one."""
    from ..io.trajectory import parse_pose  # numpy and OpenCV: only when the option is given

    try:
        return parse_pose(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from e


def setting_value(name: str) -> Callable[[str], object]:
    """An argparse type for the option of setting ``name``: the node's own type and range check, so a value the node
    would refuse stops the command there, naming the option (argparse adds it) and the range."""
    kind = type(BY_NAME[name].default)

    def parse(text: str) -> object:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if (why := problem(name, value)) is not None:
            raise argparse.ArgumentTypeError(why)
        return value

    return parse


def add_settings(p: argparse.ArgumentParser, command: str, from_params_file: bool = False) -> None:
    """The options of ``command``'s settings (:func:`~nmnet_ros.core.settings.for_tool`), named as the node's
    parameters. ``from_params_file``: their default is None, for the value of ``--params-file`` or the node's default."""
    for s in for_tool(command):
        flags = [s.option, *ALIASES.get(s.name, ())]
        default = None if from_params_file or s.name == "weights" else s.default
        shown = "the shipped weights" if s.name == "weights" else str(s.default).lower() if isinstance(s.default, bool) \
            else s.default
        source = " or --params-file's" if from_params_file else ""
        text = f"{s.full_help} (the node's {s.name}; default: {shown}{source})"
        kw: dict = {"dest": s.name, "default": default, "help": text.replace("%", "%%")}
        if isinstance(s.default, bool):
            p.add_argument(*flags, action="store_const", const=True, **kw)
        elif s.name == "weights":
            p.add_argument(*flags, type=Path, metavar="FILE", **kw)
        elif s.name == "pose_estimator":  # offline, any of eval's methods too
            p.add_argument(*flags, choices=(*POSE_ESTIMATORS, *METHODS), metavar="NAME", **kw)
        elif s.choices:
            p.add_argument(*flags, choices=s.choices, **kw)
        else:
            p.add_argument(*flags, type=setting_value(s.name), metavar=s.name.split("_")[-1].upper(), **kw)


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


def add_fleet_options(p: argparse.ArgumentParser, inputs: str) -> None:
    """--manifest and --ray-address, alike in every command that runs over many inputs (see tools/fleet.py)."""
    p.add_argument("--manifest", type=Path, default=None, metavar="FILE",
                   help="more inputs, one path or glob per line (relative to FILE's folder; # comments)")
    p.add_argument("--ray-address", default=None, metavar="ADDRESS", help=f"{inputs}: the Ray cluster to run "
                   "on (default: $RAY_ADDRESS, else a local Ray runtime on this machine's cores)")


SEQS = f"sequence folders (optional frame range): {FOLDERS_READ}"


def replay(p: argparse.ArgumentParser) -> None:
    """``nmnet replay``."""
    p.add_argument("recordings", nargs="*", metavar="BAG", help=".bag, .db3 or .mcap file, a ROS 2 bag directory, or a "
                   "folder of a ROS 1 recording's parts (rosbag record --split); several (or a quoted glob): replayed in "
                   "parallel on Ray, one task per recording")
    p.add_argument("--out", required=True, help="output .mcap with matches and relative poses; with "
                   "several recordings the run's folder: OUT/NAME/ per recording, OUT/report.json, .md, .png")
    add_fleet_options(p, "several recordings")
    p.add_argument("--json", type=file_path, default=None, help="write the summary as JSON")
    p.add_argument("--plots", type=Path, default=None, help="folder for the PNG plots, named errors.png, trajectory.png, "
                   "matches.png (default: --out's folder, named after it: OUT_errors.png, ...)")
    p.add_argument("--gt", type=Path, default=None, help="ground truth as a TUM file (else the bag's ground-truth topic, "
                   "if any)")
    p.add_argument("--gt-camera", type=gt_camera, default=None, metavar="'X Y Z QX QY QZ QW'",
                   help="the camera's pose (optical frame: z forward, x right, y down) in the frame the ground truth "
                   "tracks, when that is a body (a motion-capture marker set, base_link), not the camera")
    p.add_argument("--image-topic", default=None, help="the frames' topic (default: the bag's only image topic, the raw "
                   "one of a camera's transports)")
    p.add_argument("--info-topic", default=None, help="the camera_info topic (default: the one beside the image topic)")
    p.add_argument("--gt-topic", default=None, help="the ground-truth topic (a pose, odometry or transform message; "
                   "with --gt-tf, the TFMessage topic, default /tf)")
    p.add_argument("--gt-tf", type=gt_frames, default=None, metavar="PARENT[:CHILD]",
                   help="ground truth from /tf and /tf_static: CHILD's pose in PARENT (CHILD: the frame the images name, "
                   "their optical frame), chained through the tree as tf2 does (world:camera_optical_frame over motion "
                   "capture's world -> base_link and the robot's static mount)")
    p.add_argument("--start", type=seconds, default=None, metavar="SEC",
                   help="replay from this many seconds after the bag's first frame (by recording time, as ros2 bag play "
                   "--start-offset)")
    p.add_argument("--duration", type=seconds, default=None, metavar="SEC", help="replay this many seconds (default: to "
                   "the end)")
    p.add_argument("--camera", type=Path, default=None, help="calibration as a ROS camera_info YAML (what camera_calibration "
                   "writes), a Kalibr camchain (the camera whose rostopic is the image topic), a EuRoC sensor.yaml or an "
                   "OpenCV YAML (its calibration's camera_matrix, or ORB-SLAM's settings), for a bag without camera_info "
                   "or to use instead of it")
    p.add_argument("--params-file", type=Path, default=None, metavar="YAML",
                   help="the node's parameters file (config/nmnet.yaml's form): replay with the settings the node runs; "
                        "the setting options below, when given, override it")
    p.add_argument("--debug-images", action="store_true", help="also record the match overlay images")
    p.add_argument("--baseline", action="store_true", help="also run SIFT + ratio + MAGSAC++ on the same frames and print both")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (there is none when stderr is no terminal)")
    p.add_argument("--live", action="store_true", help="play the bag onto ROS 2 topics into the node (own process) and record it")
    p.add_argument("--rate", type=playback_rate, default=1.0, help="live mode: playback speed factor")
    add_settings(p.add_argument_group("settings (the node's parameters; offline --pose-estimator also takes any "
                                      "nmnet eval method)"), "replay", from_params_file=True)


def demo(p: argparse.ArgumentParser) -> None:
    """``nmnet demo``."""
    p.add_argument("--out", "--out-dir", dest="out", type=Path, default=Path("nmnet_demo"),
                   help="folder for the output .mcap, summary and plots")
    p.add_argument("--bag", type=Path, default=SAMPLE_BAG, help="bag to replay (default: the bundled sample)")
    p.add_argument("--rate", type=playback_rate, default=0.3,
                   help="live playback speed (x as recorded; the sample is 10 Hz); 0.3 lets a 2-core machine keep up "
                   "with the sample at 2000 keypoints")


def make_bag(p: argparse.ArgumentParser) -> None:
    """``nmnet make-bag``."""
    p.add_argument("seq", metavar="SEQ_DIR[:a-b]", help=f"sequence folder (optional frame range): {FOLDERS_READ}")
    p.add_argument("out_positional", nargs="?", type=Path, metavar="OUT", help="former place of --out")
    p.add_argument("--out", type=Path, default=None, help="output: a .mcap, .db3 or .bag file, or a ROS 2 bag folder "
                   "(a name without those extensions)")
    p.add_argument("--format", choices=BAG_FORMATS, default=None, help="the storage of a bag folder: mcap or sqlite3 "
                   "(default: as --out's extension names it, .bag: ros1, .db3: sqlite3; else mcap)")
    p.add_argument("--compressed", action="store_true", help="sensor_msgs/CompressedImage instead of Image: JPEG, PNG "
                   "for 16-bit frames")


def label(p: argparse.ArgumentParser) -> None:
    """``nmnet label``."""
    p.add_argument("recordings", nargs="*", metavar="RECORDING", help="a bag (.bag, .db3, .mcap or a bag folder), a "
                   "sequence folder (its ground truth is not used), or a folder of images with --camera; several (or a "
                   "quoted glob): labelled in parallel on Ray, one task per recording")
    p.add_argument("--out", type=Path, default=None, help="the labelled sequence folder to write; with several "
                   "recordings the run's folder: OUT/NAME/ per recording, OUT/report.json, .md, .png (without --out: "
                   "the last positional, its former place)")
    add_fleet_options(p, "several recordings")
    p.add_argument("--camera", type=Path, default=None, metavar="YAML",
                   help="calibration (a camera_info YAML, Kalibr, EuRoC or OpenCV file), for a recording without one")
    p.add_argument("--image-topic", default=None, help="a bag's image topic (default: its only camera's)")
    p.add_argument("--interval", type=seconds, default=0.1, metavar="SEC",
                   help="a keyframe at least this many seconds after the previous one")
    p.add_argument("--min-flow", type=bounded(float, 0.0, "pixels, >= 0"), default=0.0, metavar="PX",
                   help="and only once the image has moved this many pixels (median corner motion) since it; 0 = off")
    p.add_argument("--max-frames", type=whole(MIN_REGISTERED), default=400,
                   help=f"keyframes at most (COLMAP's time grows with them; a reconstruction needs {MIN_REGISTERED})")
    p.add_argument("--fps", type=bounded(float, 0.0, "frames per second > 0", strict=True), default=None,
                   help=f"a folder of images: the frame rate its stamps are made with (default: {DEFAULT_FPS:g})")
    p.add_argument("--json", type=file_path, default=None, help="write the reconstruction's summary (and --truth's check) as JSON")
    p.add_argument("--truth", default=None, metavar="SEQ_DIR",
                   help="check the labels against this sequence folder's real ground truth (the same frames, by stamp)")
    p.add_argument("--mapper", choices=("global", "incremental"), default="global",
                   help="COLMAP's global mapper (GLOMAP; steadier on driving sequences) or its incremental one")
    p.add_argument("--refine-intrinsics", action="store_true",
                   help="let the mapper refine the focal length and distortion, written to the folder's camera.yaml "
                   "(default: the calibration is fixed)")


def add_max_view_angle(p: argparse.ArgumentParser) -> None:
    """``--max-view-angle`` of eval and train: which pairs are wide enough apart to leave out."""
    p.add_argument("--max-view-angle", type=view_angle, default=MAX_VIEW_ANGLE_DEG, metavar="DEG",
                   help="leave out pairs whose cameras' optical axes are further apart (wide baselines: up to 180)")


def evaluate(p: argparse.ArgumentParser) -> None:
    """``nmnet eval``."""
    p.add_argument("seqs", nargs="*", metavar="SEQ[:a-b]", help=SEQS + "; several (or a quoted glob): scored in "
                   "parallel on Ray, one task per folder")
    add_fleet_options(p, "several folders")
    p.add_argument("--methods", default="nmnet,nmnet-sp,ratio,nn+ransac,nn+magsac,ratio+magsac,nmnet+magsac,oracle",
                   help=f"comma-separated, from: {', '.join(METHODS)}")
    p.add_argument("--gaps", type=gaps, default="1-10", help="frame gaps, e.g. 1-10 or 1,3,5")
    p.add_argument("--stride", type=whole(1), default=1, help="use every n-th frame as a pair's first frame")
    p.add_argument("--max-pairs", type=whole(1), default=None, help="at most this many pairs per sequence (evenly spread)")
    add_max_view_angle(p)
    p.add_argument("--weights-sp", type=Path, default=None, metavar="FILE", help="NM-Net-sp weights (default: shipped)")
    p.add_argument("--json", type=file_path, default=None, help="write {method: metrics} as JSON")
    p.add_argument("--plots", type=Path, default=None, help="folder for the recall-vs-error plot, eval_curves.png "
                   "(default: beside --json, named after it, else the current folder)")
    p.add_argument("--plot", type=file_path, default=None, help=argparse.SUPPRESS)  # former: the plot's file
    p.add_argument("--cache", type=Path, default=None, help="feature cache folder")
    p.add_argument("--reference", default="ratio+magsac", choices=METHODS,
                   help="method the others' AUC@5 is compared with (paired bootstrap); skipped when not run")
    p.add_argument("--max-iters", type=whole(1), default=10000, help="MAGSAC++/RANSAC iteration cap for every robust method")
    p.add_argument("--seeds", type=whole(1), default=1,
                   help="runs of every MAGSAC++/RANSAC method per pair, each with other random samples (metrics: the mean)")
    add_settings(p.add_argument_group("settings (the node's parameters, for every method that uses them)"), "eval")


def neighbors(p: argparse.ArgumentParser) -> None:
    """``nmnet neighbors``."""
    p.add_argument("seqs", nargs="+", metavar="SEQ[:a-b]", help=SEQS)
    p.add_argument("--gaps", type=gaps, default="1-10", help="frame gaps, e.g. 1-10 or 1,2")
    p.add_argument("--stride", type=whole(1), default=10, help="use every n-th frame as a pair's first frame")
    p.add_argument("--json", type=file_path, default=None, help="write the rows and table as JSON")
    p.add_argument("--cache", type=Path, default=None, help="feature cache folder")
    add_settings(p.add_argument_group("settings (the node's parameters)"), "neighbors")


def bench(p: argparse.ArgumentParser) -> None:
    """``nmnet bench``."""
    p.add_argument("--sizes", type=correspondence_counts, default=(1000, 2000), help="correspondence counts, e.g. 1000,2000")
    p.add_argument("--repeat", type=whole(1), default=20, help="timed runs of each step (the median is reported)")
    p.add_argument("--json", type=file_path, default=None, help="write the numbers as JSON")
    p.add_argument("--pipeline", action="store_true", help="also time every pipeline stage on the sample bag's frames")
    p.add_argument("--frames", type=whole(2), default=16, help="frames of the sample bag used with --pipeline")
    p.add_argument("--threads", type=whole(1), default=None,
                   help="CPU threads of the serial timings (default: torch's); 1 = one node stage's budget")


TRAIN_DEFAULTS: dict = {  # nmnet train's recipe (the network's training; the front end's settings are the node's)
    "variant": "nmnet",  # or "nmnet-sp"
    "epochs": 12,
    "steps_per_epoch": 40,
    "batch": 16,
    "num_corr": 1000,
    "lr": 1e-3,
    "seed": 0,
    "max_val_pairs": 60,
    "device": "cpu",  # "cuda" trains on a GPU; neighbours are always mined on the CPU
    "workers": 1,  # threads preparing a batch (neighbour mining releases the GIL)
    "label_threshold": LABEL_THRESHOLD,  # inlier when the squared symmetric epipolar distance is below (paper: 1e-4)
    "thin_inliers": 0.0,  # probability that a sample keeps only part of its inliers (see train.sample_correspondences)
    "turn_deg": 0.0,  # turn the second camera about its centre by up to this many degrees (see train.turn_camera)
    "balance": 0.0,  # 0 = every training pair equally often; 1 = every training folder equally often
    "ess_loss": 0.0,  # weight of the essential-matrix regression term; 0 = the paper's loss
}
MAX_ROLL_DEG = 10.0  # per-image camera roll drawn from +-this when augmenting
MIN_THINNED_RATIO = 0.05  # lowest inlier ratio a thinned sample is given


def train(p: argparse.ArgumentParser) -> None:
    """``nmnet train``."""
    d = TRAIN_DEFAULTS
    p.add_argument("--train", nargs="+", required=True, metavar="SEQ[:a-b]", help=f"training {SEQS}")
    p.add_argument("--val", nargs="+", required=True, metavar="SEQ[:a-b]", help="validation sequence folders")
    p.add_argument("--out", type=Path, required=True, help="output folder for checkpoints")
    p.add_argument("--variant", choices=NEIGHBORS, default=d["variant"],
                   help="nmnet: compatibility neighbours (the paper's, shipped); nmnet-sp: spatial neighbours")
    for key, what in (("epochs", "passes of --steps-per-epoch batches, each followed by validation"),
                      ("steps_per_epoch", "optimiser steps per epoch"), ("batch", "pairs per step"),
                      ("num_corr", "correspondences drawn per training pair"), ("seed", "random seed (same seed, same run)"),
                      ("max_val_pairs", "validation pairs used at most (evenly spaced)")):
        p.add_argument("--" + key.replace("_", "-"), type=whole(0 if key == "seed" else 1), default=d[key], help=what)
    p.add_argument("--lr", type=float, default=d["lr"], help="Adam's learning rate")
    p.add_argument("--device", default=d["device"], help="torch device for the network, e.g. cpu or cuda")
    p.add_argument("--workers", type=whole(1), default=d["workers"], help="threads mining neighbours for a batch")
    p.add_argument("--gaps", type=gaps, default="1-10", help="frame gaps, e.g. 1-10 or 1,3,5")
    add_max_view_angle(p)
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    p.add_argument("--label-threshold", type=float, default=d["label_threshold"],
                   help="inlier label: squared symmetric epipolar distance below this, normalised coordinates")
    p.add_argument("--init", type=Path, nargs="?", const=SHIPPED_WEIGHTS, default=None, metavar="CHECKPOINT",
                   help="fine-tune from this checkpoint; --init alone: from the shipped weights (default: random start)")
    p.add_argument("--cache", type=Path, default=None, help="feature cache folder (default ~/.cache/nmnet_ros)")
    p.add_argument("--augment", action="store_true",
                   help=f"augment training pairs: swap the images, mirror, roll each camera by up to {MAX_ROLL_DEG:g} degrees")
    p.add_argument("--thin-inliers", type=float, default=d["thin_inliers"], metavar="P",
                   help="probability that a training sample drops part of its inliers (inlier ratio drawn between "
                        f"{100 * MIN_THINNED_RATIO:g} %% and the pair's own); 0 = off")
    p.add_argument("--turn-deg", type=float, default=d["turn_deg"], metavar="DEG",
                   help="turn each sample's second camera about its centre by up to DEG degrees (pan/tilt; "
                        "labels recomputed, matches turned out of the image dropped); 0 = off")
    p.add_argument("--ratio-input", action="store_true",
                   help="give the network each match's descriptor distance ratio as a fifth input (not in the paper)")
    p.add_argument("--ess-loss", type=float, default=d["ess_loss"], metavar="W",
                   help="add W x the essential-matrix regression loss of Yi et al. 2018 (not in the NM-Net paper); 0 = off")
    p.add_argument("--balance", type=float, default=d["balance"], metavar="B",
                   help="share of the samples per --train folder: proportional to its pair count ** (1 - B); "
                        "0 = every pair equally often, 1 = every folder equally often")
    add_settings(p.add_argument_group("settings (the node's parameters: train on the frames the node makes)"), "train")
