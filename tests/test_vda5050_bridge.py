"""The VDA 5050 bridge's shell: without a broker, a flood of fleetlink ``State`` under ever new robot
ids does not grow the bridge without bound (capped, counted, logged once; it keeps serving), and an
order the operator link gives up on is dropped at the next tick; on a real Mosquitto, a vehicle whose
connection vanishes leaves its last will ``CONNECTIONBROKEN`` retained."""

from __future__ import annotations

import json
import logging
from typing import Any

import pytest

from fleetlink.operator.linkmanager import Failed
from fleetlink.operator.vda5050 import bridge as bridge_module
from fleetlink.operator.vda5050.bridge import Vda5050Bridge
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import (
    AgvPosition,
    BatteryState,
    CommsPolicy,
    Contact,
    EStop,
    LinkStatus,
    OperatingMode,
    Order,
    SafetyState,
    State,
    Velocity,
)
from fleetlink.shared.mqtt import MqttSettings


class FakeEndpoint:
    """Stands in for ``links.mqtt.MqttEndpoint``: records what the vehicle would publish."""

    made = 0

    def __init__(self, settings: Any, **kwargs: Any) -> None:
        FakeEndpoint.made += 1
        self.published: list[tuple[str, bytes]] = []

    def subscribe(self, topic: str, handler: Any) -> None:
        pass

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass

    def publish(self, topic: str, payload: bytes, **kwargs: Any) -> None:
        self.published.append((topic, payload))


class FakeLink:
    sender = "vda5050"

    def __init__(self) -> None:
        self.counter = wire.HeaderCounter(SimClock(), robot="r0", sender=self.sender)
        self.sent: list[wire.Message] = []
        self.listeners: list[Any] = []

    def add_sink(self, sink: Any) -> None:
        pass

    def add_listener(self, listener: Any) -> None:
        self.listeners.append(listener)

    def send(self, cls: type[wire.Message], robot: str, **fields: Any) -> wire.Message:
        msg = cls(header=self.counter.header(cls.TOPIC, robot=robot), **fields)
        self.sent.append(msg)
        return msg

    def publish(self, msg: wire.Message, **kwargs: Any) -> None:
        pass

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass


def state(robot: str) -> State:
    counter = wire.HeaderCounter(SimClock(), robot=robot, sender=f"agent-{robot}")
    return counter.make(
        State,
        agvPosition=AgvPosition(x=0.0, y=0.0, theta=0.0, mapId="", positionInitialized=True, localizationScore=1.0),
        velocity=Velocity(vx=0.0, omega=0.0),
        batteryState=BatteryState(batteryCharge=80.0, charging=False),
        errors=(),
        operatingMode=OperatingMode.AUTOMATIC,
        safetyState=SafetyState(eStop=EStop.NONE, fieldViolation=False),
        driveMode="idle",
        links=LinkStatus(zenoh=True, mqtt=True),
        uwbStale=False,
        payloadOn=False,
        boardConnected=True,
        orderId="",
        orderUpdateId=0,
        goal=None,
        driving=False,
        paused=False,
        home=None,
        contact=Contact(policy=CommsPolicy.STOP, lost=False, action="", silent_s=0.0),
        progress=None,
    )


def test_a_flood_of_new_robot_ids_is_capped_counted_and_logged_once(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(bridge_module, "MqttEndpoint", FakeEndpoint)
    FakeEndpoint.made = 0
    clock = SimClock()
    b = Vda5050Bridge(clock, FakeLink(), MqttSettings("127.0.0.1", 1), max_vehicles=4)  # type: ignore[arg-type]
    caplog.set_level(logging.WARNING, logger=bridge_module.__name__)
    for i in range(200):
        b._fleet(state(f"r{i}"), "zenoh", clock.now())
    assert len(b.vehicles) == 4 and FakeEndpoint.made == 4
    assert b.refused_vehicles == 196
    warnings = [r for r in caplog.records if "not served" in r.getMessage()]
    assert len(warnings) == 1 and "max_vehicles" in warnings[0].getMessage()
    # The robots served keep being served: their state still goes out.
    before = len(b.vehicles["r0"].endpoint.published)  # type: ignore[attr-defined]
    b._fleet(state("r0"), "zenoh", clock.now())
    b.vehicles["r0"].core._next_state = float("-inf")
    b._fleet(state("r0"), "zenoh", clock.now())
    assert len(b.vehicles["r0"].endpoint.published) > before  # type: ignore[attr-defined]
    assert set(b.stats()) == {"r0", "r1", "r2", "r3"}


def test_an_order_the_operator_link_gives_up_on_is_dropped_at_the_next_tick(monkeypatch: pytest.MonkeyPatch) -> None:
    # The link's poll thread reports a command it gave up on (no ack on any link after its re-sends);
    # the bridge hands it to the vehicle at its next tick: the order is dropped then, not 10 s later.
    monkeypatch.setattr(bridge_module, "MqttEndpoint", FakeEndpoint)
    clock = SimClock()
    link = FakeLink()
    b = Vda5050Bridge(clock, link, MqttSettings("127.0.0.1", 1))  # type: ignore[arg-type]
    monkeypatch.setattr(b._ticker, "start", lambda: None)  # ticked by hand below
    b.start()
    b._fleet(state("r0"), "zenoh", clock.now())
    doc = {
        "headerId": 1,
        "timestamp": "2026-01-01T00:00:00.00Z",
        "version": "2.1.0",
        "manufacturer": "fleetlink",
        "serialNumber": "r0",
        "orderId": "o1",
        "orderUpdateId": 0,
        "nodes": [
            {
                "nodeId": "n0",
                "sequenceId": 0,
                "released": True,
                "actions": [],
                "nodePosition": {"x": 0.0, "y": 0.0, "mapId": "site"},
            },
            {
                "nodeId": "n1",
                "sequenceId": 2,
                "released": True,
                "actions": [],
                "nodePosition": {"x": 1.0, "y": 0.0, "mapId": "site"},
            },
        ],
        "edges": [
            {"edgeId": "e1", "sequenceId": 1, "startNodeId": "n0", "endNodeId": "n1", "released": True, "actions": []}
        ],
    }
    b._master("r0", "order", "", json.dumps(doc).encode())
    (sent,) = [m for m in link.sent if isinstance(m, Order)]
    assert b.vehicles["r0"].core.busy
    clock.advance(1.2)
    (listener,) = link.listeners
    listener(Failed("r0", Order.TOPIC, sent.header.headerId, "no ack after 4 sends"))
    b._tick_once()
    core = b.vehicles["r0"].core
    assert not core.busy and core.dropped_orders == 1 and b.stats()["r0"]["dropped_orders"] == 1


def test_a_vehicle_that_vanishes_leaves_its_last_will_retained_on_a_real_broker(mosquitto: Any) -> None:
    """VDA 5050 section 6.14: the vehicle's MQTT connection carries the last will
    ``CONNECTIONBROKEN`` on ``connection`` (QoS 1, retained). The bridge's vehicle connection says
    ``ONLINE`` retained when it connects; when it vanishes without a DISCONNECT (its socket cut, as
    a crashed bridge's) the broker publishes the will, and a master that subscribes afterwards
    still gets it (retained), valid against the official 2.1.0 connection schema."""
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    from fleetlink.operator.vda5050.schema import SchemaValidator, load_schemas
    from tests.harness import wait_until
    from tests.test_vda5050_core import REFERENCE

    official = SchemaValidator(load_schemas(REFERENCE))
    topic = "uagv/v2/fleetlink/r0/connection"
    settings = MqttSettings("127.0.0.1", mosquitto.port, keepalive_s=1, reconnect_min_s=60.0, reconnect_max_s=60.0)
    b = Vda5050Bridge(SimClock(), FakeLink(), settings, robots=("r0",))  # type: ignore[arg-type]

    def retained() -> list[dict[str, Any]]:
        """What a master subscribing now gets on the vehicle's connection topic (retained only;
        nothing yet when the vehicle's own retained publication has not reached the broker)."""
        got: list[dict[str, Any]] = []
        c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="late-master")
        c.on_connect = lambda client, *_: client.subscribe(topic, qos=1)
        c.on_message = lambda _c, _u, m: got.append(json.loads(m.payload)) if m.retain else None
        c.connect("127.0.0.1", mosquitto.port)
        c.loop_start()
        try:
            wait_until(lambda: bool(got), timeout=2, message="a retained connection message")
        except AssertionError:
            pass  # asked again by the caller's wait
        finally:
            c.disconnect()
            c.loop_stop()
        return got

    heard: list[dict[str, Any]] = []

    def state_is(want: str) -> bool:
        heard[:] = retained()
        return bool(heard) and heard[-1]["connectionState"] == want

    try:
        b.start()
        endpoint = b.vehicles["r0"].endpoint
        wait_until(lambda: endpoint.up, message="the vehicle's MQTT connection")
        wait_until(lambda: state_is("ONLINE"), timeout=20, message="ONLINE retained")
        # Gone without a DISCONNECT: the broker sends the will (the vehicle tries again only after a
        # minute, which would put ONLINE back).
        endpoint.client.socket().close()
        wait_until(lambda: state_is("CONNECTIONBROKEN"), timeout=20, message="the last will")
        will = heard[-1]
        assert official.problems("connection", will) == [], will
        assert (will["manufacturer"], will["serialNumber"], will["version"]) == ("fleetlink", "r0", "2.1.0")
    finally:
        b.close()
