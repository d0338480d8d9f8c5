"""A synthetic street (or a grid of streets) with an exact ground-truth mesh: the scene geometry.

The scene (:func:`build_street`) is a street along +x in a local frame: x in ``[0, length_m]``, y in
``[-width_m/2, width_m/2]`` (the road centre line at y = 0), z up, all in metres. Every output coordinate has
``scene.origin`` added (e.g. UTM-like ``(500000, 4000000, 100)``), so georeferenced code paths are exercised.

Layout of the scene (local frame): road ``|y| < 6`` with moving cars at ``|y| = 3`` and parked cars at
``|y| = 5``; poles at ``|y| = 6.6``; trees at ``|y| = 8.2``; building fronts from ``|y| = 10`` back to at most
``width_m/2 - 0.5``. Objects are separate closed pieces that sit on or sink into the terrain; the ground truth
is the union of all surfaces (some of it, e.g. building floors and car bottoms, is never observed: restrict
evaluation with :func:`~tiled_gridpull.synthetic.observed.observed_samples`).

``StreetScene(layout="grid")`` is a wide-area variant: a square ``extent_m`` x ``extent_m`` district (x and y
in ``[0, extent_m]``) crossed by ``GRID_STREETS`` streets along x and as many along y
(:func:`grid_street_lines`; 88 m apart for the default 200 m), each with the cross-section above (road, cars,
poles, trees). Buildings line the four edges of every city block between the streets, nothing stands in the
crossings, and the terrain sheet covers the whole square. The sensor drives every street in turn, one pass per
street, back and forth like a mapping car covering the district
(:func:`~tiled_gridpull.synthetic.lidar.sensor_poses`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from ..mesh import Mesh
from .shapes import box, sphere

__all__ = ["StreetScene", "build_street", "terrain_height", "grid_street_lines", "street_to_local",
           "scene_rng",
           "FACE_CLASSES", "LAYOUTS", "GRID_STREETS", "TERRAIN_STEP_M"]

TERRAIN_STEP_M = 0.5  # terrain triangulation spacing
FACE_CLASSES = ("terrain", "building", "pole", "tree", "car")
LAYOUTS = ("street", "grid")
GRID_STREETS = 3  # grid layout: streets along x, and as many along y
# the outermost centre lines stay this far inside the square, so their outer sidewalks, poles and whole tree
# crowns (8.2 m + 2.2 m radius from the centre line) lie inside it too
_GRID_MARGIN_M = 12.0
_GRID_MIN_EXTENT_M = 150.0  # blocks of >= 63 m between centre lines: two facing 25 m rows of buildings fit


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


def scene_rng(scene: StreetScene, stream: int) -> np.random.Generator:
    """The scene's random generator for one purpose (``stream``: 1 terrain, 2-5 objects, 6-7 trajectories)."""
    # independent streams per purpose, so adding an object kind never shifts the terrain or the poses
    return np.random.default_rng([scene.seed, stream])


def _terrain_params(scene: StreetScene) -> np.ndarray:
    return scene_rng(scene, 1).uniform(0.0, 2 * np.pi, 5)


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
    rng = scene_rng(scene, 2)

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
    rng = scene_rng(scene, 3)
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
    rng = scene_rng(scene, 4)
    crown = sphere(1.0, 2)
    crown_v, crown_f = crown.vertices, crown.faces
    for side in (-1.0, 1.0):
        for x, trunk_h, r in _tree_row(rng, L, lambda x: all(abs(x - px) > 2.5 or ps != side for px, ps in poles)):
            y = side * 8.2
            _add_tree(out, x, y, float(h(x, y)), trunk_h, r, crown_v, crown_f)

    # ---- cars: moving ones in the lanes, parked ones along the curbs, small random yaw
    rng = scene_rng(scene, 5)
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


def street_to_local(axis: int, line: float, s, lateral) -> tuple[np.ndarray, np.ndarray]:
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
    rng = scene_rng(scene, 2)
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
    rng = scene_rng(scene, 3)
    for k, (axis, line) in enumerate(streets):
        for side in (-1.0, 1.0):
            s = rng.uniform(3.0, 10.0)
            while s < E - 2.0:
                if far_from_crossings(s, 10.0):
                    x, y = street_to_local(axis, line, s, side * 6.6)
                    z = float(h(x, y))
                    v, f = _cylinder(0.15, z - 0.3, z + 6.0)
                    out.add("pole", v + (float(x), float(y), 0.0), f)
                    poles.add((k, side, s))
                s += rng.uniform(20.0, 30.0)

    # ---- trees on the sidewalks, not too close to a pole; 12 m from a crossing keeps the crowns of two
    # streets' trees apart at the corners
    rng = scene_rng(scene, 4)
    crown = sphere(1.0, 2)
    crown_v, crown_f = crown.vertices, crown.faces
    for k, (axis, line) in enumerate(streets):
        for side in (-1.0, 1.0):
            def keep(s):
                return far_from_crossings(s, 12.0) and all(abs(s - ps) > 2.5 for pk, pside, ps in poles
                                                           if pk == k and pside == side)

            for s, trunk_h, r in _tree_row(rng, E, keep):
                x, y = (float(c) for c in street_to_local(axis, line, s, side * 8.2))
                _add_tree(out, x, y, float(h(x, y)), trunk_h, r, crown_v, crown_f)

    # ---- cars: moving ones in the lanes, parked ones along the curbs, small random yaw; the crossings stay
    # empty (>= 9 m: a 6 m half-road plus half a car), so no two streets' cars meet
    rng = scene_rng(scene, 5)
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
                    x, y = (float(v) for v in street_to_local(axis, line, s, lane))
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
