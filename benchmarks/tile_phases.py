"""What a dense street tile's set-up costs on one thread: its normals (PCA plane fits over 16 neighbours) and the
bridge's column fits, each beside a reference formulation in the same process.

* ``normals``: :func:`tiled_gridpull.normals.estimate_normals` (the KD-tree query, then the numba plane kernel
  :mod:`tiled_gridpull.kernels.planes`) against the numpy formulation it replaced (the same query, an (n, k, 3)
  gather, ``einsum`` covariances and batched LAPACK ``eigh``), with the largest angle between their normals;
* ``bridge columns``: :func:`tiled_gridpull.kernels.bridge.fit_columns` over every column of a 320 x 320-cell tile
  lattice (the scene config's 256-cell core and 32-cell margins at 0.1 m), bridge 24 cells, no sensor origins;
  its reference is the same kernel with each ground sample's sector taken by ``atan2`` (the formula
  :func:`~tiled_gridpull.kernels.bridge.sector_of` reproduces), outputs compared bit for bit.

The tile: the 32 m x 32 m block around the middle of the demo's street (``make demo``'s sample: 300,000 points, 16
sweeps 1 m apart), about a quarter of a million points. One worker thread, as the local cluster's workers run.
Medians of ``--repeat`` runs, alternating kernel and reference; results append to
``benchmarks/results/tile_phases.jsonl``.

Usage::

    NUMBA_NUM_THREADS=1 python -m benchmarks.tile_phases [--repeat 5]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from benchmarks.common import REPO, append_jsonl, machine, markdown_table

RESULTS = REPO / "benchmarks" / "results" / "tile_phases.jsonl"


def street_tile(side: float = 32.0) -> np.ndarray:
    """(N, 3) float64: the points of the ``side``-metre block around the sensor path's middle in the demo's street
    (``make demo``: 300,000 points, 16 sweeps 1 m apart), as its densest tile sees them."""
    import tempfile

    from tiled_gridpull.io import read_points
    from tiled_gridpull.synthetic.street_sample import make_street_sample

    with tempfile.TemporaryDirectory() as tmp:
        sample = make_street_sample(tmp, n_points=300_000, frames=16)
        xyz = np.asarray(read_points(sample["laz"]).xyz, np.float64)
    traj = np.median(xyz[:, :2], axis=0)
    keep = np.all(np.abs(xyz[:, :2] - traj) < side / 2, axis=1)
    return xyz[keep]


def numpy_normals(points: np.ndarray, k: int = 16, gaps: bool = False):
    """The reference: numpy's gather, einsum and batched eigh over each point's ``k`` nearest neighbours; with
    ``gaps``, also the gap between the two smallest eigenvalues over the largest."""
    from pykdtree.kdtree import KDTree

    _, idx = KDTree(points).query(points, k=k)
    nb = points[idx.reshape(len(points), k).astype(np.int64)]
    d = nb - nb.mean(axis=1)[:, None]
    w, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d))
    if gaps:
        return vecs[:, :, 0], (w[:, 1] - w[:, 0]) / np.maximum(w[:, 2], 1e-300)
    return vecs[:, :, 0]


def _atan2_fit_columns():
    """:func:`fit_columns` compiled with the ``atan2`` sector formula in place of :func:`sector_of`."""
    import inspect

    from numba import njit

    from tiled_gridpull.kernels import bridge as kb

    src = inspect.getsource(kb.fit_columns.py_func).split("\n", 1)[1]  # without the decorator
    src = src.replace("s = sector_of(nb[t, 0], nb[t, 1])",
                      "s = int((math.atan2(nb[t, 1], nb[t, 0]) + math.pi) / (2.0 * math.pi) * SECTORS) % SECTORS")
    scope = {"math": math, "np": np, "prange": __import__("numba").prange, "SECTORS": kb.SECTORS}
    exec(compile(src, "<fit_columns with atan2>", "exec"), scope)  # noqa: S102 - our own kernel's source
    return njit(parallel=True)(scope["fit_columns"])


def bridge_inputs(points: np.ndarray, cell: float = 0.1, n: int = 320) -> tuple:
    """fit_columns' arguments for a tile lattice of ``n`` x ``n`` columns around ``points`` (scene defaults)."""
    from tiled_gridpull.bridge import BridgeRule
    from tiled_gridpull.kernels import bridge as kb

    rule = BridgeRule(radius=24)
    lo = points.min(axis=0)
    cells = (points - lo) / cell
    nx = ny = int(math.ceil(n / rule.pixel))
    rep = kb.bin_ground(cells[:, 0].copy(), cells[:, 1].copy(), cells[:, 2].copy(), float(rule.pixel), nx, ny,
                        float(rule.layer))
    ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    cols = np.stack([ii.ravel(), jj.ravel()], axis=1).astype(np.float64)
    max_gap = int(math.floor(rule.max_gap_deg / (360.0 / kb.SECTORS)))
    return (rep, float(rule.pixel), cols, float(rule.radius), float(rule.skip), max_gap, float(rule.rms_tol),
            float(rule.step_tol), float(rule.max_slope), np.full((nx, ny, 2), np.nan), 2.0)


def run(repeat: int) -> list[dict]:
    from tiled_gridpull.kernels import bridge as kb
    from tiled_gridpull.normals import estimate_normals

    pts = street_tile()
    rows = []
    # normals
    ours, (ref, gap) = estimate_normals(pts, 16), numpy_normals(pts, 16, gaps=True)  # warm: compiled, caches
    # the angle from the cross product: arccos of a float32 normal's dot product is off by its rounding (1e-2 deg)
    o = ours.astype(np.float64)
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(o, ref), axis=1), np.abs(np.sum(o * ref, axis=1))))
    apart = gap > 1e-6
    agreement = (f"largest angle {angle[apart].max():.2g} deg where the two smallest eigenvalues are apart (gap > "
                 f"1e-6 of the largest: {apart.mean():.2%} of points)")
    if not apart.all():  # a tied eigenspace: any of its vectors is the plane's normal
        agreement += f"; {np.mean(angle[~apart] > 1.0):.2%} of the others differ by more than 1 deg"
    t_k, t_r = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        estimate_normals(pts, 16)
        t_k.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        numpy_normals(pts, 16)
        t_r.append(time.perf_counter() - t0)
    rows.append({"phase": "normals", "points": len(pts), "kernel_s": float(np.median(t_k)),
                 "reference_s": float(np.median(t_r)), "ratio": float(np.median(np.array(t_k) / np.array(t_r))),
                 "agreement": agreement})
    # bridge columns
    args = bridge_inputs(pts)
    slow = _atan2_fit_columns()
    a, b = kb.fit_columns(*args), slow(*args)
    same = bool(np.array_equal(a, b, equal_nan=True))
    t_k, t_r = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        kb.fit_columns(*args)
        t_k.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        slow(*args)
        t_r.append(time.perf_counter() - t0)
    rows.append({"phase": "bridge columns", "points": len(pts), "columns": len(args[2]),
                 "bridged": int(np.isfinite(a[:, 0]).sum()), "kernel_s": float(np.median(t_k)),
                 "reference_s": float(np.median(t_r)), "ratio": float(np.median(np.array(t_k) / np.array(t_r))),
                 "agreement": "bit for bit" if same else "DIFFERENT"})
    return rows


def table(rows: list[dict]) -> str:
    return markdown_table(rows, [("run", "run", "s"), ("phase", "phase", "s"), ("points", "points", ",d"),
                                 ("kernel_s", "kernel s", ".3f"), ("reference_s", "reference s", ".3f"),
                                 ("ratio", "ratio", ".2f"), ("agreement", "agreement", "s"),
                                 ("threads", "threads", "d")])


def main() -> None:
    import numba

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    run_id = time.strftime("%Y-%m-%d %H:%M:%S")
    append_jsonl(RESULTS, {"run": run_id, "phase": "machine", **machine()})
    rows = run(args.repeat)
    for r in rows:
        r.update(run=run_id, threads=numba.get_num_threads())
        append_jsonl(RESULTS, r)
    print(table(rows))


if __name__ == "__main__":
    main()
