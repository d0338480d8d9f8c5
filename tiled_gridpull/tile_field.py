"""A solved tile's field on disk: written atomically as ``.npz``, read back, and checksummed by content."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from .blend import TileField
from .io.atomic import atomic_path
from .tile_plan import TileSpec

__all__ = ["field_checksum", "save_tile_field", "load_tile_field"]

def field_checksum(brick_coords: np.ndarray, values: np.ndarray, flags: np.ndarray) -> str:
    """SHA-256 of a tile field's arrays (content, not file bytes: ``.npz`` files carry timestamps)."""
    h = hashlib.sha256()
    for a in (brick_coords, values, flags):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_tile_field(path: str | Path, brick_coords: np.ndarray, values: np.ndarray, flags: np.ndarray) -> str:
    """Write a tile field (global brick coordinates, values in cells, flags) atomically as ``.npz``; returns
    its :func:`field_checksum`."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, brick_coords=brick_coords, values=values, flags=flags)
    return field_checksum(brick_coords, values, flags)


def load_tile_field(path: str | Path, spec: TileSpec, overlap: int) -> TileField:
    """Read a tile field as a :class:`~tiled_gridpull.blend.TileField`."""
    with np.load(path) as z:
        lo = np.asarray(spec.block.offset, np.int64)
        return TileField(tuple(spec.index), lo, lo + np.asarray(spec.block.shape, np.int64) - 1,
                         z["brick_coords"].astype(np.int64), z["values"], z["flags"], int(overlap))
