"""The neighbourhood plane kernels against numpy's covariance and LAPACK's eigenvectors."""

import numpy as np
from numba import njit

from tiled_gridpull.kernels.planes import neighbourhood_planes, smallest_eigenvector, weighted_planes


@njit(cache=True)
def _eigvecs(C):
    out = np.empty((C.shape[0], 3))
    for n in range(C.shape[0]):
        out[n, 0], out[n, 1], out[n, 2] = smallest_eigenvector(C[n, 0, 0], C[n, 0, 1], C[n, 0, 2], C[n, 1, 1],
                                                              C[n, 1, 2], C[n, 2, 2])
    return out


def test_smallest_eigenvector_is_lapacks_where_the_eigenvalues_are_apart():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(5000, 3, 3))
    C = A @ A.transpose(0, 2, 1) * 10.0 ** rng.uniform(-6, 6, (5000, 1, 1))
    w, v = np.linalg.eigh(C)
    apart = (w[:, 1] - w[:, 0]) > 1e-6 * w[:, 2]
    got = _eigvecs(C)
    assert np.allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-12)
    dot = np.abs(np.sum(got * v[:, :, 0], axis=1))
    assert apart.mean() > 0.99 and dot[apart].min() > 1 - 1e-9
    # everywhere (near ties included) an eigenvector of the smallest eigenvalue
    res = np.linalg.norm(np.einsum("nij,nj->ni", C, got) - w[:, :1] * got, axis=1)
    assert np.all(res <= 1e-9 * w[:, 2])


def test_smallest_eigenvector_of_degenerate_matrices():
    # the zero matrix (one repeated point): the first axis, as eigh gives
    assert np.array_equal(_eigvecs(np.zeros((1, 3, 3)))[0], [1.0, 0.0, 0.0])
    # points on one line (two zero eigenvalues): some unit vector across the line
    d = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    t = np.linspace(-1, 1, 16)[:, None] * d
    C = (t.T @ t)[None]
    n = _eigvecs(C)[0]
    assert abs(np.linalg.norm(n) - 1.0) < 1e-12 and abs(n @ d) < 1e-9
    # already diagonal: the axis of the smallest entry
    assert np.allclose(np.abs(_eigvecs(np.diag([3.0, 1.0, 2.0])[None])[0]), [0.0, 1.0, 0.0])


def test_neighbourhood_planes_fit_noisy_planes_like_numpys_pca():
    rng = np.random.default_rng(5)
    m, k = 400, 16
    pts = rng.uniform(-1, 1, (m * k, 3))
    normals_true = rng.normal(size=(m, 3))
    normals_true /= np.linalg.norm(normals_true, axis=1)[:, None]
    # each neighbourhood: points squashed onto its plane, plus a little noise
    for n in range(m):
        blk = pts[n * k:(n + 1) * k]
        blk -= np.outer(blk @ normals_true[n], normals_true[n]) * 0.99
        blk += 1e3 * n  # far apart, large coordinates
    idx = np.arange(m * k, dtype=np.int64).reshape(m, k)[:, rng.permutation(k)]
    cen = np.empty((m, 3))
    nor = np.empty((m, 3))
    neighbourhood_planes(pts, idx, cen, nor)
    nb = pts[idx]
    assert np.allclose(cen, nb.mean(axis=1), rtol=0, atol=1e-9)
    d = nb - nb.mean(axis=1)[:, None]
    _, v = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d))
    assert np.abs(np.sum(nor * v[:, :, 0], axis=1)).min() > 1 - 1e-9
    assert np.abs(np.sum(nor * normals_true, axis=1)).min() > 0.99


def test_weighted_planes_with_unit_weights_are_the_plain_fit_and_zero_weights_drop_neighbours():
    rng = np.random.default_rng(9)
    m, k = 200, 12
    nb = rng.normal(size=(m, k, 3)) * [3.0, 2.0, 0.2]
    cen_a, nor_a = np.empty((m, 3)), np.empty((m, 3))
    weighted_planes(nb, np.ones((m, k)), cen_a, nor_a)
    cen_b, nor_b = np.empty((m, 3)), np.empty((m, 3))
    neighbourhood_planes(nb.reshape(-1, 3), np.arange(m * k, dtype=np.int64).reshape(m, k), cen_b, nor_b)
    assert np.allclose(cen_a, cen_b, atol=1e-12) and np.abs(np.sum(nor_a * nor_b, axis=1)).min() > 1 - 1e-12
    # the last 4 neighbours at weight 0 (pushed far off the plane): the fit of the first 8
    w = np.ones((m, k))
    w[:, 8:] = 0.0
    far = nb.copy()
    far[:, 8:, 2] += 50.0
    cen_c, nor_c = np.empty((m, 3)), np.empty((m, 3))
    weighted_planes(far, w, cen_c, nor_c)
    cen_d, nor_d = np.empty((m, 3)), np.empty((m, 3))
    weighted_planes(np.ascontiguousarray(nb[:, :8]), np.ones((m, 8)), cen_d, nor_d)
    assert np.allclose(cen_c, cen_d, atol=1e-12) and np.abs(np.sum(nor_c * nor_d, axis=1)).min() > 1 - 1e-12
