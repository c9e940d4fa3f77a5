"""Bags in: frames and calibration out of a ROS 1 .bag, a ROS 2 .db3 or .mcap (file or directory).

Reading goes through ``rosbags`` (typestore, AnyReader); .mcap input is read record by record with ``mcap``'s
stream reader so that a truncated file still yields its readable part (every file of a ROS 2 bag split into
several). Ground truth in a bag is :mod:`.bag_truth`; writing a sequence folder as a bag is
:mod:`nmnet_ros.tools.make_bag`. No ROS installation is needed.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.msg import get_types_from_msg
from rosbags.typesys.store import Typestore

from ..core.geometry import Camera, CameraError
from ..interface.caminfo import camera_from_info
from ..interface.dds import depth_encoding_note, is_depth
from ..interface.imgconv import IMAGE_TYPES, MAX_PIXELS, ImageError, decode_message, pixel_cap
from ..interface.posemsg import stamp_seconds
from .datasets import BAG_SUFFIXES, is_sequence_folder

BAG_DEPTH_ADVICE = ("the front end detects features in camera frames, not in depth images: choose the camera's colour, mono or "
                    "infrared stream with --image-topic")


class BagError(ValueError):
    """A bag that cannot be read or written as asked."""


def typestore(ros1: bool = False) -> Typestore:
    """The message types of ROS 2 Kilted (or ROS 1 Noetic for .bag files, plus tf2_msgs/TFMessage)."""
    if not ros1:
        return get_typestore(Stores.ROS2_KILTED)
    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


# ---------------------------------------------------------------------------------------------
@dataclass
class Frame:
    """One image of a bag with the calibration known at that time."""

    stamp: float
    image: np.ndarray | None  # None when the message could not be decoded
    error: str | None
    camera: Camera | None
    camera_error: str | None = None  # why the latest camera_info was refused, when it was
    frame_id: str = ""  # the image header's: the frame the node's outputs name


@dataclass
class RawMessage:
    """One message of a bag: its topic, type, deserialised message and log time."""

    topic: str
    msgtype: str
    msg: object
    log_time_ns: int


def _ros2_name(name: str) -> str:
    """A message type as rosbags names it (sensor_msgs/msg/Image) from a ROS 1 schema's sensor_msgs/Image."""
    return name if "/msg/" in name else name.replace("/", "/msg/", 1)


def _natural(path: Path) -> list:
    """Sort key putting rosbag2's split files in recording order (bag_2 before bag_10)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def _metadata(directory: Path) -> dict | None:
    """A ROS 2 bag directory's metadata.yaml (rosbag2_bagfile_information); None when absent or unreadable."""
    try:
        info = yaml.safe_load((directory / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        return info if isinstance(info, dict) and isinstance(info.get("relative_file_paths"), list) else None
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return None


def _bag_files(path: Path, meta: dict | None) -> tuple[str, list[Path], list[str]]:
    """The bag's kind (mcap, db3, bag), its storage files in recording order and what is amiss with them:
    ``path`` itself, or every file of a ROS 2 bag directory (split by ``ros2 bag record --max-bag-size`` or
    ``--max-bag-duration``; ``.zstd`` when recorded with ``--compression-mode file``) in its metadata.yaml's
    order (``meta``: :func:`_metadata`), else by name; or the .bag files of a folder (a ROS 1 recording split by
    ``rosbag record --split``)."""
    if not path.is_dir():
        if path.suffix in BAG_SUFFIXES:
            return path.suffix[1:], [path], []
        raise BagError(f"{path}: unknown bag type; expected a .bag, .db3 or .mcap file or a ROS 2 bag directory")
    for kind in ("mcap", "db3"):
        found = sorted(path.glob(f"*.{kind}"), key=_natural)
        zipped = sorted(path.glob(f"*.{kind}.zstd"), key=_natural)
        if not found and not zipped:
            continue
        if meta is None and not found:
            raise BagError(f"{path}: its .{kind}.zstd files are compressed and metadata.yaml, which says how, is missing "
                           f"or unreadable; decompress them (`zstd -d {zipped[0]}`) or restore metadata.yaml")
        if meta is None:
            note = [] if kind == "mcap" and len(found) == 1 else [
                f"{path}: no readable metadata.yaml; its {len(found)} .{kind} file(s) are read directly, in name order "
                f"(`ros2 bag reindex {path}` rewrites metadata.yaml)"]
            return kind, found, note
        listed = [path / name for name in meta["relative_file_paths"]]
        missing = [f for f in listed if not f.exists()]
        notes = [f"{f}: listed in {path / 'metadata.yaml'} but missing; the bag's other files are read" for f in missing]
        return kind, [f for f in listed if f.exists()] or found or zipped, notes
    if parts := sorted(path.glob("*.bag"), key=_natural):  # a ROS 1 recording split by `rosbag record --split`
        note = f"{path}: its {len(parts)} ROS 1 bags are read as one recording, merged in time"
        return "bag", parts, [note] if len(parts) > 1 else []
    raise BagError(f"{path}: directory holds no .mcap, .db3 or .bag file{_images_folder_hint(path)}")


def _images_folder_hint(path: Path) -> str:
    """What to do with a folder of images given as a bag (a sequence folder, a EuRoC or KITTI download), or ''."""
    if not is_sequence_folder(path):
        return ""
    return (f"; it is a folder of images with their poses: `nmnet make-bag {path} --out OUT.mcap` writes it as a "
            f"bag to replay, `nmnet eval {path}` scores its pairs directly")


SIGNATURES = {"mcap": b"\x89MCAP0\r\n", "db3": b"SQLite format 3\0", "bag": b"#ROSBAG V2.0",  # how each begins
              "zstd": b"\x28\xb5\x2f\xfd"}
KIND_NAMES = {"mcap": "an MCAP file", "db3": "an SQLite rosbag2 file", "bag": "a ROS 1 bag", "zstd": "a zstd-compressed file"}


def _check_signature(path: Path, kind: str) -> None:
    """Refuse a file whose first bytes are not its extension's format (a renamed or wrongly saved file), naming
    the format it is, so the reader's own error (a decode error, 'file is not a database') is never all one gets.
    A truncated bag keeps its first bytes, so this holds for the damaged files the readers salvage too."""
    kind = "zstd" if path.suffix == ".zstd" else kind
    with open(path, "rb") as fh:
        head = fh.read(max(map(len, SIGNATURES.values())))
    if head.startswith(SIGNATURES[kind]):
        return
    if not head:
        raise BagError(f"{path}: empty file")
    actual = next((k for k, sig in SIGNATURES.items() if head.startswith(sig)), None)
    if actual is not None:
        raise BagError(f"{path}: {KIND_NAMES[actual]} with a .{kind} name; rename it to .{actual}")
    raise BagError(f"{path}: not {KIND_NAMES[kind]} (it does not begin as one: {head[:12]!r}); expected a .bag, .db3 or "
                   ".mcap file")


def _mcap_topics(path: Path) -> tuple[dict[str, str], bool, str | None]:
    """An .mcap's topics, whether any carries ROS 1 messages, and what stopped the listing short (None when
    nothing did): from the summary section at the file's end, without reading the rest, else (a file cut short
    has none) record by record up to where it breaks."""
    from mcap.reader import make_reader
    from mcap.records import Channel, Schema
    from mcap.stream_reader import StreamReader

    try:
        with open(path, "rb") as fh:
            summary = make_reader(fh).get_summary()
    except Exception:  # noqa: BLE001 - truncated or damaged: read it record by record below
        summary = None
    if summary is not None and summary.channels:
        names = {i: _ros2_name(sc.name) for i, sc in summary.schemas.items()}
        channels = list(summary.channels.values())
        return ({ch.topic: names.get(ch.schema_id, "") for ch in channels},
                any(ch.message_encoding == "ros1" for ch in channels), None)
    names, topics, ros1 = {}, {}, False
    try:
        with open(path, "rb") as fh:
            for rec in StreamReader(fh, skip_magic=False).records:
                if isinstance(rec, Schema):
                    names[rec.id] = _ros2_name(rec.name)
                elif isinstance(rec, Channel):
                    topics[rec.topic] = names.get(rec.schema_id, "")
                    ros1 |= rec.message_encoding == "ros1"
    except Exception as e:  # noqa: BLE001 - truncated/corrupt: keep what was read
        return topics, ros1, f"{type(e).__name__} after {len(topics)} topics"
    return topics, ros1, None


class BagReader:
    """Messages of a .bag/.db3/.mcap (file or ROS 2 directory, every split file of it) in log-time order.

    ``warnings`` collects what went wrong on the way (e.g. a truncated file) so callers can
    report it; reading stops at the first unreadable record and keeps what came before.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            from .pairs import parse_seq_spec  # on this error path only: pairs loads the feature stack

            whole, frames = str(self.path), None
            with contextlib.suppress(ValueError):  # a malformed range: no bag by that name either
                whole, frames = parse_seq_spec(whole)
            if frames is not None and Path(whole).exists():
                raise BagError(f"{self.path}: a bag is read whole, it takes no frame range (:a-b is a sequence folder's); "
                               "nmnet replay reads a part of it with --start and --duration")
            raise BagError(f"{self.path}: no such bag")
        meta = _metadata(self.path) if self.path.is_dir() else None  # read once: files, compression, damage
        self.kind, self.files, self.warnings = _bag_files(self.path, meta)
        self.ros1 = self.kind == "bag"  # ROS 1 messages: a .bag, or an .mcap converted from one (`mcap convert`)
        for f in self.files:
            _check_signature(f, self.kind)
        # .mcap files are streamed record by record (a truncated one yields its readable part); rosbags decompresses
        compressed = str((meta or {}).get("compression_mode") or "none").lower() != "none"  # file or message mode
        self._streamed = self.kind == "mcap" and not compressed
        self._sources = self.files if self.kind == "bag" else [self.path]  # what rosbags opens: ROS 1 bags one by one
        self.damage: str | None = None  # what stopped the topic listing short (an .mcap cut before its channels)
        self._told: set[str] = set()
        self._salvaged: list[_Db3Salvage] = []
        self.topics = self._topics(meta)

    def new_warnings(self) -> list[str]:
        """The warnings not handed out before: a second pass over a damaged bag finds the same damage again."""
        new = [w for w in dict.fromkeys(self.warnings) if w not in self._told]
        self._told.update(new)
        return new

    def _topics(self, meta: dict | None) -> dict[str, str]:
        if self._streamed:
            topics: dict[str, str] = {}
            for file in self.files:
                listed, ros1, damage = _mcap_topics(file)
                topics.update(listed)
                self.ros1 |= ros1
                self.damage = self.damage or damage
            return topics
        from rosbags.highlevel import AnyReader

        try:
            with AnyReader(self._sources, default_typestore=typestore()) as r:
                return {c.topic: c.msgtype for c in r.connections}
        except Exception as e:  # noqa: BLE001 - rosbags raises several types
            if self.kind == "db3" and self.files[0].suffix == ".db3":
                self._salvaged = [_Db3Salvage(f, e) for f in self.files]
                if self.path.is_file() or meta is not None:  # without metadata.yaml the files are read directly, said
                    self.warnings.append(f"{self.path}: damaged or truncated ({e}); reading what is readable")
                return {t: m for s in self._salvaged for t, m in s.topics.items()}
            hint = ("a ROS 1 bag cut short has lost its index: rebuild it with `rosbag reindex` (ROS 1 tools), then replay "
                    "it") if self.kind == "bag" else "check it with `ros2 bag info`"
            raise BagError(f"{self.path}: cannot open bag ({type(e).__name__}: {e}); {hint}") from e

    def messages(self, topics: set[str]) -> Iterator[RawMessage]:
        """Deserialised messages on ``topics``."""
        if self._streamed:
            stores = {"ros2msg": typestore(), "ros1msg": typestore(ros1=True)}  # by schema encoding: rosbag2's, `mcap convert`'s
            for file in self.files:  # built once for all of a split bag's files (15 ms each)
                yield from self._mcap_messages(file, topics, stores)
            return
        if self._salvaged:
            for salvage in self._salvaged:
                yield from salvage.messages(topics, self.warnings)
            return
        from rosbags.highlevel import AnyReader

        with AnyReader(self._sources, default_typestore=typestore()) as r:
            conns = [c for c in r.connections if c.topic in topics]
            try:
                for c, t, raw in r.messages(connections=conns):
                    yield RawMessage(c.topic, c.msgtype, r.deserialize(raw, c.msgtype), t)
            except Exception as e:  # noqa: BLE001
                self.warnings.append(f"{self.path}: stopped reading at a damaged record ({type(e).__name__}: {e})")

    def _mcap_messages(self, file: Path, topics: set[str], stores: dict[str, Typestore]) -> Iterator[RawMessage]:
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader

        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        n = 0
        with open(file, "rb") as fh:
            try:
                for rec in StreamReader(fh, skip_magic=False).records:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec
                        ts = stores.get(rec.encoding)
                        if ts is not None and _ros2_name(rec.name) not in ts.types:
                            ts.register(get_types_from_msg(rec.data.decode(), _ros2_name(rec.name)))
                    elif isinstance(rec, Channel):
                        channels[rec.id] = rec
                    elif isinstance(rec, Message):
                        n += 1  # every message, read or not: each pass names the damage at the same place
                        ch = channels.get(rec.channel_id)
                        if ch is None or ch.topic not in topics:
                            continue
                        mtype = _ros2_name(schemas[ch.schema_id].name)
                        msg = (stores["ros1msg"].deserialize_ros1(rec.data, mtype) if ch.message_encoding == "ros1"
                               else stores["ros2msg"].deserialize_cdr(rec.data, mtype))
                        yield RawMessage(ch.topic, mtype, msg, rec.log_time)
            except Exception as e:  # noqa: BLE001 - EndOfFile, bad CRC, ...
                self.warnings.append(f"{file}: truncated or damaged after {n} messages "
                                     f"({type(e).__name__}); the readable part was used")


class _Db3Salvage:
    """The readable part of a truncated rosbag2 SQLite file.

    SQLite refuses a file shorter than its header's page count, so a copy is zero-padded to that
    size; rows on the missing pages then fail one by one and reading stops at the first such row.
    """

    def __init__(self, path: Path, cause: Exception) -> None:
        import sqlite3
        import struct
        import tempfile

        data = path.read_bytes()
        if len(data) < 100 or not data.startswith(b"SQLite format 3\0"):
            raise BagError(f"{path}: not an SQLite bag ({cause})") from cause
        page = struct.unpack(">H", data[16:18])[0] or 65536
        page = 65536 if page == 1 else page
        pages = struct.unpack(">I", data[28:32])[0]
        self._tmp = tempfile.NamedTemporaryFile(suffix=".db3")  # noqa: SIM115 - lives as long as the reader
        self._tmp.write(data + b"\0" * max(0, page * pages - len(data)))
        self._tmp.flush()
        self.path = path
        self._con = sqlite3.connect(f"file:{self._tmp.name}?mode=ro&immutable=1", uri=True, check_same_thread=False)
        try:
            rows = self._con.execute("SELECT id, name, type FROM topics").fetchall()
        except sqlite3.DatabaseError as e:
            raise BagError(f"{path}: damaged beyond reading ({e}); re-record the bag") from e
        self._ids = {i: (name, mtype) for i, name, mtype in rows}
        self.topics = {name: mtype for name, mtype in self._ids.values()}

    def messages(self, topics: set[str], warnings: list[str]) -> Iterator[RawMessage]:
        """Messages in recording order until the first unreadable row."""
        import sqlite3

        ts = typestore()
        n = 0
        try:
            for tid, t, data in self._con.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY id"):
                name, mtype = self._ids.get(tid, (None, None))
                if name in topics:
                    yield RawMessage(name, mtype, ts.deserialize_cdr(bytes(data), mtype), t)
                    n += 1
        except (sqlite3.DatabaseError, ValueError) as e:
            warnings.append(f"{self.path}: truncated or damaged after {n} messages ({e}); the readable part was used")


def _listing(topics: dict[str, str]) -> str:
    """A bag's topics with their types, for the errors that ask to choose among them."""
    return ", ".join(f"{t} [{m}]" for t, m in sorted(topics.items())) or "none"


def pick_topic(topics: dict[str, str], types: tuple[str, ...], what: str, wanted: str | None) -> str | None:
    """The one topic of ``types`` (or ``wanted``); a clear error listing the topics otherwise."""
    listing = _listing(topics)
    if wanted:
        if wanted not in topics:
            raise BagError(f"topic {wanted} not in the bag; it has: {listing}")
        if topics[wanted] not in types:
            raise BagError(f"--{what}-topic {wanted} carries {topics[wanted]}, not {' or '.join(types)}; the bag has: {listing}")
        return wanted
    found = [t for t, m in topics.items() if m in types]
    if len(found) == 1:
        return found[0]
    if not found:
        return None
    raise several(found, what, topics)


def several(found: list[str], what: str, topics: dict[str, str]) -> BagError:
    """The error for more than one candidate topic: names them, the option that chooses, and every topic in the bag."""
    return BagError(f"several {what} topics ({', '.join(sorted(found))}); choose one with --{what}-topic. "
                    f"Bag topics: {_listing(topics)}")


TRANSPORTS = ("compressed", "compressedDepth", "theora", "zstd", "ffmpeg", "h264")  # image_transport's sub-topics
VIDEO_TRANSPORTS = ("theora", "ffmpeg", "h264")  # the ones that carry a video stream, not images


def image_base(topic: str) -> str:
    """The image topic a transport's sub-topic carries (/cam/image_raw/compressed -> /cam/image_raw)."""
    head, _, last = topic.rstrip("/").rpartition("/")
    return head if last in TRANSPORTS and head else topic


def camera_namespace(topic: str) -> str:
    """The namespace of an image topic's camera, where its camera_info lives (/cam/image_raw/compressed -> /cam; ""
    for a topic at the root), as image_transport's camera subscriber finds it."""
    return image_base(topic).rpartition("/")[0]


def pick_image(topics: dict[str, str], wanted: str | None) -> tuple[str | None, str | None]:
    """The image topic (``wanted``, else the only one, else of one camera recorded with its transports too, as
    image_transport republishes it, the raw one; depth images beside it, as an RGB-D camera records them, are not
    frames for the front end) and a note when a choice was made."""
    found = sorted(t for t, m in topics.items() if m in IMAGE_TYPES)
    frames = [t for t in found if not is_depth(t)]
    bases = {image_base(t) for t in frames}
    if wanted is None and len(found) > 1 and len(bases) == 1:
        base = bases.pop()
        chosen = base if base in frames else frames[0] if len(frames) == 1 else None
        if chosen is not None:
            same, depth = [t for t in frames if t != chosen], [t for t in found if t not in frames]
            why = [f"the same frames on {', '.join(same)}"] * bool(same) + [f"the depth images on {', '.join(depth)}"] * bool(depth)
            return chosen, f"image topic {chosen} taken, not {' nor '.join(why)} (choose with --image-topic)"
    return pick_topic(topics, IMAGE_TYPES, "image", wanted), None


def msg_time(msg: Any) -> float:
    """A message's header stamp in seconds (NaN when it is no ROS time)."""
    return stamp_seconds(msg.header.stamp)


def choose_topics(reader: BagReader, image_topic: str | None = None, info_topic: str | None = None) -> dict[str, str | None]:
    """The image and camera_info topics to read: the ones named, else the only one of each type (of one camera's
    image and its transports, the raw one; of several camera_info topics, the one beside the image, as
    image_transport pairs them). Ground truth is chosen where it is read: :func:`.bag_truth.bag_ground_truth`.

    BagError, listing the bag's topics, when there is no image topic, a named one is missing or of another
    type, or a type has several topics and none is named.
    """
    topics = reader.topics
    img_t, note = pick_image(topics, image_topic)
    if note:
        reader.warnings.append(note)
    if img_t is None:
        listing = _listing(topics)
        damage = f"; reading stopped at {reader.damage}: the file is damaged or cut short" if reader.damage else ""
        video = [t for t in topics if t.rstrip("/").rpartition("/")[2] in VIDEO_TRANSPORTS]
        hint = (f"; {', '.join(video)} is video (image_transport's {'/'.join(VIDEO_TRANSPORTS)}), which the replay does "
                "not decode: record the camera's raw or /compressed topic") if video else ""
        raise BagError(f"{reader.path}: no sensor_msgs/Image or CompressedImage topic; the bag has: {listing}{damage}{hint}")
    infos = [t for t, m in topics.items() if m == "sensor_msgs/msg/CameraInfo"]
    sibling = f"{camera_namespace(img_t)}/camera_info"
    info_t = sibling if info_topic is None and len(infos) > 1 and sibling in infos else \
        pick_topic(topics, ("sensor_msgs/msg/CameraInfo",), "info", info_topic)
    return {"image": img_t, "camera_info": info_t}


def window_side(window: tuple[float, float] | None, first_ns: int, t_ns: int) -> int:
    """Where a message recorded at ``t_ns`` lies against ``window`` (seconds after the first frame, recorded at
    ``first_ns``; ``--start``/``--duration``): -1 before it, 0 in it (or no window), 1 after it."""
    if window is None:
        return 0
    after = (t_ns - first_ns) / 1e9
    return -1 if after < window[0] else 1 if after > window[1] else 0


class WindowWatch:
    """Where a bag's frames fall against ``--start``/``--duration``'s window (seconds after the first frame, by
    recording time), so that a window holding none can say where they are."""

    def __init__(self, window: tuple[float, float] | None) -> None:
        self.window = window
        self.first: int | None = None  # the first frame's recording time (ns)
        self.before: int | None = None  # the last frame before the window
        self.after: int | None = None  # the first frame after it
        self.inside = 0

    def side(self, t_ns: int, frame: bool = True) -> int:
        """:func:`window_side` of a message recorded at ``t_ns``; ``frame``: an image (the others are not counted,
        and before the first frame they lie before the window)."""
        if not frame:
            return 0 if self.window is None else -1 if self.first is None else window_side(self.window, self.first, t_ns)
        self.first = t_ns if self.first is None else self.first
        side = window_side(self.window, self.first, t_ns)
        if side < 0:
            self.before = t_ns
        elif side > 0:
            self.after = t_ns  # the loops stop here: the first frame after the window
        else:
            self.inside += 1
        return side

    def missed(self) -> str | None:
        """What to say when the window held no frame (None when it held some, or when there was none)."""
        if self.window is None or self.inside or self.first is None or self.before is None:
            return None
        start, end = self.window
        at = f"no frame in --start/--duration's {start:g} .. {end:g} s (seconds after the bag's first frame): "
        before = (self.before - self.first) / 1e9
        if self.after is None:
            return at + f"the bag ends before, its last frame {before:.3f} s after its first"
        return at + (f"it falls between the frames at {before:.3f} s and {(self.after - self.first) / 1e9:.3f} s; "
                     "give a longer --duration")


def read_frames(reader: BagReader, image_topic: str | None = None, info_topic: str | None = None,
                rectified: bool = False, recorded: bool = False,
                window: tuple[float, float] | None = None,
                max_pixels: int = MAX_PIXELS) -> tuple[Iterator[Frame], dict[str, str | None]]:
    """Frames of a bag with auto-detected topics (ground truth: :func:`.bag_truth.bag_ground_truth`); errors name the topics the
    bag has.

    ``rectified``: the images are rectified, so their camera is camera_info's P (see caminfo). ``recorded``: each
    frame's stamp is the time the bag recorded it, not its header's (a driver that leaves the stamp at 0).
    ``window``: only the frames recorded from ``window[0]`` to ``window[1]`` seconds after the first (a part of a
    long bag; the camera_info before it still counts), and reading stops after it. ``max_pixels``: the node's
    max_image_pixels; a larger frame (or one over 4x camera_info's size) is not decoded, its error says why.
    """
    chosen = choose_topics(reader, image_topic, info_topic)
    img_t, info_t = chosen["image"], chosen["camera_info"]

    def gen() -> Iterator[Frame]:
        camera, camera_error = None, None
        pending: list[tuple[float, np.ndarray | None, str | None, str]] = []
        watch = WindowWatch(window)
        for m in reader.messages({t for t in (img_t, info_t) if t}):
            if m.topic == info_t:
                try:
                    camera, camera_error = camera_from_info(m.msg, rectified), None
                except (CameraError, ValueError) as e:
                    camera_error = str(e)  # the frames keep the last good calibration, if any, and say why not this one
                continue
            if (side := watch.side(m.log_time_ns)) > 0:
                break
            if side < 0:
                continue
            try:
                cap = pixel_cap(max_pixels, (camera.width, camera.height) if camera is not None else None)
                img, err = decode_message(m.msg, cap), None
            except ImageError as e:
                img, err = None, str(e)
            if watch.inside == 1 and (note := depth_encoding_note(img_t, getattr(m.msg, "encoding", ""), BAG_DEPTH_ADVICE)):
                reader.warnings.append(note)  # once, on the first frame read
            pending.append((m.log_time_ns / 1e9 if recorded else msg_time(m.msg), img, err, m.msg.header.frame_id))
            # camera_info shares the image stamp and may come just after it
            while len(pending) > 1:
                s, im, er, fid = pending.pop(0)
                yield Frame(s, im, er, camera, camera_error, fid)
        for s, im, er, fid in pending:
            yield Frame(s, im, er, camera, camera_error, fid)
        if missed := watch.missed():
            reader.warnings.append(missed)

    return gen(), chosen


def image_frame(reader: BagReader, topic: str) -> str:
    """The frame_id of the first message on the image ``topic`` ("" when there is none): the camera's optical frame,
    as its driver names it."""
    first = next(iter(reader.messages({topic})), None)
    return first.msg.header.frame_id if first is not None else ""
