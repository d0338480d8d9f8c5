"""``reconstruct --dry-run``: the tile plan, memory and a rough time estimate of a tiled job, solving nothing.

The inputs are scanned and counted into tiles in memory (no file is written); when the job directory already
holds a finished partition of the same inputs and tile grid, that is read instead.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tiled_gridpull.config import SolverConfig
from tiled_gridpull.tiling import TilingConfig

__all__ = ["plan_job", "format_plan"]


def plan_job(inputs: list[str], tiling: TilingConfig, solver: SolverConfig, work_dir: str | Path, *, frames=None,
             trajectory: str | Path | None = None, workers: int | None = None,
             chunk_size: int = 2_000_000, presets: dict | None = None) -> dict:
    """Everything the dry run reports (see :func:`format_plan`).

    ``presets``: ``{quality: (SolverConfig, TilingConfig)}`` (resolved tilings) whose time is estimated too, from
    this partition where the tile grid is the same and from a partition of their own (in memory) where not;
    ``info["presets"]`` then maps each to its ``wall_seconds``, ``cpu_seconds`` and ``cell_size``.
    """
    from tiled_gridpull.indexed_inputs import all_indexed, estimate_specs, plan_indexed
    from tiled_gridpull.io.remote import recorded
    from tiled_gridpull.jobdir import JobPaths, check_job_dir
    from tiled_gridpull.memory import estimate_tiles
    from tiled_gridpull.partition import partition
    from tiled_gridpull.prepare import (carried_layout, check_registered, plan_inputs, resolve_units,
                                        scan_noise_treatment)
    from tiled_gridpull.resume import load_partition, partition_key
    from tiled_gridpull.tiling import check_compatible, with_halo

    check_job_dir(work_dir)  # the partition is read to be reused: never through a linked folder
    check_registered(inputs)
    tiling = resolve_units(inputs, tiling, frames)
    solver, noise = scan_noise_treatment(inputs, tiling, solver, frames)
    check_compatible(tiling, solver)
    tiling = with_halo(tiling, solver)
    paths = JobPaths(work_dir)
    reused = load_partition(paths, partition_key(inputs, tiling, frames, trajectory), tiling)
    occupancy = None
    sampled = None
    if reused is not None:
        plan, specs, scan = reused
    elif all_indexed(inputs) and trajectory is None and not tiling.drop_outliers:
        # headers, hierarchies and the octree's shallow levels only: seconds, whatever the input's size
        plan, scan, indexes = plan_indexed(inputs, tiling)
        specs, occupancy, sampled = estimate_specs(indexes, plan)
    else:
        plan, scan, chunks = plan_inputs(inputs, tiling, chunk_size=chunk_size, frames=frames,
                                         trajectory=trajectory)
        occupancy = {}
        specs = partition(chunks(), plan, None, scan["has_sensor"], occupancy=occupancy)
    est = estimate_tiles(specs, solver, tiling, occupancy)
    # the points each tile solves; a denoising job's tiles also read a halo around their blocks (copies)
    counts = np.array([s.block_points for s in specs], dtype=np.int64)
    read = int(sum(s.n_points for s in specs))
    cores = os.cpu_count() or 1
    # workers 0 (this process, a tile at a time on every core): estimated as that many one-thread workers
    n_workers = workers or max(1, min(cores, len(specs)))
    cpu_s = float(sum(e["time_s"] for e in est))
    wall_s = job_wall_time(est, int(scan["points"]), n_workers)
    peak = max(est, key=lambda e: e["peak"]) if est else None
    preset_times = {}
    for q, (solver_q, tiling_q) in (presets or {}).items():
        if noise is not None and noise.get("chosen"):  # the scan's treatment, whatever the preset
            solver_q = solver_q.replace(noise=solver.noise)
        if tiling_q == tiling or with_halo(tiling_q, solver_q) == tiling:
            est_q = estimate_tiles(specs, solver_q, tiling, occupancy)
            preset_times[q] = {"wall_seconds": job_wall_time(est_q, int(scan["points"]), n_workers),
                               "cpu_seconds": float(sum(e["time_s"] for e in est_q)),
                               "cell_size": tiling.voxel_size}
        else:
            other = plan_job(inputs, tiling_q, solver_q, work_dir, frames=frames, trajectory=trajectory,
                             workers=workers, chunk_size=chunk_size)
            preset_times[q] = {**{k: other["time"][k] for k in ("wall_seconds", "cpu_seconds")},
                               "cell_size": other["lattice"]["cell_size"]}
    return {
        "inputs": [recorded(p) for p in inputs], "points": int(scan["points"]), "has_sensor": bool(scan["has_sensor"]),
        # what the tiles will carry onto the vertices (--attributes of what the inputs have)
        "attributes": [n for n, _ in carried_layout(scan.get("attributes", []), tiling.attributes)],
        "partition_reused": reused is not None, "index_sample": sampled,
        "lattice": {"origin": list(plan.lattice.origin), "cell_size": plan.lattice.cell_size,
                    "shape": list(plan.lattice.shape), "tile_cells": tiling.tile_cells,
                    "overlap_cells": tiling.overlap_cells, "halo_cells": tiling.halo,
                    "tile_range": list(plan.tile_range),
                    "derived": list(tiling.derived), "units": tiling.units,
                    "levels": solver.levels_for(tiling.tile_cells + 2 * tiling.overlap_cells)},
        "tiles": {"planned": int(np.prod(plan.tile_range)), "with_points": int(np.sum(counts > 0)),
                  "below_min_points": int(np.sum(counts < tiling.min_points)),
                  "points_min": int(counts.min()) if len(counts) else 0,
                  "points_median": float(np.median(counts)) if len(counts) else 0.0,
                  "points_max": int(counts.max()) if len(counts) else 0,
                  "overlap_points": read - int(scan["points"]) if len(counts) else 0},
        "memory": {"peak_bytes": peak["peak"] if peak else 0.0, "peak_tile": peak["tile"] if peak else None,
                   "median_bytes": float(np.median([e["peak"] for e in est])) if est else 0.0},
        "time": {"cpu_seconds": cpu_s, "workers": n_workers, "cores": cores, "wall_seconds": wall_s,
                 "in_process": workers == 0},
        "estimates": est, "noise_treatment": noise, "presets": preset_times,
    }


def job_wall_time(estimates: list[dict], n_points: int, workers: int) -> float:
    """Estimated wall time of the job: the cluster's start, the partition pass, every tile's solve and mesh step
    on ``workers`` one-thread workers (costliest first, as the job submits them) and the weld."""
    from tiled_gridpull import memory as m

    tasks = [e["time_s"] + e.get("mesh_time_s", 0.0) for e in estimates]
    fine_bricks = sum(e["bricks"][-1] for e in estimates)
    return (m.JOB_SETUP_S + n_points * m.RATE_PARTITION_POINT_S + fine_bricks * m.RATE_MERGE_BRICK_S
            + m.makespan(tasks, workers))


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def format_plan(info: dict, max_memory: int | None = None) -> str:
    """The dry run's printout."""
    from tiled_gridpull.memory import format_size

    lat, t, m, tm = info["lattice"], info["tiles"], info["memory"], info["time"]
    cell = lat["cell_size"]
    units = f" ({lat['units']})" if lat.get("units") else ""
    sampled = info.get("index_sample")
    source = (" (partition of the job directory reused)" if info["partition_reused"] else
              f" (tiles estimated from the inputs' index: {sampled:.1%} of the points read)" if sampled is not None
              else "")
    lines = [
        f"dry run: nothing is solved{source}",
        f"input:    {info['points']:,} points{' with sensor origins' if info['has_sensor'] else ''} "
        f"in {len(info['inputs'])} file(s)"
        + (f"; carrying {', '.join(info['attributes'])} onto the vertices" if info.get("attributes") else ""),
        f"lattice:  cell {cell:g}{units}, origin ({', '.join(f'{v:.10g}' for v in lat['origin'])}), "
        f"{' x '.join(str(v - 1) for v in lat['shape'])} cells, {lat['levels']} solver level(s)",
        f"tiles:    {t['with_points']} with points of {t['planned']} planned "
        f"({' x '.join(str(v) for v in lat['tile_range'])}); "
        f"core {lat['tile_cells']} cells ({lat['tile_cells'] * cell:g}), "
        f"overlap {lat['overlap_cells']} cells ({lat['overlap_cells'] * cell:g}) per side{_derived(lat)}"
        + (f", and a halo of {lat['halo_cells']} cells read for denoising" if lat.get("halo_cells") else ""),
        f"points per tile: min {t['points_min']:,}, median {t['points_median']:,.0f}, max {t['points_max']:,} "
        f"({t['overlap_points']:,} copies in overlaps{' and halos' if lat.get('halo_cells') else ''}; "
        f"{t['below_min_points']} tile(s) below min_points)",
        f"memory:   peak per {'tile' if tm.get('in_process') else 'worker'} about {format_size(m['peak_bytes'])} "
        f"(largest tile, {m['peak_tile']}); "
        f"median tile {format_size(m['median_bytes'])} (estimates are upper bounds)",
        f"time:     roughly {_duration(tm['wall_seconds'])} "
        + ("in this process (--workers 0: a tile at a time, on every core) " if tm.get("in_process") else
           f"with {tm['workers']} one-thread worker(s) ")
        + f"({_duration(tm['cpu_seconds'])} of solving on one core), at rates measured on a 2-core Intel Xeon "
        f"(2026-11-24) with nothing else running: a loaded or slower machine takes longer",
    ]
    noise = info.get("noise_treatment")
    if noise and noise.get("auto"):
        given = bool(noise.get("given"))  # the user's own noise settings: nothing was measured or chosen
        what = "" if given else "denoising, " if noise["chosen"] else "no treatment, "
        lines.insert(-3, f"noise:    {what}{noise['reason']}{'' if given else ' (noise_auto)'}")
    presets = info.get("presets") or {}
    if presets:
        chosen = info.get("quality") or "standard"
        parts = [f"{q}{' (this run)' if q == chosen else ''} {_duration(p['wall_seconds'])}"
                 + (f" at cell {p['cell_size']:g}" if p["cell_size"] != cell else "") for q, p in presets.items()]
        lines.append(f"quality:  roughly {', '.join(parts)} (--quality; BENCHMARKS.md, 'Quality presets', has what "
                     f"each costs in accuracy)")
    if max_memory is not None:
        over = [e for e in info["estimates"] if e["peak"] > max_memory]
        lines.append(f"--max-memory {format_size(max_memory)}: "
                     + (f"{len(over)} tile(s) over budget" if over else "every tile fits"))
    return "\n".join(lines)


def _derived(lattice: dict) -> str:
    """What the tile line says about sizes that were not given: they follow the cell size."""
    shown = {"tile_size": "core", "overlap": "overlap"}  # a converted cell size is on the lattice line
    names = [shown[n] for n in lattice.get("derived", []) if n in shown]
    if not names:
        return ""
    return f" ({' and '.join(names)} not given: {'they follow' if len(names) > 1 else 'it follows'} the cell size)"
