"""Scenario events: the operator-command and link kinds parse into typed events, and EventRunner
executes world events itself while handing commands and network links to ``on_command``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from fleetlink.field.events import EventRunner, is_handed_over
from fleetlink.field.plans import load_plan
from fleetlink.field.scenario import (
    COMMAND_KINDS,
    EVENT_KINDS,
    TELEOP_PERIOD_S,
    ActionOrder,
    DoorClose,
    Event,
    GoalOrder,
    LinkCut,
    LinkState,
    MarkPlaced,
    PressHome,
    ScenarioError,
    TeleopBurst,
    WheelSlip,
    parse_scenario,
)
from fleetlink.shared.messages import ActionType

ROBOTS = [{"name": "r1", "start": "dock"}, {"name": "r2", "start": "dock", "drive": "agent"}]


def events(*tables: dict[str, Any]) -> tuple[Event, ...]:
    return parse_scenario({"plan": "apartment", "robots": ROBOTS, "events": list(tables)}).events


def test_operator_command_and_link_events_parse_into_typed_events() -> None:
    got = events(
        {"at_s": 1.0, "kind": "teleop", "robot": "r1", "v": 0.2, "omega": -0.5, "duration_s": 1.5},
        {"at_s": 2.0, "kind": "goal", "robot": "r2", "x": 3.0, "y": 4.0},
        {"at_s": 2.5, "kind": "goal", "robot": "r2", "x": 3.0, "y": 4.0, "theta_deg": 90.0},
        {"at_s": 3.0, "kind": "action", "robot": "r1", "action": "estop_release"},
        {"at_s": 4.0, "kind": "mark", "x": 1.0, "y": 2.0},
        {"at_s": 4.5, "kind": "mark", "x": 1.0, "y": 2.0, "mark_kind": "hazard", "label": "gas", "robot": "r1"},
        {"at_s": 5.0, "kind": "link", "robot": "r2", "link": "mqtt", "state": "cut"},
        {"at_s": 6.0, "kind": "link", "robot": "r2", "link": "board", "state": "restore"},
        {"at_s": 0.5, "kind": "link_cut", "robot": "r1"},
    )
    assert got == (
        LinkCut(0.5, "r1", 3.0),
        TeleopBurst(1.0, "r1", 1.5, v=0.2, omega=-0.5),
        GoalOrder(2.0, "r2", 3.0, 4.0, None),
        GoalOrder(2.5, "r2", 3.0, 4.0, math.pi / 2),
        ActionOrder(3.0, "r1", "estop_release"),
        MarkPlaced(4.0, 1.0, 2.0, "casualty", ""),
        MarkPlaced(4.5, 1.0, 2.0, "hazard", "gas", "r1"),
        LinkState(5.0, "r2", "mqtt", "cut"),
        LinkState(6.0, "r2", "board", "restore"),
    )
    assert got[4].action_type is ActionType.ESTOP_RELEASE  # type: ignore[union-attr]
    assert [e.kind for e in got][1:5] == ["teleop", "goal", "goal", "action"]
    assert set(COMMAND_KINDS) < set(EVENT_KINDS)
    assert {"door_close", "door_open", "obstacle", "link_cut", "wheel_slip", "press_home", "link"} < set(EVENT_KINDS)
    assert "operator drives r1 at 0.2 m/s, -0.5 rad/s for 1.5 s" in got[1].describe()
    assert parse_scenario({"plan": "apartment", "robots": ROBOTS}).robots[1].drive == "agent"


@pytest.mark.parametrize(
    ("event", "message"),
    [
        ({"kind": "teleop", "robot": "r1", "v": 0.2}, "events[0].duration_s: missing required key"),
        ({"kind": "teleop", "robot": "r1", "v": 9.0, "duration_s": 1}, "events[0].v: must be <= 5.0, got 9.0"),
        ({"kind": "teleop", "robot": "r1", "speed": 1, "duration_s": 1}, "events[0].speed: unknown key"),
        ({"kind": "goal", "robot": "r1", "x": 1}, "events[0].y: missing required key"),
        ({"kind": "goal", "robot": "r1", "x": 1, "y": 1, "theta": 1}, "events[0].theta: unknown key (did you mean theta_deg?)"),
        ({"kind": "goal", "robot": "r9", "x": 1, "y": 1}, "events[0].robot: no robot named 'r9' in this scenario"),
        ({"kind": "action", "robot": "r1", "action": "halt"}, "events[0].action: expected one of stop, pause, resume,"),
        ({"kind": "action", "robot": "r1", "action": "estop_releas"}, "got 'estop_releas' (did you mean estop_release?)"),
        ({"kind": "mark", "x": 1, "y": 1, "label": "x" * 500}, "events[0].label: at most"),
        ({"kind": "mark", "x": 1, "y": 1, "kind_": "hazard"}, "events[0].kind_: unknown key"),
        ({"kind": "link", "robot": "r1", "link": "wifi", "state": "cut"}, "events[0].link: expected one of zenoh, mqtt, board, lidar"),
        ({"kind": "link", "robot": "r1", "link": "zenoh", "state": "down"}, "events[0].state: expected one of cut, restore"),
        ({"kind": "telop", "robot": "r1"}, "events[0].kind: expected one of door_close, door_open, obstacle,"),
    ],
)  # fmt: skip
def test_bad_command_events_name_the_key(event: dict[str, Any], message: str) -> None:
    with pytest.raises(ScenarioError) as err:
        parse_scenario({"plan": "apartment", "robots": ROBOTS, "events": [{"at_s": 1.0, **event}]}, source="s.toml")
    assert str(err.value).startswith("s.toml: ")
    assert message in str(err.value)


# -- EventRunner -----------------------------------------------------------------------------------


@dataclass
class FakeBoard:
    slip: list[float] = field(default_factory=lambda: [0.0, 0.0])
    homes: int = 0

    def press_home(self) -> None:
        self.homes += 1


@dataclass
class FakeRobot:
    board: FakeBoard = field(default_factory=FakeBoard)


@dataclass
class FakeWorld:
    """What EventRunner uses of a World: robots by name and the blocking segments."""

    by_name: dict[str, FakeRobot] = field(default_factory=lambda: {"r1": FakeRobot(), "r2": FakeRobot()})
    segments: list[int] = field(default_factory=list)

    def set_segments(self, segs: np.ndarray) -> None:
        self.segments.append(len(segs))


def run(evs: tuple[Event, ...], until: float, step: float = 0.01, with_handler: bool = True) -> tuple[Any, ...]:
    world = FakeWorld()
    cuts: list[tuple[float, str, bool]] = []
    handed: list[tuple[float, Event]] = []
    now = [0.0]
    runner = EventRunner(
        evs,
        load_plan("apartment"),
        world,  # type: ignore[arg-type]
        lambda robot, cut: cuts.append((now[0], robot, cut)),
        on_command=(lambda ev, t: handed.append((t, ev))) if with_handler else None,
    )
    for k in range(round(until / step) + 1):
        now[0] = k * step
        runner.advance(now[0])
    return world, cuts, handed, runner.log


def test_world_events_run_in_the_field_and_commands_go_to_the_handler() -> None:
    plan = load_plan("apartment")
    door = next(iter(plan.doors))
    evs = events(
        {"at_s": 0.1, "kind": "goal", "robot": "r2", "x": 3.0, "y": 4.0},
        {"at_s": 0.2, "kind": "action", "robot": "r1", "action": "stop"},
        {"at_s": 0.3, "kind": "mark", "x": 1.0, "y": 2.0},
        {"at_s": 0.4, "kind": "link", "robot": "r1", "link": "zenoh", "state": "cut"},
        {"at_s": 0.5, "kind": "link", "robot": "r1", "link": "lidar", "state": "cut"},
        {"at_s": 0.6, "kind": "link", "robot": "r2", "link": "board", "state": "cut"},
        {"at_s": 0.8, "kind": "link", "robot": "r2", "link": "board", "state": "restore"},
        {"at_s": 1.0, "kind": "link_cut", "robot": "r1", "duration_s": 0.5},
        {"at_s": 1.1, "kind": "wheel_slip", "robot": "r2", "wheel": "right", "fraction": 0.4, "duration_s": 0.2},
        {"at_s": 1.2, "kind": "press_home", "robot": "r1"},
        {"at_s": 1.3, "kind": "door_close", "door": door},
    )
    world, cuts, handed, log = run(evs, until=2.0)
    assert [type(ev).__name__ for _, ev in handed] == [
        "GoalOrder",
        "ActionOrder",
        "MarkPlaced",
        "LinkState",
        "LinkState",
    ]
    assert [t for t, _ in handed] == pytest.approx([0.1, 0.2, 0.3, 0.4, 0.5])
    assert all(is_handed_over(ev) for _, ev in handed)
    assert cuts == [(pytest.approx(0.6), "r2", True), (pytest.approx(0.8), "r2", False),
                    (pytest.approx(1.0), "r1", True), (pytest.approx(1.5), "r1", False)]  # fmt: skip
    assert world.by_name["r2"].board.slip == [0.0, 0.0]  # slipped, then gripped again
    assert world.by_name["r1"].board.homes == 1
    assert len(world.segments) == 1  # the door closed: the world's walls were rebuilt
    assert "t=0.4 s: zenoh link of r1 cut" in log and "t=1.500 s: board link of r1 restored" in log
    assert "t=1.300 s: right wheel of r2 grips again" in log


def test_a_slip_holds_for_its_duration() -> None:
    world = FakeWorld()
    runner = EventRunner((WheelSlip(0.0, "r2", 1.0, "right", 0.4),), load_plan("apartment"), world, lambda r, c: None)  # type: ignore[arg-type]
    runner.advance(0.5)
    assert world.by_name["r2"].board.slip == [0.0, 0.4]
    runner.advance(1.0)
    assert world.by_name["r2"].board.slip == [0.0, 0.0]


def test_a_teleop_burst_is_handed_over_once_a_period_for_its_duration() -> None:
    burst = TeleopBurst(2.0, "r1", 1.0, v=0.3)
    _, _, handed, log = run((burst,), until=5.0)
    assert [t for t, _ in handed] == pytest.approx([2.0, 2.0 + TELEOP_PERIOD_S, 2.5, 2.75])
    assert all(ev is burst for _, ev in handed)
    assert sum("operator drives r1" in line for line in log) == 1  # logged once, not per repeat
    _, _, short, _ = run((TeleopBurst(0.0, "r1", 0.0),), until=1.0)
    assert len(short) == 1  # a zero-length burst is still one Teleop


def test_without_a_handler_a_command_event_is_refused_up_front() -> None:
    with pytest.raises(ValueError, match="operator sends stop to r1: this run has no operator side"):
        run((ActionOrder(1.0, "r1", "stop"),), until=0.0, with_handler=False)
    with pytest.raises(ValueError, match="mqtt link of r1 cut: this run has no operator side"):
        run((LinkState(1.0, "r1", "mqtt", "cut"),), until=0.0, with_handler=False)
    _, cuts, _, _ = run((LinkState(0.0, "r1", "board", "cut"), PressHome(0.0, "r2")), until=0.0, with_handler=False)
    assert cuts == [(0.0, "r1", True)]  # the board link needs no operator side


def test_unknown_doors_and_robots_are_refused() -> None:
    with pytest.raises(ValueError, match="has no door 'garage'"):
        run((DoorClose(1.0, "garage"),), until=0.0)
    with pytest.raises(ValueError, match="no robot 'r9' in the world"):
        run((GoalOrder(1.0, "r9", 0.0, 0.0),), until=0.0)
