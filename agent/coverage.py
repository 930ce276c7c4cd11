"""Coverage planning: which floor to treat, where a UV robot dwells and for how long, how several
robots share the work, and a boustrophedon route for the sweeping robot. Pure numpy + stdlib, no I/O.

    fm = FloorMap(free, resolution, origin)                 # free: True where floor (light passes)
    area = room(fm, seed_xy) | rectangle(fm, x0, y0, x1, y1) | polygon(fm, [(x, y), ...])
    plan = plan_uv(fm, area, lamp, target_dose, start_xy)   # dwell points and times, a tour
    base = park_in_middle(fm, area, lamp, target_dose, start_xy)   # the common practice, a baseline
    fleet = split_plan(fm, plan, [start_a, start_b])        # the makespan balanced over N robots
    sweep = plan_sweep(fm, area, start_xy)                   # boustrophedon lanes one tool width apart
    look = plan_survey(fm, unknown, area, start_xy)          # view points into what the map has not seen
    dose = dose_map(fm, [plan], lamp)                        # J/m² on every map cell, from the plan
    coverage(dose, area, target_dose)                        # share of the area's cells at the dose
    plan.to_dict() / CoveragePlan.from_dict(d)               # plain data: nodes, edges, prediction

Grids: row 0 at ``origin[1]``, column 0 at ``origin[0]``, cell centres at ``origin + (i + 0.5) *
resolution`` (``shared/map_codec``'s). Where the robot may stand is the pilot's planner's own
inflated free space (``PathPlanner.free``, at its 10 cm plan resolution), so every dwell point is a
goal the planner accepts; the lamp reaches floor the robot cannot stand on (along walls).

The dose model is ``fleetlink.shared.dose.irradiance(lamp, x, y, free, resolution, origin)`` (W/m²
on every map cell, 0 in a wall's shadow), or any function with that signature (``irradiance=``).

UV dwell planning (``plan_uv``), the covering problem "least dwell + travel such that every lit
target cell gets the dose":
1. candidate stand points: one per ``candidate_spacing_m`` lattice block of the area's stand cells
   (the block's cell nearest its node, so blocks cut by a wall still get one, as near the wall as the
   robot may go), plus the convex corners of the stand region (they reach deepest into corners);
2. each candidate's footprint: its irradiance on the target cells (the dose model, whole map);
3. the least total dwell over all candidates, exactly: a linear programme (min sum(t) s.t.
   footprints @ t >= dose, t >= 0), solved by column generation (candidates priced against the
   cells' dual prices, the most negative added) and constraint generation (the cells left short
   added) on one simplex tableau of its dual, kept and re-solved from where it was (``_CoverLP``);
4. travel: every point costs a stop (``stop_overhead_s``) and its detour in the tour; points are
   tried for removal, least dwell first, re-solving the LP (a few pivots from the last tableau), and
   dropped when the dwell the others must add is less than the travel and stop saved;
5. the tour: nearest neighbour from the robot's start, then 2-opt and Or-opt moves, over shortest
   path lengths on the stand grid (exact 8-connected paths by a numpy wavefront; edges are those
   paths shortened while each leg stays on stand cells); travel time = length / ``speed_mps`` +
   ``stop_overhead_s`` per stop.
The dose received while driving is not planned on (the dwell alone reaches the dose); with
``lamp_while_driving`` the lamp stays on between dwell points and ``dose_map(..., travel=True)``
counts it. A greedy set cover (dwell added where it most reduces the deficit per second, travel
included) was tried as the LP's starting support: on the synthetic rooms it gave the same plans
after the LP and pruning, ~25 % slower, so the LP starts from a plain set cover (every lit cell seen).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from fleetlink.agent.mapping.planner import MOVES8, PathPlanner, PlannerConfig
from fleetlink.shared import dose as _dose
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.shared.dose import Lamp
from fleetlink.shared.geometry import components, points_in_polygon
from fleetlink.shared.messages import (
    MAX_ORDER_NODES,
    MAX_TRAJECTORY_POINTS,
    Action,
    ActionType,
    BlockingType,
    KeyValue,
    OrderEdge,
    OrderNode,
    Trajectory,
)

__all__ = [
    "MAX_ORDER_TRAJECTORY_POINTS",
    "Area",
    "CoverageConfig",
    "CoveragePlan",
    "FleetPlan",
    "FloorMap",
    "Irradiance",
    "PlanEdge",
    "PlanNode",
    "Prediction",
    "coverage",
    "dose_map",
    "lit_within",
    "park_in_middle",
    "plan_order",
    "plan_sweep",
    "plan_uv",
    "polygon",
    "reachable",
    "rectangle",
    "room",
    "split_plan",
    "sweepable",
    "validate_polygon",
]

Point = tuple[float, float]
Cell = tuple[int, int]
BoolGrid = npt.NDArray[np.bool_]
FloatGrid = npt.NDArray[np.float64]

Irradiance = Callable[[Lamp, float, float, BoolGrid, float, Point], FloatGrid]
"""``irradiance(lamp, x, y, free, resolution, origin)``: W/m² on every cell of ``free`` from the lamp
standing at (x, y), 0 in a wall's shadow: ``fleetlink.shared.dose.irradiance`` (the default)."""


@dataclass(frozen=True, slots=True)
class CoverageConfig:
    robot_radius_m: float = BODY_RADIUS_M  # the planner's robot (PlannerConfig.robot_radius)
    margin_m: float = 0.05  # beyond the radius (PlannerConfig.margin)
    plan_resolution_m: float = 0.1  # where the robot may stand is decided on this grid (the planner's)
    speed_mps: float = 0.3  # mean speed along paths, turns included (the pilot's v_max is 0.5)
    stop_overhead_s: float = 3.0  # per dwell stop: braking, arrival window, settling
    candidate_spacing_m: float = 0.4  # lattice of candidate stand points (0.2-0.4 m: within 2 % of each other)
    corner_candidates: bool = True  # also the convex corners of the standable region
    lamp_reach_m: float = 0.75  # floor this far (through free cells) from a stand cell is reachable floor
    dose_margin: float = 0.0  # plan for target * (1 + margin)
    lamp_while_driving: bool = False  # lamp on along edges between dwell points (counted by dose_map(travel=True))
    lp_seed_cells: int = (
        500  # the LP starts from about this many target cells (a regular subsample), adds the short ones
    )
    prune: bool = True  # drop dwell points whose travel costs more than the dwell they save
    coverage_goal: float = 1.0
    """Share of the floor the lamp can reach (target cells some stand point lights) to bring to the
    dose (UV). Below 1 the plan leaves out the cells the lamp reaches worst (least irradiance from
    the best stand point: cells reached only by grazing or distant light, e.g. a gap behind
    furniture), up to ``1 - coverage_goal`` of them: in the apartment's rooms 0.3-0.7 % of the
    cells took 70-85 % of the dwell. Cells no stand point lights are never counted as reachable."""
    tool_width_m: float = 0.34  # sweeping: width swept by the robot's brush (its diameter)
    max_cell_dwell_s: float = math.inf
    """Floor that would need longer than this under the lamp at the best stand point to get the
    dose is out of the lamp's reach (UV): not planned for, reported as unlit. Grazing light
    through a gap behind furniture, or past a wall's face on a lidar map, gives a few square
    centimetres hours of dwell."""
    lane_end_clearance_m: float = 0.0
    """A sweep's lanes stop this much short of the wall they run into: the collision guard does not
    drive head-on nearer than its stopping distance, and a lane end it cannot reach costs re-plans."""
    dwell_clearance_m: float = 0.0
    """Dwell points keep this far beyond ``margin_m`` from walls (paths may pass nearer): the
    collision guard will not drive head-on up to a point nearer a wall than its stopping distance
    (0.40 m ahead), so a dwell point there is never reached. Where no point that far from walls is
    near (a corridor too narrow), points along the corridor with this much stand floor ahead and
    behind are candidates too: the robot comes to them along the corridor."""
    pass_deviation_m: float = 0.15
    """A node the robot drives through (no dwell: a sweep's lane end, a point on the way) may be
    reached this near (the order node's allowedDeviationXY): planned on the map of the moment
    the plan was made, it can lie a few centimetres inside a wall's margin on the robot's map by the
    time it gets there. Dwell points are reached exactly (the dose is planned from there)."""


# --------------------------------------------------------------------------------------------------
# The map


class FloorMap:
    """The map prepared for coverage: the floor (``free``), where the robot may stand (``stand``, on
    the planner's grid), and shortest paths between stand cells (cached per source)."""

    def __init__(
        self,
        free: npt.ArrayLike,
        resolution: float,
        origin: Point = (0.0, 0.0),
        config: CoverageConfig | None = None,
    ) -> None:
        self.config = cfg = config or CoverageConfig()
        g = np.array(free, dtype=bool)
        if g.ndim != 2 or g.size == 0:
            raise ValueError(f"free: expected a non-empty 2-D grid, got shape {g.shape}")
        if not (math.isfinite(resolution) and resolution > 0):
            raise ValueError(f"resolution: must be a finite number > 0, got {resolution!r}")
        if not all(math.isfinite(v) for v in origin):
            raise ValueError(f"origin: must be finite, got {origin!r}")
        g.setflags(write=False)
        self.free: BoolGrid = g
        self.resolution = float(resolution)
        self.origin = (float(origin[0]), float(origin[1]))
        cells = np.where(g, 0, 100).astype(np.int8)
        self.planner = PathPlanner(
            cells,
            resolution,
            self.origin,
            PlannerConfig(robot_radius=cfg.robot_radius_m, margin=cfg.margin_m, plan_resolution=cfg.plan_resolution_m),
        )
        self.factor = max(1, round(cfg.plan_resolution_m / resolution))
        self.plan_resolution = self.planner.resolution
        self.stand: BoolGrid = np.asarray(self.planner.free, dtype=bool)
        """Plan cells where the robot's centre may be (the planner's inflated free space)."""
        h, w = g.shape
        f = self.factor
        self.stand_fine: BoolGrid = self.stand[np.arange(h) // f][:, np.arange(w) // f]
        """``stand`` at the map's resolution."""
        self._fields: dict[Cell, FloatGrid] = {}
        self._window: tuple[int, int, int, int] | None = None

    @classmethod
    def from_cells(
        cls,
        cells: npt.ArrayLike,
        resolution: float,
        origin: Point = (0.0, 0.0),
        config: CoverageConfig | None = None,
        *,
        free_max: int = 25,
        unknown_is_free: bool = False,
    ) -> FloorMap:
        """From map cells as they travel (int8: -1 unknown, 0-100), with the dose model's rule
        (``FloorMask.from_occupancy``): floor at or below ``free_max``; unknown is not floor unless
        ``unknown_is_free``."""
        return cls.from_mask(
            _dose.FloorMask.from_occupancy(
                cells, resolution, origin, free_max=free_max, unknown_is_free=unknown_is_free
            ),
            config,
        )

    @classmethod
    def from_mask(cls, mask: _dose.FloorMask, config: CoverageConfig | None = None) -> FloorMap:
        """The same floor the dose model's ``FloorMask`` describes."""
        return cls(mask.free, mask.resolution, mask.origin, config)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.free.shape[0]), int(self.free.shape[1]))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the map."""
        h, w = self.shape
        return (
            self.origin[0],
            self.origin[1],
            self.origin[0] + w * self.resolution,
            self.origin[1] + h * self.resolution,
        )

    @property
    def cell_area(self) -> float:
        return self.resolution * self.resolution

    def centres(self) -> tuple[FloatGrid, FloatGrid]:
        """(x, y) of every map cell's centre, as two grids."""
        h, w = self.shape
        xs = self.origin[0] + (np.arange(w) + 0.5) * self.resolution
        ys = self.origin[1] + (np.arange(h) + 0.5) * self.resolution
        gx, gy = np.meshgrid(xs, ys)
        return gx, gy

    def plan_cell(self, p: Point) -> Cell:
        return self.planner.cell(p)

    def plan_centre(self, rc: Cell) -> Point:
        return self.planner.center(rc)

    def plan_inside(self, rc: Cell) -> bool:
        return bool(0 <= rc[0] < self.stand.shape[0] and 0 <= rc[1] < self.stand.shape[1])

    def focus(self, cells: BoolGrid, *also: Cell, margin_m: float = 2.0) -> None:
        """Keep paths (``geodesic``, ``path``, ``route``) within the bounding box of the plan
        ``cells`` and ``also``, grown by ``margin_m``: a room's plan on a whole floor's map then
        costs the room's size, not the floor's (the office's 40 x 20 m took 110 s, most of it
        here). Paths that would leave the box are not found; the margin lets them round a door."""
        rows, cols = np.nonzero(cells)
        rr = [*rows.tolist(), *(c[0] for c in also)]
        cc = [*cols.tolist(), *(c[1] for c in also)]
        if not rr:
            return
        m = math.ceil(margin_m / self.plan_resolution)
        h, w = self.stand.shape
        window = (max(0, min(rr) - m), min(h, max(rr) + m + 1), max(0, min(cc) - m), min(w, max(cc) + m + 1))
        if window != self._window:
            self._window = window
            self._fields.clear()

    def geodesic(self, src: Cell) -> FloatGrid:
        """Metres along the shortest 8-connected path (no corner cutting) over stand cells from
        ``src`` to every plan cell (inf where unreachable, and outside the ``focus``). Cached per
        source."""
        got = self._fields.get(src)
        if got is None:
            r0, r1, c0, c1 = self._window or (0, *self.stand.shape[:1], 0, self.stand.shape[1])
            got = np.full(self.stand.shape, np.inf)
            if r0 <= src[0] < r1 and c0 <= src[1] < c1:
                sub = _wavefront(self.stand[r0:r1, c0:c1], (src[0] - r0, src[1] - c0), self.plan_resolution)
                got[r0:r1, c0:c1] = sub
            got.setflags(write=False)
            if len(self._fields) > 512:
                self._fields.clear()
            self._fields[src] = got
        return got

    def escape(self, p: Point, reach_m: float = 0.5) -> Cell | None:
        """The stand cell of ``p``, or the nearest stand cell within ``reach_m`` (a robot parked near a
        wall); None when there is none."""
        if not all(math.isfinite(v) for v in p):
            return None
        rc = self.plan_cell(p)
        if self.plan_inside(rc) and self.stand[rc]:
            return rc
        n = math.ceil(reach_m / self.plan_resolution)
        best: tuple[float, Cell] | None = None
        for dr in range(-n, n + 1):
            for dc in range(-n, n + 1):
                q = (rc[0] + dr, rc[1] + dc)
                d = math.hypot(dr, dc)
                if d <= n and self.plan_inside(q) and self.stand[q] and (best is None or d < best[0]):
                    best = (d, q)
        return None if best is None else best[1]

    def path(self, a: Cell, b: Cell) -> list[Point]:
        """The centres of the cells along the shortest stand path from ``a`` to ``b`` (both
        included); [] when ``b`` is unreachable. ``route`` shortens it."""
        fld = self.geodesic(b)
        if not math.isfinite(fld[a]):
            return []
        cells = [a]
        cur = a
        h, w = fld.shape
        while cur != b:
            best: tuple[float, Cell] | None = None
            for dr, dc, step in MOVES8:
                q = (cur[0] + dr, cur[1] + dc)
                if not (0 <= q[0] < h and 0 <= q[1] < w) or not self.stand[q]:
                    continue
                if dr and dc and not (self.stand[cur[0] + dr, cur[1]] and self.stand[cur[0], cur[1] + dc]):
                    continue
                v = float(fld[q]) + step * self.plan_resolution
                if best is None or v < best[0] - 1e-12:
                    best = (v, q)
            if best is None or not fld[best[1]] < fld[cur]:
                break  # cannot happen on a converged field; guard against a loop
            cur = best[1]
            cells.append(cur)
        return [self.plan_centre(rc) for rc in cells]

    def route(self, a: Point, b: Point) -> list[Point]:
        """Waypoints from ``a`` to ``b`` (both included; ``b`` on a stand cell) along the shortest
        stand path, each leg checked along its length (``clear_xy``) and made as long as that allows;
        [a, b] when unreachable."""
        if self.clear_xy(a, b):
            return [a, b]
        ca = self.escape(a) or self.plan_cell(a)  # a robot parked near a wall leaves by the nearest stand cell
        cells = self.path(ca, self.plan_cell(b))
        if not cells:
            return [a, b]
        pts = [a, *cells, b]
        out = [a]
        i = 0
        while i < len(pts) - 1:
            j = len(pts) - 1
            while j > i + 1 and not self.clear_xy(pts[i], pts[j]):
                j -= 1
            out.append(pts[j])
            i = j
        return out

    def clear_xy(self, a: Point, b: Point, cells: BoolGrid | None = None) -> bool:
        """The segment a-b (sampled at a fifth of a plan cell) stays on stand cells (or on ``cells``,
        a mask of plan cells); a sample on a cell's edge or corner must be clear on every side of it
        (a line exactly through a corner touches all four cells)."""
        mask = self.stand if cells is None else cells
        n = max(2, math.ceil(math.dist(a, b) / (self.plan_resolution / 5)) + 1)
        t = np.linspace(0.0, 1.0, n)
        y = (a[1] + (b[1] - a[1]) * t - self.origin[1]) / self.plan_resolution
        x = (a[0] + (b[0] - a[0]) * t - self.origin[0]) / self.plan_resolution
        h, w = mask.shape
        for dy in (-1e-9, 1e-9):
            r = np.floor(y + dy).astype(np.intp)
            for dx in (-1e-9, 1e-9):
                c = np.floor(x + dx).astype(np.intp)
                if (r < 0).any() or (r >= h).any() or (c < 0).any() or (c >= w).any():
                    return False
                if not mask[r, c].all():
                    return False
        return True


def _wavefront(passable: BoolGrid, src: Cell, res: float) -> FloatGrid:
    """Exact 8-connected shortest-path distances (no corner cutting) by Bellman-Ford sweeps in numpy:
    every pass relaxes each cell from its 8 neighbours, until nothing changes."""
    h, w = passable.shape
    if not (0 <= src[0] < h and 0 <= src[1] < w) or not passable[src]:
        return np.full((h, w), np.inf)
    pad = np.zeros((h + 2, w + 2), dtype=bool)
    pad[1:-1, 1:-1] = passable
    # A move's extra cost at its destination: its length where allowed, inf where not (the
    # destination blocked, or for a diagonal either cell it would cut the corner of).
    moves = []
    for dr, dc, step in MOVES8:
        ok = passable.copy()
        if dr and dc:
            ok &= pad[1 - dr : 1 - dr + h, 1 : 1 + w] & pad[1 : 1 + h, 1 - dc : 1 - dc + w]
        moves.append((dr, dc, np.where(ok, step * res, np.inf)))
    d = np.full((h + 2, w + 2), np.inf)  # with a border of inf: neighbours are plain slices
    d[1 + src[0], 1 + src[1]] = 0.0
    inner = d[1:-1, 1:-1]
    cand = np.empty((h, w))
    while True:
        before = inner.copy()
        for dr, dc, cost in moves:
            np.add(d[1 - dr : 1 - dr + h, 1 - dc : 1 - dc + w], cost, out=cand)
            np.minimum(inner, cand, out=inner)  # in place: later moves see this pass's updates
        if np.array_equal(inner, before):
            return inner.copy()


def _shift(a: BoolGrid, dr: int, dc: int) -> BoolGrid:
    """out[r, c] = a[r - dr, c - dc] (False off the grid)."""
    h, w = a.shape
    out = np.zeros_like(a)
    out[max(dr, 0) : h + min(dr, 0), max(dc, 0) : w + min(dc, 0)] = a[
        max(-dr, 0) : h - max(dr, 0), max(-dc, 0) : w - max(dc, 0)
    ]
    return out


def _disk(radius_cells: float) -> list[tuple[int, int]]:
    n = math.floor(radius_cells)
    return [
        (dr, dc)
        for dr in range(-n, n + 1)
        for dc in range(-n, n + 1)
        if dr * dr + dc * dc <= radius_cells * radius_cells
    ]


def _dilate(mask: BoolGrid, radius_cells: float) -> BoolGrid:
    out = mask.copy()
    for dr, dc in _disk(radius_cells):
        if dr or dc:
            out |= _shift(mask, dr, dc)
    return out


def _grow(mask: BoolGrid, allowed: BoolGrid, steps: int | None = None, *, eight: bool = True) -> BoolGrid:
    """``mask`` grown through ``allowed`` cells, ``steps`` times (None: until it stops growing)."""
    cur = mask & allowed
    moves = [(dr, dc) for dr, dc, _ in MOVES8] if eight else [(1, 0), (-1, 0), (0, 1), (0, -1)]
    i = 0
    while steps is None or i < steps:
        nxt = cur.copy()
        for dr, dc in moves:
            nxt |= _shift(cur, dr, dc)
        nxt &= allowed
        if np.array_equal(nxt, cur):
            break
        cur = nxt
        i += 1
    return cur


# --------------------------------------------------------------------------------------------------
# Areas


@dataclass(frozen=True, eq=False)
class Area:
    """What to treat. ``target``: the map cells that count (reachable floor inside the area);
    ``stand``: the plan cells where the robot may stand while treating it (inside the area)."""

    kind: str  # "rectangle" | "polygon" | "room"
    target: BoolGrid
    stand: BoolGrid
    cell_area: float
    outline: tuple[Point, ...] = ()
    seed: Point | None = None

    @property
    def cells(self) -> int:
        return int(self.target.sum())

    @property
    def area_m2(self) -> float:
        return self.cells * self.cell_area


def validate_polygon(vertices: Sequence[Point], bounds: tuple[float, float, float, float] | None = None) -> list[Point]:
    """The polygon's vertices (a repeated closing vertex dropped), or ValueError saying what is wrong:
    fewer than 3 vertices, a non-finite coordinate, a zero-length edge, zero area, edges that cross
    or touch (self-intersection, including an edge doubling back), a vertex outside ``bounds``."""
    pts = [(float(p[0]), float(p[1])) for p in vertices]
    if len(pts) >= 2 and pts[0] == pts[-1]:
        pts = pts[:-1]
    if len(pts) < 3:
        raise ValueError(f"polygon: needs at least 3 vertices, got {len(pts)}")
    for i, (x, y) in enumerate(pts):
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"polygon: vertex {i} ({x}, {y}) is not finite")
    n = len(pts)
    for i in range(n):
        if math.dist(pts[i], pts[(i + 1) % n]) < 1e-9:
            raise ValueError(f"polygon: edge {i} has zero length (vertex {i} repeats)")
    if bounds is not None:
        x0, y0, x1, y1 = bounds
        for i, (x, y) in enumerate(pts):
            if not (x0 <= x <= x1 and y0 <= y <= y1):
                raise ValueError(
                    f"polygon: vertex {i} ({x:g}, {y:g}) lies outside the map [{x0:g}, {x1:g}] x [{y0:g}, {y1:g}]"
                )
    scale = max(max(abs(x), abs(y)) for x, y in pts) + 1.0
    if all(abs(_orient(pts[0], pts[1], q)) <= 1e-12 * scale * scale for q in pts[2:]):
        raise ValueError("polygon: degenerate, its area is zero (collinear vertices)")
    for i in range(n):
        a, b = pts[i], pts[(i + 1) % n]
        for j in range(i + 1, n):
            c, d = pts[j], pts[(j + 1) % n]
            if j == i + 1 or (i == 0 and j == n - 1):
                # adjacent edges share one vertex: they may only meet there (no doubling back)
                shared, p, q = (b, a, d) if j == i + 1 else (a, b, c)
                u = (p[0] - shared[0], p[1] - shared[1])
                v = (q[0] - shared[0], q[1] - shared[1])
                cross = u[0] * v[1] - u[1] * v[0]
                if abs(cross) <= 1e-12 * scale * scale and u[0] * v[0] + u[1] * v[1] > 0:
                    raise ValueError(f"polygon: self-intersecting, edge {j} doubles back over edge {i}")
                continue
            if _segments_meet(a, b, c, d):
                raise ValueError(f"polygon: self-intersecting, edges {i} and {j} cross")
    area2 = sum(pts[i][0] * pts[(i + 1) % n][1] - pts[(i + 1) % n][0] * pts[i][1] for i in range(n))
    if abs(area2) / 2.0 <= 1e-9 * scale * scale:
        raise ValueError("polygon: degenerate, its area is zero (collinear vertices)")
    return pts


def _orient(a: Point, b: Point, c: Point) -> float:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def _segments_meet(a: Point, b: Point, c: Point, d: Point) -> bool:
    """The closed segments a-b and c-d share a point."""
    o1, o2, o3, o4 = _orient(a, b, c), _orient(a, b, d), _orient(c, d, a), _orient(c, d, b)
    if ((o1 > 0 and o2 < 0) or (o1 < 0 and o2 > 0)) and ((o3 > 0 and o4 < 0) or (o3 < 0 and o4 > 0)):
        return True

    def on(p: Point, q: Point, r: Point) -> bool:  # r on segment p-q, given collinear
        return (
            min(p[0], q[0]) - 1e-12 <= r[0] <= max(p[0], q[0]) + 1e-12
            and min(p[1], q[1]) - 1e-12 <= r[1] <= max(p[1], q[1]) + 1e-12
        )

    eps = 1e-12
    return (
        (abs(o1) <= eps and on(a, b, c))
        or (abs(o2) <= eps and on(a, b, d))
        or (abs(o3) <= eps and on(c, d, a))
        or (abs(o4) <= eps and on(c, d, b))
    )


def _area_from_region(
    fm: FloorMap, kind: str, region: BoolGrid, outline: tuple[Point, ...], seed: Point | None
) -> Area:
    """The area of a map-cell ``region``: stand cells whose centre lies in it, and its free cells
    within ``lamp_reach_m`` (through free cells) of one of them."""
    f = fm.factor
    ph, pw = fm.stand.shape
    h, w = fm.shape
    # A plan cell's centre falls in map cell (r * f + f // 2, c * f + f // 2) (clipped to the map).
    rr = np.minimum(np.arange(ph) * f + f // 2, h - 1)
    cc = np.minimum(np.arange(pw) * f + f // 2, w - 1)
    stand = fm.stand & region[rr][:, cc]
    if not stand.any():
        # How much of it the map holds as floor says which: an unmapped area (none), a strip along a
        # wall (some), a room the map draws smaller than it is.
        cell_m2 = fm.resolution * fm.resolution
        floor_m2 = float(np.count_nonzero(region & fm.free)) * cell_m2
        area_m2 = float(np.count_nonzero(region)) * cell_m2
        raise ValueError(
            f"{kind}: the robot can stand nowhere inside it (narrower than the robot, or all wall):"
            f" {floor_m2:.2f} of its {area_m2:.2f} m² is floor on the map"
        )
    stand_fine = stand[np.arange(h) // f][:, np.arange(w) // f] & fm.free
    steps = max(1, math.ceil(fm.config.lamp_reach_m / fm.resolution))
    reach = _grow(stand_fine, fm.free, steps)
    target = region & fm.free & reach
    return Area(kind, target, stand, fm.cell_area, outline, seed)


def polygon(fm: FloorMap, vertices: Sequence[Point]) -> Area:
    """The reachable floor inside a polygon (validated: ``validate_polygon`` against the map's bounds)."""
    pts = validate_polygon(vertices, fm.bounds)
    gx, gy = fm.centres()
    region = points_in_polygon(gx, gy, pts)
    if not (region & fm.free).any():
        raise ValueError("polygon: contains no floor")
    return _area_from_region(fm, "polygon", region, tuple(pts), None)


def rectangle(fm: FloorMap, x0: float, y0: float, x1: float, y1: float) -> Area:
    """The reachable floor inside an axis-aligned rectangle (two opposite corners)."""
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        raise ValueError(f"rectangle: corners must be finite, got ({x0}, {y0}), ({x1}, {y1})")
    xa, xb, ya, yb = min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1)
    if xb - xa < fm.resolution or yb - ya < fm.resolution:
        raise ValueError(f"rectangle: degenerate, {xb - xa:g} x {yb - ya:g} m is less than a cell")
    pts = [(xa, ya), (xb, ya), (xb, yb), (xa, yb)]
    area = polygon(fm, pts)
    return Area("rectangle", area.target, area.stand, area.cell_area, area.outline, None)


def room(fm: FloorMap, seed: Point, door_width_m: float = 1.0) -> Area:
    """The room around ``seed``, bounded by walls and by doorways narrower than ``door_width_m``.

    The walls are dilated by a disk of half the door width (the first half of a morphological
    closing): every gap narrower than the door width closes, and what stays free falls apart into
    the rooms' cores (floor at least half a door width from any wall), each a 4-connected flood
    fill. The cores then grow back together, a cell a step at a time through free cells, into what
    the dilation took (the floor near walls, alcoves, doorways); a cell reached by two rooms in the
    same step goes to the one whose core comes first in row-major order, so the rooms partition the
    floor and a doorway is split between the rooms either side. The seed's room is the one its cell
    went to. (The closing's second half, an erosion, would not
    do: a disk can reach the middle of a gap in a thin wall from either side, so a closing leaves
    such doors open.)"""
    if not all(math.isfinite(v) for v in seed):
        raise ValueError(f"room: seed must be finite, got {seed!r}")
    if not (math.isfinite(door_width_m) and door_width_m > 0):
        raise ValueError(f"room: door width must be a finite number > 0, got {door_width_m!r}")
    x0, y0, x1, y1 = fm.bounds
    if not (x0 <= seed[0] < x1 and y0 <= seed[1] < y1):
        raise ValueError(f"room: seed ({seed[0]:g}, {seed[1]:g}) lies outside the map")
    r = int((seed[1] - fm.origin[1]) // fm.resolution)
    c = int((seed[0] - fm.origin[0]) // fm.resolution)
    if not fm.free[r, c]:
        raise ValueError(f"room: seed ({seed[0]:g}, {seed[1]:g}) lies in a wall")
    labels = _rooms(fm.free, door_width_m / 2.0 / fm.resolution)
    if not labels.any():
        raise ValueError(
            f"room: no floor is {door_width_m / 2:g} m from the walls (narrower than a door: use a polygon)"
        )
    mine = int(labels[r, c])
    if mine == 0:
        raise ValueError(f"room: seed ({seed[0]:g}, {seed[1]:g}) lies in a pocket of floor no room reaches")
    return _area_from_region(fm, "room", labels == mine, (), (float(seed[0]), float(seed[1])))


def _rooms(free: BoolGrid, radius_cells: float) -> npt.NDArray[np.int32]:
    """Room labels (1, 2, ...; 0: wall, or floor no room reaches) of every cell (``room``)."""
    core = free & ~_dilate(~free, radius_cells)
    labels = np.zeros(free.shape, dtype=np.int32)
    left = core.copy()
    k = 0
    while left.any():
        first = np.zeros_like(left)
        first.flat[int(np.argmax(left))] = True
        comp = _grow(first, left, eight=False)
        k += 1
        labels[comp] = k
        left &= ~comp
    big = np.int32(k + 1)
    while True:
        todo = free & (labels == 0)
        if not todo.any():
            break
        near = np.full(free.shape, big, dtype=np.int32)
        pad = np.where(labels > 0, labels, big)
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            shifted = np.full(free.shape, big, dtype=np.int32)
            h, w = free.shape
            shifted[max(dr, 0) : h + min(dr, 0), max(dc, 0) : w + min(dc, 0)] = pad[
                max(-dr, 0) : h - max(dr, 0), max(-dc, 0) : w - max(dc, 0)
            ]
            np.minimum(near, shifted, out=near)
        grow = todo & (near < big)
        if not grow.any():
            break
        labels[grow] = near[grow]
    return labels


# --------------------------------------------------------------------------------------------------
# Plans as plain data


@dataclass(frozen=True, slots=True)
class PlanNode:
    """A place on the route (VDA 5050 node): the robot stops there for ``dwell_s`` (0: passes
    through) with the lamp ``lamp``."""

    node_id: str
    sequence_id: int
    x: float
    y: float
    dwell_s: float
    lamp: bool

    def to_dict(self) -> dict[str, Any]:
        return {
            "nodeId": self.node_id,
            "sequenceId": self.sequence_id,
            "x": self.x,
            "y": self.y,
            "dwell_s": self.dwell_s,
            "lamp": self.lamp,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PlanNode:
        return cls(
            str(d["nodeId"]), int(d["sequenceId"]), float(d["x"]), float(d["y"]), float(d["dwell_s"]), bool(d["lamp"])
        )


@dataclass(frozen=True, slots=True)
class PlanEdge:
    """The way between two nodes (VDA 5050 edge): waypoints from the start node to the end node
    (both included), the lamp while driving it, and for a sweep what it is (``lane``, ``connect``,
    ``transit``; ``path`` for a UV route)."""

    edge_id: str
    sequence_id: int
    start_node_id: str
    end_node_id: str
    waypoints: tuple[Point, ...]
    length_m: float
    lamp: bool
    kind: str = "path"

    def to_dict(self) -> dict[str, Any]:
        return {
            "edgeId": self.edge_id,
            "sequenceId": self.sequence_id,
            "startNodeId": self.start_node_id,
            "endNodeId": self.end_node_id,
            "waypoints": [[x, y] for x, y in self.waypoints],
            "length_m": self.length_m,
            "lamp": self.lamp,
            "kind": self.kind,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PlanEdge:
        return cls(
            str(d["edgeId"]),
            int(d["sequenceId"]),
            str(d["startNodeId"]),
            str(d["endNodeId"]),
            tuple((float(p[0]), float(p[1])) for p in d["waypoints"]),
            float(d["length_m"]),
            bool(d["lamp"]),
            str(d.get("kind", "path")),
        )


@dataclass(frozen=True, slots=True)
class Prediction:
    """What the planner expects of the plan. ``coverage``: share of the area's target cells the lamp
    can reach (all but ``unlit_m2``) at the target dose (UV), or of the floor within the tool's
    reach that the route passes (sweep); ``total_s = dwell_s + travel_s``, travel
    including ``stop_overhead_s`` per dwell stop; ``ideal_path_m``: a sweep's boustrophedon ideal
    (swept area / tool width)."""

    coverage: float
    dwell_s: float
    travel_s: float
    total_s: float
    path_m: float
    area_m2: float
    unlit_m2: float = 0.0  # target floor no candidate stand point sees (UV)
    ideal_path_m: float | None = None  # sweep
    swept_m2: float | None = None  # sweep: the floor the tool can reach at all

    def to_dict(self) -> dict[str, Any]:
        return {
            "coverage": self.coverage,
            "dwell_s": self.dwell_s,
            "travel_s": self.travel_s,
            "total_s": self.total_s,
            "path_m": self.path_m,
            "area_m2": self.area_m2,
            "unlit_m2": self.unlit_m2,
            "ideal_path_m": self.ideal_path_m,
            "swept_m2": self.swept_m2,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Prediction:
        def opt(k: str) -> float | None:
            v = d.get(k)
            return None if v is None else float(v)

        return cls(
            float(d["coverage"]),
            float(d["dwell_s"]),
            float(d["travel_s"]),
            float(d["total_s"]),
            float(d["path_m"]),
            float(d["area_m2"]),
            float(d.get("unlit_m2", 0.0)),
            opt("ideal_path_m"),
            opt("swept_m2"),
        )


@dataclass(frozen=True, slots=True)
class CoveragePlan:
    """One robot's plan: ``nodes[0]`` is where it starts (dwell 0, lamp off), each edge leads to the
    next node. ``kind``: ``uv`` (dwell points), ``park`` (the park-in-the-middle baseline), ``sweep``,
    ``survey`` (view points: ``plan_survey``; lit for a UV round's)."""

    kind: str
    nodes: tuple[PlanNode, ...]
    edges: tuple[PlanEdge, ...]
    target_dose: float  # J/m² (0 for a sweep)
    predicted: Prediction
    robot: str = ""

    @property
    def dwell_points(self) -> list[tuple[float, float, float]]:
        """(x, y, dwell_s) of every node with a dwell, in route order."""
        return [(n.x, n.y, n.dwell_s) for n in self.nodes if n.dwell_s > 0]

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "robot": self.robot,
            "target_dose": self.target_dose,
            "nodes": [n.to_dict() for n in self.nodes],
            "edges": [e.to_dict() for e in self.edges],
            "predicted": self.predicted.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CoveragePlan:
        return cls(
            str(d["kind"]),
            tuple(PlanNode.from_dict(n) for n in d["nodes"]),
            tuple(PlanEdge.from_dict(e) for e in d["edges"]),
            float(d["target_dose"]),
            Prediction.from_dict(d["predicted"]),
            str(d.get("robot", "")),
        )


def plan_order(
    plan: CoveragePlan, order_id: str, *, max_speed_mps: float | None = None, pass_deviation_m: float = 0.0
) -> dict[str, Any]:
    """The plan as an order's fields (``Order(**fields)``, VDA 5050 nodes and edges): every node
    with its actions in order, the lamp switched on before a lit dwell or a lit edge and off once
    nothing lit follows, ``dwell`` for each dwell time, the lamp off at the last node; each edge
    capped at ``max_speed_mps`` (a sweep's lanes, a lamp pass at constant speed); each node without
    a dwell reached within ``pass_deviation_m`` when it cannot be exactly (allowedDeviationXY,
    ``CoverageConfig.pass_deviation_m``). ValueError if the plan has more nodes than one order
    carries (``MAX_ORDER_NODES``): split the area."""
    if len(plan.nodes) > MAX_ORDER_NODES:
        raise ValueError(
            f"the route has {len(plan.nodes)} nodes, one order carries {MAX_ORDER_NODES}: choose a smaller area"
        )

    def act(kind: ActionType, aid: str, **params: str) -> Action:
        kvs = tuple(KeyValue(key=k, value=v) for k, v in params.items())
        return Action(actionId=aid, actionType=kind, actionParameters=kvs, blockingType=BlockingType.HARD)

    nodes: list[OrderNode] = []
    lamp = False
    for i, n in enumerate(plan.nodes):
        lit_after = i < len(plan.edges) and plan.edges[i].lamp
        actions: list[Action] = []
        if n.dwell_s > 0 and n.lamp and not lamp:
            actions.append(act(ActionType.PAYLOAD, f"{n.node_id}-uv-on", device="uv", on="true"))
            lamp = True
        left, part = n.dwell_s, 0
        while left > 0:  # one dwell action holds at most an hour (the agent's DWELL_MAX_S)
            chunk = min(left, 3600.0)
            part += 1
            suffix = "" if part == 1 else f"-{part}"
            actions.append(act(ActionType.DWELL, f"{n.node_id}-dwell{suffix}", duration=f"{chunk:.3f}"))
            left -= chunk
        if lit_after and not lamp:
            actions.append(act(ActionType.PAYLOAD, f"{n.node_id}-uv-on", device="uv", on="true"))
            lamp = True
        elif not lit_after and lamp:
            actions.append(act(ActionType.PAYLOAD, f"{n.node_id}-uv-off", device="uv", on="false"))
            lamp = False
        nodes.append(
            OrderNode(
                nodeId=n.node_id,
                sequenceId=n.sequence_id,
                released=True,
                x=n.x,
                y=n.y,
                theta=None,
                actions=tuple(actions),
                allowedDeviationXY=0.0 if n.dwell_s > 0 else pass_deviation_m,
            )
        )
    # Trajectories while the order stays well inside one message (MAX_ORDER_TRAJECTORY_POINTS): the
    # edges past that plan their own way, as every edge did before.
    budget = MAX_ORDER_TRAJECTORY_POINTS
    ways: list[Trajectory | None] = []
    for e in plan.edges:
        way = _trajectory(e)
        if way is not None and len(way.controlPoints) > budget:
            way, budget = None, 0
        budget -= 0 if way is None else len(way.controlPoints)
        ways.append(way)
    edges = tuple(
        OrderEdge(
            edgeId=e.edge_id,
            sequenceId=e.sequence_id,
            startNodeId=e.start_node_id,
            endNodeId=e.end_node_id,
            released=True,
            maxSpeed=max_speed_mps,
            trajectory=way,
        )
        for e, way in zip(plan.edges, ways, strict=True)
    )
    return {
        "orderId": order_id,
        "orderUpdateId": 0,
        "goal": None,
        "returnHome": False,
        "nodes": tuple(nodes),
        "edges": edges,
    }


MAX_ORDER_TRAJECTORY_POINTS = 600
"""Control points the trajectories of one order carry at most: an order of ``MAX_ORDER_NODES`` nodes
encodes to about 166 KB without them, and each point adds about 50 bytes (under the wire's 256 KB
with room to spare; tests/test_itinerary.py encodes the largest)."""


def _trajectory(edge: PlanEdge) -> Trajectory | None:
    """The edge's path as its trajectory (a polyline): the robot drives the way planned on the map
    the plan was made on (the fleet's, merged), not only the way its own map knows, which may not
    yet hold what another robot mapped. None when the path has too many corners for one."""
    pts = edge.waypoints
    if not 2 <= len(pts) <= MAX_TRAJECTORY_POINTS:
        return None
    return Trajectory.polyline(pts)


@dataclass(frozen=True, slots=True)
class FleetPlan:
    """An area split between robots: one plan each (their dwell points are disjoint; the doses add)."""

    plans: tuple[CoveragePlan, ...]
    coverage: float  # of the whole area, all robots together

    @property
    def makespan_s(self) -> float:
        return max((p.predicted.total_s for p in self.plans), default=0.0)

    def to_dict(self) -> dict[str, Any]:
        return {"plans": [p.to_dict() for p in self.plans], "coverage": self.coverage, "makespan_s": self.makespan_s}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FleetPlan:
        return cls(tuple(CoveragePlan.from_dict(p) for p in d["plans"]), float(d["coverage"]))


# --------------------------------------------------------------------------------------------------
# Dose evaluation


def _footprints(
    fm: FloorMap, area: Area, lamp: Lamp, points: Sequence[Point], irradiance: Irradiance
) -> npt.NDArray[np.float64]:
    """Irradiance (W/m²) on each target cell (rows, in ``np.nonzero(area.target)`` order) from each
    point (columns). On the whole map, as ``dose_map`` does: a line of sight that grazes a wall
    cell's corner exactly is decided by the last bit of the coordinates, which a cropped grid's
    shifted origin changes."""
    tr, tc = np.nonzero(area.target)
    out = np.empty((tr.size, len(points)))
    for j, (x, y) in enumerate(points):
        e = np.asarray(irradiance(lamp, float(x), float(y), fm.free, fm.resolution, fm.origin), dtype=np.float64)
        out[:, j] = e[tr, tc]
    return out


def dose_map(
    fm: FloorMap,
    plans: Sequence[CoveragePlan],
    lamp: Lamp,
    irradiance: Irradiance = _dose.irradiance,
    *,
    travel: bool = False,
    speed_mps: float | None = None,
    step_m: float = 0.2,
) -> FloatGrid:
    """J/m² on every map cell from the plans' dwells (and, with ``travel``, from driving their
    lamp-on edges at ``speed_mps``, sampled every ``step_m``)."""
    dose = np.zeros(fm.shape)
    speed = speed_mps or fm.config.speed_mps
    for p in plans:
        for n in p.nodes:
            if n.lamp and n.dwell_s > 0:
                dose += n.dwell_s * np.asarray(
                    irradiance(lamp, n.x, n.y, fm.free, fm.resolution, fm.origin), dtype=np.float64
                )
        if not travel:
            continue
        for e in p.edges:
            if not e.lamp:
                continue
            for (ax, ay), (bx, by) in itertools.pairwise(e.waypoints):
                seg = math.hypot(bx - ax, by - ay)
                k = max(1, math.ceil(seg / step_m))
                for i in range(k):
                    t = (i + 0.5) / k
                    e_w = irradiance(lamp, ax + (bx - ax) * t, ay + (by - ay) * t, fm.free, fm.resolution, fm.origin)
                    dose += (seg / k / speed) * np.asarray(e_w, dtype=np.float64)
    return dose


def reachable(
    fm: FloorMap,
    area: Area,
    lamp: Lamp,
    start: Point | None = None,
    *,
    target_dose: float = _dose.DEFAULT_TARGET_J_M2,
    irradiance: Irradiance = _dose.irradiance,
) -> BoolGrid:
    """The floor a UV round can reach: the area's target cells that some candidate stand point of
    the area (``plan_uv``'s, reachable from ``start`` if given) lights well enough to give
    ``target_dose`` within ``max_cell_dwell_s``."""
    stand = area.stand
    if start is not None:
        s_cell = _start_cell(fm, start)
        fm.focus(area.stand, s_cell)
        stand = stand & np.isfinite(fm.geodesic(s_cell))
    cands = _candidates(fm, stand)
    out = np.zeros(fm.shape, dtype=bool)
    if not cands:
        return out
    best = _footprints(fm, area, lamp, [fm.plan_centre(rc) for rc in cands], irradiance).max(axis=1)
    lit = best > target_dose * (1.0 + fm.config.dose_margin) / fm.config.max_cell_dwell_s
    rows, cols = np.nonzero(area.target)
    out[rows[lit], cols[lit]] = True
    return out


def sweepable(fm: FloorMap, area: Area, start: Point, tool_width_m: float | None = None) -> BoolGrid:
    """The floor a sweep can reach: the area's target cells within half a tool width of a stand
    cell the robot can get to from ``start`` (``plan_sweep``'s ``swept_m2``)."""
    width = tool_width_m if tool_width_m is not None else fm.config.tool_width_m
    s_cell = _start_cell(fm, start)
    fm.focus(area.stand, s_cell)
    reach = np.isfinite(fm.geodesic(s_cell)) & area.stand
    return _near_centres(fm, reach, width / 2.0) & area.target


def coverage(dose: FloatGrid, area: Area, target_dose: float) -> float:
    """Share of the area's target cells whose dose reaches ``target_dose`` (to a part in 10⁶)."""
    n = area.cells
    if n == 0:
        return 0.0
    return float((dose[area.target] >= target_dose * (1.0 - 1e-6)).sum()) / n


# --------------------------------------------------------------------------------------------------
# UV dwell planning


def _check_dose(target_dose: float) -> None:
    if not (isinstance(target_dose, int | float) and math.isfinite(target_dose) and target_dose > 0):
        raise ValueError(f"target dose: must be a finite number > 0 J/m², got {target_dose!r}")


def _start_cell(fm: FloorMap, start: Point) -> Cell:
    rc = fm.escape(start)
    if rc is None:
        raise ValueError(f"start ({start[0]:g}, {start[1]:g}): the robot cannot stand there or within 0.5 m of it")
    return rc


def _candidates(fm: FloorMap, stand: BoolGrid, *, corridors: bool = True, narrow: bool = False) -> list[Cell]:
    """One stand cell per lattice block (the one nearest the block's node), and the convex corners of
    the stand region; in row-major order. ``narrow``: where no point clear of walls is near, any
    stand cell not on the stand floor's edge (a survey looks from a gap beside a desk; it does
    not dwell there)."""
    k = max(1, round(fm.config.candidate_spacing_m / fm.plan_resolution))
    extra = fm.config.dwell_clearance_m / fm.plan_resolution
    if extra > 0:  # away from the walls (the whole map's: ``stand`` may be cut to an area)
        clear = stand & ~_dilate(~fm.stand, extra)
        if corridors:
            # Where no such point is near (a corridor narrower than twice the clearance): points
            # the robot can only come to along the corridor, with nothing near ahead.
            far = stand & ~_dilate(clear, 2.0 * extra + 3.0)
            clear = clear | _along_corridor(fm.stand, far, math.ceil(extra))
        if narrow:
            # Not on the narrow floor's edge: a map that sees the furniture better once the robot
            # is there must still let it stand there (a view on the edge of the living room's
            # 0.6 m gap left the robot where no round could start from).
            inner = stand.copy()
            for dr, dc, _ in MOVES8:
                inner &= _shift(fm.stand, dr, dc)
            clear = clear | (inner & ~_dilate(clear, 2.0 * extra + 3.0))
        stand = clear
    rows, cols = np.nonzero(stand)
    if rows.size == 0:
        return []
    br = np.floor((rows + 0.5) / k).astype(np.intp)
    bc = np.floor((cols + 0.5) / k).astype(np.intp)
    node_r, node_c = br * k + (k - 1) / 2.0, bc * k + (k - 1) / 2.0
    d = (rows - node_r) ** 2 + (cols - node_c) ** 2
    block = br * (int(bc.max()) + 1) + bc
    order = np.lexsort((cols, rows, d, block))  # per block: nearest first, then row-major
    first = np.ones(order.size, dtype=bool)
    first[1:] = block[order][1:] != block[order][:-1]
    chosen = {(int(rows[i]), int(cols[i])) for i in order[first]}
    if fm.config.corner_candidates:
        blocked = np.zeros(stand.shape, dtype=np.int8)
        for dr, dc, _ in MOVES8:
            blocked += ~_shift(stand, dr, dc)
        cr, cc = np.nonzero(stand & (blocked >= 5))
        chosen.update((int(a), int(b)) for a, b in zip(cr, cc, strict=True))
    return sorted(chosen)


def _along_corridor(whole: BoolGrid, cells: BoolGrid, reach: int) -> BoolGrid:
    """``cells`` in a corridor of ``whole`` along x or y: no stand floor ``reach`` cells to either
    side across it (walls close on both sides: the robot can only come along it), and stand floor
    for ``2 * reach`` cells ahead and behind along it (nothing ahead nearer than twice the dwell
    clearance, however the guard's ultrasonic cone meets the corridor's sides). Office room-1:
    the 1 m passage south of its desks, lit from nowhere else."""
    out = np.zeros_like(cells)
    for (dr, dc), (pr, pc) in (((0, 1), (1, 0)), ((1, 0), (0, 1))):
        ok = cells.copy()
        for step in range(1, 2 * reach + 1):
            ok &= _shift(whole, dr * step, dc * step) & _shift(whole, -dr * step, -dc * step)
        walled = [np.zeros_like(cells), np.zeros_like(cells)]
        for step in range(1, reach + 1):
            walled[0] |= ~_shift(whole, pr * step, pc * step)
            walled[1] |= ~_shift(whole, -pr * step, -pc * step)
        out |= ok & walled[0] & walled[1]
    return out


class _CoverLP:
    """min sum(t) s.t. bn[cell, support] @ t >= 1 for every lit cell, t >= 0: the least total dwell
    on a support of candidates (``bn``: irradiance / dose, cells x candidates).

    Kept as the optimal simplex tableau of its dual (max sum(y) s.t. bn[cells, support].T @ y <= 1,
    y >= 0: one row per support point, one column per cell), so that it can be changed and solved
    again from where it was: a cell added (a column, when the dwell leaves it short: constraint
    generation), a candidate added (a row, then dual simplex: column generation), a candidate
    removed (its slack pivoted into the basis, then its row dropped: pruning). The dwell of each
    support point is the reduced cost of its slack; the price of each cell is its dual value.
    Layout: columns [slacks (one per support point) | cells | right-hand side], last row the
    objective."""

    TOL = 1e-10

    def __init__(self, bn: npt.NDArray[np.float64], support: Sequence[int], cells: npt.NDArray[np.intp]) -> None:
        self.bn = bn
        self.support = [int(j) for j in support]
        self.cells = [int(c) for c in np.unique(cells)]
        m, n = len(self.support), len(self.cells)
        tab = np.zeros((m + 1, m + n + 1))
        tab[:m, :m] = np.eye(m)
        tab[:m, m : m + n] = bn[np.ix_(self.cells, self.support)].T
        tab[:m, -1] = 1.0
        tab[m, m : m + n] = -1.0
        self.tab = tab
        self.basis = list(range(m))  # the column basic in each row
        self._primal()
        self.cover()

    def copy(self) -> _CoverLP:
        out = object.__new__(_CoverLP)
        out.bn, out.support, out.cells = self.bn, list(self.support), list(self.cells)
        out.tab, out.basis = self.tab.copy(), list(self.basis)
        return out

    @property
    def m(self) -> int:
        return len(self.support)

    def dwell(self) -> npt.NDArray[np.float64]:
        """Seconds at each support point (a hair over the exact optimum, so every cell gets its dose)."""
        out: npt.NDArray[np.float64] = np.maximum(self.tab[self.m, : self.m], 0.0) * (1.0 + 1e-7)
        return out

    def prices(self) -> npt.NDArray[np.float64]:
        """The dual value of every lit cell (0 for cells not in the LP: they do not bind)."""
        m = self.m
        y = np.zeros(self.bn.shape[0])
        for i, col in enumerate(self.basis):
            if col >= m:
                y[self.cells[col - m]] = self.tab[i, -1]
        return y

    def _pivot(self, i: int, e: int) -> None:
        tab = self.tab
        tab[i] /= tab[i, e]
        f = tab[:, e].copy()
        f[i] = 0.0
        tab -= np.outer(f, tab[i])
        self.basis[i] = e

    def _primal(self, limit: int = 100000) -> None:
        m, tol = self.m, self.TOL
        degenerate = 0
        for _ in range(limit):
            obj = self.tab[m, :-1]
            if degenerate > 50:  # Bland's rule against cycling
                neg = np.nonzero(obj < -tol)[0]
                if neg.size == 0:
                    return
                e = int(neg[0])
            else:
                e = int(np.argmin(obj))
                if obj[e] >= -tol:
                    return
            col = self.tab[:m, e]
            pos = col > 1e-13
            if not pos.any():
                raise ValueError("cover LP: a cell no support point reaches")  # callers make sure it cannot
            ratio = np.full(m, np.inf)
            ratio[pos] = self.tab[:m, -1][pos] / col[pos]
            best = float(ratio.min())
            ties = np.nonzero(ratio <= best + 1e-13)[0]
            i = int(ties[np.argmin([self.basis[k] for k in ties])])
            degenerate = degenerate + 1 if best <= 1e-13 else 0
            self._pivot(i, e)
        raise RuntimeError("cover LP: no optimum after the pivot limit")

    def _dual(self, limit: int = 100000) -> None:
        """Dual simplex: the objective row is optimal, some right-hand sides are negative."""
        m, tol = self.m, self.TOL
        for _ in range(limit):
            rhs = self.tab[:m, -1]
            i = int(np.argmin(rhs))
            if rhs[i] >= -1e-12:
                self._primal()
                return
            row = self.tab[i, :-1]
            neg = row < -1e-13
            if not neg.any():
                raise RuntimeError("cover LP: infeasible dual (cannot happen: y = 0 is feasible)")
            ratio = np.full(row.size, np.inf)
            ratio[neg] = np.maximum(self.tab[m, :-1][neg], 0.0) / -row[neg]
            best = float(ratio.min())
            e = int(np.nonzero(ratio <= best + tol)[0][0])
            self._pivot(i, e)
        raise RuntimeError("cover LP: no optimum after the pivot limit")

    def add_cells(self, cells: Sequence[int]) -> None:
        """Cells as new columns (``B^-1 a`` from the slack block, reduced cost ``t . a - 1``)."""
        new = [int(c) for c in cells if int(c) not in set(self.cells)]
        if not new:
            return
        m = self.m
        a = self.bn[np.ix_(new, self.support)].T  # m x k
        cols = np.vstack((self.tab[:m, :m] @ a, self.tab[m, :m] @ a - 1.0))
        self.tab = np.concatenate((self.tab[:, :-1], cols, self.tab[:, -1:]), axis=1)
        self.cells.extend(new)
        self._primal()

    def add_points(self, points: Sequence[int]) -> None:
        """Candidates as new rows of the dual (a slack each, basic), then dual simplex."""
        for j in points:
            m, n = self.m, len(self.cells)
            row = np.zeros(m + 1 + n + 1)
            row[m] = 1.0  # its own slack, inserted after the others
            row[m + 1 : m + 1 + n] = self.bn[self.cells, j]
            row[-1] = 1.0
            tab = np.insert(self.tab, m, 0.0, axis=1)  # the new slack's column
            # Express the row in the current basis: eliminate every basic column from it.
            for r, col in enumerate(self.basis):
                c = col if col < m else col + 1
                if row[c] != 0.0:
                    row -= row[c] * tab[r]
            self.tab = np.vstack((tab[:m], row, tab[m:]))
            self.basis = [c if c < m else c + 1 for c in self.basis] + [m]
            self.support.append(int(j))
        self._dual()

    def remove_point(self, k: int) -> None:
        """Drop support point ``k`` (an index into ``support``): make its slack basic (keeping the
        other basics feasible), then delete that row and the slack's column."""
        m = self.m
        if k in self.basis:
            i = self.basis.index(k)
        else:
            col, rhs = self.tab[:m, k], self.tab[:m, -1]
            pos, neg = col > 1e-13, col < -1e-13
            ratio = np.full(m, np.inf)
            if pos.any():
                ratio[pos] = rhs[pos] / col[pos]
                i = int(np.argmin(ratio))
            else:
                ratio[neg] = -(rhs[neg] / col[neg])
                i = int(np.argmin(ratio))
            self._pivot(i, k)
        self.tab = np.delete(np.delete(self.tab, i, axis=0), k, axis=1)
        del self.basis[i]
        self.basis = [c - 1 if c > k else c for c in self.basis]
        del self.support[k]
        self._primal()

    def cover(self, batch: int = 400) -> None:
        """Add the cells the dwell leaves short (the shortest first) until none is. A cell already
        in the LP and still short is the tableau's rounding after many pivots (seen on a kitchen's
        two-robot round: the loop added nothing and never ended): the tableau is solved again
        from its slack basis, once, which clears it."""
        refreshed = False
        for _ in range(1000):
            got = self.bn[:, self.support] @ self.dwell()
            short = np.nonzero(got < 1.0 - 1e-9)[0]
            if short.size == 0:
                return
            known = set(self.cells)
            if all(int(c) in known for c in short):
                if refreshed:
                    break
                self._refresh()
                refreshed = True
                continue
            self.add_cells(short[np.argsort(got[short], kind="stable")[:batch]].tolist())
        raise RuntimeError("cover LP: constraint generation did not settle")

    def _refresh(self) -> None:
        """The same LP (support and cells) solved again from the slack basis."""
        m, n = self.m, len(self.cells)
        tab = np.zeros((m + 1, m + n + 1))
        tab[:m, :m] = np.eye(m)
        tab[:m, m : m + n] = self.bn[np.ix_(self.cells, self.support)].T
        tab[:m, -1] = 1.0
        tab[m, m : m + n] = -1.0
        self.tab = tab
        self.basis = list(range(m))
        self._primal()

    def drop_idle(self) -> None:
        """Remove the support points with no dwell."""
        while True:
            t = self.tab[self.m, : self.m]
            idle = [k for k in range(self.m) if t[k] <= 1e-9 and k in self.basis]
            if not idle:
                return
            self.remove_point(idle[-1])


def _column_generation(lp: _CoverLP, batch: int = 8, rounds: int = 500) -> None:
    """The least total dwell over every candidate: price every candidate not in the support against
    the cells' prices (reduced cost ``1 - bn[:, j] @ y``), add the most negative ones, solve again
    from there, until none is negative."""
    for _ in range(rounds):
        rho = 1.0 - lp.bn.T @ lp.prices()
        rho[lp.support] = np.inf
        best = np.argsort(rho, kind="stable")[:batch]
        add = [int(j) for j in best if rho[j] < -1e-7]
        if not add:
            break
        lp.add_points(add)
        lp.cover()
    lp.drop_idle()


def _two_opt(path: list[int], d: list[list[float]]) -> bool:
    """2-opt on an open path whose first point stays first: reverse stretches while that shortens it."""
    n = len(path)
    any_change = False
    improved = True
    while improved:
        improved = False
        for i in range(1, n - 1):
            a, b = path[i - 1], path[i]
            da, db = d[a], d[b]
            ab = da[b]
            for j in range(i + 1, n):
                c = path[j]
                if j + 1 < n:
                    e = path[j + 1]
                    delta = da[c] + db[e] - ab - d[c][e]
                else:
                    delta = da[c] - ab
                if delta < -1e-9:
                    path[i : j + 1] = path[i : j + 1][::-1]
                    improved = any_change = True
                    b = path[i]
                    db = d[b]
                    ab = da[b]
    return any_change


def _or_opt(path: list[int], d: list[list[float]]) -> bool:
    """Move single points (not the first) to where they lengthen the open path least, while that
    shortens it."""
    any_change = False
    improved = True
    while improved:
        improved = False
        for i in range(1, len(path)):
            p = path[i]
            prev = path[i - 1]
            nxt = path[i + 1] if i + 1 < len(path) else -1
            gain = d[prev][p] + (d[p][nxt] - d[prev][nxt] if nxt >= 0 else 0.0)
            rest = path[:i] + path[i + 1 :]
            best, at = gain - 1e-9, -1
            for k in range(1, len(rest) + 1):  # insert before rest[k] (or at the end)
                a = rest[k - 1]
                cost = d[a][p] + (d[p][rest[k]] - d[a][rest[k]] if k < len(rest) else 0.0)
                if cost < best:
                    best, at = cost, k
            if at >= 0 and at != i:
                rest.insert(at, p)
                path[:] = rest
                improved = any_change = True
    return any_change


class _Tours:
    """Open tours from a start over stand cells: nearest neighbour, then 2-opt; distances from the
    map's shortest-path fields."""

    def __init__(self, fm: FloorMap) -> None:
        self.fm = fm

    def matrix(self, cells: Sequence[Cell]) -> npt.NDArray[np.float64]:
        n = len(cells)
        rc = np.array(cells, dtype=np.intp).reshape(n, 2)
        d = np.empty((n, n))
        for i, a in enumerate(cells):
            d[i] = self.fm.geodesic(a)[rc[:, 0], rc[:, 1]]
        out: npt.NDArray[np.float64] = np.minimum(d, d.T)
        return out

    @staticmethod
    def order(dm: npt.NDArray[np.float64]) -> list[int]:
        """Visiting order of 1..n-1 from 0 (an open path) over distance matrix ``dm``: nearest
        neighbour, then 2-opt moves (a stretch reversed) and Or-opt moves (one point moved elsewhere)
        while any shortens it."""
        n = dm.shape[0]
        if n <= 2:
            return list(range(1, n))
        d: list[list[float]] = dm.tolist()
        left = set(range(1, n))
        path = [0]
        while left:
            row = d[path[-1]]
            nxt = min(left, key=lambda j: (row[j], j))
            path.append(nxt)
            left.remove(nxt)
        improved = True
        while improved:
            improved = _two_opt(path, d) | _or_opt(path, d)
        return path[1:]

    def tour(self, start: Cell, cells: Sequence[Cell]) -> tuple[list[int], float]:
        """(order of ``cells`` as indices, path length m)."""
        allc = [start, *cells]
        d = self.matrix(allc)
        order = self.order(d)
        length = 0.0
        prev = 0
        for k in order:
            length += float(d[prev, k])
            prev = k
        return [k - 1 for k in order], length


def plan_uv(
    fm: FloorMap,
    area: Area,
    lamp: Lamp,
    target_dose: float,
    start: Point,
    *,
    irradiance: Irradiance = _dose.irradiance,
    robot: str = "",
    prior: FloatGrid | None = None,
) -> CoveragePlan:
    """Dwell points and times that bring ``target_dose`` (J/m²) to every target cell some candidate
    stand point lights, in little total time (dwell + travel). See the module's docstring.

    ``prior``: the dose (J/m²) each map cell has already received (the fleet's dose layer sampled
    on ``fm``'s grid): a top-up round plans only what is missing, and cells at the dose already
    count as covered."""
    _check_dose(target_dose)
    cfg = fm.config
    s_cell = _start_cell(fm, start)
    fm.focus(area.stand, s_cell)
    from_start = fm.geodesic(s_cell)
    cands = [rc for rc in _candidates(fm, area.stand) if math.isfinite(from_start[rc])]
    if not cands:
        raise ValueError("plan: the robot cannot reach anywhere to stand in the area from its start")
    pts = [fm.plan_centre(rc) for rc in cands]
    a = _footprints(fm, area, lamp, pts, irradiance)
    need = target_dose * (1.0 + cfg.dose_margin)
    needs = np.full(a.shape[0], need)
    done = np.zeros(a.shape[0], dtype=bool)
    if prior is not None:
        got = np.asarray(prior, dtype=np.float64)
        if got.shape != fm.shape:
            raise ValueError(f"prior: expected the map's shape {fm.shape}, got {got.shape}")
        rows, cols = np.nonzero(area.target)
        have = np.nan_to_num(np.maximum(got[rows, cols], 0.0), nan=0.0, posinf=need)
        done = have >= need * (1.0 - 1e-9)
        needs = np.maximum(need - have, need * 1e-9)
    bn = a / needs[:, None]
    best = bn.max(axis=1)
    lit = (a.max(axis=1) > need / cfg.max_cell_dwell_s) & ~done
    if not 0.0 < cfg.coverage_goal <= 1.0:
        raise ValueError(f"coverage goal must be in (0, 1], got {cfg.coverage_goal!r}")
    unlit = int((~lit & ~done).sum())
    spare = math.floor((1.0 - cfg.coverage_goal) * (lit.size - unlit) + 1e-9)
    if spare > 0:  # leave out the worst-lit cells (they cost the most dwell per cell)
        worst = np.argsort(np.where(lit, best, np.inf), kind="stable")[:spare]
        lit[worst] = False
    if not lit.any():  # nothing left to dose (a top-up of a finished room): no dwell points
        return _uv_plan(
            fm, "uv", start, [], target_dose, coverage=int(done.sum()) / max(1, area.cells - unlit),
            area_m2=area.area_m2, unlit_m2=unlit * area.cell_area, robot=robot,
        )  # fmt: skip
    lit_rows = np.nonzero(lit)[0]
    bl = bn[lit_rows]

    # A starting support that sees every lit cell, then the exact LP over every candidate (column
    # generation), its cells generated from a regular subsample of the lit cells.
    stride = max(1, math.ceil(lit_rows.size / max(1, cfg.lp_seed_cells)))
    lp = _CoverLP(bl, _patch_support(bl, []), np.arange(0, lit_rows.size, stride))
    _column_generation(lp)
    tours = _Tours(fm)

    def total_time(trial: _CoverLP) -> float:
        _, length = tours.tour(s_cell, [cands[j] for j in trial.support])
        return float(trial.dwell().sum()) + length / cfg.speed_mps + trial.m * cfg.stop_overhead_s

    total = total_time(lp)
    if cfg.prune:
        # Drop the points whose travel and stop cost more than the dwell the others must add instead,
        # least dwell first.
        t0 = lp.dwell()
        for j in sorted(lp.support, key=lambda q: (float(t0[lp.support.index(q)]), q)):
            if j not in lp.support or lp.m == 1:
                continue
            rest = [q for q in lp.support if q != j]
            if not (bl[:, rest].max(axis=1) > 0).all():
                continue  # some cell only j sees
            trial = lp.copy()
            trial.remove_point(trial.support.index(j))
            trial.cover()
            trial.drop_idle()
            total2 = total_time(trial)
            if total2 < total - 1e-9:
                lp, total = trial, total2
    # The final dwell solved afresh on the final support (no drift from the pivots above).
    lp = _CoverLP(bl, lp.support, np.arange(0, lit_rows.size, stride))
    lp.drop_idle()
    support, t = lp.support, lp.dwell()
    order, _ = tours.tour(s_cell, [cands[j] for j in support])
    route = [support[k] for k in order]
    dwell = {j: float(v) for j, v in zip(support, t, strict=True)}
    covered = int((bl[:, support] @ t >= 1.0 - 1e-9).sum()) + int(done.sum())
    return _uv_plan(
        fm,
        "uv",
        start,
        [(cands[j], dwell[j]) for j in route],
        target_dose,
        coverage=covered / max(1, area.cells - unlit),
        area_m2=area.area_m2,
        unlit_m2=unlit * area.cell_area,
        robot=robot,
    )


def _patch_support(bl: npt.NDArray[np.float64], support: list[int]) -> list[int]:
    """``support`` plus, while some lit cell is seen by none of it, the candidate that sees most of those."""
    sup = list(support)
    while True:
        seen = bl[:, sup].max(axis=1) > 0 if sup else np.zeros(bl.shape[0], dtype=bool)
        miss = ~seen
        if not miss.any():
            return sup
        j = int(np.argmax((bl[miss] > 0).sum(axis=0)))
        sup.append(j)


def _uv_plan(
    fm: FloorMap,
    kind: str,
    start: Point,
    route: Sequence[tuple[Cell, float]],
    target_dose: float,
    *,
    coverage: float,
    area_m2: float,
    unlit_m2: float,
    robot: str,
    lit: bool | None = None,
) -> CoveragePlan:
    """The plan value: the start node, then a node per dwell point in ``route`` order, each reached
    by an edge along the shortest stand path; the lamp on at every dwell point (``lit``; by default
    all but a survey's)."""
    cfg = fm.config
    lit = kind != "survey" if lit is None else lit
    nodes = [PlanNode("n0", 0, float(start[0]), float(start[1]), 0.0, False)]
    edges: list[PlanEdge] = []
    prev_pt = (float(start[0]), float(start[1]))
    length = 0.0
    for i, (rc, dwell) in enumerate(route, start=1):
        x, y = fm.plan_centre(rc)
        way = fm.route(prev_pt, (x, y))
        seg = sum(math.dist(p, q) for p, q in itertools.pairwise(way))
        length += seg
        lamp_edge = lit and cfg.lamp_while_driving and i > 1
        edges.append(PlanEdge(f"e{i}", 2 * i - 1, nodes[-1].node_id, f"n{i}", tuple(way), seg, lamp_edge))
        nodes.append(PlanNode(f"n{i}", 2 * i, x, y, dwell, lit))
        prev_pt = (x, y)
    dwell_s = sum(d for _, d in route)
    travel = length / cfg.speed_mps + len(route) * cfg.stop_overhead_s
    pred = Prediction(
        coverage=coverage,
        dwell_s=dwell_s,
        travel_s=travel,
        total_s=dwell_s + travel,
        path_m=length,
        area_m2=area_m2,
        unlit_m2=unlit_m2,
    )
    return CoveragePlan(kind, tuple(nodes), tuple(edges), float(target_dose), pred, robot)


def park_in_middle(
    fm: FloorMap,
    area: Area,
    lamp: Lamp,
    target_dose: float,
    start: Point,
    *,
    irradiance: Irradiance = _dose.irradiance,
    robot: str = "",
    within: BoolGrid | None = None,
) -> CoveragePlan:
    """The common practice, as a baseline: drive to the reachable stand cell nearest the centroid of
    the area's target cells, and dwell until the farthest target cell in line of sight has the dose
    (the lit cell with the least irradiance: irradiance falls with distance). Cells out of its line
    of sight are never dosed; the prediction's coverage says how many are. ``within``: only these
    map cells count (the floor a round counts as reachable, ``reachable``)."""
    _check_dose(target_dose)
    s_cell = _start_cell(fm, start)
    fm.focus(area.stand, s_cell)
    from_start = fm.geodesic(s_cell)
    can = area.stand & np.isfinite(from_start)
    extra = fm.config.dwell_clearance_m / fm.plan_resolution
    if extra > 0:  # as far from walls as a dwell point (the guard will not drive up to nearer ones)
        clear = can & ~_dilate(~fm.stand, extra)
        can = clear if clear.any() else can
    rows, cols = np.nonzero(can)
    if rows.size == 0:
        raise ValueError("baseline: the robot cannot reach anywhere to stand in the area from its start")
    tr, tc = np.nonzero(area.target)
    cy = fm.origin[1] + (tr.mean() + 0.5) * fm.resolution
    cx = fm.origin[0] + (tc.mean() + 0.5) * fm.resolution
    xs = fm.origin[0] + (cols + 0.5) * fm.plan_resolution
    ys = fm.origin[1] + (rows + 0.5) * fm.plan_resolution
    k = int(np.argmin(np.hypot(xs - cx, ys - cy)))
    rc = (int(rows[k]), int(cols[k]))
    e = _footprints(fm, area, lamp, [fm.plan_centre(rc)], irradiance)[:, 0]
    lit = e > 0
    if within is not None:
        tr, tc = np.nonzero(area.target)
        lit &= np.asarray(within, dtype=bool)[tr, tc]
    dwell = float(target_dose / e[lit].min()) * (1.0 + 1e-7) if lit.any() else 0.0
    return _uv_plan(
        fm,
        "park",
        start,
        [(rc, dwell)],
        target_dose,
        coverage=int(lit.sum()) / max(1, area.cells),
        area_m2=area.area_m2,
        unlit_m2=0.0,
        robot=robot,
    )


def lit_within(plan: CoveragePlan, fm: FloorMap, area: Area) -> CoveragePlan:
    """``plan`` with the lamp off on every edge whose way leaves the area (passes a plan cell more
    than a cell from where the robot may stand in it, ``FloorMap.clear_xy``): the shortest way
    between two places in the area may run outside it, through a doorway or round a desk, and the
    lamp is for the area. ``plan_order`` then switches it off before such an edge and on again at
    the next lit dwell."""
    if not any(e.lamp for e in plan.edges):
        return plan
    inside = _dilate(area.stand, 1.0)

    def stays(way: Sequence[Point]) -> bool:
        return all(fm.clear_xy(a, b, inside) for a, b in itertools.pairwise(way))

    edges = tuple(replace(e, lamp=False) if e.lamp and not stays(e.waypoints) else e for e in plan.edges)
    return plan if edges == plan.edges else replace(plan, edges=edges)


# --------------------------------------------------------------------------------------------------
# Surveying: look before planning


SURVEY_DWELL_S = 1.0
"""A survey stops this long at each view point: a few lidar revolutions standing still."""


def unseen(fm: FloorMap, unknown: BoolGrid, area: Area, *, min_pocket_m2: float = 0.1) -> BoolGrid:
    """The area's unseen floor, as far as a map can say: map cells never observed (``unknown``)
    inside the area as drawn (its outline; a room's target grown by a metre) in pockets of at least
    ``min_pocket_m2`` that border the area's floor. The lidar saw the room from where the robot came
    in; what furniture hid from there is unknown and may be floor a round should dose."""
    hid = np.asarray(unknown, dtype=bool)
    if hid.shape != fm.shape:
        raise ValueError(f"unknown: expected the map's shape {fm.shape}, got {hid.shape}")
    if area.outline:
        gx, gy = fm.centres()
        region = points_in_polygon(gx, gy, list(area.outline))
    else:
        region = _dilate(area.target, 1.0 / fm.resolution)
    hid = hid & region
    edge = np.zeros(fm.shape, dtype=bool)
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        edge |= _shift(area.target, dr, dc)
    out = np.zeros(fm.shape, dtype=bool)
    least = max(1, math.ceil(min_pocket_m2 / fm.cell_area))
    for cells in components(hid):
        r, c = cells[:, 0], cells[:, 1]
        if r.size >= least and edge[r, c].any():
            out[r, c] = True
    return out


def plan_survey(
    fm: FloorMap,
    unknown: BoolGrid,
    area: Area,
    start: Point,
    *,
    view_range_m: float = 2.5,
    min_pocket_m2: float = 0.1,
    max_views: int = 8,
    enough: float = 0.9,
    robot: str = "",
    looked_from: Sequence[Point] = (),
    lit: bool = False,
    occupied: Sequence[Point] = (),
) -> CoveragePlan | None:
    """View points from which the lidar sees into the area's ``unseen`` pockets, toured from
    ``start`` (kind ``survey``, ``SURVEY_DWELL_S`` at each; the lamp on from the first view to the
    last if ``lit``: the views stand in the area, so a UV round's survey already doses it); None
    when the area has no unseen pocket a candidate stand point sees into.

    A candidate sees an unseen cell within ``view_range_m`` (the range at which the lidar's beams
    are still closer together than a map cell) when the straight line to it crosses no known
    wall: through the known floor and into the unknown, optimistically (what hides the pocket
    may stand in it; a second survey looks again). Cells the robot's start sees so already were
    in its view, not hidden: not counted; nor are cells an earlier survey looked for from
    ``looked_from`` (still unseen: what hides them is not on the map, e.g. the side of a desk the
    lidar has not seen, and looking from there again would not show them). No view where a robot
    stands (``occupied``: within two bodies of it; another robot of the round there is in the way).
    Greedy set cover, most unseen cells first, until ``enough`` of what any candidate sees is seen
    or ``max_views`` points."""
    hid = unseen(fm, unknown, area, min_pocket_m2=min_pocket_m2)
    if not hid.any():
        return None
    s_cell = _start_cell(fm, start)
    fm.focus(area.stand, s_cell)
    from_start = fm.geodesic(s_cell)
    # A survey looks from where the robot stands freely (it drives in among what it has not seen).
    cands = [rc for rc in _candidates(fm, area.stand, corridors=False, narrow=True) if math.isfinite(from_start[rc])]
    body = 2.0 * fm.config.robot_radius_m + fm.config.margin_m
    cands = [rc for rc in cands if all(math.dist(fm.plan_centre(rc), q) > body for q in occupied)]
    if not cands:
        return None
    rows, cols = np.nonzero(hid)
    stride = max(1, math.ceil(rows.size / 600))  # a regular subsample bounds the rays cast
    rows, cols = rows[::stride], cols[::stride]
    tx = fm.origin[0] + (cols + 0.5) * fm.resolution
    ty = fm.origin[1] + (rows + 0.5) * fm.resolution
    wall = np.asarray(~fm.free & ~np.asarray(unknown, dtype=bool), dtype=bool)

    def sees(p: Point) -> BoolGrid:
        d = np.hypot(tx - p[0], ty - p[1])
        near = d <= view_range_m
        out = np.zeros(tx.size, dtype=bool)
        if not near.any():
            return out
        idx = np.nonzero(near)[0]
        n = max(2, math.ceil(float(d[idx].max()) / (fm.resolution / 2.0)) + 1)
        t = np.linspace(0.0, 1.0, n)[None, :]
        xs = p[0] + (tx[idx, None] - p[0]) * t
        ys = p[1] + (ty[idx, None] - p[1]) * t
        c = np.clip(np.floor((xs - fm.origin[0]) / fm.resolution).astype(np.intp), 0, fm.shape[1] - 1)
        r = np.clip(np.floor((ys - fm.origin[1]) / fm.resolution).astype(np.intp), 0, fm.shape[0] - 1)
        out[idx] = ~wall[r, c].any(axis=1)
        return out

    already = sees(start)
    for p in looked_from:
        already |= sees((float(p[0]), float(p[1])))
    view = np.array([sees(fm.plan_centre(rc)) & ~already for rc in cands])
    seeable = view.any(axis=0)
    if not seeable.any():
        return None
    goal = enough * int(seeable.sum())
    seen = np.zeros(tx.size, dtype=bool)
    picked: list[int] = []
    away = from_start[tuple(np.array(cands).T)] * 1e-6  # ties: nearer the start
    while int(seen.sum()) < goal and len(picked) < max_views:
        gain = (view & ~seen).sum(axis=1)
        j = int(np.argmax(gain - away))
        if gain[j] == 0:
            break
        picked.append(j)
        seen |= view[j]
    order, _ = _Tours(fm).tour(s_cell, [cands[j] for j in picked])
    route = [(cands[picked[k]], SURVEY_DWELL_S) for k in order]
    return _uv_plan(
        fm,
        "survey",
        start,
        route,
        0.0,
        coverage=float(seen.sum()) / float(seeable.sum()),
        area_m2=float(hid.sum()) * fm.cell_area,
        unlit_m2=0.0,
        robot=robot,
        lit=lit,
    )


# --------------------------------------------------------------------------------------------------
# Several robots


def split_plan(
    fm: FloorMap,
    plan: CoveragePlan,
    starts: Sequence[Point],
    robots: Sequence[str] = (),
    *,
    total_weight: float = 0.0,
) -> FleetPlan:
    """The plan's dwell points shared between ``len(starts)`` robots so that the last one finishes
    early (the makespan: dwell + travel + stops of the busiest robot). The dwell times stay as
    planned, so the doses add up to the same map. Points are first cut into contiguous runs of equal
    dwell along their principal axis, then the busiest robot's points are moved to another robot, or
    swapped with one of the 6 nearest of its points, best first, while that lowers the makespan plus
    ``total_weight`` times the robots' times summed; each robot's points are toured from its own
    start. ``total_weight`` > 0 trades a little makespan for less driving in all: for a survey,
    where the robots drive nearly all the time, a split that is a second faster by sending two
    robots across the room past each other is not one (they meet on the way)."""
    cfg = fm.config
    n = len(starts)
    if n < 1:
        raise ValueError("split: needs at least one robot")
    names = list(robots) or [f"r{i + 1}" for i in range(n)]
    if len(names) != n:
        raise ValueError("split: one name per start")
    s_cells = [_start_cell(fm, s) for s in starts]
    pts = plan.dwell_points
    cells = [fm.plan_cell((x, y)) for x, y, _ in pts]
    dwell = np.array([d for _, _, d in pts])
    tours = _Tours(fm)
    allc = s_cells + cells
    fm.focus(np.zeros(fm.stand.shape, dtype=bool), *allc)
    dm = tours.matrix(allc)

    def robot_time(r: int, members: Sequence[int]) -> float:
        if not members:
            return 0.0
        idx = [r, *(n + p for p in members)]
        sub = dm[np.ix_(idx, idx)]
        order = tours.order(sub)
        length, prev = 0.0, 0
        for k in order:
            length += float(sub[prev, k])
            prev = k
        return float(dwell[list(members)].sum()) + length / cfg.speed_mps + len(members) * cfg.stop_overhead_s

    # Initial cut along the principal axis, weighted by dwell.
    xy = np.array([(x, y) for x, y, _ in pts]) if pts else np.zeros((0, 2))
    groups: list[list[int]] = [[] for _ in range(n)]
    if len(pts):
        wsum = float(dwell.sum())
        mean = (xy * dwell[:, None]).sum(axis=0) / wsum
        cov = ((xy - mean) * dwell[:, None]).T @ (xy - mean) / wsum
        _, vecs = np.linalg.eigh(cov)
        axis = vecs[:, -1]
        if axis[0] < 0 or (axis[0] == 0 and axis[1] < 0):
            axis = -axis
        proj = (xy - mean) @ axis
        order = np.lexsort((np.arange(len(pts)), proj))
        # robots sorted by their start's projection, so the first robot takes the first run
        sproj = [float((np.array(starts[r]) - mean) @ axis) for r in range(n)]
        robots_by = sorted(range(n), key=lambda r: (sproj[r], r))
        cum = np.cumsum(dwell[order]) - dwell[order] / 2.0
        for k, p in enumerate(order):
            g = min(n - 1, int(cum[k] / wsum * n))
            groups[robots_by[g]].append(int(p))

    def cost(ts: Sequence[float]) -> float:
        return max(ts) + total_weight * sum(ts)

    times = [robot_time(r, groups[r]) for r in range(n)]
    for _ in range(200):
        worst = max(range(n), key=lambda r: (times[r], -r))
        span = cost(times)
        best: tuple[float, float, list[list[int]], list[float]] | None = None
        for p in groups[worst]:
            for o in range(n):
                if o == worst:
                    continue
                near = sorted(groups[o], key=lambda q: (float(dm[n + p, n + q]), q))[:6]  # swap partners
                for q in [None, *near]:
                    gw = [x for x in groups[worst] if x != p] + ([q] if q is not None else [])
                    go = [x for x in groups[o] if x != q] + [p]
                    tw, to = robot_time(worst, gw), robot_time(o, go)
                    new = [*times]
                    new[worst], new[o] = tw, to
                    key = (cost(new), sum(new))
                    if key[0] < span - 1e-9 and (best is None or key < (best[0], best[1])):
                        ng = [list(g) for g in groups]
                        ng[worst], ng[o] = sorted(gw), sorted(go)
                        best = (key[0], key[1], ng, new)
        if best is None:
            break
        groups, times = best[2], best[3]
    plans = []
    for r in range(n):
        members = groups[r]
        seq, _ = tours.tour(s_cells[r], [cells[p] for p in members])
        route = [(cells[members[k]], float(dwell[members[k]])) for k in seq]
        pr = plan.predicted
        plans.append(
            _uv_plan(
                fm,
                plan.kind,
                starts[r],
                route,
                plan.target_dose,
                coverage=pr.coverage,
                area_m2=pr.area_m2,
                unlit_m2=pr.unlit_m2,
                robot=names[r],
                lit=any(node.lamp for node in plan.nodes),
            )
        )
    return FleetPlan(tuple(plans), plan.predicted.coverage)


# --------------------------------------------------------------------------------------------------
# Sweeping


@dataclass(slots=True)
class _Strip:
    """One decomposition cell: consecutive lanes with one interval each, (lane y, x0, x1) bottom up."""

    lanes: list[tuple[float, float, float]] = field(default_factory=list)


def _runs(row: BoolGrid) -> list[tuple[int, int]]:
    """[c0, c1] (inclusive) of every run of True."""
    x = np.concatenate(([False], row, [False])).astype(np.int8)
    d = np.diff(x)
    starts = np.nonzero(d == 1)[0]
    ends = np.nonzero(d == -1)[0] - 1
    return [(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]


STRIP_STEP_M = 1.0
"""A lane whose interval ends this much further in (or out) than the one before it, at either end,
starts a strip of its own (measured, bench/coverage.py: the bedroom's sweep 93.9 -> 95.1 %)."""
NUB_M = 1.0
"""``plan_sweep`` also tries its lane grid spaced from the first to the last row whose longest run
of stand cells is at least this long (or half the longest row's, if that is shorter): the narrow
rows at the two ends (a doorway's floor, a ragged row along a wall) are left to the fill lanes;
narrow rows between stay in. Spaced over such a nub too, the lanes of the wide floor beside it end
a few centimetres short of its far wall (the kitchen's and the living room's north walls,
docs/payload.md)."""


def _lane_rows(stand: BoolGrid, res: float, nub_m: float) -> tuple[int, int] | None:
    """The first and last row the lane grid is spaced over (``_decompose``; ``NUB_M``), None
    without stand cells."""
    rows = np.nonzero(stand.any(axis=1))[0]
    if rows.size == 0:
        return None
    if nub_m > 0:
        longest = np.array([max((b - a + 1 for a, b in _runs(stand[r])), default=0) for r in rows]) * res
        rows = rows[longest >= min(nub_m, 0.5 * float(longest.max())) - 1e-9]
    return int(rows.min()), int(rows.max())


def _decompose(
    stand: BoolGrid, res: float, ox: float, oy: float, width: float, spread: float | None = None, nub_m: float = 0.0
) -> list[_Strip]:
    """Boustrophedon decomposition of ``stand`` (rows along y, lanes along x): lanes one tool width
    apart (evenly over the stand rows' extent; with ``nub_m`` > 0, without the narrow rows at its
    two ends, ``NUB_M``), each split into intervals of stand cells; intervals
    on consecutive lanes that overlap one-to-one continue the same cell, anything else (a split
    around an obstacle, a merge, or an interval whose end moves by more than ``STRIP_STEP_M``: a
    doorway's nub, the floor beside a wardrobe ending) starts new cells. A strip that ends at such a
    step spreads its lanes over its own floor (``_edge_lanes``) instead of leaving a lane's worth of it
    beside the shorter lane, which runs along one wall only."""
    rows = np.nonzero(stand.any(axis=1))[0]
    ends = _lane_rows(stand, res, nub_m)
    if ends is None:
        return []
    y0 = oy + (ends[0] + 0.5) * res
    y1 = oy + (ends[1] + 0.5) * res
    nl = max(1, math.ceil((y1 - y0) / width - 1e-9) + 1)
    ys = np.linspace(y0, y1, nl) if nl > 1 else np.array([0.5 * (y0 + y1)])
    lanes: list[tuple[float, list[tuple[int, int]]]] = []
    for y in ys:
        f = (y - oy) / res
        if f - math.floor(f) < 1e-6:  # not on a cell edge: a lane there would touch both rows
            y += 1e-5 * res
        r = min(max(math.floor((y - oy) / res), int(rows.min())), int(rows.max()))  # as PathPlanner.cell
        lanes.append((float(y), _runs(stand[r])))
    strips: list[_Strip] = []
    open_: dict[int, int] = {}  # interval index on the previous lane -> strip index
    prev: list[tuple[int, int]] = []
    for y, ivs in lanes:
        nxt: dict[int, int] = {}
        for i, (a, b) in enumerate(ivs):
            over_prev = [k for k, (pa, pb) in enumerate(prev) if pa <= b and a <= pb]
            s: int | None = None
            if len(over_prev) == 1:
                k = over_prev[0]
                pa, pb = prev[k]
                over_cur = [q for q, (ca, cb) in enumerate(ivs) if ca <= pb and pa <= cb]
                step = max(abs(a - pa), abs(b - pb)) * res
                if len(over_cur) == 1 and k in open_ and step <= STRIP_STEP_M:
                    s = open_[k]
            if s is None:
                strips.append(_Strip())
                s = len(strips) - 1
            strips[s].lanes.append((y, ox + (a + 0.5) * res, ox + (b + 0.5) * res))
            nxt[i] = s
        open_, prev = nxt, ivs
    for strip in strips:
        _edge_lanes(strip, stand, res, ox, oy, width, width if spread is None else spread)
    return strips


def _edge_lanes(strip: _Strip, stand: BoolGrid, res: float, ox: float, oy: float, width: float, spread: float) -> None:
    """Spread ``strip``'s lanes over its own floor where that goes on past its end lanes (the lanes are
    spaced over the whole area, so a part of it, such as the floor beside a table, ends between two
    of them): to the last row of stand cells at each end that still continues the end lane's
    interval alone (one run, not merged with a neighbour's), up to ``spread`` apart. What floor is
    left past them gets no lane more here: beside an island that lane would run the strip's whole
    length and sweep again, for the floor beside the island alone, what the lanes the island cuts
    short sweep (the kitchen's: 3.8 m for 0.1 m²); ``_fill_gaps`` adds a lane where it is worth its
    way (measured over the five rooms at seeds 16-18, docs/payload.md: no lane more was ever worth
    0.05 m² per metre)."""
    h = stand.shape[0]
    ext: list[int] = []  # rows past each end lane, bottom then top
    for top in (False, True):
        y, x0, x1 = strip.lanes[-1] if top else strip.lanes[0]
        r = math.floor((y - oy) / res)
        a, b = round((x0 - ox) / res - 0.5), round((x1 - ox) / res - 0.5)
        step = 1 if top else -1
        got = 0
        for k in range(1, max(1, math.ceil(width / res))):
            rr = r + step * k
            if not 0 <= rr < h:
                break
            over = [(c0, c1) for c0, c1 in _runs(stand[rr]) if c0 <= b and a <= c1]
            if len(over) != 1 or (over[0][1] - over[0][0]) - (b - a) > width / res:  # none, split, merged
                break
            if min(over[0][1], b) - max(over[0][0], a) + 1 < 0.9 * (b - a + 1):
                break  # narrower: the floor of the strip beyond a step (a nub), not this one's
            got = k
        ext.append(got)
    if not any(ext):
        return
    lanes = strip.lanes
    y_lo, y_hi = lanes[0][0], lanes[-1][0]
    span = y_hi - y_lo
    lo, hi = ext[0] * res, ext[1] * res
    n = len(lanes)
    room = (n - 1) * max(spread, width) - span  # how far the same lanes can spread
    if lo + hi > room:
        if room <= 1e-9:
            return
        lo, hi = lo * room / (lo + hi), hi * room / (lo + hi)
    ys = np.linspace(y_lo - lo, y_hi + hi, n) if n > 1 else np.array([y_lo - lo])
    out: list[tuple[float, float, float]] = []
    for y in ys:
        r = min(max(math.floor((y - oy) / res), 0), h - 1)
        near = min(lanes, key=lambda lane: abs(lane[0] - y))
        a, b = round((near[1] - ox) / res - 0.5), round((near[2] - ox) / res - 0.5)
        over = [(c0, c1) for c0, c1 in _runs(stand[r]) if c0 <= b and a <= c1]
        if not over:
            return  # cannot happen: every row between the end rows continues the lanes
        c0, c1 = max(over, key=lambda run: min(run[1], b) - max(run[0], a))
        out.append((float(y), ox + (c0 + 0.5) * res, ox + (c1 + 0.5) * res))
    strip.lanes = out


def swept_cells(fm: FloorMap, way: Sequence[Point], radius: float) -> BoolGrid:
    """Map cells whose centre lies within ``radius`` of the polyline ``way``."""
    out = np.zeros(fm.shape, dtype=bool)
    res = fm.resolution
    h, w = fm.shape
    pts = list(way)
    if len(pts) == 1:
        pts = pts * 2
    for (ax, ay), (bx, by) in itertools.pairwise(pts):
        c0 = max(0, int((min(ax, bx) - radius - fm.origin[0]) // res))
        c1 = min(w, int((max(ax, bx) + radius - fm.origin[0]) // res) + 1)
        r0 = max(0, int((min(ay, by) - radius - fm.origin[1]) // res))
        r1 = min(h, int((max(ay, by) + radius - fm.origin[1]) // res) + 1)
        if r0 >= r1 or c0 >= c1:
            continue
        xs = fm.origin[0] + (np.arange(c0, c1) + 0.5) * res
        ys = fm.origin[1] + (np.arange(r0, r1) + 0.5) * res
        px, py = xs[None, :] - ax, ys[:, None] - ay
        dx, dy = bx - ax, by - ay
        ll = dx * dx + dy * dy
        t = np.clip((px * dx + py * dy) / ll, 0.0, 1.0) if ll > 0 else np.zeros((r1 - r0, c1 - c0))
        d2 = (px - t * dx) ** 2 + (py - t * dy) ** 2
        out[r0:r1, c0:c1] |= d2 <= radius * radius
    return out


def plan_sweep(
    fm: FloorMap,
    area: Area,
    start: Point,
    *,
    tool_width_m: float | None = None,
    axis: int | None = None,
    robot: str = "",
) -> CoveragePlan:
    """A boustrophedon floor-coverage route over the area: the standable part of the area is cut into
    cells (``_decompose``) with lanes along x (``axis=0``) or y (``axis=1``) one tool width apart;
    each cell is swept lane by lane, turning at alternate ends, its lanes spread to its own floor
    (``_edge_lanes``); cells are taken in the order whose ways between them are shortest, each entered
    at any of its four corners (``_strip_order``), joined by shortest stand paths.
    Lanes along ``axis`` (``None``: both axes are tried), each with the lane grid spaced over all
    rows and without the narrow rows at its ends (``NUB_M``); the route kept has the least path plus
    ``SWEEP_MISS_WEIGHT`` times the ideal path for the floor it leaves.
    ``predicted.coverage``: share of the floor the tool can reach at all (``swept_m2``: target cells
    within half a tool width of a stand cell) that the route passes within half a tool width of;
    ``path_m`` counts the route from the first lane on (the drive there is in ``travel_s``), and
    ``ideal_path_m`` is ``swept_m2 / tool width``."""
    width = tool_width_m if tool_width_m is not None else fm.config.tool_width_m
    if not (math.isfinite(width) and width > 0):
        raise ValueError(f"sweep: tool width must be a finite number > 0, got {width!r}")
    s_cell = _start_cell(fm, start)
    fm.focus(area.stand, s_cell)
    reach = np.isfinite(fm.geodesic(s_cell)) & area.stand
    if not reach.any():
        raise ValueError("sweep: the robot cannot reach the area from its start")
    # Swept floor: the target cells the tool can reach at all (within half its width of a stand cell's
    # centre, where lanes run).
    rad = width / 2.0
    can = _near_centres(fm, reach, rad) & area.target
    best: tuple[float, list[tuple[Point, str]], BoolGrid] | None = None
    for ax in [axis] if axis is not None else [0, 1]:
        grid = reach if ax == 0 else reach.T
        full = _lane_rows(grid, fm.plan_resolution, 0.0)
        for nub_m in (0.0, NUB_M) if NUB_M > 0 else (0.0,):
            if nub_m > 0 and _lane_rows(grid, fm.plan_resolution, nub_m) == full:
                continue  # no narrow end rows: the same route again
            route, swept = _sweep_candidate(fm, reach, s_cell, width, ax, nub_m, can, rad)
            path = sum(math.dist(p, q) for (p, _), (q, _) in itertools.pairwise(route))
            score = path + SWEEP_MISS_WEIGHT * float((can & ~swept).sum()) * fm.cell_area / width
            if best is None or score < best[0] - 1e-9:
                best = (score, route, swept)
    assert best is not None
    _, route, swept = best
    s0 = (float(start[0]), float(start[1]))
    head = fm.route(s0, route[0][0])
    nodes = [PlanNode("n0", 0, s0[0], s0[1], 0.0, False)]
    edges: list[PlanEdge] = []
    approach = sum(math.dist(a, b) for a, b in itertools.pairwise(head))
    path_m = 0.0
    for i, (p, kind) in enumerate(route, start=1):
        wp = tuple(head) if i == 1 else (route[i - 2][0], p)
        seg = approach if i == 1 else math.dist(*wp)
        path_m += 0.0 if i == 1 else seg
        edges.append(PlanEdge(f"e{i}", 2 * i - 1, f"n{i - 1}", f"n{i}", wp, seg, False, "transit" if i == 1 else kind))
        nodes.append(PlanNode(f"n{i}", 2 * i, p[0], p[1], 0.0, False))
    swept_m2 = float(can.sum()) * fm.cell_area
    travel = (approach + path_m) / fm.config.speed_mps
    pred = Prediction(
        coverage=float(swept.sum()) / max(1, int(can.sum())),
        dwell_s=0.0,
        travel_s=travel,
        total_s=travel,
        path_m=path_m,
        area_m2=area.area_m2,
        ideal_path_m=swept_m2 / width,
        swept_m2=swept_m2,
    )
    return CoveragePlan("sweep", tuple(nodes), tuple(edges), 0.0, pred, robot)


def _sweep_candidate(
    fm: FloorMap, reach: BoolGrid, s_cell: Cell, width: float, ax: int, nub_m: float, can: BoolGrid, rad: float
) -> tuple[list[tuple[Point, str]], BoolGrid]:
    """One sweep route over ``reach`` (lanes along ``ax``, the lane grid without the narrow rows at
    its ends when ``nub_m`` > 0, ``NUB_M``), lane ends, the edge pass and fill lanes included, and
    the cells of ``can`` it sweeps. The edge pass (a band of bits along walls) keeps every row."""
    end = fm.config.lane_end_clearance_m
    route = _lane_ends_short(_distinct(_sweep_route(fm, reach, s_cell, width, ax, nub_m)), end)
    if end > 0:
        # The lanes stop short of the walls they run into: the floor there is swept by lanes across
        # them (along those walls, where the guard does not stop the robot), as a robot vacuum's
        # edge pass does.
        missed = can & ~swept_cells(fm, [p for p, _ in route], rad)
        if missed.sum() * fm.cell_area >= 0.1:
            edge = _stand_near(fm, missed, rad) & reach
            last = fm.escape(route[-1][0])
            if edge.any() and last is not None:
                more = _lane_ends_short(_distinct(_sweep_route(fm, edge, last, width, 1 - ax)), end)
                link = fm.route(route[-1][0], more[0][0])[1:-1]
                route = _distinct([*route, *((q, "transit") for q in link), (more[0][0], "transit"), *more[1:]])
    route = _fill_gaps(fm, route, can, reach, rad)
    return route, swept_cells(fm, [p for p, _ in route], rad) & can


SWEEP_MISS_WEIGHT = 6.0
"""``plan_sweep`` keeps the candidate route with the least path plus this many times the path an
ideal sweep would need for the floor it leaves (m² / tool width): leaving floor is what the sweep
is for, not saving way (measured, docs/payload.md "Sweeps that choose by what they leave")."""


FILL_MIN_M2 = 0.05
"""A strip the lanes missed is swept by a lane of its own when it is at least this big..."""
FILL_MIN_YIELD = 0.1
"""... and that lane, with the way to it and back, sweeps at least this much of it per metre added
(m²/m; a lane in the open sweeps 0.31: a third of that)."""


def _fill_gaps(
    fm: FloorMap, route: list[tuple[Point, str]], can: BoolGrid, reach: BoolGrid, rad: float
) -> list[tuple[Point, str]]:
    """``route`` with a lane inserted for each strip of sweepable floor its lanes miss (lanes are
    spaced over the whole area's extent, so where a part of it ends between two lanes, the floor
    beyond the last lane there is left; a lane is not run where the stand floor is narrower than a
    plan cell): of the rows (or columns, along the strip's longer side) of stand cells that can
    sweep it, the run that sweeps most of it, put between two lanes where it adds the least way
    (cheapest insertion, by straight distances), or after the route's last point, when it is worth
    it (``FILL_MIN_M2``, ``FILL_MIN_YIELD``)."""
    if len(route) < 2:
        return route
    missed = can & ~swept_cells(fm, [p for p, _ in route], rad)
    area = fm.cell_area
    lanes: list[tuple[float, Point, Point]] = []
    for comp in components(missed):
        if len(comp) * area < FILL_MIN_M2:
            continue
        strip = np.zeros(missed.shape, dtype=bool)
        strip[comp[:, 0], comp[:, 1]] = True
        stand = _stand_near(fm, strip, rad) & reach
        if not stand.any():
            continue
        # Along the strip's longer side: each row (or column) of the stand cells that sweep it
        # offers its runs as lanes; the one that sweeps most of the strip is taken.
        rows, cols = comp[:, 0], comp[:, 1]
        along_x = int(cols.max() - cols.min()) >= int(rows.max() - rows.min())
        grid = stand if along_x else stand.T
        best_lane: tuple[float, Point, Point] | None = None
        for k in np.flatnonzero(grid.any(axis=1)):
            for c0, c1 in _runs(grid[k]):
                ends = [(int(k), c0), (int(k), c1)] if along_x else [(c0, int(k)), (c1, int(k))]
                a, b = fm.plan_centre(ends[0]), fm.plan_centre(ends[1])
                gain = float((swept_cells(fm, [a, b], rad) & strip).sum()) * area
                if best_lane is None or gain > best_lane[0]:
                    best_lane = (gain, a, b)
        if best_lane is None or math.dist(best_lane[1], best_lane[2]) < 1e-9:
            continue
        gain, a, b = best_lane
        lanes.append((gain, a, b))
    out = list(route)
    for gain, a, b in sorted(lanes, key=lambda g: -g[0]):
        best: tuple[float, int, Point, Point] | None = None
        for i in range(len(out)):
            p = out[i][0]
            last = i == len(out) - 1  # after the route's end: no way back to add
            if not last and out[i + 1][1] == "lane":  # not into a lane: between lanes, or on the way
                continue
            for u, v in ((a, b), (b, a)):
                cost = math.dist(p, u) + math.dist(u, v)
                if not last:
                    q = out[i + 1][0]
                    cost += math.dist(v, q) - math.dist(p, q)
                if best is None or cost < best[0]:
                    best = (cost, i, u, v)
        if best is None or gain < FILL_MIN_M2 or gain / max(best[0], 1e-9) < FILL_MIN_YIELD:
            continue
        _, i, u, v = best
        into = [(w, "transit") for w in fm.route(out[i][0], u)[1:]]
        back = [(w, "transit") for w in fm.route(v, out[i + 1][0])[1:]] if i + 1 < len(out) else []
        out = [*out[: i + 1], *into, (v, "lane"), *back, *out[i + 2 :]]
    return _distinct(out)


def _distinct(way: Sequence[tuple[Point, str]]) -> list[tuple[Point, str]]:
    """``way`` without a point that repeats the one before it."""
    out = [way[0]]
    for p, kind in way[1:]:
        if math.dist(p, out[-1][0]) > 1e-9:
            out.append((p, kind))
    return out


def _lane_ends_short(route: list[tuple[Point, str]], end: float) -> list[tuple[Point, str]]:
    """Each lane of ``route`` ended ``end`` short of where it meets a wall (the guard's stopping room)."""
    if end <= 0:
        return route
    out = list(route)
    for i in range(1, len(out)):
        (a, _), (b, kind) = out[i - 1], out[i]
        length = math.dist(a, b)
        if kind != "lane" or length <= 2 * end + 0.1:
            continue
        ux, uy = (b[0] - a[0]) / length, (b[1] - a[1]) / length
        out[i - 1] = ((a[0] + ux * end, a[1] + uy * end), out[i - 1][1])
        out[i] = ((b[0] - ux * end, b[1] - uy * end), kind)
    return out


def _stand_near(fm: FloorMap, cells: BoolGrid, radius: float) -> BoolGrid:
    """Plan cells within ``radius`` of one of the map ``cells`` (where the tool sweeps them from)."""
    grown = _dilate(cells, radius / fm.resolution)
    f = fm.factor
    ph, pw = fm.stand.shape
    h, w = fm.shape
    out = np.zeros((ph, pw), dtype=bool)
    for dr in range(f):
        for dc in range(f):
            rr = np.minimum(np.arange(ph) * f + dr, h - 1)
            cc = np.minimum(np.arange(pw) * f + dc, w - 1)
            out |= grown[rr][:, cc]
    return out


def _near_centres(fm: FloorMap, cells: BoolGrid, radius: float) -> BoolGrid:
    """Map cells whose centre lies within ``radius`` of the centre of one of the plan ``cells``."""
    h, w = fm.shape
    ph, pw = cells.shape
    res, pres = fm.resolution, fm.plan_resolution
    cx = (np.arange(w) + 0.5) * res  # relative to the origin, shared by both grids
    cy = (np.arange(h) + 0.5) * res
    pc = np.floor(cx / pres).astype(np.intp)
    pr = np.floor(cy / pres).astype(np.intp)
    n = math.ceil(radius / pres) + 1
    out = np.zeros((h, w), dtype=bool)
    for dr in range(-n, n + 1):
        rr = pr + dr
        okr = (rr >= 0) & (rr < ph)
        dy = cy - (rr + 0.5) * pres
        for dc in range(-n, n + 1):
            cc = pc + dc
            okc = (cc >= 0) & (cc < pw)
            dx = cx - (cc + 0.5) * pres
            near = (dy[:, None] ** 2 + dx[None, :] ** 2) <= radius * radius + 1e-12
            near &= okr[:, None] & okc[None, :]
            if not near.any():
                continue
            hit = np.zeros((h, w), dtype=bool)
            hit[np.ix_(okr, okc)] = cells[np.ix_(rr[okr], cc[okc])]
            out |= near & hit
    return out


LANE_SPREAD = 0.5
"""A strip's lanes may spread to this share of the way from the sweep's spacing to the tool's own
width (``_edge_lanes``): half of the overlap is kept for the robot's centimetres off its lane
(1.0 measured offline on the fifteen sweeps' maps at seeds 16-18, when the shortest route was
kept: the kitchen's seed-18 plan swept 90.2 % of the true floor instead of 94.2 %)."""


def _sweep_route(
    fm: FloorMap, reach: BoolGrid, s_cell: Cell, width: float, axis: int, nub_m: float = 0.0
) -> list[tuple[Point, str]]:
    """Waypoints (and the kind of the edge that leads to each) of the boustrophedon over ``reach``,
    lanes ``width`` apart; a strip's lanes may spread to half way between that and the tool's own
    width (``_edge_lanes``: the overlap kept for the robot's centimetres off its lane halves)."""
    res = fm.plan_resolution
    ox, oy = fm.origin
    spread = width + max(0.0, fm.config.tool_width_m - width) * LANE_SPREAD
    if axis == 0:
        strips = _decompose(reach, res, ox, oy, width, spread, nub_m)

        def xy(u: float, v: float) -> Point:
            return (u, v)
    else:
        strips = _decompose(reach.T, res, oy, ox, width, spread, nub_m)

        def xy(u: float, v: float) -> Point:
            return (v, u)

    # Within a strip, lane (y, x0, x1) runs from x0 to x1 or back.
    way: list[tuple[Point, str]] = []
    cur_pt = fm.plan_centre(s_cell)
    for k, top, right in _strip_order(fm, strips, s_cell, xy):
        lanes = strips[k].lanes[::-1] if top else strips[k].lanes
        for i, (y, x0, x1) in enumerate(lanes):
            a, b = (x1, x0) if right else (x0, x1)
            pa, pb = xy(a, y), xy(b, y)
            kind = "transit" if i == 0 else "connect"
            if way:
                way.extend((q, kind) for q in fm.route(cur_pt, pa)[1:-1])
            way.append((pa, kind))
            way.append((pb, "lane"))
            cur_pt = pb
            right = not right
    return way


STRIP_ORDER_EXACT = 12
"""Up to this many strips, the order that sweeps them is the shortest (by the stand paths between
them) of all; beyond, it is built nearest first and then improved by moving strips (or-opt)."""


def _strip_order(
    fm: FloorMap, strips: list[_Strip], s_cell: Cell, xy: Callable[[float, float], Point]
) -> list[tuple[int, bool, bool]]:
    """The order to sweep ``strips`` in from ``s_cell``: (strip, from its top lane, from the right end
    of that lane) each, so that the way between strips (the stand path from where one ends to where
    the next begins) is short. A strip is entered at one of its four corners and left at the corner
    its lanes' count gives."""
    n = len(strips)
    if n == 0:
        return []

    def corner(k: int, top: bool, right: bool) -> Cell:
        y, x0, x1 = strips[k].lanes[-1] if top else strips[k].lanes[0]
        return fm.plan_cell(xy(x1 if right else x0, y))

    def leaves(k: int, top: bool, right: bool) -> tuple[bool, bool]:
        """Where a strip entered at (top, right) is left: the far lane, at the end its count gives."""
        return not top, right if len(strips[k].lanes) % 2 == 0 else not right

    entries = [(k, top, right) for k in range(n) for top in (False, True) for right in (False, True)]
    # Distance from the start and from each strip's exit corner to each entry corner.
    sources = {s_cell, *(corner(k, *leaves(k, t, r)) for k, t, r in entries)}
    fields = {src: fm.geodesic(src) for src in sources}

    def dist(src: Cell, e: tuple[int, bool, bool]) -> float:
        d = float(fields[src][corner(*e)])
        return d if math.isfinite(d) else math.inf

    def out_of(e: tuple[int, bool, bool]) -> Cell:
        return corner(e[0], *leaves(*e))

    def length(order: list[tuple[int, bool, bool]]) -> float:
        total, at = 0.0, s_cell
        for e in order:
            total += dist(at, e)
            at = out_of(e)
        return total

    if n <= STRIP_ORDER_EXACT:
        # Held-Karp over (strips swept, the last one and how it was entered), a mask at a time:
        # cost[mask, e] is the shortest way that sweeps the strips in mask and ends with entry e.
        m = len(entries)
        step = np.array([[dist(out_of(e), f) for f in entries] for e in entries])
        first = np.array([dist(s_cell, e) for e in entries])
        strip_of = np.array([e[0] for e in entries])
        cost = np.full((1 << n, m), np.inf)
        back = np.full((1 << n, m), -1, dtype=np.intp)
        for q in range(m):
            cost[1 << int(strip_of[q]), q] = first[q]
        for mask in range(1, 1 << n):
            row = cost[mask]
            if not np.isfinite(row).any():
                continue
            via = row[:, None] + step  # (last entry, next entry)
            arg = np.argmin(via, axis=0)
            got = via[arg, np.arange(m)]
            for q in np.flatnonzero(np.isfinite(got) & ((mask >> strip_of) & 1 == 0)).tolist():
                nm = mask | 1 << int(strip_of[q])
                if got[q] < cost[nm, q] - 1e-12:
                    cost[nm, q] = got[q]
                    back[nm, q] = arg[q]
        full = (1 << n) - 1
        if np.isfinite(cost[full]).any():
            q = int(np.argmin(cost[full]))
            mask = full
            order: list[tuple[int, bool, bool]] = []
            while q >= 0:
                order.append(entries[q])
                prev = int(back[mask, q])
                mask &= ~(1 << entries[q][0])
                q = prev
            return order[::-1]
    # Nearest first, then or-opt: move a strip (entered either way) to where it lengthens least.
    order = []
    left = set(range(n))
    at = s_cell
    while left:
        cands = [(dist(at, e), e) for e in entries if e[0] in left]
        d, e = min(cands)
        if not math.isfinite(d):
            break  # the rest is out of reach (cannot happen: the strips are cut from reachable cells)
        order.append(e)
        left.discard(e[0])
        at = out_of(e)
    improved = True
    while improved:
        improved = False
        now = length(order)
        for i in range(len(order)):
            rest = order[:i] + order[i + 1 :]
            k = order[i][0]
            for j in range(len(rest) + 1):
                for t in (False, True):
                    for r in (False, True):
                        trial = [*rest[:j], (k, t, r), *rest[j:]]
                        if length(trial) < now - 1e-9:
                            order, now, improved = trial, length(trial), True
    return order
