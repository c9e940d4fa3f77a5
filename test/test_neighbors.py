"""Compatibility neighbours (paper Eq. 2-5) and spatial kNN; the paper's Fig. 3 ordering on real pairs."""

import numpy as np
import pytest

from nmnet_ros.core.neighbors import compatibility_neighbors, compatibility_neighbors_loop, mine_neighbors, spatial_neighbors
from nmnet_ros.io.datasets import Sequence
from nmnet_ros.io.pairs import make_pair
from nmnet_ros.tools.neighbor_study import neighbor_inlier_ratios

from .conftest import data_dir


def random_corr(n, seed=0):
    rng = np.random.default_rng(seed)
    k0 = rng.uniform(0, 640, (n, 2))
    k1 = k0 + rng.normal(0, 30, (n, 2))
    a0 = rng.normal(0, 4, (n, 2, 2)) + 8 * np.eye(2)
    a1 = a0 @ (np.eye(2) + rng.normal(0, 0.2, (n, 2, 2)))
    return k0, a0, k1, a1


@pytest.mark.parametrize("n", [1, 5, 9, 300])
def test_vectorised_equals_literal_formula(n):
    k0, a0, k1, a1 = random_corr(n)
    fast = compatibility_neighbors(k0, a0, k1, a1, 8)
    ref = compatibility_neighbors_loop(k0, a0, k1, a1, 8)
    assert fast.shape == (n, 8)
    assert np.array_equal(fast[:, 0], np.arange(n))  # self first
    np.testing.assert_array_equal(fast, ref)


def test_threads_mine_concurrently():
    """Training mines a batch in parallel threads: concurrent calls must neither crash numba's
    thread pool nor mix up results."""
    from concurrent.futures import ThreadPoolExecutor

    sets = [random_corr(700, seed=s) for s in range(8)]
    expected = [compatibility_neighbors(*c) for c in sets]
    with ThreadPoolExecutor(4) as pool:
        for _ in range(3):
            got = list(pool.map(lambda c: compatibility_neighbors(*c), sets))
            for g, e in zip(got, expected, strict=True):
                np.testing.assert_array_equal(g, e)


def test_mining_keeps_the_callers_torch_thread_count():
    """numba's OpenMP pool shares torch's runtime: starting it must not undo torch.set_num_threads
    (the node budgets one thread per pipeline stage). A fresh process, so the pool starts here."""
    import subprocess
    import sys

    code = (
        "import numpy as np, torch\n"
        "from nmnet_ros.core.neighbors import compatibility_neighbors\n"
        "torch.set_num_threads(1)\n"
        "r = np.random.default_rng(0); a = np.tile(np.eye(2), (50, 1, 1))\n"
        "compatibility_neighbors(r.normal(size=(50, 2)), a, r.normal(size=(50, 2)), a)\n"
        "print(torch.get_num_threads())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split()[-1] == "1"


def test_concurrent_mining_on_numbas_workqueue_layer():
    """numba's fallback threading layer aborts the process when two threads launch kernels at once;
    nmnet_ros.core.jit serialises launches there (a fresh process, forced onto that layer)."""
    import os
    import subprocess
    import sys

    code = (
        "import numpy as np, numba\n"
        "from concurrent.futures import ThreadPoolExecutor\n"
        "from nmnet_ros.core.neighbors import compatibility_neighbors\n"
        "r = np.random.default_rng(0); a = np.tile(np.eye(2), (1500, 1, 1))\n"
        "sets = [(r.normal(size=(1500, 2)), a, r.normal(size=(1500, 2)), a) for _ in range(8)]\n"
        "with ThreadPoolExecutor(4) as pool:\n"
        "    got = list(pool.map(lambda c: compatibility_neighbors(*c), sets * 3))\n"
        "print(numba.threading_layer(), len(got))\n"
    )
    env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["workqueue", "24"]


def test_consistent_group_are_each_others_neighbours():
    # 20 correspondences from one affine map + 200 random ones: the 20 pick each other.
    rng = np.random.default_rng(3)
    M, b = np.array([[1.1, 0.2], [-0.1, 0.9]]), np.array([15.0, -7.0])
    k0 = rng.uniform(0, 500, (220, 2))
    a0 = rng.normal(0, 3, (220, 2, 2)) + 6 * np.eye(2)
    k1 = k0 @ M.T + b
    a1 = M @ a0
    k1[20:] = rng.uniform(0, 500, (200, 2))
    a1[20:] = rng.normal(0, 3, (200, 2, 2)) + 6 * np.eye(2)
    nb = compatibility_neighbors(k0, a0, k1, a1, 8)
    assert np.all(nb[:20] < 20)


def test_chunked_path_for_large_n():
    k0, a0, k1, a1 = random_corr(4000, seed=1)
    nb = compatibility_neighbors(k0, a0, k1, a1, 8)
    assert nb.shape == (4000, 8) and np.array_equal(nb[:, 0], np.arange(4000))
    sample = np.arange(0, 4000, 397)
    ref = compatibility_neighbors_loop(k0, a0, k1, a1, 8)[sample]
    assert np.mean(nb[sample] == ref) > 0.99  # float32 vs float64 ties may swap a rare pair


def test_spatial_neighbours_and_small_n_padding():
    k0, _, k1, _ = random_corr(5)
    nb = spatial_neighbors(k0, k1, 8)
    assert nb.shape == (5, 8) and np.array_equal(nb[:, 0], np.arange(5))
    assert np.all(nb[:, 5:] == nb[:, :1])  # N < k: padded with self
    x = np.c_[k0, k1]
    d = np.linalg.norm(x[:, None] - x[None], axis=2)
    np.testing.assert_array_equal(nb[:, 1:5], np.argsort(d, 1)[:, 1:5])


def test_empty_and_mismatched_inputs():
    z2, z22 = np.zeros((0, 2)), np.zeros((0, 2, 2))
    assert compatibility_neighbors(z2, z22, z2, z22).shape == (0, 8)
    assert spatial_neighbors(z2, z2).shape == (0, 8)
    k0, a0, k1, a1 = random_corr(10)
    with pytest.raises(ValueError, match="disagree"):
        compatibility_neighbors(k0, a0[:9], k1, a1)
    with pytest.raises(ValueError, match="unknown neighbour kind"):
        mine_neighbors("bogus", k0, a0, k1, a1)


def test_compatibility_beats_spatial_on_real_pairs(cache):
    """Paper Fig. 3: neighbours mined by compatibility hold more inliers than spatial kNN."""
    cases = [("kitti-07", 0, 3), ("kitti-07", 40, 48), ("kitti-07", 100, 105), ("strecha-fountain-p11", 2, 3),
             ("strecha-herz-jesus-p25", 10, 12)]
    for name, i, j in cases:
        seq = Sequence.load(data_dir(name))
        c, s = neighbor_inlier_ratios(make_pair(seq, i, j, cache))
        print(f"{name} {i}-{j}: compatibility {100 * c:.1f}% spatial {100 * s:.1f}%")
        assert c > s
