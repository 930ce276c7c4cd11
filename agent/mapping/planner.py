"""A* over the inflated occupancy grid: the path provider the pilot takes.

    planner = PathPlanner(cells, resolution, origin)          # map_server-style int8 cells
    planner((x0, y0), (x1, y1)) -> [(x, y), ...] | None       # waypoints after the start, ending at the goal
    planner.route(start, goal, blocked=[(x, y)]) -> [...]     # the pilot's path provider: [] when no path

The map is re-gridded at ``plan_resolution`` (a plan cell is blocked if any map cell in it is
occupied, or unknown when ``unknown_is_blocked``). Every plan cell gets its distance to the nearest
blocked cell (exact Euclidean between cell centres, up to ``inflation + cost_radius``). A cell is
traversable when that distance, less half a plan cell (so the cell's worst corner counts), is at
least ``inflation`` (robot radius plus a margin). A* runs 8-connected with octile heuristic; each
step costs its length times ``1 + cost_weight * (1 - d / cost_radius)`` near walls, so paths keep
to the middle of corridors. The cell path is then laid out as a few waypoints (``_lay``): each
leg as long as possible while its straight line stays as clear of walls as the cell path was at its
narrowest over that stretch (so shortcuts go through the middle of doorways, not past a jamb), and
while the front ultrasonic will not bar it: the collision guard refuses a drive start when the
cone (40 deg, a 1.5 m range) sees anything nearer than the leg plus its stop distance, and any
forward motion or turn in place below the stop distance. ``leg_ok`` and ``turn_ok`` ray-cast that
cone (widened by the aim tolerance) over the map at its own resolution; a leg that would be
refused on the map's own walls (a door frame seen past the end of a long approach, a waypoint
facing a wall) is cut shorter, so the approach to a door ends in front of its middle and the next
leg goes straight through. ``SensorCone`` holds the sensor's figures (``PlannerConfig.sensor``;
None turns the check off).

``blocked`` points (where the robot's own sensor found the way barred, e.g. a box not on the map)
are planned around as discs of ``blocked_radius``, inflated like walls, for that call only (the
caller keeps them for as long as they matter: the pilot, for the order that met them). A point
within ``known_tolerance`` of a wall already on the map is that wall, seen by the cone: ignored
(otherwise one echo off a door frame closes the doorway). ``bodies`` (other robots where they
report themselves standing: agent/peers.py) are such discs too, but never ignored: the lidar maps a
robot's near face, and its centre stands a radius behind it.

A start inside the inflated zone (a robot parked near a wall) is moved to the nearest traversable
cell within ``escape`` metres, which becomes the first waypoint. A goal there is reached the same
way in reverse when the robot's body fits at it (``fit_margin`` clear of every blocked map cell,
at the map's own resolution): the path ends at the nearest traversable cell, then a straight leg
the body fits along all the way. A goal the body does not fit at is refused (None).
A goal beyond what the robot has mapped (off the map, or in a plan cell it has seen nothing of) is
planned to the reachable edge of the known (a frontier cell) nearest it with no known wall on the
straight line to it, and that last leg goes on into the unknown: a scout sent to coordinates it has
not seen yet heads there, the guard watching that leg, and re-plans as the map grows (the route asks
each newer planner ``leg_meets_wall`` about the leg it drives: agent/route.py). No such frontier: no
path.

Pure numpy + heapq; no I/O.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from fleetlink.shared.body import BODY_RADIUS_M

__all__ = ["MOVABLE_SIZE_M", "MOVES8", "PathPlanner", "PlannerConfig", "SensorCone"]

Point = tuple[float, float]
_SQRT2 = math.sqrt(2.0)
MOVES8 = (
    (1, 0, 1.0),
    (-1, 0, 1.0),
    (0, 1, 1.0),
    (0, -1, 1.0),
    (1, 1, _SQRT2),
    (1, -1, _SQRT2),
    (-1, 1, _SQRT2),
    (-1, -1, _SQRT2),
)
"""The 8 grid moves (row, column, length in cells) the planners step by."""


@dataclass(frozen=True, slots=True)
class SensorCone:
    """The front ultrasonic as the collision guard reads it (defaults: ``GuardConfig``, the field's
    board): legs are laid so that the guard's drive-start check passes on the map's own walls."""

    offset: float = BODY_RADIUS_M  # m ahead of the robot's centre: on the rim
    half_angle: float = math.radians(20.0)  # the cone's half-width
    max_range: float = 1.5  # m: farther echoes read as "nothing seen"
    stop_distance: float = 0.40  # m: the guard's threshold (``GuardConfig.stop_distance_m``)
    angle_margin: float = math.radians(3.0)  # the drive starts within the aim tolerance (3 deg)
    range_margin: float = 0.08  # m: pose error, sensor noise, the map's rasterisation
    ray_step: float = math.radians(2.0)  # the cone is checked as rays this far apart


@dataclass(frozen=True, slots=True)
class PlannerConfig:
    robot_radius: float = BODY_RADIUS_M  # m
    margin: float = 0.05  # m beyond the radius
    cost_radius: float = 0.4  # m of soft cost beyond the inflation
    cost_weight: float = 3.0
    plan_resolution: float = 0.1  # m
    occupied_threshold: int = 65  # cells >= this are walls (map_saver's threshold)
    unknown_is_blocked: bool = True
    escape: float = 0.5  # m a blocked start may be moved
    max_expansions: int = 2_000_000
    blocked_radius: float = 0.25  # m: a ``blocked`` point is planned around as a disc this size
    body_radius: float = BODY_RADIUS_M  # m: another robot's body (``bodies``): the fleet's robots are alike
    known_tolerance: float = 0.15  # m: a ``blocked`` point this near a mapped wall is that wall: ignored
    back_margin: float = 0.02  # m: backing straight (``room_behind``) stops this short of what the map blocks
    fit_margin: float = 0.02  # m: a goal inside the inflation is reached if the body stays this clear there
    # m: a goal is refused where the body would stand nearer another robot's (``bodies``) than this:
    # the guard's robot rule stops a robot driving at another its lane margin (2 cm) + its gap (3 cm)
    # + what it takes to stop from the approach's 0.1 m/s (1.5 cm) short of it, 6.5 cm in all, so a
    # goal nearer is never reached (tests/test_peers.py holds this to PeerConfig, GuardConfig and
    # GoToConfig: the four live in separate configs).
    body_clearance: float = 0.08
    sensor: SensorCone | None = field(default_factory=lambda: SensorCone())  # None: legs not checked

    @property
    def inflation(self) -> float:
        return self.robot_radius + self.margin


_FAR = 1 << 40
"""A cell index no grid reaches: where a point far off the map falls."""


def _index(v: float) -> int:
    if v != v:  # NaN
        return -_FAR
    return math.floor(v) if -_FAR < v < _FAR else (_FAR if v > 0 else -_FAR)


class PathPlanner:
    def __init__(
        self,
        cells: npt.ArrayLike,
        resolution: float,
        origin: tuple[float, float] = (0.0, 0.0),
        config: PlannerConfig | None = None,
    ) -> None:
        self.config = cfg = config or PlannerConfig()
        g = np.asarray(cells)
        if g.ndim != 2 or g.size == 0:
            raise ValueError(f"cells: expected a non-empty 2-D grid, got shape {g.shape}")
        walls = g >= cfg.occupied_threshold
        blocked = walls.copy()
        if cfg.unknown_is_blocked:
            blocked |= g < 0
        f = max(1, round(cfg.plan_resolution / resolution))
        self.resolution = res = resolution * f
        self.origin = (float(origin[0]), float(origin[1]))
        h, w = -(-g.shape[0] // f), -(-g.shape[1] // f)
        pad = np.zeros((h * f, w * f), dtype=bool)
        pad[: g.shape[0], : g.shape[1]] = blocked
        # Any blocked cell blocks its plan cell: an OR of strided views (numpy's reshape(...).any(axis=(1, 3))
        # reduces along short strided axes, ~10x slower on an office map).
        cols = pad[:, 0::f].copy()
        for i in range(1, f):
            cols |= pad[:, i::f]
        self.blocked: npt.NDArray[np.bool_] = cols[0::f].copy()
        for i in range(1, f):
            self.blocked |= cols[i::f]
        self.walls = self._coarse(walls, f, h, w)
        """Plan cells holding a known wall (occupied, not merely unknown)."""
        self.known = self._coarse(g >= 0, f, h, w)
        """Plan cells holding anything the robot has seen (free or occupied)."""
        reach = cfg.inflation + cfg.cost_radius + res
        self.distance = _distance(self.blocked, res, reach)
        self.free = self.distance - res / 2.0 >= cfg.inflation
        cr = max(cfg.cost_radius, 1e-9)
        near = np.clip(1.0 - (self.distance - res / 2.0 - cfg.inflation) / cr, 0.0, 1.0)
        self.cost = 1.0 + cfg.cost_weight * near
        # What the ultrasonic echoes from, at the map's own resolution (the plan grid is coarser).
        self.echo: npt.NDArray[np.bool_] = np.asarray(blocked, dtype=bool)
        self.echo_resolution = float(resolution)
        self.wall_cells: npt.NDArray[np.bool_] = np.asarray(walls, dtype=bool)
        """Known walls at the map's own resolution (occupied, not merely unknown)."""

    @staticmethod
    def _coarse(fine: npt.NDArray[np.bool_], f: int, h: int, w: int) -> npt.NDArray[np.bool_]:
        """Plan cells (``f`` x ``f`` map cells each) holding any true map cell."""
        pad = np.zeros((h * f, w * f), dtype=bool)
        pad[: fine.shape[0], : fine.shape[1]] = fine
        out = np.zeros((h, w), dtype=bool)
        for i in range(f):
            for j in range(f):
                out |= pad[i::f, j::f]
        return out

    def cell(self, p: Point) -> tuple[int, int]:
        """(row, col) of a world point; one far outside the grid for a point far off it (a huge or
        non-finite coordinate gives no cell, never an OverflowError)."""
        return (_index((p[1] - self.origin[1]) / self.resolution), _index((p[0] - self.origin[0]) / self.resolution))

    def center(self, rc: tuple[int, int]) -> Point:
        return (self.origin[0] + (rc[1] + 0.5) * self.resolution, self.origin[1] + (rc[0] + 0.5) * self.resolution)

    def _inside(self, rc: tuple[int, int]) -> bool:
        return bool(0 <= rc[0] < self.free.shape[0] and 0 <= rc[1] < self.free.shape[1])

    def is_free(self, p: Point) -> bool:
        rc = self.cell(p)
        return self._inside(rc) and bool(self.free[rc])

    def __call__(
        self, start_xy: Point, goal_xy: Point, blocked: Sequence[Point] = (), bodies: Sequence[Point] = ()
    ) -> list[Point] | None:
        if not all(math.isfinite(v) for v in (*start_xy, *goal_xy)):
            return None
        marks = self.unknown_marks(blocked)
        robots = [(float(x), float(y)) for x, y in bodies if math.isfinite(x) and math.isfinite(y)]
        free, cost, dist = self._with_blocked(marks, robots)
        sensed = marks + self._body_echoes(robots)  # what the ultrasonic will see (the legs' checks)
        goal = self.cell(goal_xy)
        first = self.cell(start_xy)
        start = self._escape(first, free)
        if start is None:
            return None
        s = (float(start_xy[0]), float(start_xy[1]))
        g = (float(goal_xy[0]), float(goal_xy[1]))
        if self._inside(goal) and free[goal]:
            cells = self._astar(start, goal, free, cost)
            return None if cells is None else self._lay(s, g, cells, free, dist, sensed, escaped=start != first)
        near = self._near_goal(g, free, marks, robots)
        if near is not None:
            cells = self._astar(start, near, free, cost)
            if cells is None:
                return None
            path = self._lay(s, self.center(near), cells, free, dist, sensed, escaped=start != first)
            return [*path, g] if math.dist(path[-1], g) > 1e-6 else path
        if not self.unexplored(goal_xy):
            return None  # a wall, or too near one, or known space the robot cannot stand in
        # Beyond what the robot has mapped: to the reachable edge of the known (a frontier cell)
        # nearest the goal with nothing known in the way, then straight on into the unknown (the
        # guard watches that leg; the map grows and re-planning follows).
        edge = self._frontier_toward(start, g, free)
        if edge is None:
            return None
        cells = self._astar(start, edge, free, cost)
        if cells is None:
            return None
        path = self._lay(s, self.center(edge), cells, free, dist, sensed, escaped=start != first)
        return [*path, g] if math.dist(path[-1], g) > 1e-6 else path

    def _body_echoes(self, bodies: Sequence[Point]) -> list[Point]:
        """Another robot's body as the legs' checks see it: marks (discs of ``_MARK_ECHO_M``) round
        its centre whose union is its disc (to within 6 mm), so that its near face echoes, not its
        centre."""
        r = max(0.0, self.config.body_radius - _MARK_ECHO_M)
        return [(x + r * math.cos(a), y + r * math.sin(a)) for x, y in bodies for a in _BODY_ECHO_ANGLES] + list(bodies)

    def unexplored(self, p: Point) -> bool:
        """``p`` lies off the map, or in a plan cell the robot has not seen any of."""
        rc = self.cell(p)
        if not self._inside(rc):
            return math.isfinite(p[0]) and math.isfinite(p[1])
        return not bool(self.known[rc])

    def _frontier_toward(
        self, start: tuple[int, int], goal: Point, free: npt.NDArray[np.bool_], tries: int = 64
    ) -> tuple[int, int] | None:
        """A traversable cell reachable from ``start`` (4-connected, as A* moves without cutting
        corners) at the edge of the known (next to unseen space or the map's border), nearest
        ``goal`` among those with no known wall on the straight line to it."""
        seen = _flood(start, free)
        # Next to unseen space (off the map counts), or as near it as the inflation lets a robot
        # stand when unseen space is planned as blocked.
        reach = 1 + (math.ceil(self.config.inflation / self.resolution) if self.config.unknown_is_blocked else 0)
        edge = np.pad(~self.known, reach, constant_values=True)
        for _ in range(reach):
            grown = edge.copy()
            grown[1:, :] |= edge[:-1, :]
            grown[:-1, :] |= edge[1:, :]
            grown[:, 1:] |= edge[:, :-1]
            grown[:, :-1] |= edge[:, 1:]
            edge = grown
        edge = edge[reach:-reach, reach:-reach]
        rows, cols = np.nonzero(seen & edge)
        if rows.size == 0:
            return None
        xs = self.origin[0] + (cols + 0.5) * self.resolution
        ys = self.origin[1] + (rows + 0.5) * self.resolution
        for k in np.argsort(np.hypot(xs - goal[0], ys - goal[1]))[:tries]:
            if self._clear_of_walls((float(xs[k]), float(ys[k])), goal):
                return int(rows[k]), int(cols[k])
        return None

    def _clear_of_walls(self, a: Point, b: Point) -> bool:
        """No known wall on the segment a-b (sampled at half a plan cell; off the map is clear)."""
        n = max(2, math.ceil(math.dist(a, b) / (self.resolution / 2)) + 1)
        t = np.linspace(0.0, 1.0, n)
        r = np.floor((a[1] + (b[1] - a[1]) * t - self.origin[1]) / self.resolution).astype(np.int64)
        c = np.floor((a[0] + (b[0] - a[0]) * t - self.origin[0]) / self.resolution).astype(np.int64)
        inside = (r >= 0) & (r < self.walls.shape[0]) & (c >= 0) & (c < self.walls.shape[1])
        return not bool(self.walls[r[inside], c[inside]].any())

    def route(
        self, start_xy: Point, goal_xy: Point, blocked: Sequence[Point] = (), bodies: Sequence[Point] = ()
    ) -> list[Point]:
        """The pilot's path provider form: waypoints, or [] when there is no path."""
        return self(start_xy, goal_xy, blocked, bodies) or []

    def unknown_marks(self, blocked: Sequence[Point]) -> list[Point]:
        """The ``blocked`` points the map does not already explain: finite, and farther than
        ``known_tolerance`` from a mapped wall (an echo from a known wall is that wall)."""
        out = []
        tol = self.config.known_tolerance + self.resolution / 2.0
        for x, y in blocked:
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            rc = self.cell((x, y))
            if self._inside(rc) and self.distance[rc] <= tol:
                continue
            out.append((float(x), float(y)))
        return out

    def _with_blocked(
        self, pts: Sequence[Point], bodies: Sequence[Point] = ()
    ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(free, cost, distance) with ``pts`` added as discs of ``blocked_radius`` and ``bodies``
        as discs of ``body_radius`` (the planner's own arrays without any)."""
        if not pts and not bodies:
            return self.free, self.cost, self.distance
        cfg, res = self.config, self.resolution
        dist = self.distance.copy()
        h, w = dist.shape
        discs = [(x, y, cfg.blocked_radius) for x, y in pts] + [(x, y, cfg.body_radius) for x, y in bodies]
        for x, y, radius in discs:
            reach = radius + cfg.inflation + cfg.cost_radius + res
            r0, c0 = self.cell((x - reach, y - reach))
            r1, c1 = self.cell((x + reach, y + reach))
            r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1 + 1, h), min(c1 + 1, w)
            if r0 >= r1 or c0 >= c1:
                continue
            ys = self.origin[1] + (np.arange(r0, r1) + 0.5) * res
            xs = self.origin[0] + (np.arange(c0, c1) + 0.5) * res
            d = np.hypot(xs[None, :] - x, ys[:, None] - y) - radius
            np.minimum(dist[r0:r1, c0:c1], np.maximum(d, 0.0), out=dist[r0:r1, c0:c1])
        free = np.asarray(dist - res / 2.0 >= cfg.inflation, dtype=bool)
        cr = max(cfg.cost_radius, 1e-9)
        near = np.clip(1.0 - (dist - res / 2.0 - cfg.inflation) / cr, 0.0, 1.0)
        return free, 1.0 + cfg.cost_weight * near, dist

    # -- what the front ultrasonic will see (the guard's view of a leg) ----------------------------

    def cone_range(self, xy: Point, heading: float, reach: float, marks: Sequence[Point] = ()) -> float:
        """Nearest echo (m, capped at ``reach``) the front ultrasonic would report with the robot at
        ``xy`` facing ``heading``, over the cone widened by ``angle_margin``, from the map (and
        from ``marks``, the obstacles the map lacks, as small discs)."""
        return self._cone_min(xy, np.array([heading]), reach, marks)

    def echo_ahead(self, pose: tuple[float, float, float], reach: float) -> float:
        """``cone_range`` from a pose, off the map echoing nothing: what the map says the front
        ultrasonic should read there (a reading much nearer is something the map does not hold)."""
        if not all(math.isfinite(v) for v in pose) or not reach > 0.0:
            return 0.0
        return self._cone_min((pose[0], pose[1]), np.array([pose[2]]), reach, (), off_map_echoes=False)

    def _cone_min(
        self,
        xy: Point,
        headings: npt.NDArray[np.float64],
        reach: float,
        marks: Sequence[Point],
        off_map_echoes: bool = True,
    ) -> float:
        sc = self.config.sensor or SensorCone()  # (None only turns the legs' checks off)
        half = sc.half_angle + sc.angle_margin
        k = max(2, math.ceil(2.0 * half / sc.ray_step) + 1)
        offs = np.linspace(-half, half, k)
        sx = xy[0] + sc.offset * np.cos(headings)  # the sensor sits ahead of the centre
        sy = xy[1] + sc.offset * np.sin(headings)
        ang = (headings[:, None] + offs[None, :]).ravel()
        ox, oy = np.repeat(sx, k), np.repeat(sy, k)
        step = self.echo_resolution / 2.0
        ts = np.arange(step, reach + step, step)
        px = ox[:, None] + np.cos(ang)[:, None] * ts[None, :]
        py = oy[:, None] + np.sin(ang)[:, None] * ts[None, :]
        cols = np.floor((px - self.origin[0]) / self.echo_resolution).astype(np.int64)
        rows = np.floor((py - self.origin[1]) / self.echo_resolution).astype(np.int64)
        h, w = self.echo.shape
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        hit = ~inside if off_map_echoes else np.zeros_like(inside)  # off the map: unknown (may echo)
        hit[inside] = self.echo[rows[inside], cols[inside]]
        for mx, my in marks:
            hit |= np.hypot(px - mx, py - my) < _MARK_ECHO_M
        any_hit = hit.any(axis=1)
        if not any_hit.any():
            return reach
        first = np.argmax(hit, axis=1)
        return float(min(reach, ts[first[any_hit]].min()))

    def leg_ok(self, a: Point, b: Point, marks: Sequence[Point] = ()) -> bool:
        """The guard will let the robot drive from ``a`` to ``b`` (once turned toward ``b``): nothing
        in the cone nearer than the leg plus the stop distance (or, beyond the sensor's range,
        nothing it can see), and at ``b`` nothing ahead inside the stop distance."""
        sc = self.config.sensor
        if sc is None:
            return True
        length = math.dist(a, b)
        if length < 1e-9:
            return True
        h = math.atan2(b[1] - a[1], b[0] - a[0])
        need = min(length + sc.stop_distance, sc.max_range) + sc.range_margin
        if self.cone_range(a, h, need, marks) < need:
            return False
        near = sc.stop_distance + sc.range_margin
        return self.cone_range(b, h, near, marks) >= near

    def room_behind(self, pose: tuple[float, float, float], limit: float) -> float:
        """How far (m, at most ``limit``) the robot at ``pose`` can back straight before its body
        would come within ``back_margin`` of anything the map blocks (a wall, or floor it has not
        seen). The robot has no sensor behind it: the map is what it knows of the floor there.
        A cell already that near (a robot parked beside a wall) only counts if backing would touch it."""
        x, y, th = pose
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(th)) or not limit > 0.0:
            return 0.0
        cfg, res = self.config, self.echo_resolution
        touch = cfg.robot_radius + res / 2.0  # a blocked cell's centre this near: its near edge touches the body
        keep = touch + cfg.back_margin
        dx, dy = self._blocked_near((x, y), limit + keep)
        back = -(dx * math.cos(th) + dy * math.sin(th))  # how far behind the centre, along the way back
        lateral = np.abs(dy * math.cos(th) - dx * math.sin(th))
        near = np.hypot(dx, dy) < keep
        reach = np.where(near, touch, keep)
        hit = (back > 0.0) & (lateral < reach)
        if not hit.any():
            return float(limit)
        enter = back[hit] - np.sqrt(reach[hit] ** 2 - lateral[hit] ** 2)
        return float(min(limit, max(0.0, enter.min())))

    def _blocked_near(self, p: Point, span: float) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Offsets (dx, dy) from ``p`` of the centres of the blocked map cells (``echo``, the map's own
        resolution) in the square ``span`` around it; off the map counts as blocked (not seen)."""
        res = self.echo_resolution
        c0, c1 = math.floor((p[0] - span - self.origin[0]) / res), math.floor((p[0] + span - self.origin[0]) / res) + 1
        r0, r1 = math.floor((p[1] - span - self.origin[1]) / res), math.floor((p[1] + span - self.origin[1]) / res) + 1
        h, w = self.echo.shape
        window = np.ones((r1 - r0, c1 - c0), dtype=bool)
        ra, rb, ca, cb = max(r0, 0), min(r1, h), max(c0, 0), min(c1, w)
        if ra < rb and ca < cb:
            window[ra - r0 : rb - r0, ca - c0 : cb - c0] = self.echo[ra:rb, ca:cb]
        rows, cols = np.nonzero(window)
        dx = np.asarray(self.origin[0] + (cols + c0 + 0.5) * res - p[0], dtype=np.float64)
        dy = np.asarray(self.origin[1] + (rows + r0 + 0.5) * res - p[1], dtype=np.float64)
        return dx, dy

    def barred_by_movable(self, p: Point) -> bool:
        """``p`` (a goal) is barred by known walls within the inflation of it, and every one of them
        lies in a piece of occupied cells no longer than ``MOVABLE_SIZE_M`` any way across (8-connected,
        looked for within that of them): the size of a robot or a person, which may have moved since the map
        drew it, not a wall of the building, which runs on. The route goes nearer such a goal to
        look again before it gives up on it (agent/route.py ``_approach``)."""
        if not (math.isfinite(p[0]) and math.isfinite(p[1])):
            return False
        res, reach = self.echo_resolution, self.config.inflation + self.echo_resolution
        span = reach + MOVABLE_SIZE_M + res
        h, w = self.wall_cells.shape
        c0, c1 = math.floor((p[0] - span - self.origin[0]) / res), math.floor((p[0] + span - self.origin[0]) / res) + 1
        r0, r1 = math.floor((p[1] - span - self.origin[1]) / res), math.floor((p[1] + span - self.origin[1]) / res) + 1
        if r0 < 0 or c0 < 0 or r1 > h or c1 > w:
            return False  # near the map's edge (or off it): what lies beyond is not known
        window = self.wall_cells[r0:r1, c0:c1]
        ys = self.origin[1] + (np.arange(r0, r1) + 0.5) * res - p[1]
        xs = self.origin[0] + (np.arange(c0, c1) + 0.5) * res - p[0]
        near = window & (np.hypot(xs[None, :], ys[:, None]) <= reach)
        if not near.any():
            return False  # not barred by walls near it (unknown floor, or no way there)
        wh, ww = window.shape
        left = near.copy()
        while left.any():
            seed = np.argwhere(left)[0]
            piece = _flood((int(seed[0]), int(seed[1])), window, diagonal=True)
            rows, cols = np.nonzero(piece)
            if rows.min() == 0 or cols.min() == 0 or rows.max() == wh - 1 or cols.max() == ww - 1:
                return False  # runs on beyond the window: a wall
            if (max(np.ptp(rows), np.ptp(cols)) + 1) * res > MOVABLE_SIZE_M:
                return False
            # Its longest extent, not its box's side: a stub of wall on the diagonal fits a 0.6 m box
            # at 0.85 m long. So does a crate 0.5 m square (0.71 m corner to corner), now a wall too;
            # a robot (0.34 m round) or a person fits. (A piece that fits the box has a few hundred cells.)
            if (
                float(np.hypot(rows[:, None] - rows[None, :], cols[:, None] - cols[None, :]).max()) + 1
            ) * res > MOVABLE_SIZE_M:
                return False
            left &= ~piece
        return True

    def place_near(self, start: Point, goal: Point, radius: float, places: int = 16) -> Point | None:
        """The place on a ring ``radius`` about ``goal`` nearest ``start`` (``places`` about it, the
        one on the line to the start first) that a path from ``start`` reaches and that sees the
        goal (no known wall on the way to it but what lies within the inflation of the goal: what
        bars it); None: none does. One flood fill finds what the start reaches, so a goal shut away
        costs no failed searches."""
        if not all(math.isfinite(v) for v in (*start, *goal, radius)):
            return None
        first = self._escape(self.cell(start), self.free)
        if first is None:
            return None
        seen = _flood(first, self.free)
        toward = math.atan2(start[1] - goal[1], start[0] - goal[0])
        order = [0, *(k * j for j in range(1, places // 2 + 1) for k in (1, -1))][:places]
        for j in order:
            a = toward + 2.0 * math.pi * j / places
            q = (goal[0] + radius * math.cos(a), goal[1] + radius * math.sin(a))
            rc = self.cell(q)
            short = max(0.0, 1.0 - (self.config.inflation + self.resolution) / radius)
            near_goal = (q[0] + short * (goal[0] - q[0]), q[1] + short * (goal[1] - q[1]))
            if self._inside(rc) and seen[rc] and self._clear_of_walls(q, near_goal):
                return q
        return None

    def _body_fits(self, p: Point, margin: float | None = None) -> bool:
        """The robot's body, centred at ``p``, stays ``margin`` (``fit_margin``) clear of every
        blocked map cell."""
        cfg = self.config
        need = cfg.robot_radius + (cfg.fit_margin if margin is None else margin) + self.echo_resolution / 2.0
        dx, dy = self._blocked_near(p, need)
        return not bool((np.hypot(dx, dy) < need).any())

    def leg_meets_wall(self, a: Point, b: Point, skip_m: float = 0.1) -> bool:
        """A known wall (an occupied map cell; unknown does not count) touches the body somewhere
        along a-b beyond its first ``skip_m`` (what it already stands beside is not ahead): a cell's
        centre within the robot's radius and half a cell of the segment. The pilot's route asks it
        of each newer map about the leg it drives (agent/route.py): a leg planned into the unknown,
        or on an older map, that the map now shows running into something."""
        if not all(math.isfinite(v) for v in (*a, *b)):
            return False
        length = math.dist(a, b)
        if length <= skip_m:
            return False
        res = self.echo_resolution
        need = self.config.robot_radius + res / 2.0
        c0 = max(0, math.floor((min(a[0], b[0]) - need - self.origin[0]) / res))
        c1 = math.floor((max(a[0], b[0]) + need - self.origin[0]) / res) + 1
        r0 = max(0, math.floor((min(a[1], b[1]) - need - self.origin[1]) / res))
        r1 = math.floor((max(a[1], b[1]) + need - self.origin[1]) / res) + 1
        rows, cols = np.nonzero(self.wall_cells[r0:r1, c0:c1])
        if rows.size == 0:
            return False
        bx = self.origin[0] + (cols + c0 + 0.5) * res
        by = self.origin[1] + (rows + r0 + 0.5) * res
        ux, uy = (b[0] - a[0]) / length, (b[1] - a[1]) / length
        along = np.clip((bx - a[0]) * ux + (by - a[1]) * uy, skip_m, length)
        return bool((np.hypot(bx - (a[0] + along * ux), by - (a[1] + along * uy)) < need).any())

    def leg_clear(self, a: Point, b: Point) -> bool:
        """The body stays ``back_margin`` clear of every wall the map holds all along a-b (the part
        within the ultrasonic's range of ``a``: what the guard is asked to creep past), or at least
        comes no nearer to it than at ``a``: a robot that stands touching a table on the map (a goal
        the body just fits at, beside it: ``_near_goal``) may creep away from it. Otherwise such a
        robot, facing a sofa inside the stop distance with the table behind it, could neither go on
        nor back off (the living room's two-robot round at seed 18, docs/motion.md)."""
        if not all(math.isfinite(v) for v in (*a, *b)):
            return False
        length = math.dist(a, b)
        reach = (self.config.sensor or SensorCone()).max_range
        t_end = 1.0 if length <= reach else reach / length
        n = max(2, math.ceil(min(length, reach) / (self.echo_resolution / 2.0)) + 1)
        cfg = self.config
        need = cfg.robot_radius + cfg.back_margin + self.echo_resolution / 2.0
        for t in np.linspace(0.0, t_end, n):
            q = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]))
            dx, dy = self._blocked_near(q, need)
            near = np.hypot(dx, dy)
            touching = near < need
            if not touching.any():
                continue
            # Touching at q: only cells the body was at least as near to at a (it stood there).
            from_a = np.hypot(dx[touching] + q[0] - a[0], dy[touching] + q[1] - a[1])
            if bool((near[touching] < from_a - 1e-9).any()):
                return False
        return True

    def _near_goal(
        self, goal: Point, free: npt.NDArray[np.bool_], marks: Sequence[Point], bodies: Sequence[Point] = ()
    ) -> tuple[int, int] | None:
        """For a goal in known space inside the inflation margin but where the body fits (a sweep's
        lane end beside a wall, a few centimetres nearer it than the margin): the nearest traversable
        cell within ``escape``, from which a straight leg, the body clear all along it, reaches it."""
        cfg = self.config
        rc = self.cell(goal)
        if not self._inside(rc) or not self.known[rc] or not self._body_fits(goal):
            return None
        if any(math.dist(goal, m) < cfg.blocked_radius + cfg.robot_radius for m in marks):
            return None
        if any(math.dist(goal, b) < cfg.body_radius + cfg.robot_radius + cfg.body_clearance for b in bodies):
            return None
        near = self._escape(rc, free)
        if near is None:
            return None
        a = self.center(near)
        n = max(2, math.ceil(math.dist(a, goal) / (self.echo_resolution / 2.0)) + 1)
        for t in np.linspace(0.0, 1.0, n):
            if not self._body_fits((a[0] + t * (goal[0] - a[0]), a[1] + t * (goal[1] - a[1]))):
                return None
        return near

    def turn_ok(self, xy: Point, h0: float, h1: float, marks: Sequence[Point] = ()) -> bool:
        """The guard will let the robot turn in place at ``xy`` from ``h0`` to ``h1`` (shorter arc):
        the cone sees nothing inside the stop distance anywhere along the sweep."""
        sc = self.config.sensor
        if sc is None:
            return True
        d = math.remainder(h1 - h0, 2.0 * math.pi)
        n = max(1, math.ceil(abs(d) / math.radians(5.0)))
        headings = h0 + d * np.arange(n + 1) / n
        near = sc.stop_distance + sc.range_margin
        return self._cone_min(xy, headings, near, marks) >= near

    # -- waypoints ---------------------------------------------------------------------------------

    def _lay(
        self,
        start: Point,
        goal: Point,
        cells: list[tuple[int, int]],
        free: npt.NDArray[np.bool_],
        dist: npt.NDArray[np.float64],
        marks: Sequence[Point],
        escaped: bool,
    ) -> list[Point]:
        """Waypoints along the A* cell path: each leg as long as possible while (1) its straight line
        stays as clear of walls as the cell path was at its narrowest over that stretch (capped at
        ``inflation + cost_radius``), so shortcuts keep to the middle of doorways and corridors, and
        (2) the guard will accept it (``leg_ok``; the turn onto it, ``turn_ok``). When no leg
        passes (2), the longest that passes (1) is taken."""
        cfg = self.config
        n = len(cells)
        pts = [self.center(rc) for rc in cells]
        pts[-1] = goal
        out: list[Point] = []
        h_in: float | None = None
        if escaped:
            out.append(pts[0])  # out of the inflated zone first, straight to the nearest free cell
            h_in = math.atan2(pts[0][1] - start[1], pts[0][0] - start[0])
        else:
            pts[0] = start
        if n == 1:
            return [*out, goal] if out[-1:] != [goal] else out
        rr = np.array([rc[0] for rc in cells])
        cc = np.array([rc[1] for rc in cells])
        dpath = dist[rr, cc]
        keep_cap = cfg.inflation + cfg.cost_radius
        i = 0
        while i < n - 1:
            bott = np.minimum.accumulate(dpath[i:])
            chosen = fallback = None
            for j in range(n - 1, i, -1):
                need = min(float(bott[j - i]), keep_cap) - self.resolution / 2.0 - 1e-9
                if j > i + 1 and not self._visible(cells[i], cells[j], free, dist, need):
                    continue
                if fallback is None:
                    fallback = j
                if cfg.sensor is None:
                    chosen = j
                    break
                if not self.leg_ok(pts[i], pts[j], marks):
                    continue
                h = math.atan2(pts[j][1] - pts[i][1], pts[j][0] - pts[i][0])
                if h_in is not None and not self.turn_ok(pts[i], h_in, h, marks):
                    continue
                chosen = j
                break
            j = chosen if chosen is not None else (fallback if fallback is not None else i + 1)
            h_in = math.atan2(pts[j][1] - pts[i][1], pts[j][0] - pts[i][0])
            out.append(pts[j])
            i = j
        return out

    def _escape(self, rc: tuple[int, int], free_grid: npt.NDArray[np.bool_]) -> tuple[int, int] | None:
        if self._inside(rc) and free_grid[rc]:
            return rc
        n = math.ceil(self.config.escape / self.resolution)
        best: tuple[float, tuple[int, int]] | None = None
        for dr in range(-n, n + 1):
            for dc in range(-n, n + 1):
                q = (rc[0] + dr, rc[1] + dc)
                d = math.hypot(dr, dc)
                if d <= n and self._inside(q) and free_grid[q] and (best is None or d < best[0]):
                    best = (d, q)
        return None if best is None else best[1]

    def _astar(
        self,
        start: tuple[int, int],
        goal: tuple[int, int],
        free_grid: npt.NDArray[np.bool_],
        cost_grid: npt.NDArray[np.float64],
    ) -> list[tuple[int, int]] | None:
        h, w = free_grid.shape
        free = free_grid.ravel().tolist()
        cost = cost_grid.ravel().tolist()
        s, g = start[0] * w + start[1], goal[0] * w + goal[1]
        gr, gc = goal
        best = {s: 0.0}
        parent = {s: -1}
        heap = [(0.0, 0.0, s)]
        closed = set()
        expansions = 0
        while heap:
            _, gcost, u = heapq.heappop(heap)
            if u in closed:
                continue
            if u == g:
                path = []
                while u != -1:
                    path.append((u // w, u % w))
                    u = parent[u]
                return path[::-1]
            closed.add(u)
            expansions += 1
            if expansions > self.config.max_expansions:
                return None
            ur, uc = divmod(u, w)
            for dr, dc, step in MOVES8:
                r, c = ur + dr, uc + dc
                if r < 0 or r >= h or c < 0 or c >= w:
                    continue
                v = r * w + c
                if not free[v] or v in closed:
                    continue
                if dr and dc and not (free[ur * w + c] and free[r * w + uc]):
                    continue  # no corner cutting
                ng = gcost + step * 0.5 * (cost[u] + cost[v])
                if ng < best.get(v, math.inf):
                    best[v] = ng
                    parent[v] = u
                    ddr, ddc = abs(r - gr), abs(c - gc)
                    heur = (ddr + ddc) + (_SQRT2 - 2.0) * min(ddr, ddc)
                    heapq.heappush(heap, (ng + heur, ng, v))
        return None

    def _visible(
        self,
        a: tuple[int, int],
        b: tuple[int, int],
        free: npt.NDArray[np.bool_],
        dist: npt.NDArray[np.float64],
        need: float,
    ) -> bool:
        """The straight line between two cells' centres crosses only traversable cells at least
        ``need`` from the nearest blocked cell (both cells either side of it where it passes between
        two centres)."""
        n = int(max(abs(b[0] - a[0]), abs(b[1] - a[1])) * 2) + 1
        t = np.linspace(0.0, 1.0, n + 1)
        fr = a[0] + (b[0] - a[0]) * t
        fc = a[1] + (b[1] - a[1]) * t
        rows = np.concatenate((np.rint(fr), np.floor(fr + 0.5 - 1e-9))).astype(np.int64)
        cols = np.concatenate((np.rint(fc), np.floor(fc + 0.5 - 1e-9))).astype(np.int64)
        return bool(free[rows, cols].all() and (dist[rows, cols] >= need).all())


MOVABLE_SIZE_M = 0.6
"""A piece of occupied cells no longer than this (a robot here is 0.34 m across, a person about
0.5 m) may be something that moves: ``barred_by_movable``."""
_MARK_ECHO_M = 0.12  # a marked point (10 cm behind the echo the pilot met) echoes as a disc this size
_BODY_ECHO_ANGLES = tuple(k * math.pi / 4.0 for k in range(8))


def _flood(start: tuple[int, int], free: npt.NDArray[np.bool_], *, diagonal: bool = False) -> npt.NDArray[np.bool_]:
    """The ``free`` cells reachable from ``start`` 4-connected (as A* moves without cutting
    corners; ``diagonal``: 8-connected, a piece of occupied cells); ~20 ms on an office-sized map."""
    seen = np.zeros_like(free)
    seen[start] = True
    while True:
        grow = seen.copy()
        grow[1:, :] |= seen[:-1, :]
        grow[:-1, :] |= seen[1:, :]
        grow[:, 1:] |= seen[:, :-1]
        grow[:, :-1] |= seen[:, 1:]
        if diagonal:
            row = grow.copy()  # the vertical spread of each row, then sideways: the 3 x 3 neighbourhood
            grow[:, 1:] |= row[:, :-1]
            grow[:, :-1] |= row[:, 1:]
        grow &= free
        if np.array_equal(grow, seen):
            return seen
        seen = grow


def _distance(blocked: npt.NDArray[np.bool_], res: float, reach: float) -> npt.NDArray[np.float64]:
    """Distance (m, between cell centres) to the nearest blocked cell, capped at ``reach``.

    Ring by ring outwards: the offsets at one distance are OR-ed as masks, and the cells they reach
    for the first time get that distance. Per offset that is a byte-wide OR instead of a float
    ``where`` and ``minimum`` over the grid, ~4x faster (a rebuild during a drive took ~15 ms)."""
    h, w = blocked.shape
    n = math.ceil(reach / res)
    dist = np.full((h, w), reach, dtype=np.float64)
    dist[blocked] = 0.0
    pad = np.zeros((h + 2 * n, w + 2 * n), dtype=bool)
    pad[n : n + h, n : n + w] = blocked
    rings: dict[float, list[tuple[int, int]]] = {}
    for dr in range(-n, n + 1):
        for dc in range(-n, n + 1):
            d = math.hypot(dr, dc) * res
            if 0 < d < reach:
                rings.setdefault(d, []).append((dr, dc))
    unset = ~blocked  # cells whose nearest blocked cell is not found yet
    hit = np.empty((h, w), dtype=bool)
    for d in sorted(rings):
        if not unset.any():
            break
        hit.fill(False)
        for dr, dc in rings[d]:
            np.logical_or(hit, pad[n + dr : n + dr + h, n + dc : n + dc + w], out=hit)
        hit &= unset
        dist[hit] = d
        unset &= ~hit
    return dist
