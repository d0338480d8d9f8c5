"""One call from nothing to a sample on disk: build, scan and write a street or a grid of streets."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .._optional import require
from ..io.atomic import write_json
from ..io.meshes import write_mesh
from .lidar import SENSOR_HEIGHT_M, grid_passes, scan_street, street_length_for_frames
from .lidar_files import write_kitti_sequence, write_las, write_trajectory
from .street import GRID_STREETS, LAYOUTS, StreetScene, build_street

__all__ = ["make_street_sample", "grid_frames_for_points"]

_FORMATS = ("laz", "las", "kitti", "copc", "ept")


#: GPS time of the first frame (s; GPS week seconds, a Tuesday morning) and between frames (a 10 Hz sensor)
GPS_TIME_START_S = 200_000.0
FRAME_PERIOD_S = 0.1


def grid_frames_for_points(n_points: int, n_passes: int = 2 * GRID_STREETS) -> int:
    """Frames :func:`make_street_sample` uses for a grid sample of about ``n_points`` points.

    Up to 100 000 points a frame (as for the single street) with at least one frame per pass; below ~10 M
    points, more frames of fewer azimuths (~15 000 points a frame, at most 16 frames per pass, 12.5 m apart
    on the default 200 m streets): at a fixed point count, spreading the viewpoints covers more of the
    district (measured at 1 M points: 44 % of the ground truth within 0.5 m of a point with 16 frames per
    pass, 40 % with 7, 34 % with 4; roofs, courtyards and building backs are never seen).

    Returns
    -------
    int
        A multiple of ``n_passes``, so every pass gets the same number of frames.
    """
    n = int(n_points)
    per_pass = max(math.ceil(n / (n_passes * 100_000)), min(16, math.ceil(n / (n_passes * 15_000))), 1)
    return n_passes * per_pass


def make_street_sample(out_dir: str | Path, n_points: int = 100_000, seed: int = 0,
                       origin: tuple[float, float, float] = (0.0, 0.0, 0.0), formats=("laz",), *,
                       range_noise: float = 0.0, crs_wkt: str | None = None, layout: str = "street",
                       extent_m: float = 200.0, frames: int | None = None, beam_bias_deg: float = 0.0) -> dict:
    """Build, scan and write a street (or a grid of streets) sized for about ``n_points`` points.

    Single street: the scene gets ``max(4, ceil(n_points / 100 000))`` frames 1 m apart and 40 m of street
    beyond each end. Grid: an ``extent_m`` square with :func:`grid_frames_for_points` frames spread evenly
    over one pass per street. In both, the azimuth resolution is then chosen from a coarse probe scan of the
    same poses so the count lands within a few percent of ``n_points`` (full HDL-64E resolution, 2000
    azimuths, from ~400 k points up for the street and ~15 M for the grid).

    Parameters
    ----------
    out_dir : str or Path
    n_points : int
    seed : int
        Scene seed (also seeds the range noise).
    origin : (3,) float
        Scene origin added to every output coordinate.
    formats : sequence of {"laz", "las", "kitti", "copc", "ept"}
        ``street.laz`` / ``street.las`` (intensity = reflectance x 65535, GPS time of the point's frame) with
        ``street_trajectory.csv`` (time, x, y, z of the sensor at every frame), and/or a ``kitti/`` sequence.
    range_noise : float
        Gaussian range noise (m).
    beam_bias_deg : float
        Standard deviation of each beam's fixed elevation error (degrees; :func:`scan_street`): the rings sit
        a few centimetres off the ground, each its own way, as on a real multi-beam sensor.
    crs_wkt : str, optional
        Written into the LAS/LAZ header.
    layout : {"street", "grid"}
        See :class:`StreetScene`.
    extent_m : float
        Side of the grid's square (m); unused by the single street.
    frames : int, optional
        Single street: this many frames 1 m apart (a 10 Hz scanner on a car at 36 km/h), the street long enough
        for them; the points are shared among them. Default: ``max(4, ceil(n_points / 100 000))``.

    Returns
    -------
    dict
        ``points`` (the first LAS/LAZ written, else None), ``laz`` / ``las`` / ``kitti`` / ``copc`` / ``ept``
        (its ``ept.json``) / ``trajectory`` paths
        when written,
        ``gt_mesh`` (``street_gt.ply``, float64 vertices), ``meta`` (``street.json``), ``n_points``,
        ``n_frames``, ``azimuth_steps``, ``n_faces``, ``scene``, ``layout``, ``n_passes``.
    """
    formats = tuple(formats)
    bad = [f for f in formats if f not in _FORMATS]
    if bad:
        raise ValueError(f"unknown formats {bad}; choose from {_FORMATS}")
    if int(n_points) < 1:
        raise ValueError("n_points must be >= 1")
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    if "copc" in formats:
        # the one format with an optional writer: refused now, not after the other files are written
        require("copclib", "writing COPC files")
    out_dir = Path(out_dir)
    if layout == "grid":
        scene = StreetScene(seed=seed, origin=tuple(origin), layout="grid", extent_m=extent_m)
        n_passes = len(grid_passes(scene))
        n_frames = grid_frames_for_points(n_points, n_passes)
    else:
        n_passes = 1
        n_frames = max(4, int(math.ceil(int(n_points) / 100_000))) if frames is None else int(frames)
        if n_frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames!r}")
        scene = StreetScene(seed=seed, length_m=street_length_for_frames(n_frames), origin=tuple(origin))
    out_dir.mkdir(parents=True, exist_ok=True)
    mesh = build_street(scene)
    probe_steps = 200
    probe = scan_street(scene, mesh, n_frames, azimuth_steps=probe_steps)
    azimuth_steps = int(np.clip(round(probe_steps * int(n_points) / max(probe.n_points, 1)), 16, 4000))
    del probe  # freed before the full-resolution cast, which is what sets the peak memory
    scan = scan_street(scene, mesh, n_frames, azimuth_steps=azimuth_steps, range_noise=range_noise, seed=seed,
                       beam_bias_deg=beam_bias_deg)
    result: dict = {"points": None}
    # a mapping car's record: GPS time per point (one per frame: the simulated sensor moves between sweeps, not
    # during one) and the trajectory beside the points, as mobile-mapping deliveries come
    frame_time = GPS_TIME_START_S + FRAME_PERIOD_S * np.arange(scan.n_frames)
    for fmt in ("laz", "las"):
        if fmt in formats:
            p = write_las(out_dir / f"street.{fmt}", scan.xyz,
                          intensity=np.round(scan.reflectance * 65535.0), crs_wkt=crs_wkt,
                          gps_time=frame_time[scan.frame])
            result[fmt] = p
            result["points"] = result["points"] or p
    if result["points"] is not None:
        result["trajectory"] = write_trajectory(out_dir / "street_trajectory.csv", frame_time,
                                                scan.poses[:, :3, 3])
    if "kitti" in formats:
        result["kitti"] = write_kitti_sequence(out_dir / "kitti", scan)
    # the cloud-optimized forms surveys are published in: street.copc.laz (copclib) and street_ept/ept.json
    if "copc" in formats:
        from ..io.indexed_write import write_copc

        result["copc"] = write_copc(out_dir / "street.copc.laz", scan.xyz, wkt=crs_wkt,
                                    gps_time=frame_time[scan.frame])
    if "ept" in formats:
        from ..io.indexed_write import write_ept

        result["ept"] = write_ept(out_dir / "street_ept", scan.xyz, wkt=crs_wkt)
    result["gt_mesh"] = write_mesh(mesh, out_dir / "street_gt.ply")
    result.update(n_points=scan.n_points, n_frames=scan.n_frames, azimuth_steps=azimuth_steps,
                  n_faces=mesh.n_faces, scene=scene.to_dict(), range_noise=float(range_noise),
                  beam_bias_deg=float(beam_bias_deg), layout=scene.layout, n_passes=n_passes)
    meta = {k: (str(v) if isinstance(v, Path) else v) for k, v in result.items()}
    meta["face_classes"] = mesh.metadata["face_classes"]
    meta["sensor_height_m"] = SENSOR_HEIGHT_M
    result["meta"] = out_dir / "street.json"
    write_json(result["meta"], meta)
    return result
