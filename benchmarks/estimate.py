"""The dry run's time estimate against finished jobs: for each job, what ``--dry-run`` predicts for the same inputs
and settings, beside the wall time the job measured.

Usage: ``python -m benchmarks.estimate MESH.ply ...`` (each a tiled job's output; its sidecar gives the settings and
the measured time, its job directory's manifest the inputs). Appends to ``benchmarks/results/estimates.jsonl``;
``python benchmarks/report.py`` renders the table. Jobs should have run on a quiet machine with their default
local cluster (the estimate assumes it).
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, append_jsonl, markdown_table

RESULTS = REPO / "benchmarks" / "results" / "estimates.jsonl"


def estimate_row(mesh: Path) -> dict:
    from tiled_gridpull.config import SolverConfig, recorded_settings
    from tiled_gridpull.pipeline.dryrun import plan_job
    from tiled_gridpull.tiling import TilingConfig

    side = json.loads(mesh.with_suffix(".json").read_text())
    manifest = json.loads((mesh.with_suffix(".job") / "manifest.json").read_text())
    names = set(TilingConfig.__dataclass_fields__)
    tiling = TilingConfig(**{k: v for k, v in side["tiling"].items() if k in names})
    solver = SolverConfig(**recorded_settings(side["config"]))
    with tempfile.TemporaryDirectory() as work:
        info = plan_job(manifest["inputs"], tiling, solver, Path(work) / "plan.job",
                        workers=side.get("engine", {}).get("workers"))
    measured = float(side["timings_s"]["total"])
    est = float(info["time"]["wall_seconds"])
    return {"date": time.strftime("%Y-%m-%d %H:%M"), "job": mesh.stem,
            "inputs": ", ".join(Path(p).name for p in manifest["inputs"]), "points": int(info["points"]),
            "tiles": int(info["tiles"]["with_points"]), "cell": tiling.voxel_size, "estimate_s": est,
            "measured_s": measured, "ratio": est / measured, "job_date": side.get("date")}


def render(rows: list[dict]) -> str:
    """Markdown table of the estimate rows (latest row per job and date)."""
    if not rows:
        return ""
    return markdown_table(rows, [("date", "date", ""), ("job", "job", ""), ("inputs", "input", ""),
                                 ("points", "points", ""), ("tiles", "tiles", ""), ("cell", "cell", "g"),
                                 ("measured_s", "measured wall s", ".1f"), ("estimate_s", "dry-run estimate s", ".1f"),
                                 ("ratio", "estimate / measured", ".2f")])


def main(argv: list[str]) -> None:
    for arg in argv:
        row = estimate_row(Path(arg))
        append_jsonl(RESULTS, row)
        print(f"{row['job']}: measured {row['measured_s']:.1f} s, estimate {row['estimate_s']:.1f} s "
              f"({row['ratio']:.2f}x)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
