"""The fleet table: one row per robot (mode, battery, link, link health, age, UWB, lease).

The link column says where commands go: ``both`` (redundant sending), ``zenoh`` or ``mqtt``
(failover); the health column the primary's state and the fallback's when it is down or degraded.

``fleet_rows`` (pure: the model, link views and time in, styled cells out) decides what each cell
says and how it is coloured; ``FleetTable`` shows the rows, touching only the cells that changed.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Self

from rich.text import Text
from textual.cache import LRUCache
from textual.geometry import Region
from textual.message import Message
from textual.widgets import DataTable

from fleetlink.operator.fleet import FleetModel, RobotView
from fleetlink.operator.linkmanager import BOTH, PRIMARY, LinkHealth

__all__ = ["COLUMNS", "Cell", "FleetTable", "Row", "fleet_rows", "id_cell", "row_cells"]

COLUMNS = (
    ("id", "robot"),
    ("mode", "mode"),
    ("batt", "battery"),
    ("link", "link"),
    ("health", "health"),
    ("age", "age"),
    ("uwb", "uwb"),
    ("lease", "lease"),
)
"""(heading, column key)."""

Cell = str | Text
Row = tuple[Cell, ...]


def health_cell(health: Sequence[LinkHealth]) -> Text:
    """The primary's state (ok / degr / DOWN, loss, RTT p50), then a mark when the fallback is not
    fine (`` m✗`` down, `` m!`` degraded): one glance says whether a robot still has two paths."""
    primary = next((h for h in health if h.link == PRIMARY), None)
    if primary is None or primary.age_s is None:
        return Text("-", style="dim")
    rtt = f" {primary.rtt_s * 1000:.0f}ms" if primary.rtt_s is not None else ""
    if not primary.healthy:
        cell = Text(f"DOWN {primary.loss_pct:.0f}%", style="bold red")
    elif primary.degraded:
        cell = Text(f"degr {primary.loss_pct:.0f}%{rtt}", style="bold yellow")
    else:
        cell = Text(f"ok {primary.loss_pct:.0f}%{rtt}", style="green")
    for other in health:
        if other.link == PRIMARY or other.age_s is None:
            continue
        if not other.healthy:
            cell.append(f" {other.link[0]}✗", style="bold red")
        elif other.degraded:
            cell.append(f" {other.link[0]}!", style="bold yellow")
    return cell


def age_cell(age: float | None) -> str:
    if age is None:
        return "-"
    return f"{age:.1f}s" if age >= 1 else f"{age * 1000:.0f}ms"


def uwb_cell(ok: bool | None) -> Text:
    if ok is None:
        return Text("?", style="dim")
    return Text("ok", "green") if ok else Text("stale", "bold yellow")


def lease_cell(holder: str | None, me: str) -> str:
    if holder is None:
        return "-"  # the robot never announced a lease
    if not holder:
        return "free"
    return "you" if holder == me else holder


def id_cell(view: RobotView) -> Text:
    """The robot's id, red while lost (silent); with a cross when its presence is gone (its Zenoh
    liveliness token and its MQTT connection, operator/alarms.py: robot lost)."""
    if view.present is False:
        return Text(f"{view.robot} ✗", style="bold red")
    return Text(view.robot, style="bold red" if view.lost else "")


def row_cells(
    view: RobotView, link: str, health: Sequence[LinkHealth], uwb_ok: bool | None, me: str, now: float
) -> Row:
    """One robot's cells, in ``COLUMNS`` order."""
    return (
        id_cell(view),
        view.mode if not view.estop else Text("ESTOP", style="bold red"),
        "?" if view.battery is None else f"{view.battery:.0f}%",
        Text(link, style="green" if link in (PRIMARY, BOTH) else "bold yellow"),
        health_cell(health),
        age_cell(view.age(now)),
        uwb_cell(uwb_ok),
        lease_cell(view.lease_holder, me),
    )


def fleet_rows(
    fleet: FleetModel,
    active: Callable[[str], str],
    health: Callable[[str], Sequence[LinkHealth]],
    me: str,
    now: float,
    filter_text: str = "",
) -> dict[str, Row]:
    """Every robot's row, by robot id in id order; with ``filter_text`` only the rows whose text
    contains it (case-insensitive)."""
    rows: dict[str, Row] = {}
    needle = filter_text.lower()
    for robot in sorted(fleet.robots):
        cells = row_cells(fleet.robots[robot], active(robot), health(robot), fleet.uwb_ok(robot, now), me, now)
        if needle and needle not in " ".join(str(c) for c in cells).lower():
            continue
        rows[robot] = cells
    return rows


def _same(cell: Cell) -> Any:
    """What decides whether a cell must be redrawn: a Text's equality ignores its base style."""
    return (cell.plain, str(cell.style), tuple(cell.spans)) if isinstance(cell, Text) else cell


CACHE_SIZES = {"_row_render_cache": 200, "_cell_render_cache": 2000, "_row_renderable_cache": 200, "_line_cache": 200}
"""DataTable's render caches (1000, 10000, 1000, 1000 rows, cells, rows, lines by default)."""

VISIBLE_MARGIN = 2
"""Rows just above and below the visible ones are kept current too (a scroll by a row or two)."""

ROWS_PER_FRAME = 6
"""At most this many rows are redrawn in a frame, in turn (the next frame goes on after the last
one redrawn; rows just scrolled into view are all brought up to date at once): each row's cells are drawn through Rich, ~1-2 ms a row, and at 500 robots every row
on screen changes every frame (pose age, link health), so redrawing them all (20-40 ms) held up
the key presses that came meanwhile. A screen of 20 rows is current within 4 frames (0.4 s)."""


class FleetTable(DataTable[Cell]):
    """The rows of ``fleet_rows``; row keys are robot ids.

    Only the rows on screen are kept current: with hundreds of robots a frame touches the dozen
    rows a person can see, and redraws at most ``ROWS_PER_FRAME`` of them, in turn. A row off screen keeps what it showed until it is scrolled to; then
    ``Scrolled`` asks the app for a frame (``show_lazy``) or the rows last given are applied at
    once (``show``)."""

    class Scrolled(Message):
        """Other rows came into view."""

    _rows_only = False
    """``update_cell`` refreshes the whole table; while set, only the rows redrawn are."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(cursor_type="row", zebra_stripes=True, **kwargs)
        self._shown: dict[str, tuple[Any, ...]] = {}
        """robot -> what its row shows (``_same`` of each cell)."""
        self._order: list[str] = []
        """The row keys in the table's order (rows are added at the end, never sorted)."""
        self._index: dict[str, int] = {}
        self._latest: Mapping[str, Row] = {}
        """The rows ``show`` was last given, for the rows that come into view before the next."""
        self.cells_updated = 0
        """Cells rewritten so far (``update_cell`` calls)."""
        self._turn = 0
        self._shown_range = (0, 0)
        """The rows [first, end) on screen in the last frame."""
        """The row index (in ``_order``) whose turn it is to be redrawn first."""

        # DataTable's render caches are keyed by its update count, so after an update only what is
        # on screen is used again; sized for a screen, not for thousands of stale renders (which
        # the garbage collector would walk: 100-190 ms pauses at 500 robots).
        for name, size in CACHE_SIZES.items():
            cache = getattr(self, name, None)
            if isinstance(cache, LRUCache):
                cache.maxsize = size

    def on_mount(self) -> None:
        for label, key in COLUMNS:
            self.add_column(label, key=key)

    def visible_range(self) -> tuple[int, int]:
        """The row indices [first, end) on screen (all of them before the table has a size)."""
        height = self.scrollable_content_region.height - (self.header_height if self.show_header else 0)
        if height <= 0:
            return 0, len(self._order)
        first = max(0, int(self.scroll_y) - VISIBLE_MARGIN)
        return first, min(len(self._order), int(self.scroll_y) + height + 1 + VISIBLE_MARGIN)

    def show(self, rows: Mapping[str, Row]) -> None:
        """Rows gone are removed, new ones added (in order, at the end), changed cells updated
        (those on screen; the others when they come into view)."""
        self._latest = rows
        self._sync(list(rows), rows.__getitem__)

    def show_lazy(self, order: Sequence[str], cells: Callable[[str], Row]) -> None:
        """As ``show``, the rows ``order`` names, but ``cells(robot)`` is asked only for the rows
        on screen and the new ones."""
        self._latest = {}
        self._sync(order, cells)

    def _sync(self, order: Sequence[str], cells: Callable[[str], Row]) -> None:
        keep = set(order)
        gone = [r for r in self._order if r not in keep]
        if gone:
            for robot in gone:
                self.remove_row(robot)
                del self._shown[robot]
            self._order = [r for r in self._order if r in keep]
            self._index = {r: i for i, r in enumerate(self._order)}
        for robot in order:
            if robot not in self._shown:
                row = cells(robot)
                self.add_row(*row, key=robot)
                self._shown[robot] = tuple(_same(c) for c in row)
                self._index[robot] = len(self._order)
                self._order.append(robot)
        first, end = self.visible_range()
        n = end - first
        if n <= 0:
            return
        start = self._turn if first <= self._turn < end else first
        was_first, was_end = self._shown_range
        self._shown_range = (first, end)
        redrawn = 0
        self._rows_only = True
        try:
            for i in range(first, end):  # rows scrolled into view since the last frame: all at once
                if not was_first <= i < was_end and self._update(self._order[i], cells(self._order[i])):
                    self._refresh_line(i)
            for k in range(n):  # the others in turn
                i = first + (start - first + k) % n
                if not was_first <= i < was_end:
                    continue
                if self._update(self._order[i], cells(self._order[i])):
                    self._refresh_line(i)
                    redrawn += 1
                    if redrawn == ROWS_PER_FRAME:
                        self._turn = i + 1
                        break
        finally:
            self._rows_only = False

    def _refresh_line(self, index: int) -> None:
        """Refresh row ``index``'s line (rows are one line high). ``refresh_row`` does the same
        through ``ordered_rows``, which after each update walks all the rows (500)."""
        y = index - int(self.scroll_y) + (self.header_height if self.show_header else 0)
        self.refresh(Region(0, y, self.size.width, 1))

    def refresh(self, *regions: Region, repaint: bool = True, layout: bool = False, recompose: bool = False) -> Self:
        if self._rows_only and not regions and not layout and not recompose:
            return self  # update_cell's whole-table refresh: the row is refreshed on its own
        return super().refresh(*regions, repaint=repaint, layout=layout, recompose=recompose)

    def _update(self, robot: str, cells: Row) -> bool:
        """Rewrite the cells of ``robot``'s row that changed; whether any did."""
        key = tuple(_same(c) for c in cells)
        old = self._shown[robot]
        if key == old:
            return False
        for (_, column), value, was, now in zip(COLUMNS, cells, old, key, strict=True):
            if was != now:
                self.update_cell(robot, column, value)
                self.cells_updated += 1
        self._shown[robot] = key
        return True

    def watch_scroll_y(self, old_value: float, new_value: float) -> None:
        super().watch_scroll_y(old_value, new_value)
        if int(old_value) != int(new_value):
            self._revealed()

    def on_resize(self) -> None:
        self._revealed()

    def _revealed(self) -> None:
        if self._latest:
            first, end = self.visible_range()
            for robot in self._order[first:end]:
                row = self._latest.get(robot)
                if row is not None:
                    self._update(robot, row)
        else:
            self.post_message(self.Scrolled())
