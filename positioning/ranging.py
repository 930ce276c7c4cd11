"""Two-way-ranging error model: what a UWB tag would measure to each anchor from a true position.

Per range (seeded ``numpy.random.Generator``, one draw of every stream per anchor per call, so a
seed gives the same ranges whatever the outcome of earlier draws):

* dropout: with ``dropout_ratio`` the anchor answers nothing (absent from the result); anchors
  beyond ``max_range_m`` never answer;
* line of sight: true 3D distance + ``antenna_delay_m`` (constant offset of an uncalibrated
  antenna delay) + Gaussian noise of ``sigma_m``;
* non-line-of-sight: always a *positive* bias, exponential with mean ``nlos_mean_bias_m``. A range
  is NLOS at random (``nlos_ratio``), when the tag stands in one of ``nlos_zones`` (polygons), or,
  with ``use_walls``, when the straight path from tag to anchor crosses a wall (2D test: walls run
  floor to ceiling);
* gross outliers: with ``outlier_ratio`` the range jumps by ``outlier_min_m``-``outlier_max_m``,
  either way (never below 0).

Figures from the reference (docs/protocols/uwb.md): LOS about 0.1 m; NLOS a positive bias; gross
outliers of metres; antenna delay 0.1-0.5 m. Pure: no I/O, no clock.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .anchors import Anchor, anchor_array

__all__ = ["NoiseProfile", "Range", "RangingModel"]

FloatArray = npt.NDArray[np.float64]
Polygon = tuple[tuple[float, float], ...]


@dataclass(frozen=True, slots=True)
class NoiseProfile:
    """How ranges go wrong. Ratios are probabilities per range, lengths metres."""

    sigma_m: float = 0.1
    nlos_ratio: float = 0.0
    nlos_mean_bias_m: float = 0.3
    outlier_ratio: float = 0.0
    outlier_min_m: float = 0.5
    outlier_max_m: float = 5.0
    dropout_ratio: float = 0.0
    antenna_delay_m: float = 0.0
    max_range_m: float = 60.0
    nlos_zones: tuple[Polygon, ...] = ()
    use_walls: bool = False

    def __post_init__(self) -> None:
        for name in ("sigma_m", "nlos_mean_bias_m", "outlier_min_m", "outlier_max_m", "max_range_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"NoiseProfile.{name} must be a finite number >= 0, got {v!r}")
        for name in ("nlos_ratio", "outlier_ratio", "dropout_ratio"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise ValueError(f"NoiseProfile.{name} must be a probability in [0, 1], got {v!r}")
        if not math.isfinite(self.antenna_delay_m):
            raise ValueError(f"NoiseProfile.antenna_delay_m must be finite, got {self.antenna_delay_m!r}")
        if self.outlier_min_m > self.outlier_max_m:
            raise ValueError(
                f"NoiseProfile.outlier_min_m ({self.outlier_min_m}) exceeds outlier_max_m ({self.outlier_max_m})"
            )
        for i, zone in enumerate(self.nlos_zones):
            if len(zone) < 3:
                raise ValueError(f"NoiseProfile.nlos_zones[{i}]: a polygon needs at least 3 points")

    @classmethod
    def none(cls) -> NoiseProfile:
        """Exact ranges: for tests of the solver."""
        return cls(sigma_m=0.0)

    @classmethod
    def los(cls) -> NoiseProfile:
        """Line of sight only: Gaussian noise, sigma 0.1 m."""
        return cls(sigma_m=0.1)

    @classmethod
    def realistic(cls) -> NoiseProfile:
        """10 % NLOS ranges (0.3 m mean positive exponential bias), 1 % gross outliers of 0.5-5 m,
        5 % dropouts, on top of 0.1 m line-of-sight noise."""
        return cls(
            sigma_m=0.1,
            nlos_ratio=0.10,
            nlos_mean_bias_m=0.3,
            outlier_ratio=0.01,
            outlier_min_m=0.5,
            outlier_max_m=5.0,
            dropout_ratio=0.05,
        )


@dataclass(frozen=True, slots=True)
class Range:
    """One measured range. ``nlos``/``outlier`` say what the model did (for scoring only:
    a real receiver does not know)."""

    anchor_id: str
    distance_m: float
    nlos: bool = False
    outlier: bool = False


class RangingModel:
    """Simulates the ranges one tag measures. ``walls``: shape (M, 4) segments x1, y1, x2, y2
    (``FloorPlan.segments()``), used when the profile has ``use_walls``."""

    def __init__(
        self,
        anchors: Sequence[Anchor],
        profile: NoiseProfile,
        rng: np.random.Generator,
        walls: npt.ArrayLike | None = None,
    ) -> None:
        self.anchors = tuple(anchors)
        self.profile = profile
        self.rng = rng
        self._ids = [a.id for a in self.anchors]
        self._pos = anchor_array(self.anchors)
        segs = np.zeros((0, 4)) if walls is None else np.asarray(walls, dtype=np.float64).reshape(-1, 4)
        self._walls = segs
        self._zones = [np.asarray(z, dtype=np.float64) for z in profile.nlos_zones]

    def true_distances(self, x: float, y: float, z: float) -> FloatArray:
        d: FloatArray = np.sqrt(((self._pos - np.array([x, y, z])) ** 2).sum(axis=1))
        return d

    def blocked(self, x: float, y: float) -> npt.NDArray[np.bool_]:
        """Per anchor: does the straight 2D path from (x, y) to the anchor cross a wall?"""
        n = len(self.anchors)
        if self._walls.shape[0] == 0 or n == 0:
            return np.zeros(n, dtype=bool)
        px, py = x, y
        qx, qy = self._pos[:, 0:1], self._pos[:, 1:2]  # (n, 1)
        x1, y1, x2, y2 = (self._walls[:, i][None, :] for i in range(4))  # (1, m)
        rx, ry = qx - px, qy - py
        sx, sy = x2 - x1, y2 - y1
        denom = rx * sy - ry * sx
        wx, wy = x1 - px, y1 - py
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (wx * sy - wy * sx) / denom
            u = (wx * ry - wy * rx) / denom
        # Strictly inside both segments: touching a wall's end or grazing it is not blocking.
        hit = (denom != 0) & (t > 1e-9) & (t < 1 - 1e-9) & (u > 1e-9) & (u < 1 - 1e-9)
        out: npt.NDArray[np.bool_] = hit.any(axis=1)
        return out

    def in_zone(self, x: float, y: float) -> bool:
        return any(_inside(x, y, zone) for zone in self._zones)

    def measure(self, x: float, y: float, z: float) -> list[Range]:
        """The ranges the tag at (x, y, z) measures now; dropped anchors are absent."""
        p = self.profile
        n = len(self.anchors)
        if n == 0:
            return []
        u = self.rng.random((4, n))  # dropout, nlos, outlier, outlier sign
        g = self.rng.standard_normal(n)
        e = self.rng.standard_exponential(n)
        m = self.rng.random(n)  # outlier magnitude
        d = self.true_distances(x, y, z)
        nlos = u[1] < p.nlos_ratio
        if p.use_walls:
            nlos |= self.blocked(x, y)
        if self._zones and self.in_zone(x, y):
            nlos[:] = True
        outlier = u[2] < p.outlier_ratio
        r = d + p.antenna_delay_m + p.sigma_m * g + np.where(nlos, p.nlos_mean_bias_m * e, 0.0)
        jump = p.outlier_min_m + (p.outlier_max_m - p.outlier_min_m) * m
        r = np.where(outlier, r + np.where(u[3] < 0.5, -jump, jump), r)
        r = np.maximum(r, 0.0)
        keep = (u[0] >= p.dropout_ratio) & (d <= p.max_range_m)
        ids = self._ids
        return [Range(ids[i], float(r[i]), bool(nlos[i]), bool(outlier[i])) for i in np.flatnonzero(keep).tolist()]


def _inside(x: float, y: float, poly: FloatArray) -> bool:
    """Even-odd rule point-in-polygon."""
    inside = False
    n = poly.shape[0]
    j = n - 1
    for i in range(n):
        xi, yi = float(poly[i, 0]), float(poly[i, 1])
        xj, yj = float(poly[j, 0]), float(poly[j, 1])
        if (yi > y) != (yj > y) and x < (xj - xi) * (y - yi) / (yj - yi) + xi:
            inside = not inside
        j = i
    return inside
