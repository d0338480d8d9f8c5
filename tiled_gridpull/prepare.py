"""Preparing a tiled job: scan the inputs, lay the tile plan over them, and partition their points into the job
directory (reused when a finished partition of the same inputs and tile grid is there).

The driver that then solves and meshes the tiles is :mod:`tiled_gridpull.tiled_job`; the files of a job directory
are described in :mod:`tiled_gridpull.jobdir`.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from ._version import __version__
from .errors import ConfigError, InputError
from .cloud import PointCloud
from .io import iter_point_chunks, read_kitti_sequence
from .jobdir import JobPaths, write_manifest
from .outliers import SAMPLE_STRIDE, body_box, describe, far_mask
from .partition import partition
from .resume import load_partition, partition_key, scan_record
from .tile_plan import LatticeSpanError, TilePlan, TileSpec, plan_tiles
from .tiling import AUTO, TilingConfig, auto_cell_size
from .trajectory import Trajectory, read_trajectory

__all__ = ["check_registered", "resolve_units", "scan_inputs", "plan_inputs", "prepare_job"]


def check_registered(inputs: list[str]) -> None:
    """Refuse inputs that are not in one frame: a single KITTI scan (``.bin``) holds points in its own sensor
    frame, so merging it with any other input would overlay scans taken from different places as if they were
    registered. A KITTI sequence directory (its ``poses.txt`` places every frame) is the way to give several.

    Raises
    ------
    InputError
        Naming the scans, when a ``.bin`` scan is one of several inputs.
    """
    scans = [str(p) for p in inputs if Path(p).suffix.lower() == ".bin" and not Path(p).is_dir()]
    if scans and len(inputs) > 1:
        shown = ", ".join(scans[:3]) + (f" and {len(scans) - 3} more" if len(scans) > 3 else "")
        raise InputError(f"{shown}: a KITTI scan file is in its own sensor frame and cannot be merged with other "
                         f"inputs ({len(inputs)} given) without poses; give the sequence directory (velodyne/*.bin "
                         f"with poses.txt) instead, or one scan alone")


#: points ``voxel_size: auto`` reads at least from the start of each input (up to its budget over all of them)
AUTO_MIN_PER_INPUT = 100_000


def resolve_units(inputs: list[str], tiling: TilingConfig, frames=None,
                  chunk_size: int = 2_000_000) -> TilingConfig:
    """``tiling`` with its cell size in the inputs' units: ``auto`` measured from the points, a length with a
    unit (``voxel_size: 0.1 m``) converted; an already resolved config is returned as it is.

    * A unit comes from the CRS in the header of the first input declaring one (no points are read; inputs in
      different CRSs are refused later, by the scan); inputs without a CRS are taken to be in metres.
    * ``auto`` measures the sample spacing (:mod:`tiled_gridpull.spacing`) on about ``chunk_size`` points: the
      first ones of each input in turn (at least ``AUTO_MIN_PER_INPUT`` of each), one region of each scan (a
      scan's density pattern repeats along it), and picks
      :func:`tiled_gridpull.tiling.auto_cell_size`.
    """
    if tiling.resolved:
        return tiling
    if tiling.voxel_unit != AUTO:
        from .crs import linear_unit
        from .io import read_crs

        crs = next((c for c in map(read_crs, inputs) if c), None)
        unit = linear_unit(crs)
        if crs and unit is None and tiling.voxel_unit is not None:
            # taking metres here would silently make a survey in feet 3.3x too fine (or coarse)
            raise ConfigError(f"voxel_size {tiling.voxel_size:g} {tiling.voxel_unit}: the input's CRS "
                              f"({_crs_name(crs)}) does not state its unit in a form this reader understands"
                              f"{_pyproj_hint()}; give voxel_size as a number in the data's units")
        return tiling.in_data_units(unit)
    from .spacing import point_spacing

    # the first points of each input, so a sliver of a first file neither decides the cell nor is "too few"
    per_input = max(chunk_size // len(inputs), AUTO_MIN_PER_INPUT)
    parts, read = [], 0
    for path in inputs:
        head = next(_chunks([path], per_input, frames), None)
        if head is not None and len(head):
            parts.append(head.xyz[:per_input])
            read += len(parts[-1])
        if read >= chunk_size:
            break
    if read < 16:
        raise InputError(f"voxel_size auto: too few points in {', '.join(map(str, inputs))} to measure their "
                         "spacing; give voxel_size")
    sp = point_spacing(np.concatenate(parts))
    cell = auto_cell_size(sp)
    where = f"of {len(parts)} inputs" if len(parts) > 1 else "points"
    note = (f"auto: sample spacing {sp.median:.3g} by point, {sp.area_median:.3g} by area, over "
            f"{sp.measured:,} of the first {sp.points:,} {where}")
    return tiling.with_cell_size(cell, note)


def _pyproj_hint() -> str:
    try:
        import pyproj  # noqa: F401
    except ImportError:
        return " (GeoTIFF keys are read with pyproj: pip install 'tiled-gridpull[geo]')"
    return ""


def scan_inputs(inputs: list[str], chunk_size: int = 2_000_000, frames=None,
                trajectory: Trajectory | None = None) -> dict:
    """One streaming pass: bounds, point count and whether sensor origins are known."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    n = 0
    sample = []
    has_sensor = True
    crs = crs_source = None
    for chunk in _chunks(inputs, chunk_size, frames, trajectory):
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


def _far_points(inputs, chunk_size, frames, box, trajectory=None) -> tuple[np.ndarray | None, np.ndarray | None,
                                                                           int]:
    """One pass: the first point outside ``box`` (for the message; None when none), the bounds of the points
    inside it (None when none), and how many lie outside."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    example, n_far = None, 0
    for chunk in _chunks(inputs, chunk_size, frames, trajectory):
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
    for chunk in chunks:
        far = far_mask(chunk.xyz, box)
        yield chunk.take(np.flatnonzero(~far)) if far.any() else chunk


def _crs_text(crs: str) -> str:
    """A CRS's text without the layout whitespace outside quoted names (WKT pretty-printed or not)."""
    return re.sub(r'\s+(?=(?:[^"]*"[^"]*")*[^"]*$)', "", crs)


def _file_of(source) -> str:
    """The file of a chunk's ``source`` (``path[start:stop]``)."""
    return re.sub(r"\[\d+:\d+\]$", "", str(source))


def _crs_name(crs: str) -> str:
    """A short name for a CRS in a message: the WKT's first quoted name, else its start."""
    m = re.search(r'"([^"]+)"', crs)
    return m.group(1) if m else crs.split("\n")[0][:60]


def _chunks(inputs, chunk_size, frames, trajectory: Trajectory | None = None):
    """The inputs' points chunk by chunk; with a trajectory, every point gets its sensor origin by GPS time."""
    if trajectory is not None:
        for path in inputs:
            projected = None
            for chunk in iter_point_chunks([path], chunk_size, gps_time=True):
                if projected is None:  # an SBET's latitudes and longitudes, into this file's CRS
                    projected = trajectory.projected(chunk.crs)
                chunk.sensor = projected.sensor_at(chunk.attributes.pop("gps_time"), what=str(path))
                yield chunk
        return
    for path in inputs:
        p = Path(path)
        if p.is_dir():
            cloud = read_kitti_sequence(p, frames)
            for s in range(0, len(cloud), chunk_size):
                yield PointCloud(cloud.xyz[s:s + chunk_size], sensor=cloud.sensor[s:s + chunk_size],
                                 source=cloud.source, crs=cloud.crs)
        else:
            yield from iter_point_chunks([p], chunk_size)


def plan_inputs(inputs: list[str], tiling: TilingConfig, *, chunk_size: int = 2_000_000,
                frames=None, trajectory: str | Path | None = None) -> tuple[TilePlan, dict, Callable[[], Iterator]]:
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
    check_registered(inputs)
    traj = read_trajectory(trajectory) if trajectory is not None else None
    scan = scan_inputs(inputs, chunk_size, frames, traj)
    if traj is not None:
        scan["trajectory"] = str(Path(trajectory).resolve())
    sample = scan.pop("sample")
    # the body is only needed to drop far points or to explain a refused span: no quantiles on a plain job
    box = body_box(sample, pad=tiling.tile_size) if tiling.drop_outliers else None

    def chunks():
        raw = _chunks(inputs, chunk_size, frames, traj)
        return _without_far(raw, box) if scan.get("far_points_dropped") else raw

    if tiling.drop_outliers:
        example, inside, n_far = _far_points(inputs, chunk_size, frames, box, traj)
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
        example, _, n_far = _far_points(inputs, chunk_size, frames, box, traj)
        if not n_far:
            raise
        span = str(exc).split(": stray points")[0]
        raise LatticeSpanError(f"{span}: {describe(n_far, scan['points'], box, example)}; drop them with "
                               "--drop-outliers (drop_outliers: true)") from None
    return plan, scan, chunks


def prepare_job(inputs: list[str], tiling: TilingConfig, paths: JobPaths, *, frames=None,
                trajectory: str | Path | None = None, chunk_size: int = 2_000_000,
                check: Callable[[list[TileSpec], dict], None] | None = None) -> tuple[TilePlan, list[TileSpec], dict]:
    """Scan and partition the inputs into tiles; writes the manifest. Returns the plan, tiles and scan facts.

    A finished partition of the same inputs (path, size, mtime) and tile grid in ``paths`` is reused without
    reading the inputs (``scan["partition_reused"]``; see :mod:`tiled_gridpull.resume`).

    ``check(specs, occupancy)``, when given, runs on a counting pass (tiles and their occupied bricks, nothing
    written) before the partition writes its spill files: it refuses a job (e.g. ``--max-memory``) by raising,
    so a refused job leaves no partition behind. It costs one more read of the inputs.
    """
    key = partition_key(inputs, tiling, frames, trajectory)
    reused = load_partition(paths, key, tiling)
    if reused is not None:
        return reused
    paths.manifest.unlink(missing_ok=True)  # the manifest commits a partition: none while one is under way
    plan, scan, chunks = plan_inputs(inputs, tiling, chunk_size=chunk_size, frames=frames, trajectory=trajectory)
    if check is not None:
        occupancy: dict = {}
        check(partition(chunks(), plan, None, scan["has_sensor"], occupancy=occupancy), occupancy)
    specs = partition(chunks(), plan, paths.points(), scan["has_sensor"])
    write_manifest(paths.manifest, plan, specs, {"inputs": [str(Path(p).resolve()) for p in inputs],
                                                 "crs": scan["crs"], "version": __version__,
                                                 "partition_key": key, "scan": scan_record(scan)})
    scan["partition_reused"] = False
    return plan, specs, scan
