"""Dose sharing on a link: the agent's dose layer served as a ``DoseSnapshot`` and its patches
sent as ``DoseUpdate`` (agent/layer_share.py ``LayerShare`` moves the bytes, as for maps).

    share = DoseShare(link, "r1", clock)   # link: a started Link with serve()/query() (Zenoh, in-process)
    share.start()                       # answers fleetlink/v1/r1/dose, publishes fleetlink/v1/r1/dose/updates
    ... share.publish(publication)      # what the dose keeper hands out (agent/dose_layer.py)
    share.stop()

When to publish is the keeper's decision (every second while the dose changes). A receiver that
missed an update or sees the layer grow asks for a snapshot (``dose_codec.SharedDose.apply``
returns False).

``fetch_dose(link, robot)`` is the asking side (used by ``fleetlink dose save``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from fleetlink.agent.dose_layer import DosePublication
from fleetlink.agent.layer_share import LayerShare, fetch
from fleetlink.links.base import QueryLink
from fleetlink.shared.clock import Clock
from fleetlink.shared.dose_codec import patch_fields, snapshot_fields
from fleetlink.shared.messages import DoseSnapshot, DoseUpdate

__all__ = ["DoseShare", "fetch_dose"]


def _snapshot(pub: DosePublication) -> Mapping[str, Any] | None:
    return snapshot_fields(
        pub.dose, pub.resolution, pub.origin, pub.version,
        target_j_m2=pub.target_j_m2, lamp_on_s=pub.lamp_on_s, unplaced_s=pub.unplaced_s, lamp=pub.lamp,
    )  # fmt: skip


def _patch(pub: DosePublication, prev: DosePublication) -> Mapping[str, Any] | None:
    if pub.changed is None:
        return None
    return patch_fields(
        pub.dose, pub.resolution, pub.origin, pub.changed, pub.version, prev.version,
        target_j_m2=pub.target_j_m2, lamp_on_s=pub.lamp_on_s, unplaced_s=pub.unplaced_s,
    )  # fmt: skip


class DoseShare(LayerShare[DosePublication]):
    def __init__(self, link: QueryLink, robot: str, clock: Clock, *, sender: str | None = None) -> None:
        super().__init__(
            link, robot, clock, DoseSnapshot, DoseUpdate, snapshot_of=_snapshot, patch_of=_patch, sender=sender
        )


def fetch_dose(link: QueryLink, robot: str, timeout: float = 5.0) -> DoseSnapshot | None:
    """Ask ``fleetlink/v1/<robot>/dose``; the first valid snapshot, or None (bad replies are logged)."""
    return fetch(link, robot, DoseSnapshot, timeout)
