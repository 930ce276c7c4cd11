"""Stand-in drivers for simulated robots until the agents drive them: wander, a script, or idle.

Pure: a board snapshot and the time in, a velocity command out.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from fleetlink.agent.board.session import BoardSnapshot
from fleetlink.field.scenario import RobotSpec

__all__ = ["Driver", "Wanderer", "driver_for", "scripted"]

Driver = Callable[[BoardSnapshot, float], tuple[float, float]]


@dataclass(slots=True)
class Wanderer:
    """Cruise; on a bump back off and turn; when the ultrasonic sees something near, turn away."""

    speed: float = 0.25
    near: float = 0.6  # m
    rng: random.Random = field(default_factory=random.Random)
    turn_sign: float = 1.0
    turn_until: float = 0.0

    def command(self, snap: BoardSnapshot, t: float) -> tuple[float, float]:
        if not snap.connected or snap.sensors is None:
            return 0.0, 0.0
        bumped = snap.bumpers is not None and (snap.bumpers.triggered(0) or snap.bumpers.triggered(1))
        front = snap.sensors.distances[0]
        if t >= self.turn_until and (bumped or 0 < front < self.near):
            self.turn_sign = 1.0 if self.rng.random() < 0.5 else -1.0
            self.turn_until = t + 0.4 + self.rng.random() * 1.2
        if t < self.turn_until:
            return (-0.08 if bumped else 0.0), 1.2 * self.turn_sign
        return self.speed, 0.0


def scripted(script: Sequence[tuple[float, float, float]], t: float) -> tuple[float, float]:
    """The command of the last script row whose time has come; (0, 0) before the first."""
    v = w = 0.0
    for at, sv, sw in script:
        if at > t:
            break
        v, w = sv, sw
    return v, w


def driver_for(spec: RobotSpec, seed: int) -> Driver:
    """The stand-in driver a scenario asks for: wander, its script, or idle."""
    if spec.drive == "wander":
        return Wanderer(spec.speed, rng=random.Random(seed)).command
    if spec.drive == "script":
        script = spec.script
        return lambda snap, t: scripted(script, t)
    return lambda snap, t: (0.0, 0.0)
