"""Trilinear interpolation on a brick-sparse field, with analytic gradients.

Coordinates are lattice index coordinates (float32): vertex ``(i, j, k)`` sits at ``(i, j, k)``; a field value
is a distance in cells. Corner ``c = 4 dx + 2 dy + dz`` of the cell with lowest vertex ``(i, j, k)`` has weight
``w_c = wx * wy * wz`` with ``wx = tx`` if ``dx`` else ``1 - tx`` (``t`` the position inside the cell).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def slot_of(table, i, j, k):
    """Slot of vertex (i, j, k) or -1 when its brick is not allocated (no bounds check on the table)."""
    b = table[i >> 3, j >> 3, k >> 3]
    if b < 0:
        return -1
    return b * 512 + ((i & 7) << 6) + ((j & 7) << 3) + (k & 7)


@njit(cache=True, inline="always")
def bounded_slot_of(table, i, j, k):
    """Slot of vertex (i, j, k) (non-negative indices), or -1 when its brick is beyond the table or not allocated."""
    bx, by, bz = i >> 3, j >> 3, k >> 3
    if bx >= table.shape[0] or by >= table.shape[1] or bz >= table.shape[2]:
        return -1
    b = table[bx, by, bz]
    if b < 0:
        return -1
    return b * 512 + ((i & 7) << 6) + ((j & 7) << 3) + (k & 7)


@njit(cache=True, inline="always")
def locate(px, py, pz, nx, ny, nz):
    """Cell (i, j, k) holding a point and its position t inside the cell; clipped to the lattice.

    ``nx, ny, nz`` are vertex counts. Points outside are clamped to the border cell (t outside [0, 1] is
    clipped too, so values extrapolate flat). ``t`` has the coordinates' type: float32 coordinates (the solver's)
    give float32 positions, and the interpolation downstream runs in float32 (half the latency of float64
    division and square root, and the same arithmetic on a card, whose float64 units are few).
    """
    # int() truncates toward zero, not down, but only for negative coordinates, which the clamp sends to cell 0
    # either way; it compiles to one instruction where math.floor is a library call (~8 % of the query loss)
    i = min(max(int(px), 0), nx - 2)
    j = min(max(int(py), 0), ny - 2)
    k = min(max(int(pz), 0), nz - 2)
    # float32 operands keep float32 coordinates float32 (numba types float32 - int64 as float64); exact, as the
    # integer part of a coordinate below 2^24 is
    zero = np.float32(0.0)
    one = np.float32(1.0)
    tx = min(max(px - np.float32(i), zero), one)
    ty = min(max(py - np.float32(j), zero), one)
    tz = min(max(pz - np.float32(k), zero), one)
    return i, j, k, tx, ty, tz


@njit(cache=True, inline="always")
def corner_slots(table, i, j, k, out, o):
    """Write the 8 corner slots of cell (i, j, k) into ``out[o:o+8]``; False if any corner is missing."""
    if (i & 7) < 7 and (j & 7) < 7 and (k & 7) < 7:
        # all 8 corners in one brick (7 cells in 8 per axis): one table look-up
        b = table[i >> 3, j >> 3, k >> 3]
        if b < 0:
            for c in range(8):
                out[o + c] = -1
            return False
        s0 = b * 512 + ((i & 7) << 6) + ((j & 7) << 3) + (k & 7)
        out[o] = s0
        out[o + 1] = s0 + 1
        out[o + 2] = s0 + 8
        out[o + 3] = s0 + 9
        out[o + 4] = s0 + 64
        out[o + 5] = s0 + 65
        out[o + 6] = s0 + 72
        out[o + 7] = s0 + 73
        return True
    ok = True
    for c in range(8):
        s = slot_of(table, i + (c >> 2), j + ((c >> 1) & 1), k + (c & 1))
        out[o + c] = s
        if s < 0:
            ok = False
    return ok


@njit(cache=True, inline="always")
def eval_corners(values, slots, o, tx, ty, tz):
    """Value and gradient from the 8 corner slots ``slots[o:o+8]`` (all valid).

    Interpolates along z, then y, then x (11 multiply-adds for the value and its gradient, against 4 x 8 products
    of per-corner weights): the same trilinear function, rounded differently."""
    d0 = values[slots[o]]
    d1 = values[slots[o + 1]]
    d2 = values[slots[o + 2]]
    d3 = values[slots[o + 3]]
    d4 = values[slots[o + 4]]
    d5 = values[slots[o + 5]]
    d6 = values[slots[o + 6]]
    d7 = values[slots[o + 7]]
    # float32 one: a 1.0 literal would make float32 positions' whole interpolation float64
    ux = np.float32(1.0) - tx
    uy = np.float32(1.0) - ty
    uz = np.float32(1.0) - tz
    a00 = d0 * uz + d1 * tz
    a01 = d2 * uz + d3 * tz
    a10 = d4 * uz + d5 * tz
    a11 = d6 * uz + d7 * tz
    b0 = a00 * uy + a01 * ty
    b1 = a10 * uy + a11 * ty
    f = b0 * ux + b1 * tx
    gx = b1 - b0
    gy = (a01 - a00) * ux + (a11 - a10) * tx
    gz = ((d1 - d0) * uy + (d3 - d2) * ty) * ux + ((d5 - d4) * uy + (d7 - d6) * ty) * tx
    return f, gx, gy, gz


@njit(cache=True, inline="always")
def corner_gradients(out, o, tx, ty, tz, df, gx, gy, gz):
    """``out[o + c] = df * w_c + (gx, gy, gz) . grad w_c`` for the 8 corners: the gradient of a loss that reads
    the field's value (``df``) and gradient (``gx, gy, gz``) at position ``t`` of a cell w.r.t. its corner values."""
    ux = np.float32(1.0) - tx
    uy = np.float32(1.0) - ty
    uz = np.float32(1.0) - tz
    # per x side: df * wx + gx * d(wx)/dtx, and wx itself (weights the y and z derivative terms)
    for dx in range(2):
        wx = tx if dx else ux
        ax = df * wx + (gx if dx else -gx)
        for dy in range(2):
            wy = ty if dy else uy
            sy = gy if dy else -gy
            for dz in range(2):
                wz = tz if dz else uz
                sz = gz if dz else -gz
                out[o + 4 * dx + 2 * dy + dz] = ax * wy * wz + wx * (sy * wz + sz * wy)


@njit(cache=True, parallel=True)
def sample_field(values, table, shape, pts, fill):
    """Values (N,) float32 and gradients (N, 3) float32 of the field at index-space points.

    Points whose cell has a missing corner get ``fill`` and a zero gradient.
    """
    n = pts.shape[0]
    f = np.empty(n, np.float32)
    g = np.zeros((n, 3), np.float32)
    nx, ny, nz = shape[0], shape[1], shape[2]
    for p in prange(n):
        slots = np.empty(8, np.int64)
        i, j, k, tx, ty, tz = locate(pts[p, 0], pts[p, 1], pts[p, 2], nx, ny, nz)
        if corner_slots(table, i, j, k, slots, 0):
            v, gx, gy, gz = eval_corners(values, slots, 0, tx, ty, tz)
            f[p] = v
            g[p, 0] = gx
            g[p, 1] = gy
            g[p, 2] = gz
        else:
            f[p] = fill
    return f, g
