"""Mesh files: binary PLY and OBJ out; PLY, OBJ and OFF in.

Written PLY files hold float64 vertices by default (exact georeferenced coordinates). With ``float32=True`` the
vertices are stored relative to an offset recorded in the header (``comment offset x y z``) and in the
metadata, which keeps millimetres at UTM magnitudes in half the size.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..mesh import Mesh, colors_unit
from .atomic import atomic_open

__all__ = ["read_mesh", "write_mesh"]


def write_mesh(mesh: Mesh, path: str | Path, *, float32: bool = False, offset: np.ndarray | None = None) -> Path:
    """Write a mesh as binary little-endian PLY (``.ply``) or OBJ (``.obj``), atomically.

    Vertex attributes (:attr:`Mesh.vertex_attributes`) go into a PLY as vertex properties after ``x y z``, in
    their own type: ``red green blue`` (uchar or ushort), ``intensity``, ``classification`` (uchar), extra
    dimensions under their names (characters other than letters, digits and ``_`` become ``_``; 64-bit integers
    are written as double, which PLY has instead). An OBJ has room for colour only: ``v x y z r g b`` with
    ``r g b`` in [0, 1] (:func:`~tiled_gridpull.mesh.color_full_scale`), the extension MeshLab, Open3D and
    trimesh read.

    Parameters
    ----------
    mesh : Mesh
    path : str or Path
    float32 : bool
        PLY only: float32 vertices relative to ``offset`` (default: the bounding-box minimum rounded to
        metres), offset written in the header.
    offset : (3,) float, optional
    """
    path = Path(path)
    mode = _mesh_mode(path)
    with atomic_open(path, mode) as fh:
        _write_to(fh, mesh, path, float32, offset)
    return path


def write_mesh_and_sidecar(mesh: Mesh, path: str | Path, *, float32: bool = False) -> Path:
    """Write a mesh and its JSON sidecar (``mesh.metadata``) as one commit: both files or neither.

    Both are written to temporary files first; the sidecar is renamed into place, then the mesh. A sidecar that
    cannot be written (disk full, a directory at its name) leaves no mesh behind.
    """
    from .atomic import dump_json

    path = Path(path)
    with atomic_open(path, _mesh_mode(path)) as fm:
        _write_to(fm, mesh, path, float32, None)
        with atomic_open(sidecar_path(path), "w") as fs:
            dump_json(fs, mesh.metadata)
    return path


def _mesh_mode(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".obj"):
        raise InputError(f"{path}: unknown mesh format '{suffix}' (use .ply or .obj)")
    return "wb" if suffix == ".ply" else "w"


def _write_to(fh, mesh: Mesh, path: Path, float32: bool, offset) -> None:
    if path.suffix.lower() == ".ply":
        _write_ply(mesh, fh, float32, offset)
    else:
        _write_obj(mesh, fh)


def _write_ply(mesh: Mesh, fh, float32: bool, offset) -> None:
    V = mesh.vertices
    comments = []
    if float32:
        if offset is None:
            offset = np.floor(V.min(axis=0)) if len(V) else np.zeros(3)
        offset = np.asarray(offset, dtype=np.float64)
        verts = (V - offset).astype("<f4")
        vtype = "float"
        comments.append("offset {:.6f} {:.6f} {:.6f}".format(*offset))
    else:
        verts = V.astype("<f8")
        vtype = "double"
    for key in ("generator", "crs"):
        if mesh.metadata.get(key):
            # one header line, ASCII: a pretty-printed WKT is joined, a non-ASCII name (Réseau, ...) keeps its
            # place with '?' (the sidecar holds the exact text)
            text = " ".join(part.strip() for part in str(mesh.metadata[key]).splitlines() if part.strip())
            comments.append(f"{key} {text.encode('ascii', 'replace').decode('ascii')}")
    if float32 and "generator" not in mesh.metadata:
        # the offset is trusted on reading only beside this package's marker (see ply_offset)
        comments.append("generator tiled_gridpull.io")
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {c}" for c in comments]
    props = _ply_attribute_props(mesh.vertex_attributes)
    header += [f"element vertex {len(V)}", f"property {vtype} x", f"property {vtype} y", f"property {vtype} z"]
    header += [f"property {ptype} {name}" for name, ptype, _, _ in props]
    header += [f"element face {len(mesh.faces)}", "property list uchar int vertex_indices", "end_header"]
    faces = np.empty(len(mesh.faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    faces["n"] = 3
    faces["v"] = mesh.faces
    fh.write(("\n".join(header) + "\n").encode("ascii"))
    if props:
        rows = np.empty(len(V), dtype=[("xyz", verts.dtype, (3,))] + [(name, dt) for name, _, dt, _ in props])
        rows["xyz"] = verts
        for name, _, dt, values in props:
            rows[name] = values.astype(dt)
        fh.write(rows.tobytes())
    else:
        fh.write(np.ascontiguousarray(verts).tobytes())
    fh.write(faces.tobytes())


#: numpy type kind and size -> PLY scalar type
_PLY_SCALAR = {("u", 1): "uchar", ("i", 1): "char", ("u", 2): "ushort", ("i", 2): "short", ("u", 4): "uint",
               ("i", 4): "int", ("f", 4): "float", ("f", 8): "double", ("b", 1): "uchar"}


def _ply_attribute_props(attributes: dict) -> list[tuple[str, str, str, np.ndarray]]:
    """``(property name, PLY type, little-endian numpy type, values)`` of each vertex attribute."""
    out, seen = [], {"x", "y", "z"}
    for name, values in attributes.items():
        values = np.asarray(values)
        prop = "".join(ch if ch.isascii() and (ch.isalnum() or ch == "_") else "_" for ch in name) or "_"
        while prop in seen:
            prop += "_"
        seen.add(prop)
        key = (values.dtype.kind, values.dtype.itemsize)
        ptype = _PLY_SCALAR.get(key, "double")
        np_type = "<f8" if ptype == "double" else ("u1" if key == ("b", 1) else "<" + values.dtype.kind
                                                   + str(values.dtype.itemsize))
        out.append((prop, ptype, np_type, values))
    return out


def _write_obj(mesh: Mesh, fh) -> None:
    # the marker io.outputs looks for before replacing a file (one line, like the PLY header's comment)
    gen = str(mesh.metadata.get("generator", "tiled_gridpull")).splitlines()[0]
    fh.write(f"# generator {gen}\n")
    rgb = colors_unit(mesh.vertex_attributes)
    if rgb is None:
        np.savetxt(fh, mesh.vertices, fmt="v %.17g %.17g %.17g")
    else:
        np.savetxt(fh, np.column_stack([mesh.vertices, rgb]), fmt="v %.17g %.17g %.17g %.6g %.6g %.6g")
    np.savetxt(fh, mesh.faces + 1, fmt="f %d %d %d")


def read_mesh(path: str | Path) -> Mesh:
    """Read a triangle mesh (PLY, OBJ, OFF); polygons are fan-triangulated.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Mesh
        ``vertices`` (V, 3) float64 (a float32 PLY written by this package gets its recorded offset back),
        ``faces`` (F, 3) int64; a PLY's other scalar vertex properties (colour, intensity, classification, ...)
        in ``vertex_attributes``, in their own type.

    Raises
    ------
    InputError
        One line naming the file and the problem (missing, unreadable, not a mesh, damaged).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    suffix = path.suffix.lower()
    attrs: dict = {}
    try:
        if suffix == ".ply":
            V, F, attrs = _read_ply(path)
        elif suffix == ".obj":
            V, F = _read_obj(path)
        elif suffix == ".off":
            V, F = _read_off(path)
        else:
            raise InputError(f"{path}: unknown mesh format '{suffix}' (expected .ply, .obj or .off)")
    except InputError:
        raise
    except Exception as exc:  # malformed files raise anything from the parsers
        detail = str(exc).splitlines()[0] if str(exc) else "malformed"
        raise InputError(f"{path}: cannot read mesh ({exc.__class__.__name__}: {detail})") from None
    if len(V) == 0:
        raise InputError(f"{path}: mesh has no vertices")
    if len(F) == 0:
        raise InputError(f"{path}: mesh has no faces")
    if F.min() < 0 or F.max() >= len(V):
        raise InputError(f"{path}: face indices out of range")
    if not np.all(np.isfinite(V)):
        raise InputError(f"{path}: mesh has non-finite vertex coordinates")
    return Mesh(V, F, {"source": str(path)}, attrs)


def _fan(polys) -> np.ndarray:
    tris = []
    for poly in polys:
        poly = list(poly)
        for t in range(1, len(poly) - 1):
            tris.append((poly[0], poly[t], poly[t + 1]))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _read_ply(path: Path):
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise InputError(f"{path}: PLY has no vertex element")
    v = ply["vertex"].data
    V = np.column_stack([np.asarray(v[a], dtype=np.float64) for a in ("x", "y", "z")])
    offset = ply_offset(ply.comments, str(path))
    if offset is not None:
        V = V + offset
    attrs = {}
    for name in v.dtype.names:
        if name in ("x", "y", "z", "nx", "ny", "nz") or v.dtype[name].shape or v.dtype[name].kind not in "uifb":
            continue
        col = np.asarray(v[name])
        attrs[name] = col.astype(col.dtype.newbyteorder("="))
    if "face" not in names:
        return V, np.zeros((0, 3), np.int64), attrs
    fdata = ply["face"].data
    key = "vertex_indices" if "vertex_indices" in fdata.dtype.names else fdata.dtype.names[0]
    polys = fdata[key]
    try:
        F = np.vstack(polys).astype(np.int64)
        if F.shape[1] != 3:
            F = _fan(polys)
    except ValueError:
        F = _fan(polys)
    return V, F, attrs


def ply_offset(comments: list[str], where: str = "PLY") -> np.ndarray | None:
    """The base point of a PLY written by :func:`write_mesh` with ``float32=True`` (vertices are relative to it):
    its ``comment offset x y z``, trusted only beside this package's ``comment generator tiled_gridpull...``
    (another tool's comment of that form means something else, or nothing).

    Beside our marker the offset is applied to every vertex, so one that is not 3 finite numbers within
    :data:`~tiled_gridpull.cloud.COORDINATE_LIMIT` is damage (never written by :func:`write_mesh`): refused
    with an :class:`InputError` naming it and ``where`` (the file), rather than ignored (vertices off by the
    offset) or applied (sums over the points overflow).
    """
    from .input_errors import check_frame

    words = [c.split() for c in comments]
    if not any(len(w) >= 2 and w[0] == "generator" and w[1].startswith("tiled_gridpull") for w in words):
        return None
    for parts in words:
        if parts and parts[0] == "offset":
            written = " ".join(parts[1:])
            try:
                off = np.array([float(x) for x in parts[1:]])
            except ValueError:
                off = np.full(3, np.nan)
            check_frame(f"{where}: the PLY header's", off if off.shape == (3,) else np.full(3, np.nan),
                        written=written)
            return off
    return None


def _read_obj(path: Path):
    verts, polys = [], []
    with open(path, errors="replace") as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                idx = [int(tok.split("/")[0]) for tok in line.split()[1:]]
                polys.append(idx)
    V = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    fixed = [[i - 1 if i > 0 else len(V) + i for i in p] for p in polys]
    return V, _fan(fixed)


def _read_off(path: Path):
    with open(path, errors="replace") as fh:
        tokens = [ln for ln in (l.split("#")[0].strip() for l in fh) if ln]
    if not tokens or not tokens[0].startswith("OFF"):
        raise InputError(f"{path}: not an OFF file")
    head = tokens[0][3:].split() or tokens.pop(1).split()
    nv, nf = int(head[0]), int(head[1])
    body = tokens[1:]
    V = np.array([[float(x) for x in body[i].split()[:3]] for i in range(nv)], dtype=np.float64)
    polys = [[int(x) for x in body[nv + i].split()[1:]] for i in range(nf)]
    return V, _fan(polys)


def sidecar_path(mesh_path: str | Path) -> Path:
    """Path of the JSON sidecar written beside a mesh (``mesh.ply`` -> ``mesh.json``)."""
    return Path(mesh_path).with_suffix(".json")


def write_sidecar(mesh_path: str | Path, metadata: dict) -> Path:
    """Write the self-describing JSON beside a mesh (atomically)."""
    from .atomic import write_json

    p = sidecar_path(mesh_path)
    write_json(p, metadata)
    return p


def read_sidecar(mesh_path: str | Path) -> dict:
    """Read the JSON sidecar of a mesh."""
    return json.loads(sidecar_path(mesh_path).read_text())
