"""Map sharing on a link: the adapter that serves the agent's map and sends its patches.

    share = MapShare(link, "r1", clock)   # link: a started Link with serve()/query() (Zenoh, in-process)
    share.start()                      # answers fleetlink/v1/r1/map, publishes fleetlink/v1/r1/map/updates
    ... share.publish(update.publication)   # what the map keeper hands out (agent/mapping/keeper.py)
    share.stop()

When to publish is the keeper's decision (every ``SHARE_PERIOD_S`` while the map changes); the
share only moves bytes. The query answer is a ``MapSnapshot`` of the last publication's cells (a
copy, so the link's query thread never touches the mapper), compressed when first asked for and
kept until the next publication: most are never asked for, and compressing a whole map is the
costliest step. Before the first publication, and after ``stop``, it answers nothing. ``publish``
also sends a ``MapUpdate`` with the rectangle that changed since the previous one; a receiver
that missed one (``base_version`` mismatch) or sees the map grow asks for a snapshot
(``codec.SharedMap.apply`` returns False).

``stop`` withdraws the answer from the link (a map restarted in a new frame is served by a new
share on the same key).

``fetch_map(link, robot)`` is the asking side (used by ``fleetlink map save``).
"""

from __future__ import annotations

import logging
import threading

from fleetlink.agent.mapping.keeper import MapPublication
from fleetlink.links.base import QueryLink
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.map_codec import fits_whole, patch_fields, snapshot_fields
from fleetlink.shared.messages import MapSnapshot, MapUpdate

__all__ = ["MapShare", "fetch_map"]

log = logging.getLogger(__name__)


class MapShare:
    def __init__(self, link: QueryLink, robot: str, clock: Clock, *, sender: str | None = None) -> None:
        keys.check_robot_id(robot)
        self.link = link
        self.robot = robot
        self.clock = clock
        self.counter = wire.HeaderCounter(clock, robot=robot, sender=sender or f"agent-{robot}")
        self.map_key = keys.key(robot, MapSnapshot.TOPIC)
        self.updates_key = keys.key(robot, MapUpdate.TOPIC)
        self._last: MapPublication | None = None
        self._snapshot: bytes | None = None  # its encoded MapSnapshot, built on the first query
        self._serving = False
        self._started = False
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
        if self._serving:
            self._serving = False  # a query already in flight on the link's thread answers nothing
            self.link.unserve(self.map_key)

    def __enter__(self) -> MapShare:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _answer(self, _key_expr: str) -> list[tuple[str, bytes]]:
        if not self._serving:
            return []
        with self._lock:
            self.queries += 1
            last = self._last
            if self._snapshot is None and last is not None:
                fields = snapshot_fields(last.cells, last.resolution, last.origin, last.version)
                snap = self.counter.make(MapSnapshot, **fields)
                self._snapshot = wire.encode(snap)
                self.snapshots += 1
            data = self._snapshot
        return [] if data is None else [(self.map_key, data)]

    def publish(self, pub: MapPublication) -> None:
        """Serve ``pub`` from now on; send the patch of what changed since the previous one."""
        with self._lock:
            prev, self._last, self._snapshot = self._last, pub, None
            if not self._serving or prev is None or pub.changed is None:
                return
            if not fits_whole(pub.cells):  # receivers hold a coarser copy: the patch would not apply
                return
            fields = patch_fields(pub.cells, pub.resolution, pub.origin, pub.changed, pub.version, prev.version)
            if fields is not None:
                self.link.publish(self.updates_key, wire.encode(self.counter.make(MapUpdate, **fields)))
                self.updates += 1


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
