"""E57 point clouds (terrestrial laser scanners: several scans, each with its pose), read with pye57.

Every scan's points come in the file's common frame (its pose applied; spherical coordinates converted), and every
point gets its scan's position as its sensor origin, so tiled mode's ``orientation: auto`` faces each surface
towards the scanner that saw it. Points flagged invalid by the scan (``cartesianInvalidState`` /
``sphericalInvalidState``) are dropped. Intensity is kept when the scans have it. A scan is read whole (the
library reads scans, not ranges of them): memory follows the largest scan, not the file. A pose that places no
point (a translation beyond what float64 arithmetic resolves, a zero rotation quaternion) is refused, naming it.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .._optional import require
from ..cloud import PointCloud, concat_clouds
from ..errors import InputError
from .input_errors import check_frame

__all__ = ["read", "chunks", "count"]


def _open(p: Path):
    pye57 = require("pye57", "reading E57 files")
    return pye57.E57(str(p), mode="r")


def count(p: Path) -> int:
    """Points the scans' headers declare (invalid ones included)."""
    e57 = _open(p)
    try:
        return int(sum(e57.get_header(i).point_count for i in range(e57.scan_count)))
    finally:
        e57.close()


def _scans(p: Path) -> Iterator[PointCloud]:
    e57 = _open(p)
    try:
        crs = None
        try:
            root = e57.root
            if root.isDefined("coordinateMetadata"):
                crs = str(root["coordinateMetadata"].value()).strip() or None
        except Exception:  # the metadata is optional; a malformed one is not worth refusing the points for
            crs = None
        done = 0
        for i in range(e57.scan_count):
            _check_pose(p, i, e57.get_header(i))
            data = e57.read_scan(i, intensity=True, colors=True, ignore_missing_fields=True)
            xyz = np.column_stack([np.asarray(data[k], dtype=np.float64)
                                   for k in ("cartesianX", "cartesianY", "cartesianZ")])
            origin = np.asarray(e57.scan_position(i), dtype=np.float64).reshape(3)
            attrs = {"scan": np.full(len(xyz), i, np.int32)}
            if "intensity" in data:
                attrs["intensity"] = np.asarray(data["intensity"], dtype=np.float32)
            if all(f"color{c}" in data for c in ("Red", "Green", "Blue")):
                # uint8 as pye57 reads them (the colour limits of most files are 0-255)
                for c in ("Red", "Green", "Blue"):
                    attrs[c.lower()] = np.asarray(data[f"color{c}"]).copy()
            yield PointCloud(xyz, sensor=np.broadcast_to(origin, xyz.shape).copy(), attributes=attrs, crs=crs,
                             source=f"{p}[scan {i}]", report={"points_read": len(xyz)})
            done += len(xyz)
    finally:
        e57.close()


def _check_pose(p: Path, i: int, header) -> None:
    """Refuse a scan pose pye57 would apply to every point but that places none: a translation that is not
    finite or is absurd (1e308 overflowed the first sum over the points), a rotation quaternion that is not 4
    finite numbers of non-zero length (a zero one puts every point on the scanner)."""
    where = f"{p}: scan {i}'s pose"
    check_frame(where, np.asarray(header.translation, dtype=np.float64).reshape(3), label="translation")
    q = np.asarray(header.rotation, dtype=np.float64).ravel()
    if q.shape != (4,) or not np.all(np.isfinite(q)) or not np.linalg.norm(q) > 0:
        raise InputError(f"{where} rotation '{' '.join(f'{v:g}' for v in q)}' is not a quaternion (4 finite "
                         "numbers, not all zero): a damaged file")


def read(p: Path) -> PointCloud:
    """Every scan, in the file's common frame, as one cloud."""
    return concat_clouds(list(_scans(p)), str(p))


def chunks(p: Path, chunk_size: int) -> Iterator[PointCloud]:
    """Scan by scan, each cut into pieces of at most ``chunk_size`` points."""
    for scan in _scans(p):
        for s in range(0, len(scan), chunk_size):
            part = slice(s, s + chunk_size)
            yield PointCloud(scan.xyz[part], sensor=scan.sensor[part],
                             attributes={k: v[part] for k, v in scan.attributes.items()}, crs=scan.crs,
                             source=f"{scan.source}[{s}:{s + len(scan.xyz[part])}]",
                             report={"points_read": len(scan.xyz[part])})
