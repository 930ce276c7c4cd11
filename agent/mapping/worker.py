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

One turn behind is what a robot sees anyway: its mapping thread finishes a turn while the next one
is being read. The keeper is deterministic and each robot's turns reach it in order, so
``DeferredKeeper`` and ``RemoteKeeper`` give byte-identical runs.
"""

from __future__ import annotations

from collections import deque
from typing import Protocol

from fleetlink.agent.mapping.keeper import MapKeeper, Turn, Update
from fleetlink.agent.mapping.mapper import MapperConfig
from fleetlink.shared.worker import ProcessWorker

__all__ = ["DeferredKeeper", "KeeperHost", "MapWorker", "RemoteKeeper"]


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
