"""Reading and writing point clouds and meshes (atomic outputs, one-line errors)."""

from .atomic import atomic_open, atomic_path, write_json
from .meshes import read_mesh, read_sidecar, sidecar_path, write_mesh, write_sidecar

__all__ = ["atomic_open", "atomic_path", "write_json", "read_mesh", "write_mesh", "write_sidecar",
           "read_sidecar", "sidecar_path"]
