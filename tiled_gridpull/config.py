"""Solver settings: a frozen :class:`SolverConfig` made of small sections shaped like the algorithm, validated on
construction, loadable from YAML (nested sections or the flat keys of earlier versions).

Units: band widths, query noise and learning rate are in **cells** (the field is stored in cells, see
:mod:`tiled_gridpull.solver`), so the same settings behave the same at every resolution.

The sections::

    SolverConfig
    ├── resolution, margin, mode, init_radius     what is solved, and from where
    ├── relax, device                             one-shape mesh relaxation; where the solver runs (cpu/cuda/auto)
    ├── schedule: Schedule                        levels, iterations per level, learning-rate decay, UDF polish
    ├── coarse: LevelConfig                       the coarsest level's TV band, optimizer, gamma, query noise, TV form
    ├── refine: LevelConfig                       the same for every finer (refinement) level
    ├── losses: LossWeights                       alpha (TV), beta (surface), udf_beta, normal_weight
    ├── sampling: Sampling                        pull band M1, queries per iteration, query pool, kNN cache, seed
    └── noise: NoiseHandling                      one-shape mode: cell size against the noise, denoising passes

Every setting also has one flat name (``m2``, ``refine_lr``, ``iterations``, ...): the keys of earlier config
files and of ``--set``. :data:`SETTINGS` is the one table mapping each flat name to its place; a dotted name
(``refine.lr``) or a nested YAML section (``refine: {lr: 0.3}``) means the same setting.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any

from .errors import ConfigError

__all__ = ["SolverConfig", "Schedule", "LevelConfig", "LossWeights", "Sampling", "NoiseHandling", "LevelSchedule",
           "SECTIONS", "SETTINGS", "REFINE_DEFAULTS", "split_settings", "recorded_settings", "NORMALS_WEIGHT",
           "REMOVED_SETTINGS", "drop_removed_settings", "load_config_file", "parse_overrides", "NOISE_PRESETS",
           "NOISE_SETTINGS", "SCAN_NOISE_SETTINGS", "QUALITIES", "QUALITY_PRESETS", "QUALITY_CELL_SCALE",
           "quality_settings"]

MIN_COARSE_CELLS = 32
#: ``normal_weight`` that given normals switch on when no weight is set (``reconstruct(normals=...)``,
#: ``--normals``): measured on exact normals in benchmarks/paper_eval.py (normals suite).
NORMALS_WEIGHT = 1.0


def setting(default: Any, *, solve: bool = True, sphere_only: bool = False) -> Any:
    """A settings field whose metadata says whether it can change a tile solve's result.

    ``solve=False``: one-shape settings a tile solve never reads (they stay out of resume keys).
    ``sphere_only=True``: read only when the solve starts from the sphere (not from oriented normals).
    """
    return field(default=default, metadata={"solve": solve, "sphere_only": sphere_only})


@dataclass(frozen=True)
class Schedule:
    """How many levels a solve runs and how long each runs.

    Attributes
    ----------
    levels : int
        Resolution levels (at most; fewer when the coarsest lattice would have fewer than 32 cells across;
        default 3). 1 is the paper's single-level solve. With ``L > 1`` the field is first solved on a lattice
        with ``2^(L-1)`` times larger cells, then refined level by level (cells halved, values transferred by
        trilinear interpolation).
    coarse_iterations : int
        Optimizer steps of the coarsest level (when it is not also the finest).
    middle_iterations : int
        Steps of the levels between the coarsest and the finest (0: ``coarse_iterations``).
    finest_iterations : int
        Steps of the finest level (default 800; paper: 1600 at its single level). Flat name ``iterations``.
    lr_decay : float
        Every level's learning rate is multiplied by this every ``lr_step`` of its :class:`LevelConfig`
        (paper: 0.3).
    udf_polish : int
        UDF mode: once the unsigned field is solved, its vertices get signs (the side of the oriented local
        plane of the nearest point, :func:`tiled_gridpull.udf_sign.sign_unsigned_field`) and the signed field is
        refined for this many iterations at the finest level with the signed losses (the ``refine`` level's
        settings, its learning rate in four stages over the run). A trilinear field cannot bend sharply at the
        sheet, so the unsigned field alone places it coarsely (half-sphere, R = 256: exact CD-L1 0.38e-3, NC
        0.958); 200 iterations: 0.034e-3, 0.9997. 0 meshes the unsigned field, signed, as it is.
    """

    levels: int = setting(3)
    coarse_iterations: int = setting(800)
    middle_iterations: int = setting(0)
    finest_iterations: int = setting(800)
    lr_decay: float = setting(0.3)
    udf_polish: int = setting(200)


@dataclass(frozen=True)
class LevelConfig:
    """The losses' band and the optimizer of one kind of level: ``SolverConfig.coarse`` (the coarsest level,
    the only one of a single-level solve) or ``SolverConfig.refine`` (every finer level).

    Once the coarse level has settled inside and outside, the refinement levels' narrower band, wider queries and
    strong gradient-consistency term smooth the surface at the cell scale (docs/solver.md has the measurements).

    Attributes
    ----------
    m2 : int
        TV band half width in cells (paper: 14 for shapes, 25 for scenes).
    lr : float
        Adam learning rate in cells per step at the level's start (paper: 1.0).
    lr_step : int
        Iterations between multiplications of the learning rate by ``Schedule.lr_decay`` (paper: 400).
    gamma : float
        Weight of the gradient-consistency loss (paper: 0.005; SDF mode only).
    query_sigma : float
        Standard deviation of the query noise in cells (paper text: 2 cells; authors' code: ~0.05).
    tv_form : {"squared", "sqrt"}
        TV as squared differences (authors' code) or the paper's per-vertex square root.
    """

    m2: int = setting(14)
    lr: float = setting(1.0)
    lr_step: int = setting(400)
    gamma: float = setting(0.005)
    query_sigma: float = setting(0.2)
    tv_form: str = setting("sqrt")


#: What the refinement levels run unless told otherwise.
REFINE_DEFAULTS = LevelConfig(m2=8, lr=0.3, lr_step=200, gamma=3.0, query_sigma=0.5, tv_form="squared")


@dataclass(frozen=True)
class LossWeights:
    """Weights of the losses besides the pull loss (whose weight is 1) and the per-level ``gamma``.

    Attributes
    ----------
    alpha : float
        TV loss (paper: 1).
    beta : float
        Surface loss in SDF mode (paper: 1).
    udf_beta : float
        Surface loss in UDF mode. With the field clamped at 0, ``beta = 1`` flattens the whole band to ~0.4 cells
        and the sheet vanishes (half-sphere: 2 % of its area meshed); 0.1 measured best (half-sphere exact CD-L1
        0.74e-3, NC 0.979; 0 gave 0.85e-3 / 0.972).
    normal_weight : float
        Normal-supervision loss when the input has normals (0 = off). Normals passed to
        :func:`tiled_gridpull.reconstruct` (or ``--normals``) switch it to ``NORMALS_WEIGHT`` (1) when it is
        not set.
    """

    alpha: float = setting(1.0)
    beta: float = setting(1.0)
    udf_beta: float = setting(0.1)
    normal_weight: float = setting(0.0, solve=False)


@dataclass(frozen=True)
class Sampling:
    """Where the pull loss acts and how its queries are drawn and matched to points.

    Attributes
    ----------
    m1 : int
        Pull band half width in cells: queries are drawn around the points and pull the field within it
        (paper: 3).
    queries : int
        Queries per iteration (paper: 50,000).
    queries_per_point : float
        0 (paper): every iteration draws ``queries`` queries. ``r > 0``: a level holding ``N`` points (after
        the coarse levels' thinning) draws ``min(queries, max(min_queries, ceil(r N)))`` per iteration, so
        a tile's query cost follows what it holds (a tile of 500 points gets ``min_queries``, not 50,000).
    refine_queries_per_point : float
        The rate on the refinement levels (every level but the coarsest); 0 (default): ``queries_per_point``.
        The refinement levels hold every point (no thinning) and their band is narrow, so their pull loss is the
        one short of queries on sparse tiles (docs/solver.md, "Queries on the refinement levels").
    min_queries : int
        Floor of the per-iteration query count when ``queries_per_point > 0``.
    query_pool : int
        0 (paper): fresh queries every iteration. ``B > 0`` (default 200): each level draws ``B`` batches of
        queries once, finds their nearest points in one go, and cycles through them (NeuralPull's precomputed
        queries), so nearest-neighbour search costs ``B`` batches instead of one per iteration. Pays where that
        search dominates: dense LiDAR tiles (see docs/solver.md).
    points_per_cell : int
        Tiled mode: 0 (default) solves every point of a tile; ``k > 0`` keeps at most ``k`` points in each finest
        cell (chosen at random, seeded) before the tile's normals and solve, so a tile's set-up, nearest-point
        lists and queries follow the cells its surface crosses rather than the scanner's density (the ``draft``
        preset; the mesh is still trimmed against every point).
    knn : int
        Candidate list size of the nearest-neighbour cache.
    seed : int
        Random seed (queries). Results are bitwise reproducible for a given seed.
    """

    m1: int = setting(3)
    queries: int = setting(50_000)
    queries_per_point: float = setting(0.0)
    refine_queries_per_point: float = setting(0.0)
    min_queries: int = setting(2048)
    query_pool: int = setting(200)
    points_per_cell: int = setting(0)
    knn: int = setting(16)
    seed: int = setting(0)


@dataclass(frozen=True)
class NoiseHandling:
    """What is done about noise before the solve. Tiled mode takes the denoising passes (with neighbourhoods bounded
    by ``denoise_radius``), refuses ``noise_cells`` and ``denoise_bandwidth``, and chooses with a rule of its own
    (``auto``).

    Attributes
    ----------
    cell_sigmas : float
        0 keeps ``resolution``; > 0 lowers it (never raises it) so that the finest cell is at least this many
        times the cloud's estimated noise sigma (:func:`tiled_gridpull.noise.estimate_noise`). A field whose cell
        is finer than the noise reproduces the noise; ``configs/noisy.yaml`` uses 0.8 (after its robust
        denoising), ``configs/very_noisy.yaml`` 1.2. Flat name ``noise_cells``.
    denoise_passes : int
        Passes of :func:`tiled_gridpull.noise.project_to_local_planes` (each point moved onto the plane of its
        ``denoise_neighbors`` nearest neighbours) before the noise estimate and the solve; 0 (default) leaves the
        points as they are. ``configs/noisy.yaml`` uses 2. Flat name ``denoise``.
    denoise_neighbors : int
        Neighbours per plane fit.
    denoise_bandwidth : float
        0: plain least-squares planes. > 0: robust (bilateral) planes whose range scale is this many estimated
        noise sigmas, so thin walls and sharp edges keep their sheets apart. One-shape mode only (the range
        scale comes from an estimate over the whole cloud).
    denoise_radius : float
        Tiled mode: only neighbours within this many cells count (default 2). It bounds how far a point's
        result reaches, so a tile that reads ``denoise^2 x denoise_radius`` cells of points past its block (its
        halo, :func:`tiled_gridpull.tiling.with_halo`) moves every point of its block exactly as any other tiling
        would (:func:`tiled_gridpull.noise.denoise_block`). One-shape mode fits the nearest neighbours without a
        bound.
    auto : bool
        One-shape mode: when the cloud looks noisy (:attr:`tiled_gridpull.noise.NoiseEstimate.ratio`) and none
        of the noise settings above nor ``beta`` was changed from its default, apply the treatment of
        :data:`NOISE_PRESETS` that the estimate selects (the sidecar's ``noise_treatment`` records it).
        Tiled mode: when ``denoise_passes`` was not changed, apply :data:`tiled_gridpull.noise.SCAN_TREATMENT`
        if the scan's scatter (:func:`tiled_gridpull.noise.scan_noise`, measured once for the job) exceeds
        :data:`tiled_gridpull.noise.SCAN_NOISY_CELLS` (:func:`tiled_gridpull.prepare.scan_noise_treatment`).
        Default true; false keeps the settings as given. Flat name ``noise_auto``.
    """

    cell_sigmas: float = setting(0.0)
    denoise_passes: int = setting(0)
    denoise_neighbors: int = setting(64)
    denoise_bandwidth: float = setting(0.0)
    denoise_radius: float = setting(2.0)
    auto: bool = setting(True, solve=False)


#: The sections of a :class:`SolverConfig`: attribute -> class.
SECTIONS: dict[str, type] = {"schedule": Schedule, "coarse": LevelConfig, "refine": LevelConfig,
                             "losses": LossWeights, "sampling": Sampling, "noise": NoiseHandling}

#: The one table of settings: flat name (config files of earlier versions, ``--set``, keyword arguments) ->
#: ``(section, field)``; section ``None`` is a top-level field. A dotted name ``section.field`` means the same.
SETTINGS: dict[str, tuple[str | None, str]] = {
    "resolution": (None, "resolution"),
    "margin": (None, "margin"),
    "mode": (None, "mode"),
    "init_radius": (None, "init_radius"),
    "relax": (None, "relax"),
    "device": (None, "device"),
    "levels": ("schedule", "levels"),
    "coarse_iterations": ("schedule", "coarse_iterations"),
    "middle_iterations": ("schedule", "middle_iterations"),
    "iterations": ("schedule", "finest_iterations"),
    "lr_decay": ("schedule", "lr_decay"),
    "udf_polish": ("schedule", "udf_polish"),
    "m2": ("coarse", "m2"),
    "lr": ("coarse", "lr"),
    "lr_step": ("coarse", "lr_step"),
    "gamma": ("coarse", "gamma"),
    "query_sigma": ("coarse", "query_sigma"),
    "tv_form": ("coarse", "tv_form"),
    "refine_m2": ("refine", "m2"),
    "refine_lr": ("refine", "lr"),
    "refine_lr_step": ("refine", "lr_step"),
    "refine_gamma": ("refine", "gamma"),
    "refine_sigma": ("refine", "query_sigma"),
    "refine_tv_form": ("refine", "tv_form"),
    "alpha": ("losses", "alpha"),
    "beta": ("losses", "beta"),
    "udf_beta": ("losses", "udf_beta"),
    "normal_weight": ("losses", "normal_weight"),
    "m1": ("sampling", "m1"),
    "queries": ("sampling", "queries"),
    "queries_per_point": ("sampling", "queries_per_point"),
    "refine_queries_per_point": ("sampling", "refine_queries_per_point"),
    "min_queries": ("sampling", "min_queries"),
    "query_pool": ("sampling", "query_pool"),
    "points_per_cell": ("sampling", "points_per_cell"),
    "knn": ("sampling", "knn"),
    "seed": ("sampling", "seed"),
    "noise_cells": ("noise", "cell_sigmas"),
    "denoise": ("noise", "denoise_passes"),
    "denoise_neighbors": ("noise", "denoise_neighbors"),
    "denoise_bandwidth": ("noise", "denoise_bandwidth"),
    "denoise_radius": ("noise", "denoise_radius"),
    "noise_auto": ("noise", "auto"),
}

#: the most relaxation iterations a config may ask for (three are the default; past a few the mesh stops gaining)
MAX_RELAX = 100

#: The noise treatments, as settings (flat names): what ``configs/noisy.yaml`` and ``configs/very_noisy.yaml``
#: set, and what ``noise_auto`` applies when the estimate selects one (tests check the files agree).
NOISE_PRESETS: dict[str, dict[str, Any]] = {
    "noisy": {"beta": 0.0, "noise_cells": 0.8, "denoise": 2, "denoise_neighbors": 32, "denoise_bandwidth": 1.0},
    "very_noisy": {"beta": 0.0, "noise_cells": 1.2, "denoise": 2, "denoise_neighbors": 64, "denoise_bandwidth": 0.0},
}
#: The quality presets (``--quality``, config key ``quality``), cheapest first; ``standard`` is the config as given.
QUALITIES = ("draft", "standard", "fine")
#: What each preset sets (flat names). A preset replaces what the config file says for the settings it names (so
#: ``--config configs/scene.yaml --quality draft`` works); ``--set`` and the options win over it. Measured in
#: BENCHMARKS.md ("Quality presets") and docs/solver.md ("Quality presets: time against accuracy").
QUALITY_PRESETS: dict[str, dict[str, Any]] = {
    "draft": {"coarse_iterations": 150, "lr_step": 75, "middle_iterations": 50, "iterations": 100,
              "refine_lr_step": 25, "refine_m2": 5, "refine_queries_per_point": 4, "query_pool": 10,
              "points_per_cell": 8},
    "standard": {},
    "fine": {"queries_per_point": 0, "refine_queries_per_point": 0},
}
#: With ``voxel_size: auto``, the cell each preset takes: the measured cell (:func:`tiled_gridpull.tiling.
#: auto_cell_size`) times this, rounded to 1, 2, 2.5 or 5 x 10^k. A cell given as a number is kept.
QUALITY_CELL_SCALE: dict[str, float] = {"draft": 1.5, "standard": 1.0, "fine": 0.5}


def quality_settings(quality: str | None) -> dict[str, Any]:
    """The settings (flat names) of quality preset ``quality`` (None: ``standard``, nothing); a name not in
    :data:`QUALITIES` is a one-line :class:`ConfigError`."""
    if quality is None:
        return {}
    if not isinstance(quality, str) or quality not in QUALITY_PRESETS:
        raise ConfigError(f"quality must be one of {', '.join(QUALITIES)}; got {quality!r}")
    return dict(QUALITY_PRESETS[quality])


#: The settings a noise treatment changes: ``noise_auto`` stays away when the user changed any of them.
NOISE_SETTINGS = ("beta", "noise_cells", "denoise", "denoise_neighbors", "denoise_bandwidth")
#: The same in tiled mode, where the only treatment is the denoising passes (their neighbours and radius are
#: parameters the scene configs set, not a choice of treatment).
SCAN_NOISE_SETTINGS = ("denoise",)
_FLAT_OF = {path: name for name, path in SETTINGS.items()}
_DOTTED = {f"{section}.{name}": (section, name) for section, name in SETTINGS.values() if section}

_CHOICES = {"tv_form": ("squared", "sqrt"), "refine_tv_form": ("squared", "sqrt"), "mode": ("sdf", "udf"),
            "device": ("cpu", "cuda", "auto")}
_POSITIVE = ("resolution", "iterations", "queries", "min_queries", "lr", "lr_step", "knn", "levels",
             "coarse_iterations", "refine_lr", "refine_lr_step", "refine_sigma", "denoise_radius")
_NONNEGATIVE = ("margin", "m1", "m2", "alpha", "beta", "gamma", "query_sigma", "init_radius", "normal_weight",
                "seed", "refine_m2", "refine_gamma", "noise_cells", "udf_beta", "udf_polish", "query_pool",
                "denoise", "denoise_bandwidth", "queries_per_point", "refine_queries_per_point", "points_per_cell",
                "middle_iterations", "relax")


@dataclass(frozen=True, init=False)
class SolverConfig:
    """Everything that decides a GridPull solve.

    Built from keyword settings, each a flat name of :data:`SETTINGS` (``m2=8``, ``refine_lr=0.2``,
    ``iterations=400``), a dotted name (``**{"refine.lr": 0.2}``), or a whole section (``refine=LevelConfig(...)``
    replaces the section; a mapping ``refine={"lr": 0.2}`` changes only what it names). Values are validated;
    a bad one raises a one-line :class:`~tiled_gridpull.errors.ConfigError` naming the setting.

    The defaults are the schedule we ship (``configs/shape.yaml``; docs/solver.md, "The schedule we ship"), which
    differs from the paper's recipe (``configs/paper.yaml``): three levels instead of one, 800 iterations at the
    finest level instead of 1600, queries at 0.2 cells instead of 2, a query pool. The paper's values are noted
    per setting in the sections' docstrings.

    Attributes
    ----------
    resolution : int
        Cells across the padded longest side of a shape (paper: 256). Ignored when a lattice is given.
    margin : int
        Empty cells around a shape's bounding box.
    mode : {"sdf", "udf"}
        Signed field (default) or unsigned field for open surfaces (CAP-UDF pull, no gradient loss).
    init_radius : float
        An SDF solve starts from a sphere of this radius in cells at the lattice centre (paper: one or two
        cells; right for shapes that are star-shaped around their bounding-box centre). Tiled scenes start from
        oriented normals instead (see ``TilingConfig.orientation``).
    relax : int
        One-shape SDF mode: iterations of :func:`tiled_gridpull.isosurface.relax_on_field` on the marching-cubes
        mesh (Taubin steps, each followed by a projection back onto the field's zero level), which even out its
        slivers; 0 keeps the marching-cubes vertices (the paper). Default 3 (docs/solver.md, "Relaxing the mesh
        on the field"). Tiled mode does not relax (a tile's border vertices must stay where its neighbour's are).
    device : {"auto", "cpu", "cuda"}
        Where the solver's iterations run (:mod:`tiled_gridpull.device`): ``auto`` (default) a CUDA card when
        numba-cuda sees one, else the CPU. Not part of a tile's resume key: the two agree within a quarter cell
        (docs/solver.md, "On a GPU"), and a job resumed on another machine keeps the tiles it has.
    schedule : Schedule
        Levels and iterations.
    coarse, refine : LevelConfig
        TV band, optimizer, gradient-consistency weight, query noise and TV form of the coarsest level and of
        the finer levels.
    losses : LossWeights
        alpha (TV), beta (surface), udf_beta, normal_weight.
    sampling : Sampling
        Pull band M1 and the queries.
    noise : NoiseHandling
        One-shape mode: cell size against the noise, denoising.
    """

    resolution: int = setting(256, solve=False)
    margin: int = setting(4, solve=False)
    mode: str = setting("sdf")
    init_radius: float = setting(2.0, sphere_only=True)
    relax: int = setting(3, solve=False)
    device: str = setting("auto", solve=False)
    schedule: Schedule = field(default_factory=Schedule)
    coarse: LevelConfig = field(default_factory=LevelConfig)
    refine: LevelConfig = field(default_factory=lambda: REFINE_DEFAULTS)
    losses: LossWeights = field(default_factory=LossWeights)
    sampling: Sampling = field(default_factory=Sampling)
    noise: NoiseHandling = field(default_factory=NoiseHandling)

    def __init__(self, **settings: Any) -> None:
        given = _paths(settings)
        values: dict[str, Any] = {}
        for name, path in SETTINGS.items():
            value = given[path][1] if path in given else _DEFAULTS[name]
            label = given[path][0] if path in given else name
            values[name] = _checked(name, label, value)
        for f in fields(SolverConfig):
            if f.name in SECTIONS:
                section = SECTIONS[f.name](**{fname: values[_FLAT_OF[(f.name, fname)]]
                                              for fname in _FIELD_NAMES[SECTIONS[f.name]]})
                object.__setattr__(self, f.name, section)
            else:
                object.__setattr__(self, f.name, values[f.name])
        self._check_together()

    def _check_together(self) -> None:
        """Checks that involve several settings."""
        for name in _POSITIVE:
            if self.get(name) <= 0:
                raise ConfigError(f"{name} must be positive, got {self.get(name)!r}")
        for name in _NONNEGATIVE:
            if self.get(name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {self.get(name)!r}")
        if self.noise.denoise_neighbors < 4:
            raise ConfigError(f"denoise_neighbors must be at least 4 (a plane fit), got "
                              f"{self.noise.denoise_neighbors!r}")
        if self.relax > MAX_RELAX:
            raise ConfigError(f"relax must be at most {MAX_RELAX} (iterations of the mesh's relaxation), got "
                              f"{self.relax}")
        if not 0 < self.schedule.lr_decay <= 1:
            raise ConfigError(f"lr_decay must be in (0, 1], got {self.schedule.lr_decay!r}")
        m1 = self.sampling.m1
        if m1 > self.coarse.m2:
            raise ConfigError(f"m1 ({m1}) must not exceed m2 ({self.coarse.m2})")
        if self.schedule.levels > 1 and m1 > self.refine.m2:
            raise ConfigError(f"m1 ({m1}) must not exceed refine_m2 ({self.refine.m2})")
        if self.schedule.levels > 4:
            raise ConfigError(f"levels must be at most 4 (coarsest cells 8x the finest), got {self.schedule.levels}")
        if self.resolution < 2 * self.margin + 4:
            raise ConfigError(f"resolution {self.resolution} is too small for margin {self.margin}")

    @staticmethod
    def setting_names() -> list[str]:
        """Every key a config file, ``--set`` or the constructor accepts: flat names, dotted names, sections."""
        return [*SETTINGS, *_DOTTED, *SECTIONS]

    def get(self, name: str) -> Any:
        """The value of one setting by its flat (``refine_lr``) or dotted (``refine.lr``) name."""
        section, fname = SETTINGS.get(name) or _DOTTED.get(name) or (None, None)
        if fname is None:
            raise ConfigError(f"unknown solver setting {name!r}")
        return getattr(getattr(self, section) if section else self, fname)

    def replace(self, **changes: Any) -> SolverConfig:
        """Copy with some settings changed (flat names, dotted names or sections, as the constructor takes),
        validated."""
        changed = {_FLAT_OF[path]: value for path, (_, value) in _paths(changes).items()}
        return SolverConfig(**{**self.to_flat(), **changed})

    def to_dict(self) -> dict:
        """All settings, nested by section (what sidecars record)."""
        return dataclasses.asdict(self)

    def to_flat(self) -> dict:
        """All settings by flat name (what ``SolverConfig(**d)`` takes back)."""
        return {name: self.get(name) for name in SETTINGS}

    def solve_settings(self, sphere_init: bool) -> dict:
        """The settings that can change a tile solve's result (fields marked ``solve``), by flat name, for resume
        keys.

        ``sphere_init``: the solve starts from the sphere, so its radius counts too.
        """
        out = {name: self.get(name) for name, path in SETTINGS.items()
               if _META[path]["solve"] and (sphere_init or not _META[path]["sphere_only"])}
        if not out.get("points_per_cell"):  # only when set: keys of jobs that keep every point stay as they were
            out.pop("points_per_cell", None)
        return out

    def levels_for(self, cells: int) -> int:
        """Levels used on a lattice ``cells`` across: at most ``schedule.levels``, fewer when the coarsest would
        have fewer than 32 cells across."""
        n = 1
        while n < self.schedule.levels and (int(cells) >> n) >= MIN_COARSE_CELLS:
            n += 1
        return n

    def finest_m2(self) -> int:
        """TV band half width of the finest level when all ``schedule.levels`` are used."""
        return (self.refine if self.schedule.levels > 1 else self.coarse).m2

    def queries_for(self, n_points: int | None, refine: bool = False) -> int:
        """Queries per iteration on a level holding ``n_points`` points (``None``: unknown, the most); ``refine``:
        on a refinement level (``refine_queries_per_point`` when set)."""
        s = self.sampling
        rate = s.refine_queries_per_point if refine and s.refine_queries_per_point > 0 else s.queries_per_point
        if rate <= 0 or n_points is None:
            return s.queries
        return int(min(s.queries, max(s.min_queries, math.ceil(rate * n_points))))

    def level_settings(self, level: int, n_levels: int, n_points: int | None = None) -> LevelSchedule:
        """The schedule of ``level`` (0 = coarsest) out of ``n_levels``, for a level holding ``n_points`` points
        (``None``: the most queries the settings allow)."""
        sch = self.schedule
        iterations = sch.finest_iterations if level == n_levels - 1 else sch.coarse_iterations
        if 0 < level < n_levels - 1 and sch.middle_iterations:
            iterations = sch.middle_iterations
        lv = self.coarse if level == 0 else self.refine
        # a pool longer than the level would never be cycled through
        return LevelSchedule(iterations=iterations, queries=self.queries_for(n_points, refine=level > 0),
                             query_pool=min(self.sampling.query_pool, iterations), lr=lv.lr, lr_step=lv.lr_step,
                             m2=lv.m2, gamma=lv.gamma, sigma=lv.query_sigma, tv_form=lv.tv_form)

    def total_iterations(self, cells: int) -> int:
        """Iterations of a solve on a lattice ``cells`` across, over all its levels and a UDF polish."""
        levels = self.levels_for(cells)
        total = sum(self.level_settings(level, levels).iterations for level in range(levels))
        return total + (self.schedule.udf_polish if self.mode == "udf" else 0)

    def polish_settings(self) -> LevelSchedule:
        """Schedule of the signed refinement that ends a UDF solve: a refinement level's (even after a one-level
        solve: the polish refines a field that has settled), for ``udf_polish`` iterations, the learning rate
        in four stages over them (as over a refinement level's 800 at 200 each)."""
        its = self.schedule.udf_polish
        return dataclasses.replace(self.level_settings(1, 2), iterations=its,
                                   query_pool=min(self.sampling.query_pool, its), lr_step=max(1, its // 4))


def _field_of(path: tuple[str | None, str]) -> dataclasses.Field:
    section, name = path
    return {f.name: f for f in fields(SECTIONS[section] if section else SolverConfig)}[name]


_FIELD_NAMES = {cls: [f.name for f in fields(cls)] for cls in set(SECTIONS.values())}
_META = {path: _field_of(path).metadata for path in SETTINGS.values()}
_TYPE = {name: _field_of(path).type for name, path in SETTINGS.items()}
_SECTION_DEFAULTS = {"coarse": LevelConfig(), "refine": REFINE_DEFAULTS, "schedule": Schedule(),
                     "losses": LossWeights(), "sampling": Sampling(), "noise": NoiseHandling()}
_DEFAULTS = {name: (getattr(_SECTION_DEFAULTS[section], fname) if section else _field_of(path).default)
             for name, path in SETTINGS.items() for section, fname in [path]}
assert all(v is not MISSING for v in _DEFAULTS.values())
assert set(_FLAT_OF) == {(s, f) for s, cls in SECTIONS.items() for f in _FIELD_NAMES[cls]} | {
    (None, f.name) for f in fields(SolverConfig) if f.name not in SECTIONS}, "SETTINGS must name every field once"


def _paths(settings: Mapping[Any, Any]) -> dict[tuple[str | None, str], tuple[str, Any]]:
    """Keyword settings -> ``{(section, field): (key as given, value)}``; sections are expanded, unknown keys
    and a setting given twice (say ``lr`` and ``coarse.lr``) refused."""
    out: dict[tuple[str | None, str], tuple[str, Any]] = {}

    def put(path, key, value):
        if path in out:
            raise ConfigError(f"setting {_FLAT_OF[path]} is given twice (as {out[path][0]} and as {key})")
        out[path] = (key, value)

    unknown = [k for k in settings if not isinstance(k, str) or k not in SETTINGS and k not in _DOTTED
               and k not in SECTIONS]
    if unknown:
        shown = sorted(k if isinstance(k, str) and k.isidentifier() else repr(k) for k in unknown)
        raise ConfigError(f"unknown solver setting(s): {', '.join(shown)}")
    for key, value in settings.items():
        if key in SECTIONS:
            cls = SECTIONS[key]
            if isinstance(value, cls):
                for fname in _FIELD_NAMES[cls]:
                    put((key, fname), key, getattr(value, fname))
            elif isinstance(value, Mapping):
                for sub, v in value.items():
                    if not isinstance(sub, str) or (key, sub) not in _FLAT_OF:
                        raise ConfigError(f"unknown solver setting {key}.{sub} (the {key} section has "
                                          f"{', '.join(_FIELD_NAMES[cls])})")
                    put((key, sub), f"{key}.{sub}", v)
            else:
                raise ConfigError(f"{key} must be a {cls.__name__} or a mapping of its settings, got "
                                  f"{type(value).__name__}")
        else:
            put(SETTINGS.get(key) or _DOTTED[key], key, value)
    return out


def split_settings(settings: Mapping[Any, Any]) -> tuple[dict[str, Any], dict[Any, Any]]:
    """Split a mapping of settings (a config file, ``--set``) into solver settings by flat name and the rest.

    Flat names, dotted names and nested sections all come out under their flat name, so that sources merged
    later (a file, then ``--set``) override each other whichever spelling each used; one setting given twice in
    ``settings`` is a :class:`ConfigError`. The rest (tiling settings, unknown keys) is returned untouched.
    """
    mine = {k: v for k, v in settings.items() if isinstance(k, str) and (k in SETTINGS or k in _DOTTED
                                                                           or k in SECTIONS)}
    rest = {k: v for k, v in settings.items() if not (isinstance(k, str) and k in mine)}
    return {_FLAT_OF[path]: value for path, (_, value) in _paths(mine).items()}, rest


def recorded_settings(config: Mapping[str, Any]) -> dict[str, Any]:
    """Solver settings by flat name from a sidecar's ``config`` (nested by section; flat in files written by
    earlier versions). Settings it does not hold are left out; nothing is validated (it is a record)."""
    out = {}
    for name, (section, fname) in SETTINGS.items():
        holder = config.get(section) if section else config
        if isinstance(holder, Mapping) and fname in holder:
            out[name] = holder[fname]
        elif name in config and not isinstance(config[name], Mapping):
            out[name] = config[name]
    return out


def _checked(name: str, label: str, value: Any) -> Any:
    """``value`` of setting ``name`` (given as ``label``) coerced to its declared type, or a ConfigError."""
    kind = _TYPE[name]
    if kind in ("int", int):
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                raise ConfigError(f"{label} must be an integer, got {value!r}")
        if abs(value) >= 1 << 62:
            raise ConfigError(f"{label} is out of range (an integer of {value.bit_length()} bits)")
        return value
    if kind in ("float", float):
        return finite_number(label, value)
    if kind in ("bool", bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{label} must be true or false, got {value!r}")
        return value
    if value not in _CHOICES[name]:
        raise ConfigError(f"{label} must be one of {', '.join(_CHOICES[name])}; got {value!r}")
    return value


@dataclass(frozen=True)
class LevelSchedule:
    """What one resolution level (or the UDF polish) of a solve runs, resolved from a :class:`SolverConfig`.

    Attributes
    ----------
    iterations : int
        Optimizer steps of the level.
    queries : int
        Queries per iteration.
    query_pool : int
        Batches of queries whose nearest points are found once and cycled through (0: fresh every iteration);
        never more than ``iterations``.
    lr : float
        Adam learning rate in cells per step at the level's start.
    lr_step : int
        Iterations between multiplications of the learning rate by ``SolverConfig.schedule.lr_decay``.
    m2 : int
        TV band half width in cells.
    gamma : float
        Weight of the gradient-consistency loss (SDF mode; a UDF solve does not use it).
    sigma : float
        Standard deviation of the query noise in cells.
    tv_form : {"squared", "sqrt"}
        Form of the TV loss.
    """

    iterations: int
    queries: int
    query_pool: int
    lr: float
    lr_step: int
    m2: int
    gamma: float
    sigma: float
    tv_form: str


def finite_number(name: str, value: Any) -> float:
    """``value`` as a finite float, or a ConfigError naming ``name`` (bools, strings, huge ints refused)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{name} must be a finite number, got {value!r}")
    try:
        out = float(value)
    except OverflowError:
        out = math.inf
    if not math.isfinite(out):
        shown = f"an integer of {value.bit_length()} bits" if isinstance(value, int) else repr(value)
        raise ConfigError(f"{name} must be a finite number, got {shown}")
    return out


#: Settings that no longer exist, with the one value they could still mean (what the solver always does now).
#: Old config files naming that value keep working, with a warning; any other value is refused.
REMOVED_SETTINGS = {
    "init": "sphere",       # init: flood was removed (used by no config, benchmark or test); scenes start from planes
    "surface_form": "abs",  # surface_form: squared was removed; the surface loss is the paper's |f(s)|
}


def drop_removed_settings(settings: dict[str, Any]) -> dict[str, Any]:
    """``settings`` without the keys of :data:`REMOVED_SETTINGS`: a key given its remaining value is dropped
    with a warning, any other value is a one-line :class:`ConfigError`."""
    import warnings

    out = dict(settings)
    for key, kept in REMOVED_SETTINGS.items():
        if key not in out:
            continue
        value = out.pop(key)
        if value != kept:
            raise ConfigError(f"{key} {value!r} was removed; the solver always uses {key} {kept!r} "
                              f"(delete the setting)")
        warnings.warn(f"setting {key!r} was removed ({kept!r} is what the solver always does); ignored",
                      UserWarning, stacklevel=2)
    return out


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["key=value", ...]`` (from ``--set``) -> dict with YAML-typed values."""
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set expects key=value, got {item!r}")
        key, raw = item.split("=", 1)
        key = key.strip()
        if not key:
            raise ConfigError(f"--set expects key=value, got {item!r}")
        try:
            out[key] = yaml.safe_load(raw)
        except yaml.YAMLError:
            raise ConfigError(f"--set {item!r}: the value is not valid YAML") from None
    return out


def _unique_key_loader():
    """A safe YAML loader that refuses a key given twice in one mapping (plain YAML keeps the last silently, so
    a setting edited in one place and left in another would be ignored without a word)."""
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        pass

    def mapping(loader, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = loader.construct_object(key_node, deep=deep)
            if key in seen:
                raise ConfigError(f"setting {key!r} is given twice (line {key_node.start_mark.line + 1})")
            seen.add(key)
        return loader.construct_mapping(node, deep=deep)

    UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    return UniqueKeyLoader


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping of settings (flat keys or nested sections); one-line errors for a missing or malformed
    file or a key given twice."""
    import yaml

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {p}: " + ("a directory, not a YAML file" if p.is_dir() else "not found"))
    try:
        data = yaml.load(p.read_text(), Loader=_unique_key_loader())
    except ConfigError as exc:
        raise ConfigError(f"config file {p}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise ConfigError(f"config file {p}: not valid YAML{where}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config file {p}: cannot read ({exc.__class__.__name__})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {p}: expected a mapping of settings, got {type(data).__name__}")
    return data
