"""Bridging the ground between scan lines (:mod:`tiled_gridpull.bridge`): what is bridged, how exactly, what is
never bridged, and that a tiled job's bridges weld across tile borders and do not depend on the tiling."""

import numpy as np
import pytest

from tiled_gridpull.band import build_band
from tiled_gridpull.bridge import BRIDGE, BridgeRule, bridge_field, bridged_cells, unique_rows
from tiled_gridpull.field import Field
from tiled_gridpull.isosurface import extract_mesh
from tiled_gridpull.kernels import CELL_OPT, PARAM
from tiled_gridpull.lattice import Lattice
from tiled_gridpull.mesh_repair import boundary_edges
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


@pytest.mark.parametrize("n, lo, hi", [(0, 0, 1), (1, 5, 6), (50, -1, 3), (20000, -1, 300), (7, -(1 << 40), 1 << 40)])
def test_unique_rows_is_numpys_unique_over_rows(n, lo, hi):
    # the bridge's bricks come in this order (it fixes the field file's bytes): the same rows, the same order
    rows = np.random.default_rng(n).integers(lo, hi, (n, 3))
    got = unique_rows(rows)
    assert got.dtype == np.int64 and got.shape[1] == 3
    np.testing.assert_array_equal(got, np.unique(rows, axis=0).reshape(-1, 3))


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


def _sensor(pts: np.ndarray) -> np.ndarray:
    """Sensor origins of ``pts`` seen as rings from afar: a scanner 1.73 m above the plane, 30 m before y = 0."""
    return np.broadcast_to([3.0, -30.0, _height(3.0, -30.0) + 1.73], pts.shape)


def test_with_the_sensor_known_scan_lines_are_bridged_onto_their_plane_alike():
    pts = _scan_lines(1.5)
    plain, _ = bridge_field(_exact_field(pts), pts, BridgeRule(radius=24))
    seen, info = bridge_field(_exact_field(pts), pts, BridgeRule(radius=24), _sensor(pts))
    assert info["bridged_columns"] > 0
    b = _mesh(seen, pts, bridge=True)
    assert b.topology.components == 1 and b.topology.euler == 1
    n = np.linalg.norm([SLOPE[0], SLOPE[1], 1.0])
    v = b.vertices
    assert np.abs(v[:, 2] - _height(v[:, 0], v[:, 1])).max() / n < 0.02 * CELL
    # every gap between the first and last line closes, as without the sensor (beyond the last line, where
    # no ring lies beyond, the solved strip ends the surface)
    for m in (_mesh(plain, pts, bridge=True), b):
        inner = (m.vertices[:, 0] > 1.0) & (m.vertices[:, 0] < 5.5)
        assert np.diff(np.sort(m.vertices[inner, 1])).max() < 2 * CELL


@pytest.mark.parametrize("sensor", [False, True])
@pytest.mark.parametrize("case", ["kerb", "one_side", "too_wide", "off"])
def test_what_is_never_bridged(case, sensor):
    """Also with the sensor known, whose rule lets wider empty angles and rougher planes through."""
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
    out, info = bridge_field(fld, pts, rule, _sensor(pts) if sensor else None)
    if case == "kerb":
        # gaps between flat lines away from the step are bridged (lines at y = 0.5 and 1.7 m), never the one
        # across the step (lines at y = 2.9 and 4.1 m)
        cells = out.band.slot_positions()[(out.band.flags.reshape(-1) & BRIDGE) != 0]
        y = (cells[:, 1] + 0.5) * CELL
        assert np.any((y > 0.8) & (y < 1.4)) and not np.any((y > 3.1) & (y < 3.9))
    else:
        assert info == {"bridged_columns": 0, "bridged_cells": 0} and out is fld


@pytest.mark.slow
@pytest.mark.parametrize("sensor", [False, True])
def test_a_tiled_job_bridges_alike_whatever_the_tiling_and_welds_across_tiles(tmp_path, sensor):
    """Scan lines 1.5 m apart on a sloping plane, meshed by two tilings whose borders fall elsewhere: in each mesh
    the lines' span is one disc (no gap left open, no crack at a tile border; scraps of the solved field curl at
    the data's outer edge, where nothing is bridged), on the plane, and the two agree. With sensor origins (LAS
    with GPS time and a trajectory: a scanner 30 m before the first line) the same."""
    from tiled_gridpull.config import SolverConfig
    from tiled_gridpull.metrics import point_to_mesh, sample_surface
    from tiled_gridpull.tiled_job import reconstruct_scene
    from tiled_gridpull.tiling import TilingConfig

    pts = []
    for y in np.arange(0.3, 12.0, 1.5):
        x = np.arange(0.3, 12.0, 0.02)
        pts.append(np.stack([x, np.full_like(x, y), _height(x, y)], axis=1))
    pts = np.concatenate(pts)
    src, traj = tmp_path / "lines.npy", None
    if sensor:
        from tiled_gridpull.synthetic.lidar_files import write_las, write_trajectory

        src, traj = tmp_path / "lines.las", tmp_path / "trajectory.csv"
        write_las(src, pts, gps_time=np.full(len(pts), 100.0))
        write_trajectory(traj, np.array([99.0, 101.0]), np.array([[6.0, -30.0, _height(6.0, -30.0) + 1.73]] * 2))
    else:
        np.save(src, pts)
    solver = SolverConfig(m2=8, refine_m2=6, coarse_iterations=100, iterations=100, queries=20000)
    meshes = {}
    for tile in (6.4, 9.6):
        tiling = TilingConfig(voxel_size=CELL, tile_size=tile, overlap=3.2, trim_distance=3.0, bridge=24)
        meshes[tile] = reconstruct_scene([str(src)], tmp_path / f"m{tile}.ply", tiling, solver, tmp_path / f"job{tile}",
                                         trajectory=traj)
        assert meshes[tile].metadata["tiles"]["solved"] > 1
    n = np.linalg.norm([SLOPE[0], SLOPE[1], 1.0])
    for tile, m in meshes.items():
        c = m.vertices[m.faces].mean(axis=1)
        inner_faces = (c[:, 0] > 1) & (c[:, 0] < 11) & (c[:, 1] > 1) & (c[:, 1] < 10.8)
        labels = m.components()
        main = np.bincount(labels).argmax()
        # the lines' span is one piece (small closed bubbles of a lone line's solved field may float beside it)
        assert np.mean(labels[inner_faces] == main) > 0.98, tile
        # no hole and no crack inside: every boundary edge lies at the data's outer edge (with sensor origins a
        # few lie on the last line itself, y = 10.8 m, where the bridge meets that line's strip: the last ring has
        # nothing beyond it, so the shadow test leaves some of its columns to the solved field)
        be = m.vertices[boundary_edges(m)].mean(axis=1)
        top = 10.5 if sensor else 10.8
        assert not np.any((be[:, 0] > 1) & (be[:, 0] < 11) & (be[:, 1] > 1) & (be[:, 1] < top)), tile
        # between the lines (over 0.3 m from each, where the solved field has handed over) the bridge lies on
        # the plane; beside the lines the solved field of a lone scan line (no slope across itself) is less sure
        v = m.vertices
        d_line = np.abs((v[:, 1] - 0.3 + 0.75) % 1.5 - 0.75)
        inner = (v[:, 0] > 1) & (v[:, 0] < 11) & (v[:, 1] > 1) & (v[:, 1] < 10.8)
        err = np.abs(v[:, 2] - _height(v[:, 0], v[:, 1])) / n
        assert np.median(err[inner & (d_line > 0.3)]) < 0.05 * CELL, tile
        assert np.mean(err[inner]) < CELL, tile
    a, b = meshes[6.4], meshes[9.6]
    # the bridges (between the lines, where the solved field has handed over; beside the lines and at the outer
    # edge the solved field of a lone line is the tiling's, alike only roughly)
    pa, _ = sample_surface(a, 20_000, seed=0)
    pb, _ = sample_surface(b, 20_000, seed=1)
    def _between(p):
        return ((p[:, 0] > 1) & (p[:, 0] < 11) & (p[:, 1] > 1) & (p[:, 1] < 10.8)
                & (np.abs((p[:, 1] - 0.3 + 0.75) % 1.5 - 0.75) > 0.3))

    def bridged(p):
        return p[_between(p)]

    pa, pb = bridged(pa), bridged(pb)
    assert 0.5 * (np.median(point_to_mesh(pa, b)[0]) + np.median(point_to_mesh(pb, a)[0])) < 0.01 * CELL
    inner_area = []
    for m in (a, b):
        c = m.vertices[m.faces].mean(axis=1)
        inner_area.append(m.face_normals()[1][_between(c)].sum())
    assert abs(inner_area[0] - inner_area[1]) < 0.01 * inner_area[0]

