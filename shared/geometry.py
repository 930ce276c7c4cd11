"""Plane geometry every layer uses: points in polygons, distances to segments, connected regions
of a grid (pure).

The field (plans, the radio's dead zones, cliffs), the agent's lamp interlocks (people-present
zones) and its coverage planner (a chosen area) all ask the same questions of the same polygons;
they ask them here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

__all__ = [
    "Point",
    "Segment",
    "components",
    "point_in_polygon",
    "point_segment_distance",
    "points_in_polygon",
    "polygon_distance",
    "simplify",
]

Point = tuple[float, float]
Segment = tuple[float, float, float, float]
"""x1, y1, x2, y2."""


def point_in_polygon(x: float, y: float, polygon: Sequence[Point]) -> bool:
    """Even-odd test: is (x, y) inside a simple polygon given by its corners (either winding)?"""
    inside = False
    n = len(polygon)
    for i in range(n):
        x1, y1 = polygon[i]
        x2, y2 = polygon[(i + 1) % n]
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside


def points_in_polygon(
    xs: npt.NDArray[np.float64], ys: npt.NDArray[np.float64], polygon: Sequence[Point]
) -> npt.NDArray[np.bool_]:
    """``point_in_polygon`` for arrays of points (the same even-odd rule, element by element)."""
    inside = np.zeros(np.broadcast(xs, ys).shape, dtype=bool)
    n = len(polygon)
    for i in range(n):
        (x1, y1), (x2, y2) = polygon[i], polygon[(i + 1) % n]
        if y1 == y2:
            continue
        crosses = (y1 > ys) != (y2 > ys)
        inside ^= crosses & (xs < x1 + (ys - y1) * (x2 - x1) / (y2 - y1))
    return inside


def point_segment_distance(px: float, py: float, seg: Segment) -> float:
    x1, y1, x2, y2 = seg
    ex, ey = x2 - x1, y2 - y1
    n2 = ex * ex + ey * ey
    t = 0.0 if n2 == 0 else max(0.0, min(1.0, ((px - x1) * ex + (py - y1) * ey) / n2))
    return math.hypot(px - (x1 + t * ex), py - (y1 + t * ey))


def polygon_distance(x: float, y: float, polygon: Sequence[Point]) -> float:
    """Distance from (x, y) to the polygon's outline (0 on it; the inside is not 0: see
    ``point_in_polygon``)."""
    n = len(polygon)
    return min((point_segment_distance(x, y, (*polygon[i], *polygon[(i + 1) % n])) for i in range(n)), default=math.inf)


def components(mask: npt.NDArray[np.bool_]) -> list[npt.NDArray[np.intp]]:
    """8-connected components of ``mask``: each an (N, 2) array of (row, col). Union-find over row runs."""
    runs: list[tuple[int, int, int]] = []  # row, first col, last col (inclusive)
    row_runs: list[list[int]] = []
    for r in range(mask.shape[0]):
        line = np.concatenate(([False], mask[r], [False])).astype(np.int8)
        edges = np.flatnonzero(np.diff(line))
        ids = []
        for a, b in zip(edges[0::2].tolist(), edges[1::2].tolist(), strict=True):
            ids.append(len(runs))
            runs.append((r, a, b - 1))
        row_runs.append(ids)
    parent = list(range(len(runs)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for r in range(1, mask.shape[0]):
        above, here = row_runs[r - 1], row_runs[r]
        i = j = 0
        while i < len(above) and j < len(here):
            _, a0, a1 = runs[above[i]]
            _, b0, b1 = runs[here[j]]
            if a0 <= b1 + 1 and b0 <= a1 + 1:
                pa, pb = find(above[i]), find(here[j])
                if pa != pb:
                    parent[max(pa, pb)] = min(pa, pb)
            if a1 < b1:
                i += 1
            else:
                j += 1
    groups: dict[int, list[int]] = {}
    for k in range(len(runs)):
        groups.setdefault(find(k), []).append(k)
    out = []
    for ks in groups.values():
        rows = np.concatenate([np.full(runs[k][2] - runs[k][1] + 1, runs[k][0], dtype=np.intp) for k in ks])
        cols = np.concatenate([np.arange(runs[k][1], runs[k][2] + 1, dtype=np.intp) for k in ks])
        out.append(np.column_stack((rows, cols)))
    return out


def simplify(points: Sequence[Point], tolerance_m: float) -> list[Point]:
    """Ramer-Douglas-Peucker: the fewest points whose polyline stays within ``tolerance_m`` of
    ``points`` (the first and last kept)."""
    if len(points) < 3:
        return list(points)
    keep = [False] * len(points)
    keep[0] = keep[-1] = True
    stack = [(0, len(points) - 1)]
    while stack:
        i, j = stack.pop()
        (ax, ay), (bx, by) = points[i], points[j]
        dx, dy = bx - ax, by - ay
        norm = math.hypot(dx, dy)
        worst, at = -1.0, -1
        for k in range(i + 1, j):
            px, py = points[k]
            d = abs(dx * (ay - py) - dy * (ax - px)) / norm if norm > 0 else math.hypot(px - ax, py - ay)
            if d > worst:
                worst, at = d, k
        if worst > tolerance_m:
            keep[at] = True
            stack.append((i, at))
            stack.append((at, j))
    return [p for p, k in zip(points, keep, strict=True) if k]
