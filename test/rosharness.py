"""Helpers for node tests: the node as its own process, a real rclpy peer over isolated DDS."""

from __future__ import annotations

import os
import re
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


def launch_node_args(path: Path, args: dict[str, str]) -> list[str]:
    """The ``--ros-args`` that ``ros2 launch`` gives the one node of a launch XML file, with ``args``.

    launch / launch_ros have no wheels here, so this reads the few tags and substitutions the
    shipped file uses (arg, node with name and namespace, param from/name, remap; $(var), $(find-pkg-share nmnet_ros)) and
    fails on anything else. find-pkg-share is the source tree: setup.py installs config/ and launch/
    under share/nmnet_ros.
    """
    import xml.etree.ElementTree as ET

    values: dict[str, str] = {}

    def sub(text: str) -> str:
        def one(m: re.Match) -> str:
            if m.group(1) == "var":
                return values[m.group(2)]
            if m.group(1) == "find-pkg-share" and m.group(2) == "nmnet_ros":
                return str(ROOT)
            raise ValueError(f"substitution {m.group(0)} not understood")
        return re.sub(r"\$\((\S+) ([^)]+)\)", one, text)

    out: list[str] = []
    for el in ET.parse(path).getroot():
        if el.tag == "arg":
            values[el.get("name")] = args.get(el.get("name"), sub(el.get("default", "")))
        elif el.tag == "node" and (el.get("pkg"), el.get("exec")) == ("nmnet_ros", "nmnet_node"):
            out += ["-r", f"__node:={el.get('name')}"]
            if el.get("namespace") is not None:  # launch_ros makes it absolute: an empty one is the root
                out += ["-r", f"__ns:=/{sub(el.get('namespace')).strip('/')}"]
            for p in el:
                if p.tag == "param" and p.get("from"):
                    out += ["--params-file", sub(p.get("from"))]
                elif p.tag == "param":
                    out += ["-p", f"{p.get('name')}:={sub(p.get('value'))}"]
                elif p.tag == "remap":
                    out += ["-r", f"{p.get('from')}:={sub(p.get('to'))}"]
                else:
                    raise ValueError(f"<{p.tag}> in <node> not understood")
        else:
            raise ValueError(f"<{el.tag} {el.attrib}> not understood")
    unknown = set(args) - set(values)
    if unknown:
        raise ValueError(f"launch arguments {sorted(unknown)} are not declared in {path}")
    return out


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

    from nmnet_ros.interface.imgconv import array_to_image_fields

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
    from nmnet_ros.core.geometry import Camera
    from nmnet_ros.tools.live import camera_info_msg as build

    msg = build(Camera(K, dist, width, height))
    msg.header.frame_id = "camera"
    return msg
