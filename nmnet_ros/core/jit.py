"""Calling numba kernels beside torch: one thread budget, one caller at a time.

Compiled kernels (neighbour mining, NM-Net's normalisation, the fast detector's patch sampler,
orientation and descriptor) run on as many threads as torch's
intra-op setting (``torch.set_num_threads``), so the node's per-stage thread budget holds for
them too. numba's OpenMP layer shares torch's OpenMP runtime and resets its thread count when
its pool starts; that is undone here. Its fallback (workqueue) layer must not be entered by two
threads at once: then (and for the first launch, which picks the layer) calls take a lock. The
OpenMP and TBB layers are thread-safe, so the node's detection and NM-Net stages run their
kernels side by side.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Any

import numba
import torch

_LAUNCH = threading.Lock()


def launch(kernel: Callable[..., Any], *args: Any) -> Any:
    """Run ``kernel(*args)`` on torch's thread count (serialised across Python threads only on the
    workqueue layer)."""
    torch_threads = torch.get_num_threads()
    with _LAUNCH if _needs_lock() else contextlib.nullcontext():
        numba.set_num_threads(max(1, min(torch_threads, numba.config.NUMBA_NUM_THREADS)))
        out = kernel(*args)
        if torch.get_num_threads() != torch_threads:
            torch.set_num_threads(torch_threads)
    return out


def _needs_lock() -> bool:
    try:
        return numba.threading_layer() == "workqueue"
    except ValueError:  # no parallel kernel has run yet: the layer is chosen by the next launch
        return True
