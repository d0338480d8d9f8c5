"""Exact nearest input point for queries drawn around known input points.

A query ``q`` drawn around input point ``c`` is first answered from the k nearest neighbours of ``c`` (their
best is ``b``). Every point outside that list is at least ``r_k(c)`` from ``c`` (``r_k`` the distance to the
k-th neighbour), hence at least ``r_k(c) - |q - c|`` from ``q``; so ``b`` is the exact nearest neighbour
whenever ``|q - b| <= r_k(c) - |q - c|``. Queries that fail the test are flagged and answered by the KD-tree
instead, so the result is always exact.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, parallel=True, fastmath=True)
def nearest_from_candidates(points, knn, knn_dist, centres, q, out_idx, out_d2):
    """Nearest input point of each query among its centre's k nearest neighbours.

    Parameters
    ----------
    points : (N, 3) float32
    knn : (N, k) int32
        k nearest neighbours of every point (the point itself included), nearest first.
    knn_dist : (N, k) float32
        Their distances (ascending): the scan stops at the first candidate that cannot beat the best so far,
        and the last one is ``r_k``.
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
        dc = np.sqrt(dc2)
        slack = knn_dist[c, k - 1] - dc
        if slack <= 0.0:
            out_idx[n] = -1
            out_d2[n] = np.inf
            miss += 1
            continue
        best = c
        bd = dc2
        for t in range(k):
            # |x - q| >= |x - c| - |q - c|: once that bound passes the best, no later candidate can win
            lb = knn_dist[c, t] - dc
            if lb > 0.0 and lb * lb > bd:
                break
            j = knn[c, t]
            ex = qx - points[j, 0]
            ey = qy - points[j, 1]
            ez = qz - points[j, 2]
            d2 = ex * ex + ey * ey + ez * ez
            if d2 < bd or (d2 == bd and j < best):
                bd = d2
                best = j
        if bd > slack * slack:
            out_idx[n] = -1
            out_d2[n] = np.inf
            miss += 1
            continue
        out_idx[n] = best
        out_d2[n] = bd
    return miss
