"""Flood fill of free cells from the border of a small dense grid (inside/outside of closed shapes)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _face_neighbor(x, y, z, d, X, Y, Z):
    """Face neighbour ``d`` (0..5: -x, +x, -y, +y, -z, +z) of cell (x, y, z) and whether it lies in the grid."""
    nx, ny, nz = x, y, z
    if d == 0:
        nx -= 1
    elif d == 1:
        nx += 1
    elif d == 2:
        ny -= 1
    elif d == 3:
        ny += 1
    elif d == 4:
        nz -= 1
    else:
        nz += 1
    return nx, ny, nz, 0 <= nx < X and 0 <= ny < Y and 0 <= nz < Z


@njit(cache=True)
def flood_from_border(free):
    """Cells of ``free`` (X, Y, Z) uint8 reachable from the grid's border through free cells (6-connected).

    Returns
    -------
    (X, Y, Z) uint8, 1 where reached.
    """
    X, Y, Z = free.shape
    reached = np.zeros_like(free)
    queue = np.empty((X * Y * Z, 3), np.int32)
    head = 0
    tail = 0
    for x in range(X):
        for y in range(Y):
            for z in range(Z):
                if (x == 0 or y == 0 or z == 0 or x == X - 1 or y == Y - 1 or z == Z - 1) and free[x, y, z]:
                    reached[x, y, z] = 1
                    queue[tail, 0] = x
                    queue[tail, 1] = y
                    queue[tail, 2] = z
                    tail += 1
    while head < tail:
        x, y, z = queue[head, 0], queue[head, 1], queue[head, 2]
        head += 1
        for d in range(6):
            nx, ny, nz, inside = _face_neighbor(x, y, z, d, X, Y, Z)
            if not inside:
                continue
            if free[nx, ny, nz] and not reached[nx, ny, nz]:
                reached[nx, ny, nz] = 1
                queue[tail, 0] = nx
                queue[tail, 1] = ny
                queue[tail, 2] = nz
                tail += 1
    return reached


@njit(cache=True)
def spread_labels(labels, rounds):
    """Give unlabelled (0) cells the label of a labelled face neighbour, ``rounds`` times (outside wins ties)."""
    X, Y, Z = labels.shape
    cur = labels.copy()
    for _ in range(rounds):
        nxt = cur.copy()
        changed = False
        for x in range(X):
            for y in range(Y):
                for z in range(Z):
                    if cur[x, y, z] != 0:
                        continue
                    best = 0
                    for d in range(6):
                        nx, ny, nz, inside = _face_neighbor(x, y, z, d, X, Y, Z)
                        if not inside:
                            continue
                        lab = cur[nx, ny, nz]
                        if lab > best or (best == 0 and lab != 0):
                            best = lab
                    if best != 0:
                        nxt[x, y, z] = best
                        changed = True
        cur = nxt
        if not changed:
            break
    return cur
