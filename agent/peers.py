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
robot). Only poses in
the site frame count, and only while the robot itself is placed in it: an unplaced robot's pose is
in its own map's frame, which no one else shares.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fleetlink.agent.guard import RobotAhead
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.shared.messages import UNKNOWN_SD_M, Pose

__all__ = ["PeerBodies", "PeerConfig"]

Point = tuple[float, float]


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


class PeerBodies:
    """The latest pose of each peer; ``standing(now)``: where the placed, still ones stand."""

    def __init__(self, peers: tuple[str, ...] = (), config: PeerConfig | None = None) -> None:
        self.peers = frozenset(peers)
        self.config = config or PeerConfig()
        self._heard: dict[str, _Heard] = {}

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
        self._heard[robot] = _Heard(now, stamp, pose.x, pose.y, pose.theta, pose.vx, standing and ok, placed and ok, sd)
        return True

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
    ) -> tuple[RobotAhead, ...]:
        """The placed peers heard within ``fresh_s``, standing or moving, whose bodies lie in the way
        of this one's (at ``pose``, site frame, its position sd ``sd_xy`` and heading sd ``sd_theta``)
        driving straight on: how far it drives before they touch (0: they touch already, ahead or
        beside) and how fast each comes toward it. Without ``heading_known`` every peer counts, its gap
        the distance between the bodies. The bodies are taken to touch ``lane_margin_m`` apart, or
        ``margin_sds`` sd of where the peer lies across the way, if more."""
        c = self.config
        x, y, th = pose
        if not all(math.isfinite(v) for v in pose):
            return ()
        cos, sin = math.cos(th), math.sin(th)
        # Not finite (not known): no more than the fixed margin from it; ``heading_known`` says the rest.
        sd_xy = sd_xy if math.isfinite(sd_xy) else 0.0
        sd_theta = sd_theta if math.isfinite(sd_theta) else 0.0
        out: list[RobotAhead] = []
        for h in self._heard.values():
            if not h.placed or not self._fresh(h, now):
                continue
            age = min(max(0.0, now - h.at), c.extrapolate_s)
            hx, hy = h.x + h.vx * age * math.cos(h.theta), h.y + h.vx * age * math.sin(h.theta)
            dx, dy = hx - x, hy - y
            apart = math.hypot(dx, dy)
            # Its speed along the line from it to this robot (positive: coming closer).
            closing = max(0.0, -h.vx * (dx * math.cos(h.theta) + dy * math.sin(h.theta)) / apart) if apart > 0 else 0.0
            ahead, side = cos * dx + sin * dy, -sin * dx + cos * dy
            across = math.sqrt(sd_xy**2 + h.sd**2 + (apart * sd_theta) ** 2)
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

    def standing(self, now: float) -> tuple[Point, ...]:
        """Where the peers heard within ``fresh_s`` stand still in the site frame, by robot name."""
        return tuple(
            (h.x, h.y) for _, h in sorted(self._heard.items()) if h.standing and h.placed and self._fresh(h, now)
        )
