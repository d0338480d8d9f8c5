"""The tiled job: one driver (partition, solve and mesh every tile, weld, report) with interchangeable executors.

:func:`run_tiled_job` does everything a tiled job does whatever runs its tiles: the job lock, the memory budget
(``max_memory``), the partition (reused when unchanged), tile results reused by content key
(:mod:`tiled_gridpull.resume`), fail-fast, the weld, the mesh's sidecar metadata and the job's report. An
executor only runs the tiles' solve and mesh steps and yields their summaries:

* :class:`SerialExecutor` (here): every tile in this process, one after the other; no Dask needed;
* ``tiled_gridpull.pipeline.job.DaskExecutor``: tiles as tasks on a Dask cluster.

:func:`reconstruct_scene` is the serial entry point. The files of a job directory are described in
:mod:`tiled_gridpull.jobdir`.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Protocol

import numpy as np
from tqdm import tqdm

from ._version import __version__
from .attributes import ATTRIBUTE_NEIGHBORS
from .config import SolverConfig
from .errors import InputError, TileFailedError
from .io import write_mesh, write_mesh_and_sidecar
from .jobdir import JobPaths, check_job_dir, job_lock, neighbors_of
from .kernels.warmup import cold_kernels, compile_kernels, estimate_seconds
from .memory import BASE_MB, MB, band_bricks_bound, card_bytes, check_memory, peak_rss_mb, tile_memory
from .mesh import Mesh
from .partition import read_occupancy
from .prepare import check_registered, check_remote, prepare_job, resolve_units, scan_noise_treatment
from .report import write_report
from .resume import (finish_tile_resumable, mesh_tile_resumable, prepare_tile_resumable, solve_batch_resumable,
                     solve_tile_resumable)
from .stitch import MeshPiece, drop_small_components, load_piece, mesh_tile, weld_pieces
from .tile_plan import TilePlan, TileSpec
from .tile_solve import solve_tile
from .tiling import TilingConfig, check_compatible, with_halo

log = logging.getLogger("tiled_gridpull")

__all__ = ["run_tiled_job", "reconstruct_scene", "TileExecutor", "SerialExecutor", "solve_step", "prepare_step",
           "solve_batch_step", "finish_step", "mesh_step", "task_arguments", "batch_arguments", "collect_summaries",
           "finish_job", "job_metadata", "plan_centre", "key_reference", "check_some_tile_solvable",
           "check_some_tile_solved", "compile_ahead"]

#: One finished tile step from an executor: ``(kind, tile index, summary)``, ``kind`` "solve" or "mesh".
TileEvent = tuple[str, tuple[int, int, int], dict]


class TileExecutor(Protocol):
    """What runs a job's tile steps (:class:`SerialExecutor`, ``tiled_gridpull.pipeline.job.DaskExecutor``).

    Attributes
    ----------
    engine : dict
        Recorded as the job metadata's ``engine`` (``scheduler``, ``workers``).
    """

    engine: dict

    def check(self) -> None:
        """Refuse, before the partition, a job this executor cannot run (e.g. an unreachable scheduler)."""

    def map(self, fn: Callable, args: list[tuple], root: Path) -> list:
        """``fn(*a)`` for every ``a`` in ``args`` (the tile reads of indexed inputs, which write into the job
        directory ``root``), results in order; a task's error is raised as it was raised."""

    def close(self) -> None:
        """Release what the executor holds (a cluster); called when the job ends, however it ends."""

    # optional (the driver calls it when present): warm_up(n_tasks, root) compiles, before the tiles, the numba
    # kernels that numba's cache lacks, saying so on screen (:func:`compile_ahead`)

    def run(self, specs: list[TileSpec], tiling: TilingConfig, solver: SolverConfig, paths: JobPaths,
            centre: tuple[float, float, float], key_ref: np.ndarray) -> Iterator[TileEvent]:
        """Run every tile's :func:`solve_step` and then, once it and its neighbours are solved, its
        :func:`mesh_step`, with the job directory's field, piece and summary paths; yield each summary as it
        comes. Closing the iterator releases what the executor holds (a cluster)."""


def solve_step(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str, centre,
               summary_path: str | None = None, before_solve: Callable[[], None] | None = None) -> dict:
    """Solve one tile (:func:`tiled_gridpull.tile_solve.solve_tile`), or reuse its recorded result when
    ``summary_path`` is given (:func:`tiled_gridpull.resume.solve_tile_resumable`; ``before_solve()`` runs only
    when the tile is actually solved)."""
    if summary_path is None:
        return solve_tile(spec, tiling, solver, field_path, centre=centre)
    return solve_tile_resumable(spec, tiling, solver, field_path, summary_path, centre, before_solve=before_solve)


def prepare_step(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str, centre,
                 summary_path: str, prepared_path: str, solved_path: str | None = None) -> dict:
    """The first half of :func:`solve_step` for tiles solved in batches on a card: the tile's recorded summary,
    or the tile read and set up into ``prepared_path`` (status ``"prepared"``, with ``card_bytes``, the card
    memory its solve takes: :func:`tiled_gridpull.memory.card_bytes`, and ``host_bytes``, the host memory:
    :func:`tiled_gridpull.memory.tile_memory`), or its summary when it needs no solve
    (:func:`tiled_gridpull.resume.prepare_tile_resumable`)."""
    out = prepare_tile_resumable(spec, tiling, solver, field_path, summary_path, prepared_path, centre, solved_path)
    if out.get("status") == "prepared":
        bricks = band_bricks_bound(read_occupancy(spec), spec.block.shape, solver)
        out["card_bytes"] = card_bytes(spec, bricks, solver)
        # and the host memory it adds to the card worker's while its batch runs (the process's own base apart)
        out["host_bytes"] = tile_memory(spec, None, solver, tiling, bricks=bricks)["solve"] - BASE_MB * MB
    return out


def solve_batch_step(specs: list[TileSpec], tiling: TilingConfig, solver: SolverConfig, field_paths: list[str],
                     centre, summary_paths: list[str], prepared_paths: list[str],
                     solved_paths: list[str], note: dict | None = None) -> list[dict]:
    """The second step: prepared tiles solved as one batch (one launch per step for all of them on a card), each
    field left for its finish (:func:`tiled_gridpull.resume.solve_batch_resumable`)."""
    return solve_batch_resumable(specs, tiling, solver, field_paths, summary_paths, prepared_paths, solved_paths,
                                 centre, note)


def finish_step(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str, centre,
                summary_path: str, prepared_path: str, solved_path: str) -> dict:
    """The last step: a batch-solved tile oriented, bridged, written and recorded
    (:func:`tiled_gridpull.resume.finish_tile_resumable`)."""
    return finish_tile_resumable(spec, tiling, solver, field_path, summary_path, prepared_path, solved_path, centre)


def mesh_step(spec: TileSpec, own: dict, neighbor_specs: list, neighbor_summaries: list, tiling: TilingConfig,
              key_ref, field_paths: dict, piece_path: str, summary_path: str | None = None) -> dict:
    """Blend a solved tile with its solved neighbours and mesh its core (or reuse its recorded piece when
    ``summary_path`` is given). ``own`` and ``neighbor_summaries`` are solve summaries; ``field_paths`` maps the
    tile's and its neighbours' names to their fields."""
    if own.get("status") != "solved":
        return {"tile": spec.name, "status": "not solved", "faces": 0}
    solved = [(s, summ) for s, summ in zip(neighbor_specs, neighbor_summaries) if summ.get("status") == "solved"]
    if summary_path is None:
        out = mesh_tile(spec, [(s, field_paths[s.name]) for s, _ in solved], tiling, key_ref,
                        field_paths[spec.name], piece_path)
        out["status"] = "meshed"
        return out
    return mesh_tile_resumable(spec, own, [(s, summ, field_paths[s.name]) for s, summ in solved], tiling, key_ref,
                               field_paths[spec.name], piece_path, summary_path)


def task_arguments(specs: list[TileSpec], tiling: TilingConfig, solver: SolverConfig, paths: JobPaths,
                   centre, key_ref):
    """The arguments after the spec of each tile's :func:`solve_step` and, after its own and its neighbours'
    specs and summaries, of its :func:`mesh_step`: ``(solve_args, mesh_args)``, two functions of a spec; every
    executor calls the steps with them.

    A mesh task gets the field paths of its own tile and its neighbours only: the whole job's map in every task
    would make each task's message grow with the tile count (megabytes at 100,000 tiles).
    """
    by_index = {s.index: s for s in specs}

    def solve_args(s: TileSpec) -> tuple:
        return tiling, solver, str(paths.field(s)), centre, str(paths.summary("solve", s))

    def mesh_args(s: TileSpec) -> tuple:
        fields = {t.name: str(paths.field(t)) for t in [s, *neighbors_of(s, by_index)]}
        return tiling, key_ref, fields, str(paths.piece(s)), str(paths.summary("mesh", s))

    return solve_args, mesh_args


def batch_arguments(tiling: TilingConfig, solver: SolverConfig, paths: JobPaths, centre):
    """The arguments after the spec of a tile's :func:`prepare_step` and :func:`finish_step` (the same: the tile's
    files), and after the specs of a batch of tiles, of :func:`solve_batch_step`: ``(tile_args, batch_args)``,
    functions of a spec and of a list of specs."""

    def tile_args(s: TileSpec) -> tuple:
        return (tiling, solver, str(paths.field(s)), centre, str(paths.summary("solve", s)), str(paths.prepared(s)),
                str(paths.solved(s)))

    def batch_args(group: list[TileSpec]) -> tuple:
        return (tiling, solver, [str(paths.field(s)) for s in group], centre,
                [str(paths.summary("solve", s)) for s in group], [str(paths.prepared(s)) for s in group],
                [str(paths.solved(s)) for s in group])

    return tile_args, batch_args


class SerialExecutor:
    """Runs a job's tiles in this process, one after the other: every solve in tile order, then every mesh.

    Parameters
    ----------
    log : callable, optional
        Called with one line per solved tile (``tile_0_0_0: solved (12.3 s)``).
    """

    engine = {"scheduler": "serial", "workers": 1}

    def __init__(self, log: Callable[[str], None] | None = None):
        self.log = log

    def check(self) -> None:
        return None

    def warm_up(self, n_tasks: int, root: Path) -> None:
        """Compile the kernels numba's cache lacks here, before the first tile, saying so."""
        compile_ahead(lambda cold: compile_kernels(cold), 1)

    def map(self, fn: Callable, args: list[tuple], root: Path) -> list:
        return [fn(*a) for a in args]

    def close(self) -> None:
        return None

    def run(self, specs: list[TileSpec], tiling: TilingConfig, solver: SolverConfig, paths: JobPaths,
            centre: tuple[float, float, float], key_ref: np.ndarray) -> Iterator[TileEvent]:
        specs = sorted(specs, key=lambda s: s.index)
        by_index = {s.index: s for s in specs}
        solve_args, mesh_args = task_arguments(specs, tiling, solver, paths, centre, key_ref)
        summaries: dict[tuple, dict] = {}
        for s in specs:
            out = solve_step(s, *solve_args(s))
            if not out.get("reused"):
                out["worker"] = "local"
            summaries[s.index] = out
            if self.log:
                reason = f"{out['reason']}; " if out.get("reason") else ""
                self.log(f"{s.name}: {out['status']} ({reason}{out['time_s']:.1f} s)")
            yield "solve", s.index, out
        for s in specs:
            nbs = neighbors_of(s, by_index)
            yield "mesh", s.index, mesh_step(s, summaries[s.index], nbs, [summaries[n.index] for n in nbs],
                                             *mesh_args(s))


def compile_ahead(compile_shares: Callable[[list[str]], object], parts: int,
                  cold: list[str] | None = None, names: list[str] | None = None) -> list[str]:
    """Say on screen that the kernels numba's cache lacks are being compiled, and how long that takes, around
    ``compile_shares(cold)``, which compiles them (``parts`` at a time: the estimate divides the work).

    A first job on a machine compiles about 20 kernels (45 s of one core, measured on the 2-core development
    machine): its first tile looked stalled, with nothing on screen. With a warm cache this says nothing.

    Parameters
    ----------
    compile_shares : callable
        Compiles the kernels named in its list (in this process, or a share on each worker).
    parts : int
        How many processes compile at once.
    cold : list of str, optional
        The cold kernels, when the caller knows them (another machine's cache); default: this process's
        (:func:`tiled_gridpull.kernels.warmup.cold_kernels`).
    names : list of str, optional
        The kernels to consider when ``cold`` is not given (default all; one-shape mode needs fewer).

    Returns
    -------
    list of str
        The kernels compiled (empty with a warm cache, or where numba's cache cannot be read: then each kernel
        is compiled at its first call, as before).
    """
    if cold is None:
        cold = cold_kernels(names)
    if not cold:
        return []
    log.info("compiling %d numba kernels, once per installation (numba caches them): about %.0f s",
             len(cold), max(1.0, estimate_seconds(cold, parts)))
    t0 = time.perf_counter()
    compile_shares(cold)
    log.info("compiled the kernels in %.1f s", time.perf_counter() - t0)
    return cold


def reconstruct_scene(inputs: list[str], output: str | Path | None, tiling: TilingConfig, solver: SolverConfig,
                      work_dir: str | Path, *, frames=None, trajectory: str | Path | None = None,
                      float32: bool = False, log: Callable[[str], None] | None = None,
                      tile_meshes: str | Path | None = None, fail_fast: bool = False,
                      max_memory: int | None = None, tiles3d: str | Path | None = None,
                      tiles3d_crs: str | None = None) -> Mesh:
    """Tiled reconstruction, one tile after the other in this process (no Dask): :func:`run_tiled_job` with a
    :class:`SerialExecutor`.

    Parameters
    ----------
    inputs : list of str
        Point files (LAS/LAZ, PLY, NPY, text) or KITTI sequence directories.
    output : str or Path, optional
        The mesh to write (PLY or OBJ), with its ``.json`` sidecar; None writes nothing but the job directory.
    tiling : TilingConfig
        Cell size, tile core and overlap (world units), trim, orientation.
    solver : SolverConfig
        The per-tile solve.
    work_dir : str or Path
        The job directory; a rerun there reuses the partition and every tile whose inputs are unchanged.
    frames : slice, optional
        KITTI frames to read.
    trajectory : str or Path, optional
        A sensor trajectory (:mod:`tiled_gridpull.trajectory`) giving every LAS/LAZ point its sensor origin by
        GPS time.
    float32 : bool
        Write float32 vertices relative to an offset recorded in the file (smaller; exact for our reader).
    log : callable, optional
        ``log(line)`` for one line per finished tile.
    tile_meshes : str or Path, optional
        Also keep every tile's piece in this directory.
    fail_fast : bool
        Stop at the first failed tile instead of meshing around it.
    max_memory : int, optional
        Bytes the job may use; refused before the partition when a tile's estimate exceeds it.
    tiles3d : str or Path, optional
        Also write the mesh as an OGC 3D Tiles 1.1 tileset in this directory (:mod:`tiled_gridpull.tiles3d`).
    tiles3d_crs : str, optional
        The CRS of the tileset's georeferencing (``EPSG:32632``) when the inputs declare none, or instead of it.

    Returns
    -------
    Mesh
        The welded mesh (float64 vertices, world units); ``mesh.metadata`` describes the job (lattice,
        settings, per-tile summaries, timings).
    """
    return run_tiled_job(inputs, output, tiling, solver, work_dir, SerialExecutor(log), frames=frames,
                         trajectory=trajectory, float32=float32, tile_meshes=tile_meshes, fail_fast=fail_fast,
                         max_memory=max_memory, progress=False, tiles3d=tiles3d, tiles3d_crs=tiles3d_crs)


def run_tiled_job(inputs: list[str], output: str | Path | None, tiling: TilingConfig, solver: SolverConfig,
                  work_dir: str | Path, executor: TileExecutor, *, frames=None,
                  trajectory: str | Path | None = None, float32: bool = False,
                  tile_meshes: str | Path | None = None, fail_fast: bool = False, max_memory: int | None = None,
                  progress: bool = True, tiles3d: str | Path | None = None, tiles3d_crs: str | None = None) -> Mesh:
    """A tiled reconstruction whose tiles ``executor`` runs; writes ``output`` (when given) with its sidecar and
    the job's report, returns the welded mesh.

    Parameters
    ----------
    inputs : list of str
        Point files or KITTI sequence directories.
    output : str or Path, optional
        The mesh to write.
    work_dir : str or Path
        The job directory (:mod:`tiled_gridpull.jobdir`); a rerun there reuses every unchanged result.
    executor : TileExecutor
    frames : optional
        KITTI frame range.
    trajectory : str or Path, optional
        Sensor trajectory file for LAS/LAZ inputs with GPS time (:mod:`tiled_gridpull.trajectory`).
    float32 : bool
        Write float32 vertices with a recorded offset.
    tile_meshes : str or Path, optional
        Directory to also write one PLY per tile into.
    fail_fast : bool
        Stop at the first tile that fails for a data reason instead of producing the rest of the mesh.
    max_memory : int, optional
        Bytes one tile may use; the job is refused up front if a tile's estimate exceeds it.
    progress : bool
        Show a progress bar with an ETA.
    tiles3d : str or Path, optional
        Also write an OGC 3D Tiles 1.1 tileset of the mesh into this directory (one glb per tile, coarser
        levels of detail, georeferenced from the inputs' CRS or ``tiles3d_crs``).
    tiles3d_crs : str, optional
        The tileset's CRS (``EPSG:XXXX`` or WKT) instead of the inputs' (needed when they declare none).
    """
    tileset = None
    if tiles3d is not None:  # refused before anything is read or solved: no CRS, a directory not ours
        from .tiles3d import check_tileset_dir, resolve_tileset_crs

        check_tileset_dir(tiles3d)
        tileset = (Path(tiles3d), *resolve_tileset_crs(inputs, tiles3d_crs))
    check_job_dir(work_dir)  # a user's own files and linked folders, before anything is read or written
    check_registered(inputs)  # before a KITTI scan's points are read to measure them
    check_remote(inputs, trajectory, tiling)  # before the cell size or the noise reads a URL
    tiling = resolve_units(inputs, tiling, frames)  # auto, or a cell size in metres on data in feet
    solver, noise = scan_noise_treatment(inputs, tiling, solver, frames)  # before the halo it may need
    check_compatible(tiling, solver)
    tiling = with_halo(tiling, solver)  # a denoising tile reads the points its margin needs
    executor.check()  # before the partition, not after it
    work_dir = Path(work_dir).resolve()  # workers of an external cluster do not share this process's cwd
    with job_lock(work_dir):
        try:
            return _run(inputs, output, tiling, solver, JobPaths(work_dir), executor, frames=frames,
                        trajectory=trajectory, float32=float32, noise=noise,
                        tile_meshes=tile_meshes, fail_fast=fail_fast, max_memory=max_memory, progress=progress,
                        tileset=tileset)
        finally:
            close = getattr(executor, "close", None)  # executors written before close() existed have none
            if close is not None:
                close()


def _run(inputs, output, tiling: TilingConfig, solver: SolverConfig, paths: JobPaths, executor: TileExecutor, *,
         frames, trajectory, float32, tile_meshes, fail_fast, max_memory, progress, noise=None,
         tileset: tuple | None = None) -> Mesh:
    t0 = time.perf_counter()
    check = None
    if max_memory is not None:
        # refuse before the partition writes anything
        def check(planned, occupancy):
            check_some_tile_solvable(planned, tiling)
            check_memory(planned, tiling, solver, max_memory, occupancy=occupancy)
    # tasks for the tile reads of indexed inputs and the partition's segments; in this process one after the
    # other (the serial executor) the one pass is the same and cheaper
    mapper = None if isinstance(executor, SerialExecutor) else getattr(executor, "map", None)
    run_tasks = (lambda fn, args: mapper(fn, args, paths.root)) if mapper is not None else None
    plan, specs, scan = prepare_job(inputs, tiling, paths, frames=frames, trajectory=trajectory, check=check,
                                    run_tasks=run_tasks)
    t_part = time.perf_counter()
    log.info("%s %d points into %d tiles (%d planned) in %.1f s",
             "reused the partition of" if scan.get("partition_reused") else "partitioned", scan["points"],
             len(specs), int(plan.tile_range[0] * plan.tile_range[1] * plan.tile_range[2]), t_part - t0)
    check_some_tile_solvable(specs, tiling)
    if max_memory is not None and scan.get("partition_reused"):
        check_memory(specs, tiling, solver, max_memory)
    warm_up = getattr(executor, "warm_up", None)  # executors written before warm_up() existed have none
    if warm_up is not None:
        warm_up(len(specs), paths.root)
    events = executor.run(specs, tiling, solver, paths, plan_centre(plan), key_reference(plan))
    with contextlib.closing(events):
        solve_summaries, mesh_summaries = collect_summaries(events, len(specs), fail_fast=fail_fast,
                                                            progress=progress)
    for s in solve_summaries + mesh_summaries:
        if s.get("redone"):
            log.warning("%s: %s; computed again", s["tile"], s["redone"])
    check_some_tile_solved(solve_summaries)
    t_mesh = time.perf_counter()
    by_index = {s.index: s for s in specs}
    n_solve = sum(1 for s in solve_summaries if s.get("reused"))
    n_mesh = sum(1 for m in mesh_summaries if m.get("reused"))
    log.info("reused %d of %d tile solves and %d of %d mesh pieces from %s", n_solve, len(solve_summaries), n_mesh,
             sum(1 for m in mesh_summaries if m.get("status") == "meshed"), paths.root)
    failed = [s for s in solve_summaries if s["status"] == "failed"]
    if failed and fail_fast:
        raise TileFailedError(f"{len(failed)} tile(s) failed: " + "; ".join(f"{s['tile']}: {s.get('reason')}"
                                                                          for s in failed[:5]))
    meta = job_metadata(plan, tiling, solver, scan, solve_summaries, mesh_summaries,
                        {"partition": t_part - t0, "solve_and_mesh": t_mesh - t_part})
    meta["engine"] = dict(executor.engine)
    if noise is not None:
        meta["noise_treatment"] = noise
    # a mesh task that failed (it killed its worker) leaves its tile out of the mesh: report it like a solve
    meta["tiles"]["not_solved"] += [{"tile": m["tile"], "status": "failed", "reason": m.get("reason")}
                                    for m in mesh_summaries if m.get("status") == "failed"]
    meta["reused"] = {"partition": bool(scan.get("partition_reused")), "solves": n_solve, "meshes": n_mesh}
    meshed = [by_index[tuple(m["index"])] for m in mesh_summaries if m.get("status") == "meshed"]
    mesh, pieces = finish_job([paths.piece(s) for s in meshed], meta, float32=float32, tile_meshes=tile_meshes,
                              min_extent=tiling.min_component_cells * plan.lattice.cell_size)
    mesh.metadata["timings_s"]["merge"] = time.perf_counter() - t_mesh
    if tileset is not None:
        from .tiles3d import job_tiles, write_tileset

        t_tiles = time.perf_counter()
        out_dir, crs, crs_source = tileset
        summary = write_tileset(job_tiles([(s.name, s.index, p) for s, p in zip(meshed, pieces)]), out_dir, crs,
                                metadata=mesh.metadata, crs_source=crs_source)
        mesh.metadata["tiles3d"] = {"dir": str(out_dir), **summary}
        mesh.metadata["timings_s"]["tiles3d"] = time.perf_counter() - t_tiles
        log.info("wrote 3D Tiles %s: %d tiles, %d coarser level(s), in %.1f s", out_dir, summary["tiles"],
                 summary["levels"], mesh.metadata["timings_s"]["tiles3d"])
    mesh.metadata["timings_s"]["total"] = time.perf_counter() - t0
    if output is not None:
        # one commit: a sidecar that cannot be written leaves no mesh behind
        write_mesh_and_sidecar(mesh, output, float32=float32)
    write_report(paths.root, mesh.metadata, output=output)  # report.json + tiles.png in the job directory
    return mesh


def collect_summaries(events: Iterable[TileEvent], n_tiles: int, *, fail_fast: bool = False,
                      progress: bool = True) -> tuple[list, list]:
    """Consume an executor's events with a progress bar (tasks done / total, ETA); summaries in tile order.

    Returns
    -------
    solve, mesh : list of dict
        The solve and the mesh summaries, each in tile order, with ``index`` set.

    Raises
    ------
    TileFailedError
        ``fail_fast`` and a tile's solve failed.
    """
    bar = tqdm(total=2 * n_tiles, unit="task", desc="tiles", disable=not progress, dynamic_ncols=True)
    results: dict = {}
    try:
        for kind, idx, res in events:
            res["index"] = list(idx)
            results[(kind, idx)] = res
            bar.update(1)
            if kind == "solve":
                bar.set_postfix_str(f"{res['tile']} {res['status']}", refresh=False)
                if res["status"] == "failed":
                    # said now for a live view; the closing summary repeats it as a warning
                    log.info("%s failed: %s", res["tile"], res.get("reason"))
                    if fail_fast:
                        raise TileFailedError(f"{res['tile']} failed: {res.get('reason')}")
    finally:
        bar.close()
    ordered = sorted(results.items())  # by (kind, tile index)
    solve = [v for (kind, _), v in ordered if kind == "solve"]
    mesh = [v for (kind, _), v in ordered if kind == "mesh"]
    return solve, mesh


def plan_centre(plan: TilePlan) -> tuple[float, float, float]:
    """Centre of the input's bounding box (world), for the ``outward`` orientation rule."""
    return tuple(float(v) for v in plan.bounds.mean(axis=0))


def key_reference(plan: TilePlan) -> np.ndarray:
    """Global vertex index edge keys count from (below every tile block)."""
    return np.asarray(plan.lattice.offset, np.int64) - plan.config.overlap_cells


def finish_job(pieces: Iterable[Path], metadata: dict, *, float32: bool = False,
               tile_meshes: str | Path | None = None, min_extent: float = 0.0) -> tuple[Mesh, list[MeshPiece]]:
    """Weld the tile pieces into one mesh carrying ``metadata``. The caller writes it, once its timings are in,
    with its sidecar as one commit (:func:`~tiled_gridpull.io.write_mesh_and_sidecar`).

    ``min_extent``: connected parts smaller than this (world units) along every axis are dropped first, each
    judged whole across the tiles it spans (:func:`~tiled_gridpull.stitch.drop_small_components`). How many goes
    to ``metadata["small_components_removed"]`` (as in the one-shape mode); each tile's entry of
    ``metadata["mesh_summaries"]`` then counts the faces and vertices it keeps, and ``small_faces_dropped``.
    ``tile_meshes``: also write each tile's piece as ``<dir>/<tile>.ply`` (input coordinates; pieces share their
    border vertices exactly, so they fit together without gaps); a tile left without faces has none (one an
    earlier run wrote there is removed).

    Returns
    -------
    mesh : Mesh
    pieces : list of MeshPiece
        The tiles' pieces as welded (in the order of ``pieces``): what 3D Tiles are cut from.
    """
    paths = [Path(p) for p in pieces]
    loaded = [load_piece(p) for p in paths]
    kept, dropped = drop_small_components(loaded, min_extent)
    if dropped:
        summaries = {m.get("tile"): m for m in metadata.get("mesh_summaries", [])}
        for p, before, after in zip(paths, loaded, kept):
            if p.stem in summaries:
                summaries[p.stem].update(faces=len(after.faces), vertices=len(after.vertices),
                                         small_faces_dropped=len(before.faces) - len(after.faces))
    if tile_meshes is not None:
        out_dir = Path(tile_meshes)
        out_dir.mkdir(parents=True, exist_ok=True)
        for p, piece in zip(paths, kept):
            if len(piece.faces):
                write_mesh(piece.mesh(), out_dir / f"{p.stem}.ply", float32=float32)
            else:
                (out_dir / f"{p.stem}.ply").unlink(missing_ok=True)
    if dropped and not any(len(piece.faces) for piece in kept):
        log.warning("every part of the mesh is smaller than min_component_cells along every axis: the mesh is "
                    "empty (set a smaller min_component_cells, or 0 to keep every part)")
    mesh = weld_pieces(kept)
    mesh.metadata.update(metadata)
    mesh.metadata["mesh"] = mesh.topology.to_dict()
    mesh.metadata["small_components_removed"] = dropped
    return mesh, kept


def check_some_tile_solvable(specs: list[TileSpec], tiling: TilingConfig) -> None:
    """Refuse, before any solve, a job none of whose tiles holds ``min_points`` points."""
    largest = max((s.block_points for s in specs), default=0)
    if largest < tiling.min_points:
        raise InputError(f"no tile holds min_points ({tiling.min_points}) points, the largest holds {largest}: "
                         "lower min_points or raise tile_size")


def check_some_tile_solved(summaries: list[dict]) -> None:
    """Stop a job none of whose tiles was solved before it writes anything: an empty mesh with exit 0 would
    look like a result. All tiles failed: :class:`TileFailedError`; else (skipped, e.g. duplicates left too few
    points): :class:`InputError`."""
    if any(s["status"] == "solved" for s in summaries):
        return
    first = summaries[0] if summaries else {"tile": "-", "reason": "no tiles"}
    error = TileFailedError if any(s["status"] == "failed" for s in summaries) else InputError
    raise error(f"no tile was solved, nothing written ({len(summaries)} tile(s); {first['tile']}: "
                f"{first.get('reason')})")


def job_metadata(plan: TilePlan, tiling: TilingConfig, solver: SolverConfig, scan: dict, solve_summaries: list,
                 mesh_summaries: list, timings: dict) -> dict:
    """The self-describing record written beside a scene mesh."""
    failed = [s for s in solve_summaries if s["status"] != "solved"]
    return {
        "generator": f"tiled_gridpull {__version__}",
        "version": __version__,
        "lattice": plan.lattice.to_dict(),
        "tiling": tiling.to_dict(),
        "config": solver.to_dict(),
        "input": {"points": scan["points"], "bounds": np.asarray(scan["bounds"]).tolist(),
                  "has_sensor": scan["has_sensor"],
                  **({"trajectory": scan["trajectory"]} if scan.get("trajectory") else {})},
        "crs": scan.get("crs"),
        "vertex_attributes": {"rule": tiling.attributes, "carried": [list(a) for a in scan.get("attributes", [])],
                              "neighbors": ATTRIBUTE_NEIGHBORS},
        "tiles": {"planned": int(np.prod(plan.tile_range)), "with_points": len(solve_summaries),
                  "solved": len(solve_summaries) - len(failed),
                  "not_solved": [{"tile": s["tile"], "status": s["status"], "reason": s.get("reason")}
                                 for s in failed]},
        "tile_summaries": [{k: v for k, v in s.items() if k != "loss_curve"} for s in solve_summaries],
        "devices": _device_summary(solve_summaries),
        "mesh_summaries": mesh_summaries,
        "timings_s": dict(timings),
        "memory_mb": _memory_summary(solve_summaries, mesh_summaries),
    }


def _device_summary(solve_summaries: list) -> dict:
    """Tiles solved per device (``"cpu"``, or ``"cuda: <card>"``): a job may mix them when resumed elsewhere."""
    counts: dict[str, int] = {}
    for s in solve_summaries:
        d = s.get("device")
        if d:
            name = "cpu" if d.get("device") == "cpu" else f"cuda: {d.get('card')}"
            counts[name] = counts.get(name, 0) + 1
    return counts


def _memory_summary(solve_summaries: list, mesh_summaries: list) -> dict:
    """Peak resident memory: the largest single tile task (solve or mesh) and this (driver) process."""
    def biggest(rows):
        vals = [r.get("peak_rss_mb") for r in rows if r.get("peak_rss_mb") is not None]
        return max(vals) if vals else None

    return {"max_solve_task_peak_rss": biggest(solve_summaries), "max_mesh_task_peak_rss": biggest(mesh_summaries),
            "driver_peak_rss": peak_rss_mb()}
