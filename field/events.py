"""Scripted events of a scenario, applied at their times (the same in lockstep and real time).

The runner executes world events itself: doors, obstacles, wheel slip, the home button, and the
board link (``link_cut``, ``link`` with ``link = "board"``) through its ``cut_link`` callback.
Everything it cannot execute goes to ``on_command(event, t)``: operator commands (``teleop``,
``goal``, ``action``, ``mark``), the other links (``link`` with zenoh, mqtt or lidar) and an agent's
restart (``agent_restart``). A teleop burst is handed over once every ``TELEOP_PERIOD_S`` from its
time until its duration is over, so the handler sends one Teleop per call.
"""

from __future__ import annotations

import functools
import heapq
import logging
import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from fleetlink.field.plans import FloorPlan
from fleetlink.field.scenario import (
    TELEOP_PERIOD_S,
    ActionOrder,
    AgentRestart,
    DoorClose,
    DoorOpen,
    Event,
    GoalOrder,
    LinkCut,
    LinkState,
    MarkPlaced,
    Obstacle,
    PressHome,
    TeleopBurst,
    WheelSlip,
)

if TYPE_CHECKING:  # only the type: the runner needs a world's by_name and set_segments
    from fleetlink.field.world import World

log = logging.getLogger(__name__)

__all__ = ["CommandHandler", "EventRunner", "is_handed_over"]

CommandHandler = Callable[[Event, float], None]
"""``on_command(event, t)``: execute an operator command or a network link change at time ``t``."""

_UNDO, _EVENT = 0, 1  # at the same time, timed effects end before new events begin


def is_handed_over(ev: Event) -> bool:
    """True for events the field cannot execute itself: they go to ``on_command``."""
    if isinstance(ev, LinkState):
        return ev.link != "board"
    return isinstance(ev, TeleopBurst | GoalOrder | ActionOrder | MarkPlaced | AgentRestart)


class EventRunner:
    """Applies due events; undoes timed ones (link cuts, slips) when their duration is over.

    ``cut_link(robot, cut)`` severs or restores a robot's board link: the lockstep run cuts its
    in-process port, the real-time field pauses the board's server. ``on_command`` receives the
    events listed in the module docstring; a scenario that has any needs one, and ``carries_out(event)``
    (if given) says which of them it does: the rest are refused when the runner is made.
    """

    def __init__(
        self,
        events: Sequence[Event],
        plan: FloorPlan,
        world: World,
        cut_link: Callable[[str, bool], None],
        on_command: CommandHandler | None = None,
        carries_out: Callable[[Event], bool] | None = None,
    ) -> None:
        self.plan = plan
        self.world = world
        self.cut_link = cut_link
        self.on_command = on_command
        self.log: list[str] = []
        for ev in events:
            if isinstance(ev, DoorClose | DoorOpen) and ev.door not in plan.doors:
                known = ", ".join(sorted(plan.doors)) or "none"
                raise ValueError(f"event at {ev.at:g} s: plan {plan.name} has no door {ev.door!r} (doors: {known})")
            robot = getattr(ev, "robot", None)
            if robot is not None and robot not in world.by_name:
                raise ValueError(f"event at {ev.at:g} s: no robot {robot!r} in the world")
            if on_command is None and is_handed_over(ev):
                raise ValueError(f"{ev.describe()}: this run has no operator side to execute {ev.kind} events")
            if carries_out is not None and is_handed_over(ev) and not carries_out(ev):
                raise ValueError(f"{ev.describe()}: this run does not carry out {ev.kind} events")
        # (time, phase, order, action): a heap keeps equal times in the order they were scheduled.
        self._queue: list[tuple[float, int, int, Callable[[float], None]]] = []
        self._order = 0
        for ev in sorted(events, key=lambda e: e.at):
            self._schedule(ev.at, _EVENT, functools.partial(self._start, ev))
        self._closed_doors: set[str] = set()
        self._obstacles: list[np.ndarray] = []

    def advance(self, t: float) -> None:
        while self._queue and self._queue[0][0] <= t:
            _, _, _, action = heapq.heappop(self._queue)
            action(t)

    def _schedule(self, at: float, phase: int, action: Callable[[float], None]) -> None:
        heapq.heappush(self._queue, (at, phase, self._order, action))
        self._order += 1

    def _note(self, text: str) -> None:
        self.log.append(text)
        log.info("field event: %s", text)

    def _later(self, at: float, what: str, undo: Callable[[], None]) -> None:
        def run(t: float) -> None:
            undo()
            self._note(f"t={t:.3f} s: {what}")

        self._schedule(at, _UNDO, run)

    def _start(self, ev: Event, t: float) -> None:
        self._note(ev.describe())
        if is_handed_over(ev):
            self._hand_over(ev, t)
            return
        if isinstance(ev, DoorClose):
            self._closed_doors.add(ev.door)
            self._rebuild()
        elif isinstance(ev, DoorOpen):
            self._closed_doors.discard(ev.door)
            self._rebuild()
        elif isinstance(ev, Obstacle):
            pts = list(ev.polygon)
            self._obstacles.append(
                np.array([(*pts[i], *pts[(i + 1) % len(pts)]) for i in range(len(pts))], dtype=float)
            )
            self._rebuild()
        elif isinstance(ev, LinkCut):
            name = ev.robot
            self.cut_link(name, True)
            self._later(ev.at + ev.duration, f"board link of {name} restored", lambda: self.cut_link(name, False))
        elif isinstance(ev, LinkState):  # the board link (the others are handed over)
            self.cut_link(ev.robot, ev.state == "cut")
        elif isinstance(ev, WheelSlip):
            board = self.world.by_name[ev.robot].board
            wheel = 0 if ev.wheel == "left" else 1
            board.slip[wheel] = ev.fraction
            self._later(
                ev.at + ev.duration,
                f"{ev.wheel} wheel of {ev.robot} grips again",
                lambda: board.slip.__setitem__(wheel, 0.0),
            )
        elif isinstance(ev, PressHome):
            self.world.by_name[ev.robot].board.press_home()

    def _hand_over(self, ev: Event, t: float) -> None:
        assert self.on_command is not None  # checked in __init__
        self.on_command(ev, t)
        if isinstance(ev, TeleopBurst):
            # One Teleop per period while the burst lasts: repeats are scheduled from the event's
            # own time so they do not drift with the run's step.
            repeats = max(0, math.ceil(ev.duration / TELEOP_PERIOD_S - 1e-9) - 1)
            handler = self.on_command
            for k in range(1, repeats + 1):
                self._schedule(ev.at + k * TELEOP_PERIOD_S, _EVENT, functools.partial(handler, ev))

    def _rebuild(self) -> None:
        segments = [self.plan.segments(closed_doors=tuple(sorted(self._closed_doors))), *self._obstacles]
        self.world.set_segments(np.vstack(segments))
