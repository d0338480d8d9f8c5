"""Tiled jobs on a card: tiles prepared on any worker, solved in batches on the worker that holds the card
(:class:`tiled_gridpull.pipeline.job.Batching`), meshed once they and their neighbours are solved. The graph is
checked here with stand-in steps; the steps themselves in tests/test_tile_batch.py; a whole job on the simulated
card in tests/test_device.py."""

import os

import pytest

from test_pipeline_job import _grid_specs, _mesh_echo

SKIPPED = {(0, 1, 1), (2, 2, 0)}  # tiles whose preparation finds them too sparse: they need no batch


def _prepare_echo(spec):
    from distributed import get_worker

    status = "skipped" if spec.index in SKIPPED else "prepared"
    return {"tile": spec.name, "status": status, "card": get_worker().state.total_resources.get("GPU", 0)}


#: what each stand-in batch did, for its tiles' stand-in finishes (the in-process clusters share it)
_BATCHED: dict = {}


def _batch_echo(specs, **extra):
    from distributed import get_worker

    card = get_worker().state.total_resources.get("GPU", 0)
    for s in specs:
        _BATCHED[s.name] = {"batch": len(specs), "card": card, **extra}
    return [{"tile": s.name, "status": "unfinished"} for s in specs]


def _finish_echo(spec):
    from distributed import get_worker

    return {"tile": spec.name, "status": "solved", **_BATCHED.get(spec.name, {}),
            "finish_card": get_worker().state.total_resources.get("GPU", 0)}


def _batching(size, prepare_fn=None, batch_fn=None, **kwargs):
    from tiled_gridpull.pipeline.job import Batching

    return Batching(size, prepare_fn or _prepare_echo, lambda s: (), batch_fn or _batch_echo, lambda group: (),
                    _finish_echo, lambda s: (), **kwargs)


def _mesh_where(spec, own, nbs, nb_summaries):
    from distributed import get_worker

    return {**_mesh_echo(spec, own, nbs, nb_summaries), "card": get_worker().state.total_resources.get("GPU", 0)}


class _Staging:
    """A client that tracks the tiles between their preparation's submission and their batch's return."""

    def __init__(self, client):
        self.client, self.out, self.most = client, 0, 0

    def submit(self, fn, *args, key, **kwargs):
        if key.startswith("solve-"):
            self.out += 1
            self.most = max(self.most, self.out)
        return self.client.submit(fn, *args, key=key, **kwargs)

    def map(self, fn, *args, key, **kwargs):
        if key[0].startswith("solve-"):
            self.out += len(key)
            self.most = max(self.most, self.out)
        return self.client.map(fn, *args, key=key, **kwargs)

    def __getattr__(self, name):
        return getattr(self.client, name)


@pytest.mark.parametrize("size", [1, 4])
def test_prepared_tiles_are_solved_in_batches_on_the_card_and_meshed_after_their_neighbours(size):
    from distributed import Client, LocalCluster

    from tiled_gridpull.jobdir import neighbors_of
    from tiled_gridpull.pipeline.job import BATCHES_AHEAD, add_card_worker, run_tiles

    specs = _grid_specs(4, 3, 2)
    by_index = {s.index: s for s in specs}
    with LocalCluster(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=":0") as cluster:
        add_card_worker(cluster)
        with Client(cluster) as client:
            client.wait_for_workers(2, timeout=30)
            staging = _Staging(client)
            seen = []
            for kind, idx, res in run_tiles(staging, specs, None, None, _mesh_where, lambda s: (),
                                            batching=_batching(size)):
                if kind == "solve":
                    staging.out -= 1
                seen.append((kind, idx, res))
    solves = {idx: res for kind, idx, res in seen if kind == "solve"}
    meshes = {idx: res for kind, idx, res in seen if kind == "mesh"}
    assert set(solves) == set(meshes) == set(by_index)  # every tile solved once and meshed once
    assert len([k for k, _, _ in seen if k == "solve"]) == len(specs)
    for idx, res in solves.items():
        if idx in SKIPPED:  # preparations and meshes on the other workers: the card waits for none
            assert res["status"] == "skipped" and "batch" not in res and res["card"] == 0
        else:  # batches run on the card's worker only, and the finishes off it
            assert res["status"] == "solved" and 1 <= res["batch"] <= size and res["card"] == 1
            assert res["finish_card"] == 0
    if size > 1:
        assert max(r.get("batch", 0) for r in solves.values()) > 1  # launches are shared
    assert staging.most <= BATCHES_AHEAD * size  # the job directory holds a few batches of prepared tiles
    order = [(k, i) for k, i, _ in seen]
    for idx, res in meshes.items():
        want = sorted(n.name for n in neighbors_of(by_index[idx], by_index))
        assert res["neighbours"] == want and res["summaries"] == want and res["card"] == 0
        # a mesh comes after the solves of its tile and its neighbours
        assert all(order.index(("solve", n.index)) < order.index(("mesh", idx))
                   for n in [by_index[idx], *neighbors_of(by_index[idx], by_index)])


def _batch_slow(specs):
    import time

    t0 = time.monotonic()
    time.sleep(0.2)
    return _batch_echo(specs, span=(t0, time.monotonic()))


@pytest.mark.parametrize("cards", [1, 2])
def test_one_batch_per_card_at_a_time(cards):
    """Each card has one batch at a time (a second queued behind it would die with it, were it to kill its
    worker); with two cards, two batches run at once."""
    from distributed import Client, LocalCluster

    from tiled_gridpull.pipeline.job import add_card_worker, run_tiles

    class Out:  # counts the batches out (submitted and not done) as each is submitted
        def __init__(self, client):
            self.client, self.batches, self.most = client, [], 0

        def submit(self, fn, *args, key, **kwargs):
            fut = self.client.submit(fn, *args, key=key, **kwargs)
            if key.startswith("batch-"):
                self.most = max(self.most, 1 + sum(not f.done() for f in self.batches))
                self.batches.append(fut)
            return fut

        def __getattr__(self, name):
            return getattr(self.client, name)

    specs = _grid_specs(4, 4, 1)
    with LocalCluster(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=":0") as cluster:
        for _ in range(cards):
            add_card_worker(cluster, name=f"card{_}")
        with Client(cluster) as client:
            client.wait_for_workers(1 + cards, timeout=30)
            out = Out(client)
            spans = {r["span"] for k, _, r in run_tiles(out, specs, None, None, _mesh_echo, lambda s: (),
                                                        batching=_batching(2, batch_fn=_batch_slow))
                     if k == "solve" and "span" in r}
    assert out.most == cards
    spans = sorted(spans)
    overlaps = sum(b[0] < a[1] for a, b in zip(spans, spans[1:]))
    assert (overlaps > 0) == (cards == 2), spans


BIG = (1, 1, 0)  # a tile whose estimate alone exceeds the budget


def _prepare_sized(spec):
    return {"tile": spec.name, "status": "prepared", "card_bytes": 500.0 if spec.index == BIG else 100.0}


def test_batches_are_sized_to_the_cards_memory():
    """A batch takes tiles while their estimated card memory fits the budget; a tile that needs more goes alone,
    and every tile of a batch says what the batch was sized by."""
    from distributed import Client, LocalCluster

    from tiled_gridpull.pipeline.job import add_card_worker, run_tiles

    specs = _grid_specs(4, 3, 1)
    with LocalCluster(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=":0") as cluster:
        add_card_worker(cluster)
        with Client(cluster) as client:
            client.wait_for_workers(2, timeout=30)
            solves = {i: r for k, i, r in run_tiles(client, specs, None, None, _mesh_echo, lambda s: (),
                                                    batching=_batching(8, _prepare_sized, _batch_slow,
                                                                       budget=300.0))
                      if k == "solve"}
    assert len(solves) == len(specs) and all(r["status"] == "solved" for r in solves.values())
    assert solves[BIG]["batch"] == 1 and solves[BIG]["batch_card_bytes"] == 500.0
    others = [r for i, r in solves.items() if i != BIG]
    assert all(r["batch_card_bytes"] == 100.0 * r["batch"] <= 300.0 for r in others)
    assert max(r["batch"] for r in others) == 3  # the budget, not the size, bounds them


def _batch_dies_on_one(specs):
    if any(s.index == (1, 1, 0) for s in specs):
        os._exit(137)  # a crash in native code (or the card's driver) takes the worker process down
    return _batch_echo(specs)


@pytest.mark.slow
def test_a_batch_that_kills_its_worker_fails_only_the_tile_at_fault():
    """Its tiles are tried alone: the others are solved, the one at fault fails by name."""
    import dask
    from distributed import Client, LocalCluster

    from tiled_gridpull.pipeline.job import add_card_worker, run_tiles

    specs = _grid_specs(3, 2, 1)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}), \
            LocalCluster(processes=True, n_workers=1, threads_per_worker=1, dashboard_address=":0") as cluster:
        add_card_worker(cluster)
        with Client(cluster) as client:
            client.wait_for_workers(2, timeout=60)
            seen = [(k, i, r) for k, i, r in run_tiles(client, specs, None, None, _mesh_echo, lambda s: (), retries=0,
                                                       batching=_batching(8, batch_fn=_batch_dies_on_one))
                    if k == "solve"]
    failed = [i for _, i, r in seen if r["status"] == "failed"]
    assert failed == [(1, 1, 0)] and "killed the worker" in dict((i, r) for _, i, r in seen)[(1, 1, 0)]["reason"]
    assert {i for _, i, r in seen if r["status"] == "solved"} == {s.index for s in specs} - {(1, 1, 0)} - SKIPPED


def test_batches_that_no_worker_can_take_stop_the_job_in_one_line():
    """On a scheduler whose workers hold no card the batches would wait for ever: the job says why and stops."""
    from distributed import Client

    from tiled_gridpull.errors import ClusterError
    from tiled_gridpull.pipeline.job import run_tiles

    with Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=":0") as client:
        with pytest.raises(ClusterError, match="resources GPU=1.*dask worker --resources GPU=1"):
            for _ in run_tiles(client, _grid_specs(2, 1, 1), None, None, _mesh_echo, lambda s: (),
                               no_worker_timeout=1.0,
                               batching=_batching(4)):
                pass


def test_a_runs_leftover_prepared_tiles_are_swept(tmp_path):
    """A batched run leaves no prepared tile behind, however it ends (each is a copy of a tile's points)."""
    from tiled_gridpull.jobdir import JobPaths
    from tiled_gridpull.pipeline.job import _sweep_prepared

    paths = JobPaths(tmp_path / "job")
    (paths.root / "prepared").mkdir(parents=True)
    for name in ("tile_0_0_0.npz", "tile_1_0_0.npz"):
        (paths.root / "prepared" / name).write_bytes(b"x")
    (paths.root / "prepared" / "notes.txt").write_text("not ours")
    _sweep_prepared(paths)
    assert sorted(f.name for f in (paths.root / "prepared").iterdir()) == ["notes.txt"]
    _sweep_prepared(JobPaths(tmp_path / "none"))  # nothing there: nothing to do


def _run_in_thread(fn, timeout: float = 60.0):
    """``fn()``'s result, or a failed test if it has not returned within ``timeout`` (a hung driver)."""
    import threading

    box = {}
    t = threading.Thread(target=lambda: box.setdefault("out", fn()), daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), f"the job's driver hung (no end within {timeout:g} s)"
    return box["out"]


#: stand-in finishes that find their tile's files lost: how often each tile's were
_LOST: dict = {}


def _finish_loses(spec):
    if spec.index == (0, 0, 0) or (spec.index == (1, 0, 0) and _LOST.get(spec.name, 0) < 1):
        _LOST[spec.name] = _LOST.get(spec.name, 0) + 1
        return {"tile": spec.name, "status": "lost", "reason": "gone"}
    return _finish_echo(spec)


@pytest.mark.parametrize("window", [1, 4])
def test_a_small_window_or_lost_files_do_not_hang_the_job(window):
    """Tiles between their batch and their finish are in flight already: a window they fill must not stop their
    finishes (a window of 4 hung). A tile whose files were lost before its finish is prepared and batched again;
    one that keeps losing them fails by name."""
    from distributed import Client, LocalCluster

    from tiled_gridpull.pipeline.job import LOST_TRIES, Batching, add_card_worker, run_tiles

    _LOST.clear()
    specs = _grid_specs(3, 2, 1)
    with LocalCluster(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=":0") as cluster:
        add_card_worker(cluster)
        with Client(cluster) as client:
            client.wait_for_workers(2, timeout=30)
            batching = Batching(4, _prepare_echo, lambda s: (), _batch_echo, lambda group: (), _finish_loses,
                                lambda s: ())
            seen = _run_in_thread(lambda: list(run_tiles(client, specs, None, None, _mesh_echo, lambda s: (),
                                                         window=window, batching=batching)))
    solves = {i: r for k, i, r in seen if k == "solve"}
    assert set(solves) == {s.index for s in specs} and len([k for k, _, _ in seen if k == "mesh"]) == len(specs)
    assert solves[(1, 0, 0)]["status"] == "solved" and _LOST["tile_1_0_0"] == 1  # lost once, batched again
    assert solves[(0, 0, 0)]["status"] == "failed" and _LOST["tile_0_0_0"] == LOST_TRIES
    assert f"lost {LOST_TRIES} times" in solves[(0, 0, 0)]["reason"]


def test_batches_are_sized_to_the_card_with_the_least_free_memory(tmp_path, monkeypatch):
    """Each card says how much memory it has free; any card may take any batch, so the budget is the least."""
    from distributed import Client, LocalCluster, get_worker

    from tiled_gridpull import device
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.jobdir import JobPaths
    from tiled_gridpull.pipeline.job import CARD_SHARE, DaskExecutor, JobOptions, add_card_worker
    from tiled_gridpull.tiling import TilingConfig

    free = {"card0": 40e9, "card1": 10e9}
    monkeypatch.setattr(device, "card_memory", lambda: (free[get_worker().name], 80e9))  # in-process workers
    with LocalCluster(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=":0") as cluster:
        for name in free:
            add_card_worker(cluster, name=name)
        with Client(cluster) as client:
            client.wait_for_workers(3, timeout=30)
            ex = DaskExecutor(JobOptions(progress=False), device="cuda")
            batching = ex._batching(client, TilingConfig(voxel_size=0.1), SolverConfig(device="cuda"),
                                    JobPaths(tmp_path), (0.0, 0.0, 0.0))
            assert ex._batching(client, TilingConfig(voxel_size=0.1), SolverConfig(device="cpu"), JobPaths(tmp_path),
                                (0.0, 0.0, 0.0)) is None  # a CPU job never batches
    assert batching.budget == CARD_SHARE * 10e9 and batching.size == JobOptions().batch_tiles
    assert ex.engine["cards"] == 2 and ex.engine["card_memory"]["free_bytes"] == 10e9
