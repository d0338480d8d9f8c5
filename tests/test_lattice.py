import numpy as np
import pytest

from tiled_gridpull.errors import ConfigError
from tiled_gridpull.lattice import Lattice


def test_index_world_roundtrip_no_off_by_one():
    lat = Lattice((10.0, -5.0, 2.5), 0.25, (9, 5, 7))
    idx = np.array([[0, 0, 0], [8, 4, 6], [3.5, 2.25, 1.0]])
    w = lat.to_world(idx)
    assert np.allclose(w[0], lat.origin)
    assert np.allclose(w[1], lat.high_corner)
    assert np.allclose(lat.to_index(w), idx)
    # vertex (i, j, k) sits exactly at origin + i * cell
    assert np.allclose(w[1], np.array([10.0 + 8 * 0.25, -5.0 + 4 * 0.25, 2.5 + 6 * 0.25]))


def test_fit_centres_bbox_and_keeps_resolution():
    rng = np.random.default_rng(0)
    pts = rng.uniform([-3, 0, 10], [5, 2, 11], size=(1000, 3))
    lat = Lattice.fit(pts, resolution=64, margin=4)
    lo, hi = pts.min(0), pts.max(0)
    # longest side spans resolution - 2 * margin cells
    assert np.isclose((hi - lo).max() / lat.cell_size, 56)
    assert lat.n_cells[0] == 64
    centre = 0.5 * (lat.low_corner + lat.high_corner)
    assert np.allclose(centre, 0.5 * (lo + hi), atol=lat.cell_size)
    idx = lat.to_index(pts)
    assert idx.min() >= 4 - 1e-9 and np.all(idx.max(0) <= np.asarray(lat.shape) - 1 - 4 + 1e-9 + 1)


def test_blocks_share_vertices_exactly():
    glob = Lattice.aligned(np.array([500000.0, 4000000.0, 90.0]), np.array([500100.0, 4000100.0, 120.0]), 0.1)
    a = glob.block((0, 0, 0), (101, 101, 50))
    b = glob.block((100, 0, 0), (101, 101, 50))
    # global vertex 100 along x is a's last vertex and b's first: identical world position
    wa = a.to_world(np.array([[100, 7, 3]]))
    wb = b.to_world(np.array([[0, 7, 3]]))
    assert np.array_equal(wa, wb)
    assert a.origin == b.origin and a.cell_size == b.cell_size


def test_georeferenced_precision():
    lat = Lattice.aligned(np.array([500000.0, 4000000.0, 100.0]), np.array([500010.0, 4000010.0, 110.0]), 0.1)
    p = np.array([[500003.1234, 4000007.5678, 104.321]])
    assert np.abs(lat.to_world(lat.to_index(p)) - p).max() < 1e-6
    # the solver's float32 frame is small numbers: a millimetre survives
    loc = lat.to_local32(p).astype(np.float64)
    assert np.abs(lat.to_world(loc) - p).max() < 1e-4


@pytest.mark.parametrize("kwargs", [dict(cell_size=0.0), dict(cell_size=-1.0), dict(cell_size=float("nan"))])
def test_bad_lattice_rejected(kwargs):
    with pytest.raises(ConfigError):
        Lattice((0.0, 0.0, 0.0), kwargs["cell_size"], (4, 4, 4))


def test_dict_roundtrip():
    lat = Lattice((1.0, 2.0, 3.0), 0.5, (4, 5, 6), (7, 8, 9))
    assert Lattice.from_dict(lat.to_dict()) == lat


def test_shape_lattice_gives_the_coarsest_level_its_own_margin():
    """Three levels coarsen by 4: the finest lattice is padded so the coarsest still has ``margin`` empty cells
    beyond the cloud on every side, at the cell size ``resolution`` asks for."""
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.reconstruct import shape_lattice

    pts = np.random.default_rng(0).uniform([-1.0, -0.5, -0.25], [1.0, 0.5, 0.25], size=(5000, 3))
    cfg = SolverConfig(resolution=128, margin=4, levels=3)
    lat = shape_lattice(pts, cfg)
    plain = Lattice.fit(pts, 128, 4)
    assert lat.cell_size == pytest.approx(plain.cell_size)
    assert lat.shape == tuple(s + 2 * 12 for s in plain.shape)
    coarse = lat.coarsen(4)
    idx = coarse.to_index(pts)
    assert idx.min() >= 4 - 1e-9
    assert np.all(idx.max(axis=0) <= np.asarray(coarse.n_cells) - 4 + 1e-9)
    # one level: nothing to pad
    assert shape_lattice(pts, SolverConfig(resolution=128, levels=1)) == plain
    with pytest.raises(ConfigError, match="pad"):
        Lattice.fit(pts, 128, 4, pad=-1)
