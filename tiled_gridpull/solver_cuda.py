"""The solver's iterations on a CUDA card: the field and Adam's state stay on the card across iterations and levels.

Per iteration, three launches (:mod:`tiled_gridpull.kernels.cuda`): the queries (drawn, evaluated and scattered in
one kernel), the sqrt form's TV norms, and the fused TV + Adam step; the host computes the learning rate and reads
nothing back except at the history's iterations. The query pool's nearest points are found on the card too
(:meth:`CudaBackend.nearest_pool`: a hashed point grid built on the host, searched by one thread per query) and stay
there; only without a pool (``query_pool: 0``) does each iteration's batch come from the CPU's KD-tree. Between
levels the finer band's initial values are sampled from the coarser field still on the card.

Results are bitwise reproducible on one card (the query gradients are summed in fixed point) and agree with the
CPU's within float32 rounding per step (tests/test_cuda_kernels.py, tests/test_device.py).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import time

import numpy as np

from .band import Band
from .device import cuda_card, cuda_module
from .errors import GridPullError, MemoryBudgetError
from .field import Field
from .kernels import CELL_PULL
from .kernels import sampling as ksamp
from .level import ADAM_BETA1, ADAM_BETA2, ADAM_EPS, LevelRun, pool_rows, upsample
from .nearest import PointGrid

__all__ = ["CudaBackend", "ONE_LAUNCH_ENV"]

#: ``1``: run each level in one cooperative launch (:func:`~tiled_gridpull.kernels.cuda.solve_level`) instead of three
#: launches per iteration. Tested against the per-step launches in the simulator (bit for bit), not yet timed on a
#: card: its first try on an H200 found no cooperative grid for 512-thread blocks (it now picks a smaller block).
ONE_LAUNCH_ENV = "TILED_GRIDPULL_CUDA_ONE_LAUNCH"

log = logging.getLogger(__name__)

#: threads per block: one brick's 512 slots (the TV gather then reads its neighbours from the same brick)
BLOCK = 512
#: threads per block of the nearest-point search (a thread holds a shell walk's state; no shared memory)
NEAREST_BLOCK = 256
#: under the simulator every thread is a Python thread: a few of them loop over the items instead
SIM_THREADS = 8


class CudaBackend:
    """Runs :class:`~tiled_gridpull.solver.LevelRun` s on the current CUDA card (or numba's simulator)."""

    name = "cuda"
    #: the query pool's nearest points are found on the card (:meth:`nearest_pool`)
    finds_nearest = True
    #: set once the one-launch kernel failed in this process (then every solve launches per step)
    _one_launch_failed = False

    def __init__(self) -> None:
        self.k = cuda_module()
        from numba import cuda

        self.cuda = cuda
        self.simulator = cuda_card() == "CUDA simulator"
        self._normals = None
        #: the next bands' initial values on the card, from upsample(), by id of the band
        self._pending: dict[int, object] = {}
        #: the last iterations' values on the card by id of their band, until adopt() names their fields
        self._kept: dict[int, object] = {}
        #: one launch per level (grid sync), opt-in: see ONE_LAUNCH_ENV
        self.cooperative = os.environ.get(ONE_LAUNCH_ENV) == "1" and not CudaBackend._one_launch_failed
        #: the last level's fields (by id) and their values on the card: the next level upsamples from these
        self._last: dict[int, tuple[Field, object]] = {}

    def _grid(self, n: int, block: int = BLOCK) -> tuple[int, int]:
        if self.simulator:
            return 1, min(SIM_THREADS, max(n, 1))
        return max(1, -(-n // block)), block

    def _normal_table(self):
        if self._normals is None:
            self._normals = self.cuda.to_device(ksamp.NORMALS)
        return self._normals

    def nearest_pool(self, P: np.ndarray, seed: int, it0: int, pool: int, nq: int, sigma: np.float32) -> tuple:
        """Nearest point of every query of a level's pool, found on the card; they stay there for :meth:`iterate`.

        Parameters
        ----------
        P : (N, 3) float32
            The level's points (index coordinates, Morton order), as the host's pool would draw around.
        seed, it0 : int
            Sampling seed and the level's first iteration: batch ``b`` holds iteration ``it0 + b``'s queries.
        pool, nq : int
            Batches and queries per batch.
        sigma : float32
            Query spread (cells).

        Returns
        -------
        pool_nn : (pool, nq) int32 device array
        info : dict
            ``nn_queries`` and ``nn_grid_cell`` (the grid's cell edge, cells) for the level's info.
        """
        with _card_errors(f"the nearest points of {pool * nq:,} queries"):
            grid = PointGrid.for_queries(P, float(sigma))
            to = self.cuda.to_device
            out = self.cuda.device_array((pool, nq), np.int32)
            if self.simulator:
                # the simulated search costs ~13 ms a query in Python threads (a 6-iteration test solve: 24 s of
                # 44): the simulator takes the same rows from the search's CPU twin, and the kernel itself is
                # tested against that twin (tests/test_cuda_kernels.py)
                out.copy_to_device(pool_rows(P, seed, it0, pool, nq, sigma, lambda q, c: grid.query(P, q, c)[0]))
            else:
                blocks, threads = self._grid(pool * nq, NEAREST_BLOCK)
                ox, oy, oz = (float(v) for v in grid.origin)
                gx, gy, gz = (int(v) for v in grid.dims)
                order, keys, starts, counts, bits = grid.arrays
                self.k.nearest_pool[blocks, threads](to(P), to(order), to(keys), to(starts), to(counts), bits, ox, oy,
                                                     oz, grid.cell, gx, gy, gz, int(seed), int(it0), P.shape[0] / nq,
                                                     sigma, self._normal_table(), out)
                self.cuda.synchronize()  # so the level's pool time is the card's
        return out, {"nn_queries": pool * nq, "nn_grid_cell": grid.cell}

    def _level_in_one_launch(self, run: LevelRun, d_a, d_b, m, v, acc, inv, common, pool, step, sigma, form, tv_scale,
                             counts, loss_sums, tv_sums):
        """All the level's iterations in one cooperative launch (:func:`~tiled_gridpull.kernels.cuda.solve_level`);
        the history is read back once, at the end. Returns the array holding the result."""
        cfg, iters = run.cfg, run.st.iterations
        lr_ts = np.array([run.lr_t(it)[1] for it in range(iters)], np.float32)
        args = (d_a, d_b, m, v, acc, inv, *common, pool, int(cfg.sampling.seed), int(run.it0), float(step), sigma,
                self._normals, CELL_PULL, *run.loss_weights,
                self.cuda.to_device(lr_ts), form, tv_scale, np.float32(ADAM_BETA1), np.float32(ADAM_BETA2),
                np.float32(ADAM_EPS), run.udf, counts, loss_sums, tv_sums, int(run.history_every))
        if self.simulator:
            blocks, threads = 1, SIM_THREADS
            self.k.solve_level[blocks, threads](*args)
        else:
            spec = self.k.solve_level.specialize(*args)
            kernel = next(iter(spec.overloads.values()))
            # the query phase holds many registers: 512 threads a block fit no cooperative grid on an H200 (the
            # largest resident grid was 0 blocks); take the largest block that fits
            for threads in (512, 256, 128, 64):
                resident = kernel.max_cooperative_grid_blocks(threads)
                if resident > 0:
                    break
            else:
                raise RuntimeError("no block size fits a cooperative grid")
            need = -(-max(run.band.n_slots, run.st.queries) // threads)
            spec[max(1, min(need, resident)), threads](*args)
        if run.history_every:
            c, ls, tv = counts.copy_to_host(), loss_sums.copy_to_host(), tv_sums.copy_to_host()
            ls, tv = ls / self.k.SUMS_SCALE, tv / self.k.SUMS_SCALE
            for it in range(iters):
                if run.records(it):
                    run.record(it, ls[it], int(c[it]), float(tv[it]))
        return d_a if iters % 2 == 0 else d_b

    def upsample(self, coarse: Field, band: Band) -> np.ndarray:
        """The finer band's initial values (:func:`tiled_gridpull.solver.upsample`), from the coarse field on the card
        when it is the last one this backend produced; a driver failure is one line (see :meth:`iterate`)."""
        last = self._last.get(id(coarse))
        if last is None or last[0] is not coarse:
            return upsample(coarse, band)
        with _card_errors(f"upsampling to {band.n_slots:,} slots"):
            return self._upsample(coarse, last[1], band)

    def _upsample(self, coarse: Field, on_card, band: Band) -> np.ndarray:
        cb = coarse.band
        to = self.cuda.to_device
        out = self.cuda.device_array(band.n_slots, np.float32)
        nx, ny, nz = (int(v) for v in cb.lattice.shape)
        blocks, threads = self._grid(band.n_slots)
        self.k.upsample[blocks, threads](on_card, to(cb.brick_table), nx, ny, nz,
                                         to(np.ascontiguousarray(band.brick_coords, np.int32)), 2, 1e3, out)
        self._pending[id(band)] = out
        return out.copy_to_host().reshape(band.n_bricks, 512)

    def iterate(self, run: LevelRun) -> tuple[np.ndarray, dict]:
        """Run the level's iterations on the card; the optimized ``(n_slots,)`` field (on the host) and timings.

        A failure of the card's driver (out of memory, a lost device, a context made before a fork) is a one-line
        :class:`~tiled_gridpull.errors.MemoryBudgetError` or :class:`~tiled_gridpull.errors.GridPullError`."""
        with _card_errors(f"a band of {run.band.n_slots:,} slots, {run.st.queries:,} queries"):
            return self._iterate(run)

    def _iterate(self, run: LevelRun) -> tuple[np.ndarray, dict]:
        cuda, k = self.cuda, self.k
        t0 = time.perf_counter()
        band, cfg, st = run.band, run.cfg, run.st
        to = cuda.to_device
        self._normal_table()
        n_slots = band.n_slots
        pending = self._pending.pop(id(band), None)
        self._last.clear()  # the coarser fields' values: every upsample from them is done
        d_a = pending if pending is not None and pending.shape[0] == n_slots else to(run.values.reshape(-1))
        d_b = cuda.device_array(n_slots, np.float32)
        m = to(np.zeros(n_slots, np.float32))
        v = to(np.zeros(n_slots, np.float32))
        acc = to(np.zeros(n_slots, np.int64))
        inv = to(np.zeros(n_slots if run.sqrt_tv else 1, np.float32))
        flags = to(band.flags.reshape(-1))
        table = to(band.brick_table)
        neighbors = to(band.neighbors)
        points = to(run.P)
        normals = to(np.ascontiguousarray(run.normals, np.float32).reshape(-1, 3))
        use_normals = run.uses_normals
        iters = st.iterations
        counts = to(np.zeros(iters, np.int32))
        loss_sums = to(np.zeros((iters, 4), k.SUMS_DTYPE))  # fixed point (k.SUMS_SCALE): repeats bit for bit
        tv_sums = to(np.zeros(iters, k.SUMS_DTYPE))
        nq = st.queries
        pool = run.pool_nn
        if pool is not None and not hasattr(pool, "copy_to_host"):  # a host pool (a CPU-found one): copy it over
            pool = to(pool)
        fresh = cuda.device_array(nq, np.int32) if pool is None else None
        centres = np.empty(nq, np.int64)
        q = np.empty((nq, 3), np.float32)
        nx, ny, nz = (int(v) for v in band.lattice.shape)
        sigma = np.float32(st.sigma)
        step = run.P.shape[0] / nq
        form = 1 if run.sqrt_tv else 0
        qb, qt = self._grid(nq)
        sb, stt = self._grid(n_slots)
        tv_scale = np.float32(run.tv_scale)
        seed = cfg.sampling.seed
        t_setup = time.perf_counter() - t0
        common = (flags, table, neighbors, nx, ny, nz, points, normals, use_normals)
        one_launch = False
        if pool is not None and self.cooperative:
            try:
                d_a = self._level_in_one_launch(run, d_a, d_b, m, v, acc, inv, common, pool, step, sigma, form,
                                                tv_scale, counts, loss_sums, tv_sums)
                one_launch = True
            except Exception as exc:  # noqa: BLE001 - e.g. no libcudadevrt to link grid sync: fall back, once
                CudaBackend._one_launch_failed = True
                self.cooperative = False
                log.warning("one launch per level is unavailable on this card (%s): launching per iteration",
                            str(exc).splitlines()[0][:200])
        for it in range(0 if one_launch else iters):
            batch = run.batch(it)
            if pool is not None:
                nearest = pool[batch]
            else:
                ksamp.draw_queries(run.P, seed, run.it0 + batch, sigma, centres, q)
                fresh.copy_to_device(run.nn.query(q, centres)[0].astype(np.int32))
                nearest = fresh
            want = run.records(it)
            key = np.uint64(ksamp.iteration_key(seed, run.it0 + batch))  # one kernel type for every key
            k.query_scatter[qb, qt](d_a, flags, table, nx, ny, nz, points, normals, use_normals, nearest, key, step,
                                    sigma, self._normals, CELL_PULL, *run.loss_weights, acc, counts, it, loss_sums,
                                    want)
            _, lr_t = run.lr_t(it)
            if form:
                k.tv_norms[sb, stt](d_a, flags, neighbors, inv, tv_sums, it, want)
            k.tv_adam[sb, stt](d_a, d_b, m, v, acc, counts, it, flags, neighbors, inv, form, tv_scale,
                               np.float32(lr_t), np.float32(ADAM_BETA1), np.float32(ADAM_BETA2), np.float32(ADAM_EPS),
                               run.udf, tv_sums, want)
            d_a, d_b = d_b, d_a
            if want:
                n_valid = int(counts[it:it + 1].copy_to_host()[0])
                run.record(it, loss_sums[it].copy_to_host() / k.SUMS_SCALE, n_valid,
                           float(tv_sums[it:it + 1].copy_to_host()[0]) / k.SUMS_SCALE)
        values = d_a.copy_to_host()  # synchronizes: the loop's time below is the card's
        t_loop = time.perf_counter() - t0 - t_setup
        self._kept[id(band)] = d_a  # adopt() takes it (one entry per band of a batch run one after the other)
        return values, {"time_queries_s": 0.0, "time_steps_s": t_loop, "time_device_setup_s": t_setup,
                        "card": cuda_card()}

    def iterate_batch(self, runs: list[LevelRun]) -> list[tuple[np.ndarray, dict]]:
        """Run several levels' iterations together, their bands concatenated: one launch per step for all of them.

        Each run's field comes out as :meth:`iterate` gives it alone (the same draws, its own valid counts, TV
        weight and lattice; the fixed-point sums make it bit for bit). Runs that cannot share launches (different
        schedules, no query pool, normals on some only) run one after the other.

        Returns
        -------
        list of ((n_slots,) float32, dict)
            Each run's optimized field (on the host) and timings; the batch's loop time is every run's.
        """
        if not _batchable(runs):
            return [self.iterate(run) for run in runs]
        what = f"a batch of {len(runs)} bands, {sum(r.band.n_slots for r in runs):,} slots"
        with _card_errors(what):
            return self._iterate_batch(runs)

    def _iterate_batch(self, runs: list[LevelRun]) -> list[tuple[np.ndarray, dict]]:
        cuda, k = self.cuda, self.k
        t0 = time.perf_counter()
        to = cuda.to_device
        self._normal_table()
        first = runs[0]
        cfg, st = first.cfg, first.st
        n_tiles = len(runs)
        slot_start = np.cumsum([0] + [r.band.n_slots for r in runs])
        brick_start = np.cumsum([0] + [r.band.n_bricks for r in runs])
        point_start = np.cumsum([0] + [r.P.shape[0] for r in runs]).astype(np.int64)
        normal_start = np.cumsum([0] + [r.normals.shape[0] for r in runs]).astype(np.int64)
        query_start = np.cumsum([0] + [r.st.queries for r in runs]).astype(np.int64)
        n_slots, n_queries = int(slot_start[-1]), int(query_start[-1])
        # the first values: a band's upsampled start where it is still on the card, else the host's
        d_a = cuda.device_array(n_slots, np.float32)
        for b, run in enumerate(runs):
            pending = self._pending.pop(id(run.band), None)
            part = d_a[int(slot_start[b]):int(slot_start[b + 1])]
            if pending is not None and pending.shape[0] == run.band.n_slots:
                part.copy_to_device(pending)
            else:
                part.copy_to_device(np.ascontiguousarray(run.values.reshape(-1), np.float32))
        self._last.clear()
        d_b = cuda.device_array(n_slots, np.float32)
        m = to(np.zeros(n_slots, np.float32))
        v = to(np.zeros(n_slots, np.float32))
        acc = to(np.zeros(n_slots, np.int64))
        inv = to(np.zeros(n_slots if first.sqrt_tv else 1, np.float32))
        flags = to(np.concatenate([r.band.flags.reshape(-1) for r in runs]))
        # brick numbers become the batch's: tile b's bricks follow those of the tiles before it
        table_shape = np.max([r.band.brick_table.shape for r in runs], axis=0)
        tables = np.full((n_tiles, *table_shape), -1, np.int32)
        neighbors = []
        for b, run in enumerate(runs):
            t = run.band.brick_table
            tables[b, :t.shape[0], :t.shape[1], :t.shape[2]] = np.where(t >= 0, t + brick_start[b], -1)
            nb = run.band.neighbors
            neighbors.append(np.where(nb >= 0, nb + brick_start[b], -1).astype(nb.dtype))
        tables = to(tables)
        neighbors = to(np.concatenate(neighbors))
        tile_of_brick = to(np.repeat(np.arange(n_tiles, dtype=np.int32), np.diff(brick_start)))
        dims = to(np.array([r.band.lattice.shape for r in runs], np.int64))
        points = to(np.concatenate([r.P for r in runs]).astype(np.float32))
        normals = to(np.concatenate([np.asarray(r.normals, np.float32).reshape(-1, 3) for r in runs]))
        use_normals = first.uses_normals
        steps = to(np.array([r.P.shape[0] / r.st.queries for r in runs], np.float64))
        tv_scales = to(np.array([r.tv_scale for r in runs], np.float32))
        q_tile = to(np.repeat(np.arange(n_tiles, dtype=np.int32), np.diff(query_start)))
        q_start = to(query_start)
        p_start, n_start = to(point_start), to(normal_start)
        # the tiles' query pools side by side: row t holds every tile's queries of pool batch t
        pool = cuda.device_array((st.query_pool, n_queries), np.int32)
        for b, run in enumerate(runs):
            src = run.pool_nn if hasattr(run.pool_nn, "copy_to_host") else to(np.ascontiguousarray(run.pool_nn))
            cb, ct = self._grid(src.shape[0] * src.shape[1])
            k.copy_columns[cb, ct](src, pool, int(query_start[b]))
            run.pool_nn = None  # copied: the tile's own pool need not stay on the card through the level
        iters = st.iterations
        counts = to(np.zeros((n_tiles, iters), np.int32))
        loss_sums = to(np.zeros((n_tiles, iters, 4), k.SUMS_DTYPE))
        tv_sums = to(np.zeros((n_tiles, iters), k.SUMS_DTYPE))
        sigma = np.float32(st.sigma)
        form = 1 if first.sqrt_tv else 0
        qb, qt = self._grid(n_queries)
        sb, stt = self._grid(n_slots)
        seed = cfg.sampling.seed
        t_setup = time.perf_counter() - t0
        for it in range(iters):
            batch = first.batch(it)
            want = first.records(it)
            key = np.uint64(ksamp.iteration_key(seed, first.it0 + batch))
            k.query_scatter_batch[qb, qt](d_a, flags, tables, dims, points, p_start, normals, n_start, use_normals,
                                          pool[batch], q_tile, q_start, key, steps, sigma, self._normals, CELL_PULL,
                                          *first.loss_weights, acc,
                                          counts, it, loss_sums, want)
            _, lr_t = first.lr_t(it)
            if form:
                k.tv_norms_batch[sb, stt](d_a, flags, neighbors, inv, tile_of_brick, tv_sums, it, want)
            k.tv_adam_batch[sb, stt](d_a, d_b, m, v, acc, counts, it, tile_of_brick, flags, neighbors, inv, form,
                                     tv_scales, np.float32(lr_t), np.float32(ADAM_BETA1), np.float32(ADAM_BETA2),
                                     np.float32(ADAM_EPS), first.udf, tv_sums, want)
            d_a, d_b = d_b, d_a
        values = d_a.copy_to_host()  # synchronizes: the loop's time below is the card's
        t_loop = time.perf_counter() - t0 - t_setup
        if first.history_every:  # read back once, as one launch per level does
            c, ls, tv = counts.copy_to_host(), loss_sums.copy_to_host(), tv_sums.copy_to_host()
            for b, run in enumerate(runs):
                for it in range(iters):
                    if run.records(it):
                        run.record(it, ls[b, it] / k.SUMS_SCALE, int(c[b, it]), float(tv[b, it]) / k.SUMS_SCALE)
        self._kept.update({id(r.band): d_a[int(slot_start[b]):int(slot_start[b + 1])] for b, r in enumerate(runs)})
        timings = {"time_queries_s": 0.0, "time_steps_s": t_loop, "time_device_setup_s": t_setup,
                   "card": cuda_card(), "batch": n_tiles}
        return [(values[slot_start[b]:slot_start[b + 1]].copy(), dict(timings)) for b in range(n_tiles)]

    def adopt(self, field: Field) -> None:
        """Mark ``field`` (built from the last :meth:`iterate` or :meth:`iterate_batch`) as one whose values are
        still on the card."""
        on_card = self._kept.pop(id(field.band), None)
        if on_card is not None:
            self._last[id(field)] = (field, on_card)


def _batchable(runs: list[LevelRun]) -> bool:
    """Whether ``runs`` can share launches: one config, level and schedule (the queries per iteration aside, which
    follow each tile's points), each with a query pool, and the normal loss on for all or none."""
    first = runs[0]
    same = all(r.cfg == first.cfg and r.level == first.level and r.it0 == first.it0
               and dataclasses.replace(r.st, queries=first.st.queries) == first.st
               and r.uses_normals == first.uses_normals for r in runs)
    return same and all(r.pool_nn is not None and r.st.query_pool for r in runs)


#: what numba-cuda's driver raises (``CudaAPIError`` is a ``CudaDriverError``; the simulator has its own classes of
#: some of these names and not of others, hence the names)
_DRIVER_ERRORS = ("CudaAPIError", "CudaDriverError", "CudaSupportError")


@contextlib.contextmanager
def _card_errors(what: str):
    """Turn a failure of the card's driver while doing ``what`` into one line: out of memory is a
    :class:`~tiled_gridpull.errors.MemoryBudgetError` (exit 5), anything else the driver raises (``CudaAPIError``,
    ``CudaDriverError`` such as "CUDA initialized before forking", ``CudaSupportError``) a
    :class:`~tiled_gridpull.errors.GridPullError`."""
    try:
        yield
    except Exception as exc:
        if not any(c.__name__ in _DRIVER_ERRORS for c in type(exc).__mro__):
            raise
        text = " ".join(str(exc).split())
        if "OUT_OF_MEMORY" in text.upper():
            raise MemoryBudgetError(f"the CUDA card ({cuda_card()}) ran out of memory for {what}: use smaller tiles "
                                    f"or --device cpu") from None
        raise GridPullError(f"CUDA error on {cuda_card()} ({what}): {text[:300]}") from None
