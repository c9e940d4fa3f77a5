"""Output recordings: one .mcap file, ROS 2 CDR messages serialised by rosbags' typestore.

Opened before any processing (an unwritable path fails at once) and finished in ``close()``,
which callers run in ``finally`` so an interrupted run still leaves a valid, indexed file. A write
that fails (a full disk) ends the file after its last complete record (:func:`end_cut_short`): the
messages before it stay readable.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import DataEnd, Footer
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from ..interface.imgconv import array_to_image_fields, matches_to_cloud_fields
from ..interface.posemsg import SIGMAS, relative_pose_of_current
from .bags import typestore
from .outputs import LIBRARY, written_here

if TYPE_CHECKING:  # the front end (and its network) is not needed to write a bag
    from ..core.pipeline import FrameResult


DATA_SECTION = {Opcode.HEADER, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.CHUNK, Opcode.MESSAGE_INDEX,
                Opcode.ATTACHMENT, Opcode.METADATA}  # the records before DataEnd (MCAP specification)


def end_cut_short(path: Path) -> int | None:
    """End an .mcap file whose writing failed part-way: cut it after its last complete data-section record and
    append what ends a file without a summary (DataEnd, Footer, magic), which readers then scan. The messages it
    keeps; None, and the file removed, when not even that can be written (or it holds no complete header): a file
    is readable or gone."""
    try:
        with open(path, "r+b") as fh:
            size, end = fh.seek(0, 2), 0
            fh.seek(0)
            if fh.read(len(MCAP0_MAGIC)) == MCAP0_MAGIC:
                at = len(MCAP0_MAGIC)
                while len(head := fh.read(9)) == 9:
                    opcode, length = struct.unpack("<BQ", head)
                    if opcode not in DATA_SECTION or at + 9 + length > size:
                        break
                    at = fh.seek(at + 9 + length)
                    end = at
            if end == 0:
                raise OSError("no complete record")
            fh.truncate(end)
            fh.seek(end)
            tail = RecordBuilder()
            DataEnd(data_section_crc=0).write(tail)
            Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(tail)
            fh.write(tail.end() + MCAP0_MAGIC)
        with open(path, "rb") as fh:
            return sum(1 for _ in make_reader(fh).iter_messages())
    except OSError:
        path.unlink(missing_ok=True)
        return None


class McapOutput:
    """Writes the front end's outputs (matches, relative pose, debug image) to an .mcap file.

    An existing file is overwritten only when it is an earlier output: a recording (the bag being replayed, given
    as the output by mistake) or any other file is refused, as nothing of the user's may be lost.
    """

    def __init__(self, path: str | Path, pose_sigmas: tuple[float, float] = SIGMAS) -> None:
        """``pose_sigmas``: the relative poses' covariance, as the node's pose_sigma_* parameters."""
        self.path = Path(path)
        self.pose_sigmas = pose_sigmas
        if self.path.is_file() and not written_here(self.path):
            raise FileExistsError(f"output {self.path} exists and was not written by nmnet (a recording, or another "
                                  "file): it would be overwritten; choose another output path, or delete it first")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        except OSError as e:
            raise OSError(f"cannot write output {self.path}: {e.strerror or e}") from e
        self._writer = Writer(self._fh, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library=LIBRARY)
        self.ts = typestore()
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self.count = 0

    def _channel(self, topic: str, msgtype: str) -> int:
        if topic not in self._channels:
            if msgtype not in self._schemas:
                msgdef, _ = self.ts.generate_msgdef(msgtype, ros_version=2)
                self._schemas[msgtype] = self._writer.register_schema(msgtype, "ros2msg", msgdef.encode())
            self._channels[topic] = self._writer.register_channel(topic, "cdr", self._schemas[msgtype])
        return self._channels[topic]

    def write(self, topic: str, msgtype: str, msg: Any, t_ns: int) -> None:
        """Serialise and append one message."""
        self.write_raw(topic, msgtype, self.ts.serialize_cdr(msg, msgtype), t_ns)

    def write_raw(self, topic: str, msgtype: str, data: bytes, t_ns: int) -> None:
        """Append an already CDR-serialised message (e.g. from rclpy's serialize_message)."""
        try:
            self._writer.add_message(self._channel(topic, msgtype), log_time=t_ns, data=bytes(data), publish_time=t_ns)
        except OSError as e:
            raise self._cut_short(e) from e
        self.count += 1

    def _cut_short(self, e: OSError) -> OSError:
        """The file closed after a failed write and ended as :func:`end_cut_short` can; the error saying so."""
        try:
            self._fh.close()
        except OSError:
            pass  # the rest of the buffer cannot be written either
        kept = end_cut_short(self.path)
        said = "removed: not even its end could be written" if kept is None else f"it keeps the first {kept}, readable"
        return OSError(f"writing output {self.path} failed ({e.strerror or e}) with {self.count} messages given: {said}")

    def _header(self, stamp: float, frame_id: str):
        T = self.ts.types
        sec = int(np.floor(stamp))
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((stamp - sec) * 1e9)) % 10**9),
                                        frame_id=frame_id)

    def write_result(self, result: FrameResult, stamp: float, frame_id: str = "camera", debug: np.ndarray | None = None,
                     prefix: str = "/nmnet_node") -> None:
        """A FrameResult as ``{prefix}/matches`` (PointCloud2) and ``{prefix}/relative_pose`` (a stream's first frame:
        no matches, "no estimate"; see :mod:`nmnet_ros.interface.posemsg`)."""
        T = self.ts.types
        t_ns = int(round(stamp * 1e9))
        hdr = self._header(stamp, frame_id)
        sel = result.mask
        f = matches_to_cloud_fields(result.k0[sel], result.k1[sel], result.scores[sel], result.track_ids[sel])
        fields = [T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1) for n, o, d in f["fields"]]
        cloud = T["sensor_msgs/msg/PointCloud2"](header=hdr, height=1, width=f["width"], fields=fields, is_bigendian=False,
                                                 point_step=f["point_step"], row_step=f["row_step"],
                                                 data=np.frombuffer(f["data"], np.uint8), is_dense=True)
        self.write(f"{prefix}/matches", "sensor_msgs/msg/PointCloud2", cloud, t_ns)
        q, tr, cov = relative_pose_of_current(result.status, result.pose, result.pose_matches, self.pose_sigmas)
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=tr[0], y=tr[1], z=tr[2]),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        msg = T["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=hdr, pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov.ravel()))
        self.write(f"{prefix}/relative_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", msg, t_ns)
        if debug is not None:
            fi = array_to_image_fields(debug)
            fi["data"] = np.frombuffer(fi["data"], np.uint8)
            self.write(f"{prefix}/debug_image", "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](header=hdr, **fi), t_ns)

    def close(self) -> None:
        """Write the summary and index; safe to call twice."""
        if self._fh.closed:
            return
        try:
            self._writer.finish()
            self._fh.close()
        except OSError as e:
            raise self._cut_short(e) from e
        except BaseException:  # a second Ctrl-C while finishing: closed all the same
            self._fh.close()
            raise
