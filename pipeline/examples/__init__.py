"""Example batch scripts for running tiled jobs on HPC schedulers (SLURM, PBS) through dask-jobqueue."""
