"""The harness works with real clients: paho-mqtt through a private mosquitto, zenoh between peers."""

from __future__ import annotations

import queue
import socket
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
import zenoh

from tests.harness import leaked_threads, wait_until
from tests.harness.mosquitto import MosquittoBroker, MosquittoNotFound, find_mosquitto
from tests.harness.zenoh_peers import ZenohPeers

SYSTEM_BROKER_PORT = 1883


# --- MQTT helpers -------------------------------------------------------------------------------


@contextmanager
def mqtt_client(
    broker: MosquittoBroker, client_id: str, subscribe: str | None = None
) -> Iterator[tuple[mqtt.Client, queue.Queue[mqtt.MQTTMessage], threading.Event]]:
    """A connected paho 2.x client running its network loop; (re)subscribes on every connect."""
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id)
    # Fast auto-reconnect for the restart drill (paho accepts float delays; its hint says int).
    client.reconnect_delay_set(min_delay=0.05, max_delay=0.5)  # type: ignore[arg-type]
    received: queue.Queue[mqtt.MQTTMessage] = queue.Queue()
    connected = threading.Event()

    def on_connect(c: mqtt.Client, userdata: object, flags: object, reason: object, props: object) -> None:
        if subscribe is not None:
            c.subscribe(subscribe, qos=1)
        connected.set()

    def on_subscribe(c: mqtt.Client, userdata: object, mid: int, reasons: object, props: object) -> None:
        subscribed.set()

    def on_disconnect(c: mqtt.Client, userdata: object, flags: object, reason: object, props: object) -> None:
        connected.clear()
        subscribed.clear()

    subscribed = threading.Event()
    client.on_connect = on_connect
    client.on_subscribe = on_subscribe
    client.on_disconnect = on_disconnect
    client.on_message = lambda c, u, msg: received.put(msg)
    client.connect(broker.host, broker.port, keepalive=10)
    client.loop_start()
    try:
        wait_until(connected.is_set, timeout=5, message=f"{client_id} connected")
        if subscribe is not None:
            wait_until(subscribed.is_set, timeout=5, message=f"{client_id} subscribed")
        yield client, received, subscribed
    finally:
        client.disconnect()
        client.loop_stop()


def publish_qos1(client: mqtt.Client, topic: str, payload: bytes) -> None:
    info = client.publish(topic, payload, qos=1)
    info.wait_for_publish(timeout=5)
    assert info.is_published(), "no PUBACK for QoS 1 publish"


# --- Mosquitto ----------------------------------------------------------------------------------


def test_broker_is_private(mosquitto: MosquittoBroker) -> None:
    assert mosquitto.host == "127.0.0.1"
    assert mosquitto.port != SYSTEM_BROKER_PORT
    assert mosquitto.running
    conf = mosquitto.conf_path.read_text()
    for line in (
        f"listener {mosquitto.port} 127.0.0.1",
        "allow_anonymous true",
        "set_tcp_nodelay true",
        "persistence false",
    ):
        assert line in conf
    assert f"port {mosquitto.port}" in mosquitto.log_text()


def test_mqtt_qos1_roundtrip(mosquitto: MosquittoBroker) -> None:
    with (
        mqtt_client(mosquitto, "sub", subscribe="fleet/test/#") as (_, received, _),
        mqtt_client(mosquitto, "pub") as (pub, _, _),
    ):
        publish_qos1(pub, "fleet/test/hello", b"hello")
        msg = received.get(timeout=5)
        assert (msg.topic, msg.payload, msg.qos) == ("fleet/test/hello", b"hello", 1)


@pytest.mark.parametrize("how", ["stop", "kill"])
def test_mqtt_reconnects_after_broker_restart(mosquitto: MosquittoBroker, how: str) -> None:
    port = mosquitto.port
    with (
        mqtt_client(mosquitto, "sub", subscribe="fleet/restart") as (sub, received, subscribed),
        mqtt_client(mosquitto, "pub") as (pub, _, _),
    ):
        publish_qos1(pub, "fleet/restart", b"before")
        assert received.get(timeout=5).payload == b"before"

        getattr(mosquitto, how)()
        assert not mosquitto.running
        wait_until(lambda: not sub.is_connected() and not pub.is_connected(), timeout=5, message="drop")
        mosquitto.start()
        assert mosquitto.port == port

        wait_until(lambda: sub.is_connected() and pub.is_connected(), timeout=5, message="reconnect")
        wait_until(subscribed.is_set, timeout=5, message="resubscribe")
        publish_qos1(pub, "fleet/restart", b"after")
        assert received.get(timeout=5).payload == b"after"
    assert mosquitto.log_text().count(f"port {port}") >= 2  # one "Opening ... listen socket" per start


def test_factory_extra_conf_and_independent_brokers(
    mosquitto_factory: Callable[..., MosquittoBroker],
) -> None:
    a = mosquitto_factory("max_packet_size 1000")
    b = mosquitto_factory()
    assert a.port != b.port
    assert "max_packet_size 1000" in a.conf_path.read_text()
    assert "max_packet_size 1000" not in b.conf_path.read_text()  # b has only the default limit
    with mqtt_client(b, "b-sub", subscribe="x") as (_, received_b, _), mqtt_client(a, "a-pub") as (pub, _, _):
        publish_qos1(pub, "x", b"only-on-a")
        with pytest.raises(queue.Empty):
            received_b.get(timeout=0.2)


def test_stop_releases_port_and_is_idempotent(tmp_path: Path) -> None:
    broker = MosquittoBroker(tmp_path).start()
    broker.stop()
    broker.stop()
    broker.kill()
    with socket.socket() as s:  # nothing listening any more
        assert s.connect_ex((broker.host, broker.port)) != 0


def test_missing_binary_is_a_clear_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(MosquittoNotFound, match=r"\.ci/install-mosquitto"):
        find_mosquitto(fallback=str(tmp_path / "no-such-mosquitto"))


# --- Zenoh --------------------------------------------------------------------------------------


def test_zenoh_put_reaches_other_peer(zenoh_peers: Callable[..., ZenohPeers]) -> None:
    a, b = zenoh_peers(2)
    got: queue.Queue[bytes] = queue.Queue()
    b.declare_subscriber("fleet/test/**", lambda sample: got.put(sample.payload.to_bytes()))

    def delivered() -> bool:
        a.put("fleet/test/ping", b"ping")
        try:
            return got.get(timeout=0.05) == b"ping"
        except queue.Empty:
            return False

    wait_until(delivered, timeout=10, interval=0, message="zenoh put delivered a -> b")


def test_zenoh_query_roundtrip(zenoh_peers: Callable[..., ZenohPeers]) -> None:
    a, b = zenoh_peers(2)

    def answer(query: zenoh.Query) -> None:
        query.reply(query.key_expr, b"pong:" + (query.payload.to_bytes() if query.payload else b""))

    a.declare_queryable("fleet/test/echo", answer)
    replies: list[bytes] = []

    def answered() -> bool:
        for reply in b.get("fleet/test/echo", payload=b"hi", timeout=0.5):
            assert reply.ok is not None, reply.err
            replies.append(reply.ok.payload.to_bytes())
        return bool(replies)

    wait_until(answered, timeout=10, interval=0.01, message="zenoh query answered by the other peer")
    assert replies == [b"pong:hi"]


def test_zenoh_three_peers_meshed(zenoh_peers: Callable[..., ZenohPeers]) -> None:
    peers = zenoh_peers(3)
    assert len(peers) == len(peers.endpoints) == 3
    assert all(ep.startswith("tcp/127.0.0.1:") for ep in peers.endpoints)
    for s in peers:
        assert len(s.info.peers_zid()) == 2


# --- Thread-leak guard --------------------------------------------------------------------------


def test_leaked_threads_reports_stuck_non_daemon_thread_only() -> None:
    before = set(threading.enumerate())
    release = threading.Event()
    stuck = threading.Thread(target=release.wait, name="stuck", daemon=False)
    quick = threading.Thread(target=lambda: None, name="quick", daemon=False)
    daemon = threading.Thread(target=release.wait, name="daemon", daemon=True)
    for t in (stuck, quick, daemon):
        t.start()
    try:
        assert leaked_threads(before, grace=0.1) == [stuck]
    finally:
        release.set()
        for t in (stuck, daemon):
            t.join()
    assert leaked_threads(before, grace=0.1) == []
