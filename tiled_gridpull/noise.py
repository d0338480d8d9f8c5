"""Noise level of a point cloud, from how far points stray from their neighbours' best-fitting plane.

GridPull fits a field whose finest cell is the smallest detail it can express: a cloud whose noise is larger
than a cell gets that noise reproduced as bumps and bubbles (measured in ``docs/solver.md``). The estimate
here tells the user (and the noisy preset) how coarse the finest cell should be.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

from .normals import plane_fits

__all__ = ["estimate_noise", "NoiseEstimate", "project_to_local_planes", "denoise_margin", "denoise_block",
           "select_treatment", "NOISY_RATIO", "VERY_NOISY_RATIO", "LOCAL_NOISY_RATIO", "scan_noise",
           "SCAN_NOISY_CELLS", "SCAN_TREATMENT"]

#: ``sigma / spacing`` (64 neighbours) above which a cloud may be noisy (0.5 % noise: 1.22-1.53)
NOISY_RATIO = 1.2
#: and above which it is very noisy: between 0.5 % noise (at most 1.53) and 1 % (at least 1.84)
VERY_NOISY_RATIO = 1.7
#: the same ratio over 16 neighbours must exceed this too: thin walls (both sheets in one neighbourhood) and
#: sparse samples of sharp CAD edges give 1.36-2.17 over 64 neighbours on clean clouds but at most 0.77 over 16,
#: where 0.5 % noise gives at least 0.86
LOCAL_NOISY_RATIO = 0.8
#: neighbours of the local estimate
LOCAL_NEIGHBORS = 16

#: tiled mode: the 25th percentile of the scatter across planar neighbourhoods (:func:`scan_noise`), in cells,
#: above which the denoising passes are applied. Measured at 0.1 m cells on the demo street with 0 / 2 / 3 / 4 / 5 cm
#: of range noise: 0.003 / 0.057 / 0.086 / 0.114 / 0.143; denoising paid in CD-L1, NC and F-score only at 5 cm
#: (mixed at 3-4 cm, worse below). The shared real scans read 0.031-0.072 (AHN3 at 0.5 m, Autzen at 2 ft, Autzen's
#: EPT levels, a KITTI frame), and denoising made AHN3 and Autzen worse: docs/solver.md, "Denoising tiles".
SCAN_NOISY_CELLS = 0.125
#: what tiled mode's noise_auto applies when :func:`scan_noise` finds the scan noisy (the scene configs give the
#: passes' neighbours and radius)
SCAN_TREATMENT = {"denoise": 2}
#: neighbours a planar neighbourhood must hold to count in :func:`scan_noise`
SCAN_MIN_NEIGHBORS = 10
#: ... and its middle eigenvalue against the largest: scan rings are lines, whose "plane" is any plane through them
SCAN_PLANARITY = 0.1
#: the share of sampled neighbourhoods that must count for a figure at all: below it the scan is too sparse at
#: this cell for planes of ``denoise_radius`` cells (Autzen's EPT levels 0-2 at 2 ft: 8-12 %, and a reading that
#: swings from 0.07 to 0.19 with the sample), which is also where the passes would find too few neighbours
SCAN_MIN_PLANAR_SHARE = 0.25


@dataclass(frozen=True)
class NoiseEstimate:
    """Noise sigma and median sample spacing of a cloud (world units)."""

    sigma: float
    spacing: float

    @property
    def ratio(self) -> float:
        """Scatter across the surface against the spacing along it (``sigma / spacing``; 0 without spacing).
        Measured on the shared meshes: clean clouds give 0.04-0.6 at 100k points and 0.8-1.1 at 10k
        (curvature); Gaussian noise of 0.25 % of the bbox diagonal gives 1.0-1.1, of 0.5 % 1.35-1.5, of 1 %
        1.9-2.4."""
        return self.sigma / self.spacing if self.spacing > 0 else 0.0

    @property
    def noisy(self) -> bool:
        """Whether the scatter is large against the spacing (:attr:`ratio` above ``NOISY_RATIO``)."""
        return self.ratio > NOISY_RATIO

    def to_dict(self) -> dict:
        return {"sigma": self.sigma, "spacing": self.spacing, "ratio": self.ratio, "noisy": self.noisy}


def select_treatment(points: np.ndarray) -> tuple[str | None, NoiseEstimate, dict]:
    """The noise treatment a cloud needs (a key of :data:`tiled_gridpull.config.NOISE_PRESETS`, or None), its
    noise estimate (64 neighbours) and the figures that decided.

    Two scales must agree that the scatter across the surface is large against the spacing: over 64 neighbours
    (:data:`NOISY_RATIO`, :data:`VERY_NOISY_RATIO`) and over 16 (:data:`LOCAL_NOISY_RATIO`). Measured on the six
    shared meshes (100k and 10k clean samples; 100k with Gaussian noise of 0.25, 0.5 and 1 % of the bbox
    diagonal) and the merged real bunny scans: no clean cloud is treated, every 0.5 % cloud gets ``noisy``,
    every 1 % cloud ``very_noisy`` (which measured the better CD-L1 at 1 % on five meshes of six, ``noisy`` at
    0.5 % on five of six: BENCHMARKS.md, noise table).
    """
    wide = estimate_noise(points)
    local = estimate_noise(points, k=LOCAL_NEIGHBORS)
    pick = None
    if wide.ratio > NOISY_RATIO and local.ratio > LOCAL_NOISY_RATIO:
        pick = "very_noisy" if wide.ratio > VERY_NOISY_RATIO else "noisy"
    return pick, wide, {**wide.to_dict(), "local_ratio": local.ratio}


def scan_noise(points: np.ndarray, cell: float, radius_cells: float = 2.0, sample: int = 20_000,
               seed: int = 0, k: int = 64) -> dict:
    """How far a scan's points scatter across its surfaces, in cells: what tiled mode's ``noise_auto`` decides on.

    At ``sample`` seeded random points, a plane is fitted to the ``k`` nearest points within ``radius_cells``
    cells (the radius of the denoising passes); neighbourhoods with fewer than ``SCAN_MIN_NEIGHBORS`` points, or
    whose points lie along a line (middle eigenvalue below ``SCAN_PLANARITY`` x the largest: a scan ring), do
    not count, and unless ``SCAN_MIN_PLANAR_SHARE`` of them count there is no figure. Their scatter
    ``sqrt(smallest eigenvalue x n / (n - 3))`` is summarised by its 25th percentile: vegetation, edges and
    curbs scatter whatever the sensor's noise, and are a minority of the neighbourhoods of a street or a survey;
    the flat ground and walls below that percentile show the noise.

    Parameters
    ----------
    points : (N, 3) float
        A dense part of the scan (world units; georeferenced values are fine: offsets are taken from each point).
    cell : float
        The job's cell size, world units.

    Returns
    -------
    dict
        ``q25_cells`` and ``median_cells`` (None without enough planar neighbourhoods), ``planar`` (how many
        counted), ``sampled``, ``radius_cells``, ``neighbors``.
    """
    pts = np.asarray(points, dtype=np.float64)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    n = len(pts)
    out = {"q25_cells": None, "median_cells": None, "planar": 0, "sampled": 0, "radius_cells": float(radius_cells),
           "neighbors": int(k)}
    if n < SCAN_MIN_NEIGHBORS:
        return out
    # offsets from the median keep georeferenced coordinates' precision, and a stray point cannot be the origin
    origin = np.median(pts, axis=0)
    local = pts - origin
    rng = np.random.default_rng(seed)
    at = np.sort(rng.choice(n, size=min(sample, n), replace=False))
    dist, idx = KDTree(local).query(local[at], k=min(k, n), distance_upper_bound=radius_cells * cell)
    dist = dist.reshape(len(at), -1)
    idx = idx.reshape(len(at), -1).astype(np.int64)
    valid = np.isfinite(dist)
    count = valid.sum(axis=1)
    off = local[np.where(valid, idx, 0)] - local[at][:, None, :]
    off[~valid] = 0.0
    n_nb = np.maximum(count, 1)
    mean = off.sum(axis=1) / n_nb[:, None]
    cov = np.einsum("mki,mkj->mij", off, off) / n_nb[:, None, None] - mean[:, :, None] * mean[:, None, :]
    ev = np.linalg.eigvalsh(cov)
    keep = (count >= SCAN_MIN_NEIGHBORS) & (ev[:, 1] > SCAN_PLANARITY * ev[:, 2])
    out["sampled"] = int(len(at))
    out["planar"] = int(keep.sum())
    if out["planar"] < max(100, SCAN_MIN_PLANAR_SHARE * len(at)):
        return out
    m = count[keep]
    sigma = np.sqrt(np.maximum(ev[keep, 0], 0.0) * m / (m - 3)) / cell
    out["q25_cells"] = float(np.quantile(sigma, 0.25))
    out["median_cells"] = float(np.median(sigma))
    return out


def estimate_noise(points: np.ndarray, k: int = 64, sample: int = 10_000, seed: int = 0,
                   max_k: int = 512) -> NoiseEstimate:
    """Standard deviation of the points' scatter across the surface (world units).

    For ``sample`` random points, the ``k`` nearest neighbours get a least-squares plane (PCA); the spread
    along its normal is ``sqrt(smallest eigenvalue)``. The median over points, scaled by ``sqrt(k / (k - 3))``
    for the three fitted degrees of freedom, estimates the Gaussian noise sigma. When the neighbourhood's
    radius is under 3 sigma it truncates the scatter, so ``k`` is doubled (up to ``max_k``) until it is not.
    Curvature adds a bias on clean clouds (below half the sample spacing on the shared meshes).

    Parameters
    ----------
    points : (N, 3) float
        The cloud (any coordinates: it is centred first, so georeferenced values keep their precision).
    k : int
        Neighbours per plane fit.
    sample : int
        Points at which the plane is fitted (all of them when the cloud is smaller).

    Returns
    -------
    NoiseEstimate
        ``sigma`` (same units as ``points``) and the median nearest-neighbour distance ``spacing``.
    """
    pts, scale = _unit_frame(points)
    n = len(pts)
    k = int(min(k, n))
    if k < 4:
        return NoiseEstimate(0.0, 0.0)
    rng = np.random.default_rng(seed)
    at = pts[rng.choice(n, size=min(sample, n), replace=False)]
    tree = KDTree(pts)
    spacing, sigma = 0.0, 0.0
    while True:
        dist, idx = tree.query(at, k=k)
        if spacing == 0.0:
            spacing = float(np.median(dist[:, 1]))
        nb = pts[idx.astype(np.int64)]
        nb = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("mki,mkj->mij", nb, nb) / k
        smallest = np.linalg.eigvalsh(cov)[:, 0]
        sigma = float(np.sqrt(np.median(np.maximum(smallest, 0.0)) * k / (k - 3)))
        # a neighbourhood not much wider than the noise cuts the scatter's tails off and underestimates it
        # (1 % noise on the bunny: 0.62 sigma at k = 64): widen it until it spans 3 sigma
        if np.median(dist[:, -1]) >= 3.0 * sigma or k >= max_k or k >= n:
            break
        k = min(2 * k, max_k, n)
    return NoiseEstimate(sigma * scale, spacing * scale)


def _unit_frame(points: np.ndarray, centre: bool = True) -> tuple[np.ndarray, float]:
    """Points centred (unless ``centre`` is false) and divided by a power of two near their extent, and that power.

    Centring keeps georeferenced values' precision; the power-of-two scale (exact in binary floating point, so
    ordinary clouds give the same bits as unscaled) keeps squared distances and covariances finite for extents
    up to float64's limit: past about 1e154 they overflow, and pykdtree then answers "no neighbour" with index
    2^32 - 1."""
    pts = np.asarray(points, dtype=np.float64)
    if centre:
        pts = pts - pts.mean(axis=0)
    extent = float(np.abs(pts).max()) if pts.size else 0.0
    if not (np.isfinite(extent) and extent > 0.0):
        return pts, 1.0
    scale = float(2.0 ** np.round(np.log2(extent)))
    return pts / scale, scale


def project_to_local_planes(points: np.ndarray, k: int = 64, iterations: int = 2, bandwidth: float = 0.0,
                            chunk: int = 50_000, radius: float = np.inf, centre: bool = True) -> np.ndarray:
    """Denoise a cloud: move every point onto the plane of its ``k`` nearest neighbours, repeated.

    The classical point-set projection (:func:`tiled_gridpull.normals.plane_fits`, all points moved at once from
    the previous pass's positions). It removes scatter across the surface and leaves the spacing along it, so the
    noise estimate drops and the noisy preset can keep a finer grid.

    The plain least-squares plane (``bandwidth = 0``) averages whatever sheets share a neighbourhood: the two
    walls of a part thinner than the neighbourhood merge into one, and sharp edges round over about one
    neighbourhood radius. With ``bandwidth > 0`` the plane is fitted robustly (bilateral weights, see
    :func:`~tiled_gridpull.normals.plane_fits`) with a range scale of ``bandwidth`` x the noise sigma
    re-estimated before each pass, so each point moves toward the sheet it came from. Measured on
    abc_00011084 (a bushing with a thin sleeve in its bore; 100k points, noise 0.5 % of the bbox diagonal)
    by the noisy preset: docs/solver.md.

    Parameters
    ----------
    points : (N, 3) float
        The cloud (world units; centred internally, so georeferenced values keep their precision).
    k : int
        Neighbours per plane fit (at most N).
    iterations : int
        Passes; 0 returns a copy.
    bandwidth : float
        Robust range scale in units of the estimated noise sigma; 0 gives the plain least-squares plane.
    chunk : int
        Points whose neighbourhoods are fitted at once (bounds memory to about ``chunk * k * 48`` bytes).
    radius : float
        Only neighbours within this distance (world units) count (:func:`~tiled_gridpull.normals.plane_fits`);
        a point with fewer than 4 stays where it is. With a bound, each pass moves a point by at most
        ``radius`` and the result after ``P`` passes depends only on the points within ``P^2 radius``
        (:func:`denoise_margin`).
    centre : bool
        Work relative to the points' mean (keeps georeferenced values' precision). False for a tile's points,
        already near the origin: each tile's mean differs, and so would the rounding of a shared point.

    Returns
    -------
    (N, 3) float64
        The projected points, in the input's coordinates.
    """
    pts = np.asarray(points, dtype=np.float64)
    mean = pts.mean(axis=0) if centre else np.zeros(3)
    cur, scale = _unit_frame(pts, centre)
    n = len(cur)
    k = int(min(k, n))
    if k < 4 or iterations <= 0:
        return pts.copy()
    for _ in range(int(iterations)):
        h = bandwidth * estimate_noise(cur).sigma if bandwidth > 0 else 0.0
        out = np.empty_like(cur)
        for a, b, centroid, normal in plane_fits(cur, k, chunk, bandwidth=h, radius=radius / scale):
            p = cur[a:b]
            out[a:b] = p - np.sum((p - centroid) * normal, axis=1)[:, None] * normal
        cur = out
    return cur * scale + mean


def denoise_margin(passes: int, radius: float) -> float:
    """How far the result of ``passes`` radius-bounded passes reaches (``passes^2 x radius``, units of ``radius``).

    A pass moves a point onto a plane through the centroid of points within ``radius`` of it, so by at most
    ``radius``. At pass ``t`` two points that both moved at most ``(t - 1) radius`` and are neighbours now started
    within ``(2t - 1) radius`` of each other, so pass ``t`` adds ``(2t - 1) radius`` to the reach of pass
    ``t - 1``: ``radius (1 + 3 + ... + (2P - 1)) = P^2 radius``.
    """
    return float(passes) ** 2 * float(radius)


def denoise_block(points: np.ndarray, k: int, passes: int, radius: float, lo: np.ndarray,
                  hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Denoise the points of one block of a tiling so that what it keeps does not depend on the tiling.

    Every point of the block takes part in the ``passes`` radius-bounded projections
    (:func:`project_to_local_planes`), but only the points farther than :func:`denoise_margin` from a face
    beyond which the block misses points are kept: their neighbourhoods, pass after pass, lie inside the block,
    so any block holding them at the same offsets from each other gives them the same positions. A tiled job
    reads a halo as wide as the margin around each block, so every point of the block itself is kept.

    Parameters
    ----------
    points : (N, 3) float
        Every input point inside the block (any frame, e.g. metres from the block's low corner).
    k : int
        Neighbours per plane fit (the nearest, within ``radius``).
    passes : int
        Projections (> 0).
    radius : float
        Neighbourhood bound, units of ``points``.
    lo, hi : (3,) float
        The block's faces beyond which points exist that the block does not hold; ``-inf`` / ``inf`` on a side
        with no points beyond (the outer faces of the tile grid).

    Returns
    -------
    denoised : (M, 3) float64
        The kept points, moved.
    keep : (N,) bool
        Which input points were kept.
    """
    pts = np.asarray(points, dtype=np.float64)
    margin = denoise_margin(passes, radius)
    keep = np.all((pts >= np.asarray(lo, np.float64) + margin) & (pts <= np.asarray(hi, np.float64) - margin),
                  axis=1)
    moved = project_to_local_planes(pts, k, passes, 0.0, radius=radius, centre=False)
    return moved[keep], keep
