"""bfloat16 on the CPU: whether it is native here, and its bits inside numba kernels.

bfloat16 is float32 with the low 16 bits dropped (8 significant bits), so a kernel reads a bfloat16
array as uint16 and widens a value by shifting its bits up. NM-Net's fast path and the descriptor
matcher's screening GEMM use it only where the CPU multiplies bfloat16 natively.
"""

from __future__ import annotations

import functools
import platform
from pathlib import Path

from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from .settings import PRECISION_NAMES

PRECISIONS = PRECISION_NAMES  # a setting's choices: auto = bfloat16 where the CPU has it natively
# bfloat16 GEMMs pad their rows to a multiple of this: oneDNN builds (JITs) a kernel for every new shape, ~9 ms
# per frame with a new N; padded, a stream of frames meets at most max_keypoints / PAD shapes
PAD = 64


def cpu_has_bf16(cpuinfo: str, machine: str) -> bool:
    """Whether a CPU, by its /proc/cpuinfo text and ``platform.machine()``, has bfloat16 dot products
    (x86 AVX512-BF16 / AMX-BF16, Arm BF16): only there is a bfloat16 GEMM faster than float32 (elsewhere
    it is emulated)."""
    words = set(cpuinfo.split())
    if machine.lower() in ("aarch64", "arm64"):
        return "bf16" in words
    return bool(words & {"avx512_bf16", "amx_bf16"})


@functools.cache
def native_bf16() -> bool:
    """:func:`cpu_has_bf16` for this machine (False where there is no /proc/cpuinfo)."""
    try:
        return cpu_has_bf16(Path("/proc/cpuinfo").read_text(), platform.machine())
    except OSError:
        return False


def use_bf16(precision: str, what: str) -> bool:
    """Whether the setting ``what`` = ``precision`` (one of :data:`PRECISIONS`) means bfloat16 on this CPU;
    ValueError naming the setting for anything else."""
    if precision not in PRECISIONS:
        raise ValueError(f"unknown {what} {precision!r}; use one of {', '.join(PRECISIONS)}")
    return precision == "bfloat16" or (precision == "auto" and native_bf16())


@intrinsic
def f32_from_bits(typingctx, u):  # pragma: no cover - compiled
    """The float32 whose bit pattern is the uint32 ``u``."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())
    return types.float32(types.uint32), codegen


@intrinsic
def bits_from_f32(typingctx, f):  # pragma: no cover - compiled
    """The bit pattern of the float32 ``f`` as a uint32."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))
    return types.uint32(types.float32), codegen
