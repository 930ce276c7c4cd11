"""robot.toml: what one agent needs to run, validated with clear errors (shared/config.py).

```toml
robot = "r1"                                # robot id (wire-contract rule)
board = "socket://127.0.0.1:7001"           # or /dev/ttyUSB0
lidar = "socket://127.0.0.1:7002"           # optional
tag = "r1"                                  # UWB tag / PANS node id
map_id = "office"
operators = ["op-alice", "op-bob"]          # who may command this robot (header sender); [] = anyone
peers = ["r2", "r3"]                        # the other robots on the floor: standing ones are planned around

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
round_base = false                          # true: a round base may turn in place near things
creep_speed_mps = 0.0                       # > 0: creep to the walls (a sweeper), the bumper the last stop

[rates]
control_hz = 50.0
pose_hz = 20.0
state_hz = 1.0

[uv]                                        # optional: the UV-C lamp, for the dose layer (docs/payload.md)
uvc_power_w = 10.0                          # UV-C optical output (the datasheet's, derated), not electrical W
height_m = 0.6                              # lamp centre above the floor
tube_length_m = 0.0                         # 0: point source; else a vertical tube this long
target_dose_mj_cm2 = 10.0                   # the target dose (10 mJ/cm² = 100 J/m²)
dose_resolution_m = 0.1                     # cells of the dose layer
```
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from fleetlink.agent.contact import DEFAULT_TIMEOUT_S
from fleetlink.shared import keys
from fleetlink.shared.config import ConfigError, Invalid, Setting, parse, read_toml
from fleetlink.shared.dose import J_M2_PER_MJ_CM2, Lamp
from fleetlink.shared.link_tables import MqttTable, ZenohTable, zenoh_auth
from fleetlink.shared.link_tables import mqtt_settings as _mqtt_from_table
from fleetlink.shared.messages import MAX_COORDINATE_M, CommsPolicy
from fleetlink.shared.mqtt import MqttSettings

__all__ = [
    "AgentConfig",
    "Comms",
    "ConfigError",
    "HomeTable",
    "Limits",
    "MqttSettings",
    "Rates",
    "RobotFile",
    "UvTable",
    "ZenohSettings",
    "load_agent_config",
    "mqtt_settings",
    "parse_agent_config",
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


Limit = Annotated[float, Setting(lo=1e-6, hi=100.0)]
Rate = Annotated[float, Setting(lo=0.1, hi=1000.0)]


@dataclass(frozen=True, slots=True)
class Limits:
    v_max: Annotated[Limit, Setting(doc="m/s")] = 0.5
    omega_max: Annotated[Limit, Setting(doc="rad/s")] = 1.5
    a_max: Annotated[Limit, Setting(doc="m/s^2")] = 1.0
    alpha_max: Annotated[Limit, Setting(doc="rad/s^2")] = 6.0
    teleop_ttl_s: Annotated[Limit, Setting(doc="a teleop lapses after this long")] = 0.5
    stop_distance_m: Annotated[Limit, Setting(doc="the guard stops the robot this close to something")] = 0.4
    round_base: Annotated[
        bool, Setting(doc="the base is round: turning in place sweeps no new floor, so the guard allows it near things")
    ] = False
    creep_speed_mps: Annotated[
        float,
        Setting(
            lo=0.0, hi=0.2, doc="inside the stop distance creep on at this speed, the bumper the last stop; 0: stop"
        ),
    ] = 0.0


@dataclass(frozen=True, slots=True)
class Rates:
    control_hz: Annotated[Rate, Setting(doc="the control loop while driving")] = 50.0
    pose_hz: Annotated[Rate, Setting(doc="pose telemetry")] = 20.0
    state_hz: Annotated[Rate, Setting(doc="state telemetry")] = 1.0
    scan_hz: Annotated[float, Setting(lo=0.0, hi=20.0, doc="lidar scans on Zenoh (0: none)")] = 2.0


@dataclass(frozen=True, slots=True)
class HomeTable:
    """``[home]``: the robot's dock, its home from the start (docs/motion.md, "Home")."""

    x: Annotated[float, Setting(lo=-MAX_COORDINATE_M, hi=MAX_COORDINATE_M, doc="m, site frame")]
    y: Annotated[float, Setting(lo=-MAX_COORDINATE_M, hi=MAX_COORDINATE_M, doc="m, site frame")]
    theta_deg: Annotated[float | None, Setting(lo=-360.0, hi=360.0, doc="heading at home; absent: any")] = None


@dataclass(frozen=True, slots=True)
class Comms:
    """``[comms]``: what the robot does when it stops hearing its operators (docs/motion.md)."""

    policy: Annotated[
        CommsPolicy, Setting(read_as=str, convert=CommsPolicy, choices=tuple(p.value for p in CommsPolicy))
    ] = CommsPolicy.STOP
    timeout_s: Annotated[float, Setting(lo=1.0, hi=600.0, doc="silence that counts as out of contact")] = (
        DEFAULT_TIMEOUT_S
    )
    payload_on_loss: Annotated[bool, Setting(doc="keep the payload on while out of contact")] = False


@dataclass(frozen=True, slots=True)
class UvTable:
    """``[uv]``: the robot's UV-C lamp, which the agent's dose layer accumulates (docs/payload.md,
    "The lamp" and "Dose layer"); a robot without it keeps no dose layer."""

    uvc_power_w: Annotated[float, Setting(lo=1e-3, hi=10_000.0, doc="UV-C optical output, W (not electrical W)")]
    height_m: Annotated[float, Setting(lo=0.01, hi=10.0, doc="lamp centre above the floor, m")]
    tube_length_m: Annotated[float, Setting(lo=0.0, hi=5.0, doc="0: point source; else a vertical tube, m")] = 0.0
    min_distance_m: Annotated[float, Setting(lo=0.01, hi=5.0, doc="the model holds beyond this distance, m")] = 0.3
    target_dose_mj_cm2: Annotated[
        float, Setting(lo=1e-4, hi=100_000.0, doc="the dose every cell should get, mJ/cm² (10 = 100 J/m²)")
    ] = 10.0
    dose_resolution_m: Annotated[float, Setting(lo=0.02, hi=1.0, doc="cell size of the dose layer, m")] = 0.1

    def validate(self) -> None:
        self.lamp.validate()  # the lamp model's own checks (the floor beyond min_distance_m), with their keys

    @property
    def lamp(self) -> Lamp:
        return Lamp(self.uvc_power_w, self.height_m, self.tube_length_m, self.min_distance_m)

    @property
    def target_j_m2(self) -> float:
        return self.target_dose_mj_cm2 * J_M2_PER_MJ_CM2


@dataclass(frozen=True, slots=True)
class MappingTable:
    """``[mapping]``: the onboard map (docs/mapping.md, "On board")."""

    loop_closure: Annotated[
        bool, Setting(doc="close loops on board; the fused pose then moves with the map (false: the map follows it)")
    ] = True


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
    home: HomeTable | None = None
    comms: Comms = field(default_factory=Comms)
    uv: UvTable | None = None
    """The UV-C lamp (None: no lamp, no dose layer)."""
    mapping: MappingTable = field(default_factory=MappingTable)
    peers: tuple[str, ...] = ()
    """The other robots on the floor, whose fused poses the agent hears (agent/peers.py): where one
    stands still in the site frame, the robot's legs are planned around it."""


def _robot_id(robot: str) -> str:
    keys.check_robot_id(robot)
    if robot == keys.FLEET_MAP:
        raise ValueError(f"robot id {robot!r} is where the fleet map is served (fleetlink/v1/fleet/map)")
    return robot


@dataclass(frozen=True, slots=True)
class RobotFile:
    """robot.toml as written (the schema); ``parse_agent_config`` turns it into an ``AgentConfig``."""

    robot: Annotated[str, Setting(convert=_robot_id, doc="robot id (wire-contract rule)")]
    board: Annotated[str, Setting(min_len=1, doc="socket://host:port or /dev/ttyUSB0")]
    lidar: Annotated[str | None, Setting(doc="optional, as board")] = None
    tag: Annotated[str | None, Setting(min_len=1, doc="UWB tag / PANS node id (default: the robot id)")] = None
    map_id: Annotated[str, Setting(max_len=64)] = ""
    operators: Annotated[
        tuple[Annotated[str, Setting(min_len=1, max_len=64)], ...],
        Setting(what="a list of operator ids", doc="who may command this robot; [] = anyone"),
    ] = ()
    peers: Annotated[
        tuple[Annotated[str, Setting(convert=_robot_id)], ...],
        Setting(what="a list of robot ids", doc="the other robots on the floor, planned around where they stand"),
    ] = ()
    zenoh: ZenohTable | None = None
    mqtt: MqttTable | None = None
    limits: Limits = field(default_factory=Limits)
    rates: Rates = field(default_factory=Rates)
    home: HomeTable | None = None
    comms: Comms = field(default_factory=Comms)
    uv: UvTable | None = None
    mapping: MappingTable = field(default_factory=MappingTable)

    def validate(self) -> None:
        if self.zenoh is None and self.mqtt is None:
            raise Invalid("", "needs a [zenoh] or an [mqtt] table (or both): the agent must hear its operator")
        if self.robot in self.peers:
            raise Invalid("peers", f"lists the robot itself ({self.robot!r}): peers are the other robots")


def load_agent_config(path: str | Path) -> AgentConfig:
    return parse_agent_config(read_toml(path), str(path), base_dir=Path(path).resolve().parent)


def parse_agent_config(
    data: dict[str, Any], source: str = "robot.toml", base_dir: str | Path | None = None
) -> AgentConfig:
    f = parse(data, RobotFile, source=source)
    zenoh: ZenohSettings | None = None
    if f.zenoh is not None:
        auth = zenoh_auth(f.zenoh, source=source, base_dir=base_dir)
        zenoh = ZenohSettings(
            f.zenoh.listen,
            f.zenoh.connect,
            auth.mode,
            auth.username,
            auth.password,
            auth.root_ca,
            auth.tls_cert,
            auth.tls_key,
        )
    mqtt = None if f.mqtt is None else _mqtt_from_table(f.mqtt, source=source, base_dir=base_dir)
    return AgentConfig(
        f.robot,
        f.board,
        f.lidar or None,
        f.tag or f.robot,
        f.map_id,
        zenoh,
        mqtt,
        f.limits,
        f.rates,
        f.operators,
        f.home,
        f.comms,
        f.uv,
        f.mapping,
        tuple(dict.fromkeys(f.peers)),
    )
