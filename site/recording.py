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
  ground truth as a ``foxglove.PoseInFrame``): made by ``FoxgloveScene`` (site/foxglove_scene.py),
  the same as ``fleetlink foxglove`` serves live; ``/foxglove/<robot>/scan`` (``foxglove.LaserScan``)
  from the wire's ``Scan``.

Log time is when the recorder received the message (its clock's wall time), publish time the
sender's ``header.timestamp``.
"""

from __future__ import annotations

import json
from collections import Counter, OrderedDict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Final

from fleetlink.shared import keys, wire, wire_json
from fleetlink.shared.messages import DoseSnapshot, DoseUpdate
from fleetlink.site.foxglove_scene import DOSE, FOXGLOVE_PREFIX, MAP, Channel, FoxgloveScene, Record, ns

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
UWB_STATUS: Final = "uwb-status"
ALIVE: Final = "alive"
UWB_STATUS_KEY_PREFIX: Final = "fleetlink/uwb/"
MAX_REASONS: Final = 64
"""Distinct rejection reasons counted apiece (the rest as one): a sender must not grow our memory."""
OTHER: Final = "(other reasons)"
RECENT: Final = 2048
"""Messages remembered to recognise their copy on the other link (a fleet's poses of ~1 s)."""
MAX_ROBOTS: Final = 1024
"""Distinct robots recorded (each has its Foxglove channels, its map, its last pose); a message
about another one is refused (counted under ``TOO_MANY_ROBOTS``): a flood of made-up robot ids
must not grow the recorder's memory or the file's channels without bound."""
TOO_MANY_ROBOTS: Final = f"too many robots (more than {MAX_ROBOTS} distinct robot ids): a new one is not recorded"


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


class RecordingCore:
    """Wire bytes in, MCAP records out; counts what it refused. Not thread-safe: one caller at a time."""

    def __init__(self) -> None:
        self._wire: dict[tuple[str, str], Channel] = {}
        self._other: dict[str, Channel] = {}
        self.scene = FoxgloveScene(reject=self._reject)
        """Poses, truth and maps in Foxglove's schemas (site/foxglove_scene.py, as the live server's)."""
        self._recent: OrderedDict[tuple[str, bytes], tuple[wire.Message, bytes, int]] = OrderedDict()
        """(key, payload) -> (message, JSON, publish time in ns) of the last ``RECENT`` messages: the copy of a message
        that came on both links is decoded and converted once. (An ``OrderedDict``: a plain dict
        emptied from the front finds its first key by walking past every key deleted before it,
        ~2 us an insert at this size; ``popitem(last=False)`` does not.)"""
        self.robots: set[str] = set()
        self.messages: Counter[str] = Counter()
        """Records written per channel topic."""
        self.rejected: Counter[str] = Counter()
        """Inputs refused (not wire-valid, bad status JSON, bad cells, too many robots), by reason."""
        self.new_reasons: list[str] = []
        """Reasons refused for the first time since the shell last took them (it logs each once)."""
        self._doses: dict[str, tuple[int, int, int, float, float, float]] = {}
        """robot -> (version, width, height, resolution, origin x, y) of its dose layer as the recorded
        snapshot and the updates since leave it: which updates follow (``map_codec.patch_follows``'s
        rule on the headers alone; the recorder keeps no cells: it draws no dose layer)."""
        self._want_doses: set[str] = set()

    # -- inputs ---------------------------------------------------------------------------------

    def receive(self, link: str, key: str, payload: bytes, wall: float) -> list[Record]:
        """A message ``link`` delivered on ``key`` at ``wall`` (epoch seconds, the recorder's clock)."""
        if key.startswith(UWB_STATUS_KEY_PREFIX):
            return self._uwb_status(link, key, payload, wall)
        recent = self._recent
        seen = recent.get((key, payload))
        if seen is not None:  # the same bytes on the other link (an agent's pose, state, ...)
            msg, data, published = seen
        else:
            try:
                msg, unpacked = wire.decode_key_unpacked(key, payload)
            except wire.WireError as exc:
                self._reject(exc.reason)
                return []
            robot = msg.header.robot
            if robot not in self.robots and robot != keys.FLEET_MAP and not self._new_robot(robot):
                return []
            data = wire_json.unpacked_to_json(type(msg), unpacked)
            published = ns(msg.header.timestamp)
            if type(msg) is DoseUpdate or type(msg) is DoseSnapshot:
                self._follow_dose(msg)
            recent[(key, payload)] = (msg, data, published)
            if len(recent) > RECENT:
                recent.popitem(last=False)
        return self._message(link, msg, data, wall, published)

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
        if robot not in self.robots and not self._new_robot(robot):
            return []
        channel = self._other.get(f"{FLEETLINK_PREFIX}/{link}/{ALIVE}") or self._other_channel(alive_channel(link))
        data = json.dumps({"robot": robot, "alive": alive}, separators=(",", ":")).encode()
        return [self._record(channel, data, wall, wall)]

    def wanted_snapshots(self) -> list[tuple[str, str]]:
        """(robot, ``map`` or ``dose``): snapshots to fetch (then hand each to ``snapshot``), for
        the robots whose map or dose layer cannot be followed from their updates alone (the first
        update heard, one that does not follow): a replay answers the console's fetches from them
        (site/replay.py). Each is asked for once until an update fails to follow again."""
        doses, self._want_doses = sorted(self._want_doses), set()
        return [(robot, MAP) for robot, topic in self.scene.wanted() if topic == MAP] + [(r, DOSE) for r in doses]

    # -- internals ------------------------------------------------------------------------------

    def _follow_dose(self, msg: DoseUpdate | DoseSnapshot) -> None:
        """A dose snapshot (fetched by the recorder: it becomes the layer's head) or update (it
        moves the head if it follows, else the robot's snapshot is wanted). Called once per message
        (not for its copy on the other link)."""
        robot = msg.header.robot
        shape = (msg.width, msg.height, msg.resolution, msg.origin_x, msg.origin_y)
        if isinstance(msg, DoseSnapshot):
            self._doses[robot] = (msg.version, *shape)
            return
        head = self._doses.get(robot)
        if head is not None and msg.base_version == head[0] and msg.version > head[0] and shape == head[1:]:
            self._doses[robot] = (msg.version, *shape)
        elif head is None or msg.version != head[0]:  # (the same version again: nothing to fetch)
            self._want_doses.add(robot)

    def _reject(self, reason: str) -> None:
        known = reason in self.rejected or len(self.rejected) < MAX_REASONS
        key = reason if known else OTHER
        if key not in self.rejected:
            self.new_reasons.append(key)
        self.rejected[key] += 1

    def _new_robot(self, robot: str) -> bool:
        """Take ``robot`` on (True) unless ``MAX_ROBOTS`` are already recorded."""
        if len(self.robots) >= MAX_ROBOTS:
            self._reject(TOO_MANY_ROBOTS)
            return False
        self.robots.add(robot)
        return True

    def _record(self, channel: Channel, data: bytes, wall: float, published: float) -> Record:
        self.messages[channel.topic] += 1
        return Record(channel, data, ns(wall), ns(published))

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

    def _message(self, link: str, msg: wire.Message, data: bytes, wall: float, published: int) -> list[Record]:
        channel = self._wire.get((link, msg.TOPIC))
        if channel is None:
            channel = self._wire[(link, msg.TOPIC)] = wire_channel(link, msg.TOPIC)
        messages = self.messages
        messages[channel.topic] += 1
        logged = ns(wall)
        out = [Record(channel, data, logged, published)]
        scene = self.scene
        more = scene.message(msg, wall, wall_ns=logged, stamp_ns=published)
        if scene.has_pending:  # a map applied: its whole grid, after every snapshot and update
            more += scene.changed(wall)
        for r in more:
            messages[r.channel.topic] += 1
            out.append(r)
        return out


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
    from_index: bool = False
    """Read from the file's summary section (statistics, channels, metadata), no chunk read;
    False: read message by message (a file without a usable summary, or asked to)."""
    bytes_read: int = 0
    """What reading it took."""

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
        from_index: bool = False,
        bytes_read: int = 0,
    ) -> RecordingSummary:
        channels = tuple(ChannelSummary(t, schemas.get(t, "?"), n) for t, n in sorted(counts.items()) if n > 0)
        return cls(
            channels,
            None if span is None else span[0],
            None if span is None else span[1],
            tuple(sorted(set(robots))),
            complete,
            tuple(notes),
            from_index,
            bytes_read,
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
