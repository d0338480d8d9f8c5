"""Reading point clouds: the entry points over every format backend (see :mod:`tiled_gridpull.io.formats`).

Every reader returns a :class:`~tiled_gridpull.cloud.PointCloud` with float64 world coordinates: georeferenced
LiDAR (UTM northings around 4e6 m, state-plane feet around 1e6) loses millimetres in float32, so nothing here
narrows coordinates.

Every problem with an input file (missing, unreadable, truncated, corrupted, empty, degenerate) raises
:class:`~tiled_gridpull.errors.InputError` with a one-line message that starts with the file path; exceptions
from the parsers (plyfile, laspy/lazrs, numpy) never reach the user as tracebacks.

:func:`iter_point_chunks` streams LAS/LAZ through ``laspy``'s chunk iterator so memory is bounded by the chunk
size; NPY and binary PLY are memory-mapped and sliced; text and ASCII PLY files are parsed whole, then sliced.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from ..cloud import PointCloud, clean_points, cloud_slices, drop_nonfinite_rows
from ..errors import ConfigError, InputError
from .formats import PointFormat, point_format
from .input_errors import check_path, input_errors
from .kitti import kitti_chunks, kitti_sequence_count, read_kitti_sequence
from .remote import is_url, shown

__all__ = ["read_points", "iter_point_chunks", "iter_row_chunks", "point_count"]


def read_points(path: str | os.PathLike, *, clean: bool = True,
                frames: tuple[int, int] | Iterable[int] | None = None) -> PointCloud:
    """Read a point cloud file (or a KITTI sequence directory) into memory.

    Parameters
    ----------
    path : str or path-like
        A file with one of :data:`~tiled_gridpull.io.formats.SUPPORTED_POINT_FORMATS` (suffix is
        case-insensitive), or a KITTI sequence directory (see :func:`read_kitti_sequence`).
    clean : bool
        Apply :func:`~tiled_gridpull.cloud.clean_points` (drop non-finite and duplicate points, refuse
        empty or degenerate clouds).
    frames : (start, stop) tuple or iterable of int, optional
        KITTI sequences only: the frames to read (see :func:`read_kitti_sequence`).

    Returns
    -------
    PointCloud
        ``xyz`` is (N, 3) float64 in the file's units.

    Raises
    ------
    InputError
        The file is missing, unreadable, of an unknown format, truncated, corrupted, empty or degenerate.
    ConfigError
        ``frames`` given for a file, or an invalid ``frames`` selection.
    """
    if is_url(path):
        cloud = _read_url(path)
        return clean_points(cloud, what=shown(path)) if clean else cloud
    p = check_path(path)
    if p.is_dir():
        cloud = read_kitti_sequence(p, frames)
    else:
        if frames is not None:
            raise ConfigError(f"{p}: frames= applies only to KITTI sequence directories")
        fmt = point_format(p)
        with input_errors(p, fmt.name):
            cloud = _read_file(p, fmt)
    if clean:
        cloud = clean_points(cloud, what=str(p))
    return cloud


def _read_url(url: str) -> PointCloud:
    """A whole COPC file or EPT on a web server, every node in stream order."""
    from ..cloud import concat_clouds
    from .indexed import indexed_kind, read_index, read_levels

    if indexed_kind(url) is None:
        raise InputError(f"{shown(url)}: only COPC files and EPTs are read from a URL; download it and give its path")
    index = read_index(url)
    parts = list(read_levels(index, int(index.keys[:, 0].max(initial=0)) + 1, attributes=True))
    if not parts:
        raise InputError(f"{shown(url)}: no points")
    return concat_clouds(parts, shown(url))


def iter_point_chunks(paths: str | os.PathLike | Iterable[str | os.PathLike],
                      chunk_size: int = 1_000_000, *, gps_time: bool = False) -> Iterator[PointCloud]:
    """Stream points from one or more files in chunks of at most ``chunk_size`` points.

    LAS/LAZ files are decoded chunk by chunk (``laspy`` chunk iterator), so memory is bounded by the chunk,
    never the whole file. NPY and binary PLY are memory-mapped and sliced; KITTI sequences are read frame by
    frame; text and ASCII PLY files are parsed whole and then sliced.

    Chunks are *not* cleaned (duplicates and degeneracy only make sense for a whole cloud or tile), except
    that rows with non-finite coordinates are dropped and counted in ``chunk.report["nonfinite_dropped"]``;
    a chunk left empty is skipped.

    Parameters
    ----------
    paths : path or iterable of paths
    chunk_size : int
        Maximum number of points per chunk (> 0).
    gps_time : bool
        Also read each point's GPS time into ``attributes["gps_time"]`` (LAS/LAZ; other formats, and LAS point
        formats without GPS time, raise InputError).

    Yields
    ------
    PointCloud
        ``source`` is ``"<path>[start:stop]"`` (the rows of the file the chunk came from); ``crs`` is the
        file's.

    Raises
    ------
    InputError
        As :func:`read_points`; also for a file that holds no points. A file found truncated part-way raises
        after the chunks before the damage have been yielded.
    """
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size <= 0:
        raise ConfigError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    chunk_size = int(chunk_size)
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    for path in paths:
        p = check_path(path)
        if p.is_dir():
            if gps_time:
                raise InputError(f"{p}: a KITTI sequence has its poses already; a trajectory applies to LAS/LAZ")
            chunks = kitti_chunks(p, None, chunk_size)
            kind = "KITTI sequence"
        else:
            fmt = point_format(p)
            if gps_time and fmt.timed_chunks is None:
                raise InputError(f"{p}: {fmt.name} files carry no GPS time, which a trajectory needs (LAS/LAZ)")
            chunks = fmt.timed_chunks(p, chunk_size) if gps_time else _file_chunks(p, fmt, chunk_size)
            kind = fmt.name
        rows = yielded = 0
        with input_errors(p, kind):
            for chunk in chunks:
                rows += len(chunk)
                chunk = drop_nonfinite_rows(chunk)
                if len(chunk):
                    yielded += 1
                    yield chunk
        if rows == 0:
            raise InputError(f"{p}: contains no points")
        if yielded == 0:
            raise InputError(f"{p}: no finite points (all {rows} have NaN or infinite coordinates)")


def iter_row_chunks(path: str | os.PathLike, start: int, stop: int, chunk_size: int = 1_000_000, *,
                    gps_time: bool = False) -> Iterator[PointCloud]:
    """Points ``start`` to ``stop`` of a LAS/LAZ file (file order) in chunks, as :func:`iter_point_chunks`
    gives them (non-finite rows dropped): one segment of a partition run in parallel. Together, the segments of
    a file in order give exactly the chunks' points of the whole file, in order.

    Raises
    ------
    InputError
        As :func:`iter_point_chunks`; also for a format other than LAS/LAZ.
    """
    p = check_path(path)
    fmt = point_format(p)
    if fmt.name not in ("LAS", "LAZ"):
        raise InputError(f"{p}: only LAS/LAZ files are read by row ranges, not {fmt.name}")
    from .las import row_chunks

    with input_errors(p, fmt.name):
        for chunk in row_chunks(p, int(chunk_size), start, stop, gps_time=gps_time):
            chunk = drop_nonfinite_rows(chunk)
            if len(chunk):
                yield chunk


def point_count(path: str | os.PathLike) -> int:
    """Number of points stored in a file, as cheaply as possible (before any cleaning).

    From the header for LAS/LAZ, PLY and NPY; from file sizes for KITTI scans and sequences (every frame
    present); text files are scanned line by line (no header to trust), without parsing numbers.

    Raises
    ------
    InputError
        As :func:`read_points` for a missing, unreadable, unknown or corrupted file.
    """
    if is_url(path):  # a COPC file or an EPT on a web server: its header
        from .indexed import read_index

        return read_index(path).points
    p = check_path(path)
    if p.is_dir():
        with input_errors(p, "KITTI sequence"):
            return kitti_sequence_count(p)
    fmt = point_format(p)
    with input_errors(p, fmt.name):
        return fmt.count(p)


def read_crs(path: str | os.PathLike) -> str | None:
    """The coordinate reference system a file declares (WKT), from its header only; None for formats without
    one (PLY, NPY, text, KITTI) and files that declare none.

    Raises
    ------
    InputError
        As :func:`point_count`.
    """
    if is_url(path):
        from .indexed import read_index

        return read_index(path).crs
    p = check_path(path)
    if p.is_dir():
        return None
    fmt = point_format(p)
    if fmt.crs is None:
        return None
    with input_errors(p, fmt.name):
        return fmt.crs(p)


def _read_file(p: Path, fmt: PointFormat) -> PointCloud:
    return fmt.read(p)


def _file_chunks(p: Path, fmt: PointFormat, chunk_size: int) -> Iterator[PointCloud]:
    if fmt.chunks is not None:
        yield from fmt.chunks(p, chunk_size)
        return
    cloud = _read_file(p, fmt)
    yield from cloud_slices(cloud, chunk_size, str(p))
