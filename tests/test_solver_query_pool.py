"""The precomputed query pool (``query_pool``): same queries as the fresh path, one search per batch."""

import numpy as np
import pytest

from tiled_gridpull.config import ConfigError, SolverConfig
from tiled_gridpull.lattice import Lattice
from tiled_gridpull.solver import solve


def _sphere_cloud(n=3000, seed=0):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return 0.4 * v / np.linalg.norm(v, axis=1, keepdims=True)


def _solve(**changes):
    pts = _sphere_cloud()
    cfg = SolverConfig(resolution=64, levels=2, iterations=30, coarse_iterations=20, queries=2000,
                       lr_step=10, refine_lr_step=10, **changes)
    return solve(pts, Lattice.fit(pts, cfg.resolution, cfg.margin), cfg)


@pytest.mark.slow
def test_a_pool_as_long_as_the_schedule_is_the_fresh_path():
    # batch b of the pool is drawn exactly as iteration b would be: with one batch per iteration, nothing changes
    fresh, pooled = _solve(query_pool=0), _solve(query_pool=1000)
    assert np.array_equal(fresh.values, pooled.values)


def test_a_short_pool_searches_once_per_batch_and_still_converges():
    fresh, pooled = _solve(query_pool=0), _solve(query_pool=5)
    assert [lv["nn_queries"] for lv in fresh.info["levels"]] == [20 * 2000, 30 * 2000]
    assert [lv["nn_queries"] for lv in pooled.info["levels"]] == [5 * 2000, 5 * 2000]
    assert not np.array_equal(fresh.values, pooled.values)
    # both fields fit the sphere: same sign pattern at the band's vertices almost everywhere
    same = np.mean(np.sign(fresh.values) == np.sign(pooled.values))
    assert same > 0.97
    again = _solve(query_pool=5)
    assert np.array_equal(again.values, pooled.values)


@pytest.mark.parametrize("bad", [-1, 2.5, "10"])
def test_query_pool_is_validated(bad):
    with pytest.raises(ConfigError, match="query_pool"):
        SolverConfig(query_pool=bad)
