"""Property-based tests (hypothesis): readers fed damaged real files, and settings fed random values.

* Readers: real LAS/LAZ/PLY/OBJ files cut at any point of their header and first records, or with bytes of
  their header overwritten, go through every public read function of :mod:`tiled_gridpull.io`; the only
  error allowed is :class:`~tiled_gridpull.errors.InputError`, one line naming the file. (Random bytes behind
  fixed prefixes and cuts at fixed fractions are in ``test_io_formats.py``.)
* Settings: random values for every key of ``SolverConfig`` / ``TilingConfig``, random mappings in a config
  file and random ``--set`` strings: the only error allowed is :class:`~tiled_gridpull.errors.ConfigError`,
  raised before any input is read.
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import tempfile
import warnings
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from tiled_gridpull.config import SolverConfig, parse_overrides
from tiled_gridpull.errors import ConfigError, InputError
from tiled_gridpull.io import iter_point_chunks, point_count, read_mesh, read_points
from tiled_gridpull.tiling import TilingConfig

from conftest import SHARED

FAST = settings(max_examples=int(os.environ.get("FUZZ_EXAMPLES", 40)), deadline=None,
                suppress_health_check=[HealthCheck.too_slow])

# ------------------------------------------------------------------------------------------------------ readers


def _real(rel: str) -> Path | None:
    p = SHARED / rel
    return p if p.is_file() else None


def _las_bytes() -> bytes | None:
    """autzen_trim.laz rewritten as uncompressed LAS (first 2,000 points: the fuzzing needs its header)."""
    src = _real("lidar/autzen_trim.laz")
    if src is None:
        return None
    import laspy

    las = laspy.read(str(src))
    las.points = las.points[:2000]
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "a.las"
        las.write(str(p))
        return p.read_bytes()


@functools.lru_cache(maxsize=1)
def _sources() -> dict[str, tuple[str, bytes, int]]:
    """name -> (suffix, bytes, size of the region worth damaging: header plus the first records)."""
    out = {}
    for rel, suffix in [("lidar/autzen_trim.laz", ".laz"), ("lidar/autzen_ept_depth0-2.laz", ".laz"),
                        ("lidar/ahn3_cropped_2.laz", ".laz"), ("scans/stanford_bunny/bun000.ply", ".ply"),
                        ("meshes/stanford_bunny_bun_zipper.ply", ".ply")]:
        p = _real(rel)
        if p is not None:
            data = p.read_bytes()
            out[rel] = (suffix, data, min(len(data), _header_size(data, suffix) + 4000))
    las = _las_bytes()
    if las is not None:
        out["autzen.las"] = (".las", las, _header_size(las, ".las") + 20 * 34)
    return out


def _header_size(data: bytes, suffix: str) -> int:
    if suffix in (".las", ".laz"):
        return int.from_bytes(data[96:100], "little")  # offset to point data
    end = data.find(b"end_header")
    return end + 11 if end >= 0 else 1024


needs_shared = pytest.mark.skipif(_real("lidar/autzen_trim.laz") is None,
                                  reason="shared data not available: ../shared/data")


def _read_all(p: Path, mesh: bool) -> None:
    """Every public reader on ``p``: each either returns or raises a one-line InputError naming the file."""
    calls = [lambda: read_points(p), lambda: read_points(p, clean=False), lambda: point_count(p),
             lambda: sum(len(c) for c in iter_point_chunks(p, chunk_size=50_000))]
    if mesh:
        calls.append(lambda: read_mesh(p))
    for call in calls:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                call()
        except InputError as exc:
            msg = str(exc)
            assert msg.startswith(str(p)) and "\n" not in msg, msg


@needs_shared
@FAST
@given(data=st.data())
def test_real_files_cut_anywhere_in_the_header_or_first_records(data):
    name = data.draw(st.sampled_from(sorted(_sources())), label="file")
    suffix, raw, region = _sources()[name]
    cut = data.draw(st.integers(0, region), label="cut")
    assume(cut < len(raw))
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"cut{suffix}"
        p.write_bytes(raw[:cut])
        _read_all(p, mesh=suffix == ".ply")


@needs_shared
@FAST
@given(data=st.data())
@pytest.mark.slow
def test_real_files_with_damaged_headers(data):
    name = data.draw(st.sampled_from(sorted(_sources())), label="file")
    suffix, raw, region = _sources()[name]
    header = min(_header_size(raw, suffix), len(raw))
    edits = data.draw(st.lists(st.tuples(st.integers(0, max(header - 1, 0)), st.integers(0, 255)), min_size=1,
                               max_size=6), label="edits")
    buf = bytearray(raw[:region] if suffix == ".laz" and len(raw) > 2_000_000 else raw)
    for pos, value in edits:
        buf[pos] = value
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"bad{suffix}"
        p.write_bytes(bytes(buf))
        _read_all(p, mesh=suffix == ".ply")


@pytest.mark.skipif(_real("meshes/fandisk.obj") is None, reason="shared data not available: ../shared/data")
@FAST
@given(cut=st.floats(0.0, 1.0), edits=st.lists(st.tuples(st.floats(0.0, 1.0), st.binary(min_size=1, max_size=3)),
                                                max_size=4))
def test_obj_meshes_cut_or_damaged(cut, edits):
    raw = bytearray(_real("meshes/fandisk.obj").read_bytes())
    for where, junk in edits:
        i = int(where * (len(raw) - 1))
        raw[i:i + len(junk)] = junk
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "m.obj"
        p.write_bytes(bytes(raw[: int(cut * len(raw))]))
        try:
            read_mesh(p)
        except InputError as exc:
            assert str(exc).startswith(str(p)) and "\n" not in str(exc)


# ----------------------------------------------------------------------------------------------------- settings

_values = st.one_of(
    st.none(), st.booleans(), st.integers(), st.integers(-(10 ** 30), 10 ** 30),
    st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e-300, 1e-300), st.floats(0.01, 100.0),
    st.text(max_size=12), st.sampled_from(["sqrt", "squared", "abs", "sdf", "udf", "sphere", "flood", "auto", "up"]),
    st.lists(st.integers(), max_size=3), st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
)
SOLVER_KEYS = sorted(SolverConfig.setting_names())  # flat, dotted and section names
TILING_KEYS = sorted(TilingConfig.__dataclass_fields__)


@FAST
@given(st.dictionaries(st.sampled_from(SOLVER_KEYS), _values, max_size=6))
def test_solver_config_accepts_or_raises_config_error(d):
    try:
        cfg = SolverConfig(**d)
    except ConfigError as exc:
        assert "\n" not in str(exc)
        return
    from tiled_gridpull.config import _TYPE as declared

    for name, v in cfg.to_flat().items():  # what is accepted is a clean, finite value of the declared type
        assert isinstance(v, bool) == (declared[name] in ("bool", bool)), (name, v)
        if isinstance(v, float):
            assert math.isfinite(v)


@FAST
@given(st.dictionaries(st.sampled_from(TILING_KEYS), _values, max_size=5))
def test_tiling_config_accepts_or_raises_config_error(d):
    try:
        t = TilingConfig(**d)
        if not t.resolved:  # auto, or a cell size with a unit: sizes are checked once the data is known
            t = t.with_cell_size(0.1, "test") if t.voxel_unit == "auto" else t.in_data_units(None)
    except ConfigError as exc:
        assert "\n" not in str(exc)
        return
    assert t.tile_cells >= 8 and 2 * t.overlap_cells <= t.tile_cells


def _namespace(config: str | None, overrides: list[str]) -> argparse.Namespace:
    return argparse.Namespace(config=config, overrides=overrides, resolution=None, iterations=None, seed=None,
                              mode=None, voxel_size=None, tile_size=None, overlap=None)


_yaml_values = st.one_of(st.none(), st.booleans(), st.integers(-10 ** 6, 10 ** 6), st.floats(allow_nan=False),
                         st.text(max_size=8), st.lists(st.integers(), max_size=2))


@FAST
@given(st.dictionaries(st.one_of(st.sampled_from(SOLVER_KEYS + TILING_KEYS), st.text(max_size=8),
                                 st.integers(-3, 3)), _yaml_values, max_size=6))
def test_config_files_accept_or_raise_config_error(d):
    """The command line's loading path: YAML file -> resolve_settings (what ``--config`` runs)."""
    from tiled_gridpull.pipeline.cli import resolve_settings

    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "c.yaml"
        p.write_text(yaml.safe_dump(d))
        try:
            resolve_settings(_namespace(str(p), []))
        except ConfigError as exc:
            assert "\n" not in str(exc)


@FAST
@given(st.lists(st.one_of(st.text(max_size=20),
                          st.builds(lambda k, v: f"{k}={v}", st.sampled_from(SOLVER_KEYS + TILING_KEYS),
                                    st.text(max_size=10))), max_size=4))
def test_set_overrides_accept_or_raise_config_error(items):
    from tiled_gridpull.pipeline.cli import resolve_settings

    try:
        parse_overrides(items)
        resolve_settings(_namespace(None, items))
    except ConfigError as exc:
        assert "\n" not in str(exc)


def test_config_file_damaged_bytes_raise_config_error(tmp_path):
    """Not hypothesis: a config file that is not text at all."""
    from tiled_gridpull.pipeline.cli import resolve_settings

    p = tmp_path / "c.yaml"
    p.write_bytes(bytes(range(256)) + b"\xff\xfe")
    with pytest.raises(ConfigError, match="config file"):
        resolve_settings(_namespace(str(p), []))
