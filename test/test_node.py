"""The node as users start it (own process), over real DDS isolated per test run."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from contextlib import contextmanager

import cv2
import numpy as np
import pytest

from nmnet_ros.core.geometry import rotation_error_deg
from nmnet_ros.interface.imgconv import matches_of_cloud
from nmnet_ros.interface.params import read_params_file
from nmnet_ros.io.datasets import Sequence

from .conftest import ROOT, data_dir, planar_views
from .rosharness import NodeProcess, camera_info_msg, compressed_msg, image_msg, launch_node_args, ros_env, spin_until, unique_domain

rclpy = pytest.importorskip("rclpy")


def quat_to_rot(q):
    from nmnet_ros.core.geometry import quat_to_rot as q2r

    return q2r(q)


class Peer:
    """The test's own rclpy node: publishes camera data, records the node's outputs."""

    def __init__(self, ns: str = "/nmnet_node", image_topic: str = "image", compressed: bool = False,
                 info_topic: str = "camera_info", reliable: bool = False) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from rclpy.qos import QoSProfile, qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

        self.node = rclpy.create_node(f"test_peer_{unique_domain()}")
        mtype = CompressedImage if compressed else Image
        qos = QoSProfile(depth=10) if reliable else qos_profile_sensor_data
        self.pub_img = self.node.create_publisher(mtype, image_topic + ("/compressed" if compressed else ""), qos)
        self.pub_info = self.node.create_publisher(CameraInfo, info_topic, qos)
        self.poses: list = []
        self.matches: list = []
        self.diag: list = []
        self.node.create_subscription(PoseWithCovarianceStamped, f"{ns}/relative_pose",
                                      lambda m: self.poses.append((time.monotonic(), m)), 50)
        self.node.create_subscription(PointCloud2, f"{ns}/matches", lambda m: self.matches.append((time.monotonic(), m)), 50)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: self.diag.append(m), 50)

    def wait_connected(self, timeout: float = 30.0) -> None:
        ok = spin_until(self.node, lambda: self.pub_img.get_subscription_count() > 0 and self.pub_info.get_subscription_count() > 0,
                        timeout)
        assert ok, "the node did not subscribe to the image and camera_info topics"
        spin_until(self.node, lambda: False, 0.5)  # first messages after discovery can be lost

    def diag_values(self) -> dict[str, str]:
        return {kv.key: kv.value for kv in self.diag[-1].status[0].values} if self.diag else {}

    def wait_processed(self, n: int, timeout: float = 30.0) -> bool:
        return spin_until(self.node, lambda: int(self.diag_values().get("frames_processed", 0)) >= n, timeout)

    def count(self, key: str) -> int:
        return int(self.diag_values().get(key, 0))

    def first_frame(self, info, msg, tries: int = 5, timeout: float = 60.0) -> None:
        """Publish camera_info then the first image until the node has processed one frame.

        Two things can legitimately cost the first frame: the image overtaking the camera_info (they are
        separate topics, so the node skips it and warns ``no_camera_info``), and a best-effort message lost
        right after discovery. Both are retried (same message; nothing was processed, so the node's state is
        unchanged); a frame the node did receive and is working on is waited for, never sent twice. Its outputs are
        waited for too: a first frame relates to nothing, so its ~/relative_pose says "no estimate" and its
        ~/matches is empty, and a back end has the stamp of every pair's previous frame from the messages before.
        """
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        for _ in range(tries):
            self.pub_info.publish(info)
            spin_until(self.node, lambda: False, 0.3)
            received, skipped = self.count("frames_received"), self.count("warn_no_camera_info")
            self.pub_img.publish(msg)
            spin_until(self.node, lambda s=skipped: self.count("frames_processed") >= 1 or self.count("warn_no_camera_info") > s,
                       4.0)
            if self.count("frames_processed") < 1:
                if self.count("warn_no_camera_info") > skipped or self.count("frames_received") <= received:
                    continue  # skipped before camera_info arrived, or lost: send again
                assert self.wait_processed(1, timeout), "the node received the first frame but never processed it"
            assert no_estimate(self.pose_for(stamp)), "the first frame's relative_pose is not 'no estimate'"
            assert self.wait_result_for(stamp) and self.matches[0][1].width == 0, "the first frame has matches"
            return
        raise AssertionError(f"the first frame was not processed after {tries} tries (camera_info + image)")

    def stamps(self, items) -> list[float]:
        return [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for _, m in items]

    def wait_result_for(self, stamp: float, timeout: float = 30.0) -> bool:
        return spin_until(self.node, lambda: any(abs(s - stamp) < 1e-6 for s in self.stamps(self.matches)), timeout)

    def pose_for(self, stamp: float, timeout: float = 10.0):
        """The relative_pose message of the frame stamped ``stamp`` (None if none comes)."""
        def find():
            return next((m for _, m in self.poses if abs(m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec - stamp) < 1e-6), None)
        spin_until(self.node, lambda: find() is not None, timeout)
        return find()

    def close(self) -> None:
        self.node.destroy_node()


@contextmanager
def node_and_peer(ros: dict, tmp_path, node_args: list[str], stop: int = signal.SIGTERM, **peer_args):
    """``python -m nmnet_ros.node`` with ``node_args`` (log in tmp_path) and a :class:`Peer`; yields (node, peer).

    Both are stopped on leaving (the node by ``stop``), so ``node.output()`` is complete after the block; when the
    block succeeded, the node must have exited cleanly, without an unexpected error on the way.
    """
    node = NodeProcess(node_args, ros, tmp_path / "node.log")
    peer = Peer(**peer_args)
    try:
        yield node, peer
    finally:
        peer.close()
        code = node.stop(stop)
    assert code == 0, f"the node exited with {code}:\n{node.output()}"
    assert "unexpected error" not in node.output(), node.output()


def no_estimate(msg) -> bool:
    """A relative pose that says "no estimate": the identity, variance NO_ESTIMATE_VAR on every axis."""
    from nmnet_ros.interface.posemsg import NO_ESTIMATE_VAR

    o, p = msg.pose.pose.orientation, msg.pose.pose.position
    return (o.x, o.y, o.z, o.w, p.x, p.y, p.z) == (0, 0, 0, 1, 0, 0, 0) and \
        np.array_equal(np.asarray(msg.pose.covariance).reshape(6, 6), np.eye(6) * NO_ESTIMATE_VAR)


@pytest.fixture
def ros(tmp_path):
    """An isolated ROS context in this process plus the env for the node process."""
    env = ros_env(unique_domain())
    import os

    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    rclpy.init()
    yield env
    rclpy.try_shutdown()
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


def send_lockstep(peer: Peer, seq: Sequence, frames, make_msg, info) -> None:
    """Publish frames one at a time, each after the previous one's result arrived."""
    for n, i in enumerate(frames):
        stamp = float(seq.stamps[i]) + 1.0
        if n == 0:
            peer.first_frame(info, make_msg(seq.image(i), stamp))
            continue
        peer.pub_info.publish(info)
        peer.pub_img.publish(make_msg(seq.image(i), stamp))
        assert peer.wait_result_for(stamp), f"no result for frame {i}"


def check_kitti_run(peer: Peer, seq: Sequence, frames, network: bool = True) -> np.ndarray:
    spin_until(peer.node, lambda: len(peer.poses) >= len(frames), 5.0)  # the pose follows the matches
    assert len(peer.matches) == len(frames) and len(peer.poses) == len(frames)  # one each per frame, the first's empty
    errs = []
    for (_, pose), i in zip(peer.poses[1:], frames[1:], strict=True):
        o = pose.pose.pose.orientation
        R_pc = quat_to_rot([o.x, o.y, o.z, o.w])
        R_gt, _ = seq.relative_pose(i - 1, i)
        errs.append(rotation_error_deg(R_pc, R_gt.T))
    print("rotation errors (deg):", np.round(errs, 3))
    assert np.mean(np.array(errs) < 2.0) >= 0.9
    m = peer.matches[-1][1]
    assert [f.name for f in m.fields] == ["u0", "v0", "u1", "v1", "score", "track_id"] and m.width > 50
    scores = matches_of_cloud(m.point_step, m.fields, m.data)["score"]
    # tracks: a match continues the previous message's match whose current keypoint is its previous one, by id
    before, now = (matches_of_cloud(c.point_step, c.fields, c.data) for _, c in peer.matches[-2:])
    ids_at = {(u, v): t for u, v, t in zip(before["u1"], before["v1"], before["track_id"], strict=True)}
    went_on = [(ids_at[u, v], t) for u, v, t in zip(now["u0"], now["v0"], now["track_id"], strict=True) if (u, v) in ids_at]
    print(f"tracks: {len(went_on)} of {m.width} matches continue one of the {len(ids_at)} before")
    assert len(went_on) > 0.3 * m.width and all(a == b for a, b in went_on) and len(set(now["track_id"])) == m.width
    # /diagnostics says how many of the last frame's matches continue a track, for a monitor to see tracking break down
    assert spin_until(peer.node, lambda: peer.count("frames_processed") == len(frames) and
                      peer.count("tracks_continued") == len(went_on), 5.0), (peer.diag_values(), len(went_on))
    if network:
        # NM-Net probabilities, not a 0/1 mask; the default samples the confident ones first, and most of its inliers are
        assert scores.min() >= 0.0 and scores.max() <= 1.0 and len(np.unique(scores)) > 1 and np.median(scores) > 0.5
    else:
        assert np.all(scores == 1.0)  # no network: the published score is the selection itself
    return np.array(errs)


def kitti_info(seq: Sequence):
    return camera_info_msg(seq.camera.K, seq.camera.dist, seq.camera.width, seq.camera.height)


# the raw run starts the node as the shipped launch file does (params file, remaps, node name), in a namespace as
# one of a robot's several cameras: its outputs and its diagnostics' name are the namespace's
LAUNCH = ROOT / "launch" / "nmnet.launch.xml"
RAW = (launch_node_args(LAUNCH, {"image": "/cam/image_raw", "camera_info": "/cam/camera_info", "namespace": "front"}),
       {"image_topic": "/cam/image_raw", "info_topic": "/cam/camera_info", "ns": "/front/nmnet_node"}, image_msg, range(40, 60),
       signal.SIGTERM)
# the compressed run also exercises the network-free pose_estimator
COMPRESSED = (["-p", "use_compressed:=true", "-p", "pose_estimator:=classic"], {"compressed": True}, compressed_msg, range(100, 120),
              signal.SIGINT)


@pytest.mark.parametrize("node_args, peer_args, make_msg, frames, stop_signal", [RAW, COMPRESSED], ids=["raw-remapped", "compressed"])
def test_twenty_kitti_frames(ros, tmp_path, node_args, peer_args, make_msg, frames, stop_signal):
    """20 frames + CameraInfo -> 20 matches and 20 poses (the first empty), rotation error < 2 deg on >= 90 %; clean
    shutdown."""
    seq = Sequence.load(data_dir("kitti-07"))
    with node_and_peer(ros, tmp_path, ["--ros-args", *node_args], stop_signal, **peer_args) as (node, peer):
        peer.wait_connected()
        send_lockstep(peer, seq, list(frames), make_msg, kitti_info(seq))
        check_kitti_run(peer, seq, list(frames), network="pose_estimator:=classic" not in node_args)
        ns = peer_args.get("ns", "/nmnet_node")
        assert {(st.name, st.hardware_id) for st in peer.diag[-1].status} == {(f"{ns[1:]}: front end", ns)}
    assert "Traceback" not in node.output()


def wait_diag(peer: Peer, key: str, at_least: int, timeout: float = 30.0) -> bool:
    return spin_until(peer.node, lambda: int(peer.diag_values().get(key, 0)) >= at_least, timeout)


def test_bad_input_is_survived_and_counted(ros, tmp_path):
    seq = Sequence.load(data_dir("kitti-07"))
    img0, img1, img2 = seq.image(60), seq.image(61), seq.image(62)
    info = kitti_info(seq)
    with node_and_peer(ros, tmp_path, []) as (node, peer):
        peer.wait_connected()
        bad_k = kitti_info(seq)
        bad_k.k = [0.0] * 9
        peer.pub_info.publish(bad_k)
        assert wait_diag(peer, "warn_bad_camera_info", 1)
        peer.pub_img.publish(image_msg(img0, 1.0))  # no valid intrinsics yet: waits, says so
        assert wait_diag(peer, "warn_no_camera_info", 1)
        nan_k = kitti_info(seq)
        nan_k.k = [float("nan")] * 9
        peer.pub_info.publish(nan_k)
        assert wait_diag(peer, "warn_bad_camera_info", 2)
        fov = kitti_info(seq)
        fov.distortion_model, fov.d = "fov", [0.9]  # a lens model the node cannot undistort
        peer.pub_info.publish(fov)
        assert wait_diag(peer, "warn_bad_camera_info", 3)
        peer.pub_info.publish(info)
        spin_until(peer.node, lambda: False, 0.5)
        assert "K all zero)? (calibrate the camera with camera_calibration, or set the fx/fy/cx/cy parameters)" in \
            node.output(), node.output()  # what to do, not only what is wrong

        bad = [image_msg(img0, 2.0, encoding="yuv422_weird")]  # wrong encoding string
        short = image_msg(img0, 2.1)
        short.data = bytes(short.data[: len(short.data) // 2])  # shorter than height*step
        empty = image_msg(np.zeros((0, 0), np.uint8), 2.2)  # 0x0
        for n, msg in enumerate([*bad, short, empty], start=1):
            peer.pub_info.publish(info)  # as drivers do, with every frame
            peer.pub_img.publish(msg)
            assert wait_diag(peer, "warn_bad_image", n), f"bad image {n} not reported"

        peer.first_frame(info, image_msg(img0, 10.0))
        peer.pub_img.publish(image_msg(img1, 10.0))  # duplicate stamp
        assert wait_diag(peer, "warn_duplicate_stamp", 1)
        peer.pub_img.publish(image_msg(img1, 9.0))  # out of order
        assert wait_diag(peer, "warn_out_of_order_stamp", 1)
        peer.pub_img.publish(image_msg(img1, 11.0))
        assert peer.wait_result_for(11.0)
        n_poses = len(peer.poses)

        peer.pub_img.publish(image_msg(img1, 12.0))  # static camera: same view again
        assert wait_diag(peer, "warn_no_motion", 1)
        spin_until(peer.node, lambda: len(peer.poses) > n_poses, 5.0)
        o, p = peer.poses[-1][1].pose.pose.orientation, peer.poses[-1][1].pose.pose.position
        # the same view: the rotation fitted alone is the identity (to rounding), zero translation; not a garbage pose
        assert abs(o.w - 1.0) < 1e-12 and (p.x, p.y, p.z) == (0.0, 0.0, 0.0), (o, p)

        peer.pub_img.publish(image_msg(np.full_like(img1, 90), 13.0))  # textureless: < 8 matches
        assert wait_diag(peer, "warn_too_few_matches", 1)
        small = np.ascontiguousarray(img1[:, :600])
        peer.pub_img.publish(image_msg(small, 14.0))  # frame size changes
        assert wait_diag(peer, "warn_size_changed", 1)

        peer.pub_img.publish(image_msg(img1, 15.0))  # back to the camera's size, then good frames
        assert wait_diag(peer, "warn_size_changed", 2)
        peer.pub_img.publish(image_msg(img2, 16.0))
        assert peer.wait_result_for(16.0), "node did not recover after bad input"
        # every processed frame after the first has a relative pose, each relative to the frame of the one before,
        # so a back end chaining them never bridges a gap: the textureless frame (13) and the next processed one,
        # matched against it (15), say "no estimate"; 14 (a size its camera_info does not fit) was skipped, not
        # processed: no message; 16 is relative to 15
        assert no_estimate(peer.pose_for(13.0)) and no_estimate(peer.pose_for(15.0)) and peer.pose_for(14.0, 0.5) is None
        assert not no_estimate(peer.pose_for(16.0)) and peer.pose_for(16.0).pose.covariance[0] < 1.0
        big = image_msg(img2.astype(np.uint16) << 4, 20.0)  # 0.9 MB on best effort: some arrive, the node says why not all
        for n in range(50):
            big.header.stamp.sec = 20 + n
            peer.pub_img.publish(big)
            if spin_until(peer.node, lambda: "on a best-effort subscription" in node.output(), 0.2):
                break
        # a half-size stream with the full-size camera_info: K is scaled to fit, and said so
        small = [cv2.resize(im, (613, 185), interpolation=cv2.INTER_AREA) for im in (img1, img2)]
        for n in range(10):  # best effort right after the large frames may lose one: send until a pair is related
            peer.pub_img.publish(image_msg(small[n % 2], 80.0 + n))
            if peer.wait_result_for(80.0 + n, timeout=3.0):
                break
        else:
            raise AssertionError("no result for half-size frames")
        # the bag starts over (ros2 bag play --loop): the node restarts its chain instead of skipping every frame
        peer.pub_img.publish(image_msg(img1, 1.0))
        assert wait_diag(peer, "warn_time_jump", 1)
        peer.pub_img.publish(image_msg(img2, 2.0))
        assert peer.wait_result_for(2.0), "no result after the stamps started over"
        assert no_estimate(peer.pose_for(1.0)) and not no_estimate(peer.pose_for(2.0))
        for _ in range(2):  # a driver that does not stamp: 0 is a jump back, then a duplicate, said so
            peer.pub_img.publish(image_msg(img2, 0.0))
            spin_until(peer.node, lambda: False, 0.3)
        assert wait_diag(peer, "warn_duplicate_stamp", 2)
        peer.pub_img.publish(image_msg(img2, -2.0))  # not a ROS time (a bag restamped too far back)
        assert wait_diag(peer, "warn_negative_stamp", 1)
        st = peer.diag[-1].status[0]  # the level follows what went wrong lately (the counters keep everything)
        assert st.level == st.WARN and st.message.startswith("warnings in the last 10 s: ") and "negative_stamp" in st.message
        assert node.alive()
    out = node.output()
    assert "Traceback" not in out
    for needle in ("unsupported image encoding", "truncated", "0x0", "focal lengths", "NaN", "duplicate_stamp",
                   "distortion model 'fov' is not supported; use one of plumb_bob, rational_polynomial, equidistant",
                   "out_of_order_stamp", "no baseline (the camera stands or turns on the spot", "frame size changed",
                   "frames of 0.9 MB on a best-effort subscription",
                   "FASTDDS_DEFAULT_PROFILES_FILE=", "600x370 but camera_info describes 1226x370, which is not the same image scaled",
                   "613x185 but camera_info describes 1226x370: K scaled by 0.5 to fit",
                   "s before the previous one (a bag played in a loop, or the clock was reset): restarting",
                   "skipped (a stamp of 0: does the camera driver stamp its frames? If not, stamp_source:=arrival stamps "
                   "them on arrival)",
                   "frame stamp -2.000000 is negative: skipped (ROS time starts at 0"):
        assert needle in out, f"no clear warning containing {needle!r}:\n{out}"


def test_a_camera_before_a_plane_is_said_in_diagnostics_and_its_covariance(ros, tmp_path):
    """Views of a plane (a wall, flat ground): the node counts warn_plane_ambiguous in /diagnostics and its
    ~/relative_pose carries a direction sigma that reaches the plane's other pose (above 0.3; 0.02-0.05 with depth)."""
    cam, views = planar_views(seed=5, frames=3)
    info = camera_info_msg(cam.K, cam.dist, cam.width, cam.height)
    mono = [cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) for img, _ in views]  # 393 KB: a 1.2 MB bgr8 frame is often lost
    with node_and_peer(ros, tmp_path, ["--ros-args", "-p", "max_keypoints:=1000"]) as (_, peer):  # on best effort
        peer.wait_connected()
        peer.first_frame(info, image_msg(mono[0], 1.0))
        for k in (1, 2):
            peer.pub_info.publish(info)
            peer.pub_img.publish(image_msg(mono[k], 1.0 + 0.1 * k))
            msg = peer.pose_for(1.0 + 0.1 * k, timeout=30.0)
            assert msg is not None and 0.3 < np.sqrt(msg.pose.covariance[0]) < 1.0, k
        assert wait_diag(peer, "warn_plane_ambiguous", 2), peer.diag_values()


def test_the_diagnostics_level_is_warn_while_warnings_are_recent_and_ok_again_after():
    """A transient fault (a camera_info that came after the first frame, one corrupt image) used to leave the node
    WARN for good, so a robot monitor showed it faulty all day; the level now follows the last 10 s. no_motion (a
    robot that waits or turns in place) is counted but is not a fault."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from nmnet_ros.ros.node import health

    assert health({}, 100.0, "ok") == (DiagnosticStatus.OK, "ok")
    assert health({"bad_image": 91.0, "no_camera_info": 2.0}, 100.0, "ok") == (
        DiagnosticStatus.WARN, "warnings in the last 10 s: bad_image")
    assert health({"bad_image": 89.0, "no_camera_info": 2.0}, 100.0, "ok") == (DiagnosticStatus.OK, "ok")
    assert health({"no_motion": 99.0}, 100.0, "no_motion") == (DiagnosticStatus.OK, "no_motion")


def test_corrupt_jpeg_is_skipped(ros, tmp_path):
    seq = Sequence.load(data_dir("kitti-07"))
    with node_and_peer(ros, tmp_path, ["--ros-args", "-p", "use_compressed:=true"], signal.SIGINT, compressed=True) as (node, peer):
        peer.wait_connected()
        good = compressed_msg(seq.image(70), 1.0)
        corrupt = compressed_msg(None, 0.5, data=bytes(good.data[:200]) + b"\x00" * 50)
        for _ in range(3):  # camera_info first (on its own topic it may arrive after an image sent right behind it)
            peer.pub_info.publish(kitti_info(seq))
            spin_until(peer.node, lambda: False, 0.3)
            peer.pub_img.publish(corrupt)
            if wait_diag(peer, "warn_bad_image", 1, timeout=5.0):
                break
        assert peer.count("warn_bad_image") == 1
        peer.first_frame(kitti_info(seq), good)
        peer.pub_img.publish(compressed_msg(seq.image(71), 2.0))
        assert peer.wait_result_for(2.0)
    assert "cannot decode compressed image" in node.output()


def peak_rss_mb(pid: int) -> float:
    """The process's peak resident memory so far (VmHWM), in MB."""
    line = next(ln for ln in open(f"/proc/{pid}/status").read().splitlines() if ln.startswith("VmHWM:"))
    return int(line.split()[1]) / 1024


def test_hostile_frames_and_calibrations_cost_little_and_publish_no_pose(ros, tmp_path):
    """Over DDS, the cases the node took before: calibrations that cannot be true (K normalised, binning 1000, an
    roi outside the sensor) were accepted and gave confident poses; a 50 KB PNG decoding to 12260x3700 took the node
    to 2.4 GB; a float PFM ended in internal_error; a stamp with nanosec >= 1e9 was processed. Each is now refused,
    named and counted, no pose is published from it, memory stays bounded, and the next good frame is processed."""
    from sensor_msgs.msg import RegionOfInterest

    seq = Sequence.load(data_dir("kitti-07"))
    with node_and_peer(ros, tmp_path, ["--ros-args", "-p", "use_compressed:=true"], signal.SIGINT, compressed=True) as (node, peer):
        peer.wait_connected()
        normalised, binned, cut = kitti_info(seq), kitti_info(seq), kitti_info(seq)
        normalised.k = [0.577, 0.0, 0.49, 0.0, 1.74, 0.49, 0.0, 0.0, 1.0]
        binned.binning_x = binned.binning_y = 1000
        cut.roi = RegionOfInterest(x_offset=2000, y_offset=0, width=600, height=300)
        for n, info in enumerate((normalised, binned, cut), start=1):
            for _ in range(5):  # best effort: send until it is counted
                peer.pub_info.publish(info)
                if wait_diag(peer, "warn_bad_camera_info", n, timeout=3.0):
                    break
        peer.pub_img.publish(compressed_msg(seq.image(60), 0.5))  # no plausible calibration yet: skipped, said
        assert wait_diag(peer, "warn_no_camera_info", 1)
        assert not peer.poses and not peer.matches
        peer.first_frame(kitti_info(seq), compressed_msg(seq.image(60), 1.0))
        before = peak_rss_mb(node.proc.pid)

        pfm = cv2.imencode(".pfm", seq.image(61)[:120, :160].astype(np.float32) / 255)[1].tobytes()  # a float frame
        hostile = [compressed_msg(None, 2.0, data=cv2.imencode(".png", np.zeros((3700, 12260), np.uint8))[1].tobytes()),
                   compressed_msg(None, 2.1, data=cv2.imencode(".png", np.zeros((7400, 24520), np.uint8))[1].tobytes()),
                   compressed_msg(None, 2.2, data=pfm)]
        for n, msg in enumerate(hostile, start=1):
            for _ in range(5):
                peer.pub_img.publish(msg)
                if wait_diag(peer, "warn_bad_image", n, timeout=3.0):
                    break
            assert peer.count("warn_bad_image") == n, f"hostile frame {n} not refused as bad_image"
        late = compressed_msg(seq.image(61), 3.0)
        late.header.stamp.nanosec = 1_500_000_000  # no ROS time
        peer.pub_img.publish(late)
        assert wait_diag(peer, "warn_invalid_stamp", 1)
        largest = cv2.resize(seq.image(62), (2 * 1226, 2 * 370))  # 4x the calibrated pixels: the most it accepts
        for n in range(5):
            peer.pub_img.publish(compressed_msg(None, 4.0 + n, cv2.imencode(".jpg", largest)[1].tobytes()))
            if peer.wait_result_for(4.0 + n, timeout=10.0):
                break
        else:
            raise AssertionError("the largest accepted frame was not processed")
        peer.pub_img.publish(compressed_msg(seq.image(63), 10.0))  # back to the camera's size: processed
        assert peer.wait_result_for(10.0)
        peak = peak_rss_mb(node.proc.pid)
        print(f"node peak resident memory: {before:.0f} MB after its first frame, {peak:.0f} MB after the hostile "
              "frames and the largest frame it accepts (2452x740, 4x camera_info's pixels)")
        assert peak < 1500, peak
        assert all(m.header.stamp.nanosec < 10**9 for _, m in peer.poses)  # nothing republished with the bad stamp
        assert peer.count("warn_internal_error") == 0
    out = node.output()
    for needle in ("fx = 0.577 px cannot be a 1226x370 camera's", "binning 1000x1000 leaves 1x0 of the 1226x370 sensor",
                   "roi (600x300 at 2000,0) reaches outside", "png frame is 12260x3700 = 45.4 MP, over the cap of 1.8 MP",
                   "neither JPEG nor PNG", "not a ROS time"):
        assert needle in out, f"no clear warning containing {needle!r}:\n{out}"


def test_a_reliable_camera_with_large_raw_frames_is_followed(ros, tmp_path):
    """qos auto subscribes reliable to a reliable camera, so frames over 0.5 MB arrive (best effort loses them).

    The frames are the raw encodings of machine-vision drivers: bgr8 (1.4 MB), a 12-bit camera's
    mono16 (0.9 MB), a Bayer mosaic and NV21.
    """
    seq = Sequence.load(data_dir("kitti-07"))
    with node_and_peer(ros, tmp_path, [], reliable=True) as (node, peer):
        peer.wait_connected()
        assert spin_until(peer.node, lambda: peer.diag_values().get("input_qos") == "reliable", 10.0)
        spin_until(peer.node, lambda: False, 0.5)  # the new subscription's discovery
        colour = [np.dstack([seq.image(i)] * 3) for i in (80, 81)]
        peer.first_frame(kitti_info(seq), image_msg(colour[0], 1.0))
        frames = {2.0: image_msg(colour[1], 2.0), 3.0: image_msg(seq.image(82).astype(np.uint16) << 4, 3.0),
                  4.0: image_msg(seq.image(83), 4.0, encoding="bayer_rggb8")}
        luma = seq.image(84)  # a phone or Jetson camera's semi-planar YUV: luma rows, then half-height chroma rows
        frames[5.0] = image_msg(np.vstack([luma, np.full(((luma.shape[0] + 1) // 2, luma.shape[1]), 128, np.uint8)]),
                                5.0, encoding="nv21")
        frames[5.0].height = luma.shape[0]
        for stamp, msg in frames.items():
            peer.pub_img.publish(msg)
            assert peer.wait_result_for(stamp), f"no result for the {msg.encoding} frame ({len(msg.data)} bytes)"
        assert peer.count("warn_bad_image") == 0 and peer.count("warn_no_frames") == 0
    assert "subscribing reliable" in node.output()


def test_a_calibration_published_once_latched_before_the_node_started_is_received(ros, tmp_path):
    """A static calibration published once on a transient-local (latched) topic before the node subscribed: a
    volatile subscription never sees it, so the node follows the publisher's durability, gets it, and processes."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo

    seq = Sequence.load(data_dir("kitti-07"))
    with node_and_peer(ros, tmp_path, []) as (node, peer):
        latched = peer.node.create_publisher(CameraInfo, "camera_info", QoSProfile(
            depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE))
        latched.publish(kitti_info(seq))  # once, while the node is still starting
        peer.wait_connected()
        for n in range(20):  # frames before the calibration arrives are skipped (no_camera_info): send until related
            peer.pub_img.publish(image_msg(seq.image(80 + n % 2), 1.0 + n))
            if peer.wait_result_for(1.0 + n, timeout=2.0):
                break
        else:
            raise AssertionError("no frame was related: the latched camera_info never arrived")
    out = node.output()
    assert "camera_info is published latched (transient local): subscribing so too" in out, out
    assert "incompatible" not in out, out  # the peer's volatile camera_info publisher is no concern of that subscription


def test_a_camera_the_node_cannot_match_is_explained(ros, tmp_path):
    """A reliable subscription (qos:=reliable) never matches a best-effort camera: the node says so and why."""
    seq = Sequence.load(data_dir("kitti-07"))
    with node_and_peer(ros, tmp_path, ["--ros-args", "-p", "qos:=reliable"], reliable=False) as (node, peer):
        assert spin_until(peer.node, lambda: bool(peer.diag), 30.0), "the node published no diagnostics"
        img = seq.image(90)
        for n in range(60):  # 5 Hz for up to 12 s; the node speaks up after 5 s without a frame
            peer.pub_info.publish(kitti_info(seq))
            peer.pub_img.publish(image_msg(img, 1.0 + n))
            if spin_until(peer.node, lambda: peer.count("warn_no_frames") > 0, 0.2):
                break
        assert peer.count("warn_no_frames") > 0 and peer.count("frames_received") == 0
        assert node.alive()
    out = node.output()
    assert "1 publisher(s) on /image but no frame for 5 s" in out and "do not match; use qos:=auto" in out, out


@pytest.mark.parametrize("node_args", [[], ["--ros-args", "-p", "use_sim_time:=true"]], ids=["wall-time", "sim-time-no-clock"])
def test_a_node_nobody_publishes_to_names_the_image_topics_there_are(ros, tmp_path, node_args):
    """The usual set-up slip, no remap: after 10 s without a publisher the node lists the image topics and the remap.

    Also with use_sim_time and nothing on /clock (a bag played without --clock): the checks and /diagnostics run on
    the steady clock, so the advice still comes, and the missing /clock is named too."""
    sim = "use_sim_time:=true" in node_args
    with node_and_peer(ros, tmp_path, node_args, image_topic="/cam/image_raw", info_topic="/cam/camera_info") as (node, peer):
        assert spin_until(peer.node, lambda: peer.count("warn_no_publisher") > 0, 40.0), "no warning without a publisher"
        assert node.alive()
        assert (peer.count("warn_no_clock") > 0) == sim, peer.diag_values()
    out = node.output()
    assert "no publisher on /image for 10 s: image topics seen: /cam/image_raw [Image]; remap with -r image:=/cam/image_raw" \
        in out, out
    assert ("use_sim_time is true but nothing has published /clock for 5 s: the node's clock stands at 0.000 s" in out) == sim, out


def test_a_compressed_topic_remapped_as_the_raw_input_is_explained(ros, tmp_path):
    """-r image:=.../compressed without use_compressed:=true: DDS delivers nothing across message types; the node said
    "the camera may have stopped publishing". It now names both types and the settings, within seconds."""
    topic = "/cam/image_raw/compressed"
    with node_and_peer(ros, tmp_path, ["--ros-args", "-r", f"image:={topic}"], image_topic="/cam/image_raw",
                       compressed=True) as (node, peer):
        assert spin_until(peer.node, lambda: peer.count("warn_wrong_type") > 0, 20.0), peer.diag_values()
        assert peer.count("warn_no_frames") == 0 and peer.count("warn_no_publisher") == 0
    assert (f"{topic} is published as sensor_msgs/msg/CompressedImage but this node subscribes sensor_msgs/msg/Image, so "
            f"no frame can arrive: set -p use_compressed:=true -r image/compressed:={topic}") in node.output()


def test_the_advice_for_another_message_type_fits_each_direction():
    from nmnet_ros.interface.dds import mistyped_advice

    assert mistyped_advice("/cam/image_raw", ["sensor_msgs/msg/Image"], True).endswith(
        "subscribes sensor_msgs/msg/CompressedImage, so no frame can arrive: set -p use_compressed:=false -r image:=/cam/image_raw")
    assert mistyped_advice("/scan", ["sensor_msgs/msg/LaserScan"], False) == (
        "/scan is published as sensor_msgs/msg/LaserScan but this node subscribes sensor_msgs/msg/Image, so no frame can "
        "arrive: remap the input to a topic of camera frames (sensor_msgs/msg/Image or CompressedImage)")


def test_a_depth_topic_remapped_as_the_image_is_pointed_out_at_start_up(ros, tmp_path):
    """An RGB-D camera's depth image (16UC1, which the node reads as a mono frame) remapped as the node's input: said
    at start-up, naming the topic."""
    with node_and_peer(ros, tmp_path, ["--ros-args", "-r", "image:=/camera/depth/image_rect_raw"],
                       image_topic="/camera/depth/image_rect_raw") as (node, peer):
        peer.wait_connected()
        assert spin_until(peer.node, lambda: "looks like a depth topic" in node.output(), 10.0), node.output()
    assert "/camera/depth/image_rect_raw looks like a depth topic: nmnet_node detects features in camera frames, not in " \
        "depth images: remap its input to the camera's colour, mono or infrared stream" in node.output()


def test_a_depth_encoding_is_said_where_the_topic_name_did_not_say_it():
    from nmnet_ros.interface.dds import depth_encoding_note

    assert depth_encoding_note("/camera/depth/image_rect_raw", "16UC1") is None  # said at start-up, by its name
    assert depth_encoding_note("/cam/image_raw", "mono16") is None and depth_encoding_note("/cam/image_raw", "mono8") is None
    assert depth_encoding_note("/cam/image_raw", "16uc1").startswith("frames on /cam/image_raw are 16UC1")


def test_16uc1_frames_on_a_topic_not_named_depth_are_pointed_out_once(ros, tmp_path):
    """A depth stream under another name (16UC1, read as 16-bit grey): only a topic named "depth" was said; the
    frames' encoding tells too, once, and the node goes on."""
    depth = np.full((48, 64), 1500, np.uint16)
    with node_and_peer(ros, tmp_path, ["--ros-args", "-r", "image:=/camera/aligned/image_raw"],
                       image_topic="/camera/aligned/image_raw", reliable=True) as (node, peer):
        peer.wait_connected()
        for k in range(3):
            peer.pub_img.publish(image_msg(depth, 1.0 + k, encoding="16UC1"))
        # every frame has passed the check (its /diagnostics count them as they arrive) before the note is counted
        assert spin_until(peer.node, lambda: peer.count("frames_received") >= 3, 15.0), peer.diag_values()
        assert node.alive()
    assert ("frames on /camera/aligned/image_raw are 16UC1, what depth cameras publish (a 16-bit grey camera says "
            "mono16); if so: nmnet_node detects features in camera frames, not in depth images") in node.output()
    assert node.output().count("are 16UC1") == 1 and "looks like a depth topic" not in node.output()


def test_rectified_frames_take_p_and_a_rect_topic_with_distortion_is_pointed_out(ros, tmp_path):
    """KITTI's frames are rectified; given a camera_info whose K and D describe a raw, distorted camera and whose
    P is the rectified one, rectified:=true (set at run time) gives the right poses."""
    seq = Sequence.load(data_dir("kitti-07"))
    raw = kitti_info(seq)
    raw.k = [float(x) for x in (np.diag([0.9, 0.9, 1.0]) @ seq.camera.K).ravel()]  # the raw camera: another K, distorted
    raw.d = [-0.3, 0.1, 0.0, 0.0, 0.0]
    with node_and_peer(ros, tmp_path, ["--ros-args", "-r", "image:=/cam/image_rect"], image_topic="/cam/image_rect") as (node, peer):
        peer.wait_connected()
        peer.pub_info.publish(raw)
        assert spin_until(peer.node, lambda: "looks rectified but camera_info has lens distortion" in node.output(), 10.0)
        assert all(r.successful for r in set_params(peer, {"rectified": True}))
        frames = list(range(30, 36))
        send_lockstep(peer, seq, frames, image_msg, raw)
        # measured: 0.02-0.04 deg with P; 0.6-0.9 deg with the raw K and D on these rectified frames
        assert np.median(check_kitti_run(peer, seq, frames)) < 0.2
    assert "set rectified:=true if these frames are rectified" in node.output()


def test_the_subscription_follows_the_publishers_and_the_advice_fits_the_case():
    from nmnet_ros.interface.dds import LARGE_FRAMES_PROFILE, follow_reliability, silence_advice, where_are_the_images

    assert [follow_reliability(o) for o in ([], [True], [True, True], [True, False], [False])] == [False, True, True, False,
                                                                                                   False]
    assert "do not match" in silence_advice(True, [True, False])
    assert f"FASTDDS_DEFAULT_PROFILES_FILE={LARGE_FRAMES_PROFILE}" in silence_advice(False, [False])
    assert "stopped publishing" in silence_advice(True, [True])
    assert LARGE_FRAMES_PROFILE.is_file()
    raw, jpeg = ("/cam/image_raw", ["sensor_msgs/msg/Image"]), ("/cam/image_raw/compressed", ["sensor_msgs/msg/CompressedImage"])
    other = ("/imu", ["sensor_msgs/msg/Imu"])
    assert "remap with -r image/compressed:=/cam/image_raw/compressed" in where_are_the_images([raw, jpeg], {"/image"}, True)
    assert "set -p use_compressed:=true -r image/compressed:=/cam/image_raw/compressed" in where_are_the_images(
        [jpeg, other], {"/image"}, False)
    assert "set -p use_compressed:=false -r image:=/cam/image_raw" in where_are_the_images([raw], {"/image/compressed"}, True)
    assert "no image topic is published at all" in where_are_the_images([other, ("/nmnet_node/debug_image", ["sensor_msgs/msg/Image"])],
                                                              {"/image", "/nmnet_node/debug_image"}, False)
    # an RGB-D camera: its depth topics are listed, never suggested (16UC1 depth would read as mono frames)
    depth = ("/camera/depth/image_rect_raw", ["sensor_msgs/msg/Image"])
    colour = ("/camera/color/image_raw", ["sensor_msgs/msg/Image"])
    assert where_are_the_images([depth, colour], {"/image"}, False).endswith("remap with -r image:=/camera/color/image_raw")
    assert "all depth: nmnet_node detects features in camera frames, not in depth images" in where_are_the_images(
        [depth], {"/image"}, False)


def get_params(peer: Peer, names: list[str]) -> dict:
    from rclpy.parameter import parameter_value_to_python
    from rclpy.parameter_client import AsyncParameterClient

    client = AsyncParameterClient(peer.node, "/nmnet_node")
    assert client.wait_for_services(10.0)
    fut = client.get_parameters(names)
    rclpy.spin_until_future_complete(peer.node, fut, timeout_sec=10.0)
    return {n: parameter_value_to_python(v) for n, v in zip(names, fut.result().values, strict=True)}


def test_parameters_from_yaml_and_command_line(ros, tmp_path):
    seq = Sequence.load(data_dir("kitti-07"))
    yaml_file = tmp_path / "p.yaml"
    yaml_file.write_text("nmnet_node:\n  ros__parameters:\n    k: 4\n    pose_refine_iterations: 3\n"  # before /**: loses
                         "/**:\n  ros__parameters:\n    max_keypoints: 500\n    score_threshold: 0.7\n    qos: reliable\n"
                         "    pose_threshold_px: 0.8\n    pose_refine_iterations: 0\n"
                         "/nmnet_node:\n  ros__parameters:\n    k: 6\n    max_keypoint: 100\n")  # after /**: wins; a typo
    other = tmp_path / "driver.yaml"  # a file for other nodes only: rclpy applies none of it, without a word
    other.write_text("camera_driver:\n  ros__parameters:\n    fps: 30\nnmnet:\n  ros__parameters:\n    k: 2\n")
    node_args = ["--ros-args", "--params-file", str(yaml_file), "--params-file", str(other), "-p", "max_keypoints:=300",
                 "-p", "score_treshold:=0.2"]
    with node_and_peer(ros, tmp_path, node_args, signal.SIGINT, reliable=True) as (node, peer):
        peer.wait_connected()
        got = get_params(peer, ["max_keypoints", "score_threshold", "qos", "k", "pose_threshold_px", "pose_refine_iterations"])
        assert got == {"max_keypoints": 300, "score_threshold": 0.7, "qos": "reliable", "k": 6, "pose_threshold_px": 0.8,
                       "pose_refine_iterations": 0}
        # what `nmnet replay --params-file` reads from the same file: the node's values (sections in file order)
        offline = read_params_file(yaml_file)
        assert {name: offline[name] for name in got} == {**got, "max_keypoints": 500}  # 300 came from -p
        peer.first_frame(kitti_info(seq), image_msg(seq.image(0), 1.0))
        assert 0 < int(peer.diag_values()["keypoints"]) <= 300  # the -p value reached the detector
    out = node.output()  # what rclpy ignored, said: the misspelt names, the file without a section for the node
    assert "'max_keypoint' is not an nmnet_node parameter: ignored; did you mean 'max_keypoints'?" in out
    assert "'score_treshold' is not an nmnet_node parameter: ignored; did you mean 'score_threshold'?" in out
    assert f"{other}: no section applies to /nmnet_node (sections: /camera_driver, /nmnet)" in out
    # values the default estimator does not read are said, not silently kept
    assert "score_threshold 0.7 has no effect with pose_estimator 'prosac': only ratio_magsac, magsac, weighted8" in out
    assert f"{yaml_file}: no section" not in out and "'k' is not" not in out and "use_sim_time" not in out


def set_params(peer: Peer, values: dict) -> list:
    """``ros2 param set`` from the peer: one SetParametersResult per value."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    client = AsyncParameterClient(peer.node, "/nmnet_node")
    assert client.wait_for_services(10.0)
    fut = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
    rclpy.spin_until_future_complete(peer.node, fut, timeout_sec=30.0)
    return fut.result().results


def published_matches(peer: Peer, stamp: float) -> np.ndarray:
    """The ~/matches cloud published for the frame at ``stamp``: rows u0 v0 u1 v1 score."""
    assert peer.wait_result_for(stamp), f"no matches published for the frame at {stamp}"
    m = next(m for s, (_, m) in zip(peer.stamps(peer.matches), peer.matches, strict=True) if abs(s - stamp) < 1e-6)
    fields = matches_of_cloud(m.point_step, m.fields, m.data)  # by name, as a consumer reads it
    return np.stack([fields[name] for name in ("u0", "v0", "u1", "v1", "score")], 1)


def published_scores(peer: Peer, stamp: float) -> np.ndarray:
    """The score column of the ~/matches cloud published for the frame at ``stamp``."""
    return published_matches(peer, stamp)[:, 4]


def send_frame(peer: Peer, seq: Sequence, i: int, stamp: float) -> np.ndarray:
    """Publish camera_info and frame ``i`` of ``seq`` stamped ``stamp``; the scores of the matches published for it."""
    peer.pub_info.publish(kitti_info(seq))
    peer.pub_img.publish(image_msg(seq.image(i), stamp))
    return published_scores(peer, stamp)


@contextmanager
def kitti_node(ros: dict, tmp_path, first: int):
    """A node at 1000 keypoints and a peer, the node having processed KITTI-07 frame ``first`` stamped 1.0 s:
    yields (sequence, peer, node); both are stopped on leaving, so ``node.output()`` is complete after it."""
    seq = Sequence.load(data_dir("kitti-07"))
    with node_and_peer(ros, tmp_path, ["--ros-args", "-p", "max_keypoints:=1000"], signal.SIGINT) as (node, peer):
        peer.wait_connected()
        peer.first_frame(kitti_info(seq), image_msg(seq.image(first), 1.0))
        yield seq, peer, node


def test_reset_service_restarts_the_chain(ros, tmp_path):
    """~/reset (std_srvs/Trigger), as a back end that re-initialises calls it: the next frame is not related to the
    frame before the call (no estimate, no matches), the one after it is; counted in diagnostics."""
    from std_srvs.srv import Trigger

    with kitti_node(ros, tmp_path, 60) as (seq, peer, node):
        assert len(send_frame(peer, seq, 61, 2.0)) > 50 and not no_estimate(peer.pose_for(2.0))
        client = peer.node.create_client(Trigger, "/nmnet_node/reset")
        assert client.wait_for_service(timeout_sec=10.0), "no ~/reset service"
        fut = client.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(peer.node, fut, timeout_sec=10.0)
        assert fut.result() is not None and fut.result().success, fut.result()
        assert len(send_frame(peer, seq, 62, 3.0)) == 0 and no_estimate(peer.pose_for(3.0))  # a new chain starts here
        assert len(send_frame(peer, seq, 63, 4.0)) > 50 and not no_estimate(peer.pose_for(4.0))  # related to frame 62
        assert spin_until(peer.node, lambda: peer.count("chain_resets") == 1, 5.0), peer.diag_values()
    assert "reset requested: the next frame starts a new chain" in node.output()


def test_parameters_change_while_running(ros, tmp_path):
    """`ros2 param set` on a running node: a new NM-Net cut, pose estimator, resize_width, min_matches, static_flow_px,
    time_jump_s, the covariance's sigmas and matches_within_px act from the next frame;
    a bad choice, a missing weights file, a start-up-only parameter, a value out of range and one of the
    wrong type are refused with the reason,
    and the node keeps its settings and keeps running."""
    with kitti_node(ros, tmp_path, 40) as (seq, peer, node):

        def frame(i: int, stamp: float) -> np.ndarray:
            return send_frame(peer, seq, i, stamp)

        calibrated = frame(41, 2.0)
        assert calibrated.min() < 0.95 and len(np.unique(calibrated)) > 1  # NM-Net probabilities
        # the default (prosac) orders by the scores; ratio_magsac cuts at score_threshold
        assert all(r.successful for r in set_params(peer, {"pose_estimator": "ratio_magsac", "score_threshold": 0.95}))
        assert frame(42, 3.0).min() > 0.95
        assert all(r.successful for r in set_params(peer, {"pose_estimator": "classic"}))
        assert np.all(frame(43, 4.0) == 1.0)  # no network: the published score is the selection itself
        missing = str(tmp_path / "missing.pt")
        refused = {  # name: (value, what the reason says); the type check and its words are rclpy's
            "matching": ("fancy", "'fancy' is not one of"), "weights": (missing, f"{missing}: weights file not found"),
            "qos": ("reliable", "read-only parameter: qos"), "pose_threshold_px": (0.0, "pose_threshold_px out of range"),
            "max_keypoints": ("lots", "Wrong parameter type"), "nmnet_precision": ("float16", "'float16' is not one of"),
        }
        results = set_params(peer, {name: value for name, (value, _) in refused.items()})
        for (name, (_, reason)), r in zip(refused.items(), results, strict=True):
            assert not r.successful and reason in r.reason, (name, r.reason)
        assert get_params(peer, list(refused) + ["pose_estimator"]) == {"matching": "nn", "weights": "", "qos": "auto",
                                                                        "pose_threshold_px": 0.15, "max_keypoints": 1000,
                                                                        "pose_estimator": "classic", "nmnet_precision": "auto"}
        assert np.all(frame(44, 5.0) == 1.0)  # still running, still classic
        # half-size detection: another frame size restarts the chain, then matches come in the frames' own pixels
        assert all(r.successful for r in set_params(peer, {"resize_width": 613}))
        assert len(frame(45, 6.0)) == 0 and no_estimate(peer.pose_for(6.0))
        frame(46, 7.0)
        uv = published_matches(peer, 7.0)
        assert len(uv) > 50 and uv[:, [0, 2]].max() > 900 and not no_estimate(peer.pose_for(7.0))
        # the chain's limits: more matches needed than a frame has = no estimate; a flow limit above the flow = static;
        # a shorter time_jump_s restarts the chain on a frame half a second back (1 s: skipped as out of order)
        assert all(r.successful for r in set_params(peer, {"min_matches": 100000}))
        frame(47, 8.0)
        assert no_estimate(peer.pose_for(8.0))
        assert all(r.successful for r in set_params(peer, {"min_matches": 8, "static_flow_px": 1000.0}))
        frame(48, 9.0)
        static = peer.pose_for(9.0)
        p, o = static.pose.pose.position, static.pose.pose.orientation
        # no_motion: the rotation fitted alone (a fraction of a degree between these frames), zero translation
        assert (p.x, p.y, p.z) == (0, 0, 0) and 0 < np.degrees(2 * np.arccos(min(o.w, 1.0))) < 1.0 and not no_estimate(static)
        assert all(r.successful for r in set_params(peer, {"static_flow_px": 1.0, "time_jump_s": 0.2}))
        frame(49, 8.5)
        assert no_estimate(peer.pose_for(8.5))
        # the published covariance's sigmas (at 200 matches, sqrt(200 / n) beyond)
        assert all(r.successful for r in set_params(peer, {"pose_sigma_rotation_deg": 0.05, "pose_sigma_direction": 0.004}))
        n = len(frame(50, 10.0))
        cov = np.asarray(peer.pose_for(10.0).pose.covariance).reshape(6, 6)
        np.testing.assert_allclose(np.diag(cov), [0.004**2 * 200 / n] * 3 + [np.radians(0.05) ** 2 * 200 / n] * 3, rtol=1e-9)
        # matches_within_px: every match MAGSAC++ was given within 0.5 px of the pose is published; the covariance
        # still rests on the pose's own inliers, so it is wider than the published count would make it
        assert all(r.successful for r in set_params(peer, {"matches_within_px": 0.5}))
        m = len(frame(51, 11.0))
        cov = np.asarray(peer.pose_for(11.0).pose.covariance).reshape(6, 6)
        assert m > 1.2 * n and cov[0, 0] > 1.1 * 0.004**2 * 200 / m, (m, n, cov[0, 0])
    assert "parameters changed: {'score_threshold': 0.95}" in node.output()
    assert "NM-Net arithmetic: " in node.output()  # what the network runs in on this CPU, said at start-up


def test_a_driver_that_does_not_stamp_is_stamped_on_arrival(ros, tmp_path):
    """Frames stamped 0 (a driver that does not stamp): skipped with header stamps, said so with the remedy; with
    stamp_source arrival (switched on while running) each takes the node's clock when it arrives, so the chain goes
    on, and the outputs carry that time. Frames that name no frame are processed, and that is said once."""
    with kitti_node(ros, tmp_path, 60) as (seq, peer, node):
        peer.pub_info.publish(kitti_info(seq))
        peer.pub_img.publish(image_msg(seq.image(61), 0.0))
        assert wait_diag(peer, "warn_out_of_order_stamp", 1)  # 0 after the first frame's 1.0 s
        assert all(r.successful for r in set_params(peer, {"stamp_source": "arrival"}))
        before = time.time()  # the node's clock: system time (no use_sim_time)
        for n, i in enumerate((62, 63), 1):
            peer.pub_info.publish(kitti_info(seq))
            peer.pub_img.publish(image_msg(seq.image(i), 0.0, frame_id=""))  # nor names its frame
            assert spin_until(peer.node, lambda n=n: len(peer.matches) > n and len(peer.poses) > n, 30.0), i
        stamps = peer.stamps(peer.matches)[1:]  # after the first frame's, at 1.0 s
        assert before < stamps[0] < stamps[1] < time.time() and peer.stamps(peer.poses)[1:] == stamps, stamps
        assert len(published_matches(peer, stamps[1])) > 50 and not no_estimate(peer.pose_for(stamps[1]))
        assert peer.count("warn_out_of_order_stamp") == 1 and peer.count("warn_duplicate_stamp") == 0
    assert "If not, stamp_source:=arrival stamps them on arrival" in node.output()
    assert node.output().count("name no frame (empty header.frame_id)") == 1 and "camera_optical_frame" in node.output()


@pytest.mark.parametrize("name, value", [("matching", "fancy"), ("pose_threshold_px", "0.0"), ("max_keypoints", "lots")],
                         ids=["choice", "range", "type"])
def test_invalid_parameter_is_a_clear_error(ros, tmp_path, name, value):
    node = NodeProcess(["--ros-args", "-p", f"{name}:={value}"], ros, tmp_path / "node.log")
    assert node.proc.wait(60) == 2
    node.stop()
    out = node.output()
    assert "nmnet_node: error:" in out and name in out and value in out and "Traceback" not in out


@pytest.mark.parametrize("args, said", [
    (["--params-file", "/no/such/nmnet.yaml"], "Couldn't parse params file: '--params-file /no/such/nmnet.yaml'. "
                                              "Error: Error opening YAML file (the forms: -p name:=value"),
    (["--params-file", "{bad}"], "Couldn't parse params file: '--params-file {bad}'. Error: Error parsing"),
    (["-p", "max_keypoints"], "Couldn't parse parameter override rule: '-p max_keypoints'"),
    (["-r", "image:="], "Couldn't parse remap rule: '-r image:=' (the forms: "),
], ids=["missing-file", "bad-yaml", "bare-p", "bare-r"])
def test_ros_arguments_rcl_cannot_read_are_one_line_not_a_traceback(ros, tmp_path, args, said):
    """A --params-file that is missing or not YAML, a -p or -r without its value: rclpy.init raised RCLError, a
    traceback ending in rcl's C source locations."""
    bad = tmp_path / "bad.yaml"
    bad.write_text("nmnet_node:\n  ros__parameters:\n    max_keypoints: [1, 2\n")
    node = NodeProcess(["--ros-args", *[a.replace("{bad}", str(bad)) for a in args]], ros, tmp_path / "node.log")
    assert node.proc.wait(60) == 2
    node.stop()
    out = node.output()
    assert f"nmnet_node: error: {said.replace('{bad}', str(bad))}" in out and "Traceback" not in out
    assert "/project/src" not in out.split("nmnet_node: error:")[1], out


def test_weights_without_a_calibrated_cut_are_said_in_the_nodes_log(ros, tmp_path):
    """An unfinished training run's checkpoint keeps matches above 0.5; the warning is a ROS log line of the node,
    not a Python UserWarning with its source line."""
    import torch

    from nmnet_ros.core.model import weights_dir

    ck = torch.load(weights_dir() / "nmnet.pt", map_location="cpu", weights_only=True)
    del ck["score_threshold"]
    torch.save(ck, tmp_path / "last.pt")
    node = NodeProcess(["--ros-args", "-p", f"weights:={tmp_path / 'last.pt'}"], ros, tmp_path / "node.log")
    end = time.monotonic() + 60
    while "waiting for camera_info" not in node.output() and node.alive() and time.monotonic() < end:
        time.sleep(0.2)  # the node is up: it has built its front end
    node.stop()
    assert "no calibrated score threshold" in node.output(), node.output()
    line = next(ln for ln in node.output().splitlines() if "no calibrated score threshold" in ln)
    assert line.startswith("[WARN]") and "[nmnet_node]" in line and "UserWarning" not in node.output()
    # the same weights set on a running node (`ros2 param set weights ...`): taken, and said in the log likewise
    with node_and_peer(ros, tmp_path, ["--ros-args"]) as (node, peer):
        assert all(r.successful for r in set_params(peer, {"weights": str(tmp_path / "last.pt")}))
        end = time.monotonic() + 30
        while "no calibrated score threshold" not in node.output() and time.monotonic() < end:
            time.sleep(0.2)
    lines = [ln for ln in node.output().splitlines() if "no calibrated score threshold" in ln]
    assert len(lines) == 1 and lines[0].startswith("[WARN]") and "UserWarning" not in node.output(), node.output()


def rss_mb(pid: int) -> float:
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def test_flood_keeps_latency_bounded(ros, tmp_path):
    """60 Hz for 12 s into a node that manages a few Hz: old frames are dropped, not queued, memory stays flat.

    RSS is compared between medians over 2 s windows after a 4 s warm-up: glibc arenas keep freed
    buffers of varying size for a while, so single samples swing by ~20 MB; a queue or a per-frame
    leak of the 0.47 MB frames (~30 received per second) would add well over 100 MB in that time.
    """
    seq = Sequence.load(data_dir("kitti-07"))
    imgs = [seq.image(i) for i in range(80, 100)]
    sent: dict[float, float] = {}
    with node_and_peer(ros, tmp_path, [], signal.SIGINT) as (node, peer):
        peer.wait_connected()
        peer.first_frame(kitti_info(seq), image_msg(imgs[0], 0.5))
        peer.pub_img.publish(image_msg(imgs[1], 1.0))  # warm: a full pair has run once
        assert peer.wait_result_for(1.0)
        peer.matches.clear()
        rss0 = rss_mb(node.proc.pid)
        t0 = time.monotonic()
        n = 0
        rss = []
        while time.monotonic() - t0 < 12.0:
            if n % 15 == 0:
                rss.append((time.monotonic() - t0, rss_mb(node.proc.pid)))
            stamp = 2.0 + n / 60.0
            peer.pub_img.publish(image_msg(imgs[1 + n % 19], stamp))
            sent[round(stamp, 6)] = time.monotonic()
            n += 1
            spin_until(peer.node, lambda: False, max(0.0, t0 + n / 60.0 - time.monotonic()))
        spin_until(peer.node, lambda: False, 8.0)  # let the last frame finish
        rss1 = rss_mb(node.proc.pid)
        assert wait_diag(peer, "frames_dropped", 1)
        vals = peer.diag_values()
    lat = [t - sent[round(s, 6)] for (t, _), s in zip(peer.matches, peer.stamps(peer.matches), strict=True) if round(s, 6) in sent]
    received, dropped = int(vals["frames_received"]), int(vals["frames_dropped"])
    print(f"sent {n}, received {received} (best effort), results {len(lat)}, dropped {dropped}, latency s: {np.round(lat, 2)}, "
          f"RSS {rss0:.0f} -> {np.round([r for _, r in rss])} -> {rss1:.0f} MB")
    assert len(lat) >= 2 and received > len(lat) + 1  # a flood: more frames arrived than the node could take
    assert dropped >= received - 1 - len(lat) - 1 > 0  # every received frame not processed is counted
    assert max(lat) < 3 * np.median(lat) + 1.0  # bounded: no queue building up
    assert lat[-1] < 3 * lat[0] + 1.0
    early = np.median([r for t, r in rss if 4.0 <= t < 6.0])
    late = np.median([r for t, r in rss if t >= 10.0] + [rss1])
    assert late - early < 30  # flat memory: after warm-up nothing accumulates


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_stop_signal_while_frames_are_in_flight_is_a_quiet_clean_exit(ros, tmp_path, sig):
    """Stopped while both stages work (frames at 30 Hz, more than the node keeps up with): exit 0 and nothing said
    about it. The signal shuts ROS down at once, and the frame then in the second stage failed to publish: the node
    warned "frame skipped after an unexpected error: RCLError ... context is invalid" and rcl "Failed to publish
    log message to rosout", as if something had gone wrong."""
    seq = Sequence.load(data_dir("kitti-07"))
    imgs = [seq.image(i) for i in range(80, 90)]
    node = NodeProcess([], ros, tmp_path / "node.log")
    peer = Peer()
    try:
        peer.wait_connected()
        peer.first_frame(kitti_info(seq), image_msg(imgs[0], 0.5))
        for n in range(1, 61):  # 2 s at 30 Hz; the node takes ~10 Hz, so a frame is in each stage at the end
            peer.pub_img.publish(image_msg(imgs[n % 10], 0.5 + n / 30))
            spin_until(peer.node, lambda: False, 1 / 30)
        assert peer.count("frames_processed") >= 5
    finally:
        peer.close()
        code = node.stop(sig)
    out = node.output()
    assert code == 0, out
    assert "unexpected error" not in out and "Failed to publish" not in out, out


def test_node_module_caps_malloc_arenas_unless_the_user_set_it():
    """Importing the node limits glibc to one malloc arena (flat RSS); a user's MALLOC_ARENA_MAX wins."""
    import os
    import subprocess
    import sys

    code = "import nmnet_ros.ros.node, nmnet_ros.ros.one_arena as a; print(a.ENABLED)"
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, check=True)
    assert out.stdout.strip() == "True"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**env, "MALLOC_ARENA_MAX": "4"},
                         cwd=ROOT, check=True)
    assert out.stdout.strip() == "False"


def test_params_file_and_readme_give_the_parameters_defaults():
    """config/nmnet.yaml (what users copy) holds every node parameter at its default, and each row of the README's
    key-parameters table names a parameter the node has, with its default (the full table: docs/parameters.md)."""
    import re

    import yaml

    from nmnet_ros.ros.node import PARAMS

    params = yaml.safe_load((ROOT / "config" / "nmnet.yaml").read_text())["/**"]["ros__parameters"]
    assert params == {name: default for name, (default, _, _) in PARAMS.items()}
    rows = re.findall(r"^\| `(\w+)` \| `([^`]*)` \|", (ROOT / "README.md").read_text(), re.M)
    assert len(rows) >= 5
    for name, shown in rows:
        default = PARAMS[name][0]
        assert shown == (str(default).lower() if isinstance(default, bool) else '""' if default == "" else str(default)), name


def test_launch_file_gives_the_tested_invocation():
    """What `ros2 launch nmnet_ros nmnet.launch.xml image:=... camera_info:=...` runs: the shipped params
    file, the node's three input topics remapped, use_compressed passed through, the namespace (the raw DDS test
    above starts the node with these arguments, in a namespace); an undeclared launch argument is an error."""
    args = launch_node_args(LAUNCH, {"image": "/cam/image_raw", "camera_info": "/cam/camera_info", "use_compressed": "true"})
    assert args == ["-r", "__node:=nmnet_node", "-r", "__ns:=/", "--params-file", str(ROOT / "config" / "nmnet.yaml"),
                    "-p", "use_compressed:=true", "-r", "image:=/cam/image_raw", "-r", "image/compressed:=/cam/image_raw/compressed",
                    "-r", "camera_info:=/cam/camera_info"]
    assert launch_node_args(LAUNCH, {"namespace": "rear"})[:4] == ["-r", "__node:=nmnet_node", "-r", "__ns:=/rear"]
    with pytest.raises(ValueError, match="camera_topic"):
        launch_node_args(LAUNCH, {"camera_topic": "/cam/image_raw"})


def test_the_package_installs_launch_config_and_ament_index(tmp_path):
    """A wheel of the package (what pip and colcon's ament_python install) carries the launch file, the
    params file, package.xml and the ament index marker under share/, both console scripts and the licence."""
    import shutil
    import subprocess
    import sys
    import zipfile

    src = tmp_path / "src"  # built from a copy: setuptools writes build/ next to the sources
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".*", "build", "*.egg-info", "__pycache__", "docs", "test", "nmnet_demo"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path), str(src)],
                   check=True, capture_output=True, cwd=tmp_path)
    (wheel,) = tmp_path.glob("nmnet_ros-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    share = {n.split("/data/", 1)[1] for n in names if ".data/data/" in n}
    assert {"share/nmnet_ros/launch/nmnet.launch.xml", "share/nmnet_ros/config/nmnet.yaml", "share/nmnet_ros/package.xml",
            "share/ament_index/resource_index/packages/nmnet_ros"} <= share
    entry = next(zipfile.ZipFile(wheel).read(n).decode() for n in names if n.endswith("entry_points.txt"))
    assert "nmnet_node = nmnet_ros.ros.entry:node_main" in entry and "nmnet = nmnet_ros.tools.cli:main" in entry
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names), [n for n in names if "dist-info" in n]


def test_lasting_warnings_repeat_ever_less_often_until_cleared(ros, monkeypatch):
    """An idle camera (no_publisher / no_frames for hours) does not fill the log: each repeat waits twice as
    long as the one before, up to 10 min, and a new episode (the condition cleared, then back) logs at once.
    The node runs in this process, driven as its once-a-second check drives it; its logger records what it
    would print. The message (no_publisher's queries the ROS graph) is built only when it is logged."""
    from nmnet_ros.ros import node as nm

    due = [s for s in range(2000) if nm.lasting_warning_due(s, 30)]
    assert due == [0, 30, 90, 210, 450, 930, 1530]  # gaps 30, 60, 120, 240, 480, then 600
    with pytest.raises(ValueError, match="first=0"):  # a zero first gap would never reach a later second
        nm.lasting_warning_due(5, 0)
    node = nm.NMNetNode()
    logged: list[str] = []

    class Recorder:
        def warning(self, text: str) -> None:
            logged.append(text)

    monkeypatch.setattr(node, "get_logger", lambda: Recorder())
    built = [0]

    def text() -> str:
        built[0] += 1
        return "1 publisher(s) on /image but no frame for 9 s: ..."

    try:
        def idle(seconds: int) -> list[int]:
            """An episode of ``seconds`` checks; the seconds into it at which the node logged."""
            at = []
            for s in range(seconds):
                before = len(logged)
                node._warn_lasting("no_frames", s, 30, text)
                if len(logged) > before:
                    at.append(s)
            return at

        assert idle(500) == [0, 30, 90, 210, 450]
        assert node.stats.warnings["no_frames"] == 500  # every second still counts in diagnostics
        assert built[0] == len(logged) == 5
        assert idle(100) == [0, 30, 90]  # a new episode: at once, then 30 s, 60 s again
    finally:
        node.stop()
        node.destroy_node()


def test_a_live_replays_node_that_exits_or_never_subscribes_is_a_clear_error(ros):
    """The live replay's player waited for the node's subscription, then raised a bare RuntimeError: a traceback from
    `nmnet replay --live` (as when a robot's parameters file set the other image transport)."""
    from nmnet_ros.tools.live import NodeNotReady, _Player, new_stats

    player = _Player("sensor_msgs/msg/Image", None, new_stats())
    try:
        never = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
        try:
            with pytest.raises(NodeNotReady, match=r"nmnet_node did not subscribe to /nmnet_live_\d+/image within 2 s "
                                                   rf"\(ROS_DOMAIN_ID {ros['ROS_DOMAIN_ID']}\)"):
                player.wait_for_node(never, timeout=2.0)
        finally:
            never.kill()
            never.wait()
        gone = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
        with pytest.raises(NodeNotReady, match="nmnet_node exited with code 3 before it subscribed to the frames"):
            player.wait_for_node(gone, timeout=60.0)
    finally:
        player.node.destroy_node()


def test_an_rmw_the_wheels_lack_is_named_before_rclpy_ends_the_process(monkeypatch):
    """RMW_IMPLEMENTATION=rmw_cyclonedds_cpp (a common line in a robot's shell) with the pip wheels, which bring Fast
    DDS only: rcl ended nmnet_node at import with exit code 102 and its own line. The node now says what to do, exit 2;
    under a sourced ROS 2 installation (AMENT_PREFIX_PATH) rcl finds the RMW itself, and the installed one passes."""
    import os

    from nmnet_ros.interface.dds import rmw_problem

    env = {k: v for k, v in os.environ.items() if k != "AMENT_PREFIX_PATH"}
    start = [sys.executable, "-c", "import sys; from nmnet_ros.ros.entry import node_main; sys.exit(node_main(['nmnet_node']))"]
    done = subprocess.run(start, capture_output=True, text=True, cwd=ROOT, timeout=60,
                          env={**env, "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"})
    assert done.returncode == 2 and "102" not in done.stderr, done.stderr
    assert done.stderr.startswith("nmnet_node: error: RMW_IMPLEMENTATION=rmw_cyclonedds_cpp: not installed; the ROS 2 "
                                  "wheels bring rmw_fastrtps_cpp only. Unset it for nmnet"), done.stderr
    monkeypatch.delenv("AMENT_PREFIX_PATH", raising=False)
    for said, problem in (("rmw_fastrtps_cpp", False), ("", False), ("rmw_zenoh_cpp", True), ("rmw.bogus", True),
                            ("rmw_cyclonedds_cpp.x", True), (".x", True)):  # names find_spec raises on
        monkeypatch.setenv("RMW_IMPLEMENTATION", said)
        assert (rmw_problem() is not None) == problem, said
    monkeypatch.setenv("AMENT_PREFIX_PATH", "/opt/ros/kilted")  # a ROS 2 installation's RMWs are its libraries
    assert rmw_problem() is None


def test_the_demo_skips_its_live_part_where_the_ros_environment_keeps_the_node_from_running(monkeypatch):
    """`make demo` in a shell with RMW_IMPLEMENTATION=rmw_cyclonedds_cpp ended in rcl's exit 102 before its offline
    part; the live part is skipped now, saying why (as where rclpy is missing), and the offline part runs."""
    from nmnet_ros.tools.demo import live_blocked

    monkeypatch.delenv("AMENT_PREFIX_PATH", raising=False)
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)
    assert live_blocked() is None
    for name, value in (("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp"), ("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF"),
                        ("ROS_DOMAIN_ID", "abc")):
        monkeypatch.setenv(name, value)
        assert (live_blocked() or "").startswith(f"{name}="), name
        monkeypatch.delenv(name)
