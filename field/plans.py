"""Floor plans for the field: walls, obstacles, cliffs, doors, named start poses and UWB anchors.

A plan is a frozen value. It comes from a built-in name (``apartment``, ``office``, ``hall``: TOML
files in ``field/floorplans/``), from a TOML file in the same format (docs/field-plans.md), or from a
ROS map_server map (PGM + YAML, walls taken from the occupancy grid, see ``field/mapserver.py``).
Everything is validated when the plan is made; problems name the file, the key and the reason.

Units: metres, and radians inside the program. TOML files give headings in degrees
(``theta_deg``); ``Pose.theta`` is radians.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Annotated, Any, NamedTuple

import numpy as np
import numpy.typing as npt

from fleetlink.field.floor import Floor
from fleetlink.field.mapserver import MapError, OccupancyMap, image_from_grid, read_map
from fleetlink.field.radio import AccessPoint, RadioSettings
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.shared.config import ConfigError, Invalid, Setting, parse, read_toml
from fleetlink.shared.geometry import Point, Segment, point_in_polygon, points_in_polygon
from fleetlink.shared.messages import LinkName

__all__ = [
    "BUILTIN_PLANS",
    "PLANS_DIR",
    "ROBOT_RADIUS",
    "AccessPoint",
    "Anchor",
    "FloorPlan",
    "MapSidecar",
    "PlanError",
    "PlanFile",
    "Polygon",
    "Pose",
    "RadioSettings",
    "builtin_plans",
    "dump_plan",
    "load_plan",
    "nearest_segment_distances",
    "parse_plan",
    "plan_from_map",
    "save_plan",
]

ROBOT_RADIUS = BODY_RADIUS_M  # m: the body every start must clear
BUILTIN_PLANS = ("apartment", "office", "hall", "expo", "ward")  # the drawn plans; builtin_plans() adds example maps
PLANS_DIR = Path(__file__).with_name("floorplans")  # not "plans/": see docs/field-plans.md
MAX_GRID_STARTS = 10_000

Polygon = tuple[Point, ...]
Bounds = tuple[float, float, float, float]

_EPS = 1e-6  # m: tolerance for "inside the bounds" and the shortest segment
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


class PlanError(ConfigError):
    """A floor plan that cannot be used, with the place and the reason."""


class Pose(NamedTuple):
    x: float  # m
    y: float  # m
    theta: float  # rad, counter-clockwise from +x


class Anchor(NamedTuple):
    id: str
    x: float  # m
    y: float  # m
    z: float  # m above the floor


@dataclass(frozen=True, slots=True)
class FloorPlan:
    """A floor: what blocks a robot (walls, obstacles, closed doors), where it would fall (cliffs),
    where robots start and where the UWB anchors hang.

    Doors are open unless named in ``closed_doors``: an open door blocks nothing. ``doors`` and
    ``starts`` are read-only mappings that keep the file's order.
    """

    name: str
    bounds: Bounds  # xmin, ymin, xmax, ymax
    walls: tuple[Segment, ...] = ()
    obstacles: tuple[Polygon, ...] = ()
    cliffs: tuple[Polygon, ...] = ()
    doors: Mapping[str, Segment] = field(default_factory=dict)
    starts: Mapping[str, Pose] = field(default_factory=dict)
    anchors: tuple[Anchor, ...] = ()
    description: str = ""
    source: str = "<memory>"
    access_points: tuple[AccessPoint, ...] = ()  # the radio (field/radio.py): none = reachable everywhere
    dead_zones: tuple[Polygon, ...] = ()  # where no link gets through
    radio: RadioSettings = field(default_factory=RadioSettings)
    _base: npt.NDArray[np.float64] = field(init=False, repr=False, compare=False)
    _labels: tuple[str, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        src = self.source

        def fail(where: str, problem: str) -> PlanError:
            return PlanError(f"{src}: {where}: {problem}")

        def number(v: object, where: str) -> float:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise fail(where, f"expected a number, got {type(v).__name__} {v!r}")
            f = float(v)
            if not math.isfinite(f):
                raise fail(where, f"must be finite, got {f}")
            return f

        def within(x: float, y: float, where: str) -> None:
            if not (xmin - _EPS <= x <= xmax + _EPS and ymin - _EPS <= y <= ymax + _EPS):
                raise fail(
                    where, f"point ({x:g}, {y:g}) lies outside the bounds [{xmin:g}, {ymin:g}, {xmax:g}, {ymax:g}]"
                )

        def segment(v: Sequence[object], where: str) -> Segment:
            if len(v) != 4:
                raise fail(where, f"expected [x1, y1, x2, y2], got {list(v)!r}")
            x1, y1, x2, y2 = (number(c, where) for c in v)
            if math.hypot(x2 - x1, y2 - y1) < _EPS:
                raise fail(where, f"degenerate segment: both ends at ({x1:g}, {y1:g})")
            within(x1, y1, where)
            within(x2, y2, where)
            return (x1, y1, x2, y2)

        def polygon(v: Sequence[Sequence[object]], where: str) -> Polygon:
            if len(v) < 3:
                raise fail(where, f"a polygon needs at least 3 points, got {len(v)}")
            pts: list[Point] = []
            for k, q in enumerate(v):
                if len(q) != 2:
                    raise fail(f"{where}[{k}]", f"expected [x, y], got {list(q)!r}")
                pt = (number(q[0], f"{where}[{k}]"), number(q[1], f"{where}[{k}]"))
                within(*pt, f"{where}[{k}]")
                pts.append(pt)
            area = sum(pts[k][0] * pts[k - 1][1] - pts[k - 1][0] * pts[k][1] for k in range(len(pts))) / 2
            if abs(area) < 1e-9:
                raise fail(where, "the polygon has no area (its points are collinear)")
            return tuple(pts)

        def name_ok(n: object, where: str) -> str:
            if not isinstance(n, str) or not _NAME.match(n):
                raise fail(where, f"names use letters, digits, '-', '_' and '.', got {n!r}")
            return n

        if not isinstance(self.name, str) or not self.name:
            raise fail("name", f"expected a non-empty string, got {self.name!r}")
        if len(self.bounds) != 4:
            raise fail("bounds", f"expected [xmin, ymin, xmax, ymax], got {self.bounds!r}")
        xmin, ymin, xmax, ymax = (number(v, "bounds") for v in self.bounds)
        if not (xmin < xmax and ymin < ymax):
            raise fail("bounds", f"expected xmin < xmax and ymin < ymax, got [{xmin:g}, {ymin:g}, {xmax:g}, {ymax:g}]")
        walls = tuple(segment(s, f"walls[{i}]") for i, s in enumerate(self.walls))
        obstacles = tuple(polygon(p, f"obstacles[{i}]") for i, p in enumerate(self.obstacles))
        cliffs = tuple(polygon(p, f"cliffs[{i}]") for i, p in enumerate(self.cliffs))
        doors = {name_ok(k, f"doors.{k}"): segment(s, f"doors.{k}") for k, s in self.doors.items()}
        anchors: list[Anchor] = []
        for i, a in enumerate(self.anchors):
            if len(a) != 4:
                raise fail(f"anchors[{i}]", f"expected (id, x, y, z), got {a!r}")
            aid = name_ok(a[0], f"anchors[{i}].id")
            if any(b.id == aid for b in anchors):
                raise fail(f"anchors[{i}].id", f"anchor {aid!r} appears twice")
            x, y, z = (number(c, f"anchors[{i}].{k}") for c, k in zip(a[1:], "xyz", strict=True))
            anchors.append(Anchor(aid, x, y, z))
        dead_zones = tuple(polygon(p, f"dead_zones[{i}]") for i, p in enumerate(self.dead_zones))
        access_points: list[AccessPoint] = []
        for i, ap in enumerate(self.access_points):
            where = f"access_points[{i}]"
            if not isinstance(ap, AccessPoint):
                raise fail(where, f"expected an AccessPoint, got {ap!r}")
            apn = name_ok(ap.name, f"{where}.name")
            if any(b.name == apn for b in access_points):
                raise fail(f"{where}.name", f"access point {apn!r} appears twice")
            x, y = number(ap.x, f"{where}.x"), number(ap.y, f"{where}.y")
            tx = number(ap.tx_power_dbm, f"{where}.tx_power_dbm")
            links = tuple(ap.links)
            if not links or len(set(links)) != len(links) or not all(isinstance(k, LinkName) for k in links):
                raise fail(f"{where}.links", f"expected one or both of zenoh, mqtt, each once, got {list(ap.links)!r}")
            access_points.append(AccessPoint(apn, x, y, links, tx))
        if not isinstance(self.radio, RadioSettings):
            raise fail("radio", f"expected RadioSettings, got {self.radio!r}")
        for key, problem in self.radio.problems():
            raise fail(f"radio.{key}", problem)
        set_ = object.__setattr__
        set_(self, "bounds", (xmin, ymin, xmax, ymax))
        set_(self, "walls", walls)
        set_(self, "obstacles", obstacles)
        set_(self, "cliffs", cliffs)
        set_(self, "doors", MappingProxyType(doors))
        set_(self, "anchors", tuple(anchors))
        set_(self, "dead_zones", dead_zones)
        set_(self, "access_points", tuple(access_points))
        rows: list[Segment] = list(walls)
        labels = [f"walls[{i}]" for i in range(len(walls))]
        for i, poly in enumerate(obstacles):
            for k in range(len(poly)):
                rows.append((*poly[k], *poly[(k + 1) % len(poly)]))
                labels.append(f"obstacles[{i}]")
        base = np.array(rows, dtype=np.float64).reshape(-1, 4)
        base.setflags(write=False)
        set_(self, "_base", base)
        set_(self, "_labels", tuple(labels))

        starts: dict[str, Pose] = {}
        for sname, pose in self.starts.items():
            where = f"starts.{sname}"
            name_ok(sname, where)
            if len(pose) != 3:
                raise fail(where, f"expected (x, y, theta), got {pose!r}")
            x, y, theta = (number(c, f"{where}.{n}") for c, n in zip(pose, ("x", "y", "theta"), strict=True))
            if not self.contains(x, y):
                raise fail(where, f"({x:g}, {y:g}) lies outside the bounds [{xmin:g}, {ymin:g}, {xmax:g}, {ymax:g}]")
            for i, poly in enumerate(obstacles):
                if point_in_polygon(x, y, poly):
                    raise fail(where, f"({x:g}, {y:g}) is inside obstacles[{i}]")
            for i, poly in enumerate(cliffs):
                if point_in_polygon(x, y, poly):
                    raise fail(where, f"({x:g}, {y:g}) is over cliffs[{i}]")
            if len(base):
                d = _distances(base, x, y)
                j = int(np.argmin(d))
                if d[j] <= ROBOT_RADIUS:
                    raise fail(
                        where,
                        f"({x:g}, {y:g}) is {d[j]:.3f} m from {labels[j]}: a robot (radius {ROBOT_RADIUS} m) needs more room",
                    )
            starts[sname] = Pose(x, y, theta)
        set_(self, "starts", MappingProxyType(starts))

    def __hash__(self) -> int:
        return hash(
            (
                self.name,
                self.bounds,
                self.walls,
                self.obstacles,
                self.cliffs,
                tuple(self.doors.items()),
                tuple(self.starts.items()),
                self.anchors,
                self.access_points,
                self.dead_zones,
                self.radio,
            )
        )

    # -- geometry --------------------------------------------------------------------------------

    @property
    def width(self) -> float:
        return self.bounds[2] - self.bounds[0]

    @property
    def height(self) -> float:
        return self.bounds[3] - self.bounds[1]

    def _closed(self, closed_doors: Iterable[str]) -> list[Segment]:
        closed = []
        for d in closed_doors:
            if d not in self.doors:
                known = ", ".join(self.doors) or "none"
                raise PlanError(f"{self.source}: plan {self.name} has no door {d!r} (doors: {known})")
            closed.append(self.doors[d])
        return closed

    def segments(self, closed_doors: Iterable[str] = ()) -> npt.NDArray[np.float64]:
        """Every blocking segment, shape (N, 4) as x1, y1, x2, y2: walls, obstacle edges, closed doors."""
        closed = self._closed(closed_doors)
        if not closed:
            return self._base.copy()
        return np.vstack([self._base, np.array(closed, dtype=np.float64)])

    def contains(self, x: float, y: float) -> bool:
        """Is the point within the plan's bounds?"""
        xmin, ymin, xmax, ymax = self.bounds
        return xmin <= x <= xmax and ymin <= y <= ymax

    def is_cliff(self, x: float, y: float) -> bool:
        """Would a robot at this point be over a drop (inside a cliff polygon)?"""
        return any(point_in_polygon(x, y, p) for p in self.cliffs)

    def in_obstacle(self, x: float, y: float) -> bool:
        return any(point_in_polygon(x, y, p) for p in self.obstacles)

    def clearance(self, x: float, y: float, closed_doors: Iterable[str] = ()) -> float:
        """Distance from a point to the nearest blocking segment (``inf`` on an empty plan)."""
        segs = self.segments(closed_doors)
        return float(_distances(segs, x, y).min()) if len(segs) else math.inf

    def is_clear(self, x: float, y: float, radius: float = ROBOT_RADIUS, closed_doors: Iterable[str] = ()) -> bool:
        """Could a round robot of ``radius`` stand here: in bounds, not in an obstacle or over a cliff, touching nothing?"""
        return (
            self.contains(x, y)
            and not self.in_obstacle(x, y)
            and not self.is_cliff(x, y)
            and self.clearance(x, y, closed_doors) > radius
        )

    def to_floor(self, closed_doors: Iterable[str] = ()) -> Floor:
        """The board simulator's ``Floor``: blocking segments as walls, cliff polygons as cliffs."""
        walls: list[Segment] = [(float(a), float(b), float(c), float(d)) for a, b, c, d in self.segments(closed_doors)]
        return Floor(walls=walls, cliff_polygons=list(self.cliffs))

    def to_grid(self, resolution: float = 0.05, closed_doors: Iterable[str] = ()) -> OccupancyMap:
        """Rasterise the plan into an occupancy grid (e.g. to save with ``write_map`` or to score a map).

        Cells under a blocking segment or inside an obstacle are occupied, the rest free; cliffs are
        not drawn (a grid has no notion of a drop). One free cell of margin surrounds the bounds.
        """
        if not (math.isfinite(resolution) and resolution > 0):
            raise PlanError(f"resolution: must be a finite number > 0, got {resolution!r}")
        xmin, ymin, xmax, ymax = self.bounds
        ox, oy = xmin - resolution, ymin - resolution
        cols = math.ceil((xmax - xmin) / resolution - 1e-9) + 2
        rows = math.ceil((ymax - ymin) / resolution - 1e-9) + 2
        grid = np.zeros((rows, cols), dtype=np.int8)
        cx = ox + (np.arange(cols) + 0.5) * resolution
        cy = oy + (np.arange(rows) + 0.5) * resolution
        for poly in self.obstacles:
            xs, ys = [p[0] for p in poly], [p[1] for p in poly]
            c0, c1 = np.searchsorted(cx, min(xs)), np.searchsorted(cx, max(xs), side="right")
            r0, r1 = np.searchsorted(cy, min(ys)), np.searchsorted(cy, max(ys), side="right")
            if c0 < c1 and r0 < r1:
                px, py = np.meshgrid(cx[c0:c1], cy[r0:r1])
                inside = points_in_polygon(px, py, poly)
                grid[r0:r1, c0:c1][inside] = 100
        for x1, y1, x2, y2 in self.segments(closed_doors):
            n = max(2, math.ceil(math.hypot(x2 - x1, y2 - y1) / (resolution / 4)) + 1)
            t = np.linspace(0.0, 1.0, n)
            c = np.floor((x1 + t * (x2 - x1) - ox) / resolution).astype(np.intp).clip(0, cols - 1)
            r = np.floor((y1 + t * (y2 - y1) - oy) / resolution).astype(np.intp).clip(0, rows - 1)
            grid[r, c] = 100
        return OccupancyMap(
            grid=grid,
            resolution=resolution,
            origin=(ox, oy, 0.0),
            image=image_from_grid(grid),
            source=f"{self.name} rasterised at {resolution:g} m",
        )


def _distances(segs: npt.NDArray[np.float64], x: float, y: float) -> npt.NDArray[np.float64]:
    """Distance from (x, y) to each segment of an (N, 4) array."""
    x1, y1, x2, y2 = segs[:, 0], segs[:, 1], segs[:, 2], segs[:, 3]
    ex, ey = x2 - x1, y2 - y1
    n2 = ex * ex + ey * ey
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(n2 > 0, ((x - x1) * ex + (y - y1) * ey) / n2, 0.0)
    t = np.clip(t, 0.0, 1.0)
    return np.asarray(np.hypot(x - (x1 + t * ex), y - (y1 + t * ey)), dtype=np.float64)


def nearest_segment_distances(
    points: npt.ArrayLike, segs: npt.NDArray[np.float64], chunk: int = 2000
) -> npt.NDArray[np.float64]:
    """Distance from each of (M, 2) ``points`` to the nearest of the (N, 4) segments (inf without
    segments): how far a map's walls lie from the plan's (bench/mapping.py, the mapping tests)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(p), np.inf)
    if not len(segs):
        return out
    a, b = segs[None, :, :2], segs[None, :, 2:]
    ab = b - a
    n2 = np.maximum((ab**2).sum(axis=2), 1e-12)
    for i in range(0, len(p), chunk):  # bounded temporaries: chunk x N x 2
        q = p[i : i + chunk, None, :]
        t = np.clip(((q - a) * ab).sum(axis=2) / n2, 0.0, 1.0)
        out[i : i + chunk] = np.hypot(*(a + t[..., None] * ab - q).transpose(2, 0, 1)).min(axis=1)
    return out


# -- TOML ------------------------------------------------------------------------------------------
# The file format as schemas for shared/config.py; geometry is checked by FloorPlan itself.

Segment4 = Annotated[tuple[float, float, float, float], Setting(what="[x1, y1, x2, y2]")]
PointXY = Annotated[tuple[float, float], Setting(what="[x, y]")]


@dataclass(frozen=True)
class _Area:
    polygon: Annotated[tuple[PointXY, ...], Setting(min_len=3, what="a polygon of [x, y] points")]
    name: str = ""


@dataclass(frozen=True)
class _Start:
    x: float
    y: float
    theta_deg: float


@dataclass(frozen=True)
class _StartGrid:
    prefix: str
    x0: float
    y0: float
    dx: float
    dy: float
    nx: Annotated[int, Setting(lo=1, hi=MAX_GRID_STARTS)]
    ny: Annotated[int, Setting(lo=1, hi=MAX_GRID_STARTS)]
    theta_deg: float

    def validate(self) -> None:
        if self.nx * self.ny > MAX_GRID_STARTS:
            raise Invalid("", f"nx * ny must be at most {MAX_GRID_STARTS}, got {self.nx * self.ny}")
        for key, value in (("dx", self.dx), ("dy", self.dy)):
            if value < 2 * ROBOT_RADIUS:
                raise Invalid(key, f"must be at least {2 * ROBOT_RADIUS:g} m (two robot radii), got {value:g}")


@dataclass(frozen=True)
class _PlanAnchor:
    id: str
    x: float
    y: float
    z: float


@dataclass(frozen=True, kw_only=True)
class _PlanParts:
    """Every key but ``bounds``: a plan file's and a map sidecar's common part."""

    name: str | None = None
    description: str = ""
    walls: Annotated[tuple[Segment4, ...], Setting(what="a list of [x1, y1, x2, y2] segments")] = ()
    obstacles: tuple[_Area, ...] = ()
    cliffs: tuple[_Area, ...] = ()
    doors: dict[str, Segment4] = field(default_factory=dict)
    starts: dict[str, Annotated[_Start, Setting(what="a table { x = ..., y = ..., theta_deg = ... }")]] = field(
        default_factory=dict
    )
    start_grid: tuple[_StartGrid, ...] = ()
    anchors: tuple[_PlanAnchor, ...] = ()
    access_points: tuple[AccessPoint, ...] = ()
    dead_zones: tuple[_Area, ...] = ()
    radio: RadioSettings = field(default_factory=RadioSettings)


@dataclass(frozen=True, kw_only=True)
class PlanFile(_PlanParts):
    """A plan TOML file (docs/field-plans.md)."""

    bounds: Annotated[tuple[float, float, float, float], Setting(what="[xmin, ymin, xmax, ymax]")]
    walls: Annotated[tuple[Segment4, ...], Setting(required=True, what="a list of [x1, y1, x2, y2] segments")] = ()


@dataclass(frozen=True, kw_only=True)
class MapSidecar(_PlanParts):
    """``<map>.plan.toml`` beside a ROS map: a plan file without ``bounds``, plus ``unknown_is_wall``."""

    unknown_is_wall: bool = True


def _parts(f: _PlanParts, source: str) -> dict[str, Any]:
    """FloorPlan keyword arguments from a parsed file (grid starts written out one by one)."""
    starts = {k: Pose(v.x, v.y, math.radians(v.theta_deg)) for k, v in f.starts.items()}
    for i, g in enumerate(f.start_grid):
        theta = math.radians(g.theta_deg)
        width = max(2, len(str(g.nx * g.ny)))
        index = 0
        for row in range(g.ny):
            for col in range(g.nx):
                index += 1
                name = f"{g.prefix}{index:0{width}d}"
                if name in starts:
                    raise PlanError.at(source, f"start_grid[{i}]", f"start {name!r} already exists")
                starts[name] = Pose(g.x0 + col * g.dx, g.y0 + row * g.dy, theta)
    return {
        "description": f.description,
        "walls": f.walls,
        "obstacles": tuple(a.polygon for a in f.obstacles),
        "cliffs": tuple(a.polygon for a in f.cliffs),
        "doors": dict(f.doors),
        "starts": starts,
        "anchors": tuple(Anchor(a.id, a.x, a.y, a.z) for a in f.anchors),
        "access_points": f.access_points,
        "dead_zones": tuple(a.polygon for a in f.dead_zones),
        "radio": f.radio,
    }


def parse_plan(data: Mapping[str, Any], source: str = "<memory>", default_name: str = "plan") -> FloorPlan:
    """A plan from decoded TOML (a dict); raises PlanError naming ``source``, the key and the problem."""
    f = parse(data, PlanFile, source=source, error=PlanError)
    return FloorPlan(name=f.name or default_name, bounds=f.bounds, source=source, **_parts(f, source))


def _read_toml(path: Path) -> dict[str, Any]:
    return read_toml(path, PlanError)


def builtin_plans() -> tuple[str, ...]:
    """Names ``load_plan`` accepts without a path: the TOML plans and the example maps in ``field/floorplans/``."""
    tomls = {p.stem for p in PLANS_DIR.glob("*.toml") if not p.name.endswith(".plan.toml")}
    maps = {p.stem for p in PLANS_DIR.glob("*.yaml")}
    return tuple(sorted(tomls | maps))


def load_plan(plan: str | Path) -> FloorPlan:
    """A built-in plan by name, a plan TOML file, or a ROS map_server YAML (with an optional sidecar).

    For ``maps/lab.yaml`` the sidecar is ``maps/lab.plan.toml``: the TOML format without ``bounds``
    (they come from the map), adding starts, anchors, doors, obstacles, cliffs, extra walls, and
    ``unknown_is_wall`` (default true).
    """
    text = str(plan)
    path = Path(plan)
    if isinstance(plan, str) and plan in builtin_plans():
        path = next(p for p in (PLANS_DIR / f"{plan}.toml", PLANS_DIR / f"{plan}.yaml") if p.is_file())
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml"):
        return _load_map_plan(path)
    if suffix == ".toml":
        return parse_plan(_read_toml(path), str(path), default_name=path.stem)
    if path.exists():
        raise PlanError(
            f"{path}: unknown plan format {suffix or '(no suffix)'}: expected .toml, or .yaml for a ROS map"
        )
    raise PlanError(
        f"{text}: no such plan: not a built-in ({', '.join(builtin_plans())}) and no such .toml or .yaml file"
    )


def _load_map_plan(path: Path) -> FloorPlan:
    try:
        occ = read_map(path)
    except MapError as exc:
        raise PlanError(str(exc)) from exc
    sidecar = path.with_suffix(".plan.toml")
    extras = _read_toml(sidecar) if sidecar.is_file() else {}
    return plan_from_map(occ, name=path.stem, extras=extras, source=str(sidecar if extras else path))


def plan_from_map(
    occ: OccupancyMap,
    name: str = "map",
    unknown_is_wall: bool = True,
    extras: Mapping[str, Any] | None = None,
    source: str | None = None,
) -> FloorPlan:
    """A plan whose walls are the boundaries between open and blocked cells of an occupancy grid.

    Blocked cells are occupied ones and, with ``unknown_is_wall`` (the default; a sidecar may set
    ``unknown_is_wall = false``), unknown ones too: a robot should not drive into what nobody has
    seen, and most saved maps are unknown outside the building. Outside the grid counts as blocked.
    ``extras`` is a decoded sidecar TOML (every plan key but ``bounds``). Bounds are the grid's extent.
    """
    src = source or occ.source
    sidecar = parse(extras or {}, MapSidecar, source=src, error=PlanError)
    if extras and "unknown_is_wall" in extras:
        unknown_is_wall = sidecar.unknown_is_wall
    plan_name = sidecar.name or name
    parts = _parts(sidecar, src)
    segs = occ.segments(unknown_is_wall)
    map_walls = tuple((float(a), float(b), float(c), float(d)) for a, b, c, d in segs)
    parts["walls"] = map_walls + parts["walls"]
    h, w = occ.grid.shape
    ox, oy, yaw = occ.origin
    corners = [
        (
            ox + occ.resolution * (math.cos(yaw) * u - math.sin(yaw) * v),
            oy + occ.resolution * (math.sin(yaw) * u + math.cos(yaw) * v),
        )
        for u, v in ((0, 0), (w, 0), (w, h), (0, h))
    ]
    bounds = (
        min(c[0] for c in corners),
        min(c[1] for c in corners),
        max(c[0] for c in corners),
        max(c[1] for c in corners),
    )
    if not parts.get("description"):
        parts["description"] = f"from the map {occ.source} ({w} x {h} cells at {occ.resolution:g} m)"
    return FloorPlan(name=plan_name, bounds=bounds, source=src, **parts)


# -- writing ---------------------------------------------------------------------------------------


def _toml_str(s: str) -> str:
    out = []
    for ch in s:
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif ch == "\n":
            out.append("\\n")
        elif ch == "\t":
            out.append("\\t")
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _num(v: float) -> str:
    return repr(float(v))


def _key(k: str) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _toml_str(k)


def dump_plan(plan: FloorPlan) -> str:
    """The plan as TOML in the documented format (grid starts written out one by one)."""
    lines = [f"name = {_toml_str(plan.name)}"]
    if plan.description:
        lines.append(f"description = {_toml_str(plan.description)}")
    lines.append("bounds = [" + ", ".join(_num(v) for v in plan.bounds) + "]  # xmin, ymin, xmax, ymax (m)")
    lines.append("walls = [")
    lines.extend("  [" + ", ".join(_num(v) for v in w) + "]," for w in plan.walls)
    lines.append("]")
    for key, polys in (("obstacles", plan.obstacles), ("cliffs", plan.cliffs)):
        for poly in polys:
            lines += ["", f"[[{key}]]", "polygon = [" + ", ".join(f"[{_num(x)}, {_num(y)}]" for x, y in poly) + "]"]
    if plan.doors:
        lines += ["", "[doors]"]
        lines.extend(f"{_key(k)} = [" + ", ".join(_num(v) for v in s) + "]" for k, s in plan.doors.items())
    if plan.starts:
        lines += ["", "[starts]"]
        lines.extend(
            f"{_key(k)} = {{ x = {_num(p.x)}, y = {_num(p.y)}, theta_deg = {_num(math.degrees(p.theta))} }}"
            for k, p in plan.starts.items()
        )
    for a in plan.anchors:
        lines += [
            "",
            "[[anchors]]",
            f"id = {_toml_str(a.id)}",
            f"x = {_num(a.x)}",
            f"y = {_num(a.y)}",
            f"z = {_num(a.z)}",
        ]
    if plan.radio != RadioSettings():
        lines += ["", "[radio]"]
        lines.extend(f"{k} = {_num(getattr(plan.radio, k))}" for k in RadioSettings.__dataclass_fields__)
    for ap in plan.access_points:
        lines += [
            "",
            "[[access_points]]",
            f"name = {_toml_str(ap.name)}",
            f"x = {_num(ap.x)}",
            f"y = {_num(ap.y)}",
            "links = [" + ", ".join(_toml_str(k.value) for k in ap.links) + "]",
            f"tx_power_dbm = {_num(ap.tx_power_dbm)}",
        ]
    for poly in plan.dead_zones:
        lines += ["", "[[dead_zones]]", "polygon = [" + ", ".join(f"[{_num(x)}, {_num(y)}]" for x, y in poly) + "]"]
    return "\n".join(lines) + "\n"


def save_plan(plan: FloorPlan, path: str | Path) -> Path:
    p = Path(path)
    p.write_text(dump_plan(plan), encoding="utf-8")
    return p
