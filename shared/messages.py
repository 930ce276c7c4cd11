"""Fleetlink messages: every top-level message on the wire, one frozen dataclass each.

Each class derives from ``wire.Message`` (so it carries a ``header``), sets ``TOPIC`` and is
``@register``-ed so ``wire.decode_any``/``wire.decode_key`` can find it. Fields are keyword-only
(``kw_only=True``) so adding one never silently shifts positional arguments. Sequences are tuples
so messages stay immutable and hashable; ``encode`` also accepts lists.

Later issues add their messages here, and a row to the table in docs/wire-contract.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, ClassVar

from .wire import Message, bounded, register, sized

__all__ = ["MAX_BOARD_ERRORS", "MAX_BOARD_SENSORS", "BoardStatus", "Truth"]

MAX_BOARD_ERRORS = 16
MAX_BOARD_SENSORS = 16


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class BoardStatus(Message):
    """The robot agent's view of its control board, published on ``fleetlink/v1/<robot>/board``."""

    TOPIC: ClassVar[str] = "board"

    connected: bool
    """The agent currently has a working link to the board."""
    model: Annotated[str, sized(64)]
    firmware: Annotated[str, sized(64)]
    battery_percent: Annotated[float, bounded(0.0, 100.0)]
    charging: bool
    on_dock: bool
    health_flags: Annotated[int, bounded(0, 255)]
    """Board health bitmap as reported by the firmware (one byte)."""
    errors: Annotated[tuple[str, ...], sized(MAX_BOARD_ERRORS, item=sized(256))]
    """Active error descriptions, at most 16 of at most 256 characters."""
    left_mm: float
    """Cumulative left wheel distance since board start, millimetres (signed)."""
    right_mm: float
    """Cumulative right wheel distance since board start, millimetres (signed)."""
    bumpers: Annotated[int, bounded(0)]
    """Bumper bitmap, bit i set while bumper i is pressed."""
    sensors_m: Annotated[tuple[float, ...], sized(MAX_BOARD_SENSORS, item=bounded(0.0))]
    """Range sensor readings in metres, at most 16, each >= 0."""
    watchdog_tripped: bool
    """The board's motor watchdog has stopped the motors."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Truth(Message):
    """Ground truth about one simulated robot, published by the field on ``fleetlink/v1/sim/<robot>/truth``.

    Only the simulator publishes it; agents must never use it (scoring compares against it).
    """

    TOPIC: ClassVar[str] = "truth"

    sim_time_s: Annotated[float, bounded(0.0)]
    """Simulated seconds since the field started."""
    x: float
    """Metres, in the plan's frame (the UWB frame)."""
    y: float
    theta: Annotated[float, bounded(-3.2, 3.2)]
    """Heading, radians, counter-clockwise from +x, in [-pi, pi]."""
    v: float
    """Forward speed over ground, m/s."""
    omega: float
    """Turn rate, rad/s."""
    bumped: bool
    """A bump switch is pressed."""
