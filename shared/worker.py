"""One way to own a thread (``Worker``) or a second process (``ProcessWorker``).

``Worker``: start, stop, wake, error logging and join.

Every adapter that needs a thread (a board session's poll loop, an agent's control loop, a link's
delivery thread, a gateway's tick) subclasses ``Worker`` and writes only ``run``: a loop that
checks ``self.stopping`` and sleeps with ``self.wait(seconds)``. The wait is the clock's
(``Clock.wait``), so it is cut short by ``stop()`` or ``wake()`` in real and in simulated time
alike. An exception that escapes ``run`` is logged once with its traceback and kept in
``self.error``; it ends the thread, never the process. ``stop()`` is idempotent and joins.
``background=True`` runs the thread at a lower scheduling priority (``BACKGROUND_NICE``): work that
can lag (an agent's mapping) gives way, when the host is short of CPU, to what cannot (control,
links).

    class Ticker(Worker):
        def run(self) -> None:
            while not self.stopping:
                tick()
                self.wait(0.05)

``ProcessWorker``: a child process that owns a handler object and answers requests in the order
they were sent, so a lockstep run can use a second core and stay deterministic (the field's ray
casting, the agents' mapping). ``tell`` sends without a reply; ``call`` expects one, taken in order
with ``reply()``; nothing waits until a reply is needed. An exception in the handler comes back
as ``RuntimeError`` at its ``reply()``; the child goes on serving.

    worker = ProcessWorker("fleetlink-map", make_handler)   # make_handler() runs in the child
    worker.call(("add", ...)); ...; result = worker.reply()
    worker.close()
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import pickle
import threading
import traceback
from collections import deque
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any, Self

from fleetlink.shared.clock import Clock, SystemClock

__all__ = ["BACKGROUND_NICE", "ProcessWorker", "Worker"]

log = logging.getLogger(__name__)

JOIN_TIMEOUT_S = 5.0

BACKGROUND_NICE = 10
"""How much lower a background worker's thread runs (Linux nice, per thread; unprivileged: a
thread may always lower its own priority). At +10 the scheduler gives it about a tenth of the
share of a normal thread while both want the CPU, and all it wants when nothing else does."""


class Worker:
    """A thread with a lifecycle. Subclass and override ``run``, or pass ``target(worker)``."""

    def __init__(
        self,
        name: str,
        *,
        clock: Clock | None = None,
        target: Callable[[Worker], None] | None = None,
        daemon: bool = True,
        background: bool = False,
    ) -> None:
        self.name = name
        self.clock: Clock = clock or SystemClock()
        self._target = target
        self._daemon = daemon
        self.background = background
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
        if self.background:
            _lower_priority(self.name)
        try:
            self.run()
        except BaseException as exc:  # the thread ends; the process and the other workers go on
            self.error = exc
            log.exception("worker %s failed: %s", self.name, exc)


def _lower_priority(name: str) -> None:
    """This thread BACKGROUND_NICE lower (Linux: a nice value is per thread); elsewhere nothing."""
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + BACKGROUND_NICE))
    except (AttributeError, OSError) as exc:  # no setpriority (Windows), or refused: run as it is
        log.debug("worker %s keeps its priority: %s", name, exc)


_READY, _REPLY, _FAILED, _STOP = "ready", "reply", "failed", "stop"


def _serve(conn: Connection, make_handler: Callable[[], Callable[[Any], Any]]) -> None:
    """The child's loop: (wants_reply, request) in order; a reply for each call."""
    handler = make_handler()
    conn.send((_READY, None))
    while True:
        wants_reply, request = conn.recv()
        if wants_reply is None:  # stop
            conn.send((_STOP, None))
            return
        try:
            result = handler(request)
        except Exception:  # reported at the caller's reply(); the child serves on
            if wants_reply:
                conn.send((_FAILED, traceback.format_exc()))
            continue
        if wants_reply:
            try:
                conn.send((_REPLY, result))
            except (pickle.PicklingError, TypeError, AttributeError) as exc:  # a reply that cannot travel
                conn.send((_FAILED, f"the reply cannot be sent: {exc!r}"))


class ProcessWorker:
    """A second process serving requests in order. See the module docstring."""

    def __init__(self, name: str, make_handler: Callable[[], Callable[[Any], Any]]) -> None:
        # fork: the child needs only numpy, our pure cores and the pipe, and spawn would re-run the
        # parent's main module (and need a picklable ``make_handler``). Platforms without fork spawn.
        ctx: Any = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
        self.name = name
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, make_handler), name=name, daemon=True)
        self._proc.start()
        child.close()
        if self._conn.recv()[0] != _READY:
            raise RuntimeError(f"{name}: the worker process failed to start")
        self.pending = 0
        """Calls sent whose replies have not been taken by ``reply()``."""
        # Replies are read as they come by a thread of ours: a child writing a large reply must
        # never wait for us while we wait to write it a request (both ends would block for good).
        self._replies: deque[tuple[str, Any]] = deque()
        self._arrived = threading.Condition()
        self._reader = threading.Thread(target=self._read_replies, name=f"{name}-replies", daemon=True)
        self._reader.start()

    def tell(self, request: Any) -> None:
        """Send a request that has no reply."""
        self._conn.send((False, request))

    def call(self, request: Any) -> None:
        """Send a request; its reply comes, in order, from ``reply()``."""
        self._conn.send((True, request))  # a request that cannot be pickled raises here, nothing sent
        self.pending += 1

    def reply(self) -> Any:
        """The oldest call's reply, waiting for it if need be."""
        if not self.pending:
            raise RuntimeError(f"{self.name}: no call is waiting for a reply")
        with self._arrived:
            while not self._replies:
                if not self._reader.is_alive():
                    raise RuntimeError(f"{self.name}: the worker process is gone")
                self._arrived.wait(1.0)
            kind, value = self._replies.popleft()
        self.pending -= 1
        if kind == _FAILED:
            raise RuntimeError(f"{self.name}: the request failed in the worker:\n{value}")
        return value

    def close(self) -> None:
        """Stop the child (after it has served what was sent) and join it; idempotent."""
        if self._proc.is_alive():
            with contextlib.suppress(EOFError, OSError):
                self._conn.send((None, None))
            self._reader.join(10.0)  # it ends at the child's last word
            self._proc.join(5.0)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join(1.0)
        self._conn.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _read_replies(self) -> None:
        try:
            while True:
                kind, value = self._conn.recv()
                if kind == _STOP:
                    return
                with self._arrived:
                    self._replies.append((kind, value))
                    self._arrived.notify()
        except (EOFError, OSError):  # the child died, or we closed
            pass
        finally:
            with self._arrived:
                self._arrived.notify_all()
