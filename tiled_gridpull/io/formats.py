"""The point-cloud formats :func:`~tiled_gridpull.io.read_points` understands, by file suffix.

Each format is a backend module with ``read(path) -> PointCloud`` and ``count(path) -> int``, and optionally
``chunks(path, chunk_size)`` when it can stream (otherwise the whole file is read, then sliced). A new format
is one module plus one ``register`` line below.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from ..cloud import PointCloud
from ..errors import InputError
from . import e57, indexed, kitti, las, npy, pcd, ply, text

__all__ = ["PointFormat", "POINT_FORMATS", "SUPPORTED_POINT_FORMATS", "register", "point_format"]


@dataclass(frozen=True)
class PointFormat:
    """A reader backend.

    Attributes
    ----------
    name : str
        The format's name in messages ("LAZ", "KITTI scan", ...).
    read : callable
        ``read(path) -> PointCloud``: the whole file, uncleaned.
    count : callable
        ``count(path) -> int``: points stored in the file, as cheaply as possible.
    chunks : callable, optional
        ``chunks(path, chunk_size) -> iterator of PointCloud`` with bounded memory; None: read, then slice.
    crs : callable, optional
        ``crs(path) -> str | None``: the CRS the file declares (WKT), from its header; None: the format has none.
    timed_chunks : callable, optional
        As ``chunks``, with each point's GPS time in ``attributes["gps_time"]``; None: the format has none.
    """

    name: str
    read: Callable[[Path], PointCloud]
    count: Callable[[Path], int]
    chunks: Callable[[Path, int], Iterator[PointCloud]] | None = None
    crs: Callable[[Path], str | None] | None = None
    timed_chunks: Callable[[Path, int], Iterator[PointCloud]] | None = None


POINT_FORMATS: dict[str, PointFormat] = {}
"""Suffix (lower case, with the dot) -> backend, in the order formats are listed in messages."""


def register(suffix: str, fmt: PointFormat) -> None:
    """Read files ending in ``suffix`` (case-insensitive) with ``fmt``."""
    POINT_FORMATS[suffix.lower()] = fmt


register(".ply", PointFormat("PLY", ply.read, ply.count, ply.chunks))
register(".xyz", PointFormat("XYZ", text.read, text.count))
register(".txt", PointFormat("text", text.read, text.count))
register(".pts", PointFormat("PTS", text.read, text.count))
register(".csv", PointFormat("CSV", text.read, text.count))
register(".npy", PointFormat("NPY", npy.read, npy.count, npy.chunks))
register(".las", PointFormat("LAS", las.read, las.count, las.chunks, las.crs, las.timed_chunks))
register(".laz", PointFormat("LAZ", las.read, las.count, las.chunks, las.crs, las.timed_chunks))
register(".bin", PointFormat("KITTI scan", kitti.read, kitti.count))
register(".pcd", PointFormat("PCD", pcd.read, pcd.count))
register(".e57", PointFormat("E57", e57.read, e57.count, e57.chunks))
# Entwine Point Tiles: the ept.json beside its ept-hierarchy/ and ept-data/ (COPC files are LAZ files)
register(".json", PointFormat("EPT", indexed.read, indexed.count, indexed.chunks, indexed.crs))

SUPPORTED_POINT_FORMATS: tuple[str, ...] = tuple(POINT_FORMATS)
"""The built-in file suffixes (case-insensitive); a directory is a KITTI sequence. Formats registered later are
in :data:`POINT_FORMATS`, which messages list."""


def point_format(p: Path) -> PointFormat:
    """The backend for ``p``'s suffix; InputError naming the supported ones when there is none."""
    suffix = p.suffix.lower()
    if suffix not in POINT_FORMATS:
        shown = f"'{suffix}'" if suffix else "(no extension)"
        raise InputError(f"{p}: unknown point cloud format {shown} (supported: "
                         f"{', '.join(POINT_FORMATS)}, or a KITTI sequence directory)")
    return POINT_FORMATS[suffix]
