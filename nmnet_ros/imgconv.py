"""sensor_msgs/Image and CompressedImage payloads <-> numpy, without ROS imports.

Works on any object with the message's fields (rclpy messages, rosbags messages), so the node
and the bag tools share one converter. Bad payloads raise :class:`ImageError` saying what is
wrong and what the sender should do.
"""

from __future__ import annotations

from array import array

import cv2
import numpy as np

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


def _bytes(data: Buffer) -> np.ndarray:
    """A message's data as a flat uint8 array, without a copy."""
    return np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8).ravel()


class ImageError(ValueError):
    """An image message that cannot be turned into pixels."""


def image_to_array(height: int, width: int, encoding: str, step: int, data: Buffer, is_bigendian: int = 0) -> np.ndarray:
    """Image message fields -> (H,W) or (H,W,3) array (BGR for colour), zero-copy where possible."""
    enc = encoding.lower()
    if enc not in ENCODINGS:
        raise ImageError(f"unsupported image encoding {encoding!r}; publish one of {', '.join(ENCODINGS)}")
    if height <= 0 or width <= 0:
        raise ImageError(f"image is {width}x{height}: nothing to process (check the camera driver)")
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


def decode_compressed(fmt: str, data: Buffer) -> np.ndarray:
    """CompressedImage (jpeg/png) -> array as cv2.imdecode gives it (mono or BGR)."""
    buf = _bytes(data)
    if buf.size == 0:
        raise ImageError("compressed image has no data")
    if "compresseddepth" in fmt.lower():  # image_transport's depth codec: a header, then 16-bit depth or inverse depth
        raise ImageError(f"format {fmt!r} is a depth camera's compressedDepth stream, not camera frames: subscribe "
                         "the camera's colour or mono stream (its /compressed topic)")
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise ImageError(f"cannot decode compressed image (format {fmt!r}, {buf.size} bytes): corrupt or truncated data")
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


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
