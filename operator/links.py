"""The operator's two links (Zenoh primary, MQTT fallback) around the pure link manager.

With ``LinkPolicy(redundant=True)`` (the consoles' default, ``[links] redundant``) every command
goes out on both links at once, same bytes; else over the robot's active link, failing over.

``OperatorLink`` is the console's data source for the network: it subscribes to every fleetlink
key on both links (``fleetlink.links`` endpoints, keyed by ``LinkName``), decodes (bad input is
counted and logged once per reason), feeds health and acks into ``LinkManager``, hands good
messages to a sink, and sends commands where the link manager says, re-sending unacked ones on a
switch. A poll worker (``poll_hz``) drives the manager's clock-based decisions. The same bytes
travel on both links; map and marks queries go over the primary when it can answer queries, and
retained messages (the consoles' mark sets) over the links whose broker keeps them (MQTT).

Each link's copy leaves on its own path: a link whose ``publish`` may wait on the network (Zenoh,
whose commands are put with congestion control BLOCK) gets a send thread of its own
(``links.sender.LinkSender``: a bounded queue, the oldest dropped and counted when full), and a
link whose ``publish`` only queues (MQTT: paho's loop thread writes) is published to inline. So a
stalled Zenoh holds up neither the MQTT copy nor the caller (the console's key handling).
"""

from __future__ import annotations

import json
import logging
import math
import threading
from collections import Counter, deque
from collections.abc import Callable, Sequence
from typing import Any, TypeVar
from urllib.parse import urlparse

from fleetlink.links.base import Link, RetainLink
from fleetlink.links.sender import LinkSender, needs_sender
from fleetlink.operator.linkmanager import FALLBACK, PRIMARY, Failed, LinkHealth, LinkManager, LinkPolicy, Send, Switch
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import Ack, AlarmAck, DoseSnapshot, LinkName, MapSnapshot, Mark, MarkSet
from fleetlink.shared.mqtt import MqttSettings
from fleetlink.shared.worker import Worker

_S = TypeVar("_S", bound=wire.Message)

log = logging.getLogger(__name__)

__all__ = ["ROBOT_TOPICS", "OperatorLink", "mqtt_settings_for", "parse_mqtt_url"]

# Topics only a robot's agent publishes: hearing one on a link proves the robot <-> operator path
# on that link works. (UWB fixes come from the gateway, marks from other consoles: they prove nothing.)
ROBOT_TOPICS = frozenset(
    {"state", "pose", "ack", "events", "connection", "board", "lease", "map/updates", "dose/updates", "scan"}
)

UWB_STATUS = "fleetlink/uwb/*/status"
"""The UWB gateways' retained status (JSON, positioning/gateway.py), with their anchors."""
MARKS_QUERY = keys.sender_filter("*", Mark.TOPIC)
"""``fleetlink/v1/*/marks/*``: every console answers it with the marks it made (under its own
name, as it published them); a console that starts late asks it."""
AnchorSink = Callable[[str, list[tuple[str, float, float, float]]], None]
ALIVE_TOKENS = keys.ZENOH_ALL_ALIVE
"""``fleetlink/alive/v1/*``: the agents' liveliness tokens (agent/links/zenoh_link.py), watched on
every link that can (``watch_liveliness``: Zenoh, in-process)."""
PresenceSink = Callable[[str, str, bool, float], None]
"""``sink(robot, link, alive, wall time)``: a robot's token appeared (True) or went (False)."""

CONSOLE_RECONNECT_MAX_S = 4.0
"""A console's broker reconnect backoff ceiling (an operator waits; a fleet's agents spread out)."""


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


def mqtt_settings_for(url: str) -> MqttSettings:
    """Settings for a plain (no login, no TLS) broker at ``url``, as ``parse_mqtt_url`` reads it."""
    host, port = parse_mqtt_url(url)
    return MqttSettings(host=host, port=port, reconnect_max_s=CONSOLE_RECONNECT_MAX_S)


Sink = Callable[[wire.Message, str, float], None]
Listener = Callable[[Switch | Failed], None]


MAX_EARLY = 4096
"""Messages kept for the first sink while none is added (the oldest dropped beyond)."""

SENDER_STOP_S = 2.0
"""On close, how long each link's send thread may take to hand on what was queued (the stop-all
sent on quit) before the link is closed under it."""

MAX_REJECT_REASONS = 256
"""Distinct rejection reasons counted (and logged once) apiece; the rest count as ``OTHER_REASONS``."""
OTHER_REASONS = "(other reasons)"


class OperatorLink:
    """Commands out over the healthy link, messages in from both. Thread-safe."""

    def __init__(
        self,
        clock: Clock,
        sender: str,
        primary: Link,
        fallback: Link,
        *,
        policy: LinkPolicy | None = None,
        poll_hz: float = 50.0,
    ) -> None:
        self.clock = clock
        self.sender = keys.check_id(sender, "sender id")
        if primary.name is not LinkName(PRIMARY) or fallback.name is not LinkName(FALLBACK):
            raise ValueError(f"links must be {PRIMARY} then {FALLBACK}, got {primary.name} and {fallback.name}")
        self.links: dict[LinkName, Link] = {primary.name: primary, fallback.name: fallback}
        self.senders: dict[LinkName, LinkSender] = {
            name: LinkSender(link) for name, link in self.links.items() if needs_sender(link)
        }
        """The send thread of each link whose publish may wait (links/sender.py); the others are
        published to inline."""
        self.manager = LinkManager(policy)
        self.counter = wire.HeaderCounter(clock, robot="operator", sender=sender)
        self.rejected: Counter[str] = Counter()
        self._seen_reasons: set[str] = set()
        self._lock = threading.Lock()
        self._sinks: list[Sink] = []
        self._early: deque[tuple[wire.Message, str, float]] | None = deque(maxlen=MAX_EARLY)
        """What arrived before the first sink was added (None after): the retained messages a
        broker sends right after connecting (consoles' mark sets, robots' connections)."""
        self._replay: list[tuple[wire.Message, str, float]] = []
        self._anchor_sinks: list[AnchorSink] = []
        self._presence_sinks: list[PresenceSink] = []
        self._listeners: list[Listener] = []
        self._poller = Worker("operator-link-poll", target=self._poll_loop)
        self._poll_interval = 1.0 / poll_hz
        self.delivered: Counter[str] = Counter()
        """Messages accepted per link (for the console's status line and tests)."""

    # -- wiring ---------------------------------------------------------------------------------

    def add_sink(self, sink: Sink) -> None:
        """``sink(msg, link, now)`` for every good message (on a link's thread). What arrived
        before the first sink was added (a link started before the console attached its model)
        follows from the poll worker, within a poll period."""
        with self._lock:
            if self._early is not None:
                self._replay, self._early = list(self._early), None
            self._sinks.append(sink)

    def add_listener(self, listener: Listener) -> None:
        self._listeners.append(listener)

    def add_anchor_sink(self, sink: AnchorSink) -> None:
        """``sink(gateway, [(id, x, y, z), ...])`` for each UWB gateway status heard."""
        self._anchor_sinks.append(sink)

    def add_presence_sink(self, sink: PresenceSink) -> None:
        """``sink(robot, link, alive, wall)`` whenever a robot's liveliness token comes or goes."""
        self._presence_sinks.append(sink)

    def start(self) -> OperatorLink:
        for name, link in self.links.items():

            def receive(key: str, payload: bytes, name: LinkName = name) -> None:
                self._receive(name, key, payload)

            link.subscribe(keys.ZENOH_ALL, receive)
            link.subscribe(UWB_STATUS, receive)
            watch = getattr(link, "watch_liveliness", None)
            if watch is not None:

                def token(key: str, alive: bool, name: LinkName = name) -> None:
                    self._token(name, key, alive)

                watch(ALIVE_TOKENS, token)
            link.start()
        for sender in self.senders.values():
            sender.start()
        self._poller.start()
        return self

    def close(self) -> None:
        self._poller.stop()
        for sender in self.senders.values():  # what was queued goes out first (a stop-all on quit)
            sender.stop(SENDER_STOP_S)
        for link in self.links.values():
            try:
                link.close()
            except Exception as exc:  # closing must go on for the other link
                log.warning("closing %s: %s", link.name.value, exc)

    def __enter__(self) -> OperatorLink:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- inbound --------------------------------------------------------------------------------

    def _reject(self, link: str, key: str, reason: str) -> None:
        # Reasons quote what the sender sent: their number is capped (memory bounded by
        # construction); beyond the cap they are counted as one, and never logged.
        with self._lock:
            known = reason in self.rejected or len(self.rejected) < MAX_REJECT_REASONS
            self.rejected[reason if known else OTHER_REASONS] += 1
            first = known and reason not in self._seen_reasons
            if first:
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

    def _token(self, link: str, key: str, alive: bool) -> None:
        try:
            robot = keys.parse_alive_key(key)
        except ValueError as exc:
            self._reject(link, key, f"bad liveliness token: {exc}")
            return
        wall = self.clock.wall()
        for sink in self._presence_sinks:
            sink(robot, link, alive, wall)

    def _receive(self, link: str, key: str, payload: bytes) -> None:
        if key.startswith("fleetlink/uwb/"):
            self._gateway_status(link, key, payload)
            return
        try:
            msg = wire.decode_key(key, payload)
        except wire.WireError as exc:
            self._reject(link, key, exc.reason if hasattr(exc, "reason") else str(exc))
            return
        if msg.header.sender == self.sender and not isinstance(msg, Mark | MarkSet | AlarmAck):
            # Our own command, echoed by the broker or the local Zenoh session. Our own marks do
            # go on: a console restarted without its marks file gets them back from its retained
            # sets (merging a mark already held changes nothing); so do our alarm acknowledgements.
            return
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
            if self._early is not None:
                self._early.append((msg, link, now))
                return
        for sink in self._sinks:
            sink(msg, link, now)

    # -- outbound -------------------------------------------------------------------------------

    def send(self, cls: type[wire.Message], robot: str, *, expect_ack: bool = True, **fields: Any) -> wire.Message:
        """Build, encode and send a command to ``robot`` (on both links, or over its active link).
        Returns the message."""
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
        k = wire.key_of(msg)
        for link in links:
            self._put(link, k, payload)

    def publish_retained(self, msg: wire.Message) -> bool:
        """Publish ``msg`` retained on every link whose broker keeps messages (MQTT; a consoles'
        ``MarkSet``); False if it was sent on none (down: ``add_connect_listener`` says when to
        try again)."""
        payload = wire.encode(msg)
        k = wire.key_of(msg)
        sent = False
        for link in self.links.values():
            if isinstance(link, RetainLink):
                try:
                    sent = link.publish_retained(k, payload) or sent
                except Exception as exc:  # a dead transport must not take the console down
                    log.debug("retained publish on %s failed: %s", link.name.value, exc)
        return sent

    def add_connect_listener(self, listener: Callable[[], object]) -> None:
        """``listener()`` after every (re)connect of a link whose broker keeps messages (on that
        link's thread), once its subscriptions are renewed."""
        for link in self.links.values():
            if isinstance(link, RetainLink):
                link.add_connect_hook(listener)

    def flush(self, timeout: float = 2.0) -> bool:
        """Wait until every link's send thread has handed on what was sent so far; False if one
        had not within ``timeout`` (each; a stuck link)."""
        return all([sender.flush(timeout) for sender in self.senders.values()])

    def _put(self, link: str, key: str, payload: bytes) -> None:
        name = LinkName(link)
        sender = self.senders.get(name)
        if sender is not None:
            sender.submit(key, payload)  # never waits: its own thread publishes
            return
        try:
            self.links[name].publish(key, payload)
        except Exception as exc:  # a dead transport must not take the console down; health shows it
            log.debug("publish on %s failed: %s", link, exc)

    def _dispatch(self, actions: Sequence[Send | Switch | Failed]) -> None:
        for action in actions:
            if isinstance(action, Send):
                self._put(action.link, keys.sender_key(action.robot, action.topic, self.sender), action.payload)
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
            early, self._replay = self._replay, []
        for msg, link, now in early:
            for sink in self._sinks:
                sink(msg, link, now)
        self._dispatch(actions)

    def _poll_loop(self, worker: Worker) -> None:
        while not worker.stopping:
            worker.wait(self._poll_interval)
            if worker.stopping:
                return
            try:
                self.poll()
            except Exception:  # keep serving: one bad poll must not stop failover for good
                log.exception("link poll failed")

    # -- queries (over the primary, when it answers queries: Zenoh, in-process) ------------------

    def _queries(self) -> Any:
        primary = self.links[LinkName.ZENOH]
        return primary if hasattr(primary, "query") and hasattr(primary, "serve") else None

    def query_link(self) -> Any:
        """The primary link when it answers queries (Zenoh, in-process), else None: where this
        console serves what it shares (its marks; the fleet map it builds)."""
        return self._queries()

    def fetch_map(self, robot: str, timeout: float = 3.0) -> MapSnapshot | None:
        """Ask the robot's map queryable (``fleetlink/v1/<robot>/map``); None if no good answer."""
        return self._fetch(robot, MapSnapshot, timeout)

    def fetch_dose(self, robot: str, timeout: float = 3.0) -> DoseSnapshot | None:
        """Ask the robot's dose queryable (``fleetlink/v1/<robot>/dose``); None if no good answer."""
        return self._fetch(robot, DoseSnapshot, timeout)

    def _fetch(self, robot: str, cls: type[_S], timeout: float) -> _S | None:
        """The first valid ``cls`` answer of ``fleetlink/v1/<robot>/<cls.TOPIC>``; bad replies are
        counted and logged as rejected input."""
        primary = self._queries()
        if primary is None:
            return None
        for key, payload in primary.query(keys.key(robot, cls.TOPIC), timeout):
            try:
                msg = wire.decode_key(key, payload)
            except wire.WireError as exc:
                self._reject(PRIMARY, key, exc.reason)
                continue
            if isinstance(msg, cls):
                return msg
        return None

    def serve_marks(self, marks: Callable[[], Sequence[Mark]]) -> None:
        """Answer ``MARKS_QUERY`` with this console's own marks in ``marks()`` (removed ones too,
        so a late console learns of the removal): a console speaks only under its own name (the
        router lets it reply nowhere else), so each author answers for its marks."""
        primary = self._queries()
        if primary is not None:

            def answer(_key: str) -> list[tuple[str, bytes]]:
                return [(wire.key_of(m), wire.encode(m)) for m in marks() if m.header.sender == self.sender]

            primary.serve(keys.sender_filter("*", Mark.TOPIC, self.sender), answer)

    def fetch_marks(self, timeout: float = 2.0) -> int:
        """Ask every other console for its marks; they go to the sinks like published ones."""
        primary = self._queries()
        if primary is None:
            return 0
        replies = primary.query(MARKS_QUERY, timeout)
        for key, payload in replies:
            self._receive(PRIMARY, key, payload)
        return len(replies)

    # -- views ----------------------------------------------------------------------------------

    def active(self, robot: str) -> str:
        """Where ``robot``'s commands go: ``both`` (redundant sending), else its active link."""
        with self._lock:
            return self.manager.route(robot)

    @property
    def redundant(self) -> bool:
        return self.manager.policy.redundant

    def health(self, robot: str) -> tuple[LinkHealth, ...]:
        with self._lock:
            return self.manager.health(robot, self.clock.now())

    def link_states(self, robot: str) -> tuple[tuple[str, float | None, str], ...]:
        """Each link's (name, age of the last message, why it is degraded): ``LinkManager.link_states``."""
        with self._lock:
            return self.manager.link_states(robot, self.clock.now())

    def pending(self, robot: str) -> int:
        with self._lock:
            return self.manager.pending(robot)
