"""One tiled driver, two executors: the serial one and the Dask one write the same mesh, metadata, summaries and
report, and either reuses the tile results the other (or itself) left in a job directory."""

import json
import shutil

import numpy as np
import pytest
from conftest import terrain

from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import MemoryBudgetError
from tiled_gridpull.tiled_job import reconstruct_scene
from tiled_gridpull.tiling import TilingConfig

SOLVER = SolverConfig(m2=8, refine_m2=6, coarse_iterations=100, iterations=100, queries=20000)
TILING = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, trim_distance=2.0)


@pytest.fixture(scope="module")
def serial_job(tmp_path_factory):
    d = tmp_path_factory.mktemp("serial")
    np.save(d / "g.npy", terrain(12.8, 40, seed=3))
    lines = []
    mesh = reconstruct_scene([str(d / "g.npy")], d / "serial.ply", TILING, SOLVER, d / "job", log=lines.append)
    return d, mesh, lines


@pytest.fixture(scope="module")
def dask_job(serial_job):
    from tiled_gridpull.pipeline.job import JobOptions, run_job

    d, _, _ = serial_job
    mesh = run_job([str(d / "g.npy")], d / "dask.ply", TILING, SOLVER, d / "dask_job",
                   JobOptions(workers=1, progress=False))
    return mesh


def _summaries(job) -> list[str]:
    return sorted(p.name for p in (job / "summaries").iterdir())


def test_serial_job_records_every_tile_step(serial_job):
    d, mesh, lines = serial_job
    n = mesh.metadata["tiles"]["with_points"]
    assert n == 4 and mesh.metadata["tiles"]["solved"] == 4
    assert _summaries(d / "job") == sorted([f"solve_tile_{i}_{j}_0.json" for i in (0, 1) for j in (0, 1)]
                                           + [f"mesh_tile_{i}_{j}_0.json" for i in (0, 1) for j in (0, 1)])
    assert mesh.metadata["reused"] == {"partition": False, "solves": 0, "meshes": 0}
    assert mesh.metadata["engine"] == {"scheduler": "serial", "workers": 1}
    assert set(mesh.metadata["timings_s"]) == {"partition", "solve_and_mesh", "merge", "total"}
    assert len(lines) == 4 and all(": solved (" in line for line in lines)


def test_serial_rerun_reuses_every_tile_result(serial_job):
    d, first, _ = serial_job
    again = reconstruct_scene([str(d / "g.npy")], d / "again.ply", TILING, SOLVER, d / "job")
    assert again.metadata["reused"] == {"partition": True, "solves": 4, "meshes": 4}
    assert (d / "again.ply").read_bytes() == (d / "serial.ply").read_bytes()
    # a changed solver setting recomputes the solves (and so the meshes) instead of reusing them (in a copy of
    # the job directory: the other tests read the original)
    shutil.copytree(d / "job", d / "job_other")
    other = reconstruct_scene([str(d / "g.npy")], d / "other.ply", TILING,
                              SolverConfig(m2=8, refine_m2=6, coarse_iterations=100, iterations=101, queries=20000),
                              d / "job_other")
    assert other.metadata["reused"] == {"partition": True, "solves": 0, "meshes": 0}


def test_executors_write_the_same_mesh_metadata_and_report(serial_job, dask_job):
    d, serial, _ = serial_job
    assert (d / "dask.ply").read_bytes() == (d / "serial.ply").read_bytes()
    s_side = json.loads((d / "serial.json").read_text())
    d_side = json.loads((d / "dask.json").read_text())
    assert set(s_side) == set(d_side)
    assert set(s_side["timings_s"]) == set(d_side["timings_s"])
    assert [sorted(t) for t in s_side["tile_summaries"]] == [sorted(t) for t in d_side["tile_summaries"]]
    assert [sorted(t) for t in s_side["mesh_summaries"]] == [sorted(t) for t in d_side["mesh_summaries"]]
    for key in ("tiles", "mesh", "lattice", "tiling", "config", "input"):
        assert s_side[key] == d_side[key], key
    assert [t["field_sha256"] for t in s_side["tile_summaries"]] == [t["field_sha256"] for t in
                                                                    d_side["tile_summaries"]]
    assert _summaries(d / "job") == _summaries(d / "dask_job")
    s_rep = json.loads((d / "job" / "report.json").read_text())
    d_rep = json.loads((d / "dask_job" / "report.json").read_text())
    assert set(s_rep) == set(d_rep) and set(s_rep["totals"]) == set(d_rep["totals"])
    assert [sorted(r) for r in s_rep["tiles"]] == [sorted(r) for r in d_rep["tiles"]]


def test_dask_reuses_what_the_serial_executor_left(serial_job, dask_job):
    from tiled_gridpull.pipeline.job import JobOptions, run_job

    d, _, _ = serial_job
    shutil.copytree(d / "job", d / "handover")
    # results are reused by content key: a job directory moved elsewhere is still reused
    mesh = run_job([str(d / "g.npy")], d / "handover.ply", TILING, SOLVER, d / "handover",
                   JobOptions(workers=1, progress=False))
    assert mesh.metadata["reused"]["solves"] == 4 and mesh.metadata["reused"]["meshes"] == 4
    assert (d / "handover.ply").read_bytes() == (d / "serial.ply").read_bytes()


def test_serial_job_refuses_a_tile_over_the_memory_budget_before_partitioning(tmp_path):
    np.save(tmp_path / "g.npy", terrain(6.4, 40))
    with pytest.raises(MemoryBudgetError, match="would exceed --max-memory"):
        reconstruct_scene([str(tmp_path / "g.npy")], tmp_path / "g.ply", TILING, SOLVER, tmp_path / "job",
                          max_memory=1 << 20)
    assert not (tmp_path / "job" / "manifest.json").exists()
    assert not (tmp_path / "job" / "points").exists()


def test_a_tiled_job_denoises_its_points_and_the_surface_gets_closer(tmp_path):
    """Noisy ground (5 cm of Gaussian noise, 20 cm cells) reconstructed with and without denoising: every tile
    records what it moved and dropped, the sidecar the settings, and the denoised mesh lies closer to the true
    surface."""
    rng = np.random.default_rng(5)
    clean = terrain(12.8, 40, seed=5)
    np.save(tmp_path / "g.npy", clean + rng.normal(scale=0.05, size=clean.shape))
    tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=3.2, trim_distance=2.0)
    solver = SOLVER.replace(denoise=2, denoise_neighbors=32, denoise_radius=1.5)

    def height_error(mesh) -> float:
        v = mesh.vertices - np.array([500000.0, 4000000.0, 50.0])
        inner = np.all((v[:, :2] > 1.0) & (v[:, :2] < 11.8), axis=1)
        truth = 0.4 * np.sin(v[inner, 0] / 2.0) * np.cos(v[inner, 1] / 3.0)
        return float(np.abs(v[inner, 2] - truth).mean())

    plain = reconstruct_scene([str(tmp_path / "g.npy")], tmp_path / "plain.ply", tiling,
                              SOLVER.replace(noise_auto=False), tmp_path / "j0")
    denoised = reconstruct_scene([str(tmp_path / "g.npy")], tmp_path / "denoised.ply", tiling, solver,
                                 tmp_path / "j1")
    assert plain.metadata["noise_treatment"] == {"auto": False, "chosen": None, "reason": "noise_auto is off"}
    assert denoised.metadata["noise_treatment"]["reason"] == "given: denoise 2"
    assert denoised.metadata["noise_treatment"]["given"] == ["denoise"]
    assert denoised.metadata["config"]["noise"]["denoise_passes"] == 2
    assert denoised.metadata["config"]["noise"]["denoise_radius"] == 1.5
    assert denoised.metadata["tiling"]["halo"] == 6 and plain.metadata["tiling"]["halo"] == 0
    assert len(denoised.metadata["tile_summaries"]) == denoised.metadata["tiles"]["solved"] > 1
    for summary in denoised.metadata["tile_summaries"]:
        record = summary["denoise"]
        # 2 passes of 0.3 m reach 1.2 m: the tile read a halo of points that wide, so it moved every one of its own
        assert record["points"] == summary["points_used"] == summary["points"] > 0
        assert record["dropped_near_faces"] == 0
        assert record["halo_points"] > 0 and 0 < record["time_s"] < summary["time_s"]
        assert 0 < record["moved_median_m"] < 0.05 and record["moved_max_m"] <= 0.6 + 1e-9
    assert height_error(denoised) < 0.8 * height_error(plain)
    # a notebook's view of a tile shows its block's points, and the halo's on request
    from tiled_gridpull.jobview import JobView

    view = JobView(tmp_path / "j1")
    name = view.busiest_tile()
    spec = view.specs[name]
    block = view.tile_points(name)
    around = view.tile_points(name, halo=True)
    assert len(around) == spec.n_points > len(block) == spec.block_points
    assert spec.halo_points == spec.n_points - spec.block_points > 0
    assert np.all(block >= spec.block.low_corner - 1e-9) and np.all(block <= spec.block.high_corner + 1e-9)
    # the denoising job's point files hold exact float64 offsets; a job without denoising keeps float32
    from pathlib import Path

    assert spec.exact_offsets and Path(spec.points_path).stat().st_size == 24 * spec.n_points
    plain_spec = JobView(tmp_path / "j0").specs[name]
    assert not plain_spec.exact_offsets and Path(plain_spec.points_path).stat().st_size == 12 * plain_spec.n_points
    # the job report's sample reads either kind of file (it read float64 offsets as float32 pairs once)
    from pykdtree.kdtree import KDTree

    from tiled_gridpull.jobdir import sample_job_points

    noisy = np.load(tmp_path / "g.npy")
    for job in ("j0", "j1"):
        sample = sample_job_points(tmp_path / job, max_points=10 * len(noisy))  # all: each point once
        assert len(sample) == len(noisy)
        dist, _ = KDTree(noisy).query(sample)
        assert dist.max() < 1e-5  # float32 offsets from a tile's corner: micrometres


def test_noise_auto_denoises_a_noisy_scan_and_leaves_a_clean_one(tmp_path, serial_job):
    """With the defaults (``noise_auto``), the noisy ground of the test above gets the denoising passes, measured
    once on the scan's first points, so the mesh is the one the explicit setting gives; the clean terrain of the
    serial job is measured and left alone. The sidecar says what was measured and chosen, and the dry run shows it."""
    from pipeline.dryrun import format_plan, plan_job
    from tiled_gridpull.noise import SCAN_NOISY_CELLS

    _, clean, _ = serial_job
    record = clean.metadata["noise_treatment"]
    assert record["auto"] and record["chosen"] is None and record["settings"] == {}
    assert record["estimate"]["q25_cells"] < 0.2 * SCAN_NOISY_CELLS
    assert clean.metadata["tiling"]["halo"] == 0

    rng = np.random.default_rng(5)
    ground = terrain(12.8, 40, seed=5)
    np.save(tmp_path / "g.npy", ground + rng.normal(scale=0.05, size=ground.shape))
    tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=3.2, trim_distance=2.0)
    params = SOLVER.replace(denoise_neighbors=32, denoise_radius=1.5)  # the passes' parameters, as scene.yaml's
    auto = reconstruct_scene([str(tmp_path / "g.npy")], tmp_path / "auto.ply", tiling, params, tmp_path / "j0")
    given = reconstruct_scene([str(tmp_path / "g.npy")], tmp_path / "given.ply", tiling,
                              params.replace(denoise=2), tmp_path / "j1")
    record = auto.metadata["noise_treatment"]
    assert record["chosen"] == "denoise" and record["settings"] == {"denoise": 2}
    assert record["estimate"]["q25_cells"] > SCAN_NOISY_CELLS
    assert record["estimate"]["points"] == len(ground) and record["estimate"]["radius_cells"] == 1.5
    assert auto.metadata["config"]["noise"]["denoise_passes"] == 2 and auto.metadata["tiling"]["halo"] == 6
    assert np.array_equal(auto.vertices, given.vertices) and np.array_equal(auto.faces, given.faces)
    shown = format_plan(plan_job([str(tmp_path / "g.npy")], tiling, params, tmp_path / "dry"))
    assert "noise:    denoising, scatter across planes (25th percentile)" in shown
    assert "a halo of 6 cells read for denoising" in shown
    shown = format_plan(plan_job([str(tmp_path / "g.npy")], tiling, params.replace(denoise=1), tmp_path / "dry"))
    assert "noise:    given: denoise 1\n" in shown and "a halo of 2 cells read for denoising" in shown


def test_compile_ahead_says_what_it_compiles_and_nothing_on_a_warm_cache(caplog):
    """A cold cache is said on screen, with the estimate for the processes compiling at once, before the
    kernels are compiled; a warm one (or one numba's internals keep us from reading: None) says nothing."""
    import logging

    from tiled_gridpull.kernels.warmup import estimate_seconds
    from tiled_gridpull.tiled_job import compile_ahead

    cold = ["losses.query_losses", "step.tv_adam_step", "mc.count_triangles"]
    calls = []
    with caplog.at_level(logging.INFO, logger="tiled_gridpull"):
        assert compile_ahead(calls.append, 2, cold=cold) == cold
    assert calls == [cold]
    said = [r.getMessage() for r in caplog.records]
    assert said[0] == ("compiling 3 numba kernels, once per installation (numba caches them): about "
                       f"{estimate_seconds(cold, 2):.0f} s") and said[1].startswith("compiled the kernels in ")
    assert estimate_seconds(cold, 2) < estimate_seconds(cold, 1)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="tiled_gridpull"):
        assert compile_ahead(calls.append, 2, cold=[]) == []
    assert calls == [cold] and not caplog.records
