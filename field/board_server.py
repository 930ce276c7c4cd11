"""Serve a simulated control board on TCP or a pty (a ``DeviceServer`` for ``SimulatedBoard``)."""

from __future__ import annotations

import threading

from fleetlink.field.board import SimulatedBoard
from fleetlink.field.device_server import DeviceServer, Reactor
from fleetlink.shared.clock import Clock

__all__ = ["BoardServer"]


class BoardServer(DeviceServer):
    def __init__(
        self,
        board: SimulatedBoard,
        clock: Clock,
        step_hz: float | None = 200.0,
        lock: threading.Lock | None = None,
        reactor: Reactor | None = None,
    ) -> None:
        super().__init__(board, clock, step_hz, lock, name="board", reactor=reactor)
        self.board = board
