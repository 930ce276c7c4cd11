"""A private Mosquitto broker per test.

Every broker gets its own config, log and port (127.0.0.1, found by binding port 0), so tests never
talk to the system broker on 1883 and never see each other's traffic. The broker is a real
``mosquitto`` process: if the binary is missing the fixtures FAIL (run ``.ci/install-mosquitto``);
they never skip and never fall back to an embedded broker.
"""

from __future__ import annotations

import os
import pwd
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

FALLBACK_BINARY = "/usr/sbin/mosquitto"
INSTALL_HINT = "run `.ci/install-mosquitto` (apt-get install mosquitto) and try again"


class MosquittoNotFound(RuntimeError):
    pass


class MosquittoStartError(RuntimeError):
    pass


def find_mosquitto(fallback: str = FALLBACK_BINARY) -> str:
    """Path of the mosquitto binary: PATH first, then /usr/sbin (often not on a user's PATH)."""
    found = shutil.which("mosquitto")
    if found:
        return found
    if os.path.isfile(fallback) and os.access(fallback, os.X_OK):
        return fallback
    raise MosquittoNotFound(f"mosquitto binary not found on PATH nor at {fallback}: {INSTALL_HINT}")


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (bind port 0, read it back, release it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _can_connect(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


class MosquittoBroker:
    """One mosquitto process with its own config in ``workdir``.

    ``start()`` after ``stop()`` or ``kill()`` reuses the same port, so clients can reconnect.
    ``extra_conf`` is appended verbatim to the generated config (password_file, acl_file, ...).
    """

    def __init__(
        self,
        workdir: Path,
        extra_conf: str = "",
        *,
        host: str = "127.0.0.1",
        port: int | None = None,
        binary: str | None = None,
    ) -> None:
        self.binary = binary or find_mosquitto()
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.host = host
        self.port = port if port is not None else free_port(host)
        self.extra_conf = extra_conf
        self.conf_path = self.workdir / "mosquitto.conf"
        self.log_path = self.workdir / "mosquitto.log"
        self.stderr_path = self.workdir / "mosquitto.stderr"
        self._proc: subprocess.Popen[bytes] | None = None
        self._write_conf()

    def _write_conf(self) -> None:
        # Run as root, mosquitto drops to user "mosquitto", which cannot write into a private tmp
        # dir. Naming the current user keeps it as that user (the option is ignored for non-root).
        user = pwd.getpwuid(os.geteuid()).pw_name
        lines = [
            f"user {user}",
            f"listener {self.port} {self.host}",
            "allow_anonymous true",
            "set_tcp_nodelay true",
            "persistence false",
            f"log_dest file {self.log_path}",
            "log_type all",
            "log_timestamp true",
            "connection_messages true",
        ]
        text = "\n".join(lines) + "\n"
        if self.extra_conf:
            text += "\n# extra\n" + self.extra_conf.strip("\n") + "\n"
        self.conf_path.write_text(text)

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self.running and self._proc is not None else None

    def start(self, timeout: float = 10.0) -> MosquittoBroker:
        """Start (or restart, on the same port) and wait until it accepts TCP connections."""
        if self.running:
            return self
        with self.stderr_path.open("ab") as err:
            self._proc = subprocess.Popen(
                [self.binary, "-c", str(self.conf_path)],
                stdin=subprocess.DEVNULL,
                stdout=err,
                stderr=err,
                cwd=self.workdir,
            )
        deadline = time.monotonic() + timeout
        while True:
            code = self._proc.poll()
            if code is not None:
                self._proc = None
                raise MosquittoStartError(
                    f"mosquitto exited with code {code} while starting on {self.host}:{self.port}\n"
                    f"{self._diagnostics()}"
                )
            if _can_connect(self.host, self.port):
                return self
            if time.monotonic() > deadline:
                self.kill()
                raise MosquittoStartError(
                    f"mosquitto did not accept connections on {self.host}:{self.port} "
                    f"within {timeout:.1f}s\n{self._diagnostics()}"
                )
            time.sleep(0.01)

    def stop(self, timeout: float = 5.0) -> None:
        """Graceful stop: SIGTERM and wait (SIGKILL if it does not exit in ``timeout``)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def kill(self) -> None:
        """SIGKILL, no goodbye to clients: for fault drills. ``start()`` brings it back."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
        proc.wait()

    def log_text(self) -> str:
        """The broker log (appended across restarts) followed by anything it wrote to stderr."""
        parts = []
        for path in (self.log_path, self.stderr_path):
            if path.exists():
                text = path.read_text(errors="replace")
                if text:
                    parts.append(text)
        return "".join(parts)

    def _diagnostics(self) -> str:
        return f"--- config {self.conf_path} ---\n{self.conf_path.read_text()}--- log ---\n{self.log_text()}"

    def __enter__(self) -> MosquittoBroker:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def __repr__(self) -> str:
        state = "running" if self.running else "stopped"
        return f"<MosquittoBroker {self.host}:{self.port} {state} workdir={self.workdir}>"


@pytest.fixture
def mosquitto_factory(tmp_path: Path) -> Iterator[Callable[..., MosquittoBroker]]:
    """``mosquitto_factory(extra_conf="") -> MosquittoBroker`` (started); all stopped at teardown."""
    brokers: list[MosquittoBroker] = []

    def make(extra_conf: str = "") -> MosquittoBroker:
        workdir = tmp_path / f"mosquitto-{len(brokers)}"
        try:
            broker = MosquittoBroker(workdir, extra_conf)
        except MosquittoNotFound as exc:
            pytest.fail(str(exc), pytrace=False)
        brokers.append(broker)
        try:
            broker.start()
        except MosquittoStartError as exc:
            pytest.fail(str(exc), pytrace=False)
        return broker

    try:
        yield make
    finally:
        for broker in brokers:
            broker.stop()


@pytest.fixture
def mosquitto(mosquitto_factory: Callable[..., MosquittoBroker]) -> MosquittoBroker:
    """A started private broker with the default config (anonymous, loopback, no persistence)."""
    return mosquitto_factory()
