"""Meshing tiles and welding them into one crack-free mesh.

Each tile meshes only its core cells, from its blended field; every vertex is identified by the global lattice
edge it lies on (an edge key), so two tiles emit the very same key for a crossing on their shared face, and
the merge welds by key: no positional tolerance, no cracks, no duplicate vertices along tile borders.
Faces farther than ``trim_distance`` cells from every input point are trimmed; the distance is absolute and
the same in every tile, and each face is decided by the one tile that owns its cell.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .attributes import interpolate_attributes
from .band import Band, dense_brick_table
from .blend import blend_into
from .bridge import bridged_cells
from .field import Field
from .io.atomic import atomic_path
from .isosurface import extract_mesh
from .kernels import BRICK
from .kernels.band import brick_neighbors
from .kernels.graph import vertex_components
from .memory import peak_rss_mb, reset_peak_rss
from .mesh import Mesh, take_attributes
from .mesh_repair import boundary_edges, small_component_faces
from .nearest import distances_to_cloud
from .partition import read_tile_attributes, read_tile_points
from .tile_field import load_tile_field

__all__ = ["MeshPiece", "trim_faces", "save_piece", "load_piece", "weld_pieces", "drop_small_components"]


@dataclass(eq=False)
class MeshPiece:
    """A tile's part of the mesh.

    Attributes
    ----------
    vertices : (V, 3) float64
        World coordinates.
    faces : (F, 3) int64
    keys : (V,) int64
        Edge key of each vertex (>= 0), or a negative id for vertices private to the piece (loop centres).
    attributes : dict of str to (V,) arrays
        Vertex attributes interpolated from the tile's points (its overlap included), as
        :attr:`~tiled_gridpull.mesh.Mesh.vertex_attributes`.
    """

    vertices: np.ndarray
    faces: np.ndarray
    keys: np.ndarray
    info: dict = field(default_factory=dict)
    attributes: dict = field(default_factory=dict)

    def mesh(self, metadata: dict | None = None) -> Mesh:
        """The piece as a :class:`~tiled_gridpull.mesh.Mesh` (its attributes included)."""
        return Mesh(self.vertices, self.faces, dict(metadata or {}), self.attributes)


def trim_faces(mesh: Mesh, keys: np.ndarray | None, points: np.ndarray, max_distance: float,
               keep_gaps: float = 0.0, ends: np.ndarray | None = None,
               keep: np.ndarray | None = None) -> tuple[Mesh, np.ndarray | None]:
    """Drop faces whose centroid is farther than ``max_distance`` from every point (same units).

    With ``keep_gaps > 0``, a connected region of far faces stays when it is enclosed by kept faces and none of
    its faces is farther than ``keep_gaps`` from the points (``inf``: however deep): a gap between samples, not
    a hole in the data. Random samples leave such gaps (on 100k area-uniform samples of a half-sphere, points
    of the true surface lay up to 4.8 median sample spacings from the nearest sample). Far regions that reach
    the mesh's own boundary (a surface running on past the data's edge to where the field's band ends) or go
    deeper (a hole in the scan) are dropped. ``ends`` (vertex indices) narrows "the mesh's own boundary" to
    those vertices (default: every vertex of a boundary edge).

    Returns the trimmed mesh (unreferenced vertices removed) and the keys of its vertices (None when ``keys``
    is None: a mesh that is not welded to others has none).
    """
    if mesh.n_faces == 0 or max_distance <= 0:
        return mesh, keys
    deep = np.isfinite(keep_gaps)
    d = distances_to_cloud(mesh.vertices[mesh.faces].mean(axis=1), points,
                           max(max_distance, keep_gaps) if deep else max_distance)
    far = ~(np.isfinite(d) & (d <= max_distance))
    if keep is not None:
        far &= ~np.asarray(keep, bool)
    if keep_gaps > 0 and far.any():
        labels, count = vertex_components(mesh.n_vertices, mesh.faces[far])
        drop = np.zeros(count, bool)
        drop[labels[boundary_edges(mesh).reshape(-1) if ends is None else ends]] = True
        region = labels[mesh.faces[far][:, 0]]
        if deep:
            drop[region[~(np.isfinite(d[far]) & (d[far] <= keep_gaps))]] = True
        far[far] = drop[region]
    faces = mesh.faces[~far]
    used, inverse = np.unique(faces, return_inverse=True)
    trimmed = Mesh(mesh.vertices[used], inverse.reshape(-1, 3), dict(mesh.metadata),
                   take_attributes(mesh.vertex_attributes, used))
    return trimmed, (None if keys is None else keys[used])


def save_piece(piece: MeshPiece, path: str | Path) -> None:
    """Write a piece (``.npz``) atomically; each vertex attribute is stored as ``attribute/<name>``."""
    arrays = {f"{_ATTRIBUTE_PREFIX}{name}": values for name, values in piece.attributes.items()}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, vertices=piece.vertices, faces=piece.faces, keys=piece.keys, **arrays)


def load_piece(path: str | Path) -> MeshPiece:
    """Read a piece written by :func:`save_piece` (one of an earlier version has no attributes)."""
    with np.load(path) as z:
        attrs = {name[len(_ATTRIBUTE_PREFIX):]: z[name] for name in z.files if name.startswith(_ATTRIBUTE_PREFIX)}
        return MeshPiece(z["vertices"], z["faces"], z["keys"], attributes=attrs)


_ATTRIBUTE_PREFIX = "attribute/"


def weld_pieces(pieces: list[MeshPiece]) -> Mesh:
    """One mesh from tile pieces, welding vertices that share an edge key.

    Vertices with the same key come from the same lattice edge with bit-identical blended values, so their
    positions agree; the first occurrence is kept, with its attributes (each tile interpolated them from its own
    points, its overlap included, so a shared vertex's values agree up to the float32 rounding of the tiles'
    spill coordinates). Attributes that some piece with vertices lacks are dropped. The faces are the pieces'
    faces, in order.
    """
    verts, faces, keys = [], [], []
    with_vertices = [p for p in pieces if len(p.vertices)]
    names = [n for n in (with_vertices[0].attributes if with_vertices else {})
             if all(n in p.attributes for p in with_vertices)]
    attrs: dict = {n: [] for n in names}
    base = 0
    private = 0
    for p in pieces:
        k = p.keys.copy()
        neg = k < 0
        # private vertices get ids no other piece uses
        k[neg] = -1 - (private + np.arange(int(neg.sum())))
        private += int(neg.sum())
        verts.append(p.vertices)
        for n in names:
            attrs[n].append(p.attributes[n] if len(p.vertices) else np.zeros(0, with_vertices[0].attributes[n].dtype))
        faces.append(p.faces + base)
        keys.append(k)
        base += len(p.vertices)
    if not verts:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    V = np.concatenate(verts)
    F = np.concatenate(faces)
    K = np.concatenate(keys)
    uniq, first, inverse = np.unique(K, return_index=True, return_inverse=True)
    return Mesh(V[first], inverse[F], {}, {n: np.concatenate(parts)[first] for n, parts in attrs.items()})


def drop_small_components(pieces: list[MeshPiece], min_extent: float) -> tuple[list[MeshPiece], int]:
    """Drop, from every tile's piece, the faces of the welded mesh's connected parts that are smaller than
    ``min_extent`` (world units) along every axis: specks, each the bubble of a few stray points.

    Each part is judged whole, across the tiles it spans, so the welded mesh, the tile meshes and the 3D Tiles
    cut from the returned pieces agree, and a part cut by a tile border is never taken for two small ones.

    Returns
    -------
    pieces : list of MeshPiece
        The pieces without those faces (and their vertices), in order; a piece that loses nothing is returned
        as it was.
    removed : int
        How many parts were dropped.
    """
    if min_extent <= 0:
        return list(pieces), 0
    small, removed = small_component_faces(weld_pieces(pieces), min_extent)
    if not removed:
        return list(pieces), 0
    # the welded faces are the pieces' faces in order
    ends = np.cumsum([0] + [len(p.faces) for p in pieces])
    out = []
    for i, p in enumerate(pieces):
        drop = small[ends[i]:ends[i + 1]]
        if not drop.any():
            out.append(p)
            continue
        faces = p.faces[~drop]
        # the kept vertices in their order, renumbered by a running count (np.unique sorted them 10x slower)
        used = np.zeros(len(p.vertices), bool)
        used[faces.reshape(-1)] = True
        new_id = np.cumsum(used) - 1
        keep = np.flatnonzero(used)
        out.append(MeshPiece(p.vertices[keep], new_id[faces].astype(np.int64), p.keys[keep], dict(p.info),
                             take_attributes(p.attributes, keep)))
    return out, removed


def mesh_tile(spec, neighbors: list, tiling, key_ref: np.ndarray, field_path: str | Path,
              piece_path: str | Path) -> dict:
    """Blend a tile's field with its neighbours', mesh its core cells, trim, and write the piece.

    Parameters
    ----------
    spec : TileSpec
    neighbors : list of (TileSpec, field path)
        Solved tiles whose blocks overlap this one.
    tiling : TilingConfig
    key_ref : (3,) int64
        Global vertex index that edge keys are counted from (the same for every tile of a job).
    field_path, piece_path : path
        This tile's field (input) and mesh piece (output).

    Returns
    -------
    dict
        Summary: faces, vertices, trimmed faces, time (``time_s``; ``blend_s`` of it loading and blending fields).
    """
    t0 = time.perf_counter()
    reset_peak_rss()
    O = tiling.overlap_cells
    own = load_tile_field(field_path, spec, O)
    others = [load_tile_field(p, s, O) for s, p in neighbors]
    mesh_lo = np.asarray(spec.mesh_lo, np.int64)
    mesh_hi = np.asarray(spec.mesh_hi, np.int64)
    changed = blend_into(own, others, mesh_lo, mesh_hi)
    t_blend = time.perf_counter()
    block = spec.block
    off = np.asarray(block.offset, np.int64)
    local_bricks = (own.brick_coords - off // BRICK).astype(np.int32)
    bshape = tuple(int(v) for v in -(-np.asarray(block.shape) // BRICK))
    table = dense_brick_table(bshape, local_bricks)
    band = Band(block, 0, 0, local_bricks, table, brick_neighbors(local_bricks, table), own.flags)
    fld = Field(band, own.values)
    mesh, keys = extract_mesh(fld, 0.0, mesh_lo - off, mesh_hi - off, off - np.asarray(key_ref, np.int64),
                              with_keys=True)
    n_raw = mesh.n_faces
    pts = None
    if tiling.trim_distance > 0 and mesh.n_faces:
        xyz, _ = read_tile_points(spec)
        pts = xyz.astype(np.float64) + block.low_corner
        keep = None
        if tiling.bridge > 0:
            centroid = (mesh.vertices[mesh.faces].mean(axis=1) - block.low_corner) / block.cell_size
            keep = bridged_cells(fld, np.floor(centroid).astype(np.int64))
        mesh, keys = trim_faces(mesh, keys, pts, tiling.trim_distance * block.cell_size, keep=keep)
    attrs: dict = {}
    if spec.attributes:
        # from this tile's own points, its overlap included: a vertex on a shared face has the same neighbours
        # in both tiles (the overlap is far wider than a vertex's nearest points are apart)
        if pts is None:
            xyz, _ = read_tile_points(spec)
            pts = xyz.astype(np.float64) + block.low_corner
        attrs = interpolate_attributes(mesh.vertices, pts, read_tile_attributes(spec)) if len(pts) else {}
    save_piece(MeshPiece(mesh.vertices, mesh.faces, keys, attributes=attrs), piece_path)
    return {"tile": spec.name, "faces": mesh.n_faces, "vertices": mesh.n_vertices, "trimmed": n_raw - mesh.n_faces,
            "blended_vertices": changed, "piece_path": str(piece_path), "time_s": time.perf_counter() - t0,
            "blend_s": t_blend - t0,
            "peak_rss_mb": peak_rss_mb()}
