"""Shared fixtures: paths to ../shared/data, small synthetic clouds."""

from __future__ import annotations

import os
from pathlib import Path

# The CUDA kernels run in numba's simulator: CI has no card (numba reads this when it is first imported, so it is
# set before anything imports numba). On a machine with one, NUMBA_ENABLE_CUDASIM=0 runs the CUDA tests on it.
os.environ.setdefault("NUMBA_ENABLE_CUDASIM", "1")
if os.environ["NUMBA_ENABLE_CUDASIM"] == "1":
    import sys

    from tiled_gridpull.device import SIMULATOR_SWITCH_INTERVAL

    # the simulator's launching thread busy-polls its threads holding the GIL a whole switch interval (5 ms by
    # default): tiled_gridpull.device.cuda_module shortens it where the package launches (a CLI in a subprocess
    # too), this for the tests that reach the simulator another way first
    sys.setswitchinterval(SIMULATOR_SWITCH_INTERVAL)

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
# ../shared/data beside the checkout; a worktree elsewhere points at it with TILED_GRIDPULL_SHARED_DATA
SHARED = Path(os.environ.get("TILED_GRIDPULL_SHARED_DATA") or REPO.parent / "shared" / "data")


def shared_file(*parts: str) -> Path:
    """Path of a file in ../shared/data, skipping the test with a clear reason when it is absent."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not available: {p} (tests that read real files need ../shared beside the repo)")
    return p


@pytest.fixture(scope="session")
def rng():
    return np.random.default_rng(12345)


def unit_sphere_points(n: int, seed: int = 0, radius: float = 0.5) -> np.ndarray:
    r = np.random.default_rng(seed)
    p = r.normal(size=(n, 3))
    return radius * p / np.linalg.norm(p, axis=1, keepdims=True)


@pytest.fixture
def ground(tmp_path):
    """A wavy 12 m ground patch of 4,000 points at UTM-like coordinates, saved as ``g.npy``: a few 0.2 m tiles."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 12.0, size=(4000, 2))
    pts = np.column_stack([xy, 0.3 * np.sin(xy[:, 0])]) + [500000.0, 4000000.0, 20.0]
    np.save(tmp_path / "g.npy", pts)
    return tmp_path / "g.npy"


def terrain(extent: float, density: float, seed: int = 0) -> np.ndarray:
    """A wavy ground patch ``extent`` metres square, ``density`` points per square metre (UTM-like offset)."""
    rng = np.random.default_rng(seed)
    n = int(extent * extent * density)
    xy = rng.uniform(0, extent, size=(n, 2))
    z = 0.4 * np.sin(xy[:, 0] / 2.0) * np.cos(xy[:, 1] / 3.0)
    return np.column_stack([xy, z]) + np.array([500000.0, 4000000.0, 50.0])


os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


# The files whose tests take longest, longest first (task-s of each file in a `make test` run, 2026-11-27:
# pytest --durations=0): `make test` hands whole files to its two processes in collection order (with xdist's
# --no-loadscope-reorder; by default xdist orders files by their number of tests, which put the 280-s street
# file last and left one process idle for minutes), so the long files go first and the short ones fill in.
_LONG_FILES = ("test_reconstruct.py", "test_tiled_job_scene.py", "test_device.py", "test_trajectory.py",
               "test_noise.py", "test_reliability.py", "test_pipeline_job.py", "test_reconstruct_udf.py",
               "test_pipeline_cli.py", "test_tiled_job.py", "test_pipeline_cli_fuzz.py", "test_kernels_losses.py",
               "test_attributes.py", "test_io_remote.py", "test_thin_walls.py", "test_indexed_inputs.py",
               "test_bridge.py", "test_quality.py", "test_stitch.py", "test_kernels_warmup.py", "test_tiles3d.py",
               "test_notebooks.py", "test_memory.py", "test_cuda_kernels.py", "test_kernels_mc.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(_LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
