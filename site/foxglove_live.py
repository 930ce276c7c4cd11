"""The live Foxglove server's core (``fleetlink foxglove``): fleet messages in, what to send out.

Pure: no I/O, no clock of its own (``now``, monotonic seconds, and ``wall``, epoch seconds, are
passed in), no Foxglove library. The shell (site/foxglove_server.py) hands it what the links
deliver and what the WebSocket clients subscribe to, and logs the records it returns on the
Foxglove SDK's channels.

* What is drawn is ``FoxgloveScene``'s (site/foxglove_scene.py, the flight recorder's too): poses,
  lidar scans, ground truth, the robots' maps and the fleet map, the fleet's dose layer.
* Only what a client subscribed to is built: a pose or a scan on a channel nobody watches costs its decode
  (the channel must be advertised) but no JSON. The same message heard on the second link is
  recognised by its bytes and not decoded again.
* Grids are sent when they changed, at most once every ``grid_period_s`` per grid (a robot shares
  its map every second while it changes; 50 robots' maps at that rate would be megabytes a second
  for a picture that changes by a few cells), and at once to a client that subscribes (the
  Foxglove SDK keeps no last message for late subscribers).
* A message that is not wire-valid is refused, counted by reason (``rejected``); a reason seen for
  the first time is put on ``new_reasons`` for the shell to log once. Nothing a sender does
  stops the server.
"""

from __future__ import annotations

from collections import Counter, OrderedDict
from typing import Final

from fleetlink.shared import foxglove, wire
from fleetlink.shared.messages import Pose, Scan, Truth
from fleetlink.site.foxglove_scene import Channel, FoxgloveScene, Record, pose_topic, scan_topic, truth_topic

__all__ = ["DRAWN_SUFFIXES", "GRID_PERIOD_S", "LiveCore"]

GRID_PERIOD_S: Final = 1.0
"""Seconds between two sends of one grid (map, fleet map, dose layer) while it changes."""
DRAWN_SUFFIXES: Final = (
    "/pose",
    "/truth",
    "/scan",
    "/map",
    "/map/updates",
    "/dose",
    "/dose/updates",
    "/frames",
)
"""The keys worth decoding: the rest of the fleet's traffic (commands, state, acks) is not drawn."""
RECENT: Final = 2048
"""Messages remembered to recognise their copy on the other link (a fleet's poses of ~1 s)."""
MAX_REASONS: Final = 64
"""Distinct rejection reasons counted apiece (the rest as one): a sender must not grow our memory."""
OTHER: Final = "(other reasons)"


class LiveCore:
    """Not thread-safe: the shell calls it under one lock."""

    def __init__(self, *, grid_period_s: float = GRID_PERIOD_S) -> None:
        self.grid_period_s = grid_period_s
        self.scene = FoxgloveScene(dose=True, reject=self._reject)
        self.subscribed: Counter[str] = Counter()
        """Topic -> subscriptions the clients hold on it."""
        self.rejected: Counter[str] = Counter()
        self.new_reasons: list[str] = []
        """Rejection reasons seen for the first time since the shell last emptied this."""
        self.channels: dict[str, Channel] = {}
        """Every channel advertised so far."""
        self.announced: list[Channel] = []
        """Channels to advertise (new since the shell last emptied this)."""
        self.robots: set[str] = set()
        self.received = 0
        self.sent = 0
        self._recent: OrderedDict[tuple[str, bytes], None] = OrderedDict()  # FIFO (site/recording.py)
        self._grid_sent: dict[str, float] = {}

    # -- from the links -------------------------------------------------------------------------

    def receive(self, key: str, payload: bytes, wall: float) -> list[Record]:
        """A message a link delivered on ``key`` at ``wall``: the records to send now."""
        if not key.endswith(DRAWN_SUFFIXES):
            return []
        slot = (key, payload)
        if slot in self._recent:  # the same bytes on the other link
            return []
        self.received += 1
        try:
            msg = wire.decode_key(key, payload)
        except wire.WireError as exc:
            self._reject(exc.reason)
            return []
        self._recent[slot] = None
        if len(self._recent) > RECENT:
            self._recent.popitem(last=False)
        if isinstance(msg, Pose | Truth | Scan):
            robot = msg.header.robot
            self.robots.add(robot)
            if isinstance(msg, Scan):
                topic, schema = scan_topic(robot), foxglove.LASER_SCAN
            else:
                topic = pose_topic(robot) if isinstance(msg, Pose) else truth_topic(robot)
                schema = foxglove.POSE_IN_FRAME
            self._announce(topic, schema)
            if not self.subscribed[topic]:
                return []
        return self._count(self.scene.message(msg, wall))

    def snapshot(self, key: str, payload: bytes, wall: float) -> list[Record]:
        """A map or dose snapshot the shell fetched (``wanted()``), like a published message."""
        return self.receive(key, payload, wall)

    def wanted(self) -> list[tuple[str, str]]:
        """(robot, ``map`` or ``dose``) snapshots to fetch."""
        return self.scene.wanted()

    # -- on time --------------------------------------------------------------------------------

    def due(self, now: float, wall: float) -> list[Record]:
        """The grids that changed and were not sent in the last ``grid_period_s`` (those a client
        watches; the others wait, and are sent whole when one subscribes)."""
        send = []
        for topic in self.scene.pending():
            self._announce(topic, foxglove.GRID)
            if self.subscribed[topic] and now - self._grid_sent.get(topic, -1e18) >= self.grid_period_s:
                send.append(topic)
        for topic in send:
            self._grid_sent[topic] = now
        return self._count(self.scene.changed(wall, send)) if send else []

    # -- from the clients -----------------------------------------------------------------------

    def subscribe(self, topic: str, now: float, wall: float) -> list[Record]:
        """A client subscribed to ``topic``: a grid's latest picture (there may be no other for a
        while), nothing for a pose (the next one comes within 50 ms)."""
        self.subscribed[topic] += 1
        channel = self.channels.get(topic)
        if channel is not None and channel.schema_name == foxglove.FRAME_TRANSFORMS:
            held = self.scene.frames_record  # sent every 5 s: the latest at once
            return self._count([held]) if held is not None else []
        if channel is None or channel.schema_name != foxglove.GRID:
            return []
        self._grid_sent[topic] = now
        pending = self.scene.changed(wall, [topic])
        if pending:
            return self._count(pending)
        record = self.scene.grid(topic, wall)
        return self._count([record]) if record is not None else []

    def unsubscribe(self, topic: str) -> None:
        if self.subscribed[topic] > 0:
            self.subscribed[topic] -= 1
        if not self.subscribed[topic]:
            del self.subscribed[topic]

    # -- internals ------------------------------------------------------------------------------

    def _announce(self, topic: str, schema: str) -> None:
        if topic not in self.channels:
            channel = self.channels[topic] = self.scene.channel(topic, schema)
            self.announced.append(channel)

    def _count(self, records: list[Record]) -> list[Record]:
        for r in records:
            self._announce(r.channel.topic, r.channel.schema_name)
        self.sent += len(records)
        return records

    def _reject(self, reason: str) -> None:
        known = reason in self.rejected or len(self.rejected) < MAX_REASONS
        key = reason if known else OTHER
        if key not in self.rejected:
            self.new_reasons.append(key)
        self.rejected[key] += 1
