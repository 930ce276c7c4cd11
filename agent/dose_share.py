"""Dose sharing on a link: the adapter that serves the agent's dose layer and sends its patches.

    share = DoseShare(link, "r1", clock)   # link: a started Link with serve()/query() (Zenoh, in-process)
    share.start()                       # answers fleetlink/v1/r1/dose, publishes fleetlink/v1/r1/dose/updates
    ... share.publish(publication)      # what the dose keeper hands out (agent/dose_layer.py)
    share.stop()

As ``MapShare`` (agent/mapping/share.py) for maps: when to publish is the keeper's decision (every
second while the dose changes); the share only moves bytes. The query answer is a ``DoseSnapshot``
of the last publication, compressed when first asked for and kept until the next publication.
Before the first publication, and after ``stop``, it answers nothing. ``publish`` also sends a
``DoseUpdate`` with the rectangle that changed since the previous one; a receiver that missed one
or sees the layer grow asks for a snapshot (``dose_codec.SharedDose.apply`` returns False).

``fetch_dose(link, robot)`` is the asking side (used by ``fleetlink dose save``).
"""

from __future__ import annotations

import logging
import threading

from fleetlink.agent.dose_layer import DosePublication
from fleetlink.links.base import QueryLink
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.dose_codec import patch_fields, snapshot_fields
from fleetlink.shared.messages import DoseSnapshot, DoseUpdate

__all__ = ["DoseShare", "fetch_dose"]

log = logging.getLogger(__name__)


class DoseShare:
    def __init__(self, link: QueryLink, robot: str, clock: Clock, *, sender: str | None = None) -> None:
        keys.check_robot_id(robot)
        self.link = link
        self.robot = robot
        self.counter = wire.HeaderCounter(clock, robot=robot, sender=sender or f"agent-{robot}")
        self.dose_key = keys.key(robot, DoseSnapshot.TOPIC)
        self.updates_key = keys.key(robot, DoseUpdate.TOPIC)
        self._last: DosePublication | None = None
        self._snapshot: bytes | None = None  # its encoded DoseSnapshot, built on the first query
        self._serving = False
        self._started = False
        self._too_large_logged = False
        self._lock = threading.Lock()
        self.queries = 0
        self.updates = 0
        self.snapshots = 0

    def start(self) -> None:
        if self._started:
            return
        self._started = self._serving = True
        self.link.serve(self.dose_key, self._answer)

    def stop(self) -> None:
        """Stop answering and publishing (idempotent); the link stays open (its owner closes it)."""
        if self._serving:
            self._serving = False
            self.link.unserve(self.dose_key)

    def __enter__(self) -> DoseShare:
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
                fields = snapshot_fields(
                    last.dose, last.resolution, last.origin, last.version,
                    target_j_m2=last.target_j_m2, lamp_on_s=last.lamp_on_s, unplaced_s=last.unplaced_s,
                    lamp=last.lamp,
                )  # fmt: skip
                if fields is None:
                    if not self._too_large_logged:
                        self._too_large_logged = True
                        log.warning(
                            "%s: the dose layer (%s cells) does not fit one message", self.robot, last.dose.shape
                        )
                    return []
                self._snapshot = wire.encode(self.counter.make(DoseSnapshot, **fields))
                self.snapshots += 1
            data = self._snapshot
        return [] if data is None else [(self.dose_key, data)]

    def publish(self, pub: DosePublication) -> None:
        """Serve ``pub`` from now on; send the patch of what changed since the previous one."""
        with self._lock:
            prev, self._last, self._snapshot = self._last, pub, None
            if not self._serving or prev is None or pub.changed is None:
                return
            fields = patch_fields(
                pub.dose, pub.resolution, pub.origin, pub.changed, pub.version, prev.version,
                target_j_m2=pub.target_j_m2, lamp_on_s=pub.lamp_on_s, unplaced_s=pub.unplaced_s,
            )  # fmt: skip
            if fields is not None:
                self.link.publish(self.updates_key, wire.encode(self.counter.make(DoseUpdate, **fields)))
                self.updates += 1


def fetch_dose(link: QueryLink, robot: str, timeout: float = 5.0) -> DoseSnapshot | None:
    """Ask ``fleetlink/v1/<robot>/dose``; the first valid snapshot, or None (bad replies are logged)."""
    key = keys.key(robot, DoseSnapshot.TOPIC)
    for reply_key, payload in link.query(key, timeout):
        try:
            msg = wire.decode_key(reply_key, payload)
        except wire.WireError as exc:
            log.warning("dose query %s: rejected reply: %s", key, exc.reason)
            continue
        if isinstance(msg, DoseSnapshot):
            return msg
    return None
