"""Where the solver runs: on the CPU's threads (numba) or on a CUDA card (numba-cuda).

The setting is ``device: cpu | cuda | auto`` (config) or ``--device`` (command line):

* ``cpu``: the numba kernels of :mod:`tiled_gridpull.kernels`;
* ``cuda``: their twins in :mod:`tiled_gridpull.kernels.cuda`; refused in one line when numba-cuda sees no card;
* ``auto`` (default): ``cuda`` when numba-cuda is installed and sees a card, else ``cpu`` (never the simulator).

numba-cuda lives in the ``cuda`` extra (``pip install 'tiled-gridpull[cuda]'``). Under numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1``) the card is simulated on the CPU, slowly: that is how the tests run the CUDA path on
machines without one.
"""

from __future__ import annotations

import functools
import os
import sys
from types import ModuleType

from .errors import ConfigError, MissingDependencyError

__all__ = ["DEVICES", "cuda_card", "cuda_module", "driver_present", "resolve", "describe", "card_memory"]

DEVICES = ("cpu", "cuda", "auto")
SIMULATOR = "CUDA simulator"


def _import_numba_cuda() -> ModuleType:
    import numpy as np

    # numba-cuda 0.30 overloads np.row_stack, which NumPy 2.4+ dropped: without the alias nothing compiles
    if not hasattr(np, "row_stack"):
        np.row_stack = np.vstack  # noqa: NPY201
    from numba import cuda

    return cuda


@functools.cache
def cuda_card() -> str | None:
    """Name of the CUDA card numba-cuda sees (``"CUDA simulator"`` under the simulator), or None.

    Cached for the process: probing the driver costs about a second."""
    try:
        cuda = _import_numba_cuda()
    except Exception:  # noqa: BLE001 - not installed, or installed and broken (a numba it does not fit): no card
        return None
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        return SIMULATOR
    try:
        if not cuda.is_available():
            return None
        name = cuda.get_current_device().name
    except Exception:  # a driver that fails to initialise is no card (numba raises several types)
        return None
    return name.decode() if isinstance(name, bytes) else str(name)


@functools.cache
def driver_present() -> bool:
    """Whether the machine has NVIDIA's driver library (libcuda), looked up without importing numba-cuda.

    ``auto`` asks this first: importing numba-cuda costs a worker process 35-40 MB of resident memory (measured),
    which machines without a card should not pay for every tile."""
    import ctypes
    import ctypes.util

    if ctypes.util.find_library("cuda"):
        return True
    for name in ("libcuda.so.1", "libcuda.so", "nvcuda.dll"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


#: The interpreter's switch interval (s) while numba's CUDA simulator is on (see :func:`cuda_module`)
SIMULATOR_SWITCH_INTERVAL = 1e-4


def cuda_module() -> ModuleType:
    """:mod:`tiled_gridpull.kernels.cuda`, imported once numba-cuda is importable; one-line error without it."""
    try:
        _import_numba_cuda()
    except ImportError as exc:
        raise MissingDependencyError(f"device cuda needs numba-cuda (pip install 'tiled-gridpull[cuda]'): "
                                     f"{exc}") from None
    from .kernels import cuda as kernels

    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1" and sys.getswitchinterval() > SIMULATOR_SWITCH_INTERVAL:
        # The simulator runs each CUDA thread as a Python thread while the launching thread polls them in a busy
        # loop that keeps the GIL for a whole switch interval (5 ms by default): a 6-iteration solve took 273 s,
        # 28 s at 0.1 ms. Here, not in the tests' conftest alone, so that a CLI run in a subprocess gets it too.
        sys.setswitchinterval(SIMULATOR_SWITCH_INTERVAL)
    return kernels


def resolve(setting: str) -> str:
    """``"cpu"`` or ``"cuda"`` for a ``device`` setting; ``cuda`` without a card is a :class:`ConfigError`."""
    if setting not in DEVICES:
        raise ConfigError(f"device must be one of {', '.join(DEVICES)}, got {setting!r}")
    if setting == "cpu":
        return "cpu"
    if setting == "auto" and (os.environ.get("NUMBA_ENABLE_CUDASIM") == "1" or not driver_present()):
        # the simulator is for tests that ask for it by name; no driver, no card: the CPU, without importing
        # numba-cuda at all
        return "cpu"
    card = cuda_card()
    if card is None:
        if setting == "cuda":
            try:
                _import_numba_cuda()
            except ImportError:
                raise ConfigError("device cuda: numba-cuda is not installed (pip install "
                                  "'tiled-gridpull[cuda]'), use --device cpu or auto") from None
            except Exception as exc:  # noqa: BLE001 - installed but fails to import
                text = " ".join(f"{type(exc).__name__}: {exc}".split())[:200]
                raise ConfigError(f"device cuda: numba-cuda fails to import ({text}); use --device cpu or "
                                  f"auto") from None
            raise ConfigError("device cuda: numba-cuda sees no CUDA GPU on this machine (no card or no driver); "
                              "use --device cpu or auto")
        return "cpu"
    return "cuda"


def card_memory() -> tuple[float, float]:
    """``(free, total)`` bytes of this process's card (numba-cuda's current context; ``inf`` under the simulator,
    which has no limit). Call only where :func:`resolve` gave ``cuda``.

    Raises
    ------
    GridPullError
        The card's driver fails to answer (one line).
    """
    from .errors import GridPullError

    try:
        free, total = _import_numba_cuda().current_context().get_memory_info()
    except Exception as exc:  # noqa: BLE001 - numba-cuda raises several types for a driver that fails
        raise GridPullError(f"the card's free memory could not be read: {type(exc).__name__}: {exc}"[:300]) from None
    return float(free), float(total)


def describe(device: str) -> dict:
    """What sidecars record: the device, and for ``cuda`` the card and numba-cuda's version."""
    if device != "cuda":
        import numba

        return {"device": "cpu", "threads": int(numba.get_num_threads()), "cpu_count": os.cpu_count()}
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("numba-cuda")
    except PackageNotFoundError:  # pragma: no cover - numba's bundled cuda target
        v = "bundled"
    return {"device": "cuda", "card": cuda_card(), "numba_cuda": v}
