"""``nmnet bench``: stage timings on this machine, printed with the command's own baselines.

Neighbour mining: the vectorised blocked-matmul miner against the paper's formula written as a
per-correspondence loop (numpy), both in this process, for N = 1000 and 2000.
"""

from __future__ import annotations

import argparse
import json
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch

from .neighbors import compatibility_neighbors, compatibility_neighbors_loop, spatial_neighbors


def timeit(fn, repeat: int) -> list[float]:
    """Milliseconds of each of ``repeat`` calls after one warm-up call."""
    fn()
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append(1000 * (time.perf_counter() - t))
    return out


def synthetic_correspondences(n: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Matched keypoints and frames with the statistics of a 640x480 pair (timing only)."""
    rng = np.random.default_rng(seed)
    k0 = rng.uniform([0, 0], [640, 480], (n, 2)).astype(np.float32)
    k1 = (k0 + rng.normal(0, 15, (n, 2))).astype(np.float32)
    a0 = (rng.normal(0, 3, (n, 2, 2)) + 8 * np.eye(2)).astype(np.float32)
    a1 = (a0 @ (np.eye(2) + rng.normal(0, 0.1, (n, 2, 2)))).astype(np.float32)
    return k0, a0, k1, a1


def bench_neighbors(sizes: tuple[int, ...] = (1000, 2000), repeat: int = 20) -> dict:
    """Median/p90 ms of the miners and the ratio to the loop baseline."""
    res = {}
    for n in sizes:
        corr = synthetic_correspondences(n)
        fast = timeit(partial(compatibility_neighbors, *corr), repeat)
        spatial = timeit(partial(spatial_neighbors, corr[0], corr[2]), repeat)
        loop = timeit(partial(compatibility_neighbors_loop, *corr), 2)
        res[n] = {"compatibility_ms": float(np.median(fast)), "compatibility_p90_ms": float(np.percentile(fast, 90)),
                  "spatial_ms": float(np.median(spatial)), "loop_ms": float(np.median(loop)),
                  "speedup_vs_loop": float(np.median(loop) / np.median(fast))}
    return res


def add_arguments(p: argparse.ArgumentParser) -> None:
    """CLI options of ``nmnet bench``."""
    p.add_argument("--sizes", default="1000,2000", help="correspondence counts")
    p.add_argument("--repeat", type=int, default=20)
    p.add_argument("--json", type=Path, default=None, help="write the numbers as JSON")


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet bench``."""
    sizes = tuple(int(s) for s in args.sizes.split(","))
    print(f"torch threads: {torch.get_num_threads()}")
    res = {"neighbors": bench_neighbors(sizes, args.repeat)}
    print("| N | compatibility (median / p90 ms) | spatial kNN ms | per-correspondence loop ms | speed-up |")
    print("|---|---|---|---|---|")
    for n, r in res["neighbors"].items():
        print(f"| {n} | {r['compatibility_ms']:.1f} / {r['compatibility_p90_ms']:.1f} | {r['spatial_ms']:.1f} | "
              f"{r['loop_ms']:.0f} | {r['speedup_vs_loop']:.0f}x |")
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))
    return 0
