"""Accuracy of a reconstructed mesh against a ground-truth mesh, with the field's conventions.

The sample-based metrics follow Occupancy Networks / Shape As Points / NeuralPull (``MeshEvaluator``), so numbers
compare with the GridPull paper:

* ``n`` area-uniform samples on each mesh (default 100k), nearest neighbours by pykdtree;
* accuracy = mean distance pred -> GT, completeness = mean distance GT -> pred;
* Chamfer-L1 = (accuracy + completeness) / 2; Chamfer-L2 = mean of the two directions' mean *squared*
  distances (the paper reports it x100);
* normal consistency = mean of the two directions' mean ``|cos|`` between a sample's face normal and its
  nearest sample's face normal;
* F-score(tau) = harmonic mean of precision (pred samples within tau of GT) and recall (GT samples within tau);
* Hausdorff = max of the two directions' max distances.

With 100k samples per side these metrics have a floor (a perfect mesh scored against itself is not 0: about
``sqrt(area / n) / 2``, ``chamfer_l1_floor``), which on a unit shape is below a millimetre but on a street scene
of thousands of square metres is over 10 cm, more than the reconstruction's own error. The ``*_exact`` variants
measure from each side's samples to the *other mesh's surface* (closest point on a triangle, via VTK's cell
locator): no floor, so they rank good methods properly and are the figures to read for scenes.
"""

from __future__ import annotations

import zlib

import numpy as np
from pykdtree.kdtree import KDTree

from ._optional import require
from .errors import InputError
from .mesh import Mesh
from .mesh_repair import boundary_loops
from .nearest import distances_to_cloud

__all__ = ["sample_surface", "point_to_mesh", "evaluate", "class_scores", "footprint_samples", "footprint_scores",
           "DEFAULT_THRESHOLDS", "FOOTPRINT_RADII"]

DEFAULT_THRESHOLDS = (0.002, 0.004, 0.01)
# metres: how far past the scan lines a scene mesh is expected to reach (a gap of up to twice this between rings)
FOOTPRINT_RADII = (1.5, 3.0)


def sample_surface(mesh: Mesh, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform samples on a mesh.

    Returns
    -------
    points : (n, 3) float64
    normals : (n, 3) float64
        Unit normal of the face each sample lies on.
    """
    if mesh.n_faces == 0:
        raise ValueError("cannot sample a mesh without faces")
    rng = np.random.default_rng(seed)
    normals, areas = mesh.face_normals()
    total = areas.sum()
    if not total > 0:
        raise ValueError("cannot sample a mesh of zero area")
    cdf = np.cumsum(areas / total)
    face = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(areas) - 1)
    u = rng.random(n)
    v = rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    tri = mesh.vertices[mesh.faces[face]]
    pts = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    return pts, normals[face]


def point_to_mesh(points: np.ndarray, mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Exact distance from points to a mesh surface (closest point on any triangle).

    Returns
    -------
    distance : (N,) float64
    face : (N,) int64
        Index of the closest face.
    """
    pv = require("pyvista", "exact point-to-mesh distances")
    # VTK works in float64 but its locator is relative: centre the data to keep georeferenced inputs exact
    centre = mesh.vertices.mean(axis=0)
    poly = pv.PolyData.from_regular_faces(mesh.vertices - centre, mesh.faces)
    face, closest = poly.find_closest_cell(np.asarray(points, dtype=np.float64) - centre, return_closest_point=True)
    dist = np.linalg.norm(closest - (np.asarray(points, dtype=np.float64) - centre), axis=1)
    return dist, np.asarray(face, dtype=np.int64)


def _near(pts: np.ndarray, nrm: np.ndarray, ref: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Samples within ``radius`` of a reference cloud (distances from a local origin: georeferenced-safe)."""
    d = distances_to_cloud(pts, ref, radius)
    keep = np.isfinite(d) & (d <= radius)
    return pts[keep], nrm[keep]


def _fscore(acc_d: np.ndarray, comp_d: np.ndarray, tau: float) -> tuple[float, float, float]:
    precision = float(np.mean(acc_d <= tau))
    recall = float(np.mean(comp_d <= tau))
    f = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return f, precision, recall


def evaluate(pred: Mesh, gt: Mesh, n_samples: int = 100_000, thresholds=DEFAULT_THRESHOLDS,
             exact: bool = True, seed: int = 0, observed: np.ndarray | None = None,
             observed_radius: float = 0.0) -> dict:
    """All metrics of ``pred`` against ``gt`` (same units; distances in those units).

    Parameters
    ----------
    pred, gt : Mesh
    n_samples : int
        Samples per mesh.
    thresholds : sequence of float
        F-score thresholds (absolute, in the meshes' units; the defaults suit unit-cube shapes).
    exact : bool
        Also compute the exact point-to-surface variants.
    seed : int
    observed : (M, 3) float, optional
        The input points: ground-truth samples farther than ``observed_radius`` from every input point are left
        out, so a partial scan is scored over what it observed (unscanned building backs and floors are not
        "missing"). The reconstruction's samples are all kept: surfaces invented far from the data still count
        against accuracy.
    observed_radius : float

    Returns
    -------
    dict
        ``chamfer_l1``, ``chamfer_l2``, ``chamfer_l2_x100``, ``accuracy``, ``completeness``,
        ``normal_consistency``, ``hausdorff``, ``fscore@tau`` (+ precision/recall), ``chamfer_l1_floor`` (the
        sample-based Chamfer-L1 of a perfect mesh, ``(sqrt(A_gt / n) + sqrt(A_pred / n)) / 4`` for areas ``A``:
        the mean distance from a surface point to the nearest of ``n`` uniform samples; at scene scale it
        dominates the sampled figures), the ``*_exact`` variants (the ones to read for scenes), and
        the predicted mesh's topology (``watertight``, ``components``, ``boundary_edges``, ``boundary_loops``
        (simple loops; a loop through a pinched vertex is not counted), ...).
    """
    if pred.n_faces == 0:
        raise ValueError("the reconstructed mesh has no faces")
    p_pts, p_nrm = sample_surface(pred, n_samples, seed)
    g_pts, g_nrm = sample_surface(gt, n_samples, seed + 1)
    if observed is not None:
        g_pts, g_nrm = _near(g_pts, g_nrm, observed, observed_radius)
        if len(g_pts) == 0:
            raise InputError("no ground-truth sample lies within observed_radius of the input points")
    acc_d, acc_i = KDTree(g_pts).query(p_pts, k=1)
    comp_d, comp_i = KDTree(p_pts).query(g_pts, k=1)
    acc_d = acc_d.astype(np.float64)
    comp_d = comp_d.astype(np.float64)
    nc = 0.5 * (np.abs(np.einsum("ij,ij->i", p_nrm, g_nrm[acc_i])).mean()
                + np.abs(np.einsum("ij,ij->i", g_nrm, p_nrm[comp_i])).mean())
    out: dict = {
        "n_samples": int(n_samples),
        "gt_samples_used": int(len(g_pts)),
        "accuracy": float(acc_d.mean()),
        "completeness": float(comp_d.mean()),
        "chamfer_l1": float(0.5 * (acc_d.mean() + comp_d.mean())),
        "chamfer_l2": float(0.5 * ((acc_d ** 2).mean() + (comp_d ** 2).mean())),
        "normal_consistency": float(nc),
        "hausdorff": float(max(acc_d.max(), comp_d.max())),
    }
    out["chamfer_l2_x100"] = 100.0 * out["chamfer_l2"]
    # n uniform samples on an area A lie about sqrt(A / n) apart, and a point of the other surface is on average
    # half that from its nearest sample: what a perfect mesh scores from the sampling alone
    out["chamfer_l1_floor"] = float(0.25 * (np.sqrt(gt.area / n_samples) + np.sqrt(pred.area / n_samples)))
    for tau in thresholds:
        f, pr, rc = _fscore(acc_d, comp_d, tau)
        out[f"fscore@{tau:g}"] = f
        out[f"precision@{tau:g}"] = pr
        out[f"recall@{tau:g}"] = rc
    if exact:
        gt_face_n, _ = gt.face_normals()
        pr_face_n, _ = pred.face_normals()
        ea, fa = point_to_mesh(p_pts, gt)
        ec, fc = point_to_mesh(g_pts, pred)
        out["accuracy_exact"] = float(ea.mean())
        out["completeness_exact"] = float(ec.mean())
        out["chamfer_l1_exact"] = float(0.5 * (ea.mean() + ec.mean()))
        out["chamfer_l2_exact"] = float(0.5 * ((ea ** 2).mean() + (ec ** 2).mean()))
        out["normal_consistency_exact"] = float(0.5 * (
            np.abs(np.einsum("ij,ij->i", p_nrm, gt_face_n[fa])).mean()
            + np.abs(np.einsum("ij,ij->i", g_nrm, pr_face_n[fc])).mean()))
        out["hausdorff_exact"] = float(max(ea.max(), ec.max()))
        for tau in thresholds:
            f, _, _ = _fscore(ea, ec, tau)
            out[f"fscore_exact@{tau:g}"] = f
    topo = pred.topology
    out.update({"watertight": topo.watertight, "components": topo.components,
                "boundary_edges": topo.boundary_edges, "boundary_loops": len(boundary_loops(pred)),
                "nonmanifold_edges": topo.nonmanifold_edges, "vertices": topo.n_vertices, "faces": topo.n_faces})
    return out


def class_scores(pred: Mesh, gt: Mesh, classes: dict, n_samples: int = 100_000, tau: float = 0.05,
                 seed: int = 0, observed: np.ndarray | None = None, observed_radius: float = 0.0) -> dict:
    """Exact scores per class of ground-truth faces: how well each kind of object (poles, cars, terrain) came out.

    A scene-wide Chamfer distance is dominated by the large flat surfaces; thin objects such as poles hold a
    small share of the area, so their loss does not show there.

    Parameters
    ----------
    pred, gt : Mesh
        Same units.
    classes : dict of str -> (start, stop)
        Each class's faces in ``gt``: ``gt.faces[start:stop]`` (the synthetic street's ``face_classes``); integer
        ranges that do not overlap (an empty range is a class with no samples).
    n_samples : int
        Samples on each class of ``gt`` and on ``pred``.
    tau : float
        Distance (mesh units) for the recall.
    seed : int
    observed, observed_radius
        As in :func:`evaluate`: ground-truth samples farther than ``observed_radius`` from every input point are
        left out (a pole's unscanned top is not "missing").

    Returns
    -------
    dict of str -> dict
        Per class: ``gt_samples`` (the samples kept), ``completeness`` (mean distance of the class's samples to
        ``pred``'s surface), ``recall`` (share within ``tau``), ``normal_consistency`` (mean ``|cos|`` between a
        sample's face normal and that of ``pred``'s closest face, however far that face is, as in :func:`evaluate`:
        read it beside the recall), ``pred_share`` (share of ``pred``'s samples
        whose closest ground-truth face is in the class) and ``accuracy`` (their mean distance; None when there
        are none).
    """
    if pred.n_faces == 0:
        raise ValueError("the reconstructed mesh has no faces")
    spans = {}
    for name, span in classes.items():
        try:
            start, stop = span
        except (TypeError, ValueError):
            raise ValueError(f"class {name!r}: expected a (start, stop) pair of face indices, got {span!r}") from None
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (start, stop)):
            raise ValueError(f"class {name!r}: face indices must be integers, got {span!r}")
        if not 0 <= start <= stop <= gt.n_faces:
            raise ValueError(f"class {name!r}: faces [{start}, {stop}) are not within the {gt.n_faces} "
                             "ground-truth faces")
        spans[name] = (int(start), int(stop))
    order = sorted(spans.items(), key=lambda kv: kv[1])
    for (a, (_, stop_a)), (b, (start_b, _)) in zip(order, order[1:]):
        if start_b < stop_a:
            raise ValueError(f"classes {a!r} and {b!r} share faces (from face {start_b})")
    p_pts, _ = sample_surface(pred, n_samples, seed)
    acc_d, acc_f = point_to_mesh(p_pts, gt)
    pred_n, _ = pred.face_normals()
    out = {}
    for name, (start, stop) in spans.items():
        mine = (acc_f >= start) & (acc_f < stop)
        row = {"pred_share": float(mine.mean()), "accuracy": float(acc_d[mine].mean()) if mine.any() else None,
               "gt_samples": 0, "completeness": None, "recall": None, "normal_consistency": None}
        part = Mesh(gt.vertices, gt.faces[start:stop])
        if stop > start and part.face_normals()[1].sum() > 0:
            # a seed of the class's own (not of its place in the dict): the scores do not depend on the order
            g_pts, g_nrm = sample_surface(part, n_samples, seed + 1 + zlib.crc32(name.encode()) % 65536)
            if observed is not None:
                g_pts, g_nrm = _near(g_pts, g_nrm, observed, observed_radius)
            row["gt_samples"] = int(len(g_pts))
            if len(g_pts):
                d, f = point_to_mesh(g_pts, pred)
                row.update(completeness=float(d.mean()), recall=float(np.mean(d <= tau)),
                           normal_consistency=float(np.abs(np.einsum("ij,ij->i", g_nrm, pred_n[f])).mean()))
        out[name] = row
    return out


def footprint_samples(gt: Mesh, points: np.ndarray, radius: float, n_samples: int = 200_000,
                      seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The ground-truth samples :func:`footprint_scores` draws, and each one's distance to the input points.

    Returns
    -------
    samples : (n_samples, 3) float64
        Area-uniform samples on ``gt``.
    near : (n_samples,) float64
        Distance to the nearest point of ``points`` (same units); inf beyond ``radius``.
    """
    g_pts, _ = sample_surface(gt, n_samples, seed + 1)
    return g_pts, distances_to_cloud(g_pts, points, radius)


def footprint_scores(pred: Mesh, gt: Mesh, points: np.ndarray, radii=FOOTPRINT_RADII, tau: float = 0.1,
                     n_samples: int = 200_000, seed: int = 0, seen_by=None) -> dict:
    """How much of the scanned footprint a scene mesh covers, and how much of the mesh is right.

    The footprint is the ground-truth surface within ``R`` of any input point. It is method-neutral: a hole
    there is a miss whatever its cause, and a surface bridged across a gap between scan lines is a hit when it
    lies within ``tau`` of the truth. The observed-region Chamfer distance (:func:`evaluate` with
    ``observed``) charges every bridge for being less exact than data; this yardstick does not, and the
    precision over the whole mesh charges bridges that go where the truth is not (across a kerb, into empty
    space).

    Parameters
    ----------
    pred, gt : Mesh
        Same units (a scene's: metres or feet).
    points : (N, 3) float
        The input points, in the meshes' frame.
    radii : sequence of float
        Footprint radii ``R``, in the meshes' units.
    tau : float
        Distance within which a sample counts as a hit, same units.
    n_samples : int
        Area-uniform samples on each mesh (the footprint keeps those of ``gt`` within ``R``).
    seed : int
    seen_by : callable, optional
        ``seen_by(samples)`` -> (M,) bool: which of ``gt``'s (M, 3) samples some sensor of the scan sees (for a
        simulated scan, ``lambda p: synthetic.lidar.visible_from(gt, p, sensors)``; passed in, so that metrics
        does not depend on the simulator). The footprint is then also split into what some sensor sees and what
        none does (walls' backs, car undersides, shadows, walls above the highest beam), which only a guess
        could cover.

    Returns
    -------
    dict
        ``footprint_recall@R`` (share of the footprint's samples within ``tau`` of ``pred``'s surface, exact
        point-to-triangle distances) and ``footprint_samples@R`` for each ``R``; ``precision@tau`` (share of
        ``pred``'s samples within ``tau`` of ``gt``'s surface); ``tau``; ``boundary_edges`` and ``components``
        (pieces) of ``pred``. With ``seen_by`` also ``footprint_seen@R`` (share of the footprint some sensor
        sees) and ``footprint_seen_recall@R`` (the recall over that share).
    """
    if pred.n_faces == 0:
        raise ValueError("the reconstructed mesh has no faces")
    radii = tuple(float(r) for r in radii)
    if not radii or not all(np.isfinite(r) and r > 0 for r in radii):
        raise ValueError(f"footprint radii must be positive, got {radii}")
    if not (np.isfinite(tau) and tau > 0):
        raise ValueError(f"tau must be positive, got {tau}")
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError("points must be a non-empty (N, 3) array")
    g_pts, near = footprint_samples(gt, points, max(radii), n_samples, seed)
    out: dict = {"tau": float(tau)}
    within = np.isfinite(near)
    hit = np.zeros(len(g_pts), bool)
    if within.any():
        hit[within] = point_to_mesh(g_pts[within], pred)[0] <= tau
    for r in radii:
        mine = within & (near <= r)
        out[f"footprint_samples@{r:g}"] = int(mine.sum())
        out[f"footprint_recall@{r:g}"] = float(hit[mine].mean()) if mine.any() else None
    if seen_by is not None:
        seen = np.zeros(len(g_pts), bool)
        seen[within] = np.asarray(seen_by(g_pts[within]), bool)
        for r in radii:
            mine = within & (near <= r)
            out[f"footprint_seen@{r:g}"] = float(seen[mine].mean()) if mine.any() else None
            out[f"footprint_seen_recall@{r:g}"] = float(hit[mine & seen].mean()) if (mine & seen).any() else None
    p_pts, _ = sample_surface(pred, n_samples, seed)
    out[f"precision@{tau:g}"] = float(np.mean(point_to_mesh(p_pts, gt)[0] <= tau))
    topo = pred.topology
    out.update(boundary_edges=int(topo.boundary_edges), components=int(topo.components))
    return out
