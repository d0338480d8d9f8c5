"""Exact nearest input point for queries drawn around known input points.

A query ``q`` drawn around input point ``c`` is first answered from the k nearest neighbours of ``c`` (their
best is ``b``). Every point outside that list is at least ``r_k(c)`` from ``c`` (``r_k`` the distance to the
k-th neighbour), hence at least ``r_k(c) - |q - c|`` from ``q``; so ``b`` is the exact nearest neighbour
whenever ``|q - b| <= r_k(c) - |q - c|``. Queries that fail the test are flagged and answered by the KD-tree
instead, so the result is always exact.

The grid search (:func:`grid_nearest_one`) needs no tree: the points are bucketed in a uniform grid of cubic cells
whose occupied cells sit in an open-addressing hash table (:func:`fill_cell_table`); a query visits the cells in
shells of growing Chebyshev radius around its own cell and stops once every unvisited point is provably farther than
the best one. It is written as scalar code so that the CUDA query kernels compile the same source for the card
(:func:`tiled_gridpull.kernels.cuda.nearest_pool`); :func:`nearest_on_grid` is its CPU twin.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

#: Fibonacci hashing multiplier (2^64 / golden ratio): consecutive cell keys land far apart in the table
_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)


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


@njit(cache=True, inline="always")
def cell_slot(table_keys, key, bits):
    """Slot of cell ``key`` in the hash table (:func:`fill_cell_table`), -1 where the cell holds no point.

    Parameters
    ----------
    table_keys : (2**bits,) int64
        Cell key of each slot, -1 where empty.
    key : int
        Linear cell index ``(ix * gy + iy) * gz + iz``.
    bits : int
        log2 of the table's size.
    """
    mask = np.uint64((1 << bits) - 1)
    s = (np.uint64(key) * _HASH_MULT) >> np.uint64(64 - bits)
    while True:
        k = table_keys[s]
        if k == key:
            return np.int64(s)
        if k < 0:
            return np.int64(-1)
        s = (s + np.uint64(1)) & mask


@njit(cache=True)
def fill_cell_table(cell_keys, starts, counts, bits, table_keys, table_starts, table_counts):
    """Insert each occupied cell (its key, and its run in the cell-sorted point order) by linear probing.

    Parameters
    ----------
    cell_keys : (C,) int64
        Distinct occupied cells.
    starts, counts : (C,) int32
        Their runs in the cell-sorted order of the points.
    bits : int
        log2 of the table's size (at least ``2 C`` slots, so probes stay short).
    table_keys : (2**bits,) int64, out
        Filled with -1 by the caller; the cells' keys on return.
    table_starts, table_counts : (2**bits,) int32, out
    """
    mask = np.uint64((1 << bits) - 1)
    for u in range(cell_keys.shape[0]):
        key = cell_keys[u]
        s = (np.uint64(key) * _HASH_MULT) >> np.uint64(64 - bits)
        while table_keys[s] >= 0:
            s = (s + np.uint64(1)) & mask
        table_keys[s] = key
        table_starts[s] = starts[u]
        table_counts[s] = counts[u]


@njit(cache=True, inline="always")
def _gap(q, lo, h):
    """Distance along one axis from coordinate ``q`` to the cell ``[lo, lo + h]`` (0 inside)."""
    if q < lo:
        return lo - q
    if q > lo + h:
        return q - lo - h
    return 0.0


@njit(cache=True, inline="always")
def grid_nearest_one(points, order, table_keys, table_starts, table_counts, bits, ox, oy, oz, h, gx, gy, gz,
                     qx, qy, qz, c):
    """Exact nearest input point of one query, from the point grid.

    Parameters
    ----------
    points : (N, 3) float32
    order : (N,) int32
        Point rows sorted by cell; a cell's points are ``order[start:start + count]``.
    table_keys, table_starts, table_counts, bits
        The occupied cells' hash table (:func:`fill_cell_table`).
    ox, oy, oz, h : float
        The grid's origin and cell edge (units of ``points``).
    gx, gy, gz : int
        Cells along each axis.
    qx, qy, qz : float
        The query.
    c : int
        A row to start from (the query's centre): its distance bounds the search.

    Returns
    -------
    best : int
        Row of the nearest point; of several at the same distance, the lowest row.
    d2 : float64
        Its squared distance (computed in float64, so a card's fused multiply-adds decide no tie).
    """
    best = c
    ex = np.float64(qx) - np.float64(points[c, 0])
    ey = np.float64(qy) - np.float64(points[c, 1])
    ez = np.float64(qz) - np.float64(points[c, 2])
    bd = ex * ex + ey * ey + ez * ez
    ix = int(math.floor((qx - ox) / h))
    iy = int(math.floor((qy - oy) / h))
    iz = int(math.floor((qz - oz) / h))
    # past this radius every cell of the grid has been visited
    kmax = max(max(abs(ix), abs(gx - 1 - ix)), max(max(abs(iy), abs(gy - 1 - iy)), max(abs(iz), abs(gz - 1 - iz))))
    k = 0
    while k <= kmax:
        for dx in range(-k, k + 1):
            cx = ix + dx
            if cx < 0 or cx >= gx:
                continue
            wx = _gap(qx, ox + cx * h, h)
            for dy in range(-k, k + 1):
                cy = iy + dy
                if cy < 0 or cy >= gy:
                    continue
                wy = _gap(qy, oy + cy * h, h)
                # only the shell: inside it, dz = -k and +k alone
                dz_step = 1 if (dx == -k or dx == k or dy == -k or dy == k) else max(2 * k, 1)
                for dz in range(-k, k + 1, dz_step):
                    cz = iz + dz
                    if cz < 0 or cz >= gz:
                        continue
                    wz = _gap(qz, oz + cz * h, h)
                    if wx * wx + wy * wy + wz * wz > bd:
                        continue
                    s = cell_slot(table_keys, (cx * gy + cy) * gz + cz, bits)
                    if s < 0:
                        continue
                    j0 = table_starts[s]
                    for j in range(j0, j0 + table_counts[s]):
                        p = order[j]
                        ex = np.float64(qx) - np.float64(points[p, 0])
                        ey = np.float64(qy) - np.float64(points[p, 1])
                        ez = np.float64(qz) - np.float64(points[p, 2])
                        d2 = ex * ex + ey * ey + ez * ez
                        if d2 < bd or (d2 == bd and p < best):
                            bd = d2
                            best = p
        # a point in shell k + 1 or beyond is at least k h from the query (it lies in cell (ix, iy, iz))
        r = k * h
        if bd < r * r:
            break
        k += 1
    return best, bd


@njit(cache=True, parallel=True)
def nearest_on_grid(points, order, table_keys, table_starts, table_counts, bits, origin, h, dims, q, centres,
                    out_idx, out_d2):
    """Exact nearest input point of each query (:func:`grid_nearest_one`), on the CPU.

    Parameters
    ----------
    points, order, table_keys, table_starts, table_counts, bits
        See :func:`grid_nearest_one`.
    origin : (3,) float64
    h : float
    dims : (3,) int64
    q : (Nq, 3) float32
    centres : (Nq,) int64
        A row near each query (its centre): the search starts from it.
    out_idx : (Nq,) int64, out
    out_d2 : (Nq,) float64, out
    """
    for n in prange(q.shape[0]):
        b, d2 = grid_nearest_one(points, order, table_keys, table_starts, table_counts, bits, origin[0], origin[1],
                                 origin[2], h, dims[0], dims[1], dims[2], q[n, 0], q[n, 1], q[n, 2], centres[n])
        out_idx[n] = b
        out_d2[n] = d2
