"""Checks and error conversion shared by the point-cloud readers: every problem with an input file becomes one
:class:`~tiled_gridpull.errors.InputError` line that starts with the file path, never a parser's traceback."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from ..errors import GridPullError, InputError

__all__ = ["check_path", "input_errors"]


def check_path(path: str | os.PathLike) -> Path:
    """``path`` as a Path; InputError when it does not exist or cannot be read."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: file not found")
    if not os.access(p, os.R_OK):
        raise InputError(f"{p}: permission denied (cannot read)")
    return p


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

