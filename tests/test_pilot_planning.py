"""The pilot on planned paths: around a mapped wall, and re-planning around what the map lacks.

Pure: a constructed occupancy grid, the A* planner over it as the path provider, the kinematic
``Unicycle`` (motor lag) and a simulated front ultrasonic (a 40-degree cone of rays from the body's
front edge) that sees the walls *and* boxes the map does not know about.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from fleetlink.agent.guard import GuardInputs
from fleetlink.agent.mapping.planner import PathPlanner
from fleetlink.agent.pilot import ActionKind, EventKind, OperatingMode, Pilot, PilotEvent
from tests.test_motion import Unicycle

RES = 0.05
RADIUS = 0.17  # the robot's body (and where the ultrasonic sits ahead of the centre)
Box = tuple[float, float, float, float]  # xmin, ymin, xmax, ymax


def room(wall: bool) -> tuple[np.ndarray, list[Box]]:
    """8 m x 5 m, walled; with ``wall``, a wall across x = 4 m from y = 0 up to 3.5 m."""
    g = np.zeros((100, 160), dtype=np.int8)
    g[0, :] = g[-1, :] = 100
    g[:, 0] = g[:, -1] = 100
    if wall:
        g[:70, 80] = 100
    boxes = [(0.0, 0.0, 8.0, RES), (0.0, 5.0 - RES, 8.0, 5.0), (0.0, 0.0, RES, 5.0), (8.0 - RES, 0.0, 8.0, 5.0)]
    if wall:
        boxes.append((80 * RES, 0.0, 81 * RES, 70 * RES))
    return g, boxes


def _ray_box(ox: float, oy: float, dx: float, dy: float, b: Box) -> float:
    """Distance along the ray to the box (slab method), inf when it misses."""
    t0, t1 = 0.0, math.inf
    for o, d, lo, hi in ((ox, dx, b[0], b[2]), (oy, dy, b[1], b[3])):
        if abs(d) < 1e-12:
            if o < lo or o > hi:
                return math.inf
            continue
        a, c = (lo - o) / d, (hi - o) / d
        t0, t1 = max(t0, min(a, c)), min(t1, max(a, c))
    return t0 if t0 <= t1 else math.inf


def ultrasonic(pose: tuple[float, float, float], boxes: list[Box]) -> GuardInputs:
    x, y, th = pose
    sx, sy = x + RADIUS * math.cos(th), y + RADIUS * math.sin(th)
    near = [b for b in boxes if abs((b[0] + b[2]) / 2 - sx) < 1.8 and abs((b[1] + b[3]) / 2 - sy) < 1.8]
    best = math.inf
    for k in range(9):
        a = th + math.radians(-20 + 5 * k)
        for b in near:
            best = min(best, _ray_box(sx, sy, math.cos(a), math.sin(a), b))
    return GuardInputs(ultrasonic_m=None if best > 1.5 else max(0.25, best))


def body_clearance(pose: tuple[float, float, float], boxes: list[Box]) -> float:
    x, y, _ = pose
    return min(math.hypot(max(b[0] - x, 0, x - b[2]), max(b[1] - y, 0, y - b[3])) for b in boxes) - RADIUS


def run(
    pilot: Pilot, body: Unicycle, boxes: list[Box], t0: float, seconds: float, dt: float = 0.02
) -> tuple[float, list[PilotEvent], list[tuple[float, float, float]]]:
    events: list[PilotEvent] = []
    poses = []
    t = t0
    while t < t0 + seconds:
        out = pilot.tick(t, body.pose, ultrasonic(body.pose, boxes))
        events.extend(out.events)
        poses.append(body.pose)
        body.step(out.v, out.omega, dt)
        t += dt
        if pilot.mode is OperatingMode.IDLE:
            break
    return t, events, poses


def test_go_to_and_return_home_go_around_a_mapped_wall_and_keep_out_of_the_inflated_cells() -> None:
    g, walls = room(wall=True)
    planner = PathPlanner(g, RES)
    start, goal = (1.0, 1.0, 0.0), (7.0, 1.0, math.pi / 2)
    pilot = Pilot(home=start, path_provider=planner.route)
    body = Unicycle(*start)
    pilot.order(0.0, "o1", 0, *goal, "op")
    t, events, poses = run(pilot, body, walls, 0.0, 60.0)
    kinds = [e.kind for e in events]
    assert kinds[0] is EventKind.PATH_PLANNED and kinds[-1] is EventKind.GOAL_REACHED
    assert EventKind.GUARD_REFUSAL not in kinds and EventKind.REPLANNED not in kinds
    assert events[0].waypoints is not None and events[0].waypoints >= 2  # around the wall's end, not through it
    assert math.hypot(body.x - goal[0], body.y - goal[1]) < 0.02
    assert abs(math.remainder(body.th - goal[2], 2 * math.pi)) < math.radians(2)
    # The route went round the wall's end (y > 3.5 m at x = 4 m) and kept the inflation's margin.
    assert max(y for x, y, _ in poses if abs(x - 4.0) < 0.1) > 3.5 + planner.config.inflation - 0.05
    inflated = 0
    for p in poses:
        r, c = planner.cell(p[:2])
        inflated += not planner.free[r, c]
    assert inflated == 0
    assert min(body_clearance(p, walls) for p in poses) > planner.config.margin
    # Return home plans the same way back.
    pilot.action(t, ActionKind.RETURN_HOME, "op")
    _, events, poses = run(pilot, body, walls, t, 60.0)
    assert events[0].kind is EventKind.PATH_PLANNED
    assert events[-1].kind is EventKind.GOAL_REACHED and events[-1].order_id is None
    assert math.hypot(body.x - start[0], body.y - start[1]) < 0.02
    assert max(y for x, y, _ in poses if abs(x - 4.0) < 0.1) > 3.5
    assert min(body_clearance(p, walls) for p in poses) > planner.config.margin


def test_an_unmapped_box_on_the_path_is_planned_around() -> None:
    g, walls = room(wall=False)
    box = (3.85, 2.35, 4.15, 2.65)  # 30 cm, right on the straight line; the map does not have it
    calls: list[tuple[tuple[float, float], ...]] = []
    planner = PathPlanner(g, RES)

    def provider(
        s: tuple[float, float], gl: tuple[float, float], blocked: tuple[tuple[float, float], ...] = ()
    ) -> list[tuple[float, float]]:
        calls.append(tuple(blocked))
        return planner.route(s, gl, blocked)

    pilot = Pilot(path_provider=provider)
    body = Unicycle(1.0, 2.5, 0.0)
    pilot.order(0.0, "o1", 0, 7.0, 2.5, None, "op")
    _, events, poses = run(pilot, body, [*walls, box], 0.0, 90.0)
    kinds = [e.kind for e in events]
    assert kinds[0] is EventKind.PATH_PLANNED and events[0].waypoints == 1  # straight: the map is clear
    assert EventKind.GUARD_REFUSAL in kinds and EventKind.REPLANNED in kinds
    assert kinds.count(EventKind.GUARD_REFUSAL) == len([e for e in events if e.kind is EventKind.REPLANNED])
    assert kinds[-1] is EventKind.GOAL_REACHED
    assert math.hypot(body.x - 7.0, body.y - 2.5) < 0.02
    # The provider was told where: the first re-plan carries a point on the box.
    marked = next(c for c in calls if c)
    assert abs(marked[0][0] - 4.0) < 0.15 and abs(marked[0][1] - 2.5) < 0.05
    replanned = [e for e in events if e.kind is EventKind.REPLANNED]
    assert all(e.waypoints is not None and e.waypoints >= 2 for e in replanned)
    assert len(replanned) <= pilot.config.max_replans
    assert min(body_clearance(p, [box]) for p in poses) > 0.1  # never touched it


def test_an_unmapped_wall_across_the_room_fails_cleanly_after_the_bound() -> None:
    g, walls = room(wall=False)
    barrier = (3.9, 0.0, 4.1, 5.0)  # closes the room off; the map does not have it
    pilot = Pilot(path_provider=PathPlanner(g, RES).route)
    body = Unicycle(1.0, 2.5, 0.0)
    pilot.order(0.0, "o1", 0, 7.0, 2.5, None, "op")
    _, events, poses = run(pilot, body, [*walls, barrier], 0.0, 200.0)
    kinds = [e.kind for e in events]
    assert kinds.count(EventKind.REPLANNED) == pilot.config.max_replans
    assert kinds[-1] is EventKind.GOAL_FAILED and events[-1].reason == "blocked"
    assert pilot.mode is OperatingMode.IDLE
    assert min(body_clearance(p, [barrier]) for p in poses) > 0.1
    assert max(x for x, _, _ in poses) < 3.9


def door_room() -> tuple[np.ndarray, list[Box], tuple[float, float]]:
    """8 m x 5 m, walled; a wall across x = 4 m with a 0.8 m door at y 3.0-3.8 (jambs at its ends)."""
    g, boxes = room(wall=False)
    g[:60, 80] = 100
    g[76:, 80] = 100
    boxes += [(4.0, 0.0, 4.05, 3.0), (4.0, 3.8, 4.05, 5.0)]
    return g, boxes, (4.025, 3.4)


def test_the_path_through_a_doorway_keeps_to_its_middle_and_the_guard_never_objects() -> None:
    g, walls, (dx, dy) = door_room()
    planner = PathPlanner(g, RES)
    start, goal = (1.0, 4.5, 0.0), (7.0, 1.0, 0.0)  # the straight line passes south of the door
    path = planner.route(start[:2], goal[:2])
    assert len(path) >= 2
    # Where the planned path crosses the wall it is in the door's middle: >= 0.3 m from both frames
    # (half the door is 0.4 m), not skimming the south jamb at the inflation's 0.22 m as a plain
    # line-of-sight shortcut over the inflated grid does (it crossed at y = 3.24).
    pts = [start[:2], *path]
    crossings = [
        a[1] + (b[1] - a[1]) * (dx - a[0]) / (b[0] - a[0])
        for a, b in itertools.pairwise(pts)
        if (a[0] - dx) * (b[0] - dx) < 0
    ]
    assert len(crossings) == 1 and abs(crossings[0] - dy) <= 0.1
    # Every leg is one the guard accepts on the map's own walls (the cone sees nothing nearer than
    # the leg plus the stop distance), and the robot drives it without a refusal.
    assert all(planner.leg_ok(a, b) for a, b in itertools.pairwise(pts))
    pilot = Pilot(path_provider=planner.route)
    body = Unicycle(*start)
    pilot.order(0.0, "o1", 0, *goal, "op")
    _, events, poses = run(pilot, body, walls, 0.0, 60.0)
    kinds = [e.kind for e in events]
    assert kinds == [EventKind.PATH_PLANNED, EventKind.GOAL_REACHED], [(e.kind, e.text) for e in events]
    in_door = [p for p in poses if abs(p[0] - dx) < 0.05]
    assert in_door and all(min(p[1] - 3.0, 3.8 - p[1]) >= 0.3 for p in in_door)


def test_a_leg_whose_cone_sees_the_door_frame_is_cut_short_by_the_pilot_not_refused() -> None:
    # A path provider that knows nothing of the sensor: straight at the door's middle from 1.4 m.
    # At the start the cone's edge sees the wall beside the door nearer than the leg plus the stop
    # distance; the pilot drives only as far as that echo leaves clear, and from there the cone
    # looks through the doorway.
    _, walls, (dx, dy) = door_room()
    start, goal = (2.6, dy, 0.0), (7.0, dy, 0.0)
    seen = ultrasonic(start, walls).ultrasonic_m
    leg = dx - start[0]
    assert seen is not None and seen < leg + Pilot().config.guard.stop_distance_m  # would be refused
    pilot = Pilot(path_provider=lambda s, gl, blocked=(): [(dx, dy), gl])
    body = Unicycle(*start)
    pilot.order(0.0, "o1", 0, *goal, "op")
    _, events, poses = run(pilot, body, walls, 0.0, 60.0)
    kinds = [e.kind for e in events]
    assert kinds == [EventKind.PATH_PLANNED, EventKind.GOAL_REACHED], [(e.kind, e.text) for e in events]
    assert min(body_clearance(p, walls) for p in poses) > 0.15


def test_an_echo_off_a_mapped_door_frame_does_not_close_the_doorway() -> None:
    g, _, (dx, dy) = door_room()
    planner = PathPlanner(g, RES)
    start, goal = (1.0, 1.0), (7.0, 1.0)
    frame = (dx + 0.05, 3.0 - 0.05)  # where the pilot marks an echo off the south jamb
    assert planner.unknown_marks([frame]) == []
    assert planner.route(start, goal, blocked=[frame]) == planner.route(start, goal)
    # Something the map does not have, standing in the doorway, does close it.
    assert planner.unknown_marks([(dx, dy)]) == [(dx, dy)]
    assert planner.route(start, goal, blocked=[(dx, dy)]) == []


def test_a_failed_go_to_backs_off_so_the_next_one_does_not_start_stuck() -> None:
    # The cascade: a go-to barred by something the map lacks fails next to it; the next goal (back
    # the way it came) must not start with the robot facing that obstacle inside the stop distance.
    g, walls = room(wall=False)
    barrier = (3.9, 0.0, 4.1, 5.0)
    pilot = Pilot(path_provider=PathPlanner(g, RES).route)
    body = Unicycle(1.0, 2.5, 0.0)
    pilot.order(0.0, "o1", 0, 7.0, 2.5, None, "op")
    t, events, _ = run(pilot, body, [*walls, barrier], 0.0, 200.0)
    failed = events[-1]
    assert failed.kind is EventKind.GOAL_FAILED and failed.reason == "blocked" and "backed off" in failed.text
    stop = pilot.config.guard.stop_distance_m
    seen = ultrasonic(body.pose, [*walls, barrier]).ultrasonic_m
    assert seen is None or seen > stop + 0.1
    assert body.x < 3.9 - RADIUS - stop  # backed off along the way it came
    pilot.order(t, "o2", 0, 1.0, 4.0, None, "op")
    _, events, _ = run(pilot, body, [*walls, barrier], t, 60.0)
    kinds = [e.kind for e in events]
    assert kinds == [EventKind.PATH_PLANNED, EventKind.GOAL_REACHED], [(e.kind, e.text) for e in events]
    assert math.hypot(body.x - 1.0, body.y - 4.0) < 0.02


def test_the_agent_core_routes_over_the_onboard_map_and_drives_straight_while_it_is_empty() -> None:
    from fleetlink.agent.core import AgentCore
    from fleetlink.agent.mapping import OnboardMapper
    from fleetlink.shared.clock import SimClock

    mapper = OnboardMapper()
    core = AgentCore("r1", SimClock(), Pilot())
    core.use_map(mapper.plan)
    pilot = core.pilot
    pilot.order(0.0, "o1", 0, 1.0, 0.0, None, "op")
    out = pilot.tick(0.0, (0.0, 0.0, 0.0), GuardInputs())
    assert [e.kind for e in out.events] == []  # no map yet: straight, exactly as without a provider
    assert pilot.goto.waypoints == [(1.0, 0.0)]
    # A round room of 2.5 m radius seen by the lidar: now the go-to is planned over that map.
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    for k in range(5):
        mapper.add_scan(0.1 * k, np.full(360, 2.5), angles, (0.0, 0.0, 0.0))
    pilot.order(1.0, "o2", 0, 1.0, 0.5, None, "op")
    out = pilot.tick(1.0, (0.0, 0.0, 0.0), GuardInputs())
    assert [e.kind for e in out.events] == [EventKind.GOAL_CANCELLED, EventKind.PATH_PLANNED]
    assert pilot.goto.waypoints[-1] == (1.0, 0.5)
    core.use_map(None)
    assert pilot.path_provider is None
