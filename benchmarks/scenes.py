"""Scene benchmarks (issue 4): the synthetic street at several sizes and the shared real LiDAR files, end to end
through the command line on the default local Dask cluster.

For each run: wall time of ``tiled-gridpull reconstruct`` (sample generation not counted), peak RSS of the
biggest process (largest tile task or the driver, from the job's sidecar), points per second, the per-stage
split (partition, solve, blend, mesh, merge; solve/blend/mesh as summed task-seconds over the workers), and for
the synthetic street the accuracy against its ground-truth mesh over the observed region. Results append to
``benchmarks/results/scenes.jsonl``; ``python benchmarks/report.py`` renders them into BENCHMARKS.md.

Usage::

    python -m benchmarks.scenes street --points 1000000 14000000 [--workers 2]
    python -m benchmarks.scenes workers --points 1000000          # 1 vs 2 workers, same cloud
    python -m benchmarks.scenes lidar                              # ../shared/data/lidar files
    python -m benchmarks.scenes tiles --points 4000000 --copies 1 2 4 8   # time vs tile count, fixed density
    python -m benchmarks.scenes wide --points 1000000 14000000 [--variants today default]
        # a 200 m x 200 m grid of streets beside Open3D screened Poisson (depth 11) in the same run
    python -m benchmarks.scenes classes --points 300000 --variants default
        # the demo street scored per kind of object (poles, cars, ...), beside Poisson in the same run
    python -m benchmarks.scenes thin                               # a wall 0.05-0.3 m thick seen from both sides
    python -m benchmarks.scenes footprint [--grid | --grid-only]   # bridging scan-line gaps: footprint recall
        # and precision on synthetic streets, held-out points on a KITTI frame and the airborne files, beside
        # trimmed Poisson, GridPull with and without bridging, same run

``wide`` runs, per cloud, Poisson once (:mod:`benchmarks.poisson_scene`: its normal estimation included, file in
-> mesh out, its own process) and GridPull once per variant: ``default`` is configs/scene.yaml as shipped,
``today`` pins the fixed schedule the scene settings had before the content-scaled one (every level 800
iterations of 50,000 queries), so both are measured in the same run on the same machine.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, append_jsonl, machine, markdown_table
from tiled_gridpull.config import recorded_settings

RESULTS = REPO / "benchmarks" / "results" / "scenes.jsonl"
CLI = [sys.executable, "-m", "tiled_gridpull"]
#: Shared LiDAR files and the cell size each is run at (its units: metres, or US feet for Autzen).
LIDAR = {"ahn3_cropped_2.laz": 0.5, "autzen_trim.laz": 2.0}


def record(row: dict) -> None:
    row = {"date": time.strftime("%Y-%m-%d %H:%M"), **row}
    append_jsonl(RESULTS, row)
    keys = ("scene", "points", "workers", "tiles", "wall_s", "points_per_s", "peak_rss_mb", "chamfer_l1_m")
    print("  ".join(f"{k}={row[k]:.4g}" if isinstance(row.get(k), float) else f"{k}={row.get(k)}" for k in keys),
          flush=True)


def reconstruct(src: Path, out: Path, workers: int, extra: list[str]) -> dict:
    """Run the CLI job; returns wall time and the facts read back from its sidecar."""
    cmd = [*CLI, "reconstruct", str(src), "-o", str(out), "--workers", str(workers), "-q", *extra]
    # a job directory left by an earlier run would be resumed, not recomputed (the workers suite reruns a cloud)
    shutil.rmtree(out.with_suffix(".job"), ignore_errors=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    wall = time.perf_counter() - t0
    side = json.loads(out.with_suffix(".json").read_text())
    solves = side.get("tile_summaries", [])
    meshes = side.get("mesh_summaries", [])
    mem = side.get("memory_mb", {})
    t = side["timings_s"]
    mesh_s = sum(m.get("time_s", 0.0) for m in meshes)
    blend_s = sum(m.get("blend_s", 0.0) for m in meshes)
    return {
        "wall_s": wall, "tiles": side["tiles"]["solved"], "tiles_planned": side["tiles"]["planned"],
        "points": side["input"].get("points") if isinstance(side.get("input"), dict) else None,
        "peak_rss_mb": max(float(v) for v in mem.values() if isinstance(v, (int, float))) if mem else None,
        "memory_mb": mem,
        "stages_s": {"partition": t.get("partition"), "solve_task_s": sum(s.get("time_s", 0.0) for s in solves),
                     "blend_task_s": blend_s, "mesh_task_s": mesh_s - blend_s,
                     "solve_and_mesh_wall": t.get("solve_and_mesh"), "merge": t.get("merge"),
                     "total": t.get("total")},
        "faces": side["mesh"]["n_faces"] if isinstance(side.get("mesh"), dict) else None,
        "query_pool": recorded_settings(side.get("config", {})).get("query_pool", 0),
    }


def evaluate(mesh: Path, gt: Path, observed: Path) -> dict:
    out = subprocess.run([*CLI, "evaluate", str(mesh), str(gt), "--observed", str(observed), "--json",
                          "--thresholds", "0.05", "0.1", "0.2"], check=True, capture_output=True, text=True).stdout
    res = json.loads(out)
    return {"chamfer_l1_m": res["chamfer_l1_exact"], "normal_consistency": res["normal_consistency_exact"],
            "fscore_0.1m": res.get("fscore_exact@0.1", res.get("fscore@0.1")), "components": res["components"],
            "boundary_edges": res["boundary_edges"]}


def scene_args(overrides: dict) -> list[str]:
    """Command-line arguments for configs/scene.yaml with ``overrides`` (flat names) given as ``--set``, which win
    over the file whatever its spelling of the same setting (a flat key appended to the file would clash with
    its sectioned one)."""
    args = ["--config", str(REPO / "configs" / "scene.yaml")]
    for k, v in overrides.items():
        args += ["--set", f"{k}={json.dumps(v)}"]
    return args


def street(n_points: int, workers: int, work: Path, overrides: dict | None = None) -> None:
    from tiled_gridpull.synthetic.street_sample import make_street_sample

    t0 = time.perf_counter()
    sample = make_street_sample(work / f"street_{n_points}", n_points=n_points, origin=(500000.0, 4000000.0, 100.0))
    t_sample = time.perf_counter() - t0
    out = work / f"street_{n_points}" / "mesh.ply"
    row = reconstruct(sample["laz"], out, workers, scene_args(overrides or {}))
    row.update(evaluate(out, sample["gt_mesh"], sample["laz"]))
    row.update(scene="street (synthetic)", points=sample["n_points"], workers=workers, sample_s=t_sample,
               points_per_s=sample["n_points"] / row["wall_s"], cell_m=0.1, overrides=overrides or {})
    record(row)


#: Length of the street slab the ``tiles`` suite repeats: one tile core of configs/scene.yaml (256 cells of 0.1 m).
SLAB_M = 25.6


def slab_copies(xyz, copies: int, cell: float = 0.1, length: float = SLAB_M):
    """The middle ``length`` metres of a street scan along x, repeated ``copies`` times end to end.

    Every copy has the same points, so every tile the job lays over the result has the same density: the slab
    starts on a cell boundary and keeps half a cell clear of both ends, so the job's tile cores (which start at
    the first occupied cell and are ``length`` long) line up with the copies (``copies`` tiles along x).

    Parameters
    ----------
    xyz : (N, 3) float64
        Street points (m), local frame (origin 0).
    copies : int

    Returns
    -------
    (M, 3) float64
    """
    import numpy as np

    x = xyz[:, 0]
    x0 = np.floor((0.5 * (x.min() + x.max()) - 0.5 * length) / cell) * cell
    keep = (x >= x0 + 0.5 * cell) & (x < x0 + length - 0.5 * cell)
    slab = xyz[keep] - [x0, 0.0, 0.0]
    return np.concatenate([slab + [c * length, 0.0, 0.0] for c in range(copies)])


def tile_count(n_points: int, copies: list[int], workers: int, work: Path) -> None:
    """Time and memory against the number of occupied tiles at a fixed point density (issue 4's "time linear in
    the number of occupied tiles"): a slab of the ``n_points`` street repeated 1, 2, 4, ... times along x."""
    from tiled_gridpull.io import read_points
    from tiled_gridpull.synthetic.lidar_files import write_las
    from tiled_gridpull.synthetic.street_sample import make_street_sample

    sample = make_street_sample(work / f"street_{n_points}", n_points=n_points)
    xyz = read_points(sample["laz"]).xyz
    for k in copies:
        src = write_las(work / f"slab_x{k}.laz", slab_copies(xyz, k))
        out = work / f"slab_x{k}.ply"
        row = reconstruct(src, out, workers, ["--config", str(REPO / "configs" / "scene.yaml")])
        row.update(scene=f"street slab x{k}", suite="tiles", copies=k, source_points=sample["n_points"],
                   workers=workers, cell_m=0.1)
        row["points_per_s"] = (row["points"] or 0) / row["wall_s"]
        record(row)


def shared_lidar_files():
    """``(name, cell, path)`` of each shared LiDAR file of ``LIDAR`` that exists (a line for each one missing)."""
    folder = REPO.parent / "shared" / "data" / "lidar"
    for name, cell in LIDAR.items():
        src = folder / name
        if src.exists():
            yield name, cell, src
        else:
            print(f"skip {name}: not in ../shared/data/lidar", flush=True)


def lidar(workers: int, work: Path) -> None:
    for name, cell, src in shared_lidar_files():
        out = work / (src.stem + ".ply")
        row = reconstruct(src, out, workers, ["--config", str(REPO / "configs" / "scene.yaml"),
                                              "--voxel-size", str(cell), "--tile-size", str(256 * cell),
                                              "--overlap", str(32 * cell)])
        row.update(scene=name, workers=workers, cell=cell)
        row["points_per_s"] = (row["points"] or 0) / row["wall_s"]
        record(row)


#: The scene schedule before issue 16 (fixed: 3 levels x 800 iterations x 50,000 queries), as overrides.
TODAY = {"queries_per_point": 0, "iterations": 800, "coarse_iterations": 800, "middle_iterations": 0,
         "lr_step": 400, "refine_lr_step": 200, "m2": 25}
#: Tiled denoising as measured on the noisy demo street (docs/solver.md, "Denoising tiles").
DENOISE = {"denoise": 2, "denoise_neighbors": 32, "denoise_radius": 2.0}
VARIANTS = {"default": {}, "today": TODAY, "denoise": DENOISE, "no bridge": {"bridge": 0},
            "objects 0": {"bridge_objects": 0}}


def variant_settings(variant: str) -> str:
    """How a variant's settings read in a table: the shipped config, the fixed schedule, or its overrides."""
    if variant == "default":
        return "configs/scene.yaml"
    if variant == "today":
        return "fixed 3 x 800 x 50k"
    return "configs/scene.yaml + " + ", ".join(f"{k} {v:g}" for k, v in VARIANTS.get(variant, {}).items())


def poisson_scene(src: Path, out: Path, depth: int = 11, sensor=None) -> dict:
    """Open3D screened Poisson on ``src`` in a fresh process (:mod:`benchmarks.poisson_scene`); ``sensor``
    (x, y, z) orients its normals towards a scanner instead of up."""
    from benchmarks.common import run_isolated

    return run_isolated("benchmarks.poisson_scene", {"input": str(src), "output": str(out), "depth": depth,
                                                     "sensor": sensor})


def wide(n_points: int, workers: int, work: Path, variants: list[str], depth: int = 11) -> None:
    """A grid of streets (about 200 m x 200 m, one sensor pass per street) at ``n_points``: Poisson, then each
    GridPull variant, on the same file in the same run; accuracy against the ground truth over the observed
    region for all of them."""
    from tiled_gridpull.synthetic.street_sample import make_street_sample

    t0 = time.perf_counter()
    sample = make_street_sample(work / f"grid_{n_points}", n_points=n_points, origin=(500000.0, 4000000.0, 100.0),
                                layout="grid")
    t_sample = time.perf_counter() - t0
    src, gt = sample["laz"], sample["gt_mesh"]
    base = {"scene": "grid of streets (synthetic)", "suite": "wide", "points": sample["n_points"],
            "workers": workers, "sample_s": t_sample, "cell_m": 0.1}
    pout = work / f"grid_{n_points}" / "poisson.ply"
    poisson = poisson_scene(src, pout, depth)
    poisson.update(evaluate(pout, gt, src))
    record(poisson_row(base, poisson, depth))
    for name in variants:
        out = work / f"grid_{n_points}" / f"gridpull_{name}.ply"
        row = reconstruct(src, out, workers, scene_args(VARIANTS[name]))
        row.update(evaluate(out, gt, src))
        record(gridpull_row(row, base, poisson, name, tile_costs=tile_costs(out)))


def classes(n_points: int, workers: int, work: Path, variants: list[str], depth: int = 11) -> None:
    """The demo street scored per class of ground-truth faces (terrain, buildings, poles, trees, cars), Poisson and
    each GridPull variant in the same run: thin objects hold too little of the area to show in the scene-wide
    Chamfer distance."""
    from tiled_gridpull.io import read_mesh, read_points
    from tiled_gridpull.metrics import class_scores
    from tiled_gridpull.synthetic.street_sample import make_street_sample

    sample_dir = work / f"street_{n_points}"
    sample = make_street_sample(sample_dir, n_points=n_points, origin=(500000.0, 4000000.0, 100.0))
    face_classes = json.loads(Path(sample["meta"]).read_text())["face_classes"]
    gt = read_mesh(sample["gt_mesh"])
    observed = read_points(sample["laz"]).xyz
    base = {"scene": "street (synthetic)", "suite": "classes", "points": sample["n_points"], "workers": workers}

    def score(mesh_path: Path) -> dict:
        return {"classes": class_scores(read_mesh(mesh_path), gt, face_classes, n_samples=200_000, tau=0.05,
                                        observed=observed, observed_radius=0.2)}

    pout = sample_dir / "poisson.ply"
    poisson = poisson_scene(sample["laz"], pout, depth)
    record(poisson_row(base, poisson, depth, **score(pout)))
    for v in variants:
        out = sample_dir / f"gridpull_{v}.ply"
        row = reconstruct(sample["laz"], out, workers, scene_args(VARIANTS[v]))
        record(gridpull_row(row, base, poisson, v, **score(out)))


#: wall thicknesses (m) of the ``thin`` suite, at 0.1 m cells
THIN_WALLS = (0.05, 0.1, 0.15, 0.2, 0.3)


def thin_walls(workers: int, work: Path, thicknesses=THIN_WALLS) -> None:
    """A wall scanned from both sides (:func:`tiled_gridpull.synthetic.fence.fence_scene`), configs/scene.yaml at
    0.1 m cells: does each face of the wall come out? Two placements against the lattice (vertices at multiples
    of 0.1 m): the wall centred on a vertex plane, and with its front face on one (no vertex strictly inside a
    wall of a cell or less)."""
    from tiled_gridpull.io import read_mesh
    from tiled_gridpull.metrics import class_scores
    from tiled_gridpull.synthetic.fence import fence_scene

    for t in thicknesses:
        for place, centre in (("centred on a vertex plane", 0.0), ("front face on a vertex plane", t / 2)):
            d = work / f"fence_{t:g}_{centre:g}"
            scene = fence_scene(d / "seq", t, centre)
            out = d / "mesh.ply"
            row = reconstruct(scene["sequence"], out, workers, [*scene_args({}), "--voxel-size", "0.1"])
            mesh = read_mesh(out)
            scores = class_scores(mesh, scene["gt"], scene["classes"], n_samples=100_000, tau=0.02,
                                  observed=scene["points"], observed_radius=0.05)
            record({"scene": "wall seen from both sides (synthetic)", "suite": "thin", "method": "gridpull",
                    "thickness_m": t, "placement": place, "cell": 0.1, "workers": workers,
                    "wall_s": row["wall_s"], "classes": scores,
                    "boundary_edges": int(mesh.topology.boundary_edges), "components": int(mesh.topology.components)})


def poisson_row(base: dict, poisson: dict, depth: int, **extra) -> dict:
    """A results row of a Poisson run (:func:`poisson_scene` output) beside the GridPull rows of the same run."""
    return {**base, **{k: v for k, v in poisson.items() if k != "points"}, **extra, "method": "poisson",
            "variant": f"depth {depth}", "tiles": None, "tiles_planned": None, "stages_s": {},
            "points_per_s": base["points"] / poisson["wall_s"], "x_poisson_time": 1.0, "x_poisson_memory": 1.0}


def gridpull_row(row: dict, base: dict, poisson: dict, variant: str, **extra) -> dict:
    """A results row of a GridPull job (:func:`reconstruct` output) with its ratios to Poisson's run."""
    return {**row, **base, **extra, "method": "gridpull", "variant": variant, "overrides": VARIANTS[variant],
            "points_per_s": base["points"] / row["wall_s"], "x_poisson_time": row["wall_s"] / poisson["wall_s"],
            "x_poisson_memory": (row["peak_rss_mb"] or 0.0) / poisson["peak_rss_mb"]}


def footprint_scores_of(mesh: Path, gt: Path, laz: Path, trajectory: Path | None = None) -> dict:
    """The footprint yardstick (:func:`tiled_gridpull.metrics.footprint_scores`, R = 1.5 and 3 m, tau 0.1 m) and
    the observed-region scores (:func:`evaluate`) of a scene mesh; with the scan's ``trajectory`` (CSV: time, x,
    y, z) also the share of the footprint some sensor position sees and the recall there."""
    import numpy as np

    from tiled_gridpull.io import read_mesh, read_points
    from tiled_gridpull.metrics import footprint_scores

    truth = read_mesh(gt)
    seen_by = None
    if trajectory is not None:
        from tiled_gridpull.synthetic.lidar import visible_from

        sensors = np.loadtxt(trajectory, delimiter=",", skiprows=1, ndmin=2)[:, 1:4]

        def seen_by(p):
            return visible_from(truth, p, sensors)
    fp = footprint_scores(read_mesh(mesh), truth, read_points(laz).xyz, seen_by=seen_by)
    return {**evaluate(mesh, gt, laz), **{k: v for k, v in fp.items() if k != "tau"}}


def footprint(workers: int, work: Path, grid: bool = False, synthetic_only: bool = False,
              grid_only: bool = False) -> None:
    """Gaps between scan lines (issue 36): on synthetic streets the footprint recall (truth within 1.5 and 3 m of
    a point, hits within 0.1 m), the mesh's precision, boundary edges and pieces, the observed-region scores; on
    a real KITTI frame (sensor at the origin, 0.3 m cells) and the airborne files the held-out points' distance.
    Trimmed Poisson (depth 11 synthetic, 10 real; sensor-oriented normals on the KITTI frame), GridPull with the
    shipped configs and with ``bridge 0``, same run. The synthetic scenes are reconstructed with their trajectory
    (sensor origins, as a mapping car delivers them: walls face the street, shadows stay unbridged) and scored
    also over what some sensor position sees."""
    from tiled_gridpull.io import read_points
    from tiled_gridpull.synthetic.street_sample import make_street_sample

    scenes = [("demo street (4 frames)", {"n_points": 300_000}), ("drive (16 frames 1 m apart)",
                                                                   {"n_points": 300_000, "frames": 16})]
    grid_scene = ("grid of streets", {"n_points": 1_000_000, "layout": "grid"})
    if grid_only:
        scenes = [grid_scene]
    elif grid:
        scenes.append(grid_scene)
    for name, kw in scenes:
        d = work / name.split()[0]
        sample = make_street_sample(d, origin=(500000.0, 4000000.0, 100.0), **kw)
        base = {"scene": name, "suite": "footprint", "points": sample["n_points"], "workers": workers, "cell": 0.1,
                "trajectory": bool(sample.get("trajectory"))}
        pout = d / "poisson.ply"
        poisson = poisson_scene(sample["laz"], pout, 11)
        traj = sample.get("trajectory")
        record(poisson_row(base, poisson, 11, **footprint_scores_of(pout, sample["gt_mesh"], sample["laz"], traj)))
        for v in ("default", "objects 0", "no bridge"):
            out = d / f"gridpull_{v.replace(' ', '_')}.ply"
            row = reconstruct(sample["laz"], out, workers,
                              [*scene_args(VARIANTS[v]), *(["--trajectory", str(traj)] if traj else [])])
            record(gridpull_row(row, base, poisson, v,
                                **footprint_scores_of(out, sample["gt_mesh"], sample["laz"], traj)))
    if synthetic_only or grid_only:
        return
    kitti = kitti_held_out(work)
    if kitti is not None:
        train, test, pout, poisson = kitti
        train_xyz = read_points(train).xyz
        base = {"scene": "KITTI 00 frame 0", "suite": "footprint", "points": len(train_xyz),
                "held_out": len(test), "workers": workers, "cell": 0.3}
        record(poisson_row(base, poisson, 10, **holdout_scores(pout, test, train_xyz, 0.3)))
        for v in ("default", "objects 0", "no bridge"):
            out = work / "kitti" / f"gridpull_{v.replace(' ', '_')}.ply"
            row = reconstruct(train, out, workers, ["--config", str(REPO / "configs" / "kitti.yaml"),
                                                    "--voxel-size", "0.3",
                                                    *[a for k, val in VARIANTS[v].items()
                                                      for a in ("--set", f"{k}={json.dumps(val)}")]])
            record(gridpull_row(row, base, poisson, v, **holdout_scores(out, test, train_xyz, 0.3)))
    holdout(workers, work, ["default", "no bridge"], 10, suite="footprint")


def kitti_held_out(work: Path):
    """KITTI frame 0 of the shared data with 10 % of its points held out (seeded): ``(train, test, poisson_mesh,
    poisson)``, the rest written as ``work/kitti/000000.bin``, the held-out (M, 3) float64 points, and Poisson
    (depth 10, normals towards the sensor at the origin) on the rest; None (and a line) where the frame is absent."""
    import numpy as np

    kitti = REPO.parent / "shared" / "data" / "kitti" / "000000.bin"
    if not kitti.exists():
        print("skip KITTI: ../shared/data/kitti/000000.bin absent", flush=True)
        return None
    scan = np.fromfile(kitti, np.float32).reshape(-1, 4)
    held = np.random.default_rng(0).random(len(scan)) < 0.1
    (work / "kitti").mkdir(exist_ok=True)
    train = work / "kitti" / "000000.bin"
    scan[~held].tofile(train)
    pout = work / "kitti" / "poisson.ply"
    return train, scan[held, :3].astype(np.float64), pout, poisson_scene(train, pout, 10, sensor=[0.0, 0.0, 0.0])


def holdout_scores(mesh_path: Path, test, train, cell: float) -> dict:
    """Distance of held-out points to a mesh (mean, median, 90th percentile, share within one cell), its boundary
    edges and pieces, and the share of its area farther than 2 cells from every point it was made from."""
    import numpy as np

    from tiled_gridpull.io import read_mesh
    from tiled_gridpull.metrics import point_to_mesh
    from tiled_gridpull.nearest import distances_to_cloud

    mesh = read_mesh(mesh_path)
    d, _ = point_to_mesh(test, mesh)
    topo = mesh.topology
    # mesh area farther than 2 cells from every meshed point: surface the data does not support
    tri = mesh.vertices[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    far = distances_to_cloud(tri.mean(axis=1), train, 2 * cell) > 2 * cell
    return {"holdout_mean": float(d.mean()), "holdout_median": float(np.median(d)),
            "holdout_p90": float(np.quantile(d, 0.9)), "holdout_within_cell": float(np.mean(d <= cell)),
            "boundary_edges": int(topo.boundary_edges), "components": int(topo.components),
            "area_far_share": float(area[far].sum() / area.sum())}


def holdout(workers: int, work: Path, variants: list[str], depth: int = 10, fraction: float = 0.1,
            suite: str = "holdout") -> None:
    """Real scans without a ground truth: hold out ``fraction`` of each shared LiDAR file's points (seeded), run
    Poisson and each GridPull variant on the rest, and score the distance of the held-out points to each mesh
    (:func:`holdout_scores`), same run; rows are recorded under ``suite``."""
    for name, cell, train, train_xyz, test, pout, poisson in lidar_held_out(work, depth, fraction):
        base = {"scene": name, "suite": suite, "points": len(train_xyz), "held_out": len(test),
                "workers": workers, "cell": cell}
        record(poisson_row(base, poisson, depth, **holdout_scores(pout, test, train_xyz, cell)))
        for v in variants:
            out = work / f"{train.stem}_{v.replace(' ', '_')}.ply"
            row = reconstruct(train, out, workers, [*scene_args(VARIANTS[v]),
                                                    "--voxel-size", str(cell), "--tile-size", str(256 * cell),
                                                    "--overlap", str(32 * cell)])
            record(gridpull_row(row, base, poisson, v, **holdout_scores(out, test, train_xyz, cell)))


def lidar_held_out(work: Path, depth: int, fraction: float = 0.1):
    """Each shared LiDAR file with ``fraction`` of its points held out (seeded): yields ``(name, cell, train,
    train_xyz, test, poisson_mesh, poisson)``, the rest written as ``work/<stem>_train.laz`` and its (N, 3)
    points, the held-out (M, 3) points, and Poisson (``depth``, normals up) on the rest."""
    import numpy as np

    from tiled_gridpull.io import read_points
    from tiled_gridpull.synthetic.lidar_files import write_las

    for name, cell, src in shared_lidar_files():
        xyz = read_points(src).xyz
        held = np.random.default_rng(0).random(len(xyz)) < fraction
        train = write_las(work / f"{src.stem}_train.laz", xyz[~held])
        pout = work / f"{src.stem}_poisson.ply"
        yield name, cell, Path(train), xyz[~held], xyz[held], pout, poisson_scene(train, pout, depth)


#: trade suite: parts smaller than these many cells along every axis dropped after the fact (2: as shipped)
TRADE_DUST = (2.0, 4.0, 6.0, 8.0)
#: trade suite, the most closing could do: every boundary loop of a part up to this many cells across, and every
#: loop up to ``TRADE_HOLE`` cells across, closed by a fan (after the shipped 2-cell specks go)
TRADE_PART, TRADE_HOLE = 32.0, 10.0


def trade(workers: int, work: Path) -> None:
    """What the counts of issue 36 would cost on real scans: a KITTI frame (10 % of its points held out, sensor
    at the origin) at 0.3 m and at the shipped 0.1 m cells, and the airborne files (10 % held out), each beside
    Poisson (depth 10, trimmed) in the same run. GridPull runs once with ``min_component_cells`` 0; its mesh is
    then cleaned after the fact: parts smaller than :data:`TRADE_DUST` cells dropped (2 cells is what the
    shipped pipeline drops: pieces against the held-out distance), and the most closing could do for the
    boundary edges (:data:`TRADE_PART`, :data:`TRADE_HOLE`: pinched fans removed, then each such loop closed by
    a fan of triangles). Rows go under suite ``trade``."""
    import numpy as np

    from tiled_gridpull.io import read_mesh, read_points, write_mesh
    from tiled_gridpull.mesh_repair import (boundary_loops, close_holes, component_boxes, remove_pinched_fans,
                                            remove_small_components)

    def variants(raw: Path, cell: float):
        mesh = read_mesh(raw)
        for cells in TRADE_DUST:
            kept, _ = remove_small_components(mesh, cells * cell)
            yield f"min_component_cells {cells:g}" + (" (shipped)" if cells == 2.0 else ""), kept
        kept, _ = remove_small_components(mesh, 2.0 * cell)
        kept, _ = remove_pinched_fans(kept, max_rounds=8)
        part, lo, hi = component_boxes(kept)
        across = (hi - lo).max(axis=1)
        loops = [lp for lp in boundary_loops(kept) if across[part[lp[0]]] <= TRADE_PART * cell
                 or np.ptp(kept.vertices[lp], axis=0).max() <= TRADE_HOLE * cell]
        yield f"closed: parts <= {TRADE_PART:g} cells, holes <= {TRADE_HOLE:g} cells", close_holes(kept, loops)

    def score(base: dict, poisson: dict, row: dict, raw: Path, test, train, cell: float) -> None:
        for variant, mesh in variants(raw, cell):
            path = raw.with_name(raw.stem + "_v.ply")
            write_mesh(mesh, path)
            record({**row, **base, **holdout_scores(path, test, train, cell), "method": "gridpull",
                    "variant": variant, "points_per_s": base["points"] / row["wall_s"],
                    "x_poisson_time": row["wall_s"] / poisson["wall_s"]})

    kitti = kitti_held_out(work)
    if kitti is not None:
        train, test, pout, poisson = kitti
        train_xyz = read_points(train).xyz
        for cell in (0.3, 0.1):
            base = {"scene": "KITTI 00 frame 0", "suite": "trade", "points": len(train_xyz),
                    "held_out": len(test), "workers": workers, "cell": cell}
            record(poisson_row(base, poisson, 10, **holdout_scores(pout, test, train_xyz, cell)))
            raw = work / "kitti" / f"gridpull_{cell:g}.ply"
            row = reconstruct(train, raw, workers, ["--config", str(REPO / "configs" / "kitti.yaml"),
                                                    "--voxel-size", str(cell), "--set", "min_component_cells=0"])
            score(base, poisson, row, raw, test, train_xyz, cell)
    for name, cell, train, train_xyz, test, pout, poisson in lidar_held_out(work, 10):
        base = {"scene": name, "suite": "trade", "points": len(train_xyz), "held_out": len(test),
                "workers": workers, "cell": cell}
        record(poisson_row(base, poisson, 10, **holdout_scores(pout, test, train_xyz, cell)))
        raw = work / f"{train.stem}_gridpull.ply"
        row = reconstruct(train, raw, workers, [*scene_args({"min_component_cells": 0}), "--voxel-size", str(cell),
                                                "--tile-size", str(256 * cell), "--overlap", str(32 * cell)])
        score(base, poisson, row, raw, test, train_xyz, cell)


def tile_costs(mesh: Path) -> list[dict]:
    """Per-tile solve cost from a job's sidecar: points, finest-band vertices and task seconds of every tile."""
    side = json.loads(mesh.with_suffix(".json").read_text())
    return [{"tile": s["tile"], "points": s.get("points_used", s.get("points")), "band": s.get("band_params"),
             "time_s": s.get("time_s"), "status": s.get("status")} for s in side.get("tile_summaries", [])]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite", choices=("street", "workers", "lidar", "tiles", "wide", "holdout", "classes", "thin",
                                      "footprint", "trade"))
    ap.add_argument("--grid", action="store_true", help="footprint: also the 1M-point grid of streets")
    ap.add_argument("--grid-only", action="store_true", help="footprint: the 1M-point grid of streets alone")
    ap.add_argument("--synthetic-only", action="store_true", help="footprint: the synthetic streets alone")
    ap.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), default=["today", "default"],
                    help="wide: GridPull settings to run beside Poisson")
    ap.add_argument("--depth", type=int, default=None,
                    help="wide, holdout: Poisson octree depth (default 11 for wide, 10 for holdout)")
    ap.add_argument("--copies", type=int, nargs="+", default=[1, 2, 4, 8],
                    help="tiles: how many times the street slab is repeated, one run each")
    ap.add_argument("--points", type=int, nargs="+", default=[1_000_000])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--keep", action="store_true", help="keep the work directory (printed)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="street: settings added to configs/scene.yaml for this run (YAML values), e.g. query_pool=0")
    a = ap.parse_args()
    import yaml

    overrides = {}
    for item in a.set:
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--set expects KEY=VALUE, got {item!r}")
        overrides[key] = yaml.safe_load(value)
    record({"scene": "machine", **machine(), "load": os.getloadavg()[0]})
    work = Path(tempfile.mkdtemp(prefix="tg-scenes-"))
    try:
        if a.suite == "street":
            for n in a.points:
                street(n, a.workers, work, overrides)
        elif a.suite == "holdout":
            holdout(a.workers, work, a.variants, a.depth or 10)
        elif a.suite == "thin":
            thin_walls(a.workers, work)
        elif a.suite == "trade":
            trade(a.workers, work)
        elif a.suite == "footprint":
            footprint(a.workers, work, a.grid, a.synthetic_only, a.grid_only)
        elif a.suite == "classes":
            classes(a.points[0], a.workers, work, a.variants, a.depth or 11)
        elif a.suite == "wide":
            for n in a.points:
                wide(n, a.workers, work, a.variants, a.depth or 11)
        elif a.suite == "tiles":
            tile_count(a.points[0], a.copies, a.workers, work)
        elif a.suite == "workers":
            for w in (1, 2):
                street(a.points[0], w, work)
        else:
            lidar(a.workers, work)
    finally:
        if a.keep:
            print(f"work directory: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


def render(rows: list[dict]) -> str:
    """Markdown table of every scene run (newest last)."""
    runs = [r for r in rows if r.get("scene") not in (None, "machine")
            and r.get("suite") not in ("tiles", "wide", "holdout", "classes", "thin", "footprint", "trade")]
    if not runs:
        return ""
    out = ["| date | scene | coarse thinning | query pool | points | workers | tiles | wall s | points/s | "
           "peak RSS MB | partition s | solve task-s | "
           "blend task-s | mesh task-s | merge s | CD-L1 m | NC | F@0.1 m | pieces |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        st = r["stages_s"]

        def f(v, fmt=".1f"):
            return "-" if v is None else format(v, fmt)

        # rows before 2026-11-22 10:40 thinned coarse levels at one global rate (recorded as such)
        # rows before 2026-11-22 12:30 drew fresh queries every iteration (no query pool)
        pool = r.get("query_pool", 0)
        out.append(f"| {r.get('date', '-')} | {r['scene']} | {r.get('coarse_thinning', 'per cell')} | "
                   f"{pool or 'fresh'} | "
                   f"{r.get('points') or '-'} | {r['workers']} | {r['tiles']}/{r['tiles_planned']} | "
                   f"{r['wall_s']:.1f} | {r['points_per_s']:.0f} | {f(r.get('peak_rss_mb'), '.0f')} | "
                   f"{f(st['partition'])} | {f(st['solve_task_s'])} | {f(st['blend_task_s'])} | "
                   f"{f(st['mesh_task_s'])} | {f(st['merge'])} | {f(r.get('chamfer_l1_m'), '.4f')} | "
                   f"{f(r.get('normal_consistency'), '.3f')} | {f(r.get('fscore_0.1m'), '.3f')} | "
                   f"{r.get('components', '-')} |")
    return "\n".join(out)


def render_tiles(rows: list[dict]) -> str:
    """Markdown table of the ``tiles`` suite's latest series, with the least-squares line wall = a + b * tiles."""
    import numpy as np

    runs = [r for r in rows if r.get("suite") == "tiles"]
    if not runs:
        return ""
    series: list[dict] = []
    for r in runs:  # the latest run of each copy count
        series = [q for q in series if q["copies"] != r["copies"]] + [r]
    series.sort(key=lambda r: r["tiles"])
    table = [{**r, "tiles_of": f"{r['tiles']}/{r['tiles_planned']}", "wall_per_tile": r["wall_s"] / r["tiles"],
              "solve_per_tile": r["stages_s"]["solve_task_s"] / r["tiles"]} for r in series]
    out = [markdown_table(table, [("date", "date", ""), ("copies", "copies", ""), ("points", "points", ""),
                                  ("workers", "workers", ""), ("tiles_of", "tiles", ""), ("wall_s", "wall s", ".1f"),
                                  ("wall_per_tile", "wall s per tile", ".1f"),
                                  ("solve_per_tile", "solve task-s per tile", ".1f"),
                                  ("peak_rss_mb", "peak RSS MB", ".0f")])]
    if len(series) >= 2:
        t = np.array([r["tiles"] for r in series], float)
        w = np.array([r["wall_s"] for r in series], float)
        b, a = np.polyfit(t, w, 1)
        fit = a + b * t
        r2 = 1.0 - float(np.sum((w - fit) ** 2)) / float(np.sum((w - w.mean()) ** 2))
        out += ["", f"Least squares: wall = {a:.1f} s + {b:.2f} s x tiles (R^2 = {r2:.4f}); largest deviation "
                    f"from the line {np.max(np.abs(w - fit) / w) * 100:.1f} %."]
    return "\n".join(out)


def render_wide(rows: list[dict]) -> str:
    """Markdown table of the ``wide`` suite: each method and variant with its time and memory against Poisson's in
    the same run (rows are grouped by the Poisson run they follow)."""
    runs = [r for r in rows if r.get("suite") == "wide"]
    if not runs:
        return ""
    table = []
    for r in runs:
        st = r.get("stages_s") or {}
        table.append({**r, "what": "Poisson" if r["method"] == "poisson" else f"GridPull {r['variant']}",
                      "tiles_of": "-" if r.get("tiles") is None else f"{r['tiles']}/{r['tiles_planned']}",
                      "solve_task_s": st.get("solve_task_s"), "setting": r["variant"] if r["method"] == "poisson"
                      else variant_settings(r["variant"])})
    return markdown_table(table, [("date", "date", ""), ("points", "points", ""), ("what", "method", ""),
                                  ("setting", "settings", ""), ("tiles_of", "tiles", ""), ("wall_s", "wall s", ".1f"),
                                  ("x_poisson_time", "x Poisson time (same run)", ".2f"),
                                  ("peak_rss_mb", "peak RSS MB", ".0f"),
                                  ("x_poisson_memory", "x Poisson memory", ".2f"),
                                  ("solve_task_s", "solve task-s", ".1f"), ("chamfer_l1_m", "CD-L1 m", ".4f"),
                                  ("normal_consistency", "NC", ".3f"), ("fscore_0.1m", "F@0.1 m", ".3f"),
                                  ("components", "pieces", ""), ("boundary_edges", "boundary edges", "")])


def render_holdout(rows: list[dict]) -> str:
    """Markdown table of the ``holdout`` suite (held-out points' distance to each mesh, same run as Poisson)."""
    runs = [r for r in rows if r.get("suite") == "holdout"]
    if not runs:
        return ""
    table = [{**r, "what": "Poisson" if r["method"] == "poisson" else f"GridPull {r['variant']}",
              "setting": r["variant"] if r["method"] == "poisson" else variant_settings(r["variant"])} for r in runs]
    return markdown_table(table, [("date", "date", ""), ("scene", "file", ""), ("cell", "cell", "g"),
                                  ("points", "points in", ""), ("held_out", "held out", ""), ("what", "method", ""),
                                  ("setting", "settings", ""), ("wall_s", "wall s", ".1f"),
                                  ("x_poisson_time", "x Poisson time", ".2f"),
                                  ("holdout_mean", "held-out mean dist", ".4f"),
                                  ("holdout_median", "median", ".4f"), ("holdout_p90", "90th pct", ".4f"),
                                  ("holdout_within_cell", "share within 1 cell", ".3f"),
                                  ("area_far_share", "area > 2 cells from points", ".3f"),
                                  ("boundary_edges", "boundary edges", ""), ("components", "pieces", "")])


def render_trade(rows: list[dict]) -> str:
    """Markdown table of the ``trade`` suite: each real scan's Poisson row, then GridPull's mesh cleaned after the
    fact (:func:`trade`), held-out distance beside boundary edges and pieces."""
    runs = [r for r in rows if r.get("suite") == "trade"]
    if not runs:
        return ""
    table = [{**r, "what": "Poisson (trimmed)" if r["method"] == "poisson" else f"GridPull, {r['variant']}"}
             for r in runs]
    return markdown_table(table, [
        ("date", "date", ""), ("scene", "file", ""), ("cell", "cell", "g"), ("what", "method", ""),
        ("holdout_mean", "held-out mean", ".4f"), ("holdout_median", "median", ".4f"),
        ("holdout_p90", "90th pct", ".4f"), ("boundary_edges", "boundary edges", ""),
        ("components", "pieces", ""), ("area_far_share", "area > 2 cells from points", ".3f")])


def render_footprint(rows: list[dict]) -> str:
    """Markdown tables of the ``footprint`` suite: the synthetic scenes (footprint recall, precision, observed
    region) and the real ones (held-out points), each method beside Poisson in the same run."""
    runs = [r for r in rows if r.get("suite") == "footprint"]
    if not runs:
        return ""
    table = [{**r, "what": ("Poisson (trimmed)" if r["method"] == "poisson" else f"GridPull {r['variant']}")
              + (", trajectory" if r.get("trajectory") and r["method"] != "poisson" else "")} for r in runs]
    synth = [r for r in table if "footprint_recall@1.5" in r]
    real = [r for r in table if "holdout_mean" in r]
    out = []
    if synth:
        out.append(markdown_table(synth, [
            ("date", "date", ""), ("scene", "scene", ""), ("points", "points", ""), ("what", "method", ""),
            ("wall_s", "wall s", ".1f"), ("footprint_recall@1.5", "footprint recall@0.1, R 1.5 m", ".3f"),
            ("footprint_recall@3", "R 3 m", ".3f"), ("footprint_seen@1.5", "seen by a sensor, R 1.5 m", ".3f"),
            ("footprint_seen_recall@1.5", "recall there", ".3f"), ("precision@0.1", "precision@0.1", ".3f"),
            ("boundary_edges", "boundary edges", ""), ("components", "pieces", ""),
            ("chamfer_l1_m", "observed CD-L1 m", ".4f"), ("normal_consistency", "NC", ".4f"),
            ("fscore_0.1m", "F@0.1", ".3f")]))
    if real:
        out.append(markdown_table(real, [
            ("date", "date", ""), ("scene", "file", ""), ("cell", "cell", "g"), ("points", "points in", ""),
            ("what", "method", ""), ("wall_s", "wall s", ".1f"), ("holdout_mean", "held-out mean", ".4f"),
            ("holdout_median", "median", ".4f"), ("holdout_within_cell", "within 1 cell", ".3f"),
            ("area_far_share", "area > 2 cells from points", ".3f"), ("boundary_edges", "boundary edges", ""),
            ("components", "pieces", "")]))
    return "\n\n".join(out)


def render_classes(rows: list[dict]) -> str:
    """Markdown table of the latest ``classes`` run: each class of the street's ground truth, GridPull beside
    Poisson."""
    runs = [r for r in rows if r.get("suite") == "classes"]
    if not runs:
        return ""
    # the latest run: its Poisson row and the GridPull rows after it
    poissons = [i for i, r in enumerate(runs) if r["method"] == "poisson"]
    runs = runs[poissons[-1]:] if poissons else runs
    table = []
    for name in runs[0]["classes"]:
        for r in runs:
            c = r["classes"][name]
            table.append({"date": r["date"], "class": name,
                          "what": "Poisson" if r["method"] == "poisson" else f"GridPull {r['variant']}",
                          **{k: c[k] for k in ("gt_samples", "completeness", "recall", "normal_consistency",
                                               "pred_share", "accuracy")}})
    return markdown_table(table, [("date", "date", ""), ("class", "class", ""), ("what", "method", ""),
                                  ("gt_samples", "observed truth samples", ""),
                                  ("completeness", "truth to mesh m", ".4f"), ("recall", "within 5 cm", ".3f"),
                                  ("normal_consistency", "NC", ".4f"), ("pred_share", "share of the mesh", ".3f"),
                                  ("accuracy", "mesh to truth m", ".4f")])


def render_thin(rows: list[dict]) -> str:
    """Markdown table of the latest ``thin`` series: each wall's two faces, truth to mesh."""
    runs = [r for r in rows if r.get("suite") == "thin"]
    if not runs:
        return ""
    # the latest series: from the last row of the first thickness on
    first = max(i for i, r in enumerate(runs) if r["thickness_m"] == runs[0]["thickness_m"]
                and r["placement"] == runs[0]["placement"])
    table = []
    for r in runs[first:]:
        f, b = r["classes"]["front"], r["classes"]["back"]
        table.append({"date": r["date"], "t": r["thickness_m"], "cells": r["thickness_m"] / r["cell"],
                      "placement": r["placement"], "front": f["completeness"], "front_recall": f["recall"],
                      "back": b["completeness"], "back_recall": b["recall"],
                      "both": "yes" if min(f["recall"], b["recall"]) >= 0.8 else "no", "wall_s": r["wall_s"]})
    return markdown_table(table, [("date", "date", ""), ("t", "wall m", "g"), ("cells", "cells", "g"),
                                  ("placement", "against the lattice", ""),
                                  ("front", "front face: truth to mesh m", ".4f"),
                                  ("front_recall", "within 2 cm", ".3f"),
                                  ("back", "back face: truth to mesh m", ".4f"), ("back_recall", "within 2 cm", ".3f"),
                                  ("both", "both faces (80 % within 2 cm)", ""), ("wall_s", "job s", ".1f")])


def plot_tile_costs(rows: list[dict], path: Path) -> Path | None:
    """Scatter of every tile's solve time against its points and its finest band (the latest ``wide`` run of
    each variant and cloud size); written to ``path`` (PNG). None when there is nothing to plot."""
    runs = {}
    for r in rows:
        if r.get("suite") == "wide" and r.get("tile_costs"):
            runs[(r["points"], r["variant"])] = r
    if not runs:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for (n, variant), r in sorted(runs.items()):
        tiles = [t for t in r["tile_costs"] if t.get("status") == "solved"]
        label = f"{variant}, {n / 1e6:.1f}M points"
        for ax, key in zip(axes, ("points", "band")):
            ax.scatter([t[key] for t in tiles], [t["time_s"] for t in tiles], s=10, label=label, alpha=0.7)
    for ax, name in zip(axes, ("points in the tile", "finest-band vertices")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(name)
        ax.set_ylabel("solve task seconds (1 thread)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("Per-tile solve cost, grid of streets (benchmarks/scenes.py wide)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


if __name__ == "__main__":
    main()
