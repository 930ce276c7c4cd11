"""The simulated board's firmware, sans-I/O: requests go in as bytes through ``receive``, time moves
only through ``step``. No threads, no sockets, no clock but the numbers passed in.
"""

from __future__ import annotations

import math

import pytest

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.frames import Frame, FrameDecoder
from fleetlink.field.board import (
    BUMPER_LEFT,
    BUMPER_RIGHT,
    CLIFF_LEFT,
    CLIFF_RIGHT,
    BoardConfig,
    SimulatedBoard,
)
from fleetlink.field.floor import Floor, Rect

FEED = 0.02  # the master's motion poll period (50 Hz): keeps the link watchdog fed
TICK = 0.001  # how finely the tests sample the firmware


def ask(board: SimulatedBoard, req: p.Request, now: float) -> p.IncomingReply:
    """One request through the board's bytes interface; exactly one reply frame must come back."""
    out = board.receive(p.encode_request(req), now)
    frames = [f for f in FrameDecoder(valid_codes=p.REPLY_CODES).feed(out) if isinstance(f, Frame)]
    assert len(frames) == 1, f"expected one reply frame to {req}, got {frames}"
    return p.decode_reply(frames[0], req.REPLY)


def ok(board: SimulatedBoard, req: p.Request, now: float) -> p.Reply:
    reply = ask(board, req, now)
    assert not isinstance(reply, (p.ErrorReply, p.Malformed, p.InvalidReply)), f"{req} -> {reply}"
    return reply


def drive(
    board: SimulatedBoard, t: float, duration: float, req: p.Request | None, every: float = FEED, dt: float = TICK
) -> float:
    """Step the board for ``duration`` s, sending ``req`` every ``every`` s (None: the master is quiet)."""
    end = t + duration
    next_feed = t
    while t < end - 1e-12:
        if req is not None and t >= next_feed - 1e-12:
            ok(board, req, t)
            next_feed += every
        t = min(end, t + dt)
        board.step(t)
    return t


# ---------------------------------------------------------------------------------------------
# Wheels
# ---------------------------------------------------------------------------------------------


def test_stop_before_reverse() -> None:
    """Commanding +0.3 -> -0.3 m/s first brakes the wheel exactly as a stop would, to zero, then reverses."""
    rev, stop = SimulatedBoard(), SimulatedBoard()
    t = 0.0
    for b in (rev, stop):
        drive(b, t, 1.0, p.SetBaseMotor.wheels(0.3, 0.3))
    t = 1.0
    assert rev.state.v_left == pytest.approx(0.3, abs=0.005)
    ok(rev, p.SetBaseMotor.wheels(-0.3, -0.3), t)
    ok(stop, p.SetBaseMotor.wheels(0.0, 0.0), t)

    trace_rev, trace_stop = [], []
    while t < 1.5:
        t += TICK
        rev.step(t)
        stop.step(t)
        trace_rev.append(rev.state.v_left)
        trace_stop.append(stop.state.v_left)

    # While the wheel still turns forward, the reverse command behaves exactly like a stop command.
    first_nonpos = next(i for i, v in enumerate(trace_rev) if v <= 0.0)
    for i in range(first_nonpos):
        assert trace_rev[i] == pytest.approx(trace_stop[i], abs=1e-12)
    # It comes to rest (zero) before it turns the other way...
    assert trace_rev[first_nonpos] == 0.0, f"wheel went from {trace_rev[first_nonpos - 1]} straight to reverse"
    assert first_nonpos * TICK < 0.1, "braking from 0.3 m/s should take well under 100 ms"
    # ... then reverses and settles on the new set-point.
    assert min(trace_rev) < -0.25
    rev_settled = drive(rev, t, 1.0, p.SetBaseMotor.wheels(-0.3, -0.3))
    assert rev_settled > t
    assert rev.state.v_left == pytest.approx(-0.3, abs=0.005)
    assert rev.state.v_right == pytest.approx(-0.3, abs=0.005)


def test_zero_setpoint_stops_without_turning_backwards() -> None:
    b = SimulatedBoard()
    t = drive(b, 0.0, 1.0, p.SetVelocity(0.3))
    assert b.state.v_left == pytest.approx(0.3, abs=0.005)
    ok(b, p.SetVelocity(0.0), t)
    stopped_at = None
    speeds = []
    while t < 1.5:
        t += TICK
        b.step(t)
        speeds.append((b.state.v_left, b.state.v_right))
        if stopped_at is None and b.state.v_left == 0.0 and b.state.v_right == 0.0:
            stopped_at = t - 1.0
    assert stopped_at is not None and stopped_at < 0.1, f"wheels stopped after {stopped_at} s"
    # A stop never spins a wheel the other way, and once stopped the wheels stay stopped.
    assert min(min(vl, vr) for vl, vr in speeds) >= 0.0
    assert speeds[-1] == (0.0, 0.0)
    x = b.state.x
    drive(b, t, 0.5, p.SetVelocity(0.0))
    assert b.state.x == x


def test_straight_line_distances_match_speed_times_time() -> None:
    v = 0.3
    b = SimulatedBoard()
    t = drive(b, 0.0, 1.0, p.SetVelocity(v))  # motor lag settles well within the first second
    left0, right0 = b.state.dist_left, b.state.dist_right
    t = drive(b, t, 2.0, p.SetVelocity(v))
    st = b.state
    assert st.dist_left - left0 == pytest.approx(v * 2.0, rel=0.005)
    assert st.dist_right - right0 == pytest.approx(v * 2.0, rel=0.005)
    assert st.dist_left == pytest.approx(st.dist_right, abs=1e-9)
    # Straight ahead: all the distance went into x.
    assert st.x == pytest.approx(st.dist_left, abs=1e-6)
    assert st.y == pytest.approx(0.0, abs=1e-9)
    assert st.theta == pytest.approx(0.0, abs=1e-9)
    motor = ok(b, p.GetMotorData(), t)
    assert isinstance(motor, p.MotorData)
    assert motor.left == pytest.approx(st.dist_left, abs=0.001)  # mm on the wire
    assert motor.right == pytest.approx(st.dist_right, abs=0.001)
    assert motor.status == 0


def test_dead_reckoning_deltas_sum_to_true_displacement() -> None:
    start = (1.0, 2.0, 0.3)
    b = SimulatedBoard(pose=start)
    x, y, th = start
    t = 0.0
    for vx, omega, duration in ((0.25, 0.6, 3.0), (0.3, 0.0, 1.0), (0.1, -1.2, 2.0), (0.0, 0.0, 0.5)):
        end = t + duration
        while t < end - 1e-9:
            dr = ok(b, p.SetVelocity(vx, 0.0, omega), t)
            assert isinstance(dr, p.DeadReckon)
            c, s = math.cos(th), math.sin(th)
            x, y, th = x + c * dr.dx - s * dr.dy, y + s * dr.dx + c * dr.dy, th + dr.dtheta
            t += FEED
            b.step(t)
    dr = ok(b, p.SetVelocity(0.0), t)  # flush the last interval
    assert isinstance(dr, p.DeadReckon)
    c, s = math.cos(th), math.sin(th)
    x, y, th = x + c * dr.dx - s * dr.dy, y + s * dr.dx + c * dr.dy, th + dr.dtheta
    st = b.state
    assert math.hypot(st.x - start[0], st.y - start[1]) > 1.0, "the robot should have gone somewhere"
    assert x == pytest.approx(st.x, abs=1e-4)
    assert y == pytest.approx(st.y, abs=1e-4)
    assert math.remainder(th - st.theta, 2 * math.pi) == pytest.approx(0.0, abs=1e-4)


# ---------------------------------------------------------------------------------------------
# Power and payload
# ---------------------------------------------------------------------------------------------


def test_battery_drains_faster_under_load() -> None:
    idle, busy = SimulatedBoard(), SimulatedBoard()
    v0 = idle.state.voltage
    drive(idle, 0.0, 60.0, p.SetVelocity(0.0), dt=0.02)
    t = drive(busy, 0.0, 60.0, p.SetVelocity(0.5), dt=0.02)
    idle_drop = v0 - idle.state.voltage
    busy_drop = v0 - busy.state.voltage
    assert idle_drop > 0.0
    assert busy_drop > 3 * idle_drop
    power = ok(busy, p.GetPowerData(), t)
    assert isinstance(power, p.PowerData)
    assert power.current < -1.0  # discharging, amps
    assert power.voltage == pytest.approx(busy.state.voltage, abs=0.001)
    assert not busy.state.charging


def test_charging_on_dock_raises_voltage() -> None:
    docked = SimulatedBoard(BoardConfig(dock=(0.0, 0.0)))
    away = SimulatedBoard(BoardConfig(dock=(3.0, 3.0)))
    for b in (docked, away):
        b.state.voltage = 14.0
    step_to(docked, 0.0, 60.0)
    t = step_to(away, 0.0, 60.0)
    assert docked.state.voltage > 14.0 + 0.02
    assert away.state.voltage < 14.0
    status = ok(docked, p.GetBaseStatus(), t)
    assert isinstance(status, p.BaseStatus)
    assert status.charging and status.on_dock and status.external_power
    power = ok(docked, p.GetPowerData(), t)
    assert isinstance(power, p.PowerData)
    assert power.current > 0.0
    status_away = ok(away, p.GetBaseStatus(), t)
    assert isinstance(status_away, p.BaseStatus)
    assert not status_away.charging and not status_away.on_dock
    assert status_away.battery_percent < status.battery_percent


def step_to(board: SimulatedBoard, t: float, end: float, dt: float = 1.0) -> float:
    """Step in bounded increments (``step`` deliberately skips jumps longer than 5 s)."""
    while t < end:
        t = min(end, t + dt)
        board.step(t)
    return t


def test_tank_drains_with_the_atomiser_and_refuses_when_empty() -> None:
    b = SimulatedBoard()
    ok(b, p.SetAtomiser(3), 0.0)
    step_to(b, 0.0, 20.0)
    assert b.state.tank_ml == pytest.approx(500.0 - 1.0 * 20.0, abs=0.01)  # level 3: 1 ml/s
    ok(b, p.SetAtomiser(1), 20.0)
    step_to(b, 20.0, 24.0)
    assert b.state.tank_ml == pytest.approx(480.0 - 0.25 * 4.0, abs=0.01)
    status = ok(b, p.GetPayloadStatus(), 24.0)
    assert isinstance(status, p.PayloadStatus)
    assert status.atomiser_level == 1 and status.tank_percent == 96

    # Run it dry: the firmware switches the atomiser off and reports the empty tank.
    b.state.tank_ml = 0.5
    step_to(b, 24.0, 27.0)
    assert b.state.tank_ml == 0.0
    assert b.state.atomiser == 0
    assert (p.HealthErrorCode.TANK_EMPTY, "disinfectant tank empty") in b.state.errors
    refused = ask(b, p.SetAtomiser(2), 27.0)
    assert refused == p.ErrorReply(p.ErrorCode.OPERATION_FAILED)
    assert ok(b, p.SetAtomiser(0), 27.0) == p.Empty()  # switching it off is always allowed
    b.refill_tank()
    assert ok(b, p.SetAtomiser(2), 27.0) == p.Empty()
    assert all(code != p.HealthErrorCode.TANK_EMPTY for code, _ in b.state.errors)


# ---------------------------------------------------------------------------------------------
# Sensors
# ---------------------------------------------------------------------------------------------


def test_driving_into_a_wall_stops_the_robot_and_presses_the_bumpers() -> None:
    b = SimulatedBoard(floor=Floor(walls=[(1.0, -1.0, 1.0, 1.0)]))
    radius = b.config.radius
    bumpers = ok(b, p.GetBumperData(), 0.0)
    assert isinstance(bumpers, p.BumperData)
    assert bumpers.bitmap == 0xFFFF_FFFF  # nothing triggered (0 = triggered)

    # The master keeps asking to go forward at 50 Hz and reads the bumpers at 20 Hz, as a session does.
    t, next_feed, next_read, reads = 0.0, 0.0, 0.0, []
    while t < 5.0:
        if t >= next_feed - 1e-9:
            ok(b, p.SetVelocity(0.3), t)
            next_feed += FEED
        if t >= next_read - 1e-9:
            got = ok(b, p.GetBumperData(), t)
            assert isinstance(got, p.BumperData)
            reads.append((t, b.state.x, got))
            next_read += 0.05
        t += 0.005
        b.step(t)
    st = b.state
    assert st.x == pytest.approx(1.0 - radius, abs=0.003), "the body stops against the wall"
    assert st.x <= 1.0 - radius + 1e-9
    assert b.floor.clearance(st.x, st.y) >= radius - 1e-9
    # The robot reaches the wall after ~2.9 s; from then on every read shows both front bumpers pressed
    # (head-on), and the cliff sensors clear.
    touching = [got for (t_read, x, got) in reads if t_read > 3.2]
    assert touching
    for got in touching:
        assert got.triggered(BUMPER_LEFT) and got.triggered(BUMPER_RIGHT), hex(got.bitmap)
        assert not got.triggered(CLIFF_LEFT) and not got.triggered(CLIFF_RIGHT)
    assert all(not got.triggered(BUMPER_LEFT) for (t_read, x, got) in reads if x < 0.8)

    # Backing away releases them.
    t = drive(b, t, 0.5, p.SetVelocity(-0.2))
    got = ok(b, p.GetBumperData(), t)
    assert isinstance(got, p.BumperData)
    assert got.bitmap == 0xFFFF_FFFF
    assert b.state.x < 1.0 - radius - 0.05


def test_glancing_wall_presses_only_the_bumper_on_that_side() -> None:
    # A wall ahead and to the left, at 45 degrees to the robot's path.
    b = SimulatedBoard(floor=Floor(walls=[(0.2, 1.3, 1.6, -0.1)]))
    t = drive(b, 0.0, 5.0, p.SetVelocity(0.3))  # contact after ~4.2 s
    got = ok(b, p.GetBumperData(), t)
    assert isinstance(got, p.BumperData)
    assert got.triggered(BUMPER_LEFT)
    assert not got.triggered(BUMPER_RIGHT)
    assert b.floor.clearance(b.state.x, b.state.y) >= b.config.radius - 1e-9


def test_cliff_region_sets_the_cliff_bits() -> None:
    floor = Floor(cliffs=[Rect(0.3, 0.0, 2.0, 1.0)])  # a drop ahead, on the left half only
    clear = SimulatedBoard(floor=floor, pose=(0.0, 0.0, 0.0))
    left_only = SimulatedBoard(floor=floor, pose=(0.3, 0.0, 0.0))
    both = SimulatedBoard(floor=Floor(cliffs=[Rect(0.3, -1.0, 2.0, 1.0)]), pose=(0.3, 0.0, 0.0))
    got = ok(clear, p.GetBumperData(), 0.0)
    assert isinstance(got, p.BumperData)
    assert got.bitmap == 0xFFFF_FFFF
    got = ok(left_only, p.GetBumperData(), 0.0)
    assert isinstance(got, p.BumperData)
    assert got.triggered(CLIFF_LEFT) and not got.triggered(CLIFF_RIGHT)
    assert not got.triggered(BUMPER_LEFT) and not got.triggered(BUMPER_RIGHT)
    got = ok(both, p.GetBumperData(), 0.0)
    assert isinstance(got, p.BumperData)
    assert got.triggered(CLIFF_LEFT) and got.triggered(CLIFF_RIGHT)

    # Driving towards the drop: the bits change as the sensors (0.14 m ahead) pass over its edge.
    b = SimulatedBoard(floor=Floor(cliffs=[Rect(0.5, -1.0, 2.0, 1.0)]))
    t = 0.0
    while b.state.x < 0.5 and t < 5.0:
        t = drive(b, t, 0.05, p.SetVelocity(0.2))
        got = ok(b, p.GetBumperData(), t)
        assert isinstance(got, p.BumperData)
        edge_reached = b.state.x + b.config.cliff_offset * math.cos(0.5) >= 0.5
        assert got.triggered(CLIFF_LEFT) == edge_reached
        assert got.triggered(CLIFF_RIGHT) == edge_reached
    assert b.state.x >= 0.5


@pytest.mark.parametrize(
    ("wall_x", "expected"),
    [
        (1.0, 1.0 - 0.17),  # 0.83 m from the sensor on the front of the body
        (0.17 + 1.45, 1.45),  # near the top of the range
        (0.17 + 1.6, 0.0),  # beyond 1.5 m: no echo
        (0.17 + 0.1, 0.25),  # closer than 0.25 m reads as the minimum range
    ],
)
def test_ultrasonic_reads_the_distance_to_a_wall_ahead(wall_x: float, expected: float) -> None:
    b = SimulatedBoard(floor=Floor(walls=[(wall_x, -2.0, wall_x, 2.0)]))
    for i in range(5):
        got = ok(b, p.GetSensorData(), 0.1 * i)
        assert isinstance(got, p.SensorData)
        assert len(got.distances) == 16
        assert got.distances[1:] == (0.0,) * 15
        if expected == 0.0:
            assert got.distances[0] == 0.0
        else:
            assert got.distances[0] == pytest.approx(expected, abs=0.02)
            assert 0.25 <= got.distances[0] <= 1.5 + 0.02


def test_ultrasonic_follows_the_robot_towards_a_wall() -> None:
    b = SimulatedBoard(floor=Floor(walls=[(2.0, -1.0, 2.0, 1.0)]))
    t = drive(b, 0.0, 1.0, p.SetVelocity(0.3))
    seen = []
    while b.state.x < 1.5:
        t = drive(b, t, 0.1, p.SetVelocity(0.3))
        got = ok(b, p.GetSensorData(), t)
        assert isinstance(got, p.SensorData)
        truth = 2.0 - b.state.x - b.config.radius
        if 0.25 <= truth <= 1.5:
            assert got.distances[0] == pytest.approx(truth, abs=0.02)
            seen.append(got.distances[0])
    assert len(seen) >= 5
    assert seen == sorted(seen, reverse=True) or max(a - b for a, b in zip(seen[1:], seen, strict=False)) < 0.02
