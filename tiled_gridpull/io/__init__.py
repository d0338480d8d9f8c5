"""Reading and writing point clouds and meshes (atomic outputs, one-line errors)."""

from .atomic import atomic_open, atomic_path, write_json
from .meshes import read_mesh, read_sidecar, sidecar_path, write_mesh, write_mesh_and_sidecar, write_sidecar
from .outputs import check_outputs, written_by_us

__all__ = ["atomic_open", "atomic_path", "write_json", "read_mesh", "write_mesh", "write_sidecar",
           "read_sidecar", "sidecar_path", "check_outputs", "written_by_us", "write_mesh_and_sidecar"]

from .formats import SUPPORTED_POINT_FORMATS
from .kitti import read_kitti_sequence
from .points import iter_point_chunks, iter_row_chunks, point_count, read_crs, read_points

__all__ += ["read_points", "read_crs", "iter_point_chunks", "iter_row_chunks", "read_kitti_sequence", "point_count",
            "SUPPORTED_POINT_FORMATS"]
