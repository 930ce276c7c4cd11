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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from fleetlink.agent.contact import ContactKeeper
from fleetlink.agent.fusion import Fusion
from fleetlink.agent.guard import GuardInputs, RobotAhead
from fleetlink.agent.home import HomeKeeper
from fleetlink.agent.interlocks import LampSituation, PeopleZone, lamp_interlock
from fleetlink.agent.itinerary import Finished, GoTo, Itinerary, ItineraryError, RunAction, Stop, StopAction
from fleetlink.agent.lease import DRIVE_LEASE_S, LeaseKeeper
from fleetlink.agent.links.gate import Accepted, CommandGate, Duplicate, Rejected, always_allowed
from fleetlink.agent.odometry import Odometry, OdomPose
from fleetlink.agent.peers import PeerBodies
from fleetlink.agent.pilot import (
    ActionKind,
    CommandResult,
    CommandStatus,
    EventKind,
    MapSense,
    PathProvider,
    PayloadRequest,
    Pilot,
    PilotEvent,
    PilotOutput,
)
from fleetlink.agent.pilot import OperatingMode as PilotMode
from fleetlink.agent.route import BodyAwareProvider
from fleetlink.agent.uwb_input import FixObservation, fix_from_pans, fix_from_uwb
from fleetlink.devices.controlbus.snapshot import BoardSnapshot
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import (
    MAX_DIAGNOSTIC_COUNTS,
    TRAJECTORY_END_M,
    UNKNOWN_SD_M,
    AckResult,
    ActionType,
    AgvPosition,
    BatteryState,
    BoardFault,
    BoardStatus,
    CommsPolicy,
    Contact,
    Count,
    Diagnostics,
    ErrorLevel,
    EStop,
    Event,
    FleetFrames,
    Goal,
    Home,
    InstantActions,
    KeyValue,
    Lease,
    LeaseRequest,
    LinkName,
    LinkStatus,
    OperatingMode,
    Order,
    OrderEdge,
    OrderProgress,
    PeopleZones,
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
INPUT_TOPICS = (*COMMAND_TOPICS, LeaseRequest.TOPIC, PeopleZones.TOPIC, UwbFix.TOPIC)
UNKNOWN_SD = UNKNOWN_SD_M
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
_ITINERARY_ACTIONS = (ActionType.STOP, ActionType.PAUSE, ActionType.RESUME, ActionType.CANCEL, ActionType.ESTOP)
"""Instant actions that also act on a running order with nodes (``AgentCore._itinerary_action``)."""
NODE_NEAR_M = 0.3
"""An order's node the go-to ends short of (blocked) within this distance counts as reached."""
NODE_PASS_M = 0.5
"""The same for a node with no actions (a waypoint: a sweep's lane end by a wall, where the
guard stops the robot its 0.40 m stopping distance short)."""
_HAZARDS = ("cliff", "bump")
"""Go-to endings that hold an order with nodes (the operator looks first) instead of skipping the
node; one within ``NODE_NEAR_M`` / ``NODE_PASS_M`` of the node counts it reached, then holds."""
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
    estop_button: bool = False
    """The emergency-stop button on the robot is pressed."""
    home_requests: int = 0
    """Go-home requests the board raised so far (its home button): a change starts return home."""
    faults: tuple[tuple[int, str], ...] = ()
    """The board's active faults (code, text)."""
    model: str = ""
    firmware: str = ""
    voltage_v: float | None = None
    current_a: float | None = None
    on_dock: bool = False
    temperature_c: float | None = None
    humidity_percent: float | None = None
    pm2_5: float | None = None
    tvoc_ppb: int | None = None
    atomiser_level: int = 0
    fan_level: int = 0
    tank_percent: float | None = None
    has_payload: bool = False
    """The board answers for a payload (lamp, atomiser, fan, tank): a plain base does not."""
    health_flags: int = 0
    bumper_bits: int = 0
    """Bit i set while bumper/cliff i is triggered."""
    sensors_m: tuple[float, ...] = ()
    battery_known: bool = False
    """The board has reported its battery (its first status poll is in)."""


def board_view(snap: BoardSnapshot, odom_t: float | None = None) -> BoardView:
    """``odom_t``: when ``snap.motor`` was polled (the runtime tracks it); default ``snap.updated``."""
    b = snap.bumpers
    front = snap.sensors.distances[0] if snap.sensors and snap.sensors.distances else None
    env, pay, pw = snap.env, snap.payload, snap.power
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
        estop_button=bool(snap.buttons.bitmap & _ESTOP_BUTTON) if snap.buttons else False,
        home_requests=snap.home_requests,
        faults=tuple((e.code, e.message) for e in snap.errors),
        model=snap.info.model if snap.info else "",
        firmware=f"{snap.info.firmware >> 8}.{snap.info.firmware & 0xFF}" if snap.info else "",
        voltage_v=pw.voltage if pw else None,
        current_a=pw.current if pw else None,
        on_dock=bool(snap.status.power_flags & _ON_DOCK) if snap.status else False,
        temperature_c=env.temperature_c if env else None,
        humidity_percent=env.humidity_percent if env else None,
        pm2_5=env.pm2_5 if env else None,
        tvoc_ppb=env.tvoc_ppb if env else None,
        atomiser_level=pay.atomiser_level if pay else 0,
        fan_level=pay.fan_level if pay else 0,
        has_payload=pay is not None,
        tank_percent=float(pay.tank_percent) if pay else None,
        health_flags=snap.health.flags if snap.health else 0,
        bumper_bits=b.triggered_bits if b else 0,
        sensors_m=tuple(d for d in snap.sensors.distances if d > 0)[:16] if snap.sensors else (),
        battery_known=snap.status is not None,
    )


_ESTOP_BUTTON = 0x08  # devices/controlbus/protocol.py Button.ESTOP
_ON_DOCK = 0x04  # PowerFlag: on dock
LAMP_RADIUS_M = 3.0
"""How far from the robot a UV-C lamp's light is taken to be dangerous (people-present zones)."""
LAMP_RECUT_S = 1.0
"""While the board still reports the lamp on after an interlock switched it off, ask again this often."""
ARRIVED_M = 0.3
"""A retrace or a return home under the comms-loss policy that ended this near its target arrived."""
FAULT_RETRY_S = 5.0
"""A fault the agent asked the board to clear and still listed is asked again after this long."""
BOARD_STATUS_PERIOD_S = 1.0
"""``BoardStatus`` at this period, and at once when something an operator acts on changes."""
_CLEARABLE = {0x0001, 0x0003, 0x0004}
"""Board faults (HealthErrorCode) the agent clears once it sees their condition is over: the link
watchdog (it is talking to the board again; the trip is counted), tank empty (refilled), battery
low (charged). Anything else (a motor stall) stays until someone looks at the robot."""


@dataclass(slots=True)
class Output:
    velocity: tuple[float, float] | None = None
    messages: list[tuple[wire.Message, LinkName | None]] = field(default_factory=list)
    payload: list[PayloadRequest] = field(default_factory=list)
    """Payload requests for the board (device, on, level; device "all" off = every payload off)."""
    logs: list[str] = field(default_factory=list)
    clear_faults: list[int] = field(default_factory=list)
    """Board faults (codes) to clear with the board's clear_error handshake."""


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
        home: HomeKeeper | None = None,
        contact: ContactKeeper | None = None,
        lamp_radius_m: float = LAMP_RADIUS_M,
        peers: PeerBodies | None = None,
    ) -> None:
        self.robot = robot
        self.clock = clock
        self.pilot = pilot
        self.odometry = odometry or Odometry()
        self.fusion = fusion or Fusion()
        self.map_id = map_id
        self.operators = frozenset(operators)
        self.lease = lease or LeaseKeeper()
        self.home = home or HomeKeeper()
        self.contact = contact or ContactKeeper()
        self.peers = peers or PeerBodies()
        """The other robots' poses (robot.toml's ``peers``): the standing ones are planned around."""
        self.peers.robot = robot  # its own frame among the fleet map's (FleetFrames) is its id's
        self.map_began = 0.0
        """When the map its poses are in began (``Pose.map_began``; 0: no map yet): ``map_begun``."""
        self._plan_now = -math.inf
        """The control step's time, for the path provider the pilot calls inside it."""
        if self.home.home is not None:
            h = self.home.home
            self.pilot.set_home((h.x, h.y, h.theta))
        self.estop_source = EStop.NONE
        """Who latched the e-stop: REMOTE (an operator), MANUAL (the button on the robot)."""
        self.watchdog_trips = 0
        self._estop_button = False
        self._home_requests: int | None = None
        self._clearing: dict[int, float] = {}
        """Faults asked to be cleared, and when (asked again after ``FAULT_RETRY_S``)."""
        self._renewing = ""
        """The operator whose lease request holds the lease (consoles renew it: contact)."""
        self.lamp_radius_m = lamp_radius_m
        self.zones: tuple[PeopleZone, ...] = ()
        self._zones_by: dict[str, tuple[PeopleZone, ...]] = {}
        """Areas operators declared "people present": the lamp's radius may not reach into them."""
        self._lamp_operator = ""
        """Who switched the lamp on last (its lease must hold while it is on)."""
        self._lamp_cut: str | None = None
        self._lamp_cut_at = -math.inf
        self._engaged = False
        """That operator held the lease when last looked (a lease running out keeps it so)."""
        self._next_board = -math.inf
        self._last_board_key: tuple[Any, ...] | None = None
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
        self.itinerary: Itinerary | None = None
        """The order with nodes being run (agent/itinerary.py), None without one."""
        self._replaced_by_itinerary: str | None = None
        """The order the itinerary's own go-to replaced on the pilot (a goal still being driven): its
        cancellation is the itinerary starting, not an interruption of it."""

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
            if not self.operators or verdict.msg.header.sender in self.operators:
                self._heard(now, out)  # (a copy of a refused command is no contact)
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
        self._heard(now, out)
        if isinstance(msg, PeopleZones):
            self._people_zones(msg, link, out)
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

    def on_peer(self, link: LinkName, key: str, payload: bytes, now: float) -> Output:
        """A peer's fused pose (``fleetlink/v1/<peer>/pose``), or where the fleet map service found the
        robots in their own frames (``fleetlink/v1/fleet/frames``): kept to plan around, never a command
        and no contact with an operator. Anything else, or what does not decode, is refused and counted."""
        out = Output()
        try:
            robot, topic = keys.parse_key(key)
        except ValueError as exc:
            self._rejected(self.gate.reject(link, "?", f"key: {exc}"), out)
            return out
        if robot == keys.FLEET_MAP and topic == FleetFrames.TOPIC and self.peers.peers:
            try:
                frames = wire.decode_key(key, payload)
            except wire.WireError as exc:
                self._rejected(self.gate.reject(link, topic, exc.reason, exc.field), out)
                return out
            assert isinstance(frames, FleetFrames)
            had = set(self.peers.framed(now))
            if self.peers.hear_frames(frames, now):
                # The robots they newly place (itself, its peers): whom it can now keep clear of without UWB.
                new = [r for r in self.peers.framed(now) if r not in had and (r in self.peers.peers or r == self.robot)]
                if new:
                    out.logs.append(f"hears the fleet map's frames on {link.value}: {', '.join(new)} placed on it")
            return out
        if topic != Pose.TOPIC or robot not in self.peers.peers:
            self._rejected(self.gate.reject(link, topic, f"key: not a peer's pose for agent {self.robot}: {key}"), out)
            return out
        try:
            msg = wire.decode_key(key, payload)
        except wire.WireError as exc:
            self._rejected(self.gate.reject(link, topic, exc.reason, exc.field), out)
            return out
        assert isinstance(msg, Pose)  # decode_key checks the message against its key's topic
        first = not self.peers.has_heard(robot)
        if self.peers.hear(robot, msg, now) and first:
            # Once per peer: the log says whom the robot rule and the planner know of (a robot the
            # site's ACL does not let it hear is never named here).
            out.logs.append(f"hears {robot}'s pose on {link.value}: planned around and kept clear of")
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

    def use_map(self, plan: BodyAwareProvider | None, sense: MapSense | None = None) -> None:
        """Route go-tos and return home over the onboard map: the runtime passes its planner's
        ``route`` (``OnboardMapper.plan`` does as well: None while the map is still empty, so the
        pilot drives straight, exactly as without a map; [] when there is no path). None: no map,
        straight lines. ``sense``: what else the map says (room to back off, the echo to expect,
        clear legs; None: the pilot backs off blind and never creeps). With ``peers``, the provider
        is also handed those standing still (agent/peers.py)."""
        self.pilot.path_provider = plan if plan is None or not self.peers.peers else self._among_peers(plan)
        self.pilot.map_sense = sense

    def _among_peers(self, plan: BodyAwareProvider) -> PathProvider:
        """``plan`` with the peers standing still in the site frame planned around as bodies, once
        this robot is placed in that frame too. A new provider for each map: the route tells a newer
        map by the provider's identity."""

        def provider(
            start: tuple[float, float], goal: tuple[float, float], /, blocked: Sequence[tuple[float, float]] = ()
        ) -> Sequence[tuple[float, float]] | None:
            bodies = self.peers.standing(self._plan_now, self.fusion.position_initialized)
            return plan(start, goal, blocked=blocked, bodies=bodies)

        return provider

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
        self._board_inputs(now, board, out)
        self._contact_tick(now, out)
        self._control(now, out)
        self._interlock_tick(now, out)
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
        self._board_status(now, out)
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
        if ok:  # a console that asks for the lease renews it: its silence means lost contact
            self._renewing = "" if msg.release else msg.header.sender
            self._engaged = bool(self._renewing)
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
        self._plan_now = now
        self._itinerary_steps(now, out)
        if self.itinerary is not None and self.itinerary.driving:
            x, y, _ = self._map_pose()
            self.itinerary.approach(x, y)
        pose = self._map_pose()
        ahead: tuple[RobotAhead, ...] = ()
        if self.peers.peers:
            # Placed, its pose is in the site frame; else in its own map's, its heading that map's (known
            # there), where the fleet map's frames may put the others (agent/peers.py).
            placed = self.fusion.position_initialized
            sd = self.fusion.map_pose()  # how sure it is of that pose: the margin it keeps from them
            ahead = self.peers.robots_ahead(
                now,
                pose,
                self.fusion.heading_initialized or not placed,
                sd_xy=max(sd.sd_x, sd.sd_y),
                sd_theta=sd.sd_theta if placed else 0.0,
                placed=placed,
            )
        inputs = GuardInputs(
            ultrasonic_m=self.board.ultrasonic_m, cliff=self.board.cliff, bumped=self.board.bumped, robots_ahead=ahead
        )
        p = self.pilot.tick(now, pose, inputs)
        self._last_out = p
        self._velocity = (p.v, p.omega)
        out.velocity = (p.v, p.omega)
        for ev in p.events:
            out.messages.append((self._pilot_event(ev), None))
            self._itinerary_event(ev, now, out)
        for req in p.payload_requests:
            out.payload.append(req)
            if req.device == "uv" and req.on:
                self._lamp_operator = req.sender
                self._lamp_cut = None

    def _run(self, msg: Order | InstantActions | Teleop, now: float, out: Output) -> CommandResult:
        sender = msg.header.sender
        if isinstance(msg, Teleop):
            r = self.pilot.teleop(now, msg.v, msg.omega, msg.ttl_s, sender)
            it = self.itinerary
            if r.accepted and it is not None and not it.waiting and (msg.v != 0.0 or msg.omega != 0.0):
                it.moved(now, "teleop")  # driven by hand: the round waits, then comes back here
                self._itinerary_note(it, f"waits: {sender} drives it by hand; resume goes on", out)
            return r
        if isinstance(msg, Order):
            if msg.nodes or msg.edges:
                return self._order_with_nodes(msg, now, out)
            if msg.returnHome:
                return self._return_home(now, sender)
            if msg.goal is None:
                return CommandResult(CommandStatus.REJECTED, "order has neither a goal nor returnHome")
            g = msg.goal
            return self.pilot.order(now, msg.orderId, msg.orderUpdateId, g.x, g.y, g.theta, sender)
        results: list[str] = []
        status = CommandStatus.ACCEPTED
        for a in msg.actions:
            if a.actionType in (ActionType.SET_HOME, ActionType.SET_COMMS_POLICY):
                r = self._setting(a.actionType, {kv.key: kv.value for kv in a.actionParameters}, out)
            elif a.actionType is ActionType.ESTOP_RELEASE and self._estop_button:
                r = CommandResult(CommandStatus.REJECTED, "the e-stop button on the robot is pressed: release it first")
            elif a.actionType is ActionType.PAYLOAD:
                r = self._payload_action({kv.key: kv.value for kv in a.actionParameters}, now, sender)
            elif a.actionType is ActionType.RETURN_HOME:
                r = self._return_home(now, sender)
            elif a.actionType is ActionType.DWELL:
                r = CommandResult(
                    CommandStatus.REJECTED, "dwell is a node action (in an order's node), not an instant one"
                )
            elif self.itinerary is not None and a.actionType in _ITINERARY_ACTIONS:
                r = self._itinerary_action(a.actionType, now, sender, out)
            else:
                was_estop = self.pilot.estop
                r = self.pilot.action(now, _ACTION_KIND[a.actionType], sender)
                if self.pilot.estop and not was_estop:
                    self.estop_source = EStop.REMOTE
            if r.status is CommandStatus.REJECTED:
                status = CommandStatus.REJECTED
            if r.reason:
                results.append(f"{a.actionId}: {r.reason}")
        return CommandResult(status, "; ".join(results))

    def _setting(self, kind: ActionType, params: dict[str, str], out: Output) -> CommandResult:
        """setHome (x, y [, theta_deg]; none: here) and setCommsPolicy (policy)."""
        try:
            if kind is ActionType.SET_COMMS_POLICY:
                policy = self.contact.set_policy(params.get("policy", ""))
                self._next_state = -math.inf  # tell everyone at once
                return CommandResult(CommandStatus.ACCEPTED, f"comms-loss policy: {policy.value}")
            if params.keys() - {"x", "y", "theta_deg"} or ("x" in params) != ("y" in params):
                raise ValueError("setHome takes x and y (metres) and optionally theta_deg, or nothing for here")
            if "x" in params:
                theta = math.radians(float(params["theta_deg"])) if "theta_deg" in params else math.nan
                home = self.home.set(float(params["x"]), float(params["y"]), theta)
            else:
                if not self.fusion.position_initialized:
                    raise ValueError("the robot is not localised yet: give x and y")
                x, y, _ = self._map_pose()
                home = self.home.set(x, y)
        except ValueError as exc:
            return CommandResult(CommandStatus.REJECTED, str(exc)[:200])
        self.pilot.set_home((home.x, home.y, home.theta))
        self._next_state = -math.inf
        text = f"home set at ({home.x:.2f}, {home.y:.2f})"
        out.messages.append((self._event("home_set", text, Severity.INFO, source=home.source.value), None))
        return CommandResult(CommandStatus.ACCEPTED, text)

    def _people_zones(self, msg: PeopleZones, link: LinkName, out: Output) -> None:
        """An operator's people-present zones (its whole list): the lamp keeps out of them."""
        sender = msg.header.sender
        zones: list[PeopleZone] = []
        for z in msg.zones:
            if len(z.polygon) < 3:
                reason = f"zones: {z.name!r} has {len(z.polygon)} corners, a zone needs at least 3"
                self._rejected(self.gate.reject(link, msg.TOPIC, reason), out)
                return  # nothing of a bad list is taken: the previous one stands
            zones.append(PeopleZone(z.name, tuple((p.x, p.y) for p in z.polygon)))
        if zones:
            self._zones_by[sender] = tuple(zones)
        else:
            self._zones_by.pop(sender, None)
        self.zones = tuple(z for who in sorted(self._zones_by) for z in self._zones_by[who])
        names = ", ".join(z.name for z in zones) or "none"
        text = f"people-present zones from {sender}: {names}"
        out.messages.append((self._event("zones", text, Severity.INFO, sender=sender), None))

    def _payload_action(self, params: Mapping[str, str], now: float, sender: str) -> CommandResult:
        """``payload``: ``device`` uv (default), atomiser or fan; ``on`` true|false; ``level``
        0-3 (atomiser and fan; on without a level is level 1)."""
        try:
            device, on, level = _payload_params(params)
        except ValueError as exc:
            return CommandResult(CommandStatus.REJECTED, str(exc))
        if not on or level == 0:
            return self.pilot.action(now, ActionKind.PAYLOAD_OFF, sender, device=device)
        b = self.board
        if b.connected and not b.has_payload:
            return CommandResult(CommandStatus.REJECTED, "this robot has no payload (its board has none)")
        if device == "atomiser" and b.tank_percent is not None and b.tank_percent <= 0.0:
            return CommandResult(CommandStatus.REJECTED, "the disinfectant tank is empty: refill it first")
        if device == "uv":
            why = lamp_interlock(self._lamp_situation(now, sender))
            if why is not None:
                return CommandResult(CommandStatus.REJECTED, f"UV lamp interlock: {why}")
        return self.pilot.action(now, ActionKind.PAYLOAD_ON, sender, device=device, level=level or 1)

    def _lamp_situation(self, now: float, operator: str) -> LampSituation:
        b = self.board
        x, y, _ = self._map_pose()
        return LampSituation(
            estop=self.pilot.estop,
            comms_lost=self.contact.lost and not self.contact.payload_on_loss,
            bumped=b.bumped,
            cliff=b.cliff,
            lease_held=not operator or self.lease.view(now).holder == operator,
            board_connected=b.connected,
            has_lamp=b.has_payload or not b.connected,
            position=(x, y) if self.fusion.position_initialized else None,
            lamp_radius_m=self.lamp_radius_m,
            zones=self.zones,
        )

    def _interlock_tick(self, now: float, out: Output) -> None:
        """The lamp on while an interlock holds: off now, with the reason, once per episode."""
        if not self.board.payload_on:
            self._lamp_cut = None
            return
        why = lamp_interlock(self._lamp_situation(now, self._lamp_operator))
        if why is None:
            return
        if why != self._lamp_cut:
            text = f"UV lamp switched off: {why}"
            out.messages.append((self._event("interlock", text, Severity.WARNING, reason=why), None))
            out.logs.append(text)
        elif now - self._lamp_cut_at < LAMP_RECUT_S:
            return  # asked already; the board's next payload poll will say
        self._lamp_cut, self._lamp_cut_at = why, now
        out.payload.append(PayloadRequest(False, None, "interlock", "uv"))

    # -- orders with nodes (agent/itinerary.py) ---------------------------------------------------

    def _order_with_nodes(self, msg: Order, now: float, out: Output) -> CommandResult:
        refused = self.pilot.admit(msg.orderId, msg.orderUpdateId)
        if refused is not None:
            return refused
        if msg.goal is not None or msg.returnHome:
            return CommandResult(CommandStatus.REJECTED, "an order has nodes, a goal or returnHome: one of them")
        if self.pilot.estop:
            return CommandResult(CommandStatus.REJECTED, "e-stop latched: release it first")
        try:
            it = Itinerary.of(
                msg.orderId,
                msg.orderUpdateId,
                msg.header.sender,
                _stops(msg),
                extent_m=self.pilot.config.extent_m,
                check_action=self._check_node_payload,
            )
        except ItineraryError as exc:
            return CommandResult(CommandStatus.REJECTED, str(exc)[:250])
        old = self.itinerary
        if old is not None and old.order_id == msg.orderId:
            it = old.updated(it)
            text = f"order {it.order_id} updated ({it.update_id}): {len(it.stops) - it.index} nodes to go"
        else:
            if old is not None:
                self._end_itinerary(now, out, f"replaced by order {msg.orderId}")
            text = f"order {it.order_id}: {len(it.stops)} nodes from {it.sender}"
        self.itinerary = it
        self.pilot.remember(msg.orderId, msg.orderUpdateId)
        out.messages.append((self._event("order", text, Severity.INFO, order=it.order_id), None))
        return CommandResult(CommandStatus.ACCEPTED, text)

    def _check_node_payload(self, a: StopAction) -> None:
        try:
            _, on, _ = _payload_params(a.params)
        except ValueError as exc:
            raise ItineraryError(f"action {a.action_id!r}: {exc}") from None
        if on and self.board.connected and not self.board.has_payload:
            raise ItineraryError(f"action {a.action_id!r}: this robot has no payload (its board has none)")

    def _itinerary_steps(self, now: float, out: Output) -> None:
        """Do what the order with nodes asks for now: a go-to, a node action, its end."""
        for _ in range(2 * 16 + 2):  # a node's actions, at most, then a go-to or the end
            it = self.itinerary
            if it is None:
                return
            step = it.step(now)
            if step is None:
                return
            if isinstance(step, Finished):
                skipped = f", {len(step.skipped)} skipped ({', '.join(step.skipped[:5])})" if step.skipped else ""
                self._end_itinerary(now, out, f"finished: {step.nodes} nodes{skipped}", done=True)
                return
            if isinstance(step, GoTo):
                st = step.stop
                held = self.pilot.order_id if self.pilot.state.has_route else None
                r = self.pilot.order(
                    now,
                    it.order_id,
                    it.update_id,
                    st.x,
                    st.y,
                    st.theta,
                    it.sender,
                    admitted=True,
                    max_v=st.max_v,
                    deviation=st.deviation,
                    trajectory=st.trajectory,
                )
                if r.accepted and held is not None and held != it.order_id:
                    self._replaced_by_itinerary = held
                if not r.accepted:
                    it.interrupted(now, r.reason[:64] or "refused")
                    self._itinerary_note(it, f"node {st.node_id}: {r.reason}; resume tries again", out)
                continue
            if isinstance(step, RunAction):
                a = step.action
                self._node_payload(it, a.params, now, out, f"node {step.stop.node_id}, action {a.action_id}")

    def _node_payload(self, it: Itinerary, params: Mapping[str, str], now: float, out: Output, what: str) -> None:
        """An order's payload switch (``what`` names it in a note when refused): the lamp as the order
        left it (``it.lamp``, for a resume); a lamp refused holds the order for the operator."""
        r = self._payload_action(params, now, it.sender)
        device, on, _ = _payload_params(params)
        if device == "uv":
            it.lamp = on and r.accepted
        if not r.accepted:
            if device == "uv" and on:  # no dose without the lamp: wait for the operator
                it.hold(now, "lamp refused")
                it.lamp = True  # a resume tries again
            self._itinerary_note(it, f"{what}: {r.reason}", out)

    def _itinerary_event(self, ev: PilotEvent, now: float, out: Output) -> None:
        """The pilot's go-to to the current node ended: reached, failed (skip, or hold on a hazard),
        cancelled (hold: a stop, an e-stop, a teleop, the comms-loss policy took over)."""
        it = self.itinerary
        if it is None or not it.driving or ev.order_id != it.order_id:
            if (
                ev.kind is EventKind.GOAL_CANCELLED
                and ev.order_id is not None
                and ev.order_id == self._replaced_by_itinerary
            ):
                self._replaced_by_itinerary = None  # the goal the itinerary's go-to replaced: it goes on
            elif it is not None and it.driving and ev.kind is EventKind.GOAL_CANCELLED:
                it.interrupted(now, ev.reason or "cancelled")  # replaced by return home or a retrace
            return
        if ev.kind is EventKind.GOAL_REACHED:
            it.arrived(now)
            self._owed_lamp(it, now, out)
        elif ev.kind is EventKind.GOAL_FAILED and ev.reason not in _HAZARDS:
            cur = it.current
            near = NODE_NEAR_M if cur is None or cur.actions else NODE_PASS_M
            if cur is not None and it.closest_m <= near:
                # The guard keeps its stopping distance from what is ahead: a node by a wall is
                # reached as near as that allows, and its actions (a dwell) run from where it stopped.
                gap = it.closest_m
                it.arrived(now)
                self._itinerary_note(
                    it, f"node {cur.node_id}: came within {gap:.2f} m (as near as the guard allows)", out
                )
                self._owed_lamp(it, now, out)
                return
            stop = it.failed(now)
            if stop is not None:
                self._itinerary_note(
                    it,
                    f"node {stop.node_id} skipped: {ev.text}",
                    out,
                    Severity.WARNING,
                    skipped=stop.node_id,
                    sequenceId=str(stop.sequence_id),
                )
                # Its payload switches still apply (not its dwell): the route after it expects the
                # lamp as they leave it, and a skipped "lamp on" would run the rest of a round dark.
                # The lamp's switch-off at once; its switch-on at the next node reached, not here:
                # where the robot gave up may be outside the area (``_owed_lamp``).
                for a in stop.actions:
                    if a.kind == "payload":
                        device, on, _ = _payload_params(a.params)
                        if device == "uv":
                            it.lamp_owed = on
                        if not (device == "uv" and on):
                            self._node_payload(it, a.params, now, out, f"node {stop.node_id}, action {a.action_id}")
        elif ev.kind is EventKind.GOAL_FAILED:  # a hazard: hold for the operator
            cur = it.current
            near = NODE_NEAR_M if cur is None or cur.actions else NODE_PASS_M
            if cur is not None and it.closest_m <= near:
                # The body touched something (a doorway's jamb beside a lane end, a wall the map
                # put a little further out) as near the node as a blocked go-to counts reached:
                # the node was reached. Driving at it again after the resume would press the same
                # spot (measured: three bumps at one node, the round left unfinished).
                gap = it.closest_m
                it.arrived(now)
                it.hold(now, ev.reason or "hazard")
                if it.lamp_owed:  # the resume switches it on, here
                    it.lamp, it.lamp_owed = True, False
                self._itinerary_note(it, f"node {cur.node_id}: came within {gap:.2f} m before the {ev.reason}", out)
            else:
                it.interrupted(now, ev.reason or "cancelled")
        elif ev.kind is EventKind.GOAL_CANCELLED:
            it.interrupted(now, ev.reason or "cancelled")

    def _owed_lamp(self, it: Itinerary, now: float, out: Output) -> None:
        """At a node reached: the lamp a skipped node would have switched on (``lamp_owed``), before
        this node's own actions; refused, the order waits for the operator as for a node's own."""
        if not it.lamp_owed:
            return
        it.lamp_owed = False
        where = it.last.node_id if it.last is not None else "?"
        self._node_payload(it, {"device": "uv", "on": "true"}, now, out, f"node {where}, a skipped node's lamp")

    def _itinerary_action(self, kind: ActionType, now: float, sender: str, out: Output) -> CommandResult:
        """stop, cancel, pause, resume and e-stop while an order with nodes runs."""
        it = self.itinerary
        assert it is not None
        if kind in (ActionType.STOP, ActionType.CANCEL):
            r = self.pilot.action(now, _ACTION_KIND[kind], sender)
            self._end_itinerary(now, out, f"{'stopped' if kind is ActionType.STOP else 'cancelled'} by {sender}")
            return CommandResult(CommandStatus.ACCEPTED, r.reason)
        if kind is ActionType.ESTOP:
            r = self.pilot.action(now, ActionKind.ESTOP, sender)
            if r.accepted:
                self.estop_source = EStop.REMOTE
            it.interrupted(now, "e-stop")
            return r
        if kind is ActionType.PAUSE:
            if it.waiting == "paused":
                return CommandResult(CommandStatus.ACCEPTED, "already paused")
            if it.driving:
                self.pilot.action(now, ActionKind.PAUSE, sender)
            it.hold(now, "paused")
            if it.lamp:  # people may come near a paused round: the lamp goes off, resume brings it back
                out.payload.append(PayloadRequest(False, None, sender, "uv"))
            self._itinerary_note(it, f"paused by {sender}", out)
            return CommandResult(CommandStatus.ACCEPTED, f"order {it.order_id} paused")
        # resume
        if self.pilot.estop:
            return CommandResult(CommandStatus.REJECTED, "e-stop latched: release it first")
        if not it.waiting:
            return CommandResult(CommandStatus.ACCEPTED, "not waiting")
        if it.driving and self.pilot.mode is PilotMode.PAUSED:
            self.pilot.action(now, ActionKind.RESUME, sender)
        it.release(now)
        if it.lamp:
            r = self._payload_action({"device": "uv", "on": "true"}, now, it.sender)
            if not r.accepted:
                it.hold(now, "lamp refused")
                return CommandResult(CommandStatus.REJECTED, f"order {it.order_id} still waits: {r.reason}")
        self._itinerary_note(it, f"resumed by {sender}", out)
        return CommandResult(CommandStatus.ACCEPTED, f"order {it.order_id} resumed")

    def _end_itinerary(self, now: float, out: Output, why: str, *, done: bool = False) -> None:
        it = self.itinerary
        if it is None:
            return
        self.itinerary, self._replaced_by_itinerary = None, None
        if it.lamp:
            out.payload.append(PayloadRequest(False, None, it.sender, "uv"))
        if it.driving and self.pilot.order_id == it.order_id:
            self.pilot.action(now, ActionKind.CANCEL, it.sender)
        sev = Severity.INFO if done and not it.skipped else Severity.WARNING
        outcome = "finished" if done else "ended"  # for machines: the text is for people
        event = self._event("order", f"order {it.order_id} {why}", sev, order=it.order_id, outcome=outcome)
        out.messages.append((event, None))
        self._next_state = -math.inf

    def _itinerary_note(
        self, it: Itinerary, text: str, out: Output, severity: Severity = Severity.INFO, **data: str
    ) -> None:
        out.messages.append(
            (self._event("order", f"order {it.order_id}: {text}"[:256], severity, order=it.order_id, **data), None)
        )
        self._next_state = -math.inf

    def _itinerary_key(self) -> tuple[Any, ...] | None:
        it = self.itinerary
        return None if it is None else (it.index, len(it.skipped), it.waiting)

    def _progress(self) -> OrderProgress | None:
        it = self.itinerary
        if it is None:
            return None
        return OrderProgress(
            nodesTotal=len(it.stops),
            nodesDone=min(it.index, len(it.stops)),
            skipped=len(it.skipped),
            lastNodeId=it.last.node_id if it.last is not None else "",
            lastNodeSequenceId=it.last.sequence_id if it.last is not None else 0,
            dwellLeft_s=it.dwell_left_s,
            waiting=it.waiting,
        )

    def _return_home(self, now: float, sender: str) -> CommandResult:
        if self.home.home is None:
            return CommandResult(
                CommandStatus.REJECTED, "no home yet: the robot has not localised and has no dock (setHome sets one)"
            )
        return self.pilot.action(now, ActionKind.RETURN_HOME, sender)

    def _heard(self, now: float, out: Output) -> None:
        """An allowed operator's message arrived: the robot is in contact."""
        x, y, _ = self._map_pose()
        regained = self.contact.heard(now, x, y)
        if regained is None:
            return
        if self.pilot.retracing:
            self.pilot.halt(now, "comms")  # retraced far enough: the operator is back in charge
        out.messages.append(
            (self._event("contact_regained", regained.text, Severity.INFO, out_s=f"{regained.out_s:.1f}"), None)
        )
        out.logs.append(regained.text)
        self._next_state = now

    def _contact_tick(self, now: float, out: Output) -> None:
        """The comms-loss policy: lost contact starts it; how its drive ended is noted."""
        c = self.contact
        x, y, _ = self._map_pose()
        c.moved(x, y)
        if c.action in ("retracing", "homing") and not self.pilot.state.has_route:
            arrived = c.target is not None and math.dist((x, y), c.target) <= ARRIVED_M
            c.action = ("waiting" if c.action == "retracing" else "home") if arrived else "stopped"
            self._next_state = now
        # Engaged: the lease is held by an operator who asked for it (a console, which renews it
        # every couple of seconds; a script that only sends orders never heartbeats). A lease that
        # runs out during the silence leaves it engaged: running out is what silence does.
        holder = self.lease.view(now).holder
        if holder:
            self._engaged = holder == self._renewing
        lost = c.tick(now, engaged=self._engaged)
        if lost is None:
            return
        self._next_state = now
        text = f"no operator heard for {lost.silent_s:.1f} s: "
        home = self.home.home
        if self.pilot.estop:
            c.action, text = "stopped", text + "e-stop latched, staying put"
        elif self.pilot.state.has_route and not self.pilot.retracing and self.pilot.order_id is None:
            c.action, c.target = "homing", (home.x, home.y) if home else None  # already on its way home
            text += "already returning home: going on"
        elif lost.policy is CommsPolicy.RETRACE and len(lost.path) > 0:
            r = self.pilot.retrace(now, lost.path, "comms")
            c.action, c.target = ("retracing" if r.accepted else "stopped"), lost.path[-1]
            text += f"retracing {len(lost.path)} waypoints to ({lost.path[-1][0]:.2f}, {lost.path[-1][1]:.2f})"
        elif lost.policy is CommsPolicy.HOME and home is not None:
            r = self.pilot.action(now, ActionKind.RETURN_HOME, "comms")
            c.action, c.target = ("homing" if r.accepted else "stopped"), (home.x, home.y)
            text += "returning home"
        else:
            self.pilot.halt(now, "comms")
            c.action, text = "stopped", text + "stopped"
        if not c.payload_on_loss:
            self.pilot.action(now, ActionKind.PAYLOAD_OFF, "comms")
        out.messages.append((self._event("contact_lost", text, Severity.ERROR, policy=lost.policy.value), None))
        out.logs.append(text)

    def _board_inputs(self, now: float, board: BoardView, out: Output) -> None:
        """The robot's own buttons, the home it localised at, and the faults to clear."""
        if board.estop_button and not self._estop_button:
            was = self.pilot.estop
            self.pilot.action(now, ActionKind.ESTOP, "button")
            if not was:
                self.estop_source = EStop.MANUAL
            out.logs.append("e-stop button pressed on the robot: latched")
        self._estop_button = board.estop_button
        if self._home_requests is not None and board.home_requests > self._home_requests:
            r = self._return_home(now, "button")
            text = "home button pressed: returning home" if r.accepted else f"home button pressed: {r.reason}"
            out.messages.append((self._event("home_button", text, Severity.INFO), None))
        self._home_requests = board.home_requests
        if self.fusion.position_initialized and self.home.home is None:
            x, y, _ = self._map_pose()
            home = self.home.localised(x, y)
            if home is not None:
                self.pilot.set_home((home.x, home.y, home.theta))
                self._next_state = now
                text = f"home set at ({home.x:.2f}, {home.y:.2f}), where the robot first localised"
                out.messages.append((self._event("home_set", text, Severity.INFO, source=home.source.value), None))
        if board.connected:
            codes = {code for code, _ in board.faults}
            self._clearing = {c: t for c, t in self._clearing.items() if c in codes}
            for code in sorted(codes):
                asked = self._clearing.get(code)
                if (asked is None or now - asked >= FAULT_RETRY_S) and self._fault_over(code, board):
                    if code == 0x0001 and asked is None:
                        self.watchdog_trips += 1
                    self._clearing[code] = now
                    out.clear_faults.append(code)

    @staticmethod
    def _fault_over(code: int, board: BoardView) -> bool:
        if code not in _CLEARABLE:
            return False
        if code == 0x0003:  # tank empty
            return board.tank_percent is not None and board.tank_percent > 0
        if code == 0x0004:  # battery low
            return board.battery_percent >= 15.0
        return True  # the link watchdog: the agent is talking to the board again

    def _board_status(self, now: float, out: Output) -> None:
        b = self.board
        if b.connected and not b.battery_known:
            return  # connected, its first readings not in yet: no report of a battery at 0 %
        key = (
            b.connected,
            b.faults,
            b.payload_on,
            b.atomiser_level,
            b.fan_level,
            b.charging,
            b.on_dock,
            b.estop_button,
            None if b.tank_percent is None else int(b.tank_percent // 5),
            self.watchdog_trips,
        )
        if now < self._next_board and key == self._last_board_key:
            return
        self._next_board = now + BOARD_STATUS_PERIOD_S
        self._last_board_key = key
        msg = self.counter.make(
            BoardStatus,
            connected=b.connected,
            model=b.model[:64],
            firmware=b.firmware[:64],
            battery_percent=min(100.0, max(0.0, b.battery_percent)),
            battery_voltage_v=_within(b.voltage_v, 0.0, 1000.0),
            battery_current_a=_within(b.current_a, -1000.0, 1000.0),
            charging=b.charging,
            on_dock=b.on_dock,
            temperature_c=_within(b.temperature_c, -100.0, 200.0),
            humidity_percent=_within(b.humidity_percent, 0.0, 100.0),
            pm2_5_ug_m3=_within(b.pm2_5, 0.0, 1e9),
            tvoc_ppb=b.tvoc_ppb if b.tvoc_ppb is not None and b.tvoc_ppb >= 0 else None,
            uv_lamp=b.payload_on,
            atomiser_level=min(3, max(0, b.atomiser_level)),
            fan_level=min(3, max(0, b.fan_level)),
            has_payload=b.has_payload,
            tank_percent=_within(b.tank_percent, 0.0, 100.0),
            estop_button=b.estop_button,
            health_flags=b.health_flags & 0xFF,
            faults=tuple(BoardFault(code=c & 0xFFFF, text=t[:64]) for c, t in b.faults[:16]),
            bumpers=b.bumper_bits,
            sensors_m=tuple(max(0.0, d) for d in b.sensors_m[:16] if math.isfinite(d)),
            watchdog_trips=self.watchdog_trips,
        )
        out.messages.append((msg, None))

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
            map_began=self.map_began,
        )

    def map_begun(self, began: float) -> None:
        """The map keeper's map (the one the fused pose is on) began at ``began`` (its clock): the poses
        say which map they are in, and this robot's own frame among the fleet map's is the one found
        for it (agent/peers.py)."""
        self.map_began = began
        self.peers.began = began

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
                eStop=(self.estop_source if self.estop_source is not EStop.NONE else EStop.REMOTE)
                if self.pilot.estop
                else EStop.NONE,
                fieldViolation=bool(p.field_violation) if p else False,
            ),
            driveMode=mode.value.lower(),
            links=self.links,
            uwbStale=stale,
            payloadOn=self.board.payload_on,
            boardConnected=self.board.connected,
            orderId=self.itinerary.order_id if self.itinerary is not None else ((p.order_id or "") if p else ""),
            orderUpdateId=self.itinerary.update_id if self.itinerary is not None else self.pilot.order_update_id,
            goal=goal,
            driving=abs(self._velocity[0]) > 1e-3 or abs(self._velocity[1]) > 1e-3,
            paused=mode is PilotMode.PAUSED or (self.itinerary is not None and self.itinerary.waiting == "paused"),
            home=self._home_msg(),
            contact=Contact(
                policy=self.contact.policy,
                lost=self.contact.lost,
                action=self.contact.action,
                silent_s=self.contact.silent_s(now),
            ),
            progress=self._progress(),
        )

    def _home_msg(self) -> Home | None:
        h = self.home.home
        if h is None:
            return None
        theta = None if math.isnan(h.theta) else _clamp_angle(h.theta)
        return Home(x=h.x, y=h.y, theta=theta, source=h.source)

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
            self.home.home,
            self.contact.policy,
            self.contact.lost,
            self.contact.action,
            self._itinerary_key(),
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
            s.home,
            (s.contact.policy, s.contact.lost, s.contact.action),
            None if s.progress is None else (s.progress.nodesDone, s.progress.skipped, s.progress.waiting),
        )


def _payload_params(params: Mapping[str, str]) -> tuple[str, bool, int | None]:
    """(device, on, level) of a ``payload`` action's parameters; ValueError says what is wrong."""
    device = params.get("device", "uv").lower()
    on = params.get("on", "").lower()
    if on not in ("true", "false"):
        raise ValueError("payload needs parameter on=true|false")
    if device not in ("uv", "atomiser", "fan"):
        raise ValueError(f"unknown payload device {device[:32]!r} (uv, atomiser, fan)")
    level: int | None = None
    if "level" in params:
        try:
            level = int(params["level"])
        except ValueError:
            level = -1
        if not 0 <= level <= 3 or device == "uv":
            what = "the lamp has no level" if device == "uv" else f"got {params['level'][:16]!r}"
            raise ValueError(f"{device} level must be 0-3 ({what})")
    return device, on == "true", level


def _stops(msg: Order) -> list[Stop]:
    """An order's nodes as itinerary stops; ItineraryError if the nodes and edges do not form one
    route (VDA 5050: node sequence ids even and consecutive, an edge between each two nodes)."""
    nodes, edges = msg.nodes, msg.edges
    if not nodes:
        raise ItineraryError("an order with edges needs nodes")
    if len(edges) != len(nodes) - 1:
        raise ItineraryError(f"{len(nodes)} nodes need {len(nodes) - 1} edges between them, got {len(edges)}")
    first = nodes[0].sequenceId
    if first % 2:
        raise ItineraryError(f"node {nodes[0].nodeId!r}: node sequence ids are even, got {first}")
    for i, n in enumerate(nodes):
        if n.sequenceId != first + 2 * i:
            raise ItineraryError(f"node {n.nodeId!r}: sequence id {n.sequenceId}, expected {first + 2 * i}")
    ways: list[tuple[tuple[float, float], ...]] = []  # each edge's trajectory, sampled once
    for i, e in enumerate(edges):
        a, b = nodes[i], nodes[i + 1]
        if e.sequenceId != a.sequenceId + 1 or e.startNodeId != a.nodeId or e.endNodeId != b.nodeId:
            raise ItineraryError(
                f"edge {e.edgeId!r} must lead from {a.nodeId!r} to {b.nodeId!r} with sequence id {a.sequenceId + 1}"
            )
        if e.actions:
            raise ItineraryError(f"edge {e.edgeId!r}: edge actions are not supported (put them on its start node)")
        # The way must end at the node it leads to (its start may lie where the robot stood for the
        # node before: the VDA bridge sends a first node reached in place as the robot's position).
        ways.append(_trajectory(e))
        end = ways[i][-1:]
        if end and math.dist(end[0], (b.x, b.y)) > TRAJECTORY_END_M:
            raise ItineraryError(
                f"edge {e.edgeId!r}: its trajectory ends at ({end[0][0]:.2f}, {end[0][1]:.2f}), not at node"
                f" {b.nodeId!r} (within {TRAJECTORY_END_M:g} m)"
            )
        if e.released and not b.released:
            raise ItineraryError(f"edge {e.edgeId!r} is released but leads to a horizon node")
    return [
        Stop(
            n.nodeId,
            n.sequenceId,
            n.x,
            n.y,
            n.theta,
            n.released,
            edges[i - 1].maxSpeed if i > 0 else None,
            tuple(
                StopAction(a.actionId, a.actionType.value, {kv.key: kv.value for kv in a.actionParameters})
                for a in n.actions
            ),
            n.allowedDeviationXY,
            ways[i - 1] if i > 0 else (),
        )
        for i, n in enumerate(nodes)
    ]


def _trajectory(edge: OrderEdge) -> tuple[tuple[float, float], ...]:
    """The edge's trajectory as waypoints (checked whole when the order was decoded), or ()."""
    if edge.trajectory is None:
        return ()
    try:
        return tuple(edge.trajectory.waypoints())
    except ValueError as exc:  # decoded, so checked: kept as a refusal, never a crash
        raise ItineraryError(f"edge {edge.edgeId!r}: trajectory: {exc}") from None


def _within(v: float | None, lo: float, hi: float) -> float | None:
    """A board reading the wire can carry, or nil (a NaN or an impossible value is no reading)."""
    return v if v is not None and math.isfinite(v) and lo <= v <= hi else None


def _sd(v: float) -> float:
    return v if math.isfinite(v) and 0.0 <= v < UNKNOWN_SD else UNKNOWN_SD


def _clamp_angle(a: float) -> float:
    a = (a + math.pi) % (2 * math.pi) - math.pi
    return min(3.2, max(-3.2, a))
