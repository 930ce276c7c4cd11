"""The console's sortie controls (issue 15): the e-stop keys and the confirmed release, home and
comms-loss policy commands, and what the detail shows (e-stop, home, contact, the board's status)."""

from __future__ import annotations

from typing import Any

import pytest

from fleetlink.operator.detail import detail_text
from fleetlink.operator.fleet import FleetModel, LeaseRenewal
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import (
    ActionType,
    AgvPosition,
    BoardFault,
    BoardStatus,
    CommsPolicy,
    Contact,
    EStop,
    Home,
    HomeSource,
    InstantActions,
    Lease,
    LeaseRequest,
    OperatingMode,
    SafetyState,
    State,
)
from tests.harness.console_rig import ME, Rig
from tests.harness.messages import state
from tests.test_console import run_async, screen_text, settle, type_text, with_robots


def actions(rig: Rig, kind: ActionType) -> list[InstantActions]:
    """What went out on either link (under load the link manager may move a robot to MQTT), once each."""
    seen: dict[tuple[str, int], InstantActions] = {}
    for m in [*rig.zenoh.messages(InstantActions), *rig.mqtt.messages(InstantActions)]:
        if any(a.actionType is kind for a in m.actions):
            seen.setdefault((m.header.robot, m.header.headerId), m)
    return sorted(seen.values(), key=lambda m: m.header.timestamp)


async def sent(pilot: Any, rig: Rig, kind: ActionType, n: int, timeout: float = 10.0) -> list[InstantActions]:
    """Wait (under load the app takes its time) until ``n`` actions of ``kind`` went out."""
    for _ in range(int(timeout / 0.05)):
        if len(got := actions(rig, kind)) >= n:
            return got
        await settle(pilot, 0.05)
    return actions(rig, kind)


@run_async
async def test_e_latches_the_selected_robot_ctrl_e_every_robot_and_release_asks_first(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1", "r2")
        await pilot.press("E")
        assert [m.header.robot for m in await sent(pilot, rig, ActionType.ESTOP, 1)] == [rig.app.selected]
        await pilot.press("ctrl+e")
        assert sorted(m.header.robot for m in (await sent(pilot, rig, ActionType.ESTOP, 3))[1:]) == ["r1", "r2"]
        # Release: nothing goes until the operator says yes.
        await pilot.press("R")
        await settle(pilot)
        await pilot.press("n")
        await settle(pilot)
        assert actions(rig, ActionType.ESTOP_RELEASE) == []
        await pilot.press("R")
        await settle(pilot)
        await pilot.press("y")
        released = await sent(pilot, rig, ActionType.ESTOP_RELEASE, 1)
        assert [m.header.robot for m in released] == [rig.app.selected]


@pytest.mark.slow
@run_async
async def test_typed_estop_home_set_and_policy_send_their_actions(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        for line in ("estop", "home set", "home 1.5 -2", "policy retrace"):
            await pilot.press("colon")
            await type_text(pilot, line)
            await pilot.press("enter")
            await settle(pilot, 0.1)
        assert len(await sent(pilot, rig, ActionType.ESTOP, 1)) == 1
        await sent(pilot, rig, ActionType.SET_COMMS_POLICY, 1)  # the last one typed: all went
        homes = actions(rig, ActionType.SET_HOME)
        assert [tuple((kv.key, kv.value) for kv in m.actions[0].actionParameters) for m in homes] == [
            (),
            (("x", "1.5"), ("y", "-2.0")),
        ]
        (policy,) = actions(rig, ActionType.SET_COMMS_POLICY)
        assert policy.actions[0].actionParameters[0].value == "retrace"
        # A capital E typed into the command line is a letter, not an e-stop.
        await pilot.press("colon")
        await type_text(pilot, "E")
        await settle(pilot, 0.1)
        assert len(actions(rig, ActionType.ESTOP)) == 1


def _state(rig: Rig, robot: str, **over: Any) -> State:
    fields: dict[str, Any] = {
        "agvPosition": AgvPosition(x=1.0, y=2.0, theta=0.0, mapId="", positionInitialized=True, localizationScore=0.9),
        "operatingMode": OperatingMode.SERVICE,
        "safetyState": SafetyState(eStop=EStop.MANUAL, fieldViolation=False),
        "driveMode": "estop",
        "home": Home(x=0.5, y=-0.5, theta=0.0, source=HomeSource.LOCALISED),
        "contact": Contact(policy=CommsPolicy.RETRACE, lost=True, action="retracing", silent_s=7.0),
    }
    return state(rig.counter(robot), **{**fields, **over})


def _board(rig: Rig, robot: str) -> BoardStatus:
    return rig.counter(robot).make(
        BoardStatus, connected=True, model="fleetlink-db", firmware="1.2", battery_percent=64.0,
        battery_voltage_v=12.31, battery_current_a=-0.9, charging=False, on_dock=False, temperature_c=23.5,
        humidity_percent=41.0, pm2_5_ug_m3=7.5, tvoc_ppb=110, uv_lamp=False, atomiser_level=0, fan_level=0, has_payload=True,
        tank_percent=12.0, estop_button=True, health_flags=1,
        faults=(BoardFault(code=3, text="disinfectant tank empty"),), bumpers=0, sensors_m=(1.2,), watchdog_trips=1,
    )  # fmt: skip


def test_the_detail_shows_the_estop_home_contact_and_the_boards_status() -> None:
    clock = SimClock()
    fleet = FleetModel(ME)
    rig_like = _Voices(clock)
    fleet.apply(_state(rig_like, "r1"), "zenoh", 0.0)  # type: ignore[arg-type]
    fleet.apply(_board(rig_like, "r1"), "zenoh", 0.0)  # type: ignore[arg-type]
    text = detail_text("r1", fleet.robots["r1"], ())
    for part in (
        "E-STOP (button on the robot)",
        "home +0.50 -0.50 (localised)",
        "comms-loss: retrace OUT OF CONTACT (retracing)",
        "battery 64% 12.31 V",
        "tank 12%",
        "23.5°C",
        "E-STOP BUTTON PRESSED",
        "0x0003 disinfectant tank empty",
        "watchdog trips 1",
    ):
        assert part in text, (part, text)
    assert any("e-stop (MANUAL)" in n.text for n in fleet.drain())


class _Voices:
    """Header counters per robot, as the rig has (without a console)."""

    def __init__(self, clock: SimClock) -> None:
        self.clock = clock
        self.agents: dict[str, wire.HeaderCounter] = {}

    def counter(self, robot: str) -> wire.HeaderCounter:
        return self.agents.setdefault(robot, wire.HeaderCounter(self.clock, robot=robot, sender=f"agent-{robot}"))


@run_async
async def test_the_map_draws_every_robots_home(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        rig.zenoh.inject(_state(rig, "r1", home=Home(x=0.0, y=0.0, theta=0.0, source=HomeSource.DOCK)))
        await settle(pilot)
        assert "H" in screen_text(rig.app)
        assert "home +0.00 +0.00 (dock)" in screen_text(rig.app)


def test_a_held_lease_is_renewed_often_enough_to_be_the_robots_sign_of_contact() -> None:
    fleet = FleetModel(ME)
    counter = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")
    fleet.apply(counter.make(Lease, holder=ME, until=1e12), "zenoh", 0.0)
    renew = LeaseRenewal(60.0)
    due = [t / 10 for t in range(0, 100) if renew.due(fleet, t / 10)]
    assert len(due) >= 4  # every 2 s, not every 20 s: the robot hears its operator


@run_async
async def test_esc_in_the_release_dialog_stops_every_robot_and_keeps_the_estop_latched(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1", "r2")
        for _ in range(200):  # under load the robots take a while to be heard
            if len(rig.app.fleet.robots) == 2 and rig.app.selected is not None:
                break
            await settle(pilot, 0.05)
        await pilot.press("R")
        await settle(pilot)
        assert len(rig.app.screen_stack) == 2  # the confirmation
        await pilot.press("escape")
        stops = await sent(pilot, rig, ActionType.STOP, 2)
        assert sorted(m.header.robot for m in stops) == ["r1", "r2"]
        await settle(pilot)
        assert len(rig.app.screen_stack) == 1 and actions(rig, ActionType.ESTOP_RELEASE) == []
        # E works in a dialog without a text field (here the map click's), not only on the map.
        rig.app.on_map_view_clicked(type("Click", (), {"x": 1.0, "y": 1.0})())  # type: ignore[arg-type]
        await settle(pilot)
        assert len(rig.app.screen_stack) == 2
        await pilot.press("E")
        assert len(await sent(pilot, rig, ActionType.ESTOP, 1)) == 1


@run_async
async def test_quitting_gives_back_the_leases_this_console_holds(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1", "r2")
        rig.zenoh.inject(rig.counter("r1").make(Lease, holder=ME, until=1e12))
        rig.zenoh.inject(rig.counter("r2").make(Lease, holder="op-other", until=1e12))
        await settle(pilot)
        await pilot.press("ctrl+q")
    releases = [m for m in rig.zenoh.messages(LeaseRequest) if m.release]
    assert [m.header.robot for m in releases] == ["r1"]  # ours only, after the stops


@pytest.mark.slow
@run_async
async def test_a_people_present_zone_goes_to_every_robot_and_to_one_that_appears_later(rig: Rig) -> None:
    from fleetlink.shared.messages import PeopleZones

    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1", "r2")
        await pilot.press("colon")
        await type_text(pilot, "zone add ward 1 1 3 1 3 3")
        await pilot.press("enter")
        await settle(pilot)
        sent = rig.zenoh.messages(PeopleZones)
        assert sorted(m.header.robot for m in sent) == ["r1", "r2"]
        assert [(z.name, len(z.polygon)) for z in sent[0].zones] == [("ward", 3)]
        rig.voices["r3"] = (2.0, 0.0)  # a robot that joins later gets them too
        for _ in range(40):
            if any(m.header.robot == "r3" for m in rig.zenoh.messages(PeopleZones)):
                break
            await settle(pilot, 0.05)
        assert any(m.header.robot == "r3" for m in rig.zenoh.messages(PeopleZones))
        await pilot.press("colon")
        await type_text(pilot, "zone rm ward")
        await pilot.press("enter")
        await settle(pilot)
        assert all(m.zones == () for m in rig.zenoh.messages(PeopleZones)[-3:])  # withdrawn everywhere
