"""Synthetic data: analytic shapes, the street mesh, the simulated LiDAR scan and its writers."""

from __future__ import annotations

import numpy as np
import pytest

from tiled_gridpull.metrics import point_to_mesh
from tiled_gridpull.synthetic import (
    FACE_CLASSES,
    SENSOR_HEIGHT_M,
    StreetScene,
    box,
    build_street,
    make_street_sample,
    observed_samples,
    sample_shape,
    scan_street,
    sensor_poses,
    sphere,
    terrain_height,
    torus,
    write_kitti_sequence,
    write_las,
)

UTM = (500000.0, 4000000.0, 100.0)


# ---------------------------------------------------------------------- shapes
@pytest.mark.parametrize("make, volume, euler", [
    (lambda: sphere(0.5, 3), 4 / 3 * np.pi * 0.5 ** 3, 2),
    (lambda: torus(0.35, 0.12, 96, 48), 2 * np.pi ** 2 * 0.35 * 0.12 ** 2, 0),
    (lambda: box((0.8, 0.6, 0.4), 7), 0.8 * 0.6 * 0.4, 2),
    (lambda: box((1.0, 2.0, 3.0), 1), 6.0, 2),
])
def test_shapes_watertight_and_outward(make, volume, euler):
    mesh = make()
    topo = mesh.topology
    assert topo.watertight
    assert topo.components == 1
    assert topo.euler == euler
    vol = mesh.signed_volume()
    assert vol > 0
    assert vol == pytest.approx(volume, rel=0.03)
    assert np.allclose(mesh.vertices.mean(axis=0), 0.0, atol=1e-9)


def test_box_is_exact_with_sharp_edges():
    mesh = box((0.8, 0.6, 0.4), 10)
    assert mesh.n_faces == 12 * 10 * 10
    assert mesh.signed_volume() == pytest.approx(0.192, rel=1e-12)
    assert np.allclose(np.abs(mesh.vertices).max(axis=0), [0.4, 0.3, 0.2])
    normals, _ = mesh.face_normals()
    # every face normal is an axis direction pointing away from the centre
    assert np.allclose(np.abs(normals).max(axis=1), 1.0)
    centres = mesh.triangles().mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normals, centres) > 0)


@pytest.mark.parametrize("mesh", [sphere(0.5, 3), torus(0.35, 0.12, 64, 32), box(divisions=5)])
def test_sample_shape_on_surface(mesh):
    pts, nrm = sample_shape(mesh, 300, seed=3)
    assert pts.shape == (300, 3) and nrm.shape == (300, 3)
    assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0)
    dist, _ = point_to_mesh(pts, mesh)
    assert dist.max() < 1e-9
    again, _ = sample_shape(mesh, 300, seed=3)
    assert np.array_equal(pts, again)
    noisy, nrm2 = sample_shape(mesh, 300, seed=3, noise=0.01)
    assert np.array_equal(nrm, nrm2)
    assert np.std(noisy - pts) == pytest.approx(0.01, rel=0.2)


# ---------------------------------------------------------------------- street
@pytest.fixture(scope="module")
def street():
    scene = StreetScene(seed=7, length_m=50.0, width_m=36.0, origin=UTM)
    mesh = build_street(scene)
    scan = scan_street(scene, mesh, 3, frame_spacing_m=2.0, azimuth_steps=180, max_range=60.0)
    return scene, mesh, scan


def test_street_mesh(street):
    scene, mesh, _ = street
    assert 5_000 < mesh.n_faces < 300_000
    ranges = mesh.metadata["face_classes"]
    assert list(ranges) == list(FACE_CLASSES)
    assert ranges["car"][1] == mesh.n_faces
    for cls in ("terrain", "building"):
        assert ranges[cls][1] > ranges[cls][0]
    local = mesh.vertices - scene.origin
    assert local[:, 0].min() >= -1e-9 and local[:, 0].max() <= scene.length_m + 1e-9
    assert np.abs(local[:, 1]).max() <= 0.5 * scene.width_m + 1e-9
    # every object is a closed, outward piece; the terrain is an open sheet facing up
    objects = mesh.submesh(np.arange(mesh.n_faces) >= ranges["building"][0])
    assert objects.topology.watertight
    assert objects.signed_volume() > 0
    terrain = mesh.submesh(np.arange(mesh.n_faces) < ranges["terrain"][1])
    normals, _ = terrain.face_normals()
    assert normals[:, 2].min() > 0.9


def test_scan_points_on_mesh(street):
    scene, mesh, scan = street
    n = scan.n_points
    per_frame = 64 * 180
    assert 0.6 * 3 * per_frame < n <= 3 * per_frame
    assert scan.xyz.shape == (n, 3) and scan.xyz.dtype == np.float64
    assert scan.sensor.shape == (n, 3) and scan.frame.dtype == np.int32 and scan.face.shape == (n,)
    rng = np.random.default_rng(0)
    pick = rng.choice(n, 1500, replace=False)
    local_mesh = type(mesh)(mesh.vertices - scene.origin, mesh.faces)
    dist, _ = point_to_mesh(scan.xyz[pick] - scene.origin, local_mesh)
    assert dist.max() < 1e-6
    # the recorded face is the one hit: the point lies in its plane
    n_face, _ = mesh.face_normals()
    v0 = mesh.vertices[mesh.faces[scan.face[pick], 0]]
    assert np.abs(np.einsum("ij,ij->i", scan.xyz[pick] - v0, n_face[scan.face[pick]])).max() < 1e-6
    rng_m = np.linalg.norm(scan.xyz - scan.sensor, axis=1)
    assert rng_m.min() >= 0.5 and rng_m.max() <= 60.0
    assert np.all((scan.reflectance >= 0.1) & (scan.reflectance <= 0.9))
    normals = scan.normals(mesh)
    assert np.all(np.einsum("ij,ij->i", normals, scan.sensor - scan.xyz) > 0)


def test_scan_poses_and_frames(street):
    scene, mesh, scan = street
    assert scan.poses.shape == (3, 4, 4)
    assert np.all(np.diff(scan.frame) >= 0)
    counts = np.bincount(scan.frame, minlength=3)
    assert counts.sum() == scan.n_points and np.all(counts > 0)
    assert np.array_equal(scan.sensor, scan.poses[scan.frame, :3, 3])
    pos = scan.poses[:, :3, 3] - scene.origin
    assert np.allclose(np.diff(pos[:, 0]), 2.0)
    # 1.73 m above the terrain mesh, exactly
    assert np.allclose(pos[:, 2] - terrain_height(scene, pos[:, 0], pos[:, 1]), SENSOR_HEIGHT_M, atol=1e-9)
    local_mesh = type(mesh)(mesh.vertices - scene.origin, mesh.faces)
    below, _ = point_to_mesh(pos - [0.0, 0.0, SENSOR_HEIGHT_M], local_mesh)
    assert below.max() < 1e-9
    # poses are rigid, z stays vertical, heading wobbles
    R = scan.poses[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    assert np.allclose(R[:, 2, 2], 1.0)
    assert np.ptp(np.arctan2(R[:, 1, 0], R[:, 0, 0])) > 1e-4
    for i in range(3):
        p = scan.frame_points(i)
        assert p.dtype == np.float32 and len(p) == counts[i]
        world = p.astype(np.float64) @ scan.poses[i, :3, :3].T + scan.poses[i, :3, 3]
        assert np.abs(world - scan.xyz[scan.frame == i]).max() < 1e-4
    assert np.array_equal(scan.poses, sensor_poses(scene, 3, 2.0))


def test_scan_deterministic_and_noise(street):
    scene, mesh, scan = street
    again = scan_street(scene, build_street(scene), 3, frame_spacing_m=2.0, azimuth_steps=180, max_range=60.0)
    for name in ("xyz", "sensor", "frame", "poses", "face", "reflectance"):
        assert np.array_equal(getattr(scan, name), getattr(again, name)), name
    other = build_street(StreetScene(seed=8, length_m=50.0, width_m=36.0, origin=UTM))
    assert other.n_faces != mesh.n_faces or not np.array_equal(other.vertices, mesh.vertices)
    noisy = scan_street(scene, mesh, 3, frame_spacing_m=2.0, azimuth_steps=180, max_range=60.0,
                        range_noise=0.02, seed=1)
    assert noisy.n_points == scan.n_points
    d = np.linalg.norm(noisy.xyz - noisy.sensor, axis=1) - np.linalg.norm(scan.xyz - scan.sensor, axis=1)
    assert np.std(d) == pytest.approx(0.02, rel=0.1)
    # along the ray: the direction from the sensor is unchanged
    u0 = (scan.xyz - scan.sensor) / np.linalg.norm(scan.xyz - scan.sensor, axis=1)[:, None]
    u1 = (noisy.xyz - noisy.sensor) / np.linalg.norm(noisy.xyz - noisy.sensor, axis=1)[:, None]
    assert np.abs(u0 - u1).max() < 1e-9


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_round_trip(tmp_path, street, suffix):
    laspy = pytest.importorskip("laspy")
    _, _, scan = street
    intensity = np.round(scan.reflectance * 65535)
    path = write_las(tmp_path / f"street{suffix}", scan.xyz, intensity=intensity, crs_wkt='LOCAL_CS["test"]')
    assert path.is_file() and not list(tmp_path.glob(".*tmp*"))
    las = laspy.read(path)
    assert las.header.version.minor == 4
    assert len(las.points) == scan.n_points
    assert np.allclose(las.header.scales, 0.001)
    assert np.array_equal(las.header.offsets, np.floor(scan.xyz.min(axis=0)))
    got = np.column_stack([las.x, las.y, las.z])
    assert np.abs(got - scan.xyz).max() <= 0.0005 + 1e-9
    assert np.array_equal(np.asarray(las.intensity), intensity.astype(np.uint16))
    assert np.allclose(las.header.mins, scan.xyz.min(axis=0), atol=1e-3)
    assert any("LOCAL_CS" in str(getattr(v, "string", "")) for v in las.header.vlrs)


def _read_kitti(root):
    """Reference reader: KITTI's convention, world = pose_i @ Tr @ [p; 1]."""
    tr = None
    for line in (root / "calib.txt").read_text().splitlines():
        if line.startswith("Tr:"):
            tr = np.vstack([np.array(line.split()[1:], float).reshape(3, 4), [0, 0, 0, 1]])
    poses = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)
    out = []
    for i, pose in enumerate(poses):
        p = np.fromfile(root / "velodyne" / f"{i:06d}.bin", dtype=np.float32).reshape(-1, 4)
        hom = np.column_stack([p[:, :3].astype(np.float64), np.ones(len(p))])
        P = np.vstack([pose, [0, 0, 0, 1]])
        out.append((hom @ (P @ tr).T)[:, :3])
    return np.vstack(out), poses, tr


def test_kitti_round_trip(tmp_path, street):
    scene, _, scan = street
    root = write_kitti_sequence(tmp_path / "seq", scan)
    world, poses, tr = _read_kitti(root)
    assert len(poses) == scan.n_frames
    assert len(world) == scan.n_points
    # KITTI poses are local: no origin in the files
    assert np.abs(world - (scan.xyz - scene.origin)).max() < 1e-4
    # the calibration really swaps axes: velodyne x (forward) is camera z, velodyne z (up) is camera -y
    assert tr[2, 0] > 0.99 and tr[1, 2] < -0.99 and tr[0, 1] < -0.99
    refl = np.fromfile(root / "velodyne" / "000000.bin", dtype=np.float32).reshape(-1, 4)[:, 3]
    assert np.array_equal(refl, scan.reflectance[scan.frame == 0])
    assert len((root / "times.txt").read_text().split()) == scan.n_frames


def test_observed_samples(street):
    _, mesh, scan = street
    samples, normals = observed_samples(mesh, scan.xyz, 20_000, radius=0.5, seed=2)
    assert 0 < len(samples) < 20_000
    assert normals.shape == samples.shape
    from pykdtree.kdtree import KDTree

    c = scan.xyz.min(axis=0)
    d, _ = KDTree(scan.xyz - c).query(samples - c, k=1)
    assert d.max() <= 0.5


def test_make_street_sample(tmp_path):
    laspy = pytest.importorskip("laspy")
    out = make_street_sample(tmp_path, n_points=30_000, seed=3, origin=UTM, formats=("laz", "kitti"))
    assert out["points"] == out["laz"] and out["laz"].is_file()
    assert out["gt_mesh"].is_file() and out["meta"].is_file()
    assert (out["kitti"] / "velodyne" / f"{out['n_frames'] - 1:06d}.bin").is_file()
    assert 0.85 * 30_000 < out["n_points"] < 1.15 * 30_000
    las = laspy.read(out["laz"])
    assert len(las.points) == out["n_points"]
    assert abs(float(las.x.min()) - UTM[0]) < 1_000
    from tiled_gridpull.io import read_mesh

    gt = read_mesh(out["gt_mesh"])
    assert gt.n_faces == out["n_faces"]
    pts = np.column_stack([las.x, las.y, las.z])[:300]
    dist, _ = point_to_mesh(pts, gt)
    assert dist.max() < 1e-3  # millimetre quantisation of LAS


def _brute_force_hits(tri, origin, dirs, t_min, t_max):
    """Nearest hit of every ray against every triangle (numpy Moller-Trumbore), inf where none."""
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    best = np.full(len(dirs), np.inf)
    for s in range(0, len(dirs), 32):
        d = dirs[s:s + 32, None, :]
        p = np.cross(d, e2[None])
        det = np.einsum("fk,rfk->rf", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            tv = origin - v0
            u = np.einsum("fk,rfk->rf", tv, p) * inv
            q = np.cross(tv, e1)
            v = np.einsum("rk,fk->rf", d[:, 0], q) * inv
            t = np.einsum("fk,fk->f", e2, q)[None] * inv
        ok = (np.abs(det) > 1e-14) & (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1)
        ok &= (t >= t_min) & (t <= t_max)
        best[s:s + 32] = np.where(ok, t, np.inf).min(axis=1)
    return best


def test_grid_traversal_matches_brute_force():
    from tiled_gridpull.synthetic import hdl64_directions

    scene = StreetScene(seed=11, length_m=30.0, width_m=30.0)
    mesh = build_street(scene)
    scan = scan_street(scene, mesh, 1, azimuth_steps=24, max_range=40.0)
    pose = scan.poses[0]
    dirs = hdl64_directions(64, 24) @ pose[:3, :3].T
    t = _brute_force_hits(mesh.triangles(), pose[:3, 3], dirs, 0.5, 40.0)
    hit = np.isfinite(t)
    assert hit.sum() == scan.n_points
    expect = pose[:3, 3] + t[hit, None] * dirs[hit]
    assert np.abs(expect - scan.xyz).max() < 1e-6
