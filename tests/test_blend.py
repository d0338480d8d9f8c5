"""Blending tile fields in their overlaps (tiled_gridpull.blend and its kernel).

What blend.py promises: weights that are 0 on a block's border, 1/2 on its core's border and 1 deeper than the
overlap inside the core; a partition of unity over a regular tile grid; blended values that are the weighted mean
of the tiles holding a vertex, bit-identical in every tile that holds it; nothing changes where no other tile
holds the vertex (a tile with a missing neighbour keeps its own field there).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from tiled_gridpull.blend import TileField, blend_into, brick_table, pou_weight
from tiled_gridpull.kernels import BRICK, PARAM


def tile_grid_blocks(n_tiles, core: int, overlap: int, origin: int = 8):
    """Blocks of a regular tile grid: tile t's core is [origin + t core, origin + (t + 1) core] per axis."""
    for t in itertools.product(*[range(k) for k in n_tiles]):
        t = np.asarray(t)
        lo = origin + t * core - overlap
        hi = origin + (t + 1) * core + overlap
        yield tuple(t), lo, hi


def all_vertices(lo, hi):
    axes = [np.arange(a, b + 1) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.int64)


# ---------------------------------------------------------------------------------------------- pou_weight


@pytest.mark.parametrize("overlap", [1, 3, 4])
def test_weights_partition_unity_over_a_tile_grid(overlap):
    core = 16
    blocks = list(tile_grid_blocks((3, 2, 2), core, overlap))
    # every vertex of the grid's cores, away from the outer border of the grid (no tile beyond it)
    g = all_vertices(np.array([8 + overlap] * 3), np.array([8 + 3 * core, 8 + 2 * core, 8 + 2 * core]) - overlap)
    total = sum(pou_weight(g, lo, hi, overlap) for _, lo, hi in blocks)
    np.testing.assert_allclose(total, 1.0, rtol=0, atol=1e-12)
    # and the overlaps really overlap: some vertices have weights from two or more tiles
    n_holding = sum((pou_weight(g, lo, hi, overlap) > 0).astype(int) for _, lo, hi in blocks)
    assert n_holding.max() == 8  # a corner shared by 2 x 2 x 2 tiles
    assert n_holding.min() == 1


def test_weight_profile_zero_half_one():
    overlap, lo, hi = 4, np.array([4, 4, 4]), np.array([44, 44, 44])  # core [8, 40]
    deep = np.array([[24, 24, 24], [12, 12, 36], [12, 36, 12]])
    np.testing.assert_array_equal(pou_weight(deep, lo, hi, overlap), 1.0)
    on_block_border = np.array([[4, 24, 24], [24, 44, 24], [24, 24, 4]])
    np.testing.assert_array_equal(pou_weight(on_block_border, lo, hi, overlap), 0.0)
    on_core_border = np.array([[8, 24, 24], [24, 40, 24], [24, 24, 8]])
    np.testing.assert_array_equal(pou_weight(on_core_border, lo, hi, overlap), 0.5)
    outside = np.array([[3, 24, 24], [24, 50, 24]])
    np.testing.assert_array_equal(pou_weight(outside, lo, hi, overlap), 0.0)
    # on a corner of the core the per-axis factors multiply
    assert pou_weight(np.array([[8, 8, 8]]), lo, hi, overlap)[0] == 0.125


def test_weights_are_continuous_ramps():
    """One vertex step changes a weight by at most 1 / (2 O) (no jump at the core or block border)."""
    overlap, lo, hi = 3, np.array([0, 0, 0]), np.array([30, 30, 30])
    x = np.arange(-2, 33)
    g = np.column_stack([x, np.full_like(x, 15), np.full_like(x, 15)])
    w = pou_weight(g, lo, hi, overlap)
    assert np.abs(np.diff(w)).max() <= 1.0 / (2 * overlap) + 1e-15
    assert w.min() == 0.0 and w.max() == 1.0
    assert np.all(np.diff(w[: len(w) // 2]) >= 0) and np.all(np.diff(w[len(w) // 2:]) <= 0)


def test_no_overlap_weight_is_the_block_indicator():
    lo, hi = np.array([0, 0, 0]), np.array([8, 8, 8])
    g = np.array([[0, 0, 0], [8, 8, 8], [4, 4, 4], [9, 4, 4], [-1, 0, 0]])
    np.testing.assert_array_equal(pou_weight(g, lo, hi, 0), [1, 1, 1, 0, 0])


# ---------------------------------------------------------------------------------------------- brick_table


def test_brick_table_maps_coordinates_to_numbers():
    coords = np.array([[2, 3, 4], [3, 3, 4], [2, 5, 6]])
    lo, table = brick_table(coords, first=10)
    np.testing.assert_array_equal(lo, [2, 3, 4])
    assert table.shape == (2, 3, 3)
    for i, c in enumerate(coords):
        assert table[tuple(c - lo)] == 10 + i
    assert (table >= 0).sum() == 3
    lo, table = brick_table(np.zeros((0, 3), np.int64))
    assert table.shape == (1, 1, 1) and table[0, 0, 0] == -1 and np.array_equal(lo, [0, 0, 0])


# ---------------------------------------------------------------------------------------------- blend_into


def field(g):
    """A smooth field (cells) at global vertices g (M, 3), slope at most 0.1 per vertex step."""
    g = g.astype(np.float64)
    return 0.05 * g[:, 0] - 0.03 * g[:, 1] + 0.5 * np.sin(g[:, 2] / 10.0)


def make_tile(index, lo, hi, overlap, offset: float, param_box=None) -> TileField:
    """A tile holding every brick that meets its block; parameters where inside ``param_box`` (default: block).

    Its values are ``field + offset``: two tiles disagree by the difference of their offsets, as solved tiles do
    near their cut-off band."""
    lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
    blo, bhi = lo // BRICK, hi // BRICK
    coords = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(blo, bhi)], indexing="ij"),
                      -1).reshape(-1, 3).astype(np.int64)
    local = np.stack(np.meshgrid(*[np.arange(BRICK)] * 3, indexing="ij"), -1).reshape(-1, 3)
    g = (coords[:, None, :] * BRICK + local[None, :, :]).reshape(-1, 3)
    plo, phi = (lo, hi) if param_box is None else (np.asarray(param_box[0]), np.asarray(param_box[1]))
    is_param = np.all((g >= plo) & (g <= phi), axis=1)
    values = np.where(is_param, field(g) + offset, 0.0).astype(np.float32).reshape(-1, BRICK ** 3)
    flags = np.where(is_param, PARAM, 0).astype(np.uint8).reshape(-1, BRICK ** 3)
    return TileField(tuple(index), lo, hi, coords, values, flags, overlap)


def values_at(tile: TileField, g):
    vals, mask = tile.lookup(g)
    assert mask.all()
    return vals


# two tiles along x: cores [8, 40] and [40, 72], overlap 4; blocks [4, 44] and [36, 76]; y and z core [8, 24]
O = 4
A_LO, A_HI = [4, 4, 4], [44, 28, 28]
B_LO, B_HI = [36, 4, 4], [76, 28, 28]


def pair():
    return make_tile((0, 0, 0), A_LO, A_HI, O, +0.5), make_tile((1, 0, 0), B_LO, B_HI, O, -0.5)


def copy(t: TileField) -> TileField:
    """The solved field a neighbour sends (each tile blends with its neighbours' unblended fields)."""
    return TileField(t.index, t.block_lo, t.block_hi, t.brick_coords, t.values.copy(), t.flags.copy(), t.overlap)


def blend_pair(a: TileField, b: TileField) -> tuple[int, int]:
    sent_a, sent_b = copy(a), copy(b)
    return (blend_into(a, [sent_b], np.array(A_LO), np.array(A_HI)),
            blend_into(b, [sent_a], np.array(B_LO), np.array(B_HI)))


def test_lookup_reads_values_and_parameter_mask():
    a = make_tile((0, 0, 0), A_LO, A_HI, O, 0.0, param_box=([4, 4, 4], [20, 28, 28]))
    g = np.array([[10, 10, 10], [30, 10, 10], [200, 10, 10]])
    vals, mask = a.lookup(g)
    np.testing.assert_array_equal(mask, [True, False, False])
    assert vals[0] == np.float32(field(g[:1])[0])
    assert vals[2] == 0


def test_blended_overlap_is_bit_identical_in_both_tiles_and_the_weighted_mean():
    a, b = pair()
    a0, b0 = a.values.copy(), b.values.copy()
    changed_a, changed_b = blend_pair(a, b)
    shared = all_vertices(np.array(B_LO), np.array(A_HI))  # x in [36, 44]
    va, vb = values_at(a, shared), values_at(b, shared)
    np.testing.assert_array_equal(va, vb)  # bits, not a tolerance: marching cubes must agree on both sides
    # the weighted mean, summed in tile order in float64 then rounded once
    wa, wb = pou_weight(shared, np.array(A_LO), np.array(A_HI), O), pou_weight(shared, np.array(B_LO),
                                                                                 np.array(B_HI), O)
    f = field(shared)
    da, db = np.float32(f + 0.5).astype(np.float64), np.float32(f - 0.5).astype(np.float64)
    den = wa + wb
    expected = ((wa * da + wb * db) / np.where(den > 0, den, 1.0)).astype(np.float32)
    np.testing.assert_array_equal(va, expected)
    # on the shared core face (x = 40, deep in y and z) both weigh 1/2: the mean of the two
    mid = all_vertices(np.array([40, 12, 12]), np.array([40, 20, 20]))
    np.testing.assert_allclose(values_at(a, mid), field(mid), atol=1e-6)
    # everything outside the overlap is untouched
    assert changed_a == np.count_nonzero(a.values != a0) > 0
    assert changed_b == np.count_nonzero(b.values != b0) > 0
    only_a = all_vertices(np.array(A_LO), np.array([35, 28, 28]))
    np.testing.assert_array_equal(values_at(a, only_a), np.float32(field(only_a) + 0.5))


def test_blending_removes_the_jump_at_the_tile_border():
    """Reading each vertex from the tile whose core holds it: before blending the field jumps by the tiles'
    disagreement (1.0) at x = 40; after, no step exceeds the field's slope plus the ramp's 1 / (2 O)."""
    def stitched(a, b):
        line = np.column_stack([np.arange(8, 73), np.full(65, 16), np.full(65, 16)])
        own_a = line[:, 0] < 40
        return np.where(own_a, a.lookup(line)[0], b.lookup(line)[0]).astype(np.float64)

    a, b = pair()
    assert np.abs(np.diff(stitched(a, b))).max() > 0.9
    blend_pair(a, b)
    assert np.abs(np.diff(stitched(a, b))).max() <= 0.05 + 1.0 / (2 * O) + 1e-6


def test_result_does_not_depend_on_the_order_of_the_others():
    tiles = [make_tile((0, 0, 0), A_LO, A_HI, O, 0.3), make_tile((1, 0, 0), B_LO, B_HI, O, -0.2),
             make_tile((0, 1, 0), [4, 20, 4], [44, 52, 28], O, 0.7)]
    results = []
    for others in ([tiles[1], tiles[2]], [tiles[2], tiles[1]]):
        own = make_tile((0, 0, 0), A_LO, A_HI, O, 0.3)
        blend_into(own, [copy(t) for t in others], np.array(A_LO), np.array(A_HI))
        results.append(own.values)
    np.testing.assert_array_equal(results[0], results[1])


def test_a_missing_neighbour_changes_nothing():
    a, _ = pair()
    before = a.values.copy()
    assert blend_into(a, [], np.array(A_LO), np.array(A_HI)) == 0
    np.testing.assert_array_equal(a.values, before)
    # a neighbour whose blocks lie elsewhere (not meeting the region) changes nothing either
    far = make_tile((5, 0, 0), [200, 4, 4], [240, 28, 28], O, 9.0)
    assert blend_into(a, [far], np.array(A_LO), np.array(A_HI)) == 0
    np.testing.assert_array_equal(a.values, before)


def test_a_neighbour_without_the_vertex_as_parameter_leaves_it_alone():
    """Where the neighbour's band does not hold a vertex (no PARAM), only the own tile's value counts: unchanged
    wherever the own weight is positive; where the neighbour does hold it, it is blended."""
    a = make_tile((0, 0, 0), A_LO, A_HI, O, +0.5)
    # the neighbour's band stops at z = 12: above, it has no parameters
    b = make_tile((1, 0, 0), B_LO, B_HI, O, -0.5, param_box=(B_LO, [76, 28, 12]))
    before = a.values.copy()
    blend_into(a, [b], np.array(A_LO), np.array(A_HI))
    above = all_vertices(np.array([36, 8, 13]), np.array([43, 24, 24]))
    assert np.all(pou_weight(above, np.array(A_LO), np.array(A_HI), O) > 0)
    np.testing.assert_array_equal(values_at(a, above), np.float32(field(above) + 0.5))
    below = all_vertices(np.array([38, 8, 8]), np.array([43, 24, 12]))
    assert np.all(values_at(a, below) < np.float32(field(below) + 0.5))
    # nothing changed above z = 12 where the tile's own weight is positive
    local = np.stack(np.meshgrid(*[np.arange(BRICK)] * 3, indexing="ij"), -1).reshape(1, -1, 3)
    g = (a.brick_coords[:, None, :] * BRICK + local).reshape(-1, 3)
    changed = (a.values != before).reshape(-1)
    own_weight = pou_weight(g, np.array(A_LO), np.array(A_HI), O)
    assert changed.any()
    assert np.all(g[changed & (own_weight > 0)][:, 2] <= 12)


def test_only_the_region_is_blended():
    a, b = pair()
    region_lo, region_hi = np.array([36, 4, 4]), np.array([44, 28, 16])
    blend_into(a, [b], region_lo, region_hi)
    outside = all_vertices(np.array([36, 8, 17]), np.array([43, 24, 24]))
    np.testing.assert_array_equal(values_at(a, outside), np.float32(field(outside) + 0.5))
    inside = all_vertices(np.array([38, 8, 8]), np.array([43, 24, 16]))
    assert np.all(values_at(a, inside) != np.float32(field(inside) + 0.5))
