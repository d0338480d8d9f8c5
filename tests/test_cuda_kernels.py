"""The CUDA kernels against the CPU kernels whose contracts they keep, on small bands.

They run under numba's CUDA simulator (conftest sets ``NUMBA_ENABLE_CUDASIM=1``; on a machine with a card,
``NUMBA_ENABLE_CUDASIM=0 pytest`` runs them on it): every Python thread of the simulator is slow, so the bands here
are a few bricks.
"""

from __future__ import annotations

import dataclasses
import numpy as np
import pytest

# the simulator runs the 64-bit hashes in NumPy scalars, which warn where the card's integers silently wrap
pytestmark = pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")

pytest.importorskip("numba.cuda", reason="numba-cuda is not installed (pip install 'tiled-gridpull[cuda]')")

from tiled_gridpull.band import build_band  # noqa: E402
from tiled_gridpull.device import cuda_card, cuda_module  # noqa: E402
from tiled_gridpull.kernels import CELL_PULL  # noqa: E402
from tiled_gridpull.kernels import interp as ki  # noqa: E402
from tiled_gridpull.kernels import losses as kl  # noqa: E402
from tiled_gridpull.kernels import sampling as ksamp  # noqa: E402
from tiled_gridpull.kernels import step as ks  # noqa: E402
from tiled_gridpull.lattice import Lattice  # noqa: E402

if cuda_card() is None:  # pragma: no cover - conftest enables the simulator
    pytest.skip("no CUDA card and no simulator", allow_module_level=True)

from numba import cuda  # noqa: E402

K = cuda_module()
SIM = cuda_card() == "CUDA simulator"


def launch(n: int) -> tuple[int, int]:
    return (1, min(n, 16)) if SIM else (-(-n // 256), 256)


@pytest.fixture(scope="module")
def setup():
    """A sphere of points in index coordinates on a 24^3 lattice, its band, and a field that is not a distance."""
    rng = np.random.default_rng(3)
    p = rng.normal(size=(400, 3))
    P = (p / np.linalg.norm(p, axis=1, keepdims=True) * 7.0 + 11.5).astype(np.float32)
    P = np.ascontiguousarray(P[np.argsort(ksamp.morton_codes(P), kind="stable")])
    lat = Lattice((0.0, 0.0, 0.0), 1.0, (24, 24, 24))
    band = build_band(P, lat, 2, 4)
    pos = band.slot_positions().astype(np.float64)
    values = (np.linalg.norm(pos - 11.5, axis=1) - 7.0 + 0.3 * rng.normal(size=len(pos))).astype(np.float32)
    normals = rng.normal(size=P.shape).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return P, band, values, normals


def _weights(lam: float) -> tuple:
    """beta, gamma, lam as the solver passes them (:attr:`~tiled_gridpull.level.LevelRun.loss_weights`): float32,
    so that both sides run the float32 arithmetic production runs (Python floats would compile float64 twins)."""
    return np.float32(1.0), np.float32(0.005), np.float32(lam)


def _cpu_queries(P, band, values, normals, nq, seed, it, sigma, lam):
    centres = np.empty(nq, np.int64)
    q = np.empty((nq, 3), np.float32)
    ksamp.draw_queries(P, seed, it, np.float32(sigma), centres, q)
    # nearest point: any index will do for the contract (the loss reads the point it is given)
    nearest = ((centres * 7) % len(P)).astype(np.int32)
    slots = np.empty((nq, 16), np.int64)
    grads = np.empty((nq, 16), np.float32)
    losses = np.empty((nq, 4), np.float32)
    shape = np.asarray(band.lattice.shape, np.int64)
    n_valid = kl.query_losses(values, band.flags.reshape(-1), band.brick_table, shape, q, P, nearest,
                              normals if lam > 0 else np.zeros((0, 3), np.float32), CELL_PULL, *_weights(lam),
                              slots, grads, losses)
    qgrad = np.zeros(band.n_slots, np.float32)
    kl.scatter_add(qgrad, slots, grads, np.float32(1.0 / n_valid))
    return nearest, n_valid, qgrad, losses.sum(axis=0)


def _gpu_queries(P, band, values, normals, nearest, seed, it, sigma, lam, grid):
    nq = len(nearest)
    acc = cuda.to_device(np.zeros(band.n_slots, np.int64))
    counts = cuda.to_device(np.zeros(1, np.int32))
    sums = cuda.to_device(np.zeros((1, 4), K.SUMS_DTYPE))
    nx, ny, nz = band.lattice.shape
    K.query_scatter[grid](cuda.to_device(values), cuda.to_device(band.flags.reshape(-1)),
                          cuda.to_device(band.brick_table), nx, ny, nz, cuda.to_device(P),
                          cuda.to_device(normals), lam > 0, cuda.to_device(nearest), ksamp.iteration_key(seed, it),
                          len(P) / nq, np.float32(sigma), cuda.to_device(ksamp.NORMALS), CELL_PULL, *_weights(lam),
                          acc, counts, 0, sums, True)
    return acc.copy_to_host(), int(counts.copy_to_host()[0]), sums.copy_to_host()[0] / K.SUMS_SCALE


@pytest.mark.parametrize("lam", [0.0, 0.5])
def test_queries_scatter_the_cpu_gradient(setup, lam):
    P, band, values, normals = setup
    nq = 300
    nearest, n_valid, qgrad, loss_sum = _cpu_queries(P, band, values, normals, nq, 5, 2, 2.5, lam)
    assert 0 < n_valid < nq  # some queries fall outside the pull band: the valid count is part of the contract
    acc, count, sums = _gpu_queries(P, band, values, normals, nearest, 5, 2, 2.5, lam, launch(nq))
    assert count == n_valid
    got = acc.astype(np.float64) / K.FIXED_SCALE / count
    scale = np.abs(qgrad).max()
    assert scale > 0
    np.testing.assert_allclose(got, qgrad, rtol=0, atol=2e-5 * scale)
    assert np.count_nonzero(got) == np.count_nonzero(qgrad)
    np.testing.assert_allclose(sums, loss_sum, rtol=1e-4)


def test_query_sums_do_not_depend_on_the_launch(setup):
    """Fixed-point accumulation: any order of the atomics gives the same integers, bit for bit."""
    P, band, values, normals = setup
    nearest = (np.arange(300) * 13 % len(P)).astype(np.int32)
    a, _, _ = _gpu_queries(P, band, values, normals, nearest, 1, 0, 0.8, 0.0, (1, 1))
    b, _, _ = _gpu_queries(P, band, values, normals, nearest, 1, 0, 0.8, 0.0, launch(300))
    assert np.any(a != 0)
    assert np.array_equal(a, b)


def _step_inputs(band, values, seed=0):
    rng = np.random.default_rng(seed)
    n = band.n_slots
    m = (0.01 * rng.normal(size=n)).astype(np.float32)
    v = (1e-4 * rng.random(n)).astype(np.float32)
    qgrad = (1e-3 * rng.normal(size=n)).astype(np.float32)
    qgrad[(band.flags.reshape(-1) & 1) == 0] = 0.0
    return m, v, qgrad


@pytest.mark.parametrize("form,clamp", [(ks.TV_SQUARED, False), (ks.TV_SQRT, False), (ks.TV_SQUARED, True)])
def test_tv_adam_matches_the_cpu_step(setup, form, clamp):
    P, band, values, _ = setup
    n = band.n_slots
    flags = band.flags.reshape(-1)
    m, v, qgrad = _step_inputs(band, values)
    # the query gradient as the card holds it: fixed point over a valid count of 37
    acc = np.floor(qgrad.astype(np.float64) * 37 * K.FIXED_SCALE + 0.5).astype(np.int64)
    qgrad_fixed = (acc.astype(np.float32) * np.float32(1.0 / K.FIXED_SCALE / 37)).astype(np.float32)
    d0 = values.copy()
    inv = np.zeros(n, np.float32)
    tv_cpu = 0.0
    if form == ks.TV_SQRT:
        tv_cpu = ks.tv_inverse_norms(d0, flags, band.neighbors, inv)
    cm, cv, cq = m.copy(), v.copy(), qgrad_fixed.copy()
    d_cpu = np.empty_like(d0)
    sq_cpu = ks.tv_adam_step(d0, d_cpu, cm, cv, cq, flags, band.neighbors, inv, form, np.float32(0.01),
                             np.float32(0.05), np.float32(0.9), np.float32(0.999), np.float32(1e-8), clamp)
    dev = {name: cuda.to_device(a) for name, a in
           (("d", d0), ("m", m), ("v", v), ("acc", acc), ("flags", flags), ("nb", band.neighbors))}
    inv_g = cuda.to_device(np.zeros(n, np.float32))
    sums = cuda.to_device(np.zeros(1, K.SUMS_DTYPE))
    out = cuda.device_array(n, np.float32)
    grid = launch(n)
    if form == ks.TV_SQRT:
        K.tv_norms[grid](dev["d"], dev["flags"], dev["nb"], inv_g, sums, 0, True)
        np.testing.assert_allclose(inv_g.copy_to_host(), inv, rtol=1e-5, atol=1e-6)
        assert sums.copy_to_host()[0] / K.SUMS_SCALE == pytest.approx(tv_cpu, rel=1e-5)
        sums = cuda.to_device(np.zeros(1, K.SUMS_DTYPE))
    K.tv_adam[grid](dev["d"], out, dev["m"], dev["v"], dev["acc"], cuda.to_device(np.array([37], np.int32)), 0,
                    dev["flags"], dev["nb"], inv_g, 1 if form == ks.TV_SQRT else 0, np.float32(0.01),
                    np.float32(0.05), np.float32(0.9), np.float32(0.999), np.float32(1e-8), clamp, sums, True)
    par = (flags & 1) != 0
    np.testing.assert_allclose(out.copy_to_host(), d_cpu, rtol=0, atol=1e-5)
    np.testing.assert_allclose(dev["m"].copy_to_host()[par], cm[par], rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(dev["v"].copy_to_host()[par], cv[par], rtol=1e-4, atol=1e-10)
    assert not np.any(dev["acc"].copy_to_host())  # the accumulator is reset for the next iteration
    if form == ks.TV_SQUARED:
        assert sums.copy_to_host()[0] / K.SUMS_SCALE == pytest.approx(sq_cpu, rel=1e-4)
    if clamp:
        assert out.copy_to_host().min() >= 0.0
    # non-parameters keep their values
    assert np.array_equal(out.copy_to_host()[~par], d0[~par])


def test_upsample_matches_the_cpu():
    from tiled_gridpull.field import Field
    from tiled_gridpull.solver import upsample

    rng = np.random.default_rng(1)
    p = rng.normal(size=(200, 3))
    P = (p / np.linalg.norm(p, axis=1, keepdims=True) * 2.0 + 4.0).astype(np.float32)
    band = build_band(P, Lattice((0.0, 0.0, 0.0), 1.0, (24, 24, 24)), 1, 2)
    pos = band.slot_positions().astype(np.float64)
    values = (np.linalg.norm(pos - 4.0, axis=1) - 2.0).astype(np.float32)
    # a coarse brick the finer band reaches is taken out of the table: its fine slots must get the fill
    table = band.brick_table.copy()
    table[1, 0, 0] = -1  # the fine slots at x >= 14 (coarse x >= 7) have a corner in it
    holed = dataclasses.replace(band, brick_table=table)
    coarse = Field(holed, values.reshape(band.n_bricks, 512), signed=True)
    fine = build_band(P * 2, Lattice((0.0, 0.0, 0.0), 0.5, (47, 47, 47)), 1, 2)
    cpu = upsample(coarse, fine)
    out = cuda.device_array(fine.n_slots, np.float32)
    nx, ny, nz = band.lattice.shape
    K.upsample[launch(fine.n_slots)](cuda.to_device(values), cuda.to_device(table), nx, ny, nz,
                                     cuda.to_device(fine.brick_coords.astype(np.int32)), 2, 1e3, out)
    got = out.copy_to_host().reshape(fine.n_bricks, 512)
    assert np.any(cpu == np.float32(1e3)) and np.any(cpu != np.float32(1e3))
    np.testing.assert_allclose(got, cpu, rtol=1e-6, atol=1e-5)


def test_device_functions_are_the_cpu_helpers_recompiled():
    """One source for both targets: the CUDA helper runs the CPU helper's code."""
    assert K._ENV["query_one"].py_func.__code__ is kl.query_one.py_func.__code__
    assert K._ENV["locate"].py_func.__code__ is ki.locate.py_func.__code__
    assert K._ENV["draw_one"].py_func.__code__ is ksamp.draw_one.py_func.__code__


def test_the_draw_hashes_the_key_as_uint64_whatever_type_it_arrives_in(setup):
    """A kernel's Python-int argument is typed int64 on a card when it is below 2^63 (uint64 above): the device
    draw must still hash it as a uint64, or the card draws other queries than the ones the host found the nearest
    points of. numba's typing (the same for both targets; the simulator runs NumPy's instead) checked with njit."""
    from numba import njit

    P = setup[0]
    draw = njit(ksamp.draw_one.py_func)
    nq, sigma = 40, np.float32(0.8)
    seen = set()
    for it in range(8):
        key = ksamp.iteration_key(3, it)
        centres = np.empty(nq, np.int64)
        q = np.empty((nq, 3), np.float32)
        ksamp.draw_queries(P, 3, it, sigma, centres, q)
        typed = np.int64(key) if key < 2 ** 63 else np.uint64(key)
        seen.add(type(typed))
        for i in range(nq):
            c, x, y, z = draw(P, typed, i, len(P) / nq, sigma, ksamp.NORMALS)
            assert c == centres[i] and (x, y, z) == tuple(q[i])
    assert seen == {np.int64, np.uint64}


def test_the_udf_clamp_projects_every_slot_as_on_the_cpu(setup):
    """UDF mode projects the whole field onto d >= 0 (:func:`.step.tv_adam_step`), non-parameters included: a start
    that is negative outside the parameters (``solve(init=...)`` in udf mode) is clamped alike on both devices."""
    P, band, values, _ = setup
    n = band.n_slots
    flags = band.flags.reshape(-1)
    par = (flags & 1) != 0
    d0 = -values  # negative beyond the band's outer side
    assert np.any(d0[~par] < 0)
    m, v, qgrad = _step_inputs(band, d0)
    acc = np.floor(qgrad.astype(np.float64) * 37 * K.FIXED_SCALE + 0.5).astype(np.int64)
    qgrad_fixed = (acc.astype(np.float32) * np.float32(1.0 / K.FIXED_SCALE / 37)).astype(np.float32)
    d_cpu = np.empty_like(d0)
    ks.tv_adam_step(d0, d_cpu, m.copy(), v.copy(), qgrad_fixed, flags, band.neighbors, np.zeros(1, np.float32),
                    ks.TV_SQUARED, np.float32(0.01), np.float32(0.05), np.float32(0.9), np.float32(0.999),
                    np.float32(1e-8), True)
    out = cuda.device_array(n, np.float32)
    K.tv_adam[launch(n)](cuda.to_device(d0), out, cuda.to_device(m), cuda.to_device(v), cuda.to_device(acc),
                         cuda.to_device(np.array([37], np.int32)), 0, cuda.to_device(flags),
                         cuda.to_device(band.neighbors), cuda.to_device(np.zeros(1, np.float32)), 0,
                         np.float32(0.01), np.float32(0.05), np.float32(0.9), np.float32(0.999), np.float32(1e-8),
                         True, cuda.to_device(np.zeros(1, K.SUMS_DTYPE)), False)
    got = out.copy_to_host()
    assert d_cpu.min() >= 0.0
    np.testing.assert_array_equal(got[~par], d_cpu[~par])
    np.testing.assert_allclose(got, d_cpu, rtol=0, atol=1e-5)


def test_the_fixed_point_sums_cannot_wrap(setup):
    """Each slot's int64 accumulator holds the sum of its clipped fixed-point contributions, however many and however
    large: a launch of nq queries clips each to 9e18 / (2 nq + 1) units, so no sum passes the int64 range. With only
    the 1e9 clip, 137 queries of 1e9 at one slot wrapped the sum round to the other sign. (The field is absurd, flat
    at 1e5 cells, so |grad f| = 1e-6 in the pull's 1/|grad f|: degenerate gradients are all that reach the clip.)"""
    _, band, _, _ = setup
    # every query around point A, all pulled towards point B three cells away: 400 same-signed gradients at the
    # corners of one cell
    a = np.array([11.5, 11.5, 4.6], np.float32)
    P = np.vstack([np.repeat(a[None], 50, axis=0), a + np.float32([3.0, 0.0, 0.0])]).astype(np.float32)
    flat = np.full(band.n_slots, 1e5, np.float32)
    nq, sigma = 400, np.float32(0.05)
    centres = np.empty(nq, np.int64)
    q = np.empty((nq, 3), np.float32)
    ksamp.draw_queries(P, 2, 0, sigma, centres, q)
    nearest = np.full(nq, 50, np.int32)
    slots = np.empty((nq, 16), np.int64)
    grads = np.empty((nq, 16), np.float32)
    losses = np.empty((nq, 4), np.float32)
    n_valid = kl.query_losses(flat, band.flags.reshape(-1), band.brick_table, np.asarray(band.lattice.shape, np.int64),
                              q, P, nearest, np.zeros((0, 3), np.float32), CELL_PULL, *_weights(0.0), slots, grads,
                              losses)
    assert n_valid == nq
    old = np.clip(grads.astype(np.float64) * K.FIXED_SCALE, -K._FIXED_CLIP * K.FIXED_SCALE,
                  K._FIXED_CLIP * K.FIXED_SCALE)
    sums = np.zeros(band.n_slots)
    np.add.at(sums, slots.reshape(-1), old.reshape(-1))
    assert np.abs(sums).max() > 2.0 ** 63  # what the 1e9 clip alone let through
    clip = min(K._FIXED_CLIP * K.FIXED_SCALE, getattr(K, "_FIXED_ROOM", np.inf) / (2.0 * nq + 1.0))
    want = np.zeros(band.n_slots)
    np.add.at(want, slots.reshape(-1), np.clip(grads.astype(np.float64) * K.FIXED_SCALE, -clip, clip).reshape(-1))
    acc, count, _ = _gpu_queries(P, band, flat, np.zeros((51, 3), np.float32), nearest, 2, 0, sigma, 0.0,
                                 launch(nq))
    assert count == nq
    touched = want != 0
    np.testing.assert_array_equal(np.sign(acc[touched]), np.sign(want[touched]))
    np.testing.assert_allclose(acc.astype(np.float64), want, rtol=1e-4)


def test_the_history_sums_do_not_depend_on_the_launch(setup):
    """The loss and TV sums of the history iterations repeat bit for bit whatever order the atomics land in, as the
    field does (float64 atomics did not: a run's history, in its sidecar, changed in the last bits from one run or
    launch shape to the next)."""
    P, band, values, normals = setup
    dtype = getattr(K, "SUMS_DTYPE", np.float64)
    nearest = (np.arange(300) * 13 % len(P)).astype(np.int32)
    n = band.n_slots
    d, flags, nb = cuda.to_device(values), cuda.to_device(band.flags.reshape(-1)), cuda.to_device(band.neighbors)
    got = []
    for grid in ((1, 1), launch(300), (1, 7)):
        nx, ny, nz = band.lattice.shape
        sums = cuda.to_device(np.zeros((1, 4), dtype))
        key = np.uint64(ksamp.iteration_key(1, 0))
        K.query_scatter[grid](d, flags, cuda.to_device(band.brick_table), nx, ny, nz, cuda.to_device(P),
                              cuda.to_device(normals), True, cuda.to_device(nearest), key, len(P) / 300,
                              np.float32(0.8), cuda.to_device(ksamp.NORMALS), CELL_PULL, *_weights(0.5),
                              cuda.to_device(np.zeros(n, np.int64)), cuda.to_device(np.zeros(1, np.int32)), 0, sums,
                              True)
        tv = cuda.to_device(np.zeros(1, dtype))
        K.tv_norms[grid](d, flags, nb, cuda.to_device(np.zeros(n, np.float32)), tv, 0, True)
        sq = cuda.to_device(np.zeros(1, dtype))
        K.tv_adam[grid](d, cuda.device_array(n, np.float32), cuda.to_device(np.zeros(n, np.float32)),
                        cuda.to_device(np.zeros(n, np.float32)), cuda.to_device(np.zeros(n, np.int64)),
                        cuda.to_device(np.array([1], np.int32)), 0, flags, nb, cuda.to_device(np.zeros(1, np.float32)),
                        0, np.float32(0.01), np.float32(0.05), np.float32(0.9), np.float32(0.999), np.float32(1e-8),
                        False, sq, True)
        got.append((sums.copy_to_host().tobytes(), tv.copy_to_host().tobytes(), sq.copy_to_host().tobytes()))
    assert got[0] == got[1] == got[2]


def test_nearest_pool_on_the_card_is_the_hosts_pool(setup):
    """The card draws each batch's queries itself and finds their nearest points in the hashed grid: the same rows
    as the host's pool (draw_queries + PointGrid) and as pykdtree."""
    from pykdtree.kdtree import KDTree

    from tiled_gridpull.nearest import PointGrid

    P = setup[0]
    pool, nq, seed, it0, sigma = 3, 150, 7, 40, np.float32(0.8)
    grid = PointGrid.for_queries(P, float(sigma))
    out = cuda.device_array((pool, nq), np.int32)
    order, keys, starts, counts, bits = grid.arrays
    K.nearest_pool[launch(pool * nq)](cuda.to_device(P), cuda.to_device(order), cuda.to_device(keys),
                                      cuda.to_device(starts), cuda.to_device(counts), bits, *map(float, grid.origin),
                                      grid.cell, *map(int, grid.dims), seed, it0, len(P) / nq, sigma,
                                      cuda.to_device(ksamp.NORMALS), out)
    card = out.copy_to_host()
    tree = KDTree(P)
    for b in range(pool):
        centres = np.empty(nq, np.int64)
        q = np.empty((nq, 3), np.float32)
        ksamp.draw_queries(P, seed, it0 + b, sigma, centres, q)
        host, _ = grid.query(P, q, centres)
        assert np.array_equal(card[b], host)
        assert np.mean(card[b] == tree.query(q, k=1)[1]) > 0.99
    assert len(np.unique(card)) > nq  # the batches are different queries
