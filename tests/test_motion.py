"""Motion: limits, the arrival window, the heading/distance PIDs and go-to in a kinematic simulation."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from fleetlink.agent.motion import (
    ArrivalWindow,
    GoToController,
    GoToPhase,
    MotionLimits,
    RateLimiter,
    wrap_angle,
)


@dataclass
class Unicycle:
    """A differential-drive body whose speeds follow the command with a first-order motor lag."""

    x: float = 0.0
    y: float = 0.0
    th: float = 0.0
    v: float = 0.0
    w: float = 0.0
    tau: float = 0.08

    def step(self, v_cmd: float, w_cmd: float, dt: float, sub: int = 10) -> None:
        h = dt / sub
        for _ in range(sub):
            self.v += (v_cmd - self.v) * h / self.tau
            self.w += (w_cmd - self.w) * h / self.tau
            self.x += self.v * math.cos(self.th) * h
            self.y += self.v * math.sin(self.th) * h
            self.th = wrap_angle(self.th + self.w * h)

    @property
    def pose(self) -> tuple[float, float, float]:
        return self.x, self.y, self.th


def run_goto(
    goal: tuple[float, float],
    theta: float | None = None,
    start: tuple[float, float, float] = (0.0, 0.0, 0.0),
    dt: float = 0.02,
    noise: float = 0.0,
    seed: int = 0,
    limit_s: float = 60.0,
) -> tuple[Unicycle, float, list[tuple[float, float]], GoToController]:
    lim = MotionLimits()
    ctl, rl, body = GoToController(lim), RateLimiter(lim), Unicycle(*start)
    rng = np.random.default_rng(seed)
    ctl.start([goal], theta)
    t, cmds = 0.0, []
    while ctl.active and t < limit_s:
        seen = (body.x + rng.normal(0, noise), body.y + rng.normal(0, noise), body.th) if noise else body.pose
        c = ctl.step(t, seen)
        v, w = rl.step(t, c.v, c.omega)
        cmds.append((v, w))
        body.step(v, w, dt)
        t += dt
    return body, t, cmds, ctl


def test_wrap_angle_takes_the_shorter_arc() -> None:
    assert wrap_angle(math.radians(350)) == pytest.approx(math.radians(-10))
    assert wrap_angle(math.radians(-190)) == pytest.approx(math.radians(170))
    assert -math.pi <= wrap_angle(math.pi) < math.pi


def test_rate_limiter_limits_speed_and_acceleration_and_is_idempotent_in_time() -> None:
    lim = MotionLimits(v_max=0.5, omega_max=1.0, a_max=1.0, alpha_max=2.0)
    rl = RateLimiter(lim, first_step_s=0.02)
    # The first call after a stop applies at once, one small step's worth.
    assert rl.step(0.0, 5.0, 5.0) == pytest.approx((0.02, 0.04))
    v, w = rl.step(0.1, 5.0, 5.0)
    assert v == pytest.approx(0.12) and w == pytest.approx(0.24)
    assert rl.step(0.1, 5.0, 5.0) == (v, w)  # same time again: nothing moves
    assert rl.step(0.1, 0.1, 0.1) == (0.1, 0.1)  # a newer command at that time wins
    assert rl.step(0.1, 5.0, 5.0) == (v, w)
    for k in range(2, 20):
        v, w = rl.step(0.1 * k, 5.0, 5.0)
    assert (v, w) == (0.5, 1.0)
    rl.reset(2.0)
    assert rl.step(2.0, 0.0, 0.0) == (0.0, 0.0)
    assert rl.step(2.0, -1.0, 0.0) == pytest.approx((-0.02, 0.0))
    assert rl.step(2.0, -1.0, 0.0) == pytest.approx((-0.02, 0.0))


def test_limits_validated() -> None:
    with pytest.raises(ValueError, match="v_max"):
        MotionLimits(v_max=0.0)


def test_arrival_window_needs_mean_and_spread_over_the_whole_window() -> None:
    w = ArrivalWindow(0.2, mean_tol=0.01, spread_tol=0.01)
    assert not w.push(0.0, 0.0)
    assert not w.push(0.1, 0.0)
    # Repeated calls at one time do not count as samples.
    for _ in range(10):
        assert not w.push(0.1, 0.0)
    assert w.push(0.2, 0.0)
    w.reset()
    # Small mean but a wide spread (a noisy pose swinging through the goal) is not arrival.
    assert not any(w.push(0.05 * k, 0.0 if k % 2 else 0.018) for k in range(10))


@pytest.mark.parametrize(
    ("goal", "theta"),
    [((3.0, -2.0), math.radians(90)), ((-2.0, 0.5), None), ((0.0, 4.0), math.radians(-170)), ((0.6, 0.0), 0.0)],
)
def test_goto_converges_in_a_kinematic_simulation(goal: tuple[float, float], theta: float | None) -> None:
    body, t, cmds, ctl = run_goto(goal, theta)
    assert ctl.phase is GoToPhase.DONE
    assert math.hypot(body.x - goal[0], body.y - goal[1]) < 0.01
    if theta is not None:
        assert abs(wrap_angle(body.th - theta)) < math.radians(1.5)
    lim = MotionLimits()
    assert max(abs(v) for v, _ in cmds) <= lim.v_max + 1e-12
    assert max(abs(w) for _, w in cmds) <= lim.omega_max + 1e-12
    # Near the ideal time (distance / v_max + turns / omega_max) plus accelerations and settling.
    bearing = math.atan2(goal[1], goal[0])
    turn = abs(bearing) + (abs(wrap_angle(theta - bearing)) if theta is not None else 0.0)
    ideal = math.hypot(*goal) / lim.v_max + turn / lim.omega_max
    assert t < 1.3 * ideal + 1.0


def test_goto_turns_through_the_shorter_arc() -> None:
    # Facing +170 deg, goal straight at -170 deg: a 20 deg right turn... through +-180, i.e. turning left.
    start = (0.0, 0.0, math.radians(170))
    goal = (math.cos(math.radians(-170)) * 2, math.sin(math.radians(-170)) * 2)
    body, _, cmds, _ = run_goto(goal, None, start=start)
    turning = [w for v, w in cmds[:20] if abs(w) > 1e-6]
    assert turning and all(w > 0 for w in turning)  # counter-clockwise, across the +-180 seam
    assert math.hypot(body.x - goal[0], body.y - goal[1]) < 0.01


def test_goto_settles_on_a_noisy_pose() -> None:
    body, t, _, ctl = run_goto((2.5, 1.0), 0.0, noise=0.005, seed=3)
    assert ctl.phase is GoToPhase.DONE and t < 20
    assert math.hypot(body.x - 2.5, body.y - 1.0) < 0.03


def test_goto_follows_waypoints_then_stops_at_the_goal() -> None:
    lim = MotionLimits()
    ctl, rl, body = GoToController(lim), RateLimiter(lim), Unicycle()
    ctl.start([(2.0, 0.0), (2.0, 2.0)])
    t, passed = 0.0, []
    while ctl.active and t < 30:
        c = ctl.step(t, body.pose)
        passed.append((c.waypoint_index, body.x, body.y))
        body.step(*rl.step(t, c.v, c.omega), 0.02)
        t += 0.02
    # It went round the corner (never cut across) and ended on the goal.
    assert max(x for i, x, y in passed if i == 0) > 1.85
    assert all(y < 0.15 for i, x, y in passed if i == 0)
    assert math.hypot(body.x - 2.0, body.y - 2.0) < 0.01


def test_cancel_and_drive_start_report() -> None:
    ctl = GoToController()
    ctl.start([(2.0, 0.0)])
    starts = []
    for k in range(20):
        c = ctl.step(0.02 * k, (0.0, 0.0, 0.0))
        if c.drive_distance_m is not None:
            starts.append(c.drive_distance_m)
    assert starts == [pytest.approx(2.0)]  # reported once, on the tick the drive begins
    ctl.cancel()
    c = ctl.step(1.0, (0.0, 0.0, 0.0))
    assert (c.v, c.omega, c.phase) == (0.0, 0.0, GoToPhase.DONE)
    with pytest.raises(ValueError):
        ctl.start([])


def test_near_the_goal_the_approach_does_not_creep() -> None:
    # 10 cm short, aligned: the linear term alone would crawl the last centimetres; the floor keeps
    # the approach at approach_v_min (under the braking cap) until within the arrival tolerance.
    ctl = GoToController()
    c = ctl.config
    ctl.start([(0.10, 0.0)])
    t = 0.0
    while ctl.step(t, (0.0, 0.0, 0.0)).phase is not GoToPhase.DRIVE:  # aimed already: the window passes
        t += 0.02
    for x in (0.05, 0.08, 0.085):
        t += 0.02
        cmd = ctl.step(t, (x, 0.0, 0.0))
        assert cmd.phase is GoToPhase.DRIVE
        assert cmd.v >= min(c.approach_v_min, math.sqrt(2 * 0.8 * MotionLimits().a_max * (0.10 - x))) - 1e-12
    cmd = ctl.step(t + 0.02, (0.115, 0.0, 0.0))  # overshot 1.5 cm: back, at the floor
    assert cmd.v <= -min(c.approach_v_min, math.sqrt(2 * 0.8 * MotionLimits().a_max * 0.015)) + 1e-12


def test_settling_after_the_final_turn_closes_along_and_accepts_a_small_sideways_residue() -> None:
    # At the goal facing +x, final heading reached; the pose then says the goal is 2.6 cm off:
    # 1.5 cm ahead and 2.1 cm to the side. Closing it costs a drive along the heading, not a turn
    # of up to 90 deg toward a spot 2 cm away and the final turn again.
    ctl = GoToController()
    ctl.start([(1.0, 0.0)], 0.0)
    t = 0.0
    while ctl.phase is not GoToPhase.FINAL_HEADING and t < 2.0:
        ctl.step(t, (1.0, 0.0, 0.0) if t > 0.0 else (0.999, 0.0, 0.0))
        t += 0.02
    assert ctl.phase is GoToPhase.FINAL_HEADING
    pose = (1.0 - 0.015, 0.021, 0.0)
    omegas = []
    for _ in range(100):
        cmd = ctl.step(t, pose)
        omegas.append(cmd.omega)
        if cmd.phase is GoToPhase.DONE:
            break
        pose = (min(1.0, pose[0] + cmd.v * 0.02), pose[1], 0.0)
        t += 0.02
    assert ctl.phase is GoToPhase.DONE
    assert all(w == 0.0 for w in omegas)  # never turned away
    assert abs(pose[0] - 1.0) < 0.01


def test_a_reaim_near_the_goal_takes_the_shorter_total_turn_with_the_final_heading() -> None:
    # A correction re-aim 4 cm off sideways, facing +x, final heading +170 deg: the line through
    # the goal is +90 or -90 deg (90 deg of turn either way); facing +90 leaves 80 deg to the final
    # heading, -90 leaves 100: turn left, whichever side the goal is on (the drive goes back for it).
    ctl = GoToController()
    ctl.start([(0.0, 0.04)], math.radians(170))
    ctl.retries = 1  # a correction: the goal was reached once
    cmd = ctl.step(0.0, (0.0, 0.0, 0.0))
    assert cmd.phase is GoToPhase.ROTATE and cmd.omega > 0
    ctl.start([(0.0, -0.04)], math.radians(170))
    ctl.retries = 1
    cmd = ctl.step(0.0, (0.0, 0.0, 0.0))
    assert cmd.phase is GoToPhase.ROTATE and cmd.omega > 0
