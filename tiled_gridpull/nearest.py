"""Nearest input point of each query: pykdtree, sped up by a k-nearest-neighbour cache.

Queries are always drawn around input points. :class:`NearestPoints` keeps, for every input point, its ``k``
nearest neighbours (one pykdtree query at set-up); a query close enough to its centre is answered exactly
from that short list (see :mod:`tiled_gridpull.kernels.nn`), the rest by the KD-tree itself.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from .kernels import nn as knn_kernels

__all__ = ["NearestPoints"]


class NearestPoints:
    """Exact nearest-neighbour queries against a fixed cloud.

    Parameters
    ----------
    points : (N, 3) float32
        The input cloud (index coordinates; any frame works).
    k : int
        Size of the per-point candidate list.
    """

    def __init__(self, points: np.ndarray, k: int = 8):
        self.points = np.ascontiguousarray(points, dtype=np.float32)
        self.tree = KDTree(self.points)
        k = int(min(k, len(self.points)))
        d, idx = self.tree.query(self.points, k=k)
        if k == 1:
            d, idx = d[:, None], idx[:, None]
        self.knn = np.ascontiguousarray(idx, dtype=np.int32)
        self.radius = np.ascontiguousarray(d[:, -1], dtype=np.float32)
        self.fallbacks = 0
        self.queries = 0

    def query(self, q: np.ndarray, centres: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Nearest input point of each query.

        Parameters
        ----------
        q : (Nq, 3) float32
        centres : (Nq,) int64, optional
            The input point each query was drawn around (enables the fast path).

        Returns
        -------
        idx : (Nq,) int64
        dist : (Nq,) float32
        """
        q = np.ascontiguousarray(q, dtype=np.float32)
        self.queries += len(q)
        if centres is None:
            d, i = self.tree.query(q, k=1)
            return i.astype(np.int64), d.astype(np.float32)
        idx = np.empty(len(q), np.int64)
        d2 = np.empty(len(q), np.float32)
        miss = knn_kernels.nearest_from_candidates(self.points, self.knn, self.radius,
                                                   np.ascontiguousarray(centres, dtype=np.int64), q, idx, d2)
        if miss:
            self.fallbacks += miss
            sel = np.flatnonzero(idx < 0)
            d, i = self.tree.query(q[sel], k=1)
            idx[sel] = i
            d2[sel] = d.astype(np.float32) ** 2
        return idx, np.sqrt(d2)
