"""The multi-robot world: robots' bodies on a floor plan, moved by their simulated boards, in lockstep.

Each robot's ``SimulatedBoard`` runs its firmware (wheel PID, motor lag, encoders, battery) and
moves its body through a ``RobotView``: the floor's walls and obstacles plus every other robot,
so robots collide with walls and with each other, and their ultrasonic sensors see both. All
boards advance in the same control sub-steps, so the outcome depends only on the seed and the
commands. Pure: time comes in as an argument; no threads, no sockets.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from fleetlink.field.board import BoardConfig, SimulatedBoard
from fleetlink.field.raycast import Raycaster
from fleetlink.shared.geometry import point_segment_distance

__all__ = ["POSE_HISTORY_S", "Pose", "RobotView", "World", "WorldRobot"]

Pose = tuple[float, float, float]

POSE_HISTORY_S = 1.0
"""How far back ``WorldRobot.pose_at`` reaches (a lidar turn's start is at most a turn or two back)."""

NEIGHBOUR_REFRESH = 0.05  # s between neighbour-list refreshes
NEIGHBOUR_MARGIN = 0.5  # m beyond touching, so fast robots cannot cross it between refreshes
SHORT_RANGE = 2.0  # m: rays up to this long are cast in Python against nearby geometry
SENSING_MARGIN = SHORT_RANGE + 0.5  # m: robots a short-range sensor could see before the next refresh
Segment = tuple[float, float, float, float]


class SegmentGrid:
    """Uniform grid over segments: which segments pass near a point, without scanning them all."""

    def __init__(self, segments: np.ndarray, cell: float = 1.0) -> None:
        self.cell = cell
        self.segments: list[Segment] = [tuple(map(float, s)) for s in np.asarray(segments, dtype=float).reshape(-1, 4)]  # type: ignore[misc]
        self._cells: dict[tuple[int, int], list[int]] = {}
        for k, (x1, y1, x2, y2) in enumerate(self.segments):
            length = math.hypot(x2 - x1, y2 - y1)
            steps = max(1, math.ceil(length / (cell / 2)))
            seen: set[tuple[int, int]] = set()
            for i in range(steps + 1):
                t = i / steps
                key = (math.floor((x1 + t * (x2 - x1)) / cell), math.floor((y1 + t * (y2 - y1)) / cell))
                if key not in seen:
                    seen.add(key)
                    self._cells.setdefault(key, []).append(k)

        # For each cell, the segments of its 3x3 neighbourhood, computed once on demand.
        self._near: dict[tuple[int, int], tuple[int, ...]] = {}
        self._near_radius: dict[tuple[int, int, int], tuple[int, ...]] = {}

    def near(self, x: float, y: float) -> tuple[int, ...]:
        """Segments passing through the 3x3 cells around (x, y): all within ``cell`` of it, and more."""
        key = (math.floor(x / self.cell), math.floor(y / self.cell))
        hit = self._near.get(key)
        if hit is None:
            cx, cy = key
            out: set[int] = set()
            for i in (cx - 1, cx, cx + 1):
                for j in (cy - 1, cy, cy + 1):
                    out.update(self._cells.get((i, j), ()))
            hit = self._near[key] = tuple(sorted(out))
        return hit

    def near_radius(self, x: float, y: float, radius: float) -> tuple[int, ...]:
        """Segments that may come within ``radius`` of (x, y) (a superset)."""
        if radius <= self.cell:
            return self.near(x, y)
        reach = math.ceil(radius / self.cell)
        key = (math.floor(x / self.cell), math.floor(y / self.cell), reach)
        hit = self._near_radius.get(key)
        if hit is None:
            cx, cy, _ = key
            out: set[int] = set()
            for i in range(cx - reach, cx + reach + 1):
                for j in range(cy - reach, cy + reach + 1):
                    out.update(self._cells.get((i, j), ()))
            hit = self._near_radius[key] = tuple(sorted(out))
        return hit

    def clearance(self, x: float, y: float) -> float:
        """Distance to the nearest segment, exact up to ``cell``; ``cell`` or more otherwise."""
        best = math.inf
        segs = self.segments
        for k in self.near(x, y):
            d = point_segment_distance(x, y, segs[k])
            if d < best:
                best = d
        return best


@dataclass(slots=True)
class WorldRobot:
    name: str
    index: int
    board: SimulatedBoard
    view: RobotView
    extras: dict[str, object] = field(default_factory=dict)  # lidar device etc., owned by the field

    @property
    def pose(self) -> Pose:
        st = self.board.state
        return st.x, st.y, st.theta

    radius: float = field(init=False)
    _past: deque[tuple[float, float, float, float]] = field(init=False)
    """(t, x, y, theta) after each physics step of the last ``POSE_HISTORY_S``."""

    def __post_init__(self) -> None:
        self.radius = self.board.config.radius
        self._past = deque()

    def pose_at(self, t: float) -> Pose:
        """Where the robot was at ``t``: between the physics' steps of the last ``POSE_HISTORY_S``,
        linearly; its pose now for a later ``t``, the oldest kept for an earlier one. A lidar turn
        begins at its own time, which the field learns only when the device is next stepped (when its
        reader polls, in lockstep: up to a quarter turn later); cast from the pose then, a turning
        robot's turn is drawn degrees off the pose its agent dates it at."""
        past = self._past
        if not past or t >= past[-1][0]:
            return self.pose
        later = past[-1]
        for earlier in reversed(past):
            if earlier[0] <= t:
                span = later[0] - earlier[0]
                f = (t - earlier[0]) / span if span > 0.0 else 1.0
                turn = math.remainder(later[3] - earlier[3], math.tau)
                return (
                    earlier[1] + f * (later[1] - earlier[1]),
                    earlier[2] + f * (later[2] - earlier[2]),
                    earlier[3] + f * turn,
                )
            later = earlier
        return later[1], later[2], later[3]

    def _remember(self, t: float) -> None:
        st = self.board.state
        past = self._past
        past.append((t, st.x, st.y, st.theta))
        while past[0][0] < t - POSE_HISTORY_S:
            past.popleft()


class RobotView:
    """One robot's surroundings as its board sees them: the floor plus every other robot."""

    def __init__(self, world: World, index: int) -> None:
        self.world = world
        self.index = index

    @property
    def walls(self) -> list[Segment]:
        return self.world.grid.segments

    def clearance(self, x: float, y: float) -> float:
        w = self.world
        best = w.grid.clearance(x, y)
        for j in w.neighbours[self.index]:
            other = w.robots[j].board
            d = math.hypot(x - other.state.x, y - other.state.y) - other.config.radius
            if d < best:
                best = d
        return best

    def ray(self, x: float, y: float, angle: float, max_range: float) -> float:
        return self.rays(x, y, [angle], max_range)[0]

    def rays(self, x: float, y: float, angles: Sequence[float], max_range: float) -> list[float]:
        w = self.world
        if max_range <= SHORT_RANGE:
            # Short sensors (ultrasonic, bump geometry): a few nearby segments and robots in plain
            # Python beat numpy's per-call overhead by a wide margin.
            segs = [w.grid.segments[k] for k in w.grid.near_radius(x, y, max_range)]
            circles = []
            lo, hi = min(angles), max(angles)
            mid, half = (lo + hi) / 2, (hi - lo) / 2
            for j in w.sensing[self.index]:
                st = w.robots[j].board.state
                r = w.robots[j].radius
                d = math.hypot(st.x - x, st.y - y)
                # Only robots within reach and inside the fan of rays can be hit.
                if d - r > max_range:
                    continue
                bearing = math.atan2(st.y - y, st.x - x)
                if d > r and abs(math.remainder(bearing - mid, math.tau)) > half + math.asin(r / d):
                    continue
                circles.append((st.x, st.y, r))
            return [_short_ray(segs, circles, x, y, a, max_range) for a in angles]
        bodies = w.other_bodies(self.index, x, y, max_range)
        hits = w.raycaster.cast(x, y, np.asarray(angles, dtype=float), max_range, bodies)
        return [float(v) for v in hits]

    def over_cliff(self, x: float, y: float) -> bool:
        return self.world.is_cliff(x, y)


def _short_ray(
    segs: list[Segment], circles: list[tuple[float, float, float]], x: float, y: float, angle: float, max_range: float
) -> float:
    """One ray against a handful of segments and circles; ``inf`` beyond ``max_range``."""
    dx, dy = math.cos(angle), math.sin(angle)
    best = max_range
    hit = False
    for x1, y1, x2, y2 in segs:
        ex, ey = x2 - x1, y2 - y1
        denom = dx * ey - dy * ex
        if denom == 0.0:
            continue
        wx, wy = x1 - x, y1 - y
        t = (wx * ey - wy * ex) / denom
        if 0.0 <= t <= best:
            u = (wx * dy - wy * dx) / denom
            if 0.0 <= u <= 1.0:
                best, hit = t, True
    for cx, cy, r in circles:
        fx, fy = x - cx, y - cy
        b = fx * dx + fy * dy
        c = fx * fx + fy * fy - r * r
        disc = b * b - c
        if disc >= 0.0:
            t = -b - math.sqrt(disc)
            if 0.0 <= t <= best:
                best, hit = t, True
    return best if hit else math.inf


class World:
    """Robots on a plan. ``step(now)`` advances every board to ``now`` in shared control sub-steps."""

    def __init__(
        self,
        segments: np.ndarray,
        is_cliff: Callable[[float, float], bool] | None = None,
        control_period: float = 0.005,
        start: float = 0.0,
    ) -> None:
        self.control_period = control_period
        self.is_cliff: Callable[[float, float], bool] = is_cliff or (lambda x, y: False)
        self.robots: list[WorldRobot] = []
        self.by_name: dict[str, WorldRobot] = {}
        self.neighbours: list[list[int]] = []  # robots near each robot, refreshed every few sub-steps
        self.sensing: list[list[int]] = []  # robots within short-sensor reach of each robot
        self._bodies_array: np.ndarray | None = None  # every robot as (x, y, r), cached per step
        self._bodies_at = -1.0
        self._next_neighbours = start
        self._segments = np.asarray(segments, dtype=float).reshape(-1, 4)
        self.grid = SegmentGrid(self._segments)
        self.raycaster = Raycaster(self._segments)
        self.geometry_version = 0  # bumped by set_segments, so copies elsewhere know to follow
        self.now = start

    # -- building ------------------------------------------------------------------------------

    def add_robot(self, name: str, pose: Pose, config: BoardConfig | None = None) -> WorldRobot:
        if name in self.by_name:
            raise ValueError(f"robot {name!r} is already in the world")
        index = len(self.robots)
        view = RobotView(self, index)
        board = SimulatedBoard(config or BoardConfig(), view, pose=pose, now=self.now)  # type: ignore[arg-type]
        robot = WorldRobot(name, index, board, view)
        robot._remember(self.now)
        self.robots.append(robot)
        self.by_name[name] = robot
        self.neighbours.append([])
        self.sensing.append([])
        self._next_neighbours = self.now  # refresh at the next step
        return robot

    def set_segments(self, segments: np.ndarray) -> None:
        """Change the blocking geometry (a door closes, an obstacle appears)."""
        self._segments = np.asarray(segments, dtype=float).reshape(-1, 4)
        self.grid = SegmentGrid(self._segments)
        self.raycaster.set_segments(self._segments)
        self.geometry_version += 1

    @property
    def segments(self) -> np.ndarray:
        return self._segments

    # -- time ------------------------------------------------------------------------------------

    def step(self, now: float) -> None:
        """Advance all robots to ``now`` together."""
        dt = self.control_period
        while self.now < now - 1e-12:
            t = min(now, self.now + dt)
            if t >= self._next_neighbours:
                self._refresh_bodies()
                self._next_neighbours = t + NEIGHBOUR_REFRESH
            for robot in self.robots:
                robot.board.step(t, max_dt=dt)
                robot._remember(t)
            self.now = t

    def truth(self) -> dict[str, tuple[float, float, float, float, float]]:
        """Ground truth per robot: x, y, theta, v, omega."""
        out = {}
        for r in self.robots:
            st = r.board.state
            out[r.name] = (st.x, st.y, st.theta, st.true_v, st.true_w)
        return out

    # -- geometry shared by the views ------------------------------------------------------------

    @property
    def bodies(self) -> list[tuple[float, float, float]]:
        """Every robot as a circle: x, y, radius."""
        return [(r.board.state.x, r.board.state.y, r.radius) for r in self.robots]

    def other_bodies(
        self, index: int, x: float, y: float, max_range: float, at: float | None = None
    ) -> np.ndarray | None:
        """Other robots as circles (cx, cy, r) within reach of a sensor at (x, y); ``at``: where they
        were then (``WorldRobot.pose_at``), for a lidar turn cast from its start, which the physics may
        have stepped past: the robot casting it is placed where it was, and the others with it."""
        if at is not None and at < self.now:
            then = [(*robot.pose_at(at)[:2], robot.radius) for robot in self.robots]
            arr = np.asarray(then, dtype=float).reshape(-1, 3)
        else:
            if self._bodies_at != self.now or self._bodies_array is None:
                self._bodies_array = np.asarray(self.bodies, dtype=float).reshape(-1, 3)
                self._bodies_at = self.now
            arr = self._bodies_array
        reach = np.hypot(arr[:, 0] - x, arr[:, 1] - y) - arr[:, 2] <= max_range
        reach[index] = False
        return arr[reach] if reach.any() else None

    def _refresh_bodies(self) -> None:
        bodies = self.bodies
        n = len(bodies)
        if n < 2:
            self.neighbours = [[] for _ in range(n)]
            self.sensing = [[] for _ in range(n)]
            return
        # Robots that could touch before the next refresh (0.6 m/s each for NEIGHBOUR_REFRESH s
        # is well inside the margin): a numpy distance matrix, then short lists.
        arr = np.asarray(bodies)
        d = np.hypot(arr[:, None, 0] - arr[None, :, 0], arr[:, None, 1] - arr[None, :, 1])
        reach = arr[:, None, 2] + arr[None, :, 2] + NEIGHBOUR_MARGIN
        others = ~np.eye(n, dtype=bool)
        self.neighbours = [np.flatnonzero(row).tolist() for row in (d < reach) & others]
        self.sensing = [np.flatnonzero(row).tolist() for row in (d < reach + SENSING_MARGIN) & others]
