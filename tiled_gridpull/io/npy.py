"""NPY point clouds: an (N, k >= 3) numeric array (x y z, then normals or extra columns) or a structured
array with fields x, y, z [, nx, ny, nz]; memory-mapped, so the header's shape is checked before any read."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..cloud import PointCloud, unit_normals
from ..errors import InputError
from .columns import columns_are_normals, columns_cloud

__all__ = ["read", "chunks", "count"]


def read(p: Path) -> PointCloud:
    """The whole array as a cloud."""
    return _read_npy(p)


def chunks(p: Path, chunk_size: int) -> Iterator[PointCloud]:
    """Slices of the memory-mapped array; whether columns 4-6 are normals is decided once for the file."""
    arr = np.load(p, mmap_mode="r", allow_pickle=False)
    _npy_check(p, arr)
    n = arr.shape[0]
    normals = None if arr.dtype.names else columns_are_normals(p, arr)
    for start in range(0, n, chunk_size):
        stop = min(start + chunk_size, n)
        yield _npy_cloud(p, np.asarray(arr[start:stop]), f"{p}[{start}:{stop}]", normals)


def count(p: Path) -> int:
    """Rows of the array, from its header."""
    arr = np.load(p, mmap_mode="r", allow_pickle=False)
    _npy_check(p, arr)
    return int(arr.shape[0])


def _npy_check(p: Path, arr: np.ndarray) -> None:
    if arr.dtype.names:
        if not all(a in arr.dtype.names for a in ("x", "y", "z")) or arr.ndim != 1:
            raise InputError(f"{p}: structured NPY array needs fields x, y, z "
                             f"(got {', '.join(arr.dtype.names)})")
        return
    if arr.ndim != 2 or arr.shape[1] < 3 or arr.dtype.kind not in "iuf":
        raise InputError(f"{p}: expected an (N, 3) or (N, 6) numeric array, found shape {arr.shape} "
                         f"dtype {arr.dtype}")


def _npy_cloud(p: Path, arr: np.ndarray, source: str, normals: bool | None = None) -> PointCloud:
    if arr.dtype.names:
        xyz = np.column_stack([np.asarray(arr[a], dtype=np.float64) for a in ("x", "y", "z")])
        normals = None
        if all(a in arr.dtype.names for a in ("nx", "ny", "nz")):
            normals = unit_normals(np.column_stack([arr[a] for a in ("nx", "ny", "nz")]))
        return PointCloud(xyz, normals=normals, source=source, report={"points_read": len(xyz)})
    cloud = columns_cloud(p, arr, source, normals=normals)
    cloud.report = {"points_read": len(cloud)}
    return cloud


def _read_npy(p: Path) -> PointCloud:
    # mmap first: the header's shape is checked against the file size before anything is allocated.
    arr = np.load(p, mmap_mode="r", allow_pickle=False)
    _npy_check(p, arr)
    return _npy_cloud(p, np.asarray(arr), str(p))

