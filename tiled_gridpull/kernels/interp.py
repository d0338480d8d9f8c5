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
def locate(px, py, pz, nx, ny, nz):
    """Cell (i, j, k) holding a point and its position t inside the cell; clipped to the lattice.

    ``nx, ny, nz`` are vertex counts. Points outside are clamped to the border cell (t outside [0, 1] is
    clipped too, so values extrapolate flat)."""
    fx = np.floor(px)
    fy = np.floor(py)
    fz = np.floor(pz)
    i = min(max(int(fx), 0), nx - 2)
    j = min(max(int(fy), 0), ny - 2)
    k = min(max(int(fz), 0), nz - 2)
    tx = min(max(px - i, 0.0), 1.0)
    ty = min(max(py - j, 0.0), 1.0)
    tz = min(max(pz - k, 0.0), 1.0)
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
def weights(tx, ty, tz, c):
    """Weight of corner c and its derivatives along x, y, z (cell units)."""
    dx = c >> 2
    dy = (c >> 1) & 1
    dz = c & 1
    wx = tx if dx else 1.0 - tx
    wy = ty if dy else 1.0 - ty
    wz = tz if dz else 1.0 - tz
    sx = 1.0 if dx else -1.0
    sy = 1.0 if dy else -1.0
    sz = 1.0 if dz else -1.0
    return wx * wy * wz, sx * wy * wz, wx * sy * wz, wx * wy * sz


@njit(cache=True, inline="always")
def eval_corners(values, slots, o, tx, ty, tz):
    """Value and gradient from the 8 corner slots ``slots[o:o+8]`` (all valid)."""
    f = 0.0
    gx = 0.0
    gy = 0.0
    gz = 0.0
    for c in range(8):
        d = values[slots[o + c]]
        w, wx, wy, wz = weights(tx, ty, tz, c)
        f += w * d
        gx += wx * d
        gy += wy * d
        gz += wz * d
    return f, gx, gy, gz


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
