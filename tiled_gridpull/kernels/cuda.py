"""CUDA twins of the solver's kernels (numba-cuda): one iteration of one level, on the card.

The contracts are the CPU kernels' (:mod:`.sampling`, :mod:`.losses`, :mod:`.step`, :func:`.interp.sample_field`);
what differs is how the work is cut and summed:

* **Queries** (:func:`query_scatter`): one thread per query draws it (:func:`.sampling.draw_one`, the same counter-based
  hash), evaluates its losses (:func:`.losses.query_one`, the same source compiled for the card) and adds its 16
  corner gradients into an ``int64`` accumulator in fixed point (``FIXED_SCALE`` units). Integer addition is
  associative, so the sum at each vertex, and the field, do not depend on the order the atomics land in: a run is
  bitwise reproducible on one card. The CPU sums in float32 in query order; the two agree to float32 rounding.
* **TV and Adam** (:func:`tv_norms`, :func:`tv_adam`): one thread per slot gathers its six in-band neighbours
  (the CPU kernel scatters along edges brick by brick; the same sums, in another order).
* **Nearest points** (:func:`nearest_pool`): one thread per query of the level's pool draws it and finds its exact
  nearest input point in the hashed point grid (:func:`.nn.grid_nearest_one`, the CPU twin's source).
* **Upsampling** (:func:`upsample`): one thread per fine slot samples the coarse field still on the card.

The device functions are not written twice: :func:`device_function` recompiles the CPU kernels' inline helpers
(their Python source) for the CUDA target, with their calls to other helpers pointed at the CUDA versions.

Every kernel loops over its items with a grid stride, so a launch of any size covers them (the simulator,
``NUMBA_ENABLE_CUDASIM=1``, runs a handful of threads; a card one thread per item). Import this module only through
:func:`tiled_gridpull.device.cuda_module`, which makes numba-cuda importable first.
"""

from __future__ import annotations

import math
import types

import numpy as np

if not hasattr(np, "row_stack"):  # numba-cuda 0.30 overloads np.row_stack, which NumPy 2.4+ dropped
    np.row_stack = np.vstack  # noqa: NPY201
from numba import cuda  # noqa: E402

from . import interp as _interp  # noqa: E402
from . import losses as _losses  # noqa: E402
from . import nn as _nn  # noqa: E402
from . import sampling as _sampling  # noqa: E402

#: Fixed-point unit of the query-gradient accumulator: 2^-26 (1.5e-8; a query's corner gradient is O(1), so
#: this keeps float32's ~1e-7 relative precision, and an int64 holds sums up to 1.4e11 before it would wrap).
FIXED_SCALE = float(1 << 26)
_INV_FIXED = 1.0 / FIXED_SCALE
#: Largest single contribution converted (|g| beyond it is clipped: it could only come from a degenerate gradient)
_FIXED_CLIP = 1e9
#: Below 2^63 - 1 with room for rounding: a launch of ``nq`` queries clips each contribution to
#: ``_FIXED_ROOM / (2 nq + 1)`` fixed units (a query adds to a slot at most twice, once as a corner of q and once
#: of its point), so no slot's sum can wrap round to the other sign (:func:`_clip_for`)
_FIXED_ROOM = 9.0e18
#: The history's loss and TV sums (:func:`query_scatter`, :func:`tv_norms`, :func:`tv_adam`, :func:`solve_level`)
#: are int64 in units of 2^-20 too, so they repeat bit for bit like the field (float64 atomics land in any order):
#: 1e-6 per term, each clipped at 1e6 (9e6 such terms before the sum wraps; a term that is NaN counts as the clip,
#: so the history shows it). The host divides by ``SUMS_SCALE``.
SUMS_DTYPE = np.int64
SUMS_SCALE = float(1 << 20)
_SUMS_CLIP = 1e6 * SUMS_SCALE
_TV_EPS = np.float32(1e-8)  # float32: the norms run in float32 (a float64 constant would promote them)
_PARAM = np.uint8(1)


def device_function(dispatcher, env: dict):
    """Compile the Python source of a CPU ``@njit`` helper as an inline CUDA device function.

    ``env`` maps the names of the helpers it calls to their CUDA versions (built in dependency order)."""
    f = dispatcher.py_func
    g = dict(f.__globals__)
    g.update(env)
    retargeted = types.FunctionType(f.__code__, g, f.__name__, f.__defaults__, f.__closure__)
    return cuda.jit(device=True, inline=True)(retargeted)


_ENV: dict = {}
for _mod, _names in ((_interp, ("slot_of", "locate", "corner_slots", "eval_corners", "corner_gradients")),
                     (_sampling, ("mix64", "uniforms", "iteration_key", "draw_one")),
                     (_losses, ("query_one",)),
                     (_nn, ("cell_slot", "_gap", "grid_nearest_one"))):
    for _name in _names:
        _ENV[_name] = device_function(getattr(_mod, _name), _ENV)

_locate = _ENV["locate"]
_corner_slots = _ENV["corner_slots"]
_eval_corners = _ENV["eval_corners"]
_draw_one = _ENV["draw_one"]
_iteration_key = _ENV["iteration_key"]
_query_one = _ENV["query_one"]
_grid_nearest_one = _ENV["grid_nearest_one"]


@cuda.jit(device=True, inline=True)
def _sum_fixed(x):
    """A history term in ``SUMS_SCALE`` units."""
    y = np.float64(x) * SUMS_SCALE
    if not (y < _SUMS_CLIP):  # NaN lands here too
        y = _SUMS_CLIP
    elif y < -_SUMS_CLIP:
        y = -_SUMS_CLIP
    return np.int64(math.floor(y + 0.5))


@cuda.jit(device=True, inline=True)
def _clip_for(nq):
    """Largest contribution (fixed units) a launch of ``nq`` queries converts: ``_FIXED_CLIP``, or less where
    ``2 nq`` contributions of it could pass the int64 range: from 68 queries a launch on, ``1.3e11 / (2 nq + 1)`` in
    gradient units (1.3e6 at 50k queries, 6.7e4 at 1M). A corner gradient is O(1) where ``|grad f|`` is about 1;
    only a nearly flat field (the pull's ``f / |grad f|``, ``|grad f|`` below 1e-4) reaches these."""
    return min(_FIXED_CLIP * FIXED_SCALE, _FIXED_ROOM / (2.0 * nq + 1.0))


@cuda.jit(device=True, inline=True)
def _to_fixed(g, clip):
    x = g * FIXED_SCALE
    if not (x > -clip):  # NaN lands here too
        x = -clip if x == x else 0.0
    elif x > clip:
        x = clip
    return np.int64(math.floor(x + 0.5))


@cuda.jit(cache=True)
def query_scatter(values, flags, table, nx, ny, nz, points, normals, use_normals, nearest, key, step, sigma,
                  normal_table, pull_bit, beta, gamma, lam, acc, counts, t, loss_sums, want_losses):
    """Draw, evaluate and scatter one iteration's queries.

    Parameters
    ----------
    values : (n_slots,) float32
        Field in cells.
    flags : (n_slots,) uint8
    table : (BX, BY, BZ) int32
        Brick table.
    nx, ny, nz : int
        Lattice vertex counts.
    points : (N, 3) float32
        Input points (index coordinates, Morton order: the stratified centres).
    normals : (N, 3) float32 or (0, 3)
    use_normals : bool
    nearest : (Nq,) int32
        Nearest point of each query (this iteration's pool batch).
    key : uint64
        :func:`.sampling.iteration_key` of the batch (pass ``np.uint64``: a Python int below 2^63 is typed int64, a
        second compilation; :func:`.sampling.draw_one` hashes it as a uint64 either way).
    step, sigma : float
        ``N / Nq`` and the query spread (cells).
    normal_table : (65536,) float32
        :data:`.sampling.NORMALS`.
    pull_bit : int
    beta, gamma, lam : float
    acc : (n_slots,) int64, in/out
        Query gradients in fixed point (``FIXED_SCALE`` units), not yet divided by the valid count.
    counts : (iterations,) int32, in/out
        ``counts[t]`` += queries that count.
    t : int
        This iteration's row of ``counts`` and ``loss_sums``.
    loss_sums : (iterations, 4) int64, in/out
        Summed losses (monitoring) in ``SUMS_SCALE`` units, written when ``want_losses``.
    """
    start, stride = cuda.grid(1), cuda.gridsize(1)
    slots = cuda.local.array(16, np.int64)
    grads = cuda.local.array(16, np.float32)
    losses = cuda.local.array(4, np.float32)
    clip = _clip_for(nearest.shape[0])
    for n in range(start, nearest.shape[0], stride):
        _query_item(n, values, flags, table, nx, ny, nz, points, normals, use_normals, nearest[n], key, step, sigma,
                    normal_table, pull_bit, beta, gamma, lam, acc, counts, t, loss_sums, want_losses, slots, grads,
                    losses, clip)


@cuda.jit(device=True, inline=True)
def _query_item(n, values, flags, table, nx, ny, nz, points, normals, use_normals, p, key, step, sigma, normal_table,
                pull_bit, beta, gamma, lam, acc, counts, t, loss_sums, want_losses, slots, grads, losses, clip):
    """Query ``n`` of iteration ``t`` (nearest point ``p``): draw, evaluate, scatter (see :func:`query_scatter`);
    ``clip`` from :func:`_clip_for`."""
    _, qx, qy, qz = _draw_one(points, key, n, step, sigma, normal_table)
    if _query_one(values, flags, table, nx, ny, nz, qx, qy, qz, points, p, normals, use_normals, pull_bit, beta,
                  gamma, lam, slots, grads, losses):
        cuda.atomic.add(counts, t, 1)
        for c in range(16):
            cuda.atomic.add(acc, slots[c], _to_fixed(grads[c], clip))
        if want_losses:
            for c in range(4):
                cuda.atomic.add(loss_sums, (t, c), _sum_fixed(losses[c]))


@cuda.jit(device=True, inline=True)
def _neighbour(s, side, neighbors):
    """Slot of the face neighbour of slot ``s`` on ``side`` (-x, +x, -y, +y, -z, +z), -1 where none."""
    b = s >> 9
    i = s & 511
    axis = side >> 1
    shift = 6 if axis == 0 else (3 if axis == 1 else 0)
    c = (i >> shift) & 7
    if side & 1:
        if c < 7:
            return s + (1 << shift)
        nb = neighbors[b, side]
        return -1 if nb < 0 else nb * 512 + i - (7 << shift)
    if c > 0:
        return s - (1 << shift)
    nb = neighbors[b, side]
    return -1 if nb < 0 else nb * 512 + i + (7 << shift)


@cuda.jit(device=True, inline=True)
def _edge_sum(s, d, flags, neighbors, w, mode):
    """Sum over the in-band face neighbours ``u`` of parameter ``s``: ``(d_s - d_u)^2`` (mode 2),
    ``(d_s - d_u)(w_s + w_u)`` (mode 1) or ``2 (d_s - d_u)`` (mode 0)."""
    ds = d[s]
    total = np.float32(0.0)
    for side in range(6):
        u = _neighbour(s, side, neighbors)
        if u >= 0 and (flags[u] & _PARAM) != 0:
            e = ds - d[u]
            if mode == 2:
                total += e * e
            elif mode == 1:
                total += e * (w[s] + w[u])
            else:
                total += np.float32(2.0) * e
    return total


@cuda.jit(cache=True)
def tv_norms(d, flags, neighbors, inv, sums, t, want_sum):
    """Sqrt form: ``inv[s] = 1 / sqrt(eps + sum_u (d_u - d_s)^2)`` at every parameter, 0 elsewhere
    (:func:`.step.tv_inverse_norms`); ``sums[t]`` (int64) += the TV loss sum in ``SUMS_SCALE`` units when
    ``want_sum``."""
    start, stride = cuda.grid(1), cuda.gridsize(1)
    for s in range(start, d.shape[0], stride):
        _norm_item(s, d, flags, neighbors, inv, sums, t, want_sum)


@cuda.jit(device=True, inline=True)
def _norm_item(s, d, flags, neighbors, inv, sums, t, want_sum):
    if (flags[s] & _PARAM) == 0:
        inv[s] = 0.0
        return
    r = math.sqrt(_edge_sum(s, d, flags, neighbors, inv, 2) + _TV_EPS)
    inv[s] = np.float32(1.0) / r
    if want_sum:
        cuda.atomic.add(sums, t, _sum_fixed(r))


@cuda.jit(cache=True)
def tv_adam(d_in, d_out, m, v, acc, counts, t, flags, neighbors, inv, form, tv_scale, lr_t, beta1, beta2, eps,
            clamp_nonneg, sums, want_sum):
    """Fused TV gradient + Adam update of every parameter (:func:`.step.tv_adam_step`).

    The query gradient of slot ``s`` is ``acc[s] / FIXED_SCALE / counts[t]``; ``acc`` is reset to 0 here.
    ``form``: 0 squared TV (``sums[t]`` += its loss sum when ``want_sum``), 1 sqrt TV (``inv`` from
    :func:`tv_norms`).
    """
    start, stride = cuda.grid(1), cuda.gridsize(1)
    n_valid = counts[t]
    scale = np.float32(_INV_FIXED / n_valid) if n_valid > 0 else np.float32(0.0)
    for s in range(start, d_in.shape[0], stride):
        _adam_item(s, d_in, d_out, m, v, acc, scale, flags, neighbors, inv, form, tv_scale, lr_t, beta1, beta2,
                   eps, clamp_nonneg, sums, t, want_sum)


@cuda.jit(device=True, inline=True)
def _adam_item(s, d_in, d_out, m, v, acc, scale, flags, neighbors, inv, form, tv_scale, lr_t, beta1, beta2, eps,
               clamp_nonneg, sums, t, want_sum):
    d = d_in[s]
    a = acc[s]
    if (flags[s] & _PARAM) == 0:
        # the CPU step projects every slot in UDF mode, non-parameters included (they are read by the queries'
        # corners, the signing and the mesh)
        d_out[s] = max(d, np.float32(0.0)) if clamp_nonneg else d
        if a != 0:
            acc[s] = 0
        return
    qg = np.float32(0.0)
    if a != 0:  # most slots of a large band see no query: reading the zero is the only traffic they cost
        qg = np.float32(a) * scale
        acc[s] = 0
    lap = _edge_sum(s, d_in, flags, neighbors, inv, 1 if form == 1 else 0)
    if want_sum and form == 0:
        cuda.atomic.add(sums, t, _sum_fixed(lap * d))
    g = qg + tv_scale * lap
    # float32 throughout, as on the CPU (:func:`.step.tv_adam_step`)
    mm = beta1 * m[s] + (np.float32(1.0) - beta1) * g
    vv = beta2 * v[s] + (np.float32(1.0) - beta2) * g * g
    m[s] = mm
    v[s] = vv
    nd = d - lr_t * mm / (math.sqrt(vv) + eps)
    if clamp_nonneg:
        nd = max(nd, np.float32(0.0))
    d_out[s] = nd


@cuda.jit(cache=True)
def solve_level(d_a, d_b, m, v, acc, inv, flags, table, neighbors, nx, ny, nz, points, normals, use_normals, pool,
                seed, it0, step, sigma, normal_table, pull_bit, beta, gamma, lam, lr_ts, form, tv_scale, beta1, beta2,
                eps, clamp_nonneg, counts, loss_sums, tv_sums, record_every):
    """A whole level's iterations in one cooperative launch: queries, grid sync, TV norms, grid sync, TV + Adam,
    grid sync, and again, so the host launches once per level instead of three times per iteration.

    Iteration ``t`` reads the field from ``d_a`` when ``t`` is even and from ``d_b`` when odd and writes the other
    (the result is in ``d_a`` after an even number of iterations); it uses pool batch ``t % len(pool)``, whose
    queries are drawn from :func:`.sampling.iteration_key` ``(seed, it0 + batch)``, and the bias-corrected learning
    rate ``lr_ts[t]``. Iterations ``t`` with ``t % record_every == 0`` and the last one sum their losses into
    ``loss_sums[t]`` and ``tv_sums[t]`` (``record_every`` 0: none). Same arithmetic as :func:`query_scatter`,
    :func:`tv_norms` and :func:`tv_adam`.
    """
    grid = cuda.cg.this_grid()
    start, stride = cuda.grid(1), cuda.gridsize(1)
    slots = cuda.local.array(16, np.int64)
    grads = cuda.local.array(16, np.float32)
    losses = cuda.local.array(4, np.float32)
    iters = lr_ts.shape[0]
    n_batches = pool.shape[0]
    nq = pool.shape[1]
    n = d_a.shape[0]
    clip = _clip_for(nq)
    for t in range(iters):
        src = d_a if t % 2 == 0 else d_b
        dst = d_b if t % 2 == 0 else d_a
        want = record_every > 0 and (t % record_every == 0 or t == iters - 1)
        batch = t % n_batches
        key = _iteration_key(seed, it0 + batch)
        for q in range(start, nq, stride):
            _query_item(q, src, flags, table, nx, ny, nz, points, normals, use_normals, pool[batch, q], key, step,
                        sigma, normal_table, pull_bit, beta, gamma, lam, acc, counts, t, loss_sums, want, slots,
                        grads, losses, clip)
        grid.sync()
        if form == 1:
            for s in range(start, n, stride):
                _norm_item(s, src, flags, neighbors, inv, tv_sums, t, want)
            grid.sync()
        n_valid = counts[t]
        scale = np.float32(_INV_FIXED / n_valid) if n_valid > 0 else np.float32(0.0)
        for s in range(start, n, stride):
            _adam_item(s, src, dst, m, v, acc, scale, flags, neighbors, inv, form, tv_scale, lr_ts[t], beta1, beta2,
                       eps, clamp_nonneg, tv_sums, t, want)
        grid.sync()


@cuda.jit(cache=True)
def query_scatter_batch(values, flags, tables, dims, points, p_start, normals, n_start, use_normals, nearest, q_tile,
                        q_start, key, steps, sigma, normal_table, pull_bit, beta, gamma, lam, acc, counts, t, loss_sums,
                        want_losses):
    """:func:`query_scatter` for a batch of tiles whose bands are concatenated: each query is its own tile's, drawn,
    evaluated and scattered exactly as that tile's launch alone would (its points, brick table, lattice and count).

    Parameters
    ----------
    values, flags : (S,) float32, uint8
        The tiles' slots one after the other.
    tables : (T, BX, BY, BZ) int32
        Tile ``b``'s brick table (global brick numbers), padded with -1 to the largest tile's.
    dims : (T, 3) int64
        Each tile's lattice vertex counts.
    points : (sum N, 3) float32
        The tiles' points one after the other, rows ``p_start[b]:p_start[b + 1]`` tile ``b``'s.
    normals : (sum N, 3) float32 or (0, 3)
        Their normals, rows ``n_start[b]:n_start[b + 1]`` (empty ranges when unused).
    nearest : (sum Nq,) int32
        Nearest point of each query (this iteration's pool batch), a row of its tile's points.
    q_tile : (sum Nq,) int32
        Each query's tile.
    q_start : (T + 1,) int64
        Tile ``b``'s queries are ``q_start[b]:q_start[b + 1]``.
    steps : (T,) float64
        ``N_b / Nq_b``.
    counts : (T, iterations) int32, in/out
    loss_sums : (T, iterations, 4) int64, in/out
    Other parameters as :func:`query_scatter`.
    """
    start, stride = cuda.grid(1), cuda.gridsize(1)
    slots = cuda.local.array(16, np.int64)
    grads = cuda.local.array(16, np.float32)
    losses = cuda.local.array(4, np.float32)
    for n in range(start, nearest.shape[0], stride):
        b = q_tile[n]
        q0 = q_start[b]
        clip = _clip_for(q_start[b + 1] - q0)  # the tile's own launch's clip: its sums are the same
        _query_item(n - q0, values, flags, tables[b], dims[b, 0], dims[b, 1], dims[b, 2],
                    points[p_start[b]:p_start[b + 1]], normals[n_start[b]:n_start[b + 1]], use_normals, nearest[n],
                    key, steps[b], sigma, normal_table, pull_bit, beta, gamma, lam, acc, counts[b], t, loss_sums[b],
                    want_losses, slots, grads, losses, clip)


@cuda.jit(cache=True)
def tv_norms_batch(d, flags, neighbors, inv, tile_of_brick, sums, t, want_sum):
    """:func:`tv_norms` over a batch's concatenated bands (``neighbors`` in global brick numbers: no stencil crosses
    into another tile); tile ``b``'s TV sum goes to ``sums[b, t]``."""
    start, stride = cuda.grid(1), cuda.gridsize(1)
    for s in range(start, d.shape[0], stride):
        _norm_item(s, d, flags, neighbors, inv, sums[tile_of_brick[s >> 9]], t, want_sum)


@cuda.jit(cache=True)
def tv_adam_batch(d_in, d_out, m, v, acc, counts, t, tile_of_brick, flags, neighbors, inv, form, tv_scales, lr_t,
                  beta1, beta2, eps, clamp_nonneg, sums, want_sum):
    """:func:`tv_adam` over a batch's concatenated bands: each slot's query gradient is divided by its own tile's
    valid count ``counts[b, t]`` and its TV weighted by ``tv_scales[b]``, as the tile's launch alone would."""
    start, stride = cuda.grid(1), cuda.gridsize(1)
    for s in range(start, d_in.shape[0], stride):
        b = tile_of_brick[s >> 9]
        n_valid = counts[b, t]
        scale = np.float32(_INV_FIXED / n_valid) if n_valid > 0 else np.float32(0.0)
        _adam_item(s, d_in, d_out, m, v, acc, scale, flags, neighbors, inv, form, tv_scales[b], lr_t, beta1, beta2,
                   eps, clamp_nonneg, sums[b], t, want_sum)


@cuda.jit(cache=True)
def copy_columns(src, dst, c0):
    """``dst[:, c0:c0 + src.shape[1]] = src`` (a tile's query pool into the batch's)."""
    start, stride = cuda.grid(1), cuda.gridsize(1)
    rows, cols = src.shape[0], src.shape[1]
    for n in range(start, rows * cols, stride):
        r = n // cols
        c = n - r * cols
        dst[r, c0 + c] = src[r, c]


@cuda.jit(cache=True)
def upsample(coarse, table, nx, ny, nz, brick_coords, factor, fill, out):
    """Initial values of a finer band from the coarser field on the card (:func:`tiled_gridpull.solver.upsample`).

    Fine slot ``s`` of brick ``b`` sits at lattice index ``brick_coords[b] * 8 + local``, coarse index that over
    ``factor``; ``out[s] = factor * f_coarse``, or ``fill`` (in fine cells) where the coarse cell is incomplete.
    """
    start, stride = cuda.grid(1), cuda.gridsize(1)
    slots = cuda.local.array(8, np.int64)
    ff = np.float32(factor)
    for s in range(start, out.shape[0], stride):
        b = s >> 9
        i = s & 511
        px = np.float32(np.float64(brick_coords[b, 0] * 8 + (i >> 6)) / factor)
        py = np.float32(np.float64(brick_coords[b, 1] * 8 + ((i >> 3) & 7)) / factor)
        pz = np.float32(np.float64(brick_coords[b, 2] * 8 + (i & 7)) / factor)
        ci, cj, ck, tx, ty, tz = _locate(px, py, pz, nx, ny, nz)
        if _corner_slots(table, ci, cj, ck, slots, 0):
            f, _, _, _ = _eval_corners(coarse, slots, 0, tx, ty, tz)
            out[s] = np.float32(f) * ff
        else:
            out[s] = np.float32(fill / factor) * ff


@cuda.jit(cache=True)
def nearest_pool(points, order, table_keys, table_starts, table_counts, bits, ox, oy, oz, h, gx, gy, gz, seed, it0,
                 step, sigma, normal_table, out):
    """Nearest input point of every query of a level's pool: batch ``b`` holds the queries of iteration ``it0 + b``
    (:func:`.sampling.draw_one`), as the host's pool (:func:`tiled_gridpull.solver._optimize`).

    Parameters
    ----------
    points : (N, 3) float32
        Input points (index coordinates, Morton order).
    order, table_keys, table_starts, table_counts, bits, ox, oy, oz, h, gx, gy, gz
        The point grid (:class:`tiled_gridpull.nearest.PointGrid`).
    seed, it0 : int
        The sampling seed and the level's first iteration.
    step, sigma : float
        ``N / Nq`` and the query spread (cells).
    normal_table : (65536,) float32
    out : (B, Nq) int32, out
        Row of the nearest point (ties: the lowest row).
    """
    start, stride = cuda.grid(1), cuda.gridsize(1)
    nq = out.shape[1]
    for n in range(start, out.shape[0] * nq, stride):
        b = n // nq
        i = n - b * nq
        key = _iteration_key(seed, it0 + b)
        c, qx, qy, qz = _draw_one(points, key, i, step, sigma, normal_table)
        best, _ = _grid_nearest_one(points, order, table_keys, table_starts, table_counts, bits, ox, oy, oz, h, gx, gy,
                                    gz, qx, qy, qz, c)
        out[b, i] = best
