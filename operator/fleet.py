"""The console's picture of the fleet, fed by decoded messages. Pure: no I/O, time passed in.

``FleetModel.apply(msg, link, now)`` folds one message in (a copy that arrived on the other link
too is recognised by (sender, topic, headerId) and skipped) and queues what the operator should be
told; ``tick(now)`` notices robots that went quiet; ``drain()`` hands the queued notices over.
Not thread-safe: the adapter that feeds it from network threads holds a lock.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from fleetlink.operator.alarms import AlarmDesk
from fleetlink.operator.marks import marks_of_set, supersedes
from fleetlink.shared.messages import (
    UNKNOWN_SD_M,
    Ack,
    AckResult,
    AlarmAck,
    BoardStatus,
    Connection,
    ConnectionState,
    Diagnostics,
    Event,
    Goal,
    Lease,
    Mark,
    MarkSet,
    OrderEdge,
    OrderNode,
    OrderProgress,
    Pose,
    Scan,
    Severity,
    State,
    UwbFix,
    same_map,
)
from fleetlink.shared.scan_codec import scan_points
from fleetlink.shared.se2 import apart, compose, inverse
from fleetlink.shared.wire import Message, WireError

__all__ = [
    "CONTACT_RENEW_S",
    "FleetModel",
    "Grid",
    "LeaseRenewal",
    "Notice",
    "RobotView",
    "RoundFloor",
    "Route",
    "extend_trail",
    "grid_through",
]

TRAIL_POINTS = 200
SCAN_STALE_S = 3.0
"""A robot's scan is no longer drawn this long after it arrived (the robot has moved on, or its
lidar stopped)."""

Grid = tuple[float, float, float, int, int, bytes]
"""(origin_x, origin_y, resolution, width, height, cells row by row from origin_y up: 0 free,
100 occupied, 255 unknown)."""
TRAIL_MIN_STEP_M = 0.05


def grid_through(grid: Grid, frame: tuple[float, float, float]) -> Grid:
    """``grid`` (in a robot's own map frame) as it lies on the fleet map, ``frame`` being where its
    frame lies there: resampled on the lattice it was on (every onboard map shares one), so it merges
    with the others' cells. Each cell takes the source cell under its centre; each wall cell is also
    carried forward onto the cell its centre lands in, so a wall one cell thick stays unbroken
    (8-connected) at any heading."""
    ox, oy, res, w, h, data = grid
    cells = np.frombuffer(data, dtype=np.uint8).reshape(h, w)
    fx, fy, fth = frame
    c, s = math.cos(fth), math.sin(fth)
    corners = np.array([(ox, oy), (ox + w * res, oy), (ox, oy + h * res), (ox + w * res, oy + h * res)])
    px = fx + c * corners[:, 0] - s * corners[:, 1]
    py = fy + s * corners[:, 0] + c * corners[:, 1]
    offx, offy = ox - math.floor(ox / res) * res, oy - math.floor(oy / res) * res
    x0 = offx + math.floor((float(px.min()) - offx) / res) * res
    y0 = offy + math.floor((float(py.min()) - offy) / res) * res
    nw = math.ceil((float(px.max()) - x0) / res)
    nh = math.ceil((float(py.max()) - y0) / res)
    gx, gy = np.meshgrid(x0 + (np.arange(nw) + 0.5) * res - fx, y0 + (np.arange(nh) + 0.5) * res - fy)
    cols = np.floor((c * gx + s * gy - ox) / res).astype(np.int64)
    rows = np.floor((-s * gx + c * gy - oy) / res).astype(np.int64)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    out = np.full((nh, nw), 255, dtype=np.uint8)
    out[inside] = cells[rows[inside], cols[inside]]
    wr, wc = np.nonzero(cells == 100)
    wx, wy = ox + (wc + 0.5) * res, oy + (wr + 0.5) * res
    tc = np.clip(np.floor((fx + c * wx - s * wy - x0) / res).astype(np.int64), 0, nw - 1)
    tr = np.clip(np.floor((fy + s * wx + c * wy - y0) / res).astype(np.int64), 0, nh - 1)
    out[tr, tc] = 100
    return (x0, y0, res, nw, nh, out.tobytes())


def extend_trail(trail: deque[tuple[float, float]], x: float, y: float) -> bool:
    """(x, y) onto a robot's trail if it is ``TRAIL_MIN_STEP_M`` from the last point (True then)."""
    if trail and math.hypot(x - trail[-1][0], y - trail[-1][1]) < TRAIL_MIN_STEP_M:
        return False
    trail.append((x, y))
    return True


Route = tuple[str, tuple[tuple[float, float, float], ...]]
"""A round this console sent a robot: its order id and its nodes' (x, y, dwell_s), in order."""


@dataclass(frozen=True, slots=True)
class Notice:
    at: float
    severity: str
    """info, warning or error."""
    text: str


Frame = tuple[float, float, float]
"""Where a robot's own map frame lies on the fleet map: (x, y, theta)."""


def into_frame(
    frame: Frame | None, x: float, y: float, theta: float | None = None
) -> tuple[float, float, float | None]:
    """A point (and heading, None: any) on the fleet map in the frame that lies at ``frame`` on it
    (None: as it is)."""
    if frame is None:
        return x, y, theta
    rx, ry, rth = compose(inverse(frame), (x, y, theta or 0.0))
    return rx, ry, (math.remainder(rth, math.tau) if theta is not None else None)


FRAME_MOVED_M = 0.1
FRAME_MOVED_RAD = math.radians(2.0)
"""A round planned through a robot's frame is not sent if the frame moved more than this meanwhile."""
BEGAN_AGAIN_SHORT = "its map began again"
BEGAN_AGAIN = f"{BEGAN_AGAIN_SHORT}: not found on the fleet map yet"
"""Why a robot the fleet map had found is off it: its poses are in a new map (its agent restarted)."""


@dataclass(frozen=True, slots=True)
class RoundFloor:
    """What a round is planned from (``FleetModel.round_floor``), taken under the console's lock."""

    starts: dict[str, tuple[float, float]]
    """Where each robot stands on the map drawn."""
    maps: tuple[tuple[Grid, Frame | None], ...]
    """Each robot's map and where its frame lies on the fleet map (None: taken as it is)."""
    trails: tuple[tuple[tuple[float, float], ...], ...]
    """Each map's robot's trail on the map drawn."""
    frames: dict[str, Frame]
    """The robots that map and report in their own frames: each one's frame, as planned through;
    its order goes out through it (``FleetModel.order_through``)."""

    def grids(self) -> list[Grid]:
        """The maps on the map drawn (``grid_through``: the planner's worker thread calls this, not
        the UI)."""
        return [grid if frame is None else grid_through(grid, frame) for grid, frame in self.maps]


@dataclass(slots=True)
class RobotView:
    robot: str
    mode: str = "?"
    drive_mode: str = ""
    battery: float | None = None
    charging: bool = False
    pose: tuple[float, float, float] | None = None
    """Where it is on the map drawn: as it reports it, or through its frame on the fleet map
    (``FleetModel.frames``) for a robot mapping in its own frame."""
    reported: tuple[float, float, float] | None = None
    """Its pose as it reported it, in its own map's frame."""
    off_fleet_map: bool = False
    """Its map is in its own frame and the fleet map has not found that frame yet."""
    off_fleet_map_why: str = ""
    """Why not, as the fleet map's search last said ("" if it has not said)."""
    map_began: float = 0.0
    """Which of its maps its poses are in (``Pose.map_began``): a frame found for another (its agent
    restarted and began a new map) does not place it (``same_map``)."""
    map_named: bool = False
    """Its poses have named a map (a ``map_began`` other than 0) before: an agent of 1.2.0 or later."""
    began_again: bool = False
    """Its map began again while the fleet map placed it (its agent restarted), and the fleet map has not
    found the new map yet: said before the fleet map's own reason, which speaks only of the new map."""

    @property
    def in_own_frame(self) -> bool:
        """Its poses are in its own map's frame, not the site's: it has no UWB position (its ``Pose``
        says so with ``UNKNOWN_SD_M``). Only then does the fleet map's frame for it apply (a robot
        with UWB whose map has not yet restarted in the site frame reports site poses)."""
        return self.pose_sd_m is not None and self.pose_sd_m >= UNKNOWN_SD_M

    pose_sd_m: float | None = None
    """The fused pose's position uncertainty: the larger of its x and y standard deviations,
    metres (None until a ``Pose`` said; a ``State`` carries none)."""
    trail: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=TRAIL_POINTS))
    trail_added: int = 0
    """Points ever appended to ``trail`` (the map draws only the new ones, the dropped ones by count)."""
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
    present: bool | None = None
    """Presence (its Zenoh liveliness token, its retained MQTT ``Connection``): True while some
    link says the robot is there, False once one says it is gone and none that it is there, None
    until one says (``AlarmDesk.present``)."""
    refused: int = 0
    """Inputs the robot's agent refused (its ``Diagnostics``: malformed, oversized, over a rate, a
    claimed sender, a command whose handling failed), with the last reason."""
    refused_reason: str = ""
    estop_source: str = ""
    """REMOTE (an operator) or MANUAL (the button on the robot) while latched."""
    home: tuple[float, float] | None = None
    home_source: str = ""
    comms_policy: str = ""
    contact_lost: bool = False
    contact_action: str = ""
    board: BoardStatus | None = None
    """The robot's latest board status (power, environment, payload, tank, faults)."""
    order_id: str = ""
    """The robot's current (or last) order, "" if none."""
    progress: OrderProgress | None = None
    """Along its current order with nodes (a round): nodes done, skipped, dwell left, why it waits;
    None without one."""
    paused: bool = False
    order_end: tuple[str, str] | None = None
    """(order id, outcome) of the last order with nodes it ended: ``finished`` (every node done
    or skipped), ``ended`` (cancelled, stopped, replaced), as its ``order`` event says."""
    scan: npt.NDArray[np.float64] | None = None
    """Its latest lidar scan's returns in the site frame, ``(N, 2)`` metres (a ``Scan``, or
    ``set_scan``); the map draws the selected robot's. None until one arrives, and again once it is
    ``SCAN_STALE_S`` old."""
    scan_at: float | None = None

    def age(self, now: float) -> float | None:
        return None if self.last_heard is None else max(0.0, now - self.last_heard)


class FleetModel:
    def __init__(self, operator: str, *, lost_after_s: float = 3.0, uwb_timeout_s: float = 1.5) -> None:
        self.operator = operator
        self.lost_after_s = lost_after_s
        self.uwb_timeout_s = uwb_timeout_s
        self.robots: dict[str, RobotView] = {}
        self.marks: dict[str, Mark] = {}
        """markId -> its newest version (removed ones kept: a tombstone must win over an older
        version heard later)."""
        self.marks_version = 0
        """Bumped whenever ``marks`` or ``mark_sets`` changes (the marks file and this console's
        retained sets follow it)."""
        self.mark_sets: dict[tuple[str, str], tuple[Mark, ...]] = {}
        """(robot, sender) -> the last ``MarkSet`` heard from that console for that robot: what the
        broker holds (operator/marksync.py compares this console's own with what it should be)."""
        self.anchors: dict[str, tuple[float, float]] = {}
        self.grids: dict[str, Grid] = {}
        """robot -> its onboard map, drawn merged under the poses."""
        self.frames: dict[str, tuple[float, float, float]] = {}
        """robot -> where its map's frame lies on the fleet map, for a robot mapping in its own frame
        (no UWB), as the fleet map service found it (site/fleetmap.py): its poses, goals and scans are
        drawn through it, and goals typed on the fleet map sent back through it (``to_robot``)."""
        self.frames_began: dict[str, float] = {}
        """robot -> which of its maps its frame in ``frames`` was found for (``RobotFrame.began``)."""
        self.routes: dict[str, Route] = {}
        """robot -> the round this console last sent it (drawn while the robot runs that order)."""
        self.zones: dict[str, tuple[tuple[float, float], ...]] = {}
        """People-present zones this console declared, by name (drawn on the map)."""
        self.version = 0
        """Bumped on every change: views redraw only when it moved."""
        self._last: dict[tuple[str, str, str], tuple[int, float]] = {}
        self._notices: deque[Notice] = deque(maxlen=500)
        self.alarms = AlarmDesk(operator)
        """This console's alarms (operator/alarms.py), fed with the messages and presence the
        feed folds in."""

    def forget(self) -> None:
        """Back to a model that has heard nothing (a replay seeking back plays again from its
        start: operator/feed.py ``FleetFeed.forget``): a fresh model's state, with this console's
        own zones and routes, the alarm desk forgotten in place, the versions moved on (views key
        their caches on them)."""
        fresh = FleetModel(self.operator, lost_after_s=self.lost_after_s, uwb_timeout_s=self.uwb_timeout_s)
        fresh.version, fresh.marks_version = self.version + 1, self.marks_version + 1
        fresh.zones, fresh.routes = self.zones, self.routes
        self.alarms.forget()
        fresh.alarms = self.alarms
        vars(self).update(vars(fresh))

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
        if isinstance(msg, MarkSet):  # a console's retained set: each entry as its Mark
            marks = tuple(marks_of_set(msg))
            if self.mark_sets.get((h.robot, h.sender)) != marks:
                self.mark_sets[(h.robot, h.sender)] = marks
                self.marks_version += 1
            return sum(self._mark(m) for m in marks) > 0
        if isinstance(msg, AlarmAck):  # another console's acknowledgements: the feed gives them to alarms
            return False
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
            view.pose_sd_m = max(msg.sd_x_m, msg.sd_y_m)
            if msg.map_began != view.map_began:
                self._map_begun(view, msg.map_began)
            self._pose(view, msg.x, msg.y, msg.theta)
            view.uwb_stale = msg.uwbStale
        elif isinstance(msg, State):
            self._state(view, msg, now)
        elif isinstance(msg, Lease):
            self._lease(view, msg, now)
        elif isinstance(msg, BoardStatus):
            view.board = msg
        elif isinstance(msg, Event):
            sev = {Severity.INFO: "info", Severity.WARNING: "warning", Severity.ERROR: "error"}[msg.severity]
            self.notify(now, sev, f"{h.robot}: {msg.kind}: {msg.text}")
            if msg.kind == "order":
                data = {kv.key: kv.value for kv in msg.data}
                if "order" in data and "outcome" in data:
                    view.order_end = (data["order"], data["outcome"])
        elif isinstance(msg, Ack):
            if msg.result is AckResult.REJECTED and msg.commandSender == self.operator:
                self.notify(now, "warning", f"{h.robot} refused {msg.commandTopic}: {msg.reason}")
        elif isinstance(msg, Diagnostics):
            # Totals since the agent started (a restarted agent starts again from 0).
            view.refused = sum(c.count for c in (*msg.rejected, *msg.oversized)) + msg.handler_failures
            view.refused_reason = msg.last_reason
        elif isinstance(msg, Scan):
            try:
                self.set_scan(h.robot, scan_points(msg), now)
            except WireError:  # ranges that are not count uint16s: nothing to draw
                return False
        elif isinstance(msg, Connection):
            view.connection = msg.connectionState.value
            if msg.connectionState is not ConnectionState.ONLINE:
                self.notify(now, "error", f"{h.robot}: connection {msg.connectionState.value} (via {link})")
        return True

    def _pose(self, view: RobotView, x: float, y: float, theta: float) -> None:
        view.reported = (x, y, theta)
        view.pose = self._placed(view.robot, view.reported)
        self._trail(view, view.pose[0], view.pose[1])

    def _frame(self, robot: str) -> tuple[float, float, float] | None:
        """Where ``robot``'s reports lie on the fleet map: its frame there while it reports poses
        in its own frame, if found for the map they are in; None (as reported) otherwise."""
        view = self.robots.get(robot)
        if view is None or not view.in_own_frame or self._other_map(view):
            return None
        return self.frames.get(robot)

    def _other_map(self, view: RobotView) -> bool:
        """The fleet map's frame for ``view``'s robot was found for another of its maps."""
        return not same_map(self.frames_began.get(view.robot, 0.0), view.map_began, view.map_named)

    def _map_begun(self, view: RobotView, began: float) -> None:
        """``view``'s robot reports poses in another map (its agent restarted, or its first map began):
        a frame of its old map no longer places it, and its trail, drawn through that, starts again."""
        view.map_began = began
        view.map_named = view.map_named or began != 0.0
        if view.in_own_frame and view.robot in self.frames:
            stale = self._other_map(view)
            view.began_again = view.began_again or stale
            view.off_fleet_map, view.off_fleet_map_why = stale, BEGAN_AGAIN if stale else ""
            self.alarms.own_frame(view.robot, BEGAN_AGAIN if stale else None, mapping=True)
            view.trail.clear()
            view.trail_added += TRAIL_POINTS + 1  # more than the trail holds: drawn again whole

    def _placed(self, robot: str, pose: tuple[float, float, float]) -> tuple[float, float, float]:
        frame = self._frame(robot)
        return pose if frame is None else compose(frame, pose)

    def set_frames(
        self,
        frames: dict[str, tuple[float, float, float]],
        unframed: Iterable[str] = (),
        why: Mapping[str, str] | None = None,
        began: Mapping[str, float] | None = None,
    ) -> None:
        """Where each robot mapping in its own frame lies on the fleet map, and which such robots it
        has not found yet, with why not (the fleet map service, after each build); ``began``: which of
        each robot's maps its frame was found for (none: the map its poses are in). A robot whose frame
        moves is drawn there at once; its trail, drawn where it was, starts again."""
        began = {r: b for r, b in (began or {}).items() if r in frames}
        rebegun = {r for r in set(began) | set(self.frames_began) if began.get(r) != self.frames_began.get(r)}
        self.frames_began = began
        off = set(unframed) | {r for r, v in self.robots.items() if v.in_own_frame and self._other_map(v)}
        for robot in off - set(self.robots):
            self.robot(robot)
        for robot, view in self.robots.items():
            reason = (why or {}).get(robot, "") if robot in off else ""
            if robot in off and robot in frames:  # found, but for the map it reported in before
                reason = BEGAN_AGAIN
            elif robot in off and view.began_again:  # the old map forgotten, the new one not found yet
                reason = f"{BEGAN_AGAIN_SHORT}; {reason}" if reason else BEGAN_AGAIN
            view.began_again = view.began_again and robot in off
            if (view.off_fleet_map, view.off_fleet_map_why) != (robot in off, reason):
                view.off_fleet_map, view.off_fleet_map_why = robot in off, reason
                self.version += 1
            # Its localisation alarm speaks of the fleet map, not of a site position it never has.
            self.alarms.own_frame(robot, reason if robot in off else None, mapping=robot in off or robot in frames)
        if frames == self.frames and not rebegun:
            return
        moved = {r for r in set(frames) | set(self.frames) if frames.get(r) != self.frames.get(r)} | rebegun
        self.frames = dict(frames)
        for robot in moved:
            placed = self.robots.get(robot)
            if placed is None or placed.reported is None:
                continue
            placed.pose = self._placed(robot, placed.reported)
            placed.trail.clear()
            placed.trail_added += TRAIL_POINTS + 1  # more than the trail holds: drawn again whole
            self._trail(placed, placed.pose[0], placed.pose[1])
        self.version += 1

    def to_robot(self, robot: str, x: float, y: float, theta: float | None = None) -> tuple[float, float, float | None]:
        """A point (and heading) on the map drawn, in ``robot``'s own map frame: what it is sent."""
        return into_frame(self._frame(robot), x, y, theta)

    def round_floor(self, robots: Iterable[str], kind: str) -> RoundFloor | str:
        """What a round (``kind`` "uv" or "sweep") of ``robots`` is planned from, on the map drawn
        (``RoundFloor``), or why the round cannot be planned for them. A robot that maps and reports
        in its own frame is planned for through its frame on the fleet map, and refused until the
        fleet map has found it (its map and the area drawn would not be in one frame)."""
        starts: dict[str, tuple[float, float]] = {}
        maps: list[tuple[Grid, Frame | None]] = []
        trails: list[tuple[tuple[float, float], ...]] = []
        frames: dict[str, Frame] = {}
        for robot in robots:
            view = self.robots.get(robot)
            if view is None:
                return f"unknown robot {robot!r} (known: {', '.join(sorted(self.robots)) or 'none yet'})"
            ok, reason = self.may_drive(robot)
            if not ok:
                return reason
            if view.lost or view.pose is None:
                return f"{robot}: {'lost, its last pose is stale' if view.lost else 'no fused pose yet'}"
            if view.in_own_frame and view.off_fleet_map:
                return f"{robot} maps in its own frame and is not on the fleet map yet (its detail says why)"
            if view.in_own_frame and kind == "uv":
                return f"{robot} has no site position (no UWB): its lamp's dose could not be placed on the floor"
            starts[robot] = (view.pose[0], view.pose[1])
            frame = self._frame(robot)
            if frame is not None:
                frames[robot] = frame
            grid = self.grids.get(robot)
            if grid is not None:
                # Through its frame only while it reports in its own frame: a robot with UWB reports
                # site poses and plans on its map as it is.
                maps.append((grid, frame))
                trails.append(tuple(view.trail))  # its body, where another's map saw it, is no wall
        return RoundFloor(starts, tuple(maps), tuple(trails), frames)

    def frame_moved(self, robot: str, planned: Frame | None) -> str:
        """Why an order planned through ``planned`` (``RoundFloor.frames``) may not be sent to
        ``robot`` now, or "": its frame on the fleet map moved (more than ``FRAME_MOVED_M`` or
        ``FRAME_MOVED_RAD``), came or went while it was planned."""
        now = self._frame(robot)
        if now is None and planned is None:
            return ""
        if now is None or planned is None:
            return f"{robot}'s frame on the fleet map {'came' if planned is None else 'went'} while it was planned"
        if apart(planned, now, FRAME_MOVED_M, FRAME_MOVED_RAD):
            moved = math.hypot(now[0] - planned[0], now[1] - planned[1])
            return f"{robot}'s frame on the fleet map moved {moved:.2f} m while it was planned"
        return ""

    @staticmethod
    def order_through(frame: Frame | None, fields: Mapping[str, Any]) -> Mapping[str, Any]:
        """An order's fields (``Order``'s: a round as the planner gives it) planned on the map drawn,
        in the frame of a robot whose own frame lies at ``frame`` on it (None: as they are): its
        goal, its nodes (headings too) and its edges' trajectories."""
        if frame is None:
            return fields

        def moved(x: float, y: float, theta: float | None) -> tuple[float, float, float | None]:
            return into_frame(frame, x, y, theta)

        def node(n: OrderNode) -> OrderNode:
            x, y, theta = moved(n.x, n.y, n.theta)
            return replace(n, x=x, y=y, theta=theta)

        def edge(e: OrderEdge) -> OrderEdge:
            if e.trajectory is None:
                return e
            points = tuple(replace(p, x=x, y=y) for p in e.trajectory.controlPoints
                           for x, y, _ in (moved(p.x, p.y, None),))  # fmt: skip
            return replace(e, trajectory=replace(e.trajectory, controlPoints=points))

        out = dict(fields)
        goal: Goal | None = out.get("goal")
        if goal is not None:
            x, y, theta = moved(goal.x, goal.y, goal.theta)
            out["goal"] = replace(goal, x=x, y=y, theta=theta)
        out["nodes"] = tuple(node(n) for n in out.get("nodes", ()))
        out["edges"] = tuple(edge(e) for e in out.get("edges", ()))
        return out

    @staticmethod
    def _trail(view: RobotView, x: float, y: float) -> None:
        if extend_trail(view.trail, x, y):
            view.trail_added += 1

    def trail_through(self, robot: str, points: Iterable[tuple[float, float]]) -> None:
        """Where ``robot`` was at poses a busy console folded into a later one (operator/feed.py,
        before that pose is applied): on its trail, as if each had been applied."""
        view = self.robot(robot)
        for x, y in points:
            self._trail(view, x, y)

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
        view.order_id = msg.orderId
        view.progress = msg.progress
        view.paused = msg.paused
        estop = msg.safetyState.eStop.value != "NONE"
        if estop and not view.estop:
            self.notify(now, "error", f"{view.robot}: e-stop ({msg.safetyState.eStop.value})")
        view.estop = estop
        view.estop_source = msg.safetyState.eStop.value if estop else ""
        view.home = None if msg.home is None else self._placed(view.robot, (msg.home.x, msg.home.y, 0.0))[:2]
        view.home_source = "" if msg.home is None else msg.home.source.value
        view.comms_policy = msg.contact.policy.value
        view.contact_lost = msg.contact.lost
        view.contact_action = msg.contact.action
        had_goal = view.goal is not None
        view.goal = self._placed(view.robot, (msg.goal.x, msg.goal.y, 0.0))[:2] if msg.goal is not None else None
        # (A round's goal is each node in turn, none between two: its end is the agent's ``order`` event.)
        if had_goal and view.goal is None and msg.orderId and msg.progress is None:
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
        if not supersedes(msg, self.marks.get(msg.markId)):
            return False  # the same version again (both links, a set, a query), or an older one
        self.marks[msg.markId] = msg
        self.version += 1
        self.marks_version += 1
        return True

    def presence(self, robot: str, present: bool | None) -> None:
        """The robot's presence as its links tell it (``RobotView.present``)."""
        view = self.robot(robot)
        if view.present != present:
            view.present = present
            self.version += 1

    def add_anchor(self, name: str, x: float, y: float) -> None:
        if self.anchors.get(name) != (x, y):
            self.anchors[name] = (x, y)
            self.version += 1

    def set_route(self, robot: str, route: Route) -> None:
        """The round this console sent ``robot`` (the map draws it while the robot runs it)."""
        self.routes[robot] = route
        self.version += 1

    def set_zones(self, zones: dict[str, tuple[tuple[float, float], ...]]) -> None:
        """This console's people-present zones (the map draws them)."""
        if zones != self.zones:
            self.zones = dict(zones)
            self.version += 1

    def running_route(self, robot: str) -> Route | None:
        """``robot``'s round while it runs it: the order it reports is the one sent, with progress."""
        view = self.robots.get(robot)
        route = self.routes.get(robot)
        if view is None or route is None or view.progress is None or view.order_id != route[0]:
            return None
        return route

    def set_scan(self, robot: str, points: npt.NDArray[np.float64], now: float) -> None:
        """A robot's latest lidar scan, its points in the site frame (``(N, 2)`` metres)."""
        view = self.robot(robot)
        frame = self._frame(robot)
        if frame is not None and len(points):
            c, sn = math.cos(frame[2]), math.sin(frame[2])
            points = np.column_stack(
                (frame[0] + c * points[:, 0] - sn * points[:, 1], frame[1] + sn * points[:, 0] + c * points[:, 1])
            )
        view.scan = points
        view.scan_at = now
        self.version += 1

    def set_grid(self, robot: str, grid: Grid) -> None:
        """A robot's occupancy grid for the map (``operator/maps.py`` keeps them current)."""
        self.grids[robot] = grid
        self.version += 1

    def tick(self, now: float) -> None:
        """Robots silent for ``lost_after_s`` are reported lost (once); scans ``SCAN_STALE_S`` old
        are let go."""
        for view in self.robots.values():
            if view.scan_at is not None and now - view.scan_at > SCAN_STALE_S:
                view.scan = view.scan_at = None
                self.version += 1
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


CONTACT_RENEW_S = 2.0
"""A held lease is renewed at least this often: the robot counts it as hearing its operator."""


class LeaseRenewal:
    """When to renew the leases this console holds: every ``lease_s / 3`` (a lease survives two
    lost renewals). Pure: ``due(fleet, now)`` is called as often as the caller likes."""

    def __init__(self, lease_s: float) -> None:
        self.lease_s = lease_s
        # Often enough to be the robot's sign of contact too (agent/contact.py: three missed = lost).
        self.every_s = min(lease_s / 3, CONTACT_RENEW_S)
        self._last = -math.inf

    def due(self, fleet: FleetModel, now: float) -> list[str]:
        """The robots whose lease to renew now ([] between renewals)."""
        if now - self._last < self.every_s:
            return []
        self._last = now
        return fleet.leases_held()
