"""Up-front estimates of a tile's peak memory and solve time, from the partition alone (nothing is solved).

What a tile solve holds (see :mod:`tiled_gridpull.solver`, :mod:`tiled_gridpull.initial_field`):

* **points** (``N``, before duplicates are dropped): the spill records, float32 and float64 copies, normals,
  the nearest-neighbour cache of the solver (``k`` neighbours per point, int32 index + float32 distance, plus
  the KD-tree's own output while it is built; ``k`` grows to 64 where points are dense) and, while normals are
  estimated, per-neighbourhood covariances for up to 200,000 points at a time;
* **band** per level: the bricks (8^3 vertices) within reach of an occupied brick -- the candidate bricks
  :func:`tiled_gridpull.band.build_band` allocates, an upper bound of the bricks it keeps -- hold the
  float32 state of the optimizer: value (double-buffered), Adam ``m`` and ``v``, the accumulated gradient,
  the TV weights, flags, plus the transfer from the coarser level (slot positions) and the coarser field;
* **queries**: per-iteration arrays of ``queries`` x 16 corner slots and gradients, and the query pool's
  nearest-point indices (``query_pool`` x ``queries``, int32);
* the worker process itself (Python, numpy, numba's compiled kernels, Dask), ``BASE_MB``.

The mesh step of a tile blends its field with those of its solved neighbours (up to 26), so it holds every
one of their finest bands at 5 bytes per vertex slot, plus marching cubes and trimming.

The byte counts per point and per slot below are the arrays the code allocates, rounded up; they were checked
against per-task peak resident memory measured on Dask workers (``peak_rss_mb`` of the solve and mesh summaries)
on the synthetic street: the estimate is an upper bound within about 2x there (see ``tests/test_memory.py``).
Time estimates are rough: a per-query and per-slot rate per iteration, a rate per nearest-point search (the
query pool's, or every iteration's without one) and a per-point set-up cost, measured single-threaded on the
project's 2-core test machine (off by 2x either way elsewhere).
"""

from __future__ import annotations

import heapq
import logging
import math
import re
import sys

import numpy as np

from .config import SolverConfig
from .errors import ConfigError, MemoryBudgetError
from .kernels import BRICK
from .partition import read_occupancy
from .tile_plan import TileSpec
from .tiling import TilingConfig

__all__ = ["parse_size", "band_bricks_bound", "tile_memory", "card_bytes", "tile_time", "mesh_time", "makespan",
           "level_points", "format_size", "estimate_tiles", "MB", "peak_rss_mb", "reset_peak_rss", "check_memory"]

log = logging.getLogger("tiled_gridpull")

MB = 1024 * 1024
BASE_MB = 260.0  # resident size of a Dask worker that has imported and compiled everything (measured 220 MB
#                   in a long-lived virtualenv, ~250 MB in a fresh clone's; kept above both so the estimate bounds)
SLOT = BRICK ** 3
# Bytes per vertex slot of a level's band (measured with tracemalloc, rounded up):
OPT_BYTES_PER_SLOT = 30  # while optimized: d_a, d_b, m, v, qgrad, TV weights (float32), initial values, flags
INIT_BYTES_PER_SLOT = 50  # transfer from the coarser level / initial field: int64 and float64 slot positions
FIELD_BYTES_PER_SLOT = 5  # a stored field (the coarser level, a neighbour's): float32 value + flags
BLEND_BYTES_PER_SLOT = 25  # mesh step, per slot of the tile's own band: marching cubes and its band tables (the NumPy
# blend's int64 vertex indices and masks, about 30 bytes more, went with the blend kernel: the estimate had grown to
# 2.09x the measured mesh peak on the street of tests/test_memory.py)
# Bytes per input point (N, before duplicates are dropped):
POINT_BYTES = 150  # spill records, float32/float64 copies, dedupe sort, normals, index coordinates, Morton order
POINT_BYTES_SENSOR = 40  # sensor origins in the spill record, float32 and float64 copies
KNN_BYTES_PER_NEIGHBOUR = 12  # building the cache: KD-tree output (float32 + uint32) and the int32 copy kept
KNN_KEPT_BYTES_PER_NEIGHBOUR = 8
KNN_MAX = 64
NORMALS_CHUNK = 200_000
NORMALS_BYTES = 750  # per point of a normal-estimation chunk with 16 neighbours: indices, coordinates, covariance
TRIM_BYTES = 60  # mesh step: the tile's points as float64 and their KD-tree
# mesh step of a tile that carries point attributes: the centred float64 copy of its points the interpolation's
# KD-tree is built on (trim's tree is freed by then), plus the attribute records twice (read, then per field);
# counted from the arrays' sizes, not measured
ATTRIBUTE_POINT_BYTES = 24
QUERY_BYTES = 16 * 8 + 16 * 4 + 4 * 4 + 8 + 3 * 4 * 3 + 8 + 4  # slots, grads, losses, centres, q, s, nn
POOL_BYTES_PER_QUERY = 4  # int32 nearest-point index per pooled query
# Card memory (bytes) of a tile's level in a batch on a card (solver_cuda.CudaBackend._iterate_batch), counted from
# the arrays it allocates, not measured: per band slot the field twice, Adam's m and v, the int64 fixed-point
# gradient, the sqrt TV's inverse norms and the flags (4 + 4 + 4 + 4 + 8 + 4 + 1), plus the next level's start,
# upsampled on the card while this level's arrays are alive (float32 per slot of the next band); per point its
# float32 position and normal; per query of the level its pool column (int32 per pool batch), tile index and the
# host-drawn centres and positions; per brick its 27 neighbours (int32) and its cell of the padded brick table.
CARD_BYTES_PER_SLOT = 29
CARD_NEXT_BYTES_PER_SLOT = 4
CARD_POINT_BYTES = 24
CARD_QUERY_BYTES = 4 + 8 + 12
CARD_BRICK_BYTES = 27 * 4 + 4
UNTRACKED = 1.15  # allocations numpy does not see (KD-trees, numba's per-brick buffers) and heap fragmentation
# Rough rates of a job on its default local cluster (one-thread workers, two of them sharing the memory bus),
# fitted by benchmarks/calibrate_time.py (non-negative least squares) to the 32 tiles of four jobs run with
# configs/scene.yaml on a 2-core Intel Xeon, 2026-11-24: the 300k-point demo street, a quarter of the 1M-point grid
# of streets, and the shared AHN3 (0.5 m cells) and Autzen (2 ft) files. A nearest-point search is held at the
# 200 ns measured alone (once per pooled query, or every iteration without a pool: these jobs all pool, so the fit
# cannot see it); then a query costs 85 ns per iteration (drawing, losses, scatter), a band slot 3.4 ns per
# iteration (TV + Adam), a point 51 us of set-up (reading, duplicates, normals, orientation, band building).
# Per tile, measured / estimate stayed within 0.70-1.14, and 0.82-1.30 on 40 tiles of four other jobs (the
# rates of 2026-11-23 overestimated by 1.2-2.7x, after the faster query kernel and nearest-point search). The
# mesh step (blend with the neighbours, marching cubes, trim) costs about 0.4 ms per finest band brick, and the
# weld 30 us per finest band brick of the job.
RATE_QUERY_S = 8.5e-8
RATE_NN_S = 2e-7
RATE_SLOT_S = 3.37e-9
RATE_POINT_S = 5.07e-5
TILE_SETUP_S = 0.0
MESH_SETUP_S = 0.1
RATE_MESH_BRICK_S = 4e-4
JOB_SETUP_S = 4.0  # local cluster start, imports and numba's cached kernels loaded in each worker
RATE_PARTITION_POINT_S = 2.5e-6  # reading, scanning and partitioning, per input point
RATE_MERGE_BRICK_S = 3e-5  # welding the pieces and writing the mesh, per finest band brick of the job
# Denoising (a tiled job with denoise > 0), per point read (halo included), pass and neighbour fetched
# (denoise_neighbors + normals.TIE_EXTRA): 13 us per point and pass with 32 neighbours, measured over the 8 tiles
# of the demo street with 5 cm of range noise on a 2-core AMD EPYC, 2026-11-25 (19-26 us per point for 2 passes).
RATE_DENOISE_NEIGHBOUR_S = 3.2e-7

_SIZE = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*(?:([kmgt])(?:i?b)?|b)?\s*$", re.IGNORECASE)


def parse_size(text: str) -> int:
    """``"2GB"``, ``"1500MB"``, ``"512M"``, ``"1.5g"``, ``"2GiB"`` or a byte count -> bytes (powers of 1024)."""
    m = _SIZE.match(str(text))
    if not m:
        raise ConfigError(f"--max-memory expects a size such as 2GB or 1500MB, got {text!r}")
    value = float(m.group(1)) * 1024 ** " kmgt".index((m.group(2) or " ").lower())
    if not math.isfinite(value) or value < MB:
        raise ConfigError(f"--max-memory must be at least 1MB, got {text!r}")
    return int(value)


def format_size(nbytes: float) -> str:
    """Bytes as a short human string (``1.4 GB``, ``730 MB``)."""
    if nbytes >= 1024 ** 3:
        return f"{nbytes / 1024 ** 3:.1f} GB"
    return f"{nbytes / MB:.0f} MB"


def _dilate(grid: np.ndarray, r: int) -> np.ndarray:
    """Cube dilation of a small boolean grid by ``r`` (separable running max, clipped at the border)."""
    out = grid
    for axis in range(3):
        n = out.shape[axis]
        c = np.cumsum(out.astype(np.int32), axis=axis)
        c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
        i = np.arange(n)
        hi = np.minimum(n, i + r + 1)
        lo = np.maximum(0, i - r)
        out = (np.take(c, hi, axis=axis) - np.take(c, lo, axis=axis)) > 0
    return out


def band_bricks_bound(occupancy: np.ndarray, block_shape, solver: SolverConfig) -> list[int]:
    """Upper bound of the bricks of each level's band (coarsest first): the candidate bricks ``build_band``
    allocates, i.e. occupied bricks (coarsened to the level) dilated by ``ceil((m2 + 1) / 8)`` bricks."""
    cells = max(int(s) - 1 for s in block_shape)
    levels = solver.levels_for(cells)
    occupied = np.argwhere(occupancy)  # once: a dense search of the grid per level was most of a dry run's time
    out = []
    for level in range(levels):
        f = 2 ** (levels - 1 - level)
        st = solver.level_settings(level, levels)
        coarse_shape = [-(-(int(s) - 1) // f) + 1 for s in block_shape]
        bshape = [-(-s // BRICK) for s in coarse_shape]
        idx = np.minimum(occupied // f, np.asarray(bshape) - 1)
        reach = -(-(st.m2 + 1) // BRICK)
        if len(idx) * (2 * reach + 1) ** 3 < int(np.prod(bshape)):
            out.append(_dilated_count(idx, bshape, reach))
            continue
        grid = np.zeros(bshape, bool)
        grid[idx[:, 0], idx[:, 1], idx[:, 2]] = True
        out.append(int(_dilate(grid, reach).sum()))
    return out


def _dilated_count(idx: np.ndarray, shape, r: int) -> int:
    """``_dilate(grid, r).sum()`` for a grid whose set cells ``idx`` (M, 3) are few: the distinct cells of their
    clipped cubes, counted without the dense grid (a tile of a few points in a fine lattice of 40 x 40 x 40
    bricks: a dry run planning 4,000 such tiles took 90 s of cube dilations)."""
    if len(idx) == 0:
        return 0
    d = np.arange(-r, r + 1)
    offsets = np.stack(np.meshgrid(d, d, d, indexing="ij"), axis=-1).reshape(-1, 3)
    cells = (idx[:, None, :] + offsets[None]).reshape(-1, 3)
    shape = np.asarray(shape, np.int64)
    cells = cells[np.all((cells >= 0) & (cells < shape), axis=1)]
    return int(len(np.unique(np.ravel_multi_index(cells.T, tuple(int(v) for v in shape)))))


def _knn_bound(n_points: int, solver: SolverConfig) -> int:
    """The solver's candidate-list size: a power of two in [knn, 64], at most the point count."""
    return int(min(max(KNN_MAX, solver.sampling.knn), max(n_points, 1)))


def tile_memory(spec: TileSpec, occupancy: np.ndarray, solver: SolverConfig, tiling: TilingConfig,
                neighbor_bricks: list[int] | None = None, bricks: list[int] | None = None) -> dict:
    """Estimated peak resident memory (bytes) of a worker solving and meshing one tile.

    Parameters
    ----------
    spec : TileSpec
    occupancy : (BX, BY, BZ) bool
        Occupied bricks of the block (:func:`tiled_gridpull.partition.read_occupancy`).
    neighbor_bricks : list of int, optional
        Finest-level band bound of each neighbour (for the mesh step).
    bricks : list of int, optional
        The tile's own :func:`band_bricks_bound`, when the caller has it already (it is the costly part).

    Returns
    -------
    dict
        ``solve``, ``mesh`` and ``peak`` (bytes), ``bricks`` (per level bound), ``points``.
    """
    n = int(spec.n_points)
    if bricks is None:
        bricks = band_bricks_bound(occupancy, spec.block.shape, solver)
    base = BASE_MB * MB
    points = n * (POINT_BYTES + (POINT_BYTES_SENSOR if spec.has_sensor else 0))
    k = _knn_bound(n, solver)
    phases = [min(n, NORMALS_CHUNK) * NORMALS_BYTES * tiling.normal_neighbors / 16.0]
    prev = 0
    for level, b in enumerate(bricks):
        pool = solver.level_settings(level, len(bricks)).query_pool
        coarser = prev * SLOT * FIELD_BYTES_PER_SLOT
        phases.append(b * SLOT * INIT_BYTES_PER_SLOT + coarser)  # initial values / transfer
        phases.append(n * KNN_BYTES_PER_NEIGHBOUR * k + b * SLOT * FIELD_BYTES_PER_SLOT + coarser)  # NN cache
        phases.append(b * SLOT * OPT_BYTES_PER_SLOT + n * KNN_KEPT_BYTES_PER_NEIGHBOUR * k
                      + solver.sampling.queries * (QUERY_BYTES + pool * POOL_BYTES_PER_QUERY) + coarser)  # iterations
        prev = b
    solve = base + UNTRACKED * (points + max(phases))
    own = bricks[-1]
    fields = (own + sum(neighbor_bricks or [])) * SLOT * FIELD_BYTES_PER_SLOT
    carried = 0
    if getattr(spec, "attributes", ()):
        record = sum(np.dtype(t).itemsize for _, t in spec.attributes)
        carried = n * (ATTRIBUTE_POINT_BYTES + 2 * record)
    mesh = base + UNTRACKED * (fields + own * SLOT * BLEND_BYTES_PER_SLOT + n * TRIM_BYTES + carried)
    return {"solve": float(solve), "mesh": float(mesh), "peak": float(max(solve, mesh)), "bricks": bricks,
            "points": n}


def card_bytes(spec: TileSpec, bricks: list[int], solver: SolverConfig) -> int:
    """Card memory (bytes) a tile takes in a batch on a card: the most any of its levels holds (the batch solves
    its tiles level by level, so a batch takes about the sum of its tiles' figures).

    Parameters
    ----------
    spec : TileSpec
    bricks : list of int
        The tile's band bound per level (:func:`band_bricks_bound`), coarsest first.
    """
    worst = 0.0
    levels = len(bricks)
    for level, b in enumerate(bricks):
        points = level_points(spec, level, levels, solver.sampling.points_per_cell)
        st = solver.level_settings(level, levels, points)
        nxt = bricks[level + 1] if level + 1 < levels else 0
        need = (b * SLOT * CARD_BYTES_PER_SLOT + nxt * SLOT * CARD_NEXT_BYTES_PER_SLOT + b * CARD_BRICK_BYTES
                + points * CARD_POINT_BYTES + st.queries * (st.query_pool * POOL_BYTES_PER_QUERY + CARD_QUERY_BYTES))
        worst = max(worst, need)
    return int(UNTRACKED * worst)


def level_points(spec: TileSpec, level: int, levels: int, cap: int = 0) -> int:
    """Points a level of the tile's solve holds, estimated from the partition alone.

    The finest level holds them all (at most ``cap`` per cell when ``cap > 0``: ``sampling.points_per_cell``);
    a coarser level keeps at most ``COARSE_POINTS_PER_CELL`` per cell
    (:func:`tiled_gridpull.solver.thin_per_cell`), and a surface crosses about ``1.5 (8 / f)^2`` of the ``(8 / f)^3``
    cells of factor ``f`` in each occupied brick of 8^3 fine cells.
    """
    from .solver import COARSE_POINTS_PER_CELL

    # a denoising job's tile solves its block's points, not the halo's it read
    n = int(spec.n_points) - int(getattr(spec, "halo_points", 0) or 0)
    f = 2 ** (levels - 1 - level)
    per_brick = min(1.5 * (BRICK / f) ** 2, (BRICK / f) ** 3)
    cells = max(int(getattr(spec, "occupied_bricks", 0) or 0), 1) * per_brick
    if f == 1:
        return n if cap <= 0 else int(min(n, cap * cells))
    return int(min(n, COARSE_POINTS_PER_CELL * cells))


def tile_time(spec: TileSpec, bricks: list[int], solver: SolverConfig) -> float:
    """Rough seconds (one thread of a 2-worker job) to solve one tile: per level, iterations x (queries + band
    slots) with the queries the level's points give (``queries_per_point``), plus the nearest-point searches
    (the query pool's batches once, or every iteration's), the points' set-up and their denoising passes."""
    from .normals import TIE_EXTRA

    levels = len(bricks)
    cap = solver.sampling.points_per_cell
    t = TILE_SETUP_S + (level_points(spec, levels - 1, levels, cap) if cap > 0 else spec.n_points) * RATE_POINT_S
    noise = solver.noise
    if noise.denoise_passes > 0:
        t += noise.denoise_passes * spec.n_points * (noise.denoise_neighbors + TIE_EXTRA) * RATE_DENOISE_NEIGHBOUR_S
    for level, b in enumerate(bricks):
        st = solver.level_settings(level, levels, level_points(spec, level, levels, cap))
        it, nq = st.iterations, st.queries
        searched = (st.query_pool or it) * nq
        t += it * (nq * RATE_QUERY_S + b * SLOT * RATE_SLOT_S) + searched * RATE_NN_S
    return t


def mesh_time(bricks: int) -> float:
    """Rough seconds of a tile's mesh step (blend with its neighbours, marching cubes, trim) from its finest band
    bound (bricks)."""
    return MESH_SETUP_S + bricks * RATE_MESH_BRICK_S


def makespan(durations: list[float], workers: int) -> float:
    """Finish time of ``durations`` on ``workers`` when the longest start first (the job's order)."""
    load = [0.0] * max(1, int(workers))
    for d in sorted(durations, reverse=True):
        heapq.heapreplace(load, load[0] + d)
    return max(load)


def estimate_tiles(specs: list[TileSpec], solver: SolverConfig, tiling: TilingConfig,
                   occupancy: dict | None = None) -> list[dict]:
    """Memory and rough time estimates of every tile (in ``specs`` order), from the partition alone.

    ``occupancy`` maps tile index -> occupied-brick mask (a dry run's in-memory partition); by default each
    tile's mask is read from beside its spill file.
    """
    bricks = {}
    for s in specs:
        occ = occupancy[s.index] if occupancy is not None else read_occupancy(s)
        bricks[s.index] = (occ, band_bricks_bound(occ, s.block.shape, solver))
    out = []
    for s in specs:
        occ, b = bricks[s.index]
        i, j, k = s.index
        nb = [bricks[(i + di, j + dj, k + dk)][1][-1] for di in (-1, 0, 1) for dj in (-1, 0, 1)
              for dk in (-1, 0, 1) if (di, dj, dk) != (0, 0, 0) and (i + di, j + dj, k + dk) in bricks]
        est = tile_memory(s, occ, solver, tiling, nb, bricks=b)
        est["tile"] = s.name
        est["time_s"] = tile_time(s, est["bricks"], solver)
        est["mesh_time_s"] = mesh_time(est["bricks"][-1])
        out.append(est)
    return out


def check_memory(specs: list[TileSpec] | None, tiling: TilingConfig, solver: SolverConfig, budget: int,
                 occupancy: dict | None = None, estimates: list[dict] | None = None) -> list[dict]:
    """Refuse (one line, before any solve) tiles whose estimated peak memory exceeds ``budget`` bytes.

    ``estimates`` (from :func:`tiled_gridpull.memory.estimate_tiles`) are computed from ``specs`` if not given.
    """
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


def peak_rss_mb() -> float:
    """Peak resident memory of this process (MB) since :func:`reset_peak_rss` (Linux), else since it started."""
    import resource  # POSIX only: imported where it is used

    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def reset_peak_rss() -> bool:
    """Restart the peak-memory count of this process at its current size (Linux ``clear_refs``), so that the
    peak a task reports is its own and not that of an earlier task of the same worker. False if unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False
