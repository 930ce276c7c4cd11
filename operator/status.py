"""The status line at the top: operator, driving or read-only, selected robot, drive speeds.

``status_text`` is pure; ``StatusLine`` shows it.
"""

from __future__ import annotations

from textual.widgets import Static

__all__ = ["StatusLine", "status_text"]


def status_text(operator: str, read_only: bool, selected: str | None, speed: float, turn: float) -> str:
    mode = "READ-ONLY" if read_only else "driving"
    return (
        f"fleetlink console  operator {operator}  [{mode}]  robot {selected or '-'}  "
        f"speed {speed:.2f} m/s turn {turn:.2f} rad/s"
    )


class StatusLine(Static):
    def __init__(self, text: str, **kwargs: object) -> None:
        # No markup: "[driving]" / "[READ-ONLY]" would be read as style tags and vanish.
        super().__init__(text, markup=False, **kwargs)  # type: ignore[arg-type]
        self._text = text

    def show(self, text: str) -> None:
        if text != self._text:
            self._text = text
            self.update(text, layout=False)  # one line high (console.tcss): no relayout
