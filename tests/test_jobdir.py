"""The job directory and the outputs: writes never follow a planted symlink, mesh and sidecar are committed
together, and one job at a time holds a work directory."""

import contextlib
import os

import numpy as np
import pytest

from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.cloud import PointCloud
from tiled_gridpull.errors import ConfigError, InputError
from tiled_gridpull.io import read_mesh, write_mesh_and_sidecar
from tiled_gridpull.io.atomic import atomic_open
from tiled_gridpull.jobdir import job_lock
from tiled_gridpull.synthetic import sphere
from tiled_gridpull.partition import partition
from tiled_gridpull.tile_plan import plan_tiles
from tiled_gridpull.tiling import TilingConfig


def test_atomic_write_replaces_a_symlink_instead_of_writing_through_it(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    target = tmp_path / "out.txt"
    target.symlink_to(victim)
    # a link planted where an older version put its temporary file, too
    (tmp_path / f".out.txt.tmp-{os.getpid()}").symlink_to(victim)
    with atomic_open(target, "w") as fh:
        fh.write("new")
    assert victim.read_text() == "precious"
    assert not target.is_symlink() and target.read_text() == "new"
    assert oct(target.stat().st_mode & 0o777) == oct(0o666 & ~_umask())


def _umask():
    m = os.umask(0)
    os.umask(m)
    return m


def test_partition_never_writes_through_a_symlink_in_the_job_directory(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 5, size=(3000, 3))
    tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
    plan = plan_tiles(np.stack([xyz.min(0), xyz.max(0)]), len(xyz), tiling)
    out = tmp_path / "points"
    specs = partition([PointCloud(xyz)], plan, out, False)
    victim = tmp_path / "victim.bin"
    victim.write_bytes(b"precious")
    for spec in specs:
        for name in (f"{spec.name}.occ.npy", f".{spec.name}.points.partial", f"{spec.name}.points"):
            p = out / name
            if p.exists() or p.is_symlink():
                p.unlink()
            p.symlink_to(victim)
    again = partition([PointCloud(xyz)], plan, out, False)
    assert victim.read_bytes() == b"precious"
    assert [s.points_sha256 for s in again] == [s.points_sha256 for s in specs]
    for spec in again:
        assert not _is_link(out / f"{spec.name}.occ.npy") and not _is_link(out / f"{spec.name}.points")


def _is_link(p):
    return os.path.islink(p)


def test_mesh_and_sidecar_are_committed_together(tmp_path):
    m = sphere()
    m.metadata["generator"] = "tiled_gridpull 0"
    out = tmp_path / "m.ply"
    (tmp_path / "m.json").mkdir()  # the sidecar cannot be written
    with pytest.raises(InputError, match=r"m\.json: a directory stands where this file is to be written"):
        write_mesh_and_sidecar(m, out)
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json"]  # no temporary files left either
    (tmp_path / "m.json").rmdir()
    write_mesh_and_sidecar(m, out)
    assert len(read_mesh(out).faces) == len(m.faces) and (tmp_path / "m.json").is_file()


def test_second_job_on_a_work_directory_is_refused(tmp_path, capsys):
    pts = np.random.default_rng(1).uniform(0, 5, size=(2000, 3))
    np.save(tmp_path / "p.npy", pts)
    work = tmp_path / "job"
    with job_lock(work):
        code = main(["reconstruct", str(tmp_path / "p.npy"), "-o", str(tmp_path / "m.ply"), "--voxel-size", "0.2",
                     "--tile-size", "6.4", "--overlap", "3.2", "--work-dir", str(work), "-q"])
        err = capsys.readouterr().err
        assert code == 2 and f"in use by another job (PID {os.getpid()})" in err, err
        assert err.count("\n") == 1
        with pytest.raises(ConfigError, match="in use by another job"):
            with job_lock(work):
                pass
    with job_lock(work):  # released when the holder is done
        pass
    assert not (tmp_path / "m.ply").exists()


_FSIZE_JOB = """
import resource, signal, sys
import numpy as np
if __name__ == "__main__":
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead of killing the process
    resource.setrlimit(resource.RLIMIT_FSIZE, (4000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
    from tiled_gridpull.pipeline.cli import main
    sys.exit(main(sys.argv[1:]))
"""


def test_file_size_limit_mid_job_names_the_file_in_one_line(tmp_path):
    """A write refused by the machine mid-job (here a file-size limit; a full disk alike) is one line naming
    the file, exit 3 (README, "Exit codes"); the message was "error: File too large"."""
    import subprocess
    import sys
    from pathlib import Path

    pts = np.random.default_rng(1).uniform(0, 5, size=(2000, 3))
    np.save(tmp_path / "p.npy", pts)  # 48 kB, read, not written, under the limit
    work = tmp_path / "job"
    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", _FSIZE_JOB, "reconstruct", str(tmp_path / "p.npy"), "-o",
                           str(tmp_path / "m.ply"), "--voxel-size", "0.2", "--tile-size", "6.4", "--overlap", "3.2",
                           "--work-dir", str(work), "--workers", "1", "-q"],
                          cwd=repo, capture_output=True, text=True, timeout=300)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 3 and len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"error: {work / 'points'}/") and lines[0].endswith(": File too large"), lines[0]
    assert not (tmp_path / "m.ply").exists()


def test_an_atomic_write_refused_by_the_machine_names_its_file(tmp_path):
    """The storage error of a write (EFBIG here, ENOSPC or EDQUOT alike) carries no file name of its own: the
    atomic writer adds the file it was writing, and leaves neither it nor its temporary file behind."""
    import errno
    import resource
    import signal

    from tiled_gridpull.io.atomic import write_json

    target = tmp_path / "fields" / "big.json"
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (10_000, hard))
    try:
        with pytest.raises(OSError) as caught:
            write_json(target, {"values": list(range(10_000))})
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)
    assert caught.value.errno == errno.EFBIG and caught.value.filename == str(target)
    assert list(target.parent.iterdir()) == []


def test_an_occupancy_mask_refused_by_the_machine_is_a_storage_error_naming_it(tmp_path):
    """NumPy's own file writer (``np.save`` into an open file) reports a short write without an error number,
    which the command line took for a bug (exit 1): the partition's occupancy masks are written as bytes, so a
    full disk there is a storage error naming the mask like any other."""
    import errno
    import resource
    import signal

    xyz = np.random.default_rng(0).uniform(0, 1, size=(5, 3))
    tiling = TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=1.6)
    plan = plan_tiles(np.stack([xyz.min(0), xyz.max(0)]), len(xyz), tiling)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (150, hard))  # the 60-byte spill file fits, its mask does not
    try:
        with pytest.raises(OSError) as caught:
            partition([PointCloud(xyz)], plan, tmp_path / "points", False)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)
    assert caught.value.errno == errno.EFBIG, caught.value
    assert caught.value.filename.endswith(".occ.npy"), caught.value.filename


# ------------------------------------------------------------------ a chosen work directory: foreign files, links

JOB = ["--voxel-size", "0.2", "--tile-size", "6.4", "--overlap", "3.2", "--set", "m2=6", "--set", "refine_m2=6",
       "--iterations", "30", "--set", "coarse_iterations=30", "--set", "min_points=5", "-q"]


def _tree(root):
    """Every file and link under ``root``: bytes (or link target) and modification time."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = os.path.join(dirpath, name)
            st = os.lstat(p)
            if os.path.islink(p):
                out[os.path.relpath(p, root)] = ("link", os.readlink(p))
            elif os.path.isfile(p):
                out[os.path.relpath(p, root)] = (open(p, "rb").read(), st.st_mtime_ns)
    return out


@pytest.mark.parametrize("name", ["report.json", "manifest.json", "tiles.png"])
def test_a_users_own_file_at_a_job_file_name_is_refused_before_anything_is_written(tmp_path, capsys, name):
    """A work directory the user chose may hold their own files: a job replaces only the fixed-name files that
    carry this tool's generator marker (the rule of the outputs), and refuses in one line, writing nothing,
    when one of those names holds a file it did not write (their report.json used to be replaced silently)."""
    np.save(tmp_path / "p.npy", np.random.default_rng(1).uniform(0, 5, size=(2000, 3)))
    work = tmp_path / "mine"
    work.mkdir()
    (work / name).write_text('{"mine": true}\n')
    (work / "notes.txt").write_text("mine too")
    before = _tree(work)
    code = main(["reconstruct", str(tmp_path / "p.npy"), "-o", str(tmp_path / "m.ply"), "--work-dir", str(work),
                 *JOB])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and name in err, err
    assert "not written by tiled-gridpull" in err, err
    assert _tree(work) == before
    assert not (tmp_path / "m.ply").exists()


@pytest.fixture(scope="module")
def finished_job(tmp_path_factory):
    """A small finished job (serial: no cluster), copied by each test that damages it."""
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.tiled_job import reconstruct_scene

    d = tmp_path_factory.mktemp("jobdir_links")
    np.save(d / "p.npy", np.random.default_rng(1).uniform(0, 5, size=(2000, 3)))
    reconstruct_scene([str(d / "p.npy")], d / "ref.ply", TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=3.2,
                                                                       min_points=5),
                      SolverConfig(m2=6, refine_m2=6, iterations=30, coarse_iterations=30), d / "ref.job")
    return d


@pytest.mark.parametrize("folder", ["points", "fields", "pieces", "summaries", "points/.segments"])
@pytest.mark.parametrize("dry_run", [False, True])
def test_a_folder_of_the_job_directory_linked_elsewhere_is_refused_and_nothing_outside_is_touched(
        finished_job, tmp_path, capsys, folder, dry_run):
    """A folder of the job directory replaced by a symlink to a folder outside: no write goes through it, and
    no read that decides reuse either (the dry run reads the partition to reuse it). One line, exit 2, before
    anything is read or written; the folder outside is left as it was (it used to be filled and replaced)."""
    import shutil

    work, outside = tmp_path / "job", tmp_path / "outside"
    shutil.copytree(finished_job / "ref.job", work, symlinks=True)
    linked = work / folder
    if linked.exists():
        shutil.move(linked, outside)  # the job's own files, now outside: a read through the link would reuse them
    else:
        outside.mkdir()
    linked.symlink_to(outside, target_is_directory=True)
    before = _tree(outside), _tree(work)
    out = tmp_path / "m.ply"
    code = main(["reconstruct", str(finished_job / "p.npy"), "-o", str(out), "--work-dir", str(work), *JOB,
                 *(["--dry-run"] if dry_run else [])])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"{folder} is a link" in err, err
    assert (_tree(outside), _tree(work)) == before
    assert not out.exists()


def test_a_job_directory_of_an_earlier_version_is_resumed_not_refused(finished_job, tmp_path):
    """Versions before the generator marker wrote manifest.json and tiles.png without one: their directories are
    the tool's own, recognised by the manifest's structure, and a rerun resumes them; a foreign manifest that
    merely names a plan is still refused, and so are a foreign report.json (it always carried the marker) and a
    tiles.png that is no PNG in such a directory."""
    import json
    import shutil

    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.jobdir import check_job_dir
    from tiled_gridpull.tiled_job import reconstruct_scene

    job = tmp_path / "old.job"
    shutil.copytree(finished_job / "ref.job", job)
    man = json.loads((job / "manifest.json").read_text())
    del man["generator"]
    (job / "manifest.json").write_text(json.dumps(man))
    png = job / "tiles.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 64)  # a picture without the marker
    check_job_dir(job)
    mesh = reconstruct_scene([str(finished_job / "p.npy")], tmp_path / "again.ply",
                             TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=3.2, min_points=5),
                             SolverConfig(m2=6, refine_m2=6, iterations=30, coarse_iterations=30), job)
    assert mesh.metadata["reused"]["partition"] is True
    # the exemption is the manifest's and the picture's only: report.json carried the marker in every version
    # (a user's own one in such a directory was replaced silently), and a picture must at least be a PNG
    man = json.loads((job / "manifest.json").read_text())
    man.pop("generator", None)  # the reused partition's manifest is the old one
    (job / "manifest.json").write_text(json.dumps(man))
    report, picture = (job / "report.json").read_bytes(), png.read_bytes()
    for name, foreign in (("report.json", b'{"mine": 1}'), ("tiles.png", b"my own notes")):
        (job / name).write_bytes(foreign)
        with pytest.raises(ConfigError, match=f"{name} there was not written by tiled-gridpull"):
            check_job_dir(job)
        assert (job / name).read_bytes() == foreign
        (job / "report.json").write_bytes(report)
        png.write_bytes(picture)
    check_job_dir(job)
    (job / "manifest.json").write_text(json.dumps({"plan": {"name": "mine"}, "tiles": []}))
    with pytest.raises(ConfigError, match="manifest.json there was not written by tiled-gridpull"):
        check_job_dir(job)


# ------------------------------------------------------- a job directory's fixed names: not regular, unparseable


def _without_hanging(fn, fifos, seconds=30.0):
    """``fn()`` in a thread; when it is still running after ``seconds`` (blocked opening or reading one of
    ``fifos``), each FIFO is opened for writing and closed, so the reader sees its end and the thread ends, and the
    test fails. Returns what ``fn`` returned or raised (an exception instance)."""
    import threading

    box = {}

    def target():
        try:
            box["out"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box["out"] = exc

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(seconds)
    if t.is_alive():
        for f in fifos:
            with contextlib.suppress(OSError):
                os.close(os.open(f, os.O_WRONLY | os.O_NONBLOCK))
        t.join(seconds)
        pytest.fail(f"blocked on a FIFO among {[str(f) for f in fifos]}")
    return box.get("out")


@pytest.mark.parametrize("name", ["manifest.json", "report.json", "tiles.png", ".lock"])
def test_a_fifo_at_a_fixed_name_of_the_job_directory_is_refused_without_being_opened(finished_job, tmp_path,
                                                                                    capsys, name):
    """A FIFO at a fixed name (manifest.json, tiles.png) made the dry run wait for a writer for good: deciding
    whether the tool wrote it opened it for reading. Any non-regular file there is refused in one line, exit 2,
    and never opened."""
    import shutil

    work = tmp_path / "job"
    shutil.copytree(finished_job / "ref.job", work)
    (work / name).unlink(missing_ok=True)
    os.mkfifo(work / name)
    code = _without_hanging(lambda: main(["reconstruct", str(finished_job / "p.npy"), "-o", str(tmp_path / "m.ply"),
                                          "--work-dir", str(work), *JOB, "--dry-run"]), [work / name])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and f"{name} there is a FIFO" in err, err
    assert "Traceback" not in err


@pytest.mark.parametrize("kind", ["symlink", "directory", "fifo"])
def test_a_damaged_lock_file_is_one_line_not_an_internal_error(tmp_path, kind):
    """``.lock`` as a symlink (ELOOP), a directory (EISDIR) or a FIFO (flock's EINVAL) was an internal error
    (exit 1): now a ConfigError (exit 2, one line), from job_lock itself and from check_job_dir before it."""
    from tiled_gridpull.jobdir import check_job_dir

    work = tmp_path / "job"
    work.mkdir()
    lock = work / ".lock"
    if kind == "symlink":
        (tmp_path / "elsewhere").write_text("1")
        lock.symlink_to(tmp_path / "elsewhere")
    elif kind == "directory":
        lock.mkdir()
    else:
        os.mkfifo(lock)
    for fn in (lambda: job_lock(work).__enter__(), lambda: check_job_dir(work)):
        out = _without_hanging(fn, [lock] if kind == "fifo" else [])
        assert isinstance(out, ConfigError) and ".lock" in str(out), repr(out)
    assert os.path.islink(lock) or not lock.is_file()  # left as it was


def test_a_fifo_where_a_tile_summary_or_manifest_is_read_counts_as_absent(finished_job, tmp_path):
    """A FIFO at ``summaries/solve_tile_0_0_0.json`` blocked the run for good (read to decide reuse): the reads
    that decide reuse (resume._reusable, load_partition, read_manifest) take a non-regular file as absent or
    damaged, without opening it, and the rerun computes that tile again and replaces the FIFO."""
    import shutil

    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.jobdir import JobPaths, read_manifest
    from tiled_gridpull.resume import _reusable, load_partition
    from tiled_gridpull.tiled_job import reconstruct_scene

    work = tmp_path / "job"
    shutil.copytree(finished_job / "ref.job", work)
    summary = sorted((work / "summaries").glob("solve_*.json"))[0]
    summary.unlink()
    os.mkfifo(summary)
    assert _without_hanging(lambda: _reusable(summary, "k", ("solved",), work / "x"), [summary]) == (None, None)
    man = work / "manifest.json"
    saved = man.read_bytes()
    man.unlink()
    os.mkfifo(man)
    assert _without_hanging(lambda: load_partition(JobPaths(work), "k", TilingConfig()), [man]) is None
    assert isinstance(_without_hanging(lambda: read_manifest(man), [man]), InputError)
    man.unlink()
    man.write_bytes(saved)
    mesh = _without_hanging(lambda: reconstruct_scene(
        [str(finished_job / "p.npy")], tmp_path / "again.ply",
        TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=3.2, min_points=5),
        SolverConfig(m2=6, refine_m2=6, iterations=30, coarse_iterations=30), work), [summary], seconds=300)
    assert not isinstance(mesh, BaseException), repr(mesh)
    assert summary.is_file()  # the FIFO replaced by the tile's summary
    solves = mesh.metadata["reused"]
    assert solves["partition"] is True, solves


DEEP = "[" * 200_000 + "]" * 200_000


@pytest.mark.parametrize("dry_run", [True, False])
def test_a_deeply_nested_or_huge_report_json_in_the_work_directory_is_not_ours(tmp_path, capsys, dry_run):
    """A report.json nested 200,000 deep made the check of its marker raise RecursionError (internal error,
    exit 1), and a 64 GiB sparse one was read whole (out of memory, exit 5): neither is a file this tool wrote,
    refused in one line, exit 2. Nothing over MAX_OWN_FILE bytes is read to decide."""
    np.save(tmp_path / "p.npy", np.random.default_rng(1).uniform(0, 5, size=(2000, 3)))
    for how in ("deep", "huge"):
        work = tmp_path / f"{how}.job"
        work.mkdir()
        if how == "deep":
            (work / "report.json").write_text(DEEP)
        else:
            with open(work / "report.json", "wb") as fh:
                fh.truncate(64 << 30)
        code = main(["reconstruct", str(tmp_path / "p.npy"), "-o", str(tmp_path / "m.ply"), "--work-dir",
                     str(work), *JOB, *(["--dry-run"] if dry_run else [])])
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1, (how, err)
        assert "report.json there was not written by tiled-gridpull" in err, (how, err)
        assert not (tmp_path / "m.ply").exists()


def test_a_deeply_nested_or_huge_sidecar_or_report_is_refused_in_one_line(tmp_path, capsys):
    """The ``-o`` mesh's sidecar nested too deeply to parse is not ours (exit 2, not RecursionError's exit 1);
    ``tiled-gridpull report DIR`` on such a report.json, a huge one or a FIFO says so in one line, exit 3."""
    from tiled_gridpull.io.outputs import written_by_us

    np.save(tmp_path / "p.npy", np.random.default_rng(1).uniform(0, 5, size=(500, 3)))
    (tmp_path / "side.json").write_text(DEEP)
    assert written_by_us(tmp_path / "side.json") is False
    code = main(["reconstruct", str(tmp_path / "p.npy"), "-o", str(tmp_path / "side.ply"), "--resolution", "32",
                 "-q"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "side.json exists and was not written" in err, err
    assert not (tmp_path / "side.ply").exists()
    for how in ("deep", "huge", "fifo"):
        job = tmp_path / f"{how}.job"
        job.mkdir()
        if how == "deep":
            (job / "report.json").write_text(DEEP)
        elif how == "huge":
            with open(job / "report.json", "wb") as fh:
                fh.truncate(64 << 30)
        else:
            os.mkfifo(job / "report.json")
        code = _without_hanging(lambda: main(["report", str(job)]), [job / "report.json"])
        err = capsys.readouterr().err
        assert code == 3 and len(err.strip().splitlines()) == 1 and "report.json" in err, (how, err)
        assert "Traceback" not in err and "internal error" not in err, (how, err)
