"""A tiled reconstruction as a Dask job: the same steps as :func:`tiled_gridpull.scene.reconstruct_scene`, with
tiles solved and meshed as tasks on a cluster.

* Tasks carry small :class:`~tiled_gridpull.tile.TileSpec` descriptions (paths, bounds) and settings, never
  arrays; each writes its result to the job directory and returns a small summary.
* A tile's mesh task depends on the solve tasks of itself and its 26 neighbours (the blend needs their fields).
* By default a :class:`distributed.LocalCluster` sized to the machine runs the job: one thread per worker
  process, and numba/OpenMP threads per worker = cores / workers (numba's default threading layer aborts when
  parallel kernels run from several threads of one process). ``scheduler=ADDRESS`` runs the very same graph
  on an existing cluster.
* Failed tasks are retried (a worker that dies costs only its tiles in flight); a tile that fails for a data
  reason is reported by name and the rest of the mesh is still produced.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import TileFailedError
from tiled_gridpull.mesh import Mesh
from tiled_gridpull.scene import (JobPaths, finish_job, job_metadata, key_reference, neighbors_of, plan_centre,
                                  prepare_job)
from tiled_gridpull.tile import TileSpec, TilingConfig, check_compatible

log = logging.getLogger("tiled_gridpull")

__all__ = ["JobOptions", "run_job", "make_client"]


@dataclass(frozen=True)
class JobOptions:
    """How a job runs (not what it computes).

    Attributes
    ----------
    workers : int, optional
        Worker processes of the local cluster (default: one per core, capped by the number of tiles).
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:8786``); overrides ``workers``.
    retries : int
        Times a task is retried after a failure (e.g. its worker died).
    fail_fast : bool
        Stop at the first tile that fails for a data reason instead of producing the rest of the mesh.
    float32 : bool
        Write float32 vertices with a recorded offset.
    progress : bool
        Show a progress bar with an ETA.
    """

    workers: int | None = None
    scheduler: str | None = None
    retries: int = 2
    fail_fast: bool = False
    float32: bool = False
    progress: bool = True
    extra: dict = field(default_factory=dict)


def _threads_for(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(1, workers))


def make_client(options: JobOptions, n_tiles: int):
    """A Dask client: connected to ``options.scheduler``, or to a new LocalCluster sized to the machine."""
    from distributed import Client, LocalCluster

    if options.scheduler:
        return Client(options.scheduler, timeout="30s"), None
    if not log.isEnabledFor(logging.DEBUG):
        # the scheduler of a LocalCluster lives in this process: keep its chatter out of the user's terminal
        logging.getLogger("distributed").setLevel(logging.ERROR)
    cores = os.cpu_count() or 1
    workers = options.workers or max(1, min(cores, n_tiles))
    threads = _threads_for(workers)
    env = {"NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads), "OMP_WAIT_POLICY": "PASSIVE",
           "TILED_GRIDPULL_THREADS": str(threads)}
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                           silence_logs=logging.ERROR, env=env)
    return Client(cluster), cluster


def _configure_worker_threads() -> None:
    """Inside a task: keep numba's kernels safe and sized for this worker."""
    import numba

    try:
        from distributed import get_worker

        nthreads = get_worker().state.nthreads
    except (ImportError, ValueError, AttributeError):
        nthreads = 1
    if nthreads > 1 and numba.config.THREADING_LAYER == "default":
        # several task threads per process: only a thread-safe layer may run parallel kernels
        numba.config.THREADING_LAYER = "threadsafe"
    want = int(os.environ.get("TILED_GRIDPULL_THREADS", "0") or 0)
    if want > 0:
        numba.set_num_threads(min(want, numba.config.NUMBA_NUM_THREADS))


def solve_task(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str, centre) -> dict:
    """Dask task: solve one tile (see :func:`tiled_gridpull.tile.solve_tile`)."""
    from tiled_gridpull.tile import solve_tile

    _configure_worker_threads()
    out = solve_tile(spec, tiling, solver, field_path, centre=centre)
    out["worker"] = _worker_address()
    return out


def _worker_address() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return "local"


def mesh_task(spec: TileSpec, own: dict, neighbor_specs: list, neighbor_summaries: list, tiling: TilingConfig,
              key_ref, field_paths: dict, piece_path: str) -> dict:
    """Dask task: blend with the solved neighbours and mesh the tile's core."""
    from tiled_gridpull.stitch import mesh_tile

    if own.get("status") != "solved":
        return {"tile": spec.name, "status": "not solved", "faces": 0}
    _configure_worker_threads()
    nb = [(s, field_paths[s.name]) for s, summ in zip(neighbor_specs, neighbor_summaries)
          if summ.get("status") == "solved"]
    out = mesh_tile(spec, nb, tiling, key_ref, field_paths[spec.name], piece_path)
    out["status"] = "meshed"
    return out


def run_job(inputs: list[str], output: str | Path, tiling: TilingConfig, solver: SolverConfig, work_dir: str | Path,
            options: JobOptions = JobOptions(), *, frames=None) -> Mesh:
    """Tiled reconstruction on Dask; writes ``output`` and its sidecar, returns the welded mesh."""
    from distributed import as_completed

    t0 = time.perf_counter()
    check_compatible(tiling, solver)
    paths = JobPaths(work_dir)
    plan, specs, scan = prepare_job(inputs, tiling, paths, frames=frames)
    t_part = time.perf_counter()
    log.info("partitioned %d points into %d tiles (%d planned) in %.1f s", scan["points"], len(specs),
             int(plan.tile_range[0] * plan.tile_range[1] * plan.tile_range[2]), t_part - t0)
    client, cluster = make_client(options, len(specs))
    try:
        by_index = {s.index: s for s in specs}
        field_paths = {s.name: str(paths.field(s)) for s in specs}
        centre = plan_centre(plan)
        solve_futs = {s.index: client.submit(solve_task, s, tiling, solver, field_paths[s.name], centre,
                                             key=f"solve-{s.name}", retries=options.retries, pure=False)
                      for s in specs}
        ref = key_reference(plan)
        mesh_futs = {}
        for s in specs:
            nbs = neighbors_of(s, by_index)
            mesh_futs[s.index] = client.submit(
                mesh_task, s, solve_futs[s.index], nbs, [solve_futs[n.index] for n in nbs], tiling, ref,
                field_paths, str(paths.piece(s)), key=f"mesh-{s.name}", retries=options.retries, pure=False)
        solve_summaries, mesh_summaries = _collect(solve_futs, mesh_futs, options, as_completed)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    t_mesh = time.perf_counter()
    failed = [s for s in solve_summaries if s["status"] == "failed"]
    if failed and options.fail_fast:
        raise TileFailedError(f"{len(failed)} tile(s) failed: " + "; ".join(f"{s['tile']}: {s.get('reason')}"
                                                                          for s in failed[:5]))
    meta = job_metadata(plan, tiling, solver, scan, solve_summaries, mesh_summaries,
                        {"partition": t_part - t0, "solve_and_mesh": t_mesh - t_part})
    meta["engine"] = {"scheduler": options.scheduler or "LocalCluster", "workers": options.workers}
    pieces = [paths.piece(by_index[tuple(m["index"])]) for m in mesh_summaries if m.get("status") == "meshed"]
    mesh = finish_job(pieces, output, meta, float32=options.float32)
    mesh.metadata["timings_s"]["merge"] = time.perf_counter() - t_mesh
    mesh.metadata["timings_s"]["total"] = time.perf_counter() - t0
    from tiled_gridpull.io import write_sidecar

    write_sidecar(output, mesh.metadata)
    return mesh


def _collect(solve_futs: dict, mesh_futs: dict, options: JobOptions, as_completed) -> tuple[list, list]:
    """Wait for every task with a progress bar (tiles done / total, ETA); results in tile order."""
    from tqdm import tqdm

    total = len(solve_futs) + len(mesh_futs)
    bar = tqdm(total=total, unit="task", desc="tiles", disable=not options.progress, dynamic_ncols=True)
    results: dict = {}
    kinds = {f.key: ("solve", idx) for idx, f in solve_futs.items()}
    kinds.update({f.key: ("mesh", idx) for idx, f in mesh_futs.items()})
    try:
        for fut in as_completed(list(solve_futs.values()) + list(mesh_futs.values())):
            kind, idx = kinds[fut.key]
            res = fut.result()
            res["index"] = list(idx)
            results[(kind, idx)] = res
            bar.update(1)
            if kind == "solve":
                bar.set_postfix_str(f"{res['tile']} {res['status']}", refresh=False)
                if res["status"] == "failed":
                    log.warning("%s failed: %s", res["tile"], res.get("reason"))
                    if options.fail_fast:
                        raise TileFailedError(f"{res['tile']} failed: {res.get('reason')}")
    finally:
        bar.close()
    solve = [results[("solve", i)] for i in sorted(solve_futs)]
    mesh = [results[("mesh", i)] for i in sorted(mesh_futs)]
    return solve, mesh
