"""A TCP relay between an agent and a simulated device: the cable, under the test's control.

``blackhole()`` stops carrying bytes both ways while keeping the sockets open (a cut wire: the
OS notices nothing); ``restore()`` carries them again; ``inject_to_agent`` / ``inject_to_device``
put bytes on the line (noise). ``unplug()`` closes every connection and refuses new ones (both
ends see the link go: a pulled USB cable, a partitioned network); ``plug()`` accepts them again.
Otherwise new connections are accepted in every state.
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading


class TcpRelay:
    def __init__(self, target_port: int, host: str = "127.0.0.1") -> None:
        self.target = (host, target_port)
        self._listener = socket.create_server((host, 0))
        self.port = int(self._listener.getsockname()[1])
        self._stop = threading.Event()
        self._carry = threading.Event()
        self._carry.set()
        self._plugged = threading.Event()
        self._plugged.set()
        self._lock = threading.Lock()
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._threads = [threading.Thread(target=self._accept, name="relay-accept", daemon=True)]
        self._threads[0].start()
        self.dropped_bytes = 0

    def blackhole(self) -> None:
        self._carry.clear()

    def restore(self) -> None:
        self._carry.set()

    def unplug(self) -> None:
        self._plugged.clear()
        with self._lock:
            pairs = list(self._pairs)
        for a, b in pairs:
            for s in (a, b):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)

    def plug(self) -> None:
        self._plugged.set()

    @property
    def connections(self) -> int:
        with self._lock:
            return len(self._pairs)

    def inject_to_agent(self, data: bytes) -> None:
        with self._lock:
            for agent_side, _ in self._pairs:
                with contextlib.suppress(OSError):
                    agent_side.sendall(data)

    def inject_to_device(self, data: bytes) -> None:
        with self._lock:
            for _, device_side in self._pairs:
                with contextlib.suppress(OSError):
                    device_side.sendall(data)

    def close(self) -> None:
        self._stop.set()
        with contextlib.suppress(OSError):
            self._listener.close()
        with self._lock:
            for a, b in self._pairs:
                for s in (a, b):
                    with contextlib.suppress(OSError):
                        s.close()
        for t in self._threads:
            t.join(2.0)

    def _accept(self) -> None:
        self._listener.settimeout(0.1)
        while not self._stop.is_set():
            try:
                agent_side, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if not self._plugged.is_set():
                agent_side.close()
                continue
            try:
                device_side = socket.create_connection(self.target, timeout=2.0)
            except OSError:
                agent_side.close()
                continue
            for s in (agent_side, device_side):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._pairs.append((agent_side, device_side))
            t = threading.Thread(target=self._pump, args=(agent_side, device_side), name="relay-pump", daemon=True)
            self._threads.append(t)
            t.start()

    def _pump(self, a: socket.socket, b: socket.socket) -> None:
        peer = {a: b, b: a}
        try:
            while not self._stop.is_set():
                ready, _, _ = select.select([a, b], [], [], 0.05)
                for s in ready:
                    data = s.recv(65536)
                    if not data:
                        return
                    if self._carry.is_set():
                        peer[s].sendall(data)
                    else:
                        self.dropped_bytes += len(data)
        except OSError:
            return
        finally:
            for s in (a, b):
                with contextlib.suppress(OSError):
                    s.close()
            with self._lock:
                if (a, b) in self._pairs:
                    self._pairs.remove((a, b))
