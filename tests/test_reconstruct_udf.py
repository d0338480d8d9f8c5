"""Unsigned fields: signs from oriented local planes give one crack-free sheet ending where the data ends."""

from __future__ import annotations

import numpy as np
import pytest

from tiled_gridpull.band import build_band
from tiled_gridpull.errors import ConfigError
from tiled_gridpull.field import Field
from tiled_gridpull.isosurface import extract_mesh
from tiled_gridpull.lattice import Lattice
from tiled_gridpull.mesh import Mesh
from tiled_gridpull.mesh_repair import boundary_edges, boundary_loops, remove_pinched_fans
from tiled_gridpull.metrics import evaluate, point_to_mesh, sample_surface
from tiled_gridpull.normals import estimate_normals, orient_by_propagation
from tiled_gridpull.udf_sign import sign_unsigned_field
from tiled_gridpull.solver import nearest_point_init
from tiled_gridpull.stitch import trim_faces
from tiled_gridpull.synthetic.shapes import half_sphere, height_field, sample_shape

from conftest import unit_sphere_points


def _one_clean_loop(mesh: Mesh) -> bool:
    """Exactly one boundary loop, and every boundary edge on it (no pinched vertex, no second hole)."""
    loops = boundary_loops(mesh)
    return len(loops) == 1 and len(loops[0]) == len(boundary_edges(mesh))


@pytest.mark.parametrize("make", [half_sphere, height_field], ids=["half_sphere", "terrain"])
def test_signed_distance_to_samples_meshes_without_cracks(make):
    """Per-vertex signs: marching cubes of the signed field is one piece whose only boundary is the band's
    edge, where the sheet runs on past the data (the per-cell gradient signs this replaced cracked)."""
    gt = make()
    pts, _ = sample_shape(gt, 40_000, seed=1)
    lat = Lattice.fit(pts, 96, 4)
    P = lat.to_index(pts)
    band = build_band(P.astype(np.float32), lat, 3, 6)
    unsigned = Field(band, nearest_point_init(band, P), signed=False)
    with pytest.raises(ValueError, match="unsigned field"):
        extract_mesh(unsigned)
    values, info = sign_unsigned_field(band, unsigned.values, P)
    assert info["orientation"] == "propagated" and info["pieces"] == 1
    mesh = extract_mesh(Field(band, values))
    topo = mesh.topology
    assert topo.components == 1 and topo.nonmanifold_edges == 0 and topo.inconsistent_edges == 0
    assert _one_clean_loop(mesh)
    # the part over the data is the sheet, once: no double layer
    near = mesh.submesh(point_to_mesh(mesh.vertices[mesh.faces].mean(axis=1), gt)[0] < 0.5 * lat.cell_size)
    assert 0.97 * gt.area < near.area < 1.05 * gt.area
    s, _ = sample_surface(near, 20_000, seed=2)
    assert point_to_mesh(s, gt)[0].mean() < 0.2 * lat.cell_size


def test_orientation_propagates_over_a_cloud():
    rng = np.random.default_rng(3)
    a = unit_sphere_points(4000, seed=1)
    b = unit_sphere_points(3000, seed=2, radius=0.3) + np.array([3.0, 0.0, 0.0])
    pts = np.concatenate([a, b])
    normals = estimate_normals(pts, 16).astype(np.float64)
    normals *= rng.choice([-1.0, 1.0], size=(len(pts), 1))           # PCA normals: random orientations
    out, pieces = orient_by_propagation(pts, normals)
    assert pieces.max() == 1                                          # two spheres apart: each on its own
    centre = np.where(np.arange(len(pts))[:, None] < len(a), 0.0, np.array([3.0, 0.0, 0.0]))
    radial = np.einsum("ij,ij->i", out, pts - centre)
    assert np.all(radial > 0)                                         # every normal outward
    # a flat patch has no outward: it faces up
    flat = np.column_stack([rng.uniform(-1, 1, (2000, 2)), 0.01 * rng.normal(size=2000)])
    n_flat = np.tile([0.0, 0.0, 1.0], (2000, 1)) * rng.choice([-1.0, 1.0], size=(2000, 1))
    up, _ = orient_by_propagation(flat, n_flat)
    assert np.all(up[:, 2] > 0)
    # a sphere whose equator the scan missed: two caps, bridged into one piece and oriented alike (on their own,
    # each cap would face up, the lower one inward)
    s = unit_sphere_points(6000, seed=4)
    s = s[np.abs(s[:, 2]) > 0.06]
    n_s = estimate_normals(s, 16).astype(np.float64) * rng.choice([-1.0, 1.0], size=(len(s), 1))
    out, pieces = orient_by_propagation(s, n_s)
    assert pieces.max() == 0
    assert np.all(np.einsum("ij,ij->i", out, s) > 0)


def test_trim_keeps_gaps_opens_holes_and_cuts_run_off():
    # a 40 x 40 grid of unit squares; data over x < 30 but for a gap of radius 2.5 at (10, 12) and a hole of
    # radius 7 at (18, 28)
    n = 41
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)])
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + n, i + 1], 1), np.stack([i + 1, i + n, i + n + 1], 1)])
    mesh = Mesh(v, f)
    g = np.mgrid[0:30:0.5, 0:40:0.5].reshape(2, -1).T
    g = g[(np.hypot(g[:, 0] - 10, g[:, 1] - 12) > 2.5) & (np.hypot(g[:, 0] - 18, g[:, 1] - 28) > 7)]
    pts = np.column_stack([g, np.zeros(len(g))])
    plain, _ = trim_faces(mesh, None, pts, 1.0)
    kept, _ = trim_faces(mesh, None, pts, 1.0, keep_gaps=4.0)
    assert len(boundary_loops(plain)) == 3                            # gap, hole and the cut edge
    loops = boundary_loops(kept)
    assert len(loops) == 2 and sum(map(len, loops)) == len(boundary_edges(kept))  # the gap filled
    hole = min(loops, key=len)
    r = np.hypot(kept.vertices[hole, 0] - 18, kept.vertices[hole, 1] - 28)
    assert np.all((r > 7 - 2.5) & (r < 7))                            # the hole opened, up to the reach
    rim = kept.vertices[np.unique(boundary_edges(kept))]
    outer = np.hypot(rim[:, 0] - 18, rim[:, 1] - 28) > 7
    on_grid_border = (rim[:, 0] == 0) | (rim[:, 1] == 0) | (rim[:, 1] == 40)
    assert np.all((on_grid_border | ((rim[:, 0] >= 29.5) & (rim[:, 0] <= 31.0)))[outer])  # run-off cut


def test_pinched_fans_keep_the_larger_fan():
    # a fan of 4 triangles around vertex 0 and a single triangle touching it only at vertex 0
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [-1, 1, 0], [-1, 0, 0], [-1, -1, 0], [0, -2, 0],
                  [1, -2, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5], [0, 7, 8]])
    mesh = Mesh(v, f)
    assert np.bincount(boundary_edges(mesh)[:, 0]).max() == 2       # vertex 0 is pinched
    out, removed = remove_pinched_fans(mesh)
    assert removed == 1 and out.n_faces == 4 and _one_clean_loop(out)


@pytest.mark.parametrize("make", [half_sphere, height_field], ids=["half_sphere", "terrain"])
@pytest.mark.slow
def test_udf_solve_gives_one_open_sheet(make):
    """The whole UDF mode (unsigned solve, signs, signed polish, trim) on an open surface: one sheet, one rim
    where the data ends, more accurate with the polish than without."""
    from tiled_gridpull import reconstruct

    gt = make()
    pts, _ = sample_shape(gt, 30_000, seed=1)
    fast = {"resolution": 64, "iterations": 300, "coarse_iterations": 300}
    mesh = reconstruct(pts, mode="udf", **fast)
    raw = reconstruct(pts, mode="udf", udf_polish=0, **fast)
    cell = mesh.metadata["lattice"]["cell_size"]
    for m in (mesh, raw):
        topo = m.topology
        assert topo.components == 1 and topo.nonmanifold_edges == 0 and topo.inconsistent_edges == 0
        assert _one_clean_loop(m)                                     # open: one rim, no holes, no pinches
        assert 0.97 * gt.area < m.area < 1.5 * gt.area                # the sheet once (a double layer: 2x)
    # the rim is where the data ends: every rim vertex lies within the trim reach of the samples' edge
    rim = mesh.vertices[boundary_loops(mesh)[0]]
    ends = gt.vertices[boundary_edges(gt)]                                  # (B, 2, 3)
    t = np.linspace(0.0, 1.0, 16)[None, :, None]
    gt_rim = (ends[:, :1] * (1 - t) + ends[:, 1:] * t).reshape(-1, 3)      # points along the true rim
    d = np.min(np.linalg.norm(rim[:, None, :] - gt_rim[None, :, :], axis=2), axis=1)
    assert d.max() < 2.5 * cell
    polished = evaluate(mesh, gt, n_samples=20_000, thresholds=(0.01,))
    unpolished = evaluate(raw, gt, n_samples=20_000, thresholds=(0.01,))
    assert polished["chamfer_l1_exact"] < 0.15 * cell
    assert polished["chamfer_l1_exact"] < 0.8 * unpolished["chamfer_l1_exact"]
    assert polished["normal_consistency_exact"] > unpolished["normal_consistency_exact"]
    assert mesh.metadata["solve"]["udf"]["polish_iterations"] == 200


@pytest.mark.slow
def test_udf_sparse_cloud_and_stray_point_stay_one_sheet():
    """A sparse cloud (samples farther apart than a cell) keeps one sheet: the trim reach follows the spacing;
    a lone stray point far from the sheet does not come back as a bubble."""
    from tiled_gridpull import reconstruct

    gt = height_field()
    pts, _ = sample_shape(gt, 800, seed=4)
    pts = np.concatenate([pts, [[0.45, 0.45, 0.4]]])
    mesh = reconstruct(pts, mode="udf", resolution=96, iterations=300, coarse_iterations=300)
    cell = mesh.metadata["lattice"]["cell_size"]
    assert mesh.metadata["noise_estimate"]["spacing"] > 1.2 * cell
    assert mesh.topology.components == 1 and _one_clean_loop(mesh)
    assert mesh.metadata["udf_trim"]["unsupported_pieces_removed"] >= 1
    reach = mesh.metadata["udf_trim"]["reach"]
    assert point_to_mesh(mesh.vertices, gt)[0].max() < reach + cell  # no bubble


@pytest.mark.slow
def test_udf_signs_follow_input_normals():
    """Oriented input normals (``--normals``) orient the sheet, here inward, against what propagation would pick;
    points without a normal follow their neighbours."""
    from tiled_gridpull import reconstruct

    gt = half_sphere()
    pts, nrm = sample_shape(gt, 20_000, seed=5)
    inward = -np.sign(np.einsum("ij,ij->i", nrm, pts))[:, None] * nrm
    inward[::10] = 0.0                                                # no normal for every tenth point
    mesh = reconstruct(pts, normals=inward, normal_weight=1.0, mode="udf", resolution=64, iterations=300,
                       coarse_iterations=300)
    assert mesh.metadata["solve"]["udf"]["orientation"] == "input normals"
    fn, area = mesh.face_normals()
    centres = mesh.vertices[mesh.faces].mean(axis=1)
    assert np.sum(area * np.sign(np.einsum("ij,ij->i", fn, centres))) < -0.99 * area.sum()
    assert mesh.topology.components == 1 and _one_clean_loop(mesh)


def test_tiled_mode_refuses_udf():
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.tiling import check_compatible, TilingConfig

    with pytest.raises(ConfigError, match="mode udf"):
        check_compatible(TilingConfig(voxel_size=0.1), SolverConfig(mode="udf", m2=25))


def test_udf_meshes_an_exactly_planar_patch_as_a_flat_sheet():
    """An open flat surface is data for the unsigned mode (tiled mode meshes a flat parking lot too); it was
    refused as coplanar whatever the mode. The signed mode still refuses it: a plane encloses nothing."""
    from tiled_gridpull import reconstruct
    from tiled_gridpull.errors import InputError

    rng = np.random.default_rng(0)
    # tilted: the sheet must lie in the plane, not in a coordinate plane
    basis = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    origin = np.array([12.0, -40.0, 3.0])
    uv = rng.random((4000, 2)) * 4.0
    pts = np.c_[uv, np.zeros(len(uv))] @ basis.T + origin
    mesh = reconstruct(pts, mode="udf", resolution=40, iterations=150, coarse_iterations=150)
    cell = mesh.metadata["lattice"]["cell_size"]
    topo = mesh.topology
    assert topo.n_faces > 0 and topo.components == 1 and topo.nonmanifold_edges == 0
    assert np.abs((mesh.vertices - origin) @ basis[:, 2]).max() < 0.3 * cell     # in the plane
    assert 0.9 * 16.0 < mesh.area < 1.2 * 16.0                                   # the 4 x 4 patch, once
    with pytest.raises(InputError, match="coplanar"):
        reconstruct(pts, resolution=40, iterations=150, coarse_iterations=150)
