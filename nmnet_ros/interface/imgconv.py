"""sensor_msgs/Image and CompressedImage payloads <-> numpy, without ROS imports.

Works on any object with the message's fields (rclpy messages, rosbags messages), so the node
and the bag tools share one converter. Bad payloads raise :class:`ImageError` saying what is
wrong and what the sender should do.
"""

from __future__ import annotations

from array import array
from typing import Any

import cv2
import numpy as np

from ..core.settings import BY_NAME

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")  # the messages frames come in
Buffer = bytes | bytearray | memoryview | array | np.ndarray  # a message's data: array('B') from rclpy, uint8 arrays from rosbags

# encoding -> (channels, dtype, conversion to the pipeline's BGR/mono); names as sensor_msgs/image_encodings.h
ENCODINGS: dict[str, tuple[int, np.dtype, int | None]] = {
    "mono8": (1, np.dtype(np.uint8), None),
    "8uc1": (1, np.dtype(np.uint8), None),
    "mono16": (1, np.dtype(np.uint16), None),
    "16uc1": (1, np.dtype(np.uint16), None),
    "bgr8": (3, np.dtype(np.uint8), None),
    "rgb8": (3, np.dtype(np.uint8), cv2.COLOR_RGB2BGR),
    "bgra8": (4, np.dtype(np.uint8), cv2.COLOR_BGRA2BGR),
    "rgba8": (4, np.dtype(np.uint8), cv2.COLOR_RGBA2BGR),
    "bgr16": (3, np.dtype(np.uint16), None),
    "rgb16": (3, np.dtype(np.uint16), cv2.COLOR_RGB2BGR),
    "bgra16": (4, np.dtype(np.uint16), cv2.COLOR_BGRA2BGR),
    "rgba16": (4, np.dtype(np.uint16), cv2.COLOR_RGBA2BGR),
    # OpenCV's type names: what cv_bridge's cv2_to_imgmsg(frame) sends without an encoding ("passthrough"), in
    # OpenCV's BGR(A) order
    "8uc3": (3, np.dtype(np.uint8), None),
    "8uc4": (4, np.dtype(np.uint8), cv2.COLOR_BGRA2BGR),
    "16uc3": (3, np.dtype(np.uint16), None),
    "16uc4": (4, np.dtype(np.uint16), cv2.COLOR_BGRA2BGR),
    # raw sensor mosaics (machine-vision drivers), demosaiced here; the pattern names the top-left 2x2 block
    **{f"bayer_{p}{bits}": (1, np.dtype(np.uint8 if bits == 8 else np.uint16), getattr(cv2, f"COLOR_Bayer{p.upper()}2BGR"))
       for p in ("rggb", "bggr", "gbrg", "grbg") for bits in (8, 16)},
    # packed 4:2:2 (USB/UVC cameras): "yuv422" is UYVY, "yuv422_yuy2" is YUYV
    "yuv422": (2, np.dtype(np.uint8), cv2.COLOR_YUV2BGR_UYVY),
    "uyvy": (2, np.dtype(np.uint8), cv2.COLOR_YUV2BGR_UYVY),
    "yuv422_yuy2": (2, np.dtype(np.uint8), cv2.COLOR_YUV2BGR_YUY2),
    "yuyv": (2, np.dtype(np.uint8), cv2.COLOR_YUV2BGR_YUY2),
}
# semi-planar YUV (phone, Jetson and V4L2 cameras): a full-size luma plane, then interleaved chroma at half (4:2:0) or
# full (4:4:4) resolution; value: chroma rows per luma row and their bytes per luma byte. Only the luma plane is read:
# it is the grey image the detector works on (what OpenCV's COLOR_YUV2GRAY_NV21 returns).
SEMI_PLANAR: dict[str, tuple[float, int]] = {"nv12": (0.5, 1), "nv21": (0.5, 1), "nv24": (1.0, 2)}
FLOAT_ENCODINGS = ("32fc1", "64fc1")  # what depth cameras and stereo matchers publish (metres, disparities)


def _bytes(data: Buffer) -> np.ndarray:
    """A message's data as a flat uint8 array, without a copy."""
    return np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8).ravel()


class ImageError(ValueError):
    """An image message that cannot be turned into pixels."""


def image_to_array(height: int, width: int, encoding: str, step: int, data: Buffer, is_bigendian: int = 0) -> np.ndarray:
    """Image message fields -> (H,W) or (H,W,3) array (BGR for colour), zero-copy where possible."""
    enc = encoding.lower()
    if enc not in ENCODINGS and enc not in SEMI_PLANAR:
        depth = " (float pixels: a depth or disparity stream? remap image to the camera's colour or mono stream)" \
            if enc in FLOAT_ENCODINGS else ""
        raise ImageError(f"unsupported image encoding {encoding!r}{depth}; publish one of "
                         f"{', '.join([*ENCODINGS, *SEMI_PLANAR])}")
    if height <= 0 or width <= 0:
        raise ImageError(f"image is {width}x{height}: nothing to process (check the camera driver)")
    if enc in SEMI_PLANAR:
        return _luma(height, width, encoding, step, _bytes(data))
    ch, dtype, conv = ENCODINGS[enc]
    if ch == 2 and width % 2:
        raise ImageError(f"{encoding} packs two pixels in four bytes, so its width must be even, got {width}")
    row = width * ch * dtype.itemsize
    if step < row:
        raise ImageError(f"step {step} is smaller than width*channels*bytes = {row} for {encoding}")
    buf = _bytes(data)
    if buf.size < height * step:
        raise ImageError(f"image data has {buf.size} bytes, expected height*step = {height}*{step} = {height * step}; "
                         "the message is truncated")
    rows = buf[: height * step].reshape(height, step)[:, :row]
    arr = rows.view(dtype.newbyteorder(">" if is_bigendian else "<") if dtype.itemsize > 1 else dtype)
    arr = arr.reshape(height, width, ch) if ch > 1 else arr.reshape(height, width)
    if dtype.itemsize > 1 and is_bigendian:
        arr = arr.astype(dtype)
    if conv is not None:
        arr = cv2.cvtColor(np.ascontiguousarray(arr), conv)
    return arr


def _luma(height: int, width: int, encoding: str, step: int, buf: np.ndarray) -> np.ndarray:
    """The luma plane of a semi-planar YUV frame as a mono8 (H,W) view. ``step`` is the luma rows' stride (V4L2's
    bytesperline, as rviz reads it); a step of twice the width (a driver that counted two channels) with data too
    short for it is read as rows of ``width`` bytes."""
    rows, per_byte = SEMI_PLANAR[encoding.lower()]

    def frame_bytes(stride: int) -> int:
        return height * stride + int(np.ceil(height * rows)) * stride * per_byte

    if step < width:
        raise ImageError(f"step {step} is smaller than the width {width} of {encoding}'s luma plane")
    stride = width if step == 2 * width and buf.size < frame_bytes(step) else step
    if buf.size < frame_bytes(stride):
        raise ImageError(f"image data has {buf.size} bytes, expected {frame_bytes(stride)} for a {width}x{height} "
                         f"{encoding} frame of rows of {stride} bytes (luma, then chroma); the message is truncated")
    return buf[: height * stride].reshape(height, stride)[:, :width]


COMPRESSED_FORMATS = ("jpeg", "png")  # what CompressedImage may hold: image_transport's compressed codecs
MAX_PIXELS = BY_NAME["max_image_pixels"].default  # 20 MP (5472x3648); 22 MP peak at 1.4 GB through the front end
CALIBRATED_SCALE = 4  # a frame may have up to this many times the calibrated pixels (a stream resized up 2x)
_PNG = b"\x89PNG\r\n\x1a\n"
_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})  # JPEG frame headers


def pixel_cap(max_pixels: int, calibrated: tuple[int, int] | None = None) -> int:
    """The most pixels a frame may have: ``max_pixels``, or ``CALIBRATED_SCALE`` times the calibrated size
    (``calibrated``: width, height; None or 0 when not known), whichever is smaller."""
    if calibrated and calibrated[0] > 0 and calibrated[1] > 0:
        return min(max_pixels, CALIBRATED_SCALE * calibrated[0] * calibrated[1])
    return max_pixels


def _too_large(width: int, height: int, max_pixels: int, what: str) -> ImageError:
    return ImageError(f"{what} is {width}x{height} = {width * height / 1e6:.1f} MP, over the cap of "
                      f"{max_pixels / 1e6:.1f} MP (max_image_pixels, or {CALIBRATED_SCALE}x camera_info's size): not "
                      "decoded; publish frames of the calibrated size, or raise max_image_pixels")


def compressed_header(buf: np.ndarray) -> tuple[str, int, int]:
    """(format, width, height) of a JPEG or PNG from its header, without decoding it; ImageError for any other
    data, so a PFM, HDR, TIFF or WebP (or a decompression bomb in any format) is never handed to the decoder."""
    head = buf[:32].tobytes()
    if head.startswith(_PNG):
        if len(head) < 24 or head[12:16] != b"IHDR":
            raise ImageError("PNG data without its IHDR header: corrupt or truncated")
        return "png", int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if head.startswith(b"\xff\xd8"):
        data, i = buf, 2
        while i + 4 <= data.size:  # segments: 0xFF, marker, 2-byte length (which counts itself), payload
            if data[i] != 0xFF:
                break
            marker = int(data[i + 1])
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # stand-alone markers
                i += 2
                continue
            length = int(data[i + 2]) << 8 | int(data[i + 3])
            if marker in _SOF and i + 9 <= data.size:
                height, width = int(data[i + 5]) << 8 | int(data[i + 6]), int(data[i + 7]) << 8 | int(data[i + 8])
                return "jpeg", width, height
            if marker == 0xDA or length < 2:  # scan data before a frame header
                break
            i += 2 + length
        raise ImageError("JPEG data without a readable frame header (SOF): corrupt or truncated")
    raise ImageError(f"compressed data is neither JPEG nor PNG (it starts {head[:8]!r}); the node reads "
                     f"{' and '.join(COMPRESSED_FORMATS)} (image_transport's compressed codecs)")


def decode_compressed(fmt: str, data: Buffer, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """CompressedImage (JPEG or PNG, 8 or 16 bits) -> mono or BGR array; ImageError for other data, or a frame of
    more than ``max_pixels`` (found in the header: such a frame is never decoded)."""
    buf = _bytes(data)
    if buf.size == 0:
        raise ImageError("compressed image has no data")
    if "compresseddepth" in fmt.lower():  # image_transport's depth codec: a header, then 16-bit depth or inverse depth
        raise ImageError(f"format {fmt!r} is a depth camera's compressedDepth stream, not camera frames: subscribe "
                         "the camera's colour or mono stream (its /compressed topic)")
    kind, width, height = compressed_header(buf)
    if width <= 0 or height <= 0:
        raise ImageError(f"{kind} header says {width}x{height}: nothing to decode (corrupt data)")
    if width * height > max_pixels:
        raise _too_large(width, height, max_pixels, f"{kind} frame")
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise ImageError(f"cannot decode compressed image (format {fmt!r}, {buf.size} bytes): corrupt or truncated data")
    if img.dtype not in (np.uint8, np.uint16) or img.shape[:2] != (height, width):
        raise ImageError(f"{kind} decoded to {img.dtype} {img.shape}, not the 8- or 16-bit {width}x{height} image its "
                         "header describes")
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


def decode_message(msg: Any, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """An Image or CompressedImage message (rclpy or rosbags; told apart by its ``format`` field) -> array, with the
    checks above; ImageError when unusable."""
    if hasattr(msg, "format"):
        return decode_compressed(msg.format, msg.data, max_pixels)
    if msg.height * msg.width > max_pixels:
        raise _too_large(msg.width, msg.height, max_pixels, "image")
    return image_to_array(msg.height, msg.width, msg.encoding, msg.step, msg.data, msg.is_bigendian)


def array_to_image_fields(img: np.ndarray) -> dict:
    """Array -> Image message fields (mono8/mono16/bgr8); ``data`` as bytes (fast to assign in rclpy)."""
    img = np.ascontiguousarray(img)
    if img.ndim == 2:
        enc = "mono16" if img.dtype == np.uint16 else "mono8"
        ch = 1
    elif img.ndim == 3 and img.shape[2] == 3:
        enc, ch = "bgr8", 3
    else:
        raise ImageError(f"cannot encode array of shape {img.shape} as an image")
    if enc != "mono16":
        img = img.astype(np.uint8, copy=False)
    return {"height": img.shape[0], "width": img.shape[1], "encoding": enc, "is_bigendian": 0,
            "step": img.shape[1] * ch * img.dtype.itemsize, "data": img.tobytes()}


# ~/matches' point layout: name, sensor_msgs/PointField datatype (7 FLOAT32, 6 UINT32); 24 bytes, little-endian
MATCH_FIELDS = (("u0", 7), ("v0", 7), ("u1", 7), ("v1", 7), ("score", 7), ("track_id", 6))
_POINT_TYPES = {7: "<f4", 6: "<u4"}  # the PointField datatypes ~/matches uses, as numpy types
_MATCH_DTYPE = np.dtype([(name, _POINT_TYPES[kind]) for name, kind in MATCH_FIELDS])


def matches_to_cloud_fields(k0: np.ndarray, k1: np.ndarray, scores: np.ndarray, track_ids: np.ndarray) -> dict:
    """One point per match (float32 u0 v0 u1 v1 score, uint32 track_id) -> PointCloud2 fields: (name, offset,
    datatype) triples and the data. Track ids wrap at 2**32 (see tracks.py)."""
    pts = np.empty(len(scores), _MATCH_DTYPE)
    k0, k1 = np.asarray(k0, np.float32).reshape(-1, 2), np.asarray(k1, np.float32).reshape(-1, 2)
    pts["u0"], pts["v0"], pts["u1"], pts["v1"] = k0[:, 0], k0[:, 1], k1[:, 0], k1[:, 1]
    pts["score"] = scores
    pts["track_id"] = np.asarray(track_ids, np.int64) % 2**32
    n, step = len(pts), _MATCH_DTYPE.itemsize
    return {"height": 1, "width": n, "point_step": step, "row_step": step * n, "is_bigendian": False, "is_dense": True,
            "fields": [(name, _MATCH_DTYPE.fields[name][1], kind) for name, kind in MATCH_FIELDS], "data": pts.tobytes()}


def matches_of_cloud(point_step: int, fields: list, data: Buffer) -> dict[str, np.ndarray]:
    """A ``~/matches`` PointCloud2 read back by its field names (any rclpy or rosbags message's fields)."""
    if odd := [f.name for f in fields if f.datatype not in _POINT_TYPES]:
        raise ValueError(f"not a ~/matches cloud: fields {odd} are neither float32 nor uint32")
    dtype = np.dtype({"names": [f.name for f in fields], "formats": [_POINT_TYPES[f.datatype] for f in fields],
                      "offsets": [f.offset for f in fields], "itemsize": point_step})
    pts = np.frombuffer(_bytes(data), dtype)
    return {name: pts[name] for name in dtype.names}
