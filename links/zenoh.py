"""The Zenoh endpoint, and the one place a Zenoh session is configured.

``peer_config``/``open_session`` build every fleetlink session the same way: explicit listen and
connect endpoints, multicast scouting off, peer or client mode, a login and TLS files for a
secured site router. ``ZenohEndpoint`` is a ``fleetlink.links.base.Link`` over one session (its
own, or one it is given), plus queries (``serve``/``query``, as ``InProcessLink``), an optional
liveliness token (the agent's presence on ``fleetlink/alive/v1/<robot>``) and liveliness watches
(``watch_liveliness``: the console learns which robots' tokens come and go, those present when
it starts included; the changes reach it through the same inbox as samples, in arrival order).

Quality of service per key: a key whose topic is in ``URGENT_TOPICS`` (commands, acks, events,
the lease, the connection) goes express with INTERACTIVE_HIGH priority and congestion control
BLOCK; everything else (telemetry, maps) with DROP, so a slow subscriber never stalls the
publisher. Plain ``session.put``, not declared publishers: behind a router with access control, a
publisher declared before a subscriber appears never learns of it and silently drops every sample.

Order: zenoh-python runs a plain Python callback on a thread of its own per subscriber, so
samples on different keys (a teleop, then a lease release) could reach the receiver out of the
order they were sent in. Each subscriber's callback therefore runs on zenoh's network thread
(``indirect=False``) and only queues the sample in a bounded inbox; one delivery thread (a
``Worker``) hands them to the receivers in arrival order, so the network thread never waits on
the application. Beyond ``inbox_size`` waiting samples (a receiver stalled for seconds) new ones
are dropped and counted.

Direct delivery (``direct=True``, the agent's endpoint): a sample on a prioritised key (below: the
lease holder's commands) that finds the inbox empty and no receiver running is handed to its
receiver on zenoh's thread itself, so the driver's command reaches the agent's core without waking
the delivery thread (the wake-up and the wait for the GIL it costs were ~0.1 ms at the median and
up to 1 ms at p99 of the command's path to the board, docs/architecture.md "The command's path").
One sample is delivered at a time whichever thread delivers it, and only when nothing is queued,
so the order and the lanes below hold; a sample that arrives meanwhile is queued as before. The
network thread waits for that receiver meanwhile, so only receivers that return in well under a
millisecond may be direct (the agent's: decide, write the velocity to the board, publish the ack),
and only the prioritised keys are: everything else, a flood above all, is queued on the network
thread in microseconds as before, or a flood from one peer would hold zenoh's thread (and the
holder's commands behind it, in zenoh's buffers) for the whole of its decoding.

Priority lane: samples on the keys given to ``prioritise`` (the agent gives its lease holder's
command keys: the key names the sender, so this needs no decoding) wait in a lane of their own
that the delivery thread empties first; then a second lane for the topics it names (the agent:
instant actions, so anyone's stop passes a flood of other commands); then the rest. A flood --
garbage or valid, any number of names -- queues behind the holder, never in front of it. Each key
stays in one lane while it is prioritised, so a sender's own order holds on each topic.

Pull subscriptions (``subscribe_pull``, the flight recorder's): for a reader that takes everything
in batches, samples wait in zenoh's own queue (a ``FifoChannel``) until ``drain`` takes them, each
with the time zenoh stamped it on arrival (a session opened with ``timestamping=True``), so no
Python runs on zenoh's thread per sample and no thread is woken per sample: for 1200 samples a
second, ~2.6 % of a core against ~8 % through a callback, the inbox and the delivery thread
(docs/recording.md "Cost").

The session is closed explicitly in ``close()`` when the endpoint opened it: zenoh runs
callbacks on non-daemon threads that would keep the process alive.
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, Self

from fleetlink.links.base import LinkStats, Receiver
from fleetlink.shared import keys
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.messages import LinkName
from fleetlink.shared.wire import MAX_PAYLOAD
from fleetlink.shared.worker import Worker

__all__ = [
    "INBOX_SIZE",
    "URGENT_TOPICS",
    "Answer",
    "LivelinessReceiver",
    "PullSubscription",
    "ZenohEndpoint",
    "open_session",
    "peer_config",
]

log = logging.getLogger(__name__)

URGENT_TOPICS = frozenset(
    {"ack", "events", "order", "actions", "teleop", "connection", "lease", "lease/request", "alarms/ack"}
)
"""Published express with INTERACTIVE_HIGH priority and congestion control BLOCK; the rest DROP.
Zenoh keeps order within a priority only: every operator command (lease requests too) is here,
so a lease request and the teleop after it arrive in the order they were sent."""

INBOX_SIZE = 1024
"""Samples waiting for the receivers; beyond this new ones are dropped and counted."""
PRIORITY_INBOX_SIZE = 256
"""Samples on prioritised keys waiting (``ZenohEndpoint.prioritise``), in a lane of their own."""
LANE_NAMES = ("priority", "second", "bulk")
"""The inbox's lanes, in the order they are served (module docstring: priority lane)."""

Answer = Callable[[str], list[tuple[str, bytes]]]
"""``answer(key_expr asked)`` -> the replies, as (key, payload)."""
LivelinessReceiver = Callable[[str, bool], None]
"""``on_change(token key, alive)`` (``ZenohEndpoint.watch_liveliness``)."""


MAX_MESSAGE_BYTES = MAX_PAYLOAD + 16 * 1024
"""What a Zenoh session reassembles at most: the largest wire payload plus room for the key and
zenoh's own framing."""


def peer_config(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    *,
    mode: str = "peer",
    multicast_scouting: bool = False,
    username: str | None = None,
    password: str | None = None,
    root_ca: str | None = None,
    tls_cert: str | None = None,
    tls_key: str | None = None,
    timestamping: bool = False,
) -> Any:
    """A ``zenoh.Config``: explicit endpoints, multicast scouting off unless asked for.

    With no ``listen`` endpoints the session listens nowhere (zenoh's default would be every
    interface). Sites link sessions by listing routers or peers explicitly (docs/operations.md).

    Security (a site router with deploy/zenohd.json5): ``username``/``password`` log in
    (``transport/auth/usrpwd``; the router's ACL knows agents by robot id, operators as
    ``op-<name>``); ``root_ca`` is the site CA that ``tls/<host>:<port>`` endpoints are verified
    against (the router's certificate must name ``<host>``); ``tls_cert``/``tls_key`` present a
    client certificate for mutual TLS.

    ``timestamping``: the session stamps every sample it receives without a timestamp with its
    hybrid logical clock, on zenoh's own thread (``ZenohEndpoint.subscribe_pull``: a receive time
    taken without running Python per sample).
    """
    import zenoh  # imported here so modules that only build configs stay importable without it

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    # Zenoh 1.x maps a 16 MB shared-memory pool into every process that sends a message over 3 kB
    # (a map patch) to a peer on the same host: +16 MB RSS per agent in bench/scale.py. Robots talk
    # across hosts, where it cannot help; the fleet's large messages are a few maps a second.
    conf.insert_json5("transport/shared_memory/enabled", "false")
    # No message larger than the wire contract's is even reassembled (zenoh's default is 1 GiB):
    # ten 10 MB puts grew an agent by 16 MB before its own size check could refuse them.
    conf.insert_json5("transport/link/rx/max_message_size", json.dumps(MAX_MESSAGE_BYTES))
    if timestamping:
        conf.insert_json5("timestamping/enabled", "true")
    if (username is None) != (password is None):
        raise ValueError("zenoh username and password go together (both or neither)")
    if username is not None:
        conf.insert_json5("transport/auth/usrpwd", json.dumps({"user": username, "password": password}))
    if (tls_cert is None) != (tls_key is None):
        raise ValueError("zenoh tls_cert and tls_key go together (both or neither)")
    tls = {"root_ca_certificate": root_ca, "connect_certificate": tls_cert, "connect_private_key": tls_key}
    for name, value in tls.items():
        if value is not None:
            conf.insert_json5(f"transport/link/tls/{name}", json.dumps(value))
    return conf


def open_session(listen: Sequence[str] = (), connect: Sequence[str] = (), **auth: Any) -> Any:
    """A ``zenoh.Session`` opened on ``peer_config(listen, connect, **auth)``."""
    import zenoh

    return zenoh.open(peer_config(listen, connect, **auth))


Item = tuple[Receiver, str, bytes]

PULL_CAPACITY = 16_384
"""Samples a pull subscription holds for its reader (over 10 s of 50 robots' traffic); when it is
full, zenoh's thread waits for the reader, as it waits for the GIL before a callback can queue."""


class PullSubscription:
    """Samples on ``key_expr`` kept in zenoh's own queue (a ``FifoChannel``) until ``drain`` takes
    them: no Python runs per sample on zenoh's thread, and no thread is woken per sample. For a
    reader that takes everything in batches (the flight recorder); order is arrival order.

    Each sample comes with its receive time (epoch seconds) from its zenoh timestamp: the time the
    first timestamping zenoh node received it (this session's, when the endpoint was opened with
    ``timestamping=True`` and the sample came peer to peer; a site router's, which stamps every
    sample it routes), or None when it has none (the reader stamps it when it takes it).

    Pulled samples bypass the endpoint's inbox, lanes and ``stats`` (the session's own limit on a
    message's size, ``MAX_MESSAGE_BYTES``, still holds: the reader checks the wire's)."""

    def __init__(self, key_expr: str, capacity: int) -> None:
        self.key_expr = key_expr
        self.capacity = capacity
        self.failed = 0
        """Drains that ended in an error (a session closing under the reader)."""
        self._sub: Any = None

    def drain(self, out: list[tuple[str, bytes, float | None]], limit: int = 1 << 30) -> int:
        """Append up to ``limit`` waiting samples to ``out`` as (key, payload, receive time);
        how many."""
        sub = self._sub
        if sub is None:
            return 0
        n = 0
        append = out.append
        try:
            while n < limit:
                sample = sub.try_recv()
                if sample is None:
                    break
                ts = sample.timestamp
                append(
                    (
                        str(sample.key_expr),
                        sample.payload.to_bytes(),
                        None if ts is None else ts.get_time_as_ntp64().as_secs_f64(),
                    )
                )
                n += 1
        except Exception as exc:  # the session closed under us (or a bug: said once)
            if not self.failed:
                log.warning("pull %s: %s", self.key_expr, exc)
            self.failed += 1
        return n


class _Inbox:
    """Bounded FIFO lanes: the priority lane, the second lane, the rest; a lane is served only
    while every one before it is empty. Thread-safe.

    Samples go to receivers one at a time, in arrival order: from the delivery thread (``get``,
    then ``done`` once delivered) or, when nothing is queued and nothing is being delivered, on
    the network thread itself (``claim``, then ``release``), during which ``get`` waits."""

    def __init__(self, size: int, priority_size: int = PRIORITY_INBOX_SIZE) -> None:
        self._cond = threading.Condition()
        self._lanes: tuple[deque[Item | None], ...] = (deque(), deque(), deque())
        self._sizes = (priority_size, priority_size, size)
        self._delivering = False  # the delivery thread has an item from get() it has not done()
        self._claimed = False  # a network thread is delivering a sample itself

    def size(self, lane: int) -> int:
        """How many samples ``lane`` holds at most."""
        return self._sizes[lane]

    def claim(self) -> bool:
        """True if the caller may hand its sample to the receiver itself (nothing queued, nothing
        being delivered, so nothing to overtake); ``release`` when it has."""
        with self._cond:
            if self._claimed or self._delivering or self._lanes[0] or self._lanes[1] or self._lanes[2]:
                return False
            self._claimed = True
            return True

    def release(self) -> None:
        with self._cond:
            self._claimed = False
            self._cond.notify()

    def done(self) -> None:
        """The delivery thread has delivered the item ``get`` gave it."""
        with self._cond:
            self._delivering = False

    def put(self, item: Item, lane: int = 2) -> bool:
        """Queue ``item`` in ``lane`` (0 the priority lane, 1 the second, 2 the rest); False (and
        nothing queued) if that lane is full."""
        with self._cond:
            if len(self._lanes[lane]) >= self._sizes[lane]:
                return False
            self._lanes[lane].append(item)
            self._cond.notify()
        return True

    def close(self) -> None:
        """The delivery thread ends after what is already queued."""
        with self._cond:
            self._lanes[-1].append(None)
            self._cond.notify()

    def get(self) -> Item | None:
        """The next item, waiting for one (and while a sample is delivered on a network thread);
        None once closed."""
        with self._cond:
            while True:
                if not self._claimed:
                    for lane in self._lanes:
                        if lane:
                            item = lane.popleft()
                            self._delivering = item is not None
                            return item
                self._cond.wait()


class _Delivery(Worker):
    """The one thread that hands queued samples to their receivers, priority lane first."""

    def __init__(self, name: str, inbox: _Inbox) -> None:
        super().__init__(name)
        self.inbox = inbox

    def run(self) -> None:
        while (item := self.inbox.get()) is not None:
            receiver, key, payload = item
            try:
                receiver(key, payload)
            except Exception:  # a receiver's bug must not stop delivery
                log.exception("zenoh receiver for %s failed", key)
            finally:
                self.inbox.done()

    def stop(self, timeout: float = 2.0) -> None:
        if self.running:
            self.inbox.close()
        super().stop(timeout)


class ZenohEndpoint:
    """A ``Link`` on one Zenoh session. See the module docstring.

    ``session``: use this open session instead of opening one (it is not closed by ``close``).
    Otherwise ``listen``, ``connect`` and ``auth`` (``peer_config``'s keywords: mode, username,
    password, root_ca, tls_cert, tls_key) say how to open it in ``start``. ``alive_key``: a
    liveliness token declared while the endpoint is open. ``direct``: a sample on a prioritised key
    that finds nothing queued and nothing being delivered goes to its receiver on zenoh's thread,
    without the hop to the delivery thread (the module docstring: direct delivery); for receivers
    that return in well under a millisecond (the agent's), never for one that may block.
    """

    name = LinkName.ZENOH

    def __init__(
        self,
        *,
        listen: Sequence[str] = (),
        connect: Sequence[str] = (),
        session: Any = None,
        alive_key: str | None = None,
        clock: Clock | None = None,
        inbox_size: int = INBOX_SIZE,
        label: str = "zenoh",
        direct: bool = False,
        **auth: Any,
    ) -> None:
        self.listen = tuple(listen)
        self.connect = tuple(connect)
        self.auth = auth
        self.alive_key = alive_key
        self.clock: Clock = clock or SystemClock()
        self.label = label
        self.stats = LinkStats()
        self._given = session
        self._session: Any = None
        self._subs: list[tuple[str, Receiver]] = []
        self._pulls: list[PullSubscription] = []
        self._served: list[tuple[str, Answer]] = []
        self._declared: list[Any] = []  # subscribers
        self._queryables: list[tuple[str, Any]] = []
        self._watches: list[tuple[str, LivelinessReceiver]] = []
        self._token: Any = None
        self._more_alive: list[str] = []
        self._more_tokens: list[Any] = []
        self._opts: dict[str, dict[str, Any]] = {}
        self._keyexprs: dict[str, Any] = {}  # key -> the session's declared key expression
        self._lock = threading.Lock()
        self._inbox = _Inbox(inbox_size)
        self.direct = direct
        self.delivered_direct = 0
        """Samples handed to their receiver on zenoh's thread (``direct``)."""
        self._priority: frozenset[str] = frozenset()
        self._second: frozenset[str] = frozenset()
        self._delivery: _Delivery | None = None

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        with self._lock:
            if self._session is not None:
                return
            self._delivery = _Delivery(f"{self.label}-in", self._inbox).start()
            try:
                session = (
                    self._given if self._given is not None else open_session(self.listen, self.connect, **self.auth)
                )
            except BaseException:
                self._delivery.stop()
                self._delivery = None
                raise
            self._session = session
            self._keyexprs = {}
            for key_expr, receiver in self._subs:
                self._declare_subscriber(key_expr, receiver)
            for pull in self._pulls:
                self._declare_pull(pull)
            for key_expr, answer in self._served:
                self._declare_queryable(key_expr, answer)
            for key_expr, on_change in self._watches:
                self._declare_liveliness(key_expr, on_change)
            if self.alive_key is not None:
                self._token = session.liveliness().declare_token(self.alive_key)
            self._more_tokens = [session.liveliness().declare_token(k) for k in self._more_alive]
        log.info("%s: listen %s connect %s", self.label, list(self.listen), list(self.connect))

    def close(self) -> None:
        with self._lock:
            session, self._session = self._session, None
            delivery, self._delivery = self._delivery, None
            declared, self._declared = self._declared, []
            declared += [q for _, q in self._queryables]
            self._queryables = []
            token, self._token = self._token, None
            more, self._more_tokens = self._more_tokens, []
        for pull in self._pulls:
            pull._sub = None  # (undeclared below, with the other subscribers)
        if session is None:
            return
        for d in [*declared, token, *more]:
            if d is not None:
                with contextlib.suppress(Exception):  # already gone with the session
                    d.undeclare()
        if delivery is not None:
            delivery.stop()  # what was queued before is still delivered; nothing after
        if self._given is None:
            session.close()

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def session(self) -> Any:
        """The open zenoh session (None before ``start`` and after ``close``)."""
        return self._session

    @property
    def up(self) -> bool:
        """The session is open and linked to at least one peer or router."""
        s = self._session
        if s is None or s.is_closed():
            return False
        try:
            return any(True for _ in s.info.peers_zid()) or any(True for _ in s.info.routers_zid())
        except Exception:  # a session closing under us
            return False

    # -- data -----------------------------------------------------------------------------------

    def publish(self, key: str, payload: bytes) -> bool:
        """Put ``payload`` on ``key`` (True once zenoh took it: it cannot say whether anyone listened)."""
        session = self._session
        if session is None:
            self.stats.dropped += 1
            return False
        try:
            session.put(self._keyexpr(session, key), payload, **self._options(key))
        except Exception as exc:  # zenoh.ZError, or closed under us; the other link still carries it
            self.stats.dropped += 1
            if self.stats.dropped == 1:
                log.warning("%s: publish on %s failed: %s", self.label, key, exc)
            return False
        self.stats.sent += 1
        return True

    def prioritise(self, priority_keys: frozenset[str], *, then_topics: frozenset[str] = frozenset()) -> None:
        """Samples on exactly ``priority_keys`` jump the queue (the module docstring: priority
        lane); then those whose message topic is in ``then_topics``, from anyone (the agent: instant
        actions, which carry stop, pause and e-stop); then the rest."""
        self._priority = priority_keys
        self._second = then_topics

    def _lane(self, key: str) -> int:
        if key in self._priority:
            return 0
        return 1 if self._second and keys.topic_of(key) in self._second else 2

    def subscribe(self, key_expr: str, receiver: Receiver) -> None:
        with self._lock:
            self._subs.append((key_expr, receiver))
            if self._session is not None:
                self._declare_subscriber(key_expr, receiver)

    def subscribe_pull(self, key_expr: str, capacity: int = PULL_CAPACITY) -> PullSubscription:
        """Samples on ``key_expr`` for the caller to take with ``drain`` (``PullSubscription``),
        instead of a receiver called per sample; declared again at every ``start``."""
        pull = PullSubscription(key_expr, capacity)
        with self._lock:
            self._pulls.append(pull)
            if self._session is not None:
                self._declare_pull(pull)
        return pull

    def add_alive(self, key: str) -> None:
        """Another liveliness token on ``key``, declared while the endpoint is open (as
        ``alive_key``): a simulator that speaks for many robots (field/light_runner.py) holds one each."""
        with self._lock:
            self._more_alive.append(key)
            if self._session is not None:
                self._more_tokens.append(self._session.liveliness().declare_token(key))

    def watch_liveliness(self, key_expr: str, on_change: LivelinessReceiver) -> None:
        """``on_change(key, alive)`` whenever a liveliness token matching ``key_expr`` appears
        (True) or goes (False: undeclared, or its session gone or cut off from this one); the tokens
        already there are reported when the watch is declared (at ``start``, or at once)."""
        with self._lock:
            self._watches.append((key_expr, on_change))
            if self._session is not None:
                self._declare_liveliness(key_expr, on_change)

    def serve(self, key_expr: str, answer: Answer) -> None:
        """A queryable on ``key_expr``: ``answer(key_expr asked)`` gives the replies (key, payload)."""
        with self._lock:
            self._served.append((key_expr, answer))
            if self._session is not None:
                self._declare_queryable(key_expr, answer)

    def unserve(self, key_expr: str) -> None:
        """Undeclare the queryables on exactly ``key_expr``; a restart will not declare them again."""
        with self._lock:
            self._served = [(k, a) for k, a in self._served if k != key_expr]
            gone = [q for k, q in self._queryables if k == key_expr]
            self._queryables = [(k, q) for k, q in self._queryables if k != key_expr]
        for q in gone:
            with contextlib.suppress(Exception):  # the session is closing
                q.undeclare()

    def query(self, key_expr: str, timeout: float = 1.0) -> list[tuple[str, bytes]]:
        """Ask the queryables on ``key_expr`` (waiting up to ``timeout`` s): their good replies."""
        session = self._session
        if session is None:
            return []
        out: list[tuple[str, bytes]] = []
        for reply in session.get(key_expr, timeout=timeout):
            if reply.ok is not None:
                out.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
            else:
                log.debug("%s: query %s: error reply: %s", self.label, key_expr, reply.err.payload.to_string())
        return out

    # -- internals (under self._lock) ---------------------------------------------------------

    def _declare_subscriber(self, key_expr: str, receiver: Receiver) -> None:
        import zenoh

        inbox = self._inbox

        def on_sample(sample: Any) -> None:
            # On zenoh's network thread: queue and return at once -- or, direct and with nothing
            # queued or being delivered, deliver it here.
            try:
                key = str(sample.key_expr)
                if not self.stats.admit(self.label, key, len(sample.payload)):
                    return  # refused before it is copied into Python
                payload = sample.payload.to_bytes()
                lane = self._lane(key)
                if lane == 0 and self.direct and inbox.claim():
                    self.stats.received += 1
                    self.stats.last_rx = self.clock.now()
                    self.delivered_direct += 1
                    try:
                        receiver(key, payload)
                    finally:
                        inbox.release()
                    return
                queued = inbox.put((receiver, key, payload), lane)
            except Exception:  # never let a bug kill zenoh's network thread
                log.exception("%s: sample callback failed", self.label)
                return
            if not queued:
                self.stats.dropped += 1
                if self.stats.dropped == 1:
                    log.warning(
                        "%s: inbox full (%s lane, %d samples): receivers not keeping up; dropping",
                        self.label,
                        LANE_NAMES[lane],
                        inbox.size(lane),
                    )
                return
            self.stats.received += 1
            self.stats.last_rx = self.clock.now()

        handler = zenoh.handlers.Callback(on_sample, indirect=False)
        self._declared.append(self._session.declare_subscriber(key_expr, handler))

    def _declare_pull(self, pull: PullSubscription) -> None:
        import zenoh

        sub = self._session.declare_subscriber(pull.key_expr, zenoh.handlers.FifoChannel(pull.capacity))
        self._declared.append(sub)
        pull._sub = sub

    def _declare_liveliness(self, key_expr: str, on_change: LivelinessReceiver) -> None:
        import zenoh

        def deliver(key: str, payload: bytes) -> None:
            on_change(key, payload == b"1")

        def on_sample(sample: Any) -> None:
            # On zenoh's network thread. In the second lane (with the stops): a presence change is
            # rare and small, and a flood in the bulk lane must not drop a robot's going or coming.
            try:
                alive = b"0" if sample.kind == zenoh.SampleKind.DELETE else b"1"
                queued = self._inbox.put((deliver, str(sample.key_expr), alive), lane=1)
            except Exception:  # never let a bug kill zenoh's network thread
                log.exception("%s: liveliness callback failed", self.label)
                return
            if not queued:
                self.stats.dropped += 1

        handler = zenoh.handlers.Callback(on_sample, indirect=False)
        self._declared.append(self._session.liveliness().declare_subscriber(key_expr, handler, history=True))

    def _declare_queryable(self, key_expr: str, answer: Answer) -> None:
        def on_query(query: Any) -> None:
            try:
                for key, payload in answer(str(query.key_expr)):
                    query.reply(key, payload)
            except Exception as exc:  # the querier went away, or a bad answer: keep serving
                log.debug("%s: answering %s: %s", self.label, key_expr, exc)

        self._queryables.append((key_expr, self._session.declare_queryable(key_expr, on_query)))

    def _keyexpr(self, session: Any, key: str) -> Any:
        """``key`` declared on ``session`` once (``declare_keyexpr``), then reused. A put on a plain
        string costs zenoh 1.10 time in proportion to the liveliness tokens the session knows:
        ~45 us with 500 (a light fleet's, or a console's view of a fleet) against 0.7 us declared
        (docs/operations.md, "Scale"). Routing is unchanged: unlike a declared publisher, a declared
        key expression is routed on every put, to subscribers that appear later too."""
        ke = self._keyexprs.get(key)
        if ke is None:
            if len(self._keyexprs) >= 4096:  # keys are a bounded set (robots x topics); past that, plain
                return key
            ke = self._keyexprs[key] = session.declare_keyexpr(key)
        return ke

    def _options(self, key: str) -> dict[str, Any]:
        opts = self._opts.get(key)
        if opts is None:
            import zenoh

            if keys.topic_of(key) in URGENT_TOPICS:
                opts = {
                    "congestion_control": zenoh.CongestionControl.BLOCK,
                    "priority": zenoh.Priority.INTERACTIVE_HIGH,
                    "express": True,
                }
            else:
                opts = {"congestion_control": zenoh.CongestionControl.DROP, "priority": zenoh.Priority.DATA}
            if len(self._opts) < 4096:  # keys are a bounded set (robots x topics); a cache, not a leak
                self._opts[key] = opts
        return opts
