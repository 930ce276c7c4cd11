"""The console's picture of the fleet, fed by decoded messages. Pure: no I/O, time passed in.

``FleetModel.apply(msg, link, now)`` folds one message in (a copy that arrived on the other link
too is recognised by (sender, topic, headerId) and skipped) and queues what the operator should be
told; ``tick(now)`` notices robots that went quiet; ``drain()`` hands the queued notices over.
Not thread-safe: the adapter that feeds it from network threads holds a lock.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from fleetlink.shared.messages import (
    Ack,
    AckResult,
    Connection,
    ConnectionState,
    Diagnostics,
    Event,
    Lease,
    Mark,
    Pose,
    Severity,
    State,
    UwbFix,
)
from fleetlink.shared.wire import Message

__all__ = ["FleetModel", "Grid", "LeaseRenewal", "Notice", "RobotView"]

TRAIL_POINTS = 200

Grid = tuple[float, float, float, int, int, bytes]
"""(origin_x, origin_y, resolution, width, height, cells row by row from origin_y up: 0 free,
100 occupied, 255 unknown)."""
TRAIL_MIN_STEP_M = 0.05


@dataclass(frozen=True, slots=True)
class Notice:
    at: float
    severity: str
    """info, warning or error."""
    text: str


@dataclass(slots=True)
class RobotView:
    robot: str
    mode: str = "?"
    drive_mode: str = ""
    battery: float | None = None
    charging: bool = False
    pose: tuple[float, float, float] | None = None
    trail: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=TRAIL_POINTS))
    last_heard: float | None = None
    uwb_stale: bool | None = None
    uwb_fix_at: float | None = None
    goal: tuple[float, float] | None = None
    payload_on: bool = False
    estop: bool = False
    errors: tuple[str, ...] = ()
    connection: str = ""
    lease_holder: str | None = None
    """None: the robot never announced a lease (an agent without leases); '' free."""
    lease_until: float = 0.0
    lost: bool = False
    refused: int = 0
    """Inputs the robot's agent refused (its ``Diagnostics``: malformed, oversized, over a rate, a
    claimed sender, a command whose handling failed), with the last reason."""
    refused_reason: str = ""

    def age(self, now: float) -> float | None:
        return None if self.last_heard is None else max(0.0, now - self.last_heard)


class FleetModel:
    def __init__(self, operator: str, *, lost_after_s: float = 3.0, uwb_timeout_s: float = 1.5) -> None:
        self.operator = operator
        self.lost_after_s = lost_after_s
        self.uwb_timeout_s = uwb_timeout_s
        self.robots: dict[str, RobotView] = {}
        self.marks: dict[str, Mark] = {}
        self.anchors: dict[str, tuple[float, float]] = {}
        self.grids: dict[str, Grid] = {}
        """robot -> its onboard map, drawn merged under the poses."""
        self.version = 0
        """Bumped on every change: views redraw only when it moved."""
        self._last: dict[tuple[str, str, str], tuple[int, float]] = {}
        self._notices: deque[Notice] = deque(maxlen=500)

    # -- inputs ---------------------------------------------------------------------------------

    def robot(self, robot: str) -> RobotView:
        view = self.robots.get(robot)
        if view is None:
            view = self.robots[robot] = RobotView(robot)
        return view

    def notify(self, now: float, severity: str, text: str) -> None:
        self._notices.append(Notice(now, severity, text))

    def apply(self, msg: Message, link: str, now: float) -> bool:
        """Fold one message in. False if it was a copy already seen on the other link (or stale)."""
        h = msg.header
        topic = type(msg).TOPIC
        if isinstance(msg, Mark):  # by markId: late joiners get old marks in any order
            return self._mark(msg)
        slot = (h.robot, h.sender, topic)
        last = self._last.get(slot)
        if last is not None and h.headerId <= last[0] and h.timestamp <= last[1]:
            return False  # same message over the other link, or older than what we have
        self._last[slot] = (h.headerId, h.timestamp)
        self.version += 1
        view = self.robot(h.robot)
        if isinstance(msg, UwbFix):
            if msg.status.value == "ok":
                view.uwb_fix_at = now
            return True
        if h.sender == self.operator:
            return True
        view.last_heard = now
        if view.lost:
            view.lost = False
            self.notify(now, "info", f"{h.robot}: back (heard on {link})")
        if isinstance(msg, Pose):
            self._pose(view, msg.x, msg.y, msg.theta)
            view.uwb_stale = msg.uwbStale
        elif isinstance(msg, State):
            self._state(view, msg, now)
        elif isinstance(msg, Lease):
            self._lease(view, msg, now)
        elif isinstance(msg, Event):
            sev = {Severity.INFO: "info", Severity.WARNING: "warning", Severity.ERROR: "error"}[msg.severity]
            self.notify(now, sev, f"{h.robot}: {msg.kind}: {msg.text}")
        elif isinstance(msg, Ack):
            if msg.result is AckResult.REJECTED and msg.commandSender == self.operator:
                self.notify(now, "warning", f"{h.robot} refused {msg.commandTopic}: {msg.reason}")
        elif isinstance(msg, Diagnostics):
            # Totals since the agent started (a restarted agent starts again from 0).
            view.refused = sum(c.count for c in (*msg.rejected, *msg.oversized)) + msg.handler_failures
            view.refused_reason = msg.last_reason
        elif isinstance(msg, Connection):
            view.connection = msg.connectionState.value
            if msg.connectionState is not ConnectionState.ONLINE:
                self.notify(now, "error", f"{h.robot}: connection {msg.connectionState.value} (via {link})")
        return True

    def _pose(self, view: RobotView, x: float, y: float, theta: float) -> None:
        view.pose = (x, y, theta)
        if not view.trail or math.hypot(x - view.trail[-1][0], y - view.trail[-1][1]) >= TRAIL_MIN_STEP_M:
            view.trail.append((x, y))

    def _state(self, view: RobotView, msg: State, now: float) -> None:
        p = msg.agvPosition
        if view.pose is None:
            self._pose(view, p.x, p.y, p.theta)
        view.mode = msg.operatingMode.value
        view.drive_mode = msg.driveMode
        view.battery = msg.batteryState.batteryCharge
        view.charging = msg.batteryState.charging
        view.uwb_stale = msg.uwbStale
        view.payload_on = msg.payloadOn
        estop = msg.safetyState.eStop.value != "NONE"
        if estop and not view.estop:
            self.notify(now, "error", f"{view.robot}: e-stop ({msg.safetyState.eStop.value})")
        view.estop = estop
        had_goal = view.goal is not None
        view.goal = (msg.goal.x, msg.goal.y) if msg.goal is not None else None
        if had_goal and view.goal is None and msg.orderId:
            self.notify(now, "info", f"{view.robot}: order {msg.orderId} finished")
        errors = tuple(f"{e.errorType}: {e.errorDescription}" for e in msg.errors)
        for e in errors:
            if e not in view.errors:
                self.notify(now, "error", f"{view.robot}: fault {e}")
        view.errors = errors

    def _lease(self, view: RobotView, msg: Lease, now: float) -> None:
        if view.lease_holder is not None and msg.holder != view.lease_holder:
            who = msg.holder or "nobody"
            self.notify(now, "info", f"{view.robot}: control lease now held by {who}")
        view.lease_holder = msg.holder
        view.lease_until = msg.until

    def _mark(self, msg: Mark) -> bool:
        old = self.marks.get(msg.markId)
        if old is not None and (old.header.timestamp, old.header.headerId) >= (
            msg.header.timestamp,
            msg.header.headerId,
        ):
            return False  # the same mark again (both links, or a late joiner's query), or older
        self.marks[msg.markId] = msg
        self.version += 1
        return True

    def add_anchor(self, name: str, x: float, y: float) -> None:
        if self.anchors.get(name) != (x, y):
            self.anchors[name] = (x, y)
            self.version += 1

    def set_grid(self, robot: str, grid: Grid) -> None:
        """A robot's occupancy grid for the map (``operator/maps.py`` keeps them current)."""
        self.grids[robot] = grid
        self.version += 1

    def tick(self, now: float) -> None:
        """Robots silent for ``lost_after_s`` are reported lost (once)."""
        for view in self.robots.values():
            age = view.age(now)
            if age is not None and age > self.lost_after_s and not view.lost:
                view.lost = True
                self.version += 1
                self.notify(now, "error", f"{view.robot}: lost (nothing heard for {age:.1f} s)")

    # -- outputs --------------------------------------------------------------------------------

    def drain(self) -> list[Notice]:
        out = list(self._notices)
        self._notices.clear()
        return out

    def live_marks(self) -> list[Mark]:
        return [m for m in self.marks.values() if not m.removed]

    def uwb_ok(self, robot: str, now: float) -> bool | None:
        """True/False when known: a recent fix, or the agent's own flag; None if never told."""
        view = self.robots.get(robot)
        if view is None:
            return None
        if view.uwb_fix_at is not None and now - view.uwb_fix_at <= self.uwb_timeout_s:
            return True
        if view.uwb_stale is not None:
            return not view.uwb_stale
        return None if view.uwb_fix_at is None else False

    def may_drive(self, robot: str) -> tuple[bool, str]:
        """May this console drive the robot? Yes unless another operator holds its control lease."""
        view = self.robots.get(robot)
        if view is None or view.lease_holder is None:
            return True, ""
        if view.lease_holder == self.operator or not view.lease_holder:
            return True, ""  # free: driving takes it for you (the agent claims it on your first command)
        return False, f"{robot}: control lease held by {view.lease_holder}: driving refused"

    def leases_held(self) -> list[str]:
        """The robots whose control lease this console holds, as the robots last said."""
        return [r for r, v in self.robots.items() if v.lease_holder == self.operator]


class LeaseRenewal:
    """When to renew the leases this console holds: every ``lease_s / 3`` (a lease survives two
    lost renewals). Pure: ``due(fleet, now)`` is called as often as the caller likes."""

    def __init__(self, lease_s: float) -> None:
        self.lease_s = lease_s
        self.every_s = lease_s / 3
        self._last = -math.inf

    def due(self, fleet: FleetModel, now: float) -> list[str]:
        """The robots whose lease to renew now ([] between renewals)."""
        if now - self._last < self.every_s:
            return []
        self._last = now
        return fleet.leases_held()
