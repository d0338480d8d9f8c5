"""Marching cubes over the optimized cells of a brick-sparse field.

Triangles are emitted as triples of *edge keys* (the lattice edge each vertex lies on), so vertices are welded
by identity, not by position: the same edge in two cells (or two tiles) is the same vertex. Key of the edge
along ``axis`` whose low end is global vertex ``(x, y, z)`` (relative to a reference offset):
``((x << 40) | (y << 19) | z) << 2 | axis`` with 21 bits for x and y and 19 for z.

Loops of more than three vertices in a cell with an ambiguous face are triangulated around an extra vertex at
their centre (key ``-1 - id``, never shared): a fan there could draw a chord along the ambiguous face that the
neighbouring cell draws too, giving an edge with four triangles. Every other loop is a fan.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from . import CELL_OPT
from .interp import slot_of
from .mc_tables import EDGE_CORNERS, FACE_CORNERS, FACE_NSEG, FACE_SEGMENTS

_EDGE_CORNERS = np.ascontiguousarray(EDGE_CORNERS)
_FACE_CORNERS = np.ascontiguousarray(FACE_CORNERS)
_FACE_SEGMENTS = np.ascontiguousarray(FACE_SEGMENTS)
_FACE_NSEG = np.ascontiguousarray(FACE_NSEG)

KEY_BITS_X = 21
KEY_BITS_Y = 21
KEY_BITS_Z = 19


@njit(cache=True, inline="always")
def edge_key(x, y, z, axis):
    return ((np.int64(x) << 40) | (np.int64(y) << 19) | np.int64(z)) << 2 | axis


@njit(cache=True)
def _cell_loops(vals, iso, next_edge, loop_buf, loop_len, face_corners, face_segments, face_nseg):
    """Chain the face segments of one cell into loops.

    Returns the number of loops (loop ``l`` has ``loop_len[l]`` edges stored in ``loop_buf[l, :]``) and whether
    a face was ambiguous."""
    ambiguous = False
    for e in range(12):
        next_edge[e] = -1
    for f in range(6):
        cfg = 0
        for i in range(4):
            if vals[face_corners[f, i]] < iso:
                cfg |= 1 << i
        ns = face_nseg[f, cfg]
        if ns == 0:
            continue
        variant = 0
        if ns == 2:
            ambiguous = True
            v0 = vals[face_corners[f, 0]] - iso
            v1 = vals[face_corners[f, 1]] - iso
            v2 = vals[face_corners[f, 2]] - iso
            v3 = vals[face_corners[f, 3]] - iso
            den = v0 + v2 - v1 - v3
            if den != 0.0:
                saddle = (v0 * v2 - v1 * v3) / den
                # inside corners are joined through the face centre when the saddle is inside
                if saddle < 0.0:
                    variant = 1
        for k in range(ns):
            a = face_segments[f, cfg, variant, k, 0]
            b = face_segments[f, cfg, variant, k, 1]
            next_edge[a] = b
    nloops = 0
    for e in range(12):
        if next_edge[e] < 0:
            continue
        n = 0
        cur = e
        while next_edge[cur] >= 0:
            loop_buf[nloops, n] = cur
            n += 1
            nxt = next_edge[cur]
            next_edge[cur] = -1
            cur = nxt
        loop_len[nloops] = n
        nloops += 1
    return nloops, ambiguous


@njit(cache=True)
def _gather(values, table, gx, gy, gz, vals):
    for c in range(8):
        s = slot_of(table, gx + (c >> 2), gy + ((c >> 1) & 1), gz + (c & 1))
        vals[c] = values[s]


@njit(cache=True, parallel=True)
def count_triangles(values, flags, table, brick_coords, lo, hi, iso):
    """Triangles and centre vertices each brick will emit (cells with CELL_OPT inside the cell box [lo, hi)).

    Returns
    -------
    (nb, 2) int64: triangles, centre vertices.
    """
    nb = brick_coords.shape[0]
    counts = np.zeros((nb, 2), np.int64)
    for b in prange(nb):
        vals = np.empty(8, np.float32)
        next_edge = np.empty(12, np.int64)
        loop_buf = np.empty((4, 12), np.int64)
        loop_len = np.empty(4, np.int64)
        n = 0
        nc = 0
        for x in range(8):
            for y in range(8):
                for z in range(8):
                    sl = b * 512 + (x << 6) + (y << 3) + z
                    if (flags[sl] & CELL_OPT) == 0:
                        continue
                    gx = brick_coords[b, 0] * 8 + x
                    gy = brick_coords[b, 1] * 8 + y
                    gz = brick_coords[b, 2] * 8 + z
                    if gx < lo[0] or gy < lo[1] or gz < lo[2] or gx >= hi[0] or gy >= hi[1] or gz >= hi[2]:
                        continue
                    _gather(values, table, gx, gy, gz, vals)
                    ninside = 0
                    for c in range(8):
                        if vals[c] < iso:
                            ninside += 1
                    if ninside == 0 or ninside == 8:
                        continue
                    nl, amb = _cell_loops(vals, iso, next_edge, loop_buf, loop_len, _FACE_CORNERS,
                                          _FACE_SEGMENTS, _FACE_NSEG)
                    for l in range(nl):
                        if amb and loop_len[l] > 3:
                            n += loop_len[l]
                            nc += 1
                        else:
                            n += loop_len[l] - 2
        counts[b, 0] = n
        counts[b, 1] = nc
    return counts


@njit(cache=True, parallel=True)
def emit_triangles(values, flags, table, brick_coords, lo, hi, iso, offsets, key_offset, tris, centres):
    """Write triangles as edge keys into ``tris[offsets[b, 0]:]`` (same traversal as counting).

    Centre vertices get keys ``-1 - i`` with ``i`` counted from ``offsets[b, 1]``; their positions (block
    index coordinates) go to ``centres[i]``."""
    nb = brick_coords.shape[0]
    for b in prange(nb):
        vals = np.empty(8, np.float32)
        next_edge = np.empty(12, np.int64)
        loop_buf = np.empty((4, 12), np.int64)
        loop_len = np.empty(4, np.int64)
        keys = np.empty(12, np.int64)
        pts = np.empty((12, 3), np.float64)
        w = offsets[b, 0]
        wc = offsets[b, 1]
        for x in range(8):
            for y in range(8):
                for z in range(8):
                    sl = b * 512 + (x << 6) + (y << 3) + z
                    if (flags[sl] & CELL_OPT) == 0:
                        continue
                    gx = brick_coords[b, 0] * 8 + x
                    gy = brick_coords[b, 1] * 8 + y
                    gz = brick_coords[b, 2] * 8 + z
                    if gx < lo[0] or gy < lo[1] or gz < lo[2] or gx >= hi[0] or gy >= hi[1] or gz >= hi[2]:
                        continue
                    _gather(values, table, gx, gy, gz, vals)
                    ninside = 0
                    for c in range(8):
                        if vals[c] < iso:
                            ninside += 1
                    if ninside == 0 or ninside == 8:
                        continue
                    nl, amb = _cell_loops(vals, iso, next_edge, loop_buf, loop_len, _FACE_CORNERS,
                                          _FACE_SEGMENTS, _FACE_NSEG)
                    for e in range(12):
                        c0 = _EDGE_CORNERS[e, 0]
                        c1 = _EDGE_CORNERS[e, 1]
                        axis = e >> 2
                        keys[e] = edge_key(gx + key_offset[0] + (c0 >> 2), gy + key_offset[1] + ((c0 >> 1) & 1),
                                           gz + key_offset[2] + (c0 & 1), axis)
                        if amb:
                            a = np.float64(vals[c0]) - iso
                            d = np.float64(vals[c1]) - iso
                            t = a / (a - d) if a != d else 0.5
                            pts[e, 0] = gx + (c0 >> 2)
                            pts[e, 1] = gy + ((c0 >> 1) & 1)
                            pts[e, 2] = gz + (c0 & 1)
                            pts[e, axis] += t
                    for l in range(nl):
                        n = loop_len[l]
                        if amb and n > 3:
                            ck = -1 - wc
                            cx = 0.0
                            cy = 0.0
                            cz = 0.0
                            for t in range(n):
                                cx += pts[loop_buf[l, t], 0]
                                cy += pts[loop_buf[l, t], 1]
                                cz += pts[loop_buf[l, t], 2]
                            centres[wc, 0] = cx / n
                            centres[wc, 1] = cy / n
                            centres[wc, 2] = cz / n
                            wc += 1
                            for t in range(n):
                                tris[w, 0] = ck
                                tris[w, 1] = keys[loop_buf[l, t]]
                                tris[w, 2] = keys[loop_buf[l, (t + 1) % n]]
                                w += 1
                        else:
                            for t in range(1, n - 1):
                                tris[w, 0] = keys[loop_buf[l, 0]]
                                tris[w, 1] = keys[loop_buf[l, t]]
                                tris[w, 2] = keys[loop_buf[l, t + 1]]
                                w += 1


@njit(cache=True, parallel=True)
def edge_points(values, table, keys, key_offset, iso, t_clamp):
    """Crossing point (index coordinates of this block, float64) of each edge key."""
    n = keys.shape[0]
    out = np.empty((n, 3), np.float64)
    for i in prange(n):
        k = keys[i]
        axis = k & 3
        r = k >> 2
        x = (r >> 40) - key_offset[0]
        y = ((r >> 19) & ((1 << 21) - 1)) - key_offset[1]
        z = (r & ((1 << 19) - 1)) - key_offset[2]
        d0 = values[slot_of(table, x, y, z)]
        if axis == 0:
            d1 = values[slot_of(table, x + 1, y, z)]
        elif axis == 1:
            d1 = values[slot_of(table, x, y + 1, z)]
        else:
            d1 = values[slot_of(table, x, y, z + 1)]
        a = np.float64(d0) - iso
        b = np.float64(d1) - iso
        t = a / (a - b) if a != b else 0.5
        t = min(max(t, t_clamp), 1.0 - t_clamp)
        out[i, 0] = x
        out[i, 1] = y
        out[i, 2] = z
        out[i, axis] += t
    return out
