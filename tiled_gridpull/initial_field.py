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

__all__ = ["plane_distance_init", "flood_init"]


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


def flood_init(band: Band, index_points: np.ndarray, closing: int = 2) -> np.ndarray | None:
    """Initial field for a closed shape: inside/outside by flood fill, magnitude = distance to the points.

    Cells holding points are dilated by ``closing`` cells (to close gaps between samples and small holes in
    the scan), free cells reachable from the lattice border are outside, the other free cells inside. Each
    slot gets ``sign * distance to the nearest point`` (cells), the sign of the nearest labelled cell.
    Unlike the paper's sphere this does not assume the shape is star-shaped around its bounding-box centre
    (a tube, a torus or a flange with a bore). Meant for the coarsest level, where the grid is small.

    Returns
    -------
    (n_bricks, 512) float32, or None when no inside region exists (the shape is open or leaks through a hole
    wider than ``2 * closing`` cells); callers then fall back to the sphere.
    """
    from .kernels import band as kb
    from .kernels import flood as kf

    lat = band.lattice
    ncell = np.asarray(lat.n_cells, dtype=np.int64)
    cells = np.clip(np.floor(np.asarray(index_points, dtype=np.float64)).astype(np.int64), 0, ncell - 1)
    occ = np.zeros(tuple(int(v) for v in ncell), np.uint8)
    occ[cells[:, 0], cells[:, 1], cells[:, 2]] = 1
    for axis in range(3):
        occ = kb.window_any(occ, axis, closing, closing)
    reached = kf.flood_from_border((occ == 0).astype(np.uint8))
    labels = np.where(occ != 0, 0, np.where(reached != 0, 1, -1)).astype(np.int8)
    if not (labels < 0).any():
        return None
    labels = kf.spread_labels(labels, int(closing) + 2)
    pos = band.slot_positions()
    cell_of_slot = np.clip(pos, 0, ncell - 1)
    sign = labels[cell_of_slot[:, 0], cell_of_slot[:, 1], cell_of_slot[:, 2]].astype(np.float32)
    sign[sign == 0] = 1.0
    pts = np.ascontiguousarray(index_points, dtype=np.float32)
    d, _ = KDTree(pts).query(pos.astype(np.float32), k=1)
    return (sign * d.astype(np.float32)).reshape(band.n_bricks, 512)
