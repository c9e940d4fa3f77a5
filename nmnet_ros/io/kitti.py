"""KITTI odometry's folder layout, read as a sequence folder, so that ``nmnet eval`` and ``train`` take a KITTI
download as it is.

The layout: ``sequences/NN/image_0/`` (or ``image_2/``, the colour download), ``sequences/NN/calib.txt`` (the
rectified cameras' 3x4 projections ``P0:`` ... ``P3:``), ``sequences/NN/times.txt`` (seconds, a line per frame)
and ``poses/NN.txt`` beside ``sequences/`` (cam0's pose in the first frame's coordinates, a 3x4 matrix a line;
sequences 00-10 only). The colour camera's poses are cam0's moved by its baseline, read from its projection.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.geometry import Camera
from .trajectory import DatasetError, Trajectory, check_seconds, floats, read_table

CAMERAS = ("image_0", "image_2")  # grey left, colour left: the two downloads' left camera


def image_folder(root: Path) -> Path | None:
    """The left camera's image folder of a KITTI odometry sequence folder (``sequences/NN``), or None."""
    if not ((root / "times.txt").is_file() and (root / "calib.txt").is_file()):
        return None
    return next((root / c for c in CAMERAS if (root / c).is_dir()), None)


def poses_file(root: Path) -> Path:
    """Where KITTI keeps a sequence's ground truth: ``poses/NN.txt`` beside ``sequences/``."""
    return root.parent.parent / "poses" / f"{root.name}.txt"


def projection(calib: Path, images: Path) -> np.ndarray:
    """The 3x4 projection of the camera whose images are in ``images`` (``image_2`` -> ``P2:``)."""
    key = f"P{images.name[-1]}:"
    rows = read_table(calib, "NAME: 12 numbers", lambda r: (r[0], r[1:]))
    found = [values for name, values in rows if name == key]
    if not found:
        raise DatasetError(f"{calib}: no '{key}' line, the projection of {images.name}'s camera")
    try:
        return np.array(floats(12)(found[0]), np.float64).reshape(3, 4)
    except ValueError as e:
        raise DatasetError(f"{calib}: '{key}' must be 12 numbers (a 3x4 projection), got {len(found[0])}") from e


def read_frames(root: Path, images: Path) -> tuple[np.ndarray, list[Path]]:
    """The stamps (times.txt, seconds) and the image paths (``000000.png`` ..., one per line of times.txt)."""
    stamps = np.array(read_table(root / "times.txt", "seconds", lambda r: floats(1)(r)[0]), np.float64)
    if not len(stamps):
        raise DatasetError(f"{root / 'times.txt'}: no frames listed")
    check_seconds(root / "times.txt", stamps, "frames")
    return stamps, [images / f"{i:06d}.png" for i in range(len(stamps))]


def camera_and_baseline(P: np.ndarray) -> tuple[Camera, np.ndarray]:
    """The rectified camera of a projection ``P = K [I | b]`` (no distortion) and the camera's pose in cam0's
    coordinates (4x4: cam0's origin is at ``b`` in this camera's coordinates)."""
    K = P[:, :3]
    T = np.eye(4)
    T[:3, 3] = -np.linalg.solve(K, P[:, 3])
    return Camera(K, np.zeros(0)), T


def read_poses(path: Path, stamps: np.ndarray, cam0_to_camera: np.ndarray) -> Trajectory | None:
    """The camera's poses, a line of ``path`` per frame (None when the file is not there)."""
    if not path.is_file():
        return None
    rows = read_table(path, "12 numbers (a 3x4 camera-to-world matrix)", floats(12))
    if len(rows) != len(stamps):
        raise DatasetError(f"{path}: {len(rows)} poses for {len(stamps)} frames of times.txt: a line per frame, "
                           "in order; is it this sequence's file?")
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :] = np.array(rows, np.float64).reshape(-1, 3, 4)
    return Trajectory(stamps, T).moved(cam0_to_camera)
