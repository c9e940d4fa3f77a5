"""Helpers for node tests: the node as its own process, a real rclpy peer over isolated DDS."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def ros_env(domain: int) -> dict[str, str]:
    """Environment isolating a test run: its own domain, localhost discovery, large-data transport."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", FASTDDS_BUILTIN_TRANSPORTS="LARGE_DATA",
               PYTHONUNBUFFERED="1")
    return env


def unique_domain() -> int:
    """A domain id (1..100) unlikely to collide with a parallel run."""
    return 1 + (os.getpid() * 7 + int(time.time() * 1000)) % 100


class NodeProcess:
    """``python -m nmnet_ros.node`` with arguments, stdout/stderr captured to a file."""

    def __init__(self, args: list[str], env: dict[str, str], log: Path) -> None:
        self.log = log
        self._fh = open(log, "w")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen([sys.executable, "-m", "nmnet_ros.node", *args], env=env, cwd=ROOT,
                                     stdout=self._fh, stderr=subprocess.STDOUT)

    def output(self) -> str:
        return self.log.read_text()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, sig: int = signal.SIGINT, timeout: float = 15.0) -> int:
        if self.alive():
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._fh.close()
        return self.proc.returncode


def spin_until(node, cond: Callable[[], bool], timeout: float) -> bool:
    """Spin ``node`` until ``cond()`` holds or ``timeout`` seconds pass."""
    import rclpy

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        rclpy.spin_once(node, timeout_sec=0.05)
    return cond()


def image_msg(img: np.ndarray, stamp: float, frame_id: str = "camera", encoding: str | None = None):
    """sensor_msgs/Image from an array (mono8 or bgr8 unless encoding given)."""
    from sensor_msgs.msg import Image

    from nmnet_ros.imgconv import array_to_image_fields

    msg = Image()
    for k, v in array_to_image_fields(img).items():
        setattr(msg, k, v)
    if encoding:
        msg.encoding = encoding
    msg.header.frame_id = frame_id
    msg.header.stamp.sec = int(stamp)
    msg.header.stamp.nanosec = int(round((stamp - int(stamp)) * 1e9))
    return msg


def compressed_msg(img: np.ndarray, stamp: float, data: bytes | None = None):
    """sensor_msgs/CompressedImage (JPEG) from an array, or with raw ``data``."""
    from sensor_msgs.msg import CompressedImage

    msg = CompressedImage()
    msg.format = "jpeg"
    msg.data = data if data is not None else cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    msg.header.frame_id = "camera"
    msg.header.stamp.sec = int(stamp)
    msg.header.stamp.nanosec = int(round((stamp - int(stamp)) * 1e9))
    return msg


def camera_info_msg(K: np.ndarray, dist: np.ndarray, width: int, height: int):
    """sensor_msgs/CameraInfo (plumb_bob; P = [K | 0], as for a monocular camera), as the live player builds it."""
    from nmnet_ros.geometry import Camera
    from nmnet_ros.live import camera_info_msg as build

    msg = build(Camera(K, dist, width, height))
    msg.header.frame_id = "camera"
    return msg
