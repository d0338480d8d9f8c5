"""Noise estimate, the noisy preset (noise_cells, beta = 0) and its warning."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from tiled_gridpull import reconstruct
from tiled_gridpull.config import NOISE_PRESETS, SolverConfig, load_config_file
from tiled_gridpull.errors import ConfigError
from tiled_gridpull.noise import estimate_noise, project_to_local_planes, scan_noise, select_treatment
from tiled_gridpull.synthetic import sample_shape, sphere

from conftest import REPO

SPHERE = sphere(radius=0.5)
FAST = {"iterations": 150, "coarse_iterations": 150, "queries": 20_000}


def noisy_sphere(n: int, sigma: float, seed: int = 0) -> np.ndarray:
    pts, _ = sample_shape(SPHERE, n, seed=seed)
    return pts + np.random.default_rng(seed + 1).normal(scale=sigma, size=pts.shape)


def sphere_error(mesh) -> float:
    """Mean distance of the mesh's vertices to the analytic sphere of radius 0.5."""
    return float(np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.5).mean())


@pytest.mark.parametrize("sigma,noisy", [(0.004, False), (0.01, True)])
def test_estimate_recovers_gaussian_noise(sigma, noisy):
    est = estimate_noise(noisy_sphere(50_000, sigma))
    assert 0.6 * sigma < est.sigma < 1.2 * sigma
    # 0.004 is below the samples' spacing (~0.0055 here): mild; 0.01 is nearly twice it
    assert est.noisy is noisy


def test_clean_cloud_is_not_noisy_and_shift_does_not_matter():
    pts, _ = sample_shape(SPHERE, 50_000, seed=0)
    est = estimate_noise(pts)
    assert not est.noisy and est.sigma < 0.3 * est.spacing
    far = estimate_noise(pts + np.array([500000.0, 4000000.0, 100.0]))
    assert abs(far.sigma - est.sigma) < 1e-3 * est.spacing


@pytest.mark.slow
def test_noise_cells_lowers_the_resolution_and_is_recorded():
    pts = noisy_sphere(30_000, 0.006)
    mesh = reconstruct(pts, resolution=128, noise_cells=1.5, beta=0.0, **FAST)
    est = mesh.metadata["noise_estimate"]
    expected = max(64, int(1.0 / (1.5 * est["sigma"])))  # extent of the cloud ~ 1 + noise
    assert 64 <= mesh.metadata["config"]["resolution"] < 128
    assert abs(mesh.metadata["config"]["resolution"] - expected) <= 0.1 * expected
    assert est["cells"] == pytest.approx(est["sigma"] / mesh.metadata["lattice"]["cell_size"])


@pytest.mark.slow
def test_noise_is_treated_by_default_and_the_treatment_beats_none():
    """1 % of the diameter of noise, twice the samples' spacing: the defaults pick a treatment themselves and
    their surface lies closer to the sphere than with the settings as given (noise_auto off)."""
    pts = noisy_sphere(80_000, 0.01)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        untreated = reconstruct(pts, resolution=128, noise_auto=False)
    assert any("looks noisy" in str(w.message) for w in caught)
    assert untreated.metadata["noise_treatment"] == {"auto": False, "chosen": None, "reason": "noise_auto is off"}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        auto = reconstruct(pts, resolution=128)  # the full schedule: 150 iterations fragment it
    assert not any("looks noisy" in str(w.message) for w in caught)
    chosen = auto.metadata["noise_treatment"]["chosen"]
    assert chosen in NOISE_PRESETS
    # the sidecar's config is the one that ran: the preset's settings applied
    ran = SolverConfig(**auto.metadata["config"])
    assert {k: ran.get(k) for k in NOISE_PRESETS[chosen]} == NOISE_PRESETS[chosen]
    assert auto.topology.watertight and auto.topology.components == 1
    assert sphere_error(auto) < 0.7 * sphere_error(untreated)


@pytest.mark.parametrize("name", sorted(NOISE_PRESETS))
def test_the_preset_files_are_the_treatments_auto_applies(name):
    assert SolverConfig(**load_config_file(REPO / "configs" / f"{name}.yaml")) == SolverConfig(**NOISE_PRESETS[name])


def slab(n: int, gap: float, seed: int = 0) -> np.ndarray:
    """Two parallel 1 x 1 sheets ``gap`` apart (a thin wall), sampled without noise."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 1, (n, 2))
    return np.c_[xy, np.where(np.arange(n) % 2 == 0, 0.0, gap)]


@pytest.mark.parametrize("cloud,expected", [
    (lambda: sample_shape(SPHERE, 50_000, seed=0)[0], None),
    # walls 5 spacings apart: one 64-neighbour plane fit takes in both (ratio 2.4), a 16-neighbour one does not
    (lambda: slab(50_000, 0.015), None),
    # 0.5 % and 1 % of the bounding-box diagonal (ratio 1.33 / 1.86)
    (lambda: noisy_sphere(100_000, 0.0087), "noisy"),
    (lambda: noisy_sphere(100_000, 0.0173), "very_noisy"),
])
def test_the_treatment_follows_the_noise_and_not_thin_walls(cloud, expected):
    pick, est, figures = select_treatment(cloud())
    assert pick == expected, figures
    if expected is None and est.ratio > 1.2:
        assert figures["local_ratio"] < 0.8  # the local scale is what kept it clean
    assert figures["ratio"] == pytest.approx(est.ratio) and "local_ratio" in figures


def test_settings_given_by_the_user_win_over_auto():
    """Any noise setting given (a preset file, or one setting) means the user chose: nothing is added."""
    from tiled_gridpull.reconstruct import _noise_treatment

    pts = noisy_sphere(100_000, 0.0173)
    cfg, record, _ = _noise_treatment(SolverConfig(denoise=1), pts)
    assert cfg == SolverConfig(denoise=1) and record["chosen"] is None and record["reason"] == "given: denoise"
    assert record["given"] == ["denoise"]
    preset = SolverConfig(**load_config_file(REPO / "configs" / "noisy.yaml"))
    assert _noise_treatment(preset, pts)[0] == preset
    cfg, record, _ = _noise_treatment(SolverConfig(), pts)
    assert record["chosen"] == "very_noisy" and cfg == SolverConfig(**NOISE_PRESETS["very_noisy"])
    assert _noise_treatment(SolverConfig(noise_auto=False), pts)[0] == SolverConfig(noise_auto=False)


def test_noise_cells_refused_in_tiled_mode():
    from tiled_gridpull.tiling import check_compatible, TilingConfig

    with pytest.raises(ConfigError, match="noise_cells"):
        check_compatible(TilingConfig(voxel_size=0.1), SolverConfig(noise_cells=1.5))
    with pytest.raises(ConfigError, match="noise_cells"):
        SolverConfig(noise_cells=-1)


@pytest.mark.slow
def test_plane_projection_removes_scatter_across_the_surface_only():
    from tiled_gridpull.noise import project_to_local_planes

    pts = noisy_sphere(50_000, 0.01)
    radial = lambda p: np.linalg.norm(p - p.mean(axis=0), axis=1) - 0.5  # noqa: E731
    out = project_to_local_planes(pts + [500000.0, 4000000.0, 100.0], k=64, iterations=2) - [500000.0, 4000000.0, 100.0]
    assert out.shape == pts.shape
    # scatter across the sphere falls by more than half; the radius itself barely moves (curvature bias)
    assert np.std(radial(out)) < 0.5 * np.std(radial(pts))
    assert abs(np.mean(radial(out))) < 0.002
    # points keep their place along the surface: each stays within a few noise sigmas of where it was
    assert np.percentile(np.linalg.norm(out - pts, axis=1), 99) < 0.05
    assert np.array_equal(project_to_local_planes(pts, iterations=0), pts)


def test_denoise_is_recorded_and_checked_and_tiled_mode_bounds_it():
    from tiled_gridpull.tiling import check_compatible, TilingConfig

    from tiled_gridpull.resume import partition_key
    from tiled_gridpull.tiling import with_halo

    # tiles take plain planes within a radius, and read a halo of points as wide as the passes reach
    tiling = TilingConfig(voxel_size=0.1)
    check_compatible(tiling, SolverConfig(denoise=2))
    with pytest.raises(ConfigError, match="denoise_bandwidth applies to one-shape mode"):
        check_compatible(tiling, SolverConfig(denoise=2, denoise_bandwidth=1.0))
    assert with_halo(tiling, SolverConfig()).halo == 0
    assert with_halo(tiling, SolverConfig(denoise=2)).halo == 8  # 2^2 x 2 cells
    assert with_halo(tiling, SolverConfig(denoise=3, denoise_radius=1.5)).halo == 14  # 13.5, whole cells
    with pytest.raises(ConfigError, match=r"denoise 10 with denoise_radius 4 cells reaches 400 cells, more than a "
                                          r"tile core \(256 cells\)"):
        with_halo(tiling, SolverConfig(denoise=10, denoise_radius=4))
    # the partition a halo was read for is not the one without it
    assert partition_key([], with_halo(tiling, SolverConfig(denoise=2))) != partition_key([], tiling)
    for bad in (-1, 1.5, True):
        with pytest.raises(ConfigError, match="halo"):
            TilingConfig(voxel_size=0.1, halo=bad)
    for bad in (0, -1.0, float("nan")):
        with pytest.raises(ConfigError, match="denoise_radius"):
            SolverConfig(denoise_radius=bad)
    with pytest.raises(ConfigError, match="denoise"):
        SolverConfig(denoise=-1)
    with pytest.raises(ConfigError, match="denoise_neighbors"):
        SolverConfig(denoise_neighbors=2)
    preset = SolverConfig(**load_config_file(REPO / "configs" / "noisy.yaml")).noise
    assert preset.denoise_passes == 2 and preset.denoise_bandwidth > 0
    very = SolverConfig(**load_config_file(REPO / "configs" / "very_noisy.yaml")).noise
    assert very.denoise_passes == 2 and very.denoise_bandwidth == 0


def _noisy_ground(n: int, sigma: float, seed: int = 0) -> np.ndarray:
    """Wavy ground 12.8 m square with a wall along x = 6 (metres; georeferenced offset), Gaussian noise."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 12.8, size=(n, 2))
    ground = np.column_stack([xy, 0.4 * np.sin(xy[:, 0] / 2.0) * np.cos(xy[:, 1] / 3.0)])
    wy = rng.uniform(0.0, 12.8, n // 4)
    wall = np.column_stack([np.full(n // 4, 6.0), wy, rng.uniform(0.0, 3.0, n // 4)])
    pts = np.vstack([ground, wall])
    return pts + rng.normal(scale=sigma, size=pts.shape) + [500000.0, 4000000.0, 50.0]


def _grid_ground(step: float = 0.05) -> np.ndarray:
    """Ground sampled on a regular grid, heights in whole centimetres: every neighbourhood has rings of equally
    distant neighbours, so the k nearest are decided by ties."""
    g = np.arange(0.0, 9.6, step)
    x, y = np.meshgrid(g, g, indexing="ij")
    z = np.round(0.4 * np.sin(x / 2.0) * np.cos(y / 3.0), 2)
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()]) + [500000.0, 4000000.0, 50.0]


@pytest.mark.parametrize("tile_size,seed,neighbors,radius", [(3.2, 0, 32, 1.5), (4.8, 5, 16, 3.0),
                                                             (3.2, None, 12, 1.5)])
def test_tiles_denoise_every_point_as_the_whole_cloud_does(tile_size, seed, neighbors, radius):
    """Each tile reads its block plus a halo as wide as the denoising reaches: every point of every block, in
    every tiling, gets the place the whole cloud's radius-bounded projection gives it. The cloud is quantised to
    millimetres like a LAS file, or sampled on a grid, so neighbours tie at the radius and at the k-th distance
    (the last two cases have more than k points in most balls); the tiles hold tile-local float64 offsets, as
    their spill files do.
    Without the halo the points near an inner face would move otherwise, and are dropped."""
    from tiled_gridpull.tile_plan import plan_tiles
    from tiled_gridpull.tile_solve import _denoise
    from tiled_gridpull.tiling import TilingConfig, with_halo

    world = _grid_ground() if seed is None else np.round(_noisy_ground(20_000, 0.02, seed=seed), 3)
    solver = SolverConfig(denoise=2, denoise_neighbors=neighbors, denoise_radius=radius)
    whole = project_to_local_planes(world, neighbors, 2, radius=radius * 0.1)
    bare = TilingConfig(voxel_size=0.1, tile_size=tile_size, overlap=1.6)
    bounds = np.stack([world.min(axis=0), world.max(axis=0)])
    for tiling in (with_halo(bare, solver), bare):
        plan = plan_tiles(bounds, len(world), tiling)
        point, tile = plan.tiles_of(plan.lattice.to_index(world))
        block_points = dropped = halo_points = 0
        near_face_error = 0.0
        for key in {tuple(t) for t in tile.tolist()}:
            spec = plan.spec(key)
            rows = point[np.all(tile == key, axis=1)]
            corner = np.asarray(spec.block.low_corner)
            local = world[rows] - corner  # as the tile's spill file holds them
            summary: dict = {}
            moved, use = _denoise(local, spec, tiling, solver, summary)
            record = summary["denoise"]
            assert record["points"] == use.sum() == len(moved) and record["moved_max_m"] <= 2 * radius * 0.1
            assert np.abs(moved + corner - whole[rows[use]]).max() < 1e-9
            in_block = np.all((local >= 0) & (local <= (np.asarray(spec.block.shape) - 1) * 0.1), axis=1)
            block_points += int(in_block.sum())
            dropped += record["dropped_near_faces"]
            halo_points += record["halo_points"]
            # the same points without their margin lose neighbours near an inner face and move otherwise
            near = in_block & ~use
            if near.any():
                alone = project_to_local_planes(local, neighbors, 2, radius=radius * 0.1, centre=False) + corner
                near_face_error = max(near_face_error, float(np.abs(alone[near] - whole[rows[near]]).max()))
        if tiling.halo:
            assert tiling.halo == int(np.ceil(4 * radius)) and halo_points > 0 and dropped == 0
        else:
            assert halo_points == 0 and 0 < dropped < block_points and near_face_error > 1e-3


def thin_part(gap: float, sigma: float, n: int = 40_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A noisy unit square (z = 0) with a second sheet ``gap`` above it over x > 0.3, like a plate with a thin
    double-walled part; also which sheet each point came from (0: z = 0, 1: z = gap)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.5, 0.5, size=(n, 2))
    upper = xy[xy[:, 0] > 0.3]
    xy = np.vstack([xy, upper])
    which = np.r_[np.zeros(n, np.int64), np.ones(len(upper), np.int64)]
    z = which * gap + rng.normal(scale=sigma, size=len(xy))
    return np.column_stack([xy, z]), which


@pytest.mark.slow
def test_robust_projection_keeps_two_close_walls_apart():
    """Walls 4 sigma apart share every 64-point neighbourhood: the plain fit merges them into one sheet between,
    the robust (bilateral) fit moves each point toward its own wall."""
    from tiled_gridpull.noise import project_to_local_planes

    sigma, gap = 0.004, 0.016
    pts, which = thin_part(gap, sigma)
    # the double-walled part away from its border and the square's
    inner = (pts[:, 0] > 0.36) & (pts[:, 0] < 0.44) & (np.abs(pts[:, 1]) < 0.44)

    def wall_error(out):
        return float(np.abs(out[inner, 2] - which[inner] * gap).mean())

    plain = project_to_local_planes(pts, k=64, iterations=2)
    robust = project_to_local_planes(pts, k=64, iterations=2, bandwidth=1.0)
    # plain: both walls collapse toward z = gap / 2, an error of about gap / 2 for every point
    assert wall_error(plain) > 0.3 * gap
    # robust: the walls stay apart, and the scatter about each falls well below the input's (0.8 sigma)
    assert wall_error(robust) < 0.25 * gap
    assert wall_error(robust) < 0.7 * wall_error(pts)


@pytest.mark.slow
def test_robust_projection_still_denoises_a_single_sheet():
    """On one noisy surface the robust weights keep some scatter the plain fit removes (measured: 1.4x its residual
    at 64 neighbours) but still take out most of it, with 64 neighbours and with the preset's 32."""
    from tiled_gridpull.noise import project_to_local_planes

    pts = noisy_sphere(50_000, 0.01)
    radial = lambda p: np.linalg.norm(p - p.mean(axis=0), axis=1) - 0.5  # noqa: E731
    robust = np.std(radial(project_to_local_planes(pts, k=64, iterations=2, bandwidth=1.0)))
    assert robust < 0.25 * np.std(radial(pts))
    preset = SolverConfig(**load_config_file(REPO / "configs" / "noisy.yaml")).noise
    out = project_to_local_planes(pts, preset.denoise_neighbors, preset.denoise_passes, preset.denoise_bandwidth)
    assert np.std(radial(out)) < 0.35 * np.std(radial(pts))
    with pytest.raises(ConfigError, match="denoise_bandwidth"):
        SolverConfig(denoise_bandwidth=-1.0)


@pytest.mark.parametrize("scale", [1e-300, 1e160, 1e300])
def test_noise_estimate_and_denoising_at_float_extremes(scale):
    """Squared distances of a cloud 1e160 across overflow: pykdtree answered "no neighbour" (index 2^32 - 1)
    and the estimate indexed past the cloud. Scale-free now: the same answer, scaled."""
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(3000, 3))
    pts /= np.linalg.norm(pts, axis=1)[:, None]
    pts += rng.normal(scale=0.01, size=pts.shape)
    ref = estimate_noise(pts)
    with np.errstate(over="raise", invalid="raise"):
        est = estimate_noise(pts * scale)
        moved = project_to_local_planes(pts * scale, iterations=1)
    assert est.sigma == pytest.approx(ref.sigma * scale, rel=1e-9)
    assert est.spacing == pytest.approx(ref.spacing * scale, rel=1e-9)
    np.testing.assert_allclose(moved / scale, project_to_local_planes(pts, iterations=1), atol=1e-9)


@pytest.mark.parametrize("sigma", [0.0, 0.01, 0.03])
def test_scan_noise_reads_the_scatter_across_planes_in_cells(sigma):
    """Ground and a wall sampled densely (2 cm), with Gaussian noise: the scatter is read in cells of the job,
    its median near sigma and its 25th percentile below it, the same far from the origin."""
    pts = _noisy_ground(200_000, sigma, seed=1)
    est = scan_noise(pts, cell=0.1)
    assert est["sampled"] == 20_000 and est["planar"] > 0.9 * est["sampled"]
    assert est["radius_cells"] == 2.0
    if sigma == 0.0:
        assert est["q25_cells"] < 0.01  # the ground's waves, not noise
    else:
        assert 0.85 * sigma / 0.1 < est["median_cells"] < 1.15 * sigma / 0.1
        assert 0.6 * sigma / 0.1 < est["q25_cells"] < est["median_cells"]
    near = scan_noise(pts - [500000.0, 4000000.0, 50.0], cell=0.1)
    assert near["q25_cells"] == pytest.approx(est["q25_cells"], rel=1e-6)


def test_scan_noise_does_not_count_scan_rings():
    """Points along lines farther apart than the radius (the rings of a scan far from the sensor) have no plane
    to scatter from: any plane through a line fits it, so the line's own scatter would read as a plane's
    thickness of zero. Nothing is measured."""
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 50.0, 100_000)
    ring = rng.integers(0, 20, len(x)) * 0.5  # rings 0.5 m apart, radius 2 x 0.1 m
    pts = np.column_stack([x, ring, rng.normal(scale=0.01, size=len(x))])
    est = scan_noise(pts, cell=0.1)
    assert est["planar"] < 100 and est["q25_cells"] is None and est["median_cells"] is None
    assert scan_noise(pts[:5], cell=0.1)["q25_cells"] is None


def test_scan_noise_needs_planar_neighbourhoods_and_ignores_a_stray_point():
    """A stray first point far away (1e17) changes nothing: offsets are taken from the median; a cloud where few
    neighbourhoods hold a plane within the radius (too sparse for this cell) gives no figure."""
    pts = _noisy_ground(100_000, 0.03, seed=2)
    est = scan_noise(pts, cell=0.1)
    assert est["q25_cells"] > 0.1
    stray = scan_noise(np.vstack([[1e17, 1e17, 1e17], pts]), cell=0.1)
    assert stray["q25_cells"] == pytest.approx(est["q25_cells"], rel=0.02)
    # the same ground with 7 % of it kept at random: fewer than 1 in 4 neighbourhoods holds 10 points in 2 cells
    from tiled_gridpull.noise import SCAN_MIN_PLANAR_SHARE

    sparse = scan_noise(pts[np.random.default_rng(0).random(len(pts)) < 0.07], cell=0.1)
    assert 0 < sparse["planar"] < SCAN_MIN_PLANAR_SHARE * sparse["sampled"] and sparse["q25_cells"] is None
