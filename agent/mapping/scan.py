"""Scan preparation: drop invalid returns, polar to Cartesian, adaptive segmentation, thinning.

Segmentation follows the sweeping-robot seed: walking along the scan, consecutive points i-1, i are
split into different segments where the gap ``d_i = |p_i - p_{i-1}|`` exceeds ``eps`` (metres) or
where it is much larger than its neighbour gap, ``max(d_i, d_{i-1}) / min(d_i, d_{i-1}) > tau``
(the larger of the two gaps is the break). The ratio rule catches depth jumps that are short in
absolute terms; because point spacing grows with range, a fixed ``eps`` alone would either split
far walls or join near objects. Segments with fewer than ``min_points`` points are treated as
noise (stray returns, spurious mixed pixels) and dropped before matching and mapping.

Pure numpy; no I/O.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

__all__ = ["filter_segments", "prepare", "segment_labels", "surface_fill", "thin", "to_points"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def prepare(
    ranges: npt.ArrayLike,
    angles: npt.ArrayLike,
    min_range: float,
    max_range: float,
    missing_ray: float = 0.0,
    missing_run: int = 1,
) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
    """Valid beams: (ranges, angles, hit). Drops NaN/inf/negative/zero and below ``min_range``.

    Readings at or beyond ``max_range`` are kept as *no-hit* beams (``hit`` False, range clipped to
    ``max_range``): they say the space in front is free but mark no obstacle. Angles are radians,
    counter-clockwise in the sensor frame; the order of the input is kept.

    ``missing_ray`` > 0 (m): a sample with no return (0, as the RPLIDAR reports it, or +inf, as ROS
    does: REP 117) in a run of at least ``missing_run`` of them in scan order is a no-hit beam that
    long. Nothing in a whole sector within the sensor's range is open space, and says the near part
    of it is free (Cartographer's ``missing_data_ray_length``): without it a robot in an open hall
    never clears where another robot stood. A shorter run is a dropout (a dark spot on a wall) and
    says nothing.
    """
    r = np.asarray(ranges, dtype=np.float64).ravel()
    a = np.asarray(angles, dtype=np.float64).ravel()
    if r.shape != a.shape:
        raise ValueError(f"ranges and angles differ in length: {r.size} vs {a.size}")
    ok = np.isfinite(r) & np.isfinite(a) & (r >= max(min_range, 1e-9))
    missing = np.zeros(r.shape, dtype=bool)
    if missing_ray > 0.0:
        missing = _runs_of(((r == 0.0) | np.isposinf(r)) & np.isfinite(a), missing_run)
        r = np.where(missing, missing_ray, r)  # clipped to max_range below, as any reading
        ok |= missing
    r, a, missing = r[ok], a[ok], missing[ok]
    hit = (r < max_range) & ~missing
    return np.minimum(r, max_range), a, hit


def _runs_of(mask: npt.NDArray[np.bool_], n: int) -> npt.NDArray[np.bool_]:
    """``mask`` where it is True in a run of at least ``n`` consecutive elements."""
    if n <= 1 or not mask.any():
        return mask
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    out = np.zeros_like(mask)
    for start, end in zip(edges[::2], edges[1::2], strict=True):
        if end - start >= n:
            out[start:end] = True
    return out


def to_points(ranges: FloatArray, angles: FloatArray) -> FloatArray:
    """Polar to Cartesian in the sensor frame: (N, 2)."""
    return np.column_stack((ranges * np.cos(angles), ranges * np.sin(angles)))


def segment_labels(points: FloatArray, eps: float, tau: float) -> IntArray:
    """Segment index per point (0, 1, 2, ... in scan order) by the adaptive breakpoint rule."""
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    gaps = np.hypot(np.diff(points[:, 0]), np.diff(points[:, 1]))  # gaps[k] = d_{k+1}
    brk = gaps > eps
    if n > 2 and math.isfinite(tau):
        d, prev = gaps[1:], gaps[:-1]
        lo = np.maximum(np.minimum(d, prev), 1e-9)
        ratio = np.maximum(d, prev) / lo
        jump = ratio > tau
        # The larger gap of the pair is where the surface changes.
        brk[1:] |= jump & (d > prev)
        brk[:-1] |= jump & (prev > d)
    labels = np.zeros(n, dtype=np.int64)
    labels[1:] = np.cumsum(brk)
    return labels


def filter_segments(labels: IntArray, min_points: int) -> npt.NDArray[np.bool_]:
    """Mask of points whose segment has at least ``min_points`` points."""
    if labels.size == 0:
        return np.zeros(0, dtype=bool)
    counts = np.bincount(labels)
    return counts[labels] >= min_points


def thin(points: FloatArray, cell: float) -> FloatArray:
    """One point per ``cell``-sized square (the first in scan order): even density for matching."""
    if len(points) == 0 or cell <= 0:
        return points
    keys = np.floor(points / cell).astype(np.int64)
    packed = keys[:, 0] * 1_000_003 + keys[:, 1]
    # The first point of each key (np.unique(return_index=True) without its overhead: a stable sort).
    order = np.argsort(packed, kind="stable")
    ranked = packed[order]
    lead = np.empty(len(ranked), dtype=bool)
    lead[0] = True
    np.not_equal(ranked[1:], ranked[:-1], out=lead[1:])
    out: FloatArray = points[np.sort(order[lead])]
    return out


def surface_fill(
    ranges: FloatArray,
    angles: FloatArray,
    hit: npt.NDArray[np.bool_],
    max_gap: float,
    depth_share: float,
    depth_m: float,
    step: float,
) -> tuple[FloatArray, FloatArray]:
    """Beams (ranges, angles) filling the surface between neighbouring hits, ``step`` apart.

    Two consecutive beams that both hit, whose endpoints are less than ``max_gap`` apart and whose
    ranges differ by less than ``depth_share`` x the nearer range + ``depth_m``, saw one surface: the
    straight line between their endpoints is filled with returns at most ``step`` apart. A far wall
    seen by 1-degree beams is otherwise a dotted line (beams 0.17 m apart at 10 m, 0.35 m at 20 m),
    which a likelihood field blurred over a few cells reads as mostly empty. Non-positive
    ``max_gap``: nothing. Input as ``prepare`` returns it, in scan order.
    """
    empty = np.zeros(0, dtype=np.float64)
    if max_gap <= 0 or step <= 0 or ranges.size < 2:
        return empty, empty.copy()
    pair = np.flatnonzero(hit[:-1] & hit[1:])
    p = to_points(ranges, angles)
    a, b = p[pair], p[pair + 1]
    gap = np.hypot(b[:, 0] - a[:, 0], b[:, 1] - a[:, 1])
    r0, r1 = ranges[pair], ranges[pair + 1]
    same = (gap < max_gap) & (np.abs(r1 - r0) < depth_share * np.minimum(r0, r1) + depth_m)
    inner = np.where(same, np.ceil(gap / step).astype(np.int64) - 1, 0)  # points strictly between
    inner = np.maximum(inner, 0)
    total = int(inner.sum())
    if total == 0:
        return empty, empty.copy()
    which = np.repeat(np.arange(len(pair)), inner)
    # k = 1..inner within each pair: the running index less where the pair's run started.
    start = np.cumsum(inner) - inner
    k = np.arange(total) - start[which] + 1
    frac = (k / (inner[which] + 1))[:, None]
    pts = a[which] + frac * (b[which] - a[which])
    out_r: FloatArray = np.hypot(pts[:, 0], pts[:, 1])
    out_a: FloatArray = np.arctan2(pts[:, 1], pts[:, 0])
    return out_r, out_a
