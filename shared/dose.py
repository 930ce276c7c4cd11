"""The UV-C dose model: irradiance on the floor from a robot's lamp, dose accumulated per cell.

Pure numpy; no I/O (the report writers return bytes and text). docs/payload.md, "UV dose model",
states the model, its assumptions and sources; this docstring is the short form. It lives in
``shared/`` because every side uses it: the agent accumulates a robot's dose (agent/dose_layer.py),
the console merges the robots' layers and reports on them (operator/dose.py), the planner plans
with it (agent/coverage.py), and ``fleetlink dose save`` writes the reports.

Units: power W, irradiance W/m², dose J/m² (1 mJ/cm² = 10 J/m², so the common 10 mJ/cm² target is
100 J/m²), lengths m, time s. Grids follow ``shared/map_codec``'s: ``cells[row, col]``, row 0 at
``origin_y`` (the bottom), ``origin`` the outer corner of cell (0, 0), so the centre of cell
(row, col) is ``(origin_x + (col + 0.5) * res, origin_y + (row + 0.5) * res)``.

The lamp (``Lamp``):

* a point source of UV-C power ``P`` at height ``h``: on a floor cell at horizontal distance ``r``
  (3-D distance ``d = sqrt(r² + h²)``, incidence ``cos θ = h / d``)
  ``E = P / (4π d²) · cos θ = P h / (4π d³)``; over the whole (infinite, open) floor it integrates
  to ``P / 2``, the lower half of the sphere;
* or, with ``tube_length_m = L > 0``, a vertical tube from ``z1 = h - L/2`` to ``z2 = h + L/2``
  treated as a thin diffuse (Lambertian) cylinder: each length element radiates ``∝ sin φ`` (φ
  from the tube's axis; a bare tube's ends emit nothing), which integrates in closed form to
  ``E = P r / (2π² L) · (1 / (r² + z1²) - 1 / (r² + z2²))``; also ``P / 2`` over the floor.

Shadows: a floor cell gets light only if the straight segment on the floor from the lamp's floor
position to the cell's centre touches no non-free cell (the closed squares of the robot's map's
walls: grazing a wall cell's corner counts as blocked). This is exact, not sampled: rays sampled
along their length slip between the corner-touching cells of a one-cell diagonal wall and credit
dose behind it, which a certificate must never do. It is computed in two passes (``_shade``),
over the wall cells that touch a free cell only (a segment enters a wall through one of them):
their angular shadow intervals, binned at ~1/2 cell at the reach, decide almost every cell at once
(nearer than every wall cell in its bin: lit; beyond a wall cell that covers its whole bin: dark),
and the few cells left (next to wall faces, along shadow edges) get an exact segment/square test
against the wall cells of their bin. The bins only decide how much work the exact test does, never
the answer (tests/test_dose.py checks it against an exhaustive test of every segment and wall cell).
A non-free cell beside a lit floor cell (by a side) is the wall's face: the wall's surface lies
somewhere inside it, and the floor in front of it is lit; it takes the irradiance at its own
centre. Two robots' maps agree on a wall only to within a cell, and where one robot's map holds
such a cell as floor, the fleet's sum reads the dose the other robot gave it (``_faces``).

Reach: cells farther than ``lamp.reach(cutoff_w_m2)`` (where ``E`` falls below the cutoff), capped
at ``max_radius_m``, get 0: each such cell misses less than ``cutoff_w_m2`` (conservative).

Measured (this 2-core machine, shared with other sessions, load ~1.8; 194 lamp positions in a
walled 24 x 16 m apartment-like floor, 10 m radius, no cutoff): one ``irradiance_window`` call takes
a median 5-8 ms (p90 <= 12 ms) at 0.05 m cells (~125 k floor cells in the disc), 1.1-2.0 ms (p90
<= 2.3 ms) at 0.1 m; ``DoseGrid.add`` (the floor mask sampled onto the window, then the same)
6-7 ms / 2-3 ms. About 2 ms of the 0.05 m figure is the kernel's page faults on fresh 1.3 MB
temporaries (glibc hands them out by mmap; with a larger mmap threshold the median is ~4 ms): a
reused workspace would recover it. ``tests/test_dose.py::test_speed_budget`` holds a loose bound.
"""

from __future__ import annotations

import functools
import math
import struct
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Annotated

import numpy as np
import numpy.typing as npt

from fleetlink.shared.config import Invalid, Setting
from fleetlink.shared.geometry import components

__all__ = [
    "DEFAULT_TARGET_J_M2",
    "J_M2_PER_MJ_CM2",
    "DoseGrid",
    "DoseSummary",
    "FloorMask",
    "Footprint",
    "Lamp",
    "UnderDosed",
    "csv_report",
    "irradiance",
    "irradiance_window",
    "j_m2",
    "pgm_report",
    "png_report",
    "summarise",
]

F64 = npt.NDArray[np.float64]
Bools = npt.NDArray[np.bool_]
Ints = npt.NDArray[np.intp]

J_M2_PER_MJ_CM2 = 10.0
"""1 mJ/cm² = 1e-3 J / 1e-4 m² = 10 J/m²."""
DEFAULT_TARGET_J_M2 = 100.0
"""10 mJ/cm², the usual target for vegetative bacteria on surfaces (docs/payload.md)."""
DEFAULT_CUTOFF_W_M2 = 0.01
"""1 % of 1 W/m², the rate that gives the 100 J/m² target in 100 s: what ``DoseGrid`` ignores."""
DEFAULT_MAX_RADIUS_M = 10.0


def j_m2(mj_per_cm2: float) -> float:
    """A dose in mJ/cm² (how UV-C doses are usually quoted) in J/m² (what this module keeps)."""
    return mj_per_cm2 * J_M2_PER_MJ_CM2


def _finite(name: str, value: float) -> float:
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return v


def _check_target(target_j_m2: float) -> float:
    t = float(target_j_m2)
    if not (math.isfinite(t) and t > 0.0):
        raise ValueError(f"target dose must be a finite number > 0 J/m² (10 mJ/cm² = 100 J/m²), got {target_j_m2!r}")
    return t


# -- the lamp ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Lamp:
    """A robot's UV-C lamp (``[uv]`` of robot.toml, agent/config.py ``UvTable``).

    ``uvc_power_w``: UV-C optical output in W (the datasheet's "UV-C radiation" figure, not the
    electrical watts: a 36 W low-pressure tube gives ~10-15 W of UV-C at 254 nm; derate for age
    and the lamp's temperature). ``height_m``: the lamp's centre above the floor.
    ``tube_length_m``: 0 for a point source, else a vertical line source that long, centred at
    ``height_m``. ``min_distance_m``: the model is not valid nearer the lamp than this (for a point
    source, ~5x the lamp's largest dimension); the floor must be at least this far below it.
    """

    uvc_power_w: Annotated[float, Setting(lo=1e-3, hi=10_000.0, doc="UV-C optical output, W (not electrical W)")]
    height_m: Annotated[float, Setting(lo=0.01, hi=10.0, doc="lamp centre above the floor, m")]
    tube_length_m: Annotated[float, Setting(lo=0.0, hi=5.0, doc="0: point source; else a vertical tube, m")] = 0.0
    min_distance_m: Annotated[float, Setting(lo=0.01, hi=5.0, doc="the model holds beyond this distance, m")] = 0.3

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        for name in ("uvc_power_w", "height_m", "tube_length_m", "min_distance_m"):
            v = getattr(self, name)
            if not isinstance(v, int | float) or not math.isfinite(v):
                raise Invalid(name, f"must be a finite number, got {v!r}")
        if self.uvc_power_w <= 0.0:
            raise Invalid("uvc_power_w", f"must be > 0 W, got {self.uvc_power_w}")
        if self.height_m <= 0.0 or self.min_distance_m <= 0.0 or self.tube_length_m < 0.0:
            raise Invalid("", "height_m and min_distance_m must be > 0 m, tube_length_m >= 0 m")
        low = self.height_m - self.tube_length_m / 2.0
        if low < self.min_distance_m:
            what = "the tube's lower end" if self.tube_length_m > 0 else "the lamp"
            raise Invalid(
                "height_m",
                f"{what} is {low:.3g} m above the floor, nearer than min_distance_m ({self.min_distance_m:.3g} m): "
                "the model is not valid that close",
            )

    @property
    def is_point(self) -> bool:
        return self.tube_length_m == 0.0

    def at(self, r2: F64) -> F64:
        """Irradiance (W/m²) on the open floor at squared horizontal distances ``r2`` (m²)."""
        p, h = self.uvc_power_w, self.height_m
        if self.is_point:
            # In place: a second temporary of this size costs more than the arithmetic (page faults).
            q = r2 + h * h
            out: F64 = np.sqrt(q)
            out *= q
            np.divide(p * h / (4.0 * math.pi), out, out=out)
            return out
        length = self.tube_length_m
        z1, z2 = h - length / 2.0, h + length / 2.0
        line: F64 = (p / (2.0 * math.pi**2 * length)) * np.sqrt(r2) * (1.0 / (r2 + z1 * z1) - 1.0 / (r2 + z2 * z2))
        return line

    def reach(self, cutoff_w_m2: float, max_radius_m: float = math.inf) -> float:
        """The horizontal radius (m) beyond which the open-floor irradiance stays below the cutoff."""
        return _reach(self, float(cutoff_w_m2), float(max_radius_m))


@functools.lru_cache(maxsize=64)
def _reach(lamp: Lamp, cutoff: float, cap: float) -> float:
    if not (cutoff >= 0.0) or math.isnan(cap) or cap < 0.0:
        raise ValueError(f"cutoff must be >= 0 W/m² and the radius cap >= 0 m, got {cutoff}, {cap}")
    if cutoff == 0.0:
        return cap
    p, h = lamp.uvc_power_w, lamp.height_m
    if lamp.is_point:
        d = (p * h / (4.0 * math.pi * cutoff)) ** (1.0 / 3.0)
        return min(cap, math.sqrt(max(0.0, d * d - h * h)))
    # The line source's E(r) rises from 0 under the tube to one peak, then falls: find the last
    # sample at or above the cutoff, then bisect between it and the next one. E <= P h / (pi² r³)
    # (z2² - z1² = 2 h L, and each factor r² + z² >= r²) bounds where to look.
    top = min(cap, 1.01 * float((p * h / (math.pi**2 * cutoff)) ** (1.0 / 3.0)))
    r = np.linspace(0.0, top, 20001)
    e = lamp.at(r * r)
    above = np.nonzero(e >= cutoff)[0]
    if above.size == 0:
        return 0.0
    k = int(above[-1])
    if k == r.size - 1:
        return top
    lo, hi = float(r[k]), float(r[k + 1])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if float(lamp.at(np.array([mid * mid]))[0]) >= cutoff:
            lo = mid
        else:
            hi = mid
    return hi


# -- floor masks ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class FloorMask:
    """Which cells of a grid are floor that light crosses and that takes a dose (True).

    Everything else (walls, obstacles, and unknown cells unless asked) blocks light and gets none,
    but for a wall's lit face (the module's docstring, "Shadows").
    """

    free: Bools
    resolution: float
    origin: tuple[float, float]

    def __post_init__(self) -> None:
        if self.free.ndim != 2 or self.free.dtype != np.bool_:
            raise ValueError(f"free must be a 2-D bool array, got {self.free.dtype} with shape {self.free.shape}")
        if not (math.isfinite(self.resolution) and self.resolution > 0.0):
            raise ValueError(f"resolution must be > 0 m, got {self.resolution}")
        if not all(math.isfinite(v) for v in self.origin):
            raise ValueError(f"origin must be finite, got {self.origin}")

    @classmethod
    def from_occupancy(
        cls,
        cells: npt.ArrayLike,
        resolution: float,
        origin: tuple[float, float],
        *,
        free_max: int = 25,
        unknown_is_free: bool = False,
    ) -> FloorMask:
        """From map cells as they travel (int8: -1 unknown, 0-100): free at or below ``free_max``
        (map_saver's 25, as ``fleetlink map save``); unknown blocks unless ``unknown_is_free``."""
        c = np.asarray(cells)
        free = (c >= 0) & (c <= free_max)
        if unknown_is_free:
            free |= c < 0
        return cls(np.ascontiguousarray(free), float(resolution), (float(origin[0]), float(origin[1])))

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.free.shape
        return int(h), int(w)

    def centres(self) -> tuple[F64, F64]:
        """x of every column's centres, y of every row's."""
        h, w = self.shape
        res = self.resolution
        xs: F64 = self.origin[0] + (np.arange(w, dtype=np.float64) + 0.5) * res
        ys: F64 = self.origin[1] + (np.arange(h, dtype=np.float64) + 0.5) * res
        return xs, ys

    def sample(self, xs: F64, ys: F64) -> Bools:
        """Whether the points on the grid ``ys x xs`` (rows x columns) lie on floor cells of this mask."""
        h, w = self.shape
        out: Bools = np.zeros((ys.size, xs.size), dtype=bool)
        if h == 0 or w == 0:
            return out
        cols = np.floor((xs - self.origin[0]) / self.resolution).astype(np.intp)
        rows = np.floor((ys - self.origin[1]) / self.resolution).astype(np.intp)
        cin = (cols >= 0) & (cols < w)
        rin = (rows >= 0) & (rows < h)
        out[np.ix_(rin, cin)] = self.free[np.ix_(rows[rin], cols[cin])]
        return out


# -- irradiance --------------------------------------------------------------------------------


def irradiance(
    lamp: Lamp,
    x: float,
    y: float,
    free: npt.NDArray[np.bool_],
    resolution: float,
    origin: tuple[float, float],
    *,
    cutoff_w_m2: float = 0.0,
    max_radius_m: float = DEFAULT_MAX_RADIUS_M,
) -> F64:
    """Irradiance (W/m²) on every cell of the grid ``free`` for the lamp above floor point (x, y).

    Non-free cells, cells in a wall's shadow and cells beyond the reach (``Lamp.reach``) get 0.
    See the module docstring; ``irradiance_window`` returns only the window around the lamp.
    """
    out: F64 = np.zeros(free.shape, dtype=np.float64)
    row0, col0, win = irradiance_window(
        lamp, x, y, free, resolution, origin, cutoff_w_m2=cutoff_w_m2, max_radius_m=max_radius_m
    )
    out[row0 : row0 + win.shape[0], col0 : col0 + win.shape[1]] = win
    return out


def irradiance_window(
    lamp: Lamp,
    x: float,
    y: float,
    free: npt.NDArray[np.bool_],
    resolution: float,
    origin: tuple[float, float],
    *,
    cutoff_w_m2: float = 0.0,
    max_radius_m: float = DEFAULT_MAX_RADIUS_M,
) -> tuple[int, int, F64]:
    """``irradiance`` over the window of cells within the reach: (row0, col0, W/m² of the window)."""
    x, y = _finite("lamp x", x), _finite("lamp y", y)
    res = _finite("resolution", resolution)
    if res <= 0.0:
        raise ValueError(f"resolution must be > 0 m, got {resolution}")
    ox, oy = _finite("origin x", origin[0]), _finite("origin y", origin[1])
    if free.ndim != 2:
        raise ValueError(f"free must be a 2-D array, got shape {free.shape}")
    if not (cutoff_w_m2 >= 0.0 and math.isfinite(cutoff_w_m2)):
        raise ValueError(f"cutoff must be a finite number >= 0 W/m², got {cutoff_w_m2!r}")
    if not (max_radius_m >= 0.0 and math.isfinite(max_radius_m)):
        raise ValueError(f"max_radius_m must be a finite number >= 0 m, got {max_radius_m!r}")
    radius = lamp.reach(cutoff_w_m2, max_radius_m)
    h, w = free.shape
    c0 = max(0, math.floor((x - radius - ox) / res))
    c1 = min(w, math.floor((x + radius - ox) / res) + 1)
    r0 = max(0, math.floor((y - radius - oy) / res))
    r1 = min(h, math.floor((y + radius - oy) / res) + 1)
    if c1 <= c0 or r1 <= r0 or radius <= 0.0:
        return 0, 0, np.zeros((0, 0), dtype=np.float64)
    # Offsets of the window's cell centres from the lamp, separable: rows x columns.
    u = ox + (np.arange(c0, c1, dtype=np.float64) + 0.5) * res - x
    v = oy + (np.arange(r0, r1, dtype=np.float64) + 0.5) * res - y
    r2 = v[:, None] ** 2 + u[None, :] ** 2
    win_free = np.asarray(free[r0:r1, c0:c1], dtype=bool)
    inside = r2 <= radius * radius
    lit = win_free & inside
    _shade(lit, win_free, u, v, r2, radius, res)
    e = lamp.at(r2)
    e *= lit | (_faces(lit) & ~win_free & inside)
    return r0, c0, e


def _faces(lit: Bools) -> Bools:
    """Cells beside a lit cell (by a side): where the light stops at a wall, the wall's face.

    A map cell is 5-10 cm: the wall's surface lies somewhere inside its first occupied (or unknown)
    cell, and the floor in front of it there is lit as the floor beside it is. Such a cell takes its
    own irradiance (from its centre's distance), so that where another robot's map holds it as
    floor (two maps agree on a wall to within a cell) the fleet's dose there is the dose it got.
    Floor cells are unchanged: a face is never a free cell."""
    out = np.zeros_like(lit)
    out[1:, :] |= lit[:-1, :]
    out[:-1, :] |= lit[1:, :]
    out[:, 1:] |= lit[:, :-1]
    out[:, :-1] |= lit[:, 1:]
    return out


def _pseudo_angle(v: F64, u: F64) -> F64:
    """A monotone stand-in for ``atan2(v, u)`` in (-2, 2] (the "diamond angle"), ~3x cheaper.

    Counter-clockwise like atan2, with the same seam (the negative x axis: -2 and 2), quadrant
    boundaries at -1, 0, 1, and antipodes 2 apart, so an arc under 180 degrees stays under 2."""
    t = v / np.maximum(np.abs(u) + np.abs(v), 1e-300)
    out: F64 = np.where(u >= 0.0, t, np.where(v >= 0.0, 2.0, -2.0) - t)
    return out


def _shade(lit: Bools, win_free: Bools, u: F64, v: F64, r2: F64, radius: float, res: float) -> None:
    """Clear ``lit`` where the floor segment from the lamp (0, 0) to the cell centre touches a wall cell."""
    s = res / 2.0
    # A segment leaving the free cells enters a wall first through a wall cell that touches a free
    # cell (by a side or a corner), so only those can block: not the inside of thick walls, nor the
    # unknown beyond them. The lamp's own cell counts as free (see below).
    around = win_free.copy()
    lamp_row, lamp_col = int(np.searchsorted(v, -s)), int(np.searchsorted(u, -s))
    if lamp_row < v.size and lamp_col < u.size and abs(v[lamp_row]) <= s and abs(u[lamp_col]) <= s:
        around[lamp_row, lamp_col] = True
    grown = around.copy()
    grown[1:, :] |= around[:-1, :]
    grown[:-1, :] |= around[1:, :]
    around = grown.copy()
    around[:, 1:] |= grown[:, :-1]
    around[:, :-1] |= grown[:, 1:]
    brow, bcol = np.nonzero(around & ~win_free)
    if brow.size == 0:
        return
    bu, bv = u[bcol], v[brow]
    gu, gv = np.maximum(np.abs(bu) - s, 0.0), np.maximum(np.abs(bv) - s, 0.0)
    near = np.sqrt(gu * gu + gv * gv)
    # Only wall cells within the reach can block a segment that ends within it; a wall cell the
    # lamp's floor position lies in (or on) is the robot's own cell mis-mapped: ignored.
    keep = (near < radius) & (near > 0.0)
    if not keep.any():
        return
    bu, bv, near = bu[keep], bv[keep], near[keep]
    far = np.hypot(np.abs(bu) + s, np.abs(bv) + s)
    # Each wall cell's angular span seen from the lamp (a convex square not containing the lamp
    # subtends < 180 degrees, < 2 in pseudo-angle): its corners' angles relative to its centre's.
    ac = _pseudo_angle(bv, bu)
    lo = np.full(bu.shape, np.inf)
    hi = np.full(bu.shape, -np.inf)
    for du, dv in ((-s, -s), (-s, s), (s, -s), (s, s)):
        d = _pseudo_angle(bv + dv, bu + du) - ac
        d = (d + 2.0) % 4.0 - 2.0
        np.minimum(lo, d, out=lo)
        np.maximum(hi, d, out=hi)
    eps = 1e-9  # widen by far less than a bin so rounding never drops a wall cell from a bin
    # Bins ~1/2 cell wide at the reach (pseudo-angle runs 4 per turn, 0.5-1 per radian): what they
    # leave undecided is settled exactly below, so their width costs time, never exactness.
    nbins = max(64, math.ceil(16.0 * radius / res))
    scale = nbins / 4.0
    k0 = np.floor((ac + lo - eps + 2.0) * scale).astype(np.intp)
    k1 = np.floor((ac + hi + eps + 2.0) * scale).astype(np.intp)
    counts = k1 - k0 + 1
    total = int(counts.sum())
    cell = np.repeat(np.arange(bu.size, dtype=np.intp), counts)
    starts = np.cumsum(counts) - counts
    step = np.arange(total, dtype=np.intp) - np.repeat(starts, counts)
    bins = (np.repeat(k0, counts) + step) % nbins
    near_any = np.full(nbins, np.inf)
    np.minimum.at(near_any, bins, near[cell])
    # Bins a wall cell covers whole (not its first or last): every ray in them crosses the cell.
    inner = (step > 0) & (step < np.repeat(counts, counts) - 1)
    far_full = np.full(nbins, np.inf)
    np.minimum.at(far_full, bins[inner], far[cell[inner]])

    # Every cell of the window at once (cheaper than gathering the lit ones first), in place.
    rho = np.sqrt(r2)
    pa = np.abs(v)[:, None] + np.abs(u)[None, :]
    np.maximum(pa, 1e-300, out=pa)
    np.divide(v[:, None], pa, out=pa)
    west = (u < 0.0)[None, :]
    np.negative(pa, out=pa, where=west)
    np.add(pa, np.where(v >= 0.0, 2.0, -2.0)[:, None], out=pa, where=west)  # = _pseudo_angle(v, u)
    pa += 2.0
    pa *= scale
    tbin = pa.astype(np.intp)
    tbin[tbin >= nbins] = 0
    lit &= rho <= far_full[tbin]
    open_ = lit & (rho > near_any[tbin])
    trow, tcol = np.nonzero(open_)
    if trow.size == 0:
        return
    # The undecided: exact segment/square tests against the wall cells of their bin nearer than them.
    rho, tu, tv, tb = rho[trow, tcol], u[tcol], v[trow], tbin[trow, tcol]
    span = 2.0 * radius + 1.0
    key = bins * span + near[cell]
    order = np.argsort(key)
    key, cell = key[order], cell[order]
    first = np.searchsorted(key, tb * span, side="left")
    last = np.searchsorted(key, tb * span + rho, side="left")
    n = last - first
    ti = np.repeat(np.arange(tu.size, dtype=np.intp), n)
    ci = cell[np.repeat(first, n) + (np.arange(int(n.sum()), dtype=np.intp) - np.repeat(np.cumsum(n) - n, n))]
    hit = _segment_hits_square(tu[ti], tv[ti], bu[ci], bv[ci], s)
    blocked = np.bincount(ti[hit], minlength=tu.size) > 0
    lit[trow[blocked], tcol[blocked]] = False


def _segment_hits_square(tx: F64, ty: F64, cx: F64, cy: F64, s: float) -> Bools:
    """Whether the segment (0, 0)-(tx, ty) touches the closed square centred (cx, cy), half-side s."""
    t_in = np.zeros(tx.shape)
    t_out = np.ones(tx.shape)
    ok = np.ones(tx.shape, dtype=bool)
    for t, c in ((tx, cx), (ty, cy)):
        zero = t == 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            a = (c - s) / t
            b = (c + s) / t
        np.maximum(t_in, np.where(zero, -np.inf, np.minimum(a, b)), out=t_in)
        np.minimum(t_out, np.where(zero, np.inf, np.maximum(a, b)), out=t_out)
        ok &= ~zero | ((c - s <= 0.0) & (c + s >= 0.0))
    out: Bools = ok & (t_in <= t_out)
    return out


# -- the dose grid -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Footprint:
    """A lamp position's irradiance (W/m², read-only) on a dose grid's lattice: the window of cells
    whose (0, 0) is lattice cell (``kx``, ``ky``), i.e. centred at (kx, ky) * ``resolution``.
    ``DoseGrid.footprint`` makes one, ``DoseGrid.expose`` adds it for a number of seconds."""

    x: float
    y: float
    resolution: float
    kx: int
    ky: int
    irradiance: F64


class DoseGrid:
    """Dose (J/m²) per floor cell in the site frame, accumulated over time and over robots.

    Cell centres lie on multiples of the resolution (as the onboard map's, ``agent/mapping/grid.py``),
    so every robot's dose grid at one resolution shares one lattice: grids merge by adding at
    integer offsets, without resampling. The grid grows in ``grow_step_m`` chunks as lamps reach
    new ground (a fixed extent would need the site's size up front, which a robot sent into
    unmapped rooms does not know), exactly as the map does. ``dose[row, col]``, row 0 at the bottom.
    """

    def __init__(
        self,
        resolution: float = 0.05,
        *,
        grow_step_m: float = 8.0,
        cutoff_w_m2: float = DEFAULT_CUTOFF_W_M2,
        max_radius_m: float = DEFAULT_MAX_RADIUS_M,
    ) -> None:
        if not (math.isfinite(resolution) and resolution > 0.0):
            raise ValueError(f"resolution must be > 0 m, got {resolution}")
        if not (math.isfinite(grow_step_m) and grow_step_m > 0.0):
            raise ValueError(f"grow_step_m must be > 0 m, got {grow_step_m}")
        if not (math.isfinite(cutoff_w_m2) and cutoff_w_m2 >= 0.0):
            raise ValueError(f"cutoff_w_m2 must be a finite number >= 0 W/m², got {cutoff_w_m2!r}")
        if not (math.isfinite(max_radius_m) and max_radius_m >= 0.0):
            raise ValueError(f"max_radius_m must be a finite number >= 0 m, got {max_radius_m!r}")
        self.resolution = float(resolution)
        self.grow_step_m = float(grow_step_m)
        self.cutoff_w_m2 = float(cutoff_w_m2)
        self.max_radius_m = float(max_radius_m)
        self.dose: F64 = np.zeros((0, 0), dtype=np.float64)
        self._kx = 0  # cell (0, 0)'s centre is at (_kx, _ky) * resolution
        self._ky = 0
        self.lamp_seconds = 0.0
        """Seconds of lamp-on time added so far (a merged grid: the sum over its robots)."""

    @property
    def origin(self) -> tuple[float, float]:
        """The outer corner of cell (0, 0), as the map's origin."""
        res = self.resolution
        return ((self._kx - 0.5) * res, (self._ky - 0.5) * res)

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.dose.shape
        return int(h), int(w)

    def _lattice(self, origin: tuple[float, float]) -> tuple[int, int]:
        """The lattice indices of a grid's cell (0, 0) from its origin; ValueError when off the lattice."""
        res = self.resolution
        ks = []
        for o in origin:
            k = float(o) / res + 0.5
            if not (math.isfinite(k) and abs(k - round(k)) < 1e-6):
                raise ValueError(f"origin {origin} is not on the {res:g} m lattice (cell centres on multiples of it)")
            ks.append(round(k))
        return ks[0], ks[1]

    @classmethod
    def from_array(cls, dose: npt.ArrayLike, resolution: float, origin: tuple[float, float]) -> DoseGrid:
        """A dose grid from its cells (a received layer); ValueError unless on the lattice, finite, >= 0."""
        g = cls(resolution)
        a = np.array(dose, dtype=np.float64)
        if a.ndim != 2:
            raise ValueError(f"dose must be a 2-D array, got shape {a.shape}")
        if a.size and not (np.isfinite(a).all() and (a >= 0.0).all()):
            raise ValueError("dose must be finite and >= 0 J/m² in every cell")
        g._kx, g._ky = g._lattice(origin)
        g.dose = a
        return g

    def copy(self) -> DoseGrid:
        g = DoseGrid(
            self.resolution, grow_step_m=self.grow_step_m, cutoff_w_m2=self.cutoff_w_m2, max_radius_m=self.max_radius_m
        )
        g.dose, g._kx, g._ky, g.lamp_seconds = self.dose.copy(), self._kx, self._ky, self.lamp_seconds
        return g

    def _cover(self, kx0: int, ky0: int, kx1: int, ky1: int, pad: int) -> None:
        """Grow so the lattice cells kx0..kx1 x ky0..ky1 (inclusive) are on the grid, by ``pad`` cells
        at a time (an empty grid: exactly those, plus ``pad // 2`` around)."""
        h, w = self.shape
        if h == 0 or w == 0:
            half = pad // 2
            self._kx, self._ky = kx0 - half, ky0 - half
            self.dose = np.zeros((ky1 - ky0 + 1 + 2 * half, kx1 - kx0 + 1 + 2 * half), dtype=np.float64)
            return

        def more(short: int) -> int:
            return 0 if short <= 0 else (pad * math.ceil(short / pad) if pad > 0 else short)

        add_l, add_b = more(self._kx - kx0), more(self._ky - ky0)
        add_r, add_t = more(kx1 - (self._kx + w - 1)), more(ky1 - (self._ky + h - 1))
        if add_l or add_b or add_r or add_t:
            grown = np.zeros((h + add_b + add_t, w + add_l + add_r), dtype=np.float64)
            grown[add_b : add_b + h, add_l : add_l + w] = self.dose
            self.dose = grown
            self._kx -= add_l
            self._ky -= add_b

    def ensure(self, xmin: float, ymin: float, xmax: float, ymax: float) -> None:
        """Grow (in ``grow_step_m`` chunks) so the grid covers the box (m, site frame)."""
        for v in (xmin, ymin, xmax, ymax):
            _finite("box", v)
        res = self.resolution
        pad = max(1, math.ceil(self.grow_step_m / res))
        self._cover(
            round(xmin / res) - 1, round(ymin / res) - 1, round(xmax / res) + 1, round(ymax / res) + 1, pad
        )  # fmt: skip

    def add(self, lamp: Lamp, x: float, y: float, seconds: float, floor: FloorMask) -> tuple[int, int, int, int] | None:
        """The lamp was on for ``seconds`` above floor point (x, y) of the site, over ``floor`` (the
        robot's map). Returns the box of cells changed (row0, col0, row1, col1 exclusive), or None."""
        x, y = _finite("lamp x", x), _finite("lamp y", y)
        sec = _finite("seconds", seconds)
        if sec < 0.0:
            raise ValueError(f"seconds must be >= 0, got {seconds!r}")
        if sec == 0.0 or lamp.reach(self.cutoff_w_m2, self.max_radius_m) <= 0.0:
            return None
        return self.expose(self.footprint(lamp, x, y, floor), sec)

    def footprint(self, lamp: Lamp, x: float, y: float, floor: FloorMask) -> Footprint:
        """The lamp's irradiance above floor point (x, y) over ``floor``, on this grid's lattice (the
        grid grows to cover its reach). ``expose(footprint, seconds)`` adds it: a lamp standing still
        is computed once and exposed for every interval it stays on (``add`` does both)."""
        x, y = _finite("lamp x", x), _finite("lamp y", y)
        radius = lamp.reach(self.cutoff_w_m2, self.max_radius_m)
        empty = np.zeros((0, 0), dtype=np.float64)
        empty.flags.writeable = False
        if radius <= 0.0:
            return Footprint(x, y, self.resolution, 0, 0, empty)
        self.ensure(x - radius, y - radius, x + radius, y + radius)
        res = self.resolution
        ox, oy = self.origin
        h, w = self.shape
        c0 = max(0, math.floor((x - radius - ox) / res))
        c1 = min(w, math.floor((x + radius - ox) / res) + 1)
        r0 = max(0, math.floor((y - radius - oy) / res))
        r1 = min(h, math.floor((y + radius - oy) / res) + 1)
        xs = (self._kx + np.arange(c0, c1, dtype=np.float64)) * res
        ys = (self._ky + np.arange(r0, r1, dtype=np.float64)) * res
        free = floor.sample(xs, ys)
        wr0, wc0, e = irradiance_window(
            lamp,
            x,
            y,
            free,
            res,
            (ox + c0 * res, oy + r0 * res),
            cutoff_w_m2=self.cutoff_w_m2,
            max_radius_m=self.max_radius_m,
        )
        if e.size == 0:
            return Footprint(x, y, res, 0, 0, empty)
        e.flags.writeable = False
        return Footprint(x, y, res, self._kx + c0 + wc0, self._ky + r0 + wr0, e)

    def expose(self, fp: Footprint, seconds: float) -> tuple[int, int, int, int] | None:
        """Add ``fp`` (from ``footprint`` on a grid at this resolution) for ``seconds`` of lamp-on
        time. Returns the box of cells changed (row0, col0, row1, col1 exclusive), or None."""
        sec = _finite("seconds", seconds)
        if sec < 0.0:
            raise ValueError(f"seconds must be >= 0, got {seconds!r}")
        if fp.resolution != self.resolution:
            raise ValueError(f"a footprint on {fp.resolution:g} m cells does not fit a grid of {self.resolution:g} m")
        if sec == 0.0:
            return None
        self.lamp_seconds += sec
        e = fp.irradiance
        if e.size == 0:
            return None
        h, w = e.shape
        self._cover(fp.kx, fp.ky, fp.kx + w - 1, fp.ky + h - 1, max(1, math.ceil(self.grow_step_m / self.resolution)))
        rr0, cc0 = fp.ky - self._ky, fp.kx - self._kx
        self.dose[rr0 : rr0 + h, cc0 : cc0 + w] += e * sec
        return rr0, cc0, rr0 + h, cc0 + w

    def dose_at(self, xs: F64, ys: F64) -> F64:
        """Dose (J/m²) at the grid of points ``ys x xs`` (rows x columns); 0 off the grid."""
        h, w = self.shape
        out: F64 = np.zeros((ys.size, xs.size), dtype=np.float64)
        if h == 0 or w == 0:
            return out
        res = self.resolution
        cols = np.floor(xs / res + 0.5).astype(np.intp) - self._kx
        rows = np.floor(ys / res + 0.5).astype(np.intp) - self._ky
        cin = (cols >= 0) & (cols < w)
        rin = (rows >= 0) & (rows < h)
        out[np.ix_(rin, cin)] = self.dose[np.ix_(rows[rin], cols[cin])]
        return out

    def on(self, mask: FloorMask) -> F64:
        """Dose (J/m²) at the centres of ``mask``'s cells."""
        xs, ys = mask.centres()
        return self.dose_at(xs, ys)

    def covered(self, target_j_m2: float, mask: FloorMask) -> float:
        """The fraction (0-1) of ``mask``'s floor cells that received at least the target dose."""
        target = _check_target(target_j_m2)
        n = int(mask.free.sum())
        if n == 0:
            raise ValueError("the mask has no floor cells: coverage of nothing is undefined")
        return int((self.on(mask)[mask.free] >= target).sum()) / n

    def below_target(self, target_j_m2: float, mask: FloorMask) -> F64:
        """Centres (N x 2, x and y in m) of ``mask``'s floor cells below the target dose."""
        target = _check_target(target_j_m2)
        xs, ys = mask.centres()
        rows, cols = np.nonzero(mask.free & (self.on(mask) < target))
        out: F64 = np.column_stack((xs[cols], ys[rows]))
        return out

    @classmethod
    def merged(cls, grids: Iterable[DoseGrid]) -> DoseGrid:
        """The sum of several robots' dose grids (same resolution), aligned in the site frame, over
        exactly the union of their extents."""
        gs = list(grids)
        if not gs:
            raise ValueError("nothing to merge")
        res = gs[0].resolution
        for g in gs:
            if g.resolution != res:
                raise ValueError(f"cannot merge dose grids of {res:g} m and {g.resolution:g} m cells")
        out = gs[0].copy()
        out.dose = np.zeros((0, 0), dtype=np.float64)
        out.lamp_seconds = sum(g.lamp_seconds for g in gs)
        full = [g for g in gs if g.dose.size]
        if not full:
            return out
        out._cover(
            min(g._kx for g in full),
            min(g._ky for g in full),
            max(g._kx + g.shape[1] - 1 for g in full),
            max(g._ky + g.shape[0] - 1 for g in full),
            0,
        )
        for g in full:
            h, w = g.shape
            c, r = g._kx - out._kx, g._ky - out._ky
            out.dose[r : r + h, c : c + w] += g.dose
        return out


# -- reports -----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class UnderDosed:
    """One connected (8-neighbour) region of floor cells below the target."""

    area_m2: float
    centroid: tuple[float, float]
    box: tuple[float, float, float, float]
    """xmin, ymin, xmax, ymax of the cells' outer edges, m."""


@dataclass(frozen=True, slots=True)
class DoseSummary:
    target_j_m2: float
    floor_m2: float
    reached_m2: float
    below_m2: float
    fraction: float
    min_dose_j_m2: float
    regions: tuple[UnderDosed, ...]
    """The largest under-dosed regions, largest first (at most ``max_regions``)."""
    regions_total: int

    def text(self) -> str:
        lines = [
            f"target dose: {self.target_j_m2:g} J/m² ({self.target_j_m2 / J_M2_PER_MJ_CM2:g} mJ/cm²)",
            f"floor: {self.floor_m2:.2f} m²",
            f"at or above target: {self.reached_m2:.2f} m² ({100.0 * self.fraction:.1f} %)",
            f"below target: {self.below_m2:.2f} m² in {self.regions_total} region(s)",
            f"lowest dose on the floor: {self.min_dose_j_m2:.3g} J/m²",
        ]
        for i, r in enumerate(self.regions, 1):
            x0, y0, x1, y1 = r.box
            lines.append(
                f"  {i}. {r.area_m2:.2f} m² around ({r.centroid[0]:.2f}, {r.centroid[1]:.2f}),"
                f" x {x0:.2f}..{x1:.2f}, y {y0:.2f}..{y1:.2f}"
            )
        if self.regions_total > len(self.regions):
            lines.append(f"  ... and {self.regions_total - len(self.regions)} smaller region(s)")
        return "\n".join(lines) + "\n"


def _cells(grid: DoseGrid, mask: FloorMask | None) -> tuple[F64, Bools, float, tuple[float, float]]:
    """The dose on the report's lattice (the mask's, else the grid's) and which cells are floor."""
    if mask is not None:
        return grid.on(mask), mask.free, mask.resolution, mask.origin
    return grid.dose, np.ones(grid.shape, dtype=bool), grid.resolution, grid.origin


def summarise(grid: DoseGrid, target_j_m2: float, mask: FloorMask, *, max_regions: int = 20) -> DoseSummary:
    """Area reached, area below the target and where (the largest under-dosed regions)."""
    target = _check_target(target_j_m2)
    dose, floor, res, (ox, oy) = _cells(grid, mask)
    n = int(floor.sum())
    if n == 0:
        raise ValueError("the mask has no floor cells: nothing to summarise")
    below = floor & (dose < target)
    cell_m2 = res * res
    regions = []
    for cells in components(below):
        rows, cols = cells[:, 0], cells[:, 1]
        regions.append(
            UnderDosed(
                area_m2=rows.size * cell_m2,
                centroid=(ox + (float(cols.mean()) + 0.5) * res, oy + (float(rows.mean()) + 0.5) * res),
                box=(
                    ox + cols.min() * res,
                    oy + rows.min() * res,
                    ox + (cols.max() + 1) * res,
                    oy + (rows.max() + 1) * res,
                ),
            )
        )
    regions.sort(key=lambda r: (-r.area_m2, r.centroid))
    nb = int(below.sum())
    return DoseSummary(
        target_j_m2=target,
        floor_m2=n * cell_m2,
        reached_m2=(n - nb) * cell_m2,
        below_m2=nb * cell_m2,
        fraction=(n - nb) / n,
        min_dose_j_m2=float(dose[floor].min()),
        regions=tuple(regions[:max_regions]),
        regions_total=len(regions),
    )


def _fraction(grid: DoseGrid, target_j_m2: float, mask: FloorMask | None) -> tuple[F64, Bools]:
    target = _check_target(target_j_m2)
    dose, floor, _, _ = _cells(grid, mask)
    frac: F64 = np.clip(dose / target, 0.0, 1.0)
    return frac, floor


def pgm_report(grid: DoseGrid, target_j_m2: float, mask: FloorMask | None = None) -> bytes:
    """The dose as a fraction of the target, a binary PGM (P5, maxval 255), north up.

    Floor cells: ``1 + round(254 * min(dose / target, 1))`` (1: no dose, 255: target reached);
    cells that are not floor (with a mask): 0."""
    frac, floor = _fraction(grid, target_j_m2, mask)
    grey = np.where(floor, 1 + np.rint(254.0 * frac), 0).astype(np.uint8)[::-1]
    h, w = grey.shape
    return f"P5\n{w} {h}\n255\n".encode("ascii") + grey.tobytes()


def png_report(grid: DoseGrid, target_j_m2: float, mask: FloorMask | None = None) -> bytes:
    """The same picture in colour, as an 8-bit RGB PNG (stdlib zlib; no imaging dependency).

    At target: green; below: red (no dose) through yellow (nearly there); not floor: dark grey."""
    frac, floor = _fraction(grid, target_j_m2, mask)
    h, w = frac.shape
    rgb = np.empty((h, w, 3), dtype=np.uint8)
    rgb[..., 0] = 255
    rgb[..., 1] = np.rint(230.0 * frac).astype(np.uint8)
    rgb[..., 2] = 0
    rgb[frac >= 1.0] = (0, 170, 0)
    rgb[~floor] = (40, 40, 40)
    rows = np.concatenate((np.zeros((h, 1), dtype=np.uint8), rgb[::-1].reshape(h, w * 3)), axis=1)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
        + chunk(b"IEND", b"")
    )


CSV_COLUMNS: Sequence[str] = ("x_m", "y_m", "dose_j_per_m2", "at_target")


def csv_report(grid: DoseGrid, target_j_m2: float, mask: FloorMask | None = None) -> str:
    """One line per floor cell of ``mask`` (without a mask: per cell with a dose > 0): its centre,
    its dose (J/m²) and 1 if it reached the target, else 0."""
    target = _check_target(target_j_m2)
    dose, floor, res, (ox, oy) = _cells(grid, mask)
    pick = floor if mask is not None else floor & (dose > 0.0)
    rows, cols = np.nonzero(pick)
    xs = ox + (cols + 0.5) * res
    ys = oy + (rows + 0.5) * res
    d = dose[rows, cols]
    lines = [",".join(CSV_COLUMNS)]
    lines.extend(
        f"{x:.3f},{y:.3f},{v:.3f},{int(v >= target)}"
        for x, y, v in zip(xs.tolist(), ys.tolist(), d.tolist(), strict=True)
    )
    return "\n".join(lines) + "\n"
