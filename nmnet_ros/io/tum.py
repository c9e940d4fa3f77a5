"""TUM RGB-D's published colour-camera calibrations, so that a sequence folder as TUM ships it
(``rgbd_dataset_freiburg1_xyz``: rgb.txt, rgb/, groundtruth.txt, no calibration file) reads as it is.

The values are those of the benchmark's "Intrinsic Camera Calibration of the Kinect" (ROS plumb_bob order
k1 k2 p1 p2 k3; the Freiburg 3 images were undistorted by the sensor, hence no distortion).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..core.geometry import Camera

RGB_CAMERAS = {  # fx, fy, cx, cy, (k1, k2, p1, p2, k3)
    1: (517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    2: (520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    3: (535.4, 539.2, 320.1, 247.6, (0.0, 0.0, 0.0, 0.0, 0.0)),
}


def published_camera(root: Path) -> tuple[Camera, str] | None:
    """The calibration TUM publishes for the camera a TUM RGB-D folder was recorded with (named by the folder,
    ``..._freiburgN_...``), with a note saying so; None for any other folder."""
    if not (root / "rgb.txt").is_file():
        return None
    found = re.search(r"freiburg([123])", root.resolve().name)
    if found is None:
        return None
    fx, fy, cx, cy, dist = RGB_CAMERAS[int(found[1])]
    note = (f"{root / 'camera.yaml'}: missing; TUM's published calibration of the freiburg{found[1]} RGB camera is "
            f"used (fx {fx}, fy {fy}, cx {cx}, cy {cy}); a camera.yaml in the folder replaces it")
    return Camera(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), np.array(dist), 640, 480), note
