"""The ray caster (field.raycast) and the lidar model (field.lidar) against analytic geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fleetlink.field.floor import ray_cast
from fleetlink.field.lidar import LidarConfig, LidarModel, scan_source_for
from fleetlink.field.raycast import Raycaster

W, H = 6.0, 4.0
ROOM = np.array([(0, 0, W, 0), (W, 0, W, H), (W, H, 0, H), (0, H, 0, 0)], dtype=float)


def room_distance(x: float, y: float, a: np.ndarray) -> np.ndarray:
    """Analytic distance from inside the W x H room to its walls along bearings ``a``."""
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 1e-15, (W - x) / c, np.where(c < -1e-15, -x / c, np.inf))
        ty = np.where(s > 1e-15, (H - y) / s, np.where(s < -1e-15, -y / s, np.inf))
    return np.minimum(tx, ty)


def brute(segments: np.ndarray, circles: np.ndarray | None, x: float, y: float, a: float, rmax: float) -> float:
    d = ray_cast([tuple(s) for s in segments], x, y, a, math.inf)
    for cx, cy, r in [] if circles is None else circles:
        ox, oy, dx, dy = cx - x, cy - y, math.cos(a), math.sin(a)
        along, perp = ox * dx + oy * dy, ox * dy - oy * dx
        if r * r - perp * perp >= 0:
            h = math.sqrt(r * r - perp * perp)
            t = along - h if along - h >= 0 else along + h
            if t >= 0:
                d = min(d, t)
    return d if d <= rmax else math.inf


def clutter(rng: np.random.Generator, n: int) -> np.ndarray:
    segs = [tuple(s) for s in ROOM * 4]  # a 24 x 16 m hall
    while len(segs) < n:
        x, y, a, length = rng.uniform(0, 24), rng.uniform(0, 16), rng.uniform(0, 2 * math.pi), rng.uniform(0.2, 5)
        segs.append((x, y, x + length * math.cos(a), y + length * math.sin(a)))
    return np.array(segs[:n])


# -- ray caster: a known room -------------------------------------------------------------------


@pytest.mark.parametrize("n", [4, 9, 360, 1450])  # dense path (few rays) and span paths
def test_square_room_from_the_centre(n: int) -> None:
    rc = Raycaster(ROOM)
    a = np.linspace(-math.pi, math.pi, n, endpoint=False) + 0.01
    np.testing.assert_allclose(rc.cast(3.0, 2.0, a, 12.0), room_distance(3.0, 2.0, a), rtol=1e-12, atol=1e-12)
    shuffled = np.random.default_rng(0).permutation(a)  # the sorted general path
    np.testing.assert_allclose(rc.cast(3.0, 2.0, shuffled, 12.0), room_distance(3.0, 2.0, shuffled), rtol=1e-12)


@pytest.mark.parametrize(("count", "step"), [(1455, 2 * math.pi / 1454.5), (1500, 2 * math.pi / 1450), (10, 0.3)])
def test_fans_of_any_length(count: int, step: float) -> None:
    """A lidar turn may overlap itself by a sample (1455 samples of 2 pi / 1454.5) or more."""
    rc = Raycaster(ROOM)
    a = 0.7 + step * np.arange(count)
    np.testing.assert_allclose(rc.cast_fan(3.0, 2.0, 0.7, step, count, 12.0), room_distance(3.0, 2.0, a), rtol=1e-12)
    np.testing.assert_allclose(rc.cast(3.0, 2.0, a, 12.0), room_distance(3.0, 2.0, a), rtol=1e-12)


def test_cardinal_rays_parallel_to_walls() -> None:
    """Each cardinal ray is parallel to two walls: it must hit the wall ahead, not the parallel ones."""
    rc = Raycaster(ROOM)
    a = np.array([0.0, math.pi / 2, math.pi, -math.pi / 2])
    np.testing.assert_allclose(rc.cast(1.0, 1.0, a, 12.0), [5.0, 3.0, 1.0, 1.0], atol=1e-12)
    fan = rc.cast_fan(1.0, 1.0, 0.0, math.pi / 2, 4, 12.0)
    np.testing.assert_allclose(fan, [5.0, 3.0, 1.0, 1.0], atol=1e-12)


def test_ray_along_a_wall_line_misses_it() -> None:
    rc = Raycaster(np.array([(2.0, 0.0, 4.0, 0.0)]))
    assert math.isinf(rc.cast(0.0, 0.0, np.array([0.0]), 12.0)[0])  # collinear: parallel, no hit
    many = rc.cast(0.0, 0.0, np.linspace(0, 2 * math.pi, 2000, endpoint=False), 12.0)
    assert math.isinf(many[0])


def test_ray_through_corners_and_endpoints() -> None:
    rc = Raycaster(ROOM)
    corners = np.array([math.atan2(H - 2, W - 3), math.atan2(H - 2, -3), math.atan2(-2, -3), math.atan2(-2, W - 3)])
    np.testing.assert_allclose(rc.cast(3.0, 2.0, corners, 12.0), [math.hypot(3, 2)] * 4, rtol=1e-12)
    # a single free segment, aimed exactly at each endpoint, from the dense and the span paths
    seg = Raycaster(np.array([(1.0, 1.0, 1.0, 3.0)]))
    ends = np.array([math.atan2(1, 1), math.atan2(3, 1)])
    np.testing.assert_allclose(seg.cast(0.0, 0.0, ends, 12.0), [math.sqrt(2), math.sqrt(10)], rtol=1e-12)
    fan = seg.cast_fan(0.0, 0.0, ends[0], ends[1] - ends[0], 2, 12.0)
    np.testing.assert_allclose(fan, [math.sqrt(2), math.sqrt(10)], rtol=1e-12)
    many = np.concatenate([ends, np.linspace(-3, 3, 3000)])
    np.testing.assert_allclose(seg.cast(0.0, 0.0, many, 12.0)[:2], [math.sqrt(2), math.sqrt(10)], rtol=1e-12)


def test_max_range_and_nothing_in_reach() -> None:
    rc = Raycaster(ROOM)
    a = np.linspace(0, 2 * math.pi, 1450, endpoint=False)
    d = rc.cast(3.0, 2.0, a, 2.5)
    ref = room_distance(3.0, 2.0, a)
    assert np.all(np.isinf(d[ref > 2.5])) and np.allclose(d[ref <= 2.5], ref[ref <= 2.5])
    assert np.all(np.isinf(Raycaster(np.zeros((0, 4))).cast(0, 0, a, 12.0)))
    assert np.all(np.isinf(rc.cast(100.0, 100.0, a, 12.0)))  # everything culled
    assert rc.cast(3.0, 2.0, np.zeros((0,)), 12.0).shape == (0,)
    assert rc.cast(3.0, 2.0, np.zeros((3, 2)), 12.0).shape == (3, 2)


def test_circle_obstacle() -> None:
    rc = Raycaster(ROOM)
    circles = np.array([(5.0, 2.0, 0.5)])
    tangent = math.asin(0.5 / 2.0)
    a = np.array([0.0, 0.2, tangent - 1e-9, tangent + 1e-6, math.pi / 2])
    d = rc.cast(3.0, 2.0, a, 12.0, circles)
    assert d[0] == pytest.approx(1.5)  # straight at the centre: 2.0 - r
    assert d[1] == pytest.approx(2.0 * math.cos(0.2) - math.sqrt(0.25 - (2.0 * math.sin(0.2)) ** 2), rel=1e-12)
    assert d[2] == pytest.approx(math.sqrt(2.0**2 - 0.5**2), rel=1e-4)  # grazing
    assert d[3] == pytest.approx(3.0 / math.cos(tangent + 1e-6))  # just past it: the far wall
    assert d[4] == pytest.approx(2.0)  # the wall above, unaffected
    fan = rc.cast(3.0, 2.0, np.linspace(-math.pi, math.pi, 1450, endpoint=False), 12.0, circles)
    assert fan.min() == pytest.approx(1.5, abs=1e-3)
    # from inside a circle, a ray meets its rim on the way out
    assert rc.cast(5.0, 2.0, np.array([math.pi]), 12.0, circles)[0] == pytest.approx(0.5)
    # a circle beyond max_range is culled
    assert rc.cast(3.0, 2.0, np.array([0.0]), 1.0, circles)[0] == math.inf


def test_pose_on_a_segment_reads_zero() -> None:
    rc = Raycaster(np.array([(0.0, 0.0, 2.0, 0.0)]))
    d = rc.cast(1.0, 0.0, np.linspace(0.1, 6.0, 1000), 12.0)
    assert np.all(d == 0.0)


def test_set_segments_changes_the_geometry() -> None:
    rc = Raycaster(ROOM)
    a = np.linspace(0, 2 * math.pi, 1450, endpoint=False)
    before = rc.cast(1.0, 2.0, a, 12.0)
    door = np.vstack([ROOM, [(2.0, 0.0, 2.0, 4.0)]])  # a wall appears at x = 2
    rc.set_segments(door)
    assert rc.cast(1.0, 2.0, np.array([0.0]), 12.0)[0] == pytest.approx(1.0)
    rc.set_segments(ROOM)
    np.testing.assert_array_equal(rc.cast(1.0, 2.0, a, 12.0), before)
    assert rc.segments.shape == (4, 4)


@pytest.mark.parametrize("kind", ["fan", "fan-offset", "random", "few"])
def test_matches_brute_force_in_clutter(kind: str) -> None:
    rng = np.random.default_rng(["fan", "fan-offset", "random", "few"].index(kind))
    for _ in range(12):
        segs = clutter(rng, int(rng.integers(10, 200)))
        nc = int(rng.integers(0, 8))
        circles = np.column_stack([rng.uniform(0, 24, nc), rng.uniform(0, 16, nc), rng.uniform(0.1, 0.6, nc)])
        x, y, rmax = rng.uniform(0, 24), rng.uniform(0, 16), rng.uniform(2, 15)
        a: np.ndarray
        if kind == "fan":
            a = rng.uniform(-10, 10) + np.arange(1450) * 2 * math.pi / 1450
        elif kind == "fan-offset":
            a = rng.uniform(-1, 1) + np.arange(500) * 0.004  # less than a turn
        elif kind == "random":
            a = rng.uniform(-10, 10, 700)
        else:
            a = rng.uniform(-4, 4, 5)
        d = Raycaster(segs).cast(x, y, a, rmax, circles if nc else None)
        some = rng.choice(a.size, size=min(a.size, 60), replace=False)  # the scalar reference is slow
        d = d[some]
        ref = np.array([brute(segs, circles, x, y, ai, rmax) for ai in a[some]])
        assert np.array_equal(np.isinf(d), np.isinf(ref))
        fin = np.isfinite(ref)
        np.testing.assert_allclose(d[fin], ref[fin], rtol=1e-9, atol=1e-9)


def test_cast_is_fast_enough() -> None:
    """A 1450-ray turn against 300 segments: generous bound (the bench has the real numbers)."""
    import time

    rng = np.random.default_rng(3)
    rc = Raycaster(clutter(rng, 300))
    step = 2 * math.pi / 1450
    best = math.inf
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(20):
            rc.cast_fan(12.0, 8.0, rng.uniform(-3, 3), step, 1450, 12.0)
        best = min(best, (time.perf_counter() - t0) / 20)
    assert best < 0.005


# -- the lidar model ----------------------------------------------------------------------------


def test_noiseless_turn_matches_the_room() -> None:
    cfg = LidarConfig().noiseless()
    model = LidarModel(cfg, np.random.default_rng(0))
    angles, dist, qual = model.revolution(3.0, 2.0, 0.3, Raycaster(ROOM))
    assert angles.size == math.ceil(cfg.samples_per_revolution)  # 1455 at 5.5 Hz, 8000 samples/s
    assert np.all(np.diff(angles) > 0) and angles[0] == 0.0 and angles[-1] < 2 * math.pi
    np.testing.assert_allclose(dist, room_distance(3.0, 2.0, angles + 0.3), rtol=1e-12)
    assert qual.dtype == np.uint8 and np.all((qual >= 1) & (qual <= 63))
    near, far = np.argmin(dist), np.argmax(dist)
    assert qual[near] > qual[far]


def test_mount_offset() -> None:
    cfg = LidarConfig(mount_x=0.5, mount_y=0.0, mount_yaw=math.pi / 2).noiseless()
    angles, dist, _ = LidarModel(cfg, np.random.default_rng(0)).revolution(3.0, 2.0, 0.0, Raycaster(ROOM))
    # the lidar sits at (3.5, 2.0) facing +y: its forward ray reads 2.0, its left ray (towards -x) 3.5
    assert dist[0] == pytest.approx(2.0)
    i = int(np.argmin(np.abs(angles - math.pi / 2)))
    assert dist[i] == pytest.approx(3.5, rel=1e-3)


def test_out_of_range_returns_are_zero() -> None:
    cfg = LidarConfig(min_range=0.15, max_range=3.2).noiseless()
    angles, dist, qual = LidarModel(cfg, np.random.default_rng(0)).revolution(0.1, 2.0, 0.0, Raycaster(ROOM))
    ref = room_distance(0.1, 2.0, angles)
    assert np.all(dist[(ref < 0.15) | (ref > 3.2)] == 0.0)
    assert np.all(qual[dist == 0.0] == 0)
    ok = (ref >= 0.15) & (ref <= 3.2)
    np.testing.assert_allclose(dist[ok], ref[ok])


def test_seeded_noise_is_deterministic_and_plausible() -> None:
    cfg = LidarConfig(dropout=0.05, rate_hz=10.0)
    rc = Raycaster(ROOM)
    a = LidarModel(cfg, np.random.default_rng(42))
    b = LidarModel(cfg, np.random.default_rng(42))
    for _ in range(3):
        ra, rb = a.revolution(3.0, 2.0, 0.0, rc), b.revolution(3.0, 2.0, 0.0, rc)
        for xa, xb in zip(ra, rb, strict=True):
            np.testing.assert_array_equal(xa, xb)
    angles, dist, _ = ra
    assert 795 <= angles.size <= 801  # 8000 samples/s at 10 Hz, random phase
    assert 0.02 < np.mean(dist == 0.0) < 0.09  # about 5 % dropouts
    ok = dist > 0
    err = dist[ok] - room_distance(3.0, 2.0, angles[ok])
    assert 0.005 < err.std() < 0.03 and abs(err.mean()) < 0.005
    c = LidarModel(cfg, np.random.default_rng(43)).revolution(3.0, 2.0, 0.0, rc)
    assert not np.array_equal(c[1][: min(c[1].size, dist.size)], dist[: min(c[1].size, dist.size)])


def test_sample_count_follows_rate_and_phase() -> None:
    model = LidarModel(LidarConfig(), np.random.default_rng(1))
    counts = {model.revolution(3.0, 2.0, 0.0, Raycaster(ROOM))[0].size for _ in range(40)}
    assert counts <= {1454, 1455} and len(counts) == 2


def test_fov_and_other_robots() -> None:
    cfg = LidarConfig(fov_deg=180.0).noiseless()
    angles, dist, _ = LidarModel(cfg, np.random.default_rng(0)).revolution(3.0, 2.0, 0.0, Raycaster(ROOM))
    behind = np.abs(np.mod(angles + math.pi, 2 * math.pi) - math.pi) > math.pi / 2 + 1e-9
    assert np.all(dist[behind] == 0.0) and np.all(dist[~behind] > 0.0)
    model = LidarModel(LidarConfig().noiseless(), np.random.default_rng(0))
    source = scan_source_for(
        model, lambda t: (3.0, 2.0, 0.0), Raycaster(ROOM), lambda x, y, t: np.array([(4.0, 2.0, 0.2)])
    )
    _, dist, _ = source(0.0)
    assert dist[0] == pytest.approx(0.8)


def test_config_validation() -> None:
    with pytest.raises(ValueError):
        LidarConfig(fov_deg=0.0)
    with pytest.raises(ValueError):
        LidarConfig(min_range=5.0, max_range=1.0)
    with pytest.raises(ValueError):
        LidarConfig(dropout=1.5)
