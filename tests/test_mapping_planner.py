"""A* over the inflated grid keeps clear of obstacles; the mapper offers it as a path provider."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from fleetlink.agent.mapping.planner import PathPlanner, PlannerConfig

RES = 0.05


def _room_with_gap() -> np.ndarray:
    """10 m x 5 m, free; a wall across x = 5 m with a 1 m gap at y 3.5-4.5; a pillar at (2.5, 2.5)."""
    g = np.zeros((100, 200), dtype=np.int8)
    g[0, :] = g[-1, :] = 100
    g[:, 0] = g[:, -1] = 100
    g[:, 100] = 100
    g[70:90, 100] = 0
    g[45:55, 45:55] = 100
    return g


def _clearance(g: np.ndarray, pts: list[tuple[float, float]]) -> float:
    occ = np.argwhere(g >= 65)
    centres = np.column_stack(((occ[:, 1] + 0.5) * RES, (occ[:, 0] + 0.5) * RES))
    best = math.inf
    for (x0, y0), (x1, y1) in itertools.pairwise(pts):
        n = max(2, int(math.hypot(x1 - x0, y1 - y0) / 0.01))
        t = np.linspace(0, 1, n)[:, None]
        p = np.column_stack((x0 + (x1 - x0) * t[:, 0], y0 + (y1 - y0) * t[:, 0]))
        d = np.sqrt(((p[:, None, :] - centres[None, :, :]) ** 2).sum(axis=2)).min()
        best = min(best, float(d) - RES / 2)  # to the cell's edge, not its centre
    return best


def test_path_goes_through_the_gap_and_keeps_clear() -> None:
    g = _room_with_gap()
    cfg = PlannerConfig(robot_radius=0.17, margin=0.05)
    planner = PathPlanner(g, RES, (0.0, 0.0), cfg)
    start, goal = (1.0, 1.0), (9.0, 1.0)
    path = planner(start, goal)
    assert path is not None and path[-1] == goal
    pts = [start, *path]
    assert _clearance(g, pts) >= cfg.robot_radius
    assert any(3.5 <= y <= 4.5 and 4.5 <= x <= 5.5 for x, y in pts) or _crosses_gap(pts)


def _crosses_gap(pts: list[tuple[float, float]]) -> bool:
    for (x0, y0), (x1, y1) in itertools.pairwise(pts):
        if (x0 - 5.0) * (x1 - 5.0) < 0:
            y = y0 + (y1 - y0) * (5.0 - x0) / (x1 - x0)
            return 3.5 < y < 4.5
    return False


def test_no_path_when_the_gap_is_narrower_than_the_robot() -> None:
    g = _room_with_gap()
    g[70:90, 100] = 100
    g[78:84, 100] = 0  # 0.3 m: narrower than 2 x 0.22 m
    planner = PathPlanner(g, RES, (0.0, 0.0))
    assert planner((1.0, 1.0), (9.0, 1.0)) is None
    # The goal inside the inflated zone of a wall is refused; a start there may escape.
    assert planner((1.0, 1.0), (5.02, 2.0)) is None
    assert planner((0.1, 1.0), (3.0, 1.0)) is not None


def test_unknown_cells_block_unless_configured() -> None:
    g = np.full((40, 80), -1, dtype=np.int8)
    g[10:30, :] = 0
    g[:, 38:42] = -1  # an unexplored band across the free corridor
    assert PathPlanner(g, RES)((0.5, 1.0), (3.5, 1.0)) is None
    assert PathPlanner(g, RES, config=PlannerConfig(unknown_is_blocked=False))((0.5, 1.0), (3.5, 1.0)) is not None


def test_distance_field_matches_a_brute_force_one() -> None:
    """The planner's distance to the nearest wall, ring by ring, against every (cell, wall) pair."""
    from fleetlink.agent.mapping.planner import _distance

    rng = np.random.default_rng(11)
    for _ in range(20):
        h, w = (int(v) for v in rng.integers(1, 25, 2))
        blocked = rng.random((h, w)) < rng.uniform(0.0, 0.15)
        res, reach = float(rng.choice([0.05, 0.1])), float(rng.uniform(0.05, 0.8))
        walls = np.argwhere(blocked)
        want = np.full((h, w), reach)
        for r in range(h):
            for c in range(w):
                for wr, wc in walls:
                    d = math.hypot(int(wr) - r, int(wc) - c) * res
                    if d < want[r, c]:
                        want[r, c] = d
        assert np.array_equal(_distance(blocked, res, reach), want)


def test_a_goal_beyond_the_map_is_planned_to_the_nearest_reachable_cell_then_straight_on() -> None:
    """A scout sent to coordinates it has not mapped yet heads there (issue 15): through the gap to
    the map's east edge, then on into the unknown. A goal in a known wall still has no path."""
    g = _room_with_gap()
    g[1:-1, -1] = -1  # the east wall not seen yet: the map ends in unknown there
    g[:, 150:] = -1
    planner = PathPlanner(g, RES, (0.0, 0.0))
    goal = (14.0, 2.0)  # 4 m beyond the map's east edge
    path = planner((1.0, 1.0), goal)
    assert path is not None and path[-1] == goal
    edge = path[-2]
    assert 6.5 < edge[0] < 7.5  # the reachable cell nearest the goal, just short of the unknown
    assert _crosses_gap([(1.0, 1.0), *path[:-1]])  # the mapped part keeps to the map (the gap)
    unknown_inside = (8.5, 2.0)  # inside the grid, unknown, no wall near it
    inner = planner((1.0, 1.0), unknown_inside)
    assert inner is not None and inner[-1] == unknown_inside
    assert planner((1.0, 1.0), (5.0, 1.0)) is None  # in the known wall across x = 5 m
    assert planner((1.0, 1.0), (math.inf, 1.0)) is None


def test_a_goal_in_known_space_or_behind_a_known_wall_has_no_way_round_through_the_unknown() -> None:
    g = _room_with_gap()
    planner = PathPlanner(g, RES, (0.0, 0.0), PlannerConfig(unknown_is_blocked=False))
    assert planner((1.0, 1.0), (6.0, 2.0)) is not None  # through the gap, as before
    assert planner((1.0, 1.0), (5.2, 2.0)) is None  # known, too near the wall to stand: not "unexplored"
    g[70:90, 100] = 100  # the gap closed: the east half is known, free, and cut off
    closed = PathPlanner(g, RES, (0.0, 0.0), PlannerConfig(unknown_is_blocked=False))
    assert closed((1.0, 1.0), (6.0, 2.0)) is None  # known space it cannot reach: not "unexplored"
    assert closed((1.0, 1.0), (14.0, 2.0)) is None  # beyond the known outer wall: no frontier
    assert closed((1.0, 1.0), (-3.0, 2.0)) is None


def test_the_frontier_is_one_a_star_can_reach() -> None:
    """Two rooms touching only at a corner: A* does not cut corners, so neither does the search for
    the frontier (it once picked the other room's edge, nearer the goal, which A* could not reach,
    and planned nothing)."""
    g = np.full((40, 40), 100, dtype=np.int8)
    g[2:20, 2:20] = 0  # the robot's room
    g[0:20, 20:] = -1  # unseen to its east (planned as blocked here)
    g[20:38, 20:38] = 0  # a room touching it at one corner only, unseen to its east too
    g[20:38, 38:] = -1
    cfg = PlannerConfig(robot_radius=0.01, margin=0.0, sensor=None)
    planner = PathPlanner(g, RES, (0.0, 0.0), cfg)
    goal = (3.0, 1.5)  # off the map, east: the other room's edge is nearer it
    path = planner((0.5, 0.5), goal)
    assert path is not None and path[-1] == goal
    assert all(x < 1.0 and y < 1.0 for x, y in path[:-1])  # from its own room's eastern edge


def test_room_behind_stops_short_of_a_wall_behind_and_not_of_one_beside() -> None:
    res = 0.05
    g = np.zeros((80, 80), dtype=np.int8)  # 4 m x 4 m, free
    g[:, 40] = 100  # a wall along x = 2.0-2.05
    planner = PathPlanner(g, res)
    limit = 0.15
    # Facing west (away from the wall), 0.3 m from its face: backing east, the body (0.17 m)
    # stops back_margin short of it, the cell's near edge counted.
    room = planner.room_behind((2.0 - 0.3, 1.0, math.pi), limit)
    expected = 0.3 - planner.config.robot_radius - planner.config.back_margin
    assert abs(room - expected) < res / 2
    # Facing the wall: backing away from it has all the room asked for.
    assert planner.room_behind((2.0 - 0.3, 1.0, 0.0), limit) == limit
    # Beside the wall, parallel to it, nearer than the margin but not touching: backing along it is free.
    assert planner.room_behind((2.0 - 0.2, 1.0, math.pi / 2), limit) == limit
    # Touching it already, with the wall behind: no room at all.
    assert planner.room_behind((2.0 - 0.17, 1.0, math.pi), limit) < 0.01
    # Off the map behind counts as blocked; a non-finite pose has no room.
    assert planner.room_behind((0.1, 1.0, 0.0), limit) == 0.0
    assert planner.room_behind((math.nan, 1.0, 0.0), limit) == 0.0


def test_a_goal_inside_the_margin_where_the_body_fits_ends_with_a_straight_leg_to_it() -> None:
    # A sweep's lane end 0.25 m from a wall's face: inside the planner's 0.22 m margin (as plan cells
    # of 0.1 m count it) but the 0.17 m body fits with room to spare.
    g = _room_with_gap()
    planner = PathPlanner(g, RES, (0.0, 0.0), PlannerConfig(unknown_is_blocked=False))
    goal = (5.05 + 0.25, 2.0)
    assert not planner.is_free(goal)
    path = planner((1.0, 1.0), goal)
    assert path is not None and path[-1] == goal
    assert planner.is_free(path[-2]) and math.dist(path[-2], goal) <= planner.config.escape + 1e-9
    assert _clearance(g, [path[-2], goal]) >= planner.config.robot_radius
    # Where the body would touch the wall (0.15 m from its face), still no path.
    assert planner((1.0, 1.0), (5.05 + 0.15, 2.0)) is None


def test_the_echo_the_map_expects_and_legs_that_clear_its_walls() -> None:
    g = _room_with_gap()
    planner = PathPlanner(g, RES, (0.0, 0.0), PlannerConfig(unknown_is_blocked=False))
    # Facing the dividing wall (x = 5.0) from 0.6 m: the sensor, 0.17 m ahead, sees it at ~0.43 m.
    echo = planner.echo_ahead((4.4, 2.0, 0.0), 1.5)
    assert 0.38 < echo < 0.46
    assert planner.echo_ahead((4.4, 2.0, math.pi), 1.0) == 1.0  # nothing for a metre behind it
    assert planner.echo_ahead((9.0, 2.0, 0.0), 3.0) < 1.1  # the map's own border wall
    # A leg beside the wall, 0.25 m from its face, clears it; one into it does not.
    assert planner.leg_clear((5.3, 1.0), (5.3, 3.0))
    assert not planner.leg_clear((4.0, 2.0), (6.0, 2.0))
    assert not planner.leg_clear((math.nan, 1.0), (5.3, 3.0))
    # Standing touching the wall on the map (its face at x 5.05, the body's edge at 5.10 with the
    # map's half cell): a leg straight away from it clears it; along it or into it, it does not.
    assert not planner._body_fits((5.22, 2.0), planner.config.back_margin)
    assert planner.leg_clear((5.22, 2.0), (5.6, 2.0))
    assert not planner.leg_clear((5.22, 2.0), (5.22, 3.0))
    assert not planner.leg_clear((5.22, 2.0), (5.15, 2.0))


def test_leg_meets_wall_sees_known_walls_on_the_leg_only() -> None:
    """What the route asks of a newer map about the leg it drives: a known wall within the body's
    radius of the leg (beyond its first 0.1 m) meets it; unknown, a wall off the leg, or one the
    robot already stands beside, does not."""
    g = np.zeros((100, 200), dtype=np.int8)  # 10 x 5 m of floor
    g[40:60, 100] = 100  # a wall cell column at x 5.0-5.05, y 2.0-3.0
    g[:, 150:] = -1  # unknown beyond x = 7.5
    p = PathPlanner(g, RES)
    assert p.leg_meets_wall((1.0, 2.5), (8.0, 2.5))  # straight through the wall
    assert p.leg_meets_wall((1.0, 3.1), (8.0, 3.1))  # passing its end 0.075 m from the cell's centre
    assert not p.leg_meets_wall((1.0, 3.3), (8.0, 3.3))  # 0.275 m off: the body passes
    assert not p.leg_meets_wall((6.0, 1.0), (9.5, 1.0))  # into the unknown: not a wall
    assert not p.leg_meets_wall((5.2, 2.5), (6.0, 2.5))  # the wall beside the start, behind it
    assert not p.leg_meets_wall((1.0, 2.5), (1.0, 2.5))  # no leg
    assert not p.leg_meets_wall((1.0, float("nan")), (8.0, 2.5))


def test_barred_by_movable_tells_a_robot_drawn_on_the_goal_from_a_wall() -> None:
    """A goal with a robot-sized blob of occupied cells on it (another robot drawn standing there)
    is barred by something that may move; one in or beside a wall, by a wall; a free goal is not
    barred at all; a blob bigger than a person, or one joined to a wall, is not movable."""
    g = _room_with_gap()
    g[20:26, 150:156] = 100  # a robot, 0.3 m across, standing at (7.65, 1.15)
    g[60:80, 30:32] = 100  # a crate 1 m long at x 1.5-1.6, y 3-4
    g[30:35, 96:100] = 100  # a blob touching the wall at x = 5 m
    planner = PathPlanner(g, RES, (0.0, 0.0), PlannerConfig())
    robot = (7.65, 1.15)
    assert planner((1.0, 1.0), robot) is None  # no path: the goal is barred
    assert planner.barred_by_movable(robot)
    assert planner.barred_by_movable((7.65 + 0.3, 1.15))  # beside it, within the margin
    assert not planner.barred_by_movable((5.02, 2.5))  # in the dividing wall
    assert not planner.barred_by_movable((1.55, 3.5))  # on the crate
    assert not planner.barred_by_movable((4.85, 1.6))  # on the blob that joins the wall
    assert not planner.barred_by_movable((7.0, 3.0))  # free: not barred by anything
    assert not planner.barred_by_movable((math.nan, 1.0))
    g3 = g.copy()
    for k in range(11):  # a stub of wall on the diagonal, 0.76 m long, in a box 0.55 m a side
        g3[70 + k, 160 + k] = 100
    assert not PathPlanner(g3, RES, (0.0, 0.0), PlannerConfig()).barred_by_movable((8.275, 3.775))
    g2 = g.copy()
    g2[:, -1] = 0
    g2[20:26, 194:200] = 100  # a robot at the map's edge: what lies beyond is not known
    assert not PathPlanner(g2, RES, (0.0, 0.0), PlannerConfig()).barred_by_movable((9.85, 1.15))


def test_place_near_is_the_reachable_place_on_the_ring_nearest_the_start() -> None:
    """On the line to the start when the robot can stand there; else the next round the ring it can
    reach; None when the goal is shut away (one flood, no failed searches)."""
    g = _room_with_gap()
    planner = PathPlanner(g, RES, (0.0, 0.0), PlannerConfig())
    q = planner.place_near((1.0, 1.0), (7.0, 1.0), 2.0)  # beyond the wall, through the gap
    assert q is not None and math.dist(q, (7.0, 1.0)) == pytest.approx(2.0)
    assert q[0] > 5.2 and planner.route((1.0, 1.0), q)  # on the goal's side of the wall: x 5 is the wall
    q = planner.place_near((9.0, 1.0), (7.0, 1.0), 2.0)  # the start in the goal's room: on the line
    assert q == pytest.approx((9.0, 1.0))
    # The nearest place the robot reaches, (4.45, 1.15), is behind the wall from the goal: not it.
    q = planner.place_near((1.0, 1.15), (6.45, 1.15), 2.0)
    assert q is not None and q[0] > 5.1
    shut = g.copy()
    shut[70:90, 100] = 100  # the gap closed: the right-hand room cannot be reached from the left
    planner = PathPlanner(shut, RES, (0.0, 0.0), PlannerConfig())
    q = planner.place_near((1.0, 1.0), (8.5, 2.5), 1.0)
    assert q is None
    assert planner.place_near((1.0, 1.0), (math.nan, 1.0), 1.0) is None
