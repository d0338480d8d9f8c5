"""A distance field on a band: the solver's output, the blender's and the mesher's input."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .band import Band
from .kernels import interp as ki

__all__ = ["Field"]


@dataclass(eq=False)
class Field:
    """Values on the vertices of a band.

    Attributes
    ----------
    band : Band
    values : (n_bricks, 512) float32
        Distance in **cells** at every slot (multiply by ``band.lattice.cell_size`` for world units).
        Slots that are not parameters hold their initial values and are never used by marching cubes.
    signed : bool
        False for unsigned (UDF) fields.
    info : dict
        Solve statistics (timings, losses, counts) for reports.
    """

    band: Band
    values: np.ndarray
    signed: bool = True
    info: dict = field(default_factory=dict)

    @property
    def lattice(self):
        """The lattice of the band."""
        return self.band.lattice

    def sample(self, world: np.ndarray, fill: float = np.nan) -> tuple[np.ndarray, np.ndarray]:
        """Field value (world units) and gradient (unitless) at world points.

        Parameters
        ----------
        world : (N, 3) float
        fill : float
            Value where the point's cell is not in the band.

        Returns
        -------
        values : (N,) float64
        gradients : (N, 3) float64
        """
        lat = self.band.lattice
        pts = lat.to_local32(world)
        f, g = ki.sample_field(self.values.reshape(-1), self.band.brick_table,
                               np.asarray(lat.shape, np.int64), pts, np.float32(0.0))
        out = f.astype(np.float64) * lat.cell_size
        missing = self._missing(pts)
        out[missing] = fill
        return out, g.astype(np.float64)

    def _missing(self, pts: np.ndarray) -> np.ndarray:
        cells = np.clip(np.floor(pts).astype(np.int64), 0, np.asarray(self.band.lattice.n_cells) - 1)
        miss = np.zeros(len(pts), bool)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    v = cells + np.array([dx, dy, dz])
                    b = self.band.brick_table[v[:, 0] >> 3, v[:, 1] >> 3, v[:, 2] >> 3]
                    miss |= b < 0
        return miss
