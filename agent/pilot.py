"""The pilot: arbitrates every motion command and puts the collision guard in front of the motors (pure).

The runtime calls the command methods when a command arrives (``teleop``, ``order``, ``action``)
and ``tick`` every control period *and* right after every command, so commands take effect on
arrival. ``tick`` is idempotent in time: calling it again at the same ``now`` changes nothing but
delivers the events queued by the commands in between.

Modes (``OperatingMode``): IDLE (still), MANUAL (teleop; stops when no fresh command arrives
within its time-to-live), AUTOMATIC (go-to), PAUSED (go-to held), ESTOP (latched until
released). Orders are idempotent on (order_id, order_update_id): the same pair again is a
duplicate, a higher update replaces the goal, a lower one is rejected. Order of precedence:
e-stop > guard > the latest command (teleop overrides a go-to, a new order overrides teleop).

With a path provider (the A* planner over the map) a go-to or return home follows the planned
waypoints, and re-plans from where it stands when the guard bars the way (or it makes no progress),
handing the provider the points where the way was barred; after ``max_replans`` it fails (blocked).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol

from fleetlink.agent.guard import CollisionGuard, GuardConfig, GuardInputs, RefusalReason
from fleetlink.agent.motion import GoToConfig, GoToController, GoToPhase, MotionLimits, RateLimiter

__all__ = [
    "ActionKind",
    "CommandResult",
    "CommandStatus",
    "EventKind",
    "OperatingMode",
    "PathProvider",
    "PayloadRequest",
    "Pilot",
    "PilotConfig",
    "PilotEvent",
    "PilotOutput",
]

Pose = tuple[float, float, float]
Point = tuple[float, float]


class PathProvider(Protocol):
    """(start, goal, blocked) -> waypoints ending at the goal; ``[]``: no path (the goal fails);
    ``None``: no map (the pilot drives straight, as without a provider). ``blocked`` are points where
    the robot found its way barred during this go-to (to be planned around)."""

    def __call__(self, start: Point, goal: Point, /, blocked: Sequence[Point] = ()) -> Sequence[Point] | None: ...


class OperatingMode(StrEnum):
    IDLE = "IDLE"
    MANUAL = "MANUAL"
    AUTOMATIC = "AUTOMATIC"
    PAUSED = "PAUSED"
    ESTOP = "ESTOP"


class EventKind(StrEnum):
    GUARD_REFUSAL = "GUARD_REFUSAL"
    CLIFF = "CLIFF"
    BUMP = "BUMP"
    GOAL_REACHED = "GOAL_REACHED"
    GOAL_CANCELLED = "GOAL_CANCELLED"
    GOAL_FAILED = "GOAL_FAILED"
    DEADMAN_STOP = "DEADMAN_STOP"
    ESTOP_LATCHED = "ESTOP_LATCHED"
    ESTOP_RELEASED = "ESTOP_RELEASED"
    PAUSED = "PAUSED"
    RESUMED = "RESUMED"
    STOPPED = "STOPPED"
    FAULT = "FAULT"
    PATH_PLANNED = "PATH_PLANNED"  # a go-to follows a planned path (``waypoints``: how many)
    REPLANNED = "REPLANNED"  # the way was barred (or no progress): a new path from here


class ActionKind(StrEnum):
    STOP = "stop"
    PAUSE = "pause"
    RESUME = "resume"
    CANCEL = "cancel"
    ESTOP = "estop"
    ESTOP_RELEASE = "estop_release"
    RETURN_HOME = "return_home"
    PAYLOAD_ON = "payload_on"
    PAYLOAD_OFF = "payload_off"


class CommandStatus(StrEnum):
    ACCEPTED = "accepted"
    DUPLICATE = "duplicate"
    REJECTED = "rejected"


@dataclass(frozen=True, slots=True)
class CommandResult:
    status: CommandStatus
    reason: str = ""

    @property
    def accepted(self) -> bool:
        return self.status is CommandStatus.ACCEPTED


_OK = CommandResult(CommandStatus.ACCEPTED)


def _rejected(reason: str) -> CommandResult:
    return CommandResult(CommandStatus.REJECTED, reason)


@dataclass(frozen=True, slots=True)
class PilotEvent:
    kind: EventKind
    text: str  # for people
    reason: str = ""  # machine-readable (a RefusalReason value, "teleop_override", ...)
    order_id: str | None = None
    t: float = 0.0
    waypoints: int | None = None  # PATH_PLANNED / REPLANNED: the new path's waypoint count


@dataclass(frozen=True, slots=True)
class PayloadRequest:
    """For the runtime to send to the board (the pilot never talks to hardware)."""

    on: bool
    level: int | None = None
    sender: str = ""


@dataclass(frozen=True, slots=True)
class PilotOutput:
    v: float
    omega: float
    mode: OperatingMode
    events: list[PilotEvent] = field(default_factory=list)
    payload_requests: list[PayloadRequest] = field(default_factory=list)
    estop: bool = False
    field_violation: bool = False  # the guard is refusing (VDA 5050 safetyState.fieldViolation)
    goal: Pose | None = None  # (x, y, theta or nan) of the active or paused go-to
    order_id: str | None = None


@dataclass(frozen=True, slots=True)
class PilotConfig:
    guard: GuardConfig = field(default_factory=GuardConfig)
    limits: MotionLimits = field(default_factory=MotionLimits)
    goto: GoToConfig = field(default_factory=GoToConfig)
    teleop_ttl_s: float = 0.5  # default time-to-live of a teleop command
    teleop_max_ttl_s: float = 2.0  # longer ones are clamped: a lost link must stop the robot soon
    blocked_timeout_s: float = 10.0  # a go-to held by an obstacle this long fails
    remembered_orders: int = 256  # order ids kept for idempotency
    # Planned paths (only with a path provider that returned a path):
    max_replans: int = 3  # a go-to barred once more after this many re-plans fails (reason "blocked")
    replan_hold_s: float = 2.0  # held by an obstacle ahead this long: back off and re-plan around it
    no_progress_s: float = 8.0  # no waypoint passed and no closer by ``progress_m`` this long: re-plan
    progress_m: float = 0.05
    sensor_offset_m: float = 0.17  # the front ultrasonic is this far ahead of the robot's centre
    backoff_m: float = 0.15  # before re-planning around an obstacle ahead (turning is refused there)
    backoff_speed: float = 0.1  # m/s
    mark_depth_m: float = 0.1  # the blocked point handed to the provider: this far beyond the echo
    # A planned go-to that fails (blocked) first backs the robot off the spot where it was barred:
    # back along the leg it drove (free: it just drove it), at most this far, then GOAL_FAILED.
    retreat_m: float = 0.5  # 0: fail where it stands
    # On a planned path, a drive start whose echo is nearer than the leg plus the stop distance
    # (often a wall or door frame at the cone's edge, beyond the waypoint) drives only as far as
    # the echo allows, less this margin, and looks again; shorter than ``creep_min_m``: refused.
    creep_margin_m: float = 0.1
    creep_min_m: float = 0.2


@dataclass(slots=True)
class _Teleop:
    v: float
    omega: float
    t: float
    ttl: float
    sender: str


@dataclass(slots=True)
class _Order:
    order_id: str | None  # None: return home
    update_id: int
    x: float
    y: float
    theta: float | None
    sender: str
    planned: bool = False
    path: bool = False  # following a provider's path (re-plannable)
    replans: int = 0
    blocked: list[Point] = field(default_factory=list)
    backoff: Pose | None = None  # backing away from (x, y, since) before a re-plan
    progress: tuple[int, float, float] = (-1, math.inf, 0.0)  # (waypoint index, best distance, since)
    leg: int | None = None  # the waypoint index whose leg the trail's last point began
    trail: list[Point] = field(default_factory=list)  # where the robot stood as each leg began (free)
    failing: tuple[str, str] | None = None  # (reason, text): retreating before GOAL_FAILED

    @property
    def label(self) -> str:
        return "return home" if self.order_id is None else f"order {self.order_id}/{self.update_id}"


def _finite(*vals: float) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in vals)


class Pilot:
    def __init__(
        self,
        config: PilotConfig | None = None,
        home: Pose = (0.0, 0.0, 0.0),
        path_provider: PathProvider | None = None,
    ) -> None:
        self.config = config or PilotConfig()
        c = self.config
        self.guard = CollisionGuard(c.guard)
        self.goto = GoToController(c.limits, c.goto)
        self.limiter = RateLimiter(c.limits)
        self.path_provider = path_provider
        self._home: Pose = home
        self._mode = OperatingMode.IDLE
        self._resume_mode = OperatingMode.IDLE
        self._teleop: _Teleop | None = None
        self._order: _Order | None = None
        self._seen: OrderedDict[str, int] = OrderedDict()
        self._events: list[PilotEvent] = []
        self._payload: list[PayloadRequest] = []
        self._refusal: RefusalReason | None = None
        self._blocked_since: float | None = None
        self._cliff = False
        self._bump = False
        self._pose_fault = False
        self._now = 0.0

    # -- what the runtime reads ------------------------------------------------------------------

    @property
    def mode(self) -> OperatingMode:
        return self._mode

    @property
    def estop(self) -> bool:
        return self._mode is OperatingMode.ESTOP

    @property
    def home(self) -> Pose:
        return self._home

    def set_home(self, pose: Pose) -> None:
        if not _finite(*pose):
            raise ValueError(f"home pose must be finite, got {pose}")
        self._home = pose

    @property
    def goal(self) -> Pose | None:
        o = self._order
        if o is None:
            return None
        return (o.x, o.y, math.nan if o.theta is None else o.theta)

    @property
    def order_id(self) -> str | None:
        return self._order.order_id if self._order else None

    @property
    def order_update_id(self) -> int:
        """The active order's orderUpdateId (0 without one): what ``state.orderUpdateId`` carries."""
        return self._order.update_id if self._order else 0

    def next_deadline(self) -> float | None:
        """When the teleop command lapses: tick at this time to stop exactly on time."""
        t = self._teleop
        return t.t + t.ttl if t is not None and self._mode is OperatingMode.MANUAL else None

    # -- commands (called on arrival) ------------------------------------------------------------

    def teleop(self, now: float, v: float, omega: float, ttl_s: float | None, sender: str) -> CommandResult:
        c = self.config
        if not _finite(v, omega):
            return _rejected(f"teleop velocity must be finite, got v={v} omega={omega}")
        ttl = c.teleop_ttl_s if ttl_s is None else ttl_s
        if not _finite(ttl) or ttl <= 0:
            return _rejected(f"teleop ttl must be > 0 s, got {ttl_s}")
        if self._mode is OperatingMode.ESTOP:
            return _rejected("e-stop latched")
        cur = self._teleop
        if (
            self._mode is OperatingMode.MANUAL
            and cur is not None
            and cur.sender != sender
            and now < cur.t + cur.ttl
            and (cur.v != 0.0 or cur.omega != 0.0)
            and (v != 0.0 or omega != 0.0)  # anyone may stop the robot
        ):
            return _rejected(f"robot is being driven by {cur.sender}")
        if self._mode in (OperatingMode.AUTOMATIC, OperatingMode.PAUSED):
            self._end_order(
                now, EventKind.GOAL_CANCELLED, "teleop_override", f"cancelled: {sender} took manual control"
            )
        lim = c.limits
        self._teleop = _Teleop(
            max(-lim.v_max, min(lim.v_max, v)),
            max(-lim.omega_max, min(lim.omega_max, omega)),
            now,
            min(ttl, c.teleop_max_ttl_s),
            sender,
        )
        self._mode = OperatingMode.MANUAL
        return _OK

    def order(
        self,
        now: float,
        order_id: str,
        order_update_id: int,
        x: float,
        y: float,
        theta: float | None,
        sender: str,
    ) -> CommandResult:
        if not order_id:
            return _rejected("order id must not be empty")
        if isinstance(order_update_id, bool) or not isinstance(order_update_id, int) or order_update_id < 0:
            return _rejected(f"order update id must be an integer >= 0, got {order_update_id!r}")
        if not _finite(x, y) or (theta is not None and not _finite(theta)):
            return _rejected(f"goal must be finite, got x={x} y={y} theta={theta}")
        seen = self._seen.get(order_id)
        if seen is not None and order_update_id == seen:
            return CommandResult(CommandStatus.DUPLICATE, f"order {order_id}/{order_update_id} already received")
        if seen is not None and order_update_id < seen:
            return _rejected(f"order {order_id}: update {order_update_id} is older than {seen}")
        if self._mode is OperatingMode.ESTOP:
            return _rejected("e-stop latched")
        self._seen[order_id] = order_update_id
        self._seen.move_to_end(order_id)
        while len(self._seen) > self.config.remembered_orders:
            self._seen.popitem(last=False)
        cur = self._order
        if cur is not None and cur.order_id != order_id:
            self._end_order(now, EventKind.GOAL_CANCELLED, "replaced", f"replaced by order {order_id}")
        keep_paused = self._mode is OperatingMode.PAUSED and cur is not None and cur.order_id == order_id
        self._start_order(now, _Order(order_id, order_update_id, x, y, theta, sender), keep_paused)
        return _OK

    def action(self, now: float, kind: ActionKind | str, sender: str, **params: object) -> CommandResult:
        try:
            kind = ActionKind(kind)
        except ValueError:
            return _rejected(f"unknown action {kind!r}")
        estop = self._mode is OperatingMode.ESTOP
        if kind is ActionKind.ESTOP:
            if estop:
                return CommandResult(CommandStatus.DUPLICATE, "e-stop already latched")
            self._end_order(now, EventKind.GOAL_CANCELLED, "estop", "cancelled by e-stop")
            self._teleop = None
            self._mode = OperatingMode.ESTOP
            self._emit(now, EventKind.ESTOP_LATCHED, f"e-stop latched by {sender}", "estop")
            return _OK
        if kind is ActionKind.ESTOP_RELEASE:
            if not estop:
                return _rejected("e-stop is not latched")
            self._mode = OperatingMode.IDLE
            self._emit(now, EventKind.ESTOP_RELEASED, f"e-stop released by {sender}", "estop_release")
            return _OK
        if kind is ActionKind.PAYLOAD_OFF:
            self._payload.append(PayloadRequest(False, None, sender))
            return _OK
        if kind is ActionKind.STOP:
            self._end_order(now, EventKind.GOAL_CANCELLED, "stop", f"stopped by {sender}")
            self._teleop = None
            if not estop:
                self._mode = OperatingMode.IDLE
            self._emit(now, EventKind.STOPPED, f"stopped by {sender}", "stop")
            return _OK
        if estop:
            return _rejected("e-stop latched")
        if kind is ActionKind.PAYLOAD_ON:
            level = params.get("level")
            if level is not None and (isinstance(level, bool) or not isinstance(level, int) or level < 0):
                return _rejected(f"payload level must be an integer >= 0, got {level!r}")
            self._payload.append(PayloadRequest(True, level, sender))
            return _OK
        if kind is ActionKind.PAUSE:
            if self._mode is not OperatingMode.AUTOMATIC:
                return _rejected(f"nothing to pause in mode {self._mode.value}")
            self._mode = OperatingMode.PAUSED
            self._emit(now, EventKind.PAUSED, f"go-to paused by {sender}", "pause")
            return _OK
        if kind is ActionKind.RESUME:
            if self._mode is not OperatingMode.PAUSED:
                return _rejected(f"nothing to resume in mode {self._mode.value}")
            self._mode = OperatingMode.AUTOMATIC
            self.goto.resume()
            self._blocked_since = None
            if self._order is not None:
                self._order.progress = (-1, math.inf, now)  # a pause is not a lack of progress
            self._emit(now, EventKind.RESUMED, f"go-to resumed by {sender}", "resume")
            return _OK
        if kind is ActionKind.CANCEL:
            if self._order is None:
                return _rejected("no order to cancel")
            self._end_order(now, EventKind.GOAL_CANCELLED, "cancel", f"cancelled by {sender}")
            return _OK
        # RETURN_HOME
        if self._order is not None and self._order.order_id is not None:
            self._end_order(now, EventKind.GOAL_CANCELLED, "replaced", "replaced by return home")
        hx, hy, hth = self._home
        self._start_order(now, _Order(None, 0, hx, hy, hth, sender), keep_paused=False)
        return _OK

    # -- the control tick ------------------------------------------------------------------------

    def tick(self, now: float, pose: Pose, inputs: GuardInputs) -> PilotOutput:
        self._now = now
        # Safety edges first: cliff and bump are events, and they end a go-to.
        if inputs.cliff and not self._cliff:
            self._emit(now, EventKind.CLIFF, "cliff detected: stopped", "cliff")
            self._fail_if_moving(now, "cliff", "cliff detected")
        if inputs.bumped and not self._bump:
            self._emit(now, EventKind.BUMP, "bumper pressed: stopped", "bump")
            self._fail_if_moving(now, "bump", "bumper pressed")
        self._cliff, self._bump = inputs.cliff, inputs.bumped

        pose_ok = _finite(*pose)
        if not pose_ok and not self._pose_fault:
            self._emit(now, EventKind.FAULT, f"pose is not finite ({pose}): holding still", "pose_invalid")
        self._pose_fault = not pose_ok

        v = omega = 0.0
        drive_distance: float | None = None
        mode = self._mode
        if mode is OperatingMode.MANUAL:
            t = self._teleop
            if t is None or now >= t.t + t.ttl:
                if t is not None:
                    self._emit(
                        now,
                        EventKind.DEADMAN_STOP,
                        f"no teleop command from {t.sender} for {t.ttl:.2f} s: stopped",
                        "deadman",
                    )
                self._teleop = None
                self._mode = OperatingMode.IDLE
            else:
                v, omega = t.v, t.omega
        elif mode is OperatingMode.AUTOMATIC and pose_ok:
            v, omega, drive_distance = self._goto_step(now, pose)
            if drive_distance is not None and v > 0.0:
                drive_distance = self._cut_short(pose, inputs, drive_distance)

        if v == 0.0 and omega == 0.0:
            self.limiter.reset(now)
            if self._blocked_since is None or self._mode is not OperatingMode.AUTOMATIC:
                self._refusal = None  # (a held go-to re-aiming between refusals is the same episode)
            return self._output(0.0, 0.0, refusing=False)

        # The drive-start check sees the wanted speed (the limiter may still be at zero).
        decision = self.guard.filter(v, omega, inputs, goto_drive_distance_m=drive_distance)
        if decision.refusal is None:
            lv, lw = self.limiter.step(now, v, omega)
            decision = self.guard.filter(lv, lw, inputs)
        if decision.refusal is not None:
            r = decision.refusal
            if r.reason is not self._refusal:
                self._emit(now, EventKind.GUARD_REFUSAL, r.text, r.reason.value)
            self._refusal = r.reason
            self.limiter.reset(now)
            if self._mode is OperatingMode.AUTOMATIC:
                o = self._order
                barred = r.reason in (RefusalReason.OBSTACLE_IN_PATH, RefusalReason.OBSTACLE_AHEAD)
                if o is not None and o.failing is not None:
                    # Backing off a failed go-to was refused too: stop here.
                    self._end_order(now, EventKind.GOAL_FAILED, o.failing[0], f"{o.failing[1]} ({r.text})")
                    return self._output(0.0, 0.0, refusing=True)
                if o is not None and o.path and barred:
                    # On a planned path: plan around it (at once when the drive start is refused,
                    # after ``replan_hold_s`` when something stands in front: it may go away).
                    held = 0.0 if self._blocked_since is None else now - self._blocked_since
                    if r.reason is RefusalReason.OBSTACLE_IN_PATH or held >= self.config.replan_hold_s:
                        self._barred(now, pose, o, r.distance_m, r.reason is RefusalReason.OBSTACLE_AHEAD, r.text)
                        return self._output(0.0, 0.0, refusing=True)
                elif r.reason is RefusalReason.OBSTACLE_IN_PATH:
                    self._end_order(now, EventKind.GOAL_FAILED, r.reason.value, f"refused: {r.text}")
                    return self._output(0.0, 0.0, refusing=True)
                # Held: when the way clears, the leg starts afresh (turn, then the drive-start check).
                self.goto.resume()
                if self._blocked_since is None:
                    self._blocked_since = now
                elif now - self._blocked_since >= self.config.blocked_timeout_s:
                    self._end_order(
                        now,
                        EventKind.GOAL_FAILED,
                        "blocked",
                        f"blocked for {self.config.blocked_timeout_s:g} s: {r.text}",
                    )
            return self._output(0.0, 0.0, refusing=True)
        self._refusal = None
        self._blocked_since = None
        return self._output(decision.v, decision.omega, refusing=False)

    # -- internals -------------------------------------------------------------------------------

    def _goto_step(self, now: float, pose: Pose) -> tuple[float, float, float | None]:
        o = self._order
        assert o is not None
        c = self.config
        if o.backoff is not None:
            # Backing away from an obstacle ahead (the guard refuses turning near it), then re-plan.
            bx, by, since = o.backoff
            if (
                math.hypot(pose[0] - bx, pose[1] - by) < c.backoff_m
                and now - since < 3.0 * c.backoff_m / c.backoff_speed
            ):
                return -c.backoff_speed, 0.0, None
            o.backoff = None
            if o.failing is not None:
                if not self._retreat(now, pose, o):
                    return 0.0, 0.0, None
            elif not self._replan(now, pose, o, "blocked"):
                return 0.0, 0.0, None
        if not o.planned and not self._plan(now, pose, o):
            return 0.0, 0.0, None
        cmd = self.goto.step(now, pose)
        if cmd.phase is GoToPhase.DONE:
            if o.failing is not None:
                reason, text = o.failing
                self._end_order(
                    now, EventKind.GOAL_FAILED, reason, f"{text}; backed off to ({pose[0]:.2f}, {pose[1]:.2f})"
                )
                return 0.0, 0.0, None
            self._end_order(now, EventKind.GOAL_REACHED, "reached", f"reached ({cmd.distance_m * 100:.1f} cm off)")
            return 0.0, 0.0, None
        if o.failing is not None:
            return cmd.v, cmd.omega, cmd.drive_distance_m
        if o.leg != cmd.waypoint_index:
            o.leg = cmd.waypoint_index
            if not o.trail or math.hypot(o.trail[-1][0] - pose[0], o.trail[-1][1] - pose[1]) > 0.05:
                o.trail.append((pose[0], pose[1]))
                del o.trail[:-8]
        if o.path and cmd.phase is not GoToPhase.FINAL_HEADING and self._stalled(now, pose, o, cmd.waypoint_index):
            if not self._replan(now, pose, o, "no_progress"):
                return 0.0, 0.0, None
            cmd = self.goto.step(now, pose)
        return cmd.v, cmd.omega, cmd.drive_distance_m

    def _cut_short(self, pose: Pose, inputs: GuardInputs, leg: float) -> float:
        """A drive start on a planned path with an echo nearer than ``leg`` + the stop distance: ask
        for the part of the leg the echo leaves clear (a waypoint on the way), the guard checks
        that. The rest of the leg gets its own drive-start check from nearer, where a door frame
        at the cone's edge has dropped out of the cone and an obstacle really ahead still bars it."""
        o, c = self._order, self.config
        if o is None or not o.path or o.failing is not None:
            return leg
        seen = self.guard.obstacle_m(inputs)
        if seen is None or seen >= leg + c.guard.stop_distance_m:
            return leg
        short = seen - c.guard.stop_distance_m - c.creep_margin_m
        if short < c.creep_min_m or short > leg - c.goto.waypoint_tol_m:
            return leg
        wx, wy = self.goto.waypoints[self.goto.index]
        d = math.hypot(wx - pose[0], wy - pose[1])
        if d <= short:
            return leg
        k = short / d
        self.goto.insert_waypoint((pose[0] + k * (wx - pose[0]), pose[1] + k * (wy - pose[1])))
        return short

    def _plan(self, now: float, pose: Pose, o: _Order) -> bool:
        o.planned = True
        if self.path_provider is None:
            self.goto.start([(o.x, o.y)], o.theta)
            return True
        return self._follow(now, pose, o, self.path_provider((pose[0], pose[1]), (o.x, o.y)), None)

    def _follow(self, now: float, pose: Pose, o: _Order, path: Sequence[Point] | None, why: str | None) -> bool:
        """Start the go-to along ``path`` (None: no map, straight line); False when it failed."""
        goal = (o.x, o.y)
        if path is None:
            o.path = False
            self.goto.start([goal], o.theta)
            return True
        if len(path) == 0:
            if why is None:
                self._end_order(now, EventKind.GOAL_FAILED, "no_path", f"no path to ({o.x:.2f}, {o.y:.2f})")
            else:
                self._fail(now, pose, o, "blocked", f"blocked ({why}) and no way around")
            return False
        pts = [(float(px), float(py)) for px, py in path]
        # Drop waypoints at the start; make sure the goal itself ends the list.
        while pts and math.hypot(pts[0][0] - pose[0], pts[0][1] - pose[1]) < 0.05:
            pts.pop(0)
        if not pts or math.hypot(pts[-1][0] - o.x, pts[-1][1] - o.y) > 1e-6:
            pts.append(goal)
        self.goto.start(pts, o.theta)
        o.path = True
        o.progress = (-1, math.inf, now)
        o.leg = None
        self._blocked_since = None
        n = len(pts)
        if why is None:
            self._emit(now, EventKind.PATH_PLANNED, f"{o.label}: planned path, {n} waypoints", "planned", o.order_id, n)
        else:
            text = f"{o.label}: re-planned ({why}, {o.replans}/{self.config.max_replans}), {n} waypoints"
            self._emit(now, EventKind.REPLANNED, text, why, o.order_id, n)
        return True

    def _replan(self, now: float, pose: Pose, o: _Order, why: str) -> bool:
        if o.replans >= self.config.max_replans:
            self._fail(now, pose, o, "blocked", f"still blocked ({why}) after {o.replans} re-plans")
            return False
        assert self.path_provider is not None
        o.replans += 1
        path = self.path_provider((pose[0], pose[1]), (o.x, o.y), blocked=tuple(o.blocked))
        return self._follow(now, pose, o, path, why)

    def _barred(self, now: float, pose: Pose, o: _Order, seen_m: float | None, ahead: bool, text: str) -> None:
        """The guard barred the way on a planned path: mark where, then back off (if near) and re-plan."""
        c = self.config
        # The echo is the obstacle's near face: mark a point a little behind it.
        reach = c.sensor_offset_m + (seen_m if seen_m is not None else c.guard.stop_distance_m) + c.mark_depth_m
        o.blocked.append((pose[0] + reach * math.cos(pose[2]), pose[1] + reach * math.sin(pose[2])))
        self._blocked_since = None
        if o.replans >= c.max_replans:
            self._fail(now, pose, o, "blocked", f"still blocked after {o.replans} re-plans: {text}", ahead)
        elif ahead:
            o.backoff = (pose[0], pose[1], now)
        else:
            self._replan(now, pose, o, "blocked")

    def _fail(self, now: float, pose: Pose, o: _Order, reason: str, text: str, ahead: bool = False) -> None:
        """A planned go-to fails: first back off the spot (back along the leg the robot drove to get
        there, so the next go-to does not start facing what barred this one), then GOAL_FAILED."""
        o.failing = (reason, text)
        o.path = False  # no more re-planning
        if ahead:
            o.backoff = (pose[0], pose[1], now)  # turning is refused there: straight back first
        else:
            self._retreat(now, pose, o)

    def _retreat(self, now: float, pose: Pose, o: _Order) -> bool:
        """Start the go-to back along the current leg (False: the order ended here instead)."""
        assert o.failing is not None
        c = self.config
        # The latest point the robot drove on from that is not where it stands (a re-plan starts a
        # leg in place): the straight line back to it is the way it came.
        back = next((p for p in reversed(o.trail) if math.hypot(p[0] - pose[0], p[1] - pose[1]) > 0.1), None)
        if back is None or c.retreat_m <= 0.0:
            self._end_order(now, EventKind.GOAL_FAILED, *o.failing)
            return False
        k = min(1.0, c.retreat_m / math.hypot(back[0] - pose[0], back[1] - pose[1]))
        self.goto.start([(pose[0] + k * (back[0] - pose[0]), pose[1] + k * (back[1] - pose[1]))], None)
        return True

    def _stalled(self, now: float, pose: Pose, o: _Order, index: int) -> bool:
        """No waypoint passed and no closer to the current one by ``progress_m`` for ``no_progress_s``."""
        wx, wy = self.goto.waypoints[index]
        d = math.hypot(wx - pose[0], wy - pose[1])
        i, best, since = o.progress
        if index != i or d < best - self.config.progress_m:
            o.progress = (index, d, now)
            return False
        return now - since >= self.config.no_progress_s

    def _start_order(self, now: float, o: _Order, keep_paused: bool) -> None:
        self._order = o
        self._teleop = None
        self._blocked_since = None
        self._refusal = None
        self.goto.cancel()
        self._mode = OperatingMode.PAUSED if keep_paused else OperatingMode.AUTOMATIC

    def _end_order(self, now: float, kind: EventKind, reason: str, text: str) -> None:
        o = self._order
        if o is None:
            return
        self._emit(now, kind, f"{o.label}: {text}", reason, o.order_id)
        self._order = None
        self._blocked_since = None
        self.goto.cancel()
        if self._mode in (OperatingMode.AUTOMATIC, OperatingMode.PAUSED):
            self._mode = OperatingMode.IDLE

    def _fail_if_moving(self, now: float, reason: str, text: str) -> None:
        if self._mode is OperatingMode.AUTOMATIC:
            self._end_order(now, EventKind.GOAL_FAILED, reason, text)

    def _emit(
        self,
        now: float,
        kind: EventKind,
        text: str,
        reason: str = "",
        order_id: str | None = None,
        waypoints: int | None = None,
    ) -> None:
        self._events.append(PilotEvent(kind, text, reason, order_id, now, waypoints))

    def _output(self, v: float, omega: float, refusing: bool) -> PilotOutput:
        events, self._events = self._events, []
        payload, self._payload = self._payload, []
        return PilotOutput(
            v,
            omega,
            self._mode,
            events,
            payload,
            estop=self._mode is OperatingMode.ESTOP,
            field_violation=refusing,
            goal=self.goal,
            order_id=self.order_id,
        )
