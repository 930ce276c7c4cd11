"""The agent core: messages in, motor commands and telemetry out. Pure: no I/O, time passed in.

The runtime (agent/runtime.py) owns the threads, the board session and the links; it hands every
inbound payload to ``on_input`` and calls ``tick`` at the control rate with a ``BoardView`` of the
board snapshot. Both return an ``Output``: the velocity to push to the board now (commands are
applied on arrival, not at the next tick), the messages to publish (``link`` None = both links,
else only the link a command came from, for acks), payload requests for the board and lines to
log. The pipeline per tick: odometry -> fusion -> pilot.tick (the guard sits inside) -> velocity.

Localisation is wired as docs/localisation.md says: every new motor reading (``BoardView.odom_t``
changes) goes through ``Odometry.update`` (wheels + gyro yaw) into ``Fusion.predict``; a new board
session (``BoardView.connects`` changes) resets the odometry's counter baseline; UWB fixes (native
``UwbFix`` or PANS JSON) are parsed with the clock's wall-minus-monotonic offset and go to
``Fusion.add_fix``. The pilot steers on ``Fusion.map_pose()``; ``pose`` carries both frames.

Telemetry goes out on both links, except that while Zenoh is up only every
``fallback_pose_every``-th pose (default 2: 10 of 20 Hz) also goes on MQTT, same bytes and
headerId: enough for the console's link manager to judge MQTT alive (it wants a message every
0.35 s), half the fallback's load. With Zenoh down every pose goes on MQTT.

Access (issue 8): ``operators`` (robot.toml) lists the operator ids (header sender) whose commands
are accepted; empty = anyone. The control lease (agent/lease.py): driving takes it (a motion
command claims a free lease for its sender and renews it for the holder); while one operator
holds it, motion commands from anyone else are refused with the holder named in the Ack; stop,
cancel, pause, e-stop and a zero teleop are always accepted from allowed operators. ``Lease`` is published on change and
at the state rate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from fleetlink.agent.fusion import Fusion
from fleetlink.agent.guard import GuardInputs
from fleetlink.agent.lease import DRIVE_LEASE_S, LeaseKeeper
from fleetlink.agent.links.gate import Accepted, CommandGate, Duplicate, Rejected, always_allowed
from fleetlink.agent.odometry import Odometry, OdomPose
from fleetlink.agent.pilot import ActionKind, CommandResult, CommandStatus, PathProvider, Pilot, PilotEvent, PilotOutput
from fleetlink.agent.pilot import OperatingMode as PilotMode
from fleetlink.agent.uwb_input import FixObservation, fix_from_pans, fix_from_uwb
from fleetlink.devices.controlbus.snapshot import BoardSnapshot
from fleetlink.shared import wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import (
    MAX_DIAGNOSTIC_COUNTS,
    AckResult,
    ActionType,
    AgvPosition,
    BatteryState,
    Count,
    Diagnostics,
    ErrorLevel,
    EStop,
    Event,
    Goal,
    InstantActions,
    KeyValue,
    Lease,
    LeaseRequest,
    LinkName,
    LinkStatus,
    OperatingMode,
    Order,
    Pose,
    SafetyState,
    Severity,
    State,
    StateError,
    Teleop,
    UwbFix,
    Velocity,
)

__all__ = ["AgentCore", "BoardView", "Output", "board_view"]

COMMAND_TOPICS = (Order.TOPIC, InstantActions.TOPIC, Teleop.TOPIC)
INPUT_TOPICS = (*COMMAND_TOPICS, LeaseRequest.TOPIC, UwbFix.TOPIC)
UNKNOWN_SD = 1000.0
"""What ``pose.sd_*`` say before the fusion knows the position or heading (the wire has no inf)."""
DIAGNOSTICS_PERIOD_S = 5.0
"""At most one ``Diagnostics`` message this often, and only when a count moved."""
_MAX_FAILURE_KINDS = 64
"""Distinct (topic, exception type) pairs logged when a command handler fails; later ones are only counted."""

_ACTION_KIND = {
    ActionType.STOP: ActionKind.STOP,
    ActionType.PAUSE: ActionKind.PAUSE,
    ActionType.RESUME: ActionKind.RESUME,
    ActionType.CANCEL: ActionKind.CANCEL,
    ActionType.ESTOP: ActionKind.ESTOP,
    ActionType.ESTOP_RELEASE: ActionKind.ESTOP_RELEASE,
    ActionType.RETURN_HOME: ActionKind.RETURN_HOME,
}
_MODE = {
    PilotMode.IDLE: OperatingMode.SEMIAUTOMATIC,
    PilotMode.MANUAL: OperatingMode.MANUAL,
    PilotMode.AUTOMATIC: OperatingMode.AUTOMATIC,
    PilotMode.PAUSED: OperatingMode.AUTOMATIC,
    PilotMode.ESTOP: OperatingMode.SERVICE,
}
_SEVERITY = {"GUARD_REFUSAL": Severity.WARNING, "CLIFF": Severity.ERROR, "BUMP": Severity.ERROR}


@dataclass(frozen=True, slots=True)
class BoardView:
    """What the core needs from the board, in SI units."""

    connected: bool = False
    left_m: float | None = None
    right_m: float | None = None
    gyro_yaw: float | None = None
    ultrasonic_m: float | None = None
    cliff: bool = False
    bumped: bool = False
    battery_percent: float = 0.0
    charging: bool = False
    payload_on: bool = False
    errors: tuple[str, ...] = ()
    odom_t: float = 0.0
    """When the wheel/gyro readings were polled (clock time); odometry advances when it changes."""
    connects: int = 0
    """Board sessions so far: a change means a new session, so new counter baselines."""


def board_view(snap: BoardSnapshot, odom_t: float | None = None) -> BoardView:
    """``odom_t``: when ``snap.motor`` was polled (the runtime tracks it); default ``snap.updated``."""
    b = snap.bumpers
    front = snap.sensors.distances[0] if snap.sensors and snap.sensors.distances else None
    return BoardView(
        connected=snap.connected,
        left_m=snap.motor.left if snap.motor else None,
        right_m=snap.motor.right if snap.motor else None,
        gyro_yaw=snap.imu.yaw if snap.imu else None,
        ultrasonic_m=front if front is not None and front > 0 else None,
        cliff=b is not None and (b.triggered(2) or b.triggered(3)),
        bumped=b is not None and (b.triggered(0) or b.triggered(1)),
        battery_percent=float(snap.status.battery_percent) if snap.status else 0.0,
        charging=bool(snap.status.charging) if snap.status else False,
        payload_on=bool(snap.payload.uv_lamp) if snap.payload else False,
        errors=tuple(f"0x{e.code:04X} {e.message}" for e in snap.errors),
        odom_t=snap.updated if odom_t is None else odom_t,
        connects=snap.connects,
    )


@dataclass(slots=True)
class Output:
    velocity: tuple[float, float] | None = None
    messages: list[tuple[wire.Message, LinkName | None]] = field(default_factory=list)
    payload: list[bool] = field(default_factory=list)
    logs: list[str] = field(default_factory=list)


class AgentCore:
    def __init__(
        self,
        robot: str,
        clock: Clock,
        pilot: Pilot,
        *,
        odometry: Odometry | None = None,
        fusion: Fusion | None = None,
        map_id: str = "",
        pose_hz: float = 20.0,
        state_hz: float = 1.0,
        sender: str | None = None,
        operators: tuple[str, ...] = (),
        lease: LeaseKeeper | None = None,
        fallback_pose_every: int = 2,
    ) -> None:
        self.robot = robot
        self.clock = clock
        self.pilot = pilot
        self.odometry = odometry or Odometry()
        self.fusion = fusion or Fusion()
        self.map_id = map_id
        self.operators = frozenset(operators)
        self.lease = lease or LeaseKeeper()
        self.refused_operators = 0
        """Commands and lease requests refused because the sender is not in ``operators``."""
        self.refused_lease = 0
        self._board_sessions = 0
        self._next_diagnostics = -math.inf
        self._last_diagnostics: object = None
        self.handler_failures = 0
        """Commands whose handling raised (a value every check let through): refused, robot stopped."""
        self._failures_logged: set[tuple[str, str]] = set()
        """Motion commands refused because another operator holds the lease."""
        self.fixes_rejected = 0
        self._last_lease: tuple[str, float] | None = None
        self._odom_t = -math.inf
        self._connects = 0
        self.counter = wire.HeaderCounter(clock, robot=robot, sender=sender or f"agent-{robot}")
        self.gate = CommandGate(robot, topics=INPUT_TOPICS)
        self.pose_period = 1.0 / pose_hz
        if fallback_pose_every < 1:
            raise ValueError(f"fallback_pose_every must be >= 1, got {fallback_pose_every}")
        self.fallback_pose_every = fallback_pose_every
        self._poses = 0
        self.state_period = 1.0 / state_hz
        self.board = BoardView()
        self.links = LinkStatus(zenoh=False, mqtt=False)
        self.fixes_accepted = 0
        self._odom: OdomPose | None = None
        self._next_pose = -math.inf
        self._next_state = -math.inf
        self._last_state_key: tuple[Any, ...] | None = None
        self._last_out: PilotOutput | None = None
        self._velocity = (0.0, 0.0)

    # -- inputs ---------------------------------------------------------------------------------

    def on_input(self, link: LinkName, key: str, payload: bytes, now: float) -> Output:
        out = Output()
        self.gate.priority_sender = self.lease.view(now).holder
        verdict = self.gate.receive(link, key, payload, now)
        if isinstance(verdict, Rejected):
            self._rejected(verdict, out)
            return out
        if isinstance(verdict, Duplicate):
            out.messages.append((self._ack(verdict.ack), link))
            return out
        assert isinstance(verdict, Accepted)
        msg = verdict.msg
        if isinstance(msg, UwbFix):
            self._fix(link, msg.TOPIC, msg, out)
            return out
        sender = msg.header.sender
        if self.operators and sender not in self.operators:
            self.refused_operators += 1
            reason = f"operator {sender!r} is not allowed to command {self.robot}"
            self._rejected(self.gate.reject(link, msg.TOPIC, f"sender: {reason}", "sender"), out)
            if isinstance(msg, Order | InstantActions | Teleop | LeaseRequest):
                out.messages.append((self._ack(self._ack_fields(msg, link, AckResult.REJECTED, reason)), link))
            return out
        if isinstance(msg, LeaseRequest):
            self._lease_request(msg, link, now, out)
            return out
        assert isinstance(msg, Order | InstantActions | Teleop)
        refusal = self._lease_refusal(msg, now, out)
        if refusal:
            self.refused_lease += 1
            out.messages.append((self._ack(self.gate.ack(msg, link, AckResult.REJECTED, refusal)), link))
            return out
        try:
            result = self._run(msg, now, out)
        except Exception as exc:  # never a crash, never a false success: refuse it and stop
            result = self._failed(msg, now, exc, out)
        if isinstance(msg, Order) and result.status is CommandStatus.ACCEPTED:
            self.gate.executed_order(msg)
        ack = self.gate.ack(msg, link, AckResult(result.status.value), result.reason)
        out.messages.append((self._ack(ack), link))
        # Apply at once: the pilot decides with the latest sensors, the board gets it now.
        self._control(now, out)
        return out

    def on_pans(self, link: LinkName, topic: str, payload: bytes, now: float) -> Output:
        """A PANS JSON location (``dwm/node/<tag>/uplink/location``)."""
        out = Output()
        try:
            obs = fix_from_pans(topic, payload, self._wall_minus_monotonic(), received_at=now)
        except ValueError as exc:
            self._rejected(self.gate.reject(link, "pans", f"pans: {exc}"), out)
            return out
        self._add_fix(obs, out)
        return out

    def diagnostics(self, now: float, links: Mapping[str, tuple[int, int]]) -> Output:
        """Every ``DIAGNOSTICS_PERIOD_S``, if any count moved: a ``Diagnostics`` message with what the
        gate refused, the duplicates, the handler failures and, per link, (oversized, dropped)."""
        out = Output()
        stats = self.gate.stats
        counts = (
            tuple(sorted(stats.rejected.items())),
            stats.duplicates,
            self.handler_failures,
            tuple(sorted(links.items())),
        )
        if now < self._next_diagnostics or counts == self._last_diagnostics:
            return out
        self._next_diagnostics = now + DIAGNOSTICS_PERIOD_S
        self._last_diagnostics = counts
        rejected = [Count(key=f"{lk}/{topic}"[:64], count=n) for (lk, topic), n in sorted(stats.rejected.items())]
        msg = self.counter.make(
            Diagnostics,
            rejected=tuple(rejected[:MAX_DIAGNOSTIC_COUNTS]),
            duplicates=stats.duplicates,
            handler_failures=self.handler_failures,
            oversized=tuple(Count(key=lk[:64], count=o) for lk, (o, _) in sorted(links.items())),
            dropped=tuple(Count(key=lk[:64], count=d) for lk, (_, d) in sorted(links.items())),
            last_reason=stats.last_reason[:256],
        )
        out.messages.append((msg, None))
        return out

    def set_links(self, links: LinkStatus, now: float) -> Output:
        out = Output()
        if links != self.links:
            for name in ("zenoh", "mqtt"):
                was, up = getattr(self.links, name), getattr(links, name)
                if was != up:
                    text = f"{name} link {'up' if up else 'down'}"
                    out.messages.append((self._event("link_change", text, Severity.INFO, link=name), None))
                    out.logs.append(text)
            self.links = links
            self._next_state = now  # publish the change now
        return out

    def use_map(self, plan: PathProvider | None) -> None:
        """Route go-tos and return home over the onboard map: the runtime passes its mapper's
        ``OnboardMapper.plan`` (None while the map is still empty, so the pilot drives straight,
        exactly as without a map; [] when there is no path). None: no map, straight lines."""
        self.pilot.path_provider = plan

    def lidar_status(self, fault: str | None, url: str) -> Output:
        """The lidar stopped delivering scans (``fault``: why) or delivers again (None): an event
        now; the fault is in ``State.errors`` while it lasts (the runtime adds it to the board view)."""
        if fault is None:
            ev = self._event("lidar_ok", "lidar scanning again", Severity.INFO)
        else:
            text = f"lidar not delivering scans: {fault}; driving on the ultrasonic guard"[:256]
            ev = self._event("lidar_fault", text, Severity.ERROR, url=url[:256])
        return Output(messages=[(ev, None)])

    # -- the control loop -------------------------------------------------------------------------

    def tick(self, now: float, board: BoardView) -> Output:
        out = Output()
        if board.connects != self._connects:
            self._connects = board.connects
            self.odometry.reset_counters()  # a new board session: its counters are a new baseline
        if board.connected and board.left_m is not None and board.right_m is not None and board.odom_t > self._odom_t:
            self._odom_t = board.odom_t
            self._odom = self.odometry.update(board.odom_t, board.left_m, board.right_m, board.gyro_yaw)
            self.fusion.predict(self._odom)
        if board.connected != self.board.connected:
            self._next_state = now
            self._board_change(board, out)
        self.board = board
        self._control(now, out)
        if now >= self._next_pose:
            self._next_pose = max(self._next_pose + self.pose_period, now)
            out.messages.append((self._pose(now), self._pose_link()))
        key = self._change_key(now)
        if now >= self._next_state or key != self._last_state_key:
            self._next_state = max(self._next_state + self.state_period, now + self.state_period * 0.5)
            self._last_state_key = key
            out.messages.append((self._state(now), None))
            self._publish_lease(now, out, force=True)
        else:
            self._publish_lease(now, out)
        return out

    @property
    def velocity(self) -> tuple[float, float]:
        """The last (v, omega) sent towards the board, m/s and rad/s."""
        return self._velocity

    @property
    def driving(self) -> bool:
        """The robot is moving, or has a command that will move it (a go-to, teleop): the runtime
        then ticks at the control rate. Otherwise nothing changes between two sensor readings, and
        it ticks only when a pose is due (``next_pose_at``) or an input arrives."""
        return self._velocity != (0.0, 0.0) or self.pilot.mode in (PilotMode.MANUAL, PilotMode.AUTOMATIC)

    @property
    def next_pose_at(self) -> float:
        """When the next pose is due (clock time)."""
        return self._next_pose

    # -- internals --------------------------------------------------------------------------------

    def _pose_link(self) -> LinkName | None:
        """Every pose on Zenoh; on MQTT every ``fallback_pose_every``-th while Zenoh is up, all when down."""
        self._poses += 1
        if self.links.zenoh and self.links.mqtt and self._poses % self.fallback_pose_every:
            return LinkName.ZENOH
        return None

    def _map_pose(self) -> tuple[float, float, float]:
        p = self.fusion.map_pose()
        return p.x, p.y, p.theta

    def _uwb_stale(self, now: float) -> bool:
        return self.fusion.uwb_stale(now)

    def _wall_minus_monotonic(self) -> float:
        return self.clock.wall() - self.clock.now()

    # -- access: operators and the lease ---------------------------------------------------------

    def _lease_refusal(self, msg: Order | InstantActions | Teleop, now: float, out: Output) -> str:
        """Why ``msg`` may not run under the lease ('' = it may). Driving takes the lease when it is
        free and renews it for its holder (agent/lease.py), so nobody drives without holding it."""
        if always_allowed(msg):
            return ""  # stopping the robot is everyone's right
        if isinstance(msg, Teleop) and msg.v == 0.0 and msg.omega == 0.0:
            return ""  # so is a zero twist
        if not self.lease.claim(msg.header.sender, DRIVE_LEASE_S, now, self.clock.wall()):
            return self.lease.refusal(msg.header.sender, now)
        self._publish_lease(now, out)  # on change only: a new holder is announced at once
        return ""

    def _lease_request(self, msg: LeaseRequest, link: LinkName, now: float, out: Output) -> None:
        ok, reason = self.lease.request(msg.header.sender, msg.duration_s, msg.release, now, self.clock.wall())
        result = AckResult.ACCEPTED if ok else AckResult.REJECTED
        out.messages.append((self._ack(self._ack_fields(msg, link, result, reason)), link))
        self._publish_lease(now, out, force=True)

    def _publish_lease(self, now: float, out: Output, *, force: bool = False) -> None:
        v = self.lease.view(now)
        key = (v.holder, v.until_wall)
        if force or key != self._last_lease:
            self._last_lease = key
            out.messages.append((self.counter.make(Lease, holder=v.holder, until=v.until_wall), None))

    def _ack_fields(self, msg: wire.Message, link: LinkName, result: AckResult, reason: str) -> dict[str, Any]:
        if isinstance(msg, Order | InstantActions | Teleop):
            return self.gate.ack(msg, link, result, reason)
        return {
            "commandTopic": msg.TOPIC,
            "commandSender": msg.header.sender,
            "commandHeaderId": msg.header.headerId,
            "orderId": None,
            "orderUpdateId": None,
            "result": result,
            "reason": reason[:256],
            "link": link,
        }

    def _control(self, now: float, out: Output) -> None:
        inputs = GuardInputs(ultrasonic_m=self.board.ultrasonic_m, cliff=self.board.cliff, bumped=self.board.bumped)
        p = self.pilot.tick(now, self._map_pose(), inputs)
        self._last_out = p
        self._velocity = (p.v, p.omega)
        out.velocity = (p.v, p.omega)
        for ev in p.events:
            out.messages.append((self._pilot_event(ev), None))
        for req in p.payload_requests:
            out.payload.append(req.on)

    def _run(self, msg: Order | InstantActions | Teleop, now: float, out: Output) -> CommandResult:
        sender = msg.header.sender
        if isinstance(msg, Teleop):
            return self.pilot.teleop(now, msg.v, msg.omega, msg.ttl_s, sender)
        if isinstance(msg, Order):
            if msg.returnHome:
                return self.pilot.action(now, ActionKind.RETURN_HOME, sender)
            if msg.goal is None:
                return CommandResult(CommandStatus.REJECTED, "order has neither a goal nor returnHome")
            g = msg.goal
            return self.pilot.order(now, msg.orderId, msg.orderUpdateId, g.x, g.y, g.theta, sender)
        results: list[str] = []
        status = CommandStatus.ACCEPTED
        for a in msg.actions:
            if a.actionType is ActionType.PAYLOAD:
                params = {kv.key: kv.value for kv in a.actionParameters}
                on = params.get("on", "").lower()
                if on not in ("true", "false"):
                    r = CommandResult(CommandStatus.REJECTED, "payload needs parameter on=true|false")
                else:
                    kind = ActionKind.PAYLOAD_ON if on == "true" else ActionKind.PAYLOAD_OFF
                    r = self.pilot.action(now, kind, sender)
            else:
                r = self.pilot.action(now, _ACTION_KIND[a.actionType], sender)
            if r.status is CommandStatus.REJECTED:
                status = CommandStatus.REJECTED
            if r.reason:
                results.append(f"{a.actionId}: {r.reason}")
        return CommandResult(status, "; ".join(results))

    def _failed(self, msg: Order | InstantActions | Teleop, now: float, exc: Exception, out: Output) -> CommandResult:
        """A command whose handling raised: whatever it started is stopped, and it is refused."""
        self.handler_failures += 1
        what = f"{type(exc).__name__}: {exc}"[:120]
        key = (msg.TOPIC, type(exc).__name__)
        if key not in self._failures_logged and len(self._failures_logged) < _MAX_FAILURE_KINDS:
            self._failures_logged.add(key)
            out.logs.append(f"{msg.TOPIC} from {msg.header.sender} could not be carried out ({what}); stopped")
        try:
            self.pilot.action(now, ActionKind.STOP, msg.header.sender)
        except Exception:  # the stop itself failed: the velocity below is zero regardless
            self._velocity = (0.0, 0.0)
        return CommandResult(CommandStatus.REJECTED, f"could not be carried out ({what}); the robot stopped")

    def _fix(self, link: LinkName, topic: str, msg: UwbFix, out: Output) -> None:
        try:
            obs = fix_from_uwb(msg, self._wall_minus_monotonic())
        except ValueError as exc:
            self._rejected(self.gate.reject(link, topic, f"{topic}: {exc}"), out)
            return
        self._add_fix(obs, out)

    def _add_fix(self, obs: FixObservation, out: Output) -> None:
        verdict = self.fusion.add_fix(obs, self.clock.now())
        if verdict.accepted:
            self.fixes_accepted += 1
        else:
            self.fixes_rejected += 1

    def _rejected(self, r: Rejected, out: Output) -> None:
        if r.log:
            out.logs.append(f"rejected input on {r.link.value} topic {r.topic}: {r.reason} (logged once)")
            text = f"rejected {r.topic} on {r.link.value}: {r.reason}"
            out.messages.append((self._event("rejected_input", text, Severity.WARNING, topic=r.topic), None))

    def _ack(self, fields: dict[str, Any]) -> wire.Message:
        from fleetlink.shared.messages import Ack

        return self.counter.make(Ack, **fields)

    def _board_change(self, board: BoardView, out: Output) -> None:
        """The board went away (an error: the robot cannot be driven) or came back (its first
        connection, or a recovery): an event each way, and a log line."""
        if board.connected:
            self._board_sessions += 1
            kind, text, sev = "board_connected", "board connected", Severity.INFO
            if self._board_sessions > 1:
                kind, text = "board_recovered", f"board back (session {self._board_sessions})"
        else:
            kind, text, sev = "board_lost", "board link lost: the robot cannot move", Severity.ERROR
        out.messages.append((self._event(kind, text, sev), None))
        out.logs.append(text)

    def _event(self, kind: str, text: str, severity: Severity, **data: str) -> Event:
        kvs = tuple(KeyValue(key=k[:32], value=str(v)[:256]) for k, v in list(data.items())[:16])
        return self.counter.make(Event, kind=kind, text=text[:256], severity=severity, data=kvs)

    def _pilot_event(self, ev: PilotEvent) -> Event:
        data = {"reason": ev.reason} if ev.reason else {}
        if ev.order_id:
            data["orderId"] = ev.order_id
        sev = _SEVERITY.get(ev.kind.value, Severity.INFO)
        return self._event(ev.kind.value.lower(), ev.text, sev, **data)

    def _pose(self, now: float) -> Pose:
        m = self.fusion.map_pose()
        o = self._odom
        return self.counter.make(
            Pose,
            x=m.x,
            y=m.y,
            theta=_clamp_angle(m.theta),
            sd_x_m=_sd(m.sd_x),
            sd_y_m=_sd(m.sd_y),
            sd_theta_rad=_sd(m.sd_theta),
            odom_x=o.x if o else 0.0,
            odom_y=o.y if o else 0.0,
            odom_theta=_clamp_angle(o.theta) if o else 0.0,
            vx=self._velocity[0],
            omega=self._velocity[1],
            uwbStale=self._uwb_stale(now),
        )

    def _state(self, now: float) -> State:
        p = self._last_out
        mode = self.pilot.mode
        x, y, th = self._map_pose()
        goal = None
        if p is not None and p.goal is not None:
            gx, gy, gth = p.goal
            goal = Goal(x=gx, y=gy, theta=None if math.isnan(gth) else _clamp_angle(gth))
        errors = tuple(
            StateError(errorType="board", errorLevel=ErrorLevel.WARNING, errorDescription=e[:256])
            for e in self.board.errors[:15]
        )
        if not self.board.connected:
            errors = (
                StateError(errorType="board", errorLevel=ErrorLevel.FATAL, errorDescription="board not connected"),
                *errors,
            )
        stale = self._uwb_stale(now)
        return self.counter.make(
            State,
            agvPosition=AgvPosition(
                x=x,
                y=y,
                theta=_clamp_angle(th),
                mapId=self.map_id,
                positionInitialized=self.fusion.position_initialized,
                localizationScore=self.fusion.localization_score,
            ),
            velocity=Velocity(vx=self._velocity[0], omega=self._velocity[1]),
            batteryState=BatteryState(
                batteryCharge=min(100.0, max(0.0, self.board.battery_percent)), charging=self.board.charging
            ),
            errors=errors[:16],
            operatingMode=_MODE.get(mode, OperatingMode.SEMIAUTOMATIC)
            if self.board.connected
            else OperatingMode.SERVICE,
            safetyState=SafetyState(
                eStop=EStop.REMOTE if self.pilot.estop else EStop.NONE,
                fieldViolation=bool(p.field_violation) if p else False,
            ),
            driveMode=mode.value.lower(),
            links=self.links,
            uwbStale=stale,
            payloadOn=self.board.payload_on,
            boardConnected=self.board.connected,
            orderId=(p.order_id or "") if p else "",
            orderUpdateId=self.pilot.order_update_id,
            goal=goal,
            driving=abs(self._velocity[0]) > 1e-3 or abs(self._velocity[1]) > 1e-3,
            paused=mode is PilotMode.PAUSED,
        )

    def _change_key(self, now: float) -> tuple[Any, ...]:
        """``_state_key(self._state(now))`` without building the message (every tick; the State and
        its headerId only when it is published)."""
        p = self._last_out
        goal = None
        if p is not None and p.goal is not None:
            gx, gy, gth = p.goal
            goal = (gx, gy, None if math.isnan(gth) else _clamp_angle(gth))
        return (
            self.pilot.mode,
            self.pilot.estop,
            bool(p.field_violation) if p else False,
            self.links,
            self._uwb_stale(now),
            self.board.payload_on,
            self.board.connected,
            (p.order_id or "") if p else "",
            goal,
            self.board.errors[:15],
            self.fusion.position_initialized,
        )

    @staticmethod
    def _state_key(s: State) -> tuple[Any, ...]:
        # What counts as a change worth publishing at once (not position, speed or battery).
        return (
            s.operatingMode,
            s.safetyState,
            s.driveMode,
            s.links,
            s.uwbStale,
            s.payloadOn,
            s.boardConnected,
            s.orderId,
            s.goal,
            s.paused,
            s.errors,
            s.agvPosition.positionInitialized,
        )


def _sd(v: float) -> float:
    return v if math.isfinite(v) and 0.0 <= v < UNKNOWN_SD else UNKNOWN_SD


def _clamp_angle(a: float) -> float:
    a = (a + math.pi) % (2 * math.pi) - math.pi
    return min(3.2, max(-3.2, a))
