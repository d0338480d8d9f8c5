"""Relaxing a marching-cubes mesh on its field: fewer slivers, normals closer to the surface's, vertices kept on
the zero level, boundaries kept where they are."""

import numpy as np
import pytest

from tiled_gridpull.band import build_band
from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import ConfigError
from tiled_gridpull.field import Field
from tiled_gridpull.isosurface import extract_mesh, relax_on_field
from tiled_gridpull.lattice import Lattice

CELL = 0.1
CENTRE = np.array([500002.0, 4000002.03, 51.91])  # georeferenced: the field is sampled in the lattice's frame
RADIUS = 1.33


@pytest.fixture(scope="module")
def sphere():
    """The exact signed distance to a sphere on the band around points on it (lattice of 0.1 m cells)."""
    lat = Lattice(tuple(CENTRE - 2.0), CELL, (41, 41, 41))
    n = 4000
    k = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * k / n), np.pi * (1 + 5 ** 0.5) * k
    on = CENTRE + RADIUS * np.c_[np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)]
    band = build_band(lat.to_local32(on).astype(np.float64), lat, m1=3, m2=6)
    world = np.asarray(lat.origin) + band.slot_positions() * CELL
    values = ((np.linalg.norm(world - CENTRE, axis=1) - RADIUS) / CELL).astype(np.float32)
    fld = Field(band, values.reshape(band.n_bricks, -1))
    return fld, extract_mesh(fld)


def _face_normals(v, f):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True), np.linalg.norm(n, axis=1) / 2


def _normal_error(mesh) -> float:
    """Area-weighted mean angle (radians) between the faces' normals and the sphere's at their centroids."""
    n, area = _face_normals(mesh.vertices, mesh.faces)
    c = mesh.vertices[mesh.faces].mean(axis=1) - CENTRE
    cos = np.abs(np.sum(n * c / np.linalg.norm(c, axis=1, keepdims=True), axis=1))
    return float(np.sum(np.arccos(np.clip(cos, -1, 1)) * area) / area.sum())


def _slivers(mesh) -> float:
    """Share of faces with an angle under 15 degrees."""
    v = mesh.vertices[mesh.faces]
    angles = []
    for i in range(3):
        a, b = v[:, (i + 1) % 3] - v[:, i], v[:, (i + 2) % 3] - v[:, i]
        cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return float(np.mean(np.min(angles, axis=0) < 15.0))


def test_relaxing_evens_the_triangles_and_keeps_them_on_the_surface(sphere):
    fld, mesh = sphere
    relaxed = relax_on_field(mesh, fld, 3)
    assert np.array_equal(relaxed.faces, mesh.faces) and relaxed.metadata is mesh.metadata
    assert _slivers(relaxed) < 0.5 * _slivers(mesh)
    assert _normal_error(relaxed) < 0.8 * _normal_error(mesh)
    # on the field's zero level (one Newton step of the trilinear field per iteration), so on the sphere
    value, _ = fld.sample(relaxed.vertices)
    assert np.max(np.abs(value)) < 0.02 * CELL
    # the trilinear field itself misses the sphere inside a cell by at most (h^2 / 8) x the Hessian's trace,
    # 3 h^2 / (8 R) (marching cubes' vertices sit on cell edges, where it is closer)
    radial = np.abs(np.linalg.norm(relaxed.vertices - CENTRE, axis=1) - RADIUS)
    assert radial.max() < 3 * CELL ** 2 / (8 * RADIUS)
    from tiled_gridpull import isosurface

    assert isosurface.TAUBIN_MU < -isosurface.TAUBIN_LAMBDA < 0


class _Field:
    """A stand-in field: ``sample`` answers (value, gradient) from a function of the points."""

    def __init__(self, lattice, sample):
        self.lattice, self.sample = lattice, sample


def test_a_vertex_that_cannot_be_projected_stays(sphere):
    """No value (outside the band), a weak gradient or a long step: the vertex keeps its place rather than drift
    off the surface with the Taubin steps alone."""
    fld, mesh = sphere
    nothing = _Field(fld.lattice, lambda v: (np.full(len(v), np.nan), np.zeros((len(v), 3))))
    assert np.array_equal(relax_on_field(mesh, nothing, 3).vertices, mesh.vertices)

    def weak(v):
        value, grad = fld.sample(v)
        return value, 0.3 * grad  # |grad| 0.3 < MIN_GRADIENT

    assert np.array_equal(relax_on_field(mesh, _Field(fld.lattice, weak), 3).vertices, mesh.vertices)

    def far(v):
        value, grad = fld.sample(v)
        return value + CELL, grad  # every step a whole cell

    assert np.array_equal(relax_on_field(mesh, _Field(fld.lattice, far), 3).vertices, mesh.vertices)


def test_relaxing_never_turns_a_face_over(sphere):
    """A field that pushes each vertex 0.45 cells one way or the other along x (its 'gradient') folds the small
    faces that stand across x; their vertices are put back, and no face ends up facing the other way."""
    fld, mesh = sphere
    sign = np.sign(np.random.default_rng(0).normal(size=mesh.n_vertices))

    def shaky(v):
        return 0.45 * CELL * sign[:len(v)], np.tile([1.0, 0.0, 0.0], (len(v), 1))

    def normals(x):
        f = mesh.faces
        return np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]])

    moved = relax_on_field(mesh, _Field(fld.lattice, shaky), 3)
    assert not np.array_equal(moved.vertices, mesh.vertices)
    assert np.all(np.einsum("ij,ij->i", normals(moved.vertices), normals(mesh.vertices)) > 0)


def test_reconstruct_relaxes_signed_meshes_only():
    """One-shape sdf mode relaxes and says so; relax 0 is the marching-cubes mesh; tiled mode refuses the setting
    (its meshes are not relaxed) unless it is the default."""
    from tiled_gridpull import reconstruct
    from tiled_gridpull.synthetic import sample_shape, sphere as sphere_shape
    from tiled_gridpull.tiling import TilingConfig, check_compatible

    pts, _ = sample_shape(sphere_shape(), 4000, seed=0)
    small = dict(resolution=40, levels=1, iterations=60, queries=4000, min_component_cells=0)
    plain = reconstruct(pts, relax=0, **small)
    relaxed = reconstruct(pts, relax=3, **small)
    assert plain.metadata["relaxed"] == 0 and relaxed.metadata["relaxed"] == 3
    assert np.array_equal(plain.faces, relaxed.faces) and not np.array_equal(plain.vertices, relaxed.vertices)
    assert relaxed.metadata["config"]["relax"] == 3
    check_compatible(TilingConfig(voxel_size=0.1), SolverConfig())
    with pytest.raises(ConfigError, match="relax applies to one-shape mode"):
        check_compatible(TilingConfig(voxel_size=0.1), SolverConfig(relax=0))


def test_zero_iterations_and_boundaries_stay(sphere):
    fld, mesh = sphere
    assert relax_on_field(mesh, fld, 0) is mesh
    # an open cap: its boundary ring does not move, its inside does
    centroid = mesh.vertices[mesh.faces].mean(axis=1)
    cap = mesh.submesh(centroid[:, 2] > CENTRE[2] + 0.5)
    from tiled_gridpull.mesh_repair import boundary_edges

    ring = np.unique(boundary_edges(cap))
    moved = relax_on_field(cap, fld, 3)
    assert len(ring) > 10
    assert np.array_equal(moved.vertices[ring], cap.vertices[ring])
    inside = np.setdiff1d(np.unique(cap.faces), ring)
    assert np.mean(np.any(moved.vertices[inside] != cap.vertices[inside], axis=1)) > 0.9


def test_relax_setting():
    assert SolverConfig().relax == 3 and SolverConfig(relax=0).relax == 0
    with pytest.raises(ConfigError, match="relax"):
        SolverConfig(relax=-1)
    with pytest.raises(ConfigError, match="relax"):
        SolverConfig(relax=1.5)
    with pytest.raises(ConfigError, match="relax must be at most 100"):
        SolverConfig(relax=10 ** 9)
