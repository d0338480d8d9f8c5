"""The partition pass: stream the input's points into per-tile spill files, and read them back.

Spill files hold each tile's points as float32 coordinates relative to the block's low corner (tile-local
metres, where float32 keeps micrometres), plus the sensor origin of every point when it is known (record
layouts: :data:`tiled_gridpull.jobdir.SPILL_RECORD`, :data:`~tiled_gridpull.jobdir.SPILL_RECORD_SENSOR`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from .io.atomic import atomic_open, open_no_follow, replace_file
from .jobdir import spill_record
from .kernels import BRICK
from .tile_plan import TilePlan, TileSpec

__all__ = ["partition", "read_occupancy", "read_tile_points"]



def partition(chunks: Iterable, plan: TilePlan, out_dir: str | Path | None, has_sensor: bool,
              flush_points: int = 2_000_000, occupancy: dict | None = None) -> list[TileSpec]:
    """Stream point chunks into per-tile spill files (the partition pass).

    Parameters
    ----------
    chunks : iterable of PointCloud
        World coordinates (float64) and, when ``has_sensor``, sensor origins.
    plan : TilePlan
    out_dir : path or None
        Directory for ``<tile>.points`` files (created; existing spill files there are replaced) and their
        ``<tile>.occ.npy`` occupied-brick masks. ``None`` counts only (a dry run): no file is written.
    has_sensor : bool
    flush_points : int
        Buffered (point, tile) pairs before writing to disk: bounds the memory of the pass.
    occupancy : dict, optional
        Filled with ``{tile index: (BX, BY, BZ) bool}``, the bricks of each block that hold a point (what the
        memory estimate reads; also saved beside the spill files).

    Returns
    -------
    list of TileSpec
        Tiles that received at least one point, with counts, spill paths and the SHA-256 of each spill file.
    """
    write = out_dir is not None
    out = Path(out_dir) if write else None
    if write:
        out.mkdir(parents=True, exist_ok=True)
    dtype = spill_record(has_sensor)
    counts: dict[tuple, int] = {}
    buffers: dict[tuple, list] = {}
    hashes: dict[tuple, hashlib._Hash] = {}
    occ: dict[tuple, np.ndarray] = {}
    bshape = tuple(int(v) for v in -(-np.asarray(plan.spec((0, 0, 0)).block.shape) // BRICK))
    buffered = 0
    tmp_paths: dict[tuple, Path] = {}

    def flush() -> None:
        nonlocal buffered
        for key, parts in buffers.items():
            h = hashes.setdefault(key, hashlib.sha256())
            if not write:
                for part in parts:
                    h.update(part.tobytes())
                continue
            path = tmp_paths.setdefault(key, out / f".{plan.spec(key).name}.points.partial")
            with open_no_follow(path, "ab") as fh:
                for part in parts:
                    data = part.tobytes()
                    h.update(data)
                    fh.write(data)
        buffers.clear()
        buffered = 0

    started = False
    for chunk in chunks:
        if not started and write:
            for stale in out.glob(".*.points.partial"):
                stale.unlink()
        started = True
        xyz = np.asarray(chunk.xyz, dtype=np.float64)
        if len(xyz) == 0:
            continue
        # index coordinates relative to the first tile's core corner
        pidx, tiles = plan.tiles_of(plan.lattice.to_index(xyz))
        if len(pidx) == 0:
            continue
        key_arr = (tiles[:, 0] * plan.tile_range[1] + tiles[:, 1]) * plan.tile_range[2] + tiles[:, 2]
        order = np.argsort(key_arr, kind="stable")
        key_sorted = key_arr[order]
        starts = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
        ends = np.r_[starts[1:], len(order)]
        for s, e in zip(starts, ends):
            t = tuple(int(v) for v in tiles[order[s]])
            sel = pidx[order[s:e]]
            spec = plan.spec(t)
            corner = spec.block.low_corner
            rec = np.empty(len(sel), dtype)
            rec["xyz"] = xyz[sel] - corner
            if has_sensor:
                rec["sensor"] = np.asarray(chunk.sensor, dtype=np.float64)[sel] - corner
            # the cells the solver will see (tile-local float32 / cell size), as bricks
            cells = np.floor(rec["xyz"].astype(np.float64) / spec.block.cell_size).astype(np.int64)
            cells = cells[np.all((cells >= 0) & (cells < np.asarray(spec.block.shape) - 1), axis=1)] >> 3
            grid = occ.get(t)
            if grid is None:
                grid = occ[t] = np.zeros(bshape, bool)
            grid[cells[:, 0], cells[:, 1], cells[:, 2]] = True
            buffers.setdefault(t, []).append(rec)
            counts[t] = counts.get(t, 0) + len(sel)
            buffered += len(sel)
        if buffered >= flush_points:
            flush()
    flush()
    specs = []
    for t in sorted(counts):
        spec = plan.spec(t)
        grid = occ[t]
        path = ""
        if write:
            final = out / f"{spec.name}.points"
            replace_file(tmp_paths[t], final)
            path = str(final)
            with atomic_open(final.with_suffix(".occ.npy")) as fh:
                np.save(fh, np.packbits(grid.ravel()))
        if occupancy is not None:
            occupancy[t] = grid
        specs.append(plan.spec(t, n_points=counts[t], points_path=path, has_sensor=has_sensor,
                               points_sha256=hashes[t].hexdigest(), occupied_bricks=int(grid.sum())))
    return specs


def read_occupancy(spec: TileSpec) -> np.ndarray:
    """The block's occupied-brick mask written by :func:`partition`: (BX, BY, BZ) bool."""
    bshape = tuple(int(v) for v in -(-np.asarray(spec.block.shape) // BRICK))
    bits = np.load(spec.occupancy_path)
    return np.unpackbits(bits, count=int(np.prod(bshape))).astype(bool).reshape(bshape)


def read_tile_points(spec: TileSpec) -> tuple[np.ndarray, np.ndarray | None]:
    """A tile's points and sensor origins as tile-local float32 metres (relative to ``spec.block.low_corner``).

    Returns
    -------
    xyz : (N, 3) float32
    sensor : (N, 3) float32 or None
    """
    dtype = spill_record(spec.has_sensor)
    rec = np.fromfile(spec.points_path, dtype=dtype)
    xyz = np.ascontiguousarray(rec["xyz"])
    sensor = np.ascontiguousarray(rec["sensor"]) if spec.has_sensor else None
    return xyz, sensor
