"""The degenerate case: a long featureless corridor. Matching on exact odometry must not slide the
pose along the corridor (the motion prior holds the weak direction, the walls hold the others)."""

from __future__ import annotations

import math

import numpy as np

from fleetlink.agent.mapping.mapper import MapperConfig, OnboardMapper, relative
from fleetlink.agent.mapping.matcher import MatchConfig
from fleetlink.field.raycast import Raycaster

# Two parallel walls 2 m apart, 60 m long: the 12 m lidar never sees an end.
CORRIDOR = np.array([[-30.0, -1.0, 30.0, -1.0], [-30.0, 1.0, 30.0, 1.0]])
N = 181  # a 180-degree, 1-degree scan like the classic logs


def _scans(step: float, count: int, seed: int = 5) -> list[tuple[tuple[float, float, float], np.ndarray]]:
    rc = Raycaster(CORRIDOR)
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        pose = (-10.0 + step * i, 0.2 * math.sin(0.3 * i), 0.05 * math.sin(0.5 * i))
        r = rc.cast_fan(pose[0], pose[1], pose[2] - math.pi / 2, math.pi / 180, N, 12.0)
        r = np.where(np.isfinite(r), r + rng.normal(0.0, 0.01, N), 0.0)  # 1 cm range noise, no return = 0
        out.append((pose, r))
    return out


def _run(config: MapperConfig, step: float, count: int) -> tuple[float, float]:
    """(max consecutive relation error m, final position error m) on exact odometry."""
    angles = np.linspace(-math.pi / 2, math.pi / 2, N)
    m = OnboardMapper(config)
    scans = _scans(step, count)
    est = [m.add_scan_odometry(0.5 * i, r, angles, pose).pose for i, (pose, r) in enumerate(scans)]
    truth = [p for p, _ in scans]
    worst = 0.0
    for i in range(count - 1):
        e = relative(relative(truth[i], truth[i + 1]), relative(est[i], est[i + 1]))
        worst = max(worst, math.hypot(e[0], e[1]))
    end = relative(est[0], est[-1])
    ref = relative(truth[0], truth[-1])
    return worst, math.hypot(end[0] - ref[0], end[1] - ref[1])


def test_matching_on_exact_odometry_does_not_slide_along_a_corridor() -> None:
    worst, final = _run(MapperConfig(), step=0.5, count=30)
    assert worst < 0.05  # measured 0.03 m
    assert final < 0.05  # measured 0.03 m over 14.5 m


def test_without_the_motion_prior_the_corridor_slides() -> None:
    # The bound above is meaningful: the same matcher with a near-flat prior and no local refinement
    # (the former default) moves the exact odometry along the corridor.
    old = MapperConfig(refine_local=False, match=MatchConfig(prior_weight=0.0005))
    worst, final = _run(old, step=0.5, count=30)
    assert worst > 0.05 or final > 0.05  # measured: it slides metres
