"""spacing: sample spacing by point and by area; the cell size voxel_size auto picks from it."""

import numpy as np
import pytest

from tiled_gridpull.errors import ConfigError
from tiled_gridpull.spacing import Spacing, point_spacing
from tiled_gridpull.tiling import auto_cell_size


def plane(n, side, rng, z=0.0):
    return np.c_[rng.uniform(0, side, n), rng.uniform(0, side, n), np.full(n, z)]


@pytest.mark.parametrize("spacing", [0.05, 0.3, 2.0])
def test_uniform_plane_spacing_is_one_over_root_density(spacing):
    rng = np.random.default_rng(0)
    side = 200 * spacing
    xyz = plane(200 * 200, side, rng) + [5e5, 4e6, 100.0]  # georeferenced: measured from the mean
    sp = point_spacing(xyz)
    # pi r_8^2 / 8 is an unbiased-in-the-mean area per point for a Poisson process; the median is a bit below
    assert 0.75 * spacing < sp.median < 1.05 * spacing
    assert 0.8 * spacing < sp.area_median < 1.2 * spacing


def test_by_area_weighs_the_sparse_part_by_point_the_dense_part():
    rng = np.random.default_rng(1)
    dense = plane(40_000, 10.0, rng)             # 0.05 spacing on 100 m^2
    sparse = plane(2_500, 100.0, rng, z=50.0)    # 2.0 spacing on 10,000 m^2
    sp = point_spacing(np.r_[dense, sparse])
    assert sp.median < 0.1 < 1.0 < sp.area_median


@pytest.mark.parametrize("median,area,cell", [
    (0.035, 0.225, 0.1), (0.124, 0.365, 0.2), (0.386, 0.460, 0.5), (2.16, 2.80, 2.5), (0.02, 0.03, 0.025),
    (300.0, 300.0, 250.0),
])
def test_auto_cell_is_a_round_number_near_the_geometric_mean(median, area, cell):
    assert auto_cell_size(Spacing(median, area, 1000, 1000)) == cell


def test_auto_refuses_clouds_without_spacing():
    with pytest.raises(ConfigError, match="no measurable spacing"):
        auto_cell_size(Spacing(0.0, 0.0, 100, 100))
    with pytest.raises(ValueError, match="more than 8 points"):
        point_spacing(np.zeros((5, 3)))


def test_a_few_stray_points_do_not_decide_the_spacing_by_area():
    """Ten points scattered over 90 m each stand for a disc of hundreds of square metres: uncapped they held
    most of the area and made the by-area spacing 36 m for a survey sampled every 0.25 m."""
    rng = np.random.default_rng(2)
    ground = plane(30_000, np.sqrt(1800.0), rng)
    strays = np.c_[rng.uniform(0, 90, 10), rng.uniform(0, 90, 10), rng.uniform(20, 40, 10)]
    clean, with_strays = point_spacing(ground), point_spacing(np.r_[strays, ground])
    assert with_strays.area_median == pytest.approx(clean.area_median, rel=0.05)
