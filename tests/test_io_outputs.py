"""Output paths checked before any work: an input is never replaced, nor a file this tool did not write."""

import json
import os

import numpy as np
import pytest

from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.io import check_outputs, write_mesh, written_by_us
from tiled_gridpull.mesh import Mesh
from tiled_gridpull.synthetic import sample_shape, sphere

QUICK = ["-q", "--resolution", "32", "--iterations", "100", "--set", "coarse_iterations=100"]


def run(args, capsys):
    code = main(args)
    err = capsys.readouterr().err
    return code, err


def _one_line(err, needle):
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], err


@pytest.fixture
def cloud_ply(tmp_path):
    """A point cloud stored as PLY: the format a careless ``-o`` can name."""
    pts, _ = sample_shape(sphere(), 3000, seed=0)
    p = tmp_path / "scan.ply"
    write_mesh(Mesh(pts, np.zeros((0, 3), np.int64)), p)
    return p


@pytest.mark.parametrize("tiled", [False, True])
def test_output_equal_to_input_is_refused_and_input_kept(tmp_path, capsys, cloud_ply, tiled):
    before = cloud_ply.read_bytes()
    extra = ["--voxel-size", "0.05"] if tiled else QUICK
    code, err = run(["reconstruct", str(cloud_ply), "-o", str(cloud_ply), *extra], capsys)
    assert code == 2
    _one_line(err, "refusing to overwrite an input")
    assert cloud_ply.read_bytes() == before
    assert not cloud_ply.with_suffix(".json").exists() and not cloud_ply.with_suffix(".job").exists()


def test_output_through_a_symlink_to_the_input_is_refused(tmp_path, capsys, cloud_ply):
    link = tmp_path / "link.ply"
    link.symlink_to(cloud_ply)
    before = cloud_ply.read_bytes()
    code, err = run(["reconstruct", str(cloud_ply), "-o", str(link), *QUICK], capsys)
    assert code == 2
    _one_line(err, "refusing to overwrite an input")
    assert cloud_ply.read_bytes() == before


def test_sidecar_never_replaces_a_json_this_tool_did_not_write(tmp_path, capsys, cloud_ply):
    # `sample street D` writes D/street.json; `reconstruct ... -o D/street.ply` would put its sidecar there
    foreign = tmp_path / "scan_mesh.json"
    foreign.write_text(json.dumps({"generator": "tiled_gridpull.synthetic.street", "n_points": 3}))
    before = foreign.read_bytes()
    out = tmp_path / "scan_mesh.ply"
    code, err = run(["reconstruct", str(cloud_ply), "-o", str(out), *QUICK], capsys)
    assert code == 2
    _one_line(err, "--overwrite")
    assert foreign.read_bytes() == before and not out.exists()
    # told to, it replaces the file; a rerun over its own outputs needs no flag
    code, err = run(["reconstruct", str(cloud_ply), "-o", str(out), "--overwrite", *QUICK], capsys)
    assert code == 0, err
    assert json.loads(foreign.read_text())["generator"].startswith("tiled_gridpull ")
    code, err = run(["reconstruct", str(cloud_ply), "-o", str(out), *QUICK], capsys)
    assert code == 0, err


def test_mesh_not_written_by_this_tool_is_kept(tmp_path, capsys, cloud_ply):
    other = tmp_path / "truth.ply"
    write_mesh(sphere(), other)  # a synthetic ground truth: generator tiled_gridpull.synthetic.sphere
    assert not written_by_us(other)
    before = other.read_bytes()
    code, err = run(["reconstruct", str(cloud_ply), "-o", str(other), *QUICK], capsys)
    assert code == 2
    _one_line(err, "was not written by tiled-gridpull")
    assert other.read_bytes() == before


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_written_by_us_reads_the_marker(tmp_path, suffix):
    m = sphere()
    m.metadata["generator"] = "tiled_gridpull 9.9"
    p = tmp_path / f"m{suffix}"
    write_mesh(m, p)
    assert written_by_us(p)
    p.write_bytes(p.read_bytes().replace(b"tiled_gridpull 9.9", b"someone_else 9.9"))
    assert not written_by_us(p)
    assert not written_by_us(tmp_path / "missing.ply")


def test_written_by_us_reads_the_marker_of_a_picture(tmp_path):
    """A PNG the tool draws (a job's tiles.png) carries the generator in its Software text; another PNG, even
    one with the words in its pixels' bytes, does not."""
    from tiled_gridpull.images import save_png

    img = np.zeros((20, 30, 3), np.uint8)
    save_png(img, tmp_path / "ours.png")
    assert written_by_us(tmp_path / "ours.png")
    pytest.importorskip("PIL").Image.fromarray(img).save(tmp_path / "theirs.png")
    assert not written_by_us(tmp_path / "theirs.png")
    (tmp_path / "text.png").write_bytes(b"tEXtSoftware\0tiled_gridpull 1")
    assert not written_by_us(tmp_path / "text.png")


def test_directories_where_files_go_and_files_where_directories_go(tmp_path, capsys, cloud_ply):
    (tmp_path / "out.ply").mkdir()
    code, err = run(["reconstruct", str(cloud_ply), "-o", str(tmp_path / "out.ply"), *QUICK], capsys)
    assert code == 2
    _one_line(err, "is a directory")
    f = tmp_path / "afile"
    f.write_text("x")
    for opt in ("--tile-meshes", "--work-dir"):
        code, err = run(["reconstruct", str(cloud_ply), "-o", str(tmp_path / "m.ply"), "--voxel-size", "0.05",
                         opt, str(f)], capsys)
        assert code == 2
        _one_line(err, "is a file, not a directory")
    assert f.read_text() == "x"


def test_work_directory_holding_an_input_is_refused(tmp_path, cloud_ply):
    from tiled_gridpull.errors import ConfigError

    with pytest.raises(ConfigError, match="holds the input"):
        check_outputs([cloud_ply], tmp_path / "sub" / "m.ply", work_dir=tmp_path)
    tile = tmp_path / "tiles" / "tile_0_0_0.ply"
    tile.parent.mkdir()
    tile.write_bytes(cloud_ply.read_bytes())
    with pytest.raises(ConfigError, match="holds the input"):
        check_outputs([tile], tmp_path / "m.ply", tile_meshes=tile.parent)
    # other names beside the tile meshes are safe: tile meshes are only ever tile_*.ply
    check_outputs([cloud_ply], tmp_path / "m.ply", tile_meshes=tmp_path)


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root writes into read-only directories")
def test_read_only_output_directory_is_refused_before_work(tmp_path, capsys, cloud_ply):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        code, err = run(["reconstruct", str(cloud_ply), "-o", str(ro / "m.ply"), *QUICK], capsys)
    finally:
        ro.chmod(0o755)
    assert code == 2
    _one_line(err, "not writable")


def test_no_tile_with_enough_points_is_refused_before_solving(tmp_path, capsys):
    pts = np.random.default_rng(0).uniform(0, 30, size=(60, 3))
    src = tmp_path / "sparse.npy"
    np.save(src, pts)
    out = tmp_path / "m.ply"
    code, err = run(["reconstruct", str(src), "-o", str(out), "--voxel-size", "0.1", "-q"], capsys)
    assert code == 3
    _one_line(err, "no tile holds min_points (100) points, the largest holds")
    assert not out.exists() and not out.with_suffix(".json").exists()


@pytest.mark.parametrize("case", ["duplicates", "too_few_to_solve"])
def test_job_with_no_solved_tile_writes_nothing(tmp_path, case):
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.errors import InputError, TileFailedError
    from tiled_gridpull.tiled_job import reconstruct_scene
    from tiled_gridpull.tiling import TilingConfig

    rng = np.random.default_rng(1)
    if case == "duplicates":
        # 150 rows, 3 distinct points: above min_points when planned, 3 once duplicates are dropped -> skipped
        pts, min_points, error = np.repeat(rng.uniform(1, 2, size=(3, 3)), 50, axis=0), 100, InputError
    else:
        # 6 points pass min_points 5 but a solve needs 10: the tile fails for a data reason
        pts, min_points, error = rng.uniform(1, 2, size=(6, 3)), 5, TileFailedError
    src = tmp_path / "p.npy"
    np.save(src, pts)
    out = tmp_path / "m.ply"
    tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, min_points=min_points)
    with pytest.raises(error, match="no tile was solved, nothing written"):
        reconstruct_scene([str(src)], out, tiling, SolverConfig(m2=6, refine_m2=6, iterations=20,
                                                                coarse_iterations=20), tmp_path / "job")
    assert not out.exists() and not out.with_suffix(".json").exists()


@pytest.mark.parametrize("stray", [(0.0, 0.0, 0.0), (2e20, 0.0, 0.0)])
def test_lattice_beyond_the_edge_keys_is_refused_when_planning(tmp_path, capsys, stray):
    rng = np.random.default_rng(2)
    pts = np.vstack([rng.uniform(0, 10, size=(2000, 3)) + [500000.0, 4000000.0, 50.0], [stray]])
    src = tmp_path / "utm.npy"
    np.save(src, pts)
    out = tmp_path / "m.ply"
    for extra in ([], ["--dry-run"]):
        code, err = run(["reconstruct", str(src), "-o", str(out), "--voxel-size", "0.1", "-q", *extra], capsys)
        assert code == 3
        _one_line(err, "more than the lattice can hold")
        assert "stray points" in err
    assert not out.exists() and not (tmp_path / "m.job" / "fields").exists()


def test_a_crs_with_non_ascii_names_and_several_lines_goes_into_one_header_line(tmp_path):
    """The CRS rides in the PLY header as one ASCII comment; a pretty-printed WKT with an accented name used to
    stop the job at its very end (UnicodeEncodeError writing the header)."""
    from tiled_gridpull.io import read_mesh, write_mesh
    from tiled_gridpull.mesh import Mesh

    m = Mesh(np.eye(3), np.array([[0, 1, 2]]))
    m.metadata["crs"] = 'PROJCS["RGF93 / Lambert-93 (Réseau)",\n  GEOGCS["RGF93"],\n  UNIT["metre",1]]'
    p = write_mesh(m, tmp_path / "m.ply")
    header = p.read_bytes().split(b"end_header")[0].decode("ascii")
    crs_lines = [ln for ln in header.splitlines() if ln.startswith("comment crs ")]
    assert crs_lines == ['comment crs PROJCS["RGF93 / Lambert-93 (R?seau)", GEOGCS["RGF93"], UNIT["metre",1]]']
    np.testing.assert_array_equal(read_mesh(p).vertices, m.vertices)
