"""The console's typed commands (what follows ':'), parsed. Pure: text in, a command value out.

    goal X Y [THETA_DEG]     send the selected robot to (X, Y) m, facing THETA degrees if given
    mark KIND X Y [LABEL]    place a mark (casualty, hazard, ...) at (X, Y) m
    home                     return home
    payload on|off           switch the payload (disinfection lamp)
    stop                     stop every robot

``parse_command(line)`` gives one of the command classes below, ``None`` for a blank line, or a
``CommandError`` whose ``text`` is the notice to show. Nothing here sends anything: the app does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = [
    "USAGE",
    "Command",
    "CommandError",
    "Goal",
    "Home",
    "MarkAt",
    "Payload",
    "StopAll",
    "parse_command",
]

USAGE = "goal X Y [THETA_DEG] | mark KIND X Y [LABEL] | home | payload on|off | stop"


@dataclass(frozen=True, slots=True)
class Goal:
    x: float
    y: float
    theta: float | None
    """Radians in (-pi, pi], or None: the robot keeps the heading it arrives with."""


@dataclass(frozen=True, slots=True)
class MarkAt:
    kind: str
    x: float
    y: float
    label: str
    """The rest of the line, spaces kept as single spaces; '' when none was typed."""


@dataclass(frozen=True, slots=True)
class Home:
    pass


@dataclass(frozen=True, slots=True)
class Payload:
    on: bool


@dataclass(frozen=True, slots=True)
class StopAll:
    pass


Command = Goal | MarkAt | Home | Payload | StopAll


@dataclass(frozen=True, slots=True)
class CommandError:
    """A line that is not a command: ``text`` says why (shown as a warning notice)."""

    line: str
    text: str


def _numbers(line: str, words: list[str]) -> list[float] | CommandError:
    try:
        values = [float(w) for w in words]
    except ValueError as exc:  # float's own message names the word: "could not convert ... 'x'"
        return CommandError(line, f"bad command {line!r}: {exc}")
    if not all(math.isfinite(v) for v in values):
        return CommandError(line, f"bad command {line!r}: coordinates must be finite numbers")
    return values


def parse_command(line: str) -> Command | CommandError | None:
    """The command on ``line``; None if it is blank. The verb is case-insensitive, ``g`` is goal."""
    words = line.split()
    if not words:
        return None
    verb, args = words[0].lower(), words[1:]
    if verb in ("goal", "g") and len(args) in (2, 3):
        nums = _numbers(line, args)
        if isinstance(nums, CommandError):
            return nums
        theta = None
        if len(nums) == 3:
            theta = math.radians(nums[2])
            theta = math.atan2(math.sin(theta), math.cos(theta))
        return Goal(nums[0], nums[1], theta)
    if verb == "mark" and len(args) >= 3:
        nums = _numbers(line, args[1:3])
        if isinstance(nums, CommandError):
            return nums
        return MarkAt(args[0], nums[0], nums[1], " ".join(args[3:]))
    if verb == "home" and not args:
        return Home()
    if verb == "payload" and args in (["on"], ["off"]):
        return Payload(args[0] == "on")
    if verb == "stop" and not args:
        return StopAll()
    return CommandError(line, f"unknown command {line!r}: {USAGE}")
