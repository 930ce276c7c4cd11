"""One way to own a thread: start, stop, wake, error logging and join.

Every adapter that needs a thread (a board session's poll loop, an agent's control loop, a link's
delivery thread, a gateway's tick) subclasses ``Worker`` and writes only ``run``: a loop that
checks ``self.stopping`` and sleeps with ``self.wait(seconds)``. The wait is the clock's
(``Clock.wait``), so it is cut short by ``stop()`` or ``wake()`` in real and in simulated time
alike. An exception that escapes ``run`` is logged once with its traceback and kept in
``self.error``; it ends the thread, never the process. ``stop()`` is idempotent and joins.

    class Ticker(Worker):
        def run(self) -> None:
            while not self.stopping:
                tick()
                self.wait(0.05)
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Self

from fleetlink.shared.clock import Clock, SystemClock

__all__ = ["Worker"]

log = logging.getLogger(__name__)

JOIN_TIMEOUT_S = 5.0


class Worker:
    """A thread with a lifecycle. Subclass and override ``run``, or pass ``target(worker)``."""

    def __init__(
        self,
        name: str,
        *,
        clock: Clock | None = None,
        target: Callable[[Worker], None] | None = None,
        daemon: bool = True,
    ) -> None:
        self.name = name
        self.clock: Clock = clock or SystemClock()
        self._target = target
        self._daemon = daemon
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        """What ended ``run`` with an exception, if anything did."""

    # -- for the owner ----------------------------------------------------------------------------

    def start(self) -> Self:
        if self._thread is not None:
            raise RuntimeError(f"worker {self.name} already started")
        self._stop.clear()
        self._thread = threading.Thread(target=self._main, name=self.name, daemon=self._daemon)
        self._thread.start()
        return self

    def stop(self, timeout: float = JOIN_TIMEOUT_S) -> None:
        """Ask ``run`` to end, wake it, and join (idempotent; a no-op if never started)."""
        self._stop.set()
        self._wake.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
            if thread.is_alive():
                log.warning("worker %s did not stop within %.1f s", self.name, timeout)

    def wake(self) -> None:
        """Cut the current ``wait`` short (new work has come)."""
        self._wake.set()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- for run() --------------------------------------------------------------------------------

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def wait(self, timeout: float | None) -> bool:
        """Sleep up to ``timeout`` seconds of the clock's time; True if woken or stopped early."""
        woken = self.clock.wait(self._wake, timeout)
        self._wake.clear()
        if self._stop.is_set():
            self._wake.set()  # a stopped worker never sleeps again
        return woken

    def run(self) -> None:
        if self._target is None:
            raise NotImplementedError("override run() or pass target=")
        self._target(self)

    def _main(self) -> None:
        try:
            self.run()
        except BaseException as exc:  # the thread ends; the process and the other workers go on
            self.error = exc
            log.exception("worker %s failed: %s", self.name, exc)
