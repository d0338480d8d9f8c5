"""The GridPull paper's evaluation, re-run where public data allows (issue 7).

Every run is a fresh process (``benchmarks.shape_worker``), scored with exact point-to-mesh distances against the
shared ground truth (normalised so the bbox's longest side is 1). Results append to
``benchmarks/results/paper_eval.jsonl``; ``python benchmarks/report.py`` renders them into BENCHMARKS.md.

Usage::

    python -m benchmarks.paper_eval noise        # 0.5 % and 1 % noise: default, both noisy presets, Poisson
    python -m benchmarks.paper_eval scans        # the 10 real bunny range scans merged: ours vs Poisson
    python -m benchmarks.paper_eval normals      # exact normals: normal_weight 0 vs 1
    python -m benchmarks.paper_eval open         # half-sphere, terrain, bunny: --mode udf vs sdf
    python -m benchmarks.paper_eval resolution   # R = 32 .. 512 (bunny)
    python -m benchmarks.paper_eval losses       # pull; +grad; +TV; +surface (bunny)
    python -m benchmarks.paper_eval bandwidth    # M2 = 3, 14, 30, all (bunny)
    python -m benchmarks.paper_eval points       # 10k, 100k, 1M points (bunny)
    python -m benchmarks.paper_eval all
"""

from __future__ import annotations

import argparse
import os
import time

from benchmarks.common import REPO, append_jsonl, machine, require_shared, run_isolated

RESULTS = REPO / "benchmarks" / "results" / "paper_eval.jsonl"
SUITES = ("noise", "scans", "normals", "open", "resolution", "losses", "bandwidth", "points")
NOISE_MESHES = ("bunny", "armadillo", "fandisk", "abc_00011084", "abc_00016513", "abc_00994122")


def _noisy_config(name: str = "noisy") -> dict:
    from tiled_gridpull.config import load_config_file

    return load_config_file(REPO / "configs" / f"{name}.yaml")


#: Only runs whose label contains this string (``--only``), e.g. "preset" to re-run one row kind.
ONLY = ""
#: Meshes for the noise and normals suites (``--meshes``; default: all of ``NOISE_MESHES`` for noise).
MESHES: tuple = ()


def run(suite: str, label: str, method: str = "gridpull", config: dict | None = None, mesh: str = "bunny",
        points: int = 100_000, **extra) -> dict | None:
    if ONLY not in label:
        return None
    args = {"mesh": mesh, "points": points, "method": method, "config": config or {}, "seed": 0, **extra}
    out = run_isolated("benchmarks.shape_worker", args)
    row = {"suite": suite, "label": label, "date": time.strftime("%Y-%m-%d %H:%M"), **out}
    append_jsonl(RESULTS, row)
    print(f"{suite:10s} {mesh:10s} {label:28s} wall {out['wall_s']:7.1f} s  "
          f"CD-L1 {out['chamfer_l1_exact'] * 1e3:7.3f}e-3"
          f"  NC {out['normal_consistency_exact']:.4f}  pieces {out['components']}", flush=True)
    return out


def poisson(cloud_points: int) -> dict:
    return {"depth": 9, "normal_radius": 0.1 if cloud_points >= 50_000 else 0.2}


def noise() -> None:
    noisy, very = _noisy_config(), _noisy_config("very_noisy")
    for level in (0.005, 0.01):
        for mesh in MESHES or NOISE_MESHES:
            tag = f"{level * 100:g}%"
            run("noise", f"{tag} default", mesh=mesh, noise=level)
            run("noise", f"{tag} noisy preset", config=noisy, mesh=mesh, noise=level)
            run("noise", f"{tag} very_noisy preset", config=very, mesh=mesh, noise=level)
            run("noise", f"{tag} poisson", "poisson", poisson(100_000), mesh=mesh, noise=level)


def scans() -> None:
    run("scans", "default", scans=True)
    run("scans", "noisy preset", config=_noisy_config(), scans=True)
    run("scans", "poisson", "poisson", {"depth": 9, "normal_radius": 0.05}, scans=True)
    # the scans leave the bunny's base open: the unsigned mode keeps it open
    run("scans", "udf", config={"mode": "udf"}, scans=True)


def normals() -> None:
    for mesh in MESHES or NOISE_MESHES[:3]:
        run("normals", "normal_weight 0", config={"normal_weight": 0.0}, mesh=mesh, normals=True)
        run("normals", "normal_weight 1", config={"normal_weight": 1.0}, mesh=mesh, normals=True)


def open_surfaces() -> None:
    """Open surfaces: the unsigned mode (with and without its signed polish, dense and sparse) beside the signed
    one on the same clouds; the bunny, whose scanned mesh is open at the base, in both modes."""
    udf = {"mode": "udf"}
    for mesh in ("half_sphere", "terrain"):
        run("open", "udf", config=udf, mesh=mesh)
        run("open", "udf, no polish", config={**udf, "udf_polish": 0}, mesh=mesh)
        run("open", "udf, 10k points", config=udf, mesh=mesh, points=10_000)
        run("open", "sdf", mesh=mesh)
    run("open", "udf", config=udf, mesh="bunny")
    run("open", "sdf", mesh="bunny")


def resolution() -> None:
    for res in (32, 64, 128, 256, 512):
        run("resolution", f"R={res}", config={"resolution": res})


def losses() -> None:
    # gradient consistency has a coarse weight (gamma) and a refinement weight (refine_gamma)
    off = {"alpha": 0.0, "beta": 0.0, "gamma": 0.0, "refine_gamma": 0.0}
    run("losses", "pull", config=off)
    run("losses", "pull + grad", config={**off, "gamma": 0.005, "refine_gamma": 3.0})
    run("losses", "pull + grad + TV", config={**off, "gamma": 0.005, "refine_gamma": 3.0, "alpha": 1.0})
    run("losses", "pull + grad + TV + surface", config={})


def bandwidth() -> None:
    # M2 is the TV band at the coarsest level, refine_m2 at the finer ones; both must hold M1 = 3
    for m2 in (3, 14, 30):
        run("bandwidth", f"M2={m2}", config={"m2": m2, "refine_m2": max(3, min(m2, 30))})
    # TV over every vertex of every level: dilations wider than each level's padded lattice (R = 256:
    # 70 coarse cells, 280 fine ones)
    run("bandwidth", "M2=all", config={"m2": 64, "refine_m2": 256})


def points() -> None:
    for n in (10_000, 100_000, 1_000_000):
        run("points", f"{n // 1000}k points", points=n)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite", choices=(*SUITES, "all"))
    ap.add_argument("--only", default="", help="only runs whose label contains this text")
    ap.add_argument("--meshes", nargs="+", default=[], choices=NOISE_MESHES)
    a = ap.parse_args()
    global ONLY, MESHES
    ONLY, MESHES = a.only, tuple(a.meshes)
    require_shared()
    append_jsonl(RESULTS, {"suite": "machine", "date": time.strftime("%Y-%m-%d %H:%M"), **machine(),
                           "load": os.getloadavg()[0]})
    for name in SUITES:
        if a.suite in (name, "all"):
            globals()["open_surfaces" if name == "open" else name]()


def render(rows: list[dict]) -> str:
    """Markdown tables of the latest row per (suite, mesh, label)."""
    latest: dict = {}
    for i, r in enumerate(rows):
        if r.get("suite") in SUITES:
            latest[(r["suite"], r.get("mesh"), r["label"])] = (i, r)
    out = []
    for suite in SUITES:
        # in the order of their latest runs: a suite run in full comes out in the order it runs
        sel = [r for (s, _, _), (_, r) in sorted(latest.items(), key=lambda kv: kv[1][0]) if s == suite]
        if not sel:
            continue
        if suite == "noise":
            # noise level, then mesh, then run kind in the order the suite runs them
            kinds = ("default", "noisy preset", "very_noisy preset", "poisson")
            sel.sort(key=lambda r: (float(r["label"].split("%")[0]), NOISE_MESHES.index(r["mesh"]),
                                    kinds.index(r["label"].split(" ", 1)[1])))
        # open surfaces: how many boundary loops (ground truth: half-sphere and terrain 1, bunny 5)
        loops = suite == "open"
        out += [f"### {suite}", "", "| mesh | run | CD-L1 x1e3 | CD-L2 x1e5 | NC | F@0.01 | Hausdorff | pieces | "
                f"{'boundary loops | ' if loops else ''}watertight | wall s | peak MB |",
                "|---|---|---|---|---|---|---|---|" + ("---|" if loops else "") + "---|---|---|"]
        for r in sel:
            out.append(f"| {r['mesh']}{' (scans)' if r.get('scans') else ''} | {r['label']} | "
                       f"{r['chamfer_l1_exact'] * 1e3:.3f} | {r['chamfer_l2_exact'] * 1e5:.3f} | "
                       f"{r['normal_consistency_exact']:.4f} | {r['fscore_exact@0.01']:.3f} | "
                       f"{r['hausdorff_exact']:.4f} | {r['components']} | "
                       + (f"{r.get('boundary_loops', '-')} | " if loops else "")
                       + f"{'yes' if r['watertight'] else 'no'} | {r['wall_s']:.1f} | {r['peak_rss_mb']:.0f} |")
        out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    main()
