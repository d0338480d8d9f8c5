"""Tiles of a global lattice: the plan, the streaming partition of the points, and the per-tile spill files.

A scene is covered by a global :class:`~tiled_gridpull.lattice.Lattice` (float64 origin, cell size in metres).
Tile ``(i, j, k)`` owns the *core* cells ``[i T, (i+1) T)`` (and likewise on y, z; ``T`` = ``tile_cells``,
relative to the job's lattice offset) and is solved on the *block* that extends its core by ``O`` =
``overlap_cells`` on every side. Points in an overlap go to every tile whose block holds them. ``T`` and ``O``
are multiples of the brick size, so every block starts on the global brick grid and overlapping tiles store
the very same vertices in the very same bricks.

Spill files hold each tile's points as float32 coordinates relative to the block's low corner (tile-local
metres, where float32 keeps micrometres), plus the sensor origin of every point when it is known.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import ConfigError, InputError
from .io.atomic import atomic_open, open_no_follow, replace_file, write_json
from .kernels import BRICK
from .lattice import Lattice

if TYPE_CHECKING:
    from .blend import TileField
    from .config import SolverConfig

__all__ = ["TilingConfig", "TileSpec", "TilePlan", "plan_tiles", "partition", "read_tile_points", "read_occupancy",
           "ORIENTATIONS", "check_compatible", "solve_tile"]

ORIENTATIONS = ("auto", "sensor", "up", "outward", "sphere")
MAX_TILE_CELLS = 1 << 18  # a block (core + 2 overlaps) must stay within the 2^19 vertices edge keys count on z


@dataclass(frozen=True)
class TilingConfig:
    """How a scene is cut into tiles and stitched.

    Attributes
    ----------
    voxel_size : float
        Cell size in world units (metres for most LiDAR; feet for data in feet).
    tile_size : float
        Core size of a tile in world units (rounded to a multiple of 8 cells).
    overlap : float
        Extra margin solved around each core, in world units (rounded up to a multiple of 8 cells); the
        partition-of-unity blend runs over twice this width around every shared face.
    min_points : int
        Tiles with fewer points are skipped and reported (too little data for a solve).
    trim_distance : float
        Faces farther than this many cells from every input point are removed (the same absolute distance in
        every tile, so trimming never opens a crack along a tile border).
    orientation : {"auto", "sensor", "up", "outward", "sphere"}
        Which side is outside: facing the sensor (per-point sensor origins, e.g. KITTI), facing up (airborne
        LAS), facing away from the centre of the whole input (one closed, roughly star-shaped object cut into
        tiles), or the paper's sphere at each tile's own centre (kept to show why it fails: neighbouring tiles
        can disagree). ``auto`` picks sensor when sensor origins are known, else up.
    normal_neighbors : int
        Neighbours used to estimate point normals for the initial field.
    drop_outliers : bool
        Drop the points far from the rest of the input before planning (:mod:`tiled_gridpull.outliers`: outside
        the box of all but 0.1 % of a sample per axis, widened by half its size and at least a tile).
    """

    voxel_size: float = 0.1
    tile_size: float = 25.6
    overlap: float = 3.2
    min_points: int = 100
    trim_distance: float = 3.0
    orientation: str = "auto"
    normal_neighbors: int = 16
    drop_outliers: bool = False

    def __post_init__(self) -> None:
        from .config import finite_number

        for name in ("voxel_size", "tile_size", "overlap", "trim_distance"):
            object.__setattr__(self, name, finite_number(name, getattr(self, name)))
        if self.voxel_size <= 0:
            raise ConfigError(f"voxel_size must be positive, got {self.voxel_size!r}")
        if self.tile_size <= 0:
            raise ConfigError(f"tile_size must be positive, got {self.tile_size!r}")
        if self.overlap < 0:
            raise ConfigError(f"overlap must be >= 0, got {self.overlap!r}")
        if self.trim_distance < 0:
            raise ConfigError(f"trim_distance must be >= 0, got {self.trim_distance!r}")
        for name in ("min_points", "normal_neighbors"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1 or v >= 1 << 62:
                shown = f"an integer of {v.bit_length()} bits" if isinstance(v, int) and v >= 1 << 62 else repr(v)
                raise ConfigError(f"{name} must be a positive integer, got {shown}")
        if not isinstance(self.drop_outliers, bool):
            raise ConfigError(f"drop_outliers must be true or false, got {self.drop_outliers!r}")
        if self.orientation not in ORIENTATIONS:
            raise ConfigError(f"orientation must be one of {', '.join(ORIENTATIONS)}; got {self.orientation!r}")
        for name in ("tile_size", "overlap"):
            cells = getattr(self, name) / self.voxel_size
            if not cells <= MAX_TILE_CELLS:  # also catches inf
                raise ConfigError(f"{name} {getattr(self, name):g} is {cells:.3g} cells of voxel_size "
                                  f"{self.voxel_size:g}: at most {MAX_TILE_CELLS:,} (the range of edge keys)")
        if self.tile_cells < BRICK:
            raise ConfigError(f"tile_size {self.tile_size} is less than 8 cells of {self.voxel_size}")
        if 2 * self.overlap_cells > self.tile_cells:
            raise ConfigError(f"overlap {self.overlap} (={self.overlap_cells} cells) must be at most half the tile "
                              f"size {self.tile_size} (={self.tile_cells} cells)")
        if self.trim_distance > self.overlap_cells and self.trim_distance > 0:
            raise ConfigError(f"trim_distance ({self.trim_distance} cells) must not exceed the overlap "
                              f"({self.overlap_cells} cells): a tile must see every point that can keep a face")

    @property
    def tile_cells(self) -> int:
        """Core size in cells (a multiple of 8)."""
        return max(BRICK, int(round(self.tile_size / self.voxel_size / BRICK)) * BRICK)

    @property
    def overlap_cells(self) -> int:
        """Overlap in cells (a multiple of 8, rounded up)."""
        return int(math.ceil(self.overlap / self.voxel_size / BRICK - 1e-9)) * BRICK

    def to_dict(self) -> dict:
        """Plain dict of the settings (plus the derived cell counts)."""
        d = asdict(self)
        d["tile_cells"] = self.tile_cells
        d["overlap_cells"] = self.overlap_cells
        return d


def check_compatible(tiling: TilingConfig, solver: "SolverConfig") -> None:
    """Refuse settings whose neighbouring tiles could disagree on a shared face.

    Two tiles build their bands from the points of their own blocks; on a shared face the bands (and so the
    cells marching cubes may use) agree only if every point within ``M2 + 1`` cells of the face is in both
    blocks, i.e. ``overlap >= M2 + 1`` cells for the finest level's band.
    """
    if solver.mode == "udf":
        raise ConfigError("mode udf applies to one-shape mode (tiles orient estimated normals and trim "
                          "faces farther than trim_distance from the points: open ground stays open)")
    if solver.noise_cells > 0:
        raise ConfigError("noise_cells applies to one-shape mode (tiled mode fixes the cell size with voxel_size)")
    if solver.denoise > 0:
        raise ConfigError("denoise applies to one-shape mode (tiles are not denoised; it is untested across tile "
                          "borders)")
    if solver.normal_weight > 0:
        raise ConfigError("normal_weight applies to one-shape mode (tiles orient estimated normals instead)")
    m2 = solver.refine_m2 if solver.levels > 1 else solver.m2
    if tiling.overlap_cells < m2 + 1:
        raise ConfigError(f"overlap of {tiling.overlap_cells} cells is too small for a TV band of {m2} cells at "
                          f"the finest level: use overlap >= {(m2 + 1) * tiling.voxel_size:g} "
                          f"({m2 + 1} cells) or a narrower band")


@dataclass(frozen=True)
class TileSpec:
    """A small, picklable description of one tile (travels to Dask workers instead of arrays).

    Attributes
    ----------
    index : (i, j, k)
        Tile index in the tile grid.
    core_lo, core_hi : (3,) int
        Core cells ``[core_lo, core_hi)`` in global cell indices of the job lattice.
    block : Lattice
        The solve block (core plus overlap), a block of the job lattice.
    n_points : int
        Points in the block (after the partition pass).
    points_path : str
        Spill file of the tile's points.
    has_sensor : bool
        Whether the spill file holds sensor origins.
    mesh_lo, mesh_hi : (3,) int
        Cells this tile meshes, ``[mesh_lo, mesh_hi)``: its core, extended to the block's border on the sides
        where no tile follows (so a surface just beyond the outermost points is not cut off).
    points_sha256 : str
        SHA-256 of the spill file's content (what the tile's results are keyed on when a job is resumed).
    occupied_bricks : int
        Bricks (8^3 cells) of the block that hold at least one point (see :func:`read_occupancy`).
    """

    index: tuple[int, int, int]
    core_lo: tuple[int, int, int]
    core_hi: tuple[int, int, int]
    block: Lattice
    n_points: int = 0
    points_path: str = ""
    has_sensor: bool = False
    mesh_lo: tuple[int, int, int] = (0, 0, 0)
    mesh_hi: tuple[int, int, int] = (0, 0, 0)
    points_sha256: str = ""
    occupied_bricks: int = 0

    @property
    def name(self) -> str:
        """A stable name, e.g. ``tile_3_-1_0``."""
        return "tile_" + "_".join(str(v) for v in self.index)

    def core_in_block(self) -> tuple[np.ndarray, np.ndarray]:
        """Core cell range ``[lo, hi)`` in the block's own index coordinates."""
        off = np.asarray(self.block.offset)
        return np.asarray(self.core_lo) - off, np.asarray(self.core_hi) - off

    def to_dict(self) -> dict:
        d = {"index": list(self.index), "core_lo": list(self.core_lo), "core_hi": list(self.core_hi),
             "block": self.block.to_dict(), "n_points": self.n_points, "points_path": self.points_path,
             "has_sensor": self.has_sensor, "mesh_lo": list(self.mesh_lo), "mesh_hi": list(self.mesh_hi),
             "points_sha256": self.points_sha256, "occupied_bricks": self.occupied_bricks}
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TileSpec":
        return cls(tuple(d["index"]), tuple(d["core_lo"]), tuple(d["core_hi"]), Lattice.from_dict(d["block"]),
                   int(d["n_points"]), d["points_path"], bool(d["has_sensor"]), tuple(d["mesh_lo"]),
                   tuple(d["mesh_hi"]), str(d.get("points_sha256", "")), int(d.get("occupied_bricks", 0)))

    @property
    def occupancy_path(self) -> str:
        """File of the block's occupied-brick mask, beside the spill file."""
        return str(Path(self.points_path).with_suffix(".occ.npy")) if self.points_path else ""


@dataclass(eq=False)
class TilePlan:
    """The job lattice and its tile grid.

    Attributes
    ----------
    lattice : Lattice
        Job lattice: origin snapped to the cell size, block covering all points; its offset is the global
        index of the first tile's core corner.
    config : TilingConfig
    tile_range : (3,) int
        Tiles along each axis.
    bounds : (2, 3) float64
        Bounding box of the input points.
    n_points : int
    """

    lattice: Lattice
    config: TilingConfig
    tile_range: tuple[int, int, int]
    bounds: np.ndarray
    n_points: int
    tiles: dict = field(default_factory=dict)

    def spec(self, index: tuple[int, int, int], **kw) -> TileSpec:
        """Spec of tile ``index`` (block = core +- overlap, as a block of the job lattice)."""
        T, O = self.config.tile_cells, self.config.overlap_cells
        off = np.asarray(self.lattice.offset)
        core_lo = off + np.asarray(index) * T
        core_hi = core_lo + T
        block = Lattice(self.lattice.origin, self.lattice.cell_size, tuple(int(v) for v in (np.full(3, T + 2 * O + 1))),
                        tuple(int(v) for v in core_lo - O))
        idx = np.asarray(index)
        mesh_lo = np.where(idx == 0, core_lo - O, core_lo)
        mesh_hi = np.where(idx == np.asarray(self.tile_range) - 1, core_hi + O, core_hi)
        return TileSpec(tuple(int(v) for v in index), tuple(int(v) for v in core_lo), tuple(int(v) for v in core_hi),
                        block, mesh_lo=tuple(int(v) for v in mesh_lo), mesh_hi=tuple(int(v) for v in mesh_hi), **kw)

    def tiles_of(self, index_coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every (point, tile) pair whose block holds the point.

        Parameters
        ----------
        index_coords : (N, 3) float64
            Points in the job lattice's index coordinates.

        Returns
        -------
        point : (M,) int64
            Point index of each pair.
        tile : (M, 3) int64
            Tile index of each pair.
        """
        T, O = self.config.tile_cells, self.config.overlap_cells
        rng = np.asarray(self.tile_range)
        lo = np.floor((index_coords - O) / T).astype(np.int64)
        hi = np.floor((index_coords + O) / T).astype(np.int64)
        lo = np.clip(lo, 0, rng - 1)
        hi = np.clip(hi, 0, rng - 1)
        pts, tiles = [], []
        n = len(index_coords)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    t = np.stack([np.where(dx, hi[:, 0], lo[:, 0]), np.where(dy, hi[:, 1], lo[:, 1]),
                                  np.where(dz, hi[:, 2], lo[:, 2])], axis=1)
                    # a combination exists only once: skip repeats where lo == hi on a chosen axis
                    keep = np.ones(n, bool)
                    for axis, d in enumerate((dx, dy, dz)):
                        if d:
                            keep &= hi[:, axis] != lo[:, axis]
                    # the point must lie inside the tile's block (core +- O) on every axis
                    core_lo = t * T
                    inside = np.all((index_coords >= core_lo - O) & (index_coords <= core_lo + T + O), axis=1)
                    sel = np.flatnonzero(keep & inside)
                    pts.append(sel)
                    tiles.append(t[sel])
        return np.concatenate(pts), np.concatenate(tiles)

    def to_dict(self) -> dict:
        return {"lattice": self.lattice.to_dict(), "config": self.config.to_dict(),
                "tile_range": list(self.tile_range), "bounds": self.bounds.tolist(), "n_points": self.n_points}


class LatticeSpanError(InputError):
    """Bounds too wide for the global lattice (usually a few stray points: see :mod:`tiled_gridpull.outliers`)."""


def check_lattice_span(lo: np.ndarray, hi: np.ndarray, cell: float) -> None:
    """Refuse, when planning, bounds whose global lattice marching cubes cannot key (2^21 x 2^21 x 2^19
    vertices: 64-bit edge keys), before any point is partitioned or solved.

    The usual cause is a few stray points far from the rest (a ``(0, 0, 0)`` in a UTM cloud) stretching the
    bounds; the cell counts are compared as floats, so an extent of 1e21 cells is refused, not wrapped."""
    from .kernels.mc import KEY_BITS_X, KEY_BITS_Y, KEY_BITS_Z

    span = (np.asarray(hi, np.float64) - np.asarray(lo, np.float64)) / cell + 2
    limit = np.array([2.0 ** KEY_BITS_X, 2.0 ** KEY_BITS_Y, 2.0 ** KEY_BITS_Z])
    if np.all(span < limit):
        return
    size = " x ".join(f"{v:.4g}" for v in np.asarray(hi) - np.asarray(lo))
    cells = " x ".join(f"{v:.3g}" for v in span)
    raise LatticeSpanError(f"the points span {size} (units of the input) = {cells} cells of {cell:g}, more than the "
                     f"lattice can hold (2^{KEY_BITS_X} x 2^{KEY_BITS_Y} x 2^{KEY_BITS_Z}): stray points far "
                     f"from the rest? Remove them, or use a larger voxel_size")


def plan_tiles(bounds: np.ndarray, n_points: int, config: TilingConfig) -> TilePlan:
    """Lay the global lattice and the tile grid over a bounding box.

    The lattice origin is the low corner snapped down to a multiple of the cell size (so crops of the same data
    share vertices), and the first tile's core starts at the first cell of the box.
    """
    lo = np.asarray(bounds[0], dtype=np.float64)
    hi = np.asarray(bounds[1], dtype=np.float64)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ConfigError("cannot plan tiles over non-finite bounds")
    cell = config.voxel_size
    origin = np.floor(lo / cell) * cell
    check_lattice_span(lo, hi, cell)
    first = np.floor((lo - origin) / cell).astype(np.int64)
    last = np.floor((hi - origin) / cell).astype(np.int64) + 1
    T = config.tile_cells
    rng = np.maximum(1, -(-(last - first) // T))
    shape = rng * T + 1
    lattice = Lattice(tuple(origin), cell, tuple(int(v) for v in shape), tuple(int(v) for v in first))
    return TilePlan(lattice, config, tuple(int(v) for v in rng), np.stack([lo, hi]), int(n_points))


_RECORD = np.dtype([("xyz", "<f4", (3,))])
_RECORD_SENSOR = np.dtype([("xyz", "<f4", (3,)), ("sensor", "<f4", (3,))])


def partition(chunks: Iterable, plan: TilePlan, out_dir: str | Path | None, has_sensor: bool,
              flush_points: int = 2_000_000, occupancy: dict | None = None) -> list[TileSpec]:
    """Stream point chunks into per-tile spill files (the partition pass).

    Parameters
    ----------
    chunks : iterable of PointCloud
        World coordinates (float64) and, when ``has_sensor``, sensor origins.
    plan : TilePlan
    out_dir : path or None
        Directory for ``<tile>.points`` files (created; existing spill files there are replaced) and their
        ``<tile>.occ.npy`` occupied-brick masks. ``None`` counts only (a dry run): no file is written.
    has_sensor : bool
    flush_points : int
        Buffered (point, tile) pairs before writing to disk: bounds the memory of the pass.
    occupancy : dict, optional
        Filled with ``{tile index: (BX, BY, BZ) bool}``, the bricks of each block that hold a point (what the
        memory estimate reads; also saved beside the spill files).

    Returns
    -------
    list of TileSpec
        Tiles that received at least one point, with counts, spill paths and the SHA-256 of each spill file.
    """
    import hashlib

    write = out_dir is not None
    out = Path(out_dir) if write else None
    if write:
        out.mkdir(parents=True, exist_ok=True)
    dtype = _RECORD_SENSOR if has_sensor else _RECORD
    counts: dict[tuple, int] = {}
    buffers: dict[tuple, list] = {}
    hashes: dict[tuple, "hashlib._Hash"] = {}
    occ: dict[tuple, np.ndarray] = {}
    bshape = tuple(int(v) for v in -(-np.asarray(plan.spec((0, 0, 0)).block.shape) // BRICK))
    buffered = 0
    tmp_paths: dict[tuple, Path] = {}

    def flush() -> None:
        nonlocal buffered
        for key, parts in buffers.items():
            h = hashes.setdefault(key, hashlib.sha256())
            if not write:
                for part in parts:
                    h.update(part.tobytes())
                continue
            path = tmp_paths.setdefault(key, out / f".{plan.spec(key).name}.points.partial")
            with open_no_follow(path, "ab") as fh:
                for part in parts:
                    data = part.tobytes()
                    h.update(data)
                    fh.write(data)
        buffers.clear()
        buffered = 0

    started = False
    for chunk in chunks:
        if not started and write:
            for stale in out.glob(".*.points.partial"):
                stale.unlink()
        started = True
        xyz = np.asarray(chunk.xyz, dtype=np.float64)
        if len(xyz) == 0:
            continue
        # index coordinates relative to the first tile's core corner
        pidx, tiles = plan.tiles_of(plan.lattice.to_index(xyz))
        if len(pidx) == 0:
            continue
        key_arr = (tiles[:, 0] * plan.tile_range[1] + tiles[:, 1]) * plan.tile_range[2] + tiles[:, 2]
        order = np.argsort(key_arr, kind="stable")
        key_sorted = key_arr[order]
        starts = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
        ends = np.r_[starts[1:], len(order)]
        for s, e in zip(starts, ends):
            t = tuple(int(v) for v in tiles[order[s]])
            sel = pidx[order[s:e]]
            spec = plan.spec(t)
            corner = spec.block.low_corner
            rec = np.empty(len(sel), dtype)
            rec["xyz"] = xyz[sel] - corner
            if has_sensor:
                rec["sensor"] = np.asarray(chunk.sensor, dtype=np.float64)[sel] - corner
            # the cells the solver will see (tile-local float32 / cell size), as bricks
            cells = np.floor(rec["xyz"].astype(np.float64) / spec.block.cell_size).astype(np.int64)
            cells = cells[np.all((cells >= 0) & (cells < np.asarray(spec.block.shape) - 1), axis=1)] >> 3
            grid = occ.get(t)
            if grid is None:
                grid = occ[t] = np.zeros(bshape, bool)
            grid[cells[:, 0], cells[:, 1], cells[:, 2]] = True
            buffers.setdefault(t, []).append(rec)
            counts[t] = counts.get(t, 0) + len(sel)
            buffered += len(sel)
        if buffered >= flush_points:
            flush()
    flush()
    specs = []
    for t in sorted(counts):
        spec = plan.spec(t)
        grid = occ[t]
        path = ""
        if write:
            final = out / f"{spec.name}.points"
            replace_file(tmp_paths[t], final)
            path = str(final)
            with atomic_open(final.with_suffix(".occ.npy")) as fh:
                np.save(fh, np.packbits(grid.ravel()))
        if occupancy is not None:
            occupancy[t] = grid
        specs.append(plan.spec(t, n_points=counts[t], points_path=path, has_sensor=has_sensor,
                               points_sha256=hashes[t].hexdigest(), occupied_bricks=int(grid.sum())))
    return specs


def read_occupancy(spec: TileSpec) -> np.ndarray:
    """The block's occupied-brick mask written by :func:`partition`: (BX, BY, BZ) bool."""
    bshape = tuple(int(v) for v in -(-np.asarray(spec.block.shape) // BRICK))
    bits = np.load(spec.occupancy_path)
    return np.unpackbits(bits, count=int(np.prod(bshape))).astype(bool).reshape(bshape)


def read_tile_points(spec: TileSpec) -> tuple[np.ndarray, np.ndarray | None]:
    """A tile's points and sensor origins as tile-local float32 metres (relative to ``spec.block.low_corner``).

    Returns
    -------
    xyz : (N, 3) float32
    sensor : (N, 3) float32 or None
    """
    dtype = _RECORD_SENSOR if spec.has_sensor else _RECORD
    rec = np.fromfile(spec.points_path, dtype=dtype)
    xyz = np.ascontiguousarray(rec["xyz"])
    sensor = np.ascontiguousarray(rec["sensor"]) if spec.has_sensor else None
    return xyz, sensor


def write_manifest(path: str | Path, plan: TilePlan, specs: list[TileSpec], extra: dict | None = None) -> None:
    """Write the tile manifest (plan, per-tile counts and bounds) atomically."""
    data = {"plan": plan.to_dict(), "tiles": [s.to_dict() for s in specs]}
    if extra:
        data.update(extra)
    write_json(path, data)


def read_manifest(path: str | Path) -> tuple[dict, list[TileSpec]]:
    """Read a tile manifest: the raw dict and the tile specs."""
    data = json.loads(Path(path).read_text())
    return data, [TileSpec.from_dict(d) for d in data["tiles"]]


# ---------------------------------------------------------------------------------------------------------------
# per-tile processing (called by the sequential driver and by the Dask tasks alike)


def _orientation_rule(tiling: TilingConfig, has_sensor: bool) -> str:
    if tiling.orientation == "auto":
        return "sensor" if has_sensor else "up"
    if tiling.orientation == "sensor" and not has_sensor:
        raise ConfigError("orientation 'sensor' needs sensor origins (KITTI sequences); use 'up' or 'auto'")
    return tiling.orientation


def solve_tile(spec: TileSpec, tiling: TilingConfig, solver: "SolverConfig", field_path: str | Path,
               centre: tuple[float, float, float] | None = None) -> dict:
    """Solve one tile and write its field; returns a small summary (never raises for data reasons).

    The field is solved in a tile-local frame (metres from the block's low corner) so float32 is exact, and
    written with global brick coordinates for the blend pass. Orientation follows ``tiling.orientation``; after
    the solve the field is flipped if it disagrees with the oriented normals (the loss is sign-blind, so the
    initial orientation could in principle be lost; every tile applies the same rule, so tiles agree).
    ``centre`` (world) is the input's bounding-box centre, used by the ``outward`` rule.
    """
    import time

    from .errors import GridPullError
    from .initial_field import plane_distance_init
    from .normals import estimate_normals, orient_normals, orientation_score
    from .solver import solve

    t0 = time.perf_counter()
    reset_peak_rss()
    summary: dict = {"tile": spec.name, "index": list(spec.index), "points": spec.n_points}
    try:
        xyz32, sensor32 = read_tile_points(spec)
        xyz = xyz32.astype(np.float64)
        keep = np.unique(xyz32.view(np.dtype((np.void, 12))).ravel(), return_index=True)[1]
        if len(keep) < len(xyz):
            keep.sort()
            summary["duplicates_dropped"] = int(len(xyz) - len(keep))
            xyz = xyz[keep]
            sensor32 = sensor32[keep] if sensor32 is not None else None
        summary["points_used"] = int(len(xyz))
        if len(xyz) < tiling.min_points:
            summary.update(status="skipped", reason=f"{len(xyz)} points (< min_points {tiling.min_points})")
            summary["time_s"] = time.perf_counter() - t0
            summary["peak_rss_mb"] = peak_rss_mb()
            return summary
        local = Lattice((0.0, 0.0, 0.0), spec.block.cell_size, spec.block.shape)
        rule = _orientation_rule(tiling, sensor32 is not None)
        init = None
        normals = None
        if rule != "sphere":
            normals = estimate_normals(xyz, tiling.normal_neighbors)
            away = None
            if rule == "outward":
                if centre is None:
                    raise ConfigError("orientation 'outward' needs the centre of the input")
                away = np.asarray(centre, np.float64) - spec.block.low_corner
            normals = orient_normals(normals, xyz, sensor32.astype(np.float64) if rule == "sensor" else None,
                                     away_from=away)
            init = lambda band: plane_distance_init(band, xyz / band.lattice.cell_size, normals)  # noqa: E731
        fld = solve(xyz, local, solver, init=init, history_every=100)
        flipped = False
        if normals is not None:
            _, grads = fld.sample(xyz)
            if orientation_score(grads, normals) < 0:
                fld.values *= -1
                flipped = True
        off_bricks = np.asarray(spec.block.offset, np.int64) // BRICK
        field_sha = save_tile_field(field_path, fld.band.brick_coords.astype(np.int64) + off_bricks, fld.values,
                                    fld.band.flags)
        hist = fld.info.get("history", [])
        summary.update(status="solved", flipped=flipped, orientation=rule, field_sha256=field_sha,
                       band_params=int(fld.band.n_params), bricks=int(fld.band.n_bricks),
                       level_bricks=[lv["band"]["bricks"] for lv in fld.info.get("levels", [])],
                       final_pull=hist[-1]["pull"] if hist else None,
                       loss_first=_loss_point(hist[0], fld.info) if hist else None,
                       loss_last=_loss_point(hist[-1], fld.info) if hist else None,
                       loss_curve=[(h["iteration"], h["pull"], h["tv"]) for h in hist],
                       field_path=str(field_path))
    except GridPullError as exc:
        summary.update(status="failed", reason=str(exc))
    summary["time_s"] = time.perf_counter() - t0
    summary["peak_rss_mb"] = peak_rss_mb()
    return summary


def _loss_point(record: dict, info: dict) -> dict:
    """The part of a solver history record kept in a tile summary: pull and TV losses in cells of the record's
    level, that level's ``cell_size`` (world units) and the pull loss in world units (``pull_world``)."""
    level = int(record["level"])
    levels = info.get("levels", [])
    cell = float(levels[level]["cell_size"]) if level < len(levels) else float("nan")
    return {"iteration": int(record["iteration"]), "level": level, "pull": float(record["pull"]),
            "tv": float(record["tv"]), "cell_size": cell, "pull_world": float(record["pull"]) * cell}


def peak_rss_mb() -> float:
    """Peak resident memory of this process (MB) since :func:`reset_peak_rss` (Linux), else since it started."""
    import resource
    import sys

    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def reset_peak_rss() -> bool:
    """Restart the peak-memory count of this process at its current size (Linux ``clear_refs``), so that the
    peak a task reports is its own and not that of an earlier task of the same worker. False if unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def field_checksum(brick_coords: np.ndarray, values: np.ndarray, flags: np.ndarray) -> str:
    """SHA-256 of a tile field's arrays (content, not file bytes: ``.npz`` files carry timestamps)."""
    import hashlib

    h = hashlib.sha256()
    for a in (brick_coords, values, flags):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_tile_field(path: str | Path, brick_coords: np.ndarray, values: np.ndarray, flags: np.ndarray) -> str:
    """Write a tile field (global brick coordinates, values in cells, flags) atomically as ``.npz``; returns
    its :func:`field_checksum`."""
    from .io.atomic import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, brick_coords=brick_coords, values=values, flags=flags)
    return field_checksum(brick_coords, values, flags)


def load_tile_field(path: str | Path, spec: TileSpec, overlap: int) -> "TileField":
    """Read a tile field as a :class:`~tiled_gridpull.blend.TileField`."""
    from .blend import TileField

    with np.load(path) as z:
        lo = np.asarray(spec.block.offset, np.int64)
        return TileField(tuple(spec.index), lo, lo + np.asarray(spec.block.shape, np.int64) - 1,
                         z["brick_coords"].astype(np.int64), z["values"], z["flags"], int(overlap))
