"""``nmnet make-bag SEQ_DIR --out OUT [--format mcap|sqlite3|ros1] [--compressed]``: a sequence folder as a bag.

Each frame becomes an Image (or a JPEG CompressedImage), its CameraInfo, and, where the folder's ground truth has a
pose, a PoseStamped and a /tf transform, stamped as images.txt; written with ``rosbags``' writers.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from ..interface.caminfo import info_fields
from ..interface.imgconv import array_to_image_fields
from ..interface.posemsg import rot_to_quat
from ..io.bags import BagError, typestore
from ..io.datasets import DatasetError, Sequence
from ..io.outputs import not_an_input, output_folder
from ..io.pairs import parse_seq_spec
from .cli import interrupts_between_steps

TOPICS = {"image": "/camera/image_raw", "compressed": "/camera/image_raw/compressed", "info": "/camera/camera_info",
          "gt": "/ground_truth/pose", "tf": "/tf"}
FORMATS = ("mcap", "sqlite3", "ros1")


def _stamp(ts, t: float):
    sec = int(np.floor(t))
    return ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)


def _header(ts, t: float, frame_id: str, ros1: bool, seq: int = 0):
    H = ts.types["std_msgs/msg/Header"]
    return H(seq=seq, stamp=_stamp(ts, t), frame_id=frame_id) if ros1 else H(stamp=_stamp(ts, t), frame_id=frame_id)


def _messages_for_frame(ts, seq: Sequence, i: int, compressed: bool, ros1: bool) -> list[tuple[str, str, object]]:
    """(topic, msgtype, message) of frame i: image, camera_info and ground truth when known."""
    t = float(seq.stamps[i])
    hdr = _header(ts, t, "camera", ros1, i)
    img = seq.image(i)
    out = []
    if compressed:  # JPEG holds 8 bits: OpenCV clipped a 16-bit frame to 255 (white); PNG keeps it, as image_transport
        fmt, ext, opts = ("jpeg", ".jpg", [cv2.IMWRITE_JPEG_QUALITY, 90]) if img.dtype == np.uint8 else ("png", ".png", [])
        ok, buf = cv2.imencode(ext, img, opts)
        msg = ts.types["sensor_msgs/msg/CompressedImage"](header=hdr, format=fmt, data=buf.ravel())
        out.append((TOPICS["compressed"], "sensor_msgs/msg/CompressedImage", msg))
    else:
        f = array_to_image_fields(img)
        f["data"] = np.frombuffer(f["data"], np.uint8)
        out.append((TOPICS["image"], "sensor_msgs/msg/Image", ts.types["sensor_msgs/msg/Image"](header=hdr, **f)))
    Roi = ts.types["sensor_msgs/msg/RegionOfInterest"]
    info = ts.types["sensor_msgs/msg/CameraInfo"](
        header=hdr, **info_fields(seq.camera, img.shape[1], img.shape[0], ros1),
        binning_x=0, binning_y=0, roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    out.append((TOPICS["info"], "sensor_msgs/msg/CameraInfo", info))
    if seq.has_pose(i):
        T = seq.poses[i]
        q = rot_to_quat(T[:3, :3])
        P_ = ts.types["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3])
        Q_ = ts.types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])
        pose = ts.types["geometry_msgs/msg/PoseStamped"](header=_header(ts, t, "world", ros1, i),
                                                         pose=ts.types["geometry_msgs/msg/Pose"](position=P_, orientation=Q_))
        out.append((TOPICS["gt"], "geometry_msgs/msg/PoseStamped", pose))
        V_ = ts.types["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3])
        tf = ts.types["geometry_msgs/msg/TransformStamped"](
            header=_header(ts, t, "world", ros1, i), child_frame_id="camera_gt",
            transform=ts.types["geometry_msgs/msg/Transform"](translation=V_, rotation=Q_))
        out.append((TOPICS["tf"], "tf2_msgs/msg/TFMessage", ts.types["tf2_msgs/msg/TFMessage"](transforms=[tf])))
    return out


SUFFIX_FORMATS = {".bag": "ros1", ".db3": "sqlite3", ".mcap": "mcap"}  # what an output's name says it is


def bag_format(out: Path, fmt: str | None) -> str:
    """The format to write ``out`` in: ``fmt``, else the one its extension names (.bag, .db3, .mcap), else mcap. A
    BagError where the two disagree: a ROS 2 folder named .bag would be taken for a ROS 1 bag, and a .db3 holding
    mcap for what it is not."""
    if fmt is not None and fmt not in FORMATS:
        raise BagError(f"unknown bag format {fmt!r}; use one of {', '.join(FORMATS)}")
    named = SUFFIX_FORMATS.get(out.suffix)
    if fmt == "ros1" and named != "ros1":
        raise BagError(f"{out}: a ROS 1 bag is one file and is read by its .bag extension; name it {out.stem}.bag")
    if fmt is not None and named is not None and named != fmt:
        raise BagError(f"{out}: its extension says {named}, --format says {fmt}; drop one, or name the output "
                       f"{out.stem}{next(k for k, v in SUFFIX_FORMATS.items() if v == fmt)}")
    return fmt or named or "mcap"


def make_bag(seq_dir: str | Path, out: str | Path, fmt: str | None = None, compressed: bool = False,
             frames: range | None = None) -> int:
    """Write a sequence folder as a bag; returns the number of frames written.

    ``out`` named ``.mcap`` or ``.db3``: that one ROS 2 storage file, which carries the bag's metadata itself
    (``ros2 bag play run.mcap`` and Foxglove open it); another name: a ROS 2 bag folder (as ``ros2 bag record -o
    OUT``); ``.bag``: a ROS 1 bag. ``fmt`` None: the one ``out``'s extension names (:func:`bag_format`).
    """
    out = Path(out)
    fmt = bag_format(out, fmt)
    seq = Sequence.load(seq_dir)
    if out.exists():
        raise BagError(f"{out} exists already; choose a new output path")
    ros1 = fmt == "ros1"
    output_folder(out.parent, "the output's folder", "the bag")
    not_an_input(out, "the output", [Path(seq_dir), seq.root, *(p.parent for p in seq.paths[:1])])
    out.parent.mkdir(parents=True, exist_ok=True)  # the ROS 2 writer makes its own, the ROS 1 one did not
    ts = typestore(ros1)
    idx = list(seq.frames(frames))
    for note in seq.notes("they are written without a ground-truth pose"):  # as nmnet eval and train say them
        print(f"warning: {note}", file=sys.stderr)
    staging: Path | None = None
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer = Writer1(out)
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
        # rosbags writes a folder: one named run.mcap held run.mcap.mcap. A storage file's name gets the file alone,
        # written in a hidden folder beside it and moved out whole (it carries the bag's metadata itself)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent)) if out.suffix in SUFFIX_FORMATS else None
        writer = Writer2(staging / out.stem if staging else out, version=9, storage_plugin=plugin)
    try:
        with writer:  # on an exception rosbags aborts: a ROS 2 bag without metadata.yaml, which nothing reads
            storage_file = writer.storage.path if staging else None  # rosbags names it after its folder
            written, interrupted = _write_frames(writer, ts, seq, idx, compressed, ros1)
            if not written:
                raise BagError(f"{seq.root}: none of the {len(idx)} frames could be read; no bag written")
        if staging:
            os.replace(storage_file, out)
    except BaseException as e:  # an error, or an interrupt before any frame: no partial output in a rerun's way
        if out.is_dir():
            shutil.rmtree(out, ignore_errors=True)
        else:
            out.unlink(missing_ok=True)
        if isinstance(e, OSError):  # a full disk: rosbags' error names no file
            raise OSError(f"writing {out} failed ({e.strerror or e}): nothing written") from e
        raise
    finally:
        if staging:
            shutil.rmtree(staging, ignore_errors=True)
    if interrupted:
        raise Interrupted(written, len(idx))
    return written


def _write_frames(writer, ts, seq: Sequence, idx: list[int], compressed: bool, ros1: bool) -> tuple[int, bool]:
    """Write each frame's messages; (frames written, interrupted). A frame that cannot be read is skipped, named (the
    others are still a recording); Ctrl-C or SIGTERM ends the loop between two frames (one could land between a frame's
    image and its pose), so the bag closes with whole frames; before any frame, it is raised."""
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    conns: dict[str, object] = {}
    written = 0
    with interrupts_between_steps() as stop_requested:
        for i in idx:
            if stop_requested():
                if not written:
                    raise KeyboardInterrupt
                return written, True
            try:
                messages = _messages_for_frame(ts, seq, i, compressed, ros1)
            except DatasetError as e:
                print(f"warning: frame {i}: skipped, {e}", file=sys.stderr)
                continue
            for topic, mtype, msg in messages:
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, mtype, typestore=ts)
                writer.write(conns[topic], int(round(float(seq.stamps[i]) * 1e9)), serialize(msg, mtype))
            written += 1
    return written, False


class Interrupted(KeyboardInterrupt):
    """make-bag stopped by Ctrl-C or SIGTERM after ``written`` of ``total`` frames, its bag closed and readable."""

    def __init__(self, written: int, total: int) -> None:
        super().__init__(f"{written} of {total} frames written")
        self.written, self.total = written, total


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet make-bag``."""
    if (args.out is None) == (args.out_positional is None):
        raise ValueError("name the output once: --out BAG (or, as before, a second argument)")
    out = args.out or args.out_positional
    path, frames = parse_seq_spec(args.seq)
    try:
        n = make_bag(path, out, args.format, args.compressed, frames)
    except Interrupted as stop:  # Ctrl-C, or SIGTERM (cli.main raises it as Ctrl-C)
        print(f"interrupted: wrote {stop.written} of {stop.total} frames to {out}, a readable bag", file=sys.stderr)
        return 130
    print(f"wrote {n} frames to {out}")
    return 0
