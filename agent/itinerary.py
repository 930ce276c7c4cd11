"""An order's nodes, one after another (pure): where to drive next, which node action to run, how
long the robot still dwells, and why it waits.

    it = Itinerary.of(order, extent_m=100)    # ItineraryError(reason) for an order it cannot run
    step = it.step(now)                        # GoTo(stop, max_v) | RunAction(action) | Finished | None
    it.arrived(now) / it.failed(now, why)      # the pilot's go-to to the current node ended
    it.hold(now, "paused") / it.release(now)   # pause or an interruption, and the resume

The agent's core (agent/core.py) owns the pilot and the payload: it asks ``step`` every control
tick and does what it says (a go-to through ``Pilot.order(..., admitted=True)``, a node action
through its own payload handling), and tells the itinerary what became of it. The itinerary only
keeps count, so the whole order logic is here, testable with plain numbers.

Semantics (VDA 5050 2.1, "order" and "nodes", as far as fleetlink runs them):

* nodes are driven in sequence order, released (base) nodes only; an order whose last released
  node is followed by horizon nodes waits there (``waiting == "horizon"``) for an update;
* at a node its actions run one after another in the order given; ``dwell`` (parameter
  ``duration``, seconds) holds the robot there, and the time counts only while the order runs (a
  pause or an e-stop freezes it); the robot drives on when the last action has finished;
* a node the robot cannot reach (the pilot's route fails: no way there, retreated) is skipped
  and its actions are not run (``skipped``); the order goes on with the next node;
* an update of the running order (same id, higher update id) replaces the nodes; the robot goes on
  from the first node whose sequence id is past the last node it reached (VDA 5050's stitching:
  the update starts at the last base node, which counts as reached);
* the UV lamp as the order last switched it (``lamp``): the core switches it back on after a
  resume, and off when the order ends or is cancelled.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum

__all__ = [
    "DWELL_MAX_S",
    "Finished",
    "GoTo",
    "Itinerary",
    "ItineraryError",
    "RunAction",
    "Stop",
    "StopAction",
]

DWELL_MAX_S = 3600.0
"""The longest dwell one node action may ask for (an hour: a large room's park-in-the-middle)."""

NODE_ACTIONS = ("payload", "dwell")
"""What may run at a node (``ActionType`` values): the payload and standing still."""


class ItineraryError(ValueError):
    """An order the itinerary cannot run; the message says why (for the rejected ack)."""


@dataclass(frozen=True, slots=True)
class StopAction:
    action_id: str
    kind: str  # "payload" | "dwell"
    params: Mapping[str, str]

    @property
    def duration_s(self) -> float:
        return float(self.params["duration"]) if self.kind == "dwell" else 0.0


@dataclass(frozen=True, slots=True)
class Stop:
    """One node: where, the speed cap of the edge leading to it, what to do there."""

    node_id: str
    sequence_id: int
    x: float
    y: float
    theta: float | None
    released: bool = True
    max_v: float | None = None
    actions: tuple[StopAction, ...] = ()
    deviation: float = 0.0
    """m: reached within this of (x, y) when (x, y) itself cannot be (``OrderNode.allowedDeviationXY``)."""
    trajectory: tuple[tuple[float, float], ...] = ()
    """The way here from the node before, as waypoints (the edge's trajectory); (): the robot's own."""


@dataclass(frozen=True, slots=True)
class GoTo:
    stop: Stop


@dataclass(frozen=True, slots=True)
class RunAction:
    stop: Stop
    action: StopAction


@dataclass(frozen=True, slots=True)
class Finished:
    nodes: int
    skipped: tuple[str, ...]


class _Phase(Enum):
    DRIVE = "drive"  # going to stops[index] (asked for the go-to when ``_asked``)
    ACTIONS = "actions"  # at stops[index], running its actions from ``_action``
    DWELL = "dwell"  # at stops[index], standing for ``_dwell_left`` more seconds
    DONE = "done"


def _check_dwell(a: StopAction) -> None:
    raw = a.params.get("duration")
    if raw is None or a.params.keys() - {"duration"}:
        raise ItineraryError(f"action {a.action_id!r}: dwell takes one parameter, duration (seconds)")
    try:
        d = float(raw)
    except ValueError:
        raise ItineraryError(f"action {a.action_id!r}: dwell duration {raw[:16]!r} is not a number") from None
    if not (math.isfinite(d) and 0.0 <= d <= DWELL_MAX_S):
        raise ItineraryError(f"action {a.action_id!r}: dwell duration must be 0-{DWELL_MAX_S:g} s, got {raw[:16]}")


@dataclass(slots=True)
class Itinerary:
    """The nodes of one order and how far the robot has got along them."""

    order_id: str
    update_id: int
    sender: str
    stops: tuple[Stop, ...]
    index: int = 0
    skipped: list[str] = field(default_factory=list)
    last: Stop | None = None
    """The last node reached."""
    waiting: str = ""
    """"" while it runs; else what holds it until a resume (paused, e-stop, stopped, teleop, ...)."""
    lamp: bool = False
    """The UV lamp as this order last switched it."""
    lamp_owed: bool = False
    """A skipped node's lamp-on, switched on at the next node reached rather than where the robot
    gave up (which may be outside the area: a survey's robot still in the corridor)."""
    _phase: _Phase = _Phase.DRIVE
    _asked: bool = False
    _action: int = 0
    _dwell_left: float = 0.0
    _t: float | None = None
    _back: _Phase | None = None
    closest_m: float = math.inf
    """How near the robot came to the current node on the way there (``approach``)."""
    """Moved off the node mid-actions (a teleop): drive back, then carry on in this phase."""

    @classmethod
    def of(
        cls,
        order_id: str,
        update_id: int,
        sender: str,
        stops: Sequence[Stop],
        *,
        extent_m: float = math.inf,
        check_action: Callable[[StopAction], None] | None = None,
    ) -> Itinerary:
        """A checked itinerary: at least one node; positions finite and within ``extent_m``; a
        released node never after a horizon node; node actions of the kinds in ``NODE_ACTIONS``
        (``check_action(action)`` raises ItineraryError for a payload action it refuses)."""
        if not stops:
            raise ItineraryError("an order with nodes needs at least one node")
        horizon = False
        for s in stops:
            if not (math.isfinite(s.x) and math.isfinite(s.y)) or (s.theta is not None and not math.isfinite(s.theta)):
                raise ItineraryError(f"node {s.node_id!r}: position must be finite")
            if abs(s.x) > extent_m or abs(s.y) > extent_m:
                raise ItineraryError(
                    f"node {s.node_id!r} at ({s.x:.4g}, {s.y:.4g}) is outside the site's extent (|x|, |y| <= {extent_m:g} m)"
                )
            if s.released and horizon:
                raise ItineraryError(f"node {s.node_id!r} is released after a horizon node")
            horizon = horizon or not s.released
            for a in s.actions:
                if a.kind not in NODE_ACTIONS:
                    raise ItineraryError(f"action {a.action_id!r}: {a.kind!r} is not a node action (payload, dwell)")
                if a.kind == "dwell":
                    _check_dwell(a)
                elif check_action is not None:
                    check_action(a)
        if not stops[0].released:
            raise ItineraryError("the first node of an order must be released")
        return cls(order_id, update_id, sender, tuple(stops))

    def updated(self, newer: Itinerary) -> Itinerary:
        """``newer`` (an update of this order) carrying on from here: its nodes up to and including
        the last one reached count as passed; the lamp and any hold stay as they are."""
        done = self.last.sequence_id if self.last is not None else -1
        start = 0
        while start < len(newer.stops) and newer.stops[start].sequence_id <= done:
            start += 1
        newer.index = start
        newer.skipped = list(self.skipped)
        newer.last = self.last
        newer.lamp = self.lamp
        newer.lamp_owed = self.lamp_owed
        newer.waiting = self.waiting if self.waiting != "horizon" else ""
        newer._t = self._t
        if start >= len(newer.stops):
            newer._phase = _Phase.DONE
        return newer

    # -- what to do ----------------------------------------------------------------------------

    @property
    def current(self) -> Stop | None:
        return self.stops[self.index] if self.index < len(self.stops) else None

    @property
    def driving(self) -> bool:
        """A go-to to the current node has been asked for and has not ended."""
        return self._phase is _Phase.DRIVE and self._asked

    @property
    def dwell_left_s(self) -> float:
        return self._dwell_left if _Phase.DWELL in (self._phase, self._back) else 0.0

    def step(self, now: float) -> GoTo | RunAction | Finished | None:
        """The next thing to do now, or None (driving, dwelling, or waiting for a resume). Call it
        again after doing what it returned: a node's actions come one per call."""
        self._count(now)
        if self.waiting:
            return None
        if self._phase is _Phase.DWELL:
            if self._dwell_left > 0.0:
                return None
            self._phase = _Phase.ACTIONS
        if self._phase is _Phase.ACTIONS:
            stop = self.stops[self.index]
            if self._action < len(stop.actions):
                a = stop.actions[self._action]
                self._action += 1
                if a.kind == "dwell":
                    self._phase, self._dwell_left = _Phase.DWELL, a.duration_s
                    return self.step(now)
                return RunAction(stop, a)
            self._next()
        if self._phase is _Phase.DONE:
            return Finished(len(self.stops), tuple(self.skipped))
        stop = self.stops[self.index]
        if not stop.released:
            self.waiting = "horizon"
            return None
        if self._asked:
            return None
        self._asked, self.closest_m = True, math.inf
        return GoTo(stop)

    def _count(self, now: float) -> None:
        if self._t is not None and self._phase is _Phase.DWELL and not self.waiting:
            self._dwell_left = max(0.0, self._dwell_left - (now - self._t))
        self._t = now

    def _next(self) -> None:
        self.index += 1
        self._asked, self._action = False, 0
        self._phase = _Phase.DONE if self.index >= len(self.stops) else _Phase.DRIVE

    # -- what became of it ---------------------------------------------------------------------

    def approach(self, x: float, y: float) -> None:
        """The robot is at (x, y) on its way to the current node."""
        cur = self.current
        if cur is not None and self.driving:
            self.closest_m = min(self.closest_m, math.hypot(cur.x - x, cur.y - y))

    def arrived(self, now: float) -> None:
        """The go-to to the current node reached it: its actions run next."""
        self._count(now)
        if self._phase is _Phase.DRIVE and self._asked:
            self.last = self.stops[self.index]
            if self._back is not None:
                self._phase, self._back = self._back, None  # the actions carry on where they were
            else:
                self._phase, self._action = _Phase.ACTIONS, 0

    def failed(self, now: float) -> Stop | None:
        """The go-to to the current node failed (no way there): the node is skipped. Returns it."""
        self._count(now)
        if not (self._phase is _Phase.DRIVE and self._asked):
            return None
        stop = self.stops[self.index]
        self.skipped.append(stop.node_id)
        self._back = None
        self._next()
        return stop

    def hold(self, now: float, why: str) -> None:
        """Wait for a resume (a pause, an e-stop, a stop, a teleop that took over). A go-to that the
        pilot dropped is asked for again on the resume (``interrupted``)."""
        self._count(now)
        if not self.waiting:
            self.waiting = why

    def interrupted(self, now: float, why: str) -> None:
        """The pilot dropped the go-to to the current node (not reached, not failed): ask again on
        the resume."""
        self.hold(now, why)
        if self._phase is _Phase.DRIVE:
            self._asked = False

    def moved(self, now: float, why: str) -> None:
        """Something else moves the robot (a teleop): wait for a resume, then drive back to the
        current node (if the robot was at it) and carry on with its actions and the dwell left."""
        self.interrupted(now, why)
        if self._phase in (_Phase.ACTIONS, _Phase.DWELL):
            self._back, self._phase, self._asked = self._phase, _Phase.DRIVE, False

    def release(self, now: float) -> None:
        """Go on (a resume)."""
        self._count(now)
        self.waiting = ""

    def progress(self) -> dict[str, object]:
        """``OrderProgress`` fields."""
        done = min(self.index, len(self.stops))
        return {
            "nodesTotal": len(self.stops),
            "nodesDone": done,
            "skipped": len(self.skipped),
            "lastNodeId": self.last.node_id if self.last is not None else "",
            "lastNodeSequenceId": self.last.sequence_id if self.last is not None else 0,
            "dwellLeft_s": self.dwell_left_s,
            "waiting": self.waiting,
        }
