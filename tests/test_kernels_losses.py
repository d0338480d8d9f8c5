"""Analytic gradients of every loss against central finite differences (float64, small random grids)."""

import numpy as np
import pytest

from tiled_gridpull.band import build_band
from tiled_gridpull.kernels import CELL_PULL, PARAM
from tiled_gridpull.kernels import interp as ki
from tiled_gridpull.kernels import losses as kl
from tiled_gridpull.kernels import step as ks
from tiled_gridpull.lattice import Lattice


@pytest.fixture(scope="module")
def small_band():
    rng = np.random.default_rng(7)
    lat = Lattice((0.0, 0.0, 0.0), 1.0, (14, 13, 12))
    pts = rng.uniform(4, 8, size=(30, 3))
    band = build_band(pts, lat, 2, 3)
    values = rng.normal(scale=2.0, size=band.n_slots)
    return band, pts, values


def _queries(pts, rng, n=25, sigma=0.4):
    centres = rng.integers(0, len(pts), n)
    q = pts[centres] + rng.normal(scale=sigma, size=(n, 3))
    s = pts[rng.integers(0, len(pts), n)]
    return q.astype(np.float64), s.astype(np.float64)


def _total_query_loss(values, band, q, s, normals, beta, gamma, lam):
    nq = len(q)
    slots = np.empty((nq, 16), np.int64)
    grads = np.empty((nq, 16), np.float64)
    losses = np.empty((nq, 4), np.float64)
    n = kl.query_losses(values, band.flags.reshape(-1), band.brick_table, np.asarray(band.lattice.shape, np.int64),
                        q, s, np.arange(nq), normals, CELL_PULL, beta, gamma, lam, slots, grads, losses)
    total = losses[:, 0].sum() + beta * losses[:, 1].sum() + gamma * losses[:, 2].sum() + lam * losses[:, 3].sum()
    return total, slots, grads, n


@pytest.mark.parametrize("gamma,lam", [(0.0, 0.0), (0.7, 0.0), (0.3, 0.9)])
def test_query_loss_gradients_match_finite_differences(small_band, gamma, lam):
    band, pts, values = small_band
    rng = np.random.default_rng(3)
    q, s = _queries(pts, rng)
    normals = rng.normal(size=(len(q), 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    beta = 0.8
    total, slots, grads, n = _total_query_loss(values, band, q, s, normals, beta, gamma, lam)
    assert n > 10
    analytic = np.zeros_like(values)
    kl.scatter_add(analytic, slots, grads, 1.0)
    touched = np.unique(slots[slots >= 0])
    h = 1e-6
    for slot in touched[:: max(1, len(touched) // 40)]:
        vp = values.copy()
        vm = values.copy()
        vp[slot] += h
        vm[slot] -= h
        lp = _total_query_loss(vp, band, q, s, normals, beta, gamma, lam)[0]
        lm = _total_query_loss(vm, band, q, s, normals, beta, gamma, lam)[0]
        fd = (lp - lm) / (2 * h)
        assert analytic[slot] == pytest.approx(fd, rel=1e-4, abs=1e-6)


def _tv_loss(values, band, form):
    """TV loss by definition (numpy), over the in-band face neighbours of every parameter."""
    lat = band.lattice
    dense = np.full(lat.shape, np.nan)
    pos = band.slot_positions()
    inside = np.all(pos < np.asarray(lat.shape), axis=1)
    param = (band.flags.reshape(-1) & PARAM) != 0
    sel = inside & param
    dense[tuple(pos[sel].T)] = values[sel]
    total = 0.0
    for v in np.argwhere(~np.isnan(dense)):
        acc = 0.0
        for axis in range(3):
            for side in (-1, 1):
                u = v.copy()
                u[axis] += side
                if np.all(u >= 0) and np.all(u < lat.shape) and not np.isnan(dense[tuple(u)]):
                    acc += (dense[tuple(u)] - dense[tuple(v)]) ** 2
        total += acc if form == ks.TV_SQUARED else np.sqrt(acc + ks._TV_EPS)
    return total / sel.sum()


@pytest.mark.parametrize("form", [ks.TV_SQUARED, ks.TV_SQRT])
@pytest.mark.slow
def test_tv_gradient_matches_finite_differences(small_band, form):
    band, _, values = small_band
    flags = band.flags.reshape(-1)
    n_params = band.n_params
    alpha = 1.3
    inv = np.zeros_like(values)
    if form == ks.TV_SQRT:
        ks.tv_inverse_norms(values, flags, band.neighbors, inv)
    scale = (alpha if form == ks.TV_SQRT else 2 * alpha) / n_params
    # with beta1 = 0 and lr = 0 the step leaves the field alone and stores the raw gradient in m
    m = np.zeros_like(values)
    v = np.zeros_like(values)
    out = values.copy()
    ks.tv_adam_step(values, out, m, v, np.zeros_like(values), flags, band.neighbors, inv, form, scale,
                    0.0, 0.0, 0.0, 1e-8, False)
    assert np.array_equal(out, values)
    param_slots = np.flatnonzero(flags & PARAM)
    rng = np.random.default_rng(0)
    h = 1e-6
    for slot in rng.choice(param_slots, 25, replace=False):
        vp = values.copy()
        vm = values.copy()
        vp[slot] += h
        vm[slot] -= h
        fd = alpha * (_tv_loss(vp, band, form) - _tv_loss(vm, band, form)) / (2 * h)
        assert m[slot] == pytest.approx(fd, rel=1e-4, abs=1e-9)
    # non-parameters never receive a gradient
    assert np.all(m[(flags & PARAM) == 0] == 0)


def test_trilinear_exact_on_linear_fields(small_band):
    band, pts, _ = small_band
    pos = band.slot_positions().astype(np.float64)
    a = np.array([0.3, -1.2, 2.0])
    values = (pos @ a + 0.7).astype(np.float32)
    rng = np.random.default_rng(1)
    p = pts + rng.uniform(-0.5, 0.5, size=pts.shape)
    f, g = ki.sample_field(values, band.brick_table, np.asarray(band.lattice.shape, np.int64),
                           p.astype(np.float32), np.float32(np.nan))
    assert np.allclose(f, p @ a + 0.7, atol=1e-4)
    assert np.allclose(g, a[None, :], atol=1e-4)


def test_trilinear_reproduces_vertex_values(small_band):
    band, pts, values = small_band
    cells = np.unique(np.floor(pts).astype(np.int64), axis=0)
    f, _ = ki.sample_field(values.astype(np.float32), band.brick_table, np.asarray(band.lattice.shape, np.int64),
                           cells.astype(np.float32), np.float32(np.nan))
    for c, val in zip(cells, f):
        slot = ki.slot_of(band.brick_table, *c)
        assert val == pytest.approx(values[slot], abs=1e-5)


def test_bounded_slot_of_refuses_vertices_beyond_the_table_and_in_missing_bricks():
    # bounded_slot_of is slot_of with the table's bounds checked (all_corners and flag_bridged_cells walk cells
    # at the lattice's far faces, whose corners may fall one brick beyond the table)
    from numba import njit

    bounded = njit(lambda t, i, j, k: ki.bounded_slot_of(t, i, j, k))
    table = np.full((2, 1, 3), -1, np.int32)
    table[1, 0, 2] = 4
    assert bounded(table, 8 + 3, 5, 16 + 7) == 4 * 512 + (3 << 6) + (5 << 3) + 7
    assert bounded(table, 3, 5, 7) == -1          # brick (0, 0, 0) not allocated
    assert bounded(table, 16, 0, 16) == -1        # x beyond the table
    assert bounded(table, 8, 8, 16) == -1         # y beyond the table
    assert bounded(table, 8, 0, 24) == -1         # z beyond the table


def _double_ops(dispatcher, *args, ops=("fmul", "fadd", "fsub", "fdiv", "sqrt")) -> dict:
    """How many of ``ops`` act on doubles in the LLVM IR of ``dispatcher`` compiled afresh for ``args`` (a cached
    dispatcher keeps no IR to inspect); serially, which types every expression alike and compiles in a fraction of
    the time."""
    import re

    from numba import njit

    fresh = njit(fastmath=dispatcher.targetoptions.get("fastmath", False))(dispatcher.py_func)
    fresh(*args)
    ir = "".join(fresh.inspect_llvm().values())
    return {op: len(re.findall(rf"\b{op}\b[^\n]*\bdouble\b", ir)) for op in ops}


def test_the_loss_and_step_kernels_compute_in_float32(small_band):
    """With float32 arrays and weights the query losses and the TV + Adam step do no float64 arithmetic: a float64
    literal promotes every expression it touches (docs/solver.md, "Float32 iteration kernels": 20 % of a query's
    cost, 18 % of a step's). The step's loss sums for the history stay float64 (additions only)."""
    band, pts, values = small_band
    rng = np.random.default_rng(5)
    q, s = _queries(pts, rng)
    f32 = np.float32
    v32 = values.astype(f32)
    flags = band.flags.reshape(-1)
    nq = len(q)
    losses = _double_ops(kl.query_losses, v32, flags, band.brick_table, np.asarray(band.lattice.shape, np.int64),
                         q.astype(f32), s.astype(f32), np.arange(nq), np.zeros((0, 3), f32), CELL_PULL, f32(0.8),
                         f32(0.7), f32(0.0), np.empty((nq, 16), np.int64), np.empty((nq, 16), f32),
                         np.empty((nq, 4), f32))
    assert losses == dict.fromkeys(losses, 0), losses
    # one compile holds both TV forms (the form is a runtime argument)
    step = _double_ops(ks.tv_adam_step, v32.copy(), v32.copy(), np.zeros_like(v32), np.zeros_like(v32),
                       np.zeros_like(v32), flags, band.neighbors, np.ones_like(v32), ks.TV_SQRT, f32(1e-3), f32(1e-3),
                       f32(0.9), f32(0.999), f32(1e-8), False, ops=("fmul", "fsub", "fdiv", "sqrt"))
    assert step == dict.fromkeys(step, 0), step
    norms = _double_ops(ks.tv_inverse_norms, v32, flags, band.neighbors, np.zeros_like(v32),
                        ops=("fmul", "fsub", "fdiv", "sqrt"))
    assert norms == dict.fromkeys(norms, 0), norms
