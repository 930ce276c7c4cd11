"""The map's renderer (operator/maprender.py) without Textual: grids and overlays in, rows out."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from rich.color import Color
from rich.style import Style

from fleetlink.operator import maprender as mr
from fleetlink.operator.fleet import SCAN_STALE_S, FleetModel, Grid
from fleetlink.operator.maprender import (
    CLASSES,
    DOSE_PIXELS,
    FREE,
    PIXEL_COLOURS,
    SCAN,
    TRAIL,
    UNKNOWN,
    WALL,
    MapGeometry,
    MapPainter,
    cell_codes,
    dose_pixels,
    raster_grids,
    render_row,
)
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import Pose, Scan
from fleetlink.shared.scan_codec import scan_fields

ME = "operator-1"


def colour(pixel: int) -> Color:
    return Color.parse(PIXEL_COLOURS[pixel])


def grid(cells: list[list[int]], origin: tuple[float, float], res: float) -> Grid:
    """A fleet-model grid from rows listed top first (as they look), 0 free, 100 wall, 255 unknown."""
    rows = np.array(cells[::-1], dtype=np.uint8)  # the wire's grids run from origin_y up
    return (origin[0], origin[1], res, rows.shape[1], rows.shape[0], rows.tobytes())


def pose(fleet: FleetModel, robot: str, x: float, y: float, theta: float = 0.0) -> None:
    counter = wire.HeaderCounter(SimClock(start=1.0), robot=robot, sender=f"agent-{robot}")
    msg = counter.make(
        Pose, x=x, y=y, theta=theta, sd_x_m=0.05, sd_y_m=0.05, sd_theta_rad=0.01, odom_x=x, odom_y=y,
        odom_theta=theta, vx=0.0, omega=0.0, uwbStale=False,
    )  # fmt: skip
    fleet.apply(msg, "zenoh", 1.0)


# -- half blocks ------------------------------------------------------------------------------------


def test_a_2x2_block_of_grid_cells_becomes_two_half_block_characters() -> None:
    """Two cells of 1 m x 2 m over a 2 x 2 grid of 1 m cells: each cell shows its column's two
    grid cells, the top one as ▀'s colour, the bottom one as its background; one colour: a space."""
    g = MapGeometry(2, 1, center_x=0.0, center_y=0.0, scale=1.0)
    cells = [
        [255, 100],  # top: unknown, wall
        [0, 100],  # bottom: free, wall
    ]
    pixels = raster_grids(g, [grid(cells, (-1.0, -1.0), 1.0)])
    assert pixels.tolist() == [[UNKNOWN, WALL], [FREE, WALL]]
    codes = cell_codes(pixels)
    assert codes.tolist() == [[UNKNOWN * CLASSES + FREE, WALL * CLASSES + WALL]]
    segments = render_row(codes[0].tolist(), {}, {})
    assert [s.text for s in segments] == ["▀", " "]
    left, right = segments[0].style, segments[1].style
    assert left is not None and right is not None
    assert (left.color, left.bgcolor) == (colour(UNKNOWN), colour(FREE))
    assert right.bgcolor == colour(WALL)


@pytest.mark.parametrize(
    ("top", "bottom", "char"),
    [(WALL, FREE, "▀"), (FREE, WALL, "▀"), (FREE, FREE, " "), (UNKNOWN, UNKNOWN, " "), (SCAN, TRAIL, "▀")],
)
def test_every_pair_of_pixels_has_its_own_look(top: int, bottom: int, char: str) -> None:
    (segment,) = render_row([top * CLASSES + bottom], {}, {})
    assert segment.text == char and segment.style is not None
    if char == "▀":
        assert (segment.style.color, segment.style.bgcolor) == (colour(top), colour(bottom))
    else:
        assert segment.style.bgcolor == colour(top)


def test_the_grid_is_merged_wall_over_free_over_unknown_and_a_thin_wall_shows_zoomed_out() -> None:
    g = MapGeometry(4, 2, scale=1.0)  # 4 x 4 pixels of 1 m from (-2, -2)
    free = grid([[0] * 40 for _ in range(40)], (-2.0, -2.0), 0.1)
    wall = [[255] * 40 for _ in range(40)]
    for row in wall:
        row[13] = 100  # a 10 cm wall at x = -0.7 .. -0.6, between two pixel centres
    pixels = raster_grids(g, [free, grid(wall, (-2.0, -2.0), 0.1)])
    assert (pixels[:, 1] == WALL).all()  # the pixel column x = -1 .. 0 holds the wall
    assert (pixels[:, [0, 2, 3]] == FREE).all()
    assert (raster_grids(g, []) == UNKNOWN).all()


def test_cells_and_pixels_agree_with_the_geometry() -> None:
    rnd = random.Random(3)
    g = MapGeometry(50, 20, center_x=1.3, center_y=-2.1, scale=0.17)
    xs, ys = g.pixel_centres()
    for _ in range(500):
        x, y = rnd.uniform(-10, 10), rnd.uniform(-10, 10)
        col, prow = g.to_pixel(x, y)
        assert (col, prow // 2) == g.to_cell(x, y)
        if 0 <= col < g.width and 0 <= prow < 2 * g.height:
            assert abs(xs[col] - x) <= g.scale / 2 + 1e-9 and abs(ys[prow] - y) <= g.scale / 2 + 1e-9


# -- the dose layer ---------------------------------------------------------------------------------


def test_dose_is_coloured_by_its_share_of_the_target_and_walls_stay_walls() -> None:
    target = 100.0
    doses = np.array([[0.0, 10.0, 30.0, 60.0, 90.0, 100.0, 250.0, 500.0]])
    pixels = np.array([[FREE, FREE, UNKNOWN, FREE, FREE, FREE, FREE, WALL]], dtype=np.uint8)
    dose_pixels(pixels, doses, target)
    assert pixels.tolist() == [[FREE, *DOSE_PIXELS, DOSE_PIXELS[-1], WALL]]


# -- the painter: scan, glyphs, legend --------------------------------------------------------------


def test_a_scan_point_lands_in_its_character_cell_and_half() -> None:
    """The selected robot's scan: a point in the top half of a cell colours that cell's ▀, in the
    bottom half its background; another robot's scan is not drawn."""
    fleet = FleetModel(ME)
    g = MapGeometry(20, 10, scale=0.5)  # cells 0.5 m x 1 m, pixels 0.5 m
    pose(fleet, "r1", 0.1, 0.1)
    pose(fleet, "r2", -3.0, -3.0)
    top = (2.2, 1.9)  # cell (14, 3): y 1..2, its top half 1.5..2
    bottom = (-2.2, -1.7)  # cell (5, 6): y -2..-1, its bottom half -2..-1.5
    fleet.set_scan("r1", np.array([top, bottom, (100.0, 0.0)]), 1.0)  # the last one off the view
    fleet.set_scan("r2", np.array([(4.2, 0.2)]), 1.0)
    frame = MapPainter().paint(fleet, g, "r1", legend=False)
    assert g.to_cell(*top) == (14, 3) and g.to_cell(*bottom) == (5, 6)
    assert frame.pixels(14, 3) == (SCAN, UNKNOWN)
    assert frame.pixels(5, 6) == (UNKNOWN, SCAN)
    char, style = frame.cell(14, 3)
    assert char == "▀" and style.color == colour(SCAN) and style.bgcolor == colour(UNKNOWN)
    assert frame.pixels(*g.to_cell(4.2, 0.2)) == (UNKNOWN, UNKNOWN)  # r2 is not selected
    assert int((frame.codes // CLASSES == SCAN).sum() + (frame.codes % CLASSES == SCAN).sum()) == 2
    other = MapPainter().paint(fleet, g, "r2", legend=False)
    assert other.pixel(*g.to_pixel(4.2, 0.2)) == SCAN


def test_robots_homes_goals_marks_anchors_and_alarms_have_their_own_glyphs_on_the_map_colour() -> None:
    fleet = FleetModel(ME)
    g = MapGeometry(40, 12, scale=0.25)
    fleet.set_grid("r1", grid([[0] * 100 for _ in range(60)], (-5.0, -3.0), 0.1))  # all floor
    pose(fleet, "r1", 0.1, 0.1, math.pi / 2)
    view = fleet.robots["r1"]
    view.home, view.goal = (-2.0, 1.0), (2.0, -1.0)
    fleet.add_anchor("a1", -4.0, 2.0)
    frame = MapPainter().paint(fleet, g, None, legend=False)
    floor = colour(FREE)
    for (x, y), want in [((0.1, 0.1), "↑"), ((-2.0, 1.0), "⌂"), ((2.0, -1.0), "◎"), ((-4.0, 2.0), "A")]:
        char, style = frame.cell(*g.to_cell(x, y))
        assert char == want and style.bgcolor == floor, (want, char, style)
    col, row = g.to_cell(0.1, 0.1)
    assert frame.text(row)[col : col + 4] == "↑ r1"  # its name beside it
    selected = MapPainter().paint(fleet, g, "r1", legend=False)
    assert selected.cell(col, row)[1] == mr.SELECTED_STYLE  # its own background when selected


def test_names_that_would_run_into_one_already_drawn_are_left_out_the_selected_first() -> None:
    fleet = FleetModel(ME)
    g = MapGeometry(40, 12, scale=0.25)  # a cell 0.25 m wide
    for robot, x in (("r1", 0.1), ("r2", 0.35), ("r3", 2.1)):  # side by side, and 8 cells on
        pose(fleet, robot, x, 0.1)
    col, row = g.to_cell(0.1, 0.1)
    frame = MapPainter().paint(fleet, g, None, legend=False)
    # r1's name, then r2's, which would run into it: left out; r3's is clear of both.
    assert frame.text(row)[col : col + 12] == "→→r1    → r3"
    chosen = MapPainter().paint(fleet, g, "r2", legend=False)
    assert chosen.text(row)[col : col + 12] == "→→ r2   → r3"  # the selected robot's name first


def test_a_robots_alarm_is_a_bang_beside_it_coloured_by_severity() -> None:
    from fleetlink.operator.alarms import AlarmKind, AlarmSeverity

    fleet = FleetModel(ME)
    g = MapGeometry(40, 12, scale=0.25)
    pose(fleet, "r1", 0.1, 0.1)
    fleet.alarms.alarms.raise_alarm("r1", AlarmKind.LOW_BATTERY, "battery 4 %", 1.0, severity=AlarmSeverity.CRITICAL)
    painter = MapPainter()
    col, row = g.to_cell(0.1, 0.1)
    frame = painter.paint(fleet, g, None, legend=False)
    assert frame.cell(col + 1, row) == ("!", mr.ALARM_STYLES[AlarmSeverity.CRITICAL])
    assert frame.text(row)[col : col + 4] == "→!r1"
    assert not isinstance(fleet.alarms.alarms.acknowledge("r1", AlarmKind.LOW_BATTERY, "op-2", 2.0), str)
    frame = painter.paint(fleet, g, None, legend=False)  # redrawn: the alarms' version moved
    assert frame.glyph(col + 1, row) == mr.Glyph("!", mr.ACKED_ALARM_STYLE)
    fleet.robots["r1"].home = g.to_world(col + 1, row)  # its home beside it: the alarm goes over it
    pose(fleet, "r2", *g.to_world(col - 1, row))  # another robot on its left
    frame = painter.paint(fleet, g, None, legend=False)
    assert frame.text(row)[col - 1 : col + 2] == "→→!"
    pose(fleet, "r3", *g.to_world(col + 1, row))  # and one on its right: the alarm has no room
    frame = painter.paint(fleet, g, None, legend=False)
    assert frame.text(row)[col - 1 : col + 2] == "→→→"


def test_marks_of_each_kind_look_different() -> None:
    assert len({mr.mark_glyph(k).char for k in ("casualty", "hazard", "note", "anything")}) == 3
    assert mr.mark_glyph("note") == mr.mark_glyph("anything")


def test_the_legend_says_what_the_colours_and_glyphs_mean_and_fits_the_width() -> None:
    fleet = FleetModel(ME)
    g = MapGeometry(60, 12, scale=0.25)
    frame = MapPainter().paint(fleet, g, None)
    lines = [frame.text(g.height - 2), frame.text(g.height - 1)]
    text = " ".join(lines)
    for word in ("wall", "floor", "unknown", "trail", "robot", "alarm", "home", "goal", "casualty", "Anchor", "zone"):
        assert word in text, word
    assert "scan" not in text  # no scan drawn, none explained
    assert all(len(line) == g.width for line in lines)
    for width in (30, 60, 200):
        rows = mr.legend_rows(width, scan=True, dose_target=50.0)
        assert "dose of 50 J/m²" in "".join(t for t, _ in rows[0])
        assert all(sum(len(t) for t, _ in line) <= width for line in rows[1:])
        assert len(rows) <= 1 + mr.LEGEND_LINES
    hidden = MapPainter().paint(fleet, g, None, legend=False)
    assert "wall" not in hidden.text(g.height - 1)


def test_unchanged_rows_keep_their_keys_and_a_robot_that_moves_changes_only_its_row() -> None:
    fleet = FleetModel(ME)
    g = MapGeometry(40, 12, scale=0.25)
    fleet.set_grid("r1", grid([[0] * 100 for _ in range(60)], (-5.0, -3.0), 0.1))
    pose(fleet, "r1", 0.1, 0.1)
    painter = MapPainter()
    before = painter.paint(fleet, g, None)
    builds = painter.base_builds
    robot = fleet.robots["r1"]
    robot.pose = (1.1, 0.1, 0.0)  # along its row, no trail point
    after = painter.paint(fleet, g, None)
    assert painter.base_builds == builds  # the map layer kept
    changed = [y for y in range(g.height) if before.row_key(y) != after.row_key(y)]
    assert changed == [g.to_cell(0.1, 0.1)[1]]
    segments = after.row(changed[0])
    assert sum(len(s.text) for s in segments) == g.width
    assert all(isinstance(s.style, Style) for s in segments)


def test_fit_shows_every_point_and_keeps_the_zoom_for_one() -> None:
    g = MapGeometry(80, 24, scale=0.25)
    g.fit([(3.0, 4.0)])
    assert (g.center_x, g.center_y, g.scale) == (3.0, 4.0, 0.25)
    points = [(-1.0, -1.0), (7.0, -1.0), (7.0, 4.0), (-1.0, 4.0)]
    g.fit(points)
    assert (g.center_x, g.center_y) == (3.0, 1.5)
    for x, y in points:
        col, row = g.to_cell(x, y)
        assert 0 < col < g.width - 1 and 0 < row < g.height - 1
    g.fit([(0.0, 0.0), (1e6, 0.0)])
    assert g.scale == 20.0  # the zoom's bounds


def test_a_scan_on_the_wire_becomes_the_robots_points_until_it_is_stale() -> None:
    """A ``Scan`` folded into the fleet model: its returns in the site frame (no return: no point);
    a scan whose ranges are not ``count`` uint16s is refused; ``SCAN_STALE_S`` later it is let go."""
    fleet = FleetModel(ME)
    counter = wire.HeaderCounter(SimClock(start=1.0), robot="r1", sender="agent-r1")
    q = math.pi / 4  # four beams: each a quarter turn, its bearing the quarter's middle
    fields = scan_fields([q, 3 * q, 5 * q], [2.0, 0.0, 1.0], (1.0, 1.0, math.pi / 2), beams=4)
    assert fleet.apply(counter.make(Scan, **fields), "zenoh", 10.0)
    points = fleet.robots["r1"].scan
    assert points is not None and points.shape == (2, 2)  # beam 1 had no return
    heading = math.pi / 2
    for (x, y), (r, bearing) in zip(points, ((2.0, q), (1.0, 5 * q)), strict=True):
        assert (x, y) == pytest.approx((1.0 + r * math.cos(heading + bearing), 1.0 + r * math.sin(heading + bearing)))
    bad = counter.make(Scan, **{**fields, "ranges": fields["ranges"][:-2]})
    assert not fleet.apply(bad, "zenoh", 10.1)
    assert fleet.robots["r1"].scan is points
    version = fleet.version
    fleet.tick(10.0 + SCAN_STALE_S)
    assert fleet.robots["r1"].scan is points
    fleet.tick(10.0 + SCAN_STALE_S + 0.1)
    assert fleet.robots["r1"].scan is None and fleet.version > version


def test_a_map_update_rasters_that_map_only() -> None:
    fleet = FleetModel(ME)
    g = MapGeometry(40, 12, scale=0.25)
    for k, robot in enumerate(("r1", "r2", "r3")):
        fleet.set_grid(robot, grid([[0] * 20 for _ in range(20)], (-5.0 + 3 * k, -1.0), 0.1))
    painter = MapPainter()
    painter.paint(fleet, g, None)
    assert painter.rasters == 3
    wall = grid([[100] * 20 for _ in range(20)], (-2.0, -1.0), 0.1)
    fleet.set_grid("r2", wall)  # r2's map changed
    frame = painter.paint(fleet, g, None)
    assert painter.rasters == 4
    assert frame.pixel(*g.to_pixel(-1.0, 0.0)) == WALL and frame.pixel(*g.to_pixel(-4.0, 0.0)) == FREE
    painter.paint(fleet, g, None)
    assert painter.rasters == 4
    g.pan(1, 0)  # a new view: every map again
    painter.paint(fleet, g, None)
    assert painter.rasters == 7
