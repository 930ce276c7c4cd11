"""Contact with the operators, and what the robot does when it loses it: the comms-loss policy (pure).

The robot is in contact while it hears its operators: any message from an allowed operator, on
any link (commands, and the lease renewals a console sends every couple of seconds for the robots
it holds, operator/fleet.py ``LeaseRenewal``). It has lost contact when an operator who asked for
its lease holds it (a console working with it, which renews the lease every couple of seconds; a
script that only sends orders never counts) and nothing from any operator has arrived for
``timeout_s``. Then
the policy (robot.toml ``[comms] policy``, or the ``setCommsPolicy`` action) says what it does:

* ``stop``: stop where it is;
* ``retrace``: drive back along its own recorded path (``trail``: a point every ``spacing_m`` of
  travel) to the last pose at which it heard an operator, and wait there -- the way it came is
  free, and the radio reached it there;
* ``home``: return home.

Every payload goes off while out of contact, unless ``payload_on_loss``. The first message heard
again ends it: a retrace stops where it is (the operator is back in charge), a return home goes
on, and the robot reports what it did (``Regained.text``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from fleetlink.shared.geometry import simplify
from fleetlink.shared.messages import CommsPolicy

__all__ = ["DEFAULT_TIMEOUT_S", "ContactKeeper", "Lost", "Regained"]

DEFAULT_TIMEOUT_S = 6.0
"""Silence after which a held robot counts as out of contact: three missed lease renewals (every
2 s, operator/fleet.py) -- a lost packet or a failover is not a lost link."""

Point = tuple[float, float]


@dataclass(frozen=True, slots=True)
class Lost:
    """Contact lost at ``t``: do ``policy``; ``path`` is the way back for a retrace (newest first,
    ending at the last pose where an operator was heard), () for the other policies."""

    t: float
    policy: CommsPolicy
    path: tuple[Point, ...]
    silent_s: float


@dataclass(frozen=True, slots=True)
class Regained:
    t: float
    out_s: float
    """How long the robot was out of contact."""
    text: str
    """What it did meanwhile, for the operator."""


class ContactKeeper:
    def __init__(
        self,
        policy: CommsPolicy = CommsPolicy.STOP,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        *,
        payload_on_loss: bool = False,
        spacing_m: float = 0.2,
        max_points: int = 5000,
    ) -> None:
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self.policy = policy
        self.timeout_s = timeout_s
        self.payload_on_loss = payload_on_loss
        self.spacing_m = spacing_m
        self.trail: deque[Point] = deque(maxlen=max_points)
        """Where the robot has been, oldest first, a point every ``spacing_m``."""
        self.lost_at: float | None = None
        self.action = ""
        """What the policy is doing: '' in contact, else stopped, retracing, waiting (retraced, at
        the contact point), homing, home (arrived)."""
        self.target: Point | None = None
        """Where the policy's drive goes (the contact point, or home)."""
        self.travelled_m = 0.0
        """How far the robot drove while out of contact."""
        self._heard_at: float | None = None
        self._heard_pose: Point | None = None
        self._heard_trail = 0
        """Points appended to the trail before the last contact, counted since the start."""
        self._appended = 0
        self._last: Point | None = None

    @property
    def lost(self) -> bool:
        return self.lost_at is not None

    def silent_s(self, now: float) -> float:
        return 0.0 if self._heard_at is None else max(0.0, now - self._heard_at)

    def set_policy(self, policy: CommsPolicy | str) -> CommsPolicy:
        """ValueError naming the choices for anything else."""
        try:
            self.policy = CommsPolicy(policy)
        except ValueError:
            choices = ", ".join(p.value for p in CommsPolicy)
            raise ValueError(f"unknown comms-loss policy {policy!r} (one of: {choices})") from None
        return self.policy

    def moved(self, x: float, y: float) -> None:
        """The robot's current pose (every tick): the trail grows every ``spacing_m``."""
        if not (math.isfinite(x) and math.isfinite(y)):
            return
        last = self._last
        if last is not None:
            d = math.hypot(x - last[0], y - last[1])
            if d < self.spacing_m:
                return
            if self.lost:
                self.travelled_m += d
        self._last = (x, y)
        self.trail.append((x, y))
        self._appended += 1

    def heard(self, now: float, x: float, y: float) -> Regained | None:
        """An operator's message arrived, with the robot at (x, y). Regained if it had lost contact."""
        self.moved(x, y)
        self._heard_at = now
        if math.isfinite(x) and math.isfinite(y):
            self._heard_pose = (x, y)
        self._heard_trail = self._appended
        if self.lost_at is None:
            return None
        out_s = now - self.lost_at
        what = {
            "stopped": "stopped where it was",
            "retracing": "was retracing its path",
            "waiting": "retraced its path and waited",
            "homing": "was returning home",
            "home": "returned home",
        }.get(self.action, self.action or "stopped")
        text = f"contact regained after {out_s:.1f} s out of contact: {what}, {self.travelled_m:.1f} m driven"
        self.lost_at = None
        self.action = ""
        self.target = None
        self.travelled_m = 0.0
        return Regained(now, out_s, text)

    def tick(self, now: float, engaged: bool) -> Lost | None:
        """Lost when ``engaged`` (somebody holds the lease) and nobody was heard for ``timeout_s``."""
        if self.lost_at is not None or not engaged or self._heard_at is None:
            return None
        silent = now - self._heard_at
        if silent < self.timeout_s:
            return None
        self.lost_at = now
        self.travelled_m = 0.0
        path = self.retrace_path() if self.policy is CommsPolicy.RETRACE else ()
        return Lost(now, self.policy, path, silent)

    def retrace_path(self) -> tuple[Point, ...]:
        """The way back to the last pose where an operator was heard: the trail since then,
        newest first, simplified (within 5 cm of the way driven), ending at that pose."""
        trail = list(self.trail)
        new = self._appended - self._heard_trail  # points laid since the last contact
        pts = trail[-new:] if new > 0 else []
        pts.reverse()
        # If the trail no longer reaches back to the contact point, go as far back as it does.
        if self._heard_pose is not None and new <= len(trail):
            pts.append(self._heard_pose)
        return tuple(simplify(pts, 0.05))
