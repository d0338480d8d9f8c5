"""PCD input (issue 20): ascii, binary and binary_compressed; NaN rows of organised clouds dropped; the viewpoint
as sensor origin; damaged files in one line."""

from pathlib import Path

import numpy as np
import pytest
from pypcd4 import Encoding
from pypcd4 import PointCloud as PcdCloud

from tiled_gridpull.errors import InputError
from tiled_gridpull.io import iter_point_chunks, point_count, read_points
from tiled_gridpull.pipeline.cli import main

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "indoor" / "office1.pcd"


def cloud(n=500, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def with_nan_rows(xyz, every=7):
    out = xyz.copy()
    out[::every] = np.nan
    return out


@pytest.mark.parametrize("encoding", [Encoding.ASCII, Encoding.BINARY, Encoding.BINARY_COMPRESSED])
def test_every_encoding_reads_the_same_points_without_nan_rows(tmp_path, encoding):
    xyz = with_nan_rows(cloud())
    intensity = np.arange(len(xyz), dtype=np.float32)
    p = tmp_path / "c.pcd"
    PcdCloud.from_points([xyz[:, 0], xyz[:, 1], xyz[:, 2], intensity], ("x", "y", "z", "intensity"),
                         (np.float32,) * 4).save(p, encoding=encoding)
    assert point_count(p) == len(xyz)  # the header's count, NaN rows included
    with pytest.warns(UserWarning, match="non-finite"):
        c = read_points(p)
    finite = np.all(np.isfinite(xyz), axis=1)
    assert len(c) == finite.sum() == len(xyz) - len(xyz[::7])
    np.testing.assert_array_equal(np.sort(c.xyz, axis=0), np.sort(xyz[finite].astype(np.float64), axis=0))
    assert set(c.attributes["intensity"]) == set(intensity[finite])
    assert c.report["nonfinite_dropped"] == len(xyz[::7])
    # streamed in chunks, as tiled mode reads it: the same points
    chunks = list(iter_point_chunks([p], chunk_size=100))
    assert sum(len(ch) for ch in chunks) == finite.sum()


def test_organised_ascii_cloud_with_normals_and_viewpoint(tmp_path):
    """An organised 4 x 2 depth image written by hand: NaN pixels dropped, normals kept, the viewpoint becomes
    every point's sensor origin."""
    rows = ["0 0 1 0 0 -1", "nan nan nan nan nan nan", "1 0 1 0 0 -2", "0 1 1 0 0 -1",
            "nan nan nan nan nan nan", "1 1 1 0 0 -1", "2 1 1 0 0 -1", "2 0 1 0 0 -1"]
    header = ["# .PCD v0.7", "VERSION 0.7", "FIELDS x y z normal_x normal_y normal_z", "SIZE 4 4 4 4 4 4",
              "TYPE F F F F F F", "COUNT 1 1 1 1 1 1", "WIDTH 4", "HEIGHT 2", "VIEWPOINT 0.5 0.5 -3 1 0 0 0",
              "POINTS 8", "DATA ascii"]
    p = tmp_path / "depth.pcd"
    p.write_text("\n".join(header + rows) + "\n")
    raw = read_points(p, clean=False)
    assert len(raw) == 8 and np.isnan(raw.xyz[[1, 4]]).all()
    (c,) = list(iter_point_chunks([p]))  # how tiled mode reads it: NaN pixels dropped and counted
    assert len(c) == 6 and c.report["nonfinite_dropped"] == 2
    np.testing.assert_allclose(c.normals, np.tile([0, 0, -1], (6, 1)), atol=1e-7)  # unit length
    np.testing.assert_array_equal(c.sensor, np.tile([0.5, 0.5, -3.0], (6, 1)))



@pytest.mark.parametrize("height,viewpoint,sensor", [
    (1, "0 0 0 1 0 0 0", None),          # the writer's default on a map: the map origin is no sensor
    (2, "0 0 0 1 0 0 0", [0, 0, 0]),     # an organised image is in its sensor's frame
    (1, "5 6 7 1 0 0 0", [5, 6, 7]),     # a viewpoint someone set
])
def test_the_default_viewpoint_is_a_sensor_only_for_organised_clouds(tmp_path, height, viewpoint, sensor):
    header = ["VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1", f"WIDTH {4 // height}",
              f"HEIGHT {height}", f"VIEWPOINT {viewpoint}", "POINTS 4", "DATA ascii"]
    p = tmp_path / "c.pcd"
    p.write_text("\n".join(header + ["0 0 1", "1 0 1", "0 1 1", "1 1 1"]) + "\n")
    c = read_points(p, clean=False)
    if sensor is None:
        assert c.sensor is None
    else:
        np.testing.assert_array_equal(c.sensor, np.tile(sensor, (4, 1)))


@pytest.mark.parametrize("viewpoint", ["nan 0 0 1 0 0 0", "0 inf 0 1 0 0 0", "0 0 -inf 1 0 0 0", "0 0 0 nan 0 0 0",
                                       "0 0 0 1 0 0", "0 0 0 1 0 0 0 0", "0 0 x 1 0 0 0"])
def test_viewpoint_that_is_not_7_finite_numbers_is_refused_naming_it(tmp_path, capsys, viewpoint):
    """A NaN or infinite VIEWPOINT gave every point a NaN sensor origin without a word; a header's VIEWPOINT
    is 7 numbers (translation, quaternion)."""
    header = ["VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1", "WIDTH 500", "HEIGHT 1",
              f"VIEWPOINT {viewpoint}", "POINTS 500", "DATA ascii"]
    p = tmp_path / "c.pcd"
    p.write_text("\n".join(header + [" ".join(map(repr, row)) for row in cloud().tolist()]) + "\n")
    for read in (read_points, lambda q: next(iter_point_chunks([q]))):
        with pytest.raises(InputError, match=f"c.pcd: PCD header's VIEWPOINT '{viewpoint}' is not 7 finite"):
            read(p)
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "-q"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert code == 3 and len(lines) == 1 and "VIEWPOINT" in lines[0] and "Traceback" not in err, err
    assert not (tmp_path / "o.ply").exists()


@pytest.mark.parametrize("viewpoint", ["1e39 0 0 1 0 0 0", "0 1e300 0 1 0 0 0", "1e149 1e149 1e149 1 0 0 0",
                                       "0 0 -2e37 1 0 0 0"])
def test_a_viewpoint_too_far_for_the_sensor_storage_is_refused_naming_it(tmp_path, capsys, viewpoint):
    """A finite but huge VIEWPOINT (1e39, even 1e149 below the coordinate limit of 1e150) was accepted: a tiled
    job stores sensor origins as float32 offsets from a tile's corner, where it became infinite (overflow
    warnings, a degraded mesh). Refused beyond SENSOR_LIMIT (1e37) in one line naming VIEWPOINT, exit 3; a
    viewpoint at the limit still makes finite float32 offsets."""
    header = ["VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1", "WIDTH 500", "HEIGHT 1",
              f"VIEWPOINT {viewpoint}", "POINTS 500", "DATA ascii"]
    p = tmp_path / "c.pcd"
    rows = [" ".join(map(repr, row)) for row in cloud().tolist()]
    p.write_text("\n".join(header + rows) + "\n")
    for read in (read_points, lambda q: next(iter_point_chunks([q]))):
        with pytest.raises(InputError, match=f"c.pcd: PCD header's VIEWPOINT '{viewpoint}' places the sensor"):
            read(p)
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "-q", "--voxel-size", "0.2", "--dry-run"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert code == 3 and len(lines) == 1 and "VIEWPOINT" in lines[0] and "Traceback" not in err, err
    from tiled_gridpull.io.pcd import SENSOR_LIMIT

    header[7] = f"VIEWPOINT {-SENSOR_LIMIT!r} {SENSOR_LIMIT!r} 0 1 0 0 0"
    p.write_text("\n".join(header + rows) + "\n")
    c = read_points(p)
    with np.errstate(over="raise"):
        offsets = (c.sensor - c.xyz.min(axis=0)).astype(np.float32)
    assert np.all(np.isfinite(offsets))


@pytest.mark.parametrize("damage,needle", [
    (lambda b: b[: len(b) // 2], "truncated or corrupted PCD"),
    (lambda b: b.replace(b"FIELDS x y z", b"FIELDS a b c"), "without x y z fields"),
    (lambda b: b.replace(b"POINTS 500", b"POINTS many"), "POINTS is not a number"),
    (lambda b: b"hello\nworld\n", "not a PCD file"),
    (lambda b: b"", "not a PCD file"),
])
def test_damaged_pcd_is_one_line(tmp_path, capsys, damage, needle):
    p = tmp_path / "c.pcd"
    PcdCloud.from_xyz_points(cloud()).save(p, encoding=Encoding.BINARY_COMPRESSED)
    p.write_bytes(damage(p.read_bytes()))
    with pytest.raises(InputError, match=needle):
        read_points(p)
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "-q"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert code == 3 and len(lines) == 1 and str(p) in lines[0] and "Traceback" not in err, err
    assert not (tmp_path / "o.ply").exists()


def test_more_rows_declared_than_stored_is_truncation(tmp_path):
    p = tmp_path / "c.pcd"
    PcdCloud.from_xyz_points(cloud()).save(p, encoding=Encoding.ASCII)
    text = p.read_text().splitlines()
    p.write_text("\n".join(text[:-50]) + "\n")
    with pytest.raises(InputError, match="c.pcd: truncated"):
        read_points(p)


@pytest.mark.skipif(not SHARED.exists(), reason="../shared/data/indoor/office1.pcd is not present")
def test_shared_kinect_office_scan():
    """PCL's office1.pcd: 640 x 480 organised, binary_compressed; the shared MANIFEST counts 254,456 finite."""
    assert point_count(SHARED) == 307_200
    with pytest.warns(UserWarning, match="dropped 52744 of 307200"):
        c = read_points(SHARED)
    assert len(c) == 254_456 and np.all(np.isfinite(c.xyz))
    np.testing.assert_array_equal(c.sensor[0], [0.0, 0.0, 0.0])
