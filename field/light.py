"""Light robots: hundreds of simulated robots that speak the real wire contract without full agents.

A light robot publishes what an agent publishes for the consoles (``Pose`` at 20 Hz, ``State`` at
1 Hz, ``Lease`` with each state and on change, ``Ack`` for every command addressed to it), encoded
with the one codec (shared/wire.py) on the real keys (shared/keys.py), so a console, the recorder
and the network carry exactly the load that many agents would put on them. What it does not have
is everything behind the telemetry: no board, no lidar, no fusion, no guard. It accepts a teleop
(drives at the commanded speed until the teleop's time-to-live lapses), an order (drives straight
to its goal, its last node, or home), instant actions (stop, cancel, pause, resume, e-stop and its
release; the rest accepted and ignored) and lease requests, and acks each copy of a command on the
link it came on (a copy already run is acked ``duplicate``, as the agent's gate does).

``LightFleet`` is the pure core: no I/O, no thread, time passed in (``now``: the clock's monotonic
seconds; ``wall``: its epoch seconds, for headers). ``due(now, wall)`` moves the robots whose
messages are due and returns them as (key, payload); ``command(link, key, payload, now, wall)``
takes one inbound message and returns what to publish in answer. The robots' deadlines are
spread evenly over a period (robot *i* of *n* publishes ``i/n`` of a period after robot 0), as
independent robots would, and a header carries the time its message was *due*, so a simulator
that falls behind shows as staleness at the console instead of hiding it; deadlines more than a
period behind are skipped (and counted in ``stats.skipped``), never published in a burst.

field/light_runner.py is the shell: one worker publishes the whole fleet through the link layer.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

from fleetlink.shared import keys, wire
from fleetlink.shared.messages import (
    Ack,
    AckResult,
    ActionType,
    AgvPosition,
    BatteryState,
    CommsPolicy,
    Contact,
    EStop,
    Goal,
    InstantActions,
    Lease,
    LeaseRequest,
    LinkName,
    LinkStatus,
    OperatingMode,
    Order,
    Pose,
    SafetyState,
    State,
    Teleop,
    Velocity,
    ack_fields,
)

__all__ = ["COMMAND_TOPICS", "LightFleet", "LightSettings", "LightStats", "light_names"]

COMMAND_TOPICS = (Teleop.TOPIC, Order.TOPIC, InstantActions.TOPIC, LeaseRequest.TOPIC)
"""What a light robot listens to (each under ``fleetlink/v1/<robot>/<topic>/<sender>``)."""

ALWAYS_ALLOWED = frozenset({ActionType.STOP, ActionType.CANCEL, ActionType.ESTOP, ActionType.PAUSE})
"""Instant actions anyone may send without the lease (as agent/lease.py)."""

DRIVE_LEASE_S = 15.0
"""Driving a free robot takes its lease for this long (as agent/lease.py)."""

MAX_SEEN = 256
"""Commands remembered per robot to ack a second copy as a duplicate."""


def light_names(n: int, prefix: str = "L") -> list[str]:
    """``L0000``, ``L0001``, ...: ``n`` robot ids, zero-padded to at least four digits."""
    width = max(4, len(str(max(0, n - 1))))
    return [f"{prefix}{i:0{width}d}" for i in range(n)]


@dataclass(frozen=True, slots=True)
class LightSettings:
    pose_hz: float = 20.0
    state_hz: float = 1.0
    max_speed_mps: float = 1.0
    max_omega_rps: float = 2.0
    arrive_m: float = 0.05
    spacing_m: float = 2.0
    """Robots start on a square grid this far apart, facing +x."""
    columns: int = 25

    def __post_init__(self) -> None:
        if not (0 < self.pose_hz <= 200 and 0 < self.state_hz <= self.pose_hz):
            raise ValueError(f"rates: 0 < state_hz <= pose_hz <= 200, got {self.state_hz}, {self.pose_hz}")


@dataclass(slots=True)
class LightStats:
    """Counters; read them, never reset them."""

    poses: int = 0
    states: int = 0
    acks: int = 0
    accepted: int = 0
    duplicates: int = 0
    rejected: int = 0
    """Commands acked ``rejected`` (no lease, e-stop latched)."""
    undecodable: int = 0
    """Inbound messages for one of ours that did not decode (no ack: the agent's gate does the same)."""
    skipped: int = 0
    """Deadlines more than a period behind, dropped instead of published late."""
    lag_max_s: float = 0.0
    """The furthest behind its deadline a message was published."""


@dataclass(slots=True)
class _Robot:
    name: str
    x: float
    y: float
    theta: float
    home: tuple[float, float]
    updated: float
    v: float = 0.0
    omega: float = 0.0
    teleop_until: float = -math.inf
    goal: tuple[float, float] | None = None
    order_id: str = ""
    order_update_id: int = 0
    paused: bool = False
    estop: bool = False
    holder: str = ""
    holder_until: float = 0.0
    holder_until_wall: float = 0.0
    ids: dict[str, int] = field(default_factory=dict)
    seen: dict[tuple[str, str, int, float], LinkName] = field(default_factory=dict)

    def next_id(self, topic: str) -> int:
        n = self.ids.get(topic, 0)
        self.ids[topic] = n + 1
        return n


class LightFleet:
    """The light robots of one simulator process. Not thread-safe: its shell serialises calls."""

    def __init__(self, names: list[str], start: float, settings: LightSettings | None = None) -> None:
        self.settings = s = settings or LightSettings()
        self.stats = LightStats()
        self.pose_period = 1.0 / s.pose_hz
        self.state_period = 1.0 / s.state_hz
        self.robots: dict[str, _Robot] = {}
        self._keys: dict[tuple[str, str], str] = {}
        self._queue: list[tuple[float, int, str, str]] = []  # (deadline, tiebreak, robot, topic)
        n = max(1, len(names))
        for i, name in enumerate(names):
            keys.check_robot_id(name)
            x, y = (i % s.columns) * s.spacing_m, (i // s.columns) * s.spacing_m
            self.robots[name] = _Robot(name, x, y, 0.0, (x, y), start)
            heapq.heappush(self._queue, (start + self.pose_period * i / n, 2 * i, name, Pose.TOPIC))
            heapq.heappush(self._queue, (start + self.state_period * i / n, 2 * i + 1, name, State.TOPIC))
        self._tiebreak = 2 * n

    def next_deadline(self) -> float:
        """When ``due`` will next have something to publish."""
        return self._queue[0][0] if self._queue else math.inf

    # -- telemetry -------------------------------------------------------------------------------

    def due(self, now: float, wall: float) -> list[tuple[str, bytes]]:
        """Every message due by ``now``, each stamped with the time it was due."""
        out: list[tuple[str, bytes]] = []
        queue = self._queue
        while queue and queue[0][0] <= now:
            deadline, _, name, topic = heapq.heappop(queue)
            period = self.pose_period if topic == Pose.TOPIC else self.state_period
            lag = now - deadline
            nxt = deadline + period
            if lag > period:  # too far behind: publish the latest deadline passed, skip the rest
                skipped = int(lag // period)
                deadline += skipped * period
                nxt = deadline + period
                if nxt <= now:  # rounding
                    skipped, deadline, nxt = skipped + 1, nxt, nxt + period
                self.stats.skipped += skipped
                lag = now - deadline
            self.stats.lag_max_s = max(self.stats.lag_max_s, lag)
            self._tiebreak += 1
            heapq.heappush(queue, (nxt, self._tiebreak, name, topic))
            robot = self.robots[name]
            self._move(robot, deadline)
            stamp = wall - (now - deadline)
            if topic == Pose.TOPIC:
                out.append(self._pose(robot, stamp))
                self.stats.poses += 1
            else:
                out.append(self._state(robot, deadline, stamp))
                out.append(self._lease(robot, deadline, stamp))
                self.stats.states += 1
        return out

    def _key(self, robot: str, topic: str) -> str:
        k = self._keys.get((robot, topic))
        if k is None:
            k = self._keys[(robot, topic)] = keys.key(robot, topic)
        return k

    def _header(self, robot: _Robot, topic: str, stamp: float) -> wire.Header:
        return wire.Header(
            headerId=robot.next_id(topic),
            timestamp=stamp,
            version=wire.WIRE_VERSION,
            robot=robot.name,
            sender=robot.name,
        )

    def _pose(self, r: _Robot, stamp: float) -> tuple[str, bytes]:
        msg = Pose(
            header=self._header(r, Pose.TOPIC, stamp),
            x=r.x,
            y=r.y,
            theta=r.theta,
            sd_x_m=0.05,
            sd_y_m=0.05,
            sd_theta_rad=0.02,
            odom_x=r.x,
            odom_y=r.y,
            odom_theta=r.theta,
            vx=r.v,
            omega=r.omega,
            uwbStale=False,
        )
        return self._key(r.name, Pose.TOPIC), wire.encode(msg)

    def _state(self, r: _Robot, now: float, stamp: float) -> tuple[str, bytes]:
        teleop = now < r.teleop_until
        if r.estop:
            mode = OperatingMode.SERVICE
        elif teleop:
            mode = OperatingMode.MANUAL
        elif r.goal is not None:
            mode = OperatingMode.AUTOMATIC
        else:
            mode = OperatingMode.SEMIAUTOMATIC
        msg = State(
            header=self._header(r, State.TOPIC, stamp),
            agvPosition=AgvPosition(
                x=r.x, y=r.y, theta=r.theta, mapId="", positionInitialized=True, localizationScore=1.0
            ),
            velocity=Velocity(vx=r.v, omega=r.omega),
            batteryState=BatteryState(batteryCharge=80.0, charging=False),
            errors=(),
            operatingMode=mode,
            safetyState=SafetyState(eStop=EStop.REMOTE if r.estop else EStop.NONE, fieldViolation=False),
            driveMode="teleop" if teleop else ("goto" if r.goal is not None else "idle"),
            links=LinkStatus(zenoh=True, mqtt=False),
            uwbStale=False,
            payloadOn=False,
            boardConnected=True,
            orderId=r.order_id,
            orderUpdateId=r.order_update_id,
            goal=None if r.goal is None else Goal(x=r.goal[0], y=r.goal[1], theta=None),
            driving=r.v != 0.0 or r.omega != 0.0,
            paused=r.paused,
            home=None,
            contact=Contact(policy=CommsPolicy.STOP, lost=False, action="", silent_s=0.0),
        )
        return self._key(r.name, State.TOPIC), wire.encode(msg)

    def _lease(self, r: _Robot, now: float, stamp: float) -> tuple[str, bytes]:
        if r.holder and now >= r.holder_until:
            r.holder, r.holder_until, r.holder_until_wall = "", 0.0, 0.0
        msg = Lease(header=self._header(r, Lease.TOPIC, stamp), holder=r.holder, until=r.holder_until_wall)
        return self._key(r.name, Lease.TOPIC), wire.encode(msg)

    # -- motion ----------------------------------------------------------------------------------

    def _move(self, r: _Robot, now: float) -> None:
        """Move ``r`` from its last update to ``now`` as it was told (a teleop until its time-to-live
        lapses, else straight at its goal, never past it), then set what it is doing now."""
        dt = now - r.updated
        if dt > 0 and not (r.estop or r.paused):
            if r.updated < r.teleop_until:
                span = min(now, r.teleop_until) - r.updated
                theta = r.theta + r.omega * span
                r.theta = math.atan2(math.sin(theta), math.cos(theta))
                r.x += r.v * math.cos(r.theta) * span
                r.y += r.v * math.sin(r.theta) * span
            elif r.goal is not None:
                dx, dy = r.goal[0] - r.x, r.goal[1] - r.y
                dist = math.hypot(dx, dy)
                step = min(dist, self.settings.max_speed_mps * dt)
                if dist > 0:
                    r.theta = math.atan2(dy, dx)
                    r.x += dx / dist * step
                    r.y += dy / dist * step
        r.updated = max(r.updated, now)
        if r.estop or r.paused:
            r.v = r.omega = 0.0
        elif now < r.teleop_until:
            pass  # the teleop's speeds hold until its time-to-live lapses
        elif r.goal is not None and math.hypot(r.goal[0] - r.x, r.goal[1] - r.y) > self.settings.arrive_m:
            r.v, r.omega = self.settings.max_speed_mps, 0.0
        else:
            r.goal, r.v, r.omega = None, 0.0, 0.0

    # -- commands --------------------------------------------------------------------------------

    def command(self, link: LinkName, key: str, payload: bytes, now: float, wall: float) -> list[tuple[str, bytes]]:
        """One inbound message on ``link``: what to publish in answer (its ack, a lease), or nothing
        when it is not for one of ours or does not decode."""
        try:
            robot_id, topic = keys.parse_key(key)
        except ValueError:
            return []
        robot = self.robots.get(robot_id)
        if robot is None or keys.split_sender(topic)[0] not in COMMAND_TOPICS:
            return []
        try:
            msg = wire.decode_key(key, payload)
        except wire.WireError:
            self.stats.undecodable += 1
            return []
        self._move(robot, now)
        h = msg.header
        if isinstance(msg, LeaseRequest):
            self._request_lease(robot, h.sender, msg, now, wall)
            return [self._lease(robot, now, wall)]
        assert isinstance(msg, Teleop | Order | InstantActions)
        ident = (msg.TOPIC, h.sender, h.headerId, h.timestamp)
        first = robot.seen.get(ident)
        if first is not None:
            self.stats.duplicates += 1
            return [self._ack(robot, msg, link, AckResult.DUPLICATE, f"already received on {first.value}", wall)]
        robot.seen[ident] = link
        if len(robot.seen) > MAX_SEEN:
            del robot.seen[next(iter(robot.seen))]
        result, reason = self._run(robot, msg, now, wall)
        if result is AckResult.ACCEPTED:
            self.stats.accepted += 1
        else:
            self.stats.rejected += 1
        out = [self._ack(robot, msg, link, result, reason, wall)]
        if isinstance(msg, Teleop | Order) and result is AckResult.ACCEPTED:
            out.append(self._lease(robot, now, wall))
        return out

    def _request_lease(self, r: _Robot, sender: str, msg: LeaseRequest, now: float, wall: float) -> None:
        if r.holder and now >= r.holder_until:
            r.holder = ""
        if msg.release:
            if r.holder == sender:
                r.holder, r.holder_until, r.holder_until_wall = "", 0.0, 0.0
        elif not r.holder or r.holder == sender:
            r.holder, r.holder_until, r.holder_until_wall = sender, now + msg.duration_s, wall + msg.duration_s

    def _run(self, r: _Robot, msg: Teleop | Order | InstantActions, now: float, wall: float) -> tuple[AckResult, str]:
        sender = msg.header.sender
        if isinstance(msg, InstantActions):
            for action in msg.actions:
                kind = action.actionType
                if kind not in ALWAYS_ALLOWED and r.holder and r.holder != sender and now < r.holder_until:
                    return AckResult.REJECTED, f"control lease held by {r.holder}"
            for action in msg.actions:
                self._action(r, action.actionType)
            return AckResult.ACCEPTED, ""
        if r.holder and r.holder != sender and now < r.holder_until:
            return AckResult.REJECTED, f"control lease held by {r.holder}"
        if r.estop:
            return AckResult.REJECTED, "e-stop latched"
        if not r.holder or now + DRIVE_LEASE_S > r.holder_until:  # driving takes (and renews) the lease
            r.holder, r.holder_until, r.holder_until_wall = sender, now + DRIVE_LEASE_S, wall + DRIVE_LEASE_S
        if isinstance(msg, Teleop):
            r.v = max(-self.settings.max_speed_mps, min(self.settings.max_speed_mps, msg.v))
            r.omega = max(-self.settings.max_omega_rps, min(self.settings.max_omega_rps, msg.omega))
            r.teleop_until = now + msg.ttl_s
            return AckResult.ACCEPTED, ""
        if msg.goal is not None:
            goal: tuple[float, float] | None = (msg.goal.x, msg.goal.y)
        elif msg.nodes:
            goal = (msg.nodes[-1].x, msg.nodes[-1].y)
        elif msg.returnHome:
            goal = r.home
        else:
            return AckResult.REJECTED, "an order needs a goal, nodes or returnHome"
        r.goal, r.order_id, r.order_update_id, r.paused = goal, msg.orderId, msg.orderUpdateId, False
        return AckResult.ACCEPTED, ""

    def _action(self, r: _Robot, kind: ActionType) -> None:
        if kind in (ActionType.STOP, ActionType.CANCEL):
            r.goal, r.teleop_until, r.v, r.omega = None, -math.inf, 0.0, 0.0
        elif kind is ActionType.PAUSE:
            r.paused, r.v, r.omega = True, 0.0, 0.0
        elif kind is ActionType.RESUME:
            r.paused = False
        elif kind is ActionType.ESTOP:
            r.estop, r.goal, r.teleop_until, r.v, r.omega = True, None, -math.inf, 0.0, 0.0
        elif kind is ActionType.ESTOP_RELEASE:
            r.estop = False
        elif kind is ActionType.RETURN_HOME:
            r.goal = r.home

    def _ack(
        self,
        r: _Robot,
        msg: Teleop | Order | InstantActions,
        link: LinkName,
        result: AckResult,
        reason: str,
        wall: float,
    ) -> tuple[str, bytes]:
        fields = ack_fields(msg, link, result, reason)
        self.stats.acks += 1
        return self._key(r.name, Ack.TOPIC), wire.encode(Ack(header=self._header(r, Ack.TOPIC, wall), **fields))
