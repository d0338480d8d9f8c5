"""The tile layout of a job as a picture: tiles seen from above and their timings (matplotlib, Agg).

Matplotlib's Agg canvas needs no OpenGL at all, so a job can always draw it. The ``*_image`` function returns
an ``(H, W, 3) uint8`` RGB array; the other writes it as a PNG atomically.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ._optional import require
from .errors import InputError
from .images import check_size, save_png

__all__ = ["render_tile_layout", "render_tile_layout_image"]



def _columns(tiles: list[dict]) -> list[dict]:
    """Tiles merged per (i, j) column, as seen from above: summed points and times, worst status."""
    cols: dict[tuple, dict] = {}
    rank = {"solved": 0, "skipped": 1, "failed": 2}
    for t in tiles:
        i, j = int(t["index"][0]), int(t["index"][1])
        b = np.asarray(t["core_bounds"], dtype=np.float64)
        c = cols.setdefault((i, j), {"index": (i, j), "lo": b[0, :2], "hi": b[1, :2], "points": 0,
                                     "time_s": 0.0, "status": "solved", "layers": 0})
        c["points"] += int(t.get("points") or 0)
        c["time_s"] += float(t.get("solve_time_s") or 0.0)
        c["layers"] += 1
        st = t.get("status", "solved")
        if rank.get(st, 2) > rank.get(c["status"], 2):
            c["status"] = st
    return list(cols.values())


def _fmt_count(n: int) -> str:
    if n >= 1_000_000:
        return f"{n / 1e6:.1f}M"
    if n >= 10_000:
        return f"{n / 1e3:.0f}k"
    return str(n)


def render_tile_layout_image(report: dict, *, points: np.ndarray | None = None,
                             size: Sequence[int] = (1400, 700), max_labels: int = 150,
                             max_bars: int = 40) -> np.ndarray:
    """The tile layout of a job seen from above, and its per-tile timings.

    Left: the input points (a subsample, grey) and every tile's core rectangle, coloured by solve time and
    labelled ``i,j``, point count and seconds (tiles stacked along z are summed into their column and marked
    ``xK``); failed tiles are hatched red, skipped ones grey. Right: solve and mesh time per tile (a histogram
    when there are more than ``max_bars`` tiles).

    Parameters
    ----------
    report : dict
        A job report (:func:`tiled_gridpull.report.build_report`): ``tiles`` with ``index``, ``core_bounds``
        (world, ``[[x0, y0, z0], [x1, y1, z1]]``), ``points``, ``solve_time_s``, ``mesh_time_s``, ``status``;
        ``lattice`` (its ``origin`` is subtracted from the axes).
    points : (N, 3) float, optional
        World coordinates of points to draw (e.g. :func:`tiled_gridpull.jobdir.sample_job_points`).
    size : (W, H) int
        Pixels.
    max_labels : int
        Tiles are labelled only up to this many columns.
    max_bars : int

    Returns
    -------
    (H, W, 3) uint8
    """
    size = check_size(size)
    mpl = require("matplotlib", "the tile-layout picture")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch, Rectangle

    tiles = report.get("tiles") or []
    if not tiles:
        raise InputError("report lists no tiles")
    x0, y0 = (float(v) for v in report["lattice"]["origin"][:2])
    cols = _columns(tiles)
    times = np.array([c["time_s"] for c in cols])
    norm = Normalize(vmin=0.0, vmax=max(float(times.max()), 1e-6))
    cmap = mpl.colormaps["viridis"]

    dpi = 100
    fig = Figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(1, 2, width_ratios=[3, 2], wspace=0.25, left=0.06, right=0.97, top=0.88, bottom=0.1)
    ax = fig.add_subplot(gs[0])
    if points is not None and len(points):
        p = np.asarray(points, dtype=np.float64)
        ax.scatter(p[:, 0] - x0, p[:, 1] - y0, s=float(np.clip(3e4 / max(len(p), 1), 0.3, 3.0)), c="0.2",
                   alpha=0.6, linewidths=0, rasterized=True, zorder=1)
    labels = len(cols) <= max_labels
    fs = float(np.clip(11 - 0.06 * len(cols), 5, 10))
    for c in cols:
        lo, hi = c["lo"] - (x0, y0), c["hi"] - (x0, y0)
        w, h = hi - lo
        if c["status"] == "failed":
            face, edge, hatch, lw = (1.0, 0.0, 0.0, 0.12), (1.0, 0.0, 0.0, 1.0), "//", 2.0
        elif c["status"] == "skipped":
            face, edge, hatch, lw = (0.85, 0.85, 0.85, 0.55), (0.5, 0.5, 0.5, 1.0), None, 0.8
        else:
            face, edge, hatch, lw = (*cmap(norm(c["time_s"]))[:3], 0.55), (0.0, 0.0, 0.0, 1.0), None, 0.8
        ax.add_patch(Rectangle((lo[0], lo[1]), w, h, facecolor=face, edgecolor=edge, hatch=hatch, linewidth=lw,
                               zorder=2))
        if labels:
            layers = f" x{c['layers']}" if c["layers"] > 1 else ""
            ax.text(lo[0] + w / 2, lo[1] + h / 2,
                    f"{c['index'][0]},{c['index'][1]}{layers}\n{_fmt_count(c['points'])} pts\n{c['time_s']:.1f} s",
                    ha="center", va="center", fontsize=fs, zorder=3)
    lo_all = np.min([c["lo"] for c in cols], axis=0) - (x0, y0)
    hi_all = np.max([c["hi"] for c in cols], axis=0) - (x0, y0)
    pad = 0.02 * float(max(hi_all - lo_all))
    ax.set_xlim(lo_all[0] - pad, hi_all[0] + pad)
    ax.set_ylim(lo_all[1] - pad, hi_all[1] + pad)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(f"x - {x0:.10g}")
    ax.set_ylabel(f"y - {y0:.10g}")
    ax.set_title("tile cores from above (colour: solve time)", fontsize=10)
    sm = mpl.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=ax, fraction=0.04, pad=0.02, label="solve time per tile column [s]")

    ax2 = fig.add_subplot(gs[1])
    solve = np.array([float(t.get("solve_time_s") or 0.0) for t in tiles])
    mesh_t = np.array([float(t.get("mesh_time_s") or 0.0) for t in tiles])
    if len(tiles) <= max_bars:
        names = [",".join(str(v) for v in t["index"]) for t in tiles]
        y = np.arange(len(tiles))
        tnorm = Normalize(vmin=0.0, vmax=max(float(solve.max()), 1e-6))
        ax2.barh(y, solve, color=[cmap(tnorm(v)) if t.get("status") == "solved" else "0.7"
                                  for v, t in zip(solve, tiles)])
        for k, t in enumerate(tiles):
            if t.get("status") != "solved":
                ax2.text(0, k, f" {t.get('status')}", va="center", ha="left", fontsize=8,
                         color="red" if t.get("status") == "failed" else "0.3")
        ax2.barh(y, mesh_t, left=solve, color="#dd8452")
        ax2.set_yticks(y, names, fontsize=float(np.clip(12 - 0.2 * len(tiles), 5, 9)))
        ax2.invert_yaxis()
        ax2.set_xlabel("time [s]")
        ax2.set_ylabel("tile i,j,k")
        ax2.legend(handles=[Patch(facecolor=cmap(0.5), label="solve (colour: time)"),
                            Patch(facecolor="#dd8452", label="blend + mesh")], fontsize=8, loc="lower right")
    else:
        ax2.hist(solve, bins=min(40, max(5, len(tiles) // 5)), color=cmap(0.6))
        ax2.set_xlabel("solve time per tile [s]")
        ax2.set_ylabel("tiles")
    ax2.set_title("time per tile", fontsize=10)
    tot = report.get("totals", {})
    fig.suptitle(f"{tot.get('tiles_solved', '?')}/{tot.get('tiles_with_points', len(tiles))} tiles solved, "
                 f"{_fmt_count(int(tot.get('points', 0)))} points, {tot.get('faces', 0)} faces, "
                 f"wall time {float(tot.get('wall_time_s') or 0.0):.1f} s", fontsize=11)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    return img


def render_tile_layout(report: dict, path: str | Path, *, points: np.ndarray | None = None,
                       size: Sequence[int] = (1400, 700)) -> Path:
    """Write :func:`render_tile_layout_image` as a PNG (atomically).

    Parameters
    ----------
    report : dict
    path : str or Path
    points : (N, 3) float, optional
        World coordinates.
    size : (W, H) int
        Pixels.

    Returns
    -------
    Path
    """
    return save_png(render_tile_layout_image(report, points=points, size=size), path)
