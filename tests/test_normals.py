"""Orienting normals: the up rule's walls, which the rule alone cannot decide, and the flip check's mask."""

import numpy as np
import pytest

from tiled_gridpull.normals import orient_normals, orientation_decided, orientation_score


def _building_on_ground(rng, spacing=0.15):
    """Points and true outward normals of a 10 x 6 x 4 m box standing on ground that reaches 8 m beyond it
    (no points inside: a ground-level scan sees no floor), and a 0.15 m kerb along y = -10."""
    pts, nrm = [], []

    def grid(a, b):
        u, v = np.meshgrid(np.arange(a[0], a[1], spacing), np.arange(b[0], b[1], spacing), indexing="ij")
        return u.ravel(), v.ravel()

    x, y = grid((-13, 13), (-10, 11))
    out = (np.abs(x) > 5) | (np.abs(y) > 3)
    pts.append(np.c_[x[out], y[out], np.zeros(out.sum())])
    nrm.append(np.tile([0, 0, 1.0], (out.sum(), 1)))
    x, y = grid((-5, 5), (-3, 3))            # roof
    pts.append(np.c_[x, y, np.full_like(x, 4.0)])
    nrm.append(np.tile([0, 0, 1.0], (len(x), 1)))
    for axis, side in ((0, -5), (0, 5), (1, -3), (1, 3)):   # walls
        u, h = grid((-5, 5) if axis == 1 else (-3, 3), (spacing, 4))
        p = np.zeros((len(u), 3))
        p[:, axis] = side
        p[:, 1 - axis] = u
        p[:, 2] = h
        n = np.zeros_like(p)
        n[:, axis] = np.sign(side)
        pts.append(p)
        nrm.append(n)
    x, y = grid((-13, 13), (-13, -10))       # a raised pavement behind a kerb face at y = -10
    pts.append(np.c_[x, y, np.full_like(x, 0.15)])
    nrm.append(np.tile([0, 0, 1.0], (len(x), 1)))
    x, h = grid((-13, 13), (0.03, 0.15))
    pts.append(np.c_[x, np.full_like(x, -10.0), h])
    nrm.append(np.tile([0, 1.0, 0], (len(x), 1)))
    pts, nrm = np.concatenate(pts), np.concatenate(nrm)
    return pts + rng.normal(scale=0.005, size=pts.shape), nrm


def test_up_rule_turns_walls_towards_their_ground_and_away_from_their_roof():
    rng = np.random.default_rng(3)
    pts, true = _building_on_ground(rng)
    # an eigen solver's signs: arbitrary per point (LAPACK's happen to agree along a plane, a Jacobi solver's not)
    tilt = true + rng.normal(scale=0.05, size=true.shape)
    given = tilt / np.linalg.norm(tilt, axis=1, keepdims=True) * rng.choice([-1.0, 1.0], size=(len(true), 1))
    n = orient_normals(given, pts)
    agree = np.einsum("ij,ij->i", n, true) > 0
    walls = np.abs(true[:, 2]) < 0.5
    assert walls.sum() > 5000
    assert agree[~walls].all()                     # the rule itself: everything else up
    assert agree[walls].mean() > 0.995, agree[walls].mean()
    kerb = walls & (np.abs(pts[:, 1] + 10) < 0.05)
    assert agree[kerb].mean() > 0.99               # the road lies below the kerb face, the pavement above it


def test_walls_of_a_tile_without_ground_keep_their_signs():
    # nothing decided to vote with (a tile that holds only a facade): the rule leaves the walls as they came
    rng = np.random.default_rng(4)
    pts = np.c_[rng.uniform(0, 5, 500), np.zeros(500), rng.uniform(0, 4, 500)]
    given = np.tile([0, 1.0, 0], (500, 1)) * rng.choice([-1.0, 1.0], size=(500, 1))
    assert np.array_equal(orient_normals(given, pts), given.astype(np.float32))


def test_flip_check_counts_only_the_normals_the_rule_decides():
    pts = np.zeros((4, 3))
    n = np.array([[0, 0, 1.0], [0.2, 0, 0.98], [1.0, 0, 0], [0, 1.0, 0.1]])
    decided = orientation_decided(n, pts)
    assert decided.tolist() == [True, True, False, False]
    grads = np.array([[0, 0, 1.0], [0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])
    assert orientation_score(grads, n) == pytest.approx(0.0)
    assert orientation_score(grads, n, decided) == pytest.approx(1.0)


def test_a_nan_normal_among_the_walls_leaves_the_others_decided():
    rng = np.random.default_rng(5)
    pts, true = _building_on_ground(rng)
    given = true * rng.choice([-1.0, 1.0], size=(len(true), 1))
    walls = np.flatnonzero(np.abs(true[:, 2]) < 0.5)
    given[walls[::4]] = np.nan                     # degenerate neighbourhoods
    n = orient_normals(given, pts)
    ok = np.isfinite(n).all(axis=1)
    assert np.isnan(n[walls[::4]]).all()
    agree = np.einsum("ij,ij->i", n[ok], true[ok]) > 0
    assert agree.mean() > 0.995


def test_the_wall_vote_is_the_same_whatever_its_chunk():
    from tiled_gridpull.normals import _orient_walls

    rng = np.random.default_rng(6)
    pts, true = _building_on_ground(rng)
    given = (true * rng.choice([-1.0, 1.0], size=(len(true), 1))).astype(np.float32)
    whole, pieces = given.copy(), given.copy()
    _orient_walls(whole, pts, (0.0, 0.0, 1.0))
    _orient_walls(pieces, pts, (0.0, 0.0, 1.0), chunk=777)
    assert (whole != given).any()
    assert np.array_equal(whole, pieces)


def _gable_house(rng, pitch_deg, spacing=0.15):
    """A 10 x 20 m house, 4 m walls, a gable roof of ``pitch_deg`` (ridge along y), on ground reaching 8 m
    beyond it: points and true outward normals."""
    def grid(a, b):
        u, v = np.meshgrid(np.arange(a[0], a[1], spacing), np.arange(b[0], b[1], spacing), indexing="ij")
        return u.ravel(), v.ravel()

    pts, nrm = [], []
    x, y = grid((-13, 13), (-18, 18))
    out = (np.abs(x) > 5) | (np.abs(y) > 10)
    pts.append(np.c_[x[out], y[out], np.zeros(out.sum())])
    nrm.append(np.tile([0, 0, 1.0], (out.sum(), 1)))
    a = np.radians(pitch_deg)
    u, y = grid((0, 5 / np.cos(a)), (-10, 10))
    for side in (-1, 1):
        pts.append(np.c_[side * (5 - u * np.cos(a)), y, 4 + u * np.sin(a)])
        nrm.append(np.tile([side * np.sin(a), 0, np.cos(a)], (len(u), 1)))
    for side in (-1, 1):
        y, h = grid((-10, 10), (spacing, 4))
        pts.append(np.c_[np.full_like(y, 5.0 * side), y, h])
        nrm.append(np.tile([side, 0, 0.0], (len(y), 1)))
        x, h = grid((-5, 5), (spacing, 4 + 5 * np.tan(a)))
        keep = h <= 4 + (5 - np.abs(x)) * np.tan(a)
        pts.append(np.c_[x[keep], np.full(keep.sum(), 10.0 * side), h[keep]])
        nrm.append(np.tile([0, side, 0.0], (keep.sum(), 1)))
    pts, nrm = np.concatenate(pts), np.concatenate(nrm)
    return pts + rng.normal(scale=0.01, size=pts.shape), nrm


@pytest.mark.parametrize("pitch", [62, 70, 80])
def test_the_wall_vote_keeps_steep_roofs_facing_out(pitch):
    """A roof face 62-80 degrees from up is a wall to the vote; ground straight below it lies behind the face's
    plane, and with the whole normal in the vote it turned 34-46 % of such roofs upside down (the rule alone had
    them right). The vote reads the side from the normal's horizontal part."""
    from tiled_gridpull.normals import estimate_normals

    rng = np.random.default_rng(0)
    pts, true = _gable_house(rng, pitch)
    n = orient_normals(estimate_normals(pts, 16), pts)
    agree = np.einsum("ij,ij->i", n, true) > 0
    roof = (pts[:, 2] > 4.1) & (np.abs(true[:, 2]) > 0.05)
    walls = np.abs(true[:, 2]) < 0.05
    assert agree[roof].mean() > 0.97, agree[roof].mean()
    assert agree[walls].mean() > 0.97, agree[walls].mean()
