"""Bridging the gaps a scanner leaves between its scan lines on the ground.

A LiDAR on a car samples the road in rings that spread apart with range: along a ring the points are
centimetres apart, between rings metres. The solved band holds a field only within a few cells of the points,
so the road comes out as stripes. Where the ground points *around* a gap lie on one plane, the gap is a
sampling gap, not a hole, and this module extends the field across it: every lattice column that is surrounded
by ground samples (the lowest layer of points in each small bin) within ``radius`` cells, all on one gently
sloping plane (no kerb, car or wall within
reach), gets the signed distance to that plane on the few vertices around it. Marching cubes then draws the
road across the gap, welded to the solved surface at its edges, and the trim keeps those faces (their cells
carry the ``BRIDGE`` flag).

What is never bridged: a gap with points on one side only (a building's shadow, the scan's outer edge, water
with no returns wider than ``2 * radius``), a gap across a height step (the plane fit's residuals), steep
ground, and anything farther than ``radius`` from the points. Where the points' sensor origins are known
(a trajectory, KITTI), a gap must also have ground beyond it as the sensor sees it: the next ring lies there,
while the ground in the shadow of a car, a box or a wall is hidden for as long as the shadow, however near
its sides. With the sensor known, samples on things standing on the ground (cars, bushes) also leave the plane
fits, and ground the sensor could not have seen stays open: behind or under a thing, where a plane would only
graze the line of sight, and where a beam passed under the plane (across a ditch). Without sensor origins each
column is decided from the points within ``radius`` of it alone, and with ``radius`` at most a tile's overlap
every tiling decides it the same way; with them it also reads the points up to ``shadow_reach`` (48 cells) away,
and a beam under the plane opens a gap up to twice that far from its point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .band import Band, dense_brick_table, vertex_slots
from .field import Field
from .kernels import BRICK, BRICK_VOLUME, CELL_OPT, PARAM
from .kernels import bridge as kb
from .kernels.band import brick_neighbors
from .nearest import distances_to_cloud

__all__ = ["BRIDGE", "BridgeRule", "bridge_columns", "bridge_field", "bridged_cells"]

# Cell flag: all 8 corners of the cell hold bridged values; the trim keeps faces drawn there.
BRIDGE = 16


@dataclass(frozen=True)
class BridgeRule:
    """When a gap between ground samples is bridged (lengths in cells).

    Attributes
    ----------
    radius : float
        Ground samples farther than this from a column do not count for it: gaps up to about twice this wide
        are closed. 0 turns bridging off.
    pixel : float
        Ground samples are thinned to one per ``pixel`` x ``pixel`` cells.
    skip : float
        Columns with ground samples this close on every side are densely sampled and keep the solved field alone
        (beside a lone scan line, whose field has no slope across itself, the plane takes over).
    max_gap_deg : float
        Widest empty angle around a column (degrees) that still counts as surrounded by samples.
    rms_tol, step_tol : float
        Largest RMS residual of the local plane fit, and largest residual of the nearest sample in any
        direction: beyond them the neighbourhood holds a height step and the gap stays open.
    max_slope : float
        Steepest ground bridged (rise over run).
    layer : float
        The ground of each bin is its lowest layer of points, this thick.
    blend_from, blend_to : float
        Distance from the nearest point (any point) over which the solved field hands over to the bridge.
    half_height : int
        Vertices bridged above and below the plane in each column: more than the trim distance, so that the
        solved field's own stray zero crossings near a lone scan line (small bubbles above and below it) are
        replaced, not kept beside the bridge.
    open_width : int
        Bridged columns are opened (eroded, then dilated) by this many columns: specks and one-column spurs,
        which would be pieces and ragged edges of their own, go.
    beyond_deg : float
        With sensor origins: a column is bridged only where a ground sample within ``radius`` lies beyond it as
        the sensor of its nearest sample sees it, within this angle of the line of sight (0: no such test).
    sensor_max_gap_deg, sensor_rms_tol : float
        ``max_gap_deg`` and ``rms_tol`` where the ``beyond_deg`` test applies: it keeps shadows open, which the
        surround test and a tight plane fit did only in part, so both may let more sampling gaps close (beside
        a shadow's edge, on gently curved ground); the step test still keeps kerbs and walls' feet open.
    object_width, object_tol : float
        With sensor origins: a ground sample more than ``object_tol`` above the ground opened over a window
        ``object_width`` wide (:func:`~tiled_gridpull.kernels.bridge.object_bins`) stands on a thing narrower
        than the window (a car, a bush, a hedge): it leaves the plane fits and the beyond test, which it would
        otherwise lift, tilt and refuse. Levels wider than the window (both sides of a kerb, a terrace) stay
        ground, so the step test still sees them. The ground under and behind such a thing is left to the
        ``shadow_tol`` test below. 0: every sample counts.
    shadow_tol, shadow_reach, min_facing : float
        With sensor origins: a column is not bridged where the line of sight from its sensor to the bridged
        ground passes, within ``shadow_reach`` cells of the column, under the highest point of a bin by more than
        ``shadow_tol`` (under any point of a bin holding a thing standing on the ground), or meets
        the plane less than ``min_facing`` times as squarely as level ground (sines) or from below
        (:func:`~tiled_gridpull.kernels.bridge.hidden_from_sensor`): the ground there was hidden, not missed
        between rings (below a drop-off, a plane from its edge to the low ground beyond is a ramp no sensor on
        the high side could have seen).
    pierce_tol, pierce_beams, pierce_skip : float, int, float
        With sensor origins: a bridged column that ``pierce_beams`` beams passed more than ``pierce_tol`` under
        is no sampling gap: the ground there is lower than the plane, as across a ditch whose far wall the beams
        reached (:func:`~tiled_gridpull.kernels.bridge.pierced_columns`). Each beam is followed back
        ``shadow_reach`` cells from its point, but not over its last ``pierce_skip`` cells, where it meets its own
        ground at a grazing angle, within the plane fit's error of it. The stretch of empty bins the column lies
        in along that beam stays open as a whole (:func:`~tiled_gridpull.kernels.bridge.clear_pierced_gaps`):
        its near part lies in the near rim's shadow, where no beam could pass under the plane. Two beams, not
        one: single noisy returns 12-14 cm low cut correct roads at 0.1 m cells. 0 beams: no such test.
    """

    radius: float = 24.0
    pixel: float = 2.0
    skip: float = 4.0
    max_gap_deg: float = 120.0
    rms_tol: float = 0.25
    step_tol: float = 1.5
    max_slope: float = 0.6
    layer: float = 1.0
    blend_from: float = 1.5
    blend_to: float = 3.0
    half_height: int = 6
    open_width: int = 1
    beyond_deg: float = 15.0
    sensor_max_gap_deg: float = 150.0
    sensor_rms_tol: float = 0.5
    object_width: float = 24.0
    object_tol: float = 1.5
    shadow_tol: float = 1.0
    shadow_reach: float = 48.0
    min_facing: float = 0.35
    pierce_tol: float = 1.0
    pierce_beams: int = 2
    pierce_skip: float = 2.0


def _opened(mask: np.ndarray, width: int) -> np.ndarray:
    """Morphological opening of a 2D mask by a square of side ``2 width + 1`` (outside the mask counts as set,
    so the tile's edge does not erode what a neighbour's overlap continues)."""
    out = mask
    for grow in (False, True):
        for _ in range(width):
            pad = np.pad(out, 1, constant_values=not grow)
            acc = pad[1:-1, 1:-1].copy()
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    view = pad[1 + dx:pad.shape[0] - 1 + dx, 1 + dy:pad.shape[1] - 1 + dy]
                    acc = (acc | view) if grow else (acc & view)
            out = acc
    return out


def unique_rows(rows: np.ndarray) -> np.ndarray:
    """The distinct rows of an integer array, sorted lexicographically: ``np.unique(rows, axis=0)``, the same
    array, several times faster.

    ``np.unique(axis=0)`` sorts the rows as structured records, compared field by field: on the bricks of a dense
    tile's bridged vertices (and, before :func:`~tiled_gridpull.kernels.bridge.flag_bridged_cells`, the 8 cells
    around each, 16 % of the demo's densest tile) that is several times a plain sort. Each row is packed into one
    int64 instead (its columns shifted to start at 0, mixed radix), whose order is the rows' lexicographic order,
    and unpacked after a plain 1-D sort.

    Parameters
    ----------
    rows : (M, 3) integer
        Any values whose ranges' product fits in an int64 (lattice indices of a tile, negative ones included).

    Returns
    -------
    (K, 3) int64
        Sorted by column 0, then 1, then 2.
    """
    rows = np.asarray(rows, np.int64)
    if len(rows) == 0:
        return np.empty((0, rows.shape[1]), np.int64)
    lo = rows.min(axis=0)
    span = rows.max(axis=0) - lo + 1
    if np.prod(span.astype(np.float64)) >= 2.0 ** 62:  # would overflow: the slow path
        return np.unique(rows, axis=0)
    key = rows[:, 0] - lo[0]
    for c in range(1, rows.shape[1]):
        key = key * span[c] + (rows[:, c] - lo[c])
    # sorted and compared by hand: numpy 2.4's np.unique took 60x a plain sort on 2M int64 keys (7.4 s vs 0.11 s)
    key = np.sort(key)
    key = key[np.r_[True, key[1:] != key[:-1]]]
    out = np.empty((len(key), rows.shape[1]), np.int64)
    for c in range(rows.shape[1] - 1, 0, -1):
        key, out[:, c] = np.divmod(key, span[c])
    out[:, 0] = key
    return out + lo


def bridged_cells(fld: Field, cells: np.ndarray) -> np.ndarray:
    """Whether each cell (M, 3) int (lowest corner, block index) carries the ``BRIDGE`` flag."""
    slot = vertex_slots(fld.band.brick_table, cells)
    ok = slot >= 0
    out = np.zeros(len(slot), bool)
    out[ok] = (fld.band.flags.reshape(-1)[slot[ok]] & BRIDGE) != 0
    return out


def bridge_columns(cells: np.ndarray, X: int, Y: int, rule: BridgeRule,
                   sensor: np.ndarray | None = None) -> np.ndarray:
    """Which lattice columns are bridged, at what height and slope.

    Parameters
    ----------
    cells : (N, 3) float64
        The tile's points in cells of its lattice (block-local coordinates).
    X, Y : int
        Lattice columns per axis.
    rule : BridgeRule
    sensor : (N, 3) float64, optional
        Each point's sensor origin, in cells of the same lattice.

    Returns
    -------
    (X * Y, 3) float64
        Per column (x-major, as ``np.meshgrid(..., indexing="ij")``): the plane's height at the column (cells)
        and its slopes dz/dx, dz/dy; NaN rows where the column is not bridged.
    """
    nx, ny = int(math.ceil(X / rule.pixel)), int(math.ceil(Y / rule.pixel))
    # contiguous columns, once: every kernel below reads them
    x, y, z = (np.ascontiguousarray(cells[:, a], np.float64) for a in range(3))
    rep = kb.bin_ground(x, y, z, float(rule.pixel), nx, ny, float(rule.layer))
    ii, jj = np.meshgrid(np.arange(X), np.arange(Y), indexing="ij")
    cols = np.stack([ii.ravel(), jj.ravel()], axis=1).astype(np.float64)
    seen = sensor is not None and rule.beyond_deg > 0
    max_gap = int(math.floor((rule.sensor_max_gap_deg if seen else rule.max_gap_deg) / (360.0 / kb.SECTORS)))
    rms_tol = rule.sensor_rms_tol if seen else rule.rms_tol
    if seen:
        sx, sy, sz = (np.ascontiguousarray(sensor[:, a], np.float64) for a in range(3))
        seen_from = kb.bin_sensor(x, y, z, sx, sy, sz, float(rule.pixel), nx, ny, float(rule.layer))
        far_cos = math.cos(math.radians(rule.beyond_deg))
    else:
        seen_from, far_cos = np.full((nx, ny, 3), np.nan), 2.0
    objects = seen and rule.object_width > 0
    if objects:
        # things standing on the ground leave the ground samples (a car's bin read its lowest layer half a metre to
        # two metres above the road, and refused the plane fit of every column that reached it)
        # a window wider than the tile is the whole tile (and a huge setting no huge raster)
        half = max(1, min(int(math.ceil(min(rule.object_width, 4.0 * (X + Y)) / (2.0 * rule.pixel))), nx + ny))
        thing = kb.object_bins(np.ascontiguousarray(rep[..., 2]), half, float(rule.object_tol))
        rep = rep.copy()
        rep[thing] = np.nan  # so too for the beyond test and the sensor of each column (both read samples only)
    fit = kb.fit_columns(rep, float(rule.pixel), cols, float(rule.radius), float(rule.skip), max_gap,
                         float(rms_tol), float(rule.step_tol), float(rule.max_slope), seen_from, far_cos)
    if seen:
        top = kb.bin_top(x, y, z, float(rule.pixel), nx, ny)
        if not objects:
            thing = np.zeros((nx, ny), np.bool_)
        hidden = kb.hidden_from_sensor(cols, fit, rep, seen_from, top, thing, float(rule.pixel), float(rule.radius),
                                       float(rule.shadow_reach), float(rule.shadow_tol), float(rule.min_facing))
        fit[hidden] = np.nan
    mask = np.isfinite(fit[:, 0]).reshape(X, Y)
    if seen and rule.pierce_beams > 0:
        plane = fit.reshape(X, Y, 3)
        count, along = kb.pierced_columns(x, y, z, sx, sy, sz, *(np.ascontiguousarray(plane[..., a]) for a in range(3)),
                                          kb.bin_low(x, y, z, float(rule.pixel), nx, ny), float(rule.pixel),
                                          float(rule.layer), float(rule.pierce_skip), float(rule.shadow_reach),
                                          float(rule.pierce_tol))
        mask = kb.clear_pierced_gaps(mask, count, along, int(rule.pierce_beams), top, float(rule.pixel),
                                     float(rule.shadow_reach))
    if rule.open_width > 0:
        mask = _opened(mask, rule.open_width)
    fit[~mask.reshape(-1)] = np.nan
    return fit


def bridge_field(fld: Field, points: np.ndarray, rule: BridgeRule,
                 sensor: np.ndarray | None = None) -> tuple[Field, dict]:
    """The field with the ground's sampling gaps bridged.

    Parameters
    ----------
    fld : Field
        A solved signed field (values in cells, outside up) on a lattice in the points' frame.
    points : (N, 3) float64
        The tile's points (world units).
    rule : BridgeRule
    sensor : (N, 3) float, optional
        Each point's sensor origin, same frame: shadows stay open (``rule.beyond_deg``).

    Returns
    -------
    Field
        A new field: bricks added where the bridge needs them, bridged vertices made parameters, their cells
        optimised and flagged ``BRIDGE``.
    dict
        ``bridged_columns`` and ``bridged_cells``.
    """
    band = fld.band
    lat = band.lattice
    if rule.radius <= 0 or len(points) == 0:
        return fld, {"bridged_columns": 0, "bridged_cells": 0}
    X, Y, Z = (int(v) for v in lat.shape)
    cells = (np.asarray(points, np.float64) - np.asarray(lat.origin, np.float64)) / lat.cell_size
    sc = None
    if sensor is not None:
        # one float64 column at a time: a tile's sensor origins come as float32 (N, 3)
        sc = np.stack([(np.asarray(sensor[:, a], np.float64) - float(lat.origin[a])) / lat.cell_size
                       for a in range(3)], axis=1)
    fit = bridge_columns(cells, X, Y, rule, sc)
    cols = np.stack([c.ravel() for c in np.meshgrid(np.arange(X), np.arange(Y), indexing="ij")], axis=1)
    hit = np.flatnonzero(np.isfinite(fit[:, 0]))
    if len(hit) == 0:
        return fld, {"bridged_columns": 0, "bridged_cells": 0}
    h, gx, gy = fit[hit, 0], fit[hit, 1], fit[hit, 2]
    nz = 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)
    ks = np.floor(h)[:, None].astype(np.int64) + np.arange(-rule.half_height + 1, rule.half_height + 1)[None]
    col_xy = cols[hit].astype(np.int64)
    verts = np.concatenate([np.repeat(col_xy, ks.shape[1], axis=0), ks.reshape(-1, 1)], axis=1)
    plane = ((ks - h[:, None]) * nz[:, None]).reshape(-1)
    inside = (verts[:, 2] >= 0) & (verts[:, 2] < Z)
    verts, plane = verts[inside], plane[inside]
    # hand over from the solved field near the points to the plane beyond them (measured: taking the plane up to
    # the ground points themselves moved a KITTI frame's held-out points 4-11 % farther from the mesh)
    dist = distances_to_cloud(verts * lat.cell_size + np.asarray(lat.origin, np.float64), points,
                              rule.blend_to * lat.cell_size) / lat.cell_size
    w = np.clip((dist - rule.blend_from) / (rule.blend_to - rule.blend_from), 0.0, 1.0)
    w[~np.isfinite(dist)] = 1.0

    # bricks: the band's, then those only the bridge reaches
    coords = band.brick_coords.astype(np.int64)
    need = unique_rows(verts // BRICK)
    bshape = band.brick_table.shape
    have = band.brick_table[need[:, 0], need[:, 1], need[:, 2]] >= 0
    new = need[~have]
    coords = np.concatenate([coords, new]) if len(new) else coords
    values = np.concatenate([fld.values, np.zeros((len(new), BRICK_VOLUME), np.float32)])
    flags = np.concatenate([band.flags, np.zeros((len(new), BRICK_VOLUME), np.uint8)])
    table = dense_brick_table(bshape, coords.astype(np.int32))
    flat_v = values.reshape(-1)
    flat_f = flags.reshape(-1)

    # every vertex and cell corner below lies on the lattice: only an absent brick gives -1
    sv = vertex_slots(table, verts)
    solved = (flat_f[sv] & PARAM) != 0
    mixed = np.where(solved, (1.0 - w) * flat_v[sv] + w * plane, plane)
    flat_v[sv] = mixed.astype(np.float32)
    flat_f[sv] |= PARAM
    is_bridge = np.zeros(len(flat_v), np.uint8)
    is_bridge[sv] = 1

    # cells touching a bridged vertex: optimised when all 8 corners are parameters, bridged when all 8 are bridged
    n_bridged = kb.flag_bridged_cells(flat_f, is_bridge, table, np.ascontiguousarray(verts, np.int64),
                                      np.asarray([X - 1, Y - 1, Z - 1], np.int64), PARAM, CELL_OPT, BRIDGE)
    coords32 = coords.astype(np.int32)
    new_band = Band(lat, band.m1, band.m2, coords32, table, brick_neighbors(coords32, table), flags,
                    dict(band.stats))
    info = {"bridged_columns": int(len(hit)), "bridged_cells": int(n_bridged)}
    return Field(new_band, values, fld.signed, dict(fld.info)), info
