"""Narrow bands around the input points, stored in bricks.

GridPull optimizes only the vertices near the surface. With ``occ`` the cells that hold input points:

* the **pull band** (M1) is ``occ`` dilated by ``m1`` cells (Chebyshev/cube dilation): queries that fall in
  it carry the pull, surface and gradient losses;
* the **TV band** (M2) is ``occ`` dilated by ``m2`` cells: the vertices of its cells are the parameters,
  smoothed by the TV loss. Everything outside keeps its initial value and is never read by marching cubes.

Storage is sparse: the lattice is cut into bricks of 8^3 vertices and only bricks holding a parameter are
allocated, so memory and time grow with the band, not with R^3. Dilations are separable running-window ORs
on the brick-sparse masks (O(1) per cell whatever the radius), not loops over offsets.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .kernels import BRICK, BRICK_VOLUME, PARAM
from .kernels import band as kb
from .lattice import Lattice

__all__ = ["Band", "build_band", "dense_brick_table", "vertex_slots"]


@dataclass(frozen=True, eq=False)
class Band:
    """Brick-sparse description of the optimized region of a lattice.

    Attributes
    ----------
    lattice : Lattice
        The lattice (block) the band lives on.
    m1, m2 : int
        Pull-band and TV-band half widths in cells.
    brick_coords : (nb, 3) int32
        Brick grid coordinates; brick ``b`` holds vertices ``brick_coords[b] * 8 + [0, 8)^3``.
    brick_table : (BX, BY, BZ) int32
        Brick number for every brick of the lattice, -1 where no brick is allocated.
    neighbors : (nb, 6) int32
        Face-neighbour bricks (-x, +x, -y, +y, -z, +z), -1 where absent.
    flags : (nb, 512) uint8
        Per-slot bits ``PARAM``, ``CELL_OPT``, ``CELL_PULL``, ``CELL_OCC`` (see :mod:`tiled_gridpull.kernels`).
    """

    lattice: Lattice
    m1: int
    m2: int
    brick_coords: np.ndarray
    brick_table: np.ndarray
    neighbors: np.ndarray
    flags: np.ndarray
    stats: dict = field(default_factory=dict)

    @property
    def n_bricks(self) -> int:
        """Allocated bricks."""
        return int(self.brick_coords.shape[0])

    @property
    def n_slots(self) -> int:
        """Allocated vertex slots (bricks x 512)."""
        return self.n_bricks * BRICK_VOLUME

    @property
    def n_params(self) -> int:
        """Vertices that are optimisation variables."""
        return int(np.count_nonzero(self.flags & PARAM))

    def dense_mask(self, bit: int) -> np.ndarray:
        """Dense (X, Y, Z) bool array of one flag bit over the lattice's vertex grid (for tests and plots)."""
        X, Y, Z = self.lattice.shape
        out = np.zeros((self.brick_table.shape[0] * BRICK, self.brick_table.shape[1] * BRICK,
                        self.brick_table.shape[2] * BRICK), bool)
        bits = (self.flags & bit).reshape(-1, BRICK, BRICK, BRICK) != 0
        for b, (i, j, k) in enumerate(self.brick_coords):
            out[i * BRICK:(i + 1) * BRICK, j * BRICK:(j + 1) * BRICK, k * BRICK:(k + 1) * BRICK] = bits[b]
        return out[:X, :Y, :Z]

    def slot_positions(self) -> np.ndarray:
        """(nb * 512, 3) int64 lattice index of every slot (slots past the lattice edge included)."""
        local = np.indices((BRICK, BRICK, BRICK)).reshape(3, -1).T
        return (self.brick_coords[:, None, :].astype(np.int64) * BRICK + local[None]).reshape(-1, 3)


def dense_brick_table(bshape: tuple[int, ...], coords: np.ndarray, first: int = 0,
                      dtype: type = np.int32) -> np.ndarray:
    """Brick lookup: the number of each brick at its coordinates, -1 where no brick is stored.

    Parameters
    ----------
    bshape : (3,) int
        Bricks per axis of the table (for a band, its lattice's vertices per axis over ``BRICK``, rounded up).
    coords : (nb, 3) int
        Brick coordinates relative to the table's low corner, in brick order; all inside ``bshape``.
    first : int
        Number of the first brick (bricks of several fields numbered in one sequence).
    dtype : numpy integer type
        Of the table: int32 for a band (what the kernels take), int64 where numbers run past one field.

    Returns
    -------
    (bx, by, bz) ``dtype``
        ``table[coords[i]] == first + i``.
    """
    table = np.full(bshape, -1, dtype)
    table[coords[:, 0], coords[:, 1], coords[:, 2]] = first + np.arange(len(coords), dtype=dtype)
    return table


def vertex_slots(table: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Flat slot (``brick * 512 + local``) of each vertex in a brick-sparse field, or -1 where it has none.

    Parameters
    ----------
    table : (bx, by, bz) int
        Brick numbers over a brick grid (:func:`dense_brick_table`), -1 where no brick is stored.
    vertices : (M, 3) int
        Vertex indices relative to the table's low corner (brick ``(0, 0, 0)`` holds vertices ``[0, 8)^3``).

    Returns
    -------
    (M,) int64
        Slot into ``values.reshape(-1)`` / ``flags.reshape(-1)``; -1 where the vertex's brick lies outside the
        table or is not stored.
    """
    v = np.asarray(vertices, np.int64)
    b = v >> 3
    out = np.full(len(v), -1, np.int64)
    ok = np.all((b >= 0) & (b < np.asarray(table.shape)), axis=1)
    row = table[b[ok, 0], b[ok, 1], b[ok, 2]].astype(np.int64)
    loc = v[ok] & 7
    out[ok] = np.where(row >= 0, row * BRICK_VOLUME + ((loc[:, 0] << 6) | (loc[:, 1] << 3) | loc[:, 2]), -1)
    return out


def build_band(index_points: np.ndarray, lattice: Lattice, m1: int = 3, m2: int = 14) -> Band:
    """Build the pull and TV bands of a cloud.

    Parameters
    ----------
    index_points : (N, 3) float array
        Points in the lattice's index coordinates (see :meth:`Lattice.to_index`); points outside the block
        are ignored.
    lattice : Lattice
    m1, m2 : int
        Band half widths in cells, ``0 <= m1 <= m2``.

    Returns
    -------
    Band
    """
    ncell = np.asarray(lattice.n_cells, dtype=np.int64)
    vshape = np.asarray(lattice.shape, dtype=np.int64)
    cells = np.floor(np.asarray(index_points, dtype=np.float64)).astype(np.int64)
    cells = cells[np.all((cells >= 0) & (cells < ncell), axis=1)]
    bshape = tuple(int(v) for v in -(-vshape // BRICK))
    # candidate bricks: those within reach of an occupied brick (the vertex band reaches m2 + 1 cells)
    occupied = np.zeros(bshape, np.uint8)
    occupied[cells[:, 0] >> 3, cells[:, 1] >> 3, cells[:, 2] >> 3] = 1
    reach = -(-(m2 + 1) // BRICK)
    cand = occupied
    for axis in range(3):
        cand = kb.window_any(cand, axis, reach, reach)
    coords = np.argwhere(cand).astype(np.int64)
    table = dense_brick_table(bshape, coords)
    occ = kb.scatter_cells(cells, table, len(coords))

    def dilate(mask, lo, hi, limit):
        for axis in range(3):
            mask = kb.sparse_window_any(mask, table, coords, axis, lo, hi, int(limit[axis]))
        return mask

    cell_m2 = dilate(occ, m2, m2, ncell)
    cell_m1 = dilate(occ, m1, m1, ncell) if m1 != m2 else cell_m2
    # vertices of band cells: vertex v touches cells v-1 and v on each axis
    vparam = dilate(cell_m2, 1, 0, vshape)
    cell_opt = kb.all_corners(vparam, table, coords, ncell)
    keep = np.flatnonzero(vparam.any(axis=1))
    flags = kb.pack_flags(vparam, cell_opt, cell_m1, occ, keep)
    kept = coords[keep].astype(np.int32)
    table = dense_brick_table(bshape, kept)
    neighbors = kb.brick_neighbors(kept, table)
    stats = {
        "occupied_cells": int(np.count_nonzero(occ)),
        "pull_cells": int(np.count_nonzero(cell_m1)),
        "tv_cells": int(np.count_nonzero(cell_m2)),
        "params": int(np.count_nonzero(vparam)),
        "bricks": int(len(kept)),
    }
    return Band(lattice, int(m1), int(m2), kept, table, neighbors, flags, stats)
