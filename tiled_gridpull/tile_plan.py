"""The tile plan: the job lattice laid over the input's bounds, its tile grid and each tile's description.

Points in an overlap go to every tile whose block holds them (see :mod:`tiled_gridpull.tiling` for cores,
blocks and overlaps).
"""

from __future__ import annotations

import itertools

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ConfigError, InputError
from .kernels.mc import KEY_BITS_X, KEY_BITS_Y, KEY_BITS_Z
from .lattice import Lattice
from .tiling import TilingConfig

__all__ = ["TileSpec", "TilePlan", "plan_tiles", "check_lattice_span", "LatticeSpanError"]

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
    exact_offsets : bool
        Whether the spill file holds float64 offsets (a denoising job: :func:`tiled_gridpull.jobdir.spill_record`).
    halo_points : int
        Of ``n_points``, those outside the block, read for a denoising job's halo only (:attr:`block_points` are
        the ones the tile solves).
    attributes : tuple of (name, numpy type string)
        The per-point attributes of the tile's attribute spill file (:attr:`attributes_path`, one record per
        point of the spill file, in its order), carried onto the tile's mesh vertices; empty: none.
    attributes_sha256 : str
        SHA-256 of the attribute spill file (what the tile's mesh piece is keyed on).
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
    exact_offsets: bool = False
    halo_points: int = 0
    attributes: tuple = ()
    attributes_sha256: str = ""

    @property
    def attributes_path(self) -> str:
        """The attribute spill file, beside the spill file (``<tile>.attrs``); empty when none is kept."""
        return str(Path(self.points_path).with_suffix(".attrs")) if self.points_path and self.attributes else ""

    @property
    def block_points(self) -> int:
        """Points of the block itself: what the tile solves (``n_points`` less the halo's)."""
        return self.n_points - self.halo_points

    def in_block(self, local: np.ndarray) -> np.ndarray:
        """(N,) bool: which of ``local`` (N, 3; metres from the block's low corner, as spill files hold them) lie
        in the block, not in the halo a denoising job reads around it."""
        size = (np.asarray(self.block.shape, np.float64) - 1.0) * self.block.cell_size
        return np.all((local >= 0.0) & (local <= size), axis=1)

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
        if self.exact_offsets:  # only when set: manifests of other jobs stay as they were
            d["exact_offsets"] = True
            d["halo_points"] = self.halo_points
        if self.attributes:  # likewise
            d["attributes"] = [list(a) for a in self.attributes]
            d["attributes_sha256"] = self.attributes_sha256
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TileSpec:
        return cls(tuple(d["index"]), tuple(d["core_lo"]), tuple(d["core_hi"]), Lattice.from_dict(d["block"]),
                   int(d["n_points"]), d["points_path"], bool(d["has_sensor"]), tuple(d["mesh_lo"]),
                   tuple(d["mesh_hi"]), str(d.get("points_sha256", "")), int(d.get("occupied_bricks", 0)),
                   bool(d.get("exact_offsets", False)), int(d.get("halo_points", 0)),
                   tuple((str(n), str(t)) for n, t in d.get("attributes", ())), str(d.get("attributes_sha256", "")))

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
        kw.setdefault("exact_offsets", self.exact_offsets)
        return TileSpec(tuple(int(v) for v in index), tuple(int(v) for v in core_lo), tuple(int(v) for v in core_hi),
                        block, mesh_lo=tuple(int(v) for v in mesh_lo), mesh_hi=tuple(int(v) for v in mesh_hi), **kw)

    @property
    def exact_offsets(self) -> bool:
        """Whether the tiles' spill files hold float64 offsets: a denoising job's, which reads a halo
        (:func:`tiled_gridpull.jobdir.spill_record`)."""
        return self.config.halo > 0

    @property
    def reach_cells(self) -> int:
        """How far past its core a tile receives points: the overlap, plus the halo its denoising reads."""
        return self.config.overlap_cells + self.config.halo

    def tile_span(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First and last tile (inclusive, per axis) whose block (core +- overlap, + halo) may reach into each box.

        Parameters
        ----------
        lo, hi : (N, 3) float64
            Boxes' corners in the job lattice's index coordinates (a point is the box ``lo == hi``).

        Returns
        -------
        first, last : (N, 3) int64
            Clipped to the tile grid, so points beyond the lattice's edge fall to the border tiles.
        """
        T, O = self.config.tile_cells, self.reach_cells
        top = np.asarray(self.tile_range) - 1
        first = np.clip(np.floor((np.asarray(lo) - O) / T).astype(np.int64), 0, top)
        last = np.clip(np.floor((np.asarray(hi) + O) / T).astype(np.int64), 0, top)
        return first, last

    def owner_of(self, index_coords: np.ndarray) -> np.ndarray:
        """(N, 3) int64: the one tile whose core holds each point (clipped to the grid), so that counting the
        points each tile owns counts every point once, whatever the overlaps copy."""
        top = np.asarray(self.tile_range) - 1
        return np.clip(np.floor(np.asarray(index_coords) / self.config.tile_cells).astype(np.int64), 0, top)

    def tiles_of(self, index_coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every (point, tile) pair whose block (with its halo, :attr:`reach_cells`) holds the point.

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
        T, O = self.config.tile_cells, self.reach_cells
        lo, hi = self.tile_span(index_coords, index_coords)
        pts, tiles = [], []
        # blocks overlap by at most half a tile, so without a halo a point lies in at most 2 tiles per axis; a
        # halo (denoising) can make that 3
        span = int((hi - lo).max(initial=0)) + 1
        for offset in itertools.product(range(span), repeat=3):
            t = lo + np.asarray(offset, np.int64)
            # each (point, tile) pair once: tiles past the last of the point's span do not exist for it
            keep = np.all(t <= hi, axis=1)
            # the point must lie inside the tile's block (core +- O, halo included) on every axis
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
