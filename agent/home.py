"""The robot's home: where return home goes (pure).

Three sources, the later ones winning (docs/motion.md, "Home"):

* ``LOCALISED``: where the robot first localised in the site frame (its first accepted UWB fix):
  the door the firefighters deployed it at, with no configuration at all;
* ``DOCK``: a dock pose from the robot's configuration (``[home] x, y, theta_deg``), known from the
  start, so the first localisation does not move it;
* ``OPERATOR``: set by an operator (the ``setHome`` instant action): at the robot's current pose,
  or at given coordinates.

A heading of NaN means "arrive with any heading" (a localised home: the heading estimate at the
first fix is not worth steering to).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fleetlink.shared.messages import MAX_COORDINATE_M, HomeSource

__all__ = ["HomeKeeper", "HomePose"]


@dataclass(frozen=True, slots=True)
class HomePose:
    x: float
    y: float
    theta: float
    """Radians; NaN: any heading."""
    source: HomeSource


class HomeKeeper:
    def __init__(self, dock: tuple[float, float, float] | None = None) -> None:
        self.home: HomePose | None = None
        if dock is not None:
            self.home = _checked(*dock, HomeSource.DOCK)

    def localised(self, x: float, y: float) -> HomePose | None:
        """The robot is localised in the site frame at (x, y): its home, if it has none yet.
        Returns the new home, or None when nothing changed."""
        if self.home is not None or not (math.isfinite(x) and math.isfinite(y)):
            return None
        self.home = _checked(x, y, math.nan, HomeSource.LOCALISED)
        return self.home

    def set(self, x: float, y: float, theta: float = math.nan) -> HomePose:
        """An operator sets the home (ValueError with the reason for a position that cannot be one)."""
        self.home = _checked(x, y, theta, HomeSource.OPERATOR)
        return self.home


def _checked(x: float, y: float, theta: float, source: HomeSource) -> HomePose:
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"home must be finite, got ({x}, {y})")
    if abs(x) > MAX_COORDINATE_M or abs(y) > MAX_COORDINATE_M:
        raise ValueError(f"home ({x:.4g}, {y:.4g}) is outside the site (|x|, |y| <= {MAX_COORDINATE_M:g} m)")
    if math.isinf(theta):
        raise ValueError(f"home heading must be finite or unset, got {theta}")
    if not math.isnan(theta):
        theta = math.atan2(math.sin(theta), math.cos(theta))
    return HomePose(float(x), float(y), theta, source)
