"""The node as users start it (own process), over real DDS isolated per test run."""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest

from nmnet_ros.datasets import Sequence
from nmnet_ros.geometry import rotation_error_deg

from .conftest import ROOT, data_dir
from .rosharness import NodeProcess, camera_info_msg, compressed_msg, image_msg, ros_env, spin_until, unique_domain

rclpy = pytest.importorskip("rclpy")


def quat_to_rot(q):
    from nmnet_ros.datasets import quat_to_rot as q2r

    return q2r(q)


class Peer:
    """The test's own rclpy node: publishes camera data, records the node's outputs."""

    def __init__(self, ns: str = "/nmnet_node", image_topic: str = "image", compressed: bool = False,
                 info_topic: str = "camera_info") -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

        self.node = rclpy.create_node(f"test_peer_{unique_domain()}")
        mtype = CompressedImage if compressed else Image
        self.pub_img = self.node.create_publisher(mtype, image_topic + ("/compressed" if compressed else ""), qos_profile_sensor_data)
        self.pub_info = self.node.create_publisher(CameraInfo, info_topic, qos_profile_sensor_data)
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

    def stamps(self, items) -> list[float]:
        return [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for _, m in items]

    def wait_result_for(self, stamp: float, timeout: float = 30.0) -> bool:
        return spin_until(self.node, lambda: any(abs(s - stamp) < 1e-6 for s in self.stamps(self.matches)), timeout)

    def close(self) -> None:
        self.node.destroy_node()


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
        peer.pub_info.publish(info)
        peer.pub_img.publish(make_msg(seq.image(i), stamp))
        if n == 0:
            assert peer.wait_processed(1), "first frame never processed"
        else:
            assert peer.wait_result_for(stamp), f"no result for frame {i}"


def check_kitti_run(peer: Peer, seq: Sequence, frames) -> None:
    spin_until(peer.node, lambda: len(peer.poses) >= len(frames) - 1, 5.0)  # the pose follows the matches
    assert len(peer.matches) == len(frames) - 1 and len(peer.poses) == len(frames) - 1
    errs = []
    for (_, pose), i in zip(peer.poses, frames[1:], strict=True):
        o = pose.pose.pose.orientation
        R_pc = quat_to_rot([o.x, o.y, o.z, o.w])
        R_gt, _ = seq.relative_pose(i - 1, i)
        errs.append(rotation_error_deg(R_pc, R_gt.T))
    print("rotation errors (deg):", np.round(errs, 3))
    assert np.mean(np.array(errs) < 2.0) >= 0.9
    m = peer.matches[-1][1]
    assert [f.name for f in m.fields] == ["u0", "v0", "u1", "v1", "score"] and m.width > 50


def kitti_info(seq: Sequence):
    return camera_info_msg(seq.camera.K, seq.camera.dist, seq.camera.width, seq.camera.height)


def test_kitti_raw_images_remapped_with_params_file(ros, tmp_path):
    seq = Sequence.load(data_dir("kitti-07"))
    node = NodeProcess(["--ros-args", "--params-file", str(ROOT / "config" / "nmnet.yaml"),
                        "-r", "image:=/cam/image_raw", "-r", "camera_info:=/cam/camera_info"], ros, tmp_path / "node.log")
    peer = Peer(image_topic="/cam/image_raw", info_topic="/cam/camera_info")
    try:
        peer.wait_connected()
        frames = list(range(40, 60))
        send_lockstep(peer, seq, frames, image_msg, kitti_info(seq))
        check_kitti_run(peer, seq, frames)
    finally:
        peer.close()
        assert node.stop(signal.SIGTERM) == 0, node.output()
    assert "Traceback" not in node.output()


def test_kitti_compressed_images(ros, tmp_path):
    seq = Sequence.load(data_dir("kitti-07"))
    node = NodeProcess(["--ros-args", "-p", "use_compressed:=true"], ros, tmp_path / "node.log")
    peer = Peer(compressed=True)
    try:
        peer.wait_connected()
        frames = list(range(100, 120))
        send_lockstep(peer, seq, frames, compressed_msg, kitti_info(seq))
        check_kitti_run(peer, seq, frames)
    finally:
        peer.close()
        assert node.stop(signal.SIGINT) == 0, node.output()
    assert "Traceback" not in node.output()
