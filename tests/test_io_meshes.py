"""Mesh files (tiled_gridpull.io.meshes): round trips for every format written or read, one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tiled_gridpull import InputError, Mesh
from tiled_gridpull.io.meshes import (ply_offset, read_mesh, read_sidecar, sidecar_path, write_mesh,
                                      write_mesh_and_sidecar, write_sidecar)


def octahedron(offset=(0.0, 0.0, 0.0), scale: float = 1.0) -> Mesh:
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float) * scale
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return Mesh(v + np.asarray(offset), f)


UTM = (512345.678912, 4123456.789123, 87.654321)


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".PLY"])
def test_round_trip_is_exact(tmp_path, suffix):
    """float64 PLY and OBJ (%.17g) keep every bit of georeferenced coordinates, and the faces in order."""
    rng = np.random.default_rng(3)
    m = octahedron(UTM, scale=3.0)
    m.vertices += rng.normal(scale=1e-3, size=m.vertices.shape)
    out = write_mesh(m, tmp_path / f"m{suffix}")
    assert out.exists()
    back = read_mesh(out)
    np.testing.assert_array_equal(back.vertices, m.vertices)
    np.testing.assert_array_equal(back.faces, m.faces)
    assert back.metadata["source"] == str(out)


def test_float32_ply_keeps_millimetres_at_utm_magnitudes(tmp_path):
    m = octahedron(UTM, scale=50.0)
    out = write_mesh(m, tmp_path / "m.ply", float32=True)
    raw = out.read_bytes()
    header = raw[: raw.index(b"end_header")].decode()
    assert "property float x" in header
    assert "comment offset 512295.000000 4123406.000000 37.000000" in header  # bbox minimum floored
    assert "comment generator tiled_gridpull" in header
    back = read_mesh(out)
    assert np.abs(back.vertices - m.vertices).max() < 1e-5  # float32 relative to a metre-rounded offset
    np.testing.assert_array_equal(back.faces, m.faces)
    # half the vertex bytes of the float64 file
    full = write_mesh(m, tmp_path / "full.ply").read_bytes()
    body = len(raw) - raw.index(b"end_header\n") - 11
    full_body = len(full) - full.index(b"end_header\n") - 11
    assert full_body - body == m.n_vertices * 3 * 4


def test_float32_ply_with_an_explicit_offset(tmp_path):
    m = octahedron(UTM)
    out = write_mesh(m, tmp_path / "m.ply", float32=True, offset=np.array([512000.0, 4123000.0, 0.0]))
    assert b"comment offset 512000.000000 4123000.000000 0.000000" in out.read_bytes()[:400]
    assert np.abs(read_mesh(out).vertices - m.vertices).max() < 1e-4


def test_metadata_generator_and_crs_go_to_the_ply_header_one_line_each(tmp_path):
    m = octahedron()
    m.metadata.update(generator="tiled_gridpull 9.9", crs='PROJCS["x",\n  UNIT["metre",1]]')
    raw = write_mesh(m, tmp_path / "m.ply").read_bytes()
    header = raw[: raw.index(b"end_header")].decode()
    assert "comment generator tiled_gridpull 9.9" in header
    # a pretty-printed WKT is kept whole, on its one comment line
    assert 'comment crs PROJCS["x", UNIT["metre",1]]\n' in header
    assert len([ln for ln in header.splitlines() if ln.startswith("comment")]) == 2


def test_obj_starts_with_the_generator_marker(tmp_path):
    out = write_mesh(octahedron(), tmp_path / "m.obj")
    assert out.read_text().splitlines()[0] == "# generator tiled_gridpull"


def test_ply_offset_is_trusted_only_beside_our_generator():
    assert np.array_equal(ply_offset(["generator tiled_gridpull 1.0", "offset 1 2 3"]), [1.0, 2.0, 3.0])
    assert ply_offset(["generator other-tool", "offset 1 2 3"]) is None
    assert ply_offset(["offset 1 2 3"]) is None
    # beside our marker the offset is applied: a damaged one is refused, not ignored (vertices off by it)
    for bad in ("1 nan 3", "a b c", "1 2", "1e308 0 0"):
        with pytest.raises(InputError, match=f"m.ply: the PLY header's offset '{bad}'"):
            ply_offset(["generator tiled_gridpull", f"offset {bad}"], "m.ply")


def test_another_tools_offset_comment_is_not_applied(tmp_path):
    m = octahedron()
    out = write_mesh(m, tmp_path / "m.ply")
    raw = out.read_bytes().replace(b"format binary_little_endian 1.0\n",
                                   b"format binary_little_endian 1.0\ncomment offset 100 200 300\n")
    out.write_bytes(raw)
    np.testing.assert_array_equal(read_mesh(out).vertices, m.vertices)


def test_reads_ascii_ply_with_quads(tmp_path):
    p = tmp_path / "quad.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
                 "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
                 "0 0 0\n1 0 0\n1 1 0\n0 1 0\n0.5 0.5 1\n4 0 1 2 3\n3 0 1 4\n")
    m = read_mesh(p)
    assert m.n_vertices == 5
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3], [0, 1, 4]])  # the quad fan-triangulated


def test_reads_obj_with_texture_indices_polygons_and_negative_indices(tmp_path):
    p = tmp_path / "m.obj"
    p.write_text("# comment\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n"
                 "f 1/1/1 2/1/1 3/1/1 4/1/1\nf -4 -3 -1\n")
    m = read_mesh(p)
    np.testing.assert_array_equal(m.vertices[3], [0, 1, 0])
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3], [0, 1, 3]])


@pytest.mark.parametrize("text", [
    "OFF\n4 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n3 0 2 3\n",
    "OFF 4 1 0\n# a comment\n0 0 0\n1 0 0\n1 1 0  # trailing comment\n0 1 0\n4 0 1 2 3\n",
])
def test_reads_off(tmp_path, text):
    p = tmp_path / "m.off"
    p.write_text(text)
    m = read_mesh(p)
    np.testing.assert_array_equal(m.vertices, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3]])


def test_off_is_read_but_not_written(tmp_path):
    with pytest.raises(InputError, match=r"unknown mesh format '\.off' \(use \.ply or \.obj\)"):
        write_mesh(octahedron(), tmp_path / "m.off")
    assert not (tmp_path / "m.off").exists()


def one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg, "errors must be one line"
    return msg


@pytest.mark.parametrize("name, content, expected", [
    ("missing.ply", None, "file not found"),
    ("m.stl", b"solid x\n", "unknown mesh format '.stl' (expected .ply, .obj or .off)"),
    ("garbage.ply", b"not a ply at all\n\n\x00\x01", "cannot read mesh"),
    ("truncated.ply", "TRUNC", "cannot read mesh"),
    ("empty.obj", b"# nothing\n", "mesh has no vertices"),
    ("nofaces.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "mesh has no faces"),
    ("range.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "face indices out of range"),
    ("nan.obj", b"v 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n", "non-finite vertex coordinates"),
    ("bad.obj", b"v 0 zero 0\n", "cannot read mesh (ValueError:"),
    ("notoff.off", b"PLY\n3 1 0\n", "not an OFF file"),
    ("short.off", b"OFF\n3 1 0\n0 0 0\n", "cannot read mesh (IndexError:"),
    ("novertex.ply", (b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\n"
                      b"end_header\n"), "PLY has no vertex element"),
])
def test_bad_input_raises_one_line_input_errors(tmp_path, name, content, expected):
    p = tmp_path / name
    if content == "TRUNC":
        p.write_bytes(write_mesh(octahedron(), tmp_path / "ok.ply").read_bytes()[:-20])
    elif content is not None:
        p.write_bytes(content)
    with pytest.raises(InputError) as exc:
        read_mesh(p)
    msg = one_line(exc)
    assert msg.startswith(str(p) + ": ")
    assert expected in msg


def test_sidecar_round_trip(tmp_path):
    mesh_path = tmp_path / "scene.ply"
    meta = {"generator": "tiled_gridpull", "tiles": 4, "box": [1.5, 2.5]}
    side = write_sidecar(mesh_path, meta)
    assert side == sidecar_path(mesh_path) == tmp_path / "scene.json"
    assert read_sidecar(mesh_path) == meta


def test_mesh_and_sidecar_written_together(tmp_path):
    m = octahedron(UTM)
    m.metadata.update(generator="tiled_gridpull", note="x")
    out = write_mesh_and_sidecar(m, tmp_path / "scene.obj")
    np.testing.assert_array_equal(read_mesh(out).vertices, m.vertices)
    assert json.loads((tmp_path / "scene.json").read_text())["note"] == "x"


def test_unwritable_sidecar_leaves_no_mesh(tmp_path):
    (tmp_path / "scene.json").mkdir()  # a directory where the sidecar goes
    with pytest.raises(InputError, match="a directory stands where this file is to be written"):
        write_mesh_and_sidecar(octahedron(), tmp_path / "scene.ply")
    assert not (tmp_path / "scene.ply").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.json"]  # no temporary files left either


def test_failed_write_keeps_the_previous_file(tmp_path):
    out = write_mesh(octahedron(), tmp_path / "m.ply")
    before = out.read_bytes()
    bad = Mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]))
    bad.faces = "not an array"  # fails while writing, after the temporary file was opened
    with pytest.raises(ValueError):
        write_mesh(bad, out)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]
