"""Control lease, the robot's side: who may drive this robot, until when. Pure; time passed in.

The agent is the authority (several consoles may ask at once; the robot decides). Rules:

* A request is granted when nobody holds the lease, it has run out, or the requester already
  holds it (a renewal). Otherwise it is refused and the current holder is named.
* Only the holder can release it.
* ``allows(sender, now)`` is what the agent checks before running a motion command (teleop,
  order); stop, cancel and e-stop are always allowed, from anyone (safety before features).
* Driving takes the lease: a motion command from an allowed operator while the lease is free
  ``claim``s it for ``DRIVE_LEASE_S`` (and each further one renews it), so whoever is driving
  holds the lease, every console shows who, and a second operator is refused until it is
  released or runs out. Nobody ever drives without holding it.

The agent runtime calls ``request`` for each ``LeaseRequest`` it receives and publishes
``LeaseKeeper.message_fields(now)`` as a ``Lease`` on change and at 1 Hz::

    keeper = LeaseKeeper()
    ok, reason = keeper.request(msg.header.sender, msg.duration_s, msg.release, now, wall)
    if not keeper.allows(cmd.header.sender, now): ack REJECTED with keeper.refusal(cmd.header.sender, now)
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ALWAYS_ALLOWED_ACTIONS", "DRIVE_LEASE_S", "LeaseKeeper", "LeaseView"]

ALWAYS_ALLOWED_ACTIONS = frozenset({"stop", "cancel", "estop", "pause"})
"""Instant actions any operator may send without the lease."""

DRIVE_LEASE_S = 15.0
"""How long driving holds the lease after the last motion command (an explicit request may be longer)."""


@dataclass(frozen=True, slots=True)
class LeaseView:
    holder: str
    """'' when nobody holds it."""
    until_wall: float
    """Epoch seconds when it runs out (0 when free): what ``Lease.until`` carries."""


class LeaseKeeper:
    def __init__(self, max_duration_s: float = 300.0) -> None:
        if not max_duration_s > 0:
            raise ValueError(f"max_duration_s must be > 0, got {max_duration_s!r}")
        self.max_duration_s = max_duration_s
        self._holder = ""
        self._until = 0.0  # monotonic
        self._until_wall = 0.0

    def _expire(self, now: float) -> None:
        if self._holder and now >= self._until:
            self._holder, self._until, self._until_wall = "", 0.0, 0.0

    def request(self, sender: str, duration_s: float, release: bool, now: float, wall: float) -> tuple[bool, str]:
        """Handle one ``LeaseRequest``. Returns (granted or released, reason for a refusal)."""
        self._expire(now)
        if release:
            if self._holder != sender:
                return False, f"{sender} does not hold the lease" + (f" ({self._holder} does)" if self._holder else "")
            self._holder, self._until, self._until_wall = "", 0.0, 0.0
            return True, ""
        if self._holder and self._holder != sender:
            return False, f"lease held by {self._holder} for {self._until - now:.0f} s more"
        duration = min(max(duration_s, 0.0), self.max_duration_s)
        if duration <= 0:
            return False, "lease duration must be > 0"
        self._holder, self._until, self._until_wall = sender, now + duration, wall + duration
        return True, ""

    def claim(self, sender: str, duration_s: float, now: float, wall: float) -> bool:
        """Take the lease for driving: granted when free, renewed (never shortened) for its holder."""
        self._expire(now)
        if self._holder and self._holder != sender:
            return False
        duration = min(max(duration_s, 0.0), self.max_duration_s)
        if not self._holder or now + duration > self._until:
            self._holder, self._until, self._until_wall = sender, now + duration, wall + duration
        return True

    def allows(self, sender: str, now: float) -> bool:
        """May ``sender`` drive the robot now?"""
        self._expire(now)
        return bool(self._holder) and self._holder == sender

    def refusal(self, sender: str, now: float) -> str:
        """The clear message a refused driver gets back (in the Ack's reason)."""
        self._expire(now)
        if not self._holder:
            return f"{sender} has no control lease: take the lease first"
        return f"robot is leased to {self._holder} for {self._until - now:.0f} s more"

    def view(self, now: float) -> LeaseView:
        self._expire(now)
        return LeaseView(self._holder, self._until_wall)
