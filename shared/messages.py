"""Fleetlink messages: every top-level message on the wire, one frozen dataclass each.

Each class derives from ``wire.Message`` (so it carries a ``header``), sets ``TOPIC`` and is
``@register``-ed so ``wire.decode_any``/``wire.decode_key`` can find it. Fields are keyword-only
(``kw_only=True``) so adding one never silently shifts positional arguments. Sequences are tuples
so messages stay immutable and hashable; ``encode`` also accepts lists.

Later issues add their messages here, and a row to the table in docs/wire-contract.md.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Annotated, ClassVar

from .wire import Message, bounded, register, sized

MAX_COORDINATE_M = 100_000.0
"""Every position on the wire (goals, marks, fixes, poses, map origins) lies within this many
metres of its frame's origin: any site fits, and no value that passes decoding can overflow the
planner's or the controller's arithmetic (a goal at 1e308 m used to)."""
Coordinate = Annotated[float, bounded(-MAX_COORDINATE_M, MAX_COORDINATE_M)]

__all__ = [
    "MAX_ACTIONS",
    "MAX_BOARD_ERRORS",
    "MAX_BOARD_SENSORS",
    "MAX_EVENT_DATA",
    "MAX_MAP_CELLS",
    "MAX_MAP_DATA",
    "MAX_MARK_LABEL",
    "MAX_PARAMS",
    "MAX_STATE_ERRORS",
    "MAX_UWB_ANCHORS",
    "Ack",
    "AckResult",
    "Action",
    "ActionType",
    "AgvPosition",
    "BatteryState",
    "BoardStatus",
    "Connection",
    "ConnectionState",
    "EStop",
    "ErrorLevel",
    "Event",
    "FixStatus",
    "Goal",
    "InstantActions",
    "KeyValue",
    "Lease",
    "LeaseRequest",
    "LinkName",
    "LinkStatus",
    "MapEncoding",
    "MapSnapshot",
    "MapUpdate",
    "Mark",
    "OperatingMode",
    "Order",
    "Pose",
    "SafetyState",
    "Severity",
    "State",
    "StateError",
    "Teleop",
    "Truth",
    "UwbFix",
    "UwbRange",
    "UwbRanges",
    "Velocity",
]

MAX_BOARD_ERRORS = 16
MAX_BOARD_SENSORS = 16


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class BoardStatus(Message):
    """The robot agent's view of its control board, published on ``fleetlink/v1/<robot>/board``."""

    TOPIC: ClassVar[str] = "board"

    connected: bool
    """The agent currently has a working link to the board."""
    model: Annotated[str, sized(64)]
    firmware: Annotated[str, sized(64)]
    battery_percent: Annotated[float, bounded(0.0, 100.0)]
    charging: bool
    on_dock: bool
    health_flags: Annotated[int, bounded(0, 255)]
    """Board health bitmap as reported by the firmware (one byte)."""
    errors: Annotated[tuple[str, ...], sized(MAX_BOARD_ERRORS, item=sized(256))]
    """Active error descriptions, at most 16 of at most 256 characters."""
    left_mm: float
    """Cumulative left wheel distance since board start, millimetres (signed)."""
    right_mm: float
    """Cumulative right wheel distance since board start, millimetres (signed)."""
    bumpers: Annotated[int, bounded(0)]
    """Bumper bitmap, bit i set while bumper i is pressed."""
    sensors_m: Annotated[tuple[float, ...], sized(MAX_BOARD_SENSORS, item=bounded(0.0))]
    """Range sensor readings in metres, at most 16, each >= 0."""
    watchdog_tripped: bool
    """The board's motor watchdog has stopped the motors."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Truth(Message):
    """Ground truth about one simulated robot, published by the field on ``fleetlink/v1/sim/<robot>/truth``.

    Only the simulator publishes it; agents must never use it (scoring compares against it).
    """

    TOPIC: ClassVar[str] = "truth"

    sim_time_s: Annotated[float, bounded(0.0)]
    """Simulated seconds since the field started."""
    x: Coordinate
    """Metres, in the plan's frame (the UWB frame)."""
    y: Coordinate
    theta: Annotated[float, bounded(-3.2, 3.2)]
    """Heading, radians, counter-clockwise from +x, in [-pi, pi]."""
    v: float
    """Forward speed over ground, m/s."""
    omega: float
    """Turn rate, rad/s."""
    bumped: bool
    """A bump switch is pressed."""


# --------------------------------------------------------------------------------------------------
# Issue 5: the robot agent's telemetry and commands. VDA 5050 names (camelCase) where VDA has one,
# fleetlink names (snake_case with units) elsewhere. Semantic checks (an order with neither goal nor
# returnHome, unknown action parameters) are the agent's job, answered with a rejected Ack; the
# schema only bounds what may travel.

MAX_STATE_ERRORS = 16
MAX_ACTIONS = 16
MAX_PARAMS = 8
MAX_EVENT_DATA = 16


class OperatingMode(enum.StrEnum):
    """VDA 5050 operatingMode: who is in charge of the robot's motion."""

    AUTOMATIC = "AUTOMATIC"  # following an order (go-to, return home)
    SEMIAUTOMATIC = "SEMIAUTOMATIC"  # idle, accepting orders and actions
    MANUAL = "MANUAL"  # teleop drive
    SERVICE = "SERVICE"  # e-stop latched or board not connected


class EStop(enum.StrEnum):
    """VDA 5050 safetyState.eStop."""

    NONE = "NONE"
    REMOTE = "REMOTE"  # latched by an operator's estop action, until estopRelease
    MANUAL = "MANUAL"  # a button on the robot


class ErrorLevel(enum.StrEnum):
    WARNING = "WARNING"
    FATAL = "FATAL"


class ConnectionState(enum.StrEnum):
    """VDA 5050 connection.connectionState."""

    ONLINE = "ONLINE"
    OFFLINE = "OFFLINE"  # said by the agent itself on a clean shutdown
    CONNECTIONBROKEN = "CONNECTIONBROKEN"  # the MQTT last will, said by the broker


class ActionType(enum.StrEnum):
    STOP = "stop"  # stop now, drop the current order and teleop
    PAUSE = "pause"
    RESUME = "resume"
    CANCEL = "cancel"  # drop the current order
    ESTOP = "estop"  # latch: nothing moves until estopRelease
    ESTOP_RELEASE = "estopRelease"
    RETURN_HOME = "returnHome"
    PAYLOAD = "payload"  # parameter on = "true" | "false"


class AckResult(enum.StrEnum):
    ACCEPTED = "accepted"
    DUPLICATE = "duplicate"  # already executed (same sender+headerId, or same orderId+orderUpdateId)
    REJECTED = "rejected"


class LinkName(enum.StrEnum):
    ZENOH = "zenoh"
    MQTT = "mqtt"


class Severity(enum.StrEnum):
    INFO = "info"
    WARNING = "warning"
    ERROR = "error"


@dataclass(frozen=True, slots=True, kw_only=True)
class KeyValue:
    """One VDA-style key/value pair (action parameters, event data); values are text."""

    key: Annotated[str, sized(32)]
    value: Annotated[str, sized(256)]


@dataclass(frozen=True, slots=True, kw_only=True)
class AgvPosition:
    x: Coordinate
    """Metres, map (UWB) frame."""
    y: Coordinate
    theta: Annotated[float, bounded(-3.2, 3.2)]
    mapId: Annotated[str, sized(64)]
    positionInitialized: bool
    """False until the first accepted UWB fix."""
    localizationScore: Annotated[float, bounded(0.0, 1.0)]


@dataclass(frozen=True, slots=True, kw_only=True)
class Velocity:
    vx: float
    """m/s, forward."""
    omega: float
    """rad/s, counter-clockwise."""


@dataclass(frozen=True, slots=True, kw_only=True)
class BatteryState:
    batteryCharge: Annotated[float, bounded(0.0, 100.0)]
    charging: bool


@dataclass(frozen=True, slots=True, kw_only=True)
class StateError:
    errorType: Annotated[str, sized(64)]
    errorLevel: ErrorLevel
    errorDescription: Annotated[str, sized(256)]


@dataclass(frozen=True, slots=True, kw_only=True)
class SafetyState:
    eStop: EStop
    fieldViolation: bool
    """The collision guard is refusing motion (obstacle, cliff or bump)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class LinkStatus:
    zenoh: bool
    """The Zenoh session is open (commands can arrive on it)."""
    mqtt: bool
    """The MQTT client is connected to its broker."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Goal:
    x: Coordinate
    y: Coordinate
    theta: Annotated[float, bounded(-3.2, 3.2)] | None
    """Final heading in radians, or nil to keep the arrival heading."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class State(Message):
    """The agent's state, on change and at 1 Hz: ``fleetlink/v1/<robot>/state``."""

    TOPIC: ClassVar[str] = "state"

    agvPosition: AgvPosition
    velocity: Velocity
    batteryState: BatteryState
    errors: Annotated[tuple[StateError, ...], sized(MAX_STATE_ERRORS)]
    operatingMode: OperatingMode
    safetyState: SafetyState
    driveMode: Annotated[str, sized(32)]
    """The pilot's mode, e.g. idle, teleop, goto, paused, estop."""
    links: LinkStatus
    uwbStale: bool
    """No usable UWB fix within the sensor timeout."""
    payloadOn: bool
    boardConnected: bool
    orderId: Annotated[str, sized(64)]
    """The current (or last) order, "" if none."""
    orderUpdateId: Annotated[int, bounded(0)]
    goal: Goal | None
    """Where the current order is going, nil when no order is active."""
    driving: bool
    paused: bool


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Pose(Message):
    """The fused pose at 20 Hz: ``fleetlink/v1/<robot>/pose``."""

    TOPIC: ClassVar[str] = "pose"

    x: Coordinate
    """Metres, map (UWB) frame; absorbs UWB corrections."""
    y: Coordinate
    theta: Annotated[float, bounded(-3.2, 3.2)]
    sd_x_m: Annotated[float, bounded(0.0)]
    sd_y_m: Annotated[float, bounded(0.0)]
    sd_theta_rad: Annotated[float, bounded(0.0)]
    odom_x: Coordinate
    """Metres, odometry frame: continuous, never jumps."""
    odom_y: Coordinate
    odom_theta: Annotated[float, bounded(-3.2, 3.2)]
    vx: float
    omega: float
    uwbStale: bool


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Connection(Message):
    """VDA 5050 connection, ``fleetlink/v1/<robot>/connection``: retained on MQTT, last will CONNECTIONBROKEN."""

    TOPIC: ClassVar[str] = "connection"

    connectionState: ConnectionState


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Order(Message):
    """Go to a goal (or home); idempotent on (orderId, orderUpdateId). ``fleetlink/v1/<robot>/order``."""

    TOPIC: ClassVar[str] = "order"

    orderId: Annotated[str, sized(64)]
    orderUpdateId: Annotated[int, bounded(0)]
    goal: Goal | None
    """Where to go; nil only with returnHome."""
    returnHome: bool
    """Go back to where the robot started (goal ignored)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Action:
    actionId: Annotated[str, sized(64)]
    actionType: ActionType
    actionParameters: Annotated[tuple[KeyValue, ...], sized(MAX_PARAMS)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class InstantActions(Message):
    """Instant actions, executed in order on arrival: ``fleetlink/v1/<robot>/actions``."""

    TOPIC: ClassVar[str] = "actions"

    actions: Annotated[tuple[Action, ...], sized(MAX_ACTIONS)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Teleop(Message):
    """Direct drive: ``fleetlink/v1/<robot>/teleop``. The robot stops when ttl_s passes without a fresh one."""

    TOPIC: ClassVar[str] = "teleop"

    v: Annotated[float, bounded(-5.0, 5.0)]
    """m/s, forward (the agent clamps to its limits)."""
    omega: Annotated[float, bounded(-20.0, 20.0)]
    """rad/s."""
    ttl_s: Annotated[float, bounded(0.01, 5.0)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Ack(Message):
    """The agent's answer to one command, on the link it came from: ``fleetlink/v1/<robot>/ack``."""

    TOPIC: ClassVar[str] = "ack"

    commandTopic: Annotated[str, sized(32)]
    """order, actions or teleop."""
    commandSender: Annotated[str, sized(64)]
    commandHeaderId: Annotated[int, bounded(0)]
    orderId: Annotated[str, sized(64)] | None
    orderUpdateId: Annotated[int, bounded(0)] | None
    result: AckResult
    reason: Annotated[str, sized(256)]
    link: LinkName
    """The link the command arrived on (and this ack goes out on)."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Event(Message):
    """Something the operator should see: ``fleetlink/v1/<robot>/events``.

    kinds: guard_refusal, cliff, bump, fault, goal_reached, link_change, board_lost, order, estop, ...
    """

    TOPIC: ClassVar[str] = "events"

    kind: Annotated[str, sized(64)]
    text: Annotated[str, sized(256)]
    severity: Severity
    data: Annotated[tuple[KeyValue, ...], sized(MAX_EVENT_DATA)]


MAX_DIAGNOSTIC_COUNTS = 32


@dataclass(frozen=True, slots=True, kw_only=True)
class Count:
    """One counter: what (``<link>/<topic>`` or ``<link>``) and how many so far."""

    key: Annotated[str, sized(64)]
    count: Annotated[int, bounded(0)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Diagnostics(Message):
    """What the agent refused or lost, so far, every ``DIAGNOSTICS_PERIOD_S`` (the agent) while
    anything counts: ``fleetlink/v1/<robot>/diagnostics``. Counts only grow (since the process
    started); a reader diffs two of them for a rate."""

    TOPIC: ClassVar[str] = "diagnostics"

    rejected: Annotated[tuple[Count, ...], sized(MAX_DIAGNOSTIC_COUNTS)]
    """Inputs refused, per ``<link>/<topic>`` (malformed, out of range, not an input, ...)."""
    duplicates: Annotated[int, bounded(0)]
    """Commands that came again (the other link, a retry): answered, not run twice."""
    handler_failures: Annotated[int, bounded(0)]
    """Commands whose handling raised: refused and the robot stopped."""
    oversized: Annotated[tuple[Count, ...], sized(MAX_DIAGNOSTIC_COUNTS)]
    """Per link: messages over the wire limit, refused before they were read."""
    dropped: Annotated[tuple[Count, ...], sized(MAX_DIAGNOSTIC_COUNTS)]
    """Per link: messages not delivered (inbox full) or not sent (link down)."""
    last_reason: Annotated[str, sized(256)]
    """Why the latest input was refused."""


# --------------------------------------------------------------------------------------------------
# Issue 4: UWB positioning. The gateway (``fleetlink uwb``) publishes these over MQTT (and they are
# valid on Zenoh too): one fix per tag per update, and optionally the raw ranges behind it.

MAX_UWB_ANCHORS = 32


class FixStatus(enum.StrEnum):
    """Outcome of one multilateration. Only ``ok`` fixes carry a usable position."""

    OK = "ok"
    TOO_FEW_RANGES = "too_few_ranges"  # fewer than 3 usable ranges
    DEGENERATE_GEOMETRY = "degenerate_geometry"  # anchors (nearly) collinear: mirror ambiguity
    DIVERGED = "diverged"  # no convergence, or a solution far outside the anchors


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class UwbFix(Message):
    """One UWB position fix of a robot's tag: ``fleetlink/v1/<robot>/uwb``.

    Position in the plan's frame (metres); ``z`` is the tag's known height. ``measured_at`` is the
    instant the ranges were taken (sender's ``Clock.wall()``), so a receiver can place a late fix
    in its history; ``header.timestamp`` is when the fix was published.
    """

    TOPIC: ClassVar[str] = "uwb"

    tag: Annotated[str, sized(64)]
    x: Coordinate
    y: Coordinate
    z: Coordinate
    sd_x: Annotated[float, bounded(0.0)]
    """Standard deviation of x, metres (from the solver's covariance)."""
    sd_y: Annotated[float, bounded(0.0)]
    quality: Annotated[int, bounded(0, 100)]
    """0-100 %, PANS style: 100 when sd <= 0.1 m, falling as 1/sd, times the inlier share."""
    status: FixStatus
    anchors: Annotated[tuple[str, ...], sized(MAX_UWB_ANCHORS, item=sized(64))]
    """Ids of the anchors whose ranges the fix used (after robust down-weighting, weight >= 0.5)."""
    residual_rms_m: Annotated[float, bounded(0.0)]
    measured_at: Annotated[float, bounded(0.0)]
    """Seconds since the Unix epoch (sender's clock) when the ranges were measured."""


@dataclass(frozen=True, slots=True, kw_only=True)
class UwbRange:
    """One two-way-ranging measurement between a tag and an anchor."""

    anchor: Annotated[str, sized(64)]
    distance_m: Annotated[float, bounded(0.0)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class UwbRanges(Message):
    """The raw ranges behind one fix: ``fleetlink/v1/<robot>/uwb/ranges`` (for tighter fusion)."""

    TOPIC: ClassVar[str] = "uwb/ranges"

    tag: Annotated[str, sized(64)]
    ranges: Annotated[tuple[UwbRange, ...], sized(MAX_UWB_ANCHORS)]
    measured_at: Annotated[float, bounded(0.0)]


# --------------------------------------------------------------------------------------------------
# Issue 7: the operator console. Control leases (who may drive a robot; the robot's agent is the
# authority, see agent/lease.py) and marks shared between consoles.

MAX_MARK_LABEL = 64


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class LeaseRequest(Message):
    """An operator asks for (or renews, or gives back) control of a robot: ``fleetlink/v1/<robot>/lease/request``.

    The requester is ``header.sender``. The robot answers with ``Lease``.
    """

    TOPIC: ClassVar[str] = "lease/request"

    duration_s: Annotated[float, bounded(0.0, 3600.0)]
    """How long the lease should last from now; 0 with ``release``."""
    release: bool
    """Give the lease back (only the holder can)."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Lease(Message):
    """Who controls a robot, published by its agent on change and at 1 Hz: ``fleetlink/v1/<robot>/lease``."""

    TOPIC: ClassVar[str] = "lease"

    holder: Annotated[str, sized(64)]
    """Sender id of the operator who may drive the robot, "" when nobody holds it."""
    until: Annotated[float, bounded(0.0)]
    """Seconds since the Unix epoch (robot's clock) when the lease runs out; 0 when nobody holds it."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Mark(Message):
    """A point of interest an operator marked (a casualty, a hazard): ``fleetlink/v1/<robot>/marks``.

    ``header.robot`` is the robot the operator was working with when marking; every console
    subscribes to ``fleetlink/v1/*/marks``. A mark is identified by ``markId``; the latest
    ``header.timestamp`` wins, and ``removed`` deletes it.
    """

    TOPIC: ClassVar[str] = "marks"

    markId: Annotated[str, sized(64)]
    x: Coordinate
    """Metres, map (UWB) frame."""
    y: Coordinate
    label: Annotated[str, sized(MAX_MARK_LABEL)]
    kind: Annotated[str, sized(32)]
    """casualty, hazard, note, ..."""
    removed: bool


# -- onboard maps (docs/mapping.md) ------------------------------------------------------------

MAX_MAP_DATA = 240 * 1024
"""Compressed cells per message, bytes (leaves room for the fields under wire.MAX_PAYLOAD)."""
MAX_MAP_CELLS = 16_000_000
"""width * height of a whole map (e.g. 200 m x 200 m at 5 cm)."""


class MapEncoding(enum.StrEnum):
    ZLIB_INT8 = "zlib-int8"
    """zlib (RFC 1950) over the int8 cells, row-major, row 0 at the bottom."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class MapSnapshot(Message):
    """A robot's whole occupancy map, the reply of the queryable ``fleetlink/v1/<robot>/map``.

    ``cells`` is the zlib-compressed int8 grid (row-major, row 0 at ``origin_y``, the bottom):
    -1 unknown, 0-100 occupancy percent, as a ROS OccupancyGrid / map_server.
    """

    TOPIC: ClassVar[str] = "map"

    version: Annotated[int, bounded(0)]
    """+1 per scan integrated into the map; a restarted agent starts again from 0."""
    resolution: Annotated[float, bounded(0.001, 10.0)]
    """Metres per cell."""
    origin_x: Coordinate
    """Metres, map (UWB) frame: the lower-left corner of cell (0, 0); the map is not rotated."""
    origin_y: Coordinate
    width: Annotated[int, bounded(0, 65_535)]
    height: Annotated[int, bounded(0, 65_535)]
    encoding: MapEncoding
    cells: Annotated[bytes, sized(MAX_MAP_DATA)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class MapUpdate(Message):
    """What changed in a robot's map, on ``fleetlink/v1/<robot>/map/updates``: one rectangle of cells.

    Apply it to a copy at ``base_version`` with the same ``resolution``/``origin``/size to get
    ``version``; otherwise (a gap, or the map grew) fetch a ``MapSnapshot`` from the queryable.
    Cross-field rules (the patch inside the map, the cells' size) are checked where the cells are
    decoded (``shared/map_codec.py``).
    """

    TOPIC: ClassVar[str] = "map/updates"

    version: Annotated[int, bounded(0)]
    base_version: Annotated[int, bounded(0)]
    resolution: Annotated[float, bounded(0.001, 10.0)]
    origin_x: Coordinate
    origin_y: Coordinate
    width: Annotated[int, bounded(0, 65_535)]
    """Size of the whole map after the update."""
    height: Annotated[int, bounded(0, 65_535)]
    col: Annotated[int, bounded(0, 65_535)]
    """The patch: lower-left cell (col, row) and its size."""
    row: Annotated[int, bounded(0, 65_535)]
    patch_width: Annotated[int, bounded(0, 65_535)]
    patch_height: Annotated[int, bounded(0, 65_535)]
    encoding: MapEncoding
    cells: Annotated[bytes, sized(MAX_MAP_DATA)]
