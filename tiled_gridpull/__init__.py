"""tiled_gridpull: GridPull surface reconstruction for very large point clouds.

The core (this package) runs without Dask: :func:`reconstruct` turns one cloud into a mesh with the banded
GridPull solver. The tiled, out-of-core pipeline on Dask lives in :mod:`tiled_gridpull.pipeline` (the
``pipeline/`` folder of the source tree), which imports the core and never the other way round.
"""

import os as _os

# pykdtree and numba's OpenMP layer take turns every iteration; with OpenMP's default busy-wait the idle
# pool of one spins on the cores the other needs (a 50k-query nearest-neighbour call went from 1.2 ms to
# 8 ms). Passive waiting costs nothing measurable here. Respect an explicit user setting.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from ._version import __version__  # noqa: E402
from .config import SolverConfig  # noqa: E402
from .errors import ConfigError, GridPullError, InputError  # noqa: E402
from .lattice import Lattice  # noqa: E402
from .mesh import Mesh  # noqa: E402
from .reconstruct import reconstruct  # noqa: E402

__all__ = ["__version__", "reconstruct", "SolverConfig", "Lattice", "Mesh", "GridPullError", "InputError",
           "ConfigError"]
