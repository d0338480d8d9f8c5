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


@njit(cache=True)
def orient_faces(faces, edge_faces, edge_same):
    """Flip flags that make face orientation consistent across manifold edges, component by component.

    Parameters
    ----------
    faces : (F, 3) int64
    edge_faces : (E, 2) int64
        The two faces of every manifold edge.
    edge_same : (E,) bool
        True when both faces traverse the edge in the same direction (they disagree unless one is flipped).

    Returns
    -------
    flip : (F,) bool
        Breadth-first from the lowest face of each component, which keeps its orientation. Where the faces around
        a loop cannot be oriented (a Moebius-like patch), the first assignment wins.
    """
    nf = faces.shape[0]
    ne = edge_faces.shape[0]
    deg = np.zeros(nf + 1, np.int64)
    for e in range(ne):
        deg[edge_faces[e, 0] + 1] += 1
        deg[edge_faces[e, 1] + 1] += 1
    for f in range(nf):
        deg[f + 1] += deg[f]
    fill = deg[:-1].copy()
    adj = np.empty(deg[nf], np.int64)
    adj_same = np.empty(deg[nf], np.bool_)
    for e in range(ne):
        a = edge_faces[e, 0]
        b = edge_faces[e, 1]
        adj[fill[a]] = b
        adj_same[fill[a]] = edge_same[e]
        fill[a] += 1
        adj[fill[b]] = a
        adj_same[fill[b]] = edge_same[e]
        fill[b] += 1
    flip = np.zeros(nf, np.bool_)
    seen = np.zeros(nf, np.bool_)
    queue = np.empty(nf, np.int64)
    for start in range(nf):
        if seen[start]:
            continue
        seen[start] = True
        head = 0
        tail = 1
        queue[0] = start
        while head < tail:
            f = queue[head]
            head += 1
            for t in range(deg[f], deg[f + 1]):
                g = adj[t]
                if seen[g]:
                    continue
                seen[g] = True
                flip[g] = flip[f] ^ adj_same[t]
                queue[tail] = g
                tail += 1
    return flip
