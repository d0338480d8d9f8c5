"""A simulated 64-beam spinning LiDAR driving through a synthetic street: trajectory, ray casting, scans.

The scan (:func:`scan_street`) casts the rays of an HDL-64E-like sensor (64 beams from +2 to -24.8 degrees
elevation, ``azimuth_steps`` azimuths per revolution) from poses driving along the centre line at
``SENSOR_HEIGHT_M`` above the terrain, with a small heading and lateral wobble. Rays are intersected exactly
(Moller-Trumbore in float64) with the mesh triangles, so noise-free points lie on the ground truth to
~1e-12 m. With the defaults a frame of the default 100 m street gives about ``POINTS_PER_FRAME_DEFAULT``
points (~99 % of the 128 000 rays hit something); :func:`frames_for_points` measures it for any scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from ..mesh import Mesh
from .street import StreetScene, build_street, grid_street_lines, scene_rng, street_to_local, terrain_height

__all__ = ["Scan", "scan_street", "sensor_poses", "hdl64_directions", "points_per_frame", "frames_for_points",
           "street_length_for_frames", "grid_passes", "SENSOR_HEIGHT_M", "MIN_RANGE_M",
           "POINTS_PER_FRAME_DEFAULT", "visible_from"]

SENSOR_HEIGHT_M = 1.73  # KITTI's Velodyne mounting height above the road
MIN_RANGE_M = 0.5  # hits closer than this (the carrier vehicle) are dropped, as real drivers do
ELEVATION_DEG = (2.0, -24.8)  # HDL-64E vertical field of view
POINTS_PER_FRAME_DEFAULT = 126_000  # measured: default scene, 64 beams x 2000 azimuths, 80 m range
GRID_CELL_M = (1.0, 1.0, 1.0)  # ray-casting grid cell (x, y, z)
_CAST_CHUNK_RAYS = 1 << 20  # rays per kernel call: bounds the temporary arrays to ~40 MB


# ====================================================================== trajectory
def street_length_for_frames(n_frames: int, frame_spacing_m: float = 1.0, margin_m: float = 40.0) -> float:
    """Street length (m) that fits ``n_frames`` poses with ``margin_m`` of street beyond each end."""
    return max(10.0, (int(n_frames) - 1) * float(frame_spacing_m) + 2.0 * float(margin_m))


def grid_passes(scene: StreetScene) -> list[tuple[int, float, int]]:
    """The grid layout's sensor passes, in driving order: one per street.

    The streets along x first, then those along y, back and forth (each pass starts at the end of the square
    where the previous one stopped), as a mapping car would cover the district.

    Returns
    -------
    list of (axis, line, direction)
        ``axis`` 0 for a street along x, 1 along y; ``line`` its centre-line position (local m, see
        :func:`grid_street_lines`); ``direction`` +1 or -1 along the axis.
    """
    lines = [float(c) for c in grid_street_lines(scene)]
    passes = [(0, c, 1 if k % 2 == 0 else -1) for k, c in enumerate(lines)]
    # the x passes end near the far corner (x = extent if their count is odd): start the y passes there
    x_end_high = passes[-1][2] > 0
    ys = lines[::-1] if x_end_high else lines
    passes += [(1, c, -1 if k % 2 == 0 else 1) for k, c in enumerate(ys)]
    return passes


def _grid_poses(scene: StreetScene, n: int, frame_spacing_m: float | None) -> np.ndarray:
    E = scene.extent_m
    passes = grid_passes(scene)
    counts = n // len(passes) + (np.arange(len(passes)) < n % len(passes))
    ph = scene_rng(scene, 7).uniform(0.0, 2 * np.pi, (len(passes), 3))
    xs, ys, yaws = [], [], []
    for (axis, line, direction), m, q in zip(passes, counts, ph):
        if m == 0:
            continue
        if frame_spacing_m is None:
            # evenly over the whole street: frame i at the middle of the i-th of m equal stretches
            s = E * (np.arange(m) + 0.5) / m
        else:
            s = 0.5 * E + (np.arange(m) - 0.5 * (m - 1)) * float(frame_spacing_m)
            if m > 1 and (s[0] < 2.0 or s[-1] > E - 2.0):
                raise ValueError(f"{m} frames per pass {frame_spacing_m} m apart do not fit a {E:g} m grid "
                                 f"(use frame_spacing_m=None to spread them over each street)")
        if direction < 0:
            s = s[::-1]
        lateral = 0.2 * np.sin(2 * np.pi * s / 31.0 + q[0])
        wobble = 0.04 * np.sin(2 * np.pi * s / 17.0 + q[1]) + 0.02 * np.sin(2 * np.pi * s / 7.3 + q[2])
        x, y = street_to_local(axis, line, s, lateral)
        xs.append(x)
        ys.append(y)
        yaws.append(wobble + 0.5 * np.pi * axis + (np.pi if direction < 0 else 0.0))
    return _poses_from(scene, np.concatenate(xs), np.concatenate(ys), np.concatenate(yaws))


def _poses_from(scene: StreetScene, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(n, 4, 4) world poses at local (x, y), ``SENSOR_HEIGHT_M`` above the terrain mesh, heading ``yaw``."""
    n = len(x)
    z = terrain_height(scene, x, y) + SENSOR_HEIGHT_M
    poses = np.zeros((n, 4, 4))
    c, s = np.cos(yaw), np.sin(yaw)
    poses[:, 0, 0], poses[:, 0, 1] = c, -s
    poses[:, 1, 0], poses[:, 1, 1] = s, c
    poses[:, 2, 2] = 1.0
    poses[:, 3, 3] = 1.0
    poses[:, :3, 3] = np.stack([x, y, z], 1) + scene.origin_array
    return poses


def sensor_poses(scene: StreetScene, n_frames: int, frame_spacing_m: float | None = None) -> np.ndarray:
    """Sensor-to-world poses along the street centre line(s).

    Single street: frames ``frame_spacing_m`` apart along x (1 m when None), centred on the street.

    Grid: the frames are shared out over the passes of :func:`grid_passes` (one per street, the first
    ``n_frames % passes`` passes get one more) and taken in pass order; within a pass they are spread evenly
    over the whole street (``frame_spacing_m=None``) or ``frame_spacing_m`` apart around its middle.

    Every frame is at ``SENSOR_HEIGHT_M`` above the terrain mesh, with a lateral wobble of up to 0.2 m and a
    heading wobble of up to ~3.4 degrees about the driving direction.

    Parameters
    ----------
    scene : StreetScene
    n_frames : int
        Poses in all.
    frame_spacing_m : float, optional
        Distance between consecutive poses along the driving direction (m).

    Returns
    -------
    (n_frames, 4, 4) float64
        ``world = pose @ [p_sensor; 1]``, world including ``scene.origin``; the sensor z axis is vertical.
    """
    n = int(n_frames)
    if n < 1:
        raise ValueError("n_frames must be >= 1")
    if scene.layout == "grid":
        return _grid_poses(scene, n, frame_spacing_m)
    if frame_spacing_m is None:
        frame_spacing_m = 1.0
    x = 0.5 * scene.length_m + (np.arange(n) - 0.5 * (n - 1)) * float(frame_spacing_m)
    if n > 1 and (x[0] < 2.0 or x[-1] > scene.length_m - 2.0):
        raise ValueError(f"{n} frames {frame_spacing_m} m apart do not fit a {scene.length_m:g} m street "
                         f"(use street_length_for_frames)")
    ph = scene_rng(scene, 6).uniform(0.0, 2 * np.pi, 3)
    y = 0.2 * np.sin(2 * np.pi * x / 31.0 + ph[0])
    yaw = 0.04 * np.sin(2 * np.pi * x / 17.0 + ph[1]) + 0.02 * np.sin(2 * np.pi * x / 7.3 + ph[2])
    return _poses_from(scene, x, y, yaw)


def hdl64_directions(beams: int = 64, azimuth_steps: int = 2000,
                     elevation_offsets: np.ndarray | None = None) -> np.ndarray:
    """Unit ray directions in the sensor frame, in firing order (azimuth-major, then beam top to bottom).

    Elevations are spread evenly over +2 .. -24.8 degrees, each plus its ``elevation_offsets`` entry (radians,
    one per beam) when given; azimuth ``j`` is ``2 pi j / azimuth_steps`` counter-clockwise from +x (forward).

    Returns
    -------
    (azimuth_steps * beams, 3) float64
    """
    el = np.deg2rad(np.linspace(ELEVATION_DEG[0], ELEVATION_DEG[1], int(beams)))
    if elevation_offsets is not None:
        el = el + np.asarray(elevation_offsets, np.float64)
    az = 2 * np.pi * np.arange(int(azimuth_steps)) / int(azimuth_steps)
    A, E = np.meshgrid(az, el, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)


# ====================================================================== ray casting
@njit(cache=True)
def _build_grid(tmin, tmax, lo, cs, dims):
    """CSR lists of the triangles whose (padded) bounding box overlaps each cell of a uniform 3-D grid.

    Parameters
    ----------
    tmin, tmax : (F, 3) float64
        Triangle bounding boxes (local metres).
    lo, cs : (3,) float64
        Grid corner and cell size.
    dims : (3,) int64

    Returns
    -------
    start : (C + 1,) int64
    tris : (start[-1],) int32
    """
    nx, ny, nz = dims[0], dims[1], dims[2]
    n_cells = nx * ny * nz
    count = np.zeros(n_cells + 1, np.int64)
    F = tmin.shape[0]
    rng = np.empty((F, 6), np.int64)
    pad = 1e-6  # cells; a point on a cell boundary then belongs to both cells' lists
    for t in range(F):
        for a in range(3):
            i0 = int(math.floor((tmin[t, a] - lo[a]) / cs[a] - pad))
            i1 = int(math.floor((tmax[t, a] - lo[a]) / cs[a] + pad))
            rng[t, 2 * a] = min(max(i0, 0), dims[a] - 1)
            rng[t, 2 * a + 1] = min(max(i1, 0), dims[a] - 1)
        for i in range(rng[t, 0], rng[t, 1] + 1):
            for j in range(rng[t, 2], rng[t, 3] + 1):
                for k in range(rng[t, 4], rng[t, 5] + 1):
                    count[(i * ny + j) * nz + k + 1] += 1
    for c in range(n_cells):
        count[c + 1] += count[c]
    fill = count[:-1].copy()
    tris = np.empty(count[n_cells], np.int32)
    for t in range(F):
        for i in range(rng[t, 0], rng[t, 1] + 1):
            for j in range(rng[t, 2], rng[t, 3] + 1):
                for k in range(rng[t, 4], rng[t, 5] + 1):
                    c = (i * ny + j) * nz + k
                    tris[fill[c]] = t
                    fill[c] += 1
    return count, tris


@njit(cache=True, inline="always")
def _first_hit(ox, oy, oz, dx, dy, dz, tri, lo, hi, cs, dims, start, tris, t_min, t_max):
    """Nearest triangle hit along a ray with t in [t_min, t_max], walking the grid cells (3-D DDA).

    Returns (t, face), face = -1 for no hit.
    """
    # clip the ray to the grid box
    t0 = t_min
    t1 = t_max
    o = (ox, oy, oz)
    d = (dx, dy, dz)
    for a in range(3):
        if d[a] != 0.0:
            ta = (lo[a] - o[a]) / d[a]
            tb = (hi[a] - o[a]) / d[a]
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
        elif o[a] < lo[a] or o[a] > hi[a]:
            return np.inf, -1
    if t0 > t1:
        return np.inf, -1
    nx, ny, nz = dims[0], dims[1], dims[2]
    px = ox + t0 * dx
    py = oy + t0 * dy
    pz = oz + t0 * dz
    ix = min(max(int(math.floor((px - lo[0]) / cs[0])), 0), nx - 1)
    iy = min(max(int(math.floor((py - lo[1]) / cs[1])), 0), ny - 1)
    iz = min(max(int(math.floor((pz - lo[2]) / cs[2])), 0), nz - 1)
    sx = 1 if dx > 0 else -1
    sy = 1 if dy > 0 else -1
    sz = 1 if dz > 0 else -1
    inf = np.inf
    tnx = ((lo[0] + (ix + (sx > 0)) * cs[0]) - ox) / dx if dx != 0.0 else inf
    tny = ((lo[1] + (iy + (sy > 0)) * cs[1]) - oy) / dy if dy != 0.0 else inf
    tnz = ((lo[2] + (iz + (sz > 0)) * cs[2]) - oz) / dz if dz != 0.0 else inf
    tdx = cs[0] / abs(dx) if dx != 0.0 else inf
    tdy = cs[1] / abs(dy) if dy != 0.0 else inf
    tdz = cs[2] / abs(dz) if dz != 0.0 else inf
    best = t_max
    face = -1
    eps = 1e-10  # barycentric slack: a ray through a shared edge cannot slip between its two triangles
    while True:
        c = (ix * ny + iy) * nz + iz
        for q in range(start[c], start[c + 1]):
            f = tris[q]
            # Moller-Trumbore, two-sided: where a closed piece pokes through the open terrain sheet a ray
            # can meet a back face first, and the hit is still a point of the ground truth
            e1x, e1y, e1z = tri[f, 3], tri[f, 4], tri[f, 5]
            e2x, e2y, e2z = tri[f, 6], tri[f, 7], tri[f, 8]
            pvx = dy * e2z - dz * e2y
            pvy = dz * e2x - dx * e2z
            pvz = dx * e2y - dy * e2x
            det = e1x * pvx + e1y * pvy + e1z * pvz
            if abs(det) < 1e-14:
                continue
            inv = 1.0 / det
            tvx = ox - tri[f, 0]
            tvy = oy - tri[f, 1]
            tvz = oz - tri[f, 2]
            u = (tvx * pvx + tvy * pvy + tvz * pvz) * inv
            if u < -eps or u > 1.0 + eps:
                continue
            qvx = tvy * e1z - tvz * e1y
            qvy = tvz * e1x - tvx * e1z
            qvz = tvx * e1y - tvy * e1x
            v = (dx * qvx + dy * qvy + dz * qvz) * inv
            if v < -eps or u + v > 1.0 + eps:
                continue
            t = (e2x * qvx + e2y * qvy + e2z * qvz) * inv
            if t >= t_min and t < best:
                best = t
                face = f
        t_exit = min(tnx, min(tny, tnz))
        # every hit closer than this cell's exit lies in a visited cell, so none can beat it
        if face >= 0 and best <= t_exit:
            break
        if t_exit > t1:
            break
        if tnx <= tny and tnx <= tnz:
            ix += sx
            if ix < 0 or ix >= nx:
                break
            tnx += tdx
        elif tny <= tnz:
            iy += sy
            if iy < 0 or iy >= ny:
                break
            tny += tdy
        else:
            iz += sz
            if iz < 0 or iz >= nz:
                break
            tnz += tdz
    return best, face


@njit(cache=True, parallel=True)
def _cast_rays(poses, dirs, first, count, tri, nrm, lo, hi, cs, dims, start, tris, t_min, t_max,
               out_xyz, out_t, out_face, out_refl):
    """Cast rays ``first .. first + count`` of the frames' flattened (frame, ray) index.

    Parameters
    ----------
    poses : (n_frames, 4, 4) float64
        Sensor-to-local poses.
    dirs : (R, 3) float64
        Ray directions in the sensor frame.
    first, count : int
    tri : (F, 9) float64
        ``v0, v1 - v0, v2 - v0`` per triangle (local metres).
    nrm : (F, 3) float64
        Unit face normals (for the reflectance).
    out_xyz : (count, 3) float64, out
        Local hit points.
    out_t : (count,) float64, out
        Range (m).
    out_face : (count,) int32, out
        Hit face, -1 for no hit within ``t_max``.
    out_refl : (count,) float32, out
        Synthetic reflectance in [0.1, 0.9]: grows with the cosine of the incidence angle.
    """
    nr = dirs.shape[0]
    for r in prange(count):
        g = first + r
        fr = g // nr
        k = g - fr * nr
        P = poses[fr]
        sx, sy, sz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        dx = P[0, 0] * sx + P[0, 1] * sy + P[0, 2] * sz
        dy = P[1, 0] * sx + P[1, 1] * sy + P[1, 2] * sz
        dz = P[2, 0] * sx + P[2, 1] * sy + P[2, 2] * sz
        ox, oy, oz = P[0, 3], P[1, 3], P[2, 3]
        t, f = _first_hit(ox, oy, oz, dx, dy, dz, tri, lo, hi, cs, dims, start, tris, t_min, t_max)
        out_face[r] = f
        if f >= 0:
            out_t[r] = t
            out_xyz[r, 0] = ox + t * dx
            out_xyz[r, 1] = oy + t * dy
            out_xyz[r, 2] = oz + t * dz
            cosi = abs(nrm[f, 0] * dx + nrm[f, 1] * dy + nrm[f, 2] * dz)
            out_refl[r] = np.float32(0.1 + 0.8 * cosi)
        else:
            out_t[r] = np.inf


@njit(cache=True, parallel=True)
def _visible(q, sensors, tri, lo, hi, cs, dims, start, tris, el_lo, el_hi, max_range, stop_short):
    """Whether each query is seen by some sensor: within the elevation span and range, and no triangle on the
    segment between them (up to ``stop_short`` before the query, which lies on a triangle itself)."""
    n = q.shape[0]
    out = np.zeros(n, np.bool_)
    for i in prange(n):
        for s in range(sensors.shape[0]):
            dx = q[i, 0] - sensors[s, 0]
            dy = q[i, 1] - sensors[s, 1]
            dz = q[i, 2] - sensors[s, 2]
            L = math.sqrt(dx * dx + dy * dy + dz * dz)
            el = math.atan2(dz, math.sqrt(dx * dx + dy * dy))
            if L > max_range or L < MIN_RANGE_M + stop_short or el < el_lo or el > el_hi:
                continue
            _, f = _first_hit(sensors[s, 0], sensors[s, 1], sensors[s, 2], dx / L, dy / L, dz / L, tri, lo, hi,
                              cs, dims, start, tris, MIN_RANGE_M, L - stop_short)
            if f < 0:
                out[i] = True
                break
    return out


def visible_from(mesh: Mesh, points: np.ndarray, sensors: np.ndarray, max_range: float = 80.0,
                 elevation_deg: tuple[float, float] = ELEVATION_DEG, stop_short: float = 0.03) -> np.ndarray:
    """Which points on a mesh some sensor position sees: the scanner's elevation span and range hold them,
    and the segment from the sensor stops on no triangle short of them.

    What no sensor sees (the back of a wall, a car's underside, the ground in a shadow, a wall above the
    highest beam) no scan samples: a reconstruction can only guess it.

    Parameters
    ----------
    mesh : Mesh
        The scene (world coordinates).
    points : (N, 3) float
        Points on the mesh, e.g. area-uniform samples.
    sensors : (S, 3) float
        Sensor positions (world), e.g. a trajectory's.
    max_range : float
        Farthest range that returns (m).
    elevation_deg : (float, float)
        Highest and lowest beam elevation (degrees; the sensor's z axis vertical).
    stop_short : float
        The segment ends this far before the point (m), whose own triangle it would otherwise meet.

    Returns
    -------
    (N,) bool
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    sen = np.asarray(sensors, np.float64).reshape(-1, 3)
    if len(pts) == 0 or len(sen) == 0:
        return np.zeros(len(pts), bool)
    centre = sen.mean(axis=0)  # local coordinates: float64 exact at UTM magnitudes
    caster = _RayCaster(mesh.vertices - centre, mesh.faces)
    hi_el, lo_el = (math.radians(float(e)) for e in elevation_deg)
    return _visible(np.ascontiguousarray(pts - centre), np.ascontiguousarray(sen - centre), caster.tri,
                    caster.lo, caster.hi, caster.cs, caster.dims, caster.start, caster.tris, lo_el, hi_el,
                    float(max_range), float(stop_short))


class _RayCaster:
    """A mesh in local coordinates with its uniform-grid acceleration structure.

    A 3-D grid (1 m cells) rather than 2-D xy columns: a column under a facade or a pole also holds all the
    terrain triangles of its footprint, which every ray passing over it would test; in 3-D a ray above the
    ground walks empty cells (a few ns each) and tests only what it actually approaches (~1.4 M rays/s
    on 2 cores for the default street).
    """

    def __init__(self, vertices_local: np.ndarray, faces: np.ndarray, cell=GRID_CELL_M) -> None:
        tri = vertices_local[faces]  # (F, 3, 3)
        self.tri = np.ascontiguousarray(
            np.concatenate([tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=1))
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(cross, axis=1, keepdims=True)
        self.nrm = np.ascontiguousarray(cross / np.where(norm > 0, norm, 1.0))
        tmin = tri.min(axis=1)
        tmax = tri.max(axis=1)
        self.cs = np.asarray(cell, np.float64)
        self.lo = tmin.min(axis=0) - 0.5 * self.cs
        top = tmax.max(axis=0) + 0.5 * self.cs
        self.dims = np.maximum(np.ceil((top - self.lo) / self.cs), 1).astype(np.int64)
        self.hi = self.lo + self.dims * self.cs
        self.start, self.tris = _build_grid(tmin, tmax, self.lo, self.cs, self.dims)

    def cast(self, poses_local: np.ndarray, dirs: np.ndarray, t_min: float, t_max: float):
        """Hits of every ray of every pose, in (frame, ray) order.

        Returns
        -------
        ray : (H,) int64
            Flattened (frame, ray) index of each hit.
        xyz : (H, 3) float64
            Local hit points.
        t : (H,) float64
        face : (H,) int32
        refl : (H,) float32
        """
        total = len(poses_local) * len(dirs)
        parts = []
        for first in range(0, total, _CAST_CHUNK_RAYS):
            n = min(_CAST_CHUNK_RAYS, total - first)
            xyz = np.empty((n, 3))
            t = np.empty(n)
            face = np.empty(n, np.int32)
            refl = np.zeros(n, np.float32)
            _cast_rays(poses_local, dirs, first, n, self.tri, self.nrm, self.lo, self.hi, self.cs, self.dims,
                       self.start, self.tris, float(t_min), float(t_max), xyz, t, face, refl)
            hit = np.flatnonzero(face >= 0)
            parts.append((hit + first, xyz[hit], t[hit], face[hit], refl[hit]))
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(5))


# ====================================================================== scan
@dataclass(eq=False)
class Scan:
    """A simulated LiDAR scan.

    Attributes
    ----------
    xyz : (N, 3) float64
        World points (``scene.origin`` included), frame by frame in firing order.
    sensor : (N, 3) float64
        World position of the sensor that measured each point.
    frame : (N,) int32
        Frame index of each point (non-decreasing).
    poses : (n_frames, 4, 4) float64
        Sensor-to-world transforms (``world = pose @ [p_sensor; 1]``).
    face : (N,) int32
        Ground-truth mesh face each ray hit.
    reflectance : (N,) float32
        Synthetic reflectance in [0.1, 0.9] (cosine of the incidence angle).
    origin : (3,) float64
        The scene origin included in ``xyz``, ``sensor`` and ``poses``.
    """

    xyz: np.ndarray
    sensor: np.ndarray
    frame: np.ndarray
    poses: np.ndarray
    face: np.ndarray
    reflectance: np.ndarray
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self._offsets = np.searchsorted(self.frame, np.arange(len(self.poses) + 1), side="left")

    @property
    def n_points(self) -> int:
        return int(len(self.xyz))

    @property
    def n_frames(self) -> int:
        return int(len(self.poses))

    def __repr__(self) -> str:
        return f"Scan({self.n_points} points, {self.n_frames} frames)"

    def frame_slice(self, i: int) -> slice:
        """Slice of the points of frame ``i``."""
        return slice(int(self._offsets[i]), int(self._offsets[i + 1]))

    def frame_points(self, i: int) -> np.ndarray:
        """Points of frame ``i`` in that frame's sensor coordinates, (M, 3) float32 (as a sensor records)."""
        P = self.poses[i]
        # the float64 difference first: at UTM magnitudes float32 would lose the centimetres
        return ((self.xyz[self.frame_slice(i)] - P[:3, 3]) @ P[:3, :3]).astype(np.float32)

    def normals(self, mesh: Mesh) -> np.ndarray:
        """Unit ground-truth normals of the hit faces, flipped to face the sensor, (N, 3) float64."""
        n, _ = mesh.face_normals()
        n = n[self.face]
        flip = np.einsum("ij,ij->i", n, self.sensor - self.xyz) < 0
        n[flip] *= -1.0
        return n


def scan_street(scene: StreetScene, mesh: Mesh, n_frames: int, *, frame_spacing_m: float | None = None,
                beams: int = 64, azimuth_steps: int = 2000, max_range: float = 80.0, range_noise: float = 0.0,
                seed: int = 0, beam_bias_deg: float = 0.0) -> Scan:
    """Scan the street mesh with a spinning multi-beam LiDAR driving along the centre line(s).

    Parameters
    ----------
    scene : StreetScene
    mesh : Mesh
        The scene's mesh (:func:`build_street`), world coordinates.
    n_frames : int
        Revolutions, one per pose (:func:`sensor_poses`); each is a single instant (no rolling shutter). For
        the grid layout they are shared out over one pass per street.
    frame_spacing_m : float, optional
        Distance between consecutive poses along the driving direction (m). None: 1 m for the single street;
        spread evenly over each whole street for the grid.
    beams : int
        Elevation angles, spread evenly over +2 .. -24.8 degrees.
    azimuth_steps : int
        Rays per beam per revolution.
    max_range : float
        Rays hitting nothing within this range (m) are dropped; hits closer than 0.5 m too.
    range_noise : float
        Standard deviation (m) of a Gaussian added to each range along its ray (0: points exactly on the
        mesh).
    seed : int
        Seed of the range noise and the beam bias (the scene has its own).
    beam_bias_deg : float
        Standard deviation (degrees) of a fixed elevation error per beam, as a multi-beam sensor's residual
        calibration leaves it: each ray flies at its beam's true angle, and its point is reported along the
        nominal one at the measured range, so each scan ring sits a little above or below the surface (0.1
        degrees: about 3.5 cm at 20 m), consistently around the whole ring.

    Returns
    -------
    Scan
        About ``POINTS_PER_FRAME_DEFAULT * azimuth_steps / 2000 * beams / 64`` points per frame on the
        default scene; ~1-2 M rays/s on 2 cores.
    """
    if max_range <= MIN_RANGE_M:
        raise ValueError(f"max_range must exceed {MIN_RANGE_M} m")
    if range_noise < 0:
        raise ValueError("range_noise must be >= 0")
    if beams < 1 or azimuth_steps < 1:
        raise ValueError("beams and azimuth_steps must be >= 1")
    if not (math.isfinite(beam_bias_deg) and beam_bias_deg >= 0):
        raise ValueError("beam_bias_deg must be >= 0")
    origin = scene.origin_array
    poses = sensor_poses(scene, n_frames, frame_spacing_m)
    local = poses.copy()
    local[:, :3, 3] -= origin
    # cast in local coordinates: float64 keeps ~1e-14 relative, i.e. ~1e-12 m, where UTM values would not
    caster = _RayCaster(mesh.vertices - origin, mesh.faces)
    dirs = hdl64_directions(beams, azimuth_steps)
    nominal = dirs
    if beam_bias_deg > 0:
        bias = np.deg2rad(np.random.default_rng([int(seed), 0xB1A5]).normal(0.0, float(beam_bias_deg), int(beams)))
        dirs = hdl64_directions(beams, azimuth_steps, elevation_offsets=bias)
    ray, xyz, t, face, refl = caster.cast(local, dirs, MIN_RANGE_M, float(max_range))
    frame = (ray // len(dirs)).astype(np.int32)
    sensor = local[frame, :3, 3]
    if beam_bias_deg > 0 and len(t):
        # the point goes where the sensor believes its ray went: the nominal direction, at the measured range
        within = ray % len(dirs)
        xyz[:] = sensor + t[:, None] * np.einsum("nij,nj->ni", local[frame, :3, :3], nominal[within])
    # in place from here on: at ~14 M points every (N, 3) float64 temporary is 336 MB
    if range_noise > 0 and len(t):
        rng = np.random.default_rng([int(seed), 0xA1DA])
        step = rng.normal(0.0, float(range_noise), len(t)) / t  # range offset per metre of ray
        xyz -= sensor
        xyz *= (1.0 + step)[:, None]
        xyz += sensor
    xyz += origin
    sensor += origin
    return Scan(xyz=xyz, sensor=sensor, frame=frame, poses=poses, face=face, reflectance=refl, origin=origin)


def points_per_frame(scene: StreetScene, mesh: Mesh | None = None, *, beams: int = 64,
                     azimuth_steps: int = 2000, max_range: float = 80.0) -> float:
    """Points one frame at the street's centre gives (measured by casting it; for the grid, at the middle of
    the first pass's street)."""
    mesh = build_street(scene) if mesh is None else mesh
    return float(scan_street(scene, mesh, 1, beams=beams, azimuth_steps=azimuth_steps,
                             max_range=max_range).n_points)


def frames_for_points(scene: StreetScene, target_points: int, *, mesh: Mesh | None = None, beams: int = 64,
                      azimuth_steps: int = 2000, max_range: float = 80.0) -> int:
    """Frames needed for about ``target_points`` points (from one probe frame cast at the street centre).

    With the defaults a frame gives ~``POINTS_PER_FRAME_DEFAULT`` points, so 14 M points is ~111 frames (the
    street must be long enough: :func:`street_length_for_frames`).
    """
    ppf = points_per_frame(scene, mesh, beams=beams, azimuth_steps=azimuth_steps, max_range=max_range)
    return max(1, int(math.ceil(int(target_points) / max(ppf, 1.0))))
