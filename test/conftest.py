"""Shared fixtures: the real data in ../shared/data and a session-wide feature cache; the test tiers' markers.

Markers (pyproject.toml), applied here so that no test has to remember them: ``ros`` for a test over real DDS (the
``ros`` fixture, or a node or live replay started as its own process), ``data`` for one that reads ../shared/data
(itself or through a fixture). ``slow`` is set by hand on the tests that take seconds. ``make test-fast`` runs the
rest: ``-m "not ros and not data and not slow"``.
"""

from __future__ import annotations

import inspect
import os
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


def data_dir(name: str) -> Path:
    """A folder of ../shared/data; skips the test when the shared data is not beside the clone."""
    p = DATA / name
    if not p.is_dir():
        pytest.skip(f"{p} not present (the shared data sits beside the clone in development and CI)")
    return p


ROS_SIGNS = ("NodeProcess", "node_and_peer", '"--live"', "'--live'", '"demo"', "play_live", "live_replay_playing")  # a node


def _source(func) -> str:
    try:
        return inspect.getsource(func)
    except (OSError, TypeError):
        return ""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark each test ``ros`` and ``data`` by what it uses (see the module's docstring)."""
    reads_data: dict[str, bool] = {}
    for item in items:
        func = getattr(item, "function", None)
        own = _source(func)
        defs = getattr(getattr(item, "_fixtureinfo", None), "name2fixturedefs", {})
        for name in item.fixturenames:
            if name not in reads_data:
                reads_data[name] = any("data_dir(" in _source(d.func) or "planar_views(" in _source(d.func)
                                       for d in defs.get(name, ()))
        if "ros" in item.fixturenames or any(sign in own for sign in ROS_SIGNS):
            item.add_marker(pytest.mark.ros)
        if "data_dir(" in own or "planar_views(" in own or any(reads_data[n] for n in item.fixturenames):
            item.add_marker(pytest.mark.data)


@pytest.fixture(scope="session")
def detector():
    from nmnet_ros.core.features import HessianAffine

    return HessianAffine()


@pytest.fixture(scope="session", params=["hessian-affine", "hessian-affine-fast"])
def any_detector(request, detector):
    """The kornia reference and the fast Hessian-affine (both must pass the feature tests)."""
    from nmnet_ros.core.fast_hessaff import FastHessianAffine

    return detector if request.param == "hessian-affine" else FastHessianAffine()


@pytest.fixture(scope="session")
def cache(detector, tmp_path_factory):
    from nmnet_ros.io.cache import FeatureCache

    # NMNET_TEST_CACHE reuses a developer's feature cache between runs; CI starts empty.
    root = os.environ.get("NMNET_TEST_CACHE") or tmp_path_factory.mktemp("features")
    return FeatureCache(detector, Path(root))


def robust_cost(pose, x0: np.ndarray, x1: np.ndarray, sigma: float) -> float:
    """The Cauchy-robust Sampson cost refine_pose minimises, written out independently."""
    from nmnet_ros.core.geometry import skew

    E = skew(pose.t / np.linalg.norm(pose.t)) @ pose.R
    h0, h1 = np.c_[x0, np.ones(len(x0))], np.c_[x1, np.ones(len(x1))]
    Ex0, Etx1 = h0 @ E.T, h1 @ E
    r2 = np.sum(h1 * Ex0, 1) ** 2 / (Ex0[:, 0] ** 2 + Ex0[:, 1] ** 2 + Etx1[:, 0] ** 2 + Etx1[:, 1] ** 2)
    return float(np.sum(np.log1p(r2 / sigma**2)))


def planar_views(seed: int, frames: int = 4) -> tuple[object, list[tuple[np.ndarray, np.ndarray]]]:
    """A camera moving at constant velocity before a plane 5 m away, textured with Strecha fountain's first frame
    (each view its homography K (R + t n^T / d) K^-1 of that frame): the camera, and per view (image, T_WC).
    ``seed`` draws the plane's tilt, the turn per frame (~1 deg) and the direction of the 0.25 m steps."""
    import cv2

    from nmnet_ros.io.datasets import Sequence

    seq = Sequence.load(data_dir("strecha-fountain-p11"))
    img, K = seq.image(0), seq.camera.K
    rng = np.random.default_rng(seed)
    n = np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.3, 3)
    n /= np.linalg.norm(n)
    step = cv2.Rodrigues(rng.normal(0, 0.02, 3))[0]
    v = rng.normal(0, 1, 3)
    v *= 0.25 / np.linalg.norm(v)
    views, R_wc = [], np.eye(3)
    for k in range(frames):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_wc, k * v  # camera k in camera 0's frame
        R, t = R_wc.T, -R_wc.T @ (k * v)  # x_k = R x_0 + t
        H = K @ (R + np.outer(t, n) / 5.0) @ np.linalg.inv(K)
        views.append((cv2.warpPerspective(img, H, img.shape[1::-1]), T))
        R_wc = R_wc @ step
    return seq.camera, views
