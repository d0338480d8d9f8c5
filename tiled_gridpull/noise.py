"""Noise level of a point cloud, from how far points stray from their neighbours' best-fitting plane.

GridPull fits a field whose finest cell is the smallest detail it can express: a cloud whose noise is larger
than a cell gets that noise reproduced as bumps and bubbles (measured in ``docs/solver.md``). The estimate
here tells the user (and the noisy preset) how coarse the finest cell should be.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

__all__ = ["estimate_noise", "NoiseEstimate"]


@dataclass(frozen=True)
class NoiseEstimate:
    """Noise sigma and median sample spacing of a cloud (world units)."""

    sigma: float
    spacing: float

    @property
    def noisy(self) -> bool:
        """Whether the scatter across the surface is large against the spacing along it. On a clean cloud the
        plane-fit residual comes from curvature and stays below about half the spacing (measured: 0.2-0.5 on
        the shared meshes at 10k-100k points); Gaussian noise of 0.25 % of the bbox diagonal already gives 1.4."""
        return self.sigma > 0.8 * self.spacing

    def to_dict(self) -> dict:
        return {"sigma": self.sigma, "spacing": self.spacing, "noisy": self.noisy}


def estimate_noise(points: np.ndarray, k: int = 64, sample: int = 20_000, seed: int = 0) -> NoiseEstimate:
    """Standard deviation of the points' scatter across the surface (world units).

    For ``sample`` random points, the ``k`` nearest neighbours get a least-squares plane (PCA); the spread
    along its normal is ``sqrt(smallest eigenvalue)``. The median over points, scaled by ``sqrt(k / (k - 3))``
    for the three fitted degrees of freedom, estimates the Gaussian noise sigma. Curvature adds a small bias
    on clean clouds (about 0.1 of the mean sample spacing), far below the noise levels that matter.

    Parameters
    ----------
    points : (N, 3) float
        The cloud (any coordinates: it is centred first, so georeferenced values keep their precision).
    k : int
        Neighbours per plane fit.
    sample : int
        Points at which the plane is fitted (all of them when the cloud is smaller).

    Returns
    -------
    NoiseEstimate
        ``sigma`` (same units as ``points``) and the median nearest-neighbour distance ``spacing``.
    """
    pts = np.asarray(points, dtype=np.float64)
    pts = pts - pts.mean(axis=0)
    n = len(pts)
    k = int(min(k, n))
    if k < 4:
        return NoiseEstimate(0.0, 0.0)
    rng = np.random.default_rng(seed)
    at = pts[rng.choice(n, size=min(sample, n), replace=False)]
    dist, idx = KDTree(pts).query(at, k=k)
    nb = pts[idx.astype(np.int64)]
    nb = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", nb, nb) / k
    smallest = np.linalg.eigvalsh(cov)[:, 0]
    sigma = float(np.sqrt(np.median(np.maximum(smallest, 0.0)) * k / (k - 3)))
    return NoiseEstimate(sigma, float(np.median(dist[:, 1])))
