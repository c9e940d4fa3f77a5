"""NM-Net network: size, order-insensitivity, determinism, sizes, bad weights."""

import copy
import shutil

import numpy as np
import pytest
import torch

from nmnet_ros.core.model import NMNet, WeightsError, load_model, network_input
from nmnet_ros.core.neighbors import compatibility_neighbors


def inputs(n, seed=0):
    rng = np.random.default_rng(seed)
    k0 = rng.uniform(0, 600, (n, 2))
    k1 = k0 + rng.normal(0, 20, (n, 2))
    a0 = rng.normal(0, 3, (n, 2, 2)) + 8 * np.eye(2)
    a1 = a0 + rng.normal(0, 1, (n, 2, 2))
    x = torch.tensor(np.c_[(k0 - 300) / 500, (k1 - 300) / 500], dtype=torch.float32)
    return x, k0, a0, k1, a1


def test_parameter_count():
    n = sum(p.numel() for p in NMNet().parameters())
    assert 0.9e6 < n < 1.2e6  # paper/reference: about 1.1 M


def test_permutation_equivariant_and_deterministic():
    torch.manual_seed(0)
    model = NMNet().eval()
    x, k0, a0, k1, a1 = inputs(300)
    nb = torch.from_numpy(compatibility_neighbors(k0, a0, k1, a1))
    perm = np.random.default_rng(1).permutation(300)
    nbp = torch.from_numpy(compatibility_neighbors(k0[perm], a0[perm], k1[perm], a1[perm]))
    with torch.inference_mode():
        y = model(x[None], nb[None])[0]
        y2 = model(x[None], nb[None])[0]
        yp = model(x[perm][None], nbp[None])[0]
    assert torch.equal(y, y2)
    torch.testing.assert_close(yp, y[perm], atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("n", [8, 100, 4000])
def test_runs_for_many_sizes(n):
    model = NMNet().eval()
    x, k0, a0, k1, a1 = inputs(n)
    nb = torch.from_numpy(compatibility_neighbors(k0, a0, k1, a1))
    with torch.inference_mode():
        y = model(x[None], nb[None])
    assert y.shape == (1, n) and torch.isfinite(y).all()


def test_bad_weight_files_name_the_file(tmp_path):
    missing = tmp_path / "none.pt"
    with pytest.raises(WeightsError, match="none.pt"):
        load_model(missing)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(WeightsError, match="garbage.pt"):
        load_model(garbage)
    small = NMNet({"widths": (16, 16, 32, 32, 64, 64, 128, 128)})
    wrong = tmp_path / "wrong.pt"
    torch.save({"state_dict": small.state_dict()}, wrong)  # no config: shapes do not fit the default net
    with pytest.raises(WeightsError, match="wrong.pt.*do not fit"):
        load_model(wrong)
    run = tmp_path / "run"  # nmnet train --out's folder given for its weights (was "weights file not found")
    run.mkdir()
    with pytest.raises(WeightsError, match=f"^{run}: a folder, not a weights file; it holds no checkpoint"):
        load_model(run)
    shutil.copy(garbage, run / "last.pt")
    with pytest.raises(WeightsError, match=r"give one of its checkpoints \(last.pt\)"):
        load_model(run)
    shutil.copy(garbage, run / "best.pt")
    with pytest.raises(WeightsError, match=f"a folder, not a weights file; give {run / 'best.pt'}, the run's chosen"):
        load_model(run)


@pytest.mark.parametrize("variant", ["nmnet", "nmnet-sp"])
@pytest.mark.parametrize("n,k", [(2000, 8), (37, 8), (500, 4), (300, 1)])
def test_fast_model_logits_equal_the_reference(variant, n, k):
    """The inference rewrite (GEMM convolutions, folded BatchNorm) is exact.

    In float64 the logits agree to 1e-9 (a wrong rewrite shows at 1e-3 and above). In float32,
    the shipped path, rounding accumulates over the 17 normalised layers in proportion to the
    activations' size (logits reach ~40): the fast logits are within 1e-4 + 1e-5 * max|logit|
    of the float64 truth. A bare 1e-4 in float32 failed on an AMD EPYC CPU (1.9e-4 at N=2000,
    growing ~1e-5 of the activation scale per block) while the float64 check held to 5e-13.
    """
    from nmnet_ros.core.model_fast import FastNMNet

    model = load_model(variant=variant)
    x, k0, a0, k1, a1 = inputs(n, seed=n + k)
    nb = torch.from_numpy(compatibility_neighbors(k0, a0, k1, a1, k=k))
    model64 = copy.deepcopy(model).double()
    with torch.inference_mode():
        ref = model(x[None], nb[None])[0]
        ref64 = model64(x.double()[None], nb[None])[0]
    torch.testing.assert_close(FastNMNet(model64)(x.double(), nb), ref64, atol=1e-9, rtol=0)
    fast = FastNMNet(model)(x, nb)
    assert fast.dtype == torch.float32 and fast.shape == ref.shape and ref.abs().max() > 1  # real, non-trivial logits
    torch.testing.assert_close(fast.double(), ref64, atol=1e-4 + 1e-5 * ref64.abs().max().item(), rtol=0)


def test_bfloat16_normalisation_rounds_as_torch():
    """On bfloat16 activations the normalisation kernel computes as on float32 ones and rounds its output
    to nearest even, bit for bit what torch's conversion gives (with and without residual and ReLU)."""
    from nmnet_ros.core.model_fast import _norm

    g = torch.Generator().manual_seed(0)
    x = (torch.randn(3000, 64, generator=g) * 3 + 1).bfloat16()
    res = torch.randn(3000, 64, generator=g).bfloat16()
    norm = (torch.rand(64, generator=g) + 0.5, torch.randn(64, generator=g), 1e-3)
    for relu, r in ((True, res), (False, None), (True, None)):
        out = _norm(x.clone(), norm, relu, r)
        ref = _norm(x.float(), norm, relu, None if r is None else r.float()).bfloat16()
        assert out.dtype == torch.bfloat16 and torch.equal(out, ref)
        assert relu == bool((out >= 0).all())


def test_bfloat16_is_native_only_with_the_cpu_flags():
    from nmnet_ros.core.bf16 import cpu_has_bf16

    x86 = "flags\t\t: fpu sse2 avx2 avx512f avx512bw avx512_vnni {}\nbugs\t\t: spectre_v1\n"
    assert cpu_has_bf16(x86.format("avx512_bf16"), "x86_64") and cpu_has_bf16(x86.format("amx_bf16 amx_tile"), "x86_64")
    assert not cpu_has_bf16(x86.format(""), "x86_64")  # AVX-512 alone: bfloat16 is emulated
    arm = "Features\t: fp asimd sve {}\n"
    assert cpu_has_bf16(arm.format("bf16 i8mm"), "aarch64") and not cpu_has_bf16(arm.format("i8mm"), "aarch64")
    assert not cpu_has_bf16(arm.format("svebf16"), "aarch64") and not cpu_has_bf16("", "x86_64")


def test_precision_choices():
    from nmnet_ros.core.bf16 import native_bf16
    from nmnet_ros.core.model_fast import precision_note, resolve_precision

    assert resolve_precision("float32") is torch.float32 and resolve_precision("bfloat16") is torch.bfloat16
    assert resolve_precision("auto") is (torch.bfloat16 if native_bf16() else torch.float32)
    assert precision_note("auto").startswith("bfloat16 (auto" if native_bf16() else "float32 (auto")
    with pytest.raises(ValueError, match="'float16'; use one of auto, float32, bfloat16"):
        resolve_precision("float16")


def test_bfloat16_padding_leaves_the_logits_unchanged(monkeypatch):
    """bfloat16 pads N to a multiple of PAD (oneDNN builds a GEMM kernel for every new shape, ~9 ms per
    frame otherwise); the padding rows are never counted by the normalisations, so the logits equal
    those of the unpadded input (counting them would shift the moments by ~2 % here)."""
    import nmnet_ros.core.model_fast as mf

    x, k0, a0, k1, a1 = inputs(1000, seed=3)  # padded to 1024
    nb = torch.from_numpy(compatibility_neighbors(k0, a0, k1, a1))
    model = mf.FastNMNet(load_model(), torch.bfloat16)
    padded = model(x, nb)
    monkeypatch.setattr(mf, "PAD", 1)
    unpadded = model(x, nb)
    assert padded.shape == unpadded.shape == (1000,)
    torch.testing.assert_close(padded, unpadded, atol=1e-3, rtol=0)


def test_ratio_input_is_a_fifth_input_the_fast_model_runs_too():
    """``ratio_input`` (not in the paper): the descriptor ratio joins the four coordinates."""
    from nmnet_ros.core.model_fast import FastNMNet

    torch.manual_seed(0)
    model = NMNet({"ratio_input": True}).eval()
    assert model.embed[0].weight.shape[-1] == 5 and NMNet().embed[0].weight.shape[-1] == 4
    _, k0, a0, k1, a1 = inputs(300)
    ratio = np.random.default_rng(2).uniform(0.5, 1.0, 300)
    x = network_input((k0 - 300) / 500, (k1 - 300) / 500, ratio, model.config)
    assert x.shape == (300, 5) and np.allclose(x[:, 4].numpy(), ratio)
    assert network_input(k0, k1, ratio, NMNet().config).shape == (300, 4)
    nb = torch.from_numpy(compatibility_neighbors(k0, a0, k1, a1))
    model64 = copy.deepcopy(model).double()
    with torch.inference_mode():
        ref64 = model64(x.double()[None], nb[None])[0]
        other = model(network_input((k0 - 300) / 500, (k1 - 300) / 500, 1.0 - ratio, model.config)[None], nb[None])[0]
    torch.testing.assert_close(FastNMNet(model64)(x.double(), nb), ref64, atol=1e-9, rtol=0)
    assert (other.double() - ref64).abs().max() > 1e-3  # the ratio reaches the logits


def test_weights_without_a_calibrated_threshold_are_said_where_the_cut_is_used(tmp_path):
    """A training run stopped early (or its last.pt) has no calibrated cut: the front end kept matches above 0.5
    without a word. Said when the selector is built; not with the shipped weights or an explicit score_threshold."""
    import warnings

    from nmnet_ros.core.model import weights_dir
    from nmnet_ros.core.selectors import build

    ck = torch.load(weights_dir() / "nmnet.pt", map_location="cpu", weights_only=True)
    assert "score_threshold" in ck and load_model().calibrated
    del ck["score_threshold"]
    bare = tmp_path / "last.pt"
    torch.save(ck, bare)
    assert not load_model(bare).calibrated and load_model(bare).score_threshold == 0.5
    with pytest.warns(UserWarning, match=f"{bare}: no calibrated score threshold .* keeps the matches above 0.5"):
        build("nmnet+magsac", weights={"nmnet": str(bare)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build("nmnet+magsac")
        build("nmnet", {"score_threshold": 0.7}, weights={"nmnet": str(bare)})
