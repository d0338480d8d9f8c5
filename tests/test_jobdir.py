"""The job directory and the outputs: writes never follow a planted symlink, mesh and sidecar are committed
together, and one job at a time holds a work directory."""

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
