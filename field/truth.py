"""Ground truth on Zenoh: the field publishes each robot's true pose under the simulation namespace."""

from __future__ import annotations

import logging
from typing import Any

from fleetlink.field.realtime import TruthSample
from fleetlink.links.zenoh import peer_config
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import Truth

log = logging.getLogger(__name__)

__all__ = ["TruthPublisher"]


class TruthPublisher:
    """Encodes ``TruthSample``s as wire-contract ``Truth`` messages and puts them on ``fleetlink/v1/sim/<robot>/truth``."""

    def __init__(self, session: Any, clock: Clock, sender: str = "field", owns_session: bool = False) -> None:
        self.session = session
        self.counter = wire.HeaderCounter(clock, robot="field", sender=sender)
        self._owns = owns_session
        self._publishers: dict[str, Any] = {}

    @classmethod
    def open(cls, listen: str, clock: Clock, connect: tuple[str, ...] = ()) -> TruthPublisher:
        import zenoh

        session = zenoh.open(peer_config([listen] if listen else [], connect))
        return cls(session, clock, owns_session=True)

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
        pub = self._publishers.get(sample.robot)
        if pub is None:
            pub = self.session.declare_publisher(keys.truth_key(sample.robot))
            self._publishers[sample.robot] = pub
        pub.put(wire.encode(msg))

    def close(self) -> None:
        for pub in self._publishers.values():
            pub.undeclare()
        self._publishers.clear()
        if self._owns:
            self.session.close()
