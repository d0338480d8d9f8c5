"""Point normals: PCA plane fits over neighbourhoods, and their orientation (which side is outside).

The GridPull loss does not change when ``f -> -f``, so the sign of a solved field comes only from its
initialisation, and that comes from oriented normals. On a street scene cut into tiles the outside is fixed
by a rule every tile applies to the same data: normals estimated by PCA over each point's neighbours, turned
to face the sensor that saw the point (its origin is known for KITTI sequences) or, for airborne data, to
face up. A cloud with neither is oriented by propagation along its neighbour graph.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from .kernels import planes as kp

__all__ = ["plane_fits", "local_planes", "estimate_normals", "orient_normals", "orient_by_propagation",
           "orientation_decided", "orientation_score"]


def plane_fits(points: np.ndarray, k: int, chunk: int = 200_000, bandwidth: float = 0.0, reweights: int = 3,
               radius: float = np.inf):
    """Least-squares plane (PCA) of every point's ``k`` nearest neighbours, ``chunk`` points at a time.

    With ``bandwidth > 0`` the fit is robust: each neighbour is then weighted by ``exp(-d^2 / (2
    bandwidth^2))``, ``d`` its offset along the current normal from the centre point's projection onto the
    current plane (first the point itself), and the weighted plane refitted ``reweights`` times (a bilateral
    filter's range weight, iterated as a mean shift along the normal). Where two sheets lie within one
    neighbourhood (the two walls of a thin part, the faces at a sharp edge) the plain fit averages them into one
    plane between; the weighted fit settles on the sheet the centre point belongs to.

    Parameters
    ----------
    points : (N, 3) float
    k : int
        Neighbours per fit (at most N), the point itself included.
    chunk : int
        Points whose neighbourhoods are fitted at once (memory about ``chunk * k * 24`` bytes, twice that when
        robust).
    bandwidth : float
        Range scale of the robust weights, in the points' units; 0 gives the plain least-squares fit.
    reweights : int
        Weighted refits after the plain one (``bandwidth > 0`` only).
    radius : float
        Neighbours farther than this (the points' units) are left out: the neighbourhood is the ``k`` nearest
        within ``radius``, so a fit depends on nothing outside that ball (what a tile needs to fit a point the
        way its neighbour does). A point with fewer than 4 points in its ball gets itself as the centroid, so
        projecting it onto its plane leaves it in place.

    Yields
    ------
    start, stop : int
        The rows of ``points`` this chunk covers.
    centroids : (stop - start, 3) float64
        (Weighted) mean of each neighbourhood.
    normals : (stop - start, 3) float64
        Unit eigenvector of the smallest eigenvalue of each neighbourhood's (weighted) covariance (unoriented).
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    n = len(pts)
    k = int(min(k, n))
    tree = KDTree(pts)
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        if np.isfinite(radius):
            yield s, e, *_bounded_planes(tree, pts, s, e, k, float(radius), bandwidth, reweights)
            continue
        _, idx = tree.query(pts[s:e], k=k)
        idx = idx.reshape(e - s, k).astype(np.int64)
        centroids = np.empty((e - s, 3))
        normals = np.empty((e - s, 3))
        kp.neighbourhood_planes(pts, idx, centroids, normals)
        if bandwidth > 0:
            nb = pts[idx]
            anchor = pts[s:e]
            for _ in range(int(reweights)):
                offset = np.einsum("nki,ni->nk", nb - anchor[:, None], normals)
                centroids, normals = _weighted_planes(nb, np.exp(-0.5 * (offset / bandwidth) ** 2))
                # follow the point's projection, so the weights climb to its sheet's densest level (mean shift)
                anchor = pts[s:e] - np.einsum("ni,ni->n", pts[s:e] - centroids, normals)[:, None] * normals
        yield s, e, centroids, normals


#: Neighbours fetched past ``k`` so that a tie at the ``k``-th distance is broken the same way in every tile.
TIE_EXTRA = 8


def _bounded_planes(tree: KDTree, pts: np.ndarray, s: int, e: int, k: int, radius: float, bandwidth: float,
                    reweights: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`plane_fits` of rows ``s:e`` with neighbours bounded by ``radius``, computed so that two tiles holding
    the same points in frames shifted by exact offsets choose the same neighbours and fit the same plane.

    The fit works on the neighbours' offsets from the point (the same numbers in every such frame) rather than on
    their coordinates, and neighbours at equal distances are ordered by their offsets, not by the tree's visiting
    order (quantised inputs such as LAS millimetres tie often)."""
    n = len(pts)
    kq = min(k + TIE_EXTRA, n)
    dist, idx = tree.query(pts[s:e], k=kq, distance_upper_bound=radius)
    idx = idx.reshape(e - s, kq).astype(np.int64)
    found = idx < n  # pykdtree marks a missing neighbour with index n
    # a missing neighbour stands in as the point itself (the first column) with weight 0
    idx = np.where(found, idx, idx[:, :1])
    off = pts[idx] - pts[s:e, None]
    dist = np.where(found, dist.reshape(e - s, kq), np.inf)
    order = np.lexsort((off[..., 2], off[..., 1], off[..., 0], dist), axis=-1)[:, :k]
    off = np.take_along_axis(off, order[..., None], axis=1)
    inside = np.take_along_axis(found, order, axis=1).astype(np.float64)
    centroids, normals = _weighted_planes(off, inside)
    if bandwidth > 0:
        anchor = np.zeros((e - s, 3))
        for _ in range(int(reweights)):
            offset = np.einsum("nki,ni->nk", off - anchor[:, None], normals)
            weights = np.exp(-0.5 * (offset / bandwidth) ** 2) * inside
            centroids, normals = _weighted_planes(off, weights)
            # the point's projection onto the current plane (the point is the origin of the offsets)
            anchor = np.einsum("ni,ni->n", centroids, normals)[:, None] * normals
    # fewer than 4 points in the ball fit no plane: the point is its own centroid, so it stays where it is
    centroids[inside.sum(axis=1) < 4] = 0.0
    return pts[s:e] + centroids, normals


def _weighted_planes(nb: np.ndarray, weights: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Centroids (n, 3) and unit normals (n, 3) of neighbourhoods ``nb`` (n, k, 3), weights (n, k) or None."""
    nb = np.ascontiguousarray(nb, dtype=np.float64)
    # the centre point itself has a positive weight, so no row's sum vanishes
    w = (np.ones(nb.shape[:2]) if weights is None else np.ascontiguousarray(weights, dtype=np.float64))
    centroids = np.empty((len(nb), 3))
    normals = np.empty((len(nb), 3))
    kp.weighted_planes(nb, w, centroids, normals)
    return centroids, normals


def local_planes(points: np.ndarray, k: int = 16, chunk: int = 200_000) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane of every point's ``k`` nearest neighbours (:func:`plane_fits`), all at once.

    Returns
    -------
    centroids : (N, 3) float64
        Mean of each neighbourhood (a point on the plane).
    normals : (N, 3) float64
        Unoriented unit normals.
    """
    centroids = np.empty((len(points), 3), np.float64)
    normals = np.empty((len(points), 3), np.float64)
    for s, e, c, n in plane_fits(points, k, chunk):
        centroids[s:e] = c
        normals[s:e] = n
    return centroids, normals


def estimate_normals(points: np.ndarray, k: int = 16, chunk: int = 200_000) -> np.ndarray:
    """Unoriented unit normals by PCA over the ``k`` nearest neighbours (:func:`plane_fits`).

    Parameters
    ----------
    points : (N, 3) float
    k : int

    Returns
    -------
    (N, 3) float32
        Eigenvector of the smallest eigenvalue of each neighbourhood's covariance.
    """
    return local_planes(points, k, chunk)[1].astype(np.float32)


def orient_normals(normals: np.ndarray, points: np.ndarray, sensor: np.ndarray | None = None,
                   up: tuple[float, float, float] = (0.0, 0.0, 1.0), away_from: np.ndarray | None = None
                   ) -> np.ndarray:
    """Flip normals to face the sensor (``(sensor - p) . n > 0``), away from a centre, or ``up``.

    Parameters
    ----------
    normals, points : (N, 3)
    sensor : (N, 3) or (3,), optional
        Sensor origin of each point (or one for all).
    up : (3,)
        Used when neither ``sensor`` nor ``away_from`` is given (airborne data).
    away_from : (3,), optional
        A point inside a closed, roughly star-shaped object: normals point away from it.

    Returns
    -------
    (N, 3) float32
    """
    n = np.array(normals, dtype=np.float32, copy=True)
    ref = _reference(n.shape, points, sensor, up, away_from)
    flip = np.einsum("ij,ij->i", n.astype(np.float64), ref) < 0
    n[flip] *= -1
    if sensor is None and away_from is None:
        _orient_walls(n, points, up)
    return n


def _reference(shape: tuple, points: np.ndarray, sensor: np.ndarray | None, up, away_from: np.ndarray | None
               ) -> np.ndarray:
    """The direction each normal should face, (N, 3) float64 (not unit): towards its sensor, away from the
    centre, or up (:func:`orient_normals`' rules, in that order of precedence)."""
    if sensor is not None:
        ref = np.asarray(sensor, dtype=np.float64) - np.asarray(points, dtype=np.float64)
    elif away_from is not None:
        ref = np.asarray(points, dtype=np.float64) - np.asarray(away_from, dtype=np.float64)
    else:
        ref = np.asarray(up, dtype=np.float64)
    return np.broadcast_to(ref, shape)


#: Neighbours that vote on an undecided normal's side under the ``up`` rule.
WALL_VOTERS = 16


def _orient_walls(n: np.ndarray, points: np.ndarray, up: tuple[float, float, float], k: int = WALL_VOTERS,
                  chunk: int = 100_000) -> None:
    """Orient, in place, the normals the ``up`` rule cannot decide (walls: :func:`orientation_decided`'s others).

    The surface bounds the space above the decided (up-facing) points near a wall, so a wall faces the side where
    those points lie *below* it (the ground at its foot) and away from the side where they lie *above* it (the
    roof it carries). Each of a wall point's ``k`` nearest decided points ``q`` votes
    ``((q - p) . n) ((p - q) . up) / |q - p|^2``; level neighbours (the ground right at the foot) say little, so a
    second pass lets each wall point follow its wall neighbours' confident votes. Without this a wall kept the sign
    its eigen solver returned, and the field's initial sign across a street could disagree with the ground's.
    Wall points go ``chunk`` at a time (each holds a (chunk, k, 3) float64 block: 38 MB at 100,000).
    """
    pts = np.asarray(points, dtype=np.float64)
    upv = np.asarray(up, dtype=np.float64)
    upv = upv / np.linalg.norm(upv)
    nn = n.astype(np.float64)
    decided = orientation_decided(nn, pts, up=up)
    walls = np.flatnonzero(~decided)
    if len(walls) == 0 or decided.sum() == 0:
        return
    ground = pts[decided]
    kk = min(k, len(ground))
    tree = KDTree(ground)
    vote = np.empty(len(walls))
    for s in range(0, len(walls), chunk):
        w = walls[s:s + chunk]
        pw, nw = pts[w], nn[w]
        _, idx = tree.query(pw, k=kk)
        d = ground[idx.reshape(len(w), kk).astype(np.int64)] - pw[:, None]  # (W, k, 3): q - p
        # which side of the wall q lies on, from the normal's horizontal part: on a face tilted 60-80 degrees
        # (a steep roof, an embankment) ground straight below the face lies behind its plane and voted it
        # upside down (62-80 degree gable roofs came out 54-66 % right); across a vertical wall it is the normal
        horizontal = nw - np.outer(nw @ upv, upv)
        across = np.einsum("wki,wi->wk", d, horizontal)
        below = -(d @ upv)
        # a degenerate neighbourhood's normal (NaN) neither votes nor is moved
        vote[s:s + len(w)] = np.nan_to_num(
            (across * below / np.maximum(np.einsum("wki,wki->wk", d, d), 1e-300)).sum(axis=1))
    n[walls[vote < 0]] *= -1
    if len(walls) < 2:
        return
    # second pass: each wall point sums its wall neighbours' votes (each already oriented, weighted by |vote|)
    kw = min(k, len(walls))
    wtree = KDTree(pts[walls])
    wn = n[walls].astype(np.float64)
    follow = np.zeros(len(walls), bool)
    for s in range(0, len(walls), chunk):
        e = min(s + chunk, len(walls))
        _, widx = wtree.query(pts[walls[s:e]], k=kw)
        widx = widx.reshape(e - s, kw).astype(np.int64)
        agree = np.nan_to_num(np.einsum("wki,wi->wk", wn[widx], wn[s:e])) * np.abs(vote)[widx]
        follow[s:e] = agree.sum(axis=1) < 0
    n[walls[follow]] *= -1


#: Bridging pieces of the neighbour graph: query points per round, and the neighbour counts tried.
BRIDGE_QUERIES = 200_000
BRIDGE_K = (32, 256)


def orient_by_propagation(points: np.ndarray, normals: np.ndarray, k: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Consistently oriented normals for a cloud with no sensor and no inside: orientation propagated along a
    minimum spanning tree (Hoppe et al., SIGGRAPH 1992).

    The ``k``-nearest-neighbour graph is weighted by ``1 - |n_i . n_j|``, so the spanning tree crosses between
    nearly parallel planes first and reaches creases and thin parts last, where a flip is most likely to be
    wrong; each normal then takes the orientation that agrees with its parent's. Where the graph falls apart
    (a strip the scan missed cuts one surface in two), each piece is joined to its nearest other piece by the
    closest pair of points found among their ``BRIDGE_K`` nearest neighbours, round after round, with weights
    above any inside a piece so that the tree crosses a bridge only where it must: pieces oriented on their
    own would meet with opposite signs and fold the surface along the strip. Each piece left (farther apart
    than that) finally faces up (+z) when its normals are mostly vertical (terrain, a valley), else away from
    its centroid (outward on a closed or dome-like piece), else up.

    Parameters
    ----------
    points : (N, 3) float
    normals : (N, 3) float
        Unit normals, any orientation.
    k : int
        Neighbours per point in the graph.

    Returns
    -------
    normals : (N, 3) float64
        Oriented.
    pieces : (N,) int64
        Piece of the (bridged) graph each point belongs to, 0..P-1; each piece is oriented independently.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

    from .kernels.graph import propagate_flips

    pts = np.ascontiguousarray(points, dtype=np.float64)
    nrm = np.array(normals, dtype=np.float64)
    n = len(pts)
    if n < 2:
        return nrm, np.zeros(n, np.int64)
    k = int(min(k, n - 1))
    tree = KDTree(pts)
    _, idx = tree.query(pts, k=k + 1)
    rows = np.repeat(np.arange(n, dtype=np.int64), k + 1)
    cols = idx.reshape(-1).astype(np.int64)
    off = rows != cols
    rows, cols = rows[off], cols[off]
    # scipy drops explicit zeros from sparse graphs, so no weight may be 0
    weight = 1.0 - np.abs(np.einsum("ij,ij->i", nrm[rows], nrm[cols])) + 1e-6

    def pieces_of(r, c):
        return connected_components(coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n)), directed=False)

    count, labels = pieces_of(rows, cols)
    while count > 1:
        br, bc = _bridges(tree, pts, labels)
        if len(br) == 0:
            break
        rows, cols = np.r_[rows, br], np.r_[cols, bc]
        weight = np.r_[weight, 2.0 - np.abs(np.einsum("ij,ij->i", nrm[br], nrm[bc]))]
        count, labels = pieces_of(rows, cols)
    graph = coo_matrix((weight, (rows, cols)), shape=(n, n)).tocsr()
    tree_graph = minimum_spanning_tree(graph.maximum(graph.T)).tocoo()
    # one breadth-first pass over the whole forest: a virtual root (node n) holds the first node of each piece
    firsts = np.unique(labels, return_index=True)[1]
    r = np.r_[tree_graph.row, np.full(len(firsts), n)]
    c = np.r_[tree_graph.col, firsts]
    forest = coo_matrix((np.r_[tree_graph.data, np.ones(len(firsts))], (r, c)), shape=(n + 1, n + 1))
    order, parent = breadth_first_order(forest.tocsr(), n, directed=False, return_predecessors=True)
    flip = propagate_flips(order.astype(np.int64), parent.astype(np.int64), nrm, n)
    nrm[flip] *= -1.0
    # each piece faces up when mostly vertical, else away from its centroid, else up
    size = np.bincount(labels, minlength=count)
    centroid = np.stack([np.bincount(labels, pts[:, a], count) for a in range(3)], axis=1) / size[:, None]
    out = pts - centroid[labels]
    outward = np.bincount(labels, np.einsum("ij,ij->i", nrm, out), count)
    spread = np.bincount(labels, np.linalg.norm(out, axis=1), count)
    up = np.bincount(labels, nrm[:, 2], count)
    score = np.where((np.abs(up) < 0.5 * size) & (np.abs(outward) > 0.1 * spread), outward, up)
    nrm[score[labels] < 0] *= -1.0
    return nrm, labels.astype(np.int64)


def _bridges(tree: KDTree, pts: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One Boruvka round: for every piece but the largest, the closest pair of points joining it to another
    piece, among its points' ``BRIDGE_K`` nearest neighbours (at most ``BRIDGE_QUERIES`` points queried)."""
    largest = np.bincount(labels).argmax()
    query = np.flatnonzero(labels != largest)
    if len(query) > BRIDGE_QUERIES:
        query = np.sort(np.random.default_rng(0).choice(query, BRIDGE_QUERIES, replace=False))
    found_from, found_to, found_d = [], [], []
    for kk in BRIDGE_K:
        if len(query) == 0:
            break
        kk = int(min(kk, len(pts)))
        dist, idx = tree.query(pts[query], k=kk)
        idx = idx.reshape(len(query), kk).astype(np.int64)
        other = labels[idx] != labels[query][:, None]
        hit = other.any(axis=1)
        first = other.argmax(axis=1)            # neighbours come nearest first
        found_from.append(query[hit])
        found_to.append(idx[hit, first[hit]])
        found_d.append(dist.reshape(len(query), kk)[hit, first[hit]])
        # the next, wider query only for the points of pieces that found no bridge at all
        linked = np.unique(labels[query[hit]])
        query = query[~np.isin(labels[query], linked)]
        if len(query) > BRIDGE_QUERIES // 10:   # the wide query costs 8x more per point
            query = np.sort(np.random.default_rng(1).choice(query, BRIDGE_QUERIES // 10, replace=False))
    a = np.concatenate(found_from) if found_from else np.zeros(0, np.int64)
    if len(a) == 0:
        return a, a
    b, d = np.concatenate(found_to), np.concatenate(found_d)
    # the shortest bridge of each piece
    order = np.lexsort((d, labels[a]))
    keep = order[np.r_[True, labels[a][order][1:] != labels[a][order][:-1]]]
    return a[keep], b[keep]


def orientation_decided(normals: np.ndarray, points: np.ndarray, sensor: np.ndarray | None = None,
                        up: tuple[float, float, float] = (0.0, 0.0, 1.0), away_from: np.ndarray | None = None,
                        min_cos: float = 0.5) -> np.ndarray:
    """Which normals :func:`orient_normals`' rule (same arguments) orients with confidence: those within
    ``acos(min_cos)`` (60 degrees) of its reference direction, either way.

    A vertical wall under the ``up`` rule, or a surface seen edge-on by its sensor, lies across the reference:
    its orientation is a coin toss (the sign the eigen solver returned), and it must not outvote the points the
    rule does decide.

    Returns
    -------
    (N,) bool
    """
    n = np.asarray(normals, dtype=np.float64)
    ref = _reference(n.shape, points, sensor, up, away_from)
    norms = np.linalg.norm(ref, axis=1) * np.linalg.norm(n, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs(np.einsum("ij,ij->i", n, ref)) / norms
    return np.nan_to_num(cos) >= min_cos


def orientation_score(gradients: np.ndarray, normals: np.ndarray, where: np.ndarray | None = None) -> float:
    """Mean sign agreement in [-1, 1] between field gradients at the points and their oriented normals (over the
    points ``where`` is True, when given)."""
    dots = np.einsum("ij,ij->i", np.asarray(gradients, dtype=np.float64), np.asarray(normals, dtype=np.float64))
    if where is not None:
        dots = dots[np.asarray(where, bool)]
    valid = dots != 0
    if not valid.any():
        return 0.0
    return float(np.mean(np.sign(dots[valid])))
