"""Resume bookkeeping without a cluster: the partition's key and commit record, result keys, and reuse checks.

(The end-to-end runs -- Ctrl-C mid-job then rerun to identical bytes, settings invalidating only their
dependents -- are in ``test_reliability.py``.)
"""

import dataclasses
import hashlib
import json
import os

from pathlib import Path

import numpy as np
import pytest

from tiled_gridpull.config import SECTIONS, SETTINGS, SolverConfig
from tiled_gridpull.resume import mesh_key, solve_key, solve_tile_resumable
from tiled_gridpull.jobdir import JobPaths
from tiled_gridpull.prepare import prepare_job
from tiled_gridpull.partition import read_occupancy
from tiled_gridpull.tiling import TilingConfig

TILING = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
SOLVER = SolverConfig(m2=6, refine_m2=6, iterations=30, coarse_iterations=30, queries=3000)


def _names(specs):
    return [(s.name, s.n_points, s.points_sha256) for s in specs]


OTHER_CHOICE = {"tv_form": "squared", "refine_tv_form": "sqrt", "mode": "udf", "device": "cpu"}


def _changed(name: str, value):
    """A valid value of setting ``name`` different from ``value``."""
    if isinstance(value, str):
        return OTHER_CHOICE[name]
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    return value / 2 if value else 0.5


def test_solve_key_follows_exactly_the_settings_marked_solve(tmp_path, ground):
    _, specs, _ = prepare_job([str(ground)], TILING, JobPaths(tmp_path / "job"))
    s = specs[0]
    sphere = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, orientation="sphere")
    # every setting of the one table, with the dataclass field that declares it (top level or in a section)
    fields = {name: {f.name: f for f in dataclasses.fields(SECTIONS[sec] if sec else SolverConfig)}[fname]
              for name, (sec, fname) in SETTINGS.items()}
    assert all(set(f.metadata) == {"solve", "sphere_only"} for f in fields.values())  # every setting classified
    assert {n for n, f in fields.items() if not f.metadata["solve"]} == {"resolution", "margin", "normal_weight",
                                                                                "noise_auto", "relax", "device"}
    assert {n for n, f in fields.items() if f.metadata["sphere_only"]} == {"init_radius"}
    for tiling in (TILING, sphere):
        base = solve_key(s, tiling, SOLVER)
        for name, f in fields.items():
            changed = SOLVER.replace(**{name: _changed(name, SOLVER.get(name))})
            counts = f.metadata["solve"] and (tiling is sphere or not f.metadata["sphere_only"])
            assert (solve_key(s, tiling, changed) != base) == counts, name


def test_partition_is_reused_only_for_the_same_inputs_and_grid(tmp_path, ground):
    paths = JobPaths(tmp_path / "job")
    _, specs, scan = prepare_job([str(ground)], TILING, paths)
    assert scan["partition_reused"] is False and len(specs) == 4
    for s in specs:  # the recorded checksum is the spill file's content
        assert s.points_sha256 == hashlib.sha256(open(s.points_path, "rb").read()).hexdigest()
        assert read_occupancy(s).sum() == s.occupied_bricks > 0
    _, again, scan2 = prepare_job([str(ground)], TILING, paths)
    assert scan2["partition_reused"] is True and _names(again) == _names(specs)
    assert np.array_equal(scan2["bounds"], scan["bounds"]) and scan2["points"] == scan["points"]
    # settings that do not change the tile grid keep it
    other = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, trim_distance=1.0, min_points=3)
    assert prepare_job([str(ground)], other, paths)[2]["partition_reused"] is True
    # a different grid does not
    bigger = TilingConfig(voxel_size=0.2, tile_size=8.0, overlap=1.6)
    assert prepare_job([str(ground)], bigger, paths)[2]["partition_reused"] is False
    assert prepare_job([str(ground)], TILING, paths)[2]["partition_reused"] is False
    # nor does a touched input (same content: same tile checksums, so the tiles' results stay reusable)
    st = ground.stat()
    os.utime(ground, ns=(st.st_atime_ns, st.st_mtime_ns + 10 ** 9))
    _, touched, scan3 = prepare_job([str(ground)], TILING, paths)
    assert scan3["partition_reused"] is False and _names(touched) == _names(specs)


def test_damaged_spill_file_forces_a_new_partition(tmp_path, ground):
    paths = JobPaths(tmp_path / "job")
    _, specs, _ = prepare_job([str(ground)], TILING, paths)
    with open(specs[0].points_path, "r+b") as fh:
        fh.truncate(12 * (specs[0].n_points - 1))
    _, again, scan = prepare_job([str(ground)], TILING, paths)
    assert scan["partition_reused"] is False and _names(again) == _names(specs)
    # zeroed in place, size and modification time kept: the recorded SHA-256 catches it
    spill = Path(again[0].points_path)
    st = spill.stat()
    data = bytearray(spill.read_bytes())
    data[:1200] = bytes(1200)
    spill.write_bytes(bytes(data))
    os.utime(spill, ns=(st.st_atime_ns, st.st_mtime_ns))
    _, third, scan = prepare_job([str(ground)], TILING, paths)
    assert scan["partition_reused"] is False
    assert [s.points_sha256 for s in third] == [s.points_sha256 for s in again]


def test_interrupted_partition_is_never_taken_for_a_finished_one(tmp_path, ground, monkeypatch):
    import tiled_gridpull.prepare as prepare

    paths = JobPaths(tmp_path / "job")
    prepare_job([str(ground)], TILING, paths)
    real = prepare.partition

    def dies(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(prepare, "partition", dies)
    other = TilingConfig(voxel_size=0.2, tile_size=8.0, overlap=1.6)
    with pytest.raises(KeyboardInterrupt):
        prepare_job([str(ground)], other, paths)
    assert not paths.manifest.exists()  # the old commit record is gone before new spill files are written
    monkeypatch.setattr(prepare, "partition", real)
    assert prepare_job([str(ground)], TILING, paths)[2]["partition_reused"] is False


def test_solve_key_follows_the_settings_a_solve_reads(tmp_path, ground):
    _, specs, _ = prepare_job([str(ground)], TILING, JobPaths(tmp_path / "job"))
    s = specs[0]
    base = solve_key(s, TILING, SOLVER)
    assert solve_key(s, TILING, SOLVER) == base
    for changed in (SOLVER.replace(iterations=31), SOLVER.replace(seed=1), SOLVER.replace(m2=7),
                    SOLVER.replace(alpha=2.0)):
        assert solve_key(s, TILING, changed) != base
    for same in (SOLVER.replace(resolution=64), SOLVER.replace(margin=2), SOLVER.replace(init_radius=3.0),
                 SOLVER.replace(normal_weight=1.0)):
        assert solve_key(s, TILING, same) == base  # shape-mode settings a tile solve never reads
    up = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, orientation="up", trim_distance=1.0)
    assert solve_key(s, up, SOLVER) == base  # "auto" is "up" for airborne data; trimming is the mesh step's
    assert solve_key(s, TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, min_points=7), SOLVER) != base
    k = mesh_key(s, "a" * 64, [("tile_1_0_0", "b" * 64)], TILING, np.zeros(3, np.int64))
    assert mesh_key(s, "a" * 64, [("tile_1_0_0", "b" * 64)], up, np.zeros(3, np.int64)) != k  # trim distance
    assert mesh_key(s, "a" * 64, [("tile_1_0_0", "c" * 64)], TILING, np.zeros(3, np.int64)) != k  # a neighbour


def test_the_rule_for_things_on_the_ground_keys_bridging_tiles_with_sensor_origins_only(tmp_path, ground):
    """``bridge_objects`` changes what a tile with sensor origins bridges, so its solve key; a tile without them
    (or a job that does not bridge) keeps its key whatever the setting."""
    _, specs, _ = prepare_job([str(ground)], TILING, JobPaths(tmp_path / "job"))
    s = specs[0]
    bridging = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, bridge=8)
    others = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6, bridge=8, bridge_objects=0)
    seen = dataclasses.replace(s, has_sensor=True)
    assert solve_key(seen, bridging, SOLVER) != solve_key(seen, others, SOLVER)
    assert solve_key(s, bridging, SOLVER) == solve_key(s, others, SOLVER)
    off = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
    assert solve_key(seen, off, SOLVER) == solve_key(seen, dataclasses.replace(off, bridge_objects=0), SOLVER)


def test_solve_result_reused_only_while_its_field_is_intact(tmp_path, ground):
    paths = JobPaths(tmp_path / "job")
    _, specs, _ = prepare_job([str(ground)], TILING, paths)
    s = max(specs, key=lambda t: t.n_points)
    field, summary = paths.field(s), paths.summary("solve", s)
    first = solve_tile_resumable(s, TILING, SOLVER, field, summary)
    assert first["status"] == "solved" and first["reused"] is False
    rec = json.loads(summary.read_text())
    assert rec["key"] == solve_key(s, TILING, SOLVER) and rec["field_sha256"] == first["field_sha256"]
    again = solve_tile_resumable(s, TILING, SOLVER, field, summary, before_solve=pytest.fail)
    assert again["reused"] is True and again["field_sha256"] == first["field_sha256"]
    # only the content counts: a touched (or copied) field is still reused
    st = field.stat()
    os.utime(field, ns=(st.st_atime_ns, st.st_mtime_ns + 1))
    assert solve_tile_resumable(s, TILING, SOLVER, field, summary, before_solve=pytest.fail)["reused"] is True
    # a field damaged in place, size and modification time kept, no longer matches its record: solved again,
    # to the very same values, and the summary says why
    st = field.stat()
    data = bytearray(field.read_bytes())
    data[len(data) // 2: len(data) // 2 + 4096] = bytes(4096)
    field.write_bytes(bytes(data))
    os.utime(field, ns=(st.st_atime_ns, st.st_mtime_ns))
    third = solve_tile_resumable(s, TILING, SOLVER, field, summary)
    assert third["reused"] is False and third["field_sha256"] == first["field_sha256"]
    assert "damaged" in third["redone"]
    # other settings: solved again
    fourth = solve_tile_resumable(s, TILING, SOLVER.replace(iterations=20), field, summary)
    assert fourth["reused"] is False and fourth["field_sha256"] != first["field_sha256"]


def test_a_result_computed_again_is_reused_afterwards_without_a_word_of_damage(tmp_path, ground):
    """Once a damaged field has been solved again, later runs reuse it and say nothing about the damage (the
    record of the redo used to carry ``redone`` into every later reuse, and each rerun warned again)."""
    paths = JobPaths(tmp_path / "job")
    _, specs, _ = prepare_job([str(ground)], TILING, paths)
    s = max(specs, key=lambda t: t.n_points)
    field, summary = paths.field(s), paths.summary("solve", s)
    solve_tile_resumable(s, TILING, SOLVER, field, summary)
    field.write_bytes(field.read_bytes()[:-1] + b"!")
    redone = solve_tile_resumable(s, TILING, SOLVER, field, summary)
    assert redone["reused"] is False and "damaged" in redone["redone"]
    for _ in range(2):
        later = solve_tile_resumable(s, TILING, SOLVER, field, summary, before_solve=pytest.fail)
        assert later["reused"] is True and "redone" not in later, later.get("redone")


def test_a_result_is_never_reused_through_a_link(tmp_path, ground):
    """A job decides reuse only from its own files: a field, a summary or a spill file replaced by a symlink to an
    intact copy outside the job directory is not read to decide reuse; the result is computed again and the
    link replaced, the copy outside left alone."""
    import shutil

    paths = JobPaths(tmp_path / "job")
    _, specs, _ = prepare_job([str(ground)], TILING, paths)
    s = max(specs, key=lambda t: t.n_points)
    field, summary = paths.field(s), paths.summary("solve", s)
    solve_tile_resumable(s, TILING, SOLVER, field, summary)
    outside = tmp_path / "outside"
    outside.mkdir()
    for p in (field, summary):
        copy = outside / p.name
        shutil.copy2(p, copy)
        p.unlink()
        p.symlink_to(copy)
        kept = copy.read_bytes()
        again = solve_tile_resumable(s, TILING, SOLVER, field, summary)
        assert again["reused"] is False, p.name
        assert not p.is_symlink() and copy.read_bytes() == kept
    spill = Path(s.points_path)
    shutil.copy2(spill, outside / spill.name)
    spill.unlink()
    spill.symlink_to(outside / spill.name)
    assert prepare_job([str(ground)], TILING, paths)[2]["partition_reused"] is False
    assert not spill.is_symlink()


def test_kitti_partition_key_ignores_outputs_written_inside_the_sequence(tmp_path):
    """A job whose mesh, sidecar and job directory lie inside the KITTI sequence directory reuses its partition:
    the key covers the files the reader reads (scans, poses, calib), not whatever else the directory holds."""
    from test_io_formats import make_sequence

    from tiled_gridpull.resume import partition_key

    seq = tmp_path / "seq"
    make_sequence(seq, calib=True, subdir=True)
    tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
    before = partition_key([seq], tiling)
    (seq / "mesh.ply").write_text("ply\n")
    (seq / "mesh.job" / "points").mkdir(parents=True)
    (seq / "mesh.job" / "points" / "tile_0_0_0.bin").write_bytes(b"\0" * 64)
    assert partition_key([seq], tiling) == before
    # what the reader reads still counts
    scan = seq / "velodyne" / "000001.bin"
    scan.write_bytes(scan.read_bytes()[:-16])
    assert partition_key([seq], tiling) != before
    os.utime(seq / "poses.txt", ns=(0, 0))
    changed = partition_key([seq], tiling)
    (seq / "calib.txt").write_text((seq / "calib.txt").read_text() + "\n")
    assert partition_key([seq], tiling) != changed
