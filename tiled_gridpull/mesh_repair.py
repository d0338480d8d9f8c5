"""Mesh boundaries and cleanup: small components, pinched fans, boundary edges and loops, hole closing."""

from __future__ import annotations

import numpy as np

from .attributes import mean_attributes
from .kernels import graph as kg
from .mesh import Mesh, edge_groups

__all__ = ["remove_small_components", "small_component_faces", "component_boxes", "remove_pinched_fans",
           "boundary_edges", "boundary_loops", "close_holes"]


def remove_small_components(mesh: Mesh, min_extent: float) -> tuple[Mesh, int]:
    """Drop connected pieces whose bounding box is smaller than ``min_extent`` along every axis.

    Returns
    -------
    mesh : Mesh
        The kept faces (metadata copied).
    removed : int
        Number of pieces dropped.
    """
    small, removed = small_component_faces(mesh, min_extent)
    if not removed:
        return mesh, 0
    return mesh.submesh(~small), removed


def small_component_faces(mesh: Mesh, min_extent: float) -> tuple[np.ndarray, int]:
    """Which faces lie on connected pieces whose bounding box is smaller than ``min_extent`` along every axis.

    Returns
    -------
    small : (F,) bool
        True on the faces of such pieces.
    pieces : int
        How many pieces that is.
    """
    if mesh.n_faces == 0:
        return np.zeros(0, bool), 0
    labels, lo, hi = component_boxes(mesh)
    small = np.isfinite(lo[:, 0]) & np.all(hi - lo < min_extent, axis=1)
    return small[labels[mesh.faces[:, 0]]], int(small.sum())


def component_boxes(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each connected piece's bounding box.

    Returns
    -------
    labels : (V,) int64
        Piece of every vertex (unreferenced vertices are pieces of their own).
    lo, hi : (P, 3) float64
        Box corners of each piece, by label; +inf / -inf for a label without faces.
    """
    labels, _ = kg.vertex_components(mesh.n_vertices, mesh.faces)
    n = int(labels.max()) + 1 if len(labels) else 0
    lo, hi = np.full((n, 3), np.inf), np.full((n, 3), -np.inf)
    if mesh.n_faces == 0:
        return labels, lo, hi
    # grouped by sorting (ufunc.at over every face's corners cost 0.5 s a million faces, most of a tiled job's merge)
    used = np.zeros(mesh.n_vertices, bool)
    used[mesh.faces.reshape(-1)] = True
    part = labels[used]
    order = np.argsort(part, kind="stable")
    part = part[order]
    xyz = mesh.vertices[used][order]
    starts = np.flatnonzero(np.r_[True, part[1:] != part[:-1]])
    lo[part[starts]] = np.minimum.reduceat(xyz, starts, axis=0)
    hi[part[starts]] = np.maximum.reduceat(xyz, starts, axis=0)
    return labels, lo, hi


def remove_pinched_fans(mesh: Mesh, max_rounds: int = 4) -> tuple[Mesh, int]:
    """Unpinch the boundary: where the boundary passes through a vertex more than once (the faces around it form
    several fans joined only at that vertex), keep the fan with the most faces.

    Trimming faces one by one leaves such pinches along a cut edge. Removing a fan can pinch another vertex,
    so this repeats, at most ``max_rounds`` times (pinches left after that stay). Vertices where closed fans
    touch (no boundary through them) are not looked at: trimming does not make them.

    Returns
    -------
    mesh : Mesh
    removed : int
        Faces dropped.
    """
    removed = 0
    for _ in range(max_rounds):
        edges = boundary_edges(mesh)
        pinched = np.flatnonzero(np.bincount(edges[:, 0], minlength=mesh.n_vertices) > 1)
        if len(pinched) == 0:
            break
        F = mesh.faces
        drop = np.zeros(len(F), bool)
        incident = np.argsort(F.reshape(-1), kind="stable")
        first = np.searchsorted(F.reshape(-1)[incident], pinched)
        last = np.searchsorted(F.reshape(-1)[incident], pinched, side="right")
        for v, a, b in zip(pinched, first, last):
            around = incident[a:b] // 3
            # faces around v are joined when they share a spoke (an edge through v): fans = connected spokes
            spokes = F[around][F[around] != v].reshape(-1, 2)
            names, pair = np.unique(spokes, return_inverse=True)
            pair = pair.reshape(-1, 2)
            labels, _ = kg.vertex_components(len(names), np.c_[pair, pair[:, :1]])
            fan = labels[pair[:, 0]]
            drop[around[fan != np.bincount(fan).argmax()]] = True
        removed += int(drop.sum())
        mesh = mesh.submesh(~drop)
    return mesh, removed


def boundary_edges(mesh: Mesh) -> np.ndarray:
    """Edges used by one face only, (B, 2) int64 vertex ids, each in its face's direction."""
    if mesh.n_faces == 0:
        return np.zeros((0, 2), np.int64)
    directed, order, starts, counts = edge_groups(mesh.faces, mesh.n_vertices)
    return directed[order[starts[counts == 1]]]


def boundary_loops(mesh: Mesh) -> list[np.ndarray]:
    """Closed boundary loops of a mesh, each an (n,) int64 array of vertex ids in the order of its faces'
    boundary edges. Loops through a vertex with more than one outgoing boundary edge (a pinch) are skipped."""
    edges = boundary_edges(mesh)
    if len(edges) == 0:
        return []
    out_deg = np.bincount(edges[:, 0], minlength=mesh.n_vertices)
    nxt = np.full(mesh.n_vertices, -1, np.int64)
    nxt[edges[:, 0]] = edges[:, 1]
    seen = np.zeros(mesh.n_vertices, bool)
    loops = []
    for start in edges[:, 0]:
        if seen[start]:
            continue
        loop, v, ok = [], int(start), True
        while not seen[v]:
            seen[v] = True
            loop.append(v)
            ok &= out_deg[v] == 1
            v = int(nxt[v])
            if v < 0:
                ok = False
                break
        if ok and v == start and len(loop) >= 3:
            loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def close_holes(mesh: Mesh, loops: list[np.ndarray]) -> Mesh:
    """Close each boundary loop with a fan of triangles around the loop's centroid (one new vertex per loop).

    The fan runs every boundary edge ``a -> b`` the other way (``b, a, centre``), so it continues the
    orientation of the faces around the hole.
    """
    if not loops:
        return mesh
    verts = [mesh.vertices]
    faces = [mesh.faces]
    attrs = {name: [values] for name, values in mesh.vertex_attributes.items()}
    n = mesh.n_vertices
    for k, loop in enumerate(loops):
        verts.append(mesh.vertices[loop].mean(axis=0, keepdims=True))
        centre = np.full(len(loop), n + k, np.int64)
        faces.append(np.stack([np.roll(loop, -1), loop, centre], axis=1))
        # the centre's attributes: the loop's mean (its most common class)
        for name, value in mean_attributes(mesh.vertex_attributes, loop).items():
            attrs[name].append(value)
    return Mesh(np.concatenate(verts), np.concatenate(faces), dict(mesh.metadata),
                {name: np.concatenate(parts) for name, parts in attrs.items()})
