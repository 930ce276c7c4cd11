"""Scenario files: which plan, which robots where, how noisy, which seed, how long, and what happens.

A scenario is TOML (docs/field-scenarios.md). ``load_scenario`` validates it and reports problems
with the file, the key and the reason; nothing is half-loaded.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from fleetlink.shared.config import TomlReader, read_toml

__all__ = [
    "Event",
    "LidarSettings",
    "Noise",
    "RobotSpec",
    "Scenario",
    "ScenarioError",
    "load_scenario",
    "parse_scenario",
]

EVENT_KINDS = ("door_close", "door_open", "link_cut", "wheel_slip", "obstacle", "press_home")
DRIVES = ("wander", "script", "idle")


class ScenarioError(ValueError):
    """A scenario file that cannot be used, with the place and the reason."""


@dataclass(frozen=True, slots=True)
class Noise:
    wheel_scale_sd: float = 0.01  # sd of each wheel's true/nominal radius ratio, drawn once per robot
    gyro_bias_sd: float = 0.002  # rad/s, drawn once per robot
    gyro_noise_sd: float = 0.005  # rad/s per control tick
    ultrasonic_sd: float = 0.005  # m
    lidar_range_sd: float = 0.01  # m
    lidar_dropout: float = 0.01  # probability a lidar sample returns nothing
    uwb_range_sd: float = 0.10  # m (for the positioning system)

    @classmethod
    def none(cls) -> Noise:
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class LidarSettings:
    enabled: bool = True
    rate_hz: float = 10.0
    samples_per_second: float = 8000.0
    """Measurements a second (the RPLIDAR A1's 8000); a turn has ``samples_per_second / rate_hz``."""


@dataclass(frozen=True, slots=True)
class RobotSpec:
    name: str
    pose: tuple[float, float, float] | None = None  # x, y, theta (rad); None: use ``start``
    start: str | None = None  # a named start pose of the plan
    drive: str = "wander"  # wander | script | idle
    script: tuple[tuple[float, float, float], ...] = ()  # (t_s, v m/s, omega rad/s), held until the next
    speed: float = 0.25  # cruise speed for wander, m/s
    wheel_track: float = 0.22
    lidar: bool = True


@dataclass(frozen=True, slots=True)
class Event:
    at: float  # s
    kind: str
    robot: str | None = None
    door: str | None = None
    duration: float = 0.0
    wheel: str = "left"
    fraction: float = 0.5
    polygon: tuple[tuple[float, float], ...] = ()

    def describe(self) -> str:
        what = {
            "door_close": f"door {self.door} closes",
            "door_open": f"door {self.door} opens",
            "link_cut": f"board link of {self.robot} cut for {self.duration:g} s",
            "wheel_slip": f"{self.wheel} wheel of {self.robot} slips {self.fraction:.0%} for {self.duration:g} s",
            "obstacle": f"an obstacle appears ({len(self.polygon)} corners)",
            "press_home": f"someone presses the home button on {self.robot}",
        }[self.kind]
        return f"t={self.at:g} s: {what}"


@dataclass(frozen=True, slots=True)
class Scenario:
    name: str
    plan: str  # a built-in plan name, or a path (resolved against the scenario's folder)
    seed: int = 0
    duration: float = 60.0
    robots: tuple[RobotSpec, ...] = ()
    anchors: tuple[tuple[str, float, float, float], ...] = ()  # overrides the plan's when given
    noise: Noise = field(default_factory=Noise)
    lidar: LidarSettings = field(default_factory=LidarSettings)
    events: tuple[Event, ...] = ()
    truth_rate_hz: float = 20.0
    control_period: float = 0.01
    source: str = "<memory>"


def load_scenario(path: str | Path) -> Scenario:
    p = Path(path)
    scenario = parse_scenario(read_toml(p, ScenarioError), source=str(p))
    plan = scenario.plan
    if ("/" in plan or plan.endswith((".toml", ".yaml", ".yml"))) and not Path(plan).is_absolute():
        plan = str((p.parent / plan).resolve())
    return replace(scenario, plan=plan)


class _Reader(TomlReader):
    """Scenario-flavoured helpers on the shared TOML reader: optional keys with defaults."""

    def __init__(self, source: str) -> None:
        super().__init__(source, ScenarioError)

    def opt_num(
        self,
        table: Mapping[str, Any],
        key: str,
        where: str,
        default: float,
        lo: float | None = None,
        hi: float | None = None,
    ) -> float:
        return default if key not in table else self.number(table[key], f"{where}.{key}", lo, hi)

    def req_num(self, table: Mapping[str, Any], key: str, where: str, lo: float | None = None) -> float:
        if key not in table:
            raise self.fail(where, f"missing key {key}")
        return self.number(table[key], f"{where}.{key}", lo)

    def opt_text(self, table: Mapping[str, Any], key: str, where: str, default: str) -> str:
        return default if key not in table else self.text(table[key], f"{where}.{key}", nonempty=True)

    def req_text(self, table: Mapping[str, Any], key: str, where: str) -> str:
        if key not in table:
            raise self.fail(where, f"missing key {key}")
        return self.text(table[key], f"{where}.{key}", nonempty=True)

    def opt_flag(self, table: Mapping[str, Any], key: str, where: str, default: bool) -> bool:
        return default if key not in table else self.flag(table[key], f"{where}.{key}")


def parse_scenario(data: Mapping[str, Any], source: str = "<memory>") -> Scenario:
    r = _Reader(source)
    r.keys(
        data,
        "top level",
        {
            "name",
            "plan",
            "seed",
            "duration_s",
            "robots",
            "anchors",
            "noise",
            "lidar",
            "events",
            "truth_rate_hz",
            "control_period_s",
            "description",
        },
        {"plan", "robots"},
    )
    name = r.opt_text(data, "name", "top level", Path(source).stem)
    plan = r.req_text(data, "plan", "top level")
    seed = data.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise r.fail("seed", f"expected a non-negative integer, got {seed!r}")
    duration = r.opt_num(data, "duration_s", "top level", 60.0, lo=0.0)
    truth_rate = r.opt_num(data, "truth_rate_hz", "top level", 20.0, lo=0.1, hi=1000.0)
    control = r.opt_num(data, "control_period_s", "top level", 0.01, lo=0.001, hi=0.05)

    nt = r.table(data, "noise")
    r.keys(nt, "noise", set(Noise.__dataclass_fields__))
    noise = Noise(**{k: r.opt_num(nt, k, "noise", getattr(Noise(), k), lo=0.0) for k in Noise.__dataclass_fields__})
    if noise.lidar_dropout > 1.0:
        raise r.fail("noise.lidar_dropout", "is a probability (0-1)")

    lt = r.table(data, "lidar")
    r.keys(lt, "lidar", {"enabled", "rate_hz", "samples_per_second"})
    lidar = LidarSettings(
        r.opt_flag(lt, "enabled", "lidar", True),
        r.opt_num(lt, "rate_hz", "lidar", 10.0, lo=1.0, hi=20.0),
        r.opt_num(lt, "samples_per_second", "lidar", 8000.0, lo=100.0, hi=32000.0),
    )

    robots: list[RobotSpec] = []
    for i, t in enumerate(r.tables(data, "robots")):
        where = f"robots[{i}]"
        r.keys(t, where, {"name", "start", "pose", "drive", "script", "speed", "wheel_track", "lidar"}, {"name"})
        rname = r.req_text(t, "name", where)
        if any(x.name == rname for x in robots):
            raise r.fail(f"{where}.name", f"robot {rname!r} appears twice")
        pose = None
        if "pose" in t:
            pv = t["pose"]
            if not (
                isinstance(pv, list)
                and len(pv) == 3
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pv)
            ):
                raise r.fail(f"{where}.pose", "expected [x_m, y_m, theta_deg]")
            if not all(math.isfinite(v) for v in pv):
                raise r.fail(f"{where}.pose", "values must be finite")
            pose = (float(pv[0]), float(pv[1]), math.radians(float(pv[2])))
        start = t.get("start")
        if start is not None and not isinstance(start, str):
            raise r.fail(f"{where}.start", "expected the name of a start pose of the plan")
        if (pose is None) == (start is None):
            raise r.fail(where, "give exactly one of start (a named start of the plan) or pose")
        drive = r.opt_text(t, "drive", where, "wander")
        if drive not in DRIVES:
            raise r.fail(f"{where}.drive", f"expected one of {', '.join(DRIVES)}, got {drive!r}")
        script: list[tuple[float, float, float]] = []
        for j, row in enumerate(t.get("script", [])):
            if not (
                isinstance(row, list)
                and len(row) == 3
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in row)
            ):
                raise r.fail(f"{where}.script[{j}]", "expected [t_s, v_m_per_s, omega_rad_per_s] with finite numbers")
            if script and row[0] < script[-1][0]:
                raise r.fail(f"{where}.script[{j}]", "times must not go backwards")
            script.append((float(row[0]), float(row[1]), float(row[2])))
        if drive == "script" and not script:
            raise r.fail(f"{where}.script", 'drive = "script" needs a script')
        robots.append(
            RobotSpec(
                rname,
                pose,
                start,
                drive,
                tuple(script),
                r.opt_num(t, "speed", where, 0.25, lo=0.0, hi=1.0),
                r.opt_num(t, "wheel_track", where, 0.22, lo=0.05, hi=1.0),
                r.opt_flag(t, "lidar", where, True),
            )
        )
    if not robots:
        raise r.fail("robots", "a scenario needs at least one robot")

    anchors: list[tuple[str, float, float, float]] = []
    for i, t in enumerate(r.tables(data, "anchors")):
        where = f"anchors[{i}]"
        r.keys(t, where, {"id", "x", "y", "z"}, {"id", "x", "y"})
        aid = r.req_text(t, "id", where)
        if any(a[0] == aid for a in anchors):
            raise r.fail(f"{where}.id", f"anchor {aid!r} appears twice")
        anchors.append((aid, r.req_num(t, "x", where), r.req_num(t, "y", where), r.opt_num(t, "z", where, 2.4)))

    names = {rb.name for rb in robots}
    events: list[Event] = []
    for i, t in enumerate(r.tables(data, "events")):
        where = f"events[{i}]"
        r.keys(
            t, where, {"at_s", "kind", "robot", "door", "duration_s", "wheel", "fraction", "polygon"}, {"at_s", "kind"}
        )
        kind = r.req_text(t, "kind", where)
        if kind not in EVENT_KINDS:
            raise r.fail(f"{where}.kind", f"expected one of {', '.join(EVENT_KINDS)}, got {kind!r}")
        robot = t.get("robot")
        if kind in ("link_cut", "wheel_slip", "press_home"):
            robot = r.req_text(t, "robot", where)
            if robot not in names:
                raise r.fail(f"{where}.robot", f"no robot named {robot!r} in this scenario")
        door = r.req_text(t, "door", where) if kind in ("door_close", "door_open") else None
        polygon: list[tuple[float, float]] = []
        if kind == "obstacle":
            pts = t.get("polygon")
            if not (
                isinstance(pts, list)
                and len(pts) >= 3
                and all(
                    isinstance(q, list)
                    and len(q) == 2
                    and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in q)
                    for q in pts
                )
            ):
                raise r.fail(f"{where}.polygon", "expected at least 3 [x, y] points with finite numbers")
            polygon = [(float(q[0]), float(q[1])) for q in pts]
        wheel = r.opt_text(t, "wheel", where, "left")
        if wheel not in ("left", "right"):
            raise r.fail(f"{where}.wheel", "expected left or right")
        events.append(
            Event(
                r.req_num(t, "at_s", where, lo=0.0),
                kind,
                robot,
                door,
                r.opt_num(t, "duration_s", where, 0.0 if kind not in ("link_cut", "wheel_slip") else 3.0, lo=0.0),
                wheel,
                r.opt_num(t, "fraction", where, 0.5, lo=0.0, hi=1.0),
                tuple(polygon),
            )
        )
    events.sort(key=lambda e: e.at)
    return Scenario(
        name=name,
        plan=plan,
        seed=seed,
        duration=duration,
        robots=tuple(robots),
        anchors=tuple(anchors),
        noise=noise,
        lidar=lidar,
        events=tuple(events),
        truth_rate_hz=truth_rate,
        control_period=control,
        source=source,
    )
