"""A synthetic street scanned by a simulated 64-beam spinning LiDAR, with an exact ground-truth mesh.

The scene (:func:`build_street`) is a street along +x in a local frame: x in ``[0, length_m]``, y in
``[-width_m/2, width_m/2]`` (the road centre line at y = 0), z up, all in metres. Every output coordinate has
``scene.origin`` added (e.g. UTM-like ``(500000, 4000000, 100)``), so georeferenced code paths are exercised.

The scan (:func:`scan_street`) casts the rays of an HDL-64E-like sensor (64 beams from +2 to -24.8 degrees
elevation, ``azimuth_steps`` azimuths per revolution) from poses driving along the centre line at
``SENSOR_HEIGHT_M`` above the terrain, with a small heading and lateral wobble. Rays are intersected exactly
(Moller-Trumbore in float64) with the mesh triangles, so noise-free points lie on the ground truth to
~1e-12 m. With the defaults a frame of the default 100 m street gives about ``POINTS_PER_FRAME_DEFAULT``
points (~99 % of the 128 000 rays hit something); :func:`frames_for_points` measures it for any scene.

Layout of the scene (local frame): road ``|y| < 6`` with moving cars at ``|y| = 3`` and parked cars at
``|y| = 5``; poles at ``|y| = 6.6``; trees at ``|y| = 8.2``; building fronts from ``|y| = 10`` back to at most
``width_m/2 - 0.5``. Objects are separate closed pieces that sit on or sink into the terrain; the ground truth
is the union of all surfaces (some of it, e.g. building floors and car bottoms, is never observed: restrict
evaluation with :func:`observed_samples`).

``StreetScene(layout="grid")`` is a wide-area variant: a square ``extent_m`` x ``extent_m`` district (x and y
in ``[0, extent_m]``) crossed by ``GRID_STREETS`` streets along x and as many along y
(:func:`grid_street_lines`; 88 m apart for the default 200 m), each with the cross-section above (road, cars,
poles, trees). Buildings line the four edges of every city block between the streets, nothing stands in the
crossings, and the terrain sheet covers the whole square. The sensor drives every street in turn, one pass per
street, back and forth like a mapping car covering the district (:func:`sensor_poses`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from numba import njit, prange

from ..errors import InputError
from ..io.atomic import atomic_open, atomic_path, write_json
from ..io.meshes import write_mesh
from ..mesh import Mesh
from ..metrics import sample_surface
from .shapes import box, sphere

__all__ = [
    "StreetScene", "Scan", "build_street", "terrain_height", "sensor_poses", "scan_street",
    "points_per_frame", "frames_for_points", "street_length_for_frames", "write_las", "write_kitti_sequence",
    "make_street_sample", "observed_samples", "hdl64_directions", "KITTI_TR", "SENSOR_HEIGHT_M",
    "POINTS_PER_FRAME_DEFAULT", "FACE_CLASSES",
    "LAYOUTS", "GRID_STREETS", "grid_street_lines", "grid_passes", "grid_frames_for_points",
]

SENSOR_HEIGHT_M = 1.73  # KITTI's Velodyne mounting height above the road
MIN_RANGE_M = 0.5  # hits closer than this (the carrier vehicle) are dropped, as real drivers do
ELEVATION_DEG = (2.0, -24.8)  # HDL-64E vertical field of view
TERRAIN_STEP_M = 0.5  # terrain triangulation spacing
POINTS_PER_FRAME_DEFAULT = 126_000  # measured: default scene, 64 beams x 2000 azimuths, 80 m range
FACE_CLASSES = ("terrain", "building", "pole", "tree", "car")
GRID_CELL_M = (1.0, 1.0, 1.0)  # ray-casting grid cell (x, y, z)
_CAST_CHUNK_RAYS = 1 << 20  # rays per kernel call: bounds the temporary arrays to ~40 MB
LAYOUTS = ("street", "grid")
GRID_STREETS = 3  # grid layout: streets along x, and as many along y
# the outermost centre lines stay this far inside the square, so their outer sidewalks, poles and whole tree
# crowns (8.2 m + 2.2 m radius from the centre line) lie inside it too
_GRID_MARGIN_M = 12.0
_GRID_MIN_EXTENT_M = 150.0  # blocks of >= 63 m between centre lines: two facing 25 m rows of buildings fit

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


# ====================================================================== scene
@dataclass(frozen=True)
class StreetScene:
    """Parameters of a synthetic street or grid of streets (the rest follows deterministically from ``seed``).

    Attributes
    ----------
    seed : int
    length_m : float
        ``layout="street"``: street length along +x (metres). Unused by the grid.
    width_m : float
        ``layout="street"``: extent across the street (metres, >= 30: road, sidewalks and building fronts need
        20 m). Unused by the grid.
    origin : (3,) float
        Added to every output coordinate (mesh vertices, points, poses), e.g.
        ``(500000.0, 4000000.0, 100.0)``.
    layout : {"street", "grid"}
        ``"street"``: one straight street along +x, x in ``[0, length_m]``, y in ``[-width_m/2, width_m/2]``.
        ``"grid"``: ``GRID_STREETS`` streets along x and as many along y over x, y in ``[0, extent_m]``.
    extent_m : float
        ``layout="grid"``: side of the square district (metres, >= 150). Unused by the single street.
    """

    seed: int = 0
    length_m: float = 100.0
    width_m: float = 40.0
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    layout: str = "street"
    extent_m: float = 200.0

    def __post_init__(self) -> None:
        origin = tuple(float(v) for v in np.asarray(self.origin, dtype=np.float64).reshape(3))
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "seed", int(self.seed))
        object.__setattr__(self, "length_m", float(self.length_m))
        object.__setattr__(self, "width_m", float(self.width_m))
        object.__setattr__(self, "extent_m", float(self.extent_m))
        if self.layout not in LAYOUTS:
            raise ValueError(f"StreetScene.layout must be one of {LAYOUTS}, got {self.layout!r}")
        if not self.length_m >= 10.0:
            raise ValueError("StreetScene.length_m must be >= 10 m")
        if not self.width_m >= 30.0:
            raise ValueError("StreetScene.width_m must be >= 30 m")
        if self.layout == "grid" and not (self.extent_m >= _GRID_MIN_EXTENT_M and math.isfinite(self.extent_m)):
            raise ValueError(f"StreetScene.extent_m must be >= {_GRID_MIN_EXTENT_M:g} m for the grid layout "
                             f"(city blocks need room for two rows of buildings), got {self.extent_m:g}")
        if not all(math.isfinite(v) for v in origin):
            raise ValueError("StreetScene.origin must be finite")

    @property
    def size_m(self) -> tuple[float, float]:
        """Local extent ``(along x, along y)`` in metres: ``(length_m, width_m)`` or ``(extent_m, extent_m)``."""
        if self.layout == "grid":
            return self.extent_m, self.extent_m
        return self.length_m, self.width_m

    @property
    def y_min(self) -> float:
        """Local y of the scene's lower edge (m): ``-width_m/2`` for the street (centred), 0 for the grid."""
        return 0.0 if self.layout == "grid" else -0.5 * self.width_m

    @property
    def origin_array(self) -> np.ndarray:
        """``origin`` as a (3,) float64 array."""
        return np.array(self.origin, dtype=np.float64)

    def to_dict(self) -> dict:
        """Plain dict (JSON-able)."""
        return asdict(self)


def _rng(scene: StreetScene, stream: int) -> np.random.Generator:
    # independent streams per purpose, so adding an object kind never shifts the terrain or the poses
    return np.random.default_rng([scene.seed, stream])


def _terrain_params(scene: StreetScene) -> np.ndarray:
    return _rng(scene, 1).uniform(0.0, 2 * np.pi, 5)


def _terrain_analytic(ph: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth height field (m): a 0.5 % grade plus waves of 5-35 cm, ~1 m relief over 100 m."""
    return (0.005 * x
            + 0.35 * np.sin(2 * np.pi * x / 61.0 + ph[0])
            + 0.15 * np.sin(2 * np.pi * y / 23.0 + ph[1]) * np.cos(2 * np.pi * x / 41.0 + ph[2])
            + 0.05 * np.sin(2 * np.pi * (x + 0.6 * y) / 9.0 + ph[3])
            + 0.03 * np.cos(2 * np.pi * (0.7 * x - y) / 5.5 + ph[4]))


def _terrain_grid(scene: StreetScene) -> tuple[int, int, float, float]:
    sx, sy = scene.size_m
    nx = max(1, int(round(sx / TERRAIN_STEP_M)))
    ny = max(1, int(round(sy / TERRAIN_STEP_M)))
    return nx, ny, sx / nx, sy / ny


def terrain_height(scene: StreetScene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of the triangulated terrain surface (exactly the mesh's, not the smooth field's).

    Parameters
    ----------
    scene : StreetScene
    x, y : array_like
        Local coordinates (metres, without ``scene.origin``), inside the scene's extent (x in
        ``[0, size_m[0]]``, y in ``[y_min, y_min + size_m[1]]``).

    Returns
    -------
    ndarray, float64
        Local z of the terrain mesh at (x, y), same shape as ``x``.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ph = _terrain_params(scene)
    nx, ny, dx, dy = _terrain_grid(scene)
    # y - y_min with y_min = -half is bit-for-bit y + half (IEEE subtraction adds the negation), so the single
    # street's heights are unchanged
    ylo = scene.y_min
    i = np.clip(np.floor(x / dx).astype(np.int64), 0, nx - 1)
    j = np.clip(np.floor((y - ylo) / dy).astype(np.int64), 0, ny - 1)
    fx = x / dx - i
    fy = (y - ylo) / dy - j
    # node coordinates computed exactly as in _terrain_mesh, so the heights agree to the last bit
    x0, x1 = i * dx, (i + 1) * dx
    y0, y1 = ylo + j * dy, ylo + (j + 1) * dy
    h00 = _terrain_analytic(ph, x0, y0)
    h10 = _terrain_analytic(ph, x1, y0)
    h11 = _terrain_analytic(ph, x1, y1)
    h01 = _terrain_analytic(ph, x0, y1)
    # each cell is split along its (0,0)-(1,1) diagonal, as the mesh is
    lower = fx >= fy
    return np.where(lower, h00 + fx * (h10 - h00) + fy * (h11 - h10),
                    h00 + fx * (h11 - h01) + fy * (h01 - h00))


def _terrain_mesh(scene: StreetScene) -> tuple[np.ndarray, np.ndarray]:
    ph = _terrain_params(scene)
    nx, ny, dx, dy = _terrain_grid(scene)
    i, j = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), indexing="ij")
    x = i * dx
    y = scene.y_min + j * dy
    v = np.stack([x, y, _terrain_analytic(ph, x, y)], axis=-1).reshape(-1, 3)
    ci, cj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    v00 = (ci * (ny + 1) + cj).ravel()
    v10 = v00 + (ny + 1)
    v11 = v10 + 1
    v01 = v00 + 1
    f = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])  # normals +z
    return v, f


def _cylinder(radius: float, z0: float, z1: float, segments: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Closed vertical cylinder around the z axis (caps fanned from a centre vertex), outward."""
    a = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], 1)
    v = np.vstack([np.column_stack([ring, np.full(segments, z0)]),
                   np.column_stack([ring, np.full(segments, z1)]),
                   [[0.0, 0.0, z0], [0.0, 0.0, z1]]])
    k = np.arange(segments)
    k1 = (k + 1) % segments
    bottom_c, top_c = 2 * segments, 2 * segments + 1
    f = np.concatenate([
        np.stack([k, k1, k1 + segments], 1), np.stack([k, k1 + segments, k + segments], 1),
        np.stack([np.full(segments, top_c), k + segments, k1 + segments], 1),
        np.stack([np.full(segments, bottom_c), k1, k], 1)])
    return v, f


# side profile (x along the car, z up from the underbody) of a hatchback: star-shaped from _CAR_CENTRE
_CAR_PROFILE = np.array([(-2.25, 0.0), (2.25, 0.0), (2.25, 0.55), (2.0, 0.8), (1.0, 0.85), (0.3, 1.35),
                         (-1.3, 1.35), (-1.9, 0.85), (-2.25, 0.8)])
_CAR_CENTRE = (0.0, 0.6)
_CAR_WIDTH = 1.8
_CAR_CLEARANCE = 0.15


def _car() -> tuple[np.ndarray, np.ndarray]:
    """Closed car body: the side profile extruded across 1.8 m, caps fanned from the profile's centre."""
    m = len(_CAR_PROFILE)
    prof = np.vstack([_CAR_PROFILE, [_CAR_CENTRE]])
    hw = 0.5 * _CAR_WIDTH
    v = np.vstack([np.column_stack([prof[:, 0], np.full(m + 1, -hw), prof[:, 1]]),
                   np.column_stack([prof[:, 0], np.full(m + 1, hw), prof[:, 1]])])
    k = np.arange(m)
    k1 = (k + 1) % m
    o = m + 1
    f = np.concatenate([
        np.stack([np.full(m, m), k, k1], 1), np.stack([np.full(m, o + m), o + k1, o + k], 1),
        np.stack([k, k1 + o, k1], 1), np.stack([k, k + o, k1 + o], 1)])
    return v, f


def _orient_outward(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    tri = v[f]
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()
    return f if vol > 0 else f[:, ::-1].copy()


class _Builder:
    """Accumulates closed pieces (vertices, faces) per face class."""

    def __init__(self) -> None:
        self.parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {c: [] for c in FACE_CLASSES}

    def add(self, cls: str, v: np.ndarray, f: np.ndarray) -> None:
        self.parts[cls].append((np.asarray(v, np.float64), np.asarray(f, np.int64)))

    def build(self) -> tuple[np.ndarray, np.ndarray, dict]:
        verts, faces, ranges = [], [], {}
        nv = nf = 0
        for cls in FACE_CLASSES:
            start = nf
            for v, f in self.parts[cls]:
                verts.append(v)
                faces.append(f + nv)
                nv += len(v)
                nf += len(f)
            ranges[cls] = [start, nf]
        return np.vstack(verts), np.vstack(faces), ranges


def build_street(scene: StreetScene) -> Mesh:
    """Deterministic ground-truth mesh of the street.

    Terrain (height field triangulated at ``TERRAIN_STEP_M``; triangles wholly under a building dropped),
    buildings (boxes 6-20 m tall, some with a rooftop box, on both sides with gaps), poles (r = 0.15 m, 6 m),
    trees (trunk + icosphere crown) and cars (extruded hatchback profile, ~4.5 x 1.8 x 1.5 m). About 28 000
    faces for the default 100 m x 40 m street, mostly terrain, and ~3 000 more per extra 10 m of length.

    With ``scene.layout == "grid"`` the same kinds of objects line every street of the grid
    (:func:`grid_street_lines`): buildings along the four edges of each city block (footprints disjoint from
    each other and >= 10 m from every centre line, i.e. off the roads and sidewalks), poles, trees and cars
    along both sides of each street except in the crossings. About 0.4 M faces for the default 200 m square,
    ~80 % of them terrain.

    Parameters
    ----------
    scene : StreetScene

    Returns
    -------
    Mesh
        World coordinates (``scene.origin`` added). Faces are grouped by class; ``metadata["face_classes"]``
        maps each class of ``FACE_CLASSES`` to its ``[start, stop)`` face range. Every object is a closed,
        outward-oriented piece; the terrain is an open sheet with normals up.
    """
    if scene.layout == "grid":
        return _build_grid_scene(scene)
    L, W = scene.length_m, scene.width_m
    half = 0.5 * W
    ph = _terrain_params(scene)
    h = lambda x, y: _terrain_analytic(ph, np.asarray(x, np.float64), np.asarray(y, np.float64))  # noqa: E731
    out = _Builder()
    rng = _rng(scene, 2)

    # ---- buildings: a row per side, random widths and gaps (some wide enough to be alleys)
    footprints = []
    for side in (-1.0, 1.0):
        x = rng.uniform(0.0, 4.0)
        while x < L - 4.0:
            x1 = min(x + rng.uniform(8.0, 25.0), L)
            front = 10.0 + rng.uniform(0.0, 1.0)
            back = min(front + rng.uniform(8.0, 14.0), half - 0.5)
            height = rng.uniform(6.0, 20.0)
            extra = rng.random()
            gap = rng.uniform(8.0, 15.0) if rng.random() < 0.25 else rng.uniform(1.5, 6.0)
            if x1 - x >= 4.0 and back - front >= 3.0:
                y0, y1 = (front, back) if side > 0 else (-back, -front)
                footprints.append((x, x1, y0, y1))
                _add_building(out, h, x, x1, y0, y1, height, extra < 0.4)
            x = x1 + gap

    # ---- terrain, minus the triangles entirely inside a building (never visible, and they would load the
    # ray-casting grid under every wall)
    tv, tf = _terrain_mesh(scene)
    keep = np.ones(len(tf), bool)
    tri = tv[tf]
    for x0, x1, y0, y1 in footprints:
        inside = (tri[..., 0] > x0) & (tri[..., 0] < x1) & (tri[..., 1] > y0) & (tri[..., 1] < y1)
        keep &= ~inside.all(axis=1)
    used, inv = np.unique(tf[keep], return_inverse=True)
    out.add("terrain", tv[used], inv.reshape(-1, 3))

    # ---- poles along both curbs
    poles = []
    rng = _rng(scene, 3)
    for side in (-1.0, 1.0):
        x = rng.uniform(3.0, 10.0)
        while x < L - 2.0:
            y = side * 6.6
            z = float(h(x, y))
            v, f = _cylinder(0.15, z - 0.3, z + 6.0)
            out.add("pole", v + (x, y, 0.0), f)
            poles.append((x, side))
            x += rng.uniform(20.0, 30.0)

    # ---- trees on the sidewalks, not too close to a pole
    rng = _rng(scene, 4)
    crown = sphere(1.0, 2)
    crown_v, crown_f = crown.vertices, crown.faces
    for side in (-1.0, 1.0):
        for x, trunk_h, r in _tree_row(rng, L, lambda x: all(abs(x - px) > 2.5 or ps != side for px, ps in poles)):
            y = side * 8.2
            _add_tree(out, x, y, float(h(x, y)), trunk_h, r, crown_v, crown_f)

    # ---- cars: moving ones in the lanes, parked ones along the curbs, small random yaw
    rng = _rng(scene, 5)
    car_v, car_f = _car()
    car_f = _orient_outward(car_v, car_f)
    for lane_y, p in ((-5.0, 0.5), (-3.0, 0.35), (3.0, 0.35), (5.0, 0.5)):
        x = rng.uniform(3.0, 10.0)
        while x < L - 3.0:
            place = rng.random() < p
            yaw = rng.uniform(-0.04, 0.04) + (np.pi if lane_y < 0 and rng.random() < 0.8 else 0.0)
            step = rng.uniform(7.0, 16.0)
            if place:
                c, s = math.cos(yaw), math.sin(yaw)
                rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
                corners_x = x + np.array([-2.25, 2.25, 2.25, -2.25, 0.0]) * c
                corners_y = lane_y + np.array([-0.9, -0.9, 0.9, 0.9, 0.0])
                base = float(h(corners_x, corners_y).max()) + _CAR_CLEARANCE
                out.add("car", car_v @ rot.T + (x, lane_y, base), car_f)
            x += step

    v, f, ranges = out.build()
    meta = {"generator": "tiled_gridpull.synthetic.street", "scene": scene.to_dict(), "face_classes": ranges,
            "units": "m"}
    return Mesh(v + scene.origin_array, f, meta)


def _add_building(out: _Builder, h, x0: float, x1: float, y0: float, y1: float, height: float,
                  rooftop: bool) -> None:
    """A box building on footprint ``[x0, x1] x [y0, y1]`` (local m), sunk 0.5 m below its lowest ground so no
    terrain wave shows under a wall, ``height`` m above the ground at its centre; ``rooftop`` adds a stair house
    / plant room box sunk 0.2 m into the roof so the two pieces leave no gap."""
    gx, gy = np.meshgrid(np.linspace(x0, x1, 24), np.linspace(y0, y1, 12))
    z0 = float(h(gx, gy).min()) - 0.5
    z1 = float(h(0.5 * (x0 + x1), 0.5 * (y0 + y1))) + height
    _add_box(out, "building", (x0, y0, z0), (x1, y1, z1))
    if rooftop:
        cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
        sx, sy = 0.3 * (x1 - x0), 0.3 * (y1 - y0)
        _add_box(out, "building", (cx - sx / 2, cy - sy / 2, z1 - 0.2), (cx + sx / 2, cy + sy / 2, z1 + 2.5))


def grid_street_lines(scene: StreetScene) -> np.ndarray:
    """Centre-line positions of the grid layout's streets.

    The streets along x run at these local y, the streets along y at these local x (the grid is symmetric):
    ``GRID_STREETS`` lines evenly spread between ``_GRID_MARGIN_M`` and ``extent_m - _GRID_MARGIN_M``
    (12, 100 and 188 m for the default 200 m square).

    Parameters
    ----------
    scene : StreetScene
        Any layout; only ``extent_m`` is used.

    Returns
    -------
    (GRID_STREETS,) float64
        Local coordinates (m, without ``scene.origin``), increasing.
    """
    return np.linspace(_GRID_MARGIN_M, scene.extent_m - _GRID_MARGIN_M, GRID_STREETS)


def _street_to_local(axis: int, line: float, s, lateral) -> tuple[np.ndarray, np.ndarray]:
    """Local (x, y) of the point ``s`` along and ``lateral`` to the left of the street at ``line`` running
    along ``axis`` (0: +x, 1: +y); the y streets are the x streets turned +90 degrees, so "left" is -x there."""
    s = np.asarray(s, np.float64)
    lateral = np.asarray(lateral, np.float64)
    if axis == 0:
        return s, line + lateral
    return line - lateral, s


def _build_grid_scene(scene: StreetScene) -> Mesh:
    """The grid layout of :func:`build_street` (local x, y in ``[0, extent_m]``)."""
    E = scene.extent_m
    lines = grid_street_lines(scene)
    ph = _terrain_params(scene)
    h = lambda x, y: _terrain_analytic(ph, np.asarray(x, np.float64), np.asarray(y, np.float64))  # noqa: E731
    out = _Builder()
    # streets as (axis, centre line) in a fixed order: every random draw below happens in this order
    streets = [(axis, float(c)) for axis in (0, 1) for c in lines]

    def far_from_crossings(s: float, clearance: float) -> bool:
        # the crossing streets are at the same positions along either axis
        return bool(np.all(np.abs(s - lines) >= clearance))

    # ---- buildings: a row along each edge of every block. Rows along x run the block's full length between
    # the fronts of its two y streets; rows along y stop 26 m short of the x streets, beyond the deepest
    # x-row building (front <= 11 m + depth <= 14 m), so rows never meet; a row's buildings follow each other
    # with gaps, and a front is >= 10 m from its centre line (road 6 m, poles 6.6 m, trees 8.2 m).
    front_m, corner_m = 10.0, 26.0
    rng = _rng(scene, 2)
    footprints = []

    def row(axis: int, line: float, side: float, a0: float, a1: float) -> None:
        t = a0 + rng.uniform(0.0, 4.0)
        while t < a1 - 4.0:
            t1 = min(t + rng.uniform(8.0, 25.0), a1)
            front = front_m + rng.uniform(0.0, 1.0)
            back = front + rng.uniform(8.0, 14.0)
            height = rng.uniform(6.0, 20.0)
            extra = rng.random()
            gap = rng.uniform(8.0, 15.0) if rng.random() < 0.25 else rng.uniform(1.5, 6.0)
            if t1 - t >= 4.0:
                c0, c1 = (line + front, line + back) if side > 0 else (line - back, line - front)
                fp = (t, t1, c0, c1) if axis == 0 else (c0, c1, t, t1)
                footprints.append(fp)
                _add_building(out, h, *fp, height, extra < 0.4)
            t = t1 + gap

    for a in range(GRID_STREETS - 1):
        for b in range(GRID_STREETS - 1):
            xa, xb = float(lines[a]), float(lines[a + 1])
            ya, yb = float(lines[b]), float(lines[b + 1])
            row(0, ya, 1.0, xa + front_m, xb - front_m)   # facing the x street at ya
            row(0, yb, -1.0, xa + front_m, xb - front_m)  # facing the x street at yb
            row(1, xa, 1.0, ya + corner_m, yb - corner_m)   # facing the y street at xa
            row(1, xb, -1.0, ya + corner_m, yb - corner_m)  # facing the y street at xb

    # ---- terrain over the whole square, minus the triangles entirely inside a building (as for the street)
    tv, tf = _terrain_mesh(scene)
    tri = tv[tf]
    tmin, tmax = tri[..., :2].min(axis=1), tri[..., :2].max(axis=1)  # per-triangle xy box: 2 x (F, 2)
    keep = np.ones(len(tf), bool)
    for x0, x1, y0, y1 in footprints:
        keep &= ~((tmin[:, 0] > x0) & (tmax[:, 0] < x1) & (tmin[:, 1] > y0) & (tmax[:, 1] < y1))
    del tri, tmin, tmax
    used, inv = np.unique(tf[keep], return_inverse=True)
    out.add("terrain", tv[used], inv.reshape(-1, 3))

    # ---- poles along both curbs of every street, none in or at the corners of a crossing
    poles = set()
    rng = _rng(scene, 3)
    for k, (axis, line) in enumerate(streets):
        for side in (-1.0, 1.0):
            s = rng.uniform(3.0, 10.0)
            while s < E - 2.0:
                if far_from_crossings(s, 10.0):
                    x, y = _street_to_local(axis, line, s, side * 6.6)
                    z = float(h(x, y))
                    v, f = _cylinder(0.15, z - 0.3, z + 6.0)
                    out.add("pole", v + (float(x), float(y), 0.0), f)
                    poles.add((k, side, s))
                s += rng.uniform(20.0, 30.0)

    # ---- trees on the sidewalks, not too close to a pole; 12 m from a crossing keeps the crowns of two
    # streets' trees apart at the corners
    rng = _rng(scene, 4)
    crown = sphere(1.0, 2)
    crown_v, crown_f = crown.vertices, crown.faces
    for k, (axis, line) in enumerate(streets):
        for side in (-1.0, 1.0):
            def keep(s):
                return far_from_crossings(s, 12.0) and all(abs(s - ps) > 2.5 for pk, pside, ps in poles
                                                           if pk == k and pside == side)

            for s, trunk_h, r in _tree_row(rng, E, keep):
                x, y = (float(c) for c in _street_to_local(axis, line, s, side * 8.2))
                _add_tree(out, x, y, float(h(x, y)), trunk_h, r, crown_v, crown_f)

    # ---- cars: moving ones in the lanes, parked ones along the curbs, small random yaw; the crossings stay
    # empty (>= 9 m: a 6 m half-road plus half a car), so no two streets' cars meet
    rng = _rng(scene, 5)
    car_v, car_f = _car()
    car_f = _orient_outward(car_v, car_f)
    # footprint probe points (car frame): corners, edge midpoints and centre; the highest ground under them
    # sets the underbody, so a car never sinks into a terrain wave
    px, py = np.meshgrid([-2.25, 0.0, 2.25], [-0.9, 0.0, 0.9])
    probe = np.stack([px.ravel(), py.ravel()], 1)
    for axis, line in streets:
        for lane, p in ((-5.0, 0.5), (-3.0, 0.35), (3.0, 0.35), (5.0, 0.5)):
            s = rng.uniform(3.0, 10.0)
            while s < E - 3.0:
                place = rng.random() < p
                yaw = rng.uniform(-0.04, 0.04) + (np.pi if lane < 0 and rng.random() < 0.8 else 0.0)
                step = rng.uniform(7.0, 16.0)
                if place and far_from_crossings(s, 9.0):
                    yaw += 0.5 * np.pi * axis
                    c, sn = math.cos(yaw), math.sin(yaw)
                    rot = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
                    x, y = (float(v) for v in _street_to_local(axis, line, s, lane))
                    foot = probe @ rot[:2, :2].T + (x, y)
                    base = float(h(foot[:, 0], foot[:, 1]).max()) + _CAR_CLEARANCE
                    out.add("car", car_v @ rot.T + (x, y, base), car_f)
                s += step

    v, f, ranges = out.build()
    meta = {"generator": "tiled_gridpull.synthetic.street", "scene": scene.to_dict(), "face_classes": ranges,
            "units": "m"}
    return Mesh(v + scene.origin_array, f, meta)


def _tree_row(rng: np.random.Generator, length: float, keep: Callable[[float], bool]):
    """Trees along one side of a street of ``length`` m: yields ``(s, trunk height, crown radius)`` at the stations
    ``s`` that ``keep`` accepts. The random draws (first station, then height, radius and spacing per station) do
    not depend on ``keep``, so a layout's trees come out the same whatever it rejects."""
    s = rng.uniform(5.0, 12.0)
    while s < length - 3.0:
        trunk_h = rng.uniform(2.5, 4.0)
        r = rng.uniform(1.3, 2.2)
        step = rng.uniform(12.0, 18.0)
        if keep(s):
            yield s, trunk_h, r
        s += step


def _add_tree(out: _Builder, x: float, y: float, z: float, trunk_h: float, r: float, crown_v: np.ndarray,
              crown_f: np.ndarray) -> None:
    """A tree at ground point (x, y, z): a trunk (r = 0.18 m, sunk 0.3 m) and an icosphere crown of radius ``r``
    whose centre is ``trunk_h + 0.6 r`` above the ground (the trunk reaches half-way into it)."""
    v, f = _cylinder(0.18, z - 0.3, z + trunk_h + 0.5 * r, 12)
    out.add("tree", v + (x, y, 0.0), f)
    out.add("tree", crown_v * r + (x, y, z + trunk_h + 0.6 * r), crown_f)


def _add_box(out: _Builder, cls: str, lo, hi) -> None:
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    m = box(tuple(hi - lo), divisions=1)
    out.add(cls, m.vertices + 0.5 * (lo + hi), m.faces)


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
    ph = _rng(scene, 7).uniform(0.0, 2 * np.pi, (len(passes), 3))
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
        x, y = _street_to_local(axis, line, s, lateral)
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
    ph = _rng(scene, 6).uniform(0.0, 2 * np.pi, 3)
    y = 0.2 * np.sin(2 * np.pi * x / 31.0 + ph[0])
    yaw = 0.04 * np.sin(2 * np.pi * x / 17.0 + ph[1]) + 0.02 * np.sin(2 * np.pi * x / 7.3 + ph[2])
    return _poses_from(scene, x, y, yaw)


def hdl64_directions(beams: int = 64, azimuth_steps: int = 2000) -> np.ndarray:
    """Unit ray directions in the sensor frame, in firing order (azimuth-major, then beam top to bottom).

    Elevations are spread evenly over +2 .. -24.8 degrees; azimuth ``j`` is ``2 pi j / azimuth_steps``
    counter-clockwise from +x (forward).

    Returns
    -------
    (azimuth_steps * beams, 3) float64
    """
    el = np.deg2rad(np.linspace(ELEVATION_DEG[0], ELEVATION_DEG[1], int(beams)))
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
                seed: int = 0) -> Scan:
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
        Seed of the range noise only (the scene has its own).

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
    origin = scene.origin_array
    poses = sensor_poses(scene, n_frames, frame_spacing_m)
    local = poses.copy()
    local[:, :3, 3] -= origin
    # cast in local coordinates: float64 keeps ~1e-14 relative, i.e. ~1e-12 m, where UTM values would not
    caster = _RayCaster(mesh.vertices - origin, mesh.faces)
    dirs = hdl64_directions(beams, azimuth_steps)
    ray, xyz, t, face, refl = caster.cast(local, dirs, MIN_RANGE_M, float(max_range))
    frame = (ray // len(dirs)).astype(np.int32)
    sensor = local[frame, :3, 3]
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


# ====================================================================== writers
def write_las(path: str | Path, xyz: np.ndarray, *, intensity: np.ndarray | None = None,
              crs_wkt: str | None = None, chunk_size: int = 2_000_000) -> Path:
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
                writer.write_points(rec)
    return path


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


# ====================================================================== evaluation helper
def observed_samples(gt_mesh: Mesh, points: np.ndarray, n_samples: int, radius: float,
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform ground-truth samples that lie within ``radius`` of a scanned point.

    Evaluating completeness against the whole street would charge a reconstruction for surfaces no ray saw
    (roofs, building backs, car bottoms); this keeps only the observed part.

    Parameters
    ----------
    gt_mesh : Mesh
    points : (N, 3) array_like
        The scanned points (same coordinates as the mesh).
    n_samples : int
        Samples drawn on the whole mesh before the filter (fewer are returned).
    radius : float
        Maximum distance (mesh units) from a sample to its nearest scanned point.
    seed : int

    Returns
    -------
    samples : (M, 3) float64
    normals : (M, 3) float64
        Unit face normals of the kept samples.
    """
    from pykdtree.kdtree import KDTree

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise InputError("observed_samples needs at least one scanned point")
    samples, normals = sample_surface(gt_mesh, int(n_samples), seed)
    centre = np.floor(pts.min(axis=0))  # georeferenced inputs: query near zero for full precision
    dist, _ = KDTree(pts - centre).query(samples - centre, k=1, distance_upper_bound=float(radius))
    keep = np.isfinite(dist) & (dist <= radius)
    return samples[keep], normals[keep]


# ====================================================================== one-call sample
_FORMATS = ("laz", "las", "kitti")


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
                       extent_m: float = 200.0) -> dict:
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
    formats : sequence of {"laz", "las", "kitti"}
        ``street.laz`` / ``street.las`` (intensity = reflectance x 65535) and/or a ``kitti/`` sequence.
    range_noise : float
        Gaussian range noise (m).
    crs_wkt : str, optional
        Written into the LAS/LAZ header.
    layout : {"street", "grid"}
        See :class:`StreetScene`.
    extent_m : float
        Side of the grid's square (m); unused by the single street.

    Returns
    -------
    dict
        ``points`` (the first LAS/LAZ written, else None), ``laz`` / ``las`` / ``kitti`` paths when written,
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
    out_dir = Path(out_dir)
    if layout == "grid":
        scene = StreetScene(seed=seed, origin=tuple(origin), layout="grid", extent_m=extent_m)
        n_passes = len(grid_passes(scene))
        n_frames = grid_frames_for_points(n_points, n_passes)
    else:
        n_passes = 1
        n_frames = max(4, int(math.ceil(int(n_points) / 100_000)))
        scene = StreetScene(seed=seed, length_m=street_length_for_frames(n_frames), origin=tuple(origin))
    out_dir.mkdir(parents=True, exist_ok=True)
    mesh = build_street(scene)
    probe_steps = 200
    probe = scan_street(scene, mesh, n_frames, azimuth_steps=probe_steps)
    azimuth_steps = int(np.clip(round(probe_steps * int(n_points) / max(probe.n_points, 1)), 16, 4000))
    del probe  # freed before the full-resolution cast, which is what sets the peak memory
    scan = scan_street(scene, mesh, n_frames, azimuth_steps=azimuth_steps, range_noise=range_noise, seed=seed)
    result: dict = {"points": None}
    for fmt in ("laz", "las"):
        if fmt in formats:
            p = write_las(out_dir / f"street.{fmt}", scan.xyz,
                          intensity=np.round(scan.reflectance * 65535.0), crs_wkt=crs_wkt)
            result[fmt] = p
            result["points"] = result["points"] or p
    if "kitti" in formats:
        result["kitti"] = write_kitti_sequence(out_dir / "kitti", scan)
    result["gt_mesh"] = write_mesh(mesh, out_dir / "street_gt.ply")
    result.update(n_points=scan.n_points, n_frames=scan.n_frames, azimuth_steps=azimuth_steps,
                  n_faces=mesh.n_faces, scene=scene.to_dict(), range_noise=float(range_noise),
                  layout=scene.layout, n_passes=n_passes)
    meta = {k: (str(v) if isinstance(v, Path) else v) for k, v in result.items()}
    meta["face_classes"] = mesh.metadata["face_classes"]
    meta["sensor_height_m"] = SENSOR_HEIGHT_M
    result["meta"] = out_dir / "street.json"
    write_json(result["meta"], meta)
    return result
