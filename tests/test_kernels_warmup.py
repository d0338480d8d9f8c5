"""The kernels compiled ahead of a job's tiles: the signatures a tile calls, numba's cache seen from outside, the
shares of the work."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from numba.core.registry import CPUDispatcher

from tiled_gridpull.kernels import warmup

REPO = Path(__file__).resolve().parents[1]


def _python(code: str, **env) -> str:
    """Run ``code`` in a fresh interpreter (numba reads its cache directory once) and return its stdout."""
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, cwd=REPO,
                         env={**os.environ, "PYTHONPATH": str(REPO), **env}, timeout=600)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_every_entry_is_a_cached_kernel():
    for name in warmup.KERNELS:
        disp = warmup.kernel(name)
        assert isinstance(disp, CPUDispatcher), name
        assert disp._cache.__class__.__name__ == "FunctionCache", f"{name}: not @njit(cache=True)"


def test_the_cache_check_sees_what_another_process_compiled(tmp_path):
    """On an empty cache every kernel is cold; one compiled in a process is cached for the next one (the
    workers load what another compiled)."""
    code = """
        import json
        from tiled_gridpull.kernels import warmup
        before = warmup.cold_kernels()
        warmup.compile_kernels(["losses.scatter_add"])
        print(json.dumps([before, warmup.cold_kernels()]))
    """
    env = {"NUMBA_CACHE_DIR": str(tmp_path)}
    before, after = json.loads(_python(code, **env))
    assert sorted(before) == sorted(warmup.KERNELS)
    assert sorted(after) == sorted(set(warmup.KERNELS) - {"losses.scatter_add"})
    again, _ = json.loads(_python(code, **env))
    assert "losses.scatter_add" not in again and len(again) == len(warmup.KERNELS) - 1


def test_split_balances_the_compile_time():
    names = list(warmup.KERNELS)
    shares = warmup.split(names, 4)
    assert sorted(n for s in shares for n in s) == sorted(names)
    loads = [sum(warmup.KERNELS[n][1] for n in s) for s in shares]
    total = sum(warmup.KERNELS[n][1] for n in names)
    # longest-processing-time first: within the costliest kernel of an even share
    assert max(loads) <= total / 4 + max(c for _, c in warmup.KERNELS.values())
    assert warmup.estimate_seconds(names, 4) == pytest.approx(max(loads))
    assert warmup.estimate_seconds(names, 1) == pytest.approx(total)
    assert warmup.split(["losses.scatter_add"], 8) == [["losses.scatter_add"]]
    assert warmup.split([], 3) == [] and warmup.estimate_seconds([], 3) == 0.0


@pytest.mark.slow
def test_a_street_job_calls_the_kernels_with_the_tables_signatures(tmp_path):
    """A tiled street job (bridging on, with sensor origins, so every step of a scene tile runs) calls no kernel
    with argument types the table lacks: such a kernel would be compiled again at its first call, after the
    warm-up."""
    code = f"""
        import importlib, json, pkgutil
        import numpy as np
        import tiled_gridpull.kernels as K
        from numba.core.registry import CPUDispatcher
        from tiled_gridpull.config import SolverConfig
        from tiled_gridpull.synthetic.lidar import scan_street
        from tiled_gridpull.synthetic.street import StreetScene, build_street
        from tiled_gridpull.tiled_job import reconstruct_scene
        from tiled_gridpull.tiling import TilingConfig

        scene = StreetScene(seed=1, length_m=30.0, width_m=30.0, origin=(500000.0, 4000000.0, 100.0))
        from tiled_gridpull.synthetic.lidar_files import write_las, write_trajectory
        scan = scan_street(scene, build_street(scene), 2, azimuth_steps=400, max_range=15.0)
        # LAS with GPS time and the scanner's trajectory: the sensor's kernels run too
        write_las({str(tmp_path / "pts.las")!r}, scan.xyz, gps_time=100.0 + scan.frame)
        write_trajectory({str(tmp_path / "traj.csv")!r}, 100.0 + np.arange(len(scan.poses)), scan.poses[:, :3, 3])
        tiling = TilingConfig(voxel_size=0.2, tile_size=12.8, overlap=3.2, trim_distance=3.0, bridge=12)
        solver = SolverConfig(m2=8, coarse_iterations=60, middle_iterations=30, iterations=30)
        reconstruct_scene([{str(tmp_path / "pts.las")!r}], None, tiling, solver, {str(tmp_path / "job")!r},
                          trajectory={str(tmp_path / "traj.csv")!r})
        called = {{}}
        for info in pkgutil.iter_modules(K.__path__):
            mod = importlib.import_module("tiled_gridpull.kernels." + info.name)
            for name, disp in vars(mod).items():
                if (isinstance(disp, CPUDispatcher) and disp.py_func.__module__ == mod.__name__
                        and disp.signatures and not name.startswith("_")
                        and disp.targetoptions.get("inline") != "always"):
                    called[info.name + "." + name] = sorted(str(tuple(s)) for s in disp.signatures)
        print(json.dumps(called))
    """
    called = json.loads(_python(code).splitlines()[-1])
    table = {name: str(tuple(sig)) for name, (sig, _) in warmup.KERNELS.items()}
    unknown = {n: s for n, s in called.items() if n not in table or s != [table[n]]}
    assert not unknown, f"kernels called with types the warm-up table lacks: {unknown}"
    assert len(called) >= len(table) - 1, sorted(set(table) - set(called))  # the job ran (nearly) all of them
