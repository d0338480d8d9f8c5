"""One level of a solve, as the backends see it: its prepared inputs (:class:`LevelRun`), Adam's constants, and the
coarse-to-fine start of the next level (:func:`upsample`). Shared by the CPU loop (:mod:`tiled_gridpull.solver`) and
the CUDA one (:mod:`tiled_gridpull.solver_cuda`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .band import Band
from .config import LevelSchedule, SolverConfig
from .field import Field
from .kernels import interp as ki
from .kernels import sampling as ksamp
from .nearest import NearestPoints

__all__ = ["LevelRun", "pool_rows", "upsample", "ADAM_BETA1", "ADAM_BETA2", "ADAM_EPS"]

ADAM_BETA1, ADAM_BETA2, ADAM_EPS = 0.9, 0.999, 1e-8


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


def pool_rows(P: np.ndarray, seed: int, it0: int, pool: int, nq: int, sigma: np.float32,
              nearest: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """The query pool's nearest points, found on the host: batch ``b`` holds the ``nq`` queries of iteration
    ``it0 + b`` (:func:`~tiled_gridpull.kernels.sampling.draw_queries`).

    The pool keeps only the rows (4 bytes a query): a batch's queries are re-drawn from the counter-based RNG each
    time it comes round (0.2 ms).

    Parameters
    ----------
    P : (N, 3) float32
        The level's points (index coordinates, Morton order).
    seed, it0, pool, nq : int
    sigma : float32
        Query spread (cells).
    nearest : callable
        ``nearest(q, centres)``: the row of each query's nearest point, (Nq,) int, for queries (Nq, 3) float32
        drawn around rows ``centres`` (Nq,) int64.

    Returns
    -------
    (pool, nq) int32
    """
    centres = np.empty(nq, np.int64)
    q = np.empty((nq, 3), np.float32)
    rows = np.empty((pool, nq), np.int32)
    for b in range(pool):
        ksamp.draw_queries(P, seed, it0 + b, sigma, centres, q)
        rows[b] = nearest(q, centres)
    return rows


@dataclass(eq=False)
class LevelRun:
    """One level's schedule on one band, prepared for a backend (:class:`~tiled_gridpull.solver.CpuBackend`,
    :class:`~tiled_gridpull.solver_cuda.CudaBackend`).

    Attributes
    ----------
    P : (N, 3) float32
        The level's points, index coordinates, Morton order.
    normals : (N, 3) float32 or (0, 3)
        Their unit normals when the normal loss is on.
    band : Band
    values : (n_slots,) float32
        Initial field (cells).
    cfg : SolverConfig
    st : LevelSchedule
    nn : NearestPoints or None
        For the queries of iterations outside the pool (``query_pool == 0``); None where the backend found the
        pool's nearest points itself.
    pool_nn : (B, Nq) int32 or None
        Nearest point of each query of each pool batch: a host array, or the backend's device array
        (:meth:`~tiled_gridpull.solver_cuda.CudaBackend.nearest_pool`).
    """

    P: np.ndarray
    normals: np.ndarray
    band: Band
    values: np.ndarray
    cfg: SolverConfig
    st: LevelSchedule
    nn: NearestPoints | None
    pool_nn: np.ndarray | None
    progress: Callable[[int, int, dict], None] | None
    history_every: int
    it0: int
    total: int
    level: int
    history: list

    @property
    def udf(self) -> bool:
        return self.cfg.mode == "udf"

    @property
    def gamma(self) -> float:
        return 0.0 if self.udf else self.st.gamma

    @property
    def beta(self) -> float:
        return self.cfg.losses.udf_beta if self.udf else self.cfg.losses.beta

    @property
    def loss_weights(self) -> tuple[np.float32, np.float32, np.float32]:
        """``beta, gamma, lam`` (surface, gradient-consistency and normal weights) as the loss kernels take them:
        float32, since a Python float would make their arithmetic float64 (slower on the CPU, and on a card)."""
        return np.float32(self.beta), np.float32(self.gamma), np.float32(self.cfg.losses.normal_weight)

    @property
    def uses_normals(self) -> bool:
        """Whether the normal loss runs: weighted, and every point with its normal."""
        return bool(self.cfg.losses.normal_weight > 0.0 and self.normals.shape[0] == self.P.shape[0])

    @property
    def sqrt_tv(self) -> bool:
        return self.st.tv_form == "sqrt"

    @cached_property
    def n_params(self) -> int:
        """The band's parameter count (at least 1), counted once: the band does not change during the level, and
        counting its flags at every iteration (for :attr:`tv_scale`) was 1.3 % of a dense tile's solve."""
        return max(self.band.n_params, 1)

    @property
    def tv_scale(self) -> float:
        """``alpha / P`` (sqrt form) or ``2 alpha / P`` (squared form): see :func:`.kernels.step.tv_adam_step`."""
        a = self.cfg.losses.alpha
        return (a if self.sqrt_tv else 2.0 * a) / self.n_params

    def lr_t(self, it: int) -> tuple[float, float]:
        """The schedule's learning rate at iteration ``it`` of the level, and Adam's bias-corrected one."""
        lr = self.st.lr * self.cfg.schedule.lr_decay ** (it // self.st.lr_step)
        t = it + 1
        return lr, lr * np.sqrt(1.0 - ADAM_BETA2 ** t) / (1.0 - ADAM_BETA1 ** t)

    def batch(self, it: int) -> int:
        """Which pool batch (or, without a pool, which fresh draw) iteration ``it`` uses."""
        return it % self.st.query_pool if self.st.query_pool else it

    def records(self, it: int) -> bool:
        """Whether iteration ``it`` goes into the history (and to the progress callback)."""
        return bool(self.history_every) and (it % self.history_every == 0 or it == self.st.iterations - 1)

    def record(self, it: int, loss_sums: np.ndarray, n_valid: int, tv_sum: float) -> None:
        """Append iteration ``it``'s mean losses to the history and report progress."""
        lr, _ = self.lr_t(it)
        mean = np.asarray(loss_sums, np.float64) / max(n_valid, 1)
        rec = {"iteration": self.it0 + it, "level": self.level, "lr": lr, "pull": float(mean[0]),
               "surface": float(mean[1]), "gradient": float(mean[2]), "normal": float(mean[3]),
               "tv": float(tv_sum / self.n_params), "valid_queries": int(n_valid)}
        self.history.append(rec)
        if self.progress is not None:
            self.progress(self.it0 + it, self.total, rec)
