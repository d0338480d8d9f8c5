"""The tiled workflow without Dask: scan, partition, solve, blend + mesh, weld.

``tiled_gridpull.pipeline.job`` runs the same steps as Dask tasks; this module holds the steps and a sequential driver
(:func:`reconstruct_scene`) so the core runs, and is tested, without a cluster.

A job directory holds everything a run produces, so a finished or interrupted job can be inspected:
``manifest.json`` (plan, tiles), ``points/`` (spill files), ``fields/`` (solved tile fields), ``pieces/`` (tile
meshes) and ``summaries/`` (one JSON per finished tile step).
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from ._version import __version__
from .config import SolverConfig
from .errors import ConfigError, InputError, TileFailedError
from .io.atomic import write_json
from .mesh import Mesh
from .stitch import load_piece, mesh_tile, weld_pieces
from .tile import (TilePlan, TileSpec, TilingConfig, check_compatible, partition, plan_tiles, solve_tile,
                   write_manifest)

__all__ = ["scan_inputs", "prepare_job", "neighbors_of", "finish_job", "reconstruct_scene", "JobPaths",
           "plan_centre", "key_reference", "job_metadata"]


class JobPaths:
    """Where a job keeps its intermediate files."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    def points(self) -> Path:
        return self.root / "points"

    def field(self, spec: TileSpec) -> Path:
        return self.root / "fields" / f"{spec.name}.npz"

    def piece(self, spec: TileSpec) -> Path:
        return self.root / "pieces" / f"{spec.name}.npz"

    def summary(self, step: str, spec: TileSpec) -> Path:
        return self.root / "summaries" / f"{step}_{spec.name}.json"


@contextlib.contextmanager
def job_lock(root: str | Path) -> Iterator[None]:
    """Hold a work directory for one job: a second job started on it stops at once, naming the holder's PID.

    Two jobs on one directory would interleave their spill files and replace each other's fields. The lock is
    ``flock`` on ``<root>/.lock``: the kernel releases it when the holder exits, even on SIGKILL, so a crashed
    job never leaves the directory locked.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock, as before
        yield
        return
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    fd = os.open(root / ".lock", os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise ConfigError(f"work directory {root} is in use by another job (PID {holder}): wait for it to "
                              "finish, or give another --work-dir") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.close(fd)


def scan_inputs(inputs: list[str], chunk_size: int = 2_000_000, frames=None) -> dict:
    """One streaming pass: bounds, point count and whether sensor origins are known."""
    from .io.points import iter_point_chunks
    from .outliers import SAMPLE_STRIDE

    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    n = 0
    sample = []
    has_sensor = True
    crs = crs_source = None
    for chunk in _chunks(inputs, chunk_size, frames):
        if chunk.crs:
            if crs is None:
                crs, crs_source = chunk.crs, chunk.source
            elif _crs_text(chunk.crs) != _crs_text(crs):
                # merging would place one survey's points in another's frame without a word
                raise InputError(f"inputs in different coordinate reference systems: {_file_of(crs_source)} "
                                 f"({_crs_name(crs)}) and {_file_of(chunk.source)} ({_crs_name(chunk.crs)}); "
                                 "reproject them to one first")
        if len(chunk) == 0:
            continue
        lo = np.minimum(lo, chunk.xyz.min(axis=0))
        hi = np.maximum(hi, chunk.xyz.max(axis=0))
        n += len(chunk)
        has_sensor &= chunk.sensor is not None
        # a copy: a strided view would keep every whole chunk alive, i.e. the whole input in memory
        sample.append(chunk.xyz[::SAMPLE_STRIDE].copy())
    if n == 0:
        raise InputError(f"{', '.join(map(str, inputs))}: no points")
    return {"bounds": np.stack([lo, hi]), "points": n, "has_sensor": bool(has_sensor), "crs": crs,
            "sample": np.concatenate(sample)}


def _far_points(inputs, chunk_size, frames, box) -> tuple[np.ndarray | None, np.ndarray | None, int]:
    """One pass: the first point outside ``box`` (for the message; None when none), the bounds of the points
    inside it (None when none), and how many lie outside."""
    from .outliers import far_mask

    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    example, n_far = None, 0
    for chunk in _chunks(inputs, chunk_size, frames):
        far = far_mask(chunk.xyz, box)
        n_far += int(far.sum())
        if example is None and far.any():
            example = chunk.xyz[np.argmax(far)].copy()
        near = chunk.xyz[~far]
        if len(near):
            lo = np.minimum(lo, near.min(axis=0))
            hi = np.maximum(hi, near.max(axis=0))
    inside = np.stack([lo, hi]) if np.all(np.isfinite(lo)) else None
    return example, inside, n_far


def _without_far(chunks, box):
    """The chunks without their points outside ``box``."""
    from .outliers import far_mask

    for chunk in chunks:
        far = far_mask(chunk.xyz, box)
        yield chunk.take(np.flatnonzero(~far)) if far.any() else chunk


def _crs_text(crs: str) -> str:
    """A CRS's text without the layout whitespace outside quoted names (WKT pretty-printed or not)."""
    import re

    return re.sub(r'\s+(?=(?:[^"]*"[^"]*")*[^"]*$)', "", crs)


def _file_of(source) -> str:
    """The file of a chunk's ``source`` (``path[start:stop]``)."""
    import re

    return re.sub(r"\[\d+:\d+\]$", "", str(source))


def _crs_name(crs: str) -> str:
    """A short name for a CRS in a message: the WKT's first quoted name, else its start."""
    import re

    m = re.search(r'"([^"]+)"', crs)
    return m.group(1) if m else crs.split("\n")[0][:60]


def _chunks(inputs, chunk_size, frames):
    from .io import iter_point_chunks, read_kitti_sequence

    for path in inputs:
        p = Path(path)
        if p.is_dir():
            cloud = read_kitti_sequence(p, frames)
            for s in range(0, len(cloud), chunk_size):
                from .cloud import PointCloud

                yield PointCloud(cloud.xyz[s:s + chunk_size], sensor=cloud.sensor[s:s + chunk_size],
                                 source=cloud.source, crs=cloud.crs)
        else:
            yield from iter_point_chunks([p], chunk_size)


def plan_inputs(inputs: list[str], tiling: TilingConfig, *, chunk_size: int = 2_000_000,
                frames=None) -> tuple[TilePlan, dict, Callable[[], Iterator]]:
    """Scan the inputs and lay the tile plan over them (the job's and ``--dry-run``'s first step).

    Points far from the rest (:mod:`tiled_gridpull.outliers`) are dropped when ``tiling.drop_outliers`` is set
    (a warning says how many); otherwise, when they stretch the lattice past what it can hold, the refusal says
    how many there are and how to drop them.

    Returns
    -------
    plan : TilePlan
    scan : dict
        Bounds, point count (both without the dropped points), sensor and CRS facts, ``far_points_dropped``.
    chunks : callable
        ``chunks()`` streams the input's points again (without the dropped ones), for the partition.
    """
    from .outliers import body_box, describe
    from .tile import LatticeSpanError

    scan = scan_inputs(inputs, chunk_size, frames)
    sample = scan.pop("sample")
    # the body is only needed to drop far points or to explain a refused span: no quantiles on a plain job
    box = body_box(sample, pad=tiling.tile_size) if tiling.drop_outliers else None

    def chunks():
        raw = _chunks(inputs, chunk_size, frames)
        return _without_far(raw, box) if scan.get("far_points_dropped") else raw

    if tiling.drop_outliers:
        example, inside, n_far = _far_points(inputs, chunk_size, frames, box)
        scan["far_points_dropped"] = n_far
        if n_far:
            if inside is None:
                raise InputError(f"{', '.join(map(str, inputs))}: drop_outliers would drop every point")
            warnings.warn(f"drop_outliers: {describe(n_far, scan['points'], box, example)}: dropped",
                          stacklevel=2)
            scan["bounds"], scan["points"] = inside, scan["points"] - n_far
    try:
        plan = plan_tiles(scan["bounds"], scan["points"], tiling)
    except LatticeSpanError as exc:
        box = body_box(sample, pad=tiling.tile_size)
        example, _, n_far = _far_points(inputs, chunk_size, frames, box)
        if not n_far:
            raise
        span = str(exc).split(": stray points")[0]
        raise LatticeSpanError(f"{span}: {describe(n_far, scan['points'], box, example)}; drop them with "
                               "--drop-outliers (drop_outliers: true)") from None
    return plan, scan, chunks


def prepare_job(inputs: list[str], tiling: TilingConfig, paths: JobPaths, *, frames=None,
                chunk_size: int = 2_000_000,
                check: Callable[[list[TileSpec], dict], None] | None = None) -> tuple[TilePlan, list[TileSpec], dict]:
    """Scan and partition the inputs into tiles; writes the manifest. Returns the plan, tiles and scan facts.

    A finished partition of the same inputs (path, size, mtime) and tile grid in ``paths`` is reused without
    reading the inputs (``scan["partition_reused"]``; see :mod:`tiled_gridpull.resume`).

    ``check(specs, occupancy)``, when given, runs on a counting pass (tiles and their occupied bricks, nothing
    written) before the partition writes its spill files: it refuses a job (e.g. ``--max-memory``) by raising,
    so a refused job leaves no partition behind. It costs one more read of the inputs.
    """
    from .resume import load_partition, partition_key, scan_record

    key = partition_key(inputs, tiling, frames)
    reused = load_partition(paths, key, tiling)
    if reused is not None:
        return reused
    paths.manifest.unlink(missing_ok=True)  # the manifest commits a partition: none while one is under way
    plan, scan, chunks = plan_inputs(inputs, tiling, chunk_size=chunk_size, frames=frames)
    if check is not None:
        occupancy: dict = {}
        check(partition(chunks(), plan, None, scan["has_sensor"], occupancy=occupancy), occupancy)
    specs = partition(chunks(), plan, paths.points(), scan["has_sensor"])
    write_manifest(paths.manifest, plan, specs, {"inputs": [str(Path(p).resolve()) for p in inputs],
                                                 "crs": scan["crs"], "version": __version__,
                                                 "partition_key": key, "scan": scan_record(scan)})
    scan["partition_reused"] = False
    return plan, specs, scan


def neighbors_of(spec: TileSpec, solved: dict[tuple, TileSpec]) -> list[TileSpec]:
    """Solved tiles whose blocks overlap ``spec``'s (the 26 around it)."""
    out = []
    i, j, k = spec.index
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            for dk in (-1, 0, 1):
                if di == dj == dk == 0:
                    continue
                t = solved.get((i + di, j + dj, k + dk))
                if t is not None:
                    out.append(t)
    return out


def plan_centre(plan: TilePlan) -> tuple[float, float, float]:
    """Centre of the input's bounding box (world), for the ``outward`` orientation rule."""
    return tuple(float(v) for v in plan.bounds.mean(axis=0))


def key_reference(plan: TilePlan) -> np.ndarray:
    """Global vertex index edge keys count from (below every tile block)."""
    return np.asarray(plan.lattice.offset, np.int64) - plan.config.overlap_cells


def finish_job(pieces: Iterable[Path], metadata: dict, *, float32: bool = False,
               tile_meshes: str | Path | None = None) -> Mesh:
    """Weld the tile pieces into one mesh carrying ``metadata``. The caller writes it, once its timings are in,
    with its sidecar as one commit (:func:`~tiled_gridpull.io.write_mesh_and_sidecar`).

    ``tile_meshes``: also write each tile's piece as ``<dir>/<tile>.ply`` (input coordinates; pieces share their
    border vertices exactly, so they fit together without gaps).
    """
    from .io import write_mesh

    loaded = [(Path(p), load_piece(p)) for p in pieces]
    if tile_meshes is not None:
        out_dir = Path(tile_meshes)
        out_dir.mkdir(parents=True, exist_ok=True)
        for p, piece in loaded:
            if len(piece.faces):
                write_mesh(Mesh(piece.vertices, piece.faces), out_dir / f"{p.stem}.ply", float32=float32)
    mesh = weld_pieces([piece for _, piece in loaded])
    mesh.metadata.update(metadata)
    mesh.metadata["mesh"] = mesh.topology.to_dict()
    return mesh


def check_some_tile_solvable(specs: list[TileSpec], tiling: TilingConfig) -> None:
    """Refuse, before any solve, a job none of whose tiles holds ``min_points`` points."""
    largest = max((s.n_points for s in specs), default=0)
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


def reconstruct_scene(inputs: list[str], output: str | Path | None, tiling: TilingConfig, solver: SolverConfig,
                      work_dir: str | Path, *, frames=None, float32: bool = False,
                      log: Callable[[str], None] | None = None, tile_meshes: str | Path | None = None) -> Mesh:
    """Tiled reconstruction, one tile after the other in this process (no Dask).

    Returns the welded mesh; ``mesh.metadata`` describes the job (lattice, settings, per-tile summaries,
    timings).
    """
    check_compatible(tiling, solver)
    with job_lock(work_dir):
        return _reconstruct_scene(inputs, output, tiling, solver, JobPaths(work_dir), frames=frames,
                                  float32=float32, log=log, tile_meshes=tile_meshes)


def _reconstruct_scene(inputs, output, tiling, solver, paths: JobPaths, *, frames, float32, log,
                       tile_meshes) -> Mesh:
    t0 = time.perf_counter()
    plan, specs, scan = prepare_job(inputs, tiling, paths, frames=frames)
    check_some_tile_solvable(specs, tiling)
    t_part = time.perf_counter()
    solved: dict[tuple, TileSpec] = {}
    summaries = []
    centre = plan_centre(plan)
    for spec in specs:
        s = solve_tile(spec, tiling, solver, paths.field(spec), centre=centre)
        summaries.append(s)
        if s["status"] == "solved":
            solved[spec.index] = spec
        if log:
            log(f"{spec.name}: {s['status']} ({s.get('reason', '')}{s['time_s']:.1f} s)")
    check_some_tile_solved(summaries)
    t_solve = time.perf_counter()
    ref = key_reference(plan)
    mesh_summaries = []
    for spec in solved.values():
        nb = [(n, paths.field(n)) for n in neighbors_of(spec, solved)]
        mesh_summaries.append(mesh_tile(spec, nb, tiling, ref, paths.field(spec), paths.piece(spec)))
    t_mesh = time.perf_counter()
    meta = job_metadata(plan, tiling, solver, scan, summaries, mesh_summaries,
                        {"partition": t_part - t0, "solve": t_solve - t_part, "mesh": t_mesh - t_solve})
    mesh = finish_job([paths.piece(s) for s in solved.values()], meta, float32=float32, tile_meshes=tile_meshes)
    mesh.metadata["timings_s"]["merge"] = time.perf_counter() - t_mesh
    mesh.metadata["timings_s"]["total"] = time.perf_counter() - t0
    if output is not None:
        from .io import write_mesh_and_sidecar

        write_mesh_and_sidecar(mesh, output, float32=float32)
    from .report import write_report

    write_report(paths.root, mesh.metadata, output=output)  # report.json + tiles.png in the job directory
    return mesh


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
                  "has_sensor": scan["has_sensor"]},
        "crs": scan.get("crs"),
        "tiles": {"planned": int(np.prod(plan.tile_range)), "with_points": len(solve_summaries),
                  "solved": len(solve_summaries) - len(failed),
                  "not_solved": [{"tile": s["tile"], "status": s["status"], "reason": s.get("reason")} for s in failed]},
        "tile_summaries": [{k: v for k, v in s.items() if k != "loss_curve"} for s in solve_summaries],
        "mesh_summaries": mesh_summaries,
        "timings_s": dict(timings),
        "memory_mb": _memory_summary(solve_summaries, mesh_summaries),
    }


def _memory_summary(solve_summaries: list, mesh_summaries: list) -> dict:
    """Peak resident memory: the largest single tile task (solve or mesh) and this (driver) process."""
    from .tile import peak_rss_mb

    def biggest(rows):
        vals = [r.get("peak_rss_mb") for r in rows if r.get("peak_rss_mb") is not None]
        return max(vals) if vals else None

    return {"max_solve_task_peak_rss": biggest(solve_summaries), "max_mesh_task_peak_rss": biggest(mesh_summaries),
            "driver_peak_rss": peak_rss_mb()}


def read_job_summary(output: str | Path) -> dict:
    """The sidecar JSON of a scene mesh."""
    return json.loads(Path(output).with_suffix(".json").read_text())
