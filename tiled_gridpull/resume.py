"""Resuming a tiled job: every result is keyed on what produced it, and reused only when that is unchanged.

A job directory (see :mod:`tiled_gridpull.jobdir`) keeps three kinds of results, each written
atomically (a killed run leaves at most a hidden temporary file, never a result that looks complete):

* the **partition** (``points/*.points`` spill files, ``points/*.occ.npy`` occupancy masks and ``manifest.json``).
  Its key hashes each input's resolved path, size and modification time (every file of a KITTI sequence directory;
  an EPT's header, hierarchy pages and node files), the frame range, the settings that decide the tile grid
  (``voxel_size`` and the tile and overlap cell counts) and the package version. The manifest, written last, is the
  commit record: it is removed before a new partition starts, so an interrupted partition is never mistaken for a
  finished one.
* each tile's **field** (``fields/<tile>.npz``), recorded in ``summaries/solve_<tile>.json`` with its key: the
  SHA-256 of the tile's spill file content, its block, the tiling settings a solve reads (``min_points``,
  the resolved orientation rule, ``normal_neighbors``), every solver setting a tile solve reads (not
  ``resolution``, ``margin``, ``normal_weight``, nor ``init``/``init_radius`` unless orientation is
  ``sphere``), the input's centre for ``outward``, and the package version; plus the SHA-256 of the field's
  arrays.
* each tile's **mesh piece** (``pieces/<tile>.npz``), recorded in ``summaries/mesh_<tile>.json`` with its key:
  the field checksums of the tile and of its solved neighbours, its meshed cell range, ``trim_distance``,
  the overlap, the job's edge-key origin, the spill file checksum (trimming reads the points) and the version.

A result is reused when its summary's key equals the key the current run computes and its output file is
still the one the summary describes: same size and the same SHA-256 of its bytes (a file damaged in place, even
with its size and modification time kept, is recomputed and that run's summary says why in ``redone``; a later
run that reuses the new result says nothing of it). Spill files
are checked against their recorded SHA-256 before a partition is reused. Anything else is recomputed. Solves
and meshes are deterministic, so a resumed job writes the same mesh, byte for byte, as an uninterrupted one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import stat
import zipfile
from pathlib import Path

import numpy as np

from ._version import __version__
from .bridge import BridgeRule
from .config import SolverConfig
from .errors import ConfigError, InputError
from .io.atomic import json_default, write_json
from .io.outputs import load_json_file
from .io.remote import is_url, validators
from .jobdir import JobPaths, spill_record
from .memory import reset_peak_rss
from .partition import attribute_record
from .stitch import mesh_tile
from .tile_plan import TileSpec, plan_tiles
from .tile_field import load_solved_field, save_solved_field
from .tile_solve import (PreparedTile, finish_prepared, orientation_rule, prepare_tile, solve_prepared_fields,
                         solve_tile, tile_summary)
from .tiling import TilingConfig

__all__ = ["partition_key", "load_partition", "solve_key", "mesh_key", "solve_tile_resumable",
           "prepare_tile_resumable", "solve_batch_resumable", "finish_tile_resumable", "mesh_tile_resumable",
           "input_fingerprint"]

SPILL_FORMAT = 3  # bump when the spill/occupancy layout or the order of a tile's points changes


def digest(obj) -> str:
    """SHA-256 of a JSON-serialisable object (sorted keys, so dict order never matters)."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=json_default)
    return hashlib.sha256(text.encode()).hexdigest()


def _stat(path: Path) -> dict:
    st = path.stat()
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns}


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def input_fingerprint(inputs: list) -> list[dict]:
    """Resolved path, size and modification time of every input (every file of a sequence directory)."""
    out = []
    for raw in inputs:
        if is_url(raw):
            out.append(_url_fingerprint(raw))
            continue
        p = Path(raw).resolve()
        try:
            if p.is_dir():
                from .io.kitti import kitti_sequence_files

                # only what the reader reads: a job writing its output inside the sequence would change the key
                # of its own partition and never reuse it
                files = kitti_sequence_files(p)
                out.append({"path": str(p),
                            "files": [[str(f.relative_to(p)), *_stat(f).values()] for f in files]})
            elif p.name.lower() == "ept.json":
                from .io.indexed import ept_files

                # an EPT is its header, hierarchy pages and node files
                out.append({"path": str(p), "files": [[str(f.relative_to(p.parent)), *_stat(f).values()]
                                                      for f in ept_files(p)]})
            else:
                out.append({"path": str(p), **_stat(p)})
        except (OSError, InputError):  # missing, unreadable or not a sequence: the scan reports it; never reused
            out.append({"path": str(p), "unreadable": os.urandom(8).hex()})
    return out


def _url_fingerprint(url: str) -> dict:
    """A URL input's version on its server: the file's size, ETag and Last-Modified; for an EPT also its
    hierarchy's root page (what it holds, as bytes), since an EPT is rewritten file by file. A node file
    replaced on the server under the same hierarchy is not seen (asking for every node's headers would cost a
    request per node); each tile's solve key still hashes the points it read."""
    from .io.indexed import indexed_kind
    from .io.remote import fetch, url_join

    try:
        facts = validators(url)
        if indexed_kind(url) == "EPT":
            root = fetch(url_join(url, "ept-hierarchy", "0-0-0-0.json"))
            facts["hierarchy_sha256"] = hashlib.sha256(root).hexdigest()
        return facts
    except InputError:  # unreachable: the scan reports it; never reused
        return {"url": url, "unreadable": os.urandom(8).hex()}


def partition_key(inputs: list, tiling: TilingConfig, frames=None, trajectory=None) -> str:
    """Key of a partition: inputs (path, size, mtime), frames, trajectory file, tile grid settings, version."""
    facts = {"inputs": input_fingerprint(inputs), "frames": list(frames) if frames else None,
             "voxel_size": tiling.voxel_size, "tile_cells": tiling.tile_cells,
             "overlap_cells": tiling.overlap_cells, "version": __version__, "format": SPILL_FORMAT}
    if trajectory is not None:  # only when set, likewise
        facts["trajectory"] = input_fingerprint([trajectory])
    if tiling.drop_outliers:  # only when set: keys of partitions made without it stay as they were
        facts["drop_outliers"] = True
    if tiling.halo:  # likewise; such a partition stores exact (float64) offsets
        facts["halo"] = tiling.halo
        facts["exact_offsets"] = True
    if tiling.attributes != "none":  # what the attribute spill files hold
        facts["attributes"] = tiling.attributes
    return digest(facts)


def load_partition(paths: JobPaths, key: str, tiling: TilingConfig):
    """The plan, tiles and scan facts of a finished partition with this key, or None.

    Each tile's spill file must exist with the size its point count implies, and its occupancy mask must exist.
    """
    # never through a link, never a FIFO or a file too large or too deeply nested to be the job's own
    data = None if paths.manifest.is_symlink() else load_json_file(paths.manifest)
    if not isinstance(data, dict) or data.get("partition_key") != key or "scan" not in data:
        return None
    try:
        scan = data["scan"]
        bounds = np.asarray(scan["bounds"], dtype=np.float64)
        plan = plan_tiles(bounds, int(scan["points"]), tiling)
        if plan.to_dict()["lattice"] != data["plan"]["lattice"]:
            return None
        specs = []
        for d in data["tiles"]:
            spec = TileSpec.from_dict(d)
            spill = paths.points() / f"{spec.name}.points"
            size = spill_record(spec.has_sensor, spec.exact_offsets).itemsize * spec.n_points
            spec = dataclasses.replace(spec, points_path=str(spill))
            # never through a link: what the job reuses must be its own file
            if (not spec.points_sha256 or spill.is_symlink() or not spill.is_file() or spill.stat().st_size != size
                    or Path(spec.occupancy_path).is_symlink() or not Path(spec.occupancy_path).is_file()):
                return None
            # the spill's content is what every solve key stands on: a damaged one means partitioning again
            if file_sha256(spill) != spec.points_sha256:
                return None
            if spec.attributes:  # the attribute spill file beside it, likewise
                attrs = Path(spec.attributes_path)
                size = attribute_record(spec.attributes).itemsize * spec.n_points
                if (attrs.is_symlink() or not attrs.is_file() or attrs.stat().st_size != size
                        or file_sha256(attrs) != spec.attributes_sha256):
                    return None
            specs.append(spec)
    except (KeyError, TypeError, ValueError):
        return None
    facts = {"bounds": bounds, "points": int(scan["points"]), "has_sensor": bool(scan["has_sensor"]),
             "crs": scan.get("crs"), "partition_reused": True,
             "attributes": [(str(n), str(t)) for n, t in scan.get("attributes", [])]}
    return plan, specs, facts


def scan_record(scan: dict) -> dict:
    """The scan facts a manifest keeps (so a reused partition needs no new pass over the inputs)."""
    return {"bounds": np.asarray(scan["bounds"]).tolist(), "points": int(scan["points"]),
            "has_sensor": bool(scan["has_sensor"]), "crs": scan.get("crs"),
            "far_points_dropped": int(scan.get("far_points_dropped", 0)),
            "attributes": [list(a) for a in scan.get("attributes", [])],
            **({"trajectory": scan["trajectory"]} if scan.get("trajectory") else {})}


# ------------------------------------------------------------------------------------------------ tile results


#: the settings of the shadow test (bridging with sensor origins) that a solve's key names
_BRIDGE_SEEN = [BridgeRule.beyond_deg, BridgeRule.sensor_max_gap_deg, BridgeRule.sensor_rms_tol]
#: what else bridging with sensor origins reads since 2026-11-27: ground the sensor could not have seen stays
#: open, and things standing on the ground leave the plane fits (the width is the ``bridge_objects`` setting)
_BRIDGE_HIDDEN = [BridgeRule.shadow_tol, BridgeRule.shadow_reach, BridgeRule.min_facing, BridgeRule.object_tol,
                  # and, since 2026-11-27 (night), a plane a beam passed under is not there
                  BridgeRule.pierce_tol, BridgeRule.pierce_beams, BridgeRule.pierce_skip]


def solve_key(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, centre=None) -> str:
    """Key of a tile's solve: its points (content hash), block, and the settings a tile solve reads."""
    try:
        rule = orientation_rule(tiling, spec.has_sensor)
    except ConfigError:
        rule = tiling.orientation
    settings = solver.solve_settings(sphere_init=rule == "sphere")
    return digest({"points_sha256": spec.points_sha256, "n_points": spec.n_points, "has_sensor": spec.has_sensor,
                   "block": spec.block.to_dict(), "min_points": tiling.min_points, "orientation": rule,
                   "normal_neighbors": tiling.normal_neighbors, "solver": settings,
                   "centre": list(centre) if rule == "outward" and centre is not None else None,
                   "version": __version__,
                   # only when on: keys of jobs that do not bridge stay those they were
                   **({"bridge": tiling.bridge} if tiling.bridge else {}),
                   # bridges of tiles with sensor origins keep shadows open since 2026-11-26
                   **({"bridge_seen": _BRIDGE_SEEN, "bridge_hidden": [tiling.bridge_objects, *_BRIDGE_HIDDEN]}
                      if tiling.bridge and spec.has_sensor else {})})


def mesh_key(spec: TileSpec, field_sha: str, neighbors: list[tuple[str, str]], tiling: TilingConfig,
             key_ref) -> str:
    """Key of a tile's mesh piece: the fields it blends (own and solved neighbours') and the meshing settings."""
    return digest({"tile": spec.name, "field_sha256": field_sha, "neighbors": sorted(neighbors),
                   "block": spec.block.to_dict(), "mesh_lo": list(spec.mesh_lo), "mesh_hi": list(spec.mesh_hi),
                   "overlap_cells": tiling.overlap_cells, "trim_distance": tiling.trim_distance,
                   "points_sha256": spec.points_sha256 if tiling.trim_distance > 0 else None,
                   "key_ref": [int(v) for v in np.asarray(key_ref)], "version": __version__,
                   # only when carried: keys of pieces without attributes stay as they were
                   **({"attributes": [list(a) for a in spec.attributes],
                       "attributes_sha256": spec.attributes_sha256} if spec.attributes else {})})


def _reusable(summary_path: Path, key: str, statuses: tuple, output: str | Path) -> tuple[dict | None, str | None]:
    """``(summary, None)`` if the recorded summary's key matches and ``output`` (when it records one) is the file
    it describes, byte for byte; else ``(None, why)``, ``why`` naming a damaged or missing output when the
    record itself matched (None when there was nothing to reuse)."""
    # a link is nothing the job wrote: never read to decide reuse (the result is computed again, the link replaced)
    # nor anything but a regular file: a FIFO there blocked the run for good (load_json_file never opens one)
    if Path(summary_path).is_symlink():
        return None, None
    prev = load_json_file(summary_path)
    if not isinstance(prev, dict) or prev.get("key") != key or prev.get("status") not in statuses:
        return None, None
    rec = prev.get("output")
    if rec is not None:
        if Path(output).is_symlink():
            return None, f"{output} is a link"
        try:
            st = Path(output).stat()
            if not stat.S_ISREG(st.st_mode):  # a FIFO's checksum would never end
                return None, f"{output} is not a regular file"
            if st.st_size != rec["size"]:
                return None, f"{output} changed size since it was written"
            if file_sha256(output) != rec["sha256"]:
                return None, f"{output} is damaged (SHA-256 differs from the one recorded)"
        except OSError:
            return None, f"{output} is missing or unreadable"
        except (KeyError, TypeError):
            return None, None  # a record of an older layout: recompute quietly
    # ``redone`` told why the run that wrote this record computed it again; this run computed nothing, and a
    # reused record that kept it had every later rerun warn of damage long mended
    prev.pop("redone", None)
    prev["reused"] = True
    return prev, None


def _record(summary: dict, summary_path: str | Path, key: str, output: str | Path | None) -> None:
    summary["key"] = key
    if output is not None:
        summary["output"] = {**_stat(Path(output)), "sha256": file_sha256(output)}
    write_json(summary_path, summary)


def solve_tile_resumable(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str | Path,
                         summary_path: str | Path, centre=None, before_solve=None) -> dict:
    """:func:`tiled_gridpull.tile_solve.solve_tile`, unless its summary shows the same key and the field is intact.

    Solved and skipped tiles are recorded (skipping depends only on the key too); failed tiles are not, so a
    rerun tries them again. ``before_solve()`` runs only when the tile is actually solved (a test hook).
    """
    key = solve_key(spec, tiling, solver, centre)
    prev, why = _reusable(Path(summary_path), key, ("solved", "skipped"), field_path)
    if prev is not None:
        return prev
    if before_solve is not None:
        before_solve()
    out = solve_tile(spec, tiling, solver, field_path, centre=centre)
    if why:
        out["redone"] = why
    return _close_solve(out, key, summary_path, field_path)


def prepare_tile_resumable(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str | Path,
                           summary_path: str | Path, prepared_path: str | Path, centre=None,
                           solved_path: str | Path | None = None) -> dict:
    """The first step of a tile solved in a batch (on a card): its recorded summary when it can be reused; else
    the tile read and set up (:func:`tiled_gridpull.tile_solve.prepare_tile`) and written to ``prepared_path``
    for :func:`solve_batch_resumable`, with a summary of status ``"prepared"``; a tile that needs no solve
    (skipped, failed) gets its final summary here. An earlier run's files of the tile (``prepared_path``,
    ``solved_path``) go."""
    key = solve_key(spec, tiling, solver, centre)
    _unlink(solved_path)  # an interrupted run's, of no use now: this run solves the tile again or not at all
    prev, why = _reusable(Path(summary_path), key, ("solved", "skipped"), field_path)
    if prev is not None:
        _unlink(prepared_path)
        return prev
    reset_peak_rss()  # the summary's peak is the tile's, not the worker's earlier tasks'
    p = prepare_tile(spec, tiling, solver, centre)
    if why:
        p.summary["redone"] = why
    if p.status is not None:
        _unlink(prepared_path)
        return _close_solve(p.summary, key, summary_path, field_path)
    p.save(prepared_path, key)
    return tile_summary(spec, status="prepared")


def solve_batch_resumable(specs: list[TileSpec], tiling: TilingConfig, solver: SolverConfig, field_paths: list,
                          summary_paths: list, prepared_paths: list, solved_paths: list, centre=None,
                          note: dict | None = None) -> list[dict]:
    """The second step: the tiles :func:`prepare_tile_resumable` prepared, solved as one batch
    (:func:`tiled_gridpull.tile_solve.solve_prepared_fields`), each field written as its solve left it to its
    ``solved_paths`` entry for :func:`finish_tile_resumable` (status ``"unfinished"``). A tile whose solve failed
    gets its final summary here. A tile whose prepared file is gone, damaged, of another tile or of other settings
    (an earlier run's, written late; a batch run again after its worker died) is prepared again here. ``note``
    goes into each tile's summary (e.g. which worker solved the batch)."""
    reset_peak_rss()  # each summary's peak is its preparation's or the batch's, not an earlier batch's
    keys = [solve_key(spec, tiling, solver, centre) for spec in specs]
    prepared = []
    for spec, path, key in zip(specs, prepared_paths, keys, strict=True):
        try:
            prepared.append(PreparedTile.load(path, spec, key))
        except _DAMAGED:
            p = prepare_tile(spec, tiling, solver, centre)
            if p.status is None:
                p.save(path, key)  # for the tile's finish
            prepared.append(p)
    fields = solve_prepared_fields(prepared, solver)
    outs = []
    for p, fld, key, summary_path, field_path, prepared_path, solved_path in zip(
            prepared, fields, keys, summary_paths, field_paths, prepared_paths, solved_paths, strict=True):
        p.summary.update(note or {})
        if fld is None:  # failed (or, prepared again, skipped): its final summary
            _unlink(prepared_path)
            outs.append(_close_solve(p.summary, key, summary_path, field_path))
            continue
        save_solved_field(solved_path, fld, {**p.account(), "key": key})
        outs.append(tile_summary(p.spec, status="unfinished"))
    return outs


def finish_tile_resumable(spec: TileSpec, tiling: TilingConfig, solver: SolverConfig, field_path: str | Path,
                          summary_path: str | Path, prepared_path: str | Path, solved_path: str | Path,
                          centre=None) -> dict:
    """The last step: a tile's batch-solved field (:func:`solve_batch_resumable`) checked against its oriented
    normals, bridged, written and recorded as :func:`solve_tile_resumable` records it; then its prepared and
    solved files are removed. Should either be gone, damaged or not this run's (another run's settings), the
    tile comes back with status ``"lost"`` (its files removed): the caller prepares and batches it again (solved
    here, it would run on a worker without the card)."""
    key = solve_key(spec, tiling, solver, centre)
    reset_peak_rss()
    try:
        p = PreparedTile.load(prepared_path, spec, key)
        fld, state = load_solved_field(solved_path, p.local)
        if state.get("key") != key:
            raise ValueError(f"{solved_path} was solved with other settings")
    except _DAMAGED as exc:
        _unlink(prepared_path)
        _unlink(solved_path)
        return tile_summary(spec, status="lost", reason=str(exc)[:300])
    p.take_account(state)  # the batch's account of the tile: its summary and time so far, the larger peak
    out = _close_solve(finish_prepared(p, fld, tiling, field_path), key, summary_path, field_path)
    _unlink(prepared_path)  # once recorded: a worker that dies before this point leaves a finish to run again
    _unlink(solved_path)
    return out


#: What reading a prepared or batch-solved tile's file raises when it is missing, cut short or damaged.
_DAMAGED = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)


def _unlink(path: str | Path | None) -> None:
    if path is not None:
        with contextlib.suppress(OSError):
            os.unlink(path)


def _close_solve(out: dict, key: str, summary_path: str | Path, field_path: str | Path) -> dict:
    """A tile solve's summary recorded for reuse (solved with its field, or skipped), or its old record removed
    (failed: a rerun tries again)."""
    if out["status"] in ("solved", "skipped"):
        _record(out, summary_path, key, field_path if out["status"] == "solved" else None)
    else:
        out["key"] = key
        _unlink(summary_path)
    out["reused"] = False
    return out


def mesh_tile_resumable(spec: TileSpec, own: dict, neighbors: list[tuple[TileSpec, dict, str]],
                        tiling: TilingConfig, key_ref, field_path: str | Path, piece_path: str | Path,
                        summary_path: str | Path) -> dict:
    """Blend and mesh a solved tile (:func:`tiled_gridpull.stitch.mesh_tile`) unless an intact piece with the
    same key exists. ``neighbors`` are ``(spec, solve summary, field path)`` of the solved neighbours."""
    key = mesh_key(spec, own["field_sha256"], [(s.name, summ["field_sha256"]) for s, summ, _ in neighbors],
                   tiling, key_ref)
    prev, why = _reusable(Path(summary_path), key, ("meshed",), piece_path)
    if prev is not None:
        return prev
    out = mesh_tile(spec, [(s, p) for s, _, p in neighbors], tiling, key_ref, field_path, piece_path)
    out["status"] = "meshed"
    if why:
        out["redone"] = why
    _record(out, summary_path, key, piece_path)
    out["reused"] = False
    return out
