"""Quality presets (``--quality draft | standard | fine``, config key ``quality``): standard is the config as given,
bit for bit; draft and fine change the schedule; --set wins over a preset; an auto cell scales with it; the dry
run estimates every preset."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import terrain
from tiled_gridpull.config import QUALITIES, QUALITY_CELL_SCALE, QUALITY_PRESETS, SolverConfig, quality_settings
from tiled_gridpull.errors import ConfigError

SCENE = "configs/scene.yaml"


def _resolve(*argv: str):
    from tiled_gridpull.pipeline.cli import build_parser, resolve_settings

    args = build_parser().parse_args(["reconstruct", "x.laz", "-o", "y.ply", *argv])
    solver, tiling = resolve_settings(args)
    return solver, tiling, args.quality_chosen


def _repo_file(name: str) -> str:
    from pathlib import Path

    return str(Path(__file__).resolve().parents[1] / name)


def test_standard_is_the_config_as_given_and_unknown_names_are_refused():
    assert quality_settings(None) == {} and quality_settings("standard") == {}
    assert set(QUALITIES) == set(QUALITY_PRESETS) == set(QUALITY_CELL_SCALE)
    for bad in ("Draft", "fast", 3):
        with pytest.raises(ConfigError, match="quality must be one of draft, standard, fine"):
            quality_settings(bad)
    # every preset is a valid set of settings
    for q in QUALITIES:
        SolverConfig(**quality_settings(q))


def test_cli_standard_equals_no_quality_and_draft_replaces_the_file_but_not_set(tmp_path):
    scene = _repo_file(SCENE)
    plain, tiling, chosen = _resolve("--config", scene, "--voxel-size", "0.2")
    assert chosen is None
    std, tiling_std, chosen = _resolve("--config", scene, "--voxel-size", "0.2", "--quality", "standard")
    assert chosen == "standard" and std == plain and tiling_std == tiling
    # the key in a config file, and through --set, mean the same
    cfg = tmp_path / "q.yaml"
    cfg.write_text(open(scene).read() + "quality: standard\n")
    assert _resolve("--config", str(cfg), "--voxel-size", "0.2")[0] == plain
    assert _resolve("--config", scene, "--voxel-size", "0.2", "--set", "quality=standard")[0] == plain
    draft, _, chosen = _resolve("--config", scene, "--voxel-size", "0.2", "--quality", "draft")
    assert chosen == "draft" and draft != plain
    for name, value in QUALITY_PRESETS["draft"].items():
        assert draft.get(name) == value, name  # the preset replaces what configs/scene.yaml says
    # a setting the file names and the preset does not stays the file's
    assert draft.coarse.m2 == plain.coarse.m2 == 14
    # --set wins over the preset, whatever the order on the line; the last quality named wins
    its = _resolve("--set", "iterations=77", "--config", scene, "--voxel-size", "0.2", "--quality", "draft")[0]
    assert its.schedule.finest_iterations == 77
    cfg.write_text(open(scene).read() + "quality: draft\n")
    assert _resolve("--config", str(cfg), "--voxel-size", "0.2")[0] == draft
    assert _resolve("--config", str(cfg), "--voxel-size", "0.2", "--quality", "standard")[0] == plain


def test_quality_is_refused_in_one_shape_mode_and_bad_names_in_one_line():
    with pytest.raises(ConfigError, match="quality draft applies to tiled mode"):
        _resolve("--quality", "draft")
    with pytest.raises(ConfigError, match="quality must be one of"):
        _resolve("--voxel-size", "0.2", "--set", "quality=best")
    with pytest.raises(SystemExit):
        _resolve("--voxel-size", "0.2", "--quality", "best")


def test_an_auto_cell_scales_with_the_preset_and_a_given_cell_is_kept():
    from tiled_gridpull.spacing import Spacing
    from tiled_gridpull.tiling import auto_cell_size

    sp = Spacing(median=0.124, area_median=0.365, points=1000, measured=1000)  # a quarter of the grid of streets
    assert auto_cell_size(sp) == 0.2
    assert auto_cell_size(sp, QUALITY_CELL_SCALE["draft"]) == 0.25
    assert auto_cell_size(sp, QUALITY_CELL_SCALE["fine"]) == 0.1
    # an explicit cell is not touched by the preset
    assert _resolve("--voxel-size", "0.3", "--quality", "draft")[1].voxel_size == 0.3


def test_thin_per_cell_keeps_at_most_cap_points_in_each_cell():
    from tiled_gridpull.solver import thin_per_cell

    rng = np.random.default_rng(0)
    P = np.concatenate([rng.uniform(0, 1, (50, 3)), rng.uniform(3, 4, (2, 3))])  # 50 in one cell, 2 in another
    kept, keep = thin_per_cell(P, 0, cap=4)
    cells, counts = np.unique(np.floor(kept).astype(int), axis=0, return_counts=True)
    assert len(kept) == 6 and counts.max() == 4 and len(cells) == 2
    assert np.all(np.diff(keep) > 0) and np.array_equal(kept, P[keep])
    assert np.array_equal(thin_per_cell(P, 1, cap=4)[1], thin_per_cell(P, 1, cap=4)[1])  # seeded


def _job(tmp_path, name: str, *argv: str):
    """A one-tile job in this process with the CLI's settings; (vertices, faces, tile summary)."""
    from tiled_gridpull.tiled_job import reconstruct_scene

    src = tmp_path / "ground.npy"
    if not src.exists():
        pts = terrain(12.8, 30, seed=2)
        dense = terrain(3.0, 3000, seed=3)  # a patch far denser than its 0.2 m cells
        np.save(src, np.concatenate([pts, dense]))
    solver, tiling, _ = _resolve("--config", _repo_file(SCENE), "--voxel-size", "0.2", *argv)
    mesh = reconstruct_scene([str(src)], None, tiling, solver, tmp_path / f"{name}.job")
    return mesh.vertices, mesh.faces, mesh.metadata


def test_standard_meshes_are_bit_for_bit_those_without_a_quality_and_draft_differs(tmp_path):
    v0, f0, _ = _job(tmp_path, "none")
    v1, f1, _ = _job(tmp_path, "standard", "--quality", "standard")
    assert np.array_equal(v0, v1) and np.array_equal(f0, f1)
    v2, f2, meta = _job(tmp_path, "draft", "--quality", "draft")
    assert len(f2) > 0.5 * len(f0)  # still the ground
    assert v2.shape != v0.shape or not np.array_equal(v0, v2)
    if QUALITY_PRESETS["draft"].get("points_per_cell"):
        assert meta["tile_summaries"][0].get("points_thinned", 0) > 0


def test_dry_run_estimates_every_preset(tmp_path, capsys):
    from tiled_gridpull.pipeline.cli import main

    np.save(tmp_path / "ground.npy", terrain(25.6, 40, seed=4))
    code = main(["reconstruct", str(tmp_path / "ground.npy"), "-o", str(tmp_path / "m.ply"), "--config",
                 _repo_file(SCENE), "--voxel-size", "auto", "--quality", "draft", "--dry-run"])
    out = capsys.readouterr().out
    assert code == 0
    line = next(ln for ln in out.splitlines() if ln.startswith("quality:"))
    assert "draft (this run)" in line and "standard" in line and "fine" in line
    assert "at cell" in line  # auto: the other presets take other cells
    assert not (tmp_path / "m.job").exists() or not any((tmp_path / "m.job").iterdir())


def test_dry_run_preset_times_follow_the_schedule(tmp_path):
    from tiled_gridpull.pipeline.cli import build_parser, resolve_settings
    from tiled_gridpull.pipeline.dryrun import plan_job
    from tiled_gridpull.tiling import TilingConfig

    np.save(tmp_path / "g.npy", terrain(25.6, 40, seed=5))
    presets = {}
    for q in QUALITIES:
        args = build_parser().parse_args(["reconstruct", "x", "-o", "y.ply", "--config", _repo_file(SCENE),
                                          "--voxel-size", "0.2", "--quality", q])
        presets[q] = resolve_settings(args)
    solver, tiling = presets["standard"]
    info = plan_job([str(tmp_path / "g.npy")], tiling, solver, tmp_path / "j", presets=presets)
    t = {q: p["wall_seconds"] for q, p in info["presets"].items()}
    assert t["standard"] == pytest.approx(info["time"]["wall_seconds"])
    assert t["draft"] < t["standard"] <= t["fine"]
    assert isinstance(tiling, TilingConfig) and all(p["cell_size"] == 0.2 for p in info["presets"].values())


def test_resume_keys_of_jobs_that_keep_every_point_are_unchanged():
    # points_per_cell joins a tile's resume key only when set: jobs of earlier versions' settings keep theirs
    plain = SolverConfig().solve_settings(sphere_init=False)
    assert "points_per_cell" not in plain
    assert SolverConfig(points_per_cell=8).solve_settings(sphere_init=False)["points_per_cell"] == 8
    with pytest.raises(ConfigError, match="points_per_cell must be >= 0"):
        SolverConfig(points_per_cell=-1)


def test_time_estimate_follows_the_thinned_points():
    from types import SimpleNamespace

    from tiled_gridpull.memory import level_points, tile_time

    dense = SimpleNamespace(n_points=250_000, occupied_bricks=100)
    assert level_points(dense, 2, 3) == 250_000
    assert level_points(dense, 2, 3, cap=8) == 8 * 100 * 96  # 1.5 x 8^2 finest cells per brick
    assert level_points(dense, 2, 3, cap=10_000) == 250_000  # fewer points than the cap
    bricks = [100, 400, 1600]
    thinned = SolverConfig(queries_per_point=4, points_per_cell=8)
    assert tile_time(dense, bricks, thinned) < tile_time(dense, bricks, SolverConfig(queries_per_point=4))
