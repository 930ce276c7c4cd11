"""Alarms over real links (issue 15): real Zenoh sessions on loopback and a private Mosquitto.

A robot (its Zenoh endpoint with its liveliness token, and an MQTT client) reports an e-stop.
Console A (op-alice) sees the alarm and the robot present (its token), and acknowledges: the
``AlarmAck`` goes out on Zenoh and retained on MQTT. Console B (op-bob) starts later with Zenoh
down (a session linked to nothing): it learns A's acknowledgement from the broker's retained
message, which comes before the robot's first state, and shows the e-stop as acknowledged by
op-alice. Then the robot's Zenoh endpoint closes: its token goes, and A raises "robot lost".
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest

from fleetlink.links.mqtt import MqttEndpoint
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.operator.alarm_panel import AlarmKeeper
from fleetlink.operator.alarms import AlarmKind
from fleetlink.operator.audit import AuditLog
from fleetlink.operator.feed import attach
from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.links import OperatorLink, mqtt_settings_for
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import (
    AgvPosition,
    AlarmAck,
    BatteryState,
    CommsPolicy,
    Contact,
    EStop,
    LinkName,
    LinkStatus,
    OperatingMode,
    SafetyState,
    State,
    Velocity,
)
from tests.harness import MosquittoBroker, wait_until


class Console:
    """What ``fleetlink console`` assembles, without the app: OperatorLink, fleet model and feed
    (unbound: folded in at once), the alarm keeper."""

    def __init__(self, login: str, zenoh: ZenohEndpoint, broker: MosquittoBroker, clock: SystemClock) -> None:
        mqtt = MqttEndpoint(mqtt_settings_for(f"mqtt://127.0.0.1:{broker.port}"), client_id=login)
        self.link = OperatorLink(clock, login, zenoh, mqtt)
        self.fleet = FleetModel(login)
        self.lock = threading.Lock()
        attach(self.link, self.fleet, self.lock)
        self.keeper = AlarmKeeper(self.link, self.fleet.alarms, AuditLog(None, login))
        self.link.start()

    def alarm(self, kind: AlarmKind) -> Any:
        with self.lock:
            return self.fleet.alarms.alarms.get("r1", kind)

    def acknowledge(self, kind: AlarmKind, wall: float) -> None:
        with self.lock:
            outcome = self.keeper.acknowledge("r1", kind, wall)
            lists = self.fleet.alarms.outgoing()
        assert outcome.acked and not outcome.reason
        self.keeper.publish(lambda topic, robot: self.link.counter.header(topic, robot=robot), lists)

    def close(self) -> None:
        self.link.close()


class Robot:
    """The robot's voice on both links; its Zenoh endpoint holds the liveliness token."""

    def __init__(self, session: Any, broker: MosquittoBroker, clock: SystemClock) -> None:
        self.zenoh = ZenohEndpoint(session=session, alive_key=keys.alive_key("r1"), label="zenoh-r1")
        self.mqtt = MqttEndpoint(mqtt_settings_for(f"mqtt://127.0.0.1:{broker.port}"), client_id="agent-r1")
        self.counter = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
        self.zenoh.start()
        self.mqtt.start()

    def estop(self) -> bool:
        """Publish a state with the e-stop latched on both links (True: sent on both)."""
        msg = self.counter.make(
            State,
            agvPosition=AgvPosition(x=0, y=0, theta=0, mapId="m", positionInitialized=True, localizationScore=0.9),
            velocity=Velocity(vx=0.0, omega=0.0), batteryState=BatteryState(batteryCharge=80.0, charging=False),
            errors=(), operatingMode=OperatingMode.SERVICE,
            safetyState=SafetyState(eStop=EStop.MANUAL, fieldViolation=False), driveMode="estop",
            links=LinkStatus(zenoh=True, mqtt=True), uwbStale=False, payloadOn=False, boardConnected=True,
            orderId="", orderUpdateId=0, goal=None, driving=False, paused=False, home=None,
            contact=Contact(policy=CommsPolicy.STOP, lost=False, action="", silent_s=0.0),
        )  # fmt: skip
        payload = wire.encode(msg)
        sent_z = self.zenoh.publish(wire.key_of(msg), payload)
        return self.mqtt.publish(wire.key_of(msg), payload) and sent_z

    def close(self) -> None:
        self.zenoh.close()
        self.mqtt.close()


@pytest.fixture
def site(zenoh_peers: Any, mosquitto: MosquittoBroker) -> Iterator[tuple[Robot, Console, Any, MosquittoBroker]]:
    robot_session, console_session = zenoh_peers(2)
    clock = SystemClock()
    robot = Robot(robot_session, mosquitto, clock)
    alice = Console("op-alice", ZenohEndpoint(session=console_session, label="zenoh-alice"), mosquitto, clock)
    try:
        yield robot, alice, clock, mosquitto
    finally:
        alice.close()
        robot.close()


def test_a_late_console_with_zenoh_down_learns_the_ack_from_mqtt_and_a_token_gone_is_robot_lost(
    site: tuple[Robot, Console, SystemClock, MosquittoBroker],
) -> None:
    robot, alice, clock, broker = site
    wait_until(lambda: alice.link.links[LinkName.MQTT].up and robot.mqtt.up, message="both on the broker")
    wait_until(lambda: robot.estop() and alice.alarm(AlarmKind.ESTOP) is not None, message="the e-stop at alice")
    wait_until(lambda: alice.fleet.robots["r1"].present is True, message="r1's token seen by alice")
    assert alice.alarm(AlarmKind.ROBOT_LOST) is None

    # Alice acknowledges: on Zenoh, and retained on the broker.
    watcher = MqttEndpoint(mqtt_settings_for(f"mqtt://127.0.0.1:{broker.port}"), client_id="watcher")
    retained: list[bytes] = []
    watcher.subscribe(keys.sender_filter("*", AlarmAck.TOPIC), lambda _k, payload: retained.append(payload))
    alice.acknowledge(AlarmKind.ESTOP, clock.wall())
    acked_at = alice.alarm(AlarmKind.ESTOP).acked_at
    watcher.start()  # subscribes after the publication: only a retained message reaches it
    try:
        wait_until(lambda: retained, message="alice's acknowledgement retained on the broker")
    finally:
        watcher.close()
    msg = wire.decode_key(keys.sender_key("r1", AlarmAck.TOPIC, "op-alice"), retained[-1])
    assert isinstance(msg, AlarmAck) and [(a.kind, a.at) for a in msg.acks] == [("estop", acked_at)]

    # Bob starts late with Zenoh down: his session is linked to nothing.
    bob = Console("op-bob", ZenohEndpoint(label="zenoh-bob"), broker, clock)
    try:
        assert not bob.link.links[LinkName.ZENOH].up
        wait_until(
            lambda: robot.estop() and (a := bob.alarm(AlarmKind.ESTOP)) is not None and a.acked_by == "op-alice",
            message="the e-stop at bob, acknowledged by op-alice",
        )
        estop = bob.alarm(AlarmKind.ESTOP)
        assert estop.acked_at == acked_at
        assert bob.fleet.alarms.refused == {}
    finally:
        bob.close()

    # The robot's Zenoh endpoint closes: its token goes, and alice raises "robot lost".
    robot.zenoh.close()
    wait_until(lambda: alice.alarm(AlarmKind.ROBOT_LOST) is not None, message="robot lost at alice")
    lost = alice.alarm(AlarmKind.ROBOT_LOST)
    assert lost.acked_by is None and lost.severity.value == "critical"
    assert alice.fleet.robots["r1"].present is False
