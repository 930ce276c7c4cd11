"""A secured site's credentials, broker and router: deploy/'s Mosquitto and Zenoh router, run for real.

``SiteSecurity(robots, operators).start()`` makes, in a private folder (mode 0700):

* a password per user (robots by id, operators ``op-<name>``, ``uwb-gateway``, ``sim``), each in
  ``secrets/<user>.password`` (0600), the same password on both links;
* the Mosquitto password file (made by the real ``mosquitto_passwd -b``) and the ACL from
  ``shared/access.py``; a broker (``brokers.MosquittoBroker``) on ``deploy/mosquitto.conf``
  (``mosquitto-tls.conf`` with TLS) with only its ports and paths rewritten;
* the Zenoh user dictionary and a router session on ``deploy/zenohd.json5`` with the same
  rewrites and an ``access_control`` generated for these robots and operators (``simulator``:
  user ``sim`` may publish ground truth) (``zenoh_router_config``);
* with ``tls`` (default: when openssl is installed) a throwaway site CA and a certificate for
  ``localhost``/127.0.0.1 (``make_site_ca``), used by both the broker and the router.

``mqtt_settings(user)`` and ``zenoh_auth(user)`` give what a client of either link needs to log
in. The tests' deploy harness (tests/harness/deploy.py) uses the same functions, so the field and
the tests run one implementation.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import subprocess
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleetlink.shared.access import (
    GATEWAY_USER,
    SIM_USER,
    check_operator_username,
    check_robot_username,
    mosquitto_acl,
    zenoh_access_control,
)
from fleetlink.shared.mqtt import MqttSettings
from fleetlink.site.brokers import DEPLOY, BrokerSecurity, MosquittoBroker, SiteError, free_port, which_mosquitto

__all__ = [
    "SiteCA",
    "SiteSecurity",
    "make_site_ca",
    "missing_tools",
    "mosquitto_passwd",
    "private_file",
    "zenoh_router_config",
]


@dataclass(frozen=True)
class SiteCA:
    """A CA and one server certificate for ``localhost`` / 127.0.0.1, made with openssl."""

    ca_crt: Path
    server_crt: Path
    server_key: Path


def which_mosquitto_passwd() -> str | None:
    found = shutil.which("mosquitto_passwd")
    if found:
        return found
    return "/usr/bin/mosquitto_passwd" if os.access("/usr/bin/mosquitto_passwd", os.X_OK) else None


def missing_tools() -> list[str]:
    """What a secured site needs and this machine lacks (empty: all there)."""
    missing = []
    if which_mosquitto() is None:
        missing.append("mosquitto")
    if which_mosquitto_passwd() is None:
        missing.append("mosquitto_passwd")
    if not (DEPLOY / "mosquitto.conf").is_file() or not (DEPLOY / "zenohd.json5").is_file():
        missing.append(f"deploy/ configurations (looked in {DEPLOY})")
    return missing


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


def private_file(path: Path, text: str = "") -> Path:
    """Write ``text`` to a file only its owner may read (0600), replacing any earlier one."""
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    return path


def mosquitto_passwd(path: Path, users: Mapping[str, str]) -> Path:
    """A Mosquitto password file (0600) made by the real mosquitto_passwd (``-b``)."""
    tool = which_mosquitto_passwd()
    if tool is None:
        raise SiteError("mosquitto_passwd not found (the Debian package mosquitto)")
    private_file(path)
    for user, password in users.items():
        subprocess.run([tool, "-b", str(path), user, password], check=True, capture_output=True, timeout=30)
    return path


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


class SiteSecurity:
    """Broker + router + credentials for ``robots`` and ``operators``, in a private folder."""

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
        self.folder.mkdir(parents=True, exist_ok=True)
        self.folder.chmod(0o700)
        users = [*self.robots, *self.operators, GATEWAY_USER, SIM_USER]
        self.passwords: dict[str, str] = {u: secrets.token_urlsafe(18) for u in users}
        self.ca: SiteCA | None = None
        self.broker: MosquittoBroker | None = None
        self.router: Any = None
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
        if self.broker is None:
            raise SiteError("the secured site is not started")
        return self.broker.url

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
        # With TLS, clients dial the name on the router's certificate.
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

    def start(self) -> SiteSecurity:
        import zenoh

        missing = missing_tools()
        if missing:
            raise SiteError("a secured site needs " + ", ".join(missing))
        try:
            self.secrets_dir.mkdir(mode=0o700, exist_ok=True)
            for user, password in self.passwords.items():
                private_file(self.password_file(user), password + "\n")
            passwd = mosquitto_passwd(self.folder / "mosquitto.passwd", self.passwords)
            acl = self.folder / "mosquitto.acl"
            acl.write_text(mosquitto_acl(self.operators, self.robots))
            users = private_file(
                self.folder / "zenoh-users.txt", "".join(f"{u}:{p}\n" for u, p in self.passwords.items())
            )
            if self.tls:
                self.ca = make_site_ca(self.folder / "tls")
            self.broker = MosquittoBroker(
                self.folder / "broker",
                host=self.host,
                security=BrokerSecurity(passwd=passwd, acl=acl, ca=self.ca),
                die_with_parent=True,  # a killed field must not leave the broker running
            ).start()
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
        if self.broker is not None:
            self.broker.stop()
        if self._own_folder:
            shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> SiteSecurity:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def describe(self) -> list[str]:
        """Where the credentials are and how a second console joins (printed by ``fleetlink field``)."""
        op = self.operators[0]
        tls = f" --ca-file {self.ca_file}" if self.ca_file else ""
        return [
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
