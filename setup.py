"""ament_python package definition (also a plain pip-installable package)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "nmnet_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={PACKAGE: ["weights/*.pt", "weights/*.md", "sample/*", "sample/*/*", "*.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.xml")),
    ],
    install_requires=["setuptools"],
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
