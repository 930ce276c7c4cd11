"""deploy/ works with the real parts: Mosquitto on deploy/mosquitto*.conf + deploy/mosquitto.acl, a
Zenoh router on deploy/zenohd.json5, clients opened the way fleetlink opens them (shared/mqtt.py,
shared/zenoh_config.py), the systemd units verified by systemd-analyze.

Absence is shown without timing: after the forbidden messages the same client sends one it may
send (a sentinel); once the sentinel has arrived, anything sent before it would have too.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
import zenoh

from fleetlink.links.mqtt import connect_client, nodelay_enabled
from fleetlink.links.zenoh import peer_config
from fleetlink.shared import keys
from fleetlink.shared.access import mosquitto_acl, zenoh_access_control
from fleetlink.shared.mqtt import MqttSettings
from tests.harness import wait_until
from tests.harness.deploy import DEPLOY, DeployBroker, SiteCA, make_site_ca, mosquitto_passwd, zenoh_router_config
from tests.harness.mosquitto import free_port

USERS = {"r1": "pw-r1", "r2": "pw-r2", "op-alice": "pw-alice", "op-bob": "pw-bob", "uwb-gateway": "pw-gw"}


class Client:
    """A connected paho client (via connect_client) that records what it receives."""

    def __init__(self, settings: MqttSettings, user: str | None, password: str | None, subscribe: list[str]) -> None:
        self.got: list[tuple[str, bytes]] = []
        self.results: list[str] = []
        self.subscribed = threading.Event()
        s = MqttSettings(host=settings.host, port=settings.port, tls=settings.tls, ca_file=settings.ca_file)
        if user is not None:
            s = MqttSettings(host=s.host, port=s.port, tls=s.tls, ca_file=s.ca_file, username=user, password=password)
        self.client = connect_client(s, client_id=f"test-{user}", start=False)
        self.client.on_connect = self._on_connect
        self.client.on_message = lambda _c, _u, m: self.got.append((m.topic, m.payload))
        self.client.on_subscribe = lambda *_a: self.subscribed.set()
        self.topics = subscribe
        self.client.connect_async(s.host, s.port, keepalive=5)
        self.client.loop_start()

    def _on_connect(self, client: mqtt.Client, _u: object, _f: object, reason: object, _p: object) -> None:
        self.results.append(str(reason))
        if not getattr(reason, "is_failure", True):
            if self.topics:
                client.subscribe([(t, 1) for t in self.topics])
            else:
                self.subscribed.set()
        else:
            client.disconnect()  # no retrying with bad credentials

    def ready(self) -> Client:
        wait_until(lambda: self.subscribed.is_set() or (self.results and self.results[-1] != "Success"))
        assert self.results[-1] == "Success", self.results
        return self

    def publish(self, topic: str, payload: bytes = b"x") -> None:
        self.client.publish(topic, payload, qos=1).wait_for_publish(5)

    def topics_got(self) -> list[str]:
        return [t for t, _ in self.got]

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


@pytest.fixture
def site_ca(tmp_path: Path) -> SiteCA:
    return make_site_ca(tmp_path / "ca")


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[DeployBroker]:
    b = DeployBroker(tmp_path / "broker", "mosquitto.conf", passwd=mosquitto_passwd(tmp_path / "passwd", USERS))
    b.start()
    yield b
    b.stop()


@pytest.fixture
def clients() -> Iterator[list[Client]]:
    made: list[Client] = []
    yield made
    for c in made:
        c.close()


def _client(
    clients: list[Client], b: DeployBroker, user: str | None, subscribe: Sequence[str] = (), pw: str | None = None
) -> Client:
    password = pw if pw is not None else USERS.get(user or "")
    c = Client(MqttSettings(host=b.host, port=b.port), user, password, list(subscribe))
    clients.append(c)
    return c


def test_acl_file_is_the_generated_policy() -> None:
    text = (DEPLOY / "mosquitto.acl").read_text()
    operators = re.findall(r"^user (op-\S+)$", text, flags=re.M)
    robots = re.findall(r"^user (?!op-|uwb-gateway$|sim$)(\S+)$", text, flags=re.M)
    assert operators and robots
    assert text == mosquitto_acl(operators, robots)


def test_agent_writes_only_its_own_telemetry(broker: DeployBroker, clients: list[Client]) -> None:
    op = _client(clients, broker, "op-alice", ["fleetlink/v1/#", "dwm/#"]).ready()
    r1 = _client(clients, broker, "r1").ready()
    for forbidden in (
        "fleetlink/v1/r2/state",  # another robot's state
        "fleetlink/v1/r1/teleop/r1",  # a command, even to itself under its own name
        "fleetlink/v1/r1/lease/request/r1",  # asking itself for control
        "fleetlink/v1/r2/teleop/op-alice",
        "fleetlink/v1/r2/order/r1",
        "fleetlink/v1/r1/uwb",  # forging its own fix
        "dwm/node/1234/uplink/location",
        "fleetlink/v1/sim/r1/truth",
    ):
        r1.publish(forbidden, b"forbidden")
    r1.publish("fleetlink/v1/r1/pose", b"sentinel")
    wait_until(lambda: "fleetlink/v1/r1/pose" in op.topics_got(), message="the sentinel")
    r1.publish("fleetlink/v1/r1/state", b"ok")
    wait_until(lambda: "fleetlink/v1/r1/state" in op.topics_got())
    assert all(p != b"forbidden" for _, p in op.got), op.got


def test_operator_drives_and_robots_hear_only_their_own_commands(broker: DeployBroker, clients: list[Client]) -> None:
    r1 = _client(clients, broker, "r1", ["fleetlink/v1/r1/#"]).ready()
    r2 = _client(clients, broker, "r2", ["fleetlink/v1/r1/#", "fleetlink/v1/r2/#"]).ready()
    op = _client(clients, broker, "op-alice").ready()
    op.publish("fleetlink/v1/r1/teleop/op-alice", b"drive-r1")
    op.publish("fleetlink/v1/r1/order/op-alice", b"order-r1")
    op.publish("fleetlink/v1/r2/teleop/op-alice", b"drive-r2")
    wait_until(lambda: ("fleetlink/v1/r2/teleop/op-alice", b"drive-r2") in r2.got)
    wait_until(lambda: len(r1.got) == 2)
    assert r1.got == [("fleetlink/v1/r1/teleop/op-alice", b"drive-r1"), ("fleetlink/v1/r1/order/op-alice", b"order-r1")]
    # r2 asked for r1's commands too; the broker gave it only its own.
    assert r2.topics_got() == ["fleetlink/v1/r2/teleop/op-alice"]


def test_a_robot_hears_the_other_robots_poses_and_nothing_else_of_theirs(
    broker: DeployBroker, clients: list[Client]
) -> None:
    """Its peers' poses (agent/peers.py: planned around, kept out of the way), read only."""
    r1 = _client(clients, broker, "r1", ["fleetlink/v1/+/pose", "fleetlink/v1/r2/#"]).ready()
    gateway = _client(clients, broker, "uwb-gateway", ["fleetlink/v1/+/pose", "dwm/#"]).ready()  # robots' only
    r2 = _client(clients, broker, "r2").ready()
    r2.publish("fleetlink/v1/r2/state", b"state")
    r2.publish("fleetlink/v1/r2/pose", b"pose")  # after the state: once it is in, the state had its turn
    wait_until(lambda: ("fleetlink/v1/r2/pose", b"pose") in r1.got)
    assert r1.topics_got() == ["fleetlink/v1/r2/pose"]
    r1.publish("fleetlink/v1/r2/pose", b"forged")  # and it still writes only its own
    r2.publish("fleetlink/v1/r2/pose", b"after")
    wait_until(lambda: ("fleetlink/v1/r2/pose", b"after") in r1.got)
    assert ("fleetlink/v1/r2/pose", b"forged") not in r1.got
    # The gateway may not read them: its own message, after them, comes to it alone.
    gateway.publish("dwm/node/t1/uplink/location", b"fix")
    wait_until(lambda: ("dwm/node/t1/uplink/location", b"fix") in gateway.got)
    assert gateway.topics_got() == ["dwm/node/t1/uplink/location"]


def test_an_operator_commands_only_under_its_own_name(broker: DeployBroker, clients: list[Client]) -> None:
    """The last segment of a command's topic is the sender's login: op-bob cannot write under
    op-alice's name (nor under none), so the agent can trust the segment (issue 14)."""
    r1 = _client(clients, broker, "r1", ["fleetlink/v1/r1/#"]).ready()
    watcher = _client(clients, broker, "op-alice", ["fleetlink/v1/+/marks/#"]).ready()
    bob = _client(clients, broker, "op-bob").ready()
    for topic in ("teleop", "order", "actions", "lease/request"):
        bob.publish(f"fleetlink/v1/r1/{topic}/op-alice", b"forged")
        bob.publish(f"fleetlink/v1/r1/{topic}", b"forged")  # the old, nameless key
    bob.publish("fleetlink/v1/r1/marks/op-alice", b"forged")
    bob.publish("fleetlink/v1/r1/teleop/op-bob", b"sentinel")
    bob.publish("fleetlink/v1/r1/marks/op-bob", b"sentinel")
    wait_until(lambda: ("fleetlink/v1/r1/teleop/op-bob", b"sentinel") in r1.got, message="bob's own command")
    wait_until(lambda: ("fleetlink/v1/r1/marks/op-bob", b"sentinel") in watcher.got, message="bob's own mark")
    assert all(p != b"forged" for _, p in r1.got + watcher.got), (r1.got, watcher.got)


def test_only_the_gateway_publishes_fixes(broker: DeployBroker, clients: list[Client]) -> None:
    r1 = _client(clients, broker, "r1", ["fleetlink/v1/r1/uwb", "fleetlink/v1/r1/uwb/ranges"]).ready()
    op = _client(clients, broker, "op-alice", ["fleetlink/v1/+/uwb", "dwm/#", "fleetlink/uwb/+/status"]).ready()
    r2 = _client(clients, broker, "r2").ready()
    r2.publish("fleetlink/v1/r1/uwb", b"forged")
    op.publish("fleetlink/v1/r1/uwb", b"forged")
    op.publish("dwm/node/42/uplink/location", b"forged")
    gw = _client(clients, broker, "uwb-gateway").ready()
    gw.publish("fleetlink/v1/r1/uwb", b"fix")
    gw.publish("fleetlink/v1/r1/uwb/ranges", b"ranges")
    gw.publish("dwm/node/42/uplink/location", b"dwm")
    gw.publish("fleetlink/uwb/gw1/status", b"online")
    wait_until(lambda: len(r1.got) == 2 and len(op.got) == 3)
    assert r1.got == [("fleetlink/v1/r1/uwb", b"fix"), ("fleetlink/v1/r1/uwb/ranges", b"ranges")]
    assert op.got == [
        ("fleetlink/v1/r1/uwb", b"fix"),
        ("dwm/node/42/uplink/location", b"dwm"),
        ("fleetlink/uwb/gw1/status", b"online"),
    ]
    # The gateway may not drive.
    gw.publish("fleetlink/v1/r1/teleop/op-alice", b"forbidden")
    gw.publish("fleetlink/v1/r1/uwb", b"sentinel")
    wait_until(lambda: ("fleetlink/v1/r1/uwb", b"sentinel") in r1.got)
    assert all(p != b"forbidden" for _, p in r1.got)


@pytest.mark.parametrize(("user", "password"), [(None, None), ("r1", "wrong"), ("intruder", "pw")])
def test_unauthenticated_clients_are_refused(
    broker: DeployBroker, clients: list[Client], user: str | None, password: str | None
) -> None:
    c = _client(clients, broker, user, pw=password or "")
    wait_until(lambda: c.results, message="a CONNACK")
    assert c.results[0] in ("Not authorized", "Bad user name or password"), c.results


def test_last_will_reaches_operators(broker: DeployBroker, clients: list[Client], tmp_path: Path) -> None:
    op = _client(clients, broker, "op-alice", ["fleetlink/v1/+/connection"]).ready()
    from fleetlink.links.mqtt import MqttMessage

    settings = MqttSettings(host=broker.host, port=broker.port, username="r1", password=USERS["r1"], keepalive_s=1)
    agent = connect_client(
        settings, client_id="agent-r1", will=MqttMessage("fleetlink/v1/r1/connection", b"BROKEN", 1, True)
    )
    try:
        wait_until(agent.is_connected)
        assert nodelay_enabled(agent)
        # Vanish without a DISCONNECT: close the socket under paho.
        sock = agent.socket()
        assert sock is not None
        agent.loop_stop()
        sock.close()
        wait_until(lambda: ("fleetlink/v1/r1/connection", b"BROKEN") in op.got, timeout=15)
    finally:
        agent.loop_stop()


def test_tls_listener_with_site_ca(tmp_path: Path, site_ca: SiteCA, clients: list[Client]) -> None:
    passwd = mosquitto_passwd(tmp_path / "passwd", USERS)
    b = DeployBroker(tmp_path / "tls-broker", "mosquitto-tls.conf", passwd=passwd, ca=site_ca)
    b.start()
    try:
        good = MqttSettings(
            host="localhost", port=b.tls_port, tls=True, ca_file=str(site_ca.ca_crt), username="r1", password="pw-r1"
        )
        client = connect_client(good, client_id="tls-r1")
        try:
            wait_until(client.is_connected, message="a TLS connection")
            assert nodelay_enabled(client)
        finally:
            client.disconnect()
            client.loop_stop()
        # Without the site CA the broker's certificate is not trusted: never connected.
        untrusted = MqttSettings(host="localhost", port=b.tls_port, tls=True, username="r1", password="pw-r1")
        c2 = connect_client(untrusted, client_id="tls-untrusted", start=False)
        with pytest.raises(Exception, match=r"CERTIFICATE_VERIFY_FAILED|certificate verify failed"):
            c2.connect("localhost", b.tls_port, keepalive=5)
        # The plain listener is bound to loopback only and still needs a password.
        assert "listener 1883 127.0.0.1" in (DEPLOY / "mosquitto-tls.conf").read_text()
    finally:
        b.stop()


# ------------------------------------------------------------------------------------------------
# Zenoh: the router's own authentication and access control, in a real session in router mode.

ZUSERS = {"r1": "zpw-r1", "r2": "zpw-r2", "op-alice": "zpw-alice", "op-bob": "zpw-bob", "uwb-gateway": "zpw-gw"}


class Router:
    def __init__(self, tmp_path: Path, tls: SiteCA | None = None) -> None:
        users = tmp_path / "zenoh-users.txt"
        users.write_text("".join(f"{u}:{p}\n" for u, p in ZUSERS.items()))
        self.port = free_port()
        scheme = "tls" if tls else "tcp"
        self.session = zenoh.open(zenoh_router_config(users, f"{scheme}/127.0.0.1:{self.port}", ca=tls))
        self.endpoint = f"{scheme}/{'localhost' if tls else '127.0.0.1'}:{self.port}"
        self.opened: list[zenoh.Session] = []

    def client(self, user: str | None, password: str | None = None, root_ca: str | None = None) -> zenoh.Session:
        if user is not None and password is None:
            password = ZUSERS[user]
        conf = peer_config(connect=[self.endpoint], mode="client", username=user, password=password, root_ca=root_ca)
        s = zenoh.open(conf)
        self.opened.append(s)
        return s

    def close(self) -> None:
        for s in reversed(self.opened):
            s.close()
        self.session.close()


@pytest.fixture
def router(tmp_path: Path) -> Iterator[Router]:
    r = Router(tmp_path)
    yield r
    r.close()


def _collect(session: zenoh.Session, key: str) -> list[tuple[str, bytes]]:
    got: list[tuple[str, bytes]] = []
    session.declare_subscriber(key, lambda s: got.append((str(s.key_expr), s.payload.to_bytes())))
    return got


def _until_delivered(pub: zenoh.Session, key: str, got: list[tuple[str, bytes]]) -> None:
    """Publish a sentinel until it arrives (subscriptions take a moment to reach the router)."""

    def sent() -> bool:
        pub.put(key, b"sentinel")
        return (key, b"sentinel") in got

    wait_until(sent, interval=0.05, message=f"a sentinel on {key}")


def test_zenoh_router_config_acl_is_the_generated_policy() -> None:
    import json

    conf = zenoh.Config.from_file(str(DEPLOY / "zenohd.json5"))
    ac = json.loads(conf.get_json("access_control"))
    users = [u for s in ac["subjects"] for u in s["usernames"]]
    robots = [u for u in users if not u.startswith(("op-", "router-")) and u != "uwb-gateway"]
    ops = [u for u in users if u.startswith("op-")]
    routers = [u for u in users if u.startswith("router-")]
    assert robots and ops
    expected = zenoh.Config()  # through zenoh's own parser, which fills in the optional fields
    expected.insert_json5("access_control", json.dumps(zenoh_access_control(robots, ops, routers)))
    assert ac == json.loads(expected.get_json("access_control"))


def test_zenoh_agent_publishes_only_its_own_telemetry(router: Router) -> None:
    op = router.client("op-alice")
    got = _collect(op, "fleetlink/v1/**")
    r1 = router.client("r1")
    _until_delivered(r1, "fleetlink/v1/r1/state", got)
    for forbidden in (
        "fleetlink/v1/r2/state",
        "fleetlink/v1/r1/teleop/r1",
        "fleetlink/v1/r2/order/op-alice",
        "fleetlink/v1/r1/uwb",
    ):
        r1.put(forbidden, b"forbidden")
    r1.put("fleetlink/v1/r1/pose", b"after")
    wait_until(lambda: ("fleetlink/v1/r1/pose", b"after") in got)
    assert all(p != b"forbidden" for _, p in got), got


def test_zenoh_operator_drives_only_the_addressed_robot(router: Router) -> None:
    r1 = router.client("r1")
    r2 = router.client("r2")
    got1 = _collect(r1, "fleetlink/v1/r1/**")
    got2 = _collect(r2, "fleetlink/v1/r2/**")
    spy = _collect(r2, "fleetlink/v1/r1/**")  # r2 asks for r1's commands: the router never sends them
    op = router.client("op-alice")
    _until_delivered(op, "fleetlink/v1/r1/teleop/op-alice", got1)
    _until_delivered(op, "fleetlink/v1/r2/teleop/op-alice", got2)
    op.put("fleetlink/v1/r1/order/op-alice", b"order-r1")
    op.put("fleetlink/v1/r2/order/op-alice", b"order-r2")
    wait_until(lambda: ("fleetlink/v1/r2/order/op-alice", b"order-r2") in got2)
    wait_until(lambda: ("fleetlink/v1/r1/order/op-alice", b"order-r1") in got1)
    assert {k for k, _ in got2} == {"fleetlink/v1/r2/teleop/op-alice", "fleetlink/v1/r2/order/op-alice"}
    assert spy == []


def test_zenoh_a_robot_hears_the_other_robots_poses_and_nothing_else_of_theirs(router: Router) -> None:
    r1 = router.client("r1")
    poses = _collect(r1, "fleetlink/v1/r2/pose")
    spy = _collect(r1, "fleetlink/v1/r2/state")  # refused at the router: nothing arrives
    r2 = router.client("r2")
    r2.put("fleetlink/v1/r2/state", b"state")
    _until_delivered(r2, "fleetlink/v1/r2/pose", poses)
    r2.put("fleetlink/v1/r2/state", b"state")
    _until_delivered(r2, "fleetlink/v1/r2/pose", poses)
    assert spy == []


def test_zenoh_a_robot_hears_where_the_fleet_map_put_the_robots_and_cannot_say_it_itself(router: Router) -> None:
    """The fleet map's frames (a console's fleet map service shares them): what puts a peer without UWB
    in a robot's own frame (agent/peers.py). Read only: a robot cannot move where others think it is."""
    r1 = router.client("r1")
    frames = _collect(r1, "fleetlink/v1/fleet/frames")
    op = router.client("op-alice")
    watcher = _collect(op, "fleetlink/v1/fleet/frames")
    _until_delivered(op, "fleetlink/v1/fleet/frames", frames)
    r2 = router.client("r2")
    r2.put("fleetlink/v1/fleet/frames", b"forged")
    op.put("fleetlink/v1/fleet/frames", b"after")
    wait_until(lambda: ("fleetlink/v1/fleet/frames", b"after") in frames)
    wait_until(lambda: ("fleetlink/v1/fleet/frames", b"after") in watcher)
    assert all(p != b"forged" for _, p in frames + watcher)


def test_zenoh_operator_commands_only_under_its_own_name(router: Router) -> None:
    r1 = router.client("r1")
    got = _collect(r1, "fleetlink/v1/r1/**")
    alice = router.client("op-alice")
    marks = _collect(alice, "fleetlink/v1/*/marks/*")
    bob = router.client("op-bob")
    _until_delivered(bob, "fleetlink/v1/r1/teleop/op-bob", got)
    _until_delivered(bob, "fleetlink/v1/r1/marks/op-bob", marks)
    for topic in ("teleop", "order", "actions", "lease/request", "marks"):
        bob.put(f"fleetlink/v1/r1/{topic}/op-alice", b"forged")
        bob.put(f"fleetlink/v1/r1/{topic}", b"forged")
    bob.put("fleetlink/v1/r1/teleop/op-bob", b"after")
    bob.put("fleetlink/v1/r1/marks/op-bob", b"after")
    wait_until(lambda: ("fleetlink/v1/r1/teleop/op-bob", b"after") in got)
    wait_until(lambda: ("fleetlink/v1/r1/marks/op-bob", b"after") in marks)
    assert all(p != b"forged" for _, p in got + marks), (got, marks)


def test_zenoh_fixes_only_from_the_gateway(router: Router) -> None:
    r1 = router.client("r1")
    got = _collect(r1, "fleetlink/v1/r1/**")
    gw = router.client("uwb-gateway")
    _until_delivered(gw, "fleetlink/v1/r1/uwb", got)
    r2 = router.client("r2")
    op = router.client("op-alice")
    r2.put("fleetlink/v1/r1/uwb", b"forged")
    op.put("fleetlink/v1/r1/uwb", b"forged")
    gw.put("fleetlink/v1/r1/teleop/op-alice", b"forged")
    # Sentinels from each forger, on keys they may write and r1 may read.
    op.put("fleetlink/v1/r1/teleop/op-alice", b"op-after")
    gw.put("fleetlink/v1/r1/uwb", b"gw-after")
    wait_until(
        lambda: ("fleetlink/v1/r1/teleop/op-alice", b"op-after") in got and ("fleetlink/v1/r1/uwb", b"gw-after") in got
    )
    # r2 has no sentinel it could send to r1; its forged fix was sent before op's and gw's ones
    # left the router, and the router drops it on ingress (the same rule the other tests show).
    assert all(p != b"forged" for _, p in got), got


def test_zenoh_each_robot_declares_only_its_own_presence_token(router: Router) -> None:
    """Presence is ``fleetlink/alive/v1/<robot>`` (keys.alive_key, issue 18): a robot may hold its
    own token there and no other; consoles watch them all. The old key under the robot's own tree
    (``fleetlink/v1/<robot>/alive``) is refused too."""
    op = router.client("op-alice")
    seen: list[tuple[str, bool]] = []

    def heard(sample: zenoh.Sample) -> None:
        seen.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

    op.liveliness().declare_subscriber(keys.ZENOH_ALL_ALIVE, heard, history=True)
    op.liveliness().declare_subscriber("fleetlink/v1/**", heard, history=True)
    r1, r2 = router.client("r1"), router.client("r2")
    held = [
        r2.liveliness().declare_token(k)
        for k in (keys.alive_key("r1"), keys.alive_key("r3"), "fleetlink/v1/r2/alive", "fleetlink/alive/v1/r2/x")
    ]
    held.append(r2.liveliness().declare_token(keys.alive_key("r2")))  # the sentinel: its own, after the forgeries
    wait_until(lambda: (keys.alive_key("r2"), True) in seen, message="r2's own token")
    held.append(r1.liveliness().declare_token(keys.alive_key("r1")))
    wait_until(lambda: (keys.alive_key("r1"), True) in seen, message="r1's own token")
    assert seen == [(keys.alive_key("r2"), True), (keys.alive_key("r1"), True)], seen
    for token in held:
        token.undeclare()


@pytest.mark.parametrize(("user", "password"), [(None, None), ("r1", "wrong"), ("intruder", "x")])
def test_zenoh_router_refuses_unauthenticated(router: Router, user: str | None, password: str | None) -> None:
    with pytest.raises(zenoh.ZError):
        router.client(user, password)


def test_zenoh_tls_with_site_ca(tmp_path: Path, site_ca: SiteCA) -> None:
    r = Router(tmp_path, tls=site_ca)
    try:
        op = r.client("op-alice", root_ca=str(site_ca.ca_crt))
        got = _collect(op, "fleetlink/v1/**")
        r1 = r.client("r1", root_ca=str(site_ca.ca_crt))
        _until_delivered(r1, "fleetlink/v1/r1/state", got)
        with pytest.raises(zenoh.ZError):  # the router's certificate is not trusted without the CA
            r.client("r1")
    finally:
        r.close()


# ------------------------------------------------------------------------------------------------
# systemd units and udev rules


def test_systemd_units_verify(tmp_path: Path) -> None:
    tool = shutil.which("systemd-analyze")
    if tool is None:
        if os.environ.get("CI"):  # CI's machine has systemd: the units must be verified there
            pytest.fail("systemd-analyze not installed on the CI machine")
        pytest.skip("systemd-analyze not installed (Debian package systemd): the units were not verified")
    units = sorted((DEPLOY / "systemd").glob("*.service"))
    assert {u.name for u in units} == {"fleetlink-agent.service", "fleetlink-uwb.service", "fleetlink-zenohd.service"}
    for unit in units:
        text = unit.read_text()
        # The binaries are not installed here: point ExecStart at one that is, keep everything else.
        text = re.sub(r"^ExecStart=\S+", "ExecStart=/bin/true", text, flags=re.M)
        (tmp_path / unit.name).write_text(text)
    res = subprocess.run(
        [tool, "verify", *(str(tmp_path / u.name) for u in units)], capture_output=True, text=True, timeout=60
    )
    problems = [line for line in (res.stdout + res.stderr).splitlines() if "fleetlink" in line]
    assert res.returncode == 0 and not problems, res.stdout + res.stderr
    agent = (DEPLOY / "systemd" / "fleetlink-agent.service").read_text()
    assert "ExecStart=/opt/fleetlink/bin/fleetlink agent --config /etc/fleetlink/robot.toml" in agent
    assert "SupplementaryGroups=dialout" in agent and "Restart=always" in agent
    for unit in ("fleetlink-agent.service", "fleetlink-uwb.service"):  # the shutdown contract (cli/main.py)
        text = (DEPLOY / "systemd" / unit).read_text()
        assert "KillSignal=SIGTERM" in text and "TimeoutStopSec=5s" in text, unit


def test_udev_rules_name_board_and_lidar() -> None:
    rules = [
        line
        for line in (DEPLOY / "99-fleetlink.rules").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    links = {re.search(r'SYMLINK\+="([^"]+)"', r).group(1) for r in rules}  # type: ignore[union-attr]
    assert links == {"fleetlink-board", "fleetlink-lidar"}
    for r in rules:
        assert 'SUBSYSTEM=="tty"' in r and 'GROUP="dialout"' in r and 'ENV{ID_MM_DEVICE_IGNORE}="1"' in r


def test_every_zenoh_session_and_the_router_refuse_messages_over_the_wire_limit(tmp_path: Path) -> None:
    """No Zenoh node reassembles a message larger than the wire contract allows (issue 14)."""
    from fleetlink.links.zenoh import MAX_MESSAGE_BYTES, peer_config
    from fleetlink.shared.wire import MAX_PAYLOAD

    users = tmp_path / "users.txt"
    users.write_text("r1:pw\n")
    router = zenoh_router_config(users, "tcp/127.0.0.1:0")
    for conf in (router, peer_config()):
        assert json.loads(conf.get_json("transport/link/rx/max_message_size")) == MAX_MESSAGE_BYTES
    assert MAX_PAYLOAD < MAX_MESSAGE_BYTES < 2 * MAX_PAYLOAD
