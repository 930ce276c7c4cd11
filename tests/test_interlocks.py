"""The UV lamp's interlocks (agent/interlocks.py) and the payload commands (issue 16): one test per
rule, so that each fails if its rule is removed; then the agent core refusing a lamp-on and
switching a lit lamp off, the atomiser and fan levels, and bad payload commands."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest

from fleetlink.agent.core import AgentCore, BoardView, Output
from fleetlink.agent.interlocks import LampSituation, PeopleZone, lamp_interlock, zone_reached
from fleetlink.agent.pilot import Pilot
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import (
    Ack,
    AckResult,
    Action,
    ActionType,
    Event,
    InstantActions,
    KeyValue,
    LeaseRequest,
    LinkName,
)

ROOM = PeopleZone("ward-3", ((10.0, 0.0), (14.0, 0.0), (14.0, 4.0), (10.0, 4.0)))
OK = LampSituation(position=(0.0, 0.0), lamp_radius_m=3.0)

# -- the rules, one by one ------------------------------------------------------------------------


def test_nothing_holds_in_a_clear_situation() -> None:
    assert lamp_interlock(OK) is None
    assert lamp_interlock(dataclasses.replace(OK, zones=(ROOM,))) is None  # 10 m away from the ward


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"estop": True}, "e-stop latched"),
        ({"comms_lost": True}, "out of contact"),
        ({"bumped": True}, "bumper"),
        ({"cliff": True}, "cliff"),
        ({"lease_held": False}, "lease"),
        ({"board_connected": False}, "board is not connected"),
        ({"has_lamp": False}, "no UV lamp"),
        ({"zones": (ROOM,), "position": (8.0, 2.0)}, "people-present zone 'ward-3'"),  # 2 m from its edge
        ({"zones": (ROOM,), "position": (12.0, 2.0)}, "people-present zone 'ward-3'"),  # inside it
        ({"zones": (ROOM,), "position": None}, "not localised"),
    ],
)
def test_each_rule_keeps_the_lamp_off_and_says_why(change: dict[str, Any], reason: str) -> None:
    why = lamp_interlock(dataclasses.replace(OK, **change))
    assert why is not None and reason in why


def test_a_zone_is_reached_by_the_lamps_radius_not_only_by_the_robot() -> None:
    assert zone_reached((6.9, 2.0), 3.0, (ROOM,)) is None  # 3.1 m from the ward's edge
    assert zone_reached((7.1, 2.0), 3.0, (ROOM,)) == "ward-3"
    assert zone_reached((12.0, 6.5), 3.0, (ROOM,)) == "ward-3"  # 2.5 m north of it


# -- the agent core: commands and the lit lamp --------------------------------------------------------

BOARD = BoardView(connected=True, has_payload=True, tank_percent=50.0, battery_percent=80.0, battery_known=True)


class Robot:
    def __init__(self) -> None:
        self.clock = SimClock()
        self.core = AgentCore("r1", self.clock, Pilot())
        self.op = wire.HeaderCounter(self.clock, robot="r1", sender="op-a")

    def payload(self, **params: str) -> tuple[Ack, Output]:
        kvs = tuple(KeyValue(key=k, value=v) for k, v in params.items())
        msg = self.op.make(
            InstantActions, actions=(Action(actionId="p", actionType=ActionType.PAYLOAD, actionParameters=kvs),)
        )
        out = self.core.on_input(LinkName.ZENOH, wire.key_of(msg), wire.encode(msg), self.clock.now())
        return next(m for m, _ in out.messages if isinstance(m, Ack)), out

    def tick(self, board: BoardView = BOARD, dt: float = 0.05) -> Output:
        self.clock.advance(dt)
        return self.core.tick(self.clock.now(), board)


def test_the_lamp_goes_on_and_off_and_the_atomiser_and_fan_take_levels() -> None:
    r = Robot()
    r.tick()
    ack, out = r.payload(on="true")
    assert ack.result is AckResult.ACCEPTED and [(q.device, q.on) for q in out.payload] == [("uv", True)]
    ack, out = r.payload(device="atomiser", on="true", level="3")
    assert ack.result is AckResult.ACCEPTED and [(q.device, q.level) for q in out.payload] == [("atomiser", 3)]
    ack, out = r.payload(device="fan", on="true")
    assert [(q.device, q.on, q.level) for q in out.payload] == [("fan", True, 1)]
    ack, out = r.payload(device="fan", on="true", level="0")  # level 0 is off
    assert [(q.device, q.on) for q in out.payload] == [("fan", False)]


@pytest.mark.parametrize(
    ("params", "board", "reason"),
    [
        ({"device": "atomiser", "on": "true", "level": "4"}, BOARD, "atomiser level must be 0-3"),
        ({"device": "fan", "on": "true", "level": "x"}, BOARD, "fan level must be 0-3"),
        ({"device": "uv", "on": "true", "level": "2"}, BOARD, "the lamp has no level"),
        ({"device": "laser", "on": "true"}, BOARD, "unknown payload device"),
        ({"on": "maybe"}, BOARD, "on=true|false"),
        ({"device": "atomiser", "on": "true"}, dataclasses.replace(BOARD, tank_percent=0.0), "tank is empty"),
        ({"device": "fan", "on": "true"}, dataclasses.replace(BOARD, has_payload=False), "has no payload"),
        ({"on": "true"}, dataclasses.replace(BOARD, bumped=True), "UV lamp interlock: a bumper is pressed"),
    ],
)
def test_bad_payload_commands_are_refused_with_the_reason(
    params: dict[str, str], board: BoardView, reason: str
) -> None:
    r = Robot()
    r.tick(board)
    ack, out = r.payload(**params)
    assert ack.result is AckResult.REJECTED and reason in ack.reason, ack.reason
    assert out.payload == []  # nothing reaches the board


def test_a_lit_lamp_goes_off_when_a_bumper_is_pressed_once_per_episode() -> None:
    r = Robot()
    r.tick()
    r.payload(on="true")
    lit = dataclasses.replace(BOARD, payload_on=True)
    assert r.tick(lit).payload == []
    out = r.tick(dataclasses.replace(lit, bumped=True))
    assert [(q.device, q.on) for q in out.payload] == [("uv", False)]
    kinds = [m.kind for m, _ in out.messages if isinstance(m, Event)]
    assert "interlock" in kinds
    again = r.tick(dataclasses.replace(lit, bumped=True))  # the board has not answered yet
    assert again.payload == [] and "interlock" not in [m.kind for m, _ in again.messages if isinstance(m, Event)]


def test_a_lit_lamp_goes_off_when_its_operators_lease_is_given_back() -> None:
    r = Robot()
    r.tick()
    lease = r.op.make(LeaseRequest, duration_s=60.0, release=False)
    r.core.on_input(LinkName.ZENOH, wire.key_of(lease), wire.encode(lease), r.clock.now())
    r.payload(on="true")
    lit = dataclasses.replace(BOARD, payload_on=True)
    assert r.tick(lit).payload == []
    back = r.op.make(LeaseRequest, duration_s=0.0, release=True)
    r.core.on_input(LinkName.ZENOH, wire.key_of(back), wire.encode(back), r.clock.now())
    out = r.tick(lit)
    assert [(q.device, q.on) for q in out.payload] == [("uv", False)]


def test_a_lit_lamp_goes_off_when_its_radius_reaches_a_people_present_zone(monkeypatch: pytest.MonkeyPatch) -> None:
    r = Robot()
    monkeypatch.setattr(type(r.core.fusion), "position_initialized", property(lambda _self: True))
    r.tick()
    r.payload(on="true")
    lit = dataclasses.replace(BOARD, payload_on=True)
    r.core.zones = (PeopleZone("corridor", ((1.0, -1.0), (2.0, -1.0), (2.0, 1.0), (1.0, 1.0))),)
    out = r.tick(lit)
    assert [(q.device, q.on) for q in out.payload] == [("uv", False)]
    ack, _ = r.payload(on="true")
    assert ack.result is AckResult.REJECTED and "corridor" in ack.reason


# -- people-present zones from the operators ---------------------------------------------------------


def _zones(r: Robot, *zones: tuple[str, tuple[tuple[float, float], ...]], link: LinkName = LinkName.ZENOH) -> Output:
    from fleetlink.shared.messages import PeopleZones, Zone, ZonePoint

    msg = r.op.make(
        PeopleZones,
        zones=tuple(Zone(name=n, polygon=tuple(ZonePoint(x=x, y=y) for x, y in poly)) for n, poly in zones),
    )
    return r.core.on_input(link, wire.key_of(msg), wire.encode(msg), r.clock.now())


def test_an_operators_zones_reach_the_agent_and_a_new_list_replaces_the_old() -> None:
    r = Robot()
    ward = ((10.0, 0.0), (14.0, 0.0), (14.0, 4.0))
    out = _zones(r, ("ward-3", ward), ("ward-4", ((20.0, 0.0), (24.0, 0.0), (24.0, 4.0))))
    assert [z.name for z in r.core.zones] == ["ward-3", "ward-4"]
    assert "zones" in [m.kind for m, _ in out.messages if isinstance(m, Event)]
    assert not [m for m, _ in out.messages if isinstance(m, Ack)]  # not a command: no ack
    _zones(r, ("ward-3", ward))
    assert [z.name for z in r.core.zones] == ["ward-3"]
    _zones(r)  # an empty list withdraws them
    assert r.core.zones == ()


def test_a_zone_with_fewer_than_three_corners_is_refused_and_the_old_list_stands() -> None:
    r = Robot()
    _zones(r, ("ward-3", ((10.0, 0.0), (14.0, 0.0), (14.0, 4.0))))
    out = _zones(r, ("bad", ((0.0, 0.0), (1.0, 1.0))))
    assert [z.name for z in r.core.zones] == ["ward-3"]
    assert r.core.gate.stats.rejected_total == 1
    assert any("at least 3" in m.text for m, _ in out.messages if isinstance(m, Event))
