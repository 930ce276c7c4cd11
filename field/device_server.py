"""Serve a simulated serial device (control board, lidar) on TCP or a pty, in real time.

A master reaches the device through real bytes, exactly as it would reach hardware on
``/dev/ttyUSB0``. Each TCP connection (one at a time, like a UART) or the pty has a reader thread
that feeds the device and writes its replies. Unless the owner steps the device itself (the field
steps all its devices from one physics loop and passes ``step_hz=None``), a stepper thread advances
it; bytes a device emits on its own (a lidar's measurement stream) go out as they are produced.
``stop()`` closes everything; a new server on the same port models a device that restarts.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import socket
import threading
import tty
from typing import Protocol

from fleetlink.shared.clock import Clock

log = logging.getLogger(__name__)

__all__ = ["DeviceServer", "SimDevice"]


class SimDevice(Protocol):
    """A sans-I/O device: bytes in, bytes out, time passed in."""

    def receive(self, data: bytes, now: float) -> bytes: ...

    def step(self, now: float) -> bytes | None: ...

    def start_clock(self, now: float) -> None: ...


class DeviceServer:
    def __init__(
        self,
        device: SimDevice,
        clock: Clock,
        step_hz: float | None = 200.0,
        lock: threading.Lock | None = None,
        name: str = "device",
    ) -> None:
        self.device = device
        self.clock = clock
        self.lock = lock or threading.Lock()
        self.name = name
        self._period = 1.0 / step_hz if step_hz else None
        self._write_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._listener: socket.socket | None = None
        self._conn: socket.socket | None = None
        self._pty_fds: tuple[int, int] | None = None
        self.port: int | None = None
        self.pty_path: str | None = None
        self.paused = False  # a "cut cable": bytes in are dropped, nothing goes out

    # -- lifecycle -------------------------------------------------------------------------

    def serve_tcp(self, host: str = "127.0.0.1", port: int = 0) -> int:
        ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        ls.bind((host, port))
        ls.listen(1)
        ls.settimeout(0.1)
        self._listener = ls
        self.port = ls.getsockname()[1]
        self._spawn(self._accept_loop, f"{self.name}-tcp")
        self._ensure_stepper()
        return self.port

    def serve_pty(self) -> str:
        master, slave = os.openpty()
        tty.setraw(slave)
        tty.setraw(master)
        self._pty_fds = (master, slave)
        self.pty_path = os.ttyname(slave)
        self._spawn(self._pty_loop, f"{self.name}-pty")
        self._ensure_stepper()
        return self.pty_path

    def stop(self) -> None:
        self._stop.set()
        if self._conn is not None:
            _close(self._conn)
        for t in self._threads:
            t.join(2.0)
        self._threads.clear()
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        if self._pty_fds is not None:
            for fd in self._pty_fds:
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._pty_fds = None

    def emit(self, data: bytes) -> None:
        """Send bytes the device produced on its own to whoever is connected (dropped if nobody is)."""
        if not data or self.paused:
            return
        with self._write_lock:
            conn = self._conn
            if conn is not None:
                with contextlib.suppress(OSError):
                    conn.sendall(data)
            if self._pty_fds is not None:
                with contextlib.suppress(OSError):
                    os.write(self._pty_fds[0], data)

    def __enter__(self) -> DeviceServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- internals -------------------------------------------------------------------------

    def _spawn(self, target: object, name: str) -> None:
        t = threading.Thread(target=target, name=name, daemon=True)  # type: ignore[arg-type]
        t.start()
        self._threads.append(t)

    def _ensure_stepper(self) -> None:
        if self._period is None or any(t.name == f"{self.name}-step" for t in self._threads):
            return
        with self.lock:
            self.device.start_clock(self.clock.now())
        self._spawn(self._step_loop, f"{self.name}-step")

    def _step_loop(self) -> None:
        assert self._period is not None
        nxt = self.clock.now()
        while not self._stop.is_set():
            with self.lock:
                out = self.device.step(self.clock.now())
            if out:
                self.emit(out)
            nxt += self._period
            if nxt < self.clock.now():
                nxt = self.clock.now()
            self.clock.sleep_until(nxt)

    def _handle(self, data: bytes) -> bytes:
        if self.paused:
            return b""
        with self.lock:
            return self.device.receive(data, self.clock.now())

    def _accept_loop(self) -> None:
        assert self._listener is not None
        while not self._stop.is_set():
            try:
                conn, peer = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(0.1)
            self._conn = conn
            log.info("%s: master connected from %s:%d", self.name, *peer)
            try:
                while not self._stop.is_set():
                    try:
                        data = conn.recv(4096)
                    except TimeoutError:
                        continue
                    if not data:
                        break
                    # Handle and send under the write lock, so bytes the device streams on its
                    # own (a lidar's nodes) can never overtake the reply that started them.
                    with self._write_lock:
                        reply = self._handle(data)
                        if reply:
                            conn.sendall(reply)
            except OSError:
                pass
            finally:
                _close(conn)
                self._conn = None
                log.info("%s: master disconnected", self.name)

    def _pty_loop(self) -> None:
        assert self._pty_fds is not None
        master = self._pty_fds[0]
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([master], [], [], 0.1)
                if not ready:
                    continue
                data = os.read(master, 4096)
            except OSError:
                # No reader on the slave side yet (EIO), or closed: keep serving.
                if self._stop.wait(0.05):
                    return
                continue
            with self._write_lock:
                reply = self._handle(data)
                if reply:
                    with contextlib.suppress(OSError):
                        os.write(master, reply)


def _close(sock: socket.socket) -> None:
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)
    sock.close()
