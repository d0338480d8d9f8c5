"""Point cloud readers: PLY, text (XYZ/TXT/PTS/CSV), NPY, LAS/LAZ, KITTI scans and KITTI sequences.

Every reader returns a :class:`PointCloud` with float64 world coordinates: georeferenced LiDAR (UTM northings
around 4e6 m, state-plane feet around 1e6) loses millimetres in float32, so nothing here narrows coordinates.

Every problem with an input file (missing, unreadable, truncated, corrupted, empty, degenerate) raises
:class:`~tiled_gridpull.errors.InputError` with a one-line message that starts with the file path; exceptions
from the parsers (plyfile, laspy/lazrs, numpy) never reach the user as tracebacks.

:func:`iter_point_chunks` streams LAS/LAZ through ``laspy``'s chunk iterator so memory is bounded by the chunk
size; NPY and binary PLY are memory-mapped and sliced; text and ASCII PLY files are parsed whole, then sliced.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError, GridPullError, InputError

__all__ = ["PointCloud", "read_points", "iter_point_chunks", "clean_points", "read_kitti_sequence",
           "point_count", "SUPPORTED_POINT_FORMATS"]

SUPPORTED_POINT_FORMATS: tuple[str, ...] = (".ply", ".xyz", ".txt", ".pts", ".csv", ".npy", ".las", ".laz",
                                            ".bin")
"""File suffixes :func:`read_points` understands (case-insensitive); a directory is a KITTI sequence."""

_TEXT_SUFFIXES = (".xyz", ".txt", ".pts", ".csv")
_FORMAT_NAMES = {".ply": "PLY", ".xyz": "XYZ", ".txt": "text", ".pts": "PTS", ".csv": "CSV", ".npy": "NPY",
                 ".las": "LAS", ".laz": "LAZ", ".bin": "KITTI scan"}

# Relative tolerance on singular values for the collinear / coplanar tests (see clean_points).
_DEGENERATE_RTOL = 1e-9
# Degeneracy is first tested on this many evenly spaced points: a non-degenerate subset proves the whole
# cloud non-degenerate, so the full O(N) factorisation is only needed for (nearly) degenerate clouds.
_IDENTICAL_ULPS = 64
_EXTENT_RANGE = (1e-150, 1e150)
_DEGENERATE_SAMPLE = 200_000
_READ_CHUNK = 1_000_000


@dataclass(eq=False)
class PointCloud:
    """A point cloud in world coordinates, with what reading and cleaning it did.

    Attributes
    ----------
    xyz : (N, 3) float64
        World coordinates, in the file's units (metres for most data, international feet for Autzen).
    normals : (N, 3) float32, optional
        Unit normals when the file has them (a zero row means the file gave a zero-length normal).
    sensor : (N, 3) float64, optional
        Sensor origin of every point in world coordinates, when known (KITTI).
    attributes : dict of str to (N, ...) arrays
        Optional per-point arrays, e.g. ``"intensity"``, ``"frame"`` (int32, KITTI sequences).
    crs : str, optional
        Coordinate reference system as WKT or a description, when the file has one (LAS/LAZ).
    source : str
        Where the points came from (a path, plus a range for chunks).
    report : dict
        What reading and cleaning did, e.g. ``{"points_read": n, "nonfinite_dropped": k,
        "duplicates_dropped": m, "points_kept": n - k - m}``.
    """

    xyz: np.ndarray
    normals: np.ndarray | None = None
    sensor: np.ndarray | None = None
    attributes: dict = field(default_factory=dict)
    crs: str | None = None
    source: str = ""
    report: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        # Coordinates are widened, never narrowed: float32 input converts to float64 exactly.
        self.xyz = np.asarray(self.xyz, dtype=np.float64)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise InputError(f"{self.source or 'point cloud'}: xyz must have shape (N, 3), "
                             f"got {self.xyz.shape}")
        n = len(self.xyz)
        if self.normals is not None:
            self.normals = np.asarray(self.normals, dtype=np.float32)
            if self.normals.shape != (n, 3):
                raise InputError(f"{self.source or 'point cloud'}: normals have shape {self.normals.shape}, "
                                 f"expected ({n}, 3)")
        if self.sensor is not None:
            self.sensor = np.asarray(self.sensor, dtype=np.float64)
            if self.sensor.shape != (n, 3):
                raise InputError(f"{self.source or 'point cloud'}: sensor origins have shape "
                                 f"{self.sensor.shape}, expected ({n}, 3)")

    def __len__(self) -> int:
        return len(self.xyz)

    def take(self, idx) -> "PointCloud":
        """The rows ``idx`` (index or boolean array, or slice) of every per-point array."""
        return _take(self, idx)


# ------------------------------------------------------------------------------------------------------------
# public entry points


def read_points(path: str | os.PathLike, *, clean: bool = True,
                frames: tuple[int, int] | Iterable[int] | None = None) -> PointCloud:
    """Read a point cloud file (or a KITTI sequence directory) into memory.

    Parameters
    ----------
    path : str or path-like
        A file with one of :data:`SUPPORTED_POINT_FORMATS` (suffix is case-insensitive), or a KITTI sequence
        directory (see :func:`read_kitti_sequence`).
    clean : bool
        Apply :func:`clean_points` (drop non-finite and duplicate points, refuse empty or degenerate clouds).
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
    p = _check_path(path)
    if p.is_dir():
        cloud = read_kitti_sequence(p, frames)
    else:
        if frames is not None:
            raise ConfigError(f"{p}: frames= applies only to KITTI sequence directories")
        suffix = _suffix(p)
        with _input_errors(p, suffix):
            cloud = _read_file(p, suffix)
    if clean:
        cloud = clean_points(cloud, what=str(p))
    return cloud


def iter_point_chunks(paths: str | os.PathLike | Iterable[str | os.PathLike],
                      chunk_size: int = 1_000_000) -> Iterator[PointCloud]:
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
        p = _check_path(path)
        if p.is_dir():
            chunks = _kitti_chunks(p, None, chunk_size)
            suffix = ""
        else:
            suffix = _suffix(p)
            chunks = _file_chunks(p, suffix, chunk_size)
        rows = yielded = 0
        with _input_errors(p, suffix):
            for chunk in chunks:
                rows += len(chunk)
                chunk = _drop_nonfinite_rows(chunk)
                if len(chunk):
                    yielded += 1
                    yield chunk
        if rows == 0:
            raise InputError(f"{p}: contains no points")
        if yielded == 0:
            raise InputError(f"{p}: no finite points (all {rows} have NaN or infinite coordinates)")


def clean_points(cloud: PointCloud, *, what: str = "", min_points: int = 10,
                 reject_planar: bool = True) -> PointCloud:
    """Drop non-finite and duplicate points; refuse clouds the reconstruction cannot use.

    Steps, in order:

    1. an empty cloud is refused;
    2. points with a non-finite coordinate are dropped (counted in ``report["nonfinite_dropped"]``, with a
       warning); if none is finite the cloud is refused;
    3. exact duplicate points are dropped, keeping the first occurrence and the order of the rest (counted in
       ``report["duplicates_dropped"]``);
    4. a cloud whose points are all identical, or that has fewer than ``min_points`` points, is refused;
    5. a cloud whose points are all collinear, or (when ``reject_planar``) all coplanar, is refused. The test
       uses the singular values s1 >= s2 >= s3 of the mean-centred float64 coordinates: s2 <= 1e-9 s1 is
       collinear, s3 <= 1e-9 s1 is coplanar. Centring first keeps the test exact for coordinates around 1e7.

    Normals, sensor origins and per-point attributes are filtered with the points. The input is not modified.

    Parameters
    ----------
    cloud : PointCloud
    what : str
        Name used in messages (default: ``cloud.source``).
    min_points : int
        Fewest points accepted after cleaning.
    reject_planar : bool
        Refuse coplanar clouds (the tiled pipeline passes False: a flat parking lot is a legal tile).

    Returns
    -------
    PointCloud
        A new cloud; ``report`` adds ``points_read``, ``nonfinite_dropped``, ``duplicates_dropped``,
        ``points_kept``.

    Raises
    ------
    InputError
        Empty, no finite points, too few points, or degenerate (identical / collinear / coplanar).
    """
    what = what or cloud.source or "point cloud"
    xyz = cloud.xyz
    n = len(xyz)
    if n == 0:
        raise InputError(f"{what}: contains no points")
    report = dict(cloud.report)
    report["points_read"] = report.get("points_read", n)

    finite = np.isfinite(xyz).all(axis=1)
    n_finite = int(np.count_nonzero(finite))
    if n_finite == 0:
        raise InputError(f"{what}: no finite points (all {n} have NaN or infinite coordinates)")
    keep = None
    if n_finite < n:
        warnings.warn(f"{what}: dropped {n - n_finite} of {n} points with non-finite coordinates",
                      UserWarning, stacklevel=2)
        keep = np.flatnonzero(finite)
        xyz = xyz[keep]
    # accumulate, so that cleaning an already cleaned (or chunk-filtered) cloud keeps the earlier counts
    report["nonfinite_dropped"] = report.get("nonfinite_dropped", 0) + n - n_finite

    dup = _duplicate_mask(xyz)
    n_dup = int(np.count_nonzero(dup))
    if n_dup:
        unique_rows = np.flatnonzero(~dup)
        keep = unique_rows if keep is None else keep[unique_rows]
        xyz = xyz[unique_rows]
    report["duplicates_dropped"] = report.get("duplicates_dropped", 0) + n_dup

    m = len(xyz)
    if m == 1 and n_finite > 1:
        raise InputError(f"{what}: all {n_finite} points are identical")
    if m < min_points:
        dropped = n - m
        extra = f" after dropping {dropped} non-finite or duplicate points" if dropped else ""
        raise InputError(f"{what}: only {m} points{extra} (at least {min_points} needed)")
    kind = _degeneracy(xyz, reject_planar)
    if kind is not None:
        raise InputError(f"{what}: all {m} points are {kind}; a surface cannot be reconstructed from them")
    extent = float(np.max(xyz.max(axis=0) - xyz.min(axis=0)))
    if not _EXTENT_RANGE[0] <= extent <= _EXTENT_RANGE[1]:
        # squared distances of such an extent underflow or overflow float64: the mesh would be garbage
        raise InputError(f"{what}: the points span {extent:.3g} units, outside what float64 arithmetic resolves "
                         f"({_EXTENT_RANGE[0]:g} to {_EXTENT_RANGE[1]:g}): rescale the coordinates")
    report["points_kept"] = m

    out = _take(cloud, keep, xyz=xyz)
    out.report = report
    return out


def read_kitti_sequence(root: str | os.PathLike,
                        frames: tuple[int, int] | Iterable[int] | None = None) -> PointCloud:
    """Read a KITTI odometry sequence and merge its scans into one world-frame cloud.

    Layout: ``root/velodyne/NNNNNN.bin`` (or ``root/NNNNNN.bin``), one float32 ``x y z reflectance`` scan per
    frame in metres in the Velodyne frame; ``root/poses.txt`` with one line per frame (12 numbers: the 3x4
    camera-0 pose, row-major; line i is frame i); optional ``root/calib.txt`` with a ``Tr:`` line (the 3x4
    Velodyne-to-camera-0 transform; identity when the file is absent).

    World point ``= pose_i @ Tr @ [p; 1]``; the sensor origin of frame i is ``pose_i @ Tr @ [0, 0, 0, 1]``.

    Parameters
    ----------
    root : str or path-like
        The sequence directory.
    frames : (start, stop) tuple, range or iterable of int, optional
        A 2-tuple is the half-open range ``start <= i < stop``; any other iterable lists frame numbers.
        Default: every frame, which must then be numbered 0..n-1 without gaps and match poses.txt line for
        line.

    Returns
    -------
    PointCloud
        ``xyz`` and ``sensor`` are (N, 3) float64 world coordinates (metres); attributes ``"frame"`` (N,)
        int32 and ``"intensity"`` (N,) float32 (the reflectance).

    Raises
    ------
    InputError
        Not a KITTI sequence, a missing frame file, a poses.txt that does not cover the frames, a malformed
        poses or calib line, a corrupted scan.
    ConfigError
        ``frames`` is empty, negative or repeats a frame.
    """
    root = _check_path(root)
    if not root.is_dir():
        raise InputError(f"{root}: not a directory (a KITTI sequence is a directory)")
    parts = list(_kitti_frames(root, frames))
    if not parts:  # pragma: no cover - _kitti_frames always yields at least one frame
        raise InputError(f"{root}: contains no frames")
    xyz = np.concatenate([p[1] for p in parts]) if len(parts) > 1 else parts[0][1]
    sensor = np.concatenate([np.broadcast_to(p[2], (len(p[1]), 3)) for p in parts])
    frame = np.concatenate([np.full(len(p[1]), p[0], dtype=np.int32) for p in parts])
    intensity = np.concatenate([p[3] for p in parts])
    report = {"frames": [p[0] for p in parts], "points_read": len(xyz)}
    return PointCloud(xyz, sensor=sensor, attributes={"frame": frame, "intensity": intensity},
                      source=str(root), report=report)


def point_count(path: str | os.PathLike) -> int:
    """Number of points stored in a file, as cheaply as possible (before any cleaning).

    From the header for LAS/LAZ, PLY and NPY; from file sizes for KITTI scans and sequences (every frame
    present); text files are scanned line by line (no header to trust), without parsing numbers.

    Raises
    ------
    InputError
        As :func:`read_points` for a missing, unreadable, unknown or corrupted file.
    """
    p = _check_path(path)
    if p.is_dir():
        with _input_errors(p, ""):
            _, files = _kitti_layout(p)
            return sum(_kitti_scan_size(f) // 16 for f in files.values())
    suffix = _suffix(p)
    with _input_errors(p, suffix):
        if suffix == ".ply":
            hdr = _ply_header(p)
            return _ply_vertex_element(p, hdr).count
        if suffix in (".las", ".laz"):
            import laspy

            _las_precheck(p)
            with laspy.open(str(p), laz_backend=_laz_backend()) as reader:
                return int(reader.header.point_count)
        if suffix == ".npy":
            arr = np.load(p, mmap_mode="r", allow_pickle=False)
            _npy_check(p, arr)
            return int(arr.shape[0])
        if suffix == ".bin":
            return _kitti_scan_size(p) // 16
        return _text_count(p, suffix)
    raise AssertionError("unreachable")  # pragma: no cover


# ------------------------------------------------------------------------------------------------------------
# paths and error conversion


def _check_path(path) -> Path:
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: file not found")
    if not os.access(p, os.R_OK):
        raise InputError(f"{p}: permission denied (cannot read)")
    return p


def _suffix(p: Path) -> str:
    suffix = p.suffix.lower()
    if suffix not in SUPPORTED_POINT_FORMATS:
        shown = f"'{suffix}'" if suffix else "(no extension)"
        raise InputError(f"{p}: unknown point cloud format {shown} (supported: "
                         f"{', '.join(SUPPORTED_POINT_FORMATS)}, or a KITTI sequence directory)")
    return suffix


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    msg = text[0] if text else "malformed"
    if len(msg) > 160:
        msg = msg[:157] + "..."
    return f"{exc.__class__.__name__}: {msg}"


@contextlib.contextmanager
def _input_errors(path: Path, suffix: str) -> Iterator[None]:
    """Turn any parser failure into a one-line InputError naming the file (never a traceback)."""
    kind = _FORMAT_NAMES.get(suffix, "KITTI sequence" if not suffix else suffix)
    try:
        yield
    except GridPullError:
        raise
    except MemoryError:
        # Header counts are checked against the file size before reading, but third-party parsers (laspy's
        # VLR reader, lazrs) still size some buffers from fields we cannot check; either way the file cannot
        # be read.
        raise InputError(f"{path}: out of memory while reading the {kind} file (corrupted header, or the "
                         f"file is too large to read whole: stream it with iter_point_chunks)") from None
    except PermissionError:
        raise InputError(f"{path}: permission denied (cannot read)") from None
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read file ({_reason(exc)})") from None
    except Exception as exc:  # parsers raise anything (ValueError, LaspyException, LazrsError, ...)
        raise InputError(f"{path}: truncated or corrupted {kind} file ({_reason(exc)})") from None
    except BaseException as exc:
        # a Rust extension (lazrs) that panics raises pyo3's PanicException, which derives from BaseException
        if type(exc).__name__ != "PanicException":
            raise
        raise InputError(f"{path}: truncated or corrupted {kind} file ({_reason(exc)})") from None


# ------------------------------------------------------------------------------------------------------------
# dispatch


def _read_file(p: Path, suffix: str) -> PointCloud:
    if suffix == ".ply":
        return _read_ply(p)
    if suffix in (".las", ".laz"):
        return _concat(list(_las_chunks(p, _READ_CHUNK)), str(p))
    if suffix == ".npy":
        return _read_npy(p)
    if suffix == ".bin":
        return _read_kitti_scan(p)
    return _read_text(p, suffix)


def _file_chunks(p: Path, suffix: str, chunk_size: int) -> Iterator[PointCloud]:
    if suffix in (".las", ".laz"):
        # laspy decodes exactly chunk_size points per step: memory is bounded by the chunk.
        for chunk in _las_chunks(p, chunk_size):
            yield chunk
        return
    if suffix == ".npy":
        arr = np.load(p, mmap_mode="r", allow_pickle=False)
        _npy_check(p, arr)
        n = arr.shape[0]
        normals = None if arr.dtype.names else _columns_are_normals(p, arr)
        for start in range(0, n, chunk_size):
            stop = min(start + chunk_size, n)
            yield _npy_cloud(p, np.asarray(arr[start:stop]), f"{p}[{start}:{stop}]", normals)
        return
    if suffix == ".ply":
        # binary vertices stay memory-mapped: only one chunk at a time is converted to float64
        cols, n = _ply_vertex_columns(p)
        for start in range(0, n, chunk_size):
            stop = min(start + chunk_size, n)
            part = _ply_cloud(p, cols, slice(start, stop), f"{p}[{start}:{stop}]")
            part.report = {"points_read": stop - start}
            yield part
        return
    cloud = _read_file(p, suffix)
    yield from _slices(cloud, chunk_size, str(p))


def _slices(cloud: PointCloud, chunk_size: int, name: str) -> Iterator[PointCloud]:
    n = len(cloud)
    for start in range(0, n, chunk_size):
        stop = min(start + chunk_size, n)
        part = _take(cloud, slice(start, stop))
        part.source = f"{name}[{start}:{stop}]"
        part.report = {"points_read": stop - start}
        yield part


# ------------------------------------------------------------------------------------------------------------
# helpers on clouds


def _take(cloud: PointCloud, idx, *, xyz: np.ndarray | None = None) -> PointCloud:
    """Rows ``idx`` (index array, slice or None for all) of every per-point array of ``cloud``.

    ``xyz``, when given, is ``cloud.xyz[idx]`` already computed by the caller (saves a copy at 10M points).
    """
    n = len(cloud)

    def pick(a):
        if a is None or idx is None:
            return a
        return a[idx]

    attrs = {k: (pick(v) if isinstance(v, np.ndarray) and v.ndim >= 1 and len(v) == n else v)
             for k, v in cloud.attributes.items()}
    return PointCloud(pick(cloud.xyz) if xyz is None else xyz, normals=pick(cloud.normals),
                      sensor=pick(cloud.sensor), attributes=attrs, crs=cloud.crs, source=cloud.source,
                      report=dict(cloud.report))


def _concat(parts: list[PointCloud], source: str) -> PointCloud:
    if not parts:
        return PointCloud(np.zeros((0, 3)), source=source, report={"points_read": 0})
    if len(parts) == 1:
        out = parts[0]
        out.source = source
        out.report = {"points_read": len(out)}
        return out

    def cat(arrays):
        return None if any(a is None for a in arrays) else np.concatenate(arrays)

    keys = set(parts[0].attributes).intersection(*(p.attributes for p in parts[1:]))
    attrs = {k: np.concatenate([p.attributes[k] for p in parts]) for k in keys}
    xyz = np.concatenate([p.xyz for p in parts])
    return PointCloud(xyz, normals=cat([p.normals for p in parts]), sensor=cat([p.sensor for p in parts]),
                      attributes=attrs, crs=parts[0].crs, source=source, report={"points_read": len(xyz)})


def _drop_nonfinite_rows(cloud: PointCloud) -> PointCloud:
    finite = np.isfinite(cloud.xyz).all(axis=1)
    bad = len(finite) - int(np.count_nonzero(finite))
    if bad:
        cloud = _take(cloud, np.flatnonzero(finite))
    cloud.report["nonfinite_dropped"] = bad
    return cloud


def _unit_normals(n: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N, 3) float32 unit vectors; zero or non-finite rows are left as they are."""
    n = np.asarray(n, dtype=np.float64)
    length = np.sqrt(np.einsum("ij,ij->i", n, n))
    ok = np.isfinite(length) & (length > 0)
    out = n.copy()
    out[ok] /= length[ok, None]
    return out.astype(np.float32)


def _looks_like_normals(n: np.ndarray) -> bool:
    """Whether positional columns 4-6 hold normals (unit or zero vectors) rather than, say, RGB values."""
    n = np.asarray(n, dtype=np.float64)
    if len(n) == 0:
        return True
    length = np.sqrt(np.einsum("ij,ij->i", n, n))
    ok = (np.abs(length - 1.0) < 0.1) | (length == 0)
    return bool(np.mean(ok) >= 0.99)


def _columns_are_normals(p: Path, data: np.ndarray) -> bool:
    """Decide once per file whether columns 4-6 of a (N, k >= 6) table are normals; warn when they are not.

    Judged on at most ~100k evenly spaced rows, so chunks of one file are all read the same way.
    """
    if data.shape[1] < 6:
        return False
    step = max(1, len(data) // 100_000)
    if _looks_like_normals(data[::step, 3:6]):
        return True
    warnings.warn(f"{p}: columns 4-6 are not unit vectors, so they are not read as normals "
                  f"(kept as attributes['extra_columns'])", UserWarning, stacklevel=5)
    return False


def _columns_cloud(p: Path, data: np.ndarray, source: str, *, pts: bool = False,
                   normals: bool | None = None) -> PointCloud:
    """Cloud from a (N, k >= 3) numeric table: x y z, then normals (or extra columns).

    ``normals`` says whether columns 4-6 are normals (None: decide from ``data``).
    """
    xyz = np.array(data[:, :3], dtype=np.float64)
    attrs: dict = {}
    k = data.shape[1]
    if pts:
        # Leica PTS: x y z intensity [r g b]
        if k >= 4:
            attrs["intensity"] = np.asarray(data[:, 3], dtype=np.float32)
        if k >= 7:
            attrs["rgb"] = np.asarray(data[:, 4:7], dtype=np.float32)
        return PointCloud(xyz, attributes=attrs, source=source)
    if normals is None:
        normals = _columns_are_normals(p, data)
    unit = None
    if normals:
        unit = _unit_normals(data[:, 3:6])
        if k > 6:
            attrs["extra_columns"] = np.array(data[:, 6:], dtype=np.float64)
    elif k > 3:
        attrs["extra_columns"] = np.array(data[:, 3:], dtype=np.float64)
    return PointCloud(xyz, normals=unit, attributes=attrs, source=source)


# ------------------------------------------------------------------------------------------------------------
# duplicates and degeneracy


_K1, _K2, _K3 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xC2B2AE3D27D4EB4F), np.uint64(0x165667B19E3779F9)


def _row_hash(words: np.ndarray) -> np.ndarray:
    """64-bit mix of the three coordinate bit patterns of each row ((N, 3) uint64 -> (N,) uint64)."""
    with np.errstate(over="ignore"):
        h = words[:, 0] * _K1
        h ^= h >> np.uint64(29)
        h ^= words[:, 1]
        h *= _K2
        h ^= h >> np.uint64(32)
        h ^= words[:, 2]
        h *= _K3
        h ^= h >> np.uint64(29)
    return h


def _duplicate_mask(xyz: np.ndarray) -> np.ndarray:
    """(N,) bool: True for every row equal to an earlier row (the first occurrence is kept).

    Sorting 64-bit hashes is several times faster than sorting 24-byte rows (lexsort or np.unique on a void
    view), which matters at 10M points; equal-hash neighbours are then compared exactly, and the rare hash
    collision falls back to an exact lexsort.
    """
    n = len(xyz)
    dup = np.zeros(n, dtype=bool)
    if n < 2:
        return dup
    # + 0.0 turns -0.0 into 0.0 so the bit patterns of equal coordinates agree.
    words = np.ascontiguousarray(xyz + 0.0, dtype=np.float64).view(np.uint64).reshape(n, 3)
    h = _row_hash(words)
    order = np.argsort(h, kind="stable")
    hs = h[order]
    cand = np.flatnonzero(hs[1:] == hs[:-1])
    if len(cand) == 0:
        return dup
    later, earlier = order[cand + 1], order[cand]
    equal = (words[later] == words[earlier]).all(axis=1)
    if not equal.all():
        return _duplicate_mask_exact(words)
    # Stable sort: within a run of equal rows indices ascend, so the run's first row is the first occurrence.
    dup[later] = True
    return dup


def _duplicate_mask_exact(words: np.ndarray) -> np.ndarray:
    n = len(words)
    order = np.lexsort((words[:, 2], words[:, 1], words[:, 0]))  # stable
    sw = words[order]
    same = (sw[1:] == sw[:-1]).all(axis=1)
    dup = np.zeros(n, dtype=bool)
    dup[order[1:][same]] = True
    return dup


def _singular_values(xyz: np.ndarray) -> np.ndarray:
    c = xyz - xyz.mean(axis=0)
    # QR then SVD of the 3x3 R: backward-stable (unlike eigenvalues of c.T @ c, which square the condition
    # number and cannot resolve a 1e-9 ratio), and cheap for tall (N, 3) arrays.
    r = np.linalg.qr(c, mode="r")
    return np.linalg.svd(r, compute_uv=False)


def _degeneracy(xyz: np.ndarray, reject_planar: bool) -> str | None:
    """'identical', 'collinear', 'coplanar' (only if reject_planar) or None."""

    def classify(pts):
        s = _singular_values(pts)
        scale = max(float(np.abs(pts).max()), np.finfo(np.float64).tiny)
        # identical up to the rounding of coordinates this large: a few units in the last place, not a fixed
        # fraction (1e-12 of 1e12 is a metre: a 1 m object there was called a single point)
        if s[0] <= _IDENTICAL_ULPS * np.finfo(np.float64).eps * scale * np.sqrt(len(pts)):
            return "identical"
        if s[1] <= _DEGENERATE_RTOL * s[0]:
            return "collinear"
        if reject_planar and s[2] <= _DEGENERATE_RTOL * s[0]:
            return "coplanar"
        return None

    n = len(xyz)
    if n > _DEGENERATE_SAMPLE:
        sample = xyz[np.linspace(0, n - 1, _DEGENERATE_SAMPLE).astype(np.int64)]
        if classify(sample) is None:
            return None
    return classify(xyz)


# ------------------------------------------------------------------------------------------------------------
# PLY


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_MAX_HEADER = 1 << 20


@dataclass
class _PlyProp:
    name: str
    type: str                    # numpy code of the value (item type for lists)
    list_count: str | None = None  # numpy code of the list length, None for scalars


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list = field(default_factory=list)

    @property
    def scalar(self) -> bool:
        return all(p.list_count is None for p in self.props)


@dataclass
class _PlyHeader:
    fmt: str
    elements: list
    comments: list
    data_offset: int

    @property
    def byte_order(self) -> str:
        return ">" if self.fmt == "binary_big_endian" else "<"


def _ply_header(p: Path) -> _PlyHeader:
    """Parse the PLY header ourselves: cheap for point_count, and it lets us size-check before reading."""
    with open(p, "rb") as fh:
        if fh.readline(16).rstrip(b"\r\n") != b"ply":
            raise InputError(f"{p}: not a PLY file (missing 'ply' magic line)")
        fmt = None
        elements: list[_PlyElement] = []
        comments: list[str] = []
        lineno = 1
        while True:
            raw = fh.readline(8192)
            lineno += 1
            if not raw:
                raise InputError(f"{p}: truncated PLY header (no end_header line)")
            if fh.tell() > _PLY_MAX_HEADER:
                raise InputError(f"{p}: corrupted PLY header (no end_header in the first 1 MB)")
            line = raw.decode("ascii", "replace").strip()
            parts = line.split()
            if not parts:
                continue
            key = parts[0]
            if key == "end_header":
                break
            if key in ("comment", "obj_info"):
                if key == "comment":
                    comments.append(line[len(key):].strip())
                continue
            bad = InputError(f"{p}: corrupted PLY header (line {lineno}: '{line[:60]}')")
            if key == "format":
                if len(parts) != 3 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                    raise bad
                fmt = parts[1]
            elif key == "element":
                if len(parts) != 3 or not parts[2].isdigit():
                    raise bad
                elements.append(_PlyElement(parts[1], int(parts[2])))
            elif key == "property":
                if not elements:
                    raise bad
                if len(parts) == 5 and parts[1] == "list":
                    if parts[2] not in _PLY_TYPES or parts[3] not in _PLY_TYPES:
                        raise bad
                    elements[-1].props.append(_PlyProp(parts[4], _PLY_TYPES[parts[3]], _PLY_TYPES[parts[2]]))
                elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                    elements[-1].props.append(_PlyProp(parts[2], _PLY_TYPES[parts[1]]))
                else:
                    raise bad
            else:
                raise bad
        if fmt is None:
            raise InputError(f"{p}: corrupted PLY header (no format line)")
        return _PlyHeader(fmt, elements, comments, fh.tell())


def _ply_vertex_element(p: Path, hdr: _PlyHeader) -> _PlyElement:
    by_name = {e.name: e for e in hdr.elements}
    vertex = by_name.get("vertex")
    if vertex is None:
        raise InputError(f"{p}: PLY has no vertex element")
    face = by_name.get("face")
    if vertex.count == 0 and face is not None and face.count > 0:
        raise InputError(f"{p}: PLY has {face.count} faces but no vertices")
    return vertex


def _ply_min_bytes(el: _PlyElement, ascii_: bool) -> int:
    """Fewest data bytes one row of ``el`` can take (exact for scalar binary rows)."""
    if ascii_:
        return 2 * max(len(el.props), 1)  # "0 " per value (or an empty line)
    return sum(np.dtype(pr.type).itemsize if pr.list_count is None else np.dtype(pr.list_count).itemsize
               for pr in el.props)


def _read_ply(p: Path) -> PointCloud:
    cols, n = _ply_vertex_columns(p)
    return _ply_cloud(p, cols, slice(0, n), str(p))


def _ply_cloud(p: Path, cols: dict, rows: slice, source: str) -> PointCloud:
    xyz = np.column_stack([np.asarray(cols[a][rows], dtype=np.float64) for a in ("x", "y", "z")])
    if "__offset__" in cols:
        xyz += cols["__offset__"]
    normals = None
    if all(a in cols for a in ("nx", "ny", "nz")):
        normals = _unit_normals(np.column_stack([np.asarray(cols[a][rows], dtype=np.float64)
                                                 for a in ("nx", "ny", "nz")]))
    attrs = {}
    for name in ("intensity", "scalar_intensity"):
        if name in cols:
            attrs["intensity"] = np.asarray(cols[name][rows], dtype=np.float32)
            break
    return PointCloud(xyz, normals=normals, attributes=attrs, source=source)


def _ply_vertex_columns(p: Path) -> tuple[dict, int]:
    """Vertex properties as name -> (N,) array-like (memory-mapped for binary files) and the vertex count."""
    hdr = _ply_header(p)
    vertex = _ply_vertex_element(p, hdr)
    names = [pr.name for pr in vertex.props]
    missing = [a for a in ("x", "y", "z") if a not in names]
    if missing:
        raise InputError(f"{p}: PLY vertex element has no {'/'.join(missing)} property")
    if len(set(names)) != len(names):
        raise InputError(f"{p}: PLY vertex element repeats a property name")
    for pr in vertex.props:
        if pr.name in ("x", "y", "z", "nx", "ny", "nz") and pr.list_count is not None:
            raise InputError(f"{p}: PLY vertex property '{pr.name}' is a list, expected a number")

    # Size check before reading: a corrupted count must not make any reader allocate for it.
    ascii_ = hdr.fmt == "ascii"
    available = p.stat().st_size - hdr.data_offset
    needed = sum(el.count * _ply_min_bytes(el, ascii_) for el in hdr.elements) - (1 if ascii_ else 0)
    if needed > available:
        counts = ", ".join(f"{el.count} {el.name}" for el in hdr.elements)
        raise InputError(f"{p}: truncated PLY file (header declares {counts}, which needs at least {needed} "
                         f"bytes of data, but the file has {max(available, 0)})")

    idx = hdr.elements.index(vertex)
    before = hdr.elements[:idx]
    n = vertex.count
    _warn_undeclared_vertices(p, hdr, vertex, available - needed)
    cols: dict
    if n == 0:
        cols = {a: np.zeros(0) for a in names}
    elif not ascii_ and vertex.scalar and all(el.scalar for el in before):
        # Fast path: the vertex block sits at a computable offset; map it instead of parsing the file
        # (plyfile parses every element, e.g. a 204,800-row range_grid or millions of faces, row by row).
        offset = hdr.data_offset + sum(el.count * _ply_min_bytes(el, False) for el in before)
        dtype = np.dtype([(pr.name, hdr.byte_order + pr.type) for pr in vertex.props])
        data = np.memmap(p, dtype=dtype, mode="r", offset=offset, shape=(n,))
        cols = {a: data[a] for a in names}
    elif ascii_ and vertex.scalar and idx == 0:
        # Fast path: numpy's C parser on the vertex rows only, in float64 (keeps every digit written, even for
        # 'property float' coordinates), instead of plyfile's per-row Python loop.
        with open(p, "rb") as raw:
            raw.seek(hdr.data_offset)
            text = io.TextIOWrapper(raw, encoding="latin-1")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                table = np.loadtxt(text, dtype=np.float64, max_rows=n, ndmin=2, comments=None)
        if table.shape[0] < n:
            raise InputError(f"{p}: truncated PLY file (vertex element has {table.shape[0]} of {n} rows)")
        if table.shape[1] != len(names):
            raise InputError(f"{p}: corrupted PLY file (vertex rows have {table.shape[1]} values, "
                             f"header declares {len(names)})")
        cols = {a: table[:, j] for j, a in enumerate(names)}
    else:
        cols = _ply_vertex_plyfile(p, n)
    from .meshes import ply_offset

    offset = ply_offset(hdr.comments)
    if offset is not None:
        cols["__offset__"] = offset
    return cols, n


def _warn_undeclared_vertices(p: Path, hdr: _PlyHeader, vertex: _PlyElement, spare: int) -> None:
    """Warn when a PLY whose last element is its vertices holds more vertex rows than the header declares
    (readers stop at the declared count: the rest would be dropped without a word).

    ``spare``: bytes past the declared elements. Binary files are judged by those bytes (every element must be
    of fixed size), ASCII files by counting their remaining non-blank lines."""
    if hdr.elements[-1] is not vertex or not all(el.scalar for el in hdr.elements):
        return
    if hdr.fmt != "ascii":
        extra = spare // max(_ply_min_bytes(vertex, False), 1)
    else:
        rows = sum(el.count for el in hdr.elements)
        with open(p, "rb") as fh:
            fh.seek(hdr.data_offset)
            lines = sum(1 for line in fh if line.strip())
        extra = lines - rows
    if extra > 0:
        warnings.warn(f"{p}: the file holds {extra} more vertex rows than its header declares ({vertex.count}): "
                      f"they are not read", stacklevel=2)


def _ply_vertex_plyfile(p: Path, n: int) -> dict:
    from plyfile import PlyData

    with warnings.catch_warnings():
        # plyfile lets numpy warn about empty list rows (e.g. range_grid cells with no point).
        warnings.simplefilter("ignore")
        ply = PlyData.read(str(p))
    data = ply["vertex"].data
    if len(data) != n:
        raise InputError(f"{p}: truncated PLY file (vertex element has {len(data)} of {n} rows)")
    return {a: data[a] for a in data.dtype.names}


# ------------------------------------------------------------------------------------------------------------
# text


_FLOAT_RE = re.compile(r"^[+-]?(nan|inf|infinity|(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?)$", re.IGNORECASE)


def _is_comment(line: str) -> bool:
    s = line.lstrip()
    return not s or s.startswith("#") or s.startswith("//")


def _text_layout(p: Path, suffix: str) -> tuple[int, str | None]:
    """(lines to skip, delimiter): skips a header row of column names or a PTS point-count line."""
    delimiter = "," if suffix == ".csv" else None
    with open(p, "r", encoding="latin-1") as fh:
        for i, line in enumerate(fh):
            if _is_comment(line):
                if i > 10_000:
                    break
                continue
            if delimiter is None and "," in line:
                delimiter = ","
            tokens = [t.strip() for t in (line.split(delimiter) if delimiter else line.split())]
            tokens = [t for t in tokens if t]
            numeric = all(_FLOAT_RE.match(t) for t in tokens)
            if not numeric or (len(tokens) == 1 and tokens[0].isdigit()):
                return i + 1, delimiter  # a header of names, or the point count of a PTS file
            return 0, delimiter
    return 0, delimiter


def _read_text(p: Path, suffix: str) -> PointCloud:
    skip, delimiter = _text_layout(p, suffix)
    with warnings.catch_warnings():
        # numpy warns on a file with no data rows; the empty cloud says it better
        warnings.simplefilter("ignore")
        data = np.loadtxt(p, dtype=np.float64, comments=("#", "//"), delimiter=delimiter, skiprows=skip,
                          ndmin=2, encoding="latin-1")
    if data.shape[0] == 0:
        return PointCloud(np.zeros((0, 3)), source=str(p), report={"points_read": 0})
    if data.shape[1] < 3:
        raise InputError(f"{p}: expected at least 3 numeric columns (x y z), found {data.shape[1]}")
    cloud = _columns_cloud(p, data, str(p), pts=suffix == ".pts")
    cloud.report = {"points_read": len(cloud)}
    return cloud


def _text_count(p: Path, suffix: str) -> int:
    skip, _ = _text_layout(p, suffix)
    count = 0
    # text mode: the same universal-newline line splitting as np.loadtxt
    with open(p, "r", encoding="latin-1") as fh:
        for i, line in enumerate(fh):
            if i < skip:
                continue
            # Same rule as np.loadtxt: a line counts if anything is left before its first comment marker.
            body = line.split("#", 1)[0].split("//", 1)[0]
            if body.strip():
                count += 1
    return count


# ------------------------------------------------------------------------------------------------------------
# NPY


def _npy_check(p: Path, arr: np.ndarray) -> None:
    if arr.dtype.names:
        if not all(a in arr.dtype.names for a in ("x", "y", "z")) or arr.ndim != 1:
            raise InputError(f"{p}: structured NPY array needs fields x, y, z "
                             f"(got {', '.join(arr.dtype.names)})")
        return
    if arr.ndim != 2 or arr.shape[1] < 3 or arr.dtype.kind not in "iuf":
        raise InputError(f"{p}: expected an (N, 3) or (N, 6) numeric array, found shape {arr.shape} "
                         f"dtype {arr.dtype}")


def _npy_cloud(p: Path, arr: np.ndarray, source: str, normals: bool | None = None) -> PointCloud:
    if arr.dtype.names:
        xyz = np.column_stack([np.asarray(arr[a], dtype=np.float64) for a in ("x", "y", "z")])
        normals = None
        if all(a in arr.dtype.names for a in ("nx", "ny", "nz")):
            normals = _unit_normals(np.column_stack([arr[a] for a in ("nx", "ny", "nz")]))
        return PointCloud(xyz, normals=normals, source=source, report={"points_read": len(xyz)})
    cloud = _columns_cloud(p, arr, source, normals=normals)
    cloud.report = {"points_read": len(cloud)}
    return cloud


def _read_npy(p: Path) -> PointCloud:
    # mmap first: the header's shape is checked against the file size before anything is allocated.
    arr = np.load(p, mmap_mode="r", allow_pickle=False)
    _npy_check(p, arr)
    return _npy_cloud(p, np.asarray(arr), str(p))


# ------------------------------------------------------------------------------------------------------------
# LAS / LAZ


def _las_crs(header) -> str | None:
    """WKT from the header if present, else whatever description it has; never raises."""
    try:
        from laspy.vlrs.known import GeoAsciiParamsVlr, WktCoordinateSystemVlr
    except Exception:  # pragma: no cover - laspy layout changed
        return None
    vlrs = list(getattr(header, "vlrs", None) or []) + list(getattr(header, "evlrs", None) or [])
    try:
        for v in vlrs:
            if isinstance(v, WktCoordinateSystemVlr):
                wkt = str(getattr(v, "string", "") or "").strip("\x00 \n")
                if wkt:
                    return wkt
    except Exception:
        pass
    try:
        crs = header.parse_crs()  # GeoTIFF keys -> needs pyproj, which may be absent
        if crs is not None:
            return crs.to_wkt()
    except Exception:
        pass
    try:
        for v in vlrs:
            if isinstance(v, GeoAsciiParamsVlr):
                text = " ".join(s.strip("|\x00 ") for s in v.strings if s and s.strip("|\x00 "))
                if text:
                    return text
    except Exception:
        pass
    return None


def _las_normal_dims(point_format) -> tuple[str, str, str] | None:
    extra = {name.lower(): name for name in point_format.extra_dimension_names}
    for trio in (("normalx", "normaly", "normalz"), ("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z")):
        if all(t in extra for t in trio):
            return tuple(extra[t] for t in trio)
    return None


def _laz_backend():
    """The single-threaded lazrs decoder.

    The parallel one sizes its buffers from the LAZ chunk table, and a corrupted table makes it request tens
    of GB, which aborts the whole process from Rust (no Python exception to catch). The sequential decoder
    only fills the buffer laspy gives it. Tiles and files are already decoded in parallel by the pipeline.
    """
    import laspy

    return laspy.LazBackend.Lazrs


def _las_precheck(p: Path) -> int | None:
    """Check the LAS header's record counts against the file size before laspy sees them.

    laspy loops over the declared number of (E)VLRs without checking for end of file: one flipped byte in the
    count makes it spin for hours on an empty stream. Each VLR header is 54 bytes, each EVLR header 60.

    Returns the number of chunks of a LAZ file's chunk table (None: not LAZ, or no usable table).
    """
    size = p.stat().st_size
    n_chunks = None
    with open(p, "rb") as fh:
        head = fh.read(375)
        if head[:4] == b"LASF" and len(head) >= 227 and head[104] & 0xC0:
            n_chunks = _laz_chunk_table_check(p, fh, int.from_bytes(head[96:100], "little"), size)
    if head[:4] != b"LASF":
        raise InputError(f"{p}: not a LAS/LAZ file (no LASF signature)")
    if len(head) < 227:
        raise InputError(f"{p}: truncated LAS header ({len(head)} bytes)")
    n_vlrs = int.from_bytes(head[100:104], "little")
    if n_vlrs * 54 > size:
        raise InputError(f"{p}: corrupted LAS header (declares {n_vlrs} VLRs in a {size}-byte file)")
    if head[25] >= 4 and len(head) >= 247:
        start_evlr = int.from_bytes(head[235:243], "little")
        n_evlrs = int.from_bytes(head[243:247], "little")
        if n_evlrs and start_evlr + n_evlrs * 60 > size:
            raise InputError(f"{p}: corrupted LAS header (declares {n_evlrs} extended VLRs beyond the end "
                             f"of the {size}-byte file)")
    return n_chunks


def _laszip_items_check(p: Path, header) -> None:
    """Refuse a LAZ whose laszip VLR declares no compressed items (lazrs panics on it, printing a Rust backtrace).

    The VLR's record data holds the item count as a uint16 at byte 32, followed by 6 bytes per item.
    """
    data = _laszip_vlr_data(header)
    if data is None:
        return
    n_items = int.from_bytes(data[32:34], "little") if len(data) >= 34 else 0
    if n_items == 0 or len(data) < 34 + 6 * n_items:
        raise InputError(f"{p}: corrupted LAZ file (the laszip VLR declares {n_items} compressed items "
                         f"in {len(data)} bytes)")


def _laszip_vlr_data(header) -> bytes | None:
    """Record data of the laszip VLR (user "laszip encoded", record 22204), or None when the file has none."""
    for vlr in header.vlrs:
        if vlr.user_id.rstrip("\0") == "laszip encoded" and vlr.record_id == 22204:
            return bytes(getattr(vlr, "record_data", b"") or b"")
    return None


def _laz_chunk_table_check(p: Path, fh, data_start: int, size: int) -> int | None:
    """Refuse a LAZ chunk table whose chunk count cannot fit in the file.

    lazrs reserves memory for the declared number of chunks before reading them; a corrupted count aborts the
    process from Rust. The table is found as lazrs finds it: an int64 offset at the start of the point data,
    or (when a streaming writer could not fill it in) in the last 8 bytes of the file.
    """
    fh.seek(data_start)
    raw = fh.read(8)
    if len(raw) < 8:
        return  # laspy reports the truncation
    table = int.from_bytes(raw, "little", signed=True)
    if table <= data_start and size >= 8:
        fh.seek(size - 8)
        table = int.from_bytes(fh.read(8), "little", signed=True)
    if table <= data_start or table + 8 > size:
        return None  # no usable chunk table: lazrs fails cleanly (or streams without one)
    fh.seek(table)
    n_chunks = int.from_bytes(fh.read(8)[4:8], "little")
    # every chunk holds at least one raw point record (>= 20 bytes) of compressed data
    if n_chunks * 8 > size:
        raise InputError(f"{p}: corrupted LAZ file (chunk table declares {n_chunks} chunks in a "
                         f"{size}-byte file)")
    return n_chunks


def _laszip_chunk_size(header) -> int | None:
    """Points per chunk of a LAZ file written with fixed-size chunks (None: variable chunks, or no laszip VLR).

    The laszip VLR's record data holds it as a uint32 at byte 12; 0xFFFFFFFF marks variable chunks."""
    data = _laszip_vlr_data(header)
    if data is None or len(data) < 16:
        return None
    size = int.from_bytes(data[12:16], "little")
    return None if size in (0, 0xFFFFFFFF) else size


def _warn_undeclared_points(p: Path, header, n_chunks: int | None, size: int) -> None:
    """Warn when a LAS/LAZ file holds more point records than its header declares: readers stop at the declared
    count, so the rest would be dropped without a word (a header written before the writer finished, or a
    32-bit legacy count that wrapped)."""
    total = int(header.point_count)
    if header.are_points_compressed:
        chunk = _laszip_chunk_size(header)
        if chunk is None or n_chunks is None:
            return
        needed = -(-total // chunk)
        if n_chunks > needed:
            warnings.warn(f"{p}: the LAZ chunk table holds {n_chunks} chunks of {chunk} points but the header "
                          f"declares {total} points (at most {needed} chunks): points past the declared count "
                          f"are not read", stacklevel=2)
        return
    record = int(header.point_format.size)
    end = int(header.offset_to_point_data) + total * record
    limit = size
    start_evlr = int(getattr(header, "start_of_first_evlr", 0) or 0)
    if header.version.minor >= 4 and getattr(header, "number_of_evlrs", 0) and start_evlr > 0:
        limit = min(size, start_evlr)
    extra = (limit - end) // record
    if extra > 0:
        warnings.warn(f"{p}: the file holds {extra} more point records than its header declares ({total}): "
                      f"they are not read", stacklevel=2)


def _las_chunks(p: Path, chunk_size: int) -> Iterator[PointCloud]:
    import laspy

    n_chunks = _las_precheck(p)
    sel = laspy.DecompressionSelection
    # LAS 1.4 point formats 6-10 are compressed in layers: skip decoding the fields we do not keep (RGB, GPS
    # time, classification, ...), which makes the decode about 40% faster. Older formats decode everything.
    wanted = sel.XY_RETURNS_CHANNEL | sel.Z | sel.INTENSITY | sel.ALL_EXTRA_BYTES
    with laspy.open(str(p), laz_backend=_laz_backend(), decompression_selection=wanted) as reader:
        header = reader.header
        total = int(header.point_count)
        if not header.are_points_compressed:
            # Uncompressed LAS cut at a record boundary reads "successfully" with fewer points: check size.
            needed = int(header.offset_to_point_data) + total * int(header.point_format.size)
            size = p.stat().st_size
            if size < needed:
                raise InputError(f"{p}: truncated LAS file (header declares {total} points, which needs "
                                 f"{needed} bytes, but the file has {size})")
        if header.are_points_compressed:
            _laszip_items_check(p, header)
        _warn_undeclared_points(p, header, n_chunks, p.stat().st_size)
        crs = _las_crs(header)
        normal_dims = _las_normal_dims(header.point_format)
        has_intensity = "intensity" in header.point_format.dimension_names
        done = 0
        for chunk in reader.chunk_iterator(chunk_size):
            n = len(chunk)
            if n == 0:
                break
            xyz = np.empty((n, 3), dtype=np.float64)
            xyz[:, 0] = chunk.x
            xyz[:, 1] = chunk.y
            xyz[:, 2] = chunk.z
            normals = None
            if normal_dims is not None:
                normals = _unit_normals(np.column_stack([np.asarray(chunk[d], dtype=np.float64)
                                                         for d in normal_dims]))
            attrs = {"intensity": np.array(chunk.intensity)} if has_intensity else {}
            yield PointCloud(xyz, normals=normals, attributes=attrs, crs=crs,
                             source=f"{p}[{done}:{done + n}]", report={"points_read": n})
            done += n
        if done != total:
            kind = "LAZ" if header.are_points_compressed else "LAS"
            raise InputError(f"{p}: truncated or corrupted {kind} file (read {done} of {total} points)")


# ------------------------------------------------------------------------------------------------------------
# KITTI


def _kitti_scan_size(p: Path) -> int:
    size = p.stat().st_size
    if size % 16:
        raise InputError(f"{p}: corrupted KITTI scan (size {size} bytes is not a multiple of 16 = 4 float32 "
                         f"values per point)")
    return size


def _load_kitti_scan(p: Path) -> np.ndarray:
    """(N, 4) float32: x y z reflectance, metres in the sensor frame."""
    _kitti_scan_size(p)
    return np.fromfile(p, dtype="<f4").reshape(-1, 4)


def _read_kitti_scan(p: Path) -> PointCloud:
    scan = _load_kitti_scan(p)
    xyz = scan[:, :3].astype(np.float64)
    return PointCloud(xyz, sensor=np.zeros_like(xyz), attributes={"intensity": scan[:, 3].copy()},
                      source=str(p), report={"points_read": len(xyz)})


def _kitti_layout(root: Path) -> tuple[Path, dict[int, Path]]:
    scans = root / "velodyne" if (root / "velodyne").is_dir() else root
    files = {int(f.stem): f for f in scans.iterdir()
             if f.suffix.lower() == ".bin" and f.stem.isdigit() and f.is_file()}
    if not files:
        raise InputError(f"{root}: not a KITTI sequence (no velodyne/NNNNNN.bin or NNNNNN.bin scans)")
    return scans, files


def kitti_sequence_files(root: str | os.PathLike) -> list[Path]:
    """The files a KITTI sequence's reader reads: its scans (ordered by frame), ``poses.txt`` and ``calib.txt``
    where present; nothing else in the directory (an output or job directory written inside it is not part of
    the input)."""
    root = Path(root)
    _, files = _kitti_layout(root)
    side = [root / name for name in ("poses.txt", "calib.txt") if (root / name).is_file()]
    return [files[k] for k in sorted(files)] + side


def _read_matrix_lines(p: Path) -> np.ndarray:
    """poses.txt -> (n, 12) float64, one row per line; any malformed line is an error naming it."""
    rows = []
    text = p.read_text(encoding="latin-1").rstrip()
    for lineno, line in enumerate(text.splitlines() if text else [], start=1):
        rows.append(_twelve_numbers(line.split(), p, lineno))
    return np.array(rows, dtype=np.float64).reshape(-1, 12)


def _twelve_numbers(tokens: list[str], p: Path, lineno: int) -> list[float]:
    if len(tokens) != 12:
        raise InputError(f"{p}: line {lineno}: expected 12 numbers, found {len(tokens)}")
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        raise InputError(f"{p}: line {lineno}: not a number in '{' '.join(tokens)[:60]}'") from None
    if not all(np.isfinite(values)):
        raise InputError(f"{p}: line {lineno}: non-finite value")
    return values


def _read_calib(p: Path) -> np.ndarray:
    """Tr (velodyne -> camera 0) as 4x4 from calib.txt."""
    for lineno, line in enumerate(p.read_text(encoding="latin-1").splitlines(), start=1):
        key, sep, rest = line.partition(":")
        if sep and key.strip() in ("Tr", "Tr_velo_to_cam"):
            return _to4x4(np.array(_twelve_numbers(rest.split(), p, lineno)))
    raise InputError(f"{p}: no 'Tr:' line (the velodyne-to-camera transform)")


def _to4x4(row: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :] = row.reshape(3, 4)
    return m


def _frame_list(frames, root: Path, last: int) -> list[int] | None:
    """The frame numbers selected by ``frames``; ``last``: the highest frame number present in ``root``."""
    if frames is None:
        return None
    if isinstance(frames, tuple) and len(frames) == 2:
        start, stop = frames
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (start, stop)):
            raise ConfigError(f"{root}: frames=(start, stop) must be two integers, got {frames!r}")
        if 0 <= start < stop and stop - 1 > last:
            # refused before range() is listed: --frames 0:1000000000 must not build a billion-entry list
            raise InputError(f"{root}: frames {start}:{stop} requested but the sequence ends at frame {last}")
        wanted = list(range(int(start), int(stop)))
    else:
        try:
            wanted = [int(f) for f in frames]
        except (TypeError, ValueError):
            raise ConfigError(f"{root}: frames must be (start, stop) or an iterable of frame numbers, "
                              f"got {frames!r}") from None
    if not wanted:
        raise ConfigError(f"{root}: frames={frames!r} selects no frames")
    if min(wanted) < 0:
        raise ConfigError(f"{root}: frame numbers must be >= 0, got {min(wanted)}")
    if len(set(wanted)) != len(wanted):
        raise ConfigError(f"{root}: frames={frames!r} repeats a frame")
    return wanted


def _kitti_frames(root: Path, frames) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """Yield (frame, (n, 3) float64 world xyz, (3,) float64 sensor origin, (n,) float32 reflectance).

    Everything that can be checked without reading scans (frame files, poses, calib) is checked before the
    first frame is yielded.
    """
    scans, files = _kitti_layout(root)
    wanted = _frame_list(frames, root, max(files))
    width = min(len(f.stem) for f in files.values())
    if wanted is None:
        last = max(files)
        if len(files) != last + 1:
            # found without listing range(last + 1): a stray 999999999.bin must not build a huge list
            present = sorted(files)
            first = next((i for i, f in enumerate(present) if i != f), len(present))
            raise InputError(f"{root}: missing frame {first:0{width}d}.bin and {last - len(files)} more "
                             f"(frames 0..{last} expected)" if last - len(files) else
                             f"{root}: missing frame {first:0{width}d}.bin (frames 0..{last} expected)")
        wanted = list(range(last + 1))
    missing = [i for i in wanted if i not in files]
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise InputError(f"{root}: missing frame {missing[0]:0{width}d}.bin{more} (frames {min(wanted)}.."
                         f"{max(wanted)} requested)")
    poses_path = root / "poses.txt"
    if not poses_path.is_file():
        raise InputError(f"{root}: KITTI sequence has no poses.txt")
    with _input_errors(poses_path, ".txt"):
        poses = _read_matrix_lines(poses_path)
    if frames is None and len(poses) != len(wanted):
        raise InputError(f"{root}: poses.txt has {len(poses)} poses but {len(wanted)} frames")
    if max(wanted) >= len(poses):
        raise InputError(f"{root}: poses.txt has {len(poses)} poses but frame {max(wanted):0{width}d} "
                         f"was requested")
    calib_path = root / "calib.txt"
    tr = np.eye(4)
    if calib_path.is_file():
        with _input_errors(calib_path, ".txt"):
            tr = _read_calib(calib_path)
    for i in wanted:
        f = files[i]
        with _input_errors(f, ".bin"):
            scan = _load_kitti_scan(f)
        t = _to4x4(poses[i]) @ tr
        xyz = scan[:, :3].astype(np.float64) @ t[:3, :3].T + t[:3, 3]
        yield i, xyz, t[:3, 3].copy(), scan[:, 3].copy()


def _kitti_chunks(root: Path, frames, chunk_size: int) -> Iterator[PointCloud]:
    for i, xyz, origin, refl in _kitti_frames(root, frames):
        cloud = PointCloud(xyz, sensor=np.broadcast_to(origin, xyz.shape).copy(),
                           attributes={"frame": np.full(len(xyz), i, dtype=np.int32), "intensity": refl})
        yield from _slices(cloud, chunk_size, f"{root}/frame{i}")
