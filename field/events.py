"""Scripted events of a scenario, applied to a world at their times (the same in lockstep and real time)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import numpy as np

from fleetlink.field.plans import FloorPlan
from fleetlink.field.scenario import Event
from fleetlink.field.world import World

log = logging.getLogger(__name__)

__all__ = ["EventRunner"]


class EventRunner:
    """Applies due events; undoes timed ones (link cuts, slips) when their duration is over.

    ``cut_link(robot, cut)`` severs or restores a robot's board link: the lockstep run cuts its
    in-process port, the real-time field pauses the board's server.
    """

    def __init__(
        self, events: Sequence[Event], plan: FloorPlan, world: World, cut_link: Callable[[str, bool], None]
    ) -> None:
        self.plan = plan
        self.world = world
        self.cut_link = cut_link
        self.log: list[str] = []
        self._pending = sorted(events, key=lambda e: e.at)
        for ev in self._pending:
            if ev.kind in ("door_close", "door_open") and ev.door not in plan.doors:
                known = ", ".join(sorted(plan.doors)) or "none"
                raise ValueError(f"event at {ev.at:g} s: plan {plan.name} has no door {ev.door!r} (doors: {known})")
            if ev.robot is not None and ev.robot not in world.by_name:
                raise ValueError(f"event at {ev.at:g} s: no robot {ev.robot!r} in the world")
        self._undo: list[tuple[float, str, Callable[[], None]]] = []
        self._closed_doors: set[str] = set()
        self._obstacles: list[np.ndarray] = []

    def advance(self, t: float) -> None:
        while self._undo and self._undo[0][0] <= t:
            _, what, undo = self._undo.pop(0)
            undo()
            self._note(f"t={t:.3f} s: {what}")
        while self._pending and self._pending[0].at <= t:
            ev = self._pending.pop(0)
            self._apply(ev, t)
            self._note(ev.describe())

    def _note(self, text: str) -> None:
        self.log.append(text)
        log.info("field event: %s", text)

    def _apply(self, ev: Event, t: float) -> None:
        if ev.kind == "door_close":
            self._closed_doors.add(ev.door or "")
            self._rebuild()
        elif ev.kind == "door_open":
            self._closed_doors.discard(ev.door or "")
            self._rebuild()
        elif ev.kind == "obstacle":
            pts = list(ev.polygon)
            self._obstacles.append(
                np.array([(*pts[i], *pts[(i + 1) % len(pts)]) for i in range(len(pts))], dtype=float)
            )
            self._rebuild()
        else:
            name = ev.robot or ""
            board = self.world.by_name[name].board
            if ev.kind == "link_cut":
                self.cut_link(name, True)
                self._later(t + ev.duration, f"board link of {name} restored", lambda: self.cut_link(name, False))
            elif ev.kind == "wheel_slip":
                wheel = 0 if ev.wheel == "left" else 1
                board.slip[wheel] = ev.fraction
                self._later(
                    t + ev.duration,
                    f"{ev.wheel} wheel of {name} grips again",
                    lambda: board.slip.__setitem__(wheel, 0.0),
                )
            elif ev.kind == "press_home":
                board.press_home()

    def _later(self, at: float, what: str, undo: Callable[[], None]) -> None:
        self._undo.append((at, what, undo))
        self._undo.sort(key=lambda item: item[0])

    def _rebuild(self) -> None:
        segments = [self.plan.segments(closed_doors=tuple(sorted(self._closed_doors))), *self._obstacles]
        self.world.set_segments(np.vstack(segments))
