"""The text tables every dataset layout shares, and ground-truth trajectories.

Whitespace-separated tables read line by line (a malformed line is named by file and line), timestamps that a
ROS time can hold, TUM trajectories ('timestamp tx ty tz qx qy qz qw') and :class:`Trajectory`, the poses of a
recording looked up by stamp.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from ..core.geometry import quat_to_rot

Row = TypeVar("Row")  # what a table row converts to


class DatasetError(ValueError):
    """A sequence folder is missing a file or has a malformed one."""


def read_table(path: Path, columns: str, convert: Callable[[list[str]], Row], maxsplit: int = -1,
                sep: str | None = None) -> list[Row]:
    """The rows of a whitespace-separated (or ``sep``-separated) text file (blank and '#' lines skipped), each
    converted.

    ``maxsplit`` keeps the last column whole (a path with spaces in 'timestamp path').

    ``convert`` raises ValueError (or IndexError) on a malformed row; the DatasetError then names the
    file, the line and the ``columns`` it should have.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: missing; expected lines '{columns}'")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if line.strip() and not line.lstrip().startswith("#"):
            try:
                rows.append(convert(line.split(sep, maxsplit)))
            except Unfit as e:
                raise DatasetError(f"{path}:{n}: {e} in '{columns}', got {line.strip()!r}") from e
            except (ValueError, IndexError) as e:
                hint = _layout_hint(line) if sep is None else ""
                raise DatasetError(f"{path}:{n}: expected '{columns}', got {line.strip()!r}{hint}") from e
    return rows


def _layout_hint(line: str) -> str:
    """What another common trajectory layout a malformed line is in, and how to convert it ('' if none)."""
    if "," in line:
        return ("; the columns are separated by commas: this reads whitespace-separated text (for EuRoC's "
                "state_groundtruth_estimate0/data.csv, nanoseconds and qw first: `evo_traj euroc data.csv "
                "--save_as_tum` writes the TUM file)")
    if len(line.split()) == 12:
        return ("; 12 numbers: a KITTI poses file (a 3x4 camera-to-world matrix a line, no time): evo's "
                "contrib/kitti_poses_and_timestamps_to_trajectory.py POSES times.txt OUT writes it as TUM lines "
                "with the sequence's times.txt; or give the KITTI sequence folder (sequences/NN) itself, which is read "
                "with its poses/NN.txt")
    return ""


class Unfit(ValueError):
    """A row of the right form whose values cannot be right; says why."""


def floats(n: int) -> Callable[[list[str]], list[float]]:
    """A row converter: exactly ``n`` numbers."""
    def convert(fields: list[str]) -> list[float]:
        if len(fields) != n:
            raise ValueError(f"{len(fields)} fields")
        return [float(f) for f in fields]
    return convert


MAX_ROS_SECONDS = 2**31 - 1  # builtin_interfaces/Time's sec is an int32 (ROS 1's a uint32): 2038-01-19


def ros_seconds(text: str) -> float:
    """A frame's timestamp in seconds, finite and not negative (ROS time starts at 0); Unfit otherwise (read_table
    then names the file and the line), as a bag cannot record it. The upper bound is checked after
    :func:`check_seconds`, which says when the stamps are nanoseconds: :func:`check_ros_time`."""
    t = float(text)
    if not 0 <= t < float("inf"):  # NaN fails too
        raise Unfit(f"timestamp {text} is no ROS time (seconds from 0 to {MAX_ROS_SECONDS}, finite)")
    return t


def check_ros_time(path: Path, stamps: np.ndarray) -> None:
    """Refuse stamps past :data:`MAX_ROS_SECONDS`, naming the line of ``path`` (rows as read_table reads them)."""
    if (late := np.flatnonzero(stamps > MAX_ROS_SECONDS)).size:
        rows = [(n, line.split()[0]) for n, line in enumerate(path.read_text().splitlines(), 1)
                if line.strip() and not line.lstrip().startswith("#")]
        n, text = rows[late[0]]
        raise DatasetError(f"{path}:{n}: timestamp {text} is no ROS time (seconds from 0 to {MAX_ROS_SECONDS}, finite)")


def pose_problem(xyzq: list[float]) -> str | None:
    """What makes 'x y z qx qy qz qw' no pose (None: nothing). NaN poses and zero quaternions are how some
    exporters write a lost track: refused, not turned into pairs that silently drop out."""
    if not np.all(np.isfinite(xyzq)):
        return "a value that is not a finite number"
    if np.linalg.norm(xyzq[3:]) < 1e-9:
        return "a zero quaternion (qx qy qz qw all 0)"
    return None


def _pose_row(fields: list[str]) -> list[float]:
    """A TUM row converter: a stamp and a pose (:func:`pose_problem`)."""
    row = floats(8)(fields)
    why = pose_problem(row[1:]) if np.isfinite(row[0]) else "a stamp that is not a finite number"
    if why is not None:
        raise Unfit(why)
    return row


MAX_SPACING_S = 1e5  # a day between ground-truth poses or frames: stamps in ns (1e8 at 10 Hz), not seconds


def check_seconds(path: Path, stamps: np.ndarray, what: str) -> None:
    """Refuse a file whose stamps are nanoseconds (as ROS tools write them), which read as seconds put days between
    its rows, naming the conversion."""
    steps = np.diff(np.sort(stamps))
    if (steps > 0).any() and (gap := float(np.median(steps[steps > 0]))) > MAX_SPACING_S:
        raise DatasetError(f"{path}: {what} a median of {gap:.3g} s apart: the stamps look like nanoseconds (as ROS "
                           "tools write them); the first column is seconds: divide it by 1e9, e.g. "
                           "awk '!/^#/{$1 = sprintf(\"%.9f\", $1 / 1e9)} 1' in.txt > out.txt")


def read_tum(path: Path) -> Trajectory:
    """TUM trajectory file ('timestamp tx ty tz qx qy qz qw' lines, T_WC) -> :class:`Trajectory`."""
    rows = read_table(path, "timestamp tx ty tz qx qy qz qw", _pose_row)
    if not rows:
        raise DatasetError(f"{path}: no poses; expected lines 'timestamp tx ty tz qx qy qz qw'")
    a = np.array(rows, np.float64)
    check_seconds(path, a[:, 0], "poses")
    return Trajectory(a[:, 0], poses_from_xyzq(a[:, 1:8]))


def poses_from_xyzq(xyzq: np.ndarray) -> np.ndarray:
    """(N, 7) rows 'x y z qx qy qz qw' -> (N, 4, 4) poses."""
    T = np.tile(np.eye(4), (len(xyzq), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = quat_to_rot(xyzq[:, 3:7]), xyzq[:, :3]
    return T


def parse_pose(text: str) -> np.ndarray:
    """'x y z qx qy qz qw' (TUM's order, as ``static_transform_publisher`` takes it) -> 4x4; ValueError saying what is
    wrong."""
    try:
        v = [float(f) for f in text.replace(",", " ").split()]
    except ValueError:
        v = []
    if len(v) != 7 or pose_problem(v) is not None:
        raise ValueError(f"{text!r}: expected 'x y z qx qy qz qw', seven numbers with a non-zero quaternion")
    return poses_from_xyzq(np.array([v], np.float64))[0]


STAMP_TOLERANCE_S = 1e-6  # a pose "at" a frame's stamp: the same time, as seconds from the same nanoseconds


def nearest_index(sorted_stamps: np.ndarray, stamps: np.ndarray | float) -> np.ndarray:
    """Index of the one of ``sorted_stamps`` (ascending, not empty) nearest in time to each stamp (the earlier one on a
    tie)."""
    s = np.atleast_1d(np.asarray(stamps, np.float64))
    after = np.searchsorted(sorted_stamps, s).clip(0, len(sorted_stamps) - 1)
    before = (after - 1).clip(0)
    return np.where(np.abs(sorted_stamps[before] - s) <= np.abs(sorted_stamps[after] - s), before, after)


def _at_one_of(sorted_stamps: np.ndarray, stamps: np.ndarray) -> np.ndarray:
    """Per stamp, whether one of ``sorted_stamps`` is at it (:data:`STAMP_TOLERANCE_S`)."""
    return np.abs(sorted_stamps[nearest_index(sorted_stamps, stamps)] - stamps) <= STAMP_TOLERANCE_S


@dataclass
class Trajectory:
    """Ground-truth poses in time order, looked up by stamp (sorted and spaced once, not per frame)."""

    stamps: np.ndarray  # (N,) seconds, ascending
    poses: np.ndarray  # (N,4,4) T_WC
    spacing: float = field(init=False)  # median time between poses (0 for one pose)

    def __post_init__(self) -> None:
        order = np.argsort(self.stamps, kind="stable")
        self.stamps, self.poses = self.stamps[order], self.poses[order]
        self.spacing = float(np.median(np.diff(self.stamps))) if len(self.stamps) > 1 else 0.0

    def finite(self) -> tuple[Trajectory | None, int]:
        """The poses that are finite numbers (a lost track is often published as NaN, or as a zero quaternion, which
        turns into NaN) and how many were not; None when none is. What they leave is a gap, as :meth:`poses_at` sees one."""
        ok = np.isfinite(self.stamps) & np.isfinite(self.poses).all(axis=(1, 2))
        if ok.all():
            return self, 0
        return (Trajectory(self.stamps[ok], self.poses[ok]) if ok.any() else None), int((~ok).sum())

    def nearest(self, stamps: np.ndarray | float) -> np.ndarray:
        """Index of the pose nearest in time to each stamp (the earlier one on a tie)."""
        return nearest_index(self.stamps, stamps)

    def lookup(self, stamps: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Per stamp, the nearest pose's index and whether it lies within half the spacing: a frame before, after
        or in a gap of the ground truth has no pose, rather than one of another time."""
        s = np.atleast_1d(np.asarray(stamps, np.float64))
        i = self.nearest(s)
        return i, np.abs(self.stamps[i] - s) <= 0.5 * self.spacing + 1e-6

    def poses_at(self, stamps: np.ndarray | float) -> np.ndarray:
        """The pose at each stamp (N,4,4), NaN where there is none. Between two poses at most 1.5 spacings apart it
        is interpolated (rotation along the shortest arc, translation on the line): a motion-capture stream at its own
        rate and stamps, sampled between its poses. The nearest pose of a 100 Hz stream can be 5 ms off (at 30 deg/s,
        0.15 deg, five times the front end's median error), and a pair's relative pose then errs by the motion in the
        difference of its two frames' offsets, which varies unless the two clocks run in step. Elsewhere (before the
        first pose, after the last, in a gap of the stream) the nearest pose within half the spacing (:meth:`lookup`),
        else none, not one of another time."""
        s = np.atleast_1d(np.asarray(stamps, np.float64))
        i, ok = self.lookup(s)
        out = np.full((len(s), 4, 4), np.nan)
        out[ok] = self.poses[i[ok]]
        after = np.searchsorted(self.stamps, s)  # the first pose at or after each stamp
        for n in np.flatnonzero((after > 0) & (after < len(self.stamps))):
            a, b = after[n] - 1, after[n]
            gap = self.stamps[b] - self.stamps[a]
            if s[n] != self.stamps[b] and 0 < gap <= 1.5 * self.spacing:  # a pose at the stamp itself is taken as is
                out[n] = between(self.poses[a], self.poses[b], (s[n] - self.stamps[a]) / gap)
        return out

    def moved(self, T: np.ndarray) -> Trajectory:
        """The trajectory of a frame fixed to the tracked one at pose ``T`` in it (each pose times T): the camera's,
        from a tracked body's and the camera's place on it."""
        return Trajectory(self.stamps, self.poses @ T)

    def at_frames(self, stamps: np.ndarray) -> tuple[np.ndarray, bool]:
        """The pose at each frame's stamp (N,4,4; NaN where none) and whether the ground truth is a pose per frame: every
        pose within the frames' time span at one of their stamps (the sequence-folder format's). Such ground truth is
        taken at the frames' stamps only: a frame without a line of its own (a keyframe ``nmnet label``'s
        reconstruction could not register, a tracker that lost the camera) has no pose, rather than one interpolated
        between unevenly spaced neighbours. Ground truth at its own rate is :meth:`poses_at`. :class:`FrameTruth` is
        the same rule for frames read one at a time."""
        s = np.asarray(stamps, np.float64)
        poses = self.poses_at(s)
        if not s.size:
            return poses, False
        frames = np.sort(s)
        inside = self.stamps[(self.stamps >= frames[0] - STAMP_TOLERANCE_S) & (self.stamps <= frames[-1] + STAMP_TOLERANCE_S)]
        per_frame = inside.size > 0 and bool(_at_one_of(frames, inside).all())
        if per_frame:
            poses[~_at_one_of(self.stamps, s)] = np.nan
        return poses, per_frame

    def at(self, stamp: float) -> np.ndarray | None:
        """The pose at ``stamp`` (4x4 T_WC, :meth:`poses_at`), or None where there is none."""
        T = self.poses_at(stamp)[0]
        return None if np.isnan(T[0, 0]) else T


class FrameTruth:
    """Ground truth looked up frame by frame, in the order a pass reads the frames (a bag's replay, a folder's images
    in time order).

    While every pose since the first frame is at a frame's stamp (ground truth a pose per frame: the sequence-folder
    format's, and what ``nmnet make-bag`` records), a frame without a pose of its own has none: a keyframe ``nmnet
    label``'s reconstruction could not register is left out, not given a pose interpolated between unevenly spaced
    neighbours. Once a pose lies between two frames (ground truth at its own rate: motion capture) every frame is
    looked up with :meth:`Trajectory.poses_at`; so is a frame before any pose has been passed.
    """

    def __init__(self, truth: Trajectory) -> None:
        self.truth = truth
        self.per_frame: bool | None = None  # None until a pose since the first frame has been passed
        self._next: int | None = None  # the first pose not yet passed (poses before the first frame are not the frames')

    def at(self, stamp: float) -> np.ndarray | None:
        """The pose at the frame's ``stamp`` (4x4 T_WC), or None where there is none."""
        s = self.truth.stamps
        if self._next is None:
            self._next = int(np.searchsorted(s, stamp - STAMP_TOLERANCE_S))
        end = int(np.searchsorted(s, stamp + STAMP_TOLERANCE_S, side="right"))
        own = end > 0 and abs(s[end - 1] - stamp) <= STAMP_TOLERANCE_S  # a pose at this frame's stamp
        if end > self._next:  # poses passed since the frame before: all this frame's, or one lies between frames
            self.per_frame = self.per_frame is not False and bool(np.all(stamp - s[self._next:end] <= STAMP_TOLERANCE_S))
            self._next = end
        return None if self.per_frame and not own else self.truth.at(stamp)


def between(T0: np.ndarray, T1: np.ndarray, w: float) -> np.ndarray:
    """The pose a fraction ``w`` of the way from ``T0`` to ``T1`` (4x4): rotation along the shortest arc, translation
    on the line between them."""
    r, _ = cv2.Rodrigues(T0[:3, :3].T @ T1[:3, :3])
    T = np.eye(4)
    T[:3, :3] = T0[:3, :3] @ cv2.Rodrigues(w * r)[0]
    T[:3, 3] = (1 - w) * T0[:3, 3] + w * T1[:3, 3]
    return T
