"""One cloud in, one mesh out: the single-solve workflow (shapes and small scenes).

:func:`reconstruct` validates the input, fits a lattice (``resolution`` cells across the longest side of the
bounding box, centred), solves the banded GridPull field, runs marching cubes over the optimized cells and
maps the mesh back to the input's own coordinates. The mesh carries everything needed to reproduce it
(config, lattice, version, timings) in ``mesh.metadata``.
"""

from __future__ import annotations

import logging
import time
import warnings
from typing import Any

import numpy as np

from ._version import __version__
from .attributes import ATTRIBUTE_NEIGHBORS, attribute_layout, check_mode, interpolate_attributes, select_attributes
from .cloud import PointCloud, as_points, clean_points, colors_of
from .config import NOISE_PRESETS, NOISE_SETTINGS, NORMALS_WEIGHT, SolverConfig, finite_number, split_settings
from .errors import ConfigError, InputError
from .isosurface import extract_mesh, relax_on_field
from .kernels.graph import vertex_components
from .lattice import Lattice
from .mesh import Mesh
from .mesh_repair import boundary_loops, close_holes, remove_pinched_fans, remove_small_components
from .nearest import distances_to_cloud, nearest_in_cloud
from .noise import estimate_noise, project_to_local_planes, select_treatment
from .outliers import STRETCH_LIMIT, describe, far_points, stray_points
from .solver import ProgressFn, solve
from .stitch import trim_faces

log = logging.getLogger("tiled_gridpull")

__all__ = ["reconstruct", "prepare_points", "shape_lattice"]

#: Lowest resolution ``noise_cells`` may pick: below 64 cells the schedule drops to a single level, which
#: measured far worse (bunny, 1 % noise: R = 48, one level, NC 0.54; R = 64, two levels, NC 0.92).
MIN_NOISY_RESOLUTION = 64


#: UDF mode keeps faces within this many cells, or this many median sample spacings, of the data (whichever is
#: farther). Half-sphere and terrain patch at R = 256 (exact CD-L1 x 1e3 / Hausdorff x 1e3): 100k samples
#: (spacing 0.46 cells), 1.5 cells: 0.034 / 8.5 and 0.031 / 7.9; 1 cell: 0.028 / 5.1 and 0.019 / 4.0.
#: 10k samples (1.46 cells), 1.5 cells: the gaps between samples joined up and the sheets fell into 1146
#: and 85 pieces; 2 spacings: one piece each, 0.145 / 12.0 and 0.091 / 10.3; 2.5 spacings: 0.160 / 15.2 and
#: 0.154 / 15.5.
UDF_TRIM_CELLS = 1.0
UDF_TRIM_SPACINGS = 2.0
#: Far faces enclosed by kept ones stay when none is farther than this many trim reaches from the data: gaps
#: between random samples (the true surface lay up to 2.2 reaches from the samples on the half-sphere at
#: 100k points); deeper regions are holes in the data and open (the bunny's scanned base: five holes of 21-73
#: cells, whose centres lie 10-36 cells from the samples).
UDF_GAP_REACHES = 4.0
#: what :func:`reconstruct` may do with sheets that end at the band's edge (``band_edges``)
BAND_EDGES = ("trim", "close", "keep")
#: ``band_edges="trim"`` cuts such a sheet back to M1 cells from the data, or this many median sample spacings
#: where the samples are sparser: random samples leave gaps that wide (see :func:`~.stitch.trim_faces`), and a
#: cut nearer the data would run on through them into the surface the samples support (abc_00011084 at 10k
#: points, 1.5 cells apart: 37 % of the faces lay farther than 3 cells from every sample)
BAND_EDGE_SPACINGS = 5.0
#: UDF mode drops pieces that are the nearest surface of fewer input points than a plane fit uses: the signs
#: come from local planes, and a lone stray point (one in the merged bunny scans, 0.5 from the surface)
#: otherwise came back as a closed bubble 4 cells across.
UDF_MIN_SUPPORT = 16


def shape_lattice(points: np.ndarray, config: SolverConfig) -> Lattice:
    """The finest lattice of a one-shape solve.

    ``config.resolution`` cells across the bounding box's longest side, ``config.margin`` of them empty on each
    side, and the block padded further (same cell size) so that the coarsest level of the multi-level schedule
    also has ``config.margin`` of *its* cells around the cloud. Coarsening alone would leave it one coarse cell:
    a surface on the bounding box then has no room for its pull band outside, and without the surface loss
    (``configs/noisy.yaml``) the coarse field settled into a thin sign-flipped slab along fandisk's top face
    that the finer levels kept (0.5 % noise: exact CD-L1 4.7e-3 with a 1-cell coarse margin, 1.4e-3 with 4).

    Parameters
    ----------
    points : (N, 3) float64
        The cloud, world coordinates.
    config : SolverConfig

    Returns
    -------
    Lattice
        Offset ``(0, 0, 0)``; cell size ``extent / (resolution - 2 margin)`` whatever the padding.
    """
    lattice = Lattice.fit(points, config.resolution, config.margin)
    levels = config.levels_for(max(lattice.n_cells))
    pad = config.margin * (2 ** (levels - 1) - 1)
    return Lattice.fit(points, config.resolution, config.margin, pad=pad) if pad else lattice


def prepare_points(points: Any, normals: np.ndarray | None = None, *, what: str | None = None,
                   reject_planar: bool = True) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """Validate and clean a cloud given as an array or a :class:`~tiled_gridpull.cloud.PointCloud`.

    Non-finite rows are dropped (with a warning) and exact duplicates removed; empty, too small and degenerate
    (identical, collinear, and with ``reject_planar`` coplanar) clouds raise :class:`InputError`. Messages
    name ``what``: by default a PointCloud's ``source`` (its file), else "input".

    Returns
    -------
    xyz : (N, 3) float64
    normals : (N, 3) float32 or None
    report : dict
        What cleaning did.
    """
    cloud = _prepare_cloud(points, normals, what=what, reject_planar=reject_planar)
    return cloud.xyz, cloud.normals, dict(cloud.report)


def _prepare_cloud(points: Any, normals: np.ndarray | None = None, *, what: str | None = None,
                   reject_planar: bool = True) -> PointCloud:
    """:func:`prepare_points`, returning the cleaned cloud (its attributes filtered with the points)."""
    if isinstance(points, PointCloud):
        cloud = points
        what = what or cloud.source or "input"
        if normals is not None:
            cloud.normals = np.asarray(normals, dtype=np.float32)
    else:
        what = what or "input"
        try:
            xyz = np.asarray(points, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{what}: points must be a numeric (N, 3) array") from None
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(f"{what}: points must have shape (N, 3), got {xyz.shape}")
        nrm = None
        if normals is not None:
            nrm = np.asarray(normals, dtype=np.float32)
            if nrm.shape != xyz.shape:
                raise InputError(f"{what}: normals must have the shape of the points, got {nrm.shape}")
        cloud = PointCloud(xyz=xyz, normals=nrm, source=what)
    return clean_points(cloud, what=what, reject_planar=reject_planar)


def _noise_treatment(cfg: SolverConfig, xyz: np.ndarray):
    """``cfg`` with the noise treatment ``noise.auto`` selects for ``xyz`` applied, what was decided (for the
    sidecar), and the estimate on the raw points (None when none was made)."""
    if not cfg.noise.auto:
        return cfg, {"auto": False, "chosen": None, "reason": "noise_auto is off"}, None
    default = SolverConfig()
    given = [name for name in NOISE_SETTINGS if cfg.get(name) != default.get(name)]
    if given:
        # the user chose a treatment (a preset file or single settings): theirs wins
        return cfg, {"auto": True, "chosen": None, "given": given, "reason": f"given: {', '.join(given)}"}, None
    pick, raw, figures = select_treatment(xyz)
    record = {"auto": True, "chosen": pick, "estimate": figures,
              "settings": dict(NOISE_PRESETS[pick]) if pick else {},
              "reason": (f"sigma / spacing {raw.ratio:.2f} over 64 neighbours, {figures['local_ratio']:.2f} over "
                         f"16, of the raw points" + ("" if pick else ": not noisy"))}
    if pick is None:
        return cfg, record, raw
    log.info("the cloud looks %s (noise sigma %.3g, %.2f x the sample spacing): applying the %s treatment "
             "(noise_auto; set noise_auto: false to keep the settings as given)", pick.replace("_", " "),
             raw.sigma, raw.ratio, pick)
    return cfg.replace(**NOISE_PRESETS[pick]), record, None


def _without_stray_points(cloud: PointCloud, drop: bool) -> PointCloud:
    """The cloud without the points far from the rest (``drop``), or refused where they would stretch one
    lattice over them (:func:`~tiled_gridpull.outliers.stray_points`)."""
    what = cloud.source or "input"
    if drop:
        far, box = far_points(cloud.xyz)
        if far.all():
            raise InputError(f"{what}: drop_outliers would drop every point")
        if far.any():
            warnings.warn(f"drop_outliers: {describe(int(far.sum()), len(far), box, cloud.xyz[far][0])}: dropped",
                          UserWarning, stacklevel=3)
            report = dict(cloud.report, far_points_dropped=int(far.sum()))
            cloud = cloud.take(np.flatnonzero(~far))
            cloud.report = report
    else:
        stray = stray_points(cloud.xyz)
        if stray is not None:
            far, box = stray
            raise InputError(f"{what}: {describe(int(far.sum()), len(far), box, cloud.xyz[far][0])}; one lattice "
                             f"over every point would leave the rest under 1/{STRETCH_LIMIT:g} of its width: drop "
                             "them with --drop-outliers (drop_outliers=True), or remove them")
    return cloud


def reconstruct(points: Any, *, config: SolverConfig | None = None, normals: np.ndarray | None = None,
                lattice: Lattice | None = None, progress: ProgressFn | None = None,
                min_component_cells: float = 2.0, band_edges: str = "trim", attributes: str = "all",
                drop_outliers: bool = False, **options: Any) -> Mesh:
    """Reconstruct a triangle mesh from a point cloud with GridPull.

    Parameters
    ----------
    points : (N, 3) array_like, PointCloud, or a pyvista, Open3D or trimesh point cloud or mesh
        World coordinates (any magnitude: the solver works in lattice-local coordinates); normals come with
        the object when it has them (see :func:`~tiled_gridpull.cloud.as_points`) and, like a ``PointCloud``'s,
        are used when ``normal_weight > 0``; so do its colours (:func:`~tiled_gridpull.cloud.colors_of`), carried
        onto the vertices like a file's (``attributes``).
    config : SolverConfig, optional
        Solver settings (defaults: the schedule we ship, see :class:`~tiled_gridpull.config.SolverConfig`).
        Keyword ``options`` override single fields, e.g. ``resolution=128, iterations=800, seed=1``.
    normals : (N, 3) array_like, optional
        Unit normals of the points. Passing them turns the normal loss on: ``normal_weight`` becomes
        :data:`~tiled_gridpull.config.NORMALS_WEIGHT` (1) unless the config sets a weight above 0 or
        ``normal_weight`` is given as a keyword (``normal_weight=0`` keeps the loss off). In UDF mode the normals
        then also orient the signs. Normals carried by a ``PointCloud`` are used only when ``normal_weight > 0``.
    lattice : Lattice, optional
        Use this lattice instead of fitting one to the cloud.
    progress : callable, optional
        ``progress(iteration, total, stats)``.
    min_component_cells : float
        Closed pieces whose bounding box is smaller than this many cells on every side are dropped: they are
        below the lattice's resolution (sign-flip bubbles of one or two cells), not structures it can resolve.
        0 keeps everything.
    band_edges : {"trim", "close", "keep"}
        Signed mode: what becomes of a sheet that left the data and ran into the band's edge (a boundary loop
        every vertex of which lies beyond the pull band, M1 cells, from the points). A thin-walled tube whose
        bore takes the sign of its wall grows such sheets: caps over the bore's mouths that stop at the band
        edge. ``trim`` (default) cuts every such sheet back to the data: its faces farther than M1 cells (or
        ``BAND_EDGE_SPACINGS`` median sample spacings, where the samples are sparser) from the points go, the
        faces the data supports stay, and the mesh is open where the data is silent; islands the cut leaves
        around a few stray samples go too (pieces that are the nearest surface of fewer than 16 points).
        ``close`` closes each such loop with a fan of triangles (watertight, but the caps stay and cost
        accuracy: docs/solver.md, "Thin-walled tubes"); ``keep`` leaves the sheets as extracted. Holes next to
        the data (real gaps in a scan) are never touched. The metadata's ``band_edges`` records the rule and
        what it did (before the small closed pieces of ``min_component_cells`` are dropped). Replaces the
        ``close_band_holes`` keyword of earlier versions (True: ``close``, False: ``keep``; still accepted,
        with a ``DeprecationWarning``).
    attributes : {"all", "rgb", "none"}
        Which per-point attributes of a ``PointCloud`` (colour, intensity, classification, LAS extra
        dimensions) are interpolated onto the vertices (:mod:`~tiled_gridpull.attributes`): every one it has
        (default), the colour only, or none. They land in ``mesh.vertex_attributes``; the metadata's
        ``vertex_attributes`` records the rule and what was carried.
    drop_outliers : bool
        Points far from the rest (:mod:`~tiled_gridpull.outliers`: a stray ``(0, 0, 0)`` in a survey) are
        dropped, with a warning. Without it, a cloud whose far points stretch it more than
        :data:`~tiled_gridpull.outliers.STRETCH_LIMIT` times is refused (:class:`InputError` naming them): the
        lattice fitted to every point would leave the rest a few cells wide, or none. Only when ``lattice`` is
        not given.

    Returns
    -------
    Mesh
        Vertices float64 in the input's coordinates, faces int64 oriented outward; ``metadata`` holds the
        config, lattice, version, timings and solve statistics; ``vertex_attributes`` the carried attributes.
    """
    t0 = time.perf_counter()
    cfg = config or SolverConfig()
    if "close_band_holes" in options:
        # the keyword of earlier versions: True closed the band-edge loops with fans, False left them
        old = options.pop("close_band_holes")
        warnings.warn("close_band_holes is replaced by band_edges ('close' for True, 'keep' for False)",
                      DeprecationWarning, stacklevel=2)
        band_edges = "close" if old else "keep"
    if options:
        cfg = cfg.replace(**options)
    # only normals the caller hands over switch the loss on: an object's own normals (often estimated and
    # unoriented, e.g. Open3D's) are treated like a PointCloud's, used when a weight is set
    if normals is not None and cfg.losses.normal_weight == 0 and "normal_weight" not in split_settings(options)[0]:
        cfg = cfg.replace(normal_weight=NORMALS_WEIGHT)
    min_component_cells = finite_number("min_component_cells", min_component_cells)
    if min_component_cells < 0:
        raise ConfigError(f"min_component_cells must be >= 0, got {min_component_cells!r}")
    check_mode(attributes)
    if not isinstance(drop_outliers, bool):
        raise ConfigError(f"drop_outliers must be true or false, got {drop_outliers!r}")
    if band_edges not in BAND_EDGES:
        raise ConfigError(f"band_edges must be one of {', '.join(BAND_EDGES)}, got {band_edges!r}")
    if cfg.mode == "udf" and band_edges != "trim":
        raise ConfigError(f"band_edges {band_edges!r} applies to signed mode (udf mode ends its sheets at the data "
                          "already)")
    colors = colors_of(points)
    points, own_normals = as_points(points)
    if colors:  # a pyvista, Open3D or trimesh cloud with colour: carried like a file's
        points = PointCloud(np.asarray(points, dtype=np.float64), attributes=colors, source="input")
    # an open flat patch is a surface for the unsigned mode (a sheet); the signed mode needs an inside
    cleaned = _prepare_cloud(points, own_normals if normals is None else normals, reject_planar=cfg.mode == "sdf")
    if lattice is None:
        cleaned = _without_stray_points(cleaned, drop_outliers)
    xyz, nrm, report = cleaned.xyz, cleaned.normals, dict(cleaned.report)
    # interpolated from the cleaned points where they were read (not where denoising moves them)
    point_attrs, attr_xyz = select_attributes(cleaned.attributes, attributes), xyz
    if cfg.losses.normal_weight > 0 and nrm is None:
        raise InputError("normal_weight > 0 needs input normals, but the cloud has none")
    cfg, treatment, raw_noise = _noise_treatment(cfg, xyz)
    if cfg.noise.denoise_passes > 0:
        xyz = project_to_local_planes(xyz, cfg.noise.denoise_neighbors, cfg.noise.denoise_passes,
                                      cfg.noise.denoise_bandwidth)
    noise = raw_noise if raw_noise is not None and cfg.noise.denoise_passes == 0 else estimate_noise(xyz)
    if lattice is None:
        if cfg.noise.cell_sigmas > 0 and noise.sigma > 0:
            extent = float((xyz.max(axis=0) - xyz.min(axis=0)).max())
            coarse = max(MIN_NOISY_RESOLUTION, int(extent / (cfg.noise.cell_sigmas * noise.sigma)))
            if coarse < cfg.resolution:
                cfg = cfg.replace(resolution=coarse)
        lattice = shape_lattice(xyz, cfg)
    # measured: bunny with noise of 0.8 cell at R = 128 already came out rough (NC 0.69)
    if noise.noisy and cfg.losses.beta > 0 and noise.sigma > 0.5 * lattice.cell_size:
        warnings.warn(f"the cloud looks noisy (sigma ~ {noise.sigma:.3g}, {noise.sigma / lattice.cell_size:.1f} "
                      f"cells at this resolution): the surface will follow the noise; try configs/noisy.yaml "
                      f"(configs/very_noisy.yaml for noise near 1 % of the bounding-box diagonal)",
                      UserWarning, stacklevel=2)
    t_prep = time.perf_counter()
    fld = solve(xyz, lattice, cfg, normals=nrm, progress=progress)
    t_solve = time.perf_counter()
    mesh = extract_mesh(fld)
    if cfg.mode == "sdf":
        # before the band's edges are dealt with: a fan's centre lies off the band, where there is no field to
        # project on
        mesh = relax_on_field(mesh, fld, cfg.relax)
    sheet: dict = {}
    if cfg.mode == "udf" and mesh.n_faces:
        mesh, sheet = _end_sheet_at_data(mesh, xyz, max(UDF_TRIM_CELLS * lattice.cell_size,
                                                        UDF_TRIM_SPACINGS * noise.spacing))
    edges: dict = {"rule": None}
    flipped = False
    if cfg.mode == "sdf" and mesh.n_faces:
        reach = cfg.sampling.m1 * lattice.cell_size
        mesh, flipped, edges = _end_signed_mesh(mesh, xyz, reach, max(reach, BAND_EDGE_SPACINGS * noise.spacing),
                                                band_edges)
    removed = 0
    if min_component_cells > 0 and mesh.n_faces:
        mesh, removed = remove_small_components(mesh, min_component_cells * lattice.cell_size)
    if point_attrs:
        mesh = mesh.with_vertex_attributes(interpolate_attributes(mesh.vertices, attr_xyz, point_attrs))
    t_mesh = time.perf_counter()
    info = {k: v for k, v in fld.info.items() if k != "history"}
    mesh.metadata.update({
        "generator": f"tiled_gridpull {__version__}",
        "version": __version__,
        "config": cfg.to_dict(),
        "lattice": lattice.to_dict(),
        "input": {"points": int(len(xyz)), **report},
        "device": info.get("device"),
        "solve": info,
        "loss_history": fld.info.get("history", []),
        "noise_estimate": {**noise.to_dict(), "cells": noise.sigma / lattice.cell_size},
        "noise_treatment": treatment,
        "small_components_removed": int(removed),
        **({"udf_trim": sheet} if sheet else {}),
        "orientation_flipped": flipped,
        "band_edges": edges,
        "relaxed": int(cfg.relax) if cfg.mode == "sdf" else 0,
        "vertex_attributes": {"rule": attributes, "carried": attribute_layout(point_attrs),
                              "neighbors": ATTRIBUTE_NEIGHBORS},
        "timings_s": {"prepare": t_prep - t0, "solve": t_solve - t_prep, "mesh": t_mesh - t_solve,
                      "total": t_mesh - t0},
    })
    return mesh


def _band_edge_loops(mesh: Mesh, points: np.ndarray, min_distance: float) -> list[np.ndarray]:
    """The boundary loops whose every vertex is at least ``min_distance`` (world units) from the points."""
    loops = boundary_loops(mesh)
    if not loops:
        return []
    d = distances_to_cloud(mesh.vertices[np.concatenate(loops)], points)
    nearest = np.minimum.reduceat(d, np.cumsum([0] + [len(loop) for loop in loops[:-1]]))
    return [loop for loop, dmin in zip(loops, nearest) if dmin >= min_distance]


def _end_signed_mesh(mesh: Mesh, points: np.ndarray, reach: float, cut: float,
                     rule: str) -> tuple[Mesh, bool, dict]:
    """Orient a signed mesh outward and apply the ``band_edges`` rule to the sheets that end at the band's edge.

    Parameters
    ----------
    mesh : Mesh
        As extracted (and relaxed), world units.
    points : (N, 3) float64
        The input points.
    reach : float
        A boundary loop every vertex of which lies this far from the points ends at the band's edge (M1 cells).
    cut : float
        ``trim``: how far from the points such a sheet is cut back (at least ``reach``).
    rule : {"trim", "close", "keep"}

    Returns
    -------
    mesh : Mesh
    flipped : bool
        Whether the faces were turned over.
    record : dict
        ``rule``, ``loops`` (band-edge loops found), ``loops_closed``, ``faces_trimmed``,
        ``unsupported_pieces_removed`` (counted here, before the small closed pieces are dropped).
    """
    loops = _band_edge_loops(mesh, points, reach)
    sealed = close_holes(mesh, loops) if loops else mesh
    # The losses are unchanged by f -> -f, so the sign comes only from the initialisation: a sphere at the lattice
    # centre lies in the hole of a torus or a mug's handle and ends up *outside*. A closed surface whose enclosed
    # volume comes out negative is therefore inside out; flip it (nested shells keep their relative orientation).
    # It is judged with the band-edge loops closed, whatever the rule: what is left of an open sheet once it is
    # cut back can be nearly flat, and its signed volume then says nothing.
    flipped = bool(sealed.signed_volume(normalized=True) < 0)
    record = {"rule": rule, "loops": len(loops), "loops_closed": 0, "faces_trimmed": 0,
              "unsupported_pieces_removed": 0}
    if rule == "close":
        mesh = sealed
        record["loops_closed"] = len(loops)
    elif rule == "trim" and loops:
        n = mesh.n_faces
        mesh, cut_vertices = _trim_band_edge_sheets(mesh, points, cut, loops)
        record["faces_trimmed"] = n - mesh.n_faces
        # a sheet that passed near a few stray samples leaves islands around them once cut: among the pieces the
        # cut touched, those that are the nearest surface of too few points go (never the best-supported piece)
        mesh, record["unsupported_pieces_removed"] = _drop_unsupported_pieces(mesh, points, UDF_MIN_SUPPORT,
                                                                              among=cut_vertices)
    if flipped:
        mesh = Mesh(mesh.vertices, mesh.faces[:, ::-1].copy(), mesh.metadata, mesh.vertex_attributes)
    return mesh, flipped, record


def _trim_band_edge_sheets(mesh: Mesh, points: np.ndarray, reach: float,
                           loops: list[np.ndarray]) -> tuple[Mesh, np.ndarray]:
    """Cut the sheets that end at the band-edge ``loops`` (:func:`_band_edge_loops` at ``reach``) back to
    ``reach`` (world units) from ``points``.

    The faces farther than ``reach`` from the points form connected regions; those that hold a vertex of a
    band-edge loop go (:func:`~tiled_gridpull.stitch.trim_faces` with those loops as the mesh's ends). Far
    regions elsewhere (a surface bridging a gap between samples, enclosed by supported faces) stay. Returns the
    mesh and its vertices that lay on a removed face (the cut's edge)."""
    if not loops:
        return mesh, np.zeros(0, np.int64)
    out, kept = trim_faces(mesh, np.arange(mesh.n_vertices), points, reach, keep_gaps=np.inf,
                           ends=np.concatenate(loops))
    # a kept vertex with fewer faces than before lost one to the cut
    before = np.bincount(mesh.faces.ravel(), minlength=mesh.n_vertices)[kept]
    return out, np.flatnonzero(np.bincount(out.faces.ravel(), minlength=out.n_vertices) < before)


def _end_sheet_at_data(mesh: Mesh, points: np.ndarray, reach: float) -> tuple[Mesh, dict]:
    """UDF mode: cut an open sheet back to the data.

    Past the data's edge the signed field's zero level runs on along the last tangent planes to the band's
    edge. Faces farther than ``reach`` from the points are dropped where they reach that edge or where they lie
    deeper than a gap between samples (a hole in the data), then pinches left along the cut and pieces without
    data of their own."""
    mesh, _ = trim_faces(mesh, None, points, reach, keep_gaps=UDF_GAP_REACHES * reach)
    mesh, pinched = remove_pinched_fans(mesh)
    mesh, unsupported = _drop_unsupported_pieces(mesh, points, UDF_MIN_SUPPORT)
    return mesh, {"reach": reach, "pinched_faces_removed": pinched, "unsupported_pieces_removed": unsupported}


def _drop_unsupported_pieces(mesh: Mesh, points: np.ndarray, min_points: int,
                             among: np.ndarray | None = None) -> tuple[Mesh, int]:
    """Drop the connected pieces that are the nearest piece of fewer than ``min_points`` points (never the
    best-supported piece: a sparse cloud keeps its surface); with ``among`` (vertex indices), only the pieces
    that hold one of those vertices may go."""
    if mesh.n_faces == 0 or (among is not None and len(among) == 0):
        return mesh, 0
    labels, count = vertex_components(mesh.n_vertices, mesh.faces)
    if count == 1:
        return mesh, 0
    _, nearest = nearest_in_cloud(points, mesh.vertices)
    support = np.bincount(labels[nearest], minlength=count)
    support[support.argmax()] = max(support.max(), min_points)
    if among is not None:
        spared = np.ones(count, bool)
        spared[labels[among]] = False
        support[spared] = np.maximum(support[spared], min_points)
    keep = support[labels[mesh.faces[:, 0]]] >= min_points
    used = np.unique(labels[mesh.faces[:, 0]])
    dropped = int(np.count_nonzero(support[used] < min_points))
    return (mesh.submesh(keep), dropped) if dropped else (mesh, 0)
