"""Bad settings are refused with one line (exit 2) before any work: no input read, no job directory, no output.

``test_cli.py`` covers resolution 0, negative iterations and alpha, an unknown ``--set`` key, a bad choice, an
overlap larger than the tile and a negative voxel size; these are the rest.
"""

import numpy as np
import pytest

from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import ConfigError
from tiled_gridpull.tiling import TilingConfig


@pytest.fixture
def cloud(tmp_path):
    p = tmp_path / "in.npy"
    np.save(p, np.random.default_rng(0).uniform(0, 10, size=(500, 3)))
    return p


TILED = ["--voxel-size", "0.1"]


@pytest.mark.parametrize("opts,needle", [
    ([*TILED, "--tile-size", "-5"], "tile_size must be positive"),
    ([*TILED, "--tile-size", "0"], "tile_size must be positive"),
    ([*TILED, "--overlap", "-1"], "overlap must be >= 0"),
    (["--voxel-size", "0"], "voxel_size must be positive"),
    (["--voxel-size", "nan"], "voxel_size must be a finite number"),
    (["--voxel-size", "1e-300"], "tile_size 25.6 is"),
    ([*TILED, "--tile-size", "6.4", "--overlap", "6.4"], "overlap"),
    ([*TILED, "--overlap", "0.8"], "too small for a TV band"),
    ([*TILED, "--set", "trim_distance=40"], "trim_distance"),
    ([*TILED, "--set", "min_points=0"], "min_points must be a positive integer"),
    ([*TILED, "--set", "orientation=left"], "orientation must be one of"),
    ([*TILED, "--workers", "0"], "--workers must be between 1 and 1024"),
    ([*TILED, "--max-memory", "lots"], "--max-memory expects a size"),
    ([*TILED, "--max-memory", "0MB"], "--max-memory must be at least"),
    ([*TILED, "--frames", "9:3"], "--frames"),
    ([*TILED, "--set", "alpha=[1"], "not valid YAML"),
    ([*TILED, "--set", "lr=1e999"], "lr must be a finite number"),
    (["--tile-size", "12.8"], "need voxel_size"),
    (["--dry-run"], "--dry-run applies to tiled mode"),
    (["--max-memory", "2GB"], "--max-memory applies to tiled mode"),
    (["--resolution", "-3"], "resolution must be positive"),
    (["--iterations", "0"], "iterations must be positive"),
])
def test_bad_option_refused_before_any_work(tmp_path, capsys, cloud, opts, needle):
    out = tmp_path / "out.ply"
    code = main(["reconstruct", str(cloud), "-o", str(out), "-q", *opts])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    assert needle in lines[0], lines[0]
    assert not out.exists() and not out.with_suffix(".json").exists() and not out.with_suffix(".job").exists()


@pytest.mark.parametrize("text,needle", [
    ("voxel_size: 0.1\nbogus_key: 3\n", "unknown setting(s): bogus_key"),
    ("voxel_size: 0.1\n3: x\n", "unknown setting(s): 3"),
    ("voxel_size: 0.1\ntile_size: -2\n", "tile_size must be positive"),
    ("- voxel_size\n- 0.1\n", "expected a mapping"),
    ("voxel_size: [0.1\n", "not valid YAML"),
    ("voxel_size: 0.1\ninit: flood\n", "init 'flood' was removed"),
    ("voxel_size: 0.1\nsurface_form: squared\n", "surface_form 'squared' was removed"),
])
def test_bad_config_file_refused_before_any_work(tmp_path, capsys, cloud, text, needle):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    out = tmp_path / "out.ply"
    code = main(["reconstruct", str(cloud), "-o", str(out), "-q", "--config", str(cfg)])
    err = capsys.readouterr().err
    assert code == 2
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], err
    assert not out.exists() and not out.with_suffix(".job").exists()


def test_settings_are_checked_before_the_input_is_read(tmp_path, capsys):
    """A bad setting wins over a missing input: nothing is opened before the settings are valid."""
    code = main(["reconstruct", str(tmp_path / "missing.laz"), "-o", str(tmp_path / "o.ply"), "-q",
                 "--voxel-size", "0.1", "--tile-size", "-1"])
    assert code == 2 and "tile_size" in capsys.readouterr().err


@pytest.mark.parametrize("kw", [dict(tile_size=-1.0), dict(tile_size=0.0), dict(overlap=-0.1),
                                dict(trim_distance=-1.0), dict(min_points=0), dict(normal_neighbors=0),
                                dict(voxel_size=0.0), dict(voxel_size=float("inf")), dict(tile_size=True),
                                dict(tile_size="25"), dict(voxel_size=1e-9), dict(min_points=1 << 70)])
def test_tiling_config_refuses(kw):
    with pytest.raises(ConfigError):
        TilingConfig(**kw)


@pytest.mark.parametrize("kw", [dict(resolution=0), dict(resolution=-8), dict(m1=-1), dict(m1=20, m2=10),
                                dict(queries=0), dict(lr=0.0), dict(lr_decay=1.5), dict(levels=5),
                                dict(seed=-1), dict(knn=0), dict(iterations=2.5), dict(alpha=float("nan")),
                                dict(lr=10 ** 400), dict(iterations=1 << 70), dict(mode="both")])
def test_solver_config_refuses(kw):
    with pytest.raises(ConfigError):
        SolverConfig(**kw)


@pytest.mark.parametrize("key,value", [("init", "sphere"), ("surface_form", "abs")])
def test_removed_setting_with_its_remaining_value_is_ignored_with_a_warning(tmp_path, key, value):
    from tiled_gridpull.config import drop_removed_settings

    with pytest.warns(UserWarning, match=f"setting '{key}' was removed"):
        kept = drop_removed_settings({key: value, "alpha": 2.0})
    assert kept == {"alpha": 2.0}
    # and through the command line's settings, from a config file as from --set
    from tiled_gridpull.pipeline.cli import build_parser, resolve_settings

    cfg = tmp_path / "old.yaml"
    cfg.write_text(f"{key}: {value}\nalpha: 2.0\n")
    args = build_parser().parse_args(["reconstruct", "x.ply", "-o", "y.ply", "--config", str(cfg)])
    with pytest.warns(UserWarning, match="was removed"):
        solver, tiling = resolve_settings(args)
    assert solver == SolverConfig(alpha=2.0) and tiling is None
