"""Numeric tables as point clouds: x y z, then normals or extra columns (text files and NPY arrays)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..cloud import PointCloud, unit_normals

__all__ = ["columns_are_normals", "columns_cloud"]


def _looks_like_normals(n: np.ndarray) -> bool:
    """Whether positional columns 4-6 hold normals (unit or zero vectors) rather than, say, RGB values."""
    n = np.asarray(n, dtype=np.float64)
    if len(n) == 0:
        return True
    length = np.sqrt(np.einsum("ij,ij->i", n, n))
    ok = (np.abs(length - 1.0) < 0.1) | (length == 0)
    return bool(np.mean(ok) >= 0.99)


def columns_are_normals(p: Path, data: np.ndarray) -> bool:
    """Decide once per file whether columns 4-6 of a (N, k >= 6) table are normals; warn when they are not.

    Judged on at most ~100k evenly spaced rows, so chunks of one file are all read the same way.
    """
    if data.shape[1] < 6:
        return False
    step = max(1, len(data) // 100_000)
    if _looks_like_normals(data[::step, 3:6]):
        return True
    warnings.warn(f"{p}: columns 4-6 are not unit vectors, so they are not read as normals "
                  f"(kept as attributes['extra_columns'])", UserWarning, stacklevel=5)
    return False


def columns_cloud(p: Path, data: np.ndarray, source: str, *, pts: bool = False,
                   normals: bool | None = None) -> PointCloud:
    """Cloud from a (N, k >= 3) numeric table: x y z, then normals (or extra columns).

    ``normals`` says whether columns 4-6 are normals (None: decide from ``data``).
    """
    xyz = np.array(data[:, :3], dtype=np.float64)
    attrs: dict = {}
    k = data.shape[1]
    if pts:
        # Leica PTS: x y z intensity [r g b]
        if k >= 4:
            attrs["intensity"] = np.asarray(data[:, 3], dtype=np.float32)
        if k >= 7:  # 8-bit colour
            for j, c in enumerate(("red", "green", "blue")):
                attrs[c] = np.clip(np.rint(np.nan_to_num(data[:, 4 + j])), 0, 255).astype(np.uint8)
        return PointCloud(xyz, attributes=attrs, source=source)
    if normals is None:
        normals = columns_are_normals(p, data)
    unit = None
    if normals:
        unit = unit_normals(data[:, 3:6])
        if k > 6:
            attrs["extra_columns"] = np.array(data[:, 6:], dtype=np.float64)
    elif k > 3:
        attrs["extra_columns"] = np.array(data[:, 3:], dtype=np.float64)
    return PointCloud(xyz, normals=unit, attributes=attrs, source=source)

