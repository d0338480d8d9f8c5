"""One optimizer step over the band: TV gradient + query gradient + Adam, fused in a single pass.

The pass reads the current field ``d_in`` and writes the next one to ``d_out`` (double buffering), so every
vertex sees its neighbours' values from the same iteration whatever order bricks are processed in; the result
does not depend on the thread count.

TV is defined on the edges of the lattice whose two ends are parameters, so the outermost band layer is free
(Neumann), not pinned to its initial values:

* squared (authors' code): ``L = 1/P * sum_v sum_{u in N6(v)} (d_u - d_v)^2``;
* sqrt (paper): ``L = 1/P * sum_v sqrt(eps + sum_{u in N6(v)} (d_u - d_v)^2)``;

with ``P`` the number of parameters and ``N6(v)`` the in-band face neighbours of ``v``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from . import PARAM

TV_SQUARED = 0
TV_SQRT = 1
_TV_EPS = 1e-8


@njit(cache=True, inline="always")
def neighbor_slot(b, x, y, z, axis, side, neighbors):
    """Slot of the face neighbour of local vertex (x, y, z) of brick b, or -1."""
    if axis == 0:
        x2 = x + side
        if x2 < 0 or x2 > 7:
            nb = neighbors[b, 0 if side < 0 else 1]
            if nb < 0:
                return -1
            return nb * 512 + ((x2 & 7) << 6) + (y << 3) + z
        return b * 512 + (x2 << 6) + (y << 3) + z
    elif axis == 1:
        y2 = y + side
        if y2 < 0 or y2 > 7:
            nb = neighbors[b, 2 if side < 0 else 3]
            if nb < 0:
                return -1
            return nb * 512 + (x << 6) + ((y2 & 7) << 3) + z
        return b * 512 + (x << 6) + (y2 << 3) + z
    else:
        z2 = z + side
        if z2 < 0 or z2 > 7:
            nb = neighbors[b, 4 if side < 0 else 5]
            if nb < 0:
                return -1
            return nb * 512 + (x << 6) + (y << 3) + (z2 & 7)
        return b * 512 + (x << 6) + (y << 3) + z2


@njit(cache=True, parallel=True, fastmath=True)
def tv_inverse_norms(d, flags, neighbors, inv):
    """For the sqrt form: ``inv[v] = 1 / sqrt(eps + sum_u (d_u - d_v)^2)`` at every parameter (else 0).

    Returns the TV loss sum over parameters (for monitoring)."""
    nb = neighbors.shape[0]
    total = 0.0
    for b in prange(nb):
        part = 0.0
        for x in range(8):
            for y in range(8):
                for z in range(8):
                    sl = b * 512 + (x << 6) + (y << 3) + z
                    if (flags[sl] & PARAM) == 0:
                        inv[sl] = 0.0
                        continue
                    dv = d[sl]
                    acc = _TV_EPS
                    for axis in range(3):
                        for side in (-1, 1):
                            u = neighbor_slot(b, x, y, z, axis, side, neighbors)
                            if u >= 0 and (flags[u] & PARAM) != 0:
                                e = d[u] - dv
                                acc += e * e
                    r = math.sqrt(acc)
                    inv[sl] = 1.0 / r
                    part += r
        total += part
    return total


@njit(cache=True, parallel=True, fastmath=True)
def tv_adam_step(d_in, d_out, m, v, qgrad, flags, neighbors, inv, form, tv_scale,
                 lr_t, beta1, beta2, eps, clamp_nonneg):
    """Fused TV gradient + Adam update of every parameter.

    Parameters
    ----------
    d_in, d_out : (n_slots,) float32
        Field before / after the step (non-parameters must already be equal in both).
    m, v : (n_slots,) float32, in/out
        Adam moments.
    qgrad : (n_slots,) float32, in/out
        Query-loss gradient accumulated for this step; reset to 0 here.
    flags : (n_slots,) uint8
    neighbors : (nb, 6) int32
    inv : (n_slots,) float32
        ``1/|grad|`` per vertex for the sqrt form (see :func:`tv_inverse_norms`); unused for the squared form.
    form : int
        ``TV_SQUARED`` or ``TV_SQRT``.
    tv_scale : float
        ``alpha / P`` (sqrt form) or ``2 alpha / P`` (squared form: d/dd of (d_u-d_v)^2 counted from both ends
        gives ``4 (d_v - d_u)``, folded as 2 * 2).
    lr_t : float
        Bias-corrected learning rate ``lr * sqrt(1 - beta2^t) / (1 - beta1^t)``.
    clamp_nonneg : bool
        Project the field onto ``d >= 0`` (UDF mode).

    Returns
    -------
    float
        Squared-form TV loss sum (before the step), for monitoring.
    """
    nb = neighbors.shape[0]
    total = 0.0
    for b in prange(nb):
        part = 0.0
        for x in range(8):
            for y in range(8):
                for z in range(8):
                    sl = b * 512 + (x << 6) + (y << 3) + z
                    if (flags[sl] & PARAM) == 0:
                        continue
                    dv = d_in[sl]
                    acc = 0.0
                    for axis in range(3):
                        for side in (-1, 1):
                            u = neighbor_slot(b, x, y, z, axis, side, neighbors)
                            if u >= 0 and (flags[u] & PARAM) != 0:
                                e = dv - d_in[u]
                                if form == TV_SQRT:
                                    acc += e * (inv[sl] + inv[u])
                                else:
                                    acc += 2.0 * e
                                    part += e * e
                    g = qgrad[sl] + tv_scale * acc
                    qgrad[sl] = 0.0
                    mm = beta1 * m[sl] + (1.0 - beta1) * g
                    vv = beta2 * v[sl] + (1.0 - beta2) * g * g
                    m[sl] = mm
                    v[sl] = vv
                    nd = dv - lr_t * mm / (math.sqrt(vv) + eps)
                    if clamp_nonneg and nd < 0.0:
                        nd = 0.0
                    d_out[sl] = nd
        total += part
    return total
