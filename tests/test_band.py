import numpy as np
import pytest

from tiled_gridpull.band import build_band, dense_brick_table, vertex_slots
from tiled_gridpull.kernels import CELL_OCC, CELL_OPT, CELL_PULL, PARAM
from tiled_gridpull.lattice import Lattice


def brute_band(cells_occ, ncell, m):
    """Cells within Chebyshev distance m of an occupied cell (definition)."""
    out = np.zeros(ncell, bool)
    for c in cells_occ:
        lo = np.maximum(c - m, 0)
        hi = np.minimum(c + m + 1, ncell)
        out[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = True
    return out


@pytest.mark.parametrize("m1,m2,shape", [(1, 3, (27, 21, 19)), (0, 9, (30, 18, 41)), (3, 3, (12, 12, 12))])
def test_band_equals_brute_force_definition(rng, m1, m2, shape):
    lat = Lattice((0.0, 0.0, 0.0), 1.0, shape)
    hi = np.asarray(shape) - 1
    pts = rng.uniform(0, 1, size=(40, 3)) * hi
    band = build_band(pts, lat, m1, m2)
    ncell = np.asarray(lat.n_cells)
    occ_cells = np.unique(np.floor(pts).astype(int), axis=0)
    cell_m2 = brute_band(occ_cells, ncell, m2)
    cell_m1 = brute_band(occ_cells, ncell, m1)
    # parameters: every vertex of an M2 cell
    vparam = np.zeros(lat.shape, bool)
    for c in np.argwhere(cell_m2):
        vparam[c[0]:c[0] + 2, c[1]:c[1] + 2, c[2]:c[2] + 2] = True
    assert np.array_equal(band.dense_mask(PARAM), vparam)
    # optimized cells: all 8 corners are parameters
    opt = np.zeros(ncell, bool)
    for c in np.ndindex(*ncell):
        opt[c] = vparam[c[0]:c[0] + 2, c[1]:c[1] + 2, c[2]:c[2] + 2].all()
    assert np.array_equal(band.dense_mask(CELL_OPT)[:-1, :-1, :-1], opt)
    assert np.array_equal(band.dense_mask(CELL_PULL)[:-1, :-1, :-1], cell_m1)
    occ = np.zeros(ncell, bool)
    occ[tuple(occ_cells.T)] = True
    assert np.array_equal(band.dense_mask(CELL_OCC)[:-1, :-1, :-1], occ)
    assert band.n_params == vparam.sum()


def test_band_memory_scales_with_band_not_volume():
    # a small cluster in a huge lattice allocates only the bricks around it
    lat = Lattice((0.0, 0.0, 0.0), 1.0, (1025, 1025, 1025))
    pts = np.array([[500.5, 500.5, 500.5], [501.5, 500.5, 500.5]])
    band = build_band(pts, lat, 1, 2)
    assert band.n_bricks <= 8
    assert band.brick_table.shape == (129, 129, 129)


def test_brick_neighbors_consistent(rng):
    lat = Lattice((0.0, 0.0, 0.0), 1.0, (40, 40, 40))
    pts = rng.uniform(5, 35, size=(200, 3))
    band = build_band(pts, lat, 1, 4)
    coords = band.brick_coords
    for b in range(band.n_bricks):
        for side in range(6):
            nb = band.neighbors[b, side]
            axis, sign = divmod(side, 2)
            step = np.zeros(3, int)
            step[axis] = 1 if sign else -1
            target = coords[b] + step
            if nb >= 0:
                assert np.array_equal(coords[nb], target)
            else:
                inside = np.all((target >= 0) & (target < band.brick_table.shape))
                assert not inside or band.brick_table[tuple(target)] == -1


def test_dense_brick_table_numbers_bricks_in_order_and_marks_the_rest_absent():
    coords = np.array([[2, 0, 1], [0, 0, 0], [1, 2, 1]])
    table = dense_brick_table((3, 3, 2), coords)
    assert table.dtype == np.int32 and table.shape == (3, 3, 2)
    assert [int(table[tuple(c)]) for c in coords] == [0, 1, 2]
    assert np.count_nonzero(table >= 0) == 3 and set(np.unique(table)) == {-1, 0, 1, 2}
    wide = dense_brick_table((3, 3, 2), coords, first=7, dtype=np.int64)
    assert wide.dtype == np.int64 and int(wide[1, 2, 1]) == 9 and int(wide[0, 0, 1]) == -1


def test_vertex_slots_by_hand():
    # bricks (0, 0, 0) -> 0 and (1, 0, 0) -> 1 of a 2 x 1 x 1 grid
    table = dense_brick_table((2, 1, 1), np.array([[0, 0, 0], [1, 0, 0]]))
    v = np.array([[0, 0, 0], [1, 2, 3], [9, 0, 7], [16, 0, 0], [-1, 0, 0], [3, 8, 0]])
    assert vertex_slots(table, v).tolist() == [0, 64 + 16 + 3, 512 + 64 + 7, -1, -1, -1]
    # an absent brick inside the grid
    assert vertex_slots(dense_brick_table((2, 1, 1), np.array([[1, 0, 0]])), v[:3]).tolist() == [-1, -1, 64 + 7]
