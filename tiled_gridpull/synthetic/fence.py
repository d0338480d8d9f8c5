"""A thin wall on flat ground, seen from both sides: the case where a signed field must turn twice within a
few cells.

The wall (a fence panel, a thin partition) is a box ``thickness`` thick. Two sensors, one on each side, see the
ground on their side and the wall's face towards them (the wall's top is shared). It is written as a two-frame
KITTI sequence, so every point carries the origin of the sensor that saw it, as a mobile scan does.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.atomic import atomic_open
from ..mesh import Mesh

__all__ = ["FENCE_CLASSES", "fence_scene"]

#: Classes of the ground truth's faces, in order: ``classes[name] = (start, stop)`` face ranges.
FENCE_CLASSES = ("ground", "front", "back", "top")


def _rect(rng, spacing, p0, u, v):
    p0, u, v = (np.asarray(a, np.float64) for a in (p0, u, v))
    n = max(1, int(round(np.linalg.norm(u) * np.linalg.norm(v) / spacing ** 2)))
    a, b = rng.random(n), rng.random(n)
    return p0 + a[:, None] * u + b[:, None] * v, np.array([p0, p0 + u, p0 + u + v, p0 + v])


def fence_scene(root: str | Path, thickness: float, centre_y: float = 0.0, *, length: float = 8.0,
                height: float = 2.0, ground: tuple[float, float] = (12.0, 12.0), spacing: float = 0.03,
                seed: int = 0) -> dict:
    """Write a wall scanned from both sides as a KITTI sequence under ``root``.

    Parameters
    ----------
    root : path
        Directory to create (``root/velodyne/00000{0,1}.bin``, ``root/poses.txt``, ``root/calib.txt``).
    thickness : float
        Wall thickness (m): its faces are the planes ``y = centre_y -/+ thickness / 2``.
    centre_y : float
        Where the wall's mid-plane lies (m). Against a lattice with vertices at multiples of the cell size,
        this says whether a vertex falls inside the wall.
    length, height : float
        The wall spans ``x`` in ``[2, 2 + length]`` and ``z`` in ``[0, height]`` (m).
    ground : (float, float)
        Extent of the ground in x and y (m), centred on the wall across it.
    spacing : float
        Mean distance between samples (m); samples are uniform on each surface.
    seed : int

    Returns
    -------
    dict
        ``sequence`` (the directory), ``gt`` (:class:`~tiled_gridpull.mesh.Mesh`, metres), ``classes``
        (name -> (start, stop) face range of ``gt``, names :data:`FENCE_CLASSES`), ``points`` ((N, 3) float64
        world coordinates of every sample).
    """
    if not thickness > 0:
        raise ValueError(f"thickness must be > 0, got {thickness!r}")
    rng = np.random.default_rng(seed)
    gx, gy = ground
    x0, y0, y1 = 2.0, centre_y - thickness / 2, centre_y + thickness / 2
    sensors = (np.array([x0 + length / 2, centre_y - gy / 2, 1.7]),
               np.array([x0 + length / 2, centre_y + gy / 2, 1.7]))
    # (class, p0, u, v, which sensor sees it: 0, 1, or both)
    gx0 = x0 + length / 2 - gx / 2
    parts = [("ground", (gx0, centre_y - gy / 2, 0.0), (gx, 0, 0), (0, y0 - centre_y + gy / 2, 0), 0),
             ("ground", (gx0, y1, 0.0), (gx, 0, 0), (0, centre_y + gy / 2 - y1, 0), 1),
             ("front", (x0, y0, 0.0), (length, 0, 0), (0, 0, height), 0),
             ("back", (x0, y1, 0.0), (length, 0, 0), (0, 0, height), 1),
             ("top", (x0, y0, height), (length, 0, 0), (0, thickness, 0), 2)]
    verts, faces, classes = [], [], {}
    seen: tuple[list, list] = ([], [])
    for name, p0, u, v, who in parts:
        pts, quad = _rect(rng, spacing, p0, u, v)
        f0 = 2 * len(verts)
        faces.append(np.array([[0, 1, 2], [0, 2, 3]]) + 4 * len(verts))
        verts.append(quad)
        start, _ = classes.get(name, (f0, f0))
        classes[name] = (start, f0 + 2)
        if who == 2:
            half = rng.random(len(pts)) < 0.5
            seen[0].append(pts[half])
            seen[1].append(pts[~half])
        else:
            seen[who].append(pts)
    root = Path(root)
    (root / "velodyne").mkdir(parents=True, exist_ok=True)
    poses = []
    for i, s in enumerate(sensors):
        pts = np.concatenate(seen[i])
        rec = np.zeros((len(pts), 4), "<f4")
        rec[:, :3] = pts - s
        with atomic_open(root / "velodyne" / f"{i:06d}.bin", "wb") as fh:
            fh.write(rec.tobytes())
        # identity rotation and Tr: world = scan + sensor position
        poses.append(" ".join(repr(float(x)) for x in np.c_[np.eye(3), s].ravel()))
    with atomic_open(root / "poses.txt", "w") as fh:
        fh.write("\n".join(poses) + "\n")
    with atomic_open(root / "calib.txt", "w") as fh:  # the poses are the scanner's (a sequence needs its Tr)
        fh.write("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    return {"sequence": root, "gt": Mesh(np.concatenate(verts), np.concatenate(faces)), "classes": classes,
            "points": np.concatenate(seen[0] + seen[1])}
