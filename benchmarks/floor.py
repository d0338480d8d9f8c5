"""Cost per iteration against the memory-bandwidth floor (issue 4): one level of the solver on the bunny at
R = 256, beside a bandwidth measurement taken in the same process.

The floor follows the issue's model: an iteration touches about 96 bytes of optimizer state per band vertex, so
it cannot run faster than ``96 x band vertices / bandwidth``. Bandwidth is that of a 2-thread numba triad
(``a = b + s c``, float32, 3 x 256 MB) counting the bytes read and written, median of 5. Each solver run is one
level, 300 iterations, the paper's schedule and losses; rows: the paper's band (M2 = 14, sqrt TV) with fresh
queries every iteration and with the query pool, and our finest level's band (M2 = 8, squared TV). Medians of
``--repeats`` runs, each in this process after one warm-up. Results append to ``benchmarks/results/floor.jsonl``.

Usage::

    python -m benchmarks.floor [--repeats 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from numba import njit, prange

from benchmarks.common import REPO, append_jsonl, machine, markdown_table, require_shared

RESULTS = REPO / "benchmarks" / "results" / "floor.jsonl"
STATE_BYTES_PER_VERTEX = 96  # the model of the state an iteration touches

VARIANTS = {
    "paper band (M2 14, sqrt TV), fresh queries": {"m2": 14, "tv_form": "sqrt", "query_pool": 0},
    "paper band (M2 14, sqrt TV), query pool 200": {"m2": 14, "tv_form": "sqrt", "query_pool": 200},
    "finest level (M2 8, squared TV), query pool 200": {"m2": 8, "tv_form": "squared", "query_pool": 200,
                                                        "query_sigma": 0.5, "gamma": 3.0, "lr": 0.3},
}


@njit(cache=True, parallel=True)
def _triad(a, b, c, s):
    for i in prange(a.shape[0]):
        a[i] = b[i] + s * c[i]


def bandwidth_gbs(n: int = 64 * 2**20, repeats: int = 5) -> float:
    """Triad bandwidth in GB/s (bytes read + written), median of ``repeats``."""
    a = np.zeros(n, np.float32)
    b = np.ones(n, np.float32)
    c = np.ones(n, np.float32)
    _triad(a, b, c, np.float32(2.0))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        _triad(a, b, c, np.float32(2.0))
        times.append(time.perf_counter() - t)
    return 3 * 4 * n / np.median(times) / 1e9


def one_level(points: np.ndarray, settings: dict, iterations: int) -> dict:
    """Solve one level at R = 256 and return per-iteration timings and the band size."""
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.reconstruct import shape_lattice
    from tiled_gridpull.solver import solve

    cfg = SolverConfig(levels=1, iterations=iterations, lr_step=max(iterations // 4, 1), **settings)
    fld = solve(points, shape_lattice(points, cfg), cfg)
    lv = fld.info["levels"][-1]
    return {"params": lv["band"]["params"], "iteration_ms": 1e3 * lv["time_solve_s"] / iterations,
            "queries_ms": 1e3 * lv["time_queries_s"] / iterations, "steps_ms": 1e3 * lv["time_steps_s"] / iterations,
            "pool_s": lv.get("time_query_pool_s", 0.0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=300)
    a = ap.parse_args()
    require_shared()
    from benchmarks.shape_worker import load_unit_mesh
    from tiled_gridpull.metrics import sample_surface

    points = sample_surface(load_unit_mesh("bunny"), 100_000, 0)[0]
    one_level(points, {"query_pool": 20}, 40)  # compile / warm caches
    date = time.strftime("%Y-%m-%d %H:%M")
    print(f"{'variant':50s} {'params':>9s} {'GB/s':>6s} {'floor ms':>8s} {'it ms':>6s} {'queries':>7s} "
          f"{'steps':>6s} {'x floor':>7s}")
    for name, settings in VARIANTS.items():
        runs, bws = [], []
        for _ in range(a.repeats):
            bws.append(bandwidth_gbs())
            runs.append(one_level(points, settings, a.iterations))
        bw = float(np.median(bws))
        med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
        floor_ms = STATE_BYTES_PER_VERTEX * med["params"] / (bw * 1e9) * 1e3
        row = {"date": date, "variant": name, "settings": settings, "repeats": a.repeats,
               "iterations": a.iterations, "bandwidth_gbs": bw, "floor_ms": floor_ms,
               "x_floor": med["iteration_ms"] / floor_ms, **med}
        append_jsonl(RESULTS, row)
        print(f"{name:50s} {med['params']:9.0f} {bw:6.1f} {floor_ms:8.1f} {med['iteration_ms']:6.1f} "
              f"{med['queries_ms']:7.1f} {med['steps_ms']:6.1f} {row['x_floor']:7.2f}", flush=True)
    append_jsonl(RESULTS, {"date": date, "variant": "machine", **machine()})


def render(rows: list[dict]) -> str:
    """Markdown table of the floor runs (newest last)."""
    runs = [r for r in rows if r.get("variant") != "machine"]
    if not runs:
        return ""
    return markdown_table(runs, [("date", "date", ""), ("variant", "variant", ""), ("params", "band vertices", ",.0f"),
                                 ("bandwidth_gbs", "bandwidth GB/s", ".1f"), ("floor_ms", "floor ms/it", ".1f"),
                                 ("iteration_ms", "ms/it", ".1f"), ("queries_ms", "queries ms", ".1f"),
                                 ("steps_ms", "steps ms", ".1f"), ("x_floor", "x floor", ".2f")])


if __name__ == "__main__":
    main()
