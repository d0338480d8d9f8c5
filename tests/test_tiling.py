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


def test_derived_is_not_a_user_setting(tmp_path, capsys):
    p = tmp_path / "c.npy"
    np.save(p, np.random.default_rng(0).uniform(0, 10, size=(500, 3)))
    code = main(["reconstruct", str(p), "-o", str(tmp_path / "o.ply"), "--voxel-size", "0.1", "--dry-run",
                 "--set", "derived=[]", "-q"])
    assert code == 2 and "unknown setting(s): derived" in capsys.readouterr().err


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
