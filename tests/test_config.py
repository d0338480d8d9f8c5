"""Bad settings are refused with one line (exit 2) before any work: no input read, no job directory, no output.

``test_pipeline_cli.py`` covers resolution 0, negative iterations and alpha, an unknown ``--set`` key, a bad choice, an
overlap larger than the tile and a negative voxel size; these are the rest.
"""

from pathlib import Path

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
    (["--voxel-size", "1e-300", "--tile-size", "25.6"], "tile_size 25.6 is"),
    ([*TILED, "--tile-size", "6.4", "--overlap", "6.4"], "overlap"),
    ([*TILED, "--overlap", "0.8"], "too small for a TV band"),
    ([*TILED, "--set", "trim_distance=40"], "trim_distance"),
    ([*TILED, "--set", "min_points=0"], "min_points must be a positive integer"),
    ([*TILED, "--set", "orientation=left"], "orientation must be one of"),
    ([*TILED, "--workers", "-1"], "--workers must be between 0 and 1024"),
    ([*TILED, "--workers", "0", "--scheduler", "tcp://127.0.0.1:9"], "--workers 0 runs the tiles in this process"),
    ([*TILED, "--workers", "0", "--batch-tiles", "4"], "--batch-tiles needs a Dask cluster"),
    ([*TILED, "--batch-tiles", "0"], "--batch-tiles must be between 1 and 4096"),
    (["--batch-tiles", "4"], "--batch-tiles applies to tiled mode"),
    ([*TILED, "--max-memory", "lots"], "--max-memory expects a size"),
    ([*TILED, "--max-memory", "0MB"], "--max-memory must be at least"),
    ([*TILED, "--frames", "9:3"], "--frames"),
    ([*TILED, "--set", "alpha=[1"], "not valid YAML"),
    ([*TILED, "--set", "lr=1e999"], "lr must be a finite number"),
    (["--tile-size", "12.8"], "need voxel_size"),
    (["--dry-run"], "--dry-run applies to tiled mode"),
    (["--max-memory", "2GB"], "--max-memory applies to tiled mode"),
    ([*TILED, "--band-edges", "close"], "--band-edges applies to one-shape mode"),
    (["--mode", "udf", "--band-edges", "trim"], "--band-edges applies to signed mode"),
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
                                dict(tile_size="25"), dict(voxel_size=1e-9, tile_size=25.6), dict(min_points=1 << 70),
                                dict(bridge_objects=-1.0), dict(bridge_objects=float("nan")),
                                dict(min_component_cells=-1.0), dict(min_component_cells=float("inf")),
                                dict(min_component_cells="2")])
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


# ------------------------------------------------------------------------------------ the configuration's shape

def _resolve(tmp_path, text: str, *overrides: str):
    from tiled_gridpull.pipeline.cli import build_parser, resolve_settings

    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    argv = ["reconstruct", "x.ply", "-o", "y.ply", "--config", str(cfg)]
    for item in overrides:
        argv += ["--set", item]
    return resolve_settings(build_parser().parse_args(argv))[0]


def test_flat_dotted_and_nested_spellings_are_one_setting(tmp_path):
    from tiled_gridpull.config import SETTINGS

    base = SolverConfig()
    for name, (section, field) in SETTINGS.items():
        value = base.get(name)
        if isinstance(value, str):
            new = {"sqrt": "squared", "squared": "sqrt", "sdf": "udf", "auto": "cpu"}[value]
        elif isinstance(value, bool):
            new = not value
        else:
            new = value + 1 if isinstance(value, int) else value / 2 + 0.3
        flat = base.replace(**{name: new})
        assert flat.get(name) == new != value, name
        if section is None:
            continue
        # the same setting by its place: dotted, as a nested mapping, through its attribute
        assert base.replace(**{f"{section}.{field}": new}) == flat, name
        assert SolverConfig(**{section: {field: new}}) == flat, name
        assert getattr(getattr(flat, section), field) == new, name
        # everything else unchanged
        assert {k: v for k, v in flat.to_flat().items() if k != name} == \
               {k: v for k, v in base.to_flat().items() if k != name}, name


def test_nested_config_file_equals_its_flat_form_and_round_trips(tmp_path):
    nested = _resolve(tmp_path, "schedule:\n  finest_iterations: 300\n  levels: 2\nrefine:\n  lr: 0.2\n"
                                "  query_sigma: 0.4\nsampling:\n  m1: 2\n")
    flat = _resolve(tmp_path, "iterations: 300\nlevels: 2\nrefine_lr: 0.2\nrefine_sigma: 0.4\nm1: 2\n")
    assert nested == flat == SolverConfig(iterations=300, levels=2, refine_lr=0.2, refine_sigma=0.4, m1=2)
    assert nested.schedule.finest_iterations == 300 and nested.refine.query_sigma == 0.4
    assert SolverConfig(**nested.to_dict()) == nested == SolverConfig(**nested.to_flat())
    # a later source overrides an earlier one whatever the spelling: --set after the file
    assert _resolve(tmp_path, "refine:\n  lr: 0.2\n", "refine_lr=0.1").refine.lr == 0.1
    assert _resolve(tmp_path, "refine_lr: 0.2\n", "refine.lr=0.05").refine.lr == 0.05


def test_shipped_configs_are_valid_and_shape_yaml_is_the_default(tmp_path):
    from tiled_gridpull.config import load_config_file

    repo = Path(__file__).resolve().parents[1]
    assert SolverConfig(**load_config_file(repo / "configs" / "shape.yaml")) == SolverConfig()
    for path in sorted((repo / "configs").glob("*.yaml")):
        _resolve(tmp_path, path.read_text())  # every key known and valid


@pytest.mark.parametrize("text,needle", [
    ("lr: 0.5\ncoarse:\n  lr: 0.4\n", "lr is given twice"),
    ("refine:\n  rate: 0.4\n", "refine.rate"),
    ("refine: 0.4\n", "refine must be a LevelConfig or a mapping"),
    ("schedule:\n  finest_iterations: 0\n", "iterations must be positive"),
    ("refine:\n  tv_form: cubic\n", "refine.tv_form must be one of"),
])
def test_nested_settings_refused_with_one_line(tmp_path, text, needle):
    with pytest.raises(ConfigError, match=needle) as exc:
        _resolve(tmp_path, text)
    assert "\n" not in str(exc.value)


def test_a_section_object_replaces_its_section_and_sidecars_record_sections():
    from tiled_gridpull.config import REFINE_DEFAULTS, LevelConfig, recorded_settings

    cfg = SolverConfig(refine=LevelConfig(m2=6, lr=0.1, lr_step=50, gamma=1.0, query_sigma=0.3, tv_form="sqrt"))
    assert cfg.level_settings(1, 2).m2 == 6 and cfg.level_settings(0, 2).m2 == 14
    assert cfg.replace(refine=REFINE_DEFAULTS) == SolverConfig()
    record = cfg.to_dict()
    assert record["refine"]["m2"] == 6 and record["sampling"]["m1"] == 3 and "refine_m2" not in record
    # a sidecar of this version and a flat one of an earlier version read back the same settings
    assert recorded_settings(record) == cfg.to_flat() == recorded_settings(cfg.to_flat())


def test_a_noise_setting_named_on_the_command_line_is_the_users_choice(tmp_path):
    """`--set denoise=0` keeps a scan's points as they are, although 0 is the default: naming the passes turns
    the automatic choice off, unless the same source names noise_auto; the scene config names both."""
    from tiled_gridpull.config import load_config_file
    from tiled_gridpull.pipeline.cli import build_parser, resolve_settings

    from conftest import REPO

    scene = str(REPO / "configs" / "scene.yaml")

    def solver(*argv):
        return resolve_settings(build_parser().parse_args(["reconstruct", "x.laz", "-o", "y.ply", *argv]))[0]

    assert load_config_file(REPO / "configs" / "scene.yaml")["noise"]["auto"] is True
    assert solver("--config", scene).noise.auto is True
    assert solver("--config", scene, "--set", "denoise=0").noise.auto is False
    assert solver("--config", scene, "--set", "denoise=2").noise.denoise_passes == 2
    assert solver("--config", scene, "--set", "denoise=0", "--set", "noise_auto=true").noise.auto is True
    # the passes' parameters are not a choice of treatment in tiled mode; in one-shape mode every noise setting is
    assert solver("--config", scene, "--set", "denoise_radius=1.5").noise.auto is True
    assert solver("--set", "beta=1.0").noise.auto is False
    assert solver("--set", "alpha=2.0").noise.auto is True
