"""CameraInfo -> Camera: ROS 1 and ROS 2 fields, binning and ROI as image_geometry reads them, fitting to frames."""

from __future__ import annotations

import numpy as np
import pytest

from nmnet_ros.core.geometry import Camera, CameraError
from nmnet_ros.interface.caminfo import camera_from_info, fit_camera
from nmnet_ros.io.bags import typestore

K_FULL = np.array([[800.0, 0, 640.5], [0, 810.0, 360.25], [0, 0, 1]])
D = np.array([-0.2, 0.05, 0.001, -0.0005, 0.0])


def info(ros1: bool = False, binning: tuple[int, int] = (0, 0), roi: tuple[int, int, int, int] = (0, 0, 0, 0),
         model: str = "plumb_bob"):
    """A real (rosbags) CameraInfo of a 1280x720 sensor."""
    ts = typestore(ros1)
    names = ("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p")
    Roi = ts.types["sensor_msgs/msg/RegionOfInterest"]
    header = ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="cam",
                                             **({"seq": 0} if ros1 else {}))
    return ts.types["sensor_msgs/msg/CameraInfo"](
        header=header, height=720, width=1280, distortion_model=model,
        **dict(zip(names, (D, K_FULL.ravel(), np.eye(3).ravel(), np.c_[K_FULL, np.zeros(3)].ravel()), strict=True)),
        binning_x=binning[0], binning_y=binning[1],
        roi=Roi(x_offset=roi[0], y_offset=roi[1], width=roi[2], height=roi[3], do_rectify=False))


@pytest.mark.parametrize("ros1", [False, True])
def test_full_frame_camera_info_in_both_ros_versions(ros1):
    cam = camera_from_info(info(ros1))
    np.testing.assert_array_equal(cam.K, K_FULL)
    np.testing.assert_array_equal(cam.dist, D)
    assert (cam.width, cam.height, cam.model) == (1280, 720, "plumb_bob")


def test_binning_and_roi_give_the_same_rays_as_the_full_frame():
    full = camera_from_info(info())
    cam = camera_from_info(info(binning=(2, 2), roi=(100, 40, 800, 600)))
    assert (cam.width, cam.height) == (400, 300)
    px_full = np.array([[150.0, 60.0], [500.0, 400.0], [880.0, 620.0]])  # inside the ROI
    px = (px_full - [100, 40]) / 2  # the same points in the binned ROI image
    np.testing.assert_allclose(cam.normalize(px), full.normalize(px_full), atol=1e-9)


def test_a_bad_camera_info_is_refused_with_the_reason():
    msg = info()
    msg.k = np.zeros(9)
    with pytest.raises(CameraError, match="focal lengths must be positive"):
        camera_from_info(msg)
    with pytest.raises(CameraError, match="distortion model 'fov' is not supported"):
        camera_from_info(info(model="fov"))
    msg = info()
    msg.k = np.ones(6)
    with pytest.raises(CameraError, match="camera_info K must have 9 values, got 6"):
        camera_from_info(msg)
    msg.p = np.ones(9)
    with pytest.raises(CameraError, match="camera_info P must have 12 values, got 9"):
        camera_from_info(msg, rectified=True)


def test_k_is_inverted_with_its_skew_and_a_k_not_ending_in_0_0_1_is_refused():
    """Normalised coordinates are K^-1 [u v 1] also with a skew term (it was dropped: 0.004 off at a skew of 3 on
    this K, 2 px at fx 500). A K whose last row is not 0 0 1 (a homogeneous scale, rows swapped) was used as if it
    were; now it is refused, naming the rows."""
    K = np.array([[500.0, 3.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
    px = np.random.default_rng(0).random((50, 2)) * 600
    expected = (np.linalg.inv(K) @ np.c_[px, np.ones(50)].T).T[:, :2]
    np.testing.assert_allclose(Camera(K, np.zeros(5), 640, 480).normalize(px), expected, atol=1e-12)
    for last in ([0.0, 0.0, 2.0], [0.0, 0.0, 0.0], [320.0, 240.0, 1.0]):
        with pytest.raises(CameraError, match=r"K must be \[fx s cx; 0 fy cy; 0 0 1\], got rows 2-3"):
            Camera(np.vstack([K[:2], last]))
    with pytest.raises(CameraError, match=r"got rows 2-3 \[5.0, 480.0, 240.0\] \[0.0, 0.0, 1.0\]"):
        Camera(K + [[0, 0, 0], [5.0, 0, 0], [0, 0, 0]])  # rows in the wrong order, or a transposed K


def test_frames_are_fitted_to_their_calibration():
    cam = Camera(K_FULL, D, 1280, 720)
    assert fit_camera(cam, (1280, 720)) == (cam, None)
    half, note = fit_camera(cam, (640, 360))
    assert "frames are 640x360 but camera_info describes 1280x720: K scaled by 0.5 to fit" in note
    px_full = np.array([[10.5, 20.5], [1000.0, 700.0]])
    np.testing.assert_allclose(half.normalize((px_full + 0.5) * 0.5 - 0.5), cam.normalize(px_full), atol=1e-9)
    crop, note = fit_camera(cam, (1280, 600))
    assert crop is None and "not the same image scaled" in note and "frame skipped" in note
    nosize = Camera(K_FULL)  # fx..cy parameters: no size of their own; they take the frames' and are checked against it
    sized, note = fit_camera(nosize, (1280, 720))
    assert note is None and (sized.width, sized.height) == (1280, 720) and np.array_equal(sized.K, K_FULL)
    with pytest.raises(CameraError, match="principal point cx = 640.5 px lies far outside the 320x240 image"):
        fit_camera(nosize, (320, 240))


def test_rectified_frames_take_the_projection_matrix_without_distortion():
    msg = info()
    P = K_FULL.copy()
    P[0, 0] = P[1, 1] = 700.0  # rectification picks its own focal length
    msg.p = np.c_[P, np.zeros(3)].ravel()
    cam = camera_from_info(msg, rectified=True)
    np.testing.assert_array_equal(cam.K, P)
    assert not cam.dist.any() and (cam.width, cam.height) == (1280, 720)
    msg.p = np.zeros(12)
    with pytest.raises(CameraError, match="P is all zero"):
        camera_from_info(msg, rectified=True)


def test_a_resized_camera_sees_the_same_rays_and_needs_a_size_to_start_from():
    cam = Camera(K_FULL, D, 1280, 720)
    small = cam.resized(640, 480)  # uneven, as the bench's 640x480 runs of other cameras
    px = np.array([[10.5, 20.5], [1000.0, 700.0]])
    np.testing.assert_allclose(small.normalize((px + 0.5) * [0.5, 480 / 720] - 0.5), cam.normalize(px), atol=1e-9)
    np.testing.assert_allclose(Camera(K_FULL).resized(640, 360, (1280, 720)).K, cam.resized(640, 360).K)
    with pytest.raises(CameraError, match="no image size to resize from"):
        Camera(K_FULL).resized(640, 480)
