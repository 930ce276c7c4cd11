"""A fleetlink robot as a VDA 5050 2.1 vehicle: the pure mapping core (no I/O, time passed in).

``VehicleCore`` is one robot's VDA 5050 side. Inputs: the master's ``order`` and ``instantActions``
(JSON bytes, ``receive``), the robot's fleetlink messages (``fleet``: State, Pose, BoardStatus,
Event, Ack, Lease), the bridge's ``sent`` (which fleetlink header id a command got) and ``tick``.
Outputs: a list of ``Publish`` (a VDA 5050 message for MQTT), ``SendOrder``/``SendActions``/
``SendLease`` (fleetlink commands for the operator link) and ``Log`` lines (first of each kind).

It owns VDA 5050's order rules (docs/vda5050.md): a new order only while the vehicle is idle and
its first node is trivially reachable; an update of the current order only with a higher
``orderUpdateId`` (lower: ``orderUpdateError``; equal: ignored) that starts at the decision point
(the last base node: stitching); horizon nodes go to the robot as unreleased nodes, which it never
drives to. ``nodeStates``/``edgeStates``/``lastNodeId`` follow the robot's ``State.progress``
and its ``order`` events; node actions and instant actions carry VDA 5050 action states. Every
message accepted or sent is checked against the official 2.1.0 schemas (``SchemaValidator``); a
message that fails is refused with a ``validationError`` (level WARNING) in ``state.errors``,
naming the topic and headerId, and the vehicle goes on serving. ``newBaseRequest`` is set while a
horizon waits and the released base left is short (``NEW_BASE_REQUEST_M``); an action the robot
has had no word on for ``ACTION_TIMEOUT_S`` is FAILED with an ``actionTimeout`` warning.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, Protocol

from fleetlink.shared import nurbs, wire
from fleetlink.shared.messages import (
    MAX_COORDINATE_M,
    MAX_TRAJECTORY_POINTS,
    TRAJECTORY_END_M,
    Ack,
    AckResult,
    Action,
    ActionType,
    BlockingType,
    BoardStatus,
    ControlPoint,
    Event,
    KeyValue,
    Lease,
    OrderEdge,
    OrderNode,
    Pose,
    State,
    Trajectory,
)

__all__ = [
    "ACTION_TIMEOUT_S",
    "ERROR_HOLD_S",
    "NEW_BASE_REQUEST_M",
    "PROTOCOL_VERSION",
    "Log",
    "Publish",
    "SendActions",
    "SendLease",
    "SendOrder",
    "VehicleConfig",
    "VehicleCore",
    "iso8601",
]

PROTOCOL_VERSION = "2.1.0"
MAJOR = "v2"
ERROR_HOLD_S = 30.0
"""How long a refused message's error stays in ``state.errors`` (or until the next accepted order)."""
MAX_BRIDGE_ERRORS = 8
LEASE_S = 60.0
LEASE_RENEW_S = 2.0
"""While the bridge wants a robot's lease it renews it this often, as a console does
(operator/fleet.py ``CONTACT_RENEW_S``): the agent takes a lease holder that asked for the lease as
an operator working with it, and three missed renewals as lost contact (agent/contact.py)."""
LEASE_IDLE_S = 5.0
"""The lease goes back once the vehicle has been idle this long (a next order soon keeps it)."""
LEASE_REGRANT_S = 3.0
"""A ``Lease`` naming the bridge this long after it released the lease (or before it ever asked)
says a late request re-granted it (a renewal's copy on the other link overtaken by the release):
the bridge releases it again, or the robot would count the bridge's silence as lost contact."""
MAX_SKIP_ERRORS = 8
"""Skipped nodes reported in ``state.errors`` at once (the newest; every one is counted)."""
MAX_ID = 64
"""fleetlink's ids (orders, nodes, edges, actions) are at most 64 characters (factsheet idLen)."""
MAX_ACTION_STATES = 256
ACTION_TIMEOUT_S = 10.0
"""An action the bridge waits on the robot for FAILS after this long without the robot's word on
it (``actionTimeout`` in ``state.errors``): an instant action sent and not acked (the operator
link gives up re-sending after about a second, operator/linkmanager.py), a node action whose order
update the robot has neither acked nor named since (its ``State`` names the order and update it
runs, at 1 Hz and on change)."""
NEW_BASE_REQUEST_M = 1.0
"""``newBaseRequest`` goes true when the released base left to drive is this short and a horizon
waits (2 s at the factsheet's speedMax of 0.5 m/s; the robot stops at the base's last node)."""
FLEET_NODE_ACTIONS = ("payload", "dwell")
TERMINAL = ("FINISHED", "FAILED")


class Validator(Protocol):
    def problems(self, topic: str, doc: object) -> list[str]: ...


@dataclass(frozen=True, slots=True)
class Publish:
    """A VDA 5050 message for ``topic`` (``<interface>/v2/<manufacturer>/<serial>/<subtopic>``)."""

    topic: str
    doc: dict[str, Any]
    qos: int = 0
    retain: bool = False

    @property
    def payload(self) -> bytes:
        return json.dumps(self.doc, separators=(",", ":")).encode()


@dataclass(frozen=True, slots=True)
class SendOrder:
    """A fleetlink ``Order`` to the robot (its fields, header aside); ``tag`` names it in ``sent``."""

    fields: dict[str, Any]
    tag: str


@dataclass(frozen=True, slots=True)
class SendActions:
    actions: tuple[Action, ...]
    tag: str


@dataclass(frozen=True, slots=True)
class SendLease:
    release: bool
    duration_s: float = LEASE_S


@dataclass(frozen=True, slots=True)
class Log:
    text: str
    level: str = "warning"


Out = Publish | SendOrder | SendActions | SendLease | Log


@dataclass(frozen=True, slots=True)
class VehicleConfig:
    robot: str
    serial: str
    manufacturer: str = "fleetlink"
    interface: str = "uagv"
    map_id: str = "site"
    """The mapId reported and required (fleetlink robots share one site frame)."""
    first_node_tolerance_m: float = 0.5
    """A new order's first node counts as trivially reachable within this (or its allowedDeviationXY)."""
    state_period_s: float = 5.0
    visualization_period_s: float = 1.0
    speed_max_mps: float = 0.5
    action_timeout_s: float = ACTION_TIMEOUT_S
    new_base_request_m: float = NEW_BASE_REQUEST_M


def iso8601(wall: float) -> str:
    """``2026-01-01T00:00:00.000Z`` (UTC, milliseconds)."""
    return datetime.fromtimestamp(wall, UTC).strftime("%Y-%m-%dT%H:%M:%S.") + f"{int(wall * 1000) % 1000:03d}Z"


def _wrap(theta: float) -> float:
    return max(-math.pi, min(math.pi, math.remainder(theta, 2 * math.pi)))


@dataclass(slots=True)
class _ActionState:
    action_id: str
    action_type: str
    status: str = "WAITING"
    result: str = ""
    node_seq: int | None = None
    """The node it runs at (node actions), None for instant actions."""
    deadline: float = math.inf
    """It FAILS at this time unless the robot has a word on it first (``ACTION_TIMEOUT_S``)."""
    update_id: int = 0
    """A node action: the orderUpdateId that first carried it to the robot."""

    def doc(self) -> dict[str, Any]:
        d: dict[str, Any] = {"actionId": self.action_id, "actionType": self.action_type, "actionStatus": self.status}
        if self.result:
            d["resultDescription"] = self.result[:256]
        return d


@dataclass(slots=True)
class _Pending:
    """A fleetlink command sent, waiting for its ack."""

    kind: str  # "order" or an instant action's VDA type
    action_id: str = ""
    update_id: int = 0
    """An order's orderUpdateId."""
    order_id: str = ""
    """An order's orderId."""


@dataclass(slots=True)
class _Order:
    order_id: str = ""
    update_id: int = 0
    nodes: list[dict[str, Any]] = field(default_factory=list)
    edges: list[dict[str, Any]] = field(default_factory=list)
    sent_nodes: list[tuple[str, int]] = field(default_factory=list)
    """(nodeId, sequenceId) of the nodes of the last fleetlink order sent, in order."""
    last_node_id: str = ""
    last_node_seq: int = 0
    base_end: tuple[str, int] = ("", 0)
    """The last released node (nodeId, sequenceId): the decision point while the base runs."""
    skipped: set[int] = field(default_factory=set)
    """sequenceIds of the nodes the robot skipped (could not reach), over every update."""
    positions: dict[int, dict[str, Any]] = field(default_factory=dict)
    """The fleetlink position to send per sequenceId where it is not the node's own (a new order's
    first node the robot already stands within the allowedDeviationXY of: counted where it is)."""
    taken: bool = False
    """The robot has acked this order (any update) or named it in its ``State``."""
    take_by: float = math.inf
    """Not taken by then: dropped (``VehicleCore._expire_order``)."""


class VehicleCore:
    def __init__(self, config: VehicleConfig, validator: Validator, *, sender: str) -> None:
        self.config = config
        self.validator = validator
        self.sender = sender
        self._header_ids: Counter[str] = Counter()
        self.order = _Order()
        self.actions: dict[str, _ActionState] = {}
        self._errors: list[tuple[dict[str, Any], float]] = []
        self.refused: Counter[str] = Counter()
        """Messages refused, per ``<topic>/<errorType>``."""
        self.invalid_out: Counter[str] = Counter()
        """Messages the bridge would have sent that break their schema (not sent; a bug)."""
        self._logged: set[str] = set()
        self._pending: dict[tuple[str, int], _Pending] = {}
        self._tags: dict[str, _Pending] = {}
        self.fleet_state: State | None = None
        self.pose: Pose | None = None
        self.board: BoardStatus | None = None
        self.lease_holder = ""
        self.lease_until = 0.0
        self._lease_sent = -math.inf
        self._want_lease = False
        """The bridge wants the robot's lease (asked for it for an order or an action, not yet released)."""
        self._idle_since: float | None = None
        self._released_at = -math.inf
        self.lease_rereleases = 0
        """Releases sent again because a late request had re-granted the lease (``LEASE_REGRANT_S``)."""
        self._skips: list[dict[str, Any]] = []
        """The order's own warnings, held until the next new order: noRouteError for the skipped
        nodes, actionTimeout for node actions the robot went silent on."""
        self.skipped_nodes = 0
        self.timed_out_actions = 0
        """Actions FAILED because the robot had no word on them for ``action_timeout_s``."""
        self.dropped_orders = 0
        """Orders dropped because the robot never took them (``_expire_order``)."""
        self._dropped = ""
        """The last order dropped: a robot seen running it after all is sent a cancel."""
        self._cancel_dropped_at = -math.inf
        self._base_request_for: tuple[str, str, int] | None = None
        """(orderId, base end nodeId, sequenceId) newBaseRequest was set for: it stays set until an
        update moves the base's end (or the horizon is gone), so a pose jittering across the
        threshold does not flap it."""
        self.new_base_request = False
        self._state_key: tuple[Any, ...] | None = None
        self._next_state = -math.inf
        self._next_vis = -math.inf
        self._progress_key: tuple[Any, ...] | None = None

    # -- addresses and headers ----------------------------------------------------------------

    def topic(self, sub: str) -> str:
        c = self.config
        return f"{c.interface}/{MAJOR}/{c.manufacturer}/{c.serial}/{sub}"

    def _header(self, sub: str, wall: float) -> dict[str, Any]:
        hid = self._header_ids[sub]
        self._header_ids[sub] += 1
        return {
            "headerId": hid,
            "timestamp": iso8601(wall),
            "version": PROTOCOL_VERSION,
            "manufacturer": self.config.manufacturer,
            "serialNumber": self.config.serial,
        }

    def _publish(self, sub: str, body: dict[str, Any], wall: float, *, qos: int = 0, retain: bool = False) -> list[Out]:
        doc = {**self._header(sub, wall), **body}
        problems = self.validator.problems(sub, doc)
        if problems:
            self.invalid_out[sub] += 1
            return self._log_once(f"out/{sub}", f"not sending an invalid {sub}: {'; '.join(problems)}", "error")
        return [Publish(self.topic(sub), doc, qos, retain)]

    def _log_once(self, kind: str, text: str, level: str = "warning") -> list[Out]:
        if kind in self._logged or len(self._logged) >= 256:
            return []
        self._logged.add(kind)
        return [Log(f"{self.config.serial}: {text}", level)]

    # -- connection and factsheet ---------------------------------------------------------------

    def connection(self, state: str, wall: float) -> list[Out]:
        """ONLINE (every connect), OFFLINE (a clean exit): retained, QoS 1."""
        return self._publish("connection", {"connectionState": state}, wall, qos=1, retain=True)

    def will(self, wall: float) -> Publish:
        """The last will (CONNECTIONBROKEN), for the MQTT client of this vehicle."""
        doc = {**self._header("connection", wall), "connectionState": "CONNECTIONBROKEN"}
        return Publish(self.topic("connection"), doc, 1, True)

    def factsheet(self, wall: float) -> list[Out]:
        """Retained (VDA 5050 2.1 section 6.15: every message on this topic)."""
        return self._publish("factsheet", factsheet_body(self.config), wall, retain=True)

    # -- errors ---------------------------------------------------------------------------------

    def _refuse(
        self, sub: str, error_type: str, text: str, now: float, header_id: object = None, **refs: str
    ) -> list[Out]:
        self.refused[f"{sub}/{error_type}"] += 1
        references = [{"referenceKey": "topic", "referenceValue": sub}]
        if isinstance(header_id, int) and not isinstance(header_id, bool):
            references.append({"referenceKey": "headerId", "referenceValue": str(header_id)})
        references += [{"referenceKey": k, "referenceValue": v[:MAX_ID]} for k, v in refs.items()]
        error = {
            "errorType": error_type,
            "errorLevel": "WARNING",
            "errorDescription": text[:256],
            "errorReferences": references,
        }
        self._hold(error, now)
        return self._log_once(f"{sub}/{error_type}", f"refused {sub}: {error_type}: {text}")

    def _hold(self, error: dict[str, Any], now: float) -> None:
        """``error`` in ``state.errors`` for ``ERROR_HOLD_S`` (the newest ``MAX_BRIDGE_ERRORS``)."""
        self._errors = [*self._errors, (error, now + ERROR_HOLD_S)][-MAX_BRIDGE_ERRORS:]
        self._next_state = -math.inf

    # -- from the master --------------------------------------------------------------------------

    def receive(self, sub: str, payload: bytes, now: float, wall: float) -> list[Out]:
        """An ``order`` or ``instantActions`` message as it came (bytes)."""
        out: list[Out] = []
        try:
            doc = json.loads(payload)
        except (ValueError, UnicodeDecodeError) as exc:
            out += self._refuse(sub, "validationError", f"not JSON: {exc}", now)
            return out + self.tick(now, wall)
        hid = doc.get("headerId") if isinstance(doc, dict) else None
        problems = self.validator.problems(sub, doc)
        if problems:
            out += self._refuse(sub, "validationError", "; ".join(problems), now, hid)
            return out + self.tick(now, wall)
        if doc["manufacturer"] != self.config.manufacturer or doc["serialNumber"] != self.config.serial:
            text = f"addressed to {doc['manufacturer']}/{doc['serialNumber']}"
            out += self._refuse(sub, "validationError", text, now, hid)
            return out + self.tick(now, wall)
        if str(doc["version"]).split(".")[0] != "2":
            out += self._refuse(
                sub, "validationError", f"version {doc['version']!r}: this vehicle speaks 2.x", now, hid
            )
            return out + self.tick(now, wall)
        if sub == "order":
            out += self._order(doc, now, wall)
        elif sub == "instantActions":
            out += self._instant(doc, now, wall)
        else:
            out += self._refuse(sub, "validationError", f"the vehicle does not take {sub!r}", now, hid)
        return out + self.tick(now, wall)

    # -- orders -----------------------------------------------------------------------------------

    @property
    def busy(self) -> bool:
        """VDA 5050: nodeStates not empty, or an action neither FINISHED nor FAILED."""
        return bool(self.order.nodes) or any(a.status not in TERMINAL for a in self.actions.values())

    def _check_order(self, doc: dict[str, Any]) -> str | None:
        """Why fleetlink cannot run this (schema-valid) order, or None."""
        ids = [doc["orderId"]] + [n["nodeId"] for n in doc["nodes"]] + [e["edgeId"] for e in doc["edges"]]
        ids += [a["actionId"] for n in doc["nodes"] for a in n["actions"]]
        long = next((i for i in ids if len(i) > MAX_ID or not i), None)
        if long is not None:
            return f"id {long[:40]!r}: ids are 1-{MAX_ID} characters here (factsheet idLen)"
        if not doc["nodes"]:
            return "an order needs at least one node"
        for n in doc["nodes"]:
            pos = n.get("nodePosition")
            if pos is None:
                return f"node {n['nodeId']!r} has no nodePosition: fleetlink drives to positions"
            if pos["mapId"] != self.config.map_id:
                return f"node {n['nodeId']!r} is on map {pos['mapId']!r}; this vehicle is on {self.config.map_id!r}"
            for a in n["actions"]:
                if a["actionType"] not in FLEET_NODE_ACTIONS:
                    return f"node action {a['actionType']!r} is not supported (factsheet: payload, dwell)"
        for e in doc["edges"]:
            if e["actions"]:
                return f"edge {e['edgeId']!r}: edge actions are not supported (put them on its start node)"
            try:
                traj = _trajectory(e)
                way = traj.waypoints() if traj is not None else []
            except (ValueError, TypeError, OverflowError) as exc:
                return f"edge {e['edgeId']!r}: trajectory: {exc}"
            for end, node_id in ((way[:1], e["startNodeId"]), (way[-1:], e["endNodeId"])):
                pos = next((n.get("nodePosition") for n in doc["nodes"] if n["nodeId"] == node_id), None)
                if end and pos is not None and math.dist(end[0], (pos["x"], pos["y"])) > TRAJECTORY_END_M:
                    return (
                        f"edge {e['edgeId']!r}: its trajectory ends at ({end[0][0]:.2f}, {end[0][1]:.2f}), not at"
                        f" node {node_id!r} (within {TRAJECTORY_END_M:g} m; section 6.6.6: the control points include"
                        " the start and end point)"
                    )
        return None

    def _within_deviation(self, node: dict[str, Any]) -> tuple[float, float] | None:
        """Where the robot stands, if that is within the node's own allowedDeviationXY (VDA 5050
        section 6.6.3.1: such a first node counts as traversed where the vehicle is), else None."""
        here = self._position()
        pos = node["nodePosition"]
        deviation = float(pos.get("allowedDeviationXY", 0.0))
        if here is None or deviation <= 0 or math.hypot(pos["x"] - here[0], pos["y"] - here[1]) > deviation:
            return None
        return here[0], here[1]

    def _reachable(self, node: dict[str, Any]) -> bool:
        o = self.order
        if node["nodeId"] == o.last_node_id and node["sequenceId"] == o.last_node_seq and o.last_node_id:
            return True
        here = self._position()
        if here is None:
            return False
        pos = node["nodePosition"]
        tolerance = max(float(pos.get("allowedDeviationXY", 0.0)), self.config.first_node_tolerance_m)
        return math.hypot(pos["x"] - here[0], pos["y"] - here[1]) <= tolerance

    def _decision_point(self) -> tuple[str, int]:
        o = self.order
        base = [n for n in o.nodes if n["released"]]
        if base:
            return base[-1]["nodeId"], base[-1]["sequenceId"]
        if o.nodes and o.base_end[1] in o.skipped:
            return o.base_end  # the base's last node was skipped; the horizon waits behind it
        return o.last_node_id, o.last_node_seq

    def _order(self, doc: dict[str, Any], now: float, wall: float) -> list[Out]:
        hid = doc["headerId"]
        oid, uid = doc["orderId"], doc["orderUpdateId"]
        why = self._check_order(doc)
        if why is not None:
            return self._refuse("order", "orderError", why, now, hid, orderId=oid)
        o = self.order
        first = doc["nodes"][0]
        # An order dropped as never taken may come again as it was: it is new to the robot.
        if oid != o.order_id or (oid == self._dropped and not o.nodes):
            if self.busy:
                return self._refuse("order", "orderError", f"still running order {o.order_id!r}", now, hid, orderId=oid)
            if not self._reachable(first):
                text = f"first node {first['nodeId']!r} is not where the vehicle stands (trivially reachable)"
                return self._refuse("order", "noRouteError", text, now, hid, orderId=oid)
            self.order = _Order(order_id=oid, update_id=uid, last_node_id=o.last_node_id, last_node_seq=o.last_node_seq)
            self.order.nodes = [_node_state(n) for n in doc["nodes"]]
            self.order.edges = [_edge_state(e) for e in doc["edges"]]
            here = self._within_deviation(first)
            if here is not None:
                self.order.positions[first["sequenceId"]] = {"x": here[0], "y": here[1]}
            self._skips = []
            self._forget_order_actions()
            self.order.take_by = now + self.config.action_timeout_s
            if oid == self._dropped:
                self._dropped = ""
        else:
            if uid < o.update_id:
                text = f"orderUpdateId {uid} is older than {o.update_id}"
                return self._refuse("order", "orderUpdateError", text, now, hid, orderId=oid)
            if uid == o.update_id:
                return self._log_once(f"dup/{oid}/{uid}", f"order {oid}/{uid} again: ignored", "info")
            point = self._decision_point()
            if (first["nodeId"], first["sequenceId"]) != point:
                text = f"update starts at {first['nodeId']}/{first['sequenceId']}, not the decision point {point[0]}/{point[1]}"
                return self._refuse("order", "orderUpdateError", text, now, hid, orderId=oid)
            stitch = first["sequenceId"]
            o.update_id = uid
            # a decision point the robot skipped stays skipped: it is not driven to again
            new_nodes = [n for n in doc["nodes"] if n["sequenceId"] not in o.skipped]
            o.nodes = [n for n in o.nodes if n["sequenceId"] < stitch] + [_node_state(n) for n in new_nodes]
            o.edges = [e for e in o.edges if e["sequenceId"] < stitch] + [_edge_state(e) for e in doc["edges"]]
            self._drop_actions(lambda a: a.node_seq is not None and a.node_seq > stitch and a.status == "WAITING")
        released = [n for n in doc["nodes"] if n["released"]]
        if released:
            self.order.base_end = (released[-1]["nodeId"], released[-1]["sequenceId"])
        for n in doc["nodes"]:
            if n["sequenceId"] in self.order.skipped:
                continue
            for a in n["actions"]:
                if a["actionId"] not in self.actions:
                    self._add_action(
                        _ActionState(a["actionId"], a["actionType"], node_seq=n["sequenceId"], update_id=uid)
                    )
        self._errors = [(e, t) for e, t in self._errors if _ref(e, "topic") != "order"]
        out: list[Out] = []
        if not self._want_lease or now - self._lease_sent >= LEASE_RENEW_S:
            out.append(self._lease(now))
        fields = self._fleet_order(doc)
        if fields is None:  # an update of nothing but a skipped decision point: nothing to drive
            self._next_state = -math.inf
            return out
        self.order.sent_nodes = [(n.nodeId, n.sequenceId) for n in fields["nodes"]]
        tag = f"order/{oid}/{uid}"
        self._tags[tag] = _Pending("order", update_id=uid, order_id=oid)
        out.append(SendOrder(fields, tag))
        self._heard_on_order(now, uid)
        self._next_state = -math.inf
        return out

    def _fleet_order(self, doc: dict[str, Any]) -> dict[str, Any] | None:
        """The fleetlink Order's fields: the nodes not yet traversed (an update: the current base
        before the stitch point as well, so the robot misses none), their edges between them."""
        o = self.order
        nodes = [n for n in o.nodes if n["sequenceId"] > o.last_node_seq or not o.last_node_id]
        if not nodes or nodes[0]["sequenceId"] > doc["nodes"][0]["sequenceId"]:
            nodes = [n for n in o.nodes if n["sequenceId"] >= doc["nodes"][0]["sequenceId"]]
        if not nodes:
            return None
        by_seq = {n["sequenceId"]: n for n in doc["nodes"]}
        first, last = nodes[0]["sequenceId"], nodes[-1]["sequenceId"]
        edges = [e for e in o.edges if first < e["sequenceId"] < last]
        doc_actions = {n["nodeId"]: n["actions"] for n in doc["nodes"]}
        fleet_nodes = []
        for n in nodes:
            src = by_seq.get(n["sequenceId"], n)
            pos = {**src["nodePosition"], **o.positions.get(n["sequenceId"], {})}
            theta = pos.get("theta")
            acts = doc_actions.get(n["nodeId"], []) if n["sequenceId"] in by_seq else []
            fleet_nodes.append(
                OrderNode(
                    nodeId=n["nodeId"],
                    sequenceId=n["sequenceId"],
                    released=n["released"],
                    x=float(pos["x"]),
                    y=float(pos["y"]),
                    theta=None if theta is None else _wrap(float(theta)),
                    actions=tuple(_fleet_action(a) for a in acts),
                    # fleetlink's robots take the nearest place within it only when the node itself
                    # cannot be reached, and at most a metre of it
                    allowedDeviationXY=min(max(float(pos.get("allowedDeviationXY", 0.0)), 0.0), 1.0),
                )
            )
        fleet_edges = [
            OrderEdge(
                edgeId=e["edgeId"],
                sequenceId=e["sequenceId"],
                startNodeId=e["startNodeId"],
                endNodeId=e["endNodeId"],
                released=e["released"],
                maxSpeed=None if e.get("maxSpeed") is None else min(5.0, max(0.01, float(e["maxSpeed"]))),
                trajectory=_trajectory(e),
            )
            for e in edges
        ]
        return {
            "orderId": o.order_id,
            "orderUpdateId": o.update_id,
            "goal": None,
            "returnHome": False,
            "nodes": tuple(fleet_nodes),
            "edges": tuple(fleet_edges),
        }

    # -- instant actions ----------------------------------------------------------------------------

    def _instant(self, doc: dict[str, Any], now: float, wall: float) -> list[Out]:
        out: list[Out] = []
        for a in doc["actions"]:
            aid, kind = a["actionId"], a["actionType"]
            state = _ActionState(aid[:MAX_ID] or "-", kind)
            self._add_action(state)
            if kind == "stateRequest":
                state.status = "FINISHED"
                self._next_state = -math.inf
            elif kind == "factsheetRequest":
                state.status = "FINISHED"
                out += self.factsheet(wall)
            elif kind == "cancelOrder" and not self.order.nodes:
                state.status, state.result = "FAILED", "no order to cancel"
                out += self._refuse("instantActions", "noOrderToCancel", "no order to cancel", now, None, actionId=aid)
            elif kind in ("startPause", "stopPause", "cancelOrder", "payload"):
                fleet = {
                    "startPause": ActionType.PAUSE,
                    "stopPause": ActionType.RESUME,
                    "cancelOrder": ActionType.CANCEL,
                    "payload": ActionType.PAYLOAD,
                }[kind]
                params = tuple(
                    KeyValue(key=str(p["key"])[:32], value=_text(p["value"])[:256])
                    for p in a.get("actionParameters", [])[:8]
                )
                action = Action(actionId=state.action_id, actionType=fleet, actionParameters=params)
                state.status = "RUNNING" if kind == "cancelOrder" else "INITIALIZING"
                state.deadline = now + self.config.action_timeout_s
                tag = f"actions/{aid}"
                self._tags[tag] = _Pending(kind, state.action_id)
                if kind in ("startPause", "stopPause", "payload") and not self._want_lease:
                    out.append(self._lease(now))
                out.append(SendActions((action,), tag))
            else:
                state.status, state.result = "FAILED", f"{kind} is not supported (see the factsheet)"
                out += self._refuse("instantActions", "unsupportedAction", state.result, now, None, actionId=aid)
        self._next_state = -math.inf
        return out

    def _add_action(self, state: _ActionState) -> None:
        self.actions.pop(state.action_id, None)
        self.actions[state.action_id] = state
        while len(self.actions) > MAX_ACTION_STATES:
            old = next((k for k, v in self.actions.items() if v.status in TERMINAL), next(iter(self.actions)))
            del self.actions[old]

    def _drop_actions(self, which: Any) -> None:
        self.actions = {k: v for k, v in self.actions.items() if not which(v)}

    def _forget_order_actions(self) -> None:
        """A new order: the previous order's action states go (instant ones stay)."""
        self._drop_actions(lambda a: a.node_seq is not None)

    def _lease(self, now: float) -> SendLease:
        self._lease_sent = now
        self._want_lease = True
        return SendLease(release=False)

    def _lease_tick(self, now: float) -> list[Out]:
        """Renew the lease while the bridge wants it; release it once the vehicle has been idle
        ``LEASE_IDLE_S``. The release is decided first and ends the wanting, so no renewal can
        follow it: only a new order or action asks again (``_lease``)."""
        if not self._want_lease:
            return []
        if self.busy:
            self._idle_since = None
        elif self._idle_since is None:
            self._idle_since = now
        if self._idle_since is not None and now - self._idle_since >= LEASE_IDLE_S:
            self._want_lease, self._idle_since, self._released_at = False, None, now
            return [SendLease(release=True, duration_s=0.0)]
        if now - self._lease_sent >= LEASE_RENEW_S:
            return [self._lease(now)]
        return []

    def _lease_heard(self, msg: Lease, now: float) -> list[Out]:
        """The robot's lease. One naming the bridge while the bridge does not want it, and not just
        the robot's word from before the release reached it, was re-granted by a late request (or
        is left from an earlier run of the bridge): released again."""
        self.lease_holder, self.lease_until = msg.holder, msg.until
        if msg.holder != self.sender or self._want_lease or now - self._released_at < LEASE_REGRANT_S:
            return []
        self._released_at = now
        self.lease_rereleases += 1
        return [
            SendLease(release=True, duration_s=0.0),
            *self._log_once(
                "lease/regranted", "the robot's lease was granted to the bridge after it let go: released again"
            ),
        ]

    # -- from the robot ---------------------------------------------------------------------------

    def sent(self, tag: str, topic: str, header_id: int) -> None:
        """The bridge sent the command ``tag`` as fleetlink ``topic`` #``header_id``."""
        pending = self._tags.pop(tag, None)
        if pending is not None:
            self._pending[(topic, header_id)] = pending
            if len(self._pending) > 1024:
                self._pending.pop(next(iter(self._pending)))

    def fleet(self, msg: wire.Message, now: float, wall: float) -> list[Out]:
        out: list[Out] = []
        if isinstance(msg, State):
            self.fleet_state = msg
            o = self.order
            if o.order_id and msg.orderId == o.order_id:
                o.taken = True
                self._heard_on_order(now, msg.orderUpdateId)
            elif self._dropped and msg.orderId == self._dropped and msg.progress is not None:
                out += self._cancel_dropped(now)
            out += self._follow(msg)
        elif isinstance(msg, Pose):
            self.pose = msg
        elif isinstance(msg, BoardStatus):
            self.board = msg
        elif isinstance(msg, Lease):
            out += self._lease_heard(msg, now)
        elif isinstance(msg, Ack) and msg.commandSender == self.sender:
            out += self._ack(msg, now)
        elif isinstance(msg, Event) and msg.kind == "order":
            data = {kv.key: kv.value for kv in msg.data}
            if data.get("order") != self.order.order_id or not self.order.order_id:
                pass
            elif "skipped" in data:
                seq = _int(data.get("sequenceId"))
                if seq is not None:
                    self._skip(seq, data["skipped"], msg.text)
            elif data.get("outcome") in ("finished", "ended"):
                self._ended(data["outcome"] == "finished")
        return out + self.tick(now, wall)

    def _ack(self, ack: Ack, now: float) -> list[Out]:
        if ack.result is AckResult.DUPLICATE:
            # The copy on the other link (redundant sending) or a re-send: its ack may come before
            # the one that says how the command went, so it must not end the wait for that one.
            return []
        pending = self._pending.pop((ack.commandTopic, ack.commandHeaderId), None)
        if pending is None:
            return []
        ok = ack.result is AckResult.ACCEPTED
        self._next_state = -math.inf
        if pending.kind == "order":
            if ok:
                if pending.order_id == self.order.order_id:
                    self.order.taken = True
                self._heard_on_order(now, pending.update_id)
                return []
            text = f"the robot refused order {ack.orderId}: {ack.reason}"
            self._ended(False, ack.reason)
            return self._refuse("order", "orderError", text, now, None, orderId=ack.orderId or "")
        state = self.actions.get(pending.action_id)
        if state is None:
            return []
        if state.status in TERMINAL:
            # FAILED already: the ack came after ACTION_TIMEOUT_S. The master was told; the state
            # stays, but a cancel the robot did carry out ends the order as the robot has.
            if ok and pending.kind == "cancelOrder":
                self._ended(False, "cancelled")
            return self._log_once(f"late/{pending.kind}", f"the robot's ack of {pending.kind} came after it timed out")
        if not ok:
            state.status, state.result = "FAILED", ack.reason
        elif pending.kind == "cancelOrder":
            state.status = "FINISHED"
            self._ended(False, "cancelled")
        elif pending.kind in ("startPause", "stopPause", "payload"):
            state.status = "FINISHED"
        return []

    def _follow(self, s: State) -> list[Out]:
        """The robot's progress along the order: traversed nodes leave nodeStates (and so do
        skipped ones, ``_skip``)."""
        o = self.order
        p = s.progress
        out: list[Out] = []
        if p is None or s.orderId != o.order_id or not o.nodes:
            return out
        key = (p.nodesDone, p.skipped, p.lastNodeId, p.lastNodeSequenceId, p.dwellLeft_s > 0)
        if key == self._progress_key:
            return out
        self._progress_key = key
        done = o.sent_nodes[: p.nodesDone]
        done_seq = max((seq for _, seq in done), default=-1)
        # Done means reached or skipped. Done after the last node reached: skipped (the event that
        # names it may come later, or be lost). Done before it: reached, unless the robot's skip
        # count says otherwise and only those nodes can explain it.
        reached_seq = p.lastNodeSequenceId if p.lastNodeId else -1
        leaving = [n for n in o.nodes if n["sequenceId"] <= done_seq and n["sequenceId"] not in o.skipped]
        for n in leaving:
            if n["sequenceId"] > reached_seq:
                self._skip(n["sequenceId"], n["nodeId"], "")
        unexplained = p.skipped - len(o.skipped)
        earlier = [n for n in leaving if n["sequenceId"] < reached_seq]
        if unexplained > 0 and len(earlier) == unexplained:
            for n in earlier:
                self._skip(n["sequenceId"], n["nodeId"], "")
        elif unexplained > 0 and earlier:
            out += self._log_once(
                f"skips/{o.order_id}",
                f"order {o.order_id}: {unexplained} skipped node(s) among {len(earlier)} passed without the robot's "
                "word on which (states lost): counted as reached",
            )
        if p.lastNodeId:
            o.last_node_id, o.last_node_seq = p.lastNodeId, p.lastNodeSequenceId
        o.nodes = [n for n in o.nodes if n["sequenceId"] > done_seq]
        o.edges = [e for e in o.edges if e["sequenceId"] > max(done_seq, o.last_node_seq if p.lastNodeId else -1)]
        for a in self.actions.values():
            if a.node_seq is None or a.status in TERMINAL:
                continue
            if a.node_seq <= done_seq:
                a.status = "FINISHED"
            elif p.lastNodeId and a.node_seq == p.lastNodeSequenceId:
                a.status = "RUNNING"
        self._next_state = -math.inf
        return out

    def _skip(self, seq: int, node_id: str, why: str) -> None:
        """The robot skipped the node ``seq`` (no way there; agent/itinerary.py) and drove on. VDA
        5050 has no word for it, so (docs/vda5050.md "Skipped nodes"): the node leaves
        ``nodeStates`` (section 6.10.1: they are the nodes the vehicle still shall traverse) with
        the edge leading to it, but ``lastNodeId`` stays the last node reached (section 6.10.2:
        traversed nodes only); its actions, never triggered, are FAILED (section 6.11); and a
        ``noRouteError`` WARNING names the order, the node and its actions (sections 6.10.5, 7.1),
        held until the next new order."""
        o = self.order
        if seq in o.skipped:
            return
        o.skipped.add(seq)
        self.skipped_nodes += 1
        node = next((n for n in o.nodes if n["sequenceId"] == seq), None)
        if node is not None:
            node_id = node["nodeId"]
            o.nodes = [n for n in o.nodes if n is not node]
            o.edges = [e for e in o.edges if e["sequenceId"] != seq - 1]
        failed = []
        for a in self.actions.values():
            if a.node_seq == seq and a.status not in TERMINAL:
                a.status, a.result = "FAILED", f"node {node_id} skipped: the robot found no way there"
                failed.append(a.action_id)
        references = [
            {"referenceKey": "orderId", "referenceValue": o.order_id},
            {"referenceKey": "orderUpdateId", "referenceValue": str(o.update_id)},
            {"referenceKey": "nodeId", "referenceValue": node_id[:MAX_ID]},
            {"referenceKey": "sequenceId", "referenceValue": str(seq)},
        ]
        references += [{"referenceKey": "actionId", "referenceValue": aid} for aid in failed]
        text = f"node {node_id} (sequenceId {seq}) skipped: the robot found no way there and drove on"
        if failed:
            text += f"; its actions FAILED: {', '.join(failed)}"
        error = {
            "errorType": "noRouteError",
            "errorLevel": "WARNING",
            "errorDescription": (text + (f" ({why})" if why else ""))[:256],
            "errorHint": "send the node again in a new order once the way is clear, if it matters",
            "errorReferences": references,
        }
        self._skips = [*self._skips, error][-MAX_SKIP_ERRORS:]
        self._next_state = -math.inf

    def _ended(self, finished: bool, why: str = "") -> None:
        o = self.order
        if finished and o.nodes:
            base = [n for n in o.nodes if n["released"]] or o.nodes
            o.last_node_id, o.last_node_seq = base[-1]["nodeId"], base[-1]["sequenceId"]
        o.nodes, o.edges = [], []
        for a in self.actions.values():
            if a.node_seq is not None and a.status not in TERMINAL:
                a.status = "FINISHED" if finished else "FAILED"
                if not finished:
                    a.result = why or "the order ended"
        self._progress_key = None
        self._next_state = -math.inf

    # -- timeouts ---------------------------------------------------------------------------------

    def _heard_on_order(self, now: float, update_id: int) -> None:
        """The robot said it has the current order up to ``update_id`` (acked that update, names it
        in its ``State``), or the bridge just sent that update: the wait starts over for the node
        actions it carries (those of earlier updates included; a later update's, which the robot
        has not got yet, wait on)."""
        for a in self.actions.values():
            if a.node_seq is not None and a.status not in TERMINAL and a.update_id <= update_id:
                a.deadline = now + self.config.action_timeout_s

    def undelivered(self, topic: str, header_id: int, reason: str, now: float) -> list[Out]:
        """The operator link gave up on the fleetlink command ``topic`` #``header_id`` (no ack on
        any link after its re-sends, about a second): what waits on it fails now, not after
        ``action_timeout_s``. An instant action FAILED with an ``actionTimeout`` WARNING; an order
        the robot has not taken dropped (``_expire_order``; it is cancelled on the robot should it
        get there after all)."""
        pending = self._pending.pop((topic, header_id), None)
        if pending is None:
            return []
        why = f"not delivered: {reason}"
        if pending.kind == "order":
            o = self.order
            if pending.order_id == o.order_id and not o.taken and o.nodes:
                return self._drop_order(f"the robot never took order {o.order_id} ({why})")
            return []
        state = self.actions.get(pending.action_id)
        if state is None or state.status in TERMINAL:
            return []
        state.deadline = now  # FAILED by _expire_actions, as a timeout, with this reason
        state.result = why
        return self._expire_actions(now)

    def _expire_order(self, now: float) -> list[Out]:
        """Drop an order the robot has not taken (no ack, no ``State`` naming it) within
        ``action_timeout_s`` of its sending: its nodes leave the state, its actions FAIL, an
        ``orderError`` WARNING says so (held until the next new order), and the vehicle is idle
        again, so the master can send it (or another) once the robot answers. Kept, a robot that
        never got it would hold the vehicle busy for ever: new orders refused, and a
        ``cancelOrder`` that cannot reach the robot FAILED too. Should the order reach the robot
        after all, the robot is sent a cancel when its state names it (``_cancel_dropped``)."""
        o = self.order
        if not o.nodes or o.taken or now < o.take_by:
            return []
        t = self.config.action_timeout_s
        return self._drop_order(f"the robot never took order {o.order_id} (no ack, not in its state for {t:g} s)")

    def _drop_order(self, why: str) -> list[Out]:
        o = self.order
        text = f"{why}: dropped"
        self._ended(False, "order dropped: the robot never took it")
        error = {
            "errorType": "orderError",
            "errorLevel": "WARNING",
            "errorDescription": text[:256],
            "errorHint": "the robot may be out of reach: check its link; send the order again once it answers",
            "errorReferences": [
                {"referenceKey": "orderId", "referenceValue": o.order_id},
                {"referenceKey": "orderUpdateId", "referenceValue": str(o.update_id)},
            ],
        }
        self._skips = [*self._skips, error][-MAX_SKIP_ERRORS:]
        self._dropped = o.order_id
        self._cancel_dropped_at = -math.inf
        self.dropped_orders += 1
        return self._log_once("orderDropped", text)

    def _cancel_dropped(self, now: float) -> list[Out]:
        """The robot runs the order dropped as never taken (it got there late): cancel it, as the
        master was told it would not run (at most once per ``action_timeout_s``)."""
        if now < self._cancel_dropped_at:
            return []
        self._cancel_dropped_at = now + self.config.action_timeout_s
        action = Action(actionId=f"drop-{self._dropped}"[:MAX_ID], actionType=ActionType.CANCEL, actionParameters=())
        return [
            SendActions((action,), f"drop/{self._dropped}"),
            *self._log_once(
                f"late/{self._dropped}", f"order {self._dropped} reached the robot after it was dropped: cancelled"
            ),
        ]

    def _expire_actions(self, now: float) -> list[Out]:
        """FAIL the actions the robot has had no word on for ``action_timeout_s`` (VDA 5050 section
        6.11: FAILED, "could not be finished for whatever reason"), each named in an
        ``actionTimeout`` WARNING: an instant action in its own (held ``ERROR_HOLD_S``), an order's
        node actions together (held until the next new order, as skipped nodes are). The node
        states stay as last known: the bridge cannot tell whether the robot still drives."""
        late = [a for a in self.actions.values() if a.status not in TERMINAL and now >= a.deadline]
        if not late:
            return []
        t = self.config.action_timeout_s
        o = self.order
        hint = "the robot may be out of reach: check its link; send the action again once it answers"
        for a in late:
            a.status = "FAILED"
            if a.node_seq is None:
                a.result = a.result or f"no ack from the robot within {t:g} s"
                self._hold(
                    {
                        "errorType": "actionTimeout",
                        "errorLevel": "WARNING",
                        "errorDescription": f"instant action {a.action_id} ({a.action_type}) FAILED: {a.result}",
                        "errorHint": hint,
                        "errorReferences": [
                            {"referenceKey": "topic", "referenceValue": "instantActions"},
                            {"referenceKey": "actionId", "referenceValue": a.action_id},
                        ],
                    },
                    now,
                )
            else:
                a.result = f"no word from the robot on order {o.order_id} for {t:g} s"
        node = [a.action_id for a in late if a.node_seq is not None]
        if node:
            references = [
                {"referenceKey": "orderId", "referenceValue": o.order_id},
                {"referenceKey": "orderUpdateId", "referenceValue": str(o.update_id)},
            ]
            references += [{"referenceKey": "actionId", "referenceValue": aid} for aid in node[:16]]
            text = f"{len(node)} node action(s) FAILED: no word from the robot on order {o.order_id} for {t:g} s"
            error = {
                "errorType": "actionTimeout",
                "errorLevel": "WARNING",
                "errorDescription": f"{text}: {', '.join(node)}"[:256],
                "errorHint": hint,
                "errorReferences": references,
            }
            self._skips = [*self._skips, error][-MAX_SKIP_ERRORS:]
        self.timed_out_actions += len(late)
        self._next_state = -math.inf
        return self._log_once("actionTimeout", f"{len(late)} action(s) FAILED: no word from the robot for {t:g} s")

    # -- base request -----------------------------------------------------------------------------

    def _base_left_m(self, limit: float) -> float | None:
        """The released base still to drive: straight lines from the robot through the released
        nodes not yet traversed (a lower bound on the robot's own way between them); counted up to
        just past ``limit``. None when the robot's position is not known."""
        base = [n["nodePosition"] for n in self.order.nodes if n["released"]]
        if not base:
            return 0.0
        here = self._position()
        if here is None:
            return None
        left, x, y = 0.0, here[0], here[1]
        for p in base:
            left += math.hypot(p["x"] - x, p["y"] - y)
            if left > limit:
                break
            x, y = p["x"], p["y"]
        return left

    def _update_base_request(self) -> None:
        """``newBaseRequest`` (VDA 5050 2.1.0 section 6.10.3: "If the AGV detects that its base is
        running low, it can set the newBaseRequest flag to 'true' to prevent unnecessary braking";
        the state table: the AGV "is almost at the end of the base and will reduce speed, if no new
        base is transmitted. Trigger for master control to send a new base"). Set while a horizon
        waits and the released base left to drive is at most ``new_base_request_m`` (the robot at
        the decision point, waiting for an update, included); then held until an update moves the
        base's end, and cleared once no horizon is left (all released, or the order over)."""
        o = self.order
        if not any(not n["released"] for n in o.nodes):
            self._base_request_for, self.new_base_request = None, False
            return
        key = (o.order_id, *o.base_end)
        if self._base_request_for != key:
            left = self._base_left_m(self.config.new_base_request_m)
            if left is None or left > self.config.new_base_request_m:
                self._base_request_for, self.new_base_request = None, False
                return
            self._base_request_for = key
        self.new_base_request = True

    # -- time -------------------------------------------------------------------------------------

    def tick(self, now: float, wall: float) -> list[Out]:
        out: list[Out] = []
        before = len(self._errors)
        self._errors = [(e, t) for e, t in self._errors if t > now]
        if len(self._errors) != before:
            self._next_state = -math.inf
        out += self._expire_order(now)
        out += self._expire_actions(now)
        out += self._lease_tick(now)
        self._update_base_request()
        key = self._key()
        if key != self._state_key or now >= self._next_state:
            self._state_key = key
            self._next_state = now + self.config.state_period_s
            out += self._publish("state", self.state_body(), wall)
        if self.config.visualization_period_s > 0 and now >= self._next_vis and self.pose is not None:
            self._next_vis = now + self.config.visualization_period_s
            body: dict[str, Any] = {"agvPosition": self._agv_position(), "velocity": self._velocity()}
            out += self._publish("visualization", body, wall)
        return out

    def _key(self) -> tuple[Any, ...]:
        s = self.fleet_state
        o = self.order
        return (
            self.order.order_id,
            self.order.update_id,
            self.order.last_node_id,
            len(self.order.nodes),
            tuple((a.action_id, a.status) for a in self.actions.values()),
            len(self._errors),
            len(o.skipped),
            len(self._skips),
            self.new_base_request,
            None if s is None else (s.paused, s.driving, s.operatingMode, s.safetyState, s.errors),
        )

    # -- state assembly ---------------------------------------------------------------------------

    def _position(self) -> tuple[float, float, float] | None:
        if self.pose is not None:
            return self.pose.x, self.pose.y, self.pose.theta
        if self.fleet_state is not None:
            a = self.fleet_state.agvPosition
            return a.x, a.y, a.theta
        return None

    def _agv_position(self) -> dict[str, Any]:
        here = self._position() or (0.0, 0.0, 0.0)
        s = self.fleet_state
        return {
            "x": here[0],
            "y": here[1],
            "theta": _wrap(here[2]),
            "mapId": self.config.map_id,
            "positionInitialized": bool(s is not None and s.agvPosition.positionInitialized),
            "localizationScore": s.agvPosition.localizationScore if s is not None else 0.0,
        }

    def _velocity(self) -> dict[str, Any]:
        if self.pose is not None:
            return {"vx": self.pose.vx, "vy": 0.0, "omega": self.pose.omega}
        if self.fleet_state is not None:
            v = self.fleet_state.velocity
            return {"vx": v.vx, "vy": 0.0, "omega": v.omega}
        return {"vx": 0.0, "vy": 0.0, "omega": 0.0}

    def state_body(self) -> dict[str, Any]:
        """Everything of ``state`` but the header."""
        s = self.fleet_state
        o = self.order
        errors: list[dict[str, Any]] = []
        if s is None:
            errors.append(
                {"errorType": "noTelemetry", "errorLevel": "WARNING", "errorDescription": "no state from the robot yet"}
            )
        else:
            errors += [
                {"errorType": e.errorType, "errorLevel": e.errorLevel.value, "errorDescription": e.errorDescription}
                for e in s.errors
            ]
        errors += [e for e, _ in self._errors]
        errors += self._skips
        battery: dict[str, Any] = {"batteryCharge": 0.0, "charging": False}
        if s is not None:
            battery = {"batteryCharge": s.batteryState.batteryCharge, "charging": s.batteryState.charging}
        if self.board is not None and self.board.battery_voltage_v is not None:
            battery["batteryVoltage"] = self.board.battery_voltage_v
        information = []
        if s is not None:
            information.append({"infoType": "driveMode", "infoLevel": "INFO", "infoDescription": s.driveMode})
            if self.lease_holder:
                information.append({"infoType": "lease", "infoLevel": "INFO", "infoDescription": self.lease_holder})
        return {
            "maps": [{"mapId": self.config.map_id, "mapVersion": "1", "mapStatus": "ENABLED"}],
            "orderId": o.order_id,
            "orderUpdateId": o.update_id,
            "lastNodeId": o.last_node_id,
            "lastNodeSequenceId": o.last_node_seq,
            "driving": bool(s is not None and s.driving),
            "paused": bool(s is not None and s.paused),
            "newBaseRequest": self.new_base_request,
            "operatingMode": s.operatingMode.value if s is not None else "SERVICE",
            "nodeStates": [dict(n) for n in o.nodes],
            "edgeStates": [dict(e) for e in o.edges],
            "agvPosition": self._agv_position(),
            "velocity": self._velocity(),
            "loads": [],
            "actionStates": [a.doc() for a in self.actions.values()],
            "batteryState": battery,
            "errors": errors,
            "information": information,
            "safetyState": {
                "eStop": s.safetyState.eStop.value if s is not None else "NONE",
                "fieldViolation": bool(s is not None and s.safetyState.fieldViolation),
            },
        }


def _ref(error: dict[str, Any], key: str) -> str | None:
    for r in error.get("errorReferences", []):
        if r["referenceKey"] == key:
            return str(r["referenceValue"])
    return None


def _int(text: str | None) -> int | None:
    try:
        return int(text) if text is not None else None
    except ValueError:
        return None


def _text(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return value
    return json.dumps(value)


def _node_state(n: dict[str, Any]) -> dict[str, Any]:
    d: dict[str, Any] = {"nodeId": n["nodeId"], "sequenceId": n["sequenceId"], "released": n["released"]}
    if "nodeDescription" in n:
        d["nodeDescription"] = n["nodeDescription"]
    pos = n.get("nodePosition")
    if pos is not None:
        # echoed as the master sent it (section 6.10.6: the object defined in section 6.6)
        d["nodePosition"] = dict(pos)
    return d


def _trajectory(edge: dict[str, Any]) -> Trajectory | None:
    """A VDA 5050 edge's trajectory (NURBS) as fleetlink's, or None; ValueError with the reason when
    the robot cannot drive it (sizes, knots, weights: ``Trajectory``'s checks; more control points
    than the factsheet's ``maxArrayLens``)."""
    t = edge.get("trajectory")
    if t is None:
        return None
    points = t["controlPoints"]
    if len(points) > MAX_TRAJECTORY_POINTS:
        raise ValueError(f"{len(points)} control points; this vehicle takes {MAX_TRAJECTORY_POINTS}")
    for i, p in enumerate(points):
        coords = (float(p["x"]), float(p["y"]))
        if not all(abs(v) <= MAX_COORDINATE_M for v in coords) or not float(p.get("weight", 1.0)) <= 1.0e6:
            raise ValueError(f"controlPoints[{i}] out of range (|x|, |y| <= {MAX_COORDINATE_M:g} m, weight <= 1e6)")
    degree = t.get("degree", 1)
    if isinstance(degree, float) and degree.is_integer():
        degree = int(degree)  # the standard's text types it float64, its schema integer
    return Trajectory(
        degree=degree,
        knotVector=tuple(float(k) for k in t["knotVector"]),
        controlPoints=tuple(
            ControlPoint(x=float(p["x"]), y=float(p["y"]), weight=float(p.get("weight", 1.0))) for p in points
        ),
    )


def _edge_state(e: dict[str, Any]) -> dict[str, Any]:
    d: dict[str, Any] = {
        "edgeId": e["edgeId"],
        "sequenceId": e["sequenceId"],
        "released": e["released"],
        "startNodeId": e["startNodeId"],
        "endNodeId": e["endNodeId"],
    }
    if "maxSpeed" in e:
        d["maxSpeed"] = e["maxSpeed"]
    if e.get("trajectory") is not None:  # kept for the robot, and echoed in edgeStates (section 6.10.6)
        d["trajectory"] = e["trajectory"]
    return d


def _fleet_action(a: dict[str, Any]) -> Action:
    return Action(
        actionId=a["actionId"],
        actionType=ActionType(a["actionType"]),
        actionParameters=tuple(
            KeyValue(key=str(p["key"])[:32], value=_text(p["value"])[:256]) for p in a.get("actionParameters", [])[:8]
        ),
        blockingType=BlockingType(a["blockingType"]),
    )


def factsheet_body(c: VehicleConfig) -> dict[str, Any]:
    """The factsheet (everything but the header): what a fleetlink robot is and does over VDA 5050."""

    def act(kind: str, text: str, scopes: list[str], params: list[dict[str, Any]] | None = None) -> dict[str, Any]:
        d: dict[str, Any] = {"actionType": kind, "actionDescription": text, "actionScopes": scopes}
        if params:
            d["actionParameters"] = params
        # blockingTypes left out: the official 2.1.0 schema types it as one string where the
        # specification says an array, so no array passes it (docs/vda5050.md).
        return d

    def param(key: str, kind: str, text: str, optional: bool = False) -> dict[str, Any]:
        return {"key": key, "valueDataType": kind, "description": text, "isOptional": optional}

    return {
        "typeSpecification": {
            "seriesName": "fleetlink",
            "seriesDescription": "fleetlink mobile robot (differential drive), through fleetlink's VDA 5050 bridge",
            "agvKinematic": "DIFF",
            "agvClass": "CARRIER",
            "maxLoadMass": 0,
            "localizationTypes": ["NATURAL"],
            "navigationTypes": ["AUTONOMOUS", "VIRTUAL_LINE_GUIDED"],
        },
        "physicalParameters": {
            "speedMin": 0.0,
            "speedMax": c.speed_max_mps,
            "accelerationMax": 0.5,
            "decelerationMax": 1.0,
            "heightMax": 0.6,
            "width": 0.35,
            "length": 0.35,
        },
        "protocolLimits": {
            "maxStringLens": {"idLen": MAX_ID, "msgLen": wire.MAX_PAYLOAD},
            "maxArrayLens": {
                "order.nodes": 512,
                "order.edges": 511,
                "node.actions": 16,
                "edge.actions": 0,
                "actions.actionsParameters": 8,
                "instantActions": 16,
                "trajectory.knotVector": MAX_TRAJECTORY_POINTS + nurbs.MAX_DEGREE + 1,
                "trajectory.controlPoints": MAX_TRAJECTORY_POINTS,
            },
            "timing": {
                "minOrderInterval": 0.1,
                "minStateInterval": 0.1,
                "defaultStateInterval": c.state_period_s,
                "visualizationInterval": c.visualization_period_s,
            },
        },
        "protocolFeatures": {
            "optionalParameters": [
                {
                    "parameter": "order.nodes.nodePosition",
                    "support": "REQUIRED",
                    "description": "robots drive to positions",
                },
                {"parameter": "order.nodes.nodePosition.theta", "support": "SUPPORTED"},
                {
                    "parameter": "order.nodes.nodePosition.allowedDeviationXY",
                    "support": "SUPPORTED",
                    "description": "a new order's first node counts as reached within it (section 6.6.3.1); "
                    "elsewhere, up to 1 m, the nearest reachable place when the node itself cannot be reached",
                },
                {"parameter": "order.edges.maxSpeed", "support": "SUPPORTED"},
                {
                    "parameter": "order.edges.trajectory",
                    "support": "SUPPORTED",
                    "description": "followed from where the robot joins it (within 0.3 m); where the robot's "
                    "own map has a wall on it, or the way is barred, the robot plans its own",
                },
                {"parameter": "state.agvPosition", "support": "SUPPORTED"},
                {"parameter": "state.velocity", "support": "SUPPORTED"},
            ],
            "agvActions": [
                act("startPause", "hold the robot (fleetlink pause)", ["INSTANT"]),
                act("stopPause", "carry on (fleetlink resume)", ["INSTANT"]),
                act("cancelOrder", "end the order (fleetlink cancel)", ["INSTANT"]),
                act("stateRequest", "publish state now", ["INSTANT"]),
                act("factsheetRequest", "publish the factsheet", ["INSTANT"]),
                act(
                    "payload",
                    "the disinfection payload: UV lamp, atomiser, fan (interlocks apply)",
                    ["INSTANT", "NODE"],
                    [
                        param("device", "STRING", "uv (default), atomiser or fan", True),
                        param("on", "BOOL", "true or false"),
                        param("level", "INTEGER", "0-3, atomiser and fan", True),
                    ],
                ),
                act("dwell", "stand at the node", ["NODE"], [param("duration", "FLOAT", "seconds, 0-3600")]),
            ],
        },
        "agvGeometry": {},
        "loadSpecification": {},
    }
