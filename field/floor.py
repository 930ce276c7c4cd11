"""A minimal world for one simulated board: an empty floor with walls you can place and cliff regions.

The full multi-robot field (floor plans, lidar ray casting) builds on this; the board only needs
what its own sensors see: the distance ahead (ultrasonic), whether the body touches a wall
(bumpers), and whether a cliff sensor hangs over a drop.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from fleetlink.shared.geometry import Point, Segment, point_in_polygon, point_segment_distance

__all__ = ["Floor", "Point", "Rect", "Segment", "cone_range", "ray_cast"]


@dataclass(frozen=True, slots=True)
class Rect:
    x0: float
    y0: float
    x1: float
    y1: float

    def contains(self, x: float, y: float) -> bool:
        return self.x0 <= x <= self.x1 and self.y0 <= y <= self.y1


@dataclass(slots=True)
class Floor:
    walls: list[Segment] = field(default_factory=list)
    cliffs: list[Rect] = field(default_factory=list)
    cliff_polygons: list[tuple[Point, ...]] = field(default_factory=list)  # e.g. a stairwell (field.plans)

    @classmethod
    def box(cls, width: float, height: float) -> Floor:
        """A closed rectangular room from (0, 0) to (width, height)."""
        w, h = width, height
        return cls(walls=[(0, 0, w, 0), (w, 0, w, h), (w, h, 0, h), (0, h, 0, 0)])

    def add_wall(self, x1: float, y1: float, x2: float, y2: float) -> None:
        self.walls.append((x1, y1, x2, y2))

    def ray(self, x: float, y: float, angle: float, max_range: float) -> float:
        """Distance to the nearest wall along a ray, or ``inf`` if none within ``max_range``."""
        return ray_cast(self.walls, x, y, angle, max_range)

    def rays(self, x: float, y: float, angles: Sequence[float], max_range: float) -> list[float]:
        """Several rays from one point (a sensor cone); the multi-robot world vectorises this."""
        return [ray_cast(self.walls, x, y, a, max_range) for a in angles]

    def clearance(self, x: float, y: float) -> float:
        """Distance from a point to the nearest wall."""
        return min((point_segment_distance(x, y, s) for s in self.walls), default=math.inf)

    def over_cliff(self, x: float, y: float) -> bool:
        return any(r.contains(x, y) for r in self.cliffs) or any(point_in_polygon(x, y, p) for p in self.cliff_polygons)


def ray_cast(walls: Iterable[Segment], x: float, y: float, angle: float, max_range: float) -> float:
    dx, dy = math.cos(angle), math.sin(angle)
    best = math.inf
    for x1, y1, x2, y2 in walls:
        ex, ey = x2 - x1, y2 - y1
        denom = dx * ey - dy * ex
        if abs(denom) < 1e-12:
            continue
        wx, wy = x1 - x, y1 - y
        t = (wx * ey - wy * ex) / denom  # along the ray
        u = (wx * dy - wy * dx) / denom  # along the wall
        if 0.0 <= u <= 1.0 and 0.0 <= t < best:
            best = t
    return best if best <= max_range else math.inf


def cone_range(
    walls: Sequence[Segment], x: float, y: float, heading: float, half_angle: float, max_range: float, rays: int = 9
) -> float:
    """Nearest echo inside a sensor cone (an ultrasonic sensor reports the nearest reflector)."""
    if rays < 2:
        return ray_cast(walls, x, y, heading, max_range)
    step = 2 * half_angle / (rays - 1)
    return min(ray_cast(walls, x, y, heading - half_angle + i * step, max_range) for i in range(rays))
