"""Image payloads -> pixels for every encoding the node and the bag tools accept (no ROS needed)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from nmnet_ros.interface.imgconv import ImageError, decode_compressed, image_to_array

from .conftest import data_dir

BGR = (30, 120, 220)  # a flat colour with three different channels: a swapped channel shows


def mosaic(pattern: str, shape: tuple[int, int], dtype=np.uint8, scale: int = 1) -> np.ndarray:
    """A flat-colour BGR image as a raw sensor with the given 2x2 pattern (``pattern[0]`` top left)."""
    value = {"b": BGR[0], "g": BGR[1], "r": BGR[2]}
    raw = np.zeros(shape, dtype)
    for i, colour in enumerate(pattern):
        raw[i // 2::2, i % 2::2] = value[colour] * scale
    return raw


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_images_are_demosaiced_to_their_colours(pattern, bits):
    dtype, scale = (np.uint8, 1) if bits == 8 else (np.uint16, 256)
    raw = mosaic(pattern, (12, 16), dtype, scale)
    img = image_to_array(12, 16, f"bayer_{pattern}{bits}", 16 * raw.itemsize, raw.tobytes())
    assert img.shape == (12, 16, 3) and img.dtype == dtype
    np.testing.assert_array_equal(img[2:-2, 2:-2].reshape(-1, 3) // scale, np.tile(BGR, ((12 - 4) * (16 - 4), 1)))


@pytest.mark.parametrize("encoding,order", [("yuv422", "uyvy"), ("uyvy", "uyvy"), ("yuv422_yuy2", "yuyv"),
                                            ("yuyv", "yuyv")])
def test_packed_yuv422_is_read_in_its_byte_order(encoding, order):
    # luminance rising left to right, chroma pushing towards red (V > 128) and away from blue (U < 128)
    h, w = 4, 8
    y = np.tile(np.linspace(40, 200, w).astype(np.uint8), (h, 1))
    packed = np.empty((h, w * 2), np.uint8)
    u, v = 100, 170
    if order == "uyvy":
        packed[:, 0::4], packed[:, 1::2], packed[:, 2::4] = u, y, v
    else:
        packed[:, 1::4], packed[:, 0::2], packed[:, 3::4] = u, y, v
    img = image_to_array(h, w, encoding, w * 2, packed.tobytes()).astype(int)
    assert img.shape == (h, w, 3)
    assert (img[..., 2] > img[..., 1]).all() and (img[..., 2] > img[..., 0]).all()  # red dominates everywhere
    assert (np.diff(img.mean(2), axis=1) > 0).all()  # and brightness follows Y along each row


def test_an_odd_width_yuv422_image_is_refused():
    with pytest.raises(ImageError, match="width must be even, got 7"):
        image_to_array(2, 7, "yuv422", 16, bytes(32))


@pytest.mark.parametrize("encoding", ["nv12", "nv21", "NV24"])
@pytest.mark.parametrize("layout", ["tight", "padded rows", "step of two channels"])
def test_semi_planar_yuv_is_read_as_its_luma_plane(encoding, layout):
    """NV12/NV21/NV24 (phone, Jetson and V4L2 cameras) were refused as unsupported; their luma plane is the grey image
    the detector reads. The step is the luma rows' stride; a driver that gave width * 2 (two channels) with tightly
    packed rows is read too."""
    h, w = 6, 8
    bgr = np.random.default_rng(0).integers(0, 256, (h, w, 3), np.uint8)
    luma = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420)[:h]  # BT.601 Y, as a camera's encoder writes it
    stride = {"tight": w, "padded rows": w + 4, "step of two channels": w}[layout]
    chroma_rows = h if encoding == "NV24" else h // 2
    chroma_bytes = chroma_rows * stride * (2 if encoding == "NV24" else 1)
    frame = np.full(h * stride + chroma_bytes, 128, np.uint8)
    frame[: h * stride].reshape(h, stride)[:, :w] = luma
    step = 2 * w if layout == "step of two channels" else stride
    img = image_to_array(h, w, encoding, step, frame.tobytes())
    assert img.shape == (h, w) and img.dtype == np.uint8
    np.testing.assert_array_equal(img, luma)
    if layout == "tight" and encoding != "NV24":  # the grey image OpenCV reads from the same frame
        np.testing.assert_array_equal(img, cv2.cvtColor(frame.reshape(-1, w), cv2.COLOR_YUV2GRAY_NV21))
    with pytest.raises(ImageError, match=f"image data has {frame.size - 1} bytes, expected .* for a 8x6 {encoding} "
                                         f"frame of rows of {stride} bytes .*; the message is truncated"):
        image_to_array(h, w, encoding, step, frame[:-1].tobytes())


@pytest.mark.parametrize("encoding, order, dtype", [
    ("rgb8", "rgb", np.uint8), ("bgra8", "bgra", np.uint8), ("rgba8", "rgba", np.uint8),
    ("bgr16", "bgr", np.uint16), ("rgb16", "rgb", np.uint16), ("bgra16", "bgra", np.uint16), ("rgba16", "rgba", np.uint16),
    ("8UC3", "bgr", np.uint8), ("8UC4", "bgra", np.uint8), ("16UC3", "bgr", np.uint16), ("16UC4", "bgra", np.uint16),
])
def test_colour_encodings_come_out_as_bgr(encoding, order, dtype):
    scale = 1 if dtype == np.uint8 else 256
    value = {"b": BGR[0] * scale, "g": BGR[1] * scale, "r": BGR[2] * scale, "a": 255 * scale}
    px = np.array([value[c] for c in order], dtype)
    raw = np.tile(px, (3, 5, 1))
    img = image_to_array(3, 5, encoding, 5 * raw.shape[2] * raw.itemsize, raw.tobytes())
    assert img.shape == (3, 5, 3) and img.dtype == dtype
    np.testing.assert_array_equal(img.reshape(-1, 3) // scale, np.tile(BGR, (15, 1)))


def test_rows_with_padding_and_big_endian_are_read_right():
    mono = np.arange(12, dtype=">u2").reshape(3, 4)
    padded = np.zeros((3, 10), np.uint8)  # 8 bytes of pixels + 2 of padding per row
    padded[:, :8] = mono.view(np.uint8).reshape(3, 8)
    out = image_to_array(3, 4, "mono16", 10, padded.tobytes(), is_bigendian=1)
    np.testing.assert_array_equal(out, mono.astype(np.uint16))


@pytest.mark.parametrize("fields,needle", [
    ((2, 2, "bayer_xyz8", 2, bytes(4)), "unsupported image encoding 'bayer_xyz8'; publish one of mono8"),
    ((2, 4, "bayer_rggb16", 8, bytes(10)), "the message is truncated"),
    ((2, 4, "bgr8", 4, bytes(24)), "step 4 is smaller than width*channels*bytes = 12"),
    ((2, 4, "nv21", 3, bytes(24)), "step 3 is smaller than the width 4 of nv21's luma plane"),
    ((2, 2, "32FC1", 8, bytes(16)), "unsupported image encoding '32FC1' (float pixels: a depth or disparity stream? "
                                    "remap image to the camera's colour or mono stream); publish one of mono8"),
])
def test_bad_payloads_say_what_is_wrong(fields, needle):
    with pytest.raises(ImageError) as err:
        image_to_array(*fields)
    assert needle in str(err.value)


def test_a_compressed_depth_stream_is_named_not_called_corrupt():
    """image_transport's compressedDepth (a 12-byte header, then a PNG of 16-bit depth) on the node's image/compressed
    input, an easy remap slip on an RGB-D camera: said as such (it was "corrupt or truncated data")."""
    depth = np.full((48, 64), 1500, np.uint16)
    data = bytes(12) + cv2.imencode(".png", depth)[1].tobytes()
    with pytest.raises(ImageError, match="'16UC1; compressedDepth png' is a depth camera's compressedDepth stream, not "
                                         "camera frames: subscribe the camera's colour or mono stream"):
        decode_compressed("16UC1; compressedDepth png", data)
    assert decode_compressed("mono16; png compressed mono16", cv2.imencode(".png", depth)[1]).dtype == np.uint16


@pytest.mark.parametrize("name", ["sift", "hessian-affine-fast"])
def test_a_12_bit_camera_in_mono16_gives_the_features_of_its_8_bit_frame(name):
    """A 12-bit camera's mono16 frames (white = 4095) are not 16x too dark for the detectors."""
    from nmnet_ros.core.detectors import make_detector

    path = sorted((data_dir("kitti-07") / "images").iterdir())[0]
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    twelve = (gray.astype(np.uint16) << 4) | (gray.astype(np.uint16) >> 4)  # 0..255 -> 0..4095
    det = make_detector(name, {"max_keypoints": 2000})
    eight, deep = det(gray), det(twelve)
    assert len(eight.keypoints) > 500
    assert abs(len(deep.keypoints) - len(eight.keypoints)) <= 0.02 * len(eight.keypoints)


def test_one_cameras_16_bit_frames_share_a_scale_whatever_their_exposure():
    """A 12-bit camera's frames peaking at 1500, 2000 or 4095 are all scaled by 4095 (by the bits in use, a frame
    peaking at 2000 was scaled by 2047, twice the next one's contrast); 8-bit data in 16 bits keeps 255."""
    from nmnet_ros.core.features import full_scale

    for peak, white in ((1500, 4095), (2000, 4095), (3000, 4095), (4095, 4095), (1000, 1023), (200, 255), (16000, 16383),
                        (65535, 65535)):
        assert full_scale(np.array([[0, peak]], np.uint16)) == white, peak
    assert full_scale(np.zeros((2, 2), np.uint16)) == 255 and full_scale(np.zeros((2, 2), np.uint8)) == 255
