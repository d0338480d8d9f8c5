"""The Dask executor of a tiled job (:mod:`tiled_gridpull.tiled_job`): tiles solved and meshed as tasks on a
cluster. This is the one module that imports ``distributed``.

* Tasks carry small :class:`~tiled_gridpull.tile_plan.TileSpec` descriptions (paths, bounds) and settings, never
  arrays; each writes its result to the job directory and returns a small summary.
* A tile's mesh task depends on the solve tasks of itself and its 26 neighbours (the blend needs their fields).
* By default a :class:`distributed.LocalCluster` sized to the machine runs the job: one thread per worker
  process, and numba/OpenMP threads per worker = cores / workers (numba's default threading layer aborts when
  parallel kernels run from several threads of one process). ``scheduler=ADDRESS`` runs the very same graph
  on an existing cluster.
* On a card (``device`` cuda, or auto with one), the local cluster gets one more worker holding it (resource
  ``GPU=1``): tiles are prepared on the other workers and solved in batches there (:class:`Batching`).
* Failed tasks are retried (a worker that dies costs only its tiles in flight); a tile that fails for a data
  reason is reported by name and the rest of the mesh is still produced.
* Resume (every result keyed on what produced it), fail-fast, the memory budget, the report and the mesh's
  metadata are the driver's (:func:`tiled_gridpull.tiled_job.run_tiled_job`), the same whichever executor runs
  the tiles.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import ClusterError, ConfigError
from tiled_gridpull.jobdir import JobPaths, neighbors_of
from tiled_gridpull.mesh import Mesh
from tiled_gridpull.tile_plan import TileSpec
from tiled_gridpull.tile_solve import tile_summary
from tiled_gridpull.tiled_job import (SerialExecutor, TileEvent, batch_arguments, finish_step, mesh_step, prepare_step,
                                      run_tiled_job, solve_batch_step, solve_step, task_arguments)
from tiled_gridpull.tiling import TilingConfig

log = logging.getLogger("tiled_gridpull")

__all__ = ["JobOptions", "DaskExecutor", "Batching", "run_job", "run_tiles", "make_client", "compile_on_workers"]

#: Tasks in flight at once: enough to keep any cluster busy (a task is a whole tile, seconds to minutes of work)
#: and to cover a slab of tiles, so mesh tasks follow their solves closely.
DEFAULT_WINDOW = 4000

#: Tiles a card solves at once by default: launches are shared while each step stays a fraction of a second
#: (a 3.2M-slot tile's step takes 0.29 ms alone; 64 of them, 206M slots, 18 ms: issue 37's H200 prototype).
DEFAULT_BATCH_TILES = 16

#: Seconds without any worker (while tasks wait) before a job stops instead of waiting for ever.
NO_WORKER_TIMEOUT_S = 120.0


@dataclass(frozen=True)
class JobOptions:
    """How a job runs (not what it computes): ``fail_fast``, ``float32``, ``progress``, ``tile_meshes`` and
    ``max_memory`` go to the driver (:func:`tiled_gridpull.tiled_job.run_tiled_job`), the rest to the
    :class:`DaskExecutor`.

    Attributes
    ----------
    workers : int, optional
        Worker processes of the local cluster (default: one per core, capped by the number of tiles); 0: no
        cluster, the tiles one after the other in this process, each kernel on every core
        (:class:`~tiled_gridpull.tiled_job.SerialExecutor`): a job of a few tiles skips the cluster's start, but a
        tile that runs out of memory or crashes stops the whole job, and ``retries`` do not apply.
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:8786``); overrides a ``workers`` count (0, which asks
        for no cluster at all, is refused beside it).
    retries : int
        Times a task is retried after a failure (e.g. its worker died).
    fail_fast : bool
        Stop at the first tile that fails for a data reason instead of producing the rest of the mesh.
    float32 : bool
        Write float32 vertices with a recorded offset.
    progress : bool
        Show a progress bar with an ETA.
    tile_meshes : str, optional
        Directory to also write one PLY per tile into.
    max_memory : int, optional
        Bytes one worker may use for one tile; the job is refused up front if a tile's estimate exceeds it.
    window : int
        Most tasks in flight at once (:func:`run_tiles`); tiles are submitted as a sliding window in tile order.
    tiles3d : str, optional
        Directory to also write the mesh into as an OGC 3D Tiles 1.1 tileset.
    tiles3d_crs : str, optional
        The tileset's CRS when the inputs declare none (or instead of theirs), e.g. ``EPSG:32632``.
    batch_tiles : int
        On a card, most tiles solved together (one launch per step for all of them, on the card's worker;
        CPU workers read and set up the next batch meanwhile). 1 solves every tile in a task of its own on any
        worker, as on CPUs. Unused on CPUs.
    no_worker_timeout : float
        Seconds the job waits without any worker (an external scheduler none joined, or a cluster whose workers
        were all killed) before it stops with a clear message.
    """

    workers: int | None = None
    scheduler: str | None = None
    tile_meshes: str | None = None
    retries: int = 2
    fail_fast: bool = False
    float32: bool = False
    progress: bool = True
    extra: dict = field(default_factory=dict)
    max_memory: int | None = None
    window: int = DEFAULT_WINDOW
    no_worker_timeout: float = NO_WORKER_TIMEOUT_S
    tiles3d: str | None = None
    tiles3d_crs: str | None = None
    batch_tiles: int = DEFAULT_BATCH_TILES


def _threads_for(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(1, workers))


_SCHEMES = ("tcp", "tls")


#: Seconds a scheduler address has to answer Dask's handshake and an identity request (a busy scheduler answers
#: in milliseconds; something else listening there never does, and Dask's client would then wait for ever)
HANDSHAKE_TIMEOUT_S = 10.0


def check_scheduler_address(address: str, connect_timeout: float = 5.0,
                            handshake_timeout: float = HANDSHAKE_TIMEOUT_S) -> str:
    """A Dask scheduler address checked before a client waits on it: ``[tcp|tls://]host:port`` with a port in
    1-65535, something listening there, and that something a Dask scheduler (:func:`_scheduler_handshake`).
    Returns the address with its scheme.

    Raises
    ------
    ConfigError
        Malformed, nothing accepts a connection within ``connect_timeout`` seconds (Dask's client would wait
        its whole timeout, then fail as an internal error), or what accepts it does not answer as a Dask
        scheduler within ``handshake_timeout`` seconds (a silent listener or a web server left Dask's client
        waiting for ever, after the partition was written).
    """
    import re
    import socket

    m = re.fullmatch(r"(?:([A-Za-z][A-Za-z0-9+.-]*)://)?(\[[0-9A-Fa-f:]+\]|[^:/\s\[\]]+):(\d{1,5})/?", address.strip())
    if m is None:
        raise ConfigError(f"--scheduler {address!r}: expected tcp://HOST:PORT")
    scheme, host, port = (m.group(1) or "tcp").lower(), m.group(2), int(m.group(3))
    if scheme not in _SCHEMES:
        raise ConfigError(f"--scheduler {address!r}: scheme {scheme!r} is not supported (use tcp:// or tls://)")
    if not 1 <= port <= 65535:
        raise ConfigError(f"--scheduler {address!r}: port {port} is not in 1-65535")
    try:
        with socket.create_connection((host.strip("[]"), port), timeout=connect_timeout):
            pass
    except OSError as exc:
        why = "nothing listens there" if isinstance(exc, ConnectionRefusedError) else (
            "timed out" if isinstance(exc, (socket.timeout, TimeoutError)) else exc.__class__.__name__)
        raise ConfigError(f"--scheduler {address}: cannot reach a Dask scheduler ({why})") from None
    full = f"{scheme}://{host}:{port}"
    why = _scheduler_handshake(full, handshake_timeout)
    if why is not None:
        raise ConfigError(f"--scheduler {address}: not a Dask scheduler ({why})")
    return full


def _scheduler_handshake(address: str, timeout: float) -> str | None:
    """None when a Dask scheduler at ``address`` completes the comm handshake and answers an identity request
    within ``timeout`` seconds; else why not, in a few words.

    Run on a thread of its own with a hard deadline: what a foreign server sends can make distributed's reader
    wait for more bytes for ever, or size a buffer from an HTTP status line (a MemoryError of exabytes).
    """
    import asyncio

    from distributed.comm import connect
    from distributed.security import Security

    async def probe():
        comm = await connect(address, timeout=timeout, **Security().get_connection_args("client"))
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    box: dict = {}

    def run() -> None:
        try:
            box["reply"] = asyncio.run(asyncio.wait_for(probe(), timeout))
        except BaseException as exc:  # noqa: BLE001 - whatever a foreign server provokes is reported, not raised
            box["error"] = exc

    thread = threading.Thread(target=run, name="scheduler-handshake", daemon=True)
    thread.start()
    thread.join(timeout + 2.0)
    if thread.is_alive() or isinstance(box.get("error"), (TimeoutError, asyncio.TimeoutError)):
        return f"no Dask handshake within {timeout:g} s"
    if "error" in box:
        exc = box["error"]
        if isinstance(exc, OSError) and "timed out" in str(exc).lower():
            return f"no Dask handshake within {timeout:g} s"
        return f"its answer is not Dask's: {exc.__class__.__name__}"
    reply = box.get("reply")
    if not (isinstance(reply, dict) and reply.get("type") == "Scheduler"):
        kind = reply.get("type") if isinstance(reply, dict) else None
        return f"it answers as a Dask {kind}" if kind else "its answer is not a Dask scheduler's identity"
    return None


def make_client(options: JobOptions, n_tiles: int, card: bool = False):
    """A Dask client: connected to ``options.scheduler``, or to a new LocalCluster sized to the machine; with
    ``card``, the LocalCluster has one more worker, which holds the card (worker resource ``GPU=1``) and solves
    the batches of tiles (:class:`Batching`)."""
    from distributed import Client, LocalCluster

    # The scheduler of a LocalCluster lives in this process and its workers write to our stderr: their
    # messages ("Couldn't gather keys", "marked as failed because 4 workers died", worker tracebacks) are about
    # tiles this driver reports itself, one line each; -vv shows them.
    quiet = logging.ERROR if log.isEnabledFor(logging.DEBUG) else logging.CRITICAL
    _set_dask_log_level(quiet)
    if options.scheduler:
        address = check_scheduler_address(options.scheduler)
        try:
            return Client(address, timeout="15s"), None
        except (OSError, TimeoutError) as exc:
            raise ConfigError(f"--scheduler {options.scheduler}: no Dask scheduler answered "
                              f"({exc.__class__.__name__})") from None
    cores = os.cpu_count() or 1
    workers = options.workers or max(1, min(cores, n_tiles))
    threads = _threads_for(workers)
    # Not NUMBA_NUM_THREADS: a worker re-imports the driver's main module, hence numba, before this env is
    # applied, so numba's pool would be sized from the old value while its first compilation re-reads the new
    # one and refuses ("Cannot set NUMBA_NUM_THREADS ..."; a cold cache broke `make demo`). The worker caps
    # its threads with numba.set_num_threads(TILED_GRIDPULL_THREADS) instead (_configure_worker_threads).
    env = {"OMP_NUM_THREADS": str(threads), "OMP_WAIT_POLICY": "PASSIVE", "TILED_GRIDPULL_THREADS": str(threads)}
    # One task per worker at a time (Dask's default saturation 1.1 hands a one-thread worker two): a worker
    # killed by one tile's solve then takes no queued bystander down with it, which Dask would count as a death
    # of that tile too and, after four, report it as failed though it never ran.
    import dask

    with dask.config.set({"distributed.scheduler.worker-saturation": 1.0}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                               silence_logs=quiet, env=env)
        if card:
            add_card_worker(cluster)
    client = Client(cluster)
    if card:
        try:
            client.wait_for_workers(workers + 1, timeout=60)
        except TimeoutError:
            client.close()
            cluster.close()
            raise ClusterError("the local cluster's worker holding the card did not start within 60 s") from None
    return client, cluster


def add_card_worker(cluster, name: str = "card") -> None:
    """Add to a LocalCluster a worker like its others but for the card it holds (worker resource ``GPU=1``), so
    that the batches of solves go to it and to it alone; the others prepare and mesh tiles."""
    _, spec = next(iter(cluster.new_worker_spec().items()))
    cluster.worker_spec[name] = {**spec, "options": {**spec["options"], "resources": dict(GPU_RESOURCE)}}
    cluster.scale(len(cluster.worker_spec))


def _set_dask_log_level(level: int) -> None:
    """``level`` for distributed's loggers in this process: its import configures several of them
    (``distributed.client``, ``distributed.scheduler``, ...) with levels of their own, so the parent's is not
    enough."""
    names = [n for n in logging.root.manager.loggerDict if n == "distributed" or n.startswith("distributed.")]
    # and tornado's, whose loop runs distributed's coroutines: one that dies with its connection (a result
    # fetch cut by the client's close) is logged there as "Exception in callback ..." with a traceback, which
    # reached our stderr handler (distributed's own defaults for them are critical and error)
    for name in ["distributed", *names, "tornado", "tornado.application"]:
        logging.getLogger(name).setLevel(level)


def _configure_worker_threads() -> None:
    """Inside a task: keep numba's kernels safe and sized for this worker."""
    import numba

    try:
        from distributed import get_worker

        nthreads = get_worker().state.nthreads
    except (ImportError, ValueError, AttributeError):
        nthreads = 1
    if nthreads > 1 and numba.config.THREADING_LAYER == "default":
        # several task threads per process: only a thread-safe layer may run parallel kernels
        numba.config.THREADING_LAYER = "threadsafe"
    want = int(os.environ.get("TILED_GRIDPULL_THREADS", "0") or 0)
    if want > 0:
        numba.set_num_threads(min(want, numba.config.NUMBA_NUM_THREADS))


def compile_task(names: list[str]) -> dict[str, float]:
    """Dask task: compile a share of the kernels (or load them from numba's cache); seconds each took."""
    from tiled_gridpull.kernels.warmup import compile_kernels

    _configure_worker_threads()  # as a tile would, before its first compilation
    return compile_kernels(names)


def compile_on_workers(client, stop: threading.Event | None = None,
                       no_worker_timeout: float = NO_WORKER_TIMEOUT_S, kernels: list[str] | None = None) -> list[str]:
    """Compile the kernels that numba's cache lacks, before any tile, each on one worker: shares of about equal
    compile time (:func:`tiled_gridpull.kernels.warmup.split`), one per worker, said on screen
    (:func:`tiled_gridpull.tiled_job.compile_ahead`). Returns the kernels compiled.

    On a cold cache every worker compiled every kernel at its first tile, all at once, each compiling alone the
    kernels the others were compiling too; a worker now loads from the cache what another compiled. What the
    workers' caches lack is asked of the workers themselves (an external cluster's may not be this machine's).
    A warm-up that fails is only logged: each tile then compiles what it needs at its first call, as before.
    ``kernels``: the names of :data:`~tiled_gridpull.kernels.warmup.KERNELS` to consider (default all).
    """
    from distributed import wait

    from tiled_gridpull.kernels.warmup import cold_kernels, split
    from tiled_gridpull.tiled_job import compile_ahead

    try:
        client.wait_for_workers(1, timeout=no_worker_timeout or None)
        seen = client.run(cold_kernels, kernels)
    except Exception as exc:  # noqa: BLE001 - the tiles compile at first use instead
        log.debug("kernel warm-up skipped: %s", exc)
        return []
    if not seen or any(v is None for v in seen.values()):
        return []
    workers = sorted(seen)
    cold = sorted({name for names in seen.values() for name in names})

    def compile_shares(names: list[str]) -> None:
        # a share goes elsewhere if its worker dies; a cluster left without workers stops the job as it would
        futures = [client.submit(compile_task, share, key=f"compile-kernels-{i}", workers=[w],
                                 allow_other_workers=True, pure=False)
                   for i, (w, share) in enumerate(zip(workers, split(names, len(workers))))]
        watch = _WorkerWatch(client, no_worker_timeout)
        while True:
            if stop is not None and stop.is_set():
                raise KeyboardInterrupt
            watch.check()
            try:
                wait(futures, timeout=0.2)
                break
            except TimeoutError:
                continue
        for fut in futures:
            if fut.status == "error":
                log.debug("kernel warm-up on a worker failed: %s", fut.exception())
            fut.release()

    return compile_ahead(compile_shares, len(workers), cold)


def solve_task(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str, centre,
               summary_path: str | None = None) -> dict:
    """Dask task: solve one tile, or reuse its recorded result (:func:`tiled_gridpull.tiled_job.solve_step`)."""
    _configure_worker_threads()
    out = solve_step(spec, tiling, solver, field_path, centre, summary_path,
                     before_solve=lambda: _test_hooks(spec.name))
    if not out.get("reused"):
        out["worker"] = _worker_address()
    return out


def prepare_task(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str, centre,
                 summary_path: str, prepared_path: str, solved_path: str) -> dict:
    """Dask task (any worker): a tile read and set up for its batch on the card, or its recorded result
    (:func:`tiled_gridpull.tiled_job.prepare_step`)."""
    _configure_worker_threads()
    out = prepare_step(spec, tiling, solver, field_path, centre, summary_path, prepared_path, solved_path)
    if out.get("status") != "prepared" and not out.get("reused"):
        out["worker"] = _worker_address()
    return out


def batch_solve_task(specs: list[TileSpec], tiling: TilingConfig, solver: SolverConfig, field_paths: list[str],
                     centre, summary_paths: list[str], prepared_paths: list[str],
                     solved_paths: list[str]) -> list[dict]:
    """Dask task (the card's worker): prepared tiles solved as one batch, each left for its finish
    (:func:`tiled_gridpull.tiled_job.solve_batch_step`)."""
    _configure_worker_threads()
    for spec in specs:
        _test_hooks(spec.name)
    return solve_batch_step(specs, tiling, solver, field_paths, centre, summary_paths, prepared_paths, solved_paths,
                            note={"worker": _worker_address()})


def finish_task(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str, centre,
                summary_path: str, prepared_path: str, solved_path: str) -> dict:
    """Dask task (any worker, off the card's): a batch-solved tile oriented, bridged and written
    (:func:`tiled_gridpull.tiled_job.finish_step`)."""
    _configure_worker_threads()
    out = finish_step(spec, tiling, solver, field_path, centre, summary_path, prepared_path, solved_path)
    out["finish_worker"] = _worker_address()
    return out


#: Share of the card's free memory a batch may take by its tiles' estimates (:func:`tiled_gridpull.memory.card_bytes`):
#: the rest holds the nearest-point grids, numba's context and kernels, and what the estimates miss.
CARD_SHARE = 0.7


def card_memory_task() -> tuple[float, float]:
    """Dask task (the card's worker): its card's free and total memory in bytes
    (:func:`tiled_gridpull.device.card_memory`)."""
    from tiled_gridpull.device import card_memory

    return card_memory()


def _test_hooks(tile: str) -> None:
    """Test hooks, unset in normal use. ``TILED_GRIDPULL_TEST_CRASH=TILE``: every attempt at solving that tile
    kills its worker process (a tile that keeps running its worker out of memory).
    ``TILED_GRIDPULL_TEST_HOLD=DIR:SECONDS``: the first attempt at solving each tile writes ``DIR/<tile>.<pid>``
    and sleeps, so a test can kill the worker process mid-task."""
    if os.environ.get("TILED_GRIDPULL_TEST_CRASH") == tile:
        os._exit(137)
    spec = os.environ.get("TILED_GRIDPULL_TEST_HOLD")
    if not spec:
        return
    where, _, seconds = spec.rpartition(":")
    marks = Path(where)
    if any(marks.glob(f"{tile}.*")):
        return  # a retry: do not hold again
    (marks / f"{tile}.{os.getpid()}").write_text(_worker_address())
    time.sleep(float(seconds))


def _worker_address() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return "local"


def mesh_task(spec: TileSpec, own: dict, neighbor_specs: list, neighbor_summaries: list, tiling: TilingConfig,
              key_ref, field_paths: dict, piece_path: str, summary_path: str | None = None) -> dict:
    """Dask task: blend with the solved neighbours and mesh the tile's core, or reuse its recorded piece
    (:func:`tiled_gridpull.tiled_job.mesh_step`)."""
    if own.get("status") == "solved":
        _configure_worker_threads()
    return mesh_step(spec, own, neighbor_specs, neighbor_summaries, tiling, key_ref, field_paths, piece_path,
                     summary_path)


def run_job(inputs: list[str], output: str | Path, tiling: TilingConfig, solver: SolverConfig, work_dir: str | Path,
            options: JobOptions = JobOptions(), *, frames=None, trajectory: str | Path | None = None) -> Mesh:
    """Tiled reconstruction on Dask (:func:`tiled_gridpull.tiled_job.run_tiled_job` with a :class:`DaskExecutor`),
    or in this process with ``options.workers`` 0; writes ``output`` and its sidecar, returns the welded mesh.

    Raises
    ------
    ConfigError
        ``options.workers`` 0 (this process) together with ``options.scheduler`` (a cluster).
    """
    if options.workers == 0 and options.scheduler:
        raise ConfigError("workers 0 runs the tiles in this process and scheduler on a Dask cluster: give one")
    # workers 0: no cluster to start (its processes, imports and kernel loads: about 2.5 CPU-s of a 2-core job)
    executor = SerialExecutor() if options.workers == 0 else DaskExecutor(options, solver.device)
    return run_tiled_job(inputs, output, tiling, solver, work_dir, executor, frames=frames,
                         trajectory=trajectory,
                         float32=options.float32, tile_meshes=options.tile_meshes, fail_fast=options.fail_fast,
                         max_memory=options.max_memory, progress=options.progress, tiles3d=options.tiles3d,
                         tiles3d_crs=options.tiles3d_crs)


class DaskExecutor:
    """Runs a job's tiles as tasks on a Dask cluster (:func:`run_tiles`): a new LocalCluster sized to the machine,
    or the cluster at ``options.scheduler``; the cluster is closed when the run ends.

    Parameters
    ----------
    options : JobOptions
        ``workers``, ``scheduler``, ``retries``, ``window`` and ``no_worker_timeout`` are read here.
    """

    def __init__(self, options: JobOptions = JobOptions(), device: str = "cpu"):
        self.options = options
        self.device = device
        self.engine = {"scheduler": options.scheduler or "LocalCluster", "workers": options.workers}
        self._client = self._cluster = None

    def check(self) -> None:
        if self.options.scheduler:
            check_scheduler_address(self.options.scheduler)

    def _connect(self, n_tasks: int, root) -> Any:
        """The job's client, started on first use (the indexed inputs' reads or the tiles) and kept until
        :meth:`close`."""
        if self._client is None:
            card = False
            if self.options.batch_tiles > 1 and not self.options.scheduler and self.device != "cpu":
                from tiled_gridpull.device import resolve

                card = resolve(self.device) == "cuda"  # the CLI refused ``cuda`` without a card already
            self._client, self._cluster = make_client(self.options, n_tasks, card=card)
            if self._client.dashboard_link:
                log.info("Dask dashboard: %s", self._client.dashboard_link)
            if self.options.scheduler:
                check_workers_see(self._client, root, self.options.no_worker_timeout)
        return self._client

    def warm_up(self, n_tasks: int, root) -> None:
        """Start the cluster (unless :meth:`map` did) and compile the kernels numba's cache lacks before the
        tiles, a share per worker (:func:`compile_on_workers`)."""
        with _deferred_interrupt() as interrupted:
            compile_on_workers(self._connect(n_tasks, root), interrupted, self.options.no_worker_timeout)

    def map(self, fn: Callable, args: list[tuple], root) -> list:
        """``fn(*a)`` for every ``a`` in ``args`` as tasks on the cluster (the partition's tasks: segments of
        plain inputs, tiles of indexed ones); their results in order.

        Tasks go in as a sliding window of twice the cluster's threads (at most ``options.window``), which
        keeps every thread busy without putting a survey's many thousand tasks on the scheduler at once. A
        task's error is raised here, as raised in the task, once the tasks already running have returned:
        Dask cannot stop a running task, and the caller removes the directory they write into, which a task
        still running on an external cluster would fill again. Tasks not yet submitted never run.
        """
        if not args:
            return []
        from distributed import as_completed

        # sized for the tiles that follow on the same cluster, not for this first batch of tasks
        client = self._connect(os.cpu_count() or 1, root)
        threads = sum(client.nthreads().values()) or 1
        window = max(1, min(self.options.window, 2 * threads))
        results: list = [None] * len(args)
        position: dict[str, int] = {}
        # without with_results: a result fetched inside as_completed that fails to arrive (its worker died)
        # would keep the future out of the queue for ever; here each is asked for as it comes
        pending = as_completed()
        watch = _WorkerWatch(client, self.options.no_worker_timeout)
        submitted, failure = 0, None

        def submit(k: int) -> None:
            nonlocal submitted
            for i in range(submitted, min(len(args), submitted + k)):
                fut = client.submit(fn, *args[i], pure=False, retries=self.options.retries)
                position[fut.key] = i
                pending.add(fut)
            submitted = min(len(args), submitted + k)

        submit(window)
        while not pending.is_empty():
            watch.wait_for(pending)
            for fut in pending.next_batch(block=False):
                i = position.pop(fut.key)
                # the outcome is read before the future is released: release cancels its state, after which
                # its status reads "cancelled" whatever the task did
                try:
                    results[i] = fut.result()
                except BaseException as exc:  # the task's error, or cancelled (e.g. the cluster went away)
                    if failure is None:
                        failure = exc
                finally:
                    fut.release()
                if failure is None:
                    submit(1)
        if failure is not None:
            raise self._lost_cluster(failure) or failure
        return results

    def _lost_cluster(self, exc: BaseException) -> ClusterError | None:
        """The error to raise instead of ``exc`` when ``exc`` says the cluster went away under the job (its tasks
        cancelled because the client lost the scheduler, or the connection closed), else None: a task's own
        error is the task's to report."""
        import concurrent.futures

        from distributed.comm.core import CommClosedError

        client = self._client
        gone = client is not None and getattr(client, "status", "running") not in ("running", "connecting")
        if isinstance(exc, (concurrent.futures.CancelledError, CommClosedError)) or (isinstance(exc, OSError)
                                                                                     and gone):
            where = f"the Dask scheduler {self.options.scheduler}" if self.options.scheduler else "the Dask cluster"
            why = getattr(exc, "reason", None) or exc.__class__.__name__
            # one line: a cancelled future's message carries a second line of advice from distributed
            return ClusterError(f"lost {where} mid-job ({why}): the job stops; rerun to resume from the tiles "
                                "already done")
        return None

    def run(self, specs: list[TileSpec], tiling: TilingConfig, solver: SolverConfig, paths: JobPaths, centre,
            key_ref) -> Iterator[TileEvent]:
        """Start the cluster (unless :meth:`map` did), submit every tile's solve and mesh task, yield their
        summaries, close the cluster."""
        options = self.options
        with _deferred_interrupt() as interrupted:
            client = self._connect(len(specs), paths.root)
            try:
                solve_args, mesh_args = task_arguments(specs, tiling, solver, paths, centre, key_ref)
                try:
                    batching = self._batching(client, tiling, solver, paths, centre)
                    yield from run_tiles(client, specs, solve_task, solve_args, mesh_task, mesh_args,
                                         options.retries, window=options.window, stop=interrupted,
                                         no_worker_timeout=options.no_worker_timeout, batching=batching)
                except Exception as exc:
                    lost = self._lost_cluster(exc)
                    if lost is None:
                        raise
                    raise lost from None
            finally:
                self.close()
                _sweep_prepared(paths)  # once no task of this run's local cluster can write there any more

    def _batching(self, client, tiling: TilingConfig, solver: SolverConfig, paths: JobPaths, centre):
        """How the tiles are solved in batches on the cluster's cards, or None (no card, a CPU job, or
        ``batch_tiles`` 1). Each card's memory is read once on its worker; the batches are sized to the card with
        the least free (any card may take any batch), which :attr:`engine` records."""
        options = self.options
        holders = [a for a, w in _workers(client).items() if _holds(w, GPU_RESOURCE)]
        if options.batch_tiles <= 1 or solver.device == "cpu" or not holders:
            return None
        wait = max(options.no_worker_timeout, 30.0)
        futs = [client.submit(card_memory_task, workers=[a], resources=dict(GPU_RESOURCE), pure=False)
                for a in holders]
        try:
            free, total = min(f.result(timeout=wait if options.no_worker_timeout > 0 else None) for f in futs)
        except TimeoutError:
            raise ClusterError(f"a worker holding a card did not say how much memory the card has free within "
                               f"{wait:g} s: the job stops; rerun to resume") from None
        tile_args, batch_args = batch_arguments(tiling, solver, paths, centre)
        self.engine["batch_tiles"] = options.batch_tiles
        # what the card had when the job started, and what a batch may take of it (None: no limit, the simulator's)
        self.engine["card_memory"] = {k: (v if math.isfinite(v) else None) for k, v in
                                      {"free_bytes": free, "total_bytes": total,
                                       "batch_budget_bytes": CARD_SHARE * free}.items()}
        self.engine["cards"] = len(holders)
        return Batching(options.batch_tiles, prepare_task, tile_args, batch_solve_task, batch_args, finish_task,
                        tile_args, budget=CARD_SHARE * free)

    def close(self) -> None:
        """Close the client and the LocalCluster this executor started (if any)."""
        client, cluster, self._client, self._cluster = self._client, self._cluster, None, None
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()


def _sweep_prepared(paths: JobPaths) -> None:
    """Remove the prepared tiles a batched run left (interrupted, or a tile whose batch failed): each is a copy
    of a tile's points and normals, and a rerun prepares again what it needs."""
    folder = paths.prepared_dir()
    if folder.is_symlink() or not folder.is_dir():
        return
    # and the temporary files of writes a killed worker cut short (io.atomic names them .<name>.<random>.tmp)
    for f in [*folder.glob("*.npz"), *folder.glob(".*.npz.*.tmp")]:
        with contextlib.suppress(OSError):
            f.unlink()


@contextlib.contextmanager
def _deferred_interrupt():
    """Turn Ctrl-C into a flag that the task loop checks, instead of an exception raised wherever it lands.

    A KeyboardInterrupt raised inside one of distributed's blocking calls (a result fetch, ``client.close``)
    leaves its event loop half-way through a callback, which then logs a traceback from distributed's
    internals; checked between tasks, the interrupt unwinds through our own code and closes the cluster
    cleanly. A second Ctrl-C interrupts at once. Off the main thread (signals cannot be handled there) the
    event never fires and Ctrl-C behaves as usual.
    """
    interrupted = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield interrupted
        return

    def handler(signum, frame):
        if interrupted.is_set():
            raise KeyboardInterrupt
        interrupted.set()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield interrupted
    finally:
        signal.signal(signal.SIGINT, previous)
    if interrupted.is_set():
        raise KeyboardInterrupt


#: The worker resource a batch of solves needs: one card (a worker started with ``--resources GPU=1``).
GPU_RESOURCE = {"GPU": 1}


@dataclass(frozen=True)
class Batching:
    """Solves in batches on a card (:func:`run_tiles`): each tile's ``prepare_fn(spec, *prepare_args(spec))``
    on any worker reads and sets it up (its summary's status ``"prepared"`` when it awaits its solve, else its
    final solve summary), then ``batch_fn(specs, *batch_args(specs))`` solves up to ``size`` prepared tiles at
    once on a worker that holds ``resources`` (one per card: ``dask worker --resources GPU=1``) and returns their
    summaries (status ``"unfinished"`` for each solved tile), then each solved tile's
    ``finish_fn(spec, *finish_args(spec))`` on any worker orients, bridges and writes it (its final summary). A
    batch takes at most ``budget`` bytes of the card's memory by its tiles' estimates (a tile that needs more goes
    alone)."""

    size: int
    prepare_fn: Callable
    prepare_args: Callable
    batch_fn: Callable
    batch_args: Callable
    finish_fn: Callable
    finish_args: Callable
    resources: dict = field(default_factory=lambda: dict(GPU_RESOURCE))
    budget: float = math.inf  # card bytes a batch may take (the prepared tiles' ``card_bytes`` summed)

    def __post_init__(self):
        if self.size < 1:
            raise ValueError(f"a batch holds at least 1 tile, got {self.size}")


#: Times a tile's files may be lost between its batch and its finish before the tile is failed.
LOST_TRIES = 3

#: Tiles a batched job keeps prepared ahead of the card, in batches: the CPU workers read and set up the next
#: batches while the card solves one, without filling the job directory with every tile of a window.
BATCHES_AHEAD = 3


def run_tiles(client, specs: list[TileSpec], solve_fn, solve_args, mesh_fn, mesh_args, retries: int = 2,
              window: int = DEFAULT_WINDOW, stop: threading.Event | None = None,
              no_worker_timeout: float = NO_WORKER_TIMEOUT_S, batching: Batching | None = None):
    """Run the job's graph on ``client``, yielding ``(kind, tile index, summary)`` as tasks finish.

    The graph: one solve task per tile, then one mesh task per tile that needs the solve summaries of the tile
    and its (up to 26) neighbours. ``solve_fn(spec, *solve_args(spec))`` and ``mesh_fn(spec, own_summary,
    neighbour_specs, neighbour_summaries, *mesh_args(spec))``; tasks carry the small spec objects, never arrays.

    Solves are submitted as a sliding window of at most ``window`` unfinished tasks, in tile order from one
    window to the next and, within each window's worth of tiles, the costliest first (most occupied bricks, then
    most points): a short tile, not a long one, is what runs alone at the end (longest-processing-time-first
    scheduling; in the demo street the 250k-point tile had been started last). A tile's mesh task goes in as
    soon as the solves of the tile and its neighbours have come back, with their summaries as plain arguments.
    The scheduler, the workers and this process thus hold state for a window of tiles, not the whole job:
    submitting all 200,000 tasks of a 100,000-tile job at once overloaded the local scheduler until it dropped
    the client's connection. Plain summaries rather than solve futures as the mesh task's dependencies spare the
    scheduler 27 edges per mesh task and the workers fetching summaries from each other; with tasks submitted in
    batches (one graph update per round, not per task), a no-op graph of 5,000 tiles went from 4.4 to 3.4 ms per
    tile (BENCHMARKS.md).

    With ``batching`` (a job on a card) a tile's solve is two tasks: its preparation, then its part of a batch
    on the card's worker. Preparations and meshes go to the other workers, one per thread of theirs at a time
    (:class:`_CardQueue`), so that the card waits for none. One batch per card is out at a time, with up to
    ``batching.size`` of the tiles prepared so far whose estimates fit the card's memory and the card worker's:
    the first batches are small, later ones fill while the card works. Besides keeping each card's worker to one
    batch, this keeps a batch that kills its worker from taking batches queued behind it down too (Dask counts a
    death against every task the worker held); such a batch is split, each of its tiles tried alone, so only the
    tile at fault fails. At most :data:`BATCHES_AHEAD` batches' worth of tiles per card are between their
    preparation and the end of their batch (each holds a file in the job directory).

    Parameters
    ----------
    window : int
        Most tasks submitted and not yet returned; at least 1.
    stop : threading.Event, optional
        Checked between results (every 0.1 s while waiting): when set, raises KeyboardInterrupt.
    no_worker_timeout : float
        Seconds the cluster may have no worker while tasks wait before the job stops with
        :class:`~tiled_gridpull.errors.ClusterError` (0: wait for ever). Without it a cluster that lost every
        worker left the driver waiting for ever. Likewise batches with no worker holding their resources.
    batching : Batching, optional
        Solve in batches on a card (``solve_fn`` and ``solve_args`` then go unused).
    """
    from distributed import as_completed

    if window < 1:
        raise ValueError(f"window must be at least 1, got {window}")
    specs = sorted(specs, key=lambda s: s.index)
    by_index = {s.index: s for s in specs}
    position = {s.index: i for i, s in enumerate(specs)}
    neighbours = [neighbors_of(s, by_index) for s in specs]
    needs = [[i] + [position[nb.index] for nb in nbs] for i, nbs in enumerate(neighbours)]
    # solves a tile's mesh still waits for; mesh tasks still to be submitted that read a tile's solve summary
    # (the neighbour relation is symmetric, so both counts are the length of the tile's own list)
    waiting = [len(d) for d in needs]
    readers = [len(d) for d in needs]
    summaries: list = [None] * len(specs)
    ready: deque[int] = deque()  # tiles whose mesh task can be submitted
    kinds: dict[str, tuple[str, list[int]]] = {}
    pending = as_completed(with_results=True)  # results come with the futures, not one request each
    watch = _WorkerWatch(client, no_worker_timeout)
    n, next_solve, in_flight = len(specs), 0, 0  # in flight: tiles in their solve, and mesh tasks
    # tile order across windows keeps a window's meshes close to its solves; costliest first within one (both
    # sorts are stable: equal costs keep tile order)
    solve_order = sorted(range(n), key=lambda i: (specs[i].occupied_bricks, specs[i].n_points), reverse=True)
    solve_order.sort(key=lambda i: i // window)
    cards = _CardQueue(batching, client) if batching is not None else None
    if batching is not None:
        solve_fn, solve_args = batching.prepare_fn, batching.prepare_args

    def submit(kind: str, fn, rows: list[tuple], items: list[int], suffix: str = "") -> None:
        keys = [f"{kind}-{specs[i].name}{suffix}" for i in items]
        where = cards.placement() if cards is not None else {}
        if len(rows) == 1:
            futs = [client.submit(fn, *rows[0], key=keys[0], retries=retries, pure=False, **where)]
        else:
            futs = client.map(fn, *zip(*rows), key=keys, retries=retries, pure=False, **where)
        for i, fut in zip(items, futs):
            kinds[fut.key] = (kind, [i])
        pending.update(futs)
        if cards is not None:
            cards.cpu_sent(kind, len(items))

    def submit_batch(items: list[int]) -> None:
        group = [specs[i] for i in items]
        # a tile is in one batch at a time; "alone" marks the retry of a batch that killed its worker
        key = f"batch-{group[0].name}-{len(items)}" + ("-alone" if len(items) == 1 and items[0] in cards.split else "")
        fut = client.submit(batching.batch_fn, group, *batching.batch_args(group), key=key, retries=retries,
                            pure=False, resources=batching.resources)
        kinds[fut.key] = ("batch", items)
        pending.add(fut)
        cards.sent(items)

    def solved(i: int, result: dict) -> Iterator[TileEvent]:
        summaries[i] = result
        for j in needs[i]:
            waiting[j] -= 1
            if waiting[j] == 0:
                ready.append(j)
        yield "solve", specs[i].index, result

    try:
        while next_solve < n or ready or in_flight:
            room = window - in_flight
            if cards is not None:
                # finishes, then tiles whose files were lost, first and whatever the window: their tiles are in
                # flight already (bounded by the window, they hung a small one)
                cards.refresh()
                cpu = cards.cpu_room()
                if cpu > 0 and cards.to_finish:
                    take = [cards.to_finish.popleft() for _ in range(min(cpu, len(cards.to_finish)))]
                    submit("finish", batching.finish_fn, [(specs[i], *batching.finish_args(specs[i])) for i in take],
                           take)
                    cpu -= len(take)
                again = min(cpu, cards.prepare_room(), len(cards.redo))
                if again > 0:
                    take = [cards.redo.popleft() for _ in range(again)]
                    submit("solve", solve_fn, [(specs[i], *solve_args(specs[i])) for i in take], take,
                           suffix=f"-again{cards.lost[take[0]]}")
                    cpu -= len(take)
                room = min(room, cpu)
            if room > 0 and ready:  # meshes first: they finish tiles and let summaries go
                take = [ready.popleft() for _ in range(min(room, len(ready)))]
                submit("mesh", mesh_fn, [(specs[i], summaries[i], neighbours[i], [summaries[j] for j in needs[i][1:]],
                                          *mesh_args(specs[i])) for i in take], take)
                for i in take:
                    for j in needs[i]:
                        readers[j] -= 1
                        if readers[j] == 0:
                            summaries[j] = None
                room -= len(take)
                in_flight += len(take)
            if cards is not None:
                room = min(room, cards.prepare_room())
            if room > 0 and next_solve < n:
                take = solve_order[next_solve:min(n, next_solve + room)]
                submit("solve", solve_fn, [(specs[i], *solve_args(specs[i])) for i in take], take)
                next_solve += len(take)
                in_flight += len(take)
            for group in cards.groups() if cards is not None else ():
                submit_batch(group)
            watch.wait_for(pending, stop, needs=batching.resources if cards is not None and cards.out else None)
            for fut, result in pending.next_batch(block=False):
                kind, items = kinds.pop(fut.key)
                if cards is not None and kind != "batch":
                    cards.cpu_back(kind)
                if fut.status == "error":
                    if not _killed_worker(result[1]):
                        raise result[1].with_traceback(result[2])
                    if kind == "batch" and len(items) > 1:  # which tile killed it? each alone will tell
                        cards.killed(items)
                        continue
                    # the task took its worker down every time it ran (out of memory, a crash in native code):
                    # a failed tile, reported by name; the rest of the job goes on
                    what = {"batch": "solve", "solve": "preparation" if cards is not None else "solve"}.get(kind, kind)
                    result = [tile_summary(specs[i], status="failed", faces=0,
                                           reason=f"its {what} killed the worker process on every attempt (out of "
                                                  "memory?)") for i in items]
                    result = result if kind == "batch" else result[0]
                if isinstance(result, BaseException):  # cancelled (e.g. the cluster went away)
                    raise result
                if kind == "batch":
                    sizing = cards.done(items)
                    for i, res in zip(items, result, strict=True):
                        if res.get("status") == "unfinished":  # solved: its finish comes
                            cards.to_finish.append(i)
                            cards.sizing[i] = sizing
                            continue
                        in_flight -= 1
                        yield from solved(i, {**res, **sizing})
                    continue
                i = items[0]
                if kind == "finish":
                    if result.get("status") == "lost":
                        if cards.lose(i):
                            continue  # prepared and batched again
                        result = {**result, "status": "failed",
                                  "reason": f"its files between its batch and its finish were lost {LOST_TRIES} times "
                                            f"({result.get('reason')})"}
                    in_flight -= 1
                    # the estimates the tile's batch was sized by
                    yield from solved(i, {**result, **cards.sizing.pop(i, {})})
                    continue
                if kind == "solve" and cards is not None and result.get("status") == "prepared":
                    cards.stage(i, result)  # still in flight: its batch comes
                    continue
                in_flight -= 1
                if kind == "solve":
                    yield from solved(i, result)
                else:
                    yield kind, specs[i].index, result
            if stop is not None and stop.is_set():
                raise KeyboardInterrupt
    except BaseException:
        # stopping early (Ctrl-C, a task's error, the cluster lost): the caller closes the client next, so first
        # let the result fetches already under way end; cut by the close, they died on the event loop with a
        # logged traceback ("Exception in callback ... CommClosedError" after Ctrl-C, now and then)
        _settle_result_fetches(pending)
        raise


class _CardQueue:
    """The batching state of :func:`run_tiles`: the tiles between their preparation and the end of their batch,
    the batches out (one per card), and where the other tasks go.

    The preparations and meshes go to the workers without a card, at most one per thread of theirs at a time:
    a task restricted to some workers is no longer queued on the scheduler (Dask queues only unrestricted
    tasks), so without the cap they would pile up on the workers, and a task that kills its worker would take
    every one queued behind it down too (and, idle, the card's worker would steal them)."""

    def __init__(self, batching: Batching, client):
        self.batching, self.client = batching, client
        self.preparing = 0  # prepare tasks out
        self.cpu_out = 0  # prepare, finish and mesh tasks out
        self.staged: deque[int] = deque()  # prepared tiles awaiting a batch
        self.alone: deque[int] = deque()  # tiles of a batch that killed its worker, each to go in one of its own
        self.to_finish: deque[int] = deque()  # tiles solved in a batch, awaiting their finish task
        self.finishing = 0  # finish tasks out
        self.sizing: dict[int, dict] = {}  # what each solved tile's batch was sized by
        self.redo: deque[int] = deque()  # tiles whose files were lost before their finish: prepared again
        self.lost: dict[int, int] = {}  # times each tile's files were lost
        self.split: set[int] = set()
        self.out = 0  # batches out
        self.batched = 0  # tiles in them
        self.card: dict[int, float] = {}  # estimated card bytes of each prepared tile
        self.host: dict[int, float] = {}  # and host bytes
        self.cards, self.others, self.cpu_slots, self.host_budget = 1, None, 1, math.inf
        self.next_refresh = 0.0
        self.refresh()

    def refresh(self) -> None:
        """The cluster's workers as they are now (every 2 s): a restarted worker comes back at a new address."""
        now = time.monotonic()
        if now < self.next_refresh:
            return
        self.next_refresh = now + 2.0
        workers = _workers(self.client)
        holders = [w for w in workers.values() if _holds(w, self.batching.resources)]
        rest = {a: w for a, w in workers.items() if not _holds(w, self.batching.resources)}
        self.cards = max(1, len(holders))
        # loose: with no worker without a card left, the card's workers still take them
        self.others = sorted(rest) or None
        self.cpu_slots = max(1, sum(int(w.get("nthreads", 1)) for w in (rest or workers).values()))
        limits = [float(w.get("memory_limit") or 0) for w in holders]
        self.host_budget = CARD_SHARE * min(limits) if limits and min(limits) > 0 else math.inf

    def cpu_sent(self, kind: str, n: int) -> None:
        """``n`` tasks of ``kind`` ("solve": preparations, "finish", "mesh") went to the workers without a card."""
        self.cpu_out += n
        self.preparing += n if kind == "solve" else 0
        self.finishing += n if kind == "finish" else 0

    def cpu_back(self, kind: str) -> None:
        """One of them came back."""
        self.cpu_sent(kind, -1)

    def placement(self) -> dict:
        return {"workers": self.others, "allow_other_workers": True} if self.others else {}

    def cpu_room(self) -> int:
        return self.cpu_slots - self.cpu_out

    def prepare_room(self) -> int:
        """Preparations that may go out now: no more tiles between preparation and finish (each a file or two in
        the job directory) than :data:`BATCHES_AHEAD` batches per card."""
        ahead = BATCHES_AHEAD * self.batching.size * self.cards
        return min(self.cpu_room(), ahead - self.preparing - len(self.staged) - len(self.alone) - self.batched
                   - len(self.to_finish) - self.finishing - len(self.redo))

    def lose(self, i: int) -> bool:
        """Tile ``i``'s files were lost before its finish (a worker that died, a sweep): True when it is to be
        prepared and batched again, False once that happened :data:`LOST_TRIES` times."""
        self.sizing.pop(i, None)
        self.lost[i] = self.lost.get(i, 0) + 1
        if self.lost[i] >= LOST_TRIES:
            return False
        self.redo.append(i)
        return True

    def stage(self, i: int, result: dict) -> None:
        self.staged.append(i)
        self.card[i] = float(result.get("card_bytes", 0.0))
        self.host[i] = float(result.get("host_bytes", 0.0))

    def groups(self) -> Iterator[list[int]]:
        """The batches to send now: while a card has none out, the next tile alone (after a batch that killed
        its worker), or the tiles prepared so far while they fit ``size`` and the card and host budgets."""
        b = self.batching
        while self.out < self.cards and (self.alone or self.staged):
            if self.alone:
                yield [self.alone.popleft()]
                continue
            group = [self.staged.popleft()]
            card, host = self.card[group[0]], self.host[group[0]]
            while (self.staged and len(group) < b.size and card + self.card[self.staged[0]] <= b.budget
                   and host + self.host[self.staged[0]] <= self.host_budget):
                i = self.staged.popleft()
                card, host = card + self.card[i], host + self.host[i]
                group.append(i)
            yield group

    def sent(self, items: list[int]) -> None:
        self.out += 1
        self.batched += len(items)

    def killed(self, items: list[int]) -> None:
        self.out -= 1
        self.batched -= len(items)
        self.split.update(items)
        self.alone.extend(items)

    def done(self, items: list[int]) -> dict:
        """A batch came back: what it was sized by (for its tiles' summaries)."""
        self.out -= 1
        self.batched -= len(items)
        out = {}
        card, host = sum(self.card.pop(i, 0.0) for i in items), sum(self.host.pop(i, 0.0) for i in items)
        if card:
            out["batch_card_bytes"] = card
        if host:
            out["batch_host_bytes"] = host
        return out


def _settle_result_fetches(pending, timeout: float = 5.0) -> None:
    """Wait (at most ``timeout`` s) until no future of the ``as_completed(with_results=True)`` queue ``pending``
    has finished without its result having arrived: for each such future distributed's loop is fetching the
    result from the cluster, a request that must not be cut by closing the client. Unfinished futures need no
    wait: closing the client cancels them, and their trackers end without a request."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with pending.lock:
            fetching = any(f.done() for f in pending.futures)
        if not fetching:
            return
        with pending.thread_condition:  # notified as each result arrives
            pending.thread_condition.wait(timeout=0.05)


def check_workers_see(client, root: Path, timeout: float) -> None:
    """On an external cluster: wait (at most ``timeout`` s) for a worker, then check that every worker sees the
    job directory; tiles are exchanged as files there, so the cluster needs a filesystem shared with this
    machine at the same path."""
    try:
        client.wait_for_workers(1, timeout=timeout or None)
    except TimeoutError:
        raise ClusterError(f"no worker joined the Dask scheduler within {timeout:g} s") from None
    seen = client.run(os.path.isdir, str(root))
    blind = sorted(w for w, ok in seen.items() if not ok)
    if blind:
        raise ClusterError(f"{len(blind)} of {len(seen)} Dask worker(s) cannot see the job directory {root} "
                           f"(e.g. {blind[0]}): the workers need a filesystem shared with this machine at the same "
                           "path (give --work-dir on it)")


class _WorkerWatch:
    """Raises ClusterError once the cluster has had no worker for ``timeout`` seconds (checked every 2 s), or,
    while tasks that need resources wait, no worker holding them."""

    def __init__(self, client, timeout: float):
        self.client, self.timeout = client, timeout
        self.last_seen = self.next_check = self.last_holder = time.monotonic()

    def wait_for(self, pending, stop: threading.Event | None = None, needs: dict | None = None) -> None:
        """Block until the ``as_completed`` queue ``pending`` holds a finished future, checking every 0.1 s for
        ``stop`` (then KeyboardInterrupt) and for a cluster without workers (or without one holding the
        resources ``needs``: :meth:`check`)."""
        if needs is None:
            self.last_holder = time.monotonic()
        while not pending.has_ready():
            if stop is not None and stop.is_set():
                raise KeyboardInterrupt
            self.check(needs)
            with pending.thread_condition:  # notified as each task finishes
                pending.thread_condition.wait(timeout=0.1)

    def check(self, needs: dict | None = None) -> None:
        if self.timeout <= 0:  # 0: wait for ever
            return
        now = time.monotonic()
        if now < self.next_check:
            return
        self.next_check = now + 2.0
        workers = _workers(self.client)
        if workers:
            self.last_seen = now
        elif now - self.last_seen > self.timeout:
            raise ClusterError(f"the Dask cluster has had no worker for {self.timeout:g} s (workers killed, or "
                               "none started): the job stops; rerun to resume from the tiles already done")
        if needs is None or any(_holds(w, needs) for w in workers.values()):
            self.last_holder = now
        elif now - self.last_holder > self.timeout:
            what = ", ".join(f"{k}={v:g}" for k, v in needs.items())
            raise ClusterError(f"no Dask worker has held the resources {what} for {self.timeout:g} s, and the "
                               f"batches of solves on a card need one (start a worker per card with "
                               f"`dask worker --resources {what.replace(', ', ',')}`); the job stops; rerun to "
                               "resume from the tiles already done")


def _workers(client) -> dict:
    """The workers of ``client``'s cluster: address -> the scheduler's facts (``resources``, ...)."""
    try:
        return client.scheduler_info(n_workers=-1).get("workers") or {}
    except TypeError:  # older distributed: no n_workers argument
        return client.scheduler_info().get("workers") or {}


def _holds(worker: dict, needs: dict) -> bool:
    have = worker.get("resources") or {}
    return all(have.get(k, 0) >= v for k, v in needs.items())


def _killed_worker(exc: BaseException) -> bool:
    try:
        from distributed.scheduler import KilledWorker
    except ImportError:  # pragma: no cover - distributed's layout changed
        return type(exc).__name__ == "KilledWorker"
    return isinstance(exc, KilledWorker)
