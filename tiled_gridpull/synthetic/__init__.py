"""Synthetic data with exact ground truth: closed analytic shapes, a LiDAR-scanned street, and a thin wall seen
from both sides.

Feeds the tests, the demo command and the benchmarks. Everything is deterministic given its seed.
"""

from .fence import FENCE_CLASSES, fence_scene
from .shapes import box, sample_shape, sphere, torus
from .lidar import (
    POINTS_PER_FRAME_DEFAULT,
    SENSOR_HEIGHT_M,
    Scan,
    frames_for_points,
    hdl64_directions,
    points_per_frame,
    scan_street,
    sensor_poses,
    street_length_for_frames,
)
from .lidar_files import KITTI_TR, write_kitti_sequence, write_las
from .observed import observed_samples
from .street import FACE_CLASSES, StreetScene, build_street, terrain_height
from .street_sample import make_street_sample

__all__ = [
    "sphere", "torus", "box", "sample_shape",
    "StreetScene", "Scan", "build_street", "scan_street", "sensor_poses", "terrain_height",
    "hdl64_directions",
    "points_per_frame", "frames_for_points", "street_length_for_frames", "write_las", "write_kitti_sequence",
    "make_street_sample", "observed_samples", "fence_scene", "FENCE_CLASSES",
    "FACE_CLASSES", "KITTI_TR", "POINTS_PER_FRAME_DEFAULT", "SENSOR_HEIGHT_M",
]
