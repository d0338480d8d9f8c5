"""Writers for simulated scans: LAS/LAZ point files and KITTI odometry sequences."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.atomic import atomic_open, atomic_path
from .lidar import Scan

__all__ = ["write_las", "write_trajectory", "write_kitti_sequence", "KITTI_TR"]

# KITTI odometry sequence 00 velodyne -> camera-0 calibration (rows of the 3x4 [R|t]). Its rotation maps the
# velodyne axes (x forward, y left, z up) to the camera axes (x right, y down, z forward), up to ~0.5 degree.
KITTI_TR = np.array([
    [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
    [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
    [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
])
_KITTI_P = np.array([7.188560000000e+02, 0.0, 6.071928000000e+02, 0.0,
                     0.0, 7.188560000000e+02, 1.852157000000e+02, 0.0,
                     0.0, 0.0, 1.0, 0.0])


def write_las(path: str | Path, xyz: np.ndarray, *, intensity: np.ndarray | None = None,
              crs_wkt: str | None = None, gps_time: np.ndarray | None = None, chunk_size: int = 2_000_000) -> Path:
    """Write points as LAS 1.4 (point format 6), LAZ-compressed when the suffix is ``.laz``, atomically.

    Coordinates are stored with scale 0.001 (millimetres) and offset ``floor(min)``, so float64 inputs at
    UTM magnitudes round-trip to within 0.5 mm.

    Parameters
    ----------
    path : str or Path
        ``.las`` or ``.laz``.
    xyz : (N, 3) float64
        World coordinates (m).
    intensity : (N,) array_like, optional
        Stored as uint16 (clipped to 0..65535).
    crs_wkt : str, optional
        OGC WKT of the coordinate system, stored in a WKT VLR (global encoding WKT bit set).
    gps_time : (N,) float64, optional
        Each point's GPS time (s).
    chunk_size : int
        Points per write (bounds memory for large clouds).

    Returns
    -------
    Path
    """
    import laspy
    from laspy.vlrs.known import WktCoordinateSystemVlr

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".las", ".laz"):
        raise InputError(f"{path}: point cloud output must be .las or .laz")
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(xyz)):
        raise InputError(f"{path}: cannot write non-finite coordinates")
    if intensity is not None:
        intensity = np.clip(np.asarray(intensity).reshape(-1), 0, 65535).astype(np.uint16)
        if len(intensity) != len(xyz):
            raise ValueError("intensity must have one value per point")
    if gps_time is not None:
        gps_time = np.asarray(gps_time, dtype=np.float64).reshape(-1)
        if len(gps_time) != len(xyz):
            raise ValueError("gps_time must have one value per point")
    offset = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    if len(xyz) and np.any((xyz.max(axis=0) - offset) / 0.001 >= 2 ** 31 - 1):
        raise InputError(f"{path}: extent too large for millimetre LAS integers")
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = offset
    header.generating_software = "tiled_gridpull.synthetic"
    if crs_wkt:
        header.global_encoding.wkt = True
        header.vlrs.append(WktCoordinateSystemVlr(crs_wkt))
    compress = suffix == ".laz"
    # the temporary name hides the suffix from laspy, so compression is asked for explicitly
    with atomic_path(path) as tmp:
        with laspy.open(tmp, mode="w", header=header, do_compress=compress,
                        laz_backend=laspy.LazBackend.Lazrs if compress else None) as writer:
            for s in range(0, len(xyz), int(chunk_size)):
                part = xyz[s:s + int(chunk_size)]
                rec = laspy.ScaleAwarePointRecord.zeros(len(part), header=header)
                rec.x = part[:, 0]
                rec.y = part[:, 1]
                rec.z = part[:, 2]
                if intensity is not None:
                    rec.intensity = intensity[s:s + int(chunk_size)]
                if gps_time is not None:
                    rec.gps_time = gps_time[s:s + int(chunk_size)]
                writer.write_points(rec)
    return path


def write_trajectory(path: str | Path, time: np.ndarray, positions: np.ndarray) -> Path:
    """Write a sensor trajectory as CSV (``time,x,y,z`` header, then one sample per line, full precision),
    the text form :func:`tiled_gridpull.trajectory.read_trajectory` reads."""
    rows = np.column_stack([np.asarray(time, np.float64), np.asarray(positions, np.float64).reshape(-1, 3)])
    with atomic_path(Path(path)) as tmp, open(tmp, "w") as fh:
        fh.write("time,x,y,z\n")
        for r in rows:
            fh.write(",".join(repr(float(v)) for v in r) + "\n")
    return Path(path)


def write_kitti_sequence(root: str | Path, scan: Scan) -> Path:
    """Write a scan as a KITTI odometry sequence, every file atomically.

    Layout: ``root/velodyne/000000.bin ...`` (float32 ``x y z reflectance`` in the sensor frame),
    ``root/poses.txt`` (per frame the 12 numbers of the top 3x4 of the camera-0 pose, ``%.9e``),
    ``root/calib.txt`` (``P0``..``P3`` and ``Tr``: velodyne -> camera 0, :data:`KITTI_TR`) and
    ``root/times.txt`` (10 Hz). KITTI's convention holds: ``world = pose_i @ Tr @ [p_velo; 1]``.

    KITTI poses live in a local frame, so the poses are written relative to ``scan.origin``: the world
    coordinates a reader reconstructs (adding no origin of its own) are ``scan.xyz - scan.origin``.

    Returns
    -------
    Path
        ``root``.
    """
    root = Path(root)
    tr = np.vstack([KITTI_TR, [0.0, 0.0, 0.0, 1.0]])
    local = scan.poses.copy()
    local[:, :3, 3] -= scan.origin
    # pose_cam = pose_velo @ Tr^-1, so pose_cam @ Tr = pose_velo (KITTI_TR is exactly what calib.txt holds)
    cam = local @ np.linalg.inv(tr)
    (root / "velodyne").mkdir(parents=True, exist_ok=True)
    for i in range(scan.n_frames):
        sl = scan.frame_slice(i)
        pts = np.empty((sl.stop - sl.start, 4), np.float32)
        pts[:, :3] = scan.frame_points(i)
        pts[:, 3] = scan.reflectance[sl]
        with atomic_open(root / "velodyne" / f"{i:06d}.bin", "wb") as fh:
            fh.write(pts.tobytes())
    with atomic_open(root / "poses.txt", "w") as fh:
        np.savetxt(fh, cam[:, :3, :].reshape(-1, 12), fmt="%.9e")
    with atomic_open(root / "calib.txt", "w") as fh:
        for k in range(4):
            p = _KITTI_P.copy()
            p[3] = -386.1448 * k if k else 0.0  # stereo baselines, as in the real files; unused here
            fh.write(f"P{k}: " + " ".join(f"{x:.12e}" for x in p) + "\n")
        fh.write("Tr: " + " ".join(f"{x:.12e}" for x in KITTI_TR.ravel()) + "\n")
    with atomic_open(root / "times.txt", "w") as fh:
        np.savetxt(fh, 0.1 * np.arange(scan.n_frames), fmt="%.6e")
    return root
