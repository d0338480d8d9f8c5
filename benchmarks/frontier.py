"""Time against accuracy: the quality presets (``--quality draft | standard | fine``) at a few cell sizes beside
Open3D screened Poisson at depths 9, 10 and 11 (trimmed), all in the same run (issue 39).

Scenes:

* ``wide``: the synthetic grid of streets (1M points, 200 m x 200 m, ``tiled-gridpull sample street --layout
  grid``), scored against its ground truth over the observed region (exact CD-L1, F@0.1 m);
* ``airborne``: the shared AHN3 (metres) and Autzen (US feet) files with 10 % of their points held out (seeded),
  scored by the held-out points' mean distance to each mesh (file units).

Every GridPull run is ``tiled-gridpull reconstruct --config configs/scene.yaml --quality Q --voxel-size C`` on the
default local Dask cluster (2 workers), or with ``--workers 0`` in the command's own process (rows "in process");
Poisson is :mod:`benchmarks.poisson_scene` (read, normals, Poisson, 5 %
density trim, write) in its own process. Results append to ``benchmarks/results/frontier.jsonl``; each row
carries the run's id, so times are compared with the Poisson rows of the same run. ``report`` draws the plot
(``benchmarks/results/frontier.png``); ``python benchmarks/report.py`` puts it and the table in BENCHMARKS.md.

Usage::

    python -m benchmarks.frontier wide --runs draft@0.3 draft@0.5 standard@0.3 [--depths 9 10 11]
    python -m benchmarks.frontier airborne --runs draft standard [--depths 9 10 11]   # the files' own cells
    python -m benchmarks.frontier airborne --runs draft --depths 10 --workers 2 0   # each run on both engines
    python -m benchmarks.frontier airborne --runs draft draft@auto floor --depths 10 --workers 0
    python -m benchmarks.frontier tile        # a 1,000-point tile, each preset, in this process (no Dask)
    python -m benchmarks.frontier report
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, append_jsonl, machine, markdown_table

RESULTS = REPO / "benchmarks" / "results" / "frontier.jsonl"
PLOT = REPO / "benchmarks" / "results" / "frontier.png"
WIDE = "grid of streets (synthetic)"
#: The solver's iteration arithmetic, recorded on every GridPull row: runs of one preset are pooled only with runs
#: of the same arithmetic (rows without the field ran the float64-promoted kernels before 2026-11-27 12:00)
KERNELS = "float32"
#: How the job ran, recorded on every GridPull row (``--workers N``); repeats are pooled per engine. Rows without
#: the field ran on the default local cluster of 2 workers; three rounds of 2026-11-27 13:43-13:50 ran a trial,
#: left out, that started the cluster while the inputs were read ("local cluster, started while the inputs are read")
LOCAL_CLUSTER = "local cluster"
#: Run ``floor``: the draft preset with one iteration per level, what a job costs at a cell whatever its schedule
#: (reading, the noise scan, each tile's normals, level set-up and bridging, meshing, the merge and the report)
FLOOR = {"coarse_iterations": 1, "middle_iterations": 1, "iterations": 1}


def engine_of(workers: int) -> str:
    """The engine label of a run with ``--workers workers``."""
    if workers == 0:
        return "in process (--workers 0)"
    return LOCAL_CLUSTER if workers == 2 else f"local cluster of {workers} workers"


def record(row: dict) -> None:
    append_jsonl(RESULTS, row)
    shown = {k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in row.items()
             if k in ("scene", "method", "setting", "cell", "wall_s", "chamfer_l1_m", "fscore_0.1m", "holdout_mean")}
    print(shown, flush=True)


def parse_run(text: str) -> tuple[str, float | str | None]:
    """``draft@0.3`` -> ("draft", 0.3); ``draft@x2`` -> ("draft", "x2"): twice the scene's own cell;
    ``draft@auto`` -> ("draft", "auto"): the cell ``--voxel-size auto`` chooses under the preset; ``draft`` ->
    ("draft", None): the scene's own cell. ``floor`` (:data:`FLOOR`) takes the same cells."""
    quality, _, cell = text.partition("@")
    if quality not in ("draft", "standard", "fine", "floor"):
        raise SystemExit(f"--runs: quality must be draft, standard, fine or floor, got {quality!r}")
    return quality, (cell if cell.startswith("x") or cell == "auto" else float(cell)) if cell else None


def cell_of(cell: float | str | None, own: float) -> float | str:
    """A run's cell: its own number, a multiple of the scene's cell (``x2``), ``auto``, or the scene's cell."""
    if cell is None:
        return own
    if cell == "auto":
        return cell
    return own * float(cell[1:]) if isinstance(cell, str) else cell


def preset_of(setting: str) -> dict:
    """The settings a run of ``setting`` (a preset, or ``floor``) applies, as recorded on its rows."""
    from tiled_gridpull.config import QUALITY_PRESETS

    return {**QUALITY_PRESETS["draft"], **FLOOR} if setting == "floor" else QUALITY_PRESETS[setting]


def gridpull(src: Path, out: Path, quality: str, cell: float | str, extra: list[str] | None = None,
             workers: int = 2) -> dict:
    """One GridPull job; ``workers`` 0: in the command's process, no cluster (``--workers 0``); ``cell``
    ``auto``: the cell and tiles the CLI derives (recorded as ``cell``, with ``cell_auto``)."""
    from benchmarks.scenes import reconstruct

    sets = [a for k, v in FLOOR.items() for a in ("--set", f"{k}={v}")] if quality == "floor" else []
    preset = "draft" if quality == "floor" else quality
    row = reconstruct(src, out, workers, ["--config", str(REPO / "configs" / "scene.yaml"), "--quality", preset,
                                    "--voxel-size", str(cell), *sets, *(extra or [])])
    auto = cell == "auto"
    if auto:
        import json

        cell = json.loads(out.with_suffix(".json").read_text())["tiling"]["voxel_size"]
    # the preset's settings as they were: repeats of one preset are only pooled while its schedule is unchanged
    return {"wall_s": row["wall_s"], "tiles": row["tiles"], "solve_task_s": row["stages_s"]["solve_task_s"],
            "peak_rss_mb": row["peak_rss_mb"], "method": "gridpull", "setting": quality, "cell": cell,
            **({"cell_auto": True} if auto else {}), "preset": preset_of(quality), "kernels": KERNELS,
            "workers": workers, "engine": engine_of(workers)}


def poisson(src: Path, out: Path, depth: int) -> dict:
    from benchmarks.scenes import poisson_scene

    t0 = time.perf_counter()
    res = poisson_scene(src, out, depth)
    # the whole process too, as GridPull's wall_s is (python's start and its imports, open3d's about 0.6 s,
    # are not in the script's own wall_s)
    process = time.perf_counter() - t0
    return {"wall_s": res["wall_s"], "process_s": process, "normals_s": res["normals_s"], "poisson_s": res["poisson_s"],
            "peak_rss_mb": res["peak_rss_mb"], "method": "poisson", "setting": f"depth {depth}", "depth": depth}


def wide(work: Path, runs: list[tuple[str, float | None]], depths: list[int], run_id: str,
         sample_dir: Path | None = None, engines: tuple[int, ...] = (2,)) -> None:
    """``sample_dir``: a grid written earlier by ``tiled-gridpull sample street --points 1000000 --layout grid
    --origin 500000 4000000 100`` (the same seeded scene; street.laz and street_gt.ply are read)."""
    from benchmarks.scenes import evaluate
    from tiled_gridpull.io import read_points
    from tiled_gridpull.synthetic.street_sample import make_street_sample

    if sample_dir is not None:
        src, gt = Path(sample_dir) / "street.laz", Path(sample_dir) / "street_gt.ply"
        n_points = len(read_points(src).xyz)
    else:
        sample = make_street_sample(work / "grid", n_points=1_000_000, origin=(500000.0, 4000000.0, 100.0),
                                    layout="grid")
        src, gt, n_points = sample["laz"], sample["gt_mesh"], sample["n_points"]
    base = {"run": run_id, "scene": WIDE, "points": n_points}
    for depth in depths:
        out = work / f"poisson_{depth}.ply"
        row = poisson(src, out, depth)
        row.update(evaluate(out, gt, src))
        record({**base, "date": time.strftime("%Y-%m-%d %H:%M"), **row})
    for quality, cell in runs:
        cell = cell_of(cell, 0.1)
        for workers in engines:
            out = work / f"{quality}_{cell}_{workers}.ply"
            row = gridpull(src, out, quality, cell, workers=workers)
            row.update(evaluate(out, gt, src))
            record({**base, "date": time.strftime("%Y-%m-%d %H:%M"), **row})


def airborne(work: Path, runs: list[tuple[str, float | None]], depths: list[int], run_id: str,
             fraction: float = 0.1, engines: tuple[int, ...] = (2,)) -> None:
    import numpy as np

    from benchmarks.scenes import holdout_scores, shared_lidar_files
    from tiled_gridpull.io import read_points
    from tiled_gridpull.synthetic.lidar_files import write_las

    for name, own_cell, src in shared_lidar_files():
        xyz = read_points(src).xyz
        held = np.random.default_rng(0).random(len(xyz)) < fraction
        train = write_las(work / f"{src.stem}_train.laz", xyz[~held])
        test, kept = xyz[held], xyz[~held]
        base = {"run": run_id, "scene": name, "points": int((~held).sum()), "held_out": int(held.sum()),
                "own_cell": own_cell}
        for depth in depths:
            out = work / f"{src.stem}_poisson_{depth}.ply"
            row = poisson(train, out, depth)
            row.update(holdout_scores(out, test, kept, own_cell))
            record({**base, "date": time.strftime("%Y-%m-%d %H:%M"), **row})
        for quality, cell in runs:
            cell = cell_of(cell, own_cell)
            for workers in engines:
                out = work / f"{src.stem}_{quality}_{cell}_{workers}.ply"
                # tiles of the benchmarks' usual size in the file's units (scenes.py holdout); an auto cell's
                # tiles are the CLI's, 256 and 32 cells as well
                tiles = [] if cell == "auto" else ["--tile-size", str(256 * cell), "--overlap", str(32 * cell)]
                row = gridpull(train, out, quality, cell, tiles, workers=workers)
                row.update(holdout_scores(out, test, kept, own_cell))
                record({**base, "date": time.strftime("%Y-%m-%d %H:%M"), **row})


def small_tile(work: Path, run_id: str, n_points: int = 1000, repeats: int = 3) -> None:
    """A ``n_points``-point ground patch (one tile) with ``--voxel-size auto``, each preset in this process (no
    Dask: the tile's own cost, :func:`tiled_gridpull.tiled_job.reconstruct_scene`), the fastest of ``repeats``
    runs after a warm-up (numba's kernels loaded)."""
    import numpy as np

    from tiled_gridpull.config import QUALITIES, QUALITY_CELL_SCALE
    from tiled_gridpull.pipeline.cli import build_parser, resolve_settings
    from tiled_gridpull.prepare import resolve_units
    from tiled_gridpull.tiled_job import reconstruct_scene

    rng = np.random.default_rng(7)
    side = 10.0
    xy = rng.uniform(0, side, size=(n_points, 2))
    z = 0.4 * np.sin(xy[:, 0] / 2.0) * np.cos(xy[:, 1] / 3.0)
    src = work / "patch.npy"
    np.save(src, np.column_stack([xy, z]) + np.array([500000.0, 4000000.0, 50.0]))
    for quality in QUALITIES:
        args = build_parser().parse_args(["reconstruct", str(src), "-o", str(work / "p.ply"), "--config",
                                          str(REPO / "configs" / "scene.yaml"), "--voxel-size", "auto",
                                          "--quality", quality])
        solver, tiling = resolve_settings(args)
        tiling = resolve_units([str(src)], tiling, cell_scale=QUALITY_CELL_SCALE[quality])
        walls, solves = [], []
        for i in range(repeats + 1):
            t0 = time.perf_counter()
            mesh = reconstruct_scene([str(src)], None, tiling, solver, work / f"{quality}_{i}.job")
            if i:  # the first loads the kernels
                walls.append(time.perf_counter() - t0)
                solves.append(sum(t["time_s"] for t in mesh.metadata["tile_summaries"]))
        record({"run": run_id, "date": time.strftime("%Y-%m-%d %H:%M"), "scene": f"{n_points}-point tile",
                "method": "gridpull", "setting": quality, "cell": tiling.voxel_size, "points": n_points,
                "tiles": len(mesh.metadata["tile_summaries"]), "wall_s": min(walls), "solve_s": min(solves),
                "faces": int(mesh.n_faces)})


def load(path: Path = RESULTS) -> list[dict]:
    import json

    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _with_ratios(rows: list[dict]) -> list[dict]:
    """Rows with ``x_poisson_11`` / ``x_poisson_10``: wall time over the same run's Poisson at that depth (its
    script's own wall time: read to write); with ``xp_poisson_*`` over that Poisson's whole process (python's start
    and its imports included, as in GridPull's wall time), where the run recorded it."""
    out = []
    for r in rows:
        if r.get("scene") == "machine":
            continue
        peers = {p["depth"]: p for p in rows if p.get("method") == "poisson" and p["run"] == r["run"]
                 and p["scene"] == r["scene"]}
        extra = {f"x_poisson_{d}": r["wall_s"] / peers[d]["wall_s"] for d in (10, 11) if d in peers}
        extra.update({f"xp_poisson_{d}": r["wall_s"] / peers[d]["process_s"] for d in (10, 11)
                      if peers.get(d, {}).get("process_s")})
        out.append({**r, **extra, "what": r["setting"] + (f" @ {r['cell']:g}" if r.get("cell") else "")
                    + (" (auto)" if r.get("cell_auto") else "") + _engine_tag(r)})
    return out


def _engine_tag(r: dict) -> str:
    """What a row's label adds for its engine: " in process" for a ``--workers 0`` run, else nothing."""
    return " in process" if r.get("workers") == 0 else ""


def render(rows: list[dict]) -> str:
    """Markdown tables of the latest run of each scene: the synthetic scene's, then the real files'."""
    rows = all_rows = _with_ratios(rows)
    latest = {}
    for r in rows:
        latest[r["scene"]] = max(latest.get(r["scene"], ""), r["run"])
    rows = [r for r in rows if r["run"] == latest[r["scene"]]]
    parts = []
    synth = [r for r in rows if r["scene"] == WIDE]
    if synth:
        parts.append(markdown_table(synth, [("date", "date", ""), ("what", "method @ cell m", ""),
                                            ("tiles", "tiles", ""), ("wall_s", "wall s", ".1f"),
                                            ("x_poisson_11", "x Poisson 11 time", ".2f"),
                                            ("chamfer_l1_m", "CD-L1 m", ".4f"), ("fscore_0.1m", "F@0.1", ".3f"),
                                            ("normal_consistency", "NC", ".3f"), ("peak_rss_mb", "peak MB", ".0f")]))
    real = [r for r in rows if r["scene"] != WIDE and "holdout_mean" in r]
    if real:
        parts.append(markdown_table(real, [("date", "date", ""), ("scene", "file", ""),
                                           ("what", "method @ cell", ""), ("tiles", "tiles", ""),
                                           ("wall_s", "wall s", ".1f"), ("x_poisson_10", "x Poisson 10 time", ".2f"),
                                           ("xp_poisson_10", "x Poisson 10 process", ".2f"),
                                           ("holdout_mean", "held-out mean", ".4f"),
                                           ("holdout_median", "median", ".4f"),
                                           ("holdout_within_cell", "within 1 cell", ".3f")]))
    rep = repeats(all_rows)
    if rep:
        parts.append(rep)
    tile = [r for r in rows if r["scene"].endswith("-point tile")]
    if tile:
        parts.append(markdown_table(tile, [("date", "date", ""), ("scene", "cloud", ""), ("what", "preset @ cell", ""),
                                           ("wall_s", "job s (in process)", ".2f"), ("solve_s", "tile solve s", ".2f"),
                                           ("faces", "faces", "")]))
    return "\n\n".join(parts)


def repeats(rows: list[dict]) -> str:
    """The runs of each preset (and ``floor``) at today's settings (``preset`` as :func:`preset_of` gives) against
    the Poisson depth of its target (11 for the synthetic scene, 10 for the real files), each beside its own run's
    Poisson: the time ratios, their median and the median score. Empty where no preset ran at least twice."""
    import statistics

    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if r.get("method") == "gridpull" and r.get("preset") == preset_of(r["setting"]):
            depth = 11 if r["scene"] == WIDE else 10
            if f"x_poisson_{depth}" in r:
                key = (r["scene"], r["what"], depth, r.get("kernels", "float64"), r.get("engine", LOCAL_CLUSTER))
                groups.setdefault(key, []).append(r)
    out = []
    for (scene, what, depth, kernels, engine), rs in sorted(groups.items()):
        if len(rs) < 2:
            continue
        score = "chamfer_l1_m" if scene == WIDE else "holdout_mean"
        ratios = [r[f"x_poisson_{depth}"] for r in rs]
        whole = [r[f"xp_poisson_{depth}"] for r in rs if f"xp_poisson_{depth}" in r]
        out.append({"scene": scene, "what": what, "kernels": kernels, "engine": engine, "runs": len(rs),
                    "depth": depth,
                    "ratios": ", ".join(f"{x:.2f}" for x in ratios), "median": statistics.median(ratios),
                    "whole": ", ".join(f"{x:.2f}" for x in whole) or None,
                    "whole_median": statistics.median(whole) if whole else None,
                    "score": statistics.median(r[score] for r in rs),
                    "score_name": "CD-L1 m" if scene == WIDE else "held-out mean"})
    if not out:
        return ""
    return markdown_table(out, [("scene", "scene", ""), ("what", "preset @ cell", ""),
                                ("kernels", "kernel arithmetic", ""), ("engine", "engine", ""),
                                ("runs", "runs", ""),
                                ("depth", "beside Poisson depth", ""), ("ratios", "time / Poisson's, each run", ""),
                                ("median", "median", ".2f"),
                                ("whole", "time / Poisson's whole process, runs that recorded it", ""),
                                ("whole_median", "median", ".2f"), ("score_name", "score", ""),
                                ("score", "median score", ".4f")])


def plot(rows: list[dict], path: Path = PLOT) -> Path | None:
    """Time against accuracy, one panel per score: the latest run of each scene."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    rows = _with_ratios(rows)
    latest = {}
    for r in rows:
        latest[r["scene"]] = max(latest.get(r["scene"], ""), r["run"])
    rows = [r for r in rows if r["run"] == latest[r["scene"]]]
    panels = [(WIDE, "chamfer_l1_m", "CD-L1 m (lower is better)"), (WIDE, "fscore_0.1m", "F@0.1 m (higher is better)")]
    panels += [(s, "holdout_mean", "held-out mean distance (file units)") for s in sorted(
        {r["scene"] for r in rows if r["scene"] != WIDE and "holdout_mean" in r})]
    panels = [p for p in panels if any(r["scene"] == p[0] and r.get(p[1]) is not None for r in rows)]
    if not panels:
        return None
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.8))
    axes = [axes] if len(panels) == 1 else list(axes)
    style = {"poisson": ("k", "s"), "draft": ("tab:orange", "o"), "standard": ("tab:blue", "^"),
             "fine": ("tab:green", "D")}

    def series(r: dict) -> str:
        if r["method"] == "poisson":
            return "poisson"
        return r["setting"] + _engine_tag(r)

    for ax, (scene, key, label) in zip(axes, panels):
        mine = [r for r in rows if r["scene"] == scene and r.get(key) is not None]
        for what in ("poisson", "draft", "draft in process", "standard", "standard in process", "fine",
                     "fine in process"):
            pts = sorted([r for r in mine if series(r) == what], key=lambda r: r["wall_s"])
            if not pts:
                continue
            colour, marker = style[what.split()[0]]
            ax.plot([r["wall_s"] for r in pts], [r[key] for r in pts], color=colour, marker=marker,
                    linestyle="-" if what == "poisson" else "--" if what.endswith("in process") else ":",
                    fillstyle="none" if what.endswith("in process") else "full",
                    label="Poisson (trimmed)" if what == "poisson" else what)
            for r in pts:
                tag = f"d{r['depth']}" if what == "poisson" else f"{r['cell']:g}"
                ax.annotate(tag, (r["wall_s"], r[key]), textcoords="offset points", xytext=(4, 4), fontsize=7)
        from matplotlib.ticker import FormatStrFormatter, LogLocator

        ax.set_xscale("log")
        if key != "fscore_0.1m":
            ax.set_yscale("log")
        # plain numbers, not powers of ten; on the time axis at 1, 2 and 5 x 10^k only
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(FormatStrFormatter(""))
        ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(FormatStrFormatter("%g"))
        ax.set_xlabel("wall s, 2 cores (log)")
        ax.set_ylabel(label)
        ax.set_title(scene.replace(" (synthetic)", ""), fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    shown = {}
    for ax in axes:  # one legend for every method drawn in any panel
        for handle, name in zip(*ax.get_legend_handles_labels()):
            shown.setdefault(name, handle)
    axes[0].legend(list(shown.values()), list(shown), fontsize=7)
    fig.suptitle("Quality presets against screened Poisson, same run (benchmarks/frontier.py)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite", choices=("wide", "airborne", "tile", "report"))
    ap.add_argument("--runs", nargs="+", default=["draft", "standard"],
                    help="QUALITY[@CELL]: each a GridPull run (CELL in the data's units; default the scene's own: "
                         "0.1 m for the grid, 0.5 m AHN3, 2 ft Autzen)")
    ap.add_argument("--depths", type=int, nargs="+", default=[9, 10, 11], help="Poisson octree depths")
    ap.add_argument("--keep", action="store_true", help="keep the work directory (printed)")
    ap.add_argument("--sample", type=Path, help="wide: a grid of streets written before (see wide())")
    ap.add_argument("--workers", type=int, nargs="+", default=[2],
                    help="each GridPull run on a local cluster of this many workers; 0: in the command's process "
                         "(--workers 0); several: each run once per engine, in the order given")
    a = ap.parse_args()
    if a.suite == "report":
        print(render(load()))
        print(plot(load()))
        return
    runs = [parse_run(t) for t in a.runs]
    run_id = time.strftime("%Y-%m-%d %H:%M:%S")
    append_jsonl(RESULTS, {"scene": "machine", "run": run_id, **machine(), "load": os.getloadavg()[0]})
    work = Path(tempfile.mkdtemp(prefix="tg-frontier-"))
    try:
        if a.suite == "tile":
            small_tile(work, run_id)
        else:
            if a.suite == "wide":
                wide(work, runs, a.depths, run_id, a.sample, tuple(a.workers))
            else:
                airborne(work, runs, a.depths, run_id, engines=tuple(a.workers))
    finally:
        if a.keep:
            print(f"work directory: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
