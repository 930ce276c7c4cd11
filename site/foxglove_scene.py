"""What the fleet looks like in Foxglove's well-known schemas: wire messages in, Foxglove records out.

Pure: no I/O, no clock (times are passed in). One scene serves both the flight recorder
(site/recording.py: every record into the MCAP file) and the live server (site/foxglove_live.py:
the same records over Foxglove's WebSocket protocol), so a pose, a map or a dose layer looks the
same in a recording and live.

* ``/foxglove/<robot>/pose`` (``foxglove.PoseInFrame``): the fused pose in the site frame ``map``,
  once per pose (the copy that came on the second link, recognised by its header's counter, is not
  drawn again). A robot without UWB (its ``Pose`` says its position is unknown: ``UNKNOWN_SD_M``)
  maps and reports in its own frame: its pose, scan and map are in frame ``<robot>/map``.
* ``/foxglove/fleet/frames`` (``foxglove.FrameTransforms``): where those frames lie in ``map`` (the
  fleet map's frame), from a fleet map service's ``FleetFrames``; a robot not found yet has none,
  and Foxglove draws it only in its own frame. A frame the fleet map placed and then lost (the
  robot's map began again) is not drawn in ``map`` again: the robot goes on in ``<robot>/map.1``
  (``.2``, ...), placed once the fleet map finds it (Foxglove cannot take a transform back).
* ``/foxglove/sim/<robot>/truth`` (``foxglove.PoseInFrame``): the simulated field's ground truth.
* ``/foxglove/<robot>/scan`` (``foxglove.LaserScan``): the robot's latest lidar turn (the wire's
  ``Scan``, at most ``[rates] scan_hz``), in frame ``map`` at the pose it was taken from.
* ``/foxglove/<robot>/map`` (``foxglove.Grid``, one ``INT8`` field ``occupancy``: -1 unknown,
  0-100 %): a robot's onboard map (in the site frame), kept from its snapshots and patches;
  ``/foxglove/fleet/map`` the fleet map (site/fleetmap.py) when a fleet map service publishes it.
* ``/foxglove/fleet/dose`` (``foxglove.Grid``, one ``FLOAT32`` field ``dose_j_m2``): the robots'
  UV dose layers summed (``operator.dose.merge_layers``, as the console draws them), with
  ``dose=True`` only (the recorder keeps the layers' patches as wire messages).

Maps and dose layers are kept whole from snapshots and patches: ``message`` applies them and
``changed(wall)`` hands out the grids that changed since last asked (a caller that wants fewer asks
less often: the live server throttles there). A patch that does not follow the copy (the first one
heard, a lost one, a restarted agent) puts the robot on ``wanted()``: fetch its snapshot and hand
it to ``message`` like any other.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final, NamedTuple

import numpy as np

from fleetlink.operator.dose import merge_layers
from fleetlink.shared import foxglove, keys, wire
from fleetlink.shared.dose_codec import SharedDose
from fleetlink.shared.map_codec import SharedMap
from fleetlink.shared.messages import (
    UNKNOWN_SD_M,
    DoseSnapshot,
    DoseUpdate,
    FleetFrames,
    MapSnapshot,
    MapUpdate,
    Pose,
    Scan,
    Truth,
    same_map,
)
from fleetlink.shared.scan_codec import scan_ranges

__all__ = [
    "DOSE",
    "FLEET_DOSE_TOPIC",
    "FOXGLOVE_PREFIX",
    "FRAMES_TOPIC",
    "MAP",
    "RESTART_GAP",
    "Channel",
    "FoxgloveScene",
    "Record",
    "map_topic",
    "ns",
    "pose_topic",
    "robot_frame",
    "scan_topic",
    "truth_topic",
]

FOXGLOVE_PREFIX: Final = "/foxglove"
MAP: Final = "map"
DOSE: Final = "dose"
"""The wire topics of the snapshots ``wanted()`` names (``fleetlink/v1/<robot>/map``, ``.../dose``)."""
FLEET_DOSE_TOPIC: Final = f"{FOXGLOVE_PREFIX}/{keys.FLEET_MAP}/dose"
SITE_FRAMES_HOLD_S: Final = 15.0
"""``FleetFrames`` whose fleet map is a robot's own frame are passed over while ones in the site frame
(another service that has a site-frame map) came within this."""
RESTART_GAP: Final = 1000
"""A pose counted this far below the newest drawn is from a restarted agent (drawn), not a late copy."""


@dataclass(frozen=True, slots=True)
class Channel:
    """One channel: its topic, its schema (name and JSON Schema) and metadata."""

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


class Record(NamedTuple):
    """One message to write or send (a named tuple: a recorder makes thousands a second)."""

    channel: Channel
    data: bytes
    log_time_ns: int
    publish_time_ns: int


_NS_MAX = 2**64 - 1
"""MCAP's (and Foxglove's) times are uint64 nanoseconds."""


def ns(t: float) -> int:
    """Seconds as uint64 nanoseconds, clamped: a wire-valid header timestamp is any finite number
    >= 0, and one far in the future must not overflow (round(inf), or a uint64 nobody can pack)."""
    n = t * 1e9
    return max(0, round(n)) if n < _NS_MAX else _NS_MAX


def pose_topic(robot: str) -> str:
    return f"{FOXGLOVE_PREFIX}/{robot}/pose"


def scan_topic(robot: str) -> str:
    return f"{FOXGLOVE_PREFIX}/{robot}/scan"


def truth_topic(robot: str) -> str:
    return f"{FOXGLOVE_PREFIX}/{keys.SIM}/{robot}/truth"


def robot_frame(robot: str, placing: int = 0) -> str:
    """The Foxglove frame of a robot's own map (a robot without UWB reports in it): ``<robot>/map``,
    and ``<robot>/map.<n>`` once the fleet map has lost its placing ``n`` times (``FoxgloveScene``)."""
    return f"{robot}/{MAP}" if placing == 0 else f"{robot}/{MAP}.{placing}"


MAX_FRAME_SENDERS: Final = 64
"""Fleet map services whose placings a scene remembers (``FoxgloveScene._placed_by``)."""

FRAMES_TOPIC: Final = f"{FOXGLOVE_PREFIX}/{keys.FLEET_MAP}/frames"


def map_topic(robot: str) -> str:
    """A robot's map, or the fleet map's (``robot == keys.FLEET_MAP``)."""
    return f"{FOXGLOVE_PREFIX}/{robot}/map"


def _dumps(obj: object) -> bytes:
    """Compact JSON (``foxglove.dumps``: orjson, a scan's 360 ranges in a fraction of ``json.dumps``'s
    time; every float here is finite)."""
    return foxglove.dumps(obj)


class FoxgloveScene:
    """Decoded wire messages in, Foxglove records out. Not thread-safe: one caller at a time."""

    def __init__(self, *, dose: bool = False, reject: Callable[[str], None] | None = None) -> None:
        """``dose``: keep the robots' dose layers and draw their sum; ``reject(reason)``: told about
        every snapshot or patch whose cells cannot be right (it is dropped)."""
        self.dose = dose
        self._reject = reject or (lambda reason: None)
        self._channels: dict[str, Channel] = {}
        self._last_pose: dict[str, tuple[str, int]] = {}
        """robot -> (sender, headerId) of the newest pose drawn: its copy on the other link is not
        (one entry a robot, whoever sends its poses)."""
        self.maps: dict[str, SharedMap] = {}
        self.doses: dict[str, SharedDose] = {}
        self._changed: dict[str, float] = {}
        """Grid topic -> the header timestamp of the message that last changed it (not yet handed out)."""
        self._stamps: dict[str, float] = {}
        """Grid topic -> the header timestamp of the message that last changed it."""
        self._want: set[tuple[str, str]] = set()
        self._restarted: set[str] = set()
        """Robots whose dose patches went back in version (a restarted agent): the next snapshot
        replaces the copy although its version is lower."""
        self._dose_version = 0
        self.own_frames: set[str] = set()
        """Robots whose latest pose is in their own map frame (no UWB position)."""
        self.frames_record: Record | None = None
        """The latest transforms of those frames (a client that subscribes late gets it at once)."""
        self._site_frames_at: float | None = None
        self._placed_by: dict[str, set[str]] = {}
        """Sender (a console's fleet map service) -> the robots whose own frames its last
        ``FleetFrames`` placed (at most ``MAX_FRAME_SENDERS`` senders remembered)."""
        self._placings: dict[str, int] = {}
        """Robot -> how often a fleet map lost its frame (``robot_frame``'s ``placing``). Foxglove
        keeps a transform until another replaces it and none can be taken back: a robot whose map
        began again (its agent restarted) would be drawn where its old map lay. So a frame that a
        service placed and then says it has not found (its ``unframed``) is not drawn in ``map``
        again: the robot's records move to a new frame, placed once the fleet map finds it. (Another
        console that has not found it yet says nothing about the first one's placing.) Nor, from
        its first pose of a new map (``Pose.map_began``: another map's, or 0 again), before the
        service has noticed."""
        self._map_began: dict[str, float] = {}
        """Robot -> the map its latest pose is in (``Pose.map_began``): a frame found for another of
        its maps (``RobotFrame.began``) is not sent for it (``same_map``)."""
        self._named: set[str] = set()
        """Robots whose poses have named their map (not 0) before: 0 from them is a new map not begun yet."""
        self._frames_msg: FleetFrames | None = None
        """The latest ``FleetFrames`` taken: sent again when a robot's poses move to a new map."""

    # -- inputs ---------------------------------------------------------------------------------

    def message(
        self, msg: wire.Message, wall: float, *, wall_ns: int | None = None, stamp_ns: int | None = None
    ) -> list[Record]:
        """A wire-valid message heard at ``wall`` (epoch seconds): the records to show at once
        (poses, truth). Maps and dose layers are applied; ``changed`` hands out their grids.
        ``wall_ns``, ``stamp_ns``: ``ns(wall)`` and ``ns(msg.header.timestamp)`` when the caller has
        them already (the recorder: a pose's records share them)."""
        header = msg.header
        if type(msg) is Pose:
            robot, hid = header.robot, header.headerId
            last = self._last_pose.get(robot)
            if last is None or last[0] != header.sender or hid > last[1] or hid + RESTART_GAP < last[1]:
                self._last_pose[robot] = (header.sender, hid)
                if msg.sd_x_m >= UNKNOWN_SD_M:
                    self.own_frames.add(robot)
                else:
                    self.own_frames.discard(robot)
                was = self._map_began.get(robot)
                begun = was is not None and msg.map_began != was
                if begun and was != 0.0 and robot in self.own_frames:
                    # A map begun again (0: its new map has not begun yet; then the new one's began
                    # is the same map): drawn in a frame the old map's transform does not move.
                    self._placings[robot] = self._placings.get(robot, 0) + 1
                self._map_began[robot] = msg.map_began
                if msg.map_began:
                    self._named.add(robot)
                data = foxglove.pose_in_frame_json(header.timestamp, msg.x, msg.y, msg.theta, self._frame(robot))
                channel = self._channels.get(f"{FOXGLOVE_PREFIX}/{robot}/pose") or self.channel(
                    pose_topic(robot), foxglove.POSE_IN_FRAME
                )
                out = [
                    Record(
                        channel,
                        data,
                        ns(wall) if wall_ns is None else wall_ns,
                        ns(header.timestamp) if stamp_ns is None else stamp_ns,
                    )
                ]
                if begun and msg.map_began and self._frames_msg is not None:
                    # Frames heard before its first pose in the new map may hold the new map's.
                    out.append(self._frames(self._frames_msg, wall))
                return out
        elif isinstance(msg, Truth):
            data = foxglove.pose_in_frame_json(header.timestamp, msg.x, msg.y, msg.theta)
            channel = self.channel(truth_topic(header.robot), foxglove.POSE_IN_FRAME)
            return [Record(channel, data, ns(wall), ns(header.timestamp))]
        elif isinstance(msg, Scan):
            try:
                ranges = scan_ranges(msg)
            except wire.WireError as exc:
                self._reject(exc.reason)
                return []
            step = math.tau / msg.count
            data = _dumps(
                foxglove.laser_scan(
                    header.timestamp,
                    pose=(msg.x, msg.y, msg.theta),
                    start_angle=msg.start_angle,
                    end_angle=msg.start_angle + step * (msg.count - 1),
                    ranges=np.nan_to_num(ranges, nan=0.0).tolist(),  # no return: 0 (JSON has no NaN)
                    frame=self._frame(header.robot),
                )
            )
            channel = self.channel(scan_topic(header.robot), foxglove.LASER_SCAN)
            return [Record(channel, data, ns(wall), ns(header.timestamp))]
        elif isinstance(msg, FleetFrames):
            if msg.reference:
                if self._site_frames_at is not None and wall - self._site_frames_at < SITE_FRAMES_HOLD_S:
                    return []  # another service has the site frame: its placements hold
            else:
                self._site_frames_at = wall
            placed = {f.robot for f in msg.frames}
            before = self._placed_by.get(header.sender)
            if before is None and len(self._placed_by) >= MAX_FRAME_SENDERS:
                self._placed_by.clear()  # (consoles come and go: forget the old ones)
            for robot in (before or set()) & set(msg.unframed):
                self._placings[robot] = self._placings.get(robot, 0) + 1
            self._placed_by[header.sender] = placed
            self._frames_msg = msg
            return [self._frames(msg, wall)]
        elif isinstance(msg, MapSnapshot | MapUpdate):
            if self._map(msg):
                topic = map_topic(header.robot)
                self._changed[topic] = self._stamps[topic] = header.timestamp
        elif self.dose and isinstance(msg, DoseSnapshot | DoseUpdate) and self._dose(msg):
            self._dose_version += 1
            self._changed[FLEET_DOSE_TOPIC] = self._stamps[FLEET_DOSE_TOPIC] = header.timestamp
        return []

    def wanted(self) -> list[tuple[str, str]]:
        """(robot, ``MAP`` or ``DOSE``) snapshots to fetch, each named once until a patch fails
        again."""
        out = sorted(self._want)
        self._want.clear()
        return out

    # -- outputs --------------------------------------------------------------------------------

    def pending(self) -> list[str]:
        """Grid topics changed since they were last handed out."""
        return list(self._changed)

    @property
    def has_pending(self) -> bool:
        """Some grid changed since it was last handed out (``pending()`` without the list)."""
        return bool(self._changed)

    def changed(self, wall: float, topics: list[str] | None = None) -> list[Record]:
        """The grids changed since they were last handed out (of ``topics`` only, if given), as
        records logged at ``wall``. Each is handed out once per change."""
        out = []
        for topic in list(self._changed) if topics is None else topics:
            stamp = self._changed.pop(topic, None)
            if stamp is None:
                continue
            record = self.grid(topic, wall, stamp)
            if record is not None:
                out.append(record)
        return out

    def grid(self, topic: str, wall: float, stamp: float | None = None) -> Record | None:
        """The grid of ``topic`` as it is now (None if there is none), stamped when it last changed."""
        if stamp is None:
            stamp = self._stamps.get(topic)
        if topic == FLEET_DOSE_TOPIC:
            layer = merge_layers(self.doses, self._dose_version) if self.doses else None
            if layer is None or not layer.grid.dose.size:
                return None
            g = layer.grid
            cells = np.ascontiguousarray(g.dose, dtype="<f4")
            t = wall if stamp is None else stamp
            data = _dumps(
                foxglove.grid(
                    t,
                    origin=g.origin,
                    resolution=g.resolution,
                    width=int(cells.shape[1]),
                    cells=cells.tobytes(),
                    name="dose_j_m2",
                    numeric_type=foxglove.FLOAT32,
                )
            )
        else:
            robot = topic[len(FOXGLOVE_PREFIX) + 1 : -len(MAP) - 1]
            held = self.maps.get(robot)
            if held is None or topic != map_topic(robot):
                return None
            t = wall if stamp is None else stamp
            cells8 = held.cells
            data = _dumps(
                foxglove.grid(
                    t,
                    origin=held.origin,
                    resolution=held.resolution,
                    width=int(cells8.shape[1]),
                    cells=cells8.tobytes(),
                    frame=self._frame(robot),
                )
            )
        return Record(self.channel(topic, foxglove.GRID), data, ns(wall), ns(t))

    def _frames(self, msg: FleetFrames, wall: float) -> Record:
        """``msg``'s transforms, of the frames found for the maps the robots' poses are in
        (``same_map``), as the latest frames record."""
        moves = [
            (foxglove.MAP_FRAME, robot_frame(f.robot, self._placings.get(f.robot, 0)), f.x, f.y, f.theta)
            for f in msg.frames
            if same_map(f.began, self._map_began.get(f.robot, 0.0), f.robot in self._named)
        ]
        data = _dumps(foxglove.frame_transforms(msg.header.timestamp, moves))
        channel = self.channel(FRAMES_TOPIC, foxglove.FRAME_TRANSFORMS)
        self.frames_record = Record(channel, data, ns(wall), ns(msg.header.timestamp))
        return self.frames_record

    def _frame(self, robot: str) -> str:
        """The frame ``robot``'s pose, scan and map are drawn in: its own map's while it reports in it."""
        return robot_frame(robot, self._placings.get(robot, 0)) if robot in self.own_frames else foxglove.MAP_FRAME

    def channel(self, topic: str, schema: str) -> Channel:
        """The Foxglove channel ``topic`` of schema ``schema`` (made once)."""
        found = self._channels.get(topic)
        if found is None:
            found = self._channels[topic] = Channel(topic, schema, foxglove.schema_bytes(schema), "foxglove")
        return found

    # -- layers ---------------------------------------------------------------------------------

    def _map(self, msg: MapSnapshot | MapUpdate) -> bool:
        robot = msg.header.robot
        held = self.maps.get(robot)
        try:
            if isinstance(msg, MapSnapshot):
                if held is not None and (held.began, held.version) == (msg.began, msg.version):
                    return False  # the same map again (both links, or a second fetch)
                self.maps[robot] = SharedMap.from_snapshot(msg)
                return True
            if held is None or held.began != msg.began:
                self._want.add((robot, MAP))  # none yet, or its agent began a new map
                return False
            if held.version >= msg.version:
                return False
            if not held.apply(msg):
                self._want.add((robot, MAP))
                return False
        except ValueError as exc:
            self._reject(f"bad map cells: {exc}")
            return False
        return True

    def _dose(self, msg: DoseSnapshot | DoseUpdate) -> bool:
        robot = msg.header.robot
        held = self.doses.get(robot)
        try:
            if isinstance(msg, DoseSnapshot):
                if held is not None and held.version >= msg.version and robot not in self._restarted:
                    return False  # the same layer again, or an older one
                self.doses[robot] = SharedDose.from_snapshot(msg)
                self._restarted.discard(robot)
                return True
            if held is None:
                self._want.add((robot, DOSE))
                return False
            if held.apply(msg):
                return True
            if msg.version > held.version:
                self._want.add((robot, DOSE))  # missed one, or the layer grew
            elif msg.base_version < held.version and msg.version < held.version:
                self._want.add((robot, DOSE))  # the agent restarted: its layer starts again
                self._restarted.add(robot)
        except (wire.WireError, ValueError) as exc:
            self._reject(f"bad dose cells: {exc}")
        return False
