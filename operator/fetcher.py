"""Snapshots fetched in the background for the console's followers (maps, dose layers): a worker
thread asks each robot a follower wants (``follower.wanted(now)``) through ``fetch(robot)`` (the
link's query) and hands the answer to ``follower.on_snapshot``; ``after_poll`` runs after each
round (the dose layers merge there). The followers are pure and decide what to ask; this moves it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Generic, Protocol, TypeVar

from fleetlink.shared.clock import Clock
from fleetlink.shared.worker import Worker

__all__ = ["SnapshotFetcher"]

log = logging.getLogger(__name__)

S = TypeVar("S")
S_contra = TypeVar("S_contra", contravariant=True)


class Follower(Protocol[S_contra]):
    forgotten: int
    """Bumped when the follower forgets its copies: a snapshot fetched before is not handed over."""

    def wanted(self, now: float) -> list[str]: ...

    def on_snapshot(self, robot: str, msg: S_contra) -> bool: ...


class SnapshotFetcher(Generic[S]):
    """A thread fetching the snapshots ``follower`` wants, through ``fetch(robot)``, every ``period_s``."""

    def __init__(
        self,
        what: str,
        follower: Follower[S],
        fetch: Callable[[str], S | None],
        clock: Clock,
        lock: threading.Lock,
        *,
        period_s: float = 0.5,
    ) -> None:
        self.what = what
        self.follower = follower
        self.fetch = fetch
        self.clock = clock
        self.lock = lock
        self.period_s = period_s
        self.fetched = 0
        self._worker = Worker(f"console-{what.replace(' ', '-')}", target=self._run)

    def start(self) -> SnapshotFetcher[S]:
        self._worker.start()
        return self

    def stop(self) -> None:
        self._worker.stop()

    def poll(self) -> int:
        """One round: fetch what is wanted now, then ``after_poll``. How many snapshots were taken."""
        with self.lock:
            robots = self.follower.wanted(self.clock.now())
            forgotten = self.follower.forgotten
        taken = 0
        for robot in robots:
            if self._worker.stopping:
                break
            try:
                snap = self.fetch(robot)
            except Exception as exc:  # a closed session on the way out, a zenoh error: try later
                log.debug("fetching %s's %s: %s", robot, self.what, exc)
                continue
            if snap is None:
                continue
            with self.lock:
                if self.follower.forgotten != forgotten:  # asked before a replay's seek back: too new
                    break
                if self.follower.on_snapshot(robot, snap):
                    taken += 1
        self.fetched += taken
        self.after_poll()
        return taken

    def after_poll(self) -> None:
        """What a follower's fetcher does after each round (nothing here)."""

    def _run(self, worker: Worker) -> None:
        while not worker.stopping:
            worker.wait(self.period_s)
            if worker.stopping:
                return
            try:
                self.poll()
            except Exception:  # keep following
                log.exception("%s fetch round failed", self.what)
