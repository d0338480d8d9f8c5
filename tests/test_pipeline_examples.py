"""The SLURM/PBS example builds worker jobs with one thread per process and numba/OpenMP pinned to one thread."""

from __future__ import annotations

import pytest

pytest.importorskip("dask_jobqueue")

from tiled_gridpull.pipeline.examples.slurm_job import build_cluster  # noqa: E402


@pytest.mark.parametrize("system", ["slurm", "pbs"])
def test_job_script_single_threaded_workers(system):
    cluster = build_cluster(system, 4, "16GB", "normal", "01:00:00", local_directory="/tmp")
    try:
        script = cluster.job_script()
    finally:
        cluster.close()
    assert "export NUMBA_NUM_THREADS=1" in script and "export OMP_NUM_THREADS=1" in script
    assert "--nthreads 1" in script and "--nworkers 4" in script
    assert ("#SBATCH" if system == "slurm" else "#PBS") in script
