"""Marching cubes over the optimized cells of a field: the surface as a :class:`~tiled_gridpull.mesh.Mesh`."""

from __future__ import annotations

import numpy as np

from .field import Field
from .kernels import mc as kmc
from .mesh import Mesh

__all__ = ["extract_mesh"]

T_CLAMP = 1e-3  # keep crossings off the lattice vertices so no triangle collapses to zero area


def extract_mesh(fld: Field, iso: float = 0.0, cell_lo: np.ndarray | None = None,
                 cell_hi: np.ndarray | None = None, key_offset: np.ndarray | None = None,
                 with_keys: bool = False):
    """Marching cubes over the optimized cells of a field.

    Parameters
    ----------
    fld : Field
    iso : float
        Iso level in cells (0 for the surface).
    cell_lo, cell_hi : (3,) int, optional
        Only cells with lowest corner in ``[cell_lo, cell_hi)`` (block index) are meshed (a tile's core).
    key_offset : (3,) int, optional
        Added to block vertex indices to form edge keys (a tile's offset from the job lattice) so that keys
        from different tiles agree.
    with_keys : bool
        Also return the edge key of every vertex (for welding tiles).

    Returns
    -------
    Mesh, or (Mesh, keys) with ``keys`` (V,) int64
    """
    if not fld.signed:
        raise ValueError("an unsigned field has no zero crossings to mesh: sign it first "
                         "(tiled_gridpull.udf_sign.sign_unsigned_field)")
    band = fld.band
    lat = band.lattice
    lo = np.zeros(3, np.int64) if cell_lo is None else np.asarray(cell_lo, np.int64)
    hi = np.asarray(lat.n_cells, np.int64) if cell_hi is None else np.asarray(cell_hi, np.int64)
    koff = np.zeros(3, np.int64) if key_offset is None else np.asarray(key_offset, np.int64)
    top = koff + np.asarray(lat.shape, np.int64)
    if np.any(koff < 0) or top[0] >= 2 ** kmc.KEY_BITS_X or top[1] >= 2 ** kmc.KEY_BITS_Y \
            or top[2] >= 2 ** kmc.KEY_BITS_Z:
        raise ValueError("lattice too large for 64-bit edge keys (2^21 x 2^21 x 2^19 vertices)")
    values = fld.values.reshape(-1)
    flags = band.flags.reshape(-1)
    iso32 = np.float32(iso)
    counts = kmc.count_triangles(values, flags, band.brick_table, band.brick_coords, lo, hi, iso32)
    offsets = np.zeros((len(counts) + 1, 2), np.int64)
    np.cumsum(counts, axis=0, out=offsets[1:])
    tris = np.empty((int(offsets[-1, 0]), 3), np.int64)
    centres = np.empty((int(offsets[-1, 1]), 3), np.float64)
    kmc.emit_triangles(values, flags, band.brick_table, band.brick_coords, lo, hi, iso32, offsets, koff, tris,
                       centres)
    keys, inverse = np.unique(tris, return_inverse=True)
    faces = inverse.reshape(-1, 3)
    pts = np.empty((len(keys), 3), np.float64)
    is_centre = keys < 0
    pts[is_centre] = centres[-1 - keys[is_centre]]
    pts[~is_centre] = kmc.edge_points(values, band.brick_table, keys[~is_centre], koff, float(iso), T_CLAMP)
    mesh = Mesh(lat.to_world(pts), faces)
    return (mesh, keys) if with_keys else mesh
