"""Odometry: closed-form motions, the gyro blend, counter resets and bad readings."""

from __future__ import annotations

import math

import pytest

from fleetlink.agent.odometry import Odometry, wrap_angle

TRACK = 0.22


def drive(odo: Odometry, steps: int, dl: float, dr: float, dyaw: float | None = None, dt: float = 0.05) -> None:
    """From a fresh ``Odometry``: a baseline reading, then ``steps`` readings whose wheels advance by
    dl, dr (and the gyro by dyaw) each."""
    t = left = right = yaw = 0.0
    odo.update(t, left, right, None if dyaw is None else yaw)
    for _ in range(steps):
        t += dt
        left += dl
        right += dr
        yaw = wrap_angle(yaw + (dyaw or 0.0))
        odo.update(t, left, right, None if dyaw is None else yaw)


def test_straight_line() -> None:
    odo = Odometry(wheel_track_m=TRACK)
    drive(odo, 40, 0.025, 0.025)
    p = odo.pose
    assert p.x == pytest.approx(1.0)
    assert p.y == pytest.approx(0.0, abs=1e-12)
    assert p.theta == pytest.approx(0.0)
    assert p.v == pytest.approx(0.5)
    assert p.omega == pytest.approx(0.0)


def test_arc_matches_the_circle() -> None:
    odo = Odometry(wheel_track_m=TRACK)
    # Quarter circle of radius 1 m to the left: wheels at radius 1 -/+ track/2.
    n = 100
    quarter = math.pi / 2
    drive(odo, n, (1 - TRACK / 2) * quarter / n, (1 + TRACK / 2) * quarter / n)
    p = odo.pose
    assert p.x == pytest.approx(1.0, abs=1e-9)
    assert p.y == pytest.approx(1.0, abs=1e-9)
    assert p.theta == pytest.approx(quarter)
    assert p.omega == pytest.approx(quarter / n / 0.05)


def test_spin_in_place() -> None:
    odo = Odometry(wheel_track_m=TRACK)
    # A full turn counter-clockwise: each wheel travels pi * track.
    n = 200
    drive(odo, n, -math.pi * TRACK / n, math.pi * TRACK / n)
    p = odo.pose
    assert math.hypot(p.x, p.y) == pytest.approx(0.0, abs=1e-12)
    assert abs(wrap_angle(p.theta)) < 1e-9
    assert p.v == pytest.approx(0.0)


def test_gyro_gives_the_heading_when_present() -> None:
    # Encoders claim a straight line (wheel-scale error hides the turn); the gyro saw a quarter turn.
    odo = Odometry(wheel_track_m=TRACK)
    n = 100
    quarter = math.pi / 2
    drive(odo, n, quarter / n, quarter / n, dyaw=quarter / n)
    p = odo.pose
    assert p.theta == pytest.approx(quarter)
    assert p.x == pytest.approx(1.0, abs=1e-9)  # the arc of radius 1 m the gyro implies
    assert p.y == pytest.approx(1.0, abs=1e-9)


def test_gyro_blend_weight() -> None:
    odo = Odometry(wheel_track_m=TRACK, gyro_weight=0.5)
    drive(odo, 10, 0.0, 0.0, dyaw=0.01)  # the gyro turns, the encoders do not
    assert odo.pose.theta == pytest.approx(0.05)


def test_encoders_used_without_gyro_readings() -> None:
    odo = Odometry(wheel_track_m=TRACK)
    drive(odo, 10, -0.011, 0.011)  # no gyro
    assert odo.pose.theta == pytest.approx(10 * 0.022 / TRACK)


def test_counter_reset_is_not_a_jump() -> None:
    odo = Odometry(wheel_track_m=TRACK)
    drive(odo, 20, 0.02, 0.02)
    before = odo.pose
    # The board restarts: its counters start again from zero (and carry on from there).
    odo.update(before.t + 0.05, 0.0, 0.0, None)
    assert odo.counter_resets == 1
    after = odo.pose
    assert (after.x, after.y, after.theta) == (before.x, before.y, before.theta)
    odo.update(after.t + 0.05, 0.02, 0.02, None)
    assert odo.pose.x == pytest.approx(before.x + 0.02)


def test_reset_counters_rebaselines() -> None:
    odo = Odometry(wheel_track_m=TRACK)
    drive(odo, 10, 0.02, 0.02)
    x = odo.pose.x
    odo.reset_counters()
    odo.update(odo.pose.t + 3.0, 1234.0, 1234.0, None)  # a new board with other counters
    assert odo.pose.x == x
    assert odo.counter_resets == 0


def test_counter_wrap_across_s32_millimetres() -> None:
    odo = Odometry(wheel_track_m=TRACK)
    top = 2**31 / 1000 - 0.01
    odo.update(0.0, top, top, None)
    odo.update(0.05, top + 0.02 - 2**32 / 1000, top + 0.02 - 2**32 / 1000, None)
    assert odo.pose.x == pytest.approx(0.02, abs=1e-6)


def test_gyro_restart_falls_back_on_encoders() -> None:
    odo = Odometry(wheel_track_m=TRACK)
    odo.update(0.0, 0.0, 0.0, 1.0)
    odo.update(0.05, 0.0, 0.0, -2.0)  # yaw leapt 3 rad in 50 ms: the gyro restarted
    assert odo.gyro_resets == 1
    assert odo.pose.theta == 0.0


@pytest.mark.parametrize("bad", [(math.nan, 0.0, 0.0, None), (1.0, math.inf, 0.0, None), (1.0, 0.0, 0.0, math.nan)])
def test_non_finite_readings_are_rejected(bad: tuple[float, float, float, float | None]) -> None:
    odo = Odometry()
    drive(odo, 5, 0.01, 0.01)
    before = odo.pose
    assert odo.update(*bad) == before
    assert odo.rejected == 1


def test_time_going_backwards_is_rejected() -> None:
    odo = Odometry()
    drive(odo, 5, 0.01, 0.01)
    before = odo.pose
    assert odo.update(before.t - 1.0, 5.0, 5.0, None) == before
    assert odo.rejected == 1
