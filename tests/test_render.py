"""Off-screen pictures (meshes, clouds, error maps, tile layout), the job report and the render/report commands."""

import json
import logging
import re

import numpy as np
import pytest

from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.errors import ConfigError, InputError
from tiled_gridpull.images import save_png
from tiled_gridpull.io import read_sidecar, write_mesh
from tiled_gridpull.mesh import Mesh
from tiled_gridpull.jobview import load_job
from tiled_gridpull.render import render_mesh, render_meshes_image
from tiled_gridpull.report import build_report, format_report_table, read_report, write_report
from tiled_gridpull.tile_layout import render_tile_layout_image
from tiled_gridpull.synthetic import sample_shape, sphere
from conftest import terrain


def _png(path):
    from PIL import Image

    with Image.open(path) as im:
        assert im.format == "PNG"
        return np.asarray(im.convert("RGB"))


def _not_blank(img, min_std=15.0):
    """A picture, not an empty canvas: pixel spread, and a real share of pixels differing from the background."""
    assert img.std() > min_std, img.std()
    background = np.all(img > 245, axis=2)
    assert 0.03 < 1 - background.mean() < 0.97, 1 - background.mean()


def _colourful(img):
    """Share of pixels in the colour map's hues (green/blue above red), absent from the beige mesh colour."""
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return float(np.mean((g > r + 30) | (b > r + 30)))


@pytest.fixture(scope="module")
def ball():
    return sphere(subdivisions=3)


def test_render_mesh_writes_png_of_requested_size(tmp_path, ball):
    out = tmp_path / "ball.png"
    info = render_mesh(ball, out, size=(320, 200))
    img = _png(out)
    assert img.shape == (200, 320, 3) and info["size"] == [320, 200]
    _not_blank(img)
    assert _colourful(img) < 0.01  # plain mesh colour
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write left no temporary file


def test_error_colour_map_and_cloud_overlay(tmp_path, ball):
    gt = Mesh(ball.vertices * 1.04, ball.faces)  # every vertex 0.02 from the ground truth
    bumpy = Mesh(ball.vertices * (1 + 0.03 * np.sin(8 * ball.vertices[:, :1])), ball.faces)
    info = render_mesh(bumpy, tmp_path / "err.png", size=(300, 300), gt=gt)
    e = info["errors"]
    assert 0.0 <= e["median"] <= e["p95"] <= e["max"] < 0.1 and e["mean"] > 0.005
    img = _png(tmp_path / "err.png")
    _not_blank(img)
    assert _colourful(img) > 0.05
    pts, _ = sample_shape(ball, 3000, seed=0)
    cloud = render_meshes_image([], cloud=pts * 1.01, size=(240, 240), point_size=3)
    red = (cloud[..., 0].astype(int) > cloud[..., 1].astype(int) + 80)
    assert red.mean() > 0.02


def test_georeferenced_mesh_renders_like_one_at_the_origin(ball):
    far = Mesh(ball.vertices * 20 + [500000.0, 4000000.0, 100.0], ball.faces)
    near = Mesh(ball.vertices * 20, ball.faces)
    a = render_meshes_image([far], size=(200, 160)).astype(int)
    b = render_meshes_image([near], size=(200, 160)).astype(int)
    assert np.abs(a - b).mean() < 1.0


def test_render_bad_arguments(tmp_path, ball):
    with pytest.raises(ConfigError, match="PNG"):
        render_mesh(ball, tmp_path / "x.jpg")
    with pytest.raises(ConfigError, match="between 16 and 8192"):
        render_mesh(ball, tmp_path / "x.png", size=(0, 100))
    with pytest.raises(ConfigError, match="view"):
        render_meshes_image([ball], view="below")
    with pytest.raises(InputError, match="nothing to render"):
        render_meshes_image([Mesh(np.zeros((0, 3)), np.zeros((0, 3)))])
    assert not list(tmp_path.iterdir())


def _one_error_line(err):
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err


def test_cli_render(tmp_path, capsys, caplog, ball):
    write_mesh(ball, tmp_path / "ball.ply")
    write_mesh(Mesh(ball.vertices * 1.02, ball.faces), tmp_path / "gt.ply")
    pts, _ = sample_shape(ball, 2000, seed=1)
    np.savetxt(tmp_path / "pts.xyz", pts)
    out = tmp_path / "view.png"
    caplog.set_level(logging.INFO, logger="tiled_gridpull")
    code = main(["render", str(tmp_path / "ball.ply"), "-o", str(out), "--cloud", str(tmp_path / "pts.xyz"),
                 "--gt", str(tmp_path / "gt.ply"), "--size", "200", "150", "--view", "top"])
    assert code == 0, capsys.readouterr().err
    mean = float(re.search(r"distance to \S+: mean ([0-9.e-]+)", caplog.text).group(1))
    assert mean == pytest.approx(0.01, rel=0.05)  # vertices 2% of radius 0.5 inside the GT
    img = _png(out)
    assert img.shape == (150, 200, 3)
    _not_blank(img)

    missing = tmp_path / "nope.png"
    assert main(["render", str(tmp_path / "missing.ply"), "-o", str(missing)]) == 3
    _one_error_line(capsys.readouterr().err)
    assert main(["render", str(tmp_path / "ball.ply"), "-o", str(missing), "--gt", str(tmp_path / "no.ply")]) == 3
    _one_error_line(capsys.readouterr().err)
    assert main(["render", str(tmp_path / "ball.ply"), "-o", str(tmp_path / "v.jpg")]) == 2
    _one_error_line(capsys.readouterr().err)
    assert main(["render", str(tmp_path / "ball.ply"), "-o", str(missing), "--size", "10", "5000"]) == 2
    _one_error_line(capsys.readouterr().err)
    assert not missing.exists()


# ----------------------------------------------------------------------------------------------------- job report


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """A 2 x 2-tile job through the command line and Dask (one local worker)."""
    d = tmp_path_factory.mktemp("job")
    pts = terrain(12.8, 40)
    np.save(d / "ground.npy", pts)
    out = d / "ground.ply"
    code = main(["reconstruct", str(d / "ground.npy"), "-o", str(out), "--voxel-size", "0.2", "--tile-size", "6.4",
                 "--overlap", "1.6", "--set", "m2=8", "--set", "refine_m2=6", "--set", "coarse_iterations=100",
                 "--set", "iterations=100", "--set", "queries=20000", "--workers", "1", "-q",
                 "--tile-meshes", str(d / "tiles")])
    assert code == 0
    return d, out, out.with_suffix(".job"), pts


def test_tile_meshes_add_up_to_the_welded_mesh(job):
    from tiled_gridpull.io import read_mesh

    d, out, _, _ = job
    pieces = [read_mesh(p) for p in sorted((d / "tiles").glob("*.ply"))]
    whole = read_mesh(out)
    assert len(pieces) == 4
    assert sum(p.n_faces for p in pieces) == whole.n_faces
    # pieces share their border vertices: the welded mesh has fewer vertices than the pieces together
    assert whole.n_vertices < sum(p.n_vertices for p in pieces)
    allv = np.concatenate([p.vertices for p in pieces])
    assert np.abs(np.sort(np.unique(allv, axis=0), axis=0) - np.sort(whole.vertices, axis=0)).max() < 1e-9


def test_job_writes_report_and_picture(job):
    d, out, job_dir, pts = job
    rep = read_report(job_dir)
    side = read_sidecar(out)
    assert rep["output"] == str(out.resolve()) and rep["job_dir"] == str(job_dir.resolve())
    assert rep["config"] == side["config"] and rep["lattice"] == side["lattice"]
    assert rep["tiling"]["tile_cells"] == 32
    names = [t["tile"] for t in rep["tiles"]]
    assert names == [s["tile"] for s in side["tile_summaries"]] and len(names) == 4
    for t in rep["tiles"]:
        assert t["status"] == "solved"
        assert t["points"] > 0 and t["solve_time_s"] > 0 and t["mesh_time_s"] > 0 and t["peak_rss_mb"] > 50
        assert t["faces"] > 0 and t["worker"].startswith("tcp://")
        first, last = t["loss_first"], t["loss_last"]
        assert first["iteration"] < last["iteration"] and first["level"] <= last["level"]
        assert np.isfinite(first["pull"]) and np.isfinite(last["pull"])
        assert last["cell_size"] == pytest.approx(0.2)  # the last record is at the finest level
        assert last["pull_world"] == pytest.approx(last["pull"] * last["cell_size"])
        assert 0 < last["pull_world"] < 0.2  # queries end up within a cell of the points
    tot = rep["totals"]
    assert tot["tiles_solved"] == tot["tiles_with_points"] == 4 and tot["tiles_failed"] == 0
    assert tot["faces"] == side["mesh"]["n_faces"] == sum(t["faces"] for t in rep["tiles"])
    assert tot["points"] == len(pts) <= tot["points_in_tiles"]
    assert tot["solve_time_s"] == pytest.approx(sum(t["solve_time_s"] for t in rep["tiles"]))
    # the tile cores tile the input: every point lies in exactly one core
    lo = np.array([t["core_bounds"][0] for t in rep["tiles"]])
    hi = np.array([t["core_bounds"][1] for t in rep["tiles"]])
    inside = np.all((pts[:, None] >= lo[None]) & (pts[:, None] < hi[None]), axis=2)
    assert np.all(inside.sum(axis=1) == 1)
    assert rep["picture"] == "tiles.png"
    img = _png(job_dir / "tiles.png")
    assert img.shape == (700, 1400, 3)
    _not_blank(img)


def test_cli_report_table_lists_every_tile(job, capsys):
    _, _, job_dir, _ = job
    assert main(["report", str(job_dir)]) == 0
    table = capsys.readouterr().out
    rep = read_report(job_dir)
    rows = {ln.split()[0]: ln.split() for ln in table.splitlines() if ln.startswith(("tile_", "total"))}
    assert set(rows) == {t["tile"] for t in rep["tiles"]} | {"total"}
    for t in rep["tiles"]:
        cols = rows[t["tile"]]
        assert cols[1] == "solved" and int(cols[2]) == t["points"] and int(cols[-1]) == t["faces"]
    assert rows["total"][1] == "4/4" and int(rows["total"][-1]) == rep["totals"]["faces"]
    assert main(["report", str(job_dir / "report.json"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == rep


def test_cli_report_errors(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 3
    err = capsys.readouterr().err
    _one_error_line(err)
    assert "report.json" in err
    assert main(["report", str(tmp_path / "missing")]) == 3
    _one_error_line(capsys.readouterr().err)
    (tmp_path / "report.json").write_text('{"something": "else"}')
    assert main(["report", str(tmp_path)]) == 3
    assert "not a tiled_gridpull job report" in capsys.readouterr().err


def test_a_picture_that_fails_never_fails_the_report(job, tmp_path, monkeypatch, caplog):
    import tiled_gridpull.tile_layout as tile_layout

    def broken(*a, **k):
        raise RuntimeError("no canvas")

    monkeypatch.setattr(tile_layout, "render_tile_layout", broken)
    meta = read_sidecar(job[1])
    path = write_report(tmp_path, meta)
    rep = read_report(path)
    assert rep["picture"] is None and len(rep["tiles"]) == 4
    assert not (tmp_path / "tiles.png").exists()
    assert "no canvas" in caplog.text
    assert not [ln for ln in format_report_table(rep).splitlines() if ln.startswith("picture:")]


def test_layout_picture_marks_failed_and_stacked_tiles(job):
    rep = build_report(read_sidecar(job[1]))
    rep["tiles"][0].update(status="failed", reason="boom", solve_time_s=None, mesh_time_s=None)
    extra = dict(rep["tiles"][1], index=[rep["tiles"][1]["index"][0], rep["tiles"][1]["index"][1], 1])
    rep["tiles"].append(extra)  # a second layer along z: drawn in its column
    img = render_tile_layout_image(rep, size=(600, 300))
    assert img.shape == (300, 600, 3)
    _not_blank(img)
    hatched_red = (img[..., 0] > 200) & (img[..., 1] < 80) & (img[..., 2] < 80)
    assert hatched_red.sum() > 50
    text = format_report_table(rep)
    assert "tile_0_0_0 failed: boom" in text


def test_job_view_slices_pieces_and_seams(job):
    _, _, job_dir, _ = job
    view = load_job(job_dir)
    assert list(view.specs) == [t["tile"] for t in view.report["tiles"]]
    name = "tile_0_0_0"
    vals, extent, z = view.field_slice(name, axis=1)
    band = vals[np.isfinite(vals)]
    assert band.size > 100 and band.min() < 0 < band.max()  # the band straddles the surface
    assert extent[0] < extent[1] and extent[2] < extent[3]
    assert view.neighbours(name) == ["tile_0_1_0", "tile_1_0_0", "tile_1_1_0"]
    assert view.shared_vertices(name, "tile_1_0_0") > 10
    pieces = [view.tile_mesh(n) for n in view.specs]
    welded = view.welded(list(view.specs))
    assert welded.n_faces == sum(p.n_faces for p in pieces)
    assert welded.topology.boundary_edges < sum(p.topology.boundary_edges for p in pieces)
    pts = view.tile_points(name)
    lo, hi = view.core_bounds(name)
    assert len(pts) == view.specs[name].n_points and np.all(pts.min(0) >= lo - 1.6 - 1e-6)
    with pytest.raises(InputError, match="no tile"):
        view.tile_mesh("tile_9_9_9")


def test_save_png_roundtrip(tmp_path):
    img = (np.arange(48 * 32 * 3) % 251).astype(np.uint8).reshape(32, 48, 3)
    save_png(img, tmp_path / "a.png")
    assert np.array_equal(_png(tmp_path / "a.png"), img)
