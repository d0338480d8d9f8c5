"""OGC 3D Tiles 1.1 output: a tiled job's mesh as a tileset that a web viewer (CesiumJS, deck.gl, iTowns) streams.

Layout of a tileset directory::

    tileset.json            bounding volumes, geometric errors, the root transform (ENU frame -> earth-centred)
    tiles/tile_I_J_K.glb    one glTF 2.0 binary per job tile: the finest level, exactly the tile's mesh piece
    lod/lod_L_A_B.glb       coarser levels: the tiles of a 2^L x 2^L block of the tile grid, welded and simplified

The levels form a quadtree over the tile grid's (I, J) footprint: a level-L node holds the tiles whose indices
shifted right by L are (A, B), its children are the level L-1 nodes inside it, and level 1's children are the
tiles themselves (every K of the column); a coarse node alone in its block stands for the next level too (no
second simplification of the same tiles). The top level holds the whole scene in about as many triangles as one
tile, so a viewer opens a city block without loading every tile and refines (``REPLACE``) as it zooms in.
Each coarse node's geometric error is the simplification's measured deviation from the finest surface: the
larger of the farthest finest vertex from the simplified surface and the farthest simplified vertex from the
finest surface (metres), never below its children's; the finest tiles have 0.

Coordinates: every vertex goes from the input's CRS to earth-centred, earth-fixed coordinates (EPSG:4978) with
pyproj, then into the east-north-up (ENU) frame at the scene's centre; the root tile's ``transform`` is that
frame's ENU -> ECEF matrix. glTF is y-up, and 3D Tiles turns glTF content z-up on loading, so a glb stores (east,
up, -north) relative to its node's ``translation`` (the content's centre), which keeps float32 positions within a
few micrometres of the input (4 µm steps 32 m from the centre). A 2D projected CRS (LAS files usually declare one)
is taken to have heights in its horizontal unit above the ellipsoid; a compound CRS with a vertical datum goes
through pyproj's vertical transform (geoid grids when PROJ has them).

Vertex attributes (``mesh.vertex_attributes``, when a mesh has them): ``red``/``green``/``blue`` become
``COLOR_0`` (the sRGB values turned linear, as glTF defines COLOR_0, stored as normalized UNSIGNED_SHORT VEC4,
alpha 1); every other 1-D attribute (``intensity``, ``classification``, extras) becomes a custom glTF attribute
``_NAME`` (float32 scalar, exact for integers below 2^24) declared as an ``EXT_structural_metadata`` property
attribute of the class ``vertex``: the 3D Tiles 1.1 way of per-vertex properties, which CesiumJS reads in
custom shaders (``vsInput.metadata.intensity``) and styling. Coarse levels take each vertex's attributes from the
nearest finest vertex.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._optional import require
from ._version import __version__
from .errors import ConfigError, InputError
from .mesh import Mesh

log = logging.getLogger(__name__)

__all__ = ["Georeference", "TileMesh", "write_tileset", "write_glb", "read_glb", "georeference", "check_tileset_dir",
           "resolve_tileset_crs", "job_tiles",
           "TILESET_MARKER", "COLOR_NAMES"]

#: The generator text every tileset.json we write carries in ``asset.generator``.
TILESET_MARKER = "tiled_gridpull"
#: Attribute names that make COLOR_0.
COLOR_NAMES = ("red", "green", "blue")

# glTF constants
_FLOAT, _USHORT, _UINT = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_TRIANGLES = 4
# y-up glTF -> z-up 3D Tiles (the fixed transform of the 3D Tiles spec) and its inverse
_ZUP_TO_YUP = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # (e, n, u) -> (e, u, -n)


@dataclass(frozen=True)
class TileMesh:
    """One job tile's mesh for the tileset.

    Attributes
    ----------
    name : str
        ``tile_I_J_K`` (the job tile's name; the glb is ``tiles/<name>.glb``).
    index : (3,) tuple of int
        The tile's index in the job's tile grid.
    mesh : Mesh
        The tile's faces, vertices in the input's CRS (its ``vertex_attributes``, when present, go with them).
    """

    name: str
    index: tuple[int, int, int]
    mesh: Mesh


# ---------------------------------------------------------------------------------------------- georeferencing
@dataclass(frozen=True)
class Georeference:
    """The input CRS -> local ENU frame transform of a tileset.

    Attributes
    ----------
    crs : str
        The CRS as given (WKT or ``EPSG:XXXX``).
    origin : (3,) float64
        ECEF position of the frame's origin (metres).
    rotation : (3, 3) float64
        Columns: the east, north and up unit vectors in ECEF.
    z_factor : float
        Metres per height unit (a 2D projected CRS in feet has heights in feet).
    """

    crs: str
    origin: np.ndarray
    rotation: np.ndarray
    z_factor: float
    _crs3d: object
    _to_ecef: object
    _from_ecef: object

    @property
    def transform(self) -> np.ndarray:
        """(4, 4) float64 ENU -> ECEF matrix (row-major; the tileset stores it column-major)."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.origin
        return m

    def to_ecef(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) CRS coordinates -> (N, 3) ECEF metres."""
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        x, y, z = self._to_ecef.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2] * self.z_factor)
        out = np.column_stack([x, y, z]).astype(np.float64)
        if len(out) and not np.isfinite(out).all():
            raise InputError(f"3D Tiles: {crs_label(self.crs)} has coordinates pyproj cannot place on the earth "
                             "(check the CRS, or give --3d-tiles-crs)")
        return out

    def to_local(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) CRS coordinates -> (N, 3) ENU metres about :attr:`origin`."""
        return (self.to_ecef(xyz) - self.origin) @ self.rotation

    def from_local(self, enu: np.ndarray) -> np.ndarray:
        """(N, 3) ENU metres -> (N, 3) CRS coordinates (the inverse of :meth:`to_local`)."""
        ecef = np.asarray(enu, np.float64).reshape(-1, 3) @ self.rotation.T + self.origin
        x, y, z = self._from_ecef.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2])
        return np.column_stack([x, y, np.asarray(z) / self.z_factor])


def crs_label(crs: str) -> str:
    """A short name of a CRS for messages."""
    from .crs import crs_name

    return crs if re.fullmatch(r"[A-Za-z]+:\d+", crs.strip()) else crs_name(crs)


def parse_crs(crs: str, what: str = "--3d-tiles-crs"):
    """A pyproj CRS from WKT or ``AUTH:CODE`` text; :class:`ConfigError` in one line when pyproj cannot read it."""
    pyproj = require("pyproj", "3D Tiles output")
    try:
        return pyproj.CRS.from_user_input(crs)
    except pyproj.exceptions.CRSError:
        raise ConfigError(f"{what} {crs_label(str(crs))!r}: not a coordinate reference system pyproj knows "
                          "(give e.g. EPSG:32632)") from None


def georeference(crs: str, centre: Sequence[float]) -> Georeference:
    """The transform of a tileset whose mesh is in ``crs``, with the ENU frame's origin at ``centre``.

    Parameters
    ----------
    crs : str
        WKT (as LAS files declare it) or ``AUTH:CODE`` (``EPSG:32632``).
    centre : (3,) float
        A point in ``crs`` (the scene's centre), where the ENU frame is tangent to the ellipsoid.

    Raises
    ------
    ConfigError
        pyproj cannot read ``crs``, or it is an engineering (local) CRS with no place on the earth.
    """
    pyproj = require("pyproj", "3D Tiles output")
    c = parse_crs(crs)
    if not (c.is_projected or c.is_geographic or c.is_geocentric or c.is_compound):
        raise ConfigError(f"3D Tiles: {crs_label(crs)} places no point on the earth (a local, engineering or "
                          "vertical-only CRS); give --3d-tiles-crs with the CRS the coordinates are really in")
    z_factor = 1.0
    if len(c.axis_info) == 2:  # 2D: heights in the horizontal unit, above the ellipsoid
        if c.is_projected:
            z_factor = float(c.axis_info[0].unit_conversion_factor)
        c = c.to_3d()
    ecef = pyproj.CRS.from_epsg(4978)
    try:
        to_ecef = pyproj.Transformer.from_crs(c, ecef, always_xy=True)
        from_ecef = pyproj.Transformer.from_crs(ecef, c, always_xy=True)
    except pyproj.exceptions.ProjError as exc:  # e.g. a CRS of another celestial body
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(f"3D Tiles: pyproj cannot transform {crs_label(crs)} to earth-centred coordinates "
                          f"({reason})") from None
    centre = np.asarray(centre, np.float64).reshape(3)
    x, y, z = to_ecef.transform(centre[0], centre[1], centre[2] * z_factor)
    origin = np.array([x, y, z], np.float64)
    if not np.isfinite(origin).all():
        raise InputError(f"3D Tiles: the scene's centre {centre.tolist()} is not a place pyproj can transform "
                         f"from {crs_label(crs)}; check the CRS, or give --3d-tiles-crs")
    lon, lat, _ = pyproj.Transformer.from_crs(ecef, pyproj.CRS.from_epsg(4979), always_xy=True).transform(*origin)
    lo, la = math.radians(lon), math.radians(lat)
    east = np.array([-math.sin(lo), math.cos(lo), 0.0])
    north = np.array([-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)])
    up = np.array([math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)])
    return Georeference(str(crs), origin, np.column_stack([east, north, up]), z_factor, c, to_ecef, from_ecef)


# --------------------------------------------------------------------------------------------------- glb files
def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(V, 3) float32 unit area-weighted vertex normals ((0, 0, 1) where a vertex has none)."""
    n = np.zeros_like(v)
    if len(f):
        cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        for c in range(3):
            np.add.at(n, f[:, c], cross)
    norm = np.linalg.norm(n, axis=1)
    bad = ~(norm > 0)
    n[bad] = (0.0, 0.0, 1.0)
    norm[bad] = 1.0
    n = (n / norm[:, None]).astype(np.float32)
    # float32 rounding can leave a length 1 +- 1e-7: within the glTF validator's tolerance (5e-4)
    return n


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


@dataclass(frozen=True)
class _AttributePlan:
    """How a tileset writes vertex attributes: the colour scale and the custom attributes (same in every glb)."""

    color_max: float | None  # None: no COLOR_0
    custom: tuple[tuple[str, str], ...]  # (attribute name in the mesh, property name)

    def schema(self) -> dict | None:
        if not self.custom:
            return None
        return {"id": "tiled_gridpull_vertex",
                "classes": {"vertex": {"description": "per-vertex values carried from the input points",
                                       "properties": {prop: {"type": "SCALAR", "componentType": "FLOAT32"}
                                                      for _, prop in self.custom}}}}


def attribute_plan(meshes: Sequence[Mesh]) -> _AttributePlan:
    """Which attributes the tileset writes, decided over all its tiles (``COLOR_0`` when every tile has
    red, green and blue; a custom attribute for every other 1-D attribute every tile has)."""
    attrs = [getattr(m, "vertex_attributes", None) or {} for m in meshes]
    common = set(attrs[0]) if attrs else set()
    for a in attrs[1:]:
        common &= set(a)
    for a in attrs:
        for name in set(a) - common:
            log.warning("3D Tiles: vertex attribute %r is missing from some tiles; not written", name)
    color_max = None
    if all(n in common for n in COLOR_NAMES):
        dtypes = {np.asarray(a[n]).dtype for a in attrs for n in COLOR_NAMES}
        if all(np.issubdtype(d, np.integer) for d in dtypes):
            top = max((int(np.asarray(a[n]).max()) for a in attrs for n in COLOR_NAMES if len(a[n])), default=0)
            # 16-bit LAS colours that hold 8-bit values (many files): scaled as 8-bit
            color_max = 255.0 if all(d.itemsize == 1 for d in dtypes) or top <= 255 else 65535.0
        else:
            color_max = 1.0  # floats: taken as 0..1
    custom = []
    used = set()
    for name in sorted(common - set(COLOR_NAMES if color_max is not None else ())):
        if any(np.asarray(a[name]).ndim != 1 for a in attrs):
            log.warning("3D Tiles: vertex attribute %r is not one value per vertex; not written", name)
            continue
        prop = re.sub(r"\W", "_", name.lower())
        if not re.match(r"[a-z_]", prop):
            prop = "_" + prop
        while prop in used:
            prop += "_"
        used.add(prop)
        custom.append((name, prop))
    return _AttributePlan(color_max, tuple(custom))


def write_glb(mesh: Mesh, path: str | Path, local: np.ndarray, plan: _AttributePlan | None = None,
              extras: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Write one tile's content as a glb (pygltflib).

    Parameters
    ----------
    mesh : Mesh
        Faces (F, 3) and ``vertex_attributes`` (each (V,)); its vertices are not read (``local`` replaces them).
    path : path
        The glb file.
    local : (V, 3) float64
        The vertices in the tileset's ENU frame (metres, z up).
    plan : optional
        The attributes to write (default: decided from this mesh alone).
    extras : dict, optional
        Written as the glTF asset's ``extras``.

    Returns
    -------
    lo, hi : (3,) float64
        The ENU bounds of the positions as stored (float32 relative to the node's translation, added back).
    """
    gl = require("pygltflib", "3D Tiles output")
    plan = plan or attribute_plan([mesh])
    local = np.asarray(local, np.float64).reshape(-1, 3)
    centre = 0.5 * (local.min(axis=0) + local.max(axis=0)) if len(local) else np.zeros(3)
    rel_enu = (local - centre).astype(np.float32)
    pos = rel_enu @ _ZUP_TO_YUP.T.astype(np.float32)  # exact: a signed permutation
    stored = rel_enu.astype(np.float64) + centre
    normals = _vertex_normals(local - centre, mesh.faces) @ _ZUP_TO_YUP.T.astype(np.float32)
    attrs = getattr(mesh, "vertex_attributes", None) or {}

    blob = bytearray()
    views, accessors = [], []

    def add(array: np.ndarray, component: int, kind: str, target: int | None, normalized: bool = False,
            bounds: bool = False) -> int:
        data = np.ascontiguousarray(array).tobytes()
        offset = len(blob)
        blob.extend(data)
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append(gl.BufferView(buffer=0, byteOffset=offset, byteLength=len(data), target=target))
        acc = gl.Accessor(bufferView=len(views) - 1, componentType=component, count=int(len(array)), type=kind,
                          normalized=normalized or None)
        if bounds:
            acc.min = np.asarray(array).min(axis=0).astype(float).tolist()
            acc.max = np.asarray(array).max(axis=0).astype(float).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    attributes = gl.Attributes(POSITION=add(pos, _FLOAT, "VEC3", _ARRAY_BUFFER, bounds=True),
                               NORMAL=add(normals, _FLOAT, "VEC3", _ARRAY_BUFFER))
    if plan.color_max is not None:
        rgb = np.column_stack([np.asarray(attrs[n], np.float64) for n in COLOR_NAMES]) / plan.color_max
        lin = _srgb_to_linear(np.clip(rgb, 0.0, 1.0))
        rgba = np.column_stack([np.rint(lin * 65535.0), np.full(len(lin), 65535.0)]).astype(np.uint16)
        attributes.COLOR_0 = add(rgba, _USHORT, "VEC4", _ARRAY_BUFFER, normalized=True)
    prim_ext = {}
    if plan.custom:
        props = {}
        for name, prop in plan.custom:
            key = "_" + prop.upper().lstrip("_")
            setattr(attributes, key, add(np.asarray(attrs[name], np.float32), _FLOAT, "SCALAR", _ARRAY_BUFFER))
            props[prop] = {"attribute": key}
        prim_ext = {"EXT_structural_metadata": {"propertyAttributes": [0]}}
    indices = add(np.asarray(mesh.faces, np.uint32).reshape(-1), _UINT, "SCALAR", _ELEMENT_ARRAY_BUFFER,
                  bounds=False)
    prim = gl.Primitive(attributes=attributes, indices=indices, mode=_TRIANGLES, material=0,
                        extensions=prim_ext or {})
    translation = (_ZUP_TO_YUP @ centre).tolist()
    g = gl.GLTF2(
        asset=gl.Asset(version="2.0", generator=f"tiled_gridpull {__version__}", extras=extras or {}),
        scene=0, scenes=[gl.Scene(nodes=[0])],
        nodes=[gl.Node(mesh=0, translation=translation)],
        meshes=[gl.Mesh(primitives=[prim])],
        materials=[gl.Material(pbrMetallicRoughness=gl.PbrMetallicRoughness(
            baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=1.0), doubleSided=True)],
        accessors=accessors, bufferViews=views, buffers=[gl.Buffer(byteLength=len(blob))])
    if plan.custom:
        g.extensionsUsed = ["EXT_structural_metadata"]
        g.extensions = {"EXT_structural_metadata": {
            "schema": plan.schema(),
            "propertyAttributes": [{"class": "vertex",
                                    "properties": {prop: {"attribute": "_" + prop.upper().lstrip("_")}
                                                   for _, prop in plan.custom}}]}}
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(path))
    if len(stored):
        return stored.min(axis=0), stored.max(axis=0)
    return np.zeros(3), np.zeros(3)


def read_glb(path: str | Path) -> dict:
    """Read back a glb written by :func:`write_glb` (pygltflib): for tests and checks.

    Returns
    -------
    dict
        ``positions`` (V, 3) float64 ENU metres (z up, node translation applied), ``faces`` (F, 3) int64,
        ``attributes`` {glTF name: array}, ``gltf`` the pygltflib document.
    """
    gl = require("pygltflib", "3D Tiles output")
    g = gl.GLTF2().load_binary(str(path))
    blob = g.binary_blob()
    dtypes = {_FLOAT: np.float32, _USHORT: np.uint16, _UINT: np.uint32, 5121: np.uint8}
    widths = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}

    def get(i: int) -> np.ndarray:
        acc = g.accessors[i]
        view = g.bufferViews[acc.bufferView]
        dt = np.dtype(dtypes[acc.componentType])
        n = widths[acc.type]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        arr = np.frombuffer(blob, dt, count=acc.count * n, offset=start)
        return arr.reshape(acc.count, n) if n > 1 else arr

    prim = g.meshes[0].primitives[0]
    node = g.nodes[0]
    attrs = {k: get(v) for k, v in prim.attributes.__dict__.items() if v is not None}
    yup = attrs["POSITION"].astype(np.float64) + np.asarray(node.translation or [0, 0, 0], np.float64)
    positions = yup @ _ZUP_TO_YUP  # (e, u, -n) -> (e, n, u)
    faces = get(prim.indices).astype(np.int64).reshape(-1, 3)
    return {"positions": positions, "faces": faces, "attributes": attrs, "gltf": g}


# ---------------------------------------------------------------------------------------------- the tileset
def _padded(lo: np.ndarray, hi: np.ndarray, pad: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """[lo, hi] grown by ``pad`` metres (and a relative margin for rounding), never thinner than 2 cm."""
    c = 0.5 * (lo + hi)
    h = np.maximum(0.5 * (hi - lo) + pad + 1e-6 * np.abs(c), 0.01)
    return c - h, c + h


def _box(lo: np.ndarray, hi: np.ndarray) -> list[float]:
    """A 3D Tiles ``box`` (centre, three half-axes) of the axis-aligned box [lo, hi]."""
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return [*c.tolist(), h[0], 0.0, 0.0, 0.0, h[1], 0.0, 0.0, 0.0, h[2]]


def _weld(local: list[np.ndarray], faces: list[np.ndarray], attrs: list[dict]) -> tuple[np.ndarray, np.ndarray,
                                                                                            dict]:
    """Tiles' meshes as one: vertices at bit-identical positions (tile borders) merged."""
    base, fs = 0, []
    for v, f in zip(local, faces):
        fs.append(f + base)
        base += len(v)
    V = np.concatenate(local) if local else np.zeros((0, 3))
    F = np.concatenate(fs) if fs else np.zeros((0, 3), np.int64)
    uniq, first, inverse = np.unique(V, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    merged = {k: np.concatenate([a[k] for a in attrs])[first] for k in (attrs[0] if attrs else {})}
    return uniq, inverse[F], merged


def _simplify(v: np.ndarray, f: np.ndarray, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric decimation (fast-simplification) to about ``target_faces`` faces; the mesh as it is when it has
    no more than that."""
    fs = require("fast_simplification", "3D Tiles output (coarser levels of detail)")
    if len(f) <= target_faces or len(f) < 8:
        return v, f
    pts, tris = fs.simplify(np.ascontiguousarray(v, np.float64), np.ascontiguousarray(f, np.int32),
                            target_count=max(int(target_faces), 4), agg=7.0)
    tris = np.asarray(tris, np.int64).reshape(-1, 3)
    used, inverse = np.unique(tris, return_inverse=True)  # drop vertices no face uses
    return np.asarray(pts, np.float64)[used], inverse.reshape(-1, 3)


def _deviation(fine_v: np.ndarray, fine_f: np.ndarray, coarse_v: np.ndarray, coarse_f: np.ndarray,
               max_samples: int = 200_000, seed: int = 0) -> tuple[float, float]:
    """How far a simplified mesh strays from the finest one (metres).

    Returns
    -------
    hausdorff : float
        Symmetric vertex-to-surface Hausdorff distance: the larger of the farthest finest vertex from the coarse
        surface and the farthest coarse vertex from the finest surface (exact distances to the other surface; at
        most ``max_samples`` vertices of each side, chosen at random).
    p99 : float
        The 99th percentile of the finest vertices' distances to the coarse surface (small parts the
        simplification dropped make the maximum; this says how far the bulk of the surface moved).
    """
    from .metrics import point_to_mesh

    if len(coarse_f) == 0 or len(fine_f) == 0:
        return 0.0, 0.0
    rng = np.random.default_rng(seed)
    worst, p99 = 0.0, 0.0
    for side, (pts, v, f) in enumerate(((fine_v, coarse_v, coarse_f), (coarse_v, fine_v, fine_f))):
        if len(pts) > max_samples:
            pts = pts[rng.choice(len(pts), max_samples, replace=False)]
        d, _ = point_to_mesh(pts, Mesh(v, f))
        if len(d):
            worst = max(worst, float(d.max()))
            if side == 0:
                p99 = float(np.percentile(d, 99))
    return worst, p99


def check_tileset_dir(path: str | Path) -> None:
    """Refuse a ``--3d-tiles`` directory whose contents we did not write (before anything is solved).

    Raises
    ------
    ConfigError
        ``path`` is a file or a link, or a non-empty directory without a ``tileset.json`` of ours.
    """
    d = Path(path)
    if d.is_symlink():
        raise ConfigError(f"--3d-tiles {d} is a symbolic link: give the directory itself")
    if d.exists() and not d.is_dir():
        raise ConfigError(f"--3d-tiles {d} is a file, not a directory")
    if d.is_dir() and any(d.iterdir()) and not _ours(d / "tileset.json"):
        raise ConfigError(f"--3d-tiles {d} holds files tiled-gridpull did not write (no tileset.json of ours): "
                          "choose an empty or new directory")


def _ours(tileset: Path) -> bool:
    from .io.outputs import load_json_file

    try:
        if not tileset.is_file() or tileset.is_symlink():
            return False
        doc = load_json_file(tileset)
    except Exception:  # noqa: BLE001 - anything unreadable is not ours
        return False
    gen = doc.get("asset", {}).get("generator", "") if isinstance(doc, dict) else ""
    return isinstance(gen, str) and gen.startswith(TILESET_MARKER)


def write_tileset(tiles: Sequence[TileMesh], out_dir: str | Path, crs: str, *, metadata: dict | None = None,
                  crs_source: str = "input") -> dict:
    """Write ``tiles`` as a 3D Tiles 1.1 tileset in ``out_dir`` (replaced as a whole, never half-written).

    Parameters
    ----------
    tiles : sequence of TileMesh
        The job's tiles (empty ones are left out); their union is the job's mesh.
    out_dir : path
        The tileset directory: written beside it under a temporary name, then renamed into place; an earlier
        tileset of ours there is replaced, anything else refused (:func:`check_tileset_dir`).
    crs : str
        The CRS of the tiles' vertices (WKT or ``EPSG:XXXX``).
    metadata : dict, optional
        The job's record (``config``, ``tiling``, ``lattice``...): its settings go into the tileset's
        ``extras.tiled_gridpull``.
    crs_source : str
        Where ``crs`` came from (``input`` or ``--3d-tiles-crs``), recorded.

    Returns
    -------
    dict
        A summary: ``levels``, ``tiles``, ``nodes``, per-level ``geometric_error`` (metres) and ``faces``.

    Raises
    ------
    InputError
        No tile has faces.
    ConfigError
        ``out_dir`` is not ours to replace, or ``crs`` cannot be read.
    """
    tiles = [t for t in tiles if t.mesh.n_faces]
    if not tiles:
        raise InputError("3D Tiles: the mesh has no faces; nothing to write")
    out_dir = Path(out_dir)
    check_tileset_dir(out_dir)
    lo = np.min([t.mesh.vertices.min(axis=0) for t in tiles], axis=0)
    hi = np.max([t.mesh.vertices.max(axis=0) for t in tiles], axis=0)
    geo = georeference(crs, 0.5 * (lo + hi))
    plan = attribute_plan([t.mesh for t in tiles])
    glb_extras = {"generator": f"tiled_gridpull {__version__}", "crs": crs_label(crs)}

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=out_dir.parent))
    try:
        (tmp / "tiles").mkdir()
        (tmp / "lod").mkdir()
        # the finest level: one glb per tile, in the tile's own vertex order
        leaves = []
        for t in tiles:
            local = geo.to_local(t.mesh.vertices)
            lo_t, hi_t = _padded(*write_glb(t.mesh, tmp / "tiles" / f"{t.name}.glb", local, plan,
                                   {**glb_extras, "tile": t.name, "level": 0}))
            leaves.append({"name": t.name, "index": tuple(int(i) for i in t.index), "local": local,
                           "faces": t.mesh.faces, "attrs": dict(getattr(t.mesh, "vertex_attributes", None) or {}),
                           "lo": lo_t, "hi": hi_t,
                           "node": {"boundingVolume": {"box": _box(lo_t, hi_t)}, "geometricError": 0.0,
                                    "content": {"uri": f"tiles/{t.name}.glb"}}})
        ij = np.array([leaf["index"][:2] for leaf in leaves], np.int64)
        ij0 = ij - ij.min(axis=0)
        span = int(ij0.max()) + 1
        levels = max(1, math.ceil(math.log2(span))) if span > 1 else 1
        faces_per_leaf = max(int(np.median([len(leaf["faces"]) for leaf in leaves])), 64)
        summary_levels = [{"level": 0, "nodes": len(leaves), "faces": int(sum(len(x["faces"]) for x in leaves)),
                           "geometric_error": 0.0, "deviation_p99": 0.0}]
        # coarser levels: group by (I, J) >> L
        nodes_below = [{"key": tuple(k), "leaves": [i], "node": leaf["node"], "error": 0.0, "p99": 0.0,
                        "lo": leaf["lo"], "hi": leaf["hi"]} for i, (k, leaf) in enumerate(zip(ij0, leaves))]
        for level in range(1, levels + 1):
            groups: dict[tuple, list] = {}
            for nb in nodes_below:
                key = (int(nb["key"][0]) >> 1, int(nb["key"][1]) >> 1)
                groups.setdefault(key, []).append(nb)
            made, errors, p99s, n_faces = [], [], [], 0
            for key, kids in sorted(groups.items()):
                if len(kids) == 1 and level > 1:  # a coarse node alone in its block: it is this level's too
                    made.append({**kids[0], "key": key})
                    errors.append(kids[0]["error"])
                    p99s.append(kids[0]["p99"])
                    n_faces += kids[0]["faces"]
                    continue
                members = sorted({i for k in kids for i in k["leaves"]})
                fv, ff, fa = _weld([leaves[i]["local"] for i in members], [leaves[i]["faces"] for i in members],
                                   [leaves[i]["attrs"] for i in members])
                cv, cf = _simplify(fv, ff, faces_per_leaf)
                hausdorff, p99 = _deviation(fv, ff, cv, cf)
                error = max(hausdorff, max(k["error"] for k in kids))
                p99s.append(p99)
                ca = _nearest_attributes(fv, fa, cv)
                name = f"lod_{level}_{key[0]}_{key[1]}"
                lo_n, hi_n = write_glb(_with_attributes(Mesh(cv, cf), ca), tmp / "lod" / f"{name}.glb", cv, plan,
                                       {**glb_extras, "level": level, "geometric_error": error})
                lo_all, hi_all = _padded(np.min([lo_n, *[k["lo"] for k in kids]], axis=0),
                                         np.max([hi_n, *[k["hi"] for k in kids]], axis=0))
                node = {"boundingVolume": {"box": _box(lo_all, hi_all)}, "geometricError": error,
                        "content": {"uri": f"lod/{name}.glb"}, "children": [k["node"] for k in kids]}
                made.append({"key": key, "leaves": members, "node": node, "error": error, "lo": lo_all,
                             "hi": hi_all, "faces": len(cf), "p99": p99})
                errors.append(error)
                n_faces += len(cf)
            summary_levels.append({"level": level, "nodes": len(made), "faces": n_faces,
                                   "geometric_error": float(max(errors)), "deviation_p99": float(max(p99s))})
            nodes_below = made
        (root,) = nodes_below
        root_node = dict(root["node"])
        root_node["refine"] = "REPLACE"
        root_node["transform"] = geo.transform.flatten(order="F").tolist()  # column-major
        diagonal = float(np.linalg.norm(root["hi"] - root["lo"]))
        settings = {k: (metadata or {}).get(k) for k in ("config", "tiling", "lattice") if k in (metadata or {})}
        summary = {"levels": levels, "tiles": len(leaves), "per_level": summary_levels, "crs": crs_label(crs),
                   "crs_source": crs_source, "origin_ecef": geo.origin.tolist(),
                   "attributes": {"COLOR_0": plan.color_max is not None,
                                  "custom": {f"_{prop.upper().lstrip('_')}": name for name, prop in plan.custom}}}
        doc = {"asset": {"version": "1.1", "generator": f"{TILESET_MARKER} {__version__}",
                         "tilesetVersion": __version__},
               "geometricError": max(diagonal, root["error"]),
               "root": root_node,
               "extras": {"tiled_gridpull": {"version": __version__, "generator": f"tiled_gridpull {__version__}",
                                             "crs_wkt_or_code": crs, **summary, **settings}}}
        with open(tmp / "tileset.json", "w") as fh:
            json.dump(doc, fh, indent=1, default=_json_default)
        _swap_into_place(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return summary


def _with_attributes(mesh: Mesh, attrs: dict) -> Mesh:
    """``mesh`` carrying ``attrs`` as its ``vertex_attributes`` (set after construction: a Mesh made before the
    field existed takes it as a plain attribute)."""
    mesh.vertex_attributes = attrs
    return mesh


def _nearest_attributes(fine_v: np.ndarray, fine_attrs: dict, coarse_v: np.ndarray) -> dict:
    """Each coarse vertex's attributes: those of the nearest fine vertex."""
    if not fine_attrs or not len(coarse_v):
        return {}
    from pykdtree.kdtree import KDTree

    _, idx = KDTree(np.ascontiguousarray(fine_v)).query(np.ascontiguousarray(coarse_v), k=1)
    return {k: np.asarray(a)[idx.astype(np.int64)] for k, a in fine_attrs.items()}


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")


def _swap_into_place(tmp: Path, out_dir: Path) -> None:
    """Rename the finished ``tmp`` directory to ``out_dir``; an earlier tileset there is removed after."""
    os.chmod(tmp, 0o777 & ~_umask())
    old = None
    if out_dir.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".old", dir=out_dir.parent))
        os.rmdir(old)
        os.replace(out_dir, old)
    try:
        os.replace(tmp, out_dir)
    except BaseException:
        if old is not None:
            os.replace(old, out_dir)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def resolve_tileset_crs(inputs: Sequence[str], crs_option: str | None = None) -> tuple[str, str]:
    """The CRS a tileset of these inputs is georeferenced from, checked before anything is solved.

    Parameters
    ----------
    inputs : sequence of str
        The job's inputs (their headers are read for the CRS they declare).
    crs_option : str, optional
        A CRS the user gives (``--3d-tiles-crs``): used instead of the inputs'.

    Returns
    -------
    crs, source : str
        The CRS (WKT or ``AUTH:CODE``) and where it came from (``--3d-tiles-crs`` or ``input``).

    Raises
    ------
    ConfigError
        No CRS: the inputs declare none and none is given; or pyproj cannot read the one given.
    MissingDependencyError
        pyproj, pygltflib or fast-simplification is not installed.
    """
    for module in ("pyproj", "pygltflib", "fast_simplification"):
        require(module, "3D Tiles output")
    if crs_option:
        parse_crs(crs_option)
        return str(crs_option), "--3d-tiles-crs"
    from .io import read_crs

    crs = next((c for c in map(read_crs, inputs) if c), None)
    if not crs:
        raise ConfigError(f"--3d-tiles needs a coordinate reference system and {inputs[0]} declares none: give "
                          "--3d-tiles-crs (e.g. EPSG:32632)")
    parse_crs(crs, "the input's CRS")
    return crs, "input"


def job_tiles(pieces: Sequence[tuple[str, Sequence[int], object]]) -> list[TileMesh]:
    """The tiles of a finished job from its mesh pieces.

    Parameters
    ----------
    pieces : sequence of (name, index, piece)
        Each tile's name, index and piece: a :class:`~tiled_gridpull.stitch.MeshPiece` or its file
        (:func:`tiled_gridpull.stitch.save_piece`).
    """
    from .stitch import load_piece

    out = []
    for name, index, piece in pieces:
        if isinstance(piece, (str, Path)):
            piece = load_piece(piece)
        mesh = Mesh(piece.vertices, piece.faces)
        # the piece's per-vertex values, under either name (MeshPiece.attributes, Mesh.vertex_attributes)
        attrs = getattr(piece, "attributes", None) or getattr(piece, "vertex_attributes", None)
        if attrs:
            mesh = _with_attributes(mesh, dict(attrs))
        out.append(TileMesh(name, tuple(int(i) for i in index), mesh))
    return out
