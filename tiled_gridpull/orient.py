"""Which side is outside: oriented point normals and the initial field they give.

The GridPull loss does not change when ``f -> -f``, so the sign of a solved field comes only from its
initialisation. A sphere at the lattice centre (the paper) works for one closed object; on a street scene cut
into tiles it means nothing, and neighbouring tiles would disagree. Here the outside is fixed by a rule every
tile applies to the same data: normals estimated by PCA over each point's neighbours, turned to face the
sensor that saw the point (its origin is known for KITTI sequences) or, for airborne data, to face up. The
initial field is the signed distance to the tangent plane of the nearest point, so every tile starts with the
same orientation and only refines it.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from .band import Band

__all__ = ["estimate_normals", "orient_normals", "plane_distance_init", "orientation_score"]


def estimate_normals(points: np.ndarray, k: int = 16, chunk: int = 200_000) -> np.ndarray:
    """Unoriented unit normals by PCA over the ``k`` nearest neighbours.

    Parameters
    ----------
    points : (N, 3) float
    k : int

    Returns
    -------
    (N, 3) float32
        Eigenvector of the smallest eigenvalue of each neighbourhood's covariance.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    n = len(pts)
    k = int(min(k, n))
    tree = KDTree(pts)
    out = np.empty((n, 3), np.float32)
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        _, idx = tree.query(pts[s:e], k=k)
        nb = pts[idx.reshape(e - s, k)]
        nb -= nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", nb, nb)
        _, vecs = np.linalg.eigh(cov)
        out[s:e] = vecs[:, :, 0]
    return out


def orient_normals(normals: np.ndarray, points: np.ndarray, sensor: np.ndarray | None = None,
                   up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Flip normals to face the sensor (``(sensor - p) . n > 0``) or, without sensors, ``up``.

    Returns
    -------
    (N, 3) float32
    """
    n = np.array(normals, dtype=np.float32, copy=True)
    if sensor is not None:
        ref = np.asarray(sensor, dtype=np.float64) - np.asarray(points, dtype=np.float64)
    else:
        ref = np.broadcast_to(np.asarray(up, dtype=np.float64), n.shape)
    flip = np.einsum("ij,ij->i", n.astype(np.float64), ref) < 0
    n[flip] *= -1
    return n


def plane_distance_init(band: Band, index_points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Initial field: signed distance (cells) from every slot to the tangent plane of its nearest point.

    Parameters
    ----------
    band : Band
    index_points : (N, 3) float
        Points in the band's lattice index coordinates.
    normals : (N, 3) float
        Oriented unit normals (positive side = outside).

    Returns
    -------
    (n_bricks, 512) float32
    """
    pts = np.ascontiguousarray(index_points, dtype=np.float32)
    pos = band.slot_positions().astype(np.float32)
    _, idx = KDTree(pts).query(pos, k=1)
    d = np.einsum("ij,ij->i", pos - pts[idx], np.asarray(normals, dtype=np.float32)[idx])
    return d.astype(np.float32).reshape(band.n_bricks, 512)


def orientation_score(gradients: np.ndarray, normals: np.ndarray) -> float:
    """Mean sign agreement in [-1, 1] between field gradients at the points and their oriented normals."""
    dots = np.einsum("ij,ij->i", np.asarray(gradients, dtype=np.float64), np.asarray(normals, dtype=np.float64))
    valid = dots != 0
    if not valid.any():
        return 0.0
    return float(np.mean(np.sign(dots[valid])))
