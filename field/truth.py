"""Ground truth on a link: the field publishes each robot's true pose under the simulation namespace."""

from __future__ import annotations

import logging
from typing import Any

from fleetlink.field.realtime import TruthSample
from fleetlink.links.base import Link
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import Truth

log = logging.getLogger(__name__)

__all__ = ["TruthPublisher"]


class TruthPublisher:
    """Encodes ``TruthSample``s as wire-contract ``Truth`` messages and publishes them on
    ``fleetlink/v1/sim/<robot>/truth`` through ``link`` (a Zenoh endpoint: a peer that listens, or
    the ``sim`` user of a secured site's router; started here if it is not). ``owns_link``: ``close``
    closes it."""

    def __init__(self, link: Link, clock: Clock, sender: str = "field", *, owns_link: bool = False) -> None:
        link.start()  # idempotent
        self.link = link
        self.counter = wire.HeaderCounter(clock, robot="field", sender=sender)
        self._owns = owns_link

    @classmethod
    def open(cls, clock: Clock, *, listen: str = "", connect: tuple[str, ...] = (), **auth: Any) -> TruthPublisher:
        """On a Zenoh endpoint of its own (``ZenohEndpoint``'s keywords), closed with the publisher."""
        from fleetlink.links.zenoh import ZenohEndpoint

        link = ZenohEndpoint(listen=[listen] if listen else [], connect=connect, label="zenoh-truth", **auth)
        return cls(link, clock, owns_link=True)

    def publish(self, sample: TruthSample) -> None:
        header = self.counter.header(Truth.TOPIC, robot=sample.robot)
        msg = Truth(
            header=header,
            sim_time_s=max(0.0, sample.sim_time),
            x=sample.x,
            y=sample.y,
            theta=sample.theta,
            v=sample.v,
            omega=sample.omega,
            bumped=sample.bumped,
        )
        self.link.publish(keys.truth_key(sample.robot), wire.encode(msg))

    def close(self) -> None:
        if self._owns:
            self.link.close()
