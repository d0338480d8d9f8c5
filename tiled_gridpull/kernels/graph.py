"""Connectivity of triangle meshes (union-find over vertices)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _find(parent, i):
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:
        nxt = parent[i]
        parent[i] = root
        i = nxt
    return root


@njit(cache=True)
def vertex_components(n_vertices, faces):
    """Component label (0..k-1, by first appearance) of every vertex, joined through faces.

    Returns
    -------
    labels : (n_vertices,) int64
        Unreferenced vertices get their own component.
    k : int
    """
    parent = np.arange(n_vertices)
    for f in range(faces.shape[0]):
        a = _find(parent, faces[f, 0])
        for c in range(1, 3):
            b = _find(parent, faces[f, c])
            if a != b:
                if a < b:
                    parent[b] = a
                else:
                    parent[a] = b
                    a = b
    labels = np.full(n_vertices, -1, np.int64)
    k = 0
    for i in range(n_vertices):
        r = _find(parent, i)
        if labels[r] < 0:
            labels[r] = k
            k += 1
        labels[i] = labels[r]
    return labels, k
