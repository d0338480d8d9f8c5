"""A solved tile's field on disk: written atomically as ``.npz``, read back, and checksummed by content."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from .blend import TileField
from .io.atomic import atomic_path, npz_document, save_npz
from .tile_plan import TileSpec

__all__ = ["field_checksum", "save_tile_field", "load_tile_field", "save_solved_field", "load_solved_field"]

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


def save_solved_field(path: str | Path, fld, state: dict) -> None:
    """Write a tile's field as its solve left it (before the orientation check, bridging and the global brick
    numbering of :func:`save_tile_field`), with ``state`` (JSON), atomically as ``.npz``: on a card the batch
    solves on the card's worker and each tile is finished on another (:func:`load_solved_field`).

    Parameters
    ----------
    fld : :class:`~tiled_gridpull.field.Field`
        On the tile's local lattice; its ``info`` must be JSON (NumPy scalars become numbers).
    """
    band = fld.band
    save_npz(path, {"brick_coords": band.brick_coords, "flags": band.flags, "values": fld.values},
             meta={"m1": band.m1, "m2": band.m2, "signed": fld.signed, "info": fld.info, "stats": band.stats,
                   "state": state})


def load_solved_field(path: str | Path, lattice):
    """The field :func:`save_solved_field` wrote, on ``lattice`` (the tile's local one), and its ``state``.

    Returns
    -------
    (Field, dict)

    Raises
    ------
    OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile
        ``path`` missing or damaged.
    """
    from .band import Band, dense_brick_table
    from .field import Field
    from .kernels import BRICK
    from .kernels.band import brick_neighbors

    with np.load(path) as z:
        coords = np.ascontiguousarray(z["brick_coords"])
        flags, values = np.ascontiguousarray(z["flags"]), np.ascontiguousarray(z["values"])
        meta = npz_document(z, "meta")
    bshape = tuple(int(v) for v in -(-np.asarray(lattice.shape) // BRICK))
    table = dense_brick_table(bshape, coords)
    band = Band(lattice, int(meta["m1"]), int(meta["m2"]), coords, table, brick_neighbors(coords, table), flags,
                meta.get("stats") or {})
    return Field(band, values, bool(meta["signed"]), meta["info"]), meta["state"]
