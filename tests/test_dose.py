"""The UV dose model (shared/dose.py) against closed-form cases: a point source and a vertical tube over
an open floor, walls casting shadows (exact, checked against an independent brute force), dose
accumulated over time and robots, coverage, the report writers, and bad input."""

from __future__ import annotations

import math
import re
import struct
import time
import zlib

import numpy as np
import pytest

from fleetlink.shared.dose import (
    DEFAULT_TARGET_J_M2,
    DoseGrid,
    FloorMask,
    Lamp,
    csv_report,
    irradiance,
    irradiance_window,
    j_m2,
    pgm_report,
    png_report,
    summarise,
)

P, H = 10.0, 0.6  # 10 W of UV-C, lamp 0.6 m above the floor
LAMP = Lamp(P, H)


def _grid(w: int, h: int, res: float) -> tuple[np.ndarray, tuple[float, float]]:
    """An open floor of w x h cells whose centres are at (col * res, row * res)."""
    return np.ones((h, w), dtype=bool), (-res / 2.0, -res / 2.0)


def _point(d2: np.ndarray | float) -> np.ndarray:
    """P h / (4 pi d^3) for squared horizontal distances."""
    d = np.sqrt(np.asarray(d2, dtype=float) + H * H)
    return P * H / (4.0 * math.pi * d**3)


# -- the lamp over an open floor ------------------------------------------------------------


def test_units() -> None:
    assert j_m2(10.0) == pytest.approx(100.0)  # 10 mJ/cm² = 100 J/m²
    assert DEFAULT_TARGET_J_M2 == 100.0


def test_point_source_matches_closed_form_at_several_distances() -> None:
    res = 0.05
    free, origin = _grid(200, 160, res)
    x, y = 4.013, 3.007  # not on a cell centre
    e = irradiance(LAMP, x, y, free, res, origin, max_radius_m=20.0)
    for col, row in ((80, 60), (81, 60), (100, 60), (80, 100), (150, 10), (0, 0), (199, 159)):
        d2 = (col * res - x) ** 2 + (row * res - y) ** 2
        d = math.sqrt(d2 + H * H)
        expected = P * H / (4.0 * math.pi * d**3)  # = P / (4 pi d²) cos θ, cos θ = h / d
        assert e[row, col] == pytest.approx(expected, rel=1e-9)
    # Directly below: P / (4 pi h²).
    e0 = irradiance(LAMP, 4.0, 3.0, free, res, origin)
    assert e0[60, 80] == pytest.approx(P / (4.0 * math.pi * H * H), rel=1e-12)


def test_point_source_integrates_to_half_its_power() -> None:
    res, radius = 0.02, 8.0
    n = int(2 * radius / res) + 3
    free, origin = _grid(n, n, res)
    x = y = (n // 2) * res + 0.003
    e = irradiance(LAMP, x, y, free, res, origin, max_radius_m=radius)
    on_floor = float(e.sum()) * res * res
    d_r = math.hypot(radius, H)
    within = P / 2.0 * (1.0 - H / d_r)  # the disc of radius R takes all but h / d_R of P / 2
    assert on_floor == pytest.approx(within, rel=2e-4)
    # With the analytic tail beyond R, the whole floor receives P / 2: the lower half-sphere.
    assert on_floor + P * H / (2.0 * d_r) == pytest.approx(P / 2.0, rel=2e-4)


def test_line_source_closed_form_against_summed_elements() -> None:
    tube = Lamp(P, 0.9, tube_length_m=1.2, min_distance_m=0.1)
    z = np.linspace(0.3, 1.5, 200_001)
    z = 0.5 * (z[1:] + z[:-1])  # element midpoints
    dz = 1.2 / z.size
    for r in (0.05, 0.3, 1.0, 2.5, 7.0):
        rho = np.hypot(r, z)
        # Each element radiates (P / L) dz sin(phi) / pi² per steradian; on the floor cos(theta) / rho².
        summed = float(np.sum(P / 1.2 * dz * (r / rho) / math.pi**2 * (z / rho) / rho**2))
        assert float(tube.at(np.array([r * r]))[0]) == pytest.approx(summed, rel=1e-7)
    assert float(tube.at(np.array([0.0]))[0]) == 0.0  # a bare tube's end emits nothing downwards
    # Far away, a diffuse tube gives (4 / pi) (r / d) times the isotropic point of the same power.
    r = 40.0
    ratio = float(tube.at(np.array([r * r]))[0]) / float(Lamp(P, 0.9).at(np.array([r * r]))[0])
    assert ratio == pytest.approx(4.0 / math.pi * r / math.hypot(r, 0.9), rel=1e-3)


def test_line_source_integrates_to_half_its_power() -> None:
    tube = Lamp(P, 0.9, tube_length_m=1.2, min_distance_m=0.1)
    r = np.linspace(0.0, 4000.0, 4_000_001)
    rm = 0.5 * (r[1:] + r[:-1])
    total = float(np.sum(tube.at(rm * rm) * 2.0 * math.pi * rm * np.diff(r)))
    assert total == pytest.approx(P / 2.0, rel=1e-3)


def test_reach_is_where_the_irradiance_falls_to_the_cutoff() -> None:
    for lamp in (LAMP, Lamp(P, 0.9, tube_length_m=1.2, min_distance_m=0.1)):
        r = lamp.reach(0.01)
        assert float(lamp.at(np.array([r * r]))[0]) == pytest.approx(0.01, rel=1e-6)
        assert lamp.reach(0.01, max_radius_m=2.0) == 2.0
        assert lamp.reach(0.0, max_radius_m=7.0) == 7.0
    # P h / (4 pi d³) = 0.01 W/m² -> d = (P h / (4 pi 0.01))^(1/3)
    d = (P * H / (4.0 * math.pi * 0.01)) ** (1.0 / 3.0)
    assert LAMP.reach(0.01) == pytest.approx(math.sqrt(d * d - H * H), rel=1e-12)


def test_cells_beyond_the_reach_get_nothing() -> None:
    res = 0.05
    free, origin = _grid(300, 300, res)
    e = irradiance(LAMP, 7.5, 7.5, free, res, origin, cutoff_w_m2=0.05)
    radius = LAMP.reach(0.05)
    cols = np.arange(300) * res - 7.5
    r2 = cols[None, :] ** 2 + cols[:, None] ** 2
    assert (e[r2 > radius * radius] == 0.0).all()
    inside = r2 <= radius * radius
    np.testing.assert_allclose(e[inside], _point(r2[inside]), rtol=1e-12)
    assert e[inside].min() >= 0.05 * (1 - 1e-9)


def test_window_and_full_grid_agree_and_edges_of_the_grid() -> None:
    res = 0.1
    free, origin = _grid(50, 40, res)
    full = irradiance(LAMP, 0.32, 0.21, free, res, origin)  # lamp near a corner: window clipped
    r0, c0, win = irradiance_window(LAMP, 0.32, 0.21, free, res, origin)
    assert (r0, c0) == (0, 0)
    np.testing.assert_array_equal(full[: win.shape[0], : win.shape[1]], win)
    assert (irradiance(LAMP, 100.0, 100.0, free, res, origin) == 0.0).all()  # lamp far off the grid


# -- walls -------------------------------------------------------------------------------------


def _wall_case() -> tuple[np.ndarray, np.ndarray, np.ndarray, float, tuple[float, float]]:
    res = 0.1
    free, origin = _grid(100, 70, res)
    free[25:36, 40] = False  # a wall segment: x in [3.95, 4.05], y in [2.45, 3.55]
    x, y = 2.02, 3.01
    walled = irradiance(LAMP, x, y, free, res, origin)
    open_ = irradiance(LAMP, x, y, np.ones_like(free), res, origin)
    return free, walled, open_, res, (x, y)


def test_a_wall_casts_the_shadow_geometry_says() -> None:
    free, walled, open_, res, (x, y) = _wall_case()
    # The shadow is the wedge between the rays through the wall's two near corners.
    lo = math.atan2(2.45 - y, 3.95 - x)
    hi = math.atan2(3.55 - y, 3.95 - x)
    rows, cols = np.nonzero(free)
    cx, cy = cols * res, rows * res
    angle = np.arctan2(cy - y, cx - x)
    behind = (cx > 3.95) & (angle >= lo) & (angle <= hi)
    clear = np.minimum(np.abs(angle - lo), np.abs(angle - hi)) > 1e-9  # no cell sits on an edge here
    assert clear.all()
    assert (walled[rows[behind], cols[behind]] == 0.0).all()
    # In front of the wall, beside it and outside the wedge: exactly the open-floor value.
    np.testing.assert_array_equal(walled[rows[~behind], cols[~behind]], open_[rows[~behind], cols[~behind]])
    # The wall's lit face (every cell of a one-cell wall facing the lamp) takes its own irradiance.
    np.testing.assert_array_equal(walled[~free], open_[~free])


def test_only_a_walls_lit_face_takes_a_dose() -> None:
    """The first cell of a thick wall, beside lit floor, holds the floor in front of the wall's
    surface: it takes the irradiance at its own centre; the wall behind it, and the face of a wall
    in another's shadow, take none."""
    res = 0.1
    free, origin = _grid(60, 60, res)
    free[20:40, 30:33] = False  # a wall three cells thick: x in [2.95, 3.25]
    free[28:32, 45] = False  # a short wall in its shadow
    x, y = 1.02, 3.01
    e = irradiance(LAMP, x, y, free, res, origin)
    open_ = irradiance(LAMP, x, y, np.ones_like(free), res, origin)
    np.testing.assert_array_equal(e[20:40, 30], open_[20:40, 30])  # the face towards the lamp
    assert (e[20:40, 31:33] == 0.0).all()  # the inside and the back
    assert (e[28:32, 45] == 0.0).all()  # a face no light reaches
    assert (e[~free & (open_ > 0.0)] > 0.0).sum() == 20  # nothing else of the walls


def test_the_shadow_edge_at_one_column() -> None:
    _, walled, _, res, (x, y) = _wall_case()
    # At x = 6.0 the edges are at y = 3.01 + 3.98 * slope: 4.124 (upper) and 1.855 (lower).
    upper = y + (6.0 - x) * (3.55 - y) / (3.95 - x)
    lower = y + (6.0 - x) * (2.45 - y) / (3.95 - x)
    assert upper == pytest.approx(4.1236, abs=1e-3)
    assert lower == pytest.approx(1.8552, abs=1e-3)
    dark = [round(r * res, 1) for r in range(70) if walled[r, 60] == 0.0]
    assert dark == [round(v, 1) for v in np.arange(1.9, 4.15, 0.1)]


def test_a_diagonal_wall_one_cell_thick_does_not_leak() -> None:
    """Corner-touching cells: a sampled ray slips between them; the exact test does not."""
    res = 0.1
    free, origin = _grid(60, 60, res)
    for r in range(60):
        if r + 10 < 60:
            free[r, r + 10] = False
    rows, cols = np.nonzero(free)
    other_side = rows < cols - 10
    for x, y in ((1.02, 3.01), (0.51, 5.53), (2.37, 2.96)):
        e = irradiance(LAMP, x, y, free, res, origin)
        assert (e[rows[other_side], cols[other_side]] == 0.0).all()
        assert (e[rows[~other_side], cols[~other_side]] > 0.0).all()


def test_a_wall_cell_under_the_lamp_is_ignored() -> None:
    """The robot's own cell mapped as a wall (noise) must not darken the room."""
    res = 0.1
    free, origin = _grid(40, 30, res)
    open_ = irradiance(LAMP, 2.02, 1.51, free, res, origin)
    free[15, 20] = False  # the cell the lamp stands over
    free[15, 21] = False  # and a wall cell beside it, which does cast a shadow
    e = irradiance(LAMP, 2.02, 1.51, free, res, origin)
    assert e[15, 20] == open_[15, 20]  # beside lit floor: its face's dose (it is floor, in truth)
    assert e[15, 22:].max() == 0.0  # behind the neighbour, along the row
    assert e[15, :20].min() > 0.0
    # The neighbour, 3 cm from the lamp, shades a wide wedge to the right; the left half is as if
    # nothing were there.
    assert (e[:, :20] == open_[:, :20]).all()
    assert (e[:, 22:] == 0.0).sum() > 100


def _hits(tx: float, ty: float, cx: float, cy: float, s: float) -> bool:
    """Scalar Liang-Barsky: does the segment (0,0)-(tx,ty) touch the closed square centred (cx, cy)?"""
    t0, t1 = 0.0, 1.0
    for d, c in ((tx, cx), (ty, cy)):
        if d == 0.0:
            if not (c - s <= 0.0 <= c + s):
                return False
            continue
        a, b = sorted(((c - s) / d, (c + s) / d))
        t0, t1 = max(t0, a), min(t1, b)
    return t0 <= t1


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_shadows_match_an_exhaustive_segment_test(seed: int) -> None:
    rng = np.random.default_rng(seed)
    res = 0.1
    free, origin = _grid(36, 30, res)
    free &= rng.random(free.shape) > 0.06  # scattered obstacles
    free[20, 3:30] = False
    free[8:13, 3:9] = False  # a thick block: only its rim can block
    for k in range(12):
        free[2 + k, 20 + k] = False
    br, bc = np.nonzero(~free)
    for _ in range(3):
        x, y = rng.uniform(0.2, 3.3), rng.uniform(0.2, 2.7)
        e = irradiance(LAMP, x, y, free, res, origin)
        walls = [
            (c * res - x, r * res - y)
            for r, c in zip(br.tolist(), bc.tolist(), strict=True)
            if abs(c * res - x) > res / 2 or abs(r * res - y) > res / 2  # not the lamp's own cell
        ]
        for r, c in zip(*np.nonzero(free), strict=True):
            tx, ty = c * res - x, r * res - y
            seen = not any(_hits(tx, ty, u, v, res / 2) for u, v in walls)
            assert (e[r, c] > 0.0) == seen, (x, y, r, c)


# -- dose over time and robots ---------------------------------------------------------------


def _room(res: float = 0.05) -> FloorMask:
    """A 6 x 4 m room (walls one cell thick) with a wall stub, centres on multiples of res."""
    w, h = round(6.0 / res) + 1, round(4.0 / res) + 1
    free = np.ones((h, w), dtype=bool)
    free[0, :] = free[-1, :] = False
    free[:, 0] = free[:, -1] = False
    free[: round(2.0 / res), round(3.0 / res)] = False  # a stub from the bottom wall up to y = 2
    return FloorMask(free, res, (-res / 2.0, -res / 2.0))


def test_dose_is_irradiance_times_time_and_linear_in_seconds() -> None:
    room = _room()
    once, twice = DoseGrid(0.05), DoseGrid(0.05)
    once.add(LAMP, 1.51, 2.02, 60.0, room)
    twice.add(LAMP, 1.51, 2.02, 20.0, room)
    twice.add(LAMP, 1.51, 2.02, 40.0, room)
    np.testing.assert_allclose(twice.on(room), once.on(room), rtol=1e-12)
    e = irradiance(LAMP, 1.51, 2.02, room.free, room.resolution, room.origin, cutoff_w_m2=0.01)
    np.testing.assert_allclose(once.on(room), 60.0 * e, rtol=1e-12)
    assert once.lamp_seconds == 60.0 and twice.lamp_seconds == 60.0
    # The cell below the lamp (centre 1 cm and 2 cm off): one minute of P h / (4 pi d³).
    assert float(once.dose_at(np.array([1.5]), np.array([2.0]))[0, 0]) == pytest.approx(
        float(_point(0.01**2 + 0.02**2)) * 60.0, rel=1e-12
    )
    assert once.add(LAMP, 1.51, 2.02, 0.0, room) is None  # nothing to add


def test_robots_add_up_in_the_site_frame() -> None:
    room = _room()
    a, b, both = DoseGrid(0.05), DoseGrid(0.05), DoseGrid(0.05)
    a.add(LAMP, 1.51, 2.02, 30.0, room)
    b.add(LAMP, 4.53, 1.04, 45.0, room)
    both.add(LAMP, 1.51, 2.02, 30.0, room)
    both.add(LAMP, 4.53, 1.04, 45.0, room)
    assert a.origin != b.origin  # different extents on one lattice
    merged = DoseGrid.merged([a, b])
    np.testing.assert_allclose(merged.on(room), a.on(room) + b.on(room), rtol=1e-12)
    np.testing.assert_allclose(merged.on(room), both.on(room), rtol=1e-12)
    assert merged.lamp_seconds == 75.0
    # The stub shades the right half of the room from the lamp at (1.5, 2.0), low down.
    assert float(a.dose_at(np.array([3.5]), np.array([0.3]))[0, 0]) == 0.0
    assert float(b.dose_at(np.array([3.5]), np.array([0.3]))[0, 0]) > 0.0


def test_two_maps_a_cell_apart_on_a_wall_read_the_dose_where_either_calls_it_floor() -> None:
    """Two robots' maps agree on a wall only to within a cell: b's map has the wall's face one cell
    further in than a's. The floor a calls floor beside the wall, which b lit, has b's dose in the
    fleet's sum (it used to read none there: the two-robot rounds topped up for it)."""
    res = 0.05
    free_a, origin = _grid(80, 60, res)
    free_a[:, 70:] = False  # a's wall face at x = 3.475 (cells 70 on)
    free_b = free_a.copy()
    free_b[:, 69] = False  # b's one cell further in
    map_a = FloorMask(free_a, res, origin)
    map_b = FloorMask(free_b, res, origin)
    b = DoseGrid(res)
    b.add(LAMP, 3.0, 1.5, 60.0, map_b)
    face = b.dose_at(np.array([69 * res]), np.arange(10, 50) * res)
    open_ = irradiance(LAMP, 3.0, 1.5, np.ones_like(free_a), res, origin) * 60.0
    np.testing.assert_allclose(face[:, 0], open_[10:50, 69], rtol=1e-12)
    merged = DoseGrid.merged([b])
    assert (merged.on(map_a)[10:50, 69] > 0.0).all()
    assert (b.dose_at(np.array([71 * res]), np.arange(10, 50) * res) == 0.0).all()  # behind the face: none


def test_the_grid_grows_on_the_lattice() -> None:
    g = DoseGrid(0.05, grow_step_m=2.0)
    room = _room()
    g.add(LAMP, 1.0, 1.0, 1.0, room)
    before = g.dose.copy()
    ox, oy = g.origin
    g.add(Lamp(P, H), 30.0, -20.0, 1.0, FloorMask(np.ones((10, 10), dtype=bool), 0.05, (29.775, -20.225)))
    for o in g.origin:
        assert abs((o / 0.05 + 0.5) - round(o / 0.05 + 0.5)) < 1e-9  # centres on multiples of 0.05
    c, r = round((ox - g.origin[0]) / 0.05), round((oy - g.origin[1]) / 0.05)
    np.testing.assert_array_equal(g.dose[r : r + before.shape[0], c : c + before.shape[1]], before)


# -- coverage and reports ----------------------------------------------------------------------


def _layer() -> tuple[DoseGrid, FloorMask]:
    """A 10 x 8 cell floor at 0.5 m: dose 150 J/m² except two patches (2 and 3 cells) below 100."""
    res = 0.5
    dose = np.full((8, 10), 150.0)
    dose[1, 1:3] = 20.0  # a 2-cell patch at the bottom left
    dose[5:8, 8] = 99.0  # a 3-cell patch at the right
    free = np.ones((8, 10), dtype=bool)
    free[4, :] = False  # a wall row: not floor, ignored
    dose[4, :] = 0.0
    return DoseGrid.from_array(dose, res, (-0.25, -0.25)), FloorMask(free, res, (-0.25, -0.25))


def test_coverage_fraction_and_what_is_below() -> None:
    grid, mask = _layer()
    assert grid.covered(100.0, mask) == pytest.approx(65 / 70)
    assert grid.covered(10.0, mask) == 1.0
    assert grid.covered(200.0, mask) == 0.0
    below = grid.below_target(100.0, mask)
    assert sorted(map(tuple, below.tolist())) == [(0.5, 0.5), (1.0, 0.5), (4.0, 2.5), (4.0, 3.0), (4.0, 3.5)]


def test_summary_areas_and_regions() -> None:
    grid, mask = _layer()
    s = summarise(grid, 100.0, mask)
    assert s.floor_m2 == pytest.approx(70 * 0.25)
    assert s.reached_m2 == pytest.approx(65 * 0.25)
    assert s.below_m2 == pytest.approx(5 * 0.25)
    assert s.fraction == pytest.approx(65 / 70)
    assert s.min_dose_j_m2 == 20.0
    assert s.regions_total == 2
    big, small = s.regions
    assert big.area_m2 == pytest.approx(0.75) and big.centroid == pytest.approx((4.0, 3.0))
    assert big.box == pytest.approx((3.75, 2.25, 4.25, 3.75))
    assert small.area_m2 == pytest.approx(0.5) and small.centroid == pytest.approx((0.75, 0.5))
    text = s.text()
    assert "below target: 1.25 m² in 2 region(s)" in text
    assert "(92.9 %)" in text
    assert len(summarise(grid, 100.0, mask, max_regions=1).regions) == 1


def test_regions_are_eight_connected() -> None:
    res = 1.0
    dose = np.full((5, 5), 200.0)
    for k in range(5):
        dose[k, k] = 0.0  # a diagonal: one region
    dose[0, 4] = 0.0  # a lone cell: another
    grid = DoseGrid.from_array(dose, res, (-0.5, -0.5))
    mask = FloorMask(np.ones((5, 5), dtype=bool), res, (-0.5, -0.5))
    s = summarise(grid, 100.0, mask)
    assert [r.area_m2 for r in s.regions] == [5.0, 1.0]


def test_pgm_report_format() -> None:
    grid, mask = _layer()
    data = pgm_report(grid, 100.0, mask)
    m = re.match(rb"P5\n(\d+) (\d+)\n255\n", data)
    assert m is not None
    w, h = int(m.group(1)), int(m.group(2))
    assert (w, h) == (10, 8)
    pixels = np.frombuffer(data[m.end() :], dtype=np.uint8).reshape(h, w)
    assert len(data) == m.end() + w * h
    # North up: the picture's first row is the grid's top row (row 7).
    assert pixels[0, 8] == 1 + round(254 * 0.99)
    assert pixels[7 - 1, 1] == 1 + round(254 * 0.2)
    assert pixels[0, 0] == 255  # reached
    assert (pixels[7 - 4] == 0).all()  # not floor


def test_png_report_format() -> None:
    grid, mask = _layer()
    data = png_report(grid, 100.0, mask)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, chunks = 8, {}
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        (crc,) = struct.unpack(">I", data[pos + 8 + n : pos + 12 + n])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF
        chunks[kind] = body
        pos += 12 + n
    assert pos == len(data) and list(chunks) == [b"IHDR", b"IDAT", b"IEND"]
    w, h, depth, colour = struct.unpack(">IIBB", chunks[b"IHDR"][:10])
    assert (w, h, depth, colour) == (10, 8, 8, 2)
    raw = zlib.decompress(chunks[b"IDAT"])
    assert len(raw) == h * (1 + 3 * w)
    top = np.frombuffer(raw[1 : 1 + 3 * w], dtype=np.uint8).reshape(w, 3)
    assert tuple(top[0]) == (0, 170, 0)  # at target: green


def test_csv_report_columns_and_rows() -> None:
    grid, mask = _layer()
    lines = csv_report(grid, 100.0, mask).splitlines()
    assert lines[0] == "x_m,y_m,dose_j_per_m2,at_target"
    assert len(lines) == 1 + 70  # one per floor cell
    rows = {tuple(line.split(",")[:2]): line.split(",")[2:] for line in lines[1:]}
    assert rows[("0.500", "0.500")] == ["20.000", "0"]
    assert rows[("0.000", "0.000")] == ["150.000", "1"]
    assert ("0.000", "2.000") not in rows  # the wall row
    # Without a mask: the cells with any dose.
    assert len(csv_report(grid, 100.0).splitlines()) == 1 + 70


# -- bad input ----------------------------------------------------------------------------------


def test_bad_input_is_refused_with_a_reason() -> None:
    room = _room()
    g = DoseGrid(0.05)
    with pytest.raises(ValueError, match="lamp x must be a finite number"):
        g.add(LAMP, math.nan, 1.0, 1.0, room)
    with pytest.raises(ValueError, match="lamp y must be a finite number"):
        irradiance(LAMP, 1.0, math.inf, room.free, 0.05, room.origin)
    with pytest.raises(ValueError, match="seconds must be >= 0"):
        g.add(LAMP, 1.0, 1.0, -1.0, room)
    with pytest.raises(ValueError, match="seconds must be a finite number"):
        g.add(LAMP, 1.0, 1.0, math.nan, room)
    assert g.lamp_seconds == 0.0 and g.dose.size == 0  # nothing was disturbed
    for bad in (0.0, -5.0, math.nan, math.inf):
        with pytest.raises(ValueError, match=r"target dose must be a finite number > 0 J/m²"):
            g.covered(bad, room)
        with pytest.raises(ValueError, match="target dose"):
            summarise(g, bad, room)
        with pytest.raises(ValueError, match="target dose"):
            pgm_report(g, bad, room)
    with pytest.raises(ValueError, match="no floor cells"):
        g.covered(100.0, FloorMask(np.zeros((3, 3), dtype=bool), 0.05, (0.0, 0.0)))


def test_bad_lamps_and_grids_are_refused() -> None:
    with pytest.raises(ValueError, match="uvc_power_w: must be a finite number"):
        Lamp(math.nan, 0.6)
    with pytest.raises(ValueError, match="uvc_power_w: must be > 0 W"):
        Lamp(0.0, 0.6)
    with pytest.raises(ValueError, match="nearer than min_distance_m"):
        Lamp(10.0, 0.2)  # the floor is nearer the lamp than the model holds (0.3 m)
    with pytest.raises(ValueError, match="the tube's lower end"):
        Lamp(10.0, 0.6, tube_length_m=1.2)
    with pytest.raises(ValueError, match="cannot merge"):
        DoseGrid.merged([DoseGrid(0.05), DoseGrid(0.1)])
    with pytest.raises(ValueError, match=r"not on the 0\.05 m lattice"):
        DoseGrid.from_array(np.zeros((2, 2)), 0.05, (0.01, 0.0))
    with pytest.raises(ValueError, match="finite and >= 0"):
        DoseGrid.from_array(np.array([[1.0, math.nan]]), 0.05, (-0.025, -0.025))
    with pytest.raises(ValueError, match="2-D bool array"):
        FloorMask(np.ones((3, 3)), 0.05, (0.0, 0.0))  # type: ignore[arg-type]


def test_floor_mask_from_map_cells() -> None:
    cells = np.array([[-1, 0, 25, 26, 100]], dtype=np.int8)
    assert FloorMask.from_occupancy(cells, 0.05, (0.0, 0.0)).free.tolist() == [[False, True, True, False, False]]
    assert FloorMask.from_occupancy(cells, 0.05, (0.0, 0.0), unknown_is_free=True).free.tolist() == [
        [True, True, True, False, False]
    ]


def test_lamp_reads_from_configuration() -> None:
    from fleetlink.shared.config import ConfigError, loads

    lamp = loads("uvc_power_w = 12.0\nheight_m = 0.7\n", Lamp)
    assert lamp == Lamp(12.0, 0.7)
    with pytest.raises(ConfigError, match="height_m"):
        loads("uvc_power_w = 12.0\nheight_m = 0.1\n", Lamp)


# -- speed ----------------------------------------------------------------------------------------


def test_speed_budget() -> None:
    """One call for a 10 m radius at 0.05 m cells in a walled 24 x 16 m floor: ~7 ms measured here
    (docs/payload.md); the bound is loose so a shared machine never fails it."""
    res = 0.05
    free = np.ones((round(16 / res), round(24 / res)), dtype=bool)
    free[:2, :] = free[-2:, :] = False
    free[:, :2] = free[:, -2:] = False
    free[:, round(8 / res)] = False
    free[round(4 / res) : round(5 / res), round(8 / res)] = True  # a door
    free[round(8 / res), :] = False
    free[round(8 / res), round(3 / res) : round(4 / res)] = True
    rng = np.random.default_rng(0)
    irradiance_window(LAMP, 12.0, 8.5, free, res, (0.0, 0.0))
    times = []
    for _ in range(10):
        x, y = rng.uniform(1, 23), rng.uniform(1, 15)
        t0 = time.perf_counter()
        irradiance_window(LAMP, x, y, free, res, (0.0, 0.0), max_radius_m=10.0)
        times.append(time.perf_counter() - t0)
    assert float(np.median(times)) < 0.1
