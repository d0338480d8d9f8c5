"""Vertex attributes on real coloured airborne LiDAR: how close a mesh's vertex colours come to the data's.

Autzen (``shared/data/lidar/autzen_trim.laz``, 110,000 points, RGB from imagery, international feet): 10 % of the
points are held out at random, the other 90 % are written to a LAS file and meshed as a tiled job (the CLI's
path: LAS reader, spill files, per-tile interpolation, weld). For every vertex the script reports, per channel,
the median |vertex colour - colour of the nearest held-out point| and |vertex colour - colour of the nearest
input point| as a percentage of full scale (255: Autzen stores 8-bit colour in LAS's 16-bit fields), the same
for other neighbour counts (re-interpolated on the same vertices), the classification agreement with the
nearest held-out point, and how many vertices shared by two tiles got different values from their two tiles.

Run: ``nice -n 10 python -m benchmarks.attributes [--out results/attributes.json]`` (about a minute on one core).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from tiled_gridpull.attributes import ATTRIBUTE_NEIGHBORS, interpolate_attributes
from tiled_gridpull.config import SolverConfig
from tiled_gridpull.io import read_points
from tiled_gridpull.nearest import nearest_in_cloud
from tiled_gridpull.stitch import load_piece
from tiled_gridpull.tiled_job import reconstruct_scene
from tiled_gridpull.tiling import TilingConfig

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "lidar" / "autzen_trim.laz"
#: a short solve: the colours depend on where the vertices are, not on the last digits of the surface
SOLVER = SolverConfig(coarse_iterations=200, iterations=200, queries=50000)
TILING = TilingConfig(voxel_size=3.0, trim_distance=3.0)  # feet; 2 x 1 tiles of 256 cells
CHANNELS = ("red", "green", "blue")


def write_las(path: Path, src: Path, keep: np.ndarray) -> None:
    """The points ``keep`` (bool mask) of the LAS file ``src``, written to ``path`` with its header."""
    import laspy

    las = laspy.read(str(src))
    out = laspy.LasData(las.header)
    out.points = las.points[keep]
    out.write(str(path))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="write the figures as JSON here")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    cloud = read_points(DATA, clean=False)
    rng = np.random.default_rng(args.seed)
    held = rng.random(len(cloud)) < 0.10
    xyz, attrs = cloud.xyz, cloud.attributes
    full = 255.0 if max(int(attrs[c].max()) for c in CHANNELS) <= 255 else 65535.0
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        write_las(tmp / "kept.las", DATA, ~held)
        t0 = time.perf_counter()
        mesh = reconstruct_scene([str(tmp / "kept.las")], tmp / "mesh.ply", TILING, SOLVER, tmp / "job")
        seconds = time.perf_counter() - t0
        pieces = [load_piece(p) for p in sorted((tmp / "job" / "pieces").glob("*.npz"))]
    V = mesh.vertices
    out: dict = {"data": DATA.name, "points": int(len(xyz)), "held_out": int(held.sum()),
                 "vertices": int(len(V)), "faces": int(mesh.n_faces), "full_scale": full,
                 "tiles": len(pieces), "job_s": round(seconds, 1), "neighbors": ATTRIBUTE_NEIGHBORS,
                 "carried": mesh.metadata["vertex_attributes"]["carried"]}
    d_held, i_held = nearest_in_cloud(V, xyz[held])
    _, i_kept = nearest_in_cloud(V, xyz[~held])
    out["nearest_held_out_distance_median_ft"] = float(np.median(d_held))

    def errors(values: dict) -> dict:
        res = {}
        for ref, idx, rows in (("held_out", i_held, held), ("input", i_kept, ~held)):
            for c in CHANNELS:
                diff = np.abs(values[c].astype(np.float64) - attrs[c][rows][idx].astype(np.float64))
                res[f"{ref}_{c}_median_pct"] = float(100 * np.median(diff) / full)
                res[f"{ref}_{c}_mean_pct"] = float(100 * diff.mean() / full)
        return res

    out["errors"] = errors(mesh.vertex_attributes)
    out["classification_agrees_with_nearest_held_out_pct"] = float(
        100 * np.mean(mesh.vertex_attributes["classification"] == attrs["classification"][held][i_held]))
    kept_attrs = {c: attrs[c][~held] for c in CHANNELS}
    out["by_neighbors"] = {k: errors(interpolate_attributes(V, xyz[~held], kept_attrs, k=k)) for k in (1, 4, 8, 16)}
    # tiles' agreement on the vertices they share (welded by edge key)
    seen: dict = {}
    shared = differ = 0
    for piece in pieces:
        names = sorted(piece.attributes)
        for i, key in enumerate(piece.keys):
            row = tuple(float(piece.attributes[n][i]) for n in names)
            if key < 0:  # private to the piece: negative ids are counted per piece
                continue
            if key in seen:
                shared += 1
                differ += seen[key] != row
            else:
                seen[key] = row
    out["shared_border_vertices"] = shared
    out["shared_border_vertices_differing"] = differ
    print(json.dumps(out, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return out


if __name__ == "__main__":
    main()


def section(d: dict) -> str:
    """BENCHMARKS.md's "Colour on the mesh" from ``results/attributes.json``."""
    def cells(e: dict, kind: str, stat: str) -> str:
        return " / ".join(f"{e[f'{kind}_{c}_{stat}_pct']:.2f}".rstrip("0").rstrip(".") if e[f'{kind}_{c}_{stat}_pct']
                          else "0" for c in ("red", "green", "blue"))

    rows = ["| neighbours | median vs held-out, R / G / B (% of full scale) | mean vs held-out, R / G / B | "
            "median vs input, R / G / B |", "|---|---|---|---|"]
    by = {int(k): v for k, v in d.get("by_neighbors", {}).items()}
    by.setdefault(d["neighbors"], d["errors"])
    for k in sorted(by):
        e = by[k]
        name = f"**{k} (default)**" if k == d["neighbors"] else str(k)
        med = cells(e, "held_out", "median")
        rows.append(f"| {name} | {f'**{med}**' if k == d['neighbors'] else med} | {cells(e, 'held_out', 'mean')} | "
                    f"{cells(e, 'input', 'median')} |")
    return "\n".join([
        f"Autzen (`{d['data']}`, {d['points']:,} points, RGB full scale {d['full_scale']:.0f}) with "
        f"{d['held_out']:,} points held out: the rest meshed as a tiled job ({d['tiles']} tiles, "
        f"{d['vertices']:,} vertices); every vertex's colour compared with its nearest held-out point's (a median "
        f"{d['nearest_held_out_distance_median_ft']:.1f} ft away) and its nearest input point's. The job's own "
        f"output is the default row; the others re-interpolate the same vertices. Measured 2026-11-26 on the shared "
        f"2-core machine (`python -m benchmarks.attributes`).", "",
        *rows, "",
        f"Issue 40's target (median at most 3 % of full scale per channel) holds. Classification agrees with the "
        f"nearest held-out point's at {d['classification_agrees_with_nearest_held_out_pct']:.0f} % of the vertices; "
        f"of the {d['shared_border_vertices']} vertices the tiles share, {d['shared_border_vertices_differing']} got "
        f"different values from the two tiles."])
