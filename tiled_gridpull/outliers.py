"""Points far from the rest of a cloud: a stray ``(0, 0, 0)`` in a UTM survey, a GPS glitch, a return from a bird.

A handful of such points stretches the bounds of a cloud: the tiled lattice then spans a continent (and is
refused, or plans empty tiles), and a one-shape lattice fitted to the bounds leaves the real object a few cells
wide. The rule here is coarse on purpose and cheap in a streaming pass: the *body* of the cloud is the box
holding all but the outermost 0.1 % of a sample on each axis, widened on every side by half its size (and at
least ``pad``); a point outside it is *far*. It finds points that are far from everything, not noise on a
surface (that is the solve's business), and it never judges a point by its neighbours, so the same points are
far whatever the tiling.
"""

from __future__ import annotations

import numpy as np

__all__ = ["body_box", "far_mask", "far_points", "describe", "stray_points", "TAIL", "SAMPLE_STRIDE", "STRETCH_LIMIT"]

#: Share of a sample's points left out of the body's box at each end of each axis.
TAIL = 0.001
#: The streaming scan keeps every SAMPLE_STRIDE-th point of each chunk for :func:`body_box`.
SAMPLE_STRIDE = 16
#: One lattice fitted to a whole cloud (one-shape mode) is refused when its far points stretch the cloud's
#: longest side more than this many times the rest's: the rest would get under a quarter of the lattice's cells
#: across, and a stray (0, 0, 0) in a survey leaves it none (an empty mesh).
STRETCH_LIMIT = 4.0


def body_box(sample: np.ndarray, pad: float = 0.0) -> np.ndarray:
    """Box of a cloud's body, from a sample of its points.

    Parameters
    ----------
    sample : (M, 3) float64
        Points of the cloud (all of them, or an even sample), world units.
    pad : float
        Least widening on every side (world units; e.g. one tile, so a sparse edge of the scan stays in).

    Returns
    -------
    (2, 3) float64
        Low and high corners; the quantiles ``TAIL`` and ``1 - TAIL`` of each axis, each side moved out by
        ``max(pad, half the box's size on that axis)``.
    """
    sample = np.asarray(sample, dtype=np.float64)
    lo = np.quantile(sample, TAIL, axis=0)
    hi = np.quantile(sample, 1.0 - TAIL, axis=0)
    widen = np.maximum(0.5 * (hi - lo), float(pad))
    return np.stack([lo - widen, hi + widen])


def far_mask(xyz: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(N,) bool: the points of ``xyz`` (N, 3) outside ``box`` (2, 3)."""
    xyz = np.asarray(xyz)
    return np.any((xyz < box[0]) | (xyz > box[1]), axis=1)


def describe(n_far: int, total: int, box: np.ndarray, example: np.ndarray) -> str:
    """One phrase: how many of ``total`` points are far, where the body is, and one far point ``example`` (3,)."""
    point = ", ".join(f"{v:.6g}" for v in np.asarray(example))
    body = " x ".join(f"{a:.6g}..{b:.6g}" for a, b in zip(box[0], box[1]))
    return f"{n_far:,} of {total:,} points lie far from the rest (outside {body}; e.g. ({point}))"


def far_points(xyz: np.ndarray, sample_size: int = 100_000) -> tuple[np.ndarray, np.ndarray]:
    """``far`` (N,) bool, the points of ``xyz`` (N, 3) outside the body's ``box`` (2, 3), taken from about
    ``sample_size`` evenly spaced points (:func:`body_box`, no padding)."""
    box = body_box(xyz[::max(1, len(xyz) // sample_size)])
    return far_mask(xyz, box), box


def stray_points(xyz: np.ndarray, sample_size: int = 100_000) -> tuple[np.ndarray, np.ndarray] | None:
    """The far points of a cloud, when they stretch its extent more than :data:`STRETCH_LIMIT` times.

    Parameters
    ----------
    xyz : (N, 3) float64
        The cloud (world units).
    sample_size : int
        :func:`body_box` is taken from about this many evenly spaced points.

    Returns
    -------
    (far, box) or None
        ``far`` (N,) bool and the body's ``box`` (2, 3) where the cloud's longest side exceeds
        ``STRETCH_LIMIT`` times the longest side of the points that are not far; None otherwise (no far point,
        every point far, or far points close enough not to matter).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if len(xyz) == 0:
        return None
    far, box = far_points(xyz, sample_size)
    if not far.any() or far.all():
        return None
    rest = xyz[~far]
    whole = float(np.max(xyz.max(axis=0) - xyz.min(axis=0)))
    body = float(np.max(rest.max(axis=0) - rest.min(axis=0)))
    if whole <= STRETCH_LIMIT * body:
        return None
    return far, box
