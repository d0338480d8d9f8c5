"""The partition on the workers (issue 20) beside the one pass on the driver, for plain LAZ and for COPC.

For each cloud (the synthetic street at the sizes given, and ``--copies`` of the largest side by side as
several files) the street is written as LAZ and as COPC (copclib), and each method runs in a fresh process, so
its peak RSS is that method's driver:

* ``stream LAZ`` / ``stream COPC``: the driver reads every point (the COPC files as the LAZ files they are) and
  writes the spill files: the partition every input had before;
* ``segments LAZ``: the scan and the partition of the LAZ files as tasks of 4M-point segments on a
  LocalCluster of ``--workers`` workers, joined by the driver (the cluster's start, which a job pays anyway for
  its tiles, is timed apart);
* ``index COPC``: the plan from the headers, the candidate tiles from the octree's shallow levels, and every
  tile's points read from the files by a task on the LocalCluster (its start timed apart);
* ``dry stream`` (LAZ) / ``dry index`` (COPC): ``--dry-run``'s plan and estimate.

Each run records the SHA-256 of every tile's spill file; ``segments LAZ`` and ``index COPC`` say whether theirs
all equal the one pass's over the same files. Results append to ``benchmarks/results/partition.jsonl``;
``python -m benchmarks.report`` renders them into BENCHMARKS.md.

Usage::

    python -m benchmarks.partition --points 1000000 14000000 --copies 4 [--workers 2] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, append_jsonl, machine, markdown_table, run_isolated

RESULTS = REPO / "benchmarks" / "results" / "partition.jsonl"
METHODS = ("stream LAZ", "segments LAZ", "stream COPC", "index COPC", "dry stream", "dry index")
#: the one pass each parallel method is compared with (time, memory, spill files)
PEER = {"segments LAZ": "stream LAZ", "index COPC": "stream COPC", "dry index": "dry stream"}
TILING = {"voxel_size": 0.1}


def _run(args: dict) -> dict:
    """One method in this (fresh) process."""
    import hashlib

    import tiled_gridpull.prepare as prepare
    # VmHWM: ru_maxrss would carry over the parent's high-water mark across fork and exec
    from tiled_gridpull.memory import peak_rss_mb
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.jobdir import JobPaths
    from tiled_gridpull.tiling import TilingConfig

    tiling = TilingConfig(**TILING)
    method = args["method"]
    inputs = args["copc"] if ("COPC" in method or method == "dry index") else args["laz"]
    t0 = time.perf_counter()
    out = {"method": method}
    if method.startswith("dry"):
        import tiled_gridpull.indexed_inputs as indexed_inputs
        from tiled_gridpull.config import load_config_file, split_settings
        from tiled_gridpull.pipeline.dryrun import plan_job

        if method == "dry stream":  # the dry run imports the name at call time
            indexed_inputs.all_indexed = lambda _: False
        solver = SolverConfig(**split_settings(load_config_file(REPO / "configs" / "scene.yaml"))[0])
        info = plan_job(inputs, tiling, solver, args["work"], workers=args["workers"])
        out.update(tiles=info["tiles"]["with_points"], estimate_s=info["time"]["wall_seconds"])
    else:
        run_tasks = None
        if method.startswith("stream"):
            prepare.all_indexed = lambda _: False
        else:
            from tiled_gridpull.pipeline.job import DaskExecutor, JobOptions

            executor = DaskExecutor(JobOptions(workers=args["workers"], progress=False))
            # the cluster a job starts anyway (before this change, for its tiles): timed apart
            executor._connect(args["workers"], Path(args["work"]))
            out["cluster_start_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            run_tasks = lambda fn, a: executor.map(fn, a, Path(args["work"]))  # noqa: E731
        _, specs, scan = prepare.prepare_job(inputs, tiling, JobPaths(args["work"]), run_tasks=run_tasks)
        if run_tasks is not None:
            executor.close()
        h = hashlib.sha256()
        for s in sorted(specs, key=lambda s: s.index):
            h.update(f"{s.name}:{s.points_sha256};".encode())
        out.update(tiles=len(specs), tile_points=int(sum(s.n_points for s in specs)), spill_digest=h.hexdigest())
    out.update(wall_s=time.perf_counter() - t0, driver_peak_rss_mb=peak_rss_mb())
    return out


def _inputs(n_points: int, copies: int, work: Path) -> tuple[list[str], list[str], int]:
    """The street of ``n_points`` as LAZ and as COPC files, ``copies`` times side by side (60 m apart)."""
    import numpy as np

    from tiled_gridpull.io import read_points
    from tiled_gridpull.io.indexed_write import write_copc
    from tiled_gridpull.synthetic.lidar_files import write_las
    from tiled_gridpull.synthetic.street_sample import make_street_sample

    sample = make_street_sample(work / f"street_{n_points}", n_points=n_points,
                                origin=(500000.0, 4000000.0, 100.0))
    xyz = read_points(sample["points"], clean=False).xyz
    laz, copc = [], []
    for c in range(copies):
        shifted = xyz + np.array([0.0, 60.0 * c, 0.0])
        laz.append(str(write_las(work / f"street_{n_points}_{c}.laz", shifted)))
        copc.append(str(write_copc(work / f"street_{n_points}_{c}.copc.laz", shifted)))
    return laz, copc, len(xyz) * copies


def main(argv=None) -> None:
    if argv is None and len(sys.argv) > 1 and sys.argv[1].startswith("{"):
        print(json.dumps(_run(json.loads(sys.argv[1]))))
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, nargs="+", default=[1_000_000])
    ap.add_argument("--copies", type=int, default=1, help="also run the largest cloud as this many files")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    base = Path(tempfile.mkdtemp(prefix="bench_partition_"))
    cases = [(n, 1) for n in a.points] + ([(max(a.points), a.copies)] if a.copies > 1 else [])
    rows = []
    try:
        for n, copies in cases:
            laz, copc, total = _inputs(n, copies, base)
            for rep in range(a.repeat):
                for method in METHODS:
                    work = base / f"job_{n}_{copies}_{method.replace(' ', '_')}_{rep}"
                    r = run_isolated("benchmarks.partition", {"laz": laz, "copc": copc, "method": method,
                                                              "work": str(work), "workers": a.workers})
                    shutil.rmtree(work, ignore_errors=True)
                    r.update(date=time.strftime("%Y-%m-%d %H:%M"), points=total, files=copies,
                             workers=a.workers, repeat=rep, machine=machine())
                    append_jsonl(RESULTS, r)
                    rows.append(r)
                    print(json.dumps({k: r[k] for k in ("method", "points", "files", "wall_s",
                                                          "driver_peak_rss_mb")}), flush=True)
            shutil.rmtree(base / f"street_{n}", ignore_errors=True)
            for f in laz + copc:
                Path(f).unlink(missing_ok=True)
    finally:
        shutil.rmtree(base, ignore_errors=True)
    print(table(rows))


def summarize(rows: list[dict]) -> list[dict]:
    """Medians over repeats, per (points, files, method), with the ratios to the one pass over the same files
    (:data:`PEER`) and whether the tiles equal its tiles byte for byte (SHA-256 of every spill file)."""
    import statistics

    groups: dict = {}
    for r in rows:
        groups.setdefault((r["date"][:10], r["points"], r["files"], r["method"]), []).append(r)
    out = []
    for (date, n, files, method), rs in groups.items():
        peer = groups.get((date, n, files, PEER.get(method, method)))
        row = {"date": date, "points": n, "files": files, "method": method, "runs": len(rs),
               "tiles": rs[0]["tiles"], "wall_s": statistics.median(r["wall_s"] for r in rs),
               "rss": statistics.median(r["driver_peak_rss_mb"] for r in rs),
               "estimate_s": rs[0].get("estimate_s"),
               "start_s": statistics.median(r["cluster_start_s"] for r in rs) if "cluster_start_s" in rs[0] else None}
        if peer and method in PEER:
            row["x_peer_time"] = row["wall_s"] / statistics.median(r["wall_s"] for r in peer)
            row["x_peer_rss"] = row["rss"] / statistics.median(r["driver_peak_rss_mb"] for r in peer)
            if "spill_digest" in rs[0]:
                row["same_tiles"] = "yes" if {r["spill_digest"] for r in rs} == {r["spill_digest"] for r in peer} \
                    else "NO"
        out.append(row)
    return out


def table(rows: list[dict]) -> str:
    return markdown_table(summarize(rows), [
        ("date", "date", ""), ("points", "points", ""), ("files", "files", ""), ("method", "method", ""),
        ("runs", "runs", ""), ("tiles", "tiles", ""), ("wall_s", "driver wall s (median)", ".1f"),
        ("start_s", "cluster start s (apart)", ".1f"),
        ("x_peer_time", "x one pass time", ".2f"), ("rss", "driver peak RSS MB (median)", ".0f"),
        ("x_peer_rss", "x one pass RSS", ".2f"), ("same_tiles", "tiles byte-identical to the one pass", ""),
        ("estimate_s", "dry-run estimate s", ".0f")])


if __name__ == "__main__":
    main()
