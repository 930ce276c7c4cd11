"""``uwb.toml``: the UWB gateway's configuration, validated with clear messages.

Every problem names the file, the key and the reason (``ConfigError``). See docs/protocols/uwb.md
for the format. Anchors come from ``[[anchors]]``, else from ``scenario`` (its anchors, else its
plan's), else from ``plan``; the plan also gives the walls for ``noise.use_walls``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit, urlunsplit

import numpy as np
import numpy.typing as npt

from fleetlink.shared import keys
from fleetlink.shared.config import ConfigError, TomlReader, read_toml
from fleetlink.shared.mqtt import KEYS as MQTT_KEYS
from fleetlink.shared.mqtt import MqttSettings
from fleetlink.shared.zenoh_config import read_zenoh_auth

from .anchors import Anchor
from .ranging import NoiseProfile

__all__ = ["ConfigError", "GatewayConfig", "MqttSettings", "TagSpec", "ZenohAuth", "load_config", "parse_config"]

PROFILES = {"none": NoiseProfile.none, "los": NoiseProfile.los, "realistic": NoiseProfile.realistic}
SCENARIOS_DIR = Path(__file__).resolve().parent.parent / "field" / "scenarios"
DEFAULT_TAG_Z = 0.3


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


_TOP = {"gateway", "plan", "scenario", "anchors", "tags", "noise", "mqtt", "zenoh"}
_GATEWAY = {
    "id",
    "rate_hz",
    "seed",
    "auto_tags",
    "tag_z",
    "truth_timeout_s",
    "publish_ranges",
    "pans",
    "pans_prefix",
    "solver",
}
_NOISE_NUMBERS = {f.name for f in fields(NoiseProfile)} - {"nlos_zones", "use_walls"}


def load_config(path: str | Path) -> GatewayConfig:
    p = Path(path)
    return parse_config(read_toml(p), source=str(p), base=p.parent)


def _resolve(name: str, base: Path | None, builtin_dir: Path | None = None) -> str | Path:
    """A built-in name stays a name (plans) or maps into ``builtin_dir``; a path is made absolute."""
    if builtin_dir is not None and "/" not in name and not name.endswith(".toml"):
        return builtin_dir / f"{name}.toml"
    if "/" in name or name.endswith((".toml", ".yaml", ".yml")):
        p = Path(name)
        return p if p.is_absolute() or base is None else (base / p).resolve()
    return name


def parse_config(data: Mapping[str, Any], source: str = "<memory>", base: Path | None = None) -> GatewayConfig:
    from fleetlink.field.plans import FloorPlan, PlanError, load_plan
    from fleetlink.field.scenario import ScenarioError, load_scenario

    r = TomlReader(source)
    r.keys(data, "top level", _TOP)

    g = r.table(data, "gateway")
    r.keys(g, "gateway", _GATEWAY)
    gid = r.text(g.get("id", "uwb"), "gateway.id", nonempty=True)
    if not keys.is_valid_id(gid):
        raise r.fail("gateway.id", f"{gid!r} must be 1-64 characters from [A-Za-z0-9_-]")
    rate = r.number(g.get("rate_hz", 10.0), "gateway.rate_hz", lo=0.1, hi=100.0)
    seed = r.integer(g.get("seed", 0), "gateway.seed", lo=0, hi=2**63 - 1)
    auto = r.flag(g.get("auto_tags", False), "gateway.auto_tags")
    tag_z = r.number(g.get("tag_z", DEFAULT_TAG_Z), "gateway.tag_z", lo=-10.0, hi=50.0)
    timeout = r.number(g.get("truth_timeout_s", 1.0), "gateway.truth_timeout_s", lo=0.01, hi=3600.0)
    pub_ranges = r.flag(g.get("publish_ranges", True), "gateway.publish_ranges")
    pans = r.flag(g.get("pans", True), "gateway.pans")
    prefix = r.text(g.get("pans_prefix", "dwm"), "gateway.pans_prefix", nonempty=True)
    if any(c in prefix for c in "#+\0") or prefix.startswith("/") or prefix.endswith("/"):
        raise r.fail("gateway.pans_prefix", f"{prefix!r} is not a valid MQTT topic prefix")
    solver = r.text(g.get("solver", "robust"), "gateway.solver")
    if solver not in ("robust", "linear"):
        raise r.fail("gateway.solver", f"must be 'robust' or 'linear', got {solver!r}")

    plan: FloorPlan | None = None
    anchors: tuple[Anchor, ...] = ()
    try:
        if "scenario" in data:
            sc_name = r.text(data["scenario"], "scenario", nonempty=True)
            sc = load_scenario(_resolve(sc_name, base, SCENARIOS_DIR))
            plan = load_plan(sc.plan)
            anchors = tuple(Anchor(*a) for a in sc.anchors)
        if "plan" in data:
            plan = load_plan(_resolve(r.text(data["plan"], "plan", nonempty=True), base))
    except (PlanError, ScenarioError, ConfigError) as exc:
        raise r.fail("plan" if "plan" in data else "scenario", str(exc)) from None
    if plan is not None and not anchors:
        anchors = tuple(Anchor(a.id, a.x, a.y, a.z) for a in plan.anchors)
    listed = r.tables(data, "anchors")
    if listed:
        out: list[Anchor] = []
        for i, t in enumerate(listed):
            where = f"anchors[{i}]"
            r.keys(t, where, {"id", "x", "y", "z"}, {"id", "x", "y", "z"})
            aid = r.text(t["id"], f"{where}.id", nonempty=True)
            if any(a.id == aid for a in out):
                raise r.fail(f"{where}.id", f"anchor {aid!r} appears twice")
            out.append(Anchor(aid, *(r.number(t[c], f"{where}.{c}") for c in "xyz")))
        anchors = tuple(out)
    if len(anchors) < 3:
        raise r.fail(
            "anchors",
            f"need at least 3 anchors, got {len(anchors)} (give [[anchors]], or a plan/scenario that has them)",
        )

    tags: list[TagSpec] = []
    for i, t in enumerate(r.tables(data, "tags")):
        where = f"tags[{i}]"
        r.keys(t, where, {"id", "robot", "z"}, {"id", "robot"})
        tid = r.text(t["id"], f"{where}.id", nonempty=True)
        robot = r.text(t["robot"], f"{where}.robot", nonempty=True)
        if not keys.is_valid_id(tid):
            raise r.fail(f"{where}.id", f"{tid!r} must be 1-64 characters from [A-Za-z0-9_-]")
        try:
            keys.check_robot_id(robot)
        except ValueError as exc:
            raise r.fail(f"{where}.robot", str(exc)) from None
        if any(x.id == tid for x in tags):
            raise r.fail(f"{where}.id", f"tag {tid!r} appears twice")
        if any(x.robot == robot for x in tags):
            raise r.fail(f"{where}.robot", f"robot {robot!r} already has a tag")
        tags.append(TagSpec(tid, robot, r.number(t.get("z", tag_z), f"{where}.z", lo=-10.0, hi=50.0)))
    if not tags and not auto:
        raise r.fail("tags", "no [[tags]] (id, robot) and gateway.auto_tags is off: nothing to locate")

    n = r.table(data, "noise")
    r.keys(n, "noise", {"profile", "use_walls", "nlos_zones"} | _NOISE_NUMBERS)
    pname = r.text(n.get("profile", "realistic"), "noise.profile")
    if pname not in PROFILES:
        raise r.fail("noise.profile", f"must be one of {', '.join(PROFILES)}, got {pname!r}")
    profile = PROFILES[pname]()
    over: dict[str, Any] = {
        k: r.number(n[k], f"noise.{k}", lo=None if k == "antenna_delay_m" else 0.0) for k in n if k in _NOISE_NUMBERS
    }
    for k in ("nlos_ratio", "outlier_ratio", "dropout_ratio"):
        if k in over and over[k] > 1.0:
            raise r.fail(f"noise.{k}", f"is a probability (0-1), got {over[k]}")
    if "use_walls" in n:
        over["use_walls"] = r.flag(n["use_walls"], "noise.use_walls")
        if over["use_walls"] and plan is None:
            raise r.fail("noise.use_walls", "needs a plan or scenario to take the walls from")
    zones = n.get("nlos_zones", [])
    if not isinstance(zones, list):
        raise r.fail("noise.nlos_zones", "expected a list of polygons ([[x, y], ...])")
    if zones:
        over["nlos_zones"] = tuple(r.polygon(z, f"noise.nlos_zones[{i}]") for i, z in enumerate(zones))
    try:
        profile = replace(profile, **over)
    except ValueError as exc:
        raise r.fail("noise", str(exc)) from None

    mqtt = _mqtt(r, data, source, base)

    z = r.table(data, "zenoh")
    r.keys(z, "zenoh", {"connect", "listen", "mode", "username", "password", "password_file", "root_ca"})
    endpoints: dict[str, tuple[str, ...]] = {}
    for k in ("connect", "listen"):
        v = z.get(k, [])
        if not isinstance(v, list):
            raise r.fail(f"zenoh.{k}", f"expected a list of endpoints like 'tcp/127.0.0.1:7447', got {v!r}")
        for i, e in enumerate(v):
            e = r.text(e, f"zenoh.{k}[{i}]", nonempty=True)
            if "/" not in e:
                raise r.fail(f"zenoh.{k}[{i}]", f"{e!r} is not an endpoint like 'tcp/127.0.0.1:7447'")
        endpoints[k] = tuple(v)
    zenoh_auth = _zenoh_auth(r, z, base)

    return GatewayConfig(
        anchors=anchors,
        tags=tuple(tags),
        profile=profile,
        gateway_id=gid,
        rate_hz=rate,
        seed=seed,
        auto_tags=auto,
        tag_z=tag_z,
        truth_timeout_s=timeout,
        publish_ranges=pub_ranges,
        pans=pans,
        pans_prefix=prefix,
        solver=solver,
        walls=plan.segments() if plan is not None else None,
        mqtt=mqtt,
        zenoh_connect=endpoints["connect"],
        zenoh_listen=endpoints["listen"],
        zenoh_auth=zenoh_auth,
        source=source,
    )


def _mqtt(r: TomlReader, data: Mapping[str, Any], source: str, base: Path | None) -> MqttSettings:
    """``[mqtt]`` through shared/mqtt.py (credentials, TLS, backoff); keepalive defaults to 10 s.

    For older files, ``mqtt://user:password@host`` is still read: the credentials move to
    ``username``/``password`` (prefer ``password_file`` in production).
    """
    if "mqtt" not in data:
        return default_mqtt()
    m = dict(r.table(data, "mqtt"))
    r.keys(m, "mqtt", set(MQTT_KEYS))
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
    return MqttSettings.from_table(m, source=source, where="mqtt", base_dir=base)


def _zenoh_auth(r: TomlReader, z: Mapping[str, Any], base: Path | None) -> ZenohAuth:
    auth = read_zenoh_auth(r, z, base)  # one reader for every process (shared/zenoh_config.py)
    return ZenohAuth(auth.username, auth.password, auth.root_ca, auth.mode)
