"""Triangle meshes: the container, its conversions to other libraries, and topology facts.

Vertices are float64 in the input's world coordinates; faces are int64 indices, counter-clockwise seen from
outside (normals point towards larger field values, i.e. out of a closed shape).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ._optional import require
from .cloud import colors_of
from .kernels import graph as kg

__all__ = ["Mesh", "MeshTopology", "edge_groups", "take_attributes", "COLOR_CHANNELS", "color_full_scale",
           "colors_unit"]

#: The vertex attributes that hold a colour, in order (see :attr:`Mesh.vertex_attributes`).
COLOR_CHANNELS = ("red", "green", "blue")


def take_attributes(attributes: dict, idx) -> dict:
    """The rows ``idx`` (index array, boolean mask or slice) of every per-vertex array of ``attributes``.

    The one helper every operation that subsets, reorders or duplicates vertices uses to keep
    :attr:`Mesh.vertex_attributes` aligned with ``vertices``.
    """
    return {k: np.asarray(v)[idx] for k, v in attributes.items()}


def color_full_scale(attributes: dict) -> float | None:
    """The value of full intensity of the colour channels of ``attributes`` (None: they have no colour).

    uint8 channels: 255. uint16 channels: 65535, except when no value exceeds 255 -- 8-bit colour stored in
    LAS's 16-bit fields, as many files (Autzen among them) do although the LAS specification asks for 16-bit
    values -- then 255. Float channels: 1. Used only to show colours (conversions, pictures): the stored values
    are never rescaled.
    """
    if not all(c in attributes for c in COLOR_CHANNELS):
        return None
    rgb = [np.asarray(attributes[c]) for c in COLOR_CHANNELS]
    if np.issubdtype(rgb[0].dtype, np.floating):
        return 1.0
    if rgb[0].dtype == np.uint8:
        return 255.0
    top = max((int(c.max()) for c in rgb if c.size), default=0)
    return 255.0 if top <= 255 else 65535.0


def colors_unit(attributes: dict) -> np.ndarray | None:
    """The colour channels of ``attributes`` as (V, 3) float64 in [0, 1] (:func:`color_full_scale`), or None."""
    scale = color_full_scale(attributes)
    if scale is None:
        return None
    rgb = np.column_stack([np.asarray(attributes[c], dtype=np.float64) for c in COLOR_CHANNELS])
    return np.clip(rgb / scale, 0.0, 1.0)


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
    vertex_attributes : dict of str to (V,) arrays
        Per-vertex values interpolated from the input points (empty when the input had none, or with
        ``attributes="none"``), row ``i`` belonging to ``vertices[i]``:

        - ``red``, ``green``, ``blue``: (V,) in the input's own type and bit depth, never rescaled: uint16 from
          LAS/LAZ (the format's type; many files hold 8-bit values in it, see :func:`color_full_scale`),
          uint8 or uint16 from PLY as its properties are declared;
        - ``intensity``: (V,) float32, or the input's integer type (uint16 from LAS/LAZ);
        - ``classification``: (V,) uint8 (the ASPRS class codes; a vertex takes its neighbours' majority);
        - LAS extra dimensions under their own names, in their own type.

        Every operation that subsets, reorders or adds vertices keeps them aligned (:func:`take_attributes`).
    """

    vertices: np.ndarray
    faces: np.ndarray
    metadata: dict = field(default_factory=dict)
    vertex_attributes: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)
        attrs = {}
        for name, values in (self.vertex_attributes or {}).items():
            values = np.ascontiguousarray(values)
            if values.ndim != 1 or len(values) != len(self.vertices):
                raise ValueError(f"Mesh: vertex attribute {name!r} has shape {values.shape}, expected "
                                 f"({len(self.vertices)},)")
            attrs[str(name)] = values
        self.vertex_attributes = attrs

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
        directed, order, starts, counts = edge_groups(F, self.n_vertices)
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

    def submesh(self, face_mask: np.ndarray) -> Mesh:
        """Mesh of the selected faces, unreferenced vertices dropped."""
        faces = self.faces[face_mask]
        used, inverse = np.unique(faces, return_inverse=True)
        return Mesh(self.vertices[used], inverse.reshape(-1, 3), dict(self.metadata),
                    take_attributes(self.vertex_attributes, used))

    def with_vertex_attributes(self, attributes: dict) -> Mesh:
        """The same mesh (vertices and faces shared, metadata copied) carrying ``attributes`` (name to (V,))."""
        return Mesh(self.vertices, self.faces, dict(self.metadata), attributes)

    # ------------------------------------------------------------------ conversions
    def to_pyvista(self):
        """The mesh as a :class:`pyvista.PolyData` (needs pyvista).

        Returns
        -------
        pyvista.PolyData
            ``points`` (V, 3) float64 world coordinates and ``regular_faces`` (F, 3) int64, in this mesh's
            order; every vertex attribute as a point-data array of its name, and the colours as ``"RGB"``
            (V, 3) uint8 (scaled by :func:`color_full_scale`) when the mesh has them.
        """
        pv = require("pyvista", "Mesh.to_pyvista")
        poly = pv.PolyData.from_regular_faces(self.vertices, self.faces)
        for name, values in self.vertex_attributes.items():
            poly.point_data[name] = values
        rgb = colors_unit(self.vertex_attributes)
        if rgb is not None:
            # what ``plot(scalars="RGB", rgb=True)`` shows
            poly.point_data["RGB"] = np.round(rgb * 255).astype(np.uint8)
        return poly

    def to_trimesh(self):
        """The mesh as a :class:`trimesh.Trimesh` (needs trimesh).

        Returns
        -------
        trimesh.Trimesh
            ``vertices`` (V, 3) float64 world coordinates and ``faces`` (F, 3) int64, in this mesh's order:
            built with ``process=False`` so trimesh neither merges vertices nor drops faces. Colours become
            ``visual.vertex_colors`` (V, 4) uint8 (scaled by :func:`color_full_scale`, alpha 255); every vertex
            attribute is in ``vertex_attributes`` under its name, as stored.
        """
        tm = require("trimesh", "Mesh.to_trimesh")
        rgb = colors_unit(self.vertex_attributes)
        colors = None
        if rgb is not None:
            colors = np.full((self.n_vertices, 4), 255, np.uint8)
            colors[:, :3] = np.round(rgb * 255).astype(np.uint8)
        attrs = {k: v.copy() for k, v in self.vertex_attributes.items()}
        return tm.Trimesh(vertices=self.vertices.copy(), faces=self.faces.copy(), process=False,
                          vertex_colors=colors, vertex_attributes=attrs)

    def to_open3d(self):
        """The mesh as an :class:`open3d.geometry.TriangleMesh` (needs open3d).

        Returns
        -------
        open3d.geometry.TriangleMesh
            ``vertices`` (V, 3) float64 world coordinates and ``triangles`` (F, 3) int32 (Open3D's index
            type), in this mesh's order; ``vertex_colors`` (V, 3) float64 in [0, 1] (scaled by
            :func:`color_full_scale`) when the mesh has colours. Open3D's mesh has no place for the other
            attributes.
        """
        o3d = require("open3d", "Mesh.to_open3d")
        out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices),
                                        o3d.utility.Vector3iVector(self.faces.astype(np.int32)))
        rgb = colors_unit(self.vertex_attributes)
        if rgb is not None:
            out.vertex_colors = o3d.utility.Vector3dVector(rgb)
        return out

    @classmethod
    def from_trimesh(cls, mesh) -> Mesh:
        """A mesh from a :class:`trimesh.Trimesh` (vertices and faces copied as they are).

        Parameters
        ----------
        mesh : trimesh.Trimesh
            ``vertices`` (V, 3) and ``faces`` (F, 3).

        Returns
        -------
        Mesh
            ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64; per-vertex colours (``visual.vertex_colors``)
            as ``red``, ``green``, ``blue`` uint8 vertex attributes.
        """
        return cls(np.array(mesh.vertices, dtype=np.float64), np.array(mesh.faces, dtype=np.int64), {},
                   colors_of(mesh))

    @classmethod
    def from_pyvista(cls, poly, *, triangulate: bool = False) -> Mesh:
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
            ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64; colour, intensity and classification point
            arrays (:func:`~tiled_gridpull.cloud.colors_of`) as vertex attributes.

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
        return cls(np.array(poly.points, dtype=np.float64), np.array(faces, dtype=np.int64), {}, colors_of(poly))

    @classmethod
    def from_open3d(cls, mesh) -> Mesh:
        """A mesh from an :class:`open3d.geometry.TriangleMesh`.

        Parameters
        ----------
        mesh : open3d.geometry.TriangleMesh
            ``vertices`` (V, 3) and ``triangles`` (F, 3).

        Returns
        -------
        Mesh
            ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64; ``vertex_colors`` (floats in [0, 1]) as
            ``red``, ``green``, ``blue`` uint8 vertex attributes.
        """
        attrs = {}
        if mesh.has_vertex_colors():
            rgb = np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255.0), 0, 255).astype(np.uint8)
            attrs = {c: np.ascontiguousarray(rgb[:, i]) for i, c in enumerate(("red", "green", "blue"))}
        return cls(np.asarray(mesh.vertices, dtype=np.float64).copy(),
                   np.asarray(mesh.triangles, dtype=np.int64).copy(), {}, attrs)

    @classmethod
    def from_any(cls, obj, *, triangulate: bool = False) -> Mesh:
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


def edge_groups(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
