"""The operator console (Textual): fleet table, map, direct drive, goals, marks, leases, notices.

The app never opens a transport: it gets a ``ConsoleSource`` (in production ``OperatorLink``,
which owns Zenoh + MQTT and the link manager) and shows a ``FleetModel``. What the network hears
reaches the app as messages: the model's ``FleetFeed`` (operator/feed.py) keeps it in an inbox and
posts the app a ``TelemetryArrived``; the app folds the inbox into the model on its own thread and
redraws. A frame is drawn when something changed (telemetry, an operator action) and on a slow
clock tick (ages, robots going quiet, lease renewal), at most ``refresh_hz`` times a second; no
widget is ever touched off the UI thread, and no network thread ever waits for the UI.

The parts: the fleet table (operator/fleet_table.py), the robot detail (operator/detail.py), the
status line (operator/status.py), the map (operator/mapview.py); typed commands are parsed by
operator/commands.py, outgoing messages built by operator/commander.py, marks named, saved and
loaded by operator/marks.py, lease renewal timed by ``LeaseRenewal`` (operator/fleet.py), drive
keys by operator/teleop.py. The app itself decides what may be sent and tells the operator.

Safety: when drive-key repeats stop arriving the console sends stop (see operator/teleop.py), Esc
stops every robot, and quitting sends stop to every robot before the links close.
"""

from __future__ import annotations

import contextlib
import math
import threading
from pathlib import Path
from typing import ClassVar

from rich.text import Text
from textual import events
from textual.actions import SkipAction
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.css.query import NoMatches
from textual.message import Message
from textual.screen import ModalScreen
from textual.timer import Timer
from textual.widgets import DataTable, Footer, Input, RichLog, Static

from fleetlink.operator.commander import LEASE_S, Commander
from fleetlink.operator.commands import Command, CommandError, Goal, Home, MarkAt, Payload, StopAll, parse_command
from fleetlink.operator.detail import RobotDetail, detail_text
from fleetlink.operator.feed import ConsoleSource, FleetFeed, attach
from fleetlink.operator.fleet import FleetModel, LeaseRenewal, Notice
from fleetlink.operator.fleet_table import FleetTable, fleet_rows
from fleetlink.operator.maps import MapFollower
from fleetlink.operator.mapview import MapView
from fleetlink.operator.marks import MarksStore
from fleetlink.operator.status import StatusLine, status_text
from fleetlink.operator.teleop import DriveKeys, Twist
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import Mark

__all__ = ["ConsoleApp", "ConsoleSource", "TelemetryArrived", "attach"]


class TelemetryArrived(Message):
    """The feed has items waiting (posted from a network thread, once per batch)."""


class ConfirmClick(ModalScreen[str]):
    """A click on the map: y = send the robot there, m = mark it, n/Esc = nothing."""

    BINDINGS: ClassVar = [
        Binding("y", "choose('goal')", "goal"),
        Binding("m", "choose('mark')", "mark"),
        Binding("n", "choose('')", "cancel"),
        Binding("escape", "choose('')", "cancel"),
    ]

    def __init__(self, robot: str | None, x: float, y: float) -> None:
        super().__init__()
        self.robot, self.x, self.y = robot, x, y

    def compose(self) -> ComposeResult:
        who = f"send {self.robot} to" if self.robot else "(no robot selected)"
        yield Static(
            f"({self.x:.2f}, {self.y:.2f}) m\n\n[b]y[/b] {who} this point   [b]m[/b] mark it   [b]n[/b] cancel",
            id="confirm",
        )

    def action_choose(self, what: str) -> None:
        self.dismiss(what)


class ConsoleApp(App[None]):
    CSS_PATH = "console.tcss"
    TITLE = "fleetlink console"
    BINDINGS: ClassVar = [
        Binding("ctrl+q", "quit", "quit", priority=True),
        Binding("escape", "stop_all", "STOP ALL", priority=True),
        # Priority, so the focus moves while the key is first handled: the keys queued behind it
        # (a fast typist, a paste) then reach the input instead of driving the robot. In an input
        # or a dialog the action steps aside and the character is typed.
        Binding("slash", "focus_filter", "filter", priority=True),
        Binding("colon", "focus_command", "command", priority=True),
        Binding("t", "lease", "take lease"),
        Binding("T", "release_lease", "release"),
        Binding("h", "home", "home"),
        Binding("p", "payload", "payload"),
        Binding("f", "fit", "fit map"),
        Binding("plus", "zoom(0.8)", "zoom in", show=False),
        Binding("minus", "zoom(1.25)", "zoom out", show=False),
        Binding("shift+up", "pan(0, -4)", show=False),
        Binding("shift+down", "pan(0, 4)", show=False),
        Binding("shift+left", "pan(-8, 0)", show=False),
        Binding("shift+right", "pan(8, 0)", show=False),
        # Priority: the screen's own tab (focus next) would come first otherwise. In an input or
        # a dialog the action steps aside and tab moves the focus as usual.
        Binding("tab", "next_robot", "next robot", priority=True),
    ]

    def __init__(
        self,
        source: ConsoleSource,
        fleet: FleetModel,
        clock: Clock,
        *,
        lock: threading.Lock | None = None,
        maps: MapFollower | None = None,
        read_only: bool = False,
        marks_file: Path | None = None,
        refresh_hz: float = 10.0,
        clock_hz: float = 2.0,
        repeat_timeout_s: float = 0.6,
    ) -> None:
        """``lock`` guards ``fleet`` against the other threads that use it (map fetcher, marks
        queryable); if ``fleet`` was already attached to ``source`` (``attach``), that feed and its
        lock are used."""
        super().__init__()
        self.source = source
        self.fleet = fleet
        self.clock = clock
        self.feed: FleetFeed = attach(source, fleet, lock or threading.Lock(), maps)
        self.lock = self.feed.lock
        self.read_only = read_only
        self.marks_file = marks_file
        self.marks = MarksStore(marks_file)
        self.refresh_hz = refresh_hz
        self.clock_hz = clock_hz
        self.drive = DriveKeys(repeat_timeout_s=repeat_timeout_s)
        self.commander = Commander(source, clock)
        self.leases = LeaseRenewal(LEASE_S)
        self.selected: str | None = None
        self.filter_text = ""
        self.frame_times: list[float] = []
        """How long each frame took to draw (the last 1000)."""
        self.sent_stop_on_quit = False
        self._last_frame = -math.inf
        self._frame_timer: Timer | None = None
        with self.lock:
            for mark in self.marks.load():
                self.fleet.marks[mark.markId] = mark

    # -- layout ---------------------------------------------------------------------------------

    def compose(self) -> ComposeResult:
        yield StatusLine(self._status_text(), id="status")
        with Horizontal(id="main"):
            with Vertical(id="left"):
                yield Input(placeholder="/ filter robots (id, mode, link)", id="filter")
                yield FleetTable(id="fleet")
                yield RobotDetail(id="detail")
            yield MapView(self.fleet, lambda: self.selected, lock=self.lock, id="map")
        yield RichLog(id="notices", max_lines=500, markup=False, wrap=True)
        yield Input(
            placeholder=": goal X Y [THETA] | mark KIND X Y [LABEL] | home | payload on|off | stop", id="command"
        )
        yield Footer()

    def on_mount(self) -> None:
        self.query_one(MapView).focus()
        self.feed.bind(lambda: self.post_message(TelemetryArrived()))
        self.feed.drain()
        self.set_interval(1.0 / self.clock_hz, self._changed)
        self.set_interval(0.05, self._drive_tick)
        if self.read_only:
            self.notice("info", "read-only mode: this console watches, it does not command")
        self._changed()

    def on_unmount(self) -> None:
        self.feed.unbind()

    # -- frames ---------------------------------------------------------------------------------

    def on_telemetry_arrived(self, _message: TelemetryArrived) -> None:
        if self.feed.drain():
            self._changed()

    def _changed(self) -> None:
        """Something on screen may have changed: draw a frame now, or when the last one is
        1 / refresh_hz old."""
        if self._frame_timer is not None:
            return
        wait = self._last_frame + 1.0 / self.refresh_hz - self.clock.now()
        if wait <= 0:
            self._frame()
        else:
            self._frame_timer = self.set_timer(wait, self._timed_frame)

    def _timed_frame(self) -> None:
        self._frame_timer = None
        self._frame()

    def _frame(self) -> None:
        # A last timer can fire while the app shuts down and its widgets are gone.
        with contextlib.suppress(NoMatches):
            self._draw()

    def _draw(self) -> None:
        t0 = now = self.clock.now()
        self._last_frame = now
        source, fleet = self.source, self.fleet
        with self.lock:
            fleet.tick(now)
            notices = fleet.drain()
            rows = fleet_rows(fleet, source.active, source.health, source.sender, now, self.filter_text)
            for n in notices:
                self._log_notice(n)
            self.query_one(FleetTable).show(rows)
            if self.selected is None and rows:
                self.selected = next(iter(rows))
                self.query_one(MapView).fit()
            self.query_one(MapView).update_view()
            self.query_one(StatusLine).show(self._status_text())
            selected = self.selected
            health = source.health(selected) if selected is not None else ()
            view = fleet.robots.get(selected) if selected is not None else None
            self.query_one(RobotDetail).show(detail_text(selected, view, health))
            renew = [] if self.read_only else self.leases.due(fleet, now)
        for robot in renew:
            self.commander.lease(robot)
        self.frame_times.append(self.clock.now() - t0)
        del self.frame_times[:-1000]

    def _status_text(self) -> str:
        return status_text(self.source.sender, self.read_only, self.selected, self.drive.speed, self.drive.turn)

    def notice(self, severity: str, text: str) -> None:
        self._log_notice(Notice(self.clock.now(), severity, text))

    def _log_notice(self, n: Notice) -> None:
        style = {"info": "", "warning": "bold yellow", "error": "bold red"}.get(n.severity, "")
        self.query_one("#notices", RichLog).write(Text(f"{n.severity:7} {n.text}", style=style))

    # -- robot selection ------------------------------------------------------------------------

    def on_data_table_row_highlighted(self, event: DataTable.RowHighlighted) -> None:
        if event.row_key.value is not None:
            self.selected = str(event.row_key.value)
            self._changed()

    def action_next_robot(self) -> None:
        """Select the next row of the fleet table (wrapping); in an input or a dialog, tab keeps
        its usual meaning (focus next)."""
        if isinstance(self.focused, Input) or len(self.screen_stack) > 1:
            raise SkipAction()
        table = self.query_one(FleetTable)
        if table.row_count:
            table.move_cursor(row=(table.cursor_row + 1) % table.row_count)

    # -- commands -------------------------------------------------------------------------------

    def _command_ok(self, robot: str | None, what: str, *, needs_lease: bool = True) -> bool:
        if self.read_only:
            self.notice("warning", f"read-only console: {what} not sent")
            return False
        if robot is None:
            self.notice("warning", f"no robot selected: {what} not sent")
            return False
        if needs_lease:
            with self.lock:
                ok, reason = self.fleet.may_drive(robot)
            if not ok:
                self.notice("warning", f"{reason} ({what} refused)")
                return False
        return True

    def send_twist(self, twist: Twist) -> None:
        robot = self.selected
        if robot is None or self.read_only:
            return
        self.commander.teleop(robot, twist)

    def on_key(self, event: events.Key) -> None:
        if isinstance(self.focused, Input) or len(self.screen_stack) > 1:
            return
        char = event.character
        key = char if char is not None and char.isprintable() and char != " " else event.key
        if not self.drive.handles(key):
            return
        event.stop()
        event.prevent_default()
        now = self.clock.now()
        if key in ("k", "space"):
            twist = self.drive.press(key, now)
            if twist is not None and self.selected and not self.read_only:
                self.send_twist(twist)
            return
        moving = key not in ("q", "z", "W", "x", "e", "c")
        if moving and not self._command_ok(self.selected, "drive"):
            return
        twist = self.drive.press(key, now)
        if twist is not None:
            self.send_twist(twist)
        self.query_one(StatusLine).show(self._status_text())

    def _drive_tick(self) -> None:
        twist = self.drive.tick(self.clock.now())
        if twist is not None:
            self.send_twist(twist)

    def stop_all(self) -> list[str]:
        """Stop every robot we know: a stop instant action (acked, re-sent on failover) each."""
        self.drive.stop(self.clock.now())
        with self.lock:
            robots = list(self.fleet.robots)
        for robot in robots:
            self.commander.stop(robot)
        return robots

    def action_stop_all(self) -> None:
        if self.read_only:
            self.notice("warning", "read-only console: stop not sent")
            return
        robots = self.stop_all()
        self.notice("warning", f"STOP sent to every robot ({len(robots)})")

    def send_goal(self, x: float, y: float, theta: float | None = None) -> bool:
        robot = self.selected
        if not self._command_ok(robot, "goal"):
            return False
        assert robot is not None
        order_id = self.commander.goal(robot, x, y, theta)
        self.notice("info", f"{robot}: goal ({x:.2f}, {y:.2f}) sent as order {order_id}")
        return True

    def action_home(self) -> None:
        robot = self.selected
        if not self._command_ok(robot, "return home"):
            return
        assert robot is not None
        self.commander.home(robot)
        self.notice("info", f"{robot}: return home sent")

    def action_payload(self, on: bool | None = None) -> None:
        robot = self.selected
        if not self._command_ok(robot, "payload"):
            return
        assert robot is not None
        with self.lock:
            view = self.fleet.robots.get(robot)
            current = view.payload_on if view else False
        want = (not current) if on is None else on
        self.commander.payload(robot, want)
        self.notice("info", f"{robot}: payload {'on' if want else 'off'} sent")

    # -- leases ---------------------------------------------------------------------------------

    def action_lease(self) -> None:
        robot = self.selected
        if not self._command_ok(robot, "lease request", needs_lease=False):
            return
        assert robot is not None
        self.commander.lease(robot)
        self.notice("info", f"{robot}: control lease requested")

    def action_release_lease(self) -> None:
        robot = self.selected
        if not self._command_ok(robot, "lease release", needs_lease=False):
            return
        assert robot is not None
        self.commander.lease(robot, release=True)

    # -- marks ----------------------------------------------------------------------------------

    def add_mark(self, x: float, y: float, kind: str = "casualty", label: str = "") -> Mark | None:
        if self.read_only:
            self.notice("warning", "read-only console: mark not shared")
            return None
        with self.lock:
            robot = self.selected or next(iter(self.fleet.robots), None)
        if robot is None:
            self.notice("warning", "no robot known yet: a mark needs one to be published under")
            return None
        mark = self.marks.new(self.commander.header(Mark.TOPIC, robot), x, y, kind, label, self.clock.wall())
        with self.lock:
            self.fleet.apply(mark, "local", self.clock.now())
        self.source.publish(mark)
        with self.lock:
            live = self.fleet.live_marks()
        self.marks.save(live)
        self.notice("info", f"mark {mark.kind} '{mark.label}' at ({x:.2f}, {y:.2f}) shared")
        self._changed()
        return mark

    # -- map ------------------------------------------------------------------------------------

    def on_map_view_clicked(self, event: MapView.Clicked) -> None:
        x, y = event.x, event.y

        def chosen(what: str | None) -> None:
            if what == "goal":
                self.send_goal(x, y)
            elif what == "mark":
                self.add_mark(x, y)

        self.push_screen(ConfirmClick(self.selected, x, y), chosen)

    def action_fit(self) -> None:
        with self.lock:
            self.query_one(MapView).fit()

    def action_zoom(self, factor: float) -> None:
        m = self.query_one(MapView)
        m.geometry.zoom(factor)
        with self.lock:
            m.update_view()

    def action_pan(self, dcols: float, drows: float) -> None:
        m = self.query_one(MapView)
        m.geometry.pan(dcols, drows)
        with self.lock:
            m.update_view()

    # -- inputs ---------------------------------------------------------------------------------

    # The focus moves at once, not through Widget.focus() (deferred with call_later), for the
    # same reason the bindings are priority ones: the keys right behind must reach the input.
    def _focus_input(self, selector: str) -> None:
        if isinstance(self.focused, Input) or len(self.screen_stack) > 1:
            raise SkipAction()
        self.screen.set_focus(self.query_one(selector, Input))

    def action_focus_filter(self) -> None:
        self._focus_input("#filter")

    def action_focus_command(self) -> None:
        self._focus_input("#command")

    def on_input_changed(self, event: Input.Changed) -> None:
        if event.input.id == "filter":
            self.filter_text = event.value.strip()
            self._changed()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        if event.input.id == "command":
            self.run_command(event.value)
            event.input.value = ""
        self.query_one(MapView).focus()

    def run_command(self, line: str) -> None:
        """A typed command (operator/commands.py): run it, or say why not in the notices."""
        command = parse_command(line)
        if command is None:
            return
        if isinstance(command, CommandError):
            self.notice("warning", command.text)
            return
        try:
            self.execute(command)
        except ValueError as exc:  # the wire refused what the command built (a size, a range)
            self.notice("warning", f"bad command {line!r}: {exc}")

    def execute(self, command: Command) -> None:
        if isinstance(command, Goal):
            self.send_goal(command.x, command.y, command.theta)
        elif isinstance(command, MarkAt):
            self.add_mark(command.x, command.y, command.kind, command.label)
        elif isinstance(command, Home):
            self.action_home()
        elif isinstance(command, Payload):
            self.action_payload(command.on)
        elif isinstance(command, StopAll):
            self.action_stop_all()

    # -- quit -----------------------------------------------------------------------------------

    async def action_quit(self) -> None:
        self.send_stop_to_all()
        self.exit()

    def send_stop_to_all(self) -> None:
        """On quit: stop every robot (teleop zero for the selected one, stop action for all)."""
        if self.read_only or self.sent_stop_on_quit:
            return
        self.sent_stop_on_quit = True
        if self.selected is not None:
            self.send_twist(Twist(0.0, 0.0))
        self.stop_all()
