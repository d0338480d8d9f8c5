"""Initial fields for the solver, which fix the sign (inside/outside) of the solved field.

The GridPull loss does not change when ``f -> -f``, so the sign of a solved field comes only from its
initialisation. A sphere at the lattice centre (the paper) works for one closed object; on a street scene cut
into tiles it means nothing, and neighbouring tiles would disagree. The plane-distance field is the signed
distance to the tangent plane of the nearest point (normals from :mod:`tiled_gridpull.normals`), so every tile
starts with the same orientation and only refines it.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from .band import Band

__all__ = ["plane_distance_init"]


def plane_distance_init(band: Band, index_points: np.ndarray, normals: np.ndarray,
                        origins: np.ndarray | None = None) -> np.ndarray:
    """Initial field: signed distance (cells) from every slot to the tangent plane of its nearest point.

    Parameters
    ----------
    band : Band
    index_points : (N, 3) float
        Points in the band's lattice index coordinates.
    normals : (N, 3) float
        Oriented unit normals (positive side = outside).
    origins : (N, 3) float, optional
        A point on each plane (index coordinates), e.g. the centroid of the point's neighbourhood; default the
        point itself.

    Returns
    -------
    (n_bricks, 512) float32
    """
    pts = np.ascontiguousarray(index_points, dtype=np.float32)
    at = pts if origins is None else np.asarray(origins, dtype=np.float32)
    pos = band.slot_positions().astype(np.float32)
    _, idx = KDTree(pts).query(pos, k=1)
    d = np.einsum("ij,ij->i", pos - at[idx], np.asarray(normals, dtype=np.float32)[idx])
    return d.astype(np.float32).reshape(band.n_bricks, 512)

