"""The Dask engine: a real scheduler and workers on loopback, and worker memory bounded by the tile."""

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tiled_gridpull.config import SolverConfig
from tiled_gridpull.tile import TilingConfig
from conftest import terrain

BIN = Path(sys.executable).parent
SOLVER = SolverConfig(m2=8, refine_m2=6, coarse_iterations=100, iterations=100, queries=20000)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def cluster(tmp_path):
    port = _free_port()
    env = dict(os.environ, TILED_GRIDPULL_THREADS="1", OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    procs = [subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)]
    address = f"tcp://127.0.0.1:{port}"
    try:
        time.sleep(2.0)
        for i in range(2):
            procs.append(subprocess.Popen([str(BIN / "dask"), "worker", address, "--nthreads", "1",
                                           "--no-dashboard", "--name", f"w{i}", "--local-directory",
                                           str(tmp_path / f"w{i}")],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env))
        from distributed import Client

        with Client(address, timeout="30s") as c:
            c.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


def test_job_on_separately_started_scheduler_and_workers(tmp_path, cluster):
    pts = terrain(19.2, 40)
    np.save(tmp_path / "ground.npy", pts)
    out = tmp_path / "ground.ply"
    from pipeline.cli import main

    code = main(["reconstruct", str(tmp_path / "ground.npy"), "-o", str(out), "--voxel-size", "0.2",
                 "--tile-size", "6.4", "--overlap", "1.6", "--set", "m2=8", "--set", "refine_m2=6", "--set", "coarse_iterations=100",
                 "--set", "iterations=100", "--set", "queries=20000", "--scheduler", cluster, "-q"])
    assert code == 0
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["engine"]["scheduler"] == cluster
    workers = {s["worker"] for s in side["tile_summaries"]}
    assert len(workers) == 2, workers  # both workers solved tiles
    assert side["tiles"]["solved"] == side["tiles"]["with_points"] >= 9
    assert side["mesh"]["nonmanifold_edges"] == 0 and side["mesh"]["n_faces"] > 1000


def test_worker_memory_does_not_grow_with_tile_count(tmp_path):
    from pipeline.job import JobOptions, run_job

    peaks = {}
    for extent in (12.8, 25.6):  # 2 x 2 and 4 x 4 tiles, same density
        d = tmp_path / f"e{extent}"
        d.mkdir()
        np.save(d / "g.npy", terrain(extent, 60, seed=1))
        tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, trim_distance=2.0)
        mesh = run_job([str(d / "g.npy")], d / "g.ply", tiling, SOLVER, d / "job",
                       JobOptions(workers=1, progress=False))
        tiles = mesh.metadata["tile_summaries"]
        peaks[len(tiles)] = max(s["peak_rss_mb"] for s in tiles)
    small, large = sorted(peaks)
    assert small == 4 and large == 16
    assert peaks[large] < 1.25 * peaks[small], peaks
