"""Checks and error conversion shared by the point-cloud readers: every problem with an input file becomes one
:class:`~tiled_gridpull.errors.InputError` line that starts with the file path, never a parser's traceback."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..cloud import COORDINATE_LIMIT
from ..errors import GridPullError, InputError

__all__ = ["check_path", "input_errors", "check_frame"]


def check_path(path: str | os.PathLike) -> Path:
    """``path`` as a Path; InputError when it does not exist or cannot be read."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: file not found")
    if not os.access(p, os.R_OK):
        raise InputError(f"{p}: permission denied (cannot read)")
    return p


def check_frame(where: str, offset, scale=None, *, reach: float = 0.0, written: str | None = None,
                label: str = "offset") -> None:
    """Refuse the offset (and scale) a file's header applies to every coordinate when the coordinates they
    make cannot be computed with: not finite, a zero scale, or beyond
    :data:`~tiled_gridpull.cloud.COORDINATE_LIMIT` (an offset of 1e308 passes every reader, then overflows the
    first sum over the points). Such values are damage, not data; the message names them.

    Parameters
    ----------
    where : str
        The file and header, as the message starts (``"<path>: the LAS header's"``).
    offset : (3,) float
    scale : (3,) float, optional
        Multiplies stored integers of up to ``reach`` in magnitude.
    reach : float
        Largest stored value the scale multiplies (2**31 for LAS's int32 records).
    written : str, optional
        The offset as the header writes it, shown instead of the parsed numbers.
    label : str
        What the header calls the offset ("offset", an E57 pose's "translation").

    Raises
    ------
    InputError
        Naming the offset or the scale.
    """
    offset = np.asarray(offset, dtype=np.float64)
    shown_offset = written if written is not None else " ".join(f"{v:g}" for v in offset)
    if not np.all(np.isfinite(offset)) or np.abs(offset).max() > COORDINATE_LIMIT:
        raise InputError(f"{where} {label} '{shown_offset}' is not 3 finite numbers within +-{COORDINATE_LIMIT:g} "
                         "(coordinates beyond that overflow float64 arithmetic): a damaged header")
    if scale is None:
        return
    scale = np.asarray(scale, dtype=np.float64)
    shown_scale = " ".join(f"{v:g}" for v in scale)
    if not np.all(np.isfinite(scale)) or np.any(scale == 0):
        raise InputError(f"{where} scale '{shown_scale}' is not 3 finite non-zero numbers: a damaged header")
    with np.errstate(over="ignore"):  # a scale of 1e300 times 2**31 is inf: refused all the same
        largest = np.max(np.abs(offset) + np.abs(scale) * reach)
    if largest > COORDINATE_LIMIT:
        raise InputError(f"{where} scale '{shown_scale}' puts coordinates beyond +-{COORDINATE_LIMIT:g} "
                         "(which overflow float64 arithmetic): a damaged header")


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    msg = text[0] if text else "malformed"
    if len(msg) > 160:
        msg = msg[:157] + "..."
    return f"{exc.__class__.__name__}: {msg}"


@contextlib.contextmanager
def input_errors(path: Path, kind: str, problem: str | None = None) -> Iterator[None]:
    """Turn any parser failure into a one-line InputError naming the file (never a traceback).

    ``kind`` names the format in messages ("LAZ", "PLY", "KITTI sequence", ...); ``problem`` says what a parser
    failure means (default "truncated or corrupted <kind> file").
    """
    problem = problem or f"truncated or corrupted {kind} file"
    from .remote import shown

    path = shown(path)  # messages never carry a pre-signed URL's query
    try:
        yield
    except GridPullError:
        raise
    except MemoryError:
        # Header counts are checked against the file size before reading, but third-party parsers (laspy's
        # VLR reader, lazrs) still size some buffers from fields we cannot check; either way the file cannot
        # be read.
        raise InputError(f"{path}: out of memory while reading the {kind} file (corrupted header, or the "
                         f"file is too large to read whole: stream it with iter_point_chunks)") from None
    except PermissionError:
        raise InputError(f"{path}: permission denied (cannot read)") from None
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read file ({_reason(exc)})") from None
    except Exception as exc:  # parsers raise anything (ValueError, LaspyException, LazrsError, ...)
        raise InputError(f"{path}: {problem} ({_reason(exc)})") from None
    except BaseException as exc:
        # a Rust extension (lazrs) that panics raises pyo3's PanicException, which derives from BaseException
        if type(exc).__name__ != "PanicException":
            raise
        raise InputError(f"{path}: {problem} ({_reason(exc)})") from None

