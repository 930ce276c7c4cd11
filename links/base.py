"""The link interface, its counters, and key-expression matching. Pure: no I/O.

A link is one endpoint on one transport (``LinkName.ZENOH`` or ``LinkName.MQTT``). Keys are the
wire contract's keys (shared/keys.py): the same string is a Zenoh key and an MQTT topic.
Subscriptions take Zenoh-style expressions (``*`` one segment, ``**`` any number of segments);
the MQTT endpoint translates them to ``+`` and ``#``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from fleetlink.shared.messages import LinkName
from fleetlink.shared.wire import MAX_PAYLOAD

log = logging.getLogger(__name__)

__all__ = ["Link", "LinkStats", "QueryLink", "Receiver", "RetainLink", "key_matches", "to_mqtt_filter"]

Receiver = Callable[[str, bytes], None]
"""Called with (key, payload) for every message that matches a subscription."""


@dataclass(slots=True)
class LinkStats:
    """What an endpoint counts; read it for health, never reset it."""

    sent: int = 0
    received: int = 0
    dropped: int = 0
    """Publishes not sent (link down, queue full) and inbound messages not delivered."""
    last_rx: float | None = None
    """Clock time of the last message received (None: never)."""
    oversized: int = 0
    """Inbound messages over ``wire.MAX_PAYLOAD`` refused before they were copied or decoded."""

    def admit(self, label: str, key: str, size: int) -> bool:
        """Whether an inbound message of ``size`` bytes may be read; one over the wire's limit is
        counted (the first one logged) and must be dropped before it is copied."""
        if size <= MAX_PAYLOAD:
            return True
        self.oversized += 1
        if self.oversized == 1:
            log.warning("%s: refused %d bytes on %s (limit %d); counting the rest", label, size, key[:120], MAX_PAYLOAD)
        return False


@runtime_checkable
class Link(Protocol):
    name: LinkName
    stats: LinkStats

    def start(self) -> None:
        """Open the endpoint (idempotent); subscriptions made before start take effect now."""
        ...

    def publish(self, key: str, payload: bytes) -> bool:
        """Send ``payload`` on ``key``; False if it was not sent (down, or dropped)."""
        ...

    def subscribe(self, key_expr: str, receiver: Receiver) -> None:
        """Hand every message whose key matches ``key_expr`` to ``receiver(key, payload)``."""
        ...

    def prioritise(self, priority_keys: frozenset[str], *, then_topics: frozenset[str] = frozenset()) -> None:
        """Hand messages on exactly these keys on before any waiting for receivers (the agent's lease
        holder's commands). A no-op where messages do not wait (in-process; MQTT, whose one loop
        thread hands each on as it reads it)."""
        ...

    @property
    def up(self) -> bool:
        """The transport is connected (a broker session, or at least one Zenoh session)."""
        ...

    def close(self) -> None:
        """Close the endpoint (idempotent); no receiver is called after it returns."""
        ...


@runtime_checkable
class QueryLink(Link, Protocol):
    """A link that also answers queries and asks them (``ZenohEndpoint``, ``InProcessLink``)."""

    def serve(self, key_expr: str, answer: Callable[[str], list[tuple[str, bytes]]]) -> None:
        """Answer queries matching ``key_expr``: ``answer(key_expr_asked)`` -> [(key, payload)]."""
        ...

    def unserve(self, key_expr: str) -> None:
        """Stop answering on ``key_expr`` (what ``serve`` registered on exactly that expression)."""
        ...

    def query(self, key_expr: str, timeout: float = ...) -> list[tuple[str, bytes]]:
        """Every reachable answer to ``key_expr``."""
        ...


@runtime_checkable
class RetainLink(Link, Protocol):
    """A link whose broker keeps the last message on a key for whoever subscribes later (MQTT
    retained messages: ``MqttEndpoint``). Consoles keep their marks there (operator/marksync.py)."""

    def publish_retained(self, key: str, payload: bytes) -> bool:
        """``publish``, and the broker keeps ``payload`` as the key's last message; False if not sent."""
        ...

    def add_connect_hook(self, hook: Callable[[], object]) -> None:
        """Call ``hook()`` after every (re)connect, once the subscriptions are renewed (on the
        link's own thread): what was not sent while down can go now."""
        ...


def key_matches(key_expr: str, key: str) -> bool:
    """Zenoh-style matching of one concrete ``key`` against ``key_expr``: ``*`` is one segment,
    ``**`` is zero or more segments."""
    return _match(key_expr.split("/"), key.split("/"))


def _match(pat: list[str], segs: list[str]) -> bool:
    if not pat:
        return not segs
    head = pat[0]
    if head == "**":
        return any(_match(pat[1:], segs[i:]) for i in range(len(segs) + 1))
    if not segs:
        return False
    return (head == "*" or head == segs[0]) and _match(pat[1:], segs[1:])


def to_mqtt_filter(key_expr: str) -> str:
    """``fleetlink/v1/*/order`` -> ``fleetlink/v1/+/order``; a trailing ``**`` -> ``#``."""
    parts = key_expr.split("/")
    out = ["+" if p == "*" else p for p in parts]
    if "**" in out:
        if out.index("**") != len(out) - 1:
            raise ValueError(f"MQTT can only match many segments at the end: {key_expr!r}")
        out[-1] = "#"
    return "/".join(out)
