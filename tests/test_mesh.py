"""Mesh conversion to and from trimesh, pyvista and Open3D objects."""

from __future__ import annotations

import importlib
import importlib.util

import numpy as np
import pytest

from tiled_gridpull import _optional
from tiled_gridpull.errors import MissingDependencyError
from tiled_gridpull.mesh import Mesh


def _needs(package: str):
    return pytest.mark.skipif(importlib.util.find_spec(package) is None,
                              reason=f"optional package '{package}' is not installed in this venv")


@pytest.fixture
def octahedron() -> Mesh:
    """A closed, outward-oriented octahedron with georeferenced-size coordinates (float64 precision matters)."""
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
    v = v * 0.37 + np.array([500000.123456789, 4000000.987654321, 100.5])
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return Mesh(v, f)


def _assert_same(a: Mesh, b: Mesh) -> None:
    assert a.vertices.dtype == np.float64 and a.vertices.shape == b.vertices.shape
    assert a.faces.dtype == np.int64 and a.faces.shape == b.faces.shape
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)


@_needs("trimesh")
def test_trimesh_round_trip(octahedron):
    import trimesh
    tm = octahedron.to_trimesh()
    assert isinstance(tm, trimesh.Trimesh)
    assert tm.is_watertight and tm.volume > 0  # orientation kept: outward normals give a positive volume
    _assert_same(Mesh.from_trimesh(tm), octahedron)
    _assert_same(Mesh.from_any(tm), octahedron)


@_needs("trimesh")
def test_trimesh_keeps_duplicate_vertices():
    # process=False: trimesh must not merge the two coincident vertices (face indices would shift)
    m = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0.0]]), np.array([[0, 1, 2], [3, 2, 1]]))
    _assert_same(Mesh.from_trimesh(m.to_trimesh()), m)


@_needs("pyvista")
def test_pyvista_round_trip(octahedron):
    import pyvista as pv
    poly = octahedron.to_pyvista()
    assert isinstance(poly, pv.PolyData) and poly.n_cells == octahedron.n_faces
    _assert_same(Mesh.from_pyvista(poly), octahedron)
    _assert_same(Mesh.from_any(poly), octahedron)


@_needs("pyvista")
def test_pyvista_quads_refused_or_triangulated():
    import pyvista as pv
    cube = pv.Cube()  # six quads
    with pytest.raises(ValueError, match="non-triangle faces.*triangulate=True"):
        Mesh.from_pyvista(cube)
    with pytest.raises(ValueError, match="non-triangle faces"):
        Mesh.from_any(cube)
    m = Mesh.from_pyvista(cube, triangulate=True)
    assert m.n_faces == 12 and m.n_vertices == cube.n_points
    assert m.topology.watertight
    assert m.area == pytest.approx(cube.area)
    assert Mesh.from_any(cube, triangulate=True).n_faces == 12


@_needs("pyvista")
def test_pyvista_non_polydata_refused():
    import pyvista as pv
    grid = pv.ImageData(dimensions=(3, 3, 3))
    with pytest.raises(TypeError, match="pyvista.PolyData"):
        Mesh.from_pyvista(grid)


@_needs("open3d")
def test_open3d_round_trip(octahedron):
    import open3d as o3d
    om = octahedron.to_open3d()
    assert isinstance(om, o3d.geometry.TriangleMesh)
    assert len(om.triangles) == octahedron.n_faces
    _assert_same(Mesh.from_open3d(om), octahedron)
    _assert_same(Mesh.from_any(om), octahedron)


def test_from_any_mesh_is_identity(octahedron):
    assert Mesh.from_any(octahedron) is octahedron


def test_from_any_refuses_unknown_objects():
    with pytest.raises(TypeError, match="cannot convert a builtins.dict"):
        Mesh.from_any({"vertices": [], "faces": []})


@pytest.mark.parametrize("method, package", [("to_trimesh", "trimesh"), ("to_pyvista", "pyvista"),
                                             ("to_open3d", "open3d")])
def test_missing_package_is_one_clear_error(monkeypatch, octahedron, method, package):
    real = importlib.import_module

    def fake_import(name, *args, **kwargs):
        if name == package:
            raise ImportError(f"No module named '{package}'")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(_optional.importlib, "import_module", fake_import)
    with pytest.raises(MissingDependencyError, match=f"Mesh.{method} needs the optional package '{package}'") as e:
        getattr(octahedron, method)()
    assert "\n" not in str(e.value)


def test_missing_pyvista_for_from_pyvista(monkeypatch):
    real = importlib.import_module
    monkeypatch.setattr(_optional.importlib, "import_module",
                        lambda name, *a, **k: (_ for _ in ()).throw(ImportError("nope")) if name == "pyvista"
                        else real(name, *a, **k))
    with pytest.raises(MissingDependencyError, match="Mesh.from_pyvista needs the optional package 'pyvista'"):
        Mesh.from_pyvista(object())
