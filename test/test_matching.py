"""Nearest-neighbour matching, ratio test, mutual check, empty and malformed inputs."""

import numpy as np
import pytest

from nmnet_ros.matching import match_descriptors


def unit(x):
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def test_nn_ratio_mutual():
    rng = np.random.default_rng(0)
    d1 = unit(rng.normal(size=(50, 128)))
    perm = rng.permutation(50)
    d0 = unit(d1[perm] + 0.01 * rng.normal(size=(50, 128)))
    m = match_descriptors(d0, d1)
    assert len(m) == 50 and np.array_equal(m.idx[:, 1], perm)
    extra = unit(rng.normal(size=(10, 128)))
    m2 = match_descriptors(np.r_[d0, extra], d1, {"ratio": 0.8, "mutual": True})
    assert set(m2.idx[:, 0]) == set(range(50))  # random extras fail the ratio test
    assert np.all(m2.ratio < 0.8) and np.all(m2.distance >= 0)


def test_empty_inputs_give_empty_matches():
    e = np.zeros((0, 128), np.float32)
    d = unit(np.ones((5, 128)))
    for a, b in ((e, d), (d, e), (e, e)):
        m = match_descriptors(a, b)
        assert len(m) == 0 and m.idx.shape == (0, 2)


def test_single_candidate_has_ratio_one():
    d = unit(np.random.default_rng(1).normal(size=(3, 128)))
    m = match_descriptors(d, d[:1])
    assert len(m) == 3 and np.all(m.ratio == 1)


def test_mismatched_descriptor_sizes_raise():
    with pytest.raises(ValueError, match="equal D"):
        match_descriptors(np.ones((3, 128)), np.ones((3, 64)))
