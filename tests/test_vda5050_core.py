"""The VDA 5050 bridge's pure core: order update rules, stitching, horizon, action states, refusals.

Every message the core emits is checked against the official 2.1.0 schemas in the handout
(``../shared/reference/vda5050-2.1.0/`` beside the clone), and the package's copies must equal them.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

import pytest

from fleetlink.operator.vda5050.core import (
    ACTION_TIMEOUT_S,
    NEW_BASE_REQUEST_M,
    Publish,
    SendActions,
    SendLease,
    SendOrder,
    VehicleConfig,
    VehicleCore,
)
from fleetlink.operator.vda5050.schema import SCHEMA_TOPICS, SchemaValidator, load_schemas
from fleetlink.shared import wire
from fleetlink.shared.messages import (
    Ack,
    AckResult,
    AgvPosition,
    BatteryState,
    CommsPolicy,
    Contact,
    EStop,
    Event,
    KeyValue,
    Lease,
    LinkName,
    LinkStatus,
    OperatingMode,
    OrderProgress,
    SafetyState,
    Severity,
    State,
    Velocity,
)

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference" / "vda5050-2.1.0"
OFFICIAL = SchemaValidator(load_schemas(REFERENCE))
SENDER = "vda5050"


def test_the_package_carries_the_official_schemas_unchanged() -> None:
    ours = load_schemas()
    for topic in SCHEMA_TOPICS:
        assert ours[topic] == json.loads((REFERENCE / f"{topic}.schema").read_text()), topic


class Rig:
    def __init__(self) -> None:
        self.core = VehicleCore(VehicleConfig(robot="r1", serial="r1"), SchemaValidator(load_schemas()), sender=SENDER)
        self.now = 0.0
        self.out: list[Any] = []
        self.hid = {"order": 0, "instantActions": 0}
        self.fleet_hid = 100
        self.counter = wire.HeaderCounter(_Clock(), robot="r1", sender="agent-r1")

    def wall(self) -> float:
        return 1_767_225_600.0 + self.now

    def _check(self, outs: list[Any]) -> list[Any]:
        for o in outs:
            if isinstance(o, Publish):
                sub = o.topic.rsplit("/", 1)[1]
                assert o.topic == f"uagv/v2/fleetlink/r1/{sub}"
                assert OFFICIAL.problems(sub, json.loads(o.payload)) == [], o.doc
            if isinstance(o, SendOrder | SendActions):
                self.fleet_hid += 1
                self.core.sent(o.tag, "order" if isinstance(o, SendOrder) else "actions", self.fleet_hid)
        self.out += outs
        return outs

    def send(self, sub: str, body: dict[str, Any] | bytes) -> list[Any]:
        if isinstance(body, bytes):
            payload = body
        else:
            doc = {
                "headerId": self.hid[sub],
                "timestamp": "2026-01-01T00:00:00.00Z",
                "version": "2.1.0",
                "manufacturer": "fleetlink",
                "serialNumber": "r1",
                **body,
            }
            self.hid[sub] += 1
            assert OFFICIAL.problems(sub, doc) == [] or body.get("_bad")
            payload = json.dumps({k: v for k, v in doc.items() if k != "_bad"}).encode()
        return self._check(self.core.receive(sub, payload, self.now, self.wall()))

    def fleet(self, msg: wire.Message) -> list[Any]:
        return self._check(self.core.fleet(msg, self.now, self.wall()))

    def state(
        self,
        *,
        order: str = "",
        done: int = 0,
        last: str = "",
        last_seq: int = 0,
        paused: bool = False,
        skipped: int = 0,
        x: float = 0.0,
        update: int = 0,
        waiting: str = "",
    ) -> None:
        progress = None
        if order:
            progress = OrderProgress(
                nodesTotal=9,
                nodesDone=done,
                skipped=skipped,
                lastNodeId=last,
                lastNodeSequenceId=last_seq,
                dwellLeft_s=0.0,
                waiting=waiting,
            )
        self.fleet(
            self.counter.make(
                State,
                agvPosition=AgvPosition(
                    x=x, y=0.0, theta=0.0, mapId="", positionInitialized=True, localizationScore=1.0
                ),
                velocity=Velocity(vx=0.0, omega=0.0),
                batteryState=BatteryState(batteryCharge=80.0, charging=False),
                errors=(),
                operatingMode=OperatingMode.AUTOMATIC,
                safetyState=SafetyState(eStop=EStop.NONE, fieldViolation=False),
                driveMode="goto",
                links=LinkStatus(zenoh=True, mqtt=True),
                uwbStale=False,
                payloadOn=False,
                boardConnected=True,
                orderId=order,
                orderUpdateId=update,
                goal=None,
                driving=False,
                paused=paused,
                home=None,
                contact=Contact(policy=CommsPolicy.STOP, lost=False, action="", silent_s=0.0),
                progress=progress,
            )
        )

    def ack(self, topic: str, result: AckResult = AckResult.ACCEPTED, reason: str = "") -> list[Any]:
        return self.fleet(
            self.counter.make(
                Ack,
                commandTopic=topic,
                commandSender=SENDER,
                commandHeaderId=self.fleet_hid,
                orderId=None,
                orderUpdateId=None,
                result=result,
                reason=reason,
                link=LinkName.ZENOH,
            )
        )

    def last_state(self) -> dict[str, Any]:
        return [o.doc for o in self.out if isinstance(o, Publish) and o.topic.endswith("/state")][-1]


class _Clock:
    def now(self) -> float:
        return 0.0

    def wall(self) -> float:
        return 1_767_225_600.0


def node(nid: str, seq: int, x: float, released: bool = True, actions: list[Any] | None = None) -> dict[str, Any]:
    return {
        "nodeId": nid,
        "sequenceId": seq,
        "released": released,
        "actions": actions or [],
        "nodePosition": {"x": x, "y": 0.0, "mapId": "site"},
    }


def edge(a: str, b: str, seq: int, released: bool = True) -> dict[str, Any]:
    return {
        "edgeId": f"{a}-{b}",
        "sequenceId": seq,
        "released": released,
        "startNodeId": a,
        "endNodeId": b,
        "actions": [],
    }


def order(oid: str, uid: int, nodes: list[Any], edges: list[Any]) -> dict[str, Any]:
    return {"orderId": oid, "orderUpdateId": uid, "nodes": nodes, "edges": edges}


BASE_WITH_HORIZON = order(
    "o1",
    0,
    [node("n0", 0, 0.0), node("n1", 2, 1.0), node("n2", 4, 2.0, released=False)],
    [edge("n0", "n1", 1), edge("n1", "n2", 3, released=False)],
)


HEADER = {
    "headerId": 7,
    "timestamp": "2026-01-01T00:00:00.00Z",
    "version": "2.1.0",
    "manufacturer": "fleetlink",
    "serialNumber": "r1",
}


def errors(rig: Rig) -> list[dict[str, Any]]:
    return rig.last_state()["errors"]


def test_an_order_goes_to_the_robot_with_its_horizon_unreleased_and_the_lease_first() -> None:
    rig = Rig()
    rig.state()
    outs = rig.send("order", BASE_WITH_HORIZON)
    assert isinstance(outs[0], SendLease) and not outs[0].release
    sent = next(o for o in outs if isinstance(o, SendOrder)).fields
    assert [(n.nodeId, n.released) for n in sent["nodes"]] == [("n0", True), ("n1", True), ("n2", False)]
    assert [e.released for e in sent["edges"]] == [True, False]
    s = rig.last_state()
    assert s["orderId"] == "o1" and [n["nodeId"] for n in s["nodeStates"]] == ["n0", "n1", "n2"]
    # The robot reaches n0 and n1 and waits at n1 (the horizon is not driven): n2 stays, unreleased.
    rig.state(order="o1", done=2, last="n1", last_seq=2)
    s = rig.last_state()
    assert s["lastNodeId"] == "n1" and s["lastNodeSequenceId"] == 2
    assert s["nodeStates"] == [
        {"nodeId": "n2", "sequenceId": 4, "released": False, "nodePosition": {"x": 2.0, "y": 0.0, "mapId": "site"}}
    ]
    assert [e["edgeId"] for e in s["edgeStates"]] == ["n1-n2"]


def test_a_nodes_allowed_deviation_goes_to_the_robot_up_to_a_metre() -> None:
    rig = Rig()
    rig.state()
    nodes = [node("n0", 0, 0.0), node("n1", 2, 1.0), node("n2", 4, 2.0)]
    nodes[1]["nodePosition"]["allowedDeviationXY"] = 0.15
    nodes[2]["nodePosition"]["allowedDeviationXY"] = 3.0
    outs = rig.send("order", order("o1", 0, nodes, [edge("n0", "n1", 1), edge("n1", "n2", 3)]))
    sent = next(o for o in outs if isinstance(o, SendOrder)).fields
    assert [n.allowedDeviationXY for n in sent["nodes"]] == [0.0, 0.15, 1.0]


def test_an_edges_trajectory_goes_to_the_robot_and_is_echoed_in_its_edge_state() -> None:
    rig = Rig()
    rig.state()
    nodes = [node("n0", 0, 0.0), node("n1", 2, 2.0)]
    bend = edge("n0", "n1", 1)
    # A cubic from (0, 0) to (2, 0) bulging to y > 0 (floats as the standard's text types the degree).
    bend["trajectory"] = {
        "degree": 3.0,
        "knotVector": [0, 0, 0, 0, 1, 1, 1, 1],
        "controlPoints": [
            {"x": 0.0, "y": 0.0},
            {"x": 0.5, "y": 1.0, "weight": 2.0},
            {"x": 1.5, "y": 1.0},
            {"x": 2.0, "y": 0.0},
        ],
    }
    outs = rig.send("order", order("o1", 0, nodes, [bend]))
    [sent] = [o.fields for o in outs if isinstance(o, SendOrder)]
    traj = sent["edges"][0].trajectory
    assert traj.degree == 3 and [p.weight for p in traj.controlPoints] == [1.0, 2.0, 1.0, 1.0]
    pts = traj.waypoints()
    assert pts[0] == (0.0, 0.0) and pts[-1] == pytest.approx((2.0, 0.0)) and max(y for _, y in pts) > 0.5
    # The trajectory an order came with is echoed in its edge state.
    rig = Rig()
    rig.state()
    rig.send("order", order("o4", 0, nodes, [bend]))
    assert rig.last_state()["edgeStates"][0]["trajectory"] == bend["trajectory"]


CUBIC = {
    "degree": 3,
    "knotVector": [0, 0, 0, 0, 1, 1, 1, 1],
    "controlPoints": [{"x": 0.0, "y": 0.0}, {"x": 0.5, "y": 1.0}, {"x": 1.5, "y": 1.0}, {"x": 2.0, "y": 0.0}],
}


@pytest.mark.parametrize(
    ("trajectory", "why"),
    [
        # Valid against the schema, not a curve: the knot vector one short.
        ({**CUBIC, "knotVector": [0, 0, 0, 1, 1, 1, 1]}, "trajectory: knotVector has 7 values"),
        # A control point off the site: refused here, not an order that cannot be sent.
        (
            {"degree": 1, "knotVector": [0, 0, 1, 1], "controlPoints": [{"x": 0, "y": 0}, {"x": 2e5, "y": 0}]},
            "controlPoints[1] out of range",
        ),
        # A curve that does not end at its end node (section 6.6.6: the control points include it).
        (
            {"degree": 1, "knotVector": [0, 0, 1, 1], "controlPoints": [{"x": 0, "y": 0}, {"x": 1, "y": 0}]},
            "its trajectory ends at (1.00, 0.00), not at node 'n1'",
        ),
        # A weight of 0 (the standard allows it) leaves this curve undefined at its start.
        (
            {**CUBIC, "controlPoints": [{**CUBIC["controlPoints"][0], "weight": 0.0}, *CUBIC["controlPoints"][1:]]},
            "this vehicle takes finite weights > 0",
        ),
    ],
)
def test_a_trajectory_the_robot_cannot_drive_refuses_the_order_with_the_reason(
    trajectory: dict[str, Any], why: str
) -> None:
    rig = Rig()
    rig.state()
    bad = edge("n0", "n1", 1)
    bad["trajectory"] = trajectory
    outs = rig.send("order", order("o2", 0, [node("n0", 0, 0.0), node("n1", 2, 2.0)], [bad]))
    assert not any(isinstance(o, SendOrder) for o in outs)
    [err] = errors(rig)
    assert why in err["errorDescription"]


def test_an_update_is_stitched_at_the_decision_point_and_older_updates_are_refused() -> None:
    rig = Rig()
    rig.state()
    rig.send("order", BASE_WITH_HORIZON)
    rig.state(order="o1", done=1, last="n0", last_seq=0)  # still on its way to n1
    # Stitching elsewhere than the last base node (n1/2) is refused.
    rig.send("order", order("o1", 1, [node("n0", 0, 0.0), node("n1", 2, 1.0)], [edge("n0", "n1", 1)]))
    e = errors(rig)[-1]
    assert e["errorType"] == "orderUpdateError" and e["errorLevel"] == "WARNING"
    # A valid update: n1 (the decision point) released n2, n3.
    outs = rig.send(
        "order",
        order(
            "o1",
            2,
            [node("n1", 2, 1.0), node("n2", 4, 2.0), node("n3", 6, 3.0)],
            [edge("n1", "n2", 3), edge("n2", "n3", 5)],
        ),
    )
    sent = next(o for o in outs if isinstance(o, SendOrder)).fields
    assert sent["orderUpdateId"] == 2
    assert [n.nodeId for n in sent["nodes"]] == ["n1", "n2", "n3"] and all(n.released for n in sent["nodes"])
    assert [n["nodeId"] for n in rig.last_state()["nodeStates"]] == ["n1", "n2", "n3"]
    assert rig.last_state()["orderUpdateId"] == 2
    # The same update again is ignored; an older one is refused with orderUpdateError.
    assert not [o for o in rig.send("order", order("o1", 2, [node("n1", 2, 1.0)], [])) if isinstance(o, SendOrder)]
    outs = rig.send("order", order("o1", 1, [node("n1", 2, 1.0)], []))
    assert not [o for o in outs if isinstance(o, SendOrder)]
    e = errors(rig)[-1]
    assert e["errorType"] == "orderUpdateError"
    assert {"referenceKey": "headerId", "referenceValue": str(rig.hid["order"] - 1)} in e["errorReferences"]


def test_a_new_order_while_one_runs_or_far_from_the_robot_is_refused() -> None:
    rig = Rig()
    rig.state()
    rig.send("order", BASE_WITH_HORIZON)
    rig.send("order", order("o2", 0, [node("m0", 0, 0.0)], []))
    assert errors(rig)[-1]["errorType"] == "orderError"
    rig = Rig()
    rig.state()
    rig.send("order", order("far", 0, [node("m0", 0, 5.0)], []))
    assert errors(rig)[-1]["errorType"] == "noRouteError"
    assert not [o for o in rig.out if isinstance(o, SendOrder)]


def test_node_actions_wait_run_and_finish_and_a_cancel_fails_the_rest() -> None:
    rig = Rig()
    rig.state()
    dwell = {
        "actionId": "d1",
        "actionType": "dwell",
        "blockingType": "HARD",
        "actionParameters": [{"key": "duration", "value": 2}],
    }
    lamp = {
        "actionId": "uv2",
        "actionType": "payload",
        "blockingType": "HARD",
        "actionParameters": [{"key": "on", "value": True}],
    }
    outs = rig.send(
        "order",
        order(
            "o1",
            0,
            [node("n0", 0, 0.0), node("n1", 2, 1.0, actions=[dwell]), node("n2", 4, 2.0, actions=[lamp])],
            [edge("n0", "n1", 1), edge("n1", "n2", 3)],
        ),
    )
    sent = next(o for o in outs if isinstance(o, SendOrder)).fields
    assert sent["nodes"][1].actions[0].actionParameters == (KeyValue(key="duration", value="2"),)
    assert sent["nodes"][2].actions[0].actionParameters == (KeyValue(key="on", value="true"),)
    status = lambda: {a["actionId"]: a["actionStatus"] for a in rig.last_state()["actionStates"]}  # noqa: E731
    assert status() == {"d1": "WAITING", "uv2": "WAITING"}
    rig.ack("order")
    rig.state(order="o1", done=1, last="n1", last_seq=2)  # at n1, dwelling
    assert status() == {"d1": "RUNNING", "uv2": "WAITING"}
    rig.state(order="o1", done=2, last="n1", last_seq=2)
    assert status() == {"d1": "FINISHED", "uv2": "WAITING"}
    rig.send("instantActions", {"actions": [{"actionId": "c1", "actionType": "cancelOrder", "blockingType": "NONE"}]})
    assert status()["c1"] == "RUNNING"
    rig.ack("actions")
    assert status() == {"d1": "FINISHED", "uv2": "FAILED", "c1": "FINISHED"}
    s = rig.last_state()
    assert s["nodeStates"] == [] and s["orderId"] == "o1"  # VDA 5050: the ids are kept
    # Cancelling again: nothing to cancel, FAILED and a noOrderToCancel warning naming the action.
    rig.send("instantActions", {"actions": [{"actionId": "c2", "actionType": "cancelOrder", "blockingType": "NONE"}]})
    assert status()["c2"] == "FAILED"
    e = errors(rig)[-1]
    assert (
        e["errorType"] == "noOrderToCancel"
        and {"referenceKey": "actionId", "referenceValue": "c2"} in e["errorReferences"]
    )


def test_pause_and_resume_map_to_fleetlink_and_a_refusal_fails_the_action() -> None:
    rig = Rig()
    rig.state()
    outs = rig.send(
        "instantActions", {"actions": [{"actionId": "p1", "actionType": "startPause", "blockingType": "NONE"}]}
    )
    acts = next(o for o in outs if isinstance(o, SendActions)).actions
    assert acts[0].actionType.value == "pause"
    rig.ack("actions")
    outs = rig.send(
        "instantActions", {"actions": [{"actionId": "p2", "actionType": "stopPause", "blockingType": "NONE"}]}
    )
    assert next(o for o in outs if isinstance(o, SendActions)).actions[0].actionType.value == "resume"
    rig.ack("actions", AckResult.REJECTED, "lease held by op-1")
    states = {a["actionId"]: a for a in rig.last_state()["actionStates"]}
    assert states["p1"]["actionStatus"] == "FINISHED"
    assert states["p2"]["actionStatus"] == "FAILED" and states["p2"]["resultDescription"] == "lease held by op-1"
    # stateRequest and factsheetRequest are answered at once; an unknown action fails.
    outs = rig.send(
        "instantActions",
        {
            "actions": [
                {"actionId": "f", "actionType": "factsheetRequest", "blockingType": "NONE"},
                {"actionId": "x", "actionType": "pick", "blockingType": "HARD"},
            ]
        },
    )
    assert any(isinstance(o, Publish) and o.topic.endswith("/factsheet") for o in outs)
    assert errors(rig)[-1]["errorType"] == "unsupportedAction"


@pytest.mark.parametrize(
    "payload",
    [
        b"{not json",
        json.dumps({"headerId": 1, "orderId": "o"}).encode(),  # most required fields missing
        json.dumps(
            {
                "headerId": 7,
                "timestamp": "2026-01-01T00:00:00Z",
                "version": "2.1.0",
                "manufacturer": "fleetlink",
                "serialNumber": "r1",
                "orderId": "o",
                "orderUpdateId": -1,
                "nodes": [],
                "edges": [],
            }
        ).encode(),
        json.dumps([1, 2]).encode(),
        # The schema's "format": "date-time" (checked: jsonschema needs rfc3339-validator for it).
        json.dumps({**HEADER, **BASE_WITH_HORIZON, "timestamp": "yesterday, 5 pm"}).encode(),
        json.dumps({**HEADER, **BASE_WITH_HORIZON, "timestamp": "2026-01-01T00:00:00"}).encode(),  # no zone
    ],
)
def test_a_malformed_order_is_refused_with_a_validation_error_and_the_vehicle_keeps_serving(payload: bytes) -> None:
    rig = Rig()
    rig.state()
    outs = rig.send("order", payload)
    assert not [o for o in outs if isinstance(o, SendOrder)]
    e = errors(rig)[-1]
    assert e["errorType"] == "validationError" and e["errorLevel"] == "WARNING"
    assert {"referenceKey": "topic", "referenceValue": "order"} in e["errorReferences"]
    assert rig.core.refused["order/validationError"] == 1
    # The next valid order runs, and clears the order's refusal.
    outs = rig.send("order", BASE_WITH_HORIZON)
    assert [o for o in outs if isinstance(o, SendOrder)]
    assert all(e["errorType"] != "validationError" for e in errors(rig))


def test_errors_expire_and_the_finished_order_leaves_its_last_base_node() -> None:
    rig = Rig()
    rig.state()
    rig.send("order", b"[]")
    assert errors(rig)
    rig.now = 31.0
    rig._check(rig.core.tick(rig.now, rig.wall()))
    assert errors(rig) == []
    rig.send("order", order("o1", 0, [node("n0", 0, 0.0), node("n1", 2, 1.0)], [edge("n0", "n1", 1)]))
    rig.fleet(
        rig.counter.make(
            Event,
            kind="order",
            text="done",
            severity=Severity.INFO,
            data=(KeyValue(key="order", value="o1"), KeyValue(key="outcome", value="finished")),
        )
    )
    s = rig.last_state()
    assert s["nodeStates"] == [] and (s["lastNodeId"], s["lastNodeSequenceId"]) == ("n1", 2)
    # Idle again: the lease goes back.
    rig.now = 60.0
    assert any(isinstance(o, SendLease) and o.release for o in rig._check(rig.core.tick(rig.now, rig.wall())))


def test_connection_factsheet_and_headers_count_per_topic() -> None:
    rig = Rig()
    a = rig._check(rig.core.connection("ONLINE", rig.wall()))[0]
    b = rig._check(rig.core.connection("OFFLINE", rig.wall()))[0]
    will = rig.core.will(rig.wall())
    assert (a.retain, a.qos, a.doc["headerId"], b.doc["headerId"]) == (True, 1, 0, 1)
    assert will.doc["connectionState"] == "CONNECTIONBROKEN" and OFFICIAL.problems("connection", will.doc) == []
    f = rig._check(rig.core.factsheet(rig.wall()))[0]
    assert f.doc["headerId"] == 0 and f.doc["version"] == "2.1.0"
    assert f.retain  # section 6.15: all messages on this topic retained
    types = {x["actionType"] for x in f.doc["protocolFeatures"]["agvActions"]}
    assert {"startPause", "stopPause", "cancelOrder", "stateRequest", "factsheetRequest", "payload", "dwell"} <= types
    optional = {p["parameter"]: p["support"] for p in f.doc["protocolFeatures"]["optionalParameters"]}
    assert optional["order.edges.trajectory"] == "SUPPORTED"
    assert f.doc["protocolLimits"]["maxArrayLens"]["trajectory.controlPoints"] == 64


def test_the_duplicate_ack_of_the_other_links_copy_coming_first_does_not_lose_the_real_one() -> None:
    # Redundant sending: the robot acks the copy it ran on one link and the other copy as a
    # duplicate on the other; the duplicate's ack may reach the bridge first.
    rig = Rig()
    rig.state()
    rig.send("instantActions", {"actions": [{"actionId": "p1", "actionType": "startPause", "blockingType": "NONE"}]})
    rig.ack("actions", AckResult.DUPLICATE, "already received on zenoh")
    rig.ack("actions")
    assert {a["actionId"]: a["actionStatus"] for a in rig.last_state()["actionStates"]}["p1"] == "FINISHED"
    # ... and a refusal of an order still reaches the master after the duplicate's ack.
    rig.send("order", BASE_WITH_HORIZON)
    rig.ack("order", AckResult.DUPLICATE, "already received on mqtt")
    rig.ack("order", AckResult.REJECTED, "lease held by op-1")
    assert errors(rig)[-1]["errorType"] == "orderError"
    assert rig.last_state()["nodeStates"] == []


def order_event(rig: Rig, oid: str, **data: str) -> None:
    kvs = (KeyValue(key="order", value=oid), *(KeyValue(key=k, value=v) for k, v in data.items()))
    rig.fleet(rig.counter.make(Event, kind="order", text=f"order {oid}", severity=Severity.INFO, data=kvs))


def tick(rig: Rig, now: float) -> list[Any]:
    rig.now = now
    return rig._check(rig.core.tick(now, rig.wall()))


DWELL = {
    "actionId": "d1",
    "actionType": "dwell",
    "blockingType": "HARD",
    "actionParameters": [{"key": "duration", "value": 2}],
}
THREE = order(
    "o1",
    0,
    [node("n0", 0, 0.0), node("n1", 2, 1.0, actions=[DWELL]), node("n2", 4, 2.0)],
    [edge("n0", "n1", 1), edge("n1", "n2", 3)],
)


def skip_errors(rig: Rig) -> list[dict[str, Any]]:
    return [e for e in errors(rig) if e["errorType"] == "noRouteError"]


def refs(error: dict[str, Any]) -> list[tuple[str, str]]:
    return [(r["referenceKey"], r["referenceValue"]) for r in error["errorReferences"]]


def test_a_skipped_node_leaves_node_states_without_becoming_the_last_node_and_its_actions_fail() -> None:
    # The robot reports only counts (OrderProgress): n1 done while n0 stays the last node reached.
    rig = Rig()
    rig.state()
    rig.send("order", THREE)
    rig.ack("order")
    rig.state(order="o1", done=1, last="n0", last_seq=0)
    rig.state(order="o1", done=2, skipped=1, last="n0", last_seq=0)
    s = rig.last_state()
    assert [n["nodeId"] for n in s["nodeStates"]] == ["n2"]
    assert [e["edgeId"] for e in s["edgeStates"]] == ["n1-n2"]  # the way on to n2 is still to drive
    assert (s["lastNodeId"], s["lastNodeSequenceId"]) == ("n0", 0)  # section 6.10.2: traversed nodes only
    d1 = next(a for a in s["actionStates"] if a["actionId"] == "d1")
    assert d1["actionStatus"] == "FAILED" and "n1 skipped" in d1["resultDescription"]
    (e,) = skip_errors(rig)
    assert e["errorLevel"] == "WARNING"
    assert {("orderId", "o1"), ("nodeId", "n1"), ("sequenceId", "2"), ("actionId", "d1")} <= set(refs(e))
    # The robot's event naming the node, coming after, changes nothing; the warning is not doubled.
    order_event(rig, "o1", skipped="n1", sequenceId="2")
    assert len(skip_errors(rig)) == 1 and rig.core.skipped_nodes == 1
    # It reaches n2 and finishes: n2 is the last node; the warning stays until a new order.
    rig.state(order="o1", done=3, skipped=1, last="n2", last_seq=4)
    order_event(rig, "o1", outcome="finished")
    s = rig.last_state()
    assert s["nodeStates"] == [] and s["lastNodeId"] == "n2" and len(skip_errors(rig)) == 1
    rig.send("order", order("o2", 0, [node("m0", 0, 0.0)], []))
    assert skip_errors(rig) == []


def test_a_skipped_last_node_named_by_the_robots_event_is_not_reported_as_reached() -> None:
    # Skipping the last node ends the order at once: no State with that progress comes, only the
    # robot's events (agent/core.py: the skip names the node, then the order finishes).
    rig = Rig()
    rig.state()
    rig.send("order", order("o1", 0, [node("n0", 0, 0.0), node("n1", 2, 1.0)], [edge("n0", "n1", 1)]))
    rig.ack("order")
    rig.state(order="o1", done=1, last="n0", last_seq=0)
    order_event(rig, "o1", skipped="n1", sequenceId="2")
    s = rig.last_state()
    assert s["nodeStates"] == [] and s["edgeStates"] == []
    order_event(rig, "o1", outcome="finished")
    s = rig.last_state()
    assert (s["lastNodeId"], s["lastNodeSequenceId"]) == ("n0", 0)
    assert ("nodeId", "n1") in refs(skip_errors(rig)[0])
    # An event for another order, or without a usable sequence id, is not taken for a skip.
    order_event(rig, "o-other", skipped="n0", sequenceId="0")
    order_event(rig, "o1", skipped="n0", sequenceId="zero")
    assert len(skip_errors(rig)) == 1


def test_an_update_stitched_at_a_skipped_decision_point_is_accepted_and_does_not_drive_there() -> None:
    rig = Rig()
    rig.state()
    rig.send("order", BASE_WITH_HORIZON)  # n0, n1 base; n2 horizon
    rig.ack("order")
    rig.state(order="o1", done=2, skipped=1, last="n0", last_seq=0)  # n1 (the decision point) skipped
    assert [n["nodeId"] for n in rig.last_state()["nodeStates"]] == ["n2"]
    outs = rig.send(
        "order",
        order(
            "o1",
            1,
            [node("n1", 2, 1.0), node("n2", 4, 2.0), node("n3", 6, 3.0)],
            [edge("n1", "n2", 3), edge("n2", "n3", 5)],
        ),
    )
    assert not [e for e in errors(rig) if e["errorType"] == "orderUpdateError"]
    sent = next(o for o in outs if isinstance(o, SendOrder)).fields
    assert [n.nodeId for n in sent["nodes"]] == ["n2", "n3"]
    assert [n["nodeId"] for n in rig.last_state()["nodeStates"]] == ["n2", "n3"]


def test_node_states_echo_node_positions_unchanged_and_a_first_node_within_its_deviation_counts_where_the_robot_is() -> (
    None
):
    rig = Rig()
    rig.state(x=0.7)
    nodes = [node("n0", 0, 0.0), node("n1", 2, 1.5)]
    nodes[0]["nodePosition"].update(allowedDeviationXY=2.0, theta=-3.0, allowedDeviationTheta=0.1)
    nodes[1]["nodePosition"].update(allowedDeviationXY=0.15, mapDescription="ground floor")
    outs = rig.send("order", order("o1", 0, nodes, [edge("n0", "n1", 1)]))
    s = rig.last_state()
    assert [n["nodePosition"] for n in s["nodeStates"]] == [n["nodePosition"] for n in nodes]
    sent = next(o for o in outs if isinstance(o, SendOrder)).fields["nodes"]
    # n0: the robot stands 0.7 m from it, within its 2 m: reached where it is (section 6.6.3.1)
    assert (sent[0].x, sent[0].y, sent[1].x, sent[1].y) == (0.7, 0.0, 1.5, 0.0)
    assert [n.allowedDeviationXY for n in sent] == [1.0, 0.15]
    # The factsheet says allowedDeviationXY is used, and not allowedDeviationTheta.
    f = rig._check(rig.core.factsheet(rig.wall()))[0].doc
    params = {p["parameter"] for p in f["protocolFeatures"]["optionalParameters"]}
    assert "order.nodes.nodePosition.allowedDeviationXY" in params
    assert "order.nodes.nodePosition.allowedDeviationTheta" not in params


def leases(outs: list[Any]) -> list[bool]:
    """The lease requests among ``outs``: True for a release."""
    return [o.release for o in outs if isinstance(o, SendLease)]


def test_the_lease_is_renewed_often_enough_for_contact_and_released_once_idle_never_renewed_after() -> None:
    rig = Rig()
    rig.state()
    assert leases(rig.send("order", THREE)) == [False]
    rig.ack("order")
    # While the order runs: renewed every LEASE_RENEW_S (the agent's contact timeout is 6 s).
    renewals = [t for t in (0.1 * i for i in range(1, 101)) if leases(tick(rig, t)) == [False]]
    assert len(renewals) == 5 and all(b - a < 2.2 for a, b in itertools.pairwise(renewals))
    # It finishes just before a renewal would be due: idle from then, released after LEASE_IDLE_S,
    # and the renewal that was due in between is not sent after the release.
    order_event(rig, "o1", outcome="finished")
    sent = [(round(t, 1), leases(tick(rig, t))) for t in (10.0 + 0.1 * i for i in range(1, 100))]
    requests = [(t, r) for t, r in sent if r]
    assert [r for _, r in requests][-1] == [True]
    release_t = requests[-1][0]
    assert not [t for t, r in sent if r and t > release_t]
    # The robot's word from before the release reached it: not a re-grant.
    rig.now = release_t + 0.5
    assert leases(rig.fleet(rig.counter.make(Lease, holder=SENDER, until=rig.wall() + 50))) == []
    # Later still naming the bridge: a late renewal's copy re-granted it: released again, once.
    rig.now = release_t + 4.0
    assert leases(rig.fleet(rig.counter.make(Lease, holder=SENDER, until=rig.wall() + 50))) == [True]
    rig.now = release_t + 4.5
    assert leases(rig.fleet(rig.counter.make(Lease, holder=SENDER, until=rig.wall() + 50))) == []
    assert rig.core.lease_rereleases == 1
    assert not [r for r in (leases(tick(rig, release_t + 5 + i)) for i in range(10)) if r]
    # A new order asks again.
    assert leases(rig.send("order", order("o2", 0, [node("m0", 0, 0.0)], []))) == [False]


def test_a_stale_lease_without_the_bridge_does_not_stop_the_renewals() -> None:
    # The robot's Lease published before it saw the bridge's request names nobody.
    rig = Rig()
    rig.state()
    rig.send("order", THREE)
    rig.fleet(rig.counter.make(Lease, holder="", until=0.0))
    assert leases(tick(rig, 2.5)) == [False]


def states(rig: Rig) -> list[dict[str, Any]]:
    return [o.doc for o in rig.out if isinstance(o, Publish) and o.topic.endswith("/state")]


def test_new_base_request_is_set_near_the_end_of_the_base_while_a_horizon_waits_and_cleared_by_a_new_base() -> None:
    # VDA 5050 2.1.0 section 6.10.3 and the state table: "the AGV is almost at the end of the base
    # and will reduce speed, if no new base is transmitted. Trigger for master control to send a
    # new base." Every state below is checked against the official schema (Rig._check).
    assert NEW_BASE_REQUEST_M == 1.0
    rig = Rig()
    rig.state()
    flag = lambda: rig.last_state()["newBaseRequest"]  # noqa: E731
    rig.send(
        "order",
        order(
            "o1",
            0,
            [node("n0", 0, 0.0), node("n1", 2, 3.0), node("n2", 4, 5.0, released=False)],
            [edge("n0", "n1", 1), edge("n1", "n2", 3, released=False)],
        ),
    )
    rig.ack("order")
    assert flag() is False
    rig.state(order="o1", done=1, last="n0", last_seq=0, x=1.5)  # 1.5 m of base left
    assert flag() is False
    published = len(states(rig))
    rig.state(order="o1", done=1, last="n0", last_seq=0, x=2.2)  # 0.8 m left: ask for more
    assert flag() is True and len(states(rig)) == published + 1  # a state at once, not at the period
    rig.state(order="o1", done=1, last="n0", last_seq=0, x=1.9)  # the pose jitters back (1.1 m): held
    assert flag() is True
    # The master sends a new base (n2 released, n3 the horizon): 2.8 m left, no request.
    rig.send(
        "order",
        order(
            "o1",
            1,
            [node("n1", 2, 3.0), node("n2", 4, 5.0), node("n3", 6, 7.0, released=False)],
            [edge("n1", "n2", 3), edge("n2", "n3", 5, released=False)],
        ),
    )
    assert flag() is False
    # The robot reaches n2 before the master says more: it waits there for the horizon; requested.
    rig.state(order="o1", update=1, done=2, last="n2", last_seq=4, x=5.0, waiting="horizon")
    s = rig.last_state()
    assert s["newBaseRequest"] is True and [n["nodeId"] for n in s["nodeStates"]] == ["n3"]
    # Everything released: no horizon, nothing to request, even at the very end of the base.
    rig.send("order", order("o1", 2, [node("n2", 4, 5.0), node("n3", 6, 7.0)], [edge("n2", "n3", 5)]))
    assert flag() is False
    rig.state(order="o1", update=2, done=0, last="n2", last_seq=4, x=6.9)
    assert flag() is False


def test_a_base_without_a_horizon_never_requests_a_new_base_and_a_skipped_base_end_does() -> None:
    rig = Rig()
    rig.state()
    rig.send("order", order("o1", 0, [node("n0", 0, 0.0), node("n1", 2, 0.5)], [edge("n0", "n1", 1)]))
    rig.ack("order")
    rig.state(order="o1", done=1, last="n0", last_seq=0, x=0.4)
    assert rig.last_state()["newBaseRequest"] is False
    # The decision point n1 skipped (no way there): the base is used up, the horizon waits: asked.
    rig = Rig()
    rig.state()
    rig.send("order", BASE_WITH_HORIZON)  # n0 (0), n1 (1 m) released, n2 (2 m) horizon
    rig.ack("order")
    assert rig.last_state()["newBaseRequest"] is True  # 1.0 m of base: at the threshold already
    rig = Rig()
    rig.state(x=-2.0)
    nodes = [node("n0", 0, -2.0), node("n1", 2, 1.0), node("n2", 4, 2.0, released=False)]
    rig.send("order", order("o1", 0, nodes, [edge("n0", "n1", 1), edge("n1", "n2", 3, released=False)]))
    rig.ack("order")
    rig.state(order="o1", done=1, last="n0", last_seq=0, x=-2.0)
    assert rig.last_state()["newBaseRequest"] is False
    rig.state(order="o1", done=2, skipped=1, last="n0", last_seq=0, x=-1.5)
    s = rig.last_state()
    assert s["newBaseRequest"] is True and [n["nodeId"] for n in s["nodeStates"]] == ["n2"]


def action_status(rig: Rig) -> dict[str, str]:
    return {a["actionId"]: a["actionStatus"] for a in rig.last_state()["actionStates"]}


def timeouts(rig: Rig) -> list[dict[str, Any]]:
    return [e for e in errors(rig) if e["errorType"] == "actionTimeout"]


def test_an_instant_action_the_robot_never_acks_fails_with_an_action_timeout() -> None:
    rig = Rig()
    rig.state()
    rig.send("instantActions", {"actions": [{"actionId": "p1", "actionType": "startPause", "blockingType": "NONE"}]})
    tick(rig, ACTION_TIMEOUT_S - 0.1)
    assert action_status(rig)["p1"] == "INITIALIZING" and timeouts(rig) == []
    tick(rig, ACTION_TIMEOUT_S)
    p1 = next(a for a in rig.last_state()["actionStates"] if a["actionId"] == "p1")
    assert p1["actionStatus"] == "FAILED" and "no ack from the robot" in p1["resultDescription"]
    (e,) = timeouts(rig)
    assert e["errorLevel"] == "WARNING" and ("actionId", "p1") in refs(e) and "startPause" in e["errorDescription"]
    assert rig.core.timed_out_actions == 1
    # The ack coming after all does not turn the FAILED action FINISHED (the master was told).
    rig.ack("actions")
    assert action_status(rig)["p1"] == "FAILED"
    # Like the other refusals, the warning goes after ERROR_HOLD_S.
    tick(rig, ACTION_TIMEOUT_S + 31.0)
    assert timeouts(rig) == []


def test_an_unacked_cancel_fails_and_keeps_the_nodes_until_the_robot_says_it_cancelled() -> None:
    rig = Rig()
    rig.state()
    rig.send("order", THREE)
    rig.ack("order")
    rig.send("instantActions", {"actions": [{"actionId": "c1", "actionType": "cancelOrder", "blockingType": "NONE"}]})
    assert action_status(rig)["c1"] == "RUNNING"
    rig.now = ACTION_TIMEOUT_S / 2
    rig.state(order="o1", done=1, last="n0", last_seq=0)  # the robot drives on: not a word on the cancel
    tick(rig, ACTION_TIMEOUT_S)
    s = rig.last_state()
    assert action_status(rig)["c1"] == "FAILED" and [n["nodeId"] for n in s["nodeStates"]] == ["n1", "n2"]
    assert action_status(rig)["d1"] == "WAITING"  # the robot named its order all along
    # The late ack says the robot did cancel: the order ends as it has on the robot.
    rig.ack("actions")
    s = rig.last_state()
    assert s["nodeStates"] == [] and action_status(rig) == {"d1": "FAILED", "c1": "FAILED"}


def test_node_actions_fail_when_the_robot_says_nothing_of_their_order_for_the_timeout() -> None:
    rig = Rig()
    rig.state()
    rig.send("order", THREE)  # d1: a dwell at n1
    rig.ack("order")
    # The robot names the order in its state every second for a minute (a long way to n1):
    # the action waits all along.
    for t in range(1, 61):
        rig.now = float(t)
        rig.state(order="o1", done=1, last="n0", last_seq=0)
    assert action_status(rig)["d1"] == "WAITING"
    # Then silence (the robot out of reach).
    tick(rig, 60.0 + ACTION_TIMEOUT_S - 0.1)
    assert action_status(rig)["d1"] == "WAITING"
    tick(rig, 60.0 + ACTION_TIMEOUT_S)
    s = rig.last_state()
    d1 = next(a for a in s["actionStates"] if a["actionId"] == "d1")
    assert d1["actionStatus"] == "FAILED" and "no word from the robot on order o1" in d1["resultDescription"]
    (e,) = timeouts(rig)
    assert e["errorLevel"] == "WARNING" and {("orderId", "o1"), ("actionId", "d1")} <= set(refs(e))
    assert [n["nodeId"] for n in s["nodeStates"]] == ["n1", "n2"]  # as last known
    # The robot back, at n1 and past it: the action stays FAILED; the order finishes.
    rig.state(order="o1", done=2, last="n1", last_seq=2)
    order_event(rig, "o1", outcome="finished")
    assert action_status(rig)["d1"] == "FAILED" and rig.last_state()["nodeStates"] == []
    assert len(timeouts(rig)) == 1  # held until the next new order
    rig.send("order", order("o2", 0, [node("m0", 0, 0.0)], []))
    assert timeouts(rig) == []


def test_an_order_the_robot_never_takes_up_is_dropped_after_the_timeout_and_the_vehicle_is_idle_again() -> None:
    # No ack, and the robot's states go on naming no order (it never got this one).
    rig = Rig()
    rig.state()
    rig.send("order", THREE)
    for t in range(1, int(ACTION_TIMEOUT_S)):
        rig.now = float(t)
        rig.state()
    assert action_status(rig)["d1"] == "WAITING"
    # Meanwhile another order is refused: the vehicle is busy with this one.
    assert rig.send("order", order("o2", 0, [node("m0", 0, 0.0)], [])) and any(
        e["errorType"] == "orderError" and "still running" in e["errorDescription"] for e in errors(rig)
    )
    tick(rig, ACTION_TIMEOUT_S)
    s = rig.last_state()
    assert s["nodeStates"] == [] and s["edgeStates"] == [] and action_status(rig)["d1"] == "FAILED"
    (e,) = [e for e in errors(rig) if e["errorType"] == "orderError" and "never took" in e["errorDescription"]]
    assert e["errorLevel"] == "WARNING" and ("orderId", "o1") in refs(e)
    assert rig.core.dropped_orders == 1 and not rig.core.busy
    # The robot answers again: the master sends the same order again, and it goes to the robot.
    sent = [o for o in rig.send("order", THREE) if isinstance(o, SendOrder)]
    assert len(sent) == 1 and [n["nodeId"] for n in rig.last_state()["nodeStates"]] == ["n0", "n1", "n2"]
    rig.ack("order")
    tick(rig, 3 * ACTION_TIMEOUT_S)
    assert rig.last_state()["nodeStates"] != [] and rig.core.dropped_orders == 1  # taken: never dropped


def test_a_dropped_order_that_reaches_the_robot_after_all_is_cancelled_on_the_robot() -> None:
    rig = Rig()
    rig.state()
    rig.send("order", THREE)
    tick(rig, ACTION_TIMEOUT_S)
    assert rig.core.dropped_orders == 1
    rig.send("order", order("o2", 0, [node("m0", 0, 0.0)], []))  # the master moved on
    rig.now = ACTION_TIMEOUT_S + 1.0

    # The robot got o1 late (a queue delivered after all) and runs it: it is cancelled there.
    def cancels() -> list[str]:
        return [a.actionType.value for o in rig.out if isinstance(o, SendActions) for a in o.actions]

    rig.state(order="o1", done=1, last="n0", last_seq=0)
    assert cancels() == ["cancel"]
    rig.now += 1.0
    rig.state(order="o1", done=1, last="n0", last_seq=0)
    assert cancels() == ["cancel"]  # once per timeout, not per state


def test_the_actions_of_an_update_the_robot_never_gets_fail_and_the_running_bases_do_not() -> None:
    rig = Rig()
    rig.state()
    rig.send(
        "order",
        order(
            "o1",
            0,
            [node("n0", 0, 0.0), node("n1", 2, 1.0, actions=[DWELL]), node("n2", 4, 2.0, released=False)],
            [edge("n0", "n1", 1), edge("n1", "n2", 3, released=False)],
        ),
    )
    rig.ack("order")
    lamp = {
        "actionId": "uv3",
        "actionType": "payload",
        "blockingType": "HARD",
        "actionParameters": [{"key": "on", "value": True}],
    }
    rig.send(
        "order",
        order(
            "o1",
            1,
            [node("n1", 2, 1.0), node("n2", 4, 2.0), node("n3", 6, 3.0, actions=[lamp])],
            [edge("n1", "n2", 3), edge("n2", "n3", 5)],
        ),
    )
    # The update is lost: the robot's states go on naming update 0 of the order.
    for t in range(1, int(ACTION_TIMEOUT_S) + 1):
        rig.now = float(t)
        rig.state(order="o1", update=0, done=1, last="n0", last_seq=0)
    assert action_status(rig) == {"d1": "WAITING", "uv3": "FAILED"}
    (e,) = timeouts(rig)
    assert ("actionId", "uv3") in refs(e) and ("orderUpdateId", "1") in refs(e)


def test_a_command_the_operator_link_gives_up_on_fails_its_action_or_drops_its_order_at_once() -> None:
    # The link re-sends an unacked command on both links and gives up after about a second: what
    # waits on it fails then, not after ACTION_TIMEOUT_S.
    rig = Rig()
    rig.state()
    rig.send("instantActions", {"actions": [{"actionId": "p1", "actionType": "startPause", "blockingType": "NONE"}]})
    hid = rig.fleet_hid
    rig.now = 1.2
    rig._check(rig.core.undelivered("actions", hid, "no ack after 4 sends", rig.now))
    tick(rig, 1.3)
    p1 = next(a for a in rig.last_state()["actionStates"] if a["actionId"] == "p1")
    assert p1["actionStatus"] == "FAILED" and "no ack after 4 sends" in p1["resultDescription"]
    rig.send("order", THREE)
    rig._check(rig.core.undelivered("order", rig.fleet_hid, "no ack after 4 sends", 2.5))
    tick(rig, 2.6)
    s = rig.last_state()
    assert s["nodeStates"] == [] and rig.core.dropped_orders == 1 and not rig.core.busy
    assert any("no ack after 4 sends" in e["errorDescription"] for e in errors(rig) if e["errorType"] == "orderError")
    # A give-up on a command the robot did answer (an ack came first) changes nothing.
    rig.send("order", order("o2", 0, [node("m0", 0, 0.0), node("m1", 2, 1.0)], [edge("m0", "m1", 1)]))
    rig.ack("order")
    rig._check(rig.core.undelivered("order", rig.fleet_hid, "no ack after 4 sends", 3.0))
    assert rig.core.dropped_orders == 1 and rig.core.busy
