"""Log-odds grid: the update equations, clamping, one update per cell per scan, growth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fleetlink.agent.mapping.grid import GridConfig, LogOddsGrid, logit


def _beam(grid: LogOddsGrid, r: float = 2.0, hit: bool = True) -> None:
    grid.integrate((0.0, 0.0, 0.0), np.array([r]), np.array([0.0]), np.array([hit]))


def _p(grid: LogOddsGrid, x: float, y: float) -> float:
    col, row = (int(v) for v in np.floor(grid.to_cell(np.array([[x, y]])))[0])
    return float(grid.probability()[row, col])


def test_hits_and_misses_follow_the_log_odds_equations() -> None:
    cfg = GridConfig(resolution=0.1, p_occ=0.7, p_free=0.4, l_min=-5.0, l_max=5.0)
    g = LogOddsGrid(cfg)
    for n in range(1, 4):
        _beam(g)
        # l_n = n * log(p_occ / (1 - p_occ)) (prior 0.5): p = 1 - 1 / (1 + exp(l)).
        want_hit = 1.0 - 1.0 / (1.0 + math.exp(n * logit(0.7)))
        want_free = 1.0 - 1.0 / (1.0 + math.exp(n * logit(0.4)))
        assert _p(g, 2.02, 0.0) == pytest.approx(want_hit, rel=1e-5)
        assert _p(g, 1.0, 0.0) == pytest.approx(want_free, rel=1e-5)
    assert _p(g, 3.0, 0.0) == pytest.approx(0.5)  # beyond the hit: untouched
    occ = g.occupancy()
    col, row = (int(v) for v in np.floor(g.to_cell(np.array([[3.0, 0.0]])))[0])
    assert occ[row, col] == -1  # never seen


def test_non_half_prior_is_subtracted() -> None:
    cfg = GridConfig(resolution=0.1, p_occ=0.8, p_free=0.3, p_prior=0.4, l_min=-9.0, l_max=9.0)
    g = LogOddsGrid(cfg)
    _beam(g)
    # l_1 = logit(p_occ) - logit(p0) with l_0 = 0 stored as the prior's offset.
    assert g.logodds.max() == pytest.approx(logit(0.8) - logit(0.4), rel=1e-5)


def test_clamping_bounds_the_log_odds() -> None:
    g = LogOddsGrid(GridConfig(resolution=0.1, l_min=-1.0, l_max=2.0))
    for _ in range(30):
        _beam(g)
    assert g.logodds.max() == pytest.approx(2.0)
    assert g.logodds.min() == pytest.approx(-1.0)


def test_a_cell_counts_once_per_scan_and_a_hit_beats_a_crossing() -> None:
    g = LogOddsGrid(GridConfig(resolution=0.1, l_min=-9.0, l_max=9.0))
    # 50 nearly parallel beams cross the same cells near the sensor; two end in the same cell.
    ang = np.linspace(-0.01, 0.01, 50)
    r = np.full(50, 2.0)
    g.integrate((0.0, 0.0, 0.0), r, ang, np.ones(50, dtype=bool))
    assert g.logodds.min() == pytest.approx(g.l_free, rel=1e-5)
    assert g.logodds.max() == pytest.approx(g.l_occ, rel=1e-5)
    # A beam that passes through a cell another beam of the same scan ends in: still "hit".
    g2 = LogOddsGrid(GridConfig(resolution=0.1, l_min=-9.0, l_max=9.0))
    g2.integrate((0.0, 0.0, 0.0), np.array([1.05, 3.0]), np.array([0.0, 0.0]), np.array([True, True]))
    assert _p(g2, 1.05, 0.0) > 0.5


def test_no_hit_beams_only_clear() -> None:
    g = LogOddsGrid(GridConfig(resolution=0.1))
    _beam(g, 2.0, hit=False)
    assert g.logodds.max() <= 0.0
    assert g.logodds.min() < 0.0


def test_grid_grows_and_keeps_what_it_knew() -> None:
    g = LogOddsGrid(GridConfig(resolution=0.1, grow_step=2.0))
    _beam(g, 2.0)
    shape0, origin0 = g.shape, g.origin
    g.integrate((30.0, -20.0, 0.0), np.array([2.0]), np.array([math.pi / 2]), np.array([True]))
    assert g.shape[0] > shape0[0] and g.shape[1] > shape0[1]
    assert g.origin[1] < origin0[1]
    assert _p(g, 2.02, 0.0) > 0.6  # the first hit survived the move
    assert _p(g, 30.0, -17.98) > 0.6
    assert g.shape[0] % g.config.coarse == 0 and g.shape[1] % g.config.coarse == 0
    assert g.coarse_field.max() == pytest.approx(float(g.field.max())) and g.field.max() > 0.0


def test_chunked_free_space_and_banded_occupancy_change_no_value(monkeypatch: pytest.MonkeyPatch) -> None:
    """``integrate`` traces free space in chunks and ``occupancy`` works in bands of rows, to bound
    an agent's peak memory: any chunk or band size gives the same cells, box and map."""
    from fleetlink.agent.mapping import grid as grid_module

    rng = np.random.default_rng(7)
    scans = []
    for _ in range(12):
        n = int(rng.integers(1, 400))
        hit = rng.random(n) > 0.2
        scans.append(
            (
                (float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3))),
                rng.uniform(0.16, 9.0, n),
                np.sort(rng.uniform(-np.pi, np.pi, n)),
                hit,
            )
        )

    def build(chunk: int, band: int) -> tuple[list[object], LogOddsGrid, np.ndarray]:
        monkeypatch.setattr(grid_module, "_FREE_CHUNK", chunk)
        monkeypatch.setattr(grid_module, "_OCCUPANCY_BAND", band)
        g = LogOddsGrid()
        boxes: list[object] = [g.integrate(pose, r, a, hit) for pose, r, a, hit in scans]
        return boxes, g, g.occupancy()

    boxes, whole, occ = build(10**9, 10**9)  # one chunk, one band
    for chunk, band in ((1, 1), (7, 333), (150, 5000)):
        b, g, o = build(chunk, band)
        assert b == boxes
        assert np.array_equal(g.logodds, whole.logodds) and np.array_equal(g.seen, whole.seen)
        assert np.array_equal(g.field, whole.field)
        assert np.array_equal(o, occ)
    assert (occ >= 0).any() and (occ == -1).any()


def test_occupancy_read_between_scans_is_the_occupancy_computed_whole() -> None:
    """``occupancy`` computes again only the box the scans since its last call changed: read after
    every scan, through the grid's growth and a clear, it gives what computing every cell gives, and
    a caller's copy is its own."""
    from fleetlink.agent.mapping.grid import _p_occupied

    def whole(g: LogOddsGrid) -> np.ndarray:
        out = np.rint(100.0 * _p_occupied(g.logodds)).astype(np.int8)
        out[~g.seen] = -1
        return out

    rng = np.random.default_rng(11)
    g = LogOddsGrid(GridConfig(grow_step=1.0))
    reads = 0
    for k in range(40):
        n = int(rng.integers(1, 300))
        centre = (float(rng.uniform(-6, 6)), float(rng.uniform(-6, 6)))  # far apart: the grid grows
        pose = (centre[0], centre[1], float(rng.uniform(-3, 3)))
        g.integrate(pose, rng.uniform(0.16, 5.0, n), np.sort(rng.uniform(-np.pi, np.pi, n)), rng.random(n) > 0.2)
        if k == 25:
            g.clear()  # a redraw begins: every cell unknown again
        if rng.random() < 0.6:
            cells = g.occupancy()
            reads += 1
            assert np.array_equal(cells, whole(g)), k
            cells[:] = 100  # the caller's copy
    assert reads > 10 and np.array_equal(g.occupancy(), whole(g))


def test_a_field_refreshed_late_is_the_field_refreshed_per_scan() -> None:
    """``integrate(refresh=False)`` remembers what it changed (shifted when the grid grows) and
    ``refresh_stale`` brings the likelihood field and its coarse copy to the same values, to the bit,
    as refreshing after every scan: the whole grid is refreshed only when it is read."""
    rng = np.random.default_rng(11)
    now, late = LogOddsGrid(GridConfig(grow_step=2.0)), LogOddsGrid(GridConfig(grow_step=2.0))
    for k in range(15):
        pose = (float(rng.uniform(-1, 1)) + 0.8 * k, float(rng.uniform(-1, 1)) - 0.5 * k, float(rng.uniform(-3, 3)))
        n = int(rng.integers(20, 200))
        r, a, hit = rng.uniform(0.2, 6.0, n), np.sort(rng.uniform(-np.pi, np.pi, n)), rng.random(n) > 0.2
        now.integrate(pose, r, a, hit)
        late.integrate(pose, r, a, hit, refresh=False)
    assert late.stale is not None and not np.array_equal(late.field, now.field)
    late.refresh_stale()
    assert late.stale is None
    assert late.shape == now.shape and late.origin == now.origin
    assert np.array_equal(late.field, now.field) and np.array_equal(late.coarse_field, now.coarse_field)


@pytest.mark.parametrize("coarse", [1, 3, 4])
def test_the_field_refreshed_around_changed_cells_is_the_whole_field_refreshed(coarse: int) -> None:
    """Per scan the likelihood field is recomputed only over small tiles around the cells whose
    occupied evidence changed (``_refresh_cells``); it must equal, to the bit, the field and coarse
    field computed over the whole grid, through growth, walls cleared again, and any coarse factor."""
    rng = np.random.default_rng(5)
    grid = LogOddsGrid(GridConfig(grow_step=2.0, coarse=coarse))
    tiled = 0
    original = grid._refresh_cells

    def counted(changed: np.ndarray) -> bool:
        nonlocal tiled
        done = original(changed)
        tiled += done and changed.size > 0
        return done

    grid._refresh_cells = counted  # type: ignore[method-assign]
    for k in range(25):
        pose = (float(rng.uniform(-1, 1)) + 0.3 * k, float(rng.uniform(-1, 1)), float(rng.uniform(-3, 3)))
        n = int(rng.integers(20, 300))
        r, a, hit = rng.uniform(0.2, 5.0, n), np.sort(rng.uniform(-np.pi, np.pi, n)), rng.random(n) > 0.3
        grid.integrate(pose, r, a, hit)
        whole = LogOddsGrid(GridConfig(grow_step=2.0, coarse=coarse))
        whole._realloc(0, 0, *grid.shape, *grid.origin, fresh=True)
        whole.logodds[:] = grid.logodds
        whole.refresh()
        assert np.array_equal(grid.field, whole.field), k
        assert np.array_equal(grid.coarse_field, whole.coarse_field), k
    assert tiled >= 20  # the tiles did the work, not the fallback


def test_tiles_past_the_grid_edge_fall_back_to_the_box() -> None:
    grid = LogOddsGrid(GridConfig(grow_step=1.0))
    _beam(grid, 2.0)
    h, w = grid.shape
    assert not grid._refresh_cells(np.array([w + 1], dtype=np.int64))  # row 1: the tile would leave the grid
    assert not grid._refresh_cells(np.array([(h // 2) * w + w - 2], dtype=np.int64))
    assert grid._refresh_cells(np.array([(h // 2) * w + w // 2], dtype=np.int64))
