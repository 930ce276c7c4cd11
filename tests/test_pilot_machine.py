"""The pilot's state machine: the table is total and consistent, the pilot does what it declares.

Three layers: the table alone (every state x trigger has an outcome; every refusal has a reason;
effects match what each state carries), the pilot against the table (for every state and every
command, the pilot's answer, new state and events are exactly the table's), and each state's
behaviour over time (e-stop latch, teleop lapse, pause holding an order, cancel, return home).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import pytest

from fleetlink.agent import pilot_machine
from fleetlink.agent.guard import GuardInputs
from fleetlink.agent.pilot import ActionKind, CommandResult, CommandStatus, EventKind, OperatingMode, Pilot
from fleetlink.agent.pilot_machine import (
    TRANSITIONS,
    Announce,
    Cancel,
    Do,
    PilotState,
    Refused,
    Transition,
    Trigger,
    next_state,
)
from tests.test_motion import Unicycle

S = PilotState
CLEAR = GuardInputs()
HERE = (0.0, 0.0, 0.0)
HOME = (2.0, 1.0, 0.0)
COMMANDS = [t for t in Trigger if t not in (Trigger.TELEOP_LAPSED, Trigger.ROUTE_ENDED, Trigger.HAZARD)]

# -- the table alone ---------------------------------------------------------------------------


def test_the_table_is_total() -> None:
    assert len(TRANSITIONS) == len(PilotState) * len(Trigger)
    for s in PilotState:
        for t in Trigger:
            assert isinstance(next_state(s, t), Transition | Refused), (s, t)


def test_a_table_with_a_gap_does_not_load() -> None:
    rows = {t: {s: next_state(s, t) for s in PilotState} for t in Trigger}
    del rows[Trigger.PAUSE][S.HOMING]
    with pytest.raises(AssertionError, match="homing x pause"):
        pilot_machine._total(rows)


def test_every_refusal_has_a_reason_and_only_estop_twice_is_a_duplicate() -> None:
    for (s, t), outcome in TRANSITIONS.items():
        if isinstance(outcome, Refused):
            assert outcome.reason, (s, t)
            assert outcome.result == CommandResult(outcome.status, outcome.reason)
            dup = (s, t) == (S.ESTOP, Trigger.ESTOP)
            assert outcome.status is (CommandStatus.DUPLICATE if dup else CommandStatus.REJECTED), (s, t)


def test_estop_refuses_every_command_but_stop_release_and_payload_off() -> None:
    allowed = {Trigger.STOP, Trigger.HALT, Trigger.ESTOP_RELEASE, Trigger.PAYLOAD_OFF}
    for t in COMMANDS:
        outcome = next_state(S.ESTOP, t)
        assert isinstance(outcome, Transition) == (t in allowed), t
        if isinstance(outcome, Transition) and t is not Trigger.ESTOP_RELEASE:
            assert outcome.target is S.ESTOP  # latched until released
    assert next_state(S.ESTOP, Trigger.ESTOP_RELEASE) == Transition(
        S.IDLE, (Announce(EventKind.ESTOP_RELEASED, "estop_release", "e-stop released by {sender}"),)
    )
    # Every state can latch it.
    for s in PilotState:
        if s is not S.ESTOP:
            outcome = next_state(s, Trigger.ESTOP)
            assert isinstance(outcome, Transition) and outcome.target is S.ESTOP


def test_effects_keep_what_each_state_carries() -> None:
    """A teleop command exactly in MANUAL, a route exactly in the go-to states: every transition
    that enters or leaves one of them takes or drops its data, and no effect acts on data the state
    does not have."""
    for (s, t), outcome in TRANSITIONS.items():
        if not isinstance(outcome, Transition):
            continue
        fx, target = outcome.effects, outcome.target
        cancels = any(isinstance(e, Cancel) for e in fx)
        ends = Do.END_ROUTE in fx
        starts = Do.START_ROUTE in fx
        # The route held.
        if cancels or ends or Do.RESUME_ROUTE in fx:
            assert s.has_route, (s, t)
        if s.has_route and not target.has_route:
            assert cancels or ends, (s, t)
        if not s.has_route and target.has_route:
            assert starts, (s, t)
        if starts:
            assert target.has_route, (s, t)
        if s.has_route and target.has_route and s.driving_route != target.driving_route:
            assert t in (Trigger.PAUSE, Trigger.RESUME, Trigger.ORDER_NEW, Trigger.RETURN_HOME, Trigger.RETRACE), (s, t)
        # The teleop command.
        if Do.TAKE_TELEOP in fx:
            assert target is S.MANUAL, (s, t)
        if target is S.MANUAL:
            assert Do.TAKE_TELEOP in fx or (s is S.MANUAL and t is not Trigger.TELEOP), (s, t)
        if Do.DROP_TELEOP in fx:
            assert s is S.MANUAL, (s, t)
        if s is S.MANUAL and target is not S.MANUAL:
            assert Do.DROP_TELEOP in fx, (s, t)
    for s in PilotState:
        if s not in (S.GOTO, S.GOTO_PAUSED):
            outcome = next_state(s, Trigger.ORDER_UPDATE)
            assert isinstance(outcome, Refused) and outcome.reason in ("no order to update", "e-stop latched"), s


def test_states_map_onto_the_reported_modes() -> None:
    assert {s: s.mode for s in PilotState} == {
        S.IDLE: OperatingMode.IDLE,
        S.MANUAL: OperatingMode.MANUAL,
        S.GOTO: OperatingMode.AUTOMATIC,
        S.HOMING: OperatingMode.AUTOMATIC,
        S.GOTO_PAUSED: OperatingMode.PAUSED,
        S.HOMING_PAUSED: OperatingMode.PAUSED,
        S.ESTOP: OperatingMode.ESTOP,
    }


# -- the pilot against the table ---------------------------------------------------------------


def pilot_in(state: PilotState) -> Pilot:
    """A pilot brought to ``state`` through its public commands (at t = 0)."""
    p = Pilot(home=HOME)
    if state is S.MANUAL:
        p.teleop(0.0, 0.2, 0.0, 2.0, "op")
    elif state in (S.GOTO, S.GOTO_PAUSED):
        p.order(0.0, "o1", 0, 2.0, 0.0, None, "op")
    elif state in (S.HOMING, S.HOMING_PAUSED):
        p.action(0.0, ActionKind.RETURN_HOME, "op")
    elif state is S.ESTOP:
        p.action(0.0, ActionKind.ESTOP, "op")
    if state in (S.GOTO_PAUSED, S.HOMING_PAUSED):
        p.action(0.0, ActionKind.PAUSE, "op")
    p.tick(0.0, HERE, CLEAR)  # deliver the events so far
    assert p.state is state
    return p


SEND: dict[Trigger, Callable[[Pilot, float], CommandResult]] = {
    Trigger.TELEOP: lambda p, t: p.teleop(t, 0.1, 0.0, 0.5, "op"),
    Trigger.ORDER_NEW: lambda p, t: p.order(t, "o2", 0, 1.0, 1.0, None, "op"),
    Trigger.ORDER_UPDATE: lambda p, t: p.order(t, "o1", 1, 3.0, 0.0, None, "op"),
    **{Trigger(k.value): functools.partial(lambda k, p, t: p.action(t, k, "op"), k) for k in ActionKind},
    Trigger.RETRACE: lambda p, t: p.retrace(t, [(0.5, 0.0), (0.0, 0.0)], "comms"),
    Trigger.HALT: lambda p, t: p.halt(t, "comms"),
}
# An update needs the order held; elsewhere the same command is ORDER_NEW (the table refuses the rest).
CASES = [(s, t) for s in PilotState for t in COMMANDS if t is not Trigger.ORDER_UPDATE or s in (S.GOTO, S.GOTO_PAUSED)]


@pytest.mark.parametrize(("state", "trigger"), CASES)
def test_the_pilot_does_what_the_table_declares(state: PilotState, trigger: Trigger) -> None:
    p = pilot_in(state)
    goal = p.goal
    outcome = next_state(state, trigger)
    result = SEND[trigger](p, 1.0)
    out = p.tick(1.0, HERE, CLEAR)
    if isinstance(outcome, Refused):
        assert (result.status, result.reason) == (outcome.status, outcome.reason)
        assert p.state is state and p.goal == goal  # never a silent change
        assert out.events == [] and out.payload_requests == []
        return
    assert result.accepted, result
    assert p.state is outcome.target and out.mode is outcome.target.mode
    expected = []
    for e in outcome.effects:
        if isinstance(e, Cancel):
            expected.append((EventKind.GOAL_CANCELLED, e.reason))
        elif isinstance(e, Announce):
            expected.append((e.kind, e.reason))
    # (A retrace brings its path along: its first step reports it, as a planned go-to would.)
    assert [(e.kind, e.reason) for e in out.events if e.kind is not EventKind.PATH_PLANNED] == expected
    # CUT_PAYLOAD: every payload off (the deadman only for a moving teleop, as this one is).
    assert len(out.payload_requests) == (Do.PASS_PAYLOAD in outcome.effects) + (Do.CUT_PAYLOAD in outcome.effects)
    if Do.CUT_PAYLOAD in outcome.effects:
        assert out.payload_requests[-1].on is False
    assert (p.goal is not None) == outcome.target.has_route
    assert (p.next_deadline() is not None) == (outcome.target is S.MANUAL)


def test_an_order_seen_before_but_no_longer_held_is_new_not_an_update() -> None:
    p = pilot_in(S.GOTO)
    p.action(1.0, ActionKind.CANCEL, "op")
    assert p.state is S.IDLE
    assert p.order(2.0, "o1", 1, 1.0, 0.0, None, "op").accepted
    assert p.state is S.GOTO


# -- each state's behaviour --------------------------------------------------------------------


def drive(p: Pilot, body: Unicycle, t: float, seconds: float, inputs: GuardInputs = CLEAR) -> tuple[float, list]:
    events = []
    end = t + seconds
    while t < end - 1e-9:
        out = p.tick(t, body.pose, inputs)
        events.extend(out.events)
        body.step(out.v, out.omega, 0.02)
        t += 0.02
    return t, events


def test_estop_latches_through_time_and_commands_until_released() -> None:
    p = pilot_in(S.GOTO)
    p.action(1.0, ActionKind.ESTOP, "op")
    for k in range(100):
        out = p.tick(1.0 + 0.1 * k, HERE, CLEAR)
        assert out.v == 0.0 and out.omega == 0.0 and out.estop and p.state is S.ESTOP
    assert p.action(12.0, ActionKind.STOP, "op").accepted  # a stop under e-stop does not release it
    assert p.tick(12.0, HERE, CLEAR).estop and p.state is S.ESTOP
    assert p.action(13.0, ActionKind.ESTOP_RELEASE, "op").accepted
    assert p.state is S.IDLE and p.goal is None  # the cancelled order does not come back


def test_teleop_lapses_to_idle_on_its_ttl_and_a_stop_drops_it_at_once() -> None:
    p = Pilot()
    p.teleop(0.0, 0.2, 0.0, 0.3, "op")
    assert p.tick(0.29, HERE, CLEAR).mode is OperatingMode.MANUAL
    out = p.tick(0.3, HERE, CLEAR)
    assert p.state is S.IDLE and [e.kind for e in out.events] == [EventKind.DEADMAN_STOP]
    assert "0.30 s" in out.events[0].text and p.next_deadline() is None
    p.teleop(1.0, 0.2, 0.0, 2.0, "op")
    p.action(1.1, ActionKind.STOP, "op")
    out = p.tick(1.1, HERE, CLEAR)
    assert p.state is S.IDLE and out.v == 0.0 and [e.kind for e in out.events] == [EventKind.STOPPED]


def test_pause_holds_the_order_and_an_update_keeps_it_paused() -> None:
    p = Pilot()
    body = Unicycle()
    p.order(0.0, "o1", 0, 3.0, 0.0, None, "op")
    t, _ = drive(p, body, 0.0, 1.0)
    p.action(t, ActionKind.PAUSE, "op")
    assert p.order(t, "o1", 1, 1.5, 1.0, None, "op").accepted  # a new goal for the held order
    assert p.state is S.GOTO_PAUSED and p.goal == (1.5, 1.0, pytest.approx(math.nan, nan_ok=True))
    t, events = drive(p, body, t, 2.0)
    assert [e.kind for e in events] == [EventKind.PAUSED] and p.order_update_id == 1
    x = body.x
    t, _ = drive(p, body, t, 1.0)
    assert abs(body.x - x) < 1e-9  # held still
    p.action(t, ActionKind.RESUME, "op")
    t, events = drive(p, body, t, 20.0)
    assert [e.kind for e in events] == [EventKind.RESUMED, EventKind.GOAL_REACHED]
    assert math.hypot(body.x - 1.5, body.y - 1.0) < 0.01


def test_cancel_clears_the_order_paused_or_not() -> None:
    for state in (S.GOTO, S.GOTO_PAUSED, S.HOMING, S.HOMING_PAUSED):
        p = pilot_in(state)
        assert p.action(1.0, ActionKind.CANCEL, "op").accepted
        out = p.tick(1.0, HERE, CLEAR)
        assert p.state is S.IDLE and out.goal is None and out.order_id is None and p.order_update_id == 0
        assert [(e.kind, e.reason) for e in out.events] == [(EventKind.GOAL_CANCELLED, "cancel")]
        assert p.action(1.1, ActionKind.CANCEL, "op").reason == "no order to cancel"


def test_return_home_replaces_an_order_pauses_and_resumes() -> None:
    p = Pilot(home=HOME)
    body = Unicycle()
    p.order(0.0, "o1", 0, -2.0, 0.0, None, "op")
    t, _ = drive(p, body, 0.0, 0.5)
    p.action(t, ActionKind.RETURN_HOME, "op")
    out = p.tick(t, body.pose, CLEAR)
    assert [(e.kind, e.reason, e.order_id) for e in out.events] == [(EventKind.GOAL_CANCELLED, "replaced", "o1")]
    assert p.state is S.HOMING and out.order_id is None and out.goal == HOME
    t, _ = drive(p, body, t, 1.0)
    p.action(t, ActionKind.PAUSE, "op")
    assert p.state is S.HOMING_PAUSED and p.mode is OperatingMode.PAUSED
    # Home again while paused: the way home afresh, driven, nothing cancelled.
    p.action(t, ActionKind.RETURN_HOME, "op")
    t, events = drive(p, body, t, 25.0)
    assert [e.kind for e in events] == [EventKind.PAUSED, EventKind.GOAL_REACHED]
    assert events[-1].order_id is None and p.state is S.IDLE
    assert math.hypot(body.x - HOME[0], body.y - HOME[1]) < 0.01


def test_a_cliff_ends_a_go_to_under_way_but_not_a_paused_one() -> None:
    cliff = GuardInputs(cliff=True)
    p = pilot_in(S.GOTO_PAUSED)
    out = p.tick(1.0, HERE, cliff)
    assert [e.kind for e in out.events] == [EventKind.CLIFF] and p.state is S.GOTO_PAUSED
    p = pilot_in(S.HOMING)
    out = p.tick(1.0, HERE, cliff)
    assert [(e.kind, e.reason) for e in out.events] == [(EventKind.CLIFF, "cliff"), (EventKind.GOAL_FAILED, "cliff")]
    assert p.state is S.IDLE
    p = pilot_in(S.MANUAL)
    out = p.tick(1.0, HERE, cliff)
    assert p.state is S.MANUAL and out.v == 0.0 and out.field_violation  # the guard holds it, the mode stays
