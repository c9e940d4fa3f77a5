"""Geometry: normalisation, essential matrix and pose on real data, metrics, bad input."""

import numpy as np
import pytest

from nmnet_ros.core.geometry import (
    CHEIRALITY_DEPTH,
    Camera,
    CameraError,
    essential_from_pose,
    estimate_essential,
    estimate_pose,
    fit_rotation,
    pose_auc,
    pose_error_deg,
    recover_pose,
    refine_pose,
    robust_threshold,
    rotation_error_deg,
    sampson_distance,
    skew,
    sym_epipolar_sq,
    translation_error_deg,
    weighted_eight_point,
)
from nmnet_ros.io.datasets import Sequence
from nmnet_ros.io.pairs import make_pair

from .conftest import data_dir, robust_cost

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


def rot(axis, deg):
    a = np.radians(deg)
    x, y, z = np.asarray(axis, float) / np.linalg.norm(axis)
    Kx = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + np.sin(a) * Kx + (1 - np.cos(a)) * Kx @ Kx


def synthetic(n=200, seed=0):
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(4, 10, n)]
    R, t = rot([0.1, 1, 0.2], 5), np.array([0.5, 0.05, 0.1])
    X1 = X @ R.T + t
    return X[:, :2] / X[:, 2:], X1[:, :2] / X1[:, 2:], R, t


def test_auc_hand_computed():
    # errors 1, 2, 8 deg -> recall curve (0,0) (1,1/3) (2,2/3) (8,1), trapezoids as SuperGlue.
    # AUC@5:  [0,1] 1/6 + [1,2] 1/2 + [2,5] held at 2/3 -> 2          = 8/3  / 5
    # AUC@10: 1/6 + 1/2 + [2,8] (2/3+1)/2*6 = 5 + [8,10] 1*2 = 2       = 23/3 / 10
    a5, a10, a20 = pose_auc([1.0, 2.0, 8.0])
    assert a5 == pytest.approx(8 / 3 / 5)
    assert a10 == pytest.approx(23 / 3 / 10)
    assert a20 == pytest.approx((23 / 3 + 10) / 20)
    assert pose_auc([180.0, 180.0]) == [0.0, 0.0, 0.0]
    assert pose_auc([]) == [0.0, 0.0, 0.0]


def test_metrics_conventions():
    R = rot([0, 0, 1], 10)
    assert rotation_error_deg(R, np.eye(3)) == pytest.approx(10)
    assert translation_error_deg([1, 0, 0], [-1, 0, 0]) == pytest.approx(0)  # sign-agnostic
    assert translation_error_deg([1, 0, 0], [0, 1, 0]) == pytest.approx(90)
    assert pose_error_deg(None, np.eye(3), np.ones(3)) == (180.0, 180.0)


def test_exact_synthetic_pose_from_all_estimators():
    x0, x1, R, t = synthetic()
    E = essential_from_pose(R, t)
    assert np.max(sym_epipolar_sq(E, x0, x1)) < 1e-20
    for method in ("magsac", "poselib", "ransac"):
        E_est, mask = estimate_essential(x0, x1, method, 1e-4)
        pose = recover_pose(E_est, x0, x1, mask)
        r, tt = pose_error_deg(pose, R, t)
        assert r < 0.01 and tt < 0.05
    E8 = weighted_eight_point(x0, x1, np.ones(len(x0)))
    pose = recover_pose(E8, x0, x1)
    assert max(pose_error_deg(pose, R, t)) < 0.01


def test_weighted_eight_point_ignores_zero_weight_outliers():
    x0, x1, R, t = synthetic(seed=2)
    rng = np.random.default_rng(0)
    x1o = x1.copy()
    x1o[:80] = rng.uniform(-0.5, 0.5, (80, 2))
    w = np.r_[np.zeros(80), np.ones(len(x0) - 80)]
    pose = recover_pose(weighted_eight_point(x0, x1o, w), x0, x1o, w > 0)
    assert max(pose_error_deg(pose, R, t)) < 0.01
    pose_bad = recover_pose(weighted_eight_point(x0, x1o, np.ones(len(x0))), x0, x1o)
    assert max(pose_error_deg(pose_bad, R, t)) > 1.0


def test_a_camera_creeping_before_a_distant_scene_gets_its_pose():
    """A robot at walking pace filmed at 30 Hz: 1.7 cm between frames, mostly forward, before points 1.5-10 m away
    (about 1 px of parallax at f = 500: the front end takes the essential matrix, not the turning-camera rule), 0.3 px
    of noise. The pose comes out, decided by the points. OpenCV's recoverPose without a distance lets only points
    within 50 baselines (0.85 m here) vote, so none did and the front end said pose_failed; on KITTI-07's first
    frames (9 cm apart) 0-2 of ~1000 voted."""
    rng = np.random.default_rng(4)
    X = np.c_[rng.uniform(-4, 4, (400, 2)), rng.uniform(1.5, 10, 400)]
    R, t = rot([0, 1, 0], 0.3), np.array([0.004, 0.0, -0.0165])
    X1 = X @ R.T + t
    x0 = X[:, :2] / X[:, 2:] + rng.normal(0, 0.3 / 500, (400, 2))
    x1 = X1[:, :2] / X1[:, 2:] + rng.normal(0, 0.3 / 500, (400, 2))
    rot_only = (X @ R.T)[:, :2] / (X @ R.T)[:, 2:]
    parallax = np.median(np.linalg.norm(x1 - rot_only, axis=1)) * 500
    assert 0.5 < parallax < 2.0  # pixels: above static_parallax_px (0.25), so the front end takes E, not the rotation
    pose = recover_pose(essential_from_pose(R, t), x0, x1)
    assert pose is not None and pose.inliers.mean() > 0.5, None if pose is None else pose.inliers.mean()  # most in front
    rot_err, trans_err = pose_error_deg(pose, R, t)
    assert rot_err < 0.01 and trans_err < 2.0, (rot_err, trans_err)  # the true solution of the four


def test_recover_pose_equals_opencv_on_all_points_with_the_mask():
    """recover_pose triangulates only the masked points; OpenCV given all of them and the mask picks the
    same R, t and marks the same points (the unmasked never count)."""
    import cv2

    x0, x1, R, t = noisy_with_outliers(seed=3)
    E, mask = estimate_essential(x0, x1, "magsac", 0.5 / 500)
    assert 0.3 < mask.mean() < 0.9  # a real partial mask
    pose = recover_pose(E, x0, x1, mask)
    n, R_cv, t_cv, m_cv, _ = cv2.recoverPose(E, x0, x1, np.eye(3), distanceThresh=CHEIRALITY_DEPTH,
                                             mask=mask.astype(np.uint8)[:, None].copy())
    np.testing.assert_array_equal(pose.R, R_cv)
    np.testing.assert_array_equal(pose.t, t_cv.ravel() / np.linalg.norm(t_cv))
    np.testing.assert_array_equal(pose.inliers, m_cv.ravel() > 0)
    assert pose.inliers.sum() == n and not pose.inliers[~mask].any()
    assert recover_pose(E, x0, x1, np.arange(len(x0)) < 4) is None  # fewer than 5 masked points
    with pytest.raises(ValueError, match="mask length 10 does not match 600"):
        recover_pose(E, x0, x1, mask[:10])


def noisy_with_outliers(seed=0, n=600, noise_px=0.3, outliers=0.3, f=500.0):
    """Normalised matches with pixel noise and a fraction of gross outliers, and the true pose."""
    x0, x1, R, t = synthetic(n, seed)
    rng = np.random.default_rng(seed + 100)
    x0 = x0 + rng.normal(0, noise_px / f, x0.shape)
    x1 = x1 + rng.normal(0, noise_px / f, x1.shape)
    bad = rng.random(n) < outliers
    x1[bad] += rng.normal(0, 40 / f, (bad.sum(), 2))
    return x0, x1, R, t


def test_refine_pose_recovers_a_perturbed_pose_despite_outliers():
    x0, x1, R, t = noisy_with_outliers()
    R0 = R @ rot([1, 2, 3], 0.3)
    t0 = t / np.linalg.norm(t) + np.array([0.03, -0.02, 0.0])
    start = recover_pose(essential_from_pose(R0, t0), x0, x1)
    sigma = 0.3 / 500
    out = refine_pose(start, x0, x1, sigma, iterations=20)
    best = refine_pose(recover_pose(essential_from_pose(R, t), x0, x1), x0, x1, sigma, iterations=20)
    e0, e1, eb = pose_error_deg(start, R, t), pose_error_deg(out, R, t), pose_error_deg(best, R, t)
    print(f"start rot/trans {e0[0]:.3f}/{e0[1]:.3f} deg -> refined {e1[0]:.3f}/{e1[1]:.3f} deg "
          f"(the cost's minimum near the truth, set by the noise: {eb[0]:.3f}/{eb[1]:.3f})")
    assert max(e1) < 0.5 * min(e0)
    assert np.allclose(e1, eb, atol=1e-3)  # the same minimum as when started at the true pose
    assert robust_cost(out, x0, x1, sigma) < robust_cost(start, x0, x1, sigma)
    assert np.linalg.norm(out.t) == pytest.approx(1.0)
    assert np.allclose(out.R @ out.R.T, np.eye(3), atol=1e-9) and np.linalg.det(out.R) == pytest.approx(1.0)
    assert np.allclose(out.E, skew(out.t) @ out.R)


def test_a_rotation_alone_is_fitted_through_noise_and_mismatches_and_a_translation_shows_as_parallax():
    """fit_rotation (a camera that turned without moving), from rays with 0.3 px noise at f = 500 and 10 % mismatches:
    the mismatches do not tilt it (it equals the fit on the true matches alone, which the noise limits to a few
    thousandths of a degree) and the angles off it are the noise. A translation leaves parallax beyond that: forward
    much, sideways less, as a turn explains part of a sideways step before a scene 4-10 m away."""
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-2, 2, (400, 2)), rng.uniform(4, 10, 400)]
    R = rot([0.3, 1, -0.2], 0.4)
    x0 = X[:, :2] / X[:, 2:]
    parallax = {}
    for name, t in (("turned", [0, 0, 0]), ("forward", [0.02, 0.01, 0.3]), ("sideways", [0.05, 0.0, 0.02])):
        X1 = X @ R.T + np.array(t)
        x1 = X1[:, :2] / X1[:, 2:] + rng.normal(0, 0.3 / 500, (400, 2))
        R_true_matches, _ = fit_rotation(x0[40:], x1[40:])
        x1[:40] = rng.uniform(-0.4, 0.4, (40, 2))  # mismatches
        R_fit, angles = fit_rotation(x0, x1)
        parallax[name] = np.median(angles) * 500
        print(f"{name}: rotation error {rotation_error_deg(R_fit, R):.4f} deg (true matches alone "
              f"{rotation_error_deg(R_true_matches, R):.4f}), median parallax {parallax[name]:.2f} px")
        if name == "turned":
            assert rotation_error_deg(R_fit, R_true_matches) < 1e-4 and rotation_error_deg(R_fit, R) < 0.01
        assert np.allclose(R_fit @ R_fit.T, np.eye(3)) and np.linalg.det(R_fit) == pytest.approx(1.0)
    assert np.allclose(fit_rotation(x0, x0)[0], np.eye(3), atol=1e-12)  # the same rays: the identity
    assert parallax["turned"] < 0.4 and parallax["forward"] > 3.0 and parallax["sideways"] > 2 * parallax["turned"]


def test_refine_pose_improves_magsac_on_noisy_matches():
    """MAGSAC++ at the matches' noise level, then the polish: closer to the truth on every seed."""
    for seed in range(3):
        x0, x1, R, t = noisy_with_outliers(seed)
        sigma = 0.3 / 500
        E, mask = estimate_essential(x0, x1, "magsac", sigma)
        pose = recover_pose(E, x0, x1, mask)
        out = refine_pose(pose, x0, x1, sigma)
        before, after = sum(pose_error_deg(pose, R, t)), sum(pose_error_deg(out, R, t))
        print(f"seed {seed}: MAGSAC++ rot+trans {before:.3f} deg -> refined {after:.3f} deg")
        assert after < before
        assert robust_cost(out, x0, x1, sigma) <= robust_cost(pose, x0, x1, sigma)
        assert np.array_equal(out.inliers, pose.inliers)


def test_refine_pose_leaves_the_pose_alone_when_off_underdetermined_or_nan():
    x0, x1, R, t = noisy_with_outliers()
    pose = recover_pose(essential_from_pose(R @ rot([0, 1, 0], 0.5), t), x0, x1)
    x1_nan = x1.copy()
    x1_nan[3] = np.nan
    for out in (refine_pose(pose, x0, x1, 1e-3, iterations=0), refine_pose(pose, x0[:7], x1[:7], 1e-3),
                refine_pose(pose, x0, x1, 0.0), refine_pose(pose, x0, x1_nan, 1e-3)):
        assert out is pose


def test_magsac_on_ground_truth_inliers_kitti(cache):
    seq = Sequence.load(data_dir("kitti-07"))
    errs = []
    for i in range(0, 155, 10):
        for g in range(1, 6):
            p = make_pair(seq, i, i + g, cache)
            x0, x1 = p.normalized()
            x0, x1 = x0[p.labels], x1[p.labels]
            est = estimate_essential(x0, x1, "magsac", 1.0 / seq.camera.focal)
            pose = recover_pose(est[0], x0, x1, est[1]) if est else None
            errs.append(pose_error_deg(pose, p.R, p.t))
    errs = np.array(errs)
    ok = np.mean((errs[:, 0] < 1) & (errs[:, 1] < 1))
    print(f"kitti-07 gaps 1-5, {len(errs)} pairs: {100 * ok:.1f}% under 1 deg; median rot {np.median(errs[:, 0]):.3f} "
          f"trans {np.median(errs[:, 1]):.3f}")
    assert ok >= 0.95


def test_distortion_normalisation_roundtrip():
    import cv2

    cam = Camera(K, [-0.28, 0.07, 0.0002, 0.00002, 0.0])
    pts_n = np.array([[0.1, -0.2], [0.3, 0.25], [-0.4, 0.0]])
    px = cv2.projectPoints(np.c_[pts_n, np.ones(3)], np.zeros(3), np.zeros(3), K, cam.dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(cam.normalize(px), pts_n, atol=1e-5)


def test_fisheye_equidistant_normalisation_roundtrip():
    import cv2

    D = [0.05, -0.01, 0.003, -0.0005]  # Kannala-Brandt k1..k4, as camera_info's "equidistant"
    cam = Camera(K, D, model="equidistant")
    pts_n = np.array([[0.1, -0.2], [0.9, 0.6], [-1.2, 0.3]])  # up to ~50 degrees off axis
    px = cv2.fisheye.projectPoints(np.c_[pts_n, np.ones(3)][None], np.zeros(3), np.zeros(3), K, np.array(D))[0].reshape(-1, 2)
    np.testing.assert_allclose(cam.normalize(px), pts_n, atol=1e-6)
    plumb = Camera(K, D)  # the same numbers read as plumb_bob are another lens: the model is not ignored
    assert np.abs(plumb.normalize(px) - pts_n).max() > 0.01


def test_strong_lens_is_undistorted_to_the_pixel_corners():
    """EuRoC's cam0 (radtan, k1 = -0.28): every pixel, the corners too, normalises to a ray that projects back onto
    it. OpenCV's default 5 fixed-point steps left up to 0.29 px there, twice the pose's 0.15 px inlier threshold."""
    import cv2

    cam = Sequence.load(data_dir("euroc-v101-cam0")).camera
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, 60), np.linspace(0, cam.height - 1, 40))
    px = np.c_[u.ravel(), v.ravel()]
    x = cam.normalize(px)
    back = cv2.projectPoints(np.c_[x, np.ones(len(x))], np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
    assert np.abs(back - px).max() < 1e-6


@pytest.mark.parametrize("model, dist", [("plumb_bob", [-0.28, 0.07, 0.0002, 0.00002, 0.0]),
                                         ("equidistant", [0.05, -0.01, 0.003, -0.0005])])
def test_skewed_camera_with_distortion_normalises(model, dist):
    """A K with skew (u = fx x + s y + cx of the distorted point) and a lens: OpenCV's undistortPoints reads fx fy cx cy
    alone, so the skew was dropped (here 8 px of 20 px skew at y = 0.4, 0.016 in normalised coordinates)."""
    import cv2

    Ks = K.copy()
    Ks[0, 1] = 20.0
    pts_n = np.array([[0.1, -0.2], [0.3, 0.4], [-0.4, 0.0], [0.5, -0.35]])
    project = cv2.fisheye.projectPoints if model == "equidistant" else cv2.projectPoints
    xd = project(np.c_[pts_n, np.ones(4)][None], np.zeros(3), np.zeros(3), np.eye(3), np.array(dist))[0].reshape(-1, 2)
    px = (np.c_[xd, np.ones(4)] @ Ks.T)[:, :2]
    np.testing.assert_allclose(Camera(Ks, dist, model=model).normalize(px), pts_n, atol=1e-5)


@pytest.mark.parametrize("model, dist, msg", [
    ("fov", [0.9], "distortion model 'fov' is not supported; use one of plumb_bob, rational_polynomial, equidistant"),
    ("equidistant", [0.1, 0.0, 0.0, 0.0, 0.2], "equidistant (fisheye) distortion has 4 coefficients k1..k4, got 5 "
                                               "(a fifth of 0 is taken as padding; this one is 0.2)"),
    ("equidistant", [0.1, 0.0, 0.0], "equidistant (fisheye) distortion has 4 coefficients k1..k4, got 3"),
])
def test_unsupported_distortion_is_refused_by_name(model, dist, msg):
    with pytest.raises(CameraError) as err:
        Camera(K, dist, model=model)
    assert msg in str(err.value)


def test_a_fisheye_camera_info_padded_to_five_coefficients_reads_as_its_four():
    """realsense-ros (ROS 1; ROS 2 until late 2021) publishes the T265's equidistant D as k1..k4 and a 0: it was refused
    ("4 coefficients, got 5"), so no frame of such a bag was processed."""
    D = [-0.0093, 0.0462, -0.0434, 0.0080]
    padded, cam = Camera(K, D + [0.0], model="equidistant"), Camera(K, D, model="equidistant")
    px = np.array([[10.0, 20.0], [600.0, 400.0], [320.0, 240.0]])
    assert padded.dist.tolist() == D
    np.testing.assert_allclose(padded.normalize(px), cam.normalize(px), atol=0)


@pytest.mark.parametrize("model, dist", [("inverse_brown_conrady", [0.0] * 5), ("none", []), ("fov", [0.0])])
def test_a_model_not_supported_without_distortion_is_taken_as_none(model, dist):
    """Zero coefficients mean no distortion in any model: RealSense's inverse_brown_conrady with zeros (ROS 1 bags),
    a driver's "none". They were refused, and no frame of such a camera was processed."""
    cam = Camera(K, dist, model=model)
    px = np.array([[10.0, 20.0], [600.0, 400.0]])
    assert cam.model == "plumb_bob"
    np.testing.assert_allclose(cam.normalize(px), Camera(K, []).normalize(px), atol=0)


def test_a_four_coefficient_plumb_bob_is_padded_with_zeros_for_camera_info():
    np.testing.assert_array_equal(Camera(K, [0.1, 0.2, 0.3, 0.4]).distortion_for_msg(), [0.1, 0.2, 0.3, 0.4, 0.0])
    np.testing.assert_array_equal(Camera(K, [0.1, 0.2, 0.3, 0.4], model="equidistant").distortion_for_msg(),
                                  [0.1, 0.2, 0.3, 0.4])


@pytest.mark.parametrize("bad_k, msg", [
    (np.zeros((3, 3)), "focal"),
    (np.full((3, 3), np.nan), "NaN"),
    (np.eye(2), "3x3"),
])
def test_bad_intrinsics_raise(bad_k, msg):
    with pytest.raises(CameraError, match=msg):
        Camera(bad_k)


def test_too_few_and_mismatched_points():
    x0, x1, _, _ = synthetic(7)
    assert estimate_essential(x0, x1) is None
    assert weighted_eight_point(x0, x1, np.ones(7)) is None
    with pytest.raises(ValueError, match="differ in length"):
        estimate_essential(x0, x1[:5])
    with pytest.raises(ValueError, match="weights length"):
        weighted_eight_point(*synthetic(20)[:2], np.ones(3))
    with pytest.raises(ValueError, match="unknown robust estimator"):
        estimate_essential(*synthetic(20)[:2], method="lmeds2")


def _noisy_with_outliers(n_in=40, n_out=360, noise=2e-3):
    """Synthetic matches, 10 % inliers with noise: hard enough that the random samples matter."""
    x0, x1, R, t = synthetic(n_in + n_out, seed=3)
    rng = np.random.default_rng(4)
    x1 = x1 + rng.normal(0, noise, x1.shape)
    x1[n_in:] = rng.uniform(x1.min(0), x1.max(0), (n_out, 2))
    return x0, x1


def test_magsac_seed_zero_is_opencvs_usac_magsac_preset():
    import cv2

    x0, x1 = _noisy_with_outliers()
    E_flag, m_flag = cv2.findEssentialMat(x0, x1, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.999, threshold=1e-3,
                                          maxIters=10000)
    E, mask = estimate_essential(x0, x1, "magsac", 1e-3)
    assert np.array_equal(mask, m_flag.ravel().astype(bool)) and np.allclose(E, E_flag[:3])


def test_magsac_seed_picks_the_samples_and_is_repeatable():
    x0, x1 = _noisy_with_outliers()
    runs = [estimate_essential(x0, x1, "magsac", 1e-3, seed=s) for s in (0, 1, 2, 3)]
    again = estimate_essential(x0, x1, "magsac", 1e-3, seed=2)
    assert np.array_equal(again[1], runs[2][1]) and np.array_equal(again[0], runs[2][0])
    assert len({r[1].tobytes() for r in runs}) > 1  # the seed reaches USAC's generator


def test_prosac_samples_the_given_order_and_needs_magsac():
    x0, x1 = _noisy_with_outliers()  # the 40 inliers first: the best-first order PROSAC assumes
    _, _, R, t = synthetic(400, seed=3)

    def translation_errors(prosac):
        runs = [estimate_essential(x0, x1, "magsac", 1e-3, seed=s, prosac=prosac) for s in range(3)]
        return [pose_error_deg(recover_pose(E, x0, x1, m), R, t)[1] for E, m in runs]
    assert max(translation_errors(True)) < min(translation_errors(False))  # the order reaches USAC's sampler
    with pytest.raises(ValueError, match="PROSAC sampling is a MAGSAC"):
        estimate_essential(x0, x1, "ransac", 1e-3, prosac=True)
    with pytest.raises(ValueError, match="PROSAC sampling is a MAGSAC"):  # refused before the point count
        estimate_essential(x0[:5], x1[:5], "ransac", 1e-3, prosac=True)
    with pytest.raises(ValueError, match="unknown robust estimator 'lmeds'"):
        estimate_essential(x0[:5], x1[:5], "lmeds", 1e-3)


def test_poselib_finds_the_pose_among_outliers_its_order_and_seed_reach_its_sampler():
    """PoseLib's LO-RANSAC: the pose of 25 % noisy inliers among outliers, E = [t]x R with the inliers it kept;
    with PROSAC and the inliers first, 10 iterations find them, in a random order not; the seed picks other
    samples, repeatably."""
    x0, x1 = _noisy_with_outliers(100, 300, 5e-4)
    _, _, R, t = synthetic(400, seed=3)
    E, mask = estimate_essential(x0, x1, "poselib", 1e-3)
    assert max(pose_error_deg(recover_pose(E, x0, x1, mask), R, t)) < 0.5
    assert mask[:100].mean() > 0.9 and mask[100:].mean() < 0.02 and np.linalg.svd(E, compute_uv=False)[2] < 1e-9
    shuffled = np.random.default_rng(0).permutation(400)
    first = estimate_essential(x0, x1, "poselib", 1e-3, max_iters=10, prosac=True)
    mixed = estimate_essential(x0[shuffled], x1[shuffled], "poselib", 1e-3, max_iters=10, prosac=True)
    assert first[1][:100].mean() > 0.9 and (mixed is None or mixed[1][np.argsort(shuffled)][:100].mean() < 0.5)
    runs = [estimate_essential(x0, x1, "poselib", 1e-3, max_iters=30, seed=s) for s in range(4)]
    again = estimate_essential(x0, x1, "poselib", 1e-3, max_iters=30, seed=2)
    assert np.array_equal(again[1], runs[2][1]) and len({r[1].tobytes() for r in runs}) > 1


def test_estimate_pose_takes_poselibs_pose_as_recover_pose_would_decompose_its_e():
    """PoseLib's own R, t (no second decomposition) is the pose recover_pose finds in its E; the others' E goes
    through recover_pose; fewer than 8 points or no model: None. PoseLib's threshold is a bound of at least 1 px."""
    x0, x1 = _noisy_with_outliers(100, 300, 5e-4)
    _, _, R, t = synthetic(400, seed=3)
    for method in ("poselib", "magsac"):
        pose, mask = estimate_pose(x0, x1, method, 1e-3)
        _, same = estimate_essential(x0, x1, method, 1e-3)
        assert np.array_equal(mask, same)
        assert pose.t.shape == (3,) and abs(np.linalg.norm(pose.t) - 1) < 1e-12
    pose, mask = estimate_pose(x0, x1, "poselib", 1e-3)
    again = recover_pose(estimate_essential(x0, x1, "poselib", 1e-3)[0], x0, x1, mask)  # PoseLib's pose, its E's
    assert rotation_error_deg(pose.R, again.R) < 1e-6 and translation_error_deg(pose.t, again.t) < 1e-6
    assert max(pose_error_deg(pose, R, t)) < 0.5
    assert estimate_pose(x0[:7], x1[:7], "poselib") is None
    with pytest.raises(ValueError, match="unknown robust estimator 'lmeds'"):
        estimate_pose(x0, x1, "lmeds")
    with pytest.raises(ValueError, match="PROSAC"):
        estimate_pose(x0[:5], x1[:5], "ransac", prosac=True)
    assert robust_threshold("poselib", 0.5, 500.0) == 1.0 / 500 and robust_threshold("poselib", 2.0, 500.0) == 2.0 / 500
    assert robust_threshold("magsac", 0.5, 500.0) == 0.5 / 500


def test_sampson_distance_is_zero_on_the_true_model_and_grows_off_it():
    x0, x1, R, t = synthetic(50, seed=5)
    E = essential_from_pose(R, t)
    assert np.abs(sampson_distance(E, x0, x1)).max() < 1e-9
    line = np.c_[x0, np.ones(len(x0))] @ E.T  # x1's epipolar lines
    normal = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    along = sampson_distance(E, x0, x1 + 1e-2 * normal[:, ::-1] * [1, -1])  # sliding along the line: no error
    across = sampson_distance(E, x0, x1 + 1e-2 * normal)  # 0.01 off the line: about that, shared by both points
    assert along.max() < 1e-9 and (across > 0.25e-2).all() and (across <= 1.0001e-2).all()
