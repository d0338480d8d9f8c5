"""Up-front memory estimates (checked against measured per-task peaks on the synthetic street), --max-memory
and --dry-run."""

import re
import time

import numpy as np
import pytest

from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import ConfigError
from tiled_gridpull.memory import MB, estimate_tiles, parse_size
from tiled_gridpull.tiling import TilingConfig

from conftest import shared_file

ORIGIN = (500000.0, 4000000.0, 100.0)
# configs/scene.yaml's settings (10 cm cells, 25.6 m tiles, m2 = 25); few iterations: memory does not depend on them
TILING = TilingConfig(voxel_size=0.1, tile_size=25.6, overlap=3.2, trim_distance=3.0)
SOLVER = SolverConfig(m2=25, iterations=5, coarse_iterations=5)
TILE_ARGS = ["--voxel-size", "0.1", "--tile-size", "25.6", "--overlap", "3.2", "--set", "m2=25"]


@pytest.mark.parametrize("text,expected", [("2GB", 2 * 1024 ** 3), ("1500MB", 1500 * MB), ("512m", 512 * MB),
                                           ("1.5G", int(1.5 * 1024 ** 3)), ("2GiB", 2 * 1024 ** 3),
                                           ("3000000", 3000000), (" 64 MB ", 64 * MB)])
def test_parse_size(text, expected):
    assert parse_size(text) == expected


@pytest.mark.parametrize("text", ["", "GB", "2XB", "-1GB", "0", "100", "1e3MB", "two GB", "2 G B", "nan"])
def test_parse_size_refuses(text):
    with pytest.raises(ConfigError, match="--max-memory"):
        parse_size(text)


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    from tiled_gridpull.synthetic.lidar import scan_street
    from tiled_gridpull.synthetic.street import StreetScene, build_street

    d = tmp_path_factory.mktemp("street_memory")
    scene = StreetScene(seed=1, length_m=40.0, width_m=30.0, origin=ORIGIN)
    scan = scan_street(scene, build_street(scene), 3, azimuth_steps=700, max_range=20.0)
    np.save(d / "street.npy", scan.xyz)
    return d


@pytest.fixture(scope="module")
def street_job(street):
    """The street solved on a LocalCluster (2 workers) under a budget it fits, with estimates made beforehand."""
    from tiled_gridpull.pipeline.job import JobOptions, run_job
    from tiled_gridpull.jobdir import JobPaths
    from tiled_gridpull.prepare import prepare_job

    work = street / "job"
    _, specs, _ = prepare_job([str(street / "street.npy")], TILING, JobPaths(work))
    est = estimate_tiles(specs, SOLVER, TILING)
    mesh = run_job([str(street / "street.npy")], street / "street.ply", TILING, SOLVER, work,
                   JobOptions(workers=2, progress=False, max_memory=parse_size("4GB")))
    return est, mesh.metadata


@pytest.mark.slow
def test_memory_estimate_is_an_upper_bound_within_2x_on_the_street(street_job):
    est, meta = street_job
    solves = {s["tile"]: s for s in meta["tile_summaries"]}
    meshes = {m["tile"]: m for m in meta["mesh_summaries"]}
    assert meta["reused"]["partition"] is True  # estimates were made from the very partition that was solved
    checked = 0
    for e in est:
        s, m = solves[e["tile"]], meshes[e["tile"]]
        if s["status"] != "solved":
            continue
        # the band bound holds level by level (it is what build_band allocates before trimming)
        assert all(b >= k for b, k in zip(e["bricks"], s["level_bricks"])), (e["bricks"], s["level_bricks"])
        real_solve, real_mesh = s["peak_rss_mb"] * MB, m["peak_rss_mb"] * MB
        assert real_solve <= e["solve"] <= 2 * real_solve, (e["tile"], e["solve"] / MB, s["peak_rss_mb"])
        assert real_mesh <= e["mesh"] <= 2 * real_mesh, (e["tile"], e["mesh"] / MB, m["peak_rss_mb"])
        real = max(real_solve, real_mesh)
        assert real <= e["peak"] <= 2 * real
        checked += 1
    assert checked >= 4
    # the largest tile is the one that holds most points, and it costs more than the worker's baseline
    big = max(est, key=lambda e: e["points"])
    assert solves[big["tile"]]["peak_rss_mb"] > 300


def test_max_memory_refuses_before_solving(street, capsys):
    out = street / "refused.ply"
    work = street / "refused.job"
    code = main(["reconstruct", str(street / "street.npy"), "-o", str(out), "-q", "--work-dir", str(work),
                 *TILE_ARGS, "--max-memory", "300MB"])
    err = capsys.readouterr().err
    assert code == 5
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert re.search(r"tile_\d+_\d+_\d+ \(\d+ MB\)", lines[0]) and "--tile-size" in lines[0], lines[0]
    assert not out.exists() and not out.with_suffix(".json").exists()
    assert not (work / "fields").exists() and not (work / "summaries").exists()  # nothing was solved
    # nor partitioned: the estimate comes from a counting pass before any spill file is written
    assert not (work / "points").exists() and not (work / "manifest.json").exists()


def test_dry_run_prints_the_plan_and_writes_nothing(street, tmp_path, capsys):
    from tiled_gridpull.jobdir import JobPaths
    from tiled_gridpull.prepare import prepare_job

    out = street / "dry.ply"
    code = main(["reconstruct", str(street / "street.npy"), "-o", str(out), "-q", *TILE_ARGS, "--dry-run",
                 "--max-memory", "4GB"])
    text = capsys.readouterr().out
    assert code == 0
    assert not out.exists() and not out.with_suffix(".job").exists()
    assert "partition of the job directory reused" not in text
    # the plan agrees with a real partition of the same data
    _, specs, _ = prepare_job([str(street / "street.npy")], TILING, JobPaths(tmp_path / "job"))
    counts = sorted(s.n_points for s in specs)
    m = re.search(r"tiles:\s+(\d+) with points of (\d+) planned", text)
    assert m and int(m.group(1)) == len(specs)
    m = re.search(r"points per tile: min ([\d,]+), median ([\d,]+), max ([\d,]+)", text)
    assert m and int(m.group(1).replace(",", "")) == counts[0] and int(m.group(3).replace(",", "")) == counts[-1]
    assert "overlap 32 cells" in text and "cell 0.1" in text
    assert re.search(r"memory:\s+peak per worker about \d", text) and "roughly" in text
    assert "every tile fits" in text


def test_dry_run_on_real_laz_is_fast(tmp_path, capsys):
    laz = shared_file("lidar", "autzen_trim.laz")  # feet
    out = tmp_path / "autzen.ply"
    t0 = time.perf_counter()
    code = main(["reconstruct", str(laz), "-o", str(out), "-q", "--voxel-size", "0.5", "--tile-size", "64",
                 "--overlap", "8", "--dry-run"])
    elapsed = time.perf_counter() - t0
    text = capsys.readouterr().out
    assert code == 0, text
    assert elapsed < 10, elapsed
    assert "110,000 points" in text and re.search(r"tiles:\s+\d+ with points", text)
    assert not out.exists() and not out.with_suffix(".job").exists()


def test_time_estimate_counts_one_search_per_pooled_query():
    """A query pool searches each pooled query once, not every iteration: the estimate must see the difference."""
    from types import SimpleNamespace

    from tiled_gridpull.memory import RATE_NN_S, tile_time

    spec = SimpleNamespace(n_points=100_000)
    bricks = [1000, 2000, 4000]
    pooled = SolverConfig(query_pool=100)
    fresh = SolverConfig(query_pool=0)
    levels = [pooled.level_settings(i, 3) for i in range(3)]
    searches_saved = sum(st.iterations - st.query_pool for st in levels) * pooled.sampling.queries
    assert searches_saved > 0
    assert tile_time(spec, bricks, fresh) - tile_time(spec, bricks, pooled) == pytest.approx(searches_saved * RATE_NN_S)
    # more band bricks and more points cost more
    assert tile_time(spec, [2 * b for b in bricks], pooled) > tile_time(spec, bricks, pooled)
    assert tile_time(SimpleNamespace(n_points=200_000), bricks, pooled) > tile_time(spec, bricks, pooled)


def test_time_estimate_follows_the_points_with_content_scaled_queries():
    """With ``queries_per_point`` a tile's queries follow its points (per level: coarse levels hold at most 4 points
    per coarse cell of the occupied bricks), so a sparse tile is estimated cheaper than a dense one on the same band,
    while the fixed schedule charges both the same queries."""
    from types import SimpleNamespace

    from tiled_gridpull.memory import level_points, tile_time

    scaled = SolverConfig(queries_per_point=4, min_queries=2048)
    fixed = SolverConfig()
    bricks = [300, 1000, 3000]
    sparse = SimpleNamespace(n_points=1_000, occupied_bricks=500)
    dense = SimpleNamespace(n_points=250_000, occupied_bricks=500)
    assert level_points(dense, 2, 3) == 250_000                       # the finest level holds every point
    assert level_points(dense, 0, 3) == 4 * 500 * 6                   # 4 per cell, 1.5 x 2^2 cells per brick
    assert level_points(dense, 1, 3) == 4 * 500 * 24                  # 1.5 x 4^2 cells per brick
    assert level_points(sparse, 0, 3) == 1_000                        # fewer points than the cap
    assert tile_time(sparse, bricks, scaled) < tile_time(dense, bricks, scaled)
    fixed_gap = tile_time(dense, bricks, fixed) - tile_time(sparse, bricks, fixed)
    scaled_gap = tile_time(dense, bricks, scaled) - tile_time(sparse, bricks, scaled)
    assert scaled_gap > 2 * fixed_gap  # the fixed schedule differs only by the points' set-up


def test_time_estimate_counts_denoising_and_solves_only_the_block():
    """A denoising tile pays its passes over every point it read (halo included) and solves its block's points."""
    from types import SimpleNamespace

    from tiled_gridpull.memory import RATE_DENOISE_NEIGHBOUR_S, level_points, tile_time

    bricks = [300, 1000, 3000]
    plain = SolverConfig(queries_per_point=4)
    denoised = plain.replace(denoise=2, denoise_neighbors=32)
    spec = SimpleNamespace(n_points=120_000, occupied_bricks=500, halo_points=20_000)
    assert level_points(spec, 2, 3) == 100_000
    extra = tile_time(spec, bricks, denoised) - tile_time(spec, bricks, plain)
    assert extra == pytest.approx(2 * 120_000 * (32 + 8) * RATE_DENOISE_NEIGHBOUR_S)
    assert 2.0 < extra < 4.0  # about 13 us per point and pass, as measured on the demo street


def test_wall_estimate_schedules_the_costliest_tiles_first():
    from tiled_gridpull.pipeline.dryrun import job_wall_time
    from tiled_gridpull import memory as m

    assert m.makespan([5, 4, 3, 3, 3], 2) == 10  # LPT: 5+3+... on one worker, 4+3+3 on the other
    assert m.makespan([5, 4, 3, 3, 3], 1) == 18
    assert m.makespan([7], 4) == 7
    est = [{"time_s": 10.0, "mesh_time_s": 1.0, "bricks": [10, 20, 300]},
           {"time_s": 2.0, "mesh_time_s": 0.5, "bricks": [5, 10, 100]}]
    fixed = m.JOB_SETUP_S + 1000 * m.RATE_PARTITION_POINT_S + 400 * m.RATE_MERGE_BRICK_S
    assert job_wall_time(est, 1000, 2) == pytest.approx(fixed + 11.0)
    assert job_wall_time(est, 1000, 1) == pytest.approx(fixed + 13.5)


def test_band_bound_of_a_sparse_tile_counts_as_the_dense_dilation_does():
    """A few occupied bricks in a large brick grid (a fine cell over sparse points) are dilated without the dense
    grid; the count is the dense dilation's, clipped at the grid's faces alike."""
    from tiled_gridpull.memory import _dilate, band_bricks_bound

    rng = np.random.default_rng(0)
    solver = SolverConfig()
    for _ in range(20):
        block = tuple(int(v) for v in rng.integers(40, 330, 3))
        bricks = [-(-(s - 1) // 8) for s in block]  # the finest level's bricks per axis
        occupancy = np.zeros(bricks, bool)
        for _ in range(int(rng.integers(1, 6))):
            occupancy[tuple(int(rng.integers(0, b)) for b in bricks)] = True
        got = band_bricks_bound(occupancy, block, solver)
        # the dense path, level by level, as band_bricks_bound computed it before
        levels = solver.levels_for(max(block) - 1)
        want = []
        for level in range(levels):
            f = 2 ** (levels - 1 - level)
            bshape = [-(-(-(-(s - 1) // f) + 1) // 8) for s in block]
            idx = np.minimum(np.argwhere(occupancy) // f, np.asarray(bshape) - 1)
            grid = np.zeros(bshape, bool)
            grid[idx[:, 0], idx[:, 1], idx[:, 2]] = True
            want.append(int(_dilate(grid, -(-(solver.level_settings(level, levels).m2 + 1) // 8)).sum()))
        assert got == want


def test_estimates_bound_each_tiles_band_once_and_as_tile_memory_alone(tmp_path, monkeypatch):
    """A dry run estimates every tile (and every preset): each tile's band bound, the costly part, is computed once
    per estimate and handed to tile_memory, whose figures are those it computes itself."""
    from tiled_gridpull import memory
    from tiled_gridpull.jobdir import JobPaths
    from tiled_gridpull.partition import read_occupancy
    from tiled_gridpull.prepare import prepare_job

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 12.0, size=(3000, 2))
    np.save(tmp_path / "g.npy", np.column_stack([xy, 0.3 * np.sin(xy[:, 0])]))
    tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
    _, specs, _ = prepare_job([str(tmp_path / "g.npy")], tiling, JobPaths(tmp_path / "job"))
    assert len(specs) >= 3
    solver = SolverConfig()
    alone = [memory.tile_memory(s, read_occupancy(s), solver, tiling) for s in specs]
    calls = []
    real = memory.band_bricks_bound
    monkeypatch.setattr(memory, "band_bricks_bound", lambda *a: calls.append(1) or real(*a))
    est = estimate_tiles(specs, solver, tiling)
    assert len(calls) == len(specs)
    assert [e["bricks"] for e in est] == [a["bricks"] for a in alone]
    assert [e["solve"] for e in est] == [a["solve"] for a in alone]
