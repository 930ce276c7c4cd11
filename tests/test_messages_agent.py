"""Issue-5 messages: round trips with realistic values, and validation of what may travel."""

from __future__ import annotations

from typing import Any

import msgpack
import pytest

from fleetlink.shared import wire
from fleetlink.shared.messages import (
    Ack,
    AckResult,
    Action,
    ActionType,
    AgvPosition,
    BatteryState,
    CommsPolicy,
    Connection,
    ConnectionState,
    Contact,
    ErrorLevel,
    EStop,
    Event,
    Goal,
    Home,
    HomeSource,
    InstantActions,
    KeyValue,
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
    Velocity,
)
from fleetlink.shared.wire import Header, WireError, decode, decode_key, encode

H = Header(headerId=3, timestamp=1_767_225_600.5, version="1.0.0", robot="r1", sender="operator-1")


def state(**over: Any) -> State:
    fields: dict[str, Any] = {
        "header": H,
        "agvPosition": AgvPosition(
            x=1.5, y=-2.0, theta=0.25, mapId="office", positionInitialized=True, localizationScore=0.9
        ),
        "velocity": Velocity(vx=0.3, omega=-0.1),
        "batteryState": BatteryState(batteryCharge=87.0, charging=False),
        "errors": (StateError(errorType="board", errorLevel=ErrorLevel.WARNING, errorDescription="motor L hot"),),
        "operatingMode": OperatingMode.AUTOMATIC,
        "safetyState": SafetyState(eStop=EStop.NONE, fieldViolation=False),
        "driveMode": "goto",
        "links": LinkStatus(zenoh=True, mqtt=False),
        "uwbStale": False,
        "payloadOn": True,
        "boardConnected": True,
        "orderId": "o-17",
        "orderUpdateId": 2,
        "goal": Goal(x=3.0, y=4.0, theta=None),
        "driving": True,
        "paused": False,
        "home": Home(x=0.5, y=-1.0, theta=0.0, source=HomeSource.LOCALISED),
        "contact": Contact(policy=CommsPolicy.RETRACE, lost=False, action="", silent_s=1.5),
    }
    fields.update(over)
    return State(**fields)


EXAMPLES = [
    state(),
    Pose(
        header=H,
        x=1.0,
        y=2.0,
        theta=-3.1,
        sd_x_m=0.05,
        sd_y_m=0.04,
        sd_theta_rad=0.02,
        odom_x=0.9,
        odom_y=2.1,
        odom_theta=-3.0,
        vx=0.2,
        omega=0.0,
        uwbStale=True,
    ),
    Connection(header=H, connectionState=ConnectionState.CONNECTIONBROKEN),
    Order(header=H, orderId="o-1", orderUpdateId=0, goal=Goal(x=1.0, y=2.0, theta=1.57), returnHome=False),
    Order(header=H, orderId="home-1", orderUpdateId=4, goal=None, returnHome=True),
    InstantActions(
        header=H,
        actions=(
            Action(actionId="a1", actionType=ActionType.ESTOP, actionParameters=()),
            Action(actionId="a2", actionType=ActionType.PAYLOAD, actionParameters=(KeyValue(key="on", value="true"),)),
        ),
    ),
    Teleop(header=H, v=0.3, omega=-0.5, ttl_s=0.5),
    Ack(
        header=H,
        commandTopic="order",
        commandSender="operator-1",
        commandHeaderId=41,
        orderId="o-1",
        orderUpdateId=0,
        result=AckResult.DUPLICATE,
        reason="already executed",
        link=LinkName.MQTT,
    ),
    Event(
        header=H,
        kind="guard_refusal",
        text="forward refused: obstacle at 0.18 m",
        severity=Severity.WARNING,
        data=(KeyValue(key="distance_m", value="0.18"),),
    ),
]


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip(msg: wire.Message) -> None:
    raw = encode(msg)
    assert decode(type(msg), raw) == msg
    assert decode_key(wire.key_of(msg), raw) == msg


def test_topics_and_vda_names_on_the_wire() -> None:
    assert {m.TOPIC for m in EXAMPLES} == {
        "state",
        "pose",
        "connection",
        "order",
        "actions",
        "teleop",
        "ack",
        "events",
    }
    obj = msgpack.unpackb(encode(state()), raw=False)
    assert set(obj["agvPosition"]) == {"x", "y", "theta", "mapId", "positionInitialized", "localizationScore"}
    assert obj["safetyState"] == {"eStop": "NONE", "fieldViolation": False}
    assert obj["batteryState"] == {"batteryCharge": 87.0, "charging": False}
    assert obj["operatingMode"] == "AUTOMATIC"
    assert msgpack.unpackb(encode(EXAMPLES[2]), raw=False)["connectionState"] == "CONNECTIONBROKEN"
    actions = msgpack.unpackb(encode(EXAMPLES[5]), raw=False)["actions"]
    assert [a["actionType"] for a in actions] == ["estop", "payload"]


def _mutate(msg: wire.Message, path: str, value: Any) -> bytes:
    obj = msgpack.unpackb(encode(msg), raw=False)
    node = obj
    *parents, last = path.split(".")
    for p in parents:
        node = node[int(p)] if isinstance(node, list) else node[p]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return msgpack.packb(obj, use_bin_type=True)


@pytest.mark.parametrize(
    ("msg", "path", "value", "fragment"),
    [
        (EXAMPLES[6], "v", float("nan"), "v: non-finite"),
        (EXAMPLES[6], "ttl_s", 0.0, "ttl_s: 0.0 out of range"),
        (EXAMPLES[6], "ttl_s", 60.0, "ttl_s: 60.0 out of range"),
        (EXAMPLES[6], "omega", "fast", "omega: expected"),
        (EXAMPLES[3], "orderUpdateId", -1, "orderUpdateId: -1 out of range"),
        (EXAMPLES[3], "goal.theta", 7.0, "goal.theta: 7.0 out of range"),
        (EXAMPLES[3], "orderId", "x" * 65, "orderId"),
        (EXAMPLES[5], "actions.0.actionType", "selfdestruct", "actions[0].actionType"),
        (EXAMPLES[5], "actions", [{"actionId": "a", "actionType": "stop", "actionParameters": []}] * 17, "actions"),
        (EXAMPLES[2], "connectionState", "MAYBE", "connectionState"),
        (EXAMPLES[0], "agvPosition.localizationScore", 1.5, "agvPosition.localizationScore"),
        (EXAMPLES[0], "safetyState.eStop", True, "safetyState.eStop"),
        (EXAMPLES[7], "result", "ok", "result"),
        (EXAMPLES[8], "severity", "panic", "severity"),
        (EXAMPLES[1], "sd_x_m", -0.1, "sd_x_m"),
    ],
)
def test_rejects_bad_fields(msg: wire.Message, path: str, value: Any, fragment: str) -> None:
    with pytest.raises(WireError) as info:
        decode(type(msg), _mutate(msg, path, value))
    assert fragment in info.value.reason


def test_rejects_unknown_and_missing_fields() -> None:
    obj = msgpack.unpackb(encode(EXAMPLES[6]), raw=False)
    with pytest.raises(WireError, match="bogus"):
        decode(Teleop, msgpack.packb({**obj, "bogus": 1}))
    del obj["ttl_s"]
    with pytest.raises(WireError, match="ttl_s: missing field"):
        decode(Teleop, msgpack.packb(obj))


def test_command_sender_travels_in_the_header() -> None:
    # The agent dedupes on (header.sender, header.headerId): both must survive the trip.
    back = decode(Teleop, encode(EXAMPLES[6]))
    assert (back.header.sender, back.header.headerId) == ("operator-1", 3)
