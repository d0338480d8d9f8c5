"""Tiling: partition, partition-of-unity blending, welding, and closed shapes across tiles."""

import json

import numpy as np
import pytest

from tiled_gridpull.blend import TileField, blend_into, pou_weight
from tiled_gridpull.config import SolverConfig
from tiled_gridpull.errors import ConfigError
from tiled_gridpull.kernels import BRICK, PARAM
from tiled_gridpull.lattice import Lattice
from tiled_gridpull.mesh import Mesh
from tiled_gridpull.metrics import evaluate
from tiled_gridpull.partition import partition, read_tile_points
from tiled_gridpull.stitch import MeshPiece, drop_small_components, weld_pieces
from tiled_gridpull.synthetic import sample_shape, sphere
from tiled_gridpull.tile_plan import plan_tiles
from tiled_gridpull.tiled_job import reconstruct_scene
from tiled_gridpull.tiling import TilingConfig

OFFSET = np.array([500000.0, 4000000.0, 100.0])


class _Chunk:
    def __init__(self, xyz, sensor=None):
        self.xyz = xyz
        self.sensor = sensor


def test_tiling_config_validation():
    with pytest.raises(ConfigError, match="overlap"):
        TilingConfig(voxel_size=0.1, tile_size=3.2, overlap=3.2)
    with pytest.raises(ConfigError, match="voxel_size"):
        TilingConfig(voxel_size=-0.1)
    with pytest.raises(ConfigError, match="orientation"):
        TilingConfig(orientation="sideways")
    t = TilingConfig(voxel_size=0.1, tile_size=25.0, overlap=1.0)
    assert t.tile_cells % BRICK == 0 and t.overlap_cells % BRICK == 0 and t.overlap_cells * 0.1 >= 1.0 - 1e-9


def test_partition_puts_each_point_in_every_block_holding_it(tmp_path, rng):
    pts = OFFSET + rng.uniform([0, 0, 0], [30.0, 20.0, 5.0], size=(20000, 3))
    sensor = pts + np.array([0.0, 0.0, 2.0])
    tiling = TilingConfig(voxel_size=0.1, tile_size=6.4, overlap=0.8)
    plan = plan_tiles(np.stack([pts.min(0), pts.max(0)]), len(pts), tiling)
    chunks = [_Chunk(pts[i:i + 3000], sensor[i:i + 3000]) for i in range(0, len(pts), 3000)]
    specs = partition(chunks, plan, tmp_path, has_sensor=True, flush_points=5000)
    assert len(specs) == 5 * 4 * 1
    total = 0
    for spec in specs:
        xyz, sen = read_tile_points(spec)
        world = xyz.astype(np.float64) + spec.block.low_corner
        inside = np.all((pts >= spec.block.low_corner - 1e-6) & (pts <= spec.block.high_corner + 1e-6), axis=1)
        assert len(world) == inside.sum() == spec.n_points
        # tile-local float32 keeps the georeferenced points to well under a millimetre
        assert np.abs(np.sort(world[:, 0]) - np.sort(pts[inside, 0])).max() < 1e-4
        assert np.allclose(sen - xyz, [0, 0, 2.0], atol=1e-4)
        total += len(world)
    assert total > len(pts)  # points in overlaps go to several tiles


def test_partition_of_unity_weights_sum_to_one():
    T, O = 32, 8
    blocks = []
    for i in range(3):
        for j in range(3):
            lo = np.array([i * T - O, j * T - O, -O])
            blocks.append((lo, lo + T + 2 * O))
    g = np.stack(np.meshgrid(np.arange(T - 2 * O, 2 * T + 2 * O), np.arange(T, 2 * T), [16, 20], indexing="ij"),
                 -1).reshape(-1, 3)
    total = sum(pou_weight(g, lo, hi, O) for lo, hi in blocks)
    assert np.allclose(total, 1.0)


def _tile_field(index, block_lo, shape, rng, overlap):
    bcoords = np.array([[bx, by, bz] for bx in range(block_lo[0] // BRICK, (block_lo[0] + shape) // BRICK + 1)
                        for by in range(block_lo[1] // BRICK, (block_lo[1] + shape) // BRICK + 1)
                        for bz in range(0, 2)], dtype=np.int64)
    values = rng.normal(size=(len(bcoords), 512)).astype(np.float32)
    flags = np.full((len(bcoords), 512), PARAM, np.uint8)
    return TileField(index, np.asarray(block_lo), np.asarray(block_lo) + shape, bcoords, values, flags, overlap)


def test_blend_gives_identical_values_on_shared_vertices(rng):
    T, O = 32, 8
    a = _tile_field((0, 0, 0), np.array([-O, -O, 0]), T + 2 * O, rng, O)
    b = _tile_field((1, 0, 0), np.array([T - O, -O, 0]), T + 2 * O, rng, O)
    a_raw, b_raw = a.values.copy(), b.values.copy()
    a0 = TileField(a.index, a.block_lo, a.block_hi, a.brick_coords, a_raw.copy(), a.flags, O)
    b0 = TileField(b.index, b.block_lo, b.block_hi, b.brick_coords, b_raw.copy(), b.flags, O)
    blend_into(a, [b0], np.array([0, 0, 0]), np.array([T, T, 8]))
    blend_into(b, [a0], np.array([T, 0, 0]), np.array([2 * T, T, 8]))
    # the shared face x = T: both tiles hold bit-identical values
    g = np.stack(np.meshgrid([T], np.arange(0, T + 1), np.arange(0, 9), indexing="ij"), -1).reshape(-1, 3)
    va, _ = a.lookup(g)
    vb, _ = b.lookup(g)
    assert np.array_equal(va, vb)
    # deep inside a's core nothing changed
    inner = np.array([[4, 10, 3]])
    assert a.lookup(inner)[0][0] == a0.lookup(inner)[0][0]


def test_weld_pieces_by_edge_key():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    p1 = MeshPiece(v, np.array([[0, 1, 2]]), np.array([10, 11, 12]))
    p2 = MeshPiece(v + [0, 0, 0], np.array([[0, 2, 1]]), np.array([11, 12, -1]))
    m = weld_pieces([p1, p2])
    assert m.n_vertices == 4 and m.n_faces == 2


@pytest.fixture(scope="module")
def sphere_job(tmp_path_factory):
    d = tmp_path_factory.mktemp("sphere_tiles")
    gt = sphere(radius=0.5)
    pts, _ = sample_shape(gt, 40000, seed=3)
    np.save(d / "pts.npy", pts + OFFSET)
    cell = 1.0 / 48
    solver = SolverConfig(m1=3, m2=6, refine_m2=6, iterations=300, queries=20000)
    tiled = TilingConfig(voxel_size=cell, tile_size=24 * cell, overlap=8 * cell, trim_distance=0,
                         orientation="outward", min_points=50)
    one = TilingConfig(voxel_size=cell, tile_size=64 * cell, overlap=8 * cell, trim_distance=0,
                       orientation="outward", min_points=50)
    m8 = reconstruct_scene([str(d / "pts.npy")], d / "tiled.ply", tiled, solver, d / "job8")
    m1 = reconstruct_scene([str(d / "pts.npy")], d / "one.ply", one, solver, d / "job1")
    return gt, m8, m1, cell, d


@pytest.mark.slow
def test_closed_shape_across_8_tiles_is_watertight_manifold(sphere_job):
    gt, m8, m1, cell, d = sphere_job
    assert len(m8.metadata["tile_summaries"]) == 8
    assert all(s["status"] == "solved" for s in m8.metadata["tile_summaries"])
    topo = m8.topology
    assert topo.boundary_edges == 0 and topo.nonmanifold_edges == 0 and topo.inconsistent_edges == 0
    assert m8.is_manifold_solid()
    assert m8.signed_volume() > 0  # outward orientation


@pytest.mark.slow
def test_tiled_matches_single_tile(sphere_job):
    gt, m8, m1, cell, d = sphere_job
    assert len(m1.metadata["tile_summaries"]) == 1
    r = evaluate(Mesh(m8.vertices - OFFSET, m8.faces), Mesh(m1.vertices - OFFSET, m1.faces), 50000)
    assert r["chamfer_l1_exact"] < 0.25 * cell
    r_gt = evaluate(Mesh(m8.vertices - OFFSET, m8.faces), gt, 50000)
    assert r_gt["chamfer_l1_exact"] < 0.25 * cell


@pytest.mark.slow
def test_scene_outputs_are_self_describing(sphere_job):
    gt, m8, m1, cell, d = sphere_job
    side = json.loads((d / "tiled.json").read_text())
    for key in ("lattice", "tiling", "config", "version", "timings_s", "tile_summaries", "mesh"):
        assert key in side
    assert Lattice.from_dict(side["lattice"]).cell_size == pytest.approx(cell)
    mem = side["memory_mb"]
    tile_peaks = [t["peak_rss_mb"] for t in side["tile_summaries"]]
    assert mem["max_solve_task_peak_rss"] == max(tile_peaks) and 50 < max(tile_peaks) < 4000
    assert mem["driver_peak_rss"] > 50


def _blend_reference(own, others, region_lo, region_hi):
    """The NumPy blend the kernel replaced (kept here as the reference it must match bit for bit)."""
    tiles = sorted([own, *others], key=lambda t: tuple(t.index))
    g_all = (own.brick_coords[:, None, :] * BRICK
             + np.indices((BRICK, BRICK, BRICK)).reshape(3, -1).T[None]).reshape(-1, 3)
    param = (own.flags.reshape(-1) & PARAM) != 0
    in_region = np.all((g_all >= region_lo) & (g_all <= region_hi), axis=1)
    near = np.zeros(len(g_all), bool)
    for t in others:
        near |= np.all((g_all >= t.block_lo) & (g_all <= t.block_hi), axis=1)
    sel = np.flatnonzero(param & in_region & near)
    if len(sel) == 0:
        return 0
    g = g_all[sel]
    num = np.zeros(len(sel), np.float64)
    den = np.zeros(len(sel), np.float64)
    for t in tiles:
        if t is own:
            vals, mask = own.values.reshape(-1)[sel], np.ones(len(sel), bool)
        else:
            vals, mask = t.lookup(g)
        w = pou_weight(g, t.block_lo, t.block_hi, t.overlap) * mask
        num += w * vals.astype(np.float64)
        den += w
    blended = (num / np.where(den > 0, den, 1.0)).astype(np.float32)
    flat = own.values.reshape(-1)
    changed = int(np.count_nonzero(flat[sel] != blended))
    flat[sel] = blended
    return changed


@pytest.mark.parametrize("overlap", [8, 0])
def test_blend_kernel_matches_the_numpy_blend_bit_for_bit(rng, overlap):
    """3 x 3 tiles with sparse bricks (some missing) and partial parameter flags: every tile's blended field equals
    the NumPy reference's, bit for bit, and the changed counts agree."""
    T, O = 32, 8
    fields = {}
    for i in range(3):
        for j in range(3):
            f = _tile_field((i, j, 0), np.array([i * T - O, j * T - O, 0]), T + 2 * O, rng, overlap)
            keep = rng.random(len(f.brick_coords)) > 0.15  # holes in the band
            flags = np.where(rng.random(f.flags[keep].shape) < 0.8, PARAM, 0).astype(np.uint8)
            fields[(i, j)] = TileField(f.index, f.block_lo, f.block_hi, f.brick_coords[keep],
                                       f.values[keep].copy(), flags, overlap)
    for (i, j), own in fields.items():
        others = [t for k, t in fields.items() if k != (i, j)]
        region_lo = np.array([i * T, j * T, 0])
        region_hi = region_lo + np.array([T, T, 12])

        def copy(t):
            return TileField(t.index, t.block_lo, t.block_hi, t.brick_coords, t.values.copy(), t.flags, t.overlap)

        ref, new = copy(own), copy(own)
        n_ref = _blend_reference(ref, [copy(t) for t in others], region_lo, region_hi)
        n_new = blend_into(new, [copy(t) for t in others], region_lo, region_hi)
        assert n_new == n_ref and n_ref > 0
        assert np.array_equal(new.values.view(np.uint32), ref.values.view(np.uint32))


def _strip(x0: float, x1: float, key0: int, n: int = 4) -> MeshPiece:
    """A strip of ``2 n`` triangles from x0 to x1 (0.2 wide in y); border vertices keyed by their x index."""
    xs = np.linspace(x0, x1, n + 1)
    v = np.array([(x, y, 0.0) for x in xs for y in (0.0, 0.2)])
    f = np.array([t for i in range(n) for t in ((2 * i, 2 * i + 2, 2 * i + 1), (2 * i + 1, 2 * i + 2, 2 * i + 3))])
    keys = np.arange(len(v)) + key0
    return MeshPiece(v, f, keys, attributes={"intensity": np.arange(len(v), dtype=np.float32) + key0})


def test_small_components_are_judged_whole_across_tiles():
    """A strip cut by a tile border, 1.0 of it in each tile, is 2.0 long: kept at a minimum of 1.5 (either half
    alone would be dropped); a speck 0.1 across in the second tile goes, with its vertices, and what is left of
    the piece keeps its keys and attributes aligned."""
    a = _strip(0.0, 1.0, 0)
    b = _strip(1.0, 2.0, 8)  # its first two vertices are a's last two (keys 8 and 9)
    speck = MeshPiece(np.array([[1.5, 1.0, 0.0], [1.6, 1.0, 0.0], [1.5, 1.1, 0.0]]), np.array([[0, 1, 2]]),
                      np.array([-1, -2, -3]), attributes={"intensity": np.full(3, 99.0, np.float32)})
    with_speck = MeshPiece(np.concatenate([speck.vertices, b.vertices]), np.concatenate([speck.faces, b.faces + 3]),
                           np.concatenate([speck.keys, b.keys]),
                           attributes={"intensity": np.concatenate([speck.attributes["intensity"],
                                                                    b.attributes["intensity"]])})
    kept, removed = drop_small_components([a, with_speck], 1.5)
    assert removed == 1 and kept[0] is a
    assert len(kept[1].faces) == len(b.faces)
    assert np.array_equal(kept[1].vertices, b.vertices) and np.array_equal(kept[1].keys, b.keys)
    assert np.array_equal(kept[1].attributes["intensity"], b.attributes["intensity"])
    assert np.array_equal(kept[1].vertices[kept[1].faces], b.vertices[b.faces])
    whole = weld_pieces(kept)
    assert whole.n_faces == 16 and len(np.unique(whole.components())) == 1
    # a minimum over the whole strip's length drops it too; 0 keeps everything as given
    assert drop_small_components([a, with_speck], 2.5)[1] == 2
    same, none = drop_small_components([a, with_speck], 0.0)
    assert none == 0 and same[0] is a and same[1] is with_speck
