"""Tiled jobs over cloud-optimized inputs (COPC, EPT): the plan from their headers and hierarchies, and every
tile's points read from the input by the tile's own task, on a worker, instead of a driver-side partition.

* **Plan** (:func:`plan_indexed`): bounds, point count and CRS come from the headers; no point is read.
* **Candidate tiles** (:func:`candidate_tiles`): the shallow levels of the octree are an even subsample of the
  whole input (each node keeps about one point per cell of a grid over its cube). They are read (a few percent
  of the points, at most :data:`SAMPLE_POINTS`) and give the tiles holding them exactly; every deeper node adds
  the tiles its cube overlaps. That is a superset of the tiles with points: a candidate a task finds empty is
  dropped.
* **Tile reads** (:func:`read_tile`, one task per candidate): the points of the nodes overlapping the tile's
  block, filtered to the block, in the input's stream order (:mod:`tiled_gridpull.io.indexed`), written as the
  tile's spill file by :func:`tiled_gridpull.partition.partition`. The file is byte for byte the one the
  streaming partition writes for the same input, so the tile's solve key, which hashes it, is derived from
  what the tile read, and a resumed job keys every tile as the interrupted one did.
* **Degenerate inputs** (:func:`indexed_degeneracy`): identical or collinear points are refused before any tile
  is read, as streamed inputs are; the octrees' root nodes settle it unless they look degenerate themselves.
* **Dry run** (:func:`estimate_specs`): tiles, points and occupied bricks estimated from the subsample and the
  deeper nodes' counts, in seconds.

Inputs that need every point on the driver (a trajectory, ``drop_outliers``) take the streaming partition:
COPC files are LAZ files and EPTs are a registered format, so they stream like any other input.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cloud import PointCloud, stream_degeneracy
from .crs import check_same_crs
from .errors import InputError
from .io.indexed import PointIndex, indexed_kind, read_box, read_index, read_levels
from .io.remote import is_url, resolved, shown, validators
from .kernels import BRICK
from .partition import partition
from .tile_plan import TilePlan, TileSpec, plan_tiles
from .tiling import TilingConfig

__all__ = ["SAMPLE_POINTS", "IndexedSource", "all_indexed", "source_version", "cached_index", "indexed_sources",
           "plan_indexed", "candidate_tiles", "read_tile", "indexed_degeneracy", "estimate_specs", "dense_region"]

#: points of the octree's shallow levels read on the driver (candidate tiles, dry run), at most
SAMPLE_POINTS = 2_000_000


def all_indexed(inputs: list) -> bool:
    """Whether every input is a COPC file or an EPT (by name; a path or a URL)."""
    return bool(inputs) and all(indexed_kind(p) is not None and (is_url(p) or not Path(p).is_dir())
                                for p in inputs)


@dataclass(frozen=True)
class IndexedSource:
    """An indexed input as a tile task gets it: where it is, which version of it the driver planned from (so a
    worker's cached index is keyed without asking the file system or the server again), and the cube its octree
    spans (so a task skips the inputs its box does not reach without opening them).

    Attributes
    ----------
    path : str
        Absolute path or URL.
    version : tuple
        :func:`source_version`.
    lo, hi : (3,) tuple of float
        Corners of the union of the octree's nodes, file units.
    """

    path: str
    version: tuple
    lo: tuple
    hi: tuple


def source_version(path: str | os.PathLike) -> tuple:
    """What identifies this version of an input: a local file's size and modification time, a URL's size, ETag
    and Last-Modified (one request)."""
    if is_url(path):
        v = validators(path)
        return ("url", v["size"], v["etag"], v["last_modified"])
    p = Path(path)
    try:
        st = p.stat()
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    return ("file", st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=256)
def _index(path: str, version: tuple) -> PointIndex:
    return read_index(path)


def cached_index(path: str | os.PathLike, version: tuple | None = None) -> PointIndex:
    """:func:`~tiled_gridpull.io.indexed.read_index`, kept per process for this ``version`` of the input
    (:func:`source_version`, asked when not given): a worker reads many tiles of one input."""
    # keyed by the absolute path: the driver plans from the path as given, its tasks read the resolved one
    path = resolved(path)
    return _index(path, version if version is not None else source_version(path))


def indexed_sources(inputs: list[str]) -> list[IndexedSource]:
    """The inputs as the tile tasks get them (their indexes read, and cached, here)."""
    out = []
    for p in inputs:
        version = source_version(p)
        ix = cached_index(p, version)
        lo = tuple(float(v) for v in ix.lo.min(axis=0, initial=np.inf))
        hi = tuple(float(v) for v in ix.hi.max(axis=0, initial=-np.inf))
        out.append(IndexedSource(resolved(p), version, lo, hi))
    return out


def plan_indexed(inputs: list[str], tiling: TilingConfig,
                 sources: list[IndexedSource] | None = None) -> tuple[TilePlan, dict, list[PointIndex]]:
    """The tile plan of indexed inputs from their headers and hierarchies (no point read).

    ``sources``: the inputs' :func:`indexed_sources`, when the caller has them (their versions are then not
    asked again: for a URL, one request per input).

    Returns
    -------
    plan : TilePlan
    scan : dict
        As :func:`tiled_gridpull.prepare.scan_inputs` (bounds, points, ``has_sensor`` False, crs, the
        ``attributes`` every input has), plus ``indexed``: the inputs' kinds.
    indexes : list of PointIndex
    """
    indexes = ([cached_index(p) for p in inputs] if sources is None
               else [cached_index(src.path, src.version) for src in sources])
    check_same_crs([(ix.crs, ix.path) for ix in indexes])
    n = int(sum(ix.points for ix in indexes))
    if n == 0:
        raise InputError(f"{', '.join(map(shown, inputs))}: no points")
    # an empty input's header bounds are whatever its writer put there (often zeros): they bound no point
    holding = [ix for ix in indexes if ix.points > 0]
    lo = np.min([ix.bounds[0] for ix in holding], axis=0)
    hi = np.max([ix.bounds[1] for ix in holding], axis=0)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
        raise InputError(f"{', '.join(map(shown, inputs))}: the header's bounds are not finite or inverted")
    # the attributes every input with points has (the first one's types)
    layout = [a for a in holding[0].attributes if all(a[0] in dict(ix.attributes) for ix in holding[1:])]
    scan = {"bounds": np.stack([lo, hi]), "points": n, "has_sensor": False, "attributes": layout,
            "crs": next((ix.crs for ix in indexes if ix.crs), None),
            "indexed": sorted({ix.kind for ix in indexes})}
    return plan_tiles(scan["bounds"], n, tiling), scan, indexes


def _sample_depth(index: PointIndex, brick_size: float, budget: int) -> int:
    """The depth above which the octree is read as a subsample: deep enough that a node's grid cell is no larger
    than a brick, shallow enough to stay within ``budget`` points."""
    depths = index.keys[:, 0]
    edge = float((index.hi[0] - index.lo[0]).max()) * 2.0 ** depths[0] if len(depths) else 0.0
    depth = 0
    while depth <= int(depths.max(initial=0)):
        if index.counts[depths <= depth].sum() > budget:
            break
        depth += 1
        if edge / 128 / 2.0 ** (depth - 1) <= brick_size:
            break
    return max(depth, 1)


def _box_tiles(plan: TilePlan, lo: np.ndarray, hi: np.ndarray) -> set:
    """Tiles whose block overlaps any of the boxes [lo_i, hi_i] (world units)."""
    a, b = plan.tile_span(plan.lattice.to_index(lo), plan.lattice.to_index(hi))
    out = set()
    for (i0, j0, k0), (i1, j1, k1) in zip(a, b):
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                for k in range(k0, k1 + 1):
                    out.add((i, j, k))
    return out


def _sample(indexes: list[PointIndex], plan: TilePlan, budget: int):
    """Every input with its sample depth and its shallow levels' points (clouds)."""
    brick = BRICK * plan.lattice.cell_size
    per_input = max(budget // len(indexes), 1)
    for ix in indexes:
        depth = _sample_depth(ix, brick, per_input)
        yield ix, depth, list(read_levels(ix, depth))


def candidate_tiles(indexes: list[PointIndex], plan: TilePlan, budget: int = SAMPLE_POINTS) -> list[tuple]:
    """Every tile that may hold points (a superset of those that do), sorted."""
    tiles: set = set()
    for ix, depth, parts in _sample(indexes, plan, budget):
        for cloud in parts:
            _, t = plan.tiles_of(plan.lattice.to_index(cloud.xyz))
            tiles.update(map(tuple, np.unique(t, axis=0).tolist()))
        deep = ix.keys[:, 0] >= depth
        if deep.any():
            lo = np.maximum(ix.lo[deep], ix.bounds[0])
            hi = np.minimum(ix.hi[deep], ix.bounds[1])
            tiles |= _box_tiles(plan, lo, hi)
    return sorted(tiles)


def _read_box(plan: TilePlan, tile: tuple) -> tuple[np.ndarray, np.ndarray]:
    """World box holding every point the tile's block may receive (``tiles_of`` gives border tiles the points
    beyond the lattice's edge: their side of the box is open)."""
    T, O = plan.config.tile_cells, plan.reach_cells
    t = np.asarray(tile)
    lo_i = (t * T - O - 1).astype(np.float64)
    hi_i = ((t + 1) * T + O + 1).astype(np.float64)
    lo = plan.lattice.to_world(lo_i[None])[0]
    hi = plan.lattice.to_world(hi_i[None])[0]
    return np.where(t == 0, -np.inf, lo), np.where(t == np.asarray(plan.tile_range) - 1, np.inf, hi)


def read_tile(inputs: list, plan: TilePlan, tile: tuple, out_dir: str,
              attributes: list | tuple = ()) -> tuple[TileSpec | None, int]:
    """One tile's task: read its points from the indexed ``inputs`` (:class:`IndexedSource`, or paths and URLs)
    and write its spill file and occupancy in ``out_dir`` (the job's points directory). An input whose octree
    does not reach the tile's box is not opened. ``attributes`` (``[(name, numpy type string)]``): the point
    attributes to keep beside the spill file (:func:`~tiled_gridpull.partition.partition`).

    Returns
    -------
    spec : TileSpec or None
        None when the tile holds no point.
    owned : int
        Points read whose owner is this tile (:meth:`TilePlan.owner_of`): summed over the tiles, every point of
        the inputs once, which is how the driver checks that no point was lost between the tasks.
    """
    tile = tuple(int(v) for v in tile)
    owned = 0

    def chunks():
        nonlocal owned
        for cloud in _tile_clouds(inputs, plan, tile, attributes=bool(attributes)):
            owned += int(_owned(plan, tile, cloud.xyz).sum())
            yield cloud

    specs = partition(chunks(), plan, out_dir, False, only=tile, attributes=attributes)
    return (specs[0] if specs else None), owned


def _tile_clouds(inputs: list, plan: TilePlan, tile: tuple, attributes: bool = False) -> Iterator[PointCloud]:
    """The points of the inputs in the tile's read box (:func:`_read_box`), input by input in stream order."""
    lo, hi = _read_box(plan, tile)
    for src in inputs:
        if not isinstance(src, IndexedSource):
            src = indexed_sources([src])[0]
        s_lo, s_hi = np.asarray(src.lo), np.asarray(src.hi)
        if not (np.all(s_lo <= hi) and np.all(s_hi >= lo)):
            continue
        ix = cached_index(src.path, src.version)
        # an open side (a border tile) reaches as far as the input's octree does
        yield from read_box(ix, np.where(np.isinf(lo), s_lo, lo), np.where(np.isinf(hi), s_hi, hi),
                            attributes=attributes)


def _owned(plan: TilePlan, tile: tuple, xyz: np.ndarray) -> np.ndarray:
    """(N,) bool: the points whose owner is ``tile``."""
    return np.all(plan.owner_of(plan.lattice.to_index(xyz)) == tile, axis=1)


def indexed_degeneracy(inputs: list[IndexedSource], plan: TilePlan, tiles: list[tuple]) -> str | None:
    """Whether the indexed inputs' points are identical or collinear, by the rule streamed inputs are refused by
    (:func:`~tiled_gridpull.cloud.stream_degeneracy`; coplanar points are a legal scene).

    The octrees' root nodes (a few thousand points each, a subset) settle it unless they look degenerate
    themselves; only then is every point read on the driver, twice, tile by tile (each tile's own points, so
    every point once, as the tile tasks read them).
    """
    root = [c.xyz for src in inputs for c in read_levels(cached_index(src.path, src.version), 1)]

    def chunks():
        for t in tiles:
            t = tuple(int(v) for v in t)
            for cloud in _tile_clouds(inputs, plan, t):
                yield cloud.xyz[_owned(plan, t, cloud.xyz)]

    return stream_degeneracy(chunks, reject_planar=False, sample=np.concatenate(root) if root else None)


def estimate_specs(indexes: list[PointIndex], plan: TilePlan,
                   budget: int = SAMPLE_POINTS) -> tuple[list[TileSpec], dict, float]:
    """A dry run's tiles without reading them: points per tile from the subsample (its own points) plus every
    deeper node's count spread over its cube by volume; occupied bricks from the subsample.

    Returns
    -------
    specs : list of TileSpec
        ``n_points`` estimated; no spill paths.
    occupancy : dict
        Tile index -> (BX, BY, BZ) bool, from the subsample.
    share : float
        Share of the points the subsample holds.
    """
    occupancy: dict = {}
    counts: dict = {}
    sampled = 0
    for ix, depth, parts in _sample(indexes, plan, budget):
        occ: dict = {}
        for spec in partition(parts, plan, None, False, occupancy=occ):
            counts[spec.index] = counts.get(spec.index, 0) + spec.n_points
        for t, grid in occ.items():
            occupancy[t] = occupancy[t] | grid if t in occupancy else grid
        sampled += sum(len(c) for c in parts)
        deep = np.flatnonzero(ix.keys[:, 0] >= depth)
        for r in deep:
            lo = np.maximum(ix.lo[r], ix.bounds[0])
            hi = np.minimum(ix.hi[r], ix.bounds[1])
            vol = np.prod(np.maximum(hi - lo, 1e-12))
            for t in _box_tiles(plan, lo[None], hi[None]):
                blo, bhi = _read_box(plan, t)
                blo, bhi = np.maximum(blo, plan.bounds[0]), np.minimum(bhi, plan.bounds[1])
                share = np.prod(np.maximum(np.minimum(hi, bhi) - np.maximum(lo, blo), 0) + 1e-12 * (hi == lo)) / vol
                counts[t] = counts.get(t, 0) + float(ix.counts[r]) * float(min(share, 1.0))
    bshape = tuple(int(v) for v in -(-np.asarray(plan.spec((0, 0, 0)).block.shape) // BRICK))
    specs = []
    for t in sorted(counts):
        n = int(round(counts[t]))
        if n == 0:
            continue
        occ = occupancy.setdefault(t, np.zeros(bshape, bool))
        specs.append(plan.spec(t, n_points=n, occupied_bricks=int(occ.sum())))
    total = sum(ix.points for ix in indexes)
    return specs, occupancy, sampled / total if total else 0.0


def dense_region(path: str | os.PathLike, limit: int, regions: int = 8):
    """Up to ``limit`` points of an indexed input at full density, for measuring its sample spacing.

    An indexed input's first points are its coarsest level of detail, spread thin over the whole survey, so
    they say nothing of its spacing. This reads every point (all levels) inside the cubes of ``regions`` of the
    deepest nodes, chosen at even steps of their cumulative point count: regions in proportion to where the
    points are, as the first points of a plain file sample them. None for an input without points.
    """
    ix = cached_index(path)
    if len(ix.keys) == 0:
        return None
    deep = np.flatnonzero(ix.keys[:, 0] >= ix.keys[:, 0].max() - 1)
    cum = np.cumsum(ix.counts[deep])
    steps = (np.arange(regions) + 0.5) / regions * cum[-1]
    chosen = np.unique(deep[np.searchsorted(cum, steps)])
    per_region = max(limit // len(chosen), 1)
    parts = []
    for r in chosen:
        got = 0
        for cloud in read_box(ix, ix.lo[r], ix.hi[r]):
            parts.append(cloud.xyz[:per_region - got])
            got += len(parts[-1])
            if got >= per_region:
                break
    if not parts:
        return None
    return PointCloud(np.concatenate(parts), crs=ix.crs, source=str(path))
