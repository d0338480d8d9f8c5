"""tiled_gridpull: GridPull surface reconstruction for very large point clouds.

The core (this package) runs without Dask: :func:`reconstruct` turns one cloud into a mesh with the banded
GridPull solver, and :func:`reconstruct_scene` runs a tiled job in this process. The same tiled job on a Dask
cluster lives in :mod:`tiled_gridpull.pipeline` (the ``pipeline/`` folder of the source tree), which imports the
core and never the other way round. ``docs/architecture.md`` draws the layers.

The public API, all importable from here::

    reconstruct, reconstruct_scene, run_tiled_job      one shape; a tiled scene (serial, or any executor)
    SolverConfig, TilingConfig, Lattice                 the settings and the global grid
    read_points, iter_point_chunks, read_kitti_sequence, PointCloud, as_points
    read_mesh, write_mesh, Mesh                         meshes (Mesh.to_trimesh / to_pyvista / to_open3d ...)
    evaluate                                            Chamfer, normal consistency, F-score, Hausdorff
    load_job                                            a job directory, for notebooks
    GridPullError, InputError, ConfigError              the errors every failure is reported as

Names beyond the few every use needs are loaded on first access (as scikit-image does), so ``import
tiled_gridpull`` stays quick.
"""

import importlib as _importlib
import os as _os

# pykdtree and numba's OpenMP layer take turns every iteration; with OpenMP's default busy-wait the idle
# pool of one spins on the cores the other needs (a 50k-query nearest-neighbour call went from 1.2 ms to
# 8 ms). OpenMP reads the policy once, when its runtime loads (the first pykdtree import), so it has to be
# set before that, which is here. Passive waiting costs nothing measurable here. An explicit user setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _numba_cache_dir() -> str | None:
    """Where numba caches the kernels when neither of its own places is writable, else None.

    numba writes next to the source (``kernels/__pycache__``) or, where that is read-only (a system-wide or
    container install), under the user's cache directory; with neither (a container run as another user,
    ``HOME`` unset or read-only) every ``cache=True`` kernel raised "no locator available" at import, before
    ``--help``. Then a directory under the system's temporary one serves (per user)."""
    import tempfile

    kernels = _os.path.join(_os.path.dirname(__file__), "kernels")
    cache = _os.path.join(kernels, "__pycache__")
    if _os.access(cache if _os.path.isdir(cache) else kernels, _os.W_OK):
        return None
    home = _os.path.expanduser("~")
    if home != "~" and _os.path.isdir(home) and _os.access(home, _os.W_OK):
        return None  # numba's user-wide cache under ~/.cache
    uid = _os.getuid() if hasattr(_os, "getuid") else "user"
    return _os.path.join(tempfile.gettempdir(), f"tiled-gridpull-numba-{uid}")


if "NUMBA_CACHE_DIR" not in _os.environ:
    _dir = _numba_cache_dir()
    if _dir is not None:
        _os.environ["NUMBA_CACHE_DIR"] = _dir

from ._version import __version__  # noqa: E402
from .config import SolverConfig  # noqa: E402
from .errors import ConfigError, GridPullError, InputError  # noqa: E402
from .lattice import Lattice  # noqa: E402
from .mesh import Mesh  # noqa: E402
from .reconstruct import reconstruct  # noqa: E402

# public name -> module that defines it, imported on first access
_LAZY = {
    "reconstruct_scene": "tiled_job",
    "run_tiled_job": "tiled_job",
    "TilingConfig": "tiling",
    "read_points": "io",
    "iter_point_chunks": "io",
    "read_kitti_sequence": "io",
    "read_mesh": "io",
    "write_mesh": "io",
    "PointCloud": "cloud",
    "as_points": "cloud",
    "evaluate": "metrics",
    "load_job": "jobview",
}

__all__ = ["__version__", "reconstruct", "SolverConfig", "Lattice", "Mesh", "GridPullError", "InputError",
           "ConfigError", *_LAZY]


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'tiled_gridpull' has no attribute {name!r}")
    value = getattr(_importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
