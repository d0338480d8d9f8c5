"""How a scene is cut into tiles: :class:`TilingConfig` and the check that a solver configuration fits it.

A scene is covered by a global :class:`~tiled_gridpull.lattice.Lattice` (float64 origin, cell size in metres).
Tile ``(i, j, k)`` owns the *core* cells ``[i T, (i+1) T)`` (and likewise on y, z; ``T`` = ``tile_cells``,
relative to the job's lattice offset) and is solved on the *block* that extends its core by ``O`` =
``overlap_cells`` on every side. ``T`` and ``O`` are multiples of the brick size, so every block starts on the
global brick grid and overlapping tiles store the very same vertices in the very same bricks.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace

from .attributes import ATTRIBUTE_MODES
from .config import SolverConfig, finite_number
from .crs import LENGTH_UNITS, LinearUnit, parse_length
from .spacing import Spacing
from .errors import ConfigError
from .noise import denoise_margin
from .kernels import BRICK

__all__ = ["TilingConfig", "check_compatible", "with_halo", "auto_cell_size", "AUTO", "ORIENTATIONS", "MAX_TILE_CELLS",
           "DEFAULT_TILE_CELLS", "DEFAULT_OVERLAP_CELLS"]

ORIENTATIONS = ("auto", "sensor", "up", "outward", "sphere")
MAX_TILE_CELLS = 1 << 18  # a block (core + 2 overlaps) must stay within the 2^19 vertices edge keys count on z
#: Tile core and overlap when not given, in cells: they follow the cell size. 256 cells keep a dense street tile
#: within a worker's memory and its solve around half a minute; 32 cells of overlap is the finest TV band
#: (M2 + 1 = 9 cells) rounded up to bricks, with room for the blend's ramp.
DEFAULT_TILE_CELLS = 256
#: ``voxel_size: auto``: the cell size follows the data's sample spacing (:func:`auto_cell_size`).
AUTO = "auto"
DEFAULT_OVERLAP_CELLS = 32


#: the settings a config can record as derived (not given, following the cell size or converted)
DERIVABLE = ("voxel_size", "tile_size", "overlap")
#: what resolving the cell size sets (:meth:`TilingConfig.with_cell_size`); every other setting is carried over
_RESOLVED = ("voxel_size", "voxel_unit", "units", "derived", "tile_size", "overlap")

#: no survey needs cells larger than this (in any unit: a million kilometres); beyond it float32 fields overflow
MAX_VOXEL = 1e9


def _check_voxel(voxel: float) -> None:
    if voxel <= 0:
        raise ConfigError(f"voxel_size must be positive, got {voxel!r}")
    if voxel > MAX_VOXEL:
        raise ConfigError(f"voxel_size {voxel:g} is larger than any survey needs (at most {MAX_VOXEL:g})")


@dataclass(frozen=True)
class TilingConfig:
    """How a scene is cut into tiles and stitched.

    Attributes
    ----------
    voxel_size : float or str
        Cell size in world units (metres for most LiDAR; feet for data in feet), or a length with its unit
        (``"0.1 m"``; m, cm, mm, ft, us-ft), which :meth:`in_data_units` converts to the unit of the input's CRS
        (metres when the input declares none). Stored as the number; the unit goes to ``voxel_unit``.
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
    bridge : float
        Gaps between scan lines on the ground are bridged where the upward-facing points within this many cells
        surround a column on one gently sloping plane (:mod:`tiled_gridpull.bridge`): gaps up to about twice
        this wide close; 0 keeps the surface to the data alone. At most the overlap, so that every tiling
        decides each column alike (with sensor origins a column also reads the points up to 48 cells away, and
        a beam under the bridge's plane opens a gap up to 96 cells from its point, more than the default overlap:
        docs/solver.md, "With the sensor known" and "A beam under the plane").
    min_component_cells : float
        Connected parts of the mesh smaller than this many cells along every axis are dropped: specks, each the
        bubble of a few stray points (the one-shape mode's ``min_component_cells``). Each part is judged whole,
        across the tiles it spans; the mesh, ``--tile-meshes`` and ``--3d-tiles`` agree. 0 keeps every part.
    bridge_objects : float
        With sensor origins (``orientation`` sensor): ground samples on things narrower than this many cells
        standing on the ground (cars, bushes, hedges) leave the bridge's plane fits, and the ground hidden behind
        them as the sensor saw it stays open (:class:`tiled_gridpull.bridge.BridgeRule`, ``object_width``);
        0: every ground sample counts.
    orientation : {"auto", "sensor", "up", "outward", "sphere"}
        Which side is outside: facing the sensor (per-point sensor origins, e.g. KITTI), facing up (airborne
        LAS), facing away from the centre of the whole input (one closed, roughly star-shaped object cut into
        tiles), or the paper's sphere at each tile's own centre (kept to show why it fails: neighbouring tiles
        can disagree). ``auto`` picks sensor when sensor origins are known, else up. Under up, walls (normals
        more than 60 degrees from up) face the side where the up-facing points near them lie below them and away
        from where those lie above (:func:`tiled_gridpull.normals.orient_normals`).
    normal_neighbors : int
        Neighbours used to estimate point normals for the initial field.
    drop_outliers : bool
        Drop the points far from the rest of the input before planning (:mod:`tiled_gridpull.outliers`: outside
        the box of all but 0.1 % of a sample per axis, widened by half its size and at least a tile).
    halo : int
        Cells beyond the overlap whose points a tile reads but does not solve: what its denoising needs to move
        every point of its block as any other tiling would. Set by the job from the solver (:func:`with_halo`);
        0 without denoising.
    attributes : {"all", "rgb", "none"}
        Which per-point attributes (colour, intensity, classification, LAS extra dimensions) the tiles carry
        onto the mesh's vertices (:mod:`tiled_gridpull.attributes`): every one the input has (default), the
        colour only, or none. Each tile interpolates them from its own points, its overlap included.
    voxel_unit : str, optional
        The unit ``voxel_size`` was given in, until it is converted to the data's units (None: data units).
    derived : tuple of str
        Which of ``tile_size`` and ``overlap`` were not given and so follow the cell size, and ``voxel_size``
        once converted from another unit (set here; recorded in the sidecar and shown by ``--dry-run``).
    units : str, optional
        How the cell size was converted (set by :meth:`in_data_units`), e.g.
        ``"0.1 m = 0.328084 foot (the input's CRS)"``.
    """

    voxel_size: float = 0.1
    tile_size: float | None = None
    overlap: float | None = None
    min_points: int = 100
    trim_distance: float = 3.0
    bridge: float = 0.0
    bridge_objects: float = 24.0
    min_component_cells: float = 2.0
    orientation: str = "auto"
    normal_neighbors: int = 16
    drop_outliers: bool = False
    halo: int = 0
    attributes: str = "all"
    voxel_unit: str | None = None
    derived: tuple[str, ...] = field(default=(), compare=False)
    units: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if isinstance(self.voxel_size, str) and self.voxel_size.strip().lower() == AUTO:
            object.__setattr__(self, "voxel_size", AUTO)
        self._check_record_fields()
        if self.voxel_size == AUTO or self.voxel_unit == AUTO:
            if self.voxel_size != AUTO or self.voxel_unit not in (None, AUTO):
                # voxel_unit is set by voxel_size ("0.1 m", auto), not a choice of its own
                raise ConfigError(f"voxel_size {self.voxel_size!r} with voxel_unit {self.voxel_unit!r}: give the "
                                  "cell size as voxel_size alone (a number, a length such as '0.1 m', or auto)")
            # resolved from the data (:meth:`with_cell_size`); until then only the settings that need no cell
            # size can be checked
            object.__setattr__(self, "voxel_size", AUTO)
            object.__setattr__(self, "voxel_unit", AUTO)
            for name in ("tile_size", "overlap"):
                if getattr(self, name) is not None:
                    object.__setattr__(self, name, finite_number(name, getattr(self, name)))
            self._check_settings()
            return
        try:
            voxel, unit = parse_length(self.voxel_size)
        except ValueError:
            raise ConfigError(f"voxel_size must be a number (the data's units), a length with a unit "
                              f"({', '.join(LENGTH_UNITS)}), e.g. '0.1 m', or auto; got {self.voxel_size!r}"
                              ) from None
        if unit is not None and self.voxel_unit is not None and unit != self.voxel_unit:
            raise ConfigError(f"voxel_size {self.voxel_size!r} and voxel_unit {self.voxel_unit!r} disagree")
        if self.voxel_unit is not None and (not isinstance(self.voxel_unit, str)
                                            or self.voxel_unit not in LENGTH_UNITS):
            raise ConfigError(f"voxel_unit must be one of {', '.join(LENGTH_UNITS)}; got {self.voxel_unit!r}")
        object.__setattr__(self, "voxel_size", finite_number("voxel_size", voxel))
        object.__setattr__(self, "voxel_unit", unit or self.voxel_unit)
        if self.voxel_unit is not None:
            # sizes in the data's units and a cell in another unit meet once the data's unit is known
            _check_voxel(self.voxel_size)
            for name in ("tile_size", "overlap"):
                if getattr(self, name) is not None:
                    object.__setattr__(self, name, finite_number(name, getattr(self, name)))
            self._check_settings()
            return
        derived = [name for name in self.derived if name in ("tile_size", "overlap", "voxel_size")]
        for name, cells in (("tile_size", DEFAULT_TILE_CELLS), ("overlap", DEFAULT_OVERLAP_CELLS)):
            if getattr(self, name) is None:
                # exact: the cell counts are powers of two
                object.__setattr__(self, name, cells * self.voxel_size if self.voxel_size > 0 else 0.0)
                derived.append(name)
        object.__setattr__(self, "derived", tuple(n for n in ("voxel_size", "tile_size", "overlap") if n in derived))
        object.__setattr__(self, "voxel_size", finite_number("voxel_size", self.voxel_size))
        _check_voxel(self.voxel_size)
        for name in ("tile_size", "overlap"):
            object.__setattr__(self, name, finite_number(name, getattr(self, name)))
        self._check_settings()
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
        if self.bridge > self.overlap_cells:
            raise ConfigError(f"bridge ({self.bridge:g} cells) must not exceed the overlap ({self.overlap_cells} "
                              "cells): a tile must see every point that decides a bridged column")

    def _check_record_fields(self) -> None:
        """``derived`` and ``units`` are records of how sizes were found (set here, read back from sidecars)."""
        if not isinstance(self.derived, (tuple, list)) or not all(n in DERIVABLE for n in self.derived):
            raise ConfigError(f"derived must be a list of {', '.join(DERIVABLE)}, got {self.derived!r}")
        object.__setattr__(self, "derived", tuple(self.derived))
        if self.units is not None and not isinstance(self.units, str):
            raise ConfigError(f"units must be text, got {self.units!r}")

    def _check_settings(self) -> None:
        """The checks that need no cell size."""
        if self.tile_size is not None and self.tile_size <= 0:
            raise ConfigError(f"tile_size must be positive, got {self.tile_size!r}")
        if self.overlap is not None and self.overlap < 0:
            raise ConfigError(f"overlap must be >= 0, got {self.overlap!r}")
        object.__setattr__(self, "trim_distance", finite_number("trim_distance", self.trim_distance))
        if self.trim_distance < 0:
            raise ConfigError(f"trim_distance must be >= 0, got {self.trim_distance!r}")
        object.__setattr__(self, "bridge", finite_number("bridge", self.bridge))
        if self.bridge < 0:
            raise ConfigError(f"bridge must be >= 0 (cells; 0: no bridging), got {self.bridge!r}")
        object.__setattr__(self, "bridge_objects", finite_number("bridge_objects", self.bridge_objects))
        if self.bridge_objects < 0:
            raise ConfigError(f"bridge_objects must be >= 0 (cells; 0: every ground sample counts), got "
                              f"{self.bridge_objects!r}")
        object.__setattr__(self, "min_component_cells", finite_number("min_component_cells",
                                                                      self.min_component_cells))
        if self.min_component_cells < 0:
            raise ConfigError(f"min_component_cells must be >= 0 (cells; 0 keeps every part), got "
                              f"{self.min_component_cells!r}")
        for name in ("min_points", "normal_neighbors"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1 or v >= 1 << 62:
                shown = f"an integer of {v.bit_length()} bits" if isinstance(v, int) and v >= 1 << 62 else repr(v)
                raise ConfigError(f"{name} must be a positive integer, got {shown}")
        if isinstance(self.halo, bool) or not isinstance(self.halo, int) or not 0 <= self.halo <= MAX_TILE_CELLS:
            raise ConfigError(f"halo must be a whole number of cells (0 to {MAX_TILE_CELLS}), got {self.halo!r}")
        if not isinstance(self.drop_outliers, bool):
            raise ConfigError(f"drop_outliers must be true or false, got {self.drop_outliers!r}")
        if self.attributes not in ATTRIBUTE_MODES:
            raise ConfigError(f"attributes must be one of {', '.join(ATTRIBUTE_MODES)}; got {self.attributes!r}")
        if self.orientation not in ORIENTATIONS:
            raise ConfigError(f"orientation must be one of {', '.join(ORIENTATIONS)}; got {self.orientation!r}")

    @property
    def resolved(self) -> bool:
        """Whether the cell size is known in the data's units (not ``auto``, not a length with a unit)."""
        return self.voxel_unit is None

    @property
    def tile_cells(self) -> int:
        """Core size in cells (a multiple of 8)."""
        self._need_cell_size("tile_cells")
        return max(BRICK, int(round(self.tile_size / self.voxel_size / BRICK)) * BRICK)

    @property
    def overlap_cells(self) -> int:
        """Overlap in cells (a multiple of 8, rounded up)."""
        self._need_cell_size("overlap_cells")
        return int(math.ceil(self.overlap / self.voxel_size / BRICK - 1e-9)) * BRICK

    def in_data_units(self, unit: LinearUnit | None) -> TilingConfig:
        """This config with ``voxel_size`` in the data's units.

        Parameters
        ----------
        unit : LinearUnit, optional
            The horizontal unit of the input's CRS (:func:`tiled_gridpull.crs.linear_unit`); None when the
            input declares no CRS, which is then taken to be in metres.

        Raises
        ------
        ConfigError
            A cell size with a unit for data in degrees (a geographic CRS): there is no one conversion.
        """
        if self.voxel_unit is None or self.voxel_unit == AUTO:
            return self
        given = f"{self.voxel_size:g} {self.voxel_unit}"
        metres = self.voxel_size * LENGTH_UNITS[self.voxel_unit]
        if unit is None:
            voxel, note = metres, f"{given} = {metres:g} (the input declares no CRS: taken as metres)"
        elif unit.metres is None:
            raise ConfigError(f"voxel_size {given}: the input's CRS is geographic (coordinates in {unit.name}s), "
                              "so a length cannot be converted; reproject it, or give voxel_size as a number in "
                              "the data's units")
        else:
            voxel = metres / unit.metres
            note = f"{given} = {voxel:.6g} {unit.name} (the input's CRS)"
        return self.with_cell_size(voxel, note)

    def with_cell_size(self, voxel: float, note: str) -> TilingConfig:
        """This config resolved to a cell size of ``voxel`` data units (from ``auto`` or a length with a unit):
        sizes not given follow it; ``note`` says how it was found (``units``)."""
        derived = set(self.derived) | {"voxel_size"}
        if self.tile_size is None:
            derived.add("tile_size")
        if self.overlap is None:
            derived.add("overlap")
        return TilingConfig(voxel_size=float(voxel), voxel_unit=None, units=note, derived=tuple(derived),
                            tile_size=None if "tile_size" in derived else self.tile_size,
                            overlap=None if "overlap" in derived else self.overlap,
                            **{f.name: getattr(self, f.name) for f in fields(self) if f.name not in _RESOLVED})

    def _need_cell_size(self, what: str) -> None:
        if self.voxel_unit is not None:
            raise ValueError(f"{what} of a tiling whose voxel_size ({self.voxel_size} {self.voxel_unit}) is not "
                             "resolved yet: use prepare.resolve_units first")

    def to_dict(self) -> dict:
        """Plain dict of the settings (plus the derived cell counts once the cell size is known)."""
        d = asdict(self)
        d["derived"] = list(self.derived)
        if not self.resolved:
            return d
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
    if solver.noise.denoise_passes > 0 and solver.noise.denoise_bandwidth > 0:
        raise ConfigError("denoise_bandwidth applies to one-shape mode (its range scale comes from the noise of the "
                          "whole cloud; tiles fit plain planes within denoise_radius): set denoise_bandwidth: 0")
    if solver.losses.normal_weight > 0:
        raise ConfigError("normal_weight applies to one-shape mode (tiles orient estimated normals instead)")
    if solver.relax != SolverConfig().relax:
        raise ConfigError(f"relax applies to one-shape mode (a tile's border vertices must stay where its "
                          f"neighbour's are for the weld: tiled meshes are not relaxed); got relax {solver.relax}")
    if not tiling.resolved:
        return  # checked again once the data gives the cell size (prepare.resolve_units)
    m2 = solver.finest_m2()
    if tiling.overlap_cells < m2 + 1:
        raise ConfigError(f"overlap of {tiling.overlap_cells} cells is too small for a TV band of {m2} cells at "
                          f"the finest level: use overlap >= {(m2 + 1) * tiling.voxel_size:g} "
                          f"({m2 + 1} cells) or a narrower band")


def with_halo(tiling: TilingConfig, solver: SolverConfig) -> TilingConfig:
    """``tiling`` with the halo the solver's denoising needs: whole cells past :func:`noise.denoise_margin
    <tiled_gridpull.noise.denoise_margin>` (``denoise^2 x denoise_radius``), 0 without denoising."""
    halo = 0
    if solver.noise.denoise_passes > 0:
        reach = denoise_margin(solver.noise.denoise_passes, solver.noise.denoise_radius)
        # past a whole core on every side a tile would read several of its neighbours' points for each of its own
        if reach > tiling.tile_cells:
            raise ConfigError(f"denoise {solver.noise.denoise_passes} with denoise_radius "
                              f"{solver.noise.denoise_radius:g} cells reaches {reach:g} cells, more than a tile core "
                              f"({tiling.tile_cells} cells): every tile would read that far around its block; use "
                              "fewer passes or a smaller radius")
        halo = int(math.ceil(reach - 1e-9))
    return tiling if tiling.halo == halo else replace(tiling, halo=halo)


#: Cell sizes ``auto`` picks from: 1, 2, 2.5 and 5 times a power of ten (readable, and stable against the small
#: differences between two measurements of one cloud).
_NICE = (1.0, 2.0, 2.5, 5.0, 10.0)


def auto_cell_size(spacing: Spacing, scale: float = 1.0) -> float:
    """The cell size ``voxel_size: auto`` gives a cloud of this sample spacing (data units); ``scale`` multiplies
    it before the rounding (a quality preset's :data:`tiled_gridpull.config.QUALITY_CELL_SCALE`).

    The geometric mean of the spacing by point and by area (:mod:`tiled_gridpull.spacing`), rounded to the
    nearest of 1, 2, 2.5, 5 x 10^k in ratio. A cell as fine as the densest patches' spacing would cost the
    sparse parts a band of empty cells and leave them with too few points per cell to pin the surface; one as
    coarse as the sparse parts' spacing would blur the dense ones. Measured on the project's clouds (median /
    area median / pick): the demo street 0.035 / 0.225 / 0.1 m (the cell `configs/scene.yaml` always had);
    a quarter of the grid of streets 0.124 / 0.365 / 0.2 m; AHN3 0.386 / 0.460 / 0.5 m (the benchmarks' cell);
    Autzen 2.16 / 2.80 / 2.5 ft (the benchmarks used 2).
    """
    raw = math.sqrt(spacing.median * spacing.area_median) * scale
    if not raw > 0 or not math.isfinite(raw):
        raise ConfigError(f"voxel_size auto: the points have no measurable spacing (median {spacing.median:g}, "
                          f"by area {spacing.area_median:g}: all duplicates?); give voxel_size")
    power = 10.0 ** math.floor(math.log10(raw))
    best = min(_NICE, key=lambda m: abs(math.log(raw / (m * power))))
    return float(f"{best * power:.12g}")
