"""The other robots of the site as bodies to plan around and not to drive into (pure, no I/O).

An agent hears the fused poses its peers publish (``fleetlink/v1/<peer>/pose``, the robots named in
robot.toml's ``peers``) and keeps the latest of each. When its pilot plans a leg, the peers that
stand still, in the site frame, are handed to the planner as ``bodies``: discs of the planner's
``body_radius``, inflated like walls. Not as ``blocked`` points, which the planner drops near a
mapped wall (an echo off a known wall is that wall): a robot's centre stands a radius behind the
face its lidar maps.

Why: the lidar sees only a robot's near face, and a robot's map takes a standing robot in a turn
every few seconds; a leg laid before then, or to a goal just behind that face, ran into it (the
bedroom's two-robot UV round at seed 16: uvc-1's last leg to a dwell point 0.1 m from where uvc-2
stood, finished, passed 0.24 m from its centre, off the ultrasonic's axis). Where a peer says it
stands is known to the centimetre with UWB.

The collision guard is also handed the peers in the robot's way (``robots_ahead``, any placed peer,
moving or not: agent/guard.py): how far the robot can drive straight on before its body would touch
each, and how fast each comes toward it, since the front ultrasonic sees nothing inside its 0.25 m
minimum and a robot is no wall the map vouches for. A peer's pose is moved on to now by its own
speed (it is up to a pose period old, more over the fallback link). While this robot's heading is
not known yet (UWB places it before it has driven), every peer near enough counts, whichever way.

Only standing peers are planned around: a moving one is somewhere else by the time the leg is
driven, and would bar doorways it has already left (the guard and the re-plans answer a moving
robot).

**Which frame.** A pose counts only where this robot can put it in its own frame. Placed robots (UWB)
share the site frame. A robot without UWB publishes its pose in its own map's frame, which begins
where it started; the fleet map service finds each such map on the others' and publishes where each
frame lies on the fleet map (``FleetFrames``, ``fleetlink/v1/fleet/frames``: site/fleetmap.py). With
those, a peer in its own frame is put in this robot's frame (its frame onto the fleet map, then back
through this robot's), whether this robot is placed or not, so two scouts in a building without UWB
keep clear of each other once the fleet map has found both. Without them (no fleet map service, or
it has not found the map yet, or its frames are older than ``frames_fresh_s``) such a peer is not
counted, as before: the guard's ultrasonic is all there is between them.

A frame is of one map: each ``RobotFrame`` names the map it was found for (``began``) and each pose
the map it is in (``Pose.map_began``). A robot whose agent restarted begins a new map where it then
stands, and the old frame would put it where the old map began; so a frame counts only for poses of
its own map (this robot's too), until the fleet map finds the new one (a build or two).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fleetlink.agent.guard import RobotAhead
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.shared.messages import UNKNOWN_SD_M, FleetFrames, Pose, same_map
from fleetlink.shared.se2 import Pose as Frame
from fleetlink.shared.se2 import compose, inverse

__all__ = ["PeerBodies", "PeerConfig"]

Point = tuple[float, float]
_SAME: Frame = (0.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class PeerConfig:
    fresh_s: float = 1.0
    """A peer's pose older than this (by the receiver's clock) is forgotten: poses come at 20 Hz."""
    standing_mps: float = 0.02
    """At most this forward speed ..."""
    standing_radps: float = 0.05
    """... and this turn rate, a peer stands."""
    placed_sd_m: float = 0.5
    """A pose whose position sd is over this is not placed in the site frame (``UNKNOWN_SD_M``)."""
    body_radius_m: float = BODY_RADIUS_M
    """Every robot's body, this one's too (the fleet's robots are alike)."""
    lane_margin_m: float = 0.02
    """``robots_ahead`` counts a robot in the way if the bodies would pass closer than this (pose error)
    ..."""
    margin_sds: float = 1.5
    """... or than this many sd of where the peer lies across this robot's way, if more: both poses'
    position sd and this robot's heading sd times the distance between them. A robot driven off as soon
    as UWB has placed it knows its heading to 3-4 degrees and its position to 2-3 cm, and passing a
    peer 0.33 m to the side (bodies 0.34 m) the fixed 2 cm let it believe the way clear until the
    bodies were centimetres apart (tests/test_robots_meeting.py, the apartment: it bumped). At 1.5 sd it
    stops 0.41 m from it centre to centre (1 sd: 0.375 m, 2 sd: 0.44 m); the two-robot UV round in the
    bedroom (bench/coverage.py, seed 16) takes 187 s (2 sd: 195 s, past 0.6x one robot's 320 s)."""
    extrapolate_s: float = 0.25
    """A moving peer's pose is moved on by its speed for at most this long: a few pose periods (20 Hz
    on Zenoh, 10 on MQTT); poses that stop coming say nothing of where it went after."""
    step_back_s: float = 0.25
    """A pose stamped before the one kept is a late copy from the other link, unless the kept one was
    received this long ago: then the peer's clock stepped back (or it restarted), and the pose is news."""
    frames_fresh_s: float = 30.0
    """The fleet map's frames (``FleetFrames``) older than this are not used: the service sends them
    every 5 s (site/fleetmap.py ``FRAMES_PERIOD_S``), so this is several missed in a row."""
    framed_sd_m: float = 0.05
    """How well a robot in its own frame is known on the fleet map (its position sd there, for the
    margin): where the fleet map's search put its frame, measured within 3 cm on the hall's two scouts
    (docs/mapping.md, "The fleet map"), and where its own map puts it on that frame."""


@dataclass(frozen=True, slots=True)
class _Heard:
    at: float  # the receiver's clock
    stamp: float  # the peer's header timestamp (a late copy on the other link does not go back)
    x: float
    y: float
    theta: float
    vx: float
    standing: bool
    placed: bool
    sd: float  # its position sd (m), as it reports it (a placed peer's is at most ``placed_sd_m``)
    began: float  # the map its pose is in (``Pose.map_began``; 0: not said)
    named: bool  # its poses have named a map before (``same_map``)


@dataclass(frozen=True, slots=True)
class _Frames:
    """The fleet map's frames as last heard: ``reference`` "" when the fleet map's frame is the site's."""

    at: float
    reference: str
    frames: dict[str, tuple[Frame, float]]
    """Robot -> its frame on the fleet map, and which of its maps that frame was found for (``began``)."""


@dataclass(frozen=True, slots=True)
class _Placed:
    """A fresh peer put in this robot's frame."""

    heard: _Heard
    x: float
    y: float
    theta: float
    sd: float


class PeerBodies:
    """The latest pose of each peer; ``standing(now)``: where the placed, still ones stand."""

    def __init__(self, peers: tuple[str, ...] = (), config: PeerConfig | None = None, *, robot: str = "") -> None:
        """``robot``: this robot's id, to find its own frame among the fleet map's."""
        self.peers = frozenset(peers)
        self.config = config or PeerConfig()
        self.robot = robot
        self.began = 0.0
        """When this robot's own map began (``Pose.map_began``): its frame among the fleet map's is
        the one found for that map."""
        self._heard: dict[str, _Heard] = {}
        self._frames: _Frames | None = None

    def hear(self, robot: str, pose: Pose, now: float) -> bool:
        """``robot``'s fused pose, received at ``now``. False (ignored) for a robot that is not a
        peer, or a copy older than the pose already kept (the same pose sent on both links)."""
        if robot not in self.peers:
            return False
        last = self._heard.get(robot)
        stamp = pose.header.timestamp
        c = self.config
        if last is not None and stamp <= last.stamp and now - last.at < c.step_back_s:
            return False
        standing = abs(pose.vx) <= c.standing_mps and abs(pose.omega) <= c.standing_radps
        sd = max(pose.sd_x_m, pose.sd_y_m)
        placed = sd <= min(c.placed_sd_m, UNKNOWN_SD_M)
        # (The wire contract's bounds say all of these are finite too.)
        ok = all(math.isfinite(v) for v in (pose.x, pose.y, pose.theta, pose.vx))
        named = pose.map_began != 0.0 or (last is not None and last.named)
        self._heard[robot] = _Heard(
            now, stamp, pose.x, pose.y, pose.theta, pose.vx, standing and ok, placed and ok, sd, pose.map_began, named
        )
        return True

    def hear_frames(self, msg: FleetFrames, now: float) -> bool:
        """Where the robots in their own frames lie on the fleet map, received at ``now``. Two services
        may briefly disagree while one has not heard a placed robot's map: one whose frame is the site's
        is kept over one that is a robot's own for as long as it is fresh. False: not taken."""
        kept = self._frames
        if msg.reference and kept is not None and not kept.reference and now - kept.at <= self.config.frames_fresh_s:
            return False
        frames = {f.robot: ((f.x, f.y, f.theta), f.began) for f in msg.frames}
        self._frames = _Frames(now, msg.reference, frames)
        return True

    def _fresh_frames(self, now: float) -> _Frames | None:
        """The fleet map's frames, unless older than ``frames_fresh_s``."""
        f = self._frames
        return f if f is not None and now - f.at <= self.config.frames_fresh_s else None

    def framed(self, now: float) -> tuple[str, ...]:
        """The robots whose own frames the fleet map's frames (fresh) place, by name."""
        f = self._fresh_frames(now)
        return () if f is None else tuple(sorted(f.frames))

    def _frame_of(self, robot: str, placed: bool, began: float, named: bool, now: float) -> tuple[str, Frame] | None:
        """The frame ``robot``'s poses (of its map begun at ``began``; ``named``: its poses have named
        a map before) are in (a name: "" the site's, else the fleet map's reference robot's) and how
        its frame lies in it; None: in a frame no one else's can be put in (not found, or found for
        another of its maps: ``same_map``)."""
        if placed:
            return "", _SAME
        f = self._fresh_frames(now)
        found = None if f is None else f.frames.get(robot)
        if f is None or found is None or not same_map(found[1], began, named):
            return None
        return f.reference, found[0]

    def _placed(self, now: float, me_placed: bool) -> list[_Placed]:
        """The peers heard within ``fresh_s`` whose poses can be put in this robot's frame, put there."""
        mine = self._frame_of(self.robot, me_placed, self.began, True, now)
        if mine is None:
            return []
        back = inverse(mine[1])
        out: list[_Placed] = []
        for name, h in sorted(self._heard.items()):
            if not self._fresh(h, now) or not all(math.isfinite(v) for v in (h.x, h.y, h.theta, h.vx)):
                continue
            theirs = self._frame_of(name, h.placed, h.began, h.named, now)
            if theirs is None or theirs[0] != mine[0]:
                continue
            x, y, th = compose(back, compose(theirs[1], (h.x, h.y, h.theta)))
            out.append(_Placed(h, x, y, th, h.sd if h.placed else self.config.framed_sd_m))
        return out

    def _fresh(self, h: _Heard, now: float) -> bool:
        # No lower bound: the control tick may read the clock just before a pose is taken in.
        return now - h.at <= self.config.fresh_s

    def has_heard(self, robot: str) -> bool:
        """Whether ``robot``'s pose has been taken at least once."""
        return robot in self._heard

    def heard_from(self) -> tuple[str, ...]:
        """The peers heard at least once, by name."""
        return tuple(sorted(self._heard))

    def robots_ahead(
        self,
        now: float,
        pose: tuple[float, float, float],
        heading_known: bool = True,
        sd_xy: float = 0.0,
        sd_theta: float = 0.0,
        placed: bool = True,
    ) -> tuple[RobotAhead, ...]:
        """The peers heard within ``fresh_s``, standing or moving, that can be put in this robot's
        frame, whose bodies lie in the way of this one's (at ``pose``, its position sd ``sd_xy`` and
        heading sd ``sd_theta``) driving straight on: how far it drives before they touch (0: they
        touch already, ahead or beside) and how fast each comes toward it. ``placed``: ``pose`` is in
        the site frame; else in this robot's own map's frame (where the fleet map's frames, if heard,
        put the others). Without ``heading_known`` every peer counts, its gap the distance between the
        bodies. The bodies are taken to touch ``lane_margin_m`` apart, or ``margin_sds`` sd of where
        the peer lies across the way, if more."""
        c = self.config
        x, y, th = pose
        if not all(math.isfinite(v) for v in pose):
            return ()
        cos, sin = math.cos(th), math.sin(th)
        # Not finite (not known): no more than the fixed margin from it; ``heading_known`` says the rest.
        sd_xy = sd_xy if math.isfinite(sd_xy) else 0.0
        sd_theta = sd_theta if math.isfinite(sd_theta) else 0.0
        if not placed:  # its own frame: where the fleet map put it is known to its search's few cm
            sd_xy = max(sd_xy, c.framed_sd_m)
        out: list[RobotAhead] = []
        for p in self._placed(now, placed):
            h = p.heard
            age = min(max(0.0, now - h.at), c.extrapolate_s)
            hx, hy = p.x + h.vx * age * math.cos(p.theta), p.y + h.vx * age * math.sin(p.theta)
            dx, dy = hx - x, hy - y
            apart = math.hypot(dx, dy)
            # Its speed along the line from it to this robot (positive: coming closer).
            closing = max(0.0, -h.vx * (dx * math.cos(p.theta) + dy * math.sin(p.theta)) / apart) if apart > 0 else 0.0
            ahead, side = cos * dx + sin * dy, -sin * dx + cos * dy
            across = math.sqrt(sd_xy**2 + p.sd**2 + (apart * sd_theta) ** 2)
            reach = 2.0 * c.body_radius_m + max(c.lane_margin_m, c.margin_sds * across)  # centre to centre
            if not heading_known:
                gap: float | None = max(0.0, apart - reach)
            elif apart < reach:
                gap = 0.0 if ahead > 0.0 else None  # touching: forward refused unless it lies behind
            elif ahead > 0.0 and abs(side) < reach:
                gap = ahead - math.sqrt(reach * reach - side * side)
            else:
                gap = None
            if gap is not None:
                out.append(RobotAhead(gap, closing))
        return tuple(sorted(out, key=lambda r: r.gap_m))

    def standing(self, now: float, placed: bool = True) -> tuple[Point, ...]:
        """Where the peers heard within ``fresh_s`` stand still, in this robot's frame (``placed``: the
        site frame; else its own map's), by robot name: those that can be put in it."""
        return tuple((p.x, p.y) for p in self._placed(now, placed) if p.heard.standing)
