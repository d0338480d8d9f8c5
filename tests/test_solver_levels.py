"""Coarse levels: the per-cell thinning of the points they are solved on."""

import numpy as np

from tiled_gridpull.solver import COARSE_POINTS_PER_CELL, _thin


def _cell_counts(P):
    _, counts = np.unique(np.floor(P).astype(np.int64), axis=0, return_counts=True)
    return counts


def test_thinning_caps_every_cell_and_keeps_sparse_cells_whole():
    rng = np.random.default_rng(0)
    dense = rng.uniform(0.0, 1.0, (500, 3)) + [2.0, 2.0, 2.0]  # one cell with 500 points
    sparse = rng.uniform(0.0, 1.0, (20, 3)) * [20.0, 1.0, 1.0] + [5.0, 0.0, 0.0]  # ~1 point per cell
    P = np.vstack([dense, sparse]).astype(np.float32)
    kept, keep = _thin(P, seed=3)
    assert np.array_equal(kept, P[keep]) and np.all(np.diff(keep) > 0)
    assert _cell_counts(kept).max() == COARSE_POINTS_PER_CELL
    # every sparse point survives; the dense cell keeps exactly the cap
    assert set(range(500, 520)) <= set(keep.tolist())
    assert np.sum(keep < 500) == COARSE_POINTS_PER_CELL
    # occupied cells never disappear
    assert len(_cell_counts(kept)) == len(_cell_counts(P))


def test_thinning_is_seeded():
    P = np.random.default_rng(1).uniform(0.0, 4.0, (5000, 3)).astype(np.float32)
    a, b, c = _thin(P, 7)[1], _thin(P, 7)[1], _thin(P, 8)[1]
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_thinning_leaves_a_sparse_cloud_alone():
    P = (np.arange(30, dtype=np.float32)[:, None] * [1.0, 0.0, 0.0] + 0.5).astype(np.float32)
    kept, keep = _thin(P, 0)
    assert kept is P and np.array_equal(keep, np.arange(30))


def test_a_level_counts_its_parameters_once(monkeypatch):
    # the TV step's scale divides by the band's parameter count: counting the flags at every iteration was 1.3 %
    # of a dense tile's solve; the band does not change during a level, so it is counted once per level
    from tiled_gridpull.band import Band
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.lattice import Lattice
    from tiled_gridpull.solver import solve

    counted = []
    plain = Band.n_params.fget
    monkeypatch.setattr(Band, "n_params", property(lambda self: counted.append(1) or plain(self)))
    v = np.random.default_rng(0).normal(size=(2000, 3))
    pts = 0.4 * v / np.linalg.norm(v, axis=1, keepdims=True)
    cfg = SolverConfig(resolution=64, levels=2, iterations=40, coarse_iterations=30, queries=1000, lr_step=10,
                       refine_lr_step=10)
    fld = solve(pts, Lattice.fit(pts, cfg.resolution, cfg.margin), cfg, history_every=0)
    assert [lv["iterations"] for lv in fld.info["levels"]] == [30, 40]
    assert len(counted) <= 2 * 2  # a level's TV scale, and the band's stats at most
