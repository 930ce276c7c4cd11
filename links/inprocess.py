"""An in-process link: the same wire bytes between endpoints of one process, for lockstep runs.

``InProcessBus(LinkName.ZENOH)`` stands for one transport (a Zenoh network or an MQTT broker);
``bus.endpoint("agent-r1")`` gives a ``Link`` to each party. A publish only queues the bytes;
the owner of simulated time calls ``bus.deliver()`` between steps, which hands every queued
message, in publish order, to every matching subscriber (including messages published while
delivering, so a command and its ack cross in one call). Nothing runs on a thread of its own, so
a run is deterministic.

Faults: ``bus.cut("agent-r1")`` takes one endpoint off the network (its publishes and the messages
meant for it vanish, counted in ``stats.dropped``; ``up`` is False) until ``bus.restore``. A cut
has a reason (``"scenario"`` by default; the lockstep run's radio model uses ``"radio"``): the
endpoint is back only once every reason is restored, so a scripted cut and a robot out of radio
reach stay separate causes (``bus.cut_reasons(client_id)``).
Queries (``serve``/``query``) answer synchronously, as a Zenoh queryable would on loopback.
Liveliness, as on Zenoh: an endpoint's ``alive_key`` is its token while it is up (started, not
cut, not closed); ``watch_liveliness(key_expr, on_change)`` reports tokens appearing and going,
at the start of each ``deliver`` (a cut watcher sees none).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from fleetlink.links.base import LinkStats, Receiver, key_matches
from fleetlink.shared.messages import LinkName

__all__ = ["SCENARIO_CUT", "InProcessBus", "InProcessLink"]

SCENARIO_CUT = "scenario"
"""The reason of a cut that names none (a scenario's ``link`` event, a test)."""

Answer = Callable[[str], list[tuple[str, bytes]]]

MAX_DELIVERIES = 1_000_000
"""A guard against two endpoints that answer each other forever within one ``deliver``."""


class InProcessLink:
    """One party's endpoint on an ``InProcessBus``; satisfies ``fleetlink.links.base.Link``."""

    PUBLISH_QUEUES = True
    """``publish`` only queues for the bus's ``deliver`` (links/sender.py: no send thread)."""

    def __init__(self, bus: InProcessBus, client_id: str) -> None:
        self.name = bus.name
        self.client_id = client_id
        self.stats = LinkStats()
        self._bus = bus
        self._subs: list[tuple[str, Receiver]] = []
        self._routes: dict[str, list[Receiver]] = {}  # key -> its receivers, as subscriptions stand
        self._served: list[tuple[str, Answer]] = []
        self._open = False
        self.alive_key: str | None = None
        """This endpoint's liveliness token (set it before the run), present while it is up."""
        self._watches: list[tuple[str, Callable[[str, bool], None]]] = []
        self._alive_seen: set[str] = set()

    def start(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False
        self._subs.clear()
        self._routes.clear()
        self._served.clear()
        self._watches.clear()

    def watch_liveliness(self, key_expr: str, on_change: Callable[[str, bool], None]) -> None:
        """``on_change(token key, alive)`` when an endpoint's token matching ``key_expr`` appears or
        goes (reported at the start of the bus's next ``deliver``, the present ones included)."""
        self._watches.append((key_expr, on_change))
        self._alive_seen.clear()

    @property
    def up(self) -> bool:
        return self._open and self.client_id not in self._bus.cut_endpoints

    def publish(self, key: str, payload: bytes) -> bool:
        if not self.up:
            self.stats.dropped += 1
            return False
        self._bus.queue.append((self, key, bytes(payload)))
        self.stats.sent += 1
        return True

    def subscribe(self, key_expr: str, receiver: Receiver) -> None:
        self._subs.append((key_expr, receiver))
        self._routes.clear()

    def prioritise(self, priority_keys: frozenset[str], *, then_topics: frozenset[str] = frozenset()) -> None:
        """Nothing waits here: ``deliver`` hands every message on as the owner of time pumps it."""

    def serve(self, key_expr: str, answer: Answer) -> None:
        """Answer queries on ``key_expr``: ``answer(key_expr_asked)`` -> [(key, payload)]."""
        self._served.append((key_expr, answer))

    def unserve(self, key_expr: str) -> None:
        self._served = [(expr, answer) for expr, answer in self._served if expr != key_expr]

    def query(self, key_expr: str, timeout: float = 0.0) -> list[tuple[str, bytes]]:
        """Every reachable endpoint's answers to ``key_expr`` (``timeout`` is unused: in-process
        queries answer at once)."""
        if not self.up:
            return []
        replies: list[tuple[str, bytes]] = []
        for peer in self._bus.endpoints:
            if not peer.up:
                continue
            for expr, answer in peer._served:
                if key_matches(expr, key_expr) or key_matches(key_expr, expr):
                    replies.extend(answer(key_expr))
        return replies

    def _receivers(self, key: str) -> list[Receiver]:
        receivers = self._routes.get(key)
        if receivers is None:
            receivers = self._routes[key] = [r for expr, r in self._subs if key_matches(expr, key)]
        return receivers

    def _receive(self, key: str, payload: bytes, now: float | None) -> int:
        receivers = self._receivers(key)
        for receiver in receivers:
            receiver(key, payload)
        if receivers:
            self.stats.received += 1
            self.stats.last_rx = now
        return len(receivers)


class InProcessBus:
    """One transport inside one process. See the module docstring."""

    def __init__(self, name: LinkName, *, clock_now: Callable[[], float] | None = None) -> None:
        self.name = name
        self.endpoints: list[InProcessLink] = []
        self.cut_endpoints: set[str] = set()
        """Endpoints cut for at least one reason."""
        self._reasons: dict[str, set[str]] = {}
        self.queue: deque[tuple[InProcessLink, str, bytes]] = deque()
        self.delivered = 0
        self._now = clock_now

    def endpoint(self, client_id: str) -> InProcessLink:
        """A new party on the bus. A closed endpoint's id may be taken again (a restarted process
        connects under its old id, and its cuts hold for the new endpoint); an open one's may not."""
        if any(e.client_id == client_id and e._open for e in self.endpoints):
            raise ValueError(f"{self.name.value}: endpoint {client_id!r} exists already")
        self.endpoints = [e for e in self.endpoints if e.client_id != client_id]
        link = InProcessLink(self, client_id)
        self.endpoints.append(link)
        return link

    def cut(self, client_id: str, reason: str = SCENARIO_CUT) -> None:
        """Take the endpoint off the network for ``reason`` (idempotent)."""
        self._known(client_id)
        self._reasons.setdefault(client_id, set()).add(reason)
        self.cut_endpoints.add(client_id)

    def restore(self, client_id: str, reason: str = SCENARIO_CUT) -> None:
        """Lift the cut for ``reason``; the endpoint is back once no reason is left."""
        self._known(client_id)
        reasons = self._reasons.get(client_id)
        if reasons is not None:
            reasons.discard(reason)
            if reasons:
                return
            del self._reasons[client_id]
        self.cut_endpoints.discard(client_id)

    def cut_reasons(self, client_id: str) -> frozenset[str]:
        """Why the endpoint is cut (empty: it is not)."""
        return frozenset(self._reasons.get(client_id, ()))

    def deliver(self) -> int:
        """Hand every queued message to its subscribers, in order; returns how many were taken."""
        n = 0
        now = self._now() if self._now is not None else None
        self._liveliness()
        while self.queue:
            sender, key, payload = self.queue.popleft()
            n += 1
            if n > MAX_DELIVERIES:
                raise RuntimeError(f"{self.name.value}: more than {MAX_DELIVERIES} messages in one delivery")
            for peer in self.endpoints:
                if peer is sender:
                    continue  # like a Zenoh session and an MQTT client without echo: no loopback
                if not peer.up:
                    if peer._open and peer._receivers(key):
                        peer.stats.dropped += 1
                    continue
                peer._receive(key, payload, now)
        self.delivered += n
        return n

    def _liveliness(self) -> None:
        watchers = [e for e in self.endpoints if e._watches and e._open]
        if not watchers:
            return
        tokens = {e.alive_key for e in self.endpoints if e.alive_key is not None and e.up}
        for watcher in watchers:
            visible = tokens if watcher.up else set()
            for key in sorted(visible ^ watcher._alive_seen):
                for expr, on_change in list(watcher._watches):
                    if key_matches(expr, key):
                        on_change(key, key in visible)
            watcher._alive_seen = set(visible)

    def _known(self, client_id: str) -> None:
        if not any(e.client_id == client_id for e in self.endpoints):
            raise KeyError(f"{self.name.value}: no endpoint {client_id!r}")
