"""A plane's second pose: when the matches a pose rests on lie on one plane, two relative poses explain them.

Two views of a plane fit two poses equally well (the twofold ambiguity of the plane's homography; Longuet-Higgins
1986, Malis & Vargas 2007). The five-point solver, MAGSAC++ and the cheirality check then pick one of them by
noise: a camera facing a wall, or a drone over flat ground, got a translation direction 26-84 degrees off in 9 of
12 synthetic planar pairs (a Strecha frame on a plane 5 m away, test/test_planes.py), with nothing to say so.
Here the homography of the pose's inliers is decomposed into the plane's poses; the front end picks the one
nearer the camera's previous motion and publishes a covariance that covers both.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from .geometry import PoseEstimate, direction_angle_deg, essential_from_pose, sampson_px

SUPPORT_PX = 0.5  # a match lies on the plane within this transfer error (pixels)
PLANAR_SHARE = 0.8  # the pose's inliers lie on one plane when at least this share of them does
AMBIGUOUS_SUPPORT = 0.95  # a plane pose explains at least this share of what the robust fit's pose explains
MIN_PARALLAX_PX = 2.0  # a plane solution whose baseline moves points by less than this (focal x |t|/d) is not taken
MIN_INLIERS = 12
PLANE_DRAWS = 100  # homography samples (see plane_poses)
NOTE = ("the matches lie on one plane (a wall, flat ground), which two poses fit as well: published is the one nearer "
        "the previous motion, with a covariance that reaches the other")  # the node's and the replay's warning


def plane_poses(a: np.ndarray, b: np.ndarray, focal: float, px: float = SUPPORT_PX) -> list[PoseEstimate]:
    """The poses of the plane the correspondences ``a`` -> ``b`` (normalised; a pose's inliers) lie on: the
    decomposition of their homography into the solutions that keep PLANAR_SHARE of the points in front of both
    cameras (one or two). Empty when fewer than PLANAR_SHARE of them lie on one plane (within ``px`` pixels,
    ``focal`` in pixels), or when the baseline is too short against the plane's distance to say where the camera
    went."""
    if len(a) < MIN_INLIERS:
        return []
    # at PLANAR_SHARE inliers a 4-point sample is clean 41 % of the time: 100 draws miss a plane with p < 1e-22,
    # and a scene with depth (where the draws find no consensus) costs 100 draws, not the 2000 of the default
    H, on_plane = cv2.findHomography(a, b, cv2.RANSAC, px / focal, maxIters=PLANE_DRAWS)
    if H is None or on_plane.mean() < PLANAR_SHARE:
        return []
    _, rotations, translations, normals = cv2.decomposeHomographyMat(H, np.eye(3))
    h0, h1 = np.c_[a, np.ones(len(a))], np.c_[b, np.ones(len(b))]
    poses = []
    for R, t, n in zip(rotations, translations, normals, strict=True):
        t, n = t.ravel(), n.ravel()  # the plane n.X = 1 in camera 0; |t| = baseline / the plane's distance
        if focal * np.linalg.norm(t) < MIN_PARALLAX_PX or 1.0 + (R @ n) @ t <= 0:  # camera 1 behind the plane
            continue
        in_front = ((h0 @ n > 0) & (h1 @ (R @ n) > 0)).mean()  # the points on the plane in front of both cameras
        if in_front >= PLANAR_SHARE:
            t = t / np.linalg.norm(t)
            poses.append(PoseEstimate(R=R, t=t, E=essential_from_pose(R, t), inliers=np.ones(len(a), bool)))
    return poses


def support(pose: PoseEstimate, a: np.ndarray, b: np.ndarray, focal: float, px: float = SUPPORT_PX) -> int:
    """How many correspondences (normalised) lie within ``px`` Sampson pixels of ``pose``."""
    return int((sampson_px(pose, a, b, focal) < px).sum())


def plane_candidates(pose: PoseEstimate, a: np.ndarray, b: np.ndarray, focal: float) -> list[PoseEstimate]:
    """The plane's poses that explain ``pose``'s inliers (``a``, ``b``, normalised) about as well (AMBIGUOUS_SUPPORT)
    as the best of ``pose`` and them, when they lie on one plane: none (no plane, or matches off it that only ``pose``
    explains: it stands), one (the plane's other pose would put points behind a camera: this one is the pose,
    where the essential matrix's may not be: on synthetic views of a plane MAGSAC++ returned one 92 degrees off that
    every point supported), or two (two views cannot tell them apart)."""
    poses = plane_poses(a, b, focal)
    if not poses:  # the scene has depth (every real pair measured): nothing more to compute
        return []
    counts = [support(p, a, b, focal) for p in poses]
    best = max([support(pose, a, b, focal), *counts])
    return [p for p, n in zip(poses, counts, strict=True) if n >= AMBIGUOUS_SUPPORT * best]


def one_of_a_plane(pose: PoseEstimate, x0n: np.ndarray, x1n: np.ndarray, focal: float,
                   motion: np.ndarray | None) -> PoseEstimate:
    """``pose``, or when its matches (``x0n``, ``x1n``: its inliers, normalised) lie on one plane, the plane's pose
    (:func:`plane_candidates`). Of two, the one whose translation direction is nearer ``motion``
    (the pair before's; None when it had no pose: then the one nearer the robust fit's), with the other as
    ``alternative``: the published covariance covers both."""
    poses = plane_candidates(pose, x0n, x1n, focal)
    if not poses:
        return pose
    near = pose.t if motion is None else motion
    chosen, *other = sorted(poses, key=lambda p: direction_angle_deg(p.t, near))
    return replace(chosen, inliers=pose.inliers,
                   alternative=replace(other[0], inliers=pose.inliers) if other else None)
