"""Submaps drawn for matching with each scan's surfaces filled between neighbouring hits
(``CloserConfig.fill_max_gap``, ``scan.surface_fill``). In a hall, 1-degree beams draw the far walls
as dotted lines, sparser than the likelihood field's blur; a node then scores under the gate on a
submap of the very place it stands in, and no loop closes (the Acapulco convention hall's log: 1
check of 414 passed)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from fleetlink.agent.mapping.closure import Check, CloserConfig, NodeScan, draw_submap, open_space, run_check
from fleetlink.agent.mapping.grid import GridConfig
from fleetlink.agent.mapping.matcher import field_score
from fleetlink.field.raycast import Raycaster
from fleetlink.shared.se2 import relative
from tests.harness.scans import node_scan

# A 36 x 24 m hall with two stands in it: most walls 10-18 m from the lidar.
HALL = np.array(
    [
        [-18.0, -12.0, 18.0, -12.0],
        [18.0, -12.0, 18.0, 12.0],
        [18.0, 12.0, -18.0, 12.0],
        [-18.0, 12.0, -18.0, -12.0],
        [-9.0, -12.0, -9.0, -8.0],
        [6.0, 12.0, 6.0, 9.0],
        [18.0, 3.0, 14.0, 3.0],
        [-18.0, -2.0, -15.0, -2.0],
        # two stands nearer by
        [4.0, -3.0, 4.0, -1.5],
        [4.0, -1.5, 5.0, -1.5],
        [-5.0, 3.0, -3.5, 3.0],
        [-3.5, 3.0, -3.5, 4.0],
    ]
)
N = 360


def _scan_at(x: float, y: float, theta: float, walls: np.ndarray = HALL) -> NodeScan:
    angles = np.linspace(-math.pi, math.pi, N, endpoint=False)
    ranges = Raycaster(walls).cast_fan(x, y, theta - math.pi, 2.0 * math.pi / N, N, 30.0)
    return node_scan(ranges, angles, 30.0)


POSES = [(-1.0, -0.5, 0.0), (-0.4, -0.3, 0.2), (0.3, 0.0, 0.35), (0.9, 0.4, 0.5)]
NODE = (0.2, 1.2, -0.6)  # the revisit: a pose inside the submap's area, turned away


def _parts() -> tuple[tuple[tuple[float, float, float], NodeScan], ...]:
    anchor = POSES[0]
    return tuple((relative(anchor, p), _scan_at(*p)) for p in POSES)


def test_far_walls_filled_lift_a_true_match_over_the_gate() -> None:
    config = CloserConfig()  # the hall's walls are seen 5 m off and more: its submaps are filled by default
    scan = _scan_at(*NODE)
    truth = relative(POSES[0], NODE)
    filled = draw_submap(_parts(), GridConfig(), config)
    dotted = draw_submap(_parts(), GridConfig(), replace(config, fill_max_gap=0.0))
    on_filled = field_score(filled.grid, scan.match_points, truth)
    on_dotted = field_score(dotted.grid, scan.match_points, truth)
    assert on_filled >= config.min_score > on_dotted, (on_filled, on_dotted)

    guess = (truth[0] + 0.4, truth[1] - 0.3, truth[2] + math.radians(4.0))
    verdicts = {}
    for name, cfg in (("filled", config), ("dotted", replace(config, fill_max_gap=0.0))):
        check = Check(
            3, 0, 0, scan, guess, (1.0, math.radians(10.0)), None, _parts(), cfg, GridConfig(), (0.0, 0.0, 0.0)
        )
        verdicts[name] = run_check(check)
    assert verdicts["dotted"].outcome == "score"
    found = verdicts["filled"].closure
    assert verdicts["filled"].outcome == "accepted" and found is not None
    assert math.dist(found.z[:2], truth[:2]) < 0.05 and abs(found.z[2] - truth[2]) < math.radians(1.0)


def test_a_filled_drawing_is_deterministic_and_fill_is_validated() -> None:
    a = draw_submap(_parts(), GridConfig(), CloserConfig())
    b = draw_submap(_parts(), GridConfig(), CloserConfig())
    assert a.filled
    assert np.array_equal(a.grid.field, b.grid.field) and a.grid.origin == b.grid.origin
    for name in ("fill_max_gap", "fill_from_range", "fill_depth_share", "fill_depth_m"):
        for bad in (-0.1, math.nan, math.inf):
            try:
                CloserConfig(**{name: bad})
            except ValueError as e:
                assert name in str(e)
            else:
                raise AssertionError(f"{name}={bad} accepted")


def test_a_large_correction_asks_a_higher_score() -> None:
    """``large_min_score``: a fresh match moving its node more than ``confirm_above`` must score this much;
    the same match found near the guess needs only ``min_score``."""
    scan = _scan_at(*NODE)
    truth = relative(POSES[0], NODE)
    strict = CloserConfig(large_min_score=0.999)  # above what the true match scores here (~0.99)

    def verdict(off: float, cfg: CloserConfig) -> str:
        guess = (truth[0] + off, truth[1], truth[2])
        check = Check(
            3, 0, 0, scan, guess, (1.5, math.radians(10.0)), None, _parts(), cfg, GridConfig(), (0.0, 0.0, 0.0)
        )
        return run_check(check).outcome

    assert verdict(0.2, strict) == "accepted"
    assert verdict(1.0, strict) == "score"
    assert verdict(1.0, CloserConfig()) == "accepted"
    for name in ("large_min_score", "large_min_score_unfilled"):
        with pytest.raises(ValueError, match=name):
            CloserConfig(**{name: 1.5})


# A 5 x 4 m office: walls 1-3 m off, 1-degree beams 2-5 cm apart, already solid under the field's blur.
OFFICE = np.array(
    [
        [-2.5, -2.0, 2.5, -2.0],
        [2.5, -2.0, 2.5, 2.0],
        [2.5, 2.0, -2.5, 2.0],
        [-2.5, 2.0, -2.5, -2.0],
        [0.5, 2.0, 0.5, 1.0],
    ]
)


def test_only_submaps_that_saw_far_walls_are_filled() -> None:
    """An office's submap is drawn as seen unless every submap is asked for (``open_space``); the hall's
    is filled. Drawn as seen, the field is the one an unfilled closer draws, to the bit."""
    poses = [(-1.0, -0.5, 0.0), (-0.5, -0.3, 0.3), (0.0, 0.0, 0.6)]
    office = tuple((relative(poses[0], p), _scan_at(*p, OFFICE)) for p in poses)
    default = draw_submap(office, GridConfig(), CloserConfig())
    assert not default.filled
    unfilled = draw_submap(office, GridConfig(), CloserConfig(fill_max_gap=0.0))
    assert np.array_equal(default.grid.field, unfilled.grid.field)
    everywhere = draw_submap(office, GridConfig(), open_space())
    assert everywhere.filled and not np.array_equal(everywhere.grid.field, unfilled.grid.field)
    assert draw_submap(_parts(), GridConfig(), CloserConfig()).filled
    assert not draw_submap(_parts(), GridConfig(), CloserConfig(fill_from_range=50.0)).filled

    # ``large_min_score`` is asked only of filled submaps: a large correction in the office, drawn as
    # seen, needs ``large_min_score_unfilled``; filled (``open_space``), the higher score.
    node = (-0.2, 0.4, 0.9)
    scan, truth = _scan_at(*node, OFFICE), relative(poses[0], node)
    guess = (truth[0] + 0.8, truth[1], truth[2])
    outcome = {}
    for name, c in (("default", CloserConfig()), ("everywhere", open_space())):
        strict = replace(c, large_min_score=0.999)
        check = Check(
            3, 0, 0, scan, guess, (1.5, math.radians(10.0)), None, office, strict, GridConfig(), (0.0, 0.0, 0.0)
        )
        result = run_check(check)
        outcome[name] = result.outcome
        if result.closure is not None:
            assert math.dist(result.closure.z[:2], truth[:2]) < 0.05
    assert outcome == {"default": "accepted", "everywhere": "score"}, outcome
    strict = replace(CloserConfig(), large_min_score_unfilled=0.999)  # above what the office's match scores
    check = Check(3, 0, 0, scan, guess, (1.5, math.radians(10.0)), None, office, strict, GridConfig(), (0.0, 0.0, 0.0))
    assert run_check(check).outcome == "score"
    near = replace(check, guess=(truth[0] + 0.2, truth[1], truth[2]))  # a small correction: min_score alone
    assert run_check(near).outcome == "accepted"
