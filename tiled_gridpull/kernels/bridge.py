"""Bridging gaps between scan lines on near-horizontal ground: a local height fit per lattice column.

Ground samples are binned into a 2D grid of ``pixel`` cells (one representative per pixel: the mean of the
lowest layer of points there). For a lattice column, the representatives within ``radius`` cells are looked at in
``SECTORS`` directions; the column is bridged only where they surround it (no run of empty sectors wider than
``max_gap`` sectors), lie on one plane (weighted RMS residual and the largest residual of the nearest
representative of each sector below tolerances) and that plane is not steep. Every column is decided from the
representatives within ``radius`` alone, so two tiles that both hold them decide it alike. Where the points'
sensor origins are known, the column must also have a representative beyond it as the sensor sees it
(:func:`bin_sensor`): the next ring lies there, the ground in a shadow has none; ground hidden from the sensor
stays open (:func:`hidden_from_sensor`), and so does a gap a beam passed under (:func:`pierced_columns`,
:func:`clear_pierced_gaps`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .interp import bounded_slot_of

SECTORS = 12


@njit(cache=True)
def bin_low(x, y, z, pixel, nx, ny):
    """(nx, ny) float64: the lowest z of the points in each ``pixel``-wide bin; inf where a bin holds none."""
    low = np.full((nx, ny), np.inf)
    for n in range(x.shape[0]):
        i = int(math.floor(x[n] / pixel))
        j = int(math.floor(y[n] / pixel))
        if 0 <= i < nx and 0 <= j < ny and z[n] < low[i, j]:
            low[i, j] = z[n]
    return low


@njit(cache=True)
def bin_ground(x, y, z, pixel, nx, ny, layer):
    """Mean position of the lowest layer of points in each ``pixel`` x ``pixel`` bin of a 2D grid (cells).

    The lowest layer (points within ``layer`` of the bin's lowest) is the ground where anything stands on it:
    under a tree's crown, at a wall's foot (the wall's bin then reads the ground it stands on), beside a car.

    Parameters
    ----------
    x, y, z : (N,) float64
        Points in cells (block-local lattice coordinates).
    pixel : float
        Bin size in cells.
    nx, ny : int
        Bins per axis (points outside are ignored).
    layer : float
        Thickness of the lowest layer (cells).

    Returns
    -------
    rep : (nx, ny, 3) float64
        Mean x, y, z of each bin's lowest layer; NaN where a bin holds no point.
    """
    low = bin_low(x, y, z, pixel, nx, ny)
    acc = np.zeros((nx, ny, 4))
    for n in range(x.shape[0]):
        i = int(math.floor(x[n] / pixel))
        j = int(math.floor(y[n] / pixel))
        if 0 <= i < nx and 0 <= j < ny and z[n] <= low[i, j] + layer:
            acc[i, j, 0] += x[n]
            acc[i, j, 1] += y[n]
            acc[i, j, 2] += z[n]
            acc[i, j, 3] += 1.0
    rep = np.full((nx, ny, 3), np.nan)
    for i in range(nx):
        for j in range(ny):
            c = acc[i, j, 3]
            if c > 0:
                rep[i, j, 0] = acc[i, j, 0] / c
                rep[i, j, 1] = acc[i, j, 1] / c
                rep[i, j, 2] = acc[i, j, 2] / c
    return rep


@njit(cache=True)
def bin_sensor(x, y, z, sx, sy, sz, pixel, nx, ny, layer):
    """The sensor that saw each bin's ground: of the points :func:`bin_ground` averages (the lowest layer), the
    one whose rings lie densest there.

    A spinning scanner ``h`` above the ground meets it at horizontal range ``r`` with rings ``beam * (r^2 + h^2)
    / h`` apart (``beam`` the angle between beams): where several sweeps saw a bin, the sensor with the least
    ``(r^2 + h^2) / h`` samples it most closely, and its rings are those a gap there lies between.

    Parameters
    ----------
    x, y, z, sx, sy, sz : (N,) float64
        Points and their sensor origins, in cells.
    pixel, nx, ny, layer
        As :func:`bin_ground`.

    Returns
    -------
    sensor : (nx, ny, 3) float64
        x, y, z of that sensor; NaN where a bin holds no point, or no sensor above its lowest layer's points.
    """
    low = bin_low(x, y, z, pixel, nx, ny)
    best = np.full((nx, ny), np.inf)
    sensor = np.full((nx, ny, 3), np.nan)
    for n in range(x.shape[0]):
        i = int(math.floor(x[n] / pixel))
        j = int(math.floor(y[n] / pixel))
        if 0 <= i < nx and 0 <= j < ny and z[n] <= low[i, j] + layer:
            h = sz[n] - z[n]
            if h > 0.0:
                dx = sx[n] - x[n]
                dy = sy[n] - y[n]
                s = (dx * dx + dy * dy + h * h) / h
                if s < best[i, j]:
                    best[i, j] = s
                    sensor[i, j, 0] = sx[n]
                    sensor[i, j, 1] = sy[n]
                    sensor[i, j, 2] = sz[n]
    return sensor


@njit(cache=True)
def bin_top(x, y, z, pixel, nx, ny):
    """(nx, ny) float64: the highest z of the points in each ``pixel``-wide bin; -inf where a bin holds none."""
    return -bin_low(x, y, -z, pixel, nx, ny)


@njit(cache=True)
def _window_extreme(a, half, axis, lowest):
    """The least (``lowest``) or greatest value of ``a`` (nx, ny) within ``half`` bins along ``axis``."""
    nx, ny = a.shape
    out = np.empty_like(a)
    for i in range(nx):
        for j in range(ny):
            best = a[i, j]
            for d in range(-half, half + 1):
                u, v = (i + d, j) if axis == 0 else (i, j + d)
                if 0 <= u < nx and 0 <= v < ny:
                    w = a[u, v]
                    if (w < best) if lowest else (w > best):
                        best = w
            out[i, j] = best
    return out


@njit(cache=True)
def object_bins(ground, half, tol):
    """Bins whose ground sample stands on something narrower than the window: a car, a bush, a hedge, a pole.

    The samples' heights are opened (the least height within ``half`` bins, then the greatest of those within
    ``half`` bins; a square window, bins without a sample and beyond the raster left out: a thing is found where
    the windows over it hold ground samples too). Opening keeps any plane and any level wider
    than the window (a road, a raised pavement, both sides of a kerb or a terrace) where it is, and lowers
    whatever is narrower to the ground around it: a sample more than ``tol`` above its opened height stands on
    a thing, not on the ground. Each bin is decided by the samples within ``2 half`` bins of it.

    Parameters
    ----------
    ground : (nx, ny) float64
        Each bin's ground sample height (:func:`bin_ground`'s z, cells); NaN where a bin holds none.
    half : int
        Half-width of the window in bins (a thing up to ``2 half`` bins wide is found).
    tol : float
        Height above the opened ground (cells) that makes an object.

    Returns
    -------
    (nx, ny) bool
    """
    nx, ny = ground.shape
    # windows may reach past the raster (samples there unknown): a window over the raster's corner then holds the
    # corner's own samples, and a plane rising towards a corner keeps its height there
    low = np.full((nx + 2 * half, ny + 2 * half), np.inf)
    for i in range(nx):
        for j in range(ny):
            if not math.isnan(ground[i, j]):
                low[i + half, j + half] = ground[i, j]
    eroded = _window_extreme(_window_extreme(low, half, 0, True), half, 1, True)
    for i in range(eroded.shape[0]):
        for j in range(eroded.shape[1]):
            if eroded[i, j] == np.inf:
                eroded[i, j] = -np.inf  # no sample within the window: left out of the dilation
    opened = _window_extreme(_window_extreme(eroded, half, 0, False), half, 1, False)
    out = np.zeros((nx, ny), np.bool_)
    for i in range(nx):
        for j in range(ny):
            out[i, j] = not math.isnan(ground[i, j]) and ground[i, j] - opened[i + half, j + half] > tol
    return out


@njit(cache=True, parallel=True)
def hidden_from_sensor(cols, fit, rep, sensor, top, thing, pixel, radius, reach_along, tol, min_facing):
    """Whether each bridged column's plane is ground its sensor could not have seen: it faces away from the
    sensor, or something stood between them.

    The sensor is that of the column's nearest ground sample whose sensor is known. Two ways the ground at a
    column is hidden rather than missed between two rings:

    * the plane faces the sensor less than ``min_facing`` times as squarely as level ground there would (the
      sines of their angles with the line of sight), or faces away: below a drop-off (a kerb, a terrace's edge,
      an embankment, seen from its top) the ground is hidden for metres, and a plane through the edge's samples
      and the low ground beyond is a ramp the line of sight only grazes, along which rings would lie many times
      farther apart than on the ground around it (a ramp as gentle as the line of sight's own slope over the
      ground beyond passes: docs/solver.md, "What still breaks the promise");
    * the line of sight from the sensor to the plane at the column passes, within ``reach_along`` of the
      column, under the highest point of a bin by more than ``tol`` (under any point of a bin that holds a thing
      standing on the ground: a low median's or planter's top lies less than a cell above the line over most of
      its shadow): a car, a box, a wall or the edge of a drop stood between them.

    Parameters
    ----------
    cols : (M, 2) float64
        Column positions (cells).
    fit : (M, 3) float64
        Each column's plane (:func:`fit_columns`: height, dz/dx, dz/dy); NaN rows are not looked at (False).
    rep, sensor : (nx, ny, 3) float64
        Ground samples (NaN where none) and their sensors' x, y, z (:func:`bin_sensor`).
    top : (nx, ny) float64
        Highest point of each bin (:func:`bin_top`).
    thing : (nx, ny) bool
        Bins holding a thing standing on the ground (:func:`object_bins`).
    pixel, radius : float
        Bin size, and how far the column's nearest ground sample may lie (cells).
    reach_along : float
        How far along the line of sight from the column anything is looked for (cells).
    tol : float
        The height above the line of sight that hides (cells).
    min_facing : float
        Least ratio of the sine of the plane's angle with the line of sight to level ground's.

    Returns
    -------
    (M,) bool
    """
    nx, ny = rep.shape[0], rep.shape[1]
    m = cols.shape[0]
    out = np.zeros(m, np.bool_)
    reach = int(math.ceil(radius / pixel)) + 1
    for c in prange(m):
        h = fit[c, 0]
        if math.isnan(h):
            continue
        cx, cy = cols[c, 0], cols[c, 1]
        ic = int(math.floor(cx / pixel))
        jc = int(math.floor(cy / pixel))
        nearest = np.inf
        sx, sy, sz = np.nan, np.nan, np.nan
        for i in range(max(0, ic - reach), min(nx, ic + reach + 1)):
            for j in range(max(0, jc - reach), min(ny, jc + reach + 1)):
                if math.isnan(rep[i, j, 2]) or math.isnan(sensor[i, j, 0]):
                    continue
                dx = rep[i, j, 0] - cx
                dy = rep[i, j, 1] - cy
                d2 = dx * dx + dy * dy
                if d2 < nearest:
                    nearest = d2
                    sx, sy, sz = sensor[i, j, 0], sensor[i, j, 1], sensor[i, j, 2]
        if math.isnan(sx):
            continue
        ux, uy, uz = sx - cx, sy - cy, sz - h
        gx, gy = fit[c, 1], fit[c, 2]
        # the plane's upward normal (-gx, -gy, 1) against the line of sight
        norm = math.sqrt(ux * ux + uy * uy + uz * uz)
        facing = (-gx * ux - gy * uy + uz) / (math.sqrt(gx * gx + gy * gy + 1.0) * norm)
        if not (facing > 0.0 and facing >= min_facing * uz / norm):
            out[c] = True
            continue
        dist = math.sqrt(ux * ux + uy * uy)
        if dist == 0.0:
            continue
        ux /= dist
        uy /= dist
        step = 0.5 * pixel
        t = step
        while t <= min(reach_along, dist):
            i = int(math.floor((cx + t * ux) / pixel))
            j = int(math.floor((cy + t * uy) / pixel))
            if 0 <= i < nx and 0 <= j < ny and top[i, j] > h + uz * t / dist + (0.0 if thing[i, j] else tol):
                out[c] = True
                break
            t += step
    return out


@njit(cache=True)
def pierced_columns(x, y, z, sx, sy, sz, height, gx, gy, low, pixel, layer, skip, reach, tol):
    """How many beams pass under each bridged column's plane: the plane is not there.

    A beam travels through empty space from its sensor to its point, so the ground along it lies below it. A beam
    that crosses a column more than ``tol`` under the plane bridged there shows the ground lower than the plane:
    across a ditch the beams that reach its far wall pass under the plane over its rims. A point that the points
    of fewer than two neighbouring bins reach down to (within ``layer``) is left out: KITTI frames hold clusters
    of a few points metres under the road (reflections), whose beams would pierce every plane over metres of road,
    and so is a point whose sensor is not above it.

    Parameters
    ----------
    x, y, z, sx, sy, sz : (N,) float64
        Points and their sensor origins, in cells.
    height, gx, gy : (X, Y) float64
        Each lattice column's plane (height at the column, dz/dx, dz/dy; cells); NaN height where not bridged.
        Column ``(i, j)`` stands at ``(i, j)`` and holds the positions nearest it.
    low : (nx, ny) float64
        The lowest point of each ``pixel``-wide bin (inf where a bin holds none).
    pixel, layer : float
        Bin size, and how far above a point the lowest point of a neighbouring bin may lie for it to count.
    skip : float
        The last ``skip`` cells of each beam (in plan) are not looked at: there it meets its own point's ground at a
        grazing angle, within the plane fit's own error of it.
    reach : float
        How far back from its point each beam is followed (cells, in plan).
    tol : float
        Depth under the plane that counts (cells).

    Returns
    -------
    count : (X, Y) int32
        Beams that passed under each column's plane.
    along : (X, Y, 2) float64
        The unit direction (in plan, towards the sensor) of the last such beam; NaN where none.
    """
    nx, ny = height.shape
    count = np.zeros((nx, ny), np.int32)
    along = np.full((nx, ny, 2), np.nan)
    bx, by = low.shape
    step = 0.5
    for n in range(x.shape[0]):
        if not sz[n] > z[n]:
            continue  # no sensor below its point saw it (a datum error, a trajectory's glitch)
        a = int(math.floor(x[n] / pixel))
        b = int(math.floor(y[n] / pixel))
        held = 0
        for u in range(max(0, a - 1), min(bx, a + 2)):
            for v in range(max(0, b - 1), min(by, b + 2)):
                if (u != a or v != b) and low[u, v] <= z[n] + layer:
                    held += 1
        if held < 2:
            continue
        dx = sx[n] - x[n]
        dy = sy[n] - y[n]
        dist = math.sqrt(dx * dx + dy * dy)
        if not dist > 0.0:
            continue
        ux, uy = dx / dist, dy / dist
        rise = (sz[n] - z[n]) / dist
        last_i, last_j = -1, -1
        t = skip
        while t <= min(reach, dist):
            px, py = x[n] + t * ux, y[n] + t * uy
            i = int(math.floor(px + 0.5))
            j = int(math.floor(py + 0.5))
            if 0 <= i < nx and 0 <= j < ny and (i != last_i or j != last_j):
                h = height[i, j]
                if not math.isnan(h) and z[n] + t * rise < h + gx[i, j] * (px - i) + gy[i, j] * (py - j) - tol:
                    count[i, j] += 1
                    along[i, j, 0] = ux
                    along[i, j, 1] = uy
                    last_i, last_j = i, j
            t += step
    return count, along


@njit(cache=True)
def clear_pierced_gaps(mask, count, along, min_beams, top, pixel, reach):
    """The bridged columns left once every gap a beam pierced is opened along that beam's line to its ends.

    A gap between two rings is one stretch of bins without a point along the line of sight. Where beams show the
    plane over part of it to be too high (:func:`pierced_columns`), the stretch is no sampling gap: the part nearer
    the sensor lies in the shadow of the near edge, where no beam could reach below the plane, so the whole stretch
    stays open, up to the bins holding points on either side (or ``reach`` cells).

    Parameters
    ----------
    mask : (X, Y) bool
        Bridged columns.
    count, along : (X, Y) int32, (X, Y, 2) float64
        :func:`pierced_columns`' output.
    min_beams : int
        Beams needed to open a column's gap.
    top : (nx, ny) float64
        Highest point of each ``pixel``-wide bin (:func:`bin_top`; -inf where a bin holds none).
    pixel, reach : float
        Bin size and the longest stretch opened on either side (cells).

    Returns
    -------
    (X, Y) bool
    """
    nx, ny = mask.shape
    bx, by = top.shape
    out = mask.copy()
    step = 0.5
    for i in range(nx):
        for j in range(ny):
            if not mask[i, j] or count[i, j] < min_beams:
                continue
            out[i, j] = False
            for sign in (-1.0, 1.0):
                ux, uy = sign * along[i, j, 0], sign * along[i, j, 1]
                t = step
                while t <= reach:
                    px, py = i + t * ux, j + t * uy
                    a = int(math.floor(px / pixel))
                    b = int(math.floor(py / pixel))
                    if not (0 <= a < bx and 0 <= b < by) or top[a, b] > -np.inf:
                        break
                    u = int(math.floor(px + 0.5))
                    v = int(math.floor(py + 0.5))
                    if 0 <= u < nx and 0 <= v < ny:
                        out[u, v] = False
                    t += step
    return out


_ROOT3 = math.sqrt(3.0)


@njit(cache=True, inline="always")
def sector_of(dx, dy):
    """Which of the ``SECTORS`` 30-degree sectors the offset ``(dx, dy)`` points into: ``floor((atan2(dy, dx) + pi)
    / (2 pi) * SECTORS) mod SECTORS``.

    Decided by comparing ``|dy|`` with ``|dx| tan 30`` and ``|dx| tan 60``, which costs a few multiplies where
    ``atan2`` was most of :func:`fit_columns`' time; offsets within a relative 1e-9 of a sector's edge (on an
    axis, or at 30 / 60 degrees from one) take the ``atan2`` formula itself, so every offset gets the sector that
    formula gives.
    """
    ax = abs(dx)
    ay = abs(dy)
    e30 = ay * _ROOT3 - ax  # < 0: less than 30 degrees from the x axis
    e60 = ay - ax * _ROOT3  # < 0: less than 60 degrees
    tol = 1e-9 * (ax + ay)
    if ax <= tol or ay <= tol or abs(e30) <= tol or abs(e60) <= tol:
        return int((math.atan2(dy, dx) + math.pi) / (2.0 * math.pi) * SECTORS) % SECTORS
    w = 0 if e30 < 0.0 else (1 if e60 < 0.0 else 2)
    if dx > 0.0:
        return 6 + w if dy > 0.0 else 5 - w
    return 11 - w if dy > 0.0 else w


@njit(cache=True, parallel=True)
def fit_columns(rep, pixel, cols, radius, skip, max_gap, rms_tol, step_tol, max_slope, sensor, far_cos):
    """Bridged height of each lattice column, or NaN where it is not bridged.

    Parameters
    ----------
    rep : (nx, ny, 3) float64
        Ground representatives per bin (:func:`bin_ground`), NaN where none. Each must lie inside its own bin
        (``bin_ground``'s means do): bins whose nearest edge lies beyond ``radius`` are not read.
    pixel : float
        Bin size in cells.
    cols : (M, 2) float64
        Column positions (x, y) in cells.
    radius : float
        Representatives farther than this (cells, horizontally) are not used.
    skip : float
        Columns with a representative within this distance on every side (each occupied sector) are densely
        sampled: they are left to the solved field (NaN). A column beside a lone scan line is not.
    max_gap : int
        Widest run of empty sectors (of ``SECTORS``) that still counts as surrounded.
    rms_tol, step_tol : float
        Largest weighted RMS residual of the plane fit, and largest residual of the nearest representative of
        any sector (cells): more means a height step (a kerb, a car, a wall's foot) within reach.
    max_slope : float
        Largest gradient of the fitted plane (rise over run).
    sensor : (nx, ny, 2 or 3) float64
        The sensor x, y (and z, not used here) of each representative (:func:`bin_sensor`); NaN: unknown.
    far_cos : float
        Where the nearest representative's sensor is known and ``far_cos`` < 1, the column is bridged only if a
        representative within ``radius`` lies beyond it as that sensor sees it: within ``acos(far_cos)`` of the
        line of sight, the cone widened by half a bin (a sample within half a bin of the column counts). Between
        two rings the next ring is there; in the shadow of a box, a car or a wall the ground beyond is hidden for
        as long as the shadow. 1 or more: no such test.

    Returns
    -------
    out : (M, 3) float64
        Height at the column and the plane's slopes (dz/dx, dz/dy); NaN rows where not bridged.
    """
    nx, ny = rep.shape[0], rep.shape[1]
    m = cols.shape[0]
    out = np.full((m, 3), np.nan)
    reach = int(math.ceil(radius / pixel)) + 1
    r2 = radius * radius
    cull2 = (radius + 1e-6) ** 2
    cap = (2 * reach + 1) * (2 * reach + 1)
    # the beyond test's cone: half-width over length (far_cos < 1 only)
    slope = math.sqrt(max(1.0 - far_cos * far_cos, 0.0)) / far_cos if far_cos < 1.0 else 0.0
    for c in prange(m):
        cx, cy = cols[c, 0], cols[c, 1]
        ic = int(math.floor(cx / pixel))
        jc = int(math.floor(cy / pixel))
        # the representatives within reach, gathered once (offsets from the column, height, squared distance, and
        # the plane fit's weight once it is known)
        nb = np.empty((cap, 5))
        k = 0
        nearest = np.inf
        near_i, near_j = -1, -1  # the nearest representative's bin (its sensor is the one the beyond test uses)
        for i in range(max(0, ic - reach), min(nx, ic + reach + 1)):
            # a bin whose nearest edge lies beyond the radius holds no representative within it (a margin, for a
            # mean rounded a hair outside its bin)
            ex = max(i * pixel - cx, cx - (i + 1) * pixel, 0.0)
            if ex * ex > cull2:
                continue
            for j in range(max(0, jc - reach), min(ny, jc + reach + 1)):
                ey = max(j * pixel - cy, cy - (j + 1) * pixel, 0.0)
                if ex * ex + ey * ey > cull2 or math.isnan(rep[i, j, 2]):
                    continue
                dx = rep[i, j, 0] - cx
                dy = rep[i, j, 1] - cy
                d2 = dx * dx + dy * dy
                if d2 <= r2:
                    nb[k, 0] = dx
                    nb[k, 1] = dy
                    nb[k, 2] = rep[i, j, 2]
                    nb[k, 3] = d2
                    if d2 < nearest:
                        nearest = d2
                        near_i, near_j = i, j
                    k += 1
        if k == 0:
            continue
        near_d = np.full(SECTORS, np.inf)
        near_k = np.full(SECTORS, -1, np.int64)
        for t in range(k):
            d2 = nb[t, 3]
            s = sector_of(nb[t, 0], nb[t, 1])
            if d2 < near_d[s]:
                near_d[s] = d2
                near_k[s] = t
        # the tests below each reject on their own, so the cheap ones come first: a densely sampled column
        farthest = 0.0
        for s in range(SECTORS):
            if near_k[s] >= 0 and near_d[s] > farthest:
                farthest = near_d[s]
        if farthest <= skip * skip:
            continue
        # widest run of empty sectors, wrapping around
        run = 0
        widest = 0
        for t in range(2 * SECTORS):
            if near_k[t % SECTORS] < 0:
                run += 1
                if run > widest:
                    widest = run
            else:
                run = 0
        if widest > max_gap:
            continue
        if far_cos < 1.0:
            sx = sensor[near_i, near_j, 0]
            sy = sensor[near_i, near_j, 1]
            if not math.isnan(sx):
                ax = cx - sx
                ay = cy - sy
                an = math.sqrt(ax * ax + ay * ay)
                beyond = an == 0.0
                # within the cone, widened by half a bin: a bin's sample lies up to that far beside the line of
                # sight even where its ring crosses it (the last ring, a few cells beyond the column), and a sample
                # within half a bin of the column itself counts (the column lies on a ring, not in a shadow)
                for t in range(k):
                    along = (nb[t, 0] * ax + nb[t, 1] * ay) / an if an > 0.0 else 0.0
                    if along > -0.5 * pixel:
                        side = math.sqrt(max(nb[t, 3] - along * along, 0.0))
                        if side <= slope * max(along, 0.0) + 0.5 * pixel:
                            beyond = True
                            break
                if not beyond:
                    continue
        # weighted plane z = h + gx (x - cx) + gy (y - cy): Gaussian weights as wide as the gap, so the nearest
        # samples on every side shape the plane and far ones only steady it; at least as wide as the farthest
        # side's nearest sample, or a column on a scan line would see only its own line, which has no slope
        # across itself
        sigma = max(1.5 * math.sqrt(nearest), 0.7 * math.sqrt(farthest), pixel)
        inv = 1.0 / (sigma * sigma)
        A = np.zeros((3, 3))
        b = np.zeros(3)
        for t in range(k):
            w = math.exp(-nb[t, 3] * inv)
            nb[t, 4] = w
            dx, dy, zz = nb[t, 0], nb[t, 1], nb[t, 2]
            A[0, 0] += w
            A[0, 1] += w * dx
            A[0, 2] += w * dy
            A[1, 1] += w * dx * dx
            A[1, 2] += w * dx * dy
            A[2, 2] += w * dy * dy
            b[0] += w * zz
            b[1] += w * dx * zz
            b[2] += w * dy * zz
        # the symmetric 3 x 3 system by its cofactors: np.linalg.det and solve cost this kernel 10 s of numba
        # compilation (LAPACK bindings), most of it
        c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[1, 2]
        c01 = A[0, 2] * A[1, 2] - A[0, 1] * A[2, 2]
        c02 = A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]
        det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
        if not abs(det) > 1e-12 * (A[0, 0] * A[1, 1] * A[2, 2] + 1e-300):
            continue
        c11 = A[0, 0] * A[2, 2] - A[0, 2] * A[0, 2]
        c12 = A[0, 1] * A[0, 2] - A[0, 0] * A[1, 2]
        c22 = A[0, 0] * A[1, 1] - A[0, 1] * A[0, 1]
        h = (c00 * b[0] + c01 * b[1] + c02 * b[2]) / det
        gx = (c01 * b[0] + c11 * b[1] + c12 * b[2]) / det
        gy = (c02 * b[0] + c12 * b[1] + c22 * b[2]) / det
        if gx * gx + gy * gy > max_slope * max_slope:
            continue
        ss = 0.0
        sw = 0.0
        for t in range(k):
            w = nb[t, 4]
            e = nb[t, 2] - (h + gx * nb[t, 0] + gy * nb[t, 1])
            ss += w * e * e
            sw += w
        if not ss <= rms_tol * rms_tol * sw:
            continue
        worst = 0.0
        for s in range(SECTORS):
            t = near_k[s]
            if t >= 0:
                worst = max(worst, abs(nb[t, 2] - (h + gx * nb[t, 0] + gy * nb[t, 1])))
        if worst > step_tol:
            continue
        out[c, 0] = h
        out[c, 1] = gx
        out[c, 2] = gy
    return out


@njit(cache=True)
def flag_bridged_cells(flags, is_bridge, table, verts, limit, param_bit, opt_bit, bridge_bit):
    """Flag the cells around bridged vertices: ``opt_bit`` where all 8 corners are parameters, ``bridge_bit``
    where all 8 are bridged; both on the slot of the cell's lowest corner.

    Every cell that has one of ``verts`` as a corner is looked at, some several times (the flags are OR-ed, so
    that is harmless, and cheaper than first finding the distinct cells); a vertex's 8 cells read their corners
    from its 27 neighbours' slots, looked up once (4.5x faster than 64 look-ups on a 0.1 m street tile's 700k
    bridged vertices, same flags). Serial: two cells' flags may share a
    byte's other bits with a neighbour's update, and a parallel OR could lose one.

    Parameters
    ----------
    flags : (n_slots,) uint8, in/out
    is_bridge : (n_slots,) uint8
        1 at the slots of bridged vertices.
    table : (BX, BY, BZ) int32
        Brick table.
    verts : (M, 3) int64
        The bridged vertices (lattice indices).
    limit : (3,) int64
        Cells per axis (the lattice's vertex counts - 1): cells beyond are skipped.
    param_bit, opt_bit, bridge_bit : int

    Returns
    -------
    int
        Cells that took ``bridge_bit`` here (the distinct bridged cells, when none had it before).
    """
    newly = 0
    # the slots of a vertex's 3 x 3 x 3 neighbourhood, looked up once: its 8 cells' 64 corners are 27 vertices
    near = np.empty(27, np.int64)
    for m in range(verts.shape[0]):
        vx, vy, vz = verts[m, 0], verts[m, 1], verts[m, 2]
        for a in range(3):
            for b in range(3):
                for e in range(3):
                    x, y, z = vx + a - 1, vy + b - 1, vz + e - 1
                    near[9 * a + 3 * b + e] = bounded_slot_of(table, x, y, z) if x >= 0 and y >= 0 and z >= 0 else -1
        for c in range(8):
            dx, dy, dz = c >> 2, (c >> 1) & 1, c & 1
            cx, cy, cz = vx - dx, vy - dy, vz - dz
            if cx < 0 or cy < 0 or cz < 0 or cx >= limit[0] or cy >= limit[1] or cz >= limit[2]:
                continue
            all_param = True
            all_bridge = True
            low = -1
            for k in range(8):
                # corner k of the cell is the vertex at (k - d) from this one
                s = near[9 * ((k >> 2) - dx + 1) + 3 * (((k >> 1) & 1) - dy + 1) + ((k & 1) - dz + 1)]
                if s < 0:
                    low = -1
                    break
                if k == 0:
                    low = s
                if (flags[s] & param_bit) == 0:
                    all_param = False
                if is_bridge[s] == 0:
                    all_bridge = False
            if low < 0:
                continue
            if all_param:
                flags[low] |= opt_bit
            if all_bridge:
                if (flags[low] & bridge_bit) == 0:
                    newly += 1
                flags[low] |= bridge_bit
    return newly
