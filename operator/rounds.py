"""Disinfection and sweeping rounds: what an operator asks for, what comes back. Pure: no I/O.

    request = RoundRequest("uv", RoomArea(2.0, 1.5), ("uvc-1", "uvc-2"), target_j_m2=100.0)
    check_request(request)                       # RoundError with the reason, before any planning
    cells, resolution, origin = floor_of(grids)  # the robots' maps as the console holds them, merged
    plan = planner(request, cells, resolution, origin, starts, lamp, order_ids)   # a RoundPlan
    plan.summary()                               # the prediction, for the operator's notices
    for r in plan.rounds: Order(header=..., **r.order)

The planning itself is the agent's coverage planner (agent/coverage.py: ``plan_uv``, ``split_plan``,
``plan_sweep``, ``plan_order``). The operator side may not import the agent's packages (the layering
contract in pyproject.toml), so the console is handed a ``RoundPlanner`` by whoever starts it:
``fleetlink.site.rounds.plan_round`` (cli/console.py, the tests' console rig). This module holds
what both sides share: the request, its checks, the result, the order ids, the map as a planner
takes it, and the console's default lamp (the agent's ``[uv]`` defaults, deploy/robot.example.toml).

A round's orders are ordinary VDA 5050 orders with nodes (docs/payload.md, "Running a round"):
node 0 where the robot stands, then a node per dwell point (UV: lamp on, ``dwell``, lamp off once
nothing lit follows) or per lane end (sweep), edges between them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from fleetlink.shared.dose import DEFAULT_TARGET_J_M2, J_M2_PER_MJ_CM2, DoseGrid, Lamp
from fleetlink.shared.geometry import components
from fleetlink.shared.keys import is_valid_id
from fleetlink.shared.messages import MAX_COORDINATE_M, MAX_ZONE_VERTICES

__all__ = [
    "DEFAULT_LAMP",
    "DEFAULT_TARGET_J_M2",
    "MAX_AREA_CORNERS",
    "MAX_SURVEYS",
    "AreaSpec",
    "PolyArea",
    "RectArea",
    "RobotRound",
    "RoomArea",
    "RoundError",
    "RoundIds",
    "RoundKind",
    "RoundPlan",
    "RoundPlanner",
    "RoundRequest",
    "RouteNode",
    "check_request",
    "describe_area",
    "describe_time",
    "floor_of",
    "mj_cm2",
    "robots_off",
]

Point = tuple[float, float]
Grid = tuple[float, float, float, int, int, bytes]
"""A drawable map as the fleet model keeps it (``operator/fleet.py`` ``Grid``): origin x, y,
resolution, width, height, cells row by row from the bottom (0 free, 100 occupied, 255 unknown)."""

RoundKind = Literal["uv", "sweep"]

MAX_SURVEYS = 2
"""Survey passes the console allows before a round (a pocket seen into may show another behind it)."""

DEFAULT_LAMP = Lamp(uvc_power_w=10.0, height_m=0.6, tube_length_m=0.0, min_distance_m=0.3)
"""The lamp a round is planned for when the console knows no better: the agent's ``[uv]`` example
(deploy/robot.example.toml: 10 W of UV-C, 0.6 m up, a point source) and ``Lamp``'s own defaults."""
MAX_AREA_CORNERS = MAX_ZONE_VERTICES
"""Corners of a polygon area (as a people-present zone's)."""


def mj_cm2(j_m2: float) -> float:
    """J/m² in mJ/cm² (what operators quote: 10 mJ/cm² = 100 J/m²)."""
    return j_m2 / J_M2_PER_MJ_CM2


class RoundError(ValueError):
    """A round that cannot be planned or sent; the message is the operator's notice."""


# -- the request --------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class RoomArea:
    """The room around a seed point (bounded by walls and doorways, agent/coverage.py ``room``)."""

    x: float
    y: float


@dataclass(frozen=True, slots=True)
class RectArea:
    """An axis-aligned rectangle given by two opposite corners."""

    x0: float
    y0: float
    x1: float
    y1: float


@dataclass(frozen=True, slots=True)
class PolyArea:
    """A simple polygon (its corners in order, either winding)."""

    corners: tuple[Point, ...]


AreaSpec = RoomArea | RectArea | PolyArea


def describe_area(area: AreaSpec) -> str:
    if isinstance(area, RoomArea):
        return f"the room at ({area.x:.2f}, {area.y:.2f})"
    if isinstance(area, RectArea):
        return f"the rectangle ({area.x0:.2f}, {area.y0:.2f})-({area.x1:.2f}, {area.y1:.2f})"
    return f"the polygon of {len(area.corners)} corners"


@dataclass(frozen=True, slots=True)
class RoundRequest:
    """A UV round (``uv``: the target dose on the area's floor) or a sweep, by ``robots`` (a sweep:
    one robot)."""

    kind: RoundKind
    area: AreaSpec
    robots: tuple[str, ...]
    target_j_m2: float = DEFAULT_TARGET_J_M2
    """J/m² (10 mJ/cm² = 100 J/m²); a sweep ignores it."""
    surveys: int = 0
    """Survey passes still allowed before the round itself: while the maps show unseen pockets
    beside the area's floor (what furniture hid from where the robots came in), the planner sends
    the robots to look first (lamp off), and the console plans again when they are done
    (``MAX_SURVEYS`` from the console; 0: plan on the map as it is)."""
    looked_from: tuple[tuple[float, float], ...] = ()
    """Where this round's earlier surveys looked from. What the planner thought could be seen from
    there and is still unseen is hidden by something the maps do not hold yet (a desk's unseen
    side): a later survey counts it as looked at from there and looks from elsewhere."""


def _finite(values: Sequence[float]) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) and abs(v) <= MAX_COORDINATE_M for v in values)


def check_request(request: RoundRequest) -> None:
    """What can be checked without a map: RoundError with the reason (a target dose of 0, NaN, or
    negative; no robot, a robot twice, a sweep by several robots; a coordinate that is not a finite
    number within the wire's range; a polygon with too few or too many corners)."""
    if request.kind not in ("uv", "sweep"):
        raise RoundError(f"unknown round {request.kind!r}: uv or sweep")
    if not request.robots:
        raise RoundError("a round needs a robot: select one, or name them with 'with ROBOT,ROBOT'")
    for robot in request.robots:
        if not is_valid_id(robot):
            raise RoundError(f"{robot!r} is not a robot id")
    if len(set(request.robots)) != len(request.robots):
        raise RoundError(f"a robot is named twice: {', '.join(request.robots)}")
    if request.kind == "sweep" and len(request.robots) > 1:
        raise RoundError("a sweep is for one robot (a UV round may be shared)")
    target = request.target_j_m2
    if request.kind == "uv" and not (isinstance(target, int | float) and math.isfinite(target) and target > 0):
        raise RoundError(
            f"target dose must be a finite number > 0 mJ/cm² (10 mJ/cm² = 100 J/m²), got {mj_cm2(target)!r}"
        )
    area = request.area
    if isinstance(area, RoomArea):
        numbers: list[float] = [area.x, area.y]
    elif isinstance(area, RectArea):
        numbers = [area.x0, area.y0, area.x1, area.y1]
    else:
        if not 3 <= len(area.corners) <= MAX_AREA_CORNERS:
            raise RoundError(f"a polygon takes 3 to {MAX_AREA_CORNERS} corners, got {len(area.corners)}")
        numbers = [v for corner in area.corners for v in corner]
    if not _finite(numbers):
        raise RoundError(f"{describe_area(area)}: coordinates must be finite numbers within {MAX_COORDINATE_M:g} m")


# -- the result ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class RouteNode:
    """A node of a robot's route: where, how long it dwells there (0: it drives through)."""

    node_id: str
    x: float
    y: float
    dwell_s: float


@dataclass(frozen=True, slots=True)
class RobotRound:
    """One robot's share: its order (``Order(**order)`` with a header), its route, its prediction."""

    robot: str
    order_id: str
    order: Mapping[str, Any]
    """The Order's fields: orderId, orderUpdateId, goal (None), returnHome (False), nodes, edges."""
    route: tuple[RouteNode, ...]
    total_s: float
    """Dwell + travel (the stops included)."""
    dwell_s: float
    path_m: float

    @property
    def dwell_points(self) -> int:
        return sum(1 for n in self.route if n.dwell_s > 0)


@dataclass(frozen=True, slots=True)
class RoundPlan:
    request: RoundRequest
    area_m2: float
    """The floor that counts (reachable floor inside the area)."""
    coverage: float
    """Predicted share of that floor at the target dose (UV, every robot together) or that the tool
    passes over (sweep, of the floor it can reach at all)."""
    unlit_m2: float
    """UV: floor inside the area that no place the robot may stand lights (not planned)."""
    rounds: tuple[RobotRound, ...]
    survey: bool = False
    """These orders only look (view points, lamp off) into what the maps have not seen: plan the
    request again (one survey fewer) when every robot has finished its order."""
    left_out: tuple[tuple[str, str], ...] = ()
    """(robot, why) for each of several robots the plan could not use (standing where it cannot
    start from, or cannot reach the area): the others share the round without it."""

    @property
    def total_s(self) -> float:
        """Until the last robot is done (the makespan)."""
        return max((r.total_s for r in self.rounds), default=0.0)

    @property
    def path_m(self) -> float:
        return sum(r.path_m for r in self.rounds)

    def summary(self) -> str:
        """One line for the operator: area, predicted coverage, time, path, and each robot's share."""
        req = self.request
        what = "UV round" if req.kind == "uv" else "sweep"
        if self.survey:
            shares = "; ".join(
                f"{r.robot} {describe_time(r.total_s)}, {r.dwell_points} view points" for r in self.rounds
            )
            return (
                f"survey before the {what} of {describe_area(req.area)}: {self.area_m2:.1f} m² beside its floor"
                f" not seen yet, {describe_time(self.total_s)}, path {self.path_m:.1f} m: {shares}"
            )
        dose = f" at {mj_cm2(req.target_j_m2):g} mJ/cm²" if req.kind == "uv" else " swept"
        unlit = f" ({self.unlit_m2:.1f} m² no lamp reaches)" if self.unlit_m2 >= 0.05 else ""
        shares = "; ".join(
            f"{r.robot} {describe_time(r.total_s)}, {len(r.route) - 1} nodes"
            + (f" ({r.dwell_points} dwell)" if req.kind == "uv" else "")
            for r in self.rounds
        )
        return (
            f"{what} of {describe_area(req.area)}: {self.area_m2:.1f} m², predicted {100 * self.coverage:.1f} %"
            f"{dose}{unlit}, {describe_time(self.total_s)}, path {self.path_m:.1f} m: {shares}"
        )


def describe_time(seconds: float) -> str:
    """'45 s', '12 min 5 s', '1 h 02 min'."""
    s = max(0, round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s"
    return f"{s // 3600} h {(s % 3600) // 60:02d} min"


RoundPlanner = Callable[
    [
        RoundRequest,
        npt.NDArray[np.int8],
        float,
        Point,
        Mapping[str, Point],
        Lamp,
        Mapping[str, str],
        DoseGrid | None,
    ],
    RoundPlan,
]
"""``planner(request, cells, resolution, origin, starts, lamp, order_ids, prior) -> RoundPlan``, or
RoundError (ValueError) with the reason: ``fleetlink.site.rounds.plan_round``. ``cells``: int8 map
cells as they travel (-1 unknown, 0-100), row 0 at ``origin``'s y; ``starts``: where each robot
stands; ``order_ids``: the order id for each robot; ``prior``: the dose the floor has had already
(the fleet's dose layer): a UV round tops it up to the target, and plans nothing where it is."""


class RoundIds:
    """Order ids for rounds, ``<kind>-<robot>-<n>``: ``n`` counts up from the wall clock's second
    when the first was made, so ids stay new across a console's restarts (an agent takes an order
    id it has run before, at update 0, for a copy)."""

    def __init__(self) -> None:
        self._n = 0

    def next(self, kind: RoundKind, robot: str, wall: float) -> str:
        self._n = max(self._n + 1, int(wall))
        return f"{kind}-{robot}-{self._n}"[:64]


# -- the map ------------------------------------------------------------------------------------


def floor_of(
    grids: Sequence[Grid], trails: Sequence[Sequence[Point]] | None = None
) -> tuple[npt.NDArray[np.int8], float, Point]:
    """The maps ``grids`` (drawable: 0 free, 100 occupied, 255 unknown) as one map of int8 cells
    (-1 unknown, 0 free, 100 occupied), its resolution and origin. Several maps that share a
    resolution and a lattice (the onboard maps do: cells on multiples of the resolution) are merged
    with one in charge: the map that knows most cells as it is, the others' cells only where it
    knows nothing (the first of them to know a cell; occupied over free among them). Two robots'
    maps agree on a wall only to within their alignment (a few centimetres), so where both know a
    cell, "occupied wins" drew every wall and table as thick as both copies: planned on that, room-1's
    round needed 888 s of dwell for one robot, against 704 s on one robot's own map. Maps on another
    lattice are left out. RoundError without any.

    ``trails``: where the robot whose map is ``grids[i]`` has driven lately (the console's trail of
    it), one for each map: what another robot's map holds of its body there is taken off
    (``robots_off``)."""
    if not grids:
        raise RoundError("no map from the round's robots yet (the console shows each robot's map as it arrives)")
    first = grids[0]
    res = first[2]
    same = [g for g in grids if abs(g[2] - res) <= 1e-9 * res and _on_lattice(g, first)]
    xs0 = min(g[0] for g in same)
    ys0 = min(g[1] for g in same)
    w = max(round((g[0] - xs0) / res) + g[3] for g in same)
    h = max(round((g[1] - ys0) / res) + g[4] for g in same)
    out = np.full((h, w), -1, dtype=np.int8)

    def known(g: Grid) -> int:
        return int(np.count_nonzero(np.frombuffer(g[5], dtype=np.uint8) != 255))

    # The map in charge first (the one that knows most; the first on a tie), then the others, each
    # filling only what the ones before it left unknown.
    for ox, oy, _, gw, gh, data in sorted(same, key=lambda g: -known(g)):
        c0, r0 = round((ox - xs0) / res), round((oy - ys0) / res)
        cells = np.frombuffer(data, dtype=np.uint8).reshape(gh, gw)
        window = out[r0 : r0 + gh, c0 : c0 + gw]
        unknown = window == -1
        window[unknown & (cells == 100)] = 100
        window[unknown & (cells == 0)] = 0
    if trails is not None:
        for g, trail in zip(grids, trails, strict=True):
            if any(g is s for s in same):
                robots_off(out, res, (xs0, ys0), g, trail)
    return out, float(res), (float(xs0), float(ys0))


BODY_REACH_M = 0.25
"""How far from a robot's centre another robot's lidar maps its body: its radius (0.17 m) and the
cells the hits fall in (up to 0.035 m further), with both robots' pose errors (a few cm)."""


def robots_off(cells: npt.NDArray[np.int8], resolution: float, origin: Point, own: Grid, trail: Sequence[Point]) -> int:
    """Take a robot's body off a merged map (``cells``, in place): every blob of wall (8-connected
    occupied cells) that lies wholly within ``BODY_REACH_M`` of a point of its ``trail`` and that its
    own map (``own``) does not hold as wall, on or beside it. A robot's lidar maps another robot it sees like
    furniture, an arc of cells round where that robot was, and keeps it until it looks there again;
    the robot itself never sees its own body. Planned on, such an arc casts a shadow that needs
    dwell and bars the way (the kitchen's two-robot round, docs/payload.md). What stays: a wall or
    anything joined to one (the blob is larger than a body), and anything the robot's own lidar
    saw there (a chair leg it passed beside is in its own map). Returns the cells freed."""
    pts = np.array([p for p in trail if math.isfinite(p[0]) and math.isfinite(p[1])], dtype=np.float64)
    if pts.size == 0:
        return 0
    ox, oy, ores, ow, oh, data = own
    # Its own map's walls and the cells beside them (two maps agree on a wall to a cell or so): a
    # blob on any of them is something it saw there itself.
    walls = np.frombuffer(data, dtype=np.uint8).reshape(oh, ow) == 100
    mine = np.zeros((oh + 2, ow + 2), dtype=bool)
    for dr in range(3):
        for dc in range(3):
            mine[dr : dr + oh, dc : dc + ow] |= walls
    mine = mine[1:-1, 1:-1]
    span = int(2 * BODY_REACH_M / resolution) + 1
    freed = 0
    for blob in components(cells == 100):
        rows, cols = blob[:, 0], blob[:, 1]
        if int(np.ptp(rows)) + 1 > span or int(np.ptp(cols)) + 1 > span:
            continue
        xs = origin[0] + (cols + 0.5) * resolution
        ys = origin[1] + (rows + 0.5) * resolution
        d2 = (xs[:, None] - pts[None, :, 0]) ** 2 + (ys[:, None] - pts[None, :, 1]) ** 2
        if not bool((d2.min(axis=1) <= BODY_REACH_M**2).all()):
            continue
        mc = np.floor((xs - ox) / ores).astype(np.intp)
        mr = np.floor((ys - oy) / ores).astype(np.intp)
        inside = (mc >= 0) & (mc < ow) & (mr >= 0) & (mr < oh)
        if bool(mine[mr[inside], mc[inside]].any()):
            continue
        cells[rows, cols] = 0
        freed += int(rows.size)
    return freed


def _on_lattice(g: Grid, first: Grid) -> bool:
    res = first[2]
    for a, b in ((g[0], first[0]), (g[1], first[1])):
        k = (a - b) / res
        if abs(k - round(k)) > 1e-6:
            return False
    return True
