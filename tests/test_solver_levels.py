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
