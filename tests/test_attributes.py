"""Point attributes on mesh vertices: interpolation, the Mesh contract through every vertex operation, readers,
writers, conversions, one-shape and tiled modes, the CLI's --attributes and render --color."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import shared_file, terrain, unit_sphere_points

from tiled_gridpull.attributes import interpolate_attributes, mean_attributes, select_attributes
from tiled_gridpull.cloud import PointCloud
from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import ConfigError
from tiled_gridpull.io import read_points
from tiled_gridpull.io.meshes import read_mesh, write_mesh
from tiled_gridpull.mesh import Mesh, color_full_scale
from tiled_gridpull.mesh_repair import boundary_loops, close_holes
from tiled_gridpull.reconstruct import reconstruct
from tiled_gridpull.stitch import MeshPiece, load_piece, save_piece, trim_faces, weld_pieces

X0, Y0 = 500000.0, 4000000.0  # terrain()'s offset
EXTENT = 12.8


def _ramp(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """0..255 along ``x`` from ``lo`` to ``hi``, as float."""
    return np.clip((x - lo) / (hi - lo) * 255.0, 0, 255)


def _quad() -> Mesh:
    """Two triangles on the unit square, with one attribute per kind."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return Mesh(v, f, {}, {"red": np.array([0, 10, 20, 30], np.uint8),
                           "classification": np.array([2, 2, 6, 6], np.uint8),
                           "intensity": np.array([0.5, 1.5, 2.5, 3.5], np.float32)})


# ------------------------------------------------------------------------------------------------ interpolation


def test_interpolation_is_exact_on_points_and_linear_ramps_stay_close():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 10, (5000, 3))
    red = np.round(_ramp(pts[:, 0], 0, 10)).astype(np.uint8)
    inten = (pts[:, 1] * 100).astype(np.uint16)
    out = interpolate_attributes(pts[:50], pts, {"red": red, "intensity": inten})
    assert out["red"].dtype == np.uint8 and out["intensity"].dtype == np.uint16
    assert np.array_equal(out["red"], red[:50]) and np.array_equal(out["intensity"], inten[:50])
    q = rng.uniform(2, 8, (500, 3))
    got = interpolate_attributes(q, pts, {"red": red})["red"].astype(float)
    assert np.median(np.abs(got - _ramp(q[:, 0], 0, 10))) <= 3.0


def test_classification_is_a_weighted_majority_never_a_mean():
    pts = np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [5, 0, 0]], float)
    cls = np.array([2, 2, 6, 9], np.uint8)
    out = interpolate_attributes(np.array([[0.15, 0, 0], [4.9, 0, 0]]), pts, {"classification": cls}, k=4)
    # a mean of 2, 2, 6 would be a class no neighbour has
    assert out["classification"].tolist() == [2, 9]


def test_integer_results_are_clipped_to_their_type_and_keys_kept():
    pts = np.zeros((3, 3)) + np.arange(3)[:, None]
    out = interpolate_attributes(np.array([[0.5, 0.5, 0.5]]), pts, {"u": np.array([250, 255, 255], np.uint8)})
    assert out["u"].dtype == np.uint8 and 250 <= int(out["u"][0]) <= 255
    assert interpolate_attributes(np.zeros((0, 3)), pts, {"u": np.ones(3, np.uint8)})["u"].shape == (0,)


def test_select_attributes_modes():
    attrs = {"red": np.zeros(3, np.uint16), "green": np.zeros(3, np.uint16), "blue": np.zeros(3, np.uint16),
             "intensity": np.zeros(3, np.uint16), "frame": np.zeros(3, np.int32), "gps_time": np.zeros(3)}
    assert list(select_attributes(attrs, "all")) == ["red", "green", "blue", "intensity"]
    assert list(select_attributes(attrs, "rgb")) == ["red", "green", "blue"]
    assert select_attributes(attrs, "none") == {}
    assert select_attributes({"intensity": attrs["intensity"]}, "rgb") == {}
    with pytest.raises(ConfigError, match="attributes must be one of"):
        select_attributes(attrs, "colour")


# ------------------------------------------------------------------------------------------- the Mesh contract


def test_mesh_refuses_attributes_not_aligned_with_vertices():
    with pytest.raises(ValueError, match="'red' has shape"):
        Mesh(np.zeros((4, 3)), np.zeros((0, 3)), {}, {"red": np.zeros(3, np.uint8)})


def test_submesh_trim_and_flip_keep_attributes_aligned():
    m = _quad()
    sub = m.submesh(np.array([False, True]))  # face (0, 2, 3)
    assert sub.vertex_attributes["red"].tolist() == [0, 20, 30]
    assert np.array_equal(sub.vertices[:, :2], [[0, 0], [1, 1], [0, 1]])
    trimmed, keys = trim_faces(m, np.arange(4), np.array([[0.1, 0.9, 0.0]]), 0.5)
    assert trimmed.vertex_attributes["red"].tolist() == [0, 20, 30] and keys.tolist() == [0, 2, 3]


def test_closing_a_hole_gives_the_centre_the_loops_mean_and_majority():
    m = _quad()
    loops = boundary_loops(m)
    closed = close_holes(m, loops)
    assert closed.n_vertices == 5
    assert closed.vertex_attributes["red"][-1] == 15 and closed.vertex_attributes["intensity"][-1] == 2.0
    assert closed.vertex_attributes["classification"][-1] in (2, 6)
    assert mean_attributes({"classification": np.array([6, 6, 2], np.uint8)}, np.arange(3))["classification"][0] == 6


def test_weld_keeps_the_first_tiles_values_and_pieces_round_trip(tmp_path):
    a = MeshPiece(np.eye(3), np.array([[0, 1, 2]]), np.array([10, 11, 12]),
                  attributes={"red": np.array([1, 2, 3], np.uint8)})
    b = MeshPiece(np.eye(3) + [0, 0, 1], np.array([[0, 1, 2]]), np.array([12, 13, 14]),
                  attributes={"red": np.array([3, 4, 5], np.uint8)})
    save_piece(b, tmp_path / "b.npz")
    b2 = load_piece(tmp_path / "b.npz")
    assert np.array_equal(b2.attributes["red"], b.attributes["red"])
    welded = weld_pieces([a, b2])
    assert welded.n_vertices == 5
    assert welded.vertex_attributes["red"].tolist() == [1, 2, 3, 4, 5]


# -------------------------------------------------------------------------------------------- files and libraries


@pytest.mark.parametrize("dtype,ptype", [(np.uint8, "uchar"), (np.uint16, "ushort")])
def test_ply_carries_attributes_in_their_type_and_obj_carries_colour(tmp_path, dtype, ptype):
    m = _quad()
    m.vertex_attributes["red"] = (m.vertex_attributes["red"].astype(np.uint32) * 1000 if dtype == np.uint16
                                  else m.vertex_attributes["red"]).astype(dtype)
    m.vertex_attributes["green"] = m.vertex_attributes["red"].copy()
    m.vertex_attributes["blue"] = m.vertex_attributes["red"].copy()
    m.vertex_attributes["my dim"] = np.arange(4, dtype=np.int64)
    write_mesh(m, tmp_path / "m.ply")
    head = (tmp_path / "m.ply").read_bytes().split(b"end_header")[0].decode()
    assert f"property {ptype} red" in head and "property uchar classification" in head
    assert "property double my_dim" in head
    back = read_mesh(tmp_path / "m.ply")
    for name in ("red", "green", "blue", "classification", "intensity"):
        assert back.vertex_attributes[name].dtype == m.vertex_attributes[name].dtype
        assert np.array_equal(back.vertex_attributes[name], m.vertex_attributes[name])
    write_mesh(m, tmp_path / "m.obj")
    v_lines = [ln.split() for ln in (tmp_path / "m.obj").read_text().splitlines() if ln.startswith("v ")]
    full = color_full_scale(m.vertex_attributes)
    assert len(v_lines[2]) == 7
    assert float(v_lines[2][4]) == pytest.approx(m.vertex_attributes["red"][2] / full, abs=1e-5)
    assert np.allclose(read_mesh(tmp_path / "m.obj").vertices, m.vertices)


def test_colour_scale_follows_the_values_for_16_bit_fields():
    eight_in_16 = {c: np.array([0, 200], np.uint16) for c in ("red", "green", "blue")}
    assert color_full_scale(eight_in_16) == 255.0
    assert color_full_scale({c: np.array([0, 60000], np.uint16) for c in ("red", "green", "blue")}) == 65535.0
    assert color_full_scale({"red": np.zeros(2, np.uint8)}) is None


def test_conversions_keep_colours():
    m = _quad()
    for c in ("green", "blue"):
        m.vertex_attributes[c] = m.vertex_attributes["red"].copy()
    trimesh = pytest.importorskip("trimesh")
    t = m.to_trimesh()
    assert isinstance(t, trimesh.Trimesh)
    assert t.visual.vertex_colors[:, 0].tolist() == [0, 10, 20, 30]
    assert np.array_equal(t.vertex_attributes["classification"], [2, 2, 6, 6])
    o3d = pytest.importorskip("open3d")
    o = m.to_open3d()
    assert isinstance(o, o3d.geometry.TriangleMesh)
    assert np.allclose(np.asarray(o.vertex_colors)[:, 0], np.array([0, 10, 20, 30]) / 255)
    pytest.importorskip("pyvista")
    p = m.to_pyvista()
    assert p.point_data["RGB"][:, 0].tolist() == [0, 10, 20, 30]
    assert np.array_equal(p.point_data["intensity"], m.vertex_attributes["intensity"])


def test_ply_reader_keeps_colour_types_binary_and_ascii(tmp_path):
    from plyfile import PlyData, PlyElement

    pts = unit_sphere_points(100)
    v = np.empty(100, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                       ("classification", "u1")])
    v["x"], v["y"], v["z"] = pts.T
    v["red"], v["green"], v["blue"], v["classification"] = 7, 8, 9, 6
    for text in (False, True):
        PlyData([PlyElement.describe(v, "vertex")], text=text).write(str(tmp_path / "c.ply"))
        cloud = read_points(tmp_path / "c.ply", clean=False)
        assert cloud.attributes["red"].dtype == np.uint8 and set(cloud.attributes["blue"]) == {9}
        assert cloud.attributes["classification"].dtype == np.uint8 and set(cloud.attributes["classification"]) == {6}


def test_las_reader_carries_rgb_intensity_class_and_extra_dims(tmp_path):
    laspy = pytest.importorskip("laspy")
    las = laspy.create(point_format=3, file_version="1.2")
    las.add_extra_dim(laspy.ExtraBytesParams(name="height_above", type=np.float32))
    pts = unit_sphere_points(200) * 10
    las.x, las.y, las.z = pts.T
    las.red = np.full(200, 60000, np.uint16)
    las.green = np.arange(200, dtype=np.uint16)
    las.blue = np.zeros(200, np.uint16)
    las.intensity = np.full(200, 7, np.uint16)
    las.classification = np.full(200, 5, np.uint8)
    las.height_above = np.linspace(0, 1, 200).astype(np.float32)
    las.write(str(tmp_path / "p.las"))
    attrs = read_points(tmp_path / "p.las", clean=False).attributes
    assert attrs["red"].dtype == np.uint16 and set(attrs["red"]) == {60000}
    assert np.array_equal(attrs["green"], np.arange(200))
    assert attrs["intensity"].dtype == np.uint16 and attrs["classification"].dtype == np.uint8
    assert set(attrs["classification"]) == {5}
    assert np.allclose(attrs["height_above"], np.linspace(0, 1, 200))


def test_autzen_colours_are_read_as_stored():
    attrs = read_points(shared_file("lidar", "autzen_trim.laz"), clean=False).attributes
    assert {"red", "green", "blue", "intensity", "classification"} <= set(attrs)
    assert attrs["red"].dtype == np.uint16 and 0 < attrs["red"].max() <= 255  # 8-bit colour in 16-bit fields
    assert color_full_scale(attrs) == 255.0


# ------------------------------------------------------------------------------------------------ one-shape mode


@pytest.fixture(scope="module")
def coloured_sphere():
    pts = unit_sphere_points(8000, seed=1)
    red = np.round(_ramp(pts[:, 0], -0.5, 0.5)).astype(np.uint8)
    attrs = {"red": red, "green": (255 - red).astype(np.uint8), "blue": np.full(len(pts), 40, np.uint8),
             "classification": np.where(pts[:, 2] > 0, 6, 2).astype(np.uint8),
             "intensity": (pts[:, 1] * 100).astype(np.float32), "frame": np.zeros(len(pts), np.int32)}
    return PointCloud(pts, attributes=attrs, source="sphere")


def test_one_shape_mode_interpolates_every_attribute(coloured_sphere):
    mesh = reconstruct(coloured_sphere, resolution=32, iterations=60, coarse_iterations=60)
    a = mesh.vertex_attributes
    assert set(a) == {"red", "green", "blue", "classification", "intensity"}  # not the KITTI frame
    assert all(len(v) == mesh.n_vertices for v in a.values())
    assert a["red"].dtype == np.uint8 and a["intensity"].dtype == np.float32
    dir_ = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True) * 0.5
    assert np.median(np.abs(a["red"] - _ramp(dir_[:, 0], -0.5, 0.5))) <= 3.0  # <= 1.2 % of 255
    far_from_equator = np.abs(dir_[:, 2]) > 0.05
    assert np.mean(a["classification"][far_from_equator] == np.where(dir_[far_from_equator, 2] > 0, 6, 2)) > 0.99
    record = mesh.metadata["vertex_attributes"]
    assert record["rule"] == "all" and [n for n, _ in record["carried"]] == list(a)


def test_one_shape_mode_rgb_and_none(coloured_sphere):
    kw = dict(resolution=24, iterations=30, coarse_iterations=30)
    assert list(reconstruct(coloured_sphere, attributes="rgb", **kw).vertex_attributes) == ["red", "green", "blue"]
    none = reconstruct(coloured_sphere, attributes="none", **kw)
    assert none.vertex_attributes == {} and none.metadata["vertex_attributes"]["carried"] == []
    with pytest.raises(ConfigError, match="attributes must be one of"):
        reconstruct(coloured_sphere, attributes="colour", **kw)


# ---------------------------------------------------------------------------------------------------- tiled mode

SOLVER = SolverConfig(m2=8, refine_m2=6, coarse_iterations=100, iterations=100, queries=20000)


def _terrain_ply(path, seed=3):
    from plyfile import PlyData, PlyElement

    p = terrain(EXTENT, 40, seed=seed)
    v = np.empty(len(p), [("x", "f8"), ("y", "f8"), ("z", "f8"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                          ("classification", "u1")])
    v["x"], v["y"], v["z"] = p.T
    v["red"] = np.round(_ramp(p[:, 0], X0, X0 + EXTENT))
    v["green"] = np.round(_ramp(p[:, 1], Y0, Y0 + EXTENT))
    v["blue"] = 77
    v["classification"] = np.where(p[:, 0] > X0 + EXTENT / 2, 2, 6)
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))
    return path


@pytest.fixture(scope="module")
def tiled(tmp_path_factory):
    from tiled_gridpull.tiled_job import reconstruct_scene
    from tiled_gridpull.tiling import TilingConfig

    d = tmp_path_factory.mktemp("tiled_attrs")
    src = _terrain_ply(d / "g.ply")
    tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, trim_distance=2.0)
    mesh = reconstruct_scene([str(src)], d / "s.ply", tiling, SOLVER, d / "job", tile_meshes=d / "tiles")
    return d, tiling, mesh


def test_tiled_mode_carries_colour_and_class_onto_the_welded_mesh(tiled):
    d, _, mesh = tiled
    a = mesh.vertex_attributes
    assert set(a) == {"red", "green", "blue", "classification"} and a["red"].dtype == np.uint8
    x, y = mesh.vertices[:, 0], mesh.vertices[:, 1]
    assert np.median(np.abs(a["red"] - _ramp(x, X0, X0 + EXTENT))) <= 3.0
    assert np.median(np.abs(a["green"] - _ramp(y, Y0, Y0 + EXTENT))) <= 3.0
    assert set(a["blue"]) == {77}
    away = np.abs(x - (X0 + EXTENT / 2)) > 0.3
    assert np.mean(a["classification"][away] == np.where(x[away] > X0 + EXTENT / 2, 2, 6)) > 0.99
    written = read_mesh(d / "s.ply")
    assert np.array_equal(written.vertex_attributes["red"], a["red"])
    side = json.loads((d / "s.json").read_text())["vertex_attributes"]
    assert side["rule"] == "all" and [n for n, _ in side["carried"]] == ["red", "green", "blue", "classification"]
    tile = read_mesh(sorted((d / "tiles").glob("*.ply"))[0])
    assert tile.vertex_attributes["red"].dtype == np.uint8 and len(tile.vertex_attributes["red"]) == tile.n_vertices


def test_tiles_agree_on_their_shared_border_vertices(tiled):
    d, _, _ = tiled
    pieces = [load_piece(p) for p in sorted((d / "job" / "pieces").glob("*.npz"))]
    assert len(pieces) == 4
    seen, shared = {}, 0
    for piece in pieces:
        rows = np.column_stack([piece.attributes[n].astype(np.int64) for n in sorted(piece.attributes)])
        for key, row in zip(piece.keys, rows):
            if key < 0:  # a vertex private to its piece (negative ids are per piece)
                continue
            if key in seen:
                shared += 1
                assert np.array_equal(seen[key], row), key
            else:
                seen[key] = row
    assert shared > 50  # the four tiles meet along two borders


def test_tiled_rerun_reuses_and_attributes_none_drops_them(tiled):
    from tiled_gridpull.tiled_job import reconstruct_scene

    d, tiling, first = tiled
    again = reconstruct_scene([str(d / "g.ply")], d / "again.ply", tiling, SOLVER, d / "job")
    assert again.metadata["reused"] == {"partition": True, "solves": 4, "meshes": 4}
    assert np.array_equal(again.vertex_attributes["green"], first.vertex_attributes["green"])
    none = reconstruct_scene([str(d / "g.ply")], d / "none.ply", tiling.__class__(**{
        **{k: getattr(tiling, k) for k in ("voxel_size", "tile_size", "overlap", "trim_distance")},
        "attributes": "none"}), SOLVER, d / "job_none")
    assert none.vertex_attributes == {} and not list((d / "job_none" / "points").glob("*.attrs"))
    assert np.array_equal(none.vertices, first.vertices)


# ------------------------------------------------------------------------------------------------------- the CLI


def test_cli_attributes_option_and_render_color(tmp_path, capsys):
    from plyfile import PlyData, PlyElement

    from tiled_gridpull.pipeline.cli import main

    pts = unit_sphere_points(3000, seed=2)
    v = np.empty(len(pts), [("x", "f8"), ("y", "f8"), ("z", "f8"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                            ("intensity", "f4")])
    v["x"], v["y"], v["z"] = pts.T
    v["red"], v["green"], v["blue"] = 200, 100, 0
    v["intensity"] = pts[:, 2]
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "c.ply"))
    common = ["-q", "--resolution", "24", "--iterations", "30", "--set", "coarse_iterations=30"]
    assert main(["reconstruct", str(tmp_path / "c.ply"), "-o", str(tmp_path / "rgb.ply"), "--attributes", "rgb",
                 *common]) == 0
    assert set(read_mesh(tmp_path / "rgb.ply").vertex_attributes) == {"red", "green", "blue"}
    assert main(["reconstruct", str(tmp_path / "c.ply"), "-o", str(tmp_path / "all.ply"), *common]) == 0
    assert set(read_mesh(tmp_path / "all.ply").vertex_attributes) == {"red", "green", "blue", "intensity"}
    assert json.loads((tmp_path / "all.json").read_text())["vertex_attributes"]["rule"] == "all"
    assert main(["reconstruct", str(tmp_path / "c.ply"), "-o", str(tmp_path / "none.ply"), "--attributes", "none",
                 *common]) == 0
    assert read_mesh(tmp_path / "none.ply").vertex_attributes == {}
    pytest.importorskip("pyvista")
    from PIL import Image

    assert main(["render", str(tmp_path / "all.ply"), "-o", str(tmp_path / "rgb.png"), "--color", "rgb",
                 "--size", "160", "120"]) == 0
    img = np.asarray(Image.open(tmp_path / "rgb.png").convert("RGB")).astype(int)
    # the sphere's colour (200, 100, 0) shaded: red well above green, green above blue, somewhere in the picture
    assert np.any((img[..., 0] > img[..., 1] + 30) & (img[..., 1] > img[..., 2] + 20))
    assert main(["render", str(tmp_path / "all.ply"), "-o", str(tmp_path / "i.png"), "--color", "intensity",
                 "--size", "160", "120"]) == 0
    assert (tmp_path / "i.png").stat().st_size > 0
    capsys.readouterr()
    code = main(["render", str(tmp_path / "none.ply"), "-o", str(tmp_path / "x.png"), "--color", "classification"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "no vertex classification" in err[0]
    assert not (tmp_path / "x.png").exists()


@pytest.mark.slow
def test_cli_tiled_mode_takes_attributes_rgb(tmp_path, capsys):
    from tiled_gridpull.pipeline.cli import main

    src = _terrain_ply(tmp_path / "g.ply")
    out = tmp_path / "scene.ply"
    code = main(["reconstruct", str(src), "-o", str(out), "-q", "--voxel-size", "0.2", "--tile-size", "6.4",
                 "--overlap", "1.6", "--attributes", "rgb", "--workers", "1", "--set", "iterations=60",
                 "--set", "refine_m2=6", "--set", "coarse_iterations=60", "--tile-meshes", str(tmp_path / "tiles")])
    assert code == 0, capsys.readouterr().err
    mesh = read_mesh(out)
    assert set(mesh.vertex_attributes) == {"red", "green", "blue"}  # not the classification
    assert np.median(np.abs(mesh.vertex_attributes["red"] - _ramp(mesh.vertices[:, 0], X0, X0 + EXTENT))) <= 3.0
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["tiling"]["attributes"] == "rgb" and side["vertex_attributes"]["rule"] == "rgb"
    tiles = sorted((tmp_path / "tiles").glob("*.ply"))
    assert tiles and all(set(read_mesh(t).vertex_attributes) == {"red", "green", "blue"} for t in tiles)


def test_colours_of_other_libraries_go_in_and_come_back():
    trimesh = pytest.importorskip("trimesh")
    o3d = pytest.importorskip("open3d")
    pv = pytest.importorskip("pyvista")
    m = _quad()
    for c, value in (("red", 200), ("green", 100), ("blue", 0)):
        m.vertex_attributes[c] = np.full(4, value, np.uint8)
    for back in (Mesh.from_trimesh(m.to_trimesh()), Mesh.from_open3d(m.to_open3d()),
                 Mesh.from_pyvista(m.to_pyvista())):
        assert [int(back.vertex_attributes[c][0]) for c in ("red", "green", "blue")] == [200, 100, 0]
    # a coloured cloud of each library is meshed with its colour
    pts = unit_sphere_points(3000, seed=4)
    rgb = np.tile(np.array([[10, 20, 30]], np.uint8), (len(pts), 1))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.colors = o3d.utility.Vector3dVector(rgb / 255.0)
    poly = pv.PolyData(pts)
    poly.point_data["RGB"] = rgb
    for obj in (trimesh.PointCloud(pts, colors=rgb), pc, poly):
        mesh = reconstruct(obj, resolution=24, iterations=30, coarse_iterations=30)
        assert [set(mesh.vertex_attributes[c].tolist()) for c in ("red", "green", "blue")] == [{10}, {20}, {30}]


def test_pcd_packed_rgb_pts_and_e57_colours_are_read(tmp_path):
    packed = float(np.array([0x00C86400], np.uint32).view(np.float32)[0])  # (200, 100, 0), as PCL packs it
    rows = [f"{x} {y} 1 {packed!r}" for x, y in ((0, 0), (1, 0), (0, 1), (1, 1))]
    header = ["VERSION 0.7", "FIELDS x y z rgb", "SIZE 4 4 4 4", "TYPE F F F F", "COUNT 1 1 1 1", "WIDTH 4",
              "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", "POINTS 4", "DATA ascii"]
    (tmp_path / "c.pcd").write_text("\n".join(header + rows) + "\n")
    a = read_points(tmp_path / "c.pcd", clean=False).attributes
    assert [a[c].tolist() for c in ("red", "green", "blue")] == [[200] * 4, [100] * 4, [0] * 4]
    pts = "\n".join(f"{i} {i % 3} {i % 5} 7 10 20 30" for i in range(12))
    (tmp_path / "s.pts").write_text("12\n" + pts + "\n")
    a = read_points(tmp_path / "s.pts", clean=False).attributes
    assert a["red"].dtype == np.uint8 and set(a["green"]) == {20} and set(a["intensity"]) == {7}
    pye57 = pytest.importorskip("pye57")
    e57 = pye57.E57(str(tmp_path / "c.e57"), mode="w")
    n = 20
    e57.write_scan_raw({"cartesianX": np.arange(n, dtype=float), "cartesianY": np.arange(n) % 3.0,
                        "cartesianZ": np.arange(n) % 7.0, "colorRed": np.full(n, 200, np.uint8),
                        "colorGreen": np.full(n, 100, np.uint8), "colorBlue": np.zeros(n, np.uint8)})
    e57.close()
    a = read_points(tmp_path / "c.e57", clean=False).attributes
    assert set(a["red"]) == {200} and set(a["blue"]) == {0}
    assert "scan" not in select_attributes(a, "all")  # the scan number is the reader's, not the surface's


def test_kinect_office_colours_are_read():
    a = read_points(shared_file("indoor", "office1.pcd"), clean=False).attributes
    assert a["red"].dtype == np.uint8 and len(a["red"]) == 307_200
    assert len(np.unique(a["red"])) > 100  # a photograph's colours, not one constant


def test_changing_attributes_reuses_the_solves_and_remakes_the_pieces(tiled):
    """The attribute spill files sit beside the point spill files, which are unchanged: the solves are keyed on
    those and stay; the pieces are keyed on the attributes too and are made again."""
    import dataclasses
    import shutil

    from tiled_gridpull.tiled_job import reconstruct_scene

    d, tiling, first = tiled
    shutil.copytree(d / "job", d / "job_rgb")
    rgb = reconstruct_scene([str(d / "g.ply")], d / "rgb.ply", dataclasses.replace(tiling, attributes="rgb"),
                            SOLVER, d / "job_rgb")
    assert rgb.metadata["reused"] == {"partition": False, "solves": 4, "meshes": 0}
    assert list(rgb.vertex_attributes) == ["red", "green", "blue"]
    assert np.array_equal(rgb.vertex_attributes["red"], first.vertex_attributes["red"])


@pytest.mark.parametrize("kind", ["COPC", "EPT", "EPT-binary"])
def test_indexed_inputs_carry_attributes_as_their_stream_does(tmp_path, monkeypatch, kind):
    """Tiles read from an index (COPC, EPT) keep the same attribute spill files, byte for byte, as one streaming
    pass over the same file."""
    from pathlib import Path

    from tiled_gridpull import prepare
    from tiled_gridpull.io.indexed_write import write_copc, write_ept
    from tiled_gridpull.jobdir import JobPaths
    from tiled_gridpull.partition import read_tile_attributes, read_tile_points
    from tiled_gridpull.tiling import TilingConfig

    xyz = terrain(EXTENT, 30, seed=7)
    inten = np.round(_ramp(xyz[:, 0], X0, X0 + EXTENT) * 100).astype(np.uint16)
    if kind == "COPC":
        pytest.importorskip("copclib", reason="writing COPC test files needs copclib")
        src = write_copc(tmp_path / "s.copc.laz", xyz, max_node_points=2000, intensity=inten)
    else:
        src = write_ept(tmp_path / "ept", xyz, max_node_points=2000, intensity=inten,
                        data_type="binary" if kind == "EPT-binary" else "laszip")
    tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
    _, indexed, scan = prepare.prepare_job([str(src)], tiling, JobPaths(tmp_path / "a"))
    assert "intensity" in dict(scan["attributes"])
    with monkeypatch.context() as m:
        m.setattr(prepare, "all_indexed", lambda inputs: False)
        _, streamed, _ = prepare.prepare_job([str(src)], tiling, JobPaths(tmp_path / "b"))
    by_name = {s.name: s for s in streamed}
    assert sorted(by_name) == sorted(s.name for s in indexed)
    for spec in indexed:
        other = by_name[spec.name]
        assert spec.attributes == other.attributes
        assert Path(spec.attributes_path).read_bytes() == Path(other.attributes_path).read_bytes()
        local, _ = read_tile_points(spec)
        world_x = local[:, 0].astype(np.float64) + spec.block.low_corner[0]
        got = read_tile_attributes(spec)["intensity"].astype(float)
        assert np.allclose(got, np.round(_ramp(world_x, X0, X0 + EXTENT) * 100), atol=2)  # float32 offsets


def test_dry_run_says_what_is_carried_and_a_config_key_chooses_in_one_shape_mode(tmp_path, capsys):
    from tiled_gridpull.pipeline.cli import main

    src = _terrain_ply(tmp_path / "g.ply")
    tiled = ["--voxel-size", "0.2", "--tile-size", "6.4", "--overlap", "1.6", "--set", "refine_m2=6", "--dry-run"]
    assert main(["reconstruct", str(src), "-o", str(tmp_path / "d.ply"), *tiled]) == 0
    assert "carrying red, green, blue, classification onto the vertices" in capsys.readouterr().out
    assert main(["reconstruct", str(src), "-o", str(tmp_path / "d.ply"), *tiled, "--attributes", "none"]) == 0
    assert "carrying" not in capsys.readouterr().out
    (tmp_path / "c.yaml").write_text("attributes: rgb\nresolution: 24\niterations: 30\ncoarse_iterations: 30\n")
    pts = unit_sphere_points(2000, seed=3)
    cloud_file = tmp_path / "s.ply"
    write_mesh(Mesh(pts, np.zeros((0, 3)), {}, {"red": np.full(len(pts), 9, np.uint8),
                                                "green": np.full(len(pts), 8, np.uint8),
                                                "blue": np.full(len(pts), 7, np.uint8),
                                                "classification": np.full(len(pts), 6, np.uint8)}), cloud_file)
    assert main(["reconstruct", str(cloud_file), "-o", str(tmp_path / "o.ply"), "-q", "--config",
                 str(tmp_path / "c.yaml")]) == 0
    assert set(read_mesh(tmp_path / "o.ply").vertex_attributes) == {"red", "green", "blue"}


def test_float32_ply_keeps_attributes(tmp_path):
    m = _quad()
    m.vertices[:] += [500000.0, 4000000.0, 10.0]
    write_mesh(m, tmp_path / "f.ply", float32=True)
    back = read_mesh(tmp_path / "f.ply")
    assert np.allclose(back.vertices, m.vertices, atol=1e-3)
    for name, values in m.vertex_attributes.items():
        assert np.array_equal(back.vertex_attributes[name], values)


def test_memory_estimate_counts_the_attribute_interpolation():
    import dataclasses

    from tiled_gridpull.memory import tile_memory
    from tiled_gridpull.tile_plan import plan_tiles
    from tiled_gridpull.tiling import TilingConfig

    tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
    plan = plan_tiles(np.array([[0, 0, 0], [6, 6, 1.0]]), 100_000, tiling)
    spec = plan.spec((0, 0, 0), n_points=100_000)
    occ = np.ones(tuple(-(-np.asarray(spec.block.shape) // 8)), bool)
    plain = tile_memory(spec, occ, SOLVER, tiling)["mesh"]
    carried = tile_memory(dataclasses.replace(spec, attributes=(("red", "<u2"), ("classification", "|u1"))), occ,
                          SOLVER, tiling)["mesh"]
    assert carried > plain  # 100,000 x (24 + 2 x 3) bytes, times the untracked allowance
