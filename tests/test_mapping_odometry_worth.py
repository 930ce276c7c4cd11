"""The front end learns what the odometry is worth (``MapperConfig.odom_learn_*``): odometry whose
steps agree with the scans holds the refinement tighter; odometry as poor as the default prior says,
or steps too short to tell, leave the prior as it is."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from fleetlink.agent.mapping.mapper import MapperConfig, OnboardMapper, compose, relative
from fleetlink.field.raycast import Raycaster

# A room with a few pillars and alcoves, so every step is well posed.
ROOM = np.array(
    [
        [0.0, 0.0, 10.0, 0.0],
        [10.0, 0.0, 10.0, 7.0],
        [10.0, 7.0, 0.0, 7.0],
        [0.0, 7.0, 0.0, 0.0],
        [4.0, 3.0, 6.0, 3.0],
        [6.0, 3.0, 6.0, 4.0],
        [6.0, 4.0, 4.0, 4.0],
        [4.0, 4.0, 4.0, 3.0],
        [1.5, 5.5, 2.0, 5.5],
        [2.0, 5.5, 2.0, 6.0],
        [8.0, 1.0, 8.5, 1.5],
        [8.5, 1.5, 8.0, 2.0],
    ]
)


def _path(step: float, laps: int = 2) -> list[tuple[float, float, float]]:
    """Round the middle block, ``step`` metres a scan, turning at the corners."""
    corners = [(2.0, 1.5), (8.0, 1.5), (8.0, 5.5), (2.0, 5.5)]
    out: list[tuple[float, float, float]] = []
    for _ in range(laps):
        for (x0, y0), (x1, y1) in zip(corners, corners[1:] + corners[:1], strict=True):
            heading = math.atan2(y1 - y0, x1 - x0)
            n = max(1, round(math.hypot(x1 - x0, y1 - y0) / step))
            out += [(x0 + (x1 - x0) * k / n, y0 + (y1 - y0) * k / n, heading) for k in range(n)]
    return out


def _run(step: float, heading_noise: float, config: MapperConfig, seed: int = 5) -> OnboardMapper:
    """The path mapped with odometry that is the truth plus ``heading_noise`` rad (sd) per step."""
    rng = np.random.default_rng(seed)
    rc = Raycaster(ROOM)
    mapper = OnboardMapper(config)
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    truth = _path(step)
    odom = truth[0]
    for i, pose in enumerate(truth):
        if i:
            inc = relative(truth[i - 1], pose)
            odom = compose(odom, (inc[0], inc[1], inc[2] + rng.normal(0.0, heading_noise)))
        ranges = rc.cast_fan(pose[0], pose[1], pose[2] - math.pi, 2 * math.pi / 360, 360, 12.0)
        ranges = ranges + rng.normal(0.0, 0.005, ranges.shape)
        mapper.add_scan_odometry(0.1 * i, ranges, angles, odom)
    return mapper


CONFIG = MapperConfig(closer=None, odom_learn_scans=20)


def test_odometry_that_agrees_with_the_scans_holds_the_refinement_tighter() -> None:
    mapper = _run(0.4, 0.0, CONFIG)
    assert mapper.odom_scale < 0.6
    assert mapper.odom_scale >= CONFIG.odom_learn_min_scale


def test_odometry_as_poor_as_the_default_prior_is_left_at_the_default() -> None:
    # 0.4 m steps: the default's heading sd is 0.01 + 0.035 * 0.4 rad, about 1.4 degrees.
    mapper = _run(0.4, math.radians(2.0), CONFIG)
    assert mapper.odom_scale == 1.0


def test_odometry_only_somewhat_better_than_the_default_is_left_at_the_default() -> None:
    # About a third of the default's sd: learned at ~0.7 of it, short of odom_learn_engage (0.5).
    mapper = _run(0.4, math.radians(0.5), CONFIG)
    assert mapper.odom_scale == 1.0
    # ... which, lowered, lets it hold the prior there instead.
    held = _run(0.4, math.radians(0.5), replace(CONFIG, odom_learn_engage=1.0))
    assert CONFIG.odom_learn_min_scale <= held.odom_scale < 1.0


def test_steps_too_short_to_tell_the_odometry_from_the_matcher_teach_nothing() -> None:
    # 0.1 m steps: the step adds less to the guess's sd than its fixed part (0.01 rad).
    mapper = _run(0.1, 0.0, CONFIG)
    assert mapper.odom_scale == 1.0


def test_learning_can_be_turned_off() -> None:
    mapper = _run(0.4, 0.0, MapperConfig(closer=None, odom_learn_scans=0))
    assert mapper.odom_scale == 1.0


@pytest.mark.parametrize(
    "bad",
    [
        {"odom_learn_scans": -1},
        {"odom_learn_margin": 0.0},
        {"odom_learn_min_scale": 0.0},
        {"odom_learn_min_scale": 0.6},
        {"odom_learn_engage": 1.5},
    ],
)
def test_bad_learning_settings_are_refused(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="odom_learn"):
        MapperConfig(**bad)  # type: ignore[arg-type]
