"""One go-to's route: plan, follow, re-plan around what bars the way, back off and fail (pure).

A ``Route`` is made for each go-to (an order or a return home) and steers the pilot's
``GoToController`` (lent to it: the pilot keeps one controller for every go-to). The pilot calls
``step`` every control tick while the go-to runs, ``cut_short`` on a drive start, ``refused`` when
the guard refuses what the route asked for, and ``resume`` after a pause. Time, the pose and the
path provider are passed in (the provider can change between calls: the agent renews its planner
as the map grows). The route never emits events itself: it leaves ``notes`` (a path was planned or
re-planned) and, once, an ``end`` (reached or failed) for the pilot to report.

Phases (``RoutePhase``)::

    UNPLANNED --first step--> STRAIGHT (no provider, or it has no map)
              \\-------------> FOLLOWING (a provider's path)
                               --barred by something ahead--> BACKING_OFF (as far as the map
                                 behind allows; no room: straight on) --> re-plan: FOLLOWING
                               --drive start refused / no progress--> re-plan: FOLLOWING
                               --a newer map shows the leg ahead barred--> re-plan: FOLLOWING
                                 (not counted in ``max_replans``; at most ``max_map_replans``);
                                 no path on it: WAITING
                               --barred, no way around, the map alone has one--> WAITING
                                 (what barred it may move; then the marks are forgotten)
                               --re-plans used up / no way around--> [FAILING_BACKOFF -->] RETREATING
    UNPLANNED --no path--> WAITING (standing) --a newer map--> UNPLANNED (asks again)
              --``no_path_wait_s`` with none--> end (failed: no_path)
    UNPLANNED --no path, the goal farther than ``approach_m`` and barred only by something the size
              of a robot--> APPROACHING (once a go-to: to within ``approach_m`` of the goal)
              --a newer map with a path--> FOLLOWING
              --arrived, barred or no progress--> WAITING (the wait counts from there)
    RETREATING --back where it came from, or refused--> end (failed)
    STRAIGHT / FOLLOWING --arrived--> end (reached)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum
from itertools import pairwise
from typing import Protocol, runtime_checkable

from fleetlink.agent.guard import Refusal, RefusalReason
from fleetlink.agent.motion import GoToController, GoToPhase
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.shared.geometry import point_segment_distance

__all__ = [
    "BodyAwareProvider",
    "Destination",
    "Drive",
    "MovableCheck",
    "PathProvider",
    "RoomBehind",
    "Route",
    "RouteConfig",
    "RouteEnd",
    "RouteNote",
    "RoutePhase",
]

Pose = tuple[float, float, float]
Point = tuple[float, float]


class PathProvider(Protocol):
    """(start, goal, blocked) -> waypoints ending at the goal; ``[]``: no path (the goal fails);
    ``None``: no map (the pilot drives straight, as without a provider). ``blocked`` are points where
    the robot found its way barred during this go-to (to be planned around)."""

    def __call__(self, start: Point, goal: Point, /, blocked: Sequence[Point] = ()) -> Sequence[Point] | None: ...


class BodyAwareProvider(Protocol):
    """A ``PathProvider`` that also plans around ``bodies``: the centres of other robots standing
    where they report themselves (agent/peers.py), taken as they are (a ``blocked`` point near a
    wall on the map is that wall; a robot standing by its own face on the map is not)."""

    def __call__(
        self, start: Point, goal: Point, /, blocked: Sequence[Point] = (), bodies: Sequence[Point] = ()
    ) -> Sequence[Point] | None: ...


@dataclass(frozen=True, slots=True)
class RouteConfig:
    """What a route needs of ``PilotConfig`` (see there for the meaning of each)."""

    blocked_timeout_s: float = 10.0
    max_replans: int = 3
    replan_hold_s: float = 2.0
    no_progress_s: float = 8.0
    progress_m: float = 0.05
    sensor_offset_m: float = BODY_RADIUS_M
    backoff_m: float = 0.15
    backoff_speed: float = 0.1
    mark_depth_m: float = 0.1
    retreat_m: float = 0.5
    creep_margin_m: float = 0.1
    creep_min_m: float = 0.2
    stop_distance_m: float = 0.4  # the guard's
    max_map_replans: int = 10
    no_path_wait_s: float = 6.0
    approach_m: float = 2.0


MAX_DEVIATION_M = 1.0
"""The largest allowed deviation a go-to takes (``OrderNode.allowedDeviationXY``'s bound)."""
DEVIATION_STEP_M = 0.05
"""Places within a destination's allowed deviation are tried this far apart, nearest first."""
TRAJECTORY_JOIN_M = 0.3
"""A go-to follows its order's trajectory only from within this of it (about the robot's size; a
robot resumed elsewhere, or that stopped short of the node before, plans its own way)."""
APPROACH_MIN_GAIN_M = 0.5
"""A goal less than this beyond ``approach_m`` is waited for where the robot stands."""


@runtime_checkable
class WallCheck(Protocol):
    """A map sense that can say whether a leg runs into a known wall (the A* planner the agent
    hands the pilot as its map sense: ``PathPlanner.leg_meets_wall``). ``skip_m``: the leg's first
    metres not checked (what the robot already stands beside)."""

    def leg_meets_wall(self, a: Point, b: Point, skip_m: float = 0.1, /) -> bool: ...


@runtime_checkable
class MovableCheck(Protocol):
    """A map sense that can say whether a goal is barred only by something the size of a robot or a
    person, which may have moved since the map drew it (``PathPlanner.barred_by_movable``), and
    where near it the robot can go to look (``PathPlanner.place_near``)."""

    def barred_by_movable(self, p: Point, /) -> bool: ...

    def place_near(self, start: Point, goal: Point, radius: float, /) -> Point | None: ...


@dataclass(frozen=True, slots=True)
class Destination:
    order_id: str | None  # None: return home, or a retrace (``via`` given)
    update_id: int
    x: float
    y: float
    theta: float | None
    sender: str
    via: tuple[Point, ...] = ()
    """A path that comes with the destination (a retrace: the robot's own way back, free since it
    just drove it): followed instead of planning one; the planner is asked only if it is barred."""
    max_v: float | None = None
    """A speed cap for this go-to (m/s): an order edge's maxSpeed."""
    deviation: float = 0.0
    """m: when (x, y) cannot be reached, the nearest place within this that can will do (an order
    node's allowedDeviationXY)."""
    trajectory: tuple[Point, ...] = ()
    """The way the order gives (its edge's trajectory, planned on the fleet's map): followed from
    where the robot joins it, unless the robot's own map has a wall on it; then, and on every re-plan,
    the robot plans its own."""

    @property
    def label(self) -> str:
        if self.order_id is not None:
            return f"order {self.order_id}/{self.update_id}"
        return "retrace" if self.via else "return home"


@dataclass(frozen=True, slots=True)
class Drive:
    """What the route asks for: a velocity and, on a drive start, the distance it means to drive."""

    v: float = 0.0
    omega: float = 0.0
    distance_m: float | None = None


_STILL = Drive()
_MIN_BACKOFF_M = 0.02  # less room than this behind: no back-off


@dataclass(frozen=True, slots=True)
class RouteNote:
    """A path was planned (``replanned`` False, reason "planned") or re-planned (reason: why)."""

    replanned: bool
    text: str
    reason: str
    waypoints: int


@dataclass(frozen=True, slots=True)
class RouteEnd:
    reached: bool
    reason: str  # "reached", "no_path", "blocked", "obstacle_in_path", ...
    text: str  # without the destination's label (the pilot adds it)


class RoutePhase(StrEnum):
    UNPLANNED = "unplanned"  # planned at the first step
    STRAIGHT = "straight"  # straight to the goal (no map); a refused drive start fails the go-to
    FOLLOWING = "following"  # a provider's path; re-plannable
    BACKING_OFF = "backing_off"  # straight back from an obstacle ahead (turning is refused there), then re-plan
    FAILING_BACKOFF = "failing_backoff"  # failed facing an obstacle: straight back first, then retreat
    RETREATING = "retreating"  # failed: back along the way it came, then the end (failed)
    WAITING = "waiting"  # no path yet: standing, until a newer map has one or ``no_path_wait_s`` passes
    APPROACHING = "approaching"  # no path yet to a far goal: going nearer it to look, then WAITING

    @property
    def replannable(self) -> bool:
        return self in (RoutePhase.FOLLOWING, RoutePhase.BACKING_OFF)

    @property
    def failing(self) -> bool:
        return self in (RoutePhase.FAILING_BACKOFF, RoutePhase.RETREATING)


class RoomBehind(Protocol):
    """(pose, limit) -> how far (m, at most ``limit``) the robot may back straight before its body
    meets what its map holds (``PathPlanner.room_behind``): it has no sensor behind it."""

    def __call__(self, pose: Pose, limit: float, /) -> float: ...


@dataclass(slots=True)
class _Backoff:
    x: float
    y: float
    since: float
    length: float


@dataclass(slots=True)
class _Progress:
    index: int = -1  # the waypoint being approached
    best: float = math.inf  # the nearest the robot came to it
    since: float = 0.0  # when it last passed a waypoint or came ``progress_m`` closer


@dataclass(slots=True)
class Route:
    dest: Destination
    goto: GoToController
    config: RouteConfig
    phase: RoutePhase = RoutePhase.UNPLANNED
    replans: int = 0
    blocked: list[Point] = field(default_factory=list)  # where the way was barred (for the provider)
    held_since: float | None = None  # held by a guard refusal since (None: not held)
    notes: list[RouteNote] = field(default_factory=list)  # for the pilot to report and clear
    end: RouteEnd | None = None
    _backoff: _Backoff | None = None
    _progress: _Progress = field(default_factory=_Progress)
    _leg: int | None = None  # the waypoint index whose leg the trail's last point began
    _trail: list[Point] = field(default_factory=list)  # where the robot stood as each leg began (free)
    _failure: tuple[str, str] | None = None  # (reason, text) reported when the retreat ends
    _planned_with: PathProvider | None = None  # the provider (the map) the route last looked at
    _planned_sense: object | None = None  # that map's ``sense`` (``step``)
    _path_sense: object | None = None  # the ``sense`` of the map the path being driven was planned on
    _sense: object | None = None  # this tick's
    map_replans: int = 0  # re-plans because a newer map showed the leg barred (not in ``replans``)
    waiting_since: float | None = None  # no path since (the first plan, or a map re-plan, found none)
    _waiting_on_marks: bool = False  # waiting because only where it was barred (``blocked``) bars the way
    _approached: bool = False  # the one approach a go-to makes has been made (``APPROACHING``)

    # -- what the pilot calls --------------------------------------------------------------------

    def step(self, now: float, pose: Pose, provider: PathProvider | None, sense: object | None = None) -> Drive:
        """One control tick. ``sense``: the map's other answers (the planner itself, ``WallCheck``),
        a new object with each newer map; None: the provider is asked."""
        self._sense = sense if sense is not None else provider
        c = self.config
        if self._backoff is not None:
            b = self._backoff
            if math.hypot(pose[0] - b.x, pose[1] - b.y) < b.length and now - b.since < 3.0 * b.length / c.backoff_speed:
                return Drive(-c.backoff_speed, 0.0)
            self._backoff = None
            if self.phase is RoutePhase.FAILING_BACKOFF:
                self.phase = RoutePhase.RETREATING
                if not self._retreat(pose):
                    return _STILL
            else:
                self.phase = RoutePhase.FOLLOWING
                if not self._replan(now, pose, provider, "blocked"):
                    return _STILL
        if self.phase is RoutePhase.WAITING:
            waited = now - (self.waiting_since if self.waiting_since is not None else now)
            if waited >= c.no_path_wait_s and self.blocked and self._waiting_on_marks:
                # Barred by something the map does not hold, which has had its time to move: the
                # marks are forgotten and the map's own path driven again (the guard stops the
                # robot if it is still there, and that re-plan counts in ``max_replans``).
                self.blocked.clear()
                self._waiting_on_marks = False
                self.phase = RoutePhase.UNPLANNED
            elif provider is self._planned_with:  # the same map: still no path
                if waited >= c.no_path_wait_s:
                    d = self.dest
                    self._finish(False, "no_path", f"no path to ({d.x:.2f}, {d.y:.2f}) (waited {waited:.0f} s)")
                return _STILL
            else:
                self.phase = RoutePhase.UNPLANNED  # a newer map (or none): ask again
        if self.phase is RoutePhase.APPROACHING:
            return self._approach_step(now, pose, provider)
        if self.phase is RoutePhase.UNPLANNED and not self._plan(now, pose, provider):
            return _STILL
        if self.phase is RoutePhase.FOLLOWING and provider is not None and provider is not self._planned_with:
            older, self._planned_with = self._planned_with, provider
            self._planned_sense = self._sense
            # Against the map the path was planned on, not the last one looked at: a wall drawn while
            # the robot drove an earlier leg is news to the later leg it bars when that leg comes
            # within reach (two legs ahead are checked), though the maps since all held it. Compared
            # map to map, the demo's apartment drove a leg laid through the unseen wall of a hallway
            # into that wall and stood refused by it.
            if (
                older is not None
                and self.map_replans < c.max_map_replans
                and self._newly_barred(self._path_sense, self._sense, pose)
            ):
                self.map_replans += 1
                if not self._replan(now, pose, provider, "wall_on_map", counted=False):
                    return _STILL
        cmd = self.goto.step(now, pose)
        if cmd.phase is GoToPhase.DONE:
            if self._failure is not None:
                reason, text = self._failure
                self._finish(False, reason, f"{text}; backed off to ({pose[0]:.2f}, {pose[1]:.2f})")
            else:
                self._finish(True, "reached", f"reached ({cmd.distance_m * 100:.1f} cm off)")
            return _STILL
        if self.phase is RoutePhase.RETREATING:
            return Drive(cmd.v, cmd.omega, cmd.drive_distance_m)
        if self._leg != cmd.waypoint_index:
            self._leg = cmd.waypoint_index
            if not self._trail or math.hypot(self._trail[-1][0] - pose[0], self._trail[-1][1] - pose[1]) > 0.05:
                self._trail.append((pose[0], pose[1]))
                del self._trail[:-8]
        if (
            self.phase is RoutePhase.FOLLOWING
            and cmd.phase is not GoToPhase.FINAL_HEADING
            and self._stalled(now, pose, cmd.waypoint_index)
        ):
            if not self._replan(now, pose, provider, "no_progress"):
                return _STILL
            cmd = self.goto.step(now, pose)
        return Drive(cmd.v, cmd.omega, cmd.drive_distance_m)

    def cut_short(self, pose: Pose, seen_m: float | None, leg: float) -> float:
        """A drive start on a planned path with an echo (``seen_m``) nearer than ``leg`` + the stop
        distance: ask for the part of the leg the echo leaves clear (a waypoint on the way), the
        guard checks that. The rest of the leg gets its own drive-start check from nearer, where a
        door frame at the cone's edge has dropped out of the cone and an obstacle really ahead
        still bars it."""
        c = self.config
        if self.phase not in (RoutePhase.FOLLOWING, RoutePhase.APPROACHING):
            return leg
        if seen_m is None or seen_m >= leg + c.stop_distance_m:
            return leg
        short = seen_m - c.stop_distance_m - c.creep_margin_m
        if short < c.creep_min_m or short > leg - self.goto.config.waypoint_tol_m:
            return leg
        wx, wy = self.goto.waypoints[self.goto.index]
        d = math.hypot(wx - pose[0], wy - pose[1])
        if d <= short:
            return leg
        k = short / d
        self.goto.insert_waypoint((pose[0] + k * (wx - pose[0]), pose[1] + k * (wy - pose[1])))
        return short

    def refused(
        self,
        now: float,
        pose: Pose,
        refusal: Refusal,
        provider: PathProvider | None,
        room: RoomBehind | None = None,
    ) -> None:
        """The guard refused what the route asked for: fail, plan around it, or hold and wait.
        ``room``: how far the map lets the robot back off (None: no map, ``backoff_m``)."""
        c = self.config
        if self._failure is not None:
            # Backing off a failed go-to was refused too: stop here.
            self._finish(False, self._failure[0], f"{self._failure[1]} ({refusal.text})")
            return
        reason = refusal.reason
        barred = reason in (
            RefusalReason.OBSTACLE_IN_PATH,
            RefusalReason.OBSTACLE_AHEAD,
            RefusalReason.ROBOT_AHEAD,
            RefusalReason.BUMP,
        )
        in_front = reason in (RefusalReason.OBSTACLE_AHEAD, RefusalReason.ROBOT_AHEAD)  # it may go away
        if self.phase is RoutePhase.APPROACHING and barred:
            # As near as it gets: it looks from here (something in front, a person passing by, is
            # first given ``replan_hold_s`` to go, as on a path).
            held = 0.0 if self.held_since is None else now - self.held_since
            if not in_front or held >= c.replan_hold_s:
                self.held_since = None
                self._stand(now)
                return
        if self.phase.replannable and barred:
            # Plan around it: at once when the drive start is refused or the bumper is pressed (the
            # robot touches what it ran into: only backing out is allowed, so back out first), after
            # ``replan_hold_s`` when something stands in front (it may go away).
            held = 0.0 if self.held_since is None else now - self.held_since
            if not in_front or held >= c.replan_hold_s:
                robot = reason is RefusalReason.ROBOT_AHEAD
                # Backed off when the ultrasonic or the bumper barred the way (turning is refused
                # there); not from another robot, which turning passes and backing may meet (the map
                # says nothing of a robot behind, and before its heading is known a robot's rule counts
                # one there too). Nor is another robot a mark: where it stands it is planned around as
                # a body (agent/peers.py), and where it drove on, a mark would bar the way it left.
                ahead = reason is not RefusalReason.OBSTACLE_IN_PATH and not robot
                seen = 0.0 if reason is RefusalReason.BUMP else refusal.distance_m
                self._barred(now, pose, provider, seen, ahead, refusal.text, room, mark=not robot)
                return
        elif reason is RefusalReason.OBSTACLE_IN_PATH:
            self._finish(False, reason.value, f"refused: {refusal.text}")
            return
        # Held: when the way clears, the leg starts afresh (turn, then the drive-start check).
        self.goto.resume()
        if self.held_since is None:
            self.held_since = now
        elif now - self.held_since >= c.blocked_timeout_s:
            self._finish(False, "blocked", f"blocked for {c.blocked_timeout_s:g} s: {refusal.text}")

    def resume(self, now: float) -> None:
        """After a pause: the leg starts afresh, and a pause is not a lack of progress."""
        self.goto.resume()
        self.held_since = None
        self._progress = _Progress(since=now)

    # -- internals -------------------------------------------------------------------------------

    def _finish(self, reached: bool, reason: str, text: str) -> None:
        self.end = RouteEnd(reached, reason, text)

    def _plan(self, now: float, pose: Pose, provider: PathProvider | None) -> bool:
        d = self.dest
        self.phase = RoutePhase.STRAIGHT
        if d.via:
            return self._follow(now, pose, d.via, None)
        if d.trajectory:
            joined = self._join_trajectory(pose)
            if isinstance(joined, list):
                self._planned_with, self._planned_sense = provider, self._sense
                return self._follow(now, pose, joined, None, source="trajectory")
            self.notes.append(RouteNote(False, f"{d.label}: {joined}: planning its own way", "trajectory_refused", 0))
        if provider is None:
            self.goto.start([(d.x, d.y)], d.theta)
            return True
        planned = self._ask(provider, pose, tuple(self.blocked))  # marks: asked again while waiting
        self._planned_with, self._planned_sense = provider, self._sense
        if isinstance(planned, str):
            self._finish(False, "planner_failed", f"the planner failed ({planned})")
            return False
        if planned is not None and len(planned) == 0 and d.deviation > 0.0:
            planned = self._nearby(provider, pose)
        return self._follow(now, pose, planned, None)

    def _join_trajectory(self, pose: Pose) -> list[Point] | str:
        """The order's trajectory from where the robot joins it (the end of the segment nearest to
        it), or why the robot will not drive it: it stands more than ``TRAJECTORY_JOIN_M`` off it
        (the order was resumed elsewhere), or its own map (``sense``) has a wall on the way."""
        d = self.dest
        traj = d.trajectory
        here = (pose[0], pose[1])
        # The first segment it stands near, not the nearest anywhere: a curve that comes back near
        # its start is joined at its start.
        gaps = (
            [math.dist(here, traj[0])]
            if len(traj) == 1
            else [point_segment_distance(*here, (*a, *b)) for a, b in pairwise(traj)]
        )
        k = next((i for i, g in enumerate(gaps) if g <= TRAJECTORY_JOIN_M), None)
        if k is None:
            return f"the robot stands {min(gaps):.2f} m off the order's trajectory"
        rest = list(traj) if len(traj) == 1 else list(traj[k + 1 :])
        sense = self._sense
        if isinstance(sense, WallCheck):
            # Every leg as it will be driven, the last to the node itself; beyond the first (where
            # the robot stands beside what it stands beside), each whole, however short.
            way = [here, *rest]
            if math.dist(way[-1], (d.x, d.y)) > 1e-6:
                way.append((d.x, d.y))
            legs = list(pairwise(way))
            for i, (a, b) in enumerate(legs):
                if sense.leg_meets_wall(a, b, 0.1 if i == 0 else 0.0):
                    return f"its map has a wall on the order's trajectory ({b[0]:.2f}, {b[1]:.2f}), leg {i + 1}"
        return rest

    def _nearby(self, provider: PathProvider, pose: Pose) -> Sequence[Point]:
        """A path to the nearest place within the destination's allowed deviation that has one
        (rings ``DEVIATION_STEP_M`` apart, 8 places on the first and more on each further out),
        which then becomes the destination; [] when none has. A sweep's lane end planned on the map
        of an hour ago may lie in a wall's margin on the map of now: a few centimetres short of it
        is where the lane ends, not a node skipped and its lane lost."""
        d = self.dest
        rings = max(1, math.ceil(min(d.deviation, MAX_DEVIATION_M) / DEVIATION_STEP_M - 1e-9))
        for k in range(1, rings + 1):
            r = min(k * DEVIATION_STEP_M, d.deviation)
            n = 8 * k
            for j in range(n):
                a = 2.0 * math.pi * j / n
                q = (d.x + r * math.cos(a), d.y + r * math.sin(a))
                try:
                    path = provider((pose[0], pose[1]), q)
                except Exception:
                    continue
                if path:
                    self.dest = replace(d, x=q[0], y=q[1])
                    self.notes.append(
                        RouteNote(
                            False,
                            f"{d.label}: ({d.x:.2f}, {d.y:.2f}) cannot be reached: "
                            f"going to ({q[0]:.2f}, {q[1]:.2f}), {r:.2f} m from it",
                            "deviated",
                            len(path),
                        )
                    )
                    return path
        return []

    def _ask(self, provider: PathProvider, pose: Pose, blocked: tuple[Point, ...] = ()) -> Sequence[Point] | str | None:
        """The provider's path, or why it raised: a planner that fails on some input ends the
        route with a reason instead of taking the control loop down with it."""
        d = self.dest
        try:
            if blocked:
                return provider((pose[0], pose[1]), (d.x, d.y), blocked=blocked)
            return provider((pose[0], pose[1]), (d.x, d.y))
        except Exception as exc:
            return f"{type(exc).__name__}: {exc}"[:120]

    def _follow(
        self, now: float, pose: Pose, path: Sequence[Point] | None, why: str | None, *, source: str = "planned"
    ) -> bool:
        """Start the go-to along ``path`` (None: no map, straight line); False when it failed.
        ``source``: where a first path came from (``planned``, or the order's ``trajectory``)."""
        d = self.dest
        goal = (d.x, d.y)
        self._path_sense = self._planned_sense
        if path is None:
            self.phase = RoutePhase.STRAIGHT
            self.goto.start([goal], d.theta)
            return True
        if len(path) == 0:
            # No path on the first map, or on a newer map that shows the way barred (nothing has
            # stopped the robot): what bars it may move (another robot, a person; a robot that
            # stood on the goal is drawn there by every scan that saw it, and cleared only by scans
            # that see through the place since), and the map that shows it gone may have a path.
            # Standing until then, or ``no_path_wait_s``. Barred in front of the robot (the guard's
            # refusals): backing off and trying around, as ``_barred`` does.
            if why is None or (why == "wall_on_map" and self.config.no_path_wait_s > 0.0):
                on = "this map" if why is None or self._waiting_on_marks else "the newer map"
                self._wait(now, f"no path to ({d.x:.2f}, {d.y:.2f}) on {on}", pose)
            else:
                self._fail(now, pose, "blocked", f"blocked ({why}) and no way around")
            return False
        pts = _ahead(path, pose)
        # The goal itself ends the list.
        if not pts or math.hypot(pts[-1][0] - d.x, pts[-1][1] - d.y) > 1e-6:
            pts.append(goal)
        self.goto.start(pts, d.theta)
        self.phase = RoutePhase.FOLLOWING
        self._progress = _Progress(since=now)
        self._leg = None
        self.held_since = None
        self.waiting_since = None  # a later wait is for whatever bars the way then
        self._waiting_on_marks = False
        n = len(pts)
        if why is None:
            text = "planned path" if source == "planned" else "the order's trajectory"
            self.notes.append(RouteNote(False, f"{d.label}: {text}, {n} waypoints", source, n))
        else:
            text = f"{d.label}: re-planned ({why}, {self.replans}/{self.config.max_replans}), {n} waypoints"
            self.notes.append(RouteNote(True, text, why, n))
        return True

    def _wait(self, now: float, text: str, pose: Pose | None = None) -> None:
        """Stand (``WAITING``) for a newer map with a path, at most ``no_path_wait_s`` since the wait
        began (0: the route fails at once, ``no_path``). With ``pose``, a goal farther than
        ``approach_m`` is first approached (``_approach``)."""
        d = self.dest
        c = self.config
        if self.waiting_since is None:
            wait = f"waiting up to {c.no_path_wait_s:g} s for the way to clear"
            if c.no_path_wait_s > 0.0 and pose is not None and self._approach(now, pose):
                wait = f"going within {c.approach_m:g} m of it to look, then {wait}"
                self.notes.append(RouteNote(False, f"{d.label}: {text}: {wait}", "waiting", len(self.goto.waypoints)))
                return
            self.waiting_since = now
            self.notes.append(RouteNote(False, f"{d.label}: {text}: {wait}", "waiting", 0))
        if c.no_path_wait_s <= 0.0:
            self._finish(False, "no_path", f"no path to ({d.x:.2f}, {d.y:.2f})")
        else:
            self.phase = RoutePhase.WAITING

    def _approach(self, now: float, pose: Pose) -> bool:
        """Start going to within ``approach_m`` of a goal the map has no path to, barred only by
        something the size of a robot or a person (``MovableCheck``; once per go-to): the map of a
        far place may be stale. What stood there and went (another robot on the goal) is cleared
        only by beams through the place since, and from far off few pass near it, none at all
        across an open hall where nothing returns them (a no-return sector clears only 5 m:
        agent/mapping/scan.py). From nearer the robot looks again; a newer map with a path ends the
        approach. A goal in a wall is not driven at. The robot goes to the place on a ring
        ``approach_m`` about the goal nearest it that it can reach (``MovableCheck.place_near``);
        False: no approach (the goal is near already, barred by a wall, or no such place)."""
        c, d = self.config, self.dest
        provider, sense = self._planned_with, self._planned_sense
        if self._approached or provider is None or c.approach_m <= 0.0:
            return False
        if math.hypot(d.x - pose[0], d.y - pose[1]) <= c.approach_m + APPROACH_MIN_GAIN_M:
            return False
        if not isinstance(sense, MovableCheck) or not sense.barred_by_movable((d.x, d.y)):
            return False
        self._approached = True
        here = (pose[0], pose[1])
        try:
            place = sense.place_near(here, (d.x, d.y), c.approach_m)
            path = None if place is None else provider(here, place)
        except Exception:
            return False  # the wait, as without an approach
        if not path:
            return False
        pts = _ahead(path, pose)
        if not pts:
            return False  # already there
        self.goto.start(pts, None)
        self.phase = RoutePhase.APPROACHING
        self._progress = _Progress(since=now)
        self.held_since = None
        return True

    def _approach_step(self, now: float, pose: Pose, provider: PathProvider | None) -> Drive:
        """One tick of the approach: a newer map with a path to the goal takes the route there;
        arrived, or no nearer for ``no_progress_s``: stand and wait from here."""
        if provider is not self._planned_with:
            self._planned_with, self._planned_sense = provider, self._sense
            path = None if provider is None else self._ask(provider, pose, tuple(self.blocked))
            if path is None or (not isinstance(path, str) and len(path) > 0):
                self.waiting_since = None
                self._follow(now, pose, path, None)  # driven from the next tick
                return _STILL
        cmd = self.goto.step(now, pose)
        if cmd.phase is GoToPhase.DONE or self._stalled(now, pose, cmd.waypoint_index):
            self._stand(now)
            return _STILL
        return Drive(cmd.v, cmd.omega, cmd.drive_distance_m)

    def _stand(self, now: float) -> None:
        """The approach ends where the robot stands: the wait for a newer map counts from now."""
        self.phase = RoutePhase.WAITING
        self.waiting_since = now

    def _replan(self, now: float, pose: Pose, provider: PathProvider | None, why: str, *, counted: bool = True) -> bool:
        """Plan again from here. ``counted``: a re-plan because the way was barred (at most
        ``max_replans``); not counted: because a newer map showed the leg barred before the robot
        got there (``max_map_replans``, checked by the caller)."""
        if counted:
            if self.replans >= self.config.max_replans:
                self._fail(now, pose, "blocked", f"still blocked ({why}) after {self.replans} re-plans")
                return False
            self.replans += 1
        # A provider withdrawn mid-route (the map was dropped) means no map: straight from here.
        path = None if provider is None else self._ask(provider, pose, tuple(self.blocked))
        self._planned_with, self._planned_sense = provider, self._sense
        if isinstance(path, str):
            self._fail(now, pose, "planner_failed", f"the planner failed ({path})")
            return False
        if why == "blocked" and path is not None and len(path) == 0 and self.config.no_path_wait_s > 0.0:
            # No way around where the robot was barred, but the map alone has one: what barred it is
            # not on the map (a wall would be: ``unknown_marks``), so it may move. A robot met head
            # on where its goal lies, a person standing there: wait for it rather than fail.
            assert provider is not None
            own = self._ask(provider, pose)
            if not isinstance(own, str) and own:
                d = self.dest
                self._waiting_on_marks = True
                self._wait(now, f"barred on the way to ({d.x:.2f}, {d.y:.2f}) by something not on the map")
                return False
        return self._follow(now, pose, path, why)

    def _newly_barred(self, older: object | None, newer: object | None, pose: Pose) -> bool:
        """The leg being driven (or the next) runs into a wall on the newer map that the older did
        not hold: a leg laid into the unknown (a goal beyond the robot's map, e.g. floor only another
        robot had mapped) or on an older map. The front ultrasonic sees ahead, not a corner beside
        the robot as it passes (the kitchen's two-robot round, docs/payload.md)."""
        if not isinstance(newer, WallCheck):
            return False
        ahead = [(pose[0], pose[1]), *self.goto.waypoints[self.goto.index : self.goto.index + 2]]
        for a, b in pairwise(ahead):
            if newer.leg_meets_wall(a, b) and not (isinstance(older, WallCheck) and older.leg_meets_wall(a, b)):
                return True
        return False

    def _barred(
        self,
        now: float,
        pose: Pose,
        provider: PathProvider | None,
        seen_m: float | None,
        ahead: bool,
        text: str,
        room: RoomBehind | None,
        *,
        mark: bool = True,
    ) -> None:
        """The guard barred the way on a planned path: mark where (``mark``), then back off (if near)
        and re-plan."""
        c = self.config
        if mark:
            # The echo is the obstacle's near face: mark a point a little behind it.
            reach = c.sensor_offset_m + (seen_m if seen_m is not None else c.stop_distance_m) + c.mark_depth_m
            self.blocked.append((pose[0] + reach * math.cos(pose[2]), pose[1] + reach * math.sin(pose[2])))
        self.held_since = None
        if self.replans >= c.max_replans:
            self._fail(now, pose, "blocked", f"still blocked after {self.replans} re-plans: {text}", ahead, room)
        elif ahead and self._back_off(now, pose, room):
            self.phase = RoutePhase.BACKING_OFF
        else:
            self._replan(now, pose, provider, "blocked")

    def _back_off(self, now: float, pose: Pose, room: RoomBehind | None) -> bool:
        """Start backing straight off the spot, as far as ``backoff_m`` and the map behind allow
        (False: no room behind, a door jamb or a wall there: plan on from here)."""
        length = (
            self.config.backoff_m if room is None else min(self.config.backoff_m, room(pose, self.config.backoff_m))
        )
        if length < _MIN_BACKOFF_M:
            return False
        self._backoff = _Backoff(pose[0], pose[1], now, length)
        return True

    def _fail(
        self, now: float, pose: Pose, reason: str, text: str, ahead: bool = False, room: RoomBehind | None = None
    ) -> None:
        """A planned go-to fails: first back off the spot (back along the leg the robot drove to get
        there, so the next go-to does not start facing what barred this one), then the end."""
        self._failure = (reason, text)
        if ahead and self._back_off(now, pose, room):  # turning is refused there: straight back first
            self.phase = RoutePhase.FAILING_BACKOFF
        else:
            self.phase = RoutePhase.RETREATING
            self._retreat(pose)

    def _retreat(self, pose: Pose) -> bool:
        """Start the go-to back along the current leg (False: the route ended here instead)."""
        assert self._failure is not None
        c = self.config
        # The latest point the robot drove on from that is not where it stands (a re-plan starts a
        # leg in place): the straight line back to it is the way it came.
        back = next((p for p in reversed(self._trail) if math.hypot(p[0] - pose[0], p[1] - pose[1]) > 0.1), None)
        if back is None or c.retreat_m <= 0.0:
            self._finish(False, *self._failure)
            return False
        k = min(1.0, c.retreat_m / math.hypot(back[0] - pose[0], back[1] - pose[1]))
        self.goto.start([(pose[0] + k * (back[0] - pose[0]), pose[1] + k * (back[1] - pose[1]))], None)
        return True

    def _stalled(self, now: float, pose: Pose, index: int) -> bool:
        """No waypoint passed and no closer to the current one by ``progress_m`` for ``no_progress_s``."""
        wx, wy = self.goto.waypoints[index]
        d = math.hypot(wx - pose[0], wy - pose[1])
        p = self._progress
        if index != p.index or d < p.best - self.config.progress_m:
            self._progress = _Progress(index, d, now)
            return False
        return now - p.since >= self.config.no_progress_s


def _ahead(path: Sequence[Point], pose: Pose) -> list[Point]:
    """``path``'s waypoints without those where the robot already stands (within 5 cm) at its start."""
    pts = [(float(px), float(py)) for px, py in path]
    while pts and math.hypot(pts[0][0] - pose[0], pts[0][1] - pose[1]) < 0.05:
        pts.pop(0)
    return pts
