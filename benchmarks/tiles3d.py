"""3D Tiles output of a finished tiled job (``--3d-tiles``): time to write the tileset from the job's mesh pieces,
its size, and what a viewer loads first (the root's content) against every finest tile.

Usage::

    python -m benchmarks.tiles3d JOB_DIR CRS LABEL     # appends one row to benchmarks/results/tiles3d.jsonl

``JOB_DIR`` is a finished job's directory (its ``pieces/``), ``CRS`` the input's (``EPSG:32632``, or the input file
whose CRS to read).
"""

from __future__ import annotations

import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import REPO, markdown_table  # noqa: E402

RESULTS = REPO / "benchmarks" / "results" / "tiles3d.jsonl"


def measure(job_dir: Path, crs: str, label: str) -> dict:
    """Write the tileset of ``job_dir``'s pieces into a temporary directory and measure it."""
    from tiled_gridpull.tiles3d import job_tiles, write_tileset

    pieces = [(p.stem, tuple(int(v) for v in p.stem.split("_")[1:]), p)
              for p in sorted((job_dir / "pieces").glob("tile_*.npz"))]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        tiles = job_tiles(pieces)
        t1 = time.perf_counter()
        summary = write_tileset(tiles, Path(tmp) / "ts", crs)
        t2 = time.perf_counter()
        out = Path(tmp) / "ts"
        doc = json.loads((out / "tileset.json").read_text())
        finest = sum(f.stat().st_size for f in (out / "tiles").glob("*.glb"))
        coarse = sum(f.stat().st_size for f in (out / "lod").glob("*.glb"))
        root = (out / doc["root"]["content"]["uri"]).stat().st_size
    return {"label": label, "job": str(job_dir), "crs": summary["crs"], "tiles": summary["tiles"],
            "faces": summary["per_level"][0]["faces"], "levels": summary["levels"],
            "per_level": summary["per_level"], "load_s": t1 - t0, "write_s": t2 - t1,
            "finest_mb": finest / 1e6, "coarse_mb": coarse / 1e6, "root_mb": root / 1e6,
            "tileset_json_kb": (len(json.dumps(doc)) / 1e3), "date": time.strftime("%Y-%m-%d"),
            "machine": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "load_avg": os.getloadavg()[0]}


def table(rows: list[dict]) -> str:
    """BENCHMARKS.md table: one row per measured job."""
    shown = [{**r, "faces_per_level": " / ".join(f"{lv['faces']:,}" for lv in r["per_level"]),
              "errors": " / ".join(f"{lv['geometric_error']:.3f}" for lv in r["per_level"]),
              "p99": " / ".join(f"{lv['deviation_p99']:.3f}" if "deviation_p99" in lv else "-"
                                for lv in r["per_level"])} for r in rows]
    return markdown_table(shown, [
        ("label", "job", ""), ("date", "date", ""), ("tiles", "tiles", ""), ("faces", "faces", ",d"),
        ("faces_per_level", "faces per level, finest first", ""),
        ("errors", "geometric error per level (m)", ""), ("p99", "99th percentile deviation (m)", ""),
        ("write_s", "write s", ".1f"),
        ("finest_mb", "finest tiles MB", ".1f"), ("coarse_mb", "coarser levels MB", ".1f"),
        ("root_mb", "root content MB", ".2f"), ("load_avg", "load avg", ".1f")])


def main() -> None:
    job_dir, crs, label = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
    if Path(crs).is_file():  # an input file: the CRS it declares
        from tiled_gridpull.io import read_crs

        crs = read_crs(crs)
    row = measure(job_dir, crs, label)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    with open(RESULTS, "a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row, indent=1))


if __name__ == "__main__":
    main()
