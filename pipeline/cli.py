"""``tiled-gridpull`` command line.

Exit codes: 0 success; 2 bad option or config value; 3 bad input file; 4 missing optional dependency;
5 memory budget exceeded; 6 some tiles failed (the rest of the mesh was written); 130 interrupted;
1 internal error (a bug: rerun with ``-vv`` for the traceback and report it).
"""

from __future__ import annotations

import argparse
import errno
import json
import logging
import math
import os
import sys
import time
from pathlib import Path

from tiled_gridpull.errors import GridPullError

log = logging.getLogger("tiled_gridpull")


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Shows the default of options that have one (settings left to the config file say so in their help)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if "%(default)" not in text and action.default not in (None, False, argparse.SUPPRESS) \
                and action.option_strings and action.nargs != 0:
            text += " (default: %(default)s)"
        return text


class _Parser(argparse.ArgumentParser):
    """Usage mistakes as one line, like every other error (argparse prints the whole usage block first)."""

    def error(self, message: str):
        self.exit(2, f"error: {message} (see `{self.prog} --help`)\n")


def _add_common(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("-v", "--verbose", action="count", default=0, help="more output (-vv: debug, tracebacks)")
    g.add_argument("-q", "--quiet", action="store_true", help="only errors")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (also used to document the options)."""
    from tiled_gridpull import __version__

    parser = _Parser(
        prog="tiled-gridpull", formatter_class=_Formatter,
        description="GridPull surface reconstruction for point clouds, from one shape to KITTI-scale LiDAR "
                    "sequences (tiled on Dask).",
        epilog=__doc__.split("\n", 1)[1])
    parser.add_argument("--version", action="version", version=f"tiled-gridpull {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser("reconstruct", formatter_class=_Formatter,
                       help="point cloud(s) -> mesh (one solve, or tiled with --voxel-size)",
                       description="Reconstruct a mesh. Without --voxel-size the cloud is solved as one shape on "
                                   "a lattice of --resolution cells; with it, the cloud is cut into tiles of a "
                                   "global lattice and solved on Dask.")
    r.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="PLY, XYZ/TXT/PTS/CSV, NPY, LAS/LAZ, COPC (.copc.laz) or EPT (ept.json; each tile read "
                        "from their index on a worker), PCD, E57 (e57 extra), KITTI .bin or a KITTI sequence "
                        "directory")
    r.add_argument("-o", "--output", required=True,
                   help="output mesh (.ply or .obj); a .json sidecar is written beside it")
    r.add_argument("--overwrite", action="store_true",
                   help="replace an existing output mesh or sidecar that tiled-gridpull did not write (inputs are "
                        "never replaced)")
    r.add_argument("--config", help="YAML file of settings (see configs/)")
    r.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one setting (repeatable), by flat or dotted name: --set alpha=2, --set refine.lr=0.2")
    r.add_argument("--resolution", type=int, help="cells across the longest side (one-shape mode; default 256)")
    r.add_argument("--iterations", type=int, help="optimizer iterations at the finest level (default 800)")
    r.add_argument("--seed", type=int, help="random seed (default 0)")
    r.add_argument("--mode", choices=("sdf", "udf"), help="signed (closed surfaces) or unsigned (open) field")
    r.add_argument("--device", choices=("auto", "cpu", "cuda"),
                   help="where the solver runs: a CUDA GPU (cuda, needs the cuda extra), the CPU's threads (cpu), "
                        "or a GPU when numba-cuda sees one (auto, default)")
    r.add_argument("--normals", action="store_true",
                   help="supervise the field's gradient with the input's normals (PLY nx ny nz, LAS extra bytes, "
                        "XYZ/NPY columns 4-6): normal_weight 1 unless the config sets it; one-shape mode")
    r.add_argument("--band-edges", choices=("trim", "close", "keep"),
                   help="one-shape signed mode: a surface that runs past the data to the solved band's edge (a cap "
                        "over a bore, a scan's unseen side) is cut back to the data (trim, default), sealed with a "
                        "fan of triangles so the mesh is watertight (close), or kept as extracted (keep)")
    r.add_argument("--float32", action="store_true",
                   help="store vertices as float32 relative to an offset recorded in the header (half the size)")
    r.add_argument("--attributes", choices=("all", "rgb", "none"),
                   help="per-point values interpolated onto the mesh's vertices: every one the input has (colour, "
                        "intensity, classification, LAS extra dimensions; default all), the colour only, or none "
                        "(both modes; config key attributes)")
    t = r.add_argument_group("tiled mode (scenes; enabled by --voxel-size or a config that sets voxel_size)")
    t.add_argument("--voxel-size", metavar="SIZE",
                   help="cell size in the data's units (0.1), or with a unit (0.1m, 0.33ft; m, cm, mm, ft, us-ft) "
                        "converted to the unit of the input's CRS (metres when it declares none), or auto "
                        "(from the points' spacing)")
    t.add_argument("--quality", choices=("draft", "standard", "fine"),
                   help="schedule preset: draft (minutes where standard takes tens of them, a few times less "
                        "accurate; BENCHMARKS.md, 'Quality presets'), standard (the config as given) or fine; with "
                        "--voxel-size auto it also scales the cell (draft x1.5, fine x0.5); --set wins over it "
                        "(default: the config's quality key, else standard)")
    t.add_argument("--tile-size", type=float,
                   help="tile core size in the data's units (default: 256 cells, following --voxel-size)")
    t.add_argument("--overlap", type=float,
                   help="overlap solved around each tile core, in the data's units (default: 32 cells)")
    t.add_argument("--workers", type=int,
                   help="worker processes of the local Dask cluster (default: one per core); 0: no cluster, the "
                        "tiles one after the other in this process, each on every core (no cluster to start: "
                        "1.4-2.5 s less on a 190k-point file of 2 tiles, 2 cores; a tile that runs out of memory "
                        "then stops the whole job)")
    t.add_argument("--scheduler", metavar="ADDR", help="run on an existing Dask scheduler, e.g. tcp://host:8786")
    t.add_argument("--batch-tiles", type=int, metavar="N",
                   help="on a card: most tiles solved together, one launch per step for all of them, on a worker "
                        "that holds the card (the local cluster starts one; on a scheduler, start one per card "
                        "with `dask worker --resources GPU=1`); 1 solves each tile in a task of its own "
                        "(default: 16)")
    t.add_argument("--work-dir", help="job directory for intermediate files (default: OUTPUT with .job suffix)")
    t.add_argument("--frames", metavar="START:STOP", help="KITTI sequences: frame range, e.g. 3000:4000")
    t.add_argument("--trajectory", metavar="FILE",
                   help="sensor trajectory for LAS/LAZ points with GPS time: text/CSV 'time x y z' in the points' "
                        "coordinates, or SBET (.sbet/.out, projected into the points' CRS); every point gets its "
                        "sensor origin, so walls face the street they were scanned from")
    t.add_argument("--fail-fast", action="store_true", help="stop at the first tile that fails")
    t.add_argument("--drop-outliers", action="store_true", default=None,
                   help="drop points far from the rest of the input (a stray (0,0,0) in a UTM cloud) before planning")
    t.add_argument("--tile-meshes", metavar="DIR", help="also write one PLY per tile into DIR")
    t.add_argument("--3d-tiles", dest="tiles3d", metavar="DIR",
                   help="also write the mesh as an OGC 3D Tiles 1.1 tileset into DIR (tileset.json, one glb per "
                        "tile, coarser levels of detail above them) for CesiumJS, deck.gl or iTowns, georeferenced "
                        "from the input's CRS (needs the tiles3d extra)")
    t.add_argument("--3d-tiles-crs", dest="tiles3d_crs", metavar="CRS",
                   help="with --3d-tiles: the CRS of the input's coordinates (EPSG:32632, or WKT) when the input "
                        "declares none, or to use instead of the one it declares")
    t.add_argument("--max-memory", metavar="SIZE",
                   help="memory one worker may use for one tile, e.g. 2GB or 1500MB: tiles estimated to need more "
                        "are refused before anything is solved")
    t.add_argument("--min-transfer-rate", metavar="BYTES_PER_S",
                   help="URL inputs: a transfer slower than this on average after its first 10 s is a failed "
                        "attempt (retried, then refused), so a server that trickles bytes cannot keep a job "
                        "running indefinitely (default 1024; 0: no minimum)")
    t.add_argument("--dry-run", action="store_true",
                   help="print the tile plan, memory and a rough time estimate; solve nothing")
    _add_common(r)

    sm = sub.add_parser("sample", formatter_class=_Formatter, help="write a synthetic sample with ground truth",
                        description="Synthetic data made by the project: a street scanned by a simulated 64-beam "
                                    "LiDAR (LAZ and/or KITTI sequence, with its ground-truth mesh) or an analytic "
                                    "shape (PLY points + ground-truth mesh).")
    sm.add_argument("kind", choices=("street", "sphere", "torus", "box"))
    sm.add_argument("out_dir")
    sm.add_argument("--points", type=int, default=300_000, help="approximate number of points")
    sm.add_argument("--kitti", action="store_true", help="street: also write a KITTI-format sequence")
    sm.add_argument("--copc", action="store_true",
                    help="street: also write street.copc.laz (COPC; needs the copc extra)")
    sm.add_argument("--ept", action="store_true", help="street: also write Entwine Point Tiles (street_ept/ept.json)")
    sm.add_argument("--layout", choices=("street", "grid"), default="street",
                    help="street: one straight street ('street'), or a ~200 m x 200 m grid of 3 x 3 streets "
                         "scanned by one pass per street ('grid')")
    sm.add_argument("--origin", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                    help="street: offset added to every coordinate (e.g. UTM-like 500000 4000000 100)")
    sm.add_argument("--range-noise", type=float, default=0.0, metavar="M",
                    help="street: Gaussian noise of each return's range, in metres (a survey scanner: about 0.01-0.03)")
    sm.add_argument("--beam-bias", type=float, default=0.0, metavar="DEG",
                    help="street: standard deviation of each beam's fixed elevation error, in degrees (a calibrated "
                         "HDL-64: about 0.1; each ring then sits a few cm off the ground, as on KITTI)")
    sm.add_argument("--frames", type=int, default=None, metavar="N",
                    help="street: N frames 1 m apart, as a 10 Hz scanner on a car driving 36 km/h (default: "
                         "max(4, points / 100,000), one sensor position's worth)")
    sm.add_argument("--seed", type=int, default=0)
    _add_common(sm)

    e = sub.add_parser("evaluate", formatter_class=_Formatter,
                       help="accuracy of a mesh against a ground-truth mesh",
                       description="Chamfer-L1/L2, normal consistency, F-score and Hausdorff (ONet/SAP/NeuralPull "
                                   "conventions): the exact figures (samples to the other mesh's surface) "
                                   "first, then mesh facts, then the sample-to-sample figures, whose floor "
                                   "(chamfer_l1_floor) grows with the meshes' area: read the exact ones for "
                                   "scenes.")
    e.add_argument("mesh")
    e.add_argument("gt")
    e.add_argument("--samples", type=int, default=100_000, help="area-uniform samples per mesh")
    e.add_argument("--thresholds", type=float, nargs="+", default=[0.002, 0.004, 0.01],
                   help="F-score thresholds, in the meshes' units")
    e.add_argument("--normalize", action="store_true",
                   help="scale both meshes by the GT's bounding box (longest side 1) before measuring")
    e.add_argument("--no-exact", action="store_true", help="skip the exact point-to-surface distances")
    e.add_argument("--observed", metavar="CLOUD",
                   help="score only the ground truth observed by this point cloud (partial scans)")
    e.add_argument("--observed-radius", type=float, default=0.2,
                   help="with --observed: GT samples farther than this from every input point are left out")
    e.add_argument("--footprint", type=float, nargs="+", metavar="R",
                   help="with --observed: also score the footprint, the ground truth within R of any input point "
                        "(recall within --footprint-tau: holes there are misses, bridges across scan-line gaps "
                        "hits), and the precision of the whole mesh within --footprint-tau")
    e.add_argument("--footprint-tau", type=float, default=0.1, metavar="TAU",
                   help="with --footprint: distance of a hit, in the meshes' units")
    e.add_argument("--json", action="store_true", help="print JSON instead of a table")
    _add_common(e)

    v = sub.add_parser("render", formatter_class=_Formatter, help="picture of a mesh (PNG, off-screen)",
                       description="Render a mesh to a PNG without a screen (pyvista off-screen: EGL or OSMesa), "
                                   "optionally with its point cloud drawn over it and/or coloured by each vertex's "
                                   "distance to a ground-truth mesh.")
    v.add_argument("mesh", help="mesh to draw (.ply, .obj, .off)")
    v.add_argument("-o", "--output", required=True, help="PNG file to write")
    v.add_argument("--cloud", metavar="CLOUD", help="point cloud to draw over the mesh (any input format)")
    v.add_argument("--gt", metavar="GT_MESH", help="colour the mesh by distance to this ground-truth mesh")
    v.add_argument("--size", type=int, nargs=2, default=[1024, 768], metavar=("W", "H"), help="pixels")
    v.add_argument("--view", choices=("iso", "top", "front", "side"), default="iso", help="camera direction")
    v.add_argument("--point-size", type=float, default=2.0, help="with --cloud: point size in pixels")
    v.add_argument("--max-points", type=int, default=200_000, help="with --cloud: points drawn at most")
    v.add_argument("--clim", type=float, nargs=2, metavar=("LO", "HI"),
                   help="with --gt: colour range in the mesh's units (default 0 to the 99th percentile)")
    v.add_argument("--edges", action="store_true", help="draw triangle edges")
    v.add_argument("--color", choices=("rgb", "intensity", "classification"),
                   help="colour the mesh by its vertex attribute: its colours, intensity (grey ramp, 1st-99th "
                        "percentile or --clim) or class codes (not with --gt)")
    _add_common(v)

    rp = sub.add_parser("report", formatter_class=_Formatter, help="per-tile table of a finished tiled job",
                        description="Print the report.json a tiled job writes in its job directory: settings, "
                                    "lattice, one row per tile (points, solve/mesh time, peak memory, first and "
                                    "last loss, faces) and totals.")
    rp.add_argument("job_dir", metavar="JOBDIR", help="job directory (default of reconstruct: OUTPUT.job) or its "
                                                      "report.json")
    rp.add_argument("--json", action="store_true", help="print the raw JSON")
    _add_common(rp)
    return parser


def _setup_logging(args) -> None:
    level = logging.WARNING if getattr(args, "quiet", False) else (
        logging.DEBUG if getattr(args, "verbose", 0) >= 2 else logging.INFO)
    logging.basicConfig(level=level, format="%(message)s", stream=sys.stderr)
    logging.captureWarnings(True)
    if getattr(args, "verbose", 0) < 2:
        # laspy's own log lines ("Could only read 3 of 5 points", lazrs errors) repeat what our one-line errors
        # say: -vv shows them (distributed's are quieted by tiled_gridpull.pipeline.job.make_client, after
        # its import has set their levels)
        logging.getLogger("laspy").setLevel(logging.CRITICAL)
        # one line per warning, like errors: Python's default adds the source path and the line of code
        import warnings

        warnings.formatwarning = lambda message, category, filename, lineno, line=None: \
            f"warning: {str(message).splitlines()[0] if str(message) else category.__name__}"


_CLI_KEYS = {"resolution": "resolution", "iterations": "iterations", "seed": "seed", "mode": "mode", "device": "device",
             "voxel_size": "voxel_size", "tile_size": "tile_size", "overlap": "overlap",
             "drop_outliers": "drop_outliers", "quality": "quality"}


def _shown_key(key) -> str:
    """A settings key for a one-line message: identifiers as they are, anything else quoted."""
    return key if isinstance(key, str) and key.isidentifier() else repr(key)


def resolve_settings(args, quality: str | None = None) -> tuple:
    """Config file, then the quality preset, then ``--set``, then explicit options -> validated (SolverConfig,
    TilingConfig or None).

    Every key is checked before any data is read: unknown keys and bad values are refused with one line. The
    preset is the last ``quality`` named (config file, ``--set quality=``, ``--quality``), or ``quality`` when
    given (the dry run's estimate of each preset); the one chosen is left in ``args.quality_chosen``.
    """
    from tiled_gridpull.config import (NOISE_SETTINGS, NORMALS_WEIGHT, SCAN_NOISE_SETTINGS, SolverConfig,
                                       drop_removed_settings, load_config_file, parse_overrides, quality_settings,
                                       split_settings)
    from tiled_gridpull.errors import ConfigError
    from tiled_gridpull.tiling import TilingConfig

    sources = [load_config_file(args.config)] if args.config else []
    sources.append(parse_overrides(args.overrides))
    sources.append({key: getattr(args, attr) for attr, key in _CLI_KEYS.items()
                    if getattr(args, attr, None) is not None})
    named_quality = None
    for source in sources:
        if "quality" in source:
            named_quality = source.pop("quality")
    chosen = named_quality if quality is None else quality
    # the preset replaces what the config file says, and --set and the options win over it
    sources.insert(1 if args.config else 0, quality_settings(chosen))
    if quality is None:
        args.quality_chosen = chosen
    # each source by flat names first: a file's nested `refine: {lr: ..}` and `--set refine_lr=..` are one setting
    solver_settings: dict = {}
    settings: dict = {}
    named = []
    for source in sources:
        mine, rest = split_settings(drop_removed_settings(source))
        solver_settings.update(mine)
        settings.update(rest)
        named.append(set(mine))
    # a noise treatment named by a source that does not also name noise_auto is the user's choice, and wins even
    # where it is the default's value (`--set denoise=0` keeps a scan's points as they are)
    choices = set(SCAN_NOISE_SETTINGS if "voxel_size" in settings else NOISE_SETTINGS)
    for names in reversed(named):
        if "noise_auto" in names:
            break
        if names & choices:
            solver_settings["noise_auto"] = False
            break
    if getattr(args, "normals", False):
        if "voxel_size" in settings:
            raise ConfigError("--normals applies to one-shape mode (tiles orient estimated normals instead)")
        solver_settings.setdefault("normal_weight", NORMALS_WEIGHT)
    if getattr(args, "attributes", None) is not None:  # the option wins over a config file's key
        settings["attributes"] = args.attributes
    for key in ("attributes", "drop_outliers", "min_component_cells"):
        if key in settings and "voxel_size" not in settings:
            # one-shape mode takes it as reconstruct's keyword (checked there), not as a tiling setting
            setattr(args, key, settings.pop(key))
    tiling_keys = set(TilingConfig.__dataclass_fields__) - {"derived", "units", "halo"}  # recorded, not settings
    unknown = set(settings) - tiling_keys
    if unknown:
        raise ConfigError(f"unknown setting(s): {', '.join(sorted(_shown_key(k) for k in unknown))}")
    solver = SolverConfig(**solver_settings)
    tiling_settings = {k: v for k, v in settings.items() if k in tiling_keys}
    tiling = None
    if chosen not in (None, "standard") and "voxel_size" not in tiling_settings:
        raise ConfigError(f"quality {chosen} applies to tiled mode: give --voxel-size too")
    if "voxel_size" in tiling_settings:
        from tiled_gridpull.tiling import check_compatible

        tiling = TilingConfig(**tiling_settings)
        check_compatible(tiling, solver)
    elif tiling_settings:
        raise ConfigError(f"tiling setting(s) {', '.join(sorted(tiling_settings))} need voxel_size (tiled mode)")
    return solver, tiling


def cmd_reconstruct(args) -> int:
    """Run ``reconstruct``."""
    from tiled_gridpull.errors import ConfigError, InputError
    from tiled_gridpull.io import check_outputs, read_points, write_mesh_and_sidecar
    from tiled_gridpull.reconstruct import reconstruct

    out = Path(args.output)
    if out.suffix.lower() not in (".ply", ".obj"):
        raise ConfigError(f"output {out}: use a .ply or .obj file name")
    cfg, tiling = resolve_settings(args)  # validated before any file is read
    if cfg.device == "cuda" and not getattr(args, "scheduler", None):
        from tiled_gridpull.device import resolve as resolve_device

        # no card: one line, exit 2, before any file is read (a --scheduler's workers hold their own cards)
        resolve_device(cfg.device)
    _set_min_transfer_rate(args)
    if tiling is not None and getattr(args, "band_edges", None) is not None:
        raise ConfigError("--band-edges applies to one-shape mode (tiled mode removes every face farther than "
                          "trim_distance from the points)")
    if tiling is not None and getattr(args, "frames", None) is not None:
        files = [p for p in args.inputs if not Path(p).is_dir()]
        if files:
            raise ConfigError(f"--frames applies to KITTI sequence directories only, not {files[0]}")
    if tiling is not None:
        # the trajectory is read as much as the points are: never an output
        reads = [*args.inputs, *([args.trajectory] if getattr(args, "trajectory", None) else [])]
        check_outputs(reads, out, work_dir=args.work_dir or out.with_suffix(".job"),
                      tile_meshes=args.tile_meshes, overwrite=args.overwrite)
        _check_tiles3d(args, reads, out)
    else:
        check_outputs(args.inputs, out, overwrite=args.overwrite)
    if tiling is not None:
        return _reconstruct_tiled(args, out, cfg, tiling)
    for opt, flag in (("tiles3d", "--3d-tiles"), ("tiles3d_crs", "--3d-tiles-crs")):
        if getattr(args, opt, None) is not None:
            raise ConfigError(f"{flag} applies to tiled mode: give --voxel-size too")
    for opt in ("workers", "scheduler", "work_dir", "frames", "max_memory", "trajectory", "batch_tiles"):
        if getattr(args, opt, None) is not None:
            raise ConfigError(f"--{opt.replace('_', '-')} applies to tiled mode: give --voxel-size too")
    if getattr(args, "band_edges", None) is not None and cfg.mode != "sdf":
        raise ConfigError("--band-edges applies to signed mode (udf mode ends its sheets at the data already)")
    if getattr(args, "dry_run", False):
        raise ConfigError("--dry-run applies to tiled mode: give --voxel-size too")
    if len(args.inputs) != 1:
        raise InputError("one-shape mode reads one input; give --voxel-size to reconstruct several files as tiles")
    # cleaned by reconstruct, whose mode decides whether a flat patch is data (udf) or degenerate (sdf)
    cloud = read_points(args.inputs[0], clean=False)
    import numpy as np

    # said here, before the progress bar: the cleaning's own warning would land on the bar's line
    bad = len(cloud) - int(np.count_nonzero(np.isfinite(cloud.xyz).all(axis=1)))
    log.info("read %s: %d points%s", args.inputs[0], len(cloud),
             f" ({bad} with NaN or infinite coordinates, dropped)" if bad else "")
    from tiled_gridpull.kernels.warmup import KERNELS, TILED_ONLY, compile_kernels
    from tiled_gridpull.tiled_job import compile_ahead

    # said before the progress bar, which would otherwise sit at 0 while numba compiles
    compile_ahead(compile_kernels, 1, names=[n for n in KERNELS if n not in TILED_ONLY])
    bar = _progress_bar(cfg.total_iterations(cfg.resolution), args)
    try:
        mesh = reconstruct(cloud, config=cfg, progress=bar.update if bar else None,
                           band_edges=getattr(args, "band_edges", None) or "trim",
                           attributes=getattr(args, "attributes", None) or "all",
                           drop_outliers=getattr(args, "drop_outliers", None) or False,
                           **({} if getattr(args, "min_component_cells", None) is None
                              else {"min_component_cells": args.min_component_cells}))
    finally:
        if bar:
            bar.close()
    if mesh.n_faces == 0:
        # nothing to write: an empty file would look like a finished mesh
        if mesh.metadata.get("small_components_removed"):
            raise InputError(f"{args.inputs[0]}: every part of the mesh is smaller than min_component_cells along "
                             "every axis (an empty mesh; nothing written): set a smaller min_component_cells")
        raise InputError(f"{args.inputs[0]}: the solve found no surface in these points (an empty mesh; nothing "
                         "written): check the cloud's extent and --resolution")
    from tiled_gridpull.io.remote import recorded

    mesh.metadata["inputs"] = [recorded(p) for p in args.inputs]
    if cloud.crs:
        mesh.metadata["crs"] = cloud.crs
    write_mesh_and_sidecar(mesh, out, float32=args.float32)
    topo = mesh.topology
    log.info("wrote %s: %d vertices, %d faces, %d component(s), %s in %.1f s", out, topo.n_vertices, topo.n_faces,
             topo.components, "watertight" if topo.watertight else f"{topo.boundary_edges} boundary edges",
             mesh.metadata["timings_s"]["total"])
    return 0


def _check_tiles3d(args, reads: list, out: Path) -> None:
    """``--3d-tiles`` and ``--3d-tiles-crs`` checked before anything is read or solved: a directory that is not
    an input's nor holds one, nor someone else's files; a CRS (the input's or the option's) pyproj reads."""
    from tiled_gridpull.errors import ConfigError

    d = getattr(args, "tiles3d", None)
    if d is None:
        if getattr(args, "tiles3d_crs", None) is not None:
            raise ConfigError("--3d-tiles-crs applies with --3d-tiles")
        return
    from tiled_gridpull.io.remote import is_url
    from tiled_gridpull.tiles3d import check_tileset_dir, resolve_tileset_crs

    rd = Path(d).resolve()
    for p in [*reads, out, args.work_dir or out.with_suffix(".job"), args.tile_meshes]:
        if p is None or is_url(str(p)):
            continue
        rp = Path(p).resolve()
        if rd == rp or rd in rp.parents or (p not in reads and rp in rd.parents and p != out):
            raise ConfigError(f"--3d-tiles {d} overlaps {p}: the tileset directory is replaced as a whole; "
                              "choose a directory of its own")
    check_tileset_dir(d)
    resolve_tileset_crs(args.inputs, args.tiles3d_crs)  # the dry run refuses it too


def _parse_frames(text):
    from tiled_gridpull.errors import ConfigError

    if text is None:
        return None
    try:
        a, b = text.split(":")
        start, stop = int(a), int(b)
    except ValueError:
        raise ConfigError(f"--frames expects START:STOP, got {text!r}") from None
    if start < 0 or stop <= start:
        raise ConfigError(f"--frames {text}: need 0 <= START < STOP")
    return (start, stop)


def _reconstruct_tiled(args, out: Path, solver, tiling) -> int:
    from tiled_gridpull.pipeline.job import JobOptions, run_job
    from tiled_gridpull.errors import ConfigError, InputError

    if args.workers is not None and not 0 <= args.workers <= MAX_WORKERS:
        shown = args.workers if abs(args.workers) < 1 << 62 else f"an integer of {args.workers.bit_length()} bits"
        raise ConfigError(f"--workers must be between 0 and {MAX_WORKERS}, got {shown}")
    if args.batch_tiles is not None and not 1 <= args.batch_tiles <= MAX_BATCH_TILES:
        shown = args.batch_tiles if abs(args.batch_tiles) < 1 << 62 else "a huge integer"
        raise ConfigError(f"--batch-tiles must be between 1 and {MAX_BATCH_TILES}, got {shown}")
    if args.workers == 0 and args.scheduler:
        raise ConfigError("--workers 0 runs the tiles in this process and --scheduler on a Dask cluster: give one")
    if args.workers == 0 and args.batch_tiles is not None and args.batch_tiles > 1:
        raise ConfigError("--batch-tiles needs a Dask cluster (a worker holding the card); --workers 0 runs the "
                          "tiles one at a time in this process")
    if out.suffix.lower() != ".ply":
        raise ConfigError(f"output {out}: tiled mode writes PLY")
    frames = _parse_frames(args.frames)
    from tiled_gridpull.io.remote import is_url

    for p in args.inputs:
        if not is_url(p) and not Path(p).exists():
            raise InputError(f"{p}: file not found")
    from tiled_gridpull.prepare import check_registered, check_remote, resolve_units
    from tiled_gridpull.tiling import check_compatible

    check_registered(args.inputs)  # before the job directory is made
    check_remote(args.inputs, args.trajectory, tiling)
    if args.trajectory is not None:
        from tiled_gridpull.trajectory import read_trajectory

        not_las = [p for p in args.inputs if Path(p).suffix.lower() not in (".las", ".laz")]
        if not_las:
            raise InputError(f"--trajectory applies to LAS/LAZ points with GPS time; {not_las[0]} is not one")
        read_trajectory(args.trajectory)  # a bad file is refused before the job directory is made
    from tiled_gridpull.config import QUALITY_CELL_SCALE

    quality = getattr(args, "quality_chosen", None) or "standard"
    # voxel_size auto, or with a unit; a preset scales an auto cell
    tiling = resolve_units(args.inputs, tiling, frames, cell_scale=QUALITY_CELL_SCALE[quality])
    check_compatible(tiling, solver)
    if "voxel_size" in tiling.derived and not args.dry_run:  # the dry run prints it on its lattice line
        log.info("voxel_size %g (%s)", tiling.voxel_size, tiling.units)
    work = Path(args.work_dir) if args.work_dir else out.with_suffix(".job")
    max_memory = None
    if args.max_memory is not None:
        from tiled_gridpull.memory import parse_size

        max_memory = parse_size(args.max_memory)
    if args.dry_run:
        from tiled_gridpull.pipeline.dryrun import format_plan, plan_job

        info = plan_job(args.inputs, tiling, solver, work, frames=frames, trajectory=args.trajectory,
                        workers=args.workers, presets=_preset_plans(args, frames, tiling))
        info["quality"] = quality
        print(format_plan(info, max_memory))
        if max_memory is not None:
            from tiled_gridpull.memory import check_memory

            check_memory(None, tiling, solver, max_memory, estimates=info["estimates"])
        return 0
    opts = JobOptions(workers=args.workers, scheduler=args.scheduler, fail_fast=args.fail_fast,
                      tile_meshes=args.tile_meshes, tiles3d=args.tiles3d, tiles3d_crs=args.tiles3d_crs,
                      float32=args.float32, progress=not args.quiet, max_memory=max_memory,
                      **({"batch_tiles": args.batch_tiles} if args.batch_tiles is not None else {}))
    mesh = run_job(args.inputs, out, tiling, solver, work, opts, frames=frames, trajectory=args.trajectory)
    topo = mesh.topology
    tiles = mesh.metadata["tiles"]
    log.info("wrote %s: %d vertices, %d faces, %d boundary edges; %d/%d tiles solved in %.1f s (job files in %s)",
             out, topo.n_vertices, topo.n_faces, topo.boundary_edges, tiles["solved"], tiles["with_points"],
             mesh.metadata["timings_s"]["total"], work)
    for t in tiles["not_solved"]:
        log.warning("tile %s %s: %s", t["tile"], t["status"], t["reason"])
    failed = [t for t in tiles["not_solved"] if t["status"] == "failed"]
    if failed:
        return 6
    return 0


def _preset_plans(args, frames, tiling) -> dict:
    """The dry run's quality presets: ``{quality: (SolverConfig, TilingConfig)}``, each with the settings ``args``
    give under that preset and its cell (an auto cell scales with the preset; ``tiling``: this run's, resolved)."""
    from tiled_gridpull.config import QUALITIES, QUALITY_CELL_SCALE
    from tiled_gridpull.prepare import resolve_units

    out = {}
    chosen_scale = QUALITY_CELL_SCALE[getattr(args, "quality_chosen", None) or "standard"]
    for q in QUALITIES:
        solver_q, tiling_q = resolve_settings(args, quality=q)
        scale = QUALITY_CELL_SCALE[q]
        if tiling_q.voxel_unit == "auto" and scale == chosen_scale:
            tiling_q = tiling  # the same measurement: not read again
        else:
            tiling_q = resolve_units(args.inputs, tiling_q, frames, cell_scale=scale)
        out[q] = (solver_q, tiling_q)
    return out


def cmd_sample(args) -> int:
    """Run ``sample``."""
    from tiled_gridpull.errors import ConfigError

    if args.points < 100:
        raise ConfigError(f"--points must be at least 100, got {args.points}")
    if not (math.isfinite(args.range_noise) and args.range_noise >= 0):
        raise ConfigError(f"--range-noise must be a length >= 0 in metres, got {args.range_noise}")
    if not (math.isfinite(args.beam_bias) and 0 <= args.beam_bias <= 5):
        raise ConfigError(f"--beam-bias must be an angle between 0 and 5 degrees, got {args.beam_bias}")
    if args.frames is not None and not (1 <= args.frames <= 10_000):
        raise ConfigError(f"--frames must be between 1 and 10,000, got {args.frames}")
    if args.frames is not None and (args.kind != "street" or args.layout != "street"):
        raise ConfigError("--frames applies to 'sample street' with the street layout only")
    if args.origin is not None and not all(math.isfinite(v) for v in args.origin):
        raise ConfigError(f"--origin must be three finite coordinates, got {' '.join(map(str, args.origin))}")
    out = Path(args.out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a directory (sample writes its files into a directory)")
    if args.kind == "street":
        from tiled_gridpull.synthetic.street_sample import make_street_sample

        formats = ("laz",) + tuple(f for f in ("kitti", "copc", "ept") if getattr(args, f))
        info = make_street_sample(out, n_points=args.points, seed=args.seed, origin=tuple(args.origin),
                                  formats=formats, layout=args.layout, range_noise=args.range_noise,
                                  frames=args.frames, beam_bias_deg=args.beam_bias)
        log.info("wrote %s (%s layout, %d points, %d frames in %d passes) and ground truth %s", info["points"],
                 info["layout"], info["n_points"], info["n_frames"], info["n_passes"], info["gt_mesh"])
        return 0
    if args.layout != "street":
        raise ConfigError(f"--layout {args.layout} applies to 'sample street' only, not '{args.kind}'")
    if args.range_noise:
        raise ConfigError(f"--range-noise applies to 'sample street' only, not '{args.kind}'")
    if args.beam_bias:
        raise ConfigError(f"--beam-bias applies to 'sample street' only, not '{args.kind}'")
    from tiled_gridpull import synthetic
    from tiled_gridpull.io import write_mesh
    from tiled_gridpull.io.atomic import atomic_path

    mesh = getattr(synthetic, args.kind)()
    pts, nrm = synthetic.sample_shape(mesh, args.points, seed=args.seed)
    out.mkdir(parents=True, exist_ok=True)
    import numpy as np

    with atomic_path(out / f"{args.kind}.xyz") as tmp:
        np.savetxt(tmp, np.hstack([pts, nrm]), fmt="%.9g")
    write_mesh(mesh, out / f"{args.kind}_gt.ply")
    log.info("wrote %s (%d points with normals) and ground truth %s", out / f"{args.kind}.xyz", args.points,
             out / f"{args.kind}_gt.ply")
    return 0


class _IterationBar:
    def __init__(self, total: int):
        from tqdm import tqdm

        self.bar = tqdm(total=total, unit="it", desc="solve", dynamic_ncols=True, file=sys.stderr)

    def update(self, it: int, total: int, stats: dict) -> None:
        # the solver knows the total over all its levels (and a UDF polish); the bar's first guess may not
        if self.bar.total != total:
            self.bar.total = total
        self.bar.n = it + 1
        self.bar.set_postfix(pull=f"{stats['pull']:.3g}", lr=f"{stats['lr']:.3g}", refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        self.bar.close()


def _progress_bar(total: int, args):
    if args.quiet:
        return None
    return _IterationBar(total)


def cmd_evaluate(args) -> int:
    """Run ``evaluate``."""
    import numpy as np

    from tiled_gridpull.io import read_mesh
    from tiled_gridpull.mesh import Mesh
    from tiled_gridpull.errors import ConfigError, InputError
    from tiled_gridpull.metrics import evaluate, footprint_scores

    if args.samples is not None and args.samples < 1:
        raise ConfigError(f"--samples must be a positive count, got {args.samples}")
    if not (np.isfinite(args.observed_radius) and args.observed_radius > 0):
        raise ConfigError(f"--observed-radius must be a positive distance, got {args.observed_radius}")
    if not all(np.isfinite(t) and t > 0 for t in args.thresholds):
        raise ConfigError(f"--thresholds must be positive distances, got {' '.join(map(str, args.thresholds))}")
    if args.footprint is not None:
        if not args.observed:
            raise ConfigError("--footprint needs --observed CLOUD (the input points the footprint is measured from)")
        if not all(np.isfinite(r) and r > 0 for r in [*args.footprint, args.footprint_tau]):
            raise ConfigError("--footprint radii and --footprint-tau must be positive numbers")
    pred = read_mesh(args.mesh)
    gt = read_mesh(args.gt)
    centre, scale = np.zeros(3), 1.0
    if args.normalize:
        lo, hi = gt.vertices.min(0), gt.vertices.max(0)
        centre, scale = (lo + hi) / 2, float((hi - lo).max())
        pred = Mesh((pred.vertices - centre) / scale, pred.faces)
        gt = Mesh((gt.vertices - centre) / scale, gt.faces)
    observed = None
    if args.observed:
        from tiled_gridpull.io import read_points

        observed = read_points(args.observed).xyz
    if args.normalize:
        if observed is not None:
            observed = (observed - centre) / scale
    try:
        res = evaluate(pred, gt, n_samples=args.samples, thresholds=tuple(args.thresholds), exact=not args.no_exact,
                       observed=observed, observed_radius=args.observed_radius / (scale if args.normalize else 1.0))
    except InputError:
        # the library's words name its keyword; these name the options
        raise InputError(f"--observed {args.observed}: no ground-truth sample lies within --observed-radius "
                         f"{args.observed_radius:g} of its points (do the cloud and {args.gt} share coordinates?)") \
            from None
    if args.footprint is not None:
        unit = scale if args.normalize else 1.0
        fp = footprint_scores(pred, gt, observed, radii=[r / unit for r in args.footprint],
                              tau=args.footprint_tau / unit, n_samples=args.samples)
        # named in the user's units, whatever --normalize did
        res.update({"footprint_tau": args.footprint_tau,
                    f"footprint_precision@{args.footprint_tau:g}": fp[f"precision@{args.footprint_tau / unit:g}"]})
        for r in args.footprint:
            res[f"footprint_recall@{r:g}"] = fp[f"footprint_recall@{r / unit:g}"]
            res[f"footprint_samples@{r:g}"] = fp[f"footprint_samples@{r / unit:g}"]
    if args.json:
        print(json.dumps(res, indent=2, sort_keys=True,
                         default=lambda o: o.item() if isinstance(o, np.generic) else str(o)))
    else:
        print("\n".join(_evaluate_table(res)))
    return 0


#: the sample counts and mesh facts of ``evaluate``'s result, printed in a section of their own
_MESH_FACTS = ("n_samples", "gt_samples_used", "watertight", "components", "boundary_edges", "boundary_loops",
               "nonmanifold_edges", "vertices", "faces")


def _evaluate_table(res: dict) -> list[str]:
    """``evaluate``'s table: the exact figures first, then the footprint and the mesh facts, and last the
    sample-to-sample figures, labelled with their floor (on the demo street the floor is 0.12 m, and its sampled
    Chamfer-L1, 14 times the exact one, had led the table and read as the mesh's error). The ``--json`` keys
    are unchanged (``chamfer_l1_floor`` is new)."""
    exact = [k for k in res if "_exact" in k]
    footprint = [k for k in res if k.startswith("footprint_")]
    facts = [k for k in _MESH_FACTS if k in res]
    sampled = [k for k in res if k not in {*exact, *footprint, *facts}]
    width = max(len(k) for k in res)

    def rows(keys):
        return [f"  {k:<{width}}  {res[k]:.6g}" if isinstance(res[k], float) else f"  {k:<{width}}  {res[k]}"
                for k in keys]

    lines = []
    if exact:
        lines += ["exact: each mesh's samples to the other mesh's surface (no floor; the figures to read)",
                  *rows(exact)]
    if footprint:
        lines += ["footprint: ground truth within R of the input points, within tau of the mesh (exact)",
                  *rows(footprint)]
    lines += ["samples and mesh", *rows(facts)]
    floor = res.get("chamfer_l1_floor")
    lines.append("sampled: each mesh's samples to the other's nearest sample (the papers' convention, for unit "
                 "shapes)" + (f"; the samples alone give a perfect mesh chamfer_l1 {floor:.3g}" if floor else ""))
    lines += rows(sampled)
    return lines


def cmd_render(args) -> int:
    """Run ``render``."""
    from tiled_gridpull.errors import ConfigError
    from tiled_gridpull.io import read_mesh
    from tiled_gridpull.io.outputs import check_output_file

    out = Path(args.output)
    if out.suffix.lower() != ".png":
        raise ConfigError(f"output {out}: use a .png file name")
    w, h = args.size
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise ConfigError(f"--size {w} {h}: width and height must be between 16 and 8192 pixels")
    if args.point_size <= 0 or args.max_points < 1:
        raise ConfigError("--point-size must be positive and --max-points at least 1")
    if args.clim is not None and not args.clim[0] < args.clim[1]:
        raise ConfigError(f"--clim {args.clim[0]:g} {args.clim[1]:g}: need LO < HI")
    check_output_file(out)  # before the render, not after it
    mesh = read_mesh(args.mesh)
    cloud = gt = None
    if args.cloud:
        from tiled_gridpull.io import read_points

        cloud = read_points(args.cloud).xyz
    if args.gt and args.color:
        raise ConfigError("--color and --gt both colour the mesh: give one")
    if args.gt:
        gt = read_mesh(args.gt)
    from tiled_gridpull.render import render_mesh

    info = render_mesh(mesh, out, size=(w, h), cloud=cloud, gt=gt, clim=tuple(args.clim) if args.clim else None,
                       view=args.view, point_size=args.point_size, max_points=args.max_points,
                       show_edges=args.edges, color=args.color)
    msg = f"wrote {out} ({w} x {h})"
    if "errors" in info:
        e = info["errors"]
        msg += (f"; vertex distance to {args.gt}: mean {e['mean']:.4g}, median {e['median']:.4g}, "
                f"95% {e['p95']:.4g}, max {e['max']:.4g}")
    log.info(msg)
    return 0


def cmd_report(args) -> int:
    """Run ``report``."""
    from tiled_gridpull.report import format_report_table, read_report

    report = read_report(args.job_dir)
    if args.json:
        print(json.dumps(report, indent=2, sort_keys=True))
    else:
        print(format_report_table(report))
    return 0


COMMANDS = {"reconstruct": cmd_reconstruct, "evaluate": cmd_evaluate, "sample": cmd_sample, "render": cmd_render,
            "report": cmd_report}


#: Most worker processes a local cluster may start (each holds a Python process and a tile's arrays).
MAX_WORKERS = 1024

#: Most tiles one batch on a card may hold (a batch's bands share the card's memory).
MAX_BATCH_TILES = 4096

#: OSError numbers that name a storage problem of the machine (exit 3, one line), not a bug.
_STORAGE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO,
                   errno.ENAMETOOLONG, errno.EMFILE, errno.ENFILE, errno.EFBIG}


def _set_min_transfer_rate(args) -> None:
    """``--min-transfer-rate`` into the environment, where the remote reader looks for it: in this process and in
    the workers a local cluster starts from it (an external cluster's workers need it in their own environment)."""
    text = getattr(args, "min_transfer_rate", None)
    if text is None:
        return
    from tiled_gridpull.errors import ConfigError
    from tiled_gridpull.io.remote import MIN_RATE_ENV

    try:
        rate = float(text)
    except ValueError:
        rate = -1.0
    if not (0 <= rate < float("inf")):
        raise ConfigError(f"--min-transfer-rate expects bytes per second, 0 or more, got {text!r}")
    os.environ[MIN_RATE_ENV] = repr(rate)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``tiled-gridpull``; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args)
    t0 = time.perf_counter()
    try:
        code = COMMANDS[args.command](args)
    except GridPullError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # output piped into `head` and closed early: not an error; keep Python from complaining at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except MemoryError:
        print("error: out of memory (reduce --resolution or the tile size, or set --max-memory)", file=sys.stderr)
        return 5
    except OSError as exc:
        # the machine, not the data or a bug: a full disk, a read-only or foreign directory met mid-job
        if exc.errno not in _STORAGE_ERRNOS or getattr(args, "verbose", 0) >= 2:
            return _internal_error(exc, args)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"error: {where}{exc.strerror or os.strerror(exc.errno)}", file=sys.stderr)
        return 3
    except Exception as exc:  # a bug: one line unless asked for the traceback
        return _internal_error(exc, args)
    log.debug("done in %.1f s", time.perf_counter() - t0)
    return code


def _internal_error(exc: Exception, args) -> int:
    """A bug: one line, or the traceback with -vv (re-raised from inside the handler that called this)."""
    if getattr(args, "verbose", 0) >= 2:
        raise exc
    print(f"internal error: {exc.__class__.__name__}: {exc} (rerun with -vv for the traceback)", file=sys.stderr)
    return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
