"""One benchmark run in a fresh process: sample a shared mesh, reconstruct it, score it; prints one JSON line.

Usage: ``python -m benchmarks.shape_worker '{"mesh": "bunny", "points": 100000, "method": "gridpull", ...}'``
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from benchmarks.common import MESHES, SHARED, peak_rss_mb


def unit_transform(name: str):
    """(mesh in its own units, centre (3,), scale): ``(v - centre) / scale`` fits the bbox's longest side to 1."""
    from tiled_gridpull.io import read_mesh

    gt = read_mesh(SHARED / "meshes" / MESHES[name])
    lo, hi = gt.vertices.min(0), gt.vertices.max(0)
    return gt, (lo + hi) / 2, float((hi - lo).max())


#: Open surfaces made by the project (already about unit size): the UDF benchmarks' ground truth.
SYNTHETIC_OPEN = ("half_sphere", "terrain")


def load_unit_mesh(name: str):
    """A shared ground-truth mesh scaled so its bounding box's longest side is 1, centred at the origin
    (or one of the project's open surfaces, ``SYNTHETIC_OPEN``)."""
    from tiled_gridpull.mesh import Mesh

    if name in SYNTHETIC_OPEN:
        from tiled_gridpull.synthetic.shapes import half_sphere, height_field

        return half_sphere() if name == "half_sphere" else height_field(200)

    gt, centre, scale = unit_transform(name)
    return Mesh((gt.vertices - centre) / scale, gt.faces)


def quaternion_matrix(qi: float, qj: float, qk: float, qr: float) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion, scalar last."""
    q = np.array([qi, qj, qk, qr], dtype=np.float64)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def bunny_scans() -> np.ndarray:
    """The 10 real Stanford bunny range scans merged by ``bun.conf`` into the GT mesh's frame, then into the
    unit frame of :func:`load_unit_mesh` ("bunny"): (N, 3) float64, about 362k points.

    The conf's rotations are applied transposed (``p' = R(q)^T p + t``), as the data's manifest records."""
    from tiled_gridpull.io import read_points

    folder = SHARED / "scans" / "stanford_bunny"
    parts = []
    for line in (folder / "bun.conf").read_text().splitlines():
        f = line.split()
        if not f or f[0] != "bmesh":
            continue
        t = np.array(f[2:5], dtype=np.float64)
        R = quaternion_matrix(*map(float, f[5:9]))
        parts.append(read_points(folder / f[1]).xyz @ R + t)  # rows: (R^T p)^T = p^T R
    _, centre, scale = unit_transform("bunny")
    return (np.concatenate(parts) - centre) / scale


def input_cloud(gt, points: int, seed: int, noise: float) -> np.ndarray:
    """``points`` area-uniform samples, plus Gaussian noise of ``noise`` x the bbox diagonal."""
    from tiled_gridpull.metrics import sample_surface

    pts, _ = sample_surface(gt, points, seed=seed)
    if noise > 0:
        diag = float(np.linalg.norm(gt.vertices.max(0) - gt.vertices.min(0)))
        pts = pts + np.random.default_rng(seed + 7).normal(scale=noise * diag, size=pts.shape)
    return pts


def run_gridpull(pts: np.ndarray, cfg: dict, normals: np.ndarray | None = None):
    from tiled_gridpull import reconstruct

    mesh = reconstruct(pts, normals=normals, **cfg)
    return mesh, {"solve_s": mesh.metadata["timings_s"]["solve"],
                  "query_pool": mesh.metadata["config"]["sampling"]["query_pool"],
                  "noise_treatment": (mesh.metadata.get("noise_treatment") or {}).get("chosen")}


def run_poisson(pts: np.ndarray, cfg: dict):
    import open3d as o3d

    from tiled_gridpull.mesh import Mesh

    depth = int(cfg.get("depth", 9))
    t0 = time.perf_counter()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.get("normal_radius", 0.1), max_nn=30))
    pc.orient_normals_consistent_tangent_plane(30)
    t1 = time.perf_counter()
    m, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=depth)
    t2 = time.perf_counter()
    return Mesh(np.asarray(m.vertices), np.asarray(m.triangles)), {"normals_s": t1 - t0, "poisson_s": t2 - t1}


def main(args: dict) -> dict:
    from tiled_gridpull.metrics import evaluate

    gt = load_unit_mesh(args["mesh"])
    normals = None
    if args.get("scans"):
        pts = bunny_scans()
    elif args.get("normals"):
        from tiled_gridpull.metrics import sample_surface

        pts, normals = sample_surface(gt, args["points"], seed=args.get("seed", 0))  # exact normals
    else:
        pts = input_cloud(gt, args["points"], args.get("seed", 0), args.get("noise", 0.0))
    t0 = time.perf_counter()
    if args["method"] in ("gridpull", "gridpull-paper", "gridpull-paper-pool"):
        mesh, extra = run_gridpull(pts, args.get("config", {}), normals)
    elif args["method"] == "poisson":
        mesh, extra = run_poisson(pts, args.get("config", {}))
    else:
        raise SystemExit(f"unknown method {args['method']}")
    wall = time.perf_counter() - t0
    peak = peak_rss_mb()
    res = evaluate(mesh, gt, n_samples=args.get("samples", 100_000), thresholds=(0.002, 0.004, 0.01))
    out = {**args, "wall_s": wall, "peak_rss_mb": peak, **extra}
    keep = ("chamfer_l1", "chamfer_l2", "chamfer_l2_x100", "normal_consistency", "fscore@0.002", "fscore@0.004",
            "fscore@0.01", "hausdorff", "chamfer_l1_exact", "chamfer_l2_exact", "normal_consistency_exact",
            "hausdorff_exact", "fscore_exact@0.002", "fscore_exact@0.01", "watertight", "components",
            "boundary_edges", "boundary_loops", "faces")
    out.update({k: res[k] for k in keep})
    return out


if __name__ == "__main__":
    print(json.dumps(main(json.loads(sys.argv[1])), default=float))
