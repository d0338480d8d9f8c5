"""The command line: one-line errors with the right exit code and no output file; working subcommands."""

import json
import subprocess
import sys

import numpy as np
import pytest

from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.synthetic import sample_shape, sphere


def run(args, capsys):
    code = main(args)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture
def sphere_xyz(tmp_path):
    pts, _ = sample_shape(sphere(), 5000, seed=0)
    p = tmp_path / "sphere.xyz"
    np.savetxt(p, pts)
    return p


def _one_error_line(err):
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("error: ")
    assert "Traceback" not in err


@pytest.mark.parametrize("content,suffix,needle", [
    (None, ".ply", "not found"),
    ("1 2 3\n", ".foo", "unknown"),
    ("", ".xyz", "no points"),
    ("1 2 3\n4 5 6\n", ".xyz", "points"),
    ("nan nan nan\n" * 20, ".xyz", "finite"),
    ("1 1 1\n" * 50, ".xyz", ""),
    ("".join(f"{i} {2 * i} {3 * i}\n" for i in range(50)), ".xyz", "collinear"),
])
def test_bad_inputs_one_line_no_output(tmp_path, capsys, content, suffix, needle):
    src = tmp_path / f"in{suffix}"
    if content is not None:
        src.write_text(content)
    out = tmp_path / "out.ply"
    code, _, err = run(["reconstruct", str(src), "-o", str(out), "-q"], capsys)
    assert code == 3
    _one_error_line(err)
    assert needle in err.lower()
    assert not out.exists() and not out.with_suffix(".json").exists()


@pytest.mark.parametrize("opts,needle", [
    (["--resolution", "0"], "resolution"),
    (["--iterations", "-5"], "iterations"),
    (["--set", "alpha=-1"], "alpha"),
    (["--set", "bogus=1"], "unknown"),
    (["--set", "tv_form=cubic"], "tv_form"),
    (["--voxel-size", "0.1", "--tile-size", "1", "--overlap", "5"], "overlap"),
    (["--voxel-size", "-1"], "voxel_size"),
    (["--normals", "--voxel-size", "0.1"], "one-shape"),
    (["--set", "noise_cells=-1"], "noise_cells"),
    (["--set", "noise_cells=1.5", "--voxel-size", "0.1"], "noise_cells"),
])
def test_bad_options_rejected_before_work(tmp_path, capsys, sphere_xyz, opts, needle):
    out = tmp_path / "out.ply"
    code, _, err = run(["reconstruct", str(sphere_xyz), "-o", str(out), "-q", *opts], capsys)
    assert code == 2
    _one_error_line(err)
    assert needle in err
    assert not out.exists()


def test_bad_config_file(tmp_path, capsys, sphere_xyz):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("resolution: [1, 2\n")
    code, _, err = run(["reconstruct", str(sphere_xyz), "-o", str(tmp_path / "o.ply"), "--config", str(cfg)],
                       capsys)
    assert code == 2 and "YAML" in err
    _one_error_line(err)


def test_config_key_given_twice_is_refused(tmp_path, capsys, sphere_xyz):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("resolution: 40\niterations: 100\nresolution: 64\n")
    code, _, err = run(["reconstruct", str(sphere_xyz), "-o", str(tmp_path / "o.ply"), "--config", str(cfg)],
                       capsys)
    assert code == 2 and "'resolution' is given twice (line 3)" in err, err
    _one_error_line(err)
    assert not (tmp_path / "o.ply").exists()


@pytest.mark.slow
def test_reconstruct_evaluate_roundtrip(tmp_path, capsys, sphere_xyz):
    out = tmp_path / "mesh.ply"
    code, _, err = run(["reconstruct", str(sphere_xyz), "-o", str(out), "-q", "--resolution", "40",
                        "--iterations", "200", "--set", "coarse_iterations=200"], capsys)
    assert code == 0, err
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["config"]["resolution"] == 40 and "lattice" in side and "timings_s" in side
    gt = tmp_path / "gt.ply"
    from tiled_gridpull.io import write_mesh

    write_mesh(sphere(), gt)
    code, text, _ = run(["evaluate", str(out), str(gt), "--json", "--samples", "20000"], capsys)
    assert code == 0
    res = json.loads(text)
    assert res["watertight"] is True
    assert res["chamfer_l1_exact"] < 0.01


def test_help_lists_defaults():
    out = subprocess.run([sys.executable, "-m", "tiled_gridpull", "evaluate", "--help"], capture_output=True,
                         text=True, check=True).stdout
    assert "default: 100000" in out


def test_normals_flag_needs_normals_in_the_input(tmp_path, capsys, sphere_xyz):
    out = tmp_path / "out.ply"
    code, _, err = run(["reconstruct", str(sphere_xyz), "-o", str(out), "-q", "--normals"], capsys)
    assert code == 3
    _one_error_line(err)
    assert "normals" in err and not out.exists()


def test_normals_flag_supervises_with_the_file_normals(tmp_path, capsys):
    from tiled_gridpull.metrics import sample_surface

    pts, nrm = sample_surface(sphere(), 5000, seed=0)
    src = tmp_path / "with_normals.xyz"
    np.savetxt(src, np.hstack([pts, nrm]))
    out = tmp_path / "mesh.ply"
    code, _, err = run(["reconstruct", str(src), "-o", str(out), "-q", "--normals", "--resolution", "40",
                        "--iterations", "100", "--set", "coarse_iterations=100"], capsys)
    assert code == 0, err
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["config"]["losses"]["normal_weight"] == 1.0
    assert side["loss_history"][-1]["normal"] > 0  # the normal loss was evaluated
    code, _, err = run(["reconstruct", str(src), "-o", str(out), "-q", "--normals", "--resolution", "40",
                        "--iterations", "100", "--set", "coarse_iterations=100", "--set", "normal_weight=0.25"],
                       capsys)
    assert code == 0 and json.loads(out.with_suffix(".json").read_text())["config"]["losses"]["normal_weight"] == 0.25


@pytest.mark.parametrize("argv,needle", [
    (["reconstruct"], "required: INPUT"),
    (["reconstruct", "a.ply", "-o", "b.ply", "--workers", "abc"], "invalid int value: 'abc'"),
    (["frob"], "invalid choice: 'frob'"),
])
def test_usage_mistakes_are_one_line(argv, needle, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and needle in err and "--help" in err
    _one_error_line(err)


def test_warnings_are_one_line_without_source_paths(tmp_path, sphere_xyz):
    pts = np.loadtxt(sphere_xyz)
    pts[:5] = np.nan
    src = tmp_path / "holes.xyz"
    np.savetxt(src, pts)
    proc = subprocess.run([sys.executable, "-m", "tiled_gridpull", "reconstruct", str(src), "-o",
                           str(tmp_path / "m.ply"), "-q", "--resolution", "32", "--iterations", "50", "--set",
                           "coarse_iterations=50"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert any(ln.startswith("warning: ") and "dropped 5 of 5000 points" in ln for ln in lines), proc.stderr
    assert ".py:" not in proc.stderr and "UserWarning" not in proc.stderr


def test_truncated_laz_is_one_line_without_laspy_log(tmp_path):
    """laspy logs lazrs's error ("IoError: failed to fill whole buffer") before raising; our one-line error says
    it already, so the library's line must not reach stderr."""
    import laspy

    xyz = np.random.default_rng(0).uniform(0, 50, size=(60_000, 3))
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001] * 3)
    header.offsets = np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    whole = tmp_path / "whole.laz"
    las.write(str(whole))
    cut = tmp_path / "cut.laz"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size * 2 // 3])
    cmd = [sys.executable, "-m", "tiled_gridpull", "reconstruct", str(cut), "-o", str(tmp_path / "m.ply")]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 3, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "cut.laz: truncated" in lines[0], proc.stderr
    assert not (tmp_path / "m.ply").exists()


def test_disk_full_while_writing_is_one_line_exit_3_and_leaves_no_file(tmp_path, capsys, monkeypatch, sphere_xyz):
    """A full disk is the machine's problem, not a bug: one line naming the file, exit 3, no partial output
    (it was 'internal error', exit 1)."""
    import errno

    import tiled_gridpull.io.meshes as meshes

    real = meshes._write_to

    def full(fh, mesh, path, float32, offset):
        real(fh, mesh, path, float32, offset)
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(meshes, "_write_to", full)
    out = tmp_path / "m.ply"
    code = main(["reconstruct", str(sphere_xyz), "-o", str(out), "-q", "--resolution", "32", "--iterations", "30",
                 "--set", "coarse_iterations=30"])
    err = capsys.readouterr().err
    assert code == 3, err
    assert err.strip() == f"error: {out}: No space left on device"
    assert sorted(p.name for p in tmp_path.iterdir()) == [sphere_xyz.name]  # no mesh, sidecar or temporary


def test_separate_kitti_scans_are_refused_not_merged_unregistered(tmp_path, capsys):
    """Two KITTI scan files, each in its own sensor frame: merging them would overlay unregistered scans."""
    rng = np.random.default_rng(0)
    scans = []
    for i in range(2):
        xyz = rng.uniform(-20, 20, size=(3000, 3)).astype("<f4")
        scans.append(tmp_path / f"{i:06d}.bin")
        np.column_stack([xyz, np.zeros(len(xyz), "<f4")]).tofile(scans[-1])
    out = tmp_path / "mesh.ply"
    tiled = ["--voxel-size", "0.5", "--overlap", "5", "-q"]
    code, _, err = run(["reconstruct", *map(str, scans), "-o", str(out), *tiled], capsys)
    assert code == 3 and "own sensor frame" in err and "poses.txt" in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and not out.with_suffix(".job").exists()
    code, _, err = run(["reconstruct", *map(str, scans), "-o", str(out), *tiled, "--dry-run"], capsys)
    assert code == 3 and "own sensor frame" in err


def test_band_edges_option_reaches_the_solve_and_the_sidecar(tmp_path, capsys):
    """A tube's wall without its ends: the sheets past the data are cut back by default, sealed with --band-edges
    close; the sidecar says which."""
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 2 * np.pi, 8000)
    src = tmp_path / "tube.xyz"
    np.savetxt(src, np.stack([0.2 * np.cos(t), 0.2 * np.sin(t), rng.uniform(-0.5, 0.5, len(t))], axis=1))
    for rule in ("trim", "close"):
        out = tmp_path / f"{rule}.ply"
        code, _, err = run(["reconstruct", str(src), "-o", str(out), "-q", "--resolution", "64",
                            *(["--band-edges", rule] if rule != "trim" else [])], capsys)
        assert code == 0, err
        rec = json.loads(out.with_suffix(".json").read_text())["band_edges"]
        assert rec["rule"] == rule and rec["loops"] == 2, rec  # one at each end of the tube
        assert (rec["faces_trimmed"] > 0, rec["loops_closed"]) == (rule == "trim", 2 if rule == "close" else 0), rec


def test_evaluate_footprint(tmp_path, capsys):
    from tiled_gridpull.io import write_mesh
    from tiled_gridpull.mesh import Mesh

    def rect(x1, z):
        v = np.array([[0, 0, z], [x1, 0, z], [x1, 10, z], [0, 10, z]], dtype=np.float64)
        return Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))

    write_mesh(rect(10, 0.0), tmp_path / "gt.ply")
    write_mesh(rect(4, 0.0), tmp_path / "mesh.ply")
    gx, gy = np.meshgrid(np.arange(0.0, 4.01, 0.5), np.arange(0.0, 10.01, 0.1))
    # a millimetre of scatter: an exactly planar cloud is refused as input
    z = np.random.default_rng(0).uniform(-1e-3, 1e-3, gx.size)
    np.save(tmp_path / "pts.npy", np.stack([gx.ravel(), gy.ravel(), z], axis=1))
    args = ["evaluate", str(tmp_path / "mesh.ply"), str(tmp_path / "gt.ply"), "--json", "--samples", "50000"]
    code, text, _ = run([*args, "--observed", str(tmp_path / "pts.npy"), "--footprint", "1", "3"], capsys)
    assert code == 0
    res = json.loads(text)
    # the mesh covers x <= 4 (plus what lies within 0.1 of its edge); the footprint within 1 m is x <= 5
    assert res["footprint_recall@1"] == pytest.approx(4.1 / 5, abs=0.01)
    assert res["footprint_recall@3"] == pytest.approx(4.1 / 7, abs=0.01)
    assert res["footprint_precision@0.1"] == 1.0 and res["footprint_tau"] == 0.1
    # --normalize scales the radii with the meshes, and the names stay in the user's units
    code, text, _ = run([*args, "--observed", str(tmp_path / "pts.npy"), "--footprint", "1", "--normalize"], capsys)
    assert code == 0 and json.loads(text)["footprint_recall@1"] == pytest.approx(4.1 / 5, abs=0.01)
    code, _, err = run([*args, "--footprint", "1"], capsys)
    assert code == 2 and "--footprint needs --observed" in err
    code, _, err = run([*args, "--observed", str(tmp_path / "pts.npy"), "--footprint", "0"], capsys)
    assert code == 2 and "positive" in err


def test_evaluate_table_leads_with_the_exact_figures(tmp_path, capsys):
    """The table opens on the exact figures; the sample-to-sample ones come last under a header that gives their
    floor (on the demo street they had led, 12x the exact Chamfer-L1). ``--json`` keeps every key."""
    from tiled_gridpull.io import write_mesh
    from tiled_gridpull.mesh import Mesh

    v = np.array([[0, 0, 0], [40, 0, 0], [40, 40, 0], [0, 40, 0]], dtype=np.float64)
    write_mesh(Mesh(v, np.array([[0, 1, 2], [0, 2, 3]])), tmp_path / "gt.ply")
    write_mesh(Mesh(v + [0, 0, 0.01], np.array([[0, 1, 2], [0, 2, 3]])), tmp_path / "mesh.ply")
    args = ["evaluate", str(tmp_path / "mesh.ply"), str(tmp_path / "gt.ply"), "--samples", "20000",
            "--thresholds", "0.05"]
    code, text, _ = run(args, capsys)
    assert code == 0
    lines = text.splitlines()
    assert lines[0].startswith("exact:")
    assert lines[1].split()[0].endswith("_exact") or "_exact@" in lines[1].split()[0]
    values = {ln.split()[0]: ln.split()[1] for ln in lines if ln.startswith("  ")}
    assert float(values["chamfer_l1_exact"]) == pytest.approx(0.01, rel=1e-3)
    sampled = next(i for i, ln in enumerate(lines) if ln.startswith("sampled:"))
    order = [ln.split()[0] for ln in lines if ln.startswith("  ")]
    assert lines.index(next(ln for ln in lines if ln.split()[0] == "chamfer_l1")) > sampled
    assert order.index("chamfer_l1_exact") < order.index("watertight") < order.index("chamfer_l1")
    floor = float(values["chamfer_l1_floor"])
    assert f"chamfer_l1 {floor:.3g}" in lines[sampled] and floor == pytest.approx(0.5 * 40 / np.sqrt(20000), rel=1e-5)
    assert float(values["chamfer_l1"]) > 5 * float(values["chamfer_l1_exact"])  # why they must not lead
    code, text, _ = run([*args, "--json"], capsys)
    assert code == 0
    assert set(json.loads(text)) == set(values)
    code, text, _ = run([*args, "--no-exact"], capsys)
    assert code == 0 and text.splitlines()[0] == "samples and mesh" and "_exact" not in text


def test_one_shape_mode_says_it_compiles_the_kernels_its_cache_lacks(sphere_xyz, tmp_path, capsys, monkeypatch,
                                                                    caplog):
    """Before the progress bar (which sat at 0 while numba compiled): the kernels one-shape mode calls, not those
    of tiled jobs only."""
    from tiled_gridpull.kernels import warmup

    asked, compiled = [], []

    def cold(names=None):
        asked.append(list(names))
        return ["losses.query_losses", "step.tv_adam_step"]

    monkeypatch.setattr(warmup, "cold_kernels", cold)
    monkeypatch.setattr("tiled_gridpull.tiled_job.cold_kernels", cold)
    monkeypatch.setattr(warmup, "compile_kernels", compiled.append)
    import logging

    with caplog.at_level(logging.INFO, logger="tiled_gridpull"):
        code, _, err = run(["reconstruct", str(sphere_xyz), "-o", str(tmp_path / "m.ply"), "--resolution", "32",
                            "--iterations", "30", "--set", "coarse_iterations=30"], capsys)
    assert code == 0, err
    said = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("compiling 2 numba kernels, once per installation") for m in said), said
    assert any(m.startswith("compiled the kernels in") for m in said)
    assert compiled == [["losses.query_losses", "step.tv_adam_step"]]
    assert asked and not set(asked[0]) & set(warmup.TILED_ONLY) and "losses.query_losses" in asked[0]


@pytest.mark.parametrize("tiled", [False, True])
def test_absurd_ply_offset_is_exit_3_one_line_in_both_modes(tmp_path, capsys, sphere_xyz, tiled):
    """Our own PLY's ``comment offset 1e308 0 0``: one-shape mode failed with "internal error: LinAlgError"
    (exit 1), tiled mode with a numpy message about the lattice origin (exit 2)."""
    pts = np.loadtxt(sphere_xyz)
    src = tmp_path / "ours.ply"
    src.write_text("ply\nformat ascii 1.0\ncomment generator tiled_gridpull 0.1.0\ncomment offset 1e308 0 0\n"
                   f"element vertex {len(pts)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
                   + "".join(f"{a} {b} {c}\n" for a, b, c in pts))
    out = tmp_path / "out.ply"
    mode = ["--voxel-size", "0.1"] if tiled else ["--resolution", "32"]
    code, _, err = run(["reconstruct", str(src), "-o", str(out), "-q", *mode], capsys)
    assert code == 3, err
    _one_error_line(err)
    assert "offset '1e308 0 0'" in err and str(src) in err
    assert not out.exists() and not out.with_suffix(".json").exists()


def test_planar_patch_is_meshed_in_udf_mode_and_refused_in_signed_mode(tmp_path, capsys):
    """``--mode udf`` takes an exactly planar patch (an open flat surface); the signed mode refuses it."""
    from tiled_gridpull.io import read_mesh

    rng = np.random.default_rng(0)
    src = tmp_path / "plane.xyz"
    np.savetxt(src, np.c_[rng.random((3000, 2)) * 4.0, np.full(3000, 1.5)])
    out = tmp_path / "out.ply"
    fast = ["--resolution", "32", "--iterations", "100", "--set", "coarse_iterations=100"]
    code, _, err = run(["reconstruct", str(src), "-o", str(out), "-q", *fast], capsys)
    assert code == 3 and "coplanar" in err and not out.exists()
    _one_error_line(err)
    code, _, err = run(["reconstruct", str(src), "-o", str(out), "-q", "--mode", "udf", *fast], capsys)
    assert code == 0, err
    mesh = read_mesh(out)
    assert mesh.n_faces > 0 and np.abs(mesh.vertices[:, 2] - 1.5).max() < 0.05


@pytest.mark.parametrize("dry_run", [False, True])
def test_collinear_points_are_refused_in_tiled_mode_too(tmp_path, capsys, dry_run):
    """Tiled mode meshed points on a line (a mesh made from a line) that one-shape mode refuses: the same rule
    (tiled_gridpull.cloud.degeneracy) now refuses them before anything is written, from the dry run too."""
    t = np.linspace(0.0, 10.0, 3000)
    src = tmp_path / "line.xyz"
    np.savetxt(src, np.c_[t, 2 * t + 1, 3 * t - 2])
    out = tmp_path / "out.ply"
    code, _, err = run(["reconstruct", str(src), "-o", str(out), "-q", "--voxel-size", "0.25",
                        *(["--dry-run"] if dry_run else [])], capsys)
    assert code == 3, err
    _one_error_line(err)
    assert "collinear" in err and str(src) in err
    assert not out.exists() and not out.with_suffix(".json").exists()
    assert not (out.with_suffix(".job") / "manifest.json").exists()


@pytest.mark.parametrize("args", [["street", "--frames", "0"], ["street", "--frames", "16", "--layout", "grid"],
                                  ["sphere", "--frames", "4"]])
def test_sample_frames_is_checked_before_anything_is_written(tmp_path, capsys, args):
    out = tmp_path / "s"
    code, _, err = run(["sample", args[0], str(out), *args[1:]], capsys)
    assert code == 2 and "--frames" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
