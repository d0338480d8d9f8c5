"""Nearest input point of each query: pykdtree, sped up by a k-nearest-neighbour cache.

Queries are always drawn around input points. :class:`NearestPoints` keeps, for every input point, its ``k``
nearest neighbours (one pykdtree query at set-up); a query whose best candidate provably beats every point
outside that list is answered from it (see :mod:`tiled_gridpull.kernels.nn`), the rest by the KD-tree itself.
Where the lists would answer too few queries (points much denser than the query spread, as on LiDAR close to
the scanner) they are not built and every query goes to the KD-tree.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from .kernels import nn as knn_kernels

__all__ = ["NearestPoints", "distances_to_cloud", "nearest_in_cloud"]


def distances_to_cloud(queries: np.ndarray, points: np.ndarray, upper_bound: float = np.inf) -> np.ndarray:
    """Distance from each query to its nearest point (:func:`nearest_in_cloud`), (M,) float64."""
    return nearest_in_cloud(queries, points, upper_bound)[0]


def nearest_in_cloud(queries: np.ndarray, points: np.ndarray,
                     upper_bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point of each query, measured from the cloud's mean in float64.

    Subtracting a local origin first keeps georeferenced coordinates (y ~ 4e6) exact.

    Parameters
    ----------
    queries : (M, 3) float
    points : (N, 3) float
        Same units and frame as ``queries``.
    upper_bound : float
        Distances beyond this (times 1.0001, so the bound itself is kept) come back as ``inf``; a finite bound
        lets the KD-tree stop early.

    Returns
    -------
    distances : (M,) float64
    indices : (M,) int64
        Row of ``points``; ``N`` where the distance is ``inf``.
    """
    pts = np.asarray(points, dtype=np.float64)
    ref = pts.mean(axis=0)
    tree = KDTree(np.ascontiguousarray(pts - ref))
    q = np.ascontiguousarray(np.asarray(queries, dtype=np.float64) - ref)
    if np.isfinite(upper_bound):
        d, i = tree.query(q, k=1, distance_upper_bound=upper_bound * 1.0001)
    else:
        d, i = tree.query(q, k=1)
    return d, i.astype(np.int64)


class NearestPoints:
    """Exact nearest-neighbour queries against a fixed cloud.

    Parameters
    ----------
    points : (N, 3) float32
        The input cloud (index coordinates; any frame works).
    k : int
        Size of the per-point candidate list.
    sigma : float, optional
        Spread of the queries around their centres (same units as ``points``): the list size and the share of
        queries the lists would answer are then predicted (:meth:`candidates_for`) and the lists are built only
        where they pay.
    k_max : int
        Largest list size ``sigma`` may ask for.
    expected_queries : int, optional
        How many queries this object will answer: lists of ``N`` points x ``k`` candidates cost about as much
        to build as ``N k / LIST_BUILD_RATIO`` tree queries, so they are not built for fewer queries than that
        saves (the predicted share of them, needs ``sigma``).
    """

    def __init__(self, points: np.ndarray, k: int = 8, sigma: float | None = None, k_max: int = 64,
                 expected_queries: int | None = None):
        self.points = np.ascontiguousarray(points, dtype=np.float32)
        self.tree = KDTree(self.points)
        self.fallbacks = 0
        self.queries = 0
        #: predicted share of queries the candidate lists answer (None: not predicted)
        self.fast_share: float | None = None
        if sigma is not None:
            k, self.fast_share = self.candidates_for(sigma, k, k_max)
        #: why the candidate lists were not built (None: they were)
        self.lists_skipped: str | None = None
        if self.fast_share is not None and self.fast_share < self.MIN_FAST_SHARE:
            # every query goes to the KD-tree: a list scan that mostly fails costs more than it saves
            self.lists_skipped = "share"
        elif (self.fast_share is not None and expected_queries is not None
              and len(self.points) * min(k, len(self.points))
              > self.LIST_BUILD_RATIO * self.fast_share * expected_queries):
            # a dense cloud answering few queries per point: building the lists costs more than they save
            self.lists_skipped = "cost"
        if self.lists_skipped is not None:
            self.knn = self.knn_dist = None
            return
        k = int(min(k, len(self.points)))
        d, idx = self.tree.query(self.points, k=k)
        if k == 1:
            d, idx = d[:, None], idx[:, None]
        self.knn = np.ascontiguousarray(idx, dtype=np.int32)
        self.knn_dist = np.ascontiguousarray(d, dtype=np.float32)

    #: Below this predicted fast-path share the lists are not built. Measured per 50k queries (2 threads): bunny
    #: at R = 256, sigma 2 cells, 62 % answered by the lists: 11.8 ms with lists vs 12.4 ms KD-tree alone; a dense
    #: LiDAR tile (26 points per cell), sigma 0.5 cells, 21 % answered: 22.5 ms vs 19.1 ms (same process).
    MIN_FAST_SHARE = 0.45

    #: Lists are built when ``N k <= LIST_BUILD_RATIO * share * queries``. Measured on the finest level of the
    #: demo street's densest tile (2 threads, same process): building the 64-candidate lists of 250,654 points
    #: costs about 6 us a point (0.09 us a candidate), and a query answered by a list instead of the tree saves
    #: about 0.18 us, so the lists pay when a candidate is read for fewer than 2 answered queries. There, with
    #: 5M pooled queries and a 64 % share, the level's solve went from 6.5-7.3 s with lists to 5.1-5.5 s
    #: without; its middle level (44,432 points, 2.8M candidates, 95 % share) stayed 2x faster with them.
    LIST_BUILD_RATIO = 2.0

    def candidates_for(self, sigma: float, k_min: int, k_max: int, sample: int = 2000) -> tuple[int, float]:
        """Smallest list size (power of two in ``[k_min, k_max]``) whose radius covers most queries, and the
        share of queries such lists would answer.

        A query at distance ``r`` from its centre takes the fast path when its best candidate is within
        ``r_k - r``; Gaussian offsets of standard deviation ``sigma`` stay within ``2.5 sigma`` nine times out
        of ten and the best candidate is about as far as the query's offset from the surface, so aim for a median
        ``r_k >= 5 sigma``. The share is measured on one query per sampled point (exact nearest by the tree).
        """
        n = len(self.points)
        if n <= k_min:
            return k_min, 1.0
        pick = np.linspace(0, n - 1, min(sample, n)).astype(np.int64)
        kk = int(min(k_max, n))
        d, _ = self.tree.query(self.points[pick], k=kk)
        d = d.reshape(len(pick), kk)
        k = k_min
        while k < kk and np.median(d[:, k - 1]) < 5.0 * sigma:
            k *= 2
        k = int(min(k, kk))
        rng = np.random.default_rng(0)
        off = rng.normal(0.0, sigma, (len(pick), 3)).astype(np.float32)
        q = self.points[pick] + off
        best, _ = self.tree.query(q, k=1)
        share = float(np.mean(best <= d[:, k - 1] - np.linalg.norm(off, axis=1)))
        return k, share

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
        if centres is None or self.knn is None:
            if self.knn is None:
                self.fallbacks += len(q)
            d, i = self.tree.query(q, k=1)
            return i.astype(np.int64), d.astype(np.float32)
        idx = np.empty(len(q), np.int64)
        d2 = np.empty(len(q), np.float32)
        miss = knn_kernels.nearest_from_candidates(self.points, self.knn, self.knn_dist,
                                                   np.ascontiguousarray(centres, dtype=np.int64), q, idx, d2)
        if miss:
            self.fallbacks += miss
            sel = np.flatnonzero(idx < 0)
            d, i = self.tree.query(q[sel], k=1)
            idx[sel] = i
            d2[sel] = d.astype(np.float32) ** 2
        return idx, np.sqrt(d2)
