"""Relative pose in the form the ROS outputs carry (no ROS imports).

The front end estimates x_cur = R x_prev + t. Published is the pose of the current camera in
the previous camera's optical frame: T_prev_cur = inv([R | t]), translation a unit direction
(monocular: the scale is unknown) and a diagonal covariance that shrinks with the number of
selected matches.

Every processed frame gets one message, relative to the frame of the message before it, so a back end knows
both frames of every pair from the messages alone. A frame without an estimate (a stream's first, too few
matches, a failed pose, a restart of the chain: new frame size, time jump, new detector settings) gets the
identity with NO_ESTIMATE_VAR on every axis: no information, so that a back end chaining the messages sees the
gap instead of bridging it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..core.geometry import PoseEstimate, quat_to_rot, rotation_error_deg
from ..core.settings import BY_NAME

ROT_SIGMA_DEG = BY_NAME["pose_sigma_rotation_deg"].default  # per-axis rotation sigma at REF_MATCHES selected matches
ROT_SIGMA_RAD = np.radians(ROT_SIGMA_DEG)
DIR_SIGMA = BY_NAME["pose_sigma_direction"].default  # per-axis sigma of the unit translation direction at REF_MATCHES
SIGMAS = (ROT_SIGMA_DEG, DIR_SIGMA)  # the default (rotation degrees, direction) at REF_MATCHES
REF_MATCHES = 200
NO_ESTIMATE_VAR = 1e6  # variance on every axis of a frame without an estimate


def stamp_seconds(stamp: Any) -> float:
    """A header stamp (builtin_interfaces/Time: sec, nanosec) in seconds; NaN when it is no ROS time (nanosec
    outside 0 .. 999,999,999), which :func:`~nmnet_ros.core.pipeline.stamp_order` refuses as ``invalid_stamp``."""
    return stamp.sec + 1e-9 * stamp.nanosec if 0 <= stamp.nanosec < 1_000_000_000 else float("nan")


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """3x3 rotation -> quaternion (x, y, z, w), w >= 0."""
    R = np.asarray(R, np.float64)
    w = np.sqrt(max(0.0, 1.0 + np.trace(R))) / 2.0
    x = np.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2])) / 2.0
    y = np.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2])) / 2.0
    z = np.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2])) / 2.0
    x = np.copysign(x, R[2, 1] - R[1, 2])
    y = np.copysign(y, R[0, 2] - R[2, 0])
    z = np.copysign(z, R[1, 0] - R[0, 1])
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


def relative_pose_of_current(status: str, pose: PoseEstimate | None, num_matches: int,
                             sigmas: tuple[float, float] = SIGMAS
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(quaternion xyzw, translation direction, 6x6 covariance [x y z roll pitch yaw]) of T_prev_cur for a
    frame of ``status`` (a FrameResult's).

    ``sigmas``: (rotation degrees, direction) per axis at REF_MATCHES selected matches, scaled by
    sqrt(REF_MATCHES / num_matches).

    ``ok``: the estimate; when the matches lie on one plane and a second pose fits them as well
    (``pose.alternative``), each variance is at least the squared distance to that pose (radians; the chord between
    the directions). ``no_motion`` (a camera that turned or stood without a measurable baseline): its
    rotation (the identity when ``pose`` is None) with zero translation, the rotation covariance and a tiny
    translation variance. Any other status: the identity with NO_ESTIMATE_VAR on every axis.
    """
    cov = np.zeros((6, 6))
    if status not in ("ok", "no_motion") or (status == "ok" and pose is None):
        return np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3), np.eye(6) * NO_ESTIMATE_VAR
    scale = REF_MATCHES / max(num_matches, 1)
    rot_var, dir_var = np.radians(sigmas[0]) ** 2 * scale, sigmas[1] ** 2 * scale
    if status == "no_motion":
        cov[:3, :3] = np.eye(3) * 1e-6
        cov[3:, 3:] = np.eye(3) * rot_var
        return (rot_to_quat(pose.R.T) if pose is not None else np.array([0.0, 0.0, 0.0, 1.0])), np.zeros(3), cov
    R_pc, t_pc = _of_current(pose)
    if (other := pose.alternative) is not None:  # a plane's two poses: the covariance reaches the other one
        R_alt, t_alt = _of_current(other)
        rot_var = max(rot_var, np.radians(rotation_error_deg(R_pc, R_alt)) ** 2)
        dir_var = max(dir_var, float(np.sum((t_pc - t_alt) ** 2)))
    cov[:3, :3] = np.eye(3) * dir_var
    cov[3:, 3:] = np.eye(3) * rot_var
    return rot_to_quat(R_pc), t_pc, cov


def widened(cov: np.ndarray, sigmas: tuple[float, float] = SIGMAS) -> bool:
    """Whether a published covariance (6x6) was widened to reach a plane's second pose: its rotation and direction
    variances are no longer in the proportion of ``sigmas``, the (rotation degrees, direction) it was published
    with. Such a frame's variance says how far the other pose is, not how the estimate scatters."""
    rot, direction = cov[3, 3] * sigmas[1] ** 2, cov[0, 0] * np.radians(sigmas[0]) ** 2
    return bool(abs(rot - direction) > 1e-9 * max(rot, direction))


def _of_current(pose: PoseEstimate) -> tuple[np.ndarray, np.ndarray]:
    """T_prev_cur's rotation and unit translation of a pose x_cur = R x_prev + t."""
    t_pc = -pose.R.T @ pose.t
    return pose.R.T, t_pc / max(np.linalg.norm(t_pc), 1e-12)


def estimate_of_message(q_xyzw: np.ndarray, position: np.ndarray, covariance: np.ndarray) -> tuple[str, PoseEstimate | None]:
    """A relative_pose message read back in the front end's terms (the inverse of :func:`relative_pose_of_current`):
    status ``ok`` with the pose (x_cur = R x_prev + t), ``no_motion`` with the rotation and t = 0, or ``no_estimate``
    without one."""
    if np.asarray(covariance).ravel()[0] >= NO_ESTIMATE_VAR:  # the message carries it row-major, 36 values
        return "no_estimate", None
    p = np.asarray(position, np.float64)
    R_pc = quat_to_rot(q_xyzw)
    pose = PoseEstimate(R_pc.T, -R_pc.T @ p, np.zeros((3, 3)), np.zeros(0, bool))
    return ("ok" if p.any() else "no_motion"), pose  # an estimate's translation is a unit direction
