"""The banded GridPull solver (driver around the numba kernels).

Units
-----
The field is stored **in cells** and queries live in lattice index coordinates, so a value of 1 means one cell
of distance at every resolution. Adam moves each vertex by about ``lr`` per step whatever the loss scale, so
``lr = 1.0`` is one cell per step, decaying x0.3 every 400 iterations to 0.0081 cells after 1600: the paper's
schedule then converges in the same number of steps at every R (the authors' code also starts from a field in
cells with steps of 1.0, but reads it as object units; a field in world units stepping one cell did not
converge at R=256 in 1600 iterations). World distances are ``value * cell_size``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from dataclasses import field as dc_field

import numpy as np
from pykdtree.kdtree import KDTree

from .band import Band, build_band
from .config import LevelSchedule, SolverConfig
from .device import describe as describe_device
from .device import resolve as resolve_device
from .errors import InputError
from .field import Field
from .kernels import CELL_PULL
from .kernels import losses as kl
from .kernels import sampling as ksamp
from .kernels import step as ks
from .lattice import Lattice
from .level import ADAM_BETA1, ADAM_BETA2, ADAM_EPS, LevelRun, pool_rows, upsample
from .nearest import NearestPoints

__all__ = ["solve", "solve_batch", "SolveProblem", "sphere_init", "upsample", "ProgressFn", "InitFn", "CpuBackend",
           "backend_for"]

ProgressFn = Callable[[int, int, dict], None]
InitFn = Callable[[Band], np.ndarray]

MIN_POINTS = 10


def sphere_init(band: Band, radius: float, centre: np.ndarray | None = None) -> np.ndarray:
    """Signed distance (cells) to a sphere of ``radius`` cells at ``centre`` (default: lattice centre).

    Returns
    -------
    (n_bricks, 512) float32
    """
    if centre is None:
        centre = (np.asarray(band.lattice.shape, dtype=np.float64) - 1.0) / 2.0
    pos = band.slot_positions().astype(np.float64)
    d = np.linalg.norm(pos - centre, axis=1) - radius
    return d.astype(np.float32).reshape(band.n_bricks, 512)


def nearest_point_init(band: Band, points: np.ndarray) -> np.ndarray:
    """Unsigned start for UDF mode: each band vertex's distance (cells) to the nearest input point.

    A sphere's distance means nothing for an open sheet, while the distance to the samples is already the
    unsigned field up to the sampling density; the solve then sharpens it at the surface.

    Returns
    -------
    (n_bricks, 512) float32
    """
    pos = band.slot_positions().astype(np.float32)
    d, _ = KDTree(np.ascontiguousarray(points, dtype=np.float32)).query(pos, k=1)
    return d.astype(np.float32).reshape(band.n_bricks, 512)


COARSE_POINTS_PER_CELL = 4


def thin_per_cell(P: np.ndarray, seed: int, cap: int = COARSE_POINTS_PER_CELL) -> tuple[np.ndarray, np.ndarray]:
    """At most ``cap`` (default ``COARSE_POINTS_PER_CELL``) points in every occupied cell, chosen at random
    (coarse levels; a tile's finest cells with ``sampling.points_per_cell``).

    A coarse cell holds many points; its field needs a few. Capping each cell (rather than thinning the whole
    cloud at one rate) evens out LiDAR's density, tens of times higher near the scanner than far from it:
    the queries, drawn around points, then cover the scene evenly instead of crowding the dense patches, and
    the candidate lists of the exact nearest-neighbour fast path span a useful distance everywhere. On the
    1M-point street this cut solve time 7 % and Chamfer-L1 21 % against a single global rate
    (docs/solver.md).

    Parameters
    ----------
    P : (N, 3) float
        Points in index units of the level's lattice (cell ``(i, j, k)`` spans ``[i, i + 1)`` etc.).
    seed : int
    cap : int
        Points kept per cell.

    Returns
    -------
    kept : (M, 3) float32
    keep : (M,) int64
        Indices of the kept points, ascending.
    """
    cells = np.floor(P).astype(np.int64)
    key = cells[:, 0] * (1 << 42) + cells[:, 1] * (1 << 21) + cells[:, 2]
    perm = np.random.default_rng(seed).permutation(len(P))
    order = perm[np.argsort(key[perm], kind="stable")]  # by cell, random within a cell
    sorted_key = key[order]
    first = np.r_[0, np.flatnonzero(np.diff(sorted_key)) + 1]
    rank = np.arange(len(P)) - np.repeat(first, np.diff(np.r_[first, len(P)]))
    keep = np.sort(order[rank < cap])
    if len(keep) == len(P):
        return P, np.arange(len(P))
    return np.ascontiguousarray(P[keep]), keep


#: the name the solver and its tests have used
_thin = thin_per_cell


def _threads() -> int:
    import numba

    return int(numba.get_num_threads())


@dataclass(frozen=True, eq=False)
class SolveProblem:
    """One cloud to solve on one lattice: an item of :func:`solve_batch` (the arguments of :func:`solve`)."""

    points: np.ndarray
    lattice: Lattice
    normals: np.ndarray | None = None
    init: InitFn | None = None
    progress: ProgressFn | None = None


def solve(points: np.ndarray, lattice: Lattice, config: SolverConfig, *,
          normals: np.ndarray | None = None, init: InitFn | None = None,
          progress: ProgressFn | None = None, history_every: int = 50, device: str | None = None) -> Field:
    """Optimize a GridPull field for one cloud on one lattice.

    Parameters
    ----------
    points : (N, 3) float64
        Input points, world coordinates (outside points are ignored).
    lattice : Lattice
        The finest lattice; coarser levels (``config.schedule.levels > 1``) coarsen it by powers of 2.
    config : SolverConfig
    normals : (N, 3) float, optional
        Unit normals of the points, used when ``config.losses.normal_weight > 0`` (in UDF mode they then also orient
        the signs).
    init : callable, optional
        ``init(band) -> (n_bricks, 512) float32`` initial field (cells) on the coarsest band; default: the
        paper's sphere of ``config.init_radius`` cells at the lattice centre.
    progress : callable, optional
        ``progress(iteration, total, stats)`` called every ``history_every`` iterations (iterations counted over
        all levels).

    Returns
    -------
    Field
        The optimized field on the finest band, ``info`` holding timings, band sizes and a loss history.
    """
    return solve_batch([SolveProblem(points, lattice, normals, init, progress)], config, history_every=history_every,
                       device=device)[0]


def solve_batch(problems: Sequence[SolveProblem], config: SolverConfig, *, history_every: int = 50,
                device: str | None = None) -> list[Field]:
    """:func:`solve` for several clouds at once, level by level: each level of every problem runs in one batch on
    the backend (on a card, one launch per step for all of them, their bands concatenated; on the CPU one after the
    other). Each field is the one :func:`solve` gives for its problem alone: the same draws, per-problem query
    counts and TV weights (bit for bit on either device; tests/test_device.py).

    Parameters
    ----------
    problems : sequence of SolveProblem
        Lattices with the same number of levels (tiles of one job: the same block shape).
    config : SolverConfig
    history_every : int
    device : str, optional
        ``cpu``, ``cuda`` or ``auto`` (default: ``config.device``).

    Returns
    -------
    list of Field
        One per problem, in order.

    Raises
    ------
    InputError
        A problem with fewer than ``MIN_POINTS`` points inside its lattice.
    ValueError
        Problems whose lattices need different numbers of levels.
    """
    t0 = time.perf_counter()
    resolved = resolve_device(device or config.device)
    backend = backend_for(resolved)
    states = [_Solving.start(p, config) for p in problems]
    if not states:
        return []
    levels = states[0].levels
    if any(s.levels != levels for s in states):
        raise ValueError(f"a batch solves lattices with the same number of levels, got {[s.levels for s in states]}")
    for level in range(levels):
        _run_level(states, level, levels, backend, history_every)
    out = []
    for s in states:
        fld = s.fld
        udf_info = None
        if config.mode == "udf":
            # P: the finest level's points, all of them
            fld, udf_info = _sign_and_polish(fld, s.P, s.N, config, levels, s.problem.progress, history_every,
                                             s.done, s.total, s.history, backend)
            if config.schedule.udf_polish:
                s.per_level.append({"level": levels, "polish": True,
                                    **{k: v for k, v in fld.info.items() if k != "history"}})
        fld.info = {
            "points_used": int(len(s.idx)),
            "band": fld.band.stats,
            "levels": s.per_level,
            "history": s.history,
            "time_total_s": time.perf_counter() - t0,
            "device": describe_device(resolved),
        }
        if len(states) > 1:
            fld.info["batch"] = len(states)
        if udf_info is not None:
            fld.info["udf"] = udf_info
        out.append(fld)
    return out


def _run_level(states: list[_Solving], level: int, levels: int, backend, history_every: int) -> None:
    """Level ``level`` of every problem, in one batch on the backend. A function of its own so that the level's
    runs (points, query pools, nearest-point structures, on a card their device arrays) go when it returns."""
    factor = 2 ** (levels - 1 - level)
    runs = [s.level_run(level, factor, backend, history_every) for s in states]
    results = backend.iterate_batch([r.run for r in runs]) if len(runs) > 1 else [backend.iterate(runs[0].run)]
    for s, r, (d, timings) in zip(states, runs, results):
        s.finish_level(r, d, timings, backend)


@dataclass(eq=False)
class _Solving:
    """A problem of :func:`solve_batch` between its levels."""

    problem: SolveProblem
    config: SolverConfig
    idx: np.ndarray  # (N, 3) the points inside the lattice, index coordinates
    N: np.ndarray | None  # their normals when the normal loss is on
    levels: int
    total: int
    fld: Field | None = None
    P: np.ndarray | None = None  # the last level's points
    done: int = 0
    per_level: list = dc_field(default_factory=list)
    history: list = dc_field(default_factory=list)

    @classmethod
    def start(cls, problem: SolveProblem, config: SolverConfig) -> _Solving:
        lattice = problem.lattice
        idx = lattice.to_index(problem.points)
        inside = np.all((idx >= 0) & (idx <= np.asarray(lattice.shape) - 1), axis=1)
        idx = idx[inside]
        if len(idx) < MIN_POINTS:
            raise InputError(f"too few points to solve: {len(idx)} inside the lattice (need at least {MIN_POINTS})")
        N = None
        if problem.normals is not None and config.losses.normal_weight > 0:
            N = np.ascontiguousarray(np.asarray(problem.normals, dtype=np.float32)[inside])
        cells = max(lattice.n_cells)
        return cls(problem, config, idx, N, config.levels_for(cells), config.total_iterations(cells))

    def level_run(self, level: int, factor: int, backend, history_every: int) -> _LevelStart:
        """This problem's level ``level`` (lattice coarsened ``factor`` times) prepared for the backend."""
        config = self.config
        lat = self.problem.lattice.coarsen(factor)
        P = np.ascontiguousarray(self.idx / factor, dtype=np.float32)
        # an unsigned field has no direction to compare with a normal: UDF levels skip the normal loss
        Nl = None if config.mode == "udf" else self.N
        if factor > 1:
            P, keep = _thin(P, config.sampling.seed + level)
            Nl = Nl[keep] if Nl is not None else None
        st = config.level_settings(level, self.levels, len(P))
        tb = time.perf_counter()
        band = build_band(P, lat, config.sampling.m1, st.m2)
        t_band = time.perf_counter() - tb
        if self.fld is not None:
            values = backend.upsample(self.fld, band)
        elif self.problem.init is not None:
            values = np.ascontiguousarray(self.problem.init(band), dtype=np.float32).reshape(band.n_bricks, 512)
        elif config.mode == "udf":
            values = nearest_point_init(band, P)
        else:
            values = sphere_init(band, config.init_radius)
        self.P = P
        start = _level_start(P, Nl, band, values, config, st, self.problem.progress, history_every, self.done,
                             self.total, level, self.history, backend)
        start.extra = {"level": level, "cell_size": lat.cell_size, "shape": list(lat.shape), "band": band.stats,
                       "time_band_s": t_band}
        return start

    def finish_level(self, start: _LevelStart, d: np.ndarray, timings: dict, backend) -> None:
        self.fld = _level_field(start, d, timings, backend)
        self.done += start.run.st.iterations
        self.per_level.append({**start.extra, **{k: v for k, v in self.fld.info.items() if k != "history"}})


def _sign_and_polish(fld: Field, P: np.ndarray, N: np.ndarray | None, config: SolverConfig, levels: int,
                     progress: ProgressFn | None, history_every: int, done: int, total: int,
                     history: list, backend) -> tuple[Field, dict]:
    """End of a UDF solve: sign the unsigned field, then refine it as a signed one (``config.schedule.udf_polish``).

    ``N``: the input normals, present when the normal loss is on (``--normals``): they then orient the signs
    too; a file's normals are not trusted otherwise."""
    from .udf_sign import sign_unsigned_field

    values, info = sign_unsigned_field(fld.band, fld.values, P, N)
    info["polish_iterations"] = config.schedule.udf_polish
    if config.schedule.udf_polish == 0:
        return Field(fld.band, values, signed=True, info=fld.info), info
    signed = config.replace(mode="sdf")
    out = _optimize(P, N, fld.band, values, signed, signed.polish_settings(), progress, history_every,
                    done, total, levels, history, backend)
    return out, info


class CpuBackend:
    """The solver's iterations on the CPU's threads (the numba kernels of :mod:`tiled_gridpull.kernels`)."""

    name = "cpu"
    #: the query pool's nearest points are found by the caller (:class:`NearestPoints`), not by the backend
    finds_nearest = False

    def adopt(self, field: Field) -> None:
        """Nothing to keep: the field's values are the host arrays."""

    def upsample(self, coarse: Field, band: Band) -> np.ndarray:
        """:func:`upsample` (factor 2)."""
        return upsample(coarse, band)

    def iterate(self, run: LevelRun) -> tuple[np.ndarray, dict]:
        """Run the level's iterations; the optimized ``(n_slots,)`` field and timings."""
        band, cfg, st = run.band, run.cfg, run.st
        P = run.P
        flat_flags = band.flags.reshape(-1)
        d_a = run.values.reshape(-1).copy()
        d_b = d_a.copy()
        m = np.zeros_like(d_a)
        v = np.zeros_like(d_a)
        qgrad = np.zeros_like(d_a)
        inv = np.zeros_like(d_a) if run.sqrt_tv else np.zeros(1, np.float32)
        form = ks.TV_SQRT if run.sqrt_tv else ks.TV_SQUARED
        shape = np.asarray(band.lattice.shape, np.int64)
        nq = st.queries
        sigma = np.float32(st.sigma)
        slots = np.empty((nq, 16), np.int64)
        grads = np.empty((nq, 16), np.float32)
        losses = np.empty((nq, 4), np.float32)
        centres = np.empty(nq, np.int64)
        q = np.empty((nq, 3), np.float32)
        beta, gamma, lam = run.loss_weights
        t_query = t_step = 0.0
        for it in range(st.iterations):
            ta = time.perf_counter()
            # the iteration number seeds the queries: levels draw different queries
            batch = run.batch(it)
            ksamp.draw_queries(P, cfg.sampling.seed, run.it0 + batch, sigma, centres, q)
            nn_idx = run.pool_nn[batch] if run.pool_nn is not None else run.nn.query(q, centres)[0]
            n_valid = kl.query_losses(d_a, flat_flags, band.brick_table, shape, q, P, nn_idx, run.normals,
                                      CELL_PULL, beta, gamma, lam, slots, grads, losses)
            if n_valid:
                kl.scatter_add(qgrad, slots, grads, np.float32(1.0 / n_valid))
            tb = time.perf_counter()
            _, lr_t = run.lr_t(it)
            tv_sum = 0.0
            if form == ks.TV_SQRT:
                tv_sum = ks.tv_inverse_norms(d_a, flat_flags, band.neighbors, inv)
            tv_sq = ks.tv_adam_step(d_a, d_b, m, v, qgrad, flat_flags, band.neighbors, inv, form,
                                    np.float32(run.tv_scale), np.float32(lr_t), np.float32(ADAM_BETA1),
                                    np.float32(ADAM_BETA2), np.float32(ADAM_EPS), run.udf)
            d_a, d_b = d_b, d_a
            tc = time.perf_counter()
            t_query += tb - ta
            t_step += tc - tb
            if run.records(it):
                run.record(it, losses.sum(axis=0), n_valid, tv_sum if form == ks.TV_SQRT else tv_sq)
        return d_a, {"time_queries_s": t_query, "time_steps_s": t_step, "threads": _threads()}

    def iterate_batch(self, runs: list[LevelRun]) -> list[tuple[np.ndarray, dict]]:
        """:meth:`iterate` for each run, one after the other (the CPU's threads are busy with one already)."""
        return [self.iterate(run) for run in runs]


def backend_for(device: str):
    """The backend object of a resolved device (``"cpu"`` or ``"cuda"``, :func:`tiled_gridpull.device.resolve`)."""
    if device == "cuda":
        from .solver_cuda import CudaBackend

        return CudaBackend()
    return CpuBackend()


def _nearest_info(nn: NearestPoints) -> dict:
    """What a level's :class:`NearestPoints` did, for the level's info."""
    return {"nn_queries": nn.queries, "nn_fallback_fraction": nn.fallbacks / max(nn.queries, 1),
            "nn_candidates": int(nn.knn.shape[1]) if nn.knn is not None else 0,
            "nn_fast_share_predicted": nn.fast_share, "nn_lists_skipped": nn.lists_skipped}


@dataclass(eq=False)
class _LevelStart:
    """A level prepared for the backend (:func:`_level_start`), and what its field's info needs afterwards."""

    run: LevelRun
    t0: float
    t_pool: float
    nn: NearestPoints | None
    nn_info: dict | None
    extra: dict = dc_field(default_factory=dict)


def _level_start(P: np.ndarray, N: np.ndarray | None, band: Band, values: np.ndarray, cfg: SolverConfig,
                 st: LevelSchedule, progress: ProgressFn | None, history_every: int, it0: int, total: int, level: int,
                 history: list, backend) -> _LevelStart:
    """One level's schedule ``st`` on one band, ready for the backend's iterations (its points in Morton order,
    the query pool's nearest points found)."""
    t0 = time.perf_counter()
    # Morton order: stratified centres then come out spatially sorted
    order = np.argsort(ksamp.morton_codes(P), kind="stable")
    P = np.ascontiguousarray(P[order])
    if N is not None:
        N = np.ascontiguousarray(N[order])
    sigma = np.float32(st.sigma)
    pool = st.query_pool
    nq = st.queries
    nn_info = None
    if pool and backend.finds_nearest:
        # the card draws the pool's queries and searches a point grid itself: no tree, nothing copied back
        nn = None
        tp = time.perf_counter()
        pool_nn, nn_info = backend.nearest_pool(P, cfg.sampling.seed, it0, pool, nq, sigma)
    else:
        nn = NearestPoints(P, cfg.sampling.knn, sigma=float(sigma),
                           expected_queries=st.queries * (pool if pool else st.iterations))
        tp = time.perf_counter()
        pool_nn = (pool_rows(P, cfg.sampling.seed, it0, pool, nq, sigma, lambda q, c: nn.query(q, c)[0])
                   if pool else None)
    t_pool = time.perf_counter() - tp
    run = LevelRun(P=P, normals=N if N is not None else np.zeros((0, 3), np.float32), band=band,
                   values=values, cfg=cfg, st=st, nn=nn, pool_nn=pool_nn, progress=progress,
                   history_every=history_every, it0=it0, total=total, level=level, history=history)
    return _LevelStart(run, t0, t_pool, nn, nn_info)


def _level_field(start: _LevelStart, d: np.ndarray, timings: dict, backend) -> Field:
    """The field a level's iterations ended with (``d``, the backend's ``(n_slots,)`` values), with its info."""
    run = start.run
    info = {
        "iterations": run.st.iterations,
        "queries": run.st.queries,
        "points": int(len(run.P)),
        "time_solve_s": time.perf_counter() - start.t0,
        "time_query_pool_s": start.t_pool,
        **timings,
        **(_nearest_info(start.nn) if start.nn is not None else start.nn_info),
        "device": backend.name,
    }
    band = run.band
    fld = Field(band, d.reshape(band.n_bricks, 512), signed=run.cfg.mode == "sdf", info=info)
    backend.adopt(fld)
    return fld


def _optimize(P: np.ndarray, N: np.ndarray | None, band: Band, values: np.ndarray, cfg: SolverConfig,
              st: LevelSchedule, progress: ProgressFn | None, history_every: int, it0: int, total: int, level: int,
              history: list, backend=None) -> Field:
    """Run one level's schedule ``st`` on one band."""
    backend = backend or CpuBackend()
    start = _level_start(P, N, band, values, cfg, st, progress, history_every, it0, total, level, history, backend)
    d, timings = backend.iterate(start.run)
    return _level_field(start, d, timings, backend)
