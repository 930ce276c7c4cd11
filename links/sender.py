"""A link's own send thread, for a link whose ``publish`` may wait on the network.

Zenoh puts a command with congestion control BLOCK (links/zenoh.py): when the session's transmit
queue towards some peer is full -- a peer that stopped reading (a frozen process, a radio that
stalls with its TCP connection still open) -- ``session.put`` waits for room, up to zenoh's
``wait_before_close`` (5 s), before it gives up on that peer. Whoever called ``publish`` waits
with it. An operator sending every command on both links (redundant sending) must not let one
link's wait hold up the other link's copy, nor the console.

``LinkSender`` is a ``Worker`` that owns a bounded FIFO of (key, payload) for one link and
publishes them in order on its own thread; ``submit`` only queues and returns. When the queue is
full (the link has been stuck for ``capacity`` messages) the *oldest* waiting message is dropped
and counted (``dropped``, and in the link's ``stats.dropped``; the first drop is logged): the
caller never waits, and what goes out once the link moves again is the newest. A dropped command
is the link manager's to re-send (operator/linkmanager.py), exactly as a lost one.

``needs_sender(link)`` says which links get one: every link except those whose ``publish``
only queues the bytes for a thread (or a pump) of their own, which they say with a class
attribute ``PUBLISH_QUEUES = True`` -- MQTT (paho hands the packet to the endpoint's loop thread,
links/mqtt.py), the in-process bus (queued until ``deliver``: lockstep runs stay deterministic).
A link that does not say so is assumed to be able to wait.
"""

from __future__ import annotations

import logging
import threading
from collections import deque

from fleetlink.links.base import Link
from fleetlink.shared.worker import Worker

__all__ = ["SEND_QUEUE", "LinkSender", "needs_sender"]

log = logging.getLogger(__name__)

SEND_QUEUE = 256
"""Messages a link's sender holds while its link is stuck (5 s of a console's commands at 50/s)."""


def needs_sender(link: object) -> bool:
    """Whether ``link.publish`` may wait on the network (no ``PUBLISH_QUEUES = True`` on its class)."""
    return not getattr(link, "PUBLISH_QUEUES", False)


class LinkSender(Worker):
    """Publishes what is submitted on ``link``, in order, on a thread of its own. Thread-safe."""

    def __init__(self, link: Link, capacity: int = SEND_QUEUE) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        super().__init__(f"{link.name.value}-send")
        self.link = link
        self.capacity = capacity
        self.dropped = 0
        """Messages dropped because the queue was full (the oldest waiting one each time)."""
        self.failed = 0
        """Messages the link refused or failed to send (``publish`` returned False or raised)."""
        self._queue: deque[tuple[str, bytes]] = deque()
        self._cond = threading.Condition()
        self._busy = False

    def submit(self, key: str, payload: bytes) -> bool:
        """Queue ``payload`` for ``key``; never waits. False if an older message had to be dropped
        to make room."""
        with self._cond:
            room = len(self._queue) < self.capacity
            if not room:
                self._queue.popleft()
                self.dropped += 1
                self.link.stats.dropped += 1
            self._queue.append((key, payload))
        if not room and self.dropped == 1:
            log.warning("%s: send queue full (%d), dropping the oldest; counting the rest", self.name, self.capacity)
        self.wake()
        return room

    @property
    def waiting(self) -> int:
        """Messages queued and not yet handed to the link."""
        with self._cond:
            return len(self._queue)

    def flush(self, timeout: float) -> bool:
        """Wait until everything submitted so far has been handed to the link (tests, shutdown);
        False if ``timeout`` real seconds passed first."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._queue and not self._busy, timeout)

    def run(self) -> None:
        # Stopping ends the loop only once the queue is empty: what was submitted before ``stop``
        # (a console's stop-all on quit) still goes out.
        while True:
            with self._cond:
                item = self._queue.popleft() if self._queue else None
                self._busy = item is not None
                if item is None:
                    self._cond.notify_all()
            if item is None:
                if self.stopping:
                    return
                self.wait(None)
                continue
            key, payload = item
            try:
                ok = self.link.publish(key, payload)
            except Exception as exc:  # a dead transport must not end the thread
                ok = False
                log.debug("%s: publish on %s failed: %s", self.name, key, exc)
            if not ok:
                self.failed += 1
