"""MQTT connection settings. Pure: parsing only (the client is made in fleetlink.links.mqtt).

Every fleetlink process that speaks MQTT (agent, UWB gateway, console, field) reads a ``[mqtt]``
table into ``MqttSettings`` and opens its endpoint with ``links.mqtt.MqttEndpoint`` (or a bare
client with ``links.mqtt.connect_client``), so credentials, TLS, TCP_NODELAY and the reconnect
backoff are the same everywhere::

    [mqtt]
    url = "mqtts://broker.site-a.example:8883"   # mqtt://host[:1883] or mqtts://host[:8883]
    username = "r1"                              # agents: the robot id; operators: op-<name>
    password_file = "/etc/fleetlink/secrets/mqtt-password"   # or password = "..." (not both)
    ca_file = "/etc/fleetlink/tls/ca.crt"        # mqtts: the site CA (default: the system's CAs)
    cert_file = "/etc/fleetlink/tls/r1.crt"      # optional client certificate (mutual TLS) ...
    key_file = "/etc/fleetlink/tls/r1.key"       # ... and its key (both or neither)
    client_id = "agent-r1"                       # optional; default: given by the program
    keepalive_s = 5                              # broker declares the client dead after 1.5x
    reconnect_min_s = 0.5                        # reconnect backoff, doubling up to ...
    reconnect_max_s = 10                         # ... this (each client jitters both)

``MqttSettings.from_table`` reads the password file at load time so a missing or empty file is
reported with the configuration's other errors, not on the first reconnect.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from fleetlink.shared.config import ConfigError, TomlReader

__all__ = ["ConfigError", "MqttSettings", "parse_url"]

DEFAULT_PORTS = {"mqtt": 1883, "mqtts": 8883}
KEYS = (
    "url",
    "username",
    "password",
    "password_file",
    "ca_file",
    "cert_file",
    "key_file",
    "client_id",
    "keepalive_s",
    "reconnect_min_s",
    "reconnect_max_s",
)


@dataclass(frozen=True, slots=True)
class MqttSettings:
    host: str
    port: int
    tls: bool = False
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    client_id: str | None = None
    keepalive_s: int = 5
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 10.0

    @property
    def url(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"

    @classmethod
    def from_url(cls, url: str, **kw: Any) -> MqttSettings:
        """Settings for ``url`` (mqtt://host:port or mqtts://host:port) with ``kw`` as the other fields."""
        host, port, tls = parse_url(url, TomlReader("url"), "url")
        return cls(host=host, port=port, tls=tls, **kw)

    @classmethod
    def from_table(
        cls, table: object, *, source: str = "config", where: str = "mqtt", base_dir: str | Path | None = None
    ) -> MqttSettings:
        """Parse a ``[mqtt]`` TOML table; ``ConfigError`` naming ``source``, the key and the problem.

        Relative file paths are taken relative to ``base_dir`` (the configuration file's folder).
        """
        r = TomlReader(source)
        if not isinstance(table, dict):
            raise r.fail(where, f"expected a table ([{where}]), got {type(table).__name__}")
        r.keys(table, where, KEYS, required=("url",))
        host, port, tls = parse_url(r.text(table["url"], f"{where}.url", nonempty=True), r, f"{where}.url")

        def opt_text(k: str) -> str | None:
            return r.text(table[k], f"{where}.{k}", nonempty=True) if k in table else None

        def opt_path(k: str) -> str | None:
            v = opt_text(k)
            if v is None:
                return None
            p = Path(v)
            if not p.is_absolute() and base_dir is not None:
                p = Path(base_dir) / p
            if not p.is_file():
                raise r.fail(f"{where}.{k}", f"no such file {str(p)!r}")
            return str(p)

        username = opt_text("username")
        password = opt_text("password")
        password_file = opt_path("password_file")
        if password is not None and password_file is not None:
            raise r.fail(where, "give password or password_file, not both")
        if password_file is not None:
            try:
                password = Path(password_file).read_text(encoding="utf-8").strip("\r\n")
            except (OSError, UnicodeDecodeError) as exc:
                raise r.fail(f"{where}.password_file", f"cannot read {password_file!r}: {exc}") from exc
            if not password:
                raise r.fail(f"{where}.password_file", f"{password_file!r} is empty")
        if password is not None and username is None:
            raise r.fail(where, "a password needs a username")
        ca_file, cert_file, key_file = opt_path("ca_file"), opt_path("cert_file"), opt_path("key_file")
        if not tls and (ca_file or cert_file or key_file):
            raise r.fail(where, "ca_file, cert_file and key_file need an mqtts:// url")
        if (cert_file is None) != (key_file is None):
            raise r.fail(where, "cert_file and key_file go together (both or neither)")
        keepalive = r.integer(table.get("keepalive_s", 5), f"{where}.keepalive_s", 1, 3600)
        rmin = r.number(table.get("reconnect_min_s", 0.5), f"{where}.reconnect_min_s", 0.05, 600.0)
        rmax = r.number(table.get("reconnect_max_s", 10.0), f"{where}.reconnect_max_s", 0.05, 3600.0)
        if rmax < rmin:
            raise r.fail(where, f"reconnect_max_s ({rmax}) must be >= reconnect_min_s ({rmin})")
        client_id = opt_text("client_id")
        return cls(
            host=host,
            port=port,
            tls=tls,
            username=username,
            password=password,
            ca_file=ca_file,
            cert_file=cert_file,
            key_file=key_file,
            client_id=client_id,
            keepalive_s=keepalive,
            reconnect_min_s=rmin,
            reconnect_max_s=rmax,
        )


def parse_url(url: str, r: TomlReader, where: str) -> tuple[str, int, bool]:
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise r.fail(where, f"invalid url {url!r}: {exc}") from None
    if parts.scheme not in DEFAULT_PORTS:
        raise r.fail(where, f"invalid url {url!r}: scheme must be mqtt:// or mqtts://")
    if not parts.hostname:
        raise r.fail(where, f"invalid url {url!r}: no host")
    if parts.username or parts.password:
        raise r.fail(where, f"invalid url {url!r}: put credentials in username/password_file, not the url")
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise r.fail(where, f"invalid url {url!r}: expected mqtt[s]://host[:port] and nothing after")
    return parts.hostname, port if port is not None else DEFAULT_PORTS[parts.scheme], parts.scheme == "mqtts"
