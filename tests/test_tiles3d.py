"""OGC 3D Tiles output (``--3d-tiles``): every glb parses, bounding volumes hold their vertices, the finest tiles
add up to the written mesh, coarser levels carry their measured deviation, the georeferencing agrees with a direct
pyproj transform, vertex attributes become COLOR_0 and EXT_structural_metadata property attributes, and VTK's
3D Tiles reader (vtkCesium3DTilesReader, from the vtk wheel on PyPI) opens the tileset at every level and draws it
off-screen; Debian's gltfpack (cgltf's validator) loads every glb when it is installed."""

import json
import os

import numpy as np
import pytest
from conftest import terrain

pytest.importorskip("pygltflib")
pytest.importorskip("fast_simplification")
pyproj = pytest.importorskip("pyproj")

from tiled_gridpull.config import SolverConfig  # noqa: E402
from tiled_gridpull.errors import ConfigError  # noqa: E402
from tiled_gridpull.io import read_mesh  # noqa: E402
from tiled_gridpull.mesh import Mesh  # noqa: E402
from tiled_gridpull.pipeline.cli import main  # noqa: E402
from tiled_gridpull.tiled_job import reconstruct_scene  # noqa: E402
from tiled_gridpull.tiles3d import TileMesh, georeference, read_glb, write_tileset  # noqa: E402
from tiled_gridpull.tiling import TilingConfig  # noqa: E402

SOLVER = SolverConfig(m2=8, refine_m2=6, coarse_iterations=100, iterations=100, queries=20000)
TILING = TilingConfig(voxel_size=0.2, tile_size=3.2, overlap=1.6, trim_distance=2.0)
UTM = "EPSG:32632"


def _nodes(node, depth=0, parent=None):
    """Every node of a tileset's tree with its depth and parent."""
    yield node, depth, parent
    for child in node.get("children", []):
        yield from _nodes(child, depth + 1, node)


def _box_contains(box, pts, tol=1e-9):
    c = np.asarray(box[:3])
    axes = np.asarray(box[3:]).reshape(3, 3)
    half = np.linalg.norm(axes, axis=1)
    u = (pts - c) @ (axes / half[:, None]).T  # coordinates along the box's unit axes
    return np.all(np.abs(u) <= half + tol, axis=1)


def _leaves(doc):
    return [n for n, _, _ in _nodes(doc["root"]) if not n.get("children")]


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """A 4 x 4-tile job of a UTM-like ground patch, written with its tileset (two coarser levels)."""
    d = tmp_path_factory.mktemp("tiles3d")
    np.save(d / "g.npy", terrain(12.8, 40, seed=3))
    mesh = reconstruct_scene([str(d / "g.npy")], d / "m.ply", TILING, SOLVER, d / "job", tiles3d=d / "tiles",
                             tiles3d_crs=UTM)
    doc = json.loads((d / "tiles" / "tileset.json").read_text())
    return d, mesh, doc


def test_every_glb_parses_and_every_file_is_referenced(job):
    d, _, doc = job
    uris = [n["content"]["uri"] for n, _, _ in _nodes(doc["root"]) if "content" in n]
    on_disk = sorted(str(p.relative_to(d / "tiles")) for p in (d / "tiles").rglob("*.glb"))
    assert sorted(uris) == on_disk and len(set(uris)) == len(uris)
    assert len([u for u in uris if u.startswith("tiles/")]) == 16
    for uri in uris:
        g = read_glb(d / "tiles" / uri)
        pos, faces = g["positions"], g["faces"]
        assert len(faces) > 0 and faces.min() >= 0 and faces.max() < len(pos)
        assert np.isfinite(pos).all()
        n = g["attributes"]["NORMAL"].astype(np.float64)
        assert np.abs(np.linalg.norm(n, axis=1) - 1).max() < 1e-5  # unit normals, as glTF requires
        acc = g["gltf"].accessors[g["gltf"].meshes[0].primitives[0].attributes.POSITION]
        raw = g["attributes"]["POSITION"]
        assert np.allclose(acc.min, raw.min(axis=0)) and np.allclose(acc.max, raw.max(axis=0))
        assert g["gltf"].asset.generator.startswith("tiled_gridpull")


def test_bounding_volumes_contain_their_vertices_and_children(job):
    d, _, doc = job
    for node, _, parent in _nodes(doc["root"]):
        box = node["boundingVolume"]["box"]
        if "content" in node:
            pos = read_glb(d / "tiles" / node["content"]["uri"])["positions"]
            assert _box_contains(box, pos).all(), node["content"]["uri"]
        if parent is not None:  # a child's box lies inside its parent's (its eight corners do)
            c, axes = np.asarray(box[:3]), np.asarray(box[3:]).reshape(3, 3)
            corners = c + np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) @ axes
            assert _box_contains(parent["boundingVolume"]["box"], corners, tol=1e-6).all()


def test_union_of_the_finest_tiles_is_the_written_mesh(job):
    d, mesh, doc = job
    written = read_mesh(d / "m.ply")
    geo = georeference(UTM, np.zeros(3))  # any origin: only its inverse transform is used below
    root = np.asarray(doc["root"]["transform"]).reshape(4, 4).T  # column-major -> row-major
    verts, n_faces = [], 0
    for leaf in _leaves(doc):
        g = read_glb(d / "tiles" / leaf["content"]["uri"])
        ecef = g["positions"] @ root[:3, :3].T + root[:3, 3]
        verts.append(geo.from_local((ecef - geo.origin) @ geo.rotation))
        n_faces += len(g["faces"])
    allv = np.concatenate(verts)
    assert n_faces == written.n_faces == mesh.n_faces
    # tiles share their border vertices: welding them by position gives the mesh's vertex set
    uniq = np.unique(np.round(allv / 1e-4).astype(np.int64), axis=0)
    assert len(uniq) == written.n_vertices
    from pykdtree.kdtree import KDTree

    d1, _ = KDTree(allv).query(written.vertices, k=1)
    d2, _ = KDTree(written.vertices).query(allv, k=1)
    assert max(d1.max(), d2.max()) < 1e-4  # float32 positions about each tile's centre, pyproj both ways


def test_coarser_levels_are_smaller_and_their_error_is_measured(job):
    d, mesh, doc = job
    levels = doc["extras"]["tiled_gridpull"]["per_level"]
    assert [lv["nodes"] for lv in levels] == [16, 4, 1]
    assert levels[2]["faces"] < levels[1]["faces"] < levels[0]["faces"] == mesh.n_faces
    assert doc["geometricError"] >= doc["root"]["geometricError"] > 0
    assert all(0 <= lv["deviation_p99"] <= lv["geometric_error"] for lv in levels)
    for node, _, parent in _nodes(doc["root"]):
        if not node.get("children"):
            assert node["geometricError"] == 0
        if parent is not None:
            assert parent["geometricError"] >= node["geometricError"]
    # the root's error bounds the distance of every finest vertex from the root's coarse surface
    from tiled_gridpull.metrics import point_to_mesh

    coarse = read_glb(d / "tiles" / doc["root"]["content"]["uri"])
    fine = np.concatenate([read_glb(d / "tiles" / leaf["content"]["uri"])["positions"] for leaf in _leaves(doc)])
    dist, _ = point_to_mesh(fine, Mesh(coarse["positions"], coarse["faces"]))
    assert dist.max() <= doc["root"]["geometricError"] + 1e-4
    assert doc["root"]["geometricError"] < 2.0  # metres, on a patch 12.8 m across with 0.4 m waves


def test_georeferencing_matches_a_direct_pyproj_transform(job):
    d, mesh, doc = job
    root = np.asarray(doc["root"]["transform"]).reshape(4, 4).T
    rot = root[:3, :3]
    assert np.abs(rot.T @ rot - np.eye(3)).max() < 1e-12  # a rotation (ENU frame) and a translation
    origin = root[:3, 3]
    assert np.dot(rot[:, 2], origin / np.linalg.norm(origin)) > 0.99  # up is (nearly) away from the earth's centre
    to_ecef = pyproj.Transformer.from_crs(pyproj.CRS(UTM).to_3d(), "EPSG:4978", always_xy=True)
    leaf = _leaves(doc)[0]
    g = read_glb(d / "tiles" / leaf["content"]["uri"])
    ecef = g["positions"] @ rot.T + origin
    back = pyproj.Transformer.from_crs("EPSG:4978", pyproj.CRS(UTM).to_3d(), always_xy=True)
    x, y, z = back.transform(*ecef.T)
    crs_pts = np.column_stack([x, y, z])
    assert np.abs(np.column_stack(to_ecef.transform(*crs_pts.T)) - ecef).max() < 1e-6
    # the points land where the input was: near UTM 32N (500000, 4000000), 50 m up
    assert np.abs(crs_pts[:, :2] - [500006, 4000006]).max() < 8 and np.abs(crs_pts[:, 2] - 50).max() < 2
    extras = doc["extras"]["tiled_gridpull"]
    assert extras["crs"] == UTM and extras["crs_source"] == "--3d-tiles-crs"
    assert extras["config"]["refine"]["m2"] == 6 and extras["tiling"]["voxel_size"] == pytest.approx(0.2)
    assert doc["asset"]["version"] == "1.1" and doc["asset"]["generator"].startswith("tiled_gridpull")
    assert mesh.metadata["tiles3d"]["tiles"] == 16


def test_vtk_3d_tiles_reader_opens_every_level_and_draws_it(job, tmp_path):
    """The fixture tileset through a third-party 3D Tiles loader (VTK's vtkCesium3DTilesReader, on PyPI in the
    vtk wheel pyvista brings): every level loads, in earth-centred coordinates where pyproj puts the mesh, and
    renders off-screen."""
    pv = pytest.importorskip("pyvista")
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    d, mesh, doc = job
    counts = []
    for level in range(3):
        reader = vtk.vtkCesium3DTilesReader()
        reader.SetFileName(str(d / "tiles" / "tileset.json"))
        reader.SetLevel(level)
        reader.Update()
        out = reader.GetOutput()
        pts, faces, parts = [], 0, []
        for i in range(out.GetNumberOfPartitionedDataSets()):
            part = out.GetPartitionedDataSet(i)
            for j in range(part.GetNumberOfPartitions()):
                ds = part.GetPartition(j)
                pts.append(vtk_to_numpy(ds.GetPoints().GetData()).astype(np.float64))
                faces += ds.GetNumberOfCells()
                parts.append(pv.wrap(ds))
        counts.append((out.GetNumberOfPartitionedDataSets(), faces))
        if level == 2:
            finest, finest_parts = np.concatenate(pts), parts
    levels = doc["extras"]["tiled_gridpull"]["per_level"]
    # level 0 of the reader is the root: the coarsest of ours
    assert counts == [(lv["nodes"], lv["faces"]) for lv in reversed(levels)]
    to_ecef = pyproj.Transformer.from_crs(pyproj.CRS(UTM).to_3d(), "EPSG:4978", always_xy=True)
    expect = np.column_stack(to_ecef.transform(*mesh.vertices.T))
    from pykdtree.kdtree import KDTree

    dist, _ = KDTree(expect).query(finest, k=1)
    assert dist.max() < 1e-3  # metres: VTK placed every vertex where pyproj puts the input's
    plotter = pv.Plotter(off_screen=True, window_size=(160, 120))
    plotter.set_background("black")
    centre = finest.mean(axis=0)
    for part in finest_parts:
        part = part.copy()
        part.points = part.points - centre
        plotter.add_mesh(part, color="orange")
    image = plotter.screenshot(return_img=True)
    plotter.close()
    lit = (image.max(axis=2) > 40).mean()
    assert 0.05 < lit < 0.99  # the tiles were drawn and fill part of the picture


def test_every_glb_passes_gltfpack(job, tmp_path):
    """Debian's gltfpack (``apt-get install gltfpack``) loads every glb through cgltf's parser and validator
    (accessor and buffer bounds, index ranges); a glb with one accessor past its buffer is refused."""
    import shutil
    import subprocess

    exe = shutil.which("gltfpack")
    if exe is None:
        pytest.skip("gltfpack not installed (Debian: apt-get install gltfpack)")
    d, _, _ = job
    files = sorted((d / "tiles").rglob("*.glb"))
    assert len(files) == 16 + 4 + 1
    for f in files:
        r = subprocess.run([exe, "-i", str(f), "-o", str(tmp_path / "o.glb")], capture_output=True, text=True)
        assert r.returncode == 0, (f, r.stderr)
    import pygltflib

    g = pygltflib.GLTF2().load_binary(str(files[0]))
    g.accessors[0].count += 10
    g.save_binary(str(tmp_path / "bad.glb"))
    r = subprocess.run([exe, "-i", str(tmp_path / "bad.glb"), "-o", str(tmp_path / "o.glb")], capture_output=True,
                       text=True)
    assert r.returncode != 0 and "buffer too short" in r.stderr


# ------------------------------------------------------------------------------------------ attributes, units
def _grid_tiles(n=2, cells=8, size=10.0, origin=(500000.0, 4000000.0, 100.0), attrs=True):
    tiles = []
    h = size / cells
    for ti in range(n):
        for tj in range(n):
            xs, ys = ti * size + np.arange(cells + 1) * h, tj * size + np.arange(cells + 1) * h
            X, Y = np.meshgrid(xs, ys, indexing="ij")
            V = np.column_stack([X.ravel(), Y.ravel(), (np.sin(X / 3.0) + np.cos(Y / 2.0)).ravel()]) + origin
            idx = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
            a, b, c, e = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
            m = Mesh(V, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, e])]))
            if attrs:
                k = np.arange(len(V))
                m.vertex_attributes = {"red": (k * 7 % 256).astype(np.uint8), "green": np.full(len(V), 128, np.uint8),
                                       "blue": np.zeros(len(V), np.uint8),
                                       "intensity": (k * 911 % 65536).astype(np.uint16),
                                       "classification": np.where(V[:, 2] > origin[2], 6, 2).astype(np.uint8)}
            tiles.append(TileMesh(f"tile_{ti}_{tj}_0", (ti, tj, 0), m))
    return tiles


def test_vertex_attributes_become_color_0_and_property_attributes(tmp_path):
    tiles = _grid_tiles()
    summary = write_tileset(tiles, tmp_path / "ts", UTM)
    assert summary["attributes"] == {"COLOR_0": True, "custom": {"_CLASSIFICATION": "classification",
                                                                 "_INTENSITY": "intensity"}}
    doc = json.loads((tmp_path / "ts" / "tileset.json").read_text())
    by_uri = {leaf["content"]["uri"]: leaf for leaf in _leaves(doc)}
    for t in tiles:
        g = read_glb(tmp_path / "ts" / "tiles" / f"{t.name}.glb")
        a = t.mesh.vertex_attributes
        srgb = a["red"] / 255.0
        linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
        color = g["attributes"]["COLOR_0"]
        assert color.dtype == np.uint16 and color.shape == (t.mesh.n_vertices, 4)
        assert np.abs(color[:, 0] / 65535.0 - linear).max() < 1e-4 and (color[:, 3] == 65535).all()
        assert np.array_equal(g["attributes"]["_INTENSITY"], a["intensity"].astype(np.float32))
        assert np.array_equal(g["attributes"]["_CLASSIFICATION"], a["classification"].astype(np.float32))
        ext = g["gltf"].extensions["EXT_structural_metadata"]
        assert set(ext["schema"]["classes"]["vertex"]["properties"]) == {"intensity", "classification"}
        assert ext["propertyAttributes"][0]["properties"]["intensity"] == {"attribute": "_INTENSITY"}
        assert g["gltf"].meshes[0].primitives[0].extensions["EXT_structural_metadata"] == {"propertyAttributes": [0]}
        assert "EXT_structural_metadata" in g["gltf"].extensionsUsed
        assert f"tiles/{t.name}.glb" in by_uri
    # the coarse level takes each vertex's values from the finest vertices (nearest): no invented classes
    coarse = read_glb(tmp_path / "ts" / doc["root"]["content"]["uri"])
    assert set(np.unique(coarse["attributes"]["_CLASSIFICATION"])) <= {2.0, 6.0}
    assert len(coarse["faces"]) < sum(t.mesh.n_faces for t in tiles)


def test_16_bit_colours_holding_8_bit_values_and_meshes_without_attributes(tmp_path):
    tiles = _grid_tiles(n=1)
    a = tiles[0].mesh.vertex_attributes
    for k in ("red", "green", "blue"):
        a[k] = a[k].astype(np.uint16)  # LAS stores 16 bits; many files hold 0..255 in them
    write_tileset(tiles, tmp_path / "a", UTM)
    g = read_glb(tmp_path / "a" / "tiles" / "tile_0_0_0.glb")
    assert g["attributes"]["COLOR_0"][:, 1].max() > 0.2 * 65535  # green 128 read as 8-bit, not 128/65535
    plain = _grid_tiles(n=1, attrs=False)
    summary = write_tileset(plain, tmp_path / "b", UTM)
    g = read_glb(tmp_path / "b" / "tiles" / "tile_0_0_0.glb")
    assert set(g["attributes"]) == {"POSITION", "NORMAL"} and summary["levels"] == 1
    assert g["gltf"].extensionsUsed in (None, [])


def test_levels_over_a_row_of_tiles_and_a_stacked_column(tmp_path):
    """Five tiles in a row (one of them with a second tile above it): three coarser levels, every tile reached
    once, a coarse node alone in its block passed up rather than simplified again."""
    row = _grid_tiles(n=5, attrs=False)
    tiles = [t for t in row if t.index[1] == 0]  # (0..4, 0, 0)
    above = Mesh(tiles[2].mesh.vertices + [0.0, 0.0, 10.0], tiles[2].mesh.faces)
    tiles.append(TileMesh("tile_2_0_1", (2, 0, 1), above))
    summary = write_tileset(tiles, tmp_path / "ts", UTM)
    doc = json.loads((tmp_path / "ts" / "tileset.json").read_text())
    assert summary["levels"] == 3 and [lv["nodes"] for lv in summary["per_level"]] == [6, 3, 2, 1]
    leaves = sorted(leaf["content"]["uri"] for leaf in _leaves(doc))
    assert leaves == sorted(f"tiles/{t.name}.glb" for t in tiles)
    uris = [n["content"]["uri"] for n, _, _ in _nodes(doc["root"])]
    # 6 tiles, 3 level-1 nodes, one new level-2 node, the root: the lone level-1 node of tile 4 is level 2's too
    assert len(uris) == len(set(uris)) == 6 + 3 + 1 + 1
    assert not any(u.startswith("lod/lod_2_1") for u in uris)
    stacked = next(n for n, _, _ in _nodes(doc["root"]) if n.get("content", {}).get("uri") == "lod/lod_1_1_0.glb")
    assert sorted(c["content"]["uri"] for c in stacked["children"]) == [
        "tiles/tile_2_0_0.glb", "tiles/tile_2_0_1.glb", "tiles/tile_3_0_0.glb"]


def test_crs_in_feet_and_one_without_a_place(tmp_path):
    # NAD83 / Oregon GIC Lambert (ft), the Autzen survey's CRS: heights in feet too
    tiles = _grid_tiles(n=1, origin=(637000.0, 851000.0, 400.0), attrs=False)
    write_tileset(tiles, tmp_path / "ft", "EPSG:2992")
    doc = json.loads((tmp_path / "ft" / "tileset.json").read_text())
    g = read_glb(tmp_path / "ft" / doc["root"]["children"][0]["content"]["uri"])
    v = tiles[0].mesh.vertices
    a, b = 0, 8 * 9  # two vertices 10 ft apart along the grid's x, at different heights
    assert v[b, 0] - v[a, 0] == 10 and abs(v[b, 2] - v[a, 2]) > 0.1
    lon, lat = pyproj.Transformer.from_crs("EPSG:2992", "EPSG:4326", always_xy=True).transform(*v[a, :2])
    k = pyproj.Proj("EPSG:2992").get_factors(lon, lat).parallel_scale  # the projection's scale there
    enu = g["positions"]
    up = 1 + v[a, 2] * 0.3048 / 6.37e6  # ~122 m above the ellipsoid, where the projection's scale holds
    assert np.linalg.norm(enu[b, :2] - enu[a, :2]) == pytest.approx(10 * 0.3048 / k * up, rel=3e-6)  # metres
    assert enu[b, 2] - enu[a, 2] == pytest.approx((v[b, 2] - v[a, 2]) * 0.3048, abs=2e-4)  # heights in feet too
    root = np.asarray(doc["root"]["transform"]).reshape(4, 4).T
    height = pyproj.Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True).transform(*root[:3, 3])[2]
    assert height == pytest.approx(400 * 0.3048, abs=3)  # ~122 m above the ellipsoid, not 400 m
    with pytest.raises(ConfigError, match="not a coordinate reference system"):
        write_tileset(tiles, tmp_path / "bad", "EPSG:999999")
    with pytest.raises(ConfigError, match="places no point on the earth"):
        write_tileset(tiles, tmp_path / "bad", "EPSG:5714")  # heights above mean sea level, nothing else
    with pytest.raises(ConfigError, match="cannot transform"):
        write_tileset(tiles, tmp_path / "bad", "IAU_2015:30100")  # the Moon
    assert not (tmp_path / "bad").exists()


def test_a_failed_write_leaves_the_earlier_tileset_and_no_temporary_files(tmp_path, monkeypatch):
    import tiled_gridpull.tiles3d as t3

    write_tileset(_grid_tiles(), tmp_path / "ts", UTM)
    before = (tmp_path / "ts" / "tileset.json").read_bytes()
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise OSError(28, "No space left on device")
        return real(*args, **kwargs)

    real = t3.write_glb
    monkeypatch.setattr(t3, "write_glb", failing)
    with pytest.raises(OSError):
        write_tileset(_grid_tiles(), tmp_path / "ts", UTM)
    assert (tmp_path / "ts" / "tileset.json").read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["ts"]
    monkeypatch.undo()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="did not write"):
        write_tileset(_grid_tiles(), tmp_path / "other", UTM)
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


# ------------------------------------------------------------------------------------------------ command line
def _one_error_line(err: str) -> str:
    lines = [line for line in err.strip().splitlines() if line]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def test_cli_refuses_before_solving(tmp_path, capsys):
    np.save(tmp_path / "g.npy", terrain(6.4, 20))
    base = ["reconstruct", str(tmp_path / "g.npy"), "-o", str(tmp_path / "m.ply"), "-q"]
    tiled = [*base, "--voxel-size", "0.2", "--3d-tiles", str(tmp_path / "ts")]
    # an NPY declares no CRS
    assert main(tiled) == 2
    assert "--3d-tiles-crs" in _one_error_line(capsys.readouterr().err)
    assert main([*tiled, "--3d-tiles-crs", "EPSG:999999"]) == 2
    assert "EPSG:999999" in _one_error_line(capsys.readouterr().err)
    assert main([*base, "--3d-tiles", str(tmp_path / "ts")]) == 2  # one-shape mode
    assert "tiled mode" in _one_error_line(capsys.readouterr().err)
    assert main([*base, "--voxel-size", "0.2", "--3d-tiles-crs", UTM]) == 2
    assert "--3d-tiles" in _one_error_line(capsys.readouterr().err)
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "a.txt").write_text("x")
    assert main([*base, "--voxel-size", "0.2", "--3d-tiles", str(tmp_path / "foreign"), "--3d-tiles-crs", UTM]) == 2
    assert "did not write" in _one_error_line(capsys.readouterr().err)
    assert main([*base, "--voxel-size", "0.2", "--3d-tiles", str(tmp_path), "--3d-tiles-crs", UTM]) == 2
    assert "overlaps" in _one_error_line(capsys.readouterr().err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["foreign", "g.npy"]  # nothing solved, nothing written


def test_cli_says_which_extra_is_missing(tmp_path, capsys, monkeypatch):
    import sys

    np.save(tmp_path / "g.npy", terrain(6.4, 20))
    monkeypatch.setitem(sys.modules, "pygltflib", None)  # as if not installed: import raises ImportError
    code = main(["reconstruct", str(tmp_path / "g.npy"), "-o", str(tmp_path / "m.ply"), "-q", "--voxel-size", "0.2",
                 "--3d-tiles", str(tmp_path / "ts"), "--3d-tiles-crs", UTM])
    assert code == 4
    assert "tiled-gridpull[tiles3d]" in _one_error_line(capsys.readouterr().err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.npy"]


@pytest.mark.slow
def test_cli_takes_the_crs_of_a_las_input(tmp_path):
    from tiled_gridpull.synthetic.lidar_files import write_las

    pts = terrain(6.4, 40, seed=1)
    write_las(tmp_path / "g.laz", pts, crs_wkt=pyproj.CRS(UTM).to_wkt())
    args = ["reconstruct", str(tmp_path / "g.laz"), "-o", str(tmp_path / "m.ply"), "--voxel-size", "0.2",
            "--tile-size", "3.2", "--overlap", "1.6", "--set", "m2=8", "--set", "refine_m2=6", "--set",
            "coarse_iterations=50", "--set", "iterations=50", "--set", "queries=10000", "--workers", "1", "-q",
            "--3d-tiles", str(tmp_path / "ts")]
    assert main(args) == 0
    doc = json.loads((tmp_path / "ts" / "tileset.json").read_text())
    extras = doc["extras"]["tiled_gridpull"]
    assert extras["crs_source"] == "input" and "UTM zone 32N" in extras["crs"]
    assert len(_leaves(doc)) == 4 and extras["levels"] == 1
    side = json.loads((tmp_path / "m.json").read_text())
    assert side["tiles3d"]["tiles"] == 4
    # a rerun replaces its own tileset
    assert main(args) == 0
    assert json.loads((tmp_path / "ts" / "tileset.json").read_text())["root"] == doc["root"]


def test_specks_leave_the_mesh_the_tile_meshes_and_the_tileset_alike(tmp_path):
    """Two small balls of points float over the ground: the smaller one's bubble (and the scraps at the data's
    edge) are parts under ``min_component_cells`` (2) cells along every axis and go from the mesh, the tile
    meshes and the finest 3D Tiles alike; the larger one (3 cells across) stays; 0 keeps them all, the same
    solves reused."""
    rng = np.random.default_rng(1)
    u = rng.normal(size=(300, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    base = np.array([500000.0, 4000000.0, 50.0])
    balls = [base + c + 0.12 * u for c in ([4.1, 4.3, 3.0], [8.0, 6.35, 2.5])]
    np.save(tmp_path / "g.npy", np.concatenate([terrain(12.8, 40, seed=3), *balls]))
    out = {}
    for cells in (2.0, 0.0):
        tiling = TilingConfig(voxel_size=0.2, tile_size=3.2, overlap=1.6, trim_distance=2.0, min_component_cells=cells)
        mesh = reconstruct_scene([str(tmp_path / "g.npy")], tmp_path / f"m{cells}.ply", tiling, SOLVER,
                                 tmp_path / "job", tile_meshes=tmp_path / f"tiles{cells}",
                                 tiles3d=tmp_path / f"ts{cells}", tiles3d_crs=UTM)
        doc = json.loads((tmp_path / f"ts{cells}" / "tileset.json").read_text())
        finest = sum(len(read_glb(tmp_path / f"ts{cells}" / n["content"]["uri"])["faces"]) for n in _leaves(doc))
        pieces = sum(read_mesh(p).n_faces for p in (tmp_path / f"tiles{cells}").glob("*.ply"))
        assert finest == pieces == read_mesh(tmp_path / f"m{cells}.ply").n_faces == mesh.n_faces
        out[cells] = mesh
    kept, every = out[2.0], out[0.0]
    # each tile's record counts what it keeps, and a tile left with specks only leaves no PLY, even where an
    # earlier run wrote one (the same run again into the first run's tile folder)
    assert sum(m.get("faces") or 0 for m in kept.metadata["mesh_summaries"]) == kept.n_faces
    assert sum(m.get("small_faces_dropped", 0) for m in kept.metadata["mesh_summaries"]) == \
        every.n_faces - kept.n_faces
    assert len(list((tmp_path / "tiles0.0").glob("*.ply"))) > len(list((tmp_path / "tiles2.0").glob("*.ply")))
    tiling = TilingConfig(voxel_size=0.2, tile_size=3.2, overlap=1.6, trim_distance=2.0)
    again = reconstruct_scene([str(tmp_path / "g.npy")], tmp_path / "again.ply", tiling, SOLVER, tmp_path / "job",
                              tile_meshes=tmp_path / "tiles0.0")
    assert sum(read_mesh(p).n_faces for p in (tmp_path / "tiles0.0").glob("*.ply")) == again.n_faces == kept.n_faces
    labels = every.components()
    tri = every.vertices[every.faces]
    extent = np.array([np.ptp(tri[labels == c].reshape(-1, 3), axis=0).max() for c in range(labels.max() + 1)])
    small = extent < 0.4
    assert small.sum() == kept.metadata["small_components_removed"] > 0
    assert kept.n_faces == every.n_faces - np.isin(labels, np.flatnonzero(small)).sum()
    assert kept.metadata["mesh"]["components"] == (~small).sum() >= 2  # the ground and the larger ball
    assert every.metadata["small_components_removed"] == 0
    assert every.metadata["reused"]["solves"] == every.metadata["tiles"]["solved"]
