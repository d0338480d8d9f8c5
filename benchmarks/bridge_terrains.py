"""Where the bridge goes wrong: its column kernel over random terrains with known heights (issue 36).

Each trial draws a terrain over a 96 x 96-cell tile (the kind in turn: flat, a step, a raised or sunken strip, a
slope break, a V; a gentle tilt under each; steps and strips 1.6-5 cells high, in either direction), scan lines
8-22 cells apart across it at a random angle (a sample every half cell along them), and 0-3 boxes 2-8 cells high
standing on it (parked cars, bins). :func:`tiled_gridpull.kernels.bridge.fit_columns` then decides the middle
48 x 48 columns with the scene defaults (radius 24, surround 120 degrees, RMS 0.25, step 1.5 cells, no sensor),
once with every sample taken for ground (``object_tol`` 0, the rule before 2026-11-27) and once with the shipped
rule for things standing on the ground (:class:`tiled_gridpull.bridge.BridgeRule`). A column bridged more than one
cell off the true height is **wrong** (a bridge across a step, a ramp); one within half a cell is **right**.
Seeded: the same terrains every run. Results append to ``benchmarks/results/bridge_terrains.jsonl``.

Usage::

    python -m benchmarks.bridge_terrains [--trials 400]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from benchmarks.common import REPO, append_jsonl, markdown_table

RESULTS = REPO / "benchmarks" / "results" / "bridge_terrains.jsonl"
KINDS = ("flat", "step", "strip", "slope break", "V")
N = 48  # bins of 2 cells per side


def _height(kind: str, p: dict):
    def z(x, y):
        x, y = np.asarray(x, float), np.asarray(y, float)
        base = 5.0 + p["gx"] * x + p["gy"] * y
        s = (x - p["cx"]) * math.cos(p["th"]) + (y - p["cy"]) * math.sin(p["th"])  # across the feature
        if kind == "step":
            return base + np.where(s > 0, p["h"], 0.0)
        if kind == "strip":
            return base + np.where((s > 0) & (s < p["w"]), p["h"], 0.0)
        if kind == "slope break":
            return base + np.where(s > 0, p["sl"] * s, 0.0)
        if kind == "V":
            return base + p["sl"] * np.abs(s)
        return base
    return z


def terrains(trials: int, seed: int = 1):
    """Yield ``(kind, rep, z)``: the kernel's ground samples (``bin_ground``, 2-cell bins) and the true height."""
    from tiled_gridpull.kernels.bridge import bin_ground

    rng = np.random.default_rng(seed)
    pixel = 2.0
    for trial in range(trials):
        kind = KINDS[trial % len(KINDS)]
        p = dict(gx=rng.uniform(-.15, .15), gy=rng.uniform(-.15, .15), cx=rng.uniform(35, 60), cy=rng.uniform(35, 60),
                 th=rng.uniform(0, 2 * math.pi), h=rng.choice([-1, 1]) * rng.uniform(1.6, 5), w=rng.uniform(4, 16),
                 sl=rng.uniform(0.2, 0.6))
        z = _height(kind, p)
        spacing = rng.uniform(8, 22)
        angle = rng.uniform(0, math.pi)
        t = np.arange(-80, 200, 0.5)
        pts = []
        for y0 in np.arange(rng.uniform(0, spacing), N * pixel, spacing):
            x = 48 + t * math.cos(angle) - (y0 - 48) * math.sin(angle)
            y = 48 + t * math.sin(angle) + (y0 - 48) * math.cos(angle)
            keep = (x >= 0) & (x < N * pixel) & (y >= 0) & (y < N * pixel)
            pts.append(np.stack([x[keep], y[keep], z(x[keep], y[keep])], 1))
        pts = np.concatenate(pts)
        rep = bin_ground(pts[:, 0].copy(), pts[:, 1].copy(), pts[:, 2].copy(), pixel, N, N, 1.0)
        centres = (np.arange(N) + 0.5) * pixel
        for _ in range(rng.integers(0, 4)):  # boxes: the bins under them read their tops
            lo = rng.uniform(10, 80, 2)
            hi = lo + rng.uniform(4, 12, 2)
            inside = ((centres[:, None] >= lo[0]) & (centres[:, None] <= hi[0]) & (centres[None] >= lo[1])
                      & (centres[None] <= hi[1]) & np.isfinite(rep[..., 2]))
            for i, j in zip(*np.nonzero(inside)):
                rep[i, j, 2] = z(rep[i, j, 0], rep[i, j, 1]) + rng.uniform(2, 8)
        yield kind, rep, z


def run(trials: int) -> list[dict]:
    from tiled_gridpull.bridge import BridgeRule
    from tiled_gridpull.kernels.bridge import fit_columns

    rule = BridgeRule()
    cols = np.stack(np.meshgrid(np.arange(24.0, 72.0), np.arange(24.0, 72.0), indexing="ij"), -1).reshape(-1, 2)
    counts = {(k, r): [0, 0] for k in KINDS for r in ("before", "shipped")}
    for kind, rep, z in terrains(trials):
        truth = z(cols[:, 0], cols[:, 1])
        args = (rep, 2.0, cols, 24.0, rule.skip, int(rule.max_gap_deg // 30), rule.rms_tol, rule.step_tol,
                rule.max_slope, np.full((N, N, 2), np.nan), 2.0)
        for name, tol in (("before", 0.0), ("shipped", rule.object_tol)):
            off = np.abs(fit_columns(*args, tol, rule.ground_share)[:, 0] - truth)
            counts[kind, name][0] += int((off > 1.0).sum())
            counts[kind, name][1] += int((off <= 0.5).sum())
    return [{"terrain": k, "trials": trials // len(KINDS), "object_tol": rule.object_tol,
             "wrong_before": counts[k, "before"][0], "wrong_shipped": counts[k, "shipped"][0],
             "right_before": counts[k, "before"][1], "right_shipped": counts[k, "shipped"][1]} for k in KINDS]


def table(rows: list[dict]) -> str:
    return markdown_table(rows, [("run", "run", "s"), ("terrain", "terrain", "s"), ("trials", "trials", "d"),
                                 ("object_tol", "object_tol (cells)", "g"),
                                 ("wrong_before", "wrong: every sample ground", ",d"),
                                 ("wrong_shipped", "wrong: things left out", ",d"),
                                 ("right_before", "right: every sample ground", ",d"),
                                 ("right_shipped", "right: things left out", ",d")])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=400)
    a = ap.parse_args()
    run_id = time.strftime("%Y-%m-%d %H:%M:%S")
    rows = run(a.trials)
    for r in rows:
        r["run"] = run_id
        append_jsonl(RESULTS, r)
    print(table(rows))


if __name__ == "__main__":
    main()
