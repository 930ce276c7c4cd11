"""The selected robot's detail under the fleet table: drive mode, pose, goal, payload, both links.

``detail_text`` is pure; ``RobotDetail`` shows it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from textual.widgets import Static

from fleetlink.operator.fleet import RobotView
from fleetlink.operator.linkmanager import LinkHealth

__all__ = ["RobotDetail", "detail_text"]


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
    goal = "" if view.goal is None else f"  goal {view.goal[0]:+.2f} {view.goal[1]:+.2f}"
    links = "  ".join(h.describe() for h in health)
    refused = ""
    if view.refused:  # someone is sending it garbage, too much, or under another's name
        refused = f"\nrefused {view.refused} inputs" + (
            f" (last: {view.refused_reason[:80]})" if view.refused_reason else ""
        )
    return f"{view.robot} {view.drive_mode} {pose}{goal} payload {'on' if view.payload_on else 'off'}\n{links}{refused}"


class RobotDetail(Static):
    def __init__(self, **kwargs: object) -> None:
        super().__init__("", **kwargs)  # type: ignore[arg-type]
        self._text: str | None = None

    def show(self, text: str) -> None:
        if text != self._text:  # unchanged text: no relayout
            self._text = text
            self.update(text)
