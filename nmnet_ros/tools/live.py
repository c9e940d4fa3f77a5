"""``nmnet replay BAG --live``: play a ROS 2 bag onto topics, the node in its own process, record its outputs.

The bag's image and camera_info messages are published at recorded timing (x ``rate``) after the
node has subscribed; the node's ``~/matches`` and ``~/relative_pose`` are recorded to the output
.mcap and then scored against the bag's ground truth like the offline mode.
"""

from __future__ import annotations

import importlib
import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..core.geometry import Camera
from ..core.tracks import TrackLengths
from ..interface.caminfo import info_fields
from ..interface.dds import LARGE_FRAMES_PROFILE, rmw_problem
from ..interface.imgconv import matches_of_cloud
from ..interface.params import NODE_NAME
from ..interface.posemsg import SIGMAS, estimate_of_message
from ..io.bags import BagError, BagReader, WindowWatch, choose_topics, typestore
from ..io.mcap_out import McapOutput
from ..io.trajectory import FrameTruth, Trajectory
from .scoring import PairScores, truth_missed

# the ROS packages the live mode runs on: the player's (this module) and the node's (node.py, its own process);
# test_core_no_ros checks that both modules import no other
LIVE_ROS_PACKAGES = ("rclpy", "diagnostic_msgs", "geometry_msgs", "rcl_interfaces", "sensor_msgs", "std_srvs")


def require_ros() -> None:
    """Import what the live mode runs on (player and node); a missing package raises ImportError naming it.

    Called before anything is written, so a machine without ROS leaves no empty output behind, and a missing
    message package is named here rather than by a node that exits before subscribing. The environment is checked
    first (:func:`check_ros_environment`, a ValueError): an RMW_IMPLEMENTATION not installed ends the process at
    rclpy's import.
    """
    check_ros_environment()
    for package in LIVE_ROS_PACKAGES:
        importlib.import_module(package)


def check_ros_environment() -> None:
    """The ROS environment the user set lets the player and the node talk, checked before rclpy is imported and the
    output file made: an RMW_IMPLEMENTATION that is installed (else rcl ends the process on importing rclpy); a
    ROS_DOMAIN_ID ROS can use (a whole number from 0 to 232; empty: the default), else rcl refuses it once both start,
    in a traceback; no ROS_AUTOMATIC_DISCOVERY_RANGE=OFF over DDS, where the two never find each other (60 s of
    silence, then an error that cannot say why)."""
    if (problem := rmw_problem()) is not None:
        raise ValueError(problem)
    said = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if said and not (said.isdigit() and int(said) <= 232):
        raise ValueError(f"ROS_DOMAIN_ID={said!r}: a live replay runs on that domain, and ROS takes a whole number from "
                         "0 to 232; set one, or unset it for a random free one")
    zenoh = "zenoh" in os.environ.get("RMW_IMPLEMENTATION", "")  # which ignores the variable
    if os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "OFF" and not zenoh:  # rcl: "off" is invalid, so LOCALHOST
        raise ValueError("ROS_AUTOMATIC_DISCOVERY_RANGE=OFF: a live replay's player and node are two processes that "
                         "would never discover each other; unset it (the replay uses LOCALHOST) or set LOCALHOST")


def _rclpy_type(msgtype: str):
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def camera_info_msg(camera: Camera, header: Any = None) -> Any:
    """An rclpy CameraInfo of ``camera`` with the image's header (none: an empty one)."""
    from sensor_msgs.msg import CameraInfo

    msg = CameraInfo() if header is None else CameraInfo(header=header)
    for key, value in info_fields(camera, camera.width, camera.height).items():
        setattr(msg, key, value.tolist() if isinstance(value, np.ndarray) else value)
    return msg


def live_env() -> dict[str, str]:
    """The environment for player and node: an own domain on localhost unless the user set one."""
    env = dict(os.environ)
    env.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("FASTDDS_BUILTIN_TRANSPORTS", "LARGE_DATA")
    env.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(LARGE_FRAMES_PROFILE))  # raw frames over 0.5 MB (see dds.py)
    return env


def live_topics(reader: BagReader, image_topic: str | None = None, info_topic: str | None = None) -> dict[str, str | None]:
    """The topics a live replay plays and scores (:func:`~nmnet_ros.io.bags.choose_topics`); BagError for a ROS 1 bag."""
    if reader.ros1:
        raise BagError(f"{reader.path}: live replay plays ROS 2 bags (.mcap/.db3); replay ROS 1 bags (and .mcap files "
                       "converted from them) offline (without --live)")
    return choose_topics(reader, image_topic, info_topic)


def _input_topic(image_type: str) -> str:
    """The node's (relative) input topic for frames of ``image_type``, as the player publishes them under its prefix."""
    return "image/compressed" if image_type.endswith("CompressedImage") else "image"


def _prefix() -> str:
    """This replay's own topics: every topic between player and node lives under it, so two live replays that share a
    domain (two at once on one machine with the same random domain, or a domain the user set, with a robot's
    nmnet_node on it) never hear each other."""
    return f"/nmnet_live_{os.getpid()}"


# the node's outputs, remapped under the prefix; recorded under the node's own names (/nmnet_node/matches, ...)
_OUTPUTS = (("matches", "sensor_msgs/msg/PointCloud2"), ("relative_pose", "geometry_msgs/msg/PoseWithCovarianceStamped"))


def _start_node(image_type: str, node_args: list[str] | None) -> subprocess.Popen:
    """``nmnet_node`` in its own process, on the player's domain, its inputs, outputs and /diagnostics remapped under
    :func:`_prefix`; ``node_args``: its settings (``replay.live_node_args``).

    The frames' transport is the player's, set after ``node_args`` (rcl: the last value given wins): the message type
    the bag holds, and qos auto, which follows the player's publisher. A robot's parameters file saying otherwise
    (use_compressed for another camera, qos reliable) left the node deaf to the player."""
    env = live_env()
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "FASTDDS_BUILTIN_TRANSPORTS",
                                           "FASTDDS_DEFAULT_PROFILES_FILE")})  # the player's own participant
    in_topic, pre = _input_topic(image_type), _prefix()
    remaps = [f"{in_topic}:={pre}/{in_topic}", f"camera_info:={pre}/camera_info", f"/diagnostics:={pre}/diagnostics",
              *(f"~/{name}:={pre}/{name}" for name, _ in _OUTPUTS)]
    transport = [f"use_compressed:={str(in_topic != 'image').lower()}", "qos:=auto"]
    args = ["--ros-args", "-r", f"__node:={NODE_NAME}", *(a for r in remaps for a in ("-r", r)), *(node_args or []),
            *(a for p in transport for a in ("-p", p))]
    return subprocess.Popen([sys.executable, "-m", "nmnet_ros.node", *args], env=env)


class NodeNotReady(RuntimeError):
    """The node of a live replay exited, or never subscribed, before the first frame: nothing was played."""


class _Player:
    """The rclpy side of a live replay: publishes the bag's frames and calibration, records the node's outputs to
    ``out`` and counts them (``stats``: published, results, latency_ms, the node's last diagnostics)."""

    def __init__(self, image_type: str, out: McapOutput, stats: dict) -> None:
        import rclpy
        from rclpy.qos import QoSProfile, qos_profile_sensor_data

        self.rclpy, self.out = rclpy, out
        self.stats = stats
        self.sent_at: dict[int, float] = {}  # image stamp -> when it was published
        self.answered: set[int] = set()  # stamps the node published matches for
        self.last_stamp: int | None = None  # the last frame published
        self.node = rclpy.create_node("nmnet_player")
        pre = _prefix()
        self.pub_img = self.node.create_publisher(_rclpy_type(image_type), f"{pre}/{_input_topic(image_type)}",
                                                  qos_profile_sensor_data)
        self.pub_info = self.node.create_publisher(_rclpy_type("sensor_msgs/msg/CameraInfo"), f"{pre}/camera_info",
                                                   qos_profile_sensor_data)
        for suffix, mtype in _OUTPUTS:
            topic = f"/{NODE_NAME}/{suffix}"  # the name it is recorded under, as the node publishes it on a robot
            self.node.create_subscription(_rclpy_type(mtype), f"{pre}/{suffix}", self._recorder(topic, mtype),
                                          QoSProfile(depth=100))
        self.node.create_subscription(_rclpy_type("diagnostic_msgs/msg/DiagnosticArray"), f"{pre}/diagnostics",
                                      self._on_diagnostics, QoSProfile(depth=10))

    def _recorder(self, topic: str, msgtype: str) -> Callable[[Any], None]:
        from rclpy.serialization import serialize_message

        def record(msg) -> None:
            t_ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            self.out.write_raw(topic, msgtype, serialize_message(msg), t_ns)
            if topic.endswith("matches"):
                self.stats["results"] += 1
                self.answered.add(t_ns)
                if t_ns in self.sent_at:
                    self.stats["latency_ms"].append(1000 * (time.monotonic() - self.sent_at[t_ns]))
        return record

    def _on_diagnostics(self, msg) -> None:
        """The node's counters, as of its latest report (1 Hz)."""
        for st in msg.status:
            if st.hardware_id == f"/{NODE_NAME}":
                self.stats["diagnostics"] = {kv.key: kv.value for kv in st.values}

    def spin_for(self, seconds: float, until: Callable[[], bool] = lambda: False, step: float = 0.05) -> None:
        """Serve callbacks for up to ``seconds``, or until ``until()``."""
        t_end = time.monotonic() + seconds
        while not until() and (wait := t_end - time.monotonic()) > 0:
            self.rclpy.spin_once(self.node, timeout_sec=min(wait, step))

    def wait_for_node(self, node_proc: subprocess.Popen, timeout: float = 60.0) -> None:
        """Until the node subscribes to the frames (:class:`NodeNotReady` if it exits or does not within ``timeout``),
        then 1 s more: the first messages after discovery can be lost."""
        t_end = time.monotonic() + timeout
        while self.pub_img.get_subscription_count() == 0 and time.monotonic() < t_end:
            if node_proc.poll() is not None:
                raise NodeNotReady(f"nmnet_node exited with code {node_proc.returncode} before it subscribed to the "
                                   "frames; its log above says why")
            self.rclpy.spin_once(self.node, timeout_sec=0.1)
        if self.pub_img.get_subscription_count() == 0:
            raise NodeNotReady(f"nmnet_node did not subscribe to {self.pub_img.topic_name} within {timeout:.0f} s "
                               f"(ROS_DOMAIN_ID {os.environ['ROS_DOMAIN_ID']}): DDS discovery between two processes on "
                               "this machine failed, or the node is still starting; its log above may say which")
        self.spin_for(1.0)

    def publish(self, msg: Any, is_image: bool, camera: Camera | None) -> None:
        """One of the bag's messages; with ``camera``, its camera_info goes with every frame."""
        if not is_image:
            self.pub_info.publish(msg)
            return
        if camera:
            self.pub_info.publish(camera_info_msg(camera, msg.header))
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        self.sent_at[stamp] = time.monotonic()
        self.pub_img.publish(msg)
        self.stats["published"] += 1
        self.stats["stamps"].append(stamp)
        self.last_stamp = stamp

    def finish(self) -> None:
        """The camera is done: wait for the last frame's result (3 s at most, under the node's 5 s no_frames delay;
        a frame the node dropped never answers), remove the publishers, then record until results stop (8 s quiet).

        No publisher left, so the node does not take the drain for a stalled camera (no_frames). Not before the last
        frame has arrived: a writer destroyed right after publishing a large frame can take the frame with it (the
        last of 6 raw 1.2 MB frames went missing in 3 of 26 runs); its result shows it arrived."""
        if self.last_stamp is not None:
            self.spin_for(3.0, lambda: self.last_stamp in self.answered)
        self.node.destroy_publisher(self.pub_img)
        self.node.destroy_publisher(self.pub_info)
        count, quiet = self.stats["results"], time.monotonic()
        while time.monotonic() - quiet < 8.0:
            self.rclpy.spin_once(self.node, timeout_sec=0.1)
            if self.stats["results"] != count:
                count, quiet = self.stats["results"], time.monotonic()


def new_stats() -> dict:
    """A live replay's counts, as :func:`play_live` fills them: frames published, results, latencies, diagnostics."""
    return {"published": 0, "results": 0, "latency_ms": [], "diagnostics": {}, "node_exit": None,
            "stamps": []}  # every frame published (ns): the ground truth's frames, those the node dropped too


def play_live(reader: BagReader, out: McapOutput, rate: float = 1.0, node_args: list[str] | None = None,
              camera: Camera | None = None, topics: dict[str, str | None] | None = None, recorded: bool = False,
              window: tuple[float, float] | None = None, stats: dict | None = None) -> dict:
    """Play, record, stop the node; returns counts and latencies.

    ``stats`` (from :func:`new_stats`) is filled as the bag plays, so a caller whose replay is interrupted
    (KeyboardInterrupt: rclpy's own signal handlers are not installed, Ctrl-C raises as in any script) has the counts
    so far.

    ``camera``: published as camera_info with every image instead of the bag's camera_info; ``topics``: the
    :func:`live_topics` to play (default: the bag's only image and camera_info topics); ``recorded``: each message
    is restamped with the time the bag recorded it (``--stamp-source arrival``); ``window``: play only the messages
    recorded from ``window[0]`` to ``window[1]`` seconds after the first frame.
    """
    import rclpy
    from rclpy.serialization import deserialize_message

    topics = topics or live_topics(reader)
    img_t, info_t = topics["image"], None if camera else topics["camera_info"]
    node_proc = _start_node(reader.topics[img_t], node_args)
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)  # Ctrl-C raises here; rclpy would end the context
    ts = typestore()

    def ros_msg(m):  # a bag message as the rclpy message it was
        return deserialize_message(bytes(ts.serialize_cdr(m.msg, m.msgtype)), _rclpy_type(m.msgtype))

    try:
        player = _Player(reader.topics[img_t], out, new_stats() if stats is None else stats)
        player.wait_for_node(node_proc)
        # calibration first, so the first frame is usable (bags often log it just after the image)
        first_info = None if camera or not info_t else next(iter(reader.messages({info_t})), None)
        if camera or first_info is not None:
            player.pub_info.publish(camera_info_msg(camera) if camera else ros_msg(first_info))
            player.spin_for(0.2)
        first_ns, t_start = None, time.monotonic()
        watch = WindowWatch(window)  # a calibration before the first frame lies before a window: published above
        for m in reader.messages({t for t in (img_t, info_t) if t}):
            if (side := watch.side(m.log_time_ns, m.topic == img_t)) > 0:
                break
            if side < 0:
                continue
            first_ns = m.log_time_ns if first_ns is None else first_ns
            player.spin_for(t_start + (m.log_time_ns - first_ns) / 1e9 / rate - time.monotonic(), step=0.02)
            if node_proc.poll() is not None:  # it crashed or was killed: nothing more can be processed
                break
            msg = ros_msg(m)
            if recorded:
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(m.log_time_ns, 10**9)
            player.publish(msg, m.topic == img_t, camera)
        if missed := watch.missed():
            reader.warnings.append(missed)
        if node_proc.poll() is None:
            player.finish()
        player.stats["node_exit"] = node_proc.poll()  # None: still running, as it should be
        player.node.destroy_node()
        return player.stats
    finally:
        rclpy.try_shutdown()
        if node_proc.poll() is None:
            node_proc.send_signal(signal.SIGINT)
            try:
                node_proc.wait(15)
            except subprocess.TimeoutExpired:
                node_proc.kill()


def _truth_lookup(truth: Trajectory, frames: list[int] | None) -> Callable[[int], np.ndarray | None]:
    """The ground truth's pose at a pose message's stamp (ns), or None: see :func:`recording_summary`."""
    if not frames:
        look = FrameTruth(truth)
        return lambda t_ns: look.at(t_ns / 1e9)
    poses, _ = truth.at_frames(np.asarray(frames, np.float64) / 1e9)
    return {t: T for t, T in zip(frames, poses, strict=True) if not np.isnan(T[0, 0])}.get


def recording_summary(path: Path, truth: Trajectory | None, sigmas: tuple[float, float] = SIGMAS,
                      frames: list[int] | None = None) -> tuple[dict, dict]:
    """A recording of the node's outputs, read once: its ``~/relative_pose`` stream scored against ``truth`` as the
    offline replay scores its results (:class:`~nmnet_ros.tools.scoring.PairScores`; "no estimate" is a failure), and the
    feature tracks of its ``~/matches`` (:class:`~nmnet_ros.core.tracks.TrackLengths`, counted as they are read).
    ``sigmas``: the node's pose_sigma_* parameters, which the recorded covariances were published with. ``frames``:
    the stamps (ns) of every frame played into the node, those it dropped too (:func:`new_stats`' ``stamps``); the
    ground truth is then looked up as for a folder of those frames (:meth:`Trajectory.at_frames`), so the frames the
    node dropped do not change it. Without them, frame by frame as recorded (:class:`FrameTruth`).

    Each pose message is relative to the frame of the message before it (see :mod:`nmnet_ros.interface.posemsg`); the
    first (the node's first frame, or a recording that starts later) relates to no frame here and is not scored.
    """
    pose_topic, matches_topic = f"/{NODE_NAME}/relative_pose", f"/{NODE_NAME}/matches"
    scores, tracks = PairScores(sigmas), TrackLengths()  # scored and counted as they come: a long recording is not held
    first = last = None  # the pose messages' first and last stamps
    T_prev, any_truth = None, False
    truth_at = None if truth is None else _truth_lookup(truth, frames)
    for m in BagReader(path).messages({pose_topic, matches_topic}):
        if m.topic == matches_topic:
            tracks.add(matches_of_cloud(m.msg.point_step, m.msg.fields, m.msg.data)["track_id"])
            continue
        last = m.log_time_ns / 1e9
        if truth is None:
            continue
        T = truth_at(m.log_time_ns)
        if first is not None:  # the first message relates to no frame here
            o, p = m.msg.pose.pose.orientation, m.msg.pose.pose.position
            cov = np.reshape(m.msg.pose.covariance, (6, 6))
            scores.add(*estimate_of_message(np.array([o.x, o.y, o.z, o.w]), np.array([p.x, p.y, p.z]), cov),
                       T_prev, T, last, cov)
        first = last if first is None else first
        T_prev, any_truth = T, any_truth or T is not None
    if first is not None and not any_truth and (note := truth_missed(truth, [first, last])):
        print(f"warning: {note}", file=sys.stderr)
    return scores.summary(), tracks.summary()
