"""The dose keeper: what one robot's UV-C lamp has given the floor, as the agent runs. Pure.

The agent's control step hands ``DoseKeeper.step`` a ``DoseSample`` per tick: the time, the fused
map pose, whether the *board* reports the lamp on (its own report, not what was commanded) and
whether the fusion has placed the robot in the site frame. The lamp's state is held from one
sample to the next: an interval counts when the sample that opens it says the lamp was on. The
floor is the robot's own onboard map in the site frame (``set_floor``, from the map keeper's
publications; unknown cells block light and take no dose but for a lit wall's face, shared/dose.py); the dose grid is in
the same frame, at ``resolution`` on the lattice every robot's layer shares.

Where the keeper puts lamp-on time:

* placed and with a site-frame map: into the grid (``DoseGrid.expose``), at the lamp's position;
* otherwise (no UWB position yet, or the map has not restarted in the site frame): into
  ``unplaced_s``, counted and reported, never guessed onto the floor.

CPU stays bounded. Consecutive lamp-on intervals are gathered into a run and exposed as one at
the run's midpoint with its whole duration when the run has lasted ``hold_s`` (0.2 s) or the
robot moved ``step_m`` (0.1 m) since it began, when the lamp goes off, or when placement is lost.
A run that moved less than ``still_m`` (2 cm) and lies within ``still_m`` of the last footprint,
on the same floor, reuses that footprint scaled by its seconds (a few microseconds) instead of
computing a new one (milliseconds: docs/payload.md, "Measured"). The heading plays no part: the
lamp is modelled at the robot's centre, so turning in place moves it nowhere. Driving at 0.5 m/s
that is five footprints a second; standing, one per floor change (the map keeper publishes at
most once a second).

Every ``share_period`` (1 s), if anything changed, ``step`` returns a ``DosePublication``: the
cells copied at one version and the box changed since the previous publication (None when the
grid grew, or at the first one), for the agent's ``DoseShare`` to serve and patch. Time is an
argument; no clock, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fleetlink.shared.dose import DoseGrid, FloorMask, Footprint, Lamp

__all__ = [
    "HOLD_S",
    "SHARE_PERIOD_S",
    "STEP_M",
    "STILL_M",
    "DoseKeeper",
    "DosePublication",
    "DoseSample",
]

SHARE_PERIOD_S = 1.0
"""Seconds between publications (a snapshot to serve, a patch to send) while the dose changes."""
HOLD_S = 0.2
"""A run of lamp-on time is exposed at least this often."""
STEP_M = 0.1
"""... or once the lamp has moved this far since the run began."""
STILL_M = 0.02
"""A run that moved less than this, this near the last footprint, reuses it."""

Box = tuple[int, int, int, int]


@dataclass(frozen=True, slots=True)
class DoseSample:
    """One control tick as the dose keeper takes it."""

    t: float
    """Clock time, s."""
    x: float
    """The fused map pose, m (site frame once ``placed``)."""
    y: float
    lamp_on: bool
    """The board reports the lamp on."""
    placed: bool
    """The fusion has placed the robot in the site frame (``position_initialized``)."""


@dataclass(frozen=True, slots=True)
class DosePublication:
    """The layer as the share sends it: the dose (J/m²) copied at ``version``, and the box of cells
    (row0, col0, row1, col1) changed since the previous publication (None: send no patch)."""

    version: int
    dose: npt.NDArray[np.float64]
    resolution: float
    origin: tuple[float, float]
    changed: Box | None
    target_j_m2: float
    lamp_on_s: float
    unplaced_s: float
    lamp: Lamp


@dataclass(slots=True)
class _Run:
    """Lamp-on time gathered since the last exposure, and where the lamp went meanwhile."""

    x0: float
    y0: float
    x1: float
    y1: float
    seconds: float

    @property
    def moved(self) -> float:
        return math.hypot(self.x1 - self.x0, self.y1 - self.y0)


class DoseKeeper:
    def __init__(
        self,
        lamp: Lamp,
        target_j_m2: float,
        resolution: float = 0.1,
        *,
        share_period: float = SHARE_PERIOD_S,
        hold_s: float = HOLD_S,
        step_m: float = STEP_M,
        still_m: float = STILL_M,
    ) -> None:
        if not (math.isfinite(target_j_m2) and target_j_m2 > 0.0):
            raise ValueError(f"target dose must be a finite number > 0 J/m², got {target_j_m2!r}")
        self.lamp = lamp
        self.target_j_m2 = float(target_j_m2)
        self.grid = DoseGrid(resolution)
        self.share_period = share_period
        self.hold_s = hold_s
        self.step_m = step_m
        self.still_m = still_m
        self.unplaced_s = 0.0
        """Lamp-on seconds that could not be placed on the floor."""
        self.version = 0
        """+1 per change (an exposure, unplaced time)."""
        self.footprints = 0
        """Footprints computed (the costly part)."""
        self.exposures = 0
        """Runs exposed (computed or reused footprints)."""
        self._floor: tuple[FloorMask, int] | None = None
        self._last: DoseSample | None = None
        self._run: _Run | None = None
        self._fp: tuple[Footprint, int] | None = None  # the last footprint and its floor's version
        self._changed: Box | None = None  # lattice cells changed since the last publication (ky0, kx0, ky1, kx1)
        self._shared_version = 0
        self._shared_frame: tuple[tuple[float, float], tuple[int, int]] | None = None
        self._next_share = -math.inf

    # -- inputs -------------------------------------------------------------------------------------

    def set_floor(self, floor: FloorMask | None, version: int) -> None:
        """The robot's map in the site frame (None: none yet), at map ``version``. One assignment:
        the map's thread may call it while the control thread steps."""
        self._floor = None if floor is None else (floor, version)

    @property
    def floor(self) -> FloorMask | None:
        """The floor in use (None: no site-frame map yet)."""
        floor = self._floor
        return None if floor is None else floor[0]

    @property
    def floor_version(self) -> int | None:
        """The map version of the floor in use (None: no site-frame map yet)."""
        floor = self._floor
        return None if floor is None else floor[1]

    @property
    def sampled_until(self) -> float | None:
        """Clock time of the last tick taken (None before the first)."""
        return None if self._last is None else self._last.t

    def step(self, s: DoseSample) -> DosePublication | None:
        """One tick. A publication when one is due."""
        prev, self._last = self._last, s
        if prev is not None and s.t > prev.t and prev.lamp_on:
            dt = s.t - prev.t
            floor = self._floor
            if prev.placed and s.placed and floor is not None and _finite(s.x, s.y, prev.x, prev.y):
                run = self._run
                if run is None:
                    self._run = _Run(prev.x, prev.y, s.x, s.y, dt)
                else:
                    run.x1, run.y1, run.seconds = s.x, s.y, run.seconds + dt
            else:
                self._flush()
                self.unplaced_s += dt
                self.version += 1
        run = self._run
        if run is not None and (
            not s.lamp_on or not s.placed or run.seconds >= self.hold_s - 1e-9 or run.moved >= self.step_m - 1e-9
        ):
            self._flush()
        return self._publication(s.t)

    # -- internals ----------------------------------------------------------------------------------

    def _flush(self) -> None:
        run, self._run = self._run, None
        floor = self._floor
        if run is None or run.seconds <= 0.0:
            return
        if floor is None:  # the map went away mid-run (never, today): the time is still counted
            self.unplaced_s += run.seconds
            self.version += 1
            return
        mask, floor_version = floor
        x, y = 0.5 * (run.x0 + run.x1), 0.5 * (run.y0 + run.y1)
        cached = self._fp
        if (
            cached is not None
            and cached[1] == floor_version
            and run.moved < self.still_m
            and math.hypot(cached[0].x - x, cached[0].y - y) < self.still_m
        ):
            fp = cached[0]
        else:
            fp = self.grid.footprint(self.lamp, x, y, mask)
            self._fp = (fp, floor_version)
            self.footprints += 1
        self.grid.expose(fp, run.seconds)
        self.exposures += 1
        self.version += 1
        h, w = fp.irradiance.shape
        if h and w:
            box = (fp.ky, fp.kx, fp.ky + h, fp.kx + w)
            c = self._changed
            self._changed = (
                box if c is None else (min(c[0], box[0]), min(c[1], box[1]), max(c[2], box[2]), max(c[3], box[3]))
            )

    def _lattice(self) -> tuple[int, int]:
        res = self.grid.resolution
        ox, oy = self.grid.origin
        return round(ox / res + 0.5), round(oy / res + 0.5)

    def _publication(self, now: float) -> DosePublication | None:
        if now < self._next_share or self.version == self._shared_version:
            return None
        self._next_share = now + self.share_period
        g = self.grid
        kx, ky = self._lattice()
        frame = (g.origin, g.shape)
        changed: Box | None = None
        if self._shared_frame == frame:
            c = self._changed
            changed = (0, 0, 0, 0) if c is None else (c[0] - ky, c[1] - kx, c[2] - ky, c[3] - kx)
        self._shared_frame = frame
        self._shared_version = self.version
        self._changed = None
        return DosePublication(
            version=self.version,
            dose=g.dose.copy(),
            resolution=g.resolution,
            origin=g.origin,
            changed=changed,
            target_j_m2=self.target_j_m2,
            lamp_on_s=g.lamp_seconds,
            unplaced_s=self.unplaced_s,
            lamp=self.lamp,
        )


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)
