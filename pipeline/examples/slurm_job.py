"""Reconstruct a LiDAR sequence on a SLURM (or PBS) cluster through dask-jobqueue.

Run it from a login node (it submits the worker jobs itself and waits for them)::

    python -m tiled_gridpull.pipeline.examples.slurm_job /data/seq/*.laz -o /scratch/$USER/street.ply \
        --voxel-size 0.1 --jobs 8 --cores 8 --memory 32GB --queue normal --walltime 04:00:00

Each SLURM job runs one Dask worker process *per core*, each with one thread (numba's parallel kernels must not
run from several threads of one process; one tile per process also bounds memory by the tile). The job
directory must be on a filesystem every node sees. Re-running the same command after a crash reuses every
finished tile. For PBS use ``--system pbs``. The equivalent with a scheduler you started yourself is
``tiled-gridpull reconstruct ... --scheduler tcp://HOST:8786``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def build_cluster(system: str, jobs_cores: int, memory: str, queue: str | None, walltime: str,
                  account: str | None = None, local_directory: str | None = None):
    """A dask-jobqueue cluster whose jobs each hold ``jobs_cores`` single-threaded worker processes.

    Returns
    -------
    dask_jobqueue.JobQueueCluster (not yet scaled)
    """
    try:
        import dask_jobqueue
    except ImportError:
        sys.exit("this example needs dask-jobqueue: pip install 'tiled-gridpull[hpc]'")
    cls = {"slurm": dask_jobqueue.SLURMCluster, "pbs": dask_jobqueue.PBSCluster}[system]
    # numba and OpenMP threads: one per worker process, set before the workers import anything
    env = ["export NUMBA_NUM_THREADS=1", "export OMP_NUM_THREADS=1", "export OMP_WAIT_POLICY=PASSIVE"]
    kwargs = dict(cores=jobs_cores, processes=jobs_cores, memory=memory, walltime=walltime,
                  job_script_prologue=env, local_directory=local_directory or "$TMPDIR")
    if queue:
        kwargs["queue"] = queue
    if account:
        kwargs["account"] = account
    return cls(**kwargs)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("inputs", nargs="+")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--config", default=str(Path(__file__).resolve().parents[2] / "configs" / "scene.yaml"))
    ap.add_argument("--voxel-size", type=float)
    ap.add_argument("--system", choices=("slurm", "pbs"), default="slurm")
    ap.add_argument("--jobs", type=int, default=4, help="batch jobs to submit")
    ap.add_argument("--cores", type=int, default=8, help="cores (= worker processes) per job")
    ap.add_argument("--memory", default="32GB", help="memory per job")
    ap.add_argument("--queue")
    ap.add_argument("--account")
    ap.add_argument("--walltime", default="04:00:00")
    ap.add_argument("--work-dir", help="shared job directory (default: OUTPUT.job)")
    a = ap.parse_args(argv)

    from tiled_gridpull.pipeline.job import JobOptions, run_job
    from tiled_gridpull.config import SolverConfig, drop_removed_settings, load_config_file, split_settings
    from tiled_gridpull.tiling import check_compatible, TilingConfig

    settings = load_config_file(a.config)
    if a.voxel_size:
        settings["voxel_size"] = a.voxel_size
    solver_settings, rest = split_settings(drop_removed_settings(settings))
    unknown = set(rest) - set(TilingConfig.__dataclass_fields__)
    if unknown:
        raise SystemExit(f"{a.config}: unknown setting(s): {', '.join(sorted(map(str, unknown)))}")
    solver = SolverConfig(**solver_settings)
    tiling = TilingConfig(**rest)
    check_compatible(tiling, solver)
    cluster = build_cluster(a.system, a.cores, a.memory, a.queue, a.walltime, a.account)
    cluster.scale(jobs=a.jobs)
    try:
        work_dir = a.work_dir or str(Path(a.output).with_suffix(".job"))
        run_job(a.inputs, a.output, tiling, solver, work_dir, JobOptions(scheduler=cluster.scheduler_address))
    finally:
        cluster.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
