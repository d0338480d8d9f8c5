"""Bad input found by a red-team pass over the command line (2026-11-27): each case is one line naming the
problem, the right exit code, nothing written, and never an "internal error"."""

import logging
import os
import sys
import tempfile

import numpy as np
import pytest

import tiled_gridpull
from tiled_gridpull import reconstruct
from tiled_gridpull.errors import InputError
from tiled_gridpull.outliers import STRETCH_LIMIT, stray_points
from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.synthetic import sample_shape, sphere

FAST = ["--resolution", "32", "--iterations", "30", "-q"]


def run(args, capsys):
    code = main(args)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _one_error_line(err, needle):
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert needle in lines[0], lines[0]


@pytest.fixture
def survey(tmp_path):
    """A sphere 10 m across at UTM-like coordinates, and the same with one stray (0, 0, 0)."""
    pts, _ = sample_shape(sphere(), 3000, seed=0)
    pts = pts * 10.0 + [500000.0, 4000000.0, 100.0]
    clean = tmp_path / "clean.xyz"
    stray = tmp_path / "stray.xyz"
    np.savetxt(clean, pts, fmt="%.4f")
    np.savetxt(stray, np.vstack([pts, [[0.0, 0.0, 0.0]]]), fmt="%.4f")
    return pts, clean, stray


def test_stray_points_are_found_only_where_they_stretch_the_cloud(survey):
    pts, _, _ = survey
    assert stray_points(pts) is None
    far, box = stray_points(np.vstack([pts, [[0.0, 0.0, 0.0]]]))
    assert far.sum() == 1 and far[-1]
    # a far point that stretches the cloud less than STRETCH_LIMIT times is left to the lattice
    near = pts.min(axis=0) - 0.5 * STRETCH_LIMIT * 10.0 * np.array([1.0, 0.0, 0.0])
    assert stray_points(np.vstack([pts, [near]])) is None


def test_one_shape_refuses_a_stray_point_and_drops_it_on_request(survey, tmp_path, capsys):
    """Before: exit 0 and an empty mesh (the lattice spanned 4,000 km; the sphere got no cell)."""
    _, _, stray = survey
    out = tmp_path / "m.ply"
    code, _, err = run(["reconstruct", str(stray), "-o", str(out), *FAST], capsys)
    assert code == 3
    _one_error_line(err, "far from the rest")
    assert "(0, 0, 0)" in err and "--drop-outliers" in err
    assert not out.exists() and not out.with_suffix(".json").exists()
    code, _, err = run(["reconstruct", str(stray), "-o", str(out), *FAST, "--drop-outliers"], capsys)
    assert code == 0, err
    import json

    assert json.loads(out.with_suffix(".json").read_text())["input"]["far_points_dropped"] == 1
    from tiled_gridpull.io import read_mesh

    mesh = read_mesh(out)
    assert mesh.n_faces > 500
    assert np.all(mesh.vertices.min(axis=0) > [499990.0, 3999990.0, 90.0])


def test_the_api_refuses_a_stray_point_too(survey):
    pts, _, _ = survey
    with pytest.raises(InputError, match="far from the rest"):
        reconstruct(np.vstack([pts, [[0.0, 0.0, 0.0]]]), resolution=32, iterations=10)
    mesh = reconstruct(np.vstack([pts, [[0.0, 0.0, 0.0]]]), resolution=32, iterations=30, drop_outliers=True)
    assert mesh.n_faces > 500 and mesh.metadata["input"]["far_points_dropped"] == 1


def test_an_empty_mesh_is_refused_not_written(survey, tmp_path, capsys, monkeypatch):
    from tiled_gridpull.mesh import Mesh

    _, clean, _ = survey
    # the command imports reconstruct when it runs (the package's own name is the function)
    monkeypatch.setattr(sys.modules["tiled_gridpull.reconstruct"], "reconstruct",
                        lambda *a, **k: Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64)))
    out = tmp_path / "m.ply"
    code, _, err = run(["reconstruct", str(clean), "-o", str(out), *FAST], capsys)
    assert code == 3
    _one_error_line(err, "no surface")
    assert not out.exists() and not out.with_suffix(".json").exists()


def test_non_finite_rows_are_said_on_the_read_line(survey, tmp_path, capsys, caplog):
    caplog.set_level(logging.INFO)
    pts, _, _ = survey
    src = tmp_path / "nan.xyz"
    np.savetxt(src, np.vstack([pts, [[np.nan, 1.0, 2.0]]]), fmt="%.4f")
    code, _, err = run(["reconstruct", str(src), "-o", str(tmp_path / "m.ply"), "--resolution", "32",
                        "--iterations", "30"], capsys)
    assert code == 0
    assert "1 with NaN or infinite coordinates, dropped" in err + caplog.text


@pytest.fixture
def meshes(tmp_path):
    from tiled_gridpull.io import write_mesh
    from tiled_gridpull.synthetic import sphere as sphere_mesh

    m = sphere_mesh()
    path = tmp_path / "gt.ply"
    write_mesh(m, path)
    return path


@pytest.mark.parametrize("opts,needle", [
    (["--samples", "0"], "--samples"),
    (["--samples", "-5"], "--samples"),
    (["--thresholds", "nan"], "--thresholds"),
    (["--thresholds", "0.1", "-1"], "--thresholds"),
    (["--observed-radius", "-1"], "--observed-radius"),
    (["--observed-radius", "nan"], "--observed-radius"),
])
def test_evaluate_refuses_bad_numbers(meshes, capsys, opts, needle):
    code, _, err = run(["evaluate", str(meshes), str(meshes), *opts], capsys)
    assert code == 2
    _one_error_line(err, needle)


def test_evaluate_with_a_cloud_elsewhere_is_a_bad_input_not_a_bug(meshes, tmp_path, capsys):
    far = tmp_path / "far.xyz"
    np.savetxt(far, np.random.default_rng(0).normal(size=(200, 3)) + [5e5, 4e6, 0.0])
    code, _, err = run(["evaluate", str(meshes), str(meshes), "--samples", "2000", "--observed", str(far)], capsys)
    assert code == 3
    _one_error_line(err, "no ground-truth sample lies within --observed-radius")


def test_sample_refuses_a_file_as_its_directory_and_a_non_finite_origin(tmp_path, capsys):
    f = tmp_path / "a_file"
    f.write_text("x")
    code, _, err = run(["sample", "sphere", str(f), "--points", "500"], capsys)
    assert code == 2
    _one_error_line(err, "not a directory")
    code, _, err = run(["sample", "street", str(tmp_path / "s"), "--points", "2000", "--frames", "1",
                        "--origin", "nan", "0", "0"], capsys)
    assert code == 2
    _one_error_line(err, "--origin")
    assert not (tmp_path / "s").exists()


def test_render_checks_its_output_before_rendering(meshes, tmp_path, capsys):
    f = tmp_path / "a_file"
    f.write_text("x")
    code, _, err = run(["render", str(meshes), "-o", str(f / "a.png")], capsys)
    assert code == 2
    _one_error_line(err, "is a file, not a directory")


def test_frames_on_a_file_is_refused_in_tiled_mode(survey, tmp_path, capsys):
    _, clean, _ = survey
    code, _, err = run(["reconstruct", str(clean), "-o", str(tmp_path / "m.ply"), "--voxel-size", "0.5",
                        "--frames", "0:1"], capsys)
    assert code == 2
    _one_error_line(err, "--frames applies to KITTI sequence directories only")


def test_numba_cache_goes_to_a_temporary_directory_where_nothing_else_is_writable(monkeypatch):
    """A container run as another user with HOME unset: every cached kernel raised "no locator available" at
    import, before --help."""
    real_access = os.access
    kernels = os.path.join(os.path.dirname(tiled_gridpull.__file__), "kernels")
    monkeypatch.setattr(os, "access", lambda p, mode: False if str(p).startswith(kernels) else real_access(p, mode))
    monkeypatch.setenv("HOME", "/nonexistent")
    got = tiled_gridpull._numba_cache_dir()
    assert got is not None and got.startswith(tempfile.gettempdir())
    monkeypatch.setattr(os, "access", real_access)
    assert tiled_gridpull._numba_cache_dir() is None  # this checkout's kernels directory is writable


def test_a_directory_as_the_config_file_is_named_as_such(survey, tmp_path, capsys):
    _, clean, _ = survey
    code, _, err = run(["reconstruct", str(clean), "-o", str(tmp_path / "m.ply"), "--config", str(tmp_path)], capsys)
    assert code == 2
    _one_error_line(err, "a directory, not a YAML file")


def test_one_shape_takes_min_component_cells_from_the_command_line(survey, tmp_path, capsys):
    """``--set min_component_cells`` reaches the one-shape mode (it once answered "need voxel_size"): this short
    solve leaves specks that 2 cells (the default, as in tiled mode) drop and 0 keeps; more cells than the sphere is
    across drop it all, said as such, nothing written; a bad value is one line."""
    import json

    from tiled_gridpull.io import read_mesh

    pts, clean, _ = survey
    removed, faces = {}, {}
    for value in ("0", "2", None):
        out = tmp_path / f"m{value}.ply"
        code, _, err = run(["reconstruct", str(clean), "-o", str(out), *FAST,
                            *(["--set", f"min_component_cells={value}"] if value else [])], capsys)
        assert code == 0, err
        removed[value] = json.loads(out.with_suffix(".json").read_text())["small_components_removed"]
        faces[value] = read_mesh(out).n_faces
    assert removed["0"] == 0 < removed["2"] == removed[None] and faces["0"] > faces["2"] == faces[None]
    out = tmp_path / "none.ply"
    code, _, err = run(["reconstruct", str(clean), "-o", str(out), *FAST, "--set", "min_component_cells=60"], capsys)
    assert code != 0
    _one_error_line(err, "smaller than min_component_cells")
    assert not out.exists() and not out.with_suffix(".json").exists()
    for bad in ("abc", "-1", ".nan", "true"):
        code, _, err = run(["reconstruct", str(clean), "-o", str(out), *FAST, "--set", f"min_component_cells={bad}"],
                           capsys)
        assert code == 2, (bad, err)
        _one_error_line(err, "min_component_cells")
    with pytest.raises(Exception, match="min_component_cells must be a finite number"):
        reconstruct(pts, resolution=32, iterations=10, min_component_cells="2")
