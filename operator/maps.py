"""The robots' onboard maps on the console: a snapshot per robot from its Zenoh queryable, then
its ``map/updates`` patches; a copy that misses a patch (or sees the map grow) is fetched again.

``MapFollower`` is pure (time passed in): it says which robots' maps to fetch (``wanted``), takes
snapshots and updates, and hands each changed map to the fleet model as a drawable grid.
``MapFetcher`` is the thin adapter: a worker thread that asks ``fetch(robot)`` (``OperatorLink.fetch_map``)
for the robots the follower wants. Map updates reach the follower through ``attach`` in
operator/console.py, like every other message.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np

from fleetlink.operator.fetcher import SnapshotFetcher
from fleetlink.operator.fleet import FleetModel, Grid
from fleetlink.shared.clock import Clock
from fleetlink.shared.keys import FLEET_MAP
from fleetlink.shared.map_codec import SharedMap
from fleetlink.shared.messages import MapSnapshot, MapUpdate

__all__ = ["MapFetcher", "MapFollower", "to_grid"]

log = logging.getLogger(__name__)

OCCUPIED_AT = 65  # map_server's occupied_thresh 0.65
FREE_AT = 25  # and free_thresh 0.25 (0.196 in ROS; cells here are 0 or 100 in practice)


def to_grid(shared: SharedMap) -> Grid:
    """A drawable grid: 100 occupied, 0 free, 255 unknown, row 0 at the bottom."""
    cells = shared.cells
    out = np.full(cells.shape, 255, dtype=np.uint8)
    out[(cells >= 0) & (cells <= FREE_AT)] = 0
    out[cells >= OCCUPIED_AT] = 100
    h, w = cells.shape
    return (shared.origin[0], shared.origin[1], shared.resolution, int(w), int(h), out.tobytes())


class MapFollower:
    """Which maps to fetch, and the copies kept current. Not thread-safe (the caller locks)."""

    def __init__(self, fleet: FleetModel, *, retry_s: float = 2.0) -> None:
        self.fleet = fleet
        self.retry_s = retry_s
        self.maps: dict[str, SharedMap] = {}
        self._stale: set[str] = set()
        """Robots heard publishing map updates whose copy is missing or behind: fetch them."""
        self._asked: dict[str, float] = {}
        self.rejected = 0
        self.forgotten = 0
        """Times ``forget`` was called: a snapshot fetched before it is dropped (operator/fetcher.py)."""

    def forget(self) -> None:
        """No copies, as a fresh follower (a replay seeking back: operator/feed.py ``FleetFeed.forget``)."""
        fresh = MapFollower(self.fleet, retry_s=self.retry_s)
        fresh.forgotten = self.forgotten + 1
        vars(self).update(vars(fresh))

    def on_update(self, msg: MapUpdate) -> bool:
        """A patch from ``map/updates``: applied (True), or the copy is marked for a fresh snapshot."""
        robot = msg.header.robot
        if robot == FLEET_MAP:
            return False  # a fleet map service's own: this side builds its fleet map from the robots'
        shared = self.maps.get(robot)
        if shared is None:
            self._stale.add(robot)
            return False
        try:
            applied = shared.apply(msg)
        except ValueError as exc:
            self.rejected += 1
            log.debug("map update from %s rejected: %s", robot, exc)
            applied = False
        if not applied:
            if msg.version > shared.version or msg.began != shared.began:
                # Missed one, the map grew, or its agent began a new map (its versions from 0
                # again): fetch the whole map.
                self._stale.add(robot)
            return False
        self.fleet.set_grid(robot, to_grid(shared))
        return True

    def on_snapshot(self, robot: str, msg: MapSnapshot) -> bool:
        if robot == FLEET_MAP:
            return False
        try:
            shared = SharedMap.from_snapshot(msg)
        except ValueError as exc:
            self.rejected += 1
            log.warning("map snapshot from %s rejected: %s", robot, exc)
            return False
        old = self.maps.get(robot)
        if old is not None and old.began == shared.began and old.version > shared.version:
            return False  # an older copy of the same map (another map replaces it, whatever its version)
        self.maps[robot] = shared
        self._stale.discard(robot)
        self.fleet.set_grid(robot, to_grid(shared))
        return True

    def wanted(self, now: float) -> list[str]:
        """Robots to fetch now: known robots with no map yet, and stale copies (at most every retry_s)."""
        robots = [r for r in self.fleet.robots if r not in self.maps] + sorted(self._stale)
        out = []
        for robot in dict.fromkeys(robots):
            if now - self._asked.get(robot, -1e9) >= self.retry_s:
                self._asked[robot] = now
                out.append(robot)
        return out


class MapFetcher(SnapshotFetcher[MapSnapshot]):
    """A thread fetching the snapshots ``follower`` wants, through ``fetch(robot)``."""

    def __init__(
        self,
        follower: MapFollower,
        fetch: Callable[[str], MapSnapshot | None],
        clock: Clock,
        lock: threading.Lock,
        *,
        period_s: float = 0.5,
        after_poll: Callable[[], object] | None = None,
    ) -> None:
        """``after_poll``: run after each fetch round (the fleet map service's ``step``)."""
        super().__init__("map", follower, fetch, clock, lock, period_s=period_s)
        self._after = after_poll

    def after_poll(self) -> None:
        if self._after is not None:
            self._after()
