"""E57 input (issue 20): several scans with their poses, each point's scan position as its sensor origin."""

import numpy as np
import pytest

from tiled_gridpull.errors import InputError
from tiled_gridpull.io import iter_point_chunks, point_count, read_points
from tiled_gridpull.pipeline.cli import main

pye57 = pytest.importorskip("pye57", reason="E57 input needs pye57 (the e57 extra)")

POSES = [((0.0, 0.0, 0.0), 0.0), ((10.0, 5.0, 1.5), 90.0)]  # translation, yaw in degrees


def quaternion_z(degrees):
    h = np.radians(degrees) / 2
    return np.array([np.cos(h), 0.0, 0.0, np.sin(h)])  # w x y z, E57's order


def write_scans(path, n=1000, invalid_every=10):
    """Two scans of a sphere of radius 5 around their scanners, in each scanner's own frame, with poses; every
    ``invalid_every``-th point flagged invalid. Returns the expected global points and sensors of valid points."""
    rng = np.random.default_rng(0)
    e57 = pye57.E57(str(path), mode="w")
    world, sensors = [], []
    for t, yaw in POSES:
        p = rng.normal(size=(n, 3))
        p = 5.0 * p / np.linalg.norm(p, axis=1, keepdims=True)
        invalid = (np.arange(n) % invalid_every == 0).astype(np.int8)
        e57.write_scan_raw({"cartesianX": p[:, 0], "cartesianY": p[:, 1], "cartesianZ": p[:, 2],
                            "intensity": np.linspace(0, 1, n), "cartesianInvalidState": invalid},
                           rotation=quaternion_z(yaw), translation=np.array(t))
        c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        keep = invalid == 0
        world.append(p[keep] @ rot.T + t)
        sensors.append(np.tile(t, (keep.sum(), 1)))
    e57.close()
    return np.concatenate(world), np.concatenate(sensors)


def test_scans_come_in_the_common_frame_with_their_scanner_positions(tmp_path):
    p = tmp_path / "two.e57"
    world, sensors = write_scans(p)
    assert point_count(p) == 2000  # what the headers declare, invalid points included
    c = read_points(p)
    assert len(c) == len(world) == 1800 and c.report["points_read"] == 1800
    np.testing.assert_allclose(c.xyz, world, atol=1e-6)  # pye57 applies the quaternion: micrometre rounding
    np.testing.assert_array_equal(c.sensor, sensors)
    assert set(np.unique(c.attributes["scan"])) == {0, 1} and "intensity" in c.attributes
    # every point is 5 m from its own scanner: the pose is applied to the points, and gives the origin
    np.testing.assert_allclose(np.linalg.norm(c.xyz - c.sensor, axis=1), 5.0, atol=1e-6)
    # streamed as tiled mode reads it: the same points, in pieces no larger than asked
    parts = list(iter_point_chunks([p], chunk_size=300))
    assert max(len(q) for q in parts) <= 300
    np.testing.assert_allclose(np.concatenate([q.xyz for q in parts]), world, atol=1e-6)
    np.testing.assert_array_equal(np.concatenate([q.sensor for q in parts]), sensors)


def test_tiled_dry_run_sees_the_sensor_origins(tmp_path, capsys):
    p = tmp_path / "two.e57"
    write_scans(p)
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "--voxel-size", "0.2", "--dry-run"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "1,800 points with sensor origins in 1 file(s)" in out


@pytest.mark.parametrize("damage", [lambda b: b[: len(b) // 2], lambda b: b"E57 " + b"\0" * 2000,
                                    lambda b: b""])
def test_damaged_e57_is_one_line(tmp_path, capsys, damage):
    p = tmp_path / "two.e57"
    write_scans(p)
    p.write_bytes(damage(p.read_bytes()))
    with pytest.raises(InputError, match=r"two\.e57: "):
        read_points(p)
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "-q"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert code == 3 and len(lines) == 1 and "two.e57" in lines[0] and "Traceback" not in err, err
    assert not (tmp_path / "o.ply").exists()


@pytest.mark.parametrize("translation,rotation,needle", [
    ((1e308, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), "scan 0's pose translation '1e+308 0 0'"),
    ((0.0, -1e200, 0.0), (1.0, 0.0, 0.0, 0.0), "scan 0's pose translation '0 -1e+200 0'"),
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), "scan 0's pose rotation '0 0 0 0' is not a quaternion"),
])
def test_absurd_scan_pose_is_refused_naming_it(tmp_path, capsys, translation, rotation, needle):
    """pye57 applies every scan's pose to its points: a translation of 1e308 made the one-shape solve fail with
    LinAlgError, a zero quaternion put every point on the scanner ("all points are identical")."""
    p = tmp_path / "pose.e57"
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(500, 3))
    e57 = pye57.E57(str(p), mode="w")
    e57.write_scan_raw({"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]},
                       rotation=np.array(rotation), translation=np.array(translation))
    e57.close()
    for read in (read_points, lambda q: next(iter_point_chunks([q]))):
        with pytest.raises(InputError, match=needle.replace("+", r"\+")):
            read(p)
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "-q"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert code == 3 and len(lines) == 1 and "pose" in lines[0] and "Traceback" not in err, err
    assert not (tmp_path / "o.ply").exists()
