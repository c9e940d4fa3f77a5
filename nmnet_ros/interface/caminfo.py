"""sensor_msgs/CameraInfo -> :class:`~nmnet_ros.core.geometry.Camera` for the frames it describes, without ROS imports.

Works on ROS 1 and ROS 2 messages (``K``/``k``, ``D``/``d``), from rclpy or rosbags, so the node and
the bag tools read calibration the same way. Binning and region of interest are read as
image_geometry reads them: K and D describe the full-resolution sensor, and an image binned by
(bx, by) and cut at (x0, y0) has fx / bx, (cx - x0) / bx, and so on.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..core.geometry import Camera, CameraError

MIN_SIZE = 16  # pixels a side: a binned or cut image smaller than this is no camera's


def _field(msg, name: str):
    """ROS 2 lower-case field, else the ROS 1 upper-case one."""
    value = getattr(msg, name.lower(), None)
    return getattr(msg, name.upper(), None) if value is None else value


def camera_from_info(msg: Any, rectified: bool = False) -> Camera:
    """The camera of the images a CameraInfo message belongs to; CameraError when K or D is unusable.

    ``rectified``: the images are image_proc's rectified ones (``image_rect``), whose camera is P's left
    3x3 with no distortion; K and D describe the raw images.
    """
    if rectified:
        P = np.asarray(_field(msg, "p"), np.float64)
        if P.size != 12:
            raise CameraError(f"camera_info P must have 12 values, got {P.size}")
        K = P.reshape(3, 4)[:, :3].copy()
        if not K.any():
            raise CameraError("camera_info P is all zero, so rectified frames have no camera (is the camera calibrated?)")
    else:
        K = np.asarray(_field(msg, "k"), np.float64)
        if K.size != 9:
            raise CameraError(f"camera_info K must have 9 values, got {K.size}")
        K = K.reshape(3, 3).copy()
    width, height = int(msg.width), int(msg.height)
    bx, by = max(int(getattr(msg, "binning_x", 0)), 1), max(int(getattr(msg, "binning_y", 0)), 1)
    roi = getattr(msg, "roi", None)
    if roi is not None and (roi.width or roi.height or roi.x_offset or roi.y_offset):
        if width > 0 and height > 0 and (roi.x_offset + roi.width > width or roi.y_offset + roi.height > height):
            raise CameraError(f"camera_info roi ({roi.width}x{roi.height} at {roi.x_offset},{roi.y_offset}) reaches "
                              f"outside the {width}x{height} sensor it is cut from: check the driver's roi")
        K[0, 2] -= roi.x_offset
        K[1, 2] -= roi.y_offset
        width, height = int(roi.width) or width - int(roi.x_offset), int(roi.height) or height - int(roi.y_offset)
    if bx > 1 or by > 1:
        if width > 0 and height > 0 and (width // bx < MIN_SIZE or height // by < MIN_SIZE):
            raise CameraError(f"camera_info binning {bx}x{by} leaves {width // bx}x{height // by} of the {width}x{height} "
                              "sensor: not a camera's image; check the driver's binning_x/binning_y (0 or 1: none)")
        K[0] /= bx
        K[1] /= by
        width, height = width // bx, height // by
    if rectified:
        return Camera(K, np.zeros(5), width, height)
    return Camera(K, np.asarray(_field(msg, "d"), np.float64), width, height, getattr(msg, "distortion_model", ""))


def fit_camera(camera: Camera, size: tuple[int, int]) -> tuple[Camera | None, str | None]:
    """The camera for frames of ``size`` (w, h), and a note when the calibration is for another size.

    A frame that is the calibrated size scaled evenly (a resized stream with the full-size
    camera_info) gets K scaled to fit, with a note; any other size (a crop, a wrong topic) cannot be
    fitted: ``None`` and the reason. A camera without a size (parameters, old bags) takes the frame's, so its K and D
    are checked against it (:func:`~nmnet_ros.core.geometry.calibration_problem`: CameraError when implausible).
    """
    w, h = size
    if camera.width <= 0 or camera.height <= 0:  # checked against these frames (CameraError when implausible)
        return Camera(camera.K, camera.dist, w, h, camera.model), None
    if (w, h) == (camera.width, camera.height):
        return camera, None
    sx, sy = w / camera.width, h / camera.height
    seen = f"frames are {w}x{h} but camera_info describes {camera.width}x{camera.height}"
    if abs(sx - sy) > 0.01 * max(sx, sy):
        return None, (f"{seen}, which is not the same image scaled (a crop or another camera's calibration?): frame "
                      "skipped; publish the camera_info that belongs to these frames (or set its roi)")
    return camera.resized(w, h), f"{seen}: K scaled by {sx:.4g} to fit; publish the camera_info that belongs to these frames"


def info_fields(camera: Camera, width: int, height: int, ros1: bool = False) -> dict:
    """The calibration fields of a CameraInfo for frames of ``width`` x ``height``: K, D, R = I, P = [K | 0].

    Field names as ROS 2 (``k``, ``d``, ...) or ROS 1 (``K``, ``D``, ...) spell them; plumb_bob D padded to 5.
    """
    names = ("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p")
    values = (camera.distortion_for_msg(), camera.K.ravel(), np.eye(3).ravel(), np.c_[camera.K, np.zeros(3)].ravel())
    return {"height": height, "width": width, "distortion_model": camera.model, **dict(zip(names, values, strict=True))}
