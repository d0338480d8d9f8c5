"""Open3D screened Poisson on a LiDAR file, end to end (file in -> mesh out), in its own process.

The peer a user would otherwise pick, measured the way a user would run it: read the file (laspy), estimate
normals (Open3D, 30 nearest neighbours) and orient them up (the same information GridPull's "up" rule has for a
LAS file without sensor positions), screened Poisson at ``depth``, then drop the vertices whose Poisson density
lies in the lowest ``trim_quantile`` (the usual trim of the surface Poisson invents where there is no data),
and write a PLY (``"sensor": [x, y, z]`` orients the normals towards a scanner's position instead of up).
Coordinates are shifted to the cloud's low corner first and back on writing (float64
throughout), so georeferenced inputs lose nothing.

Usage: ``python -m benchmarks.poisson_scene '{"input": "street.laz", "output": "poisson.ply", "depth": 11}'``;
prints one JSON line: wall time, its parts, peak RSS and the mesh size.
"""

from __future__ import annotations

import json
import sys
import time


def main(args: dict) -> dict:
    import numpy as np
    import open3d as o3d

    from benchmarks.common import peak_rss_mb
    from tiled_gridpull.io import read_points, write_mesh
    from tiled_gridpull.mesh import Mesh

    t0 = time.perf_counter()
    xyz = read_points(args["input"]).xyz
    low = xyz.min(axis=0)
    t1 = time.perf_counter()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz - low))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
    if args.get("sensor") is not None:  # one scan from a known place (a KITTI frame): normals face the sensor
        pc.orient_normals_towards_camera_location(np.asarray(args["sensor"], np.float64) - low)
    else:
        pc.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
    t2 = time.perf_counter()
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=int(args.get("depth", 11)))
    t3 = time.perf_counter()
    q = float(args.get("trim_quantile", 0.05))
    if q > 0:
        density = np.asarray(density)
        mesh.remove_vertices_by_mask(density < np.quantile(density, q))
    out = Mesh(np.asarray(mesh.vertices) + low, np.asarray(mesh.triangles, dtype=np.int64))
    write_mesh(out, args["output"])
    t4 = time.perf_counter()
    return {"wall_s": t4 - t0, "read_s": t1 - t0, "normals_s": t2 - t1, "poisson_s": t3 - t2,
            "trim_and_write_s": t4 - t3, "peak_rss_mb": peak_rss_mb(), "faces": int(out.n_faces),
            "points": int(len(xyz))}


if __name__ == "__main__":
    print(json.dumps(main(json.loads(sys.argv[1])), default=float))
