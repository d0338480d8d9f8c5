"""``--workers 0``: a tiled job with no Dask cluster, its tiles one after the other in the command's own process."""

import json

import numpy as np
import pytest

from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import ConfigError
from tiled_gridpull.io import read_mesh
from tiled_gridpull.pipeline.cli import main
from tiled_gridpull.synthetic.lidar_files import write_las
from tiled_gridpull.tiling import TilingConfig
from conftest import terrain

SMALL = ["--voxel-size", "0.2", "--tile-size", "6.4", "--overlap", "2.0", "--set", "coarse_iterations=60",
         "--set", "iterations=40", "--set", "middle_iterations=20", "--set", "min_points=50"]


@pytest.fixture
def patch_laz(tmp_path):
    """A 12 m x 9 m wavy ground patch (about 4 tiles of 6.4 m) at UTM-like coordinates, as LAZ."""
    xyz = terrain(12.0, 30.0, seed=5)
    return write_las(tmp_path / "patch.laz", xyz[xyz[:, 1] < 4_000_009.0])


def _reconstruct(src, out, *extra):
    code = main(["reconstruct", str(src), "-o", str(out), "-q", *SMALL, *extra])
    assert code == 0
    return read_mesh(out), json.loads(out.with_suffix(".json").read_text())


def test_workers_0_runs_the_tiles_in_this_process_and_gives_the_clusters_mesh(tmp_path, patch_laz, monkeypatch):
    """The same mesh, vertex for vertex, whether the tiles ran on the local cluster's two one-thread workers or
    one after the other in this process on every core; and with ``--workers 0`` no cluster is made at all."""
    cluster_mesh, cluster_side = _reconstruct(patch_laz, tmp_path / "cluster.ply")
    import tiled_gridpull.pipeline.job as job

    def no_cluster(*args, **kwargs):
        raise AssertionError("--workers 0 started a Dask cluster")

    monkeypatch.setattr(job, "make_client", no_cluster)
    mesh, side = _reconstruct(patch_laz, tmp_path / "here.ply", "--workers", "0")
    assert side["engine"]["scheduler"] == "serial" and cluster_side["engine"]["scheduler"] == "LocalCluster"
    assert side["tiles"]["solved"] == cluster_side["tiles"]["solved"] > 1
    assert mesh.n_faces > 1000
    np.testing.assert_array_equal(mesh.faces, cluster_mesh.faces)
    np.testing.assert_array_equal(mesh.vertices, cluster_mesh.vertices)


def test_workers_0_beside_a_scheduler_is_refused_through_the_api_too(tmp_path, patch_laz):
    """The CLI refuses the pair (tests/test_config.py); a caller of ``run_job`` gets the same one line before
    anything is read or written, rather than a job that silently ignores one of them."""
    from tiled_gridpull.pipeline.job import JobOptions, run_job

    out = tmp_path / "o.ply"
    with pytest.raises(ConfigError, match="workers 0 runs the tiles in this process and scheduler"):
        run_job([str(patch_laz)], out, TilingConfig(voxel_size=0.2, tile_size=6.4, overlap=2.0), SolverConfig(),
                tmp_path / "o.job", JobOptions(workers=0, scheduler="tcp://127.0.0.1:9", progress=False))
    assert not out.exists() and not (tmp_path / "o.job").exists()


def test_the_dry_run_of_workers_0_says_the_tiles_run_in_this_process(tmp_path, patch_laz, capsys):
    out = tmp_path / "o.ply"
    assert main(["reconstruct", str(patch_laz), "-o", str(out), *SMALL, "--workers", "0", "--dry-run"]) == 0
    text = capsys.readouterr().out
    time_line = next(ln for ln in text.splitlines() if ln.startswith("time:"))
    memory_line = next(ln for ln in text.splitlines() if ln.startswith("memory:"))
    assert "in this process (--workers 0" in time_line and "one-thread worker" not in time_line
    assert "peak per tile" in memory_line
    assert main(["reconstruct", str(patch_laz), "-o", str(out), *SMALL, "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert "one-thread worker(s)" in text and "peak per worker" in text and "in this process" not in text
    assert not out.exists() and not out.with_suffix(".job").exists()
