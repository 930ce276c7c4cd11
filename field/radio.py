"""The field's radio: where each of a robot's links (Zenoh, MQTT) reaches it. Pure: no I/O, no time.

A plan's access points (``[[access_points]]``: a name, a position, the links it carries, a
transmit power) and dead zones (``[[dead_zones]]``: polygons where nothing gets through) make a
``RadioModel`` (docs/field-plans.md, "Radio"). At a point, each access point's received power is

    P_rx = tx_power_dbm - reference_loss_db - 10 * path_loss_exponent * log10(max(d, 1 m))
           - wall_loss_db * (the plan's walls crossed by the line of sight)

(the log-distance model with a per-wall loss), and a link's level is the best of the access points
that carry it. A link is reachable where its level is at least ``sensitivity_dbm``; once up it stays
up down to ``sensitivity_dbm - hysteresis_db``, so a robot standing on the edge does not flap
(``RadioTracker`` keeps that state per robot). Inside a dead zone every link is down. A link no
access point carries is not modelled: it reaches everywhere but the dead zones. A plan with neither
access points nor dead zones reaches everywhere (``RadioModel.enabled`` is False), as before the
radio existed.

Walls are the plan's ``walls`` only: doors (open or closed), obstacles and cliffs do not attenuate.
Deterministic: no random draw.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated

import numpy as np
import numpy.typing as npt

from fleetlink.shared.config import Invalid, Setting
from fleetlink.shared.geometry import Point, Segment, point_in_polygon
from fleetlink.shared.messages import LinkName

if TYPE_CHECKING:
    from fleetlink.field.plans import FloorPlan

__all__ = [
    "LINKS",
    "AccessPoint",
    "ContactLog",
    "FleetRadio",
    "RadioModel",
    "RadioSettings",
    "RadioTracker",
    "walls_crossed",
]

LINKS: tuple[LinkName, ...] = (LinkName.ZENOH, LinkName.MQTT)
"""The links the radio decides, in a fixed order."""

REFERENCE_DISTANCE_M = 1.0
"""The reference loss is the loss at this distance; nearer counts as this near."""

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class RadioSettings:
    """A plan's ``[radio]`` table: the model's constants (defaults: 2.4 GHz Wi-Fi indoors)."""

    sensitivity_dbm: Annotated[
        float, Setting(lo=-130.0, hi=0.0, doc="a link is reachable at or above this received power")
    ] = -80.0
    reference_loss_db: Annotated[float, Setting(lo=0.0, hi=120.0, doc="path loss at 1 m")] = 40.0
    path_loss_exponent: Annotated[
        float, Setting(lo=1.0, hi=6.0, doc="log-distance exponent (2 free space, 3 indoors)")
    ] = 3.0
    wall_loss_db: Annotated[float, Setting(lo=0.0, hi=60.0, doc="loss per wall crossed")] = 5.0
    hysteresis_db: Annotated[
        float, Setting(lo=0.0, hi=30.0, doc="an up link stays up down to sensitivity - hysteresis")
    ] = 3.0

    def problems(self) -> list[tuple[str, str]]:
        """(key, problem) for every value a plan built in Python got wrong (TOML is checked by the schema)."""
        out: list[tuple[str, str]] = []
        for key in ("sensitivity_dbm", "reference_loss_db", "path_loss_exponent", "wall_loss_db", "hysteresis_db"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                out.append((key, f"expected a finite number, got {v!r}"))
        if not out:
            if self.path_loss_exponent <= 0:
                out.append(("path_loss_exponent", f"must be > 0, got {self.path_loss_exponent:g}"))
            if self.hysteresis_db < 0:
                out.append(("hysteresis_db", f"must be >= 0, got {self.hysteresis_db:g}"))
        return out


def _links(value: Sequence[LinkName]) -> tuple[LinkName, ...]:
    if len(set(value)) != len(value):
        raise Invalid("", f"a link is named twice in {[str(v) for v in value]}")
    return tuple(value)


@dataclass(frozen=True, slots=True)
class AccessPoint:
    """One ``[[access_points]]`` entry: a Wi-Fi access point (or a broker's radio) in the plan's frame."""

    name: str
    x: float  # m
    y: float  # m
    links: Annotated[
        tuple[LinkName, ...], Setting(min_len=1, convert=_links, doc="the links it carries: zenoh, mqtt or both")
    ] = LINKS
    tx_power_dbm: Annotated[float, Setting(lo=-40.0, hi=40.0, doc="transmit power (EIRP)")] = 20.0


def walls_crossed(walls: Iterable[Segment], x0: float, y0: float, x: float, y: float) -> int:
    """How many of ``walls`` (x1, y1, x2, y2 each) the segment (x0, y0)-(x, y) crosses.

    Ends touching a wall do not count (an access point on a wall, a robot against one); a wall
    parallel to the line never counts. ``field/floor.py``'s ``ray_cast`` finds the nearest hit of
    a ray; this counts every hit of a bounded segment, for many walls at once."""
    return int(_Sight(np.array(list(walls), dtype=np.float64).reshape(-1, 4), np.array([[x0, y0]])).crossed(x, y)[0])


class _Sight:
    """Walls crossed on the lines of sight from fixed origins (the access points) to any point.

    With d = point - origin, e = wall end - wall start and w = wall start - origin, the line meets
    the wall's line at t = (w x e) / (d x e) along the sight and u = (w x d) / (d x e) along the
    wall; ``w x e`` does not depend on the point, so it is computed once."""

    def __init__(self, walls: FloatArray, origins: FloatArray) -> None:
        self.ox = origins[:, 0][:, None]  # (A, 1)
        self.oy = origins[:, 1][:, None]
        self.ex = (walls[:, 2] - walls[:, 0])[None, :]  # (1, W)
        self.ey = (walls[:, 3] - walls[:, 1])[None, :]
        self.wx = walls[:, 0][None, :] - self.ox  # (A, W)
        self.wy = walls[:, 1][None, :] - self.oy
        self.w_e = self.wx * self.ey - self.wy * self.ex
        self.empty = walls.shape[0] == 0 or origins.shape[0] == 0
        self.count = origins.shape[0]

    def crossed(self, x: float, y: float) -> npt.NDArray[np.int64]:
        """Walls crossed from each origin to (x, y): an (A,) count."""
        if self.empty:
            return np.zeros(self.count, dtype=np.int64)
        dx = x - self.ox  # (A, 1): the lines of sight
        dy = y - self.oy
        d_e = dx * self.ey - dy * self.ex  # (A, W)
        w_d = self.wx * dy - self.wy * dx
        # 0 < t < 1 and 0 <= u < 1 without dividing: scale both by d x e (sign s, size m).
        s = np.sign(d_e)
        m = np.abs(d_e)
        tm, um = self.w_e * s, w_d * s
        eps = 1e-9 * m
        hit = (m > 1e-12) & (tm > eps) & (tm < m - eps) & (um >= 0.0) & (um < m)
        return np.asarray(np.count_nonzero(hit, axis=1), dtype=np.int64)


class RadioModel:
    """Received power and reachability per link at any point of a plan. See the module docstring."""

    def __init__(
        self,
        access_points: Iterable[AccessPoint] = (),
        walls: Iterable[Segment] = (),
        dead_zones: Iterable[Sequence[Point]] = (),
        settings: RadioSettings | None = None,
    ) -> None:
        self.access_points = tuple(access_points)
        self.dead_zones: tuple[tuple[Point, ...], ...] = tuple(tuple(p) for p in dead_zones)
        self.settings = settings or RadioSettings()
        self._origins: FloatArray = np.array([(a.x, a.y) for a in self.access_points], dtype=np.float64).reshape(-1, 2)
        self._sight = _Sight(np.array(list(walls), dtype=np.float64).reshape(-1, 4), self._origins)
        self._tx: FloatArray = np.array([a.tx_power_dbm for a in self.access_points], dtype=np.float64)
        self._carries: dict[LinkName, npt.NDArray[np.bool_]] = {
            link: np.array([link in a.links for a in self.access_points], dtype=bool) for link in LINKS
        }
        self.modelled: tuple[LinkName, ...] = tuple(link for link in LINKS if self._carries[link].any())
        """The links some access point carries (the others reach everywhere but the dead zones)."""
        self._boxes = tuple(
            (min(p[0] for p in z), min(p[1] for p in z), max(p[0] for p in z), max(p[1] for p in z))
            for z in self.dead_zones
        )

    @classmethod
    def from_plan(cls, plan: FloorPlan) -> RadioModel:
        """The plan's access points, walls, dead zones and ``[radio]`` settings."""
        return cls(plan.access_points, plan.walls, plan.dead_zones, plan.radio)

    @property
    def enabled(self) -> bool:
        """False when the plan has neither access points nor dead zones: every link reaches everywhere."""
        return bool(self.access_points or self.dead_zones)

    def in_dead_zone(self, x: float, y: float) -> bool:
        for (x0, y0, x1, y1), zone in zip(self._boxes, self.dead_zones, strict=True):
            if x0 <= x <= x1 and y0 <= y <= y1 and point_in_polygon(x, y, zone):
                return True
        return False

    def powers(self, x: float, y: float) -> FloatArray:
        """Each access point's received power at (x, y), dBm (in the plan's order; -inf in a dead zone)."""
        if self.in_dead_zone(x, y):
            return np.full(len(self.access_points), -math.inf)
        return self._powers(x, y)

    def _powers(self, x: float, y: float) -> FloatArray:
        """``powers`` as if no dead zone were there."""
        if not self.access_points:
            return np.zeros(0)
        s = self.settings
        d = np.hypot(self._origins[:, 0] - x, self._origins[:, 1] - y)
        loss = s.reference_loss_db + 10.0 * s.path_loss_exponent * np.log10(np.maximum(d, REFERENCE_DISTANCE_M))
        walls = self._sight.crossed(x, y)
        return np.asarray(self._tx - loss - s.wall_loss_db * walls, dtype=np.float64)

    def levels(self, x: float, y: float, *, dead_zones: bool = True) -> dict[LinkName, float]:
        """Each modelled link's best received power at (x, y), dBm (-inf in a dead zone, unless
        ``dead_zones`` is False)."""
        p = self.powers(x, y) if dead_zones else self._powers(x, y)
        return {link: float(p[self._carries[link]].max()) for link in self.modelled}

    def reachable(self, link: LinkName, x: float, y: float, was_up: bool | None = None) -> bool:
        """Does ``link`` reach (x, y)? ``was_up`` True: it stays up down to sensitivity - hysteresis;
        False or None (no history): it needs the sensitivity."""
        return self.reachable_all(x, y, {link: bool(was_up)})[link]

    def reachable_all(
        self, x: float, y: float, was_up: Mapping[LinkName, bool], levels: Mapping[LinkName, float] | None = None
    ) -> dict[LinkName, bool]:
        """``reachable`` for every link of ``was_up`` at once (one pass over the access points);
        ``levels``: ``levels(x, y, dead_zones=False)`` if the caller has them (dead zones are
        checked here in any case)."""
        if not self.enabled:
            return dict.fromkeys(was_up, True)
        if self.in_dead_zone(x, y):
            return dict.fromkeys(was_up, False)
        s = self.settings
        if levels is None:
            levels = self.levels(x, y, dead_zones=False) if self.modelled else {}
        out: dict[LinkName, bool] = {}
        for link, up in was_up.items():
            level = levels.get(link)
            if level is None:
                out[link] = True  # no access point carries it: not modelled
            else:
                out[link] = level >= s.sensitivity_dbm - (s.hysteresis_db if up else 0.0)
        return out


class RadioTracker:
    """One robot's links under a ``RadioModel``, with hysteresis: ``update(x, y)`` at each new pose.

    ``up`` holds each link's state; before the first ``update`` every link is up (give the start
    pose as ``x``, ``y`` to begin from it instead, judged without hysteresis). Received levels are
    computed again once the robot has moved ``resolution_m`` from where they last were (a step of
    the physics moves it millimetres; a robot at rest costs nothing); dead zones are checked at
    every pose."""

    def __init__(
        self, model: RadioModel, x: float | None = None, y: float | None = None, *, resolution_m: float = 0.02
    ) -> None:
        self.model = model
        self.resolution_m = resolution_m
        self.up: dict[LinkName, bool] = dict.fromkeys(LINKS, True)
        self._at: tuple[float, float] | None = None
        self._levels: dict[LinkName, float] = {}
        self._levels_at = (math.inf, math.inf)
        if x is not None and y is not None:
            self.up = model.reachable_all(x, y, dict.fromkeys(LINKS, False), self._levels_for(x, y))
            self._at = (x, y)

    def _levels_for(self, x: float, y: float) -> dict[LinkName, float]:
        lx, ly = self._levels_at
        if math.hypot(x - lx, y - ly) >= self.resolution_m:
            self._levels = self.model.levels(x, y, dead_zones=False)
            self._levels_at = (x, y)
        return self._levels

    def update(self, x: float, y: float) -> tuple[LinkName, ...]:
        """The links whose state changed at (x, y) (in ``LINKS`` order)."""
        if not self.model.enabled or (x, y) == self._at:
            return ()  # a robot at rest: nothing changes (hysteresis keeps whatever it decided here)
        self._at = (x, y)
        now = self.model.reachable_all(x, y, self.up, self._levels_for(x, y))
        changed = tuple(link for link in LINKS if now[link] != self.up[link])
        self.up = now
        return changed

    def reachable(self, link: LinkName) -> bool:
        return self.up[link]

    @property
    def in_contact(self) -> bool:
        """At least one link reaches the robot."""
        return any(self.up.values())


class FleetRadio:
    """Every robot's ``RadioTracker``: ``update(robot, x, y)`` with its true pose, then
    ``reachable(robot, link)`` (any thread may read while one thread updates)."""

    def __init__(self, model: RadioModel, poses: Mapping[str, tuple[float, float]]) -> None:
        self.model = model
        self.trackers = {name: RadioTracker(model, x, y) for name, (x, y) in poses.items()}

    def update(self, robot: str, x: float, y: float) -> tuple[LinkName, ...]:
        """The robot's links whose state changed at (x, y)."""
        return self.trackers[robot].update(x, y)

    def reachable(self, robot: str, link: LinkName) -> bool:
        return self.trackers[robot].up[link]


class ContactLog:
    """When each robot was out of contact: ``update(robot, t, in_contact)`` at every step, then
    ``intervals[robot]`` holds (t_lost, t_regained) pairs, t_regained None while still lost."""

    def __init__(self, robots: Iterable[str] = ()) -> None:
        self.intervals: dict[str, list[tuple[float, float | None]]] = {r: [] for r in robots}

    def update(self, robot: str, t: float, in_contact: bool) -> bool:
        """Record the robot's contact at ``t``; True if it changed."""
        spans = self.intervals.setdefault(robot, [])
        lost = bool(spans) and spans[-1][1] is None
        if lost and in_contact:
            spans[-1] = (spans[-1][0], t)
            return True
        if not lost and not in_contact:
            spans.append((t, None))
            return True
        return False

    def lost_seconds(self, robot: str, until: float) -> float:
        """Seconds the robot spent out of contact up to ``until`` (an open interval counts to it)."""
        return sum((until if b is None else b) - a for a, b in self.intervals.get(robot, []))
