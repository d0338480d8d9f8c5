"""Bridging with the sensor known, on scenes scanned by the synthetic LiDAR: things standing on the ground leave
the plane fits, and ground the sensor could not have seen (below a drop-off, behind a car) stays open.

Each scene is a height field 40 m across, scanned once by a 64-beam spinning LiDAR 1.73 m above the ground at the
origin; the
columns are decided at 0.3 m cells (a KITTI frame's cell in the benchmarks). A column bridged more than a cell
off the truth (the truth within a cell of the column, so a column beside a kerb's line may take either level)
is a wrong bridge. Ground within 4 m of the sensor lies below its lowest beam: unseen, but not hidden by anything
(the road under the scanning car), so the counts of bridged ground the sensor did not see leave it out.
"""

import math

import numpy as np
import pytest

from tiled_gridpull.bridge import BridgeRule, bridge_columns
from tiled_gridpull.io import read_points
from tiled_gridpull.kernels.bridge import (bin_low, bin_top, clear_pierced_gaps, hidden_from_sensor, object_bins,
                                           pierced_columns)
from tiled_gridpull.mesh import Mesh
from tiled_gridpull.synthetic.lidar import _RayCaster, hdl64_directions, visible_from

from conftest import shared_file

CELL = 0.3
HALF = 20.0
HEIGHT = 1.73  # the scanner above the ground under it


def _heightfield(fn, res=0.1):
    g = np.arange(-HALF, HALF + 1e-9, res)
    X, Y = np.meshgrid(g, g, indexing="ij")
    n = len(g)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(np.stack([X.ravel(), Y.ravel(), fn(X, Y).ravel()], 1), faces)


def _scan(mesh, sensor):
    pose = np.eye(4)[None].copy()
    pose[0, :3, 3] = sensor
    return _RayCaster(mesh.vertices, mesh.faces).cast(pose, hdl64_directions(64, 700), 0.5, 80.0)[1]


def _bridged(fn, **rule):
    """Bridged columns of the scene ``fn(x, y)`` (metres): their (x, y), height and distance to the truth (cells),
    and whether the sensor sees the truth there."""
    mesh = _heightfield(fn)
    sensor = np.array([0.0, 0.0, float(fn(np.zeros(1), np.zeros(1))[0]) + HEIGHT])
    xyz = _scan(mesh, sensor)
    lo = np.array([-HALF, -HALF, -3.0])
    cells = (xyz - lo) / CELL
    n = int(2 * HALF / CELL)
    fit = bridge_columns(cells, n, n, BridgeRule(**rule), np.broadcast_to((sensor - lo) / CELL, cells.shape).copy())
    ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    xy = np.stack([ii.ravel(), jj.ravel()], 1) * CELL + lo[:2]
    ok = np.isfinite(fit[:, 0])
    xy, z = xy[ok], fit[ok, 0] * CELL + lo[2]
    steps = (-CELL, -CELL / 2, 0.0, CELL / 2, CELL)
    near = [fn(xy[:, 0] + dx, xy[:, 1] + dy) for dx in steps for dy in steps]
    off = np.min([np.abs(z - t) for t in near], axis=0) / CELL
    seen = visible_from(mesh, np.c_[xy, fn(xy[:, 0], xy[:, 1]) + 0.02], sensor[None], stop_short=0.05)
    return xy, off, seen | (np.hypot(xy[:, 0], xy[:, 1]) < 4.0)


def _box(x0, x1, y0, y1, h):
    return lambda x, y: np.where((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1), h, 0.0)


def _drop(height, angle=0.7, at=10.0):
    """Ground ``height`` up on the sensor's side of a straight edge ``at`` m ahead, slanted by ``angle``."""
    return lambda x, y: height * (((x - at) * math.sin(angle) - y * math.cos(angle)) < 0)


@pytest.mark.parametrize("height", [0.6, 1.0, 2.0])
def test_a_slanted_drop_off_seen_from_its_top_is_not_ramped_down_to(height):
    """A drop-off crossing the scan at a slant, the sensor on its high side: no column more than a cell off the
    truth; a drop of 2 cells (0.6 m) is within the step test's reach, and its bridges stay within that test's 1.5
    cells."""
    _, off, _ = _bridged(_drop(height))
    worst = BridgeRule.step_tol if height / CELL <= 2 * BridgeRule.step_tol else 1.0
    assert not (off > worst).any(), (height, int((off > worst).sum()), float(off.max()))


def _square_drop(height, at=10.0):
    """The ground ``height`` lower beyond ``x = at``: an edge square to the line of sight, seen from its top."""
    return lambda x, y: np.where(x > at, -height, 0.0)


def test_the_grazing_test_cuts_the_ramps_below_a_drop_off_seen_from_its_top():
    """Seen from the top of a drop-off square to the line of sight, the low ground beyond the edge is hidden for
    metres, and a plane from the edge's samples to the low ground farther on is a ramp the line of sight only
    grazes. A 1.2 m (4-cell) drop 10 m ahead: 1,690 columns more than a cell off the truth without the
    hidden-ground tests, 151 with them (measured 2026-11-27)."""
    _, off_without, _ = _bridged(_square_drop(1.2), min_facing=-1e9, shadow_tol=1e9)
    _, off, _ = _bridged(_square_drop(1.2))
    assert (off > 1.0).sum() < 0.2 * (off_without > 1.0).sum()


@pytest.mark.xfail(strict=True, reason="known open failure (docs/solver.md, 'With the sensor known'): below a drop "
                                       "of 3-4 cells seen from its top, ramps as gentle as the ground's own slope "
                                       "pass both hidden-ground tests")
@pytest.mark.parametrize("height", [0.9, 1.2])
def test_no_ramp_at_all_below_a_drop_off_seen_from_its_top(height):
    _, off, _ = _bridged(_square_drop(height))
    assert not (off > 1.0).any()


def test_cars_leave_the_plane_fits_and_the_ground_around_them_closes():
    """Three parked cars: their samples (the lowest layer of their bins, half a metre up or more) refused the plane
    fit of every column within reach, and bridged a few wrong. Left out, the road around them closes, every
    bridge within a cell of the road, and no more ground the sensor did not see is bridged than before."""
    cars = lambda x, y: (_box(12, 16.5, -0.9, 0.9, 1.5)(x, y) + _box(8, 12.5, 5, 6.8, 1.5)(x, y)  # noqa: E731
                         + _box(-16, -11.5, -4, -2.2, 1.5)(x, y))
    xy0, off0, seen0 = _bridged(cars, object_width=0)
    xy1, off1, seen1 = _bridged(cars)
    assert len(xy1) > len(xy0) + 200
    assert not (off1 > 1.0).any()
    assert (~seen1).sum() <= (~seen0).sum()


def test_the_shadow_of_a_car_stays_open_with_things_left_out():
    """A car 6 m ahead hides the road behind it for metres. Its samples left out of the fits, the road on both sides
    of the shadow surrounds it and lies on one plane; the line of sight from the sensor to the road there passes
    under the car's roof, so the shadow stays open (no column more than a metre into it is bridged)."""
    car = _box(6, 10.5, -0.9, 0.9, 1.5)
    xy, off, seen = _bridged(car)
    # the shadow: behind the car, within its angular width as the sensor sees it
    deep = (xy[:, 0] > 11.5) & (np.abs(xy[:, 1]) < 0.9 * xy[:, 0] / 10.5 - 0.3) & (xy[:, 0] < 18.0)
    assert not deep.any(), xy[deep][:5]
    assert not (off > 1.0).any()


def test_a_hedge_beyond_a_cars_shadow_does_not_close_it():
    """A car and, beyond its shadow, a hedge: the hedge is no ground beyond the shadow."""
    scene = lambda x, y: _box(6, 10.5, -0.9, 0.9, 1.5)(x, y) + _box(14, 15, -4, 4, 1.2)(x, y)  # noqa: E731
    xy, off, _ = _bridged(scene)
    between = (xy[:, 0] > 11.5) & (xy[:, 0] < 13.5) & (np.abs(xy[:, 1]) < 0.6)
    assert not between.any()
    assert not (off > 1.0).any()


@pytest.mark.parametrize("scene", ["raised strip 1 m", "raised strip 2.4 m", "terrace 1 m", "kerb 0.3 m",
                                   "slope 10 % and a car"])
def test_steps_strips_and_slopes_are_never_bridged_off_the_truth(scene):
    fn = {"raised strip 1 m": _box(14, 16, -30, 30, 1.0), "raised strip 2.4 m": _box(14, 16, -30, 30, 2.4),
          "terrace 1 m": lambda x, y: np.where(x > 14, 1.0, 0.0), "kerb 0.3 m": _drop(0.3),
          "slope 10 % and a car": lambda x, y: 0.1 * x + _box(12, 16.5, -0.9, 0.9, 1.5)(x, y)}[scene]
    xy, off, _ = _bridged(fn)
    assert len(xy) > 1000
    assert not (off > 1.0).any(), (int((off > 1.0).sum()), float(off.max()))


def test_object_bins_flag_things_narrower_than_the_window_and_keep_wide_levels():
    n = 40
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    ground = 5.0 + 0.2 * i + 0.1 * j  # a tilted plane (cells)
    ground = np.where(j >= 25, ground + 4.0, ground)  # a terrace wider than the window
    thing = (i >= 10) & (i < 13) & (j >= 5) & (j < 9)  # a car 3 x 4 bins
    ground = np.where(thing, ground + 5.0, ground)
    ground[0:3, 30:33] = np.nan  # bins without a sample
    out = object_bins(ground, 6, 1.5)
    assert out[thing].all()
    # the rest, the terrace's edge on both sides included, is ground (an erosion alone would flag the terrace's
    # top along its edge: the least height within the window there is the lower level's)
    assert not out[~thing].any()
    # a thing wider than the window is a level of its own
    assert not object_bins(np.where(thing, 10.0, 5.0), 1, 1.5).any()


def test_hidden_from_sensor_sees_a_line_of_sight_blocked_and_a_plane_it_only_grazes():
    n = 30
    rep = np.full((n, n, 3), np.nan)
    sensor = np.full((n, n, 3), np.nan)
    top = np.full((n, n), -np.inf)
    # ground samples 5 cells up in every bin, seen from a sensor 10 cells above the ground at x = -40
    for a in range(n):
        for b in range(n):
            rep[a, b] = (2 * a + 1.0, 2 * b + 1.0, 5.0)
            sensor[a, b] = (-40.0, 31.0, 15.0)
            top[a, b] = 5.2
    top[10, 15] = 12.0  # a car's bin, 2 bins before the column as the sensor sees it
    cols = np.array([[25.0, 31.0], [25.0, 11.0], [17.0, 31.0]])  # behind the car, beside it, the car's far side
    level = np.array([[5.0, 0.0, 0.0]] * 3)
    none = np.zeros((n, n), bool)
    out = hidden_from_sensor(cols, level, rep, sensor, top, none, 2.0, 24.0, 24.0, 1.0, 0.5)
    assert out.tolist() == [True, False, False]
    # the car beyond the reach: not looked at
    assert not hidden_from_sensor(cols[:1], level[:1], rep, sensor, top, none, 2.0, 24.0, 3.0, 1.0, 0.5)[0]
    # a low thing (a median's top) half a cell above the line of sight: within the tolerance of ground, above it as
    # a thing standing on the ground
    low = np.full((n, n), 5.2)
    low[10, 15] = 5.0 + 10.0 * 4.0 / 65.0 + 0.5
    assert not hidden_from_sensor(cols[:1], level[:1], rep, sensor, low, none, 2.0, 24.0, 24.0, 1.0, 0.5)[0]
    thing = none.copy()
    thing[10, 15] = True
    assert hidden_from_sensor(cols[:1], level[:1], rep, sensor, low, thing, 2.0, 24.0, 24.0, 1.0, 0.5)[0]
    # a plane descending away from the sensor almost as steeply as the line of sight (a ramp below a drop-off)
    col = np.array([[40.0, 11.0]])
    sight = 10.0 / 80.0  # the line of sight's descent there
    for slope, hidden in ((0.0, False), (0.3 * sight, False), (0.7 * sight, True), (2.0 * sight, True)):
        plane = np.array([[5.0, -slope, 0.0]])
        assert hidden_from_sensor(col, plane, rep, sensor, np.full((n, n), -np.inf), none, 2.0, 24.0, 24.0, 1.0,
                                  0.5)[0] == hidden, slope


def test_bin_top_is_the_highest_point_of_each_bin():
    x = np.array([0.5, 1.5, 1.0, 3.0])
    y = np.array([0.5, 1.0, 1.0, 3.0])
    z = np.array([1.0, 1.5, 6.5, 7.0])
    top = bin_top(x, y, z, 2.0, 3, 3)
    assert top[0, 0] == 6.5 and top[1, 1] == 7.0 and top[2, 2] == -np.inf


def test_a_window_wider_than_the_tile_is_the_whole_tile():
    """``bridge_objects`` far beyond the tile (1e30 cells) decides as a window over the whole tile does, without
    a raster that size."""
    rng = np.random.default_rng(0)
    cells = np.c_[rng.uniform(0, 40, 4000), rng.uniform(0, 40, 4000), 5.0 + 0.1 * rng.standard_normal(4000)]
    sensor = np.broadcast_to([20.0, -30.0, 20.0], cells.shape).copy()
    huge = bridge_columns(cells, 40, 40, BridgeRule(object_width=1e30), sensor)
    whole = bridge_columns(cells, 40, 40, BridgeRule(object_width=160.0), sensor)
    np.testing.assert_array_equal(huge, whole)


def _ditch(width, depth, at=10.0):
    """A ditch across the view ``at`` m ahead: its bottom hidden behind its near rim, its far wall seen in part."""
    return lambda x, y: np.where((x > at) & (x < at + width), -depth, 0.0)


def test_a_ditch_whose_far_wall_the_beams_reach_gets_no_lid():
    """A ditch 3 m wide and 1.2 m deep 10 m ahead: its near rim and far rim lie on one plane, and nothing stands in
    the way, so the plane over its rims passed every other test (837 columns more than a cell off the truth). The
    beams that reach its far wall pass under that plane: 180 are left (measured 2026-11-27)."""
    _, off_without, _ = _bridged(_ditch(3.0, 1.2), pierce_beams=0)
    _, off, _ = _bridged(_ditch(3.0, 1.2))
    assert (off_without > 1.0).sum() > 500
    assert (off > 1.0).sum() < 0.25 * (off_without > 1.0).sum()


@pytest.mark.xfail(strict=True, reason="known open failure (docs/solver.md, 'A beam under the plane'): the beams "
                                       "to a narrower ditch's far wall pass under the plane over its rims by less "
                                       "than a cell, or only within the last 2 cells before the wall")
def test_no_lid_at_all_over_a_ditch():
    _, off, _ = _bridged(_ditch(2.0, 1.0))
    assert not (off > 1.0).any()


def _flat_plane(n, height=10.0):
    return np.full((n, n), height), np.zeros((n, n)), np.zeros((n, n))


def test_pierced_columns_counts_the_columns_a_beam_passes_under_the_plane():
    """A beam from a sensor 20 cells up to a point 5 cells under a level plane at 10: it runs more than a cell under
    the plane over the last 8 cells before its point (in plan), and the last 2 are not looked at."""
    n = 40
    h, gx, gy = _flat_plane(n)
    pt = [np.array([30.0]), np.array([20.0]), np.array([5.0])]
    sensor = [np.array([0.0]), np.array([20.0]), np.array([20.0])]
    low = np.full((n // 2, n // 2), np.inf)
    low[14, 10] = low[16, 10] = 5.0  # the bins on either side of the point's hold points as low

    def pierced(low=low, reach=48.0, height=h):
        return pierced_columns(*pt, *sensor, height, gx, gy, low, 2.0, 1.0, 2.0, reach, 1.0)

    count, along = pierced()
    assert sorted(zip(*np.nonzero(count))) == [(i, 20) for i in range(23, 29)]
    assert (count[count > 0] == 1).all()
    np.testing.assert_allclose(along[25, 20], [-1.0, 0.0])
    assert np.isnan(along[20, 20]).all()
    # only as far back as the reach
    assert sorted(zip(*np.nonzero(pierced(reach=5.0)[0]))) == [(i, 20) for i in range(25, 29)]
    # a column not bridged is not counted
    holed = h.copy()
    holed[25, 20] = np.nan
    assert pierced(height=holed)[0][25, 20] == 0 and pierced(height=holed)[0][26, 20] == 1
    # a point that one neighbouring bin's points reach down to, or none, is a reflection: left out
    one = low.copy()
    one[16, 10] = np.inf
    assert not pierced(low=one)[0].any()
    assert not pierced(low=np.full_like(low, np.inf))[0].any()
    # a beam over the plane pierces nothing
    assert not pierced_columns(pt[0], pt[1], np.array([10.5]), *sensor, h, gx, gy, low, 2.0, 1.0, 2.0, 48.0,
                               1.0)[0].any()
    # nor does a beam from a sensor below its point (a datum error, a trajectory's glitch): no sensor saw it so
    under = [sensor[0], sensor[1], np.array([-40.0])]
    assert not pierced_columns(*pt, *under, h, gx, gy, low, 2.0, 1.0, 2.0, 48.0, 1.0)[0].any()


def test_a_pierced_gap_opens_along_the_beam_up_to_the_points_on_either_side():
    """A beam showed the plane at column (25, 20) too high; the stretch of empty bins it lies in along that beam,
    between the bins holding points at x 20-21 and 30-31, opens as a whole."""
    n = 40
    mask = np.ones((n, n), bool)
    count = np.zeros((n, n), np.int32)
    along = np.full((n, n, 2), np.nan)
    count[25, 20] = 1
    along[25, 20] = (-1.0, 0.0)
    top = np.full((n // 2, n // 2), -np.inf)
    top[10, 10] = top[15, 10] = 3.0
    out = clear_pierced_gaps(mask, count, along, 1, top, 2.0, 48.0)
    assert not out[22:30, 20].any()
    assert out[:21, 20].all() and out[31:, 20].all()
    assert out[:, :20].all() and out[:, 21:].all()
    # too few beams: nothing opens
    assert clear_pierced_gaps(mask, count, along, 2, top, 2.0, 48.0).all()
    # a column not bridged stays as it was, and so does its stretch
    none = mask.copy()
    none[25, 20] = False
    assert (clear_pierced_gaps(none, count, along, 1, top, 2.0, 48.0) == none).all()


def _kitti_bridges(xyz, cell, **rule):
    """Which lattice columns a KITTI frame (sensor at the origin) bridges at ``cell``."""
    lo = xyz.min(axis=0) - 2 * cell
    cells = (xyz - lo) / cell
    nx, ny = (int(math.ceil(v)) + 2 for v in cells.max(axis=0)[:2])
    sensor = np.broadcast_to(-lo / cell, cells.shape).copy()
    return np.isfinite(bridge_columns(cells, nx, ny, BridgeRule(**rule), sensor)[:, 0])


def test_reflections_under_a_kitti_road_do_not_cut_its_bridges():
    """KITTI 00 frame 1 holds three points 3.4 m under the road 13 m from the car (a reflection): their beams run
    under the bridged road for 5 m. Points that no neighbouring bins' points reach down to are left out, so the
    frame's bridges are those without the test."""
    xyz = np.asarray(read_points(shared_file("kitti", "000001.bin")).xyz, np.float64)
    with_test = _kitti_bridges(xyz, CELL)
    without = _kitti_bridges(xyz, CELL, pierce_beams=0)
    assert without.sum() > 10_000
    np.testing.assert_array_equal(with_test, without)


def test_noisy_returns_under_a_kitti_road_do_not_cut_its_bridges_at_fine_cells():
    """At 0.1 m cells the test's cell of depth is 0.1 m: with 3 cm of noise added to a KITTI frame, single returns
    12-14 cm under their neighbours pierce the road's plane just past the skip, and one beam a column cut 59
    correct columns of this crop (radial slivers 13-32 m out; found by a review). Two beams a column cut none."""
    xyz = np.asarray(read_points(shared_file("kitti", "000001.bin")).xyz, np.float64)
    xyz = xyz[np.all(np.abs(xyz[:, :2]) < 35.0, axis=1)]
    xyz = xyz + np.random.default_rng(4).normal(0.0, 0.03, xyz.shape)
    with_test = _kitti_bridges(xyz, 0.1)
    without = _kitti_bridges(xyz, 0.1, pierce_beams=0)
    assert without.sum() > 50_000
    np.testing.assert_array_equal(with_test, without)


def test_bin_low_is_the_lowest_point_of_each_bin():
    x = np.array([0.5, 1.5, 1.0, 3.0])
    y = np.array([0.5, 1.0, 1.0, 3.0])
    z = np.array([1.0, 1.5, 6.5, 7.0])
    low = bin_low(x, y, z, 2.0, 3, 3)
    assert low[0, 0] == 1.0 and low[1, 1] == 7.0 and low[2, 2] == np.inf
