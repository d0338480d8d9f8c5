"""A sensor trajectory: where the scanner was at each GPS time, so mobile-mapping LAS/LAZ points get sensor
origins.

Mobile-mapping files store each point's GPS time but not the scanner's position; the vehicle's path comes in a
separate file. With it every point gets the position of the sensor when it was measured (linear interpolation
between trajectory samples), and tiled mode orients the outside towards the sensor, so a wall faces the street
it was scanned from instead of "up".

Formats
-------
* Text or CSV (any suffix but ``.sbet``/``.out``): columns ``time x y z`` (extra columns ignored), in the point
  cloud's own coordinates, separated by commas or white space; one line of words before the first sample is a
  header, ``#`` starts a comment.
* SBET (``.sbet``, ``.out``: Applanix's smoothed best estimate of trajectory): records of 17 little-endian
  float64, of which time (s), latitude and longitude (radians) and ellipsoidal height (m) are used. Positions are
  projected into the point cloud's CRS (its WKT) with pyproj; the height is converted to the CRS's vertical unit
  (else its horizontal one: a survey in feet has heights in feet) but not to another datum, so the vertical datum
  should be ellipsoidal, or the offset (a geoid height, tens of metres) shifts every sensor origin up or
  down by as much, which moves no normal's side for points a street's width away.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError

__all__ = ["Trajectory", "read_trajectory", "SBET_SUFFIXES", "SBET_RECORD"]

SBET_SUFFIXES = (".sbet", ".out")
#: float64 fields per SBET record: time, latitude, longitude, altitude, 3 velocities, roll, pitch, heading,
#: wander angle, 3 accelerations, 3 angular rates
SBET_RECORD = 17
#: GPS times this far (s) outside the trajectory's span still get its end positions: time stamps of the last
#: points of a sweep and of the trajectory's last sample differ by rounding, not by a drive
TIME_SLACK_S = 1e-3


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Sensor positions over time.

    Attributes
    ----------
    time : (M,) float64
        Strictly increasing GPS times (s).
    xyz : (M, 3) float64
        Sensor positions, in the point cloud's coordinates (text) or still geodetic (SBET: latitude and
        longitude in radians, ellipsoidal height in metres) until :meth:`projected`.
    source : str
        The file it was read from.
    geodetic : bool
        True for SBET positions not yet projected.
    """

    time: np.ndarray
    xyz: np.ndarray
    source: str
    geodetic: bool = False

    def projected(self, crs_wkt: str | None) -> Trajectory:
        """This trajectory in the coordinates of a point cloud whose CRS is ``crs_wkt`` (a no-op unless it is
        geodetic).

        Raises
        ------
        InputError
            A geodetic trajectory for points without a CRS, or pyproj missing.
        """
        if not self.geodetic:
            return self
        if not crs_wkt:
            raise InputError(f"{self.source}: an SBET trajectory is in latitude and longitude, and the points "
                             "declare no CRS to project it into; give the trajectory as text (time x y z in the "
                             "points' coordinates)")
        from ._optional import require

        pyproj = require("pyproj", f"{self.source}: projecting an SBET trajectory")
        CRS, Transformer = pyproj.CRS, pyproj.Transformer
        try:
            target = CRS.from_wkt(crs_wkt)
            tr = Transformer.from_crs(CRS.from_epsg(4326), target.to_2d() if hasattr(target, "to_2d") else target,
                                      always_xy=True)
            x, y = tr.transform(np.degrees(self.xyz[:, 1]), np.degrees(self.xyz[:, 0]))
            _height_unit(target)
        except Exception as exc:  # pyproj raises CRSError, ProjError, ...
            raise InputError(f"{self.source}: cannot project the trajectory into the points' CRS "
                             f"({type(exc).__name__}: {str(exc).splitlines()[0][:120]})") from None
        xyz = np.column_stack([x, y, self.xyz[:, 2] / _height_unit(target)])
        if not np.all(np.isfinite(xyz)):
            raise InputError(f"{self.source}: the trajectory does not project into the points' CRS "
                             "(non-finite coordinates)")
        return Trajectory(self.time, xyz, self.source, geodetic=False)

    def sensor_at(self, times: np.ndarray, what: str = "points") -> np.ndarray:
        """Sensor position at each of ``times`` (linear interpolation), (N, 3) float64.

        Raises
        ------
        InputError
            Times outside the trajectory (beyond ``TIME_SLACK_S``) or not finite, naming how many and the span.
        """
        if self.geodetic:
            raise ValueError("project a geodetic trajectory first (Trajectory.projected)")
        t = np.asarray(times, dtype=np.float64)
        t0, t1 = float(self.time[0]), float(self.time[-1])
        bad = ~((t >= t0 - TIME_SLACK_S) & (t <= t1 + TIME_SLACK_S))  # NaN times are bad too
        if bad.any():
            outside = t[bad][np.isfinite(t[bad])]
            span = f"from {outside.min():.6f} to {outside.max():.6f} s" if len(outside) else "not finite"
            raise InputError(f"{what}: {int(bad.sum()):,} of {len(t):,} points have GPS times outside the "
                             f"trajectory {self.source} ({t0:.6f} to {t1:.6f} s): {span}; "
                             "is it the trajectory of this scan (and the same time base: GPS week seconds or "
                             "adjusted standard GPS time)?")
        return np.column_stack([np.interp(t, self.time, self.xyz[:, k]) for k in range(3)])


def _height_unit(crs) -> float:
    """Metres per unit of the heights of points in ``crs`` (a pyproj CRS): its vertical axis' unit when it has
    one (a compound CRS), else that of its horizontal axes (a projected CRS in feet keeps heights in feet, as LAS
    surveys in feet do); 1 for a CRS whose axes are not lengths."""
    axes = list(crs.axis_info)
    if len(axes) >= 3 and axes[2].direction.lower() == "up":
        return float(axes[2].unit_conversion_factor)
    if crs.is_projected and axes:
        return float(axes[0].unit_conversion_factor)
    return 1.0


def read_trajectory(path: str | Path) -> Trajectory:
    """Read a trajectory file (text/CSV or SBET, by suffix; see the module docstring).

    Raises
    ------
    InputError
        Missing, empty or malformed files, fewer than 2 samples, times that do not increase.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: trajectory file not found")
    if p.suffix.lower() in SBET_SUFFIXES:
        time, xyz, geodetic = *_read_sbet(p), True
    else:
        time, xyz, geodetic = *_read_text(p), False
    if len(time) < 2:
        raise InputError(f"{p}: a trajectory needs at least 2 samples, got {len(time)}")
    if not (np.all(np.isfinite(time)) and np.all(np.isfinite(xyz))):
        raise InputError(f"{p}: the trajectory has non-finite times or positions")
    order = np.argsort(time, kind="stable")
    time, xyz = time[order], xyz[order]
    if np.any(np.diff(time) <= 0):
        k = int(np.flatnonzero(np.diff(time) <= 0)[0])
        raise InputError(f"{p}: two trajectory samples share the time {time[k]:.6f} s")
    return Trajectory(np.ascontiguousarray(time), np.ascontiguousarray(xyz), str(p), geodetic=geodetic)


def _read_sbet(p: Path) -> tuple[np.ndarray, np.ndarray]:
    size = p.stat().st_size
    record = SBET_RECORD * 8
    if size == 0 or size % record:
        raise InputError(f"{p}: not an SBET file ({size} bytes is not a whole number of {record}-byte records)")
    rec = np.fromfile(p, dtype="<f8").reshape(-1, SBET_RECORD)
    lat, lon, alt = rec[:, 1], rec[:, 2], rec[:, 3]
    if np.any(np.abs(lat) > np.pi / 2 + 1e-9) or np.any(np.abs(lon) > 2 * np.pi + 1e-9):
        raise InputError(f"{p}: not an SBET file (latitudes or longitudes beyond the range of radians)")
    return rec[:, 0].copy(), np.column_stack([lat, lon, alt])


_NUMBER_ROW = re.compile(r"^\s*[-+0-9.eE]+([\s,;]+[-+0-9.eE]+)+\s*$")


def _read_text(p: Path) -> tuple[np.ndarray, np.ndarray]:
    rows = []
    try:
        with open(p, encoding="utf-8", errors="replace") as fh:
            header_seen = False
            for number, line in enumerate(fh, 1):
                # a byte-order mark and trailing separators (spreadsheet exports) are not part of the data
                text = line.split("#", 1)[0].lstrip("\ufeff").strip().rstrip(",;").strip()
                if not text:
                    continue
                if not _NUMBER_ROW.match(text):
                    # a header is words, before the first sample; a row of numbers that does not parse is an error
                    if rows or header_seen or not re.search(r"[A-Za-z_]{2,}", text):
                        raise InputError(f"{p}: line {number} of the trajectory is not numbers: {text[:60]!r}")
                    header_seen = True
                    continue
                values = [float(v) for v in re.split(r"[\s,;]+", text)]
                if len(values) < 4:
                    raise InputError(f"{p}: line {number} has {len(values)} columns; a trajectory needs "
                                     "time x y z")
                rows.append(values[:4])
    except InputError:
        raise
    except (OSError, UnicodeError) as exc:
        raise InputError(f"{p}: cannot read the trajectory ({type(exc).__name__})") from None
    except ValueError as exc:
        raise InputError(f"{p}: malformed trajectory ({str(exc).splitlines()[0][:80]})") from None
    if not rows:
        raise InputError(f"{p}: the trajectory file has no samples")
    a = np.asarray(rows, dtype=np.float64)
    return a[:, 0].copy(), a[:, 1:4].copy()
