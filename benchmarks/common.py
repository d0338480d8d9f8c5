"""Shared helpers for the benchmark scripts: data paths, isolated runs, machine description, tables."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
MESHES = {
    "bunny": "stanford_bunny_bun_zipper.ply",
    "armadillo": "armadillo_libigl.obj",
    "fandisk": "fandisk.obj",
    "abc_00011084": "abc_00011084_fddd53ce45f640f3ab922328_trimesh_019.ply",
    "abc_00016513": "abc_00016513_3d6966cd42eb44ab8f4224f2_trimesh_053.ply",
    "abc_00994122": "abc_00994122_57d9d4755722f9d2d7436f0a_trimesh_000.ply",
}


def require_shared() -> Path:
    """The shared data folder, or exit with a clear reason."""
    if not SHARED.is_dir():
        sys.exit(f"benchmarks need the shared data at {SHARED} (../shared beside the repository)")
    return SHARED


def machine() -> dict:
    """What the numbers were measured on."""
    import numba

    info = {"python": platform.python_version(), "cpus": os.cpu_count(), "machine": platform.machine(),
            "numba": numba.__version__, "numpy": np.__version__}
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    info["cpu"] = line.split(":", 1)[1].strip()
                    break
        with open("/proc/meminfo") as fh:
            info["memory_gib"] = round(int(fh.readline().split()[1]) / 2**20, 1)
    except OSError:
        pass
    return info


def append_jsonl(path: Path, row: dict) -> None:
    """Append ``row`` as one JSON line to a results file (created with its folder if missing)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as fh:
        fh.write(json.dumps(row, default=float) + "\n")


def run_isolated(module: str, args: dict, timeout: float = 3600) -> dict:
    """Run ``python -m <module>`` with JSON args in a fresh process; returns its JSON result.

    A fresh process per run gives an honest peak RSS (``ru_maxrss`` of that process) and no cache sharing
    except numba's on-disk cache (warm by design: compile time is reported apart).
    """
    env = dict(os.environ)
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    proc = subprocess.run([sys.executable, "-m", module, json.dumps(args)], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"{module} failed: {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def markdown_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """``columns``: (key, header, format). Missing values print as a dash."""
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    sep = "|" + "|".join("---" for _ in columns) + "|"
    lines = [head, sep]
    for r in rows:
        cells = []
        for key, _, fmt in columns:
            v = r.get(key)
            cells.append("-" if v is None else (format(v, fmt) if fmt else str(v)))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
