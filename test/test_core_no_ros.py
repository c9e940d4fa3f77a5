"""The algorithmic core must import without any ROS module."""

import subprocess
import sys

CORE = ["features", "matching", "neighbors", "geometry", "datasets", "model", "pairs", "metrics", "cache", "train",
        "neighbor_study"]


def test_core_imports_no_ros():
    code = (
        "import sys\n"
        + "".join(f"import nmnet_ros.{m}\n" for m in CORE)
        + "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
        "{'rclpy','sensor_msgs','geometry_msgs','nav_msgs','std_msgs','diagnostic_msgs','rosidl_runtime_py','rpyutils'})\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"core modules pulled in ROS modules: {out}"


def test_cli_lists_subcommands():
    out = subprocess.run([sys.executable, "-m", "nmnet_ros.cli", "--help"], capture_output=True, text=True, check=True).stdout
    for sub in ("demo", "train", "eval", "neighbors", "bench"):
        assert sub in out
