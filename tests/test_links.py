"""One suite, three endpoints: the same ``Link`` behaviours in-process, over Zenoh on loopback and
over a real private Mosquitto.

Each case gets a pair of endpoints (``a`` publishes, ``b`` subscribes) and a ``settle`` that
waits for a condition: the in-process bus is pumped (``deliver``) until it holds, the real
transports are polled. Zenoh sessions are opened by ``ZenohEndpoint`` itself (the one session
factory: explicit loopback endpoints, multicast scouting off); MQTT clients by ``MqttEndpoint``
(``connect_client``: TCP_NODELAY, backoff).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from fleetlink.links.base import Link
from fleetlink.links.inprocess import InProcessBus
from fleetlink.links.mqtt import MqttEndpoint, nodelay_enabled
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.shared import keys
from fleetlink.shared.messages import LinkName
from fleetlink.shared.mqtt import MqttSettings
from tests.harness import wait_until
from tests.harness.zenoh_peers import loopback_endpoint

PROBE = "fleetlink/v1/probe/ping"


@dataclass
class Pair:
    kind: str
    a: Any
    b: Any
    pump: Callable[[], object] = lambda: None

    def settle(self, cond: Callable[[], object], message: str, timeout: float = 10.0) -> None:
        def pumped() -> object:
            self.pump()
            return cond()

        wait_until(pumped, timeout=timeout, message=f"{self.kind}: {message}")

    def ready(self) -> None:
        """Start both, then wait until ``b``'s subscriptions (made before this) reach ``a``: a probe
        subscription declared last is heard, so the earlier ones have propagated too."""
        heard = threading.Event()
        self.b.subscribe(PROBE, lambda _k, _p: heard.set())
        self.a.start()
        self.b.start()
        self.settle(lambda: self.a.up and self.b.up, "both endpoints up")
        self.settle(lambda: self.a.publish(PROBE, b"?") is None or heard.is_set(), "a probe through")


@dataclass
class Inbox:
    got: list[tuple[str, bytes]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, key: str, payload: bytes) -> None:
        with self.lock:
            self.got.append((key, payload))

    def snapshot(self) -> list[tuple[str, bytes]]:
        with self.lock:
            return list(self.got)


@pytest.fixture(params=["inprocess", "zenoh", "mqtt"])
def pair(request: pytest.FixtureRequest) -> Iterator[Pair]:
    kind = request.param
    if kind == "inprocess":
        bus = InProcessBus(LinkName.ZENOH)
        p = Pair(kind, bus.endpoint("a"), bus.endpoint("b"), bus.deliver)
    elif kind == "zenoh":
        endpoint = loopback_endpoint()
        p = Pair(kind, ZenohEndpoint(listen=[endpoint]), ZenohEndpoint(connect=[endpoint]))
    else:
        broker = request.getfixturevalue("mosquitto")
        settings = MqttSettings("127.0.0.1", broker.port, reconnect_min_s=0.1, reconnect_max_s=0.5)
        p = Pair(kind, MqttEndpoint(settings, client_id="link-a"), MqttEndpoint(settings, client_id="link-b"))
    try:
        yield p
    finally:
        p.b.close()
        p.a.close()


def test_every_endpoint_is_a_link(pair: Pair) -> None:
    assert isinstance(pair.a, Link) and isinstance(pair.b, Link)
    assert pair.a.name in (LinkName.ZENOH, LinkName.MQTT)


def test_wildcards_one_segment_and_many(pair: Pair) -> None:
    one, many = Inbox(), Inbox()
    pair.b.subscribe(keys.zenoh_all_robots("pose"), one)  # fleetlink/v1/*/pose
    pair.b.subscribe(keys.zenoh_robot("r2"), many)  # fleetlink/v1/r2/**
    pair.ready()
    sent = {
        keys.key("r1", "pose"): b"1",  # one
        keys.key("r1", "state"): b"2",  # neither
        keys.key("r2", "state"): b"3",  # many
        keys.key("r2", "map/updates"): b"4",  # many: two segments below r2
        keys.key("r3", "map/pose"): b"5",  # neither: * is one segment only
    }
    for k, v in sent.items():
        assert pair.a.publish(k, v)
    pair.settle(lambda: len(one.snapshot()) >= 1 and len(many.snapshot()) >= 2, "the matching messages")
    pair.a.publish(keys.key("r9", "pose"), b"end")  # after everything above, on the same path
    pair.settle(lambda: (keys.key("r9", "pose"), b"end") in one.snapshot(), "the last message")
    assert one.snapshot() == [(keys.key("r1", "pose"), b"1"), (keys.key("r9", "pose"), b"end")]
    assert many.snapshot() == [(keys.key("r2", "state"), b"3"), (keys.key("r2", "map/updates"), b"4")]


def test_messages_on_different_keys_arrive_in_the_order_sent(pair: Pair) -> None:
    # One priority class on Zenoh (commands): zenoh keeps order within a priority. 200 QoS 1
    # messages: within what paho queues (MAX_QUEUED) beyond its 20 in flight.
    topics = ("order", "actions", "teleop", "lease/request")
    inbox = Inbox()
    for t in topics:
        pair.b.subscribe(keys.sender_filter("r1", t), inbox)
    pair.ready()
    sent = [(keys.sender_key("r1", topics[i % len(topics)], "op-a"), i.to_bytes(4, "big")) for i in range(200)]
    for k, v in sent:
        assert pair.a.publish(k, v)
    pair.settle(lambda: len(inbox.snapshot()) >= len(sent), f"{len(sent)} messages")
    assert inbox.snapshot() == sent


def test_up_and_down_and_close_is_idempotent(pair: Pair) -> None:
    inbox = Inbox()
    pair.b.subscribe(keys.key("r1", "pose"), inbox)
    assert not pair.a.up
    assert pair.a.publish(keys.key("r1", "pose"), b"early") is False  # not started: not sent
    assert pair.a.stats.dropped == 1 and pair.a.stats.sent == 0
    pair.ready()
    assert pair.a.publish(keys.key("r1", "pose"), b"x")
    pair.settle(lambda: inbox.snapshot(), "one message")
    pair.b.close()
    pair.b.close()  # idempotent
    assert not pair.b.up
    n = len(inbox.snapshot())
    pair.a.publish(keys.key("r1", "pose"), b"after b closed")
    pair.pump()
    assert len(inbox.snapshot()) == n  # no receiver is called after close returns
    pair.a.close()
    pair.a.close()
    assert not pair.a.up
    assert pair.a.publish(keys.key("r1", "pose"), b"late") is False


def test_stats_count_what_went_out_and_came_in(pair: Pair) -> None:
    inbox = Inbox()
    pair.b.subscribe(keys.zenoh_all_robots("pose"), inbox)
    pair.ready()
    a0, b0 = pair.a.stats.sent, pair.b.stats.received  # the probes
    for i in range(5):
        assert pair.a.publish(keys.key(f"r{i}", "pose"), b"p")
    pair.settle(lambda: len(inbox.snapshot()) == 5, "five poses")
    pair.settle(lambda: pair.b.stats.received - b0 >= 5, "five counted")  # (and a late probe, maybe)
    assert pair.a.stats.sent - a0 == 5 and pair.a.stats.dropped == 0
    assert pair.b.stats.last_rx is not None or pair.kind == "inprocess"  # the bus has no clock here


def test_a_receiver_that_raises(pair: Pair) -> None:
    """On a real transport the error is logged and delivery goes on; the in-process bus lets it
    through to whoever pumps it, so a lockstep run fails loudly."""
    inbox = Inbox()

    def broken(_key: str, _payload: bytes) -> None:
        raise RuntimeError("a receiver's bug")

    pair.b.subscribe(keys.key("r1", "state"), broken)
    pair.b.subscribe(keys.key("r1", "pose"), inbox)
    pair.ready()
    pair.a.publish(keys.key("r1", "state"), b"boom")
    pair.a.publish(keys.key("r1", "pose"), b"still here")
    if pair.kind == "inprocess":
        with pytest.raises(RuntimeError, match="a receiver's bug"):
            pair.pump()
        return
    pair.settle(
        lambda: inbox.snapshot() == [(keys.key("r1", "pose"), b"still here")], "the message after the failing one"
    )


# -- transport-specific -----------------------------------------------------------------------------


def test_zenoh_serve_and_query_and_the_alive_token() -> None:
    endpoint = loopback_endpoint()
    alive = keys.alive_key("r1")
    a = ZenohEndpoint(listen=[endpoint], alive_key=alive)
    b = ZenohEndpoint(connect=[endpoint])
    a.serve(keys.key("r1", "map"), lambda asked: [(keys.key("r1", "map"), b"snapshot for " + asked.encode())])
    try:
        a.start()
        b.start()
        wait_until(lambda: a.up and b.up, message="zenoh peers linked")
        wait_until(lambda: b.query(keys.key("r1", "map"), 0.5), message="an answer")
        assert b.query(keys.key("r1", "map"), 1.0) == [(keys.key("r1", "map"), b"snapshot for fleetlink/v1/r1/map")]
        assert b.query(keys.key("r2", "map"), 0.3) == []
        tokens = lambda: [str(r.ok.key_expr) for r in b.session.liveliness().get(keys.ZENOH_ALL_ALIVE)]  # noqa: E731
        wait_until(lambda: tokens() == [alive], message="the alive token")
        a.unserve(keys.key("r1", "map"))  # withdrawn: nobody answers any more
        wait_until(lambda: b.query(keys.key("r1", "map"), 0.3) == [], message="the queryable withdrawn")
        a.serve(keys.key("r1", "map"), lambda asked: [(keys.key("r1", "map"), b"again")])
        wait_until(lambda: b.query(keys.key("r1", "map"), 0.5), message="served again")
        assert b.query(keys.key("r1", "map"), 1.0) == [(keys.key("r1", "map"), b"again")]
    finally:
        b.close()
        a.close()
    assert b.query(keys.key("r1", "map"), 0.1) == []  # closed: nobody to ask


def test_inprocess_serve_query_and_unserve() -> None:
    bus = InProcessBus(LinkName.ZENOH)
    a, b = bus.endpoint("a"), bus.endpoint("b")
    a.start()
    b.start()
    key = keys.key("r1", "map")
    a.serve(key, lambda asked: [(key, b"for " + asked.encode())])
    a.serve(keys.key("r2", "map"), lambda asked: [(keys.key("r2", "map"), b"r2")])
    assert b.query(key) == [(key, b"for fleetlink/v1/r1/map")]
    assert b.query(keys.zenoh_all_robots("map")) == [(key, b"for fleetlink/v1/*/map"), (keys.key("r2", "map"), b"r2")]
    a.unserve(key)
    assert b.query(key) == [] and b.query(keys.key("r2", "map")) == [(keys.key("r2", "map"), b"r2")]
    a.close()
    assert b.query(keys.key("r2", "map")) == []  # down: nobody to ask


def test_mqtt_will_on_connect_hook_and_resubscribe_after_a_broker_restart(mosquitto: Any) -> None:
    from fleetlink.links.mqtt import MqttMessage

    settings = MqttSettings("127.0.0.1", mosquitto.port, keepalive_s=1, reconnect_min_s=0.1, reconnect_max_s=0.3)
    status = "fleetlink/v1/r1/connection"
    watcher, inbox, states = MqttEndpoint(settings, client_id="watcher"), Inbox(), Inbox()
    watcher.subscribe(keys.key("r1", "pose"), inbox)
    watcher.subscribe(status, states)
    robot = MqttEndpoint(
        settings,
        client_id="robot",
        will=MqttMessage(status, b"BROKEN", qos=1, retain=True),
        on_connect=lambda ep: ep.publish(status, b"ONLINE", qos=1, retain=True),
        on_close=lambda ep: ep.publish(status, b"OFFLINE", qos=1, retain=True),
    )
    try:
        watcher.start()
        robot.start()
        wait_until(lambda: (status, b"ONLINE") in states.snapshot(), message="ONLINE from the hook")
        assert nodelay_enabled(robot.client)
        robot.client.socket().close()  # vanish without a DISCONNECT: the broker sends the will
        wait_until(lambda: (status, b"BROKEN") in states.snapshot(), message="the last will")
        wait_until(lambda: states.snapshot()[-1] == (status, b"ONLINE"), message="ONLINE again after reconnecting")
        assert robot.connects >= 2
        mosquitto.kill()
        wait_until(lambda: not watcher.up and not robot.up, message="both see the broker gone")
        assert robot.publish(keys.key("r1", "pose"), b"lost") is False
        mosquitto.start()
        wait_until(lambda: watcher.up and robot.up, timeout=15, message="both back")
        wait_until(  # the watcher's subscriptions were made again on its new (clean) session
            lambda: (
                robot.publish(keys.key("r1", "pose"), b"again")
                and (keys.key("r1", "pose"), b"again") in inbox.snapshot()
            ),
            message="a pose after the restart",
        )
    finally:
        robot.close()
        wait_until(lambda: states.snapshot()[-1] == (status, b"OFFLINE"), message="OFFLINE on a clean close")
        watcher.close()


def test_mqtt_reads_a_burst_in_blocks_and_leaves_nothing_in_its_buffer(
    mosquitto: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The endpoint's client reads its socket ``READ_SIZE`` bytes at a time: a burst of packets
    costs a few ``recv`` calls, not three or four a packet, and every packet a ``recv`` brought is
    delivered although nothing more arrives after it (paho's own ``select`` knows nothing of them).
    Packets of every size: one byte, ones split across two reads, one larger than a read."""
    import paho.mqtt.client as paho

    from fleetlink.links.mqtt import READ_SIZE

    # No keepalive pings during the test: nothing but the burst makes the socket readable.
    settings = MqttSettings("127.0.0.1", mosquitto.port, keepalive_s=60, reconnect_min_s=0.1, reconnect_max_s=0.5)
    a, b, inbox = MqttEndpoint(settings, client_id="burst-a"), MqttEndpoint(settings, client_id="burst-b"), Inbox()
    b.subscribe("fleetlink/v1/burst/**", inbox)
    reads = [0]
    real = paho.Client._sock_recv

    def counted(self: Any, bufsize: int) -> bytes:
        if self is b.client:
            reads[0] += 1
        return real(self, bufsize)

    monkeypatch.setattr(paho.Client, "_sock_recv", counted)
    sizes = [1 + (i * 997) % 3000 for i in range(1500)] + [3 * READ_SIZE + 17] + [5] * 10
    sent = [(f"fleetlink/v1/burst/t{i % 7}", bytes([i % 256]) * n) for i, n in enumerate(sizes)]
    try:
        a.start()
        b.start()
        wait_until(lambda: a.up and b.up, message="both up")
        wait_until(  # the subscription is in place
            lambda: a.publish("fleetlink/v1/burst/probe", b"?") and bool(inbox.snapshot()), message="a probe"
        )
        reads[0] = 0
        for key, payload in sent:
            assert a.publish(key, payload)

        def burst() -> list[tuple[str, bytes]]:
            return [m for m in inbox.snapshot() if not m[0].endswith("/probe")]

        wait_until(lambda: len(burst()) >= len(sent), message="the whole burst")
        assert burst() == sent
        assert reads[0] < len(sent) / 4, reads[0]
    finally:
        a.close()
        b.close()


def test_per_key_quality_of_service() -> None:
    import zenoh

    mqtt = MqttEndpoint(MqttSettings("127.0.0.1", 1))
    commands = [keys.sender_key("r1", t, "op-a") for t in ("teleop", "lease/request", "marks")]
    telemetry_keys = [keys.key("r1", t) for t in ("ack", "pose", "map/updates")]
    assert [mqtt.qos_of(k) for k in commands + telemetry_keys] == [1, 1, 1, 1, 0, 0]
    assert mqtt.qos_of("dwm/node/0d7f/uplink/location") == 0
    z = ZenohEndpoint()
    urgent, telemetry = z._options(keys.sender_key("r1", "teleop", "op-a")), z._options(keys.key("r1", "pose"))
    assert urgent["express"] and urgent["congestion_control"] == zenoh.CongestionControl.BLOCK
    assert urgent["priority"] == zenoh.Priority.INTERACTIVE_HIGH
    assert telemetry["congestion_control"] == zenoh.CongestionControl.DROP and "express" not in telemetry
