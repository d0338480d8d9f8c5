"""Pictures without a screen: meshes, point clouds and error maps (pyvista, off-screen) and the tile layout of a
job (matplotlib, Agg).

Off-screen rendering needs no X server: on Linux without ``DISPLAY`` VTK is pointed at EGL (``libEGL``, e.g.
Debian's ``libegl1`` + ``libegl-mesa0``, software-rendered by llvmpipe when there is no GPU) or else OSMesa;
``VTK_DEFAULT_OPENGL_WINDOW`` set by the user wins. When neither library exists the call fails with one line
instead of letting VTK crash the process. The tile-layout picture uses matplotlib's Agg canvas (no OpenGL at
all), so a job can always draw it.

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
from .mesh import Mesh

__all__ = ["render_mesh", "render_mesh_image", "render_meshes_image", "render_tile_layout",
           "render_tile_layout_image", "vertex_errors", "save_png", "png_bytes", "VIEWS"]

VIEWS = ("iso", "top", "front", "side")
MESH_COLOR = "#d8c7a6"
POINT_COLOR = "#c0392b"
PIECE_COLORS = ("#4c72b0", "#dd8452", "#55a868", "#c44e52", "#8172b3", "#937860", "#da8bc3", "#8c8c8c",
                "#ccb974", "#64b5cd")


# ---------------------------------------------------------------------------------------------------------------
# helpers


def _check_size(size: Sequence[int]) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ConfigError(f"image size must be two integers (width, height), got {size!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise ConfigError(f"image size {w} x {h}: width and height must be between 16 and 8192 pixels")
    return w, h


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


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an RGB(A) image as a PNG, atomically.

    Parameters
    ----------
    image : (H, W, 3) or (H, W, 4) uint8
    path : str or Path
        Target file (``.png``).

    Returns
    -------
    Path
    """
    from .io.atomic import atomic_path

    pil = require("PIL.Image", "writing PNG files")
    path = Path(path)
    with atomic_path(path) as tmp:
        pil.fromarray(np.asarray(image, dtype=np.uint8)).save(tmp, format="PNG")
    return path


def png_bytes(image: np.ndarray) -> bytes:
    """PNG-encoded bytes of an ``(H, W, 3)`` uint8 image (e.g. for ``IPython.display.Image``)."""
    import io

    pil = require("PIL.Image", "encoding PNG images")
    buf = io.BytesIO()
    pil.fromarray(np.asarray(image, dtype=np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


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
                        centre: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
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

    Returns
    -------
    (H, W, 3) uint8
        RGB image.
    """
    size = _check_size(size)
    view = _check_view(view)
    meshes = list(meshes)
    if scalars is not None:
        scalars = np.asarray(scalars, dtype=np.float64).reshape(-1)
        if not meshes or len(scalars) != meshes[0].n_vertices:
            raise InputError(f"scalars: need one value per vertex of the first mesh, got {len(scalars)}")
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


def render_mesh_image(mesh: Mesh, *, size: Sequence[int] = (1024, 768), cloud=None, gt: Mesh | None = None,
                      errors: np.ndarray | None = None, clim: tuple[float, float] | None = None,
                      view: str = "iso", point_size: float = 2.0, max_points: int = 200_000,
                      show_edges: bool = False) -> np.ndarray:
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

    Returns
    -------
    (H, W, 3) uint8
    """
    if errors is None and gt is not None:
        errors = vertex_errors(mesh, gt)
    return render_meshes_image([mesh], size=size, cloud=cloud, scalars=errors, clim=clim, view=view,
                               point_size=point_size, max_points=max_points, show_edges=show_edges)


def render_mesh(mesh: Mesh, path: str | Path, *, size: Sequence[int] = (1024, 768), cloud=None,
                gt: Mesh | None = None, clim: tuple[float, float] | None = None, view: str = "iso",
                point_size: float = 2.0, max_points: int = 200_000, show_edges: bool = False) -> dict:
    """Render a mesh to a PNG file (see :func:`render_mesh_image`).

    Parameters
    ----------
    mesh : Mesh
    path : str or Path
        Output PNG, written atomically.
    size : (W, H) int
        Pixels.
    cloud, gt, clim, view, point_size, max_points, show_edges
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
    errors = vertex_errors(mesh, gt) if gt is not None else None
    img = render_mesh_image(mesh, size=size, cloud=cloud, errors=errors, clim=clim, view=view,
                            point_size=point_size, max_points=max_points, show_edges=show_edges)
    save_png(img, path)
    out: dict = {"path": str(path), "size": [int(img.shape[1]), int(img.shape[0])]}
    if errors is not None and len(errors):
        out["errors"] = {"mean": float(errors.mean()), "median": float(np.median(errors)),
                         "p95": float(np.percentile(errors, 95)), "max": float(errors.max())}
    return out


# ---------------------------------------------------------------------------------------------------------------
# tile layout (matplotlib, no OpenGL)


def _columns(tiles: list[dict]) -> list[dict]:
    """Tiles merged per (i, j) column, as seen from above: summed points and times, worst status."""
    cols: dict[tuple, dict] = {}
    rank = {"solved": 0, "skipped": 1, "failed": 2}
    for t in tiles:
        i, j = int(t["index"][0]), int(t["index"][1])
        b = np.asarray(t["core_bounds"], dtype=np.float64)
        c = cols.setdefault((i, j), {"index": (i, j), "lo": b[0, :2], "hi": b[1, :2], "points": 0,
                                     "time_s": 0.0, "status": "solved", "layers": 0})
        c["points"] += int(t.get("points") or 0)
        c["time_s"] += float(t.get("solve_time_s") or 0.0)
        c["layers"] += 1
        st = t.get("status", "solved")
        if rank.get(st, 2) > rank.get(c["status"], 2):
            c["status"] = st
    return list(cols.values())


def _fmt_count(n: int) -> str:
    if n >= 1_000_000:
        return f"{n / 1e6:.1f}M"
    if n >= 10_000:
        return f"{n / 1e3:.0f}k"
    return str(n)


def render_tile_layout_image(report: dict, *, points: np.ndarray | None = None,
                             size: Sequence[int] = (1400, 700), max_labels: int = 150,
                             max_bars: int = 40) -> np.ndarray:
    """The tile layout of a job seen from above, and its per-tile timings.

    Left: the input points (a subsample, grey) and every tile's core rectangle, coloured by solve time and
    labelled ``i,j``, point count and seconds (tiles stacked along z are summed into their column and marked
    ``xK``); failed tiles are hatched red, skipped ones grey. Right: solve and mesh time per tile (a histogram
    when there are more than ``max_bars`` tiles).

    Parameters
    ----------
    report : dict
        A job report (:func:`tiled_gridpull.report.build_report`): ``tiles`` with ``index``, ``core_bounds``
        (world, ``[[x0, y0, z0], [x1, y1, z1]]``), ``points``, ``solve_time_s``, ``mesh_time_s``, ``status``;
        ``lattice`` (its ``origin`` is subtracted from the axes).
    points : (N, 3) float, optional
        World coordinates of points to draw (e.g. :func:`tiled_gridpull.jobdir.sample_job_points`).
    size : (W, H) int
        Pixels.
    max_labels : int
        Tiles are labelled only up to this many columns.
    max_bars : int

    Returns
    -------
    (H, W, 3) uint8
    """
    size = _check_size(size)
    mpl = require("matplotlib", "the tile-layout picture")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch, Rectangle

    tiles = report.get("tiles") or []
    if not tiles:
        raise InputError("report lists no tiles")
    x0, y0 = (float(v) for v in report["lattice"]["origin"][:2])
    cols = _columns(tiles)
    times = np.array([c["time_s"] for c in cols])
    norm = Normalize(vmin=0.0, vmax=max(float(times.max()), 1e-6))
    cmap = mpl.colormaps["viridis"]

    dpi = 100
    fig = Figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(1, 2, width_ratios=[3, 2], wspace=0.25, left=0.06, right=0.97, top=0.88, bottom=0.1)
    ax = fig.add_subplot(gs[0])
    if points is not None and len(points):
        p = np.asarray(points, dtype=np.float64)
        ax.scatter(p[:, 0] - x0, p[:, 1] - y0, s=float(np.clip(3e4 / max(len(p), 1), 0.3, 3.0)), c="0.2",
                   alpha=0.6, linewidths=0, rasterized=True, zorder=1)
    labels = len(cols) <= max_labels
    fs = float(np.clip(11 - 0.06 * len(cols), 5, 10))
    for c in cols:
        lo, hi = c["lo"] - (x0, y0), c["hi"] - (x0, y0)
        w, h = hi - lo
        if c["status"] == "failed":
            face, edge, hatch, lw = (1.0, 0.0, 0.0, 0.12), (1.0, 0.0, 0.0, 1.0), "//", 2.0
        elif c["status"] == "skipped":
            face, edge, hatch, lw = (0.85, 0.85, 0.85, 0.55), (0.5, 0.5, 0.5, 1.0), None, 0.8
        else:
            face, edge, hatch, lw = (*cmap(norm(c["time_s"]))[:3], 0.55), (0.0, 0.0, 0.0, 1.0), None, 0.8
        ax.add_patch(Rectangle((lo[0], lo[1]), w, h, facecolor=face, edgecolor=edge, hatch=hatch, linewidth=lw,
                               zorder=2))
        if labels:
            layers = f" x{c['layers']}" if c["layers"] > 1 else ""
            ax.text(lo[0] + w / 2, lo[1] + h / 2,
                    f"{c['index'][0]},{c['index'][1]}{layers}\n{_fmt_count(c['points'])} pts\n{c['time_s']:.1f} s",
                    ha="center", va="center", fontsize=fs, zorder=3)
    lo_all = np.min([c["lo"] for c in cols], axis=0) - (x0, y0)
    hi_all = np.max([c["hi"] for c in cols], axis=0) - (x0, y0)
    pad = 0.02 * float(max(hi_all - lo_all))
    ax.set_xlim(lo_all[0] - pad, hi_all[0] + pad)
    ax.set_ylim(lo_all[1] - pad, hi_all[1] + pad)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(f"x - {x0:.10g}")
    ax.set_ylabel(f"y - {y0:.10g}")
    ax.set_title("tile cores from above (colour: solve time)", fontsize=10)
    sm = mpl.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=ax, fraction=0.04, pad=0.02, label="solve time per tile column [s]")

    ax2 = fig.add_subplot(gs[1])
    solve = np.array([float(t.get("solve_time_s") or 0.0) for t in tiles])
    mesh_t = np.array([float(t.get("mesh_time_s") or 0.0) for t in tiles])
    if len(tiles) <= max_bars:
        names = [",".join(str(v) for v in t["index"]) for t in tiles]
        y = np.arange(len(tiles))
        tnorm = Normalize(vmin=0.0, vmax=max(float(solve.max()), 1e-6))
        ax2.barh(y, solve, color=[cmap(tnorm(v)) if t.get("status") == "solved" else "0.7"
                                  for v, t in zip(solve, tiles)])
        for k, t in enumerate(tiles):
            if t.get("status") != "solved":
                ax2.text(0, k, f" {t.get('status')}", va="center", ha="left", fontsize=8,
                         color="red" if t.get("status") == "failed" else "0.3")
        ax2.barh(y, mesh_t, left=solve, color="#dd8452")
        ax2.set_yticks(y, names, fontsize=float(np.clip(12 - 0.2 * len(tiles), 5, 9)))
        ax2.invert_yaxis()
        ax2.set_xlabel("time [s]")
        ax2.set_ylabel("tile i,j,k")
        ax2.legend(handles=[Patch(facecolor=cmap(0.5), label="solve (colour: time)"),
                            Patch(facecolor="#dd8452", label="blend + mesh")], fontsize=8, loc="lower right")
    else:
        ax2.hist(solve, bins=min(40, max(5, len(tiles) // 5)), color=cmap(0.6))
        ax2.set_xlabel("solve time per tile [s]")
        ax2.set_ylabel("tiles")
    ax2.set_title("time per tile", fontsize=10)
    tot = report.get("totals", {})
    fig.suptitle(f"{tot.get('tiles_solved', '?')}/{tot.get('tiles_with_points', len(tiles))} tiles solved, "
                 f"{_fmt_count(int(tot.get('points', 0)))} points, {tot.get('faces', 0)} faces, "
                 f"wall time {float(tot.get('wall_time_s') or 0.0):.1f} s", fontsize=11)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    return img


def render_tile_layout(report: dict, path: str | Path, *, points: np.ndarray | None = None,
                       size: Sequence[int] = (1400, 700)) -> Path:
    """Write :func:`render_tile_layout_image` as a PNG (atomically).

    Parameters
    ----------
    report : dict
    path : str or Path
    points : (N, 3) float, optional
        World coordinates.
    size : (W, H) int
        Pixels.

    Returns
    -------
    Path
    """
    return save_png(render_tile_layout_image(report, points=points, size=size), path)
