"""Multilateration: exact recovery, minimal geometry, dropped anchors, degenerate geometry, outliers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fleetlink.field.plans import load_plan
from fleetlink.positioning.anchors import Anchor, anchors_from
from fleetlink.positioning.ranging import NoiseProfile, Range, RangingModel
from fleetlink.positioning.solver import FixStatus, Loss, quality_from_sd, solve, solve_linear

ROOM = (
    Anchor("A", 0.0, 0.0, 2.5),
    Anchor("B", 10.0, 0.0, 2.5),
    Anchor("C", 10.0, 8.0, 2.5),
    Anchor("D", 0.0, 8.0, 2.5),
)
TAG_Z = 0.3


def exact(anchors: tuple[Anchor, ...], x: float, y: float, z: float = TAG_Z) -> list[Range]:
    return [Range(a.id, math.dist((x, y, z), (a.x, a.y, a.z))) for a in anchors]


@pytest.mark.parametrize("fn", [solve, solve_linear])
@pytest.mark.parametrize(("x", "y"), [(3.0, 2.0), (9.5, 7.5), (5.0, 4.0), (0.1, 7.9)])
def test_exact_recovery_without_noise(fn, x: float, y: float) -> None:
    sol = fn(ROOM, exact(ROOM, x, y), TAG_Z)
    assert sol.status is FixStatus.OK
    assert sol.x == pytest.approx(x, abs=1e-4) and sol.y == pytest.approx(y, abs=1e-4)
    assert sol.z == TAG_Z
    assert sol.residual_rms_m < 1e-3
    assert sol.used == ("A", "B", "C", "D")
    assert sol.quality == 100


def test_three_anchors_suffice() -> None:
    three = ROOM[:3]
    sol = solve(three, exact(three, 6.0, 3.0), TAG_Z)
    assert sol.ok and math.hypot(sol.x - 6.0, sol.y - 3.0) < 1e-4
    assert len(sol.used) == 3


def test_a_dropped_anchor_still_gives_the_fix() -> None:
    ranges = [r for r in exact(ROOM, 7.0, 5.0) if r.anchor_id != "C"]
    sol = solve(ROOM, ranges, TAG_Z)
    assert sol.ok and math.hypot(sol.x - 7.0, sol.y - 5.0) < 1e-4
    assert "C" not in sol.used


def test_too_few_ranges_is_refused() -> None:
    sol = solve(ROOM, exact(ROOM, 7.0, 5.0)[:2], TAG_Z)
    assert sol.status is FixStatus.TOO_FEW_RANGES
    assert math.isnan(sol.x) and sol.quality == 0 and math.isinf(sol.sd_x)


def test_unknown_anchors_nan_and_negative_ranges_are_ignored() -> None:
    ranges = [*exact(ROOM, 4.0, 4.0)[:3], Range("ghost", 3.0), ("D", math.nan), ("D", -1.0)]
    sol = solve(ROOM, ranges, TAG_Z)
    assert sol.ok and sol.used == ("A", "B", "C")
    assert solve(ROOM, [("ghost", 1.0), ("A", math.inf), ("B", 2.0)], TAG_Z).status is FixStatus.TOO_FEW_RANGES


@pytest.mark.parametrize("fn", [solve, solve_linear])
def test_collinear_anchors_give_a_clear_status_not_a_wild_fix(fn) -> None:
    line = tuple(Anchor(f"L{i}", 4.0 * i, 1.0, 2.5) for i in range(4))
    sol = fn(line, exact(line, 5.0, 4.0), TAG_Z)
    assert sol.status is FixStatus.DEGENERATE_GEOMETRY
    assert math.isnan(sol.x) and math.isnan(sol.y) and sol.quality == 0
    # Nearly collinear (5 mm off the line over 12 m) is just as ambiguous.
    bent = (*line[:3], Anchor("L3", 12.0, 1.005, 2.5))
    assert fn(bent, exact(bent, 5.0, 4.0), TAG_Z).status is FixStatus.DEGENERATE_GEOMETRY


def test_one_outlier_range_is_handled_by_the_robust_loss() -> None:
    anchors = (*ROOM, Anchor("E", 5.0, -1.0, 2.5), Anchor("F", 5.0, 9.0, 2.5))
    ranges = exact(anchors, 3.0, 5.0)
    ranges[1] = Range("B", ranges[1].distance_m + 3.0, outlier=True)
    robust = solve(anchors, ranges, TAG_Z)
    linear = solve_linear(anchors, ranges, TAG_Z)
    l2 = solve(anchors, ranges, TAG_Z, loss=Loss.L2)
    err = math.hypot(robust.x - 3.0, robust.y - 5.0)
    assert robust.ok and err < 0.03  # Cauchy keeps a sliver of pull: 1 cm here
    assert "B" not in robust.used and len(robust.used) == 5
    assert robust.quality < 100  # it trusted 5 of 6
    assert math.hypot(linear.x - 3.0, linear.y - 5.0) > 10 * max(err, 0.03)
    assert math.hypot(l2.x - 3.0, l2.y - 5.0) > 10 * max(err, 0.03)


def test_previous_fix_is_a_start_not_an_anchor() -> None:
    first = solve(ROOM, exact(ROOM, 2.0, 2.0), TAG_Z)
    # The robot moved far since: the old fix must not hold the new one back.
    sol = solve(ROOM, exact(ROOM, 8.0, 6.0), TAG_Z, previous=first)
    assert sol.ok and math.hypot(sol.x - 8.0, sol.y - 6.0) < 1e-4
    assert solve(ROOM, exact(ROOM, 8.0, 6.0), TAG_Z, previous=(8.1, 5.9)).ok


def test_covariance_follows_geometry() -> None:
    """Inside the anchors sd is small and balanced; far outside along x it grows across the rays."""
    rng = np.random.default_rng(3)
    model = RangingModel(ROOM, NoiseProfile.los(), rng)
    inside = solve(ROOM, model.measure(5.0, 4.0, TAG_Z), TAG_Z)
    outside = solve(ROOM, model.measure(40.0, 4.0, TAG_Z), TAG_Z)
    assert inside.ok and outside.ok
    assert 0.02 < inside.sd_x < 0.15 and 0.02 < inside.sd_y < 0.15
    assert outside.sd_y > 3 * inside.sd_y
    assert outside.quality < inside.quality


def test_quality_scale() -> None:
    assert quality_from_sd(0.05, 0.05) == 100
    assert quality_from_sd(0.2, 0.2) == 50
    assert quality_from_sd(1.0, 1.0) == 10
    assert quality_from_sd(0.05, 0.05, inlier_share=0.5) == 50
    assert quality_from_sd(math.inf, 1.0) == 0


def test_office_los_accuracy_and_robust_beats_linear_on_realistic_noise() -> None:
    """A small version of bench/uwb.py: the goals hold on a few hundred random office positions."""
    anchors = anchors_from(load_plan("office").anchors)
    rng = np.random.default_rng(11)
    pts = rng.uniform((0.5, 0.5), (39.5, 19.5), size=(300, 2))
    errors: dict[str, list[float]] = {}
    for name, profile in (("los", NoiseProfile.los()), ("realistic", NoiseProfile.realistic())):
        model = RangingModel(anchors, profile, np.random.default_rng(5))
        for label, fn in (("robust", solve), ("linear", solve_linear)):
            errs = errors.setdefault(f"{name}-{label}", [])
            model.rng = np.random.default_rng(5)
            for x, y in pts:
                sol = fn(anchors, model.measure(x, y, TAG_Z), TAG_Z)
                assert sol.ok
                errs.append(math.hypot(sol.x - x, sol.y - y))

    def rmse(k: str) -> float:
        return float(np.sqrt(np.mean(np.square(errors[k]))))

    assert rmse("los-robust") <= 0.12
    assert rmse("realistic-robust") <= 0.6 * rmse("realistic-linear")
