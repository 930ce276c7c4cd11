"""Where a map keeper runs: in line, one turn behind, or one turn behind in a second process.

``AgentNode`` hands each lidar turn to a ``KeeperHost`` and applies the ``Update`` it returns:

* ``MapKeeper`` itself (agent/mapping/keeper.py): the update of this very turn. The real-time
  agent maps on its own lidar thread, so nothing else waits for it.
* ``DeferredKeeper``: the update of the *previous* turn (None for the first). A lockstep run that
  maps in line uses it, so its outputs do not depend on where mapping runs.
* ``RemoteKeeper``, from ``MapWorker.keeper(robot)``: the same one-turn-behind contract, the
  keeper living in a second process (``ProcessWorker``). A lockstep run with many robots maps on
  the second core while the first steps physics, devices and agents; a turn's update is waited for
  only when the next turn arrives, a tenth of a simulated second later, by which time it is
  normally done.

Loop closure's checks (agent/mapping/closure.py) run where the keeper's ``search`` says: in line,
one node behind (``DeferredSearch``, the keeper's default: lockstep runs stay deterministic), or on
a thread of their own (``SearchWorker``, the real-time agent's): the lidar thread maps each turn
without waiting for a branch and bound, and takes the verdicts when the next node is made.

One turn behind is what a robot sees anyway: its mapping thread finishes a turn while the next one
is being read. The keeper is deterministic and each robot's turns reach it in order, so
``DeferredKeeper`` and ``RemoteKeeper`` give byte-identical runs.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from typing import Protocol

from fleetlink.agent.mapping.closure import Check, CheckResult, run_check
from fleetlink.agent.mapping.keeper import MapKeeper, Turn, Update
from fleetlink.agent.mapping.mapper import MapperConfig
from fleetlink.shared.clock import Clock
from fleetlink.shared.worker import ProcessWorker, Worker

__all__ = ["DeferredKeeper", "KeeperHost", "MapWorker", "RemoteKeeper", "SearchWorker"]

log = logging.getLogger(__name__)


class KeeperHost(Protocol):
    def add(self, turn: Turn) -> Update | None:
        """One turn in; an update out, or None (none yet)."""
        ...


class DeferredKeeper:
    """A keeper in line whose updates come one turn late (see the module docstring)."""

    def __init__(self, keeper: MapKeeper | None = None) -> None:
        self.keeper = keeper or MapKeeper()
        self._held: Update | None = None

    def add(self, turn: Turn) -> Update | None:
        held, self._held = self._held, self.keeper.add(turn)
        return held


class _Keepers:
    """The worker process's side: one keeper per robot."""

    def __init__(self) -> None:
        self.keepers: dict[str, MapKeeper] = {}

    def __call__(self, request: tuple[str, str, Turn | MapperConfig | None]) -> Update | None:
        kind, robot, item = request
        if kind == "open":
            self.keepers[robot] = MapKeeper(item if isinstance(item, MapperConfig) else None)
            return None
        assert isinstance(item, Turn)
        return self.keepers[robot].add(item)


class MapWorker:
    """A second process holding the map keepers of several robots. Close it (or use ``with``)."""

    def __init__(self) -> None:
        self._worker = ProcessWorker("fleetlink-map", _Keepers)
        self._waiting: dict[str, int] = {}  # robot -> its calls not yet taken
        self._order: deque[str] = deque()  # whose call each pending reply answers, oldest first
        self._replies: dict[str, list[Update | None]] = {}

    def keeper(self, robot: str, config: MapperConfig | None = None) -> RemoteKeeper:
        if robot in self._waiting:
            raise ValueError(f"the map worker holds {robot!r}'s keeper already")
        self._worker.tell(("open", robot, config))
        self._waiting[robot] = 0
        self._replies[robot] = []
        return RemoteKeeper(self, robot)

    def forget(self, robot: str) -> None:
        """Let ``robot``'s keeper go (its agent restarted): the replies still owed it are read and
        dropped, and ``keeper`` may open a new one under its name."""
        while self._waiting.get(robot, 0):
            self._take(robot)
        self._waiting.pop(robot, None)
        self._replies.pop(robot, None)

    def _submit(self, robot: str, request: tuple[str, str, Turn | MapperConfig | None]) -> None:
        self._worker.call(request)
        self._order.append(robot)
        self._waiting[robot] += 1

    def _take(self, robot: str) -> Update | None:
        """``robot``'s oldest reply, reading (and keeping) other robots' replies that come first."""
        while not self._replies[robot]:
            who = self._order.popleft()
            self._replies[who].append(self._worker.reply())
        self._waiting[robot] -= 1
        return self._replies[robot].pop(0)

    def close(self) -> None:
        self._worker.close()

    def __enter__(self) -> MapWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RemoteKeeper:
    """A robot's keeper in the ``MapWorker``'s process; updates come one turn late."""

    def __init__(self, worker: MapWorker, robot: str) -> None:
        self.worker = worker
        self.robot = robot

    def add(self, turn: Turn) -> Update | None:
        w = self.worker
        w._submit(self.robot, ("add", self.robot, turn))
        # The reply to this robot's previous turn, if there was one (this turn's is the newest).
        return w._take(self.robot) if w._waiting[self.robot] > 1 else None


class SearchWorker(Worker):
    """Loop closure's checks on a thread of their own (``ClosureSearch``; the real-time agent's): a
    batch submitted is run in order while the lidar thread maps on; its verdicts wait for
    ``collect``. One batch at a time (the mapper submits none while ``busy``): the search costs at
    most one thread's time, whatever the nodes' rate. A check that raises is logged and counts as
    found nothing. ``start()`` before use, ``stop()`` after (``Worker``)."""

    def __init__(self, name: str, clock: Clock | None = None) -> None:
        super().__init__(name, clock=clock, background=True)  # closures can wait: control cannot
        self._lock = threading.Lock()
        self._queue: deque[list[Check]] = deque()
        self._done: list[CheckResult] = []
        self._batches = 0  # submitted, verdicts not yet ready
        self.checks = 0
        self.failures = 0

    def submit(self, checks: list[Check]) -> None:
        with self._lock:
            self._queue.append(list(checks))
            self._batches += 1
        self.wake()

    def collect(self) -> list[CheckResult]:
        with self._lock:
            done, self._done = self._done, []
        return done

    @property
    def busy(self) -> bool:
        with self._lock:
            return self._batches > 0

    def run(self) -> None:
        while not self.stopping:
            with self._lock:
                batch = self._queue.popleft() if self._queue else None
            if batch is None:
                self.wait(1.0)  # woken by submit (or stop)
                continue
            results = []
            for check in batch:
                try:
                    results.append(run_check(check))
                except Exception as exc:  # a bug in one check must not end the search
                    self.failures += 1
                    if self.failures == 1:
                        log.exception("%s: a closure check failed: %s", self.name, exc)
                    results.append(CheckResult(check, None, "failed", None))
                self.checks += 1
            with self._lock:
                self._done.extend(results)
                self._batches -= 1
