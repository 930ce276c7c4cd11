"""The selected robot's detail under the fleet table: drive mode, e-stop, pose, goal, its round's
progress, home, the comms-loss policy, payload, both links, what its agent refused, and its board's
status.

``detail_text`` is pure; ``RobotDetail`` shows it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from textual.visual import visualize
from textual.widgets import Static

from fleetlink.operator.fleet import RobotView
from fleetlink.operator.linkmanager import LinkHealth
from fleetlink.operator.rounds import describe_time
from fleetlink.shared.messages import BoardStatus

__all__ = ["RobotDetail", "board_text", "detail_text", "progress_text"]


def detail_text(selected: str | None, view: RobotView | None, health: Sequence[LinkHealth]) -> str:
    if selected is None:
        return "no robot"
    if view is None:
        return selected
    pose = (
        "pose ?"
        if view.pose is None
        else f"pose {view.pose[0]:+.2f} {view.pose[1]:+.2f} {math.degrees(view.pose[2]):+.0f}°"
    )
    if view.off_fleet_map and view.in_own_frame:
        pose += "\nits own frame: not on the fleet map yet" + (
            f" ({view.off_fleet_map_why})" if view.off_fleet_map_why else ""
        )
    goal = "" if view.goal is None else f"  goal {view.goal[0]:+.2f} {view.goal[1]:+.2f}"
    links = "  ".join(h.describe() for h in health)
    refused = ""
    if view.refused:  # someone is sending it garbage, too much, or under another's name
        refused = f"\nrefused {view.refused} inputs" + (
            f" (last: {view.refused_reason[:80]})" if view.refused_reason else ""
        )
    safety = ""
    if view.estop:
        safety = f"  E-STOP ({'button on the robot' if view.estop_source == 'MANUAL' else 'remote'})"
    home = "" if view.home is None else f"\nhome {view.home[0]:+.2f} {view.home[1]:+.2f} ({view.home_source})"
    contact = ""
    if view.comms_policy:
        contact = f"  comms-loss: {view.comms_policy}"
        if view.contact_lost:
            contact += f" OUT OF CONTACT ({view.contact_action or 'stopped'})"
    payload = "" if view.board is not None else f" payload {'on' if view.payload_on else 'off'}"
    head = f"{view.robot} {view.drive_mode}{safety} {pose}{goal}{payload}"
    power, more = board_text(view.board)
    # Most important first: a small terminal shows the first lines only.
    return f"{head}{progress_text(view)}{power}{home}{contact}\n{links}{refused}{more}"


def progress_text(view: RobotView) -> str:
    """The robot's order with nodes (a round) as it reports it, with its newline: node k of N,
    skipped nodes, the dwell still to run, and why it waits (paused, e-stop, lamp refused, ...)."""
    p = view.progress
    if p is None:
        return ""
    text = f"\nround {view.order_id}: {p.nodesDone}/{p.nodesTotal} nodes done"
    if p.skipped:
        text += f", {p.skipped} skipped"
    if p.dwellLeft_s > 0:
        text += f", dwell {describe_time(p.dwellLeft_s)} left"
    if p.waiting:
        text += f"  WAITING: {p.waiting}"
    return text


def board_text(b: BoardStatus | None) -> tuple[str, str]:
    """The board's status for people: the power and payload line (with its newline), and the
    rest (environment, the e-stop button, faults, watchdog trips)."""
    if b is None:
        return "", ""
    if not b.connected:
        return "\nboard: not connected", ""
    power = f"battery {b.battery_percent:.0f}%"
    if b.battery_voltage_v is not None:
        power += f" {b.battery_voltage_v:.2f} V"
    if b.charging:
        power += " charging"
    if b.on_dock:
        power += " on dock"
    payload = f"lamp {'on' if b.uv_lamp else 'off'} atomiser {b.atomiser_level} fan {b.fan_level}"
    if b.tank_percent is not None:
        payload += f" tank {b.tank_percent:.0f}%"
    env = []
    if b.temperature_c is not None:
        env.append(f"{b.temperature_c:.1f}°C")
    if b.humidity_percent is not None:
        env.append(f"RH {b.humidity_percent:.0f}%")
    if b.pm2_5_ug_m3 is not None:
        env.append(f"PM2.5 {b.pm2_5_ug_m3:.1f}")
    if b.tvoc_ppb is not None:
        env.append(f"TVOC {b.tvoc_ppb} ppb")
    more = f"\n{'  '.join(env)}" if env else ""
    if b.estop_button:
        more += "\nE-STOP BUTTON PRESSED"
    if b.faults:
        more += "\nfaults: " + "; ".join(f"0x{f.code:04X} {f.text}" for f in b.faults)
    if b.watchdog_trips:
        more += f"\nwatchdog trips {b.watchdog_trips}"
    return f"\n{power}  {payload}", more


class RobotDetail(Static):
    def __init__(self, **kwargs: object) -> None:
        super().__init__("", **kwargs)  # type: ignore[arg-type]
        self._text: str | None = None
        self._height: int | None = None
        """Lines the text took when last shown (wrapped at the width it had)."""

    def show(self, text: str) -> None:
        if text == self._text:
            return
        # Its height follows its lines as wrapped (height: auto): a relayout of the screen only
        # when that height changes, not for every pose (a relayout redraws the whole screen,
        # 15-40 ms at 50 robots on a busy host, and a key pressed meanwhile waits for it).
        width = self.content_size.width
        visual = visualize(self, text, markup=self._render_markup)
        height = visual.get_height(self.styles, width) if width else None  # type: ignore[arg-type]  # (as Widget does)
        self._text = text
        self.update(text, layout=height is None or height != self._height)
        self._height = height
