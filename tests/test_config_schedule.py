"""A solve's work follows its content: queries per iteration from the points a level holds
(``queries_per_point``), and per-level iteration counts and learning-rate steps."""

import numpy as np
import pytest

from tiled_gridpull.config import ConfigError, LevelSchedule, SolverConfig
from tiled_gridpull.lattice import Lattice
from tiled_gridpull.solver import solve


def _sphere_cloud(n, seed=0):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return 0.4 * v / np.linalg.norm(v, axis=1, keepdims=True)


def test_queries_follow_the_points_between_the_floor_and_the_cap():
    cfg = SolverConfig(queries=50_000, queries_per_point=4, min_queries=2048)
    assert cfg.queries_for(100) == 2048          # floor
    assert cfg.queries_for(1000) == 4000         # 4 per point
    assert cfg.queries_for(12_501) == 50_000     # cap (ceil(50,004) > 50,000)
    assert cfg.queries_for(None) == 50_000       # unknown content: the most
    assert SolverConfig(queries=50_000).queries_for(100) == 50_000  # 0 (default): the paper's fixed count


def test_the_refinement_levels_draw_their_own_rate_of_queries():
    cfg = SolverConfig(queries=50_000, queries_per_point=4, refine_queries_per_point=16, min_queries=2048)
    assert cfg.queries_for(1000) == 4000 and cfg.queries_for(1000, refine=True) == 16_000
    assert cfg.queries_for(100, refine=True) == 2048           # the same floor
    assert cfg.queries_for(5000, refine=True) == 50_000        # and cap
    assert [cfg.level_settings(level, 3, 1000).queries for level in range(3)] == [4000, 16_000, 16_000]
    # unset (0): the refinement levels draw queries_per_point, as before the option existed
    same = SolverConfig(queries=50_000, queries_per_point=4, min_queries=2048)
    assert [same.level_settings(level, 3, 1000).queries for level in range(3)] == [4000, 4000, 4000]
    # a single-level solve has only its coarsest level
    assert cfg.level_settings(0, 1, 1000).queries == 4000
    # the solve records what it drew per level
    pts = _sphere_cloud(1500)
    small = SolverConfig(resolution=64, levels=2, iterations=20, coarse_iterations=20, queries=20_000,
                         queries_per_point=2, refine_queries_per_point=6, min_queries=512, lr_step=10,
                         refine_lr_step=10)
    fld = solve(pts, Lattice.fit(pts, small.resolution, small.margin), small)
    coarse, fine = fld.info["levels"]
    assert coarse["queries"] == max(512, 2 * coarse["points"]) and fine["queries"] == 6 * 1500


def test_a_refinement_rate_alone_scales_only_the_refinement_levels():
    cfg = SolverConfig(queries=50_000, refine_queries_per_point=16, min_queries=2048)
    assert [cfg.level_settings(level, 3, 1000).queries for level in range(3)] == [50_000, 16_000, 16_000]


def test_level_settings_carry_per_level_iterations():
    cfg = SolverConfig(levels=3, coarse_iterations=800, middle_iterations=400, iterations=200,
                       lr_step=400, refine_lr_step=100)
    st = [cfg.level_settings(level, 3) for level in range(3)]
    assert [s.iterations for s in st] == [800, 400, 200]
    assert [s.lr_step for s in st] == [400, 100, 100]
    # unset, the middle level runs the coarse count (as before the option existed)
    old = SolverConfig(levels=3, coarse_iterations=800, iterations=600)
    assert [old.level_settings(level, 3).iterations for level in range(3)] == [800, 800, 600]
    # with two levels there is no middle level
    assert [cfg.level_settings(level, 2).iterations for level in range(2)] == [800, 200]
    # the solve runs what the settings say
    pts = _sphere_cloud(800)
    small = SolverConfig(resolution=128, levels=3, coarse_iterations=30, middle_iterations=20, iterations=10,
                         queries=1000, lr_step=10, refine_lr_step=10)
    fld = solve(pts, Lattice.fit(pts, small.resolution, small.margin), small)
    assert [lv["iterations"] for lv in fld.info["levels"]] == [30, 20, 10]


def test_a_small_cloud_draws_fewer_queries_and_the_solve_records_them():
    pts = _sphere_cloud(1500)
    cfg = SolverConfig(resolution=64, levels=2, iterations=40, coarse_iterations=40, queries=20_000,
                       queries_per_point=2, min_queries=512, lr_step=20, refine_lr_step=20)
    fld = solve(pts, Lattice.fit(pts, cfg.resolution, cfg.margin), cfg)
    for lv in fld.info["levels"]:
        assert lv["queries"] == cfg.queries_for(lv["points"])
        assert lv["queries"] < cfg.sampling.queries
    # the coarse level is thinned (at most 4 points per coarse cell): fewer points, fewer queries
    coarse, fine = fld.info["levels"]
    assert fine["points"] == 1500 and coarse["points"] <= fine["points"]
    fixed = solve(pts, Lattice.fit(pts, cfg.resolution, cfg.margin), cfg.replace(queries_per_point=0))
    assert [lv["queries"] for lv in fixed.info["levels"]] == [20_000, 20_000]
    # deterministic: the same settings give the same field bit for bit
    again = solve(pts, Lattice.fit(pts, cfg.resolution, cfg.margin), cfg)
    assert np.array_equal(again.values, fld.values)
    # and it still fits the sphere: the field (world units) is within half a cell of zero at the points
    f, _ = fld.sample(pts)
    assert np.median(np.abs(f)) < 0.5 * fld.band.lattice.cell_size


@pytest.mark.parametrize("kw,needle", [({"queries_per_point": -1}, "queries_per_point"),
                                       ({"min_queries": 0}, "min_queries"),
                                       ({"middle_iterations": -5}, "middle_iterations"),
                                       ({"queries_per_point": float("nan")}, "queries_per_point"),
                                       ({"refine_queries_per_point": -2}, "refine_queries_per_point")])
def test_schedule_settings_are_validated(kw, needle):
    with pytest.raises(ConfigError, match=needle):
        SolverConfig(**kw)


@pytest.mark.parametrize("mode,levels", [("sdf", 3), ("sdf", 1), ("udf", 2)])
def test_total_iterations_is_the_total_the_solver_reports(mode, levels):
    cfg = SolverConfig(levels=levels, coarse_iterations=30, middle_iterations=20, iterations=10, queries=2000,
                       mode=mode, udf_polish=7)
    lat = Lattice((-0.5, -0.5, -0.5), 1.0 / 128, (129, 129, 129))
    totals = set()
    solve(_sphere_cloud(3000), lat, cfg, progress=lambda it, total, stats: totals.add(total), history_every=5)
    assert totals == {cfg.total_iterations(128)}
    assert cfg.total_iterations(128) == {1: 10, 3: 60, 2: 40}[levels] + (7 if mode == "udf" else 0)


def test_level_schedules_are_typed_and_take_the_coarse_or_refinement_settings():
    cfg = SolverConfig(lr=0.9, lr_step=300, m2=12, gamma=0.01, query_sigma=0.3, tv_form="sqrt", refine_lr=0.2,
                       refine_lr_step=150, refine_m2=7, refine_gamma=2.0, refine_sigma=0.6,
                       refine_tv_form="squared", query_pool=500, iterations=400, coarse_iterations=600)
    coarse, fine = cfg.level_settings(0, 2), cfg.level_settings(1, 2)
    assert coarse == LevelSchedule(iterations=600, queries=50_000, query_pool=500, lr=0.9, lr_step=300, m2=12,
                                   gamma=0.01, sigma=0.3, tv_form="sqrt")
    assert fine == LevelSchedule(iterations=400, queries=50_000, query_pool=400, lr=0.2, lr_step=150, m2=7,
                                 gamma=2.0, sigma=0.6, tv_form="squared")
    with pytest.raises(AttributeError):
        fine.iterations = 1  # frozen
    polish = cfg.replace(udf_polish=120).polish_settings()
    assert polish == LevelSchedule(iterations=120, queries=50_000, query_pool=120, lr=0.2, lr_step=30, m2=7,
                                   gamma=2.0, sigma=0.6, tv_form="squared")
