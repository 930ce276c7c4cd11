"""Marks shared between consoles, so that one that joins late -- or restarts -- has them all, with
either link down.

``MarkSharing(link, fleet, lock)`` does three things for one console:

* **Retained sets on MQTT.** For every robot it marked under, the console keeps one retained
  ``MarkSet`` on ``fleetlink/v1/<robot>/marks/set/<login>``: every mark whose newest version this
  login wrote under that robot, removed ones included (``marks.own_sets``). It is published when
  that set changes (a mark placed, edited or removed here, or one of ours edited elsewhere) and
  after every (re)connect (a broker restarted without persistence has forgotten it). A console
  subscribing to ``fleetlink/v1/#`` gets every console's sets from the broker at once, with no
  other console up and Zenoh down. Our own sets come back too: a console restarted without its
  marks file gets its marks from them, and one whose marks were since edited elsewhere replaces
  its stale set (the model keeps the last set heard per console and robot, ``mark_sets``: what
  the broker holds is compared with what it should hold).
* **Zenoh queries.** It answers ``fleetlink/v1/*/marks/<login>`` with this console's marks and
  asks ``fleetlink/v1/*/marks/*`` a few times after start (peers take a moment to find each other).
* Live ``Mark``s go out on both links when they are placed (the console does that, operator/console.py).

Everything heard goes into the fleet model through the console's feed and is merged there by
``markId`` (operator/marks.py ``supersedes``). A worker looks for changed sets ``check_hz`` times a
second (when the model's ``marks_version`` moved), and at once when ``wake()``-d; publishing waits
for nothing the UI holds. Sets are computed from the model alone, under its lock, so a set is
never published without marks the model has heard.

With ``publish=False`` (a read-only console) it only answers and asks.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from typing import Protocol, Self

from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.marks import SetTracker, own_sets, set_message
from fleetlink.shared import wire
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.messages import Mark, MarkSet
from fleetlink.shared.worker import Worker

__all__ = ["MarkLink", "MarkSharing"]

log = logging.getLogger(__name__)

ASKS_S = (0.5, 2.0, 6.0)
"""When (seconds after start) a console asks the others for their marks over Zenoh."""


class MarkLink(Protocol):
    """What marks sharing needs from the console's link (``OperatorLink`` provides it)."""

    sender: str

    def serve_marks(self, marks: Callable[[], Sequence[Mark]]) -> None: ...

    def fetch_marks(self, timeout: float = ...) -> int: ...

    def publish_retained(self, msg: wire.Message) -> bool: ...

    def add_connect_listener(self, listener: Callable[[], object]) -> None: ...


class MarkSharing:
    def __init__(
        self,
        link: MarkLink,
        fleet: FleetModel,
        lock: threading.Lock,
        *,
        clock: Clock | None = None,
        publish: bool = True,
        asks: Sequence[float] = ASKS_S,
        check_hz: float = 4.0,
    ) -> None:
        self.link = link
        self.fleet = fleet
        self.lock = lock
        self.login = link.sender
        self.clock: Clock = clock or getattr(link, "clock", None) or SystemClock()
        self.publish = publish
        self.asks = tuple(asks)
        self.check_s = 1.0 / check_hz
        self.published = 0
        """Sets the broker took so far."""
        self._counter: wire.HeaderCounter = getattr(link, "counter", None) or wire.HeaderCounter(
            self.clock, robot="operator", sender=self.login
        )
        self._tracker = SetTracker()
        self._state = threading.Lock()
        self._dirty = True
        self._seen_version = -1
        self._publisher = Worker("console-mark-sets", clock=self.clock, target=self._publish_loop)
        self._asker = Worker("console-marks-ask", clock=self.clock, target=self._ask_loop)

    # -- lifecycle --------------------------------------------------------------------------------

    def start(self) -> Self:
        self.link.serve_marks(self._all_marks)
        if self.publish:
            self.link.add_connect_listener(self._on_connect)
            self._publisher.start()
        if self.asks:
            self._asker.start()
        return self

    def stop(self) -> None:
        """Stop asking and publishing; a set changed since the last check goes out first (call
        before the link closes)."""
        self._asker.stop()
        running = self._publisher.running
        self._publisher.stop()
        if running:
            try:
                self.publish_due()
            except Exception as exc:  # the link may be closing: the next start publishes them all
                log.debug("last marks sets not sent: %s", exc)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def wake(self) -> None:
        """This console's marks changed: look at the sets now rather than at the next check."""
        with self._state:
            self._dirty = True
        self._publisher.wake()

    # -- the retained sets --------------------------------------------------------------------------

    def _all_marks(self) -> list[Mark]:
        with self.lock:
            return list(self.fleet.marks.values())

    def _on_connect(self) -> None:
        with self._state:
            self._tracker.resend()
            self._dirty = True
        self._publisher.wake()

    def publish_due(self) -> int:
        """Publish the sets that changed (or all of them after a connect); how many went out."""
        with self.lock:
            version = self.fleet.marks_version
            with self._state:
                if version == self._seen_version and not self._dirty:
                    return 0
                self._dirty = False
                self._seen_version = version
                # Our sets as the broker returned them (from before a restart), and the marks
                # they hold, come from the same model: never a set computed without them.
                for (robot, sender), held in self.fleet.mark_sets.items():
                    if sender == self.login:
                        self._tracker.heard(robot, held)
                sets = own_sets(self.fleet.marks.values(), self.login)
                due = self._tracker.due(sets)
        sent = 0
        for robot, marks in due:
            msg = set_message(self._counter.header(MarkSet.TOPIC, robot=robot), marks)
            if self.link.publish_retained(msg):
                sent += 1
                with self._state:
                    self._tracker.sent(robot, marks)
            else:  # down: every set goes again after the next connect
                log.debug("marks set for %s not sent (MQTT down)", robot)
        self.published += sent
        return sent

    def _publish_loop(self, worker: Worker) -> None:
        while not worker.stopping:
            try:
                self.publish_due()
            except Exception:  # keep sharing: one bad round must not stop it for good
                log.exception("publishing the marks sets failed")
            worker.wait(self.check_s)

    # -- Zenoh queries ------------------------------------------------------------------------------

    def _ask_loop(self, worker: Worker) -> None:
        waited = 0.0
        for at in self.asks:
            worker.wait(max(0.0, at - waited))
            if worker.stopping:
                return
            waited = at
            try:
                self.link.fetch_marks()
            except Exception as exc:  # closed on the way out: nothing to ask any more
                log.debug("asking for marks: %s", exc)
