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
