"""The solver on a CUDA card against the same machine's CPU threads, in one run (BENCHMARKS.md, "GPU").

Usage (on a machine with a CUDA card and numba-cuda; every stage appends JSON lines to ``--out``)::

    python -m benchmarks.gpu all --out gpu.jsonl [--budget 500] [--work /tmp/gpu]
    python -m benchmarks.gpu agree|step|batch|shape|wide|street --out gpu.jsonl

Stages:

* ``env``: the card, the versions, and the card's measured device-to-device copy bandwidth (the yardstick of the
  step kernel, which is bandwidth-bound);
* ``agree``: a small shape solved on both devices: field and mesh differences, and two CUDA runs compared byte for
  byte (determinism);
* ``step``: the kernels alone on a synthetic band of dense bricks (64 tiles' worth, ~200M slots, and one tile's
  3.2M): ms per iteration, ns per slot, bandwidth against the copy's; the query kernel on 16M queries;
* ``batch``: the grid of streets' densest ``--batch-tiles`` tiles solved one by one and then as one batch
  (:func:`tiled_gridpull.solver.solve_batch`), wall and kernel times each way, fields compared bit for bit;
* ``shape``: a 100k-point torus at R = 256, one-shape mode, both devices;
* ``wide``: the 1M-point grid of streets (configs/scene.yaml, 0.1 m), tiled on a local Dask cluster, both devices;
  on the card once with tiles batched (``--batch-tiles 16``) and once a task per tile (``--scene-batches``);
* ``street``: the 14M-point street, likewise.

Accuracy here is the sampled metric of :func:`tiled_gridpull.metrics.evaluate` (``exact=False``: pyvista is not on
such machines), on both devices' meshes alike; the exact figures of the CPU path are in BENCHMARKS.md.
Stages past ``--budget`` seconds are skipped (and say so).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-m", "tiled_gridpull"]
T0 = time.perf_counter()


def out_line(path: Path, row: dict) -> None:
    row = {"stage": row.pop("stage"), **row, "elapsed_s": round(time.perf_counter() - T0, 1)}
    with open(path, "a") as f:
        f.write(json.dumps(row, default=float) + "\n")
    print(json.dumps(row, default=float), flush=True)


def stage_env(out: Path) -> None:
    from tiled_gridpull.device import cuda_card, cuda_module, describe

    cuda_module()  # numba-cuda made importable first (tiled_gridpull.device)
    from numba import cuda

    n = 1 << (28 if os.environ.get("NUMBA_ENABLE_CUDASIM") != "1" else 10)  # 1 GiB of float32
    a = cuda.device_array(n, np.float32)
    b = cuda.device_array(n, np.float32)
    a.copy_to_device(b)
    cuda.synchronize()
    e0, e1 = cuda.event(), cuda.event()
    e0.record()
    for _ in range(10):
        b.copy_to_device(a)
    e1.record()
    e1.synchronize()
    ms = e0.elapsed_time(e1) / 10
    import numba

    out_line(out, {"stage": "env", "card": cuda_card(), **describe("cuda"), "numba": numba.__version__,
                   "numpy": np.__version__, "cpu_count": os.cpu_count(),
                   "copy_gbps": 2 * n * 4 / ms / 1e6, "copy_ms_1gib": ms})
    del a, b


def _sphere_cloud(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def stage_agree(out: Path, small: bool = False) -> None:
    from tiled_gridpull import reconstruct
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.lattice import Lattice
    from tiled_gridpull.metrics import evaluate
    from tiled_gridpull.solver import solve

    P = _sphere_cloud(2_000 if small else 20_000)
    cfg = SolverConfig(resolution=20, levels=1, iterations=4, queries=200) if small else SolverConfig(resolution=64)
    lat = Lattice.fit(P, cfg.resolution, cfg.margin)
    rows = {}
    for dev in ("cpu", "cuda", "cuda"):
        t = time.perf_counter()
        f = solve(P, lat, cfg, device=dev)
        rows.setdefault(dev, []).append((f, time.perf_counter() - t))
    a, b, c = rows["cpu"][0][0], rows["cuda"][0][0], rows["cuda"][1][0]
    one = _one_launch(P, lat, cfg, b)
    par = (a.band.flags.reshape(-1) & 1) != 0
    d = np.abs(a.values.reshape(-1) - b.values.reshape(-1))[par]
    # near the zero level (where the mesh is cut); farther out Adam's sign steps on rounding-noise gradients differ
    near = par & (np.abs(a.values.reshape(-1)) < 1.5)
    dn = np.abs(a.values.reshape(-1) - b.values.reshape(-1))[near]
    meshes = {dev: reconstruct(P, config=cfg.replace(device=dev)) for dev in ("cpu", "cuda")}
    m2 = reconstruct(P, config=cfg.replace(device="cuda"))
    ev = evaluate(meshes["cuda"], meshes["cpu"], exact=False)
    cell = lat.cell_size
    out_line(out, {"stage": "agree", "points": len(P), "resolution": cfg.resolution,
                   "field_max_abs_diff_cells": float(d.max()), "field_mean_abs_diff_cells": float(d.mean()),
                   "near_surface_max_abs_diff_cells": float(dn.max()),
                   "near_surface_mean_abs_diff_cells": float(dn.mean()),
                   "field_bitwise_repeat": bool(np.array_equal(b.values, c.values)),
                   "mesh_bitwise_repeat": bool(np.array_equal(meshes["cuda"].vertices, m2.vertices)
                                               and np.array_equal(meshes["cuda"].faces, m2.faces)),
                   "mesh_chamfer_cells": ev["chamfer_l1"] / cell,
                   "solve_s_cpu": rows["cpu"][0][1], "solve_s_cuda_first": rows["cuda"][0][1],
                   "solve_s_cuda_second": rows["cuda"][1][1],
                   "sha_cuda": hashlib.sha1(b.values.tobytes()).hexdigest()[:12], **one})


def _one_launch(P, lat, cfg, per_step) -> dict:
    """Time the opt-in one-launch-per-level kernel on the same solve, and check it repeats the per-step field."""
    import logging

    from tiled_gridpull.solver import solve
    from tiled_gridpull.solver_cuda import ONE_LAUNCH_ENV

    fell_back = []

    class Catch(logging.Handler):
        def emit(self, record):
            if "one launch per level" in record.getMessage():
                fell_back.append(record.getMessage()[:300])

    h = Catch()
    logging.getLogger("tiled_gridpull").addHandler(h)
    os.environ[ONE_LAUNCH_ENV] = "1"
    try:
        times = []
        for _ in range(2):  # the first includes compiling the kernel
            t = time.perf_counter()
            f = solve(P, lat, cfg, device="cuda")
            times.append(time.perf_counter() - t)
    finally:
        del os.environ[ONE_LAUNCH_ENV]
        logging.getLogger("tiled_gridpull").removeHandler(h)
    return {"solve_s_cuda_one_launch_first": times[0], "solve_s_cuda_one_launch": times[1],
            "one_launch_fell_back": fell_back[:1] or None,
            "one_launch_bitwise_equal": bool(np.array_equal(f.values, per_step.values))}


def dense_band(bricks_per_axis: tuple[int, int, int]):
    """A synthetic band of dense bricks (every slot a parameter) over a block of bricks: the step kernel's
    bandwidth test (a real band's bricks have the same layout, with some slots not parameters)."""
    from tiled_gridpull.band import Band, dense_brick_table
    from tiled_gridpull.lattice import Lattice

    bx, by, bz = bricks_per_axis
    coords = np.stack(np.meshgrid(np.arange(bx), np.arange(by), np.arange(bz), indexing="ij"), -1).reshape(-1, 3)
    table = dense_brick_table((bx, by, bz), coords)
    nb = len(coords)
    neighbors = np.full((nb, 6), -1, np.int32)
    for side, (ax, sgn) in enumerate([(0, -1), (0, 1), (1, -1), (1, 1), (2, -1), (2, 1)]):
        c = coords.copy()
        c[:, ax] += sgn
        ok = (c[:, ax] >= 0) & (c[:, ax] < (bx, by, bz)[ax])
        neighbors[ok, side] = table[c[ok, 0], c[ok, 1], c[ok, 2]]
    flags = np.full((nb, 512), 0xF, np.uint8)
    lat = Lattice((0.0, 0.0, 0.0), 1.0, (bx * 8, by * 8, bz * 8))
    return Band(lat, 3, 3, coords.astype(np.int32), table, neighbors, flags)


def stage_step(out: Path, copy_gbps: float | None, small: bool = False) -> None:
    from numba import cuda

    from tiled_gridpull.device import cuda_module
    from tiled_gridpull.kernels import CELL_PULL
    from tiled_gridpull.kernels import sampling as ksamp

    k = cuda_module()
    sizes = (("one tile (3.2M slots)", (25, 16, 16)), ("64-tile batch (206M slots)", (100, 64, 63)))
    for label, shape in (sizes if not small else (("smoke", (2, 2, 2)),)):
        band = dense_band(shape)
        n = band.n_slots
        to = cuda.to_device
        rng = np.random.default_rng(0)
        d_a = to(rng.normal(size=n).astype(np.float32))
        d_b = cuda.device_array(n, np.float32)
        m = to(np.zeros(n, np.float32))
        v = to(np.zeros(n, np.float32))
        acc = to(np.zeros(n, np.int64))
        inv = to(np.zeros(n, np.float32))
        flags = to(band.flags.reshape(-1))
        nbr = to(band.neighbors)
        counts = to(np.ones(64, np.int32))
        sums = to(np.zeros(64, np.float64))
        blocks = -(-n // 512) if not small else 1
        res = {}
        for form in (0, 1):
            def it(i):
                if form:
                    k.tv_norms[blocks, 512](d_a, flags, nbr, inv, sums, 0, False)
                k.tv_adam[blocks, 512](d_a, d_b, m, v, acc, counts, 0, flags, nbr, inv, form, np.float32(1e-6),
                                       np.float32(0.01), np.float32(0.9), np.float32(0.999), np.float32(1e-8),
                                       False, sums, False)
            it(0)
            cuda.synchronize()
            e0, e1 = cuda.event(), cuda.event()
            reps = 20
            e0.record()
            for i in range(reps):
                it(i)
            e1.record()
            e1.synchronize()
            ms = e0.elapsed_time(e1) / reps
            # bytes per slot of the fused step: d 4 + flags 1 + m, v 8 + acc 8 read; d_out 4 + m, v 8 + acc 8 written
            # (neighbours' reads hit the cache: a brick is one block); the sqrt form adds its norm pass
            bytes_per_slot = 41 + (4 + 1 + 4 + 4 if form else 0)
            gbps = bytes_per_slot * n / ms / 1e6
            res["squared" if form == 0 else "sqrt"] = {
                "ms_per_iteration": ms, "ns_per_slot": ms * 1e6 / n, "effective_gbps": gbps,
                "share_of_copy": gbps / copy_gbps if copy_gbps else None}
        # queries: 16 per point on a 1M-point-like load against this band
        nq = 16_000_000 if n > 50_000_000 else (1_000_000 if not small else 64)
        pts = (rng.random((max(nq // 16, 1000), 3)) * (np.array(band.lattice.shape) - 2)).astype(np.float32)
        pts_d = to(pts)
        near = to(rng.integers(0, len(pts), nq).astype(np.int32))
        tab = to(band.brick_table)
        nrm_t = to(ksamp.NORMALS)
        nx, ny, nz = band.lattice.shape
        key = ksamp.iteration_key(0, 0)
        qb = -(-nq // 512) if not small else 1
        no_normals = to(np.zeros((0, 3), np.float32))
        loss_sums = to(np.zeros((1, 4)))

        def q():
            k.query_scatter[qb, 512](d_a, flags, tab, nx, ny, nz, pts_d, no_normals, False, near, key,
                                     len(pts) / nq, np.float32(0.5), nrm_t, CELL_PULL, *np.float32([1.0, 0.005, 0.0]),
                                     acc, counts, 0, loss_sums, False)
        q()
        cuda.synchronize()
        e0, e1 = cuda.event(), cuda.event()
        e0.record()
        for _ in range(5):
            q()
        e1.record()
        e1.synchronize()
        out_line(out, {"stage": "step", "band": label, "slots": n, **res, "queries": nq,
                       "query_ms": e0.elapsed_time(e1) / 5})


def _sampled_scores(mesh_path: Path, gt_path: Path, points_path: Path | None) -> dict:
    from tiled_gridpull.io import read_mesh, read_points
    from tiled_gridpull.metrics import evaluate

    obs = read_points(str(points_path)).xyz if points_path else None
    # a million samples a side: the sampled Chamfer's floor (sample spacing) then sits below the surfaces' errors
    r = evaluate(read_mesh(str(mesh_path)), read_mesh(str(gt_path)), n_samples=1_000_000, exact=False, observed=obs,
                 observed_radius=0.2 if obs is not None else 0.0, thresholds=(0.05, 0.1, 0.2))
    return {"chamfer_l1_sampled": r["chamfer_l1"], "fscore_sampled@0.1": r.get("fscore@0.1"),
            "normal_consistency_sampled": r.get("normal_consistency")}


def _cli(args: list[str]) -> float:
    t = time.perf_counter()
    subprocess.run([*CLI, *args], check=True)
    return time.perf_counter() - t


def _sidecar(mesh: Path) -> dict:
    side = json.loads(mesh.with_suffix(".json").read_text())
    keep = {"timings_s": side.get("timings_s"), "devices": side.get("devices"), "device": side.get("device"),
            "tiles": (side.get("tiles") or {}).get("solved")}
    lv = [t.get("solve_levels") for t in side.get("tile_summaries", []) if t.get("solve_levels")]
    if lv:
        per = {}
        for levels in lv:
            for x in levels:
                acc = per.setdefault(x["level"], {})
                for key in ("time_band_s", "time_solve_s", "time_query_pool_s", "time_steps_s"):
                    acc[key] = acc.get(key, 0.0) + (x.get(key) or 0.0)
                acc["iterations"] = acc.get("iterations", 0) + (x.get("iterations") or 0)
        keep["task_s_per_level"] = per
        keep["solve_task_s"] = sum(t.get("time_s", 0.0) for t in side.get("tile_summaries", []))
        # the card's busy time: each batch's solve once (its tiles each carry it), each lone tile's own
        solves = {t.get("batch_of") or t.get("tile"): (t.get("phases_s") or {}).get("solve", 0.0)
                  for t in side.get("tile_summaries", [])}
        keep["solve_s_batches_once"] = sum(solves.values())
        keep["batches"] = sum(1 for t in side.get("tile_summaries", []) if t.get("batch_of") in (None, t.get("tile")))
        phases: dict = {}
        for t in side.get("tile_summaries", []):
            for k, v in (t.get("phases_s") or {}).items():
                phases[k] = phases.get(k, 0.0) + v
        keep["task_s_phases"] = phases
        keep["mesh_task_s"] = sum(t.get("time_s", 0.0) for t in side.get("mesh_summaries", []))
    if "solve" in side:
        keep["solve_levels"] = [{k: v for k, v in x.items() if k.startswith("time") or k == "iterations"}
                                for x in side["solve"].get("levels", [])]
    return keep


def stage_shape(out: Path, work: Path, devices=("cuda", "cpu")) -> None:
    d = work / "torus"
    src, gt = d / "torus.xyz", d / "torus_gt.ply"
    if not src.exists():
        subprocess.run([*CLI, "sample", "torus", str(d), "--points", "100000", "-q"], check=True)
    for dev in devices:
        mesh = d / f"mesh_{dev}.ply"
        wall = _cli(["reconstruct", str(src), "-o", str(mesh), "--resolution", "256", "--device", dev, "-q",
                     "--overwrite"])
        row = {"stage": "shape", "device": dev, "points": 100_000, "resolution": 256, "wall_s": wall,
               **_sidecar(mesh)}
        row.update(_sampled_scores(mesh, gt, None))
        out_line(out, row)


def stage_scene(out: Path, work: Path, name: str, n_points: int, layout: str, devices, workers: int,
                repeat: int = 1, one_launch: bool = False, batches=(16,)) -> None:
    """The scene tiled on a local Dask cluster on each device; CUDA ``repeat`` times for each ``--batch-tiles`` of
    ``batches`` (scored once: a card repeats its mesh bit for bit, batched or not, which the repeats check), and
    with ``one_launch`` once more with one launch per level (its mesh compared byte for byte with the per-step
    launches')."""
    d = work / name
    if not (d / "street.laz").exists():
        t = time.perf_counter()
        subprocess.run([*CLI, "sample", "street", str(d), "--points", str(n_points), "--layout", layout,
                        "--origin", "500000", "4000000", "100", "-q"], check=True)
        out_line(out, {"stage": name, "sample_s": time.perf_counter() - t})
    runs = []
    for dev in devices:
        for batch in batches if dev == "cuda" else batches[:1]:
            runs += [(dev, False, i, batch) for i in range(repeat if dev == "cuda" else 1)]
        if dev == "cuda" and one_launch:
            runs.append((dev, True, 0, 1))  # each worker its own launches: the cooperative kernel is per tile
    first_sha: dict = {}
    for dev, one, i, batch in runs:
        mesh = d / f"mesh_{dev}{'_one' if one else ''}_b{batch}.ply"
        shutil.rmtree(mesh.with_suffix(".job"), ignore_errors=True)
        env = dict(os.environ)
        if one:
            from tiled_gridpull.solver_cuda import ONE_LAUNCH_ENV

            env[ONE_LAUNCH_ENV] = "1"
        t = time.perf_counter()
        subprocess.run([*CLI, "reconstruct", str(d / "street.laz"), "-o", str(mesh), "--config",
                        str(REPO / "configs" / "scene.yaml"), "--device", dev, "--workers", str(workers), "-q",
                        "--overwrite", "--batch-tiles", str(batch)], check=True, env=env)
        wall = time.perf_counter() - t
        sha = hashlib.sha256(mesh.read_bytes()).hexdigest()
        row = {"stage": name, "device": dev, "points": n_points, "workers": workers, "wall_s": wall,
               "one_launch": one, "repeat": i, "batch_tiles": batch, "mesh_sha256": sha, **_sidecar(mesh)}
        if dev in first_sha:
            row["same_mesh_as_first"] = sha == first_sha[dev]
        else:
            first_sha[dev] = sha
            try:
                row.update(_sampled_scores(mesh, d / "street_gt.ply", d / "street.laz"))
            except Exception as exc:  # the timings are worth keeping without the scores
                row["score_error"] = f"{type(exc).__name__}: {exc}"[:500]
        out_line(out, row)
        shutil.copy(mesh.with_suffix(".json"),
                    out.parent / f"{name}_{dev}{'_one' if one else ''}_b{batch}_{i}_sidecar.json")


class _Stop(Exception):
    pass


def stage_batch(out: Path, work: Path, n_tiles: int, small: bool = False) -> None:
    """The grid of streets' ``n_tiles`` densest tiles solved on the card one by one and then as one batch
    (:func:`tiled_gridpull.solver.solve_batch`: their bands concatenated, one launch per step for all): the wall and
    the kernels' time each way, and whether every tile's field came out the same bit for bit. The tiles are read and
    set up (normals) once, outside the timings; ``small``: a tiny street in the simulator (a smoke test)."""
    from tiled_gridpull import tiled_job
    from tiled_gridpull.pipeline import cli
    from tiled_gridpull.solver import solve_batch
    from tiled_gridpull.tile_solve import prepare_tile

    name, n_points, layout = ("batch_small", 4000, "street") if small else ("wide", 1_000_000, "grid")
    d = work / name
    if not (d / "street.laz").exists():
        subprocess.run([*CLI, "sample", "street", str(d), "--points", str(n_points), "--layout", layout,
                        "--origin", "500000", "4000000", "100", "-q"], check=True)
    tiny = ["bridge=0", "levels=1", "iterations=2", "queries=60", "m1=2", "m2=2"]
    extra = (["--voxel-size", "0.5", "--tile-size", "12", "--overlap", "2"] + [x for t in tiny for x in ("--set", t)]
             if small else [])
    args = cli.build_parser().parse_args(["reconstruct", str(d / "street.laz"), "-o", str(d / "probe.ply"),
                                          "--config", str(REPO / "configs" / "scene.yaml"), *extra])
    solver, tiling = cli.resolve_settings(args)[:2]

    class Probe(tiled_job.SerialExecutor):
        def run(self, specs, tiling, solver, paths, centre, key_ref):
            densest = sorted(specs, key=lambda s: -s.block_points)[:n_tiles]
            ready = [p for p in (prepare_tile(s, tiling, solver, centre) for s in densest) if p.status is None]
            problems = [p.problem() for p in ready]
            # both paths' kernels compiled (a batch of one launches the single-tile kernels) and the card warm
            solve_batch(problems[:1], solver, device="cuda", history_every=0)
            solve_batch(problems[:2], solver, device="cuda", history_every=0)
            t = time.perf_counter()
            alone = [solve_batch([pr], solver, device="cuda", history_every=0)[0] for pr in problems]
            t_alone = time.perf_counter() - t
            t = time.perf_counter()
            together = solve_batch(problems, solver, device="cuda", history_every=0)
            t_batch = time.perf_counter() - t
            steps = [sum(lv["time_steps_s"] for lv in f.info["levels"]) for f in alone]
            out_line(out, {"stage": "batch", "scene": name, "tiles": len(ready),
                           "slots": int(sum(f.band.n_slots for f in alone)),
                           "alone_wall_s": t_alone, "alone_steps_s": sum(steps),
                           "batch_wall_s": t_batch,
                           "batch_steps_s": sum(lv["time_steps_s"] for lv in together[0].info["levels"]),
                           "speedup_wall": t_alone / t_batch,
                           "same_fields": all(np.array_equal(a.values, b.values) for a, b in zip(alone, together))})
            raise _Stop

    shutil.rmtree(d / "probe.job", ignore_errors=True)
    try:
        tiled_job.run_tiled_job([str(d / "street.laz")], None, tiling, solver, d / "probe.job", Probe(),
                                progress=False)
    except _Stop:
        pass


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("stages", nargs="+", choices=("env", "agree", "step", "batch", "shape", "wide", "street", "warm",
                                                  "all"))
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "gpu.jsonl")
    ap.add_argument("--work", type=Path, default=Path("/tmp/tiled_gridpull_gpu"))
    ap.add_argument("--budget", type=float, default=1e9, help="skip stages that start after this many seconds")
    ap.add_argument("--workers", type=int, default=os.cpu_count())
    ap.add_argument("--scene-devices", default="cuda", help="devices of the scene stages, comma-separated")
    ap.add_argument("--repeat", type=int, default=1, help="CUDA runs of each scene (timing medians)")
    ap.add_argument("--one-launch", action="store_true", help="each scene once more with one launch per level")
    ap.add_argument("--small", action="store_true", help="tiny sizes: a smoke test of the script (the simulator)")
    ap.add_argument("--batch-tiles", type=int, default=16, help="tiles of the batch stage (the densest)")
    ap.add_argument("--scene-batches", default="16,1",
                    help="--batch-tiles of the scene stages' CUDA runs, comma-separated (1: a task per tile)")
    a = ap.parse_args(argv)
    stages = ["env", "agree", "step", "batch", "shape", "wide", "street"] if "all" in a.stages else a.stages
    a.work.mkdir(parents=True, exist_ok=True)
    copy = None
    devices = tuple(a.scene_devices.split(","))
    batches = tuple(int(b) for b in a.scene_batches.split(","))
    for st in stages:
        if time.perf_counter() - T0 > a.budget:
            out_line(a.out, {"stage": st, "skipped": f"past the budget of {a.budget:.0f} s"})
            continue
        try:
            if st == "env":
                stage_env(a.out)
                copy = json.loads(a.out.read_text().strip().splitlines()[-1]).get("copy_gbps")
            elif st == "agree":
                stage_agree(a.out, a.small)
            elif st == "step":
                stage_step(a.out, copy, a.small)
            elif st == "batch":
                stage_batch(a.out, a.work, a.batch_tiles, a.small)
            elif st == "shape":
                stage_shape(a.out, a.work, devices)
            elif st == "warm":
                stage_scene(a.out, a.work, "warm", 20_000, "street", devices[:1], a.workers)
            elif st == "wide":
                stage_scene(a.out, a.work, "wide", 1_000_000, "grid", devices, a.workers, a.repeat, a.one_launch,
                            batches)
            elif st == "street":
                stage_scene(a.out, a.work, "street", 14_000_000, "street", devices, a.workers, a.repeat,
                            a.one_launch, batches)
        except Exception as exc:  # one stage's failure must not lose the others' figures
            out_line(a.out, {"stage": st, "error": f"{type(exc).__name__}: {exc}"[:2000]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


def table(rows: list[dict]) -> str:
    """Markdown tables of ``results/gpu.jsonl`` (BENCHMARKS.md, "GPU"): every run's rows, the card of the latest."""
    runs = sorted({r.get("run", 0) for r in rows})
    env = next((r for r in reversed(rows) if r["stage"] == "env" and "card" in r), {})
    lines = [f"Card: {env.get('card')}, copy bandwidth {env.get('copy_gbps', 0):,.0f} GB/s (device to device, read + "
             f"write); {env.get('cpu_count')} CPU cores; numba {env.get('numba')}, numba-cuda {env.get('numba_cuda')}, "
             f"numpy {env.get('numpy')}.", ""]
    lines += ["| band | form | ms / iteration | ns / slot | GB/s (41 B/slot fused step, 54 sqrt) | share of copy | "
              "queries | query ms |", "|---|---|---|---|---|---|---|---|"]
    for run in runs:
        for r in (x for x in rows if x.get("run", 0) == run and x["stage"] == "step" and "error" not in x):
            for form in ("squared", "sqrt"):
                f = r[form]
                lines.append(f"| {r['band']} (run {run}) | {form} | {f['ms_per_iteration']:.3f} | "
                             f"{f['ns_per_slot']:.4f} | {f['effective_gbps']:,.0f} | {f['share_of_copy']:.0%} | "
                             f"{r['queries']:,} | {r['query_ms']:.2f} |")
    lines += ["", "| job | device | run | wall s | solve task-s | solve s per level (summed over tiles) | "
              "sampled CD-L1 | sampled F@0.1 | sampled NC |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["stage"] not in ("shape", "wide", "street") or "wall_s" not in r:
            continue
        dev = r["device"] if isinstance(r["device"], str) else (r["device"] or {}).get("device")
        if dev is None and r.get("devices"):
            dev = ", ".join(r["devices"])
        if r.get("one_launch"):
            dev += ", one launch per level"
        if r.get("batch_tiles", 1) > 1 and "cuda" in dev:  # rows before batched jobs: a task per tile
            dev += f", batches of up to {r['batch_tiles']} tiles"
        if "task_s_per_level" in r:
            per = " / ".join(f"{v['time_solve_s']:.0f}" for _, v in sorted(r["task_s_per_level"].items()))
            task = f"{r['solve_task_s']:.0f}"
            if r.get("batch_tiles", 1) > 1 and "solve_s_batches_once" in r:  # a batch's solve is each of its tiles'
                task += f" (the card solved for {r['solve_s_batches_once']:.0f} s, {r['batches']} batches)"
        else:
            per = " / ".join(f"{v['time_solve_s']:.2f}" for v in r.get("solve_levels", []))
            task = f"{(r.get('timings_s') or {}).get('solve', 0):.1f}"
        name = {"shape": "torus 100k, R = 256", "wide": "grid of streets 1M, 0.1 m", "street": "street 14M"}[r["stage"]]
        f = r.get("fscore_sampled@0.1")
        if "chamfer_l1_sampled" not in r and r.get("same_mesh_as_first") is not None:
            same = "same mesh bytes as the run's first" if r["same_mesh_as_first"] else "mesh differs from the first"
            scores = f"{same} | | "
        else:
            scores = (f"{r.get('chamfer_l1_sampled', float('nan')):.4g} | {'' if f is None else f'{f:.3f}'} | "
                      f"{r.get('normal_consistency_sampled', float('nan')):.4f}")
        lines.append(f"| {name} | {dev} | {r.get('run', 0)} | {r['wall_s']:.1f} | {task} | {per} | {scores} |")
    phased = [r for r in rows if r.get("task_s_phases")]
    if phased:
        names = ("read", "normals", "solve", "orient_and_bridge", "save")
        lines += ["", "| where the tile tasks' time goes (task-s, summed over tiles) | device | run | "
                  + " | ".join(names) + " | solve: nearest-point pool | mesh tasks |",
                  "|---|---|---|" + "---|" * (len(names) + 2)]
        for r in phased:
            dev = r["device"] if isinstance(r["device"], str) else ", ".join(r.get("devices") or {})
            pool = sum(v.get("time_query_pool_s", 0.0) for v in r["task_s_per_level"].values())
            lines.append(f"| {r['stage']} | {dev}{', one launch' if r.get('one_launch') else ''} | {r.get('run', 0)} | "
                         + " | ".join(f"{r['task_s_phases'].get(n, 0.0):.0f}" for n in names)
                         + f" | {pool:.0f} | {r.get('mesh_task_s', 0.0):.0f} |")
    batches = [r for r in rows if r["stage"] == "batch" and "error" not in r and "skipped" not in r]
    if batches:
        lines += ["", "| tiles solved one by one and as one batch | run | tiles | slots (finest) | alone: wall s / "
                  "steps s | batch: wall s / steps s | wall speed-up | fields the same bit for bit |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in batches:
            lines.append(f"| {r['scene']} | {r.get('run', 0)} | {r['tiles']} | {r['slots']:,} | "
                         f"{r['alone_wall_s']:.2f} / {r['alone_steps_s']:.2f} | {r['batch_wall_s']:.2f} / "
                         f"{r['batch_steps_s']:.2f} | {r['speedup_wall']:.2f}x | {r['same_fields']} |")
    agree = [r for r in rows if r["stage"] == "agree" and "error" not in r]
    if agree:
        lines += ["", "| agreement (20k-point sphere) | run | near-surface field mean / max diff (cells) | "
                  "mesh CD (cells, sampled) | card repeats field / mesh bit for bit | solve s CPU / card | "
                  "card, one launch per level: solve s / same field |",
                  "|---|---|---|---|---|---|---|"]
        for r in agree:
            mean = r.get("near_surface_mean_abs_diff_cells", r["field_mean_abs_diff_cells"])
            top = r.get("near_surface_max_abs_diff_cells", r["field_max_abs_diff_cells"])
            where = "" if "near_surface_mean_abs_diff_cells" in r else " (every parameter)"
            lines.append(f"| R = {r['resolution']} | {r['run']} | {mean:.3f} / {top:.3f}{where} | "
                         f"{r['mesh_chamfer_cells']:.3f} | {r['field_bitwise_repeat']} / {r['mesh_bitwise_repeat']} | "
                         f"{r['solve_s_cpu']:.1f} / {r['solve_s_cuda_second']:.2f} | {_one_launch_cell(r)} |")
    return "\n".join(lines)


def _one_launch_cell(r: dict) -> str:
    if "solve_s_cuda_one_launch" not in r:
        return "not timed"
    if r.get("one_launch_fell_back"):
        return "fell back to per-step launches"
    return f"{r['solve_s_cuda_one_launch']:.2f} / {'bit for bit' if r['one_launch_bitwise_equal'] else 'differs'}"
