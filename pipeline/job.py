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
* Every field and mesh piece is recorded with a key of what produced it (:mod:`tiled_gridpull.resume`): running
  the same job again in the same job directory reuses the partition and every tile result whose inputs and
  settings are unchanged, and recomputes only the rest.
* ``max_memory`` refuses, before anything is solved, a job whose tiles are estimated
  (:mod:`tiled_gridpull.memory`) to need more than that much memory on a worker.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
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
    tile_meshes : str, optional
        Directory to also write one PLY per tile into.
    max_memory : int, optional
        Bytes one worker may use for one tile; the job is refused up front if a tile's estimate exceeds it.
    """

    workers: int | None = None
    scheduler: str | None = None
    tile_meshes: str | None = None
    retries: int = 2
    fail_fast: bool = False
    float32: bool = False
    progress: bool = True
    extra: dict = field(default_factory=dict)
    max_memory: int | None = None


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
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
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


def solve_task(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str, centre,
               summary_path: str | None = None) -> dict:
    """Dask task: solve one tile (see :func:`tiled_gridpull.tile.solve_tile`), or reuse its recorded result."""
    from tiled_gridpull.resume import solve_tile_resumable
    from tiled_gridpull.tile import solve_tile

    _configure_worker_threads()
    if summary_path is None:
        out = solve_tile(spec, tiling, solver, field_path, centre=centre)
    else:
        out = solve_tile_resumable(spec, tiling, solver, field_path, summary_path, centre,
                                   before_solve=lambda: _test_hold(spec.name))
    if not out.get("reused"):
        out["worker"] = _worker_address()
    return out


def _test_hold(tile: str) -> None:
    """Test hook: with ``TILED_GRIDPULL_TEST_HOLD=DIR:SECONDS``, the first attempt at solving each tile writes
    ``DIR/<tile>.<pid>`` and sleeps, so a test can kill the worker process mid-task. Unset in normal use."""
    spec = os.environ.get("TILED_GRIDPULL_TEST_HOLD")
    if not spec:
        return
    where, _, seconds = spec.rpartition(":")
    marks = Path(where)
    if any(marks.glob(f"{tile}.*")):
        return  # a retry: do not hold again
    (marks / f"{tile}.{os.getpid()}").write_text(_worker_address())
    time.sleep(float(seconds))


def _worker_address() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return "local"


def mesh_task(spec: TileSpec, own: dict, neighbor_specs: list, neighbor_summaries: list, tiling: TilingConfig,
              key_ref, field_paths: dict, piece_path: str, summary_path: str | None = None) -> dict:
    """Dask task: blend with the solved neighbours and mesh the tile's core (or reuse its recorded piece)."""
    from tiled_gridpull.resume import mesh_tile_resumable
    from tiled_gridpull.stitch import mesh_tile

    if own.get("status") != "solved":
        return {"tile": spec.name, "status": "not solved", "faces": 0}
    _configure_worker_threads()
    solved = [(s, summ) for s, summ in zip(neighbor_specs, neighbor_summaries) if summ.get("status") == "solved"]
    if summary_path is None:
        out = mesh_tile(spec, [(s, field_paths[s.name]) for s, _ in solved], tiling, key_ref,
                        field_paths[spec.name], piece_path)
        out["status"] = "meshed"
        return out
    return mesh_tile_resumable(spec, own, [(s, summ, field_paths[s.name]) for s, summ in solved], tiling, key_ref,
                               field_paths[spec.name], piece_path, summary_path)


def run_job(inputs: list[str], output: str | Path, tiling: TilingConfig, solver: SolverConfig, work_dir: str | Path,
            options: JobOptions = JobOptions(), *, frames=None) -> Mesh:
    """Tiled reconstruction on Dask; writes ``output`` and its sidecar, returns the welded mesh."""
    t0 = time.perf_counter()
    check_compatible(tiling, solver)
    paths = JobPaths(work_dir)
    plan, specs, scan = prepare_job(inputs, tiling, paths, frames=frames)
    t_part = time.perf_counter()
    log.info("%s %d points into %d tiles (%d planned) in %.1f s",
             "reused the partition of" if scan.get("partition_reused") else "partitioned", scan["points"],
             len(specs), int(plan.tile_range[0] * plan.tile_range[1] * plan.tile_range[2]), t_part - t0)
    if options.max_memory is not None:
        check_memory(specs, tiling, solver, options.max_memory)
    with _deferred_interrupt() as interrupted:
        solve_summaries, mesh_summaries = _run_tasks(specs, tiling, solver, paths, plan, options, interrupted)
    t_mesh = time.perf_counter()
    by_index = {s.index: s for s in specs}
    n_solve = sum(1 for s in solve_summaries if s.get("reused"))
    n_mesh = sum(1 for m in mesh_summaries if m.get("reused"))
    log.info("reused %d of %d tile solves and %d of %d mesh pieces from %s", n_solve, len(solve_summaries), n_mesh,
             sum(1 for m in mesh_summaries if m.get("status") == "meshed"), paths.root)
    failed = [s for s in solve_summaries if s["status"] == "failed"]
    if failed and options.fail_fast:
        raise TileFailedError(f"{len(failed)} tile(s) failed: " + "; ".join(f"{s['tile']}: {s.get('reason')}"
                                                                          for s in failed[:5]))
    meta = job_metadata(plan, tiling, solver, scan, solve_summaries, mesh_summaries,
                        {"partition": t_part - t0, "solve_and_mesh": t_mesh - t_part})
    meta["engine"] = {"scheduler": options.scheduler or "LocalCluster", "workers": options.workers}
    meta["reused"] = {"partition": bool(scan.get("partition_reused")), "solves": n_solve, "meshes": n_mesh}
    pieces = [paths.piece(by_index[tuple(m["index"])]) for m in mesh_summaries if m.get("status") == "meshed"]
    mesh = finish_job(pieces, output, meta, float32=options.float32, tile_meshes=options.tile_meshes)
    mesh.metadata["timings_s"]["merge"] = time.perf_counter() - t_mesh
    mesh.metadata["timings_s"]["total"] = time.perf_counter() - t0
    from tiled_gridpull.io import write_sidecar

    write_sidecar(output, mesh.metadata)
    from tiled_gridpull.report import write_report

    write_report(paths.root, mesh.metadata, output=output)  # report.json + tiles.png in the job directory
    return mesh


@contextlib.contextmanager
def _deferred_interrupt():
    """Turn Ctrl-C into a flag that the task loop checks, instead of an exception raised wherever it lands.

    A KeyboardInterrupt raised inside one of distributed's blocking calls (a result fetch, ``client.close``)
    leaves its event loop half-way through a callback, which then logs a traceback from distributed's
    internals; checked between tasks, the interrupt unwinds through our own code and closes the cluster
    cleanly. A second Ctrl-C interrupts at once. Off the main thread (signals cannot be handled there) the
    event never fires and Ctrl-C behaves as usual.
    """
    interrupted = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield interrupted
        return

    def handler(signum, frame):
        if interrupted.is_set():
            raise KeyboardInterrupt
        interrupted.set()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield interrupted
    finally:
        signal.signal(signal.SIGINT, previous)
    if interrupted.is_set():
        raise KeyboardInterrupt


def _run_tasks(specs: list[TileSpec], tiling: TilingConfig, solver: SolverConfig, paths: JobPaths, plan,
               options: JobOptions, interrupted: threading.Event) -> tuple[list, list]:
    """Start the cluster, submit every tile's solve and mesh task, collect their summaries, close the cluster."""
    client, cluster = make_client(options, len(specs))
    if client.dashboard_link:
        log.info("Dask dashboard: %s", client.dashboard_link)
    try:
        field_paths = {s.name: str(paths.field(s)) for s in specs}
        centre = plan_centre(plan)
        ref = key_reference(plan)
        solve_futs, mesh_futs = submit_tiles(
            client, specs, solve_task,
            lambda s: (tiling, solver, field_paths[s.name], centre, str(paths.summary("solve", s))),
            mesh_task,
            lambda s: (tiling, ref, field_paths, str(paths.piece(s)), str(paths.summary("mesh", s))),
            options.retries)
        return _collect(solve_futs, mesh_futs, options, interrupted)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def submit_tiles(client, specs: list[TileSpec], solve_fn, solve_args, mesh_fn, mesh_args, retries: int = 2
                 ) -> tuple[dict, dict]:
    """Submit the job's graph: one solve task per tile, then one mesh task per tile that depends on the solves of
    the tile and its (up to 26) neighbours.

    ``solve_fn(spec, *solve_args(spec))`` and ``mesh_fn(spec, own_summary, neighbour_specs, neighbour_summaries,
    *mesh_args(spec))``; tasks carry the small spec objects, never arrays. Returns the futures by tile index.
    """
    by_index = {s.index: s for s in specs}
    solve_futs = {s.index: client.submit(solve_fn, s, *solve_args(s), key=f"solve-{s.name}", retries=retries,
                                         pure=False)
                  for s in specs}
    mesh_futs = {}
    for s in specs:
        nbs = neighbors_of(s, by_index)
        mesh_futs[s.index] = client.submit(mesh_fn, s, solve_futs[s.index], nbs, [solve_futs[n.index] for n in nbs],
                                           *mesh_args(s), key=f"mesh-{s.name}", retries=retries, pure=False)
    return solve_futs, mesh_futs


def check_memory(specs: list[TileSpec] | None, tiling: TilingConfig, solver: SolverConfig, budget: int,
                 occupancy: dict | None = None, estimates: list[dict] | None = None) -> list[dict]:
    """Refuse (one line, before any solve) tiles whose estimated peak memory exceeds ``budget`` bytes.

    ``estimates`` (from :func:`tiled_gridpull.memory.estimate_tiles`) are computed from ``specs`` if not given.
    """
    from tiled_gridpull.errors import MemoryBudgetError
    from tiled_gridpull.memory import estimate_tiles, format_size

    est = estimates if estimates is not None else estimate_tiles(specs, solver, tiling, occupancy)
    over = sorted((e for e in est if e["peak"] > budget), key=lambda e: -e["peak"])
    if over:
        names = ", ".join(f"{e['tile']} ({format_size(e['peak'])})" for e in over[:5])
        more = f" and {len(over) - 5} more" if len(over) > 5 else ""
        raise MemoryBudgetError(
            f"{len(over)} of {len(est)} tiles would exceed --max-memory {format_size(budget)}: {names}{more}; "
            f"use a smaller --tile-size (now {tiling.tile_size:g}) or a larger budget")
    if est:
        top = max(est, key=lambda e: e["peak"])
        log.info("largest tile memory estimate: %s (%s), within --max-memory %s", format_size(top["peak"]),
                 top["tile"], format_size(budget))
    return est


def _collect(solve_futs: dict, mesh_futs: dict, options: JobOptions, interrupted: threading.Event
             ) -> tuple[list, list]:
    """Wait for every task with a progress bar (tiles done / total, ETA); results in tile order.

    Finished tasks are taken in batches, and ``interrupted`` (Ctrl-C, see :func:`_deferred_interrupt`) is checked
    between them: the job stops within a tenth of a second, outside any of distributed's own calls.
    """
    from distributed import as_completed
    from tqdm import tqdm

    total = len(solve_futs) + len(mesh_futs)
    bar = tqdm(total=total, unit="task", desc="tiles", disable=not options.progress, dynamic_ncols=True)
    results: dict = {}
    kinds = {f.key: ("solve", idx) for idx, f in solve_futs.items()}
    kinds.update({f.key: ("mesh", idx) for idx, f in mesh_futs.items()})
    pending = as_completed(list(solve_futs.values()) + list(mesh_futs.values()))
    try:
        while not pending.is_empty():
            if interrupted.wait(0.1 if not pending.has_ready() else 0):
                raise KeyboardInterrupt
            for fut in pending.next_batch(block=False):
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
