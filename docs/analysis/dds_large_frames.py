"""How many large frames reach a subscriber on one machine, by QoS and Fast DDS profile (nmnet_ros/dds.py, README QoS).

An analysis behind the node's ``qos: auto`` default and the shipped large-frames profile, not part of
the package. For each case a publisher process sends 20 sensor_msgs/Image of the given size at 5 Hz
to a subscriber process (both with ``FASTDDS_BUILTIN_TRANSPORTS=LARGE_DATA``, own domain, localhost),
and the subscriber counts what arrives.

    python docs/analysis/dds_large_frames.py            # about 2 minutes
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

from nmnet_ros.interface.dds import LARGE_FRAMES_PROFILE

FRAMES, GAP_S = 20, 0.2
# (size in bytes, publisher reliable, subscriber reliable, publisher uses the large-frames profile)
CASES = [
    (450_000, False, False, False), (520_000, False, False, False), (600_000, False, False, False),
    (900_000, True, False, False), (1_400_000, False, False, False), (1_400_000, True, False, False),
    (1_400_000, True, True, False), (1_400_000, False, False, True), (1_400_000, True, False, True),
    (2_800_000, False, False, True),
]

ROLE = r"""
import sys, time
import rclpy
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import Image
role, reliable, size, frames, gap = sys.argv[1], sys.argv[2] == "1", int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
qos = QoSProfile(depth=10) if reliable else qos_profile_sensor_data
rclpy.init()
node = rclpy.create_node(role)
if role == "sub":
    got = []
    node.create_subscription(Image, "frames", lambda m: got.append(len(m.data)), qos)
    end = time.time() + 6 + frames * gap + 4
    while time.time() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    print(len(got), flush=True)
else:
    pub = node.create_publisher(Image, "frames", qos)
    while pub.get_subscription_count() == 0:
        rclpy.spin_once(node, timeout_sec=0.1)
    time.sleep(1.0)
    for _ in range(frames):
        msg = Image(height=1, width=size, step=size, encoding="mono8")
        msg.data = bytes(size)
        pub.publish(msg)
        t = time.time()
        while time.time() - t < gap:
            rclpy.spin_once(node, timeout_sec=0.05)
"""


def run_case(domain: int, size: int, pub_rel: bool, sub_rel: bool, profile: bool) -> int:
    """Frames received of FRAMES sent."""
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "FASTDDS_BUILTIN_TRANSPORTS": "LARGE_DATA"}
    env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    args = [str(size), str(FRAMES), str(GAP_S)]
    sub = subprocess.Popen([sys.executable, "-c", ROLE, "sub", str(int(sub_rel)), *args], env=env, stdout=subprocess.PIPE,
                           text=True)
    time.sleep(1.0)
    pub_env = {**env, "FASTDDS_DEFAULT_PROFILES_FILE": str(LARGE_FRAMES_PROFILE)} if profile else env
    subprocess.run([sys.executable, "-c", ROLE, "pub", str(int(pub_rel)), *args], env=pub_env, timeout=120,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    out, _ = sub.communicate(timeout=120)
    return int(out.strip().splitlines()[-1])


def main() -> None:
    print("| frame MB | publisher | subscriber | publisher profile | received of 20 |")
    print("|---|---|---|---|---|")
    for n, (size, pub_rel, sub_rel, profile) in enumerate(CASES):
        got = run_case(90 + n % 10, size, pub_rel, sub_rel, profile)
        kinds = ["reliable" if r else "best effort" for r in (pub_rel, sub_rel)]
        print(f"| {size / 1e6:.2f} | {kinds[0]} | {kinds[1]} | {'large frames' if profile else 'default'} | {got} |",
              flush=True)


if __name__ == "__main__":
    main()
