"""The operator console (Textual): fleet table, map, direct drive, goals, marks, leases, notices.

The app never opens a transport: it gets a ``ConsoleSource`` (in production ``OperatorLink``,
which owns Zenoh + MQTT and the link manager) and a ``FleetModel`` fed by that source's sink.
Network threads only touch the fleet model (under ``self.lock``) and queue notices; the app reads
both from a 10 Hz timer on its own thread, so no widget is ever touched off the UI thread.

Safety: when drive-key repeats stop arriving the console sends stop (see operator/teleop.py), Esc
stops every robot, and quitting sends stop to every robot before the links close.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ClassVar, Protocol

from rich.text import Text
from textual import events
from textual.actions import SkipAction
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.css.query import NoMatches
from textual.screen import ModalScreen
from textual.widgets import DataTable, Footer, Input, RichLog, Static

from fleetlink.operator.fleet import FleetModel, Notice
from fleetlink.operator.linkmanager import PRIMARY, Failed, LinkHealth, Switch
from fleetlink.operator.maps import MapFollower
from fleetlink.operator.mapview import MapView
from fleetlink.operator.teleop import DriveKeys, Twist
from fleetlink.shared import wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import (
    Action,
    ActionType,
    Goal,
    InstantActions,
    KeyValue,
    LeaseRequest,
    MapUpdate,
    Mark,
    Order,
    Teleop,
)

log = logging.getLogger(__name__)

__all__ = ["ConsoleApp", "ConsoleSource", "attach"]

TELEOP_TTL_S = 0.5
LEASE_S = 60.0


class ConsoleSource(Protocol):
    """What the console needs from the network side (``OperatorLink`` provides it)."""

    sender: str

    def send(self, cls: type[wire.Message], robot: str, *, expect_ack: bool = True, **fields: Any) -> wire.Message: ...

    def publish(self, msg: wire.Message, *, links: Sequence[str] = ...) -> None: ...

    def active(self, robot: str) -> str: ...

    def health(self, robot: str) -> tuple[LinkHealth, ...]: ...

    def add_listener(self, listener: Callable[[Switch | Failed], None]) -> None: ...

    def add_sink(self, sink: Callable[[wire.Message, str, float], None]) -> None: ...


def attach(source: ConsoleSource, fleet: FleetModel, lock: threading.Lock, maps: MapFollower | None = None) -> None:
    """Feed ``fleet`` from ``source`` (messages, link switches, UWB anchors), under ``lock``; map
    updates also go to ``maps``."""

    def sink(msg: wire.Message, link: str, now: float) -> None:
        with lock:
            if fleet.apply(msg, link, now) and maps is not None and isinstance(msg, MapUpdate):
                maps.on_update(msg)

    def anchors(gateway: str, found: list[tuple[str, float, float, float]]) -> None:
        with lock:
            for name, x, y, _z in found:
                fleet.add_anchor(name, x, y)

    add_anchor_sink = getattr(source, "add_anchor_sink", None)
    if add_anchor_sink is not None:
        add_anchor_sink(anchors)

    def listener(action: Switch | Failed) -> None:
        with lock:
            if isinstance(action, Switch):
                sev = "warning" if action.to_link != PRIMARY else "info"
                fleet.notify(action.at, sev, f"failover: {action.describe()}")
            else:
                fleet.notify(0.0, "error", f"{action.robot}: {action.topic} #{action.header_id} lost: {action.reason}")

    source.add_sink(sink)
    source.add_listener(listener)


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
        read_only: bool = False,
        marks_file: Path | None = None,
        refresh_hz: float = 10.0,
        repeat_timeout_s: float = 0.6,
    ) -> None:
        super().__init__()
        self.source = source
        self.fleet = fleet
        self.clock = clock
        self.lock = lock or threading.Lock()
        self.read_only = read_only
        self.marks_file = marks_file
        self.refresh_hz = refresh_hz
        self.drive = DriveKeys(repeat_timeout_s=repeat_timeout_s)
        self.selected: str | None = None
        self.filter_text = ""
        self._mark_seq = 0
        self._last_lease_renew = -1e9
        self._saved_marks: set[str] = set()
        self.frame_times: list[float] = []
        self.sent_stop_on_quit = False
        if marks_file is not None:
            self._load_marks(marks_file)

    # -- layout ---------------------------------------------------------------------------------

    def compose(self) -> ComposeResult:
        # No markup: "[driving]" / "[READ-ONLY]" would be read as style tags and vanish.
        yield Static(self._status_text(), id="status", markup=False)
        with Horizontal(id="main"):
            with Vertical(id="left"):
                yield Input(placeholder="/ filter robots (id, mode, link)", id="filter")
                yield DataTable(id="fleet", cursor_type="row", zebra_stripes=True)
                yield Static("", id="detail")
            yield MapView(self.fleet, lambda: self.selected, id="map")
        yield RichLog(id="notices", max_lines=500, markup=False, wrap=True)
        yield Input(
            placeholder=": goal X Y [THETA] | mark KIND X Y [LABEL] | home | payload on|off | stop", id="command"
        )
        yield Footer()

    def on_mount(self) -> None:
        table = self.query_one("#fleet", DataTable)
        for label, key in COLUMNS:
            table.add_column(label, key=key)
        self.query_one(MapView).focus()
        self.set_interval(1.0 / self.refresh_hz, self._refresh)
        self.set_interval(0.05, self._drive_tick)
        if self.read_only:
            self.notice("info", "read-only mode: this console watches, it does not command")

    # -- periodic -------------------------------------------------------------------------------

    def _refresh(self) -> None:
        # A last timer tick can come while the app shuts down and its widgets are gone.
        with contextlib.suppress(NoMatches):
            self._refresh_once()

    def _refresh_once(self) -> None:
        t0 = self.clock.now()
        now = t0
        with self.lock:
            self.fleet.tick(now)
            notices = self.fleet.drain()
            rows = self._rows(now)
        for n in notices:
            self._log_notice(n)
        self._update_table(rows)
        self.query_one(MapView).update_view()
        self.query_one("#status", Static).update(self._status_text())
        self.query_one("#detail", Static).update(self._detail_text(now))
        self._renew_lease(now)
        self.frame_times.append(self.clock.now() - t0)
        del self.frame_times[:-1000]

    def _rows(self, now: float) -> dict[str, tuple[str | Text, ...]]:
        rows: dict[str, tuple[str | Text, ...]] = {}
        for robot in sorted(self.fleet.robots):
            view = self.fleet.robots[robot]
            link = self.source.active(robot)
            health = self.source.health(robot)
            hp = next((h for h in health if h.link == PRIMARY), None)
            if hp is None or hp.age_s is None:
                htext = Text("-", style="dim")
            elif hp.healthy:
                rtt = f" {hp.rtt_s * 1000:.0f}ms" if hp.rtt_s is not None else ""
                htext = Text(f"ok {hp.loss_pct:.0f}%{rtt}", style="green")
            else:
                htext = Text(f"DOWN {hp.loss_pct:.0f}%", style="bold red")
            age = view.age(now)
            uwb = self.fleet.uwb_ok(robot, now)
            if view.lease_holder is None:
                lease = "-"
            elif not view.lease_holder:
                lease = "free"
            else:
                lease = "you" if view.lease_holder == self.source.sender else view.lease_holder
            cells: tuple[str | Text, ...] = (
                Text(robot, style="bold red" if view.lost else ""),
                view.mode if not view.estop else Text("ESTOP", style="bold red"),
                "?" if view.battery is None else f"{view.battery:.0f}%",
                Text(link, style="green" if link == PRIMARY else "bold yellow"),
                htext,
                "-" if age is None else (f"{age:.1f}s" if age >= 1 else f"{age * 1000:.0f}ms"),
                Text("?", style="dim") if uwb is None else Text("ok", "green") if uwb else Text("stale", "bold yellow"),
                lease,
            )
            text = " ".join(str(c) for c in cells).lower()
            if self.filter_text and self.filter_text.lower() not in text:
                continue
            rows[robot] = cells
        return rows

    def _update_table(self, rows: dict[str, tuple[str | Text, ...]]) -> None:
        table = self.query_one("#fleet", DataTable)
        present = {str(k.value) for k in table.rows}
        for robot in present - rows.keys():
            table.remove_row(robot)
        for robot, cells in rows.items():
            if robot in present:
                for (_, key), value in zip(COLUMNS, cells, strict=True):
                    table.update_cell(robot, key, value)
            else:
                table.add_row(*cells, key=robot)
        if self.selected is None and rows:
            self.selected = next(iter(rows))
            self.query_one(MapView).fit()

    def _status_text(self) -> str:
        mode = "READ-ONLY" if self.read_only else "driving"
        sel = self.selected or "-"
        return (
            f"fleetlink console  operator {self.source.sender}  [{mode}]  robot {sel}  "
            f"speed {self.drive.speed:.2f} m/s turn {self.drive.turn:.2f} rad/s"
        )

    def _detail_text(self, now: float) -> str:
        if self.selected is None:
            return "no robot"
        view = self.fleet.robots.get(self.selected)
        if view is None:
            return self.selected
        pose = (
            "pose ?"
            if view.pose is None
            else f"pose {view.pose[0]:+.2f} {view.pose[1]:+.2f} {math.degrees(view.pose[2]):+.0f}°"
        )
        goal = "" if view.goal is None else f"  goal {view.goal[0]:+.2f} {view.goal[1]:+.2f}"
        links = "  ".join(h.describe() for h in self.source.health(self.selected))
        return f"{view.robot} {view.drive_mode} {pose}{goal} payload {'on' if view.payload_on else 'off'}\n{links}"

    def notice(self, severity: str, text: str) -> None:
        self._log_notice(Notice(self.clock.now(), severity, text))

    def _log_notice(self, n: Notice) -> None:
        style = {"info": "", "warning": "bold yellow", "error": "bold red"}.get(n.severity, "")
        self.query_one("#notices", RichLog).write(Text(f"{n.severity:7} {n.text}", style=style))

    # -- robot selection ------------------------------------------------------------------------

    def on_data_table_row_highlighted(self, event: DataTable.RowHighlighted) -> None:
        if event.row_key.value is not None:
            self.selected = str(event.row_key.value)

    def action_next_robot(self) -> None:
        """Select the next row of the fleet table (wrapping); in an input or a dialog, tab keeps
        its usual meaning (focus next)."""
        if isinstance(self.focused, Input) or len(self.screen_stack) > 1:
            raise SkipAction()
        table = self.query_one("#fleet", DataTable)
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
        self.source.send(Teleop, robot, expect_ack=False, v=twist.v, omega=twist.omega, ttl_s=TELEOP_TTL_S)

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
        self.query_one("#status", Static).update(self._status_text())

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
            self.source.send(
                InstantActions,
                robot,
                actions=(Action(actionId="stop-all", actionType=ActionType.STOP, actionParameters=()),),
            )
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
        order_id = f"{self.source.sender}-{self.clock.wall():.3f}"
        self.source.send(
            Order, robot, orderId=order_id[:64], orderUpdateId=0, goal=Goal(x=x, y=y, theta=theta), returnHome=False
        )
        self.notice("info", f"{robot}: goal ({x:.2f}, {y:.2f}) sent as order {order_id}")
        return True

    def action_home(self) -> None:
        robot = self.selected
        if not self._command_ok(robot, "return home"):
            return
        assert robot is not None
        order_id = f"{self.source.sender}-home-{self.clock.wall():.3f}"
        self.source.send(Order, robot, orderId=order_id[:64], orderUpdateId=0, goal=None, returnHome=True)
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
        action = Action(
            actionId=f"payload-{self.clock.wall():.3f}",
            actionType=ActionType.PAYLOAD,
            actionParameters=(KeyValue(key="on", value="true" if want else "false"),),
        )
        self.source.send(InstantActions, robot, actions=(action,))
        self.notice("info", f"{robot}: payload {'on' if want else 'off'} sent")

    def action_lease(self) -> None:
        robot = self.selected
        if not self._command_ok(robot, "lease request", needs_lease=False):
            return
        assert robot is not None
        self._request_lease(robot, release=False)
        self.notice("info", f"{robot}: control lease requested")

    def action_release_lease(self) -> None:
        robot = self.selected
        if not self._command_ok(robot, "lease release", needs_lease=False):
            return
        assert robot is not None
        self._request_lease(robot, release=True)

    def _request_lease(self, robot: str, *, release: bool) -> None:
        header = self._header(LeaseRequest.TOPIC, robot)
        self.source.publish(
            LeaseRequest(header=header, duration_s=0.0 if release else LEASE_S, release=release),
            links=("zenoh", "mqtt"),
        )

    def _renew_lease(self, now: float) -> None:
        if self.read_only or now - self._last_lease_renew < LEASE_S / 3:
            return
        self._last_lease_renew = now
        with self.lock:
            mine = [r for r, v in self.fleet.robots.items() if v.lease_holder == self.source.sender]
        for robot in mine:
            self._request_lease(robot, release=False)

    def _header(self, topic: str, robot: str) -> wire.Header:
        counter: wire.HeaderCounter | None = getattr(self.source, "counter", None)
        if counter is None:
            counter = self._counter = getattr(self, "_counter", None) or wire.HeaderCounter(
                self.clock, robot=robot, sender=self.source.sender
            )
        return counter.header(topic, robot=robot)

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
        self._mark_seq += 1
        mark_id = f"{self.source.sender}-{int(self.clock.wall())}-{self._mark_seq}"[:64]
        mark = Mark(
            header=self._header(Mark.TOPIC, robot),
            markId=mark_id,
            x=x,
            y=y,
            label=label[:64] or kind,
            kind=kind[:32],
            removed=False,
        )
        with self.lock:
            self.fleet.apply(mark, "local", self.clock.now())
        self.source.publish(mark)
        self._save_marks()
        self.notice("info", f"mark {mark.kind} '{mark.label}' at ({x:.2f}, {y:.2f}) shared")
        return mark

    def _save_marks(self) -> None:
        if self.marks_file is None:
            return
        with self.lock:
            marks = [
                {
                    "markId": m.markId,
                    "x": m.x,
                    "y": m.y,
                    "label": m.label,
                    "kind": m.kind,
                    "by": m.header.sender,
                    "robot": m.header.robot,
                    "timestamp": m.header.timestamp,
                }
                for m in self.fleet.live_marks()
            ]
        tmp = self.marks_file.with_suffix(".tmp")
        tmp.write_text(json.dumps({"marks": marks}, indent=2) + "\n")
        tmp.replace(self.marks_file)

    def _load_marks(self, path: Path) -> None:
        if not path.exists():
            return
        try:
            data = json.loads(path.read_text())
            for m in data.get("marks", []):
                header = wire.Header(
                    headerId=0,
                    timestamp=float(m["timestamp"]),
                    version=wire.WIRE_VERSION,
                    robot=m["robot"],
                    sender=m["by"],
                )
                mark = Mark(
                    header=header,
                    markId=m["markId"],
                    x=float(m["x"]),
                    y=float(m["y"]),
                    label=m["label"],
                    kind=m["kind"],
                    removed=False,
                )
                wire.encode(mark)  # validates
                self.fleet.marks[mark.markId] = mark
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("marks file %s ignored: %s", path, exc)

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
        self.query_one(MapView).fit()

    def action_zoom(self, factor: float) -> None:
        m = self.query_one(MapView)
        m.geometry.zoom(factor)
        m.update_view()

    def action_pan(self, dcols: float, drows: float) -> None:
        m = self.query_one(MapView)
        m.geometry.pan(dcols, drows)
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

    def on_input_submitted(self, event: Input.Submitted) -> None:
        if event.input.id == "command":
            self.run_command(event.value)
            event.input.value = ""
        self.query_one(MapView).focus()

    def run_command(self, line: str) -> None:
        """Typed commands: goal X Y [THETA_DEG], mark KIND X Y [LABEL], home, payload on|off, stop."""
        words = line.split()
        if not words:
            return
        verb, args = words[0].lower(), words[1:]
        try:
            if verb in ("goal", "g") and len(args) in (2, 3):
                nums = [float(a) for a in args]
                if not all(math.isfinite(v) for v in nums):
                    raise ValueError("coordinates must be finite numbers")
                theta = math.radians(nums[2]) if len(nums) == 3 else None
                if theta is not None:
                    theta = math.atan2(math.sin(theta), math.cos(theta))
                self.send_goal(nums[0], nums[1], theta)
            elif verb == "mark" and len(args) >= 3:
                x, y = float(args[1]), float(args[2])
                if not (math.isfinite(x) and math.isfinite(y)):
                    raise ValueError("coordinates must be finite numbers")
                self.add_mark(x, y, args[0], " ".join(args[3:]))
            elif verb == "home" and not args:
                self.action_home()
            elif verb == "payload" and args in (["on"], ["off"]):
                self.action_payload(args[0] == "on")
            elif verb == "stop" and not args:
                self.action_stop_all()
            else:
                self.notice(
                    "warning",
                    f"unknown command {line!r}: goal X Y [THETA_DEG] | mark KIND X Y [LABEL] | home | payload on|off | stop",
                )
        except ValueError as exc:
            self.notice("warning", f"bad command {line!r}: {exc}")

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
