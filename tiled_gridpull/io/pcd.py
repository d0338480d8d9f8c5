"""PCD point clouds (PCL, ROS): ``ascii``, ``binary`` and ``binary_compressed`` (LZF) data, read with pypcd4.

Fields ``x y z`` are required; ``normal_x normal_y normal_z`` become normals and ``intensity`` an attribute. The
header's ``VIEWPOINT`` is where the sensor stood (translation, then orientation): every point gets that position
as its sensor origin, so tiled mode's ``orientation: auto`` faces the outside towards the sensor, as for KITTI.
The default viewpoint (``0 0 0 1 0 0 0``, written when nobody set one) counts only for organised clouds, which are
in their sensor's frame; an unorganised cloud with it (a registered map, its origin anywhere) gets no sensor.
A VIEWPOINT that is not 7 finite numbers is refused (a NaN one would make every sensor origin NaN), and so is one
whose position lies beyond :data:`SENSOR_LIMIT` (a tiled job stores sensor origins as float32 offsets from a
tile's corner: a farther one became infinite there).
Organised clouds (``HEIGHT > 1``, e.g. a depth camera's 640 x 480 image) mark pixels without a return with NaN
coordinates; those rows are dropped like every non-finite row (counted in the cloud's report).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cloud import PointCloud, unit_normals
from ..errors import InputError

__all__ = ["read", "count", "DEFAULT_VIEWPOINT", "SENSOR_LIMIT"]

#: Largest magnitude of a VIEWPOINT's position. A tiled job stores every sensor origin as a float32 offset from
#: its tile's low corner (:data:`tiled_gridpull.jobdir.SPILL_RECORD_SENSOR`), whose largest finite value is
#: about 3.4e38; ``cloud.COORDINATE_LIMIT`` (1e150, for float64 arithmetic) is far beyond it. 1e37 leaves room for
#: the offset from any corner a float32 PCD's points can make (below about 3.3e38).
SENSOR_LIMIT = 1e37

#: the VIEWPOINT every PCL writer puts in a header unless told otherwise (origin, identity quaternion)
DEFAULT_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)

_HEADER_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")


def header(p: Path) -> dict[str, list[str]]:
    """The header's entries (keyword -> words), read as text up to and including ``DATA``.

    Raises
    ------
    InputError
        Not a PCD header (no ``FIELDS``/``POINTS``/``DATA`` line before the data, or over 64 kB of header).
    """
    entries: dict[str, list[str]] = {}
    with open(p, "rb") as fh:
        for _ in range(256):
            raw = fh.readline(65536)
            if not raw:
                break
            line = raw.decode("ascii", "replace").strip()
            if not line or line.startswith("#"):
                continue
            key, *words = line.split()
            entries[key.upper()] = words
            if key.upper() == "DATA":
                break
    missing = [k for k in ("FIELDS", "POINTS", "DATA") if k not in entries]
    if missing:
        raise InputError(f"{p}: not a PCD file (no {', '.join(missing)} line in its header)")
    return entries


def count(p: Path) -> int:
    """The header's ``POINTS`` (NaN rows of an organised cloud included)."""
    h = header(p)
    try:
        n = int(h["POINTS"][0])
    except (IndexError, ValueError):
        raise InputError(f"{p}: PCD header's POINTS is not a number: {' '.join(h['POINTS'])!r}") from None
    if n < 0:
        raise InputError(f"{p}: PCD header's POINTS is negative ({n})")
    return n


def read(p: Path) -> PointCloud:
    """The whole file as one cloud (float64 coordinates; NaN rows are dropped later, like every reader's)."""
    from pypcd4 import PointCloud as PcdCloud

    h = header(p)
    fields = [f.lower() for f in h["FIELDS"]]
    if not {"x", "y", "z"} <= set(fields):
        raise InputError(f"{p}: PCD file without x y z fields (it has {' '.join(h['FIELDS'])})")
    expected = count(p)
    view = _viewpoint(p, h)
    pc = PcdCloud.from_path(p)
    data = pc.pc_data
    if len(data) != expected:
        raise InputError(f"{p}: truncated PCD file ({len(data):,} of the {expected:,} points its header declares)")
    names = {n.lower(): n for n in data.dtype.names}
    xyz = np.stack([np.asarray(data[names[c]], dtype=np.float64) for c in ("x", "y", "z")], axis=1)
    normals = None
    if all(f"normal_{c}" in names for c in "xyz"):
        normals = unit_normals(np.stack([np.asarray(data[names[f"normal_{c}"]], dtype=np.float64)
                                         for c in "xyz"], axis=1))
    attrs = {}
    if "intensity" in names:
        attrs["intensity"] = np.asarray(data[names["intensity"]], dtype=np.float32)
    for name in ("rgb", "rgba"):
        if name in names and np.asarray(data[names[name]]).dtype.itemsize == 4:
            # PCL packs 8-bit colour in one 4-byte field (a float's bits, or uint32 for rgba): 0x00RRGGBB
            packed = np.ascontiguousarray(data[names[name]]).view(np.uint32)
            for shift, c in ((16, "red"), (8, "green"), (0, "blue")):
                attrs[c] = ((packed >> shift) & 0xFF).astype(np.uint8)
            break
    sensor = None
    if view is not None:
        height = (h.get("HEIGHT") or ["1"])[0]
        organised = height.isdigit() and int(height) > 1
        # every PCL writer puts the default there: it says where the sensor was only for an organised cloud,
        # which is in its sensor's own frame; an unorganised one (a registered map) keeps no sensor
        if organised or tuple(view) != DEFAULT_VIEWPOINT:
            sensor = np.broadcast_to(view[:3], xyz.shape).copy()
    return PointCloud(xyz, normals=normals, sensor=sensor, attributes=attrs, source=str(p),
                      report={"points_read": len(xyz)})


def _viewpoint(p: Path, h: dict[str, list[str]]) -> np.ndarray | None:
    """The header's VIEWPOINT as 7 float64 (translation, then the orientation quaternion w x y z); None when
    the header has none.

    Raises
    ------
    InputError
        A VIEWPOINT that is not 7 finite numbers: its translation would be every point's sensor origin (a NaN
        one made every origin NaN), and no writer puts a non-finite orientation there. A position beyond
        :data:`SENSOR_LIMIT`.
    """
    words = h.get("VIEWPOINT")
    if words is None:
        return None
    try:
        view = np.array([float(w) for w in words], dtype=np.float64)
    except ValueError:
        view = np.full(0, np.nan)
    if view.shape != (7,) or not np.all(np.isfinite(view)):
        raise InputError(f"{p}: PCD header's VIEWPOINT '{' '.join(words)}' is not 7 finite numbers "
                         "(the sensor's position x y z, then its orientation quaternion w x y z)")
    if np.abs(view[:3]).max() > SENSOR_LIMIT:
        raise InputError(f"{p}: PCD header's VIEWPOINT '{' '.join(words)}' places the sensor beyond "
                         f"+-{SENSOR_LIMIT:g} (sensor origins are kept as float32 offsets from the points): a "
                         "damaged header?")
    return view
