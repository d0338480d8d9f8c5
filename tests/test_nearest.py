"""Exactness of the solver's nearest-neighbour search: candidate lists with the KD-tree fallback."""

import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from tiled_gridpull.nearest import NearestPoints


def _dense_sheet(n: int, seed: int = 0) -> np.ndarray:
    """A wavy sheet with ~25 points per unit cell (LiDAR close to the scanner), in index units."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, np.sqrt(n / 25.0), (n, 2))
    z = 5.0 + 1.5 * np.sin(xy[:, 0] / 3.0) + rng.normal(0.0, 0.05, n)
    return np.column_stack([xy, z]).astype(np.float32)


def _queries(points: np.ndarray, sigma: float, n: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    centres = rng.integers(0, len(points), n)
    q = (points[centres] + rng.normal(0.0, sigma, (n, 3))).astype(np.float32)
    return q, centres


@pytest.mark.parametrize("sigma", [0.05, 0.5, 2.0])
def test_nearest_is_exact(sigma):
    pts = _dense_sheet(40_000)
    q, centres = _queries(pts, sigma, 20_000)
    nn = NearestPoints(pts, 8, sigma=sigma)
    idx, dist = nn.query(q, centres)
    ref_d, _ = KDTree(pts).query(q, k=1)
    # the nearest distance is unique even where two points tie; compare it, and that idx is at that distance
    np.testing.assert_allclose(dist, ref_d, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(pts[idx] - q, axis=1), ref_d, rtol=1e-5, atol=1e-6)
    if sigma == 0.05:
        assert nn.fallbacks < 0.2 * len(q)  # the fast path answers most queries close to the points


def test_nearest_in_an_offset_frame():
    pts = _dense_sheet(10_000) + np.float32([-37.25, 1000.5, -8.0])
    q, centres = _queries(pts, 0.7, 5000)
    idx, dist = NearestPoints(pts, 8).query(q, centres)
    ref_d, _ = KDTree(pts).query(q, k=1)
    np.testing.assert_allclose(dist, ref_d, rtol=1e-5, atol=1e-5)


def test_fast_path_and_kdtree_agree_on_indices():
    """The solver's result must not depend on which path answered: same indices with candidate lists of any
    size (no exact ties in a random cloud)."""
    pts = _dense_sheet(20_000, seed=3)
    q, centres = _queries(pts, 0.5, 10_000, seed=4)
    a, _ = NearestPoints(pts, 64).query(q, centres)
    b, _ = NearestPoints(pts, 1).query(q, centres)
    _, ref = KDTree(pts).query(q, k=1)
    assert np.array_equal(a, b) and np.array_equal(a, ref)


@pytest.mark.parametrize("sigma", [0.5, 2.0])
def test_predicted_fast_share_matches_the_measured_one(sigma, monkeypatch):
    monkeypatch.setattr(NearestPoints, "MIN_FAST_SHARE", 0.0)  # build the lists whatever the prediction
    pts = _dense_sheet(40_000)
    nn = NearestPoints(pts, 8, sigma=sigma)
    q, centres = _queries(pts, sigma, 20_000)
    nn.query(q, centres)
    assert abs(nn.fast_share - (1.0 - nn.fallbacks / nn.queries)) < 0.05


def test_lists_are_skipped_where_they_would_rarely_answer():
    pts = _dense_sheet(40_000)  # ~25 points per cell: 64 neighbours span less than the query spread
    nn = NearestPoints(pts, 8, sigma=2.0)
    assert nn.fast_share < NearestPoints.MIN_FAST_SHARE and nn.knn is None
    q, centres = _queries(pts, 2.0, 5000)
    idx, dist = nn.query(q, centres)
    ref_d, ref = KDTree(pts).query(q, k=1)
    assert np.array_equal(idx, ref) and nn.fallbacks == len(q)
    close = NearestPoints(pts, 8, sigma=0.02)  # queries close to their centres: the lists answer them
    assert close.fast_share > 0.9 and close.knn is not None


def test_nearest_in_cloud_is_exact_for_georeferenced_coordinates():
    """Indices and distances match a brute-force search on the cloud at the origin; a bound marks far queries."""
    from tiled_gridpull.nearest import distances_to_cloud, nearest_in_cloud

    rng = np.random.default_rng(4)
    pts = rng.uniform(0.0, 10.0, (3000, 3))
    q = rng.uniform(-1.0, 11.0, (500, 3))
    brute = np.linalg.norm(q[:, None] - pts[None], axis=2)
    shift = np.array([500000.0, 4000000.0, 100.0])
    d, i = nearest_in_cloud(q + shift, pts + shift)
    assert i.dtype == np.int64
    np.testing.assert_array_equal(i, brute.argmin(axis=1))
    np.testing.assert_allclose(d, brute.min(axis=1), atol=1e-9)
    bound = float(np.median(d))
    d_b, i_b = nearest_in_cloud(q + shift, pts + shift, bound)
    far = brute.min(axis=1) > bound * 1.0001
    assert np.all(np.isinf(d_b[far])) and np.all(i_b[far] == len(pts))
    np.testing.assert_array_equal(i_b[~far], i[~far])
    np.testing.assert_array_equal(distances_to_cloud(q + shift, pts + shift, bound), d_b)


# --- PointGrid: the tree-free search the CUDA backend runs on the card -------------------------------------------

def _surface_cloud(n: int, seed: int = 0) -> np.ndarray:
    """Points on a wavy sheet and a sphere: dense and sparse parts, as LiDAR tiles have."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, 60, n), rng.uniform(0, 60, n)
    sheet = np.c_[x, y, 2 * np.sin(x / 5)]
    d = rng.normal(size=(n // 4, 3))
    ball = d / np.linalg.norm(d, axis=1, keepdims=True) * 8 + 30
    return np.vstack([sheet, ball]).astype(np.float32)


@pytest.mark.parametrize("sigma", [0.1, 0.5, 3.0])
def test_point_grid_is_exact(sigma):
    from tiled_gridpull.kernels import sampling as ksamp
    from tiled_gridpull.nearest import PointGrid

    P = _surface_cloud(20000)
    nq = 30000
    centres = np.empty(nq, np.int64)
    q = np.empty((nq, 3), np.float32)
    ksamp.draw_queries(P, 5, 1, np.float32(sigma), centres, q)
    grid = PointGrid.for_queries(P, sigma)
    idx, d = grid.query(P, q, centres)
    d_ref, i_ref = KDTree(P).query(q, k=1)
    assert np.abs(d - d_ref).max() < 1e-5 * max(1.0, sigma)
    assert np.mean(idx == i_ref) > 0.999  # the rest: float32 near-ties of the tree
    # exact ties go to the lowest row, whatever the start
    far = np.full(nq, len(P) - 1, np.int64)
    assert np.array_equal(grid.query(P, q, far)[0], idx)


def test_point_grid_answers_queries_outside_its_cells_and_lowest_row_ties():
    from tiled_gridpull.nearest import PointGrid

    P = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [10, 10, 10]], np.float32)
    grid = PointGrid.build(P, 0.5)
    q = np.array([[-40, -3, 1], [1, 0, 0], [1, 1, 0], [30, 30, 30], [2.1, -0.1, 0]], np.float32)
    idx, d = grid.query(P, q, np.full(len(q), 3))
    assert idx.tolist() == [0, 0, 0, 3, 1]  # [1, 0, 0] and [1, 1, 0] are ties (2 and 3 points): the lowest row wins
    assert np.allclose(d, KDTree(P).query(q, k=1)[0], atol=1e-6)
    one = PointGrid.build(P[:1], 1.0)
    assert one.query(P[:1], q, np.zeros(len(q), np.int64))[0].tolist() == [0] * len(q)


def test_point_grid_sizes_its_cell_to_the_points_and_refuses_bad_input():
    from tiled_gridpull.nearest import PointGrid

    P = _surface_cloud(20000)
    for sigma in (0.05, 0.2, 1.0, 20.0):
        g = PointGrid.for_queries(P, sigma)
        per_cell = len(P) / np.count_nonzero(g.table_keys >= 0)
        assert sigma / 4 <= g.cell <= sigma * 4
        # within the clamp, the occupancy lands near the target
        if sigma / 4 < g.cell < sigma * 4:
            assert PointGrid.TARGET_PER_CELL / 2.5 < per_cell < PointGrid.TARGET_PER_CELL * 2.5, (sigma, g.cell)
        assert np.count_nonzero(g.table_keys >= 0) * 2 <= len(g.table_keys)
    with pytest.raises(ValueError, match="at least one point"):
        PointGrid.build(np.zeros((0, 3), np.float32), 1.0)
    with pytest.raises(ValueError, match="positive cell"):
        PointGrid.build(P, 0.0)
    g = PointGrid.build(P, 1.0)
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError, match="finite queries"):
            g.query(P, np.array([[bad, 0, 0]], np.float32), np.zeros(1, np.int64))


def test_point_grid_cell_keys_do_not_overflow_for_fine_cells_over_a_wide_cloud():
    """Clusters 1e5 apart in cells of 0.01: 1e7 cells an axis, whose product (1e21) would wrap the int64 cell keys
    (negative keys read as empty hash slots, dropping cells): the search must stay exact."""
    from tiled_gridpull.nearest import PointGrid

    rng = np.random.default_rng(0)
    cen = rng.uniform(0, 1e5, (50, 3))
    P = (cen[:, None, :] + rng.normal(0, 0.01, (50, 40, 3))).reshape(-1, 3).astype(np.float32)
    q = (P[rng.integers(0, len(P), 3000)] + rng.normal(0, 0.01, (3000, 3))).astype(np.float32)
    d_ref = KDTree(P).query(q, k=1)[0]
    for cell in (0.01, 0.02):
        grid = PointGrid.build(P, cell)
        assert np.all(grid.table_keys >= -1)
        assert np.prod(grid.dims.astype(np.float64)) < 2.0 ** 62
        _, d = grid.query(P, q, rng.integers(0, len(P), len(q)))
        assert np.abs(d - d_ref).max() < 1e-4
