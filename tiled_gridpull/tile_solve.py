"""Solving one tile: its points in, its field written (run alike by the serial and the Dask executor)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .bridge import BridgeRule, bridge_field
from .cloud import duplicate_mask
from .config import SolverConfig
from .errors import ConfigError, GridPullError
from .io.atomic import npz_document, save_npz
from .kernels import BRICK
from .lattice import Lattice
from .memory import peak_rss_mb, reset_peak_rss
from .noise import denoise_block
from .normals import estimate_normals, orient_normals, orientation_decided, orientation_score
from .initial_field import plane_distance_init
from .partition import read_tile_points
from .solver import SolveProblem, solve_batch, thin_per_cell
from .tile_field import save_tile_field
from .tile_plan import TileSpec
from .tiling import TilingConfig

__all__ = ["solve_tile", "solve_tiles", "solve_prepared", "solve_prepared_fields", "finish_prepared",
           "prepare_tile", "PreparedTile", "orientation_rule", "tile_summary"]

def tile_summary(spec: TileSpec, **fields) -> dict:
    """The start of a tile's solve summary, whichever step writes it: the tile's name, grid index and block
    points, then ``fields``."""
    return {"tile": spec.name, "index": list(spec.index), "points": spec.block_points, **fields}


def orientation_rule(tiling: TilingConfig, has_sensor: bool) -> str:
    """The orientation rule a tile applies: ``tiling.orientation`` with ``auto`` resolved (sensor when the tile
    has sensor origins, else up).

    Raises
    ------
    ConfigError
        ``sensor`` asked for a tile without sensor origins.
    """
    if tiling.orientation == "auto":
        return "sensor" if has_sensor else "up"
    if tiling.orientation == "sensor" and not has_sensor:
        raise ConfigError("orientation 'sensor' needs sensor origins (KITTI sequences); use 'up' or 'auto'")
    return tiling.orientation


def solve_tile(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str | Path,
               centre: tuple[float, float, float] | None = None) -> dict:
    """Solve one tile and write its field; returns a small summary (never raises for data reasons).

    The field is solved in a tile-local frame (metres from the block's low corner) so float32 is exact, and
    written with global brick coordinates for the blend pass. Orientation follows ``tiling.orientation``; after
    the solve the field is flipped if it disagrees with the oriented normals (the loss is sign-blind, so the
    initial orientation could in principle be lost; every tile applies the same rule, so tiles agree).
    ``centre`` (world) is the input's bounding-box centre, used by the ``outward`` rule.
    """
    return solve_tiles([spec], tiling, solver, [field_path], centre)[0]


def solve_tiles(specs: list[TileSpec], tiling: TilingConfig, solver: SolverConfig,
                field_paths: list[str | Path], centre: tuple[float, float, float] | None = None) -> list[dict]:
    """:func:`solve_tile` for several tiles, their solves batched (:func:`tiled_gridpull.solver.solve_batch`: on a
    card one launch per step for all of them; on the CPU one after the other). Each tile's field and summary are
    those it gets alone but for its figures of time and memory: ``phases_s["solve"]`` is the batch's solve,
    ``time_s`` runs from the tile's read to its own end (the other tiles' reads and finishes before it included)
    and ``peak_rss_mb`` is the batch's.

    Returns
    -------
    list of dict
        The tiles' summaries, in order.
    """
    if len(field_paths) != len(specs):
        raise ValueError(f"{len(specs)} tiles need as many field paths, got {len(field_paths)}")
    reset_peak_rss()  # each summary's peak is the batch's
    return solve_prepared([prepare_tile(spec, tiling, solver, centre) for spec in specs], tiling, solver,
                          field_paths)


def solve_prepared(prepared: list[PreparedTile], tiling: TilingConfig, solver: SolverConfig,
                   field_paths: list[str | Path]) -> list[dict]:
    """The second half of :func:`solve_tiles`: tiles already read and set up (:func:`prepare_tile`, here or on
    another machine: :meth:`PreparedTile.save`) solved as one batch (:func:`solve_prepared_fields`), then each
    checked, bridged and written (:func:`finish_prepared`).

    Returns
    -------
    list of dict
        The tiles' summaries, in order (a tile ``prepare_tile`` skipped or failed keeps its summary).
    """
    if len(field_paths) != len(prepared):
        raise ValueError(f"{len(prepared)} tiles need as many field paths, got {len(field_paths)}")
    fields = solve_prepared_fields(prepared, solver)
    for p, fld, path in zip(prepared, fields, field_paths):
        if fld is not None:
            finish_prepared(p, fld, tiling, path)
    return [p.summary for p in prepared]


def solve_prepared_fields(prepared: list[PreparedTile], solver: SolverConfig) -> list:
    """The tiles awaiting their solve (``status`` None) solved as one batch
    (:func:`tiled_gridpull.solver.solve_batch`: on a card one launch per step for all): their fields, in order,
    None for a tile that needed no solve or whose solve failed (its summary then closed, with the reason). A batch
    that fails for one tile's data reason is solved tile by tile, so only that tile fails. Each solved tile's
    summary gets the batch's solve time and, in a batch of several, its size (``batch``) and first tile
    (``batch_of``)."""
    ready = [p for p in prepared if p.status is None]
    out: dict[int, object] = {}
    if ready:
        start = time.perf_counter()
        for p in ready:
            p.mark = start  # a batch's solve is each of its tiles' solve
        fields: list = []
        batch = len(ready)
        try:
            fields = solve_batch([p.problem() for p in ready], solver, history_every=100)
        except GridPullError as exc:
            reason = str(exc)  # not the exception: its traceback holds the failed batch's arrays (on a card, memory)
        if not fields:
            # outside the except block, for the same reason: the retries run with the failed batch gone
            if batch == 1:
                _fail(ready[0], reason)
                fields = [None]
            else:  # one tile's data reason (too few points in its lattice) must not fail the others: each alone
                fields = [_solve_alone(p, solver) for p in ready]
                batch = 1
        for p, fld in zip(ready, fields):
            out[id(p)] = fld
            if fld is not None:
                p.lap("solve")  # before any tile's finish: its solve is the batch's time, not its neighbours'
                if batch > 1:  # the batch's size, and its first tile's name: which tiles shared the solve
                    p.summary["batch"] = batch
                    p.summary["batch_of"] = ready[0].spec.name
            else:
                p.close()
    return [out.get(id(p)) for p in prepared]


def finish_prepared(p: PreparedTile, fld, tiling: TilingConfig, field_path: str | Path) -> dict:
    """After a tile's solve: its sign checked against the oriented normals (flipped where they disagree), the
    ground's sampling gaps bridged, the field written; its summary filled in, closed and returned."""
    _finish(p, fld, tiling, field_path)
    p.close()
    return p.summary


def _solve_alone(p: PreparedTile, solver: SolverConfig):
    """``p``'s field solved on its own, or None with ``p`` failed for the reason its solve gave."""
    try:
        return solve_batch([p.problem()], solver, history_every=100)[0]
    except GridPullError as exc:
        _fail(p, exc)
        return None


@dataclass(eq=False)
class PreparedTile:
    """A tile read and set up for its solve (:func:`prepare_tile`), and its summary so far.

    ``status`` is None while the tile awaits its solve (:meth:`problem`), ``"skipped"`` or ``"failed"`` (with the
    summary closed) once it needs none."""

    spec: TileSpec
    summary: dict
    t0: float
    mark: float
    status: str | None = None  # "skipped" or "failed" once the tile needs no solve
    xyz: np.ndarray | None = None  # (N, 3) float64, metres from the block's low corner
    sensor32: np.ndarray | None = None  # (N, 3) each point's sensor origin, where known
    local: Lattice | None = None
    rule: str = ""
    normals: np.ndarray | None = None  # (N, 3) oriented unit normals, where the rule orients them
    decided: np.ndarray | None = None  # (N,) bool: the normals the orientation check counts (None: all)
    peak_before_mb: float = 0.0  # peak memory of the process that prepared the tile, when it was another

    def lap(self, name: str) -> None:
        """Add the time since the last lap to phase ``name`` (where a tile's time goes besides the solve's levels;
        on a card the solve is the small part)."""
        now = time.perf_counter()
        phases = self.summary["phases_s"]
        phases[name] = phases.get(name, 0.0) + now - self.mark
        self.mark = now

    def problem(self) -> SolveProblem:
        """The tile's solve: its points on its local lattice, started from the planes of its oriented normals where
        it has them (else from the solver's sphere)."""
        xyz, normals = self.xyz, self.normals
        init = None
        if normals is not None:
            init = lambda band: plane_distance_init(band, xyz / band.lattice.cell_size, normals)  # noqa: E731
        return SolveProblem(xyz, self.local, init=init)

    def close(self) -> None:
        """The summary's closing figures."""
        self.summary["time_s"] = time.perf_counter() - self.t0
        self.summary["peak_rss_mb"] = max(peak_rss_mb(), self.peak_before_mb)

    def account(self) -> dict:
        """The tile's account so far, for the process that goes on with it (:meth:`take_account`): its summary,
        the time it has taken and the memory peak of the processes it went through."""
        return {"summary": self.summary, "elapsed_s": time.perf_counter() - self.t0,
                "peak_rss_mb": max(peak_rss_mb(), self.peak_before_mb)}

    def take_account(self, state: dict) -> None:
        """Go on from an :meth:`account` another process wrote: its summary, its time (the wait between the two
        processes is not the tile's) and the larger memory peak."""
        now = time.perf_counter()
        self.summary, self.t0, self.mark = state["summary"], now - float(state["elapsed_s"]), now
        self.peak_before_mb = max(self.peak_before_mb, float(state["peak_rss_mb"]))

    def save(self, path: str | Path, key: str | None = None) -> None:
        """Write a tile awaiting its solve (``status`` None) to ``path`` (``.npz``, atomically), for
        :meth:`load` in another process: a job on a card prepares its tiles on CPU workers and solves them in
        batches on the card's worker. ``key`` names what it was prepared for (the solve key of
        :mod:`tiled_gridpull.resume`)."""
        if self.status is not None:
            raise ValueError(f"tile {self.spec.name} is {self.status}: only a tile awaiting its solve is saved")
        arrays = {name: getattr(self, name) for name in _PREPARED_ARRAYS if getattr(self, name) is not None}
        save_npz(path, arrays, state={**self.account(), "rule": self.rule, "key": key})

    @classmethod
    def load(cls, path: str | Path, spec: TileSpec, key: str | None = None) -> PreparedTile:
        """A tile :meth:`save` wrote for ``spec`` (and for ``key``, when given: a file an earlier run with other
        settings left, or wrote late, is not this run's). Its ``time_s`` goes on from the time its preparation
        took (the wait for the batch is not the tile's), its ``peak_rss_mb`` is the larger of both processes'.

        Raises
        ------
        OSError, ValueError, KeyError
            ``path`` missing, damaged, or written for another tile or key.
        """
        with np.load(path) as z:
            state = npz_document(z, "state")
            arrays = {name: z[name] for name in _PREPARED_ARRAYS if name in z.files}
        if state["summary"].get("tile") != spec.name:
            raise ValueError(f"{path} holds tile {state['summary'].get('tile')!r}, not {spec.name!r}")
        if key is not None and state.get("key") != key:
            raise ValueError(f"{path} was prepared with other settings (solve key {state.get('key')!r})")
        now = time.perf_counter()
        p = cls(spec, state["summary"], now, now, rule=state["rule"], **arrays)
        p.take_account(state)
        p.local = _local_lattice(spec)
        return p


#: the arrays of a :class:`PreparedTile` that :meth:`PreparedTile.save` writes (those it has)
_PREPARED_ARRAYS = ("xyz", "sensor32", "normals", "decided")


def _local_lattice(spec: TileSpec) -> Lattice:
    """The lattice a tile is solved on: its block's, in metres from the block's low corner (float32 stays exact
    there, whatever the georeferenced coordinates)."""
    return Lattice((0.0, 0.0, 0.0), spec.block.cell_size, spec.block.shape)


def _fail(p: PreparedTile, exc: BaseException | str) -> None:
    p.status = "failed"
    p.summary.update(status="failed", reason=str(exc))


def prepare_tile(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig,
                 centre: tuple[float, float, float] | None = None) -> PreparedTile:
    """Read a tile's points and set up its solve: duplicates dropped, denoised, thinned, normals estimated and
    oriented. A tile with too few points comes back ``skipped``, one that fails for a data reason ``failed``
    (both with their summaries closed)."""
    t0 = time.perf_counter()
    summary = tile_summary(spec, phases_s={})
    p = PreparedTile(spec, summary, t0, time.perf_counter())
    try:
        stored, sensor32 = read_tile_points(spec)
        xyz = stored.astype(np.float64)
        # points the solver's float32 frame cannot tell apart are duplicates, as always (the bytes of the float32
        # rows decide: -0.0 and 0.0 stay apart)
        keep = np.flatnonzero(~duplicate_mask(stored.astype(np.float32).astype(np.float64), signed_zeros=True))
        if len(keep) < len(xyz):
            summary["duplicates_dropped"] = int(len(xyz) - len(keep))
            xyz = xyz[keep]
            sensor32 = sensor32[keep] if sensor32 is not None else None
        p.lap("read")
        if solver.noise.denoise_passes > 0:
            xyz, keep = _denoise(xyz, spec, tiling, solver, summary)
            sensor32 = sensor32[keep] if sensor32 is not None else None
        summary["points_used"] = int(len(xyz))
        if len(xyz) < tiling.min_points:
            p.status = "skipped"
            summary.update(status="skipped", reason=f"{len(xyz)} points (< min_points {tiling.min_points})")
            p.close()
            return p
        if solver.sampling.points_per_cell > 0:
            # at most k points per finest cell: the set-up and the solve follow the surface, not the density
            _, keep = thin_per_cell(xyz / spec.block.cell_size, solver.sampling.seed, solver.sampling.points_per_cell)
            if len(keep) < len(xyz):
                summary["points_thinned"] = int(len(xyz) - len(keep))
                xyz = xyz[keep]
                sensor32 = sensor32[keep] if sensor32 is not None else None
        p.lap("prepare")
        p.xyz, p.sensor32 = xyz, sensor32
        p.local = _local_lattice(spec)
        p.rule = orientation_rule(tiling, sensor32 is not None)
        if p.rule != "sphere":
            normals = estimate_normals(xyz, tiling.normal_neighbors)
            away = None
            if p.rule == "outward":
                if centre is None:
                    raise ConfigError("orientation 'outward' needs the centre of the input")
                away = np.asarray(centre, np.float64) - spec.block.low_corner
            ref = sensor32.astype(np.float64) if p.rule == "sensor" else None
            p.normals = orient_normals(normals, xyz, ref, away_from=away)
            # under "up" the field's sign is checked against the normals the rule decides (not the walls, which
            # only a vote orients); a sensor orients even grazing ground reliably, so there every normal counts
            decided = orientation_decided(p.normals, xyz, ref, away_from=away) if p.rule == "up" else None
            if decided is not None and decided.sum() < max(20, 0.05 * len(xyz)):
                decided = None  # too few to outvote: every normal counts
            p.decided = decided
        p.lap("normals")
    except GridPullError as exc:
        _fail(p, exc)
        p.close()
    return p


def _finish(p: PreparedTile, fld, tiling: TilingConfig, field_path: str | Path) -> None:
    """After a tile's solve: its sign checked against the oriented normals (flipped where they disagree), the
    ground's sampling gaps bridged, the field written; the summary filled in."""
    spec, summary, xyz = p.spec, p.summary, p.xyz
    try:
        flipped = False
        if p.normals is not None:
            _, grads = fld.sample(xyz)
            if orientation_score(grads, p.normals, p.decided) < 0:
                fld.values *= -1
                flipped = True
        if tiling.bridge > 0 and p.rule in ("up", "sensor"):
            # ground is bridged where outside is up; a closed object cut into tiles ("outward") has no ground
            # with sensor origins the ground in a shadow stays open (nothing lies beyond it as the sensor sees it)
            rule = BridgeRule(radius=tiling.bridge, object_width=tiling.bridge_objects)
            fld, bridged = bridge_field(fld, xyz, rule, p.sensor32)
            summary.update(bridged)
        p.lap("orient_and_bridge")
        off_bricks = np.asarray(spec.block.offset, np.int64) // BRICK
        field_sha = save_tile_field(field_path, fld.band.brick_coords.astype(np.int64) + off_bricks, fld.values,
                                    fld.band.flags)
        p.lap("save")
        hist = fld.info.get("history", [])
        summary.update(status="solved", flipped=flipped, orientation=p.rule, field_sha256=field_sha,
                       band_params=int(fld.band.n_params), bricks=int(fld.band.n_bricks),
                       level_bricks=[lv["band"]["bricks"] for lv in fld.info.get("levels", [])],
                       final_pull=hist[-1]["pull"] if hist else None,
                       loss_first=_loss_point(hist[0], fld.info) if hist else None,
                       loss_last=_loss_point(hist[-1], fld.info) if hist else None,
                       loss_curve=[(h["iteration"], h["pull"], h["tv"]) for h in hist],
                       field_path=str(field_path), device=fld.info.get("device"),
                       solve_levels=[{k: lv.get(k) for k in LEVEL_TIMINGS} for lv in fld.info.get("levels", [])])
    except GridPullError as exc:
        _fail(p, exc)


#: per-level figures a tile's summary keeps (where a solve spends its time, on either device)
LEVEL_TIMINGS = ("level", "time_band_s", "time_solve_s", "time_query_pool_s", "time_queries_s", "time_steps_s",
                 "time_device_setup_s", "iterations", "queries", "points")


def _denoise(xyz: np.ndarray, spec: TileSpec, tiling: TilingConfig, solver: SolverConfig,
             summary: dict) -> tuple[np.ndarray, np.ndarray]:
    """The block's points denoised the same whatever the tiling (:func:`tiled_gridpull.noise.denoise_block`), and
    which of ``xyz`` (N, 3; metres from the block's low corner, halo included) they are; figures go into
    ``summary``."""
    cell = spec.block.cell_size
    size = (np.asarray(spec.block.shape, np.float64) - 1.0) * cell
    halo = tiling.halo * cell
    # the tile read its block and a halo around it (TilingConfig.halo); the outer faces of the tile grid have
    # no points beyond them (mesh_lo/hi reach into the overlap there)
    lo = np.where(np.asarray(spec.mesh_lo) < np.asarray(spec.core_lo), -np.inf, -halo)
    hi = np.where(np.asarray(spec.mesh_hi) > np.asarray(spec.core_hi), np.inf, size + halo)
    noise = solver.noise
    t0 = time.perf_counter()
    moved, keep = denoise_block(xyz, noise.denoise_neighbors, noise.denoise_passes, noise.denoise_radius * cell,
                                lo, hi)
    # the halo's points only served the neighbourhoods: the solve takes the block's, every one of them when the
    # halo covers the denoising's reach (as with_halo sets it); any other would be dropped, never left unmoved
    in_block = spec.in_block(xyz)
    use = in_block & keep
    moved = moved[use[keep]]
    shift = np.linalg.norm(moved - xyz[use], axis=1)
    summary["denoise"] = {"points": int(use.sum()), "halo_points": int((~in_block).sum()),
                          "dropped_near_faces": int((in_block & ~keep).sum()),
                          "moved_median_m": float(np.median(shift)) if len(shift) else 0.0,
                          "moved_max_m": float(shift.max()) if len(shift) else 0.0,
                          "time_s": time.perf_counter() - t0}
    return moved, use


def _loss_point(record: dict, info: dict) -> dict:
    """The part of a solver history record kept in a tile summary: pull and TV losses in cells of the record's
    level, that level's ``cell_size`` (world units) and the pull loss in world units (``pull_world``)."""
    level = int(record["level"])
    levels = info.get("levels", [])
    cell = float(levels[level]["cell_size"]) if level < len(levels) else float("nan")
    return {"iteration": int(record["iteration"]), "level": level, "pull": float(record["pull"]),
            "tv": float(record["tv"]), "cell_size": cell, "pull_world": float(record["pull"]) * cell}
