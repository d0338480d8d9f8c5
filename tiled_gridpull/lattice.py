"""The uniform lattice every field lives on.

A :class:`Lattice` is a float64 origin, a cell size and an integer block ``[offset, offset + shape)`` of vertex
indices. The same object serves both workflows:

* shapes: :meth:`Lattice.fit` puts ``R`` cells across the longest side of the cloud's bounding box (plus a margin),
  centred on the box;
* scenes: :meth:`Lattice.aligned` fixes a global origin and a cell size in metres; every tile is a
  :meth:`Lattice.block` of it, so overlapping tiles sample the very same vertices (they share ``origin`` and
  ``cell_size`` exactly and differ only in their integer ``offset``).

Coordinates
-----------
*world*: the input's own coordinates, float64 (metres, feet, UTM eastings ...).
*index*: ``(world - origin) / cell_size - offset``; vertex ``(i, j, k)`` of the block sits at index ``(i, j, k)``.
The solver works in index coordinates (float32, small numbers), so precision never depends on how far the
data is from the world origin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import ConfigError

__all__ = ["Lattice"]


@dataclass(frozen=True)
class Lattice:
    """A block of a uniform lattice.

    Parameters
    ----------
    origin : tuple of 3 float
        World position (float64) of global vertex index ``(0, 0, 0)``.
    cell_size : float
        Edge length of one cell, in world units.
    shape : tuple of 3 int
        Number of vertices of this block along x, y, z (cells are ``shape - 1``).
    offset : tuple of 3 int
        Global index of this block's vertex ``(0, 0, 0)``.
    """

    origin: tuple[float, float, float]
    cell_size: float
    shape: tuple[int, int, int]
    offset: tuple[int, int, int] = (0, 0, 0)

    def __post_init__(self) -> None:
        if len(self.origin) != 3 or not all(math.isfinite(float(v)) for v in self.origin):
            raise ConfigError(f"lattice origin must be 3 finite numbers, got {self.origin!r}")
        if not (math.isfinite(self.cell_size) and self.cell_size > 0):
            raise ConfigError(f"lattice cell size must be a positive number, got {self.cell_size!r}")
        if len(self.shape) != 3 or min(self.shape) < 2:
            raise ConfigError(f"lattice needs at least 2 vertices per axis, got shape {self.shape!r}")
        object.__setattr__(self, "origin", tuple(float(v) for v in self.origin))
        object.__setattr__(self, "cell_size", float(self.cell_size))
        object.__setattr__(self, "shape", tuple(int(v) for v in self.shape))
        object.__setattr__(self, "offset", tuple(int(v) for v in self.offset))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def fit(cls, points: np.ndarray, resolution: int = 256, margin: int = 4, pad: int = 0) -> Lattice:
        """Lattice for one shape: ``resolution`` cells across the padded longest side, centred on the bbox.

        Parameters
        ----------
        points : (N, 3) float array
            The cloud, world coordinates.
        resolution : int
            Cells across the longest side of the bounding box including ``margin`` cells on each side.
        margin : int
            Empty cells kept around the bounding box on every side (room for the pull band).
        pad : int
            Further empty cells on every side that do not count in ``resolution``: the cell size stays
            ``extent / (resolution - 2 margin)`` and the block grows by ``2 pad`` cells per axis.
        """
        if resolution < 2 * margin + 4:
            raise ConfigError(f"resolution must be at least {2 * margin + 4} (got {resolution})")
        if pad < 0:
            raise ConfigError(f"lattice pad must be >= 0, got {pad!r}")
        pts = np.asarray(points, dtype=np.float64)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        extent = float((hi - lo).max())
        if not extent > 0:
            raise ConfigError("cannot fit a lattice to a cloud with zero extent")
        cell = extent / (resolution - 2 * margin)
        centre = 0.5 * (lo + hi)
        cells = np.ceil((hi - lo) / cell - 1e-9).astype(np.int64) + 2 * (margin + int(pad))
        cells = np.maximum(cells, 1)
        origin = centre - 0.5 * cells * cell
        return cls(tuple(origin), cell, tuple(int(c) + 1 for c in cells))

    @classmethod
    def aligned(cls, bounds_lo: np.ndarray, bounds_hi: np.ndarray, cell_size: float,
                origin: tuple[float, float, float] | None = None, pad: int = 0) -> Lattice:
        """Lattice for a scene: cell size in world units, vertices on a global grid.

        ``origin`` defaults to the low corner snapped down to a multiple of ``cell_size`` (so two runs over
        different crops of the same data share vertices). The block covers ``[bounds_lo, bounds_hi]`` plus
        ``pad`` cells on each side.
        """
        if not (math.isfinite(cell_size) and cell_size > 0):
            raise ConfigError(f"voxel size must be a positive number, got {cell_size!r}")
        lo = np.asarray(bounds_lo, dtype=np.float64)
        hi = np.asarray(bounds_hi, dtype=np.float64)
        if origin is None:
            origin = tuple(np.floor(lo / cell_size) * cell_size)
        o = np.asarray(origin, dtype=np.float64)
        first = np.floor((lo - o) / cell_size).astype(np.int64) - pad
        last = np.ceil((hi - o) / cell_size).astype(np.int64) + pad
        last = np.maximum(last, first + 1)
        return cls(tuple(o), cell_size, tuple(int(v) for v in (last - first + 1)), tuple(int(v) for v in first))

    def block(self, lo: tuple[int, int, int] | np.ndarray, shape: tuple[int, int, int] | np.ndarray) -> Lattice:
        """Sub-block whose vertex ``(0, 0, 0)`` is this block's vertex ``lo`` (same global lattice)."""
        lo = np.asarray(lo, dtype=np.int64)
        return Lattice(self.origin, self.cell_size, tuple(int(v) for v in shape),
                       tuple(int(v) for v in np.asarray(self.offset) + lo))

    def coarsen(self, factor: int) -> Lattice:
        """The lattice with ``factor`` times larger cells sharing this block's vertex ``(0, 0, 0)``.

        Fine vertex ``i`` sits at coarse index ``i / factor``; the coarse block covers the fine one (one more
        coarse cell where the fine cell count is not a multiple of ``factor``). ``offset`` must be divisible by
        ``factor`` (tile blocks are multiples of 8).
        """
        factor = int(factor)
        if factor == 1:
            return self
        off = np.asarray(self.offset, dtype=np.int64)
        if factor < 1 or np.any(off % factor):
            raise ConfigError(f"cannot coarsen a block at offset {self.offset} by {factor}")
        cells = -(-(np.asarray(self.shape, dtype=np.int64) - 1) // factor)
        return Lattice(self.origin, self.cell_size * factor, tuple(int(c) + 1 for c in cells),
                       tuple(int(v) for v in off // factor))

    # ------------------------------------------------------------------ properties
    @property
    def n_cells(self) -> tuple[int, int, int]:
        """Cells per axis, ``shape - 1``."""
        return tuple(s - 1 for s in self.shape)

    @property
    def n_vertices(self) -> int:
        """Total vertices of the block (dense count; the band stores far fewer)."""
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def low_corner(self) -> np.ndarray:
        """World position of this block's vertex ``(0, 0, 0)``, (3,) float64."""
        return np.asarray(self.origin) + np.asarray(self.offset, dtype=np.float64) * self.cell_size

    @property
    def high_corner(self) -> np.ndarray:
        """World position of this block's last vertex, (3,) float64."""
        return self.low_corner + (np.asarray(self.shape, dtype=np.float64) - 1) * self.cell_size

    # ------------------------------------------------------------------ mappings
    def to_index(self, world: np.ndarray) -> np.ndarray:
        """World (N, 3) -> block index coordinates (N, 3) float64."""
        w = np.asarray(world, dtype=np.float64)
        return (w - np.asarray(self.origin)) / self.cell_size - np.asarray(self.offset, dtype=np.float64)

    def to_world(self, index: np.ndarray) -> np.ndarray:
        """Block index coordinates (N, 3) -> world (N, 3) float64 (exact inverse of :meth:`to_index`)."""
        i = np.asarray(index, dtype=np.float64)
        return (i + np.asarray(self.offset, dtype=np.float64)) * self.cell_size + np.asarray(self.origin)

    def to_local32(self, world: np.ndarray) -> np.ndarray:
        """World -> index coordinates as C-contiguous float32, the solver's working frame."""
        return np.ascontiguousarray(self.to_index(world), dtype=np.float32)

    def cell_of(self, world: np.ndarray) -> np.ndarray:
        """Integer cell (N, 3) int64 holding each world point (clipped into the block)."""
        idx = np.floor(self.to_index(world)).astype(np.int64)
        return np.clip(idx, 0, np.asarray(self.n_cells) - 1)

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        """Plain dict (JSON-ready) describing the lattice."""
        return {"origin": list(self.origin), "cell_size": self.cell_size, "shape": list(self.shape),
                "offset": list(self.offset)}

    @classmethod
    def from_dict(cls, d: dict) -> Lattice:
        """Inverse of :meth:`to_dict`."""
        return cls(tuple(d["origin"]), float(d["cell_size"]), tuple(d["shape"]), tuple(d.get("offset", (0, 0, 0))))
