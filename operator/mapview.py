"""The map widget: occupancy grids, robots (pose, heading, trail), anchors, homes (H), goals, marks,
people-present zones (░) and the selected robot's running round (dwell points o, lane ends +), and
(``D``) the fleet's UV dose layer as cell backgrounds, with its legend on the bottom line.

The geometry (``MapGeometry``) is pure and tested on its own: one terminal cell is ``scale`` metres
wide and ``2 * scale`` metres tall (terminal cells are about twice as tall as wide), world +y is up.
The widget renders line by line from a cell table that is rebuilt only when the fleet model's
version or the view changed, in layers: the maps, zones and anchors only when they or the view
changed; the trails by their new and dropped points only; goals, marks and robots each time. Only
the lines whose cells changed are refreshed, and rendered lines are cached.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from rich.segment import Segment
from rich.style import Style
from textual import events
from textual.geometry import Region
from textual.message import Message
from textual.strip import Strip
from textual.widget import Widget

from fleetlink.operator.dose import AT_TARGET, BELOW, FleetDose
from fleetlink.operator.fleet import FleetModel
from fleetlink.shared.geometry import points_in_polygon
from fleetlink.shared.keys import FLEET_MAP

__all__ = ["MapGeometry", "MapView"]

ASPECT = 2.0
HEADING_CHARS = "→↗↑↖←↙↓↘"


@dataclass(slots=True)
class MapGeometry:
    width: int
    height: int
    center_x: float = 0.0
    center_y: float = 0.0
    scale: float = 0.25
    """Metres per cell, horizontally."""

    def to_world(self, col: int, row: int) -> tuple[float, float]:
        """Centre of cell (col, row) in metres."""
        x = self.center_x + (col + 0.5 - self.width / 2) * self.scale
        y = self.center_y - (row + 0.5 - self.height / 2) * self.scale * ASPECT
        return x, y

    def to_cell(self, x: float, y: float) -> tuple[int, int]:
        col = math.floor((x - self.center_x) / self.scale + self.width / 2)
        row = math.floor(-(y - self.center_y) / (self.scale * ASPECT) + self.height / 2)
        return col, row

    def inside(self, col: int, row: int) -> bool:
        return 0 <= col < self.width and 0 <= row < self.height

    def zoom(self, factor: float) -> None:
        self.scale = min(20.0, max(0.02, self.scale * factor))

    def pan(self, dcols: float, drows: float) -> None:
        self.center_x += dcols * self.scale
        self.center_y -= drows * self.scale * ASPECT


def heading_char(theta: float) -> str:
    return HEADING_CHARS[round(theta / (math.pi / 4)) % 8]


ROBOT_STYLE = Style(color="bright_green", bold=True)
SELECTED_STYLE = Style(color="black", bgcolor="bright_green", bold=True)
LOST_STYLE = Style(color="red", bold=True)
TRAIL_STYLE = Style(color="green", dim=True)
GOAL_STYLE = Style(color="yellow", bold=True)
MARK_STYLE = Style(color="magenta", bold=True)
ANCHOR_STYLE = Style(color="cyan", bold=True)
ZONE_STYLE = Style(color="red")
ROUTE_STYLE = Style(color="bright_cyan", bold=True)
ROUTE_DONE_STYLE = Style(color="cyan", dim=True)
WALL_STYLE = Style(color="white")
FREE_STYLE = Style(color="grey30")
EMPTY = Style()
DOSE_BG = {AT_TARGET: Style(bgcolor="dark_green"), BELOW: Style(bgcolor="dark_orange3")}
"""The dose layer's cell backgrounds: at or over the target, under it (no dose: none)."""
LEGEND_STYLE = Style(color="white", bgcolor="grey15")

Cell = tuple[str, Style]


class MapView(Widget, can_focus=True):
    """Click: ``MapView.Clicked`` with the world coordinate. Wheel: zoom. Shift+arrows: pan."""

    class Clicked(Message):
        def __init__(self, x: float, y: float) -> None:
            super().__init__()
            self.x = x
            self.y = y

    def __init__(
        self,
        fleet: FleetModel,
        selected: Callable[[], str | None],
        *,
        lock: threading.Lock | None = None,
        **kwargs: object,
    ) -> None:
        """``lock`` guards ``fleet`` when the widget redraws on its own (resize, wheel); the app
        holds it when it calls ``update_view`` or ``fit``."""
        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.fleet = fleet
        self.selected = selected
        self._lock: contextlib.AbstractContextManager[object] = lock if lock is not None else contextlib.nullcontext()
        self.geometry = MapGeometry(80, 24)
        self._cells: dict[tuple[int, int], Cell] = {}
        self._drawn: tuple[object, ...] = ()
        self.frames = 0
        self.dose: FleetDose | None = None
        """The fleet's dose layer to draw (None: hidden); the app sets it under ``lock``."""
        self._dose_styles: dict[tuple[Style, int], Style] = {}
        self._base: dict[tuple[int, int], Cell] = {}
        """The maps, zones and anchors (``_base_layer``), for ``_base_key``."""
        self._base_protected: set[tuple[int, int]] = set()
        self._base_key: tuple[object, ...] = ()
        self._trail_cells: dict[tuple[int, int], int] = {}
        """Terminal cell -> trail points in it, every robot's, for the view ``_trails_view``."""
        self._trail_of: dict[str, tuple[int, collections.deque[tuple[int, int] | None]]] = {}
        """robot -> (its ``trail_added`` when last seen, the cell of each of its trail points)."""
        self._trails_view: tuple[object, ...] = ()
        self._strips: dict[int, Strip] = {}
        """Rendered lines, by row, dropped when a line's cells change."""
        self._full_refresh = True

    def on_resize(self, event: events.Resize) -> None:
        self._sync_size()
        with self._lock:
            self.update_view()

    def _sync_size(self) -> None:
        size = self.content_size
        if size.width and size.height:
            self.geometry.width, self.geometry.height = size.width, size.height

    def fit(self) -> None:
        """Centre on the robots."""
        points = [v.pose[:2] for v in self.fleet.robots.values() if v.pose is not None]
        points += list(self.fleet.anchors.values())
        if points:
            self.geometry.center_x = sum(p[0] for p in points) / len(points)
            self.geometry.center_y = sum(p[1] for p in points) / len(points)
        self.refresh()

    def update_view(self) -> None:
        """Redraw if anything the picture depends on changed (called on every frame of the app):
        only the lines whose cells changed are refreshed."""
        self._sync_size()
        g = self.geometry
        dose = None if self.dose is None else (id(self.dose), self.dose.version)
        key = (self.fleet.version, g.width, g.height, g.center_x, g.center_y, g.scale, self.selected(), dose)
        if key != self._drawn:
            self._drawn = key
            old = self._cells
            self._rebuild()
            if self._full_refresh:
                self._full_refresh = False
                self._strips.clear()
                self.refresh()
                return
            dirty = {c[1] for c, v in self._cells.items() if old.get(c) != v}
            dirty.update(c[1] for c in old if c not in self._cells)
            width = self.content_size.width
            for row in dirty:
                self._strips.pop(row, None)
                self.refresh(Region(0, row, width, 1))

    def _base_layer(self, xs: npt.NDArray[np.floating[Any]], ys: npt.NDArray[np.floating[Any]]) -> None:
        """The robots' maps, the zones and the anchors: rebuilt only when they or the view changed."""
        g = self.geometry
        cells: dict[tuple[int, int], Cell] = {}
        protected: set[tuple[int, int]] = set()

        def put(x: float, y: float, char: str, style: Style, *, protect: bool = True) -> None:
            c = g.to_cell(x, y)
            if g.inside(*c):
                cells[c] = (char, style)
                if protect:
                    protected.add(c)

        # The robots' maps merged (occupied wins over free, free over unknown), sampled at the
        # terminal cells' centres.
        merged = np.full((g.height, g.width), 255, dtype=np.uint8)
        # The fleet map, when there is one, is every robot's map registered and merged: drawn alone.
        grids = self.fleet.grids
        if FLEET_MAP in grids:
            grids = {FLEET_MAP: grids[FLEET_MAP]}
        for ox, oy, res, w, h, data in grids.values():
            grid = np.frombuffer(data, dtype=np.uint8).reshape(h, w)
            i = np.floor((xs - ox) / res).astype(np.int64)
            j = np.floor((ys - oy) / res).astype(np.int64)
            ci, cj = (i >= 0) & (i < w), (j >= 0) & (j < h)
            if not ci.any() or not cj.any():
                continue
            sample = np.full((g.height, g.width), 255, dtype=np.uint8)
            sample[np.ix_(cj, ci)] = grid[np.ix_(j[cj], i[ci])]
            merged = np.where(sample == 100, 100, np.where((sample == 0) & (merged == 255), 0, merged))
            # Zoomed out, a terminal cell covers several grid cells: a thin wall between the
            # sampled centres must still show, so every occupied grid cell marks its terminal cell.
            jj, ii = np.nonzero(grid == 100)
            cols = np.floor((ox + (ii + 0.5) * res - g.center_x) / g.scale + g.width / 2).astype(np.int64)
            rows = np.floor(-(oy + (jj + 0.5) * res - g.center_y) / (g.scale * ASPECT) + g.height / 2).astype(np.int64)
            keep = (cols >= 0) & (cols < g.width) & (rows >= 0) & (rows < g.height)
            merged[rows[keep], cols[keep]] = 100
        for row, col in zip(*np.nonzero(merged == 100), strict=True):
            cells[(int(col), int(row))] = ("█", WALL_STYLE)
        for row, col in zip(*np.nonzero(merged == 0), strict=True):
            cells[(int(col), int(row))] = ("·", FREE_STYLE)
        if self.fleet.zones:  # people-present zones: a fill over everything but walls, under the rest
            gx, gy = np.meshgrid(xs, ys)
            for corners in self.fleet.zones.values():
                inside = points_in_polygon(gx, gy, corners) & (merged != 100)
                for row, col in zip(*np.nonzero(inside), strict=True):
                    cells[(int(col), int(row))] = ("░", ZONE_STYLE)
                for x, y in corners:  # a zone smaller than a terminal cell still shows
                    put(x, y, "░", ZONE_STYLE, protect=False)
        for x, y in self.fleet.anchors.values():
            put(x, y, "A", ANCHOR_STYLE)
        self._base = cells
        self._base_protected = protected

    def _update_trails(self, view_key: tuple[object, ...]) -> None:
        """Keep ``_trail_cells`` (terminal cell -> how many trail points fall in it) current by
        adding each robot's new points and dropping the ones its trail let go: per message O(1)."""
        if view_key != self._trails_view:
            self._trails_view = view_key
            self._trail_of.clear()
            self._trail_cells.clear()
        g = self.geometry
        counts = self._trail_cells
        half_w, half_h, sx, sy = g.width / 2, g.height / 2, g.scale, g.scale * ASPECT
        cx, cy, width, height = g.center_x, g.center_y, g.width, g.height

        def cell(p: tuple[float, float]) -> tuple[int, int] | None:
            col = math.floor((p[0] - cx) / sx + half_w)
            row = math.floor(-(p[1] - cy) / sy + half_h)
            return (col, row) if 0 <= col < width and 0 <= row < height else None

        def drop(c: tuple[int, int] | None) -> None:
            if c is not None:
                n = counts[c] - 1
                if n:
                    counts[c] = n
                else:
                    del counts[c]

        for robot, view in self.fleet.robots.items():
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
                points = list(itertools.islice(trail, len(trail) - new, None)) if new else []
            for p in points:
                c = cell(p)
                mine.append(c)
                if c is not None:
                    counts[c] = counts.get(c, 0) + 1
            while len(mine) > len(trail):
                drop(mine.popleft())
            self._trail_of[robot] = (view.trail_added, mine)

    def _rebuild(self) -> None:
        g = self.geometry
        view_key = (g.width, g.height, g.center_x, g.center_y, g.scale)
        xs = g.center_x + (np.arange(g.width) + 0.5 - g.width / 2) * g.scale
        ys = g.center_y - (np.arange(g.height) + 0.5 - g.height / 2) * g.scale * ASPECT
        fleet = self.fleet
        base_key = (
            view_key,
            tuple((k, id(v)) for k, v in fleet.grids.items()),
            tuple((k, id(v)) for k, v in fleet.zones.items()),
            tuple(fleet.anchors.items()),
        )
        if base_key != self._base_key:
            self._base_key = base_key
            self._base_layer(xs, ys)
            self._full_refresh = True
        self._update_trails(view_key)
        cells = dict(self._base)
        for c in self._trail_cells:  # trails over the maps, under everything else
            cells[c] = ("∙", TRAIL_STYLE)
        protected = set(self._base_protected)
        """Anchors, marks, goals and robots: a name label is drawn over the map (walls, free
        space, trails) but never over one of these."""

        def put(x: float, y: float, char: str, style: Style, *, protect: bool = True) -> None:
            c = g.to_cell(x, y)
            if g.inside(*c):
                cells[c] = (char, style)
                if protect:
                    protected.add(c)

        selected = self.selected()
        self._draw_round(selected, put)
        for mark in fleet.live_marks():
            put(mark.x, mark.y, "✚" if mark.kind == "casualty" else "*", MARK_STYLE)
        for view in fleet.robots.values():
            if view.home is not None:  # every robot's home, where return home goes
                put(view.home[0], view.home[1], "H", GOAL_STYLE)
            if view.goal is not None:
                put(view.goal[0], view.goal[1], "G", GOAL_STYLE)
        labels: list[tuple[int, int, str, Style]] = []
        for view in fleet.robots.values():
            if view.pose is None:
                continue
            x, y, th = view.pose
            style = LOST_STYLE if view.lost else SELECTED_STYLE if view.robot == selected else ROBOT_STYLE
            col, row = g.to_cell(x, y)
            if g.inside(col, row):
                cells[(col, row)] = (heading_char(th), style)
                protected.add((col, row))
            if -8 <= col < g.width and 0 <= row < g.height:
                labels.append((col, row, view.robot[:6], style))
        for col, row, name, style in labels:  # after every glyph, so no label hides a robot
            for k, ch in enumerate(name):
                c = (col + 2 + k, row)
                if g.inside(*c) and c not in protected:
                    cells[c] = (ch, style)
        if self.dose is not None:
            self._draw_dose(cells, self.dose, np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64))
        self._cells = cells
        self.frames += 1

    def _draw_round(self, robot: str | None, put: Callable[..., None]) -> None:
        """The selected robot's round while it runs it (``FleetModel.running_route``): the way still
        ahead as dots, dwell points ``o`` (other nodes, a sweep's lane ends, ``+``), the nodes
        already done dimmed."""
        route = self.fleet.running_route(robot) if robot is not None else None
        view = self.fleet.robots.get(robot) if robot is not None else None
        if route is None or view is None or view.progress is None:
            return
        nodes = route[1]
        done = view.progress.nodesDone
        step = self.geometry.scale / 2
        for k in range(max(1, done), len(nodes)):  # the legs still to drive
            (ax, ay, _), (bx, by, _) = nodes[k - 1], nodes[k]
            n = max(1, math.ceil(math.hypot(bx - ax, by - ay) / step))
            for i in range(1, n):
                put(ax + (bx - ax) * i / n, ay + (by - ay) * i / n, "∙", ROUTE_STYLE, protect=False)
        for k, (x, y, dwell) in enumerate(nodes[1:], start=1):
            put(x, y, "o" if dwell > 0 else "+", ROUTE_DONE_STYLE if k < done else ROUTE_STYLE, protect=False)

    def _draw_dose(
        self,
        cells: dict[tuple[int, int], Cell],
        dose: FleetDose,
        xs: npt.NDArray[np.float64],
        ys: npt.NDArray[np.float64],
    ) -> None:
        """The dose at each terminal cell's centre as its background (whatever is drawn there
        stays), and the legend on the bottom line."""
        classes = dose.classes(xs, ys)
        styles = self._dose_styles
        for row, col in zip(*np.nonzero(classes), strict=True):
            c = (int(col), int(row))
            char, style = cells.get(c, (" ", EMPTY))
            k = int(classes[row, col])
            lit = styles.get((style, k))
            if lit is None:
                lit = styles[(style, k)] = style + DOSE_BG[k]
            cells[c] = (char, lit)
        t = dose.target_j_m2
        parts = [
            (" dose ", LEGEND_STYLE),
            ("  ", DOSE_BG[AT_TARGET]),
            (f" at/over {t:g} J/m² ", LEGEND_STYLE),
            ("  ", DOSE_BG[BELOW]),
            (f" under {t:g} ", LEGEND_STYLE),
            ("  ", EMPTY),
            (" none ", LEGEND_STYLE),
        ]
        row, col = self.geometry.height - 1, 0
        for text, style in parts:
            for ch in text:
                if col < self.geometry.width:
                    cells[(col, row)] = (ch, style)
                col += 1

    def render_line(self, y: int) -> Strip:
        """One line of the map, from the cache unless its cells changed since it was rendered."""
        width = self.content_size.width
        strip = self._strips.get(y)
        if strip is not None and strip.cell_length == width:
            return strip
        strip = self._strips[y] = self._render_line(y, width)
        return strip

    def _render_line(self, y: int, width: int) -> Strip:
        cells = self._cells
        segments: list[Segment] = []
        run: list[str] = []
        run_style = EMPTY
        for x in range(width):
            char, style = cells.get((x, y), (" ", EMPTY))
            if style is not run_style and run:
                segments.append(Segment("".join(run), run_style))
                run = []
            run_style = style
            run.append(char)
        if run:
            segments.append(Segment("".join(run), run_style))
        return Strip(segments, width)

    def on_click(self, event: events.Click) -> None:
        offset = event.get_content_offset(self)
        if offset is None:  # on the border
            return
        self._sync_size()
        x, y = self.geometry.to_world(offset.x, offset.y)
        self.post_message(self.Clicked(x, y))

    def on_mouse_scroll_up(self, event: events.MouseScrollUp) -> None:
        self.geometry.zoom(1 / 1.25)
        with self._lock:
            self.update_view()

    def on_mouse_scroll_down(self, event: events.MouseScrollDown) -> None:
        self.geometry.zoom(1.25)
        with self._lock:
            self.update_view()
