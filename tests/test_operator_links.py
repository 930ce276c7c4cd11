"""The operator's links against real parts: Zenoh peers on loopback and a private Mosquitto.

The robot here is the agent's real command gate (agent/links/gate.py: decode, dedupe, ack on the
link a command came from) behind a real Zenoh session and a real MQTT client, publishing its pose
at 20 Hz on both links. Cutting the primary closes the robot's Zenoh session: nothing more of it
reaches the operator over Zenoh, exactly like a dead radio.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

import paho.mqtt.client as mqtt
import pytest
import zenoh

from fleetlink.agent.links.gate import Accepted, CommandGate, Duplicate
from fleetlink.links.mqtt import MqttEndpoint
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.operator.linkmanager import FALLBACK, PRIMARY, LinkPolicy, Switch
from fleetlink.operator.links import OperatorLink, mqtt_settings_for
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, AckResult, Goal, LinkName, Order, Pose
from tests.harness import wait_until
from tests.harness.zenoh_peers import loopback_endpoint, zenoh_config

COMMANDS = ("order", "actions", "teleop")


@dataclass
class Execution:
    topic: str
    sender: str
    header_id: int
    link: str
    at: float
    order: tuple[str, int] | None


class LinkRobot:
    """A robot's two links and its command gate; records every command it executes."""

    def __init__(self, robot: str, zenoh_connect: str, mqtt_port: int, clock: SystemClock) -> None:
        self.robot = robot
        self.clock = clock
        self.zenoh_connect = zenoh_connect
        self.gate = CommandGate(robot)
        self.counter = wire.HeaderCounter(clock, robot=robot, sender=f"agent-{robot}")
        self.executed: list[Execution] = []
        self.lock = threading.Lock()
        self.session: Any = None
        self._subs: list[Any] = []
        self.mqtt = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"agent-{robot}")
        self.mqtt.on_connect = lambda c, *_: [c.subscribe(keys.key(robot, t), qos=1) for t in COMMANDS]
        self.mqtt.on_message = lambda c, u, m: self._on_input(LinkName.MQTT, m.topic, bytes(m.payload))
        self.mqtt.connect("127.0.0.1", mqtt_port)
        self.mqtt.loop_start()
        self.open_primary()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._publish_poses, name=f"robot-{robot}", daemon=True)
        self._thread.start()

    def open_primary(self) -> None:
        session = zenoh.open(zenoh_config(connect=[self.zenoh_connect], scouting_delay_ms=0))
        subs = [
            session.declare_subscriber(
                keys.key(self.robot, t),
                lambda s: self._on_input(LinkName.ZENOH, str(s.key_expr), s.payload.to_bytes()),
            )
            for t in COMMANDS
        ]
        with self.lock:
            self.session, self._subs = session, subs

    def cut_primary(self) -> None:
        with self.lock:
            session, self.session, subs, self._subs = self.session, None, self._subs, []
        for sub in subs:
            sub.undeclare()
        session.close()

    def _put(self, link: LinkName, key: str, payload: bytes) -> None:
        if link is LinkName.MQTT:
            self.mqtt.publish(key, payload, qos=1)
            return
        with self.lock:
            if self.session is not None:
                self.session.put(key, payload)

    def _on_input(self, link: LinkName, key: str, payload: bytes) -> None:
        now = self.clock.now()
        with self.lock:
            verdict = self.gate.receive(link, key, payload, now)
            if isinstance(verdict, Accepted):
                msg = verdict.msg
                order = (msg.orderId, msg.orderUpdateId) if isinstance(msg, Order) else None
                if isinstance(msg, Order):
                    self.gate.executed_order(msg)
                h = msg.header
                self.executed.append(Execution(type(msg).TOPIC, h.sender, h.headerId, link.value, now, order))
                ack = self.gate.make_ack(self.counter, self.gate.ack(msg, link, AckResult.ACCEPTED))
            elif isinstance(verdict, Duplicate):
                ack = self.gate.make_ack(self.counter, verdict.ack)
            else:
                return
        self._put(link, keys.key(self.robot, Ack.TOPIC), wire.encode(ack))

    def _publish_poses(self) -> None:
        key = keys.key(self.robot, Pose.TOPIC)
        while not self._stop.wait(0.05):
            pose = self.counter.make(
                Pose,
                x=1.0,
                y=2.0,
                theta=0.0,
                sd_x_m=0.05,
                sd_y_m=0.05,
                sd_theta_rad=0.01,
                odom_x=0.0,
                odom_y=0.0,
                odom_theta=0.0,
                vx=0.0,
                omega=0.0,
                uwbStale=False,
            )
            payload = wire.encode(pose)
            self._put(LinkName.ZENOH, key, payload)
            self._put(LinkName.MQTT, key, payload)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        if self.session is not None:
            self.cut_primary()
        self.mqtt.disconnect()
        self.mqtt.loop_stop()


def open_operator(mqtt_port: int, policy: LinkPolicy, sender: str = "operator-1") -> tuple[OperatorLink, str]:
    """An operator link listening on a fresh loopback Zenoh endpoint (robots connect to it)."""
    endpoint = loopback_endpoint()
    primary = ZenohEndpoint(listen=[endpoint])
    fallback = MqttEndpoint(mqtt_settings_for(f"mqtt://127.0.0.1:{mqtt_port}"), client_id=sender)
    link = OperatorLink(SystemClock(), sender, primary, fallback, policy=policy, poll_hz=50.0)
    link.start()
    wait_until(lambda: fallback.up, timeout=5.0, message="operator MQTT client to connect")
    return link, endpoint


def goal(i: int) -> dict[str, Any]:
    return {
        "orderId": f"goal-{i}",
        "orderUpdateId": 0,
        "goal": Goal(x=float(i), y=0.0, theta=None),
        "returnHome": False,
    }


POLICY = LinkPolicy(state_window_s=0.35, ack_timeout_s=0.25, holdoff_s=0.6)


@pytest.fixture
def pair(mosquitto: Any) -> Any:
    op, endpoint = open_operator(mosquitto.port, POLICY)
    robot = LinkRobot("r1", endpoint, mosquitto.port, SystemClock())
    try:
        wait_until(
            lambda: op.health("r1")[0].age_s is not None and op.health("r1")[1].age_s is not None,
            message="poses from r1 on both links",
        )
        yield op, robot
    finally:
        robot.close()
        op.close()


def test_commands_use_zenoh_while_healthy(pair: Any) -> None:
    op, robot = pair
    for i in range(5):
        op.send(Order, "r1", **goal(i))
    wait_until(lambda: len(robot.executed) == 5 and op.pending("r1") == 0, message="5 goals executed and acked")
    assert {e.link for e in robot.executed} == {"zenoh"}
    assert op.active("r1") == PRIMARY
    zenoh_health = op.health("r1")[0]
    assert zenoh_health.healthy and zenoh_health.rtt_s is not None


def test_cut_primary_fails_over_without_loss_or_duplicates_and_fails_back(pair: Any) -> None:
    op, robot = pair
    switches: list[Switch] = []
    op.add_listener(lambda a: switches.append(a) if isinstance(a, Switch) else None)
    sent = 0
    for _ in range(5):
        op.send(Order, "r1", **goal(sent))
        sent += 1
        time.sleep(0.05)
    wait_until(lambda: op.pending("r1") == 0, message="acks before the cut")
    robot.cut_primary()
    cut_at = time.monotonic()
    # Keep commanding through the cut: every goal must run exactly once.
    while time.monotonic() - cut_at < 1.0:
        op.send(Order, "r1", **goal(sent))
        sent += 1
        time.sleep(0.05)
    wait_until(lambda: op.pending("r1") == 0, message="every goal acked after the cut")
    assert op.active("r1") == FALLBACK
    assert switches and switches[0].to_link == FALLBACK
    first_fallback = min(e.at for e in robot.executed if e.link == "mqtt")
    print(f"failover: first command over MQTT {1000 * (first_fallback - cut_at):.0f} ms after the cut")
    orders = [e.order for e in robot.executed if e.topic == "order"]
    assert sorted(orders) == sorted((f"goal-{i}", 0) for i in range(sent)), "lost or duplicated goals"
    assert len(orders) == len(set(orders)) == sent
    # The primary comes back: after the hold-off commands return to Zenoh.
    robot.open_primary()
    wait_until(lambda: op.active("r1") == PRIMARY, timeout=10.0, message="fail-back to zenoh")
    assert switches[-1].to_link == PRIMARY
    before = len(robot.executed)
    op.send(Order, "r1", **goal(sent))
    wait_until(lambda: len(robot.executed) == before + 1, message="goal after fail-back")
    assert robot.executed[-1].link == "zenoh"


def test_garbage_is_counted_and_logged_once(pair: Any, mosquitto: Any, caplog: Any) -> None:
    op, robot = pair
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="vandal")
    client.connect("127.0.0.1", mosquitto.port)
    client.loop_start()
    try:
        for _ in range(5):
            client.publish(keys.key("r1", "pose"), b"\xc1garbage", qos=1).wait_for_publish(2)
            client.publish("fleetlink/v1/r1/nosuchtopic", b"\x80", qos=1).wait_for_publish(2)
        wait_until(lambda: sum(op.rejected.values()) >= 10, message="10 rejections")
    finally:
        client.disconnect()
        client.loop_stop()
    assert len(op.rejected) == 2
    assert len([r for r in caplog.records if "rejected a message" in r.getMessage()]) == 2
    # Still serving.
    op.send(Order, "r1", **goal(99))
    wait_until(lambda: any(e.order == ("goal-99", 0) for e in robot.executed), message="goal after garbage")
