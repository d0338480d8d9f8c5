"""Why a mesh misses the footprint of a synthetic street: the ceiling a gap rule can reach (issue 36).

    python -m benchmarks.footprint_misses SAMPLE_DIR MESH [--radius 1.5]

``SAMPLE_DIR`` is a ``tiled-gridpull sample street`` directory (``street.json``: ground truth, face classes,
points, trajectory). The footprint (truth samples within R of a point, as
:func:`tiled_gridpull.metrics.footprint_scores`) is split by the class of the truth face under each sample and by
whether some sensor position sees it (:func:`tiled_gridpull.synthetic.lidar.visible_from`: beam span, range,
nothing on the segment). The samples the mesh misses fall into:

* (a) terrain some sensor sees: only the ring and azimuth pattern left it without a point (a sampling gap);
* (b) terrain no sensor sees: a shadow (of a car, a wall, a box), which the issue says never to bridge;
* (c) other classes (walls, cars, poles, trees), seen or not: what no ground bridge reaches;

and the ceilings: the recall if every (a) sample were bridged and nothing else, and if every seen sample of
any class were covered (no method that keeps to what was seen does better).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def classify(sample_dir: Path, mesh_path: Path, radius: float = 1.5, tau: float = 0.1, n_samples: int = 200_000,
             seed: int = 0) -> dict:
    from tiled_gridpull.io import read_mesh, read_points
    from tiled_gridpull.metrics import footprint_samples, point_to_mesh
    from tiled_gridpull.synthetic.lidar import visible_from

    meta = json.loads((sample_dir / "street.json").read_text())
    gt = read_mesh(meta["gt_mesh"])
    pts = read_points(meta["laz"]).xyz
    sensors = np.loadtxt(meta["trajectory"], delimiter=",", skiprows=1, ndmin=2)[:, 1:4]
    # the footprint's samples as footprint_scores draws them
    g, near = footprint_samples(gt, pts, radius, n_samples, seed)
    g = g[np.isfinite(near)]
    hit = point_to_mesh(g, read_mesh(mesh_path))[0] <= tau
    face = point_to_mesh(g, gt)[1]
    terrain = np.zeros(len(g), bool)
    a, b = meta["face_classes"]["terrain"]
    terrain[(face >= a) & (face < b)] = True
    seen = visible_from(gt, g, sensors)
    n = len(g)
    miss = ~hit
    out = {"radius": radius, "footprint_samples": n, "recall": float(hit.mean()), "seen_share": float(seen.mean()),
           "seen_recall": float(hit[seen].mean()),
           "miss_a_sampling_gap": int((miss & terrain & seen).sum()),
           "miss_b_shadow": int((miss & terrain & ~seen).sum()),
           "miss_c_other_seen": int((miss & ~terrain & seen).sum()),
           "miss_c_other_unseen": int((miss & ~terrain & ~seen).sum())}
    out["ceiling_gaps_bridged"] = float((hit.sum() + out["miss_a_sampling_gap"]) / n)
    out["ceiling_all_seen"] = float((hit | seen).mean())
    for name, (lo, hi) in meta["face_classes"].items():
        k = (face >= lo) & (face < hi)
        out[f"class_{name}"] = {"share": float(k.mean()), "recall": float(hit[k].mean()) if k.any() else None,
                                "seen": float(seen[k].mean()) if k.any() else None}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sample_dir", type=Path)
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--radius", type=float, default=1.5)
    a = ap.parse_args()
    print(json.dumps(classify(a.sample_dir, a.mesh, a.radius), indent=1))


if __name__ == "__main__":
    main()
