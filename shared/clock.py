"""The one clock. Every component takes a Clock; nothing else reads the wall clock.

``SystemClock`` is the only place in fleetlink that calls ``time``. ``SimClock`` is advanced by its
owner (the field's lockstep loop), so many robots can run faster than real time and a seeded run
gives the same numbers twice.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "SimClock", "SystemClock"]

EVENT_POLL_S = 0.02
"""How often (real seconds) a thread waiting on a ``SimClock`` re-checks its event."""


@runtime_checkable
class Clock(Protocol):
    def now(self) -> float:
        """Monotonic seconds; only differences are meaningful."""
        ...

    def wall(self) -> float:
        """Seconds since the Unix epoch, for message timestamps only (never for timing)."""
        ...

    def sleep_until(self, deadline: float) -> None:
        """Return once ``now() >= deadline`` (at once if it already is)."""
        ...

    def wait(self, event: threading.Event, timeout: float | None) -> bool:
        """Block until ``event`` is set or ``timeout`` seconds of this clock's time pass.

        True if the event is set. The one interruptible wait: a worker sleeps here and wakes at
        once when it is stopped or woken, in real time and in simulated time alike, so no adapter
        asks which clock it has."""
        ...


class SystemClock:
    """Real time: ``time.monotonic`` for timing, ``time.time`` for timestamps."""

    def now(self) -> float:
        return time.monotonic()

    def wall(self) -> float:
        return time.time()

    def sleep_until(self, deadline: float) -> None:
        delay = deadline - time.monotonic()
        if delay > 0:
            time.sleep(delay)

    def sleep(self, seconds: float) -> None:
        self.sleep_until(self.now() + seconds)

    def wait(self, event: threading.Event, timeout: float | None) -> bool:
        return event.wait(None if timeout is None else max(0.0, timeout))


class SimClock:
    """Simulated time for lockstep runs.

    Time moves only through ``advance``/``set`` (the scheduler) or ``sleep_until`` (a single
    actor that is allowed to jump ahead). Threads blocked in ``wait_until`` wake when the owner
    advances time past their deadline, so threaded code can also run against it.
    """

    def __init__(self, start: float = 0.0, epoch: float = 1_767_225_600.0) -> None:
        # epoch: 2026-01-01T00:00:00Z, so simulated timestamps are plausible wall times.
        self._now = float(start)
        self._epoch = float(epoch)
        self._cond = threading.Condition()

    def now(self) -> float:
        return self._now

    def wall(self) -> float:
        return self._epoch + self._now

    def advance(self, dt: float) -> float:
        if dt < 0:
            raise ValueError(f"cannot advance a clock backwards (dt={dt})")
        return self.set(self._now + dt)

    def set(self, t: float) -> float:
        with self._cond:
            if t < self._now:
                raise ValueError(f"cannot move a clock backwards ({t} < {self._now})")
            self._now = float(t)
            self._cond.notify_all()
            return self._now

    def sleep_until(self, deadline: float) -> None:
        """Lockstep semantics: the caller owns time, so sleeping jumps straight to the deadline."""
        if deadline > self._now:
            self.set(deadline)

    def sleep(self, seconds: float) -> None:
        self.sleep_until(self._now + seconds)

    def wait(self, event: threading.Event, timeout: float | None) -> bool:
        """Block until ``event`` is set or the owner advances time by ``timeout``.

        The event is a plain ``threading.Event``, which cannot notify this clock's condition, so
        the wait re-checks it every ``EVENT_POLL_S`` of real time; advancing time wakes it at once."""
        if event.is_set():
            return True
        deadline = None if timeout is None else self._now + max(0.0, timeout)
        with self._cond:
            while not event.is_set():
                if deadline is not None and self._now >= deadline:
                    return False
                self._cond.wait(EVENT_POLL_S)
        return True

    def wait_until(self, deadline: float, timeout: float | None = None) -> bool:
        """Block a thread until another thread advances time to ``deadline``."""
        with self._cond:
            return self._cond.wait_for(lambda: self._now >= deadline, timeout)
