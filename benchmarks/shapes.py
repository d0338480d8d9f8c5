"""Single-shape benchmarks: GridPull beside Open3D screened Poisson on the shared meshes.

Every run is a fresh process (``benchmarks.shape_worker``) so peak RSS is that run's own; numba's on-disk cache is
warm (``compile`` measures the cold start apart). Results append to ``benchmarks/results/shapes.jsonl``;
``python benchmarks/report.py`` turns them into BENCHMARKS.md.

Usage::

    python -m benchmarks.shapes accuracy        # every mesh: 100k, 10k and noisy clouds, GridPull vs Poisson
    python -m benchmarks.shapes speed --repeats 3   # bunny: R = 128/256/512, 10k/100k/1M points, medians
    python -m benchmarks.shapes paper           # the paper's literal single-level recipe beside ours
    python -m benchmarks.shapes grid --meshes bunny armadillo   # 10k/100k/1M points x R = 128/256/512 vs Poisson
    python -m benchmarks.shapes compile         # numba compile time (empty cache) vs a warm run
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time

from benchmarks.common import MESHES, REPO, append_jsonl, machine, require_shared, run_isolated

RESULTS = REPO / "benchmarks" / "results" / "shapes.jsonl"
CLOUDS = {"100k": (100_000, 0.0), "10k": (10_000, 0.0), "noisy0.5%": (100_000, 0.005)}


def record(suite: str, row: dict) -> None:
    row = {"suite": suite, "date": time.strftime("%Y-%m-%d %H:%M"), **row}
    append_jsonl(RESULTS, row)
    keys = ("mesh", "cloud", "method", "resolution", "wall_s", "peak_rss_mb", "chamfer_l1_exact",
            "normal_consistency_exact", "watertight", "components")
    print("  ".join(f"{k}={row[k]:.4g}" if isinstance(row.get(k), float) else f"{k}={row.get(k)}" for k in keys),
          flush=True)


def run(suite: str, mesh: str, cloud: str, method: str, config: dict | None = None, **extra) -> dict:
    points, noise = CLOUDS.get(cloud, (None, 0.0))
    args = {"mesh": mesh, "points": extra.pop("points", points), "noise": noise, "method": method,
            "config": config or {}, "seed": 0, **extra}
    out = run_isolated("benchmarks.shape_worker", args)
    out["cloud"] = cloud
    record(suite, out)
    return out


def poisson_config(cloud: str) -> dict:
    # Open3D's normal estimation radius must see ~30 neighbours: wider for the sparse cloud
    return {"depth": 9, "normal_radius": 0.1 if cloud != "10k" else 0.2}


def accuracy(meshes, clouds, methods=("gridpull", "poisson")) -> None:
    for mesh in meshes:
        for cloud in clouds:
            if "gridpull" in methods:
                run("accuracy", mesh, cloud, "gridpull")
            if "poisson" in methods:
                run("accuracy", mesh, cloud, "poisson", poisson_config(cloud))


def speed(repeats: int, extras: bool = True) -> None:
    """Bunny, 100k points, R = 256: GridPull and Poisson interleaved ``repeats`` times (same machine load); then
    R = 128 / 512 and 10k / 1M points once each unless ``extras`` is False."""
    for _ in range(repeats):
        run("speed", "bunny", "100k", "gridpull", {"resolution": 256}, resolution=256)
        run("speed", "bunny", "100k", "poisson", poisson_config("100k"))
    if not extras:
        return
    for res in (128, 512):
        run("speed", "bunny", "100k", "gridpull", {"resolution": res}, resolution=res)
    for n in (10_000, 1_000_000):
        run("speed", "bunny", "100k", "gridpull", {"resolution": 256}, points=n, resolution=256)


#: Point counts and resolutions of the ``grid`` suite (issue 4's single-shape matrix).
GRID_POINTS = (10_000, 100_000, 1_000_000)
GRID_RESOLUTIONS = (128, 256, 512)


def grid(meshes) -> None:
    """Every mesh at 10k / 100k / 1M points and R = 128 / 256 / 512, with Poisson on the same cloud (same seed)
    once per point count, so the report can give each GridPull run as a ratio to Poisson."""
    for mesh in meshes:
        for n in GRID_POINTS:
            label = f"{n // 1000}k"
            run("grid", mesh, label, "poisson", poisson_config("10k" if n <= 10_000 else "100k"), points=n)
            for res in GRID_RESOLUTIONS:
                run("grid", mesh, label, "gridpull", {"resolution": res}, points=n, resolution=res)


def paper(meshes) -> None:
    from tiled_gridpull.config import load_config_file

    cfg = load_config_file(REPO / "configs" / "paper.yaml")
    for mesh in meshes:
        run("paper", mesh, "100k", "gridpull-paper", cfg)


def compile_time() -> None:
    """First run with an empty numba cache minus a warm run, same process count, same small cloud."""
    tmp = tempfile.mkdtemp(prefix="numba-cold-")
    try:
        os.environ["NUMBA_CACHE_DIR"] = tmp
        cold = run("compile", "bunny", "10k", "gridpull", {"resolution": 64}, points=10_000, cache="cold")
        warm = run("compile", "bunny", "10k", "gridpull", {"resolution": 64}, points=10_000, cache="warm")
        record("compile", {"mesh": "bunny", "method": "compile", "compile_s": cold["wall_s"] - warm["wall_s"],
                           "cold_s": cold["wall_s"], "warm_s": warm["wall_s"]})
    finally:
        os.environ.pop("NUMBA_CACHE_DIR", None)
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite", choices=("accuracy", "speed", "paper", "compile", "grid", "all"))
    ap.add_argument("--meshes", nargs="+", default=list(MESHES), choices=list(MESHES))
    ap.add_argument("--clouds", nargs="+", default=list(CLOUDS), choices=list(CLOUDS))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--methods", nargs="+", default=["gridpull", "poisson"], choices=["gridpull", "poisson"],
                    help="accuracy: which methods to run (Poisson does not change when our solver does)")
    ap.add_argument("--no-extras", action="store_true", help="speed: only the R = 256 pair")
    a = ap.parse_args()
    require_shared()
    record("machine", {"method": "machine", **machine(), "load": os.getloadavg()[0]})
    if a.suite in ("compile", "all"):
        compile_time()
    if a.suite in ("accuracy", "all"):
        accuracy(a.meshes, a.clouds, a.methods)
    if a.suite in ("paper", "all"):
        paper(a.meshes[:2])
    if a.suite == "grid":
        grid(a.meshes)
    if a.suite in ("speed", "all"):
        speed(a.repeats, not a.no_extras)


if __name__ == "__main__":
    main()
