"""``nmnet label``: ground truth for an unlabeled recording, by reconstructing its keyframes (COLMAP via pycolmap).

Reads a bag (as replay reads it), a sequence folder (its ground truth, if any, is not used) or a folder of images
with ``--camera``; picks keyframes by time and, optionally, by image motion; reconstructs them with the camera's
calibration held fixed; and, when the reconstruction passes its quality checks, writes a sequence folder whose
groundtruth.txt holds the reconstructed poses (scale arbitrary), with ``reconstruction.json`` saying so. That
folder trains (``nmnet train --train OUT``) and evaluates as any other. The output is built beside ``--out`` and
renamed into place at the end: a failed or interrupted run leaves no output.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from ..core.geometry import Camera, fit_rotation, rotation_error_deg, translation_error_deg
from ..core.settings import FRONTEND_DEFAULTS
from ..interface.posemsg import rot_to_quat
from ..io.bags import BAG_SUFFIXES, BagReader, read_frames
from ..io.datasets import DatasetError, Sequence, decode_image, epipolar_labels, read_camera_yaml, write_camera_yaml
from ..io.outputs import not_an_input, output_file, output_folder, write_json, written_here
from ..io.pairs import parse_seq_spec
from ..io.reconstruction import MIN_REGISTERED, STAGES, ReconstructionError, quality_problem, reconstruct
from . import fleet
from .options import DEFAULT_FPS

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif", ".tiff")
STAMP_ROUNDING_S = 1e-6  # stamps as float seconds: 0.7 - 0.6 < 0.1, and ROS times of ~1.7e9 s round to 2.4e-7 s
MIN_PARALLAX_PX = 0.5  # median between consecutive keyframes; KITTI at 10 Hz has >= 1.7 px, a standing MAV 0.07
OUTPUTS = ("camera.yaml", "images.txt", "groundtruth.txt", "reconstruction.json")


def frames_of(source: Path, args: argparse.Namespace) -> tuple[Iterator[tuple[float, np.ndarray]], Camera | None]:
    """(stamp, image) of every frame of ``source`` and its calibration (``--camera``'s when given)."""
    camera = read_camera_yaml(args.camera) if args.camera else None
    path, chosen = parse_seq_spec(str(source))
    path = Path(path)  # the bag or folder, without a frame range
    bag = path.suffix in BAG_SUFFIXES or (path / "metadata.yaml").is_file()
    # a folder of loose images: none for a bag or a sequence folder (Sequence.load says what else it may be)
    files = [] if bag or (path / "images.txt").is_file() or (path / "camera.yaml").is_file() else _images_in(path)
    for option, value, applies, what in (("--fps", args.fps, bool(files), "stamps a folder of images"),
                                         ("--image-topic", args.image_topic, bag, "names a bag's topic")):
        if value is not None and not applies:  # given for nothing: said, as the user meant something by it
            print(f"warning: {option} {what}; {source} is not one: {option} is ignored", file=sys.stderr)
    if bag:
        reader = BagReader(source)
        frames, _ = read_frames(reader, args.image_topic)
        first: dict = {}

        def from_bag() -> Iterator[tuple[float, np.ndarray]]:
            for f in frames:  # as the node: from the first frame with a calibration (camera_info, or --camera)
                if f.image is not None and (camera is not None or f.camera is not None):
                    first.setdefault("camera", f.camera)
                    yield f.stamp, f.image
            for w in reader.new_warnings():  # a recording cut short: its readable part is used, and said
                print(f"warning: {w}", file=sys.stderr)
        it = from_bag()
        head = next(it, None)
        if head is None:
            raise ValueError(f"{source}: no readable frame with a calibration (no camera_info? give --camera)")
        camera = camera or first.get("camera")
        return _chain(head, it), camera
    if not files:
        seq = Sequence.load(path)  # its ground truth, if any, is not looked at
        return ((float(seq.stamps[i]), seq.image(i)) for i in seq.frames(chosen)), camera or seq.camera
    if camera is None:
        raise ValueError(f"{source}: a folder of images needs --camera (a camera_info YAML) for its calibration")
    return _folder_frames(files, camera, args.camera, args.fps or DEFAULT_FPS), camera


def _folder_frames(files: list[Path], camera: Camera, calibration: Path, fps: float) -> Iterator[tuple[float, np.ndarray]]:
    """(stamp, image) of a folder of images, the k-th by name stamped k / ``fps``. An image that does not decode is
    skipped with a warning (the others keep their stamps); one of another size than ``calibration`` says (or, where
    it says none, than the first image) is an error."""
    size = (camera.width, camera.height) if camera.width > 0 else None
    for k, path in enumerate(files):
        try:
            image = decode_image(path)
        except DatasetError as e:
            print(f"warning: {e}: skipped", file=sys.stderr)
            continue
        (h, w) = image.shape[:2]
        if size is not None and (w, h) != size:
            raise ValueError(f"{path}: {w}x{h}, but " + (
                f"--camera {calibration} is for {size[0]}x{size[1]} images: give the calibration of the camera that "
                "took them" if camera.width > 0 else
                f"the folder's first image is {size[0]}x{size[1]}: one camera's images are one size"))
        size = size or (w, h)
        yield k / fps, image


def _chain(head: tuple, rest: Iterator) -> Iterator:
    yield head
    yield from rest


def _images_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []


def _gray(image: np.ndarray) -> np.ndarray:
    g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return (g / 256).astype(np.uint8) if g.dtype == np.uint16 else g


def tracked(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners of gray image ``a`` and where Lucas-Kanade tracks them in ``b`` (N, 2 each)."""
    pts = cv2.goodFeaturesToTrack(a, 400, 0.01, 8)
    if pts is None:
        return np.zeros((0, 2)), np.zeros((0, 2))
    moved, ok, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, None)
    ok = ok.ravel().astype(bool)
    return pts.reshape(-1, 2)[ok], moved.reshape(-1, 2)[ok]


def motion_px(a: np.ndarray, b: np.ndarray, camera: Camera) -> tuple[float, float]:
    """(median flow, median parallax) in pixels of the corners of gray image ``a`` tracked into ``b``: all their
    motion, and what the best rotation alone does not explain (the front end's no-motion test; near 0: no baseline,
    whatever the camera turned). inf for both when too few corners track (a motion too large for the tracker; no
    texture at all is COLMAP's to say)."""
    p0, p1 = tracked(a, b)
    if len(p0) < 8:
        return float("inf"), float("inf")
    _, angles = fit_rotation(camera.normalize(p0), camera.normalize(p1))
    return float(np.median(np.linalg.norm(p1 - p0, axis=1))), float(np.median(angles) * camera.focal)


def pick_keyframes(frames: Iterator[tuple[float, np.ndarray]], interval: float, min_flow: float, max_frames: int,
                   camera: Camera, parallax: list[float]) -> Iterator[tuple[float, np.ndarray]]:
    """Frames at least ``interval`` s after the last keyframe and, with ``min_flow``, moved at least that many pixels
    from it; at most ``max_frames`` (a warning says where they ran out). Appends each keyframe's parallax to the one
    before to ``parallax``."""
    first, last, last_gray, n = None, None, None, 0
    for stamp, image in frames:
        if last is not None and stamp - last < interval - STAMP_ROUNDING_S:
            continue
        if n >= max_frames:  # a keyframe more, had there been room: said, as the rest goes unlabelled
            print(f"warning: --max-frames {max_frames} keyframes reached {last - first:.1f} s into the recording; the "
                  "rest of it is not labelled: raise --max-frames, or --interval to spread them over it", file=sys.stderr)
            return
        first = stamp if first is None else first
        gray = _gray(image)
        if last_gray is not None:  # the corners are found and tracked once for both tests
            flow, moved = motion_px(last_gray, gray, camera)
            if flow < min_flow:
                continue
            parallax.append(moved)
        last, last_gray, n = stamp, gray, n + 1
        yield stamp, image


def write_sequence(out: Path, camera: Camera, stamps: list[float], names: list[str], poses: dict[str, np.ndarray],
                   note: dict) -> None:
    """The sequence folder (images/ written already): camera.yaml, images.txt, groundtruth.txt, reconstruction.json."""
    write_camera_yaml(out / "camera.yaml", camera)
    (out / "images.txt").write_text("# timestamp filename\n" + "".join(
        f"{s:.9f} images/{n}\n" for s, n in zip(stamps, names, strict=True)))
    lines = ["# timestamp tx ty tz qx qy qz qw: a reconstruction (see reconstruction.json); scale arbitrary\n"]
    for s, n in zip(stamps, names, strict=True):
        if n in poses:
            T = poses[n]
            q = rot_to_quat(T[:3, :3])
            lines.append(f"{s:.9f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)) + "\n")
    (out / "groundtruth.txt").write_text("".join(lines))
    write_json(out / "reconstruction.json", note)


def truth_sequence(spec: str) -> Sequence:
    """``--truth``'s folder, refused before any work when it has no ground truth to check against."""
    truth = Sequence.load(parse_seq_spec(spec)[0])
    if truth.poses is None:
        raise ValueError(f"--truth {spec}: has no groundtruth.txt to check against")
    return truth


def keyframes_in(stamps: list[float] | np.ndarray, truth: Sequence, spec: str) -> list[tuple[int, int, int]]:
    """(i, a, b) for each pair of consecutive keyframes i, i + 1 that ``truth`` has as its frames a, b (by stamp, to the
    millisecond); a ValueError naming ``spec`` where it has none."""
    at = {round(float(s), 3): k for k, s in enumerate(truth.stamps)}
    frame = [at.get(round(float(s), 3)) for s in stamps]
    found = [(i, a, b) for i, (a, b) in enumerate(zip(frame[:-1], frame[1:], strict=True)) if a is not None and b is not None]
    if not found:
        raise ValueError(f"--truth {spec}: none of its frames has a keyframe's stamp: give the folder labelled")
    return found


def truth_check(out: Path, truth: Sequence, truth_spec: str) -> dict:
    """How the labels of the folder ``out`` agree with ``truth``, the real ground truth of the sequence folder
    ``truth_spec`` (holding the same frames, by stamp): each consecutive keyframe pair's rotation and translation-direction error,
    and the share of its nearest-neighbour matches (the network's input) whose epipolar label is the same."""
    from ..core.detectors import make_detector
    from ..io.cache import FeatureCache
    from ..io.pairs import make_pair

    labelled = Sequence.load(out)
    cache = FeatureCache(make_detector(FRONTEND_DEFAULTS["detector"], {"max_keypoints": FRONTEND_DEFAULTS["max_keypoints"]}))
    rot, direction, same, total = [], [], 0, 0
    for i, a, b in keyframes_in(labelled.stamps, truth, truth_spec):
        if not (labelled.has_pose(i) and labelled.has_pose(i + 1) and truth.has_pose(a) and truth.has_pose(b)):
            continue
        (R, t), (R_gt, t_gt) = labelled.relative_pose(i, i + 1), truth.relative_pose(a, b)
        rot.append(rotation_error_deg(R, R_gt))
        direction.append(translation_error_deg(t, t_gt))
        p = make_pair(truth, a, b, cache)
        mine, _ = epipolar_labels(labelled, i, i + 1, p.k0, p.k1)
        same += int((mine == p.labels).sum())
        total += len(p.labels)
    if not rot:
        raise ValueError(f"--truth {truth_spec}: it has no pose at any two consecutive keyframes the reconstruction "
                         "posed: nothing to check the labels against; give ground truth that covers the labelled frames")
    return {"pairs": len(rot), "median_rot_deg": float(np.median(rot)), "median_trans_deg": float(np.median(direction)),
            "label_agreement_percent": 100 * same / max(total, 1), "matches": total}


def _label_into(args: argparse.Namespace, recording: Path, folder: Path) -> int:
    """One recording of a fleet run: its labelled sequence folder is ``folder``."""
    args.recordings, args.manifest, args.out = [str(recording)], None, folder
    return label_recording(args)


def _refused_for_a_fleet(args: argparse.Namespace) -> None:
    fleet.several_refused({"json": args.json, "truth": args.truth},
                          {"truth": "one --truth folder cannot check several recordings' labels"})


FLEET = fleet.Job("label", _label_into, "reconstruction.json", (
    fleet.Column("keyframes", "keyframes", "{}", "sum"), fleet.Column("registered", "registered", "{}", "sum"),
    fleet.Column("mean_reprojection_px", "reprojection error (px)", "{:.2f}", "mean")), _refused_for_a_fleet)


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet label``: one recording here, several (a glob, ``--manifest``) on Ray."""
    if args.out is None:  # the output's former place: the last positional, after the recordings
        if len(args.recordings) < (1 if args.manifest else 2):
            raise ValueError("name the labelled sequence folder to write: --out DIR")
        args.out = Path(args.recordings.pop())
    if not args.recordings and not args.manifest:
        raise ValueError("name a recording to label: a bag, a sequence folder or a folder of images")
    if fleet.several(args.recordings, args.manifest):
        return fleet.run(FLEET, args)
    return label_recording(args)


def label_recording(args: argparse.Namespace) -> int:
    """One recording labelled into ``args.out``."""
    source, out = Path(args.recordings[0]), Path(args.out)
    recording = Path(parse_seq_spec(str(source))[0])  # without a frame range
    output_file(args.json, "--json", "label.json", [recording])
    ours = (out / "reconstruction.json").is_file() and written_here(out / "reconstruction.json")  # an earlier label run
    output_folder(out, "--out", "the labelled sequence folder", [recording, args.camera],
                  () if ours else OUTPUTS)
    if out.is_dir() and any(out.iterdir()) and not ours:
        raise ValueError(f"--out {out} holds files nmnet label did not write: give a new or empty folder")
    truth = truth_sequence(args.truth) if args.truth else None
    frames, camera = frames_of(source, args)
    if camera is None:
        raise ValueError(f"{source}: no camera_info in the recording; give its calibration with --camera")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        building = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    except OSError as e:
        raise OSError(f"--out {out}: cannot write in {out.parent} ({e.strerror}): choose a folder you can write") from None
    not_an_input(building, "--out", [source])
    from tqdm import tqdm

    try:
        (building / "images").mkdir()
        stamps, names, parallax = [], [], []
        with tqdm(desc="label: keyframes", unit="keyframe", file=sys.stderr, disable=None) as bar:  # a count
            for stamp, image in pick_keyframes(frames, args.interval, args.min_flow, args.max_frames, camera, parallax):
                name = f"{len(names):06d}.png"
                if not cv2.imwrite(str(building / "images" / name), image):
                    raise OSError(f"cannot write {building / 'images' / name}")
                stamps.append(stamp)
                names.append(name)
                bar.update(1)
        if len(names) < MIN_REGISTERED:  # fewer never pass quality_problem: said before the reconstruction's work
            raise ReconstructionError(f"{source}: {len(names)} keyframe(s), and a reconstruction needs at least "
                                      f"{MIN_REGISTERED}; give a longer recording or a shorter --interval"
                                      + (" or a lower --min-flow" if args.min_flow > 0 else ""))
        if np.median(parallax) < MIN_PARALLAX_PX:
            raise ReconstructionError(
                f"{source}: the camera barely moves between keyframes (median parallax {np.median(parallax):.2f} px, "
                f"under {MIN_PARALLAX_PX} px, once its turning is taken out: a standing or only turning camera); poses "
                "from it would be drawn from noise: record while the robot moves, or skip the still parts (--min-flow)")
        if truth is not None:  # said before the reconstruction's minutes
            keyframes_in(stamps, truth, args.truth)
        print(f"label: {len(names)} keyframes; reconstructing (COLMAP, {args.mapper} mapper)", file=sys.stderr)
        with tqdm(desc="label: COLMAP", total=len(STAGES), unit="stage", file=sys.stderr, disable=None) as bar:
            rec = reconstruct(building / "images", names, camera, building / "colmap", args.refine_intrinsics,
                              mapper=args.mapper, stage=lambda name: (bar.set_postfix_str(name), bar.update(1)))
        if (why := quality_problem(rec, names)) is not None:
            raise ReconstructionError(f"{source}: {why}")
        shutil.rmtree(building / "colmap")
        note = {"what": f"poses reconstructed by COLMAP's {args.mapper} mapper (pycolmap), not measured: scale arbitrary",
                "source": str(source), "keyframes": len(names), "registered": rec.registered,
                "mean_reprojection_px": rec.mean_reprojection_px, "points": rec.points, "models": rec.models,
                "kept": "the largest model", "intrinsics": "refined (camera.yaml holds them)" if args.refine_intrinsics
                else "fixed",
                "interval_s": args.interval, "min_flow_px": args.min_flow}
        write_sequence(building, rec.camera, stamps, names, rec.poses, note)
        if out.exists():
            shutil.rmtree(out)  # an earlier label run's (checked above)
        building.rename(out)
    finally:
        shutil.rmtree(building, ignore_errors=True)
    print(f"label: {rec.registered} of {len(names)} keyframes registered, mean reprojection error "
          f"{rec.mean_reprojection_px:.2f} px -> {out}")
    if truth is not None:
        note["truth_check"] = check = truth_check(out, truth, args.truth)
        print(f"label: against {args.truth}, {check['pairs']} consecutive keyframe pairs: median rotation error "
              f"{check['median_rot_deg']:.3f} deg, translation direction {check['median_trans_deg']:.2f} deg; the "
              f"same epipolar label on {check['label_agreement_percent']:.1f} % of {check['matches']} matches")
    if args.json:
        write_json(args.json, note)
    return 0
