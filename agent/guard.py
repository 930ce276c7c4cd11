"""Collision guard: sits between every velocity command and the motors (pure, no I/O).

The rescue-robot seed's rules:

* front ultrasonic nearer than ``stop_distance_m``: forward and turning commands are refused and
  the robot stops; backing away (v < 0) stays allowed. A domestic robot that sweeps to the walls
  (``creep_speed_mps`` > 0) creeps on forward at that speed instead while it follows a path
  planned on its map, the bumper its last stop, and those drive starts are not checked against
  the cone (below);
* go-to, once turned toward the goal: refuse to drive when the obstacle ahead is nearer than the
  drive distance plus ``stop_distance_m`` (the robot would end up inside the safety margin);
* cliff: stop; forward and turning refused, backing away allowed (the cliff sensors look ahead);
* bump: stop; forward and turning refused, backing out allowed;
* another robot (where it reports itself, agent/peers.py) whose body lies in the robot's way ahead
  nearer than the two need to stop short of each other, this one at its speed and that one at the
  speed it closes in at: forward refused (turning in place and backing allowed; a round body
  turning sweeps nothing new). Never crept into: the ultrasonic sees nothing inside its 0.25 m
  minimum, and the bumper is no way to meet a robot.

A reading of ``None`` or outside the sensor's range (0.25-1.5 m on the US-100) means "nothing
seen": the sensor reports no echo as 0 and clamps at its minimum, so an out-of-range value is not
evidence of an obstacle. Non-finite commands are refused as invalid. Every refusal carries a
machine-readable reason and a human text.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

__all__ = [
    "CollisionGuard",
    "GuardConfig",
    "GuardDecision",
    "GuardInputs",
    "Refusal",
    "RefusalReason",
    "RobotAhead",
]


class RefusalReason(StrEnum):
    OBSTACLE_AHEAD = "obstacle_ahead"  # ultrasonic below the stop distance
    ROBOT_AHEAD = "robot_ahead"  # another robot's body in the way, where it reports itself
    OBSTACLE_IN_PATH = "obstacle_in_path"  # go-to: obstacle nearer than drive distance + stop distance
    CLIFF = "cliff"
    BUMP = "bump"
    INVALID_COMMAND = "invalid_command"  # NaN or infinite velocity


@dataclass(frozen=True, slots=True)
class Refusal:
    reason: RefusalReason
    text: str
    distance_m: float | None = None  # the ultrasonic reading that caused it (robot_ahead: the gap), when one did


@dataclass(frozen=True, slots=True)
class GuardConfig:
    stop_distance_m: float = 0.40  # refuse forward/turning below this front reading
    sensor_min_m: float = 0.25  # US-100 range; readings outside it mean "nothing seen"
    sensor_max_m: float = 1.5
    # The seed refuses turning in place near an obstacle (its base was not round). A round base
    # sweeps no new floor when it spins, so such robots may set this True.
    allow_turn_in_place: bool = False
    # A domestic robot that sweeps to the walls: inside the stop distance it creeps on at this speed
    # (m/s) instead of stopping, and a drive start is not refused for what the cone sees; the
    # bumper is the last stop. 0: the seed's rule (stop at the stop distance).
    creep_speed_mps: float = 0.0
    # Another robot ahead (``GuardInputs.robots_ahead``): forward at v refused once the gap is
    # under robot_gap_m + stop(v) + stop(w), stop(u) = u^2 / (2 brake_mps2) + u robot_latency_s,
    # where w is the speed the other closes in at: each robot keeps room for both to stop (it runs
    # the same rule, and two robots meeting head-on would each count only itself and touch). The
    # latency: a control tick of ours and the peer's pose, moved on to now by its own speed.
    # Alone: 0.2 m at 0.5 m/s, 4.5 cm at 0.1; head-on at 0.5 m/s each, 0.38 m.
    robot_gap_m: float = 0.03
    brake_mps2: float = 1.0
    robot_latency_s: float = 0.1

    def __post_init__(self) -> None:
        for name in (
            "stop_distance_m",
            "sensor_min_m",
            "sensor_max_m",
            "creep_speed_mps",
            "robot_gap_m",
            "robot_latency_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"GuardConfig.{name} must be a finite distance >= 0, got {v!r}")
        if self.sensor_min_m >= self.sensor_max_m:
            raise ValueError(
                f"GuardConfig: sensor_min_m ({self.sensor_min_m}) must be below sensor_max_m ({self.sensor_max_m})"
            )
        if not (math.isfinite(self.brake_mps2) and self.brake_mps2 > 0):
            raise ValueError(f"GuardConfig.brake_mps2 must be a finite deceleration > 0, got {self.brake_mps2!r}")


@dataclass(frozen=True, slots=True)
class RobotAhead:
    """Another robot whose body lies in this one's way straight ahead."""

    gap_m: float  # how far this body drives before it touches that one (0: they touch)
    closing_mps: float = 0.0  # how fast that one comes toward this one (0: standing or going away)


@dataclass(frozen=True, slots=True)
class GuardInputs:
    ultrasonic_m: float | None = None  # front range; None or out of range = clear
    cliff: bool = False
    bumped: bool = False
    robots_ahead: tuple[RobotAhead, ...] = ()  # the other robots in the way ahead (agent/peers.py)


@dataclass(frozen=True, slots=True)
class GuardDecision:
    v: float
    omega: float
    refusal: Refusal | None = None

    @property
    def refused(self) -> bool:
        return self.refusal is not None


class CollisionGuard:
    """Stateless filter: a requested (v, omega) and the sensors in, the allowed (v, omega) out."""

    def __init__(self, config: GuardConfig | None = None) -> None:
        self.config = config or GuardConfig()

    def stopping_m(self, v: float) -> float:
        """How far a robot at ``v`` goes before it stands: it brakes after the latency."""
        cfg = self.config
        return v * v / (2.0 * cfg.brake_mps2) + v * cfg.robot_latency_s

    def obstacle_m(self, inputs: GuardInputs) -> float | None:
        """The front reading if it is a valid echo inside the sensor's range, else None."""
        d = inputs.ultrasonic_m
        cfg = self.config
        if d is None or not math.isfinite(d) or d < cfg.sensor_min_m or d > cfg.sensor_max_m:
            return None
        return d

    def filter(
        self,
        v: float,
        omega: float,
        inputs: GuardInputs,
        *,
        goto_drive_distance_m: float | None = None,
        on_path: bool = False,
    ) -> GuardDecision:
        """``on_path``: the robot follows a path planned on its map, which the map says is clear;
        only there may it creep (``creep_speed_mps``): straight at a goal with no map, or driven
        by hand, it would creep into every wall on the way."""
        if not (math.isfinite(v) and math.isfinite(omega)):
            return GuardDecision(
                0.0, 0.0, Refusal(RefusalReason.INVALID_COMMAND, f"invalid command v={v} omega={omega}")
            )
        cfg = self.config
        backing = v < 0.0
        forward = v > 0.0
        turning_in_place = v == 0.0 and omega != 0.0
        if backing:
            # Backing away is always allowed: it is how a robot gets out of every situation below.
            return GuardDecision(v, omega)
        moving = forward or turning_in_place
        if inputs.cliff and moving:
            return GuardDecision(0.0, 0.0, Refusal(RefusalReason.CLIFF, "cliff ahead: only backing away is allowed"))
        if inputs.bumped and moving:
            return GuardDecision(0.0, 0.0, Refusal(RefusalReason.BUMP, "bumper pressed: only backing out is allowed"))
        for robot in inputs.robots_ahead if forward else ():
            gap, w = robot.gap_m, max(0.0, robot.closing_mps) if math.isfinite(robot.closing_mps) else math.inf
            need = cfg.robot_gap_m + self.stopping_m(v) + self.stopping_m(w)
            if not gap >= need:  # (NaN: refused too)
                coming = f", it coming at {w:.2f} m/s" if w > 0.0 else ""
                return GuardDecision(
                    0.0,
                    0.0,
                    Refusal(
                        RefusalReason.ROBOT_AHEAD,
                        f"another robot {gap:.2f} m ahead (< {need:.2f} m at {v:.2f} m/s{coming}): driving forward"
                        " refused, turning and backing away allowed",
                        max(0.0, gap) if math.isfinite(gap) else 0.0,
                    ),
                )
        d = self.obstacle_m(inputs)
        creeping = on_path and cfg.creep_speed_mps > 0.0
        if d is not None and d < cfg.stop_distance_m and forward and creeping:
            return GuardDecision(min(v, cfg.creep_speed_mps), omega)
        if (
            d is not None
            and d < cfg.stop_distance_m
            and (forward or (turning_in_place and not cfg.allow_turn_in_place))
        ):
            what = "driving forward" if forward else "turning"
            return GuardDecision(
                0.0,
                0.0,
                Refusal(
                    RefusalReason.OBSTACLE_AHEAD,
                    f"obstacle {d:.2f} m ahead (< {cfg.stop_distance_m:.2f} m): {what} refused, backing away allowed",
                    d,
                ),
            )
        if forward and goto_drive_distance_m is not None and d is not None and not creeping:
            need = goto_drive_distance_m + cfg.stop_distance_m
            if d < need:
                return GuardDecision(
                    0.0,
                    0.0,
                    Refusal(
                        RefusalReason.OBSTACLE_IN_PATH,
                        f"obstacle {d:.2f} m ahead, goal {goto_drive_distance_m:.2f} m away needs {need:.2f} m clear",
                        d,
                    ),
                )
        return GuardDecision(v, omega)
