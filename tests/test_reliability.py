"""Reliability of tiled jobs on a real LocalCluster (2 worker processes): resume after an interruption, a worker
killed mid-job, a tile that fails for a data reason, --fail-fast, and bitwise-identical reruns.

Every job here reconstructs the same small georeferenced terrain plus a tiny cluster of 6 points far from it:
with ``min_points=5`` that tile is solved and fails for a data reason (a solve needs 10 points), so every run
also checks that a failed tile is reported by name while the rest of the mesh is produced.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.config import SolverConfig
from tiled_gridpull.io import read_mesh
from tiled_gridpull.tiling import TilingConfig

REPO = Path(__file__).resolve().parents[1]
OFFSET = np.array([500000.0, 4000000.0, 50.0])
BAD_TILE = "tile_3_0_0"  # the 6 points at x = 23 m
OPTS = ["--voxel-size", "0.2", "--tile-size", "6.4", "--overlap", "1.6", "--set", "m2=6", "--set", "refine_m2=6",
        "--iterations", "80", "--set", "coarse_iterations=80", "--set", "queries=5000", "--set", "min_points=5",
        "--workers", "2"]
SOLVER = SolverConfig(m2=6, refine_m2=6, iterations=80, coarse_iterations=80, queries=5000)
TILING = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, min_points=5)


def scene_points() -> np.ndarray:
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 12.8, size=(6000, 2))
    z = 0.4 * np.sin(xy[:, 0] / 2.0) * np.cos(xy[:, 1] / 3.0)
    ground = np.column_stack([xy, z])
    stray = np.array([23.0, 2.0, 0.0]) + rng.normal(scale=0.05, size=(6, 3))
    return np.vstack([ground, stray]) + OFFSET


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("reliability")
    np.save(d / "pts.npy", scene_points())
    return d


def run_cli(args, capsys):
    code = main(args)
    err = capsys.readouterr().err
    return code, err


@pytest.fixture(scope="module")
def shared(data):
    """``OPTS`` plus ``--scheduler`` of one LocalCluster made by ``make_client`` (2 workers, as a job's own) that
    the undisturbed runs share: it saves starting a cluster per run. The fault and interruption tests start
    their own."""
    from tiled_gridpull.pipeline.job import JobOptions, make_client

    client, cluster = make_client(JobOptions(workers=2), 8)
    try:
        yield [*OPTS, "--scheduler", cluster.scheduler_address]
    finally:
        client.close()
        cluster.close()


@pytest.fixture(scope="module")
def reference(data, shared):
    """An undisturbed run: output PLY bytes and its sidecar."""
    out = data / "ref.ply"
    code = main(["reconstruct", str(data / "pts.npy"), "-o", str(out), "-q", *shared])
    assert code == 6  # BAD_TILE failed; everything else was meshed
    return out.read_bytes(), json.loads(out.with_suffix(".json").read_text())


@pytest.mark.slow
def test_failed_tile_is_named_and_the_rest_is_meshed(data, shared, reference, capsys, caplog):
    _, side = reference
    failed = [t for t in side["tiles"]["not_solved"] if t["status"] == "failed"]
    assert [t["tile"] for t in failed] == [BAD_TILE]
    assert "too few points" in failed[0]["reason"]
    assert side["tiles"]["solved"] == side["tiles"]["with_points"] - 1 >= 6
    assert side["mesh"]["n_faces"] > 1000 and side["mesh"]["nonmanifold_edges"] == 0
    # the command line names it too (a warning), and exits 6 after writing the mesh
    out = data / "again.ply"
    caplog.clear()
    code, err = run_cli(["reconstruct", str(data / "pts.npy"), "-o", str(out), "-q", "--work-dir",
                         str(data / "ref.job"), *shared], capsys)
    assert code == 6 and out.exists()
    assert any(r.levelname == "WARNING" and BAD_TILE in r.getMessage() and "too few points" in r.getMessage()
               for r in caplog.records), caplog.text
    assert "Traceback" not in err


@pytest.mark.slow
def test_fail_fast_stops_without_writing_a_mesh(data, shared, capsys):
    out = data / "ff.ply"
    code, err = run_cli(["reconstruct", str(data / "pts.npy"), "-o", str(out), "-q", "--fail-fast", *shared],
                        capsys)
    assert code == 6
    lines = [ln for ln in err.splitlines() if ln.startswith("error: ")]
    assert len(lines) == 1 and BAD_TILE in lines[0] and "too few points" in lines[0], err
    assert "Traceback" not in err
    assert not out.exists() and not out.with_suffix(".json").exists()


@pytest.mark.slow
def test_same_inputs_seed_and_workers_give_identical_bytes(data, shared, reference):
    ref_bytes, _ = reference
    out = data / "second.ply"
    assert main(["reconstruct", str(data / "pts.npy"), "-o", str(out), "-q", *shared]) == 6
    assert out.read_bytes() == ref_bytes


def test_solver_result_does_not_depend_on_thread_count(data, tmp_path):
    """The documented claim: numba's thread count changes no field value (bitwise)."""
    import numba

    from tiled_gridpull.tile_solve import solve_tile
    from tiled_gridpull.jobdir import JobPaths
    from tiled_gridpull.prepare import prepare_job

    most = numba.config.NUMBA_NUM_THREADS
    if most < 2:
        pytest.skip("one core: nothing to compare")
    _, specs, _ = prepare_job([str(data / "pts.npy")], TILING, JobPaths(tmp_path / "job"))
    spec = max(specs, key=lambda s: s.n_points)
    before = numba.get_num_threads()
    sums = []
    try:
        for n in (1, most):
            numba.set_num_threads(n)
            sums.append(solve_tile(spec, TILING, SOLVER, tmp_path / f"f{n}.npz")["field_sha256"])
    finally:
        numba.set_num_threads(before)
    assert sums[0] == sums[1]


# ---------------------------------------------------------------------------------------------- worker faults


@pytest.mark.slow
def test_worker_killed_mid_job_gives_the_undisturbed_mesh(data, reference, monkeypatch):
    """SIGKILL a worker process while it solves a tile: Dask reschedules its tasks and the job's mesh equals
    the undisturbed run's, array for array."""
    from tiled_gridpull.pipeline.job import JobOptions, run_job

    marks = data / "marks"
    marks.mkdir()
    monkeypatch.setenv("TILED_GRIDPULL_TEST_HOLD", f"{marks}:1")  # inherited by the LocalCluster's workers
    result: dict = {}

    def job():
        try:
            result["mesh"] = run_job([str(data / "pts.npy")], data / "fault.ply", TILING, SOLVER, data / "fault.job",
                                     JobOptions(workers=2, progress=False))
        except BaseException as exc:  # reported by the assertion below
            result["error"] = exc

    t = threading.Thread(target=job)
    t.start()
    deadline = time.monotonic() + 120
    while not any(marks.iterdir()) and time.monotonic() < deadline:
        time.sleep(0.05)
    first = next(marks.iterdir())
    victim_tile, pid = first.name.rsplit(".", 1)
    os.kill(int(pid), signal.SIGKILL)
    t.join(timeout=300)
    assert not t.is_alive()
    assert "error" not in result, result.get("error")
    mesh = result["mesh"]
    ref = read_mesh(data / "ref.ply")
    assert np.array_equal(mesh.vertices, ref.vertices) and np.array_equal(mesh.faces, ref.faces)
    summaries = {s["tile"]: s for s in mesh.metadata["tile_summaries"]}
    # the killed worker's tile was solved again, by a live worker, without holding a second time
    assert summaries[victim_tile]["worker"] != first.read_text()
    assert len(list(marks.glob(f"{victim_tile}.*"))) == 1
    assert (data / "fault.ply").read_bytes() == reference[0]


@pytest.mark.slow
def test_tile_that_keeps_killing_its_worker_is_a_failed_tile(data, monkeypatch, capsys):
    """A tile whose solve takes its worker process down on every attempt (Dask's KilledWorker) is reported as a
    failed tile by name, exit 6, with the rest of the mesh written; it used to end the job as an internal error."""
    victim = "tile_0_0_0"
    monkeypatch.setenv("TILED_GRIDPULL_TEST_CRASH", victim)  # inherited by the LocalCluster's workers
    out = data / "crash.ply"
    code, err = run_cli(["reconstruct", str(data / "pts.npy"), "-o", str(out), "-q", "--work-dir",
                         str(data / "crash.job"), *OPTS], capsys)
    assert code == 6, err
    assert "Traceback" not in err and "KilledWorker" not in err
    side = json.loads(out.with_suffix(".json").read_text())
    failed = {t["tile"]: t["reason"] for t in side["tiles"]["not_solved"] if t["status"] == "failed"}
    assert "killed the worker process on every attempt" in failed[victim]
    assert read_mesh(out).faces.shape[0] > 0


@pytest.mark.slow
def test_killed_worker_job_prints_only_its_own_lines_and_fails_no_bystander(data):
    """Run as a user would (a process of its own, whose LocalCluster workers share its stderr): Dask's chatter
    ("Couldn't gather keys", "marked as failed because 4 workers died") stays out of the terminal, and a tile
    queued on the same worker as the crashing one is not counted as failed with it (Dask handed a one-thread
    worker two tasks, so every death took the queued one down too)."""
    victim = "tile_0_0_0"
    out = data / "crash_cli.ply"
    env = dict(os.environ, TILED_GRIDPULL_TEST_CRASH=victim)
    proc = subprocess.run([sys.executable, "-m", "tiled_gridpull", "reconstruct", str(data / "pts.npy"), "-o",
                           str(out), "-q", "--work-dir", str(data / "crash_cli.job"), *OPTS],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 6, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert lines and all(ln.startswith("tile ") for ln in lines), proc.stderr
    side = json.loads(out.with_suffix(".json").read_text())
    failed = {t["tile"] for t in side["tiles"]["not_solved"]
              if t["status"] == "failed" and "too few points" not in (t["reason"] or "")}
    assert failed == {victim}, side["tiles"]["not_solved"]


@pytest.mark.slow
def test_far_stray_point_is_counted_at_planning_and_dropped_on_request(data, capsys):
    """A point far from the rest (a (0, 0, 0) in a UTM cloud; here 1e6 away) stretches the lattice past what it
    can hold: refused at planning with how many points are far and how to drop them. With --drop-outliers the
    job equals, mesh for mesh, the job on the cloud without them."""
    pts = scene_points()
    np.save(data / "stray.npy", np.vstack([pts, [[1e6, 1e6, 0.0]]]))
    out = data / "stray.ply"
    code, err = run_cli(["reconstruct", str(data / "stray.npy"), "-o", str(out), "-q", *OPTS], capsys)
    assert code == 3, err
    assert "more than the lattice can hold" in err and "lie far from the rest" in err and "e.g. (1e+06, 1e+06, 0)" \
        in err and "--drop-outliers" in err
    assert len([ln for ln in err.splitlines() if ln.strip()]) == 1
    assert not out.exists() and not (data / "stray.job" / "points").exists()

    with pytest.warns(UserWarning, match=r"drop_outliers: 1 of 6,007 points lie far from the rest .*e\.g\. \(1e\+06"):
        code, err = run_cli(["reconstruct", str(data / "stray.npy"), "-o", str(out), "-q", *OPTS,
                             "--drop-outliers"], capsys)
    assert code == 6, err  # as without the far point: the 6-point cluster's tile has too few points to solve
    side = json.loads(out.with_suffix(".json").read_text())
    ref = data / "kept.ply"
    code, err = run_cli(["reconstruct", str(data / "pts.npy"), "-o", str(ref), "-q", *OPTS], capsys)
    assert code == 6, err
    assert read_mesh(out).faces.shape[0] > 0
    assert np.array_equal(read_mesh(out).vertices, read_mesh(ref).vertices)
    assert np.array_equal(read_mesh(out).faces, read_mesh(ref).faces)
    assert side["lattice"] == json.loads(ref.with_suffix(".json").read_text())["lattice"]


@pytest.mark.parametrize("address,needle", [
    ("tcp://127.0.0.1:1", "cannot reach a Dask scheduler (nothing listens there)"),
    ("tcp://127.0.0.1:99999", "port 99999 is not in 1-65535"),
    ("http://127.0.0.1:8786", "scheme 'http' is not supported"),
    ("not an address", "expected tcp://HOST:PORT"),
])
def test_bad_scheduler_address_is_refused_before_any_work(data, capsys, address, needle):
    out = data / "sched.ply"
    code, err = run_cli(["reconstruct", str(data / "pts.npy"), "-o", str(out), "-q", "--work-dir",
                         str(data / "sched.job"), *OPTS[:-2], "--scheduler", address], capsys)
    assert code == 2 and needle in err, err
    assert len([ln for ln in err.splitlines() if ln.strip()]) == 1
    # refused before partitioning, and without a client waiting out its 30 s connect timeout
    assert not out.exists() and not (data / "sched.job" / "points").exists()


# ---------------------------------------------------------------------------------------------------- resume


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.0, 0.5], ids=["at-first-solve", "mid-task"])
def test_interrupted_job_resumes_to_the_same_bytes(data, shared, reference, capsys, delay):
    """Ctrl-C once the first solve is recorded, or half a held task later: at the second timing another task's
    result is often on its way back to the driver when the client closes (that fetch, cut, used to print a
    tornado traceback now and then)."""
    ref_bytes, ref_side = reference
    out, work = data / f"resumed_{delay}.ply", data / f"resumed_{delay}.job"
    marks = data / f"marks_interrupt_{delay}"
    marks.mkdir()
    cmd = [sys.executable, "-m", "tiled_gridpull", "reconstruct", str(data / "pts.npy"), "-o", str(out), "-q",
           "--work-dir", str(work), *OPTS]
    env = dict(os.environ, TILED_GRIDPULL_TEST_HOLD=f"{marks}:1")
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not list((work / "summaries").glob("solve_*.json")) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        time.sleep(delay)
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert not out.exists() and not out.with_suffix(".json").exists()  # no half-written output
    done = len(list((work / "summaries").glob("solve_*.json")))
    n_tiles = ref_side["tiles"]["with_points"]
    assert 1 <= done < n_tiles - 1  # the failed tile is never recorded

    code, err = run_cli(["reconstruct", str(data / "pts.npy"), "-o", str(out), "-q", "--work-dir", str(work),
                         *shared], capsys)
    assert code == 6, err
    assert out.read_bytes() == ref_bytes
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["reused"]["partition"] is True
    assert side["reused"]["solves"] == done


@pytest.mark.slow
def test_changed_settings_invalidate_only_what_depends_on_them(data, shared, reference, caplog):
    """Trim distance is read only by the mesh step; iterations by the solve (and so the mesh)."""
    _, ref_side = reference
    work = data / "inval.job"
    shutil.copytree(data / "ref.job", work)  # timestamps kept: a copied job directory stays reusable
    ok = ref_side["tiles"]["with_points"] - 1  # all but the failed tile
    meshed = ref_side["tiles"]["solved"]

    def run(*extra):
        out = data / "inval.ply"
        with caplog.at_level("INFO", logger="tiled_gridpull"):
            assert main(["reconstruct", str(data / "pts.npy"), "-o", str(out), "-q", "--work-dir", str(work),
                         *shared, *extra]) == 6
        return json.loads(out.with_suffix(".json").read_text())["reused"]

    assert run() == {"partition": True, "solves": ok, "meshes": meshed}
    assert run("--set", "trim_distance=1.5") == {"partition": True, "solves": ok, "meshes": 0}
    assert f"reused {ok} of {ok + 1} tile solves and 0 of {meshed} mesh pieces" in caplog.text
    assert run("--set", "trim_distance=1.5", "--iterations", "60") == {"partition": True, "solves": 0, "meshes": 0}
