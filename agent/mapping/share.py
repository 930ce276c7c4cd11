"""Map sharing on a link: the adapter around ``OnboardMapper`` (the only module here that does I/O).

    share = MapShare(link, "r1", clock)   # link: a started Link with serve()/query() (Zenoh, in-process)
    share.start()                      # answers fleetlink/v1/r1/map, publishes fleetlink/v1/r1/map/updates
    ... share.publish(mapper)          # from the thread that owns the mapper, after add_scan (rate-limited)
    share.stop()

The query answer is a cached, already encoded ``MapSnapshot`` that ``publish`` refreshes (at most
every ``period`` seconds, when the map changed), so the link's query thread never touches the
mapper; before the first snapshot, and after ``stop``, it answers nothing. ``publish`` also sends a
``MapUpdate`` with the rectangle that changed since the last one; a receiver that missed one
(``base_version`` mismatch) or sees the map grow asks for a snapshot (``codec.SharedMap.apply``
returns False).

A link cannot withdraw what it serves, so a stopped share keeps its (silent) answer registered
until the link closes: a map restarted in a new frame costs one idle queryable.

``fetch_map(link, robot)`` is the asking side (used by ``fleetlink map save``).
"""

from __future__ import annotations

import logging
import threading

from fleetlink.agent.mapping.mapper import OnboardMapper
from fleetlink.links.base import QueryLink
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.map_codec import patch_fields, snapshot_fields
from fleetlink.shared.messages import MapSnapshot, MapUpdate

__all__ = ["MapShare", "fetch_map"]

log = logging.getLogger(__name__)


class MapShare:
    def __init__(
        self, link: QueryLink, robot: str, clock: Clock, *, sender: str | None = None, period: float = 1.0
    ) -> None:
        keys.check_robot_id(robot)
        self.link = link
        self.robot = robot
        self.clock = clock
        self.period = period
        self.counter = wire.HeaderCounter(clock, robot=robot, sender=sender or f"agent-{robot}")
        self.map_key = keys.key(robot, MapSnapshot.TOPIC)
        self.updates_key = keys.key(robot, MapUpdate.TOPIC)
        self._snapshot: bytes | None = None  # swapped atomically; read by the link's query thread
        self._serving = False
        self._started = False
        self._last_version = -1
        self._last_geometry: tuple[float, float, float, int, int] | None = None
        self._next = -float("inf")
        self._lock = threading.Lock()
        self.queries = 0
        self.updates = 0
        self.snapshots = 0

    def start(self) -> None:
        if self._started:
            return
        self._started = self._serving = True
        self.link.serve(self.map_key, self._answer)

    def stop(self) -> None:
        """Stop answering and publishing (idempotent); the link stays open (its owner closes it)."""
        self._serving = False

    def __enter__(self) -> MapShare:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _answer(self, _key_expr: str) -> list[tuple[str, bytes]]:
        data = self._snapshot
        if not self._serving:
            return []
        self.queries += 1
        return [] if data is None else [(self.map_key, data)]

    def publish(self, mapper: OnboardMapper, force: bool = False) -> bool:
        """Refresh the snapshot and publish an update if the map changed and ``period`` has passed."""
        now = self.clock.now()
        if not force and (now < self._next or mapper.version == self._last_version):
            return False
        with self._lock:
            cells, res, origin = mapper.occupancy()
            version = mapper.version
            snap = self.counter.make(MapSnapshot, **snapshot_fields(cells, res, origin, version))
            self._snapshot = wire.encode(snap)
            self.snapshots += 1
            box = mapper.grid.take_dirty()
            geometry = (res, origin[0], origin[1], int(cells.shape[0]), int(cells.shape[1]))
            if self._serving and box is not None and self._last_version >= 0:
                fields = patch_fields(cells, res, origin, box, version, self._last_version)
                if fields is not None and snap.resolution == res:
                    upd = self.counter.make(MapUpdate, **fields)
                    self.link.publish(self.updates_key, wire.encode(upd))
                    self.updates += 1
            self._last_version = version
            self._last_geometry = geometry
            self._next = now + self.period
        return True


def fetch_map(link: QueryLink, robot: str, timeout: float = 5.0) -> MapSnapshot | None:
    """Ask ``fleetlink/v1/<robot>/map``; the first valid snapshot, or None (bad replies are logged)."""
    key = keys.key(robot, MapSnapshot.TOPIC)
    for reply_key, payload in link.query(key, timeout):
        try:
            msg = wire.decode_key(reply_key, payload)
        except wire.WireError as exc:
            log.warning("map query %s: rejected reply: %s", key, exc.reason)
            continue
        if isinstance(msg, MapSnapshot):
            return msg
    return None
