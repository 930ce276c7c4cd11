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

``fetch_map(link, robot)`` is the asking side (used by ``fleetlink map save``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from fleetlink.agent.layer_share import LayerShare, fetch
from fleetlink.agent.mapping.keeper import MapPublication
from fleetlink.links.base import QueryLink
from fleetlink.shared.clock import Clock
from fleetlink.shared.map_codec import fits_whole, patch_fields, snapshot_fields
from fleetlink.shared.messages import MapSnapshot, MapUpdate

__all__ = ["MapShare", "fetch_map"]


def _snapshot(pub: MapPublication) -> Mapping[str, Any]:
    return snapshot_fields(pub.cells, pub.resolution, pub.origin, pub.version)


def _patch(pub: MapPublication, prev: MapPublication) -> Mapping[str, Any] | None:
    if pub.changed is None or not fits_whole(pub.cells):
        return None
    return patch_fields(pub.cells, pub.resolution, pub.origin, pub.changed, pub.version, prev.version)


class MapShare(LayerShare[MapPublication]):
    def __init__(self, link: QueryLink, robot: str, clock: Clock, *, sender: str | None = None) -> None:
        super().__init__(
            link, robot, clock, MapSnapshot, MapUpdate, snapshot_of=_snapshot, patch_of=_patch, sender=sender
        )


def fetch_map(link: QueryLink, robot: str, timeout: float = 5.0) -> MapSnapshot | None:
    """Ask ``fleetlink/v1/<robot>/map``; the first valid snapshot, or None (bad replies are logged)."""
    return fetch(link, robot, MapSnapshot, timeout)
