"""A robot's two links and its real command gate, for the operator's link tests and bench/failover.py.

The robot is the agent's command gate (agent/links/gate.py: decode, dedupe, ack on the link a
command came from) behind its own Zenoh session and MQTT client, publishing its pose at 20 Hz on
both links. ``cut_primary`` closes its Zenoh session: nothing more of it reaches the operator over
Zenoh, exactly like a dead radio. ``ack_delay_s[link]`` holds its acks on that link back (a link
that delivers late).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import paho.mqtt.client as mqtt
import zenoh

from fleetlink.agent.links.gate import Accepted, CommandGate, Duplicate
from fleetlink.links.base import to_mqtt_filter
from fleetlink.links.mqtt import MqttEndpoint
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.operator.linkmanager import LinkPolicy
from fleetlink.operator.links import OperatorLink, mqtt_settings_for
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, AckResult, Goal, LinkName, Order, Pose
from tests.harness import wait_until
from tests.harness.zenoh_peers import loopback_endpoint, zenoh_config

__all__ = ["COMMANDS", "Execution", "LinkRobot", "StallingLink", "goal", "open_operator"]

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

    def __init__(
        self, robot: str, zenoh_connect: str, mqtt_port: int, clock: SystemClock, *, zenoh_mode: str = "peer"
    ) -> None:
        """``zenoh_mode`` "client": the robot's session talks only through the router it connects
        to (a peer would also reach the operator directly once the router told it where)."""
        self.robot = robot
        self.clock = clock
        self.zenoh_connect = zenoh_connect
        self.zenoh_mode = zenoh_mode
        self.gate = CommandGate(robot)
        self.counter = wire.HeaderCounter(clock, robot=robot, sender=f"agent-{robot}")
        self.executed: list[Execution] = []
        self.ack_delay_s: dict[LinkName, float] = {}
        self.lock = threading.Lock()
        self.session: Any = None
        self._subs: list[Any] = []
        self.mqtt = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"agent-{robot}")
        self.mqtt.on_connect = lambda c, *_: [
            c.subscribe(to_mqtt_filter(keys.sender_filter(robot, t)), qos=1) for t in COMMANDS
        ]
        self.mqtt.on_message = lambda c, u, m: self._on_input(LinkName.MQTT, m.topic, bytes(m.payload))
        self.mqtt.connect("127.0.0.1", mqtt_port)
        self.mqtt.loop_start()
        self.open_primary()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._publish_poses, name=f"robot-{robot}", daemon=True)
        self._thread.start()

    def open_primary(self) -> None:
        session = zenoh.open(zenoh_config(connect=[self.zenoh_connect], mode=self.zenoh_mode, scouting_delay_ms=0))
        subs = [
            session.declare_subscriber(
                keys.sender_filter(self.robot, t),
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
        delay = self.ack_delay_s.get(link, 0.0)
        if delay > 0:
            timer = threading.Timer(delay, self._put, (link, keys.key(self.robot, Ack.TOPIC), wire.encode(ack)))
            timer.daemon = True
            timer.start()
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


class StallingLink:
    """A link whose ``publish`` waits while ``stall()`` is in force, as a Zenoh put with congestion
    control BLOCK waits when its queue towards a peer is full (tests/test_link_stall.py makes that
    for real); everything else is the inner link's. It says nothing of ``PUBLISH_QUEUES``, so an
    ``OperatorLink`` gives it a send thread (links/sender.py) as it gives Zenoh."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.name = inner.name
        self.stats = inner.stats
        self._flowing = threading.Event()
        self._flowing.set()

    def stall(self) -> None:
        self._flowing.clear()

    def resume(self) -> None:
        self._flowing.set()

    def publish(self, key: str, payload: bytes) -> bool:
        self._flowing.wait()
        return bool(self.inner.publish(key, payload))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def open_operator(
    mqtt_port: int,
    policy: LinkPolicy,
    sender: str = "operator-1",
    *,
    stalling: bool = False,
    inline: bool = False,
    listen: str | None = None,
) -> tuple[OperatorLink, str]:
    """An operator link listening on a fresh loopback Zenoh endpoint (robots connect to it), or on
    ``listen``. ``stalling``: its Zenoh endpoint is a ``StallingLink`` (``op.links[ZENOH]``);
    ``inline``: no send threads, every copy published on the caller's thread one after the other
    (as before issue 18: the baseline of bench/failover.py's stall mode)."""
    endpoint = listen or loopback_endpoint()
    primary: Any = ZenohEndpoint(listen=[endpoint])
    if stalling:
        primary = StallingLink(primary)
    fallback = MqttEndpoint(mqtt_settings_for(f"mqtt://127.0.0.1:{mqtt_port}"), client_id=sender)
    link = OperatorLink(SystemClock(), sender, primary, fallback, policy=policy, poll_hz=50.0)
    if inline:
        link.senders.clear()
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
