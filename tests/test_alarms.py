"""Alarms (operator/alarms.py): every kind raised and cleared from its input, episodes,
acknowledgements shared between consoles, renotification, the audit log, and bad input refused."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import msgpack
import pytest

from fleetlink.operator.alarms import (
    LINK_QUIET_S,
    MAX_PENDING_ROBOTS,
    RENOTIFY_S,
    AckEntry,
    AlarmDesk,
    AlarmKind,
    AlarmList,
    AlarmSeverity,
    AuditEvent,
    derive,
    links_quiet,
    parse_kind,
)
from fleetlink.operator.audit import AuditLog
from fleetlink.operator.commands import AckAlarm, CommandError, parse_command
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import (
    MAX_ALARM_ACKS,
    UNKNOWN_SD_M,
    AckedAlarm,
    AgvPosition,
    AlarmAck,
    BatteryState,
    BoardFault,
    BoardStatus,
    CommsPolicy,
    Connection,
    ConnectionState,
    Contact,
    EStop,
    Event,
    Pose,
    SafetyState,
    Severity,
    State,
)
from tests.harness.messages import board_fields, state_fields

T0 = 1_767_225_600.0
K = AlarmKind


class Robot:
    """A robot's voice: its messages with headers stamped by a simulated clock."""

    def __init__(self, robot: str = "r1", clock: SimClock | None = None) -> None:
        self.clock = clock or SimClock(start=0.0, epoch=T0)
        self.counter = wire.HeaderCounter(self.clock, robot=robot, sender=f"agent-{robot}")

    def state(self, **over: Any) -> State:
        return self._make(State, state_fields(**over))  # type: ignore[no-any-return]

    def board(self, **over: Any) -> BoardStatus:
        return self._make(BoardStatus, board_fields(**over))  # type: ignore[no-any-return]

    def event(self, kind: str, text: str = "", severity: Severity = Severity.ERROR) -> Event:
        return self._make(Event, {"kind": kind, "text": text, "severity": severity, "data": ()})

    def connection(self, state: ConnectionState) -> Connection:
        return self._make(Connection, {"connectionState": state})

    def _make(self, cls: type[Any], fields: dict[str, Any]) -> Any:
        msg = self.counter.make(cls, **fields)
        self.clock.advance(1.0)
        return wire.decode_key(wire.key_of(msg), wire.encode(msg))  # as a console receives it


def ack_msg(robot: str, by: str, acks: list[AckedAlarm], at: float = T0 + 500, header_id: int = 0) -> AlarmAck:
    header = wire.Header(headerId=header_id, timestamp=at, version=wire.WIRE_VERSION, robot=robot, sender=by)
    return AlarmAck(header=header, acks=tuple(acks))


def publish(desk: AlarmDesk, hid: list[int] | None = None) -> list[AlarmAck]:
    """What ``desk``'s console would publish now, as the wire carries it."""
    out = []
    counter = wire.HeaderCounter(SimClock(start=1000.0, epoch=T0), robot="x", sender=desk.operator)
    for robot, entries in desk.outgoing():
        msg = AlarmAck(header=counter.header(AlarmAck.TOPIC, robot=robot), acks=tuple(e.wire() for e in entries))
        out.append(wire.decode_key(wire.key_of(msg), wire.encode(msg)))
    return out


def active(desk: AlarmDesk, robot: str = "r1") -> dict[AlarmKind, AlarmSeverity]:
    return {a.kind: a.severity for a in desk.alarms.active(robot)}


def heard(desk: AlarmDesk, *msgs: Any, now: float | None = None) -> None:
    for msg in msgs:
        desk.observe(msg, msg.header.timestamp + 0.01 if now is None else now)


# -- every kind from its input ---------------------------------------------------------------------


def test_estop_from_state_and_from_the_button_clears_when_both_are_released() -> None:
    desk, r = AlarmDesk("op-a"), Robot()
    heard(desk, r.state())
    assert active(desk) == {}
    heard(desk, r.state(safetyState=SafetyState(eStop=EStop.REMOTE, fieldViolation=False)))
    assert active(desk) == {K.ESTOP: AlarmSeverity.CRITICAL}
    heard(desk, r.board(estop_button=True))  # a second source: the same alarm, still one episode
    heard(desk, r.state())  # released remotely, the button still pressed
    assert active(desk) == {K.ESTOP: AlarmSeverity.CRITICAL}
    assert desk.alarms.get("r1", K.ESTOP).count == 1  # type: ignore[union-attr]
    heard(desk, r.board())
    assert active(desk) == {}


def test_localisation_degraded_with_hysteresis() -> None:
    desk, r = AlarmDesk("op-a"), Robot()
    pos = AgvPosition(x=0, y=0, theta=0, mapId="m", positionInitialized=False, localizationScore=0.9)
    heard(desk, r.state(agvPosition=pos))
    assert active(desk) == {K.LOCALISATION: AlarmSeverity.WARNING}
    assert "not initialised" in desk.alarms.get("r1", K.LOCALISATION).text  # type: ignore[union-attr]
    heard(desk, r.state())
    assert active(desk) == {}
    heard(desk, r.state(uwbStale=True))
    assert K.LOCALISATION in active(desk)
    heard(desk, r.state())
    for score, on in ((0.49, True), (0.55, True), (0.61, False), (0.55, False), (0.45, True)):
        pos = dataclasses.replace(pos, positionInitialized=True, localizationScore=score)
        heard(desk, r.state(agvPosition=pos))
        assert (K.LOCALISATION in active(desk)) is on, score


def test_a_placed_robot_not_yet_driven_says_its_heading_is_not_found() -> None:
    """UWB places a robot before it has driven, its heading found from the fixes along its first
    half metre: the score is 0 till then, and the warning says why rather than "score 0.00"."""
    desk, r = AlarmDesk("op-a"), Robot()
    placed = AgvPosition(x=1, y=2, theta=0, mapId="m", positionInitialized=True, localizationScore=0.0)

    def pose(sd_theta: float) -> Pose:
        return r._make(  # type: ignore[no-any-return]
            Pose,
            {
                "x": 1.0, "y": 2.0, "theta": 0.0, "sd_x_m": 0.05, "sd_y_m": 0.05, "sd_theta_rad": sd_theta,
                "odom_x": 0.0, "odom_y": 0.0, "odom_theta": 0.0, "vx": 0.0, "omega": 0.0, "uwbStale": False,
            },
        )  # fmt: skip

    heard(desk, pose(UNKNOWN_SD_M), r.state(agvPosition=placed))
    alarm = desk.alarms.get("r1", K.LOCALISATION)
    assert alarm is not None and alarm.severity is AlarmSeverity.WARNING
    assert alarm.text == "localisation: heading not found yet: it is found as the robot drives"
    # Driven, the heading found: judged on its score again.
    heard(desk, pose(0.02), r.state(agvPosition=dataclasses.replace(placed, localizationScore=0.3)))
    assert desk.alarms.get("r1", K.LOCALISATION).text == "localisation: score 0.30"  # type: ignore[union-attr]
    heard(desk, r.state(agvPosition=dataclasses.replace(placed, localizationScore=0.9)))
    assert K.LOCALISATION not in active(desk)


def test_a_robot_in_its_own_frame_is_localised_once_the_fleet_map_places_it() -> None:
    """A robot without UWB never has a site position: "position not initialised" would stand all
    its life. Once the fleet map says where its own frame lies, its localisation is that, and the
    alarm clears; while the fleet map has not found it, the warning says so, and why."""
    desk, r = AlarmDesk("op-a"), Robot()
    dark = AgvPosition(x=1, y=2, theta=0, mapId="m", positionInitialized=False, localizationScore=0.0)
    heard(desk, r.state(agvPosition=dark, uwbStale=True))
    assert "not initialised" in desk.alarms.get("r1", K.LOCALISATION).text  # type: ignore[union-attr]
    desk.own_frame("r1", "on r2's map: too few walls")
    heard(desk, r.state(agvPosition=dark, uwbStale=True))
    alarm = desk.alarms.get("r1", K.LOCALISATION)
    assert alarm is not None and alarm.severity is AlarmSeverity.WARNING
    assert alarm.text == "localisation: its own map, not on the fleet map yet (on r2's map: too few walls)"
    desk.own_frame("r1", None)  # placed
    heard(desk, r.state(agvPosition=dark, uwbStale=True))
    assert K.LOCALISATION not in active(desk)
    # It gets a site position after all (UWB came back): judged as any robot again.
    heard(desk, r.state(agvPosition=dataclasses.replace(dark, positionInitialized=True, localizationScore=0.2)))
    assert "score 0.20" in desk.alarms.get("r1", K.LOCALISATION).text  # type: ignore[union-attr]
    # No longer mapping in its own frame: an uninitialised position warns again.
    desk.own_frame("r1", None, mapping=False)
    heard(desk, r.state(agvPosition=dark, uwbStale=True))
    assert "not initialised" in desk.alarms.get("r1", K.LOCALISATION).text  # type: ignore[union-attr]


def test_link_lost_from_the_robot_and_from_the_console() -> None:
    desk, r = AlarmDesk("op-a"), Robot()
    heard(desk, r.state(contact=Contact(policy=CommsPolicy.RETRACE, lost=True, action="retracing", silent_s=12.0)))
    alarm = desk.alarms.get("r1", K.LINK_LOST)
    assert alarm is not None and alarm.severity is AlarmSeverity.CRITICAL
    assert alarm.text == "robot hears no operator for 12 s (retrace, retracing)"
    heard(desk, r.state())
    assert active(desk) == {}
    # The console's own view: heard on neither link for LINK_QUIET_S.
    assert not links_quiet([None, None]) and not links_quiet([LINK_QUIET_S + 1, 0.2])
    assert links_quiet([LINK_QUIET_S + 1, None]) and links_quiet([LINK_QUIET_S + 1, LINK_QUIET_S + 5])
    desk.link_quiet("r1", True, T0 + 100)
    assert active(desk) == {K.LINK_LOST: AlarmSeverity.CRITICAL}
    desk.link_quiet("r1", False, T0 + 101)
    assert active(desk) == {}


def test_low_battery_warning_then_critical_then_recovery_with_hysteresis() -> None:
    desk, r = AlarmDesk("op-a"), Robot()

    def battery(percent: float) -> None:
        heard(desk, r.board(battery_percent=percent))

    battery(21)
    assert active(desk) == {}
    battery(20)
    assert active(desk) == {K.LOW_BATTERY: AlarmSeverity.WARNING}
    first = desk.alarms.get("r1", K.LOW_BATTERY)
    assert first is not None and first.text == "battery 20 %"
    first_since = first.since
    battery(21.5)  # within the hysteresis: still low
    assert K.LOW_BATTERY in active(desk)
    battery(10)
    assert active(desk) == {K.LOW_BATTERY: AlarmSeverity.CRITICAL}
    escalated = desk.alarms.get("r1", K.LOW_BATTERY)
    assert escalated is not None and escalated.count == 2 and escalated.since > first_since
    battery(11.5)  # a critical alarm stays critical within its episode
    assert active(desk) == {K.LOW_BATTERY: AlarmSeverity.CRITICAL}
    battery(22.5)
    assert active(desk) == {}
    events = [rec.event for rec in desk.drain_audit()]
    assert events == [AuditEvent.RAISED, AuditEvent.ESCALATED, AuditEvent.CLEARED]


def test_board_fault_battery_tank_and_button_from_the_board() -> None:
    desk, r = AlarmDesk("op-a"), Robot()
    heard(desk, r.board(faults=(BoardFault(code=7, text="motor overcurrent"),)))
    alarm = desk.alarms.get("r1", K.BOARD_FAULT)
    assert alarm is not None and alarm.text == "board fault 7: motor overcurrent"
    heard(desk, r.board(faults=(), tank_percent=15.0, battery_percent=9.0))
    assert active(desk) == {K.TANK_LOW: AlarmSeverity.INFO, K.LOW_BATTERY: AlarmSeverity.CRITICAL}
    heard(desk, r.board(tank_percent=16.5, battery_percent=50.0))  # the tank within its hysteresis
    assert active(desk) == {K.TANK_LOW: AlarmSeverity.INFO}
    heard(desk, r.board(tank_percent=17.5))
    assert active(desk) == {}
    heard(desk, r.board(tank_percent=None, connected=False))  # no tank: no tank alarm
    assert active(desk) == {K.BOARD_FAULT: AlarmSeverity.WARNING}
    heard(desk, r.state(boardConnected=False), r.board())  # the agent says so too
    assert active(desk) == {K.BOARD_FAULT: AlarmSeverity.WARNING}
    heard(desk, r.state())
    assert active(desk) == {}


def test_cliff_and_bump_latch_until_acknowledged() -> None:
    desk, r = AlarmDesk("op-a"), Robot()
    heard(desk, r.state())
    heard(desk, r.event("cliff", "cliff sensor 2: drop ahead"), r.event("bump", "front bumper"))
    heard(desk, r.event("cliff", "cliff sensor 3"), r.event("goal_reached", "", Severity.INFO))
    assert active(desk) == {K.CLIFF: AlarmSeverity.CRITICAL, K.BUMP: AlarmSeverity.WARNING}
    cliff = desk.alarms.get("r1", K.CLIFF)
    assert cliff is not None and cliff.count == 2 and cliff.text == "cliff sensor 3"
    heard(desk, r.state())  # nothing clears them by itself
    assert set(active(desk)) == {K.CLIFF, K.BUMP}
    done = desk.acknowledge("r1", None, T0 + 100)  # the most severe first
    assert [a.kind for a in done.acked] == [K.CLIFF] and not done.reason
    assert active(desk) == {K.BUMP: AlarmSeverity.WARNING}
    heard(desk, r.event("cliff", "again"))  # a new episode
    again = desk.alarms.get("r1", K.CLIFF)
    assert again is not None and again.count == 1 and again.acked_by is None


def test_robot_lost_from_the_liveliness_token_and_the_mqtt_connection() -> None:
    desk, r = AlarmDesk("op-a"), Robot()
    assert desk.present("r1") is None
    desk.presence("r1", "zenoh", True, T0 + 1)
    assert desk.present("r1") is True and active(desk) == {}
    desk.presence("r1", "zenoh", False, T0 + 2)
    assert desk.present("r1") is False
    assert active(desk) == {K.ROBOT_LOST: AlarmSeverity.CRITICAL}
    desk.presence("r1", "zenoh", True, T0 + 3)  # the token back
    assert active(desk) == {}
    # While MQTT says the robot is online, a token that went is no loss (the console's own Zenoh
    # may be what failed); the last will says it is gone.
    heard(desk, r.connection(ConnectionState.ONLINE), now=T0 + 4)
    desk.presence("r1", "zenoh", False, T0 + 5)
    assert active(desk) == {} and desk.present("r1") is True
    heard(desk, r.connection(ConnectionState.CONNECTIONBROKEN), now=T0 + 6)
    assert active(desk) == {K.ROBOT_LOST: AlarmSeverity.CRITICAL}
    assert desk.alarms.get("r1", K.ROBOT_LOST).text == "gone: mqtt connection, zenoh token"  # type: ignore[union-attr]


def test_derive_is_pure_and_ignores_what_shows_no_alarm() -> None:
    r = Robot()
    obs = derive(r.board(battery_percent=15.0))
    assert {(o.kind, o.severity) for o in obs if o.severity is not None} == {(K.LOW_BATTERY, AlarmSeverity.WARNING)}
    # The battery comes from the board's report only: a State says 0 % until the first status
    # poll, and a board the agent does not hear says nothing about its battery.
    assert not [
        o
        for o in derive(r.state(batteryState=BatteryState(batteryCharge=0.0, charging=False)))
        if o.kind is K.LOW_BATTERY
    ]
    assert not [o for o in derive(r.board(battery_percent=0.0, connected=False)) if o.kind is K.LOW_BATTERY]
    assert derive(r.event("guard_refusal", "obstacle", Severity.WARNING)) == []
    assert derive(r.connection(ConnectionState.ONLINE)) == []
    assert parse_kind("E-Stop") is K.ESTOP and parse_kind("battery") is K.LOW_BATTERY and parse_kind("x") is None


# -- acknowledgement, episodes, sharing -------------------------------------------------------------


def estop_on(r: Robot) -> State:
    return r.state(safetyState=SafetyState(eStop=EStop.MANUAL, fieldViolation=False))


def test_an_acknowledgement_is_shared_and_applies_to_its_episode_only() -> None:
    alice, bob, r = AlarmDesk("op-alice"), AlarmDesk("op-bob"), Robot()
    first = r.state()
    on = estop_on(r)
    for desk in (alice, bob):
        heard(desk, first, on)
    done = alice.acknowledge("r1", K.ESTOP, T0 + 50)
    assert done.acked[0].acked_by == "op-alice"
    [msg] = publish(alice)
    assert msg.acks == (AckedAlarm(kind="estop", since=on.header.timestamp, at=T0 + 50),)
    assert bob.observe(msg, T0 + 51) is None
    alarm = bob.alarms.get("r1", K.ESTOP)
    assert alarm is not None and (alarm.acked_by, alarm.acked_at) == ("op-alice", T0 + 50)
    # The episode ends: alice withdraws it (an empty list), and her old acknowledgement does not
    # cover the next episode at bob's even if it comes again late.
    off, on2 = r.state(), estop_on(r)
    for desk in (alice, bob):
        heard(desk, off)
    [withdrawn] = publish(alice)
    assert withdrawn.acks == ()
    for desk in (alice, bob):
        heard(desk, on2)
    bob.observe(ack_msg("r1", "op-alice", list(msg.acks), at=T0 + 9999), T0 + 60)
    assert bob.alarms.get("r1", K.ESTOP).acked_by is None  # type: ignore[union-attr]


def test_a_late_console_takes_the_retained_acknowledgement_even_before_it_hears_the_robot() -> None:
    alice, r = AlarmDesk("op-alice"), Robot()
    heard(alice, r.state(), estop_on(r))
    alice.acknowledge("r1", None, T0 + 50)
    [retained] = publish(alice)
    late = AlarmDesk("op-carol")
    assert late.observe(retained, T0 + 100) is None  # held: the broker gives it before the robot speaks
    assert late.alarms.active() == []
    heard(late, estop_on(r))  # its first message shows the e-stop: the console never saw it off
    alarm = late.alarms.get("r1", K.ESTOP)
    assert alarm is not None and alarm.acked_by == "op-alice"


def test_a_worse_episode_needs_a_new_acknowledgement() -> None:
    desk, r = AlarmDesk("op-a"), Robot()
    heard(desk, r.board(battery_percent=18.0))
    desk.acknowledge("r1", K.LOW_BATTERY, T0 + 30)
    [acked] = publish(desk)
    assert [a.kind for a in acked.acks] == ["low_battery"]
    heard(desk, r.board(battery_percent=8.0))
    alarm = desk.alarms.get("r1", K.LOW_BATTERY)
    assert alarm is not None and alarm.severity is AlarmSeverity.CRITICAL and alarm.acked_by is None
    [msg] = publish(desk)  # the warning's acknowledgement withdrawn: that episode is over
    assert msg.acks == ()


def test_own_acknowledgements_come_back_from_the_broker_after_a_restart() -> None:
    r = Robot()
    before = AlarmDesk("op-a")
    heard(before, r.state(), estop_on(r))
    before.acknowledge("r1", K.ESTOP, T0 + 40)
    [retained] = publish(before)
    after = AlarmDesk("op-a")  # the same login, restarted
    heard(after, estop_on(r))
    after.observe(retained, T0 + 60)
    assert after.alarms.get("r1", K.ESTOP).acked_by == "op-a"  # type: ignore[union-attr]
    assert publish(after) == []  # nothing new to say
    assert after.alarms.acks_of("r1", "op-a") == (AckEntry(K.ESTOP, retained.acks[0].since, T0 + 40),)


def test_copies_and_older_lists_change_nothing() -> None:
    desk, r = AlarmDesk("op-a"), Robot()
    heard(desk, r.state(), estop_on(r))
    since = desk.alarms.get("r1", K.ESTOP).since  # type: ignore[union-attr]
    newer = ack_msg("r1", "op-b", [], at=T0 + 80, header_id=2)
    older = ack_msg("r1", "op-b", [AckedAlarm(kind="estop", since=since, at=T0 + 70)], at=T0 + 70, header_id=1)
    desk.observe(newer, T0 + 81)
    desk.observe(older, T0 + 82)  # came late on the other link: older than the list already held
    assert desk.alarms.get("r1", K.ESTOP).acked_by is None  # type: ignore[union-attr]
    # A clear stamped by a lagging clock still ends the episode, and the next one starts after it.
    assert desk.alarms.clear("r1", K.ESTOP, T0 + 90, since=since - 5)
    again = desk.alarms.raise_alarm("r1", K.ESTOP, "e-stop", T0 + 91, since=since - 6)
    assert again.since > since and desk.alarms.floor("r1", K.ESTOP) == since


# -- renotification and the audit -------------------------------------------------------------------


def test_an_unacknowledged_critical_alarm_renotifies_every_renotify_s() -> None:
    alarms = AlarmList()
    alarms.raise_alarm("r1", K.ESTOP, "e-stop manual", T0)
    alarms.raise_alarm("r1", K.BUMP, "bump", T0)  # a warning: never renotified
    assert alarms.due_renotifications(T0 + RENOTIFY_S - 0.1) == []
    [due] = alarms.due_renotifications(T0 + RENOTIFY_S)
    assert due.kind is K.ESTOP
    assert alarms.due_renotifications(T0 + RENOTIFY_S + 1) == []
    assert [a.kind for a in alarms.due_renotifications(T0 + 2 * RENOTIFY_S)] == [K.ESTOP]
    alarms.acknowledge("r1", K.ESTOP, "op-a", T0 + 2 * RENOTIFY_S + 1)
    assert alarms.due_renotifications(T0 + 10 * RENOTIFY_S) == []
    events = [(rec.event, rec.kind) for rec in alarms.drain_audit()]
    assert events == [
        (AuditEvent.RAISED, "estop"),
        (AuditEvent.RAISED, "bump"),
        (AuditEvent.RENOTIFIED, "estop"),
        (AuditEvent.RENOTIFIED, "estop"),
        (AuditEvent.ACKNOWLEDGED, "estop"),
    ]
    with pytest.raises(ValueError, match="renotify_s"):
        AlarmList(renotify_s=0)


def test_the_audit_log_is_json_lines_appended_and_flushed(tmp_path: Path) -> None:
    path = tmp_path / "logs" / "alarms.jsonl"
    desk, r = AlarmDesk("op-a"), Robot()
    heard(desk, r.state(), estop_on(r))
    log = AuditLog(path, "op-a")
    log.write(desk.drain_audit())
    assert log.lines == 1 and len(path.read_text().splitlines()) == 1  # flushed: readable at once
    desk.acknowledge("r1", K.ESTOP, T0 + 5)
    heard(desk, r.state())
    log.write(desk.drain_audit())
    log.close()
    again = AuditLog(path, "op-a")  # append, never rewrite
    again.write(desk.drain_audit())
    desk.observe(ack_msg("r1", "op-b", [AckedAlarm(kind="warp_core", since=1.0, at=2.0)]), T0 + 9)
    again.write(desk.drain_audit())
    again.close()
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert [(d["event"], d["kind"], d["by"]) for d in lines] == [
        ("raised", "estop", None),
        ("acknowledged", "estop", "op-a"),
        ("cleared", "estop", None),
        ("refused", "warp_core", "op-b"),
    ]
    assert all(d["console"] == "op-a" and d["robot"] == "r1" and math.isfinite(d["at"]) for d in lines)
    assert lines[0]["severity"] == "critical" and lines[0]["since"] == lines[1]["since"]
    AuditLog(None, "op-a").write(desk.drain_audit())  # no path: nothing written, no error


def test_an_unwritable_audit_log_is_logged_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    (tmp_path / "file").write_text("")
    log = AuditLog(tmp_path / "file" / "alarms.jsonl", "op-a")  # its folder is a file
    alarms = AlarmList()
    for kind in (K.ESTOP, K.BUMP):
        alarms.raise_alarm("r1", kind, "x", T0)
    log.write(alarms.drain_audit())
    log.write(alarms.drain_audit())
    assert log.lines == 0 and caplog.text.count("alarm audit log") == 1


# -- bad input ---------------------------------------------------------------------------------------


def test_bad_acknowledgements_are_refused_with_a_reason_counted_and_recorded_once() -> None:
    desk, r = AlarmDesk("op-a"), Robot()
    heard(desk, r.state(), estop_on(r))
    since = desk.alarms.get("r1", K.ESTOP).since  # type: ignore[union-attr]
    desk.drain_audit()
    # An unknown kind is refused alone; the known ones in the same list still count.
    mixed = [AckedAlarm(kind="warp_core", since=1.0, at=2.0), AckedAlarm(kind="estop", since=since, at=T0 + 5)]
    assert desk.observe(ack_msg("r1", "op-b", mixed), T0 + 6) == "unknown alarm kind 'warp_core'"
    assert desk.alarms.get("r1", K.ESTOP).acked_by == "op-b"  # type: ignore[union-attr]
    desk.observe(ack_msg("r1", "op-c", mixed[:1], header_id=1), T0 + 7)
    assert desk.refused["unknown alarm kind 'warp_core'"] == 2
    twice = [AckedAlarm(kind="estop", since=since, at=T0 + 5)] * 2
    assert desk.observe(ack_msg("r1", "op-d", twice), T0 + 7) == "an alarm kind is listed twice"
    # Robots never heard: held up to a bound (retained lists come before the robot speaks), then refused.
    for i in range(MAX_PENDING_ROBOTS):
        assert desk.observe(ack_msg(f"ghost-{i}", "op-b", []), T0 + 8) is None
    reason = desk.observe(ack_msg("ghost-x", "op-b", []), T0 + 9)
    assert reason == "unknown robot 'ghost-x'" and desk.refused[reason] == 1
    refused = [rec for rec in desk.drain_audit() if rec.event is AuditEvent.REFUSED]
    assert [(rec.kind, rec.text) for rec in refused] == [
        ("warp_core", "unknown alarm kind 'warp_core'"),
        ("", "an alarm kind is listed twice"),
        ("", "unknown robot 'ghost-x'"),
    ]
    # Nothing else was disturbed.
    assert active(desk) == {K.ESTOP: AlarmSeverity.CRITICAL}


def test_malformed_and_oversized_acknowledgements_do_not_decode() -> None:
    entry = {"kind": "estop", "since": 1.0, "at": 2.0}
    good = ack_msg("r1", "op-b", [AckedAlarm(**entry)])  # type: ignore[arg-type]
    key = wire.key_of(good)
    assert key == "fleetlink/v1/r1/alarms/ack/op-b"
    doc = wire.encode(good)
    assert wire.decode_key(key, doc) == good
    raw = msgpack.unpackb(doc)
    cases = {
        "oversized": [{**entry, "kind": f"k{i}"} for i in range(MAX_ALARM_ACKS + 1)],
        "nan": [{**entry, "since": math.nan}],
        "negative": [{**entry, "at": -1.0}],
    }
    reasons = {}
    for name, acks in cases.items():
        with pytest.raises(wire.WireError) as err:
            wire.decode_key(key, msgpack.packb({**raw, "acks": acks}, use_bin_type=True))
        reasons[name] = err.value.reason
    assert "more than the limit of 16" in reasons["oversized"]
    # Under another console's name: the key vouches for the sender.
    with pytest.raises(wire.WireError, match=r"header\.sender"):
        wire.decode_key("fleetlink/v1/r1/alarms/ack/op-c", doc)


def test_an_operator_acknowledging_nothing_is_told_why() -> None:
    desk, r = AlarmDesk("op-a"), Robot()
    assert desk.acknowledge("nobody", None, T0).reason == "unknown robot 'nobody'"
    heard(desk, r.state())
    assert desk.acknowledge("r1", None, T0).reason == "r1: no unacknowledged alarm"
    assert desk.acknowledge("r1", K.CLIFF, T0).reason == "r1: no cliff alarm"
    heard(desk, estop_on(r), r.event("bump"))
    done = desk.acknowledge("r1", None, T0 + 20, every=True)
    assert [a.kind for a in done.acked] == [K.ESTOP, K.BUMP]
    assert desk.acknowledge("r1", K.ESTOP, T0 + 21).reason == "r1: e-stop already acknowledged by op-a"


def test_the_ack_command() -> None:
    assert parse_command("ack") == AckAlarm(None, None)
    assert parse_command("ack all") == AckAlarm(None, None, every=True)
    assert parse_command("ack r1") == AckAlarm("r1", None)
    assert parse_command("ack r1 e-stop") == AckAlarm("r1", K.ESTOP)
    assert parse_command("ACK uvc-2 all") == AckAlarm("uvc-2", None, every=True)
    bad = parse_command("ack r1 warp_core")
    assert isinstance(bad, CommandError) and "unknown alarm kind 'warp_core'" in bad.text
    assert isinstance(parse_command("ack r/1"), CommandError)


# -- presence on the in-process bus (lockstep) ------------------------------------------------------


def test_in_process_liveliness_follows_start_cut_restore_and_close() -> None:
    from fleetlink.links.inprocess import InProcessBus
    from fleetlink.shared.messages import LinkName

    bus = InProcessBus(LinkName.ZENOH)
    agent, console = bus.endpoint("agent-r1"), bus.endpoint("console")
    agent.alive_key = "fleetlink/alive/v1/r1"
    seen: list[tuple[str, bool]] = []
    console.watch_liveliness("fleetlink/alive/v1/*", lambda key, alive: seen.append((key, alive)))
    console.start()
    bus.deliver()
    assert seen == []
    agent.start()
    bus.deliver()
    bus.deliver()
    assert seen == [("fleetlink/alive/v1/r1", True)]
    bus.cut("agent-r1")
    bus.deliver()
    bus.restore("agent-r1")
    bus.deliver()
    agent.close()
    bus.deliver()
    assert seen[1:] == [
        ("fleetlink/alive/v1/r1", False),
        ("fleetlink/alive/v1/r1", True),
        ("fleetlink/alive/v1/r1", False),
    ]


def test_the_operator_link_turns_tokens_into_presence_and_robot_lost() -> None:
    import threading

    from fleetlink.links.inprocess import InProcessBus
    from fleetlink.operator.feed import attach
    from fleetlink.operator.fleet import FleetModel
    from fleetlink.operator.links import OperatorLink
    from fleetlink.shared.messages import LinkName

    clock = SimClock(start=0.0, epoch=T0)
    zenoh, mqtt = InProcessBus(LinkName.ZENOH), InProcessBus(LinkName.MQTT)
    agent = zenoh.endpoint("agent-r1")
    agent.alive_key = "fleetlink/alive/v1/r1"
    bogus = zenoh.endpoint("bogus")
    bogus.alive_key = "fleetlink/v1/r2/alive"  # the old key (before issue 18) matches no watch: never reported
    link = OperatorLink(clock, "op-a", zenoh.endpoint("op-a"), mqtt.endpoint("op-a"))
    fleet = FleetModel("op-a")
    attach(link, fleet, threading.Lock())
    link.start()
    agent.start()
    bogus.start()
    zenoh.deliver()
    assert fleet.robots["r1"].present is True and set(fleet.robots) == {"r1"}
    zenoh.cut("agent-r1")
    zenoh.deliver()
    assert fleet.robots["r1"].present is False
    lost = fleet.alarms.alarms.get("r1", K.ROBOT_LOST)
    assert lost is not None and lost.severity is AlarmSeverity.CRITICAL
    zenoh.restore("agent-r1")
    zenoh.deliver()
    assert fleet.alarms.alarms.get("r1", K.ROBOT_LOST) is None and fleet.robots["r1"].present is True
    link.close()


def test_a_token_under_the_contracts_key_is_presence_and_a_bad_one_is_rejected_counted_logged_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Issue 18: presence is ``fleetlink/alive/v1/<robot>`` (``keys.alive_key``). A token there
    whose last segment is no valid robot id (a reserved one, characters outside the id rule) is
    refused: counted each time it comes or goes, logged once, never a robot in the console."""
    import logging
    import threading

    from fleetlink.links.inprocess import InProcessBus
    from fleetlink.operator.feed import attach
    from fleetlink.operator.fleet import FleetModel
    from fleetlink.operator.links import ALIVE_TOKENS, OperatorLink
    from fleetlink.shared import keys
    from fleetlink.shared.messages import LinkName

    assert ALIVE_TOKENS == keys.ZENOH_ALL_ALIVE == "fleetlink/alive/v1/*"
    clock = SimClock(start=0.0, epoch=T0)
    zenoh, mqtt = InProcessBus(LinkName.ZENOH), InProcessBus(LinkName.MQTT)
    agent = zenoh.endpoint("agent-r7")
    agent.alive_key = keys.alive_key("r7")
    reserved, invalid = zenoh.endpoint("reserved"), zenoh.endpoint("invalid")
    reserved.alive_key = "fleetlink/alive/v1/sim"
    invalid.alive_key = "fleetlink/alive/v1/r7!"
    link = OperatorLink(clock, "op-a", zenoh.endpoint("op-a"), mqtt.endpoint("op-a"))
    fleet = FleetModel("op-a")
    attach(link, fleet, threading.Lock())
    with caplog.at_level(logging.WARNING, logger="fleetlink.operator.links"):
        link.start()
        for e in (agent, reserved, invalid):
            e.start()
        zenoh.deliver()
        assert set(fleet.robots) == {"r7"} and fleet.robots["r7"].present is True
        for client in ("reserved", "invalid"):  # each bad token goes and comes back: 2 more each
            zenoh.cut(client)
            zenoh.deliver()
            zenoh.restore(client)
            zenoh.deliver()
        link.close()
    bad = {reason: n for reason, n in link.rejected.items() if reason.startswith("bad liveliness token")}
    assert len(bad) == 2 and sorted(bad.values()) == [3, 3], link.rejected
    assert any("reserved" in r for r in bad) and any("r7!" in r for r in bad)
    logged = [r for r in caplog.records if "bad liveliness token" in r.getMessage()]
    assert len(logged) == 2
    assert set(fleet.robots) == {"r7"}
