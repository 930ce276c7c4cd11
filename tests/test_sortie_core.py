"""The rescue sortie's agent cores (issue 15): home, contact and the comms-loss policy, the latching
e-stop (remote and the board's button), payload off, the home button, BoardStatus and its faults."""

from __future__ import annotations

import math
from typing import Any

import pytest

from fleetlink.agent.contact import ContactKeeper
from fleetlink.agent.core import AgentCore, BoardView, Output
from fleetlink.agent.home import HomeKeeper
from fleetlink.agent.pilot import Pilot, PilotState
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.geometry import simplify
from fleetlink.shared.messages import (
    Ack,
    AckResult,
    Action,
    ActionType,
    BoardStatus,
    CommsPolicy,
    EStop,
    Event,
    HomeSource,
    InstantActions,
    KeyValue,
    LeaseRequest,
    LinkName,
    LinkStatus,
    Order,
    State,
    Teleop,
)

# -- home ------------------------------------------------------------------------------------------


def test_home_is_where_the_robot_first_localised_and_only_then() -> None:
    h = HomeKeeper()
    assert h.home is None
    first = h.localised(2.0, 3.0)
    assert first is not None and (first.x, first.y, first.source) == (2.0, 3.0, HomeSource.LOCALISED)
    assert math.isnan(first.theta)  # arrive with any heading
    assert h.localised(5.0, 5.0) is None and h.home == first


def test_a_dock_is_home_from_the_start_and_an_operator_overrides_both() -> None:
    h = HomeKeeper((1.0, -1.0, math.pi / 2))
    assert h.home is not None and h.home.source is HomeSource.DOCK
    assert h.localised(9.0, 9.0) is None  # the first fix does not move a dock
    set_ = h.set(4.0, 4.0)
    assert (set_.x, set_.y, set_.source) == (4.0, 4.0, HomeSource.OPERATOR)


@pytest.mark.parametrize(
    ("x", "y", "why"), [(math.nan, 0.0, "finite"), (0.0, math.inf, "finite"), (2e5, 0.0, "outside")]
)
def test_a_home_that_cannot_be_one_is_refused_with_the_reason(x: float, y: float, why: str) -> None:
    h = HomeKeeper()
    with pytest.raises(ValueError, match=why):
        h.set(x, y)
    assert h.home is None


# -- contact ------------------------------------------------------------------------------------------


def test_silence_is_a_lost_contact_only_while_somebody_holds_the_lease() -> None:
    c = ContactKeeper(CommsPolicy.STOP, timeout_s=5.0)
    assert c.tick(100.0, engaged=True) is None  # never heard anyone: nobody to lose
    c.heard(0.0, 0.0, 0.0)
    assert c.tick(4.9, engaged=True) is None
    assert c.tick(10.0, engaged=False) is None  # nobody is working with the robot
    lost = c.tick(10.0, engaged=True)
    assert lost is not None and lost.policy is CommsPolicy.STOP and lost.path == ()
    assert c.lost and c.tick(11.0, engaged=True) is None  # once per episode
    c.action = "stopped"
    back = c.heard(20.0, 0.0, 0.0)
    assert back is not None and back.out_s == pytest.approx(10.0)
    assert "stopped where it was" in back.text and not c.lost and c.action == ""


def test_retrace_goes_back_along_the_trail_newest_first_to_where_an_operator_was_heard() -> None:
    c = ContactKeeper(CommsPolicy.RETRACE, timeout_s=5.0, spacing_m=0.2)
    for i in range(11):  # 0..2 m along x, then heard at (2, 0)
        c.moved(0.2 * i, 0.0)
    c.heard(1.0, 2.0, 0.0)
    for i in range(1, 11):  # then 2 m up along y, into the dead room
        c.moved(2.0, 0.2 * i)
    lost = c.tick(10.0, engaged=True)
    assert lost is not None
    path = lost.path
    assert path[0] == pytest.approx((2.0, 2.0))
    assert path[-1] == pytest.approx((2.0, 0.0))  # where it last heard an operator
    assert len(path) == 2  # a straight way back is two points, not ten
    assert all(x == pytest.approx(2.0) for x, _ in path)  # never beyond the contact point


def test_retrace_with_a_trail_shorter_than_the_way_goes_as_far_back_as_it_reaches() -> None:
    c = ContactKeeper(CommsPolicy.RETRACE, spacing_m=0.15, max_points=5)
    c.heard(0.0, 0.0, 0.0)
    for i in range(1, 21):
        c.moved(0.0, 0.2 * i)
    path = c.retrace_path()
    assert path[0] == pytest.approx((0.0, 4.0))
    assert path[-1] == pytest.approx((0.0, 3.2))  # the oldest point kept, not a jump to (0, 0)


def test_simplify_keeps_corners_and_drops_points_on_a_line() -> None:
    pts = [(0.0, 0.0), (1.0, 0.0), (2.0, 0.0), (2.0, 1.0), (2.0, 2.0)]
    assert simplify(pts, 0.05) == [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0)]


def test_an_unknown_policy_is_refused_naming_the_choices() -> None:
    with pytest.raises(ValueError, match="stop, retrace, home"):
        ContactKeeper().set_policy("fly")


# -- the core: e-stop, home, comms loss, board status ------------------------------------------------

BOARD = BoardView(
    connected=True, left_m=0.0, right_m=0.0, gyro_yaw=0.0, odom_t=0.0, battery_percent=80.0, battery_known=True
)


class Sortie:
    """One agent core and two operators; the robot's pose is what the test says it is."""

    def __init__(self, **kw: Any) -> None:
        self.clock = SimClock()
        self.core = AgentCore("r1", self.clock, Pilot(), **kw)
        self.pose = (0.0, 0.0, 0.0)
        self.core._map_pose = lambda: self.pose  # type: ignore[method-assign]
        self.counters = {op: wire.HeaderCounter(self.clock, robot="r1", sender=op) for op in ("op-a", "op-b")}

    def send(self, op: str, cls: type[wire.Message], **fields: Any) -> Output:
        msg = self.counters[op].make(cls, **fields)
        return self.core.on_input(LinkName.ZENOH, wire.key_of(msg), wire.encode(msg), self.clock.now())

    def action(self, op: str, kind: ActionType, **params: str) -> Ack:
        kvs = tuple(KeyValue(key=k, value=v) for k, v in params.items())
        out = self.send(op, InstantActions, actions=(Action(actionId="a", actionType=kind, actionParameters=kvs),))
        return next(m for m, _ in out.messages if isinstance(m, Ack))

    def teleop(self, op: str, v: float = 0.2) -> Ack:
        out = self.send(op, Teleop, v=v, omega=0.0, ttl_s=0.5)
        return next(m for m, _ in out.messages if isinstance(m, Ack))

    def tick(self, dt: float = 0.02, board: BoardView = BOARD) -> Output:
        self.clock.advance(dt)
        return self.core.tick(self.clock.now(), board)

    def state(self) -> State:
        return self.core._state(self.clock.now())


def events(out: Output) -> list[str]:
    return [m.kind for m, _ in out.messages if isinstance(m, Event)]


def test_an_estop_latches_refuses_motion_switches_the_payload_off_and_needs_an_authorised_release() -> None:
    s = Sortie()
    assert s.teleop("op-a").result is AckResult.ACCEPTED  # op-a drives: it holds the lease
    out = s.send(
        "op-b", InstantActions, actions=(Action(actionId="e", actionType=ActionType.ESTOP, actionParameters=()),)
    )
    assert s.core.pilot.state is PilotState.ESTOP and out.velocity == (0.0, 0.0)
    assert any(not r.on for r in out.payload)  # every payload off
    assert s.state().safetyState.eStop is EStop.REMOTE
    assert s.teleop("op-a").result is AckResult.REJECTED  # nothing moves until released
    refused = s.action("op-b", ActionType.ESTOP_RELEASE)  # op-b does not hold the lease
    assert refused.result is AckResult.REJECTED and "op-a" in refused.reason
    assert s.core.pilot.estop
    assert s.action("op-a", ActionType.ESTOP_RELEASE).result is AckResult.ACCEPTED
    assert not s.core.pilot.estop and s.state().safetyState.eStop is EStop.NONE


def test_the_boards_estop_button_latches_it_as_manual_until_released_on_the_robot_and_by_an_operator() -> None:
    s = Sortie()
    s.tick()
    out = s.tick(board=_with(estop_button=True))
    assert s.core.pilot.estop and s.state().safetyState.eStop is EStop.MANUAL
    assert any(not r.on for r in out.payload)
    held = s.action("op-a", ActionType.ESTOP_RELEASE)
    assert held.result is AckResult.REJECTED and "button" in held.reason
    s.tick(board=_with(estop_button=False))
    assert s.core.pilot.estop  # the latch outlives the button
    assert s.action("op-a", ActionType.ESTOP_RELEASE).result is AckResult.ACCEPTED
    assert not s.core.pilot.estop


def _with(**fields: Any) -> BoardView:
    import dataclasses

    return dataclasses.replace(BOARD, **fields)


def test_a_stop_switches_every_payload_off_and_a_zero_teleop_lapsing_does_not() -> None:
    s = Sortie()
    s.action("op-a", ActionType.PAYLOAD, on="true")
    s.teleop("op-a", v=0.0)
    outs = [s.tick(0.1) for _ in range(10)]  # the zero twist lapses: the operator stopped driving
    assert not any(any(not r.on for r in o.payload) for o in outs)
    s.teleop("op-a", v=0.2)
    outs = [s.tick(0.1) for _ in range(10)]  # a moving command lapses: the deadman
    assert any(any(not r.on for r in o.payload) for o in outs) and any("deadman_stop" in events(o) for o in outs)
    out = s.send(
        "op-b", InstantActions, actions=(Action(actionId="s", actionType=ActionType.STOP, actionParameters=()),)
    )
    assert any(not r.on for r in out.payload)


def test_home_is_the_first_localised_pose_and_the_home_button_returns_there(monkeypatch: pytest.MonkeyPatch) -> None:
    s = Sortie()
    s.pose = (3.0, 4.0, 0.0)
    monkeypatch.setattr(type(s.core.fusion), "position_initialized", property(lambda _self: True))
    s.tick()
    home = s.state().home
    assert home is not None and (home.x, home.y, home.source) == (3.0, 4.0, HomeSource.LOCALISED)
    s.pose = (6.0, 4.0, 0.0)
    out = s.tick(board=_with(home_requests=1))
    assert s.core.pilot.state is PilotState.HOMING and "home_button" in events(out)
    assert s.core.pilot.goal is not None and s.core.pilot.goal[:2] == (3.0, 4.0)


def test_set_home_here_or_at_coordinates_and_refuses_what_cannot_be_home() -> None:
    s = Sortie()
    not_yet = s.action("op-a", ActionType.SET_HOME)
    assert not_yet.result is AckResult.REJECTED and "not localised" in not_yet.reason
    assert s.action("op-a", ActionType.SET_HOME, x="1.5", y="-2", theta_deg="90").result is AckResult.ACCEPTED
    home = s.state().home
    assert home is not None and (home.x, home.y, home.source) == (1.5, -2.0, HomeSource.OPERATOR)
    assert home.theta == pytest.approx(math.pi / 2)
    for bad in ({"x": "nan", "y": "0"}, {"x": "1"}, {"x": "1", "y": "1", "z": "0"}, {"x": "1e9", "y": "0"}):
        ack = s.action("op-a", ActionType.SET_HOME, **bad)
        assert ack.result is AckResult.REJECTED and ack.reason
    assert s.state().home == home  # nothing disturbed


def test_out_of_contact_a_robot_retraces_to_where_it_last_heard_an_operator_and_reports_when_back() -> None:
    s = Sortie(contact=ContactKeeper(CommsPolicy.RETRACE, timeout_s=2.0))
    s.action("op-a", ActionType.PAYLOAD, on="true")
    s.send("op-a", LeaseRequest, duration_s=60.0, release=False)  # op-a holds the lease, heard at (0, 0)
    for i in range(1, 11):  # it drives on into the dead room, hearing nothing
        s.pose = (0.2 * i, 0.0, 0.0)
        s.tick(0.1)
    outs = [s.tick(0.1) for _ in range(12)]
    lost = [o for o in outs if "contact_lost" in events(o)]
    assert len(lost) == 1 and any(not r.on for r in lost[0].payload)  # the payload off while out of contact
    assert s.core.pilot.state is PilotState.HOMING  # a retrace is a way home of its own kind
    assert s.core.pilot.goal is not None and s.core.pilot.goal[:2] == pytest.approx((0.0, 0.0))
    st = s.state()
    assert st.contact.lost and st.contact.action == "retracing" and st.contact.policy is CommsPolicy.RETRACE
    back = s.send("op-a", LeaseRequest, duration_s=60.0, release=False)
    assert "contact_regained" in events(back)
    assert s.core.pilot.state is PilotState.IDLE  # the operator is back in charge
    assert not s.state().contact.lost


def test_the_policy_is_changed_by_an_operator_and_an_unknown_one_is_refused() -> None:
    s = Sortie()
    assert s.action("op-a", ActionType.SET_COMMS_POLICY, policy="home").result is AckResult.ACCEPTED
    assert s.state().contact.policy is CommsPolicy.HOME
    bad = s.action("op-a", ActionType.SET_COMMS_POLICY, policy="fly")
    assert bad.result is AckResult.REJECTED and "fly" in bad.reason
    assert s.state().contact.policy is CommsPolicy.HOME


def test_board_status_goes_out_at_1_hz_and_at_once_on_a_change() -> None:
    s = Sortie()
    first = [m for m, _ in s.tick().messages if isinstance(m, BoardStatus)]
    assert len(first) == 1 and first[0].connected
    quiet = [m for _ in range(10) for m, _ in s.tick(0.05).messages if isinstance(m, BoardStatus)]
    assert quiet == []
    changed = [m for m, _ in s.tick(0.05, _with(payload_on=True)).messages if isinstance(m, BoardStatus)]
    assert len(changed) == 1 and changed[0].uv_lamp
    later = [
        m for _ in range(25) for m, _ in s.tick(0.05, _with(payload_on=True)).messages if isinstance(m, BoardStatus)
    ]
    assert len(later) == 1  # the next one a second later
    wire.encode(later[0])


def test_faults_whose_condition_is_over_are_cleared_once_and_the_watchdog_trip_counted() -> None:
    s = Sortie()
    faults = ((0x0001, "core disconnected"), (0x0002, "motor stall"), (0x0003, "disinfectant tank empty"))
    out = s.tick(board=_with(faults=faults, tank_percent=0.0))
    assert out.clear_faults == [0x0001]  # the stall stays for a person; the tank is still empty
    assert s.core.watchdog_trips == 1
    assert s.tick(board=_with(faults=faults, tank_percent=0.0)).clear_faults == []  # asked once
    assert s.tick(board=_with(faults=faults[1:], tank_percent=40.0)).clear_faults == [0x0003]  # refilled
    status = [m for m, _ in s.tick(1.0, _with(faults=faults[1:2])).messages if isinstance(m, BoardStatus)]
    assert [f.code for f in status[0].faults] == [2] and status[0].watchdog_trips == 1


def test_the_estop_outlives_reconnects_and_a_restarted_console() -> None:
    s = Sortie()
    s.action("op-a", ActionType.ESTOP)
    s.core.set_links(LinkStatus(zenoh=False, mqtt=False), s.clock.now())  # both links drop...
    s.tick(1.0)
    s.core.set_links(LinkStatus(zenoh=True, mqtt=True), s.clock.now())  # ...and come back
    s.tick(1.0)
    # The console restarts: a new counter (headerIds from 0 again), a lease request, a drive key.
    s.counters["op-a"] = wire.HeaderCounter(s.clock, robot="r1", sender="op-a")
    s.send("op-a", LeaseRequest, duration_s=60.0, release=False)
    assert s.teleop("op-a").result is AckResult.REJECTED
    assert s.core.pilot.estop and s.state().safetyState.eStop is EStop.REMOTE


# -- review findings: who counts as contact, what the policy keeps, long timeouts ------------------


def _lost(s: Sortie, outs: list[Output]) -> bool:
    return any("contact_lost" in events(o) for o in outs)


def test_a_refused_senders_repeated_command_is_no_contact() -> None:
    s = Sortie(contact=ContactKeeper(CommsPolicy.RETRACE, timeout_s=2.0), operators=("op-a",))
    s.send("op-a", LeaseRequest, duration_s=60.0, release=False)
    for i in range(1, 6):
        s.pose = (0.2 * i, 0.0, 0.0)
        s.tick(0.1)
    assert _lost(s, [s.tick(0.1) for _ in range(20)]) and s.core.pilot.retracing
    msg = s.counters["op-b"].make(
        InstantActions, actions=(Action(actionId="p", actionType=ActionType.PAUSE, actionParameters=()),)
    )
    for _ in range(2):  # refused, then the same bytes again: a duplicate of a refused command
        out = s.core.on_input(LinkName.ZENOH, wire.key_of(msg), wire.encode(msg), s.clock.now())
        assert "contact_regained" not in events(out)
    assert s.state().contact.lost and s.core.pilot.retracing


def test_contact_lost_while_returning_home_goes_on_home() -> None:
    s = Sortie(contact=ContactKeeper(CommsPolicy.RETRACE, timeout_s=2.0))
    s.core.home.set(-5.0, 0.0)
    s.core.pilot.set_home((-5.0, 0.0, math.nan))
    s.send("op-a", LeaseRequest, duration_s=60.0, release=False)
    s.pose = (2.0, 0.0, 0.0)
    s.send("op-a", Order, orderId="h", orderUpdateId=0, goal=None, returnHome=True)
    outs = [s.tick(0.1) for _ in range(30)]
    assert _lost(s, outs)
    goal = s.core.pilot.goal
    assert goal is not None and goal[:2] == (-5.0, 0.0) and not s.core.pilot.retracing
    assert s.state().contact.action == "homing"


def test_payload_on_loss_keeps_the_payload_on_under_the_stop_policy() -> None:
    s = Sortie(contact=ContactKeeper(CommsPolicy.STOP, timeout_s=2.0, payload_on_loss=True))
    s.send("op-a", LeaseRequest, duration_s=60.0, release=False)
    s.teleop("op-a", v=0.2)
    outs = [s.tick(0.1) for _ in range(30)]
    assert _lost(s, outs)
    lost = next(o for o in outs if "contact_lost" in events(o))
    assert not any(not r.on for r in lost.payload)  # kept on, as configured
    assert s.core.pilot.state is PilotState.IDLE


def test_a_lease_running_out_in_the_silence_is_still_lost_contact() -> None:
    s = Sortie(contact=ContactKeeper(CommsPolicy.STOP, timeout_s=90.0))
    s.send("op-a", LeaseRequest, duration_s=60.0, release=False)
    outs = [s.tick(1.0) for _ in range(100)]  # the lease runs out at 60 s, the timeout at 90 s
    assert _lost(s, outs)
    s2 = Sortie(contact=ContactKeeper(CommsPolicy.STOP, timeout_s=5.0))
    s2.send("op-a", LeaseRequest, duration_s=60.0, release=False)
    s2.send("op-a", LeaseRequest, duration_s=0.0, release=True)  # given back: nobody to lose
    assert not _lost(s2, [s2.tick(1.0) for _ in range(20)])


def test_return_home_without_a_home_is_refused_with_the_reason() -> None:
    s = Sortie()
    out = s.send("op-a", Order, orderId="h", orderUpdateId=0, goal=None, returnHome=True)
    ack = next(m for m, _ in out.messages if isinstance(m, Ack))
    assert ack.result is AckResult.REJECTED and "no home yet" in ack.reason
    assert s.core.pilot.state is PilotState.IDLE


def test_a_fault_still_listed_is_asked_again_after_a_while() -> None:
    s = Sortie()
    faults = ((0x0001, "core disconnected"),)
    assert s.tick(board=_with(faults=faults)).clear_faults == [1]
    assert s.tick(1.0, _with(faults=faults)).clear_faults == []
    assert s.tick(5.0, _with(faults=faults)).clear_faults == [1]  # the clear was lost: again
    assert s.core.watchdog_trips == 1  # one trip, asked twice
