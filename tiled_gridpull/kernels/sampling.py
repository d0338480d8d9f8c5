"""Query sampling with a counter-based random generator: parallel, and identical for any thread count.

Every random number is a hash (splitmix64) of ``(seed, iteration, query index, stream)``, so query ``i`` of
iteration ``t`` is the same whichever thread draws it. Gaussian offsets are read from a table of 2^16 normal
quantiles at hashed positions (three 16-bit fields of one hash), which costs no transcendental function. Centres
are *stratified* over the input points, which are stored in Morton order: query ``i`` takes a random point of
the ``i``-th of ``n`` equal slices, so each point is drawn with the same probability as with i.i.d. sampling,
the queries cover the surface evenly, and they come out spatially sorted (cache-friendly gathers and scatters
downstream).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_INV24 = 1.0 / 16777216.0
_TABLE_BITS = 16


def _normal_table() -> np.ndarray:
    """2^16 standard normal quantiles (midpoints): a hash picks entries, so noise costs no transcendental."""
    from statistics import NormalDist

    n = 1 << _TABLE_BITS
    nd = NormalDist()
    return np.array([nd.inv_cdf((i + 0.5) / n) for i in range(n)], dtype=np.float32)


NORMALS = _normal_table()


@njit(cache=True, inline="always")
def mix64(z):
    """splitmix64 finalizer (a bijective 64-bit hash)."""
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


@njit(cache=True, inline="always")
def uniforms(h):
    """Two uniforms in (0, 1) from the two 24-bit halves of a 64-bit hash."""
    a = (np.float64(h >> np.uint64(40)) + 0.5) * _INV24
    b = (np.float64((h >> np.uint64(8)) & np.uint64(0xFFFFFF)) + 0.5) * _INV24
    return a, b


@njit(cache=True, parallel=True)
def draw_queries(points, seed, iteration, sigma, centres, q):
    """Draw ``len(q)`` queries around stratified random input points.

    Parameters
    ----------
    points : (N, 3) float32
        Input points (Morton-sorted for locality).
    seed, iteration : int
    sigma : float
        Standard deviation of the Gaussian offset (same units as ``points``).
    centres : (Nq,) int64, out
    q : (Nq, 3) float32, out
    """
    n = points.shape[0]
    nq = q.shape[0]
    step = n / nq
    key = iteration_key(seed, iteration)
    for i in prange(nq):
        c, x, y, z = draw_one(points, key, i, step, sigma, NORMALS)
        centres[i] = c
        q[i, 0] = x
        q[i, 1] = y
        q[i, 2] = z


@njit(cache=True, inline="always")
def iteration_key(seed, iteration):
    """The hash every query of one iteration starts from."""
    return mix64(np.uint64(seed) * _GOLDEN + np.uint64(iteration))


@njit(cache=True, inline="always")
def draw_one(points, key, i, step, sigma, table):
    """Query ``i`` of an iteration (``key`` from :func:`iteration_key`): its centre row and position.

    ``step`` is ``len(points) / n_queries``; ``table`` the normal quantiles (:data:`NORMALS`), an argument so the
    CUDA kernel can read them from device memory.
    """
    n = points.shape[0]
    # np.uint64(key): a CUDA kernel's Python-int argument is typed int64 below 2^63 (uint64 above), and numba hashes
    # an int64 key differently (signed shifts): the card would draw other queries than the host found nearest
    # points for. A no-op on the CPU, whose key comes from iteration_key as a uint64.
    h = mix64(np.uint64(key) ^ (np.uint64(i) * _GOLDEN))
    u0, _ = uniforms(h)
    c = int((i + u0) * step)
    if c >= n:
        c = n - 1
    h1 = mix64(h + np.uint64(1))
    mask = np.uint64((1 << _TABLE_BITS) - 1)
    n0 = table[h1 & mask]
    n1 = table[(h1 >> np.uint64(16)) & mask]
    n2 = table[(h1 >> np.uint64(32)) & mask]
    return c, points[c, 0] + sigma * n0, points[c, 1] + sigma * n1, points[c, 2] + sigma * n2


@njit(cache=True)
def _spread(v):
    v = v & np.uint64(0x1FFFFF)
    v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)
    return v


@njit(cache=True, parallel=True)
def morton_codes(points):
    """64-bit Morton code of each point's integer cell (coordinates must be >= 0 and < 2^21)."""
    n = points.shape[0]
    out = np.empty(n, np.uint64)
    for i in prange(n):
        x = np.uint64(max(int(points[i, 0]), 0))
        y = np.uint64(max(int(points[i, 1]), 0))
        z = np.uint64(max(int(points[i, 2]), 0))
        out[i] = _spread(x) | (_spread(y) << np.uint64(1)) | (_spread(z) << np.uint64(2))
    return out
