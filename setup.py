"""ament_python package definition (also a plain pip-installable package)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "nmnet_ros"

setup(
    name=PACKAGE,
    version="0.2.0",
    packages=find_packages(exclude=["test"]),
    package_data={PACKAGE: ["weights/*.pt", "weights/*.md", "sample/*", "sample/*/*", "*.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.xml")),
    ],
    python_requires=">=3.10",
    # compatible ranges (requirements.txt is the exact lock that `make` installs); the node's ROS 2 Python packages
    # come from a sourced ROS 2 installation (colcon), or from PyPI's wheels on x86_64 Linux: `pip install .[ros]`
    install_requires=[
        "numpy>=1.26,<3",
        "opencv-contrib-python-headless>=4.10",
        "torch>=2.5,<3",
        "kornia>=0.8,<1",
        "numba>=0.60",
        "pyyaml>=6",
        "matplotlib>=3.8",
        "tqdm>=4.66",
        "rosbags>=0.10.4,<0.12",
        "mcap>=1.1,<2",
        "mcap-ros2-support>=0.5,<1",
        "pycolmap>=4.2,<5",  # nmnet label: reconstruction of unlabeled recordings
        "poselib>=2.0.5,<3",  # PoseLib's robust relative pose (nmnet eval's ratio+poselib, nmnet+prosac)
        "ray>=2.40,<3",  # nmnet replay over many recordings
    ],
    extras_require={
        "ros": [f"ros-{name}; sys_platform == 'linux' and platform_machine == 'x86_64'" for name in
                ("rclpy[fastrtps]>=9.1,<10", "sensor-msgs>=5.5,<6", "geometry-msgs>=5.5,<6", "std-msgs>=5.5,<6",
                 "std-srvs>=5.5,<6", "diagnostic-msgs>=5.5,<6")],
        "test": ["pytest>=8", "ruff>=0.6", "mkdocs>=1.6,<2"],
    },
    zip_safe=False,
    maintainer="nmnet_ros maintainers",
    maintainer_email="nmnet-ros@example.org",
    description="NM-Net learned correspondence selection as a ROS 2 visual-odometry front end",
    license="BSD-3-Clause",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "nmnet = nmnet_ros.tools.cli:main",
            "nmnet_node = nmnet_ros.ros.entry:node_main",
        ],
    },
)
