"""Overhead of the job's Dask graph with a no-op solve and mesh: the pipeline's own cost per tile.

The graph is the one ``run_job`` runs (:func:`tiled_gridpull.pipeline.job.run_tiles`): a solve task per tile
and a mesh task per tile that takes the solve summaries of the tile and its neighbours, with the arguments the
job's tasks carry (:func:`tiled_gridpull.tiled_job.task_arguments`: real ``TileSpec``, ``TilingConfig`` and
``SolverConfig`` objects, paths), submitted as a sliding window of at most ``DEFAULT_WINDOW`` tasks, on a
LocalCluster of 2 single-threaded worker processes. Results append to ``benchmarks/results/dask.jsonl``.

Usage: ``python -m benchmarks.dask_overhead 1000 10000 100000``
"""

from __future__ import annotations

import json
import math
import sys
import time

from benchmarks.common import REPO, append_jsonl, machine, peak_rss_mb

RESULTS = REPO / "benchmarks" / "results" / "dask.jsonl"


def noop_solve(spec, *args):
    return {"tile": spec.name, "status": "solved"}


def noop_mesh(spec, own, nbs, nb_summaries, *args):
    return {"tile": spec.name, "status": "meshed", "neighbours": len(nb_summaries)}


def make_specs(n: int):
    from tiled_gridpull.lattice import Lattice
    from tiled_gridpull.tile_plan import TileSpec

    side = math.ceil(math.sqrt(n))
    block = Lattice(origin=(500000.0, 4000000.0, 100.0), cell_size=0.1, shape=(321, 321, 321))
    specs = []
    for i in range(side):
        for j in range(side):
            if len(specs) == n:
                break
            specs.append(TileSpec(index=(i, j, 0), core_lo=(0, 0, 0), core_hi=(256, 256, 256), block=block,
                                  n_points=100_000, points_path=f"/job/points/tile_{i}_{j}_0.npy"))
    return specs


def run(n: int, workers: int = 2) -> dict:
    from distributed import Client, LocalCluster

    import numpy as np

    from tiled_gridpull.pipeline.job import DEFAULT_WINDOW, run_tiles
    from tiled_gridpull.tiled_job import task_arguments
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.jobdir import JobPaths
    from tiled_gridpull.tiling import TilingConfig

    specs = make_specs(n)
    solve_args, mesh_args = task_arguments(specs, TilingConfig(), SolverConfig(), JobPaths("/job"),
                                           (500000.0, 4000000.0, 100.0), np.zeros(3, np.int64))
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    client = Client(cluster)
    try:
        client.run(lambda: None)  # workers up before the clock starts
        t0 = time.perf_counter()
        meshed = sum(1 for kind, _, r in run_tiles(client, specs, noop_solve, solve_args, noop_mesh, mesh_args, 2,
                                                   window=DEFAULT_WINDOW)
                     if kind == "mesh" and r["status"] == "meshed")
        t2 = time.perf_counter()
        assert meshed == n
    finally:
        client.close()
        cluster.close()
    return {"tiles": n, "tasks": 2 * n, "workers": workers, "window": DEFAULT_WINDOW,
            "variant": "window; summaries as arguments, batched submits, job-shaped arguments", "total_s": t2 - t0,
            "per_tile_ms": 1e3 * (t2 - t0) / n, "driver_peak_rss_mb": peak_rss_mb()}


def main() -> None:
    sizes = [int(a) for a in sys.argv[1:]] or [1000, 10000]
    for n in sizes:
        row = {"suite": "dask_noop", "date": time.strftime("%Y-%m-%d %H:%M"), **run(n), "machine": machine()}
        print(json.dumps({k: v for k, v in row.items() if k != "machine"}), flush=True)
        append_jsonl(RESULTS, row)


if __name__ == "__main__":
    main()
