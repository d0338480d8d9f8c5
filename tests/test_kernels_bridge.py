"""The bridge's column kernel: which lattice columns a ground gap closes over, and at what height."""

import numpy as np

from tiled_gridpull.kernels.bridge import bin_ground, fit_columns

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
                       a["rms_tol"], a["step_tol"], a["max_slope"])


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
