"""The MQTT endpoint, and the one place a paho client is made.

``connect_client(settings, ...)`` is every fleetlink paho client: MQTT 3.1.1, callback API v2,
credentials, TLS, TCP_NODELAY on every socket it opens (QoS 1 with Nagle against delayed ACKs
costs ~40 ms per message, GUIDE.md), the last will, and a jittered reconnect backoff.

``MqttEndpoint`` is a ``fleetlink.links.base.Link`` over one such client:

* subscriptions take Zenoh-style key expressions (translated with ``to_mqtt_filter``), are made
  again after every reconnect (the session is clean), and hand (topic, payload) to their receiver;
* ``publish(key, payload, qos=None, retain=False)``: QoS 1 for the keys whose topic is in
  ``QOS1_TOPICS`` (commands, acks, the lease, the connection, marks), QoS 0 for telemetry, unless
  asked otherwise; False (counted as dropped) while disconnected; ``publish_retained`` (the
  consoles' mark sets) and ``add_connect_hook`` make it a ``links.base.RetainLink``;
* a last will (``MqttMessage``), an ``on_connect(endpoint)`` hook run after every (re)connect
  (the agent re-publishes its retained ``Connection``, the UWB gateway its ``online`` status) and
  an ``on_close(endpoint)`` hook run while still connected on a clean close (their ``OFFLINE``).

The network loop is the endpoint's own ``Worker`` rather than paho's ``loop_start``, so that
reconnects use jittered exponential backoff (a fleet whose broker restarts must not reconnect in
lockstep). Every socket operation happens on that thread: a publish from any other thread only
queues its packet and wakes the loop through paho's socket pair, which writes it at once. (Paho
writes directly from the publishing thread when it runs no loop of its own and no socket callback
is registered: over TLS that let two threads use one SSL connection at the same time, and the
broker dropped it with "decryption failed or bad record mac" several times a minute; once the
process died in glibc's ``free()``. tests/faults/test_tls_drill.py.) Receivers run on the loop
thread, in the order the broker delivered.

With overlapping subscriptions a broker may deliver a message once per matching filter (Mosquitto
2 does): each delivery goes to every matching receiver. Fleetlink's subscriptions do not overlap.
"""

from __future__ import annotations

import contextlib
import logging
import random
import socket
import ssl
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Self

from fleetlink.links.base import LinkStats, Receiver, key_matches, to_mqtt_filter
from fleetlink.shared import keys
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.messages import LinkName
from fleetlink.shared.mqtt import MqttSettings
from fleetlink.shared.worker import Worker

if TYPE_CHECKING:
    import paho.mqtt.client as mqtt

__all__ = ["QOS1_TOPICS", "MqttEndpoint", "MqttMessage", "connect_client", "nodelay_enabled"]

log = logging.getLogger(__name__)

MAX_ROUTES = 1024
"""Topics whose receivers an endpoint remembers."""

QOS1_TOPICS = frozenset(
    {
        "order",
        "actions",
        "teleop",
        "connection",
        "ack",
        "lease",
        "lease/request",
        "marks",
        "marks/set",
        "alarms/ack",
        "zones",
    }
)
"""Published at QoS 1; every other topic at QoS 0 (a late pose is worthless, a lost command is not)."""

LOOP_TIMEOUT_S = 0.25
"""The loop's idle wake-up: inbound bytes and every publish (paho pokes its socket pair) wake it
at once, so this only paces keepalives when nothing else happens."""

MAX_QUEUED = 256
"""QoS 1 messages paho keeps while disconnected; QoS 0 ones are not sent at all then."""

READ_SIZE = 64 * 1024
"""Bytes a buffered client (``connect_client(buffered=True)``) asks its socket for at a time."""

MAX_BUFFERED_PACKETS = 1024
"""Packets the endpoint's loop takes from the client's buffer before it lets paho write and ping."""

_BUFFERED: Any = None


def _buffered_client_class() -> Any:
    """paho's ``Client``, reading its socket ``READ_SIZE`` bytes at a time, and taking the QoS 0
    publications in what it read without paho's own handling.

    paho reads every packet with three or four ``recv`` calls (its command byte, each byte of its
    length, its body), and turns a publication into an ``MQTTMessage`` (with a ``Condition`` of its
    own), logs it and looks it up in its callback filters: ~30 us of Python a message, which a
    recorder or a console of 50 robots pays a few hundred times a second. This client keeps what
    one ``recv`` brought and hands it out as paho asks for it, so a burst costs one ``recv``; and
    when ``_fl_publish(topic, payload)`` is set (``MqttEndpoint``) every whole QoS 0 PUBLISH of MQTT
    3.1.1 in the buffer goes straight to it, parsed here. Everything else (QoS 1, a packet not yet
    all read, a topic that is not UTF-8, MQTT 5, any other packet) is paho's, read from the same
    buffer. paho's loop does not know about buffered bytes (its ``select`` waits on the socket), so
    whoever runs the loop must take them after each ``loop()`` (``buffered_bytes`` says how many:
    ``MqttEndpoint._run``). The buffer is dropped with the connection (``reconnect``)."""
    global _BUFFERED
    if _BUFFERED is None:
        import paho.mqtt.client as mqtt

        # paho's private read path, as 2.0-2.1 have it. A paho without it gets paho's own reads (the
        # endpoint asks ``buffered_bytes`` and sets ``_fl_publish`` either way), not a broken link.
        private = ("_packet_read", "_sock_recv", "_msgtime_mutex", "_last_bytes_received", "_in_packet")
        known = set(dir(mqtt.Client)) | set(mqtt.Client.__init__.__code__.co_names)  # methods, attributes set
        if not (all(a in known for a in private) and hasattr(mqtt, "time_func")):
            log.warning("this paho-mqtt reads differently: the MQTT endpoint uses paho's own reads")

            class PlainClient(mqtt.Client):
                _fl_publish: Callable[[str, bytes], None] | None = None

                def buffered_bytes(self) -> int:
                    return 0

            _BUFFERED = PlainClient
            return _BUFFERED

        fallback = mqtt.Client._packet_read
        raw_recv = mqtt.Client._sock_recv
        ok, again, lost = mqtt.MQTT_ERR_SUCCESS, mqtt.MQTT_ERR_AGAIN, mqtt.MQTT_ERR_CONN_LOST
        now = mqtt.time_func

        class BufferedClient(mqtt.Client):
            _fl_buf = b""
            _fl_pos = 0
            _fl_publish: Callable[[str, bytes], None] | None = None

            def _packet_read(self) -> Any:
                deliver = self._fl_publish
                if deliver is None or self._in_packet["command"] != 0 or self._protocol == mqtt.MQTTv5:
                    return fallback(self)
                buf, pos = self._fl_buf, self._fl_pos
                if pos >= len(buf):
                    try:
                        buf, pos = raw_recv(self, READ_SIZE), 0
                    except BlockingIOError:
                        return again
                    except OSError:  # paho's own read meets it again, and logs it
                        return fallback(self)
                    if not buf:
                        return lost
                    self._fl_buf, self._fl_pos = buf, 0
                n = len(buf)
                if buf[pos] & 0xF6 != 0x30:  # not a PUBLISH at QoS 0 (dup and retain flags aside)
                    return fallback(self)
                i, length, shift = pos + 1, 0, 0
                while True:  # the remaining length: 1-4 bytes, 7 bits each
                    if i >= n or shift > 21:
                        return fallback(self)
                    byte = buf[i]
                    i += 1
                    length |= (byte & 127) << shift
                    shift += 7
                    if not byte & 128:
                        break
                end = i + length
                if end > n or length < 2:
                    return fallback(self)
                start = i + 2 + ((buf[i] << 8) | buf[i + 1])
                if start > end:
                    return fallback(self)
                try:
                    topic = buf[i + 2 : start].decode("utf-8")
                except UnicodeDecodeError:
                    return fallback(self)
                self._fl_pos = end
                with self._msgtime_mutex:
                    self._last_bytes_received = now()
                deliver(topic, buf[start:end])
                return ok

            def _sock_recv(self, bufsize: int) -> bytes:
                buf, pos = self._fl_buf, self._fl_pos
                if pos >= len(buf):
                    buf = super()._sock_recv(READ_SIZE)  # BlockingIOError when nothing is there
                    if not buf:
                        return buf  # the broker closed the connection
                    pos = 0
                out = buf[pos : pos + bufsize]
                self._fl_buf, self._fl_pos = buf, pos + len(out)
                return out

            def buffered_bytes(self) -> int:
                return len(self._fl_buf) - self._fl_pos

            def reconnect(self) -> Any:
                self._fl_buf, self._fl_pos = b"", 0  # a new connection: the old one's bytes are not its
                return super().reconnect()

        _BUFFERED = BufferedClient
    return _BUFFERED


@dataclass(frozen=True, slots=True)
class MqttMessage:
    """One MQTT publication: a last will, a gateway's fix, a retained status."""

    topic: str
    payload: bytes
    qos: int = 0
    retain: bool = False


def _set_nodelay(sock: Any) -> None:
    # TLS sockets forward setsockopt to the TCP socket underneath.
    with contextlib.suppress(OSError, AttributeError):  # not a TCP socket: nothing to do
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


def nodelay_enabled(client: mqtt.Client) -> bool:
    """True if the client's current socket has TCP_NODELAY on (False when not connected)."""
    sock: Any = client.socket()
    if sock is None:
        return False
    try:
        return bool(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))
    except (OSError, AttributeError):
        return False


def connect_client(
    settings: MqttSettings,
    *,
    client_id: str | None = None,
    will: MqttMessage | None = None,
    clean_session: bool = True,
    start: bool = True,
    rng: random.Random | None = None,
    buffered: bool = False,
) -> mqtt.Client:
    """A paho 2.x client (MQTT 3.1.1, callback API v2) set up from ``settings``.

    Sets the username/password, TLS (site CA or the system's, optional client certificate),
    TCP_NODELAY on every socket it opens (``on_socket_open``, so reconnects get it too), the last
    will, and a reconnect backoff from ``reconnect_min_s`` doubling to ``reconnect_max_s`` whose
    bounds are jittered per client (x1-2 and x0.5-1) so a fleet does not reconnect in lockstep
    after a broker restart. ``settings.client_id`` wins over ``client_id``.

    With ``start`` (the default) it calls ``connect_async`` and ``loop_start``: the client keeps
    trying in the background until it connects and reconnects after every loss. Set the
    ``on_connect``/``on_message`` callbacks first or pass ``start=False`` and start it yourself.
    Stop it with ``client.disconnect(); client.loop_stop()``. ``MqttEndpoint`` is the usual way in.

    ``buffered``: the client reads its socket in blocks (``_buffered_client_class``), for a caller
    that runs the loop itself and takes what is buffered after each ``loop()``; not with ``start``.
    """
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    if buffered and start:
        raise ValueError("a buffered client needs a loop that takes its buffer: start=False")
    rng = rng if rng is not None else random.Random()
    cid = settings.client_id or client_id or ""
    client = (_buffered_client_class() if buffered else mqtt.Client)(
        CallbackAPIVersion.VERSION2,
        client_id=cid,
        clean_session=clean_session,
        protocol=mqtt.MQTTv311,
    )
    if settings.username is not None:
        client.username_pw_set(settings.username, settings.password)
    if settings.tls:
        client.tls_set(
            ca_certs=settings.ca_file,
            certfile=settings.cert_file,
            keyfile=settings.key_file,
            cert_reqs=ssl.CERT_REQUIRED,
            tls_version=ssl.PROTOCOL_TLS_CLIENT,
        )
    if will is not None:
        client.will_set(will.topic, will.payload, qos=will.qos, retain=will.retain)
    client.on_socket_open = lambda _client, _userdata, sock: _set_nodelay(sock)
    lo = settings.reconnect_min_s * rng.uniform(1.0, 2.0)
    hi = max(lo, settings.reconnect_max_s * rng.uniform(0.5, 1.0))
    # paho's signature says int; it only ever multiplies and compares them.
    client.reconnect_delay_set(lo, hi)  # type: ignore[arg-type]
    if start:
        client.connect_async(settings.host, settings.port, keepalive=settings.keepalive_s)
        client.loop_start()
    return client


Hook = Callable[["MqttEndpoint"], object]


@dataclass(slots=True)
class _Subscription:
    key_expr: str
    filter: str
    qos: int
    receiver: Receiver


def _write_wanted(client: Any, userdata: Any, sock: Any) -> None:
    """Paho's write-interest callback: nothing to do, the loop thread writes (see ``MqttEndpoint``)."""


class MqttEndpoint:
    """A ``Link`` on one broker connection. See the module docstring."""

    name = LinkName.MQTT
    PUBLISH_QUEUES = True
    """``publish`` only queues the packet for the loop thread (never waits on the network):
    no send thread of its own is needed (links/sender.py)."""

    def __init__(
        self,
        settings: MqttSettings,
        *,
        client_id: str | None = None,
        will: MqttMessage | None = None,
        on_connect: Hook | None = None,
        on_close: Hook | None = None,
        qos1_topics: frozenset[str] = QOS1_TOPICS,
        clock: Clock | None = None,
        seed: int | None = None,
        label: str = "mqtt",
    ) -> None:
        self.settings = settings
        self.client_id = settings.client_id or client_id or ""
        self.will = will
        self.on_connect = on_connect
        self.on_close = on_close
        self.qos1_topics = qos1_topics
        self.clock: Clock = clock or SystemClock()
        self.label = label
        self.stats = LinkStats()
        self.connects = 0
        """Successful connections so far (reconnects included)."""
        self.refused = 0
        """CONNACKs that refused us (credentials, ACL)."""
        self._rng = random.Random(seed)
        self._subs: list[_Subscription] = []
        self._routes: dict[str, list[Receiver]] = {}
        """topic -> its receivers: matching every subscription costs a few microseconds apiece per
        message, which a flood multiplies. Bounded (cleared when full: topics may be anyone's)."""
        self._lock = threading.Lock()
        self._client: Any = None
        self._connected = False
        self._closing = False
        self._loop: Worker | None = None
        self._connect_hooks: list[Callable[[], object]] = []

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        with self._lock:
            if self._client is not None:
                return
            c: Any = connect_client(
                self.settings, client_id=self.client_id, will=self.will, start=False, rng=self._rng, buffered=True
            )
            c.max_queued_messages_set(MAX_QUEUED)
            c.on_connect = self._on_connect
            c.on_disconnect = self._on_disconnect
            c.on_message = self._on_message
            c._fl_publish = self._deliver  # QoS 0 publications straight from the read buffer
            # Registering for write interest makes paho queue every packet for the loop thread
            # instead of writing from the caller's (see the module docstring); the loop's select
            # already watches the socket whenever something is queued.
            c.on_socket_register_write = _write_wanted
            self._client = c
            self._closing = False
            self._loop = Worker(f"{self.label}-loop", target=self._run).start()

    def close(self) -> None:
        """Run ``on_close`` if connected, disconnect cleanly (no last will), end the loop (idempotent)."""
        if self._client is None:
            return
        if self._connected and self.on_close is not None:
            try:
                self.on_close(self)  # its publishes are queued; the loop writes them before it ends
            except Exception:  # best effort on the way out
                log.exception("%s: on_close failed", self.label)
        with self._lock:
            c, self._client = self._client, None
            loop, self._loop = self._loop, None
        if c is None:
            return
        self._closing = True  # the loop must not take the DISCONNECT for a loss and reconnect
        with contextlib.suppress(Exception):
            c.disconnect()  # queued, waking the loop out of its select
        if loop is not None:
            loop.stop()
        with contextlib.suppress(Exception):
            c.loop_write()  # the loop has ended: what it had not written yet, DISCONNECT last
        self._connected = False

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def up(self) -> bool:
        return self._connected

    @property
    def client(self) -> Any:
        """The paho client (None before ``start`` and after ``close``)."""
        return self._client

    # -- data -----------------------------------------------------------------------------------

    def qos_of(self, key: str) -> int:
        return 1 if keys.topic_of(key) in self.qos1_topics else 0

    def publish(self, key: str, payload: bytes, *, qos: int | None = None, retain: bool = False) -> bool:
        c = self._client
        if c is None or not self._connected:
            self.stats.dropped += 1
            return False
        try:
            info = c.publish(key, payload, qos=self.qos_of(key) if qos is None else qos, retain=retain)
        except Exception as exc:
            self.stats.dropped += 1
            log.warning("%s: publish on %s failed: %s", self.label, key, exc)
            return False
        if info.rc != 0:
            self.stats.dropped += 1
            return False
        self.stats.sent += 1
        return True

    def send(self, message: MqttMessage) -> bool:
        """Publish ``message`` with its own QoS and retain flag."""
        return self.publish(message.topic, message.payload, qos=message.qos, retain=message.retain)

    def publish_retained(self, key: str, payload: bytes) -> bool:
        """Publish at the key's QoS, retained: the broker hands it to every later subscriber."""
        return self.publish(key, payload, retain=True)

    def add_connect_hook(self, hook: Callable[[], object]) -> None:
        """Call ``hook()`` after every (re)connect, after ``on_connect`` (on the loop thread)."""
        with self._lock:
            self._connect_hooks.append(hook)

    def prioritise(self, priority_keys: frozenset[str], *, then_topics: frozenset[str] = frozenset()) -> None:
        """Nothing waits here: the loop thread hands each message on as it reads it."""

    def subscribe(self, key_expr: str, receiver: Receiver, *, qos: int = 1) -> None:
        """``qos`` is the most the broker may deliver at; each message keeps its publisher's QoS
        up to that, so the default (1) downgrades nothing."""
        sub = _Subscription(key_expr, to_mqtt_filter(key_expr), qos, receiver)
        with self._lock:
            self._subs.append(sub)
            self._routes = {}
            c = self._client if self._connected else None
        if c is not None:
            c.subscribe(sub.filter, sub.qos)

    # -- the loop (a Worker) --------------------------------------------------------------------

    def _run(self, worker: Worker) -> None:
        import paho.mqtt.client as mqtt

        c = self._client
        s = self.settings
        backoff = s.reconnect_min_s
        first = True
        need_connect = True
        while not worker.stopping and not self._closing:
            if need_connect:
                try:
                    if first:
                        c.connect(s.host, s.port, keepalive=s.keepalive_s)
                        first = False
                    else:
                        c.reconnect()
                    backoff = s.reconnect_min_s
                    need_connect = False
                except (OSError, ssl.SSLError) as exc:
                    delay = backoff * (0.5 + self._rng.random())  # jitter: 0.5x-1.5x
                    backoff = min(s.reconnect_max_s, backoff * 2)
                    if self.connects == 0 or backoff >= s.reconnect_max_s:
                        log.info(
                            "%s: %s:%d unreachable (%s); retrying in %.2f s", self.label, s.host, s.port, exc, delay
                        )
                    worker.wait(delay)
                    continue
            rc = c.loop(timeout=LOOP_TIMEOUT_S)
            taken = 0  # the packets one recv brought with the one paho read (see READ_SIZE)
            while rc == mqtt.MQTT_ERR_SUCCESS and c.buffered_bytes() and taken < MAX_BUFFERED_PACKETS:
                rc = c.loop_read()
                taken += 1
            if rc != mqtt.MQTT_ERR_SUCCESS and not worker.stopping and not self._closing:
                self._connected = False
                need_connect = True
                delay = backoff * (0.5 + self._rng.random())
                backoff = min(s.reconnect_max_s, backoff * 2)
                worker.wait(delay)

    # -- paho callbacks (on the loop thread) ----------------------------------------------------

    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason_code: Any, properties: Any) -> None:
        if reason_code.is_failure:
            self.refused += 1
            if self.refused == 1:
                log.warning("%s: %s refused the connection: %s", self.label, self.settings.url, reason_code)
            return
        with self._lock:
            subs = list(self._subs)
            self._connected = True
            self.connects += 1
        filters: dict[str, int] = {}
        for sub in subs:  # one SUBSCRIBE per distinct filter, at the highest QoS asked
            filters[sub.filter] = max(sub.qos, filters.get(sub.filter, 0))
        if filters:
            client.subscribe(list(filters.items()))
        if self.on_connect is not None:
            try:
                self.on_connect(self)
            except Exception:
                log.exception("%s: on_connect failed", self.label)
        with self._lock:
            hooks = list(self._connect_hooks)
        for hook in hooks:
            try:
                hook()
            except Exception:
                log.exception("%s: a connect hook failed", self.label)
        log.info("%s: up (%s, connect #%d)", self.label, self.settings.url, self.connects)

    def _on_disconnect(self, client: Any, userdata: Any, flags: Any, reason_code: Any, properties: Any) -> None:
        if self._connected and not self._closing:
            log.warning("%s: down (%s); reconnecting", self.label, reason_code)
        self._connected = False

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        self._deliver(msg.topic, bytes(msg.payload))

    def _deliver(self, topic: str, payload: bytes) -> None:
        if not self.stats.admit(self.label, topic, len(payload)):  # the broker should have refused it
            return
        routes = self._routes
        receivers = routes.get(topic)
        if receivers is None:
            receivers = [sub.receiver for sub in self._subs if key_matches(sub.key_expr, topic)]
            if len(routes) >= MAX_ROUTES:
                routes.clear()
            routes[topic] = receivers
        for receiver in receivers:
            try:
                receiver(topic, payload)
            except Exception:  # a receiver's bug must not kill the loop thread
                log.exception("%s: receiver for %s failed", self.label, topic)
        if receivers:
            self.stats.received += 1
            self.stats.last_rx = self.clock.now()
