"""The one MQTT broker launcher: a real ``mosquitto`` process, or the pure-Python amqtt broker.

``MosquittoBroker(workdir)`` runs mosquitto on a generated configuration in its own folder, on a
free loopback port: anonymous for the demo field, the tests and the benches; or, with
``security=BrokerSecurity(...)``, deploy/'s configuration with only its listeners and paths
rewritten (password file, ACL, TLS), as a secured site runs it. ``start()`` waits until it accepts
connections; ``stop()`` (SIGTERM), ``kill()`` (SIGKILL, for drills) and ``start()`` again on the
same port, or ``restart()``.

``AmqttBroker`` is the demo's fallback when no mosquitto binary is installed: no password file, no
ACL, so never a secured site, and never the tests' (their MQTT path must run on real mosquitto).
``start_demo_broker()`` picks between them.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pwd
import random
import re
import shutil
import signal
import socket
import subprocess
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fleetlink.shared.clock import SystemClock

if TYPE_CHECKING:
    from fleetlink.site.security import SiteCA

log = logging.getLogger(__name__)

__all__ = [
    "DEPLOY",
    "INSTALL_HINT",
    "AmqttBroker",
    "BrokerSecurity",
    "MosquittoBroker",
    "MosquittoNotFound",
    "MosquittoStartError",
    "SiteError",
    "find_mosquitto",
    "free_port",
    "mosquitto_conf",
    "start_demo_broker",
    "which_mosquitto",
]

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
FALLBACK_BINARY = "/usr/sbin/mosquitto"  # Debian's; often not on a user's PATH
INSTALL_HINT = "run `.ci/install-mosquitto` (apt-get install mosquitto) and try again"
QUIET_LOG = ("error", "warning", "notice", "information")


class SiteError(RuntimeError):
    """A part of the site cannot start (a tool missing, a broker refusing its configuration)."""


class MosquittoNotFound(SiteError):
    pass


class MosquittoStartError(SiteError):
    pass


def which_mosquitto(fallback: str = FALLBACK_BINARY) -> str | None:
    """Path of the mosquitto binary (PATH first, then ``fallback``), or None."""
    found = shutil.which("mosquitto")
    if found:
        return found
    return fallback if os.path.isfile(fallback) and os.access(fallback, os.X_OK) else None


def find_mosquitto(fallback: str = FALLBACK_BINARY) -> str:
    """Path of the mosquitto binary; ``MosquittoNotFound`` (saying how to install it) if missing."""
    found = which_mosquitto(fallback)
    if found is None:
        raise MosquittoNotFound(f"mosquitto binary not found on PATH nor at {fallback}: {INSTALL_HINT}")
    return found


EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
"""Where Linux says which ports it hands out to outgoing connections (and to a bind to port 0)."""
PORT_SPAN = 12_000
"""``free_port`` picks among this many ports just below that range."""


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (bound, released), from just below the range the OS
    hands out to outgoing connections: a port the OS picked (bind to port 0) comes from that range,
    and a connection made before the caller binds it could take it ("Address already in use": a
    test's listener, after its field's clients had connected, 2026-12-07). Picked at random there,
    so callers in other processes seldom pick the same one; where that range cannot be read, the
    OS picks."""
    try:
        low = int(EPHEMERAL_RANGE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 0
    if low - PORT_SPAN >= 1024:
        pick = random.SystemRandom()
        for _ in range(64):
            port = pick.randrange(low - PORT_SPAN, low)
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                try:
                    s.bind((host, port))
                except OSError:
                    continue
                return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _can_connect(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


def _run_as() -> str:
    # Started as root, mosquitto drops to the user "mosquitto", who can read neither our private
    # folder nor the password file; naming the current user keeps it (ignored when not root).
    return pwd.getpwuid(os.geteuid()).pw_name


def mosquitto_conf(
    deploy_text: str,
    *,
    host: str,
    port: int,
    tls_port: int,
    passwd: Path,
    acl: Path,
    workdir: Path,
    log_path: Path,
    ca: SiteCA | None = None,
) -> str:
    """A deploy/ Mosquitto configuration with only its listeners, paths and log file rewritten."""
    text = deploy_text
    text = text.replace("/etc/mosquitto/fleetlink.passwd", str(passwd))
    text = text.replace("/etc/mosquitto/fleetlink.acl", str(acl))
    text = text.replace("/var/lib/mosquitto/", f"{workdir}/")
    if ca is not None:
        text = text.replace("/etc/mosquitto/certs/ca.crt", str(ca.ca_crt))
        text = text.replace("/etc/mosquitto/certs/broker.crt", str(ca.server_crt))
        text = text.replace("/etc/mosquitto/certs/broker.key", str(ca.server_key))
    text = re.sub(r"^listener 1883.*$", f"listener {port} {host}", text, flags=re.M)
    text = re.sub(r"^listener 8883.*$", f"listener {tls_port} {host}", text, flags=re.M)
    text = re.sub(r"^log_dest .*$", f"log_dest file {log_path}", text, flags=re.M)
    return f"user {_run_as()}\n{text}"


@dataclass(frozen=True)
class BrokerSecurity:
    """A broker as a secured site runs it: deploy/'s ``template`` with these files.

    ``template`` is a file name in deploy/; by default ``mosquitto-tls.conf`` when ``ca`` is given
    (TLS listener, plus the plain one on loopback), else ``mosquitto.conf``.
    """

    passwd: Path
    acl: Path = DEPLOY / "mosquitto.acl"
    ca: SiteCA | None = None
    template: str | None = None

    @property
    def template_path(self) -> Path:
        return DEPLOY / (self.template or ("mosquitto-tls.conf" if self.ca is not None else "mosquitto.conf"))


class MosquittoBroker:
    """One mosquitto process with its own configuration, log and port in ``workdir``.

    ``start()`` after ``stop()`` or ``kill()`` reuses the same port, so clients reconnect.
    ``extra_conf`` is appended verbatim to the generated configuration. ``log_types`` are
    mosquitto's ``log_type`` lines (``("all",)`` logs every packet: the tests' diagnostics).
    ``die_with_parent``: Linux SIGTERMs the broker when the thread that started it dies, so a
    killed field leaves no broker behind (only for a broker started and restarted by one thread).
    """

    def __init__(
        self,
        workdir: Path,
        extra_conf: str = "",
        *,
        host: str = "127.0.0.1",
        port: int | None = None,
        binary: str | None = None,
        security: BrokerSecurity | None = None,
        log_types: tuple[str, ...] = QUIET_LOG,
        die_with_parent: bool = False,
    ) -> None:
        self.binary = binary or find_mosquitto()
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.host = host
        self.port = port if port is not None else free_port(host)
        self.security = security
        self.tls_port = free_port(host) if security is not None else 0
        self.extra_conf = extra_conf
        self.log_types = log_types
        self.die_with_parent = die_with_parent
        self.conf_path = self.workdir / "mosquitto.conf"
        self.log_path = self.workdir / "mosquitto.log"
        self.stderr_path = self.workdir / "mosquitto.stderr"
        self._proc: subprocess.Popen[bytes] | None = None
        self.conf_path.write_text(self.config_text())

    def config_text(self) -> str:
        if self.security is not None:
            s = self.security
            text = mosquitto_conf(
                s.template_path.read_text(),
                host=self.host,
                port=self.port,
                tls_port=self.tls_port,
                passwd=s.passwd,
                acl=s.acl,
                workdir=self.workdir,
                log_path=self.log_path,
                ca=s.ca,
            )
        else:
            lines = [
                f"user {_run_as()}",
                f"listener {self.port} {self.host}",
                "allow_anonymous true",
                "set_tcp_nodelay true",  # Nagle against delayed ACK: ~40 ms per QoS 1 message
                "max_packet_size 270000",  # as deploy/mosquitto.conf: the wire's 256 KiB plus headers
                "persistence false",
                f"log_dest file {self.log_path}",
                *(f"log_type {t}" for t in self.log_types),
                "log_timestamp true",
                "connection_messages true",
            ]
            text = "\n".join(lines) + "\n"
        if self.extra_conf:
            text += "\n# extra\n" + self.extra_conf.strip("\n") + "\n"
        return text

    @property
    def url(self) -> str:
        """Where clients connect: ``mqtts://localhost:<tls port>`` (the certificate's name) with TLS."""
        if self.security is not None and self.security.ca is not None:
            return f"mqtts://localhost:{self.tls_port}"
        return f"mqtt://{self.host}:{self.port}"

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
                preexec_fn=_die_with_parent if self.die_with_parent else None,
            )
        clock = SystemClock()  # waiting for a real process: real time
        deadline = clock.now() + timeout
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
            if clock.now() > deadline:
                self.kill()
                raise MosquittoStartError(
                    f"mosquitto did not accept connections on {self.host}:{self.port} "
                    f"within {timeout:.1f}s\n{self._diagnostics()}"
                )
            clock.sleep(0.01)

    def stop(self, timeout: float = 5.0) -> None:
        """Graceful stop: SIGTERM and wait (SIGKILL if it does not exit in ``timeout``). Idempotent."""
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

    def restart(self, timeout: float = 10.0) -> MosquittoBroker:
        """Stop gracefully and start again on the same port."""
        self.stop()
        return self.start(timeout)

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


def _die_with_parent() -> None:
    """In the child before exec: ask Linux to SIGTERM it when its parent dies (no-op elsewhere)."""
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class AmqttBroker:
    """A pure-Python MQTT broker (amqtt) on a free loopback port, in a thread of this process.

    The demo's fallback when no mosquitto binary is installed, so a fresh machine still has the
    MQTT fallback link (retained messages, QoS 1). Slower than mosquitto; anonymous only.
    """

    def __init__(self, host: str = "127.0.0.1") -> None:
        self.host = host
        self.port = 0
        self._loop: Any = None
        self._broker: Any = None
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"mqtt://{self.host}:{self.port}"

    def start(self, timeout: float = 15.0) -> AmqttBroker:
        """Start it; ``SiteError`` if amqtt is not installed or did not start."""
        import asyncio

        try:
            from amqtt.broker import Broker
        except ImportError as exc:
            raise SiteError(f"the amqtt package is not installed: {exc}") from exc
        self.port = free_port(self.host)
        config = {
            "listeners": {"default": {"type": "tcp", "bind": f"{self.host}:{self.port}"}},
            "plugins": {"amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}},
        }
        self._loop = loop = asyncio.new_event_loop()
        started = threading.Event()
        failed: list[BaseException] = []

        def run() -> None:
            asyncio.set_event_loop(loop)
            try:
                self._broker = Broker(config, loop=loop)
                loop.run_until_complete(self._broker.start())
            except BaseException as exc:  # reported by start()
                failed.append(exc)
                started.set()
                return
            started.set()
            loop.run_forever()

        self._thread = threading.Thread(target=run, name="amqtt-broker", daemon=True)
        self._thread.start()
        if not started.wait(timeout) or failed:
            self.stop()
            raise SiteError(f"the amqtt broker did not start: {failed[0] if failed else 'timeout'}")
        return self

    def stop(self) -> None:
        import asyncio

        loop, broker = self._loop, self._broker
        self._loop = self._broker = None
        if loop is None:
            return
        if broker is not None and loop.is_running():
            with contextlib.suppress(Exception):
                asyncio.run_coroutine_threadsafe(broker.shutdown(), loop).result(5.0)
        if loop.is_running():
            loop.call_soon_threadsafe(loop.stop)
        if self._thread is not None:
            self._thread.join(5.0)

    def __enter__(self) -> AmqttBroker:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start_demo_broker(workdir: Path) -> tuple[MosquittoBroker | AmqttBroker | None, str]:
    """A started broker for the demo field: mosquitto (in ``workdir``) if installed, else amqtt.

    (broker or None, what it is or why there is none). Never for tests or a secured site.
    """
    if which_mosquitto() is not None:
        broker = MosquittoBroker(workdir, die_with_parent=True)
        try:
            return broker.start(), "embedded mosquitto"
        except SiteError as exc:
            log.warning("the embedded mosquitto did not start: %s", exc)
    try:
        return AmqttBroker().start(), "embedded amqtt (no mosquitto binary)"
    except SiteError as exc:
        log.warning("%s", exc)
        return None, str(exc)
