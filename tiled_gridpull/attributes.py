"""Point attributes carried onto mesh vertices: colour, intensity, classification and LAS extra dimensions.

Readers put per-point values in :attr:`~tiled_gridpull.cloud.PointCloud.attributes`; :func:`select_attributes`
picks the ones a run carries (``--attributes none|rgb|all``) and :func:`interpolate_attributes` gives every mesh
vertex a value from its ``k`` nearest input points: inverse-distance weights for the continuous values (colour,
intensity, extra dimensions), a weighted majority for the categorical ones (classification). Values keep the
input's type and bit depth (integers are rounded and clipped to their type's range, never rescaled).
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from .errors import ConfigError
from .mesh import COLOR_CHANNELS

__all__ = ["ATTRIBUTE_MODES", "CATEGORICAL", "NOT_CARRIED", "ATTRIBUTE_NEIGHBORS", "select_attributes",
           "interpolate_attributes", "attribute_layout", "mean_attributes", "check_mode"]

#: What ``--attributes`` accepts: none, the colour channels only, or every attribute the input has.
ATTRIBUTE_MODES = ("none", "rgb", "all")
#: Attributes that name a category: a vertex takes the weighted majority of its neighbours, never a mean.
CATEGORICAL = ("classification",)
#: Per-point arrays readers keep for the pipeline's own use, never carried onto the mesh: a KITTI sequence's
#: frame number, an E57 file's scan number, the GPS time a trajectory is looked up with, a text file's unnamed
#: extra columns.
NOT_CARRIED = ("frame", "scan", "gps_time", "extra_columns")
#: Neighbours a vertex's value is interpolated from. Autzen with 10 % held out (benchmarks/attributes.py; the
#: same vertices re-interpolated): median |colour - nearest held-out point's| 3 of 255 per channel with 4, 8 or
#: 16 neighbours (red 4 with 1); mean red 2.67 %, 2.60 %, 2.56 % of full scale with 4, 8, 16.
ATTRIBUTE_NEIGHBORS = 8


def check_mode(mode: str) -> str:
    """``mode`` if it is one of :data:`ATTRIBUTE_MODES`, else a one-line :class:`ConfigError`."""
    if mode not in ATTRIBUTE_MODES:
        raise ConfigError(f"attributes must be one of {', '.join(ATTRIBUTE_MODES)}, got {mode!r}")
    return mode


def select_attributes(attributes: dict, mode: str = "all") -> dict:
    """The per-point attributes a run with ``--attributes mode`` carries onto the mesh.

    Parameters
    ----------
    attributes : dict of str to (N,) arrays
        A cloud's attributes (:attr:`~tiled_gridpull.cloud.PointCloud.attributes`).
    mode : {"none", "rgb", "all"}
        ``none``: nothing; ``rgb``: ``red``, ``green`` and ``blue`` (nothing when one is missing); ``all``: every
        one-dimensional numeric attribute but :data:`NOT_CARRIED`.

    Returns
    -------
    dict of str to (N,) arrays
        The same arrays (not copied), in the input's order.
    """
    check_mode(mode)
    if mode == "none":
        return {}
    if mode == "rgb":
        if all(c in attributes for c in COLOR_CHANNELS):
            return {c: attributes[c] for c in COLOR_CHANNELS}
        return {}
    out = {}
    for name, values in attributes.items():
        if name in NOT_CARRIED or not isinstance(values, np.ndarray) or values.ndim != 1:
            continue
        if values.dtype.kind not in "uif" and values.dtype != np.bool_:
            continue
        out[name] = values
    return out


def attribute_layout(attributes: dict) -> list[tuple[str, str]]:
    """``[(name, numpy type string), ...]`` of ``attributes``: what a spill file stores of each point, and what
    a sidecar records as carried."""
    return [(name, np.asarray(v).dtype.str) for name, v in attributes.items()]


def interpolate_attributes(vertices: np.ndarray, points: np.ndarray, attributes: dict,
                           k: int = ATTRIBUTE_NEIGHBORS) -> dict:
    """Every attribute at every vertex, from the vertex's ``k`` nearest points.

    Continuous attributes take the inverse-square-distance weighted mean of the neighbours (a vertex on a point
    takes that point's value); :data:`CATEGORICAL` ones the class with the largest summed weight (ties: the
    class of the nearest point among them). Integer results are rounded and clipped to their type's range.

    Parameters
    ----------
    vertices : (V, 3) float
        World coordinates.
    points : (N, 3) float
        The points the attributes belong to, same units and frame.
    attributes : dict of str to (N,) arrays
    k : int
        Neighbours per vertex (fewer when the cloud has fewer points).

    Returns
    -------
    dict of str to (V,) arrays
        Same names and types as ``attributes``.
    """
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not attributes:
        return {}
    if len(points) == 0:
        raise ValueError("interpolate_attributes: no points to interpolate from")
    for name, values in attributes.items():
        if len(values) != len(points):
            raise ValueError(f"interpolate_attributes: attribute {name!r} has {len(values)} rows for "
                             f"{len(points)} points")
    if len(vertices) == 0:
        return {name: np.zeros(0, np.asarray(v).dtype) for name, v in attributes.items()}
    k = int(max(1, min(k, len(points))))
    # local origin: georeferenced coordinates (y ~ 5e6) would cost the distances their digits
    ref = points.mean(axis=0)
    tree = KDTree(np.ascontiguousarray(points - ref))
    dist, idx = tree.query(np.ascontiguousarray(vertices - ref), k=k)
    dist = np.asarray(dist, np.float64).reshape(len(vertices), k)
    idx = np.asarray(idx, np.int64).reshape(len(vertices), k)
    weights = _idw_weights(dist)
    out = {}
    for name, values in attributes.items():
        values = np.asarray(values)
        if name in CATEGORICAL:
            out[name] = _weighted_majority(values[idx], weights)
        else:
            out[name] = _cast(np.einsum("vk,vk->v", weights, values[idx].astype(np.float64)), values.dtype)
    return out


def mean_attributes(attributes: dict, rows: np.ndarray) -> dict:
    """One new vertex's attributes from the vertices ``rows`` (e.g. the centre of a hole closed with a fan):
    their mean, or their most common class for :data:`CATEGORICAL` attributes; each array gets one value,
    returned as a (1,) array of its type."""
    out = {}
    for name, values in attributes.items():
        v = np.asarray(values)[rows]
        if name in CATEGORICAL:
            classes, counts = np.unique(v, return_counts=True)
            out[name] = classes[[counts.argmax()]] if len(v) else np.zeros(1, values.dtype)
        else:
            out[name] = _cast(np.array([v.astype(np.float64).mean() if len(v) else 0.0]), np.asarray(values).dtype)
    return out


def _idw_weights(dist: np.ndarray) -> np.ndarray:
    """(V, k) inverse-square-distance weights summing to 1 per row; a row with a zero distance puts all its
    weight on those neighbours."""
    exact = dist <= 0
    with np.errstate(divide="ignore"):
        w = 1.0 / (dist * dist)
    hit = exact.any(axis=1)
    w[hit] = exact[hit].astype(np.float64)
    w = np.where(np.isfinite(w), w, 0.0)
    total = w.sum(axis=1, keepdims=True)
    total[total == 0] = 1.0
    return w / total


def _weighted_majority(classes: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(V,) the class of each row of ``classes`` (V, k) with the largest summed weight; ties go to the first
    (nearest) column among them."""
    same = classes[:, :, None] == classes[:, None, :]
    score = np.einsum("vjk,vk->vj", same, weights)
    best = np.argmax(score >= score.max(axis=1, keepdims=True) - 1e-12, axis=1)
    return classes[np.arange(len(classes)), best]


def _cast(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """``values`` (float64) in ``dtype``: rounded and clipped for integer types."""
    dtype = np.dtype(dtype)
    if dtype.kind in "ui":
        info = np.iinfo(dtype)
        return np.clip(np.rint(values), info.min, info.max).astype(dtype)
    if dtype == np.bool_:
        return values >= 0.5
    return values.astype(dtype)
