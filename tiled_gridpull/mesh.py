"""Triangle meshes: the container, marching cubes over a field, and topology facts.

Vertices are float64 in the input's world coordinates; faces are int64 indices, counter-clockwise seen from
outside (normals point towards larger field values, i.e. out of a closed shape).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ._optional import require
from .field import Field
from .kernels import graph as kg
from .kernels import mc as kmc

__all__ = ["Mesh", "extract_mesh", "MeshTopology", "remove_small_components", "boundary_edges",
           "boundary_loops", "close_holes", "remove_pinched_fans"]

T_CLAMP = 1e-3  # keep crossings off the lattice vertices so no triangle collapses to zero area


@dataclass(frozen=True)
class MeshTopology:
    """Facts about a mesh's connectivity."""

    n_vertices: int
    n_faces: int
    n_edges: int
    boundary_edges: int
    nonmanifold_edges: int
    inconsistent_edges: int
    components: int
    euler: int

    @property
    def watertight(self) -> bool:
        """Every edge has exactly two faces, oriented oppositely (closed, oriented 2-manifold edges)."""
        return self.n_faces > 0 and self.boundary_edges == 0 and self.nonmanifold_edges == 0 \
            and self.inconsistent_edges == 0

    def to_dict(self) -> dict:
        """Plain dict, ``watertight`` included."""
        d = dict(self.__dict__)
        d["watertight"] = self.watertight
        return d


@dataclass(eq=False)
class Mesh:
    """A triangle mesh.

    Attributes
    ----------
    vertices : (V, 3) float64
        World coordinates.
    faces : (F, 3) int64
    metadata : dict
        Provenance (config, lattice, version, timings), written beside the mesh.
    """

    vertices: np.ndarray
    faces: np.ndarray
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)

    @property
    def n_vertices(self) -> int:
        return int(len(self.vertices))

    @property
    def n_faces(self) -> int:
        return int(len(self.faces))

    def __repr__(self) -> str:
        return f"Mesh({self.n_vertices} vertices, {self.n_faces} faces)"

    # ------------------------------------------------------------------ geometry
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) float64 corner positions."""
        return self.vertices[self.faces]

    def face_normals(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit face normals (F, 3) and face areas (F,)."""
        tri = self.triangles()
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(cross, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            n = cross / norm[:, None]
        n[norm == 0] = 0.0
        return n, 0.5 * norm

    @property
    def area(self) -> float:
        """Total surface area (world units squared)."""
        return float(self.face_normals()[1].sum())

    def signed_volume(self, *, normalized: bool = False) -> float:
        """Signed enclosed volume (positive for a closed mesh with outward normals).

        ``normalized``: the volume of the mesh scaled to a largest centred coordinate of 1, whose sign is
        the orientation at any extent (a mesh 1e-150 across has a volume that underflows to 0, one 1e110
        across one that overflows to inf)."""
        if not self.n_faces:
            return 0.0
        # centred first: with georeferenced coordinates the triple products would cancel catastrophically;
        # scaled to unit extent: cubes of extents past 1e102 overflow, and inf - inf would make the sign NaN
        centred = self.vertices - self.vertices.mean(axis=0)
        scale = float(np.abs(centred).max()) or 1.0
        tri = (centred / scale)[self.faces]
        unit = float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)
        if normalized:
            return unit
        with np.errstate(over="ignore", under="ignore"):
            return float(np.float64(unit) * np.float64(scale) ** 3)

    # ------------------------------------------------------------------ topology
    @cached_property
    def topology(self) -> MeshTopology:
        """Edge and component counts (computed once)."""
        F = self.faces
        if len(F) == 0:
            return MeshTopology(self.n_vertices, 0, 0, 0, 0, 0, 0, self.n_vertices)
        directed, order, starts, counts = _edge_groups(F, self.n_vertices)
        forward = (directed[:, 0] < directed[:, 1])[order]
        fwd_count = np.add.reduceat(forward.astype(np.int64), starts)
        n_edges = len(starts)
        boundary = int(np.count_nonzero(counts == 1))
        nonmanifold = int(np.count_nonzero(counts > 2))
        inconsistent = int(np.count_nonzero((counts == 2) & (fwd_count != 1)))
        used = np.unique(F)
        labels, _ = kg.vertex_components(self.n_vertices, F)
        components = int(len(np.unique(labels[used])))
        euler = int(len(used) - n_edges + len(F))
        return MeshTopology(self.n_vertices, len(F), n_edges, boundary, nonmanifold, inconsistent, components,
                            euler)

    def components(self) -> np.ndarray:
        """Component label of every face (F,) int64."""
        labels, _ = kg.vertex_components(self.n_vertices, self.faces)
        return labels[self.faces[:, 0]]

    def submesh(self, face_mask: np.ndarray) -> "Mesh":
        """Mesh of the selected faces, unreferenced vertices dropped."""
        faces = self.faces[face_mask]
        used, inverse = np.unique(faces, return_inverse=True)
        return Mesh(self.vertices[used], inverse.reshape(-1, 3), dict(self.metadata))

    # ------------------------------------------------------------------ conversions
    def to_pyvista(self):
        """The mesh as a :class:`pyvista.PolyData` (needs pyvista).

        Returns
        -------
        pyvista.PolyData
            ``points`` (V, 3) float64 world coordinates and ``regular_faces`` (F, 3) int64, in this mesh's
            order.
        """
        pv = require("pyvista", "Mesh.to_pyvista")
        return pv.PolyData.from_regular_faces(self.vertices, self.faces)

    def to_trimesh(self):
        """The mesh as a :class:`trimesh.Trimesh` (needs trimesh).

        Returns
        -------
        trimesh.Trimesh
            ``vertices`` (V, 3) float64 world coordinates and ``faces`` (F, 3) int64, in this mesh's order:
            built with ``process=False`` so trimesh neither merges vertices nor drops faces.
        """
        tm = require("trimesh", "Mesh.to_trimesh")
        return tm.Trimesh(vertices=self.vertices.copy(), faces=self.faces.copy(), process=False)

    def to_open3d(self):
        """The mesh as an :class:`open3d.geometry.TriangleMesh` (needs open3d).

        Returns
        -------
        open3d.geometry.TriangleMesh
            ``vertices`` (V, 3) float64 world coordinates and ``triangles`` (F, 3) int32 (Open3D's index
            type), in this mesh's order.
        """
        o3d = require("open3d", "Mesh.to_open3d")
        return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices),
                                         o3d.utility.Vector3iVector(self.faces.astype(np.int32)))

    @classmethod
    def from_trimesh(cls, mesh) -> "Mesh":
        """A mesh from a :class:`trimesh.Trimesh` (vertices and faces copied as they are).

        Parameters
        ----------
        mesh : trimesh.Trimesh
            ``vertices`` (V, 3) and ``faces`` (F, 3).

        Returns
        -------
        Mesh
            ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64.
        """
        return cls(np.array(mesh.vertices, dtype=np.float64), np.array(mesh.faces, dtype=np.int64))

    @classmethod
    def from_pyvista(cls, poly, *, triangulate: bool = False) -> "Mesh":
        """A mesh from a :class:`pyvista.PolyData` (needs pyvista).

        Parameters
        ----------
        poly : pyvista.PolyData
            ``points`` (V, 3) and its polygon and strip cells; vertex and line cells are ignored.
        triangulate : bool
            Split quads, polygons and strips into triangles with pyvista's ``triangulate()``. Without it a
            polydata holding anything but triangles is refused, so a caller never gets a silently re-cut
            surface.

        Returns
        -------
        Mesh
            ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64.

        Raises
        ------
        TypeError
            ``poly`` is not a ``pyvista.PolyData``.
        ValueError
            ``poly`` has non-triangle faces and ``triangulate`` is false.
        """
        pv = require("pyvista", "Mesh.from_pyvista")
        if not isinstance(poly, pv.PolyData):
            raise TypeError(f"Mesh.from_pyvista needs a pyvista.PolyData, got {type(poly).__name__} "
                            "(call .extract_surface() first)")
        has_polys = poly.faces.size > 0
        if has_polys and not poly.is_all_triangles or poly.n_strips:
            if not triangulate:
                raise ValueError("Mesh.from_pyvista: the polydata has non-triangle faces (quads, polygons or "
                                 "strips); pass triangulate=True to split them into triangles")
            poly = poly.triangulate()
            has_polys = poly.faces.size > 0
        faces = poly.regular_faces if has_polys else np.empty((0, 3), dtype=np.int64)
        return cls(np.array(poly.points, dtype=np.float64), np.array(faces, dtype=np.int64))

    @classmethod
    def from_open3d(cls, mesh) -> "Mesh":
        """A mesh from an :class:`open3d.geometry.TriangleMesh`.

        Parameters
        ----------
        mesh : open3d.geometry.TriangleMesh
            ``vertices`` (V, 3) and ``triangles`` (F, 3).

        Returns
        -------
        Mesh
            ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64.
        """
        return cls(np.asarray(mesh.vertices, dtype=np.float64).copy(),
                   np.asarray(mesh.triangles, dtype=np.int64).copy())

    @classmethod
    def from_any(cls, obj, *, triangulate: bool = False) -> "Mesh":
        """A mesh from a trimesh, pyvista or Open3D triangle mesh, told apart by the object's package.

        Parameters
        ----------
        obj : trimesh.Trimesh, pyvista.PolyData, open3d.geometry.TriangleMesh or Mesh
            The mesh to convert; a :class:`Mesh` is returned as it is.
        triangulate : bool
            Passed to :meth:`from_pyvista` for pyvista input.

        Returns
        -------
        Mesh

        Raises
        ------
        TypeError
            ``obj`` is none of the above.
        """
        if isinstance(obj, cls):
            return obj
        package = type(obj).__module__.split(".")[0]
        if package == "trimesh":
            return cls.from_trimesh(obj)
        if package == "pyvista":
            return cls.from_pyvista(obj, triangulate=triangulate)
        if package == "open3d" and hasattr(obj, "triangles"):
            return cls.from_open3d(obj)
        raise TypeError(f"Mesh.from_any: cannot convert a {type(obj).__module__}.{type(obj).__name__} "
                        "(expected trimesh.Trimesh, pyvista.PolyData or open3d.geometry.TriangleMesh)")

    def is_manifold_solid(self) -> bool:
        """Whether manifold3d accepts the mesh as a closed, oriented 2-manifold (needs manifold3d)."""
        m3d = require("manifold3d", "Mesh.is_manifold_solid")
        if self.n_faces == 0:
            return False
        mesh = m3d.Mesh64(vert_properties=np.ascontiguousarray(self.vertices, dtype=np.float64),
                          tri_verts=np.ascontiguousarray(self.faces, dtype=np.uint64))
        solid = m3d.Manifold(mesh)
        return solid.status() == m3d.Error.NoError and not solid.is_empty()


def extract_mesh(fld: Field, iso: float = 0.0, cell_lo: np.ndarray | None = None,
                 cell_hi: np.ndarray | None = None, key_offset: np.ndarray | None = None,
                 with_keys: bool = False):
    """Marching cubes over the optimized cells of a field.

    Parameters
    ----------
    fld : Field
    iso : float
        Iso level in cells (0 for the surface).
    cell_lo, cell_hi : (3,) int, optional
        Only cells with lowest corner in ``[cell_lo, cell_hi)`` (block index) are meshed (a tile's core).
    key_offset : (3,) int, optional
        Added to block vertex indices to form edge keys (a tile's offset from the job lattice) so that keys
        from different tiles agree.
    with_keys : bool
        Also return the edge key of every vertex (for welding tiles).

    Returns
    -------
    Mesh, or (Mesh, keys) with ``keys`` (V,) int64
    """
    if not fld.signed:
        raise ValueError("an unsigned field has no zero crossings to mesh: sign it first "
                         "(tiled_gridpull.udf_sign.sign_unsigned_field)")
    band = fld.band
    lat = band.lattice
    lo = np.zeros(3, np.int64) if cell_lo is None else np.asarray(cell_lo, np.int64)
    hi = np.asarray(lat.n_cells, np.int64) if cell_hi is None else np.asarray(cell_hi, np.int64)
    koff = np.zeros(3, np.int64) if key_offset is None else np.asarray(key_offset, np.int64)
    top = koff + np.asarray(lat.shape, np.int64)
    if np.any(koff < 0) or top[0] >= 2 ** kmc.KEY_BITS_X or top[1] >= 2 ** kmc.KEY_BITS_Y \
            or top[2] >= 2 ** kmc.KEY_BITS_Z:
        raise ValueError("lattice too large for 64-bit edge keys (2^21 x 2^21 x 2^19 vertices)")
    values = fld.values.reshape(-1)
    flags = band.flags.reshape(-1)
    iso32 = np.float32(iso)
    counts = kmc.count_triangles(values, flags, band.brick_table, band.brick_coords, lo, hi, iso32)
    offsets = np.zeros((len(counts) + 1, 2), np.int64)
    np.cumsum(counts, axis=0, out=offsets[1:])
    tris = np.empty((int(offsets[-1, 0]), 3), np.int64)
    centres = np.empty((int(offsets[-1, 1]), 3), np.float64)
    kmc.emit_triangles(values, flags, band.brick_table, band.brick_coords, lo, hi, iso32, offsets, koff, tris,
                       centres)
    keys, inverse = np.unique(tris, return_inverse=True)
    faces = inverse.reshape(-1, 3)
    pts = np.empty((len(keys), 3), np.float64)
    is_centre = keys < 0
    pts[is_centre] = centres[-1 - keys[is_centre]]
    pts[~is_centre] = kmc.edge_points(values, band.brick_table, keys[~is_centre], koff, float(iso), T_CLAMP)
    mesh = Mesh(lat.to_world(pts), faces)
    return (mesh, keys) if with_keys else mesh


def _edge_groups(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The faces' directed edges grouped by undirected edge.

    Returns
    -------
    directed : (3F, 2) int64
        Edges (a, b) of faces 0..F-1, then their (b, c), then their (c, a).
    order : (3F,) int64
        Directed edges sorted by undirected edge (stable).
    starts, counts : (E,) int64
        Where each undirected edge's run begins in ``order`` and how many faces use it.
    """
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = directed.min(axis=1) * np.int64(n_vertices) + directed.max(axis=1)
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    starts = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
    counts = np.diff(np.r_[starts, len(key_sorted)])
    return directed, order, starts, counts


def remove_small_components(mesh: Mesh, min_extent: float) -> tuple[Mesh, int]:
    """Drop connected pieces whose bounding box is smaller than ``min_extent`` along every axis.

    Returns
    -------
    mesh : Mesh
        The kept faces (metadata copied).
    removed : int
        Number of pieces dropped.
    """
    labels = mesh.components()
    if len(labels) == 0:
        return mesh, 0
    n = int(labels.max()) + 1
    tri = mesh.vertices[mesh.faces]
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    np.minimum.at(lo, labels, tri.min(axis=1))
    np.maximum.at(hi, labels, tri.max(axis=1))
    present = np.isfinite(lo[:, 0])
    small = present & np.all(hi - lo < min_extent, axis=1)
    if not small.any():
        return mesh, 0
    return mesh.submesh(~small[labels]), int(small.sum())


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
    directed, order, starts, counts = _edge_groups(mesh.faces, mesh.n_vertices)
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
    n = mesh.n_vertices
    for k, loop in enumerate(loops):
        verts.append(mesh.vertices[loop].mean(axis=0, keepdims=True))
        centre = np.full(len(loop), n + k, np.int64)
        faces.append(np.stack([np.roll(loop, -1), loop, centre], axis=1))
    return Mesh(np.concatenate(verts), np.concatenate(faces), dict(mesh.metadata))
