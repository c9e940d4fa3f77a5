"""Scoring a pass over a recording against its ground truth, pair by pair: what the offline replay and the live
scoring report alike (rotation and translation-direction errors, pose AUC, pairs without motion, the pose sigmas
that fit the errors), and what a pass keeps of each frame (:class:`Run`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.geometry import PoseEstimate, pose_auc, pose_error_deg, relative_pose, rotation_error_deg
from ..core.pipeline import RESTARTS, FrameResult
from ..core.tracks import TrackLengths
from ..interface.posemsg import SIGMAS, relative_pose_of_current, widened
from ..io.trajectory import Trajectory

STATIC_GT_M = 0.01  # ground-truth motion below this (in GT units) is a static pair
CHI2_MEDIAN = {2: 1.386294, 3: 2.365974}  # the median of a chi-square with 2 and 3 degrees of freedom
CHI2_999 = {2: 13.815511, 3: 16.266236}  # and its 99.9 % quantile


def _gt_step(status: str, T_prev: np.ndarray | None, T_cur: np.ndarray | None
             ) -> tuple[np.ndarray, np.ndarray, bool] | None:
    """The ground truth's (R, t) over a pair and whether it moved (over STATIC_GT_M); None when the pair cannot be
    scored (a pose missing, a restart of the chain)."""
    if T_prev is None or T_cur is None or status in RESTARTS:
        return None
    R, t = relative_pose(T_prev, T_cur)
    return R, t, bool(np.linalg.norm(t) > STATIC_GT_M)


def frame_error(status: str, pose: PoseEstimate | None, T_prev: np.ndarray | None, T_cur: np.ndarray | None
                ) -> tuple[float, float] | None:
    """(rot, trans) error of one frame's result (a FrameResult's status and pose, or what a recorded
    relative_pose says: ``no_estimate`` too); failures count as 180; None when not scorable."""
    step = _gt_step(status, T_prev, T_cur)
    return None if step is None else _step_error(status, pose, *step)


def _step_error(status: str, pose: PoseEstimate | None, R: np.ndarray, t: np.ndarray, moving: bool
                ) -> tuple[float, float] | None:
    """:func:`frame_error` against the ground truth's step (R, t, moving) over the pair."""
    if status == "no_motion":
        return None if not moving else (180.0, 180.0)
    if status != "ok" or pose is None:
        return (180.0, 180.0)
    if not moving:
        return None
    return pose_error_deg(pose, R, t)


def normalised_errors(rot_deg: float, pose: PoseEstimate, R: np.ndarray, t: np.ndarray, cov: np.ndarray
                      ) -> tuple[float, float]:
    """An estimate's squared errors over the variances its relative_pose message publishes (``cov``, 6x6: x y z
    roll pitch yaw): its rotation error ``rot_deg`` (radians) over the rotation's variance per axis, and the chord
    between the published and the true translation directions over the direction's (signed: a reversed direction
    is an error here, unlike in :func:`~nmnet_ros.core.geometry.translation_error_deg`). (R, t): the ground
    truth's step."""
    t_est, t_true = -pose.R.T @ pose.t, -R.T @ t  # T_prev_cur's translations, as published
    chord = np.linalg.norm(t_est / max(np.linalg.norm(t_est), 1e-12) - t_true / np.linalg.norm(t_true))
    return float(np.radians(rot_deg) ** 2 / cov[3, 3]), float(chord**2 / cov[0, 0])


def fitted_sigmas(normalised: list[tuple[float, float]], sigmas: tuple[float, float]) -> dict:
    """The pose_sigma_rotation_deg and pose_sigma_direction at which the published covariance fits the errors that
    ``normalised`` (:func:`normalised_errors`) holds, the covariance having been published with ``sigmas``; None
    without estimates. The rotation's error spreads over 3 axes, the direction's over the 2 across it."""
    if not normalised:
        return {"fitted_pose_sigma_rotation_deg": None, "fitted_pose_sigma_direction": None}
    z = np.asarray(normalised)
    return {"fitted_pose_sigma_rotation_deg": sigmas[0] * _gaussian_sigma(z[:, 0], 3),
            "fitted_pose_sigma_direction": sigmas[1] * _gaussian_sigma(z[:, 1], 2)}


def _gaussian_sigma(z: np.ndarray, dof: int) -> float:
    """The sigma of the Gaussian whose squared errors over ``dof`` axes (chi-square times sigma^2) ``z`` holds, beside
    gross failures, which no Gaussian describes: fitted to the median, then again to the errors below the 99.9 %
    quantile of the fit, until none leaves (the median alone is pulled up by failures: by 15 % where a fifth fail).
    Where half or more fail, the median is a failure's and so is the fit."""
    kept = z
    for _ in range(10):
        var = float(np.median(kept)) / CHI2_MEDIAN[dof]
        if len(inside := z[z <= CHI2_999[dof] * var]) == len(kept):
            break
        kept = inside
    return float(np.sqrt(var))


class PairScores:
    """A pass's scores against ground truth, pair by pair, as the offline replay and the live scoring collect them:
    the (rotation, translation) errors of :func:`frame_error` (failures included, at 180) with their frames'
    stamps, the rotation errors of the estimates over pairs whose ground truth did not move (standing, or
    turning on the spot), which have no direction to score, and each estimate's errors against the covariance it
    was published with (:func:`normalised_errors`).

    ``sigmas``: the pose_sigma_rotation_deg and pose_sigma_direction the covariances were published with."""

    def __init__(self, sigmas: tuple[float, float] = SIGMAS) -> None:
        self.sigmas = sigmas
        self.errors: list[tuple[float, float]] = []
        self.stamps: list[float] = []
        self.still: list[float] = []
        self.normalised: list[tuple[float, float]] = []

    def add(self, status: str, pose: PoseEstimate | None, T_prev: np.ndarray | None, T_cur: np.ndarray | None,
            stamp: float, cov: np.ndarray | None = None) -> None:
        """Score the pair that ends at the frame stamped ``stamp``; ``cov``: the covariance its relative_pose
        message carries (6x6), to check against the errors (where it was not widened to a plane's second pose,
        which does not scale with the sigmas)."""
        if (step := _gt_step(status, T_prev, T_cur)) is None:
            return
        if (err := _step_error(status, pose, *step)) is not None:
            self.errors.append(err)
            self.stamps.append(stamp)
            if status == "ok" and pose is not None and cov is not None and not widened(cov, self.sigmas):
                self.normalised.append(normalised_errors(err[0], pose, step[0], step[1], cov))
        elif pose is not None and not step[2]:
            self.still.append(rotation_error_deg(pose.R, step[0]))

    def summary(self) -> dict:
        """What the offline replay and the live scoring report alike: the median rotation / translation errors, pose
        AUC@5/10/20 (percent) and the count of the pairs scored, the median rotation error of the still pairs and
        the :func:`fitted_sigmas`."""
        e = np.array(self.errors) if self.errors else np.zeros((0, 2))
        aucs = pose_auc(e.max(1)) if len(e) else [float("nan")] * 3
        return {"median_rot_deg": float(np.median(e[:, 0])) if len(e) else None,
                "median_trans_deg": float(np.median(e[:, 1])) if len(e) else None,
                "auc5": 100 * aucs[0], "auc10": 100 * aucs[1], "auc20": 100 * aucs[2], "scored_pairs": len(e),
                "still_pairs": len(self.still),
                "median_still_rot_deg": float(np.median(self.still)) if self.still else None,
                **fitted_sigmas(self.normalised, self.sigmas)}


def truth_missed(truth: Trajectory | None, stamps: list[float]) -> str | None:
    """What to say when the ground truth has a pose for none of the frames (stamped on another clock, or of another
    recording), instead of a summary that silently scores nothing."""
    if truth is None or not stamps or np.isfinite(truth.poses_at(np.asarray(stamps))[:, 0, 0]).any():
        return None
    return (f"the ground truth has no pose at any frame's stamp (poses {truth.stamps[0]:.3f} .. "
            f"{truth.stamps[-1]:.3f} s, frames {min(stamps):.3f} .. {max(stamps):.3f} s): nothing is scored; the two "
            "must be stamped on the same clock")


def truth_uncovered(stamps: list[float], posed: list[bool], per_frame: bool | None) -> str | None:
    """What to say when the ground truth has a pose for some of the frames but not all (None: all, or none, which
    :func:`truth_missed` says): the pairs with the others are not scored. ``per_frame``: the ground truth is a pose
    per frame (:class:`~nmnet_ros.io.trajectory.FrameTruth`), which gives a frame without its own none."""
    missing = [t for t, p in zip(stamps, posed, strict=True) if not p]
    if not missing or len(missing) == len(stamps):
        return None
    why = ("its poses are the frames' own, and these have none" if per_frame else
           "none close enough to their stamps to take or interpolate")
    listed = ", ".join(f"{t:.3f}" for t in missing[:5]) + (", ..." if len(missing) > 5 else "")
    return (f"the ground truth has no pose for {len(missing)} of {len(stamps)} frames ({why}; at {listed} s): "
            "the pairs with them are not scored")


@dataclass
class Step:
    """What a pass keeps of a frame: its counts and pose, not its matches (58 KB a frame at 2000 keypoints: an
    hour-long bag's would fill the memory; they are in the output file)."""

    stamp: float
    status: str
    matches: int
    selected: int
    R: np.ndarray | None  # the pose, x_cur = R x_prev + t, where the frame has one
    t: np.ndarray | None
    T: np.ndarray | None  # the ground truth's camera pose at the frame's stamp, where it has one


class Run:
    """Everything one pass over the frames collects, a few hundred bytes a frame."""

    def __init__(self, name: str, sigmas: tuple[float, float] = SIGMAS) -> None:
        """``sigmas``: the relative poses' covariance, as the node's pose_sigma_* parameters."""
        self.name = name
        self.warnings: dict[str, int] = {}  # per kind, as :class:`Notes` counted them
        self.recording_warnings: list[str] = []  # about the recording as a whole: damaged, ground truth missing
        self.steps: list[Step] = []
        self.scores = PairScores(sigmas)
        self.tracks = TrackLengths()
        self.seconds = 0.0

    def add(self, r: FrameResult, T: np.ndarray | None) -> None:
        """One more frame's result ``r``, with the ground truth's pose ``T`` at its stamp (None: none there)."""
        cov = None if T is None else relative_pose_of_current(r.status, r.pose, r.pose_matches, self.scores.sigmas)[2]
        self.scores.add(r.status, r.pose, self.steps[-1].T if self.steps else None, T, r.stamp, cov)
        self.tracks.add(r.track_ids[r.mask])
        R, t = (r.pose.R, r.pose.t) if r.pose else (None, None)
        self.steps.append(Step(r.stamp, r.status, len(r.k0), r.num_selected, R, t, T))

    def summary(self, frames: int, dropped: int = 0) -> dict:
        """The summary JSON: counts, rate, median errors, pose AUCs, selections per frame, statuses."""
        related = [s for s in self.steps if s.status not in RESTARTS]
        statuses: dict[str, int] = {}
        for s in self.steps:
            statuses[s.status] = statuses.get(s.status, 0) + 1
        return {
            "frames": frames, "processed": len(self.steps), "dropped": dropped,
            "fps": len(self.steps) / self.seconds if self.seconds else 0.0, **self.scores.summary(),
            "matches_per_frame": float(np.mean([s.matches for s in related])) if related else 0.0,
            "selected_per_frame": float(np.mean([s.selected for s in related])) if related else 0.0,
            "status": statuses, "warnings": dict(self.warnings), "recording_warnings": list(self.recording_warnings),
            "tracks": self.tracks.summary(),
        }
