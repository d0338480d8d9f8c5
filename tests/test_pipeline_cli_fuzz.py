"""Fuzzing the command line and the job directory (hypothesis): whatever the options or the damage, the tool
answers with a result or one line and a documented exit code, never an internal error or a traceback.

The readers and the config dataclasses have their own property tests (test_properties.py); these go through
``main`` as a user does.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.io import read_mesh

from test_reliability import OPTS, scene_points

EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", 40))
# CI replays the same examples (a red CI names a bug, not a roll of the dice); FUZZ_RANDOM=1 explores new ones
DERANDOMIZE = not os.environ.get("FUZZ_RANDOM")
DOCUMENTED = {0, 2, 3, 5, 6}  # success, option, input, memory budget, failed tiles (README, "Exit codes")

_junk = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(min_value=-(1 << 70), max_value=1 << 70).map(str),
    st.text(alphabet=st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=12),
    st.sampled_from(["0", "-1", "1e400", "nan", "0x10", "1_000", "", " ", "3:1", "0:99999999999999999999",
                     "2GB", "0B", "-5MB", "tcp://", "auto"]),
)
_keys = st.sampled_from(["m1", "m2", "refine_m2", "iterations", "queries", "queries_per_point", "min_points",
                         "trim_distance", "orientation", "levels", "lr", "alpha", "mode", "drop_outliers",
                         "voxel_size", "overlap", "seed", "unknown_key"])
_options = st.lists(st.one_of(
    st.tuples(st.sampled_from(["--voxel-size", "--tile-size", "--overlap", "--iterations", "--seed",
                               "--workers", "--frames", "--max-memory", "--mode", "--resolution"]), _junk),
    st.tuples(st.just("--set"), st.tuples(_keys, _junk).map(lambda kv: f"{kv[0]}={kv[1]}")),
), max_size=4)


def _run(argv: list[str], capsys) -> tuple[int, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code
    return int(code), capsys.readouterr().err


def _one_line_or_success(code: int, err: str) -> None:
    assert code in DOCUMENTED, err
    assert "internal error" not in err and "Traceback" not in err, err
    if code not in (0, 6):
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("error: "), err


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz_cli")
    np.save(d / "pts.npy", scene_points())
    return d


@settings(max_examples=EXAMPLES, deadline=None, derandomize=DERANDOMIZE,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(options=_options)
def test_reconstruct_options_give_a_plan_or_one_line(cloud, capsys, options):
    """Random option values on ``reconstruct --dry-run`` (tiled: it plans and partitions but never solves, so
    valid combinations stay fast). Nothing is written but the dry run's job directory."""
    argv = ["reconstruct", str(cloud / "pts.npy"), "-o", str(cloud / "out.ply"), "--dry-run", "-q",
            "--voxel-size", "0.2", "--tile-size", "6.4", "--overlap", "1.6", "--set", "m2=6", "--set", "refine_m2=6"]
    for flag, value in options:
        argv += [flag, value] if not value.startswith("-") else [f"{flag}={value}"]
    code, err = _run(argv, capsys)
    _one_line_or_success(code, err)
    assert not (cloud / "out.ply").exists()


# ------------------------------------------------------------------------------------------------ job directory


@pytest.fixture(scope="module")
def finished_job(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz_job")
    np.save(d / "pts.npy", scene_points())
    out, work = d / "ref.ply", d / "ref.job"
    code = main(["reconstruct", str(d / "pts.npy"), "-o", str(out), "-q", "--work-dir", str(work), *OPTS])
    assert code == 6  # the 6-point stray cluster's tile is too small to solve (test_reliability)
    return d, read_mesh(out)


def _damage(path: Path, how: str, where: float, target: Path) -> None:
    data = path.read_bytes()
    if how == "truncate":
        path.write_bytes(data[: int(len(data) * where)])
    elif how == "flip":
        i = min(int(len(data) * where), max(len(data) - 1, 0))
        if data:
            path.write_bytes(data[:i] + bytes([data[i] ^ 0xFF]) + data[i + 1:])
    elif how == "zero":
        i = int(len(data) * where)
        path.write_bytes(data[:i] + b"\0" * min(64, len(data) - i) + data[i + 64:])
    elif how == "delete":
        path.unlink()
    elif how == "symlink":
        path.unlink()
        path.symlink_to(target)
    elif how == "directory":
        path.unlink()
        path.mkdir()


@settings(max_examples=max(3, EXAMPLES // 8), deadline=None, derandomize=DERANDOMIZE,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(pick=st.floats(0.0, 1.0, exclude_max=True), how=st.sampled_from(
    ["truncate", "flip", "zero", "delete", "symlink", "directory"]), where=st.floats(0.0, 1.0))
@pytest.mark.slow
def test_damaged_job_directory_is_redone_or_refused_in_one_line(finished_job, capsys, pick, how, where):
    """Damage one file of a finished job directory (truncate, flip or zero bytes, delete it, or put a symlink or
    a directory in its place) and rerun: the job redoes what it cannot trust and writes the same mesh, or refuses
    in one line. A symlink is never written through."""
    d, reference = finished_job
    work = d / "fuzz.job"
    shutil.rmtree(work, ignore_errors=True)
    shutil.copytree(d / "ref.job", work, symlinks=True)
    files = sorted(p for p in work.rglob("*") if p.is_file() and not p.is_symlink() and p.name != ".lock")
    victim = files[int(pick * len(files))]
    bystander = d / "bystander.txt"
    bystander.write_text("not the job's")
    _damage(victim, how, where, bystander)
    out = d / "fuzz.ply"
    code, err = _run(["reconstruct", str(d / "pts.npy"), "-o", str(out), "-q", "--work-dir", str(work), *OPTS],
                     capsys)
    _one_line_or_success(code, err)
    assert bystander.read_text() == "not the job's"
    if code == 6:
        side = json.loads(out.with_suffix(".json").read_text())
        failed = {t["tile"]: t["reason"] for t in side["tiles"]["not_solved"] if t["status"] == "failed"}
        extra = {t: r for t, r in failed.items() if "too few points" not in r}
        if extra:  # a tile that could not be redone is named, with the damaged file in its one-line reason
            assert all(str(victim) in r for r in extra.values()), extra
        else:
            mesh = read_mesh(out)
            assert np.array_equal(mesh.vertices, reference.vertices) and \
                np.array_equal(mesh.faces, reference.faces), (victim.relative_to(work), how)


_FOLDERS = ["points", "fields", "pieces", "summaries", "points/.segments"]


def _snapshot(root: Path) -> dict:
    """Every file and link under ``root`` (not followed): bytes or link target, and modification time."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            if p.is_symlink():
                out[str(p.relative_to(root))] = ("link", os.readlink(p))
            elif p.is_file():
                out[str(p.relative_to(root))] = (p.read_bytes(), p.stat().st_mtime_ns)
    return out


@settings(max_examples=max(3, EXAMPLES // 8), deadline=None, derandomize=DERANDOMIZE,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(linked=st.lists(st.sampled_from(_FOLDERS), min_size=0, max_size=3, unique=True),
       target=st.sampled_from(["moved", "empty", "dangling", "inside"]),
       file_links=st.integers(0, 2), dry_run=st.booleans())
@example(linked=[], target="moved", file_links=2, dry_run=False)  # file links alone: replaced, a full rerun
@example(linked=["points"], target="moved", file_links=0, dry_run=True)  # the dry run reads what to reuse
@pytest.mark.slow
def test_linked_job_folders_are_never_written_or_read_through(finished_job, capsys, linked, target, file_links,
                                                               dry_run):
    """Replace folders of a finished job directory by symlinks (to the folder moved outside, to an empty folder
    outside, to nowhere, or to another folder of the job), and some of its files by symlinks to folders outside,
    then rerun (or dry-run): the job refuses a linked folder in one line, exit 2, and nothing outside the job
    directory is written, whatever it answers."""
    d, reference = finished_job
    work, outside = d / "links.job", d / "outside"
    for p in (work, outside):
        shutil.rmtree(p, ignore_errors=True)
    shutil.copytree(d / "ref.job", work, symlinks=True)
    outside.mkdir()
    for k, name in enumerate(sorted(linked, key=len, reverse=True)):  # points/.segments before points
        folder, away = work / name, outside / f"folder{k}"
        if target == "moved" and folder.is_dir():
            shutil.move(folder, away)  # the job's own files, outside: a read through the link would reuse them
        else:
            shutil.rmtree(folder, ignore_errors=True)
            if target == "empty":
                away.mkdir()
            elif target == "inside":
                away = work / "summaries" if name != "summaries" else work / "fields"
        folder.parent.mkdir(parents=True, exist_ok=True)
        folder.symlink_to(away, target_is_directory=True)
    files = sorted(p for p in work.rglob("*") if p.is_file() and not p.is_symlink() and p.suffix in (".npz", ".json")
                   and p.parent != work)
    for k, victim in enumerate(files[:: max(1, len(files) // max(file_links, 1))][:file_links]):
        (outside / f"dir{k}").mkdir()
        victim.unlink()
        victim.symlink_to(outside / f"dir{k}", target_is_directory=True)
    before = _snapshot(outside)
    out = d / "links.ply"
    out.unlink(missing_ok=True)
    code, err = _run(["reconstruct", str(d / "pts.npy"), "-o", str(out), "-q", "--work-dir", str(work), *OPTS,
                      *(["--dry-run"] if dry_run else [])], capsys)
    _one_line_or_success(code, err)
    assert _snapshot(outside) == before
    if linked:
        assert code == 2 and " is a link (to " in err, err
        assert not out.exists()
    elif code == 6 and not dry_run:  # file links only: replaced, never followed; the same mesh
        mesh = read_mesh(out)
        assert np.array_equal(mesh.vertices, reference.vertices) and np.array_equal(mesh.faces, reference.faces)


# ------------------------------------------------------------------------------------------------ damaged indexes


@pytest.fixture(scope="module")
def ept_index(tmp_path_factory):
    from tiled_gridpull.io.indexed_write import write_ept

    d = tmp_path_factory.mktemp("fuzz_ept")
    write_ept(d / "ref", scene_points(), max_node_points=1500)
    return d


_index_junk = st.one_of(st.integers(min_value=-(1 << 66), max_value=1 << 66), st.sampled_from([-1, 0, -2]),
                        st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=6), st.none(),
                        st.booleans(), st.lists(st.integers(), max_size=3))
_node_keys = st.one_of(st.tuples(st.integers(-2, 70), st.integers(-2, 9), st.integers(-2, 9), st.integers(-2, 9))
                       .map(lambda k: "-".join(map(str, k))), st.text(max_size=8))


@settings(max_examples=max(10, EXAMPLES // 2), deadline=None, derandomize=DERANDOMIZE,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(edits=st.lists(st.one_of(
    st.tuples(st.just("entry"), st.integers(0, 10 ** 6), _index_junk),    # an existing node's count
    st.tuples(st.just("add"), _node_keys, _index_junk),                   # a node or page entry added
    st.tuples(st.just("page"), _node_keys, st.dictionaries(_node_keys, _index_junk, max_size=3)),  # a sub-page
    st.tuples(st.just("meta"), st.sampled_from(["span", "points", "bounds", "boundsConforming", "schema"]),
              _index_junk),
    st.tuples(st.just("bound"), st.integers(0, 11), st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                                                              st.integers(-(1 << 66), 1 << 66))),
), min_size=1, max_size=3))
def test_a_damaged_index_gives_a_plan_or_one_line(ept_index, capsys, edits):
    """Damage an EPT's hierarchy pages and ept.json (counts, keys, pages that list themselves or their ancestors,
    junk values, bounds and spans of no extent) and dry-run it: a plan or one line with a documented exit code,
    never a hang (a damaged hierarchy once sent the walk round a cycle for ever) or an internal error."""
    d = ept_index / "fuzz"
    shutil.rmtree(d, ignore_errors=True)
    shutil.copytree(ept_index / "ref", d)
    meta = json.loads((d / "ept.json").read_text())
    root = json.loads((d / "ept-hierarchy" / "0-0-0-0.json").read_text())
    for what, a, b in edits:
        if what == "entry":
            root[sorted(root)[a % len(root)]] = b
        elif what == "add":
            root[a] = b
        elif what == "page":
            root.setdefault(a, -1)
            if all(c.isalnum() or c == "-" for c in a) and a:  # a file name the page can have
                (d / "ept-hierarchy" / f"{a}.json").write_text(json.dumps(b))
        elif what == "meta":
            meta[a] = b
        else:
            cube = meta.get("bounds" if a < 6 else "boundsConforming")
            if isinstance(cube, list) and len(cube) == 6:
                cube[a % 6] = b
    (d / "ept-hierarchy" / "0-0-0-0.json").write_text(json.dumps(root))
    (d / "ept.json").write_text(json.dumps(meta))
    out = ept_index / "out.ply"
    code, err = _run(["reconstruct", str(d / "ept.json"), "-o", str(out), "--dry-run", "-q", "--voxel-size", "0.2",
                      "--tile-size", "6.4", "--overlap", "1.6", "--set", "m2=6", "--set", "refine_m2=6"], capsys)
    _one_line_or_success(code, err)
    assert not out.exists()
