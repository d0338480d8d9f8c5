"""The point-cloud type and its cleaning: what every reader returns and what every solve starts from.

:class:`PointCloud` holds float64 world coordinates with optional normals, sensor origins and per-point
attributes; :func:`clean_points` drops non-finite and duplicate points and refuses clouds a surface cannot be
reconstructed from; :func:`duplicate_mask` is the one duplicate test (the tile solve uses it too);
:func:`as_points` accepts point clouds of pyvista, Open3D and trimesh without importing them.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import InputError

__all__ = ["PointCloud", "clean_points", "duplicate_mask", "concat_clouds", "cloud_slices",
           "drop_nonfinite_rows", "unit_normals", "as_points", "degeneracy", "stream_degeneracy",
           "degenerate_error", "COORDINATE_LIMIT", "colors_of"]

# Relative tolerance on singular values for the collinear / coplanar tests (see clean_points).
_DEGENERATE_RTOL = 1e-9
_IDENTICAL_ULPS = 64
#: Largest coordinate magnitude float64 arithmetic on a cloud resolves: beyond it squared distances overflow
#: (and sums over a few points). Readers refuse a header's offset or scale that would put points there.
COORDINATE_LIMIT = 1e150
_EXTENT_RANGE = (1e-150, COORDINATE_LIMIT)
# Degeneracy is first tested on this many evenly spaced points: a non-degenerate subset proves the whole
# cloud non-degenerate, so the full O(N) factorisation is only needed for (nearly) degenerate clouds.
_DEGENERATE_SAMPLE = 200_000


@dataclass(eq=False)
class PointCloud:
    """A point cloud in world coordinates, with what reading and cleaning it did.

    Attributes
    ----------
    xyz : (N, 3) float64
        World coordinates, in the file's units (metres for most data, international feet for Autzen).
    normals : (N, 3) float32, optional
        Unit normals when the file has them (a zero row means the file gave a zero-length normal).
    sensor : (N, 3) float64, optional
        Sensor origin of every point in world coordinates, when known (KITTI).
    attributes : dict of str to (N, ...) arrays
        Optional per-point arrays, e.g. ``"intensity"``, ``"frame"`` (int32, KITTI sequences).
    crs : str, optional
        Coordinate reference system as WKT or a description, when the file has one (LAS/LAZ).
    source : str
        Where the points came from (a path, plus a range for chunks).
    report : dict
        What reading and cleaning did, e.g. ``{"points_read": n, "nonfinite_dropped": k,
        "duplicates_dropped": m, "points_kept": n - k - m}``.
    """

    xyz: np.ndarray
    normals: np.ndarray | None = None
    sensor: np.ndarray | None = None
    attributes: dict = field(default_factory=dict)
    crs: str | None = None
    source: str = ""
    report: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        # Coordinates are widened, never narrowed: float32 input converts to float64 exactly.
        self.xyz = np.asarray(self.xyz, dtype=np.float64)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise InputError(f"{self.source or 'point cloud'}: xyz must have shape (N, 3), "
                             f"got {self.xyz.shape}")
        n = len(self.xyz)
        if self.normals is not None:
            self.normals = np.asarray(self.normals, dtype=np.float32)
            if self.normals.shape != (n, 3):
                raise InputError(f"{self.source or 'point cloud'}: normals have shape {self.normals.shape}, "
                                 f"expected ({n}, 3)")
        if self.sensor is not None:
            self.sensor = np.asarray(self.sensor, dtype=np.float64)
            if self.sensor.shape != (n, 3):
                raise InputError(f"{self.source or 'point cloud'}: sensor origins have shape "
                                 f"{self.sensor.shape}, expected ({n}, 3)")

    def __len__(self) -> int:
        return len(self.xyz)

    def take(self, idx, *, xyz: np.ndarray | None = None) -> PointCloud:
        """The rows ``idx`` (index or boolean array, or slice) of every per-point array."""
        return _take(self, idx, xyz=xyz)


def clean_points(cloud: PointCloud, *, what: str = "", min_points: int = 10,
                 reject_planar: bool = True) -> PointCloud:
    """Drop non-finite and duplicate points; refuse clouds the reconstruction cannot use.

    Steps, in order:

    1. an empty cloud is refused;
    2. points with a non-finite coordinate are dropped (counted in ``report["nonfinite_dropped"]``, with a
       warning); if none is finite the cloud is refused;
    3. exact duplicate points are dropped, keeping the first occurrence and the order of the rest (counted in
       ``report["duplicates_dropped"]``);
    4. a cloud whose points are all identical, or that has fewer than ``min_points`` points, is refused;
    5. a cloud whose points are all collinear, or (when ``reject_planar``) all coplanar, is refused. The test
       uses the singular values s1 >= s2 >= s3 of the mean-centred float64 coordinates: s2 <= 1e-9 s1 is
       collinear, s3 <= 1e-9 s1 is coplanar. Centring first keeps the test exact for coordinates around 1e7.

    Normals, sensor origins and per-point attributes are filtered with the points. The input is not modified.

    Parameters
    ----------
    cloud : PointCloud
    what : str
        Name used in messages (default: ``cloud.source``).
    min_points : int
        Fewest points accepted after cleaning.
    reject_planar : bool
        Refuse coplanar clouds (the tiled pipeline passes False: a flat parking lot is a legal tile).

    Returns
    -------
    PointCloud
        A new cloud; ``report`` adds ``points_read``, ``nonfinite_dropped``, ``duplicates_dropped``,
        ``points_kept``.

    Raises
    ------
    InputError
        Empty, no finite points, too few points, or degenerate (identical / collinear / coplanar).
    """
    what = what or cloud.source or "point cloud"
    xyz = cloud.xyz
    n = len(xyz)
    if n == 0:
        raise InputError(f"{what}: contains no points")
    report = dict(cloud.report)
    report["points_read"] = report.get("points_read", n)

    finite = np.isfinite(xyz).all(axis=1)
    n_finite = int(np.count_nonzero(finite))
    if n_finite == 0:
        raise InputError(f"{what}: no finite points (all {n} have NaN or infinite coordinates)")
    keep = None
    if n_finite < n:
        warnings.warn(f"{what}: dropped {n - n_finite} of {n} points with non-finite coordinates",
                      UserWarning, stacklevel=2)
        keep = np.flatnonzero(finite)
        xyz = xyz[keep]
    # accumulate, so that cleaning an already cleaned (or chunk-filtered) cloud keeps the earlier counts
    report["nonfinite_dropped"] = report.get("nonfinite_dropped", 0) + n - n_finite

    dup = duplicate_mask(xyz)
    n_dup = int(np.count_nonzero(dup))
    if n_dup:
        unique_rows = np.flatnonzero(~dup)
        keep = unique_rows if keep is None else keep[unique_rows]
        xyz = xyz[unique_rows]
    report["duplicates_dropped"] = report.get("duplicates_dropped", 0) + n_dup

    m = len(xyz)
    if m == 1 and n_finite > 1:
        raise InputError(f"{what}: all {n_finite} points are identical")
    if m < min_points:
        dropped = n - m
        extra = f" after dropping {dropped} non-finite or duplicate points" if dropped else ""
        raise InputError(f"{what}: only {m} points{extra} (at least {min_points} needed)")
    kind = degeneracy(xyz, reject_planar=reject_planar)
    if kind is not None:
        raise degenerate_error(what, m, kind)
    extent = float(np.max(xyz.max(axis=0) - xyz.min(axis=0)))
    if not _EXTENT_RANGE[0] <= extent <= _EXTENT_RANGE[1]:
        # squared distances of such an extent underflow or overflow float64: the mesh would be garbage
        raise InputError(f"{what}: the points span {extent:.3g} units, outside what float64 arithmetic resolves "
                         f"({_EXTENT_RANGE[0]:g} to {_EXTENT_RANGE[1]:g}): rescale the coordinates")
    report["points_kept"] = m

    out = _take(cloud, keep, xyz=xyz)
    out.report = report
    return out


# ------------------------------------------------------------------------------------------------------------
# rows of clouds


def _take(cloud: PointCloud, idx, *, xyz: np.ndarray | None = None) -> PointCloud:
    """Rows ``idx`` (index array, slice or None for all) of every per-point array of ``cloud``.

    ``xyz``, when given, is ``cloud.xyz[idx]`` already computed by the caller (saves a copy at 10M points).
    """
    n = len(cloud)

    def pick(a):
        if a is None or idx is None:
            return a
        return a[idx]

    attrs = {k: (pick(v) if isinstance(v, np.ndarray) and v.ndim >= 1 and len(v) == n else v)
             for k, v in cloud.attributes.items()}
    return PointCloud(pick(cloud.xyz) if xyz is None else xyz, normals=pick(cloud.normals),
                      sensor=pick(cloud.sensor), attributes=attrs, crs=cloud.crs, source=cloud.source,
                      report=dict(cloud.report))


def concat_clouds(parts: list[PointCloud], source: str) -> PointCloud:
    """One cloud of the rows of ``parts`` in order; attributes present in every part are kept."""
    if not parts:
        return PointCloud(np.zeros((0, 3)), source=source, report={"points_read": 0})
    if len(parts) == 1:
        out = parts[0]
        out.source = source
        out.report = {"points_read": len(out)}
        return out

    def cat(arrays):
        return None if any(a is None for a in arrays) else np.concatenate(arrays)

    keys = set(parts[0].attributes).intersection(*(p.attributes for p in parts[1:]))
    attrs = {k: np.concatenate([p.attributes[k] for p in parts]) for k in keys}
    xyz = np.concatenate([p.xyz for p in parts])
    return PointCloud(xyz, normals=cat([p.normals for p in parts]), sensor=cat([p.sensor for p in parts]),
                      attributes=attrs, crs=parts[0].crs, source=source, report={"points_read": len(xyz)})


def cloud_slices(cloud: PointCloud, chunk_size: int, name: str) -> Iterator[PointCloud]:
    """Consecutive slices of at most ``chunk_size`` rows, each with ``source`` ``"<name>[start:stop]"``."""
    n = len(cloud)
    for start in range(0, n, chunk_size):
        stop = min(start + chunk_size, n)
        part = _take(cloud, slice(start, stop))
        part.source = f"{name}[{start}:{stop}]"
        part.report = {"points_read": stop - start}
        yield part


def drop_nonfinite_rows(cloud: PointCloud) -> PointCloud:
    """The rows of ``cloud`` with finite coordinates; ``report["nonfinite_dropped"]`` counts the others."""
    finite = np.isfinite(cloud.xyz).all(axis=1)
    bad = len(finite) - int(np.count_nonzero(finite))
    if bad:
        cloud = _take(cloud, np.flatnonzero(finite))
    cloud.report["nonfinite_dropped"] = bad
    return cloud


def unit_normals(n: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N, 3) float32 unit vectors; zero or non-finite rows are left as they are."""
    n = np.asarray(n, dtype=np.float64)
    length = np.sqrt(np.einsum("ij,ij->i", n, n))
    ok = np.isfinite(length) & (length > 0)
    out = n.copy()
    out[ok] /= length[ok, None]
    return out.astype(np.float32)


# ------------------------------------------------------------------------------------------------------------
# duplicates and degeneracy


_K1, _K2, _K3 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xC2B2AE3D27D4EB4F), np.uint64(0x165667B19E3779F9)


def _row_hash(words: np.ndarray) -> np.ndarray:
    """64-bit mix of the three coordinate bit patterns of each row ((N, 3) uint64 -> (N,) uint64)."""
    with np.errstate(over="ignore"):
        h = words[:, 0] * _K1
        h ^= h >> np.uint64(29)
        h ^= words[:, 1]
        h *= _K2
        h ^= h >> np.uint64(32)
        h ^= words[:, 2]
        h *= _K3
        h ^= h >> np.uint64(29)
    return h


def duplicate_mask(xyz: np.ndarray, *, signed_zeros: bool = False) -> np.ndarray:
    """(N,) bool: True for every row equal to an earlier row (the first occurrence is kept).

    Rows are compared bit for bit, so ``~duplicate_mask(xyz)`` keeps the first occurrence of every point, in
    the order of ``xyz``.

    Parameters
    ----------
    xyz : (N, 3) float array
        Coordinates (float32 rows compare as their exact float64 values).
    signed_zeros : bool
        Whether -0.0 and 0.0 are different coordinates. :func:`clean_points` treats them as equal; the tile
        solve (which always compared the bytes of its float32 rows) keeps them apart.

    Sorting 64-bit hashes is several times faster than sorting 24-byte rows (lexsort or np.unique on a void
    view), which matters at 10M points; equal-hash neighbours are then compared exactly, and the rare hash
    collision falls back to an exact lexsort.
    """
    n = len(xyz)
    dup = np.zeros(n, dtype=bool)
    if n < 2:
        return dup
    # + 0.0 turns -0.0 into 0.0 so the bit patterns of equal coordinates agree.
    rows = xyz if signed_zeros else xyz + 0.0
    words = np.ascontiguousarray(rows, dtype=np.float64).view(np.uint64).reshape(n, 3)
    h = _row_hash(words)
    order = np.argsort(h, kind="stable")
    hs = h[order]
    cand = np.flatnonzero(hs[1:] == hs[:-1])
    if len(cand) == 0:
        return dup
    later, earlier = order[cand + 1], order[cand]
    equal = (words[later] == words[earlier]).all(axis=1)
    if not equal.all():
        return _duplicate_mask_exact(words)
    # Stable sort: within a run of equal rows indices ascend, so the run's first row is the first occurrence.
    dup[later] = True
    return dup


def _duplicate_mask_exact(words: np.ndarray) -> np.ndarray:
    n = len(words)
    order = np.lexsort((words[:, 2], words[:, 1], words[:, 0]))  # stable
    sw = words[order]
    same = (sw[1:] == sw[:-1]).all(axis=1)
    dup = np.zeros(n, dtype=bool)
    dup[order[1:][same]] = True
    return dup


def _singular_values(xyz: np.ndarray) -> np.ndarray:
    c = xyz - xyz.mean(axis=0)
    # QR then SVD of the 3x3 R: backward-stable (unlike eigenvalues of c.T @ c, which square the condition
    # number and cannot resolve a 1e-9 ratio), and cheap for tall (N, 3) arrays.
    r = np.linalg.qr(c, mode="r")
    return np.linalg.svd(r, compute_uv=False)


def _classify(s: np.ndarray, largest: float, n: int, reject_planar: bool) -> str | None:
    """The degeneracy of ``n`` points from the singular values ``s`` of their mean-centred coordinates and
    their largest coordinate magnitude: the one rule of :func:`degeneracy` and :func:`stream_degeneracy`."""
    scale = max(largest, np.finfo(np.float64).tiny)
    # identical up to the rounding of coordinates this large: a few units in the last place, not a fixed
    # fraction (1e-12 of 1e12 is a metre: a 1 m object there was called a single point)
    if s[0] <= _IDENTICAL_ULPS * np.finfo(np.float64).eps * scale * np.sqrt(n):
        return "identical"
    if s[1] <= _DEGENERATE_RTOL * s[0]:
        return "collinear"
    if reject_planar and s[2] <= _DEGENERATE_RTOL * s[0]:
        return "coplanar"
    return None


def degeneracy(xyz: np.ndarray, *, reject_planar: bool = True) -> str | None:
    """Whether the points are degenerate, by the rule of :func:`clean_points` (step 5).

    Parameters
    ----------
    xyz : (N, 3) float64
        Finite points.
    reject_planar : bool
        Also call coplanar points degenerate.

    Returns
    -------
    str or None
        ``"identical"``, ``"collinear"``, ``"coplanar"`` (only with ``reject_planar``) or None.
    """

    def classify(pts):
        return _classify(_singular_values(pts), float(np.abs(pts).max()), len(pts), reject_planar)

    n = len(xyz)
    if n > _DEGENERATE_SAMPLE:
        sample = xyz[np.linspace(0, n - 1, _DEGENERATE_SAMPLE).astype(np.int64)]
        if classify(sample) is None:
            return None
    return classify(xyz)


def stream_degeneracy(chunks: Callable[[], Iterable[np.ndarray]], *, reject_planar: bool = True,
                      sample: np.ndarray | None = None) -> str | None:
    """:func:`degeneracy` of points that come in chunks and are never held whole (tiled mode's inputs).

    A ``sample`` of the points that is not degenerate proves the whole set is not (no pass over the points).
    Otherwise two passes over ``chunks()``: the mean and the largest magnitude, then the R factor of the
    centred points, chunk by chunk (the R of stacked rows is the R of [R; next rows], so its singular values
    are those of the whole centred set).

    Parameters
    ----------
    chunks : callable
        ``chunks()`` yields (M, 3) float64 arrays of finite points, the same each call.
    reject_planar : bool
    sample : (K, 3) float64, optional
        Some of the points.

    Returns
    -------
    str or None
        As :func:`degeneracy`; None when there are no points.
    """
    if sample is not None and len(sample) >= 3 and degeneracy(sample, reject_planar=reject_planar) is None:
        return None
    n, total, largest = 0, np.zeros(3), 0.0
    for xyz in chunks():
        if len(xyz):
            n += len(xyz)
            total += xyz.sum(axis=0)
            largest = max(largest, float(np.abs(xyz).max()))
    if n == 0:
        return None
    mean = total / n
    r = np.zeros((0, 3))
    for xyz in chunks():
        if len(xyz):
            r = np.linalg.qr(np.vstack([r, xyz - mean]), mode="r")
    s = np.zeros(3)  # fewer than 3 points have fewer singular values: the missing ones are 0
    sv = np.linalg.svd(r, compute_uv=False)
    s[:len(sv)] = sv
    return _classify(s, largest, n, reject_planar)


def degenerate_error(what: str, n: int, kind: str) -> InputError:
    """The refusal of ``n`` points whose :func:`degeneracy` is ``kind``, as one line naming ``what``."""
    hint = " (an open flat patch is meshed by the unsigned mode: --mode udf)" if kind == "coplanar" else ""
    return InputError(f"{what}: all {n} points are {kind}; a surface cannot be reconstructed from them{hint}")


# ------------------------------------------------------------------------------------------------------------
# point clouds of other libraries


def colors_of(obj: Any) -> dict:
    """Per-point colour (and, from pyvista, intensity and classification) of a pyvista, Open3D or trimesh cloud.

    Parameters
    ----------
    obj : object
        As :func:`as_points` takes it. pyvista: point arrays ``red``, ``green``, ``blue`` (in their type), or
        ``RGB``/``RGBA`` (N, 3 or 4); and 1-D ``intensity`` and ``classification`` arrays. Open3D: ``colors``
        when ``has_colors()`` (floats in [0, 1], scaled to 8 bits). trimesh: a ``PointCloud``'s ``colors`` or a
        ``Trimesh``'s per-vertex ``visual.vertex_colors`` (uint8).

    Returns
    -------
    dict of str to (N,) arrays
        ``red``, ``green``, ``blue`` (uint8 unless pyvista gave another type), ``intensity``, ``classification``
        as found; empty for anything else (arrays, :class:`PointCloud`) or an object without colour.
    """
    if isinstance(obj, (np.ndarray, PointCloud, list, tuple)):
        return {}
    out: dict = {}
    rgb = None
    if hasattr(obj, "point_data") and hasattr(obj, "points"):  # pyvista.DataSet
        data = obj.point_data
        keys = set(data.keys())
        if {"red", "green", "blue"} <= keys:
            out.update({c: np.asarray(data[c]).reshape(-1) for c in ("red", "green", "blue")})
        else:
            for name in ("RGB", "RGBA"):
                if name in keys and np.asarray(data[name]).ndim == 2:
                    rgb = np.asarray(data[name])[:, :3]
                    break
        for name in ("intensity", "classification"):
            if name in keys and np.asarray(data[name]).ndim == 1:
                out[name] = np.asarray(data[name]).copy()
    elif callable(getattr(obj, "has_colors", None)) and hasattr(obj, "colors"):  # open3d.geometry.PointCloud
        if obj.has_colors():
            rgb = np.clip(np.rint(np.asarray(obj.colors) * 255.0), 0, 255).astype(np.uint8)
    elif hasattr(obj, "vertices"):  # trimesh
        colors = getattr(obj, "colors", None) if not hasattr(obj, "faces") else None
        visual = getattr(obj, "visual", None)
        if colors is None and visual is not None and getattr(visual, "kind", None) == "vertex":
            colors = visual.vertex_colors
        if colors is not None and len(colors) == len(obj.vertices) and len(colors):
            rgb = np.asarray(colors)[:, :3]
    if rgb is not None:
        if rgb.dtype.kind == "f":  # floats in [0, 1]
            rgb = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
        out.update({c: np.ascontiguousarray(rgb[:, i]) for i, c in enumerate(("red", "green", "blue"))})
    return out


def as_points(obj: Any) -> tuple[Any, np.ndarray | None]:
    """Coordinates and normals of a point cloud from pyvista, Open3D or trimesh (found by duck typing).

    Parameters
    ----------
    obj : object
        A ``pyvista.PolyData`` (``points``; normals from its active point normals or a ``"Normals"`` point
        array), an ``open3d.geometry.PointCloud`` (``points``; ``normals`` when ``has_normals()``), a
        ``trimesh.PointCloud`` (``vertices``) or ``trimesh.Trimesh`` (``vertices``; its ``vertex_normals``).
        Anything else (an (N, 3) array_like, a :class:`PointCloud`) is returned unchanged, for the caller to
        validate.

    Returns
    -------
    points : (N, 3) ndarray, or ``obj`` unchanged
        The coordinates as the library stores them (float64 for Open3D and trimesh, often float32 in pyvista).
    normals : (N, 3) ndarray or None
        The object's normals, when it has them.
    """
    if isinstance(obj, (np.ndarray, PointCloud, list, tuple)):
        return obj, None
    if hasattr(obj, "point_data") and hasattr(obj, "points"):  # pyvista.DataSet
        normals = getattr(obj.point_data, "active_normals", None)
        if normals is None and "Normals" in obj.point_data.keys():
            normals = obj.point_data["Normals"]
        return np.asarray(obj.points), None if normals is None else np.asarray(normals)
    if callable(getattr(obj, "has_normals", None)) and hasattr(obj, "points"):  # open3d.geometry.PointCloud
        return np.asarray(obj.points), np.asarray(obj.normals) if obj.has_normals() else None
    if hasattr(obj, "vertices"):  # trimesh.Trimesh or trimesh.PointCloud
        faces = getattr(obj, "faces", None)
        has_faces = faces is not None and len(faces) > 0
        return np.asarray(obj.vertices), np.asarray(obj.vertex_normals) if has_faces else None
    return obj, None
