"""Closed analytic shapes with exact ground truth: icosphere, torus and a finely gridded box.

Every shape is centred at the origin, watertight (each edge shared by exactly two faces with opposite
directions) and oriented outwards (counter-clockwise seen from outside, positive signed volume), the
conventions of :class:`~tiled_gridpull.mesh.Mesh`. Units are whatever the caller means (the defaults fit
the unit cube the solver's paper shapes live in).
"""

from __future__ import annotations

import numpy as np

from ..mesh import Mesh
from ..metrics import sample_surface

__all__ = ["sphere", "torus", "box", "half_sphere", "height_field", "sample_shape"]


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """Unit-circumradius icosahedron, faces counter-clockwise seen from outside."""
    t = (1.0 + 5.0 ** 0.5) / 2.0
    v = np.array([(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0),
                  (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
                  (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)], dtype=np.float64)
    f = np.array([(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11),
                  (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8),
                  (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9),
                  (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)], dtype=np.int64)
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


def _subdivide(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split every triangle in four through its edge midpoints (midpoints shared between neighbours)."""
    n = len(v)
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    ends = np.stack([np.stack([a, b], 1), np.stack([b, c], 1), np.stack([c, a], 1)])  # (3, F, 2)
    lo = ends.min(axis=2)
    hi = ends.max(axis=2)
    # one key per undirected edge, so both faces of an edge reuse the same midpoint vertex (watertightness)
    keys, inverse = np.unique((lo * n + hi).ravel(), return_inverse=True)
    mid = 0.5 * (v[keys // n] + v[keys % n])
    m = inverse.reshape(3, -1) + n
    m_ab, m_bc, m_ca = m[0], m[1], m[2]
    faces = np.concatenate([np.stack([a, m_ab, m_ca], 1), np.stack([b, m_bc, m_ab], 1),
                            np.stack([c, m_ca, m_bc], 1), np.stack([m_ab, m_bc, m_ca], 1)])
    return np.vstack([v, mid]), faces


def sphere(radius: float = 0.5, subdivisions: int = 5) -> Mesh:
    """Icosphere: a subdivided icosahedron with vertices projected on the sphere.

    Parameters
    ----------
    radius : float
        Sphere radius (vertices lie exactly on it; the flat faces lie slightly inside).
    subdivisions : int
        Number of 1-to-4 splits; the mesh has ``20 * 4**subdivisions`` faces (5 -> 20 480).

    Returns
    -------
    Mesh
        Watertight, genus 0, outward oriented, centred at the origin.
    """
    if radius <= 0:
        raise ValueError("sphere radius must be positive")
    if subdivisions < 0:
        raise ValueError("subdivisions must be >= 0")
    v, f = _icosahedron()
    for _ in range(int(subdivisions)):
        v, f = _subdivide(v, f)
        # re-project each level so the next midpoints are taken on the sphere (even triangle sizes)
        v /= np.linalg.norm(v, axis=1, keepdims=True)
    meta = {"generator": "tiled_gridpull.synthetic.sphere", "radius": float(radius)}
    return Mesh(v * float(radius), f, meta)


def torus(major: float = 0.35, minor: float = 0.12, n_major: int = 192, n_minor: int = 96) -> Mesh:
    """Ring torus around the z axis.

    Parameters
    ----------
    major : float
        Distance from the centre to the tube centre line.
    minor : float
        Tube radius (must be smaller than ``major``).
    n_major, n_minor : int
        Segments around the ring and around the tube; ``2 * n_major * n_minor`` faces.

    Returns
    -------
    Mesh
        Watertight, genus 1 (Euler characteristic 0), outward oriented.
    """
    if not 0 < minor < major:
        raise ValueError("torus needs 0 < minor < major")
    if n_major < 3 or n_minor < 3:
        raise ValueError("torus needs at least 3 segments each way")
    u = 2 * np.pi * np.arange(n_major) / n_major
    w = 2 * np.pi * np.arange(n_minor) / n_minor
    uu, ww = np.meshgrid(u, w, indexing="ij")
    ring = major + minor * np.cos(ww)
    v = np.stack([ring * np.cos(uu), ring * np.sin(uu), minor * np.sin(ww)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij")
    i1 = (i + 1) % n_major
    j1 = (j + 1) % n_minor
    a = (i * n_minor + j).ravel()
    b = (i1 * n_minor + j).ravel()
    c = (i1 * n_minor + j1).ravel()
    d = (i * n_minor + j1).ravel()
    # dP/du x dP/dv points out of the tube, so (u, then v) is counter-clockwise seen from outside
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(v, f, {"generator": "tiled_gridpull.synthetic.torus", "major": float(major),
                       "minor": float(minor)})


def box(size: tuple[float, float, float] = (0.8, 0.6, 0.4), divisions: int = 40) -> Mesh:
    """Axis-aligned box with sharp edges, each face a regular ``divisions x divisions`` grid.

    Parameters
    ----------
    size : (3,) float
        Edge lengths along x, y, z.
    divisions : int
        Grid cells along every edge; ``12 * divisions**2`` faces. Vertices on the box edges are shared by the
        two faces that meet there, so the mesh is watertight.

    Returns
    -------
    Mesh
        Watertight, genus 0, outward oriented, centred at the origin.
    """
    size = np.asarray(size, dtype=np.float64).reshape(3)
    if np.any(size <= 0):
        raise ValueError("box sizes must be positive")
    d = int(divisions)
    if d < 1:
        raise ValueError("box divisions must be >= 1")
    g = np.arange(d + 1)
    ii, jj, kk = np.meshgrid(g, g, g, indexing="ij")
    on_surface = (ii == 0) | (ii == d) | (jj == 0) | (jj == d) | (kk == 0) | (kk == d)
    # one vertex per lattice point on the surface, looked up by (i, j, k) when building every face's grid
    index = np.full((d + 1,) * 3, -1, np.int64)
    index[on_surface] = np.arange(int(on_surface.sum()))
    ijk = np.stack([ii[on_surface], jj[on_surface], kk[on_surface]], axis=1)
    v = (ijk / d - 0.5) * size
    faces = []
    p, q = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
    p, q = p.ravel(), q.ravel()
    for axis in range(3):
        b_ax, c_ax = (axis + 1) % 3, (axis + 2) % 3  # e_b x e_c = +e_axis
        for side in (0, d):
            def vid(pp, qq, _axis=axis, _side=side, _b=b_ax, _c=c_ax):
                coords = [None, None, None]
                coords[_axis] = np.full_like(pp, _side)
                coords[_b] = pp
                coords[_c] = qq
                return index[coords[0], coords[1], coords[2]]

            v00, v10, v11, v01 = vid(p, q), vid(p + 1, q), vid(p + 1, q + 1), vid(p, q + 1)
            if side == d:  # normal +axis: (b, then c) is counter-clockwise seen from outside
                faces += [np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)]
            else:
                faces += [np.stack([v00, v11, v10], 1), np.stack([v00, v01, v11], 1)]
    return Mesh(v, np.concatenate(faces), {"generator": "tiled_gridpull.synthetic.box",
                                           "size": size.tolist()})


def half_sphere(radius: float = 0.5) -> Mesh:
    """Upper half (z > 0) of :func:`sphere`: an open surface with one circular boundary."""
    gt = sphere(radius)
    centroids = gt.vertices[gt.faces].mean(axis=1)
    return gt.submesh(centroids[:, 2] > 0)


def height_field(n: int = 80, amplitude: float = 0.08) -> Mesh:
    """An open terrain patch ``z = a sin(3x) cos(2y)`` over [-0.5, 0.5]^2, ``n`` x ``n`` vertices."""
    x, y = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(-0.5, 0.5, n), indexing="ij")
    z = amplitude * np.sin(3 * x) * np.cos(2 * y)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + n, i + 1], 1), np.stack([i + 1, i + n, i + n + 1], 1)])
    return Mesh(v, f)


def sample_shape(mesh: Mesh, n: int, seed: int = 0, noise: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform points on a mesh, optionally with isotropic Gaussian noise.

    Parameters
    ----------
    mesh : Mesh
    n : int
        Number of points.
    seed : int
        Same seed, same points (the noise uses a stream derived from the same seed).
    noise : float
        Standard deviation of the Gaussian added to every coordinate, in the mesh's units (0: points lie
        exactly on the surface).

    Returns
    -------
    points : (n, 3) float64
    normals : (n, 3) float64
        Unit outward normal of the face each point was drawn on (not perturbed by the noise).
    """
    if noise < 0:
        raise ValueError("noise must be >= 0")
    pts, nrm = sample_surface(mesh, int(n), seed)
    if noise > 0:
        # a separate stream so the noise-free positions do not depend on whether noise is asked for
        rng = np.random.default_rng([int(seed), 0x5E15E])
        pts = pts + rng.normal(0.0, float(noise), size=pts.shape)
    return pts, nrm
