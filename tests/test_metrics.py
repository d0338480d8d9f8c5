"""The metric functions against tiny cases whose answers are computed by hand."""

from __future__ import annotations

import numpy as np
import pytest

from tiled_gridpull.metrics import _fscore, class_scores, evaluate, footprint_scores, point_to_mesh, sample_surface
from tiled_gridpull.mesh import Mesh


def square(z: float = 0.0, tilt_deg: float = 0.0) -> Mesh:
    """The unit square [0,1]^2 at height z, two triangles, optionally rotated about its centre line y = 0.5."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
    t = np.radians(tilt_deg)
    y, zz = v[:, 1] - 0.5, v[:, 2]
    v[:, 1] = 0.5 + y * np.cos(t) - zz * np.sin(t)
    v[:, 2] = y * np.sin(t) + zz * np.cos(t) + z
    return Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))


def test_point_to_mesh_hand_computed():
    tri = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
    pts = np.array([
        [0.2, 0.2, 0.5],    # above the interior: straight down, 0.5
        [-1.0, -1.0, 0.0],  # off vertex 0: sqrt(2)
        [0.5, -2.0, 0.0],   # off the edge y = 0: 2
        [1.0, 1.0, 0.0],    # off the hypotenuse x + y = 1: (2 - 1) / sqrt(2)
    ])
    d, face = point_to_mesh(pts, tri)
    np.testing.assert_allclose(d, [0.5, np.sqrt(2), 2.0, 1 / np.sqrt(2)], atol=1e-9)
    assert (face == 0).all()


def test_point_to_mesh_georeferenced():
    """Distances stay exact with UTM-sized coordinates (the locator works on centred data)."""
    off = np.array([500000.0, 4000000.0, 100.0])
    tri = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float) + off, np.array([[0, 1, 2]]))
    d, _ = point_to_mesh(np.array([[0.25, 0.25, 0.003]]) + off, tri)
    assert abs(d[0] - 0.003) < 1e-7


def test_fscore_hand_computed():
    f, precision, recall = _fscore(np.array([0.0, 0.1, 0.3]), np.array([0.05, 0.2]), 0.15)
    assert precision == pytest.approx(2 / 3) and recall == pytest.approx(1 / 2)
    assert f == pytest.approx(4 / 7)
    assert _fscore(np.array([1.0]), np.array([1.0]), 0.5)[0] == 0.0


def test_parallel_squares():
    """Two unit squares 0.01 apart: every exact distance is 0.01, normals agree."""
    d = 0.01
    res = evaluate(square(d), square(0.0), n_samples=20000, thresholds=(0.005, 0.02))
    assert res["chamfer_l1_exact"] == pytest.approx(d, rel=1e-6)
    assert res["chamfer_l2_exact"] == pytest.approx(d * d, rel=1e-5)
    assert res["hausdorff_exact"] == pytest.approx(d, rel=1e-6)
    assert res["normal_consistency"] == pytest.approx(1.0) and res["normal_consistency_exact"] == pytest.approx(1.0)
    assert res["fscore_exact@0.005"] == 0.0 and res["fscore_exact@0.02"] == 1.0
    # sample-based: nearest *sample* is at least d away and, with 20k samples on a unit square, within ~1/100
    assert d <= res["chamfer_l1"] < d + 0.01
    assert res["chamfer_l2"] >= d * d
    assert res["chamfer_l2_x100"] == pytest.approx(100 * res["chamfer_l2"])
    assert res["fscore@0.005"] == 0.0
    assert res["watertight"] is False and res["boundary_edges"] == 4 and res["components"] == 1


def test_tilted_square_normal_consistency_is_cosine():
    res = evaluate(square(0.0, tilt_deg=60.0), square(0.0), n_samples=5000)
    assert res["normal_consistency"] == pytest.approx(0.5, abs=1e-9)
    assert res["normal_consistency_exact"] == pytest.approx(0.5, abs=1e-9)
    # flipping the prediction's orientation leaves |cos| unchanged
    flipped = square(0.0, tilt_deg=60.0)
    flipped = Mesh(flipped.vertices, flipped.faces[:, ::-1])
    assert evaluate(flipped, square(0.0), n_samples=5000)["normal_consistency"] == pytest.approx(0.5, abs=1e-9)


def test_identical_meshes_have_zero_exact_error_and_a_sampling_floor():
    m = square(0.0)
    res = evaluate(m, m, n_samples=10000)
    assert res["chamfer_l1_exact"] < 1e-12 and res["hausdorff_exact"] < 1e-12
    assert 0 < res["chamfer_l1"] < 0.01  # independent samples of one surface are not at zero distance


@pytest.mark.parametrize("side", [1.0, 40.0])
def test_chamfer_l1_floor_predicts_the_sampled_score_of_a_perfect_mesh(side):
    """The floor is what the samples alone score (within 10%), and it grows with the side: a 40 m square with
    20,000 samples scores ~7 cm with nothing wrong (the exact figure stays 0)."""
    m = Mesh(square(0.0).vertices * side, square(0.0).faces)
    res = evaluate(m, m, n_samples=20000)
    assert res["chamfer_l1_floor"] == pytest.approx(0.5 * side / np.sqrt(20000))
    assert res["chamfer_l1"] == pytest.approx(res["chamfer_l1_floor"], rel=0.1)
    assert res["chamfer_l1_exact"] < 1e-9 * side


def test_sample_surface_is_area_uniform():
    # two triangles of areas 1 and 3 in the plane z = 0
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [10, 0, 0], [13, 0, 0], [10, 2, 0]], float)
    m = Mesh(v, np.array([[0, 1, 2], [3, 4, 5]]))
    pts, nrm = sample_surface(m, 40000, seed=1)
    share = np.mean(pts[:, 0] >= 10)
    assert share == pytest.approx(0.75, abs=0.01)
    np.testing.assert_allclose(np.abs(nrm[:, 2]), 1.0)
    first = pts[pts[:, 0] < 10]
    assert np.all(first[:, 0] / 1 + first[:, 1] / 2 <= 1 + 1e-9) and np.all(first >= -1e-12)


def test_topology_of_a_tetrahedron_and_two_pieces():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    tet = Mesh(v, f)
    t = tet.topology
    assert t.watertight and t.components == 1 and t.boundary_edges == 0 and t.nonmanifold_edges == 0
    two = Mesh(np.vstack([v, v + 5]), np.vstack([f, f + 4]))
    assert two.topology.components == 2 and two.topology.watertight
    open_tet = Mesh(v, f[:3])
    assert not open_tet.topology.watertight and open_tet.topology.boundary_edges == 3


def two_classes() -> tuple[Mesh, dict]:
    """A floor (the unit square) and a second square 3 to 4 along x: faces 0-1 and 2-3."""
    a, b = square(), square()
    verts = np.concatenate([a.vertices, b.vertices + [3.0, 0.0, 0.0]])
    return Mesh(verts, np.concatenate([a.faces, b.faces + 4])), {"floor": (0, 2), "post": (2, 4)}


def test_class_scores_hand_computed():
    gt, classes = two_classes()
    # the floor tilted by 20 degrees about its centre line; a half-width copy of the post tilted by 40 degrees:
    # a third of the mesh's area lies by the post
    floor = square(tilt_deg=20.0)
    post = square(tilt_deg=40.0)
    post_v = post.vertices * [0.5, 1.0, 1.0] + [3.0, 0.0, 0.0]
    # the post's copy wound the other way (its normal points down): the consistency is of unoriented normals
    pred = Mesh(np.concatenate([floor.vertices, post_v]), np.concatenate([floor.faces, post.faces[:, ::-1] + 4]))
    s = class_scores(pred, gt, classes, n_samples=20000, tau=0.05)
    for name, tilt, share in (("floor", 20.0, 2 / 3), ("post", 40.0, 1 / 3)):
        c = s[name]
        # every sample of a square faces a face of the tilted copy above it
        assert c["normal_consistency"] == pytest.approx(np.cos(np.radians(tilt)), abs=1e-9)
        assert c["pred_share"] == pytest.approx(share, abs=0.015)
        # a point of the copy at y along its surface is |y - 0.5| sin(tilt) from the truth's plane: mean sin / 4
        assert c["accuracy"] == pytest.approx(np.sin(np.radians(tilt)) / 4, rel=0.03)
    # the truth's floor, measured to the tilted floor: the distance of (x, y, 0) to it, integrated over y
    y = np.linspace(0, 1, 200001)
    d, _ = point_to_mesh(np.c_[np.full(len(y), 0.5), y, np.zeros(len(y))], floor)
    assert s["floor"]["completeness"] == pytest.approx(d.mean(), rel=0.03)
    assert s["floor"]["recall"] == pytest.approx(np.mean(d <= 0.05), abs=0.02)
    # half of the post's truth (x beyond 3.5) has no pred face above it: at least its distance to the copy's edge
    assert s["post"]["recall"] < 0.6


def test_class_scores_a_missing_class_and_the_order_of_classes():
    gt, classes = two_classes()
    pred = square(z=0.01)
    s = class_scores(pred, gt, classes, n_samples=4000, tau=0.05)
    assert s["floor"]["pred_share"] == 1.0 and s["post"]["pred_share"] == 0.0 and s["post"]["accuracy"] is None
    assert s["post"]["completeness"] >= 2.0 and s["post"]["recall"] == 0.0
    assert s["floor"]["completeness"] == pytest.approx(0.01) and s["floor"]["recall"] == 1.0
    # the same scores whatever the order of the classes
    assert class_scores(pred, gt, dict(reversed(list(classes.items()))), n_samples=4000, tau=0.05) == s


def test_class_scores_observed_and_bad_spans():
    gt, classes = two_classes()
    pred = gt
    near_floor = np.random.default_rng(0).random((500, 3)) * [1, 1, 0]
    s = class_scores(pred, gt, classes, n_samples=2000, observed=near_floor, observed_radius=0.1)
    assert s["post"]["gt_samples"] == 0 and s["post"]["completeness"] is None
    assert s["floor"]["gt_samples"] > 1500 and s["floor"]["completeness"] < 1e-9
    with pytest.raises(ValueError, match="class 'post'"):
        class_scores(pred, gt, {"post": (2, 9)})
    with pytest.raises(ValueError, match="integers"):
        class_scores(pred, gt, {"post": (0.5, 2.9)})
    with pytest.raises(ValueError, match="share faces"):
        class_scores(pred, gt, {"floor": (0, 3), "post": (2, 4)})
    # an empty class: no samples, not an error
    empty = class_scores(pred, gt, {"floor": (0, 2), "none": (2, 2)}, n_samples=500)
    assert empty["none"] == {"pred_share": 0.0, "accuracy": None, "gt_samples": 0, "completeness": None,
                             "recall": None, "normal_consistency": None}


def rect(x0: float, x1: float, y0: float, y1: float, z: float = 0.0) -> Mesh:
    """An axis-aligned rectangle at height z, two triangles."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
    return Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))


def test_footprint_scores_hand_computed():
    # truth: the ground [0, 10] x [0, 10]; points cover x <= 4 (a line every 0.5 m): the footprint within R = 1
    # is x <= 5, within R = 3 it is x <= 7
    gx, gy = np.meshgrid(np.arange(0.0, 4.01, 0.5), np.arange(0.0, 10.01, 0.1))
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    gt = rect(0, 10, 0, 10)
    # the mesh: the data's part bridged 5 cm high (a hit), and a far sheet 1 m up over [0, 4] x [0, 2]
    near = rect(0, 4, 0, 10, z=0.05)
    far = rect(0, 4, 0, 2, z=1.0)
    pred = Mesh(np.concatenate([near.vertices, far.vertices]), np.concatenate([near.faces, far.faces + 4]))
    out = footprint_scores(pred, gt, pts, radii=(1.0, 3.0), tau=0.1, n_samples=100_000)
    # the truth within tau of the bridge's edge counts too: sqrt(0.1^2 - 0.05^2) past x = 4
    reach = 4 + np.sqrt(0.1 ** 2 - 0.05 ** 2)
    assert out["footprint_recall@1"] == pytest.approx(reach / 5, abs=0.005)
    assert out["footprint_recall@3"] == pytest.approx(reach / 7, abs=0.005)
    assert out["footprint_samples@1"] == pytest.approx(50_000, rel=0.02)
    # 40 m2 right, 8 m2 a metre off
    assert out["precision@0.1"] == pytest.approx(40 / 48, abs=0.01)
    assert out["boundary_edges"] == 8 and out["components"] == 2
    # a bridge 15 cm off the truth is a miss at tau 0.1 and a hit at 0.2
    high = rect(0, 4, 0, 10, z=0.15)
    assert footprint_scores(high, gt, pts, radii=(1.0,), tau=0.1)["footprint_recall@1"] == 0.0
    reach = 4 + np.sqrt(0.2 ** 2 - 0.15 ** 2)
    assert footprint_scores(high, gt, pts, radii=(1.0,), tau=0.2)["footprint_recall@1"] == pytest.approx(reach / 5,
                                                                                                        abs=0.005)


@pytest.mark.parametrize("kw", [{"radii": ()}, {"radii": (0.0,)}, {"radii": (np.inf,)}, {"tau": -1.0}])
def test_footprint_scores_refuses_bad_settings(kw):
    pts = np.zeros((3, 3))
    with pytest.raises(ValueError):
        footprint_scores(rect(0, 1, 0, 1), rect(0, 1, 0, 1), pts, **kw)


def test_visible_from_leaves_out_shadows_and_what_the_beams_do_not_reach():
    from tiled_gridpull.synthetic.lidar import visible_from

    ground = rect(0, 20, -5, 5)
    # a wall 2 m wide and 3 m high across the line of sight at x = 10
    wv = np.array([[10, -1, 0], [10, 1, 0], [10, 1, 3], [10, -1, 3]], np.float64)
    scene = Mesh(np.concatenate([ground.vertices, wv]), np.concatenate([ground.faces, [[4, 5, 6], [4, 6, 7]]]))
    sensor = np.array([[0.0, 0.0, 1.73]])
    q = np.array([[15, 0, 0],      # ground in the wall's shadow
                  [15, 3, 0],      # ground beside the shadow, 6.5 degrees down
                  [2, 0, 0],       # ground 41 degrees down: below the lowest beam (-24.8)
                  [10, 0, 1.0],    # the wall's face, in view
                  [10, 0, 2.9],    # the wall 6.7 degrees up: above the highest beam (+2)
                  [19, -4.5, 0]], np.float64)
    assert visible_from(scene, q, sensor).tolist() == [False, True, False, True, False, True]
    # a second sensor past the wall sees its shadow; far ranges do not return
    assert visible_from(scene, q[:1], np.array([[0.0, 0.0, 1.73], [20.0, 0.0, 1.73]])).tolist() == [True]
    assert not visible_from(scene, q[1:2], sensor, max_range=10.0)[0]


def test_footprint_scores_split_what_a_sensor_sees():
    # truth: the ground [0, 20] x [-5, 5] and a wall 2 m wide at x = 10, seen from (0, 0, 1.73); the points:
    # lines across the ground, none in the wall's shadow (|y| < x / 10 beyond it)
    ground = rect(0, 20, -5, 5)
    wv = np.array([[10, -1, 0], [10, 1, 0], [10, 1, 3], [10, -1, 3]], np.float64)
    gt = Mesh(np.concatenate([ground.vertices, wv]), np.concatenate([ground.faces, [[4, 5, 6], [4, 6, 7]]]))
    gx, gy = np.meshgrid(np.arange(4.0, 20.01, 1.0), np.arange(-5.0, 5.01, 0.1))
    keep = (gx < 10) | (np.abs(gy) > gx / 10)
    pts = np.stack([gx[keep], gy[keep], np.zeros(keep.sum())], axis=1)
    sensor = np.array([[0.0, 0.0, 1.73]])
    # two meshes: the whole ground, and the ground less a strip inside the shadow
    parts = [rect(0, 20, -5, -1), rect(0, 20, 1, 5), rect(0, 10.5, -1, 1)]
    holed = Mesh(np.concatenate([p.vertices for p in parts]), np.concatenate([p.faces + 4 * k
                                                                             for k, p in enumerate(parts)]))
    from tiled_gridpull.synthetic.lidar import visible_from

    def seen_by(p):
        return visible_from(gt, p, sensor)

    whole = footprint_scores(ground, gt, pts, radii=(1.5,), n_samples=100_000, seen_by=seen_by)
    cut = footprint_scores(holed, gt, pts, radii=(1.5,), n_samples=100_000, seen_by=seen_by)
    assert 0.5 < whole["footprint_seen@1.5"] < 0.97 and cut["footprint_seen@1.5"] == whole["footprint_seen@1.5"]
    # the strip is a miss of the footprint, not of what the sensor saw
    assert cut["footprint_recall@1.5"] < whole["footprint_recall@1.5"] - 0.02
    assert cut["footprint_seen_recall@1.5"] == pytest.approx(whole["footprint_seen_recall@1.5"], abs=0.002)
    assert "footprint_seen@1.5" not in footprint_scores(ground, gt, pts, radii=(1.5,), n_samples=20_000)
