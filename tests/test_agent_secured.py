"""An agent on a secured site (issue 8): the deploy/ Mosquitto (password file + ACL) and a Zenoh
router on deploy/zenohd.json5 (usrpwd + access control), both real. The agent logs in with its
credentials from its configuration and an allowed operator drives it on either link; a client
without credentials is refused by the router, so it cannot drive over Zenoh.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest
import zenoh

from fleetlink.agent.config import AgentConfig, Rates, ZenohSettings, mqtt_settings
from fleetlink.agent.runtime import AgentRuntime
from fleetlink.field.board import SimulatedBoard
from fleetlink.field.device_server import DeviceServer
from fleetlink.links.mqtt import connect_client
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, AckResult, State, Teleop
from fleetlink.shared.mqtt import MqttSettings
from tests.harness import wait_until
from tests.harness.deploy import DeployBroker, mosquitto_passwd
from tests.test_deploy import USERS, ZUSERS, Router


class Seen:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.acks: list[tuple[str, Ack]] = []
        self.states: list[tuple[str, State]] = []

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

    def ack(self, link: str, header_id: int) -> Ack | None:
        with self.lock:
            return next((a for lk, a in self.acks if lk == link and a.commandHeaderId == header_id), None)

    def state_on(self, link: str) -> State | None:
        with self.lock:
            return next((s for lk, s in reversed(self.states) if lk == link), None)


@pytest.fixture
def site(tmp_path: Path) -> Iterator[tuple[DeployBroker, Router]]:
    broker = DeployBroker(tmp_path / "broker", "mosquitto.conf", passwd=mosquitto_passwd(tmp_path / "passwd", USERS))
    broker.start()
    router = Router(tmp_path)
    try:
        yield broker, router
    finally:
        router.close()
        broker.stop()


def test_agent_logs_in_to_the_secured_site_and_only_credentialed_operators_reach_it(
    site: tuple[DeployBroker, Router],
) -> None:
    broker, router = site
    clock = SystemClock()
    board = SimulatedBoard()
    server = DeviceServer(board, clock, name="board")
    port = server.serve_tcp()
    cfg = AgentConfig(
        robot="r1",
        board=f"socket://127.0.0.1:{port}",
        zenoh=ZenohSettings(connect=(router.endpoint,), mode="client", username="r1", password=ZUSERS["r1"]),
        mqtt=mqtt_settings(f"mqtt://{broker.host}:{broker.port}", "r1", USERS["r1"]),
        rates=Rates(state_hz=5.0),
        operators=("op-alice",),
    )
    agent = AgentRuntime(cfg, clock, seed=1)
    seen = Seen()
    mc: Any = None
    try:
        agent.start()
        op_z = router.client("op-alice")
        op_z.declare_subscriber(
            keys.zenoh_robot("r1"), lambda s: seen.record("zenoh", str(s.key_expr), s.payload.to_bytes())
        )
        mc = connect_client(
            MqttSettings(host=broker.host, port=broker.port, username="op-alice", password=USERS["op-alice"]),
            client_id="op-alice",
            start=False,
        )
        mc.on_message = lambda c, u, m: seen.record("mqtt", m.topic, bytes(m.payload))
        mc.on_connect = lambda c, u, f, rc, p: c.subscribe(keys.mqtt_robot("r1"), qos=1)
        mc.connect(broker.host, broker.port)
        mc.loop_start()
        # The agent logged in on both links: its state says so, on both.
        for link in ("zenoh", "mqtt"):
            wait_until(
                lambda link=link: (s := seen.state_on(link)) is not None and s.links.zenoh and s.links.mqtt,
                timeout=15.0,
                message=f"a state on {link} saying both links are up",
            )
        alice = wire.HeaderCounter(clock, robot="r1", sender="op-alice")
        # The allowed operator drives over Zenoh, then over MQTT.
        for link in ("zenoh", "mqtt"):
            sent: list[int] = []

            def drive(link: str = link, sent: list[int] = sent) -> bool:
                m = alice.make(Teleop, v=0.3, omega=0.0, ttl_s=0.5)
                sent.append(m.header.headerId)
                data = wire.encode(m)
                if link == "zenoh":
                    op_z.put(wire.key_of(m), data)
                else:
                    mc.publish(wire.key_of(m), data, qos=1)
                a = seen.ack(link, sent[0])
                return a is not None and board.state.v_left > 0.1

            wait_until(drive, interval=0.1, message=f"op-alice's teleop over {link} to turn the wheels")
            first = seen.ack(link, sent[0])
            assert first is not None and first.result is AckResult.ACCEPTED
            wait_until(lambda: abs(board.state.v_left) < 0.01, message="the stop after the ttl")
        # Without credentials the router refuses the session: nothing to drive with over Zenoh.
        for user, password in ((None, None), ("op-alice", "wrong")):
            with pytest.raises(zenoh.ZError):
                router.client(user, password)
        # Without credentials the broker refuses the MQTT client too.
        intruder = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="intruder")
        with pytest.raises(Exception):  # noqa: B017  (paho raises on the refused CONNACK's loop)
            intruder.connect(broker.host, broker.port)
            for _ in range(50):
                intruder.loop(0.05)
                if intruder.is_connected():
                    break
            if not intruder.is_connected():
                raise ConnectionRefusedError("refused")
        assert abs(board.state.v_left) < 0.01
    finally:
        if mc is not None:
            mc.loop_stop()
            mc.disconnect()
        agent.stop()
        server.stop()
