"""Two robots driven by hand toward each other on lanes 0.33 m apart, as a mission: whole agents in
lockstep in the exhibition hall, placed by UWB. Their bodies (0.17 m each) would touch, but neither
front ultrasonic ever sees the other (its 40-degree cone is 0.15 m wide at the 0.4 m stop distance,
and the other body starts 0.16 m to the side): only the guard's robot rule (agent/guard.py, the
peers' poses from agent/peers.py) keeps them apart. Scored against the truth: they stop short of
each other, say why (``robot_ahead``), and bump nothing.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from fleetlink.field.scenario import load_scenario
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.site.lockstep import MissionRun

pytestmark = pytest.mark.slow

OFFSET_M = 0.33  # the lanes' distance apart, centre to centre: under two radii (0.34 m)
SCENARIO = f"""
name = "robots-meeting"
description = "Two robots driven toward each other on lanes {OFFSET_M} m apart in the hall."
plan = "expo"
seed = 5
duration_s = 30.0

[lidar]
enabled = false

[noise]  # wheels alike: with the keys held straight ahead each drives its lane, not a curve
wheel_scale_sd = 0.0
gyro_bias_sd = 0.0

[[robots]]
name = "r1"
pose = [17.0, 6.5, 0.0]

[[robots]]
name = "r2"
pose = [23.0, {6.5 + OFFSET_M}, 180.0]
"""


def test_two_robots_driven_at_each_other_stop_short_where_the_ultrasonic_sees_neither(tmp_path: Path) -> None:
    path = tmp_path / "meeting.toml"
    path.write_text(SCENARIO)
    apart: list[float] = []
    with MissionRun(load_scenario(path), record=False, map_worker=False) as run:
        for robot in run.robots:
            robot.wander = False  # they stand until the keys are held
        boards = [rig.robot.board.state for rig in run.field.rigs]
        op = run.operator
        held = [0.0]

        def operate(t: float) -> None:
            apart.append(math.dist((boards[0].x, boards[0].y), (boards[1].x, boards[1].y)))
            if t >= 5.0 and t - held[0] >= 0.25:  # both keys held from 5 s on, a Teleop every 0.25 s
                held[0] = t
                op.teleop("r1", 0.5, 0.0)
                op.teleop("r2", 0.5, 0.0)

        run.field.controllers.append(operate)
        result = run.run(20.0)
    refusals = [e for e in result.events if e.kind == "guard_refusal"]
    bumps = [e for e in result.events if e.kind == "bump"]
    assert not bumps, [(e.header.robot, e.text) for e in bumps]
    # They drove (each most of the way) and never touched.
    assert apart[0] - min(apart) > 4.0, min(apart)
    assert min(apart) > 2 * BODY_RADIUS_M, min(apart)
    said = [(e.header.robot, {kv.key: kv.value for kv in e.data}.get("reason"), e.text) for e in refusals]
    assert {robot for robot, reason, _ in said if reason == "robot_ahead"} == {"r1", "r2"}, said
    assert all(reason == "robot_ahead" for _, reason, _ in said), said  # the ultrasonic saw neither


APARTMENT = f"""
name = "robot-driven-off-at-once"
description = "uvc-1 driven at uvc-2 in the living room as soon as UWB has placed it, lanes {OFFSET_M} m apart."
plan = "apartment"
seed = 3
duration_s = 20.0

[noise]
wheel_scale_sd = 0.0
gyro_bias_sd = 0.0

[[robots]]
name = "uvc-1"
pose = [2.2, 2.0, 0.0]

[[robots]]
name = "uvc-2"
pose = [3.5, {2.0 + OFFSET_M}, 180.0]
"""


def test_a_robot_driven_off_as_soon_as_it_is_placed_stops_short_of_a_robot_beside_its_way(tmp_path: Path) -> None:
    """The same lanes in the apartment's living room (lidar on), one robot standing, the other driven
    at 0.3 m/s from 2 s on, as an operator does the moment the console shows it placed. It knows its
    heading only from driving (3-4 degrees) and its position to 2-3 cm: with the fixed 2 cm margin it
    believed the way clear until the bodies touched (the console's test found it: a bump). With the
    margin grown by both poses' uncertainty (``PeerConfig.margin_sds``) it stops short."""
    path = tmp_path / "apartment.toml"
    path.write_text(APARTMENT)
    apart: list[float] = []
    with MissionRun(load_scenario(path), record=False, map_worker=False) as run:
        for robot in run.robots:
            robot.wander = False
        boards = [rig.robot.board.state for rig in run.field.rigs]
        op = run.operator
        held = [0.0]

        def operate(t: float) -> None:
            apart.append(math.dist((boards[0].x, boards[0].y), (boards[1].x, boards[1].y)))
            if t >= 2.0 and t - held[0] >= 0.05:  # the key held from 2 s on, as the console repeats it
                held[0] = t
                op.teleop("uvc-1", 0.3, 0.0)

        run.field.controllers.append(operate)
        result = run.run(12.0)
    bumps = [e for e in result.events if e.kind == "bump"]
    assert not bumps, [(e.header.robot, e.text) for e in bumps]
    assert apart[0] - min(apart) > 0.7, min(apart)  # it drove most of the way
    assert min(apart) > 2 * BODY_RADIUS_M + 0.03, min(apart)
    said = {
        (e.header.robot, {kv.key: kv.value for kv in e.data}.get("reason"))
        for e in result.events
        if e.kind == "guard_refusal"
    }
    assert ("uvc-1", "robot_ahead") in said, said
