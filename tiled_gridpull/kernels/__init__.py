"""Numba kernels: arrays in, arrays out; no I/O, no logging, no Python objects in hot loops.

Every kernel here trusts its inputs (dtypes, shapes, contiguity). The validating wrappers live in the domain
modules of :mod:`tiled_gridpull` (``band``, ``solver``, ``mesh``, ...).

Brick layout shared by all kernels
----------------------------------
The band is stored in bricks of ``B = 8`` vertices per axis. A field is a ``(n_bricks, 512)`` float32 array; the
vertex at local position ``(x, y, z)`` of brick ``b`` lives in slot ``b * 512 + x * 64 + y * 8 + z``. A dense
``brick_table`` over the brick grid maps brick coordinates to brick numbers (-1 where absent).
"""

BRICK = 8
BRICK_SHIFT = 3
BRICK_MASK = 7
BRICK_VOLUME = 512

# Per-slot flags (uint8). Cell flags describe the cell whose lowest corner is the slot's vertex.
PARAM = 1        # vertex is an optimisation variable (in the M2 band)
CELL_OPT = 2     # all 8 corners of the cell are parameters: the cell is "optimized", marching cubes may use it
CELL_PULL = 4    # cell is in the M1 band: queries falling in it carry the pull loss
CELL_OCC = 8     # cell holds at least one input point
