"""Soak: kitti-07 frames 120-159 looped into a live nmnet_node at 10 Hz; the node's memory after every loop.

An analysis behind the README's "How it behaves on a live robot", not part of the package. Each loop
starts again at the first frame's stamp, a time jump that restarts the node's chain, so a long run
also exercises the restart path. Prints per loop the `~/matches` messages received so far and the
node's resident memory (RSS, from /proc).

    python docs/analysis/node_soak.py ../shared/data/kitti-07 --loops 40     # 1600 frames, 3 min
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

from nmnet_ros.interface.caminfo import info_fields
from nmnet_ros.interface.imgconv import array_to_image_fields
from nmnet_ros.io.datasets import Sequence


def rss_mb(pid: int) -> int:
    """Resident memory of a process, MB."""
    with open(f"/proc/{pid}/status") as f:
        return int(f.read().split("VmRSS:")[1].split()[0]) // 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", help="kitti-07 sequence folder")
    ap.add_argument("--frames", default="120-159", help="frame range a-b")
    ap.add_argument("--loops", type=int, default=40)
    ap.add_argument("--rate", type=float, default=10.0, help="frames per second")
    args = ap.parse_args()
    os.environ.update(ROS_DOMAIN_ID=os.environ.get("ROS_DOMAIN_ID", "77"), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    import rclpy
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    seq = Sequence.load(args.seq)
    a, b = (int(v) for v in args.frames.split("-"))
    frames = [seq.image(i) for i in range(a, b + 1)]
    node = subprocess.Popen([sys.executable, "-m", "nmnet_ros.node"], env=os.environ.copy())
    rclpy.init()
    player = Node("soak_player")
    images = player.create_publisher(Image, "image", 10)
    infos = player.create_publisher(CameraInfo, "camera_info", 10)
    received = [0]
    player.create_subscription(PointCloud2, "/nmnet_node/matches", lambda _: received.__setitem__(0, received[0] + 1), 10)
    info = info_fields(seq.camera, seq.camera.width, seq.camera.height)
    time.sleep(8)  # the node's start-up (kernels loaded from numba's cache)
    t0 = time.time()
    try:
        for loop in range(args.loops):
            for i, img in enumerate(frames):
                stamp = 1000.0 + i / args.rate
                msg = Image(**array_to_image_fields(img))
                msg.header.stamp.sec, msg.header.stamp.nanosec = int(stamp), round(stamp % 1 * 1e9)
                msg.header.frame_id = "camera"
                ci = CameraInfo(**info)
                ci.header = msg.header
                infos.publish(ci)
                images.publish(msg)
                end = time.time() + 1 / args.rate
                while time.time() < end:
                    rclpy.spin_once(player, timeout_sec=0.01)
            print(f"loop {loop + 1}: {received[0]} matches messages, node RSS {rss_mb(node.pid)} MB, "
                  f"{time.time() - t0:.0f} s", flush=True)
    finally:
        node.terminate()
        node.wait(10)
        player.destroy_node()
        rclpy.shutdown()


if __name__ == "__main__":
    main()
