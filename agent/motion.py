"""Motion controllers: go-to-coordinate by rotate-then-drive, and velocity/acceleration limits (pure).

The rescue-robot seed's go-to: turn toward the goal with a PI(D) on heading through the shorter
arc, then drive with a PD on distance that brakes below a threshold, and judge arrival by the mean
and the spread of a rolling window of errors (a single small error sample proves nothing on a
noisy pose). Here the braking threshold follows from the deceleration limit (v_max^2 / 2a): above
it the robot cruises at v_max, below it the speed follows sqrt(2 a d), and in the last few
centimetres the linear PD term takes over. The same shape, with the angular limits, turns the
robot. Everything takes the time and the pose as arguments and returns a command.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

__all__ = [
    "ArrivalWindow",
    "GoToCommand",
    "GoToConfig",
    "GoToController",
    "GoToPhase",
    "MotionLimits",
    "Pid",
    "RateLimiter",
    "wrap_angle",
]

Pose = tuple[float, float, float]
Point = tuple[float, float]


def wrap_angle(a: float) -> float:
    """Into [-pi, pi): the shorter arc."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True, slots=True)
class MotionLimits:
    v_max: float = 0.5  # m/s
    omega_max: float = 1.5  # rad/s
    a_max: float = 1.0  # m/s^2
    alpha_max: float = 6.0  # rad/s^2

    def __post_init__(self) -> None:
        for name in ("v_max", "omega_max", "a_max", "alpha_max"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"MotionLimits.{name} must be finite and > 0, got {v!r}")


class RateLimiter:
    """Clamps speed to the limits and its change to the acceleration limits.

    Idempotent in time: every call at the same ``now`` ramps from the output committed at the
    previous distinct time, so the latest command at that instant wins and repeated calls move
    nothing. A command that arrives right after a stop still gets ``first_step_s`` worth of
    acceleration at once (commands apply on arrival, not one tick later). ``reset`` sets the state
    directly: a safety stop does not ramp down (the motors' own lag is the only softening).
    """

    def __init__(self, limits: MotionLimits, max_dt: float = 0.2, first_step_s: float = 0.02) -> None:
        self.limits = limits
        self.max_dt = max_dt  # a stalled caller does not earn a huge jump
        self.first_step_s = first_step_s
        self.v = 0.0
        self.omega = 0.0
        self._t: float | None = None  # time of (v, omega)
        self._base: tuple[float, float, float] | None = None  # (t, v, omega) committed before _t

    def reset(self, now: float, v: float = 0.0, omega: float = 0.0) -> None:
        self.v, self.omega, self._t, self._base = v, omega, now, None

    def step(self, now: float, v: float, omega: float) -> tuple[float, float]:
        lim = self.limits
        v = max(-lim.v_max, min(lim.v_max, v))
        omega = max(-lim.omega_max, min(lim.omega_max, omega))
        if self._t is not None and now > self._t:
            self._base = (self._t, self.v, self.omega)
        if self._base is None:
            self._base = (now - self.first_step_s, self.v, self.omega)
        bt, bv, bw = self._base
        dt = max(0.0, min(self.max_dt, now - bt))
        if self._t is None or now > self._t:
            self._t = now
        dv, dw = lim.a_max * dt, lim.alpha_max * dt
        self.v = max(bv - dv, min(bv + dv, v))
        self.omega = max(bw - dw, min(bw + dw, omega))
        return self.v, self.omega


class ArrivalWindow:
    """Rolling window of |error| over ``window_s``: arrived when its mean and spread are both small.

    Samples at the same time as the last one are ignored, so extra calls (the runtime ticks after
    every command) do not fill the window faster than time passes.
    """

    def __init__(self, window_s: float, mean_tol: float, spread_tol: float, min_samples: int = 3) -> None:
        self.window_s = window_s
        self.mean_tol = mean_tol
        self.spread_tol = spread_tol
        self.min_samples = min_samples
        self._samples: deque[tuple[float, float]] = deque()
        self._since: float | None = None

    def reset(self) -> None:
        self._samples.clear()
        self._since = None

    def push(self, now: float, error: float) -> bool:
        s = self._samples
        if s and now <= s[-1][0]:
            return self.settled(now)
        if self._since is None:
            self._since = now
        s.append((now, abs(error)))
        while s and s[0][0] < now - self.window_s:
            s.popleft()
        return self.settled(now)

    def settled(self, now: float) -> bool:
        s = self._samples
        if self._since is None or now - self._since < self.window_s or len(s) < self.min_samples:
            return False
        errs = [e for _, e in s]
        return sum(errs) / len(errs) <= self.mean_tol and max(errs) - min(errs) <= self.spread_tol

    @property
    def mean(self) -> float:
        s = self._samples
        return sum(e for _, e in s) / len(s) if s else math.inf


class Pid:
    """PID on an error with a braking-profile output cap, an integral zone and anti-windup.

    ``step(now, e)`` returns ``clamp(kp e + ki I + kd de/dt, +-cap(e))`` where ``cap(e) =
    min(limit, sqrt(2 decel |e|))``: far from the target the cap (time-optimal braking) rules,
    near it the linear terms do. Idempotent in time (dt = 0 integrates and differentiates nothing).
    """

    def __init__(
        self, kp: float, ki: float, kd: float, limit: float, decel: float, i_zone: float, i_max: float
    ) -> None:
        self.kp, self.ki, self.kd = kp, ki, kd
        self.limit, self.decel = limit, decel
        self.i_zone, self.i_max = i_zone, i_max
        self.reset()

    def reset(self) -> None:
        self.integral = 0.0
        self._last: tuple[float, float] | None = None
        self._deriv = 0.0

    def step(self, now: float, e: float) -> float:
        if self._last is not None and now > self._last[0]:
            dt = now - self._last[0]
            if abs(e) < self.i_zone:
                self.integral += e * dt
                if self.ki > 0:
                    bound = self.i_max / self.ki
                    self.integral = max(-bound, min(bound, self.integral))
            else:
                self.integral = 0.0
            # Low-pass the derivative: it is taken on a noisy pose.
            self._deriv += 0.5 * ((e - self._last[1]) / dt - self._deriv)
            self._last = (now, e)
        elif self._last is None:
            self._last = (now, e)
        u = self.kp * e + self.ki * self.integral + self.kd * self._deriv
        cap = min(self.limit, math.sqrt(2.0 * self.decel * abs(e)))
        return max(-cap, min(cap, u))


class GoToPhase(StrEnum):
    ROTATE = "rotate"  # turn toward the next waypoint
    DRIVE = "drive"  # drive to it, steering on heading
    FINAL_HEADING = "final_heading"  # at the goal, turn to the requested heading
    DONE = "done"


@dataclass(frozen=True, slots=True)
class GoToConfig:
    heading_kp: float = 6.0  # 1/s
    heading_ki: float = 1.0  # 1/s^2
    heading_kd: float = 0.0
    distance_kp: float = 3.0  # 1/s
    distance_kd: float = 0.0
    brake_margin: float = 0.8  # brake with this share of the acceleration limit (motor lag eats the rest)
    aim_tol_rad: float = math.radians(3.0)  # start driving when the heading error settles below this
    aim_window_s: float = 0.06
    reaim_rad: float = math.radians(35.0)  # while driving, a larger heading error means turn again
    near_radius_m: float = 0.08  # inside it, hold the heading and close the along-track error
    approach_v_min: float = 0.1  # m/s: inside near_radius, no slower than this until within arrive_tol_m
    arrive_tol_m: float = 0.01  # mean distance error over the window
    arrive_spread_m: float = 0.015  # passing through the goal is not arrival
    arrive_window_s: float = 0.15
    retry_m: float = 0.015  # along-track closed but this far off (window mean): aim again
    max_retries: int = 3
    settle_m: float = 0.025  # after the final heading, still this far off (the pose moved on): go again
    heading_tol_rad: float = math.radians(1.0)  # final heading: window mean and spread
    heading_window_s: float = 0.12
    heading_spread_rad: float = math.radians(0.5)  # still turning through the goal is not arrival
    waypoint_tol_m: float = 0.10  # intermediate waypoints are passed, not settled on


@dataclass(frozen=True, slots=True)
class GoToCommand:
    v: float
    omega: float
    phase: GoToPhase
    distance_m: float  # to the final goal, straight line
    drive_distance_m: float | None = None  # set on the tick that starts a drive (for the guard)
    waypoint_index: int = 0


class GoToController:
    """Rotate-then-drive through waypoints to a goal, with an optional final heading."""

    def __init__(self, limits: MotionLimits | None = None, config: GoToConfig | None = None) -> None:
        self.limits = limits or MotionLimits()
        self.config = config or GoToConfig()
        c, lim = self.config, self.limits
        self._heading = Pid(
            c.heading_kp, c.heading_ki, c.heading_kd, lim.omega_max, c.brake_margin * lim.alpha_max, 0.3, 0.3
        )
        self._distance = Pid(c.distance_kp, 0.0, c.distance_kd, lim.v_max, c.brake_margin * lim.a_max, 0.0, 0.0)
        self._aim = ArrivalWindow(c.aim_window_s, c.aim_tol_rad, 2 * c.aim_tol_rad, min_samples=2)
        self._arrive = ArrivalWindow(c.arrive_window_s, c.arrive_tol_m, c.arrive_spread_m)
        self._along = ArrivalWindow(c.arrive_window_s, c.arrive_tol_m, c.arrive_spread_m)
        self._turned = ArrivalWindow(c.heading_window_s, c.heading_tol_rad, c.heading_spread_rad)
        self.waypoints: list[Point] = []
        self.index = 0
        self.theta: float | None = None
        self.phase = GoToPhase.DONE
        self.retries = 0
        self._correcting = False  # closing a pose that settled during the final turn

    @property
    def goal(self) -> Point | None:
        return self.waypoints[-1] if self.waypoints else None

    @property
    def active(self) -> bool:
        return self.phase is not GoToPhase.DONE

    def start(self, waypoints: Sequence[Point], theta: float | None = None) -> None:
        """Go through ``waypoints`` (the last one is the goal), then turn to ``theta`` if given."""
        if not waypoints:
            raise ValueError("go-to needs at least one waypoint")
        self.waypoints = [(float(x), float(y)) for x, y in waypoints]
        self.index = 0
        self.theta = theta
        self.retries = 0
        self._correcting = False
        self._enter(GoToPhase.ROTATE)

    def cancel(self) -> None:
        self.phase = GoToPhase.DONE

    def insert_waypoint(self, point: Point) -> None:
        """Put ``point`` before the current waypoint (the pilot cutting a drive short), same phase."""
        if self.phase is GoToPhase.DONE or self.phase is GoToPhase.FINAL_HEADING:
            raise ValueError(f"no leg to cut short in phase {self.phase.value}")
        self.waypoints.insert(self.index, (float(point[0]), float(point[1])))

    def resume(self) -> None:
        """After a pause or a blocked spell: start the current leg afresh (the robot may have moved)."""
        if self.phase is not GoToPhase.DONE:
            self._enter(GoToPhase.FINAL_HEADING if self.phase is GoToPhase.FINAL_HEADING else GoToPhase.ROTATE)

    def _enter(self, phase: GoToPhase) -> None:
        self.phase = phase
        self._heading.reset()
        self._distance.reset()
        self._aim.reset()
        self._arrive.reset()
        self._along.reset()
        self._turned.reset()

    def step(self, now: float, pose: Pose) -> GoToCommand:
        # Bounded: every transition below moves forward or is limited by ``retries``.
        for _ in range(8):
            cmd = self._step(now, pose)
            if cmd is not None:
                return cmd
        return self._out(0.0, 0.0, pose)  # pragma: no cover - would need a transition cycle

    def _out(self, v: float, omega: float, pose: Pose, drive: float | None = None) -> GoToCommand:
        g = self.goal
        dist = math.hypot(g[0] - pose[0], g[1] - pose[1]) if g else 0.0
        return GoToCommand(v, omega, self.phase, dist, drive, self.index)

    def _step(self, now: float, pose: Pose) -> GoToCommand | None:
        c = self.config
        x, y, th = pose
        if self.phase is GoToPhase.DONE:
            return self._out(0.0, 0.0, pose)
        if self.phase is GoToPhase.FINAL_HEADING:
            assert self.theta is not None
            e = wrap_angle(self.theta - th)
            if self._turned.push(now, e):
                # The pose estimate keeps settling while the robot turns in place: if it now puts
                # the goal a little off, close that (the short way, forward or back) and turn again.
                gx, gy = self.waypoints[-1]
                ex, ey = gx - x, gy - y
                if math.hypot(ex, ey) > c.settle_m and self.retries < c.max_retries:
                    self.retries += 1
                    self._correcting = True
                    # A sideways residue up to settle_m is accepted after the along-track part is
                    # closed: aiming at a spot 2-3 cm away takes a turn of up to 90 deg, and then
                    # the final turn again (2-3 s for a centimetre).
                    if abs(ey * math.cos(th) - ex * math.sin(th)) <= c.settle_m:
                        # Mostly along the heading: close it forward or back without turning.
                        self._enter(GoToPhase.DRIVE)
                        return self._drive(now, pose, gx, gy, True, start=True)
                    self._enter(GoToPhase.ROTATE)
                    return None
                self.phase = GoToPhase.DONE
                return self._out(0.0, 0.0, pose)
            return self._out(0.0, self._heading.step(now, e), pose)

        tx, ty = self.waypoints[self.index]
        last = self.index == len(self.waypoints) - 1
        dx, dy = tx - x, ty - y
        dist = math.hypot(dx, dy)
        bearing = math.atan2(dy, dx)
        e_h = wrap_angle(bearing - th)

        if self.phase is GoToPhase.ROTATE:
            if (last and dist < c.arrive_tol_m) or (not last and dist < c.waypoint_tol_m):
                return self._leg_done(last)
            if last and self.retries > 0 and dist <= c.near_radius_m:
                # A correction of a few centimetres on a spot the robot has just left: put the
                # heading's line through the goal by the shorter total turn (this one plus the final
                # heading's); the drive closes it forward or back.
                e_h = (e_h + math.pi / 2.0) % math.pi - math.pi / 2.0
                if self.theta is not None:
                    other = e_h - math.copysign(math.pi, e_h)
                    if abs(other) + abs(wrap_angle(self.theta - th - other)) < abs(e_h) + abs(
                        wrap_angle(self.theta - th - e_h)
                    ):
                        e_h = other
            if self._aim.push(now, e_h):
                self._enter(GoToPhase.DRIVE)
                return self._drive(now, pose, tx, ty, last, start=True)
            return self._out(0.0, self._heading.step(now, e_h), pose)

        return self._drive(now, pose, tx, ty, last, start=False)

    def _leg_done(self, last: bool) -> GoToCommand | None:
        if not last:
            self.index += 1
            self._enter(GoToPhase.ROTATE)
            return None
        if self.theta is not None:
            self._enter(GoToPhase.FINAL_HEADING)
            return None
        self.phase = GoToPhase.DONE
        return None

    def _drive(self, now: float, pose: Pose, tx: float, ty: float, last: bool, start: bool) -> GoToCommand | None:
        c = self.config
        x, y, th = pose
        dx, dy = tx - x, ty - y
        dist = math.hypot(dx, dy)
        if not last:
            if dist < c.waypoint_tol_m:
                return self._leg_done(last)
            e_h = wrap_angle(math.atan2(dy, dx) - th)
            if abs(e_h) > c.reaim_rad:
                self._enter(GoToPhase.ROTATE)
                return None
            v = self._distance.step(now, dist) * max(0.0, math.cos(e_h))
            return self._out(v, self._heading.step(now, e_h), pose, dist if start else None)
        if dist > c.near_radius_m:
            e_h = wrap_angle(math.atan2(dy, dx) - th)
            if abs(e_h) > c.reaim_rad:
                self._enter(GoToPhase.ROTATE)
                return None
            v = self._distance.step(now, dist) * max(0.0, math.cos(e_h))
            return self._out(v, self._heading.step(now, e_h), pose, dist if start else None)
        # Near the goal the bearing is ill-defined (it swings with every centimetre of pose noise):
        # hold the heading and close the along-track error, forward or back.
        along = dx * math.cos(th) + dy * math.sin(th)
        if self._arrive.push(now, dist):
            return self._leg_done(last)
        if self._along.push(now, along):
            # Along-track closed but off sideways: aim again, or accept a small residue.
            residue = c.settle_m if self._correcting else c.retry_m
            if self._arrive.mean > residue and self.retries < c.max_retries:
                self.retries += 1
                self._enter(GoToPhase.ROTATE)
                return None
            return self._leg_done(last)
        v = self._distance.step(now, along)
        if abs(along) > c.arrive_tol_m:
            # No creeping on the linear term's tail: a floor, still under the braking cap.
            floor = min(c.approach_v_min, math.sqrt(2.0 * self._distance.decel * abs(along)))
            v = math.copysign(max(abs(v), floor), along)
        return self._out(v, 0.0, pose, dist if start else None)
