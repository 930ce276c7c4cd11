"""Test harness: private Mosquitto brokers, loopback Zenoh peers and small waiting helpers.

The pytest fixtures live in the submodules and are registered by ``tests/conftest.py``.
"""

from __future__ import annotations

import subprocess
import threading
import time
from collections.abc import Callable, Iterable

from tests.harness.mosquitto import MosquittoBroker, MosquittoNotFound, MosquittoStartError, find_mosquitto
from tests.harness.zenoh_peers import ZenohPeers, zenoh_config

__all__ = [
    "MosquittoBroker",
    "MosquittoNotFound",
    "MosquittoStartError",
    "StallWatch",
    "ZenohPeers",
    "end_child",
    "find_mosquitto",
    "leaked_threads",
    "wait_until",
    "zenoh_config",
]


def end_child(proc: subprocess.Popen[bytes]) -> None:
    """End a child process: close its stdin if we hold it (a child that ends at EOF), else terminate
    it; wait, and kill it if it hangs."""
    if proc.stdin is not None:
        proc.stdin.close()
    else:
        proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def wait_until(
    predicate: Callable[[], object],
    timeout: float = 10.0,
    interval: float = 0.02,
    message: str = "condition",
) -> None:
    """Poll ``predicate`` until it is truthy; raise AssertionError after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.1f}s waiting for {message}")
        time.sleep(interval)


def leaked_threads(before: Iterable[threading.Thread], grace: float = 2.0) -> list[threading.Thread]:
    """Non-daemon threads alive now that were not in ``before``, after joining them for ``grace`` s.

    Daemon threads are not reported (they cannot keep the interpreter alive); that also covers
    ``threading._DummyThread`` objects, which stand for threads started outside Python (e.g. by
    zenoh's Rust runtime) and cannot be joined. Zenoh's own callback threads are ordinary
    non-daemon ``pyo3-closure`` threads that end when their session is closed, so they need no
    exclusion: a session left open IS a leak (it hangs the process at exit).
    """
    known = set(before)
    suspects = [
        t for t in threading.enumerate() if t not in known and not t.daemon and t is not threading.main_thread()
    ]
    deadline = time.monotonic() + grace
    for t in suspects:
        t.join(max(0.0, deadline - time.monotonic()))
    return [t for t in suspects if t.is_alive()]


class StallWatch:
    """Notes when this process itself stalls (a thread that sleeps ``period_s`` and wakes late: CPU
    starvation on a loaded host, a long GIL hold), so a timing test can tell a gap its links made
    from one the whole process suffered (the sender, the links' threads and the receiver alike).

        with StallWatch() as watch:
            ...                                  # the timed part
        watch.stalled(t0, t1)                    # seconds of [t0, t1] (monotonic) the process stalled
    """

    def __init__(self, period_s: float = 0.005, late_s: float = 0.03) -> None:
        self.period_s = period_s
        self.late_s = late_s
        self.stalls: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stall-watch", daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            time.sleep(self.period_s)
            t1 = time.monotonic()
            if t1 - t0 > self.period_s + self.late_s:
                self.stalls.append((t0 + self.period_s, t1))

    def stalled(self, a: float, b: float) -> float:
        """Seconds of [a, b] that fall in a stall this watch noticed."""
        return sum(max(0.0, min(b, s1) - max(a, s0)) for s0, s1 in self.stalls)

    def __enter__(self) -> StallWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
