"""Tests for tiled_gridpull.cloud: the point-cloud type, its cleaning, the one duplicate test, and point clouds
of pyvista, Open3D and trimesh as input."""

from __future__ import annotations

import numpy as np
import pytest

import tiled_gridpull.cloud as cloud_mod
from tiled_gridpull.cloud import PointCloud, as_points, clean_points, duplicate_mask
from tiled_gridpull.errors import InputError
from test_io_formats import cloud_xyz, unit_normals


def test_duplicates_dropped_keep_first_and_order():
    xyz = cloud_xyz(20)
    nrm = unit_normals(20)
    rows = [0, 1, 2, 1, 3, 0, 4, 5, 6, 7, 8, 9, 10, 2, 11]
    cloud = PointCloud(xyz[rows], normals=nrm[rows], attributes={"id": np.arange(len(rows))}, source="dups")
    out = clean_points(cloud)
    np.testing.assert_array_equal(out.xyz, xyz[[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11]])
    np.testing.assert_array_equal(out.attributes["id"], [0, 1, 2, 4, 6, 7, 8, 9, 10, 11, 12, 14])
    assert out.report["duplicates_dropped"] == 3
    assert len(cloud.xyz) == len(rows)  # input untouched
    # -0.0 and 0.0 are the same coordinate
    z = np.vstack([cloud_xyz(12), [[0.0, -0.0, 1.0], [-0.0, 0.0, 1.0]]])
    assert clean_points(PointCloud(z)).report["duplicates_dropped"] == 1


def test_duplicate_mask_matches_exact_and_survives_collisions(monkeypatch):
    rng = np.random.default_rng(3)
    base = rng.normal(size=(2000, 3)) * 1e6
    xyz = base[rng.integers(0, 2000, 20_000)]
    fast = duplicate_mask(xyz)
    words = np.ascontiguousarray(xyz + 0.0).view(np.uint64).reshape(-1, 3)
    np.testing.assert_array_equal(fast, cloud_mod._duplicate_mask_exact(words))
    # every row colliding: the exact fallback must give the same answer
    monkeypatch.setattr(cloud_mod, "_row_hash", lambda w: np.zeros(len(w), dtype=np.uint64))
    np.testing.assert_array_equal(duplicate_mask(xyz), fast)


def test_identical_collinear_coplanar_refused():
    with pytest.raises(InputError, match="all 50 points are identical"):
        clean_points(PointCloud(np.tile([4e6, 5e5, 12.0], (50, 1)), source="same"))
    t = np.linspace(0, 100, 40)[:, None]
    line = np.array([4e6, 5e5, 10.0]) + t * np.array([1.0, 2.0, 0.5])
    with pytest.raises(InputError, match=r"line: all 40 points are collinear"):
        clean_points(PointCloud(line, source="line"))
    rng = np.random.default_rng(5)
    uv = rng.uniform(0, 100, size=(200, 2))
    plane = np.array([4e6, 5e5, 10.0]) + uv[:, :1] * [1.0, 0.0, 0.3] + uv[:, 1:] * [0.0, 1.0, -0.2]
    with pytest.raises(InputError, match=r"plane: all 200 points are coplanar"):
        clean_points(PointCloud(plane, source="plane"))
    assert len(clean_points(PointCloud(plane), reject_planar=False).xyz) == 200
    # 1 mm of relief over 100 m at UTM magnitude is not coplanar
    bumpy = plane.copy()
    bumpy[::7, 2] += 0.001
    assert len(clean_points(PointCloud(bumpy)).xyz) == 200


def test_degeneracy_on_large_cloud_uses_full_check():
    # 300k coplanar points except one: the subsample may look planar, the full check must not
    rng = np.random.default_rng(6)
    pts = np.column_stack([rng.uniform(0, 10, 300_000), rng.uniform(0, 10, 300_000), np.zeros(300_000)])
    pts[123_457, 2] = 0.5
    assert len(clean_points(PointCloud(pts)).xyz) == 300_000
    pts[123_457, 2] = 0.0
    with pytest.raises(InputError, match="coplanar"):
        clean_points(PointCloud(pts))


def test_empty_and_too_few():
    with pytest.raises(InputError, match="empty: contains no points"):
        clean_points(PointCloud(np.zeros((0, 3)), source="empty"))
    with pytest.raises(InputError, match=r"few: only 5 points \(at least 10 needed\)"):
        clean_points(PointCloud(cloud_xyz(5), source="few"))
    assert len(clean_points(PointCloud(cloud_xyz(5)), min_points=4).xyz) == 5


def test_pointcloud_never_narrows():
    c = PointCloud(np.array([[4e6, 1.0, 2.0]], dtype=np.float32))
    assert c.xyz.dtype == np.float64 and len(c) == 1
    with pytest.raises(InputError, match="shape"):
        PointCloud(np.zeros((4, 2)))


def test_clean_twice_accumulates_report():
    xyz = np.vstack([cloud_xyz(12), cloud_xyz(12)[:2], [[np.nan, 0, 0]]])
    with pytest.warns(UserWarning):
        once = clean_points(PointCloud(xyz, source="twice"))
    again = clean_points(once)
    assert again.report == once.report == {"points_read": 15, "nonfinite_dropped": 1, "duplicates_dropped": 2,
                                           "points_kept": 12}


def test_identical_follows_the_extent_not_the_coordinates_size():
    from tiled_gridpull.synthetic import sample_shape, sphere

    pts, _ = sample_shape(sphere(), 2000, seed=0)
    far = pts * 0.5 + 1e12  # a 1 m sphere at 1e12: 4,500 float64 steps across, plenty to mesh
    assert len(clean_points(PointCloud(far))) == 2000
    # rounding noise of a few units in the last place around one point is still one point
    jitter = 1e12 + np.random.default_rng(0).integers(-2, 3, size=(500, 3)) * np.spacing(1e12)
    with pytest.raises(InputError, match="identical"):
        clean_points(PointCloud(jitter))


@pytest.mark.parametrize("scale", [1e-300, 1e200])
def test_extent_float64_cannot_resolve_is_refused(scale):
    from tiled_gridpull.synthetic import sample_shape, sphere

    pts, _ = sample_shape(sphere(), 500, seed=0)
    with pytest.raises(InputError, match="outside what float64 arithmetic resolves"):
        clean_points(PointCloud(pts * scale))


# -- headers that declare fewer points than the file holds: the rest is not read, and the user is told ---------


def test_duplicate_mask_with_signed_zeros_is_the_tile_solves_byte_test():
    # solve_tile used np.unique on the bytes of its float32 rows (first occurrences, put back in order): the
    # shared mask must keep exactly those rows, -0.0 and 0.0 apart
    rng = np.random.default_rng(11)
    for _ in range(20):
        base = (rng.integers(-3, 4, size=(300, 3)) * 0.5).astype(np.float32)
        xyz32 = np.ascontiguousarray(base[rng.integers(0, len(base), 1000)])
        zeros = (xyz32 == 0) & (rng.random(xyz32.shape) < 0.5)
        xyz32[zeros] = np.float32(-0.0)
        by_bytes = np.sort(np.unique(xyz32.view(np.dtype((np.void, 12))).ravel(), return_index=True)[1])
        kept = np.flatnonzero(~duplicate_mask(xyz32.astype(np.float64), signed_zeros=True))
        np.testing.assert_array_equal(kept, by_bytes)
    z = np.array([[0.0, 1.0, 2.0], [-0.0, 1.0, 2.0], [0.0, 1.0, 2.0]])
    assert duplicate_mask(z, signed_zeros=True).tolist() == [False, False, True]
    assert duplicate_mask(z).tolist() == [False, True, True]


# ------------------------------------------------------------------------------------- other libraries' clouds


class FakeOpen3dCloud:
    """The attributes of open3d.geometry.PointCloud that as_points uses (points, normals, has_normals)."""

    def __init__(self, points, normals=None):
        self.points = points
        self.normals = normals if normals is not None else np.zeros((0, 3))

    def has_normals(self):
        return len(self.normals) > 0


def test_as_points_passes_arrays_and_pointclouds_through():
    xyz = cloud_xyz(20)
    assert as_points(xyz)[0] is xyz and as_points(xyz)[1] is None
    cloud = PointCloud(xyz)
    assert as_points(cloud) == (cloud, None)
    listed = xyz.tolist()
    assert as_points(listed) == (listed, None)


def test_as_points_open3d_like():
    xyz, nrm = cloud_xyz(20), unit_normals(20)
    got, normals = as_points(FakeOpen3dCloud(xyz, nrm))
    np.testing.assert_array_equal(got, xyz)
    np.testing.assert_array_equal(normals, nrm)
    got, normals = as_points(FakeOpen3dCloud(xyz))
    np.testing.assert_array_equal(got, xyz)
    assert normals is None


def test_as_points_pyvista():
    pv = pytest.importorskip("pyvista")
    xyz, nrm = cloud_xyz(20), unit_normals(20)
    poly = pv.PolyData(xyz)
    got, normals = as_points(poly)
    np.testing.assert_array_equal(got, xyz)
    assert normals is None
    poly.point_data["Normals"] = nrm
    got, normals = as_points(poly)
    np.testing.assert_array_equal(normals, nrm)


def test_as_points_trimesh():
    trimesh = pytest.importorskip("trimesh")
    xyz = cloud_xyz(20)
    got, normals = as_points(trimesh.PointCloud(xyz))
    np.testing.assert_array_equal(got, xyz)
    assert normals is None
    box = trimesh.creation.box()
    got, normals = as_points(box)
    np.testing.assert_array_equal(got, box.vertices)
    np.testing.assert_array_equal(normals, box.vertex_normals)


def test_as_points_open3d():
    o3d = pytest.importorskip("open3d")
    xyz, nrm = cloud_xyz(20), unit_normals(20)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    assert as_points(pc)[1] is None
    pc.normals = o3d.utility.Vector3dVector(nrm)
    got, normals = as_points(pc)
    np.testing.assert_array_equal(got, xyz)
    np.testing.assert_allclose(normals, nrm)


def test_reconstruct_accepts_pyvista_and_open3d_like_clouds_with_their_normals():
    pv = pytest.importorskip("pyvista")
    from tiled_gridpull import reconstruct
    from tiled_gridpull.synthetic import sample_shape, sphere

    pts, nrm = sample_shape(sphere(), 3000, seed=0)
    fast = {"resolution": 32, "iterations": 60, "coarse_iterations": 60, "queries": 5000, "seed": 0}
    ref = reconstruct(pts, **fast)
    poly = reconstruct(pv.PolyData(pts), **fast)
    np.testing.assert_array_equal(poly.vertices, ref.vertices)
    np.testing.assert_array_equal(poly.faces, ref.faces)
    # the object's normals are used like normals=: the same mesh as passing them explicitly
    with_normals = reconstruct(pts, normals=nrm, normal_weight=0.1, **fast)
    got = reconstruct(FakeOpen3dCloud(pts, nrm), normal_weight=0.1, **fast)
    np.testing.assert_array_equal(got.vertices, with_normals.vertices)
    with pytest.raises(InputError, match="needs input normals"):
        reconstruct(FakeOpen3dCloud(pts), normal_weight=0.1, **fast)


def test_stream_degeneracy_is_the_rule_of_clean_points():
    """The streamed test (tiled mode) gives what the whole-array test gives, chunk size and sample aside."""
    from tiled_gridpull.cloud import degeneracy, stream_degeneracy

    rng = np.random.default_rng(4)
    t = rng.random(1000)
    line = np.c_[t, 2 * t, 3 * t] * 50 + [4e6, 5e5, 100.0]
    plane = np.c_[rng.random((1000, 2)), np.zeros(1000)] @ np.linalg.qr(rng.normal(size=(3, 3)))[0].T
    off_line = line.copy()
    off_line[5] += [0.0, 1.0, 0.0]  # one point off the line, not in an every-16th sample
    same = np.tile([[1e6, 2e6, 3.0]], (100, 1))
    for pts, flat in ((line, False), (plane, False), (plane, True), (off_line, False), (same, False),
                      (rng.random((500, 3)), True)):
        expected = degeneracy(pts, reject_planar=flat)
        for size in (7, 100, 5000):
            got = stream_degeneracy(lambda: (pts[i:i + size] for i in range(0, len(pts), size)),
                                    reject_planar=flat, sample=pts[::16])
            assert got == expected, (expected, got, size)
    assert degeneracy(off_line, reject_planar=False) is None and degeneracy(line, reject_planar=False) == "collinear"
    two = line[:2]
    assert stream_degeneracy(lambda: iter([two[:1], two[1:]]), reject_planar=False) == "collinear"
    assert stream_degeneracy(lambda: iter([]), reject_planar=False) is None
