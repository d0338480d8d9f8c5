"""A finished or unfinished job directory opened for inspection (the notebooks' view of a tiled job).

:func:`load_job` returns a :class:`JobView`: tile points, solved fields, slices of the SDF band, meshed pieces and
neighbours, read from the files of :mod:`tiled_gridpull.jobdir`.
"""

from __future__ import annotations

from dataclasses import fields as dc_fields
from pathlib import Path

import numpy as np

from .errors import InputError
from .jobdir import JobPaths, neighbors_of, read_manifest
from .lattice import Lattice
from .mesh import Mesh
from .partition import read_tile_points
from .report import REPORT_NAME, read_report
from .stitch import load_piece, weld_pieces
from .tile_field import load_tile_field
from .tiling import TilingConfig

__all__ = ["JobView", "load_job"]


class JobView:
    """Read access to a job directory (see :mod:`tiled_gridpull.jobdir` for its layout).

    Parameters
    ----------
    job_dir : str or Path
        Holds at least ``manifest.json``; fields and pieces exist for the tiles that were solved and meshed.

    Attributes
    ----------
    root : Path
    manifest : dict
        The raw manifest (plan, tiles, inputs).
    specs : dict[str, TileSpec]
        Tiles by name (``tile_i_j_k``), in tile order.
    tiling : TilingConfig
    lattice : Lattice
        The job lattice.
    report : dict or None
        ``report.json`` when the job finished.
    """

    def __init__(self, job_dir: str | Path):
        self.root = Path(job_dir)
        self.paths = JobPaths(self.root)
        if not self.paths.manifest.is_file():
            raise InputError(f"{job_dir}: no manifest.json (not a tiled job directory)")
        self.manifest, specs = read_manifest(self.paths.manifest)
        self.specs = {s.name: s for s in sorted(specs, key=lambda s: s.index)}
        plan = self.manifest["plan"]
        names = {f.name for f in dc_fields(TilingConfig)}
        self.tiling = TilingConfig(**{k: v for k, v in plan["config"].items() if k in names})
        self.lattice = Lattice.from_dict(plan["lattice"])
        rp = self.root / REPORT_NAME
        self.report = read_report(rp) if rp.is_file() else None

    def __repr__(self) -> str:
        return f"JobView({str(self.root)!r}, {len(self.specs)} tiles)"

    def _spec(self, name: str):
        try:
            return self.specs[name]
        except KeyError:
            raise InputError(f"{self.root}: no tile named {name!r}") from None

    def core_bounds(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """World corners ``(lo, hi)`` (3,) float64 of a tile's core."""
        s = self._spec(name)
        cell = self.lattice.cell_size
        origin = np.asarray(self.lattice.origin)
        return origin + np.asarray(s.core_lo) * cell, origin + np.asarray(s.core_hi) * cell

    def busiest_tile(self) -> str:
        """Name of the tile with the most points."""
        return max(self.specs.values(), key=lambda s: s.block_points).name

    def tile_points(self, name: str, *, halo: bool = False) -> np.ndarray:
        """A tile's points (its whole block: core plus overlap), (N, 3) float64 world coordinates; with ``halo``
        also the points a denoising job read around the block (``TilingConfig.halo``; none without denoising)."""
        s = self._spec(name)
        xyz, _ = read_tile_points(s)
        if not halo:
            xyz = xyz[s.in_block(xyz)]
        return xyz + s.block.low_corner

    def neighbours(self, name: str, *, meshed: bool = True) -> list[str]:
        """Names of the (up to 26) tiles around ``name``; with ``meshed`` only those whose piece exists."""
        s = self._spec(name)
        out = [n.name for n in neighbors_of(s, {t.index: t for t in self.specs.values()})]
        return [n for n in out if not meshed or self.paths.piece(self.specs[n]).is_file()]

    def tile_mesh(self, name: str) -> Mesh:
        """The piece a tile meshed (its core, blended with its neighbours), before the job drops the mesh's small
        parts (``min_component_cells``, judged across tiles)."""
        p = self.paths.piece(self._spec(name))
        if not p.is_file():
            raise InputError(f"{name}: no mesh piece ({p} missing: tile not solved or not meshed yet)")
        piece = load_piece(p)
        return piece.mesh({"tile": name})

    def welded(self, names: list[str]) -> Mesh:
        """The pieces of several tiles welded by edge key, as the job does (shared border vertices merged; its
        small parts kept)."""
        return weld_pieces([load_piece(self.paths.piece(self._spec(n))) for n in names])

    def shared_vertices(self, a: str, b: str) -> int:
        """Vertices the pieces of tiles ``a`` and ``b`` share (same lattice edge key): welded along their seam."""
        ka = load_piece(self.paths.piece(self._spec(a))).keys
        kb = load_piece(self.paths.piece(self._spec(b))).keys
        return int(len(np.intersect1d(ka[ka >= 0], kb[kb >= 0])))

    def tile_field(self, name: str):
        """A solved tile's field (:class:`~tiled_gridpull.blend.TileField`, values in cells, unblended)."""
        s = self._spec(name)
        p = self.paths.field(s)
        if not p.is_file():
            raise InputError(f"{name}: no solved field ({p} missing)")
        return load_tile_field(p, s, self.tiling.overlap_cells)

    def field_slice(self, name: str, axis: int = 2, position: float | None = None
                    ) -> tuple[np.ndarray, tuple[float, float, float, float], float]:
        """One plane of a tile's solved field across its whole block (the SDF band, unblended).

        Parameters
        ----------
        name : str
            Tile name.
        axis : {0, 1, 2}
            Normal of the plane (2: a horizontal slice).
        position : float, optional
            World coordinate of the plane along ``axis`` (snapped to the lattice); default: the median of the
            tile's points.

        Returns
        -------
        values : (n_a, n_b) float64
            Signed distance in world units (cells x cell size) at the block's lattice vertices of the plane,
            NaN where the vertex is not a parameter of the band; rows follow the first remaining axis, columns
            the second (``imshow(values.T, origin="lower", extent=extent)`` draws it the usual way up).
        extent : (a0, a1, b0, b1)
            World extent along the two remaining axes.
        position : float
            World coordinate of the plane actually used.
        """
        if axis not in (0, 1, 2):
            raise InputError(f"axis must be 0, 1 or 2, got {axis!r}")
        fld = self.tile_field(name)
        lat = self.lattice
        if position is None:
            position = float(np.median(self.tile_points(name)[:, axis]))
        k = int(round((position - lat.origin[axis]) / lat.cell_size))
        k = int(np.clip(k, fld.block_lo[axis], fld.block_hi[axis]))
        a, b = [ax for ax in (0, 1, 2) if ax != axis]
        ga = np.arange(fld.block_lo[a], fld.block_hi[a] + 1)
        gb = np.arange(fld.block_lo[b], fld.block_hi[b] + 1)
        A, B = np.meshgrid(ga, gb, indexing="ij")
        g = np.empty((A.size, 3), np.int64)
        g[:, a], g[:, b], g[:, axis] = A.ravel(), B.ravel(), k
        vals, mask = fld.lookup(g)
        out = np.where(mask, vals.astype(np.float64) * lat.cell_size, np.nan).reshape(A.shape)
        o, c = lat.origin, lat.cell_size
        extent = (o[a] + ga[0] * c, o[a] + ga[-1] * c, o[b] + gb[0] * c, o[b] + gb[-1] * c)
        return out, extent, o[axis] + k * c


def load_job(job_dir: str | Path) -> JobView:
    """Open a job directory for inspection (see :class:`JobView`).

    Parameters
    ----------
    job_dir : str or Path
        A tiled job's work directory (``<output>.job`` unless ``--work-dir`` named another).

    Returns
    -------
    JobView
        Its manifest and tiles; fields, pieces and points are read when asked for.
    """
    return JobView(job_dir)
