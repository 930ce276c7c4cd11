"""Maps and trajectories scored against the field's truth: the lines the mission tests share."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import numpy.typing as npt

from fleetlink.agent.mapping.relations import align_se2, transform_xy
from fleetlink.field.plans import nearest_segment_distances
from fleetlink.shared.se2 import Pose

__all__ = ["aligned_rmse", "truth_at", "wall_distances", "wall_points"]

F64 = npt.NDArray[np.float64]
OCCUPIED_AT = 65
"""A cell at or over this is a wall (map_server's occupied_thresh 0.65, as the console draws it)."""


def wall_points(cells: npt.NDArray[np.int8], origin: tuple[float, float], resolution: float) -> F64:
    """The centres of a map's wall cells, ``(N, 2)`` metres in its frame."""
    rows, cols = np.nonzero(cells >= OCCUPIED_AT)
    return np.column_stack((origin[0] + (cols + 0.5) * resolution, origin[1] + (rows + 0.5) * resolution))


def wall_distances(
    cells: npt.NDArray[np.int8],
    origin: tuple[float, float],
    resolution: float,
    segments: F64,
    tf: Pose | None = None,
) -> F64:
    """Each wall cell's distance to the plan's nearest wall or obstacle edge (``segments``), the map
    moved by ``tf`` first (an alignment onto the truth) if given."""
    pts = wall_points(cells, origin, resolution)
    return nearest_segment_distances(pts if tf is None else transform_xy(tf, pts), segments)


def aligned_rmse(est: Sequence[Pose], truth: Sequence[Pose]) -> tuple[float, Pose]:
    """The RMSE of ``est``'s positions against ``truth``'s after the one rigid motion that fits them
    best (``align_se2``), and that motion."""
    tf = align_se2(list(est), list(truth))
    xy = transform_xy(tf, np.array([p[:2] for p in est]))
    ref = np.array([p[:2] for p in truth])
    return math.sqrt(float(np.mean(np.sum((xy - ref) ** 2, axis=1)))), tf


def truth_at(rows: Sequence[Sequence[float]]) -> Callable[[float], Pose]:
    """A lockstep run's truth rows of one robot (t, x, y, theta, ...) as its pose at any time,
    interpolated (the heading unwrapped first)."""
    truth = np.array([row[:4] for row in rows], dtype=np.float64)
    t, x, y, th = truth[:, 0], truth[:, 1], truth[:, 2], np.unwrap(truth[:, 3])
    return lambda s: (float(np.interp(s, t, x)), float(np.interp(s, t, y)), float(np.interp(s, t, th)))
