"""NM-Net inference by exact rewrites of :class:`nmnet_ros.core.model.NMNet` (same logits to float rounding).

- Features live as one (N*k, C) matrix, so a convolution is a few GEMMs: a (1,3) convolution
  along the neighbour axis is ``x_{j-1} @ W_0 + x_j @ W_1 + x_{j+1} @ W_2`` (zero padded, every
  second j for stride 2), each tap only over the positions that meet data; at width 1 only the
  centre tap does, so it is ``x @ W_centre``.
- A convolution bias followed by InstanceNorm cancels (IN subtracts the channel mean): dropped.
- Eval-mode BatchNorm after InstanceNorm is a per-channel affine map: folded into the
  normalisation's scale and shift, so IN+BN(+residual)+ReLU is one compiled kernel: a moments
  pass and one fused multiply-add pass over the activations.

``dtype=torch.bfloat16`` (the default where the CPU multiplies bfloat16 natively, see
:func:`native_bf16`) keeps weights and activations in bfloat16 and runs the GEMMs there (2-3x the
float32 rate on AVX512-BF16); the normalisation still computes in float32/float64 and rounds its
output to nearest even. Not exact: logits move by ~0.01-0.03 (median), ~0.1 % of the cut flips.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba.core import types
from numba.extending import overload

from .bf16 import PAD, bits_from_f32, f32_from_bits, native_bf16, use_bf16
from .jit import launch
from .model import NMNet, ResBlock

Norm = tuple[torch.Tensor, torch.Tensor, float]  # BN scale, BN shift, IN eps


def resolve_precision(precision: str) -> torch.dtype:
    """'auto' | 'float32' | 'bfloat16' -> the dtype NM-Net runs in ('auto': bfloat16 where native)."""
    return torch.bfloat16 if use_bf16(precision, "NM-Net precision") else torch.float32


def precision_note(precision: str) -> str:
    """One line for a log: what NM-Net will run in under ``precision``, and why."""
    dtype = str(resolve_precision(precision)).removeprefix("torch.")
    if precision != "auto":
        return f"{dtype} (set)"
    if native_bf16():
        return f"{dtype} (auto: this CPU has native bfloat16; set float32 for the exact network)"
    return f"{dtype} (auto: this CPU has no native bfloat16)"


def _get(x, r, c):  # pragma: no cover - replaced by the overload below inside compiled kernels
    """x[r, c] as a float; bfloat16 arrives as its uint16 bits."""


def _put(x, r, c, v):  # pragma: no cover - replaced by the overload below inside compiled kernels
    """x[r, c] = v; for bfloat16 bits (uint16) rounded to nearest even."""


@overload(_get)
def _get_impl(x, r, c):  # pragma: no cover - compiled
    if x.dtype == types.uint16:
        return lambda x, r, c: f32_from_bits(np.uint32(x[r, c]) << np.uint32(16))
    return lambda x, r, c: x[r, c]


@overload(_put)
def _put_impl(x, r, c, v):  # pragma: no cover - compiled
    if x.dtype == types.uint16:
        def put_bf16(x, r, c, v):
            u = bits_from_f32(np.float32(v))
            x[r, c] = np.uint16((u + np.uint32(0x7FFF) + ((u >> np.uint32(16)) & np.uint32(1))) >> np.uint32(16))
        return put_bf16

    def put(x, r, c, v):
        x[r, c] = v
    return put


def _fold_norm(seq: torch.nn.Sequential) -> Norm:
    """(gamma / sqrt(var + eps), beta - mean * that, IN eps) of an InstanceNorm -> BatchNorm pair."""
    inorm, bn = seq[0], seq[1]
    a = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    return a.detach().clone(), (bn.bias - bn.running_mean * a).detach().clone(), float(inorm.eps)


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _norm_kernel(x, valid, a, b, eps, res, relu):  # pragma: no cover - compiled
    """In place: x = [relu]((x - mean) * a / sqrt(var + eps) + b [+ res]), moments per column over the
    first ``valid`` rows (the rest is padding: normalised alike, never counted).

    Moments in one read pass with float64 sums (no cancellation for float32 data), then one
    read-write pass: two sweeps over x where separate torch ops need six. x and res are float
    arrays, or bfloat16 bits (uint16): then the arithmetic is in a's dtype (float32).
    """
    rows, cols = x.shape
    tasks = min(valid, 64)
    part = np.zeros((tasks, 2, cols))
    for t in numba.prange(tasks):
        for r in range(t * valid // tasks, (t + 1) * valid // tasks):
            for c in range(cols):
                v = np.float64(_get(x, r, c))
                part[t, 0, c] += v
                part[t, 1, c] += v * v
    mean = np.empty(cols, a.dtype)
    scale = np.empty(cols, a.dtype)
    for c in range(cols):
        m = part[:, 0, c].sum() / valid
        var = max(part[:, 1, c].sum() / valid - m * m, 0.0)
        mean[c] = m
        scale[c] = a[c] / np.sqrt(var + eps)
    tasks = min(rows, 64)
    for t in numba.prange(tasks):
        for r in range(t * rows // tasks, (t + 1) * rows // tasks):
            for c in range(cols):
                v = (_get(x, r, c) - mean[c]) * scale[c] + b[c]
                if res.shape[0]:
                    v += _get(res, r, c)
                _put(x, r, c, v if v > 0 or not relu else 0.0)


_NO_RES = np.zeros((0, 0), np.float32)  # "no residual" for every activation dtype (the kernel only reads its shape)


def _array(t: torch.Tensor) -> np.ndarray:
    """A tensor's memory as numpy (bfloat16 as its uint16 bits, which the kernel reads)."""
    return t.view(torch.uint16).numpy() if t.dtype == torch.bfloat16 else t.numpy()


def _norm(x: torch.Tensor, norm: Norm, relu: bool, residual: torch.Tensor | None = None, valid: int | None = None) -> torch.Tensor:
    """InstanceNorm over the rows (all correspondences and neighbours; the first ``valid`` when the
    rest is padding) + folded BatchNorm (+ residual) (+ ReLU), in place on x (a fresh GEMM output)."""
    a, b, eps = norm
    res = _array(residual.contiguous()) if residual is not None else _NO_RES
    launch(_norm_kernel, _array(x), len(x) if valid is None else valid, a.numpy(), b.numpy(), eps, res, relu)
    return x


def _conv_weight(conv: torch.nn.Conv2d) -> torch.Tensor:
    """(1,3) conv weight (out, in, 1, 3) -> (3, in, out): one matrix per tap (x_{j-1}, x_j, x_{j+1})."""
    return conv.weight.detach()[:, :, 0, :].permute(2, 1, 0).contiguous()


def _rows(v: torch.Tensor, j: slice) -> torch.Tensor:
    """Neighbour positions ``j`` of every correspondence of v (n, k, C) as one (n*len(j), C) matrix."""
    return v[:, j].reshape(-1, v.shape[2])


def _conv13(x: torch.Tensor, w: torch.Tensor, n: int, k: int, stride: int) -> torch.Tensor:
    """(1,3) convolution along the neighbour axis, zero padded: (n*k, C) -> (n*k_out, C_out).

    Each tap's GEMMs cover only the input positions that meet data (a side tap skips one
    position in k: a third of the work at k=2).
    """
    if k == 1:  # only the centre tap meets data
        return x @ w[1]
    v = x.view(n, k, -1)
    if stride == 1:  # side taps accumulate in place, position by position (strided operands, no copies)
        y = (x @ w[1]).view(n, k, -1)
        for j in range(1, k):
            y[:, j].addmm_(v[:, j - 1], w[0])  # output j reads input j-1
            y[:, j - 1].addmm_(v[:, j], w[2])  # and j+1
    else:  # output j reads inputs 2j-1, 2j, 2j+1 (k even)
        ko = k // 2
        y = (_rows(v, slice(0, None, 2)) @ w[1]).addmm_(_rows(v, slice(1, None, 2)), w[2]).view(n, ko, -1)
        if ko > 1:
            y[:, 1:] += (_rows(v, slice(1, -1, 2)) @ w[0]).view(n, ko - 1, -1)
    return y.reshape(-1, w.shape[2])


class _Block:
    def __init__(self, blk: ResBlock, dtype: torch.dtype) -> None:
        self.stride = blk.conv1.stride[1]
        self.w1, self.w2 = _conv_weight(blk.conv1).to(dtype), _conv_weight(blk.conv2).to(dtype)
        self.n1, self.n2 = _fold_norm(blk.norm1), _fold_norm(blk.norm2)
        sc = blk.shortcut
        conv = isinstance(sc, torch.nn.Conv2d)
        self.ws = sc.weight.detach()[:, :, 0, 0].t().contiguous().to(dtype) if conv else None
        self.bs = sc.bias.detach().clone().to(dtype) if conv else None

    def __call__(self, x: torch.Tensor, n: int, k: int, real: int) -> tuple[torch.Tensor, int]:
        """x (n*k, C) -> (n*k_out, C_out); the first ``real`` of the n correspondences are data."""
        k_out = (k - 1) // self.stride + 1
        y = _norm(_conv13(x, self.w1, n, k, self.stride), self.n1, relu=True, valid=real * k_out)
        if self.ws is None:
            s = x
        else:
            xs = x if self.stride == 1 else x.view(n, k, -1)[:, ::self.stride].reshape(n * k_out, -1)
            s = torch.addmm(self.bs, xs, self.ws)
        return _norm(_conv13(y, self.w2, n, k_out, 1), self.n2, relu=True, residual=s, valid=real * k_out), k_out


class FastNMNet:
    """Inference-only NM-Net built from a trained :class:`NMNet`; call with (N,4|5) inputs, (N,k) neighbours.

    ``dtype``: what the blocks' GEMMs and activations run in; None = the model's own (exact),
    ``torch.bfloat16`` = the faster approximation (module docstring). Embedding, normalisation
    arithmetic, head normalisation and logits stay in the model's dtype.
    """

    def __init__(self, model: NMNet, dtype: torch.dtype | None = None) -> None:
        model = model.eval()
        self.config = model.config
        self.score_threshold = model.score_threshold
        self.we = model.embed[0].weight.detach()[:, 0, 0, :].t().contiguous()  # (inputs, C)
        self.dtype = dtype or self.we.dtype
        self.ne = _fold_norm(model.embed[1])
        self.blocks = [_Block(b, self.dtype) for b in model.blocks]
        self.wh = model.head[0].weight.detach()[:, :, 0, 0].t().contiguous().to(self.dtype)
        self.nh = _fold_norm(model.head[1])
        self.wo = model.head[2].weight.detach()[:, :, 0, 0].t().contiguous()  # (C, 1)
        self.bo = model.head[2].bias.detach().clone()
        k = self.config["k"]  # compile (or load from numba's disk cache) the kernel now, not on the first frame
        self(torch.zeros(k, self.we.shape[0], dtype=self.we.dtype), torch.arange(k).repeat(k, 1))

    @torch.inference_mode()
    def __call__(self, corr: torch.Tensor, neighbors: torch.Tensor) -> torch.Tensor:
        """corr (N,4 or 5) float32 (``model.network_input``), neighbors (N,k) int64 (itself first) -> logits (N,)."""
        real, k = neighbors.shape
        f = _norm(corr @ self.we, self.ne, relu=True).to(self.dtype)  # (N, C): the embedding is a linear map
        n = real if self.dtype == self.we.dtype else -(-real // PAD) * PAD
        if n > real:  # padding correspondences (rows of the first one's features), never counted by the norms
            neighbors = torch.cat([neighbors, neighbors.new_zeros(n - real, k)])
        x = f[neighbors.reshape(-1)]  # grouping: (N*k, C)
        for blk in self.blocks:
            x, k = blk(x, n, k, real)
        if k != 1:
            x = x.view(n, k, -1).mean(1)
        h = _norm((x @ self.wh).to(self.we.dtype), self.nh, relu=True, valid=real)
        return torch.addmm(self.bo, h, self.wo)[:real, 0]
