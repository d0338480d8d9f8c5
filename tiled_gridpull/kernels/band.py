"""Band construction on brick-sparse masks: cost and memory grow with the band, never with the lattice volume.

Masks are ``(n_bricks, 512)`` uint8 arrays in the brick layout of :mod:`tiled_gridpull.kernels` (cell masks use
the slot of a cell's lowest vertex). A dense ``table`` over the brick grid maps brick coordinates to rows.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from . import BRICK, BRICK_VOLUME
from .interp import bounded_slot_of


@njit(cache=True, parallel=True)
def window_any(mask, axis, lo, hi):
    """Running-window OR of a small dense grid along ``axis``: ``out[i] = any(mask[i-lo : i+hi+1])``.

    Used on the brick grid (one byte per brick), so a dense array is cheap there.
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
        for i in range(n):
            found = 0
            for j in range(max(0, i - lo), min(n, i + hi + 1)):
                if axis == 0:
                    found |= mask[j, u, v]
                elif axis == 1:
                    found |= mask[u, j, v]
                else:
                    found |= mask[u, v, j]
            if found:
                if axis == 0:
                    out[i, u, v] = 1
                elif axis == 1:
                    out[u, i, v] = 1
                else:
                    out[u, v, i] = 1
    return out


@njit(cache=True)
def scatter_cells(cells, table, n_bricks):
    """Brick-sparse occupancy (n_bricks, 512) from integer cells (N, 3) whose bricks are in ``table``."""
    occ = np.zeros((n_bricks, BRICK_VOLUME), np.uint8)
    for n in range(cells.shape[0]):
        x, y, z = cells[n, 0], cells[n, 1], cells[n, 2]
        b = table[x >> 3, y >> 3, z >> 3]
        occ[b, ((x & 7) << 6) | ((y & 7) << 3) | (z & 7)] = 1
    return occ


@njit(cache=True, parallel=True)
def sparse_window_any(src, table, coords, axis, lo, hi, limit):
    """Running-window OR along ``axis`` of a brick-sparse mask.

    ``out[p] = any(src[p - lo*e : p + hi*e])`` where missing bricks read as 0, and positions at or beyond
    ``limit`` (global index along ``axis``) are forced to 0 in the output.
    """
    nb = coords.shape[0]
    out = np.zeros_like(src)
    BX, BY, BZ = table.shape
    span = BRICK + lo + hi
    for b in prange(nb):
        line = np.zeros(span, np.uint8)
        base = coords[b, axis] * BRICK
        for u in range(BRICK):
            for v in range(BRICK):
                # gather the line from this brick and its neighbours along axis
                for t in range(span):
                    g = base - lo + t
                    val = 0
                    if g >= 0:
                        bk = g >> 3
                        local = g & 7
                        if axis == 0:
                            if bk < BX:
                                nbk = table[bk, coords[b, 1], coords[b, 2]]
                                if nbk >= 0:
                                    val = src[nbk, (local << 6) | (u << 3) | v]
                        elif axis == 1:
                            if bk < BY:
                                nbk = table[coords[b, 0], bk, coords[b, 2]]
                                if nbk >= 0:
                                    val = src[nbk, (u << 6) | (local << 3) | v]
                        else:
                            if bk < BZ:
                                nbk = table[coords[b, 0], coords[b, 1], bk]
                                if nbk >= 0:
                                    val = src[nbk, (u << 6) | (v << 3) | local]
                    line[t] = val
                count = 0
                for t in range(lo + hi + 1):
                    count += line[t]
                for i in range(BRICK):
                    if count > 0 and base + i < limit:
                        if axis == 0:
                            out[b, (i << 6) | (u << 3) | v] = 1
                        elif axis == 1:
                            out[b, (u << 6) | (i << 3) | v] = 1
                        else:
                            out[b, (u << 6) | (v << 3) | i] = 1
                    if i + 1 < BRICK:
                        count += line[i + lo + hi + 1]
                        count -= line[i]
    return out


@njit(cache=True, parallel=True)
def all_corners(vmask, table, coords, cell_limit):
    """Cells whose 8 corner vertices are all set in ``vmask`` (cells at or beyond ``cell_limit`` excluded)."""
    nb = coords.shape[0]
    out = np.zeros_like(vmask)
    for b in prange(nb):
        for x in range(BRICK):
            gx = coords[b, 0] * BRICK + x
            if gx >= cell_limit[0]:
                continue
            for y in range(BRICK):
                gy = coords[b, 1] * BRICK + y
                if gy >= cell_limit[1]:
                    continue
                for z in range(BRICK):
                    gz = coords[b, 2] * BRICK + z
                    if gz >= cell_limit[2]:
                        continue
                    ok = 1
                    for c in range(8):
                        s = bounded_slot_of(table, gx + (c >> 2), gy + ((c >> 1) & 1), gz + (c & 1))
                        if s < 0 or vmask[s >> 9, s & 511] == 0:
                            ok = 0
                            break
                    out[b, (x << 6) | (y << 3) | z] = ok
    return out


@njit(cache=True, parallel=True)
def pack_flags(vparam, cell_opt, cell_pull, cell_occ, keep):
    """Per-slot flag bits for the kept bricks: PARAM=1, CELL_OPT=2, CELL_PULL=4, CELL_OCC=8."""
    nk = keep.shape[0]
    flags = np.zeros((nk, BRICK_VOLUME), np.uint8)
    for r in prange(nk):
        b = keep[r]
        for s in range(BRICK_VOLUME):
            flags[r, s] = (vparam[b, s] | (cell_opt[b, s] << 1) | (cell_pull[b, s] << 2)
                           | (cell_occ[b, s] << 3))
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
