"""The map's renderer: occupancy grids, layers and overlays in, styled rows out (docs/console.md, "Map").

Pure: numpy and Rich styles, no Textual, no I/O; the widget (operator/mapview.py) only sizes it,
asks for rows and refreshes the lines whose rows changed.

**Half blocks.** One terminal cell is ``scale`` metres wide and ``2 * scale`` metres tall
(``MapGeometry``; terminal cells are about twice as tall as wide) and shows two *pixels*, each
``scale`` metres square: the top one as the foreground of ``▀``, the bottom one as its background
(a cell whose two pixels have one colour is a space on that colour). Every pixel has its own
colour, so floor, walls, unknown, trails, the dose layer and the lidar scan are all areas of
colour at twice the old vertical resolution. Braille (2 x 4 dots a cell) has four times the
pixels but one colour per cell and dots that do not fill: an occupancy grid turns into a stipple
and free, unknown and dose cannot be told apart dot by dot; docs/console.md says more.

**Layers, bottom up.** Pixels: the robots' maps merged (occupied wins over free, free over
unknown; every occupied grid cell marks its pixel, so a thin wall shows zoomed out), the dose
layer when shown (floor and unknown pixels coloured by dose relative to the target), the trails
(under the dose), the selected robot's latest lidar scan. Glyphs over the pixels (on the colour of
the pixel beneath): people-present zones ``░``, anchors ``A``, the selected robot's round, marks,
homes ``⌂``, goals ``◎``, robots (an arrow for the heading), their alarms ``!`` and names; the
legend on the bottom line (and the dose scale above it when the layer is shown).

``MapPainter.paint`` keeps what does not change between frames: the base pixels (maps, dose,
zones, anchors) are rebuilt only when the maps, the dose layer, the zones or the view changed; the
trails are kept by each robot's new and dropped points (``RobotView.trail_added``); goals, marks,
robots and the scan each frame. A ``MapFrame`` gives each row a key: a row whose key did not
change renders the same, so the widget keeps its rendered line.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from rich.color import Color
from rich.segment import Segment
from rich.style import Style

from fleetlink.operator.alarms import AlarmSeverity
from fleetlink.operator.dose import FleetDose
from fleetlink.operator.fleet import FleetModel, Grid
from fleetlink.shared.geometry import points_in_polygon
from fleetlink.shared.keys import FLEET_MAP

__all__ = [
    "ASPECT",
    "DOSE_STEPS",
    "PIXEL_COLOURS",
    "Glyph",
    "MapFrame",
    "MapGeometry",
    "MapPainter",
    "cell_codes",
    "dose_pixels",
    "fit_points",
    "heading_char",
    "legend_rows",
    "raster_grids",
    "render_row",
    "scan_pixels",
]

ASPECT = 2.0
"""A terminal cell is this many times as tall as it is wide (and holds this many pixels)."""
HEADING_CHARS = "→↗↑↖←↙↓↘"

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]


@dataclass(slots=True)
class MapGeometry:
    """Which part of the world the map shows: ``width`` x ``height`` terminal cells centred on
    (``center_x``, ``center_y``), world +y up; a cell is ``scale`` m wide and ``ASPECT * scale``
    m tall, two pixels of ``scale`` m each stacked."""

    width: int
    height: int
    center_x: float = 0.0
    center_y: float = 0.0
    scale: float = 0.25
    """Metres per cell, horizontally (and per pixel, both ways)."""

    def to_world(self, col: int, row: int) -> tuple[float, float]:
        """Centre of cell (col, row) in metres."""
        x = self.center_x + (col + 0.5 - self.width / 2) * self.scale
        y = self.center_y - (row + 0.5 - self.height / 2) * self.scale * ASPECT
        return x, y

    def to_cell(self, x: float, y: float) -> tuple[int, int]:
        col = math.floor((x - self.center_x) / self.scale + self.width / 2)
        row = math.floor(-(y - self.center_y) / (self.scale * ASPECT) + self.height / 2)
        return col, row

    def to_pixel(self, x: float, y: float) -> tuple[int, int]:
        """(col, pixel row): pixel row ``2 * row`` is the top half of cell row ``row``."""
        col = math.floor((x - self.center_x) / self.scale + self.width / 2)
        prow = math.floor(-(y - self.center_y) / self.scale + self.height * ASPECT / 2)
        return col, prow

    def pixel_centres(self) -> tuple[F64, F64]:
        """The world x of every pixel column and y of every pixel row (top first)."""
        xs = self.center_x + (np.arange(self.width) + 0.5 - self.width / 2) * self.scale
        ys = self.center_y - (np.arange(2 * self.height) + 0.5 - self.height) * self.scale
        return xs.astype(np.float64), ys.astype(np.float64)

    def inside(self, col: int, row: int) -> bool:
        return 0 <= col < self.width and 0 <= row < self.height

    def zoom(self, factor: float) -> None:
        self.scale = min(20.0, max(0.02, self.scale * factor))

    def pan(self, dcols: float, drows: float) -> None:
        self.center_x += dcols * self.scale
        self.center_y -= drows * self.scale * ASPECT

    def fit(self, points: Sequence[tuple[float, float]], *, margin: float = 0.1) -> None:
        """Centre on ``points`` and, when they spread, zoom so they all show with ``margin`` (a
        fraction of the view) to spare on every side; one point: centre only, same zoom."""
        if not points:
            return
        xs = [p[0] for p in points]
        ys = [p[1] for p in points]
        x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
        self.center_x, self.center_y = (x0 + x1) / 2, (y0 + y1) / 2
        if x1 - x0 > 0 or y1 - y0 > 0:
            usable = 1 - 2 * margin
            scale = max((x1 - x0) / (self.width * usable), (y1 - y0) / (self.height * ASPECT * usable))
            self.scale = max(FIT_FINEST, scale)
            self.zoom(1.0)  # within the zoom's bounds

    def key(self) -> tuple[int, int, float, float, float]:
        return (self.width, self.height, self.center_x, self.center_y, self.scale)


FIT_FINEST = 0.05
"""``fit`` zooms in no further than this many metres a cell (a map's usual resolution)."""


def fit_points(fleet: FleetModel) -> list[tuple[float, float]]:
    """What ``f`` fits the view to: the robots, the UWB anchors and the corners of what the maps
    have seen (the fleet map's alone when there is one)."""
    points = [v.pose[:2] for v in fleet.robots.values() if v.pose is not None]
    points += list(fleet.anchors.values())
    grids = fleet.grids
    if FLEET_MAP in grids:
        grids = {FLEET_MAP: grids[FLEET_MAP]}
    for ox, oy, res, w, h, data in grids.values():
        known = np.frombuffer(data, dtype=np.uint8).reshape(h, w) != 255
        rows, cols = np.nonzero(known.any(axis=1))[0], np.nonzero(known.any(axis=0))[0]
        if rows.size:
            points.append((ox + float(cols[0]) * res, oy + float(rows[0]) * res))
            points.append((ox + float(cols[-1] + 1) * res, oy + float(rows[-1] + 1) * res))
    return points


def heading_char(theta: float) -> str:
    return HEADING_CHARS[round(theta / (math.pi / 4)) % 8]


# -- pixels ------------------------------------------------------------------------------------------

UNKNOWN, FREE, WALL, TRAIL, SCAN = 0, 1, 2, 3, 4
DOSE_PIXELS = (5, 6, 7, 8, 9)
"""The dose layer's pixels: under 25 %, 50 %, 75 %, 100 % of the target, at or over it."""
DOSE_STEPS = (0.25, 0.5, 0.75, 1.0)
CLASSES = 10

PIXEL_COLOURS: tuple[str, ...] = (
    "#1c1f24",  # unknown: nobody has seen it
    "#3b4656",  # free: floor
    "#e6e6e6",  # wall: occupied
    "#3f7a46",  # trail
    "#ff2f2f",  # the selected robot's lidar scan
    "#5c2600",  # dose under 25 % of the target
    "#a34700",  # under 50 %
    "#d98200",  # under 75 %
    "#d9c400",  # under 100 %
    "#1fa346",  # at or over the target
)
PIXEL_NAMES = ("unknown", "floor", "wall", "trail", "scan", "<25%", "<50%", "<75%", "<100%", "at target")
_RANK = (0, 5, 1, 4, 2, 5, 5, 5, 5, 5)
"""Which of a cell's two pixels a glyph's background takes: floor and dose first, then trail,
scan, wall, unknown (a robot beside a wall is drawn on the floor)."""


def raster_grids(g: MapGeometry, grids: Iterable[Grid]) -> U8:
    """The grids merged into pixel classes (``2 * height`` x ``width``: ``UNKNOWN``, ``FREE``,
    ``WALL``) sampled at the pixel centres; every occupied grid cell marks its pixel too (zoomed
    out, a thin wall between two sampled centres still shows)."""
    xs, ys = g.pixel_centres()
    ph, pw = ys.size, xs.size
    merged = np.zeros((ph, pw), dtype=np.uint8)
    for ox, oy, res, w, h, data in grids:
        grid = np.frombuffer(data, dtype=np.uint8).reshape(h, w)
        i = np.floor((xs - ox) / res).astype(np.int64)
        j = np.floor((ys - oy) / res).astype(np.int64)
        ci, cj = (i >= 0) & (i < w), (j >= 0) & (j < h)
        if not ci.any() or not cj.any():
            continue
        sample = np.full((ph, pw), 255, dtype=np.uint8)
        sample[np.ix_(cj, ci)] = grid[np.ix_(j[cj], i[ci])]
        merged[sample == 100] = WALL
        merged[(sample == 0) & (merged == UNKNOWN)] = FREE
        # Each occupied grid cell marks the pixel its centre is in: zoomed out (or with the
        # pixel centres on the grid's cell edges) a thin wall still shows.
        jj, ii = np.nonzero(grid == 100)
        cols = np.floor((ox + (ii + 0.5) * res - g.center_x) / g.scale + pw / 2).astype(np.int64)
        rows = np.floor(-(oy + (jj + 0.5) * res - g.center_y) / g.scale + ph / 2).astype(np.int64)
        keep = (cols >= 0) & (cols < pw) & (rows >= 0) & (rows < ph)
        merged[rows[keep], cols[keep]] = WALL
    return merged


def dose_pixels(pixels: U8, dose: F64, target: float) -> None:
    """Colour ``pixels`` by ``dose`` (J/m² at each pixel, same shape) relative to ``target``: the
    floor and unknown pixels with any dose take one of ``DOSE_PIXELS`` (walls stay walls)."""
    lit = (dose > 0.0) & (pixels != WALL)
    if not lit.any():
        return
    steps = np.asarray(DOSE_STEPS, dtype=np.float64) * target
    buckets = np.searchsorted(steps, dose[lit], side="right")  # 0: under 25 %, ..., 4: at or over
    pixels[lit] = np.asarray(DOSE_PIXELS, dtype=np.uint8)[buckets]


def scan_pixels(g: MapGeometry, points: npt.NDArray[np.floating[Any]]) -> tuple[npt.NDArray[np.intp], ...]:
    """The (pixel rows, columns) of world points ``(N, 2)`` that fall inside the view."""
    if points.size == 0:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty
    cols = np.floor((points[:, 0] - g.center_x) / g.scale + g.width / 2).astype(np.intp)
    rows = np.floor(-(points[:, 1] - g.center_y) / g.scale + g.height * ASPECT / 2).astype(np.intp)
    keep = (cols >= 0) & (cols < g.width) & (rows >= 0) & (rows < 2 * g.height)
    return rows[keep], cols[keep]


def cell_codes(pixels: U8) -> U8:
    """Each cell's two pixels as one code, ``top * CLASSES + bottom`` (``height`` x ``width``)."""
    return (pixels[0::2] * CLASSES + pixels[1::2]).astype(np.uint8)


def _cell_looks() -> tuple[list[str], list[Style], list[Style]]:
    """Per code: its character, its style, and the background a glyph drawn over it takes."""
    chars, styles, under = [], [], []
    for code in range(CLASSES * CLASSES):
        top, bottom = divmod(code, CLASSES)
        if top == bottom:
            chars.append(" ")
            styles.append(Style(bgcolor=PIXEL_COLOURS[top]))
        else:
            chars.append("▀")
            styles.append(Style(color=PIXEL_COLOURS[top], bgcolor=PIXEL_COLOURS[bottom]))
        beneath = top if _RANK[top] >= _RANK[bottom] else bottom
        under.append(Style(bgcolor=PIXEL_COLOURS[beneath]))
    return chars, styles, under


CELL_CHARS, CELL_STYLES, CELL_UNDER = _cell_looks()


# -- glyphs ------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Glyph:
    """A character over the map; without a background of its own it takes the pixel's beneath."""

    char: str
    style: Style


def _bold(colour: str) -> Style:
    return Style(color=colour, bold=True)


ROBOT_STYLE = _bold("#5fff5f")
SELECTED_STYLE = Style(color="black", bgcolor="#5fff5f", bold=True)
LOST_STYLE = _bold("#ff5f5f")
HOME_STYLE = _bold("#5fd7ff")
GOAL_STYLE = _bold("#ffff5f")
ANCHOR_STYLE = _bold("#af87ff")
ZONE_STYLE = Style(color="#ff3030")
ROUTE_STYLE = _bold("#00ffff")
ROUTE_DONE_STYLE = Style(color="#008787", dim=True)
MARK_GLYPHS = {"casualty": ("✚", _bold("#ff5fff")), "hazard": ("▲", _bold("#ff8700"))}
OTHER_MARK = ("✱", _bold("#d0d0d0"))
ALARM_STYLES = {
    AlarmSeverity.CRITICAL: Style(color="white", bgcolor="#d70000", bold=True),
    AlarmSeverity.WARNING: Style(color="black", bgcolor="#ffd700", bold=True),
    AlarmSeverity.INFO: Style(color="white", bgcolor="#005fd7", bold=True),
}
ACKED_ALARM_STYLE = _bold("#ffaf00")
"""An acknowledged alarm's ``!``: still active, nobody needs calling."""
LEGEND_STYLE = Style(color="#e4e4e4", bgcolor="#000000")
LEGEND_LINES = 2
"""The legend's lines at most (the dose scale's comes on top)."""

ROBOT = Glyph("→", ROBOT_STYLE)
HOME = Glyph("⌂", HOME_STYLE)
GOAL = Glyph("◎", GOAL_STYLE)
ANCHOR = Glyph("A", ANCHOR_STYLE)
ZONE = Glyph("░", ZONE_STYLE)


def mark_glyph(kind: str) -> Glyph:
    char, style = MARK_GLYPHS.get(kind, OTHER_MARK)
    return Glyph(char, style)


def _swatch(pixel: int) -> tuple[str, Style]:
    return "█", Style(color=PIXEL_COLOURS[pixel], bgcolor=LEGEND_STYLE.bgcolor)


def _legend_items(scan: bool) -> list[list[tuple[str, Style]]]:
    lg = LEGEND_STYLE
    items: list[list[tuple[str, Style]]] = [
        [_swatch(WALL), ("wall", lg)],
        [_swatch(FREE), ("floor", lg)],
        [_swatch(UNKNOWN), ("unknown", lg)],
        [_swatch(TRAIL), ("trail", lg)],
    ]
    if scan:
        items.append([_swatch(SCAN), ("scan", lg)])
    items += [
        [("→", ROBOT_STYLE + lg), ("robot", lg)],
        [("!", ALARM_STYLES[AlarmSeverity.CRITICAL]), ("alarm", lg)],
        [(HOME.char, HOME_STYLE + lg), ("home", lg)],
        [(GOAL.char, GOAL_STYLE + lg), ("goal", lg)],
        *([(char, style + lg), (kind, lg)] for kind, (char, style) in MARK_GLYPHS.items()),
        [(OTHER_MARK[0], OTHER_MARK[1] + lg), ("mark", lg)],
        [(ANCHOR.char, ANCHOR_STYLE + lg), ("nchor", lg)],
        [(ZONE.char, ZONE_STYLE + lg), ("zone", lg)],
    ]
    return items


def legend_rows(width: int, *, scan: bool = False, dose_target: float | None = None) -> list[list[tuple[str, Style]]]:
    """The legend's lines, top first: while the dose layer is shown, its scale against the target;
    then what the colours and glyphs mean, on as many lines as ``width`` needs (at most
    ``LEGEND_LINES``; what does not fit is left out)."""
    lg = LEGEND_STYLE
    rows: list[list[tuple[str, Style]]] = []
    if dose_target is not None:
        dose: list[tuple[str, Style]] = [(f" dose of {dose_target:g} J/m²:", lg)]
        for pixel, label in zip(DOSE_PIXELS, ("<25%", "<50%", "<75%", "<100%", "at/over"), strict=True):
            dose += [(" ", lg), _swatch(pixel), (label, lg)]
        dose += [(" ", lg), _swatch(FREE), ("none", lg), (" ", lg)]
        rows.append(dose)
    line: list[tuple[str, Style]] = [(" ", lg)]
    used = 1
    lines = 1
    for item in _legend_items(scan):
        n = sum(len(text) for text, _ in item) + 1
        if used + n > width:
            if lines == LEGEND_LINES or used == 1:
                break
            rows.append(line)
            line, used, lines = [(" ", lg)], 1, lines + 1
        line += [*item, (" ", lg)]
        used += n
    rows.append(line)
    return rows


# -- rows --------------------------------------------------------------------------------------------

Overlays = dict[int, Glyph]
"""The glyphs of one row, by column."""


def render_row(
    codes: Sequence[int], glyphs: Mapping[int, Glyph], cache: dict[tuple[Style, int], Style]
) -> list[Segment]:
    """One row of cells: each cell's half-block look, or the glyph drawn there on the colour of the
    pixel beneath (``cache`` keeps the combined styles); runs of one style are one segment."""
    segments: list[Segment] = []
    run: list[str] = []
    run_style: Style | None = None
    for x, code in enumerate(codes):
        glyph = glyphs.get(x)
        if glyph is None:
            char, style = CELL_CHARS[code], CELL_STYLES[code]
        elif glyph.style.bgcolor is not None:
            char, style = glyph.char, glyph.style
        else:
            char = glyph.char
            combined = cache.get((glyph.style, code))
            if combined is None:
                combined = cache[(glyph.style, code)] = CELL_UNDER[code] + glyph.style
            style = combined
        if style is not run_style and run:
            segments.append(Segment("".join(run), run_style))
            run = []
        run_style = style
        run.append(char)
    if run:
        segments.append(Segment("".join(run), run_style))
    return segments


class MapFrame:
    """One picture: the cells' pixel codes and the glyphs over them, row by row."""

    __slots__ = ("_keys", "_styles", "codes", "glyphs")

    def __init__(self, codes: U8, glyphs: dict[int, Overlays], styles: dict[tuple[Style, int], Style]) -> None:
        self.codes = codes
        self.glyphs = glyphs
        """row -> column -> glyph."""
        self._styles = styles
        self._keys: dict[int, object] = {}

    @property
    def height(self) -> int:
        return int(self.codes.shape[0])

    @property
    def width(self) -> int:
        return int(self.codes.shape[1])

    def row_key(self, y: int) -> object:
        """Equal keys: the row renders the same."""
        key = self._keys.get(y)
        if key is None:
            row = self.glyphs.get(y)
            key = self._keys[y] = (self.codes[y].tobytes(), tuple(row.items()) if row else ())
        return key

    def row(self, y: int) -> list[Segment]:
        if not 0 <= y < self.height:
            return []
        return render_row(self.codes[y].tolist(), self.glyphs.get(y, {}), self._styles)

    def text(self, y: int) -> str:
        return "".join(s.text for s in self.row(y))

    def cell(self, col: int, row: int) -> tuple[str, Style]:
        """What cell (col, row) shows: its character and style."""
        glyph = self.glyph(col, row)
        segments = render_row([int(self.codes[row, col])], {} if glyph is None else {0: glyph}, self._styles)
        return segments[0].text, segments[0].style or Style()

    def pixels(self, col: int, row: int) -> tuple[int, int]:
        """The classes of cell (col, row)'s top and bottom pixels."""
        return divmod(int(self.codes[row, col]), CLASSES)

    def pixel(self, col: int, prow: int) -> int:
        """The class of the pixel at (col, pixel row)."""
        return self.pixels(col, prow // 2)[prow % 2]

    def glyph(self, col: int, row: int) -> Glyph | None:
        return self.glyphs.get(row, {}).get(col)

    def styles(self) -> set[Style]:
        """Every glyph's own style (tests look for a layer by it)."""
        return {g.style for row in self.glyphs.values() for g in row.values()}

    def chars(self, style: Style) -> list[str]:
        """The glyphs drawn in ``style``."""
        return [g.char for row in self.glyphs.values() for g in row.values() if g.style == style]


# -- the painter -------------------------------------------------------------------------------------


class MapPainter:
    """Paints ``MapFrame``s of a fleet model, keeping the layers that did not change."""

    def __init__(self) -> None:
        self._base_key: tuple[object, ...] = ()
        self._base: U8 = np.zeros((0, 0), dtype=np.uint8)
        self._base_glyphs: dict[tuple[int, int], Glyph] = {}
        self._trails_view: tuple[object, ...] = ()
        self._trail_counts: dict[tuple[int, int], int] = {}
        """Pixel (row, col) -> trail points in it, every robot's, for the view ``_trails_view``."""
        self._trail_mask: npt.NDArray[np.bool_] = np.zeros((0, 0), dtype=bool)
        """The pixels with any trail point (set and cleared as a count leaves or reaches 0)."""
        self._trail_of: dict[str, tuple[int, collections.deque[tuple[int, int] | None]]] = {}
        """robot -> (its ``trail_added`` when last seen, the pixel of each of its trail points)."""
        self._styles: dict[tuple[Style, int], Style] = {}
        self._alarms: tuple[int, dict[str, Style]] = (-1, {})
        self._legend_glyphs: tuple[object, dict[tuple[int, int], Glyph]] = (None, {})
        self._looks: dict[tuple[str, Style], tuple[tuple[Glyph, ...], tuple[Glyph, ...]]] = {}
        """(robot, style) -> its arrows (by heading) and its name's letters, made once."""
        self._rasters: dict[str, tuple[int, tuple[object, ...], U8]] = {}
        """map -> (id of its grid, the view, its pixels): the maps rastered one by one."""
        self.rasters = 0
        self.frames = 0
        self.base_builds = 0

    def paint(
        self,
        fleet: FleetModel,
        g: MapGeometry,
        selected: str | None,
        dose: FleetDose | None = None,
        *,
        legend: bool = True,
    ) -> MapFrame:
        view_key = g.key()
        self._update_base(fleet, g, view_key, dose)
        self._update_trails(fleet, g, view_key)
        pixels = self._base.copy()
        if self._trail_of:
            trail = self._trail_mask & (pixels <= FREE)  # under walls and the dose layer
            pixels[trail] = TRAIL
        view = fleet.robots.get(selected) if selected is not None else None
        scan = view.scan if view is not None else None
        if scan is not None:
            rows, cols = scan_pixels(g, scan)
            pixels[rows, cols] = SCAN
        glyphs = dict(self._base_glyphs)
        protected = {c for c, gl in glyphs.items() if gl is not ZONE}
        """Anchors, marks, homes, goals, robots and alarms: a name is drawn over the map but never
        over one of these."""

        def put(x: float, y: float, glyph: Glyph, *, protect: bool = True) -> None:
            c = g.to_cell(x, y)
            if g.inside(*c):
                glyphs[c] = glyph
                if protect:
                    protected.add(c)

        self._draw_round(fleet, g, selected, put)
        for mark in fleet.live_marks():
            put(mark.x, mark.y, mark_glyph(mark.kind))
        width, height = g.width, g.height
        cx, cy, sx, sy, hw, hh = g.center_x, g.center_y, g.scale, g.scale * ASPECT, width / 2, height / 2
        for rv in fleet.robots.values():
            if rv.home is not None:  # every robot's home, where return home goes
                put(rv.home[0], rv.home[1], HOME)
            if rv.goal is not None:
                put(rv.goal[0], rv.goal[1], GOAL)
        alarms = self._alarm_styles(fleet)
        looks = self._looks
        labels: list[tuple[int, int, tuple[Glyph, ...]]] = []
        first: list[tuple[int, int, tuple[Glyph, ...]]] = []
        alarmed: list[tuple[int, int, tuple[Glyph, ...]]] = []
        robots: set[tuple[int, int]] = set()
        """Cells with a robot or an alarm: an alarm goes beside its robot but over neither."""
        for rv in fleet.robots.values():
            pose = rv.pose
            if pose is None:
                continue
            x, y, th = pose
            row = math.floor(-(y - cy) / sy + hh)
            if not 0 <= row < height:  # neither it, its alarm nor its name shows
                continue
            col = math.floor((x - cx) / sx + hw)
            style = LOST_STYLE if rv.lost else SELECTED_STYLE if rv.robot == selected else ROBOT_STYLE
            look = looks.get((rv.robot, style))
            if look is None:  # its eight arrows and its name's letters in this style, made once
                arrows = tuple(Glyph(ch, style) for ch in HEADING_CHARS)
                look = looks[(rv.robot, style)] = (arrows, tuple(Glyph(ch, style) for ch in rv.robot[:6]))
            robots.add((col, row))
            if 0 <= col < width:
                glyphs[(col, row)] = look[0][round(th / (math.pi / 4)) % 8]
                protected.add((col, row))
            alarm = alarms.get(rv.robot)
            if alarm is not None:  # right of it (over a home, goal or mark), else left of it
                for c in ((col + 1, row), (col - 1, row)):
                    if 0 <= c[0] < width and c not in robots:
                        glyphs[c] = Glyph("!", alarm)
                        protected.add(c)
                        robots.add(c)
                        break
            if -8 <= col < width:
                label = (col + 2, row, look[1])
                if rv.robot == selected:
                    first.append(label)
                elif alarm is not None:
                    alarmed.append(label)
                else:
                    labels.append(label)
        # After every glyph, so no name hides a robot; a name that would run into one already
        # drawn is left out (the selected robot's first, then those with an alarm): zoomed out
        # over hundreds of robots the map shows the names that can be read, not a jumble.
        taken: set[tuple[int, int]] = set()
        for col, row, name in (*first, *alarmed, *labels):
            span = [(k, row) for k in range(col, col + len(name) + 1)]  # and a space after it
            if not taken.isdisjoint(span):
                continue
            taken.update(span)
            for k, glyph in enumerate(name, start=col):
                if 0 <= k < width and (k, row) not in protected:
                    glyphs[(k, row)] = glyph
        if legend:
            glyphs.update(self._legend(g, scan is not None, dose.target_j_m2 if dose is not None else None))
        by_row: dict[int, Overlays] = {}
        for (col, row), glyph in glyphs.items():  # drawn in the same order each frame: equal rows, equal keys
            by_row.setdefault(row, {})[col] = glyph
        self.frames += 1
        return MapFrame(cell_codes(pixels), by_row, self._styles)

    def _legend(self, g: MapGeometry, scan: bool, target: float | None) -> dict[tuple[int, int], Glyph]:
        """The legend's glyphs on the bottom lines (kept while the view's size and what it says hold)."""
        key = (g.width, g.height, scan, target)
        if self._legend_glyphs[0] != key:
            glyphs: dict[tuple[int, int], Glyph] = {}
            lines = legend_rows(g.width, scan=scan, dose_target=target)
            for k, line in enumerate(lines):
                row = g.height - len(lines) + k
                col = 0
                for text, style in line:
                    for ch in text:
                        if row >= 0 and col < g.width:
                            glyphs[(col, row)] = Glyph(ch, style)
                        col += 1
            self._legend_glyphs = (key, glyphs)
        return self._legend_glyphs[1]

    def _update_base(
        self, fleet: FleetModel, g: MapGeometry, view_key: tuple[object, ...], dose: FleetDose | None
    ) -> None:
        """The robots' maps (the fleet map alone when there is one), the dose layer, the zones and
        the anchors: rebuilt only when one of them or the view changed."""
        key = (
            view_key,
            tuple((k, id(v)) for k, v in fleet.grids.items()),
            tuple((k, id(v)) for k, v in fleet.zones.items()),
            tuple(fleet.anchors.items()),
            None if dose is None else (id(dose), dose.version),
        )
        if key == self._base_key:
            return
        self._base_key = key
        self.base_builds += 1
        grids = fleet.grids
        if FLEET_MAP in grids:  # every robot's map registered and merged: drawn alone
            grids = {FLEET_MAP: grids[FLEET_MAP]}
        # Each map rastered on its own and kept until it or the view changes: a robot's map update
        # re-rasters that map only. Merged by the larger class: wall over free over unknown.
        kept: dict[str, tuple[int, tuple[object, ...], U8]] = {}
        for robot, grid in grids.items():
            had = self._rasters.get(robot)
            if had is None or had[0] != id(grid) or had[1] != view_key:
                had = (id(grid), view_key, raster_grids(g, [grid]))
                self.rasters += 1
            kept[robot] = had
        self._rasters = kept
        pixels = np.zeros((2 * g.height, g.width), dtype=np.uint8)
        for _, _, raster in kept.values():
            np.maximum(pixels, raster, out=pixels)
        xs, ys = g.pixel_centres()
        if dose is not None:
            dose_pixels(pixels, dose.grid.dose_at(xs, ys), dose.target_j_m2)
        glyphs: dict[tuple[int, int], Glyph] = {}
        if fleet.zones:  # people-present zones: over the floor, never over a wall
            cx, cy = g.pixel_centres()
            gx, gy = np.meshgrid(cx, cy[0::2] - g.scale / 2)  # the cells' centres
            walls = (pixels[0::2] == WALL) | (pixels[1::2] == WALL)
            for corners in fleet.zones.values():
                inside = points_in_polygon(gx, gy, corners) & ~walls
                for row, col in zip(*np.nonzero(inside), strict=True):
                    glyphs[(int(col), int(row))] = ZONE
                for x, y in corners:  # a zone smaller than a cell still shows
                    c = g.to_cell(x, y)
                    if g.inside(*c):
                        glyphs[c] = ZONE
        for x, y in fleet.anchors.values():
            c = g.to_cell(x, y)
            if g.inside(*c):
                glyphs[c] = ANCHOR
        self._base = pixels
        self._base_glyphs = glyphs

    def _update_trails(self, fleet: FleetModel, g: MapGeometry, view_key: tuple[object, ...]) -> None:
        """Keep ``_trail_counts`` (pixel -> how many trail points fall in it) and ``_trail_mask``
        current by adding each robot's new points and dropping the ones its trail let go: per
        message O(1)."""
        if view_key != self._trails_view:
            self._trails_view = view_key
            self._trail_of.clear()
            self._trail_counts = {}
            self._trail_mask = np.zeros((2 * g.height, g.width), dtype=bool)
        counts, mask = self._trail_counts, self._trail_mask
        cx, cy, scale = g.center_x, g.center_y, g.scale
        half_w, half_h, width, height = g.width / 2, g.height * ASPECT / 2, g.width, 2 * g.height

        def pixel(p: tuple[float, float]) -> tuple[int, int] | None:
            col = math.floor((p[0] - cx) / scale + half_w)
            row = math.floor(-(p[1] - cy) / scale + half_h)
            return (row, col) if 0 <= col < width and 0 <= row < height else None

        def add(c: tuple[int, int] | None) -> None:
            if c is not None:
                n = counts.get(c, 0)
                counts[c] = n + 1
                if not n:
                    mask[c] = True

        def drop(c: tuple[int, int] | None) -> None:
            if c is not None:
                n = counts[c] - 1
                if n:
                    counts[c] = n
                else:
                    del counts[c]
                    mask[c] = False

        for robot, view in fleet.robots.items():
            trail = view.trail
            seen = self._trail_of.get(robot)
            if seen is not None and seen[0] == view.trail_added and len(seen[1]) == len(trail):
                continue
            new = view.trail_added - seen[0] if seen is not None else len(trail)
            if seen is None or new > len(trail) or new < 0:
                if seen is not None:
                    for c in seen[1]:
                        drop(c)
                mine: collections.deque[tuple[int, int] | None] = collections.deque()
                points = list(trail)
            else:
                mine = seen[1]
                n = len(trail)  # the new points at the deque's right end: indexed from there, O(1) each
                points = [trail[k] for k in range(n - new, n)]
            for p in points:
                c = pixel(p)
                mine.append(c)
                add(c)
            while len(mine) > len(trail):
                drop(mine.popleft())
            self._trail_of[robot] = (view.trail_added, mine)

    def _alarm_styles(self, fleet: FleetModel) -> dict[str, Style]:
        """robot -> the style of its ``!``: its most severe unacknowledged alarm's, else the
        acknowledged one's (worked out again only when the alarms changed)."""
        version = fleet.alarms.alarms.version
        if self._alarms[0] != version:
            out: dict[str, Style] = {}
            for alarm in fleet.alarms.rows():  # unacknowledged first, then the most severe
                if alarm.robot not in out:
                    out[alarm.robot] = ALARM_STYLES[alarm.severity] if alarm.acked_by is None else ACKED_ALARM_STYLE
            self._alarms = (version, out)
        return self._alarms[1]

    def trail_points(self) -> int:
        """Trail points inside the view (tests compare with the robots' trails)."""
        return sum(self._trail_counts.values())

    @staticmethod
    def _draw_round(fleet: FleetModel, g: MapGeometry, robot: str | None, put: Callable[..., None]) -> None:
        """The selected robot's round while it runs it (``FleetModel.running_route``): the way still
        ahead as dots, dwell points ``o`` (other nodes, a sweep's lane ends, ``+``), the nodes
        already done dimmed."""
        route = fleet.running_route(robot) if robot is not None else None
        view = fleet.robots.get(robot) if robot is not None else None
        if route is None or view is None or view.progress is None:
            return
        nodes = route[1]
        done = view.progress.nodesDone
        step = g.scale / 2
        dot = Glyph("∙", ROUTE_STYLE)
        for k in range(max(1, done), len(nodes)):  # the legs still to drive
            (ax, ay, _), (bx, by, _) = nodes[k - 1], nodes[k]
            n = max(1, math.ceil(math.hypot(bx - ax, by - ay) / step))
            for i in range(1, n):
                put(ax + (bx - ax) * i / n, ay + (by - ay) * i / n, dot, protect=False)
        for k, (x, y, dwell) in enumerate(nodes[1:], start=1):
            glyph = Glyph("o" if dwell > 0 else "+", ROUTE_DONE_STYLE if k < done else ROUTE_STYLE)
            put(x, y, glyph, protect=False)


def colour_of(pixel: int) -> Color:
    return Color.parse(PIXEL_COLOURS[pixel])
