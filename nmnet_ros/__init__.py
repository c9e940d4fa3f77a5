"""NM-Net learned correspondence selection as a ROS 2 visual-odometry front end.

Layers, each importing only the ones before it: ``core`` (perception) -> ``interface`` (ROS messages and
parameters, without ROS) -> ``io`` (datasets, recordings, outputs) -> ``ros`` (the node) -> ``tools`` (``nmnet``).

A back end reads the node's outputs with :func:`matches_of_cloud` (``~/matches``) and :func:`estimate_of_message`
(``~/relative_pose``), both importable from here without ROS.
"""

from importlib import import_module

_PUBLIC = {"matches_of_cloud": "nmnet_ros.interface.imgconv", "estimate_of_message": "nmnet_ros.interface.posemsg",
           "LARGE_FRAMES_PROFILE": "nmnet_ros.interface.dds"}
__all__ = list(_PUBLIC)


def __getattr__(name: str):
    """The public names, imported when first used (``import nmnet_ros.tools.cli`` stays light)."""
    if name in _PUBLIC:
        return getattr(import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'nmnet_ros' has no attribute {name!r}")
