"""The UV lamp's interlocks: when it must go off, and why it may not go on (pure).

UV-C burns skin and eyes in seconds, so the lamp is the one payload with interlocks of its own.
Two kinds of rule keep it off:

* **Events** that stop the robot switch every payload off as they happen: a stop (anyone's,
  stop-all included), the e-stop (an operator's or the button), the deadman of a moving robot.
  They are effects in the pilot's state machine (``Do.CUT_PAYLOAD``, agent/pilot_machine.py).
* **States** in which the lamp must be off, checked here every control tick and before any
  lamp-on command: ``lamp_interlock(situation)`` returns the first reason that holds, or None.

  - the e-stop is latched;
  - the robot is out of contact with its operators (agent/contact.py), unless its configuration
    keeps the payload on while out of contact;
  - a bumper or a cliff sensor is triggered (something, or someone, is against the robot);
  - the lamp's operator no longer holds the control lease (it ran out, or was given back);
  - the lamp's radius reaches into a zone an operator declared "people present";
  - the robot's board is not connected, or has no lamp.

The agent (agent/core.py) switches the lamp off when a reason appears while it is on (event
``interlock``, with the reason) and refuses a lamp-on command while one holds (the ack says why).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from fleetlink.shared.geometry import Point, point_in_polygon, polygon_distance

__all__ = ["LampSituation", "PeopleZone", "lamp_interlock", "zone_reached"]


@dataclass(frozen=True, slots=True)
class PeopleZone:
    """An area an operator declared occupied by people: no UV light may reach into it."""

    name: str
    polygon: tuple[Point, ...]
    """At least three corners, metres, site frame."""


@dataclass(frozen=True, slots=True)
class LampSituation:
    estop: bool = False
    comms_lost: bool = False
    """Out of contact, and the configuration switches the payload off then."""
    bumped: bool = False
    cliff: bool = False
    lease_held: bool = True
    """The operator who switched the lamp on (or asks to) holds the robot's lease."""
    board_connected: bool = True
    has_lamp: bool = True
    position: Point | None = None
    """The robot's position in the site frame (None: not localised)."""
    lamp_radius_m: float = 0.0
    """How far the lamp's light is dangerous, m."""
    zones: tuple[PeopleZone, ...] = ()


def lamp_interlock(s: LampSituation) -> str | None:
    """The first reason the lamp must be off in situation ``s``, or None when it may be on."""
    if not s.board_connected:
        return "the board is not connected"
    if not s.has_lamp:
        return "this robot has no UV lamp"
    if s.estop:
        return "e-stop latched"
    if s.comms_lost:
        return "out of contact with the operators"
    if s.bumped:
        return "a bumper is pressed"
    if s.cliff:
        return "a cliff sensor is triggered"
    if not s.lease_held:
        return "its operator no longer holds the control lease"
    if s.zones:
        if s.position is None:
            return "people-present zones are declared and the robot is not localised"
        zone = zone_reached(s.position, s.lamp_radius_m, s.zones)
        if zone is not None:
            return f"the lamp's {s.lamp_radius_m:g} m radius reaches people-present zone {zone!r}"
    return None


def zone_reached(p: Point, radius: float, zones: Sequence[PeopleZone]) -> str | None:
    """The first zone that a disc of ``radius`` around ``p`` touches (inside it, or within
    ``radius`` of an edge), or None."""
    for zone in zones:
        if point_in_polygon(*p, zone.polygon) or polygon_distance(*p, zone.polygon) <= radius:
            return zone.name
    return None
