"""RGB images as arrays: their size checks and PNG output, shared by every picture the package draws."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ._optional import require
from .errors import ConfigError

__all__ = ["check_size", "save_png", "png_bytes"]


def check_size(size: Sequence[int]) -> tuple[int, int]:
    """``(width, height)`` in pixels as ints, each in [16, 8192]; else :class:`ConfigError`."""
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ConfigError(f"image size must be two integers (width, height), got {size!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise ConfigError(f"image size {w} x {h}: width and height must be between 16 and 8192 pixels")
    return w, h


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an RGB(A) image as a PNG, atomically.

    Parameters
    ----------
    image : (H, W, 3) or (H, W, 4) uint8
    path : str or Path
        Target file (``.png``).

    Returns
    -------
    Path
    """
    from .io.atomic import atomic_path

    pil = require("PIL.Image", "writing PNG files")
    from PIL.PngImagePlugin import PngInfo

    from ._version import __version__
    from .io.outputs import GENERATOR_PREFIX

    # the generator marker (io.outputs.written_by_us): a rerun may replace the picture a job wrote, not a user's
    info = PngInfo()
    info.add_text("Software", f"{GENERATOR_PREFIX}{__version__}")
    path = Path(path)
    with atomic_path(path) as tmp:
        pil.fromarray(np.asarray(image, dtype=np.uint8)).save(tmp, format="PNG", pnginfo=info)
    return path


def png_bytes(image: np.ndarray) -> bytes:
    """PNG-encoded bytes of an ``(H, W, 3)`` uint8 image (e.g. for ``IPython.display.Image``)."""
    import io

    pil = require("PIL.Image", "encoding PNG images")
    buf = io.BytesIO()
    pil.fromarray(np.asarray(image, dtype=np.uint8)).save(buf, format="PNG")
    return buf.getvalue()
