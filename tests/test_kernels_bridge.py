"""The bridge's column kernel: which lattice columns a ground gap closes over, and at what height."""

import math

import numpy as np
from numba import njit

from tiled_gridpull.kernels.bridge import (SECTORS, bin_ground, bin_sensor, fit_columns, flag_bridged_cells,
                                          sector_of)

PIXEL = 2.0
ARGS = dict(radius=24.0, skip=2.0, max_gap=4, rms_tol=0.25, step_tol=1.5, max_slope=0.6)


def _reps(lines, nx=40, ny=40):
    """Ground samples on lines y = const (cells), every 0.5 cell along x, binned."""
    pts = []
    for y, zfun in lines:
        x = np.arange(0.0, nx * PIXEL, 0.5)
        pts.append(np.stack([x, np.full_like(x, y), zfun(x, y)], axis=1))
    p = np.concatenate(pts)
    return bin_ground(p[:, 0].copy(), p[:, 1].copy(), p[:, 2].copy(), PIXEL, nx, ny, 1.0)


def _fit(rep, cols, **kw):
    a = {**ARGS, **kw}
    return fit_columns(rep, PIXEL, np.asarray(cols, np.float64), a["radius"], a["skip"], a["max_gap"],
                       a["rms_tol"], a["step_tol"], a["max_slope"],
                       a.get("sensor", np.full((*rep.shape[:2], 2), np.nan)), a.get("far_cos", 2.0))


def test_bin_ground_means_the_lowest_layer_of_each_bin():
    # bin (0, 0): two ground points and one 5 cells up (a crown, a car's roof); bin (1, 1): one point
    x = np.array([0.5, 1.5, 1.0, 3.0])
    y = np.array([0.5, 1.0, 1.0, 3.0])
    z = np.array([1.0, 1.5, 6.5, 7.0])
    rep = bin_ground(x, y, z, 2.0, 3, 3, 1.0)
    assert np.allclose(rep[0, 0], [1.0, 0.75, 1.25]) and np.allclose(rep[1, 1], [3.0, 3.0, 7.0])
    assert np.isnan(rep[2, 2]).all()


def test_a_gap_between_two_scan_lines_is_bridged_on_their_plane():
    plane = lambda x, y: 5.0 + 0.1 * x - 0.05 * y  # noqa: E731
    rep = _reps([(10.0, plane), (30.0, plane)])
    out = _fit(rep, [(40.0, 20.0), (41.0, 15.0)])
    assert np.all(np.isfinite(out))
    assert np.allclose(out[:, 0], [plane(40.0, 20.0), plane(41.0, 15.0)], atol=1e-6)
    assert np.allclose(out[:, 1:], [[0.1, -0.05]] * 2, atol=1e-6)


def test_one_sided_far_stepped_and_steep_gaps_stay_open():
    flat = lambda x, y: np.full_like(x, 5.0)  # noqa: E731
    high = lambda x, y: np.full_like(x, 8.0)  # noqa: E731
    # points on one side only (a shadow's edge, the scan's outer edge)
    assert np.isnan(_fit(_reps([(10.0, flat)]), [(40.0, 20.0)])).all()
    # a height step of 3 cells in the gap, two scan lines on each side (a kerb, a raised verge)
    stepped = [(4.0, flat), (10.0, flat), (30.0, high), (36.0, high)]
    assert np.isnan(_fit(_reps(stepped), [(40.0, 20.0)])).all()
    # the same lines bridge without the step
    assert np.isfinite(_fit(_reps([(4.0, flat), (10.0, flat), (30.0, flat), (36.0, flat)]), [(40.0, 20.0)])).all()
    # lines farther apart than twice the radius
    assert np.isnan(_fit(_reps([(5.0, flat), (75.0, flat)]), [(40.0, 40.0)])).all()
    # steep ground
    steep = lambda x, y: 0.9 * y + 0.0 * x  # noqa: E731
    assert np.isnan(_fit(_reps([(10.0, steep), (30.0, steep)]), [(40.0, 20.0)])).all()
    assert np.isfinite(_fit(_reps([(10.0, steep), (30.0, steep)]), [(40.0, 20.0)], max_slope=1.0)).all()


def test_densely_sampled_columns_are_left_to_the_solved_field():
    flat = lambda x, y: np.full_like(x, 5.0)  # noqa: E731
    # beside a lone line with another 20 cells away: bridged, the line's own field has no slope across it
    assert np.isfinite(_fit(_reps([(10.0, flat), (30.0, flat)]), [(40.0, 11.0)], skip=4.0)).all()
    # amid lines 2 cells apart (dense ground): the solved field's
    dense = [(y, flat) for y in np.arange(2.0, 60.0, 2.0)]
    assert np.isnan(_fit(_reps(dense), [(40.0, 21.0)], skip=4.0)).all()
    assert np.isfinite(_fit(_reps(dense), [(40.0, 21.0)], skip=1.0)).all()


def _weighted_plane(rep, cx, cy, radius):
    """The kernel's plane at column (cx, cy) by numpy's least squares: the representatives within ``radius``,
    Gaussian weights as wide as the kernel makes them (from the nearest one and the farthest sector's nearest)."""
    r = rep.reshape(-1, 3)
    r = r[np.isfinite(r[:, 2])]
    dx, dy, z = r[:, 0] - cx, r[:, 1] - cy, r[:, 2]
    d2 = dx * dx + dy * dy
    keep = d2 <= radius * radius
    dx, dy, z, d2 = dx[keep], dy[keep], z[keep], d2[keep]
    sector = ((np.arctan2(dy, dx) + np.pi) / (2 * np.pi) * 12).astype(int) % 12
    farthest = max(d2[sector == s].min() for s in np.unique(sector))
    sigma = max(1.5 * np.sqrt(d2.min()), 0.7 * np.sqrt(farthest), PIXEL)
    sw = np.sqrt(np.exp(-d2 / sigma ** 2))
    sol, *_ = np.linalg.lstsq(np.stack([sw, sw * dx, sw * dy], axis=1), sw * z, rcond=None)
    return sol


def test_the_plane_of_noisy_ground_is_the_weighted_least_squares_plane():
    """The 3 x 3 normal equations solved by cofactors (not np.linalg, whose bindings took most of the kernel's
    compile time) give numpy's weighted least-squares plane on bumpy, noisy scan lines."""
    rng = np.random.default_rng(3)
    bumpy = lambda x, y: 5.0 + 0.05 * x + 0.02 * y + 0.08 * np.sin(x / 3.0) + rng.normal(0, 0.03, x.shape)  # noqa: E731
    rep = _reps([(y, bumpy) for y in (6.0, 14.0, 26.0, 34.0, 50.0)])
    cols = np.column_stack([rng.uniform(20, 60, 40), rng.uniform(16, 24, 40)])
    out = _fit(rep, cols)
    done = np.isfinite(out[:, 0])
    assert done.sum() >= 30
    want = np.array([_weighted_plane(rep, cx, cy, ARGS["radius"]) for cx, cy in cols[done]])
    np.testing.assert_allclose(out[done], want, rtol=0, atol=1e-9)


def test_a_tall_line_beyond_the_ground_is_not_ramped_up_to():
    """Two ground lines and a wall's or hedge's line 10 cells up beyond them: no ramp runs from the ground up to
    the line (a rule that left the tall line out of the plane fit as a thing standing on the ground, tried on
    2026-11-27, dropped the farther ground line with it and bridged one)."""
    flat = lambda x, y: np.full_like(x, 5.0)  # noqa: E731
    rep = _reps([(4.0, flat), (10.0, flat)])
    rep[:, 14] = np.stack([np.arange(rep.shape[0]) * PIXEL + 1.0, np.full(rep.shape[0], 29.0),
                           np.full(rep.shape[0], 15.0)], axis=1)
    cols = np.stack(np.meshgrid(np.arange(20.0, 60.0), np.arange(12.0, 27.0), indexing="ij"), -1).reshape(-1, 2)
    out = _fit(rep, cols)
    assert not (np.abs(out[:, 0] - 5.0) > 0.5).any()


def _kerb_reps(height, angle_deg, lines=(10.0, 30.0)):
    """Scan lines y = const over ground 5 cells up with a kerb ``height`` cells high crossing them at
    ``angle_deg`` through (40, 20), binned; the height function too."""
    a = math.radians(angle_deg)

    def z(x, y):
        return 5.0 + height * (((x - 40.0) * math.sin(a) - (y - 20.0) * math.cos(a)) < 0)

    return _reps([(y, z) for y in lines]), z


def test_a_kerb_across_the_scan_lines_is_not_bridged_as_a_ramp():
    """A kerb or step crossing two scan lines at a slant: no column between the lines is bridged more than a cell
    off the truth, whatever its height (the rule for things standing on the ground tried on 2026-11-27 bridged
    such steps over 3 cells high as ramps from one line to the other)."""
    cols = np.stack(np.meshgrid(np.arange(16.0, 65.0), np.arange(10.0, 31.0), indexing="ij"), -1).reshape(-1, 2)
    for height in (3.0, 3.5, 4.0, 6.0, 8.0):
        for angle in (30.0, 45.0, 90.0):
            rep, z = _kerb_reps(height, angle)
            out = _fit(rep, cols, skip=4.0)
            off = np.abs(out[:, 0] - z(cols[:, 0], cols[:, 1]))
            assert not (off > 1.0).any(), (height, angle)


def test_a_raised_strip_between_road_lines_keeps_its_gaps_open():
    """A raised strip (a median, a terrace) between road lines, 8 and 15 cells up: the road is not bridged
    towards it."""
    level = lambda v: (lambda x, y: np.full_like(x, v))  # noqa: E731
    for top in (13.0, 20.0):
        rep = _reps([(2.0, level(5.0)), (8.0, level(5.0)), (14.0, level(5.0)), (26.0, level(top)),
                     (30.0, level(top)), (38.0, level(5.0)), (44.0, level(5.0))])
        assert np.isnan(_fit(rep, [(40.0, float(y)) for y in range(15, 26)])).all(), top


def test_a_hedge_beyond_a_shadow_is_not_ground_beyond_it():
    """The sensor known: a car, its shadow, a hedge beyond the shadow. The hedge lies beyond the shadow's columns
    as the sensor sees it, but the car's and the hedge's samples keep the plane fit from closing the shadow: no
    column of it is bridged."""
    n = 40
    rep = np.full((n, n, 3), np.nan)
    for i in range(n):
        for j in range(n):
            x, y = (i + 0.5) * PIXEL, (j + 0.5) * PIXEL
            if 34 <= x <= 46 and 20 <= y <= 26:
                rep[i, j] = (x, y, 9.5)  # the car
            elif 33 <= x <= 47 and 26 < y < 50:
                continue  # its shadow
            elif 33 <= x <= 47 and 50 <= y <= 54:
                rep[i, j] = (x, y, 10.0)  # the hedge, its foot hidden
            elif 33 <= x <= 47 and y > 54:
                continue  # the hedge's shadow
            else:
                rep[i, j] = (x, y, 5.0)
    sensor = np.zeros((n, n, 2))
    sensor[..., 0], sensor[..., 1] = 40.0, -20.0
    kw = dict(skip=4.0, max_gap=5, rms_tol=0.5, sensor=sensor, far_cos=math.cos(math.radians(15.0)))
    shadow = [(float(x), float(y)) for x in range(34, 47) for y in range(28, 49)]
    assert np.isnan(_fit(rep, shadow, **kw)).all()


def _scan(lines, sensor, nx=40, ny=40, cut=None, extra=None):
    """Ground samples on lines y = const every 0.5 cell along x (less those ``cut(x, y)`` removes, plus
    ``extra`` points), binned, and the sensor of each bin: all seen from ``sensor`` (cells)."""
    pts = []
    for y, z in lines:
        x = np.arange(0.0, nx * PIXEL, 0.5)
        p = np.stack([x, np.full_like(x, y), np.full_like(x, z)], axis=1)
        pts.append(p[~cut(p[:, 0], p[:, 1])] if cut is not None else p)
    if extra is not None:
        pts.append(extra)
    p = np.concatenate(pts)
    s = np.broadcast_to(np.asarray(sensor, np.float64), p.shape)
    rep = bin_ground(p[:, 0].copy(), p[:, 1].copy(), p[:, 2].copy(), PIXEL, nx, ny, 1.0)
    seen_from = bin_sensor(p[:, 0].copy(), p[:, 1].copy(), p[:, 2].copy(), s[:, 0].copy(), s[:, 1].copy(),
                           s[:, 2].copy(), PIXEL, nx, ny, 1.0)
    return rep, seen_from


def test_bin_sensor_takes_the_sensor_whose_rings_lie_densest():
    # bin (0, 0): seen from 100 cells away and from 10 cells away (the nearer wins) and a point 5 cells up
    # whose sensor is nearer still (not the lowest layer: ignored); bin (1, 1): its sensor below it (none)
    x = np.array([0.5, 1.5, 1.0, 3.0])
    y = np.array([0.5, 1.0, 1.0, 3.0])
    z = np.array([1.0, 1.2, 6.5, 7.0])
    sx = np.array([100.0, 10.0, 1.0, 3.0])
    sy = np.zeros(4)
    sz = np.array([18.0, 18.0, 24.0, 5.0])
    out = bin_sensor(x, y, z, sx, sy, sz, 2.0, 3, 3, 1.0)
    assert np.allclose(out[0, 0], [10.0, 0.0, 18.0])
    assert np.isnan(out[1, 1]).all() and np.isnan(out[2, 2]).all()


def test_a_shadow_behind_a_box_stays_open_with_the_sensor_known():
    # rings every 12 cells seen from 100 cells before y = 0; a box 12 cells wide on the ground at y = 28 (its
    # side reaches the ground: its bins read the ground at its foot) hides a widening wedge behind it
    sensor = (40.0, -100.0, 22.3)

    def shadow(x, y):
        return (y > 28.0) & (np.abs(x - 40.0) < 6.0 * (y + 100.0) / 128.0)

    bx, bz = np.meshgrid(np.arange(34.0, 46.01, 0.5), np.arange(5.0, 20.01, 0.5))
    box = np.stack([bx.ravel(), np.full(bx.size, 28.0), bz.ravel()], axis=1)
    lines = [(y, 5.0) for y in np.arange(0.0, 79.0, 12.0)]
    rep, seen_from = _scan(lines, sensor, cut=shadow, extra=box)
    far = np.cos(np.radians(15))
    inside, beside = [(40.0, 54.0), (40.0, 66.0)], [(10.0, 54.0), (70.0, 66.0)]
    # without the sensor the shadow's sides surround its middle: bridged
    assert np.isfinite(_fit(rep, inside)).all()
    # with it nothing lies beyond the middle as the sensor sees it: the shadow stays open, the rings beside close
    assert np.isnan(_fit(rep, inside, sensor=seen_from, far_cos=far)).all()
    out = _fit(rep, beside, sensor=seen_from, far_cos=far)
    assert np.isfinite(out).all() and np.allclose(out[:, 0], 5.0)
    # without the box the same columns all close: the next ring lies beyond each
    rep, seen_from = _scan(lines, sensor)
    assert np.isfinite(_fit(rep, inside + beside, sensor=seen_from, far_cos=far)).all()


def test_two_tiles_decide_the_columns_they_share_alike_with_the_sensor_known():
    # rings 10 cells apart around a sensor below the tiles' edge, a box's shadow across them; two blocks 30 cells
    # apart (an even shift: the 2-cell bins align) each see their own points only; the columns both see within
    # the radius on every side are decided alike (the bridged height to rounding)
    sensor = np.array([65.0, -60.0, 22.3])
    pts = []
    for r in np.arange(70.0, 200.0, 10.0):
        a = np.arange(0.0, np.pi, 0.5 / r)
        pts.append(np.stack([sensor[0] + r * np.cos(a), sensor[1] + r * np.sin(a), np.full_like(a, 5.0)], axis=1))
    p = np.concatenate(pts)
    ang = np.degrees(np.arctan2(p[:, 1] - sensor[1], p[:, 0] - sensor[0]))
    dist = np.hypot(p[:, 0] - sensor[0], p[:, 1] - sensor[1])
    p = p[~((np.abs(ang - 90.0) < 5.0) & (dist > 95.0))]  # the shadow of a box 95 cells out
    decided = {}
    for shift in (0, 30):
        q = p[(p[:, 0] >= shift) & (p[:, 0] < shift + 100) & (p[:, 1] >= 0) & (p[:, 1] < 120)] - [shift, 0, 0]
        s = np.broadcast_to(sensor - [shift, 0, 0], q.shape)
        rep = bin_ground(q[:, 0].copy(), q[:, 1].copy(), q[:, 2].copy(), PIXEL, 50, 60, 1.0)
        seen = bin_sensor(q[:, 0].copy(), q[:, 1].copy(), q[:, 2].copy(), s[:, 0].copy(), s[:, 1].copy(),
                          s[:, 2].copy(), PIXEL, 50, 60, 1.0)
        cx, cy = np.meshgrid(np.arange(56.0, 74.0), np.arange(26.0, 94.0), indexing="ij")
        cols = np.stack([cx.ravel() - shift, cy.ravel()], axis=1)
        decided[shift] = _fit(rep, cols, sensor=seen, far_cos=np.cos(np.radians(15)))
    a, b = decided[0], decided[30]
    assert np.array_equal(np.isfinite(a[:, 0]), np.isfinite(b[:, 0]))
    ok = np.isfinite(a[:, 0])
    # the gaps between rings are bridged, the shadow's middle not
    x, y = np.meshgrid(np.arange(56.0, 74.0), np.arange(26.0, 94.0), indexing="ij")
    in_shadow = (np.abs(x - 65.0) < 3.0).ravel() & (y.ravel() > 40.0)
    assert ok.mean() > 0.25 and not ok[in_shadow].any() and ok[~in_shadow].mean() > 0.3
    np.testing.assert_allclose(a[ok], b[ok], rtol=0, atol=1e-9)


@njit(cache=True)
def _sectors(dx, dy):
    out = np.empty(dx.shape[0], np.int64)
    for n in range(dx.shape[0]):
        out[n] = sector_of(dx[n], dy[n])
    return out


def test_sector_of_gives_the_atan2_formulas_sector_everywhere_and_on_the_edges():
    rng = np.random.default_rng(7)
    # random directions at several scales, the axes and the 30 / 60 degree edges (both signs of zero), and offsets
    # a few ulps off an edge
    r = 10.0 ** rng.uniform(-6, 3, 20000)
    a = rng.uniform(-math.pi, math.pi, 20000)
    dx, dy = [r * np.cos(a)], [r * np.sin(a)]
    edges = np.radians(np.arange(-180, 181, 30, dtype=np.float64))
    for rr in (1e-3, 1.0, 7.3, 1e3):
        ex, ey = rr * np.cos(edges), rr * np.sin(edges)
        dx += [ex, np.nextafter(ex, np.inf), np.nextafter(ex, -np.inf), ex]
        dy += [ey, ey, ey, np.nextafter(ey, np.inf)]
    dx += [np.array([1.0, -1.0, 0.0, 0.0, 1.0, -1.0, 0.0, -0.0])]
    dy += [np.array([0.0, 0.0, 1.0, -1.0, -0.0, -0.0, 0.0, -1.0])]
    dx, dy = np.concatenate(dx), np.concatenate(dy)
    expected = np.array([int((math.atan2(y, x) + math.pi) / (2.0 * math.pi) * SECTORS) % SECTORS
                         for x, y in zip(dx, dy)])
    got = _sectors(dx, dy)
    assert np.array_equal(got, expected), np.flatnonzero(got != expected)[:10]
    assert set(np.unique(got)) == set(range(SECTORS))


def test_flag_bridged_cells_flags_the_cells_a_direct_search_finds():
    """The kernel against the distinct cells found with numpy: every cell with a bridged corner, flagged optimised
    where its 8 corners are parameters and bridged where they are all bridged; cells with a corner in a missing
    brick or past the lattice left alone; the count is of distinct bridged cells."""
    from tiled_gridpull.band import dense_brick_table, vertex_slots
    from tiled_gridpull.bridge import BRIDGE
    from tiled_gridpull.kernels import CELL_OPT, PARAM

    rng = np.random.default_rng(4)
    shape = np.array([20, 18, 17])  # vertices; the last bricks are partial
    bshape = tuple(int(v) for v in -(-shape // 8))
    coords = np.argwhere(np.ones(bshape, bool))
    coords = coords[rng.random(len(coords)) < 0.8].astype(np.int32)  # some bricks missing
    table = dense_brick_table(bshape, coords)
    n = len(coords) * 512
    flags = (rng.random(n) < 0.9).astype(np.uint8) * np.uint8(PARAM)
    verts = np.unique(rng.integers(0, shape, size=(600, 3)), axis=0)
    verts = verts[vertex_slots(table, verts) >= 0]
    is_bridge = np.zeros(n, np.uint8)
    is_bridge[vertex_slots(table, verts)] = 1
    # a few bridged blocks, so that some cells have all 8 corners bridged
    block = np.stack(np.meshgrid(np.arange(3, 7), np.arange(2, 6), np.arange(9, 12), indexing="ij"), -1).reshape(-1, 3)
    block = block[vertex_slots(table, block) >= 0]
    verts = np.unique(np.concatenate([verts, block]), axis=0)
    is_bridge[vertex_slots(table, verts)] = 1
    flags[vertex_slots(table, block)] |= PARAM

    corner = np.indices((2, 2, 2)).reshape(3, -1).T
    cand = np.unique((verts[:, None, :] - corner[None]).reshape(-1, 3), axis=0)
    cand = cand[np.all((cand >= 0) & (cand < shape - 1), axis=1)]
    cs = np.stack([vertex_slots(table, cand + c) for c in corner], axis=1)
    cs = cs[np.all(cs >= 0, axis=1)]
    expected = flags.copy()
    all_param = np.all((expected[cs] & PARAM) != 0, axis=1)
    all_bridge = np.all(is_bridge[cs] == 1, axis=1)
    expected[cs[all_param, 0]] |= CELL_OPT
    expected[cs[all_bridge, 0]] |= BRIDGE

    got = flags.copy()
    count = flag_bridged_cells(got, is_bridge, table, np.ascontiguousarray(verts, np.int64), shape - 1, PARAM,
                               CELL_OPT, BRIDGE)
    assert np.array_equal(got, expected)
    assert count == int(all_bridge.sum()) > 0 and all_param.sum() > 0
