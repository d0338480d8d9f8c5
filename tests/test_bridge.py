"""Bridging the ground between scan lines (:mod:`tiled_gridpull.bridge`): what is bridged, how exactly, what is
never bridged, and that a tiled job's bridges weld across tile borders and do not depend on the tiling."""

import numpy as np
import pytest

from tiled_gridpull.band import build_band
from tiled_gridpull.bridge import BRIDGE, BridgeRule, bridge_field, bridged_cells
from tiled_gridpull.field import Field
from tiled_gridpull.isosurface import extract_mesh
from tiled_gridpull.kernels import CELL_OPT, PARAM
from tiled_gridpull.lattice import Lattice
from tiled_gridpull.stitch import trim_faces

CELL = 0.1
SLOPE = (0.05, -0.03)


def _height(x, y):
    return 2.0 + SLOPE[0] * x + SLOPE[1] * y


def _scan_lines(spacing_y: float, lo=0.5, hi=6.0, step=0.02, step_height: float = 0.0):
    """Points on lines along x (scan rings seen from afar) every ``spacing_y`` metres on a sloping plane; the
    lines with y > 3.2 m raised by ``step_height`` (a kerb)."""
    pts = []
    for y in np.arange(lo, hi, spacing_y):
        x = np.arange(lo, hi, step)
        z = _height(x, y) + (step_height if y > 3.2 else 0.0)
        pts.append(np.stack([x, np.full_like(x, y), z], axis=1))
    return np.concatenate(pts)


def _exact_field(points: np.ndarray, step_height: float = 0.0) -> Field:
    """The band of ``points`` holding the exact signed distance to their plane (a perfect solve)."""
    lat = Lattice((0.0, 0.0, 0.0), CELL, (66, 66, 50))
    band = build_band(points / CELL, lat, 3, 8)
    v = band.slot_positions().astype(np.float64) * CELL
    n = np.array([-SLOPE[0], -SLOPE[1], 1.0])
    raised = step_height * (v[:, 1] > 3.2)
    d = (v[:, 2] - _height(v[:, 0], v[:, 1]) - raised) / np.linalg.norm(n)
    return Field(band, (d / CELL).astype(np.float32).reshape(band.n_bricks, -1))


def _mesh(fld: Field, points: np.ndarray, bridge: bool):
    mesh = extract_mesh(fld)
    keep = None
    if bridge:
        keep = bridged_cells(fld, np.floor(mesh.vertices[mesh.faces].mean(axis=1) / CELL).astype(np.int64))
    return trim_faces(mesh, None, points, 3 * CELL, keep=keep)[0]


def test_scan_lines_farther_apart_than_the_band_are_bridged_onto_their_plane():
    pts = _scan_lines(1.5)
    fld = _exact_field(pts)
    bridged, info = bridge_field(fld, pts, BridgeRule(radius=24))
    assert info["bridged_columns"] > 0 and info["bridged_cells"] > 0
    before = _mesh(fld, pts, bridge=False)
    after = _mesh(bridged, pts, bridge=True)
    # the trimmed solve leaves a strip around each line; the bridge closes the gaps between them
    assert after.topology.components == 1 < before.topology.components
    # one disc (Euler characteristic 1: no hole left between the lines), its edge the data's outline
    assert after.topology.euler == 1 and after.topology.boundary_edges < before.topology.boundary_edges
    v = after.vertices
    n = np.linalg.norm([SLOPE[0], SLOPE[1], 1.0])
    assert np.abs(v[:, 2] - _height(v[:, 0], v[:, 1])).max() / n < 0.02 * CELL
    # the bridge reaches across every gap between the first and last line
    inner = (v[:, 0] > 1.0) & (v[:, 0] < 5.5)
    ys = np.sort(v[inner, 1])
    assert np.diff(ys).max() < 2 * CELL
    # the band's own parameters near the points are kept as solved
    flags_before = fld.band.flags.reshape(-1)
    assert np.all((bridged.band.flags.reshape(-1)[:len(flags_before)] & flags_before) == flags_before)


def test_bridged_cells_are_flagged_and_optimised():
    pts = _scan_lines(1.5)
    bridged, _ = bridge_field(_exact_field(pts), pts, BridgeRule(radius=24))
    flags = bridged.band.flags
    assert np.all(flags[(flags & BRIDGE) != 0] & CELL_OPT)
    assert np.all(flags[(flags & CELL_OPT) != 0] & PARAM)


@pytest.mark.parametrize("case", ["kerb", "one_side", "too_wide", "off"])
def test_what_is_never_bridged(case):
    rule = BridgeRule(radius=24)
    if case == "kerb":
        # lines 1.2 m apart, a 0.3 m (3-cell) step between two of them: the plane fit sees the step
        pts, step = _scan_lines(1.2, step_height=0.3), 0.3
        fld = _exact_field(pts, step)
    elif case == "one_side":
        pts, step = _scan_lines(1.5, hi=0.6), 0.0
        fld = _exact_field(pts)
    elif case == "too_wide":
        # lines 5 m apart, more than twice the 2.4 m reach
        pts, step = _scan_lines(5.0, hi=5.6), 0.0
        fld = _exact_field(pts)
    else:
        pts, step = _scan_lines(1.5), 0.0
        fld = _exact_field(pts)
        rule = BridgeRule(radius=0)
    out, info = bridge_field(fld, pts, rule)
    if case == "kerb":
        # the gaps between flat lines are bridged, never the one across the step (lines at y = 2.9 and 4.1 m)
        cells = out.band.slot_positions()[(out.band.flags.reshape(-1) & BRIDGE) != 0]
        y = (cells[:, 1] + 0.5) * CELL
        assert np.any((y > 1.9) & (y < 2.6)) and not np.any((y > 3.1) & (y < 3.9))
    else:
        assert info == {"bridged_columns": 0, "bridged_cells": 0} and out is fld
