"""Solver settings: one frozen dataclass, validated on construction, loadable from flat YAML.

Units: band widths, query noise and learning rate are in **cells** (the field is stored in cells, see
:mod:`tiled_gridpull.solver`), so the same settings behave the same at every resolution.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from .errors import ConfigError

__all__ = ["LevelSchedule", "SolverConfig", "NORMALS_WEIGHT", "REMOVED_SETTINGS", "drop_removed_settings",
           "load_config_file", "parse_overrides"]

MIN_COARSE_CELLS = 32
#: ``normal_weight`` that given normals switch on when no weight is set (``reconstruct(normals=...)``,
#: ``--normals``): measured on exact normals in benchmarks/paper_eval.py (normals suite).
NORMALS_WEIGHT = 1.0

_CHOICES = {
    "tv_form": ("squared", "sqrt"),
    "refine_tv_form": ("squared", "sqrt"),
    "mode": ("sdf", "udf"),
}


def setting(default: Any, *, solve: bool = True, sphere_only: bool = False) -> Any:
    """A :class:`SolverConfig` field whose metadata says whether it can change a tile solve's result.

    ``solve=False``: one-shape settings a tile solve never reads (they stay out of resume keys).
    ``sphere_only=True``: read only when the solve starts from the sphere (not from oriented normals).
    """
    return field(default=default, metadata={"solve": solve, "sphere_only": sphere_only})


@dataclass(frozen=True)
class SolverConfig:
    """Everything that decides a GridPull solve.

    The defaults are the schedule we ship (``configs/shape.yaml``; docs/solver.md, "The schedule we ship"), which
    differs from the paper's recipe (``configs/paper.yaml``): three levels instead of one, 800 iterations at the
    finest level instead of 1600, queries at 0.2 cells instead of 2, a query pool. The paper's values are noted
    per setting.

    Attributes
    ----------
    resolution : int
        Cells across the padded longest side of a shape (paper: 256). Ignored when a lattice is given.
    margin : int
        Empty cells around a shape's bounding box.
    m1, m2 : int
        Pull band and TV band half widths in cells (paper: 3 and 14; 25 for scenes).
    iterations : int
        Optimizer steps at the finest level (default 800; paper: 1600 at its single level).
    queries : int
        Queries per iteration (paper: 50,000).
    lr, lr_decay, lr_step : float, float, int
        Adam learning rate in cells per step, multiplied by ``lr_decay`` every ``lr_step`` iterations
        (paper: 1.0, 0.3, 400).
    alpha, beta, gamma : float
        Weights of the TV, surface and gradient-consistency losses (paper: 1, 1, 0.005).
    tv_form : {"squared", "sqrt"}
        TV as squared differences (authors' code) or the paper's per-vertex square root.
    query_sigma : float
        Standard deviation of the query noise in cells (default 0.2; paper text: 2 cells; authors' code: ~0.05).
    init_radius : float
        An SDF solve starts from a sphere of this radius in cells at the lattice centre (paper: one or two
        cells; right for shapes that are star-shaped around their bounding-box centre). Tiled scenes start from
        oriented normals instead (see ``TilingConfig.orientation``).
    mode : {"sdf", "udf"}
        Signed field (default) or unsigned field for open surfaces (CAP-UDF pull, no gradient loss).
    udf_beta : float
        Surface-loss weight in UDF mode (``beta`` is the SDF one). With the field clamped at 0, ``beta = 1``
        flattens the whole band to ~0.4 cells and the sheet vanishes (half-sphere: 2 % of its area meshed);
        0.1 measured best (half-sphere exact CD-L1 0.74e-3, NC 0.979; 0 gave 0.85e-3 / 0.972).
    udf_polish : int
        UDF mode: once the unsigned field is solved, its vertices get signs (the side of the oriented local
        plane of the nearest point, :func:`tiled_gridpull.udf_sign.sign_unsigned_field`) and the signed field is
        refined for this many iterations at the finest level with the signed losses (the refinement levels'
        settings, ``refine_lr`` in four stages over the run, decaying by ``lr_decay`` between them). A trilinear
        field cannot bend sharply at the sheet, so the unsigned field alone places it coarsely (half-sphere, R =
        256: exact CD-L1 0.38e-3, NC 0.958); 200 iterations: 0.034e-3, 0.9997. 0 meshes the unsigned field,
        signed, as it is.
    normal_weight : float
        Weight of the normal-supervision loss when the input has normals (0 = off). Normals passed to
        :func:`tiled_gridpull.reconstruct` (or ``--normals``) switch it to ``NORMALS_WEIGHT`` (1) when it is
        not set.
    levels : int
        Resolution levels (at most; fewer when the coarsest lattice would have fewer than 32 cells across;
        default 3). 1 is the paper's single-level solve. With ``L > 1`` the field is first solved on a lattice with
        ``2^(L-1)`` times larger cells (``coarse_iterations`` with the schedule above), then refined
        level by level (cells halved, values transferred by trilinear interpolation), each refinement over a
        ``refine_m2`` band with ``refine_lr`` decaying every ``refine_lr_step``; the finest level runs
        ``iterations``, the others ``coarse_iterations``.
    coarse_iterations, refine_m2, refine_lr, refine_lr_step
        See ``levels``.
    middle_iterations : int
        Iterations of the levels between the coarsest and the finest (0: ``coarse_iterations``).
    refine_gamma, refine_sigma, refine_tv_form
        Gradient-consistency weight, query noise (cells) and TV form of the refinement levels. Once the coarse level
        has settled inside and outside, wider queries and a strong gradient-consistency term smooth the
        surface at the cell scale (see docs/solver.md for the measurements).
    knn : int
        Candidate list size of the nearest-neighbour cache.
    queries_per_point : float
        0 (paper): every iteration draws ``queries`` queries. ``r > 0``: a level holding ``N`` points (after
        the coarse levels' thinning) draws ``min(queries, max(min_queries, ceil(r N)))`` per iteration, so
        a tile's query cost follows what it holds (a tile of 500 points gets ``min_queries``, not 50,000).
    min_queries : int
        Floor of the per-iteration query count when ``queries_per_point > 0``.
    query_pool : int
        0 (paper): fresh queries every iteration. ``B > 0`` (default 200): each level draws ``B`` batches of
        queries once, finds their nearest points in one go, and cycles through them (NeuralPull's precomputed
        queries), so nearest-neighbour search costs ``B`` batches instead of one per iteration. Pays where that
        search dominates: dense LiDAR tiles (see docs/solver.md).
    seed : int
        Random seed (queries). Results are bitwise reproducible for a given seed.
    noise_cells : float
        One-shape mode: 0 keeps ``resolution``; > 0 lowers it (never raises it) so that the finest cell is at
        least ``noise_cells`` x the cloud's estimated noise sigma (:func:`tiled_gridpull.noise.estimate_noise`).
        A field whose cell is finer than the noise reproduces the noise; ``configs/noisy.yaml`` uses 0.8 (after its
        robust denoising), ``configs/very_noisy.yaml`` 1.2.
    denoise : int
        One-shape mode: passes of :func:`tiled_gridpull.noise.project_to_local_planes` (each point moved onto
        the plane of its ``denoise_neighbors`` nearest neighbours) before the noise estimate and the solve;
        0 (default) leaves the points as they are. ``configs/noisy.yaml`` uses 2.
    denoise_neighbors : int
        Neighbours per plane fit of ``denoise``.
    denoise_bandwidth : float
        0: ``denoise`` fits plain least-squares planes. > 0: robust (bilateral) planes whose range scale is this
        many estimated noise sigmas, so thin walls and sharp edges keep their sheets apart.
    """

    resolution: int = setting(256, solve=False)
    margin: int = setting(4, solve=False)
    m1: int = setting(3)
    m2: int = setting(14)
    iterations: int = setting(800)
    queries: int = setting(50_000)
    queries_per_point: float = setting(0.0)
    min_queries: int = setting(2048)
    lr: float = setting(1.0)
    lr_decay: float = setting(0.3)
    lr_step: int = setting(400)
    alpha: float = setting(1.0)
    beta: float = setting(1.0)
    gamma: float = setting(0.005)
    tv_form: str = setting("sqrt")
    query_sigma: float = setting(0.2)
    init_radius: float = setting(2.0, sphere_only=True)
    mode: str = setting("sdf")
    udf_beta: float = setting(0.1)
    udf_polish: int = setting(200)
    normal_weight: float = setting(0.0, solve=False)
    levels: int = setting(3)
    coarse_iterations: int = setting(800)
    middle_iterations: int = setting(0)
    refine_m2: int = setting(8)
    refine_lr: float = setting(0.3)
    refine_lr_step: int = setting(200)
    refine_gamma: float = setting(3.0)
    refine_sigma: float = setting(0.5)
    refine_tv_form: str = setting("squared")
    knn: int = setting(16)
    query_pool: int = setting(200)
    seed: int = setting(0)
    noise_cells: float = setting(0.0)
    denoise: int = setting(0)
    denoise_neighbors: int = setting(64)
    denoise_bandwidth: float = setting(0.0)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", int):
                if isinstance(value, bool) or not isinstance(value, int):
                    if isinstance(value, float) and value.is_integer():
                        object.__setattr__(self, f.name, int(value))
                    else:
                        raise ConfigError(f"{f.name} must be an integer, got {value!r}")
                if abs(getattr(self, f.name)) >= 1 << 62:
                    raise ConfigError(f"{f.name} is out of range (an integer of "
                                      f"{getattr(self, f.name).bit_length()} bits)")
            elif f.type in ("float", float):
                object.__setattr__(self, f.name, finite_number(f.name, value))
            elif f.type in ("str", str):
                if value not in _CHOICES[f.name]:
                    raise ConfigError(f"{f.name} must be one of {', '.join(_CHOICES[f.name])}; got {value!r}")
        positive = ["resolution", "iterations", "queries", "min_queries", "lr", "lr_step", "knn", "levels",
                    "coarse_iterations", "refine_lr", "refine_lr_step", "refine_sigma"]
        if self.denoise_neighbors < 4:
            raise ConfigError(f"denoise_neighbors must be at least 4 (a plane fit), got {self.denoise_neighbors!r}")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)!r}")
        nonneg = ["margin", "m1", "m2", "alpha", "beta", "gamma", "query_sigma", "init_radius", "normal_weight",
                  "seed", "refine_m2", "refine_gamma", "noise_cells", "udf_beta", "udf_polish", "query_pool",
                  "denoise", "denoise_bandwidth", "queries_per_point", "middle_iterations"]
        for name in nonneg:
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0 < self.lr_decay <= 1:
            raise ConfigError(f"lr_decay must be in (0, 1], got {self.lr_decay!r}")
        if self.m1 > self.m2:
            raise ConfigError(f"m1 ({self.m1}) must not exceed m2 ({self.m2})")
        if self.levels > 1 and self.m1 > self.refine_m2:
            raise ConfigError(f"m1 ({self.m1}) must not exceed refine_m2 ({self.refine_m2})")
        if self.levels > 4:
            raise ConfigError(f"levels must be at most 4 (coarsest cells 8x the finest), got {self.levels}")

        if self.resolution < 2 * self.margin + 4:
            raise ConfigError(f"resolution {self.resolution} is too small for margin {self.margin}")

    def replace(self, **changes: Any) -> SolverConfig:
        """Copy with some fields changed (validated)."""
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            raise ConfigError(f"unknown solver option(s): {', '.join(sorted(unknown))}")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """Plain dict of all settings."""
        return dataclasses.asdict(self)

    def solve_settings(self, sphere_init: bool) -> dict:
        """The settings that can change a tile solve's result (fields marked ``solve``), for resume keys.

        ``sphere_init``: the solve starts from the sphere, so its radius counts too.
        """
        return {f.name: getattr(self, f.name) for f in fields(self)
                if f.metadata["solve"] and (sphere_init or not f.metadata["sphere_only"])}

    def levels_for(self, cells: int) -> int:
        """Levels used on a lattice ``cells`` across: at most ``levels``, fewer when the coarsest would have
        fewer than 32 cells across."""
        n = 1
        while n < self.levels and (int(cells) >> n) >= MIN_COARSE_CELLS:
            n += 1
        return n

    def queries_for(self, n_points: int | None) -> int:
        """Queries per iteration on a level holding ``n_points`` points (``None``: unknown, the most)."""
        if self.queries_per_point <= 0 or n_points is None:
            return self.queries
        return int(min(self.queries, max(self.min_queries, math.ceil(self.queries_per_point * n_points))))

    def level_settings(self, level: int, n_levels: int, n_points: int | None = None) -> LevelSchedule:
        """The schedule of ``level`` (0 = coarsest) out of ``n_levels``, for a level holding ``n_points`` points
        (``None``: the most queries the settings allow)."""
        iterations = self.iterations if level == n_levels - 1 else self.coarse_iterations
        if 0 < level < n_levels - 1 and self.middle_iterations:
            iterations = self.middle_iterations
        # a pool longer than the level would never be cycled through
        common = {"iterations": iterations, "query_pool": min(self.query_pool, iterations),
                  "queries": self.queries_for(n_points)}
        if level == 0:
            return LevelSchedule(**common, lr=self.lr, lr_step=self.lr_step, m2=self.m2, gamma=self.gamma,
                                 sigma=self.query_sigma, tv_form=self.tv_form)
        return LevelSchedule(**common, lr=self.refine_lr, lr_step=self.refine_lr_step, m2=self.refine_m2,
                             gamma=self.refine_gamma, sigma=self.refine_sigma, tv_form=self.refine_tv_form)

    def total_iterations(self, cells: int) -> int:
        """Iterations of a solve on a lattice ``cells`` across, over all its levels and a UDF polish."""
        levels = self.levels_for(cells)
        total = sum(self.level_settings(level, levels).iterations for level in range(levels))
        return total + (self.udf_polish if self.mode == "udf" else 0)

    def polish_settings(self) -> LevelSchedule:
        """Schedule of the signed refinement that ends a UDF solve: a refinement level's (even after a one-level
        solve: the polish refines a field that has settled), for ``udf_polish`` iterations, the learning rate
        in four stages over them (as over a refinement level's 800 at 200 each)."""
        its = self.udf_polish
        return dataclasses.replace(self.level_settings(1, 2), iterations=its, query_pool=min(self.query_pool, its),
                                   lr_step=max(1, its // 4))


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
        Iterations between multiplications of the learning rate by ``SolverConfig.lr_decay``.
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
    """Read a flat YAML mapping of settings; one-line errors for a missing or malformed file or a key given
    twice."""
    import yaml

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {p}: not found")
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
