"""robot.toml: what one agent needs to run, validated with clear errors (shared/config.py).

```toml
robot = "r1"                                # robot id (wire-contract rule)
board = "socket://127.0.0.1:7001"           # or /dev/ttyUSB0
lidar = "socket://127.0.0.1:7002"           # optional
tag = "r1"                                  # UWB tag / PANS node id
map_id = "office"
operators = ["op-alice", "op-bob"]          # who may command this robot (header sender); [] = anyone

[zenoh]
listen = []
connect = ["tcp/127.0.0.1:7447"]
mode = "peer"                               # or "client"
username = "r1"                             # optional: the router's usrpwd login (with password or password_file)
password_file = "/etc/fleetlink/secrets/zenoh-password"
root_ca = "/etc/fleetlink/tls/ca.crt"       # optional: for tls/ endpoints
# tls_cert / tls_key: optional client certificate (mutual TLS)

[mqtt]                                      # optional: no table, no fallback link
url = "mqtt://127.0.0.1:1883"               # or mqtts://host:8883; every key of shared/mqtt.py
username = "r1"                             # optional
password_file = "/etc/fleetlink/secrets/mqtt-password"   # or password = "..."

[limits]                                    # optional, defaults shown in deploy/robot.example.toml
v_max = 0.5
omega_max = 1.5
a_max = 1.0
alpha_max = 6.0
teleop_ttl_s = 0.5
stop_distance_m = 0.4

[rates]
control_hz = 50.0
pose_hz = 20.0
state_hz = 1.0
```
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fleetlink.shared import keys
from fleetlink.shared.config import ConfigError, TomlReader, read_toml
from fleetlink.shared.mqtt import MqttSettings
from fleetlink.shared.zenoh_config import read_zenoh_auth

__all__ = [
    "AgentConfig",
    "ConfigError",
    "Limits",
    "MqttSettings",
    "Rates",
    "ZenohSettings",
    "load_agent_config",
    "mqtt_settings",
]


def mqtt_settings(url: str, username: str | None = None, password: str | None = None) -> MqttSettings:
    """``shared.mqtt.MqttSettings`` from a url (mqtt[s]://host:port) and optional credentials."""
    return MqttSettings.from_url(url, username=username, password=password)


@dataclass(frozen=True, slots=True)
class ZenohSettings:
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    mode: str = "peer"
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    root_ca: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None


@dataclass(frozen=True, slots=True)
class Limits:
    v_max: float = 0.5
    omega_max: float = 1.5
    a_max: float = 1.0
    alpha_max: float = 6.0
    teleop_ttl_s: float = 0.5
    stop_distance_m: float = 0.4


@dataclass(frozen=True, slots=True)
class Rates:
    control_hz: float = 50.0
    pose_hz: float = 20.0
    state_hz: float = 1.0


@dataclass(frozen=True, slots=True)
class AgentConfig:
    robot: str
    board: str
    lidar: str | None = None
    tag: str = ""
    map_id: str = ""
    zenoh: ZenohSettings | None = field(default_factory=ZenohSettings)
    mqtt: MqttSettings | None = None
    limits: Limits = field(default_factory=Limits)
    rates: Rates = field(default_factory=Rates)
    operators: tuple[str, ...] = ()
    """Operator ids (header sender) whose commands are accepted; empty: anyone's."""


def load_agent_config(path: str | Path) -> AgentConfig:
    return parse_agent_config(read_toml(path), str(path), base_dir=Path(path).resolve().parent)


def parse_agent_config(
    data: dict[str, Any], source: str = "robot.toml", base_dir: str | Path | None = None
) -> AgentConfig:
    r = TomlReader(source)
    top = ("robot", "board", "lidar", "tag", "map_id", "operators", "zenoh", "mqtt", "limits", "rates")
    r.keys(data, "top level", top, required=("robot", "board"))
    robot = r.text(data["robot"], "robot", nonempty=True)
    try:
        keys.check_robot_id(robot)
    except ValueError as exc:
        raise r.fail("robot", str(exc)) from None
    board = r.text(data["board"], "board", nonempty=True)
    lidar = r.text(data["lidar"], "lidar") if "lidar" in data else None
    tag = r.text(data.get("tag", robot), "tag", nonempty=True)
    map_id = r.text(data.get("map_id", ""), "map_id")
    if len(map_id) > 64:
        raise r.fail("map_id", "at most 64 characters")
    ops = data.get("operators", [])
    if not isinstance(ops, list) or not all(isinstance(o, str) and 0 < len(o) <= 64 for o in ops):
        raise r.fail("operators", f"expected a list of operator ids (1-64 characters each), got {ops!r}")
    operators = tuple(ops)

    zenoh: ZenohSettings | None = None
    if "zenoh" in data:
        z = r.table(data, "zenoh")
        zenoh = _zenoh(r, z, base_dir)

    mqtt: MqttSettings | None = None
    if "mqtt" in data:
        mqtt = MqttSettings.from_table(data["mqtt"], source=source, where="mqtt", base_dir=base_dir)
    if zenoh is None and mqtt is None:
        raise r.fail("top level", "needs a [zenoh] or an [mqtt] table (or both): the agent must hear its operator")

    lim = r.table(data, "limits")
    r.keys(lim, "limits", Limits.__dataclass_fields__)
    d = Limits()
    limits = Limits(
        **{
            name: r.number(lim.get(name, getattr(d, name)), f"limits.{name}", lo=1e-6, hi=100.0)
            for name in Limits.__dataclass_fields__
        }
    )
    rt = r.table(data, "rates")
    r.keys(rt, "rates", Rates.__dataclass_fields__)
    dr = Rates()
    rates = Rates(
        **{
            name: r.number(rt.get(name, getattr(dr, name)), f"rates.{name}", lo=0.1, hi=1000.0)
            for name in Rates.__dataclass_fields__
        }
    )
    return AgentConfig(robot, board, lidar or None, tag, map_id, zenoh, mqtt, limits, rates, operators)


def _zenoh(r: TomlReader, z: Any, base_dir: str | Path | None) -> ZenohSettings:
    r.keys(
        z,
        "zenoh",
        ("listen", "connect", "mode", "username", "password", "password_file", "root_ca", "tls_cert", "tls_key"),
    )
    auth = read_zenoh_auth(r, z, base_dir)
    return ZenohSettings(
        _endpoints(r, z, "listen"),
        _endpoints(r, z, "connect"),
        auth.mode,
        auth.username,
        auth.password,
        auth.root_ca,
        auth.tls_cert,
        auth.tls_key,
    )


def _endpoints(r: TomlReader, table: Any, name: str) -> tuple[str, ...]:
    v = table.get(name, [])
    if not isinstance(v, list) or not all(isinstance(e, str) and "/" in e for e in v):
        raise r.fail(f"zenoh.{name}", f"expected a list of endpoints like 'tcp/127.0.0.1:7447', got {v!r}")
    return tuple(v)
