"""Drive keys taken on the terminal's input thread (docs/console.md, "Responsiveness").

Textual's driver reads the terminal on a thread of its own and hands each event it parsed to the
app's event loop (``Driver.process_message``), where it waits behind whatever the loop is doing: a
redraw of the screen's changed lines (15-18 ms of CPU at 500 robots, 40-60 ms of wall time on a
busy host), a slice of telemetry, a frame. ``KeyLane`` sits in the driver's ``process_message``,
on that thread: a key the app would hand to the drive anyway is given to ``take`` there, which
sends its teleop at once (``True``: taken, it never reaches the loop); every other event, and a
key ``take`` declines, goes on to the loop as before.

Order: a key is offered to ``take`` only when every key and mouse button event handed on before
it has been handled by the app (``handled``, called by the app's ``on_event`` when it is done
with one: a priority binding has run, the key was forwarded to the focused widget). So ``:`` then
``i`` typed fast still types the ``i`` (the ``:`` is in flight, the ``i`` follows it through the
loop, where the command line has the focus by then), and Tab then ``i`` drives the robot Tab
selected. What ``take`` reads of the app (the focus, the open screens, the selected robot) is what
the app's own handling of the key would read; it is read without a lock, on this thread.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from textual import events
from textual.message import Message

__all__ = ["ORDERED", "KeyLane"]

log = logging.getLogger(__name__)

ORDERED = (events.Key, events.MouseDown, events.MouseUp, events.MouseScrollDown, events.MouseScrollUp)
"""Events that may change where a key goes (the focus, a dialog, the selection): a key behind one
of them waits for it in the loop. (Mouse moves and resizes change nothing a drive key depends on.)"""


class KeyLane:
    """See the module docstring. ``install`` on the UI thread (on mount), ``process`` on the
    driver's input thread, ``handled`` on the UI thread."""

    def __init__(self, take: Callable[[events.Key], bool]) -> None:
        self._take = take
        self._lock = threading.Lock()
        self._in_flight: set[int] = set()
        """ids of the ordered events handed on to the loop and not yet handled (alive until then)."""
        self._driver: Any = None
        self._forward: Callable[[Message], None] | None = None
        self.taken = 0
        """Keys taken on the input thread."""
        self.handed_on = 0
        """Keys handed on to the loop (declined, or behind another event)."""

    def install(self, driver: Any) -> bool:
        """Sit in ``driver.process_message`` (every Textual driver's input thread calls it for each
        event it parsed). False if the driver has none."""
        forward = getattr(driver, "process_message", None)
        if forward is None or self._driver is not None:
            return False
        self._driver, self._forward = driver, forward
        driver.process_message = self.process
        return True

    def uninstall(self) -> None:
        driver, self._driver = self._driver, None
        if driver is not None and driver.__dict__.get("process_message") == self.process:
            del driver.process_message  # the class's own again

    def process(self, message: Message) -> None:
        """On the driver's input thread: take a key, or hand the event on to the loop."""
        forward = self._forward
        assert forward is not None
        if isinstance(message, ORDERED):
            with self._lock:
                behind = bool(self._in_flight)
            if isinstance(message, events.Key):
                if not behind and self._offer(message):
                    self.taken += 1
                    return
                self.handed_on += 1
            with self._lock:
                self._in_flight.add(id(message))
        forward(message)

    def _offer(self, key: events.Key) -> bool:
        try:
            return self._take(key)
        except Exception:  # never lose the terminal's input thread: the loop handles the key instead
            log.exception("a drive key on the input thread failed; handed on to the app")
            return False

    def handled(self, message: Message) -> None:
        """On the UI thread: the app is done with ``message`` (a no-op for events not handed on
        by ``process``)."""
        if self._in_flight:
            with self._lock:
                self._in_flight.discard(id(message))

    @property
    def waiting(self) -> int:
        """Ordered events handed on to the loop and not yet handled."""
        return len(self._in_flight)
