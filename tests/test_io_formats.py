"""Tests for the point-cloud readers (tiled_gridpull.io): every format, the real shared data, corrupted input."""

from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tiled_gridpull.errors import ConfigError, InputError
from tiled_gridpull.io import (SUPPORTED_POINT_FORMATS, iter_point_chunks, point_count, read_kitti_sequence,
                               read_points)
from tiled_gridpull.io.input_errors import input_errors
from conftest import shared_file as shared  # a path under ../shared/data, or skip


# ---------------------------------------------------------------------------------------------------- writers


def cloud_xyz(n: int = 20, seed: int = 0, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Non-degenerate points whose values survive float32 and 3-decimal text exactly (multiples of 1/8)."""
    rng = np.random.default_rng(seed)
    pts = rng.integers(-80, 80, size=(n, 3)) / 8.0
    pts = np.unique(pts, axis=0)[:n]
    rng.shuffle(pts)
    return pts + np.asarray(offset)


def unit_normals(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def write_ply(path: Path, xyz, normals=None, *, fmt="binary_little_endian", vtype="double", faces=None,
              extra_elements="") -> Path:
    props = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals is not None else [])
    data = np.asarray(xyz, dtype=np.float64)
    if normals is not None:
        data = np.column_stack([data, normals])
    header = ["ply", f"format {fmt} 1.0", f"element vertex {len(data)}"]
    header += [f"property {vtype} {p}" for p in props]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header += [extra_elements] if extra_elements else []
    header.append("end_header")
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode())
        if fmt == "ascii":
            for row in data:
                fh.write((" ".join(repr(float(v)) for v in row) + "\n").encode())
            for f in faces if faces is not None else []:
                fh.write((f"{len(f)} " + " ".join(map(str, f)) + "\n").encode())
        else:
            bo = "<" if fmt == "binary_little_endian" else ">"
            code = "f8" if vtype == "double" else "f4"
            fh.write(data.astype(bo + code).tobytes())
            if faces is not None:
                rec = np.empty(len(faces), dtype=[("n", "u1"), ("v", bo + "i4", (3,))])
                rec["n"] = 3
                rec["v"] = faces
                fh.write(rec.tobytes())
    return path


def write_las(path: Path, xyz, *, scale=0.001, offset=None, intensity=None, normals=None, version="1.2",
              point_format=3) -> Path:
    import laspy

    xyz = np.asarray(xyz, dtype=np.float64)
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales = np.array([scale] * 3)
    header.offsets = np.floor(xyz.min(axis=0)) if offset is None else np.asarray(offset)
    if normals is not None:
        header.add_extra_dims([laspy.ExtraBytesParams(name=n, type=np.float32)
                               for n in ("NormalX", "NormalY", "NormalZ")])
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if intensity is not None:
        las.intensity = intensity
    if normals is not None:
        las.NormalX, las.NormalY, las.NormalZ = normals[:, 0], normals[:, 1], normals[:, 2]
    las.write(str(path))
    return path


def write_bin(path: Path, xyz, refl=None) -> Path:
    xyz = np.asarray(xyz, dtype=np.float32)
    refl = np.zeros(len(xyz), np.float32) if refl is None else np.asarray(refl, np.float32)
    np.column_stack([xyz, refl]).astype("<f4").tofile(path)
    return path


def write_text(path: Path, xyz, extra=None, *, delimiter=" ", header: str | None = None) -> Path:
    data = np.asarray(xyz, dtype=np.float64)
    if extra is not None:
        data = np.column_stack([data, extra])
    with open(path, "w") as fh:
        if header is not None:
            fh.write(header + "\n")
        for row in data:
            fh.write(delimiter.join(repr(float(v)) for v in row) + "\n")
    return path


def write_cloud(path: Path, xyz) -> Path:
    """Write xyz in the format chosen by the suffix of ``path``."""
    s = path.suffix.lower()
    if s == ".ply":
        return write_ply(path, xyz)
    if s in (".las", ".laz"):
        return write_las(path, xyz)
    if s == ".npy":
        np.save(path, np.asarray(xyz, dtype=np.float64))
        return path
    if s == ".bin":
        return write_bin(path, xyz)
    if s == ".e57":
        import pye57

        a = np.asarray(xyz, dtype=np.float64)
        e57 = pye57.E57(str(path), mode="w")
        e57.write_scan_raw({"cartesianX": a[:, 0], "cartesianY": a[:, 1], "cartesianZ": a[:, 2]})
        e57.close()
        return path
    if s == ".pcd":
        from pypcd4 import Encoding
        from pypcd4 import PointCloud as PcdCloud

        a = np.asarray(xyz, dtype=np.float64)  # 8-byte fields: exact, like the other formats
        PcdCloud.from_points([a[:, 0], a[:, 1], a[:, 2]], ("x", "y", "z"), (np.float64,) * 3).save(
            path, encoding=Encoding.BINARY_COMPRESSED)
        return path
    return write_text(path, xyz, delimiter="," if s == ".csv" else " ")


ALL_SUFFIXES = [".ply", ".xyz", ".txt", ".pts", ".csv", ".npy", ".las", ".laz", ".bin", ".pcd", ".e57"]


# ------------------------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("suffix", ALL_SUFFIXES)
def test_round_trip_every_format(tmp_path, suffix):
    xyz = cloud_xyz(25)
    p = write_cloud(tmp_path / f"c{suffix}", xyz)
    cloud = read_points(p)
    assert cloud.xyz.dtype == np.float64 and cloud.xyz.shape == (25, 3)
    if suffix in (".las", ".laz"):
        np.testing.assert_allclose(cloud.xyz, xyz, rtol=0, atol=1e-9)
    else:
        np.testing.assert_array_equal(cloud.xyz, xyz)
    assert cloud.report["points_kept"] == 25
    assert cloud.source == str(p)


@pytest.mark.parametrize("suffix", ALL_SUFFIXES)
def test_point_count_agrees_with_read(tmp_path, suffix):
    p = write_cloud(tmp_path / f"c{suffix}", cloud_xyz(33))
    assert point_count(p) == len(read_points(p).xyz) == 33


def test_suffix_is_case_insensitive(tmp_path):
    xyz = cloud_xyz(12)
    p = write_ply(tmp_path / "UPPER.PLY", xyz)
    np.testing.assert_array_equal(read_points(p).xyz, xyz)


def test_supported_formats_tuple():
    # EPT (".json": an ept.json beside its node files) is tested in test_io_indexed.py
    assert set(ALL_SUFFIXES) | {".json"} == set(SUPPORTED_POINT_FORMATS)


def test_text_comments_header_and_normals(tmp_path):
    xyz, nrm = cloud_xyz(15), unit_normals(15)
    p = tmp_path / "n.xyz"
    write_text(p, xyz, nrm)
    body = p.read_text()
    p.write_text("# made by a test\n// another comment\n\n" + body + "# trailing comment\n")
    cloud = read_points(p)
    np.testing.assert_array_equal(cloud.xyz, xyz)
    assert cloud.normals.dtype == np.float32
    np.testing.assert_allclose(cloud.normals, nrm, atol=1e-6)
    assert point_count(p) == 15


def test_csv_with_header_row(tmp_path):
    xyz = cloud_xyz(11)
    p = write_text(tmp_path / "h.csv", xyz, delimiter=",", header="x,y,z")
    np.testing.assert_array_equal(read_points(p).xyz, xyz)
    assert point_count(p) == 11


def test_pts_with_count_line_and_intensity(tmp_path):
    xyz = cloud_xyz(14)
    inten = np.arange(14, dtype=float)
    rgb = np.tile([10.0, 20.0, 30.0], (14, 1))
    p = write_text(tmp_path / "s.pts", xyz, np.column_stack([inten, rgb]), header="14")
    cloud = read_points(p)
    np.testing.assert_array_equal(cloud.xyz, xyz)
    assert cloud.normals is None
    np.testing.assert_array_equal(cloud.attributes["intensity"], inten)
    assert point_count(p) == 14


def test_xyz_rgb_columns_are_not_normals(tmp_path):
    xyz = cloud_xyz(12)
    rgb = np.tile([255.0, 128.0, 0.0], (12, 1))
    p = write_text(tmp_path / "rgb.xyz", xyz, rgb)
    with pytest.warns(UserWarning, match="not read as normals"):
        cloud = read_points(p)
    assert cloud.normals is None
    np.testing.assert_array_equal(cloud.attributes["extra_columns"], rgb)


def test_text_too_few_columns(tmp_path):
    p = tmp_path / "two.xyz"
    p.write_text("1 2\n3 4\n")
    with pytest.raises(InputError, match=r"two\.xyz: expected at least 3 numeric columns"):
        read_points(p)


def test_text_ragged_rows(tmp_path):
    p = tmp_path / "ragged.txt"
    p.write_text("1 2 3\n4 5 6\n7 8\n")
    with pytest.raises(InputError, match=r"ragged\.txt: truncated or corrupted"):
        read_points(p)


def test_npy_with_normals_and_structured(tmp_path):
    xyz, nrm = cloud_xyz(16), unit_normals(16)
    p = tmp_path / "n.npy"
    np.save(p, np.column_stack([xyz, nrm]))
    cloud = read_points(p)
    np.testing.assert_array_equal(cloud.xyz, xyz)
    np.testing.assert_allclose(cloud.normals, nrm, atol=1e-6)
    rec = np.zeros(16, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    rec["x"], rec["y"], rec["z"] = xyz.T
    q = tmp_path / "s.npy"
    np.save(q, rec)
    np.testing.assert_array_equal(read_points(q).xyz, xyz)
    assert point_count(q) == 16


def test_npy_wrong_shape(tmp_path):
    p = tmp_path / "bad.npy"
    np.save(p, np.zeros((10, 2)))
    with pytest.raises(InputError, match=r"bad\.npy: expected an \(N, 3\)"):
        read_points(p)
    np.save(p, np.array(["a", "b"]))
    with pytest.raises(InputError, match=r"bad\.npy"):
        read_points(p)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_with_normals(tmp_path, fmt):
    xyz, nrm = cloud_xyz(18), unit_normals(18)
    p = write_ply(tmp_path / "n.ply", xyz, nrm, fmt=fmt)
    cloud = read_points(p)
    np.testing.assert_array_equal(cloud.xyz, xyz)
    assert cloud.normals.dtype == np.float32
    np.testing.assert_allclose(cloud.normals, nrm, atol=1e-6)
    assert point_count(p) == 18


def test_ply_mesh_vertices_are_read(tmp_path):
    xyz = cloud_xyz(12)
    faces = np.array([[0, 1, 2], [2, 3, 4], [5, 6, 7]])
    for fmt in ("ascii", "binary_little_endian"):
        p = write_ply(tmp_path / f"mesh_{fmt}.ply", xyz, faces=faces, fmt=fmt)
        np.testing.assert_array_equal(read_points(p).xyz, xyz)


def test_ply_float_ascii_keeps_written_digits(tmp_path):
    # A 'property float' ASCII file with UTM-size values: the digits written are kept (parsed as float64).
    xyz = cloud_xyz(12, offset=(500000.0, 4000000.0, 100.0)) + 0.001
    p = write_ply(tmp_path / "f.ply", xyz, fmt="ascii", vtype="float")
    np.testing.assert_allclose(read_points(p).xyz, xyz, rtol=0, atol=1e-6)


def test_ply_list_property_in_vertex_uses_plyfile(tmp_path):
    xyz = cloud_xyz(12)
    p = tmp_path / "lists.ply"
    lines = ["ply", "format ascii 1.0", "element vertex 12", "property float x", "property float y",
             "property float z", "property list uchar int idx", "end_header"]
    lines += [f"{x} {y} {z} 2 7 8" for x, y, z in xyz]
    p.write_text("\n".join(lines) + "\n")
    np.testing.assert_array_equal(read_points(p).xyz, xyz)


def test_ply_offset_comment_from_write_mesh(tmp_path):
    from tiled_gridpull.io import write_mesh
    from tiled_gridpull.mesh import Mesh

    xyz = cloud_xyz(12, offset=(500000.0, 4000000.0, 10.0))
    p = tmp_path / "m.ply"
    write_mesh(Mesh(xyz, np.array([[0, 1, 2]]), {}), p, float32=True)
    np.testing.assert_allclose(read_points(p).xyz, xyz, rtol=0, atol=1e-6)


def test_ply_offset_comment_of_another_tool_is_not_applied(tmp_path):
    """Another writer's ``comment offset x y z`` may mean anything: only this package's files are shifted."""
    from tiled_gridpull.io import read_mesh

    xyz = cloud_xyz(12)
    p = tmp_path / "other.ply"
    head = ("ply\nformat ascii 1.0\ncomment offset 1000 2000 3000\nelement vertex 12\nproperty double x\n"
            "property double y\nproperty double z\nelement face 1\nproperty list uchar int vertex_indices\n"
            "end_header\n")
    rows = "".join(f"{a!r} {b!r} {c!r}\n" for a, b, c in xyz.tolist()) + "3 0 1 2\n"
    p.write_text(head + rows)
    np.testing.assert_array_equal(read_points(p).xyz, xyz)
    np.testing.assert_array_equal(read_mesh(p).vertices, xyz)
    p.write_text(head.replace("comment offset", "comment generator tiled_gridpull 0.1.0\ncomment offset") + rows)
    np.testing.assert_allclose(read_points(p).xyz, xyz + [1000, 2000, 3000], rtol=0, atol=1e-9)
    np.testing.assert_allclose(read_mesh(p).vertices, xyz + [1000, 2000, 3000], rtol=0, atol=1e-9)


@pytest.mark.parametrize("offset", ["1e308 0 0", "nan 0 0", "0 inf 0", "-1e200 5 5", "1 two 3"])
def test_ply_absurd_offset_beside_our_generator_is_refused_naming_it(tmp_path, offset):
    """Our own file's offset is trusted: one that is not finite, or beyond what float64 arithmetic resolves
    (1e308 made the one-shape solve fail with LinAlgError), is damage, refused in one line naming it."""
    from tiled_gridpull.io import read_mesh

    xyz = cloud_xyz(12)
    p = tmp_path / "ours.ply"
    p.write_text("ply\nformat ascii 1.0\ncomment generator tiled_gridpull 0.1.0\n"
                 f"comment offset {offset}\nelement vertex 12\nproperty float x\nproperty float y\n"
                 "property float z\nend_header\n" + "".join(f"{a!r} {b!r} {c!r}\n" for a, b, c in xyz.tolist()))
    for read in (read_points, lambda q: next(iter_point_chunks(q)), read_mesh):
        with pytest.raises(InputError, match=rf"ours\.ply: .*offset '{offset}'"):
            read(p)


@pytest.mark.parametrize("scale,offset,needle", [
    (float("nan"), 0.0, "scale"), (0.0, 0.0, "scale"), (1e300, 0.0, "scale"),
    (0.001, 1e308, "offset"), (0.001, float("inf"), "offset"),
])
def test_las_absurd_scale_or_offset_is_refused_naming_it(tmp_path, scale, offset, needle):
    """laspy applies the header's scale and offset to every point: non-finite, zero or absurd ones
    are refused in one line naming them (not points that are all NaN, identical or overflowing)."""
    import laspy

    p = write_las(tmp_path / "bad.las", cloud_xyz(20), offset=[0.0, 0.0, 0.0])
    las = laspy.read(str(p))
    raw = p.read_bytes()
    # scales at bytes 131..155, offsets at 155..179 of the public header block (LAS 1.2)
    fields = np.frombuffer(raw[131:179], "<f8").copy()
    fields[0], fields[3] = scale, offset
    p.write_bytes(raw[:131] + fields.tobytes() + raw[179:])
    assert len(las.points) == 20
    for read in (read_points, lambda q: next(iter_point_chunks(q))):
        with pytest.raises(InputError, match=rf"bad\.las: .*{needle}"):
            read(p)


def test_ply_faces_but_no_vertices(tmp_path):
    p = tmp_path / "faces.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                 "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                 "3 0 1 2\n")
    with pytest.raises(InputError, match=r"faces\.ply: PLY has 1 faces but no vertices"):
        read_points(p)
    q = tmp_path / "novertex.ply"
    q.write_text("ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                 "3 0 1 2\n")
    with pytest.raises(InputError, match=r"novertex\.ply: PLY has no vertex element"):
        read_points(q)
    with pytest.raises(InputError, match="no vertex element"):
        point_count(q)


def test_ply_missing_coordinate_property(tmp_path):
    p = tmp_path / "xy.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                 "end_header\n1 2\n")
    with pytest.raises(InputError, match="no z property"):
        read_points(p)


def test_ply_huge_declared_count_is_refused_cheaply(tmp_path):
    for fmt in ("ascii", "binary_little_endian"):
        p = tmp_path / f"huge_{fmt}.ply"
        p.write_bytes(f"ply\nformat {fmt} 1.0\nelement vertex 999999999999\nproperty double x\n"
                      f"property double y\nproperty double z\nend_header\n".encode() + b"1 2 3\n" * 4)
        with pytest.raises(InputError, match="truncated PLY file"):
            read_points(p)


def test_las_intensity_normals_and_crs_absent(tmp_path):
    xyz, nrm = cloud_xyz(20), unit_normals(20)
    inten = np.arange(20, dtype=np.uint16) * 100
    p = write_las(tmp_path / "n.las", xyz, intensity=inten, normals=nrm, version="1.4", point_format=6)
    cloud = read_points(p)
    np.testing.assert_allclose(cloud.xyz, xyz, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(cloud.attributes["intensity"], inten)
    np.testing.assert_allclose(cloud.normals, nrm, atol=1e-6)
    assert cloud.crs is None
    assert point_count(p) == 20


def test_kitti_single_scan_round_trip(tmp_path):
    xyz = cloud_xyz(30)
    refl = np.linspace(0, 1, 30)
    p = write_bin(tmp_path / "000007.bin", xyz, refl)
    cloud = read_points(p)
    np.testing.assert_array_equal(cloud.xyz, xyz)
    np.testing.assert_array_equal(cloud.sensor, np.zeros((30, 3)))
    np.testing.assert_allclose(cloud.attributes["intensity"], refl, atol=1e-7)


def test_kitti_scan_bad_size(tmp_path):
    p = tmp_path / "bad.bin"
    p.write_bytes(b"\0" * 100)
    with pytest.raises(InputError, match=r"bad\.bin: corrupted KITTI scan .*not a multiple of 16"):
        read_points(p)
    with pytest.raises(InputError, match="not a multiple of 16"):
        point_count(p)


# -------------------------------------------------------------------------------------------------- real data


def test_real_bunny_scan_with_range_grid():
    p = shared("scans/stanford_bunny/bun000.ply")
    cloud = read_points(p)
    assert cloud.xyz.shape == (40256, 3) and cloud.xyz.dtype == np.float64
    assert cloud.normals is None
    assert point_count(p) == 40256
    # the bunny is about 0.16 m across
    assert 0.1 < np.ptp(cloud.xyz, axis=0).max() < 0.25


def test_real_bunny_agrees_with_plyfile():
    from plyfile import PlyData

    p = shared("scans/stanford_bunny/bun000.ply")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        v = PlyData.read(str(p))["vertex"].data
    ref = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    # plyfile parses 'property float' as float32; we parse the same text in float64
    np.testing.assert_allclose(read_points(p, clean=False).xyz, ref, rtol=0, atol=1e-7)


def test_real_autzen_laz():
    p = shared("lidar/autzen_trim.laz")
    cloud = read_points(p, clean=False)
    assert cloud.xyz.shape == (110000, 3) and cloud.xyz.dtype == np.float64
    lo, hi = cloud.xyz.min(axis=0), cloud.xyz.max(axis=0)
    # Oregon Lambert, international feet: ~636,000 E, ~849,000 N, 406-521 ft elevation
    assert 635_000 < lo[0] and hi[0] < 638_000 and 848_000 < lo[1] and hi[1] < 850_000
    assert 400 < lo[2] and hi[2] < 530
    assert 1100 < hi[0] - lo[0] < 1250 and 500 < hi[1] - lo[1] < 620
    # 0.01 ft scale: float64 keeps the hundredths
    assert np.allclose(np.round(cloud.xyz * 100), cloud.xyz * 100, atol=1e-5)
    assert cloud.crs is not None and "NAD_1983_HARN" in cloud.crs
    assert cloud.attributes["intensity"].shape == (110000,)
    assert point_count(p) == 110000


def test_real_laz_chunks_match_full_read():
    p = shared("lidar/autzen_trim.laz")
    full = read_points(p, clean=False)
    chunks = list(iter_point_chunks(p, chunk_size=30_000))
    assert [len(c) for c in chunks] == [30_000, 30_000, 30_000, 20_000]
    assert all(c.crs == full.crs for c in chunks)
    assert chunks[1].source == f"{p}[30000:60000]"
    np.testing.assert_array_equal(np.concatenate([c.xyz for c in chunks]), full.xyz)


def test_real_ahn3_has_duplicates():
    p = shared("lidar/ahn3_cropped_2.laz")
    cloud = read_points(p)
    assert cloud.report["points_read"] == 208_432 == point_count(p)
    assert cloud.report["duplicates_dropped"] + len(cloud.xyz) == 208_432
    assert cloud.crs is None  # the header does not state RD New


def test_real_kitti_scan():
    p = shared("kitti/000000.bin")
    cloud = read_points(p)
    assert cloud.xyz.shape == (124_668, 3)
    assert point_count(p) == 124_668
    assert np.abs(cloud.xyz).max() < 130
    np.testing.assert_array_equal(cloud.sensor, 0.0)


def test_real_text_scan():
    p = shared("meshes/abc_00016513_3d6966cd42eb44ab8f4224f2_trimesh_053_scan.xyz")
    cloud = read_points(p, clean=False)
    assert cloud.xyz.shape == (86_648, 3)
    assert point_count(p) == 86_648


def _cut(src: Path, dst: Path, fraction: float = 0.5) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    return dst


def test_truncated_laz(tmp_path):
    p = _cut(shared("lidar/autzen_trim.laz"), tmp_path / "half.laz")
    with pytest.raises(InputError, match=r"half\.laz: truncated or corrupted LAZ file"):
        read_points(p)
    with pytest.raises(InputError, match=r"half\.laz: truncated or corrupted LAZ file"):
        for _ in iter_point_chunks(p, chunk_size=30_000):
            pass


def test_truncated_las(tmp_path):
    import laspy

    las = laspy.read(str(shared("lidar/autzen_trim.laz")))
    full = tmp_path / "full.las"
    las.write(str(full))
    half = _cut(full, tmp_path / "half.las")
    with pytest.raises(InputError, match=r"half\.las: truncated"):
        read_points(half)
    # cut exactly at a record boundary: laspy alone would read 50,000 points "successfully"
    header = las.header
    boundary = tmp_path / "boundary.las"
    boundary.write_bytes(full.read_bytes()[: header.offset_to_point_data + 50_000 * header.point_format.size])
    with pytest.raises(InputError, match=r"boundary\.las: truncated LAS file"):
        read_points(boundary)
    with pytest.raises(InputError, match=r"boundary\.las: truncated"):
        list(iter_point_chunks(boundary, chunk_size=30_000))


def test_truncated_ply(tmp_path):
    half = _cut(shared("scans/stanford_bunny/bun000.ply"), tmp_path / "half.ply")
    with pytest.raises(InputError, match=r"half\.ply: truncated"):
        read_points(half)
    binary = write_ply(tmp_path / "bin.ply", cloud_xyz(500))
    bhalf = _cut(binary, tmp_path / "bhalf.ply")
    with pytest.raises(InputError, match=r"bhalf\.ply: truncated"):
        read_points(bhalf)
    header_only = _cut(binary, tmp_path / "hdr.ply", 0.02)
    with pytest.raises(InputError, match=r"hdr\.ply: truncated"):
        read_points(header_only)


# -------------------------------------------------------------------------------------------- KITTI sequences


def rot_z(quarter_turns: int) -> np.ndarray:
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][quarter_turns % 4]
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


def make_sequence(root: Path, n_frames=3, *, poses=None, calib=True, subdir=True, skip=()):
    scans = root / "velodyne" if subdir else root
    scans.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n_frames):
        xyz = cloud_xyz(10 + i, seed=i)
        frames.append(xyz)
        if i not in skip:
            write_bin(scans / f"{i:06d}.bin", xyz, np.full(len(xyz), i / 10))
    if poses is None:
        poses = []
        for i in range(n_frames):
            m = np.zeros((3, 4))
            m[:, :3] = rot_z(i)
            m[:, 3] = [10.0 * i, -2.0 * i, 0.5 * i]
            poses.append(m)
    lines = [" ".join(repr(float(v)) for v in m.ravel()) for m in poses]
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    # velodyne -> camera: x_cam = -y_velo, y_cam = -z_velo, z_cam = x_velo, plus a small shift
    tr = np.array([[0, -1, 0, 0.25], [0, 0, -1, -0.5], [1, 0, 0, 1.0]], dtype=np.float64)
    if calib == "identity":  # poses already in the velodyne frame: said so with an identity Tr
        tr = np.eye(4)[:3]
    if calib:
        (root / "calib.txt").write_text("P0: " + " ".join(["0"] * 12) + "\nTr: "
                                        + " ".join(repr(float(v)) for v in tr.ravel()) + "\n")
    return frames, poses, tr


def expected_world(frames, poses, tr, which):
    t4 = np.vstack([tr, [0, 0, 0, 1]])
    pts, origins, ids = [], [], []
    for i in which:
        m = np.vstack([poses[i], [0, 0, 0, 1]]) @ t4
        h = np.column_stack([frames[i], np.ones(len(frames[i]))])
        pts.append((m @ h.T).T[:, :3])
        origins.append(np.tile(m[:3, 3], (len(frames[i]), 1)))
        ids.append(np.full(len(frames[i]), i))
    return np.concatenate(pts), np.concatenate(origins), np.concatenate(ids)


@pytest.mark.parametrize("calib,subdir", [(True, True), ("identity", False)])
def test_kitti_sequence_world_transform(tmp_path, calib, subdir):
    frames, poses, tr = make_sequence(tmp_path / "seq", calib=calib, subdir=subdir)
    cloud = read_kitti_sequence(tmp_path / "seq")
    xyz, origins, ids = expected_world(frames, poses, tr, range(3))
    np.testing.assert_array_equal(cloud.xyz, xyz)
    np.testing.assert_array_equal(cloud.sensor, origins)
    assert cloud.attributes["frame"].dtype == np.int32
    np.testing.assert_array_equal(cloud.attributes["frame"], ids)
    # the sensor of frame i sits at pose_i @ Tr @ origin
    np.testing.assert_array_equal(cloud.sensor[cloud.attributes["frame"] == 2][0],
                                  poses[2][:, :3] @ tr[:, 3] + poses[2][:, 3])
    assert point_count(tmp_path / "seq") == len(xyz)
    # read_points on the directory is the same (plus cleaning)
    np.testing.assert_array_equal(read_points(tmp_path / "seq").xyz, xyz)


def test_kitti_sequence_frame_selection(tmp_path):
    frames, poses, tr = make_sequence(tmp_path / "seq")
    sub = read_kitti_sequence(tmp_path / "seq", frames=(1, 3))
    np.testing.assert_array_equal(sub.xyz, expected_world(frames, poses, tr, [1, 2])[0])
    pick = read_points(tmp_path / "seq", frames=[2, 0], clean=False)
    np.testing.assert_array_equal(pick.xyz, expected_world(frames, poses, tr, [2, 0])[0])
    np.testing.assert_array_equal(np.unique(pick.attributes["frame"]), [0, 2])
    with pytest.raises(ConfigError, match="selects no frames"):
        read_kitti_sequence(tmp_path / "seq", frames=(2, 2))
    with pytest.raises(ConfigError, match="repeats"):
        read_kitti_sequence(tmp_path / "seq", frames=[1, 1])


def test_kitti_chunks_frame_by_frame(tmp_path):
    frames, poses, tr = make_sequence(tmp_path / "seq")
    chunks = list(iter_point_chunks(tmp_path / "seq", chunk_size=7))
    xyz, origins, _ = expected_world(frames, poses, tr, range(3))
    np.testing.assert_array_equal(np.concatenate([c.xyz for c in chunks]), xyz)
    np.testing.assert_array_equal(np.concatenate([c.sensor for c in chunks]), origins)
    assert max(len(c) for c in chunks) <= 7


def test_the_partition_reads_a_sequence_frame_by_frame(tmp_path, monkeypatch):
    """The job's read of a KITTI sequence (prepare._chunks) streams it: no frame is loaded before the chunks of
    the frames before it are handed on, the sequence is never read whole, and the chunks, points, sensor origins
    and frame range are those of the sequence read whole."""
    from tiled_gridpull import prepare
    from tiled_gridpull.io import kitti

    frames, poses, tr = make_sequence(tmp_path / "seq", n_frames=4)
    monkeypatch.setattr(kitti, "read_kitti_sequence", lambda *a, **k: pytest.fail("the sequence was read whole"))
    loaded = []
    load = kitti._load_kitti_scan
    monkeypatch.setattr(kitti, "_load_kitti_scan", lambda p: loaded.append(p.stem) or load(p))
    chunks = prepare._chunks([str(tmp_path / "seq")], 5, (1, 4))
    first = next(chunks)
    assert len(loaded) == 1 and len(first) <= 5
    rest = list(chunks)
    assert len(loaded) == 3
    # the chunks of the sequence read whole: 5 points each but the last (the scan's outlier sample takes every
    # 16th point of each chunk, so the cut must not move)
    assert [len(c) for c in [first, *rest]][:-1] == [5] * len(rest) and 0 < len(rest[-1]) <= 5
    xyz, origins, _ = expected_world(frames, poses, tr, range(1, 4))
    np.testing.assert_array_equal(np.concatenate([c.xyz for c in [first, *rest]]), xyz)
    np.testing.assert_array_equal(np.concatenate([c.sensor for c in [first, *rest]]), origins)


def test_a_sample_of_a_sequence_reads_its_first_frames_only(tmp_path, monkeypatch):
    """What voxel_size auto and noise_auto measure of a KITTI sequence: its first frames, read frame by frame (a
    long sequence is not read whole for a sample), in the job's frame range."""
    from tiled_gridpull import prepare
    from tiled_gridpull.io import kitti
    from tiled_gridpull.prepare import head_points

    monkeypatch.setattr(prepare, "AUTO_MIN_PER_INPUT", 1)  # these frames are far smaller than a real sample
    frames, poses, tr = make_sequence(tmp_path / "seq")
    seen = []
    load = kitti._load_kitti_scan
    monkeypatch.setattr(kitti, "_load_kitti_scan", lambda p: seen.append(p.stem) or load(p))
    head, n = head_points([str(tmp_path / "seq")], None, budget=len(frames[0]))
    assert n == 1 and len(seen) == 1
    np.testing.assert_array_equal(head, expected_world(frames, poses, tr, [0])[0])
    seen.clear()
    head, _ = head_points([str(tmp_path / "seq")], (1, 3), budget=len(frames[1]) + 1)
    np.testing.assert_array_equal(head, expected_world(frames, poses, tr, [1, 2])[0][:len(frames[1]) + 1])
    assert len(seen) == 2


def test_kitti_missing_frame(tmp_path):
    make_sequence(tmp_path / "seq", n_frames=4, skip=(1,))
    with pytest.raises(InputError, match=r"seq: missing frame 000001\.bin"):
        read_kitti_sequence(tmp_path / "seq")
    with pytest.raises(InputError, match=r"missing frame 000001\.bin"):
        read_kitti_sequence(tmp_path / "seq", frames=(0, 3))
    # frames that avoid the gap are fine
    assert len(read_kitti_sequence(tmp_path / "seq", frames=[2, 3]).xyz) == 12 + 13


def test_kitti_wrong_poses_length(tmp_path):
    frames, poses, _ = make_sequence(tmp_path / "seq", n_frames=5)
    (tmp_path / "seq" / "poses.txt").write_text(
        "\n".join(" ".join(map(str, m.ravel())) for m in poses[:3]) + "\n")
    with pytest.raises(InputError, match="poses.txt has 3 poses but 5 frames"):
        read_kitti_sequence(tmp_path / "seq")
    with pytest.raises(InputError, match="poses.txt has 3 poses but frame 000004 was requested"):
        read_kitti_sequence(tmp_path / "seq", frames=(2, 5))
    assert len(read_kitti_sequence(tmp_path / "seq", frames=(0, 3)).xyz) == 10 + 11 + 12


def test_kitti_sequence_without_calib_is_refused_not_merged_with_identity(tmp_path, capsys):
    """KITTI poses are camera-0 poses: without calib.txt's velodyne-to-camera Tr the scans would be placed
    rotated by 90 degrees about two axes (they were merged with an identity Tr, without a word). Refused in one
    line naming the file and the way on (the calibration, or an identity Tr for poses in the velodyne frame)."""
    from tiled_gridpull.pipeline.cli import main

    make_sequence(tmp_path / "seq", calib=False)
    for read in (read_kitti_sequence, lambda q: next(iter_point_chunks(q))):
        with pytest.raises(InputError, match=r"seq: KITTI sequence has no calib\.txt.*Tr: 1 0 0 0 0 1 0 0 0 0 1 0"):
            read(tmp_path / "seq")
    out = tmp_path / "o.ply"
    code = main(["reconstruct", str(tmp_path / "seq"), "-o", str(out), "-q", "--voxel-size", "1"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert code == 3 and len(lines) == 1 and "calib.txt" in lines[0] and "Traceback" not in err, err
    assert not out.exists()


@pytest.mark.parametrize("how", ["scaled", "rank-deficient", "reflection"])
def test_kitti_calib_whose_tr_is_not_rigid_is_refused(tmp_path, capsys, how):
    """KITTI's Tr is a rigid velodyne-to-camera transform; one with its rotation scaled by 0.001 or with two
    equal rows (rank-deficient) was accepted and shrank or flattened every scan without a word. Refused in one
    line naming calib.txt's Tr, exit 3, when its 3x3 part is not orthonormal within 1e-3 (or mirrors)."""
    from tiled_gridpull.pipeline.cli import main

    make_sequence(tmp_path / "seq")
    tr = np.array([[0, -1, 0, 0.25], [0, 0, -1, -0.5], [1, 0, 0, 1.0]], dtype=np.float64)
    if how == "scaled":
        tr[:, :3] *= 0.001
    elif how == "rank-deficient":
        tr[1] = tr[0]
    else:
        tr[0, :3] *= -1
    (tmp_path / "seq" / "calib.txt").write_text("P0: " + " ".join(["0"] * 12) + "\nTr: "
                                                + " ".join(repr(float(v)) for v in tr.ravel()) + "\n")
    with pytest.raises(InputError, match=r"calib\.txt: line 2: Tr is not a rigid transform"):
        read_kitti_sequence(tmp_path / "seq")
    out = tmp_path / "o.ply"
    code = main(["reconstruct", str(tmp_path / "seq"), "-o", str(out), "-q", "--voxel-size", "1"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert code == 3 and len(lines) == 1 and "calib.txt" in lines[0] and "Tr is not a rigid" in lines[0], err
    assert not out.exists()
    # a real calibration's Tr (sequence 00), given to 1e-12: rigid within its digits
    (tmp_path / "seq" / "calib.txt").write_text(
        "Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 "
        "-7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 "
        "9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01\n")
    read_kitti_sequence(tmp_path / "seq")


def test_kitti_malformed_files(tmp_path):
    make_sequence(tmp_path / "seq")
    poses = tmp_path / "seq" / "poses.txt"
    lines = poses.read_text().splitlines()
    poses.write_text("\n".join([lines[0], lines[1] + " 7", lines[2]]) + "\n")
    with pytest.raises(InputError, match=r"poses\.txt: line 2: expected 12 numbers, found 13"):
        read_kitti_sequence(tmp_path / "seq")
    poses.write_text("\n".join([lines[0], lines[1].replace("0.0", "zero", 1), lines[2]]) + "\n")
    with pytest.raises(InputError, match=r"poses\.txt: line 2: not a number"):
        read_kitti_sequence(tmp_path / "seq")
    poses.write_text("\n".join(lines) + "\n")
    (tmp_path / "seq" / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(InputError, match=r"calib\.txt: no 'Tr:' line"):
        read_kitti_sequence(tmp_path / "seq")
    (tmp_path / "seq" / "calib.txt").unlink()
    (tmp_path / "seq" / "poses.txt").unlink()
    with pytest.raises(InputError, match="no poses.txt"):
        read_kitti_sequence(tmp_path / "seq")


def test_directory_that_is_not_kitti(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match="not a KITTI sequence"):
        read_points(tmp_path)
    with pytest.raises(InputError, match="not a KITTI sequence"):
        point_count(tmp_path)


# --------------------------------------------------------------------------------------------------- cleaning


def test_nan_rows_dropped_with_warning(tmp_path):
    xyz = cloud_xyz(20)
    nrm = unit_normals(20)
    bad = xyz.copy()
    bad[[3, 7], 1] = np.nan
    bad[11, 2] = np.inf
    p = tmp_path / "nan.npy"
    np.save(p, np.column_stack([bad, nrm]))
    with pytest.warns(UserWarning, match=r"nan\.npy: dropped 3 of 20 points with non-finite"):
        cloud = read_points(p)
    keep = np.setdiff1d(np.arange(20), [3, 7, 11])
    np.testing.assert_array_equal(cloud.xyz, xyz[keep])
    np.testing.assert_allclose(cloud.normals, nrm[keep], atol=1e-6)
    assert cloud.report["nonfinite_dropped"] == 3 and cloud.report["points_read"] == 20
    # text "nan" parses too
    q = write_text(tmp_path / "nan.xyz", bad)
    with pytest.warns(UserWarning, match="dropped 3 of 20"):
        assert len(read_points(q).xyz) == 17


def test_all_nan_refused(tmp_path):
    p = tmp_path / "allnan.npy"
    np.save(p, np.full((15, 3), np.nan))
    with pytest.raises(InputError, match=r"allnan\.npy: no finite points"):
        read_points(p)
    assert len(read_points(p, clean=False).xyz) == 15


@pytest.mark.parametrize("suffix", ALL_SUFFIXES)
def test_empty_file(tmp_path, suffix):
    p = tmp_path / f"empty{suffix}"
    p.write_bytes(b"")
    with pytest.raises(InputError, match=rf"empty\{suffix}: "):
        read_points(p)


@pytest.mark.parametrize("suffix", [".ply", ".xyz", ".npy", ".las", ".bin", ".pcd"])
def test_file_with_zero_points(tmp_path, suffix):
    p = tmp_path / f"zero{suffix}"
    if suffix == ".pcd":
        write_cloud(p, np.zeros((0, 3)))
    elif suffix == ".ply":
        write_ply(p, np.zeros((0, 3)))
    elif suffix == ".las":
        write_las(p, np.zeros((0, 3)), offset=[0, 0, 0])
    elif suffix == ".npy":
        np.save(p, np.zeros((0, 3)))
    else:
        p.write_bytes(b"" if suffix == ".bin" else b"# nothing here\n")
    with pytest.raises(InputError, match="contains no points"):
        read_points(p)
    assert point_count(p) == 0
    assert len(read_points(p, clean=False).xyz) == 0
    with pytest.raises(InputError, match="contains no points"):
        list(iter_point_chunks(p))


@pytest.mark.parametrize("suffix", [".xyz", ".npy", ".las", ".ply", ".pcd"])
def test_utm_coordinates_keep_millimetres(tmp_path, suffix):
    xyz = cloud_xyz(30, offset=(512_345.0, 4_123_456.0, 123.0)) + np.array([0.001, 0.002, 0.003])
    p = tmp_path / f"utm{suffix}"
    if suffix == ".las":
        write_las(p, xyz, scale=0.001, offset=[512_000, 4_123_000, 0])
    else:
        write_cloud(p, xyz)
    cloud = read_points(p)
    assert cloud.xyz.dtype == np.float64
    assert np.abs(cloud.xyz - xyz).max() < 1e-6


# ------------------------------------------------------------------------------------------------ path errors


def test_unknown_extension(tmp_path):
    p = tmp_path / "cloud.rcp"
    p.write_bytes(b"x")
    with pytest.raises(InputError,
                       match=r"cloud\.rcp: unknown point cloud format '\.rcp' \(supported: \.ply.*\.e57"):
        read_points(p)
    with pytest.raises(InputError, match="unknown point cloud format"):
        point_count(p)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match=r"nope\.laz: file not found"):
        read_points(tmp_path / "nope.laz")
    with pytest.raises(InputError, match="file not found"):
        point_count(tmp_path / "nope.laz")
    with pytest.raises(InputError, match="file not found"):
        list(iter_point_chunks([tmp_path / "nope.ply"]))


def test_unreadable_file(tmp_path, monkeypatch):
    p = write_cloud(tmp_path / "secret.xyz", cloud_xyz(12))
    monkeypatch.setattr(os, "access", lambda *a, **k: False)
    with pytest.raises(InputError, match=r"secret\.xyz: permission denied"):
        read_points(p)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root can read any file")
def test_unreadable_file_real_permissions(tmp_path):
    p = write_cloud(tmp_path / "secret.xyz", cloud_xyz(12))
    p.chmod(0)
    try:
        with pytest.raises(InputError, match="permission denied"):
            read_points(p)
    finally:
        p.chmod(0o600)


def test_frames_only_for_sequences(tmp_path):
    p = write_cloud(tmp_path / "a.xyz", cloud_xyz(12))
    with pytest.raises(ConfigError, match="frames= applies only"):
        read_points(p, frames=(0, 1))


# ----------------------------------------------------------------------------------------------------- chunks


def test_chunks_over_several_files(tmp_path):
    a = write_cloud(tmp_path / "a.npy", cloud_xyz(25, seed=1))
    b = write_cloud(tmp_path / "b.ply", cloud_xyz(12, seed=2))
    c = write_cloud(tmp_path / "c.xyz", cloud_xyz(9, seed=3))
    chunks = list(iter_point_chunks([a, str(b), c], chunk_size=10))
    assert [len(x) for x in chunks] == [10, 10, 5, 10, 2, 9]
    assert chunks[2].source == f"{a}[20:25]"
    np.testing.assert_array_equal(np.concatenate([x.xyz for x in chunks]),
                                  np.concatenate([cloud_xyz(25, seed=1), cloud_xyz(12, seed=2),
                                                  cloud_xyz(9, seed=3)]))


def test_chunks_drop_nonfinite_rows(tmp_path):
    xyz = cloud_xyz(20)
    xyz[4] = np.nan
    p = tmp_path / "n.npy"
    np.save(p, xyz)
    chunks = list(iter_point_chunks(p, chunk_size=8))
    assert [len(c) for c in chunks] == [7, 8, 4]
    assert chunks[0].report["nonfinite_dropped"] == 1


@pytest.mark.parametrize("bad", [0, -3, 2.5, True])
def test_chunk_size_validated(tmp_path, bad):
    with pytest.raises(ConfigError, match="chunk_size"):
        list(iter_point_chunks(tmp_path / "x.ply", chunk_size=bad))


# ---------------------------------------------------------------------------------------------------- fuzzing

_PREFIXES = {
    ".ply": [b"", b"ply\nformat ascii 1.0\nelement vertex 12\nproperty float x\nproperty float y\n"
                  b"property float z\nend_header\n",
             b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty double x\nproperty double y\n"
             b"property double z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"],
    ".las": [b"", b"LASF"],
    ".xyz": [b"", b"1 2 3\n4 5 6\n"],
    ".npy": [b"", b"\x93NUMPY\x01\x00v\x00{'descr': '<f8', 'fortran_order': False, 'shape': (4, 3), }"],
    ".bin": [b""],
}


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(suffix=st.sampled_from(sorted(_PREFIXES)), choice=st.integers(0, 2), body=st.binary(max_size=600))
def test_random_bytes_read_or_input_error(suffix, choice, body):
    prefixes = _PREFIXES[suffix]
    data = prefixes[choice % len(prefixes)] + body
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"fuzz{suffix}"
        p.write_bytes(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for call in (lambda: read_points(p), lambda: read_points(p, clean=False), lambda: point_count(p),
                         lambda: list(iter_point_chunks(p, chunk_size=4))):
                try:
                    call()
                except InputError as exc:
                    msg = str(exc)
                    assert msg.startswith(str(p)) and "\n" not in msg


def test_las_header_with_absurd_vlr_count(tmp_path):
    # laspy alone would loop over four billion VLRs on an empty stream
    p = write_las(tmp_path / "vlrs.laz", cloud_xyz(20))
    data = bytearray(p.read_bytes())
    data[100:104] = b"\xff\xff\xff\xff"
    p.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"vlrs\.laz: corrupted LAS header \(declares 4294967295 VLRs"):
        read_points(p)
    with pytest.raises(InputError, match="corrupted LAS header"):
        point_count(p)


def test_laz_chunk_table_with_absurd_count(tmp_path):
    # lazrs would reserve tens of GB for the declared chunks and abort the process
    p = write_las(tmp_path / "chunks.laz", cloud_xyz(20))
    data = bytearray(p.read_bytes())
    start = int.from_bytes(data[96:100], "little")
    table = int.from_bytes(data[start:start + 8], "little", signed=True)
    if table <= start:
        table = int.from_bytes(data[-8:], "little", signed=True)
    data[table + 4:table + 8] = b"\xff\xff\xff\xf0"
    p.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"chunks\.laz: corrupted LAZ file \(chunk table declares"):
        read_points(p)
    with pytest.raises(InputError, match="corrupted LAZ file"):
        list(iter_point_chunks(p))


def test_real_laz_1_4_point_format_7():
    p = shared("lidar/autzen_ept_depth0-2.laz")
    assert point_count(p) == 2_264_378
    first = next(iter_point_chunks(p, chunk_size=50_000))
    assert len(first) == 50_000 and first.xyz.dtype == np.float64
    assert "NAD_1983_HARN" in first.crs
    # 406-615 ft elevation (international feet)
    assert 400 < first.xyz[:, 2].min() and first.xyz[:, 2].max() < 620
    assert first.attributes["intensity"].any()


def test_npy_chunks_read_normals_consistently(tmp_path):
    xyz, nrm = cloud_xyz(30), unit_normals(30)
    p = tmp_path / "n.npy"
    np.save(p, np.column_stack([xyz, nrm]))
    chunks = list(iter_point_chunks(p, chunk_size=7))
    assert all(c.normals is not None for c in chunks)
    np.testing.assert_allclose(np.concatenate([c.normals for c in chunks]), nrm, atol=1e-6)


def test_binary_ply_chunks(tmp_path):
    xyz, nrm = cloud_xyz(25), unit_normals(25)
    p = write_ply(tmp_path / "b.ply", xyz, nrm)
    chunks = list(iter_point_chunks(p, chunk_size=10))
    assert [len(c) for c in chunks] == [10, 10, 5]
    np.testing.assert_array_equal(np.concatenate([c.xyz for c in chunks]), xyz)
    np.testing.assert_allclose(np.concatenate([c.normals for c in chunks]), nrm, atol=1e-6)


def test_chunks_of_all_nan_file(tmp_path):
    p = tmp_path / "nan.npy"
    np.save(p, np.full((5, 3), np.nan))
    with pytest.raises(InputError, match=r"nan\.npy: no finite points"):
        list(iter_point_chunks(p))


def test_text_with_cr_line_endings(tmp_path):
    xyz = cloud_xyz(12)
    p = tmp_path / "mac.xyz"
    p.write_bytes("\r".join(" ".join(repr(float(v)) for v in row) for row in xyz).encode())
    np.testing.assert_array_equal(read_points(p).xyz, xyz)
    assert point_count(p) == 12


def test_kitti_stray_huge_frame_number(tmp_path):
    make_sequence(tmp_path / "seq", n_frames=3)
    write_bin(tmp_path / "seq" / "velodyne" / "999999999.bin", cloud_xyz(10))
    with pytest.raises(InputError, match=r"missing frame 000003\.bin and 999999995 more"):
        read_kitti_sequence(tmp_path / "seq")
    assert len(read_kitti_sequence(tmp_path / "seq", frames=(0, 3)).xyz) == 10 + 11 + 12


def test_laz_with_no_compressed_items_is_refused_before_lazrs(tmp_path, capfd):
    """A laszip VLR declaring zero items made lazrs panic (found by the hypothesis header test)."""
    src = shared("lidar/autzen_trim.laz")
    data = bytearray(src.read_bytes())
    record = data.find(b"laszip encoded") - 2 + 54  # VLR header: 2 reserved bytes, then user id; 54 bytes in all
    data[record + 32:record + 34] = (0).to_bytes(2, "little")
    bad = tmp_path / "no_items.laz"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match="laszip VLR declares 0 compressed items") as err:
        read_points(bad)
    assert "\n" not in str(err.value)
    assert "panicked" not in capfd.readouterr().err  # refused before the Rust decoder could panic


def test_rust_panics_become_one_line_input_errors(tmp_path):
    class PanicException(BaseException):  # what pyo3 raises when a Rust extension panics
        pass

    with pytest.raises(InputError, match=r"x\.laz: truncated or corrupted .*PanicException: boom"):
        with input_errors(tmp_path / "x.laz", "LAZ"):
            raise PanicException("boom\nbacktrace")
    with pytest.raises(KeyboardInterrupt):  # other BaseExceptions pass through
        with input_errors(tmp_path / "x.laz", "LAZ"):
            raise KeyboardInterrupt


def test_kitti_frame_range_past_the_end_refused_without_listing_it(tmp_path, capsys):
    from tiled_gridpull.pipeline.cli import main

    make_sequence(tmp_path / "seq", n_frames=3)
    # refused before range() is listed (a billion-entry list takes gigabytes)
    with pytest.raises(InputError, match="frames 0:1000000000 requested but the sequence ends at frame 2"):
        read_kitti_sequence(tmp_path / "seq", frames=(0, 1_000_000_000))
    code = main(["reconstruct", str(tmp_path / "seq"), "-o", str(tmp_path / "m.ply"), "--voxel-size", "0.5",
                 "--overlap", "8",
                 "--frames", "0:99999999999999999999", "-q"])
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1 and "sequence ends at frame 2" in err, err


def _declare(path: Path, old: bytes, new: bytes) -> Path:
    data = path.read_bytes()
    assert data.count(old) >= 1
    path.write_bytes(data.replace(old, new, 1))
    return path


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_ply_declaring_fewer_vertices_warns(tmp_path, fmt):
    xyz = np.random.default_rng(0).normal(size=(100, 3))
    whole = write_ply(tmp_path / "whole.ply", xyz, fmt=fmt)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(read_points(whole, clean=False)) == 100
    short = _declare(write_ply(tmp_path / "short.ply", xyz, fmt=fmt), b"element vertex 100\n",
                     b"element vertex 90\n")
    with pytest.warns(UserWarning, match=r"short\.ply: the file holds 10 more vertex rows than its header "
                                         r"declares \(90\)"):
        cloud = read_points(short, clean=False)
    assert len(cloud) == 90
    np.testing.assert_allclose(cloud.xyz, xyz[:90])


def _las_declaring(tmp_path, name: str, xyz, declared: int) -> Path:
    """A LAS/LAZ of ``xyz`` (read back without a warning) and a copy ``short.<ext>`` whose LAS 1.2 legacy point
    count (uint32 at byte 107) says ``declared``."""
    import struct

    whole = write_las(tmp_path / name, xyz)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(read_points(whole, clean=False)) == len(xyz)
    data = bytearray(whole.read_bytes())
    assert struct.unpack_from("<I", data, 107)[0] == len(xyz)
    struct.pack_into("<I", data, 107, declared)
    short = tmp_path / f"short{whole.suffix}"
    short.write_bytes(bytes(data))
    return short


def test_las_declaring_fewer_points_warns(tmp_path):
    xyz = np.random.default_rng(1).uniform(0, 10, size=(1000, 3))
    short = _las_declaring(tmp_path, "whole.las", xyz, 900)
    with pytest.warns(UserWarning, match=r"short\.las: the file holds 100 more point records than its header "
                                         r"declares \(900\)"):
        cloud = read_points(short, clean=False)
    assert len(cloud) == 900


def test_laz_declaring_fewer_points_warns(tmp_path):
    xyz = np.random.default_rng(2).uniform(0, 100, size=(120_000, 3))
    # lazrs writes chunks of 50,000 points: 3 chunks
    short = _las_declaring(tmp_path, "whole.laz", xyz, 40_000)
    with pytest.warns(UserWarning, match=r"short\.laz: the LAZ chunk table holds 3 chunks of 50000 points but "
                                         r"the header declares 40000 points"):
        cloud = read_points(short, clean=False)
    assert len(cloud) == 40_000


def test_a_registered_format_is_read_and_listed(tmp_path, monkeypatch):
    from tiled_gridpull.io import formats

    monkeypatch.setitem(formats.POINT_FORMATS, ".pnp", formats.POINT_FORMATS[".npy"])
    xyz = np.random.default_rng(3).uniform(0, 1, size=(50, 3))
    with open(tmp_path / "a.pnp", "wb") as fh:
        np.save(fh, xyz)
    assert np.array_equal(read_points(tmp_path / "a.pnp", clean=False).xyz, xyz)
    (tmp_path / "b.zzz").write_text("0 0 0\n")
    with pytest.raises(InputError, match=r"unknown point cloud format '\.zzz' \(supported: .*\.pnp"):
        read_points(tmp_path / "b.zzz")
