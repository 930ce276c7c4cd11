"""A goal past a wall the robot has not seen yet, as a mission: the demo's apartment, whole agents in
lockstep, placed by UWB. uvc-1, in the living room, is sent beside uvc-2 in the bedroom. Its onboard
map counts the unseen as free, so its first path runs through the hallway's north wall; the wall is
drawn while the robot drives the legs before it, and the route re-plans (``wall_on_map``) before it
gets there. Before the route judged each newer map against the map its path was planned on, it drove
into the wall and stood refused there, a ``guard_refusal`` every 0.12 s, till a lack of progress
re-planned 8 s on. Scored against the truth: it stands at the goal and was never refused or bumped.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from fleetlink.field.scenario import load_scenario
from fleetlink.site.lockstep import MissionRun

pytestmark = pytest.mark.slow

DEMO = Path(__file__).resolve().parents[1] / "field" / "scenarios" / "demo.toml"
GOAL = (3.53, 6.2)  # in the bedroom, 0.6 m in front of uvc-2


def test_a_path_laid_through_an_unseen_wall_is_replanned_before_the_robot_meets_it() -> None:
    with MissionRun(load_scenario(DEMO), record=False, map_worker=False) as run:
        for robot in run.robots:
            robot.wander = False
        board = run.field.rigs[0].robot.board.state
        assert run.field.rigs[0].spec.name == "uvc-1"
        op = run.operator
        sent: set[str] = set()

        def operate(t: float) -> None:
            if t >= 5.0 and "east" not in sent:  # a few steps east first: the map restarts in the UWB frame
                sent.add("east")
                op.goal("uvc-1", 4.65, 1.95, None, "east")
            if t >= 40.0 and "bedroom" not in sent:
                sent.add("bedroom")
                op.goal("uvc-1", *GOAL, None, "bedroom")

        run.field.controllers.append(operate)
        result = run.run(75.0)
    mine = [e for e in result.events if e.header.robot == "uvc-1"]
    said = [(e.kind, e.text) for e in mine]
    assert any(e.kind == "replanned" and "wall_on_map" in e.text for e in mine), said
    assert not [e for e in mine if e.kind in ("guard_refusal", "bump", "goal_failed")], said
    assert any(e.kind == "goal_reached" and "bedroom" in e.text for e in mine), said
    assert math.dist((board.x, board.y), GOAL) < 0.1, (board.x, board.y)
