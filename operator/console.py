"""The operator console (Textual): fleet table, map, direct drive, goals, marks, leases, notices.

The app never opens a transport: it gets a ``ConsoleSource`` (in production ``OperatorLink``,
which owns Zenoh + MQTT and the link manager) and shows a ``FleetModel``. What the network hears
reaches the app as messages: the model's ``FleetFeed`` (operator/feed.py) keeps it in an inbox and
posts the app a ``TelemetryArrived``; the app folds the inbox into the model on its own thread (in
slices of ``DRAIN_SLICE_S``, so a key waits one slice, not a burst) and redraws. A drive key on the
map sends its teleop on the terminal's input thread, without waiting for the event loop
(operator/keylane.py), or, behind a key the app has not handled yet, when the app first sees it,
before any frame queued meanwhile. A frame is
drawn when something changed (telemetry, an operator action) and on a slow clock tick (ages,
robots going quiet, lease renewal), at most ``refresh_hz`` times a second (fewer when frames take
long: ``FRAME_SPACING``); no widget is ever
touched off the UI thread, and no network thread ever waits for the UI.

The parts: the fleet table (operator/fleet_table.py), the robot detail (operator/detail.py), the
status line (operator/status.py), the map (operator/mapview.py); typed commands are parsed by
operator/commands.py, outgoing messages built by operator/commander.py, marks named, saved and
loaded by operator/marks.py, lease renewal timed by ``LeaseRenewal`` (operator/fleet.py), drive
keys by operator/teleop.py, rounds (``:disinfect``, ``:sweep``) planned in a worker thread by the
planner the app is given (operator/rounds.py). The app itself decides what may be sent and tells
the operator.

Safety: when drive-key repeats stop arriving the console sends stop (see operator/teleop.py), Esc
stops every robot, and quitting sends stop to every robot before the links close.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import threading
from pathlib import Path
from typing import Any, ClassVar

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

from fleetlink.operator.alarm_panel import AlarmKeeper, AlarmPanel, Said, alarm_lines, link_states_of
from fleetlink.operator.alarms import AckEntry, AlarmKind
from fleetlink.operator.audit import AuditLog
from fleetlink.operator.collector import Collector, untangle_strips
from fleetlink.operator.commander import LEASE_S, Commander
from fleetlink.operator.commands import (
    AckAlarm,
    Command,
    CommandError,
    CommsPolicySet,
    Dose,
    DoseSave,
    EStop,
    EStopRelease,
    Goal,
    Home,
    HomeSet,
    MarkAt,
    MarkEdit,
    MarkHere,
    MarkRemove,
    MarksExport,
    MarksList,
    Payload,
    RoundAction,
    Seek,
    Speed,
    StartRound,
    StopAll,
    ZoneAdd,
    ZoneRemove,
    ZonesList,
    parse_command,
)
from fleetlink.operator.detail import RobotDetail, detail_text
from fleetlink.operator.dose import DoseFollower, dose_report, save_report
from fleetlink.operator.feed import ConsoleSource, FleetFeed, attach
from fleetlink.operator.fleet import FleetModel, LeaseRenewal, Notice
from fleetlink.operator.fleet_table import FleetTable, fleet_rows, row_cells
from fleetlink.operator.keylane import KeyLane
from fleetlink.operator.maps import MapFollower
from fleetlink.operator.mapview import MapView
from fleetlink.operator.marks import DEFAULT_KIND, MARK_KINDS, MAX_LABEL, MarksStore, export_marks, find_mark, revised
from fleetlink.operator.rounds import (
    DEFAULT_LAMP,
    DEFAULT_TARGET_J_M2,
    MAX_SURVEYS,
    RoomArea,
    RoundError,
    RoundIds,
    RoundPlan,
    RoundPlanner,
    RoundRequest,
    check_request,
    describe_area,
    floor_of,
    mj_cm2,
)
from fleetlink.operator.status import StatusLine, status_text
from fleetlink.operator.teleop import DRIVE_KEYS, SPEED_KEYS, STOP_KEYS, DriveKeys, Twist
from fleetlink.shared import wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.dose import Lamp, j_m2
from fleetlink.shared.map_codec import SharedMap
from fleetlink.shared.messages import ActionType, Mark, PeopleZones, Zone, ZonePoint

READ_ONLY_NOTICE = "read-only mode: this console watches, it does not command"
LINK_CHECK_S = 0.1
"""How often the link alarms look at their share of the robots' links (between frames)."""
DRAIN_SLICE_S = 0.008
"""Telemetry is folded into the model in slices of about this long (keys wait at most one)."""
FRAME_SPACING = 4.0
"""The next frame comes at least this many times as long after the last one as that one took to
work out (and never sooner than 1 / refresh_hz): a host too busy for 10 frames a second of 500
robots draws fewer, and keys and telemetry get the time between them."""

__all__ = ["ConsoleApp", "ConsoleSource", "RoundPlanned", "TelemetryArrived", "attach"]

log = logging.getLogger(__name__)


def drive_key(event: events.Key) -> str:
    """The name ``DriveKeys`` knows a key by: its printable character (``i``, ``,``, ``W``),
    else its key name (``space``, ``up``)."""
    char = event.character
    return char if char is not None and char.isprintable() and char != " " else event.key


class TelemetryArrived(Message):
    """The feed has items waiting (posted from a network thread, once per batch)."""


class RoundPlanned(Message):
    """A round's planning worker is done: the plan, or why there is none (posted from its thread)."""

    def __init__(self, request: RoundRequest, result: RoundPlan | str) -> None:
        super().__init__()
        self.request = request
        self.result = result


class ConfirmClick(ModalScreen[str]):
    """A click on the map: y = send the robot there, m = mark it, d = a UV round of the room
    there, s = a sweep of it, n/Esc = nothing."""

    BINDINGS: ClassVar = [
        Binding("y", "choose('goal')", "goal"),
        Binding("m", "choose('mark')", "mark"),
        Binding("d", "choose('disinfect')", "disinfect the room"),
        Binding("s", "choose('sweep')", "sweep the room"),
        Binding("n", "choose('')", "cancel"),
        Binding("escape", "choose('')", "cancel"),
    ]

    def __init__(self, robot: str | None, x: float, y: float) -> None:
        super().__init__()
        self.robot, self.x, self.y = robot, x, y

    def compose(self) -> ComposeResult:
        who = f"send {self.robot} to" if self.robot else "(no robot selected)"
        yield Static(
            f"({self.x:.2f}, {self.y:.2f}) m\n\n[b]y[/b] {who} this point   [b]m[/b] mark it\n"
            "[b]d[/b] disinfect the room here   [b]s[/b] sweep it   [b]n[/b] cancel",
            id="confirm",
        )

    def action_choose(self, what: str) -> None:
        self.dismiss(what)


class MarkDialog(ModalScreen[tuple[str, str] | None]):
    """Mark here: the kind (up/down: casualty, hazard, note) and a label; Enter places the mark,
    ctrl+c cancels (letters are typed into the label, and Esc stays STOP ALL)."""

    BINDINGS: ClassVar = [
        Binding("up", "kind(-1)", "kind", show=False),
        Binding("down", "kind(1)", "kind", show=False),
        Binding("ctrl+c", "cancel", "cancel", priority=True),
    ]

    def __init__(self, robot: str, x: float, y: float, sd_m: float) -> None:
        super().__init__()
        self.robot, self.x, self.y, self.sd_m = robot, x, y, sd_m
        self.kind = DEFAULT_KIND

    def compose(self) -> ComposeResult:
        with Vertical(id="mark-dialog"):
            yield Static(
                f"mark at {self.robot}: ({self.x:.2f}, {self.y:.2f}) m \u00b1{self.sd_m:.2f} m", id="mark-where"
            )
            yield Static(self._kinds(), id="mark-kind")
            yield Input(
                placeholder="label (Enter: place the mark, ctrl+c: cancel)", max_length=MAX_LABEL, id="mark-label"
            )

    def on_mount(self) -> None:
        self.set_focus(self.query_one("#mark-label", Input))

    def _kinds(self) -> str:
        return "kind (up/down): " + "  ".join(f"[b reverse]{k}[/]" if k == self.kind else k for k in MARK_KINDS)

    def action_kind(self, step: int) -> None:
        self.kind = MARK_KINDS[(MARK_KINDS.index(self.kind) + step) % len(MARK_KINDS)]
        self.query_one("#mark-kind", Static).update(self._kinds())

    def action_cancel(self) -> None:
        self.dismiss(None)

    def on_input_submitted(self, event: Input.Submitted) -> None:
        event.stop()
        self.dismiss((self.kind, event.value.strip()))


class ConfirmRelease(ModalScreen[bool]):
    """Releasing an e-stop lets the robot move again: y releases, n keeps it latched (Esc is STOP
    ALL, as everywhere, and keeps it latched too)."""

    BINDINGS: ClassVar = [
        Binding("y", "choose(True)", "release"),
        Binding("n", "choose(False)", "keep"),
    ]

    def __init__(self, robot: str) -> None:
        super().__init__()
        self.robot = robot

    def compose(self) -> ComposeResult:
        yield Static(
            f"Release the e-stop on {self.robot}? It may move again.\n\n[b]y[/b] release   [b]n[/b] keep it latched"
            "   [b]Esc[/b] STOP ALL",
            id="confirm",
        )

    def action_choose(self, release: bool) -> None:
        self.dismiss(release)


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
        # shift-m (m drives back-right). Priority, so its dialog opens while the key is first
        # handled: a label typed right behind it ("victim": i and m drive) goes into the dialog.
        Binding("M", "mark_here", "mark here", show=False, priority=True),
        # E-stop: latched on the robot until an authorised release (R, with a confirmation).
        Binding("E", "estop", "E-STOP", priority=True),
        Binding("ctrl+e", "estop_all", "E-STOP ALL", priority=True),
        Binding("R", "release_estop", "release e-stop", show=False),
        Binding("A", "acknowledge", "ack alarm", show=False),  # shift-a: a drives (WASD)
        Binding("f", "fit", "fit map"),
        Binding("P", "pause_resume", "pause/resume", show=False),  # shift-p: p is the lamp
        Binding("D", "dose_layer", "dose layer", show=False),  # shift-d: d drives (WASD)
        Binding("L", "legend", "map legend", show=False),  # shift-l: l turns right
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
        doses: DoseFollower | None = None,
        read_only: bool = False,
        marks_file: Path | None = None,
        audit_log: Path | None = None,
        refresh_hz: float = 10.0,
        clock_hz: float = 2.0,
        repeat_timeout_s: float = 0.6,
        planner: RoundPlanner | None = None,
        lamp: Lamp = DEFAULT_LAMP,
        target_j_m2: float = DEFAULT_TARGET_J_M2,
    ) -> None:
        """``lock`` guards ``fleet`` against the other threads that use it (map fetcher, marks
        queryable); if ``fleet`` was already attached to ``source`` (``attach``), that feed and its
        lock are used. ``planner`` plans the rounds of ``:disinfect`` and ``:sweep``
        (``fleetlink.site.rounds.plan_round``; None: this console plans none) for ``lamp`` and a
        target dose of ``target_j_m2`` unless the command gives one."""
        super().__init__()
        self.source = source
        self.fleet = fleet
        self.clock = clock
        self.feed: FleetFeed = attach(source, fleet, lock or threading.Lock(), maps, doses or DoseFollower(fleet))
        self.lock = self.feed.lock
        assert self.feed.doses is not None
        self.doses: DoseFollower = self.feed.doses
        """The robots' UV dose layers and the fleet's (operator/dose.py; a ``DoseFetcher`` keeps them)."""
        self.show_dose = False
        """The map draws the fleet's dose layer (``D``)."""
        self.read_only = read_only
        self.marks_file = marks_file
        self.marks = MarksStore(marks_file)
        self.alarm_keeper = AlarmKeeper(source, fleet.alarms, AuditLog(audit_log, source.sender))
        self._link_states = link_states_of(source)
        """Each robot's links as the link alarms look at them (cheaper than ``health``)."""
        """Alarms (operator/alarm_panel.py): the panel's rows, acknowledgements, the audit log."""
        self.refresh_hz = refresh_hz
        self.clock_hz = clock_hz
        self.drive = DriveKeys(repeat_timeout_s=repeat_timeout_s)
        self._drive_lock = threading.Lock()
        """Guards ``drive`` and the teleop each of its decisions sends (the UI thread's keys and
        ticks, the input thread's keys: ``KeyLane``), so teleops leave in the order decided."""
        self.key_lane = KeyLane(self._drive_key_now)
        """Drive keys taken on the terminal's input thread (operator/keylane.py)."""
        self.commander = Commander(source, clock)
        self.leases = LeaseRenewal(LEASE_S)
        self.selected: str | None = None
        self.zones: dict[str, tuple[tuple[float, float], ...]] = {}
        """People-present zones this console declared, by name (sent to every robot)."""
        self._zones_sent: set[str] = set()
        self._zones_sent_empty = False
        """A withdrawal (the empty list) is still owed to robots that had zones."""
        self.planner = planner
        self.lamp = lamp
        self.target_j_m2 = target_j_m2
        self.round_ids = RoundIds()
        self.planning: RoundRequest | None = None
        """The round being planned in a worker thread (one at a time)."""
        self._plan_dropped = False
        """``:cancel`` came while it was being planned: nothing is sent when it is ready."""
        self._planned_frames: dict[str, tuple[float, float, float]] = {}
        """The frames the round being planned was planned through (``RoundFloor.frames``): its orders
        go out through them, and not at all if a robot's frame moved meanwhile."""
        self.survey: tuple[RoundRequest, dict[str, str], tuple[tuple[float, float], ...]] | None = None
        """A survey under way before a round: the request to plan again when every robot has
        finished its survey order, those orders' ids by robot, and where the survey looks from
        (the next plan's survey does not count on looking from there again)."""
        self.filter_text = ""
        self.frame_times: list[float] = []
        """How long each frame took to draw (the last 1000)."""
        self.collector = Collector(clock.now)
        """Python's garbage collector while the app runs: paced by the app (operator/collector.py)."""
        self.sent_stop_on_quit = False
        self._last_frame = -math.inf
        self._frame_cost = 0.0
        """How long the last frame took to work out (the spacing of the next, ``FRAME_SPACING``)."""
        self._frame_timer: Timer | None = None
        self._notices_forgotten = False
        """The feed forgot what was heard (a replay's seek back): the notices shown go at the next."""
        with self.lock:
            self._load_marks()
        self.feed.on_forget(self._heard_forgotten)

    def _load_marks(self) -> None:
        """The marks file into the model (the caller holds ``lock``)."""
        for mark in self.marks.load():
            self.fleet.apply(mark, "file", self.clock.now())
        self._saved_marks = self.fleet.marks_version

    def _heard_forgotten(self) -> None:
        """The app's part of ``FleetFeed.forget`` (a replay seeking back; the feed's lock held, on
        the replay's thread): what it keeps besides the model is as at its start: the marks file
        read again, the link alarms looked at afresh, the notices shown cleared (on the UI thread,
        before the next one is shown)."""
        self.alarm_keeper.forget()
        self._load_marks()
        self._notices_forgotten = True

    # -- layout ---------------------------------------------------------------------------------

    def compose(self) -> ComposeResult:
        yield StatusLine(self._status_text(), id="status")
        with Horizontal(id="main"):
            with Vertical(id="left"):
                yield Input(placeholder="/ filter robots (id, mode, link)", id="filter")
                yield FleetTable(id="fleet")
                yield RobotDetail(id="detail")
                yield AlarmPanel(id="alarms")
            yield MapView(self.fleet, lambda: self.selected, lock=self.lock, id="map")
        yield RichLog(id="notices", max_lines=500, markup=False, wrap=True)
        yield Input(
            placeholder=(
                ": goal X Y [THETA] | mark here|KIND X Y | home [set|X Y] | estop [all] | release"
                " | policy stop|retrace|home | ack | marks export PATH | payload on|off | stop"
            ),
            id="command",
        )
        yield Footer()

    def on_mount(self) -> None:
        # Everything built so far (modules, widgets, styles) lives as long as the app: out of the
        # collector's full passes, which then walk only what the fleet adds (at 500 robots a full
        # pass held the UI thread 80-190 ms). Given back on unmount. From now on the app collects
        # when it chooses (operator/collector.py), not whichever thread allocates.
        untangle_strips()
        gc.freeze()
        self.collector.start()
        self.query_one(MapView).focus()
        self.key_lane.install(self._driver)
        self.feed.bind(lambda: self.post_message(TelemetryArrived()))
        self.feed.drain()
        self.set_interval(1.0 / self.clock_hz, self._changed)
        self.set_interval(0.05, self._drive_tick)
        self.set_interval(LINK_CHECK_S, self._check_links)
        if self.read_only:
            self.notice("info", READ_ONLY_NOTICE)
        self._changed()

    def on_unmount(self) -> None:
        self.key_lane.uninstall()
        self.collector.stop()
        gc.unfreeze()
        self.feed.unbind()
        with self.lock:
            self.alarm_keeper.close()  # the last audit lines
        with contextlib.suppress(NoMatches):
            self._save_if_changed()

    # -- frames ---------------------------------------------------------------------------------

    def on_telemetry_arrived(self, _message: TelemetryArrived) -> None:
        # In slices: what is left waits behind whatever came meanwhile (a key press), not before it.
        if self.feed.drain(DRAIN_SLICE_S):
            self._changed()
        if self.feed.pending:
            self.post_message(TelemetryArrived())
        self.collector.step()

    def _changed(self) -> None:
        """Something on screen may have changed: draw a frame now, or when the last one is
        1 / refresh_hz old (or ``FRAME_SPACING`` times its own cost, if that is longer)."""
        if self._frame_timer is not None:
            return
        wait = self._last_frame + self.frame_period() - self.clock.now()
        if wait <= 0:
            self._frame()
        else:
            self._frame_timer = self.set_timer(wait, self._timed_frame)

    def frame_period(self) -> float:
        """The least time from one frame to the next: 1 / refresh_hz, or ``FRAME_SPACING`` times
        what the last frame took, if that is longer."""
        return max(1.0 / self.refresh_hz, FRAME_SPACING * self._frame_cost)

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
            self._survey_done()
            notices = fleet.drain()
            for n in notices:
                self._log_notice(n)
            table = self.query_one(FleetTable)
            if self.filter_text:  # the filter reads every row's text
                rows = fleet_rows(fleet, source.active, source.health, source.sender, now, self.filter_text)
                table.show(rows)
                order: list[str] = list(rows)
            else:  # only the rows on screen are worked out (the rest when scrolled to)
                order = sorted(fleet.robots)
                table.show_lazy(
                    order,
                    lambda r: row_cells(
                        fleet.robots[r], source.active(r), source.health(r), fleet.uwb_ok(r, now), source.sender, now
                    ),
                )
            if self.selected is None and order:
                self.selected = order[0]
                self.query_one(MapView).fit()
            mapview = self.query_one(MapView)
            mapview.dose = self.doses.layer if self.show_dose else None
            mapview.update_view()
            self.query_one(StatusLine).show(self._status_text())
            selected = self.selected
            health = source.health(selected) if selected is not None else ()
            view = fleet.robots.get(selected) if selected is not None else None
            self.query_one(RobotDetail).show(detail_text(selected, view, health))
            wall = self.clock.wall()
            said, acks = self.alarm_keeper.frame(wall)
            alarms = fleet.alarms.rows()
            self.query_one(AlarmPanel).show(alarm_lines(alarms, wall, source.sender, selected), bool(alarms))
            renew = [] if self.read_only else self.leases.due(fleet, now)
            new_robots = bool(self.zones) and any(r not in self._zones_sent for r in fleet.robots)
        self._alarms_said(said, acks)
        for robot in renew:
            self.commander.lease(robot)
        if new_robots:
            self.share_zones()
        self._save_if_changed()
        self._frame_cost = self.clock.now() - t0
        self.frame_times.append(self._frame_cost)
        del self.frame_times[:-1000]
        # A full pass, when one is due, right after the frame: the next is 1 / refresh_hz away.
        self.collector.step(after_frame=True, fleet=len(fleet.robots))

    def _check_links(self) -> None:
        """The link alarms' turn (``AlarmKeeper.check_links``): on a clock of its own between
        frames, a share of the robots' links each time (each robot about every 0.5 s); a frame
        follows when it raised or cleared an alarm."""
        fleet = self.fleet
        with self.lock:
            version = fleet.alarms.alarms.version
            self.alarm_keeper.check_links(self.clock.wall(), list(fleet.robots), self._link_states)
            changed = fleet.alarms.alarms.version != version
        if changed:
            self._changed()

    def _status_text(self) -> str:
        return status_text(self.source.sender, self.read_only, self.selected, self.drive.speed, self.drive.turn)

    def notice(self, severity: str, text: str) -> None:
        self._log_notice(Notice(self.clock.now(), severity, text))

    def _log_notice(self, n: Notice) -> None:
        style = {"info": "", "warning": "bold yellow", "error": "bold red"}.get(n.severity, "")
        log = self.query_one("#notices", RichLog)
        if self._notices_forgotten:  # the notices of a past the replay went back before
            self._notices_forgotten = False
            log.clear()
            if self.read_only:
                log.write(Text(f"{'info':7} {READ_ONLY_NOTICE}"))
        log.write(Text(f"{n.severity:7} {n.text}", style=style))

    # -- robot selection ------------------------------------------------------------------------

    def on_fleet_table_scrolled(self, _message: FleetTable.Scrolled) -> None:
        self._changed()  # the rows that came into view are worked out in the next frame

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
            row = (table.cursor_row + 1) % table.row_count
            table.move_cursor(row=row)
            # Selected now, not when the table's highlight comes back through the queues: a drive
            # key typed right behind Tab drives the robot Tab selected.
            key = table.ordered_rows[row].key.value
            if key is not None:
                self.selected = str(key)

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
        with self._drive_lock:
            self._send_twist(twist)

    def _send_twist(self, twist: Twist) -> None:
        """(Under ``_drive_lock``.)"""
        robot = self.selected
        if robot is None or self.read_only:
            return
        self.commander.teleop(robot, twist)

    def _press(self, key: str) -> None:
        """A drive, stop or speed key into ``drive``; the teleop it decides, sent (either thread)."""
        with self._drive_lock:
            twist = self.drive.press(key, self.clock.now())
            if twist is not None:
                self._send_twist(twist)

    def _drive_stop(self) -> None:
        """Driving ends (an order, an e-stop, a pause replaces it): no repeat and no auto-stop
        follows (the caller sends what replaces it)."""
        with self._drive_lock:
            self.drive.stop(self.clock.now())

    def _drive_key_now(self, event: events.Key) -> bool:
        """On the terminal's input thread (``KeyLane``, every event before this one handled): a
        drive or stop key the app would hand to the drive (the map has the focus, no dialog,
        no priority binding, a robot selected that this console may drive) sends its teleop now;
        True if so. False hands the key on to the app: speed steps (they redraw the status line),
        refusals (the app says why), every other key."""
        key = drive_key(event)
        if key not in DRIVE_KEYS and key not in STOP_KEYS:
            return False
        if self.selected is None or self.read_only or self._priority_key(event.key):
            return False
        stack = self._screen_stack
        if len(stack) != 1 or not isinstance(stack[-1].focused, MapView) or stack[-1].focused.click_pending:
            return False
        # Read without the model's lock (a frame may hold it for tens of ms): one robot's lease
        # holder, as the app's own check reads it; the robot enforces its lease either way.
        if key not in STOP_KEYS and not self.fleet.may_drive(self.selected)[0]:
            return False
        self._press(key)
        return True

    async def on_event(self, event: events.Event) -> None:
        # A drive key on the map (where the focus is by default) that the input thread handed on
        # (behind another key, operator/keylane.py) is handled the moment the app first sees it,
        # before it travels to the map and bubbles back through the queues: its Teleop goes out
        # without waiting for a frame or telemetry queued meanwhile.
        try:
            if (
                isinstance(event, events.Key)
                and not event.is_forwarded
                and isinstance(self.focused, MapView)
                and len(self.screen_stack) == 1
                and not self._priority_key(event.key)
            ):
                self.on_key(event)
                if event._stop_propagation:
                    return
            await super().on_event(event)
        finally:
            self.key_lane.handled(event)

    def _priority_key(self, key: str) -> bool:
        return any(b.priority for b in self._bindings.key_to_bindings.get(key, ()))

    def on_key(self, event: events.Key) -> None:
        if isinstance(self.focused, Input) or len(self.screen_stack) > 1:
            return
        if isinstance(self.focused, MapView) and self.focused.click_pending:
            return  # the click's dialog is on its way: the key is its answer
        key = drive_key(event)
        if not self.drive.handles(key):
            return
        event.stop()
        event.prevent_default()
        if key in STOP_KEYS:
            self._press(key)
            return
        if key not in SPEED_KEYS and not self._command_ok(self.selected, "drive"):
            return
        self._press(key)
        self.query_one(StatusLine).show(self._status_text())

    def _drive_tick(self) -> None:
        with self._drive_lock:
            twist = self.drive.tick(self.clock.now())
            if twist is not None:
                self._send_twist(twist)
        self.collector.step()

    def stop_all(self) -> list[str]:
        """Stop every robot we know: a stop instant action (acked, re-sent on failover) each."""
        self._drive_stop()
        with self.lock:
            robots = list(self.fleet.robots)
        for robot in robots:
            self.commander.stop(robot)
        return robots

    def action_stop_all(self) -> None:
        # Esc is STOP ALL everywhere (a priority binding): it also closes a confirmation, which
        # then does nothing (the e-stop stays latched, no goal goes out).
        if isinstance(self.screen, ConfirmRelease):
            self.screen.dismiss(False)
        elif isinstance(self.screen, ConfirmClick):
            self.screen.dismiss("")
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
        self._drive_stop()  # the order replaces driving: no auto-stop may cancel it later
        # On the map drawn; a robot mapping in its own frame is sent it in that frame.
        rx, ry, rtheta = self.fleet.to_robot(robot, x, y, theta)
        order_id = self.commander.goal(robot, rx, ry, rtheta)
        self.notice("info", f"{robot}: goal ({x:.2f}, {y:.2f}) sent as order {order_id}")
        view = self.fleet.robots.get(robot)
        if view is not None and view.off_fleet_map and view.in_own_frame:
            self.notice("warning", f"{robot} is not on the fleet map yet: the goal is in its own map's frame")
        return True

    def action_home(self) -> None:
        robot = self.selected
        if not self._command_ok(robot, "return home"):
            return
        assert robot is not None
        self._drive_stop()  # (as a goal: a late auto-stop would cancel the way home)
        self.commander.home(robot)
        self.notice("info", f"{robot}: return home sent")

    def action_payload(self, on: bool | None = None, device: str = "uv", level: int | None = None) -> None:
        """``p`` toggles the UV lamp; ``:payload DEVICE on|off|LEVEL`` sets one payload."""
        robot = self.selected
        if not self._command_ok(robot, "payload"):
            return
        assert robot is not None
        with self.lock:
            view = self.fleet.robots.get(robot)
            current = view.payload_on if view else False
        want = (not current) if on is None else on
        self.commander.payload(robot, want, device, level)
        what = {"uv": "UV lamp"}.get(device, device) + (f" level {level}" if level is not None else "")
        self.notice("info", f"{robot}: {what} {'on' if want else 'off'} sent")

    # -- people-present zones -----------------------------------------------------------------

    def share_zones(self) -> None:
        """This console's zones to every robot it knows that has not had them yet: on Zenoh, and
        retained on MQTT (a robot that starts later gets them from the broker)."""
        if self.read_only or (not self.zones and not self._zones_sent_empty):
            return
        with self.lock:
            robots = [r for r in self.fleet.robots if r not in self._zones_sent]
        zones = tuple(
            Zone(name=name, polygon=tuple(ZonePoint(x=x, y=y) for x, y in corners))
            for name, corners in self.zones.items()
        )
        for robot in robots:
            msg = PeopleZones(header=self.commander.header(PeopleZones.TOPIC, robot), zones=zones)
            self.source.publish(msg, links=("zenoh",))
            retained = getattr(self.source, "publish_retained", None)  # (an OperatorLink has it)
            if retained is None or not retained(msg):  # no broker keeps it: send it plain
                self.source.publish(msg, links=("mqtt",))
            self._zones_sent.add(robot)
        self._zones_sent_empty = bool(self.zones)

    # -- e-stop, home, comms-loss policy ----------------------------------------------------------

    def action_estop(self) -> None:
        if isinstance(self.focused, Input):
            raise SkipAction()  # an E typed into an input (the command line, a mark's label) is a letter
        self.estop_selected()

    def estop_selected(self) -> None:
        """Latch the selected robot's e-stop (anyone may: no lease needed)."""
        robot = self.selected
        if not self._command_ok(robot, "e-stop", needs_lease=False):
            return
        assert robot is not None
        self._drive_stop()
        self.commander.estop(robot)
        self.notice("error", f"{robot}: E-STOP sent (latched until released: R)")

    def action_estop_all(self) -> None:
        if self.read_only:
            self.notice("warning", "read-only console: e-stop not sent")
            return
        self._drive_stop()
        with self.lock:
            robots = list(self.fleet.robots)
        for robot in robots:
            self.commander.estop(robot)
        self.notice("error", f"E-STOP sent to every robot ({len(robots)})")

    def action_release_estop(self) -> None:
        """Release the selected robot's e-stop, once the operator confirms (y)."""
        robot = self.selected
        if not self._command_ok(robot, "e-stop release"):
            return
        assert robot is not None

        def confirmed(yes: bool | None) -> None:
            if yes:
                self.commander.estop_release(robot)
                self.notice("warning", f"{robot}: e-stop release sent")
            else:
                self.notice("info", f"{robot}: e-stop stays latched")

        self.push_screen(ConfirmRelease(robot), confirmed)

    def set_home(self, at: tuple[float, float] | None) -> None:
        robot = self.selected
        if not self._command_ok(robot, "set home"):
            return
        assert robot is not None
        sent = at
        if at is not None:  # on the map drawn; a robot mapping in its own frame is sent it in that frame
            hx, hy, _ = self.fleet.to_robot(robot, at[0], at[1])
            sent = (hx, hy)
        self.commander.set_home(robot, sent)
        where = "where it stands" if at is None else f"({at[0]:.2f}, {at[1]:.2f})"
        self.notice("info", f"{robot}: home set {where} sent")

    def set_comms_policy(self, policy: str) -> None:
        robot = self.selected
        if not self._command_ok(robot, "comms-loss policy"):
            return
        assert robot is not None
        self.commander.comms_policy(robot, policy)
        self.notice("info", f"{robot}: comms-loss policy {policy} sent")

    # -- alarms ---------------------------------------------------------------------------------

    def action_acknowledge(self) -> None:
        """A: acknowledge the selected robot's most severe unacknowledged alarm."""
        self.acknowledge(None, None)

    def acknowledge(self, robot: str | None, kind: AlarmKind | None, *, every: bool = False) -> None:
        """Acknowledge ``robot``'s (None: the selected robot's) alarm of ``kind`` (None: its most
        severe unacknowledged one; ``every``: all of them), shared with every console."""
        if self.read_only:
            self.notice("warning", "read-only console: acknowledgement not sent")
            return
        robot = robot or self.selected
        if robot is None:
            self.notice("warning", "no robot selected: nothing acknowledged")
            return
        with self.lock:
            outcome = self.alarm_keeper.acknowledge(robot, kind, self.clock.wall(), every=every)
            acks = self.fleet.alarms.outgoing()
        if outcome.reason:
            self.notice("warning", f"nothing acknowledged: {outcome.reason}")
        for alarm in outcome.acked:
            self.notice("info", f"{alarm.robot}: {alarm.label} acknowledged ({alarm.text})")
        self._alarms_said([], acks)
        self._changed()

    def _alarms_said(self, said: list[Said], acks: list[tuple[str, tuple[AckEntry, ...]]]) -> None:
        for s in said:
            self.notice(s.severity, s.text)
        if any(s.bell for s in said):
            self.bell()
        if acks and not self.read_only:
            self.alarm_keeper.publish(self.commander.header, acks)

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

    def _save_if_changed(self) -> None:
        """Every mark this console holds, removed ones too (operator/marks.py), to the marks file
        when they changed since the last save (marks placed here or heard from other consoles)."""
        with self.lock:
            if self.fleet.marks_version == self._saved_marks:
                return
            self._saved_marks = self.fleet.marks_version
            marks = list(self.fleet.marks.values())
        try:
            self.marks.save(marks)
        except OSError as exc:
            self.notice("error", f"marks file {self.marks.path}: not saved: {exc}")

    def _share(self, mark: Mark) -> bool:
        """Check ``mark`` as the wire would, fold it into the model and publish it on both links
        (QoS 1 on MQTT); the retained set follows (operator/marksync.py). False if refused."""
        try:
            wire.encode(mark)
        except wire.WireError as exc:
            self.notice("warning", f"mark refused: {exc.reason}")
            return False
        with self.lock:
            self.fleet.apply(mark, "local", self.clock.now())
        self.source.publish(mark, links=("zenoh", "mqtt"))
        self._save_if_changed()  # now: the file is what a restarted console starts from
        self._changed()
        return True

    def _refuse_read_only(self) -> bool:
        if self.read_only:
            self.notice("warning", "read-only console: mark not shared")
        return self.read_only

    def _marking_robot(self) -> str | None:
        with self.lock:
            robot = self.selected or next(iter(self.fleet.robots), None)
        if robot is None:
            self.notice("warning", "no robot known yet: a mark needs one to be published under")
        return robot

    def add_mark(
        self,
        x: float,
        y: float,
        kind: str = DEFAULT_KIND,
        label: str = "",
        *,
        sd_m: float = 0.0,
        robot: str | None = None,
    ) -> Mark | None:
        """A new mark at (x, y) with uncertainty ``sd_m``, published under ``robot`` (default: the
        selected one)."""
        if self._refuse_read_only():
            return None
        robot = robot or self._marking_robot()
        if robot is None:
            return None
        mark = self.marks.new(self.commander.header(Mark.TOPIC, robot), x, y, kind, label, self.clock.wall(), sd_m)
        if not self._share(mark):
            return None
        sd = f" \u00b1{mark.sd_m:.2f} m" if mark.sd_m else ""
        self.notice("info", f"mark {mark.markId}: {mark.kind} '{mark.label}' at ({x:.2f}, {y:.2f}){sd} shared")
        return mark

    def action_mark_here(self) -> None:
        """``M``: ask for a kind and a label, then mark at the selected robot's fused pose."""
        if len(self.screen_stack) > 1 or isinstance(self.focused, Input):
            raise SkipAction()
        if self._refuse_read_only():
            return
        place = self._pose_to_mark()
        if place is None:
            return
        robot, x, y, sd = place

        def chosen(answer: tuple[str, str] | None) -> None:
            # Where the robot was when M was pressed (what the dialog showed), not where it
            # has drifted while the label was typed.
            if answer is not None:
                self.add_mark(x, y, answer[0], answer[1], sd_m=sd, robot=robot)

        self.push_screen(MarkDialog(robot, x, y, sd), chosen)

    def _pose_to_mark(self, robot: str | None = None) -> tuple[str, float, float, float] | None:
        robot = robot or self._marking_robot()
        if robot is None:
            return None
        with self.lock:
            view = self.fleet.robots.get(robot)
            pose = view.pose if view is not None else None
            sd = view.pose_sd_m if view is not None else None
            lost = view.lost if view is not None else False
        if pose is None or sd is None:
            self.notice("warning", f"{robot}: no fused pose yet: mark refused (type ':mark KIND X Y' instead)")
            return None
        if lost:
            self.notice("warning", f"{robot}: lost, its last pose is stale: mark refused (type ':mark KIND X Y')")
            return None
        return robot, pose[0], pose[1], sd

    def mark_here(self, kind: str = DEFAULT_KIND, label: str = "", *, robot: str | None = None) -> Mark | None:
        """A mark at ``robot``'s (default: the selected robot's) current fused pose, carrying the
        pose's uncertainty (the larger of its x and y standard deviations)."""
        if self._refuse_read_only():
            return None
        place = self._pose_to_mark(robot)
        if place is None:
            return None
        robot, x, y, sd = place
        return self.add_mark(x, y, kind, label, sd_m=sd, robot=robot)

    def revise_mark(
        self, ref: str, *, label: str | None = None, kind: str | None = None, removed: bool | None = None
    ) -> Mark | None:
        """A new version of the mark ``ref`` names (its id or a unique tail): a new label or kind,
        or removed. Any console may edit any mark; the editor is the new version's author."""
        what = "removal" if removed else "edit"
        if self.read_only:
            self.notice("warning", f"read-only console: mark {what} not shared")
            return None
        with self.lock:
            found = find_mark(self.fleet.marks, ref)
        if isinstance(found, str):
            self.notice("warning", f"mark {what} refused: {found}")
            return None
        header = self.commander.header(Mark.TOPIC, found.header.robot)
        mark = revised(found, header, label=label, kind=kind, removed=removed)
        if not self._share(mark):
            return None
        if removed:
            self.notice("info", f"mark {mark.markId} removed")
        else:
            self.notice("info", f"mark {mark.markId} now {mark.kind} '{mark.label}'")
        return mark

    def list_marks(self, limit: int = 20) -> None:
        with self.lock:
            live = sorted(self.fleet.live_marks(), key=lambda m: m.header.timestamp)
        if not live:
            self.notice("info", "no marks")
            return
        now = self.clock.wall()
        for m in live[-limit:]:
            age = max(0.0, now - m.header.timestamp)
            self.notice(
                "info",
                f"{m.markId}  {m.kind} '{m.label}' ({m.x:.2f}, {m.y:.2f}) \u00b1{m.sd_m:.2f} m  "
                f"{m.header.robot} by {m.header.sender}, {age:.0f} s ago",
            )
        if len(live) > limit:
            self.notice("info", f"... and {len(live) - limit} older marks (':marks export PATH' writes them all)")

    def export(self, path: Path) -> int | None:
        with self.lock:
            marks = list(self.fleet.marks.values())
        try:
            n = export_marks(marks, path)
        except (OSError, ValueError) as exc:
            self.notice("warning", f"marks export refused: {exc}")
            return None
        self.notice("info", f"{n} marks written to {path}")
        return n

    # -- map ------------------------------------------------------------------------------------

    def on_map_view_clicked(self, event: MapView.Clicked) -> None:
        x, y = event.x, event.y

        def chosen(what: str | None) -> None:
            if what == "goal":
                self.send_goal(x, y)
            elif what == "mark":
                self.add_mark(x, y)
            elif what in ("disinfect", "sweep"):  # as ``:disinfect room X Y`` / ``:sweep room X Y``
                self.start_round(StartRound("uv" if what == "disinfect" else "sweep", RoomArea(x, y)))

        try:
            self.push_screen(ConfirmClick(self.selected, x, y), chosen)
        finally:
            self.query_one(MapView).click_pending = False  # the dialog is up: keys go to it

    def action_fit(self) -> None:
        with self.lock:
            self.query_one(MapView).fit()

    # -- the UV dose layer ----------------------------------------------------------------------

    def action_dose_layer(self) -> None:
        """``D``: show or hide the fleet's UV dose layer on the map."""
        self.show_dose = not self.show_dose
        with self.lock:
            layer = self.doses.layer
        if not self.show_dose:
            self.notice("info", "dose layer hidden")
        elif layer is None:
            self.notice("info", "dose layer shown: none yet (no robot has shared one)")
        else:
            self.notice(
                "info",
                f"dose layer shown: {', '.join(layer.robots)}; target {layer.target_j_m2:g} J/m²; ':dose' summarises",
            )
        self._changed()

    def dose_summary(
        self,
        box: tuple[float, float, float, float] | None = None,
        save: Path | None = None,
        *,
        target_mj_cm2: float | None = None,
    ) -> bool:
        """``:dose`` (and ``:dose save DIR``): the report on the fleet's dose layer over the robots'
        mapped floor (or ``box``), against the robots' target or ``target_mj_cm2``, worked out on a thread (a large layer takes longer than a frame);
        its lines, or the files written, come back as notices. False if there is nothing to report."""
        with self.lock:
            layers = self.doses.copies()
            maps_of = self.feed.maps.maps if self.feed.maps is not None else {}
            maps = [SharedMap(m.cells.copy(), m.resolution, m.origin, m.version) for m in maps_of.values()]
        if not layers:
            self.notice("warning", "no dose layer yet: no robot has shared one")
            return False

        def work() -> None:
            try:
                target = None if target_mj_cm2 is None else j_m2(target_mj_cm2)
                report = dose_report(layers, maps, box, target_j_m2=target)
                written = save_report(report, save) if save is not None else []
            except (OSError, ValueError) as exc:
                self.call_from_thread(self.notice, "warning", f"dose report refused: {exc}")
                return
            if save is not None:
                names = ", ".join(p.name for p in written)
                self.call_from_thread(self.notice, "info", f"dose report written to {save}: {names}")
                return
            for line in report.text().splitlines():
                self.call_from_thread(self.notice, "info", f"dose: {line}")

        self.run_worker(work, thread=True, group="dose", exit_on_error=False)
        return True

    def action_legend(self) -> None:
        """``L``: hide or show the map's legend."""
        m = self.query_one(MapView)
        m.legend = not m.legend
        with self.lock:
            m.update_view()

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
        elif isinstance(command, MarkHere):
            self.mark_here(command.kind, command.label)
        elif isinstance(command, MarkEdit):
            self.revise_mark(command.ref, label=command.label, kind=command.kind)
        elif isinstance(command, MarkRemove):
            self.revise_mark(command.ref, removed=True)
        elif isinstance(command, MarksList):
            self.list_marks()
        elif isinstance(command, MarksExport):
            self.export(Path(command.path).expanduser())
        elif isinstance(command, Home):
            self.action_home()
        elif isinstance(command, HomeSet):
            self.set_home(command.at)
        elif isinstance(command, EStop):
            self.action_estop_all() if command.every_robot else self.estop_selected()
        elif isinstance(command, EStopRelease):
            self.action_release_estop()
        elif isinstance(command, CommsPolicySet):
            self.set_comms_policy(command.policy)
        elif isinstance(command, Payload):
            self.action_payload(command.on, command.device, command.level)
        elif isinstance(command, StopAll):
            self.action_stop_all()
        elif isinstance(command, StartRound):
            self.start_round(command)
        elif isinstance(command, RoundAction):
            self.round_action(command.action)
        elif isinstance(command, ZoneAdd):
            self.zones[command.name] = command.corners
            self._zones_sent.clear()
            self.share_zones()
            self._draw_zones()
            self.notice("info", f"people-present zone {command.name!r} ({len(command.corners)} corners) sent")
        elif isinstance(command, ZoneRemove):
            if self.zones.pop(command.name, None) is None:
                self.notice("warning", f"no zone {command.name!r} (:zones lists them)")
                return
            self._zones_sent.clear()
            self.share_zones()
            self._draw_zones()
            self.notice("info", f"people-present zone {command.name!r} removed")
        elif isinstance(command, ZonesList):
            shown = "; ".join(f"{n}: {len(c)} corners" for n, c in self.zones.items()) or "none"
            self.notice("info", f"people-present zones: {shown}")
        elif isinstance(command, AckAlarm):
            self.acknowledge(command.robot, command.kind, every=command.every)
        elif isinstance(command, Dose):
            self.dose_summary(command.box, target_mj_cm2=command.target_mj_cm2)
        elif isinstance(command, DoseSave):
            self.dose_summary(command.box, Path(command.path).expanduser(), target_mj_cm2=command.target_mj_cm2)
        elif isinstance(command, Seek | Speed):
            self.replay_control(command)

    def replay_control(self, command: Seek | Speed) -> None:
        """``:seek`` and ``:speed``: what a replay's source (site/replay.py ``ReplaySource``) does;
        a live console says they are not for it. Both run on a thread of their own, never the UI's:
        a seek applies everything up to its target at once, as ``--start`` does (a seek back from
        the recording's start, after the feed forgot what it heard: ``FleetFeed.forget``), and a
        speed change waits for a seek under way."""
        source: Any = self.source
        seek, set_speed = getattr(source, "seek", None), getattr(source, "set_speed", None)
        if seek is None or set_speed is None:
            self.notice("warning", "seek and speed are for a replay (fleetlink replay FILE)")
            return
        if isinstance(command, Speed):
            factor = command.factor

            def work() -> str:
                set_speed(factor)
                return f"replay at {factor:g}x real time"

        else:
            # Relative: from where it plays now, back to the start at most (on past the end: the end).
            target = max(0.0, source.position + command.seconds) if command.relative else command.seconds

            def work() -> str:
                with self.feed.at_once():
                    seek(target)
                return f"replay at {source.position:.1f} s"

        def run() -> None:
            try:
                said = work()
            except ValueError as exc:  # not a time in the recording, not a speed: nothing moved
                self.call_from_thread(self.notice, "warning", f"{exc}")
                return
            self.call_from_thread(self._replay_moved, said)

        threading.Thread(target=run, name="replay-control", daemon=True).start()

    def _replay_moved(self, text: str) -> None:
        """A seek or a speed change is done. The replay's clock paces the frames (after a seek
        back the next frame was timed for when it would pass the last one's time again; a frame
        drawn during a seek on took the jump as its cost): paced afresh from now."""
        if self._frame_timer is not None:
            self._frame_timer.stop()
            self._frame_timer = None
        self._last_frame, self._frame_cost = -math.inf, 0.0
        self.notice("info", text)
        self._changed()

    # -- rounds: disinfection and sweeping (operator/rounds.py, docs/payload.md) ------------------

    def start_round(
        self, command: StartRound, surveys: int = MAX_SURVEYS, looked_from: tuple[tuple[float, float], ...] = ()
    ) -> bool:
        """``:disinfect`` / ``:sweep``: check what can be checked at once (a warning notice and
        nothing else when it is wrong), then plan in a worker thread; the orders go out when the
        plan is ready (``on_round_planned``). While the maps have not seen all of the area the plan
        is a survey first (up to ``surveys`` of them), and the round is planned again when the
        robots have looked (``_survey_done``). False if refused at once."""
        what = "UV round" if command.kind == "uv" else "sweep"
        if self.read_only:
            self.notice("warning", f"read-only console: {what} not planned")
            return False
        robots = command.robots or ((self.selected,) if self.selected is not None else ())
        if not robots:
            self.notice("warning", f"no robot selected: {what} not planned")
            return False
        if self.planner is None:
            self.notice("warning", f"this console has no round planner: {what} not planned")
            return False
        if self.planning is not None:
            self.notice("warning", f"still planning {describe_area(self.planning.area)}: {what} not planned")
            return False
        with self.lock:
            target = self.target_for(robots) if command.target_mj_cm2 is None else j_m2(command.target_mj_cm2)
            floor = self.fleet.round_floor(robots, command.kind)
        request = RoundRequest(
            "uv" if command.kind == "uv" else "sweep", command.area, robots, target, surveys, looked_from
        )
        try:
            if isinstance(floor, str):
                raise RoundError(floor)
            check_request(request)
        except RoundError as exc:
            self.notice("warning", f"{what} not planned: {exc}")
            return False
        self._planned_frames = floor.frames
        wall = self.clock.wall()
        ids = {robot: self.round_ids.next(request.kind, robot, wall) for robot in robots}
        planner, lamp = self.planner, self.lamp_for(robots)
        # A UV round tops up the dose the floor has had already (the fleet's layer as it stands).
        layer = self.doses.layer if request.kind == "uv" else None
        prior = layer.grid if layer is not None else None
        self.planning, self._plan_dropped, self.survey = request, False, None
        self.notice("info", f"planning the {what} of {describe_area(request.area)} for {', '.join(robots)} ...")

        def plan() -> None:  # in a worker thread: only the message goes back to the app
            result: RoundPlan | str
            try:
                cells, resolution, origin = floor_of(floor.grids(), floor.trails)
                result = planner(request, cells, resolution, origin, floor.starts, lamp, ids, prior)
            except ValueError as exc:  # RoundError, or the planner's own reasons
                result = str(exc)
            except Exception as exc:  # a planner bug must not leave the console planning forever
                log.exception("planning a round failed")
                result = f"the planner failed: {exc!r}"
            self.post_message(RoundPlanned(request, result))

        self.run_worker(plan, name="round planner", group="rounds", thread=True, exit_on_error=False)
        return True

    def target_for(self, robots: tuple[str, ...]) -> float:
        """The target dose of a round whose command names none: each robot's as its dose layer
        advertises it (its ``[uv] target_dose_mj_cm2``), the console's for a robot without one; the
        highest of them (the strictest). Under the lock."""
        layers = self.doses.layers
        return max(
            (layers[r].target_j_m2 if r in layers else self.target_j_m2 for r in robots), default=self.target_j_m2
        )

    def lamp_for(self, robots: tuple[str, ...]) -> Lamp:
        """The lamp a UV round is planned for: the first robot's own, as its dose layer advertises
        it (``DoseSnapshot.lamp``), else the console's (``[uv]`` in console.toml, the agent's defaults)."""
        for robot in robots:
            layer = self.doses.layers.get(robot)
            if layer is not None and layer.lamp is not None:
                return layer.lamp
        return self.lamp

    def on_round_planned(self, message: RoundPlanned) -> None:
        request, result = message.request, message.result
        self.planning = None
        what = "UV round" if request.kind == "uv" else "sweep"
        if self._plan_dropped:
            self.notice("info", f"{what} of {describe_area(request.area)}: cancelled while planned, not sent")
            return
        if isinstance(result, str):
            self.notice("warning", f"{what} not sent: {result}")
            return
        if self.read_only:
            return
        frames = self._planned_frames
        with self.lock:  # the lease may have moved while it was planned, and a robot's frame
            refusals = [why for ok, why in (self.fleet.may_drive(r.robot) for r in result.rounds) if not ok]
            refusals += [why for r in result.rounds if (why := self.fleet.frame_moved(r.robot, frames.get(r.robot)))]
        if refusals:
            self.notice("warning", f"{what} not sent: {refusals[0]}")
            return
        self._drive_stop()  # the orders replace driving: no late auto-stop may cancel them
        self.notice("info", result.summary())
        for robot, why in result.left_out:
            self.notice("warning", f"{robot} left out of the {what}: {why}")
        for r in result.rounds:
            try:  # planned on the map drawn: sent in the robot's own frame if it maps in one
                self.commander.order(r.robot, self.fleet.order_through(frames.get(r.robot), r.order))
            except ValueError as exc:  # the wire refused it (a size, a range)
                self.notice("warning", f"{r.robot}: {what} not sent: {exc}")
                continue
            with self.lock:
                self.fleet.set_route(r.robot, (r.order_id, tuple((n.x, n.y, n.dwell_s) for n in r.route)))
            self.notice("info", f"{r.robot}: {what} sent as order {r.order_id} ({len(r.route) - 1} nodes)")
        if result.survey:
            views = tuple((n.x, n.y) for r in result.rounds for n in r.route[1:])
            self.survey = (request, {r.robot: r.order_id for r in result.rounds}, views)
            self.notice("info", f"the {what} is planned when the survey is done (':cancel' drops both)")
        self._changed()

    def _survey_done(self) -> None:
        """Under the lock, each frame: the survey's orders all finished, plan the round again on
        the maps as they are now (one survey fewer); one ended otherwise (cancelled, stopped,
        replaced), drop the round."""
        if self.survey is None:
            return
        request, orders, views = self.survey
        ends = {r: v.order_end if (v := self.fleet.robots.get(r)) is not None else None for r in orders}
        what = "UV round" if request.kind == "uv" else "sweep"
        if any(e is not None and e[0] == orders[r] and e[1] != "finished" for r, e in ends.items()):
            self.survey = None
            self.notice(
                "warning",
                f"survey ended before it finished: the {what} of {describe_area(request.area)} is not planned",
            )
        elif all(e == (orders[r], "finished") for r, e in ends.items()):
            self.survey = None
            again = StartRound(request.kind, request.area, mj_cm2(request.target_j_m2), request.robots)
            self.call_later(self.start_round, again, request.surveys - 1, (*request.looked_from, *views))

    def round_action(self, action: str) -> None:
        """``:pause`` / ``:resume`` / ``:cancel`` the selected robot's round (or goal): instant
        actions. Anyone may pause or cancel (they stop the robot); resuming needs the lease."""
        robot = self.selected
        if not self._command_ok(robot, action, needs_lease=action == "resume"):
            return
        assert robot is not None
        if action == "cancel" and self.planning is not None and robot in self.planning.robots:
            self._plan_dropped = True
        if action in ("pause", "cancel"):
            self._drive_stop()
        kind = {"pause": ActionType.PAUSE, "resume": ActionType.RESUME, "cancel": ActionType.CANCEL}[action]
        self.commander.action(robot, kind)
        self.notice("info", f"{robot}: {action} sent")

    def action_pause_resume(self) -> None:
        """``P``: pause the selected robot's round, or resume it when it is paused."""
        if isinstance(self.focused, Input) or len(self.screen_stack) > 1:
            raise SkipAction()
        robot = self.selected
        with self.lock:
            view = self.fleet.robots.get(robot) if robot is not None else None
            paused = view is not None and (
                view.paused or (view.progress is not None and view.progress.waiting == "paused")
            )
        self.round_action("resume" if paused else "pause")

    def _draw_zones(self) -> None:
        with self.lock:
            self.fleet.set_zones(self.zones)
        self._changed()

    # -- quit -----------------------------------------------------------------------------------

    async def action_quit(self) -> None:
        self.send_stop_to_all()
        self.exit()

    def send_stop_to_all(self) -> None:
        """On quit: stop every robot (teleop zero for the selected one, stop action for all)."""
        if self.read_only or self.sent_stop_on_quit:
            return
        self.sent_stop_on_quit = True
        with self._drive_lock:  # the stop decided and sent in one step: no repeat after it
            self.drive.stop(self.clock.now())
            self._send_twist(Twist(0.0, 0.0))
        self.stop_all()
        # Then give back the leases we hold: a console that leaves on purpose is not a lost link,
        # so no robot acts on its comms-loss policy (a console that crashes leaves them held).
        with self.lock:
            held = [r for r, v in self.fleet.robots.items() if v.lease_holder == self.source.sender]
        for robot in held:
            self.commander.lease(robot, release=True)
