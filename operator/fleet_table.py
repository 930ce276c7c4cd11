"""The fleet table: one row per robot (mode, battery, link, link health, age, UWB, lease).

The link column says where commands go: ``both`` (redundant sending), ``zenoh`` or ``mqtt``
(failover); the health column the primary's state and the fallback's when it is down or degraded.

``fleet_rows`` (pure: the model, link views and time in, styled cells out) decides what each cell
says and how it is coloured; ``FleetTable`` shows the rows, touching only the cells that changed.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

from rich.text import Text
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


class FleetTable(DataTable[Cell]):
    """The rows of ``fleet_rows``; row keys are robot ids."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(cursor_type="row", zebra_stripes=True, **kwargs)
        self._shown: dict[str, tuple[Any, ...]] = {}

    def on_mount(self) -> None:
        for label, key in COLUMNS:
            self.add_column(label, key=key)

    def show(self, rows: Mapping[str, Row]) -> None:
        """Rows gone are removed, new ones added (in order, at the end), changed cells updated."""
        for robot in [r for r in self._shown if r not in rows]:
            self.remove_row(robot)
            del self._shown[robot]
        for robot, cells in rows.items():
            key = tuple(_same(c) for c in cells)
            old = self._shown.get(robot)
            if old is None:
                self.add_row(*cells, key=robot)
            else:
                for (_, column), value, was, now in zip(COLUMNS, cells, old, key, strict=True):
                    if was != now:
                        self.update_cell(robot, column, value)
            self._shown[robot] = key
