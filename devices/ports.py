"""The one Port family for the board and the lidar: opened by URL, or an in-process pair for lockstep.

* ``/dev/ttyUSB0``, a pty path, ``socket://host:port``, ``loop://``: pyserial's ``serial_for_url``.
* ``InProcessPort``: a simulated device in the same process (its ``receive``, and for a device
  that streams, its ``step``), for lockstep runs where simulated time only moves when we move it.

Ports expose ``write(data)``, ``read_some(clock, deadline) -> bytes`` (whatever arrives before the
deadline; ``b""`` on timeout) and ``close()``. A port that has failed raises ``PortClosed``.
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
from collections.abc import Callable
from typing import Protocol

from fleetlink.shared.clock import Clock

__all__ = ["InProcessPort", "Port", "PortClosed", "SerialPort", "open_port"]

BAUDRATE = 115200  # the Control Bus and the RPLIDAR A1 both run 115200 8N1


class PortClosed(ConnectionError):
    """The port could not be opened, or the other end went away."""


class Port(Protocol):
    def write(self, data: bytes) -> None: ...

    def read_some(self, clock: Clock, deadline: float) -> bytes: ...

    def close(self) -> None: ...


class SerialPort:
    """A pyserial port; ``read_some`` returns whatever has arrived as soon as anything has.

    Ports with a file descriptor (ttys, ptys, ``socket://``) wait in ``select()`` and then take
    everything available in one non-blocking read (``os.read`` on POSIX, where all three are
    plain descriptors; pyserial's ``read`` with timeout 0 elsewhere). pyserial's ``in_waiting``
    is only 0 or 1 on ``socket://``, so sizing reads by it fetched one byte per call. Ports
    without a descriptor (``loop://``, ...) fall back to short blocking reads sized by
    ``in_waiting``. Either way the wait is cut into slices of at most ``slice_s``, so a deadline
    on any clock is honoured.
    """

    READ_CHUNK = 4096

    def __init__(self, url: str, baudrate: int = BAUDRATE, slice_s: float = 0.005) -> None:
        import serial  # pyserial: imported here so sans-I/O users never load it

        self.url = url
        self._serial_error: type[Exception] = serial.SerialException
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=slice_s, write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise PortClosed(f"cannot open {url}: {exc}") from exc
        self._slice = slice_s
        _no_delay(self._port)
        self._fd: int | None = None
        try:
            fd = self._port.fileno()
            if isinstance(fd, int) and fd >= 0:
                self._port.timeout = 0  # reads never block: select() does the waiting
                self._fd = fd
        except (AttributeError, NotImplementedError, OSError, ValueError, self._serial_error):
            pass  # no descriptor to wait on (e.g. loop://)
        self._os_read = os.name == "posix"  # the descriptor is non-blocking (pyserial opens it so)

    def write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except (self._serial_error, OSError) as exc:
            raise PortClosed(f"{self.url}: write failed: {exc}") from exc

    def read_some(self, clock: Clock, deadline: float) -> bytes:
        try:
            if self._fd is None:
                return self._read_polling(clock, deadline)
            fd = (self._fd,)
            while True:
                wait = min(self._slice, deadline - clock.now())
                ready, _, _ = select.select(fd, (), (), wait if wait > 0 else 0)
                if ready:
                    data = self._read_ready()
                    if data:
                        return data
                if clock.now() >= deadline:
                    return b""
        except PortClosed:
            raise
        except (self._serial_error, OSError, ValueError) as exc:
            raise PortClosed(f"{self.url}: read failed: {exc}") from exc

    def _read_ready(self) -> bytes:
        """Everything available now, once select() has said the descriptor is readable."""
        if not self._os_read:
            data: bytes = self._port.read(self.READ_CHUNK)  # timeout 0: returns what is there
            return data
        assert self._fd is not None
        try:
            data = os.read(self._fd, self.READ_CHUNK)
        except BlockingIOError:
            return b""  # a spurious wake-up
        if not data:
            raise PortClosed(f"{self.url}: closed by the other end")
        return data

    def _read_polling(self, clock: Clock, deadline: float) -> bytes:
        while True:
            waiting = self._port.in_waiting
            data: bytes = self._port.read(waiting or 1)  # blocks at most one slice
            if data:
                if self._port.in_waiting:
                    data += self._port.read(self._port.in_waiting)
                return data
            if clock.now() >= deadline:
                return b""

    def set_dtr(self, level: bool) -> None:
        """The RPLIDAR A1's motor is switched by DTR (low = motor on)."""
        with contextlib.suppress(self._serial_error, OSError, AttributeError):
            self._port.dtr = level

    def close(self) -> None:
        with contextlib.suppress(self._serial_error, OSError):
            self._port.close()


def _no_delay(port: object) -> None:
    """TCP_NODELAY on a ``socket://`` port (pyserial leaves Nagle on): a request of a few bytes
    goes out when it is written, as on a serial line, never held back for an ACK."""
    sock = getattr(port, "_socket", None)
    if isinstance(sock, socket.socket) and sock.family in (socket.AF_INET, socket.AF_INET6):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class InProcessPort:
    """The master's end of an in-process byte pair with a simulated device (a board, a lidar).

    ``peer(data)`` answers each write at once (the device's ``receive``, with the time bound in).
    ``stream(now)``, for a device that talks on its own (a lidar's scan), is asked on every read
    for the bytes due by ``now``. ``dtr(level)`` is the DTR line (the RPLIDAR A1's motor).

    Waiting for bytes that do not come advances the clock to the deadline (one actor owns time, as
    in a unit test: a ``SimClock`` moves, a ``SystemClock`` sleeps), in ``tick`` steps when there
    is a stream so that it can produce on the way; with ``advance_clock=False`` the read returns at
    once without moving time (the lockstep field, where one robot's dead link must not move
    everybody's clock). ``cut`` models a severed cable: writes vanish and nothing comes back.
    """

    def __init__(
        self,
        peer: Callable[[bytes], bytes],
        *,
        stream: Callable[[float], bytes | None] | None = None,
        dtr: Callable[[bool], None] | None = None,
        advance_clock: bool = True,
        tick: float = 0.005,
    ) -> None:
        self._peer = peer
        self._stream = stream
        self._dtr = dtr
        self.advance_clock = advance_clock
        self.tick = tick
        self._inbox = bytearray()
        self.cut = False
        self.closed = False

    def write(self, data: bytes) -> None:
        if self.closed:
            raise PortClosed("in-process port is closed")
        if not self.cut:
            self._inbox += self._peer(bytes(data))

    def inject(self, data: bytes) -> None:
        """Bytes that arrive without being asked for (line noise in tests)."""
        self._inbox += data

    def read_some(self, clock: Clock, deadline: float) -> bytes:
        if self.closed:
            raise PortClosed("in-process port is closed")
        while True:
            if self._stream is not None:
                out = self._stream(clock.now())
                if out and not self.cut:
                    self._inbox += out
            if self._inbox:
                data = bytes(self._inbox)
                self._inbox.clear()
                return data
            now = clock.now()
            if now >= deadline or not self.advance_clock:
                return b""
            clock.sleep_until(deadline if self._stream is None else min(deadline, now + self.tick))

    def set_dtr(self, level: bool) -> None:
        if self._dtr is not None and not self.closed and not self.cut:
            self._dtr(level)

    def close(self) -> None:
        self.closed = True


def open_port(url: str, baudrate: int = BAUDRATE) -> SerialPort:
    return SerialPort(url, baudrate)
