"""Two-view geometry: camera model, normalisation, essential matrix, pose, error metrics.

Conventions: for a pair (image 0, image 1), R, t map camera-0 coordinates to camera 1
(x1 = R x0 + t) and E = [t]x R, so x1n^T E x0n = 0 for normalised coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import ModuleType
from typing import TypeVar

import cv2
import numpy as np
import poselib

ArrayT = TypeVar("ArrayT")  # a numpy array, or a torch tensor where gradients are needed


class CameraError(ValueError):
    """Invalid intrinsics (zeros, NaN, wrong shape)."""


# camera_info distortion models (sensor_msgs/distortion_models.h) this camera model undistorts
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant")
# plumb_bob / rational_polynomial inversion: OpenCV's default of 5 fixed-point steps leaves up to 0.29 px in the
# corners of EuRoC's lens (k1 = -0.28), twice the pose's inlier threshold; 50 steps or 1e-12 leave < 1e-9 px
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
# focal length in pixels per pixel of image size: below 0.1 the field of view exceeds any lens' (a 220-degree fisheye
# has about 0.26), above 100 it is under 0.6 degrees; K in normalised units or in millimetres lands far below
FOCAL_PER_PIXEL = (0.1, 100.0)
PRINCIPAL_MARGIN = 0.25  # the principal point may lie this share of the image size outside it (a shifted lens)


def scale_pixels(pts: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Pixel positions (..., 2) in the image resized by (sx, sy): pixel centres scale, u' + 0.5 = (u + 0.5) * s."""
    return (np.asarray(pts, np.float64) + 0.5) * np.array([sx, sy]) - 0.5


@dataclass
class Camera:
    """Pinhole camera with optional distortion: plumb_bob / rational_polynomial (OpenCV's k1 k2 p1 p2 k3 ...)
    or equidistant (the fisheye model, k1..k4, as camera_info names it)."""

    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    width: int = 0
    height: int = 0
    model: str = "plumb_bob"

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, np.float64)
        self.dist = np.asarray(self.dist, np.float64).ravel()
        self.model = self.model or "plumb_bob"  # an empty distortion_model is the usual "no distortion"
        if self.model not in DISTORTION_MODELS and not self.dist.any():  # no coefficients, or all 0: none in any model
            self.model, self.dist = "plumb_bob", np.zeros(0)  # (RealSense's inverse_brown_conrady, a driver's "none")
        if self.model not in DISTORTION_MODELS:
            raise CameraError(f"distortion model {self.model!r} is not supported; use one of {', '.join(DISTORTION_MODELS)}, "
                              "or rectify the images and publish zero distortion")
        if self.K.shape != (3, 3):
            raise CameraError(f"K must be 3x3, got shape {self.K.shape}")
        if not np.all(np.isfinite(self.K)) or not np.all(np.isfinite(self.dist)):
            raise CameraError("camera intrinsics contain NaN or inf; check the calibration (camera_info K/D)")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise CameraError(f"camera focal lengths must be positive, got fx={self.K[0, 0]}, fy={self.K[1, 1]}: "
                              "is the camera calibrated (camera_info K all zero)?")
        if not np.allclose(self.K[2], [0.0, 0.0, 1.0]) or self.K[1, 0] != 0:
            raise CameraError(f"K must be [fx s cx; 0 fy cy; 0 0 1], got rows 2-3 {self.K[1].tolist()} "
                              f"{self.K[2].tolist()}: divide K by its last element, or check its row order")
        if self.model == "equidistant" and self.dist.size == 5 and self.dist[4] == 0:
            self.dist = self.dist[:4]  # realsense-ros pads the T265's k1..k4 with a 0 (ROS 1; ROS 2 until late 2021)
        if self.model == "equidistant" and self.dist.size not in (0, 4):
            fifth = f" (a fifth of 0 is taken as padding; this one is {self.dist[4]:g})" if self.dist.size == 5 else ""
            raise CameraError(f"equidistant (fisheye) distortion has 4 coefficients k1..k4, got {self.dist.size}{fifth}")
        if self.dist.size not in (0, 4, 5, 8, 12, 14):
            raise CameraError(f"distortion must have 0/4/5/8/12/14 coefficients, got {self.dist.size}")
        if self.width > 0 and self.height > 0 and (problem := calibration_problem(self)) is not None:
            raise CameraError(problem)

    @property
    def focal(self) -> float:
        """Mean focal length in pixels (for pixel <-> normalised thresholds)."""
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    def normalize(self, pts: np.ndarray) -> np.ndarray:
        """Pixel (N,2) -> undistorted normalised image coordinates (N,2)."""
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        if len(pts) == 0:
            return np.zeros((0, 2))
        y = (pts[:, 1] - self.K[1, 2]) / self.K[1, 1]  # K^-1 [u v 1], skew included
        x = np.stack([(pts[:, 0] - self.K[0, 2] - self.K[0, 1] * y) / self.K[0, 0], y], axis=1)
        if not np.any(self.dist):
            return x
        # the lens model in normalised coordinates: OpenCV's undistortPoints would read fx fy cx cy of K and drop the skew
        eye = np.eye(3)
        if self.model == "equidistant":  # its default (10 steps, 1e-8) converges on fisheye lenses
            return cv2.fisheye.undistortPoints(x[:, None], eye, self.dist).reshape(-1, 2)
        return cv2.undistortPoints(x[:, None], eye, self.dist, None, eye, eye, UNDISTORT_CRITERIA).reshape(-1, 2)

    def resized(self, width: int, height: int, original: tuple[int, int] | None = None) -> Camera:
        """The camera of these frames resized to ``width`` x ``height`` (from ``original``, else its own size).

        Pixel centres scale, not corners: u' + 0.5 = (u + 0.5) * s. Distortion is in normalised
        coordinates, so it stays.
        """
        w0, h0 = original or (self.width, self.height)
        if w0 <= 0 or h0 <= 0:
            raise CameraError("the camera has no image size to resize from")
        sx, sy = width / w0, height / h0
        K = self.K.copy()
        K[0, :2] *= sx
        K[1, :2] *= sy
        K[:2, 2] = scale_pixels(self.K[:2, 2], sx, sy)  # the principal point is a pixel position
        return Camera(K, self.dist, width, height, self.model)

    def distortion_for_msg(self) -> np.ndarray:
        """The D of a camera_info message: plumb_bob padded with zeros to its 5 coefficients."""
        if self.model == "plumb_bob" and self.dist.size < 5:
            return np.r_[self.dist, np.zeros(5 - self.dist.size)]
        return self.dist


def calibration_problem(camera: Camera) -> str | None:
    """Why K and D cannot be a calibration of ``camera``'s image size (None when they can): a focal length or
    principal point out of proportion to the image (K in normalised units, in millimetres, of another resolution),
    or a lens model that folds back before the image's corners, so that undistortion cannot be inverted there.
    A camera with such K or D gives poses with a confidence they do not have; no pose is better."""
    w, h, K = camera.width, camera.height, camera.K
    for axis, f, size in (("fx", K[0, 0], w), ("fy", K[1, 1], h)):
        lo, hi = FOCAL_PER_PIXEL[0] * size, FOCAL_PER_PIXEL[1] * size
        if not lo <= f <= hi:
            return (f"{axis} = {f:.6g} px cannot be a {w}x{h} camera's (a focal length from {lo:.4g} to {hi:.4g} px: "
                    "fields of view from 0.6 degrees to a fisheye's): K must be in pixels of these frames, not "
                    "normalised or in millimetres")
    for axis, c, size in (("cx", K[0, 2], w), ("cy", K[1, 2], h)):
        if not -PRINCIPAL_MARGIN * size <= c <= (1 + PRINCIPAL_MARGIN) * size:
            return (f"principal point {axis} = {c:.6g} px lies far outside the {w}x{h} image: K must be in pixels of "
                    "these frames (check the camera_info's roi, binning and image size)")
    if not camera.dist.any():
        return None
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    y = (corners[:, 1] - K[1, 2]) / K[1, 1]
    reach = float(np.hypot((corners[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0], y).max())  # distorted radius needed
    angle = np.linspace(0.0, np.radians(179.0) if camera.model == "equidistant" else np.radians(89.0), 4000)[1:]
    radius = _distorted_radius(camera, angle)
    past = np.flatnonzero(radius >= reach)
    end = past[0] + 1 if past.size else radius.size
    if past.size == 0 or np.any(np.diff(radius[:end]) <= 0):
        top = float(radius[: end].max())
        return (f"the {camera.model} distortion D = {np.round(camera.dist, 6).tolist()} folds back at a distorted "
                f"radius of {top:.3g} (normalised), before the image's corners at {reach:.3g}: no lens maps pixels so, "
                "and the frames cannot be undistorted there; check D's order and units (OpenCV's k1 k2 p1 p2 k3)")
    return None


def _distorted_radius(camera: Camera, angle: np.ndarray) -> np.ndarray:
    """The distorted normalised radius of rays ``angle`` (radians) off the optical axis, tangential terms aside."""
    d = np.r_[camera.dist, np.zeros(8)]
    if camera.model == "equidistant":  # r_d = theta (1 + k1 theta^2 + ... + k4 theta^8)
        t2 = angle ** 2
        return angle * (1 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))))
    r2 = np.tan(angle) ** 2  # plumb_bob / rational_polynomial: k1 k2 p1 p2 k3 k4 k5 k6
    return np.sqrt(r2) * (1 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))) / (1 + r2 * (d[5] + r2 * (d[6] + r2 * d[7])))


def _checked_pair(x0: np.ndarray, x1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x0 = np.asarray(x0, np.float64).reshape(-1, 2) if np.size(x0) else np.zeros((0, 2))
    x1 = np.asarray(x1, np.float64).reshape(-1, 2) if np.size(x1) else np.zeros((0, 2))
    if len(x0) != len(x1):
        raise ValueError(f"point arrays differ in length: {len(x0)} vs {len(x1)}")
    return x0, x1


def relative_pose(T_wc_a: np.ndarray, T_wc_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with x_b = R x_a + t, from two camera-to-world poses."""
    T = np.linalg.inv(T_wc_b) @ T_wc_a
    return T[:3, :3], T[:3, 3]


def skew(t: np.ndarray) -> np.ndarray:
    """Cross-product matrix [t]x."""
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]], np.float64)


def essential_from_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """E = [t]x R (t normalised)."""
    t = np.asarray(t, np.float64).ravel()
    return skew(t / max(np.linalg.norm(t), 1e-12)) @ R


def sym_epipolar_sq(E: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Squared symmetric epipolar distance of normalised correspondences (the paper's label rule)."""
    x0, x1 = _checked_pair(x0, x1)
    h0 = np.c_[x0, np.ones(len(x0))]
    h1 = np.c_[x1, np.ones(len(x1))]
    l1 = h0 @ E.T  # epipolar lines in image 1
    l0 = h1 @ E  # epipolar lines in image 0
    num = np.sum(h1 * l1, axis=1) ** 2
    return num * (1.0 / (l1[:, 0] ** 2 + l1[:, 1] ** 2 + 1e-15) + 1.0 / (l0[:, 0] ** 2 + l0[:, 1] ** 2 + 1e-15))


def apply_homography(H: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,2) points mapped by the 3x3 homography H, and their homogeneous scale w (w <= 0: behind)."""
    p = np.c_[pts, np.ones(len(pts))] @ np.asarray(H, np.float64).T
    w = p[:, 2]
    return p[:, :2] / np.where(np.abs(w) > 1e-12, w, 1.0)[:, None], w


def homography_jacobian(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """d(H(x))/dx at each point, (N,2,2): how H maps a local affine frame there."""
    H = np.asarray(H, np.float64)
    p = np.c_[pts, np.ones(len(pts))] @ H.T
    w = p[:, 2, None, None]
    return (H[None, :2, :2] * w - p[:, :2, None] * H[None, 2, None, :2]) / w**2


@dataclass
class PoseEstimate:
    """Relative pose from two views: x1 = R x0 + t, |t| = 1 (scale unknown)."""

    R: np.ndarray
    t: np.ndarray
    E: np.ndarray
    inliers: np.ndarray  # (N,) bool: correspondences consistent with the pose
    alternative: PoseEstimate | None = None  # another pose the matches fit as well (a plane's second: planes.py)


MIN_MATCHES = 8
# PoseLib stops no earlier than this (its own default, 1000, took 4x the time on ordinary pairs for the same poses)
POSELIB_MIN_ITERATIONS = 100


@dataclass(frozen=True)
class RobustEstimator:
    """What a caller must know of a robust estimator beyond its name."""

    min_threshold_px: float = 0.0  # a hard bound on the error: never tighter than this
    refines_pose: bool = False  # it polishes its own pose: a polish after it is not needed


ROBUST_ESTIMATORS = {
    "magsac": RobustEstimator(),  # the threshold is a noise scale
    # its own default threshold, a hard bound: 0.5 px lost 4 AUC@5 on the hard validation set's pairs with < 10 %
    # inliers; the Cauchy polish after its own refinement lost 0.1-0.2 AUC@5 (validation, hard set)
    "poselib": RobustEstimator(min_threshold_px=1.0, refines_pose=True),
    "ransac": RobustEstimator(),
}


def _magsac_params(threshold: float, confidence: float, max_iters: int, seed: int, prosac: bool = False) -> cv2.UsacParams:
    """OpenCV's USAC_MAGSAC preset spelled out, so that its random generator can be seeded.

    The ``cv2.USAC_MAGSAC`` flag always starts USAC's generator from the same state
    (``cv2.setRNGSeed`` does not reach it); these parameters give the same estimate at seed 0.
    """
    p = cv2.UsacParams()
    p.sampler, p.score = cv2.SAMPLING_PROSAC if prosac else cv2.SAMPLING_UNIFORM, cv2.SCORE_METHOD_MAGSAC
    p.loMethod, p.loIterations, p.loSampleSize = cv2.LOCAL_OPTIM_SIGMA, 10, 50
    p.final_polisher, p.final_polisher_iterations = cv2.MAGSAC, 20  # cv2.MAGSAC: the polisher
    p.maxIterations, p.confidence, p.threshold, p.randomGeneratorState = max_iters, confidence, threshold, seed
    return p


def robust_threshold(method: str, px: float, focal: float) -> float:
    """``method``'s inlier threshold in normalised units for a threshold of ``px`` pixels (at least its
    ``min_threshold_px``)."""
    return max(ROBUST_ESTIMATORS[method].min_threshold_px, px) / focal


def _checked_call(x0n: np.ndarray, x1n: np.ndarray, method: str, prosac: bool) -> tuple[np.ndarray, np.ndarray]:
    """The arguments of a robust fit checked first: a bad call fails however few points it has."""
    if method not in ROBUST_ESTIMATORS:
        raise ValueError(f"unknown robust estimator {method!r}; use one of {list(ROBUST_ESTIMATORS)}")
    if prosac and method == "ransac":
        raise ValueError("PROSAC sampling is a MAGSAC++ (USAC) and PoseLib option; use method='magsac' or 'poselib'")
    return _checked_pair(x0n, x1n)


def estimate_essential(x0n: np.ndarray, x1n: np.ndarray, method: str = "magsac", threshold: float = 1e-3,
                       confidence: float = 0.999, max_iters: int = 10000, seed: int = 0,
                       prosac: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
    """Robust E from normalised points: ``magsac`` (OpenCV USAC MAGSAC++), ``poselib`` (PoseLib's LO-RANSAC on the
    five-point solver with its own non-linear refinement) or ``ransac`` (OpenCV's).

    ``threshold`` is in normalised units (pixels / focal length; PoseLib's is a Sampson distance); ``seed`` picks
    the random samples (on hard pairs a different seed can give a different pose); ``prosac``: the points come best
    first (e.g. by a network's score) and MAGSAC++ or PoseLib samples them with PROSAC instead of uniformly.
    Returns (E, inlier mask) or None when there are fewer than 8 correspondences or no model was found.
    """
    x0n, x1n = _checked_call(x0n, x1n, method, prosac)
    if len(x0n) < MIN_MATCHES:
        return None
    if method == "poselib":
        found = _poselib_pose(x0n, x1n, threshold, confidence, max_iters, seed, prosac)
        return None if found is None else (found.E, found.inliers)
    return _opencv_essential(x0n, x1n, method, threshold, confidence, max_iters, seed, prosac)


def _opencv_essential(x0n: np.ndarray, x1n: np.ndarray, method: str, threshold: float, confidence: float,
                      max_iters: int, seed: int, prosac: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """OpenCV's MAGSAC++ or RANSAC on checked points, as (E, inlier mask)."""
    if method == "magsac":
        eye, no_dist = np.eye(3), np.zeros(5)
        E, mask = cv2.findEssentialMat(x0n, x1n, eye, eye, no_dist, no_dist,
                                       _magsac_params(threshold, confidence, max_iters, seed, prosac))
    else:
        cv2.setRNGSeed(seed)
        E, mask = cv2.findEssentialMat(x0n, x1n, np.eye(3), method=cv2.RANSAC, prob=confidence,
                                       threshold=threshold, maxIters=max_iters)
    if E is None or E.shape[0] < 3 or mask is None:
        return None
    return E[:3], mask.ravel().astype(bool)  # several stacked solutions: the first is the best


def estimate_pose(x0n: np.ndarray, x1n: np.ndarray, method: str = "magsac", threshold: float = 1e-3,
                  confidence: float = 0.999, max_iters: int = 10000, seed: int = 0,
                  prosac: bool = False) -> tuple[PoseEstimate | None, np.ndarray] | None:
    """``estimate_essential``'s fit as a pose: (pose, the estimator's inlier mask), or None where it found no model.

    PoseLib's pose is taken as it comes (it checks cheirality itself); the E of the others is decomposed by
    ``recover_pose``, whose pose is None where no solution has the points in front of both cameras.
    """
    x0n, x1n = _checked_call(x0n, x1n, method, prosac)
    if len(x0n) < MIN_MATCHES:
        return None
    if method == "poselib":
        found = _poselib_pose(x0n, x1n, threshold, confidence, max_iters, seed, prosac)
        return None if found is None else (found, found.inliers)
    est = _opencv_essential(x0n, x1n, method, threshold, confidence, max_iters, seed, prosac)
    return None if est is None else (recover_pose(est[0], x0n, x1n, est[1]), est[1])


def _poselib_pose(x0n: np.ndarray, x1n: np.ndarray, threshold: float, confidence: float, max_iters: int,
                  seed: int, prosac: bool) -> PoseEstimate | None:
    """PoseLib's relative pose on normalised points (a unit pinhole camera); inliers: PoseLib's."""
    camera = {"model": "PINHOLE", "width": 1, "height": 1, "params": [1.0, 1.0, 0.0, 0.0]}
    ransac = {"max_epipolar_error": threshold, "success_prob": confidence, "max_iterations": max_iters,
              "min_iterations": min(POSELIB_MIN_ITERATIONS, max_iters), "seed": seed, "progressive_sampling": prosac,
              "max_prosac_iterations": max_iters}
    pose, info = poselib.estimate_relative_pose(x0n, x1n, camera, camera, ransac, {})
    t = np.asarray(pose.t, np.float64)
    if info["num_inliers"] < 5 or not np.isfinite(t).all() or np.linalg.norm(t) < 1e-12:
        return None
    t = t / np.linalg.norm(t)
    R = np.array(pose.R, np.float64)
    return PoseEstimate(R=R, t=t, E=skew(t) @ R, inliers=np.asarray(info["inliers"], bool))


def eight_point_rows(x0: ArrayT, y0: ArrayT, x1: ArrayT, y1: ArrayT, xp: ModuleType = np) -> ArrayT:
    """Rows of x1^T E x0 = 0 as linear equations in E's nine entries (row-major), one per correspondence.

    Array-module generic (``xp``: numpy, or torch where the loss needs gradients), so the eight-point's
    design matrix is written once.
    """
    return xp.stack([x1 * x0, x1 * y0, x1, y1 * x0, y1 * y0, y1, x0, y0, xp.ones_like(x0)], -1)


def weighted_eight_point(x0n: np.ndarray, x1n: np.ndarray, weights: np.ndarray) -> np.ndarray | None:
    """Essential matrix minimising the weighted algebraic epipolar error (as in Yi et al. 2018).

    Used with network scores as weights; returns None when fewer than 8 weights are positive.
    """
    x0n, x1n = _checked_pair(x0n, x1n)
    w = np.clip(np.asarray(weights, np.float64).ravel(), 0, None)
    if len(w) != len(x0n):
        raise ValueError(f"weights length {len(w)} does not match {len(x0n)} correspondences")
    if np.count_nonzero(w > 1e-6) < MIN_MATCHES:
        return None
    X = eight_point_rows(x0n[:, 0], x0n[:, 1], x1n[:, 0], x1n[:, 1])
    XwX = X.T @ (X * w[:, None])
    _, vecs = np.linalg.eigh(XwX)
    E = vecs[:, 0].reshape(3, 3)
    U, _, Vt = np.linalg.svd(E)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


CHEIRALITY_DEPTH = 1e4  # baselines: a point triangulated farther away does not vote in the cheirality check


def recover_pose(E: np.ndarray, x0n: np.ndarray, x1n: np.ndarray, mask: np.ndarray | None = None) -> PoseEstimate | None:
    """R, t from E by the cheirality check (OpenCV recoverPose) over the masked points.

    OpenCV's recoverPose without a distance lets only points within 50 baselines vote: a camera creeping before a
    distant scene (KITTI-07's first frames, 9 cm apart; a robot at walking pace at 30 Hz, 1-2 cm) had none or a
    handful to decide between the four solutions, and failed. Here every point within CHEIRALITY_DEPTH votes.
    """
    x0n, x1n = _checked_pair(x0n, x1n)
    if E is None or len(x0n) < 5:
        return None
    if mask is not None and len(mask) != len(x0n):
        raise ValueError(f"mask length {len(mask)} does not match {len(x0n)} correspondences")
    # only the masked points: the others never count, but OpenCV triangulates all it is given
    idx = np.arange(len(x0n)) if mask is None else np.flatnonzero(mask)
    if len(idx) < 5:
        return None
    n, R, t, m_out, _ = cv2.recoverPose(E, x0n[idx], x1n[idx], np.eye(3), distanceThresh=CHEIRALITY_DEPTH)
    if n == 0:
        return None
    inliers = np.zeros(len(x0n), bool)
    inliers[idx] = m_out.ravel() > 0
    return PoseEstimate(R=R, t=t.ravel() / max(np.linalg.norm(t), 1e-12), E=E, inliers=inliers)


def _pose_jacobian_basis(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dE/dp for the 5 pose parameters (3 rotation, 2 on the unit sphere of t), and the sphere basis."""
    B = np.linalg.svd(t[None])[2][1:]  # (2,3) orthonormal, perpendicular to t
    tx = skew(t)
    dE = [tx @ R @ skew(e) for e in np.eye(3)] + [skew(b) @ R for b in B]
    return np.stack(dE), B


def _sampson(E: np.ndarray, h0: np.ndarray, h1: np.ndarray, dE: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray | None]:
    """Signed Sampson residuals of homogeneous normalised points, and their (P,N) derivatives for dE."""
    v0, v1 = h0 @ E.T, h1 @ E
    a = np.sum(h1 * v0, axis=1)
    d = v0[:, 0] ** 2 + v0[:, 1] ** 2 + v1[:, 0] ** 2 + v1[:, 1] ** 2 + 1e-30
    r = a / np.sqrt(d)
    if dE is None:
        return r, None
    dv0 = h0 @ dE.transpose(0, 2, 1)  # (P,N,3): dE x0 per parameter
    dv1 = h1 @ dE  # dE^T x1
    da = np.sum(h1[None] * dv0, axis=2)
    dd = 2.0 * (v0[:, 0] * dv0[..., 0] + v0[:, 1] * dv0[..., 1] + v1[:, 0] * dv1[..., 0] + v1[:, 1] * dv1[..., 1])
    return r, da / np.sqrt(d) - 0.5 * a * dd / d ** 1.5


def sampson_distance(E: np.ndarray, x0n: np.ndarray, x1n: np.ndarray) -> np.ndarray:
    """Sampson distance of every correspondence to E (normalised units; x focal length = pixels)."""
    x0n, x1n = _checked_pair(x0n, x1n)
    return np.abs(_sampson(E, np.c_[x0n, np.ones(len(x0n))], np.c_[x1n, np.ones(len(x1n))])[0])


def sampson_px(pose: PoseEstimate, x0n: np.ndarray, x1n: np.ndarray, focal: float) -> np.ndarray:
    """Sampson distance of every correspondence (normalised) to ``pose``'s epipolar geometry, in pixels."""
    return sampson_distance(essential_from_pose(pose.R, pose.t), x0n, x1n) * focal


def refine_pose(pose: PoseEstimate, x0n: np.ndarray, x1n: np.ndarray, sigma: float,
                iterations: int = 5) -> PoseEstimate:
    """Polish (R, t) by Levenberg-Marquardt on the Cauchy-robust Sampson error over all given matches.

    A robust estimator's answer comes from its best minimal sample and local optimisation on the
    inliers of one threshold; a smooth robust cost over every candidate match (``sigma`` in
    normalised units, e.g. the inlier threshold) weighs each by how well it fits; measured +0.5 to
    +3.5 pose AUC@5 on the validation pairs. Only steps that lower the cost are taken,
    so the result is never worse than the input by that cost; a degenerate system (NaN input, a
    singular step) returns the best pose so far. Mask and inliers are kept.
    """
    x0n, x1n = _checked_pair(x0n, x1n)
    if len(x0n) < MIN_MATCHES or iterations <= 0 or sigma <= 0:
        return pose
    h0, h1 = np.c_[x0n, np.ones(len(x0n))], np.c_[x1n, np.ones(len(x1n))]
    R, t = np.asarray(pose.R, np.float64), np.ravel(pose.t).astype(np.float64)
    t = t / max(np.linalg.norm(t), 1e-12)
    s2 = sigma * sigma

    def cost(E: np.ndarray) -> float:
        return float(np.sum(np.log1p(_sampson(E, h0, h1)[0] ** 2 / s2)))

    E = skew(t) @ R
    current = cost(E)
    if not np.isfinite(current):
        return pose
    lam = 1e-3
    for _ in range(iterations):
        dE, B = _pose_jacobian_basis(R, t)
        r, J = _sampson(E, h0, h1, dE)
        w = 1.0 / (s2 + r * r)  # IRLS weight of the Cauchy loss
        H = (J * w) @ J.T
        g = (J * w) @ r
        improved = False
        while lam < 1e8:
            try:
                step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), -g)
            except np.linalg.LinAlgError:
                break
            R_new = R @ cv2.Rodrigues(step[:3])[0]
            t_new = t + B.T @ step[3:]
            t_new /= np.linalg.norm(t_new)
            E_new = skew(t_new) @ R_new
            c = cost(E_new)
            if c < current:
                R, t, E, current, lam, improved = R_new, t_new, E_new, c, max(lam / 10, 1e-7), True
                break
            lam *= 10
        if not improved or np.linalg.norm(step) < 1e-10:
            break
    return PoseEstimate(R=R, t=t.reshape(np.shape(pose.t)), E=E, inliers=pose.inliers)


def fit_rotation(x0n: np.ndarray, x1n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation alone that best maps the matches' viewing rays (x1 ~ R x0, no translation) and each match's
    angle (radians) off it: the parallax a translation leaves once the rotation is taken out.

    For a camera that turns without measurably moving, where the essential matrix is undefined (it is [t]x R
    with t = 0). Orthogonal Procrustes (Kabsch) on the unit rays, fitted again without the matches beyond three
    times the median angle until that set settles, so that mismatches do not tilt it.
    """
    x0n, x1n = _checked_pair(x0n, x1n)
    b0, b1 = (np.c_[x, np.ones(len(x))] for x in (x0n, x1n))
    b0, b1 = b0 / np.linalg.norm(b0, axis=1, keepdims=True), b1 / np.linalg.norm(b1, axis=1, keepdims=True)

    def kabsch(keep: np.ndarray) -> np.ndarray:
        U, _, Vt = np.linalg.svd(b1[keep].T @ b0[keep])
        return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt

    def angles(R: np.ndarray) -> np.ndarray:
        return np.arccos(np.clip(np.einsum("ij,ij->i", b1, b0 @ R.T), -1.0, 1.0))

    keep = np.ones(len(b0), bool)
    for _ in range(4):  # the kept set settles in one or two rounds
        R = kabsch(keep)
        a = angles(R)
        keep, kept = a <= 3.0 * np.median(a) + 1e-12, keep
        if np.array_equal(keep, kept):
            break
    return R, a


def rotation_error_deg(R: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle of R R_gt^T in degrees."""
    c = (np.trace(R @ R_gt.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def direction_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two translation directions in degrees, signs counted (0 .. 180)."""
    a, b = np.ravel(a), np.ravel(b)
    c = float(np.dot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def translation_error_deg(t: np.ndarray, t_gt: np.ndarray) -> float:
    """Angle between translation directions, sign-agnostic: min(e, 180 - e)."""
    if np.linalg.norm(t) * np.linalg.norm(t_gt) < 1e-12:
        return 180.0 if np.linalg.norm(t_gt) > 1e-12 else 0.0
    e = direction_angle_deg(t, t_gt)
    return min(e, 180.0 - e)


def pose_error_deg(pose: PoseEstimate | None, R_gt: np.ndarray, t_gt: np.ndarray) -> tuple[float, float]:
    """(rotation, translation) errors in degrees; a failed estimate counts as 180 each."""
    if pose is None:
        return 180.0, 180.0
    return rotation_error_deg(pose.R, R_gt), translation_error_deg(pose.t, t_gt)


def pose_auc(errors: np.ndarray, thresholds: tuple[float, ...] = (5.0, 10.0, 20.0)) -> list[float]:
    """Area under the recall-vs-error curve up to each threshold, in [0, 1] (SuperGlue's trapezoid)."""
    errors = np.sort(np.asarray(errors, np.float64).ravel())
    if errors.size == 0:
        return [0.0 for _ in thresholds]
    recall = (np.arange(len(errors)) + 1) / len(errors)
    errors = np.r_[0.0, errors]
    recall = np.r_[0.0, recall]
    aucs = []
    for th in thresholds:
        last = np.searchsorted(errors, th)
        r = np.r_[recall[:last], recall[last - 1]]
        e = np.r_[errors[:last], th]
        aucs.append(float(np.trapezoid(r, x=e) / th))
    return aucs


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """(qx, qy, qz, qw) -> 3x3 rotation matrix; (..., 4) -> (..., 3, 3)."""
    q = np.asarray(q, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):  # a zero quaternion gives NaN: the caller's to refuse
        x, y, z, w = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)
