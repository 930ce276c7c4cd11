"""``uwb.toml``: the UWB gateway's configuration, validated with clear messages.

Every problem names the file, the key and the reason (``ConfigError``). See docs/protocols/uwb.md
for the format. Anchors come from ``[[anchors]]``, else from ``scenario`` (its anchors, else its
plan's), else from ``plan``; the plan also gives the walls for ``noise.use_walls``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import unquote, urlsplit, urlunsplit

import numpy as np
import numpy.typing as npt

from fleetlink.shared import keys
from fleetlink.shared.config import ConfigError, Invalid, Setting, parse, read_toml
from fleetlink.shared.link_tables import MqttTable, ZenohTable, mqtt_settings, zenoh_auth
from fleetlink.shared.mqtt import MqttSettings

from .anchors import Anchor
from .ranging import NoiseProfile

__all__ = [
    "ConfigError",
    "GatewayConfig",
    "MqttSettings",
    "SiteGeometry",
    "SiteLoader",
    "TagSpec",
    "UwbFile",
    "ZenohAuth",
    "load_config",
    "parse_config",
]

PROFILES = {"none": NoiseProfile.none, "los": NoiseProfile.los, "realistic": NoiseProfile.realistic}
DEFAULT_TAG_Z = 0.3


AnchorRow = tuple[str, float, float, float]
SiteGeometry = tuple[tuple[AnchorRow, ...], npt.NDArray[np.float64] | None]
"""What the gateway takes from a plan or scenario: anchors (id, x, y, z) and walls (N x 4) or None."""

SiteLoader = Callable[[str | None, str | None, Path | None], SiteGeometry]
"""``site(plan, scenario, base_dir)``: the geometry a ``plan = ...``/``scenario = ...`` names.

positioning does not read plans or scenarios itself (they belong to the field): the program that
loads a uwb.toml passes one, ``fleetlink.field.scenario.site_geometry``. It raises ValueError."""


@dataclass(frozen=True, slots=True)
class TagSpec:
    id: str  # the tag's node id (PANS topic), [A-Za-z0-9_-]
    robot: str  # the robot it rides on
    z: float = DEFAULT_TAG_Z  # m above the floor, known to the solver


DEFAULT_MQTT_KEEPALIVE_S = 10


def default_mqtt() -> MqttSettings:
    """No ``[mqtt]`` table: the local broker, anonymous (a development setup)."""
    return MqttSettings(host="127.0.0.1", port=1883, keepalive_s=DEFAULT_MQTT_KEEPALIVE_S)


@dataclass(frozen=True, slots=True)
class ZenohAuth:
    """Credentials for the truth subscription on a secured site router (deploy/zenohd.json5)."""

    username: str | None = None
    password: str | None = field(default=None, repr=False)
    root_ca: str | None = None  # the site CA for tls/ endpoints
    mode: str = "peer"  # "client" against a site router


@dataclass(frozen=True, slots=True)
class GatewayConfig:
    anchors: tuple[Anchor, ...]
    tags: tuple[TagSpec, ...] = ()
    profile: NoiseProfile = field(default_factory=NoiseProfile.los)
    gateway_id: str = "uwb"
    rate_hz: float = 10.0
    seed: int = 0
    auto_tags: bool = False  # a robot seen in the truth without a [[tags]] entry gets tag id = robot id
    tag_z: float = DEFAULT_TAG_Z  # height of auto tags
    truth_timeout_s: float = 1.0  # no fix for a robot whose truth is older than this
    publish_ranges: bool = True
    pans: bool = True
    pans_prefix: str = "dwm"
    solver: str = "robust"  # robust | linear
    walls: npt.NDArray[np.float64] | None = field(default=None, compare=False, repr=False)
    mqtt: MqttSettings = field(default_factory=default_mqtt)
    zenoh_connect: tuple[str, ...] = ()
    zenoh_listen: tuple[str, ...] = ()
    zenoh_auth: ZenohAuth = field(default_factory=ZenohAuth)
    source: str = "<memory>"


# -- the file, as schemas for shared/config.py -----------------------------------------------------


def _node_id(v: str) -> str:
    if not keys.is_valid_id(v):
        raise ValueError(f"{v!r} must be 1-64 characters from [A-Za-z0-9_-]")
    return v


def _robot_id(v: str) -> str:
    keys.check_robot_id(v)
    return v


def _topic_prefix(v: str) -> str:
    if any(c in v for c in "#+\0") or v.startswith("/") or v.endswith("/"):
        raise ValueError(f"{v!r} is not a valid MQTT topic prefix")
    return v


Height = Annotated[float, Setting(lo=-10.0, hi=50.0, doc="m above the floor")]


@dataclass(frozen=True, slots=True)
class GatewayTable:
    id: Annotated[str, Setting(convert=_node_id, doc="the gateway's id (status topic)")] = "uwb"
    rate_hz: Annotated[float, Setting(lo=0.1, hi=100.0, doc="fixes a second per tag")] = 10.0
    seed: Annotated[int, Setting(lo=0, hi=2**63 - 1)] = 0
    auto_tags: Annotated[bool, Setting(doc="a robot without a [[tags]] entry gets tag id = robot id")] = False
    tag_z: Annotated[Height, Setting(doc="height of auto tags, m")] = DEFAULT_TAG_Z
    truth_timeout_s: Annotated[float, Setting(lo=0.01, hi=3600.0, doc="no fix from older truth")] = 1.0
    publish_ranges: bool = True
    pans: Annotated[bool, Setting(doc="PANS JSON on <pans_prefix>/node/<tag>/uplink/location")] = True
    pans_prefix: Annotated[str, Setting(min_len=1, convert=_topic_prefix)] = "dwm"
    solver: Literal["robust", "linear"] = "robust"


@dataclass(frozen=True, slots=True)
class AnchorTable:
    id: Annotated[str, Setting(min_len=1)]
    x: float
    y: float
    z: float


@dataclass(frozen=True, slots=True)
class TagTable:
    id: Annotated[str, Setting(convert=_node_id, doc="the tag's node id (PANS topic)")]
    robot: Annotated[str, Setting(convert=_robot_id, doc="the robot it rides on")]
    z: Height | None = None  # default: gateway.tag_z


Ratio = Annotated[float | None, Setting(lo=0.0, hi=1.0, what="a probability (0-1)")]
Length = Annotated[float | None, Setting(lo=0.0, doc="m")]
Zone = Annotated[
    tuple[Annotated[tuple[float, float], Setting(what="[x, y]")], ...],
    Setting(min_len=3, what="a polygon of [x, y] points"),
]


@dataclass(frozen=True, slots=True)
class NoiseTable:
    """``[noise]``: a profile, and any of its numbers overridden."""

    profile: Literal["none", "los", "realistic"] = "realistic"
    sigma_m: Length = None
    nlos_ratio: Ratio = None
    nlos_mean_bias_m: Length = None
    outlier_ratio: Ratio = None
    outlier_min_m: Length = None
    outlier_max_m: Length = None
    dropout_ratio: Ratio = None
    antenna_delay_m: Annotated[float | None, Setting(doc="m, may be negative")] = None
    max_range_m: Length = None
    use_walls: Annotated[bool | None, Setting(doc="walls of the plan or scenario cause NLOS")] = None
    nlos_zones: Annotated[tuple[Zone, ...], Setting(what="a list of polygons ([[x, y], ...])")] = ()

    def profile_of(self) -> NoiseProfile:
        over: dict[str, Any] = {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if f.name != "profile" and getattr(self, f.name) not in (None, ())
        }
        try:
            return dataclasses.replace(PROFILES[self.profile](), **over)
        except ValueError as exc:
            raise Invalid("", str(exc)) from None


@dataclass(frozen=True, slots=True)
class UwbFile:
    """uwb.toml as written (docs/protocols/uwb.md)."""

    gateway: GatewayTable = field(default_factory=GatewayTable)
    plan: Annotated[str | None, Setting(min_len=1, doc="a built-in plan or a path: anchors and walls")] = None
    scenario: Annotated[str | None, Setting(min_len=1, doc="a built-in scenario or a path: anchors and walls")] = None
    anchors: tuple[AnchorTable, ...] = ()
    tags: tuple[TagTable, ...] = ()
    noise: NoiseTable = field(default_factory=NoiseTable)
    mqtt: MqttTable | None = None
    zenoh: ZenohTable = field(default_factory=ZenohTable)

    def validate(self) -> None:
        for i, a in enumerate(self.anchors):
            if any(b.id == a.id for b in self.anchors[:i]):
                raise Invalid(f"anchors[{i}].id", f"anchor {a.id!r} appears twice")
        for i, t in enumerate(self.tags):
            if any(x.id == t.id for x in self.tags[:i]):
                raise Invalid(f"tags[{i}].id", f"tag {t.id!r} appears twice")
            if any(x.robot == t.robot for x in self.tags[:i]):
                raise Invalid(f"tags[{i}].robot", f"robot {t.robot!r} already has a tag")
        if not self.tags and not self.gateway.auto_tags:
            raise Invalid("tags", "no [[tags]] (id, robot) and gateway.auto_tags is off: nothing to locate")
        self.noise.profile_of()
        if self.noise.use_walls and self.plan is None and self.scenario is None:
            raise Invalid("noise.use_walls", "needs a plan or scenario to take the walls from")
        if self.zenoh.tls_cert is not None or self.zenoh.tls_key is not None:
            raise Invalid("zenoh.tls_cert", "the UWB gateway does not present a client certificate")


def load_config(path: str | Path, site: SiteLoader | None = None) -> GatewayConfig:
    p = Path(path)
    return parse_config(read_toml(p), source=str(p), base=p.parent, site=site)


def parse_config(
    data: Mapping[str, Any], source: str = "<memory>", base: Path | None = None, site: SiteLoader | None = None
) -> GatewayConfig:
    """A gateway configuration from decoded TOML; ``ConfigError`` naming ``source``, the key and the problem.

    ``site`` reads what ``plan``/``scenario`` name (see ``SiteLoader``); without one, a file that
    names either is refused.
    """
    data = dict(data)
    if isinstance(data.get("mqtt"), dict):
        data["mqtt"] = _legacy_mqtt(data["mqtt"])
    f = parse(data, UwbFile, source=source)
    g = f.gateway

    geometry: SiteGeometry = ((), None)
    if f.plan is not None or f.scenario is not None:
        key = "plan" if f.plan is not None else "scenario"
        if site is None:
            raise ConfigError.at(source, key, "this program reads no plans or scenarios (give [[anchors]])")
        try:
            geometry = site(f.plan, f.scenario, base)
        except ValueError as exc:
            raise ConfigError.at(source, key, str(exc)) from None
    anchors = tuple(Anchor(*a) for a in geometry[0])
    if f.anchors:
        anchors = tuple(Anchor(a.id, a.x, a.y, a.z) for a in f.anchors)
    if len(anchors) < 3:
        raise ConfigError.at(
            source,
            "anchors",
            f"need at least 3 anchors, got {len(anchors)} (give [[anchors]], or a plan/scenario that has them)",
        )
    tags = tuple(TagSpec(t.id, t.robot, g.tag_z if t.z is None else t.z) for t in f.tags)
    mqtt = default_mqtt() if f.mqtt is None else mqtt_settings(f.mqtt, source=source, base_dir=base)
    auth = zenoh_auth(f.zenoh, source=source, base_dir=base)
    return GatewayConfig(
        anchors=anchors,
        tags=tags,
        profile=f.noise.profile_of(),
        gateway_id=g.id,
        rate_hz=g.rate_hz,
        seed=g.seed,
        auto_tags=g.auto_tags,
        tag_z=g.tag_z,
        truth_timeout_s=g.truth_timeout_s,
        publish_ranges=g.publish_ranges,
        pans=g.pans,
        pans_prefix=g.pans_prefix,
        solver=g.solver,
        walls=geometry[1],
        mqtt=mqtt,
        zenoh_connect=f.zenoh.connect,
        zenoh_listen=f.zenoh.listen,
        zenoh_auth=ZenohAuth(auth.username, auth.password, auth.root_ca, auth.mode),
        source=source,
    )


def _legacy_mqtt(table: dict[str, Any]) -> dict[str, Any]:
    """``[mqtt]`` defaults for the gateway (keepalive 10 s, the local broker), and for older files
    ``mqtt://user:password@host``: the credentials move to ``username``/``password`` (prefer
    ``password_file`` in production)."""
    m = dict(table)
    m.setdefault("url", "mqtt://127.0.0.1:1883")
    m.setdefault("keepalive_s", DEFAULT_MQTT_KEEPALIVE_S)
    url = m["url"]
    if isinstance(url, str):
        try:
            parts = urlsplit(url)
            has_userinfo = parts.username is not None or parts.password is not None
        except ValueError:
            has_userinfo = False
        if has_userinfo:
            if parts.username and "username" not in m:
                m["username"] = unquote(parts.username)
            if parts.password and "password" not in m and "password_file" not in m:
                m["password"] = unquote(parts.password)
            netloc = parts.netloc.rpartition("@")[2]
            m["url"] = urlunsplit((parts.scheme, netloc, parts.path, parts.query, parts.fragment))
    return m
