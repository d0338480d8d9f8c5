"""Cloud-optimized point clouds read by region: COPC (``*.copc.laz``) and Entwine Point Tiles (``ept.json``).

Both store the points in the nodes of an octree over a cube, with a hierarchy that lists every node's key
(depth, x, y, z) and point count. :func:`read_index` reads the header and the hierarchy only (no point), which is
what a tile plan and a dry run need; :func:`read_box` reads the points of the nodes that overlap a box, which is
what a tile task on a worker needs. Points come in one fixed order, the **stream order**: a COPC file's own
order (nodes by file offset), an EPT's nodes in key order; within a node, as stored. A whole-input stream
(:func:`chunks`) has the same order, so filtering a region's points keeps them in the order the streaming
partition sees them, and a tile read from the index is byte for byte the tile the streaming partition writes.

COPC is read with laspy's ``CopcReader`` (lazrs decompresses the nodes' chunks); EPT is parsed here (a JSON
header, JSON hierarchy pages) with its nodes read by laspy (``laszip``) or NumPy (``binary``). Either may be a
local path or an ``http(s)://`` URL (:mod:`tiled_gridpull.io.remote`): a COPC file is then read by byte ranges,
an EPT's JSON and node files are fetched one by one, so a tile's task fetches only the nodes its box overlaps.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError
from .input_errors import check_frame, input_errors
from .remote import RemoteFile, fetch, is_url, shown, url_join, url_name

__all__ = ["PointIndex", "indexed_kind", "read_index", "read_box", "read_levels", "chunks", "read", "count",
           "crs", "ept_files"]


def indexed_kind(path: str | os.PathLike) -> str | None:
    """``"COPC"`` for ``*.copc.laz``, ``"EPT"`` for an ``ept.json`` (a path or a URL), else None (by name only)."""
    name = (url_name(path) if is_url(path) else Path(path).name).lower()
    if name.endswith(".copc.laz"):
        return "COPC"
    if name == "ept.json":
        return "EPT"
    return None


@dataclass(frozen=True, eq=False)
class PointIndex:
    """What an indexed input's header and hierarchy say, without its points.

    Attributes
    ----------
    path : str
    kind : {"COPC", "EPT"}
    bounds : (2, 3) float64
        Low and high corner of the points (the header's conforming bounds), file units.
    points : int
        Point count the header declares.
    crs : str or None
        WKT.
    keys : (M, 4) int64
        (depth, x, y, z) of the nodes holding points, in stream order.
    lo, hi : (M, 3) float64
        Each node's cube.
    counts : (M,) int64
        Points per node.
    """

    path: str
    kind: str
    bounds: np.ndarray
    points: int
    crs: str | None
    keys: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    counts: np.ndarray

    def overlapping(self, lo, hi) -> np.ndarray:
        """Rows of the nodes whose cube overlaps the box [lo, hi] (closed), in stream order."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        return np.flatnonzero(np.all((self.lo <= hi) & (self.hi >= lo), axis=1))


def _cubes(keys: np.ndarray, cube_lo: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    edge = size / (2.0 ** keys[:, 0])
    lo = cube_lo + keys[:, 1:] * edge[:, None]
    return lo, lo + edge[:, None]


def read_index(path: str | os.PathLike) -> PointIndex:
    """The header and hierarchy of a COPC file or an EPT; InputError (one line) when they are not readable."""
    p = path if is_url(path) else Path(path)
    kind = indexed_kind(p)
    if kind is None:
        raise InputError(f"{shown(p)}: not a cloud-optimized point cloud (a *.copc.laz file or an ept.json)")
    with input_errors(p, kind, f"not a readable {kind}"):
        try:
            return _copc_index(p) if kind == "COPC" else _ept_index(p)
        except FileNotFoundError as exc:  # a hierarchy page or the file itself: name the one missing
            raise InputError(f"{shown(p)}: {kind} file missing: {exc.filename}") from None


# ---------------------------------------------------------------- COPC


def _copc_reader(p, stream=None):
    """laspy's COPC reader of ``p`` (a path or a URL), or of ``stream``, an open file of it (left open)."""
    from laspy import CopcReader, DecompressionSelection

    sel = DecompressionSelection
    selection = sel.XY_RETURNS_CHANNEL | sel.Z
    if stream is not None:
        return CopcReader(stream, close_fd=False, decompression_selection=selection)
    if is_url(p):
        return CopcReader(RemoteFile(p), decompression_selection=selection)
    return CopcReader.open(str(p), decompression_selection=selection)


def _copc_index(p) -> PointIndex:
    from . import las

    # through the LAS reader: its checks of the header's counts come first, and it reads the EVLRs, where COPC
    # writers put the WKT (the COPC reader's header does not load them)
    if not is_url(p):
        return _copc_index_read(p, las.crs(p), None)
    with RemoteFile(p) as fh:  # one remote file for both readers: its size asked once, its header fetched once
        crs = las.stream_crs(shown(p), fh, fh.size)
        fh.seek(0)
        return _copc_index_read(p, crs, fh)


def _copc_index_read(p, crs: str | None, stream) -> PointIndex:
    from laspy.copc import load_octree_for_query

    with _copc_reader(p, stream) as reader:
        header = reader.header
        nodes = [n for n in load_octree_for_query(reader.source, reader.copc_info, reader.root_page)
                 if n.point_count > 0]
        nodes.sort(key=lambda n: n.offset)
        keys = np.array([[n.key.level, n.key.x, n.key.y, n.key.z] for n in nodes], np.int64).reshape(-1, 4)
        counts = np.array([n.point_count for n in nodes], np.int64)
        info = reader.copc_info
        half = float(info.halfsize)
        lo, hi = _cubes(keys, np.asarray(info.center, np.float64) - half, 2 * half)
        # applied to every point, as a LAS header's: refused at planning, before a tile is read
        check_frame(f"{shown(p)}: the COPC header's", header.offsets, header.scales, reach=2.0 ** 31)
        bounds = np.stack([np.asarray(header.mins, np.float64), np.asarray(header.maxs, np.float64)])
        declared = int(header.point_count)
    if counts.sum() != declared:
        raise InputError(f"{shown(p)}: corrupted COPC file (its hierarchy holds {int(counts.sum())} points, its header "
                         f"declares {declared})")
    return PointIndex(str(p), "COPC", bounds, declared, crs, keys, lo, hi, counts)


def _copc_points(index: PointIndex, lo=None, hi=None, depth: int | None = None) -> np.ndarray:
    """(N, 3) float64 of the nodes overlapping the box [lo, hi] (padded by a few of the file's scale steps, so
    that no node touching it is missed; the caller filters exactly), or of the nodes above ``depth``, in file
    order."""
    from laspy.copc import Bounds

    with _copc_reader(index.path) as reader:
        bounds = None
        if lo is not None:
            pad = 4 * np.asarray(reader.header.scales, np.float64)
            bounds = Bounds(np.asarray(lo, np.float64) - pad, np.asarray(hi, np.float64) + pad)
        pts = reader.query(bounds=bounds, level=None if depth is None else range(0, depth))
        if not len(pts):
            return np.empty((0, 3))
        return np.column_stack([np.asarray(pts.x, np.float64), np.asarray(pts.y, np.float64),
                                np.asarray(pts.z, np.float64)])


# ---------------------------------------------------------------- EPT

_EPT_TYPES = {("signed", 1): "<i1", ("signed", 2): "<i2", ("signed", 4): "<i4", ("signed", 8): "<i8",
              ("unsigned", 1): "<u1", ("unsigned", 2): "<u2", ("unsigned", 4): "<u4", ("unsigned", 8): "<u8",
              ("floating", 4): "<f4", ("floating", 8): "<f8"}


def _read_bytes(source) -> bytes:
    return fetch(source) if is_url(source) else Path(source).read_bytes()


def _beside(ept_json, *parts: str):
    """A file of the EPT whose ``ept.json`` is ``ept_json`` (a path or a URL)."""
    return url_join(ept_json, *parts) if is_url(ept_json) else Path(ept_json).parent.joinpath(*parts)


def _ept_meta(p) -> dict:
    meta = json.loads(_read_bytes(p))
    for field in ("bounds", "points", "schema", "dataType"):
        if field not in meta:
            raise InputError(f"{shown(p)}: not an EPT ept.json (no '{field}')")
    if meta["dataType"] not in ("laszip", "binary"):
        raise InputError(f"{shown(p)}: EPT dataType '{meta['dataType']}' is not read (laszip and binary are)")
    if meta.get("hierarchyType", "json") != "json":
        raise InputError(f"{shown(p)}: EPT hierarchyType '{meta['hierarchyType']}' is not read (json is)")
    _ept_schema_frame(p, meta)
    return meta


def _ept_schema_frame(p, meta: dict) -> None:
    """Refuse a schema whose X Y Z scale or offset (applied to every stored integer) cannot make usable
    coordinates, as a LAS header's (:func:`~tiled_gridpull.io.input_errors.check_frame`)."""
    dims = {d.get("name"): d for d in meta["schema"] if isinstance(d, dict)}
    if not all(a in dims for a in "XYZ"):
        raise InputError(f"{shown(p)}: EPT schema has no X, Y and Z dimensions")
    try:
        offset = [float(dims[a].get("offset", 0.0)) for a in "XYZ"]
        scale = [float(dims[a].get("scale", 1.0)) for a in "XYZ"]
        size = max(int(dims[a].get("size", 4)) for a in "XYZ")
    except (TypeError, ValueError):
        raise InputError(f"{shown(p)}: EPT schema's X Y Z scale, offset or size is not a number") from None
    check_frame(f"{shown(p)}: the ept.json schema's", offset, scale, reach=2.0 ** (8 * min(size, 8) - 1))


def _ept_hierarchy(p) -> dict[str, int]:
    """Every node's point count, following the pages a count of -1 points to."""
    out: dict[str, int] = {}
    pages = ["0-0-0-0"]
    while pages:
        page = json.loads(_read_bytes(_beside(p, "ept-hierarchy", f"{pages.pop()}.json")))
        for key, value in page.items():
            if int(value) == -1:
                pages.append(key)
            else:
                out[key] = int(value)
    return out


def _ept_index(p) -> PointIndex:
    meta = _ept_meta(p)
    counts_by_key = {k: v for k, v in _ept_hierarchy(p).items() if v > 0}
    keys = np.array(sorted(tuple(int(v) for v in k.split("-")) for k in counts_by_key), np.int64).reshape(-1, 4)
    counts = np.array([counts_by_key["-".join(map(str, k))] for k in keys], np.int64)
    cube = np.asarray(meta["bounds"], np.float64)
    lo, hi = _cubes(keys, cube[:3], float((cube[3:] - cube[:3]).max()))
    conforming = np.asarray(meta.get("boundsConforming", meta["bounds"]), np.float64)
    declared = int(meta["points"])
    if counts.sum() != declared:
        raise InputError(f"{shown(p)}: corrupted EPT (its hierarchy holds {int(counts.sum())} points, ept.json "
                         f"declares {declared})")
    srs = meta.get("srs") or {}
    crs = srs.get("wkt") or None
    return PointIndex(str(p), "EPT", conforming.reshape(2, 3), declared, crs, keys, lo, hi, counts)


def _ept_node(p, meta: dict, key: np.ndarray, count: int) -> np.ndarray:
    name = "-".join(str(int(v)) for v in key)
    f = _beside(p, "ept-data", f"{name}.{'laz' if meta['dataType'] == 'laszip' else 'bin'}")
    with input_errors(f, "EPT node", "damaged EPT node"):
        xyz = _ept_node_points(f, meta, count)
    if len(xyz) != count:
        raise InputError(f"{shown(f)}: truncated EPT node (holds {len(xyz)} points, the hierarchy says {count})")
    return xyz


def _ept_node_points(f, meta: dict, count: int) -> np.ndarray:
    if meta["dataType"] == "laszip":
        import io

        import laspy

        from .las import laz_backend

        source = io.BytesIO(fetch(f)) if is_url(f) else str(f)  # a node is small: fetched whole
        with laspy.open(source, laz_backend=laz_backend()) as reader:
            check_frame(f"{shown(f)}: the LAZ header's", reader.header.offsets, reader.header.scales,
                        reach=2.0 ** 31)
            pts = reader.read_points(count)
        return np.column_stack([np.asarray(pts.x, np.float64), np.asarray(pts.y, np.float64),
                                np.asarray(pts.z, np.float64)])
    dtype = np.dtype([(d["name"], _EPT_TYPES[(d["type"], int(d["size"]))]) for d in meta["schema"]])
    raw = np.frombuffer(fetch(f), dtype=dtype) if is_url(f) else np.fromfile(f, dtype=dtype)
    xyz = np.empty((len(raw), 3))
    for d in meta["schema"]:
        if d["name"] in ("X", "Y", "Z"):
            xyz[:, "XYZ".index(d["name"])] = raw[d["name"]] * d.get("scale", 1.0) + d.get("offset", 0.0)
    return xyz


def _ept_points(index: PointIndex, rows: np.ndarray) -> Iterator[np.ndarray]:
    meta = _ept_meta(index.path)
    for r in rows:
        yield _ept_node(index.path, meta, index.keys[r], int(index.counts[r]))


# ---------------------------------------------------------------- reading


def _clouds(index: PointIndex, parts) -> Iterator[PointCloud]:
    with input_errors(index.path, index.kind, f"damaged {index.kind}"):
        for xyz in parts:
            if len(xyz):
                yield PointCloud(xyz, crs=index.crs, source=index.path, report={"points_read": len(xyz)})


def read_box(index: PointIndex, lo, hi) -> Iterator[PointCloud]:
    """The points inside the closed box [lo, hi] (file units), in stream order: only the nodes overlapping it
    are read."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if index.kind == "COPC":
        parts = _lazy(_copc_points, index, lo, hi)
    else:
        parts = _ept_points(index, index.overlapping(lo, hi))
    for cloud in _clouds(index, parts):
        inside = np.all((cloud.xyz >= lo) & (cloud.xyz <= hi), axis=1)
        if inside.all():
            yield cloud
        elif inside.any():
            yield cloud.take(np.flatnonzero(inside))


def read_levels(index: PointIndex, depth: int) -> Iterator[PointCloud]:
    """The points of the nodes shallower than ``depth``: an even subsample of the whole input (each level of
    detail keeps about one point per cell of a grid over its node), in stream order."""
    if index.kind == "COPC":
        parts = _lazy(_copc_points, index, depth=depth)
    else:
        parts = _ept_points(index, np.flatnonzero(index.keys[:, 0] < depth))
    yield from _clouds(index, parts)


def _lazy(fn, *args, **kwargs) -> Iterator[np.ndarray]:
    yield fn(*args, **kwargs)


# ---------------------------------------------------------------- the format backend (whole inputs, for ".json")


def chunks(p: Path, chunk_size: int) -> Iterator[PointCloud]:
    """An EPT streamed node by node in key order (the stream order), at most ``chunk_size`` points a chunk."""
    index = read_index(p)
    done = 0
    for cloud in _clouds(index, _ept_points(index, np.arange(len(index.keys)))):
        for s in range(0, len(cloud), chunk_size):
            part = cloud.xyz[s:s + chunk_size]
            yield PointCloud(part, crs=index.crs, source=f"{p}[{done}:{done + len(part)}]",
                             report={"points_read": len(part)})
            done += len(part)


def read(p: Path) -> PointCloud:
    """A whole EPT in memory (stream order)."""
    from ..cloud import concat_clouds

    return concat_clouds(list(chunks(p, 1 << 24)), str(p))


def count(p: Path) -> int:
    """The point count ``ept.json`` declares."""
    return int(_ept_meta(p)["points"])


def crs(p: Path) -> str | None:
    """The WKT of ``ept.json``'s ``srs``, or None."""
    return (_ept_meta(p).get("srs") or {}).get("wkt") or None


def ept_files(p: Path) -> list[Path]:
    """Every file an EPT reader reads: ``ept.json``, its hierarchy pages and data files (sorted)."""
    root = p.parent
    files = [p]
    for sub in ("ept-hierarchy", "ept-data"):
        d = root / sub
        if d.is_dir():
            files += sorted(f for f in d.iterdir() if f.is_file())
    return files
