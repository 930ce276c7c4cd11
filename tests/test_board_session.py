"""BoardSession against the simulated board: the link watchdog, reconnection and the snapshot.

Real-time tests serve the board on TCP and on a pty (``DeviceServer``) and poll with deadlines;
the lockstep tests run the same session on a ``SimClock`` through an ``InProcessPort``, stepping
the board by hand, so their timings are exact.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable, Iterator

import pytest

from fleetlink.agent.board.session import BoardSession, PollRates
from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.client import BoardRefused
from fleetlink.devices.controlbus.snapshot import BoardSnapshot
from fleetlink.devices.ports import InProcessPort, SerialPort
from fleetlink.field.board import BoardConfig, SimulatedBoard
from fleetlink.field.device_server import DeviceServer
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.shared.clock import SimClock, SystemClock
from tests.test_board_link import serve_board

CLOCK = SystemClock()
MOTION_PERIOD = 1.0 / 50  # the session's motion poll (which is what feeds the watchdog)
WATCHDOG = 1.0
# From 0.3 m/s the wheels brake to a standstill in ~35 ms (PID and 80 ms motor lag); allow 100 ms.
BRAKE_BUDGET = 0.1
# How late a real-time test may see the board's state change on a loaded machine (two workers on
# two cores, other work besides): the board steps on its own thread, the test polls from another.
LATE_SEEN = 0.5
CORE_DISCONNECTED = p.HealthError(p.HealthErrorCode.CORE_DISCONNECTED, "core disconnected")


def wait_for(predicate: Callable[[], object], timeout: float, what: str, interval: float = 0.002) -> float:
    """Poll until ``predicate`` is true; return the time it was first seen true. Fails after ``timeout``."""
    deadline = CLOCK.now() + timeout
    while True:
        now = CLOCK.now()
        if predicate():
            return now
        if now > deadline:
            raise AssertionError(f"timed out after {timeout:.2f} s waiting for {what}")
        CLOCK.sleep_until(now + interval)


@pytest.fixture(params=["tcp", "pty"])
def served_board(request: pytest.FixtureRequest) -> Iterator[tuple[DeviceServer, str]]:
    with serve_board(request.param) as served:
        yield served


def session_for(url: str, **kwargs: object) -> BoardSession:
    return BoardSession(lambda: SerialPort(url), CLOCK, seed=1, **kwargs)


def wheels(server: DeviceServer) -> tuple[float, float]:
    st = server.device.state
    return st.v_left, st.v_right


# ---------------------------------------------------------------------------------------------
# Watchdog, real time
# ---------------------------------------------------------------------------------------------


def test_watchdog_stops_the_wheels_when_the_agent_goes_quiet(served_board: tuple[DeviceServer, str]) -> None:
    server, url = served_board
    board = server.device
    session = session_for(url)
    try:
        session.start()
        session.set_velocity(0.3, 0.0)
        wait_for(lambda: min(wheels(server)) > 0.28, 3.0, "the wheels to reach 0.3 m/s")
        assert session.snapshot.connected
    finally:
        # The agent goes quiet. (stop() also closes the port, which for socket:// URLs includes
        # pyserial's 0.3 s courtesy sleep, so the time is taken before it.)
        quiet_at = CLOCK.now()
        session.stop()
    with server.lock:
        last = board.state.last_ctrl_bus
        assert not board.state.watchdog_tripped
        assert min(wheels(server)) > 0.25
    assert last is not None

    tripped_at = wait_for(lambda: board.state.watchdog_tripped, WATCHDOG + 5.0, "the watchdog")
    stopped_at = wait_for(lambda: wheels(server) == (0.0, 0.0), 5.0, "the wheels to stop")
    with server.lock:
        assert (board.state.set_left, board.state.set_right) == (0.0, 0.0)
        assert board.state.watchdog_trips == 1
        assert (p.HealthErrorCode.CORE_DISCONNECTED, "core disconnected") in board.state.errors
    # Not before the threshold (measured from the board's own record of the last CTRL_BUS request)...
    assert tripped_at - last > WATCHDOG
    # ... and about a second after the agent went quiet, the wheels stopped soon after. Here the
    # times are when this thread saw the board's state, which on a loaded machine can be a good
    # part of a second after the board's own step. The exact bounds (1000 ms + one poll period to
    # trip, 50 ms to brake) are held in simulated time: test_watchdog_in_lockstep below.
    assert tripped_at - quiet_at <= WATCHDOG + LATE_SEEN, f"{tripped_at - quiet_at:.3f} s"
    assert tripped_at - last <= WATCHDOG + LATE_SEEN, f"{tripped_at - last:.3f} s"
    assert stopped_at - tripped_at <= BRAKE_BUDGET + LATE_SEEN, f"wheels took {stopped_at - tripped_at:.3f} s to stop"
    # Stopped means stopped: the wheels stay at zero and did not turn backwards.
    x = board.state.x
    wait_for(lambda: CLOCK.now() > stopped_at + 0.1, 1.0, "100 ms")
    assert wheels(server) == (0.0, 0.0)
    assert board.state.x == x

    # A new session: the board resumes driving, and the master learns why it had stopped.
    with session_for(url) as session:
        session.set_velocity(0.3, 0.0)
        wait_for(lambda: min(wheels(server)) > 0.25, 5.0, "driving to resume")
        assert not board.state.watchdog_tripped
        wait_for(lambda: CORE_DISCONNECTED in session.snapshot.errors, 5.0, "the health error in the snapshot")
        health = session.snapshot.health
        assert health is not None and health.flags & p.HealthFlag.WARNING and health.error_count >= 1
        # The master acknowledges it.
        assert session.clear_error(p.HealthErrorCode.CORE_DISCONNECTED).result(timeout=2.0) == p.Empty()
        wait_for(lambda: CORE_DISCONNECTED not in session.snapshot.errors, 5.0, "the error to clear")
    assert any("link restored" in e for e in board.events)


# ---------------------------------------------------------------------------------------------
# Lockstep: SimClock + InProcessPort + board.step
# ---------------------------------------------------------------------------------------------


class Lockstep:
    """A session and a board sharing a SimClock; the test decides when time moves."""

    def __init__(self, board: SimulatedBoard | None = None, rates: PollRates | None = None) -> None:
        self.clock = SimClock(start=10.0)
        self.board = board or SimulatedBoard(now=self.clock.now())
        self.board.start_clock(self.clock.now())
        self.ports: list[InProcessPort] = []
        self.session = BoardSession(self._open, self.clock, seed=3, rates=rates)
        self.served: list[type] = []  # every Control Bus request the board answered, by type
        serve = self.board._serve

        def spy(req: p.Request) -> p.Reply:
            self.served.append(type(req))
            return serve(req)

        self.board._serve = spy  # type: ignore[method-assign]

    def _open(self) -> InProcessPort:
        port = self.board.in_process_port(self.clock)
        self.ports.append(port)
        return port

    def run(self, duration: float) -> None:
        """The agent is alive: tick the session whenever it is due, stepping the board in between."""
        end = self.clock.now() + duration
        while self.clock.now() < end:
            nxt = self.session.tick()
            self.clock.set(min(end, max(nxt, self.clock.now())))
            self.board.step(self.clock.now())

    def quiet(self, duration: float, dt: float = 0.001) -> None:
        """The agent is silent: only the board runs."""
        end = self.clock.now() + duration
        while self.clock.now() < end - 1e-12:
            self.clock.advance(dt)
            self.board.step(self.clock.now())


def test_watchdog_in_lockstep() -> None:
    ls = Lockstep()
    board, st = ls.board, ls.board.state
    ls.session.set_velocity(0.3, 0.0)
    ls.run(1.0)
    assert ls.session.snapshot.connected
    assert st.v_left == pytest.approx(0.3, abs=0.005) and st.v_right == pytest.approx(0.3, abs=0.005)
    last, quiet_at = st.last_ctrl_bus, ls.clock.now()
    assert last is not None and quiet_at - last <= MOTION_PERIOD

    tripped_at = stopped_at = None
    while stopped_at is None and ls.clock.now() < quiet_at + 2.0:
        ls.quiet(0.001)
        if tripped_at is None and st.watchdog_tripped:
            tripped_at = ls.clock.now()
            assert (st.set_left, st.set_right) == (0.0, 0.0)
        if tripped_at is not None and (st.v_left, st.v_right) == (0.0, 0.0):
            stopped_at = ls.clock.now()
        if tripped_at is None:
            assert st.v_left > 0.29, "the wheels must keep going until the watchdog fires"
    assert tripped_at is not None and stopped_at is not None
    assert tripped_at - last == pytest.approx(WATCHDOG, abs=0.0011)  # 1 ms sampling
    assert tripped_at - last > WATCHDOG
    assert tripped_at - quiet_at <= WATCHDOG + MOTION_PERIOD
    assert stopped_at - tripped_at <= 0.05, f"{stopped_at - tripped_at:.3f} s to brake from 0.3 m/s"
    assert (p.HealthErrorCode.CORE_DISCONNECTED, "core disconnected") in st.errors
    assert any("link watchdog" in e for e in board.events)
    ls.quiet(1.0)
    assert (st.v_left, st.v_right) == (0.0, 0.0) and st.watchdog_trips == 1

    # The agent comes back (same session, same link): the next request re-arms driving.
    ls.run(1.0)
    assert not st.watchdog_tripped
    assert st.v_left == pytest.approx(0.3, abs=0.005)
    assert CORE_DISCONNECTED in ls.session.snapshot.errors
    assert ls.session.snapshot.connects == 1
    ls.session.stop()
    assert not ls.session.snapshot.connected
    assert all(port.closed for port in ls.ports)


def test_lockstep_odometry_follows_an_arc() -> None:
    ls = Lockstep(SimulatedBoard(pose=(0.0, 0.0, 0.0)))
    ls.session.set_velocity(0.25, 0.5)
    ls.run(4.0)
    ls.session.set_velocity(0.0, 0.0)
    ls.run(0.5)  # stop, and let one more motion poll collect the last of the motion
    st, snap = ls.board.state, ls.session.snapshot
    assert (st.v_left, st.v_right) == (0.0, 0.0)
    assert math.hypot(st.x, st.y) > 0.8
    assert snap.odom[0] == pytest.approx(st.x, abs=1e-4)
    assert snap.odom[1] == pytest.approx(st.y, abs=1e-4)
    assert math.remainder(snap.odom[2] - st.theta, 2 * math.pi) == pytest.approx(0.0, abs=1e-4)
    ls.session.stop()


# ---------------------------------------------------------------------------------------------
# GET_TELEMETRY, and the fallback for a plain SLAMTEC base
# ---------------------------------------------------------------------------------------------

TELEMETRY_RATES = PollRates(motion=10.0, telemetry=20.0, motor=20.0, imu=20.0, sensors=20.0, bumpers=20.0)
SEPARATE_POLLS = (p.GetMotorData, p.GetImuData, p.GetSensorData, p.GetBumperData)


def test_a_board_with_telemetry_is_polled_with_it_alone() -> None:
    ls = Lockstep(SimulatedBoard(pose=(0.0, 0.0, 0.0)), rates=TELEMETRY_RATES)
    ls.session.set_velocity(0.25, 0.5)
    ls.run(2.0)
    assert ls.session.telemetry_supported is True
    assert not set(SEPARATE_POLLS) & set(ls.served), "the four separate polls must not run"
    # 20 Hz for 2 s, plus the probe at connect.
    assert 40 <= ls.served.count(p.GetTelemetry) <= 42
    st, snap = ls.board.state, ls.session.snapshot
    assert snap.motor is not None and snap.imu is not None and snap.sensors is not None and snap.bumpers is not None
    # The last reading is at most one poll period old: the wheels moved at most 0.3 m/s x 50 ms since.
    assert snap.motor.left == pytest.approx(st.dist_left, abs=0.02)
    assert snap.motor.right == pytest.approx(st.dist_right, abs=0.02)
    assert snap.motor.right > snap.motor.left > 0.2
    assert math.remainder(snap.imu.yaw - st.gyro_yaw, 2 * math.pi) == pytest.approx(0.0, abs=0.05)
    assert snap.imu.samples > 0
    assert len(snap.sensors.distances) == 1 and snap.bumpers.bitmap == 0xFFFF_FFFF
    ls.session.stop()


def test_a_plain_slamtec_base_is_polled_command_by_command() -> None:
    ls = Lockstep(SimulatedBoard(BoardConfig(extensions=False), pose=(0.0, 0.0, 0.0)), rates=TELEMETRY_RATES)
    ls.session.set_velocity(0.25, 0.0)
    ls.run(2.0)
    assert ls.session.telemetry_supported is False
    assert ls.served.count(p.GetTelemetry) == 1  # asked once, refused, never again
    assert 39 <= ls.served.count(p.GetMotorData) <= 41
    assert 39 <= ls.served.count(p.GetSensorData) <= 41
    assert 39 <= ls.served.count(p.GetBumperData) <= 41
    assert ls.served.count(p.GetImuData) == 1  # no gyro on this base either: dropped after one refusal
    snap = ls.session.snapshot
    assert snap.connected and snap.last_error == "" and snap.imu is None
    assert snap.motor is not None and snap.motor.left == pytest.approx(ls.board.state.dist_left, abs=0.02)
    assert snap.sensors is not None and len(snap.sensors.distances) == 16
    assert snap.bumpers is not None and snap.bumpers.bitmap == 0xFFFF_FFFF
    ls.session.stop()


def test_a_base_of_another_size_is_reported(caplog: pytest.LogCaptureFixture) -> None:
    """The agent plans and guards for the fleet's base (shared/body.py): a board that says its base
    is another size is still driven, and the log says what it is driven as."""
    with caplog.at_level(logging.WARNING, logger="fleetlink.agent.board.session"):
        ls = Lockstep(SimulatedBoard(BoardConfig(radius=0.25), pose=(0.0, 0.0, 0.0)), rates=TELEMETRY_RATES)
        ls.run(0.5)
    assert ls.session.snapshot.connected
    assert ls.session.snapshot.conf is not None and ls.session.snapshot.conf.radius == pytest.approx(0.25, abs=0.001)
    said = [r.getMessage() for r in caplog.records if "radius" in r.getMessage()]
    assert said == [f"board reports a base of radius 0.250 m; the agent plans and guards for {BODY_RADIUS_M:.3f} m"]
    ls.session.stop()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="fleetlink.agent.board.session"):
        ls = Lockstep(SimulatedBoard(pose=(0.0, 0.0, 0.0)), rates=TELEMETRY_RATES)
        ls.run(0.5)
    assert ls.session.snapshot.connected and not [r for r in caplog.records if "radius" in r.getMessage()]
    ls.session.stop()


# ---------------------------------------------------------------------------------------------
# Reconnection
# ---------------------------------------------------------------------------------------------


def test_session_reconnects_after_the_board_restarts() -> None:
    first = DeviceServer(SimulatedBoard(), CLOCK, name="board")
    tcp_port = first.serve_tcp()
    second: DeviceServer | None = None
    try:
        with session_for(f"socket://127.0.0.1:{tcp_port}") as session:
            wait_for(lambda: session.snapshot.connected, 3.0, "the first connection")
            assert session.snapshot.connects == 1
            session.set_velocity(0.2, 0.0)
            wait_for(lambda: first.device.state.v_left > 0.15, 2.0, "driving on the first board")

            first.stop()  # the board restarts: the socket closes and the port is gone for a moment
            second = DeviceServer(SimulatedBoard(), CLOCK, name="board")
            assert second.serve_tcp(port=tcp_port) == tcp_port
            restarted_at = CLOCK.now()

            wait_for(
                lambda: session.snapshot.connects == 2 and session.snapshot.connected,
                5.0,
                "the session to reconnect by itself",
            )
            reconnect_s = CLOCK.now() - restarted_at
            assert reconnect_s < 3.0
            snap = session.snapshot
            assert snap.info is not None and snap.info.model == "FLK-UVC-01"
            assert second.device.state.connected
            # The new board drives on the command the agent still holds.
            wait_for(lambda: second.device.state.v_left > 0.15, 2.0, "driving on the restarted board")
            assert session.snapshot.last_error == ""
    finally:
        first.stop()
        if second is not None:
            second.stop()


# ---------------------------------------------------------------------------------------------
# The snapshot
# ---------------------------------------------------------------------------------------------


def _filled(s: BoardSnapshot) -> bool:
    fields = (s.info, s.conf, s.status, s.motor, s.sensors, s.bumpers, s.health, s.payload, s.env, s.power)
    return s.connected and all(f is not None for f in fields)


def test_snapshot_fills_in_and_odometry_tracks_the_board(served_board: tuple[DeviceServer, str]) -> None:
    server, url = served_board
    board = server.device
    updates: list[BoardSnapshot] = []
    # A reply timeout of a second, not the agent's 0.1 s: on a loaded machine a SET_V_AND_GET_DEADRECKON
    # reply can come later than that, and the retry asks again after the board has already handed
    # out (and zeroed) that stretch's dead reckoning, so the odometry below would miss it. Retries
    # are test_board_link.py's; here the odometry's sum is checked.
    with session_for(url, on_update=updates.append, timeout=1.0) as session:
        wait_for(lambda: _filled(session.snapshot), 3.0, "every part of the snapshot")
        snap = session.snapshot
        assert snap.connects == 1 and snap.last_error == ""
        assert snap.info is not None and snap.info.model == "FLK-UVC-01"
        assert snap.conf is not None and snap.conf.radius == pytest.approx(0.17, abs=1e-3)
        assert snap.status is not None and snap.status.battery_percent == 100
        assert snap.power is not None and snap.power.voltage == pytest.approx(16.8, abs=0.05)
        assert snap.bumpers is not None and snap.bumpers.bitmap == 0xFFFF_FFFF
        assert snap.health == p.Health(0, 0) and snap.errors == ()
        assert snap.payload == p.PayloadStatus(False, 0, 0, 100)
        assert snap.env is not None and snap.env.disinfectant_percent == 100
        assert snap.sensors is not None and len(snap.sensors.distances) == 16
        assert updates and updates[-1].connected

        # Non-finite commands are refused and do not replace the current one.
        for vx, omega in ((math.nan, 0.0), (0.0, math.inf), (-math.inf, math.nan)):
            with pytest.raises(ValueError):
                session.set_velocity(vx, omega)
        assert session.snapshot.command == (0.0, 0.0)

        # Drive forward, stop, and compare the integrated odometry with where the board really is.
        session.set_velocity(0.25, 0.0)
        wait_for(lambda: board.state.x > 0.2, 3.0, "the robot to move 20 cm")
        assert session.snapshot.command == (0.25, 0.0)
        session.set_velocity(0.0, 0.0)
        wait_for(lambda: wheels(server) == (0.0, 0.0), 5.0, "the robot to stop")

        def odometry_and_truth() -> tuple[tuple[float, float, float], tuple[float, float, float]]:
            with server.lock:
                return session.snapshot.odom, (board.state.x, board.state.y, board.state.theta)

        def caught_up() -> bool:
            odom, truth = odometry_and_truth()
            return all(abs(a - b) <= 0.002 for a, b in zip(odom, truth, strict=True))

        # The last stretch reaches the odometry with the next motion poll's dead-reckoning delta.
        # (Waiting for the snapshot's `updated` to move on is not the same: telemetry polls set it
        # too, and on a loaded machine one of those can come first.) The asserts say by how much.
        with contextlib.suppress(AssertionError):
            wait_for(caught_up, 5.0, "the odometry to take in the motion up to the stop")
        (x, y, th), (true_x, true_y, true_th) = odometry_and_truth()
        assert x == pytest.approx(true_x, abs=0.002)
        assert y == pytest.approx(true_y, abs=0.002)
        assert th == pytest.approx(true_th, abs=0.002)
        motor = session.snapshot.motor
        assert motor is not None
        wait_for(lambda: session.snapshot.motor is not motor, 5.0, "a fresh motor poll")
        motor = session.snapshot.motor
        assert motor is not None
        assert motor.left == pytest.approx(true_x, abs=0.002) and motor.right == pytest.approx(true_x, abs=0.002)

        # One-off calls between polls.
        assert session.call(p.SetUvLamp(True)).result(timeout=2.0) == p.Empty()
        assert board.state.uv_lamp
        status = session.call(p.GetPayloadStatus()).result(timeout=2.0)
        assert isinstance(status, p.PayloadStatus) and status.uv_lamp
        wait_for(
            lambda: session.snapshot.payload is not None and session.snapshot.payload.uv_lamp,
            2.0,
            "the polled payload status to show the lamp on",
        )
        # A refused call fails its future without upsetting the session.
        refused = session.call(p.GetHealthError(99)).exception(timeout=2.0)
        assert isinstance(refused, BoardRefused) and refused.code == p.ErrorCode.BAD_ARGUMENTS
        assert session.snapshot.connected and session.snapshot.connects == 1
    assert not session.snapshot.connected
