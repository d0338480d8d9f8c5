"""How a scene is cut into tiles: :class:`TilingConfig` and the check that a solver configuration fits it.

A scene is covered by a global :class:`~tiled_gridpull.lattice.Lattice` (float64 origin, cell size in metres).
Tile ``(i, j, k)`` owns the *core* cells ``[i T, (i+1) T)`` (and likewise on y, z; ``T`` = ``tile_cells``,
relative to the job's lattice offset) and is solved on the *block* that extends its core by ``O`` =
``overlap_cells`` on every side. ``T`` and ``O`` are multiples of the brick size, so every block starts on the
global brick grid and overlapping tiles store the very same vertices in the very same bricks.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from .config import SolverConfig, finite_number
from .errors import ConfigError
from .kernels import BRICK

__all__ = ["TilingConfig", "check_compatible", "ORIENTATIONS", "MAX_TILE_CELLS", "DEFAULT_TILE_CELLS",
           "DEFAULT_OVERLAP_CELLS"]

ORIENTATIONS = ("auto", "sensor", "up", "outward", "sphere")
MAX_TILE_CELLS = 1 << 18  # a block (core + 2 overlaps) must stay within the 2^19 vertices edge keys count on z
#: Tile core and overlap when not given, in cells: they follow the cell size. 256 cells keep a dense street tile
#: within a worker's memory and its solve around half a minute; 32 cells of overlap is the finest TV band
#: (M2 + 1 = 9 cells) rounded up to bricks, with room for the blend's ramp (docs/tiling.md).
DEFAULT_TILE_CELLS = 256
DEFAULT_OVERLAP_CELLS = 32


@dataclass(frozen=True)
class TilingConfig:
    """How a scene is cut into tiles and stitched.

    Attributes
    ----------
    voxel_size : float
        Cell size in world units (metres for most LiDAR; feet for data in feet).
    tile_size : float, optional
        Core size of a tile in world units (rounded to a multiple of 8 cells). Default (None):
        ``DEFAULT_TILE_CELLS`` cells, so the tile follows the cell size.
    overlap : float, optional
        Extra margin solved around each core, in world units (rounded up to a multiple of 8 cells); the
        partition-of-unity blend runs over twice this width around every shared face. Default (None):
        ``DEFAULT_OVERLAP_CELLS`` cells.
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
    derived : tuple of str
        Which of ``tile_size`` and ``overlap`` were not given and so follow the cell size (set here; recorded in
        the sidecar and shown by ``--dry-run``).
    """

    voxel_size: float = 0.1
    tile_size: float | None = None
    overlap: float | None = None
    min_points: int = 100
    trim_distance: float = 3.0
    orientation: str = "auto"
    normal_neighbors: int = 16
    drop_outliers: bool = False
    derived: tuple[str, ...] = field(default=(), compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "voxel_size", finite_number("voxel_size", self.voxel_size))
        derived = [name for name in self.derived if name in ("tile_size", "overlap")]
        for name, cells in (("tile_size", DEFAULT_TILE_CELLS), ("overlap", DEFAULT_OVERLAP_CELLS)):
            if getattr(self, name) is None:
                # exact: the cell counts are powers of two
                object.__setattr__(self, name, cells * self.voxel_size if self.voxel_size > 0 else 0.0)
                derived.append(name)
        object.__setattr__(self, "derived", tuple(n for n in ("tile_size", "overlap") if n in derived))
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
        d["derived"] = list(self.derived)
        d["tile_cells"] = self.tile_cells
        d["overlap_cells"] = self.overlap_cells
        return d


def check_compatible(tiling: TilingConfig, solver: SolverConfig) -> None:
    """Refuse settings whose neighbouring tiles could disagree on a shared face.

    Two tiles build their bands from the points of their own blocks; on a shared face the bands (and so the
    cells marching cubes may use) agree only if every point within ``M2 + 1`` cells of the face is in both
    blocks, i.e. ``overlap >= M2 + 1`` cells for the finest level's band.
    """
    if solver.mode == "udf":
        raise ConfigError("mode udf applies to one-shape mode (tiles orient estimated normals and trim "
                          "faces farther than trim_distance from the points: open ground stays open)")
    if solver.noise.cell_sigmas > 0:
        raise ConfigError("noise_cells applies to one-shape mode (tiled mode fixes the cell size with voxel_size)")
    if solver.noise.denoise_passes > 0:
        raise ConfigError("denoise applies to one-shape mode (tiles are not denoised; it is untested across tile "
                          "borders)")
    if solver.losses.normal_weight > 0:
        raise ConfigError("normal_weight applies to one-shape mode (tiles orient estimated normals instead)")
    m2 = solver.finest_m2()
    if tiling.overlap_cells < m2 + 1:
        raise ConfigError(f"overlap of {tiling.overlap_cells} cells is too small for a TV band of {m2} cells at "
                          f"the finest level: use overlap >= {(m2 + 1) * tiling.voxel_size:g} "
                          f"({m2 + 1} cells) or a narrower band")
