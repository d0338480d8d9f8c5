"""Graphs: connected pieces of triangle meshes (union-find over vertices), orientation along trees."""

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


@njit(cache=True)
def propagate_flips(order, parent, normals, root):
    """Flip flags that orient every normal like its parent in a spanning forest.

    Parameters
    ----------
    order : (M,) int64
        Nodes in breadth-first order (every parent before its children), starting with ``root``.
    parent : (N + 1,) int64
        Parent of each node; children of ``root`` (a virtual node holding the forest's roots) keep their sign.
    normals : (N, 3) float64
    root : int

    Returns
    -------
    flip : (N,) bool
        Nodes not in ``order`` stay unflipped.
    """
    n = normals.shape[0]
    flip = np.zeros(n + 1, np.bool_)
    for t in range(1, order.shape[0]):
        i = order[t]
        p = parent[i]
        if p == root or p < 0:
            continue
        dot = normals[i, 0] * normals[p, 0] + normals[i, 1] * normals[p, 1] + normals[i, 2] * normals[p, 2]
        # the raw normals: a child ends flipped when its parent does, or (exclusively) when the two disagree
        flip[i] = flip[p] ^ (dot < 0.0)
    return flip[:n]
