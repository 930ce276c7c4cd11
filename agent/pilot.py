"""The pilot: arbitrates every motion command and puts the collision guard in front of the motors (pure).

The runtime calls the command methods when a command arrives (``teleop``, ``order``, ``action``)
and ``tick`` every control period *and* right after every command, so commands take effect on
arrival. ``tick`` is idempotent in time: calling it again at the same ``now`` changes nothing but
delivers the events queued by the commands in between.

The modes are one state machine, declared in ``agent/pilot_machine.py`` (``PilotState`` x
``Trigger`` -> a transition and its effects, or a refusal with a reason): IDLE, MANUAL (teleop;
stops when no fresh command arrives within its time-to-live), GOTO / HOMING (a go-to to an order's
goal or home), GOTO_PAUSED / HOMING_PAUSED (held), ESTOP (latched until released). They are
reported as ``OperatingMode``. Orders are idempotent on (order_id, order_update_id): the same pair
again is a duplicate, a higher update replaces the goal, a lower one is rejected. Order of
precedence: e-stop > guard > the latest command (teleop overrides a go-to, a new order overrides
teleop).

A go-to is a ``Route`` (``agent/route.py``): with a path provider (the A* planner over the map) it
follows the planned waypoints and re-plans from where it stands when the guard bars the way (or it
makes no progress); after ``max_replans`` it fails (blocked).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol

from fleetlink.agent.guard import CollisionGuard, GuardConfig, GuardInputs, RefusalReason
from fleetlink.agent.motion import GoToConfig, GoToController, MotionLimits, RateLimiter
from fleetlink.agent.pilot_machine import (
    Announce,
    Cancel,
    CommandResult,
    CommandStatus,
    Do,
    Effect,
    EventKind,
    OperatingMode,
    PilotState,
    Refused,
    Transition,
    Trigger,
    next_state,
)
from fleetlink.agent.route import (
    MAX_DEVIATION_M,
    Destination,
    Drive,
    PathProvider,
    Point,
    Route,
    RouteConfig,
    RouteEnd,
    RoutePhase,
)
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.shared.messages import MAX_COORDINATE_M

__all__ = [
    "PAYLOAD_DEVICES",
    "ActionKind",
    "CommandResult",
    "CommandStatus",
    "EventKind",
    "MapSense",
    "OperatingMode",
    "PathProvider",
    "PayloadRequest",
    "Pilot",
    "PilotConfig",
    "PilotEvent",
    "PilotOutput",
    "PilotState",
]

Pose = tuple[float, float, float]

ECHO_TOLERANCE_M = 0.1
"""A front reading within this of what the map says the ultrasonic should see there is that wall."""


class MapSense(Protocol):
    """What the robot's map tells the pilot beyond paths (``PathPlanner`` has them all)."""

    def room_behind(self, pose: Pose, limit: float, /) -> float:
        """How far (m, at most ``limit``) the robot may back straight before its body meets what the map holds."""
        ...

    def echo_ahead(self, pose: Pose, reach: float, /) -> float:
        """The nearest echo (m, at most ``reach``) the front ultrasonic should read at ``pose`` by the map."""
        ...

    def leg_clear(self, a: Point, b: Point, /) -> bool:
        """The robot's body clears every wall the map holds all along the straight line a-b."""
        ...


PAYLOAD_DEVICES = ("uv", "atomiser", "fan", "all")
"""What a payload request switches: the UV-C lamp, the atomiser, the HEPA fan, or every one (off)."""


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


_ACTION_TRIGGER: dict[ActionKind, Trigger] = {kind: Trigger(kind.value) for kind in ActionKind}

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
    device: str = "uv"
    """``PAYLOAD_DEVICES``: uv (the lamp), atomiser, fan; "all" (every payload; off only)."""


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
    extent_m: float = MAX_COORDINATE_M  # goals (and home) farther from the origin are refused
    teleop_ttl_s: float = 0.5  # default time-to-live of a teleop command
    teleop_max_ttl_s: float = 2.0  # longer ones are clamped: a lost link must stop the robot soon
    blocked_timeout_s: float = 10.0  # a go-to held by an obstacle this long fails
    remembered_orders: int = 256  # order ids kept for idempotency
    # Planned paths (only with a path provider that returned a path):
    max_replans: int = 3  # a go-to barred once more after this many re-plans fails (reason "blocked")
    max_map_replans: int = 10  # re-plans because a newer map showed the leg ahead barred (not counted above)
    no_path_wait_s: float = 6.0  # no path to a goal: stand this long for a newer map with one, then fail (no_path)
    approach_m: float = (
        2.0  # no path to a goal farther off, barred by something robot-sized: go within this first, to look (0: not)
    )
    replan_hold_s: float = 2.0  # held by an obstacle ahead this long: back off and re-plan around it
    no_progress_s: float = 8.0  # no waypoint passed and no closer by ``progress_m`` this long: re-plan
    progress_m: float = 0.05
    sensor_offset_m: float = BODY_RADIUS_M  # the front ultrasonic, on the rim, is this far ahead of the centre
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

    @property
    def route(self) -> RouteConfig:
        return RouteConfig(
            blocked_timeout_s=self.blocked_timeout_s,
            max_replans=self.max_replans,
            max_map_replans=self.max_map_replans,
            no_path_wait_s=self.no_path_wait_s,
            approach_m=self.approach_m,
            replan_hold_s=self.replan_hold_s,
            no_progress_s=self.no_progress_s,
            progress_m=self.progress_m,
            sensor_offset_m=self.sensor_offset_m,
            backoff_m=self.backoff_m,
            backoff_speed=self.backoff_speed,
            mark_depth_m=self.mark_depth_m,
            retreat_m=self.retreat_m,
            creep_margin_m=self.creep_margin_m,
            creep_min_m=self.creep_min_m,
            stop_distance_m=self.guard.stop_distance_m,
        )


@dataclass(frozen=True, slots=True)
class _Teleop:
    v: float
    omega: float
    t: float
    ttl: float
    sender: str

    def lapsed(self, now: float) -> bool:
        return now >= self.t + self.ttl


@dataclass(frozen=True, slots=True)
class _Command:
    """What a trigger's effects need: who sent it and what it carries."""

    sender: str = ""
    teleop: _Teleop | None = None
    dest: Destination | None = None
    payload: PayloadRequest | None = None
    ending: tuple[EventKind, str, str] | None = None  # ROUTE_ENDED / HAZARD: (kind, reason, text)


@dataclass(slots=True)
class _Edges:
    """Rising edges of the safety inputs: each is reported once, not every tick."""

    cliff: bool = False
    bump: bool = False
    pose_fault: bool = False


def _finite(*vals: float) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in vals)


class Pilot:
    def __init__(
        self,
        config: PilotConfig | None = None,
        home: Pose = (0.0, 0.0, 0.0),
        path_provider: PathProvider | None = None,
        map_sense: MapSense | None = None,
    ) -> None:
        self.config = config or PilotConfig()
        c = self.config
        self.guard = CollisionGuard(c.guard)
        self.goto = GoToController(c.limits, c.goto)  # lent to each route in turn
        self.limiter = RateLimiter(c.limits)
        self.path_provider = path_provider
        # What the map says of the robot's surroundings (None: backs off blind, never creeps).
        self.map_sense = map_sense
        self._home: Pose = home
        self._state = PilotState.IDLE
        self._teleop: _Teleop | None = None  # set exactly in MANUAL
        self._route: Route | None = None  # set exactly in the go-to states (driving or paused)
        self._seen: OrderedDict[str, int] = OrderedDict()
        self._events: list[PilotEvent] = []
        self._payload: list[PayloadRequest] = []
        self._refusal: RefusalReason | None = None  # the guard refusal episode under way
        self._edges = _Edges()

    # -- what the runtime reads ------------------------------------------------------------------

    @property
    def state(self) -> PilotState:
        return self._state

    @property
    def mode(self) -> OperatingMode:
        return self._state.mode

    @property
    def estop(self) -> bool:
        return self._state is PilotState.ESTOP

    @property
    def home(self) -> Pose:
        return self._home

    def set_home(self, pose: Pose) -> None:
        """Where return home goes; a NaN heading: arrive with any heading."""
        if not _finite(pose[0], pose[1]) or math.isinf(pose[2]):
            raise ValueError(f"home pose must be finite, got {pose}")
        self._home = pose

    @property
    def goal(self) -> Pose | None:
        if self._route is None:
            return None
        d = self._route.dest
        return (d.x, d.y, math.nan if d.theta is None else d.theta)

    @property
    def order_id(self) -> str | None:
        return self._route.dest.order_id if self._route else None

    @property
    def order_update_id(self) -> int:
        """The active order's orderUpdateId (0 without one): what ``state.orderUpdateId`` carries."""
        return self._route.dest.update_id if self._route else 0

    def next_deadline(self) -> float | None:
        """When the teleop command lapses: tick at this time to stop exactly on time."""
        t = self._teleop
        return t.t + t.ttl if t is not None else None

    # -- commands (called on arrival) ------------------------------------------------------------

    def teleop(self, now: float, v: float, omega: float, ttl_s: float | None, sender: str) -> CommandResult:
        c = self.config
        if not _finite(v, omega):
            return _rejected(f"teleop velocity must be finite, got v={v} omega={omega}")
        ttl = c.teleop_ttl_s if ttl_s is None else ttl_s
        if not _finite(ttl) or ttl <= 0:
            return _rejected(f"teleop ttl must be > 0 s, got {ttl_s}")
        cur = self._teleop
        if (
            cur is not None
            and cur.sender != sender
            and not cur.lapsed(now)
            and (cur.v != 0.0 or cur.omega != 0.0)
            and (v != 0.0 or omega != 0.0)  # anyone may stop the robot
        ):
            return _rejected(f"robot is being driven by {cur.sender}")
        lim = c.limits
        cmd = _Teleop(
            max(-lim.v_max, min(lim.v_max, v)),
            max(-lim.omega_max, min(lim.omega_max, omega)),
            now,
            min(ttl, c.teleop_max_ttl_s),
            sender,
        )
        return self._fire(now, Trigger.TELEOP, _Command(sender, teleop=cmd))

    def order(
        self,
        now: float,
        order_id: str,
        order_update_id: int,
        x: float,
        y: float,
        theta: float | None,
        sender: str,
        *,
        admitted: bool = False,
        max_v: float | None = None,
        deviation: float = 0.0,
        trajectory: Sequence[Point] = (),
    ) -> CommandResult:
        """Go to (x, y[, theta]). ``admitted``: a node of an order ``admit`` has let in already (the
        agent's itinerary drives an order's nodes one by one under its id). ``max_v``: a speed cap
        for this go-to (m/s; an order edge's maxSpeed). ``deviation``: the nearest place within this
        (m) will do when (x, y) cannot be reached (a node's allowedDeviationXY). ``trajectory``: the
        way to drive there (an order edge's, as waypoints), followed where the map allows."""
        if not admitted:
            refused = self.admit(order_id, order_update_id)
            if refused is not None:
                return refused
        if not _finite(x, y) or (theta is not None and not _finite(theta)):
            return _rejected(f"goal must be finite, got x={x} y={y} theta={theta}")
        if max_v is not None and not (_finite(max_v) and max_v > 0.0):
            return _rejected(f"speed cap must be a positive number, got {max_v!r}")
        if not (_finite(deviation) and 0.0 <= deviation <= MAX_DEVIATION_M):
            return _rejected(f"allowed deviation must be 0-{MAX_DEVIATION_M:g} m, got {deviation!r}")
        if not all(_finite(px, py) for px, py in trajectory):
            return _rejected("the trajectory's waypoints must be finite")
        extent = self.config.extent_m
        if abs(x) > extent or abs(y) > extent:
            return _rejected(f"goal ({x:.4g}, {y:.4g}) is outside the site's extent (|x|, |y| <= {extent:g} m)")
        held = self._route is not None and self._route.dest.order_id == order_id
        trigger = Trigger.ORDER_UPDATE if held else Trigger.ORDER_NEW
        dest = Destination(
            order_id,
            order_update_id,
            x,
            y,
            theta,
            sender,
            max_v=max_v,
            deviation=deviation,
            trajectory=tuple((float(px), float(py)) for px, py in trajectory),
        )
        result = self._fire(now, trigger, _Command(sender, dest=dest))
        if result.accepted:
            self.remember(order_id, order_update_id)
        return result

    def remember(self, order_id: str, order_update_id: int) -> None:
        """(order_id, order_update_id) was accepted: the same again is a duplicate, an older one refused."""
        self._seen[order_id] = order_update_id
        self._seen.move_to_end(order_id)
        while len(self._seen) > self.config.remembered_orders:
            self._seen.popitem(last=False)

    def admit(self, order_id: str, order_update_id: int) -> CommandResult | None:
        """None if (order_id, order_update_id) is a new order or a newer update of one; else the
        answer: rejected (no id, a bad or older update) or a duplicate (already received)."""
        if not order_id:
            return _rejected("order id must not be empty")
        if isinstance(order_update_id, bool) or not isinstance(order_update_id, int) or order_update_id < 0:
            return _rejected(f"order update id must be an integer >= 0, got {order_update_id!r}")
        seen = self._seen.get(order_id)
        if seen is not None and order_update_id == seen:
            return CommandResult(CommandStatus.DUPLICATE, f"order {order_id}/{order_update_id} already received")
        if seen is not None and order_update_id < seen:
            return _rejected(f"order {order_id}: update {order_update_id} is older than {seen}")
        return None

    def action(self, now: float, kind: ActionKind | str, sender: str, **params: object) -> CommandResult:
        try:
            kind = ActionKind(kind)
        except ValueError:
            return _rejected(f"unknown action {kind!r}")
        outcome = next_state(self._state, _ACTION_TRIGGER[kind])
        if isinstance(outcome, Refused):
            return outcome.result
        cmd = _Command(sender)
        if kind in (ActionKind.PAYLOAD_ON, ActionKind.PAYLOAD_OFF):
            device = params.get("device", "uv" if kind is ActionKind.PAYLOAD_ON else "all")
            if device not in PAYLOAD_DEVICES or (device == "all" and kind is ActionKind.PAYLOAD_ON):
                return _rejected(f"unknown payload device {device!r} (one of: uv, atomiser, fan)")
            level = params.get("level")
            if level is not None and (isinstance(level, bool) or not isinstance(level, int) or not 0 <= level <= 3):
                return _rejected(f"payload level must be an integer 0-3, got {level!r}")
            on = kind is ActionKind.PAYLOAD_ON
            cmd = _Command(sender, payload=PayloadRequest(on, level if on else None, sender, str(device)))
        elif kind is ActionKind.RETURN_HOME:
            hx, hy, hth = self._home
            cmd = _Command(sender, dest=Destination(None, 0, hx, hy, None if math.isnan(hth) else hth, sender))
        self._enter(now, outcome, cmd)
        return _OK

    def halt(self, now: float, sender: str) -> CommandResult:
        """Stop as ``stop`` does, leaving the payload as it is (the comms-loss policy's own stops)."""
        return self._fire(now, Trigger.HALT, _Command(sender))

    @property
    def waiting_for_way(self) -> bool:
        """The go-to held stands waiting for the way to clear (``RoutePhase.WAITING``): the map is
        to look more often (``Turn.waiting``), so that it shows the way clear once it is."""
        return self._route is not None and self._route.phase is RoutePhase.WAITING

    @property
    def retracing(self) -> bool:
        """The go-to held is a retrace (the comms-loss policy's way back), not an order or home."""
        return self._route is not None and bool(self._route.dest.via)

    def retrace(self, now: float, path: Sequence[Point], sender: str) -> CommandResult:
        """Drive back along ``path`` (the robot's own, newest first, ending where it last heard an
        operator): the comms-loss policy's retrace. A go-to of its own kind (reported as homing)."""
        if not path or not all(_finite(x, y) for x, y in path):
            return _rejected("retrace needs a finite path")
        outcome = next_state(self._state, Trigger.RETRACE)
        if isinstance(outcome, Refused):
            return outcome.result
        gx, gy = path[-1]
        dest = Destination(None, 0, gx, gy, None, sender, via=tuple((float(x), float(y)) for x, y in path))
        self._enter(now, outcome, _Command(sender, dest=dest))
        return _OK

    # -- the control tick ------------------------------------------------------------------------

    def tick(self, now: float, pose: Pose, inputs: GuardInputs) -> PilotOutput:
        pose_ok = self._read_inputs(now, pose, inputs)
        t = self._teleop
        if t is not None and t.lapsed(now):
            self._fire(now, Trigger.TELEOP_LAPSED, _Command(t.sender, teleop=t))
        drive = self._behave(now, pose, inputs, pose_ok)
        return self._guarded(now, pose, inputs, drive)

    # -- the machine -----------------------------------------------------------------------------

    def _fire(self, now: float, trigger: Trigger, cmd: _Command) -> CommandResult:
        outcome = next_state(self._state, trigger)
        if isinstance(outcome, Refused):
            return outcome.result
        self._enter(now, outcome, cmd)
        return _OK

    def _enter(self, now: float, transition: Transition, cmd: _Command) -> None:
        for effect in transition.effects:
            self._apply(now, effect, cmd)
        self._state = transition.target
        # What each state carries (a teleop command in MANUAL, a route in the go-to states) and nothing else.
        assert (self._teleop is not None) == (self._state is PilotState.MANUAL), (self._state, self._teleop)
        assert (self._route is not None) == self._state.has_route, (self._state, self._route)

    def _apply(self, now: float, effect: Effect, cmd: _Command) -> None:
        if isinstance(effect, Cancel):
            order_id = cmd.dest.order_id if cmd.dest is not None else None
            self._drop_route(
                now, EventKind.GOAL_CANCELLED, effect.reason, effect.text.format(sender=cmd.sender, order_id=order_id)
            )
        elif isinstance(effect, Announce):
            ttl = cmd.teleop.ttl if cmd.teleop is not None else 0.0
            self._emit(now, effect.kind, effect.text.format(sender=cmd.sender, ttl=ttl), effect.reason)
        elif effect is Do.TAKE_TELEOP:
            assert cmd.teleop is not None
            self._teleop = cmd.teleop
        elif effect is Do.DROP_TELEOP:
            self._teleop = None
        elif effect is Do.START_ROUTE:
            assert cmd.dest is not None
            self._route = Route(cmd.dest, self.goto, self.config.route)
            self._teleop = None
            self._refusal = None
            self.goto.cancel()
        elif effect is Do.RESUME_ROUTE:
            assert self._route is not None
            self._route.resume(now)
        elif effect is Do.END_ROUTE:
            assert cmd.ending is not None
            self._drop_route(now, *cmd.ending)
        elif effect is Do.PASS_PAYLOAD:
            assert cmd.payload is not None
            self._payload.append(cmd.payload)
        elif effect is Do.CUT_PAYLOAD:
            t = cmd.teleop
            if t is None or t.v != 0.0 or t.omega != 0.0:  # a zero twist lapsing is not a lost link
                self._payload.append(PayloadRequest(False, None, cmd.sender, "all"))

    def _drop_route(self, now: float, kind: EventKind, reason: str, text: str) -> None:
        r = self._route
        assert r is not None
        self._emit(now, kind, f"{r.dest.label}: {text}", reason, r.dest.order_id)
        self._route = None
        self.goto.cancel()

    # -- the tick's parts ------------------------------------------------------------------------

    def _read_inputs(self, now: float, pose: Pose, inputs: GuardInputs) -> bool:
        """Safety edges first: cliff and bump are events, and they end a go-to. True: the pose is usable."""
        e = self._edges
        if inputs.cliff and not e.cliff:
            self._emit(now, EventKind.CLIFF, "cliff detected: stopped", "cliff")
            self._fire(now, Trigger.HAZARD, _Command(ending=(EventKind.GOAL_FAILED, "cliff", "cliff detected")))
        if inputs.bumped and not e.bump:
            self._emit(now, EventKind.BUMP, "bumper pressed: stopped", "bump")
            self._fire(now, Trigger.HAZARD, _Command(ending=(EventKind.GOAL_FAILED, "bump", "bumper pressed")))
        pose_ok = _finite(*pose)
        if not pose_ok and not e.pose_fault:
            self._emit(now, EventKind.FAULT, f"pose is not finite ({pose}): holding still", "pose_invalid")
        e.cliff, e.bump, e.pose_fault = inputs.cliff, inputs.bumped, not pose_ok
        return pose_ok

    def _behave(self, now: float, pose: Pose, inputs: GuardInputs, pose_ok: bool) -> Drive:
        """What the state wants: teleop's velocity, the route's step, or stillness."""
        if self._teleop is not None:
            return Drive(self._teleop.v, self._teleop.omega)
        r = self._route
        if r is None or not self._state.driving_route or not pose_ok:
            return Drive()
        drive = r.step(now, pose, self.path_provider, self.map_sense)
        self._settle_route(now, r)
        cap = r.dest.max_v
        if cap is not None and abs(drive.v) > cap:
            drive = Drive(math.copysign(cap, drive.v), drive.omega, drive.distance_m)
        if drive.distance_m is not None and drive.v > 0.0:
            drive = Drive(drive.v, drive.omega, r.cut_short(pose, self.guard.obstacle_m(inputs), drive.distance_m))
        return drive

    def _guarded(self, now: float, pose: Pose, inputs: GuardInputs, drive: Drive) -> PilotOutput:
        """The guard in front of the motors; a refusal is one event per episode and the route's to handle."""
        r = self._route if self._state.driving_route else None
        if drive.v == 0.0 and drive.omega == 0.0:
            self.limiter.reset(now)
            if r is None or r.held_since is None:
                self._refusal = None  # (a held go-to re-aiming between refusals is the same episode)
            return self._output(0.0, 0.0, refusing=False)
        # The drive-start check sees the wanted speed (the limiter may still be at zero).
        on_path = r is not None and self._may_creep(pose, inputs, r)
        decision = self.guard.filter(
            drive.v, drive.omega, inputs, goto_drive_distance_m=drive.distance_m, on_path=on_path
        )
        if decision.refusal is None:
            lv, lw = self.limiter.step(now, drive.v, drive.omega)
            decision = self.guard.filter(lv, lw, inputs, on_path=on_path)
        refusal = decision.refusal
        if refusal is None:
            # On a route, only a drive forward ends the episode: the leg starts afresh after each
            # refusal (turn, then the drive-start check), and a turn the guard lets through moves
            # nothing out of the way. Ended by it, a door frame 0.37 m ahead was an event every
            # 0.12 s and never held for replan_hold_s, till no_progress re-planned 8 s on.
            if r is None or decision.v > 0.0:
                self._refusal = None
                if r is not None:
                    r.held_since = None
            return self._output(decision.v, decision.omega, refusing=False)
        if refusal.reason is not self._refusal:
            self._emit(now, EventKind.GUARD_REFUSAL, refusal.text, refusal.reason.value)
        self._refusal = refusal.reason
        self.limiter.reset(now)
        if r is not None:
            room = self.map_sense.room_behind if self.map_sense is not None else None
            r.refused(now, pose, refusal, self.path_provider, room)
            self._settle_route(now, r)
        return self._output(0.0, 0.0, refusing=True)

    def _may_creep(self, pose: Pose, inputs: GuardInputs, r: Route) -> bool:
        """The guard may creep on (``GuardConfig.creep_speed_mps``) only where the map vouches for
        the way: the leg to the current waypoint clears every wall it holds (a leg planned into
        the unknown, through a wall seen since, does not), and the front reading is a wall it holds
        (something it lacks, a box or a person, gets the seed's rules)."""
        sense = self.map_sense
        if r.phase not in (RoutePhase.FOLLOWING, RoutePhase.APPROACHING) or sense is None:
            return False
        d = self.guard.obstacle_m(inputs)
        if d is None:
            return True
        reach = d + ECHO_TOLERANCE_M
        if not sense.echo_ahead(pose, reach) < reach:
            return False
        goto = r.goto
        if not 0 <= goto.index < len(goto.waypoints):
            return False
        return sense.leg_clear((pose[0], pose[1]), goto.waypoints[goto.index])

    def _settle_route(self, now: float, r: Route) -> None:
        """Report what the route noted, and end it if it ended. A new path (or a wait for one)
        starts a new refusal episode: a refusal on it is news."""
        if r.notes:
            self._refusal = None
        for note in r.notes:
            if note.replanned:
                kind = EventKind.REPLANNED
            else:
                kind = EventKind.WAITING if note.reason == "waiting" else EventKind.PATH_PLANNED
            self._emit(now, kind, note.text, note.reason, r.dest.order_id, note.waypoints)
        r.notes.clear()
        if r.end is not None:
            self._fire(now, Trigger.ROUTE_ENDED, _Command(ending=_ending(r.end)))

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
            self.mode,
            events,
            payload,
            estop=self.estop,
            field_violation=refusing,
            goal=self.goal,
            order_id=self.order_id,
        )


def _ending(end: RouteEnd) -> tuple[EventKind, str, str]:
    return (EventKind.GOAL_REACHED if end.reached else EventKind.GOAL_FAILED, end.reason, end.text)
