"""Preparing a tiled job: scan the inputs, lay the tile plan over them, and partition their points into the job
directory (reused when a finished partition of the same inputs and tile grid is there).

The driver that then solves and meshes the tiles is :mod:`tiled_gridpull.tiled_job`; the files of a job directory
are described in :mod:`tiled_gridpull.jobdir`.
"""

from __future__ import annotations

import logging
import shutil
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._version import __version__
from .attributes import attribute_layout, select_attributes
from .config import SCAN_NOISE_SETTINGS, SolverConfig
from .crs import check_same_crs, crs_name
from .errors import ConfigError, InputError
from .cloud import PointCloud, degenerate_error, stream_degeneracy
from .io import iter_point_chunks, iter_row_chunks
from .io.kitti import kitti_chunks
from .io.indexed import indexed_kind
from .io.remote import is_url, recorded, shown
from .jobdir import JobPaths, write_manifest
from .outliers import SAMPLE_STRIDE, body_box, describe, far_mask
from .indexed_inputs import (all_indexed, candidate_tiles, indexed_degeneracy, indexed_sources, plan_indexed,
                             read_tile)
from .partition import merge_segments, partition
from .resume import load_partition, partition_key, scan_record
from .tile_plan import LatticeSpanError, TilePlan, TileSpec, plan_tiles
from .tiling import AUTO, TilingConfig, auto_cell_size, with_halo
from .trajectory import Trajectory, read_trajectory

log = logging.getLogger("tiled_gridpull")

__all__ = ["check_registered", "resolve_units", "head_points", "scan_noise_treatment", "scan_inputs", "plan_inputs",
           "prepare_job", "Segment", "plan_segments", "scan_segment", "partition_segment", "SEGMENT_POINTS"]


def check_registered(inputs: list[str]) -> None:
    """Refuse inputs that are not in one frame: a single KITTI scan (``.bin``) holds points in its own sensor
    frame, so merging it with any other input would overlay scans taken from different places as if they were
    registered. A KITTI sequence directory (its ``poses.txt`` and ``calib.txt`` place every frame) is the way to give
    several.

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
                         f"with poses.txt and calib.txt) instead, or one scan alone")


def check_remote(inputs: list[str], trajectory=None, tiling: TilingConfig | None = None) -> None:
    """Refuse URL inputs that would have to be streamed whole: only COPC files and EPTs are read from a web
    server (by region, through their index), and only when every input is one and nothing needs every point on
    the driver (a trajectory, ``drop_outliers``).

    Raises
    ------
    InputError
        Naming the first URL and what to do instead (download it).
    """
    urls = [p for p in inputs if is_url(p)]
    if not urls:
        return
    plain = [p for p in inputs if indexed_kind(p) is None]
    if plain and plain[0] in urls:
        raise InputError(f"{shown(plain[0])}: only COPC files and EPTs are read from a URL (by region, through their "
                         "index); download it and give its path")
    why = (f"{plain[0]}, given with it, is not a COPC file or an EPT" if plain else
           "--trajectory reads every point's GPS time on the driver" if trajectory is not None else
           "drop_outliers reads every point on the driver" if tiling is not None and tiling.drop_outliers else
           None)
    if why:
        raise InputError(f"{shown(urls[0])}: a URL is read tile by tile through its index, but {why}; download the "
                         "files and give their paths")


#: points ``voxel_size: auto`` reads at least from the start of each input (up to its budget over all of them)
AUTO_MIN_PER_INPUT = 100_000


def resolve_units(inputs: list[str], tiling: TilingConfig, frames=None,
                  chunk_size: int = 2_000_000, cell_scale: float = 1.0) -> TilingConfig:
    """``tiling`` with its cell size in the inputs' units: ``auto`` measured from the points, a length with a
    unit (``voxel_size: 0.1 m``) converted; an already resolved config is returned as it is.

    * A unit comes from the CRS in the header of the first input declaring one (no points are read; inputs in
      different CRSs are refused later, by the scan); inputs without a CRS are taken to be in metres.
    * ``auto`` measures the sample spacing (:mod:`tiled_gridpull.spacing`) on about ``chunk_size`` points: the
      first ones of each input in turn (at least ``AUTO_MIN_PER_INPUT`` of each), one region of each scan (a
      scan's density pattern repeats along it), and picks
      :func:`tiled_gridpull.tiling.auto_cell_size`, times ``cell_scale`` (a quality preset's,
      :data:`tiled_gridpull.config.QUALITY_CELL_SCALE`) before its rounding.
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
                              f"({crs_name(crs)}) does not state its unit in a form this reader understands"
                              f"{_pyproj_hint()}; give voxel_size as a number in the data's units")
        return tiling.in_data_units(unit)
    from .spacing import point_spacing

    head, parts = head_points(inputs, frames, chunk_size)
    if len(head) < 16:
        raise InputError(f"voxel_size auto: too few points in {', '.join(map(shown, inputs))} to measure their "
                         "spacing; give voxel_size")
    sp = point_spacing(head)
    cell = auto_cell_size(sp, cell_scale)
    where = f"of {parts} inputs" if parts > 1 else "points"
    scaled = f", x {cell_scale:g} for the quality preset" if cell_scale != 1.0 else ""
    note = (f"auto: sample spacing {sp.median:.3g} by point, {sp.area_median:.3g} by area, over "
            f"{sp.measured:,} of the first {sp.points:,} {where}{scaled}")
    return tiling.with_cell_size(cell, note)


def head_points(inputs: list[str], frames=None, budget: int = 2_000_000) -> tuple[np.ndarray, int]:
    """A dense sample of the inputs, the same whatever the tiling: what ``voxel_size: auto`` and tiled mode's
    ``noise_auto`` measure.

    The first points of each input in turn (at least ``AUTO_MIN_PER_INPUT`` of each, ``budget`` in all), so a
    sliver of a first file neither decides alone nor is "too few": a scan's points come in acquisition order,
    one region of it at full density, and its density and noise repeat along it. An indexed input's first points
    are its coarsest level of detail (spread thin over the whole survey), so a region of it at full density is
    read instead.

    Returns
    -------
    points : (M, 3) float64
    inputs_read : int
        How many inputs the sample came from.
    """
    per_input = max(budget // len(inputs), AUTO_MIN_PER_INPUT)
    parts, read = [], 0
    for path in inputs:
        if all_indexed([path]):
            from .indexed_inputs import dense_region

            head = dense_region(path, per_input)
        elif Path(path).is_dir():
            head = _first_frames(Path(path), frames, per_input)
        else:
            head = next(_chunks([path], per_input, frames), None)
        if head is not None and len(head):
            parts.append(head.xyz[:per_input])
            read += len(parts[-1])
        if read >= budget:
            break
    return (np.concatenate(parts) if parts else np.zeros((0, 3))), len(parts)


def _first_frames(root: Path, frames, points: int) -> PointCloud:
    """The first frames of a KITTI sequence holding ``points`` points (frame by frame: a long sequence is not
    read whole for a sample)."""
    parts, n = [], 0
    for chunk in kitti_chunks(root, frames, points):
        parts.append(chunk.xyz)
        n += len(chunk.xyz)
        if n >= points:
            break
    return PointCloud(np.concatenate(parts) if parts else np.zeros((0, 3)))


def scan_noise_treatment(inputs: list[str], tiling: TilingConfig, solver: SolverConfig,
                         frames=None) -> tuple[SolverConfig, dict]:
    """``solver`` with the denoising passes when ``noise.auto`` finds the scan noisy, and what was decided (the
    sidecar's ``noise_treatment``).

    The scatter is measured once for the whole job, on :func:`head_points` (:func:`tiled_gridpull.noise.scan_noise`
    in the job's cells), so every tile gets the same treatment whatever the tiling. The user's choice wins: with
    one of :data:`~tiled_gridpull.config.SCAN_NOISE_SETTINGS` given (or ``noise_auto: false``) nothing is
    measured.
    """
    from .noise import SCAN_NOISY_CELLS, SCAN_TREATMENT, scan_noise

    if not solver.noise.auto:
        return solver, {"auto": False, "chosen": None, "reason": "noise_auto is off"}
    default = SolverConfig()
    given = [name for name in SCAN_NOISE_SETTINGS if solver.get(name) != default.get(name)]
    if given:
        return solver, {"auto": True, "chosen": None, "given": given,
                        "reason": "given: " + ", ".join(f"{name} {solver.get(name)}" for name in given)}
    head, _ = head_points(inputs, frames, NOISE_SAMPLE_POINTS)
    est = scan_noise(head, tiling.voxel_size, solver.noise.denoise_radius)
    q25 = est["q25_cells"]
    noisy = q25 is not None and q25 > SCAN_NOISY_CELLS
    record = {"auto": True, "chosen": "denoise" if noisy else None, "estimate": {**est, "points": int(len(head))},
              "settings": dict(SCAN_TREATMENT) if noisy else {},
              "reason": (f"too few planar neighbourhoods within {est['radius_cells']:g} cells to measure the "
                         f"scatter ({est['planar']:,} of {est['sampled']:,})" if q25 is None else
                         f"scatter across planes (25th percentile) {q25:.3f} cells "
                         f"{'>' if noisy else '<='} {SCAN_NOISY_CELLS}")}
    if not noisy:
        return solver, record
    log.info("the scan looks noisy (scatter across planes %.3f cells, above %.3g): denoising it "
             "(noise_auto; set noise_auto: false to keep the settings as given)", q25, SCAN_NOISY_CELLS)
    chosen = solver.replace(**SCAN_TREATMENT)
    try:
        with_halo(tiling, chosen)
    except ConfigError as err:
        raise ConfigError(f"{err} (noise_auto chose denoising for a scatter of {q25:.3f} cells; set noise_auto: "
                          "false to leave the points as they are)") from None
    return chosen, record


#: points read from the start of the inputs to measure a scan's noise
NOISE_SAMPLE_POINTS = 1_000_000


def _pyproj_hint() -> str:
    try:
        import pyproj  # noqa: F401
    except ImportError:
        return " (GeoTIFF keys are read with pyproj: pip install 'tiled-gridpull[geo]')"
    return ""


def scan_inputs(inputs: list[str], chunk_size: int = 2_000_000, frames=None,
                trajectory: Trajectory | None = None) -> dict:
    """One streaming pass: bounds, point count and whether sensor origins are known."""
    return _joined_scan([_scan(_chunks(inputs, chunk_size, frames, trajectory))], inputs)


def _scan(chunks) -> dict:
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    n = 0
    sample = []
    has_sensor = True
    attrs: dict | None = None  # name -> type of the attributes every chunk so far has
    crs = crs_source = bare_source = None  # the first chunk declaring a CRS, and the first declaring none
    for chunk in chunks:
        if chunk.crs:
            if crs is None:
                crs, crs_source = chunk.crs, chunk.source
            check_same_crs([(crs, crs_source), (chunk.crs, chunk.source)])
        elif bare_source is None:
            bare_source = chunk.source
        if crs is not None and bare_source is not None:
            check_same_crs([(crs, crs_source), (None, bare_source)])
        if len(chunk) == 0:
            continue
        lo = np.minimum(lo, chunk.xyz.min(axis=0))
        hi = np.maximum(hi, chunk.xyz.max(axis=0))
        n += len(chunk)
        has_sensor &= chunk.sensor is not None
        mine = dict(attribute_layout(select_attributes(chunk.attributes, "all")))
        attrs = mine if attrs is None else {name: t for name, t in attrs.items() if name in mine}
        # a copy: a strided view would keep every whole chunk alive, i.e. the whole input in memory
        sample.append(chunk.xyz[::SAMPLE_STRIDE].copy())
    return {"lo": lo, "hi": hi, "points": n, "has_sensor": bool(has_sensor), "crs": crs, "crs_source": crs_source,
            "bare_source": bare_source, "sample": sample, "attributes": list((attrs or {}).items())}


def _joined_scan(parts: list[dict], inputs) -> dict:
    """The scan of the whole stream from its segments' scans, in stream order (the same facts, the same refusal
    of a second CRS or of inputs without one, as one pass)."""
    check_same_crs([(p["crs"], p["crs_source"]) for p in parts if p["crs"]]
                   + [(None, p["bare_source"]) for p in parts if p["bare_source"] is not None])
    n = sum(p["points"] for p in parts)
    if n == 0:
        raise InputError(f"{', '.join(map(shown, inputs))}: no points")
    lo = np.min([p["lo"] for p in parts], axis=0)
    hi = np.max([p["hi"] for p in parts], axis=0)
    # the attributes every point has (the first segment's types)
    with_points = [dict(p.get("attributes", [])) for p in parts if p["points"]]
    attrs = [(a, t) for a, t in with_points[0].items() if all(a in w for w in with_points[1:])]
    return {"bounds": np.stack([lo, hi]), "points": n, "attributes": attrs,
            "has_sensor": all(p["has_sensor"] for p in parts if p["points"]),
            "crs": next((p["crs"] for p in parts if p["crs"]), None),
            "sample": np.concatenate([x for p in parts for x in p["sample"]])}


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


def _chunks(inputs, chunk_size, frames, trajectory: Trajectory | None = None):
    """The inputs' points chunk by chunk; with a trajectory, every point gets its sensor origin by GPS time."""
    if trajectory is not None:
        for path in inputs:
            yield from _with_sensor(iter_point_chunks([path], chunk_size, gps_time=True), trajectory, path)
        return
    for path in inputs:
        p = Path(path)
        if p.is_dir():
            # frame by frame (a sequence of thousands of scans is never held whole), cut into the same chunks as
            # the sequence read whole would be: the scan's outlier sample takes every 16th point of each chunk
            yield from _rechunk(kitti_chunks(p, frames, chunk_size), chunk_size, str(p))
        else:
            yield from iter_point_chunks([p], chunk_size)


def _rechunk(clouds, size: int, source: str):
    """``clouds`` (with sensor origins) as consecutive chunks of ``size`` points, the last one shorter; at most
    ``size`` points plus one cloud are held at a time."""
    xyz, sensor, held = [], [], 0
    attrs: dict | None = None  # the per-point attributes every cloud so far has (a KITTI scan's intensity)
    for c in clouds:
        xyz.append(c.xyz)
        sensor.append(c.sensor)
        mine = select_attributes(c.attributes, "all")
        attrs = ({n: [v] for n, v in mine.items()} if attrs is None
                 else {n: parts + [mine[n]] for n, parts in attrs.items() if n in mine})
        held += len(c)
        while held >= size:
            x, o = np.concatenate(xyz), np.concatenate(sensor)
            a = {n: np.concatenate(parts) for n, parts in attrs.items()}
            yield PointCloud(x[:size], sensor=o[:size], source=source, attributes={n: v[:size] for n, v in a.items()})
            xyz, sensor, held = [x[size:]], [o[size:]], held - size
            attrs = {n: [v[size:]] for n, v in a.items()}
    if held:
        yield PointCloud(np.concatenate(xyz), sensor=np.concatenate(sensor), source=source,
                         attributes={n: np.concatenate(parts) for n, parts in (attrs or {}).items()})


def _with_sensor(chunks, trajectory: Trajectory, path):
    """``chunks`` (with their GPS times) with each point's sensor origin from the trajectory."""
    projected = None
    for chunk in chunks:
        if projected is None:  # an SBET's latitudes and longitudes, into this file's CRS
            projected = trajectory.projected(chunk.crs)
        chunk.sensor = projected.sensor_at(chunk.attributes.pop("gps_time"), what=str(path))
        yield chunk


# ------------------------------------------------------------------------------ the partition run in segments

#: points of a LAS/LAZ file one partition task reads at most (a multiple of the chunk size is used)
SEGMENT_POINTS = 4_000_000


@dataclass(frozen=True)
class Segment:
    """Rows ``[start, stop)`` of one input, in file order; ``start`` None: the whole input, as it streams."""

    path: str
    start: int | None = None
    stop: int | None = None


def plan_segments(inputs: list[str], chunk_size: int = 2_000_000,
                  segment_points: int = SEGMENT_POINTS) -> list[Segment]:
    """The input stream cut into consecutive segments, one task each: a LAS/LAZ file of more than
    ``segment_points`` points is cut at multiples of ``chunk_size`` rows (its header's count; LAZ seeks through
    its chunk table); any other input (and a COPC file, whose chunks vary) is one segment."""
    from .io import point_count

    step = max(chunk_size, segment_points // chunk_size * chunk_size)
    out = []
    for path in inputs:
        p = Path(path)
        if p.is_dir() or p.suffix.lower() not in (".las", ".laz") or all_indexed([path]):
            out.append(Segment(str(path)))
            continue
        n = point_count(p)
        if n <= step:
            out.append(Segment(str(path)))
        else:
            out += [Segment(str(path), s, min(s + step, n)) for s in range(0, n, step)]
    return out


def _segment_chunks(seg: Segment, chunk_size: int, frames, trajectory: Trajectory | None):
    if seg.start is None:
        yield from _chunks([seg.path], chunk_size, frames, trajectory)
        return
    chunks = iter_row_chunks(seg.path, seg.start, seg.stop, chunk_size, gps_time=trajectory is not None)
    yield from (_with_sensor(chunks, trajectory, seg.path) if trajectory is not None else chunks)


def scan_segment(seg: Segment, chunk_size: int, frames=None, trajectory: Trajectory | None = None) -> dict:
    """One task of the scan run in segments: :func:`scan_inputs`'s facts of one segment (not yet checked for
    emptiness; the CRS of its first chunk declaring one)."""
    return _scan(_segment_chunks(seg, chunk_size, frames, trajectory))


def partition_segment(seg: Segment, plan: TilePlan, out_dir: str | None, has_sensor: bool, chunk_size: int,
                      frames=None, trajectory: Trajectory | None = None,
                      attributes: list | tuple = ()) -> tuple[list[TileSpec], dict | None]:
    """One task of the partition run in segments: :func:`~tiled_gridpull.partition.partition` of the segment's
    points into ``out_dir`` (its own directory), or counted only (``out_dir`` None; its masks returned)."""
    occupancy: dict | None = {} if out_dir is None else None
    specs = partition(_segment_chunks(seg, chunk_size, frames, trajectory), plan, out_dir, has_sensor,
                      occupancy=occupancy, attributes=attributes if out_dir is not None else ())
    return specs, occupancy


def plan_inputs(inputs: list[str], tiling: TilingConfig, *, chunk_size: int = 2_000_000,
                frames=None, trajectory: str | Path | None = None,
                segments: list[Segment] | None = None,
                run_tasks: Callable | None = None) -> tuple[TilePlan, dict, Callable[[], Iterator]]:
    """Scan the inputs and lay the tile plan over them (the job's and ``--dry-run``'s first step).

    Identical or collinear points are refused as one-shape mode refuses them
    (:func:`~tiled_gridpull.cloud.stream_degeneracy`); coplanar ones are a legal scene.

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

    With ``segments`` (:func:`plan_segments`) and ``run_tasks`` (as :func:`prepare_job`'s), the scan runs as
    one task per segment; the facts are the same as one pass's.
    """
    check_registered(inputs)
    traj = read_trajectory(trajectory) if trajectory is not None else None
    if segments is not None and run_tasks is not None:
        scan = _joined_scan(run_tasks(scan_segment, [(seg, chunk_size, frames, traj) for seg in segments]), inputs)
    else:
        scan = scan_inputs(inputs, chunk_size, frames, traj)
    if traj is not None:
        scan["trajectory"] = str(Path(trajectory).resolve())
    scan["attributes"] = carried_layout(scan.get("attributes", []), tiling.attributes)
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
                raise InputError(f"{', '.join(map(shown, inputs))}: drop_outliers would drop every point")
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
    # one-shape mode's rule (coplanar points are a legal scene: a flat parking lot); a sample that is not
    # degenerate settles it, so only a degenerate-looking input is read again. After the span: a stray point
    # far away makes the rest look collinear, and the span's refusal names it
    kind = stream_degeneracy(lambda: (c.xyz for c in chunks()), reject_planar=False,
                             sample=None if scan.get("far_points_dropped") else sample)  # it holds them
    if kind is not None:
        raise degenerate_error(", ".join(map(shown, inputs)), scan["points"], kind)
    return plan, scan, chunks


def carried_layout(layout: list, mode: str) -> list[tuple[str, str]]:
    """Of the attribute ``layout`` (``[(name, numpy type string)]``) the inputs have, those ``--attributes mode``
    carries (:func:`~tiled_gridpull.attributes.select_attributes`)."""
    dummy = {str(n): np.zeros(0, np.dtype(t)) for n, t in layout}
    return [(n, str(t)) for n, t in layout if n in select_attributes(dummy, mode)]


def prepare_job(inputs: list[str], tiling: TilingConfig, paths: JobPaths, *, frames=None,
                trajectory: str | Path | None = None, chunk_size: int = 2_000_000,
                check: Callable[[list[TileSpec], dict], None] | None = None,
                run_tasks: Callable[[Callable, list[tuple]], list] | None = None,
                segment_points: int | None = None) -> tuple[TilePlan, list[TileSpec], dict]:
    """Scan and partition the inputs into tiles; writes the manifest. Returns the plan, tiles and scan facts.

    A finished partition of the same inputs (path, size, mtime) and tile grid in ``paths`` is reused without
    reading the inputs (``scan["partition_reused"]``; see :mod:`tiled_gridpull.resume`).

    ``check(specs, occupancy)``, when given, runs on a counting pass (tiles and their occupied bricks, nothing
    written) before the partition writes its spill files: it refuses a job (e.g. ``--max-memory``) by raising,
    so a refused job leaves no partition behind. It costs one more read of the inputs.

    Indexed inputs (COPC, EPT; :mod:`tiled_gridpull.indexed_inputs`) are planned from their headers, and each
    tile's points are read by a task of its own: ``run_tasks(fn, argument_tuples)`` runs them (on the
    executor's workers; in this process by default) and returns their results in order. There ``check`` runs
    after the reads (with ``occupancy`` None: the masks are on disk), and a refusal removes the spill files.

    Other inputs stream, and with ``run_tasks`` the stream is cut into segments (:func:`plan_segments`: LAS/LAZ
    files by ``segment_points`` rows, :data:`SEGMENT_POINTS` by default) whose scan and partition run as tasks,
    each segment into a directory of its own; the driver joins them
    (:func:`~tiled_gridpull.partition.merge_segments`) into the very files one pass writes. ``drop_outliers``
    keeps the one pass.
    """
    check_remote(inputs, trajectory, tiling)
    key = partition_key(inputs, tiling, frames, trajectory)
    reused = load_partition(paths, key, tiling)
    if reused is not None:
        return reused
    paths.manifest.unlink(missing_ok=True)  # the manifest commits a partition: none while one is under way
    segments = (plan_segments(inputs, chunk_size, segment_points or SEGMENT_POINTS) if run_tasks is not None
                else [])
    shutil.rmtree(paths.points() / ".segments", ignore_errors=True)  # a stopped run's segment files
    if all_indexed(inputs) and trajectory is None and not tiling.drop_outliers:
        plan, scan, specs = _uncommitted_on_failure(paths, _read_indexed, inputs, tiling, paths, check, run_tasks)
    elif len(segments) > 1 and not tiling.drop_outliers:
        plan, scan, specs = _uncommitted_on_failure(paths, _partition_in_segments, inputs, tiling, paths, segments,
                                                    chunk_size, frames, trajectory, check, run_tasks)
    else:
        plan, scan, chunks = plan_inputs(inputs, tiling, chunk_size=chunk_size, frames=frames,
                                         trajectory=trajectory)
        if check is not None:
            occupancy: dict = {}
            check(partition(chunks(), plan, None, scan["has_sensor"], occupancy=occupancy), occupancy)
        specs = partition(chunks(), plan, paths.points(), scan["has_sensor"], attributes=scan["attributes"])
    write_manifest(paths.manifest, plan, specs, {"inputs": [recorded(p) for p in inputs],
                                                 "crs": scan["crs"], "version": __version__,
                                                 "partition_key": key, "scan": scan_record(scan)})
    scan["partition_reused"] = False
    return plan, specs, scan


def _uncommitted_on_failure(paths: JobPaths, fn, *args):
    """``fn(*args)``; when it fails (a task's error, a refusal), the points directory it was filling goes: no
    manifest commits it, and tiles already written by other tasks would only be left behind."""
    try:
        return fn(*args)
    except BaseException:
        shutil.rmtree(paths.points(), ignore_errors=True)
        raise


def _partition_in_segments(inputs, tiling, paths: JobPaths, segments, chunk_size, frames, trajectory, check,
                           run_tasks):
    """The scan and the partition as one task per segment of the stream, joined in stream order."""
    plan, scan, _ = plan_inputs(inputs, tiling, chunk_size=chunk_size, frames=frames, trajectory=trajectory,
                                segments=segments, run_tasks=run_tasks)
    traj = read_trajectory(trajectory) if trajectory is not None else None
    has_sensor = scan["has_sensor"]
    if check is not None:
        counted = run_tasks(partition_segment, [(seg, plan, None, has_sensor, chunk_size, frames, traj)
                                                for seg in segments])
        occupancy: dict = {}
        check(merge_segments([c[0] for c in counted], plan, None, has_sensor, occupancy=occupancy,
                             part_occupancy=[c[1] for c in counted]), occupancy)
    out = paths.points()
    parts = out / ".segments"  # one directory per segment; removed once joined
    shutil.rmtree(parts, ignore_errors=True)
    layout = scan["attributes"]
    written = run_tasks(partition_segment, [(seg, plan, str(parts / str(k)), has_sensor, chunk_size, frames, traj,
                                             layout) for k, seg in enumerate(segments)])
    out.mkdir(parents=True, exist_ok=True)
    specs = merge_segments([w[0] for w in written], plan, out, has_sensor, attributes=layout)
    shutil.rmtree(parts, ignore_errors=True)
    scan["segments"] = len(segments)
    return plan, scan, specs


def _read_indexed(inputs, tiling, paths: JobPaths, check, run_tasks):
    """Plan indexed inputs from their headers and read every candidate tile in a task of its own."""
    sources = indexed_sources(inputs)
    plan, scan, indexes = plan_indexed(inputs, tiling, sources)
    tiles = candidate_tiles(indexes, plan)
    kind = indexed_degeneracy(sources, plan, tiles)  # as plan_inputs refuses streamed inputs
    if kind is not None:
        raise degenerate_error(", ".join(map(shown, inputs)), scan["points"], kind)
    out = paths.points()
    out.mkdir(parents=True, exist_ok=True)
    scan["attributes"] = carried_layout(scan.get("attributes", []), tiling.attributes)
    args = [(sources, plan, t, str(out), scan["attributes"]) for t in tiles]
    results = run_tasks(read_tile, args) if run_tasks is not None else [read_tile(*a) for a in args]
    specs = [s for s, _ in results if s is not None]
    scan["candidate_tiles"] = len(tiles)
    owned = sum(n for _, n in results)
    if owned != scan["points"]:
        # every point has one owner tile, whatever the overlaps copy: fewer means a node no candidate tile read
        # or a node holding fewer points than its hierarchy entry says, more a point read twice
        raise InputError(f"{', '.join(map(shown, inputs))}: the tiles read {owned:,} points, the headers declare "
                         f"{scan['points']:,}: a damaged index")
    if check is not None:
        check(specs, None)  # a refusal leaves no partition behind: _uncommitted_on_failure removes the tiles
    return plan, scan, specs
