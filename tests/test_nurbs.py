"""NURBS trajectories (shared/nurbs.py, VDA 5050 ``edge.trajectory``) against closed-form curves."""

from __future__ import annotations

import itertools
import math

import pytest

from fleetlink.shared import nurbs
from fleetlink.shared.messages import ControlPoint, Trajectory
from fleetlink.shared.wire import WireError


def test_a_polyline_is_a_degree_1_curve_through_its_points_knotted_by_length() -> None:
    pts = [(0.0, 0.0), (3.0, 0.0), (3.0, 1.0)]
    knots = nurbs.polyline_knots(pts)
    assert knots == (0.0, 0.0, 0.75, 1.0, 1.0)  # 3 m of 4 driven at the corner
    assert nurbs.waypoints(1, knots, pts, [1.0] * 3) == pts
    # Weights move a rational degree-1 curve's parameter, not its path: the same polyline.
    assert nurbs.waypoints(1, knots, pts, [1.0, 5.0, 0.2]) == pts


def test_a_rational_quadratic_is_a_circular_arc() -> None:
    """The quarter circle of radius 2 about (1, 1): control points (3, 1), (3, 3), (1, 3), the middle
    one weighted cos(45 deg) (Piegl and Tiller, section 7.3)."""
    w = math.cos(math.pi / 4)
    pts = nurbs.waypoints(2, (0, 0, 0, 1, 1, 1), [(3.0, 1.0), (3.0, 3.0), (1.0, 3.0)], [1.0, w, 1.0])
    assert pts[0] == (3.0, 1.0) and pts[-1] == pytest.approx((1.0, 3.0))
    assert all(abs(math.hypot(x - 1.0, y - 1.0) - 2.0) < 1e-9 for x, y in pts)
    # Thinned: legs within a centimetre of the arc (a chord's sagitta r(1 - cos(a/2)) <= 1 cm).
    for (ax, ay), (bx, by) in itertools.pairwise(pts):
        mid = math.hypot((ax + bx) / 2 - 1.0, (ay + by) / 2 - 1.0)
        assert 2.0 - mid <= nurbs.TOLERANCE_M + 1e-9
    assert 5 <= len(pts) <= 20


def test_a_clamped_cubic_starts_and_ends_at_its_end_points_and_a_straight_one_stays_straight() -> None:
    pts = [(0.0, 0.0), (1.0, 0.0), (2.0, 0.0), (3.0, 0.0), (4.0, 0.0)]
    knots = (0, 0, 0, 0, 0.5, 1, 1, 1, 1)
    out = nurbs.waypoints(3, knots, pts, [1.0] * 5)
    assert out == [(0.0, 0.0), (4.0, 0.0)]  # collinear: nothing to keep in between
    bent = nurbs.waypoints(3, knots, [(0.0, 0.0), (1.0, 0.0), (2.0, 2.0), (3.0, 0.0), (4.0, 0.0)], [1.0] * 5)
    assert bent[0] == (0.0, 0.0) and bent[-1] == pytest.approx((4.0, 0.0)) and len(bent) > 3
    assert max(y for _, y in bent) < 2.0  # a B-spline stays inside its control polygon's hull


@pytest.mark.parametrize(
    ("degree", "knots", "points", "weights", "why"),
    [
        (0, (0, 1), [(0, 0)], [1], "degree must be an integer"),
        (True, (0, 0, 1, 1), [(0, 0), (1, 0)], [1, 1], "degree must be an integer"),
        (2, (0, 0, 0, 1, 1), [(0, 0), (1, 0)], [1, 1], "needs at least 3 control points"),
        (1, (0, 0, 1), [(0, 0), (1, 0)], [1, 1], "knotVector has 3 values"),
        (1, (0, 0, 1.5, 1), [(0, 0), (1, 0)], [1, 1], "knots lie in [0, 1]"),
        (1, (0, 0.6, 0.5, 1, 1), [(0, 0), (1, 0), (2, 0)], [1, 1, 1], "knots never decrease"),
        (1, (0, 0.5, 0.5, 1), [(0, 0), (1, 0)], [1, 1], "no length"),
        (1, (0, 0, 1, 1), [(0, 0), (math.nan, 0)], [1, 1], "not finite"),
        (1, (0, 0, 1, 1), [(0, 0), (1, 0)], [1, -1], "finite weights > 0"),
        (1, (0, 0, 1, 1), [(0, 0), (1, 0)], [0, 0], "finite weights > 0"),
        # Allowed by the standard, undefined at u = 0 (0/0): refused.
        (2, (0, 0, 0, 1, 1, 1), [(0, 0), (1, 1), (2, 0)], [0, 1, 1], "finite weights > 0"),
    ],
)
def test_what_is_not_a_curve_is_refused_with_the_reason(
    degree: int, knots: tuple[float, ...], points: list[tuple[float, float]], weights: list[float], why: str
) -> None:
    with pytest.raises(ValueError, match=why.replace("[", r"\[").replace("]", r"\]")):
        nurbs.check(degree, knots, points, weights)


def test_a_trajectory_on_the_wire_is_checked_whole_on_decode() -> None:
    from fleetlink.shared.messages import OrderEdge

    edge = OrderEdge(
        edgeId="e1",
        sequenceId=1,
        startNodeId="n0",
        endNodeId="n1",
        released=True,
        trajectory=Trajectory.polyline(((0.0, 0.0), (1.0, 0.0), (1.0, 1.0))),
    )
    assert edge.trajectory is not None and edge.trajectory.waypoints() == [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)]
    from fleetlink.shared import wire

    codec = wire._struct(OrderEdge)
    raw = codec.enc(edge)
    assert codec.dec(raw) == edge
    raw["trajectory"]["knotVector"] = [0.0, 1.0, 1.0, 1.0, 1.0]
    raw["trajectory"]["knotVector"][1] = 0.7
    raw["trajectory"]["knotVector"][2] = 0.5
    with pytest.raises(WireError, match="knots never decrease"):
        codec.dec(raw)
    with pytest.raises(ValueError, match="finite weights > 0"):
        Trajectory(
            degree=1, knotVector=(0, 0, 1, 1), controlPoints=(ControlPoint(x=0, y=0), ControlPoint(x=1, y=0, weight=-1))
        )
