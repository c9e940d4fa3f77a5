"""The TF tree: chains walked up and down, static and republished edges, moving edges at their own rates."""

from __future__ import annotations

import numpy as np
import pytest

from nmnet_ros.core.geometry import quat_to_rot
from nmnet_ros.interface.posemsg import rot_to_quat
from nmnet_ros.io.tftree import TfError, TfTree
from nmnet_ros.io.trajectory import between

RNG = np.random.default_rng(7)


def pose() -> np.ndarray:
    """A random rigid transform."""
    q = RNG.normal(size=4)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quat_to_rot(q / np.linalg.norm(q)), RNG.normal(size=3)
    return T


def add(tree: TfTree, parent: str, child: str, stamp: float, T: np.ndarray, static: bool = False) -> None:
    """A 4x4 transform into the tree, as a TF message carries it (translation, quaternion)."""
    tree.add(parent, child, stamp, T[:3, 3], rot_to_quat(T[:3, :3]), static)


def robot(stamps: np.ndarray) -> tuple[TfTree, list[np.ndarray], np.ndarray, np.ndarray]:
    """Motion capture's world -> base_link at ``stamps``; base_link -> camera_link on /tf_static; camera_link ->
    camera_optical republished on /tf every 0.25 s stamped 0.1 s ahead (ROS 1's static_transform_publisher)."""
    tree, body = TfTree(), [pose() for _ in stamps]
    mount, optical = pose(), pose()
    for t, T in zip(stamps, body, strict=True):
        add(tree, "/world", "/base_link", t, T)
    add(tree, "base_link", "camera_link", 0.0, mount, static=True)
    for t in np.arange(stamps[0] - 1, stamps[-1] + 1, 0.25):
        add(tree, "camera_link", "camera_optical", t + 0.1, optical)
    return tree, body, mount, optical


def test_a_chain_down_the_tree_composes_each_edge_at_the_moving_edges_stamps():
    stamps = np.arange(10) * 0.1 + 100.0
    tree, body, mount, optical = robot(stamps)
    truth = tree.trajectory("world", "camera_optical")
    assert np.allclose(truth.stamps, stamps) and len(truth.poses) == 10
    assert np.allclose(truth.poses, np.array(body) @ mount @ optical)
    assert tree.route("world", "camera_optical") == "world -> base_link -> camera_link -> camera_optical (moving: world:base_link)"
    up = tree.trajectory("camera_optical", "world")  # walked up: the inverse
    assert np.allclose(up.poses @ truth.poses, np.eye(4))
    assert tree.route("camera_optical", "world").startswith("camera_optical <- camera_link <- base_link <- world")
    still = tree.trajectory("camera_link", "camera_optical")  # only an edge on /tf that never changes: at its stamps
    assert np.allclose(still.poses, optical) and len(still.stamps) == 12
    with pytest.raises(TfError, match="every transform from camera_link to base_link is on /tf_static"):
        tree.trajectory("camera_link", "base_link")


def test_two_moving_edges_at_their_own_rates_are_interpolated_to_the_sparser_ones_stamps():
    """world -> odom at 10 Hz, odom -> base_link at 50 Hz, 3 ms late: the chain comes at the sparser edge's stamps,
    the other interpolated between its two transforms around each; a stamp in a gap of it is left out, not paired
    with another time."""
    tree, slow, fast = TfTree(), {}, {}
    for t in np.round(np.arange(0, 1, 0.1), 6):
        slow[t] = pose()
        add(tree, "world", "odom", t, slow[t])
    for t in np.round(np.arange(0, 1, 0.02) + 0.003, 6):
        if not 0.45 < t < 0.55:  # a gap around 0.5
            fast[t] = pose()
            add(tree, "odom", "base_link", t, fast[t])
    truth = tree.trajectory("world", "base_link")
    assert 0.5 not in np.round(truth.stamps, 6) and len(truth.stamps) == 9
    assert np.allclose(truth.poses[0], slow[0.0] @ fast[0.003])  # before the first: the nearest, 3 ms away
    for t, T in zip(truth.stamps[1:], truth.poses[1:], strict=True):
        before, after = max(s for s in fast if s < t), min(s for s in fast if s > t)
        assert np.allclose(T, slow[round(t, 6)] @ between(fast[before], fast[after], (t - before) / (after - before)))


def test_frames_no_chain_joins_are_named_with_the_edges_there_are():
    tree, *_ = robot(np.arange(3.0))
    add(tree, "map", "odom", 0.0, pose())
    for a, b in (("world", "odom"), ("world", "world"), ("world", "nowhere")):
        with pytest.raises(TfError, match=f"no transforms lead from {a} to {b}; there are base_link:camera_link, "
                                          "camera_link:camera_optical, map:odom, world:base_link"):
            tree.trajectory(a, b)
    clocks = TfTree()  # two moving edges that never meet in time
    add(clocks, "world", "odom", 0.0, pose())
    add(clocks, "world", "odom", 1.0, pose())
    add(clocks, "odom", "base", 50.0, pose())
    add(clocks, "odom", "base", 51.0, pose())
    with pytest.raises(TfError, match="never published at the same time"):
        clocks.trajectory("world", "base")
