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
from collections.abc import Callable

import numpy as np
from pykdtree.kdtree import KDTree

from .band import Band, build_band
from .config import LevelSchedule, SolverConfig
from .errors import InputError
from .field import Field
from .kernels import CELL_PULL
from .kernels import interp as ki
from .kernels import losses as kl
from .kernels import sampling as ksamp
from .kernels import step as ks
from .lattice import Lattice
from .nearest import NearestPoints

__all__ = ["solve", "sphere_init", "upsample", "ProgressFn", "InitFn"]

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


def upsample(coarse: Field, band: Band, factor: int = 2, fill: float = 1e3) -> np.ndarray:
    """Initial values on a finer band from a coarser field (trilinear, rescaled to the finer cells).

    Fine vertex ``i`` sits at coarse index ``i / factor``; a distance of ``d`` coarse cells is ``factor * d``
    fine cells. Slots whose coarse cell has no values get ``fill`` (they are never parameters: the coarser band
    is wider in world units).

    Returns
    -------
    (n_bricks, 512) float32
    """
    pos = (band.slot_positions().astype(np.float64) / factor).astype(np.float32)
    f, _ = ki.sample_field(coarse.values.reshape(-1), coarse.band.brick_table,
                           np.asarray(coarse.band.lattice.shape, np.int64), pos, np.float32(fill / factor))
    # the kernel clamps to the lattice: positions beyond it (slots past the fine block's edge) are never used
    return (f * np.float32(factor)).reshape(band.n_bricks, 512)


def solve(points: np.ndarray, lattice: Lattice, config: SolverConfig, *,
          normals: np.ndarray | None = None, init: InitFn | None = None,
          progress: ProgressFn | None = None, history_every: int = 50) -> Field:
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
    t0 = time.perf_counter()
    idx = lattice.to_index(points)
    inside = np.all((idx >= 0) & (idx <= np.asarray(lattice.shape) - 1), axis=1)
    idx = idx[inside]
    if len(idx) < MIN_POINTS:
        raise InputError(f"too few points to solve: {len(idx)} inside the lattice (need at least {MIN_POINTS})")
    N = None
    if normals is not None and config.losses.normal_weight > 0:
        N = np.ascontiguousarray(np.asarray(normals, dtype=np.float32)[inside])
    udf = config.mode == "udf"
    levels = config.levels_for(max(lattice.n_cells))
    total = config.total_iterations(max(lattice.n_cells))
    fld: Field | None = None
    done = 0
    per_level = []
    history: list[dict] = []
    for level in range(levels):
        factor = 2 ** (levels - 1 - level)
        lat = lattice.coarsen(factor)
        P = np.ascontiguousarray(idx / factor, dtype=np.float32)
        # an unsigned field has no direction to compare with a normal: UDF levels skip the normal loss
        Nl = None if udf else N
        if factor > 1:
            P, keep = _thin(P, config.sampling.seed + level)
            Nl = Nl[keep] if Nl is not None else None
        st = config.level_settings(level, levels, len(P))
        tb = time.perf_counter()
        band = build_band(P, lat, config.sampling.m1, st.m2)
        t_band = time.perf_counter() - tb
        if fld is not None:
            values = upsample(fld, band)
        elif init is not None:
            values = np.ascontiguousarray(init(band), dtype=np.float32).reshape(band.n_bricks, 512)
        elif config.mode == "udf":
            values = nearest_point_init(band, P)
        else:
            values = sphere_init(band, config.init_radius)
        fld = _optimize(P, Nl, band, values, config, st, progress, history_every, done, total, level, history)
        done += st.iterations
        per_level.append({"level": level, "cell_size": lat.cell_size, "shape": list(lat.shape), "band": band.stats,
                          "time_band_s": t_band, **{k: v for k, v in fld.info.items() if k != "history"}})
    assert fld is not None
    udf_info = None
    if udf:
        # P: the finest level's points, all of them
        fld, udf_info = _sign_and_polish(fld, P, N, config, levels, progress, history_every, done, total,
                                         history)
        if config.schedule.udf_polish:
            per_level.append({"level": levels, "polish": True,
                              **{k: v for k, v in fld.info.items() if k != "history"}})
    fld.info = {
        "points_used": int(len(idx)),
        "band": fld.band.stats,
        "levels": per_level,
        "history": history,
        "time_total_s": time.perf_counter() - t0,
    }
    if udf_info is not None:
        fld.info["udf"] = udf_info
    return fld


def _sign_and_polish(fld: Field, P: np.ndarray, N: np.ndarray | None, config: SolverConfig, levels: int,
                     progress: ProgressFn | None, history_every: int, done: int, total: int,
                     history: list) -> tuple[Field, dict]:
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
                    done, total, levels, history)
    return out, info


def _optimize(P: np.ndarray, N: np.ndarray | None, band: Band, values: np.ndarray, cfg: SolverConfig,
              st: LevelSchedule, progress: ProgressFn | None, history_every: int, it0: int, total: int, level: int,
              history: list) -> Field:
    """Run one level's schedule ``st`` on one band."""
    t0 = time.perf_counter()
    # Morton order: stratified centres then come out spatially sorted
    order = np.argsort(ksamp.morton_codes(P), kind="stable")
    P = np.ascontiguousarray(P[order])
    if N is not None:
        N = np.ascontiguousarray(N[order])
    gamma = 0.0 if cfg.mode == "udf" else st.gamma
    beta = cfg.losses.udf_beta if cfg.mode == "udf" else cfg.losses.beta
    sigma = np.float32(st.sigma)
    pool = st.query_pool
    nn = NearestPoints(P, cfg.sampling.knn, sigma=float(sigma),
                       expected_queries=st.queries * (pool if pool else st.iterations))
    flat_flags = band.flags.reshape(-1)
    d_a = values.reshape(-1).copy()
    d_b = d_a.copy()
    m = np.zeros_like(d_a)
    v = np.zeros_like(d_a)
    qgrad = np.zeros_like(d_a)
    inv = np.zeros_like(d_a) if st.tv_form == "sqrt" else np.zeros(1, np.float32)
    n_params = max(band.n_params, 1)
    form = ks.TV_SQRT if st.tv_form == "sqrt" else ks.TV_SQUARED
    tv_scale = (cfg.losses.alpha if form == ks.TV_SQRT else 2.0 * cfg.losses.alpha) / n_params
    clamp = cfg.mode == "udf"
    shape = np.asarray(band.lattice.shape, np.int64)
    nq = st.queries
    slots = np.empty((nq, 16), np.int64)
    grads = np.empty((nq, 16), np.float32)
    losses = np.empty((nq, 4), np.float32)
    centres = np.empty(nq, np.int64)
    q = np.empty((nq, 3), np.float32)
    nrm = N if N is not None else np.zeros((0, 3), np.float32)
    beta1, beta2, eps = 0.9, 0.999, 1e-8
    iterations, lr0, lr_step = st.iterations, st.lr, st.lr_step
    t_query = t_step = 0.0
    tp = time.perf_counter()
    if pool:
        # nearest points found once per batch; the batch's queries are re-drawn from the counter-based RNG each
        # time it comes round (0.2 ms), so the pool holds 4 bytes per query
        pool_nn = np.empty((pool, nq), np.int32)
        for b in range(pool):
            ksamp.draw_queries(P, cfg.sampling.seed, it0 + b, sigma, centres, q)
            pool_nn[b] = nn.query(q, centres)[0]
    t_pool = time.perf_counter() - tp
    for it in range(iterations):
        ta = time.perf_counter()
        # the iteration number seeds the queries: levels draw different queries
        batch = it % pool if pool else it
        ksamp.draw_queries(P, cfg.sampling.seed, it0 + batch, sigma, centres, q)
        nn_idx = pool_nn[batch] if pool else nn.query(q, centres)[0]
        n_valid = kl.query_losses(d_a, flat_flags, band.brick_table, shape, q, P, nn_idx, nrm, CELL_PULL,
                                  beta, gamma, cfg.losses.normal_weight, slots, grads, losses)
        if n_valid:
            kl.scatter_add(qgrad, slots, grads, np.float32(1.0 / n_valid))
        tb = time.perf_counter()
        lr = lr0 * cfg.schedule.lr_decay ** (it // lr_step)
        t = it + 1
        lr_t = lr * np.sqrt(1.0 - beta2 ** t) / (1.0 - beta1 ** t)
        tv_sum = 0.0
        if form == ks.TV_SQRT:
            tv_sum = ks.tv_inverse_norms(d_a, flat_flags, band.neighbors, inv)
        tv_sq = ks.tv_adam_step(d_a, d_b, m, v, qgrad, flat_flags, band.neighbors, inv, form,
                                np.float32(tv_scale), np.float32(lr_t), np.float32(beta1), np.float32(beta2),
                                np.float32(eps), clamp)
        d_a, d_b = d_b, d_a
        tc = time.perf_counter()
        t_query += tb - ta
        t_step += tc - tb
        if history_every and (it % history_every == 0 or it == iterations - 1):
            mean = losses.sum(axis=0) / max(n_valid, 1)
            tv = (tv_sum if form == ks.TV_SQRT else tv_sq) / n_params
            rec = {"iteration": it0 + it, "level": level, "lr": lr, "pull": float(mean[0]),
                   "surface": float(mean[1]), "gradient": float(mean[2]), "normal": float(mean[3]),
                   "tv": float(tv), "valid_queries": int(n_valid)}
            history.append(rec)
            if progress is not None:
                progress(it0 + it, total, rec)
    info = {
        "iterations": iterations,
        "queries": nq,
        "points": int(len(P)),
        "time_solve_s": time.perf_counter() - t0,
        "time_queries_s": t_query,
        "time_query_pool_s": t_pool,
        "time_steps_s": t_step,
        "nn_queries": nn.queries,
        "nn_fallback_fraction": nn.fallbacks / max(nn.queries, 1),
        "nn_candidates": int(nn.knn.shape[1]) if nn.knn is not None else 0,
        "nn_fast_share_predicted": nn.fast_share,
        "nn_lists_skipped": nn.lists_skipped,
        "threads": _threads(),
    }
    return Field(band, d_a.reshape(band.n_bricks, 512), signed=cfg.mode == "sdf", info=info)
