"""The observed part of a ground truth: what a scan could be scored against."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..mesh import Mesh
from ..metrics import sample_surface

__all__ = ["observed_samples"]


def observed_samples(gt_mesh: Mesh, points: np.ndarray, n_samples: int, radius: float,
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform ground-truth samples that lie within ``radius`` of a scanned point.

    Evaluating completeness against the whole street would charge a reconstruction for surfaces no ray saw
    (roofs, building backs, car bottoms); this keeps only the observed part.

    Parameters
    ----------
    gt_mesh : Mesh
    points : (N, 3) array_like
        The scanned points (same coordinates as the mesh).
    n_samples : int
        Samples drawn on the whole mesh before the filter (fewer are returned).
    radius : float
        Maximum distance (mesh units) from a sample to its nearest scanned point.
    seed : int

    Returns
    -------
    samples : (M, 3) float64
    normals : (M, 3) float64
        Unit face normals of the kept samples.
    """
    from pykdtree.kdtree import KDTree

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise InputError("observed_samples needs at least one scanned point")
    samples, normals = sample_surface(gt_mesh, int(n_samples), seed)
    centre = np.floor(pts.min(axis=0))  # georeferenced inputs: query near zero for full precision
    dist, _ = KDTree(pts - centre).query(samples - centre, k=1, distance_upper_bound=float(radius))
    keep = np.isfinite(dist) & (dist <= radius)
    return samples[keep], normals[keep]
