"""Scan preparation and adaptive segmentation on constructed scans."""

from __future__ import annotations

import math

import numpy as np

from fleetlink.agent.mapping.scan import filter_segments, prepare, segment_labels, surface_fill, thin, to_points


def test_prepare_drops_invalid_and_marks_max_range_as_no_hit() -> None:
    r = np.array([1.0, np.nan, 0.0, -1.0, 0.05, np.inf, 12.0, 30.0, 2.0])
    a = np.linspace(0, 1, r.size)
    rr, aa, hit = prepare(r, a, min_range=0.1, max_range=12.0)
    assert rr.tolist() == [1.0, 12.0, 12.0, 2.0]
    assert hit.tolist() == [True, False, False, True]
    assert np.allclose(aa, a[[0, 6, 7, 8]])


def test_two_walls_at_different_depths_split_by_distance() -> None:
    # A wall at x = 2 (beams -30..-1 deg) and one at x = 4 (0..30 deg): one depth jump.
    ang = np.radians(np.arange(-30, 31, 1.0))
    r = np.where(ang < 0, 2.0 / np.cos(ang), 4.0 / np.cos(ang))
    labels = segment_labels(to_points(r, ang), eps=0.3, tau=5.0)
    assert labels.max() == 1
    assert (labels[ang < 0] == 0).all() and (labels[ang >= 0] == 1).all()


def test_ratio_rule_splits_a_small_jump_that_eps_misses() -> None:
    # Points 1 cm apart along a line, then a 20 cm step (under eps = 0.3), then 1 cm apart again.
    a = np.column_stack((np.arange(10) * 0.01, np.zeros(10)))
    b = np.column_stack((0.09 + 0.2 + np.arange(10) * 0.01, np.zeros(10)))
    pts = np.vstack((a, b))
    assert segment_labels(pts, eps=0.3, tau=math.inf).max() == 0  # distance rule alone: one segment
    labels = segment_labels(pts, eps=0.3, tau=5.0)
    assert labels.tolist() == [0] * 10 + [1] * 10


def test_evenly_spaced_points_stay_one_segment_and_isolated_points_are_noise() -> None:
    ang = np.radians(np.arange(0, 90, 1.0))
    pts = to_points(np.full(ang.size, 3.0), ang)  # an arc: equal gaps
    assert segment_labels(pts, 0.3, 5.0).max() == 0
    # A stray return in the middle of the arc forms its own tiny segment, which is filtered.
    r = np.full(ang.size, 3.0)
    r[45] = 1.0
    labels = segment_labels(to_points(r, ang), 0.3, 5.0)
    keep = filter_segments(labels, min_points=3)
    assert not keep[45] and keep.sum() == ang.size - 1


def test_thin_keeps_one_point_per_cell() -> None:
    pts = np.array([[0.01, 0.01], [0.02, 0.02], [0.5, 0.5], [0.51, 0.52], [1.0, 0.0]])
    assert thin(pts, 0.1).tolist() == [[0.01, 0.01], [0.5, 0.5], [1.0, 0.0]]


def test_thin_keeps_the_first_point_of_each_cell_in_scan_order() -> None:
    """Against np.unique's first occurrences: the first point (in scan order) of every cell, in scan order."""
    rng = np.random.default_rng(6)
    pts = rng.uniform(-3.0, 3.0, (500, 2))
    keys = np.floor(pts / 0.25).astype(np.int64)
    _, first = np.unique(keys[:, 0] * 1_000_003 + keys[:, 1], return_index=True)
    assert np.array_equal(thin(pts, 0.25), pts[np.sort(first)])
    assert thin(pts[:1], 0.25).tolist() == pts[:1].tolist()


def test_surface_fill_puts_points_on_a_far_wall_between_its_beams() -> None:
    # A wall at x = 10 seen by 1-degree beams: hits 0.17 m apart, filled every 5 cm on the wall itself.
    ang = np.radians(np.arange(-10, 11, 1.0))
    r = 10.0 / np.cos(ang)
    fr, fa = surface_fill(r, ang, np.ones(r.size, dtype=bool), 0.5, 0.05, 0.1, 0.05)
    pts = to_points(fr, fa)
    assert np.allclose(pts[:, 0], 10.0)
    ys = np.sort(np.concatenate((pts[:, 1], 10.0 * np.tan(ang))))
    assert np.diff(ys).max() <= 0.05 + 1e-9  # no gap wider than a cell left
    assert fr.size == 20 * 3  # 0.175 m gaps: three points strictly between each pair


def test_surface_fill_bridges_no_depth_jump_no_miss_and_no_wide_gap() -> None:
    ang = np.radians(np.arange(0, 8, 1.0))
    # Wall at 3 m, then a beam that returned nothing, then the same wall, then a wall 2 m behind.
    r = np.array([3.0, 3.0, 3.0, 12.0, 3.0, 3.0, 5.0, 5.0])
    hit = np.array([True, True, True, False, True, True, True, True])
    _fr, fa = surface_fill(r, ang, hit, 0.5, 0.05, 0.1, 0.05)
    # Only (0,1), (1,2), (4,5) and (6,7) are one surface: each gets its in-between points.
    between = np.degrees(fa)
    for lo, hi in ((2, 4), (5, 6)):
        assert not ((between > lo) & (between < hi)).any(), (lo, hi)
    assert ((between > 6) & (between < 7)).sum() == 1  # 5 m at 1 degree: 0.087 m, one point between
    # Too far apart (> max_gap), or off: nothing.
    assert surface_fill(r * 10, ang, hit, 0.5, 0.05, 0.1, 0.05)[0].size == 0
    assert surface_fill(r, ang, hit, 0.0, 0.05, 0.1, 0.05)[0].size == 0
    empty = np.zeros(0)
    assert surface_fill(empty, empty, np.zeros(0, dtype=bool), 0.5, 0.05, 0.1, 0.05)[0].size == 0


def test_prepare_turns_a_sector_with_no_return_into_free_beams_and_ignores_dropouts() -> None:
    """The RPLIDAR's 0 (and ROS's +inf) is "nothing within range": in a run of ``missing_run`` it is a
    free beam ``missing_ray`` long; a shorter run (a dark spot on a wall) says nothing."""
    a = np.radians(np.arange(12, dtype=np.float64))
    r = np.array([2.0, 0.0, 2.0, 0.0, 0.0, 0.0, np.inf, 0.0, 2.5, 0.0, 0.0, np.nan])
    rr, aa, hit = prepare(r, a, 0.15, 12.0)  # off: every no-return dropped, as before
    assert list(rr) == [2.0, 2.0, 2.5] and hit.all()
    rr, aa, hit = prepare(r, a, 0.15, 12.0, missing_ray=3.0, missing_run=3)
    assert list(np.degrees(aa).round()) == [0, 2, 3, 4, 5, 6, 7, 8]  # the run 3-7 kept, lone 1 and 9-10 not
    assert list(rr) == [2.0, 2.0, 3.0, 3.0, 3.0, 3.0, 3.0, 2.5]
    assert list(hit) == [True, True, False, False, False, False, False, True]
    rr, _, hit = prepare(r, a, 0.15, 2.2, missing_ray=3.0, missing_run=3)  # never beyond max_range
    assert rr.max() == 2.2 and not hit[2:7].any()
