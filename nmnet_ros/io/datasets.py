"""Sequence folders (../shared/data format): camera.yaml, images.txt (or TUM RGB-D's rgb.txt), groundtruth.txt, pairs.txt.

Also pair sampling by frame gap and ground-truth labels of correspondences.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..core.geometry import Camera, CameraError, essential_from_pose, relative_pose, sym_epipolar_sq
from ..interface.caminfo import fit_camera
from ..interface.params import yaml_problem
from . import asl, kitti, tum
from .trajectory import DatasetError, Trajectory, check_ros_time, check_seconds, read_table, read_tum, ros_seconds

LABEL_THRESHOLD = 1e-4  # squared symmetric epipolar distance, normalised coordinates (paper)
MAX_VIEW_ANGLE_DEG = 40.0  # a pair's cameras turned further apart share too little of the scene to label


KALIBR_DISTORTION = {"radtan": "plumb_bob", "radial-tangential": "plumb_bob", "plumb_bob": "plumb_bob", "none": "plumb_bob",
                     "equidistant": "equidistant", "equi": "equidistant", "fisheye": "equidistant"}  # -> camera_info's


def read_camera_yaml(path: Path, topic: str | None = None) -> Camera:
    """A calibration file -> Camera: ROS camera_info YAML (camera_calibration_parsers' layout, a sequence folder's
    camera.yaml), Kalibr's camchain (its one camera, or the one whose ``rostopic`` is ``topic``) or EuRoC's
    sensor.yaml (Kalibr's fields for one camera), or OpenCV's own YAML (its calibration sample's, ORB-SLAM's
    settings), so bags recorded without camera_info replay with the calibration they came with."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: {'not a file' if path.exists() else 'no such file'}")
    try:
        text = path.read_text()
        if text.lstrip().startswith("%YAML:") or "!!opencv-matrix" in text:  # OpenCV's YAML: PyYAML cannot read it
            return _opencv_camera(path)
        d = yaml.safe_load(text)
        if isinstance(d, dict) and "camera_matrix" in d:
            K = np.array(d["camera_matrix"]["data"], np.float64).reshape(3, 3)
            dist = np.array(d.get("distortion_coefficients", {}).get("data", []) or [], np.float64)
            return Camera(K, dist, int(d.get("image_width", 0)), int(d.get("image_height", 0)),
                          d.get("distortion_model") or "")
        if isinstance(d, dict) and "intrinsics" in d:
            return _kalibr_camera(d)
        cams = {k: v for k, v in d.items() if isinstance(v, dict) and "intrinsics" in v} if isinstance(d, dict) else {}
        if not cams:
            raise DatasetError(f"{path}: not a camera calibration; expected a ROS camera_info YAML (camera_matrix, "
                               "distortion_coefficients, ...), a Kalibr camchain (cam0: intrinsics, ...), a EuRoC "
                               "sensor.yaml or an OpenCV YAML ('%YAML:1.0': camera_matrix, or ORB-SLAM's Camera.fx, ...)")
        on_topic = [k for k, v in cams.items() if topic is not None and v.get("rostopic") == topic]
        if len(cams) > 1 and len(on_topic) != 1:
            listed = ", ".join(f"{k} ({v.get('rostopic', 'no rostopic')})" for k, v in cams.items())
            raise DatasetError(f"{path}: {len(cams)} cameras ({listed}) and none's rostopic is the image topic "
                               f"{topic}; replay the camera's topic (--image-topic) or keep its entry only")
        return _kalibr_camera(cams[on_topic[0] if on_topic else next(iter(cams))])
    except DatasetError:
        raise
    except CameraError as e:
        raise DatasetError(f"{path}: {e}") from e
    except yaml.YAMLError as e:
        raise DatasetError(f"{path}: not valid YAML ({yaml_problem(e)})") from e
    except (KeyError, TypeError, ValueError) as e:  # a missing field, a wrong count, words for numbers
        raise DatasetError(f"{path}: malformed camera YAML ({type(e).__name__}: {e})") from e


def write_camera_yaml(path: Path, camera: Camera) -> None:
    """``camera`` as a ROS camera_info YAML (camera_calibration_parsers' layout), as :func:`read_camera_yaml` reads it."""
    def matrix(rows: int, cols: int, data: np.ndarray) -> dict:
        return {"rows": rows, "cols": cols, "data": [float(v) for v in np.ravel(data)]}

    P = np.c_[camera.K, np.zeros(3)]
    doc = {"image_width": int(camera.width), "image_height": int(camera.height), "camera_name": "camera",
           "camera_matrix": matrix(3, 3, camera.K), "distortion_model": camera.model,
           "distortion_coefficients": matrix(1, camera.dist.size, camera.dist),
           "rectification_matrix": matrix(3, 3, np.eye(3)), "projection_matrix": matrix(3, 4, P)}
    Path(path).write_text(yaml.safe_dump(doc, sort_keys=False))


def _opencv_camera(path: Path) -> Camera:
    """OpenCV's FileStorage YAML ('%YAML:1.0', or matrices tagged !!opencv-matrix; read with cv2.FileStorage): its
    calibration's ``camera_matrix`` and ``distortion_coefficients``, or ORB-SLAM2/3's settings (``Camera.fx`` or
    ``Camera1.fx``, ..., ``Camera.type`` PinHole with k1 k2 p1 p2 [k3], KannalaBrandt8 with k1..k4)."""
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:  # OpenCV's parser error comes as a SystemError from the constructor
        raise DatasetError(f"{path}: malformed OpenCV YAML ({str(e.__cause__ or e).strip().splitlines()[-1]})") from e

    def number(*names: str) -> float | None:
        """The first of ``names`` the file has, as a number (None: none of them)."""
        node = next((node for node in map(fs.getNode, names) if not node.empty()), None)
        return None if node is None else node.real()

    size = [int(number(f"image_{side}", f"Camera.{side}") or 0) for side in ("width", "height")]
    if not fs.getNode("camera_matrix").empty():
        K = fs.getNode("camera_matrix").mat()
        dist = fs.getNode("distortion_coefficients").mat()
        dist = np.zeros(0) if dist is None else dist.ravel()
        return Camera(K, dist, *size, "rational_polynomial" if dist.size > 5 else "plumb_bob")
    cam = next((p for p in ("Camera1.", "Camera.") if not fs.getNode(p + "fx").empty()), None)
    if cam is None:
        raise DatasetError(f"{path}: an OpenCV YAML without a camera; expected camera_matrix and "
                           "distortion_coefficients (OpenCV's calibration), or Camera.fx, ... (ORB-SLAM's settings)")
    fx, fy, cx, cy = intrinsics = [number(cam + k) for k in ("fx", "fy", "cx", "cy")]
    if None in intrinsics:
        raise DatasetError(f"{path}: {cam}{('fx', 'fy', 'cx', 'cy')[intrinsics.index(None)]} missing")
    kind = fs.getNode("Camera.type").string() or "PinHole"
    if kind not in ("PinHole", "KannalaBrandt8", "Rectified"):
        raise DatasetError(f"{path}: Camera.type {kind!r} is not supported; PinHole, KannalaBrandt8 or Rectified")
    names = ("k1", "k2", "k3", "k4") if kind == "KannalaBrandt8" else ("k1", "k2", "p1", "p2", "k3")
    dist = [number(cam + k) or 0.0 for k in names]
    if kind != "KannalaBrandt8" and number(cam + "k3") is None:
        dist = dist[:4]  # ORB-SLAM's k3 is optional: k1 k2 p1 p2, as OpenCV takes 4 coefficients
    return Camera(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), np.array(dist), *size,
                  "equidistant" if kind == "KannalaBrandt8" else "plumb_bob")


def _kalibr_camera(d: dict) -> Camera:
    """One camera of Kalibr's camchain / EuRoC's sensor.yaml: pinhole ``intrinsics`` [fu, fv, pu, pv],
    ``resolution`` [w, h], radtan or equidistant ``distortion_coeffs`` (EuRoC: ``distortion_coefficients``)."""
    if (model := d.get("camera_model", "pinhole")) != "pinhole":
        raise CameraError(f"camera_model {model!r} is not supported: only pinhole (with radtan or equidistant "
                          "distortion); calibrate with Kalibr's pinhole-radtan or pinhole-equi, or rectify the images")
    fu, fv, pu, pv = (float(v) for v in d["intrinsics"])
    name = str(d.get("distortion_model", "none"))
    if name not in KALIBR_DISTORTION:
        raise CameraError(f"distortion model {name!r} is not supported; use one of {', '.join(KALIBR_DISTORTION)}, or "
                          "rectify the images")
    dist = [] if name == "none" else d.get("distortion_coeffs", d.get("distortion_coefficients", []))
    w, h = (int(v) for v in d.get("resolution", (0, 0)))
    return Camera(np.array([[fu, 0, pu], [0, fv, pv], [0, 0, 1]]), np.array(dist, np.float64), w, h,
                  KALIBR_DISTORTION[name])


def _poses_at(gt: Trajectory, stamps: np.ndarray, source: Path, listing: Path) -> tuple[np.ndarray, bool]:
    """Each image's pose by its stamp, NaN where the ground truth has none (:meth:`Trajectory.at_frames`: a pose per
    frame is taken at the images' stamps only, ground truth at its own rate is interpolated), and whether it is a pose
    per frame. ``source`` and ``listing`` are the files of the poses and of the images' stamps."""
    poses, at_frames = gt.at_frames(stamps)
    if np.isnan(poses[:, 0, 0]).all():
        raise DatasetError(f"{source}: no pose at any image's stamp (stamps {gt.stamps[0]:.6f} .. "
                           f"{gt.stamps[-1]:.6f}, images {stamps.min():.6f} .. {stamps.max():.6f}); its timestamps must be "
                           f"those of {listing.name}")
    return poses, at_frames


FOLDERS_READ = ("camera.yaml + images.txt + groundtruth.txt, a EuRoC (ASL) or KITTI odometry download, or a TUM RGB-D "
                "sequence")  # what Sequence.load takes, for the tools' --help
BAG_SUFFIXES = (".mcap", ".db3", ".bag")
_BAG_HINT = ("this is a recording (a bag), which nmnet replay scores against its ground truth (`nmnet replay BAG --out "
             "o.mcap --json s.json`); nmnet eval and train read sequence folders")


def is_sequence_folder(root: Path) -> bool:
    """Whether ``root`` is laid out as a folder :meth:`Sequence.load` reads (ours, TUM's, EuRoC's or KITTI's)."""

    return any((root / name).is_file() for name in ("camera.yaml", "images.txt", "rgb.txt")) or \
        asl.camera_folder(root) is not None or kitti.image_folder(root) is not None


def _other_layout(root: Path) -> str | None:
    """What to do with a folder of another benchmark's layout (or a bag's folder) that lacks camera.yaml, or None."""
    if (root / "metadata.yaml").is_file() or any(p.suffix in BAG_SUFFIXES for p in root.iterdir()):
        return _BAG_HINT
    if any(root.glob("H_1_to_*")):
        return ("H_1_to_N files: a homography benchmark (Oxford affine regions, HPatches), which has no camera poses; "
                "nmnet eval and train score relative poses: they need camera.yaml and groundtruth.txt")
    if (root / "rgb.txt").is_file():
        return ("rgb.txt: a TUM RGB-D sequence, read as it is (rgb.txt for images.txt, its groundtruth.txt) once "
                "camera.yaml holds its camera's calibration (ROS camera_info YAML: the K and D TUM lists for "
                "freiburg1/2/3), or, named as TUM names it (rgbd_dataset_freiburg1_xyz), with TUM's published one")
    if inside := sorted(p.name for p in root.iterdir() if (p / "camera.yaml").is_file()):
        shown = ", ".join(inside[:4]) + (f" and {len(inside) - 4} more" if len(inside) > 4 else "")
        return f"it holds sequence folders ({shown}): give those, e.g. {' '.join(str(root / n) for n in inside[:2])}"
    return None


def decode_image(path: Path) -> np.ndarray:
    """An image file as stored; DatasetError naming it when missing, truncated or not an image."""
    try:  # decoded from its bytes: cv2.imread returns a truncated JPEG's top part, grey below, with a mere warning
        data = np.fromfile(path, np.uint8)
    except OSError as e:
        raise DatasetError(f"{path}: cannot read image: {e.strerror or e}") from e
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise DatasetError(f"{path}: cannot decode image ({data.size} bytes): truncated, corrupt or not an image "
                           "(PNG, JPEG, PGM, ...); copy it again from its source")
    return img


@dataclass
class Sequence:
    """One sequence folder with camera, frames, optional ground-truth poses and pairs."""

    root: Path
    camera: Camera
    stamps: np.ndarray  # (N,)
    paths: list[Path]
    poses: np.ndarray | None  # (N,4,4) T_WC; NaN for a frame groundtruth.txt has no pose for
    pairs_file: list[tuple[int, int]] | None
    calibration: Path  # camera.yaml (EuRoC's layout: the camera's sensor.yaml; KITTI's: calib.txt), named in messages
    truth_file: Path  # groundtruth.txt (EuRoC's: the body's data.csv; KITTI's: poses/NN.txt), named in messages
    size_note: str | None = None  # camera.yaml's K scaled to the images (a resized copy of a dataset)
    camera_note: str | None = None  # where the calibration came from when the folder has none (TUM RGB-D's)
    truth_at_frames: bool = False  # the ground truth is a pose per image's stamp (not at a rate of its own)

    @classmethod
    def load(cls, root: str | Path) -> Sequence:
        """Read a folder; raises DatasetError naming the missing or malformed file."""
        root = Path(root)
        if not root.is_dir():
            raise DatasetError(f"{root}: not a directory{'; ' + _BAG_HINT if root.suffix in BAG_SUFFIXES else ''}")
        published = None
        if not (root / "camera.yaml").is_file():
            if (cam := asl.camera_folder(root)) is not None:
                return cls._load_asl(root, cam)
            if (images := kitti.image_folder(root)) is not None:
                return cls._load_kitti(root, images)
            if (published := tum.published_camera(root)) is None:
                hint = _other_layout(root) or "a sequence folder needs camera.yaml (ROS camera_info YAML)"
                raise DatasetError(f"{root / 'camera.yaml'}: missing; {hint}")
        camera, camera_note = published or (read_camera_yaml(root / "camera.yaml"), None)
        listing = root / "images.txt"
        if not listing.is_file() and (root / "rgb.txt").is_file():
            listing = root / "rgb.txt"  # a TUM RGB-D sequence: the same 'timestamp path' lines
        rows = read_table(listing, "timestamp path", lambda r: (ros_seconds(r[0]), root / r[1].strip()), maxsplit=1)
        if not rows:
            raise DatasetError(f"{listing}: no frames listed")
        stamps = np.array([stamp for stamp, _ in rows])
        check_seconds(listing, stamps, "frames")
        check_ros_time(listing, stamps)
        paths = [path for _, path in rows]
        poses, at_frames = None, False
        if (root / "groundtruth.txt").is_file():
            poses, at_frames = _poses_at(read_tum(root / "groundtruth.txt"), stamps, root / "groundtruth.txt", listing)
        pairs = None
        if (root / "pairs.txt").is_file():
            pairs = read_table(root / "pairs.txt", "i j", lambda r: (int(r[0]), int(r[1])))
            bad = [p for p in pairs if not (0 <= p[0] < len(paths) and 0 <= p[1] < len(paths))]
            if bad:
                raise DatasetError(f"{root / 'pairs.txt'}: pair indices out of range: {bad[:3]}")
        seq = cls(root, camera, stamps, paths, poses, pairs, root / "camera.yaml", root / "groundtruth.txt",
                  camera_note=camera_note, truth_at_frames=at_frames)
        seq._fit_camera()
        return seq

    @classmethod
    def _load_asl(cls, root: Path, cam: Path) -> Sequence:
        """A folder in EuRoC's ASL layout (:mod:`nmnet_ros.io.asl`), its camera folder ``cam``."""

        stamps, paths = asl.read_frames(cam)
        return cls._of_layout(root, read_camera_yaml(cam / "sensor.yaml"), stamps, paths,
                              asl.read_ground_truth(cam.parent, cam / "sensor.yaml"),
                              (cam / "sensor.yaml", cam.parent / asl.GROUND_TRUTH, cam / "data.csv"))

    @classmethod
    def _load_kitti(cls, root: Path, images: Path) -> Sequence:
        """A KITTI odometry sequence folder (:mod:`nmnet_ros.io.kitti`), its left camera's ``images``."""

        camera, cam0_to_camera = kitti.camera_and_baseline(kitti.projection(root / "calib.txt", images))
        stamps, paths = kitti.read_frames(root, images)
        poses = kitti.poses_file(root)
        return cls._of_layout(root, camera, stamps, paths, kitti.read_poses(poses, stamps, cam0_to_camera),
                              (root / "calib.txt", poses, root / "times.txt"))

    @classmethod
    def _of_layout(cls, root: Path, camera: Camera, stamps: np.ndarray, paths: list[Path], truth: Trajectory | None,
                   files: tuple[Path, Path, Path]) -> Sequence:
        """A sequence read from another dataset's layout; ``files``: its calibration, ground-truth and frame list."""
        calibration, truth_file, listing = files
        poses, at_frames = (None, False) if truth is None else _poses_at(truth, stamps, truth_file, listing)
        seq = cls(root, camera, stamps, paths, poses, None, calibration, truth_file, truth_at_frames=at_frames)
        seq._fit_camera()
        return seq

    def _fit_camera(self) -> None:
        """Fit camera.yaml to the first image's size: K scaled, with a note, when the images are its size scaled
        evenly (a downscaled copy of a dataset); refused for any other size. Poses and labels from a camera of
        another size were silently wrong (AUC 0 on Strecha at half size). A calibration without a size (KITTI's
        calib.txt, a camera.yaml without image_width) takes the first image's, so that every frame is checked
        against it."""
        try:
            h, w = decode_image(self.paths[0]).shape[:2]
        except DatasetError:
            return  # named where the frame is used
        cam = self.camera
        if cam.width <= 0 or cam.height <= 0:
            self.camera = replace(cam, width=w, height=h)
            return
        fitted, _ = fit_camera(cam, (w, h))
        said = f"{self.calibration} describes {cam.width}x{cam.height} frames but {self.paths[0].name} is {w}x{h}"
        if fitted is None:
            raise DatasetError(f"{said}, which is not the same image scaled (cropped images, another camera's "
                               f"calibration?): give the folder the {self.calibration.name} of these images")
        if fitted is not cam:
            self.camera = fitted
            self.size_note = f"{said}: K scaled by {w / cam.width:.4g} to fit (a {self.calibration.name} of these images silences this)"

    @property
    def name(self) -> str:
        return self.root.name

    def __len__(self) -> int:
        return len(self.paths)

    def image(self, i: int) -> np.ndarray:
        """Frame i as stored (uint8 gray or BGR), the size of the folder's camera."""
        img = decode_image(self.paths[i])
        (h, w), cam = img.shape[:2], self.camera
        if cam.width > 0 and (w, h) != (cam.width, cam.height):
            raise DatasetError(f"{self.paths[i]}: {w}x{h}, but the folder's frames are {cam.width}x{cam.height} "
                               f"({'as its first image' if self.size_note else f'as {self.calibration.name} says'}): every frame "
                               "of a sequence folder must be one size")
        return img

    def image_version(self, i: int) -> str:
        """Frame i's file as it is now (its path in the folder, size and modification time), for caches: an image
        replaced or edited since is a new entry, and two files of one name in different subfolders are two."""
        path = self.paths[i]
        try:
            st = path.stat()
        except OSError as e:
            raise DatasetError(f"{path}: cannot read image: {e.strerror or e}") from e
        return f"{path.relative_to(self.root) if path.is_relative_to(self.root) else path}|{st.st_size}|{st.st_mtime_ns}"

    def has_pose(self, i: int) -> bool:
        """Whether groundtruth.txt gives frame i a pose."""
        return self.poses is not None and not np.isnan(self.poses[i, 3, 3])

    def notes(self, uncovered: str = "pairs with them are left out") -> list[str]:
        """What to tell the user before using the folder: K scaled to the images, frames without a pose (and
        ``uncovered``: what the tool does with those), a calibration the folder does not hold."""
        return [note for note in (self.camera_note, self.size_note, self.uncovered_note(uncovered)) if note]

    def uncovered_note(self, consequence: str = "pairs with them are left out") -> str | None:
        """What to tell the user when groundtruth.txt leaves frames without a pose (None when it covers all)."""
        if self.poses is None:
            return None
        missing = np.flatnonzero(np.isnan(self.poses[:, 3, 3]))
        if not len(missing):
            return None
        listed = ", ".join(map(str, missing[:5])) + (", ..." if len(missing) > 5 else "")
        why = "no line at their stamps" if self.truth_at_frames else \
            "none between two of the file's poses nor within half its spacing of one"
        return f"{self.truth_file}: {len(missing)} of {len(self)} frames have no pose ({why}; frames {listed}); {consequence}"

    def relative_pose(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of frame i in frame j: x_j = R x_i + t."""
        if self.poses is None:
            raise DatasetError(f"{self.truth_file}: missing, so no ground-truth pose")
        for k in (i, j):
            if not self.has_pose(k):
                raise DatasetError(f"{self.truth_file}: no pose for frame {k} ({self.paths[k].name})")
        return relative_pose(self.poses[i], self.poses[j])

    def frames(self, frames: range | None = None) -> range:
        """``frames`` (a 'PATH:a-b' range), checked against the folder; all of them for None."""
        if frames is None:
            return range(len(self))
        if not len(frames) or frames.start < 0 or frames.stop > len(self):
            raise DatasetError(f"{self.root}: frames {frames.start}-{frames.stop - 1} "
                               + ("are none (the first is after the last)" if not len(frames) else
                                  f"are not all in the folder; it has frames 0-{len(self) - 1}"))
        return frames

    def pairs(self, gaps: tuple[int, ...] = (1,), frames: range | None = None) -> list[tuple[int, int]]:
        """pairs.txt's pairs with both frames in ``frames`` when it is present, else (i, i+g) for every gap g with
        both frames in ``frames`` (default: all)."""
        frames = self.frames(frames)
        fs = set(frames)
        if self.pairs_file is not None:
            return [(i, j) for i, j in self.pairs_file if i in fs and j in fs]
        return [(i, i + g) for g in gaps for i in frames if i + g in fs]


def epipolar_labels(seq: Sequence, i: int, j: int, k0: np.ndarray, k1: np.ndarray,
                    threshold: float = LABEL_THRESHOLD) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth inlier labels and squared symmetric epipolar distances for pixel matches k0 (frame i) <-> k1 (frame j)."""
    R, t = seq.relative_pose(i, j)
    return pose_labels(R, t, seq.camera.normalize(k0), seq.camera.normalize(k1), threshold)


def pose_labels(R: np.ndarray, t: np.ndarray, x0: np.ndarray, x1: np.ndarray,
                threshold: float = LABEL_THRESHOLD) -> tuple[np.ndarray, np.ndarray]:
    """Inlier labels and squared symmetric epipolar distances of normalised matches under the pose (R, t)."""
    d = sym_epipolar_sq(essential_from_pose(R, t), x0, x1)
    return d < threshold, d


def has_baseline(seq: Sequence, i: int, j: int, min_translation: float = 1e-2) -> bool:
    """Whether the pair moved enough for epipolar labels (translation norm in GT units).

    A static camera (e.g. the EuRoC excerpt, MAV on the ground) has an undefined epipolar
    geometry: every match would be labelled by noise, so such pairs are excluded.
    """
    _, t = seq.relative_pose(i, j)
    return bool(np.linalg.norm(t) > min_translation)
