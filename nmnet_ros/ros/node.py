"""The ROS 2 node: consecutive camera frames in, selected matches and relative pose out.

Frames land in a one-slot mailbox (the newest wins; overwritten frames are counted as dropped)
and two worker threads run the front end as a pipeline (decode, detect and match of frame t+1
beside NM-Net and pose of frame t), so the executor never blocks on the heavy work.
Run: ``nmnet_node --ros-args -r image:=/cam/image_raw -r camera_info:=/cam/camera_info``.
"""

from __future__ import annotations

# isort: off
from .one_arena import ENABLED as _ONE_ARENA  # noqa: F401 - first: before any thread allocates
# isort: on

import re
import sys
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import cv2
import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField
from std_srvs.srv import Trigger

from ..core.debug_view import draw_matches
from ..core.geometry import Camera, CameraError
from ..core.model_fast import precision_note
from ..core.pipeline import FrameResult, Frontend, Prepared
from ..core.planes import NOTE as PLANE_NOTE
from ..interface.caminfo import camera_from_info
from ..interface.dds import (
    DEPTH_ADVICE,
    LARGE_FRAME_BYTES,
    depth_encoding_note,
    follow_reliability,
    is_depth,
    large_frames_advice,
    mistyped_advice,
    silence_advice,
    where_are_the_images,
)
from ..interface.framecheck import FrameChecks
from ..interface.imgconv import IMAGE_TYPES, ImageError, array_to_image_fields, decode_message, matches_to_cloud_fields, pixel_cap
from ..interface.params import (
    NODE_NAME,
    PARAMS,
    STARTUP_ONLY,
    check_choices,
    frontend_config,
    not_parameters,
    params_file_misses,
    pose_sigmas,
    rcl_arguments_error,
)
from ..interface.posemsg import relative_pose_of_current, stamp_seconds

T = TypeVar("T")


def lasting_warning_due(seconds: int, first: int, cap: int = 600) -> bool:
    """Whether a warning about a condition that has lasted ``seconds`` (0: it just began) is logged now:
    at once, then after ``first``, 2 x ``first``, 4 x ``first``, ... seconds, at most ``cap`` apart, so an
    idle camera does not fill the log."""
    if first < 1 or cap < first:
        raise ValueError(f"lasting warnings need 1 <= first <= cap seconds, got first={first}, cap={cap}")  # else: no end
    at, gap = 0, first
    while at < seconds:
        at, gap = at + gap, min(2 * gap, cap)
    return at == seconds


RECENT_S = 10.0  # a warning counted this recently makes /diagnostics' level WARN
NOT_FAULTS = ("no_motion",)  # counted, but a normal state: a robot that waits or turns in place


def health(last_warned: dict[str, float], now: float, status: str) -> tuple[bytes, str]:
    """/diagnostics' level and message: WARN naming the kinds counted in the last RECENT_S seconds, else OK with
    the last frame's status. A fault that passed (a camera_info that came after the first frame, one corrupt
    image) does not leave the node WARN for good; the counters (``warn_<kind>``) keep every one."""
    recent = sorted(k for k, t in last_warned.items() if now - t < RECENT_S and k not in NOT_FAULTS)
    if recent:
        return DiagnosticStatus.WARN, f"warnings in the last {RECENT_S:.0f} s: " + ", ".join(recent)
    return DiagnosticStatus.OK, status


@dataclass
class _Detected:
    """A decoded, detected frame on its way from stage 1 to stage 2."""

    header: object
    img: np.ndarray
    prepared: Prepared  # features, and matches to the frame stage 1 handed over before
    stamp: float
    timings: dict
    t_recv: float


@dataclass
class Stats:
    """Counters and recent latencies for /diagnostics."""

    received: int = 0
    processed: int = 0
    dropped: int = 0
    estimated: int = 0  # relative poses with an estimate (ok, no_motion)
    resets: int = 0  # ~/reset calls
    warnings: dict[str, int] = field(default_factory=dict)
    last_warned: dict[str, float] = field(default_factory=dict)  # monotonic time each kind was last counted
    latency_ms: deque = field(default_factory=lambda: deque(maxlen=100))
    stage_ms: dict[str, deque] = field(default_factory=dict)
    last_matches: int = 0
    last_keypoints: int = 0
    last_selected: int = 0
    last_continued: int = 0  # the last frame's selected matches that continue a track of the frame before
    last_status: str = "waiting"
    t_start: float = field(default_factory=time.monotonic)


class NMNetNode(Node):
    """rclpy shell around :class:`~nmnet_ros.core.pipeline.Frontend`."""

    def __init__(self, params_files: tuple[str, ...] = ()) -> None:
        """``params_files``: the ``--params-file`` arguments, checked for a section that applies to this node."""
        super().__init__(NODE_NAME)
        for name, (default, desc, rng) in PARAMS.items():
            d = ParameterDescriptor(description=desc)
            if isinstance(rng, tuple) and isinstance(rng[0], float):
                d.floating_point_range = [FloatingPointRange(from_value=rng[0], to_value=rng[1])]
            elif isinstance(rng, tuple) and isinstance(rng[0], int) and not isinstance(rng[0], bool):
                d.integer_range = [IntegerRange(from_value=rng[0], to_value=rng[1], step=1)]
            elif isinstance(rng, tuple):
                d.additional_constraints = "one of: " + ", ".join(rng)
            if name in STARTUP_ONLY:
                d.read_only = True  # `ros2 param set` refuses it: set it at start-up
            self.declare_parameter(name, default, d)
        p = {name: self.get_parameter(name).value for name in PARAMS}
        check_choices(p)
        # rclpy ignores, silently, a name the node does not declare and a file whose sections are for other nodes
        for said in not_parameters(getattr(self, "_parameter_overrides", {})):  # every -p and file value for this node
            self.get_logger().warning(said)
        for path in params_files:
            if (said := params_file_misses(path, self.get_fully_qualified_name())) is not None:
                self.get_logger().warning(said)
        self.params = p
        import torch

        torch.set_num_threads(p["threads"])
        cv2.setNumThreads(p["threads"])
        self.frontend = self._logging_warnings(lambda: Frontend(None, frontend_config(p)))
        self.get_logger().info(f"NM-Net arithmetic: {precision_note(p['nmnet_precision'])}")
        # the calibration as received (camera_info, else the fx..cy parameters); each frame gets it fitted to its size
        self.camera: Camera | None = None
        if p["fx"] > 0 and p["fy"] > 0:
            self.camera = Camera(np.array([[p["fx"], 0, p["cx"]], [0, p["fy"], p["cy"]], [0, 0, 1.0]]))
        self.stats = Stats()
        self._slot: object | None = None
        self._cv = threading.Condition()
        self._running = True
        self._checks = FrameChecks()  # the stream's last stamp and size
        self._warned: dict[str, float] = {}
        self._reset_due = False  # ~/reset: stage 2 forgets the previous frame before the next one

        self._image_type, self._image_topic = (CompressedImage, "image/compressed") if p["use_compressed"] else (Image, "image")
        self._image_sub = None
        self._subscribe_image(reliable=p["qos"] == "reliable")
        self._silent_s = 0  # seconds with image publishers but no frame
        self._unpublished_s = 0  # seconds without any publisher on the image topic
        self._mistyped_s = 0  # seconds with publishers on it, all of another message type
        self._clockless_s = 0  # seconds under use_sim_time without a publisher on /clock
        self._received_before = 0
        self._large_hint = False
        self._frameless_said = False  # frames whose header names no frame: said once
        self._depth_said = p["use_compressed"]  # 16UC1 frames (a depth stream?): said once; compressed ones name no encoding
        # a topic named like image_proc's rectified output: say once if its camera_info is the distorted raw one
        self._rect_hint_due = bool(re.search(r"(^|/|_)rect", self._image_sub.topic_name))
        if is_depth(self._image_sub.topic_name):  # an RGB-D camera's depth, remapped by mistake: 16UC1 reads as mono
            self.get_logger().warning(f"{self._image_sub.topic_name} looks like a depth topic: {DEPTH_ADVICE}")
        # camera_info is small: best effort matches publishers of either kind and loses nothing here
        self._info_sub = self.create_subscription(CameraInfo, "camera_info", self._on_info,
                                                  QoSProfile(depth=10) if p["qos"] == "reliable" else qos_profile_sensor_data)
        self._latched_info_sub = None  # a transient-local one, made when a latched camera_info publisher shows up
        self.pub_matches = self.create_publisher(PointCloud2, "~/matches", 10)
        self.pub_pose = self.create_publisher(PoseWithCovarianceStamped, "~/relative_pose", 10)
        self.pub_debug = self.create_publisher(Image, "~/debug_image", 2)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(Trigger, "~/reset", self._on_reset)
        # health checks and /diagnostics on the steady clock: under use_sim_time with nothing on /clock (a bag
        # played without --clock) a timer on the node's clock never fires, and the node would never say why it is idle
        self.create_timer(1.0, self._tick, clock=Clock(clock_type=ClockType.STEADY_TIME))
        # Two stages on two threads: detection of frame t+1 overlaps matching/NM-Net/pose of frame t
        # (OpenCV and torch release the GIL). Each frame's features are computed once and handed over.
        self._ready: _Detected | None = None
        self._workers = [threading.Thread(target=self._work, name="nmnet-detect", daemon=True),
                         threading.Thread(target=self._relate, name="nmnet-relate", daemon=True)]
        for w in self._workers:
            w.start()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        if self.camera is None:
            self.get_logger().info("waiting for camera_info (or set fx/fy/cx/cy parameters) before processing frames")

    def _logging_warnings(self, build: Callable[[], T]) -> T:
        """``build()``, with the core's Python warnings (weights without a calibrated cut) as this node's log lines."""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = build()
        for w in caught:
            self.get_logger().warning(str(w.message))
        return out

    def _on_set_parameters(self, params: list) -> SetParametersResult:
        """``ros2 param set``: check the new values, rebuild what they change, or refuse with the reason.

        rclpy has already checked types, ranges and read-only; a refused change leaves everything as it was.
        """
        p = {**self.params, **{q.name: q.value for q in params}}
        try:
            check_choices(p)
            self._logging_warnings(lambda: self.frontend.reconfigure(frontend_config(p)))
        except (ValueError, KeyError) as e:  # WeightsError is a ValueError: it names the file
            return SetParametersResult(successful=False, reason=str(e))
        changed = {q.name: q.value for q in params if self.params.get(q.name) != q.value}
        self.params = p
        if changed:
            self.get_logger().info(f"parameters changed: {changed} (from the next frame)")
        return SetParametersResult(successful=True)

    def _on_reset(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """``~/reset`` (std_srvs/Trigger): the next frame starts a new chain, as after a time jump.

        For a back end that re-initialises (relocalisation, a robot carried elsewhere): the next frame's
        relative_pose says "no estimate" instead of relating it to the frame before the call. Stage 2 applies
        it before its next frame, so a frame in flight is never related to a forgotten one.
        """
        with self._cv:
            self._reset_due = True
        self.stats.resets += 1
        self.get_logger().info("reset requested: the next frame starts a new chain")
        response.success, response.message = True, "the next frame starts a new chain (its relative_pose: no estimate)"
        return response

    # -- input ------------------------------------------------------------------------------
    def _subscribe_image(self, reliable: bool) -> None:
        """(Re)create the image subscription with the given reliability."""
        if self._image_sub is not None:
            self.destroy_subscription(self._image_sub)
        qos = QoSProfile(depth=10) if reliable else qos_profile_sensor_data
        self._image_sub = self.create_subscription(self._image_type, self._image_topic, self._on_image, qos)
        self.image_reliable = reliable

    def _follow_latched_info(self) -> None:
        """A camera_info published once, latched (transient local; a static calibration): a volatile subscription
        never gets what was sent before the node started, so subscribe transient local too, as the publisher offers,
        until the calibration is in (later ones reach the first subscription too)."""
        if self._latched_info_sub is not None and self.camera is not None:
            self.destroy_subscription(self._latched_info_sub)
            self._latched_info_sub = None
        if self._latched_info_sub is not None or self.camera is not None:
            return
        latched = [i.qos_profile for i in self.get_publishers_info_by_topic(self._info_sub.topic_name)
                   if i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL]
        if not latched:
            return
        reliable = all(q.reliability == ReliabilityPolicy.RELIABLE for q in latched)
        qos = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)
        self._latched_info_sub = self.create_subscription(  # volatile publishers beside it: not for it, no warning
            CameraInfo, self._info_sub.topic_name, self._on_info, qos,
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=lambda _: None))
        self.get_logger().info(f"{self._info_sub.topic_name} is published latched (transient local): subscribing so "
                               "too, for the calibration sent before the node started")

    def _tick(self) -> None:
        """Every second: follow the image publishers' reliability (qos auto) and a latched camera_info, say when
        frames stop, diagnostics."""
        self._follow_latched_info()
        topic = self._image_sub.topic_name
        compressed = self.params["use_compressed"]  # read-only: the subscription's type for the node's life
        ours = IMAGE_TYPES[compressed]
        publishers = self.get_publishers_info_by_topic(topic)
        offers = [i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in publishers if i.topic_type == ours]
        others = [i.topic_type for i in publishers if i.topic_type != ours]  # DDS delivers them nothing
        self._mistyped_s = self._mistyped_s + 1 if others and not offers else 0
        if self._mistyped_s:
            self._warn_lasting("wrong_type", self._mistyped_s - 1, 30, lambda: (
                mistyped_advice(topic, others, compressed)))
        want_reliable = follow_reliability(offers)
        if self.params["qos"] == "auto" and want_reliable != self.image_reliable:
            self._subscribe_image(want_reliable)
            self.get_logger().info(f"image publishers on {topic}: {sum(offers)} of {len(offers)} reliable; subscribing "
                                   + ("reliable" if self.image_reliable else "best effort"))
        self._unpublished_s = 0 if offers or others else self._unpublished_s + 1
        if self._unpublished_s >= 10:
            self._warn_lasting("no_publisher", self._unpublished_s - 10, 60, lambda: (
                f"no publisher on {topic} for {self._unpublished_s} s: " + where_are_the_images(
                    self.get_topic_names_and_types(), {topic, self.pub_debug.topic_name}, compressed)))
        self._silent_s = self._silent_s + 1 if offers and self.stats.received == self._received_before else 0
        self._received_before = self.stats.received
        if self._silent_s >= 5:
            self._warn_lasting("no_frames", self._silent_s - 5, 30, lambda: (
                f"{len(offers)} publisher(s) on {topic} but no frame for {self._silent_s} s: "
                + silence_advice(self.image_reliable, offers)))
        self._check_clock()
        self._publish_diagnostics()

    def _check_clock(self) -> None:
        """Under use_sim_time the node's clock is /clock's: say when nothing publishes it (a bag played without
        --clock), as the clock then stands at 0 and so do /diagnostics' stamps and stamp_source arrival's."""
        sim = self.get_parameter("use_sim_time").value
        self._clockless_s = self._clockless_s + 1 if sim and self.count_publishers("/clock") == 0 else 0
        if self._clockless_s >= 5:
            self._warn_lasting("no_clock", self._clockless_s - 5, 60, lambda: (
                f"use_sim_time is true but nothing has published /clock for {self._clockless_s} s: the node's clock "
                f"stands at {self.get_clock().now().nanoseconds * 1e-9:.3f} s, which /diagnostics' stamps"
                + (" and every frame's (stamp_source arrival) carry" if self.params["stamp_source"] == "arrival" else " carry")
                + "; play the bag with `ros2 bag play --clock` or start the simulator's clock, else use_sim_time:=false"))

    def _warn(self, key: str, text: str, period: float = 5.0) -> None:
        """Warning counted per kind in diagnostics; the same message (numbers aside) at most once per period."""
        self._count(key)
        now = time.monotonic()
        throttle = key + re.sub(r"[\d.]+", "#", text)
        if now - self._warned.get(throttle, -1e9) >= period:
            self._warned[throttle] = now
            self.get_logger().warning(f"{text} [{key}: {self.stats.warnings[key]} so far]")

    def _warn_lasting(self, key: str, seconds: int, first: int, text: Callable[[], str]) -> None:
        """A condition that has lasted ``seconds`` (0: it just began), checked once a second: counted every
        time, logged when :func:`lasting_warning_due`; ``text`` (which may query the graph) is built only then."""
        if lasting_warning_due(seconds, first):
            self._warn(key, text(), period=0.0)
        else:
            self._count(key)

    def _count(self, key: str) -> None:
        """One more warning of this kind in diagnostics (``warn_<key>``)."""
        self.stats.warnings[key] = self.stats.warnings.get(key, 0) + 1
        self.stats.last_warned[key] = time.monotonic()

    def _on_info(self, msg: CameraInfo) -> None:
        try:
            cam = camera_from_info(msg, self.params["rectified"])
        except (CameraError, ValueError) as e:
            self._warn("bad_camera_info", f"ignoring camera_info: {e} (calibrate the camera with camera_calibration, "
                                          "or set the fx/fy/cx/cy parameters)")
            return
        if self._rect_hint_due and not self.params["rectified"] and np.any(cam.dist):
            self._rect_hint_due = False
            self.get_logger().warning(f"{self._image_sub.topic_name} looks rectified but camera_info has lens distortion, "
                                      "which would be removed twice: set rectified:=true if these frames are rectified")
        if self.camera is None:
            self.get_logger().info(f"camera_info received: fx={cam.K[0, 0]:.1f} fy={cam.K[1, 1]:.1f} {cam.width}x{cam.height}")
        self.camera = cam

    def _on_image(self, msg) -> None:
        """Executor callback: O(1), puts the message in the latest-frame slot."""
        self.stats.received += 1
        if self.params["stamp_source"] == "arrival":  # a driver that does not stamp: the time it arrives, now
            msg.header.stamp = self.get_clock().now().to_msg()
        if not self.image_reliable and not self._large_hint and len(msg.data) > LARGE_FRAME_BYTES:
            self._large_hint = True  # said once: with a large-frames profile on the camera's side they all arrive
            self.get_logger().info(f"frames of {len(msg.data) / 1e6:.1f} MB on a best-effort subscription: "
                                   f"{large_frames_advice()}")
        if not self._depth_said:
            self._depth_said = True  # the stream's encoding does not change: the first frame tells
            if note := depth_encoding_note(self._image_sub.topic_name, msg.encoding):
                self.get_logger().warning(note)
        if not msg.header.frame_id and not self._frameless_said:
            self._frameless_said = True  # a driver setting: said once, not a fault of each frame
            self.get_logger().warning(f"frames on {self._image_sub.topic_name} name no frame (empty header.frame_id): "
                                      "~/relative_pose and ~/matches carry their header, so tf2 and a back end cannot "
                                      "tell which camera they belong to; set the camera driver's frame_id (its optical "
                                      "frame, e.g. camera_optical_frame)")
        with self._cv:
            if self._slot is not None:
                self.stats.dropped += 1
            self._slot = msg
            self._cv.notify_all()

    # -- work -------------------------------------------------------------------------------
    def _work(self) -> None:
        """Stage 1: take the latest frame, check, decode, detect, match to the frame before; hand over to stage 2
        (waits while it is busy, so stage 2 gets every frame stage 1 prepared, in order)."""
        while self._running:
            with self._cv:
                while self._slot is None and self._running:
                    self._cv.wait(0.2)
                msg, self._slot = self._slot, None
            if msg is None:
                continue
            try:
                det = self._detect(msg)
            except Exception as e:  # noqa: BLE001 - the node must survive any one frame
                self._skipped(e)
                continue
            if det is None:
                continue
            with self._cv:
                while self._ready is not None and self._running:
                    self._cv.wait(0.2)
                self._ready = det
                self._cv.notify_all()

    def _relate(self) -> None:
        """Stage 2: NM-Net and pose against the previous frame, publish."""
        while self._running:
            with self._cv:
                while self._ready is None and self._running:
                    self._cv.wait(0.2)
                det, self._ready = self._ready, None
                self._cv.notify_all()
            if det is None:
                continue
            try:
                self._finish(det)
            except Exception as e:  # noqa: BLE001 - the node must survive any one frame
                self._skipped(e)

    def _skipped(self, e: Exception) -> None:
        """A frame an unexpected error stopped: warned and counted, and the node goes on. Not while shutting down:
        a stop signal ends ROS at once, so the frame then in flight fails to publish; the workers just end."""
        if not self.context.ok():
            self._running = False
            return
        self._warn("internal_error", f"frame skipped after an unexpected error: {type(e).__name__}: {e}")

    def _detect(self, msg) -> _Detected | None:
        t_recv = time.perf_counter()
        if self.camera is None:
            self._warn("no_camera_info", "no camera_info yet and no fx/fy/cx/cy parameters: frame skipped")
            return None
        stamp = stamp_seconds(msg.header.stamp)
        go_on, said = self._checks.stamp(stamp, self.frontend.config["time_jump_s"])
        if said is not None:
            self._warn(said.kind, said.text)
        if not go_on:
            return None
        t = time.perf_counter()
        try:
            cam = self.camera
            img = decode_message(msg, pixel_cap(self.params["max_image_pixels"], (cam.width, cam.height)))
        except ImageError as e:
            self._warn("bad_image", f"bad image message skipped: {e}")
            return None
        t_dec = time.perf_counter()
        cam, said = self._checks.camera(self.camera, (img.shape[1], img.shape[0]), stamp)
        for r in said:
            self._warn(r.kind, r.text)
        if cam is None:
            return None
        self.frontend.camera = cam
        return _Detected(msg.header, img, self.frontend.prepare(img), stamp, {"decode": 1000 * (t_dec - t)}, t_recv)

    def _finish(self, d: _Detected) -> None:
        with self._cv:
            reset, self._reset_due = self._reset_due, False
        if reset:
            self.frontend.reset()
        result = self.frontend.process_prepared(d.prepared, d.stamp, d.timings)
        self.stats.processed += 1
        self._publish(d.header, d.img, result)
        self.stats.latency_ms.append(1000 * (time.perf_counter() - d.t_recv))
        for k, v in result.timings_ms.items():
            self.stats.stage_ms.setdefault(k, deque(maxlen=100)).append(v)

    # -- output -----------------------------------------------------------------------------
    def _publish(self, header, img: np.ndarray, r: FrameResult) -> None:
        s = self.stats
        s.last_status, s.last_matches, s.last_selected, s.last_keypoints = r.status, len(r.k0), r.num_selected, r.num_keypoints
        s.last_continued = r.tracks_continued
        if r.status == "too_few_matches":
            self._warn("too_few_matches", f"only {r.num_selected} matches selected of {len(r.k0)} (need min_matches = "
                                             f"{self.frontend.config['min_matches']}): relative_pose says no estimate")
        elif r.status == "no_motion":
            self._warn("no_motion", "no baseline (the camera stands or turns on the spot; static_flow_px, "
                                    "static_parallax_px): publishing its rotation alone, with zero translation", period=30.0)
        elif r.status == "pose_failed":
            self._warn("pose_failed", "pose estimation failed on the selected matches")
        elif r.plane_ambiguous:
            self._warn("plane_ambiguous", PLANE_NOTE, period=30.0)
        sel = r.mask
        cloud = PointCloud2(header=header)
        f = matches_to_cloud_fields(r.k0[sel], r.k1[sel], r.scores[sel], r.track_ids[sel])
        cloud.height, cloud.width, cloud.point_step, cloud.row_step = f["height"], f["width"], f["point_step"], f["row_step"]
        cloud.is_bigendian, cloud.is_dense = f["is_bigendian"], f["is_dense"]
        cloud.fields = [PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in f["fields"]]
        cloud.data = f["data"]
        self.pub_matches.publish(cloud)
        pose_msg = PoseWithCovarianceStamped(header=header)
        q, t, cov = relative_pose_of_current(r.status, r.pose, r.pose_matches, pose_sigmas(self.params))
        pose_msg.pose.pose.position.x, pose_msg.pose.pose.position.y, pose_msg.pose.pose.position.z = (float(v) for v in t)
        o = pose_msg.pose.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in q)
        pose_msg.pose.covariance = [float(v) for v in cov.ravel()]
        self.pub_pose.publish(pose_msg)
        if r.status in ("ok", "no_motion"):
            s.estimated += 1
        if self.params["publish_debug_image"] and self.pub_debug.get_subscription_count() > 0:
            dbg = Image(header=header)
            for k, v in array_to_image_fields(draw_matches(img, r.k0, r.k1, r.mask)).items():
                setattr(dbg, k, v)
            self.pub_debug.publish(dbg)

    def _publish_diagnostics(self) -> None:
        s = self.stats
        elapsed = max(time.monotonic() - s.t_start, 1e-9)
        lat = np.array(s.latency_ms) if s.latency_ms else np.zeros(1)
        values = {
            "frames_received": s.received, "frames_processed": s.processed, "frames_dropped": s.dropped,
            "poses_estimated": s.estimated, "chain_resets": s.resets, "rate_hz": round(s.processed / elapsed, 3),
            "latency_p50_ms": round(float(np.percentile(lat, 50)), 1), "latency_p90_ms": round(float(np.percentile(lat, 90)), 1),
            "input_qos": "reliable" if self.image_reliable else "best_effort",
            "keypoints": s.last_keypoints, "matches": s.last_matches, "selected": s.last_selected,
            "tracks_continued": s.last_continued, "last_status": s.last_status,
            **{f"stage_{k}_ms": round(float(np.median(v)), 1) for k, v in dict(s.stage_ms).items()},
            **{f"warn_{k}": v for k, v in dict(s.warnings).items()},  # a copy: the worker threads add kinds
        }
        # named as diagnostic_updater names a task, with the namespace: a robot's cameras' front ends stay apart
        me = self.get_fully_qualified_name()
        st = DiagnosticStatus(name=f"{me.lstrip('/')}: front end", hardware_id=me)
        st.level, st.message = health(dict(s.last_warned), time.monotonic(), s.last_status)
        st.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        arr = DiagnosticArray(status=[st])
        arr.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(arr)

    def stop(self) -> None:
        """Stop the worker threads."""
        self._running = False
        with self._cv:
            self._cv.notify_all()
        for w in self._workers:
            w.join(timeout=5.0)


def params_files_of(argv: list[str]) -> tuple[str, ...]:
    """The ``--params-file`` values among the ROS arguments (after ``--ros-args``, up to a ``--``)."""
    if "--ros-args" not in argv:
        return ()
    ros = argv[argv.index("--ros-args") + 1:]
    ros = ros[:ros.index("--")] if "--" in ros else ros
    return tuple(ros[i + 1] for i, a in enumerate(ros[:-1]) if a == "--params-file")


def main(args: list[str] | None = None) -> int:
    """Entry point of ``nmnet_node`` / ``python -m nmnet_ros.node``."""
    argv = sys.argv if args is None else args
    try:
        rclpy.init(args=argv)
    except RuntimeError as e:  # RCLError: rcl could not read the arguments after --ros-args
        print(f"nmnet_node: error: {rcl_arguments_error(str(e))}", file=sys.stderr)
        return 2
    node = None
    try:
        node = NMNetNode(params_files_of(argv))
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:  # rclpy's RCLError "context is not valid": a SIGTERM/SIGINT shut the context down
        if rclpy.ok():     # between two waits of the executor (the race of ros2/ros2cli#854); anything else is a real failure
            raise
    except (ValueError, ParameterException) as e:  # rclpy checks types and ranges when the node declares them
        print(f"nmnet_node: error: {e} (parameters, types and ranges: nmnet_node --help)", file=sys.stderr)
        return 2
    finally:
        if node is not None:
            node.stop()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0

