"""Thin walls in a scene: a wall two cells thick, scanned from both sides, keeps both of its faces."""

import subprocess
import sys

import pytest

from tiled_gridpull.io import read_mesh
from tiled_gridpull.metrics import class_scores
from tiled_gridpull.synthetic.fence import FENCE_CLASSES, fence_scene

from conftest import REPO


def test_fence_scene_ground_truth_and_sensors(tmp_path):
    s = fence_scene(tmp_path / "seq", 0.2, 0.05, length=2.0, height=1.0, ground=(4.0, 4.0), spacing=0.05)
    assert tuple(s["classes"]) == FENCE_CLASSES
    gt = s["gt"]
    front = gt.vertices[gt.faces[slice(*s["classes"]["front"])]]
    back = gt.vertices[gt.faces[slice(*s["classes"]["back"])]]
    assert front[..., 1].max() == pytest.approx(-0.05) and back[..., 1].min() == pytest.approx(0.15)
    # every sample lies on the truth, and the two frames' scans are in their own sensor's frame
    from tiled_gridpull.io.kitti import read_kitti_sequence
    from tiled_gridpull.metrics import point_to_mesh

    cloud = read_kitti_sequence(s["sequence"])
    assert len(cloud.xyz) == len(s["points"])
    d, _ = point_to_mesh(cloud.xyz, gt)
    assert d.max() < 1e-5
    # the front face is seen from y < 0 only, the back face from y > 0 only
    on_front = abs(cloud.xyz[:, 1] + 0.05) < 1e-5
    on_back = abs(cloud.xyz[:, 1] - 0.15) < 1e-5
    assert (cloud.sensor[on_front, 1] < 0).all() and (cloud.sensor[on_back, 1] > 0).all()
    with pytest.raises(ValueError, match="thickness"):
        fence_scene(tmp_path / "bad", 0.0)


def test_a_wall_two_cells_thick_keeps_both_faces(tmp_path):
    """configs/scene.yaml at 0.1 m cells: a 0.2 m wall with vertex planes inside it comes out as two faces, each
    within 2 cm of its truth over most of its area, not as one sheet in the middle (which would lie 10 cm from
    both)."""
    s = fence_scene(tmp_path / "seq", 0.2, 0.05, length=4.0, height=1.5, ground=(8.0, 8.0))
    out = tmp_path / "mesh.ply"
    subprocess.run([sys.executable, "-m", "tiled_gridpull", "reconstruct", str(s["sequence"]), "-o", str(out),
                    "--config", str(REPO / "configs" / "scene.yaml"), "--voxel-size", "0.1", "--workers", "1",
                    "-q"], check=True)
    scores = class_scores(read_mesh(out), s["gt"], s["classes"], n_samples=50_000, tau=0.02,
                          observed=s["points"], observed_radius=0.05)
    for face in ("front", "back"):
        assert scores[face]["recall"] > 0.8, (face, scores[face])
        assert scores[face]["completeness"] < 0.02, (face, scores[face])
        assert scores[face]["normal_consistency"] > 0.9, (face, scores[face])
    assert scores["ground"]["recall"] > 0.95
