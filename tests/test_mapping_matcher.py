"""The scan matcher recovers a known offset; the mapper falls back to the guess when the match is poor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fleetlink.agent.mapping.mapper import MapperConfig, OnboardMapper
from fleetlink.field.raycast import Raycaster

ROOM = np.array(
    [
        [0.0, 0.0, 8.0, 0.0],
        [8.0, 0.0, 8.0, 5.0],
        [8.0, 5.0, 0.0, 5.0],
        [0.0, 5.0, 0.0, 0.0],
        [3.0, 2.0, 3.6, 2.0],  # a box: breaks the room's symmetry
        [3.6, 2.0, 3.6, 2.5],
        [3.6, 2.5, 3.0, 2.5],
        [3.0, 2.5, 3.0, 2.0],
        [6.0, 4.0, 6.5, 3.2],  # a slanted cabinet
    ]
)
ANGLES = np.linspace(0.0, 2 * math.pi, 360, endpoint=False)


def _scan(rc: Raycaster, pose: tuple[float, float, float]) -> np.ndarray:
    step = 2 * math.pi / 360
    r = rc.cast_fan(pose[0], pose[1], pose[2], step, 360, 12.0)
    return np.where(np.isfinite(r), r, 0.0)


@pytest.mark.parametrize("offset", [(0.2, -0.15, 0.08), (-0.25, 0.1, -0.2), (0.05, 0.05, 0.0)])
def test_matcher_recovers_a_known_offset(offset: tuple[float, float, float]) -> None:
    rc = Raycaster(ROOM)
    m = OnboardMapper()
    first = (2.0, 1.2, 0.3)
    m.add_scan(0.0, _scan(rc, first), ANGLES, first)
    true = (2.4, 1.5, 0.45)
    guess = (true[0] + offset[0], true[1] + offset[1], true[2] + offset[2])
    res = m.add_scan(0.1, _scan(rc, true), ANGLES, guess)
    assert res.matched
    # Sub-cell: the Gauss-Newton refinement interpolates the field.
    assert math.hypot(res.pose[0] - true[0], res.pose[1] - true[1]) < 0.02
    assert abs(res.pose[2] - true[2]) < math.radians(0.5)


def test_without_matching_the_guess_is_kept() -> None:
    rc = Raycaster(ROOM)
    m = OnboardMapper(MapperConfig(matching=False))
    m.add_scan(0.0, _scan(rc, (2.0, 1.2, 0.3)), ANGLES, (2.0, 1.2, 0.3))
    res = m.add_scan(0.1, _scan(rc, (2.4, 1.5, 0.45)), ANGLES, (2.6, 1.4, 0.5))
    assert res.pose == pytest.approx((2.6, 1.4, 0.5))
    assert not res.matched


def test_poor_match_falls_back_to_the_guess() -> None:
    rc = Raycaster(ROOM)
    m = OnboardMapper()
    m.add_scan(0.0, _scan(rc, (2.0, 1.2, 0.3)), ANGLES, (2.0, 1.2, 0.3))
    # A scan of somewhere else entirely (a different room) cannot match this map: keep the guess.
    other = Raycaster(np.array([[0.0, 0.0, 1.5, 0.0], [1.5, 0.0, 1.5, 20.0], [1.5, 20.0, 0.0, 20.0], [0, 20, 0, 0]]))
    guess = (2.4, 1.5, 0.45)
    res = m.add_scan(0.1, _scan(other, (0.7, 10.0, 0.0)), ANGLES, guess)
    assert not res.matched
    assert res.pose == pytest.approx(guess)
    assert m.fallbacks == 1


def test_empty_and_nonfinite_input() -> None:
    m = OnboardMapper()
    res = m.add_scan(0.0, np.zeros(10), np.linspace(0, 1, 10), (0.0, 0.0, 0.0))
    assert not res.integrated and m.grid.empty
    with pytest.raises(ValueError):
        m.add_scan(0.1, np.ones(10), np.linspace(0, 1, 10), (math.nan, 0.0, 0.0))
    assert m.rejected == 1
