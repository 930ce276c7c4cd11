"""The operator's two links (Zenoh primary, MQTT fallback) around the pure link manager.

``OperatorLink`` is the console's data source for the network: it subscribes to every fleetlink
key on both transports, decodes (bad input is counted and logged once per reason), feeds health
and acks into ``LinkManager``, hands good messages to a sink, and sends commands where the link
manager says, re-sending unacked ones on a switch. A poll thread (``poll_hz``) drives the
manager's clock-based decisions. The same bytes travel on both transports.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import math
import socket
import threading
from collections import Counter
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol
from urllib.parse import urlparse

from fleetlink.operator.linkmanager import FALLBACK, PRIMARY, Failed, LinkHealth, LinkManager, LinkPolicy, Send, Switch
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import Ack, MapSnapshot, Mark

if TYPE_CHECKING:
    from fleetlink.shared.mqtt import MqttSettings

log = logging.getLogger(__name__)

__all__ = [
    "ROBOT_TOPICS",
    "MqttTransport",
    "OperatorLink",
    "Transport",
    "ZenohTransport",
    "parse_mqtt_url",
]

# Topics only a robot's agent publishes: hearing one on a link proves the robot <-> operator path
# on that link works. (UWB fixes come from the gateway, marks from other consoles: they prove nothing.)
ROBOT_TOPICS = frozenset({"state", "pose", "ack", "events", "connection", "board", "lease", "map/updates"})

Receiver = Callable[[str, bytes], None]

UWB_STATUS = "fleetlink/uwb/+/status"
"""The UWB gateways' retained status (JSON, positioning/gateway.py), with their anchors."""
MARKS_QUERY = f"{keys.PREFIX}/*/marks"
"""Every console answers this with the marks it holds: a console that starts late asks it."""
AnchorSink = Callable[[str, list[tuple[str, float, float, float]]], None]


class Transport(Protocol):
    name: str

    def start(self, on_message: Receiver) -> None: ...

    def publish(self, key: str, payload: bytes) -> None: ...

    def close(self) -> None: ...


class ZenohTransport:
    """A Zenoh session subscribed to ``fleetlink/v1/**``."""

    name = PRIMARY

    def __init__(self, session: Any, *, owns_session: bool = False) -> None:
        self.session = session
        self._owns = owns_session
        self._sub: Any = None
        self._queryables: list[Any] = []
        self._lock = threading.Lock()
        self._closed = False

    @classmethod
    def open(cls, listen: Sequence[str] = (), connect: Sequence[str] = (), **auth: Any) -> ZenohTransport:
        """``auth``: ``peer_config``'s ``mode``, ``username``, ``password``, ``root_ca`` (a secured router)."""
        import zenoh

        from fleetlink.shared.zenoh_config import peer_config

        return cls(zenoh.open(peer_config(listen, connect, **auth)), owns_session=True)

    def start(self, on_message: Receiver) -> None:
        def callback(sample: Any) -> None:
            on_message(str(sample.key_expr), sample.payload.to_bytes())

        self._sub = self.session.declare_subscriber(keys.ZENOH_ALL, callback)

    def publish(self, key: str, payload: bytes) -> None:
        with self._lock:
            if not self._closed:
                self.session.put(key, payload)

    def query(self, key_expr: str, timeout: float) -> list[tuple[str, bytes]]:
        """Ask the queryables on ``key_expr``: their good replies as (key, payload)."""
        out: list[tuple[str, bytes]] = []
        for reply in self.session.get(key_expr, timeout=timeout):
            if reply.ok is not None:
                out.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
        return out

    def serve(self, key_expr: str, answer: Callable[[str], list[tuple[str, bytes]]]) -> None:
        """A queryable on ``key_expr``: ``answer(query key)`` gives the replies (key, payload)."""

        def on_query(query: Any) -> None:
            try:
                for key, payload in answer(str(query.key_expr)):
                    query.reply(key, payload)
            except Exception as exc:  # the querier went away, or a bad answer: keep serving
                log.debug("answering %s: %s", key_expr, exc)

        self._queryables.append(self.session.declare_queryable(key_expr, on_query))

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for q in self._queryables:
            with contextlib.suppress(Exception):
                q.undeclare()
        if self._sub is not None:
            self._sub.undeclare()
        if self._owns:
            self.session.close()


def parse_mqtt_url(url: str) -> tuple[str, int]:
    """``mqtt://host:port`` (or ``host:port``) -> (host, port); ValueError with the reason."""
    parsed = urlparse(url if "://" in url else f"mqtt://{url}")
    if parsed.scheme not in ("mqtt", "tcp"):
        raise ValueError(f"MQTT url {url!r}: scheme must be mqtt:// (got {parsed.scheme!r})")
    if not parsed.hostname:
        raise ValueError(f"MQTT url {url!r}: no host")
    try:
        port = parsed.port or 1883
    except ValueError as exc:
        raise ValueError(f"MQTT url {url!r}: {exc}") from None
    return parsed.hostname, port


class MqttTransport:
    """A paho client subscribed to ``fleetlink/v1/#`` (QoS 1, TCP_NODELAY, reconnecting)."""

    name = FALLBACK

    def __init__(self, url: str, client_id: str, *, settings: MqttSettings | None = None) -> None:
        """``settings`` (credentials, TLS: a secured broker) win over ``url``."""
        import paho.mqtt.client as mqtt

        if settings is not None:
            from fleetlink.shared.mqtt import connect_client

            self.host, self.port = settings.host, settings.port
            self.client = connect_client(settings, client_id=client_id, start=False)
        else:
            self.host, self.port = parse_mqtt_url(url)
            self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id)
        self.client.reconnect_delay_set(min_delay=1, max_delay=4)
        self.connected = threading.Event()
        self._on_message: Receiver | None = None

        def on_socket_open(client: Any, userdata: Any, sock: Any) -> None:
            # Nagle against delayed ACK costs ~40 ms per QoS 1 message (GUIDE section 7).
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

        def on_connect(client: Any, userdata: Any, flags: Any, reason: Any, props: Any) -> None:
            if not reason.is_failure:
                client.subscribe([(keys.MQTT_ALL, 1), (UWB_STATUS, 1)])
                self.connected.set()

        def on_disconnect(client: Any, userdata: Any, flags: Any, reason: Any, props: Any) -> None:
            self.connected.clear()

        def on_message(client: Any, userdata: Any, message: Any) -> None:
            if self._on_message is not None:
                self._on_message(message.topic, bytes(message.payload))

        self.client.on_socket_open = on_socket_open
        self.client.on_connect = on_connect
        self.client.on_disconnect = on_disconnect
        self.client.on_message = on_message

    def start(self, on_message: Receiver) -> None:
        self._on_message = on_message
        self.client.connect_async(self.host, self.port, keepalive=5)
        self.client.loop_start()

    def publish(self, key: str, payload: bytes) -> None:
        self.client.publish(key, payload, qos=1)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


Sink = Callable[[wire.Message, str, float], None]
Listener = Callable[[Switch | Failed], None]


class OperatorLink:
    """Commands out over the healthy link, messages in from both. Thread-safe."""

    def __init__(
        self,
        clock: Clock,
        sender: str,
        primary: Transport,
        fallback: Transport,
        *,
        policy: LinkPolicy | None = None,
        poll_hz: float = 50.0,
    ) -> None:
        self.clock = clock
        self.sender = keys.check_id(sender, "sender id")
        self.transports = {PRIMARY: primary, FALLBACK: fallback}
        self.manager = LinkManager(policy)
        self.counter = wire.HeaderCounter(clock, robot="operator", sender=sender)
        self.rejected: Counter[str] = Counter()
        self._seen_reasons: set[str] = set()
        self._lock = threading.Lock()
        self._sinks: list[Sink] = []
        self._anchor_sinks: list[AnchorSink] = []
        self._listeners: list[Listener] = []
        self._poll_interval = 1.0 / poll_hz
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.delivered: Counter[str] = Counter()
        """Messages accepted per link (for the console's status line and tests)."""

    # -- wiring ---------------------------------------------------------------------------------

    def add_sink(self, sink: Sink) -> None:
        self._sinks.append(sink)

    def add_listener(self, listener: Listener) -> None:
        self._listeners.append(listener)

    def add_anchor_sink(self, sink: AnchorSink) -> None:
        """``sink(gateway, [(id, x, y, z), ...])`` for each UWB gateway status heard."""
        self._anchor_sinks.append(sink)

    def start(self) -> OperatorLink:
        for name, transport in self.transports.items():
            transport.start(functools.partial(self._receive, name))
        self._thread = threading.Thread(target=self._poll_loop, name="operator-link-poll", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        for transport in self.transports.values():
            try:
                transport.close()
            except Exception as exc:  # closing must go on for the other transport
                log.warning("closing %s: %s", transport.name, exc)

    def __enter__(self) -> OperatorLink:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- inbound --------------------------------------------------------------------------------

    def _reject(self, link: str, key: str, reason: str) -> None:
        with self._lock:
            self.rejected[reason] += 1
            first = reason not in self._seen_reasons
            self._seen_reasons.add(reason)
        if first:  # once per reason, or a flood of garbage floods the log
            log.warning("rejected a message on %s (%s): %s", link, key[:120], reason)

    def _gateway_status(self, link: str, key: str, payload: bytes) -> None:
        try:
            doc = json.loads(payload)
            gateway = str(doc["gateway"])
            anchors = [(str(a[0]), float(a[1]), float(a[2]), float(a[3])) for a in doc.get("anchors", [])]
            if not all(math.isfinite(v) for a in anchors for v in a[1:]):
                raise ValueError("an anchor coordinate is not finite")
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            self._reject(link, key, f"bad UWB gateway status: {exc}")
            return
        for sink in self._anchor_sinks:
            sink(gateway, anchors)

    def _receive(self, link: str, key: str, payload: bytes) -> None:
        if key.startswith("fleetlink/uwb/"):
            self._gateway_status(link, key, payload)
            return
        try:
            msg = wire.decode_key(key, payload)
        except wire.WireError as exc:
            self._reject(link, key, exc.reason if hasattr(exc, "reason") else str(exc))
            return
        if msg.header.sender == self.sender:
            return  # our own command, echoed by the broker or the local Zenoh session
        now = self.clock.now()
        topic = type(msg).TOPIC
        robot = msg.header.robot
        if topic in ROBOT_TOPICS:
            with self._lock:
                self.manager.heard(robot, link, now)
                if isinstance(msg, Ack) and msg.commandSender == self.sender:
                    self.manager.acked(robot, link, msg.commandTopic, msg.commandHeaderId, now)
        with self._lock:
            self.delivered[link] += 1
        for sink in self._sinks:
            sink(msg, link, now)

    # -- outbound -------------------------------------------------------------------------------

    def send(self, cls: type[wire.Message], robot: str, *, expect_ack: bool = True, **fields: Any) -> wire.Message:
        """Build, encode and send a command to ``robot`` over its active link. Returns the message."""
        msg = cls(header=self.counter.header(cls.TOPIC, robot=robot), **fields)
        payload = wire.encode(msg)
        now = self.clock.now()
        with self._lock:
            sends, failed = self.manager.command(
                robot, cls.TOPIC, msg.header.headerId, payload, now, expect_ack=expect_ack
            )
        self._dispatch([*sends, *failed])
        return msg

    def publish(self, msg: wire.Message, *, links: Sequence[str] = (PRIMARY,)) -> None:
        """Publish a non-command message (marks, lease requests) as is, on the given links."""
        payload = wire.encode(msg)
        k = keys.key(msg.header.robot, type(msg).TOPIC)
        for link in links:
            self._put(link, k, payload)

    def _put(self, link: str, key: str, payload: bytes) -> None:
        try:
            self.transports[link].publish(key, payload)
        except Exception as exc:  # a dead transport must not take the console down; health shows it
            log.debug("publish on %s failed: %s", link, exc)

    def _dispatch(self, actions: Sequence[Send | Switch | Failed]) -> None:
        for action in actions:
            if isinstance(action, Send):
                self._put(action.link, keys.key(action.robot, action.topic), action.payload)
                continue
            if isinstance(action, Switch):
                log.warning("link switch: %s", action.describe())
            else:
                log.warning("%s: %s #%d failed: %s", action.robot, action.topic, action.header_id, action.reason)
            for listener in self._listeners:
                listener(action)

    def poll(self) -> None:
        with self._lock:
            actions = self.manager.poll(self.clock.now())
        self._dispatch(actions)

    def _poll_loop(self) -> None:
        while not self._stop.wait(self._poll_interval):
            try:
                self.poll()
            except Exception:  # keep serving: one bad poll must not stop failover for good
                log.exception("link poll failed")

    # -- queries (Zenoh) ------------------------------------------------------------------------

    def fetch_map(self, robot: str, timeout: float = 3.0) -> MapSnapshot | None:
        """Ask the robot's map queryable (``fleetlink/v1/<robot>/map``); None if no good answer."""
        primary = self.transports[PRIMARY]
        if not isinstance(primary, ZenohTransport):
            return None
        for key, payload in primary.query(keys.key(robot, MapSnapshot.TOPIC), timeout):
            try:
                msg = wire.decode_key(key, payload)
            except wire.WireError as exc:
                self._reject(PRIMARY, key, exc.reason)
                continue
            if isinstance(msg, MapSnapshot):
                return msg
        return None

    def serve_marks(self, marks: Callable[[], Sequence[Mark]]) -> None:
        """Answer ``fleetlink/v1/*/marks`` queries with ``marks()`` (each under its robot's key)."""
        primary = self.transports[PRIMARY]
        if isinstance(primary, ZenohTransport):
            primary.serve(
                MARKS_QUERY, lambda _key: [(keys.key(m.header.robot, Mark.TOPIC), wire.encode(m)) for m in marks()]
            )

    def fetch_marks(self, timeout: float = 2.0) -> int:
        """Ask every other console for its marks; they go to the sinks like published ones."""
        primary = self.transports[PRIMARY]
        if not isinstance(primary, ZenohTransport):
            return 0
        replies = primary.query(MARKS_QUERY, timeout)
        for key, payload in replies:
            self._receive(PRIMARY, key, payload)
        return len(replies)

    # -- views ----------------------------------------------------------------------------------

    def active(self, robot: str) -> str:
        with self._lock:
            return self.manager.active(robot)

    def health(self, robot: str) -> tuple[LinkHealth, ...]:
        with self._lock:
            return self.manager.health(robot, self.clock.now())

    def pending(self, robot: str) -> int:
        with self._lock:
            return self.manager.pending(robot)
