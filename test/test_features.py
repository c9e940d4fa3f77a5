"""Hessian-affine features: bad images, and local affine frames against the boat homographies."""

import cv2
import numpy as np
import pytest

from nmnet_ros.core.features import Features, SiftSimilarity
from nmnet_ros.core.geometry import homography_jacobian
from nmnet_ros.core.matching import match_descriptors

from .conftest import data_dir


@pytest.mark.parametrize("image", [
    np.zeros((480, 640), np.uint8),  # blank
    np.full((480, 640, 3), 128, np.uint8),  # blank colour
    np.zeros((10, 10), np.uint8),  # tiny
    np.zeros((0, 0), np.uint8),  # empty
])
def test_blank_tiny_empty_images_give_empty_features(any_detector, image):
    f = any_detector(image)
    assert len(f) == 0 and f.frames.shape == (0, 2, 2) and f.descriptors.shape == (0, 128)


def test_bad_channel_count_is_a_clear_error(any_detector):
    with pytest.raises(ValueError, match="channels"):
        any_detector(np.zeros((64, 64, 2), np.uint8))


def test_colour_and_mono_give_features(any_detector):
    img = cv2.imread(str(data_dir("strecha-fountain-p11") / "images" / "0000.jpg"), cv2.IMREAD_COLOR)
    img = cv2.resize(img, (384, 256))
    fc, fm = any_detector(img), any_detector(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    assert len(fc) > 200 and len(fm) > 200
    for f in (fc, fm):
        assert f.keypoints.shape == (len(f), 2) and f.frames.shape == (len(f), 2, 2)
        assert np.all(np.abs(np.linalg.det(f.frames)) > 0)
        np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-4)


def frame_errors(f1: Features, f2: Features, H: np.ndarray):
    m = match_descriptors(f1.descriptors, f2.descriptors, {"ratio": 0.8, "mutual": True})
    k1, k2 = f1.keypoints[m.idx[:, 0]].astype(float), f2.keypoints[m.idx[:, 1]].astype(float)
    p = np.c_[k1, np.ones(len(k1))] @ H.T
    correct = np.linalg.norm(p[:, :2] / p[:, 2:] - k2, axis=1) < 3.0
    J = homography_jacobian(H, k1[correct])
    A1, A2 = f1.frames[m.idx[correct, 0]].astype(float), f2.frames[m.idx[correct, 1]].astype(float)
    err = np.linalg.norm(A2 @ np.linalg.inv(A1) - J, axis=(1, 2)) / np.linalg.norm(J, axis=(1, 2))
    return int(correct.sum()), float(np.median(err))


def test_affine_frames_follow_the_homography_on_boat(any_detector):
    root = data_dir("oxford-boat")
    img1 = cv2.imread(str(root / "images" / "img1.pgm"), cv2.IMREAD_GRAYSCALE)
    sift = SiftSimilarity()
    f1, s1 = any_detector(img1), sift(img1)
    for n, min_correct in ((2, 600), (3, 1)):
        H = np.loadtxt(root / f"H_1_to_{n}.txt")
        img = cv2.imread(str(root / "images" / f"img{n}.pgm"), cv2.IMREAD_GRAYSCALE)
        correct, med = frame_errors(f1, any_detector(img), H)
        s_correct, s_med = frame_errors(s1, sift(img), H)
        print(f"boat 1->{n}: Hessian-affine {correct} correct, median frame error {med:.3f}; "
              f"SIFT similarity {s_correct} correct, median {s_med:.3f}")
        assert correct >= min_correct
        assert med <= 0.15


def test_fast_detector_keeps_the_reference_accuracy_on_boat(detector):
    """Fast path: frame error within 0.02 of the kornia path and >= 90 % of its correct matches."""
    from nmnet_ros.core.fast_hessaff import FastHessianAffine

    root = data_dir("oxford-boat")
    fast = FastHessianAffine()
    img1 = cv2.imread(str(root / "images" / "img1.pgm"), cv2.IMREAD_GRAYSCALE)
    r1, q1 = detector(img1), fast(img1)
    for n in (2, 3):
        H = np.loadtxt(root / f"H_1_to_{n}.txt")
        img = cv2.imread(str(root / "images" / f"img{n}.pgm"), cv2.IMREAD_GRAYSCALE)
        ref_correct, ref_err = frame_errors(r1, detector(img), H)
        correct, err = frame_errors(q1, fast(img), H)
        print(f"boat 1->{n}: kornia {ref_correct} correct, err {ref_err:.3f}; fast {correct} correct, err {err:.3f}")
        assert correct >= 0.9 * ref_correct
        assert err <= ref_err + 0.02


@pytest.mark.parametrize("shape", [(16, 16), (17, 40), (376, 1241)])
def test_hessian_kernel_equals_the_opencv_sobel_formula(shape):
    """The fused kernel gives cv2.Sobel's 5x5 determinant of the Hessian, borders (reflect-101) included."""
    from nmnet_ros.core.fast_hessaff import FastHessianAffine

    img = cv2.GaussianBlur(np.random.default_rng(1).random(shape, np.float32), (0, 0), 1.5)
    s2 = 2.3**2
    k = s2 / 48
    dxx = cv2.Sobel(img, cv2.CV_32F, 2, 0, ksize=5, scale=k)
    dyy = cv2.Sobel(img, cv2.CV_32F, 0, 2, ksize=5, scale=k)
    dxy = cv2.Sobel(img, cv2.CV_32F, 1, 1, ksize=5, scale=k)
    out = np.full(shape, np.nan, np.float32)
    FastHessianAffine._hessian(img, s2, out)
    ref = dxx * dyy - dxy * dxy
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-5 * np.abs(ref).max())


def _maxima_reference(r: np.ndarray, threshold: float) -> np.ndarray:
    """(level, y, x) rows of the 3x3x3 maxima as the detector found them with cv2.dilate before the kernel."""
    dil = [cv2.dilate(level, np.ones((3, 3), np.uint8)) for level in r]
    rows = []
    for i in range(1, len(r) - 1):
        m = (r[i] >= dil[i]) & (r[i] > threshold)
        m[[0, -1], :] = m[:, [0, -1]] = False
        ys, xs = np.nonzero(m)
        keep = (r[i, ys, xs] >= dil[i - 1][ys, xs]) & (r[i, ys, xs] >= dil[i + 1][ys, xs])
        rows.append(np.stack([np.full(int(keep.sum()), i), ys[keep], xs[keep]], 1))
    return np.concatenate(rows)


def test_maxima_kernel_finds_the_dilation_maxima_in_their_order():
    """Same maxima, same order (level, row, column) as the dilation reference; plateaus that overflow
    the first buffer are counted and found on the second run."""
    from nmnet_ros.core.fast_hessaff import _maxima_kernel

    rng = np.random.default_rng(2)
    r = np.stack([cv2.GaussianBlur(rng.random((60, 90), np.float32), (0, 0), 1.2) for _ in range(5)]) - 0.45
    ref = _maxima_reference(r, 0.0)
    out = np.empty((len(ref) + 5, 3), np.int32)
    n = _maxima_kernel(r, np.float32(0.0), out)
    assert n == len(ref) > 20
    np.testing.assert_array_equal(out[:n], ref)
    flat = np.ones((3, 20, 20), np.float32)  # a plateau: every inner sample ties with its neighbours
    small = np.empty((10, 3), np.int32)
    assert _maxima_kernel(flat, np.float32(0.5), small) == 18 * 18
    np.testing.assert_array_equal(small, _maxima_reference(flat, 0.5)[:10])


def test_extrema_survive_a_plateau_larger_than_the_maxima_buffer():
    """A flat response above threshold: 38 x 38 tied maxima, more than the buffer sized for strict
    maxima (20 x 20); all are found, none refined, and those far enough inside are kept."""
    from nmnet_ros.core.fast_hessaff import FastHessianAffine

    rows = FastHessianAffine()._extrema(np.ones((3, 40, 40), np.float32), 0)
    # sigma = 1.6 * 2^(1/3) = 2.02, half the measurement region 6.05 px, 5 px margin: x, y in 12..27
    assert rows.shape == (16 * 16, 4)
    assert set(rows[:, 0]) == set(rows[:, 1]) == set(range(12, 28))
