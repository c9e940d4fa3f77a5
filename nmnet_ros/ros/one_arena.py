"""Importing this module makes glibc serve all threads from one malloc arena (``MALLOC_ARENA_MAX=1``).

Why: the node's two stages allocate frame-sized buffers of varying size on their own threads. With
glibc's default of an arena per thread, freed blocks scatter over several heaps and RSS creeps up for
~100 frames before it levels (flood test: anonymous memory 160 -> 200 MB over 25 s). With one arena
it levels within ~30 frames, lower, at the same frame rate (the stages spend their time inside
OpenCV/torch, not in malloc). glibc fixes the arena limit when the first extra arena is made, so this
must run before any thread allocates: ``nmnet_ros.ros.node`` imports it first. No-op off glibc or when
``MALLOC_ARENA_MAX`` is already set by the user.
"""

from __future__ import annotations

import ctypes
import os

M_ARENA_MAX = -8  # from glibc's malloc.h


def limit_arenas(n: int = 1) -> bool:
    """Cap the number of malloc arenas at ``n``; True when glibc accepted it."""
    if "MALLOC_ARENA_MAX" in os.environ:
        return False
    try:
        return bool(ctypes.CDLL("libc.so.6").mallopt(M_ARENA_MAX, n))
    except (OSError, AttributeError):
        return False


ENABLED = limit_arenas(1)
