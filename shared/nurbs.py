"""NURBS curves as VDA 5050 carries an edge's trajectory: checked, sampled into waypoints, and a
polyline written as one. Pure.

    check(degree, knots, points, weights)   # ValueError with the reason, or None
    waypoints(degree, knots, points, weights)  # the curve as a polyline (a robot's go-to legs)
    polyline_knots(points)                  # the knot vector that makes a polyline a degree-1 NURBS

VDA 5050 2.1.0, section 6.6.6 (``trajectory``): ``degree`` >= 1, ``knotVector`` of
``len(controlPoints) + degree + 1`` values in [0, 1], ``controlPoints`` (x, y, weight >= 0, default 1)
"explicitly including the start and end point". The curve is evaluated with de Boor's algorithm in
homogeneous coordinates (Piegl and Tiller, *The NURBS Book*, 2nd ed., algorithms A2.1 and A4.1) over
the knot vector's valid range ``[knots[degree], knots[n]]``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from itertools import pairwise

from fleetlink.shared.geometry import simplify

__all__ = ["MAX_DEGREE", "MAX_SAMPLES", "Point", "check", "polyline_knots", "waypoints"]

Point = tuple[float, float]

MAX_DEGREE = 5
"""Highest degree taken (a trajectory is a drive path: cubic is the usual, quintic is generous; the
agent samples each curve on its control path, at a cost that grows with the degree squared)."""
MAX_SAMPLES = 256
"""Curve points evaluated for one curved trajectory (before it is thinned to waypoints): a 64-point
quintic samples in about 2 ms."""
SAMPLES_PER_SPAN = 32
"""Curve points per non-empty knot span."""
TOLERANCE_M = 0.01
"""A curved trajectory's waypoints stay within this of the curve (the legs between them are straight)."""


def check(degree: int, knots: Sequence[float], points: Sequence[Point], weights: Sequence[float]) -> None:
    """ValueError with the reason when (degree, knots, points, weights) is not a curve a robot can
    drive: the sizes the standard asks for, knots non-decreasing in [0, 1] with a valid range of
    non-zero length, finite coordinates, weights > 0."""
    n = len(points)
    if isinstance(degree, bool) or not isinstance(degree, int) or not 1 <= degree <= MAX_DEGREE:
        raise ValueError(f"degree must be an integer 1-{MAX_DEGREE}, got {degree!r}")
    if n < degree + 1:
        raise ValueError(f"a degree-{degree} curve needs at least {degree + 1} control points, got {n}")
    if len(weights) != n:
        raise ValueError(f"{len(weights)} weights for {n} control points")
    if len(knots) != n + degree + 1:
        raise ValueError(
            f"knotVector has {len(knots)} values; {n} control points of degree {degree} need {n + degree + 1}"
        )
    for i, k in enumerate(knots):
        if not (math.isfinite(k) and 0.0 <= k <= 1.0):
            raise ValueError(f"knotVector[{i}] = {k!r}: knots lie in [0, 1]")
        if i and k < knots[i - 1]:
            raise ValueError(f"knotVector[{i}] = {k!r} is below the knot before it: knots never decrease")
    if not knots[n] > knots[degree]:
        raise ValueError("the knot vector leaves the curve no length (knotVector[degree] == knotVector[n])")
    for i, (x, y) in enumerate(points):
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"controlPoints[{i}] = ({x!r}, {y!r}) is not finite")
    # Each point of the curve is a weighted mean of the control points acting there, and at a knot
    # some of their basis functions vanish: a weight of 0, which the standard allows, can leave the
    # curve undefined (0/0) at a single point. With every weight above 0 it is defined everywhere.
    for i, w in enumerate(weights):
        if not (math.isfinite(w) and w > 0.0):
            raise ValueError(f"controlPoints[{i}].weight = {w!r}: this vehicle takes finite weights > 0")


def polyline_knots(points: Sequence[Point]) -> tuple[float, ...]:
    """The knot vector of ``points`` as a clamped degree-1 NURBS (unit weights): the polyline through
    them, each knot at the share of the length driven (chord-length parametrisation)."""
    if len(points) < 2:
        raise ValueError(f"a polyline needs at least 2 points, got {len(points)}")
    steps = [math.dist(a, b) for a, b in pairwise(points)]
    total = sum(steps)
    inner: list[float] = [0.0]
    run = 0.0
    for s in steps[:-1]:
        run += s
        inner.append(min(1.0, run / total) if total > 0 else len(inner) / len(steps))
    inner.append(1.0)
    return (0.0, *inner, 1.0)


def waypoints(degree: int, knots: Sequence[float], points: Sequence[Point], weights: Sequence[float]) -> list[Point]:
    """The curve as waypoints from its start to its end: a degree-1 curve's own control points (a
    rational degree-1 curve is still the polyline through them); a higher degree's curve sampled
    and thinned (Douglas-Peucker) to waypoints within ``TOLERANCE_M`` of it. Consecutive repeats are
    dropped. ValueError as ``check``."""
    check(degree, knots, points, weights)
    if degree == 1:
        pts = list(points)
    else:
        n = len(points)
        spans = [i for i in range(degree, n) if knots[i + 1] > knots[i]]
        per = max(2, min(SAMPLES_PER_SPAN, MAX_SAMPLES // len(spans)))
        pts = []
        for i in spans:
            for j in range(per):
                pts.append(_point(degree, knots, points, weights, i, knots[i] + (knots[i + 1] - knots[i]) * j / per))
        last = spans[-1]
        pts.append(_point(degree, knots, points, weights, last, knots[last + 1]))
        pts = simplify(pts, TOLERANCE_M)
    out: list[Point] = []
    for p in pts:
        if not out or math.dist(out[-1], p) > 1e-9:
            out.append((float(p[0]), float(p[1])))
    return out


def _point(
    degree: int, knots: Sequence[float], points: Sequence[Point], weights: Sequence[float], span: int, u: float
) -> Point:
    """The curve at ``u`` in knot span ``span`` (knots[span] <= u <= knots[span + 1]): de Boor's
    algorithm on the homogeneous points (w x, w y, w)."""
    p = degree
    d = [(weights[j] * points[j][0], weights[j] * points[j][1], weights[j]) for j in range(span - p, span + 1)]
    for r in range(1, p + 1):
        for j in range(p, r - 1, -1):
            i = span - p + j
            den = knots[i + p - r + 1] - knots[i]
            a = 0.0 if den <= 0.0 else (u - knots[i]) / den
            (x0, y0, w0), (x1, y1, w1) = d[j - 1], d[j]
            d[j] = ((1.0 - a) * x0 + a * x1, (1.0 - a) * y0 + a * y1, (1.0 - a) * w0 + a * w1)
    x, y, w = d[p]
    if not w > 0.0:
        raise ValueError(f"the curve's weight is 0 at u = {u:g}: undefined there")
    return (x / w, y / w)
