"""The report of a tiled job.

Every tiled job (:func:`tiled_gridpull.tiled_job.run_tiled_job`, whichever executor runs its tiles) ends by
writing, in its job directory:

* ``report.json``: the job's settings, lattice, one row per tile (points, solve and mesh time, peak memory,
  first and last loss, faces) and totals. It is built from the same record as the mesh's ``.json`` sidecar
  (:func:`tiled_gridpull.tiled_job.job_metadata`), arranged per tile; nothing is measured twice.
* ``tiles.png``: the tile layout seen from above with per-tile timings (only when matplotlib is importable;
  a picture that cannot be drawn is logged and never fails the job).

Both are written atomically. ``tiled-gridpull report JOBDIR`` prints the report as a table.
:func:`tiled_gridpull.jobview.load_job` opens a job directory (finished or not) for the notebooks.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from .config import recorded_settings
from .errors import InputError
from .io.atomic import write_json
from .io.outputs import MAX_OWN_FILE
from .jobdir import LAYOUT_NAME, REPORT_NAME, sample_job_points

log = logging.getLogger("tiled_gridpull")

__all__ = ["REPORT_NAME", "LAYOUT_NAME", "build_report", "write_report", "read_report", "format_report_table",
           "tile_core_bounds", "TIMING_PHASES"]

REPORT_FORMAT = "tiled_gridpull.report/1"


def tile_core_bounds(lattice: dict, tile_cells: int, index) -> list[list[float]]:
    """World bounding box of a tile's core.

    Parameters
    ----------
    lattice : dict
        The job lattice as written by :meth:`tiled_gridpull.lattice.Lattice.to_dict` (``origin``,
        ``cell_size``, ``offset``: global index of the first tile's core corner).
    tile_cells : int
        Core size in cells.
    index : (3,) int
        Tile index.

    Returns
    -------
    [[x0, y0, z0], [x1, y1, z1]]
        World coordinates (the data's units).
    """
    origin = np.asarray(lattice["origin"], dtype=np.float64)
    cell = float(lattice["cell_size"])
    lo = (np.asarray(lattice.get("offset", (0, 0, 0)), np.int64) + np.asarray(index, np.int64) * tile_cells)
    return [(origin + lo * cell).tolist(), (origin + (lo + tile_cells) * cell).tolist()]


def _max_or_none(*values):
    present = [float(v) for v in values if v is not None]
    return max(present) if present else None


def build_report(metadata: dict, *, job_dir: str | Path | None = None, output: str | Path | None = None,
                 picture: str | None = None) -> dict:
    """Arrange a job's metadata (the mesh sidecar) as a per-tile report.

    Parameters
    ----------
    metadata : dict
        ``mesh.metadata`` of a tiled job (:func:`tiled_gridpull.tiled_job.job_metadata` plus ``mesh`` topology and
        final ``timings_s``).
    job_dir, output : str or Path, optional
        Recorded as given (absolute paths).
    picture : str, optional
        File name of the layout picture, relative to the job directory.

    Returns
    -------
    dict
        ``format``, ``version``, ``job_dir``, ``output``, ``config`` (solver), ``noise_treatment``, ``tiling``,
        ``lattice``, ``input``, ``crs``, ``engine``, ``mesh`` (topology), ``timings_s`` (wall clock per phase, s),
        ``tiles`` (one row per tile with points: ``tile``, ``index``, ``status``, ``reason``, ``points``,
        ``points_used``, ``core_bounds`` (world), ``solve_time_s``, ``mesh_time_s``, ``peak_rss_mb`` (MB, of
        the solve or the mesh step, whichever is higher), ``worker``, ``loss_first`` / ``loss_last``
        (``iteration``, ``level``, ``pull`` and ``tv`` in cells of that level, its ``cell_size`` and
        ``pull_world``: the pull loss in the data's units), ``faces``, ``vertices``, ``trimmed``,
        ``flipped``) and ``totals`` (tile counts, summed tile times, highest peak memory, mesh size, wall time).
    """
    tiling = metadata.get("tiling", {})
    lattice = metadata.get("lattice", {})
    tile_cells = int(tiling.get("tile_cells") or 0)
    meshes = {m.get("tile"): m for m in metadata.get("mesh_summaries", [])}
    rows = []
    for s in metadata.get("tile_summaries", []):
        m = meshes.get(s.get("tile"), {})
        row = {
            "tile": s.get("tile"),
            "index": list(s.get("index", [])),
            "status": s.get("status"),
            "reason": s.get("reason"),
            "points": s.get("points"),
            "points_used": s.get("points_used"),
            "core_bounds": (tile_core_bounds(lattice, tile_cells, s["index"])
                            if tile_cells and lattice and "index" in s else None),
            "solve_time_s": s.get("time_s"),
            "mesh_time_s": m.get("time_s"),
            "peak_rss_mb": _max_or_none(s.get("peak_rss_mb"), m.get("peak_rss_mb")),
            "worker": s.get("worker"),
            "loss_first": s.get("loss_first"),
            "loss_last": s.get("loss_last"),
            "faces": m.get("faces"),
            "vertices": m.get("vertices"),
            "trimmed": m.get("trimmed"),
            "flipped": s.get("flipped"),
        }
        rows.append(row)
    status = [r["status"] for r in rows]
    topo = metadata.get("mesh", {})
    timings = metadata.get("timings_s", {})
    solve_times = [float(r["solve_time_s"]) for r in rows if r["solve_time_s"] is not None]
    mesh_times = [float(r["mesh_time_s"]) for r in rows if r["mesh_time_s"] is not None]
    peaks = [float(r["peak_rss_mb"]) for r in rows if r["peak_rss_mb"] is not None]
    totals = {
        "tiles_planned": metadata.get("tiles", {}).get("planned"),
        "tiles_with_points": len(rows),
        "tiles_solved": status.count("solved"),
        "tiles_failed": status.count("failed"),
        "tiles_skipped": status.count("skipped"),
        "points": metadata.get("input", {}).get("points"),
        "points_in_tiles": int(sum(int(r["points"] or 0) for r in rows)),
        "solve_time_s": float(sum(solve_times)),
        "mesh_time_s": float(sum(mesh_times)),
        "max_tile_time_s": max(solve_times, default=None),
        "peak_rss_mb": max(peaks, default=None),
        "faces": topo.get("n_faces"),
        "vertices": topo.get("n_vertices"),
        "boundary_edges": topo.get("boundary_edges"),
        "wall_time_s": timings.get("total"),
    }
    return {
        "format": REPORT_FORMAT,
        "generator": metadata.get("generator"),
        "version": metadata.get("version"),
        "job_dir": str(Path(job_dir).resolve()) if job_dir is not None else None,
        "output": str(Path(output).resolve()) if output is not None else None,
        "picture": picture,
        "config": metadata.get("config"),
        "noise_treatment": metadata.get("noise_treatment"),
        "tiling": tiling,
        "lattice": lattice,
        "input": metadata.get("input"),
        "crs": metadata.get("crs"),
        "engine": metadata.get("engine"),
        "mesh": topo,
        "timings_s": timings,
        "tiles": rows,
        "totals": totals,
    }


def write_report(job_dir: str | Path, metadata: dict, *, output: str | Path | None = None,
                 picture: bool = True, max_points: int = 50_000) -> Path:
    """Write ``report.json`` (and ``tiles.png``) into a job directory, atomically.

    The picture is drawn only when matplotlib is importable; any failure to draw it is logged as a warning and
    the report records ``picture: null``. The report itself is always written.

    Parameters
    ----------
    job_dir : str or Path
    metadata : dict
        ``mesh.metadata`` of the finished job.
    output : str or Path, optional
        The mesh the job wrote.
    picture : bool
        Draw ``tiles.png``.
    max_points : int
        Input points drawn in the picture at most (read from the job's spill files).

    Returns
    -------
    Path
        The report file.
    """
    job_dir = Path(job_dir)
    report = build_report(metadata, job_dir=job_dir, output=output)
    if picture:
        report["picture"] = _write_layout(job_dir, report, max_points)
    path = job_dir / REPORT_NAME
    write_json(path, report)
    return path


def _write_layout(job_dir: Path, report: dict, max_points: int) -> str | None:
    import importlib.util

    if importlib.util.find_spec("matplotlib") is None:
        log.info("matplotlib is not installed: no %s picture", LAYOUT_NAME)
        return None
    try:
        from .tile_layout import render_tile_layout

        pts = sample_job_points(job_dir, max_points) if (job_dir / "manifest.json").exists() else None
        render_tile_layout(report, job_dir / LAYOUT_NAME, points=pts)
        return LAYOUT_NAME
    except Exception as exc:  # a picture never fails a job
        log.warning("could not draw %s: %s: %s", job_dir / LAYOUT_NAME, exc.__class__.__name__, exc)
        return None


def read_report(path: str | Path) -> dict:
    """Read a job report.

    Parameters
    ----------
    path : str or Path
        A job directory or its ``report.json``.

    Returns
    -------
    dict

    Raises
    ------
    InputError
        No report there, or not a report: not a regular file (never opened then), larger than
        :data:`~tiled_gridpull.io.outputs.MAX_OWN_FILE`, not JSON or nested too deeply to parse.
    """
    p = Path(path)
    if p.is_dir():
        p = p / REPORT_NAME
        if not p.exists():
            raise InputError(f"{path}: no {REPORT_NAME} in this directory (is it the job directory of a finished "
                             "tiled run? by default OUTPUT with a .job suffix)")
    elif not p.exists():
        raise InputError(f"{path}: not found")
    if not p.is_file():  # a FIFO is never opened: reading it would wait for a writer for good
        raise InputError(f"{p}: not a regular file, so not a job report")
    try:
        if p.stat().st_size > MAX_OWN_FILE:
            raise InputError(f"{p}: larger than {MAX_OWN_FILE >> 20} MiB, so not a job report")
        with open(p, "rb") as fh:
            data = json.loads(fh.read(MAX_OWN_FILE + 1))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{p}: cannot read report ({exc.__class__.__name__})") from None
    except RecursionError:
        raise InputError(f"{p}: cannot read report (nested too deeply to be a job report)") from None
    if not isinstance(data, dict) or data.get("format") != REPORT_FORMAT or not isinstance(data.get("tiles"), list):
        raise InputError(f"{p}: not a tiled_gridpull job report")
    return data


def _num(v, fmt: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, fmt)


#: Wall-clock phases of a tiled job (``timings_s``), in the order the table shows them.
TIMING_PHASES = ("partition", "solve_and_mesh", "merge", "total")


def format_report_table(report: dict) -> str:
    """A job report as plain text: a header, one row per tile, a totals row and the reasons of failed tiles.

    Columns: tile, status, points, solve and blend+mesh time (s), peak resident memory of the process that
    solved the tile (MB), mean pull loss at the first and last recorded iteration (in the data's units: the
    mean distance from a pulled query to its nearest point), faces meshed.
    """
    tot = report.get("totals", {})
    lat = report.get("lattice", {})
    til = report.get("tiling", {})
    lines = []
    if report.get("output"):
        lines.append(f"output:  {report['output']}")
    if report.get("job_dir"):
        lines.append(f"job:     {report['job_dir']}")
    if lat:
        shape = "x".join(str(v) for v in lat.get("shape", []))
        origin = ", ".join(f"{v:.10g}" for v in lat.get("origin", []))
        lines.append(f"lattice: cell {lat.get('cell_size'):g}, {shape} vertices, origin ({origin})")
    if til:
        lines.append(f"tiles:   {til.get('tile_size'):g} core ({til.get('tile_cells')} cells) + "
                     f"{til.get('overlap'):g} overlap ({til.get('overlap_cells')} cells), "
                     f"{tot.get('tiles_planned')} planned, {tot.get('tiles_with_points')} with points, "
                     f"{tot.get('tiles_solved')} solved")
    cfg = recorded_settings(report.get("config") or {})
    if cfg:
        lines.append(f"solver:  {cfg.get('mode')}, {cfg.get('levels')} levels, {cfg.get('coarse_iterations')}+"
                     f"{cfg.get('iterations')} iterations, m1 {cfg.get('m1')}, m2 {cfg.get('m2')}, "
                     f"seed {cfg.get('seed')}")
    lines.append("")
    head = ("tile", "status", "points", "solve_s", "mesh_s", "peak_MB", "pull_first", "pull_last", "faces")
    rows = []
    for t in report.get("tiles", []):
        first, last = t.get("loss_first") or {}, t.get("loss_last") or {}
        rows.append((str(t.get("tile")), str(t.get("status")), _num(t.get("points"), "d"),
                     _num(t.get("solve_time_s"), ".2f"), _num(t.get("mesh_time_s"), ".2f"),
                     _num(t.get("peak_rss_mb"), ".0f"), _num(first.get("pull_world"), ".4g"),
                     _num(last.get("pull_world"), ".4g"), _num(t.get("faces"), "d")))
    rows.append(("total", f"{tot.get('tiles_solved')}/{tot.get('tiles_with_points')}",
                 _num(tot.get("points_in_tiles"), "d"), _num(tot.get("solve_time_s"), ".2f"),
                 _num(tot.get("mesh_time_s"), ".2f"), _num(tot.get("peak_rss_mb"), ".0f"), "", "",
                 _num(tot.get("faces"), "d")))
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(len(head))]

    def fmt(r):
        return "  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip()

    lines.append(fmt(head))
    lines.extend(fmt(r) for r in rows[:-1])
    lines.append("  ".join("-" * w for w in widths))
    lines.append(fmt(rows[-1]))
    lines.append("")
    tim = {k: v for k, v in (report.get("timings_s") or {}).items() if isinstance(v, (int, float))}
    if tim:
        order = [k for k in TIMING_PHASES if k in tim] + sorted(k for k in tim if k not in TIMING_PHASES)
        lines.append("wall time: " + ", ".join(f"{k} {tim[k]:.2f} s" for k in order))
    lines.append(f"mesh: {tot.get('vertices')} vertices, {tot.get('faces')} faces, "
                 f"{tot.get('boundary_edges')} boundary edges; input: {tot.get('points')} points "
                 f"({tot.get('points_in_tiles')} in tiles, overlaps counted in each)")
    lines.append("pull_first/pull_last: mean pull loss (distance from a pulled query to its nearest point, in the "
                 "data's units) at the first (coarsest level) and last (finest level) recorded iteration")
    for t in report.get("tiles", []):
        if t.get("status") != "solved":
            lines.append(f"{t.get('tile')} {t.get('status')}: {t.get('reason')}")
    if report.get("picture"):
        lines.append(f"picture: {report['picture']}")
    return "\n".join(lines)
