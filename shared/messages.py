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
from typing import Annotated, Any, ClassVar, Final

from . import nurbs
from .wire import Message, bounded, register, sized

MAX_COORDINATE_M = 100_000.0
"""Every position on the wire (goals, marks, fixes, poses, map origins) lies within this many
metres of its frame's origin: any site fits, and no value that passes decoding can overflow the
planner's or the controller's arithmetic (a goal at 1e308 m used to)."""
Coordinate = Annotated[float, bounded(-MAX_COORDINATE_M, MAX_COORDINATE_M)]

__all__ = [
    "MAX_ACTIONS",
    "MAX_ALARM_ACKS",
    "MAX_BOARD_ERRORS",
    "MAX_BOARD_SENSORS",
    "MAX_DOSE_CELLS",
    "MAX_DOSE_DATA",
    "MAX_DOSE_J_M2",
    "MAX_EVENT_DATA",
    "MAX_FRAMED_ROBOTS",
    "MAX_MAP_CELLS",
    "MAX_MAP_DATA",
    "MAX_MARK_LABEL",
    "MAX_MARK_SET",
    "MAX_ORDER_NODES",
    "MAX_PARAMS",
    "MAX_SCAN_BEAMS",
    "MAX_STATE_ERRORS",
    "MAX_TRAJECTORY_POINTS",
    "MAX_UWB_ANCHORS",
    "TRAJECTORY_END_M",
    "UNKNOWN_SD_M",
    "Ack",
    "AckResult",
    "AckedAlarm",
    "Action",
    "ActionType",
    "AgvPosition",
    "AlarmAck",
    "BatteryState",
    "BlockingType",
    "BoardFault",
    "BoardStatus",
    "CommsPolicy",
    "Connection",
    "ConnectionState",
    "Contact",
    "ControlPoint",
    "DoseEncoding",
    "DoseLamp",
    "DoseSnapshot",
    "DoseUpdate",
    "EStop",
    "ErrorLevel",
    "Event",
    "FixStatus",
    "FleetFrames",
    "Goal",
    "Home",
    "HomeSource",
    "InstantActions",
    "KeyValue",
    "Lease",
    "LeaseRequest",
    "LinkName",
    "LinkStatus",
    "MapEncoding",
    "MapSnapshot",
    "MapSubmap",
    "MapSubmaps",
    "MapUpdate",
    "Mark",
    "MarkEntry",
    "MarkSet",
    "OperatingMode",
    "Order",
    "OrderEdge",
    "OrderNode",
    "OrderProgress",
    "PeopleZones",
    "Pose",
    "RobotFrame",
    "SafetyState",
    "Scan",
    "Severity",
    "State",
    "StateError",
    "SubmapEntry",
    "Teleop",
    "Trajectory",
    "Truth",
    "UwbFix",
    "UwbRange",
    "UwbRanges",
    "Velocity",
    "Zone",
    "ZonePoint",
    "ack_fields",
    "same_map",
]

MAX_BOARD_ERRORS = 16
MAX_BOARD_SENSORS = 16


@dataclass(frozen=True, slots=True, kw_only=True)
class BoardFault:
    """One active board fault: the firmware's code and its text."""

    code: Annotated[int, bounded(0, 65_535)]
    text: Annotated[str, sized(64)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class BoardStatus(Message):
    """The robot agent's view of its control board, published on ``fleetlink/v1/<robot>/board`` at
    1 Hz and at once when something an operator acts on changes (a fault, the payload, the tank,
    charging, the e-stop button, the link to the board). A reading the board does not give (a
    plain SLAMTEC base has no environment sensors) is nil."""

    TOPIC: ClassVar[str] = "board"

    connected: bool
    """The agent currently has a working link to the board."""
    model: Annotated[str, sized(64)]
    firmware: Annotated[str, sized(64)]
    battery_percent: Annotated[float, bounded(0.0, 100.0)]
    battery_voltage_v: Annotated[float, bounded(0.0, 1000.0)] | None
    battery_current_a: Annotated[float, bounded(-1000.0, 1000.0)] | None
    """Positive while charging."""
    charging: bool
    on_dock: bool
    temperature_c: Annotated[float, bounded(-100.0, 200.0)] | None
    humidity_percent: Annotated[float, bounded(0.0, 100.0)] | None
    pm2_5_ug_m3: Annotated[float, bounded(0.0)] | None
    tvoc_ppb: Annotated[int, bounded(0)] | None
    uv_lamp: bool
    atomiser_level: Annotated[int, bounded(0, 3)]
    fan_level: Annotated[int, bounded(0, 3)]
    """The HEPA fan, 0 (off) - 3."""
    has_payload: bool
    """The board has the disinfection payload (lamp, atomiser, fan, tank): a plain base has not."""
    tank_percent: Annotated[float, bounded(0.0, 100.0)] | None
    """Disinfectant left in the tank, nil for a board without one."""
    estop_button: bool
    """The emergency-stop button on the robot is pressed."""
    health_flags: Annotated[int, bounded(0, 255)]
    """Board health bitmap as reported by the firmware (one byte)."""
    faults: Annotated[tuple[BoardFault, ...], sized(MAX_BOARD_ERRORS)]
    """The board's active faults; a fault the agent cleared (``clear_error``) leaves the list."""
    bumpers: Annotated[int, bounded(0)]
    """Bumper and cliff bitmap (bits 0-1 bumpers, 2-3 cliffs), bit set while triggered."""
    sensors_m: Annotated[tuple[float, ...], sized(MAX_BOARD_SENSORS, item=bounded(0.0))]
    """Range sensor readings in metres, at most 16, each >= 0."""
    watchdog_trips: Annotated[int, bounded(0)]
    """Times the board's link watchdog stopped the motors since the agent started."""


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
MAX_ORDER_NODES = 512
"""Nodes (and edges) in one order: a coverage round of a large room is a few dozen dwell points or
a few hundred sweep lane ends (office room-8's sweep on a crisp map: 272). A node and its edge
without actions encode in ~170 bytes: 512 of them ~87 KB, a third of ``wire.MAX_PAYLOAD``."""
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
    SET_HOME = "setHome"  # parameters x, y [, theta_deg] (metres, site frame); none: the current pose
    SET_COMMS_POLICY = "setCommsPolicy"  # parameter policy = "stop" | "retrace" | "home"
    DWELL = "dwell"  # a node action only: stand at the node for parameter duration (seconds)


class BlockingType(enum.StrEnum):
    """VDA 5050 blockingType of an action at a node: NONE runs while the robot drives on, SOFT
    lets other actions run but not driving, HARD runs alone (fleetlink runs a node's actions one
    after another and drives on when the last has finished, so SOFT and HARD behave alike)."""

    NONE = "NONE"
    SOFT = "SOFT"
    HARD = "HARD"


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


class HomeSource(enum.StrEnum):
    """Where a robot's home came from (docs/motion.md, "Home")."""

    LOCALISED = "localised"  # where it first localised in the site frame
    DOCK = "dock"  # the dock pose in its configuration
    OPERATOR = "operator"  # set by an operator (setHome)


@dataclass(frozen=True, slots=True, kw_only=True)
class Home:
    x: Coordinate
    """Metres, site (UWB) frame."""
    y: Coordinate
    theta: Annotated[float, bounded(-3.2, 3.2)] | None
    """Radians, or nil: arrive with any heading."""
    source: HomeSource


class CommsPolicy(enum.StrEnum):
    """What a robot does when it stops hearing its operators (docs/motion.md, "Comms loss")."""

    STOP = "stop"  # stop where it is
    RETRACE = "retrace"  # drive back along its own path to where it last heard an operator, and wait
    HOME = "home"  # return home


@dataclass(frozen=True, slots=True, kw_only=True)
class Contact:
    """The robot's contact with its operators."""

    policy: CommsPolicy
    lost: bool
    """No operator heard within the comms timeout while someone held the lease."""
    action: Annotated[str, sized(32)]
    """What the policy is doing: "" in contact, then stopped, retracing, waiting or homing."""
    silent_s: Annotated[float, bounded(0.0)]
    """Seconds since the robot last heard an operator (0 when it never has)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class OrderProgress:
    """How far the robot is along an order with nodes (VDA 5050 lastNodeId/lastNodeSequenceId, and
    what an operator asks: how many nodes are left, how long the dwell still runs)."""

    nodesTotal: Annotated[int, bounded(0)]
    nodesDone: Annotated[int, bounded(0)]
    """Nodes reached (their actions done) or skipped."""
    skipped: Annotated[int, bounded(0)]
    """Nodes the robot could not reach (no way there): passed over, named in an ``order`` event."""
    lastNodeId: Annotated[str, sized(64)]
    """The last node reached, "" before the first."""
    lastNodeSequenceId: Annotated[int, bounded(0)]
    dwellLeft_s: Annotated[float, bounded(0.0)]
    """Seconds the robot will still stand at the current node (0 while driving)."""
    waiting: Annotated[str, sized(64)]
    """"" while the order runs; else why it waits for a resume: paused, e-stop, stopped, teleop."""


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
    home: Home | None
    """The robot's home (where return home goes), nil until it is known."""
    contact: Contact
    progress: OrderProgress | None = None
    """Along the current order with nodes; nil without one."""


UNKNOWN_SD_M: Final = 1000.0
"""What a ``Pose``'s standard deviations say when they are not known (the wire has no inf): the
robot is not placed in the site frame."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Pose(Message):
    """The fused pose at 20 Hz: ``fleetlink/v1/<robot>/pose``. Its ``sd_x_m`` / ``sd_y_m`` are
    ``UNKNOWN_SD_M`` while the robot has no position in the site frame (no UWB yet, or none on the
    site): ``x``, ``y``, ``theta`` are then in its own map's frame, which begins where it started."""

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
    map_began: Annotated[float, bounded(0.0)] = 0.0
    """When the map that ``x``, ``y``, ``theta`` are in began (``MapSubmaps.began``, the agent's clock);
    0 before the agent's map has begun (no lidar, or no turn mapped yet). A robot in its own frame
    whose agent restarted begins a new map, in a new frame: a ``RobotFrame`` found for the old one
    (its ``began``) no longer places it."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Connection(Message):
    """VDA 5050 connection, ``fleetlink/v1/<robot>/connection``: retained on MQTT, last will CONNECTIONBROKEN."""

    TOPIC: ClassVar[str] = "connection"

    connectionState: ConnectionState


@dataclass(frozen=True, slots=True, kw_only=True)
class Action:
    actionId: Annotated[str, sized(64)]
    actionType: ActionType
    actionParameters: Annotated[tuple[KeyValue, ...], sized(MAX_PARAMS)]
    blockingType: BlockingType = BlockingType.HARD
    """At a node: whether the robot may drive on while it runs (instant actions run at once)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class OrderNode:
    """A VDA 5050 node: a place the robot drives to, and the actions it runs there in order."""

    nodeId: Annotated[str, sized(64)]
    sequenceId: Annotated[int, bounded(0)]
    """Even, from 0, +2 from one node to the next (edges take the odd numbers between)."""
    released: bool
    """Base (true) or horizon (false): the robot drives to released nodes only."""
    x: Coordinate
    y: Coordinate
    theta: Annotated[float, bounded(-3.2, 3.2)] | None
    """Heading to arrive with, radians; nil: any."""
    actions: Annotated[tuple[Action, ...], sized(MAX_ACTIONS)] = ()
    allowedDeviationXY: Annotated[float, bounded(0.0, 1.0)] = 0.0
    """m (VDA 5050 ``nodePosition.allowedDeviationXY``): when (x, y) itself cannot be reached (the
    robot's map of the moment puts it inside a wall's margin), the nearest place within this that
    can is; 0: (x, y) or nothing."""


MAX_TRAJECTORY_POINTS = 64
"""Control points of one edge's trajectory (VDA 5050 factsheet ``maxArrayLens.trajectory.controlPoints``)."""
TRAJECTORY_END_M = 0.05
"""An edge's trajectory starts at its start node and ends at its end node (VDA 5050: the control
points "explicitly including the start and end point"), each within this."""


@dataclass(frozen=True, slots=True, kw_only=True)
class ControlPoint:
    x: Coordinate
    """Metres, site frame."""
    y: Coordinate
    weight: Annotated[float, bounded(0.0, 1.0e6)] = 1.0
    """How hard it pulls on the curve (VDA 5050: >= 0, default 1)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Trajectory:
    """VDA 5050 ``edge.trajectory``: the way from the edge's start node to its end node as a NURBS
    curve (shared/nurbs.py). A route planned on the fleet's merged map is a polyline: degree 1, its
    corners as control points, ``nurbs.polyline_knots``. Checked whole on decode: sizes, knots in
    [0, 1] and never decreasing, weights that leave the curve defined."""

    degree: Annotated[int, bounded(1, nurbs.MAX_DEGREE)]
    knotVector: Annotated[
        tuple[float, ...], sized(MAX_TRAJECTORY_POINTS + nurbs.MAX_DEGREE + 1, item=bounded(0.0, 1.0))
    ]
    controlPoints: Annotated[tuple[ControlPoint, ...], sized(MAX_TRAJECTORY_POINTS)]

    def __post_init__(self) -> None:
        nurbs.check(
            self.degree,
            self.knotVector,
            [(p.x, p.y) for p in self.controlPoints],
            [p.weight for p in self.controlPoints],
        )

    @classmethod
    def polyline(cls, points: tuple[tuple[float, float], ...]) -> Trajectory:
        """``points`` (at least two) as a degree-1 trajectory through them."""
        return cls(
            degree=1,
            knotVector=nurbs.polyline_knots(points),
            controlPoints=tuple(ControlPoint(x=float(x), y=float(y)) for x, y in points),
        )

    def waypoints(self) -> list[tuple[float, float]]:
        """The curve as waypoints (``nurbs.waypoints``), start to end."""
        return nurbs.waypoints(
            self.degree,
            self.knotVector,
            [(p.x, p.y) for p in self.controlPoints],
            [p.weight for p in self.controlPoints],
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class OrderEdge:
    """A VDA 5050 edge between two consecutive nodes: the robot follows its trajectory when it has
    one (and its own map does not bar it), else plans its own way."""

    edgeId: Annotated[str, sized(64)]
    sequenceId: Annotated[int, bounded(0)]
    startNodeId: Annotated[str, sized(64)]
    endNodeId: Annotated[str, sized(64)]
    released: bool
    maxSpeed: Annotated[float, bounded(0.01, 5.0)] | None = None
    """m/s on this edge (a sweep lane, a lamp pass at constant speed); nil: the robot's own limit."""
    actions: Annotated[tuple[Action, ...], sized(MAX_ACTIONS)] = ()
    trajectory: Trajectory | None = None
    """The way to drive (VDA 5050 ``trajectory``); nil: the robot plans its own."""


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
    nodes: Annotated[tuple[OrderNode, ...], sized(MAX_ORDER_NODES)] = ()
    """A route (VDA 5050 nodes, goal nil): driven node by node, each node's actions run there."""
    edges: Annotated[tuple[OrderEdge, ...], sized(MAX_ORDER_NODES)] = ()
    """One edge between each two consecutive nodes."""


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


def ack_fields(
    command: Order | InstantActions | Teleop, link: LinkName, result: AckResult, reason: str = ""
) -> dict[str, Any]:
    """The fields of the ``Ack`` answering ``command`` on ``link`` (stamp them with a header:
    ``HeaderCounter.make(Ack, **fields)``): what an agent and a light robot both send."""
    order = command if isinstance(command, Order) else None
    return {
        "commandTopic": command.TOPIC,
        "commandSender": command.header.sender,
        "commandHeaderId": command.header.headerId,
        "orderId": order.orderId if order else None,
        "orderUpdateId": order.orderUpdateId if order else None,
        "result": result,
        "reason": reason[:256],
        "link": link,
    }


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
MAX_MARK_SET = 256
"""Marks in one ``MarkSet`` (worst case, every text at its limit in 4-byte characters: 183 KiB
encoded, under ``wire.MAX_PAYLOAD``)."""


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
    sd_m: Annotated[float, bounded(0.0, 1000.0)]
    """The position's uncertainty (one standard deviation, metres): the robot's fused pose
    uncertainty for a mark placed at a robot, 0 for typed coordinates."""
    removed: bool


@dataclass(frozen=True, slots=True, kw_only=True)
class MarkEntry:
    """One mark in a ``MarkSet``: a ``Mark``'s fields and its version's ``header.timestamp``; the
    author and the robot are the set's ``header.sender`` and ``header.robot``."""

    markId: Annotated[str, sized(64)]
    x: Coordinate
    y: Coordinate
    label: Annotated[str, sized(MAX_MARK_LABEL)]
    kind: Annotated[str, sized(32)]
    sd_m: Annotated[float, bounded(0.0, 1000.0)]
    removed: bool
    timestamp: Annotated[float, bounded(0.0)]
    """Seconds since the Unix epoch: the ``header.timestamp`` of the ``Mark`` this entry is."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class MarkSet(Message):
    """Every mark whose latest version ``header.sender`` wrote under ``header.robot``, removed
    ones (tombstones) included: ``fleetlink/v1/<robot>/marks/set/<sender>``, published by each
    console retained on MQTT (QoS 1) whenever that set changes and after every connect, so a
    console that starts late -- or restarts -- gets every mark from the broker even with Zenoh
    down. Receivers merge each entry like a ``Mark`` (by ``markId``, newest timestamp wins). At
    ``MAX_MARK_SET`` the publisher leaves out the oldest tombstones first, then the oldest marks."""

    TOPIC: ClassVar[str] = "marks/set"

    marks: Annotated[tuple[MarkEntry, ...], sized(MAX_MARK_SET)]


MAX_ALARM_ACKS = 16
"""Acknowledgements in one ``AlarmAck``: at most one per alarm kind (docs/console.md, "Alarms")."""


@dataclass(frozen=True, slots=True, kw_only=True)
class AckedAlarm:
    """One acknowledged alarm episode: the alarm ``kind`` on the message's robot, the episode that
    began at ``since``, acknowledged at ``at``."""

    kind: Annotated[str, sized(32)]
    """low_battery, robot_lost, board_fault, cliff, bump, estop, link_lost, tank_low, localisation
    (operator/alarms.py ``AlarmKind``); a console refuses a kind it does not know."""
    since: Annotated[float, bounded(0.0)]
    """When the episode began, seconds since the Unix epoch: the ``header.timestamp`` of the robot's
    message that first showed it, or the acknowledging console's clock for what only a console sees
    (robot_lost, its own link_lost). A console applies it to its current episode of the alarm if
    ``since`` is later than the last time it saw the alarm off."""
    at: Annotated[float, bounded(0.0)]
    """When the operator acknowledged it, seconds since the Unix epoch (the console's clock)."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class AlarmAck(Message):
    """Every alarm on ``header.robot`` that ``header.sender`` acknowledged and whose episode is still
    on at that console: ``fleetlink/v1/<robot>/alarms/ack/<sender>``, published by the acknowledging
    console on both links whenever that list changes, retained on MQTT (QoS 1), so a console that
    starts late learns earlier acknowledgements from the broker even with Zenoh down. Retained per
    (robot, login), each message carries the whole list; an empty list withdraws them all."""

    TOPIC: ClassVar[str] = "alarms/ack"

    acks: Annotated[tuple[AckedAlarm, ...], sized(MAX_ALARM_ACKS)]
    """At most one per kind (a console refuses a list that names a kind twice)."""


# -- people-present zones (issue 16, docs/payload.md) ------------------------------------------

MAX_ZONES = 16
MAX_ZONE_VERTICES = 32


@dataclass(frozen=True, slots=True, kw_only=True)
class ZonePoint:
    x: Coordinate
    """Metres, site (UWB) frame."""
    y: Coordinate


@dataclass(frozen=True, slots=True, kw_only=True)
class Zone:
    name: Annotated[str, sized(32)]
    polygon: Annotated[tuple[ZonePoint, ...], sized(MAX_ZONE_VERTICES)]
    """At least three corners (the agent refuses fewer), in order around the zone."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class PeopleZones(Message):
    """The areas an operator declared "people present" (no UV light may reach into them), sent by
    the console to every robot: ``fleetlink/v1/<robot>/zones/<sender>``, on both links, retained on
    MQTT (QoS 1). Each message carries that operator's whole list; an empty one withdraws them."""

    TOPIC: ClassVar[str] = "zones"

    zones: Annotated[tuple[Zone, ...], sized(MAX_ZONES)]


# -- onboard maps (docs/mapping.md) ------------------------------------------------------------

# -- lidar scans (docs/wire-contract.md "scan") ---------------------------------------------------

MAX_SCAN_BEAMS = 2048
"""Beams of one ``Scan`` (an RPLIDAR A1 gives 360-1450 samples a turn; the agent sends 360)."""


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class Scan(Message):
    """A robot's latest lidar turn, on ``fleetlink/v1/<robot>/scan`` (Zenoh only, at most
    ``[rates] scan_hz`` a second): what consoles and ``fleetlink foxglove`` draw over the map.

    ``count`` beams at equal steps of ``2 pi / count`` counter-clockwise from ``start_angle``
    (radians from the robot's heading), each the nearest return in its step; taken at the fused pose
    (``x``, ``y``, ``theta``, the site frame as ``Pose``'s) at the turn's start, as the map takes it.
    ``ranges``: ``count`` little-endian uint16 millimetres, 0 for no return (checked where decoded:
    ``shared/scan_codec.py``)."""

    TOPIC: ClassVar[str] = "scan"

    x: Coordinate
    y: Coordinate
    theta: Annotated[float, bounded(-3.2, 3.2)]
    start_angle: Annotated[float, bounded(-6.3, 6.3)]
    count: Annotated[int, bounded(1, MAX_SCAN_BEAMS)]
    ranges: Annotated[bytes, sized(2 * MAX_SCAN_BEAMS)]


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
    """+1 per scan integrated into the map; a restarted agent starts again from 0 (in a new map:
    ``began``)."""
    resolution: Annotated[float, bounded(0.001, 10.0)]
    """Metres per cell."""
    origin_x: Coordinate
    """Metres, map (UWB) frame: the lower-left corner of cell (0, 0); the map is not rotated."""
    origin_y: Coordinate
    width: Annotated[int, bounded(0, 65_535)]
    height: Annotated[int, bounded(0, 65_535)]
    encoding: MapEncoding
    cells: Annotated[bytes, sized(MAX_MAP_DATA)]
    began: Annotated[float, bounded(0.0)] = 0.0
    """Which of the robot's maps this is (``MapSubmaps.began``; since 1.2.0): a restarted agent's new
    map counts its versions from 0 again, so a copy of another map is replaced whatever its version."""


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
    began: Annotated[float, bounded(0.0)] = 0.0
    """Which of the robot's maps it patches (as ``MapSnapshot.began``): an update of another map than
    the copy's does not follow it, whatever its versions say."""


MAX_SUBMAPS = 2000
"""Submaps listed per robot (one per ~3 m of travel: 6 km of mapping)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class SubmapEntry:
    """One submap of a robot's map and where its pose graph puts it now."""

    index: Annotated[int, bounded(0, 999_999_999)]
    version: Annotated[int, bounded(0)]
    """How many nodes it was drawn from (a finished submap holds 10): it changes only while it is the
    open one, each time a node joins it and it is drawn again."""
    x: Coordinate
    """Metres, map frame: the submap's own frame (its first node's pose)."""
    y: Coordinate
    theta: Annotated[float, bounded(-3.2, 3.2)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class MapSubmaps(Message):
    """The submaps a robot's map is drawn from, the reply of the queryable
    ``fleetlink/v1/<robot>/map/submaps`` (after Cartographer's ``SubmapList``): each one's index,
    version and pose in the map frame as the robot's optimised pose graph has them now. A console
    fetches the submaps whose version it lacks from ``fleetlink/v1/<robot>/map/submap/<index>``."""

    TOPIC: ClassVar[str] = "map/submaps"

    began: Annotated[float, bounded(0.0)]
    """When this map began (seconds, the agent's clock): a map begun again (placed in the site frame,
    or a restarted agent) numbers its submaps from 0 again, so indices are of one map only."""
    site_frame: bool
    """The map is in the site (UWB) frame."""
    submaps: Annotated[tuple[SubmapEntry, ...], sized(MAX_SUBMAPS)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class MapSubmap(Message):
    """One submap's cells, the reply of the queryable ``fleetlink/v1/<robot>/map/submap/<index>``
    (``.../submap/*``: every submap, one reply each; after Cartographer's ``SubmapQuery``).

    ``cells`` is the zlib-compressed int8 grid (row-major, row 0 at the bottom) in the submap's own
    frame, as in ``MapSnapshot``; ``x``, ``y``, ``theta`` place that frame in the map frame as the
    robot's pose graph had it when the submap was drawn (``MapSubmaps`` gives it as it is now).
    """

    TOPIC: ClassVar[str] = "map/submap"

    began: Annotated[float, bounded(0.0)]
    """As ``MapSubmaps.began``: which map this submap is of."""
    index: Annotated[int, bounded(0, 999_999_999)]
    version: Annotated[int, bounded(0)]
    x: Coordinate
    y: Coordinate
    theta: Annotated[float, bounded(-3.2, 3.2)]
    resolution: Annotated[float, bounded(0.001, 10.0)]
    origin_x: Coordinate
    """Metres, the submap's own frame: the lower-left corner of cell (0, 0)."""
    origin_y: Coordinate
    width: Annotated[int, bounded(0, 65_535)]
    height: Annotated[int, bounded(0, 65_535)]
    encoding: MapEncoding
    cells: Annotated[bytes, sized(MAX_MAP_DATA)]


MAX_FRAMED_ROBOTS = 1000
"""Robots one ``FleetFrames`` names (each way: found, not found)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class RobotFrame:
    """Where a robot's own map frame lies on the fleet map."""

    robot: Annotated[str, sized(64)]
    """A robot id (as a header's ``robot``)."""
    x: Coordinate
    """Metres, the fleet map's frame."""
    y: Coordinate
    theta: Annotated[float, bounded(-3.2, 3.2)]
    began: Annotated[float, bounded(0.0)] = 0.0
    """Which of the robot's maps the frame was found for (its ``MapSubmaps.began``; since 1.2.0, 0: the
    service does not say): a pose whose ``Pose.map_began`` differs is in another frame (a map begun
    again) that this one does not place (``same_map``)."""


def same_map(frame_began: float, pose_began: float, reported_before: bool) -> bool:
    """Whether a frame found for the map begun at ``frame_began`` places a pose of the map begun at
    ``pose_began``, ``reported_before``: the robot's poses have named a map before (a ``map_began``
    other than 0). 0 on either side is a sender that does not say (before 1.2.0), and then the frame
    holds, but for a robot that has named its map before: its poses say 0 again when its agent
    restarted and its new map has not begun yet, and an old frame would place them where it is not."""
    if frame_began == 0.0:
        return True
    if pose_began == 0.0:
        return not reported_before
    return frame_began == pose_began


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class FleetFrames(Message):
    """Where the robots that map in their own frames (no UWB) lie on the fleet map, as a fleet map
    service found them: ``fleetlink/v1/fleet/frames``, published when they change and every few
    seconds. The fleet map's frame is the site frame if any robot maps in it, else the own frame of
    the robot first by name (docs/mapping.md, "Robots in their own frames"). A client draws such a
    robot's poses, scans and map (all in its own frame) through its frame here."""

    TOPIC: ClassVar[str] = "frames"

    reference: Annotated[str, sized(64)]
    """"" when the fleet map's frame is the site frame; else the robot whose own frame it is (no robot
    maps in the site frame). Two services may briefly disagree (one has not heard a site-frame map
    yet): a client prefers the site-referenced one."""
    frames: Annotated[tuple[RobotFrame, ...], sized(MAX_FRAMED_ROBOTS)]
    unframed: Annotated[tuple[str, ...], sized(MAX_FRAMED_ROBOTS, item=sized(64))]
    """Robots in their own frames that the fleet map has not found yet (left out of it)."""


# -- UV dose layers (docs/payload.md, "Dose layer") --------------------------------------------

MAX_DOSE_DATA = 240 * 1024
"""Compressed cells per message, bytes (as ``MAX_MAP_DATA``: room for the fields under wire.MAX_PAYLOAD)."""
MAX_DOSE_CELLS = 4_000_000
"""width * height of a whole dose layer (200 m x 200 m at 0.1 m; 16 MB once inflated)."""
MAX_DOSE_J_M2 = 1.0e9
"""The largest dose a cell may carry, J/m² (a 10 W lamp 0.3 m above a cell for 30 years)."""
DoseSeconds = Annotated[float, bounded(0.0, 1.0e9)]


class DoseEncoding(enum.StrEnum):
    ZLIB_F32LE = "zlib-f32le"
    """zlib (RFC 1950) over the cells as float32 little-endian (J/m², finite, >= 0), row-major, row 0
    at the bottom; each value rounded *down* from the agent's float64, never up."""


@dataclass(frozen=True, slots=True, kw_only=True)
class DoseLamp:
    """The robot's UV-C lamp as its ``[uv]`` configures it (``shared.dose.Lamp``): what a console
    plans a round for, so the plan and the dose the robot counts use the same lamp."""

    uvc_power_w: Annotated[float, bounded(0.001, 10_000.0)]
    height_m: Annotated[float, bounded(0.01, 10.0)]
    tube_length_m: Annotated[float, bounded(0.0, 5.0)]
    min_distance_m: Annotated[float, bounded(0.01, 5.0)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class DoseSnapshot(Message):
    """A robot's whole UV dose layer, the reply of the queryable ``fleetlink/v1/<robot>/dose``.

    Dose (J/m²) received by each floor cell from this robot's lamp since its agent started, in the
    site frame, on the lattice of cell centres at multiples of ``resolution`` (so the layers of
    several robots add cell by cell). Cross-field rules (the cells' size and values) are checked
    where the cells are decoded (``shared/dose_codec.py``), which raises ``WireError``.
    """

    TOPIC: ClassVar[str] = "dose"

    version: Annotated[int, bounded(0)]
    """+1 per exposure added to the layer; a restarted agent starts again from 0."""
    resolution: Annotated[float, bounded(0.001, 10.0)]
    """Metres per cell."""
    origin_x: Coordinate
    """Metres, site (map, UWB) frame: the lower-left corner of cell (0, 0); not rotated."""
    origin_y: Coordinate
    width: Annotated[int, bounded(0, 65_535)]
    height: Annotated[int, bounded(0, 65_535)]
    target_j_m2: Annotated[float, bounded(0.001, 1.0e6)]
    """The robot's configured target dose, J/m² (10 mJ/cm² = 100 J/m²)."""
    lamp_on_s: DoseSeconds
    """Seconds the lamp was on and counted into the layer."""
    unplaced_s: DoseSeconds
    """Seconds the lamp was on while the robot was not placed in the site frame (no UWB position,
    or no map in the site frame yet): counted nowhere in the cells."""
    mantissa_bits: Annotated[int, bounded(0, 23)]
    """Mantissa bits kept in the cells: 23 is float32 itself; fewer (a layer too large for one
    message otherwise) means each value was cut *down* to that many, relative error < 2^-bits."""
    lamp: DoseLamp
    """The lamp that gave the dose."""
    encoding: DoseEncoding
    cells: Annotated[bytes, sized(MAX_DOSE_DATA)]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class DoseUpdate(Message):
    """What changed in a robot's dose layer, on ``fleetlink/v1/<robot>/dose/updates``: one
    rectangle of cells (float32, 23 mantissa bits), about once a second while the lamp adds dose.

    Apply it to a copy at ``base_version`` with the same ``resolution``/``origin``/size to get
    ``version``; otherwise (a gap, or the layer grew) fetch a ``DoseSnapshot``.
    """

    TOPIC: ClassVar[str] = "dose/updates"

    version: Annotated[int, bounded(0)]
    base_version: Annotated[int, bounded(0)]
    resolution: Annotated[float, bounded(0.001, 10.0)]
    origin_x: Coordinate
    origin_y: Coordinate
    width: Annotated[int, bounded(0, 65_535)]
    """Size of the whole layer after the update."""
    height: Annotated[int, bounded(0, 65_535)]
    col: Annotated[int, bounded(0, 65_535)]
    """The patch: lower-left cell (col, row) and its size."""
    row: Annotated[int, bounded(0, 65_535)]
    patch_width: Annotated[int, bounded(0, 65_535)]
    patch_height: Annotated[int, bounded(0, 65_535)]
    target_j_m2: Annotated[float, bounded(0.001, 1.0e6)]
    lamp_on_s: DoseSeconds
    unplaced_s: DoseSeconds
    encoding: DoseEncoding
    cells: Annotated[bytes, sized(MAX_DOSE_DATA)]
