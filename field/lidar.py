"""What a 2D spinning lidar measures in the field: one revolution at a time, from a pose.

``LidarModel(config, rng).revolution(x, y, theta, raycaster, circles)`` casts one turn of rays from
the lidar's position on the robot and returns ``(angles, distances, qualities)`` the way a real unit
reports them: a sample with no return has distance 0.0 and quality 0.

Frames and conventions:

* ``angles`` are radians in the *sensor frame*, counter-clockwise, in [0, 2 pi), increasing. The
  sensor frame is the robot frame moved to the mount point and turned by ``mount_yaw``; with the
  default mount (at the robot's centre, facing forward) it is the robot frame. Distances are from the
  mount point. (On the wire the RPLIDAR reports clockwise degrees; ``field.rplidar`` converts.)
* Samples are evenly spaced in time, ``samples_per_second``; one turn takes ``1 / rate_hz``, so a
  turn has about ``samples_per_second / rate_hz`` samples (1454.5 at the A1's 5.5 Hz). Each turn
  starts at a random phase within one sample step (``random_phase``), as a real unit's first
  sample after its zero crossing does, so sample counts alternate (1454 / 1455) and angles differ
  from turn to turn.
* The whole turn is cast from one pose: motion during the ~0.1-0.2 s of a turn is not smeared in.
* Noise: range sd = ``range_noise_sd + range_noise_rel * d``; samples are dropped (distance 0) with
  probability ``dropout`` plus ``far_dropout * (d / max_range) ** 2``; returns nearer than
  ``min_range`` or beyond ``max_range`` (after noise) are 0; quality falls from 63 at close range
  towards ``quality_far`` at ``max_range`` (linear in the true distance, plus noise). Samples outside ``fov_deg`` (centred on the sensor's
  forward axis) are 0.
* Every random draw comes from the ``numpy.random.Generator`` passed in, in a fixed order and a
  fixed number per sample whatever the settings, so a seeded model gives the same turns twice, and
  changing one noise parameter does not reshuffle the others.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from fleetlink.field.raycast import Raycaster

__all__ = ["LidarConfig", "LidarModel", "ScanSource", "Turn", "scan_source_for"]

FloatArray = npt.NDArray[np.float64]
Turn = tuple[FloatArray, FloatArray, npt.NDArray[np.uint8]]  # angles (rad), distances (m), qualities
ScanSource = Callable[[float], Turn]

_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True, slots=True)
class LidarConfig:
    """A 2D lidar; the defaults are a SLAMTEC RPLIDAR A1."""

    fov_deg: float = 360.0
    rate_hz: float = 5.5  # revolutions per second (the A1 runs 5.5 Hz typically, up to 10 Hz)
    samples_per_second: float = 8000.0
    min_range: float = 0.15  # m
    max_range: float = 12.0  # m
    range_noise_sd: float = 0.01  # m, constant part of the range noise sd
    range_noise_rel: float = 0.005  # proportional part: sd += range_noise_rel * distance
    dropout: float = 0.0  # probability that any sample returns nothing
    far_dropout: float = 0.0  # extra dropout probability at max_range, growing with (d / max_range)^2
    quality_near: int = 63  # quality of a return at close range (6 bits on the wire)
    quality_far: int = 10  # quality of a return at max_range
    quality_noise: float = 2.0  # sd of the quality, in quality units
    random_phase: bool = True  # each turn starts at a random fraction of a sample step
    mount_x: float = 0.0  # m, lidar position in the robot frame
    mount_y: float = 0.0
    mount_yaw: float = 0.0  # rad, the sensor's forward axis relative to the robot's

    def __post_init__(self) -> None:
        if not 0.0 < self.fov_deg <= 360.0:
            raise ValueError(f"fov_deg must be in (0, 360], not {self.fov_deg}")
        if self.rate_hz <= 0.0 or self.samples_per_second <= 0.0:
            raise ValueError("rate_hz and samples_per_second must be positive")
        if self.samples_per_second / self.rate_hz < 2.0:
            raise ValueError("fewer than two samples per revolution")
        if not 0.0 <= self.min_range < self.max_range:
            raise ValueError("need 0 <= min_range < max_range")
        if not (0.0 <= self.dropout <= 1.0 and 0.0 <= self.far_dropout <= 1.0):
            raise ValueError("dropout probabilities must be in [0, 1]")
        if self.range_noise_sd < 0.0 or self.range_noise_rel < 0.0 or self.quality_noise < 0.0:
            raise ValueError("noise levels must not be negative")

    @property
    def angle_step(self) -> float:
        """Radians between consecutive samples."""
        return _TWO_PI * self.rate_hz / self.samples_per_second

    @property
    def samples_per_revolution(self) -> float:
        return self.samples_per_second / self.rate_hz

    def noiseless(self) -> LidarConfig:
        """The same lidar without noise, dropouts or random phase (for tests against geometry)."""
        return replace(
            self,
            range_noise_sd=0.0,
            range_noise_rel=0.0,
            dropout=0.0,
            far_dropout=0.0,
            quality_noise=0.0,
            random_phase=False,
        )


class LidarModel:
    """Turns of a simulated lidar. Deterministic given the generator's seed and the call sequence."""

    def __init__(self, config: LidarConfig, rng: np.random.Generator) -> None:
        self.config = config
        self.rng = rng
        self.revolutions = 0

    def revolution(
        self,
        x: float,
        y: float,
        theta: float,
        raycaster: Raycaster,
        circles: npt.ArrayLike | None = None,
    ) -> Turn:
        """One turn from the robot pose (x, y, theta): (angles rad sensor frame, distances m, qualities).

        ``circles`` (M, 3: cx, cy, r) are other bodies the rays can hit (other robots).
        """
        cfg = self.config
        rng = self.rng
        step = cfg.angle_step
        phase = float(rng.random()) * step if cfg.random_phase else 0.0
        n = max(1, math.ceil((_TWO_PI - phase) / step - 1e-9))  # samples with phase + k step < 2 pi
        angles = phase + step * np.arange(n, dtype=np.float64)

        c, s = math.cos(theta), math.sin(theta)
        lx = x + c * cfg.mount_x - s * cfg.mount_y
        ly = y + s * cfg.mount_x + c * cfg.mount_y
        yaw = theta + cfg.mount_yaw
        true = raycaster.cast_fan(lx, ly, yaw + phase, step, n, cfg.max_range, circles)

        # Fixed draws per sample, whatever the settings (common random numbers).
        gauss = rng.standard_normal((2, n))  # range noise, quality noise
        drop_u = rng.random(n)

        hit = np.isfinite(true)
        d = np.where(hit, true, 0.0)
        measured = d * (1.0 + cfg.range_noise_rel * gauss[0])
        measured += cfg.range_noise_sd * gauss[0]
        ok = hit & (measured >= cfg.min_range) & (measured <= cfg.max_range)
        if cfg.far_dropout > 0.0:
            frac = d / cfg.max_range
            ok &= drop_u >= cfg.dropout + cfg.far_dropout * frac * frac
        elif cfg.dropout > 0.0:
            ok &= drop_u >= cfg.dropout
        if cfg.fov_deg < 360.0:
            half = math.radians(cfg.fov_deg) / 2.0
            off = np.mod(angles + math.pi, _TWO_PI) - math.pi  # bearing from the forward axis
            ok &= np.abs(off) <= half
        distances = np.where(ok, measured, 0.0)
        slope = (cfg.quality_far - cfg.quality_near) / cfg.max_range
        q = np.rint(cfg.quality_near + slope * d + cfg.quality_noise * gauss[1])
        np.clip(q, 1, 63, out=q)
        qualities = np.where(ok, q, 0.0).astype(np.uint8)
        self.revolutions += 1
        return angles, distances, qualities


def scan_source_for(
    model: LidarModel,
    pose: Callable[[float], tuple[float, float, float]],
    raycaster: Raycaster | Callable[[], Raycaster],
    circles: Callable[[float, float, float], npt.ArrayLike | None] | None = None,
) -> ScanSource:
    """A ``scan_source(now)`` for ``SimulatedRplidar``: one turn of ``model`` from ``pose(now)``.

    ``raycaster`` may be a callable returning the current one (the world may rebuild it);
    ``circles(x, y, now)`` gives the other bodies near the lidar, where they were at ``now``.
    """

    def source(now: float) -> Turn:
        x, y, theta = pose(now)
        rc = raycaster if isinstance(raycaster, Raycaster) else raycaster()
        return model.revolution(x, y, theta, rc, circles(x, y, now) if circles is not None else None)

    return source
