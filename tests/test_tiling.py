"""TilingConfig: tile core and overlap follow the cell size unless given (issue 19)."""

import json
from pathlib import Path

import numpy as np
import pytest

from tiled_gridpull.errors import ConfigError
from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.tiling import DEFAULT_OVERLAP_CELLS, DEFAULT_TILE_CELLS, TilingConfig

SCENE = str(Path(__file__).resolve().parents[1] / "configs" / "scene.yaml")


@pytest.mark.parametrize("voxel", [0.05, 0.1, 0.3, 0.5, 2.0])
def test_sizes_not_given_follow_the_cell_size(voxel):
    t = TilingConfig(voxel_size=voxel)
    assert (t.tile_cells, t.overlap_cells) == (DEFAULT_TILE_CELLS, DEFAULT_OVERLAP_CELLS)
    assert t.tile_size == pytest.approx(DEFAULT_TILE_CELLS * voxel)
    assert t.overlap == pytest.approx(DEFAULT_OVERLAP_CELLS * voxel)
    assert t.derived == ("tile_size", "overlap")


def test_the_default_grid_is_the_one_of_earlier_versions():
    # 0.1 m cells: 25.6 m cores and 3.2 m overlaps exactly, so keys and meshes of earlier jobs stay valid
    t = TilingConfig()
    assert (t.tile_size, t.overlap) == (25.6, 3.2)
    assert t == TilingConfig(voxel_size=0.1, tile_size=25.6, overlap=3.2)


def test_a_size_given_in_data_units_is_kept():
    t = TilingConfig(voxel_size=0.3, tile_size=25.6)
    assert t.tile_size == 25.6 and t.tile_cells == 88
    assert t.overlap_cells == DEFAULT_OVERLAP_CELLS
    assert t.derived == ("overlap",)
    t = TilingConfig(voxel_size=0.3, tile_size=25.6, overlap=3.0)
    assert t.derived == () and t.overlap_cells == 16


def test_the_record_survives_a_round_trip_through_the_sidecar():
    d = TilingConfig(voxel_size=0.5, overlap=8.0).to_dict()
    assert d["derived"] == ["tile_size"]
    again = TilingConfig(**{k: v for k, v in json.loads(json.dumps(d)).items()
                            if k in TilingConfig.__dataclass_fields__})
    assert again == TilingConfig(voxel_size=0.5, overlap=8.0) and again.derived == ("tile_size",)


def test_bad_cell_size_is_still_refused_when_sizes_follow_it():
    with pytest.raises(ConfigError, match="voxel_size must be positive"):
        TilingConfig(voxel_size=0.0)
    with pytest.raises(ConfigError, match="voxel_size must be a finite number"):
        TilingConfig(voxel_size=float("inf"))


@pytest.mark.parametrize("name,value", [("derived", "[]"), ("halo", "4")])
def test_recorded_fields_are_not_user_settings(tmp_path, capsys, name, value):
    """``derived`` records how sizes were found, ``halo`` is set by the job from its denoising."""
    p = tmp_path / "c.npy"
    np.save(p, np.random.default_rng(0).uniform(0, 10, size=(500, 3)))
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "--voxel-size", "0.1", "--dry-run",
                 "--set", f"{name}={value}", "-q"])
    assert code == 2 and f"unknown setting(s): {name}" in capsys.readouterr().err


def test_the_denoising_halo_is_shown_by_the_dry_run(tmp_path, capsys):
    p = tmp_path / "c.npy"
    np.save(p, np.random.default_rng(0).uniform(0, 30, size=(3000, 3)))
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "--voxel-size", "0.1", "--tile-size",
                 "12.8", "--dry-run", "--set", "denoise=2"])
    out = capsys.readouterr().out
    assert code == 0 and "and a halo of 8 cells read for denoising" in out and "copies in overlaps and halos" in out
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "--voxel-size", "0.1", "--tile-size",
                 "12.8", "--dry-run"])
    assert code == 0 and "halo" not in capsys.readouterr().out


def test_coarser_cells_with_the_scene_config_need_no_scaled_sizes(tmp_path, capsys):
    """`--voxel-size 0.5` with configs/scene.yaml used to be refused ("overlap of 8 cells is too small"); the
    dry run now plans 256-cell cores and says why."""
    rng = np.random.default_rng(1)
    xyz = np.c_[rng.uniform(0, 300, 20_000), rng.uniform(0, 40, 20_000), rng.normal(0, 0.05, 20_000)]
    p = tmp_path / "ground.npy"
    np.save(p, xyz)
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "--config", SCENE,
                 "--voxel-size", "0.5", "--dry-run"])
    out, err = capsys.readouterr()
    assert code == 0, err
    line = next(ln for ln in (out + err).splitlines() if ln.startswith("tiles:"))
    assert "core 256 cells (128), overlap 32 cells (16) per side" in line
    assert "core and overlap not given: they follow the cell size" in line
    # a size given on the command line is the user's, in the data's units
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "--config", SCENE,
                 "--voxel-size", "0.5", "--tile-size", "64", "--dry-run"])
    out, err = capsys.readouterr()
    line = next(ln for ln in (out + err).splitlines() if ln.startswith("tiles:"))
    assert code == 0 and "core 128 cells (64)" in line and "overlap not given: it follows" in line


def test_a_cell_size_in_metres_follows_the_data_unit():
    from tiled_gridpull.crs import LinearUnit

    t = TilingConfig(voxel_size="0.1 m")
    assert (t.voxel_size, t.voxel_unit) == (0.1, "m")
    feet = t.in_data_units(LinearUnit("foot", 0.3048))
    assert feet.voxel_size == pytest.approx(0.1 / 0.3048) and feet.voxel_unit is None
    assert (feet.tile_cells, feet.overlap_cells) == (DEFAULT_TILE_CELLS, DEFAULT_OVERLAP_CELLS)
    assert feet.derived == ("voxel_size", "tile_size", "overlap") and "foot" in feet.units
    # no CRS: metres, and the very grid a bare 0.1 gives
    plain = t.in_data_units(None)
    assert plain == TilingConfig(voxel_size=0.1) and "no CRS" in plain.units
    # a bare number is already in the data's units
    assert TilingConfig(voxel_size=0.3).in_data_units(LinearUnit("foot", 0.3048)).voxel_size == 0.3
    with pytest.raises(ConfigError, match="geographic"):
        t.in_data_units(LinearUnit("degree", None))
    with pytest.raises(ConfigError, match="voxel_size must be a number"):
        TilingConfig(voxel_size="0.1 furlong")


def test_resolving_the_cell_size_keeps_every_other_setting():
    """``with_cell_size`` (a length with a unit, or auto) builds a new config: every setting it does not resolve
    must come across, including any added later (it once listed them by hand)."""
    from dataclasses import fields

    from tiled_gridpull.tiling import _RESOLVED

    given = {"trim_distance": 5.0, "min_points": 7, "orientation": "up", "normal_neighbors": 9,
             "drop_outliers": True, "halo": 3, "bridge": 12.0, "bridge_objects": 16.0, "attributes": "rgb",
             "min_component_cells": 4.5}
    assert set(given) | set(_RESOLVED) == {f.name for f in fields(TilingConfig)}, "a new setting needs a value here"
    for t in (TilingConfig(voxel_size="0.1 m", **given), TilingConfig(voxel_size="auto", **given)):
        out = t.with_cell_size(0.25, "test")
        assert {k: getattr(out, k) for k in given} == given
        assert out.voxel_size == 0.25 and out.tile_cells == DEFAULT_TILE_CELLS


def test_scene_config_on_a_survey_in_feet_plans_ten_centimetre_cells(tmp_path, capsys):
    """The issue's Autzen case: configs/scene.yaml on data in feet used 0.1 ft cells (8,979 tiles)."""
    from test_crs import FEET_WKT1

    from tiled_gridpull.synthetic.lidar_files import write_las

    rng = np.random.default_rng(2)
    xyz = np.c_[rng.uniform(0, 300, 20_000), rng.uniform(0, 120, 20_000), rng.normal(0, 0.1, 20_000)]
    feet, metres = tmp_path / "feet.laz", tmp_path / "metres.laz"
    write_las(feet, xyz + [1_312_000.0, 400_000.0, 0.0], crs_wkt=FEET_WKT1)
    write_las(metres, xyz)

    def tiles_line(path, *extra):
        code = main(["reconstruct", str(path), "-o", str(tmp_path / f"{path.stem}.ply"), "--config", SCENE,
                     "--dry-run", *extra])
        out, err = capsys.readouterr()
        assert code == 0, err
        lines = (out + err).splitlines()
        return next(ln for ln in lines if ln.startswith("lattice:")), next(ln for ln in lines
                                                                          if ln.startswith("tiles:"))

    lattice, tiles = tiles_line(feet)
    assert "cell 0.328084 (0.1 m = 0.328084 foot (the input's CRS))" in lattice
    assert "core 256 cells (83.9895)" in tiles and "(4 x 2 x 1)" in tiles
    lattice, tiles = tiles_line(metres)
    assert "cell 0.1 (0.1 m = 0.1 (the input declares no CRS: taken as metres))" in lattice
    assert "core 256 cells (25.6)" in tiles and "(12 x 5 x 1)" in tiles
    # a bare number on the command line is the data's unit, whatever the CRS
    lattice, _ = tiles_line(feet, "--voxel-size", "2")
    assert lattice.startswith("lattice:  cell 2, ")


def test_voxel_size_auto_measures_the_points_and_says_so(tmp_path, capsys):
    from tiled_gridpull.prepare import resolve_units

    rng = np.random.default_rng(3)
    n = 30_000
    xyz = np.c_[rng.uniform(0, 60, n), rng.uniform(0, 30, n), rng.normal(0, 0.01, n)]  # 0.245 spacing
    p = tmp_path / "ground.npy"
    np.save(p, xyz)
    auto = TilingConfig(voxel_size="auto", overlap=10.0)
    assert not auto.resolved and auto.voxel_size == "auto"
    with pytest.raises(ValueError, match="not resolved"):
        _ = auto.tile_cells
    t = resolve_units([str(p)], auto)
    assert t.resolved and t.voxel_size == 0.25 and t.tile_cells == DEFAULT_TILE_CELLS
    assert t.overlap == 10.0 and t.overlap_cells == 40  # given: data units
    assert t.derived == ("voxel_size", "tile_size") and t.units.startswith("auto: sample spacing")
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "--config", SCENE, "--voxel-size", "auto",
                 "--dry-run"])
    out, err = capsys.readouterr()
    assert code == 0, err
    lattice = next(ln for ln in (out + err).splitlines() if ln.startswith("lattice:"))
    assert lattice.startswith("lattice:  cell 0.25 (auto: sample spacing 0.2")
    # a cloud whose points are all one: one line, no traceback
    np.save(p, np.ones((500, 3)))
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "--voxel-size", "auto", "--dry-run"])
    err = capsys.readouterr().err
    assert code == 2 and "no measurable spacing" in err and "Traceback" not in err


def test_voxel_size_auto_reads_every_input_not_only_the_first(tmp_path):
    """A sliver of 10 points first, then the survey: neither "too few points" nor a cell from the sliver."""
    from tiled_gridpull.prepare import resolve_units

    rng = np.random.default_rng(4)
    sliver, ground = tmp_path / "a_sliver.npy", tmp_path / "b_ground.npy"
    np.save(sliver, np.c_[rng.uniform(0, 90, 10), rng.uniform(0, 90, 10), np.zeros(10)])
    np.save(ground, np.c_[rng.uniform(0, 60, 30_000), rng.uniform(0, 30, 30_000), np.zeros(30_000)])
    t = resolve_units([str(sliver), str(ground)], TilingConfig(voxel_size="auto"))
    assert t.voxel_size == 0.25 and "of 2 inputs" in t.units
    # and a budget split over many inputs still reads each one's start
    t = resolve_units([str(sliver), str(ground)], TilingConfig(voxel_size="auto"), chunk_size=1_000)
    assert t.voxel_size == 0.25


def test_a_crs_whose_unit_cannot_be_read_refuses_a_length_with_a_unit(tmp_path):
    """Taking metres for a CRS that declares some other, unread, unit would silently scale the cells."""
    from tiled_gridpull.errors import ConfigError as Refused
    from tiled_gridpull.prepare import resolve_units
    from tiled_gridpull.synthetic.lidar_files import write_las

    rng = np.random.default_rng(3)
    site = write_las(tmp_path / "site.laz", rng.uniform(0, 50, (2_000, 3)), crs_wkt='LOCAL_CS["my site"]')
    with pytest.raises(Refused, match=r"0\.1 m: the input's CRS \(my site\) does not state its unit") as err:
        resolve_units([str(site)], TilingConfig(voxel_size="0.1 m"))
    assert "\n" not in str(err.value)
    # a bare number is the data's own unit and needs no conversion
    assert resolve_units([str(site)], TilingConfig(voxel_size=0.1)).voxel_size == 0.1


def test_geotiff_keys_that_cannot_be_read_still_count_as_a_crs(monkeypatch):
    import laspy
    from laspy.vlrs.known import GeoKeyDirectoryVlr

    from tiled_gridpull.io import las

    header = laspy.LasHeader(point_format=3, version="1.2")
    keys = GeoKeyDirectoryVlr()
    header.vlrs.append(keys)

    def no_pyproj():
        raise ImportError("pyproj")

    monkeypatch.setattr(header, "parse_crs", no_pyproj)
    assert las._las_crs(header) == las.GEOTIFF_UNREAD
    header.vlrs.remove(keys)
    assert las._las_crs(header) is None


@pytest.mark.parametrize("voxel", [1e300, "1e12 m", 2e9])
def test_an_absurd_cell_size_is_one_line(voxel):
    with pytest.raises(ConfigError, match="larger than any survey needs"):
        TilingConfig(voxel_size=voxel)


@pytest.mark.parametrize("kw,needle", [
    ({"voxel_size": "auto", "derived": 5}, "derived must be a list of"),
    ({"voxel_size": 0.1, "derived": ["trim_distance"]}, "derived must be a list of"),
    ({"voxel_size": "auto", "voxel_unit": "m"}, "give the cell size as voxel_size alone"),
    ({"voxel_size": 0.1, "voxel_unit": "auto"}, "give the cell size as voxel_size alone"),
])
def test_record_fields_are_not_settings_of_their_own(kw, needle):
    with pytest.raises(ConfigError, match=needle):
        TilingConfig(**kw)


def test_every_point_has_one_owner_among_the_tiles_holding_it_and_boxes_span_them():
    from tiled_gridpull.tile_plan import plan_tiles

    rng = np.random.default_rng(3)
    cfg = TilingConfig(voxel_size=0.5, tile_size=8.0, overlap=2.0)  # 16-cell cores, 4-cell overlaps
    xyz = rng.uniform([0, 0, 0], [40, 30, 9], (4000, 3))
    plan = plan_tiles(np.stack([xyz.min(0), xyz.max(0)]), len(xyz), cfg)
    idx = plan.lattice.to_index(xyz)
    idx[:50, 0] = 16.0 * rng.integers(1, 3, 50)  # on core borders, where a floor decides the owner
    owner = plan.owner_of(idx)
    rows, tiles = plan.tiles_of(idx)
    holds = {(int(r), *map(int, t)) for r, t in zip(rows, tiles)}
    assert all((r, *map(int, owner[r])) in holds for r in range(len(xyz)))
    assert len(holds) > len(xyz)  # overlaps copy points, owners do not
    # a box's span covers every tile holding a point of the box, and no tile beyond the grid
    lo, hi = idx.min(0), idx.max(0)
    first, last = plan.tile_span(lo[None], hi[None])
    assert np.all(tiles >= first) and np.all(tiles <= last)
    assert np.all(first >= 0) and np.all(last < np.asarray(plan.tile_range))
