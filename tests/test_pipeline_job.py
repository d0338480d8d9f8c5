"""The Dask engine: a real scheduler and workers on loopback, and worker memory bounded by the tile."""

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tiled_gridpull.config import SolverConfig
from tiled_gridpull.tiling import TilingConfig
from conftest import terrain

BIN = Path(sys.executable).parent
SOLVER = SolverConfig(m2=8, refine_m2=6, coarse_iterations=100, iterations=100, queries=20000)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def cluster(tmp_path):
    port = _free_port()
    env = dict(os.environ, TILED_GRIDPULL_THREADS="1", OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    procs = [subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)]
    address = f"tcp://127.0.0.1:{port}"
    try:
        time.sleep(2.0)
        for i in range(2):
            procs.append(subprocess.Popen([str(BIN / "dask"), "worker", address, "--nthreads", "1",
                                           "--no-dashboard", "--name", f"w{i}", "--local-directory",
                                           str(tmp_path / f"w{i}")],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env))
        from distributed import Client

        with Client(address, timeout="30s") as c:
            c.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


@pytest.mark.slow
def test_job_on_separately_started_scheduler_and_workers(tmp_path, cluster):
    pts = terrain(19.2, 40)
    np.save(tmp_path / "ground.npy", pts)
    out = tmp_path / "ground.ply"
    from tiled_gridpull.pipeline.cli import main

    code = main(["reconstruct", str(tmp_path / "ground.npy"), "-o", str(out), "--voxel-size", "0.2",
                 "--tile-size", "6.4", "--overlap", "1.6", "--set", "m2=8", "--set", "refine_m2=6",
                 "--set", "coarse_iterations=100",
                 "--set", "iterations=100", "--set", "queries=20000", "--scheduler", cluster, "-q"])
    assert code == 0
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["engine"]["scheduler"] == cluster
    workers = {s["worker"] for s in side["tile_summaries"]}
    assert len(workers) == 2, workers  # both workers solved tiles
    assert side["tiles"]["solved"] == side["tiles"]["with_points"] >= 9
    assert side["mesh"]["nonmanifold_edges"] == 0 and side["mesh"]["n_faces"] > 1000


@pytest.mark.slow
def test_worker_memory_does_not_grow_with_tile_count(tmp_path):
    from tiled_gridpull.pipeline.job import JobOptions, run_job

    peaks = {}
    for extent in (12.8, 25.6):  # 2 x 2 and 4 x 4 tiles, same density
        d = tmp_path / f"e{extent}"
        d.mkdir()
        np.save(d / "g.npy", terrain(extent, 60, seed=1))
        tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, trim_distance=2.0)
        mesh = run_job([str(d / "g.npy")], d / "g.ply", tiling, SOLVER, d / "job",
                       JobOptions(workers=1, progress=False))
        tiles = mesh.metadata["tile_summaries"]
        peaks[len(tiles)] = max(s["peak_rss_mb"] for s in tiles)
    small, large = sorted(peaks)
    assert small == 4 and large == 16
    assert peaks[large] < 1.25 * peaks[small], peaks


def _grid_specs(nx: int, ny: int, nz: int):
    from tiled_gridpull.lattice import Lattice
    from tiled_gridpull.tile_plan import TileSpec

    block = Lattice(origin=(0.0, 0.0, 0.0), cell_size=0.1, shape=(41, 41, 41))
    return [TileSpec(index=(i, j, k), core_lo=(0, 0, 0), core_hi=(32, 32, 32), block=block, n_points=100,
                     points_path=f"/nowhere/tile_{i}_{j}_{k}.npy")
            for i in range(nx) for j in range(ny) for k in range(nz) if (i + j + k) % 5 != 3]  # some tiles empty


def _solve_echo(spec):
    return {"tile": spec.name, "status": "solved"}


def _mesh_echo(spec, own, nbs, nb_summaries):
    return {"tile": spec.name, "own": own["tile"], "neighbours": sorted(n.name for n in nbs),
            "summaries": sorted(s["tile"] for s in nb_summaries)}


class _CountingClient:
    """Counts submissions, so the test can see how many tasks were in flight."""

    def __init__(self, client):
        self.client, self.submitted = client, 0

    def submit(self, *args, **kwargs):
        self.submitted += 1
        return self.client.submit(*args, **kwargs)

    def map(self, *args, key, **kwargs):
        self.submitted += len(key)
        return self.client.map(*args, key=key, **kwargs)

    def __getattr__(self, name):  # everything else (scheduler_info for the no-worker watch) as the client
        return getattr(self.client, name)


@pytest.mark.parametrize("window", [1, 7, 10_000])
def test_sliding_window_keeps_the_graph_and_bounds_tasks_in_flight(window):
    from distributed import Client

    from tiled_gridpull.pipeline.job import run_tiles
    from tiled_gridpull.jobdir import neighbors_of

    specs = _grid_specs(5, 4, 3)
    by_index = {s.index: s for s in specs}
    with Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=":0") as client:
        counting = _CountingClient(client)
        seen, most_in_flight = [], 0
        for kind, idx, res in run_tiles(counting, specs, _solve_echo, lambda s: (), _mesh_echo, lambda s: (),
                                        window=window):
            most_in_flight = max(most_in_flight, counting.submitted - len(seen))
            seen.append((kind, idx, res))
    assert most_in_flight <= window
    if window < len(specs):
        assert most_in_flight == window  # the window is used, not just respected
    assert sorted((k, i) for k, i, _ in seen) == sorted([("solve", s.index) for s in specs]
                                                       + [("mesh", s.index) for s in specs])
    for kind, idx, res in seen:
        if kind == "mesh":
            want = sorted(n.name for n in neighbors_of(by_index[idx], by_index))
            assert res["own"] == by_index[idx].name
            assert res["neighbours"] == want and res["summaries"] == want


def test_sliding_window_rejects_an_empty_window():
    from tiled_gridpull.pipeline.job import run_tiles

    with pytest.raises(ValueError, match="window"):
        next(run_tiles(None, _grid_specs(1, 1, 1), _solve_echo, lambda s: (), _mesh_echo, lambda s: (), window=0))


def test_task_arguments_do_not_grow_with_the_tile_count():
    """A mesh task carries the field paths of its own tile and neighbours only (not the whole job's map, which
    made every task's message grow with the tile count)."""
    import pickle

    import numpy as np

    from tiled_gridpull.tiled_job import task_arguments
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.jobdir import JobPaths, neighbors_of
    from tiled_gridpull.tiling import TilingConfig

    def mesh_arg_bytes(specs, spec):
        _, mesh_args = task_arguments(specs, TilingConfig(), SolverConfig(), JobPaths("/job"), (0.0, 0.0, 0.0),
                                      np.zeros(3, np.int64))
        args = mesh_args(spec)
        by_index = {s.index: s for s in specs}
        assert set(args[2]) == {t.name for t in [spec, *neighbors_of(spec, by_index)]}
        assert args[2][spec.name] == str(JobPaths("/job").field(spec))
        return len(pickle.dumps(args))

    small = _grid_specs(3, 3, 3)
    large = _grid_specs(20, 20, 5)
    centre = next(s for s in small if s.index == (1, 1, 0))
    assert mesh_arg_bytes(large, centre) == mesh_arg_bytes(small, centre)


def _solve_fails_on_one(spec):
    if spec.index == (1, 1, 0):
        raise RuntimeError(f"worker crashed on {spec.name}")
    return {"tile": spec.name, "status": "solved"}


def test_sliding_window_raises_a_task_error():
    from distributed import Client

    from tiled_gridpull.pipeline.job import run_tiles

    with Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=":0") as client:
        with pytest.raises(RuntimeError, match="worker crashed on tile_1_1_0"):
            for _ in run_tiles(client, _grid_specs(3, 3, 3), _solve_fails_on_one, lambda s: (), _mesh_echo,
                               lambda s: (), retries=0, window=5):
                pass


WORKER_COMPILE_SCRIPT = '''
import numba  # imported by the main module, as the CLI does: spawned workers re-import it before their env is set
from numba import njit, prange
import numpy as np

from tiled_gridpull.pipeline.job import JobOptions, make_client, _configure_worker_threads


def fresh_compile(seed):
    _configure_worker_threads()

    @njit(parallel=True)  # no cache: compiles inside the worker, as a cold numba cache does
    def total(a):
        s = 0.0
        for i in prange(a.shape[0]):
            s += a[i]
        return s

    total(np.ones(1000))  # launches the worker's thread pool
    numba.core.config.reload_config()  # what every further compilation does first
    return total(np.arange(seed + 10.0)), numba.get_num_threads()


if __name__ == "__main__":
    client, cluster = make_client(JobOptions(workers=2, progress=False), n_tiles=2)
    try:
        print(client.gather(client.map(fresh_compile, [0, 1])))
    finally:
        client.close()
        cluster.close()
'''


@pytest.mark.slow
def test_workers_compile_fresh_kernels_when_numba_was_imported_first(tmp_path):
    """A cold numba cache compiles inside the workers; that must not trip over the thread-pool size (it did:
    `make demo` on a fresh machine failed with "Cannot set NUMBA_NUM_THREADS ...")."""
    script = tmp_path / "compile_in_workers.py"
    script.write_text(WORKER_COMPILE_SCRIPT)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    env.pop("NUMBA_NUM_THREADS", None)
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    expected_threads = max(1, (os.cpu_count() or 1) // 2)
    assert f"[(45.0, {expected_threads}), (55.0, {expected_threads})]" in run.stdout


WARM_UP_SCRIPT = '''
import json, logging, sys

from tiled_gridpull.kernels.warmup import cold_kernels
from tiled_gridpull.pipeline.job import JobOptions, compile_on_workers, make_client

logging.basicConfig(level=logging.INFO, format="%(message)s")
NAMES = ["losses.scatter_add", "band.scatter_cells", "band.brick_neighbors"]

if __name__ == "__main__":
    client, cluster = make_client(JobOptions(workers=2, progress=False), n_tiles=2)
    try:
        first = compile_on_workers(client, kernels=NAMES)
        tasks = client.run_on_scheduler(lambda dask_scheduler: sorted(
            str(e[0]) for e in dask_scheduler.transition_log if str(e[0]).startswith("compile-kernels")))
        again = compile_on_workers(client, kernels=NAMES)
        print(json.dumps({"first": first, "again": again, "driver": cold_kernels(NAMES), "tasks": sorted(set(tasks))}))
    finally:
        client.close()
        cluster.close()
'''


@pytest.mark.slow
def test_workers_compile_the_cold_kernels_ahead_in_shares_and_say_so(tmp_path):
    """On an empty numba cache the kernels are compiled before any tile, a share on each of the two workers, with
    a line on screen; the cache then holds them for every process, and a second warm-up does nothing, silently."""
    script = tmp_path / "warm_up.py"
    script.write_text(WARM_UP_SCRIPT)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]), NUMBA_CACHE_DIR=str(tmp_path / "nc"))
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert sorted(out["first"]) == sorted(["losses.scatter_add", "band.scatter_cells", "band.brick_neighbors"])
    assert out["again"] == [] and out["driver"] == []  # cached for this process too
    assert out["tasks"] == ["compile-kernels-0", "compile-kernels-1"]  # one share per worker
    assert run.stderr.count("compiling 3 numba kernels, once per installation") == 1
    assert "compiled the kernels in" in run.stderr


_STARTED: list = []


def _solve_records_start(spec):
    _STARTED.append(spec.name)
    return {"tile": spec.name, "status": "solved"}


@pytest.mark.parametrize("window", [3, 10_000])
def test_costliest_tiles_start_first_within_a_window(window):
    """Longest-processing-time-first: within each window's worth of tiles (in tile order), solves start in
    order of decreasing cost, so a big tile never starts last and runs alone while the other workers idle."""
    import dataclasses

    from distributed import Client

    from tiled_gridpull.pipeline.job import run_tiles

    specs = _grid_specs(3, 3, 1)
    # costs unrelated to tile order: occupied bricks from a fixed permutation
    specs = [dataclasses.replace(s, occupied_bricks=int(c), n_points=1000)
             for s, c in zip(specs, [5, 90, 20, 70, 10, 60, 30, 80, 40])]
    by_name = {s.name: s for s in specs}
    _STARTED.clear()
    with Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=":0") as client:
        list(run_tiles(client, specs, _solve_records_start, lambda s: (), _mesh_echo, lambda s: (), window=window))
    started = [by_name[n] for n in _STARTED]
    ordered = sorted(specs, key=lambda s: s.index)
    for w in range(0, len(ordered), window):
        group = {s.name for s in ordered[w:w + window]}
        costs = [s.occupied_bricks for s in started if s.name in group]
        assert costs == sorted(costs, reverse=True), (w, costs)
    if window >= len(specs):
        assert [s.occupied_bricks for s in started] == sorted((s.occupied_bricks for s in specs), reverse=True)


def _slow_solve(spec):
    time.sleep(0.5)
    return {"tile": spec.name, "status": "solved"}


@pytest.mark.slow
def test_cluster_without_workers_stops_the_job_instead_of_hanging():
    """Every worker gone (scaled away here; killed in real life): the job stops with a clear error after the
    no-worker timeout instead of waiting for ever."""
    from distributed import Client, LocalCluster

    from tiled_gridpull.pipeline.job import run_tiles
    from tiled_gridpull.errors import ClusterError

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as lc, \
            Client(lc) as client:
        events = run_tiles(client, _grid_specs(4, 4, 1), _slow_solve, lambda s: (), _mesh_echo, lambda s: (),
                           window=2, no_worker_timeout=3)
        next(events)
        lc.scale(0)
        t0 = time.monotonic()
        with pytest.raises(ClusterError, match="no worker for 3 s"):
            for _ in events:
                pass
        assert time.monotonic() - t0 < 60


def test_external_scheduler_without_workers_or_shared_directory(tmp_path):
    from distributed import Client, LocalCluster

    from tiled_gridpull.pipeline.job import check_workers_see
    from tiled_gridpull.errors import ClusterError

    with LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as lc, Client(lc) as client:
        with pytest.raises(ClusterError, match="no worker joined the Dask scheduler within 1 s"):
            check_workers_see(client, tmp_path, 1)
        lc.scale(1)
        check_workers_see(client, tmp_path, 30)
        with pytest.raises(ClusterError, match="cannot see the job directory .*shared"):
            check_workers_see(client, tmp_path / "not-on-the-workers", 30)


def _slow_marked(i, where):
    """A task: marks its start, fails at once when ``i`` is 3, else marks its end after 0.2 s."""
    from pathlib import Path

    Path(where, f"{i}.start").touch()
    if i == 3:
        raise ValueError("task 3 failed")
    time.sleep(0.2)
    Path(where, f"{i}.end").touch()
    return i * i


def test_executor_map_keeps_order_and_a_failure_leaves_no_task_running(tmp_path):
    from distributed import Client, LocalCluster

    from tiled_gridpull.pipeline.job import DaskExecutor, JobOptions

    cluster = LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=":0")
    executor = DaskExecutor(JobOptions(progress=False))
    executor._client = Client(cluster)
    try:
        ok = tmp_path / "ok"
        ok.mkdir()
        assert executor.map(_slow_marked, [(i, str(ok)) for i in (5, 1, 4, 2, 6, 0)], tmp_path) == \
            [25, 1, 16, 4, 36, 0]
        bad = tmp_path / "bad"
        bad.mkdir()
        with pytest.raises(ValueError, match="task 3 failed"):
            executor.map(_slow_marked, [(i, str(bad)) for i in range(40)], tmp_path)
        started = {p.stem for p in bad.glob("*.start")}
        ended = {p.stem for p in bad.glob("*.end")}
        # every task that started (but the failed one) had returned when the error came; the rest never ran,
        # not even later: the caller may now remove what they wrote
        assert ended == started - {"3"}
        assert len(started) <= 3 + 2 * 2 + 1
        time.sleep(0.5)
        assert {p.stem for p in bad.glob("*.start")} == started
    finally:
        executor._client.close()
        cluster.close()


class _Listener:
    """Something that is not a Dask scheduler on 127.0.0.1: a TCP listener that accepts and never answers
    (``silent``), or a web server (``http``) answering every request with a page. It stops by itself after
    ``life`` seconds, or when the test leaves the ``with``."""

    def __init__(self, kind: str, life: float = 60.0):
        import threading

        self.kind, self.sock = kind, socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.until, self.conns = time.monotonic() + life, []
        self.thread = threading.Thread(target=self._serve, daemon=True)

    def _serve(self):
        while time.monotonic() < self.until:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            self.conns.append(conn)
            if self.kind == "http":
                conn.settimeout(2)
                try:
                    conn.recv(65536)
                    conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: 13\r\n\r\n"
                                 b"<h1>hello</h1>")
                except OSError:
                    pass
        self.close()

    def close(self):
        self.until = 0
        for c in self.conns:
            c.close()
        self.sock.close()

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.close()


@pytest.mark.parametrize("kind", ["silent", "http"])
def test_a_scheduler_address_where_something_else_listens_is_refused_before_any_work(tmp_path, kind):
    """A silent TCP listener or a web server at --scheduler accepted the connection and the job hung after the
    partition, with no message: now a handshake timeout, one line, exit 2, nothing written."""
    np.save(tmp_path / "ground.npy", terrain(12.8, 30))
    out, work = tmp_path / "out.ply", tmp_path / "out.job"
    with _Listener(kind) as server:
        t0 = time.monotonic()
        proc = subprocess.run([sys.executable, "-m", "tiled_gridpull", "reconstruct", str(tmp_path / "ground.npy"),
                               "-o", str(out), "--work-dir", str(work), "-q", "--voxel-size", "0.2",
                               "--scheduler", f"tcp://127.0.0.1:{server.port}"],
                              capture_output=True, text=True, timeout=90,
                              env=dict(os.environ, NUMBA_NUM_THREADS="1"))
    err = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert not out.exists() and not (work.exists() and any(work.iterdir())), sorted(work.rglob("*"))
    assert proc.returncode == 2 and len(err) == 1, proc.stderr
    assert err[0].startswith(f"error: --scheduler tcp://127.0.0.1:{server.port}: not a Dask scheduler"), err
    assert time.monotonic() - t0 < 60


@pytest.mark.slow
def test_an_external_scheduler_that_dies_mid_job_is_exit_7_in_one_line_and_the_rerun_resumes(tmp_path):
    """The external scheduler killed while tiles are solving: "internal error: FutureCancelledError" (exit 1, two
    lines) before; now the README's exit code for a lost cluster (7) and one line, and the same command on a
    cluster of its own resumes from the tiles already done."""
    import signal

    repo = Path(__file__).resolve().parents[1]
    np.save(tmp_path / "ground.npy", terrain(19.2, 40))
    out, work, marks = tmp_path / "g.ply", tmp_path / "g.job", tmp_path / "marks"
    marks.mkdir()
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    # the workers import this checkout, as the driver does; the first attempt at each tile holds 60 s
    env = dict(os.environ, TILED_GRIDPULL_THREADS="1", OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join(filter(None, [str(repo), os.environ.get("PYTHONPATH")])),
               TILED_GRIDPULL_TEST_HOLD=f"{marks}:60")
    scheduler = subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                  "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    procs = [scheduler]
    opts = ["--voxel-size", "0.2", "--tile-size", "6.4", "--overlap", "1.6", "--set", "m2=8", "--set", "refine_m2=6",
            "--set", "coarse_iterations=40", "--set", "iterations=40", "--set", "queries=5000"]
    cmd = [sys.executable, "-m", "tiled_gridpull", "reconstruct", str(tmp_path / "ground.npy"), "-o", str(out),
           "--work-dir", str(work), *opts]
    try:
        time.sleep(2.0)
        procs.append(subprocess.Popen([str(BIN / "dask"), "worker", address, "--nthreads", "1", "--no-dashboard",
                                       "--local-directory", str(tmp_path / "w")], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL, env=env))
        job = subprocess.Popen(cmd + ["-q", "--scheduler", address], cwd=repo, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
        procs.append(job)
        deadline = time.monotonic() + 120
        while not any(marks.iterdir()) and time.monotonic() < deadline:
            assert job.poll() is None, job.communicate()
            time.sleep(0.1)
        assert any(marks.iterdir()), "no tile started solving"
        scheduler.send_signal(signal.SIGKILL)
        _, err = job.communicate(timeout=180)
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.kill()
            p.wait(timeout=30)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert job.returncode == 7 and len(lines) == 1, err
    assert lines[0].startswith("error: ") and "scheduler" in lines[0] and "rerun to resume" in lines[0], err
    assert not out.exists() and not out.with_suffix(".json").exists()
    # the same command on a cluster of its own resumes: the partition is reused, and so is every tile recorded
    done = {p.name for p in (work / "summaries").glob("solve_*.json")}
    rerun = subprocess.run(cmd + ["--workers", "1", "-v"], cwd=repo, capture_output=True, text=True, timeout=400,
                           env=dict(os.environ, NUMBA_NUM_THREADS="1"))
    assert rerun.returncode == 0, rerun.stderr
    assert "reused the partition" in rerun.stderr, rerun.stderr
    assert done <= {p.name for p in (work / "summaries").glob("solve_*.json")}
