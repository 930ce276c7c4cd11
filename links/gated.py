"""A link behind a gate: while ``is_open()`` is False nothing passes either way and ``up`` reads False.

The real-time field's radio model (field/radio.py) puts each agent's Zenoh and MQTT endpoints
behind one (``AgentRuntime(reachable=...)``, built by site/agents.py): a robot out of radio reach
stops hearing commands and UWB fixes, its telemetry stops, and its agent sees the link down, while
the transport underneath stays connected (a real robot's session would time out; the gate's
effect on the messages is the same, sooner). Pure: the gate only reads a predicate.

Closed, the gate drops publishes (``publish`` returns False) and inbound messages, counting both in
``stats.dropped``, answers no query and asks none. The inner endpoint's ``stats`` are shared.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

from fleetlink.links.base import Link, LinkStats, QueryLink, Receiver
from fleetlink.shared.messages import LinkName

__all__ = ["GatedLink"]

Answer = Callable[[str], list[tuple[str, bytes]]]


class GatedLink:
    """``inner`` behind ``is_open``; satisfies ``Link`` (and ``QueryLink`` when ``inner`` does)."""

    def __init__(self, inner: Link, is_open: Callable[[], bool]) -> None:
        self.inner = inner
        self.is_open = is_open
        self.name: LinkName = inner.name
        self.stats: LinkStats = inner.stats

    def start(self) -> None:
        self.inner.start()

    def close(self) -> None:
        self.inner.close()

    @property
    def up(self) -> bool:
        return self.is_open() and self.inner.up

    def publish(self, key: str, payload: bytes) -> bool:
        if not self.is_open():
            self.stats.dropped += 1
            return False
        return self.inner.publish(key, payload)

    def subscribe(self, key_expr: str, receiver: Receiver) -> None:
        def gated(key: str, payload: bytes) -> None:
            if self.is_open():
                receiver(key, payload)
            else:
                self.stats.dropped += 1

        self.inner.subscribe(key_expr, gated)

    def prioritise(self, priority_keys: frozenset[str], *, then_topics: frozenset[str] = frozenset()) -> None:
        self.inner.prioritise(priority_keys, then_topics=then_topics)

    # -- queries (when the inner link has them) ---------------------------------------------------

    def serve(self, key_expr: str, answer: Answer) -> None:
        def gated(asked: str) -> list[tuple[str, bytes]]:
            return answer(asked) if self.is_open() else []

        cast(QueryLink, self.inner).serve(key_expr, gated)

    def unserve(self, key_expr: str) -> None:
        cast(QueryLink, self.inner).unserve(key_expr)

    def query(self, key_expr: str, timeout: float = 1.0) -> list[tuple[str, bytes]]:
        if not self.is_open():
            return []
        return cast(QueryLink, self.inner).query(key_expr, timeout)
