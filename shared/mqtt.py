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

The table is declared once, as a config schema (``shared/link_tables.py``: ``MqttTable``), and
turned into ``MqttSettings`` by ``link_tables.mqtt_settings``, which reads the password file at load
time so a missing or empty file is reported with the configuration's other errors, not on the
first reconnect.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

from fleetlink.shared.config import ConfigError

__all__ = ["ConfigError", "MqttSettings", "parse_url"]

DEFAULT_PORTS = {"mqtt": 1883, "mqtts": 8883}


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
        """Settings for ``url`` (mqtt://host:port or mqtts://host:port) with ``kw`` as the other fields.

        ``ConfigError`` for a url that is not one."""
        try:
            host, port, tls = parse_url(url)
        except ValueError as exc:
            raise ConfigError(f"url: {exc}") from None
        return cls(host=host, port=port, tls=tls, **kw)


def parse_url(url: str) -> tuple[str, int, bool]:
    """(host, port, tls) of mqtt[s]://host[:port]; ValueError saying what is wrong with anything else."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"invalid url {url!r}: {exc}") from None
    if parts.scheme not in DEFAULT_PORTS:
        raise ValueError(f"invalid url {url!r}: scheme must be mqtt:// or mqtts://")
    if not parts.hostname:
        raise ValueError(f"invalid url {url!r}: no host")
    if parts.username or parts.password:
        raise ValueError(f"invalid url {url!r}: put credentials in username/password_file, not the url")
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise ValueError(f"invalid url {url!r}: expected mqtt[s]://host[:port] and nothing after")
    return parts.hostname, port if port is not None else DEFAULT_PORTS[parts.scheme], parts.scheme == "mqtts"
