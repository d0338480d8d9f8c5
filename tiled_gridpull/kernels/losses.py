"""Per-query GridPull losses and their analytic gradients w.r.t. the vertex values.

For a query ``q`` with nearest input point ``s = P[NN(q)]`` (index coordinates, field in cells):

* pull     ``|q - f(q) n(q) - s|`` with ``n = grad f / |grad f|`` (flows through both f and n);
* surface  ``|f(s)|`` (paper) or ``f(s)^2`` (authors' code), weight ``beta``;
* gradient ``1 - cos(grad f(q), grad f(s))``, weight ``gamma`` (0 in UDF mode, where the field is kept
  non-negative by the optimizer step and the same pull formula is CAP-UDF's);
* normals  ``1 - cos(grad f(s), N(s))`` when input normals are given, weight ``lam``.

Each query writes its 16 corner slots (8 around q, 8 around s) and the loss gradient at each (in parallel, each
query to its own rows: no shared writes); the scatter into the vertex array follows in query order (see
:func:`scatter_add`).

The arithmetic follows the inputs' type: the solver passes float32 arrays and float32 weights, so everything is
computed in float32, as the field is stored (float64 arithmetic cost 20 % more per query on the CPU, and a card has
few float64 units). The gradients agree with float64 ones to about 5e-6 of their largest on a scene tile (index
coordinates up to ~320 cells) and 1e-4 at 1,500 cells: a position's rounding grows with its coordinate. The constants
are float32 so that they promote nothing; float64 inputs (the finite-difference tests) compute in float64.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .interp import corner_gradients, corner_slots, eval_corners, locate

# float32 constants: the losses run in float32 (a float64 literal would promote every expression it touches)
_EPS = np.float32(1e-12)
_TINY = np.float32(1e-20)
_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)


@njit(cache=True, inline="always")
def query_one(values, flags, table, nx, ny, nz, qx, qy, qz, points, p, normals, use_normals, pull_bit,
              beta, gamma, lam, slots, grads, losses):
    """The losses of one query at ``(qx, qy, qz)`` whose nearest input point is ``points[p]``.

    Writes its 16 corner slots into ``slots[0:16]`` (-1 where it does not count), their loss gradients into
    ``grads[0:16]`` and the pull, surface, gradient and normal losses into ``losses[0:4]`` (0 where it does not
    count); returns whether it counts. One query per call, so the CPU loop (:func:`query_losses`) and the CUDA
    kernel (:mod:`tiled_gridpull.kernels.cuda`) compile the same source.
    """
    sx, sy, sz = points[p, 0], points[p, 1], points[p, 2]
    qi, qj, qk, qtx, qty, qtz = locate(qx, qy, qz, nx, ny, nz)
    si, sj, sk, stx, sty, stz = locate(sx, sy, sz, nx, ny, nz)
    ok = corner_slots(table, qi, qj, qk, slots, 0)
    ok = corner_slots(table, si, sj, sk, slots, 8) and ok
    if ok:
        c0 = slots[0]
        ok = (flags[c0] & pull_bit) != 0
    if not ok:
        for c in range(16):
            slots[c] = -1
            grads[c] = 0.0
        for c in range(4):
            losses[c] = 0.0
        return False
    fq, gqx, gqy, gqz = eval_corners(values, slots, 0, qtx, qty, qtz)
    fs, gsx, gsy, gsz = eval_corners(values, slots, 8, stx, sty, stz)
    gq = math.sqrt(gqx * gqx + gqy * gqy + gqz * gqz + _EPS)
    gs = math.sqrt(gsx * gsx + gsy * gsy + gsz * gsz + _EPS)
    nqx, nqy, nqz = gqx / gq, gqy / gq, gqz / gq
    nsx, nsy, nsz = gsx / gs, gsy / gs, gsz / gs
    # --- pull
    rx = qx - fq * nqx - sx
    ry = qy - fq * nqy - sy
    rz = qz - fq * nqz - sz
    lp = math.sqrt(rx * rx + ry * ry + rz * rz + _TINY)
    ux, uy, uz = rx / lp, ry / lp, rz / lp
    un = ux * nqx + uy * nqy + uz * nqz
    dfq = -un
    k = -fq / gq
    dgqx = k * (ux - un * nqx)
    dgqy = k * (uy - un * nqy)
    dgqz = k * (uz - un * nqz)
    # --- surface at s
    ls = abs(fs)
    dfs = beta * (_ONE if fs > 0 else (-_ONE if fs < 0 else _ZERO))
    # --- gradient consistency
    dgsx = _ZERO
    dgsy = _ZERO
    dgsz = _ZERO
    lg = _ZERO
    if gamma > 0:
        cs = nqx * nsx + nqy * nsy + nqz * nsz
        lg = _ONE - cs
        a = -gamma / gq
        dgqx += a * (nsx - cs * nqx)
        dgqy += a * (nsy - cs * nqy)
        dgqz += a * (nsz - cs * nqz)
        b = -gamma / gs
        dgsx += b * (nqx - cs * nsx)
        dgsy += b * (nqy - cs * nsy)
        dgsz += b * (nqz - cs * nsz)
    # --- normal supervision at s
    ln = _ZERO
    if use_normals:
        Nx, Ny, Nz = normals[p, 0], normals[p, 1], normals[p, 2]
        cn = nsx * Nx + nsy * Ny + nsz * Nz
        ln = _ONE - cn
        b = -lam / gs
        dgsx += b * (Nx - cn * nsx)
        dgsy += b * (Ny - cn * nsy)
        dgsz += b * (Nz - cn * nsz)
    corner_gradients(grads, 0, qtx, qty, qtz, dfq, dgqx, dgqy, dgqz)
    corner_gradients(grads, 8, stx, sty, stz, dfs, dgsx, dgsy, dgsz)
    losses[0] = lp
    losses[1] = ls
    losses[2] = lg
    losses[3] = ln
    return True


@njit(cache=True, parallel=True, fastmath=True)
def query_losses(values, flags, table, shape, q, points, nearest, normals, pull_bit,
                 beta, gamma, lam, slots, grads, losses):
    """Evaluate the losses of every query and the gradient at its 16 corner slots.

    Parameters
    ----------
    values : (n_slots,) float32
        Field in cells.
    flags : (n_slots,) uint8
        Slot flags; a query counts only if its cell has ``pull_bit``.
    table : (BX, BY, BZ) int32
        Brick table.
    shape : (3,) int64
        Lattice vertex counts.
    q : (Nq, 3) float32
        Queries (index coordinates).
    points : (N, 3) float32
        Input points (index coordinates).
    nearest : (Nq,) integer
        Row of ``points`` nearest to each query (read here rather than gathered into an (Nq, 3) copy first).
    normals : (N, 3) float32 or (0, 3)
        Unit normals of ``points`` (used when ``lam > 0``).
    beta, gamma, lam : float
        Weights of the surface, gradient-consistency and normal losses (the pull has weight 1); pass
        ``np.float32`` with float32 arrays (a Python float is a float64 and would make the losses float64).
    slots : (Nq, 16) int64, out
        Corner slots (-1 for queries that do not count).
    grads : (Nq, 16) float32, out
        d(loss of this query)/d(value at slot).
    losses : (Nq, 4) float32, out
        pull, surface, gradient, normal loss of each query (0 where it does not count).

    Returns
    -------
    int
        Number of queries that count.
    """
    nq = q.shape[0]
    nx, ny, nz = shape[0], shape[1], shape[2]
    valid = np.zeros(nq, np.uint8)
    use_normals = lam > 0.0 and normals.shape[0] == points.shape[0]
    for n in prange(nq):
        if query_one(values, flags, table, nx, ny, nz, q[n, 0], q[n, 1], q[n, 2], points, nearest[n], normals,
                     use_normals, pull_bit, beta, gamma, lam, slots[n], grads[n], losses[n]):
            valid[n] = 1
    return int(valid.sum())


@njit(cache=True)
def scatter_add(target, slots, grads, scale):
    """``target[slots] += scale * grads`` (slots < 0 skipped), in query order.

    Deliberately serial: the queries arrive spatially sorted, so 800k adds take ~0.35 ms (about 2 % of an
    iteration) -- less than zeroing and merging per-thread buffers would -- there is no race by construction,
    and the sum at every vertex is accumulated in the same order whatever the thread count (bitwise
    reproducible runs).
    """
    nq, nc = slots.shape
    for n in range(nq):
        for c in range(nc):
            sl = slots[n, c]
            if sl >= 0:
                target[sl] += scale * grads[n, c]
