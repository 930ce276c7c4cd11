"""The primary link: one Zenoh session, subscriptions on the agent's own input keys.

Thin: every sample's key and bytes go to ``on_input(LinkName.ZENOH, key, payload)``; the gate
does the rest. Telemetry goes out with congestion control DROP (a slow subscriber never stalls
the control loop); acks and events go express with high priority. Presence is a liveliness token
on ``fleetlink/v1/<robot>/alive``. The session is closed explicitly in ``stop()``: zenoh runs
callbacks on non-daemon threads that would keep the process alive.

Order: zenoh-python runs a plain Python callback on a thread of its own per subscriber, so
samples on different keys (a teleop, then a lease release) could reach the agent out of the
order they were sent in. Each subscriber's callback therefore runs on zenoh's network thread
(``indirect=False``) and only queues the sample; one delivery thread hands them to ``on_input``
in arrival order, so the network thread never waits on the agent.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from collections.abc import Callable, Sequence
from typing import Any

from fleetlink.shared import keys
from fleetlink.shared.messages import LinkName
from fleetlink.shared.zenoh_config import peer_config

log = logging.getLogger(__name__)

__all__ = ["ALIVE_TOPIC", "URGENT_TOPICS", "ZenohLink"]

ALIVE_TOPIC = "alive"
URGENT_TOPICS = frozenset({"ack", "events", "order", "actions", "teleop", "connection", "lease"})
"""Published express with INTERACTIVE_HIGH priority and congestion control BLOCK; the rest DROP."""

OnInput = Callable[[LinkName, str, bytes], None]

INBOX_SIZE = 1024
"""Samples waiting for the agent; beyond this (an agent stalled for seconds) new ones are dropped and counted."""


class ZenohLink:
    name = LinkName.ZENOH

    def __init__(
        self,
        robot: str,
        on_input: OnInput,
        *,
        listen: Sequence[str] = (),
        connect: Sequence[str] = (),
        inputs: Sequence[str] = ("order", "actions", "teleop"),
        extra_keys: Sequence[str] = (),
        mode: str = "peer",
        username: str | None = None,
        password: str | None = None,
        root_ca: str | None = None,
        tls_cert: str | None = None,
        tls_key: str | None = None,
    ) -> None:
        self.robot = keys.check_robot_id(robot)
        self.on_input = on_input
        self.listen = tuple(listen)
        self.connect = tuple(connect)
        self.mode = mode
        self._security: dict[str, Any] = {
            "username": username,
            "password": password,
            "root_ca": root_ca,
            "tls_cert": tls_cert,
            "tls_key": tls_key,
        }
        self.input_keys = [keys.key(robot, t) for t in inputs] + list(extra_keys)
        self._session: Any = None
        self._subs: list[Any] = []
        self._opts: dict[str, dict[str, Any]] = {}
        self._token: Any = None
        self._lock = threading.Lock()
        self._inbox: queue.Queue[tuple[str, bytes] | None] = queue.Queue(INBOX_SIZE)
        self._delivery: threading.Thread | None = None
        self.publish_errors = 0
        self.inbox_dropped = 0

    def start(self) -> None:
        import zenoh

        self._delivery = threading.Thread(target=self._deliver, name=f"zenoh-in-{self.robot}", daemon=True)
        self._delivery.start()
        self._session = zenoh.open(peer_config(self.listen, self.connect, mode=self.mode, **self._security))
        for k in self.input_keys:
            handler = zenoh.handlers.Callback(self._on_sample, indirect=False)
            self._subs.append(self._session.declare_subscriber(k, handler))
        self._token = self._session.liveliness().declare_token(keys.key(self.robot, ALIVE_TOPIC))
        log.info("zenoh link for %s: listen %s connect %s", self.robot, self.listen, self.connect)

    @property
    def session(self) -> Any:
        """The open zenoh session (None before ``start`` and after ``stop``): shared with the map share."""
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

    def publish(self, topic: str, payload: bytes) -> bool:
        session = self._session
        if session is None:
            return False
        try:
            session.put(keys.key(self.robot, topic), payload, **self._options(topic))
            return True
        except Exception as exc:  # zenoh.ZError; the other link still carries it
            self.publish_errors += 1
            if self.publish_errors == 1:
                log.warning("zenoh publish on %s failed: %s", topic, exc)
            return False

    def stop(self) -> None:
        with self._lock:
            session, self._session = self._session, None
            delivery, self._delivery = self._delivery, None
        if delivery is not None:
            with contextlib.suppress(queue.Full):
                self._inbox.put(None, timeout=1.0)
            delivery.join(timeout=2.0)
        if session is None:
            return
        for d in [*self._subs, self._token]:
            if d is None:
                continue
            with contextlib.suppress(Exception):  # already gone with the session
                d.undeclare()
        self._subs.clear()
        self._token = None
        session.close()

    # -- internals ------------------------------------------------------------------------------

    def _options(self, topic: str) -> dict[str, Any]:
        # Plain session.put, not declared publishers: behind a router with access control, a
        # publisher declared before a subscriber appears never learns of it (the router does not
        # forward the subscriber's declaration to the agent) and silently drops every sample.
        opts = self._opts.get(topic)
        if opts is None:
            import zenoh

            if topic in URGENT_TOPICS:
                opts = {
                    "congestion_control": zenoh.CongestionControl.BLOCK,
                    "priority": zenoh.Priority.INTERACTIVE_HIGH,
                    "express": True,
                }
            else:
                opts = {"congestion_control": zenoh.CongestionControl.DROP, "priority": zenoh.Priority.DATA}
            self._opts[topic] = opts
        return opts

    def _on_sample(self, sample: Any) -> None:
        # On zenoh's network thread: queue and return at once.
        try:
            self._inbox.put_nowait((str(sample.key_expr), sample.payload.to_bytes()))
        except queue.Full:
            self.inbox_dropped += 1
            if self.inbox_dropped == 1:
                log.warning("zenoh inbox full (%d samples): the agent is not keeping up; dropping input", INBOX_SIZE)
        except Exception:  # never let a bug kill zenoh's network thread
            log.exception("zenoh input callback failed")

    def _deliver(self) -> None:
        while (item := self._inbox.get()) is not None:
            try:
                self.on_input(self.name, *item)
            except Exception:  # a handler bug must not stop delivery
                log.exception("zenoh input handler failed")
