"""The device setting: cpu | cuda | auto, its refusals, and the CUDA path end to end (in numba's simulator)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from tiled_gridpull import device
from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import ConfigError
from tiled_gridpull.lattice import Lattice
from tiled_gridpull.solver import solve

from conftest import unit_sphere_points

try:
    import numba.cuda  # noqa: F401

    HAVE_NUMBA_CUDA = True
except ImportError:  # pragma: no cover - the cuda extra is part of dev
    HAVE_NUMBA_CUDA = False
pytestmark = pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")  # the simulator's hashes
needs_cuda = pytest.mark.skipif(not HAVE_NUMBA_CUDA, reason="numba-cuda is not installed (the cuda extra)")

def near_surface_diff(a, b):
    """|a - b| (cells) at the parameters within 1.5 cells of a's zero level: the field the mesh is cut from.

    Farther out, where the queries do not reach and the field is nearly linear, the gradient is rounding noise, and
    Adam's first steps (each about lr along the gradient's sign) move such a vertex by up to a cell one way on one
    device and the other way on the other: both fine, and invisible to the mesh."""
    v = a.values.reshape(-1)
    near = ((a.band.flags.reshape(-1) & 1) != 0) & (np.abs(v) < 1.5)
    assert near.sum() > 50
    return np.abs(v - b.values.reshape(-1))[near]


TINY = dict(resolution=16, levels=1, iterations=6, queries=300, margin=3)


def test_config_takes_the_three_devices_and_refuses_others():
    assert SolverConfig().device == "auto"
    for d in ("cpu", "cuda", "auto"):
        assert SolverConfig(device=d).device == d
    with pytest.raises(ConfigError, match="device"):
        SolverConfig(device="gpu")
    # where a solve runs does not change what it computes: a resumed job keeps tiles solved elsewhere
    assert "device" not in SolverConfig(device="cuda").solve_settings(True)


def test_auto_never_picks_the_simulator_and_cpu_is_cpu(monkeypatch):
    assert device.resolve("cpu") == "cpu"
    monkeypatch.setattr(device, "cuda_card", lambda: device.SIMULATOR)
    monkeypatch.setattr(device, "driver_present", lambda: True)
    assert device.resolve("auto") == "cpu"
    assert device.resolve("cuda") == "cuda"
    monkeypatch.setattr(device, "cuda_card", lambda: "NVIDIA H200")
    monkeypatch.setenv("NUMBA_ENABLE_CUDASIM", "0")
    assert device.resolve("auto") == "cuda"
    monkeypatch.setattr(device, "driver_present", lambda: False)
    assert device.resolve("auto") == "cpu"  # no driver library: no card, whatever numba-cuda would say


def test_auto_without_a_driver_does_not_import_numba_cuda():
    """Importing numba-cuda costs every worker 35-40 MB: a machine without NVIDIA's driver never pays it."""
    code = ("import sys; from tiled_gridpull.device import driver_present, resolve; "
            "print(driver_present(), resolve('auto'), 'numba.cuda' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                       env={**os.environ, "NUMBA_ENABLE_CUDASIM": "0"})
    present, dev, imported = r.stdout.split()
    if present == "True":
        pytest.skip("this machine has NVIDIA's driver")
    assert (dev, imported) == ("cpu", "False")


def test_cuda_without_a_card_is_one_line(monkeypatch):
    monkeypatch.setattr(device, "cuda_card", lambda: None)
    assert device.resolve("auto") == "cpu"
    with pytest.raises(ConfigError) as e:
        device.resolve("cuda")
    msg = str(e.value)
    assert "\n" not in msg and "cuda" in msg and ("no CUDA GPU" in msg or "not installed" in msg)
    with pytest.raises(ConfigError):
        solve(unit_sphere_points(200), Lattice.fit(unit_sphere_points(200), 20, 3), SolverConfig(**TINY),
              device="cuda")


def test_cli_refuses_cuda_without_a_card_before_reading(tmp_path):
    """Exit 2 and one line, even for an input that does not exist: nothing was read."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "0"}
    probe = subprocess.run([sys.executable, "-c", "from tiled_gridpull.device import cuda_card; print(cuda_card())"],
                           capture_output=True, text=True, env=env)
    if probe.stdout.strip() not in ("None", ""):
        pytest.skip(f"this machine has a CUDA card ({probe.stdout.strip()})")
    r = subprocess.run([sys.executable, "-m", "tiled_gridpull", "reconstruct", str(tmp_path / "missing.ply"), "-o",
                        str(tmp_path / "m.ply"), "--device", "cuda"], capture_output=True, text=True, env=env)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "cuda" in lines[0] and "missing.ply" not in lines[0]
    assert not (tmp_path / "m.ply").exists() and not (tmp_path / "m.json").exists()


@needs_cuda
def test_cuda_solve_matches_the_cpu_and_repeats_bit_for_bit():
    P = unit_sphere_points(600)
    cfg = SolverConfig(**TINY)
    lat = Lattice.fit(P, cfg.resolution, cfg.margin)
    cpu = solve(P, lat, cfg, device="cpu")
    gpu = solve(P, lat, cfg, device="cuda")
    again = solve(P, lat, cfg, device="cuda")
    assert gpu.info["device"]["device"] == "cuda" and gpu.info["device"]["card"]
    assert cpu.info["device"]["device"] == "cpu"
    diff = near_surface_diff(cpu, gpu)
    assert diff.mean() < 1e-3 and diff.max() < 0.05  # cells, after 6 Adam steps of about lr = 1 cell
    assert np.array_equal(gpu.values, again.values)
    # the history is recorded on both
    assert len(gpu.info["history"]) == len(cpu.info["history"])
    assert gpu.info["history"][-1]["valid_queries"] == cpu.info["history"][-1]["valid_queries"]


@needs_cuda
def test_cuda_solve_two_levels_upsamples_on_the_card():
    """The finer level starts from the coarse field upsampled on the card (the hand-over between levels)."""
    P = unit_sphere_points(800, radius=0.25)
    cfg = SolverConfig(resolution=64, levels=2, coarse_iterations=3, iterations=3, queries=200, refine_m2=3)
    # a small sphere in a large lattice: a thin band, so the simulator's threads have little to do
    lat = Lattice((-2.0, -2.0, -2.0), 4.0 / 64, (65, 65, 65))
    assert cfg.levels_for(max(lat.n_cells)) == 2
    cpu = solve(P, lat, cfg, device="cpu")
    gpu = solve(P, lat, cfg, device="cuda")
    assert len(gpu.info["levels"]) == 2
    diff = near_surface_diff(cpu, gpu)
    assert diff.mean() < 1e-3 and diff.max() < 0.05


@needs_cuda
@pytest.mark.slow
def test_reconstruct_device_cuda_end_to_end_matches_the_cpu(tmp_path):
    """``reconstruct --device cuda`` (the simulator here) gives the CPU's mesh within a quarter cell."""
    from tiled_gridpull.io import read_mesh
    from tiled_gridpull.nearest import distances_to_cloud

    src = tmp_path / "sphere.npy"
    np.save(src, unit_sphere_points(1500))
    meshes = {}
    for dev in ("cpu", "cuda"):
        out = tmp_path / f"m_{dev}.ply"
        subprocess.run([sys.executable, "-m", "tiled_gridpull", "reconstruct", str(src), "-o", str(out),
                        "--device", dev, "--resolution", "20", "--set", "levels=1", "--set", "iterations=8",
                        "--set", "queries=300", "--set", "margin=3", "-q"], check=True)
        meshes[dev] = read_mesh(out)
        side = json.loads(out.with_suffix(".json").read_text())
        assert side["device"]["device"] == dev
        cell = side["lattice"]["cell_size"]
    a, b = meshes["cpu"], meshes["cuda"]
    assert a.n_faces > 100 and b.n_faces > 100
    mean = 0.5 * (distances_to_cloud(a.vertices, b.vertices).mean() + distances_to_cloud(b.vertices, a.vertices).mean())
    assert mean < 0.25 * cell


@needs_cuda
def test_one_launch_per_level_equals_one_launch_per_step(monkeypatch, caplog):
    """The cooperative whole-level kernel and the per-iteration launches run the same arithmetic: the same field,
    bit for bit (the fixed-point sums do not depend on the order), and the same history."""
    from tiled_gridpull.solver_cuda import ONE_LAUNCH_ENV, CudaBackend

    P = unit_sphere_points(600)
    cfg = SolverConfig(**{**TINY, "tv_form": "sqrt", "iterations": 5})
    lat = Lattice.fit(P, cfg.resolution, cfg.margin)
    assert not CudaBackend().cooperative  # opt-in
    per_step = solve(P, lat, cfg, device="cuda", history_every=2)
    monkeypatch.setenv(ONE_LAUNCH_ENV, "1")
    assert CudaBackend().cooperative
    with caplog.at_level("WARNING"):
        one = solve(P, lat, cfg, device="cuda", history_every=2)
    assert not [r for r in caplog.records if "one launch per level" in r.getMessage()]
    assert np.array_equal(one.values, per_step.values)
    h1, h2 = one.info["history"], per_step.info["history"]
    assert [h["iteration"] for h in h1] == [h["iteration"] for h in h2] == [0, 2, 4]
    assert h1 == h2  # the history too: its sums are fixed point


@needs_cuda
@pytest.mark.parametrize("message,kind", [("CUDA_ERROR_OUT_OF_MEMORY", "MemoryBudgetError"),
                                          ("CUDA_ERROR_LAUNCH_FAILED", "GridPullError")])
def test_a_card_failure_is_one_line(monkeypatch, message, kind):
    from numba.cuda.cudadrv.driver import CudaAPIError

    from tiled_gridpull import errors
    from tiled_gridpull.solver_cuda import CudaBackend

    def fail(self, run):
        raise CudaAPIError(2, f"Call to cuMemAlloc results in {message}\n(more)")

    monkeypatch.setattr(CudaBackend, "_iterate", fail)
    P = unit_sphere_points(300)
    with pytest.raises(errors.GridPullError) as e:
        solve(P, Lattice.fit(P, 20, 3), SolverConfig(**TINY), device="cuda")
    assert type(e.value).__name__ == kind
    assert "\n" not in str(e.value) and "CUDA" in str(e.value)


@needs_cuda
@pytest.mark.parametrize("error,kind", [("api_oom", "MemoryBudgetError"), ("fork", "GridPullError")])
def test_a_card_failure_between_levels_or_after_a_fork_is_one_line(monkeypatch, error, kind):
    """The upsampling between levels allocates the finer band on the card (its out of memory is the band's), and the
    driver raises CudaDriverError, not only CudaAPIError (a context made before a fork): each is one line."""
    from numba.cuda.cudadrv.driver import CudaAPIError

    from tiled_gridpull import errors
    from tiled_gridpull.band import build_band
    from tiled_gridpull.field import Field
    from tiled_gridpull.solver_cuda import CudaBackend

    class CudaDriverError(Exception):  # numba.cuda.cudadrv.error's, which the simulator does not define
        pass

    exc = (CudaAPIError(2, "Call to cuMemAlloc results in CUDA_ERROR_OUT_OF_MEMORY\n(more)") if error == "api_oom"
           else CudaDriverError("CUDA initialized before forking"))
    backend = CudaBackend()
    P = (unit_sphere_points(200) * 5 + 8).astype(np.float32)
    band = build_band(P, Lattice((0.0, 0.0, 0.0), 1.0, (17, 17, 17)), 2, 3)
    coarse = Field(band, np.zeros((band.n_bricks, 512), np.float32), signed=True)
    backend._last = {id(coarse): (coarse, backend.cuda.to_device(coarse.values.reshape(-1)))}

    def fail(*args, **kwargs):
        raise exc

    real_device_array = backend.cuda.device_array
    monkeypatch.setattr(backend.cuda, "device_array", fail)
    with pytest.raises(errors.GridPullError) as e:
        backend.upsample(coarse, band)
    assert type(e.value).__name__ == kind
    assert "\n" not in str(e.value) and "CUDA" in str(e.value)
    if error == "fork":  # and the same inside a level's iterations
        monkeypatch.setattr(CudaBackend, "_iterate", lambda self, run: fail())
        with pytest.raises(errors.GridPullError) as e:
            solve(unit_sphere_points(300), Lattice.fit(unit_sphere_points(300), 20, 3), SolverConfig(**TINY),
                  device="cuda")
        assert "\n" not in str(e.value) and "forking" in str(e.value)
        # and inside a batch of levels
        from tiled_gridpull.solver import solve_batch

        monkeypatch.setattr(backend.cuda, "device_array", real_device_array)  # the pools are found, the batch fails
        monkeypatch.setattr(CudaBackend, "_iterate_batch", lambda self, runs: fail())
        with pytest.raises(errors.GridPullError) as e:
            solve_batch(_batch_problems(), SolverConfig(**BATCH), device="cuda")
        assert "\n" not in str(e.value) and "forking" in str(e.value) and "batch of 2 bands" in str(e.value)


def test_a_numba_cuda_that_fails_to_import_is_no_card(monkeypatch):
    """``auto`` is the default: a numba-cuda that is installed but breaks on import (a numba or NumPy it does not fit
    raises AttributeError, RuntimeError, ...) must leave every solve on the CPU, and ``cuda`` refuse in one line."""
    def broken():
        raise AttributeError("module 'numpy' has no attribute 'row_stack'")

    monkeypatch.setattr(device, "_import_numba_cuda", broken)
    monkeypatch.setattr(device, "cuda_card", device.cuda_card.__wrapped__)  # uncached, this test's import
    assert device.cuda_card() is None
    assert device.resolve("auto") == "cpu"
    with pytest.raises(ConfigError) as e:
        device.resolve("cuda")
    assert "\n" not in str(e.value) and "numba-cuda" in str(e.value) and "row_stack" in str(e.value)


def _batch_problems():
    """Two small spheres on lattices of different placement and band size (tiles of one job share a block shape)."""
    from tiled_gridpull.solver import SolveProblem

    return [SolveProblem(unit_sphere_points(500, radius=0.15), Lattice((-2.0, -2.0, -2.0), 4.0 / 64, (65, 65, 65))),
            SolveProblem(unit_sphere_points(300, seed=1, radius=0.12) + 0.3,
                         Lattice((-1.7, -1.9, -2.1), 4.0 / 64, (65, 65, 65)))]


BATCH = dict(resolution=64, levels=2, coarse_iterations=2, iterations=2, queries=80, m1=2, m2=2, refine_m2=2)


@needs_cuda
def test_a_batch_on_the_card_gives_each_tile_its_own_solve_bit_for_bit():
    """Tiles solved together (bands concatenated, one launch per step for all) come out as each alone: the same
    draws, each tile's own valid count, TV weight and lattice clamp, and the upsampling between levels from each
    tile's part of the batch's field on the card. The coarse level runs the sqrt TV form, the finer the squared."""
    from tiled_gridpull.solver import solve_batch

    problems = _batch_problems()
    cfg = SolverConfig(**BATCH)
    assert cfg.level_settings(0, 2).tv_form != cfg.level_settings(1, 2).tv_form  # both forms run
    alone = [solve(p.points, p.lattice, cfg, device="cuda", history_every=1) for p in problems]
    together = solve_batch(problems, cfg, device="cuda", history_every=1)
    assert alone[0].band.n_slots != alone[1].band.n_slots  # bands of different sizes share the launches
    for a, b in zip(alone, together):
        assert np.array_equal(a.values, b.values)
        assert a.info["history"] == b.info["history"]  # each tile's own counts and sums
        assert b.info["batch"] == 2 and [lv["batch"] for lv in b.info["levels"]] == [2, 2]
        assert len(a.info["levels"]) == 2


def test_a_batch_on_the_cpu_is_each_solve_alone_and_levels_must_agree():
    from tiled_gridpull.solver import SolveProblem, solve_batch

    problems = _batch_problems()
    cfg = SolverConfig(**BATCH)
    together = solve_batch(problems, cfg, device="cpu")
    for p, b in zip(problems, together):
        a = solve(p.points, p.lattice, cfg, device="cpu")
        assert np.array_equal(a.values, b.values)
        # the CPU's TV sum is a threaded float reduction: its last bit may differ from run to run
        assert a.info["history"] == [pytest.approx(h, rel=1e-12) for h in b.info["history"]]
    assert solve_batch([], cfg, device="cpu") == []
    one_level = SolveProblem(problems[0].points, Lattice((-2.0, -2.0, -2.0), 4.0 / 32, (33, 33, 33)))
    with pytest.raises(ValueError, match="same number of levels"):
        solve_batch([problems[0], one_level], cfg, device="cpu")


@needs_cuda
def test_a_batch_that_cannot_share_launches_still_upsamples_each_tile_on_the_card(monkeypatch):
    """Without a query pool the tiles' levels run one after the other; each next level still starts from its own
    tile's field on the card (not the host's upsampling, which rounds differently), so each field is its own."""
    from tiled_gridpull import solver_cuda
    from tiled_gridpull.solver import solve_batch

    problems = _batch_problems()
    cfg = SolverConfig(**{**BATCH, "query_pool": 0, "coarse_iterations": 1, "iterations": 1})
    alone = [solve(p.points, p.lattice, cfg, device="cuda") for p in problems]
    host = []
    real = solver_cuda.upsample
    monkeypatch.setattr(solver_cuda, "upsample", lambda *a, **k: host.append(1) or real(*a, **k))
    together = solve_batch(problems, cfg, device="cuda")
    assert host == []
    for a, b in zip(alone, together):
        assert np.array_equal(a.values, b.values)
        assert [lv.get("batch") for lv in b.info["levels"]] == [None, None]  # not batched: one after the other


@needs_cuda
def test_runs_share_launches_only_with_one_schedule_a_pool_each_and_the_same_normal_loss():
    """Tiles' levels batch when they differ only in their queries per iteration (which follow their points)."""
    import dataclasses
    from types import SimpleNamespace

    from tiled_gridpull.solver_cuda import _batchable

    cfg = SolverConfig(**BATCH)
    st = cfg.level_settings(0, 2, 500)

    def run(**kw):
        base = dict(cfg=cfg, level=0, it0=0, st=st, uses_normals=False, pool_nn=np.zeros((1, 1), np.int32))
        return SimpleNamespace(**{**base, **kw})

    assert _batchable([run(), run(st=dataclasses.replace(st, queries=st.queries + 7))])
    assert not _batchable([run(), run(st=dataclasses.replace(st, lr=st.lr / 2))])
    assert not _batchable([run(), run(level=1)])
    assert not _batchable([run(), run(uses_normals=True)])
    assert not _batchable([run(), run(pool_nn=None)])
    assert not _batchable([run(), run(cfg=cfg.replace(alpha=cfg.losses.alpha * 2))])


@needs_cuda
@pytest.mark.slow
def test_a_tiled_job_on_the_card_solves_its_tiles_in_batches_and_meshes_as_the_cpu(tmp_path):
    """``reconstruct --voxel-size ... --device cuda`` on the local cluster: a worker holds the card and solves the
    tiles in batches (the others prepare and mesh them), and the mesh is the CPU's within a quarter cell."""
    from tiled_gridpull.io import read_mesh
    from tiled_gridpull.nearest import distances_to_cloud
    from tiled_gridpull.tiled_job import reconstruct_scene
    from tiled_gridpull.tiling import TilingConfig

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 1, size=(800, 2)) * [6.0, 1.0]  # a strip of ground three tiles long
    src = tmp_path / "strip.npy"
    np.save(src, np.column_stack([xy, 0.2 * np.sin(xy[:, 0])]) + [500000.0, 4000000.0, 50.0])
    schedule = dict(levels=1, iterations=4, queries=300, m1=2, m2=2)
    out = tmp_path / "card.ply"
    subprocess.run([sys.executable, "-m", "tiled_gridpull", "reconstruct", str(src), "-o", str(out), "--voxel-size",
                    "0.15", "--tile-size", "2.4", "--overlap", "1.2", "--device", "cuda", "--workers", "1", "-q",
                    *[a for k, v in schedule.items() for a in ("--set", f"{k}={v}")]], check=True)
    side = json.loads(out.with_suffix(".json").read_text())
    tiles = side["tile_summaries"]
    assert side["engine"]["batch_tiles"] == 16 and side["engine"]["cards"] == 1 and len(tiles) == 3
    # the card's memory as the job found it (the simulator's has no limit) and what each batch was sized by
    memory = side["engine"]["card_memory"]
    if device.cuda_card() == device.SIMULATOR:
        assert memory == {"free_bytes": None, "total_bytes": None, "batch_budget_bytes": None}
    else:
        assert 0 < memory["batch_budget_bytes"] < memory["free_bytes"] <= memory["total_bytes"]
    assert all(t["batch_card_bytes"] > 0 and t["batch_host_bytes"] > 0 for t in tiles)
    assert all(t["status"] == "solved" and t["device"]["device"] == "cuda" for t in tiles)
    if device.cuda_card() == device.SIMULATOR:
        # the card was idle when the first tile was ready: it went alone; the others share the next launches
        # (they are ready long before the simulated card is done; a real card may be done first)
        assert max(t.get("batch", 1) for t in tiles) == 2
    assert len({t["worker"] for t in tiles}) == 1  # the card's worker solved them; another oriented and wrote them
    assert all(t["finish_worker"] != t["worker"] for t in tiles)
    assert not list((tmp_path / "card.job" / "prepared").iterdir())  # each prepared tile removed once solved
    cpu = reconstruct_scene([str(src)], tmp_path / "cpu.ply", TilingConfig(voxel_size=0.15, tile_size=2.4, overlap=1.2),
                            SolverConfig(**schedule, device="cpu"), tmp_path / "cpu.job")
    card = read_mesh(out)
    assert card.n_faces > 100 and cpu.n_faces > 100
    mean = 0.5 * (distances_to_cloud(cpu.vertices, card.vertices).mean()
                  + distances_to_cloud(card.vertices, cpu.vertices).mean())
    assert mean < 0.25 * 0.15
