"""Tiled jobs over COPC and EPT inputs: the plan from their index, every tile read by its own task.

The promise tested here: a tile read from the index is byte for byte the tile the streaming partition of the same
input writes, so everything after (solve keys, meshes, resume) is the same as for a streamed input.
"""

import dataclasses

import numpy as np
import pytest

import tiled_gridpull.prepare as prepare
from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import InputError, MemoryBudgetError
from tiled_gridpull.indexed_inputs import candidate_tiles, estimate_specs, plan_indexed
from tiled_gridpull.io.indexed import read_index
from tiled_gridpull.io.indexed_write import write_copc, write_ept
from tiled_gridpull.jobdir import JobPaths
from tiled_gridpull.prepare import prepare_job
from tiled_gridpull.resume import partition_key
from tiled_gridpull.tiled_job import reconstruct_scene
from tiled_gridpull.tiling import TilingConfig

pytest.importorskip("copclib", reason="writing COPC test files needs copclib (pip install 'tiled-gridpull[copc]')")

TILING = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
SOLVER = SolverConfig(m2=6, refine_m2=6, iterations=30, coarse_iterations=30, queries=3000)
ORIGIN = np.array([500000.0, 4000000.0, 20.0])


def _scene(n=30000, seed=5):
    """A wavy ground in two patches with an empty gap between them (tiles there hold nothing) and a wall."""
    rng = np.random.default_rng(seed)
    x = np.concatenate([rng.uniform(0, 10, n // 2), rng.uniform(30, 40, n // 2)])
    y = rng.uniform(0, 12, n)
    ground = np.column_stack([x, y, 0.3 * np.sin(x) * np.cos(y / 2)])
    wall = np.column_stack([rng.uniform(30, 40, n // 5), np.full(n // 5, 11.0), rng.uniform(0, 3, n // 5)])
    return np.concatenate([ground, wall]) + ORIGIN


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("indexed_job")
    xyz = _scene()
    return {"COPC": str(write_copc(d / "s.copc.laz", xyz, max_node_points=3000)),
            "EPT": str(write_ept(d / "ept", xyz, max_node_points=3000)), "dir": d}


def _streamed(monkeypatch, *args, **kw):
    """prepare_job as it runs for any input: one streaming partition pass over the whole file."""
    with monkeypatch.context() as m:
        m.setattr(prepare, "all_indexed", lambda inputs: False)
        return prepare_job(*args, **kw)


def _files(specs):
    from pathlib import Path

    return {s.name: (s.n_points, s.points_sha256, Path(s.points_path).read_bytes(),
                     Path(s.occupancy_path).read_bytes()) for s in specs}


@pytest.mark.parametrize("kind,halo", [("COPC", 0), ("EPT", 0), ("COPC", 12)])
def test_each_tile_read_from_the_index_is_the_streaming_partition_byte_for_byte(inputs, tmp_path, monkeypatch,
                                                                                kind, halo):
    """Also with a denoising halo wide enough that a point reaches 3 tiles along an axis (8 + 12 cells past a
    32-cell core)."""
    calls = []

    def run_tasks(fn, args):  # what an executor does, recorded
        calls.append(len(args))
        return [fn(*a) for a in args]

    tiling = dataclasses.replace(TILING, halo=halo)
    plan, specs, scan = prepare_job([inputs[kind]], tiling, JobPaths(tmp_path / "a"), run_tasks=run_tasks)
    plan_s, specs_s, scan_s = _streamed(monkeypatch, [inputs[kind]], tiling, JobPaths(tmp_path / "b"))
    assert calls and calls[0] == scan["candidate_tiles"] >= len(specs)  # one task per candidate tile
    assert plan.to_dict() == plan_s.to_dict()  # the header's bounds give the streamed plan
    assert scan["points"] == scan_s["points"] and scan["indexed"] == [kind]
    assert len(specs) >= 6
    assert _files(specs) == _files(specs_s)
    # tiles over the empty gap are planned but hold nothing, in both
    assert len(specs) < np.prod(plan.tile_range)
    # each spill holds exactly the points within its block and halo, and says how many are the halo's
    index = plan.lattice.to_index(_scene())
    O, T = plan.config.overlap_cells, plan.config.tile_cells
    for spec, streamed in zip(specs, specs_s):
        core = np.asarray(spec.core_lo) - np.asarray(plan.lattice.offset)
        inside = np.all((index >= core - O - halo) & (index <= core + T + O + halo), axis=1)
        block = np.all((index >= core - O) & (index <= core + T + O), axis=1)
        assert spec.n_points == inside.sum()
        assert spec.halo_points == streamed.halo_points == (inside & ~block).sum()
        assert (spec.halo_points > 0) == bool(halo)
        assert spec.block_points == block.sum()


def test_candidate_tiles_cover_every_tile_with_points(inputs, tmp_path, monkeypatch):
    _, specs_s, _ = _streamed(monkeypatch, [inputs["COPC"]], TILING, JobPaths(tmp_path / "b"))
    plan, _, indexes = plan_indexed([inputs["COPC"]], TILING)
    cands = candidate_tiles(indexes, plan)
    assert {s.index for s in specs_s} <= set(cands)
    # a small budget reads shallower levels: more (coarser) candidates, never fewer
    assert set(cands) <= set(candidate_tiles(indexes, plan, budget=500))


def test_dry_run_estimate_from_the_index_reads_few_points_and_finds_the_tiles(inputs, tmp_path, monkeypatch):
    _, specs_s, _ = _streamed(monkeypatch, [inputs["EPT"]], TILING, JobPaths(tmp_path / "b"))
    plan, _, indexes = plan_indexed([inputs["EPT"]], TILING)
    specs, occupancy, share = estimate_specs(indexes, plan)
    assert 0 < share < 0.5
    est = {s.index: s.n_points for s in specs}
    real = {s.index: s.n_points for s in specs_s}
    assert set(real) <= set(est)
    total_est, total_real = sum(est.values()), sum(real.values())
    assert 0.7 < total_est / total_real < 1.3, (total_est, total_real)
    assert all(occupancy[t].any() for t in real)


def test_job_on_an_index_is_the_job_on_its_stream_and_resumes(inputs, tmp_path, monkeypatch):
    a = reconstruct_scene([inputs["COPC"]], tmp_path / "a.ply", TILING, SOLVER, tmp_path / "ja")
    with monkeypatch.context() as m:
        m.setattr(prepare, "all_indexed", lambda inputs: False)
        b = reconstruct_scene([inputs["COPC"]], tmp_path / "b.ply", TILING, SOLVER, tmp_path / "jb")
    assert len(a.faces) > 1000
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    again = reconstruct_scene([inputs["COPC"]], tmp_path / "a2.ply", TILING, SOLVER, tmp_path / "ja")
    assert again.metadata["reused"] == {"partition": True, "solves": a.metadata["tiles"]["solved"],
                                        "meshes": len(a.metadata["mesh_summaries"])}
    np.testing.assert_array_equal(again.vertices, a.vertices)


def test_ept_key_follows_its_node_files(inputs, tmp_path):
    import shutil

    e = tmp_path / "e"
    shutil.copytree(inputs["EPT"].rsplit("/", 1)[0], e)
    before = partition_key([str(e / "ept.json")], TILING)
    node = sorted((e / "ept-data").iterdir())[0]
    node.write_bytes(node.read_bytes())  # same bytes, new modification time
    import os

    os.utime(node, ns=(node.stat().st_atime_ns, node.stat().st_mtime_ns + 10**9))
    assert partition_key([str(e / "ept.json")], TILING) != before


def test_indexed_inputs_in_different_crs_are_refused(tmp_path):
    xyz = _scene(3000)
    a = write_copc(tmp_path / "a.copc.laz", xyz, wkt='PROJCS["A",UNIT["metre",1]]')
    b = write_copc(tmp_path / "b.copc.laz", xyz + [40, 0, 0], wkt='PROJCS["B",UNIT["metre",1]]')
    with pytest.raises(InputError, match="different coordinate reference systems"):
        prepare_job([str(a), str(b)], TILING, JobPaths(tmp_path / "j"))


def test_a_refused_budget_leaves_no_tile_read_behind(inputs, tmp_path):
    from tiled_gridpull.memory import check_memory

    work = tmp_path / "j"

    def check(specs, occupancy):
        check_memory(specs, TILING, SOLVER, 1000, occupancy=occupancy)

    with pytest.raises(MemoryBudgetError):
        prepare_job([inputs["COPC"]], TILING, JobPaths(work), check=check)
    assert not (work / "points").exists() and not (work / "manifest.json").exists()


def test_an_index_that_loses_points_is_refused(inputs, tmp_path):
    import shutil

    e = tmp_path / "e"
    shutil.copytree(inputs["EPT"].rsplit("/", 1)[0], e)
    ix = read_index(e / "ept.json")
    # a node file with fewer points than its hierarchy entry says
    name = "-".join(map(str, ix.keys[-1]))
    import laspy

    las = laspy.read(str(e / "ept-data" / f"{name}.laz"))
    las.points = las.points[: len(las.points) // 2]
    las.write(str(e / "ept-data" / f"{name}.laz"))
    with pytest.raises(InputError, match="truncated EPT node"):
        prepare_job([str(e / "ept.json")], TILING, JobPaths(tmp_path / "j"))
    assert not (tmp_path / "j" / "points").exists()  # the tiles read before it are not left behind


def test_tile_reads_run_as_dask_tasks_and_give_the_serial_job(inputs, tmp_path):
    from tiled_gridpull.pipeline.job import DaskExecutor, JobOptions, run_job

    seen = []
    original = DaskExecutor.map

    def spy(self, fn, args, root):
        out = original(self, fn, args, root)
        seen.append((fn.__name__, len(args), self._client is not None))
        return out

    DaskExecutor.map = spy
    try:
        mesh = run_job([inputs["EPT"]], tmp_path / "d.ply", TILING, SOLVER, tmp_path / "jd",
                       JobOptions(workers=2, progress=False))
    finally:
        DaskExecutor.map = original
    assert seen and seen[0][0] == "read_tile" and seen[0][2]  # on the cluster the tiles then ran on
    serial = reconstruct_scene([inputs["EPT"]], tmp_path / "s.ply", TILING, SOLVER, tmp_path / "js")
    np.testing.assert_array_equal(mesh.vertices, serial.vertices)
    np.testing.assert_array_equal(mesh.faces, serial.faces)


def test_a_damaged_node_read_on_a_worker_is_one_line(inputs, tmp_path, capsys):
    import shutil

    from tiled_gridpull.pipeline.cli import main

    e = tmp_path / "e"
    shutil.copytree(inputs["EPT"].rsplit("/", 1)[0], e)
    victim = sorted((e / "ept-data").iterdir())[-1]
    victim.write_bytes(b"not a laz file")
    code = main(["reconstruct", str(e / "ept.json"), "-o", str(tmp_path / "x.ply"), "-q", "--workers", "1",
                 "--voxel-size", "0.2", "--tile-size", "6.4", "--overlap", "2.4"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 3 and len(err) == 1, err
    assert victim.name in err[0] and "damaged EPT" in err[0], err
    assert not (tmp_path / "x.ply").exists()


def test_sample_street_writes_copc_and_ept_and_a_trajectory_streams_them(tmp_path):
    from tiled_gridpull.io import point_count
    from tiled_gridpull.synthetic.street_sample import make_street_sample

    info = make_street_sample(tmp_path / "s", n_points=6000, origin=(500000.0, 4000000.0, 100.0),
                              formats=("laz", "copc", "ept"))
    n = point_count(info["laz"])
    assert point_count(info["copc"]) == point_count(info["ept"]) == n
    tiling = TilingConfig(voxel_size=0.2, tile_size=12.8, overlap=2.4)
    _, specs, scan = prepare_job([str(info["copc"])], tiling, JobPaths(tmp_path / "a"),
                                 trajectory=info["trajectory"])
    # a trajectory needs every point's GPS time on the driver: the streaming partition, with sensor origins
    assert "indexed" not in scan and scan["has_sensor"] and all(s.has_sensor for s in specs)
    _, specs_i, scan_i = prepare_job([str(info["copc"])], tiling, JobPaths(tmp_path / "b"))
    assert scan_i["indexed"] == ["COPC"] and sum(s.n_points for s in specs_i) == sum(s.n_points for s in specs)


def test_an_empty_input_does_not_widen_the_plan(inputs, tmp_path):
    import json
    import shutil

    # an EPT with no point, its bounds at the origin (what writers put in an empty header): 4e6 m from the others
    e = tmp_path / "empty"
    shutil.copytree(inputs["EPT"].rsplit("/", 1)[0], e)
    meta = json.loads((e / "ept.json").read_text())
    meta.update(points=0, boundsConforming=[0, 0, 0, 0, 0, 0])
    (e / "ept.json").write_text(json.dumps(meta))
    pages = e / "ept-hierarchy"
    for page in pages.iterdir():
        page.write_text(json.dumps({k: 0 for k in json.loads(page.read_text())}))
    plan_one, specs_one, _ = prepare_job([inputs["COPC"]], TILING, JobPaths(tmp_path / "a"))
    plan, specs, scan = prepare_job([inputs["COPC"], str(e / "ept.json")], TILING, JobPaths(tmp_path / "b"))
    assert plan.to_dict() == plan_one.to_dict()
    assert _files(specs) == _files(specs_one)


def test_a_point_no_tile_task_read_is_refused(inputs, tmp_path, monkeypatch):
    import tiled_gridpull.indexed_inputs as indexed_inputs

    plan, specs, scan = prepare_job([inputs["EPT"]], TILING, JobPaths(tmp_path / "a"))
    # every point is owned by one tile whatever the overlaps copy: the owned counts add up to the header's
    owned = sum(indexed_inputs.read_tile([inputs["EPT"]], plan, s.index, str(tmp_path / "x"))[1] for s in specs)
    assert owned == scan["points"]
    # a candidate tile missing from the tasks (its points are also in its neighbours' overlaps, so the tiles
    # still hold more points than the input declares): the driver refuses the job instead of meshing a hole
    real = prepare.candidate_tiles
    dropped = max(specs, key=lambda s: s.n_points).index
    monkeypatch.setattr(prepare, "candidate_tiles", lambda *a: [t for t in real(*a) if t != dropped])
    with pytest.raises(InputError, match="the tiles read [0-9,]+ points, the headers declare"):
        prepare_job([inputs["EPT"]], TILING, JobPaths(tmp_path / "b"))
    assert not (tmp_path / "b" / "points").exists()


@pytest.mark.parametrize("kind", ["COPC", "EPT"])
def test_collinear_indexed_inputs_are_refused_before_any_tile_is_read(tmp_path, kind):
    """Tiled mode's rule for streamed inputs (one-shape mode's: identical or collinear points are refused) holds
    for indexed inputs too; a line with one point off it is a (thin) scene, not refused."""
    from tiled_gridpull.cloud import degeneracy
    from tiled_gridpull.io import read_points

    k = np.random.default_rng(1).permutation(6000).astype(np.float64)
    line = np.c_[4 * k, 2 * k, k] * 0.001 + [500000.0, 4000000.0, 2.0]  # on the files' millimetre grid
    write = write_copc if kind == "COPC" else write_ept
    name = "l.copc.laz" if kind == "COPC" else "l"
    p = write(tmp_path / name, line, max_node_points=1000, scale=0.001)
    assert degeneracy(read_points(p, clean=False).xyz, reject_planar=False) == "collinear"  # as stored
    with pytest.raises(InputError, match=r"all 6000 points are collinear"):
        prepare_job([str(p)], TILING, JobPaths(tmp_path / "j"))
    assert not (tmp_path / "j" / "points").exists() and not (tmp_path / "j" / "manifest.json").exists()
    bent = line.copy()
    bent[4321] += [0.0, 1.0, 0.0]
    q = write(tmp_path / ("b.copc.laz" if kind == "COPC" else "b"), bent, max_node_points=1000, scale=0.001)
    plan, specs, scan = prepare_job([str(q)], TILING, JobPaths(tmp_path / "k"))
    assert scan["points"] == 6000 and specs


@pytest.mark.parametrize("how", ["EPT page lists itself", "EPT pages in a cycle", "EPT span 0",
                                 "COPC page lists itself"])
@pytest.mark.parametrize("dry", [True, False])
def test_a_damaged_index_is_one_line_and_exit_3_from_the_dry_run_and_the_run(inputs, tmp_path, how, dry):
    """A hierarchy that lists itself or runs in a cycle hung the dry run, and a span of 0 the run: the command
    line answers in one line, exit 3, within seconds, and writes nothing (a subprocess: a hang fails the test)."""
    import os
    import shutil
    import subprocess
    import sys

    from test_io_indexed import _copc_damage, _ept_damage

    kind, _, damage = how.partition(" ")
    if kind == "EPT":
        shutil.copytree(inputs["EPT"].rsplit("/", 1)[0], tmp_path / "e")
        _ept_damage(tmp_path / "e", damage)
        src = tmp_path / "e" / "ept.json"
    else:
        src = tmp_path / "d.copc.laz"
        shutil.copy(inputs["COPC"], src)
        _copc_damage(src, damage)
    out, work = tmp_path / "x.ply", tmp_path / "x.job"
    cmd = [sys.executable, "-m", "tiled_gridpull", "reconstruct", str(src), "-o", str(out), "-q", "--workers", "1",
           "--work-dir", str(work), "--voxel-size", "0.2", "--tile-size", "6.4", "--overlap", "2.4"]
    proc = subprocess.run(cmd + (["--dry-run"] if dry else []), capture_output=True, text=True, timeout=90,
                          env={**os.environ, "NUMBA_NUM_THREADS": "1"})
    err = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 3 and len(err) == 1 and err[0].startswith(f"error: {src}"), proc.stderr
    assert not out.exists() and not (work / "points").exists()
