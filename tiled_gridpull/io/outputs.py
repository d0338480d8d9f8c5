"""Checks on a job's output paths, made before any work: never replace an input, nor a file this tool did not
write, and say so in one line while there is still nothing to lose.

A file counts as written by this tool when it carries the marker every reconstruction writes: the PLY header's
``comment generator tiled_gridpull <version>``, the OBJ's first line ``# generator tiled_gridpull <version>``, a
JSON sidecar (or job file) whose ``generator`` is ``tiled_gridpull <version>``, or a PNG whose ``Software`` text is
``tiled_gridpull <version>`` (:func:`tiled_gridpull.images.save_png`). The sample generator's files
(``tiled_gridpull.synthetic.*``) are not reconstructions and are protected like any other file.

Deciding whether a file is ours never opens one that is not a regular file (a FIFO would block the reader, a
device could be endless), never reads more than :data:`MAX_OWN_FILE` bytes of a JSON document, and takes a
document nested too deeply to parse (``RecursionError``) as not ours (:func:`read_regular`, :func:`load_json_file`).
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Sequence
from pathlib import Path

from ..errors import ConfigError
from .meshes import sidecar_path

#: what ``generator`` of a reconstruction starts with (``tiled_gridpull 0.1.0``)
GENERATOR_PREFIX = "tiled_gridpull "


#: The most bytes of a JSON file read to decide whether this tool wrote it (or to reuse what it records): a
#: larger one is not ours. A job's manifest and report hold about 1 kB per tile, so this is some 250,000 tiles.
MAX_OWN_FILE = 256 << 20


def _resolved(p: str | Path) -> Path:
    return Path(os.path.realpath(p))


def read_regular(path: str | Path, limit: int = MAX_OWN_FILE, *, head: bool = False) -> bytes | None:
    """The bytes of ``path`` when it is a regular file (a symlink is followed), else None; never opens a FIFO,
    device, socket or directory.

    Parameters
    ----------
    path : str or Path
    limit : int
        Bytes read at most.
    head : bool
        Return the first ``limit`` bytes of a larger file; without it a file over ``limit`` bytes gives None.

    Returns
    -------
    bytes or None
        None also when the file is missing or cannot be opened or read.
    """
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        # O_NONBLOCK: a regular file swapped for a FIFO after the stat does not block the open
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except (OSError, ValueError):
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or (st.st_size > limit and not head):
            return None
        with os.fdopen(os.dup(fd), "rb") as fh:
            data = fh.read(limit + 1)
    except OSError:
        return None
    finally:
        os.close(fd)
    if len(data) > limit:
        return data[:limit] if head else None
    return data


def load_json_file(path: str | Path, limit: int = MAX_OWN_FILE):
    """The JSON document in ``path`` (:func:`read_regular`), or None when it is not a regular file, larger than
    ``limit`` bytes, unreadable, not JSON, or nested too deeply to parse."""
    data = read_regular(path, limit)
    if data is None:
        return None
    try:
        return json.loads(data)
    except (ValueError, RecursionError):  # UnicodeDecodeError is a ValueError
        return None


def written_by_us(path: str | Path) -> bool:
    """True when ``path`` is a mesh, sidecar, job file or picture written by this tool (see the module's
    docstring)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        meta = load_json_file(path)
        gen = meta.get("generator") if isinstance(meta, dict) else None
        return isinstance(gen, str) and gen.startswith(GENERATOR_PREFIX)
    marker = {".ply": b"comment generator " + GENERATOR_PREFIX.encode(),
              ".obj": b"# generator " + GENERATOR_PREFIX.encode(),
              ".png": b"tEXtSoftware\0" + GENERATOR_PREFIX.encode()}.get(suffix)
    if marker is None:
        return False
    head = read_regular(path, 4096, head=True)
    if head is None:
        return False
    if suffix == ".ply":
        header = head.split(b"end_header", 1)[0]
        return any(line.strip().startswith(marker) for line in header.splitlines())
    if suffix == ".png":  # a text chunk before the image data, which save_png writes right after the header
        return head.startswith(b"\x89PNG") and marker in head.split(b"IDAT", 1)[0]
    return head.startswith(marker)


def _existing_ancestor(path: Path) -> Path:
    """The nearest ancestor of ``path`` that exists (the directory a write would have to create its way from)."""
    d = path.parent
    while not d.exists() and d != d.parent:
        d = d.parent
    return d


def _writable_dir(path: Path) -> Path | None:
    """The nearest existing ancestor of ``path`` when it cannot be written into, else None."""
    d = _existing_ancestor(path)
    return None if os.access(d, os.W_OK | os.X_OK) else d


def check_output_file(path: str | Path, what: str = "output") -> None:
    """Refuse, before any work, a file output that cannot be written: a directory, a path through a file, or a
    directory that cannot be written into (:class:`ConfigError`, one line naming ``path``)."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{what} {path} is a directory")
    d = _existing_ancestor(path)
    if not d.is_dir():
        raise ConfigError(f"{what} {path}: {d} is a file, not a directory")
    blocked = _writable_dir(path)
    if blocked is not None:
        raise ConfigError(f"{what} {path}: directory {blocked} is not writable")


def check_outputs(inputs: Sequence[str | Path], mesh: str | Path, *, work_dir: str | Path | None = None,
                  tile_meshes: str | Path | None = None, overwrite: bool = False) -> None:
    """Refuse output paths that would lose data, before anything is read or solved.

    Parameters
    ----------
    inputs : sequence of path
        Input files (or KITTI sequence directories).
    mesh : path
        The output mesh; its JSON sidecar is ``mesh`` with the suffix ``.json``.
    work_dir, tile_meshes : path, optional
        The tiled job's work directory and ``--tile-meshes`` directory.
    overwrite : bool
        Replace an existing mesh or sidecar even when this tool did not write it (never an input).

    Raises
    ------
    ConfigError
        When an output is an input, would be written into an input, is a directory where a file goes (or a file
        where a directory goes), lies in a directory that cannot be written, or exists without this tool's marker
        and ``overwrite`` is False.
    """
    from .remote import is_url

    inputs = [p for p in inputs if not is_url(p)]  # a URL is nothing an output could overwrite
    ins = [_resolved(p) for p in inputs]
    mesh = Path(mesh)
    files = {"output": mesh, "sidecar": sidecar_path(mesh)}
    for what, path in files.items():
        r = _resolved(path)
        for src, orig in zip(ins, inputs):
            if r == src:
                raise ConfigError(f"{what} {path} is the input {orig}: refusing to overwrite an input")
        check_output_file(path, what)
        if path.exists() and not overwrite and not written_by_us(path):
            raise ConfigError(f"{what} {path} exists and was not written by tiled-gridpull: pass --overwrite to "
                              "replace it, or choose another name")
    for what, d in (("--work-dir", work_dir), ("--tile-meshes", tile_meshes)):
        if d is None:
            continue
        d = Path(d)
        if d.exists() and not d.is_dir():
            raise ConfigError(f"{what} {d} is a file, not a directory")
        rd = _resolved(d)
        for src, orig in zip(ins, inputs):
            # the work directory is the job's to rewrite as a whole; tile meshes only take tile_*.ply names
            clash = rd in src.parents if what == "--work-dir" else (
                src.parent == rd and src.name.startswith("tile_") and src.suffix.lower() == ".ply")
            if rd == src or clash:
                raise ConfigError(f"{what} {d} holds the input {orig}: job files there could replace it; "
                                  "choose another directory")
        blocked = _writable_dir(d / "x")
        if blocked is not None:
            raise ConfigError(f"{what} {d}: directory {blocked} is not writable")
