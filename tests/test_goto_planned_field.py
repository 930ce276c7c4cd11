"""Lockstep field: a go-to on the office plan from one room to another through two doors, planned
by A* over the plan's rasterised occupancy (the map a robot would have), then home the same way.

The pilot drives the simulated board through real Control Bus bytes and steers on the board's own
dead reckoning (perfect wheels: this is about planning and control, not odometry drift); the
board's ultrasonic sees the real walls and door jambs. Truth comes from the field.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

from fleetlink.agent.mapping.planner import PathPlanner
from fleetlink.agent.pilot import ActionKind, EventKind, Pilot
from fleetlink.field.lockstep import FieldRun
from fleetlink.field.plans import load_plan
from fleetlink.field.scenario import LidarSettings, Noise, RobotSpec, Scenario
from fleetlink.site.lockstep import drive_by_session
from tests.test_goto_field import Agent

Pose = tuple[float, float, float]
HOME_AT = 45.0  # s: the go-to takes about 30 s


def office_planner() -> PathPlanner:
    grid = load_plan("office").to_grid(0.05)
    return PathPlanner(grid.grid, grid.resolution, grid.origin[:2])


def run(start: Pose, script: list[tuple[float, Callable[[Pilot, float], object]]], duration: float, pilot: Pilot):  # type: ignore[no-untyped-def]
    scenario = Scenario(
        name="planned",
        plan="office",
        seed=7,
        duration=duration,
        robots=(RobotSpec("r1", pose=start, drive="idle", lidar=False),),
        noise=Noise(wheel_scale_sd=0.0, gyro_bias_sd=0.0),
        lidar=LidarSettings(enabled=False),
    )
    agent = Agent(start, pilot, sorted(script, key=lambda s: s[0]))
    fr = FieldRun(scenario, open_loop=False)
    drive_by_session(fr, 0, agent.drive)
    return agent, fr, fr.run().truth["r1"]


def test_planned_go_to_from_room_1_to_room_7_through_the_doors_and_home() -> None:
    planner = office_planner()
    plan = load_plan("office")
    start: Pose = (9.0, 5.0, 0.0)  # in room-1 (south of the corridor)
    goal = (9.0, 14.0, math.pi)  # in room-7 (north), straight across: two walls in between
    assert plan.clearance(*start[:2]) > 1.0 and plan.clearance(*goal[:2]) > 1.0
    pilot = Pilot(home=start, path_provider=planner.route)
    script: list[tuple[float, Callable[[Pilot, float], object]]] = [
        (0.5, lambda p, t: p.order(t, "rooms", 0, *goal, "op")),
        (HOME_AT, lambda p, t: p.action(t, ActionKind.RETURN_HOME, "op")),
    ]
    agent, fr, truth = run(start, script, HOME_AT + 40.0, pilot)
    kinds = agent.kinds()
    assert kinds == [EventKind.PATH_PLANNED, EventKind.GOAL_REACHED] * 2, [(e.kind, e.text) for e in agent.events]
    assert all((e.waypoints or 0) >= 3 for e in agent.events if e.kind is EventKind.PATH_PLANNED)
    reached = agent.events[1].t
    at = next(row for row in truth if row[0] >= reached)
    assert math.hypot(at[1] - goal[0], at[2] - goal[1]) < 0.05
    _, x, y, _th, *_ = truth[-1]
    assert math.hypot(x - start[0], y - start[1]) < 0.05 and agent.events[3].order_id is None
    # Through the doors (x 7.0-7.9) at y = 8.5 and y = 11, never through a wall.
    board = fr.rigs[0].robot.board
    assert min(plan.clearance(x, y) for _, x, y, *_ in truth) > board.config.radius + 0.03
    for wall_y in (8.5, 11.0):
        crossing = [a[1] for a, b in itertools.pairwise(truth) if min(a[2], b[2]) < wall_y <= max(a[2], b[2])]
        assert len(crossing) == 2 and all(7.0 + 0.17 < x < 7.9 - 0.17 for x in crossing)  # there and back
