"""Open-loop motion for field-only runs: wander, a script, or idle, straight onto the boards.

A run of the field alone (``FieldRun`` with no agents: physics and lidar benchmarks, plan checks)
still needs its robots to move. These programs read the simulated board's own sensors (front
ultrasonic, bumpers) and set its wheel velocity directly, as a Control Bus velocity request would.
They are not agents: a run with agents (``fleetlink.site.lockstep``) drives every board through
its bytes, and turns a robot's ``script`` into operator teleop instead.

Pure: sensor readings and the time in, a velocity command out.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from fleetlink.field.board import SimulatedBoard
from fleetlink.field.scenario import RobotSpec

__all__ = ["Motion", "Wanderer", "motion_for", "scripted"]

Motion = Callable[[SimulatedBoard, float], tuple[float, float]]
"""A board and the time in, the body velocity (v m/s, omega rad/s) out."""


@dataclass(slots=True)
class Wanderer:
    """Cruise; on a bump back off and turn; when the ultrasonic sees something near, turn away."""

    speed: float = 0.25
    near: float = 0.6  # m
    rng: random.Random = field(default_factory=random.Random)
    turn_sign: float = 1.0
    turn_until: float = 0.0

    def command(self, front_m: float, bumped: bool, t: float) -> tuple[float, float]:
        if t >= self.turn_until and (bumped or 0 < front_m < self.near):
            self.turn_sign = 1.0 if self.rng.random() < 0.5 else -1.0
            self.turn_until = t + 0.4 + self.rng.random() * 1.2
        if t < self.turn_until:
            return (-0.08 if bumped else 0.0), 1.2 * self.turn_sign
        return self.speed, 0.0

    def __call__(self, board: SimulatedBoard, t: float) -> tuple[float, float]:
        st = board.state
        return self.command(board.ultrasonic(), st.bumped_left or st.bumped_right, t)


def scripted(script: Sequence[tuple[float, float, float]], t: float) -> tuple[float, float]:
    """The command of the last script row whose time has come; (0, 0) before the first."""
    v = w = 0.0
    for at, sv, sw in script:
        if at > t:
            break
        v, w = sv, sw
    return v, w


def motion_for(spec: RobotSpec, seed: int) -> Motion:
    """The open-loop motion a scenario asks for: wander, its script, or standing still."""
    if spec.drive == "wander":
        return Wanderer(spec.speed, rng=random.Random(seed))
    if spec.drive == "script":
        script = spec.script
        return lambda board, t: scripted(script, t)
    return lambda board, t: (0.0, 0.0)
