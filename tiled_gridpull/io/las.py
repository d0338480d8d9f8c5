"""LAS/LAZ point clouds through laspy (single-threaded lazrs for LAZ), decoded chunk by chunk so memory is
bounded by the chunk; header counts (VLRs, EVLRs, the LAZ chunk table, the laszip VLR's items) are checked
against the file before laspy or lazrs see them, because a corrupted count makes them spin or abort the
process."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..cloud import PointCloud, concat_clouds, unit_normals
from ..errors import InputError
from .input_errors import check_frame

__all__ = ["read", "chunks", "count", "carried_dims", "record_attributes"]

_READ_CHUNK = 1_000_000


def read(p: Path) -> PointCloud:
    """The whole file as one cloud (float64 coordinates, normals from extra bytes, intensity, CRS)."""
    return concat_clouds(list(_las_chunks(p, _READ_CHUNK)), str(p))


def chunks(p: Path, chunk_size: int) -> Iterator[PointCloud]:
    """The file in chunks of ``chunk_size`` points: laspy decodes exactly one chunk per step."""
    yield from _las_chunks(p, chunk_size)


def timed_chunks(p: Path, chunk_size: int) -> Iterator[PointCloud]:
    """As :func:`chunks`, with each point's GPS time in ``attributes["gps_time"]`` (float64, s).

    Raises
    ------
    InputError
        The file's point format has no GPS time (formats 0 and 2).
    """
    yield from _las_chunks(p, chunk_size, gps_time=True)


def row_chunks(p: Path, chunk_size: int, start: int, stop: int, gps_time: bool = False) -> Iterator[PointCloud]:
    """Points ``start`` to ``stop`` of the file (in file order), in chunks of ``chunk_size``: one segment of a
    partition run in parallel. LAZ seeks through its chunk table."""
    yield from _las_chunks(p, chunk_size, gps_time=gps_time, rows=(int(start), int(stop)))


def count(p: Path) -> int:
    """The header's point count (after the header checks)."""
    import laspy

    _las_precheck(p)
    with laspy.open(str(p), laz_backend=laz_backend()) as reader:
        return int(reader.header.point_count)


#: what a LAS file's CRS is called when it is GeoTIFF keys that could not be read (pyproj absent)
GEOTIFF_UNREAD = "GeoTIFF keys (not read: pyproj is not installed)"


def crs(p: Path) -> str | None:
    """The CRS in the header (WKT), without reading points; None when it has none."""
    import laspy

    _las_precheck(p)
    with laspy.open(str(p), laz_backend=laz_backend()) as reader:
        return _las_crs(reader.header)


def stream_crs(name: str, fh, size: int) -> str | None:
    """:func:`crs` of an open binary file of ``size`` bytes (a COPC file on a web server, read by ranges);
    ``name`` names it in messages. Leaves ``fh`` open."""
    import laspy

    _las_precheck_stream(name, fh, size)
    fh.seek(0)
    with laspy.open(fh, closefd=False, laz_backend=laz_backend()) as reader:
        return _las_crs(reader.header)


def _las_crs(header) -> str | None:
    """WKT from the header if present, else whatever description it has; never raises."""
    try:
        from laspy.vlrs.known import GeoAsciiParamsVlr, WktCoordinateSystemVlr
    except Exception:  # pragma: no cover - laspy layout changed
        return None
    vlrs = list(getattr(header, "vlrs", None) or []) + list(getattr(header, "evlrs", None) or [])
    try:
        for v in vlrs:
            if isinstance(v, WktCoordinateSystemVlr):
                wkt = str(getattr(v, "string", "") or "").strip("\x00 \n")
                if wkt:
                    return wkt
    except Exception:
        pass
    try:
        crs = header.parse_crs()  # GeoTIFF keys -> needs pyproj, which may be absent
        if crs is not None:
            return crs.to_wkt()
    except Exception:
        pass
    try:
        for v in vlrs:
            if isinstance(v, GeoAsciiParamsVlr):
                text = " ".join(s.strip("|\x00 ") for s in v.strings if s and s.strip("|\x00 "))
                if text:
                    return text
    except Exception:
        pass
    if any(type(v).__name__ == "GeoKeyDirectoryVlr" for v in vlrs):
        # a CRS is declared even if it could not be read: saying "none" would make it metres by default
        return GEOTIFF_UNREAD
    return None


def _las_normal_dims(point_format) -> tuple[str, str, str] | None:
    extra = {name.lower(): name for name in point_format.extra_dimension_names}
    for trio in (("normalx", "normaly", "normalz"), ("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z")):
        if all(t in extra for t in trio):
            return tuple(extra[t] for t in trio)
    return None


def carried_dims(point_format) -> list[tuple[str, str, np.dtype]]:
    """``(attribute name, LAS dimension, type)`` of what a point carries onto mesh vertices: ``red``, ``green``,
    ``blue`` (uint16, as stored), ``intensity`` (uint16), ``classification`` (uint8; the class code, without the
    flags older formats pack beside it) and every one-valued numeric extra dimension but the normals, under its
    own name."""
    names = set(point_format.dimension_names)
    normal_dims = _las_normal_dims(point_format)
    out = []
    for dim in ("red", "green", "blue", "intensity"):
        if dim in names:
            out.append((dim, dim, np.dtype(np.uint16)))
    if "classification" in names:
        out.append(("classification", "classification", np.dtype(np.uint8)))
    skip = set(normal_dims or ())
    for dim in point_format.extra_dimensions:
        if dim.name in skip or dim.name in {n for n, _, _ in out}:
            continue
        dtype = np.dtype(dim.dtype)
        if dtype.kind in "uif" and dtype.shape == () and getattr(dim, "num_elements", 1) == 1:
            # scaled extra bytes come out of laspy as float64 values
            scaled = getattr(dim, "scales", None) is not None or getattr(dim, "offsets", None) is not None
            out.append((dim.name, dim.name, np.dtype(np.float64) if scaled else dtype))
    return out


def record_attributes(points, point_format) -> dict:
    """The :func:`carried_dims` of laspy point records ``points``: name to (N,) array of its type."""
    return {name: np.array(points[dim], dtype=dtype) for name, dim, dtype in carried_dims(point_format)}


def laz_backend():
    """The single-threaded lazrs decoder.

    The parallel one sizes its buffers from the LAZ chunk table, and a corrupted table makes it request tens
    of GB, which aborts the whole process from Rust (no Python exception to catch). The sequential decoder
    only fills the buffer laspy gives it. Tiles and files are already decoded in parallel by the pipeline.
    """
    import laspy

    return laspy.LazBackend.Lazrs


def _las_precheck(p: Path) -> int | None:
    """Check the LAS header's record counts against the file size before laspy sees them.

    laspy loops over the declared number of (E)VLRs without checking for end of file: one flipped byte in the
    count makes it spin for hours on an empty stream. Each VLR header is 54 bytes, each EVLR header 60.

    Returns the number of chunks of a LAZ file's chunk table (None: not LAZ, or no usable table).
    """
    with open(p, "rb") as fh:
        return _las_precheck_stream(p, fh, p.stat().st_size)


def _las_precheck_stream(p, fh, size: int) -> int | None:
    """:func:`_las_precheck` on an open binary file of ``size`` bytes (``p`` names it in messages)."""
    n_chunks = None
    head = fh.read(375)
    if head[:4] == b"LASF" and len(head) >= 227 and head[104] & 0xC0:
        n_chunks = _laz_chunk_table_check(p, fh, int.from_bytes(head[96:100], "little"), size)
    if head[:4] != b"LASF":
        raise InputError(f"{p}: not a LAS/LAZ file (no LASF signature)")
    if len(head) < 227:
        raise InputError(f"{p}: truncated LAS header ({len(head)} bytes)")
    n_vlrs = int.from_bytes(head[100:104], "little")
    if n_vlrs * 54 > size:
        raise InputError(f"{p}: corrupted LAS header (declares {n_vlrs} VLRs in a {size}-byte file)")
    if head[25] >= 4 and len(head) >= 247:
        start_evlr = int.from_bytes(head[235:243], "little")
        n_evlrs = int.from_bytes(head[243:247], "little")
        if n_evlrs and start_evlr + n_evlrs * 60 > size:
            raise InputError(f"{p}: corrupted LAS header (declares {n_evlrs} extended VLRs beyond the end "
                             f"of the {size}-byte file)")
    return n_chunks


def _laszip_items_check(p: Path, header) -> None:
    """Refuse a LAZ whose laszip VLR declares no compressed items (lazrs panics on it, printing a Rust backtrace).

    The VLR's record data holds the item count as a uint16 at byte 32, followed by 6 bytes per item.
    """
    data = _laszip_vlr_data(header)
    if data is None:
        return
    n_items = int.from_bytes(data[32:34], "little") if len(data) >= 34 else 0
    if n_items == 0 or len(data) < 34 + 6 * n_items:
        raise InputError(f"{p}: corrupted LAZ file (the laszip VLR declares {n_items} compressed items "
                         f"in {len(data)} bytes)")


def _laszip_vlr_data(header) -> bytes | None:
    """Record data of the laszip VLR (user "laszip encoded", record 22204), or None when the file has none."""
    for vlr in header.vlrs:
        if vlr.user_id.rstrip("\0") == "laszip encoded" and vlr.record_id == 22204:
            return bytes(getattr(vlr, "record_data", b"") or b"")
    return None


def _laz_chunk_table_check(p: Path, fh, data_start: int, size: int) -> int | None:
    """Refuse a LAZ chunk table whose chunk count cannot fit in the file.

    lazrs reserves memory for the declared number of chunks before reading them; a corrupted count aborts the
    process from Rust. The table is found as lazrs finds it: an int64 offset at the start of the point data,
    or (when a streaming writer could not fill it in) in the last 8 bytes of the file.
    """
    fh.seek(data_start)
    raw = fh.read(8)
    if len(raw) < 8:
        return  # laspy reports the truncation
    table = int.from_bytes(raw, "little", signed=True)
    if table <= data_start and size >= 8:
        fh.seek(size - 8)
        table = int.from_bytes(fh.read(8), "little", signed=True)
    if table <= data_start or table + 8 > size:
        return None  # no usable chunk table: lazrs fails cleanly (or streams without one)
    fh.seek(table)
    n_chunks = int.from_bytes(fh.read(8)[4:8], "little")
    # every chunk holds at least one raw point record (>= 20 bytes) of compressed data
    if n_chunks * 8 > size:
        raise InputError(f"{p}: corrupted LAZ file (chunk table declares {n_chunks} chunks in a "
                         f"{size}-byte file)")
    return n_chunks


def _laszip_chunk_size(header) -> int | None:
    """Points per chunk of a LAZ file written with fixed-size chunks (None: variable chunks, or no laszip VLR).

    The laszip VLR's record data holds it as a uint32 at byte 12; 0xFFFFFFFF marks variable chunks."""
    data = _laszip_vlr_data(header)
    if data is None or len(data) < 16:
        return None
    size = int.from_bytes(data[12:16], "little")
    return None if size in (0, 0xFFFFFFFF) else size


def _warn_undeclared_points(p: Path, header, n_chunks: int | None, size: int) -> None:
    """Warn when a LAS/LAZ file holds more point records than its header declares: readers stop at the declared
    count, so the rest would be dropped without a word (a header written before the writer finished, or a
    32-bit legacy count that wrapped)."""
    total = int(header.point_count)
    if header.are_points_compressed:
        chunk = _laszip_chunk_size(header)
        if chunk is None or n_chunks is None:
            return
        needed = -(-total // chunk)
        if n_chunks > needed:
            warnings.warn(f"{p}: the LAZ chunk table holds {n_chunks} chunks of {chunk} points but the header "
                          f"declares {total} points (at most {needed} chunks): points past the declared count "
                          f"are not read", stacklevel=2)
        return
    record = int(header.point_format.size)
    end = int(header.offset_to_point_data) + total * record
    limit = size
    start_evlr = int(getattr(header, "start_of_first_evlr", 0) or 0)
    if header.version.minor >= 4 and getattr(header, "number_of_evlrs", 0) and start_evlr > 0:
        limit = min(size, start_evlr)
    extra = (limit - end) // record
    if extra > 0:
        warnings.warn(f"{p}: the file holds {extra} more point records than its header declares ({total}): "
                      f"they are not read", stacklevel=2)


def _las_chunks(p: Path, chunk_size: int, gps_time: bool = False,
                rows: tuple[int, int] | None = None) -> Iterator[PointCloud]:
    import laspy

    n_chunks = _las_precheck(p)
    sel = laspy.DecompressionSelection
    # LAS 1.4 point formats 6-10 are compressed in layers: skip decoding the fields we do not keep (GPS time,
    # flags, scan angle, ...), which makes the decode faster. Older formats decode everything.
    wanted = (sel.XY_RETURNS_CHANNEL | sel.Z | sel.INTENSITY | sel.ALL_EXTRA_BYTES | sel.RGB
              | sel.CLASSIFICATION)
    if gps_time:
        wanted = wanted | sel.GPS_TIME
    with laspy.open(str(p), laz_backend=laz_backend(), decompression_selection=wanted) as reader:
        header = reader.header
        if gps_time and "gps_time" not in header.point_format.dimension_names:
            raise InputError(f"{p}: its points have no GPS time (LAS point format {header.point_format.id}), "
                             "which a trajectory needs")
        total = int(header.point_count)
        if not header.are_points_compressed:
            # Uncompressed LAS cut at a record boundary reads "successfully" with fewer points: check size.
            needed = int(header.offset_to_point_data) + total * int(header.point_format.size)
            size = p.stat().st_size
            if size < needed:
                raise InputError(f"{p}: truncated LAS file (header declares {total} points, which needs "
                                 f"{needed} bytes, but the file has {size})")
        if header.are_points_compressed:
            _laszip_items_check(p, header)
        _warn_undeclared_points(p, header, n_chunks, p.stat().st_size)
        # laspy applies them to every record (int32): a damaged one makes NaN, identical or overflowing points
        check_frame(f"{p}: the LAS header's", header.offsets, header.scales, reach=2.0 ** 31)
        crs = _las_crs(header)
        normal_dims = _las_normal_dims(header.point_format)
        carried = carried_dims(header.point_format)
        first, last = rows if rows is not None else (0, total)
        if not 0 <= first <= last <= total:
            raise InputError(f"{p}: rows {first}:{last} are outside its {total} points")
        if first:
            reader.seek(first)
        done = first
        for chunk in reader.chunk_iterator(chunk_size):
            n = len(chunk)
            if n == 0:
                break
            if done + n > last:
                chunk, n = chunk[:last - done], last - done
            xyz = np.empty((n, 3), dtype=np.float64)
            xyz[:, 0] = chunk.x
            xyz[:, 1] = chunk.y
            xyz[:, 2] = chunk.z
            normals = None
            if normal_dims is not None:
                normals = unit_normals(np.column_stack([np.asarray(chunk[d], dtype=np.float64)
                                                         for d in normal_dims]))
            attrs = {name: np.array(chunk[dim], dtype=dtype) for name, dim, dtype in carried}  # record_attributes
            if gps_time:
                attrs["gps_time"] = np.asarray(chunk.gps_time, dtype=np.float64)
            yield PointCloud(xyz, normals=normals, attributes=attrs, crs=crs,
                             source=f"{p}[{done}:{done + n}]", report={"points_read": n})
            done += n
            if done >= last:
                break
        if done != last:
            kind = "LAZ" if header.are_points_compressed else "LAS"
            raise InputError(f"{p}: truncated or corrupted {kind} file (read {done} of {total} points)")

