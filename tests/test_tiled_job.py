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
