"""Unsigned-field extraction: per-cell pseudo-signs from gradients give one open sheet, no double layer."""

from __future__ import annotations

import numpy as np
import pytest

from tiled_gridpull.lattice import Lattice
from tiled_gridpull.mesh import extract_mesh
from tiled_gridpull.metrics import point_to_mesh, sample_surface
from tiled_gridpull.band import build_band
from tiled_gridpull.field import Field
from tiled_gridpull.solver import nearest_point_init
from tiled_gridpull.synthetic.shapes import half_sphere, height_field, sample_shape


@pytest.mark.parametrize("make", [half_sphere, height_field], ids=["half_sphere", "terrain"])
def test_unsigned_distance_field_meshes_as_one_open_sheet(make):
    gt = make()
    pts, _ = sample_shape(gt, 40_000, seed=1)
    lat = Lattice.fit(pts, 96, 4)
    P = lat.to_index(pts).astype(np.float32)
    band = build_band(P, lat, 3, 6)
    # the distance to the samples is an unsigned field of the sheet (up to the sampling density)
    fld = Field(band, nearest_point_init(band, P), signed=False)
    mesh = extract_mesh(fld)
    topo = mesh.topology
    labels = mesh.components()
    largest = mesh.submesh(labels == np.bincount(labels).argmax())
    # one sheet: the largest piece covers the surface, the whole mesh is not a closed double layer around it
    assert largest.area > 0.95 * gt.area
    assert mesh.area < 1.1 * gt.area, f"area {mesh.area / gt.area:.2f} x GT: a double layer"
    assert topo.boundary_edges > 0 and not topo.watertight     # open where the data ends
    assert topo.inconsistent_edges == 0 and topo.nonmanifold_edges == 0
    cell = lat.cell_size
    s, _ = sample_surface(mesh, 20_000, seed=2)
    d, _ = point_to_mesh(s, gt)
    assert d.mean() < 0.2 * cell
    # the signed extraction of the same field finds no zero crossing at all (it never changes sign)
    assert extract_mesh(fld, unsigned=False).n_faces == 0


@pytest.mark.parametrize("make", [half_sphere, height_field], ids=["half_sphere", "terrain"])
def test_udf_solve_gives_one_open_sheet(make):
    """The whole UDF solve (pull, TV, weak surface loss, no gradient loss) on an open surface."""
    from tiled_gridpull import reconstruct

    gt = make()
    pts, _ = sample_shape(gt, 30_000, seed=1)
    mesh = reconstruct(pts, mode="udf", resolution=64, iterations=300, coarse_iterations=300)
    topo = mesh.topology
    labels = mesh.components()
    largest = mesh.submesh(labels == np.bincount(labels).argmax())
    assert largest.area > 0.9 * gt.area                  # the sheet is there (beta = 1 kept 2 % of it)
    assert mesh.area < 1.1 * gt.area                      # and not twice (no closed double layer)
    assert topo.boundary_edges > 0 and topo.nonmanifold_edges == 0 and topo.inconsistent_edges == 0
    s, _ = sample_surface(mesh, 20_000, seed=2)
    d, _ = point_to_mesh(s, gt)
    assert d.mean() < 0.25 * mesh.metadata["lattice"]["cell_size"]
