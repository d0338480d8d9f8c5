"""Tiles solved as one batch (:func:`tiled_gridpull.tile_solve.solve_tiles`) come out as each tile solved alone:
the same fields written, byte for byte, and the same summaries but for timings; a tile that cannot be solved fails
alone. (That a card's batch shares its launches and gives each tile its own field is tests/test_device.py's.)"""

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


def test_a_tile_prepared_in_one_process_and_solved_in_another_is_the_tile_solved_alone(tmp_path, specs):
    """On a card a job prepares its tiles on CPU workers (:func:`prepare_tile_resumable` writes them to the job
    directory) and solves them in batches on the card's worker (:func:`solve_prepared_resumable`): the fields and
    records are those of each tile solved alone, the prepared files go once solved, and a rerun reuses the
    records without preparing anything."""
    from tiled_gridpull.resume import prepare_tile_resumable, solve_prepared_resumable, solve_tile_resumable

    paths = JobPaths(tmp_path / "job")
    alone = [solve_tile_resumable(s, TILING, SOLVER, tmp_path / f"alone_{s.name}.npz",
                                  tmp_path / f"alone_{s.name}.json") for s in specs[:3]]
    fields = [str(paths.field(s)) for s in specs[:3]]
    records = [str(paths.summary("solve", s)) for s in specs[:3]]
    prepared = [str(paths.prepared(s)) for s in specs[:3]]
    rows = list(zip(specs, fields, records, prepared))
    firsts = [prepare_tile_resumable(s, TILING, SOLVER, f, r, p) for s, f, r, p in rows]
    assert [f["status"] for f in firsts] == ["prepared"] * 3
    assert all(paths.prepared(s).is_file() for s in specs[:3]) and not any(paths.field(s).exists() for s in specs[:3])
    out = solve_prepared_resumable(specs[:3], TILING, SOLVER, fields, records, prepared)
    for a, b in zip(alone, out):
        _same({**a, "key": None, "output": None}, {**b, "key": None, "output": None})
        assert b["batch"] == 3 and b["field_sha256"] == a["field_sha256"] and b["key"] == a["key"]
        # the time of the preparation is the tile's, and so is the solve's
        assert set(b["phases_s"]) == set(a["phases_s"]) and b["time_s"] >= sum(b["phases_s"].values()) - 1e-6
    assert not any(paths.prepared(s).exists() for s in specs[:3])
    again = [prepare_tile_resumable(s, TILING, SOLVER, f, r, p) for s, f, r, p in rows]
    assert all(a["reused"] and a["status"] == "solved" for a in again)
    assert not any(paths.prepared(s).exists() for s in specs[:3])


def test_a_batch_whose_prepared_file_is_gone_or_another_tiles_prepares_it_again(tmp_path, specs):
    """A batch run again after its worker died may find its tiles' files gone or damaged, or one of another tile
    or of other settings: it prepares those tiles itself rather than failing them or solving the wrong points."""
    from tiled_gridpull.resume import prepare_tile_resumable, solve_prepared_resumable

    paths = JobPaths(tmp_path / "job")
    args = [(str(paths.field(s)), str(paths.summary("solve", s)), str(paths.prepared(s))) for s in specs[:2]]
    for s, (f, r, p) in zip(specs, args):
        prepare_tile_resumable(s, TILING, SOLVER, f, r, p)
    paths.prepared(specs[0]).unlink()
    whole = paths.prepared(specs[1]).read_bytes()
    paths.prepared(specs[1]).write_bytes(whole[:len(whole) // 2])  # cut short: a zip without its directory
    out = solve_prepared_resumable(specs[:2], TILING, SOLVER, *([a[k] for a in args] for k in range(3)))
    alone = [solve_tile(s, TILING, SOLVER, tmp_path / f"alone_{s.name}.npz") for s in specs[:2]]
    assert [o["field_sha256"] for o in out] == [a["field_sha256"] for a in alone]
    # a file of another tile, or of other settings (an earlier run's, written late), is not solved: the tile is
    # prepared again in the batch
    from tiled_gridpull.resume import solve_key

    other = SolverConfig(m2=6, refine_m2=6, iterations=30, coarse_iterations=30, queries=3000, device="cpu", seed=7)
    stale = prepare_tile(specs[1], TILING, other)
    stale.save(paths.prepared(specs[1]), solve_key(specs[1], TILING, other))
    with pytest.raises(ValueError, match="prepared with other settings"):
        type(stale).load(paths.prepared(specs[1]), specs[1], solve_key(specs[1], TILING, SOLVER))
    prepare_tile(specs[0], TILING, SOLVER).save(paths.prepared(specs[0]), solve_key(specs[0], TILING, SOLVER))
    with pytest.raises(ValueError, match=f"holds tile '{specs[0].name}', not '{specs[1].name}'"):
        type(stale).load(paths.prepared(specs[0]), specs[1])
    paths.prepared(specs[0]).replace(paths.prepared(specs[1]))  # tile 0's points where tile 1's should be
    again = solve_prepared_resumable(specs[:2], TILING, SOLVER, *([a[k] for a in args] for k in range(3)))
    assert [o["field_sha256"] for o in again] == [a["field_sha256"] for a in alone]
    assert not list(paths.prepared(specs[0]).parent.iterdir())


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
