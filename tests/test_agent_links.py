"""The agent's command links: the pure gate, then the real thing (Mosquitto + Zenoh peers on loopback).

The transport tests run a whole AgentRuntime against a simulated board over TCP and talk to it
the way an operator would: one Zenoh peer and one paho client, both real.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import paho.mqtt.client as mqtt
import pytest
import zenoh

from fleetlink.agent.config import AgentConfig, Rates, ZenohSettings, mqtt_settings
from fleetlink.agent.links.gate import Accepted, CommandGate, Duplicate, Rejected
from fleetlink.agent.node import input_keys
from fleetlink.agent.runtime import AgentRuntime
from fleetlink.field.board import SimulatedBoard
from fleetlink.field.device_server import DeviceServer
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SimClock, SystemClock
from fleetlink.shared.messages import (
    Ack,
    AckResult,
    Action,
    ActionType,
    Event,
    Goal,
    InstantActions,
    Lease,
    LinkName,
    Order,
    Pose,
    State,
    Teleop,
)
from tests.harness import MosquittoBroker, wait_until
from tests.harness.mosquitto import free_port
from tests.harness.zenoh_peers import zenoh_config

OP = wire.HeaderCounter(SimClock(), robot="r1", sender="operator-1")
K = {
    t: keys.sender_key("r1", t, "operator-1") if t in keys.SENDER_TOPICS else keys.key("r1", t)
    for t in ("order", "actions", "teleop", "ack", "state", "uwb")
}

# --------------------------------------------------------------------------------------------------
# The gate (pure)


def test_gate_runs_a_command_once_across_links() -> None:
    gate = CommandGate("r1")
    raw = wire.encode(OP.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5))
    first = gate.receive(LinkName.ZENOH, K["teleop"], raw, 0.0)
    second = gate.receive(LinkName.MQTT, K["teleop"], raw, 0.001)
    assert isinstance(first, Accepted)
    assert isinstance(second, Duplicate)
    assert second.ack["result"] is AckResult.DUPLICATE and second.ack["link"] is LinkName.MQTT
    assert "zenoh" in second.ack["reason"]
    # A fresh header is a new command, even with the same content.
    assert isinstance(
        gate.receive(LinkName.MQTT, K["teleop"], wire.encode(OP.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5)), 0.01),
        Accepted,
    )


def test_gate_the_copy_on_the_other_link_takes_no_rate() -> None:
    # A console sending everything on both links (redundant sending) at the sender's full rate:
    # every first copy runs, every second copy is a free duplicate -- none refused over the rate.
    gate = CommandGate("r1")
    verdicts = []
    for i in range(400):  # 400 teleops at 50/s (the rate) over 8 s, each on both links
        raw = wire.encode(OP.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5))
        verdicts.append(gate.receive(LinkName.ZENOH, K["teleop"], raw, i * 0.02))
        verdicts.append(gate.receive(LinkName.MQTT, K["teleop"], raw, i * 0.02 + 0.001))
    assert [type(v) for v in verdicts[0::2]] == [Accepted] * 400
    assert [type(v) for v in verdicts[1::2]] == [Duplicate] * 400
    assert gate.limit.limited == 0
    # A replay of a copy already answered on both links pays like anything else.
    raw = wire.encode(OP.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5))
    gate.receive(LinkName.ZENOH, K["teleop"], raw, 9.0)
    gate.receive(LinkName.MQTT, K["teleop"], raw, 9.0)
    for _ in range(150):
        gate.receive(LinkName.MQTT, K["teleop"], raw, 9.0)
    assert gate.limit.limited > 0


def test_gate_orders_are_idempotent_on_order_id_and_update() -> None:
    gate = CommandGate("r1")
    goal = Goal(x=1.0, y=2.0, theta=None)
    o1 = OP.make(Order, orderId="o", orderUpdateId=1, goal=goal, returnHome=False)
    v = gate.receive(LinkName.ZENOH, K["order"], wire.encode(o1), 0.0)
    assert isinstance(v, Accepted)
    gate.executed_order(o1)
    # Same order re-sent with a new header (another console, a retry): a duplicate.
    again = OP.make(Order, orderId="o", orderUpdateId=1, goal=goal, returnHome=False)
    assert isinstance(gate.receive(LinkName.MQTT, K["order"], wire.encode(again), 0.1), Duplicate)
    older = OP.make(Order, orderId="o", orderUpdateId=0, goal=goal, returnHome=False)
    stale = gate.receive(LinkName.MQTT, K["order"], wire.encode(older), 0.2)
    assert isinstance(stale, Rejected) and "older" in stale.reason
    newer = OP.make(Order, orderId="o", orderUpdateId=2, goal=goal, returnHome=False)
    assert isinstance(gate.receive(LinkName.MQTT, K["order"], wire.encode(newer), 0.3), Accepted)


def test_gate_restarted_sender_is_not_a_replay() -> None:
    gate = CommandGate("r1")
    a = wire.HeaderCounter(SimClock(start=0.0), robot="r1", sender="operator-1")
    b = wire.HeaderCounter(SimClock(start=5.0), robot="r1", sender="operator-1")  # restarted: headerId 0 again
    assert isinstance(
        gate.receive(LinkName.ZENOH, K["teleop"], wire.encode(a.make(Teleop, v=0.1, omega=0.0, ttl_s=0.5)), 0.0),
        Accepted,
    )
    assert isinstance(
        gate.receive(LinkName.ZENOH, K["teleop"], wire.encode(b.make(Teleop, v=0.1, omega=0.0, ttl_s=0.5)), 5.0),
        Accepted,
    )


@pytest.mark.parametrize(
    ("key", "payload", "fragment"),
    [
        (K["teleop"], b"\xc1garbage", "payload: not valid msgpack"),
        (K["order"], wire.encode(OP.make(Teleop, v=0.1, omega=0.0, ttl_s=0.5)), "missing field"),
        (K["actions"], b"\x93\x01\x02\x03", "payload: expected a map"),
        (K["uwb"], b"", "payload"),
        (
            keys.sender_key("r2", "teleop", "operator-1"),
            wire.encode(OP.make(Teleop, v=0.1, omega=0.0, ttl_s=0.5)),
            "not an input",
        ),
        ("nonsense", b"x", "key"),
    ],
)
def test_gate_rejects_counts_and_logs_once(key: str, payload: bytes, fragment: str) -> None:
    gate = CommandGate("r1", topics=("order", "actions", "teleop", "uwb"))
    first = gate.receive(LinkName.MQTT, key, payload, 0.0)
    second = gate.receive(LinkName.MQTT, key, payload, 0.1)
    assert isinstance(first, Rejected) and isinstance(second, Rejected)
    assert fragment in first.reason
    assert first.log and not second.log
    assert gate.stats.rejected_total == 2


# --------------------------------------------------------------------------------------------------
# Real links


@dataclass
class Operator:
    """The operator's side: a Zenoh peer and a paho client, recording acks and states per link."""

    zsession: Any
    mclient: Any
    acks: list[tuple[str, Ack]] = field(default_factory=list)
    states: list[tuple[str, State]] = field(default_factory=list)
    leases: list[tuple[str, Lease]] = field(default_factory=list)
    poses: list[tuple[str, Pose]] = field(default_factory=list)
    events: list[tuple[str, Event]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    counter: wire.HeaderCounter = field(
        default_factory=lambda: wire.HeaderCounter(SystemClock(), robot="r1", sender="operator-1")
    )

    def record(self, link: str, key: str, data: bytes) -> None:
        try:
            msg = wire.decode_key(key, data)
        except wire.WireError:
            return
        with self.lock:
            if isinstance(msg, Ack):
                self.acks.append((link, msg))
            elif isinstance(msg, State):
                self.states.append((link, msg))
            elif isinstance(msg, Lease):
                self.leases.append((link, msg))
            elif isinstance(msg, Pose):
                self.poses.append((link, msg))
            elif isinstance(msg, Event):
                self.events.append((link, msg))

    def send(self, msg: wire.Message, *, zenoh_: bool = True, mqtt_: bool = True) -> bytes:
        data = wire.encode(msg)
        self.send_raw(wire.key_of(msg), data, zenoh_=zenoh_, mqtt_=mqtt_)
        return data

    def send_raw(self, topic: str, data: bytes, *, zenoh_: bool = True, mqtt_: bool = True) -> None:
        if "/" in topic:
            k = topic
        elif topic in keys.SENDER_TOPICS:
            k = keys.sender_key("r1", topic, self.counter.sender)
        else:
            k = keys.key("r1", topic)
        if zenoh_:
            self.zsession.put(k, data)
        if mqtt_:
            self.mclient.publish(k, data, qos=1)

    def acks_for(self, header_id: int, topic: str) -> list[tuple[str, Ack]]:
        with self.lock:
            return [(lk, a) for lk, a in self.acks if a.commandHeaderId == header_id and a.commandTopic == topic]

    def last_state(self) -> State | None:
        with self.lock:
            return self.states[-1][1] if self.states else None


@dataclass
class Rig:
    agent: AgentRuntime
    board: SimulatedBoard
    op: Operator
    broker: MosquittoBroker


@pytest.fixture
def rig(mosquitto: MosquittoBroker) -> Iterator[Rig]:
    with make_rig(mosquitto) as r:
        yield r


@contextlib.contextmanager
def make_rig(mosquitto: MosquittoBroker, **overrides: Any) -> Iterator[Rig]:
    """An agent (config fields overridden by ``overrides``) on a simulated board, an operator on both links."""
    clock = SystemClock()
    board = SimulatedBoard()
    server = DeviceServer(board, clock, name="board")
    port = server.serve_tcp()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = AgentConfig(
        robot="r1",
        board=f"socket://127.0.0.1:{port}",
        zenoh=ZenohSettings(listen=(endpoint,)),
        mqtt=mqtt_settings(f"mqtt://127.0.0.1:{mosquitto.port}"),
        rates=Rates(control_hz=50.0, pose_hz=20.0, state_hz=5.0),
    )
    agent = AgentRuntime(replace(cfg, **overrides), clock, seed=1)
    zs = None
    mc = None
    try:
        agent.start()
        zs = zenoh.open(zenoh_config(connect=[endpoint]))
        mc = mqtt.Client(callback_api_version=mqtt.CallbackAPIVersion.VERSION2, client_id="operator-1")
        op = Operator(zs, mc)
        zs.declare_subscriber(
            keys.zenoh_robot("r1"), lambda s: op.record("zenoh", str(s.key_expr), s.payload.to_bytes())
        )
        mc.on_message = lambda c, u, m: op.record("mqtt", m.topic, bytes(m.payload))
        mc.connect("127.0.0.1", mosquitto.port)
        mc.subscribe(keys.mqtt_robot("r1"), qos=1)
        mc.loop_start()
        wait_until(lambda: board.state is not None and agent.board.snapshot.connected, message="agent's board link")
        wait_until(
            lambda: (s := op.last_state()) is not None and s.links.zenoh and s.links.mqtt,
            message="a state saying both links are up",
        )
        wait_until(
            lambda: any(lk == "mqtt" for lk, _ in op.states) and any(lk == "zenoh" for lk, _ in op.states),
            message="states on both links",
        )
        yield Rig(agent, board, op, mosquitto)
    finally:
        if mc is not None:
            mc.loop_stop()
            mc.disconnect()
        agent.stop()
        if zs is not None:
            zs.close()
        server.stop()


def test_command_sent_on_both_links_runs_once_and_acks_on_each(rig: Rig) -> None:
    op = rig.op
    msg = op.counter.make(
        InstantActions, actions=(Action(actionId="e1", actionType=ActionType.ESTOP, actionParameters=()),)
    )
    op.send(msg)
    wait_until(lambda: len(op.acks_for(msg.header.headerId, "actions")) >= 2, message="an ack on each link")
    results = {(lk, a.link.value, a.result) for lk, a in op.acks_for(msg.header.headerId, "actions")}
    # One execution (accepted), one duplicate; each ack on the link its copy came from.
    assert sorted(r for _, _, r in results) == [AckResult.ACCEPTED, AckResult.DUPLICATE]
    assert all(lk == link for lk, link, _ in results)
    assert rig.agent.core.gate.stats.duplicates == 1
    wait_until(
        lambda: (s := op.last_state()) is not None and s.safetyState.eStop.value == "REMOTE", message="e-stop in state"
    )


def test_broker_killed_zenoh_keeps_serving_and_mqtt_reconnects(rig: Rig) -> None:
    op = rig.op
    rig.broker.kill()
    wait_until(lambda: not rig.agent.mqtt.up, message="the agent to notice the broker is gone")  # type: ignore[union-attr]
    wait_until(
        lambda: any(lk == "zenoh" and not s.links.mqtt for lk, s in list(op.states)),
        message="a state on zenoh saying mqtt is down",
    )
    t = op.send(op.counter.make(Teleop, v=0.2, omega=0.0, ttl_s=1.0), mqtt_=False)
    hid = wire.decode(Teleop, t).header.headerId
    wait_until(lambda: op.acks_for(hid, "teleop"), message="an ack on zenoh while the broker is down")
    assert op.acks_for(hid, "teleop")[0][1].result is AckResult.ACCEPTED
    connects = rig.agent.mqtt.connects  # type: ignore[union-attr]
    rig.broker.start()
    wait_until(
        lambda: rig.agent.mqtt.connects > connects and rig.agent.mqtt.up,
        timeout=15.0,  # type: ignore[union-attr]
        message="mqtt to reconnect by itself",
    )
    # Commands flow on MQTT again.
    op.mclient.reconnect() if not op.mclient.is_connected() else None
    wait_until(lambda: op.mclient.is_connected(), message="the operator's client back")
    op.mclient.subscribe(keys.mqtt_robot("r1"), qos=1)
    m = op.counter.make(Teleop, v=0.1, omega=0.0, ttl_s=1.0)
    deadline_ok = lambda: any(lk == "mqtt" for lk, _ in op.acks_for(m.header.headerId, "teleop"))  # noqa: E731
    op.send(m, zenoh_=False)
    wait_until(deadline_ok, message="an ack on mqtt after the reconnect")


def test_malformed_payloads_on_every_input_topic_are_rejected_and_counted(rig: Rig) -> None:
    op = rig.op
    bad = [
        b"\xc1",
        b"not msgpack at all",
        b"\x81\xa6header\x01",
        wire.encode(op.counter.make(Teleop, v=0.0, omega=0.0, ttl_s=0.5)),
    ]
    topics = ["order", "actions", "teleop", "uwb"]
    n = 0
    for topic in topics:
        for data in bad:
            if topic == "teleop" and data == bad[-1]:
                continue  # that one is valid here
            op.send_raw(topic, data)
            n += 2
    op.send_raw("dwm/node/r1/uplink/location", b"{not json", zenoh_=False)
    n += 1
    gate = rig.agent.core.gate
    wait_until(lambda: gate.stats.rejected_total >= n, message=f"{n} rejections")
    for topic in topics:
        for link in ("zenoh", "mqtt"):
            assert gate.stats.rejected.get((link, topic), 0) >= 1, (link, topic)
    assert gate.stats.rejected.get(("mqtt", "pans"), 0) == 1
    # Still serving: a good command is acked.
    m = op.counter.make(Teleop, v=0.1, omega=0.0, ttl_s=0.5)
    op.send(m, mqtt_=False)
    wait_until(lambda: op.acks_for(m.header.headerId, "teleop"), message="an ack after the garbage")


def test_zenoh_link_delivers_samples_on_different_keys_in_the_order_sent(zenoh_peers: Any) -> None:
    """A teleop then a lease release must reach the agent in that order: zenoh-python would run
    each subscriber's callback on a thread of its own, so the link queues them on one."""
    from fleetlink.agent.links.zenoh_link import agent_zenoh_link

    peers = zenoh_peers(1)
    operator = peers[0]
    got: list[tuple[str, bytes]] = []
    done = threading.Event()
    n = 600

    probed: set[str] = set()

    def on_input(key: str, payload: bytes) -> None:
        if payload == b"probe":
            probed.add(key)
            return
        got.append((key, payload))
        if len(got) == n:
            done.set()

    inputs = ("order", "actions", "teleop", "lease/request")
    link = agent_zenoh_link("r1", ZenohSettings(connect=tuple(peers.endpoints)))
    for t in inputs:
        for k in input_keys("r1", t):
            link.subscribe(k, on_input)
    link.start()
    try:
        wait_until(lambda: link.up, message="the agent's zenoh link to the operator")
        # Declarations take a moment to propagate: probe until a sample on each key gets through.
        sent_keys = [keys.sender_key("r1", t, "op-a") for t in inputs]
        for k in sent_keys:
            wait_until(
                lambda k=k: operator.put(k, b"probe") is None and k in probed,
                interval=0.05,
                message=f"the subscription on {k}",
            )
        sent = [(sent_keys[i % len(inputs)], i.to_bytes(4, "big")) for i in range(n)]
        for k, payload in sent:
            operator.put(k, payload)
        assert done.wait(10.0), f"only {len(got)} of {n} samples arrived"
        assert got == sent
    finally:
        link.close()
