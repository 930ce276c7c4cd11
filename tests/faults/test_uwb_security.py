"""The UWB gateway on a secured site: it logs in as ``uwb-gateway`` to a Mosquitto running deploy/'s
password file and ACL and to a Zenoh router with authentication and default-deny access control
(its truth subscription), and publishes fixes that a robot receives. A robot or an operator that
forges a fix on the robot's uwb key is dropped by the broker: the robot never sees it.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
import zenoh

from fleetlink.field.realtime import TruthSample
from fleetlink.field.scenario import site_geometry
from fleetlink.field.truth import TruthPublisher
from fleetlink.links.mqtt import connect_client
from fleetlink.links.zenoh import peer_config
from fleetlink.positioning.config import parse_config
from fleetlink.positioning.publisher import UwbGateway
from fleetlink.shared import keys, wire
from fleetlink.shared.access import zenoh_access_control
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import FixStatus, UwbFix
from fleetlink.shared.mqtt import MqttSettings
from tests.harness import wait_until
from tests.harness.deploy import DeployBroker, mosquitto_passwd, zenoh_router_config
from tests.harness.mosquitto import free_port

USERS = {"r1": "pw-r1", "r2": "pw-r2", "op-alice": "pw-alice", "uwb-gateway": "pw-gw"}
ZUSERS = {"uwb-gateway": "zpw-gw", "sim": "zpw-sim", "r1": "zpw-r1"}
TRUE_X, TRUE_Y = 4.0, 3.0
FORGED_X = 42.0  # far from anything the gateway would report


class Listener:
    """A client logged in as robot r1 (what its agent does), subscribed to its own uwb key."""

    def __init__(self, broker: DeployBroker) -> None:
        self.fixes: list[UwbFix] = []
        self.lock = threading.Lock()
        self.subscribed = threading.Event()
        s = MqttSettings(host=broker.host, port=broker.port, username="r1", password=USERS["r1"])
        self.client = connect_client(s, client_id="agent-r1", start=False)
        self.client.on_connect = lambda c, *_: c.subscribe(keys.key("r1", "uwb"), qos=0)
        self.client.on_subscribe = lambda *_: self.subscribed.set()
        self.client.on_message = self._on_message
        self.client.connect_async(s.host, s.port, keepalive=s.keepalive_s)
        self.client.loop_start()

    def _on_message(self, _c: object, _u: object, m: mqtt.MQTTMessage) -> None:
        msg = wire.decode_key(m.topic, m.payload)  # the agent's own check: a bad one would raise here
        assert isinstance(msg, UwbFix)
        with self.lock:
            self.fixes.append(msg)

    def count(self) -> int:
        with self.lock:
            return len(self.fixes)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


@pytest.fixture
def site(tmp_path: Path) -> Iterator[tuple[DeployBroker, str, Path]]:
    broker = DeployBroker(tmp_path / "broker", "mosquitto.conf", passwd=mosquitto_passwd(tmp_path / "passwd", USERS))
    users = tmp_path / "zenoh-users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in ZUSERS.items()))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh_router_config(users, endpoint)
    # A test site: the simulated field (user sim) may publish ground truth.
    conf.insert_json5("access_control", json.dumps(zenoh_access_control(["r1"], ["op-alice"], simulator=True)))
    broker.start()
    router = zenoh.open(conf)
    try:
        yield broker, endpoint, tmp_path
    finally:
        router.close()
        broker.stop()


def _gateway_config(broker: DeployBroker, endpoint: str, folder: Path, password: str = USERS["uwb-gateway"]) -> dict:
    pw_file = folder / "uwb-mqtt-password"
    pw_file.write_text(password + "\n")
    return {
        "plan": "office",
        "gateway": {"id": "gw1", "rate_hz": 20.0},
        "tags": [{"id": "0d7f", "robot": "r1"}],
        "noise": {"profile": "none"},
        "mqtt": {
            "url": f"mqtt://127.0.0.1:{broker.port}",
            "username": "uwb-gateway",
            "password_file": pw_file.name,
            "keepalive_s": 5,
        },
        "zenoh": {
            "connect": [endpoint],
            "mode": "client",
            "username": "uwb-gateway",
            "password": ZUSERS["uwb-gateway"],
        },
    }


def test_gateway_publishes_through_the_secured_site_and_nobody_else_forges_fixes(
    site: tuple[DeployBroker, str, Path],
) -> None:
    broker, endpoint, folder = site
    clock = SystemClock()
    cfg = parse_config(_gateway_config(broker, endpoint, folder), source="uwb.toml", base=folder, site=site_geometry)
    assert cfg.mqtt.username == "uwb-gateway" and cfg.zenoh_auth.username == "uwb-gateway"
    truth = TruthPublisher.open(clock, connect=(endpoint,), mode="client", username="sim", password=ZUSERS["sim"])
    stop = threading.Event()

    def feed() -> None:  # the field's ground truth, over the router, as user sim
        t = 0.0
        while not stop.wait(0.02):
            t += 0.02
            truth.publish(TruthSample("r1", t, TRUE_X, TRUE_Y, 0.0, 0.0, 0.0, False))

    feeder = threading.Thread(target=feed, name="truth", daemon=True)
    feeder.start()
    agent = Listener(broker)
    gateway = UwbGateway(cfg, clock)
    forgers: list[mqtt.Client] = []
    try:
        gateway.start()
        wait_until(agent.subscribed.is_set, message="the robot's subscription")
        wait_until(lambda: agent.count() >= 3, timeout=15, message="fixes from the gateway, truth over the router")
        assert gateway.refused == 0
        for user in ("r2", "op-alice", "r1"):
            s = MqttSettings(host=broker.host, port=broker.port, username=user, password=USERS[user])
            c = connect_client(s, client_id=f"forger-{user}")
            forgers.append(c)
            wait_until(c.is_connected, message=f"{user} connected")
            counter = wire.HeaderCounter(clock, robot="r1", sender="gw1")  # even claiming the gateway's id
            fix = counter.make(
                UwbFix,
                tag="0d7f",
                x=FORGED_X,
                y=FORGED_X,
                z=0.3,
                sd_x=0.01,
                sd_y=0.01,
                quality=100,
                status=FixStatus.OK,
                anchors=("A1", "A2", "A3"),
                residual_rms_m=0.0,
                measured_at=clock.wall(),
            )
            for _ in range(5):
                # QoS 1: the broker has dealt with (and, by the ACL, dropped) each one when it acks.
                c.publish(keys.key("r1", "uwb"), wire.encode(fix), qos=1).wait_for_publish(5)
        # Sentinel: fixes the gateway published after every forgery was acknowledged by the broker.
        after = agent.count()
        wait_until(lambda: agent.count() >= after + 5, timeout=15, message="fixes after the forgeries")
        with agent.lock:
            got = list(agent.fixes)
        assert all(f.x < 30.0 and f.y < 30.0 for f in got), [(f.x, f.y) for f in got if f.x >= 30.0]
        assert all(f.header.sender == "gw1" for f in got)
        ok = [f for f in got if f.status is FixStatus.OK]
        assert ok and all(abs(f.x - TRUE_X) < 0.3 and abs(f.y - TRUE_Y) < 0.3 for f in ok)
        # The gateway is still serving (no crash) after all that.
        n = gateway.published
        wait_until(lambda: gateway.published > n)
    finally:
        stop.set()
        feeder.join(2)
        for c in forgers:
            c.disconnect()
            c.loop_stop()
        gateway.stop()
        agent.close()
        truth.close()


def test_gateway_with_a_wrong_password_is_refused_and_publishes_nothing(
    site: tuple[DeployBroker, str, Path],
) -> None:
    broker, endpoint, folder = site
    cfg = parse_config(
        _gateway_config(broker, endpoint, folder, password="wrong"), source="uwb.toml", base=folder, site=site_geometry
    )
    agent = Listener(broker)
    gateway = UwbGateway(cfg, SystemClock(), subscribe_truth=False)
    try:
        gateway.start()
        wait_until(agent.subscribed.is_set, message="the robot's subscription")
        wait_until(lambda: gateway.refused >= 1, timeout=15, message="the broker refusing the gateway")
        for _ in range(20):
            gateway.on_truth("r1", TRUE_X, TRUE_Y)
        assert not gateway.up
        # A sentinel the real gateway account may send (over a second, good login) arrives; no fix before it.
        s = MqttSettings(host=broker.host, port=broker.port, username="uwb-gateway", password=USERS["uwb-gateway"])
        good = connect_client(s, client_id="sentinel")
        try:
            wait_until(good.is_connected)
            counter = wire.HeaderCounter(SystemClock(), robot="r1", sender="sentinel")
            fix = counter.make(
                UwbFix,
                tag="0d7f",
                x=1.0,
                y=1.0,
                z=0.3,
                sd_x=0.01,
                sd_y=0.01,
                quality=100,
                status=FixStatus.OK,
                anchors=("A1", "A2", "A3"),
                residual_rms_m=0.0,
                measured_at=1.0,
            )
            good.publish(keys.key("r1", "uwb"), wire.encode(fix), qos=1).wait_for_publish(5)
            wait_until(lambda: agent.count() >= 1, message="the sentinel")
        finally:
            good.disconnect()
            good.loop_stop()
        with agent.lock:
            assert [f.header.sender for f in agent.fixes] == ["sentinel"]
    finally:
        gateway.stop()
        agent.close()


def test_zenoh_forged_fixes_through_the_secured_router_never_reach_the_agent(tmp_path: Path) -> None:
    """The drill on the Zenoh side: a real agent logged in to a router with deploy/'s usrpwd and
    access control (fleetlink.site.security's site); robots, operators and the simulator put forged fixes on
    fleetlink/v1/r1/uwb; only the gateway's login gets a fix to the agent (the sentinel)."""
    from fleetlink.agent.config import AgentConfig, Rates, ZenohSettings
    from fleetlink.agent.runtime import AgentRuntime
    from fleetlink.field.board import SimulatedBoard
    from fleetlink.field.device_server import DeviceServer
    from fleetlink.site.security import SiteSecurity

    clock = SystemClock()
    site = SiteSecurity(["r1", "r2"], ["op-alice"], tls=False, folder=tmp_path).start()
    server = DeviceServer(SimulatedBoard(), clock, name="board")
    agent = None
    try:
        auth = site.zenoh_auth("r1")
        cfg = AgentConfig(
            robot="r1",
            board=f"socket://127.0.0.1:{server.serve_tcp()}",
            zenoh=ZenohSettings(
                connect=tuple(auth["connect"]), mode="client", username="r1", password=auth["password"]
            ),
            rates=Rates(state_hz=5.0),
            operators=("op-alice",),
        )
        agent = AgentRuntime(cfg, clock, seed=1).start()
        assert agent.zenoh is not None
        got: list[bytes] = []
        # What reaches the agent's Zenoh endpoint on its uwb key: a second receiver beside the agent's.
        agent.zenoh.subscribe(keys.key("r1", "uwb"), lambda _key, payload: got.append(payload))
        wait_until(lambda: agent.zenoh is not None and agent.zenoh.up, message="the agent on the router")

        def fix(x: float, sender: str) -> bytes:
            c = wire.HeaderCounter(clock, robot="r1", sender=sender)
            return wire.encode(c.make(
                UwbFix, tag="r1", x=x, y=x, z=0.3, sd_x=0.01, sd_y=0.01, quality=100, status=FixStatus.OK,
                anchors=("A1", "A2", "A3"), residual_rms_m=0.0, measured_at=clock.wall(),
            ))  # fmt: skip

        forged = fix(FORGED_X, "field-uwb")
        for user in ("r2", "r1", "op-alice", "sim"):
            s = zenoh.open(peer_config(**site.zenoh_auth(user)))
            try:
                for _ in range(5):
                    s.put(keys.key("r1", "uwb"), forged)
            finally:
                s.close()
        gw = zenoh.open(peer_config(**site.zenoh_auth("uwb-gateway")))
        try:
            good = fix(TRUE_X, "field-uwb")

            def sentinel() -> bool:
                gw.put(keys.key("r1", "uwb"), good)
                return good in got

            wait_until(sentinel, interval=0.1, message="the gateway's fix through the router")
        finally:
            gw.close()
        assert forged not in got
        assert agent._thread is not None and agent._thread.is_alive()
    finally:
        if agent is not None:
            agent.stop()
        server.stop()
        site.stop()
