"""The ``[mqtt]`` and ``[zenoh]`` tables every configuration file shares, as config schemas.

The agent's robot.toml, the UWB gateway's uwb.toml and the console's file declare these tables
with ``MqttTable`` and ``ZenohTable`` (shared/config.py checks keys, types and ranges); the files
they name (passwords, CA, certificates) are then found relative to the configuration file and read
by ``mqtt_settings`` / ``zenoh_auth``, so a missing or empty one is reported with the file and key.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from fleetlink.shared.config import ConfigError, Invalid, Setting
from fleetlink.shared.mqtt import MqttSettings, parse_url
from fleetlink.shared.zenoh_config import ZenohAuth

__all__ = ["Endpoint", "MqttTable", "ZenohTable", "check_endpoint", "mqtt_settings", "zenoh_auth"]

Text = Annotated[str, Setting(min_len=1)]


def _check_mqtt_url(url: str) -> str:
    parse_url(url)  # ValueError saying what is wrong
    return url


@dataclass(frozen=True, slots=True)
class MqttTable:
    """``[mqtt]``: the broker and how to log in (docs/operations.md)."""

    url: Annotated[str, Setting(min_len=1, convert=_check_mqtt_url, doc="mqtt://host[:1883] or mqtts://host[:8883]")]
    username: Annotated[str | None, Setting(min_len=1, doc="agents: the robot id; operators: op-<name>")] = None
    password: Annotated[str | None, Setting(min_len=1, doc="prefer password_file")] = None
    password_file: Annotated[str | None, Setting(min_len=1, doc="relative to this file")] = None
    ca_file: Annotated[str | None, Setting(min_len=1, doc="mqtts: the site CA (default: the system's)")] = None
    cert_file: Annotated[str | None, Setting(min_len=1, doc="client certificate (mutual TLS)")] = None
    key_file: Annotated[str | None, Setting(min_len=1, doc="its key (with cert_file)")] = None
    client_id: Annotated[str | None, Setting(min_len=1)] = None
    keepalive_s: Annotated[int, Setting(lo=1, hi=3600, doc="the broker declares the client dead after 1.5x")] = 5
    reconnect_min_s: Annotated[float, Setting(lo=0.05, hi=600.0, doc="reconnect backoff, doubling up to ...")] = 0.5
    reconnect_max_s: Annotated[float, Setting(lo=0.05, hi=3600.0, doc="... this")] = 10.0

    def validate(self) -> None:
        if self.password is not None and self.password_file is not None:
            raise Invalid("", "give password or password_file, not both")
        tls_files = self.ca_file or self.cert_file or self.key_file
        if tls_files and not self.url.startswith("mqtts://"):
            raise Invalid("", "ca_file, cert_file and key_file need an mqtts:// url")
        if (self.cert_file is None) != (self.key_file is None):
            raise Invalid("", "cert_file and key_file go together (both or neither)")
        if self.reconnect_max_s < self.reconnect_min_s:
            raise Invalid(
                "", f"reconnect_max_s ({self.reconnect_max_s}) must be >= reconnect_min_s ({self.reconnect_min_s})"
            )


def check_endpoint(endpoint: str) -> str:
    if "/" not in endpoint:
        raise ValueError(f"{endpoint!r} is not an endpoint like 'tcp/127.0.0.1:7447'")
    return endpoint


Endpoint = Annotated[str, Setting(min_len=1, convert=check_endpoint)]
Endpoints = Annotated[tuple[Endpoint, ...], Setting(what="a list of endpoints like 'tcp/127.0.0.1:7447'")]


@dataclass(frozen=True, slots=True)
class ZenohTable:
    """``[zenoh]``: endpoints, mode and the login on a secured site router (deploy/zenohd.json5)."""

    listen: Endpoints = ()
    connect: Endpoints = ()
    mode: Literal["peer", "client"] = "peer"
    username: Annotated[str | None, Setting(min_len=1, doc="the router's usrpwd login")] = None
    password: Annotated[str | None, Setting(min_len=1, doc="prefer password_file")] = None
    password_file: Annotated[str | None, Setting(min_len=1, doc="relative to this file")] = None
    root_ca: Annotated[str | None, Setting(min_len=1, doc="the site CA, for tls/ endpoints")] = None
    tls_cert: Annotated[str | None, Setting(min_len=1, doc="client certificate (mutual TLS)")] = None
    tls_key: Annotated[str | None, Setting(min_len=1, doc="its key")] = None

    def validate(self) -> None:
        if self.password is not None and self.password_file is not None:
            raise Invalid("", "give password or password_file, not both")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise Invalid("", "tls_cert and tls_key go together (both or neither)")


class _Files:
    """Files named by a table, relative to the configuration file's folder, checked as they are read."""

    def __init__(self, source: str, where: str, base_dir: str | Path | None) -> None:
        self.source, self.where, self.base_dir = source, where, base_dir

    def fail(self, key: str, problem: str) -> ConfigError:
        return ConfigError.at(self.source, f"{self.where}.{key}" if key else self.where, problem)

    def path(self, key: str, value: str | None) -> str | None:
        if value is None:
            return None
        p = Path(value)
        if not p.is_absolute() and self.base_dir is not None:
            p = Path(self.base_dir) / p
        if not p.is_file():
            raise self.fail(key, f"no such file {str(p)!r}")
        return str(p)

    def password(self, key: str, value: str | None) -> str | None:
        path = self.path(key, value)
        if path is None:
            return None
        try:
            password = Path(path).read_text(encoding="utf-8").strip("\r\n")
        except (OSError, UnicodeDecodeError) as exc:
            raise self.fail(key, f"cannot read {path!r}: {exc}") from None
        if not password:
            raise self.fail(key, f"{path!r} is empty")
        return password


def mqtt_settings(
    t: MqttTable, *, source: str, where: str = "mqtt", base_dir: str | Path | None = None
) -> MqttSettings:
    """``MqttSettings`` from a checked table: files found and read (``ConfigError`` naming the key)."""
    files = _Files(source, where, base_dir)
    password = t.password if t.password is not None else files.password("password_file", t.password_file)
    if password is not None and t.username is None:
        raise files.fail("", "a password needs a username")
    base = MqttSettings.from_url(t.url)
    return MqttSettings(
        host=base.host,
        port=base.port,
        tls=base.tls,
        username=t.username,
        password=password,
        ca_file=files.path("ca_file", t.ca_file),
        cert_file=files.path("cert_file", t.cert_file),
        key_file=files.path("key_file", t.key_file),
        client_id=t.client_id,
        keepalive_s=t.keepalive_s,
        reconnect_min_s=t.reconnect_min_s,
        reconnect_max_s=t.reconnect_max_s,
    )


def zenoh_auth(t: ZenohTable, *, source: str, where: str = "zenoh", base_dir: str | Path | None = None) -> ZenohAuth:
    """The login part of a checked ``[zenoh]`` table, files found and read (``ConfigError`` naming the key)."""
    files = _Files(source, where, base_dir)
    password = t.password if t.password is not None else files.password("password_file", t.password_file)
    if (t.username is None) != (password is None):
        raise files.fail("", "username and password (or password_file) go together")
    return ZenohAuth(
        t.mode,
        t.username,
        password,
        files.path("root_ca", t.root_ca),
        files.path("tls_cert", t.tls_cert),
        files.path("tls_key", t.tls_key),
    )
