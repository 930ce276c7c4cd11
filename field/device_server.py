"""Serve a simulated serial device (control board, lidar) on TCP or a pty, in real time.

A master reaches the device through real bytes, exactly as it would reach hardware on
``/dev/ttyUSB0``. Each TCP connection (one at a time, like a UART) or the pty has a reader thread
that feeds the device and writes its replies. Unless the owner steps the device itself (the field
steps all its devices from one physics loop and passes ``step_hz=None``), a stepper thread advances
it; bytes a device emits on its own (a lidar's measurement stream) go out as they are produced.
``stop()`` closes everything; a new server on the same port models a device that restarts.

Many devices in one process (the real-time field serves 50 boards) can share one ``Reactor``:
a single selector thread accepts and serves every TCP connection instead of a thread per device,
so a request costs one wake-up of one thread rather than a thread switch (and a fight for the
GIL) among dozens. Behaviour on the wire is the same: one master at a time per device (the
listener is not watched while a master is connected), replies written before the next request
is read, a paused device silent.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import selectors
import socket
import threading
import tty
from collections.abc import Callable
from typing import Protocol

from fleetlink.shared.clock import Clock
from fleetlink.shared.worker import Worker

log = logging.getLogger(__name__)

__all__ = ["DeviceServer", "Reactor", "SimDevice"]


class SimDevice(Protocol):
    """A sans-I/O device: bytes in, bytes out, time passed in."""

    def receive(self, data: bytes, now: float) -> bytes: ...

    def step(self, now: float) -> bytes | None: ...

    def start_clock(self, now: float) -> None: ...


class Reactor:
    """One selector thread serving the TCP sockets of many ``DeviceServer``s."""

    def __init__(self, name: str = "device-reactor") -> None:
        self._sel = selectors.DefaultSelector()
        self._lock = threading.Lock()  # guards register/unregister against the loop's select
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._closing = False
        self._worker = Worker(name, target=self._run).start()

    def register(self, sock: socket.socket, callback: Callable[[], None]) -> None:
        with self._lock:
            self._sel.register(sock, selectors.EVENT_READ, callback)
        self._wake()

    def unregister(self, sock: socket.socket) -> None:
        with self._lock, contextlib.suppress(KeyError, ValueError, OSError):
            self._sel.unregister(sock)
        self._wake()

    def stop(self) -> None:
        self._closing = True  # seen by the loop as soon as the wake-up below ends its select
        self._wake()
        self._worker.stop(2.0)
        self._sel.close()
        self._wake_r.close()
        self._wake_w.close()

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            self._wake_w.send(b"\0")

    def _run(self, worker: Worker) -> None:
        while not (self._closing or worker.stopping):
            with self._lock:
                pass  # let a pending register/unregister in before blocking
            try:
                events = self._sel.select(1.0)
            except (OSError, ValueError):
                if self._closing:
                    return
                continue
            for key, _ in events:
                if key.data is None:
                    with contextlib.suppress(OSError):
                        self._wake_r.recv(4096)
                    continue
                try:
                    key.data()
                except Exception:  # one device's bug must not stop every other device
                    log.exception("device reactor callback failed")


class DeviceServer:
    def __init__(
        self,
        device: SimDevice,
        clock: Clock,
        step_hz: float | None = 200.0,
        lock: threading.Lock | None = None,
        name: str = "device",
        reactor: Reactor | None = None,
    ) -> None:
        self.device = device
        self.reactor = reactor
        self.clock = clock
        self.lock = lock or threading.Lock()
        self.name = name
        self._period = 1.0 / step_hz if step_hz else None
        self._write_lock = threading.Lock()
        self._stop = threading.Event()  # closing: every loop and reactor callback sees it at once
        self._workers: list[Worker] = []
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
        if self.reactor is not None:
            ls.setblocking(False)
            self.reactor.register(ls, self._on_accept)
        else:
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
        if self.reactor is not None:
            if self._listener is not None:
                self.reactor.unregister(self._listener)
            if self._conn is not None:
                self.reactor.unregister(self._conn)
        if self._conn is not None:
            _close(self._conn)
        for w in self._workers:
            w.stop(2.0)
        self._workers.clear()
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

    def _spawn(self, target: Callable[[Worker], None], name: str, clock: Clock | None = None) -> None:
        """A worker; ``clock`` None: real time (waits for bytes and retries are real-time waits)."""
        self._workers.append(Worker(name, clock=clock, target=target).start())

    def _ensure_stepper(self) -> None:
        if self._period is None or any(w.name == f"{self.name}-step" for w in self._workers):
            return
        with self.lock:
            self.device.start_clock(self.clock.now())
        self._spawn(self._step_loop, f"{self.name}-step", self.clock)

    def _step_loop(self, worker: Worker) -> None:
        assert self._period is not None
        nxt = self.clock.now()
        while not self._stop.is_set():
            with self.lock:
                out = self.device.step(self.clock.now())
            if out:
                self.emit(out)
            nxt += self._period
            now = self.clock.now()
            if nxt < now:
                nxt = now
            worker.wait(nxt - now)

    def _handle(self, data: bytes) -> bytes:
        if self.paused:
            return b""
        with self.lock:
            return self.device.receive(data, self.clock.now())

    def _accept_loop(self, _worker: Worker) -> None:
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

    # -- on a shared reactor (its thread) ----------------------------------------------------

    def _on_accept(self) -> None:
        assert self._listener is not None and self.reactor is not None
        try:
            conn, peer = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self.reactor.unregister(self._listener)
            return
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.settimeout(1.0)  # reads only when ready; a reply write never blocks the reactor long
        self._conn = conn
        log.info("%s: master connected from %s:%d", self.name, *peer)
        self.reactor.unregister(self._listener)  # one master at a time, like a UART
        self.reactor.register(conn, self._on_readable)

    def _on_readable(self) -> None:
        conn, reactor = self._conn, self.reactor
        if conn is None or reactor is None:
            return
        try:
            data = conn.recv(4096)
            if data:
                with self._write_lock:
                    reply = self._handle(data)
                    if reply:
                        conn.sendall(reply)
                return
        except (BlockingIOError, InterruptedError, TimeoutError):
            return
        except OSError:
            pass
        # Closed by the master (or broken): forget it, listen for the next one.
        reactor.unregister(conn)
        _close(conn)
        self._conn = None
        log.info("%s: master disconnected", self.name)
        if not self._stop.is_set() and self._listener is not None:
            reactor.register(self._listener, self._on_accept)

    def _pty_loop(self, worker: Worker) -> None:
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
                worker.wait(0.05)
                if self._stop.is_set():
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
