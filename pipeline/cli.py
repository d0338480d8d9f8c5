"""``tiled-gridpull`` command line.

Exit codes: 0 success; 2 bad option or config value; 3 bad input file; 4 missing optional dependency;
5 memory budget exceeded; 6 some tiles failed (the rest of the mesh was written); 130 interrupted;
1 internal error (a bug: rerun with ``-vv`` for the traceback and report it).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from tiled_gridpull.errors import GridPullError

log = logging.getLogger("tiled_gridpull")


class _Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    pass


def _add_common(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("-v", "--verbose", action="count", default=0, help="more output (-vv: debug, tracebacks)")
    g.add_argument("-q", "--quiet", action="store_true", help="only errors")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (also used to document the options)."""
    from tiled_gridpull import __version__

    parser = argparse.ArgumentParser(
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
                   help="PLY, XYZ/TXT/PTS/CSV, NPY, LAS/LAZ, KITTI .bin or a KITTI sequence directory")
    r.add_argument("-o", "--output", required=True, help="output mesh (.ply or .obj); a .json sidecar is written beside it")
    r.add_argument("--config", help="YAML file of settings (see configs/)")
    r.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one setting (repeatable), e.g. --set alpha=2")
    r.add_argument("--resolution", type=int, help="cells across the longest side (one-shape mode; default 256)")
    r.add_argument("--iterations", type=int, help="optimizer iterations (default 1600)")
    r.add_argument("--seed", type=int, help="random seed (default 0)")
    r.add_argument("--mode", choices=("sdf", "udf"), help="signed (closed surfaces) or unsigned (open) field")
    r.add_argument("--float32", action="store_true",
                   help="store vertices as float32 relative to an offset recorded in the header (half the size)")
    _add_common(r)

    e = sub.add_parser("evaluate", formatter_class=_Formatter,
                       help="accuracy of a mesh against a ground-truth mesh",
                       description="Chamfer-L1/L2, normal consistency, F-score and Hausdorff (ONet/SAP/NeuralPull "
                                   "conventions), sample-based and exact, plus mesh facts.")
    e.add_argument("mesh")
    e.add_argument("gt")
    e.add_argument("--samples", type=int, default=100_000, help="area-uniform samples per mesh")
    e.add_argument("--thresholds", type=float, nargs="+", default=[0.002, 0.004, 0.01],
                   help="F-score thresholds, in the meshes' units")
    e.add_argument("--normalize", action="store_true",
                   help="scale both meshes by the GT's bounding box (longest side 1) before measuring")
    e.add_argument("--no-exact", action="store_true", help="skip the exact point-to-surface distances")
    e.add_argument("--json", action="store_true", help="print JSON instead of a table")
    _add_common(e)
    return parser


def _setup_logging(args) -> None:
    level = logging.WARNING if getattr(args, "quiet", False) else (
        logging.DEBUG if getattr(args, "verbose", 0) >= 2 else logging.INFO)
    logging.basicConfig(level=level, format="%(message)s", stream=sys.stderr)
    logging.captureWarnings(True)


def _solver_settings(args) -> dict:
    from tiled_gridpull.config import load_config_file, parse_overrides

    settings: dict = {}
    if args.config:
        settings.update(load_config_file(args.config))
    settings.update(parse_overrides(args.overrides))
    for key in ("resolution", "iterations", "seed", "mode"):
        value = getattr(args, key, None)
        if value is not None:
            settings[key] = value
    return settings


def cmd_reconstruct(args) -> int:
    """Run ``reconstruct``."""
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.errors import ConfigError, InputError
    from tiled_gridpull.io import read_points, write_mesh, write_sidecar
    from tiled_gridpull.reconstruct import reconstruct

    out = Path(args.output)
    if out.suffix.lower() not in (".ply", ".obj"):
        raise ConfigError(f"output {out}: use a .ply or .obj file name")
    settings = _solver_settings(args)
    unknown = set(settings) - set(SolverConfig.__dataclass_fields__)
    if unknown:
        raise ConfigError(f"unknown setting(s): {', '.join(sorted(unknown))}")
    cfg = SolverConfig(**settings)  # validated before any file is read
    if len(args.inputs) != 1:
        raise InputError("one-shape mode reads one input; give --voxel-size to reconstruct several files as tiles")
    cloud = read_points(args.inputs[0])
    log.info("read %s: %d points", args.inputs[0], len(cloud))
    bar = _progress_bar(cfg.iterations, args)
    try:
        mesh = reconstruct(cloud, config=cfg, progress=bar.update if bar else None)
    finally:
        if bar:
            bar.close()
    mesh.metadata["inputs"] = [str(Path(p).resolve()) for p in args.inputs]
    if cloud.crs:
        mesh.metadata["crs"] = cloud.crs
    write_mesh(mesh, out, float32=args.float32)
    write_sidecar(out, mesh.metadata)
    topo = mesh.topology
    log.info("wrote %s: %d vertices, %d faces, %d component(s), %s in %.1f s", out, topo.n_vertices, topo.n_faces,
             topo.components, "watertight" if topo.watertight else f"{topo.boundary_edges} boundary edges",
             mesh.metadata["timings_s"]["total"])
    return 0


class _IterationBar:
    def __init__(self, total: int):
        from tqdm import tqdm

        self.bar = tqdm(total=total, unit="it", desc="solve", dynamic_ncols=True, file=sys.stderr)

    def update(self, it: int, total: int, stats: dict) -> None:
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
    from tiled_gridpull.metrics import evaluate

    pred = read_mesh(args.mesh)
    gt = read_mesh(args.gt)
    if args.normalize:
        lo, hi = gt.vertices.min(0), gt.vertices.max(0)
        centre, scale = (lo + hi) / 2, float((hi - lo).max())
        pred = Mesh((pred.vertices - centre) / scale, pred.faces)
        gt = Mesh((gt.vertices - centre) / scale, gt.faces)
    res = evaluate(pred, gt, n_samples=args.samples, thresholds=tuple(args.thresholds), exact=not args.no_exact)
    if args.json:
        print(json.dumps(res, indent=2, sort_keys=True, default=lambda o: o.item() if isinstance(o, np.generic) else str(o)))
    else:
        width = max(len(k) for k in res)
        for k, v in res.items():
            print(f"{k:<{width}}  {v:.6g}" if isinstance(v, float) else f"{k:<{width}}  {v}")
    return 0


COMMANDS = {"reconstruct": cmd_reconstruct, "evaluate": cmd_evaluate}


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
    except MemoryError:
        print("error: out of memory (reduce --resolution or the tile size, or set --max-memory)", file=sys.stderr)
        return 5
    except Exception as exc:  # a bug: one line unless asked for the traceback
        if getattr(args, "verbose", 0) >= 2:
            raise
        print(f"internal error: {exc.__class__.__name__}: {exc} (rerun with -vv for the traceback)", file=sys.stderr)
        return 1
    log.debug("done in %.1f s", time.perf_counter() - t0)
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
