"""Soft imports for heavy optional dependencies (pyvista, manifold3d, open3d, pye57, pyproj, copclib, pygltflib,
fast_simplification).

``import tiled_gridpull`` never imports them; the first use raises a one-line
:class:`~tiled_gridpull.errors.MissingDependencyError` telling the user what to install.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from .errors import MissingDependencyError

_HINTS = {
    "pyvista": "pip install 'tiled-gridpull[viz]'",
    "manifold3d": "pip install 'tiled-gridpull[manifold]'",
    "open3d": "pip install 'tiled-gridpull[bench]'",
    "matplotlib": "pip install 'tiled-gridpull[viz]'",
    "PIL.Image": "pip install pillow",
    "pye57": "pip install 'tiled-gridpull[e57]'",
    "pyproj": "pip install 'tiled-gridpull[geo]'",
    "copclib": "pip install 'tiled-gridpull[copc]'",
    "pygltflib": "pip install 'tiled-gridpull[tiles3d]'",
    "fast_simplification": "pip install 'tiled-gridpull[tiles3d]'",
}


def require(module: str, feature: str) -> ModuleType:
    """Import ``module`` or raise a clear error naming the ``feature`` that needs it."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - exercised only without the package
        hint = _HINTS.get(module, f"pip install {module}")
        raise MissingDependencyError(f"{feature} needs the optional package '{module}' ({hint}): {exc}") from None
