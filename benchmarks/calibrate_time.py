"""Fit the dry run's time rates (:mod:`tiled_gridpull.memory`) to the tile times of finished jobs.

For every solved tile of the given job directories: the work the estimate counts (query evaluations, nearest-point
searches, band slot updates, iterations, points; from the partition alone, exactly as ``--dry-run`` sees it) and
the measured task seconds from the job's summaries; a non-negative least-squares fit of the rates, and each
tile's estimate against its measurement with today's rates.

Usage: ``python -m benchmarks.calibrate_time JOB_DIR[:CONFIG.yaml] ...`` (config default configs/scene.yaml).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def tile_work(spec, solver, occupancy=None) -> dict:
    """The work counts of one tile's solve as the estimate sees them, and its band bounds per level."""
    from tiled_gridpull import memory as m
    from tiled_gridpull.partition import read_occupancy

    occ = read_occupancy(spec) if occupancy is None else occupancy
    bricks = m.band_bricks_bound(occ, spec.block.shape, solver)
    levels = len(bricks)
    w = {"query": 0.0, "nn": 0.0, "slot": 0.0, "iteration": 0.0, "point": float(spec.n_points), "one": 1.0}
    for level, b in enumerate(bricks):
        st = solver.level_settings(level, levels, m.level_points(spec, level, levels))
        it, nq = st.iterations, st.queries
        w["query"] += it * nq
        w["nn"] += (st.query_pool or it) * nq
        w["slot"] += it * b * m.SLOT
        w["iteration"] += it
    return w, bricks


def main(argv: list[str]) -> None:
    import argparse

    from tiled_gridpull.pipeline.cli import resolve_settings
    from tiled_gridpull import memory as m
    from tiled_gridpull.jobdir import read_manifest

    rows, names = [], ["query", "nn", "slot", "iteration", "point", "one"]
    for arg in argv:
        job, _, cfg = arg.partition(":")
        # the settings exactly as `tiled-gridpull reconstruct --config CFG` resolves them
        solver, _ = resolve_settings(argparse.Namespace(config=cfg or "configs/scene.yaml", overrides=[]))
        _, specs = read_manifest(Path(job) / "manifest.json")
        for spec in specs:
            p = Path(job) / "summaries" / f"solve_{spec.name}.json"
            if not p.exists():
                continue
            s = json.loads(p.read_text())
            if s.get("status") != "solved":
                continue
            w, bricks = tile_work(spec, solver)
            est = m.tile_time(spec, bricks, solver)
            rows.append((w, s["time_s"], est, spec.name, job))
    A = np.array([[r[0][k] for k in names] for r in rows])
    y = np.array([r[1] for r in rows])
    from scipy.optimize import nnls

    scale = A.max(axis=0) + 1e-30
    coef, _ = nnls(A / scale, y)
    coef /= scale
    print("fitted rates:", {k: f"{c:.3g}" for k, c in zip(names, coef)})
    fit = A @ coef
    est = np.array([r[2] for r in rows])
    print(f"tiles {len(rows)}; measured/estimate with today's rates: median {np.median(y / est):.2f}, "
          f"range {np.min(y / est):.2f}..{np.max(y / est):.2f}; with the fit: median {np.median(y / fit):.2f}, "
          f"range {np.min(y / fit):.2f}..{np.max(y / fit):.2f}; sums measured {y.sum():.0f} s, today's "
          f"{est.sum():.0f} s, fit {fit.sum():.0f} s")


if __name__ == "__main__":
    main(sys.argv[1:])
