"""DDS facts the node and the live player share (no ROS imports).

Measured with the ROS 2 Kilted wheels (Fast DDS 3.2.3) on one machine, 20 frames at 5 Hz, with
``FASTDDS_BUILTIN_TRANSPORTS=LARGE_DATA`` on both ends:
a best-effort subscription received every frame up to 0.52 MB, but 6-11 of 20 at 0.6 MB and 0-7 of
20 at 1.4 MB, from a best-effort or a reliable publisher (Fast DDS's shared-memory segment is
512 KB). A reliable subscription to a reliable publisher received 20 of 20, and so did a best-effort
one when the publisher ran with :data:`LARGE_FRAMES_PROFILE` (a 16 MB segment), at 1.4 and 2.8 MB.
"""

from __future__ import annotations

import importlib.util
import os
import re
from pathlib import Path

from .imgconv import IMAGE_TYPES

LARGE_FRAMES_PROFILE = Path(__file__).parents[1] / "fastdds_large_frames.xml"  # shipped at the package root
LARGE_FRAME_BYTES = 512 * 1024  # above this, best effort over Fast DDS's default shared memory loses frames


def rmw_problem() -> str | None:
    """Why rclpy cannot start here, said before it is imported: an RMW_IMPLEMENTATION that the pip wheels do not carry
    (they bring rmw_fastrtps_cpp only; rcl then ends the process at import with exit code 102). None where it is
    installed, or under a sourced ROS 2 installation (AMENT_PREFIX_PATH), whose RMWs are libraries rcl finds itself."""
    said = os.environ.get("RMW_IMPLEMENTATION", "").strip()
    if not said or os.environ.get("AMENT_PREFIX_PATH"):
        return None
    try:
        if importlib.util.find_spec(said) is not None:  # each wheel-installed RMW is also a Python package
            return None
    except (ImportError, ValueError):  # a name no module can have
        pass
    return (f"RMW_IMPLEMENTATION={said}: not installed; the ROS 2 wheels bring rmw_fastrtps_cpp only. Unset it for "
            "nmnet (other nodes may keep theirs: DDS implementations talk across vendors on one domain), or run "
            "under a ROS 2 installation that has it")


def large_frames_advice() -> str:
    """What happens to large frames on a best-effort subscription, and the two ways out."""
    return ("a best-effort subscription loses most frames larger than about 0.5 MB over Fast DDS's default shared "
            "memory (640x480 bgr8 is 0.9 MB): publish the images reliable (qos:=auto follows), or start the camera "
            f"driver with FASTDDS_DEFAULT_PROFILES_FILE={LARGE_FRAMES_PROFILE}")


def follow_reliability(publishers_reliable: list[bool]) -> bool:
    """Subscribe reliable only when there are publishers and every one of them offers reliable.

    A reliable subscription does not match a best-effort publisher; a best-effort one matches both,
    but loses large frames, so it is the choice while any publisher is best effort or none is known.
    """
    return bool(publishers_reliable) and all(publishers_reliable)


def silence_advice(subscribed_reliable: bool, publishers_reliable: list[bool]) -> str:
    """Why image publishers exist but no frame arrives, and what to do."""
    if subscribed_reliable and not all(publishers_reliable):
        return ("a publisher offers best effort and this node subscribes reliable (qos:=reliable), which do not match; "
                "use qos:=auto or qos:=sensor_data")
    if not subscribed_reliable:
        return large_frames_advice() + "; or the camera stopped publishing"
    return "the camera may have stopped publishing"


def _switch_to(topic: str, compressed: bool) -> str:
    """The settings that take ``topic``, of the other message type than the node's (``compressed``: it subscribes
    CompressedImage)."""
    return (f"set -p use_compressed:=false -r image:={topic}" if compressed
            else f"set -p use_compressed:=true -r image/compressed:={topic}")


def mistyped_advice(topic: str, their_types: list[str], compressed: bool) -> str:
    """For an image topic whose publishers all send another message type than the node subscribes (which DDS never
    delivers): what they send and the settings that take it (``-r image:=.../compressed`` without use_compressed)."""
    ours = IMAGE_TYPES[compressed]
    theirs = ", ".join(sorted(set(their_types)))
    fix = (_switch_to(topic, compressed) if IMAGE_TYPES[not compressed] in their_types
           else "remap the input to a topic of camera frames (sensor_msgs/msg/Image or CompressedImage)")
    return f"{topic} is published as {theirs} but this node subscribes {ours}, so no frame can arrive: {fix}"


DEPTH_ADVICE = ("nmnet_node detects features in camera frames, not in depth images: remap its input to the camera's "
                "colour, mono or infrared stream")


def depth_encoding_note(topic: str, encoding: str, advice: str = DEPTH_ADVICE) -> str | None:
    """What to say of frames on ``topic`` in ``encoding`` that look like depth: 16UC1 is what depth cameras publish
    (in millimetres), read here as 16-bit grey; None for another encoding, or where the topic's name said so already.
    ``advice``: what to do if they are depth (the node's remap by default)."""
    if encoding.lower() != "16uc1" or is_depth(topic):
        return None
    return f"frames on {topic} are 16UC1, what depth cameras publish (a 16-bit grey camera says mono16); if so: {advice}"


def is_depth(topic: str) -> bool:
    """Whether an image topic's name says it carries depth (/camera/depth/image_rect_raw, /aligned_depth_to_color/)."""
    return "depth" in re.split(r"[^a-z0-9]+", topic.lower())


def where_are_the_images(topics: list[tuple[str, list[str]]], ours: set[str], compressed: bool) -> str:
    """For a node whose image topic has no publisher: the image topics that do exist, and the remap to use.

    ``topics`` as ``Node.get_topic_names_and_types()`` gives them; ``ours``: the node's own image topics
    (its subscription, its debug image), not listed; ``compressed``: it subscribes CompressedImage. An RGB-D
    camera's depth topics are listed but not suggested.
    """
    seen = [(name, t) for name, types in topics for t in types if t in IMAGE_TYPES and name not in ours]
    if not seen:
        return "no image topic is published at all: is the camera driver running, on this ROS_DOMAIN_ID?"
    listing = ", ".join(f"{name} [{t.rsplit('/', 1)[-1]}]" for name, t in seen)
    frames = [(name, t) for name, t in seen if not is_depth(name)]
    if not frames:
        return f"image topics seen: {listing}, all depth: {DEPTH_ADVICE} (is that stream enabled in the driver?)"
    same = [name for name, t in frames if t == IMAGE_TYPES[compressed]]
    if same:
        hint = f"remap with -r {'image/compressed' if compressed else 'image'}:={same[0]}"
    else:
        hint = f"for {'raw' if compressed else 'compressed'} frames {_switch_to(frames[0][0], compressed)}"
    return f"image topics seen: {listing}; {hint}"
