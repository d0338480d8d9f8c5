"""Boundary loops and the closing of holes a signed solve leaves at its band's edge."""

from __future__ import annotations

import numpy as np
import pytest

from tiled_gridpull.mesh import Mesh
from tiled_gridpull.mesh_repair import boundary_loops, close_holes
from tiled_gridpull.metrics import sample_surface
from tiled_gridpull.nearest import distances_to_cloud
from tiled_gridpull.reconstruct import _band_edge_loops, _end_signed_mesh, _trim_band_edge_sheets

# unit cube, outward-oriented, two triangles per side: -x, +x, -y, +y, -z, +z
CUBE_V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)
CUBE_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                   [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.int64)


def open_cube(offset=(0.0, 0.0, 0.0), drop=(10, 11)) -> Mesh:
    keep = np.setdiff1d(np.arange(12), drop)
    return Mesh(CUBE_V + np.asarray(offset), CUBE_F[keep])


def test_cube_is_closed_and_outward():
    cube = Mesh(CUBE_V, CUBE_F)
    assert cube.topology.watertight and cube.signed_volume() > 0.99


@pytest.mark.parametrize("scale", [1e-150, 1e110, 1e150])
def test_orientation_sign_survives_extents_past_float_cubes(scale):
    """The one-shape driver flips a mesh whose signed volume is negative: at 1e110 the triple products overflow
    (inf - inf = NaN, never < 0), so an inside-out mesh was kept as it was."""
    with np.errstate(all="raise"):
        out = Mesh(CUBE_V * scale, CUBE_F)
        inv = Mesh(CUBE_V * scale, CUBE_F[:, ::-1])
        assert out.signed_volume(normalized=True) > 0 > inv.signed_volume(normalized=True)
        if scale > 1:
            assert out.signed_volume() == np.inf and inv.signed_volume() == -np.inf
        else:
            assert out.signed_volume() == 0.0  # 1e-450 underflows: hence the normalized sign


def test_loops_of_a_cube_missing_two_sides():
    mesh = open_cube(drop=(0, 1, 2, 3))  # the -x and +x sides
    loops = boundary_loops(mesh)
    assert sorted(len(loop) for loop in loops) == [4, 4]
    assert {frozenset(loop.tolist()) for loop in loops} == {frozenset({0, 1, 2, 3}), frozenset({4, 5, 6, 7})}
    closed = close_holes(mesh, loops)
    topo = closed.topology
    assert topo.boundary_edges == 0 and topo.inconsistent_edges == 0 and topo.nonmanifold_edges == 0
    assert closed.n_vertices == 8 + 2
    assert abs(closed.signed_volume() - 1.0) < 1e-12  # fans over planar squares add the missing sides exactly
    assert closed.is_manifold_solid()


def test_no_loops_on_a_closed_mesh():
    assert boundary_loops(Mesh(CUBE_V, CUBE_F)) == []


def test_only_holes_away_from_the_data_are_closed():
    near = open_cube()                        # its hole (the +z side) is where the samples are
    far = open_cube(offset=(10.0, 0.0, 0.0))  # a sheet that ran away from the data
    both = Mesh(np.vstack([near.vertices, far.vertices]), np.vstack([near.faces, far.faces + 8]))
    pts, _ = sample_surface(Mesh(CUBE_V, CUBE_F), 5000, seed=0)
    shift = np.array([500000.0, 4000000.0, 100.0])  # georeferenced: distances must stay exact
    moved = Mesh(both.vertices + shift, both.faces)
    loops = _band_edge_loops(moved, pts + shift, min_distance=0.5)
    assert len(loops) == 1
    out = close_holes(moved, loops)
    assert out.topology.boundary_edges == 4      # the hole next to the data stays open
    far_part = out.submesh(out.components() == out.components()[-1])
    assert far_part.topology.watertight


def tube(length=10.0, radius=1.0, n_theta=64, n_z=100) -> Mesh:
    """An open cylinder along z from 0 to ``length`` (both ends open)."""
    t = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    z = np.linspace(0, length, n_z + 1)
    T, Z = np.meshgrid(t, z, indexing="ij")
    verts = np.stack([radius * np.cos(T), radius * np.sin(T), Z], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_theta), np.arange(n_z), indexing="ij")
    a = i * (n_z + 1) + j
    b = ((i + 1) % n_theta) * (n_z + 1) + j
    faces = np.concatenate([np.stack([a, b, b + 1], -1).reshape(-1, 3), np.stack([a, b + 1, a + 1], -1).reshape(-1, 3)])
    return Mesh(verts, faces)


def test_sheets_that_end_at_the_band_edge_are_cut_back_to_the_data():
    """A sheet that leaves the data and stops at the band's edge (a cap over a bore) is cut back to ``reach``;
    a far patch enclosed by supported faces (a gap in the samples) and the rim next to the data stay."""
    mesh = tube()
    pts, _ = sample_surface(mesh, 40_000, seed=0)
    angle = np.arctan2(pts[:, 1], pts[:, 0])
    gap = (pts[:, 2] > 2.0) & (pts[:, 2] < 3.5) & (np.abs(angle) < 0.8)  # a patch without samples
    pts = pts[(pts[:, 2] <= 6.0) & ~gap]
    shift = np.array([500000.0, 4000000.0, 100.0])
    reach = 0.3
    moved = Mesh(mesh.vertices + shift, mesh.faces)
    loops = _band_edge_loops(moved, pts + shift, reach)
    assert len(loops) == 1  # the far end; the near rim at z = 0 is the data's edge
    out, on_cut = _trim_band_edge_sheets(moved, pts + shift, reach, loops)
    n = mesh.n_faces - out.n_faces
    assert np.abs(out.vertices[on_cut, 2] - shift[2] - 6.0 - reach).max() < 0.15  # the cut's edge
    v = out.vertices - shift
    centres = v[out.faces].mean(axis=1)
    assert n > 0
    assert 6.0 + reach - 0.1 <= v[:, 2].max() <= 6.0 + reach + 0.1  # the far end went, back to the reach
    assert v[:, 2].min() == 0.0                                      # the rim next to the data stays

    def in_gap(c):
        return (c[:, 2] > 2.6) & (c[:, 2] < 2.9) & (np.abs(np.arctan2(c[:, 1], c[:, 0])) < 0.2)

    before = mesh.vertices[mesh.faces].mean(axis=1)
    assert distances_to_cloud(before[in_gap(before)], pts).min() > reach  # far from the data, yet enclosed
    assert in_gap(centres).sum() == in_gap(before).sum() > 0
    assert len(boundary_loops(out)) == 2
    # samples over the whole tube: no loop ends away from the data
    assert _band_edge_loops(moved, sample_surface(mesh, 40_000, seed=1)[0] + shift, reach) == []


def grid_sheet(n: int, size: float = 1.0) -> Mesh:
    """A flat square sheet in z = 0 from (0, 0) to (size, size), n x n squares, normals +z."""
    g = np.linspace(0.0, size, n + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    verts = np.stack([X, Y, np.zeros_like(X)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    faces = np.concatenate([np.stack([a, a + n + 1, a + n + 2], 1), np.stack([a, a + n + 2, a + 1], 1)])
    return Mesh(verts, faces)


def open_box(n: int = 20) -> Mesh:
    """A unit cube without its bottom, faces inward (inside out), each side an n x n grid."""
    sheet = grid_sheet(n)
    v, f = sheet.vertices, sheet.faces
    u, w = v[:, 0], v[:, 1]
    zero, one = np.zeros_like(u), np.ones_like(u)
    # each side mapped so that (d/du x d/dw) is its outward normal
    sides = [np.stack([u, w, one], 1),                            # top, +z
             np.stack([u, zero, w], 1), np.stack([w, one, u], 1),  # -y, +y
             np.stack([zero, w, u], 1), np.stack([one, u, w], 1)]  # -x, +x
    verts = np.concatenate(sides)
    faces = np.concatenate([f + k * len(v) for k in range(len(sides))])
    uniq, inverse = np.unique(np.round(verts, 9), axis=0, return_inverse=True)
    return Mesh(uniq, inverse.reshape(-1)[faces][:, ::-1].copy())  # welded, then turned inside out


def test_orientation_is_judged_on_the_sealed_mesh():
    """An inside-out box open at the bottom, sampled only in the middle of its top: cut back, only a flat patch is
    left, whose own signed volume is 0 and says nothing; sealed, the box is closed and inside out, so the patch
    must come out facing up."""
    box = open_box()
    assert box.topology.boundary_edges > 0 and box.signed_volume() < 0
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0.3, 0.7, (3000, 2)), np.ones(3000)])
    out, flipped, rec = _end_signed_mesh(box, pts, 0.1, 0.1, "trim")
    assert flipped and rec["loops"] == 1 and rec["faces_trimmed"] > 0
    normals, _ = out.face_normals()
    assert abs(out.signed_volume()) < 1e-12                 # flat: its own volume cannot tell
    assert np.all(normals[:, 2] > 0.99)                     # facing up, as the sealed box says
    kept, flipped_kept, rec_kept = _end_signed_mesh(box, pts, 0.1, 0.1, "keep")
    assert flipped_kept and rec_kept["faces_trimmed"] == 0 and kept.n_faces == box.n_faces


def test_islands_the_cut_leaves_around_stray_samples_go():
    """A sheet sampled densely in its middle and at three stray points near its corners: cut back, it leaves
    discs around the strays, which go; a piece the cut never touched stays, however few points it has."""
    sheet = grid_sheet(100, 10.0)
    cube = Mesh(CUBE_V * 0.5 + [2.0, 2.0, 5.0], CUBE_F)  # closed, no sample near it
    mesh = Mesh(np.vstack([sheet.vertices, cube.vertices]), np.vstack([sheet.faces, cube.faces + sheet.n_vertices]))
    rng = np.random.default_rng(0)
    dense = np.column_stack([rng.uniform(4.0, 6.0, (5000, 2)), np.zeros(5000)])
    strays = np.array([[1.0, 1.0, 0.0], [9.0, 9.0, 0.0], [1.0, 9.0, 0.0]])
    pts = np.vstack([dense, strays])
    out, _, rec = _end_signed_mesh(mesh, pts, 0.3, 0.3, "trim")
    assert rec["unsupported_pieces_removed"] == 3
    assert out.topology.components == 2                     # the middle patch and the untouched cube
    assert np.isclose(out.vertices[:, 2].max(), 5.5)
