"""Writing a point cloud as a cloud-optimized point cloud (COPC) or as Entwine Point Tiles (EPT), the formats
survey archives publish so that a reader can fetch one region without the rest.

Both lay the points into an octree over a cube: every node keeps at most one point per cell of a ``span``^3
grid over its cube (an even subsample, the node's level of detail) and hands the others to its children; a node
left with ``max_node_points`` or fewer keeps them all. That is the layout PDAL's COPC writer and Entwine build.
The project writes these files for its tests and benchmarks (``tiled-gridpull sample street --format copc``);
the readers are :mod:`tiled_gridpull.io.indexed`.

* COPC through copclib (``pip install 'tiled-gridpull[copc]'``): one LAZ chunk per node, the hierarchy in an
  EVLR. Point format 6, 1 mm scale unless given.
* EPT written here (its structures are a JSON header, JSON hierarchy pages and one file per node): ``ept.json``,
  ``ept-hierarchy/0-0-0-0.json`` and ``ept-data/<d>-<x>-<y>-<z>.laz`` (``data_type="laszip"``, through laspy) or
  ``.bin`` (``"binary"``: the schema's fields packed little-endian).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .._optional import require
from ..errors import ConfigError

__all__ = ["octree_layout", "write_copc", "write_ept"]

#: a node's grid of kept points (cells per side), as in PDAL's and Entwine's writers
SPAN = 128


def octree_layout(xyz: np.ndarray, *, max_node_points: int = 50_000, span: int = SPAN,
                  max_depth: int = 16) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Assign every point to an octree node.

    Parameters
    ----------
    xyz : (N, 3) float64
    max_node_points : int
        A node with at most this many points left keeps them all (a leaf).
    span : int
        Cells per side of a node's grid: a node keeps the first point of each cell.
    max_depth : int
        Nodes at this depth keep everything left (bounds the tree on duplicate-heavy data).

    Returns
    -------
    keys : (M, 4) int64
        The nodes holding points, as (depth, x, y, z), sorted.
    node_of : (N,) int64
        Row of ``keys`` each point belongs to.
    halfsize : float
        Half the cube's edge (file units).
    center : (3,) float64
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    center = (lo + hi) / 2
    halfsize = float(max((hi - lo).max() / 2, 1e-9)) * (1 + 1e-9)
    base = center - halfsize
    n = len(xyz)
    level = np.full(n, -1, np.int64)
    cell = np.zeros((n, 3), np.int64)
    left = np.arange(n)
    for depth in range(max_depth + 1):
        if len(left) == 0:
            break
        size = 2 * halfsize / (1 << depth)
        node = np.clip(np.floor((xyz[left] - base) / size).astype(np.int64), 0, (1 << depth) - 1)
        node_id = (node[:, 0] << 40) | (node[:, 1] << 20) | node[:, 2]
        uniq, inv, counts = np.unique(node_id, return_inverse=True, return_counts=True)
        keep = counts[inv] <= max_node_points  # a small node keeps all it has
        if depth == max_depth:
            keep[:] = True
        else:
            sub = np.clip(np.floor((xyz[left] - base - node * size) / size * span).astype(np.int64), 0, span - 1)
            vox = ((inv * span + sub[:, 0]) * span + sub[:, 1]) * span + sub[:, 2]
            _, first = np.unique(vox, return_index=True)  # first point (in input order) of every cell
            keep[first] = True
        level[left[keep]] = depth
        cell[left[keep]] = node[keep]
        left = left[~keep]
    full = np.column_stack([level, cell])
    keys, node_of = np.unique(full, axis=0, return_inverse=True)
    return keys, node_of.ravel(), halfsize, center


def _check(xyz) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0 or not np.all(np.isfinite(xyz)):
        raise ConfigError("indexed point cloud writers need a non-empty (N, 3) array of finite coordinates")
    return xyz


def _quantized(xyz: np.ndarray, scale: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points as the file will store them (integers times the scale plus the offset), the scales and the
    offsets: the header's bounds and the octree are computed from these, so they describe the stored points."""
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    if scale is None:  # 1 mm, or finer for small objects
        scale = min(0.001, float((hi - lo).max()) / 1e6 or 0.001)
    scales = np.full(3, float(scale))
    offsets = np.round((lo + hi) / 2, 3)
    ints = np.round((xyz - offsets) / scales)
    if np.abs(ints).max() >= 2**31 - 1:
        raise ConfigError(f"scale {scale:g} is too fine for 32-bit coordinates over an extent of "
                          f"{float((hi - lo).max()):g}")
    return ints * scales + offsets, scales, offsets


def _format6_records(xyz: np.ndarray, scales, offsets, gps_time=None, intensity=None):
    """Point format 6 records (LAS 1.4) of ``xyz``, as a laspy ScaleAwarePointRecord."""
    import laspy

    rec = laspy.ScaleAwarePointRecord.zeros(len(xyz), point_format=laspy.PointFormat(6), scales=scales,
                                            offsets=offsets)
    rec.x, rec.y, rec.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec.return_number[:] = 1
    rec.number_of_returns[:] = 1
    if gps_time is not None:
        rec.gps_time = gps_time
    if intensity is not None:
        rec.intensity = intensity
    return rec


def write_copc(path: str | os.PathLike, xyz, *, wkt: str | None = None, scale: float | None = None,
               max_node_points: int = 50_000, gps_time=None, intensity=None) -> Path:
    """Write ``xyz`` as a COPC file (``*.copc.laz``) with copclib; returns the path.

    Points keep their input order within a node; nodes are written depth first in key order. ``gps_time``
    and ``intensity`` ((N,) float64 and uint16), when given, fill those fields of each point.
    """
    copc = require("copclib", "writing COPC files")
    path = Path(path)
    xyz, scales, offsets = _quantized(_check(xyz), scale)
    keys, node_of, halfsize, center = octree_layout(xyz, max_node_points=max_node_points)
    order = np.argsort(node_of, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(node_of, minlength=len(keys)))]
    cfg = copc.CopcConfigWriter(6, copc.Vector3(*scales), copc.Vector3(*offsets), wkt or "")
    hdr = cfg.las_header
    hdr.min = copc.Vector3(*xyz.min(axis=0))
    hdr.max = copc.Vector3(*xyz.max(axis=0))
    info = cfg.copc_info
    info.center_x, info.center_y, info.center_z = (float(v) for v in center)
    info.halfsize = halfsize
    info.spacing = 2 * halfsize / SPAN
    writer = copc.FileWriter(str(path), cfg)
    try:
        for k, key in enumerate(keys):
            rows = order[bounds[k]:bounds[k + 1]]
            rec = _format6_records(xyz[rows], scales, offsets, None if gps_time is None else gps_time[rows],
                                   None if intensity is None else intensity[rows])
            raw = np.frombuffer(rec.array.tobytes(), np.int8)  # copclib takes the records as signed chars
            writer.AddNode(copc.VoxelKey(*(int(v) for v in key)), copc.VectorChar(raw))
    finally:
        writer.Close()
    return path


def write_ept(directory: str | os.PathLike, xyz, *, wkt: str | None = None, scale: float | None = None,
              max_node_points: int = 50_000, data_type: str = "laszip", intensity=None) -> Path:
    """Write ``xyz`` as Entwine Point Tiles under ``directory``; returns the path of its ``ept.json``.

    Parameters
    ----------
    data_type : {"laszip", "binary"}
        Node files as LAZ (``.laz``) or as packed binary records of the schema (``.bin``).
    intensity : (N,) uint16, optional
        Each point's intensity, listed in the schema as ``Intensity``.
    """
    import laspy

    if data_type not in ("laszip", "binary"):
        raise ConfigError(f"EPT data_type must be 'laszip' or 'binary', got {data_type!r}")
    xyz, scales, offsets = _quantized(_check(xyz), scale)
    root = Path(directory)
    (root / "ept-data").mkdir(parents=True, exist_ok=True)
    (root / "ept-hierarchy").mkdir(exist_ok=True)
    keys, node_of, halfsize, center = octree_layout(xyz, max_node_points=max_node_points)
    order = np.argsort(node_of, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(node_of, minlength=len(keys)))]
    hierarchy = {}
    for k, key in enumerate(keys):
        name = "-".join(str(int(v)) for v in key)
        rows = order[bounds[k]:bounds[k + 1]]
        pts = xyz[rows]
        hierarchy[name] = len(pts)
        if data_type == "laszip":
            header = laspy.LasHeader(point_format=6, version="1.4")
            header.scales, header.offsets = scales, offsets
            las = laspy.LasData(header)
            las.points = _format6_records(pts, scales, offsets, None, None if intensity is None else intensity[rows])
            las.write(str(root / "ept-data" / f"{name}.laz"))
        else:
            rec = np.empty(len(pts), [("xyz", "<i4", (3,))] + ([("i", "<u2")] if intensity is not None else []))
            rec["xyz"] = np.round((pts - offsets) / scales)
            if intensity is not None:
                rec["i"] = intensity[rows]
            (root / "ept-data" / f"{name}.bin").write_bytes(rec.tobytes())
    # a node every reader reaches has its ancestors listed (with 0 points when they hold none)
    for key in keys:
        d, x, y, z = (int(v) for v in key)
        while d > 0:
            d, x, y, z = d - 1, x >> 1, y >> 1, z >> 1
            hierarchy.setdefault(f"{d}-{x}-{y}-{z}", 0)
    (root / "ept-hierarchy" / "0-0-0-0.json").write_text(json.dumps(hierarchy, sort_keys=True))
    cube = np.r_[center - halfsize, center + halfsize]
    schema = [{"name": axis, "type": "signed", "size": 4, "scale": float(s), "offset": float(o)}
              for axis, s, o in zip("XYZ", scales, offsets)]
    if intensity is not None:
        schema.append({"name": "Intensity", "type": "unsigned", "size": 2})
    meta = {"bounds": cube.tolist(), "boundsConforming": np.r_[xyz.min(axis=0), xyz.max(axis=0)].tolist(),
            "dataType": data_type, "hierarchyType": "json", "points": int(len(xyz)), "schema": schema,
            "span": SPAN, "srs": {"wkt": wkt} if wkt else {}, "version": "1.0.0"}
    out = root / "ept.json"
    out.write_text(json.dumps(meta, indent=1))
    return out
