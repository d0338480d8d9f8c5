"""The partition pass: stream the input's points into per-tile spill files, and read them back.

Spill files hold each tile's points as float32 coordinates relative to the block's low corner (tile-local
metres, where float32 keeps micrometres; float64 in a denoising job, whose tiles must agree exactly), plus the
sensor origin of every point when it is known (record layouts: :func:`tiled_gridpull.jobdir.spill_record`).
"""

from __future__ import annotations

import hashlib
import io
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from .io.atomic import atomic_open, naming, open_no_follow, replace_file
from .jobdir import spill_record
from .kernels import BRICK
from .tile_plan import TilePlan, TileSpec

__all__ = ["partition", "merge_segments", "read_occupancy", "read_tile_points", "read_tile_attributes",
           "attribute_record"]



def partition(chunks: Iterable, plan: TilePlan, out_dir: str | Path | None, has_sensor: bool,
              flush_points: int = 2_000_000, occupancy: dict | None = None,
              only: tuple[int, int, int] | None = None, attributes: list | tuple = ()) -> list[TileSpec]:
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
    only : (i, j, k), optional
        Write this tile alone and ignore the chunks' points in other tiles: one tile's task reading its region
        of an indexed input (:mod:`tiled_gridpull.indexed_inputs`). Its spill file is the one a whole partition
        of the same stream writes for it, byte for byte.
    attributes : list of (name, numpy type string)
        Per-point attributes of the chunks to keep (:func:`tiled_gridpull.attributes.attribute_layout`): each
        tile also gets ``<tile>.attrs``, one record of them per point of its spill file, in the same order.

    Returns
    -------
    list of TileSpec
        Tiles that received at least one point, with counts, spill paths and the SHA-256 of each spill file.
    """
    write = out_dir is not None
    out = Path(out_dir) if write else None
    if write:
        out.mkdir(parents=True, exist_ok=True)
    exact = plan.exact_offsets
    dtype = spill_record(has_sensor, exact)
    attributes = tuple((str(n), str(t)) for n, t in attributes)
    adtype = attribute_record(attributes)
    attr_buffers: dict[tuple, list] = {}
    attr_hashes: dict[tuple, hashlib._Hash] = {}
    counts: dict[tuple, int] = {}
    halo_counts: dict[tuple, int] = {}
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
            with naming(out / f"{plan.spec(key).name}.points"), open_no_follow(path, "ab") as fh:
                for part in parts:
                    data = part.tobytes()
                    h.update(data)
                    fh.write(data)
        for key, parts in attr_buffers.items():
            h = attr_hashes.setdefault(key, hashlib.sha256())
            if not write:
                for part in parts:
                    h.update(part.tobytes())
                continue
            path = tmp_paths.setdefault(("attrs", key), out / f".{plan.spec(key).name}.attrs.partial")
            with naming(out / f"{plan.spec(key).name}.attrs"), open_no_follow(path, "ab") as fh:
                for part in parts:
                    data = part.tobytes()
                    h.update(data)
                    fh.write(data)
        buffers.clear()
        attr_buffers.clear()
        buffered = 0

    started = False
    for chunk in chunks:
        if not started and write:
            # other tiles' tasks may be writing beside a one-tile partition: remove only its own leftovers
            for kind in ("points", "attrs"):
                pattern = f".{plan.spec(only).name}.{kind}.partial" if only is not None else f".*.{kind}.partial"
                for stale in out.glob(pattern):
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
        # by tile, then by row: a tile's points keep the stream's order whatever the chunks (tiles_of lists the
        # pairs by block corner, not by row), so a stream cut anywhere -- in chunks, in segments partitioned
        # apart, or read back by region from an index -- gives the same spill files
        order = np.lexsort((pidx, key_arr))
        key_sorted = key_arr[order]
        starts = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
        ends = np.r_[starts[1:], len(order)]
        for s, e in zip(starts, ends):
            t = tuple(int(v) for v in tiles[order[s]])
            if only is not None and t != only:
                continue
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
            if exact:
                # the points read for the denoising halo only (what the solve crops them to: tile_solve._denoise)
                halo_counts[t] = halo_counts.get(t, 0) + int((~spec.in_block(rec["xyz"])).sum())
            buffers.setdefault(t, []).append(rec)
            if attributes:
                arec = np.empty(len(sel), adtype)
                for name, _ in attributes:
                    arec[name] = chunk.attributes[name][sel]
                attr_buffers.setdefault(t, []).append(arec)
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
            if attributes:
                replace_file(tmp_paths[("attrs", t)], final.with_suffix(".attrs"))
            path = str(final)
            write_occupancy(final.with_suffix(".occ.npy"), grid)
        if occupancy is not None:
            occupancy[t] = grid
        specs.append(plan.spec(t, n_points=counts[t], points_path=path, has_sensor=has_sensor,
                               points_sha256=hashes[t].hexdigest(), occupied_bricks=int(grid.sum()),
                               halo_points=halo_counts.get(t, 0), attributes=attributes,
                               attributes_sha256=attr_hashes[t].hexdigest() if attributes else ""))
    return specs


def merge_segments(parts: list[list[TileSpec]], plan: TilePlan, out_dir: str | Path | None, has_sensor: bool,
                   occupancy: dict | None = None, part_occupancy: list[dict] | None = None,
                   attributes: list | tuple = ()) -> list[TileSpec]:
    """Join the partitions of consecutive segments of the input stream (each written by :func:`partition` into
    a directory of its own, in stream order) into the partition of the whole stream.

    A tile's spill file is its segments' files concatenated in order: :func:`partition` keeps every tile's
    points in stream order whatever the chunks, so the result is byte for byte the one pass's. The segments'
    files are removed.

    Parameters
    ----------
    parts : list of list of TileSpec
        What :func:`partition` returned for each segment, in stream order.
    out_dir : path or None
        The job's points directory; None joins counts only (``part_occupancy`` then gives the masks).
    occupancy : dict, optional
        Filled with the joined masks, as :func:`partition` fills it.
    part_occupancy : list of dict, optional
        Each segment's masks (a counting pass, nothing on disk); by default read beside the segments' files.
    attributes : list of (name, numpy type string)
        The attribute layout the segments were partitioned with: their ``.attrs`` files are joined alike.
    """
    attributes = tuple((str(n), str(t)) for n, t in attributes)
    by_tile: dict[tuple, list[tuple[int, TileSpec]]] = {}
    for k, specs in enumerate(parts):
        for spec in specs:
            by_tile.setdefault(spec.index, []).append((k, spec))
    out = Path(out_dir) if out_dir is not None else None
    merged = []
    for t in sorted(by_tile):
        pieces = by_tile[t]
        grid = None
        for k, piece in pieces:
            g = part_occupancy[k][t] if part_occupancy is not None else read_occupancy(piece)
            grid = g.copy() if grid is None else grid | g
        n = sum(piece.n_points for _, piece in pieces)
        spec = plan.spec(t)
        # a counting pass hashed each segment's records apart: the hash of their join is not known there
        path, digest = "", pieces[0][1].points_sha256 if len(pieces) == 1 else ""
        attr_digest = pieces[0][1].attributes_sha256 if len(pieces) == 1 else ""
        if out is not None:
            final = out / f"{spec.name}.points"
            h = hashlib.sha256()
            with atomic_open(final) as fh:
                for _, piece in pieces:
                    with open(piece.points_path, "rb") as src:
                        for block in iter(lambda: src.read(1 << 22), b""):
                            h.update(block)
                            fh.write(block)
            if attributes:
                ha = hashlib.sha256()
                with atomic_open(final.with_suffix(".attrs")) as fh:
                    for _, piece in pieces:
                        with open(piece.attributes_path, "rb") as src:
                            for block in iter(lambda: src.read(1 << 22), b""):
                                ha.update(block)
                                fh.write(block)
                attr_digest = ha.hexdigest()
            write_occupancy(final.with_suffix(".occ.npy"), grid)
            path, digest = str(final), h.hexdigest()
            for _, piece in pieces:
                Path(piece.points_path).unlink(missing_ok=True)
                Path(piece.occupancy_path).unlink(missing_ok=True)
                if piece.attributes_path:
                    Path(piece.attributes_path).unlink(missing_ok=True)
        if occupancy is not None:
            occupancy[t] = grid
        merged.append(plan.spec(t, n_points=n, points_path=path, has_sensor=has_sensor, points_sha256=digest,
                                occupied_bricks=int(grid.sum()),
                                halo_points=sum(piece.halo_points for _, piece in pieces),
                                attributes=attributes, attributes_sha256=attr_digest if attributes else ""))
    return merged


def write_occupancy(path: Path, grid: np.ndarray) -> None:
    """Write a tile's occupied-brick mask (packed bits, ``.npy``) atomically.

    The ``.npy`` is made in memory and written with the file's own ``write``: ``np.save`` into an open file
    writes through NumPy's C stream, whose short write on a full disk or a file-size limit was silent (a
    truncated mask committed) or an error without a number.
    """
    buf = io.BytesIO()
    np.save(buf, np.packbits(grid.ravel()))
    with atomic_open(path) as fh:
        fh.write(buf.getbuffer())


def read_occupancy(spec: TileSpec) -> np.ndarray:
    """The block's occupied-brick mask written by :func:`partition`: (BX, BY, BZ) bool."""
    bshape = tuple(int(v) for v in -(-np.asarray(spec.block.shape) // BRICK))
    bits = np.load(spec.occupancy_path)
    return np.unpackbits(bits, count=int(np.prod(bshape))).astype(bool).reshape(bshape)


def attribute_record(attributes) -> np.dtype:
    """The record of an attribute spill file: one field per ``(name, numpy type string)`` of ``attributes``."""
    return np.dtype([(str(n), np.dtype(t)) for n, t in attributes])


def read_tile_attributes(spec: TileSpec) -> dict:
    """A tile's per-point attributes (name to (N,) array, the spill file's order); empty when it keeps none."""
    if not spec.attributes:
        return {}
    rec = np.fromfile(spec.attributes_path, dtype=attribute_record(spec.attributes))
    if len(rec) != spec.n_points:
        raise ValueError(f"{spec.attributes_path}: {len(rec)} attribute records for {spec.n_points} points")
    return {name: np.ascontiguousarray(rec[name]) for name, _ in spec.attributes}


def read_tile_points(spec: TileSpec) -> tuple[np.ndarray, np.ndarray | None]:
    """A tile's points and sensor origins as tile-local metres (relative to ``spec.block.low_corner``).

    Returns
    -------
    xyz : (N, 3) float32, or float64 for a denoising job's tile (``spec.exact_offsets``)
    sensor : (N, 3) float32 or None
    """
    dtype = spill_record(spec.has_sensor, spec.exact_offsets)
    rec = np.fromfile(spec.points_path, dtype=dtype)
    xyz = np.ascontiguousarray(rec["xyz"])
    sensor = np.ascontiguousarray(rec["sensor"]) if spec.has_sensor else None
    return xyz, sensor
