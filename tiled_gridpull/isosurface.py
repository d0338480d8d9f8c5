"""Marching cubes over the optimized cells of a field: the surface as a :class:`~tiled_gridpull.mesh.Mesh`."""

from __future__ import annotations

import numpy as np

from .field import Field
from .kernels import mc as kmc
from .mesh import Mesh, edge_groups

__all__ = ["extract_mesh", "relax_on_field", "TAUBIN_LAMBDA", "TAUBIN_MU"]

T_CLAMP = 1e-3  # keep crossings off the lattice vertices so no triangle collapses to zero area
#: Taubin's smoothing and inflating steps (lambda | mu | slightly above lambda keeps the volume: Taubin 1995)
TAUBIN_LAMBDA = 0.5
TAUBIN_MU = -0.53
#: relaxation: a vertex is projected back onto the zero level only where the field's gradient is at least this
#: long (a distance field's is about 1) and the Newton step at most ``MAX_PROJECTION`` cells; elsewhere it stays
MIN_GRADIENT = 0.5
MAX_PROJECTION = 0.5


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


def relax_on_field(mesh: Mesh, fld: Field, iterations: int) -> Mesh:
    """Even out a marching-cubes mesh's triangles while keeping its vertices on the field's zero level.

    Marching cubes puts a vertex where the zero level crosses a cell edge, so its triangles are slivers and
    fans whose flat faces tilt against the surface they stand for. Each iteration moves every vertex by a
    Taubin step (``TAUBIN_LAMBDA`` toward the mean of its neighbours, then ``TAUBIN_MU`` away from it: smoothing
    without shrinking) and then back onto the zero level of ``fld`` along its gradient (one Newton step of the
    trilinear field). Vertices on a boundary edge stay where they are, and so does a vertex that cannot be
    projected (its cell outside the band, a gradient shorter than ``MIN_GRADIENT``, a step longer than
    ``MAX_PROJECTION`` cells) and every vertex of a face that the move would turn over. Measured on the shared
    meshes: docs/solver.md, "Relaxing the mesh on the field".

    Parameters
    ----------
    mesh : Mesh
        Extracted from ``fld`` (world units).
    fld : Field
        A signed field.
    iterations : int
        0 returns ``mesh`` unchanged.

    Returns
    -------
    Mesh
        Same faces, moved vertices, ``mesh.metadata`` kept.
    """
    if iterations <= 0 or mesh.n_faces == 0:
        return mesh
    faces = mesh.faces
    # each undirected edge once: an interior edge appears in two faces, once in each direction
    directed, order, starts, counts = edge_groups(faces, mesh.n_vertices)
    first = directed[order[starts]]
    i, j = first[:, 0], first[:, 1]
    n = mesh.n_vertices
    degree = np.bincount(i, minlength=n) + np.bincount(j, minlength=n)
    pinned = np.zeros(n, bool)
    pinned[directed[order[starts[counts == 1]]].ravel()] = True
    pinned |= degree == 0
    free = ~pinned
    v = mesh.vertices.astype(np.float64, copy=True)
    cell = fld.lattice.cell_size
    facing = _normals(v, faces)  # every face must keep facing the way it did in the extracted mesh
    for _ in range(int(iterations)):
        old = v.copy()
        for weight in (TAUBIN_LAMBDA, TAUBIN_MU):
            total = np.zeros_like(v)
            for axis in range(3):
                total[:, axis] = (np.bincount(i, weights=v[j, axis], minlength=n)
                                  + np.bincount(j, weights=v[i, axis], minlength=n))
            step = total[free] / degree[free, None] - v[free]
            v[free] += weight * step
        value, grad = fld.sample(v[free])
        norm2 = np.einsum("ij,ij->i", grad, grad)
        # a distance field's gradient is near unit length; where it is weak (a fold of the field, the band's
        # edge) the Newton step is long and unreliable, and the vertex keeps its place instead
        ok = np.isfinite(value) & (norm2 >= MIN_GRADIENT ** 2)
        newton = np.zeros_like(grad)
        newton[ok] = (value[ok] / norm2[ok])[:, None] * grad[ok]  # world units: the gradient is unitless
        ok &= np.linalg.norm(newton, axis=1) <= MAX_PROJECTION * cell
        moved = v[free]
        moved[ok] -= newton[ok]
        moved[~ok] = old[free][~ok]
        v[free] = moved
        _undo_folds(v, old, faces, facing)
    return Mesh(v, faces, mesh.metadata, mesh.vertex_attributes)


def _normals(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    return np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])


def _undo_folds(v: np.ndarray, old: np.ndarray, faces: np.ndarray, facing: np.ndarray) -> None:
    """Put back (in place) the vertices of faces that would face against ``facing`` (their normals in the extracted
    mesh), until none does; ``old`` (the positions before this move) has none. Relaxing evens out triangles, it
    must not fold them."""
    valid = np.einsum("ij,ij->i", facing, facing) > 0.0  # a face degenerate from the start cannot turn over
    for _ in range(8):
        flipped = valid & (np.einsum("ij,ij->i", _normals(v, faces), facing) <= 0.0)
        if not flipped.any():
            return
        back = np.unique(faces[flipped])
        v[back] = old[back]
    v[:] = old  # pragma: no cover - each pass puts back more vertices; eight passes have always sufficed
