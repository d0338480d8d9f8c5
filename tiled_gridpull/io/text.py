"""Text point clouds (XYZ, TXT, PTS, CSV): numeric columns x y z [nx ny nz | extra ...], after an optional
header row of column names (or a PTS point-count line); ``#`` and ``//`` start comments."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError
from .columns import columns_cloud

__all__ = ["read", "count"]


def read(p: Path) -> PointCloud:
    """The whole file as a cloud: PTS columns 4-7 are intensity and RGB, other files' 4-6 normals or extras."""
    return _read_text(p, p.suffix.lower())


def count(p: Path) -> int:
    """Data lines of the file, counted without parsing numbers."""
    return _text_count(p, p.suffix.lower())


_FLOAT_RE = re.compile(r"^[+-]?(nan|inf|infinity|(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?)$", re.IGNORECASE)


def _is_comment(line: str) -> bool:
    s = line.lstrip()
    return not s or s.startswith("#") or s.startswith("//")


def _text_layout(p: Path, suffix: str) -> tuple[int, str | None]:
    """(lines to skip, delimiter): skips a header row of column names or a PTS point-count line."""
    delimiter = "," if suffix == ".csv" else None
    with open(p, encoding="latin-1") as fh:
        for i, line in enumerate(fh):
            if _is_comment(line):
                if i > 10_000:
                    break
                continue
            if delimiter is None and "," in line:
                delimiter = ","
            tokens = [t.strip() for t in (line.split(delimiter) if delimiter else line.split())]
            tokens = [t for t in tokens if t]
            numeric = all(_FLOAT_RE.match(t) for t in tokens)
            if not numeric or (len(tokens) == 1 and tokens[0].isdigit()):
                return i + 1, delimiter  # a header of names, or the point count of a PTS file
            return 0, delimiter
    return 0, delimiter


def _read_text(p: Path, suffix: str) -> PointCloud:
    skip, delimiter = _text_layout(p, suffix)
    with warnings.catch_warnings():
        # numpy warns on a file with no data rows; the empty cloud says it better
        warnings.simplefilter("ignore")
        data = np.loadtxt(p, dtype=np.float64, comments=("#", "//"), delimiter=delimiter, skiprows=skip,
                          ndmin=2, encoding="latin-1")
    if data.shape[0] == 0:
        return PointCloud(np.zeros((0, 3)), source=str(p), report={"points_read": 0})
    if data.shape[1] < 3:
        raise InputError(f"{p}: expected at least 3 numeric columns (x y z), found {data.shape[1]}")
    cloud = columns_cloud(p, data, str(p), pts=suffix == ".pts")
    cloud.report = {"points_read": len(cloud)}
    return cloud


def _text_count(p: Path, suffix: str) -> int:
    skip, _ = _text_layout(p, suffix)
    count = 0
    # text mode: the same universal-newline line splitting as np.loadtxt
    with open(p, encoding="latin-1") as fh:
        for i, line in enumerate(fh):
            if i < skip:
                continue
            # Same rule as np.loadtxt: a line counts if anything is left before its first comment marker.
            body = line.split("#", 1)[0].split("//", 1)[0]
            if body.strip():
                count += 1
    return count

