"""Picture of a tileset's levels side by side, as VTK's 3D Tiles reader (vtkCesium3DTilesReader) loads them,
coloured by their COLOR_0, seen from above.

Usage: ``python benchmarks/tiles3d_picture.py TILESET.json OUT.png 0,3`` (the reader's levels: 0 is the root).
docs/images/tiles3d_autzen_levels.png: the tileset of ``reconstruct autzen_trim.laz --voxel-size 3ft --tile-size 300
--set coarse_iterations=150 --set iterations=150 --attributes all --3d-tiles DIR`` (with the vertex attributes of
issue 40 part 1), levels 0,3.
"""
import sys
import numpy as np
import pyvista as pv
import vtk

tileset, out = sys.argv[1], sys.argv[2]
levels = [int(v) for v in sys.argv[3].split(",")]


def load(level):
    r = vtk.vtkCesium3DTilesReader()
    r.SetFileName(tileset)
    r.SetLevel(level)
    r.Update()
    o = r.GetOutput()
    parts = []
    for i in range(o.GetNumberOfPartitionedDataSets()):
        p = o.GetPartitionedDataSet(i)
        for j in range(p.GetNumberOfPartitions()):
            parts.append(pv.wrap(p.GetPartition(j)))
    return parts


meshes = {lv: load(lv) for lv in levels}
allp = np.concatenate([m.points for m in meshes[levels[-1]]])
centre = allp.mean(axis=0)
up = centre / np.linalg.norm(centre)
pl = pv.Plotter(off_screen=True, shape=(1, len(levels)), window_size=(700 * len(levels), 520))
for k, lv in enumerate(levels):
    pl.subplot(0, k)
    nf = 0
    for m in meshes[lv]:
        m = m.copy()
        m.points = m.points - centre
        c = m.point_data["COLOR_0"]
        c = np.asarray(c, np.float64)
        c = c / (65535.0 if c.max() > 1.5 else 1.0)
        srgb = np.clip(c[:, :3], 0, 1) ** (1 / 2.2)
        m.point_data["rgb"] = (srgb * 255).astype(np.uint8)
        nf += m.n_cells
        pl.add_mesh(m, scalars="rgb", rgb=True, smooth_shading=True)
    pl.add_text(f"level {lv} of the reader: {len(meshes[lv])} glb, {nf:,} triangles", font_size=11)
    north = np.cross(np.cross(up, [0, 0, 1]), up)  # the ellipsoid's north at the scene, in ECEF
    pl.camera_position = [tuple(up * 420), (0, 0, 0), tuple(north)]  # 420 m above, north up
pl.link_views()
pl.screenshot(out)
print(out, {lv: sum(m.n_cells for m in meshes[lv]) for lv in levels})
