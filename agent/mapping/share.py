"""Map sharing over Zenoh: the adapter around ``OnboardMapper`` (the only module here that does I/O).

    share = MapShare(session, "r1", clock)
    share.start()                      # queryable fleetlink/v1/r1/map, publisher fleetlink/v1/r1/map/updates
    ... share.publish(mapper)          # from the thread that owns the mapper, after add_scan (rate-limited)
    share.stop()

The queryable answers from a cached, already encoded ``MapSnapshot`` that ``publish`` refreshes (at
most every ``period`` seconds, when the map changed), so the Zenoh callback thread never touches
the mapper. ``publish`` also sends a ``MapUpdate`` with the rectangle that changed since the last
one; a receiver that missed one (``base_version`` mismatch) or sees the map grow asks the
queryable for a snapshot (``codec.SharedMap.apply`` returns False).

``fetch_map(session, robot)`` is the asking side (used by ``fleetlink map save``).
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from fleetlink.shared.map_codec import patch_fields, snapshot_fields
from fleetlink.agent.mapping.mapper import OnboardMapper
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import MapSnapshot, MapUpdate

__all__ = ["MapShare", "fetch_map"]

log = logging.getLogger(__name__)


class MapShare:
    def __init__(
        self, session: Any, robot: str, clock: Clock, *, sender: str | None = None, period: float = 1.0
    ) -> None:
        keys.check_robot_id(robot)
        self.session = session
        self.robot = robot
        self.clock = clock
        self.period = period
        self.counter = wire.HeaderCounter(clock, robot=robot, sender=sender or f"agent-{robot}")
        self.map_key = keys.key(robot, MapSnapshot.TOPIC)
        self.updates_key = keys.key(robot, MapUpdate.TOPIC)
        self._snapshot: bytes | None = None  # swapped atomically; read by the queryable callback
        self._queryable: Any = None
        self._publisher: Any = None
        self._last_version = -1
        self._last_geometry: tuple[float, float, float, int, int] | None = None
        self._next = -float("inf")
        self._lock = threading.Lock()
        self.queries = 0
        self.updates = 0
        self.snapshots = 0

    def start(self) -> None:
        if self._queryable is not None:
            return
        if hasattr(self.session, "serve"):  # a link (fleetlink.links): serve() and publish()
            link = self.session
            link.serve(self.map_key, self._answer)
            self._queryable = link
            self._publisher = _LinkPublisher(link, self.updates_key)
            return
        self._queryable = self.session.declare_queryable(self.map_key, self._on_query, complete=True)
        self._publisher = self.session.declare_publisher(self.updates_key)

    def _answer(self, asked: str) -> list[tuple[str, bytes]]:
        self.queries += 1
        data = self._snapshot
        return [] if data is None or self._queryable is None else [(self.map_key, data)]

    def stop(self) -> None:
        """Undeclare (idempotent); the session stays open (its owner closes it)."""
        q, p = self._queryable, self._publisher
        self._queryable = self._publisher = None
        for d in (q, p):
            if d is not None and hasattr(d, "undeclare"):
                try:
                    d.undeclare()
                except Exception as exc:  # a closed session: nothing left to undeclare
                    log.debug("undeclare: %s", exc)

    def __enter__(self) -> MapShare:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _on_query(self, query: Any) -> None:
        self.queries += 1
        data = self._snapshot
        try:
            if data is None:
                query.reply_err("no map yet")
            else:
                query.reply(self.map_key, data)
        except Exception as exc:  # the querier went away: nothing to do
            log.debug("map query reply failed: %s", exc)

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
            if self._publisher is not None and box is not None and self._last_version >= 0:
                fields = patch_fields(cells, res, origin, box, version, self._last_version)
                if fields is not None and snap.resolution == res:
                    upd = self.counter.make(MapUpdate, **fields)
                    self._publisher.put(wire.encode(upd))
                    self.updates += 1
            self._last_version = version
            self._last_geometry = geometry
            self._next = now + self.period
        return True


class _LinkPublisher:
    def __init__(self, link: Any, key: str) -> None:
        self.link, self.key = link, key

    def put(self, data: bytes) -> None:
        self.link.publish(self.key, data)


def fetch_map(session: Any, robot: str, timeout: float = 5.0) -> MapSnapshot | None:
    """Ask ``fleetlink/v1/<robot>/map``; the first valid snapshot, or None (bad replies are logged)."""
    key = keys.key(robot, MapSnapshot.TOPIC)
    for reply in session.get(key, timeout=timeout):
        if reply.ok is None:
            log.warning("map query %s: error reply: %s", key, reply.err.payload.to_string())
            continue
        sample = reply.ok
        try:
            msg = wire.decode_key(str(sample.key_expr), sample.payload.to_bytes())
        except wire.WireError as exc:
            log.warning("map query %s: rejected reply: %s", key, exc.reason)
            continue
        if isinstance(msg, MapSnapshot):
            return msg
    return None
