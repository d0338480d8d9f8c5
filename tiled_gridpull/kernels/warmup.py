"""The kernels a tiled job runs, with the argument types it calls them with: compiled ahead of the tiles.

numba compiles a kernel on its first call and caches the machine code beside the module (``__pycache__``), so a
first job on a machine spent most of its first tile compiling, one kernel after the other, in every worker at
once, with nothing said on screen. Knowing the signatures lets a job

* tell whether numba's cache already holds them (:func:`cold_kernels`) and say that it is compiling;
* compile them before the tiles (:func:`compile_kernels`), a share per worker (:func:`split`): each kernel is
  compiled once on the machine, the workers load the others' from the cache.

``tests/test_kernels_warmup.py`` checks that a tile's solve and mesh call nothing but these signatures (a kernel
called with other types would be compiled again at its first call, the warm-up wasted).
"""

from __future__ import annotations

import importlib
import time

from numba import types

__all__ = ["KERNELS", "TILED_ONLY", "kernel", "cold_kernels", "compile_kernels", "split", "estimate_seconds"]


def _c(dtype, ndim: int) -> types.Array:
    return types.Array(dtype, ndim, "C")


_F32, _F64, _I32, _I64, _U8 = types.float32, types.float64, types.int32, types.int64, types.uint8
_F, _TABLE = _c(_F32, 1), _c(_I32, 3)  # a band field (slots,), the brick table

#: ``"module.kernel"`` -> (argument types, seconds of one core to compile it on a cold cache, measured on a
#: 2-core development machine; they order the work and make the estimate said on screen).
KERNELS: dict[str, tuple[tuple, float]] = {
    "band.window_any": ((_c(_U8, 3), _I64, _I64, _I64), 1.0),
    "band.scatter_cells": ((_c(_I64, 2), _TABLE, _I64), 0.2),
    "band.sparse_window_any": ((_c(_U8, 2), _TABLE, types.Array(_I64, 2, "F"), _I64, _I64, _I64, _I64), 2.0),
    "band.all_corners": ((_c(_U8, 2), _TABLE, types.Array(_I64, 2, "F"), _c(_I64, 1)), 1.1),
    "band.pack_flags": ((_c(_U8, 2),) * 4 + (_c(_I64, 1),), 0.9),
    "band.brick_neighbors": ((_c(_I32, 2), _TABLE), 0.3),
    "blend.blend_bricks": ((_c(_I64, 2), _c(_F32, 2), _c(_U8, 2), _I64, _c(_I64, 1), _c(_I64, 1), _c(_I64, 2),
                            _c(_I64, 2), _c(_I64, 1), _c(_I64, 2), _c(_I64, 2), _c(_I64, 1), _c(_I64, 1),
                            _c(_F32, 2), _c(_U8, 2)), 4.1),
    "bridge.bin_ground": ((_c(_F64, 1),) * 3 + (_F64, _I64, _I64, _F64), 0.7),
    "bridge.fit_columns": ((_c(_F64, 3), _F64, _c(_F64, 2), _F64, _F64, _I64, _F64, _F64, _F64, _c(_F64, 3), _F64),
                           4.6),
    "bridge.flag_bridged_cells": ((_c(_U8, 1), _c(_U8, 1), _TABLE, _c(_I64, 2), _c(_I64, 1), _I64, _I64, _I64), 0.8),
    "bridge.bin_sensor": ((_c(_F64, 1),) * 6 + (_F64, _I64, _I64, _F64), 0.7),
    "bridge.bin_top": ((_c(_F64, 1),) * 3 + (_F64, _I64, _I64), 0.3),
    "bridge.bin_low": ((_c(_F64, 1),) * 3 + (_F64, _I64, _I64), 0.7),
    "bridge.pierced_columns": ((_c(_F64, 1),) * 6 + (_c(_F64, 2),) * 4 + (_F64,) * 5, 1.0),
    "bridge.clear_pierced_gaps": ((_c(types.boolean, 2), _c(_I32, 2), _c(_F64, 3), _I64, _c(_F64, 2), _F64, _F64),
                                  0.3),
    "bridge.object_bins": ((_c(_F64, 2), _I64, _F64), 2.6),
    "bridge.hidden_from_sensor": ((_c(_F64, 2), _c(_F64, 2), _c(_F64, 3), _c(_F64, 3), _c(_F64, 2),
                                   _c(types.boolean, 2), _F64, _F64, _F64, _F64, _F64), 1.8),
    "graph.vertex_components": ((_I64, _c(_I64, 2)), 0.6),
    "interp.sample_field": ((_F, _TABLE, _c(_I64, 1), _c(_F32, 2), _F32), 2.0),
    "losses.query_losses": ((_F, _c(_U8, 1), _TABLE, _c(_I64, 1), _c(_F32, 2), _c(_F32, 2), _c(_I32, 1),
                             _c(_F32, 2), _I64, _F32, _F32, _F32, _c(_I64, 2), _c(_F32, 2), _c(_F32, 2)), 6.9),
    "losses.scatter_add": ((_F, _c(_I64, 2), _c(_F32, 2), _F32), 0.1),
    "mc.count_triangles": ((_F, _c(_U8, 1), _TABLE, _c(_I32, 2), _c(_I64, 1), _c(_I64, 1), _F32), 3.1),
    "mc.emit_triangles": ((_F, _c(_U8, 1), _TABLE, _c(_I32, 2), _c(_I64, 1), _c(_I64, 1), _F32, _c(_I64, 2),
                           _c(_I64, 1), _c(_I64, 2), _c(_F64, 2)), 2.6),
    "mc.edge_points": ((_F, _TABLE, _c(_I64, 1), _c(_I64, 1), _F64, _F64), 0.9),
    "nn.nearest_from_candidates": ((_c(_F32, 2), _c(_I32, 2), _c(_F32, 2), _c(_I64, 1), _c(_F32, 2),
                                    _c(_I64, 1), _F), 1.1),
    "planes.neighbourhood_planes": ((_c(_F64, 2), _c(_I64, 2), _c(_F64, 2), _c(_F64, 2)), 2.8),
    "sampling.draw_queries": ((_c(_F32, 2), _I64, _I64, _F32, _c(_I64, 1), _c(_F32, 2)), 0.6),
    "sampling.morton_codes": ((_c(_F32, 2),), 0.8),
    "step.tv_inverse_norms": ((_F, _c(_U8, 1), _c(_I32, 2), _F), 5.0),
    "step.tv_adam_step": ((_F, _F, _F, _F, _F, _c(_U8, 1), _c(_I32, 2), _F, _I64, _F32, _F32, _F32, _F32, _F32,
                           types.boolean), 7.0),
}


#: the kernels only a tiled job calls (blending tiles, bridging scan-line gaps); one-shape mode calls the others
TILED_ONLY = ("blend.blend_bricks", "bridge.bin_ground", "bridge.fit_columns", "bridge.bin_sensor",
              "bridge.flag_bridged_cells", "bridge.bin_top", "bridge.object_bins", "bridge.hidden_from_sensor",
              "bridge.bin_low", "bridge.pierced_columns", "bridge.clear_pierced_gaps")


def kernel(name: str):
    """The numba dispatcher of ``"module.kernel"`` (a key of :data:`KERNELS`)."""
    module, func = name.split(".")
    return getattr(importlib.import_module(f"{__package__}.{module}"), func)


def _in_cache(name: str) -> bool | None:
    """Whether numba's on-disk cache holds ``name`` compiled for its signature (an index entry for this source
    file's stamp, this CPU and this bytecode); None where it cannot tell (numba's caching internals changed)."""
    disp = kernel(name)
    try:
        cache = disp._cache
        index = cache._cache_file._load_index()  # {} when the file's source stamp differs from the index's
        key = cache._index_key(KERNELS[name][0], disp.targetctx.codegen())
    except Exception:  # noqa: BLE001 - private numba API: unknown, not an error
        return None
    return key in index


def cold_kernels(names=None) -> list[str] | None:
    """The kernels (of ``names``, default all of :data:`KERNELS`) that numba's cache does not hold yet and that
    will therefore be compiled; None where that cannot be told."""
    out = []
    for name in names if names is not None else KERNELS:
        hit = _in_cache(name)
        if hit is None:
            return None
        if not hit:
            out.append(name)
    return out


def compile_kernels(names) -> dict[str, float]:
    """Compile (or load from numba's cache) each of ``names`` for its signature; seconds each took."""
    took = {}
    for name in names:
        t0 = time.perf_counter()
        kernel(name).compile(KERNELS[name][0])
        took[name] = time.perf_counter() - t0
    return took


def split(names, parts: int) -> list[list[str]]:
    """``names`` in ``parts`` shares of about equal compile time (costliest first, each to the lightest share);
    empty shares are left out."""
    shares: list[list[str]] = [[] for _ in range(max(1, parts))]
    load = [0.0] * len(shares)
    for name in sorted(names, key=lambda n: -KERNELS[n][1]):
        i = load.index(min(load))
        shares[i].append(name)
        load[i] += KERNELS[name][1]
    return [s for s in shares if s]


def estimate_seconds(names, parts: int = 1) -> float:
    """Seconds to compile ``names`` on ``parts`` cores (the longest share of :func:`split`)."""
    return max((sum(KERNELS[n][1] for n in share) for share in split(names, parts)), default=0.0)
