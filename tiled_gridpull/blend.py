"""Blending tile fields in their overlaps with a partition of unity.

Tile ``t`` with block ``[lo_t, hi_t]`` (global vertex indices, its core extended by ``O`` cells) weighs a vertex
``g`` by ``w_t(g) = prod_axis clip(min(g - lo_t, hi_t - g) / (2 O), 0, 1)``: 0 on the block's border (where its
band is cut off), 1/2 on its core's border, 1 deeper than ``O`` inside the core. Across a shared face the
weights of the two tiles sum to 1, and over a regular tile grid the products sum to 1 everywhere.

The blended value at ``g`` is ``sum_t w_t d_t / sum_t w_t`` over the tiles whose band has ``g`` as a
parameter, summed in tile order. Every tile that needs ``g`` evaluates this same expression on the same
numbers in the same order, so neighbours hold bit-identical values on every shared vertex and marching cubes
draws the same crossings on both sides of a tile border.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .band import dense_brick_table, vertex_slots
from .kernels import BRICK, PARAM

__all__ = ["TileField", "brick_table", "pou_weight", "blend_into"]


@dataclass(eq=False)
class TileField:
    """A tile's solved field with its global placement.

    Attributes
    ----------
    index : (3,) int
        Tile index (the blend sums tiles in increasing index order).
    block_lo, block_hi : (3,) int64
        First and last global vertex index of the tile's block.
    brick_coords : (nb, 3) int64
        Global brick coordinates (block offsets are multiples of 8, so bricks are shared by all tiles).
    values : (nb, 512) float32
        Field in cells.
    flags : (nb, 512) uint8
    overlap : int
        Overlap ``O`` in cells (the ramp of the weights is ``2 O`` wide).
    """

    index: tuple
    block_lo: np.ndarray
    block_hi: np.ndarray
    brick_coords: np.ndarray
    values: np.ndarray
    flags: np.ndarray
    overlap: int

    def lookup(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values and parameter mask at global vertices ``g`` (M, 3) (False where the tile has none)."""
        lo, table = brick_table(self.brick_coords)
        slot = vertex_slots(table, np.asarray(g, np.int64) - lo * BRICK)
        ok = slot >= 0
        vals = np.zeros(len(g), np.float32)
        mask = np.zeros(len(g), bool)
        vals[ok] = self.values.reshape(-1)[slot[ok]]
        mask[ok] = (self.flags.reshape(-1)[slot[ok]] & PARAM) != 0
        return vals, mask


def brick_table(coords: np.ndarray, first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Dense table over the box of some bricks: ``table[c - lo]`` is ``first + i`` for brick ``i``, -1 elsewhere.

    Parameters
    ----------
    coords : (nb, 3) int
        Brick coordinates.
    first : int
        Number of the first brick.

    Returns
    -------
    lo : (3,) int64
        Low corner of the box (zeros for no bricks).
    table : (dx, dy, dz) int64
        At least one entry along each axis.
    """
    coords = np.asarray(coords, np.int64)
    if len(coords) == 0:
        return np.zeros(3, np.int64), np.full((1, 1, 1), -1, np.int64)
    lo = coords.min(axis=0)
    return lo, dense_brick_table(tuple(coords.max(axis=0) + 1 - lo), coords - lo, first, np.int64)


def pou_weight(g: np.ndarray, block_lo: np.ndarray, block_hi: np.ndarray, overlap: int) -> np.ndarray:
    """Partition-of-unity weight (M,) float64 of a tile at global vertices ``g`` (M, 3)."""
    if overlap <= 0:
        inside = np.all((g >= block_lo) & (g <= block_hi), axis=1)
        return inside.astype(np.float64)
    dist = np.minimum(g - block_lo, block_hi - g).astype(np.float64)
    return np.prod(np.clip(dist / (2.0 * overlap), 0.0, 1.0), axis=1)


def blend_into(own: TileField, others: list[TileField], region_lo: np.ndarray, region_hi: np.ndarray) -> int:
    """Replace ``own``'s parameters in the vertex box ``[region_lo, region_hi]`` by the blended values.

    Only vertices that some other tile's block holds can change; each is ``sum_t w_t d_t / sum_t w_t`` over the
    tiles (``own`` included) that hold it as a parameter, summed in tile index order in float64
    (:func:`tiled_gridpull.kernels.blend.blend_bricks`).

    Parameters
    ----------
    own : TileField
        Modified in place.
    others : list of TileField
        Every other tile whose block may hold vertices of the region (order does not matter).
    region_lo, region_hi : (3,) int
        Inclusive global vertex box (the vertices ``own``'s marching cubes will read).

    Returns
    -------
    int
        Number of vertices whose value changed.
    """
    from .kernels.blend import blend_bricks

    tiles = sorted([own, *others], key=lambda t: tuple(t.index))
    rank = next(i for i, t in enumerate(tiles) if t is own)
    region_lo = np.asarray(region_lo, np.int64)
    region_hi = np.asarray(region_hi, np.int64)
    lo = np.zeros((len(tiles), 3), np.int64)
    dims = np.zeros((len(tiles), 3), np.int64)
    start = np.zeros(len(tiles), np.int64)
    tables, values, flags = [], [], []
    offset = n_bricks = 0
    for i, t in enumerate(tiles):
        if i == rank:
            continue
        coords = np.asarray(t.brick_coords, np.int64)
        # only a neighbour's bricks that reach into the region are ever read: the overlap strip, not its field
        keep = np.flatnonzero(np.all((coords * BRICK + BRICK - 1 >= region_lo) & (coords * BRICK <= region_hi),
                                     axis=1))
        if len(keep) == 0:
            continue
        lo[i], table = brick_table(coords[keep], n_bricks)
        dims[i] = table.shape
        tables.append(table.ravel())
        start[i] = offset
        offset += table.size
        n_bricks += len(keep)
        values.append(np.asarray(t.values).reshape(-1, BRICK ** 3)[keep])
        flags.append(np.asarray(t.flags).reshape(-1, BRICK ** 3)[keep])
    if not tables:
        return 0
    own_values = own.values.reshape(-1, BRICK ** 3)
    changed = blend_bricks(np.ascontiguousarray(own.brick_coords, np.int64), own_values,
                           np.ascontiguousarray(own.flags, np.uint8).reshape(-1, BRICK ** 3), rank, region_lo,
                           region_hi, np.array([t.block_lo for t in tiles], np.int64),
                           np.array([t.block_hi for t in tiles], np.int64),
                           np.array([t.overlap for t in tiles], np.int64), lo, dims, start, np.concatenate(tables),
                           np.concatenate(values).astype(np.float32, copy=False),
                           np.concatenate(flags).astype(np.uint8, copy=False))
    return int(changed)
