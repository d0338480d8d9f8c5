"""Nearest input point of each query: pykdtree, sped up by a k-nearest-neighbour cache.

Queries are always drawn around input points. :class:`NearestPoints` keeps, for every input point, its ``k``
nearest neighbours (one pykdtree query at set-up); a query whose best candidate provably beats every point
outside that list is answered from it (see :mod:`tiled_gridpull.kernels.nn`), the rest by the KD-tree itself.
Where the lists would answer too few queries (points much denser than the query spread, as on LiDAR close to
the scanner) they are not built and every query goes to the KD-tree.

:class:`PointGrid` answers the same queries exactly without a tree (a uniform grid of cells hashed by key), in
scalar code that the CUDA backend compiles for the card.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

from .kernels import nn as knn_kernels

__all__ = ["NearestPoints", "PointGrid", "distances_to_cloud", "nearest_in_cloud"]


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


@dataclass(frozen=True, eq=False)
class PointGrid:
    """Input points bucketed in a uniform grid of cubic cells, for exact nearest-point queries without a tree.

    Only occupied cells are stored, in an open-addressing hash table, so a grid over a tile's bounding box costs
    memory in proportion to its points, not its volume. The search (:func:`~tiled_gridpull.kernels.nn.grid_nearest_one`)
    visits shells of cells around the query and is exact; the CUDA backend runs it on the card
    (:func:`~tiled_gridpull.kernels.cuda.nearest_pool`), :meth:`query` on the CPU.

    Attributes
    ----------
    origin : (3,) float64
        Corner of cell (0, 0, 0) (units of the points).
    cell : float
        Cell edge.
    dims : (3,) int64
        Cells along each axis.
    order : (N,) int32
        Point rows sorted by cell.
    table_keys : (T,) int64
        Cell key ``(ix * gy + iy) * gz + iz`` of each table slot, -1 where empty; ``T = 2**bits``.
    table_starts, table_counts : (T,) int32
        The cell's run in ``order``.
    bits : int
    """

    origin: np.ndarray
    cell: float
    dims: np.ndarray
    order: np.ndarray
    table_keys: np.ndarray
    table_starts: np.ndarray
    table_counts: np.ndarray
    bits: int

    #: Points per occupied cell the automatic cell edge aims at: a query then reads a few dozen points in the 27
    #: cells around it, and few cells are empty.
    TARGET_PER_CELL = 4.0

    @classmethod
    def build(cls, points: np.ndarray, cell: float) -> PointGrid:
        """Bucket ``points`` ((N, 3) float32, N >= 1) in cells of edge ``cell`` (> 0, same units; raised to a
        2^-20th of the cloud's extent where it is finer, so that the cell keys fit an int64)."""
        P = np.asarray(points, dtype=np.float32)
        if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
            raise ValueError(f"PointGrid needs an (N, 3) array of at least one point, got shape {P.shape}")
        if not cell > 0:
            raise ValueError(f"PointGrid needs a positive cell edge, got {cell}")
        lo = P.min(axis=0).astype(np.float64)
        # at most 2^20 + 1 cells an axis, so the cell keys (the dims' product, < 2^61) stay positive int64s: a
        # wrapped, negative key reads as an empty slot and drops its cell (any edge keeps the search exact)
        cell = max(float(cell), float((P.max(axis=0) - lo).max()) / 2.0 ** 20)
        ijk = np.floor((P - lo) / cell).astype(np.int64)
        dims = ijk.max(axis=0) + 1
        keys = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        order = np.argsort(keys, kind="stable")
        sk = keys[order]
        first = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]])
        counts = np.diff(np.r_[first, len(sk)]).astype(np.int32)
        bits = max(4, int(np.ceil(np.log2(2 * len(first)))))
        tk = np.full(1 << bits, -1, np.int64)
        ts = np.zeros(1 << bits, np.int32)
        tc = np.zeros(1 << bits, np.int32)
        knn_kernels.fill_cell_table(sk[first], first.astype(np.int32), counts, bits, tk, ts, tc)
        return cls(origin=lo, cell=float(cell), dims=dims, order=order.astype(np.int32), table_keys=tk,
                   table_starts=ts, table_counts=tc, bits=bits)

    @classmethod
    def for_queries(cls, points: np.ndarray, sigma: float) -> PointGrid:
        """A grid whose cell suits queries spread by ``sigma`` around ``points``.

        The cell starts at ``sigma`` and is rescaled (at most three builds, and within ``sigma / 4`` and
        ``4 sigma``) until an occupied cell holds about :attr:`TARGET_PER_CELL` points: on surfaces the count goes
        as the edge squared; where cells are finer than the point spacing it saturates at one, and the edge
        grows by the largest step."""
        grid = cls.build(points, sigma)
        for _ in range(2):
            per_cell = len(grid.order) / max(int(np.count_nonzero(grid.table_keys >= 0)), 1)
            scale = 4.0 if per_cell < 1.1 else np.sqrt(cls.TARGET_PER_CELL / per_cell)
            cell = float(np.clip(grid.cell * scale, sigma / 4, sigma * 4))
            if 0.7 < cell / grid.cell < 1.4:
                break
            grid = cls.build(points, cell)
        return grid

    @property
    def arrays(self) -> tuple:
        """The search's arguments after the points: order, table keys, starts, counts, bits."""
        return self.order, self.table_keys, self.table_starts, self.table_counts, self.bits

    def query(self, points: np.ndarray, q: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest point of each query, exact (ties: the lowest row).

        Parameters
        ----------
        points : (N, 3) float32
            The points the grid was built from.
        q : (Nq, 3) float32
        centres : (Nq,) int
            A point near each query (where it was drawn); any row works, a near one makes the search short.

        Returns
        -------
        idx : (Nq,) int64
        dist : (Nq,) float64
        """
        q = np.ascontiguousarray(q, dtype=np.float32)
        if not np.isfinite(q).all():
            # a NaN or inf query would walk shells without end
            raise ValueError("PointGrid.query needs finite queries")
        idx = np.empty(len(q), np.int64)
        d2 = np.empty(len(q), np.float64)
        knn_kernels.nearest_on_grid(np.ascontiguousarray(points, dtype=np.float32), *self.arrays, self.origin,
                                    self.cell, self.dims.astype(np.int64), q,
                                    np.ascontiguousarray(centres, dtype=np.int64), idx, d2)
        return idx, np.sqrt(d2)
