"""The command gate: every inbound payload passes here, from either link. Pure: no I/O, time passed in.

* decodes and validates (``wire.decode_key``: the header's robot must match the key, and a
  command's ``header.sender`` the login its key names -- on a secured site only that login may
  publish there, so the sender is the transport's word, not the payload's);
* drops a command already executed: same (topic, sender, headerId, timestamp) -- an operator
  sends the same bytes on both links (redundant sending: the first copy runs, the other is acked
  as a duplicate on its own link and costs the sender no rate), and re-sends are byte-identical
  -- or an order whose
  (orderId, orderUpdateId) was already executed; an order update older than the last one is stale;
* counts rejections per (link, topic) and says which ones are new enough to log (once per
  link, topic and offending field), so garbage never floods the log;
* builds the ``Ack`` for a command, addressed to the link it came from.

The header timestamp is part of the dedupe key so a sender that restarts (headerId back to 0)
is not mistaken for a replay.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from fleetlink.agent.lease import ALWAYS_ALLOWED_ACTIONS
from fleetlink.shared import keys, wire
from fleetlink.shared.messages import Ack, AckResult, InstantActions, LinkName, Order, Teleop, ack_fields

__all__ = ["COMMAND_TOPICS", "Accepted", "CommandGate", "Duplicate", "GateStats", "Rejected", "Verdict"]

COMMAND_TOPICS = (Order.TOPIC, InstantActions.TOPIC, Teleop.TOPIC)
Command = Order | InstantActions | Teleop


@dataclass(frozen=True, slots=True)
class Accepted:
    """A fresh message: run it (and, for a command, ack it on ``link``)."""

    msg: wire.Message
    link: LinkName


@dataclass(frozen=True, slots=True)
class Duplicate:
    """A command already executed: do not run it again; ``ack`` answers it on ``link``."""

    msg: Command
    link: LinkName
    ack: dict[str, Any]


@dataclass(frozen=True, slots=True)
class Rejected:
    """Malformed or unwanted input. ``log`` is true the first time this (link, topic) is refused
    -- or, apart, the first time a sender is (someone claiming another's name, or not allowed)."""

    link: LinkName
    topic: str
    reason: str
    log: bool


Verdict = Accepted | Duplicate | Rejected


SENDER_FIELDS = frozenset({"header.sender", "sender"})
"""Rejections of who sent a command (a name the key does not vouch for, an operator not allowed)."""

MAX_LOGGED_TAGS = 256
"""Distinct (link, topic) pairs whose first rejection is logged and published; beyond
them rejections are only counted."""


@dataclass(slots=True)
class GateStats:
    accepted: int = 0
    duplicates: int = 0
    rejected: dict[tuple[str, str], int] = field(default_factory=dict)
    """(link, topic) -> count; topic is ``?`` when the key itself was unusable."""
    last_reason: str = ""

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


def always_allowed(msg: Command) -> bool:
    """A stop, an e-stop or a pause: nobody may be kept from stopping the robot."""
    return isinstance(msg, InstantActions) and all(
        a.actionType.value.lower() in ALWAYS_ALLOWED_ACTIONS for a in msg.actions
    )


class RateLimit:
    """Token buckets: one per sender (``rate`` commands a second on average, ``burst`` at once) and
    one that every sender but the priority one (the lease holder) shares (``shared_rate``,
    ``shared_burst``). On an open site (no logins) sender names are the sender's to choose: the
    shared bucket keeps a flood under invented names from crowding out the holder. Pure; at most
    ``max_senders`` buckets are remembered (the one unheard from longest is forgotten first)."""

    def __init__(
        self,
        rate: float = 50.0,
        burst: float = 100.0,
        *,
        shared_rate: float = 100.0,
        shared_burst: float = 200.0,
        max_senders: int = 256,
    ) -> None:
        self.rate, self.burst, self.max_senders = rate, burst, max_senders
        self.shared_rate, self.shared_burst = shared_rate, shared_burst
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # sender -> (tokens, at)
        self._shared: tuple[float, float | None] = (shared_burst, None)  # (tokens, at)
        self.limited = 0

    def allow(self, sender: str, now: float, *, priority: bool = False) -> bool:
        """Take one command from ``sender``; ``priority``: it is the lease holder (no shared bucket)."""
        tokens, at = self._buckets.pop(sender, (self.burst, now))
        tokens = min(self.burst, tokens + (now - at) * self.rate)
        ok = tokens >= 1.0
        if ok and not priority:
            shared, shared_at = self._shared
            if shared_at is not None:
                shared = min(self.shared_burst, shared + (now - shared_at) * self.shared_rate)
            ok = shared >= 1.0
            self._shared = (shared - 1.0 if ok else shared, now)
        self._buckets[sender] = (tokens - 1.0 if ok else tokens, now)
        while len(self._buckets) > self.max_senders:
            self._buckets.popitem(last=False)
        if not ok:
            self.limited += 1
        return ok


class CommandGate:
    def __init__(
        self,
        robot: str,
        *,
        topics: tuple[str, ...] = COMMAND_TOPICS,
        horizon_s: float = 120.0,
        max_entries: int = 8192,
    ) -> None:
        self.robot = keys.check_robot_id(robot)
        self.topics = frozenset(topics)
        self.horizon_s = horizon_s
        self.max_entries = max_entries
        self.stats = GateStats()
        # (topic, sender, headerId, timestamp) -> (time seen, link it first came on, whether its
        # copy on the other link came too)
        self._seen: OrderedDict[tuple[str, str, int, float], tuple[float, LinkName, bool]] = OrderedDict()
        self._orders: dict[str, int] = {}  # orderId -> highest executed orderUpdateId
        self._logged: set[tuple[str, str, bool]] = set()
        self.limit = RateLimit()
        """Commands per sender and second: a flood from one sender costs a decode and a count."""
        self.priority_sender = ""
        """The lease holder (the agent's core keeps it current): only its own bucket limits it."""

    # -- inbound -----------------------------------------------------------------------------

    def receive(self, link: LinkName, key: str, payload: bytes, now: float) -> Verdict:
        try:
            robot, topic = keys.parse_key(key)
        except ValueError as exc:
            return self.reject(link, "?", f"key: {exc}")
        topic = keys.split_sender(topic)[0]  # counted per topic, whoever the key names
        if robot != self.robot or topic not in self.topics:
            return self.reject(link, topic, f"key: not an input of agent {self.robot}: {key}")
        try:
            msg = wire.decode_key(key, payload)
        except wire.WireError as exc:
            return self.reject(link, topic, exc.reason, exc.field)
        if not isinstance(msg, Order | InstantActions | Teleop):
            self.stats.accepted += 1
            return Accepted(msg, link)
        sender = msg.header.sender
        h = msg.header
        ident = (topic, h.sender, h.headerId, h.timestamp)
        first = self._seen.get(ident)
        if first is not None and first[1] is not link and not first[2]:
            # The copy on the other link of a command sent on both (redundant sending): acked as a
            # duplicate, never run, and free -- it takes no token from the sender's rate, or a
            # console sending everything twice would be held to half of it. Only the first such
            # copy is free: replays of it go through the rate like anything else.
            self._seen[ident] = (first[0], first[1], True)
            self.stats.duplicates += 1
            return Duplicate(
                msg, link, self.ack(msg, link, AckResult.DUPLICATE, f"already received on {first[1].value}")
            )
        if not always_allowed(msg) and not self.limit.allow(sender, now, priority=sender == self.priority_sender):
            # Over its rate: refused before any work (not remembered, no ack, no lease check),
            # counted, logged once per link and topic. The lease holder's teleops (10 Hz) are far
            # below the rate; stops are never limited.
            return self.reject(link, topic, f"sender {sender!r}: over its rate ({self.limit.rate:g} commands/s)")
        self._expire(now)
        first = self._seen.get(ident)
        if first is not None:
            self.stats.duplicates += 1
            return Duplicate(
                msg, link, self.ack(msg, link, AckResult.DUPLICATE, f"already received on {first[1].value}")
            )
        self._seen[ident] = (now, link, False)
        if isinstance(msg, Order):
            last = self._orders.get(msg.orderId)
            if last is not None and msg.orderUpdateId == last:
                self.stats.duplicates += 1
                reason = f"order {msg.orderId}/{msg.orderUpdateId} already executed"
                return Duplicate(msg, link, self.ack(msg, link, AckResult.DUPLICATE, reason))
            if last is not None and msg.orderUpdateId < last:
                return self.reject(
                    link,
                    topic,
                    f"orderUpdateId: {msg.orderUpdateId} is older than the executed {last}",
                    "orderUpdateId",
                )
        self.stats.accepted += 1
        return Accepted(msg, link)

    def reject(self, link: LinkName, topic: str, reason: str, what: str = "") -> Rejected:
        """Count one rejected input (also for inputs decoded elsewhere, e.g. PANS JSON)."""
        slot = (link.value, topic)
        self.stats.rejected[slot] = self.stats.rejected.get(slot, 0) + 1
        self.stats.last_reason = reason
        # Logged (and published) once per link and topic: a reason or a field name may be the
        # sender's own words (an unknown field's name, an out-of-range value), so they are not part
        # of the tag, or a sender could make every rejection a "first" one by varying them. Only
        # whether the sender itself was refused is (an impersonation or a stranger, which garbage
        # seen earlier must not hide from the log). The set is capped all the same and silent when
        # full. Counting and the last reason (Diagnostics) go on regardless.
        tag = (link.value, topic, what in SENDER_FIELDS)
        first = tag not in self._logged and len(self._logged) < MAX_LOGGED_TAGS
        if first:
            self._logged.add(tag)
        return Rejected(link, topic, reason, first)

    def executed_order(self, order: Order) -> None:
        """The pilot took this order: later copies of (orderId, orderUpdateId) are duplicates."""
        last = self._orders.get(order.orderId)
        if last is None or order.orderUpdateId > last:
            self._orders[order.orderId] = order.orderUpdateId
            if len(self._orders) > 1024:  # old orders are forgotten first (dicts keep insertion order)
                del self._orders[next(iter(self._orders))]

    # -- acks ------------------------------------------------------------------------------------

    def ack(self, msg: Command, link: LinkName, result: AckResult, reason: str = "") -> dict[str, Any]:
        """The fields of the ``Ack`` answering ``msg`` (stamp with ``HeaderCounter.make(Ack, **fields)``)."""
        return ack_fields(msg, link, result, reason)

    def make_ack(self, counter: wire.HeaderCounter, fields: dict[str, Any]) -> Ack:
        return counter.make(Ack, **fields)

    # -- internals ------------------------------------------------------------------------------

    def _expire(self, now: float) -> None:
        seen = self._seen
        while seen:
            ident, (t, _, _) = next(iter(seen.items()))
            if now - t <= self.horizon_s and len(seen) < self.max_entries:
                break
            del seen[ident]
