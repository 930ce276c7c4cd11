"""A layer shared on a link: the adapter that serves an agent's layer (its map, its dose) as a
snapshot and sends patches of what changed. Generic over what the layer is.

    share = LayerShare(link, "r1", clock, MapSnapshot, MapUpdate, snapshot_of=..., patch_of=...)
    share.start()                  # answers fleetlink/v1/r1/<snapshot topic>, publishes .../updates
    ... share.publish(publication) # what the layer's keeper hands out
    share.stop()

When to publish is the keeper's decision; the share only moves bytes. The query answer is a
snapshot of the last publication (``snapshot_of(pub)``: the message's fields, or None when it does
not fit one message: logged once), compressed when first asked for and kept until the next
publication: most are never asked for, and compressing a whole layer is the costliest step. Before
the first publication, and after ``stop``, it answers nothing. ``publish`` also sends an update
(``patch_of(pub, previous)``: the rectangle that changed, or None for none); a receiver that missed
one or sees the layer grow asks for a snapshot. ``stop`` withdraws the answer from the link (a map
restarted in a new frame is served by a new share on the same key).

``fetch(link, robot, cls)`` is the asking side.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from typing import Any, Generic, TypeVar

from fleetlink.links.base import QueryLink
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock

__all__ = ["LayerShare", "fetch", "fetch_all"]

log = logging.getLogger(__name__)

P = TypeVar("P")
M = TypeVar("M", bound=wire.Message)
Fields = Mapping[str, Any]


class LayerShare(Generic[P]):
    def __init__(
        self,
        link: QueryLink,
        robot: str,
        clock: Clock,
        snapshot: type[wire.Message],
        update: type[wire.Message],
        *,
        snapshot_of: Callable[[P], Fields | None],
        patch_of: Callable[[P, P], Fields | None],
        sender: str | None = None,
    ) -> None:
        keys.check_robot_id(robot)
        self.link = link
        self.robot = robot
        self.clock = clock
        self.counter = wire.HeaderCounter(clock, robot=robot, sender=sender or f"agent-{robot}")
        self.snapshot_cls, self.update_cls = snapshot, update
        self.snapshot_key = keys.key(robot, snapshot.TOPIC)
        self.updates_key = keys.key(robot, update.TOPIC)
        self._snapshot_of, self._patch_of = snapshot_of, patch_of
        self._last: P | None = None
        self._snapshot: bytes | None = None  # the encoded snapshot of _last, built on the first query
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
        self.link.serve(self.snapshot_key, self._answer)

    def stop(self) -> None:
        """Stop answering and publishing (idempotent); the link stays open (its owner closes it)."""
        if self._serving:
            self._serving = False  # a query already in flight on the link's thread answers nothing
            self.link.unserve(self.snapshot_key)

    def __enter__(self) -> LayerShare[P]:
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
                fields = self._snapshot_of(last)
                if fields is None:
                    if not self._too_large_logged:
                        self._too_large_logged = True
                        log.warning("%s: its %s does not fit one message", self.robot, self.snapshot_cls.TOPIC)
                    return []
                self._snapshot = wire.encode(self.counter.make(self.snapshot_cls, **fields))
                self.snapshots += 1
            data = self._snapshot
        return [] if data is None else [(self.snapshot_key, data)]

    def publish(self, pub: P) -> None:
        """Serve ``pub`` from now on; send the patch of what changed since the previous one."""
        with self._lock:
            prev, self._last, self._snapshot = self._last, pub, None
            if not self._serving or prev is None:
                return
            fields = self._patch_of(pub, prev)
            if fields is not None:
                self.link.publish(self.updates_key, wire.encode(self.counter.make(self.update_cls, **fields)))
                self.updates += 1


def fetch(link: QueryLink, robot: str, cls: type[M], timeout: float = 5.0) -> M | None:
    """Ask ``fleetlink/v1/<robot>/<cls.TOPIC>``; the first valid ``cls`` reply, or None (bad replies
    are logged)."""
    replies = fetch_all(link, keys.key(robot, cls.TOPIC), cls, timeout, robot=robot)
    return replies[0] if replies else None


def fetch_all(
    link: QueryLink,
    key_expr: str,
    cls: type[M],
    timeout: float = 5.0,
    *,
    robot: str | None = None,
    rejected: list[str] | None = None,
) -> list[M]:
    """Ask ``key_expr``; every valid ``cls`` reply (about ``robot``, if given), in the order they came.
    Why each other reply was left out goes to ``rejected`` if given (the caller counts and logs), else
    to the log."""
    out: list[M] = []
    for reply_key, payload in link.query(key_expr, timeout):
        try:
            msg = wire.decode_key(reply_key, payload)
        except wire.WireError as exc:
            reason = f"rejected reply on {reply_key}: {exc.reason}"
        else:
            if isinstance(msg, cls) and (robot is None or msg.header.robot == robot):
                out.append(msg)
                continue
            reason = (
                f"a {type(msg).__name__} on {reply_key}, not a {cls.__name__}"
                if not isinstance(msg, cls)
                else f"a {cls.__name__} about {msg.header.robot!r} on {reply_key}, not about {robot!r}"
            )
        if rejected is not None:
            rejected.append(reason)
        else:
            log.warning("%s query %s: %s", cls.TOPIC, key_expr, reason)
    return out
