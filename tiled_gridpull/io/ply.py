"""PLY point clouds: our own header parser (size checks before any read), memory-mapped binary vertices,
numpy's parser for ASCII vertices, plyfile for the rest (list properties before the vertices)."""

from __future__ import annotations

import io
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cloud import PointCloud, unit_normals
from ..errors import InputError
from .meshes import ply_offset

__all__ = ["read", "chunks", "count"]


def read(p: Path) -> PointCloud:
    """The whole vertex element of ``p`` as a cloud (normals and intensity when present)."""
    cols, n = _ply_vertex_columns(p)
    return _ply_cloud(p, cols, slice(0, n), str(p))


def chunks(p: Path, chunk_size: int) -> Iterator[PointCloud]:
    """Vertices in slices of ``chunk_size`` rows; binary ones stay memory-mapped (one chunk in float64)."""
    cols, n = _ply_vertex_columns(p)
    for start in range(0, n, chunk_size):
        stop = min(start + chunk_size, n)
        part = _ply_cloud(p, cols, slice(start, stop), f"{p}[{start}:{stop}]")
        part.report = {"points_read": stop - start}
        yield part


def count(p: Path) -> int:
    """The vertex count of the header."""
    hdr = _ply_header(p)
    return _ply_vertex_element(p, hdr).count


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


def _ply_cloud(p: Path, cols: dict, rows: slice, source: str) -> PointCloud:
    xyz = np.column_stack([np.asarray(cols[a][rows], dtype=np.float64) for a in ("x", "y", "z")])
    if "__offset__" in cols:
        xyz += cols["__offset__"]
    normals = None
    if all(a in cols for a in ("nx", "ny", "nz")):
        normals = unit_normals(np.column_stack([np.asarray(cols[a][rows], dtype=np.float64)
                                                 for a in ("nx", "ny", "nz")]))
    attrs = {}
    for name in ("intensity", "scalar_intensity"):
        if name in cols:
            attrs["intensity"] = np.asarray(cols[name][rows], dtype=np.float32)
            break
    # colour in the type the header declares (uchar: 8-bit, ushort: 16-bit), as Open3D and CloudCompare write it
    for prefix in ("", "diffuse_"):
        if all(prefix + c in cols for c in ("red", "green", "blue")):
            for c in ("red", "green", "blue"):
                values = np.asarray(cols[prefix + c][rows])
                attrs[c] = values.astype(values.dtype.newbyteorder("="))
            break
    for name in ("classification", "scalar_classification"):
        if name in cols:
            values = np.asarray(cols[name][rows], dtype=np.float64)
            attrs["classification"] = np.clip(np.nan_to_num(values), 0, 255).astype(np.uint8)
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
        # integer properties (colour, classification) in their declared type, as the binary paths give them
        cols = {a: table[:, j].astype(pr.type) if np.dtype(pr.type).kind in "ui" else table[:, j]
                for j, (a, pr) in enumerate(zip(names, vertex.props))}
    else:
        cols = _ply_vertex_plyfile(p, n)
    offset = ply_offset(hdr.comments, str(p))
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

