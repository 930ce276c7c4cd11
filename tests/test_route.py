"""The route follower alone: planning, re-planning on refusals and lack of progress, backing off, failing.

Pure: a ``Route`` with a fresh ``GoToController``, scripted path providers and guard refusals,
times passed in; no pilot, no guard.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
import pytest

from fleetlink.agent.guard import Refusal, RefusalReason
from fleetlink.agent.motion import GoToController
from fleetlink.agent.route import Destination, Route, RouteConfig, RoutePhase
from tests.test_motion import Unicycle

Point = tuple[float, float]
DEST = Destination("o1", 0, 4.0, 0.0, None, "op")
IN_PATH = Refusal(RefusalReason.OBSTACLE_IN_PATH, "something in the way", 0.8)
AHEAD = Refusal(RefusalReason.OBSTACLE_AHEAD, "something in front", 0.3)


class Provider:
    """Answers with scripted paths in turn (the last one repeats) and records each call."""

    def __init__(self, *answers: Sequence[Point] | None) -> None:
        self.answers = list(answers)
        self.calls: list[tuple[Point, Point, tuple[Point, ...]]] = []

    def __call__(self, start: Point, goal: Point, /, blocked: Sequence[Point] = ()) -> Sequence[Point] | None:
        self.calls.append((start, goal, tuple(blocked)))
        return self.answers.pop(0) if len(self.answers) > 1 else self.answers[0]


def route(config: RouteConfig | None = None) -> Route:
    return Route(DEST, GoToController(), config or RouteConfig())


def test_without_a_provider_it_drives_straight_and_reaches_the_goal() -> None:
    r, body, t = route(), Unicycle(), 0.0
    first = r.step(t, body.pose, None)
    assert r.phase is RoutePhase.STRAIGHT and r.notes == [] and r.goto.waypoints == [(4.0, 0.0)]
    assert first.distance_m is None or first.distance_m > 0  # turning or starting the drive
    while r.end is None and t < 30.0:
        d = r.step(t, body.pose, None)
        body.step(d.v, d.omega, 0.02)
        t += 0.02
    assert r.end is not None and r.end.reached and r.end.reason == "reached"
    assert math.hypot(body.x - 4.0, body.y) < 0.01


def test_a_provider_without_a_map_means_straight_and_an_empty_path_fails() -> None:
    r = route()
    r.step(0.0, (0.0, 0.0, 0.0), Provider(None))
    assert r.phase is RoutePhase.STRAIGHT and r.end is None and r.notes == []
    r = route()
    provider = Provider([])
    d = r.step(0.0, (0.0, 0.0, 0.0), provider)
    assert (d.v, d.omega) == (0.0, 0.0)
    assert r.end is None and r.phase is RoutePhase.WAITING  # the way may clear: a newer map may have one
    [note] = r.notes
    assert note.reason == "waiting" and "no path to (4.00, 0.00)" in note.text
    d = r.step(5.9, (0.0, 0.0, 0.0), provider)  # the same map: not asked again
    assert (d.v, d.omega) == (0.0, 0.0) and r.end is None and len(provider.calls) == 1
    r.step(6.0, (0.0, 0.0, 0.0), provider)
    assert r.end is not None and not r.end.reached and r.end.reason == "no_path" and "(4.00, 0.00)" in r.end.text
    assert "waited 6 s" in r.end.text
    r = route(RouteConfig(no_path_wait_s=0.0))  # no waiting: fails at once
    r.step(0.0, (0.0, 0.0, 0.0), Provider([]))
    assert r.end is not None and r.end.reason == "no_path"


def test_no_path_waits_for_a_newer_map_and_goes_when_it_has_one() -> None:
    """Another robot standing in the way: no path on the map of the moment; the next map (it has
    moved on) has one, and the go-to goes, within ``no_path_wait_s``."""
    r, body = route(), Unicycle()
    barred = Provider([])
    r.step(0.0, body.pose, barred)
    assert r.phase is RoutePhase.WAITING
    still = Provider([])  # a newer map, still barred: asked, still waiting, the clock not restarted
    r.step(2.0, body.pose, still)
    assert r.phase is RoutePhase.WAITING and len(still.calls) == 1 and r.waiting_since == 0.0
    clear = Provider([(2.0, 0.5), (4.0, 0.0)])
    r.step(4.0, body.pose, clear)
    assert r.phase is RoutePhase.FOLLOWING and r.end is None and r.goto.waypoints == [(2.0, 0.5), (4.0, 0.0)]
    t = 4.0
    while r.end is None and t < 40.0:
        d = r.step(t, body.pose, clear)
        body.step(d.v, d.omega, 0.02)
        t += 0.02
    assert r.end is not None and r.end.reached


class GoalBarred(Provider):
    """A map on which the goal itself is barred and every other place has a straight path: by
    another robot drawn standing on it (``barred_by_movable``), or by a wall (``wall``); ``clear``:
    the goal is free too (a newer map that saw the place empty)."""

    def __init__(self, goal: Point = (8.0, 0.0), clear: bool = False, wall: bool = False) -> None:
        super().__init__([])
        self.goal, self.clear, self.wall = goal, clear, wall

    def __call__(self, start: Point, goal: Point, /, blocked: Sequence[Point] = ()) -> Sequence[Point] | None:
        self.calls.append((start, goal, tuple(blocked)))
        return [goal] if self.clear or math.dist(goal, self.goal) > 0.5 else []

    def barred_by_movable(self, p: Point, /) -> bool:
        return not self.clear and not self.wall and math.dist(p, self.goal) < 1e-9

    def place_near(self, start: Point, goal: Point, radius: float, /) -> Point | None:
        d = math.dist(start, goal)
        return (goal[0] + radius * (start[0] - goal[0]) / d, goal[1] + radius * (start[1] - goal[1]) / d)


FAR = Destination("o1", 0, 8.0, 0.0, None, "op")


def drive(r: Route, body: Unicycle, t: float, provider: Provider, until: float, go_on: Callable[[], bool]) -> float:
    """Step the route on ``provider`` while ``go_on()`` and it has not ended (up to ``until``); the
    time reached."""
    while go_on() and r.end is None and t < until:
        d = r.step(t, body.pose, provider)
        body.step(d.v, d.omega, 0.02)
        t += 0.02
    return t


def test_no_path_to_a_far_goal_goes_nearer_to_look_then_waits_from_there() -> None:
    """The map of a place 8 m off shows it barred (another robot stood there, and from afar no beam
    has passed through it since it went): the robot first goes to within ``approach_m`` of it, nearest
    place on the ring first, then stands and waits ``no_path_wait_s`` from where it arrived. A newer
    map still barred there changes nothing: the approach is made once."""
    r, body = Route(FAR, GoToController(), RouteConfig()), Unicycle()
    barred = GoalBarred()
    r.step(0.0, body.pose, barred)
    assert r.phase is RoutePhase.APPROACHING and r.end is None and r.waiting_since is None
    [note] = r.notes
    assert note.reason == "waiting" and "going within 2 m of it to look" in note.text
    [(x, y)] = r.goto.waypoints  # the ring's place nearest the robot
    assert (x, y) == pytest.approx((6.0, 0.0))
    t = drive(r, body, 0.0, barred, 30.0, lambda: r.phase is RoutePhase.APPROACHING)
    assert r.phase is RoutePhase.WAITING and r.end is None and r.waiting_since == pytest.approx(t, abs=0.03)
    assert math.hypot(body.x - 6.0, body.y) < 0.1
    arrived = t
    still = GoalBarred()  # a newer map, the goal still barred: asked once, no second approach
    assert r.step(t, body.pose, still).v == 0.0 and r.phase is RoutePhase.WAITING and len(still.calls) == 1
    r.step(arrived + 5.9, body.pose, still)
    assert r.end is None
    r.step(arrived + 6.0, body.pose, still)
    assert r.end is not None and r.end.reason == "no_path" and "waited 6 s" in r.end.text


def test_a_newer_map_with_a_path_ends_the_approach_and_the_goal_is_reached() -> None:
    """Half way there the robot's map shows the goal clear: it goes on to the goal itself."""
    r, body = Route(FAR, GoToController(), RouteConfig()), Unicycle()
    barred = GoalBarred()
    r.step(0.0, body.pose, barred)
    t = drive(r, body, 0.0, barred, 30.0, lambda: body.x < 3.0)
    assert r.phase is RoutePhase.APPROACHING
    r.notes.clear()
    clear = GoalBarred(clear=True)
    assert r.step(t, body.pose, clear).v == 0.0
    assert r.phase is RoutePhase.FOLLOWING and r.goto.waypoints == [(8.0, 0.0)]
    assert [n.reason for n in r.notes] == ["planned"]
    drive(r, body, t, clear, 60.0, lambda: r.phase is RoutePhase.FOLLOWING)
    assert r.end is not None and r.end.reached and math.hypot(body.x - 8.0, body.y) < 0.05


def test_barred_on_the_approach_it_waits_where_it_stands() -> None:
    """The guard bars the approach (something in the way): no marks, no re-plans, no failure; the
    robot looks from where it stands, and the wait counts from then."""
    r, body = Route(FAR, GoToController(), RouteConfig()), Unicycle()
    barred = GoalBarred()
    r.step(0.0, body.pose, barred)
    r.refused(1.0, body.pose, IN_PATH, barred)
    assert r.phase is RoutePhase.WAITING and r.waiting_since == 1.0 and r.end is None
    assert r.blocked == [] and r.replans == 0
    r.step(6.9, body.pose, barred)
    assert r.end is None
    r.step(7.0, body.pose, barred)
    assert r.end is not None and r.end.reason == "no_path"


class BarredAgain(GoalBarred):
    """A newer map on which the goal is barred again and the leg ahead meets a wall (``WallCheck``)."""

    def leg_meets_wall(self, a: Point, b: Point, skip_m: float = 0.1, /) -> bool:
        return True


def test_the_approach_is_made_once_a_go_to() -> None:
    """Approached, then a map with a path, then one barring the goal again further off than
    ``approach_m``: the robot waits where it is, it does not go nearer a second time."""
    r, body = Route(FAR, GoToController(), RouteConfig()), Unicycle()
    r.step(0.0, body.pose, GoalBarred())
    assert r.phase is RoutePhase.APPROACHING
    clear = GoalBarred(clear=True)
    r.step(0.1, body.pose, clear)
    assert r.phase is RoutePhase.FOLLOWING
    t = drive(r, body, 0.1, clear, 30.0, lambda: body.x < 1.0)
    again = BarredAgain()
    r.step(t, body.pose, again)
    assert r.phase is RoutePhase.WAITING and r.waiting_since == t and r.map_replans == 1
    assert math.dist((body.x, body.y), (8.0, 0.0)) > 2.5  # far enough for an approach, had it been the first


def test_no_progress_on_the_approach_or_something_in_front_for_long_ends_it_where_the_robot_stands() -> None:
    """Wheels that do not turn (a body that never moves) for ``no_progress_s``; something in front
    (held ``replan_hold_s`` first, as on a path): the robot stands and waits from then."""
    r = Route(FAR, GoToController(), RouteConfig())
    barred = GoalBarred()
    r.step(0.0, (0.0, 0.0, 0.0), barred)
    t = 0.0
    while r.phase is RoutePhase.APPROACHING and t < 20.0:
        t += 0.1
        r.step(t, (0.0, 0.0, 0.0), barred)
    assert r.phase is RoutePhase.WAITING and r.end is None
    assert RouteConfig().no_progress_s <= r.waiting_since <= RouteConfig().no_progress_s + 0.2
    r = Route(FAR, GoToController(), RouteConfig())
    r.step(0.0, (0.0, 0.0, 0.0), barred)
    r.refused(1.0, (0.0, 0.0, 0.0), AHEAD, barred)
    assert r.phase is RoutePhase.APPROACHING and r.held_since == 1.0  # held: it may go away
    r.refused(2.9, (0.0, 0.0, 0.0), AHEAD, barred)
    assert r.phase is RoutePhase.APPROACHING
    r.refused(3.0, (0.0, 0.0, 0.0), AHEAD, barred)
    assert r.phase is RoutePhase.WAITING and r.waiting_since == 3.0 and r.blocked == []


def test_a_goal_in_a_wall_a_near_goal_or_no_approach_distance_waits_where_it_stands() -> None:
    """A goal in a wall is not driven at (tests/test_vda5050_e2e.py: a node inside a wall is
    skipped at once); nor is one already near, or any with ``approach_m`` 0."""
    r = Route(FAR, GoToController(), RouteConfig())
    in_wall = GoalBarred(wall=True)
    r.step(0.0, (0.0, 0.0, 0.0), in_wall)
    assert r.phase is RoutePhase.WAITING and r.waiting_since == 0.0 and len(in_wall.calls) == 1
    r = Route(FAR, GoToController(), RouteConfig())
    plain = Provider([])  # a provider that cannot tell (no map sense): no approach either
    r.step(0.0, (0.0, 0.0, 0.0), plain)
    assert r.phase is RoutePhase.WAITING and len(plain.calls) == 1
    for dest, config in (
        (Destination("o1", 0, 2.4, 0.0, None, "op"), RouteConfig()),
        (FAR, RouteConfig(approach_m=0.0)),
    ):
        r = Route(dest, GoToController(), config)
        provider = GoalBarred((dest.x, dest.y))
        r.step(0.0, (0.0, 0.0, 0.0), provider)
        assert r.phase is RoutePhase.WAITING and r.waiting_since == 0.0 and len(provider.calls) == 1


class WallAt:
    """A provider with a wall's margin where x > 3.9: goals there have no path, others a straight one."""

    def __init__(self) -> None:
        self.calls: list[Point] = []

    def __call__(self, start: Point, goal: Point, /, blocked: Sequence[Point] = ()) -> Sequence[Point] | None:
        self.calls.append(goal)
        return [] if goal[0] > 3.9 else [start, goal]


def test_a_goal_that_cannot_be_reached_is_taken_at_the_nearest_place_within_its_allowed_deviation() -> None:
    r = Route(replace(DEST, deviation=0.15), GoToController(), RouteConfig())
    walls = WallAt()
    body, t = Unicycle(), 0.0
    r.step(t, body.pose, walls)
    assert r.phase is RoutePhase.FOLLOWING
    assert r.dest.x == pytest.approx(3.9, abs=1e-9) and r.dest.y == pytest.approx(0.0, abs=1e-9)  # 0.10 m short
    assert (r.dest.order_id, r.dest.deviation) == ("o1", 0.15)
    assert walls.calls[0] == (4.0, 0.0) and len(walls.calls) <= 1 + 8 + 16  # two rings at most
    deviated, planned = r.notes
    assert deviated.reason == "deviated" and "(4.00, 0.00) cannot be reached: going to (3.90, 0.00)" in deviated.text
    assert planned.reason == "planned"
    while r.end is None and t < 30.0:
        d = r.step(t, body.pose, walls)
        body.step(d.v, d.omega, 0.02)
        t += 0.02
    assert r.end is not None and r.end.reached
    assert math.hypot(body.x - 3.9, body.y) < 0.01


def test_no_place_within_the_allowed_deviation_means_no_path_and_none_means_only_the_goal() -> None:
    now = RouteConfig(no_path_wait_s=0.0)
    r = Route(replace(DEST, deviation=0.05), GoToController(), now)
    r.step(0.0, (0.0, 0.0, 0.0), WallAt())  # 3.95 is in the margin too
    assert r.end is not None and r.end.reason == "no_path" and "(4.00, 0.00)" in r.end.text
    walls = WallAt()
    r = route(now)
    r.step(0.0, (0.0, 0.0, 0.0), walls)
    assert r.end is not None and r.end.reason == "no_path" and walls.calls == [(4.0, 0.0)]


def test_a_planned_path_drops_the_start_and_ends_at_the_goal() -> None:
    r = route()
    r.step(0.0, (0.0, 0.0, 0.0), Provider([(0.01, 0.0), (2.0, 1.0), (4.0, 0.02)]))
    assert r.phase is RoutePhase.FOLLOWING
    assert r.goto.waypoints == [(2.0, 1.0), (4.0, 0.02), (4.0, 0.0)]
    [note] = r.notes
    assert (note.replanned, note.reason, note.waypoints) == (False, "planned", 3)
    assert note.text.startswith("order o1/0: planned path")


def test_a_refused_drive_start_marks_the_echo_and_replans_around_it() -> None:
    provider = Provider([(2.0, 0.0), (4.0, 0.0)], [(2.0, 1.0), (4.0, 0.0)])
    r = route()
    r.step(0.0, (0.0, 0.0, 0.0), provider)
    r.notes.clear()
    r.refused(1.0, (0.5, 0.0, 0.0), IN_PATH, provider)
    c = r.config
    assert r.replans == 1 and r.phase is RoutePhase.FOLLOWING and r.end is None
    assert r.blocked == [(pytest.approx(0.5 + c.sensor_offset_m + 0.8 + c.mark_depth_m), 0.0)]
    assert provider.calls[-1] == ((0.5, 0.0), (4.0, 0.0), tuple(r.blocked))
    [note] = r.notes
    assert (note.replanned, note.reason, note.waypoints) == (True, "blocked", 2)
    assert "re-planned (blocked, 1/3)" in note.text


class BarredOnlyByMarks(Provider):
    """A map with a straight way to the goal; no way at all with any marks (something met on the
    goal itself: a robot head on, a person standing there)."""

    def __call__(self, start: Point, goal: Point, /, blocked: Sequence[Point] = ()) -> Sequence[Point] | None:
        self.calls.append((start, goal, tuple(blocked)))
        return [] if blocked else [goal]


def test_barred_with_no_way_around_by_what_the_map_does_not_hold_waits_then_tries_again() -> None:
    """Two scouts met head on, the goal of one behind the other (CI's two-scout console test in
    lockstep): the guard bars the way, the mark covers the goal, so no way around, but the map alone
    has one. What barred it may move: the route waits ``no_path_wait_s``, then forgets its marks and
    drives again (barred again, that counts as a re-plan, and the bound still ends it)."""
    provider = BarredOnlyByMarks()
    r = route()
    r.step(0.0, (0.0, 0.0, 0.0), provider)
    r.notes.clear()
    r.refused(1.0, (3.0, 0.0, 0.0), IN_PATH, provider)
    assert r.replans == 1 and r.phase is RoutePhase.WAITING and r.end is None and r.blocked
    [note] = r.notes
    assert note.reason == "waiting"
    assert "barred on the way to (4.00, 0.00) by something not on the map: waiting up to 6 s" in note.text
    assert r.step(4.0, (3.0, 0.0, 0.0), provider).v == 0.0 and r.phase is RoutePhase.WAITING
    newer = BarredOnlyByMarks()  # a newer map within the wait: asked with the marks, still waiting
    r.step(5.0, (3.0, 0.0, 0.0), newer)
    assert r.phase is RoutePhase.WAITING and newer.calls[-1][2] == tuple(r.blocked)
    r.step(7.0, (3.0, 0.0, 0.0), newer)
    assert r.phase is RoutePhase.FOLLOWING and r.blocked == [] and r.end is None
    assert r.goto.waypoints == [(4.0, 0.0)] and r.waiting_since is None
    # Still there: barred again, and again, until the re-plans are used up.
    r.refused(8.0, (3.0, 0.0, 0.0), IN_PATH, newer)
    assert r.replans == 2 and r.phase is RoutePhase.WAITING
    r.step(14.0, (3.0, 0.0, 0.0), newer)
    r.refused(15.0, (3.0, 0.0, 0.0), IN_PATH, newer)
    r.step(21.0, (3.0, 0.0, 0.0), newer)
    r.refused(22.0, (3.0, 0.0, 0.0), IN_PATH, newer)
    assert r.replans == 3 and (r.phase.failing or r.end is not None)
    assert r._failure is not None and "still blocked after 3 re-plans" in r._failure[1]


def test_barred_with_no_way_around_on_the_map_itself_fails_as_before() -> None:
    provider = Provider([(4.0, 0.0)], [])  # the map has no way either (planned on, then a wall)
    r = route()
    r.step(0.0, (0.0, 0.0, 0.0), provider)
    r.refused(1.0, (3.0, 0.0, 0.0), IN_PATH, provider)
    assert r.phase.failing or r.end is not None
    assert r._failure is not None and r._failure[1] == "blocked (blocked) and no way around"


def test_on_a_straight_route_a_refused_drive_start_fails_it() -> None:
    r = route()
    r.step(0.0, (0.0, 0.0, 0.0), None)
    r.refused(0.5, (0.0, 0.0, 0.0), IN_PATH, None)
    assert r.end is not None and (r.end.reached, r.end.reason) == (False, "obstacle_in_path")


def test_held_by_something_in_front_waits_then_backs_off_and_replans() -> None:
    provider = Provider([(4.0, 0.0)])
    r = route()
    pose = (1.0, 0.0, 0.0)
    r.step(0.0, pose, provider)
    r.refused(1.0, pose, AHEAD, provider)
    assert r.held_since == 1.0 and r.phase is RoutePhase.FOLLOWING  # it may go away
    r.refused(1.0 + r.config.replan_hold_s - 0.01, pose, AHEAD, provider)
    assert r.phase is RoutePhase.FOLLOWING and r.blocked == []
    r.refused(1.0 + r.config.replan_hold_s, pose, AHEAD, provider)
    assert r.phase is RoutePhase.BACKING_OFF and len(r.blocked) == 1 and r.held_since is None
    t = 3.1
    d = r.step(t, pose, provider)
    assert (d.v, d.omega) == (-r.config.backoff_speed, 0.0)  # straight back: turning is refused there
    backed = (pose[0] - r.config.backoff_m, 0.0, 0.0)
    r.step(t + 1.5, backed, provider)
    assert r.phase is RoutePhase.FOLLOWING and r.replans == 1 and r.notes[-1].replanned
    assert provider.calls[-1][2] == tuple(r.blocked)


def test_held_by_another_robot_waits_then_replans_where_it_stands_without_a_mark() -> None:
    """Another robot is no mark: standing, it is planned around as a body; gone, a mark would bar
    the way it left. Nor is the robot backed off: turning passes another robot, and backing may
    meet one behind, which the map does not hold."""
    robot = Refusal(RefusalReason.ROBOT_AHEAD, "another robot 0.05 m ahead", 0.05)
    provider = Provider([(4.0, 0.0)])
    r = route()
    pose = (1.0, 0.0, 0.0)
    r.step(0.0, pose, provider)
    r.refused(1.0, pose, robot, provider)
    assert r.held_since == 1.0 and r.phase is RoutePhase.FOLLOWING  # it may go on
    r.refused(1.0 + r.config.replan_hold_s, pose, robot, provider)
    assert r.phase is RoutePhase.FOLLOWING and r.blocked == [] and r.held_since is None
    assert r.replans == 1 and provider.calls[-1] == ((pose[0], pose[1]), (4.0, 0.0), ())


def test_held_past_the_blocked_timeout_fails_a_straight_route() -> None:
    r = route(RouteConfig(blocked_timeout_s=5.0))
    r.step(0.0, (0.0, 0.0, 0.0), None)
    r.refused(1.0, (0.0, 0.0, 0.0), AHEAD, None)
    r.refused(5.9, (0.0, 0.0, 0.0), AHEAD, None)
    assert r.end is None
    r.refused(6.0, (0.0, 0.0, 0.0), AHEAD, None)
    assert r.end is not None and r.end.reason == "blocked" and "blocked for 5 s" in r.end.text


def test_resume_ends_the_hold_and_restarts_the_progress_clock() -> None:
    r = route()
    r.step(0.0, (0.0, 0.0, 0.0), Provider([(4.0, 0.0)]))
    r.refused(1.0, (0.0, 0.0, 0.0), AHEAD, None)
    r.resume(50.0)
    assert r.held_since is None
    r.step(50.0, (0.0, 0.0, 0.0), None)
    assert r.replans == 0  # 50 s without progress, but paused: not stalled


def test_no_progress_replans_and_the_bound_ends_in_a_failure_after_retreating() -> None:
    c = RouteConfig(no_progress_s=1.0, max_replans=1)
    provider = Provider([(2.0, 0.0), (4.0, 0.0)])
    r = route(c)
    t = 0.0
    pose = (0.0, 0.0, 0.0)
    while r.replans == 0 and t < 5.0:
        r.step(t, pose, provider)  # the robot never moves: no progress
        t += 0.02
    assert r.replans == 1 and r.notes[-1].reason == "no_progress" and t < 1.2
    # It drives on and gets stuck past x = 1 m: stalled again, the bound is reached, so it backs
    # off along the way it came (the trail holds where the legs began), then fails.
    body = Unicycle(*pose)
    while r.phase is not RoutePhase.RETREATING and t < 30.0:
        d = r.step(t, body.pose, provider)
        if body.x < 1.0:
            body.step(d.v, d.omega, 0.02)
        t += 0.02
    assert r.phase is RoutePhase.RETREATING
    while r.end is None and t < 60.0:
        d = r.step(t, body.pose, provider)
        body.step(d.v, d.omega, 0.02)
        t += 0.02
    assert r.end is not None and not r.end.reached and r.end.reason == "blocked"
    assert "after 1 re-plans" in r.end.text and "backed off to" in r.end.text
    assert body.x < 1.0  # back along the way it came


def test_a_refusal_while_retreating_ends_it_there() -> None:
    r = route(RouteConfig(max_replans=0))
    provider = Provider([(4.0, 0.0)])
    r.step(0.0, (0.0, 0.0, 0.0), provider)
    r._trail.append((-1.0, 0.0))  # a leg began 1 m behind
    r.refused(1.0, (0.0, 0.0, 0.0), IN_PATH, provider)
    assert r.phase is RoutePhase.RETREATING and r.end is None and r.goto.waypoints == [(-0.5, 0.0)]
    r.refused(1.5, (0.0, 0.0, 0.0), AHEAD, provider)
    assert r.end is not None and r.end.reason == "blocked" and "(something in front)" in r.end.text


def test_a_provider_withdrawn_mid_route_means_straight_from_here() -> None:
    r = route()
    r.step(0.0, (0.0, 0.0, 0.0), Provider([(2.0, 0.0), (4.0, 0.0)]))
    r.refused(1.0, (0.5, 0.0, 0.0), IN_PATH, None)  # the map was dropped meanwhile
    assert r.phase is RoutePhase.STRAIGHT and r.goto.waypoints == [(4.0, 0.0)] and r.end is None


def test_cut_short_asks_for_what_the_echo_leaves_clear_on_a_path_only() -> None:
    r = route()
    r.step(0.0, (0.0, 0.0, 0.0), Provider([(4.0, 0.0)]))
    c = r.config
    short = r.cut_short((0.0, 0.0, 0.0), 2.0, 4.0)
    assert short == 2.0 - c.stop_distance_m - c.creep_margin_m
    assert r.goto.waypoints[0] == (short, 0.0)
    assert r.cut_short((0.0, 0.0, 0.0), None, 4.0) == 4.0  # nothing seen
    assert r.cut_short((0.0, 0.0, 0.0), 0.6, 4.0) == 4.0  # too short to creep: the guard decides
    straight = route()
    straight.step(0.0, (0.0, 0.0, 0.0), None)
    assert straight.cut_short((0.0, 0.0, 0.0), 2.0, 4.0) == 4.0


def test_a_back_off_goes_only_as_far_as_the_map_behind_allows() -> None:
    # A door jamb 7 cm behind the robot: it backs 7 cm, not the full 15 (it has no sensor behind
    # it; backing the full way drove it into the jamb, whose bumper then allowed only more backing).
    provider = Provider([(4.0, 0.0)])
    r = route()
    pose = (1.0, 0.0, 0.0)
    asked: list[tuple[tuple[float, float, float], float]] = []

    def room(p: tuple[float, float, float], limit: float) -> float:
        asked.append((p, limit))
        return 0.07

    r.step(0.0, pose, provider)
    r.refused(0.0, pose, Refusal(RefusalReason.BUMP, "bumper pressed"), provider, room)
    assert asked == [(pose, r.config.backoff_m)] and r.phase is RoutePhase.BACKING_OFF
    assert r.step(0.5, (0.95, 0.0, 0.0), provider).v == -r.config.backoff_speed  # 5 cm: still backing
    r.step(1.0, (0.92, 0.0, 0.0), provider)  # 8 cm: done, re-planned
    assert r.phase is RoutePhase.FOLLOWING and r.replans == 1


def test_no_room_behind_means_no_back_off_a_replan_from_where_it_stands() -> None:
    provider = Provider([(4.0, 0.0)])
    r = route()
    pose = (1.0, 0.0, 0.0)
    r.step(0.0, pose, provider)
    r.refused(0.0, pose, Refusal(RefusalReason.BUMP, "bumper pressed"), provider, lambda p, limit: 0.0)
    assert r.phase is RoutePhase.FOLLOWING and r.replans == 1 and r.notes[-1].replanned
    assert r.step(0.1, pose, provider).v >= 0.0  # never backs into what is behind it


class Mapped(Provider):
    """A provider that also answers ``leg_meets_wall``: a known wall at ``wall`` (a disc of 0.2 m)."""

    def __init__(self, wall: Point | None, *answers: Sequence[Point] | None) -> None:
        super().__init__(*answers)
        self.wall = wall
        self.asked: list[tuple[Point, Point]] = []

    def leg_meets_wall(self, a: Point, b: Point, skip_m: float = 0.1, /) -> bool:
        self.asked.append((a, b))
        if self.wall is None:
            return False
        (ax, ay), (bx, by), (wx, wy) = a, b, self.wall
        length = math.hypot(bx - ax, by - ay)
        t = max(0.0, min(length, ((wx - ax) * (bx - ax) + (wy - ay) * (by - ay)) / length))
        return math.hypot(wx - (ax + t * (bx - ax) / length), wy - (ay + t * (by - ay) / length)) < 0.2


def test_a_newer_map_that_shows_the_leg_ahead_barred_replans_uncounted() -> None:
    """A leg laid into the unknown (a goal beyond the robot's map): the map the next planner holds
    has a wall on it, the route plans again from where it is, without using up ``max_replans``."""
    r = route()
    old = Mapped(None, [(4.0, 0.0)])
    r.step(0.0, (0.0, 0.0, 0.0), old)
    r.notes.clear()
    r.step(0.1, (0.5, 0.0, 0.0), old)  # the same map: nothing asked
    assert old.asked == []
    new = Mapped((2.5, 0.1), [(2.0, 1.0), (4.0, 0.0)])
    r.step(0.2, (0.5, 0.0, 0.0), new)
    assert new.asked and new.calls == [((0.5, 0.0), (4.0, 0.0), ())]
    assert r.replans == 0 and r.map_replans == 1 and r.phase is RoutePhase.FOLLOWING
    assert r.goto.waypoints == [(2.0, 1.0), (4.0, 0.0)]
    [note] = r.notes
    assert (note.replanned, note.reason) == (True, "wall_on_map")
    # The same wall on the next map too is not news: no further re-plan.
    again = Mapped((2.5, 0.1), [(2.0, 1.0), (4.0, 0.0)])
    r.step(0.3, (0.6, 0.1, 0.0), again)
    assert again.calls == [] and r.map_replans == 1


def test_a_newer_map_that_bars_the_goal_itself_waits_for_one_that_shows_it_clear() -> None:
    """Another robot stood on the goal as the robot drove up (CI's two-scout console test): the newer
    map shows the leg barred and has no path at all. Nothing has stopped the robot, and what bars the
    way may move on: it stands and waits, as for a first plan with none, then goes on the map that
    shows the goal clear, and reaches it. A second wait later on the same route gets its own
    ``no_path_wait_s``."""
    r, body = route(), Unicycle()
    old = Mapped(None, [(4.0, 0.0)])
    r.step(0.0, body.pose, old)
    t = drive(r, body, 0.0, old, 30.0, lambda: body.x < 3.0)
    r.notes.clear()
    barred = Mapped((4.0, 0.0), [])
    d = r.step(t, body.pose, barred)
    assert (d.v, d.omega) == (0.0, 0.0) and r.end is None and r.phase is RoutePhase.WAITING
    assert r.waiting_since == t and r.map_replans == 1 and r.replans == 0
    [note] = r.notes
    assert note.reason == "waiting" and "no path to (4.00, 0.00) on the newer map" in note.text
    assert r.step(t + 3.0, body.pose, barred).v == 0.0 and r.end is None  # the same map: still waiting
    clear = Mapped(None, [(4.0, 0.0)])
    r.step(t + 4.0, body.pose, clear)
    assert r.phase is RoutePhase.FOLLOWING and r.waiting_since is None
    # Barred again further on: a fresh wait, which runs out on a map that never clears.
    again = Mapped((4.0, 0.0), [])
    r.step(t + 5.0, body.pose, again)
    assert r.phase is RoutePhase.WAITING and r.waiting_since == t + 5.0 and r.end is None
    r.step(t + 5.0 + 6.0, body.pose, again)
    assert r.end is not None and not r.end.reached and r.end.reason == "no_path" and "waited 6 s" in r.end.text


def test_a_newer_map_with_no_path_fails_at_once_without_waiting() -> None:
    """``no_path_wait_s`` 0: as before waiting existed, the route fails as barred (and backs off)."""
    r = route(RouteConfig(no_path_wait_s=0.0))
    r.step(0.0, (0.0, 0.0, 0.0), Mapped(None, [(4.0, 0.0)]))
    r.step(0.1, (1.0, 0.0, 0.0), Mapped((3.0, 0.0), []))
    assert r.phase.failing or r.end is not None
    assert r._failure is not None and r._failure[1] == "blocked (wall_on_map) and no way around"


def test_a_wall_the_older_map_held_already_or_off_the_leg_changes_nothing() -> None:
    r = route()
    old = Mapped((2.5, 0.1), [(4.0, 0.0)])  # planned on a map that had it (as the planner's margin allows)
    r.step(0.0, (0.0, 0.0, 0.0), old)
    new = Mapped((2.5, 0.1), [(2.0, 1.0), (4.0, 0.0)])
    r.step(0.1, (0.5, 0.0, 0.0), new)
    assert new.calls == [] and r.map_replans == 0
    beside = Mapped((2.5, 1.5), [(2.0, 1.0), (4.0, 0.0)])  # a new wall, but not on the leg
    r.step(0.2, (0.5, 0.0, 0.0), beside)
    assert beside.calls == [] and r.map_replans == 0 and r.goto.waypoints == [(4.0, 0.0)]


def test_map_replans_are_bounded() -> None:
    """Maps that flip between two walls, each on the leg the other's path takes: every map is news
    to the path planned on the one before, and the re-plans stop at ``max_map_replans``."""
    r = route(RouteConfig(max_map_replans=2))
    straight, bent = [(4.0, 0.0)], [(2.0, 1.0), (4.0, 0.0)]
    r.step(0.0, (0.0, 0.0, 0.0), Mapped(None, straight))
    for k in range(4):
        r.step(0.1 * (k + 1), (0.5, 0.0, 0.0), Mapped((2.5, 0.0), bent))  # bars the straight leg
        r.step(0.1 * (k + 1) + 0.05, (0.5, 0.0, 0.0), Mapped((2.0, 1.0), straight))  # bars the bend
    assert r.map_replans == 2 and r.replans == 0 and r.end is None


def test_a_wall_drawn_while_an_earlier_leg_is_driven_is_news_when_its_leg_comes_within_reach() -> None:
    """Two legs ahead are checked against each newer map. A wall on the third leg, drawn while the
    first is driven, is on every map from then on; it is news to the path, which was planned on a map
    without it, when the third leg comes within reach (compared map to map it never was: the demo's
    apartment drove a leg laid through a hallway's unseen wall into that wall)."""
    r = route()
    path = [(1.0, 0.0), (2.0, 0.0), (3.0, 0.0), (4.0, 0.0)]
    r.step(0.0, (0.0, 0.0, 0.0), Mapped(None, path))
    drawn = Mapped((3.5, 0.0), [(3.0, 0.0), (3.5, 0.5), (4.0, 0.0)])
    r.step(0.1, (0.1, 0.0, 0.0), drawn)  # legs (0.1)-(1)-(2): clear of it
    assert r.map_replans == 0
    r.goto.index = 2  # on to the leg toward (3, 0): the next, (3)-(4), meets the wall
    later = Mapped((3.5, 0.0), [(3.0, 0.0), (3.5, 0.5), (4.0, 0.0)])
    r.step(0.2, (2.1, 0.0, 0.0), later)
    assert r.map_replans == 1 and r.notes[-1].reason == "wall_on_map"


# -- an order's trajectory ------------------------------------------------------------------------

BEND = ((0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (4.0, 0.0))
"""An edge's trajectory from (0, 0) to the destination (4, 0), round something the robot's own map
does not hold (planned on the fleet's merged map)."""


def along(trajectory: tuple[Point, ...] = BEND) -> Route:
    return Route(replace(DEST, trajectory=trajectory), GoToController(), RouteConfig())


def test_an_orders_trajectory_is_followed_instead_of_a_planned_path() -> None:
    r, body, t = along(), Unicycle(), 0.0
    own = Mapped(None, [(4.0, 0.0)])  # its own map: straight on (it knows nothing in the way)
    r.step(t, body.pose, own)
    assert own.calls == [] and r.phase is RoutePhase.FOLLOWING
    assert r.goto.waypoints == [(2.0, 0.0), (2.0, 2.0), (4.0, 0.0)]
    [note] = r.notes
    assert (note.replanned, note.reason, note.waypoints) == (False, "trajectory", 3)
    assert "the order's trajectory" in note.text
    corner = False
    while r.end is None and t < 60.0:
        d = r.step(t, body.pose, own)
        body.step(d.v, d.omega, 0.02)
        corner |= math.hypot(body.x - 2.0, body.y - 2.0) < 0.15
        t += 0.02
    assert r.end is not None and r.end.reached and corner  # it went round by (2, 2)
    assert own.calls == []


def test_the_trajectory_is_joined_where_the_robot_stands_on_it() -> None:
    """Resumed half-way along the second segment: on from the end of that segment."""
    r = along()
    r.step(0.0, (2.1, 1.0, 0.0), Mapped(None, [(4.0, 0.0)]))
    assert r.goto.waypoints == [(2.0, 2.0), (4.0, 0.0)]


def test_a_trajectory_the_robot_stands_off_or_its_map_bars_is_planned_afresh() -> None:
    r = along()
    own = Mapped(None, [(4.0, 0.0)])
    r.step(0.0, (0.0, -0.5, 0.0), own)  # 0.5 m off it (more than TRAJECTORY_JOIN_M)
    assert own.calls == [((0.0, -0.5), (4.0, 0.0), ())] and r.goto.waypoints == [(4.0, 0.0)]
    assert [n.reason for n in r.notes] == ["trajectory_refused", "planned"]
    assert "0.50 m off the order's trajectory" in r.notes[0].text
    r = along()
    walled = Mapped((2.0, 1.0), [(1.0, -1.0), (4.0, 0.0)])  # its own map has a wall on the trajectory
    r.step(0.0, (0.0, 0.0, 0.0), walled)
    assert walled.calls and r.goto.waypoints == [(1.0, -1.0), (4.0, 0.0)]
    assert "wall on the order's trajectory (2.00, 2.00), leg 2" in r.notes[0].text


def test_a_newer_map_that_bars_the_trajectory_ahead_replans() -> None:
    r = along()
    r.step(0.0, (0.0, 0.0, 0.0), Mapped(None, [(4.0, 0.0)]))
    newer = Mapped((2.0, 1.0), [(1.0, -1.0), (4.0, 0.0)])
    r.step(0.1, (1.0, 0.0, 0.0), newer)
    assert r.map_replans == 1 and newer.calls and r.goto.waypoints == [(1.0, -1.0), (4.0, 0.0)]


def test_every_leg_of_a_trajectory_is_checked_on_the_robots_own_map_however_short() -> None:
    """A wall across x = 5 m on the robot's own map (a real planner as its map sense): a trajectory
    through it in 9 cm steps, or one that stops short of the node and leaves the last leg through
    it, is not driven."""
    from fleetlink.agent.mapping.planner import PathPlanner

    cells = np.zeros((100, 200), dtype=np.int8)
    cells[:, 100] = 100
    planner = PathPlanner(cells, 0.05, (0.0, 0.0))
    dense = tuple((4.0 + 0.09 * k, 2.0) for k in range(23))  # 4.0 .. 5.98
    for trajectory, goal in ((dense, dense[-1]), (((4.0, 2.0), (4.5, 2.0)), (6.0, 2.0))):
        r = Route(replace(DEST, x=goal[0], y=goal[1], trajectory=trajectory), GoToController(), RouteConfig())
        r.step(0.0, (4.0, 2.0, 0.0), planner.route, planner)
        assert r.notes and r.notes[0].reason == "trajectory_refused", (trajectory[-1], [n.text for n in r.notes])
        assert "wall on the order's trajectory" in r.notes[0].text


def test_a_trajectory_that_comes_back_past_its_start_is_joined_at_its_start() -> None:
    loop = ((0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (0.2, 0.2), (0.0, 2.0))
    r = Route(replace(DEST, x=0.0, y=2.0, trajectory=loop), GoToController(), RouteConfig())
    r.step(0.0, (0.18, 0.19, 0.0), Mapped(None, [(0.0, 2.0)]))  # 2 cm from the return leg, 19 cm from the first
    assert r.goto.waypoints == [(2.0, 0.0), (2.0, 1.0), (0.2, 0.2), (0.0, 2.0)]
