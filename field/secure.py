"""A secured site for the simulated field: deploy/'s Mosquitto and Zenoh router, run for real.

``SecureSite(robots, operators).start()`` makes, in a private temporary folder (mode 0700):

* a password per user (robots by id, operators ``op-<name>``, ``uwb-gateway``, ``sim``), each in
  ``secrets/<user>.password`` (0600), the same password on both links;
* the Mosquitto password file (made by the real ``mosquitto_passwd -b``) and the ACL from
  ``shared/access.py``; a broker on ``deploy/mosquitto.conf`` (``mosquitto-tls.conf`` with TLS)
  with only its ports and paths rewritten (``mosquitto_conf``);
* the Zenoh user dictionary and a router session on ``deploy/zenohd.json5`` with the same
  rewrites and an ``access_control`` generated for these robots and operators (``simulator``:
  user ``sim`` may publish ground truth) (``zenoh_router_config``);
* with ``tls`` (default: when openssl is installed) a throwaway site CA and a certificate for
  ``localhost``/127.0.0.1 (``make_site_ca``), used by both the broker and the router.

``mqtt_settings(user)`` and ``zenoh_auth(user)`` give what a client of either link needs to log
in. The tests' deploy harness (tests/harness/deploy.py) uses the same functions, so the field and
the tests run one implementation. ``SecureField`` puts the field's agents, UWB gateway and ground
truth on such a site, each logged in as itself.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import pwd
import re
import secrets
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleetlink.shared.access import GATEWAY_USER, SIM_USER, check_operator_username, check_robot_username
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.mqtt import MqttSettings

log = logging.getLogger(__name__)

__all__ = [
    "DEPLOY",
    "SecureField",
    "SecureSite",
    "SiteCA",
    "SiteError",
    "make_site_ca",
    "missing_tools",
    "mosquitto_conf",
    "mosquitto_passwd",
    "zenoh_router_config",
]

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"


class SiteError(RuntimeError):
    """The secured site cannot start (a tool missing, the broker refusing its configuration)."""


@dataclass(frozen=True)
class SiteCA:
    """A CA and one server certificate for ``localhost`` / 127.0.0.1, made with openssl."""

    ca_crt: Path
    server_crt: Path
    server_key: Path


def find_mosquitto() -> str | None:
    found = shutil.which("mosquitto")
    if found:
        return found
    return "/usr/sbin/mosquitto" if os.access("/usr/sbin/mosquitto", os.X_OK) else None


def find_mosquitto_passwd() -> str | None:
    found = shutil.which("mosquitto_passwd")
    if found:
        return found
    return "/usr/bin/mosquitto_passwd" if os.access("/usr/bin/mosquitto_passwd", os.X_OK) else None


def missing_tools() -> list[str]:
    """What a secured site needs and this machine lacks (empty: all there)."""
    missing = []
    if find_mosquitto() is None:
        missing.append("mosquitto")
    if find_mosquitto_passwd() is None:
        missing.append("mosquitto_passwd")
    if not (DEPLOY / "mosquitto.conf").is_file() or not (DEPLOY / "zenohd.json5").is_file():
        missing.append(f"deploy/ configurations (looked in {DEPLOY})")
    return missing


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def make_site_ca(folder: Path) -> SiteCA:
    openssl = shutil.which("openssl")
    if openssl is None:
        raise SiteError("openssl not found (the Debian package openssl)")
    folder.mkdir(parents=True, exist_ok=True)
    ca_key, ca_crt = folder / "ca.key", folder / "ca.crt"
    key, csr, crt, ext = folder / "server.key", folder / "server.csr", folder / "server.crt", folder / "server.ext"

    def run(*args: str) -> None:
        subprocess.run([openssl, *args], check=True, capture_output=True, timeout=60)

    run(
        "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "2",
        "-subj", "/CN=fleetlink test CA", "-keyout", str(ca_key), "-out", str(ca_crt),
    )  # fmt: skip
    run(
        "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
        "-subj", "/CN=localhost", "-keyout", str(key), "-out", str(csr),
    )  # fmt: skip
    ext.write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n")
    run(
        "x509", "-req", "-in", str(csr), "-CA", str(ca_crt), "-CAkey", str(ca_key), "-CAcreateserial",
        "-days", "2", "-extfile", str(ext), "-out", str(crt),
    )  # fmt: skip
    return SiteCA(ca_crt, crt, key)


def _private_file(path: Path, text: str = "") -> Path:
    """Write ``text`` to a file only its owner may read (0600), replacing any earlier one."""
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    return path


def mosquitto_passwd(path: Path, users: Mapping[str, str]) -> Path:
    """A Mosquitto password file (0600) made by the real mosquitto_passwd (``-b``)."""
    tool = find_mosquitto_passwd()
    if tool is None:
        raise SiteError("mosquitto_passwd not found (the Debian package mosquitto)")
    _private_file(path)
    for user, password in users.items():
        subprocess.run([tool, "-b", str(path), user, password], check=True, capture_output=True, timeout=30)
    return path


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
    user = pwd.getpwuid(os.geteuid()).pw_name
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
    # Started as root, mosquitto would drop to the user "mosquitto", who cannot read private files.
    return f"user {user}\n{text}"


def zenoh_router_config(
    users_file: Path,
    listen: str,
    *,
    ca: SiteCA | None = None,
    path: Path = DEPLOY / "zenohd.json5",
    access_control: Mapping[str, Any] | None = None,
) -> Any:
    """deploy/zenohd.json5 as a session config, with the listen endpoint, user file and TLS paths
    swapped (and ``access_control`` replaced when given: the site's own robots and operators)."""
    import zenoh

    conf = zenoh.Config.from_file(str(path))
    conf.insert_json5("listen/endpoints", json.dumps([listen]))
    conf.insert_json5("connect/endpoints", "[]")
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users_file)))
    if ca is not None:
        conf.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(ca.server_crt)))
        conf.insert_json5("transport/link/tls/listen_private_key", json.dumps(str(ca.server_key)))
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(ca.ca_crt)))
    if access_control is not None:
        conf.insert_json5("access_control", json.dumps(dict(access_control)))
    return conf


def _die_with_parent() -> None:
    """In the child before exec: ask Linux to SIGTERM it when its parent dies (no-op elsewhere)."""
    import ctypes
    import signal

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class _Broker:
    """One mosquitto process on a rewritten deploy/ configuration."""

    def __init__(self, workdir: Path, conf_text: str, host: str, port: int) -> None:
        self.workdir, self.host, self.port = workdir, host, port
        workdir.mkdir(parents=True, exist_ok=True)
        self.conf_path = workdir / "mosquitto.conf"
        self.conf_path.write_text(conf_text)
        self.log_path = workdir / "mosquitto.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 10.0) -> None:
        binary = find_mosquitto()
        if binary is None:
            raise SiteError("mosquitto not found")
        with (self.workdir / "mosquitto.stderr").open("ab") as err:
            self.proc = subprocess.Popen(
                [binary, "-c", str(self.conf_path)],
                stdin=subprocess.DEVNULL,
                stdout=err,
                stderr=err,
                cwd=self.workdir,
                preexec_fn=_die_with_parent,  # a killed field must not leave the broker running
            )
        clock = SystemClock()  # waiting for a real process: real time
        deadline = clock.now() + timeout
        while True:
            if self.proc.poll() is not None:
                code, self.proc = self.proc.returncode, None
                raise SiteError(f"mosquitto exited with code {code}: see {self.workdir}/mosquitto.stderr")
            try:
                with socket.create_connection((self.host, self.port), timeout=0.2):
                    return
            except OSError:
                if clock.now() > deadline:
                    self.stop()
                    raise SiteError(
                        f"mosquitto did not listen on {self.host}:{self.port} within {timeout:.0f} s"
                    ) from None
                clock.sleep(0.02)

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


class SecureSite:
    """Broker + router + credentials for ``robots`` and ``operators``, in a private temp folder."""

    def __init__(
        self,
        robots: Iterable[str],
        operators: Sequence[str],
        *,
        tls: bool | None = None,
        host: str = "127.0.0.1",
        folder: Path | None = None,
    ) -> None:
        self.robots = tuple(check_robot_username(r) for r in robots)
        self.operators = tuple(check_operator_username(o) for o in operators)
        if not self.operators:
            raise ValueError("a secured site needs at least one operator")
        self.tls = shutil.which("openssl") is not None if tls is None else tls
        self.host = host
        self._own_folder = folder is None
        self.folder = Path(tempfile.mkdtemp(prefix="fleetlink-secure-")) if folder is None else folder
        self.folder.chmod(0o700)
        users = [*self.robots, *self.operators, GATEWAY_USER, SIM_USER]
        self.passwords: dict[str, str] = {u: secrets.token_urlsafe(18) for u in users}
        self.ca: SiteCA | None = None
        self._broker: _Broker | None = None
        self.router: Any = None
        self.mqtt_port = 0
        self.zenoh_port = 0

    # -- what clients need ------------------------------------------------------------------------

    @property
    def secrets_dir(self) -> Path:
        return self.folder / "secrets"

    def password_file(self, user: str) -> Path:
        return self.secrets_dir / f"{user}.password"

    @property
    def ca_file(self) -> str | None:
        return str(self.ca.ca_crt) if self.ca is not None else None

    @property
    def mqtt_url(self) -> str:
        # With TLS, clients dial the name on the broker's certificate.
        return f"mqtts://localhost:{self.mqtt_port}" if self.tls else f"mqtt://{self.host}:{self.mqtt_port}"

    def mqtt_settings(self, user: str | None = None) -> MqttSettings:
        """How ``user`` logs in to the broker (``None``: no credentials, only the address and CA)."""
        return MqttSettings.from_url(
            self.mqtt_url,
            username=user,
            password=self.passwords[user] if user is not None else None,
            ca_file=self.ca_file,
        )

    @property
    def zenoh_endpoint(self) -> str:
        return f"tls/localhost:{self.zenoh_port}" if self.tls else f"tcp/{self.host}:{self.zenoh_port}"

    def zenoh_auth(self, user: str) -> dict[str, Any]:
        """``peer_config`` keyword arguments for ``user``: a client of the site's router."""
        return {
            "connect": [self.zenoh_endpoint],
            "mode": "client",
            "username": user,
            "password": self.passwords[user],
            "root_ca": self.ca_file,
        }

    # -- life cycle -------------------------------------------------------------------------------

    def start(self) -> SecureSite:
        import zenoh

        from fleetlink.shared.access import mosquitto_acl, zenoh_access_control

        missing = missing_tools()
        if missing:
            raise SiteError("a secured site needs " + ", ".join(missing))
        self.secrets_dir.mkdir(mode=0o700, exist_ok=True)
        for user, password in self.passwords.items():
            _private_file(self.password_file(user), password + "\n")
        passwd = mosquitto_passwd(self.folder / "mosquitto.passwd", self.passwords)
        acl = self.folder / "mosquitto.acl"
        acl.write_text(mosquitto_acl(self.operators))
        users = _private_file(self.folder / "zenoh-users.txt", "".join(f"{u}:{p}\n" for u, p in self.passwords.items()))
        if self.tls:
            self.ca = make_site_ca(self.folder / "tls")
        try:
            plain, tls_port = free_port(self.host), free_port(self.host)
            self.mqtt_port = tls_port if self.tls else plain
            workdir = self.folder / "broker"
            workdir.mkdir(exist_ok=True)
            conf = "mosquitto-tls.conf" if self.tls else "mosquitto.conf"
            text = mosquitto_conf(
                (DEPLOY / conf).read_text(),
                host=self.host,
                port=plain,
                tls_port=tls_port,
                passwd=passwd,
                acl=acl,
                workdir=workdir,
                log_path=workdir / "mosquitto.log",
                ca=self.ca,
            )
            self._broker = _Broker(workdir, text, self.host, self.mqtt_port)
            self._broker.start()
            self.zenoh_port = free_port(self.host)
            scheme = "tls" if self.tls else "tcp"
            access = zenoh_access_control(self.robots, self.operators, simulator=True)
            self.router = zenoh.open(
                zenoh_router_config(users, f"{scheme}/{self.host}:{self.zenoh_port}", ca=self.ca, access_control=access)
            )
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        """Close the router, stop the broker, delete the folder (if this site made it)."""
        if self.router is not None:
            with contextlib.suppress(Exception):
                self.router.close()
            self.router = None
        if self._broker is not None:
            self._broker.stop()
            self._broker = None
        if self._own_folder:
            shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> SecureSite:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def describe(self) -> list[str]:
        """Where the credentials are and how a second console joins (printed by ``fleetlink field``)."""
        op = self.operators[0]
        tls = f" --ca-file {self.ca_file}" if self.ca_file else ""
        lines = [
            f"secured site: credentials in {self.secrets_dir} (one <user>.password per user, both links)",
            f"  MQTT {self.mqtt_url} (deploy/{'mosquitto-tls.conf' if self.tls else 'mosquitto.conf'}, "
            f"ACL {self.folder / 'mosquitto.acl'})",
            f"  Zenoh router {self.zenoh_endpoint} (deploy/zenohd.json5: usrpwd, access control, default deny)",
            f"  users: robots {', '.join(self.robots)}; operators {', '.join(self.operators)}; "
            f"{GATEWAY_USER}; {SIM_USER}",
            "  another console joins with:",
            f"    fleetlink console --user {op} --password-file {self.password_file(op)} "
            f"--zenoh-connect {self.zenoh_endpoint} --mqtt {self.mqtt_url}{tls}",
        ]
        return lines


class SecureField:
    """The field's agents, UWB gateway and ground truth on a ``SecureSite``, each logged in as itself.

    Agents log in as their robot ids and accept commands only from the site's operators; the UWB
    gateway logs in as ``uwb-gateway`` (fed in-process from the field's truth sink, fixes out on
    MQTT); ground truth goes to the router as ``sim``. ``truth_sink`` is the field's sink.
    """

    def __init__(
        self,
        site: SecureSite,
        endpoints: Mapping[str, Any],
        clock: Any,
        *,
        scenario: Any = None,
        plan: Any = None,
        rates: Any = None,
    ) -> None:
        self.site, self.endpoints, self.clock = site, endpoints, clock
        self.scenario, self.plan, self.rates = scenario, plan, rates
        self.agents: Any = None
        self.gateway: Any = None
        self.truth: Any = None

    def start(self) -> SecureField:
        import zenoh

        from fleetlink.field.agents import FieldAgents
        from fleetlink.shared.zenoh_config import peer_config

        site = self.site
        try:
            self.truth = _RoutedTruth(zenoh.open(peer_config(**site.zenoh_auth(SIM_USER))), self.clock)
            if self.scenario is not None and self.plan is not None:
                self.gateway = _gateway(self.scenario, self.plan, site.mqtt_settings(GATEWAY_USER), self.clock)
                if self.gateway is not None:
                    self.gateway.start()
            self.agents = FieldAgents(
                self.endpoints,
                clock=self.clock,
                zenoh_connect=[site.zenoh_endpoint],
                zenoh_mode="client",
                zenoh_passwords={r: site.passwords[r] for r in self.endpoints},
                zenoh_root_ca=site.ca_file,
                mqtt=site.mqtt_settings(),
                mqtt_passwords={r: site.passwords[r] for r in self.endpoints},
                operators=site.operators,
                rates=self.rates,
            )
            self.agents.start()
        except BaseException:
            self.stop()
            raise
        return self

    def truth_sink(self, sample: Any) -> None:
        if self.truth is not None:
            self.truth.publish(sample)
        if self.gateway is not None:
            self.gateway.on_truth_sample(sample)

    def operator_link(self, operator: str | None = None) -> Any:
        """An ``OperatorLink`` (not started) logged in to both links as ``operator``."""
        return open_operator_link(self.site, operator or self.site.operators[0], self.clock)

    def stop(self) -> None:
        if self.agents is not None:
            self.agents.stop()
            self.agents = None
        if self.gateway is not None:
            self.gateway.stop()
            self.gateway = None
        if self.truth is not None:
            self.truth.close()
            self.truth = None

    def __enter__(self) -> SecureField:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def open_operator_link(site: SecureSite, operator: str, clock: Any) -> Any:
    """The console's ``OperatorLink`` (not started), logged in as ``operator`` on both links."""
    from fleetlink.operator.links import MqttTransport, OperatorLink, ZenohTransport

    auth = site.zenoh_auth(operator)
    primary = ZenohTransport.open((), auth.pop("connect"), **auth)
    try:
        fallback = MqttTransport(site.mqtt_url, client_id=operator, settings=site.mqtt_settings(operator))
    except BaseException:
        primary.close()
        raise
    return OperatorLink(clock, operator, primary, fallback)


class _RoutedTruth:
    """Ground truth as ``sim``. ``session.put`` per sample: behind a router, a publisher declared
    before the subscriber appears would drop every sample (docs/operations.md section 3)."""

    def __init__(self, session: Any, clock: Any) -> None:
        from fleetlink.field.truth import TruthPublisher

        self.session = session
        self._encoder = TruthPublisher(_PutOnly(session), clock)  # its encoding, our puts

    def publish(self, sample: Any) -> None:
        self._encoder.publish(sample)

    def close(self) -> None:
        self._encoder.close()
        self.session.close()


class _PutOnly:
    """Stands in for a session: ``declare_publisher`` gives a putter that puts on the session."""

    def __init__(self, session: Any) -> None:
        self._session = session

    def declare_publisher(self, key: str) -> Any:
        return _Putter(self._session, key)


@dataclass(frozen=True)
class _Putter:
    session: Any
    key: str

    def put(self, payload: bytes) -> None:
        self.session.put(self.key, payload)

    def undeclare(self) -> None:
        pass


def _gateway(scenario: Any, plan: Any, mqtt: MqttSettings, clock: Any) -> Any:
    """The UWB simulator for the field (as cli/console.py's field_gateway), logged in as uwb-gateway."""
    from fleetlink.positioning.anchors import Anchor
    from fleetlink.positioning.config import GatewayConfig
    from fleetlink.positioning.publisher import UwbGateway

    anchors = tuple(Anchor(*a) for a in scenario.anchors) or tuple(Anchor(a.id, a.x, a.y, a.z) for a in plan.anchors)
    if len(anchors) < 3:
        return None
    config = GatewayConfig(anchors=anchors, auto_tags=True, walls=plan.segments(), mqtt=mqtt, gateway_id="field-uwb")
    return UwbGateway(config, clock, subscribe_truth=False)
