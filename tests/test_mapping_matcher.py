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


def _refine_one_step_at_a_time(grid, points, pose, iterations=8):  # type: ignore[no-untyped-def]
    """The refinement as first written: every halved step scored on its own, the field's corners looked
    up again for each gradient (the reference the batched refinement must equal, to the bit)."""
    from fleetlink.agent.mapping.matcher import field_score

    x, y, th = pose
    res = grid.resolution
    ox, oy = grid.origin
    px, py = points[:, 0], points[:, 1]
    h, w = grid.field.shape
    current = -1.0
    for _ in range(iterations):
        c, s = math.cos(th), math.sin(th)
        u = (x + c * px - s * py - ox) / res - 0.5
        v = (y + s * px + c * py - oy) / res - 0.5
        uf, vf = np.floor(u), np.floor(v)
        fu, fv = u - uf, v - vf
        u0, v0 = uf.astype(np.int64), vf.astype(np.int64)
        ok = (u0 >= 0) & (u0 < w - 1) & (v0 >= 0) & (v0 < h - 1)
        f = grid.field.astype(np.float64)
        uc, vc = np.clip(u0, 0, w - 2), np.clip(v0, 0, h - 2)
        m00, m10 = np.where(ok, f[vc, uc], 0.0), np.where(ok, f[vc, uc + 1], 0.0)
        m01, m11 = np.where(ok, f[vc + 1, uc], 0.0), np.where(ok, f[vc + 1, uc + 1], 0.0)
        gu, gv = 1 - fu, 1 - fv
        val = gv * (gu * m00 + fu * m10) + fv * (gu * m01 + fu * m11)
        du = gv * (m10 - m00) + fv * (m11 - m01)
        dv = gu * (m01 - m00) + fu * (m11 - m10)
        if current < 0.0:
            current = float(val.mean())
        gx, gy = du / res, dv / res
        jac = np.column_stack((gx, gy, gx * (-s * px - c * py) + gy * (c * px - s * py)))
        hess = jac.T @ jac
        grad = jac.T @ (1.0 - val)
        if not np.isfinite(hess).all() or np.trace(hess) < 1e-9:
            break
        hess += np.diag(np.maximum(np.diag(hess), 1e-6) * 0.1 + 1e-6)
        step = np.linalg.solve(hess, grad)
        step = step / max(1.0, math.hypot(step[0], step[1]) / res, abs(step[2]) / math.radians(1.0))
        for _half in range(4):
            cand = (x + float(step[0]), y + float(step[1]), th + float(step[2]))
            score = field_score(grid, points, cand)
            if score > current:
                break
            step = step / 2.0
        else:
            break
        x, y, th = cand
        gain, current = score - current, score
        if gain < 1e-5:
            break
    return (x, y, th), current


def test_the_refinement_is_the_one_step_at_a_time_refinement_to_the_bit() -> None:
    """``refine`` scores its halved steps together and keeps the corners of the pose it takes; its answer
    (and the score ``match_scan`` takes from it) must be the plain one's, bit for bit, near the grid's
    edge too (where the corners are checked per point)."""
    from fleetlink.agent.mapping.matcher import _refine, field_score

    rc = Raycaster(ROOM)
    m = OnboardMapper(MapperConfig(closer=None))
    truth = (2.0, 1.2, 0.3)
    m.add_scan(0.0, _scan(rc, truth), ANGLES, truth)
    grid = m.grid
    rng = np.random.default_rng(4)
    pts = np.column_stack((np.cos(ANGLES), np.sin(ANGLES))) * _scan(rc, truth)[:, None]
    pts = pts[np.hypot(pts[:, 0], pts[:, 1]) > 0][::3]
    for k in range(30):
        start = (truth[0] + rng.normal(0, 0.05), truth[1] + rng.normal(0, 0.05), truth[2] + rng.normal(0, 0.03))
        if k == 29:  # far off: points past the grid's edge
            start = (start[0] - 9.0, start[1], start[2])
        pose, score = _refine(grid, pts, start)
        ref_pose, ref_score = _refine_one_step_at_a_time(grid, pts, start)
        assert pose == ref_pose and score == ref_score, k
        assert score == field_score(grid, pts, pose)


def test_the_local_map_finds_the_nearest_fused_point_in_the_cells_around() -> None:
    """``LocalMap.nearest_xy`` against brute force: the nearest fused point among the 3 x 3 cells around
    each query (-1 and an infinite distance where they hold none), and its distance."""
    from fleetlink.agent.mapping.matcher import LocalMap

    rng = np.random.default_rng(8)
    local = LocalMap(keyframes=3, cell=0.1)
    for _ in range(3):
        pts = rng.uniform(-2.0, 2.0, (150, 2))
        normals = np.tile([[1.0, 0.0]], (150, 1))
        local.add((0.0, 0.0, 0.0), pts, normals)
    q = rng.uniform(-2.6, 2.6, (400, 2))
    idx, dist = local.nearest_xy(q[:, 0], q[:, 1])
    cell = np.floor(local.points / 0.1)
    for k, (x, y) in enumerate(q):
        here = np.floor(np.array([x, y]) / 0.1)
        near = np.flatnonzero((np.abs(cell - here) <= 1).all(axis=1))
        if not near.size:
            assert idx[k] == -1 and dist[k] == np.inf
            continue
        d = np.hypot(local.points[near, 0] - x, local.points[near, 1] - y)
        assert idx[k] == near[np.argmin(d)] and dist[k] == d.min()
    assert (idx == -1).any() and (idx >= 0).sum() > 200


def test_a_local_map_extended_at_once_is_the_one_added_to_frame_by_frame() -> None:
    """Submaps fuse their scans' points once (``LocalMap.extend``): the same fused points, normals and
    lookups as adding the frames one by one, the oldest dropped alike when there are more than it keeps."""
    from fleetlink.agent.mapping.matcher import LocalMap

    rng = np.random.default_rng(2)
    frames = []
    for k in range(7):
        pts = rng.uniform(-3.0, 3.0, (120, 2))
        normals = rng.normal(size=(120, 2))
        normals /= np.hypot(normals[:, 0], normals[:, 1])[:, None]
        normals[::17] = np.nan  # points without a normal are left out
        frames.append(((0.1 * k, -0.05 * k, 0.02 * k), pts, normals))
    one, many = LocalMap(keyframes=5, cell=0.05), LocalMap(keyframes=5, cell=0.05)
    for f in frames:
        one.add(*f)
    many.extend(frames)
    assert np.array_equal(one.keys, many.keys) and np.array_equal(one.points, many.points)
    assert np.array_equal(one.normals, many.normals) and np.array_equal(one.stacked, many.stacked)
    q = rng.uniform(-3.5, 3.5, (300, 2))
    for a, b in zip(one.nearest(q), many.nearest(q), strict=True):
        assert np.array_equal(a, b)


@pytest.mark.parametrize(("sd_cells", "spread"), [(0.07, 3.0), (0.3, 3.0), (1.0, 3.0), (0.07, 9.0), (5.0, 3.0)])
def test_the_correlative_search_skips_only_candidates_the_prior_leaves_no_chance(
    sd_cells: float, spread: float
) -> None:
    """With top 1 the search scores only candidates penalised less than 1 beyond the least penalised
    (a mean field value lies in [0, 1]); its answer must be the one scoring every candidate gives: tight
    priors (few scored), loose ones (all scored), points past the grid's edge (clipped lookups)."""
    from fleetlink.agent.mapping.matcher import _grid_offsets, _search

    rng = np.random.default_rng(int(sd_cells * 100 + spread))
    field = np.clip(rng.random((120, 140)).astype(np.float32) * 1.2 - 0.1, 0.0, 1.0)
    pts = rng.uniform(-spread, spread, (90, 2))
    thetas = 0.3 + np.radians(1.5) * np.arange(-10, 11)
    offs = _grid_offsets(-3, 3)
    pen = 0.15 * (
        ((offs[:, 0] ** 2 + offs[:, 1] ** 2) / sd_cells**2)[None, :] + (np.arange(-10, 11) / 8.0)[:, None] ** 2
    )
    for x, y in ((3.1, 2.9), (0.4, 0.3)):
        got = _search(field, pts, 0.05, (0.0, 0.0), x, y, thetas, offs, pen)
        every = _search(field, pts, 0.05, (0.0, 0.0), x, y, thetas, offs, pen, top=2)[0]
        assert got == [every]


def test_the_correlative_search_finds_walls_the_prior_disfavours_but_allows() -> None:
    """The walls lie where a candidate penalised 0.8 beyond the least penalised puts the points: the
    mean field value (1 there, 0 elsewhere) outweighs the prior, and the search must score that one."""
    from fleetlink.agent.mapping.matcher import _grid_offsets, _search

    rng = np.random.default_rng(1)
    pts = rng.uniform(-2.0, 2.0, (60, 2))
    thetas = np.radians(1.5) * np.arange(-5, 6)
    offs = _grid_offsets(-3, 3)
    pen = 0.2 * (offs[:, 0] ** 2 + offs[:, 1] ** 2)[None, :] + 0.0 * thetas[:, None]  # one cell: 0.2, two: 0.8
    a, t = 7, int(np.flatnonzero((offs[:, 0] == 2) & (offs[:, 1] == 0))[0])
    field = np.zeros((200, 200), dtype=np.float32)
    c, s = math.cos(thetas[a]), math.sin(thetas[a])
    cols = np.floor((5.0 + c * pts[:, 0] - s * pts[:, 1]) / 0.05).astype(int) + offs[t, 0]
    rows = np.floor((5.0 + s * pts[:, 0] + c * pts[:, 1]) / 0.05).astype(int) + offs[t, 1]
    field[rows, cols] = 1.0
    got = _search(field, pts, 0.05, (0.0, 0.0), 5.0, 5.0, thetas, offs, pen)
    assert got[0][:2] == (a, t) and got[0][2] == pytest.approx(1.0 - 0.8)
    assert got == [_search(field, pts, 0.05, (0.0, 0.0), 5.0, 5.0, thetas, offs, pen, top=2)[0]]


def _icp_every_point_again(local, points, pose, prior_pose, prior, sigma=0.03, max_distance=0.15, iterations=8):  # type: ignore[no-untyped-def]
    """Point-to-line as first written: every point's correspondence looked up afresh each iteration."""
    x, y, th = pose
    px, py = points[:, 0], points[:, 1]
    sxy, sth = max(prior[0], 1e-3), max(prior[1], 1e-4)
    lam = np.diag([1.0 / sxy**2, 1.0 / sxy**2, 1.0 / sth**2])
    inliers, hd_last = 0, None
    for _ in range(iterations):
        c, s = math.cos(th), math.sin(th)
        wx, wy = x + c * px - s * py, y + s * px + c * py
        idx, dist = local.nearest_xy(wx, wy)
        ok = dist <= max_distance
        inliers = int(np.count_nonzero(ok))
        if inliers < 3:
            break
        i = idx[ok]
        nx, ny = local.normals[i, 0], local.normals[i, 1]
        pxo, pyo = px[ok], py[ok]
        r = nx * (wx[ok] - local.points[i, 0]) + ny * (wy[ok] - local.points[i, 1])
        w = 1.0 / (1.0 + (r / sigma) ** 2) / sigma**2
        jac = np.column_stack((nx, ny, nx * (-s * pxo - c * pyo) + ny * (c * pxo - s * pyo)))
        jw = (jac * w[:, None]).T
        hd = jw @ jac
        dev = np.array([x - prior_pose[0], y - prior_pose[1], math.remainder(th - prior_pose[2], 2.0 * math.pi)])
        step = -np.linalg.solve(hd + lam, jw @ r + lam @ dev)
        x, y, th = x + float(step[0]), y + float(step[1]), th + float(step[2])
        hd_last = hd
        if math.hypot(step[0], step[1]) < 1e-4 and abs(step[2]) < 1e-4:
            break
    weak = 0.0 if hd_last is None else float(np.linalg.eigvalsh(hd_last)[0])
    return (x, y, th), inliers, weak, hd_last


def test_point_to_line_is_the_one_that_looks_every_correspondence_up_again() -> None:
    """``icp_refine`` gathers the 3 x 3 cells' points again only for points whose cell changed, and
    solves through LAPACK directly: its answer must be the plain one's, bit for bit, from starts far
    enough off that many points change cells."""
    from fleetlink.agent.mapping.matcher import LocalMap, icp_refine, scan_normals
    from fleetlink.agent.mapping.scan import segment_labels, to_points

    rc = Raycaster(ROOM)
    truth = (2.0, 1.2, 0.3)
    r = _scan(rc, truth)
    pts = to_points(r[r > 0], ANGLES[r > 0])
    normals = scan_normals(pts, segment_labels(pts, 0.3, 5.0))
    local = LocalMap(keyframes=5, cell=0.1)
    local.add(truth, pts, normals)
    rng = np.random.default_rng(9)
    for k in range(12):
        start = (truth[0] + rng.normal(0, 0.06), truth[1] + rng.normal(0, 0.06), truth[2] + rng.normal(0, 0.03))
        got = icp_refine(local, pts, start, start, (0.1, 0.05) if k % 2 else (1.0, 1.0))
        pose, inliers, weak, info = _icp_every_point_again(
            local, pts, start, start, (0.1, 0.05) if k % 2 else (1.0, 1.0)
        )
        assert got.pose == pose and got.inliers == inliers and got.weak == weak, k
        assert info is not None and got.information is not None and np.array_equal(got.information, info)


def test_many_refinements_at_once_are_each_refined_alone(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """``icp_refine_many`` (a replay's final pass: thousands of scan pairs) is ``icp_refine`` of each task:
    the same pose, inliers, weakest information and information to rounding (its sums over the points
    are taken in another order), tasks sharing a reference or not, a reference or a scan with nothing
    in it, a start too far off for three points to find a wall, more iterations for some tasks than
    others; and the answers do not depend on how the tasks are cut into batches."""
    import fleetlink.agent.mapping.matcher as matcher
    from fleetlink.agent.mapping.matcher import LocalMap, icp_refine, icp_refine_many, scan_normals
    from fleetlink.agent.mapping.scan import segment_labels, to_points

    rc = Raycaster(ROOM)

    def seen(pose: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
        r = _scan(rc, pose)
        pts = to_points(r[r > 0], ANGLES[r > 0])
        return pts, scan_normals(pts, segment_labels(pts, 0.3, 5.0))

    views = [(2.0, 1.2, 0.3), (5.5, 3.0, -1.0), (6.8, 1.0, 2.5)]
    refs = []
    for v in views:
        pts, nrm = seen(v)
        ref = LocalMap(1, 0.05)
        ref.add((0.0, 0.0, 0.0), pts, nrm)
        refs.append(ref)
    rng = np.random.default_rng(4)
    tasks = []
    for k in range(24):
        i = k % len(views)
        moved = (
            views[i][0] + rng.normal(0, 0.15),
            views[i][1] + rng.normal(0, 0.15),
            views[i][2] + rng.normal(0, 0.05),
        )
        pts, _ = seen(moved)
        dx, dy = moved[0] - views[i][0], moved[1] - views[i][1]
        c, s = math.cos(-views[i][2]), math.sin(-views[i][2])
        truth = (c * dx - s * dy, s * dx + c * dy, moved[2] - views[i][2])  # the scan in the reference's frame
        start = (truth[0] + rng.normal(0, 0.05), truth[1] + rng.normal(0, 0.05), truth[2] + rng.normal(0, 0.02))
        tasks.append((refs[i], pts, start))
    tasks.append((LocalMap(1, 0.05), tasks[0][1], (0.0, 0.0, 0.0)))  # an empty reference
    tasks.append((refs[0], np.zeros((0, 2)), (0.1, 0.0, 0.0)))  # no points
    tasks.append((refs[1], tasks[1][1], (40.0, -30.0, 0.0)))  # nothing within reach
    alone = [
        icp_refine(ref, pts, st, st, (1.0, 1.0), 0.03, 0.15, iterations=20, tolerance=1e-3) for ref, pts, st in tasks
    ]
    together = icp_refine_many(tasks, (1.0, 1.0), 0.03, 0.15, iterations=20, tolerance=1e-3)
    assert len(together) == len(tasks)
    assert len({a.inliers for a in alone[:24]}) > 1 and alone[-1].inliers < 3 and alone[-3].inliers == 0
    for a, b in zip(alone, together, strict=True):
        assert b.inliers == a.inliers
        assert b.pose == pytest.approx(a.pose, abs=1e-9)
        assert b.weak == pytest.approx(a.weak, rel=1e-9, abs=1e-9)
        assert (a.information is None) == (b.information is None)
        if a.information is not None:
            assert np.allclose(a.information, b.information, rtol=1e-9)
    monkeypatch.setattr(matcher, "_MANY_POINTS", 300)  # a batch of a task or two
    cut = icp_refine_many(tasks, (1.0, 1.0), 0.03, 0.15, iterations=20, tolerance=1e-3)
    assert [(r.pose, r.inliers, r.weak) for r in cut] == [(r.pose, r.inliers, r.weak) for r in together]


def test_many_field_refinements_at_once_are_each_refined_alone() -> None:
    """``_refine_many`` (the final pass: a submap's checks together) is ``_refine`` of each (points,
    pose): the same pose and score to rounding, starts near and far (points past the grid's edge),
    scans of different lengths, one with no points (kept where it is, score -1) and no iterations."""
    from fleetlink.agent.mapping.matcher import _refine, _refine_many

    rc = Raycaster(ROOM)
    m = OnboardMapper(MapperConfig(closer=None))
    truth = (2.0, 1.2, 0.3)
    m.add_scan(0.0, _scan(rc, truth), ANGLES, truth)
    rng = np.random.default_rng(5)
    pts = np.column_stack((np.cos(ANGLES), np.sin(ANGLES))) * _scan(rc, truth)[:, None]
    pts = pts[np.hypot(pts[:, 0], pts[:, 1]) > 0]
    tasks = []
    for k in range(30):
        start = (truth[0] + rng.normal(0, 0.08), truth[1] + rng.normal(0, 0.08), truth[2] + rng.normal(0, 0.04))
        if k % 10 == 9:  # far off: points past the grid's edge
            start = (start[0] - 9.0, start[1], start[2])
        tasks.append((pts[k % 3 :: 2 + k % 4], start))
    tasks.append((np.zeros((0, 2)), truth))
    together = _refine_many(m.grid, tasks)
    assert together[-1] == (truth, -1.0)
    moved = 0
    for (p, start), (pose, score) in zip(tasks[:-1], together[:-1], strict=True):
        ref_pose, ref_score = _refine(m.grid, p, start)
        assert pose == pytest.approx(ref_pose, abs=1e-9) and score == pytest.approx(ref_score, abs=1e-9)
        moved += math.dist(pose[:2], start[:2]) > 0.01
    assert moved > 10
    assert _refine_many(m.grid, tasks[:3], iterations=0) == [(t[1], -1.0) for t in tasks[:3]]


def test_a_refused_odometry_leaves_the_next_turn_measured_from_the_last_good_one() -> None:
    # The agent without UWB and a replay take each turn through add_scan_odometry: one NaN odometry
    # pose is refused, and the turns after it map as if it had not come.
    rc = Raycaster(ROOM)
    m, clean = OnboardMapper(), OnboardMapper()
    poses = [(2.0 + 0.05 * i, 1.2, 0.3) for i in range(6)]
    for i, p in enumerate(poses[:3]):
        m.add_scan_odometry(0.1 * i, _scan(rc, p), ANGLES, p)
        clean.add_scan_odometry(0.1 * i, _scan(rc, p), ANGLES, p)
    with pytest.raises(ValueError):
        m.add_scan_odometry(0.3, _scan(rc, poses[3]), ANGLES, (math.nan, 1.2, 0.3))
    assert m.rejected == 1
    for i, p in enumerate(poses[3:], start=3):
        a = m.add_scan_odometry(0.1 * i + 0.05, _scan(rc, p), ANGLES, p)
        b = clean.add_scan_odometry(0.1 * i + 0.05, _scan(rc, p), ANGLES, p)
        assert a.matched and a.pose == pytest.approx(b.pose, abs=1e-9)
