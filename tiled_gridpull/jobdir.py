"""The job directory: where a tiled job keeps its files, their record layouts, and the lock that keeps it to one job.

A job directory holds everything a run produces, so a finished or interrupted job can be inspected and resumed
(:mod:`tiled_gridpull.resume`):

* ``manifest.json``: the tile plan and the tiles (:func:`write_manifest`), written last by the partition;
* ``points/<tile>.points``: each tile's spill file, records of :data:`SPILL_RECORD` (or
  :data:`SPILL_RECORD_SENSOR` when sensor origins are known), and ``points/<tile>.occ.npy``, its occupied-brick
  mask (:mod:`tiled_gridpull.partition`); ``points/<tile>.attrs`` beside it when the job carries point attributes
  (one record of them per point, in the spill file's order: :func:`tiled_gridpull.partition.attribute_record`);
* ``fields/<tile>.npz``: solved tile fields (:mod:`tiled_gridpull.tile_field`);
* ``pieces/<tile>.npz``: tile meshes (:mod:`tiled_gridpull.stitch`);
* ``prepared/<tile>.npz``: on a card, a tile read and set up on a CPU worker
  (:meth:`tiled_gridpull.tile_solve.PreparedTile.save`), and ``prepared/<tile>.solved.npz``, its field as the
  batch on the card left it (:func:`tiled_gridpull.tile_field.save_solved_field`), until the tile's finish
  removes both;
* ``summaries/<step>_<tile>.json``: one JSON per finished tile step, with the key of what produced it;
* ``report.json`` and ``tiles.png`` once the job finished (:mod:`tiled_gridpull.report`);
* ``.lock``: held while a job runs (:func:`job_lock`).

A work directory may be one the user chose and keeps files of their own in: :func:`check_job_dir` refuses, before
a job reads or writes anything there, a fixed-name file this tool did not write and a folder that is a link.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ._version import __version__
from .errors import ConfigError, InputError
from .io.atomic import write_json
from .io.outputs import GENERATOR_PREFIX, load_json_file, read_regular, written_by_us
from .lattice import Lattice
from .tile_plan import TilePlan, TileSpec

__all__ = ["JobPaths", "job_lock", "check_job_dir", "JOB_FILES", "JOB_FOLDERS", "REPORT_NAME", "LAYOUT_NAME",
           "SPILL_RECORD", "SPILL_RECORD_SENSOR", "SPILL_RECORD_EXACT", "SPILL_RECORD_EXACT_SENSOR", "spill_record",
           "neighbors_of", "write_manifest", "read_manifest", "sample_job_points"]

#: One point of a spill file: float32 coordinates in metres from the block's low corner (tile-local).
SPILL_RECORD = np.dtype([("xyz", "<f4", (3,))])
#: One point of a spill file with its sensor origin (tile-local float32 metres, like ``xyz``).
SPILL_RECORD_SENSOR = np.dtype([("xyz", "<f4", (3,)), ("sensor", "<f4", (3,))])
#: The layouts of a denoising job (``TilingConfig.halo``): float64 offsets, because the difference of a
#: georeferenced coordinate and a corner near it is exact (Sterbenz), so every tile holds a shared point at the
#: same offsets from its neighbours. Denoising needs that to give it the same place in every tile: float32
#: rounding, different per corner, flipped neighbours tied at the radius by millimetres.
SPILL_RECORD_EXACT = np.dtype([("xyz", "<f8", (3,))])
SPILL_RECORD_EXACT_SENSOR = np.dtype([("xyz", "<f8", (3,)), ("sensor", "<f4", (3,))])


def spill_record(has_sensor: bool, exact: bool = False) -> np.dtype:
    """The record layout of a spill file with or without sensor origins, float32 or ``exact`` float64 offsets."""
    if exact:
        return SPILL_RECORD_EXACT_SENSOR if has_sensor else SPILL_RECORD_EXACT
    return SPILL_RECORD_SENSOR if has_sensor else SPILL_RECORD


#: The job's report and its picture (:mod:`tiled_gridpull.report`).
REPORT_NAME = "report.json"
LAYOUT_NAME = "tiles.png"
#: The files a job writes at fixed names in its directory; each carries the generator marker of
#: :func:`tiled_gridpull.io.outputs.written_by_us` (``.lock`` holds only a PID, and a job never replaces it).
JOB_FILES = ("manifest.json", REPORT_NAME, LAYOUT_NAME)
#: The file :func:`job_lock` holds.
LOCK_NAME = ".lock"
#: The folders a job writes into, and the one a job makes inside one of them (the partition's segments).
JOB_FOLDERS = ("points", "fields", "pieces", "summaries", "prepared", "points/.segments")


class JobPaths:
    """Where a job keeps its intermediate files."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    def points(self) -> Path:
        return self.root / "points"

    def field(self, spec: TileSpec) -> Path:
        return self.root / "fields" / f"{spec.name}.npz"

    def piece(self, spec: TileSpec) -> Path:
        return self.root / "pieces" / f"{spec.name}.npz"

    def prepared_dir(self) -> Path:
        return self.root / "prepared"

    def prepared(self, spec: TileSpec) -> Path:
        return self.prepared_dir() / f"{spec.name}.npz"

    def solved(self, spec: TileSpec) -> Path:
        return self.prepared_dir() / f"{spec.name}.solved.npz"

    def summary(self, step: str, spec: TileSpec) -> Path:
        return self.root / "summaries" / f"{step}_{spec.name}.json"


def check_job_dir(root: str | Path) -> None:
    """Refuse a work directory a job cannot use without harm, before it reads or writes anything there.

    A job replaces its fixed-name files (:data:`JOB_FILES`) only when they carry this tool's generator marker
    (the rule outputs follow, :func:`~tiled_gridpull.io.outputs.written_by_us`): a user's own ``report.json`` in
    the directory they chose is theirs. A folder of the job (:data:`JOB_FOLDERS`) that is a symlink would take
    the job's writes, and the reads that decide what to reuse, to a folder outside the job directory (file
    symlinks are replaced, never written through, by :mod:`tiled_gridpull.io.atomic`). The work directory itself
    may be a link: the user named it.

    A fixed-name file (or the ``.lock``) that is not a regular file (a FIFO, a directory, a device) is refused
    without being opened: reading a FIFO would block the job for good.

    Raises
    ------
    ConfigError
        The directory is a file; a fixed-name file is a link, not a regular file, or was not written by this tool;
        a folder is a link or a file.
    """
    root = Path(root)
    if not root.exists():
        return
    if not root.is_dir():
        raise ConfigError(f"work directory {root} is a file, not a directory")
    for name in (*JOB_FILES, LOCK_NAME):
        _check_not_special(root, name)
    legacy = _legacy_job(root)
    for name in JOB_FILES:
        p = root / name
        if p.exists() and not written_by_us(p) and not (legacy and _legacy_file(p)):
            raise ConfigError(f"work directory {root}: {name} there was not written by tiled-gridpull (a job "
                              f"writes its own {name}): move it, or choose another work directory")
    for name in JOB_FOLDERS:
        p = root / name
        if p.is_symlink():
            raise ConfigError(f"work directory {root}: {name} is a link (to {os.readlink(p)}); a job writes only "
                              "into folders of its own: put a folder there, or choose another work directory")
        if p.exists() and not p.is_dir():
            raise ConfigError(f"work directory {root}: {name} is a file where a job keeps a folder: move it, or "
                              "choose another work directory")


def _check_not_special(root: Path, name: str) -> None:
    """Refuse a link, or anything but a regular file, at a fixed name of the job directory (absent is fine)."""
    p = root / name
    try:
        mode = p.lstat().st_mode
    except FileNotFoundError:
        return
    except OSError as exc:  # e.g. permission: reading it later would fail the same way
        raise ConfigError(f"work directory {root}: {name} cannot be examined ({exc.strerror}): move it, or "
                          "choose another work directory") from None
    if stat.S_ISLNK(mode):
        # a link is nothing this tool writes, and reading the manifest through one would decide reuse
        raise ConfigError(f"work directory {root}: {name} (a link) there was not written by tiled-gridpull (a job "
                          f"writes its own {name}): move it, or choose another work directory")
    if not stat.S_ISREG(mode):
        what = "a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else "not a regular file"
        raise ConfigError(f"work directory {root}: {name} there is {what}, where a job keeps a file of its own: "
                          "move it, or choose another work directory")


def _legacy_file(p: Path) -> bool:
    """Whether the fixed-name file ``p`` of an earlier version's job directory (:func:`_legacy_job`) may be
    replaced without the generator marker: its manifest, and its picture when it is a PNG (the versions before the
    marker wrote ``tiles.png`` without one). ``report.json`` carried ``generator`` in every version: never
    exempt."""
    if p.name == "manifest.json":
        return True
    if p.name == LAYOUT_NAME:
        head = read_regular(p, 8, head=True)
        return head is not None and head.startswith(b"\x89PNG\r\n\x1a\n")
    return False


def _legacy_job(root: Path) -> bool:
    """Whether ``root`` is a job directory of a version that wrote no generator into its manifest and picture
    (those before the marker was recorded): a manifest holding a plan with a lattice and a config, and a list of
    tiles. Its rerun resumes instead of being refused as someone else's directory; the files it exempts from the
    marker are :func:`_legacy_file`'s."""
    p = root / "manifest.json"
    if p.is_symlink():
        return False
    meta = load_json_file(p)  # None for a FIFO, a huge or a too deeply nested file: not a job's manifest
    plan = meta.get("plan") if isinstance(meta, dict) else None
    return (isinstance(plan, dict) and "generator" not in meta and isinstance(plan.get("lattice"), dict)
            and isinstance(plan.get("config"), dict) and isinstance(meta.get("tiles"), list))


@contextlib.contextmanager
def job_lock(root: str | Path) -> Iterator[None]:
    """Hold a work directory for one job: a second job started on it stops at once, naming the holder's PID.

    Two jobs on one directory would interleave their spill files and replace each other's fields. The lock is
    ``flock`` on ``<root>/.lock``: the kernel releases it when the holder exits, even on SIGKILL, so a crashed
    job never leaves the directory locked.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock, as before
        yield
        return
    root = Path(root)
    created = not root.exists()
    root.mkdir(parents=True, exist_ok=True)
    _check_not_special(root, LOCK_NAME)  # a link, a directory or a FIFO: one line, not an OSError
    try:
        # O_NONBLOCK: a FIFO put there after the check does not block the open
        fd = os.open(root / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0),
                     0o666)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.EISDIR, errno.ENXIO):  # became a link, a directory, a socket
            raise ConfigError(f"work directory {root}: {LOCK_NAME} there is not a regular file: move it, or "
                              "choose another work directory") from None
        raise
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ConfigError(f"work directory {root}: {LOCK_NAME} there is not a regular file: move it, or "
                              "choose another work directory")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise ConfigError(f"work directory {root} is in use by another job (PID {holder}): wait for it to "
                              "finish, or give another --work-dir") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.close(fd)
        if created:
            _remove_if_only_the_lock(root)


def _remove_if_only_the_lock(root: Path) -> None:
    """A job that stopped before writing anything (a refused input) leaves no directory of its own behind."""
    try:
        if [p.name for p in root.iterdir()] == [".lock"]:
            (root / ".lock").unlink()
            root.rmdir()
    except OSError:
        pass


def neighbors_of(spec: TileSpec, solved: dict[tuple, TileSpec]) -> list[TileSpec]:
    """Solved tiles whose blocks overlap ``spec``'s (the 26 around it)."""
    out = []
    i, j, k = spec.index
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            for dk in (-1, 0, 1):
                if di == dj == dk == 0:
                    continue
                t = solved.get((i + di, j + dj, k + dk))
                if t is not None:
                    out.append(t)
    return out


def write_manifest(path: str | Path, plan: TilePlan, specs: list[TileSpec], extra: dict | None = None) -> None:
    """Write the tile manifest (plan, per-tile counts and bounds) atomically."""
    # the generator marks the file as the tool's, so a rerun may replace it (check_job_dir)
    data = {"generator": f"{GENERATOR_PREFIX}{__version__}", "plan": plan.to_dict(),
            "tiles": [s.to_dict() for s in specs]}
    if extra:
        data.update(extra)
    write_json(path, data)


def read_manifest(path: str | Path) -> tuple[dict, list[TileSpec]]:
    """Read a tile manifest: the raw dict and the tile specs.

    Raises
    ------
    InputError
        Not a regular file (a FIFO is never opened), larger than
        :data:`~tiled_gridpull.io.outputs.MAX_OWN_FILE`, unreadable, or not a manifest.
    """
    data = load_json_file(path)
    try:
        return data, [TileSpec.from_dict(d) for d in data["tiles"]]
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{path}: not a readable tile manifest (missing, not a regular file, damaged or not "
                         "written by tiled-gridpull)") from None


def sample_job_points(job_dir: str | Path, max_points: int = 50_000) -> np.ndarray:
    """About ``max_points`` input points of a job, read from its tile spill files (each point once).

    Every tile contributes a regular stride of its file (memory-mapped, so a huge job reads only the pages it
    samples), keeping the points inside its own core.

    Parameters
    ----------
    job_dir : str or Path
        A job directory with its ``manifest.json``.
    max_points : int

    Returns
    -------
    (N, 3) float64
        World coordinates.

    Raises
    ------
    InputError
        No manifest there (not a tiled job directory).
    """
    manifest = JobPaths(job_dir).manifest
    if not manifest.is_file():
        raise InputError(f"{job_dir}: no manifest.json (not a tiled job directory)")
    data, specs = read_manifest(manifest)
    specs = sorted(specs, key=lambda s: s.index)
    lattice = Lattice.from_dict(data["plan"]["lattice"])
    origin = np.asarray(lattice.origin)
    total = sum(s.n_points for s in specs)
    if total == 0:
        return np.zeros((0, 3))
    step = max(1, int(math.ceil(total / max(int(max_points), 1))))
    out = []
    for spec in specs:
        p = Path(spec.points_path)
        if spec.n_points == 0 or not p.is_file() or p.stat().st_size == 0:
            continue
        rec = np.memmap(p, dtype=spill_record(spec.has_sensor, spec.exact_offsets), mode="r")
        xyz = np.asarray(rec["xyz"][::step], dtype=np.float64) + spec.block.low_corner
        lo = origin + np.asarray(spec.core_lo) * lattice.cell_size
        hi = origin + np.asarray(spec.core_hi) * lattice.cell_size
        out.append(xyz[np.all((xyz >= lo) & (xyz < hi), axis=1)])
    return np.concatenate(out) if out else np.zeros((0, 3))
