"""KITTI odometry data: single Velodyne scans (``.bin``, float32 x y z reflectance) and whole sequences (a
directory of scans with ``poses.txt`` and ``calib.txt``) merged into one world-frame cloud."""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from ..cloud import PointCloud, cloud_slices
from ..errors import ConfigError, InputError
from .input_errors import check_path, input_errors

__all__ = ["read", "count", "read_kitti_sequence", "kitti_sequence_files", "kitti_chunks",
           "kitti_sequence_count"]


def read(p: Path) -> PointCloud:
    """One scan in the sensor frame (metres); ``sensor`` is the origin for every point."""
    return _read_kitti_scan(p)


def count(p: Path) -> int:
    """Points of one scan, from its file size."""
    return _kitti_scan_size(p) // 16


def kitti_sequence_count(root: Path) -> int:
    """Points of every scan of a sequence, from the file sizes."""
    _, files = _kitti_layout(root)
    return sum(_kitti_scan_size(f) // 16 for f in files.values())


def read_kitti_sequence(root: str | os.PathLike,
                        frames: tuple[int, int] | Iterable[int] | None = None) -> PointCloud:
    """Read a KITTI odometry sequence and merge its scans into one world-frame cloud.

    Layout: ``root/velodyne/NNNNNN.bin`` (or ``root/NNNNNN.bin``), one float32 ``x y z reflectance`` scan per
    frame in metres in the Velodyne frame; ``root/poses.txt`` with one line per frame (12 numbers: the 3x4
    camera-0 pose, row-major; line i is frame i); ``root/calib.txt`` with a ``Tr:`` line (the 3x4
    Velodyne-to-camera-0 transform). Without calib.txt the sequence is refused: the poses are in the camera frame,
    and an identity Tr would merge the scans turned and shifted without a word. Poses already in the Velodyne
    frame are given with a calib.txt whose line is ``Tr: 1 0 0 0 0 1 0 0 0 0 1 0``.

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
        Not a KITTI sequence, a missing frame file, a poses.txt that does not cover the frames, no calib.txt,
        a malformed poses or calib line, a corrupted scan.
    ConfigError
        ``frames`` is empty, negative or repeats a frame.
    """
    root = check_path(root)
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


#: Largest deviation of Tr's 3x3 part from an orthonormal matrix (``max |R^T R - I|``): KITTI's Tr is a rigid
#: transform, given to about 1e-9; a scaled or rank-deficient one would distort every scan without a word.
RIGID_TOLERANCE = 1e-3


def _read_calib(p: Path) -> np.ndarray:
    """Tr (velodyne -> camera 0) as 4x4 from calib.txt.

    Raises
    ------
    InputError
        No Tr line, a malformed one, or a Tr that is not rigid (its rotation part not orthonormal within
        :data:`RIGID_TOLERANCE`, or a reflection).
    """
    for lineno, line in enumerate(p.read_text(encoding="latin-1").splitlines(), start=1):
        key, sep, rest = line.partition(":")
        if sep and key.strip() in ("Tr", "Tr_velo_to_cam"):
            tr = _to4x4(np.array(_twelve_numbers(rest.split(), p, lineno)))
            rot = tr[:3, :3]
            with np.errstate(over="ignore", invalid="ignore"):  # 1e200 entries: inf, refused below
                err = float(np.abs(rot.T @ rot - np.eye(3)).max())
                det = float(np.linalg.det(rot))
            if not (err <= RIGID_TOLERANCE and det > 0):  # NaN fails too
                raise InputError(f"{p}: line {lineno}: {key.strip()} is not a rigid transform (its 3x3 part is "
                                 f"not a rotation: |R^T R - I| = {err:.3g}, det {det:.3g}); "
                                 "KITTI's Tr places the velodyne in the camera frame by a rotation and a shift")
            return tr
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
    with input_errors(poses_path, "text"):
        poses = _read_matrix_lines(poses_path)
    if frames is None and len(poses) != len(wanted):
        raise InputError(f"{root}: poses.txt has {len(poses)} poses but {len(wanted)} frames")
    if max(wanted) >= len(poses):
        raise InputError(f"{root}: poses.txt has {len(poses)} poses but frame {max(wanted):0{width}d} "
                         f"was requested")
    calib_path = root / "calib.txt"
    if not calib_path.is_file():
        # the poses place camera 0, not the scanner: with an identity Tr every scan would be merged turned by
        # 90 degrees about two axes and shifted, silently; a user whose poses are in the velodyne frame says so
        raise InputError(f"{root}: KITTI sequence has no calib.txt (poses.txt gives camera-0 poses; its 'Tr:' "
                         "line places the velodyne in that frame): copy the sequence's calib.txt from the KITTI "
                         "odometry calibration, or, if the poses are already in the velodyne frame, write one "
                         "with the line 'Tr: 1 0 0 0 0 1 0 0 0 0 1 0'")
    with input_errors(calib_path, "text"):
        tr = _read_calib(calib_path)
    for i in wanted:
        f = files[i]
        with input_errors(f, "KITTI scan"):
            scan = _load_kitti_scan(f)
        t = _to4x4(poses[i]) @ tr
        xyz = scan[:, :3].astype(np.float64) @ t[:3, :3].T + t[:3, 3]
        yield i, xyz, t[:3, 3].copy(), scan[:, 3].copy()


def kitti_chunks(root: Path, frames, chunk_size: int) -> Iterator[PointCloud]:
    """The frames of a sequence in world coordinates, each cut into slices of ``chunk_size`` points."""
    for i, xyz, origin, refl in _kitti_frames(root, frames):
        cloud = PointCloud(xyz, sensor=np.broadcast_to(origin, xyz.shape).copy(),
                           attributes={"frame": np.full(len(xyz), i, dtype=np.int32), "intensity": refl})
        yield from cloud_slices(cloud, chunk_size, f"{root}/frame{i}")
