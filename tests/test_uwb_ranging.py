"""The ranging error model: seeded, each error kind where and how often the profile says."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fleetlink.field.plans import load_plan
from fleetlink.positioning.anchors import Anchor, anchors_from
from fleetlink.positioning.ranging import NoiseProfile, RangingModel

ANCHORS = tuple(Anchor(f"A{i}", x, y, 2.5) for i, (x, y) in enumerate([(0, 0), (10, 0), (10, 8), (0, 8)]))


def many(profile: NoiseProfile, n: int = 2000, walls=None, at=(3.0, 2.0), seed: int = 1):
    model = RangingModel(ANCHORS, profile, np.random.default_rng(seed), walls=walls)
    true = dict(zip([a.id for a in ANCHORS], model.true_distances(*at, 0.3), strict=True))
    out = [r for _ in range(n) for r in model.measure(*at, 0.3)]
    return out, true


def test_seeded_and_repeatable() -> None:
    a, _ = many(NoiseProfile.realistic(), 200, seed=4)
    b, _ = many(NoiseProfile.realistic(), 200, seed=4)
    c, _ = many(NoiseProfile.realistic(), 200, seed=5)
    assert a == b and a != c


def test_exact_without_noise() -> None:
    out, true = many(NoiseProfile.none(), 3)
    assert len(out) == 12
    assert all(r.distance_m == pytest.approx(true[r.anchor_id]) for r in out)


def test_los_noise_is_gaussian_with_sigma() -> None:
    out, true = many(NoiseProfile.los())
    err = np.array([r.distance_m - true[r.anchor_id] for r in out])
    assert len(out) == 8000 and not any(r.nlos or r.outlier for r in out)
    assert abs(err.mean()) < 0.01 and err.std() == pytest.approx(0.1, rel=0.05)


def test_realistic_rates_and_positive_nlos_bias() -> None:
    out, true = many(NoiseProfile.realistic(), 5000)
    n = 5000 * 4
    assert len(out) / n == pytest.approx(0.95, abs=0.01)  # 5 % dropouts
    nlos = [r for r in out if r.nlos and not r.outlier]
    assert len(nlos) / len(out) == pytest.approx(0.10, abs=0.01)
    bias = np.mean([r.distance_m - true[r.anchor_id] for r in nlos])
    assert bias == pytest.approx(0.3, abs=0.03)  # always positive, mean 0.3 m
    outliers = [r for r in out if r.outlier]
    assert len(outliers) / len(out) == pytest.approx(0.01, abs=0.004)
    jumps = [abs(r.distance_m - true[r.anchor_id]) for r in outliers]
    assert min(jumps) > 0.2 and max(jumps) < 6.5


def test_antenna_delay_is_a_constant_offset() -> None:
    out, true = many(NoiseProfile(sigma_m=0.0, antenna_delay_m=0.25), 5)
    assert all(r.distance_m - true[r.anchor_id] == pytest.approx(0.25) for r in out)


def test_out_of_range_anchors_never_answer() -> None:
    out, _ = many(NoiseProfile(sigma_m=0.0, max_range_m=5.0), 3)
    assert {r.anchor_id for r in out} == {"A0"}


def test_nlos_zones() -> None:
    zone = ((2.0, 1.0), (4.0, 1.0), (4.0, 3.0), (2.0, 3.0))
    inside, _ = many(NoiseProfile(sigma_m=0.0, nlos_zones=(zone,)), 50, at=(3.0, 2.0))
    outside, _ = many(NoiseProfile(sigma_m=0.0, nlos_zones=(zone,)), 50, at=(7.0, 6.0))
    assert all(r.nlos for r in inside) and not any(r.nlos for r in outside)


def test_walls_block_line_of_sight_on_the_office_plan() -> None:
    plan = load_plan("office")
    anchors = anchors_from(plan.anchors)
    model = RangingModel(anchors, NoiseProfile(sigma_m=0.0, use_walls=True), np.random.default_rng(0), plan.segments())
    blocked = dict(zip([a.id for a in anchors], model.blocked(14.0, 9.75).tolist(), strict=True))
    # In the corridor: the corridor anchors A5/A6 are in sight, the corner anchors behind room walls.
    assert not blocked["A5"] and not blocked["A6"]
    assert blocked["A1"] and blocked["A3"]
    ranges = model.measure(14.0, 9.75, 0.3)
    true = dict(zip([a.id for a in anchors], model.true_distances(14.0, 9.75, 0.3), strict=True))
    for r in ranges:
        assert r.nlos == blocked[r.anchor_id]
        assert r.distance_m >= true[r.anchor_id] - 1e-12  # NLOS only ever adds


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"sigma_m": -0.1}, "sigma_m"),
        ({"nlos_ratio": 1.5}, "nlos_ratio"),
        ({"outlier_min_m": 6.0}, "outlier_min_m"),
        ({"sigma_m": math.nan}, "sigma_m"),
        ({"nlos_zones": (((0.0, 0.0), (1.0, 1.0)),)}, "nlos_zones"),
    ],
)
def test_bad_profiles_are_refused(kwargs, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        NoiseProfile(**kwargs)


def test_anchor_rejects_non_finite_and_duplicates() -> None:
    with pytest.raises(ValueError, match="finite"):
        Anchor("X", math.inf, 0.0, 0.0)
    with pytest.raises(ValueError, match="twice"):
        anchors_from([("A", 0, 0, 0), ("A", 1, 1, 1)])
