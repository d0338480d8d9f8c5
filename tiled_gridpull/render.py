"""Pictures of meshes, point clouds and error maps without a screen (pyvista, off-screen).

Off-screen rendering needs no X server: on Linux without ``DISPLAY`` VTK is pointed at EGL (``libEGL``, e.g.
Debian's ``libegl1`` + ``libegl-mesa0``, software-rendered by llvmpipe when there is no GPU) or else OSMesa;
``VTK_DEFAULT_OPENGL_WINDOW`` set by the user wins. When neither library exists the call fails with one line
instead of letting VTK crash the process. (The job's tile-layout picture, drawn with matplotlib, is in
:mod:`tiled_gridpull.tile_layout`.)

Geometry is shifted to its own centre before it reaches VTK, whose pipeline is float32: georeferenced inputs
(UTM-like coordinates) render as crisply as data near the origin.

Every ``*_image`` function returns an ``(H, W, 3) uint8`` RGB array; the others write it as a PNG atomically.
"""

from __future__ import annotations

import ctypes.util
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ._optional import require
from .errors import ConfigError, InputError, MissingDependencyError
from .images import check_size, save_png
from .mesh import Mesh, colors_unit

__all__ = ["render_mesh", "render_mesh_image", "render_meshes_image", "vertex_errors", "VIEWS", "COLOR_BY",
           "attribute_colors"]

VIEWS = ("iso", "top", "front", "side")
MESH_COLOR = "#d8c7a6"
POINT_COLOR = "#c0392b"
PIECE_COLORS = ("#4c72b0", "#dd8452", "#55a868", "#c44e52", "#8172b3", "#937860", "#da8bc3", "#8c8c8c",
                "#ccb974", "#64b5cd")


# ---------------------------------------------------------------------------------------------------------------
# helpers


def _check_view(view: str) -> str:
    if view not in VIEWS:
        raise ConfigError(f"view must be one of {', '.join(VIEWS)}; got {view!r}")
    return view


def _points_array(cloud) -> np.ndarray:
    """(N, 3) float64 from an array or a :class:`~tiled_gridpull.cloud.PointCloud`."""
    xyz = np.asarray(getattr(cloud, "xyz", cloud), dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"point cloud must be an (N, 3) array, got shape {xyz.shape}")
    return xyz[np.all(np.isfinite(xyz), axis=1)]


def _subsample(xyz: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
    if len(xyz) <= max_points:
        return xyz
    rng = np.random.default_rng(seed)
    return xyz[np.sort(rng.choice(len(xyz), size=max_points, replace=False))]


def _prepare_offscreen() -> None:
    """Point VTK at a window class that works without a screen, or fail with one line.

    VTK's own fallback order is X, then EGL, then OSMesa; with no library for any of them it segfaults, which
    would take a whole job down. Linux only (other platforms render off-screen natively).
    """
    if not sys.platform.startswith("linux") or os.environ.get("VTK_DEFAULT_OPENGL_WINDOW"):
        return
    if os.environ.get("DISPLAY"):
        return  # X first; VTK falls back to EGL/OSMesa by itself if the server is unreachable
    if ctypes.util.find_library("EGL"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"
    elif ctypes.util.find_library("OSMesa"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkOSMesaRenderWindow"
    else:
        raise MissingDependencyError(
            "off-screen rendering needs an OpenGL library and found neither libEGL nor libOSMesa "
            "(Debian/Ubuntu: apt-get install libegl1 libegl-mesa0), or a DISPLAY")


def _plotter(size: tuple[int, int]):
    pv = require("pyvista", "rendering")
    _prepare_offscreen()
    pl = pv.Plotter(off_screen=True, window_size=list(size))
    pl.set_background("white")
    return pv, pl


def _set_view(pl, view: str) -> None:
    if view == "top":
        pl.view_xy()
    elif view == "front":
        pl.view_xz()
    elif view == "side":
        pl.view_yz()
    else:
        pl.view_isometric()
    pl.reset_camera()
    pl.camera.zoom(1.3)  # reset_camera frames the bounding sphere: generous margins otherwise


def _snapshot(pl, size: tuple[int, int]) -> np.ndarray:
    try:
        img = pl.screenshot(return_img=True)
    finally:
        pl.close()
    if img is None or img.ndim != 3 or img.shape[:2] != (size[1], size[0]):
        got = None if img is None else img.shape
        raise MissingDependencyError(f"off-screen rendering returned no usable image (got {got}); check the "
                                     "OpenGL libraries (libEGL/libOSMesa)")
    return np.ascontiguousarray(img[..., :3], dtype=np.uint8)


# ---------------------------------------------------------------------------------------------------------------
# meshes and clouds


def vertex_errors(mesh: Mesh, gt: Mesh) -> np.ndarray:
    """Distance from every vertex of ``mesh`` to the surface of ``gt`` (closest point on any triangle).

    Parameters
    ----------
    mesh : Mesh
        ``V`` vertices, world coordinates.
    gt : Mesh
        Ground truth in the same frame and units.

    Returns
    -------
    (V,) float64
        Unsigned distances, in the meshes' units (metres for LiDAR scenes).
    """
    from .metrics import point_to_mesh

    if gt.n_faces == 0:
        raise InputError("ground-truth mesh has no faces")
    if mesh.n_vertices == 0:
        return np.zeros(0, np.float64)
    dist, _ = point_to_mesh(mesh.vertices, gt)
    return dist


def render_meshes_image(meshes: Sequence[Mesh], *, size: Sequence[int] = (1024, 768),
                        colors: Sequence[str] | None = None, cloud=None, scalars: np.ndarray | None = None,
                        clim: tuple[float, float] | None = None, scalar_title: str = "distance to ground truth",
                        cmap: str = "viridis", view: str = "iso", point_size: float = 2.0,
                        point_color: str = POINT_COLOR, max_points: int = 200_000, show_edges: bool = False,
                        centre: np.ndarray | None = None, seed: int = 0,
                        rgb: np.ndarray | None = None) -> np.ndarray:
    """Render several meshes (and optionally a point cloud) into one off-screen image.

    Parameters
    ----------
    meshes : sequence of Mesh
        World coordinates; empty meshes are skipped.
    size : (W, H) int
        Image size in pixels (16..8192 each).
    colors : sequence of str, optional
        One colour per mesh (matplotlib names or hex); default: :data:`MESH_COLOR` for a single mesh, a
        qualitative palette for several.
    cloud : (N, 3) float or PointCloud, optional
        Points drawn over the meshes (at most ``max_points``, a random subset beyond that).
    scalars : (V,) float, optional
        Per-vertex values of the *first* mesh shown as a colour map (e.g. :func:`vertex_errors`, in the
        mesh's units).
    clim : (lo, hi), optional
        Colour-map range; default ``(0, 99th percentile)`` so a few outliers do not wash the map out.
    scalar_title : str
        Title of the colour bar.
    cmap : str
        Matplotlib colour map name.
    view : {"iso", "top", "front", "side"}
        Camera direction: isometric, from +z, from -y, from +x.
    point_size : float
        Point size in pixels.
    point_color : str
    max_points : int
    show_edges : bool
        Draw triangle edges.
    centre : (3,) float, optional
        World point moved to the origin before rendering (default: centre of the geometry's bounding box).
    seed : int
        Seed of the point subsample.
    rgb : (V, 3) uint8, optional
        Per-vertex colours of the *first* mesh, drawn as they are (e.g. :func:`attribute_colors`); ``scalars``
        wins when both are given.

    Returns
    -------
    (H, W, 3) uint8
        RGB image.
    """
    size = check_size(size)
    view = _check_view(view)
    meshes = list(meshes)
    if scalars is not None:
        scalars = np.asarray(scalars, dtype=np.float64).reshape(-1)
        if not meshes or len(scalars) != meshes[0].n_vertices:
            raise InputError(f"scalars: need one value per vertex of the first mesh, got {len(scalars)}")
    if rgb is not None:
        rgb = np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)
        if not meshes or len(rgb) != meshes[0].n_vertices:
            raise InputError(f"rgb: need one colour per vertex of the first mesh, got {len(rgb)}")
    drawn = [m for m in meshes if m.n_faces > 0]
    pts = _subsample(_points_array(cloud), int(max_points), seed) if cloud is not None else None
    if not drawn and (pts is None or len(pts) == 0):
        raise InputError("nothing to render: no faces and no points")
    if centre is None:
        boxes = [np.stack([m.vertices.min(0), m.vertices.max(0)]) for m in drawn]
        if pts is not None and len(pts):
            boxes.append(np.stack([pts.min(0), pts.max(0)]))
        allb = np.concatenate(boxes)
        centre = (allb.min(0) + allb.max(0)) / 2
    centre = np.asarray(centre, dtype=np.float64)
    if colors is None:
        colors = [MESH_COLOR] if len(meshes) == 1 else [PIECE_COLORS[i % len(PIECE_COLORS)]
                                                        for i in range(len(meshes))]
    pv, pl = _plotter(size)
    try:
        for i, m in enumerate(meshes):
            if m.n_faces == 0:
                continue
            poly = pv.PolyData.from_regular_faces(m.vertices - centre, m.faces)
            kw = dict(show_edges=show_edges, edge_color="#555555", smooth_shading=True, split_sharp_edges=True)
            if i == 0 and scalars is not None:
                finite = scalars[np.isfinite(scalars)]
                if clim is None:
                    hi = float(np.percentile(finite, 99)) if len(finite) else 1.0
                    clim = (0.0, hi if hi > 0 else 1.0)
                poly.point_data["scalars"] = scalars
                pl.add_mesh(poly, scalars="scalars", cmap=cmap, clim=list(clim), **kw,
                            scalar_bar_args={"title": scalar_title, "color": "black", "fmt": "%.3g",
                                             "n_labels": 4, "title_font_size": 16, "label_font_size": 13,
                                             "vertical": False, "position_x": 0.25, "position_y": 0.02,
                                             "width": 0.5, "height": 0.09})
            elif i == 0 and rgb is not None:
                poly.point_data["RGB"] = rgb
                pl.add_mesh(poly, scalars="RGB", rgb=True, **kw)
            else:
                pl.add_mesh(poly, color=colors[i % len(colors)], **kw)
        if pts is not None and len(pts):
            pl.add_points(pts - centre, color=point_color, point_size=float(point_size),
                          render_points_as_spheres=False)
        _set_view(pl, view)
    except BaseException:
        pl.close()
        raise
    return _snapshot(pl, size)


#: what ``render --color`` colours a mesh by (its vertex attributes)
COLOR_BY = ("rgb", "intensity", "classification")


def attribute_colors(mesh: Mesh, color: str) -> dict:
    """How :func:`render_meshes_image` shows the vertex attribute ``color`` of ``mesh``.

    Parameters
    ----------
    mesh : Mesh
    color : {"rgb", "intensity", "classification"}
        ``rgb``: the colour as it is (scaled by :func:`~tiled_gridpull.mesh.color_full_scale`);
        ``intensity``: a grey ramp from its 1st to its 99th percentile; ``classification``: a qualitative map of
        the class codes.

    Returns
    -------
    dict
        Keyword arguments of :func:`render_meshes_image`: ``rgb``, or ``scalars``, ``clim``, ``cmap`` and
        ``scalar_title``.

    Raises
    ------
    ConfigError
        ``color`` is not one of :data:`COLOR_BY`.
    InputError
        The mesh does not carry that attribute.
    """
    if color not in COLOR_BY:
        raise ConfigError(f"color must be one of {', '.join(COLOR_BY)}, got {color!r}")
    attrs = mesh.vertex_attributes
    if color == "rgb":
        unit = colors_unit(attrs)
        if unit is None:
            raise InputError(f"{mesh.metadata.get('source', 'mesh')}: has no vertex colours (red, green, blue) to "
                             "render; reconstruct a coloured cloud with --attributes all or rgb")
        return {"rgb": np.round(unit * 255).astype(np.uint8)}
    if color not in attrs:
        raise InputError(f"{mesh.metadata.get('source', 'mesh')}: has no vertex {color} to render; reconstruct a "
                         f"cloud that has it with --attributes all")
    values = np.asarray(attrs[color], dtype=np.float64)
    if color == "intensity":
        lo, hi = (np.percentile(values, [1, 99]) if len(values) else (0.0, 1.0))
        return {"scalars": values, "clim": (float(lo), float(hi) if hi > lo else float(lo) + 1.0), "cmap": "gray",
                "scalar_title": "intensity"}
    hi = float(values.max()) if len(values) else 1.0
    return {"scalars": values, "clim": (0.0, max(hi, 1.0)), "cmap": "tab20", "scalar_title": "classification"}


def render_mesh_image(mesh: Mesh, *, size: Sequence[int] = (1024, 768), cloud=None, gt: Mesh | None = None,
                      errors: np.ndarray | None = None, clim: tuple[float, float] | None = None,
                      view: str = "iso", point_size: float = 2.0, max_points: int = 200_000,
                      show_edges: bool = False, color: str | None = None) -> np.ndarray:
    """Render one mesh off-screen, optionally with its point cloud and an error colour map.

    Parameters
    ----------
    mesh : Mesh
        World coordinates.
    size : (W, H) int
        Image size in pixels.
    cloud : (N, 3) float or PointCloud, optional
        Points overlaid on the mesh.
    gt : Mesh, optional
        Ground truth: vertices are coloured by their distance to it (:func:`vertex_errors`).
    errors : (V,) float, optional
        Precomputed per-vertex values to colour by instead (units of the mesh).
    clim : (lo, hi), optional
        Colour-map range in the mesh's units (default ``0`` to the 99th percentile).
    view : {"iso", "top", "front", "side"}
    point_size : float
        Pixels.
    max_points : int
        Cloud points drawn at most.
    show_edges : bool
    color : {"rgb", "intensity", "classification"}, optional
        Colour the mesh by this vertex attribute (:func:`attribute_colors`) instead of one colour; not with
        ``gt`` or ``errors``. ``clim``, when given, bounds intensity and classification.

    Returns
    -------
    (H, W, 3) uint8
    """
    if color is not None:
        if gt is not None or errors is not None:
            raise ConfigError("colour by an attribute or by the distance to a ground truth, not both")
        kw = attribute_colors(mesh, color)
        if clim is not None and "scalars" in kw:
            kw["clim"] = clim
        return render_meshes_image([mesh], size=size, cloud=cloud, view=view, point_size=point_size,
                                   max_points=max_points, show_edges=show_edges, **kw)
    if errors is None and gt is not None:
        errors = vertex_errors(mesh, gt)
    return render_meshes_image([mesh], size=size, cloud=cloud, scalars=errors, clim=clim, view=view,
                               point_size=point_size, max_points=max_points, show_edges=show_edges)


def render_mesh(mesh: Mesh, path: str | Path, *, size: Sequence[int] = (1024, 768), cloud=None,
                gt: Mesh | None = None, clim: tuple[float, float] | None = None, view: str = "iso",
                point_size: float = 2.0, max_points: int = 200_000, show_edges: bool = False,
                color: str | None = None) -> dict:
    """Render a mesh to a PNG file (see :func:`render_mesh_image`).

    Parameters
    ----------
    mesh : Mesh
    path : str or Path
        Output PNG, written atomically.
    size : (W, H) int
        Pixels.
    cloud, gt, clim, view, point_size, max_points, show_edges, color
        As in :func:`render_mesh_image`.

    Returns
    -------
    dict
        ``path``, ``size`` ``[W, H]``, and with ``gt`` an ``errors`` summary (``mean``, ``median``, ``p95``,
        ``max`` distance of the mesh's vertices to the ground truth, in the mesh's units).
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ConfigError(f"{path}: pictures are written as PNG (use a .png file name)")
    if color is not None:
        attribute_colors(mesh, color)  # refused before any rendering
        if gt is not None:
            raise ConfigError("colour by an attribute or by the distance to a ground truth, not both")
    errors = vertex_errors(mesh, gt) if gt is not None else None
    img = render_mesh_image(mesh, size=size, cloud=cloud, errors=errors, clim=clim, view=view,
                            point_size=point_size, max_points=max_points, show_edges=show_edges, color=color)
    save_png(img, path)
    out: dict = {"path": str(path), "size": [int(img.shape[1]), int(img.shape[0])]}
    if errors is not None and len(errors):
        out["errors"] = {"mean": float(errors.mean()), "median": float(np.median(errors)),
                         "p95": float(np.percentile(errors, 95)), "max": float(errors.max())}
    return out
