"""The UWB gateway's core: true poses and time in, what to publish out. Pure: no I/O, no clock.

``GatewayCore.on_truth`` records where each robot really is (and when, on the caller's monotonic
clock). ``GatewayCore.tick(now, wall)`` is one ranging round: for every tag whose robot has a fresh
truth pose it simulates ranges (``RangingModel``), solves (``solver.solve``) and returns
``MqttMessage``s (MQTT topic, payload bytes, QoS, retain):

* the native ``UwbFix`` (msgpack, wire contract) on ``fleetlink/v1/<robot>/uwb``, QoS 0;
* the raw ``UwbRanges`` on ``fleetlink/v1/<robot>/uwb/ranges``, QoS 0 (optional);
* a Qorvo DWM1001 PANS location on ``<prefix>/node/<tag>/uplink/location``, JSON, QoS 0,
  retained (as the PANS MQTT connector does).

The shell (``publisher.UwbGateway``) only moves bytes and time.
"""

from __future__ import annotations

import json
import logging
import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fleetlink.links.mqtt import MqttMessage
from fleetlink.shared import keys, wire
from fleetlink.shared.messages import FixStatus, UwbFix, UwbRange, UwbRanges

from .anchors import Anchor
from .config import GatewayConfig, TagSpec
from .ranging import RangingModel
from .solver import Solution, solve, solve_linear

__all__ = ["GatewayCore", "pans_location", "pans_topic", "status_payload", "status_topic"]

log = logging.getLogger(__name__)

SUPERFRAME_MODULO = 65_536


def pans_topic(prefix: str, tag: str) -> str:
    return f"{prefix}/node/{tag}/uplink/location"


def status_topic(gateway_id: str) -> str:
    """The gateway's retained status (online/offline, last will): outside ``fleetlink/v1/`` so the
    fleet's robot wildcards never match it."""
    return f"fleetlink/uwb/{keys.check_id(gateway_id, 'gateway id')}/status"


def pans_location(x: float, y: float, z: float, quality: int, superframe: int, wall: float) -> bytes:
    """A DWM1001 PANS ``uplink/location`` payload: metres to the millimetre, quality 0-100,
    ``timestamp`` a string of microseconds since the Unix epoch."""
    doc = {
        "position": {"x": round(x, 3), "y": round(y, 3), "z": round(z, 3), "quality": int(quality)},
        "superFrameNumber": int(superframe),
        "timestamp": str(round(wall * 1e6)),
    }
    return json.dumps(doc, separators=(",", ":")).encode()


def status_payload(gateway_id: str, state: str, wall: float, extra: dict[str, Any] | None = None) -> bytes:
    doc: dict[str, Any] = {"gateway": gateway_id, "state": state, "timestamp": wall}
    if extra:
        doc.update(extra)
    return json.dumps(doc, separators=(",", ":"), sort_keys=True).encode()


@dataclass(slots=True)
class _Truth:
    x: float
    y: float
    theta: float
    v: float
    at: float  # caller's monotonic seconds


class _Tag:
    __slots__ = ("model", "previous", "spec")

    def __init__(self, spec: TagSpec, model: RangingModel) -> None:
        self.spec = spec
        self.model = model
        self.previous: Solution | None = None


class GatewayCore:
    """All tags of one gateway. Not thread-safe: the shell serialises calls."""

    def __init__(self, config: GatewayConfig) -> None:
        self.config = config
        self.anchors: tuple[Anchor, ...] = config.anchors
        self._by_id = {a.id: a for a in self.anchors}
        self._solve: Callable[..., Solution] = solve if config.solver == "robust" else solve_linear
        self._tags: dict[str, _Tag] = {}  # robot -> tag
        self._truth: dict[str, _Truth] = {}
        self._next_id: dict[tuple[str, str], int] = {}
        self._superframe = 0
        self._logged: set[str] = set()
        self.counts: Counter[str] = Counter()
        for spec in config.tags:
            self._add_tag(spec)

    # ----------------------------------------------------------------------------------------------

    def _add_tag(self, spec: TagSpec) -> _Tag:
        # One random stream per tag, from (seed, tag id): a tag's ranges do not depend on which
        # other tags exist or in what order robots appeared.
        rng = np.random.default_rng([self.config.seed, *spec.id.encode()])
        tag = _Tag(spec, RangingModel(self.anchors, self.config.profile, rng, self.config.walls))
        self._tags[spec.robot] = tag
        return tag

    def _once(self, reason: str, *args: object) -> None:
        if reason not in self._logged:
            self._logged.add(reason)
            log.warning(reason, *args)

    @property
    def tags(self) -> tuple[TagSpec, ...]:
        return tuple(t.spec for t in self._tags.values())

    def on_truth(self, robot: str, x: float, y: float, now: float, theta: float = 0.0, v: float = 0.0) -> bool:
        """Record a true pose; False (counted, logged once) for a robot without a tag or a bad pose."""
        if not all(math.isfinite(f) for f in (x, y, theta, v, now)):
            self.counts["truth_rejected"] += 1
            self._once("truth for %s rejected: non-finite value (further ones counted only)", robot)
            return False
        if robot not in self._tags:
            if not self.config.auto_tags or not keys.is_valid_id(robot) or robot == keys.SIM:
                self.counts["truth_unknown_robot"] += 1
                self._once(f"truth for robot {robot!r} ignored: it has no tag (add a [[tags]] entry)")
                return False
            self._add_tag(TagSpec(robot, robot, self.config.tag_z))
        self._truth[robot] = _Truth(x, y, theta, v, now)
        self.counts["truth"] += 1
        return True

    def forget(self, robot: str) -> None:
        self._truth.pop(robot, None)

    def _header(self, robot: str, topic: str, wall: float) -> wire.Header:
        slot = (robot, topic)
        n = self._next_id.get(slot, 0)
        self._next_id[slot] = n + 1
        return wire.Header(
            headerId=n, timestamp=wall, version=wire.WIRE_VERSION, robot=robot, sender=self.config.gateway_id
        )

    def where(self, robot: str, now: float) -> tuple[float, float] | None:
        """The robot's true position at ``now``: the last truth, carried forward at its speed
        (truth arrives at 20 Hz, ranging at 10 Hz: up to 50 ms of motion otherwise lost)."""
        t = self._truth.get(robot)
        if t is None:
            return None
        age = now - t.at
        if age > self.config.truth_timeout_s:
            return None
        dt = max(0.0, age)
        return t.x + t.v * math.cos(t.theta) * dt, t.y + t.v * math.sin(t.theta) * dt

    def tick(self, now: float, wall: float) -> list[MqttMessage]:
        """One ranging round for every tag with a fresh truth pose."""
        self._superframe = (self._superframe + 1) % SUPERFRAME_MODULO
        out: list[MqttMessage] = []
        for robot, tag in self._tags.items():
            pos = self.where(robot, now)
            if pos is None:
                if robot in self._truth:
                    self.counts["truth_stale"] += 1
                continue
            out.extend(self.locate(tag, pos[0], pos[1], wall))
        return out

    def locate(self, tag: _Tag, x: float, y: float, wall: float) -> list[MqttMessage]:
        spec = tag.spec
        ranges = tag.model.measure(x, y, spec.z)
        sol = self._solve(self._by_id, ranges, spec.z, tag.previous, sigma_m=max(self.config.profile.sigma_m, 0.05))
        out: list[MqttMessage] = []
        if self.config.publish_ranges:
            rmsg = UwbRanges(
                header=self._header(spec.robot, UwbRanges.TOPIC, wall),
                tag=spec.id,
                ranges=tuple(UwbRange(anchor=r.anchor_id, distance_m=r.distance_m) for r in ranges),
                measured_at=wall,
            )
            out.append(MqttMessage(keys.key(spec.robot, UwbRanges.TOPIC), wire.encode(rmsg)))
        if sol.status is not FixStatus.OK:
            tag.previous = None
            self.counts[f"fix_{sol.status.value}"] += 1
            return out
        tag.previous = sol
        self.counts["fixes"] += 1
        fix = UwbFix(
            header=self._header(spec.robot, UwbFix.TOPIC, wall),
            tag=spec.id,
            x=sol.x,
            y=sol.y,
            z=sol.z,
            sd_x=sol.sd_x,
            sd_y=sol.sd_y,
            quality=sol.quality,
            status=sol.status,
            anchors=sol.used,
            residual_rms_m=sol.residual_rms_m,
            measured_at=wall,
        )
        out.append(MqttMessage(keys.key(spec.robot, UwbFix.TOPIC), wire.encode(fix)))
        if self.config.pans:
            payload = pans_location(sol.x, sol.y, sol.z, sol.quality, self._superframe, wall)
            out.append(MqttMessage(pans_topic(self.config.pans_prefix, spec.id), payload, 0, True))
        return out

    def status(self, state: str, wall: float) -> MqttMessage:
        extra: dict[str, Any] = {
            "rate_hz": self.config.rate_hz,
            "tags": {t.spec.id: t.spec.robot for t in self._tags.values()},
            "counts": dict(sorted(self.counts.items())),
            # Consoles draw the anchors from this retained status (docs/wire-contract.md).
            "anchors": [[a.id, a.x, a.y, a.z] for a in self.config.anchors],
        }
        return MqttMessage(
            status_topic(self.config.gateway_id), status_payload(self.config.gateway_id, state, wall, extra), 1, True
        )

    def tag_ids(self) -> Sequence[str]:
        return [t.spec.id for t in self._tags.values()]
