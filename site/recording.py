"""The flight recorder's core: what each fleet message becomes in an MCAP file, and what a file holds.

Pure: no I/O, no MCAP library. ``RecordingCore.receive(link, key, payload, wall)`` takes the bytes a
link delivered and returns the records to write: ``Record(channel, data, log_time_ns,
publish_time_ns)``, where a ``Channel`` is an MCAP topic with its JSON Schema. The shell
(site/recorder.py) registers each channel once and writes the records.

Channels (docs/recording.md):

* ``/fleetlink/<link>/<topic>``: every wire message as it came, one channel per message type and
  link (``/fleetlink/zenoh/pose``, ``/fleetlink/mqtt/actions``), JSON in the wire's field names
  (``shared/wire_json.py``), schema ``fleetlink.<Class>``, the JSON Schema generated from the wire
  contract. Map snapshots fetched over Zenoh's queryables are on ``/fleetlink/zenoh/map``.
* ``/fleetlink/<link>/uwb-status`` (the UWB gateways' retained JSON status, with their anchors) and
  ``/fleetlink/<link>/alive`` (a robot's liveliness token coming or going): what the console hears
  besides wire messages.
* ``/foxglove/<robot>/pose`` (``foxglove.PoseInFrame``, the fused pose; the first copy of a pose
  that came on both links), ``/foxglove/<robot>/map`` (``foxglove.Grid`` of the robot's whole
  occupancy map, kept from snapshots and updates), ``/foxglove/sim/<robot>/truth`` (the field's
  ground truth as a ``foxglove.PoseInFrame``). The wire carries no lidar scans, so no
  ``foxglove.LaserScan`` is written (``shared/foxglove.py`` has it for when one does).

Log time is when the recorder received the message (its clock's wall time), publish time the
sender's ``header.timestamp``.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Final

from fleetlink.shared import foxglove, keys, wire, wire_json
from fleetlink.shared.map_codec import SharedMap
from fleetlink.shared.messages import MapSnapshot, MapUpdate, Pose, Truth

__all__ = [
    "ALIVE",
    "FLEETLINK_PREFIX",
    "FOXGLOVE_PREFIX",
    "UWB_STATUS",
    "Channel",
    "Record",
    "RecordingCore",
    "RecordingSummary",
    "alive_channel",
    "uwb_status_channel",
    "wire_channel",
]

FLEETLINK_PREFIX: Final = "/fleetlink"
FOXGLOVE_PREFIX: Final = "/foxglove"
UWB_STATUS: Final = "uwb-status"
ALIVE: Final = "alive"
UWB_STATUS_KEY_PREFIX: Final = "fleetlink/uwb/"
MAX_REASONS: Final = 64
"""Distinct rejection reasons counted apiece (the rest as one): a sender must not grow our memory."""
OTHER: Final = "(other reasons)"
RECENT: Final = 2048
"""Messages remembered to recognise their copy on the other link (a fleet's poses of ~1 s)."""
RESTART_GAP: Final = 1000
"""A pose counted this far below the newest drawn is from a restarted agent (drawn), not a late copy."""


@dataclass(frozen=True, slots=True)
class Channel:
    """One MCAP channel: its topic, its schema (name and JSON Schema) and metadata."""

    topic: str
    schema_name: str
    schema: bytes = field(repr=False)
    kind: str
    """``wire`` (a fleet message), ``uwb-status``, ``alive``, ``foxglove``."""
    link: str = ""
    """``zenoh`` or ``mqtt`` for what came on a link; ``""`` for the derived Foxglove channels."""
    wire_topic: str = ""
    """The wire topic (``pose``, ``map/updates``) of a ``wire`` channel."""

    def metadata(self) -> dict[str, str]:
        out = {"kind": self.kind}
        if self.link:
            out["link"] = self.link
        if self.wire_topic:
            out["wire_topic"] = self.wire_topic
        return out


@dataclass(frozen=True, slots=True)
class Record:
    channel: Channel
    data: bytes = field(repr=False)
    log_time_ns: int
    publish_time_ns: int


_NS_MAX = 2**64 - 1
"""MCAP's times are uint64 nanoseconds."""


def _ns(t: float) -> int:
    # A wire-valid header timestamp is any finite number >= 0: one far in the future must not
    # overflow (round(inf), or a uint64 the writer cannot pack) and end the recorder's writer.
    ns = t * 1e9
    return max(0, round(ns)) if ns < _NS_MAX else _NS_MAX


def wire_channel(link: str, topic: str) -> Channel:
    """``/fleetlink/<link>/<topic>`` for the wire messages of ``topic`` heard on ``link``."""
    cls = wire.message_type(topic)
    return Channel(
        f"{FLEETLINK_PREFIX}/{link}/{topic}",
        f"fleetlink.{cls.__name__}",
        wire_json.schema_bytes(cls),
        "wire",
        link,
        topic,
    )


_UWB_STATUS_SCHEMA = json.dumps(
    {
        "title": "fleetlink.UwbGatewayStatus",
        "description": "A UWB gateway's retained status (positioning/gateway.py): JSON as the gateway published it",
        "type": "object",
        "properties": {"key": {"type": "string"}, "status": {"type": "object"}},
        "required": ["key", "status"],
    },
    sort_keys=True,
).encode()

_ALIVE_SCHEMA = json.dumps(
    {
        "title": "fleetlink.Liveliness",
        "description": "A robot's liveliness token fleetlink/alive/v1/<robot> appeared (alive) or went",
        "type": "object",
        "properties": {"robot": {"type": "string"}, "alive": {"type": "boolean"}},
        "required": ["robot", "alive"],
        "additionalProperties": False,
    },
    sort_keys=True,
).encode()


def uwb_status_channel(link: str) -> Channel:
    return Channel(
        f"{FLEETLINK_PREFIX}/{link}/{UWB_STATUS}", "fleetlink.UwbGatewayStatus", _UWB_STATUS_SCHEMA, UWB_STATUS, link
    )


def alive_channel(link: str) -> Channel:
    return Channel(f"{FLEETLINK_PREFIX}/{link}/{ALIVE}", "fleetlink.Liveliness", _ALIVE_SCHEMA, ALIVE, link)


def _foxglove_channel(topic: str, schema: str) -> Channel:
    return Channel(topic, schema, foxglove.schema_bytes(schema), "foxglove")


class RecordingCore:
    """Wire bytes in, MCAP records out; counts what it refused. Not thread-safe: one caller at a time."""

    def __init__(self) -> None:
        self._wire: dict[tuple[str, str], Channel] = {}
        self._other: dict[str, Channel] = {}
        self._last_pose: dict[tuple[str, str], int] = {}
        """(robot, sender) -> headerId of the newest pose drawn: its copy on the other link is not."""
        self._maps: dict[str, SharedMap] = {}
        self._recent: dict[tuple[str, bytes], tuple[wire.Message, bytes]] = {}
        """(key, payload) -> (message, JSON) of the last ``RECENT`` messages: the copy of a message
        that came on both links is decoded and converted once."""
        self._want_map: set[str] = set()
        self.robots: set[str] = set()
        self.messages: Counter[str] = Counter()
        """Records written per channel topic."""
        self.rejected: Counter[str] = Counter()
        """Inputs refused (not wire-valid, bad status JSON, bad cells), by reason."""

    # -- inputs ---------------------------------------------------------------------------------

    def receive(self, link: str, key: str, payload: bytes, wall: float) -> list[Record]:
        """A message ``link`` delivered on ``key`` at ``wall`` (epoch seconds, the recorder's clock)."""
        if key.startswith(UWB_STATUS_KEY_PREFIX):
            return self._uwb_status(link, key, payload, wall)
        seen = self._recent.get((key, payload))
        if seen is not None:  # the same bytes on the other link (an agent's pose, state, ...)
            msg, data = seen
        else:
            try:
                msg = wire.decode_key(key, payload)
            except wire.WireError as exc:
                self._reject(exc.reason)
                return []
            data = wire_json.wire_to_json(type(msg), payload)
            self._recent[(key, payload)] = (msg, data)
            if len(self._recent) > RECENT:
                del self._recent[next(iter(self._recent))]
        return self._message(link, msg, data, wall)

    def snapshot(self, link: str, key: str, payload: bytes, wall: float) -> list[Record]:
        """A queryable's answer (a ``MapSnapshot``, a ``DoseSnapshot``) the shell fetched: recorded
        like a published message."""
        return self.receive(link, key, payload, wall)

    def alive(self, link: str, key: str, alive: bool, wall: float) -> list[Record]:
        """A liveliness token ``key`` (``fleetlink/alive/v1/<robot>``, ``keys.alive_key``) came
        (True) or went."""
        try:
            robot = keys.parse_alive_key(key)
        except ValueError as exc:
            self._reject(f"bad liveliness token: {exc}")
            return []
        self.robots.add(robot)
        channel = self._other.get(f"{FLEETLINK_PREFIX}/{link}/{ALIVE}") or self._other_channel(alive_channel(link))
        data = json.dumps({"robot": robot, "alive": alive}, separators=(",", ":")).encode()
        return [self._record(channel, data, wall, wall)]

    def wanted_maps(self) -> list[str]:
        """Robots whose map the recorder cannot draw from updates alone: fetch their snapshot (then
        hand it to ``snapshot``). Each is asked for once until an update fails again."""
        out = sorted(self._want_map)
        self._want_map.clear()
        return out

    # -- internals ------------------------------------------------------------------------------

    def _reject(self, reason: str) -> None:
        known = reason in self.rejected or len(self.rejected) < MAX_REASONS
        self.rejected[reason if known else OTHER] += 1

    def _record(self, channel: Channel, data: bytes, wall: float, published: float) -> Record:
        self.messages[channel.topic] += 1
        return Record(channel, data, _ns(wall), _ns(published))

    def _other_channel(self, made: Channel) -> Channel:
        found = self._other.get(made.topic)
        if found is None:
            found = self._other[made.topic] = made
        return found

    def _uwb_status(self, link: str, key: str, payload: bytes, wall: float) -> list[Record]:
        try:
            status = json.loads(payload)
        except (ValueError, UnicodeDecodeError) as exc:
            self._reject(f"bad UWB gateway status: {exc}")
            return []
        if not isinstance(status, dict):
            self._reject("bad UWB gateway status: not a JSON object")
            return []
        data = json.dumps({"key": key, "status": status}, separators=(",", ":")).encode()
        channel = self._other.get(f"{FLEETLINK_PREFIX}/{link}/{UWB_STATUS}") or self._other_channel(
            uwb_status_channel(link)
        )
        return [self._record(channel, data, wall, wall)]

    def _message(self, link: str, msg: wire.Message, data: bytes, wall: float) -> list[Record]:
        cls = type(msg)
        header = msg.header
        slot = (link, cls.TOPIC)
        channel = self._wire.get(slot)
        if channel is None:
            channel = self._wire[slot] = wire_channel(link, cls.TOPIC)
        if header.robot != keys.FLEET_MAP:
            self.robots.add(header.robot)
        out = [self._record(channel, data, wall, header.timestamp)]
        if isinstance(msg, Pose):
            last = self._last_pose.get((header.robot, header.sender))
            if last is None or header.headerId > last or header.headerId + RESTART_GAP < last:
                self._last_pose[(header.robot, header.sender)] = header.headerId
                data = foxglove.pose_in_frame_json(header.timestamp, msg.x, msg.y, msg.theta)
                topic = f"{FOXGLOVE_PREFIX}/{header.robot}/pose"
                out.append(self._record(self._fox(topic, foxglove.POSE_IN_FRAME), data, wall, header.timestamp))
        elif isinstance(msg, Truth):
            data = foxglove.pose_in_frame_json(header.timestamp, msg.x, msg.y, msg.theta)
            topic = f"{FOXGLOVE_PREFIX}/{keys.SIM}/{header.robot}/truth"
            out.append(self._record(self._fox(topic, foxglove.POSE_IN_FRAME), data, wall, header.timestamp))
        elif isinstance(msg, MapSnapshot | MapUpdate):
            grid = self._map(msg)
            if grid is not None:
                topic = f"{FOXGLOVE_PREFIX}/{header.robot}/map"
                out.append(self._record(self._fox(topic, foxglove.GRID), grid, wall, header.timestamp))
        return out

    def _fox(self, topic: str, schema: str) -> Channel:
        found = self._other.get(topic)
        if found is None:
            found = self._other[topic] = _foxglove_channel(topic, schema)
        return found

    def _map(self, msg: MapSnapshot | MapUpdate) -> bytes | None:
        robot = msg.header.robot
        held = self._maps.get(robot)
        try:
            if isinstance(msg, MapSnapshot):
                if held is not None and held.version == msg.version:
                    return None  # the same map again (both links, or a second fetch)
                held = self._maps[robot] = SharedMap.from_snapshot(msg)
            elif held is None or held.version >= msg.version:
                if held is None:
                    self._want_map.add(robot)
                return None
            elif not held.apply(msg):
                self._want_map.add(robot)
                return None
        except ValueError as exc:
            self._reject(f"bad map cells: {exc}")
            return None
        cells = held.cells
        return _dumps(
            foxglove.grid(
                msg.header.timestamp,
                origin=held.origin,
                resolution=held.resolution,
                width=int(cells.shape[1]),
                cells=cells.tobytes(),
            )
        )


def _dumps(obj: object) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode()


# --------------------------------------------------------------------------------------------------
# What a file holds (``fleetlink record --summary``)


@dataclass(frozen=True, slots=True)
class ChannelSummary:
    topic: str
    schema_name: str
    messages: int


@dataclass(frozen=True, slots=True)
class RecordingSummary:
    channels: tuple[ChannelSummary, ...]
    start_ns: int | None
    end_ns: int | None
    robots: tuple[str, ...]
    complete: bool
    """The file was closed properly (it has its summary); False: recovered after a crash."""
    notes: tuple[str, ...] = ()

    @property
    def messages(self) -> int:
        return sum(c.messages for c in self.channels)

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    @classmethod
    def build(
        cls,
        counts: Mapping[str, int],
        schemas: Mapping[str, str],
        span: tuple[int, int] | None,
        robots: Iterable[str],
        *,
        complete: bool,
        notes: Iterable[str] = (),
    ) -> RecordingSummary:
        channels = tuple(ChannelSummary(t, schemas.get(t, "?"), n) for t, n in sorted(counts.items()))
        return cls(
            channels,
            None if span is None else span[0],
            None if span is None else span[1],
            tuple(sorted(set(robots))),
            complete,
            tuple(notes),
        )

    def text(self, path: str = "") -> str:
        """What ``fleetlink record --summary`` prints."""
        lines = [f"{path}: " if path else ""]
        lines[0] += f"{self.messages} messages on {len(self.channels)} channels, {self.duration_s:.1f} s" + (
            "" if self.complete else " (recovered: the file was not closed, its last chunk may be lost)"
        )
        if self.start_ns is not None and self.end_ns is not None:
            lines.append(f"time: {_iso(self.start_ns)} .. {_iso(self.end_ns)} (UTC)")
        lines.append(f"robots ({len(self.robots)}): {', '.join(self.robots) if self.robots else '-'}")
        width = max([len(c.topic) for c in self.channels] + [7])
        swidth = max([len(c.schema_name) for c in self.channels] + [6])
        lines.append(f"{'channel':<{width}}  {'schema':<{swidth}}  {'messages':>8}")
        for c in self.channels:
            lines.append(f"{c.topic:<{width}}  {c.schema_name:<{swidth}}  {c.messages:>8}")
        lines.extend(self.notes)
        return "\n".join(lines)


def _iso(ns: int) -> str:
    import datetime

    return datetime.datetime.fromtimestamp(ns / 1e9, tz=datetime.UTC).isoformat(timespec="milliseconds")[:-6]
