"""The command's hot path (issue 18): a command is decided on the thread that received it and its
velocity written to the board from there -- and it still goes through the guard, and the
deadman still stops the robot.

* ``ZenohEndpoint(direct=True)`` hands a sample that finds nothing queued to its receiver on
  zenoh's own thread; samples still reach the receiver one at a time, in the order they came;
* ``BoardSession(direct=True)`` writes a new velocity from the caller's thread when no exchange is
  in flight, and its own thread takes the board's reply; with an exchange in flight the velocity
  goes the old way, woken and sent by the session first thing;
* the real-time agent has both on: a teleop reaches the board without a thread hop, a wall in
  front keeps the wheels still, and a teleop that is not renewed stops them.

Timings are bench/latency.py's business; these tests assert behaviour only.
"""

from __future__ import annotations

import itertools
import threading

from fleetlink.agent.board.session import BoardSession
from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.ports import InProcessPort
from fleetlink.field.board import SimulatedBoard
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.shared import keys
from fleetlink.shared.clock import SimClock, SystemClock
from fleetlink.shared.messages import AckResult, Teleop
from tests.harness import wait_until
from tests.harness.zenoh_peers import loopback_endpoint
from tests.test_agent_links import Rig, rig  # noqa: F401  (the fixture)

# -- the board session ------------------------------------------------------------------------------


class Served:
    """A simulated board in lockstep with a session, noting every request it answered."""

    def __init__(self, *, direct: bool) -> None:
        self.clock = SimClock(start=10.0)
        self.board = SimulatedBoard(now=self.clock.now())
        self.board.start_clock(self.clock.now())
        self.requests: list[type] = []
        serve = self.board._serve

        def spy(req: p.Request) -> p.Reply:
            self.requests.append(type(req))
            return serve(req)

        self.board._serve = spy  # type: ignore[method-assign]
        self.ports: list[InProcessPort] = []
        self.session = BoardSession(self._open, self.clock, seed=3, direct=direct)

    def _open(self) -> InProcessPort:
        port = self.board.in_process_port(self.clock)
        self.ports.append(port)
        return port

    def run(self, duration: float) -> None:
        end = self.clock.now() + duration
        while self.clock.now() < end:
            nxt = self.session.tick()
            self.clock.set(min(end, max(nxt, self.clock.now())))
            self.board.step(self.clock.now())


def test_a_direct_velocity_is_written_by_the_caller_and_answered_to_the_session() -> None:
    s = Served(direct=True)
    s.run(0.2)  # connected, polling
    s.requests.clear()
    s.session.set_velocity(0.3, 0.0)
    # Written at once, by this thread: the board has it before the session's thread runs at all.
    assert s.requests == [p.SetVelocity]
    assert s.board.state.set_left > 0.0
    assert not s.session.urgent and s.session.direct_sends == 1
    assert s.session.snapshot.command == (0.0, 0.0)  # its reply is not taken yet
    s.session.tick()  # the session takes the reply first thing; it counted as the motion poll
    assert s.session.snapshot.command == (0.3, 0.0)
    assert s.requests.count(p.SetVelocity) == 1
    s.run(1.0)  # and polls on as before, without a timeout or a stale reply
    client = s.session.client
    assert client is not None
    assert client.stats.timeouts == 0 and client.stats.stale_replies == 0
    assert s.session.snapshot.connected and s.session.snapshot.last_error == ""
    assert s.board.state.v_left > 0.25
    s.session.stop()


def test_with_an_exchange_in_flight_the_velocity_waits_for_the_session() -> None:
    s = Served(direct=True)
    s.run(0.2)
    s.requests.clear()
    with s.session._io:  # the session's thread is in the middle of an exchange
        s.session.set_velocity(0.2, 0.0)
    assert s.requests == [] and s.board.state.set_left == 0.0
    assert s.session.urgent and s.session.direct_sends == 0
    s.session.tick()  # the velocity first, before anything else due
    assert s.requests[0] is p.SetVelocity and s.board.state.set_left > 0.0
    s.session.stop()


def test_a_direct_velocity_lost_on_a_cut_line_goes_again_once_the_board_is_back() -> None:
    s = Served(direct=True)
    s.run(0.2)
    s.ports[-1].cut = True  # the cable is cut: writes vanish, nothing comes back
    s.session.set_velocity(0.2, 0.0)
    assert s.session.direct_sends == 1 and s.board.state.set_left == 0.0
    # The reply never comes: timeouts, retries, the session gives the link up and opens a new
    # port (not cut), and the velocity asked for goes out again on it.
    s.run(3.0)
    assert s.session.snapshot.connects == 2 and len(s.ports) == 2
    assert s.session.snapshot.connected
    assert s.board.state.set_left > 0.0
    assert s.session.snapshot.command == (0.2, 0.0)
    s.session.stop()


def test_without_direct_the_velocity_goes_with_the_next_tick() -> None:
    """Lockstep runs (site/lockstep.py) keep the session's own order of steps."""
    s = Served(direct=False)
    s.run(0.2)
    s.requests.clear()
    s.session.set_velocity(0.2, 0.0)
    assert s.requests == [] and s.session.urgent
    s.session.tick()
    assert s.requests[0] is p.SetVelocity
    s.session.stop()


# -- the Zenoh endpoint -----------------------------------------------------------------------------


def test_direct_delivery_is_for_the_holder_one_sample_at_a_time_in_order() -> None:
    endpoint = loopback_endpoint()
    rx, tx = ZenohEndpoint(listen=[endpoint], direct=True), ZenohEndpoint(connect=[endpoint])
    holder, other = keys.sender_key("r1", "teleop", "op-a"), keys.sender_key("r1", "teleop", "op-b")
    rx.prioritise(frozenset({holder}))
    got: dict[str, list[bytes]] = {holder: [], other: []}
    inside = threading.Lock()
    overlapped: list[bytes] = []
    n = 200

    def receive(key: str, payload: bytes) -> None:
        if not inside.acquire(blocking=False):
            overlapped.append(payload)  # two receivers at once: order could not hold
            return
        try:
            if payload != b"probe":
                got[key].append(payload)
                if len(got[key]) % 25 == 1:
                    SystemClock().sleep(0.01)  # a slow receiver now and then: samples queue behind it
        finally:
            inside.release()

    rx.subscribe(keys.zenoh_robot("r1"), receive)
    rx.start()
    tx.start()
    try:
        for k in (holder, other):
            wait_until(lambda k=k: tx.publish(k, b"probe") and rx.stats.received > 0, interval=0.05, message=k)
        start = rx.stats.received
        sent = {holder: [i.to_bytes(4, "big") for i in range(n)], other: [i.to_bytes(4, "big") for i in range(n)]}
        for i in range(n):  # interleaved: the holder's, then someone else's
            tx.publish(holder, sent[holder][i])
            tx.publish(other, sent[other][i])
        wait_until(lambda: rx.stats.received - start >= 2 * n, message=f"{2 * n} samples")
        wait_until(lambda: len(got[holder]) + len(got[other]) >= 2 * n, message="every sample delivered")
        assert got == sent  # each sender's in the order sent
        assert overlapped == []  # never two receivers at once, whichever thread delivered
        # Only the holder's went direct: at least the first, never more than the holder sent.
        assert 1 <= rx.delivered_direct <= n + 1
    finally:
        tx.close()
        rx.close()


# -- the agent --------------------------------------------------------------------------------------


def test_a_teleop_goes_straight_to_the_board_through_the_guard_and_the_deadman_stops_it(rig: Rig) -> None:  # noqa: F811
    op, board, agent = rig.op, rig.board, rig.agent
    assert agent.zenoh is not None and agent.zenoh.direct and agent.board.direct
    direct_before = agent.board.direct_sends
    sent: list[int] = []

    def drive(v: float) -> None:
        m = op.counter.make(Teleop, v=v, omega=0.0, ttl_s=0.5)
        sent.append(m.header.headerId)
        op.send(m, mqtt_=False)

    drive(0.3)
    wait_until(lambda: board.state.set_left > 0.0, message="the teleop's set-point at the board")
    # Written by the thread that decided it when the port is free; while the board worker holds
    # the port for a poll the set-point waits for the worker instead (seen once in CI under load),
    # so a few changed set-points are allowed for one to find the port free.
    speeds = itertools.cycle([0.25, 0.3])
    wait_until(
        lambda: agent.board.direct_sends > direct_before or drive(next(speeds)),
        interval=0.05,
        message="a set-point written by the thread that decided it",
    )
    wait_until(lambda: op.acks_for(sent[0], "teleop"), message="the ack")
    assert op.acks_for(sent[0], "teleop")[0][1].result is AckResult.ACCEPTED
    # The first teleop took the lease; the holder's next ones are handed to the agent on zenoh's
    # thread when nothing is queued (the first went through the delivery thread).
    wait_until(lambda: drive(0.3) or agent.zenoh.delivered_direct >= 1, interval=0.05, message="a direct delivery")

    # The deadman: nothing more is sent, the teleop lapses and the wheels stop (the agent is alive,
    # so this is not the board's watchdog).
    wait_until(lambda: board.state.set_left == 0.0 and abs(board.state.v_left) < 0.01, message="the deadman stop")
    assert not board.state.watchdog_tripped

    # The guard: a wall 0.3 m in front of the ultrasonic (the guard stops at 0.4 m). Forward
    # teleops, sent straight to the board as before, never get past it.
    st = board.state
    ahead = st.x + board.config.radius + 0.3
    board.floor.add_wall(ahead, st.y - 1.0, ahead, st.y + 1.0)
    # The guard reads the agent's board view, taken from the snapshot at its next control tick: a
    # teleop between the two was once decided on the view from before the wall (one ramp step,
    # 0.015 m/s, then refused), so the test waits for the view.
    wait_until(
        lambda: (
            (s := agent.board.snapshot.sensors) is not None
            and 0.0 < s.distances[0] < 0.4
            and (u := agent.core.board.ultrasonic_m) is not None
            and u < 0.4
        ),
        message="the agent to see the wall",
    )
    highest = 0.0
    clock = SystemClock()
    t_end = clock.now() + 0.4
    while clock.now() < t_end:
        drive(0.3)
        highest = max(highest, board.state.set_left)
        clock.sleep(0.02)
    highest = max(highest, board.state.set_left)
    assert highest == 0.0, f"the wheels were asked for {highest} m/s towards a wall 0.3 m away"
    assert agent.core.velocity[0] == 0.0
