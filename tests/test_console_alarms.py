"""The console's alarm panel, ``A`` and ``:ack`` (run_test on the in-memory rig of test_console.py):
an alarm appears, the operator acknowledges it, the acknowledgement goes out as an ``AlarmAck``,
another console's acknowledgement shows, a critical alarm left alone renotifies, and every step
is in the audit log."""

from __future__ import annotations

import asyncio
import functools
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fleetlink.operator.alarm_panel import AlarmPanel
from fleetlink.operator.alarms import AlarmKind
from fleetlink.operator.audit import AuditLog
from fleetlink.shared import wire
from fleetlink.shared.messages import (
    AckedAlarm,
    AgvPosition,
    AlarmAck,
    BatteryState,
    BoardStatus,
    EStop,
    Event,
    SafetyState,
    Severity,
    State,
)
from tests.harness.console_rig import ME, Rig
from tests.harness.messages import board_status as harness_board_status
from tests.harness.messages import state as harness_state


def run_async(fn: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        return asyncio.run(fn(*args, **kwargs))

    return wrapper


def state(rig: Rig, robot: str, estop: EStop = EStop.NONE, battery: float = 80.0) -> State:
    return harness_state(
        rig.counter(robot),
        agvPosition=AgvPosition(x=1.0, y=1.0, theta=0.0, mapId="m", positionInitialized=True, localizationScore=0.9),
        batteryState=BatteryState(batteryCharge=battery, charging=False),
        safetyState=SafetyState(eStop=estop, fieldViolation=False),
    )


def board_status(rig: Rig, robot: str, battery: float) -> BoardStatus:
    return harness_board_status(rig.counter(robot), battery_percent=battery, tank_percent=None)


async def until(pilot: Any, predicate: Callable[[], object], what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.05)
    await pilot.pause()


def panel(rig: Rig) -> str:
    return str(rig.app.query_one(AlarmPanel).render())


def alarm(rig: Rig, robot: str, kind: AlarmKind) -> Any:
    with rig.lock:
        return rig.fleet.alarms.alarms.get(robot, kind)


@run_async
async def test_an_alarm_appears_and_shift_a_acknowledges_it(tmp_path: Path) -> None:
    rig = Rig(tmp_path)
    audit = tmp_path / "alarms.jsonl"
    rig.app.alarm_keeper.audit = AuditLog(audit, ME)
    rig.start()
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            rig.voices["r1"] = (1.0, 1.0)
            rig.zenoh.inject(state(rig, "r1"))
            await until(pilot, lambda: rig.app.selected == "r1", "r1 selected")
            assert not rig.app.query_one(AlarmPanel).display  # no alarm: no panel
            rig.zenoh.inject(state(rig, "r1", estop=EStop.MANUAL, battery=15.0))
            rig.zenoh.inject(board_status(rig, "r1", 15.0))
            await until(pilot, lambda: "e-stop" in panel(rig), "the e-stop in the alarm panel")
            assert rig.app.query_one(AlarmPanel).display and "low battery" in panel(rig)
            assert "CRIT" in panel(rig) and "WARN" in panel(rig)

            await pilot.press("A")  # the most severe first: the e-stop
            await until(pilot, lambda: rig.zenoh.messages(AlarmAck), "an AlarmAck on Zenoh")
            [ack] = rig.zenoh.messages(AlarmAck)
            estop = alarm(rig, "r1", AlarmKind.ESTOP)
            assert ack.header.sender == ME and ack.header.robot == "r1"
            assert ack.acks == (AckedAlarm(kind="estop", since=estop.since, at=estop.acked_at),)
            assert estop.acked_by == ME and alarm(rig, "r1", AlarmKind.LOW_BATTERY).acked_by is None
            await until(pilot, lambda: "ack you" in panel(rig), "'ack you' in the panel")

            # Another console acknowledges the low battery: shown here, with a notice.
            battery = alarm(rig, "r1", AlarmKind.LOW_BATTERY)
            other = wire.HeaderCounter(rig.clock, robot="r1", sender="operator-2")
            rig.mqtt.inject(
                other.make(AlarmAck, acks=(AckedAlarm(kind="low_battery", since=battery.since, at=time.time()),))
            )
            await until(pilot, lambda: "ack operator-2" in panel(rig), "the other console's acknowledgement")

            # A bump (latching) and the typed command: ':ack r1 all' acknowledges it, and it goes.
            rig.zenoh.inject(rig.counter("r1").make(Event, kind="bump", text="front", severity=Severity.ERROR, data=()))
            await until(pilot, lambda: "bump" in panel(rig), "the bump in the panel")
            await pilot.press("colon")
            await pilot.press(*"ack", "space", *"r1", "space", *"all", "enter")
            await until(pilot, lambda: alarm(rig, "r1", AlarmKind.BUMP) is None, "the bump acknowledged")
            await until(pilot, lambda: len(rig.zenoh.messages(AlarmAck)) == 2, "the second AlarmAck")
            assert {a.kind for a in rig.zenoh.messages(AlarmAck)[-1].acks} == {"estop", "bump"}
            # Nothing left to acknowledge: the operator is told so; an unknown robot is refused.
            await pilot.press("A")
            await pilot.press("colon")
            await pilot.press(*"ack", "space", *"ghost", "enter")
            await pilot.pause()
            assert len(rig.zenoh.messages(AlarmAck)) == 2

            # The e-stop released: the alarm clears and the acknowledgement is withdrawn.
            rig.zenoh.inject(state(rig, "r1", battery=15.0))
            await until(pilot, lambda: "e-stop" not in panel(rig), "the e-stop cleared")
            await until(pilot, lambda: len(rig.zenoh.messages(AlarmAck)) == 3, "the withdrawal")
            assert [a.kind for a in rig.zenoh.messages(AlarmAck)[-1].acks] == ["bump"]
    finally:
        rig.close()
    lines = [json.loads(line) for line in audit.read_text().splitlines()]
    events = [(d["event"], d["kind"], d["by"]) for d in lines]
    assert events[:3] == [("raised", "estop", None), ("raised", "low_battery", None), ("acknowledged", "estop", ME)]
    assert ("acknowledged", "low_battery", "operator-2") in events
    assert ("acknowledged", "bump", ME) in events and ("cleared", "bump", ME) in events
    assert events[-1] == ("cleared", "estop", None)


@run_async
async def test_an_unacknowledged_critical_alarm_renotifies_with_an_error_notice_and_the_bell(tmp_path: Path) -> None:
    rig = Rig(tmp_path)
    rig.fleet.alarms.alarms.renotify_s = 0.3  # 30 s in service; the time is what is tested in test_alarms.py
    rang: list[bool] = []
    rig.app.bell = lambda: rang.append(True)  # type: ignore[method-assign]
    rig.start()
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            notices: list[str] = []
            original = rig.app.notice

            def notice(severity: str, text: str) -> None:
                notices.append(f"{severity} {text}")
                original(severity, text)

            rig.app.notice = notice  # type: ignore[method-assign]
            rig.zenoh.inject(state(rig, "r1", estop=EStop.REMOTE))
            await until(pilot, lambda: rang, "the bell for the new critical alarm")
            await until(pilot, lambda: any("still unacknowledged" in n for n in notices), "a renotification")
            assert any(n.startswith("error ALARM r1") for n in notices)
            await pilot.press("A")
            await until(pilot, lambda: alarm(rig, "r1", AlarmKind.ESTOP).acked_by == ME, "the acknowledgement")
            count = sum("still unacknowledged" in n for n in notices)
            await asyncio.sleep(0.4)
            await pilot.pause()
            assert sum("still unacknowledged" in n for n in notices) == count  # acknowledged: quiet
    finally:
        rig.close()
