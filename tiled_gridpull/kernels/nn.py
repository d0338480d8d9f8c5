"""Exact nearest input point for queries drawn around known input points.

A query ``q`` drawn around input point ``c`` has its nearest neighbour among the k nearest neighbours of ``c``
whenever ``|q - c| <= r_k(c) / 2`` (``r_k`` the distance from ``c`` to its k-th neighbour): any point closer
to ``q`` than ``c`` is within ``r_k(c)`` of ``c``. Queries that fail the test are flagged and answered by the
KD-tree instead, so the result is always exact.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, parallel=True, fastmath=True)
def nearest_from_candidates(points, knn, radius, centres, q, out_idx, out_d2):
    """Nearest input point of each query among its centre's k nearest neighbours.

    Parameters
    ----------
    points : (N, 3) float32
    knn : (N, k) int32
        k nearest neighbours of every point (the point itself included).
    radius : (N,) float32
        Distance from each point to its k-th neighbour.
    centres : (Nq,) int64
        Input point each query was drawn around.
    q : (Nq, 3) float32
    out_idx : (Nq,) int64, out
        Nearest point index; -1 where the candidate test cannot guarantee exactness.
    out_d2 : (Nq,) float32, out
        Squared distance to it.

    Returns
    -------
    int
        Number of queries flagged for the exact fallback.
    """
    nq = q.shape[0]
    k = knn.shape[1]
    miss = 0
    for n in prange(nq):
        c = centres[n]
        qx, qy, qz = q[n, 0], q[n, 1], q[n, 2]
        dx = qx - points[c, 0]
        dy = qy - points[c, 1]
        dz = qz - points[c, 2]
        dc2 = dx * dx + dy * dy + dz * dz
        half = 0.5 * radius[c]
        if dc2 > half * half:
            out_idx[n] = -1
            out_d2[n] = np.inf
            miss += 1
            continue
        best = c
        bd = dc2
        for t in range(k):
            j = knn[c, t]
            ex = qx - points[j, 0]
            ey = qy - points[j, 1]
            ez = qz - points[j, 2]
            d2 = ex * ex + ey * ey + ez * ez
            if d2 < bd or (d2 == bd and j < best):
                bd = d2
                best = j
        out_idx[n] = best
        out_d2[n] = bd
    return miss
