"""Atomic file output: write to a temporary name beside the target, then rename into place.

A run killed mid-write leaves at most a ``.<name>.<random>.tmp`` file, never a target that looks complete. The
temporary file is created exclusively under a fresh name (``O_EXCL``: never through a symlink planted in the
directory, never shared by two jobs), and the rename replaces a symlink at the target rather than writing
through it.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from ..errors import InputError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()


def open_no_follow(path: str | os.PathLike, mode: str = "ab") -> IO:
    """Open ``path`` for appending ("ab") or writing ("wb") without following a symlink at it (``OSError``
    ELOOP if there is one)."""
    flags = os.O_WRONLY | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | (os.O_APPEND if mode == "ab" else os.O_TRUNC)
    return os.fdopen(os.open(path, flags, 0o666), mode)


def replace_file(src: str | os.PathLike, target: str | os.PathLike) -> None:
    """``os.replace`` of a finished temporary file; a directory at ``target`` (damage in a job directory, or a
    user's directory named like an output: never removed for them) is one clear :class:`InputError`."""
    try:
        os.replace(src, target)
    except IsADirectoryError:
        raise InputError(f"{target}: a directory stands where this file is to be written; remove it "
                         "and rerun") from None


@contextlib.contextmanager
def naming(path: str | os.PathLike) -> Iterator[None]:
    """Name ``path`` in an ``OSError`` raised inside without a file name, and raise it again.

    A write the machine refuses (``ENOSPC``, ``EDQUOT``, ``EFBIG``, ``EIO``) fails in ``write`` or ``close``,
    whose errors carry no file name; the command line's one line for a storage error names the file from it
    (README, "Exit codes"). The error keeps its type, number and traceback.
    """
    try:
        yield
    except OSError as exc:
        if exc.filename is None and exc.errno is not None:
            exc.filename = os.fspath(path)
        raise


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``target`` atomically, on error it is removed."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        # mkstemp makes the file private (0600); outputs get the permissions any new file would
        os.chmod(tmp, 0o666 & ~_UMASK)
        with naming(target):  # the file being written, not its temporary name
            yield tmp
            replace_file(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


@contextlib.contextmanager
def atomic_open(target: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file for writing; it becomes ``target`` only when the block completes."""
    with atomic_path(target) as tmp:
        with open(tmp, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())


def write_json(target: str | os.PathLike, data: dict) -> None:
    """Write a JSON document atomically (sorted keys, 2-space indent)."""
    with atomic_open(target, "w") as fh:
        dump_json(fh, data)


def dump_json(fh: IO, data: dict) -> None:
    """The JSON document of :func:`write_json`, into an open text file."""
    import json

    json.dump(data, fh, indent=2, sort_keys=True, default=json_default)
    fh.write("\n")


def save_npz(target: str | os.PathLike, arrays: dict, **documents: dict) -> None:
    """Write ``arrays`` atomically as ``.npz``, with each of ``documents`` as JSON in a uint8 array of its name
    (read back by :func:`npz_document`): a file another process picks up whole, arrays and their account."""
    import json

    import numpy as np

    docs = {name: np.frombuffer(json.dumps(doc, default=json_default).encode(), np.uint8)
            for name, doc in documents.items()}
    with atomic_path(target) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays, **docs)


def npz_document(z, name: str) -> dict:
    """The JSON document :func:`save_npz` stored as ``name`` in the open ``.npz`` ``z``."""
    import json

    return json.loads(z[name].tobytes().decode())


def json_default(obj):
    """``json.dump``'s ``default``: NumPy scalars and arrays, and paths, as plain JSON values (shared by the
    job files written here and the content keys of :mod:`tiled_gridpull.resume`)."""
    import numpy as np

    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
