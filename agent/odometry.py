"""Wheel odometry with a gyro: the board's cumulative wheel distances and integrated yaw in, a pose out.

Pure: ``Odometry.update(t, left_m, right_m, gyro_yaw_rad)`` takes the readings and their time and
returns the odometry-frame pose. The frame starts at (0, 0, 0) and never jumps: a counter reset
(board restart, reconnect) or a gyro restart contributes no motion for that step instead of a leap.

Heading: the gyro's yaw change when a gyro reading is there (the encoders' heading suffers from the
wheel-scale difference, about 0.02 rad per metre on a 0.22 m track with 1 % scale error), the
encoders' ``(dr - dl) / track`` otherwise; ``gyro_weight`` blends the two.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["OdomPose", "Odometry", "wrap_angle"]

_COUNTER_SPAN_M = 2**32 / 1000.0  # the board's s32 millimetre counters wrap at this span
_HALF_SPAN_M = _COUNTER_SPAN_M / 2


def wrap_angle(a: float) -> float:
    """Angle in [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True, slots=True)
class OdomPose:
    """Pose in the odometry frame at time ``t`` (the agent's monotonic clock), with body velocities."""

    t: float
    x: float  # m
    y: float  # m
    theta: float  # rad, wrapped to [-pi, pi)
    v: float  # m/s, forward
    omega: float  # rad/s, counter-clockwise


@dataclass(slots=True)
class Odometry:
    """Integrates cumulative wheel distances (m) and an optional integrated gyro yaw (rad)."""

    wheel_track_m: float = 0.22
    gyro_weight: float = 1.0  # share of the heading change taken from the gyro when it is there
    max_wheel_speed_mps: float = 2.0  # a wheel step faster than this is a counter reset, not motion
    max_turn_rate_rps: float = 10.0  # a gyro step faster than this is a gyro restart
    step_margin_m: float = 0.05  # slack on the reset test for quantisation and jitter
    # counters
    updates: int = 0
    rejected: int = 0  # non-finite readings or time going backwards
    counter_resets: int = 0
    gyro_resets: int = 0
    # state
    _pose: OdomPose = OdomPose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    _last: tuple[float, float, float | None] | None = None  # left, right, gyro yaw of the last update
    last_problem: str = ""

    def __post_init__(self) -> None:
        if not (self.wheel_track_m > 0 and math.isfinite(self.wheel_track_m)):
            raise ValueError(f"wheel_track_m must be a positive number, not {self.wheel_track_m!r}")
        if not 0.0 <= self.gyro_weight <= 1.0:
            raise ValueError(f"gyro_weight is a share (0-1), not {self.gyro_weight!r}")

    @property
    def pose(self) -> OdomPose:
        return self._pose

    def reset_counters(self) -> None:
        """Forget the last readings (e.g. the board session reconnected): the next update is a new baseline."""
        self._last = None

    def update(self, t: float, left_m: float, right_m: float, gyro_yaw_rad: float | None = None) -> OdomPose:
        """Feed one reading (cumulative wheel distances, integrated yaw) taken at time ``t``."""
        pose = self._pose
        if not (math.isfinite(t) and math.isfinite(left_m) and math.isfinite(right_m)) or (
            gyro_yaw_rad is not None and not math.isfinite(gyro_yaw_rad)
        ):
            return self._reject("non-finite reading")
        if self._last is None:
            # First reading (or after reset_counters): a baseline, no motion.
            self._last = (left_m, right_m, gyro_yaw_rad)
            self._pose = OdomPose(t, pose.x, pose.y, pose.theta, 0.0, 0.0)
            self.updates += 1
            return self._pose
        dt = t - pose.t
        if dt < 0.0:
            return self._reject("time went backwards")
        last_l, last_r, last_yaw = self._last
        dl = _counter_delta(left_m, last_l)
        dr = _counter_delta(right_m, last_r)
        limit = self.max_wheel_speed_mps * dt + self.step_margin_m
        if abs(dl) > limit or abs(dr) > limit:
            # The board restarted (counters back near zero) or a reading is corrupt: no motion this step.
            self.counter_resets += 1
            self.last_problem = f"wheel counters jumped ({dl:+.3f} m, {dr:+.3f} m in {dt:.3f} s): re-baselined"
            dl = dr = 0.0
        ds = (dl + dr) / 2.0
        dth = (dr - dl) / self.wheel_track_m
        if gyro_yaw_rad is not None and last_yaw is not None and self.gyro_weight > 0.0:
            dg = wrap_angle(gyro_yaw_rad - last_yaw)
            if abs(dg) > self.max_turn_rate_rps * dt + 0.05:
                self.gyro_resets += 1
                self.last_problem = f"gyro yaw jumped {dg:+.3f} rad in {dt:.3f} s: encoders used for this step"
            else:
                dth = self.gyro_weight * dg + (1.0 - self.gyro_weight) * dth
        self._last = (left_m, right_m, gyro_yaw_rad)
        x, y, th = _arc(pose.x, pose.y, pose.theta, ds, dth)
        v, w = (ds / dt, dth / dt) if dt > 0.0 else (pose.v, pose.omega)
        self._pose = OdomPose(t, x, y, th, v, w)
        self.updates += 1
        return self._pose

    def _reject(self, why: str) -> OdomPose:
        self.rejected += 1
        self.last_problem = why
        return self._pose


def _counter_delta(new: float, old: float) -> float:
    """Difference of two cumulative counters, across the board's s32 millimetre wrap."""
    d = new - old
    if d > _HALF_SPAN_M:
        d -= _COUNTER_SPAN_M
    elif d < -_HALF_SPAN_M:
        d += _COUNTER_SPAN_M
    return d


def _arc(x: float, y: float, th: float, ds: float, dth: float) -> tuple[float, float, float]:
    """Move ``ds`` along a circular arc turning ``dth`` (exact, so closed-form checks hold)."""
    if abs(dth) < 1e-9:
        return x + ds * math.cos(th), y + ds * math.sin(th), wrap_angle(th + dth)
    r = ds / dth
    return (
        x + r * (math.sin(th + dth) - math.sin(th)),
        y - r * (math.cos(th + dth) - math.cos(th)),
        wrap_angle(th + dth),
    )
