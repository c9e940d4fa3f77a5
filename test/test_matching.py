"""Nearest-neighbour matching, ratio test, mutual check, empty and malformed inputs."""

import numpy as np
import pytest

from nmnet_ros.core.matching import match_descriptors


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


def _reference(d0, d1, config):
    """The plain matcher the kernels replace: float32 GEMM, torch's top-2 per row, max per column."""
    import torch

    sim = torch.from_numpy(d0) @ torch.from_numpy(d1).T
    top, inds = sim.topk(2, dim=1)
    mutual = (top[:, 0] >= sim.amax(0)[inds[:, 0]]).numpy()
    dist = (2 - 2 * top).clamp_min(0).sqrt().numpy()
    ratio = dist[:, 0] / np.maximum(dist[:, 1], 1e-12)
    keep = np.ones(len(d0), bool)
    if config.get("ratio") is not None:
        keep &= ratio < config["ratio"]
    if config.get("mutual"):
        keep &= mutual
    return np.c_[np.nonzero(keep)[0], inds[:, 0].numpy()[keep]], dist[keep, 0], ratio[keep], mutual[keep]


def _same_matches(d0, d1, config=None):
    """The bfloat16-screened matcher on the same descriptors: the plain matcher's matches (the float32 path
    is that matcher, so it is not compared with itself here)."""
    idx, dist, ratio, mutual = _reference(d0, d1, config or {})
    got = match_descriptors(d0, d1, {**(config or {}), "gemm": "bfloat16"})
    assert np.array_equal(got.idx, idx) and np.array_equal(got.mutual, mutual)
    assert np.allclose(got.distance, dist, atol=1e-4) and np.allclose(got.ratio, ratio, atol=1e-3)


@pytest.mark.parametrize("seq, i, j", [("kitti-07", 120, 123), ("strecha-herz-jesus-p25", 0, 1)])
def test_bfloat16_screen_finds_the_float32_matches_on_real_descriptors(seq, i, j):
    from nmnet_ros.core.fast_hessaff import FastHessianAffine
    from nmnet_ros.io.datasets import Sequence

    from .conftest import data_dir

    s, det = Sequence.load(data_dir(seq)), FastHessianAffine()
    d0, d1 = det(s.image(i)).descriptors, det(s.image(j)).descriptors
    assert min(len(d0), len(d1)) > 1500
    for config in ({}, {"ratio": 0.8}, {"mutual": True}):
        _same_matches(d0, d1, config)
    _same_matches(d0[:1001], d1[:937])  # sizes off the GEMM padding
    _same_matches(d0[:5], d1[:2])  # the fewest candidates the kernels take


def test_bfloat16_screen_resolves_differences_below_bfloat16_resolution():
    """Candidates ~1e-4 apart in similarity (bfloat16 resolves ~4e-3 near 1): the float32 re-check
    must still pick the nearest and the second nearest (float64 decides, where float32 can)."""
    rng = np.random.default_rng(3)
    base = unit(np.abs(rng.normal(size=(40, 128))))  # non-negative like RootSIFT
    d1 = unit(np.repeat(base, 5, 0) + 2e-3 * np.abs(rng.normal(size=(200, 128))))  # 5 near-copies of each
    d0 = unit(base + 1e-3 * np.abs(rng.normal(size=(40, 128))))
    for a, b in ((d0, d1), (d1, d0)):  # rows, then columns (the mutual check) ~1e-4 apart
        sim = a.astype(np.float64) @ b.T.astype(np.float64)
        top3 = np.sort(sim, 1)[:, -3:]
        close = top3 if a is d0 else np.sort(sim, 0)[-3:].T
        assert np.median(close[:, 2] - close[:, 1]) < 1e-3  # the screen alone could not order these
        col2 = np.sort(sim, 0)[-2:]
        decided = np.minimum(top3[:, 2] - top3[:, 1], top3[:, 1] - top3[:, 0]) > 1e-6  # no float32 tie
        decided &= (col2[1] - col2[0])[sim.argmax(1)] > 1e-6  # in the row's column neither
        assert decided.sum() > len(a) // 3
        for gemm in ("float32", "bfloat16"):
            m = match_descriptors(a, b, {"gemm": gemm})
            assert np.array_equal(m.idx[decided, 1], sim.argmax(1)[decided])
            # squared distances, where float32's error is bounded (a sum of 128 products: < 128 * 2^-24 in
            # the similarity); near-duplicates' distances are ~0.01, so their ratios are ill-conditioned
            tol = 2 * 128 * 2.0**-24
            assert np.allclose(m.distance[decided] ** 2, (2 - 2 * top3[:, 2])[decided], atol=tol)
            assert np.allclose((m.distance / m.ratio)[decided] ** 2, (2 - 2 * top3[:, 1])[decided], atol=tol)
            is_col_best = sim.max(0)[sim.argmax(1)] <= sim.max(1) + 1e-7
            assert np.array_equal(m.mutual[decided], is_col_best[decided])


def test_bfloat16_screen_margin_covers_worst_case_rounding():
    """A nearest neighbour the bfloat16 GEMM ranks two steps below two decoys (every input rounds the
    wrong way): the screen's margin must still take it to the float32 re-check."""
    import torch

    step, eps = 2.0**-10, 1e-6  # bfloat16 spacing just above 0.125
    down, up, low_up = 0.125 + step / 2 - eps, 0.125 + step / 2 + eps, 0.125 - step / 4 + eps  # -> 0.125, +step, 0.125

    def column(values, order):
        b = np.zeros(128)
        b[order[: len(values)]] = values
        b[127] = np.sqrt(1 - (b**2).sum())  # off a's support: unit norm, no say in the similarity
        return b

    a = np.zeros(128)
    a[:64] = 0.125  # exact in bfloat16, unit norm
    rng = np.random.default_rng(0)
    true = column([down] * 60 + [low_up] * 3, np.arange(63))
    decoys = [column([up] * 56 + [low_up] * 7, rng.permutation(63)) for _ in range(2)]
    others = unit(np.abs(rng.normal(size=(30, 128))))
    d1 = np.r_[others[:10], true[None], decoys, others[10:]].astype(np.float32)
    exact = d1.astype(np.float64) @ a
    screened = (torch.from_numpy(a[None].astype(np.float32)).bfloat16() @ torch.from_numpy(d1).bfloat16().T).float()[0]
    assert exact.argmax() == 10 and exact[10] - exact[11:13].max() > 3e-4
    assert screened[11:13].min() - screened[10] >= 2 * 2.0**-8  # two steps below both decoys in the screen
    m = match_descriptors(a[None].astype(np.float32), d1, {"gemm": "bfloat16"})
    assert m.idx[0, 1] == 10 and m.mutual[0]
    assert m.ratio[0] == pytest.approx(np.sqrt(2 - 2 * exact[10]) / np.sqrt(2 - 2 * np.sort(exact)[-2]), abs=1e-3)


def test_matching_gemm_choice_is_checked():
    d = unit(np.random.default_rng(1).normal(size=(3, 128)))
    for a, b in ((d, d), (d[:0], d)):  # refused before anything else, empty input included
        with pytest.raises(ValueError, match="unknown matching gemm 'float16'; use one of auto, float32, bfloat16"):
            match_descriptors(a, b, {"gemm": "float16"})
    m = match_descriptors(d, d[:1], {"gemm": "bfloat16"})  # one candidate: nothing to screen
    assert len(m) == 3 and np.all(m.ratio == 1)


def test_frontend_readies_the_screening_kernels_before_the_first_frame():
    """Compiling them takes seconds: on the first frame pair a live camera would drop frames meanwhile."""
    import subprocess
    import sys

    from nmnet_ros.core.bf16 import native_bf16

    if not native_bf16():
        pytest.skip("this CPU has no native bfloat16: matching runs the float32 GEMM, nothing to compile")
    code = ("from nmnet_ros.core import matching; from nmnet_ros.core.pipeline import Frontend; "
            "before = len(matching._recheck.signatures); Frontend(); print(before, len(matching._recheck.signatures))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["0", "1"]
