"""Solving one tile: its points in, its field written (run alike by the serial and the Dask executor)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .bridge import BridgeRule, bridge_field
from .cloud import duplicate_mask
from .config import SolverConfig
from .errors import ConfigError, GridPullError
from .kernels import BRICK
from .lattice import Lattice
from .memory import peak_rss_mb, reset_peak_rss
from .noise import denoise_block
from .normals import estimate_normals, orient_normals, orientation_decided, orientation_score
from .initial_field import plane_distance_init
from .partition import read_tile_points
from .solver import solve, thin_per_cell
from .tile_field import save_tile_field
from .tile_plan import TileSpec
from .tiling import TilingConfig

__all__ = ["solve_tile", "orientation_rule"]

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
    t0 = time.perf_counter()
    reset_peak_rss()
    summary: dict = {"tile": spec.name, "index": list(spec.index), "points": spec.block_points}
    # where a tile's time goes besides the solve's levels (seconds): on a card the solve is the small part
    phases: dict = {}
    summary["phases_s"] = phases
    mark = [time.perf_counter()]

    def lap(name: str) -> None:
        now = time.perf_counter()
        phases[name] = phases.get(name, 0.0) + now - mark[0]
        mark[0] = now

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
        lap("read")
        if solver.noise.denoise_passes > 0:
            xyz, keep = _denoise(xyz, spec, tiling, solver, summary)
            sensor32 = sensor32[keep] if sensor32 is not None else None
        summary["points_used"] = int(len(xyz))
        if len(xyz) < tiling.min_points:
            summary.update(status="skipped", reason=f"{len(xyz)} points (< min_points {tiling.min_points})")
            summary["time_s"] = time.perf_counter() - t0
            summary["peak_rss_mb"] = peak_rss_mb()
            return summary
        if solver.sampling.points_per_cell > 0:
            # at most k points per finest cell: the set-up and the solve follow the surface, not the density
            _, keep = thin_per_cell(xyz / spec.block.cell_size, solver.sampling.seed, solver.sampling.points_per_cell)
            if len(keep) < len(xyz):
                summary["points_thinned"] = int(len(xyz) - len(keep))
                xyz = xyz[keep]
                sensor32 = sensor32[keep] if sensor32 is not None else None
        lap("prepare")
        local = Lattice((0.0, 0.0, 0.0), spec.block.cell_size, spec.block.shape)
        rule = orientation_rule(tiling, sensor32 is not None)
        init = None
        normals = None
        if rule != "sphere":
            normals = estimate_normals(xyz, tiling.normal_neighbors)
            away = None
            if rule == "outward":
                if centre is None:
                    raise ConfigError("orientation 'outward' needs the centre of the input")
                away = np.asarray(centre, np.float64) - spec.block.low_corner
            ref = sensor32.astype(np.float64) if rule == "sensor" else None
            normals = orient_normals(normals, xyz, ref, away_from=away)
            # under "up" the field's sign is checked against the normals the rule decides (not the walls, which
            # only a vote orients); a sensor orients even grazing ground reliably, so there every normal counts
            decided = orientation_decided(normals, xyz, ref, away_from=away) if rule == "up" else None
            if decided is not None and decided.sum() < max(20, 0.05 * len(xyz)):
                decided = None  # too few to outvote: every normal counts
            init = lambda band: plane_distance_init(band, xyz / band.lattice.cell_size, normals)  # noqa: E731
        lap("normals")
        fld = solve(xyz, local, solver, init=init, history_every=100)
        lap("solve")
        flipped = False
        if normals is not None:
            _, grads = fld.sample(xyz)
            if orientation_score(grads, normals, decided) < 0:
                fld.values *= -1
                flipped = True
        if tiling.bridge > 0 and rule in ("up", "sensor"):
            # ground is bridged where outside is up; a closed object cut into tiles ("outward") has no ground
            # with sensor origins the ground in a shadow stays open (nothing lies beyond it as the sensor sees it)
            fld, bridged = bridge_field(fld, xyz, BridgeRule(radius=tiling.bridge), sensor32)
            summary.update(bridged)
        lap("orient_and_bridge")
        off_bricks = np.asarray(spec.block.offset, np.int64) // BRICK
        field_sha = save_tile_field(field_path, fld.band.brick_coords.astype(np.int64) + off_bricks, fld.values,
                                    fld.band.flags)
        lap("save")
        hist = fld.info.get("history", [])
        summary.update(status="solved", flipped=flipped, orientation=rule, field_sha256=field_sha,
                       band_params=int(fld.band.n_params), bricks=int(fld.band.n_bricks),
                       level_bricks=[lv["band"]["bricks"] for lv in fld.info.get("levels", [])],
                       final_pull=hist[-1]["pull"] if hist else None,
                       loss_first=_loss_point(hist[0], fld.info) if hist else None,
                       loss_last=_loss_point(hist[-1], fld.info) if hist else None,
                       loss_curve=[(h["iteration"], h["pull"], h["tv"]) for h in hist],
                       field_path=str(field_path), device=fld.info.get("device"),
                       solve_levels=[{k: lv.get(k) for k in LEVEL_TIMINGS} for lv in fld.info.get("levels", [])])
    except GridPullError as exc:
        summary.update(status="failed", reason=str(exc))
    summary["time_s"] = time.perf_counter() - t0
    summary["peak_rss_mb"] = peak_rss_mb()
    return summary


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
