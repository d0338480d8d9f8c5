"""How far apart a cloud's samples are on its surface: the basis of ``voxel_size: auto``.

LiDAR density varies by orders of magnitude within one scan (centimetres next to a mobile scanner, decimetres
on a façade across the street), so one number needs care. For each measured point the area it stands for on
the surface is ``pi r_k^2 / k`` (``r_k`` its distance to its ``k``-th neighbour: ``k`` points share that disc)
and its spacing is the square root of that area. Two medians of it describe the cloud:

* ``median``: over points, i.e. where the points are (dominated by the dense patches);
* ``area_median``: over surface area, i.e. the spacing at which half of the scanned surface is sampled at least
  this densely (dominated by the sparse parts). Areas are capped at their 99th percentile first: a handful of
  stray points (birds, multipath, a few points of a neighbouring file) each "stand for" a huge disc and would
  otherwise outweigh the whole survey; a sparse part of the scan holding more than 1 % of the points still
  counts in full.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

__all__ = ["Spacing", "point_spacing", "STRAY_QUANTILE"]

#: areas above this quantile (by point) are capped to it in the by-area median: the sparsest 1 % of points are
#: strays, not a part of the surface
STRAY_QUANTILE = 0.99


@dataclass(frozen=True)
class Spacing:
    """Sample spacing of a cloud in its own units (see the module docstring), and how it was measured."""

    median: float
    area_median: float
    points: int
    measured: int

    def to_dict(self) -> dict:
        return {"median": self.median, "area_median": self.area_median, "points": self.points,
                "measured": self.measured}


def point_spacing(points: np.ndarray, k: int = 8, sample: int = 20_000) -> Spacing:
    """Median sample spacing of a cloud, by point and by surface area.

    Parameters
    ----------
    points : (N, 3) float
        At least ``k + 1`` points (world units; measured from their mean in float64, so georeferenced
        coordinates stay exact).
    k : int
        Neighbours sharing the disc a point stands for.
    sample : int
        Points measured (evenly spaced in the input's order); all of them are neighbours.

    Returns
    -------
    Spacing
    """
    xyz = np.asarray(points, dtype=np.float64)
    if len(xyz) <= k:
        raise ValueError(f"need more than {k} points to measure their spacing, got {len(xyz)}")
    xyz = xyz - xyz.mean(axis=0)
    pick = np.unique(np.linspace(0, len(xyz) - 1, min(sample, len(xyz))).astype(np.int64))
    d, _ = KDTree(xyz).query(xyz[pick], k=k + 1)  # the point itself comes first
    area = np.pi * d[:, k] ** 2 / k
    spacing = np.sqrt(area)
    area = np.minimum(area, np.quantile(area, STRAY_QUANTILE))
    order = np.argsort(spacing, kind="stable")
    cum = np.cumsum(area[order])
    area_median = float(spacing[order][np.searchsorted(cum, 0.5 * cum[-1])])
    return Spacing(float(np.median(spacing)), area_median, len(xyz), len(pick))
