"""Tiles solved as one batch (:func:`tiled_gridpull.tile_solve.solve_tiles`) come out as each tile solved alone:
the same fields written, byte for byte, and the same summaries but for timings; a tile that cannot be solved fails
alone. (That a card's batch shares its launches and gives each tile its own field is tests/test_device.py's.)"""

import numpy as np
import pytest

from tiled_gridpull.config import SolverConfig
from tiled_gridpull.jobdir import JobPaths
from tiled_gridpull.prepare import prepare_job
from tiled_gridpull.tile_solve import prepare_tile, solve_tile, solve_tiles
from tiled_gridpull.tiling import TilingConfig

TILING = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
SOLVER = SolverConfig(m2=6, refine_m2=6, iterations=30, coarse_iterations=30, queries=3000, device="cpu")
#: what differs between two runs of one tile: where the time went, the memory, the batch's size
TIMINGS = {"phases_s", "time_s", "peak_rss_mb", "batch", "batch_of", "solve_levels", "field_path"}


@pytest.fixture
def specs(tmp_path, ground):
    _, specs, _ = prepare_job([str(ground)], TILING, JobPaths(tmp_path / "job"))
    assert len(specs) >= 3
    return specs


def _same(a: dict, b: dict) -> None:
    assert {k: v for k, v in a.items() if k not in TIMINGS} == {k: v for k, v in b.items() if k not in TIMINGS}


def test_a_batch_of_tiles_writes_each_tiles_own_field(tmp_path, specs):
    alone = [solve_tile(s, TILING, SOLVER, tmp_path / f"alone_{s.name}.npz") for s in specs[:3]]
    paths = [tmp_path / f"batch_{s.name}.npz" for s in specs[:3]]
    together = solve_tiles(specs[:3], TILING, SOLVER, paths)
    assert [t["status"] for t in together] == ["solved"] * 3
    for a, b, path in zip(alone, together, paths):
        _same(a, b)
        assert b["batch"] == 3 and "batch" not in a and b["batch_of"] == specs[0].name
        assert b["field_path"] == str(path) and b["field_sha256"] == a["field_sha256"]
        assert set(b["phases_s"]) == set(a["phases_s"])


def test_a_tile_with_too_few_points_is_skipped_and_the_others_solved(tmp_path, specs):
    few = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6,
                       min_points=sorted(s.block_points for s in specs)[1])  # the sparsest tile falls short
    out = solve_tiles(specs, few, SOLVER, [tmp_path / f"{s.name}.npz" for s in specs])
    skipped = [o for o in out if o["status"] == "skipped"]
    assert len(skipped) >= 1 and all("min_points" in o["reason"] for o in skipped)
    assert all(o["status"] == "solved" for o in out if o not in skipped)
    assert all(o.get("batch") == len(out) - len(skipped) for o in out if o not in skipped)


def test_a_tile_whose_solve_fails_fails_alone(tmp_path, specs, monkeypatch):
    """A batch that raises for a data reason is solved tile by tile: only the tile at fault fails."""
    from tiled_gridpull import tile_solve
    from tiled_gridpull.errors import InputError

    real = tile_solve.solve_batch
    bad = specs[1].name

    def picky(problems, *args, **kwargs):
        if any(p.points is bad_points[0] for p in problems):
            raise InputError("too few points to solve: 3 inside the lattice (need at least 10)")
        return real(problems, *args, **kwargs)

    bad_points = [None]
    real_problem = tile_solve.PreparedTile.problem

    def problem(self):
        pr = real_problem(self)
        if self.spec.name == bad:
            bad_points[0] = pr.points
        return pr

    monkeypatch.setattr(tile_solve, "solve_batch", picky)
    monkeypatch.setattr(tile_solve.PreparedTile, "problem", problem)
    out = solve_tiles(specs[:3], TILING, SOLVER, [tmp_path / f"{s.name}.npz" for s in specs[:3]])
    assert [o["status"] for o in out] == ["solved", "failed", "solved"]
    assert "too few points" in out[1]["reason"] and "time_s" in out[1]
    assert "batch" not in out[0]  # each was solved alone


def test_prepare_tile_names_what_its_solve_needs(specs):
    p = prepare_tile(specs[0], TILING, SOLVER)
    assert p.status is None and p.rule == "up" and p.normals.shape == p.xyz.shape
    pr = p.problem()
    assert pr.points is p.xyz and pr.lattice == p.local and pr.init is not None


def test_solve_tiles_needs_a_field_path_per_tile(tmp_path, specs):
    with pytest.raises(ValueError, match="3 tiles need as many field paths, got 2"):
        solve_tiles(specs[:3], TILING, SOLVER, [tmp_path / "a.npz", tmp_path / "b.npz"])


def _batch_then_finish(specs, paths, solver=SOLVER):
    """The card job's last two steps, in this process: the batch, then each solved tile's finish."""
    from tiled_gridpull.resume import finish_tile_resumable, solve_batch_resumable

    cols = [[str(f(s)) for s in specs] for f in (paths.field, lambda s: paths.summary("solve", s), paths.prepared,
                                                 paths.solved)]
    outs = solve_batch_resumable(specs, TILING, solver, *cols)
    return [finish_tile_resumable(s, TILING, solver, *(c[k] for c in cols)) if o["status"] == "unfinished" else o
            for k, (s, o) in enumerate(zip(specs, outs))]


def test_a_tile_prepared_solved_and_finished_in_three_processes_is_the_tile_solved_alone(tmp_path, specs):
    """On a card a job prepares its tiles on CPU workers (:func:`prepare_tile_resumable` writes them to the job
    directory), solves them in batches on the card's worker (:func:`solve_batch_resumable` writes each field as
    the solve left it) and finishes each on a CPU worker (:func:`finish_tile_resumable`): the fields and records
    are those of each tile solved alone, the files between the steps go once the tile is finished, and a rerun
    reuses the records without preparing anything."""
    from tiled_gridpull.resume import prepare_tile_resumable, solve_tile_resumable

    paths = JobPaths(tmp_path / "job")
    alone = [solve_tile_resumable(s, TILING, SOLVER, tmp_path / f"alone_{s.name}.npz",
                                  tmp_path / f"alone_{s.name}.json") for s in specs[:3]]
    rows = [(s, str(paths.field(s)), str(paths.summary("solve", s)), str(paths.prepared(s))) for s in specs[:3]]
    firsts = [prepare_tile_resumable(s, TILING, SOLVER, f, r, p) for s, f, r, p in rows]
    assert [f["status"] for f in firsts] == ["prepared"] * 3
    assert all(paths.prepared(s).is_file() for s in specs[:3]) and not any(paths.field(s).exists() for s in specs[:3])
    out = _batch_then_finish(specs[:3], paths)
    for a, b in zip(alone, out):
        _same({**a, "key": None, "output": None}, {**b, "key": None, "output": None})
        assert b["batch"] == 3 and b["field_sha256"] == a["field_sha256"] and b["key"] == a["key"]
        # the time of the preparation is the tile's, and so are the solve's and the finish's
        assert set(b["phases_s"]) == set(a["phases_s"]) and b["time_s"] >= sum(b["phases_s"].values()) - 1e-6
    assert not list(paths.prepared(specs[0]).parent.iterdir())
    again = [prepare_tile_resumable(s, TILING, SOLVER, f, r, p) for s, f, r, p in rows]
    assert all(a["reused"] and a["status"] == "solved" for a in again)
    assert not list(paths.prepared(specs[0]).parent.iterdir())


def test_a_solved_field_on_disk_is_the_field_its_solve_left(tmp_path, specs):
    """The field a batch leaves for the tile's finish comes back with the same band (brick table and neighbours
    rebuilt), values and solve record."""
    from tiled_gridpull.solver import solve_batch
    from tiled_gridpull.tile_field import load_solved_field, save_solved_field

    p = prepare_tile(specs[0], TILING, SOLVER)
    fld = solve_batch([p.problem()], SOLVER, history_every=10)[0]
    save_solved_field(tmp_path / "f.npz", fld, {"n": 1})
    back, state = load_solved_field(tmp_path / "f.npz", p.local)
    assert state == {"n": 1} and back.signed == fld.signed and back.lattice == fld.lattice
    for name in ("brick_coords", "brick_table", "neighbors", "flags"):
        np.testing.assert_array_equal(getattr(back.band, name), getattr(fld.band, name))
    assert (back.band.m1, back.band.m2) == (fld.band.m1, fld.band.m2)
    np.testing.assert_array_equal(back.values, fld.values)
    assert back.info["history"] == fld.info["history"] and len(back.info["levels"]) == len(fld.info["levels"])


def test_a_batch_or_finish_whose_files_are_gone_or_another_tiles_still_gives_the_tiles_field(tmp_path, specs):
    """A batch run again after its worker died may find its tiles' prepared files gone or damaged, or one of
    another tile or of other settings: it prepares those tiles itself rather than failing them or solving the
    wrong points. A finish that finds its files gone or foreign gives the tile back to be batched again."""
    from tiled_gridpull.resume import finish_tile_resumable, prepare_tile_resumable, solve_batch_resumable, solve_key

    paths = JobPaths(tmp_path / "job")
    args = [(str(paths.field(s)), str(paths.summary("solve", s)), str(paths.prepared(s))) for s in specs[:2]]
    for s, (f, r, p) in zip(specs, args):
        prepare_tile_resumable(s, TILING, SOLVER, f, r, p)
    paths.prepared(specs[0]).unlink()
    whole = paths.prepared(specs[1]).read_bytes()
    paths.prepared(specs[1]).write_bytes(whole[:len(whole) // 2])  # cut short: a zip without its directory
    out = _batch_then_finish(specs[:2], paths)
    alone = [solve_tile(s, TILING, SOLVER, tmp_path / f"alone_{s.name}.npz") for s in specs[:2]]
    assert [o["field_sha256"] for o in out] == [a["field_sha256"] for a in alone]
    # a file of another tile, or of other settings (an earlier run's, written late), is not solved: the tile is
    # prepared again in the batch
    other = SolverConfig(m2=6, refine_m2=6, iterations=30, coarse_iterations=30, queries=3000, device="cpu", seed=7)
    stale = prepare_tile(specs[1], TILING, other)
    stale.save(paths.prepared(specs[1]), solve_key(specs[1], TILING, other))
    with pytest.raises(ValueError, match="prepared with other settings"):
        type(stale).load(paths.prepared(specs[1]), specs[1], solve_key(specs[1], TILING, SOLVER))
    prepare_tile(specs[0], TILING, SOLVER).save(paths.prepared(specs[0]), solve_key(specs[0], TILING, SOLVER))
    with pytest.raises(ValueError, match=f"holds tile '{specs[0].name}', not '{specs[1].name}'"):
        type(stale).load(paths.prepared(specs[0]), specs[1])
    paths.prepared(specs[0]).replace(paths.prepared(specs[1]))  # tile 0's points where tile 1's should be
    paths.summary("solve", specs[1]).unlink()  # not reusable: solved again
    again = _batch_then_finish(specs[1:2], paths)
    assert again[0]["field_sha256"] == alone[1]["field_sha256"]
    # a finish whose solved field is gone, or is another run's (other settings, written late), does not solve the
    # tile on its (card-less) worker nor write the foreign field: the tile is "lost", to be batched again
    paths.summary("solve", specs[0]).unlink()
    cols = [[str(f(specs[0]))] for f in (paths.field, lambda s: paths.summary("solve", s), paths.prepared,
                                         paths.solved)]

    def batched():
        prepare_tile_resumable(specs[0], TILING, SOLVER, *args[0])
        assert solve_batch_resumable(specs[:1], TILING, SOLVER, *cols)[0]["status"] == "unfinished"

    batched()
    paths.solved(specs[0]).unlink()
    lost = finish_tile_resumable(specs[0], TILING, SOLVER, *(c[0] for c in cols))
    assert lost["status"] == "lost" and not list(paths.prepared(specs[0]).parent.iterdir())
    assert not paths.summary("solve", specs[0]).exists()
    batched()
    foreign = tmp_path / "foreign.npz"
    oth = [[str(tmp_path / f"o_{k}")] for k in ("field.npz", "sum.json", "prep.npz")] + [[str(foreign)]]
    prepare_tile_resumable(specs[0], TILING, other, *(c[0] for c in oth[:3]))
    solve_batch_resumable(specs[:1], TILING, other, *oth)
    foreign.replace(paths.solved(specs[0]))
    lost = finish_tile_resumable(specs[0], TILING, SOLVER, *(c[0] for c in cols))
    assert lost["status"] == "lost" and "other settings" in lost["reason"]
    batched()  # and batched again, it is the tile's own field
    done = finish_tile_resumable(specs[0], TILING, SOLVER, *(c[0] for c in cols))
    assert done["field_sha256"] == alone[0]["field_sha256"] and not list(paths.prepared(specs[0]).parent.iterdir())


def test_a_tiles_card_memory_estimate_bounds_its_levels_arrays(tmp_path, specs):
    """The estimate a batch on a card is sized by (:func:`tiled_gridpull.memory.card_bytes`, from the partition
    alone) is at least what the tile's solved levels hold on the card (per slot of a level's band its arrays, the
    next level's start, its points), and not wildly more."""
    from tiled_gridpull.memory import (CARD_BYTES_PER_SLOT, CARD_NEXT_BYTES_PER_SLOT, CARD_POINT_BYTES, SLOT,
                                       band_bricks_bound, card_bytes)
    from tiled_gridpull.partition import read_occupancy

    for spec in specs[:3]:
        out = solve_tile(spec, TILING, SOLVER, tmp_path / f"{spec.name}.npz")
        est = card_bytes(spec, band_bricks_bound(read_occupancy(spec), spec.block.shape, SOLVER), SOLVER)
        lv = out["level_bricks"]
        held = max(b * SLOT * CARD_BYTES_PER_SLOT + (lv[i + 1] * SLOT * CARD_NEXT_BYTES_PER_SLOT if i + 1 < len(lv)
                                                     else 0) for i, b in enumerate(lv))
        held += out["points_used"] * CARD_POINT_BYTES
        assert held <= est <= 3 * held
