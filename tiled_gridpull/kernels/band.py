"""Dense-mask morphology and brick packing for band construction."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from . import BRICK, BRICK_VOLUME


@njit(cache=True, parallel=True)
def window_any(mask, axis, lo, hi):
    """Running-window OR along ``axis``: ``out[i] = any(mask[i - lo : i + hi + 1])`` (clipped at the ends).

    Parameters
    ----------
    mask : (X, Y, Z) uint8
    axis : int, 0..2
    lo, hi : int >= 0, window reach below and above ``i``.

    Returns
    -------
    (X, Y, Z) uint8 of 0/1.
    """
    X, Y, Z = mask.shape
    out = np.zeros_like(mask)
    if axis == 0:
        n, a, b = X, Y, Z
    elif axis == 1:
        n, a, b = Y, X, Z
    else:
        n, a, b = Z, X, Y
    for t in prange(a * b):
        u = t // b
        v = t % b
        # prefix count along the line keeps the cost O(n) whatever the radius
        count = 0
        # window for i=0 is [0, hi]
        for j in range(min(hi + 1, n)):
            if axis == 0:
                count += mask[j, u, v] != 0
            elif axis == 1:
                count += mask[u, j, v] != 0
            else:
                count += mask[u, v, j] != 0
        for i in range(n):
            if count > 0:
                if axis == 0:
                    out[i, u, v] = 1
                elif axis == 1:
                    out[u, i, v] = 1
                else:
                    out[u, v, i] = 1
            # slide: add i+hi+1, drop i-lo
            add = i + hi + 1
            if add < n:
                if axis == 0:
                    count += mask[add, u, v] != 0
                elif axis == 1:
                    count += mask[u, add, v] != 0
                else:
                    count += mask[u, v, add] != 0
            drop = i - lo
            if drop >= 0:
                if axis == 0:
                    count -= mask[drop, u, v] != 0
                elif axis == 1:
                    count -= mask[u, drop, v] != 0
                else:
                    count -= mask[u, v, drop] != 0
    return out


@njit(cache=True)
def mark_cells(cells, shape):
    """Dense uint8 occupancy (X, Y, Z) from integer cells (N, 3) (already clipped into the block)."""
    occ = np.zeros((shape[0], shape[1], shape[2]), np.uint8)
    for n in range(cells.shape[0]):
        occ[cells[n, 0], cells[n, 1], cells[n, 2]] = 1
    return occ


@njit(cache=True, parallel=True)
def brick_any(vmask, bshape):
    """(bx, by, bz) uint8: whether each brick of ``vmask`` (vertex grid) holds a set vertex."""
    X, Y, Z = vmask.shape
    out = np.zeros((bshape[0], bshape[1], bshape[2]), np.uint8)
    for bi in prange(bshape[0]):
        for bj in range(bshape[1]):
            for bk in range(bshape[2]):
                found = 0
                for x in range(bi * BRICK, min(X, bi * BRICK + BRICK)):
                    for y in range(bj * BRICK, min(Y, bj * BRICK + BRICK)):
                        for z in range(bk * BRICK, min(Z, bk * BRICK + BRICK)):
                            if vmask[x, y, z]:
                                found = 1
                                break
                        if found:
                            break
                    if found:
                        break
                out[bi, bj, bk] = found
    return out


@njit(cache=True, parallel=True)
def pack_flags(brick_coords, vparam, cell_opt, cell_pull, cell_occ):
    """Per-slot flags (nb, 512) uint8 from dense masks (vertex grid for ``vparam``, cell grid for the rest)."""
    nb = brick_coords.shape[0]
    X, Y, Z = vparam.shape
    CX, CY, CZ = cell_opt.shape
    flags = np.zeros((nb, BRICK_VOLUME), np.uint8)
    for b in prange(nb):
        ox = brick_coords[b, 0] * BRICK
        oy = brick_coords[b, 1] * BRICK
        oz = brick_coords[b, 2] * BRICK
        for x in range(BRICK):
            gx = ox + x
            if gx >= X:
                continue
            for y in range(BRICK):
                gy = oy + y
                if gy >= Y:
                    continue
                for z in range(BRICK):
                    gz = oz + z
                    if gz >= Z:
                        continue
                    f = np.uint8(0)
                    if vparam[gx, gy, gz]:
                        f |= 1
                    if gx < CX and gy < CY and gz < CZ:
                        if cell_opt[gx, gy, gz]:
                            f |= 2
                        if cell_pull[gx, gy, gz]:
                            f |= 4
                        if cell_occ[gx, gy, gz]:
                            f |= 8
                    flags[b, x * 64 + y * 8 + z] = f
    return flags


@njit(cache=True)
def brick_neighbors(brick_coords, table):
    """(nb, 6) int32 neighbour bricks in order -x, +x, -y, +y, -z, +z (-1 where absent)."""
    nb = brick_coords.shape[0]
    BX, BY, BZ = table.shape
    out = np.full((nb, 6), -1, np.int32)
    for b in range(nb):
        i, j, k = brick_coords[b, 0], brick_coords[b, 1], brick_coords[b, 2]
        if i > 0:
            out[b, 0] = table[i - 1, j, k]
        if i + 1 < BX:
            out[b, 1] = table[i + 1, j, k]
        if j > 0:
            out[b, 2] = table[i, j - 1, k]
        if j + 1 < BY:
            out[b, 3] = table[i, j + 1, k]
        if k > 0:
            out[b, 4] = table[i, j, k - 1]
        if k + 1 < BZ:
            out[b, 5] = table[i, j, k + 1]
    return out
