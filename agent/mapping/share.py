"""Map sharing on a link: the agent's map served as a ``MapSnapshot`` and its patches sent as
``MapUpdate`` (agent/layer_share.py ``LayerShare`` moves the bytes).

    share = MapShare(link, "r1", clock)   # link: a started Link with serve()/query() (Zenoh, in-process)
    share.start()                      # answers fleetlink/v1/r1/map, publishes fleetlink/v1/r1/map/updates
    ... share.publish(update.publication)   # what the map keeper hands out (agent/mapping/keeper.py)
    share.stop()

When to publish is the keeper's decision (every ``SHARE_PERIOD_S`` while the map changes). The
snapshot is of the last publication's cells (a copy, so the link's query thread never touches the
mapper). A receiver that missed an update (``base_version`` mismatch) or sees the map grow asks for
a snapshot (``codec.SharedMap.apply`` returns False); a map too large for one message whole goes
out coarser, and then no patch is sent (the receivers' copy is coarser: it would not apply).

The share also serves the submaps the map is drawn from (after Cartographer's ``SubmapList`` and
``SubmapQuery``): ``fleetlink/v1/<robot>/map/submaps`` answers the list (``MapSubmaps``: each
submap's index, version and pose as the pose graph has it now), ``.../map/submap/<index>`` one
submap's cells (``MapSubmap``; ``.../map/submap/*`` every one). Nothing is published for them: the
fleet map (site/fleetmap.py) asks for the list as it builds and fetches only the submaps it lacks.
A map without submaps (loop closure off) answers an empty list: it still says the map's frame, so
the fleet map places a map in its own frame (no UWB) by search instead of taking it as the site's.

``fetch_map(link, robot)`` is the asking side (used by ``fleetlink map save``); ``fetch_submaps``
and ``fetch_submap`` for the submaps.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Mapping
from typing import Any

from fleetlink.agent.layer_share import LayerShare, fetch, fetch_all
from fleetlink.agent.mapping.fleetmap import Submap
from fleetlink.agent.mapping.keeper import MapPublication
from fleetlink.links.base import QueryLink
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.map_codec import decode_cells, fits_whole, patch_fields, snapshot_fields
from fleetlink.shared.messages import MAX_SUBMAPS, MapSnapshot, MapSubmap, MapSubmaps, MapUpdate, SubmapEntry

__all__ = ["MapShare", "fetch_map", "fetch_submap", "fetch_submaps", "submap_of"]

log = logging.getLogger(__name__)


def _snapshot(pub: MapPublication) -> Mapping[str, Any]:
    return snapshot_fields(pub.cells, pub.resolution, pub.origin, pub.version, pub.began)


def _patch(pub: MapPublication, prev: MapPublication) -> Mapping[str, Any] | None:
    if pub.changed is None or not fits_whole(pub.cells) or pub.began != prev.began:
        return None  # (a map begun again is fetched whole)
    return patch_fields(pub.cells, pub.resolution, pub.origin, pub.changed, pub.version, prev.version, pub.began)


class MapShare(LayerShare[MapPublication]):
    def __init__(self, link: QueryLink, robot: str, clock: Clock, *, sender: str | None = None) -> None:
        super().__init__(
            link, robot, clock, MapSnapshot, MapUpdate, snapshot_of=_snapshot, patch_of=_patch, sender=sender
        )
        self.list_key = keys.key(robot, MapSubmaps.TOPIC)
        self.submap_keys = keys.indexed_key(robot, MapSubmap.TOPIC, "*")
        self._sub_lock = threading.Lock()
        self._began = 0.0
        self._site_frame = False
        self._published = False  # a map has been shared: the list can say its frame, with or without submaps
        self._submaps: dict[int, Submap] = {}  # the latest drawing of each
        self._encoded: dict[int, bytes] = {}  # each submap's reply, made when first asked for
        self._poses: tuple[tuple[int, int, tuple[float, float, float]], ...] = ()
        self._list: bytes | None = None
        self.submap_queries = 0
        self.list_queries = 0

    def start(self) -> None:
        if self._started:
            return
        super().start()
        self.link.serve(self.list_key, self._answer_list)
        self.link.serve(self.submap_keys, self._answer_submaps)

    def stop(self) -> None:
        was = self._serving
        super().stop()
        if was:
            self.link.unserve(self.list_key)
            self.link.unserve(self.submap_keys)

    def publish(self, pub: MapPublication) -> None:
        with self._sub_lock:
            if (pub.began, pub.site_frame) != (self._began, self._site_frame) or not self._published:
                self._began, self._site_frame, self._published, self._list = pub.began, pub.site_frame, True, None
            if pub.submap_poses or pub.submaps:
                for sm in pub.submaps:
                    self._submaps[sm.index] = sm
                    self._encoded.pop(sm.index, None)
                # The newest MAX_SUBMAPS (a list that fits one message; a robot maps ~3 m per submap),
                # and only poses that can go on the wire (the mapper refuses non-finite poses: this is
                # so that one bad pose cannot silence the whole list).
                poses = [e for e in pub.submap_poses if all(math.isfinite(v) for v in e[2])][-MAX_SUBMAPS:]
                self._poses, self._list = tuple(poses), None
                listed = {i for i, _, _ in poses}
                for i in [i for i in self._submaps if i not in listed]:
                    del self._submaps[i]
                    self._encoded.pop(i, None)
        super().publish(pub)

    def _answer_list(self, _key_expr: str) -> list[tuple[str, bytes]]:
        if not self._serving:
            return []
        with self._sub_lock:
            self.list_queries += 1
            if not self._published:
                return []
            if self._list is None:
                entries = tuple(
                    SubmapEntry(index=i, version=v, x=p[0], y=p[1], theta=math.remainder(p[2], math.tau))
                    for i, v, p in self._poses
                )
                msg = self.counter.make(MapSubmaps, began=self._began, site_frame=self._site_frame, submaps=entries)
                self._list = wire.encode(msg)
            return [(self.list_key, self._list)]

    def _answer_submaps(self, key_expr: str) -> list[tuple[str, bytes]]:
        """``.../map/submap/<index>``: that submap; ``.../map/submap/*`` (or ``**``): every one; any
        other last segment (not an index as keys write it): none."""
        if not self._serving:
            return []
        last = key_expr.rpartition("/")[2]
        asked = None if last in ("*", "**") else keys.split_index(f"{MapSubmap.TOPIC}/{last}")[1]
        with self._sub_lock:
            self.submap_queries += 1
            if asked is None and last not in ("*", "**"):
                return []
            wanted = sorted(self._submaps) if asked is None else [asked] if asked in self._submaps else []
            todo = [(i, self._submaps[i], self._encoded.get(i)) for i in wanted]
            began = self._began
        # Compressed outside the lock (a first "every one" may be hundreds of submaps: the keeper's
        # publish must not wait for it); the bytes are kept unless a newer drawing came meanwhile.
        replies = []
        for i, sm, data in todo:
            if data is None:
                fields = snapshot_fields(sm.cells, sm.resolution, sm.origin, sm.version, began)
                x, y, th = sm.pose
                msg = self.counter.make(MapSubmap, index=i, x=x, y=y, theta=math.remainder(th, math.tau), **fields)
                data = wire.encode(msg)
                with self._sub_lock:
                    if self._submaps.get(i) is sm:
                        self._encoded[i] = data
            replies.append((keys.indexed_key(self.robot, MapSubmap.TOPIC, i), data))
        return replies


def fetch_map(link: QueryLink, robot: str, timeout: float = 5.0) -> MapSnapshot | None:
    """Ask ``fleetlink/v1/<robot>/map``; the first valid snapshot, or None (bad replies are logged)."""
    return fetch(link, robot, MapSnapshot, timeout)


def fetch_submaps(link: QueryLink, robot: str, timeout: float = 5.0) -> MapSubmaps | None:
    """Ask ``fleetlink/v1/<robot>/map/submaps``: the robot's submap list (empty from an agent
    without loop closure: its map is shared whole, the list says its frame), or None (no answer: no
    map shared yet, or an agent that predates submaps)."""
    return fetch(link, robot, MapSubmaps, timeout)


def fetch_submap(
    link: QueryLink, robot: str, index: int | str = "*", timeout: float = 5.0, *, rejected: list[str] | None = None
) -> list[MapSubmap]:
    """Ask ``fleetlink/v1/<robot>/map/submap/<index>`` (``*``: every submap): the valid replies. The
    reason for each reply left out goes to ``rejected`` if given (the caller counts and logs), else
    to the log."""
    key = keys.indexed_key(robot, MapSubmap.TOPIC, index)
    return fetch_all(link, key, MapSubmap, timeout, robot=robot, rejected=rejected)


def submap_of(msg: MapSubmap, pose: tuple[float, float, float] | None = None) -> Submap:
    """The submap a ``MapSubmap`` carries, at ``pose`` (the list's, newer) or its own; ValueError for
    cells that do not decode."""
    cells = decode_cells(msg.cells, msg.width, msg.height)
    return Submap(
        msg.index, msg.version, pose or (msg.x, msg.y, msg.theta), cells, msg.resolution, (msg.origin_x, msg.origin_y)
    )
