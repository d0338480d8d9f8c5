"""Tables for marching cubes with face disambiguation, generated from the cube's geometry.

Rather than transcribe the classic 256-case table (whose ambiguous faces can leave cracks), the iso-curve is
built face by face at run time: every face of a cell contributes 0, 1 or 2 oriented segments between the
edges it crosses, chosen from the 4 signs of the face (and, for the two ambiguous face configurations, from
the asymptotic decider, which depends only on the face's own 4 values). Two cells sharing a face therefore
draw the very same segments, so the surface is crack-free and manifold; the segments of one cell chain into
closed loops that are triangulated as fans.

Conventions
-----------
corner ``c = 4 dx + 2 dy + dz``; edge ``e = 4 a + 2 ob + oc`` along axis ``a`` with offsets ``(ob, oc)`` on the
other two axes in increasing order; face ``f = 2 a + side``. Inside means value < iso. Segments run so that
the inside is on their right seen from outside the cube, which makes fan triangles face the outside
(towards larger values).
"""

from __future__ import annotations

import numpy as np

CORNER_POS = np.array([[c >> 2, (c >> 1) & 1, c & 1] for c in range(8)], dtype=np.int64)


def _other_axes(a: int) -> tuple[int, int]:
    return tuple(x for x in range(3) if x != a)  # type: ignore[return-value]


def _edge_corners() -> np.ndarray:
    out = np.zeros((12, 2), np.int64)
    for a in range(3):
        b, c = _other_axes(a)
        for ob in range(2):
            for oc in range(2):
                e = 4 * a + 2 * ob + oc
                lo = np.zeros(3, np.int64)
                lo[b], lo[c] = ob, oc
                hi = lo.copy()
                hi[a] = 1
                out[e] = [4 * lo[0] + 2 * lo[1] + lo[2], 4 * hi[0] + 2 * hi[1] + hi[2]]
    return out


EDGE_CORNERS = _edge_corners()


def _edge_between(c0: int, c1: int) -> int:
    for e in range(12):
        if set(EDGE_CORNERS[e]) == {c0, c1}:
            return e
    raise ValueError("corners are not adjacent")


def _face_corners() -> np.ndarray:
    """(6, 4) corners of each face in the cycle (0,0), (1,0), (1,1), (0,1) of its two other axes."""
    out = np.zeros((6, 4), np.int64)
    for a in range(3):
        b, c = _other_axes(a)
        for side in range(2):
            for i, (ob, oc) in enumerate([(0, 0), (1, 0), (1, 1), (0, 1)]):
                p = np.zeros(3, np.int64)
                p[a], p[b], p[c] = side, ob, oc
                out[2 * a + side, i] = 4 * p[0] + 2 * p[1] + p[2]
    return out


FACE_CORNERS = _face_corners()


def _orient(face: int, e0: int, e1: int, inside_corner: int | None, outside_corner: int | None) -> tuple[int, int]:
    """Order (e0, e1) so the inside lies on the right of the segment seen from outside the cube."""
    a, side = divmod(face, 2)
    normal = np.zeros(3)
    normal[a] = 1.0 if side else -1.0
    P = CORNER_POS[EDGE_CORNERS[e0]].mean(axis=0)
    Q = CORNER_POS[EDGE_CORNERS[e1]].mean(axis=0)
    if inside_corner is not None:
        s = np.dot(np.cross(Q - P, CORNER_POS[inside_corner] - P), normal)
        return (e0, e1) if s < 0 else (e1, e0)
    s = np.dot(np.cross(Q - P, CORNER_POS[outside_corner] - P), normal)
    return (e0, e1) if s > 0 else (e1, e0)


def _face_segments() -> tuple[np.ndarray, np.ndarray]:
    """Segments per (face, 4-bit face config, variant).

    Returns
    -------
    seg : (6, 16, 2, 2, 2) int64
        ``seg[f, cfg, variant, k] = (edge_from, edge_to)``; -1 where absent. ``cfg`` bit i is corner i of the
        face cycle being inside. Variant 0 separates the inside corners, 1 joins them (ambiguous faces only).
    nseg : (6, 16) int64
    """
    seg = np.full((6, 16, 2, 2, 2), -1, np.int64)
    nseg = np.zeros((6, 16), np.int64)
    for f in range(6):
        cyc = FACE_CORNERS[f]
        edges = [_edge_between(int(cyc[i]), int(cyc[(i + 1) % 4])) for i in range(4)]
        for cfg in range(16):
            inside = [(cfg >> i) & 1 for i in range(4)]
            crossing = [i for i in range(4) if inside[i] != inside[(i + 1) % 4]]
            if not crossing:
                continue
            if len(crossing) == 2:
                inside_corner = next((int(cyc[i]) for i in range(4) if inside[i]), None)
                s = _orient(f, edges[crossing[0]], edges[crossing[1]], inside_corner,
                            None if inside_corner is not None else int(cyc[0]))
                for variant in range(2):
                    seg[f, cfg, variant, 0] = s
                nseg[f, cfg] = 1
                continue
            # ambiguous: corners 0,2 share a state, 1,3 the other
            nseg[f, cfg] = 2
            for variant in range(2):
                cut_inside = variant == 0  # separate inside corners: cut each inside corner off
                k = 0
                for i in range(4):
                    if bool(inside[i]) != cut_inside:
                        continue
                    e_prev, e_next = edges[(i - 1) % 4], edges[i]
                    if inside[i]:
                        s = _orient(f, e_prev, e_next, int(cyc[i]), None)
                    else:
                        s = _orient(f, e_prev, e_next, None, int(cyc[i]))
                    seg[f, cfg, variant, k] = s
                    k += 1
    return seg, nseg


FACE_SEGMENTS, FACE_NSEG = _face_segments()
