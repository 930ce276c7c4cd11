"""A lidar turn as a ``Scan`` message and back (docs/wire-contract.md "scan").

An RPLIDAR's samples come at uneven angles (a few hundred to ~1450 a turn); the wire carries
``beams`` equal steps over the whole turn, each the nearest return in its step (an obstacle is
never thinned away), in millimetres as little-endian uint16 (0: no return). 360 beams are 720
bytes: 2 Hz from 50 robots is ~80 kB/s on Zenoh.

Pure: no I/O.
"""

from __future__ import annotations

import math
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from fleetlink.shared.messages import MAX_SCAN_BEAMS, Scan
from fleetlink.shared.wire import WireError

__all__ = ["BEAMS", "MAX_RANGE_M", "scan_fields", "scan_points", "scan_ranges"]

BEAMS: Final = 360
"""Beams the agent sends a turn (one a degree)."""
MAX_RANGE_M: Final = 65.535
"""uint16 millimetres; a farther return is sent as this."""

F64 = npt.NDArray[np.float64]


def scan_fields(
    angles_rad: npt.ArrayLike,
    distances_m: npt.ArrayLike,
    pose: tuple[float, float, float],
    beams: int = BEAMS,
) -> dict[str, Any]:
    """Keyword fields of a ``Scan`` from a turn's samples (sensor frame, counter-clockwise
    radians; distances 0 or not finite for no return) taken at ``pose`` (x, y, heading)."""
    if not 1 <= beams <= MAX_SCAN_BEAMS:
        raise ValueError(f"beams must be 1..{MAX_SCAN_BEAMS}, got {beams}")
    a = np.asarray(angles_rad, dtype=np.float64).ravel()
    d = np.asarray(distances_m, dtype=np.float64).ravel()
    if a.shape != d.shape:
        raise ValueError(f"{a.size} angles but {d.size} distances")
    ok = np.isfinite(a) & np.isfinite(d) & (d > 0.0)
    step = math.tau / beams
    nearest = np.full(beams, np.inf)
    if ok.any():
        bins = np.floor(np.mod(a[ok], math.tau) / step).astype(np.intp) % beams
        np.minimum.at(nearest, bins, d[ok])
    mm = np.where(np.isfinite(nearest), np.clip(np.round(nearest * 1000.0), 1, 65_535), 0).astype("<u2")
    x, y, theta = pose
    return {
        "x": float(x),
        "y": float(y),
        "theta": math.remainder(float(theta), math.tau),
        "start_angle": step / 2.0,
        "count": beams,
        "ranges": mm.tobytes(),
    }


def scan_ranges(msg: Scan) -> F64:
    """The beams' ranges in metres (NaN: no return); ``WireError`` if ``ranges`` is not ``count``
    uint16s."""
    if len(msg.ranges) != 2 * msg.count:
        raise WireError(f"{len(msg.ranges)} bytes for {msg.count} beams (2 each)", "ranges")
    mm = np.frombuffer(msg.ranges, dtype="<u2").astype(np.float64)
    out: F64 = np.where(mm > 0, mm / 1000.0, np.nan)
    return out


def scan_points(msg: Scan) -> F64:
    """The returns as ``(N, 2)`` site-frame points (what a console draws over its map)."""
    r = scan_ranges(msg)
    bearings = msg.theta + msg.start_angle + np.arange(msg.count) * (math.tau / msg.count)
    ok = np.isfinite(r)
    pts: F64 = np.column_stack((msg.x + r[ok] * np.cos(bearings[ok]), msg.y + r[ok] * np.sin(bearings[ok])))
    return pts
