"""Partition-of-unity blending of tile fields at the vertices of one tile (see :mod:`tiled_gridpull.blend`).

Every tile is given as its block box, its overlap and a dense brick table over the box of its allocated bricks,
so a neighbour's value at a global vertex is two array reads; only the bricks of a neighbour that reach into the
blended region are passed (the overlap strip: a tenth of a neighbour's field on the demo street). Vertices are
visited brick by brick in parallel (each brick writes only its own slots); at each vertex the tiles are summed
in the order given (tile index order), in float64, exactly as the NumPy expression this replaces, so every tile
that holds a shared vertex computes the same bits.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from . import BRICK_VOLUME, PARAM


@njit(cache=True, inline="always")
def _weight(gx, gy, gz, lo, hi, overlap):
    """Partition-of-unity weight of a tile (block ``[lo, hi]``, ramp ``2 overlap``) at global vertex g."""
    if overlap <= 0:
        inside = (lo[0] <= gx <= hi[0]) and (lo[1] <= gy <= hi[1]) and (lo[2] <= gz <= hi[2])
        return 1.0 if inside else 0.0
    ramp = 2.0 * overlap
    w = 1.0
    for axis in range(3):
        g = gx if axis == 0 else (gy if axis == 1 else gz)
        d = np.float64(min(g - lo[axis], hi[axis] - g)) / ramp
        if d < 0.0:
            d = 0.0
        elif d > 1.0:
            d = 1.0
        w = w * d
    return w


@njit(cache=True, parallel=True)
def blend_bricks(own_coords, own_values, own_flags, own_rank, region_lo, region_hi, block_lo, block_hi,
                 overlaps, table_lo, table_dims, table_start, tables, values, flags):
    """Blend the parameters of one tile (``own``) inside a vertex box with the other tiles' fields.

    Parameters
    ----------
    own_coords : (nb, 3) int64
        Global brick coordinates of the tile's bricks.
    own_values : (nb, 512) float32
        The tile's field (cells); blended in place.
    own_flags : (nb, 512) uint8
    own_rank : int
        Position of the tile itself in the tile order below.
    region_lo, region_hi : (3,) int64
        Inclusive global vertex box to blend.
    block_lo, block_hi : (T, 3) int64
        Every tile's block (first and last global vertex), in the order the blend sums them.
    overlaps : (T,) int64
    table_lo, table_dims : (T, 3) int64
        Box of each tile's brick table (global brick coordinates) and its size.
    table_start : (T,) int64
        Offset of each tile's table in ``tables`` (C order over ``table_dims``).
    tables : (total,) int64
        Row of ``values`` / ``flags`` of each brick of each tile, -1 where the tile has no (kept) brick; a tile
        with an empty table (``table_dims`` 0) holds nothing here; unused for ``own_rank``.
    values, flags : (nk, 512) float32 / uint8
        The other tiles' bricks that can be read, stacked.

    Returns
    -------
    int
        Vertices whose value changed.
    """
    n_tiles = block_lo.shape[0]
    nb = own_coords.shape[0]
    changed = np.zeros(nb, np.int64)
    for b in prange(nb):
        bx, by, bz = own_coords[b, 0] * 8, own_coords[b, 1] * 8, own_coords[b, 2] * 8
        # the brick's vertex box must meet the region and some other tile's block
        if (bx + 7 < region_lo[0] or bx > region_hi[0] or by + 7 < region_lo[1] or by > region_hi[1]
                or bz + 7 < region_lo[2] or bz > region_hi[2]):
            continue
        meets = False
        for t in range(n_tiles):
            if t == own_rank:
                continue
            if (bx + 7 >= block_lo[t, 0] and bx <= block_hi[t, 0] and by + 7 >= block_lo[t, 1]
                    and by <= block_hi[t, 1] and bz + 7 >= block_lo[t, 2] and bz <= block_hi[t, 2]):
                meets = True
                break
        if not meets:
            continue
        for s in range(BRICK_VOLUME):
            if (own_flags[b, s] & PARAM) == 0:
                continue
            gx = bx + (s >> 6)
            gy = by + ((s >> 3) & 7)
            gz = bz + (s & 7)
            if (gx < region_lo[0] or gx > region_hi[0] or gy < region_lo[1] or gy > region_hi[1]
                    or gz < region_lo[2] or gz > region_hi[2]):
                continue
            near = False
            for t in range(n_tiles):
                if t != own_rank and (block_lo[t, 0] <= gx <= block_hi[t, 0] and block_lo[t, 1] <= gy
                                      <= block_hi[t, 1] and block_lo[t, 2] <= gz <= block_hi[t, 2]):
                    near = True
                    break
            if not near:
                continue
            num = 0.0
            den = 0.0
            for t in range(n_tiles):
                if t == own_rank:
                    v = np.float64(own_values[b, s])
                else:
                    tx = (gx >> 3) - table_lo[t, 0]
                    ty = (gy >> 3) - table_lo[t, 1]
                    tz = (gz >> 3) - table_lo[t, 2]
                    if (tx < 0 or ty < 0 or tz < 0 or tx >= table_dims[t, 0] or ty >= table_dims[t, 1]
                            or tz >= table_dims[t, 2]):
                        continue
                    k = tables[table_start[t] + (tx * table_dims[t, 1] + ty) * table_dims[t, 2] + tz]
                    if k < 0:
                        continue
                    slot = ((gx & 7) << 6) | ((gy & 7) << 3) | (gz & 7)
                    if (flags[k, slot] & PARAM) == 0:
                        continue
                    v = np.float64(values[k, slot])
                w = _weight(gx, gy, gz, block_lo[t], block_hi[t], overlaps[t])
                num += w * v
                den += w
            out = np.float32(num / (den if den > 0.0 else 1.0))
            if out != own_values[b, s]:
                changed[b] += 1
            own_values[b, s] = out
    return changed.sum()
