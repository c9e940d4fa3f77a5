"""Ground truth in a bag: a pose topic (motion capture, a simulator), or the transforms on /tf that lead from a
world frame to the camera, as a :class:`~.trajectory.Trajectory` the frames are scored against by stamp."""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from .bags import BagError, BagReader, msg_time, pick_topic, several
from .tftree import TfError, TfTree
from .trajectory import Trajectory, poses_from_xyzq

TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")  # ROS 2 and Noetic; ROS 1 before tf2 (TUM RGB-D's bags)
GT_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry",
            "geometry_msgs/msg/TransformStamped")  # what a ground-truth topic may carry
GT_NAMES = ("ground_truth", "groundtruth", "vicon", "mocap", "optitrack", "qualisys", "vrpn", "leica")  # and be called


def looks_like_ground_truth(topic: str) -> bool:
    """Whether a topic's name says ground truth (/ground_truth/pose, /vicon/robot/robot, /mocap/odom, /gt/pose):
    a pose topic is taken as ground truth by itself only then, as a robot's bag also holds poses that are not
    (/odom from the wheels, nav2's /goal_pose)."""
    name = topic.lower()
    return any(n in name for n in GT_NAMES) or "gt" in re.split(r"[^a-z0-9]+", name)


def pick_ground_truth(topics: dict[str, str], wanted: str | None) -> tuple[str | None, str | None]:
    """The ground-truth topic (``wanted``, else the one pose topic whose name says so) and a note naming the pose
    topics not taken (None when there are none)."""
    if wanted:
        return pick_topic(topics, GT_TYPES, "gt", wanted), None
    poses = sorted(t for t, m in topics.items() if m in GT_TYPES)
    named = [t for t in poses if looks_like_ground_truth(t)]
    if len(named) > 1:
        raise several(named, "gt", topics)
    chosen = named[0] if named else None
    others = [f"{t} [{topics[t]}]" for t in poses if t != chosen]
    return chosen, (f"not taken as ground truth: {', '.join(others)} (the name does not say so); name one with --gt-topic "
                    "to score against it (the camera's pose; --gt-camera for a tracked body)") if others else None


def pose_from_msg(msg: Any) -> np.ndarray:
    """A ground-truth message (:data:`GT_TYPES`) -> 4x4: PoseStamped's pose, PoseWithCovarianceStamped's and
    Odometry's pose.pose, TransformStamped's transform."""
    if hasattr(msg, "transform"):
        p, o = msg.transform.translation, msg.transform.rotation
    else:
        pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
        p, o = pose.position, pose.orientation
    return poses_from_xyzq(np.array([[p.x, p.y, p.z, o.x, o.y, o.z, o.w]], np.float64))[0]


def bag_ground_truth(reader: BagReader, wanted: str | None = None) -> Trajectory | None:
    """The bag's ground-truth poses (:data:`GT_TYPES` on ``wanted``, else on :func:`pick_ground_truth`'s topic, by
    header stamp) as a :class:`Trajectory`, looked up as a ``--gt`` TUM file is (:class:`~.trajectory.FrameTruth`): a pose per
    frame at the frames' stamps only, a motion-capture stream at its own rate and stamps interpolated between its
    poses. None without the topic or its messages; the pose topics not taken are noted in the reader's warnings."""
    topic, note = pick_ground_truth(reader.topics, wanted)
    if note:
        reader.warnings.append(note)
    if topic is None:
        return None
    truth = _trajectory([(msg_time(m.msg), pose_from_msg(m.msg)) for m in reader.messages({topic})])
    return _finite(truth, topic, reader) if truth is not None else None


def _finite(truth: Trajectory, source: str, reader: BagReader) -> Trajectory | None:
    """``truth``'s finite poses; the ones that are not (NaN, a zero quaternion: a lost track) noted in the reader's
    warnings and left out, a gap in the ground truth (:meth:`Trajectory.poses_at`) rather than pairs scored against
    NaN."""
    finite, dropped = truth.finite()
    if dropped:
        reader.warnings.append(f"{source}: {dropped} of {len(truth.stamps)} ground-truth poses are not finite numbers "
                               "(NaN, or a zero quaternion: a lost track?): left out as a gap in the ground truth (a frame in it "
                               "is scored on poses interpolated across a short gap, not scored in a long one)")
    return finite


def _trajectory(stamped: list[tuple[float, np.ndarray]]) -> Trajectory | None:
    """(stamp, 4x4 pose) pairs as a :class:`Trajectory`; None for none."""
    return Trajectory(np.array([t for t, _ in stamped]), np.array([T for _, T in stamped])) if stamped else None


def tf_ground_truth(reader: BagReader, topic: str, parent: str, child: str, camera_frame: str = "") -> Trajectory:
    """Ground truth from the transforms that lead from ``parent`` to ``child`` on a TF ``topic`` (/tf) and on /tf_static:
    one edge a motion-capture system or simulator publishes, or a chain through the tree (:class:`~.tftree.TfTree`:
    motion capture's world -> base_link, then the robot's base_link -> camera_optical_frame). The chain is noted in
    the reader's warnings, and so is a ``child`` other than ``camera_frame`` (the images' frame_id) when the tree has
    that: scoring a camera_link (x forward) as the optical frame (z forward) gives errors of 90 degrees. BagError
    naming the transforms there are when none lead from one frame to the other."""
    topic = pick_topic(reader.topics, TF_TYPES, "gt", topic)
    static = {t for t, m in reader.topics.items() if t == "/tf_static" and m in TF_TYPES} - {topic}
    tree = TfTree()
    for m in reader.messages({topic, *static}):
        for tf in m.msg.transforms:
            p, q = tf.transform.translation, tf.transform.rotation
            tree.add(tf.header.frame_id, tf.child_frame_id, msg_time(tf), (p.x, p.y, p.z), (q.x, q.y, q.z, q.w),
                     m.topic in static)
    try:
        truth = tree.trajectory(parent, child)
    except TfError as e:
        raise BagError(f"--gt-tf {parent}:{child}: {e} (on {' and '.join([topic, *static])})") from e
    if (finite := _finite(truth, f"--gt-tf {parent}:{child}", reader)) is None:
        raise BagError(f"--gt-tf {parent}:{child}: no transform from one to the other is a finite number (on {topic})")
    truth = finite
    if len(tree.chain(parent, child)) > 1:  # say which way it went, for the user to check
        reader.warnings.append(f"--gt-tf {parent}:{child}: chained {tree.route(parent, child)}")
    if (cam := camera_frame.strip("/")) and cam != child.strip("/") and cam in tree.frames():
        reader.warnings.append(f"--gt-tf {parent}:{child}: the images are in frame {cam}, which the transforms have; "
                               f"--gt-tf {parent}:{cam} scores the camera itself (its optical frame: z forward, x right). "
                               f"Scored against {child}, the camera's own motion is seen from another frame, unless "
                               "--gt-camera gives the camera's place on it")
    return truth
