"""A recorded TF tree: the transforms between two frames over time, chained through the tree as tf2 would.

A robot's bag rarely holds the transform one wants to score against as one edge: motion capture publishes
``world -> base_link``, the robot description adds ``base_link -> camera_link -> camera_optical_frame`` on
/tf_static (or, in ROS 1, again and again on /tf from static_transform_publisher, stamped ahead of time).
:class:`TfTree` collects every edge and gives the chained poses of one frame in another at the stamps of the
edge that moves. No ROS needed: the bag reader hands in the transforms.
"""

from __future__ import annotations

from array import array
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .trajectory import Trajectory, poses_from_xyzq

Edge = tuple[str, str]  # (parent frame, child frame) as published


class TfError(ValueError):
    """No chain of transforms between the two frames asked for, or none that moves."""


@dataclass
class TfTree:
    """Every transform seen, per edge, as rows of (stamp, x, y, z, qx, qy, qz, qw) packed in an array: 64 bytes each,
    as a robot's /tf over an hour holds millions (every joint, 50-100 times a second), of which the chain needs a
    few edges; and which edges came on /tf_static."""

    stamped: dict[Edge, array] = field(default_factory=dict)
    static: set[Edge] = field(default_factory=set)

    def add(self, parent: str, child: str, stamp: float, xyz: Sequence[float], quat: Sequence[float],
            static: bool = False) -> None:
        """One transform: ``child``'s pose in ``parent`` (translation, quaternion x y z w) at ``stamp``; leading
        slashes (ROS 1) are dropped."""
        edge = (parent.strip("/"), child.strip("/"))
        self.stamped.setdefault(edge, array("d")).extend((stamp, *xyz, *quat))
        if static:
            self.static.add(edge)

    def rows(self, edge: Edge) -> np.ndarray:
        """The edge's transforms, (N, 8): stamp, translation, quaternion."""
        return np.frombuffer(self.stamped[edge], np.float64).reshape(-1, 8)

    def track(self, edge: Edge) -> Trajectory:
        """The edge's transforms as poses (4x4) over time."""
        rows = self.rows(edge)
        return Trajectory(rows[:, 0].copy(), poses_from_xyzq(rows[:, 1:8]))

    def frames(self) -> set[str]:
        """Every frame the transforms name."""
        return {frame for edge in self.stamped for frame in edge}

    def edges(self) -> str:
        """The edges as ``parent:child``, for errors that say what there is."""
        return ", ".join(f"{a}:{b}" for a, b in sorted(self.stamped)) or "none"

    def chain(self, start: str, goal: str) -> list[tuple[Edge, bool]]:
        """The edges from frame ``start`` to ``goal``, each with whether it is walked from child to parent (the tree
        is walked up and down, as tf2's lookupTransform does); TfError when no chain joins them."""
        start, goal = start.strip("/"), goal.strip("/")
        links: dict[str, list[tuple[str, Edge, bool]]] = {}
        for a, b in self.stamped:
            links.setdefault(a, []).append((b, (a, b), False))
            links.setdefault(b, []).append((a, (a, b), True))
        came: dict[str, tuple[str, Edge, bool] | None] = {start: None}
        queue = deque([start])
        while queue and goal not in came:
            frame = queue.popleft()
            for nxt, edge, up in links.get(frame, []):
                if nxt not in came:
                    came[nxt] = (frame, edge, up)
                    queue.append(nxt)
        if goal not in came or start == goal:
            raise TfError(f"no transforms lead from {start} to {goal}; there are {self.edges()}")
        steps, frame = [], goal
        while (step := came[frame]) is not None:
            frame = step[0]
            steps.append(step[1:])
        return steps[::-1]

    def moves(self, edge: Edge) -> bool:
        """Whether the edge changes over the recording (not on /tf_static and not the same every time)."""
        values = self.rows(edge)[:, 1:]
        return edge not in self.static and not np.allclose(values, values[0], rtol=0.0, atol=1e-9)

    def route(self, start: str, goal: str) -> str:
        """The chain as words, for the user to check: ``world -> base_link -> camera (moving: world:base_link)``."""
        chain = self.chain(start, goal)
        words = start.strip("/") + "".join(f" {'<-' if up else '->'} {e[0] if up else e[1]}" for e, up in chain)
        return f"{words} (moving: {', '.join(f'{a}:{b}' for (a, b), _ in chain if self.moves((a, b))) or 'none'})"

    def trajectory(self, start: str, goal: str) -> Trajectory:
        """``goal``'s pose in ``start`` over time, at the stamps of the chain's sparsest moving edge. The other moving
        edges are looked up as ground truth is (:meth:`Trajectory.poses_at`: interpolated between their transforms),
        and a stamp where one has none is left out; an edge that never changes counts at any time (its latest value).
        TfError when no edge is on /tf."""
        chain = self.chain(start, goal)
        tracks = {e: self.track(e) for e, _ in chain}
        moving = [e for e, _ in chain if self.moves(e)] or [e for e, _ in chain if e not in self.static]
        if not moving:
            raise TfError(f"every transform from {start} to {goal} is on /tf_static: no motion to score against; give the "
                          f"frames a motion-capture system or simulator moves (there are {self.edges()})")
        clock = max(moving, key=lambda e: tracks[e].spacing)
        stamps = tracks[clock].stamps
        poses, ok = np.broadcast_to(np.eye(4), (len(stamps), 4, 4)).copy(), np.ones(len(stamps), bool)
        for edge, up in chain:
            track = tracks[edge]
            if edge == clock:
                T = track.poses
            elif edge in moving:
                T = track.poses_at(stamps)
                found = np.isfinite(T[:, 0, 0])
                T[~found], ok = np.eye(4), ok & found  # a stamp it has no transform for is left out
            else:
                T = np.broadcast_to(track.poses[-1], (len(stamps), 4, 4))
            poses = poses @ (np.linalg.inv(T) if up else T)
        if not ok.any():
            raise TfError(f"the moving transforms from {start} to {goal} ({', '.join(f'{a}:{b}' for a, b in moving)}) "
                          "are never published at the same time (another clock?)")
        return Trajectory(stamps[ok], poses[ok])
