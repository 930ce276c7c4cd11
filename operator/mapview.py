"""The map widget: a thin Textual shell over the renderer (operator/maprender.py).

The renderer paints a ``MapFrame`` from the fleet model (maps, dose layer, trails, the selected
robot's scan, glyphs, the legend) in half blocks, two pixels a cell; this widget keeps the view
(``MapGeometry``: zoom, pan, fit, its size), asks for a frame when anything the picture depends on
changed, refreshes only the lines whose rows changed and keeps each rendered line until its row
changes. Clicks become world coordinates (``MapView.Clicked``), the wheel zooms.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable

from rich.style import Style
from textual import events
from textual.geometry import Region
from textual.message import Message
from textual.strip import Strip
from textual.widget import Widget

from fleetlink.operator.dose import FleetDose
from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.maprender import ASPECT, MapFrame, MapGeometry, MapPainter, fit_points, heading_char

__all__ = ["ASPECT", "MapGeometry", "MapView", "heading_char"]


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
        self.painter = MapPainter()
        self.frame: MapFrame | None = None
        self._drawn: tuple[object, ...] = ()
        self.dose: FleetDose | None = None
        """The fleet's dose layer to draw (None: hidden); the app sets it under ``lock``."""
        self.legend = True
        """The legend on the bottom lines (``L`` hides and shows it)."""
        self._strips: dict[int, tuple[object, Strip]] = {}
        """Rendered lines by row, with the row's key when rendered."""
        self.click_pending = False
        """A click posted (``Clicked``) that the app has not yet answered with its dialog: a key
        typed meanwhile is the dialog's (``d``, ``s``, ``m``), not a drive key."""

    @property
    def frames(self) -> int:
        return self.painter.frames

    def on_resize(self, event: events.Resize) -> None:
        self._sync_size()
        with self._lock:
            self.update_view()

    def _sync_size(self) -> None:
        size = self.content_size
        if size.width and size.height:
            self.geometry.width, self.geometry.height = size.width, size.height

    def fit(self) -> None:
        """Centre on the robots, the UWB anchors and the maps, zoomed so they all show."""
        self._sync_size()
        self.geometry.fit(fit_points(self.fleet))
        self.refresh()

    def update_view(self) -> None:
        """Paint a new frame if anything the picture depends on changed (called on every frame of
        the app): only the lines whose rows changed are refreshed."""
        self._sync_size()
        g = self.geometry
        fleet = self.fleet
        dose = None if self.dose is None else (id(self.dose), self.dose.version)
        key = (fleet.version, fleet.alarms.alarms.version, g.key(), self.selected(), dose, self.legend)
        if key == self._drawn:
            return
        self._drawn = key
        old = self.frame
        self.frame = frame = self.painter.paint(fleet, g, self.selected(), self.dose, legend=self.legend)
        if old is None or old.codes.shape != frame.codes.shape:
            self._strips.clear()
            self.refresh()
            return
        dirty = [y for y in range(frame.height) if frame.row_key(y) != old.row_key(y)]
        if len(dirty) > frame.height // 2:
            self.refresh()
            return
        width = self.content_size.width
        for y in dirty:
            self.refresh(Region(0, y, width, 1))

    def render_line(self, y: int) -> Strip:
        """One line of the map, kept until its row changes."""
        width = self.content_size.width
        frame = self.frame
        if frame is None or y >= frame.height:
            return Strip.blank(width)
        key = frame.row_key(y)
        cached = self._strips.get(y)
        if cached is not None and cached[0] == key and cached[1].cell_length == width:
            return cached[1]
        strip = Strip(frame.row(y), frame.width).adjust_cell_length(width)
        self._strips[y] = (key, strip)
        return strip

    # -- what is drawn (tests) -------------------------------------------------------------------

    def cell(self, col: int, row: int) -> tuple[str, Style]:
        """The character and style drawn at cell (col, row)."""
        assert self.frame is not None
        return self.frame.cell(col, row)

    def pixel_at(self, x: float, y: float) -> int | None:
        """The pixel class (``maprender.UNKNOWN``, ``FREE``, ``WALL``, ...) drawn at world (x, y),
        None off the view."""
        assert self.frame is not None
        col, prow = self.geometry.to_pixel(x, y)
        if not self.geometry.inside(col, prow // 2):
            return None
        return self.frame.pixel(col, prow)

    # -- input -----------------------------------------------------------------------------------

    def on_click(self, event: events.Click) -> None:
        offset = event.get_content_offset(self)
        if offset is None:  # on the border
            return
        self._sync_size()
        x, y = self.geometry.to_world(offset.x, offset.y)
        self.click_pending = True
        self.post_message(self.Clicked(x, y))

    def on_mouse_scroll_up(self, event: events.MouseScrollUp) -> None:
        self.geometry.zoom(1 / 1.25)
        with self._lock:
            self.update_view()

    def on_mouse_scroll_down(self, event: events.MouseScrollDown) -> None:
        self.geometry.zoom(1.25)
        with self._lock:
            self.update_view()
