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

from .bags import BagError, BagReader, choose_topics, typestore, window_side
from .caminfo import info_fields
from .datasets import Trajectory
from .dds import LARGE_FRAMES_PROFILE
from .geometry import Camera
from .mcap_out import McapOutput
from .params import NODE_NAME
from .posemsg import estimate_of_message
from .replay import PairScores, truth_missed

# the ROS packages the live mode runs on: the player's (this module) and the node's (node.py, its own process);
# test_core_no_ros checks that both modules import no other
LIVE_ROS_PACKAGES = ("rclpy", "diagnostic_msgs", "geometry_msgs", "rcl_interfaces", "sensor_msgs", "std_srvs")


def require_ros() -> None:
    """Import what the live mode runs on (player and node); a missing package raises ImportError naming it.

    Called before anything is written, so a machine without ROS leaves no empty output behind, and a missing
    message package is named here rather than by a node that exits before subscribing.
    """
    for package in LIVE_ROS_PACKAGES:
        importlib.import_module(package)


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
    """The topics a live replay plays and scores (:func:`~nmnet_ros.bags.choose_topics`); BagError for a ROS 1 bag."""
    if reader.ros1:
        raise BagError(f"{reader.path}: live replay plays ROS 2 bags (.mcap/.db3); replay ROS 1 bags (and .mcap files "
                       "converted from them) offline (without --live)")
    return choose_topics(reader, image_topic, info_topic)


def play_live(reader: BagReader, out: McapOutput, rate: float = 1.0, node_args: list[str] | None = None, log: Callable[[str], None] = print,
              camera: Camera | None = None, topics: dict[str, str | None] | None = None, recorded: bool = False,
              window: tuple[float, float] | None = None) -> dict:
    """Play, record, stop the node; returns counts and latencies.

    ``camera``: published as camera_info with every image instead of the bag's camera_info; ``topics``: the
    :func:`live_topics` to play (default: the bag's only image and camera_info topics); ``recorded``: each message
    is restamped with the time the bag recorded it (``--stamp-source arrival``); ``window``: play only the messages
    recorded from ``window[0]`` to ``window[1]`` seconds after the first frame.
    """
    import rclpy
    from rclpy.qos import QoSProfile, qos_profile_sensor_data
    from rclpy.serialization import deserialize_message, serialize_message

    topics = topics or live_topics(reader)
    img_t, info_t = topics["image"], None if camera else topics["camera_info"]
    compressed = reader.topics[img_t].endswith("CompressedImage")
    env = live_env()
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "FASTDDS_BUILTIN_TRANSPORTS",
                                           "FASTDDS_DEFAULT_PROFILES_FILE")})
    args = ["--ros-args", "-r", f"__node:={NODE_NAME}", "-p", f"use_compressed:={str(compressed).lower()}"]
    in_topic = "image/compressed" if compressed else "image"
    args += ["-r", f"{in_topic}:=/live/{in_topic}", "-r", "camera_info:=/live/camera_info", *(node_args or [])]
    node_proc = subprocess.Popen([sys.executable, "-m", "nmnet_ros.node", *args], env=env)
    rclpy.init()
    ts = typestore()
    stats: dict = {"published": 0, "results": 0, "latency_ms": [], "diagnostics": {}}
    sent_at: dict[int, float] = {}
    answered: set[int] = set()  # stamps the node published matches for
    try:
        player = rclpy.create_node("nmnet_player")
        pub_img = player.create_publisher(_rclpy_type(reader.topics[img_t]), f"/live/{in_topic}", qos_profile_sensor_data)
        pub_info = player.create_publisher(_rclpy_type("sensor_msgs/msg/CameraInfo"), "/live/camera_info", qos_profile_sensor_data)

        def record(topic: str, msgtype: str):
            def cb(msg) -> None:
                t_ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                out.write_raw(topic, msgtype, serialize_message(msg), t_ns)
                if topic.endswith("matches"):
                    stats["results"] += 1
                    answered.add(t_ns)
                    if t_ns in sent_at:
                        stats["latency_ms"].append(1000 * (time.monotonic() - sent_at[t_ns]))
            return cb

        for suffix, mtype in (("matches", "sensor_msgs/msg/PointCloud2"),
                              ("relative_pose", "geometry_msgs/msg/PoseWithCovarianceStamped")):
            player.create_subscription(_rclpy_type(mtype), f"/{NODE_NAME}/{suffix}", record(f"/{NODE_NAME}/{suffix}", mtype),
                                       QoSProfile(depth=100))

        def diagnostics(msg) -> None:  # the node's counters, as of its latest report (1 Hz)
            for st in msg.status:
                if st.hardware_id == f"/{NODE_NAME}":
                    stats["diagnostics"] = {kv.key: kv.value for kv in st.values}

        player.create_subscription(_rclpy_type("diagnostic_msgs/msg/DiagnosticArray"), "/diagnostics", diagnostics,
                                   QoSProfile(depth=10))
        t_end = time.monotonic() + 60
        while pub_img.get_subscription_count() == 0 and time.monotonic() < t_end:
            if node_proc.poll() is not None:
                raise RuntimeError(f"the node exited with code {node_proc.returncode} before subscribing")
            rclpy.spin_once(player, timeout_sec=0.1)
        if pub_img.get_subscription_count() == 0:
            raise RuntimeError("the node did not subscribe within 60 s")
        t0 = time.monotonic() + 1.0  # first messages after discovery can be lost
        while time.monotonic() < t0:
            rclpy.spin_once(player, timeout_sec=0.05)
        # calibration first, so the first frame is usable (bags often log it just after the image)
        if camera:
            pub_info.publish(camera_info_msg(camera))
            rclpy.spin_once(player, timeout_sec=0.2)
        elif info_t:
            first_info = next(iter(reader.messages({info_t})), None)
            if first_info is not None:
                pub_info.publish(deserialize_message(bytes(ts.serialize_cdr(first_info.msg, first_info.msgtype)),
                                                     _rclpy_type(first_info.msgtype)))
                rclpy.spin_once(player, timeout_sec=0.2)
        first_ns, t_start, last_ns = None, time.monotonic(), None  # last_ns: the stamp of the last image published
        first_frame = None  # the bag's first frame's recording time, where --start/--duration count from
        for m in reader.messages({t for t in (img_t, info_t) if t}):
            first_frame = m.log_time_ns if first_frame is None and m.topic == img_t else first_frame
            if window is not None and first_frame is None:  # a calibration before the first frame: published above
                continue
            if (side := window_side(window, first_frame, m.log_time_ns)) > 0:
                break
            if side < 0:
                continue
            first_ns = m.log_time_ns if first_ns is None else first_ns
            due = t_start + (m.log_time_ns - first_ns) / 1e9 / rate
            while (wait := due - time.monotonic()) > 0:
                rclpy.spin_once(player, timeout_sec=min(wait, 0.02))
            msg = deserialize_message(bytes(ts.serialize_cdr(m.msg, m.msgtype)), _rclpy_type(m.msgtype))
            if recorded:
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(m.log_time_ns, 10**9)
            if m.topic == img_t:
                if camera:
                    pub_info.publish(camera_info_msg(camera, msg.header))
                last_ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                sent_at[last_ns] = time.monotonic()
                pub_img.publish(msg)
                stats["published"] += 1
            else:
                pub_info.publish(msg)
        # the camera is done: no publisher left, so the node does not take the drain for a stalled camera (no_frames).
        # Not before the last frame has arrived: a writer destroyed right after publishing a large frame can take the
        # frame with it (the last of 6 raw 1.2 MB frames went missing in 3 of 26 runs); its result shows it arrived.
        t_last = time.monotonic() + 3.0  # < the node's 5 s no_frames delay; a frame the node dropped never answers
        while last_ns is not None and last_ns not in answered and time.monotonic() < t_last:
            rclpy.spin_once(player, timeout_sec=0.05)
        player.destroy_publisher(pub_img)
        player.destroy_publisher(pub_info)
        # drain: wait until results stop coming
        last, quiet = stats["results"], time.monotonic()
        while time.monotonic() - quiet < 8.0:
            rclpy.spin_once(player, timeout_sec=0.1)
            if stats["results"] != last:
                last, quiet = stats["results"], time.monotonic()
        player.destroy_node()
    finally:
        rclpy.try_shutdown()
        if node_proc.poll() is None:
            node_proc.send_signal(signal.SIGINT)
            try:
                node_proc.wait(15)
            except subprocess.TimeoutExpired:
                node_proc.kill()
    return stats


def score_recording(path: Path, truth: Trajectory | None) -> dict:
    """Pose errors of a recorded ``~/relative_pose`` stream against ``truth`` (the replay's
    :func:`~nmnet_ros.replay.ground_truth`), scored as the offline replay scores its results
    (:class:`~nmnet_ros.replay.PairScores`; "no estimate" is a failure).

    Each message is relative to the frame of the message before it (see :mod:`nmnet_ros.posemsg`); the
    first, relative to the node's first frame, which has no message, is not scored.
    """
    scores = PairScores()
    if truth is None:  # nothing to score against: the recording is not read
        return scores.summary()
    rec = BagReader(path)
    recorded = list(rec.messages({f"/{NODE_NAME}/relative_pose"}))
    msgs, stamps = [m.msg for m in recorded], [m.log_time_ns / 1e9 for m in recorded]
    if note := truth_missed(truth, stamps):
        print(f"warning: {note}", file=sys.stderr)
    gt = [None if np.isnan(T[0, 0]) else T for T in truth.poses_at(np.asarray(stamps))]  # each looked up once
    for msg, stamp, T_prev, T_cur in zip(msgs[1:], stamps[1:], gt, gt[1:], strict=False):
        o, p = msg.pose.pose.orientation, msg.pose.pose.position
        scores.add(*estimate_of_message(np.array([o.x, o.y, o.z, o.w]), np.array([p.x, p.y, p.z]), msg.pose.covariance),
                   T_prev, T_cur, stamp)
    return scores.summary()
