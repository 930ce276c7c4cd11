"""shared/config.py: the one configuration mechanism, error by error."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, ClassVar, Literal

import pytest

from fleetlink.shared.config import ConfigError, Invalid, Setting, describe, load, loads, parse


class Mode(enum.Enum):
    FAST = "fast"
    SLOW = "slow"


@dataclass(frozen=True, slots=True)
class Lidar:
    rate_hz: Annotated[float, Setting(lo=1.0, hi=20.0, doc="turns a second")] = 10.0
    enabled: bool = True


@dataclass(frozen=True, slots=True)
class Robot:
    name: Annotated[str, Setting(min_len=1)]
    lidar: Lidar = field(default_factory=Lidar)
    drive: Literal["wander", "script", "idle"] = "wander"
    script: tuple[tuple[float, float, float], ...] = ()
    tag: str | None = None
    heading: Annotated[float, Setting(key="heading_deg", convert=math.radians)] = 0.0

    def validate(self) -> None:
        if self.drive == "script" and not self.script:
            raise Invalid("script", 'drive = "script" needs a script')


class PlanishError(ConfigError):
    pass


@dataclass(frozen=True, slots=True)
class Door:
    kind: ClassVar[str] = "door"
    at: Annotated[float, Setting(key="at_s", lo=0.0)]
    door: str


@dataclass(frozen=True, slots=True)
class Slip:
    kind: ClassVar[str] = "slip"
    at: Annotated[float, Setting(key="at_s", lo=0.0)]
    fraction: Annotated[float, Setting(lo=0.0, hi=1.0)] = 0.5


@dataclass(frozen=True, slots=True)
class Site:
    robots: Annotated[tuple[Robot, ...], Setting(min_len=1)]
    seed: Annotated[int, Setting(lo=0)] = 0
    mode: Mode = Mode.FAST
    bounds: Annotated[tuple[float, float, float, float], Setting(what="[xmin, ymin, xmax, ymax]")] = (0, 0, 1, 1)
    doors: dict[str, tuple[float, float]] = field(default_factory=dict)
    events: tuple[Door | Slip, ...] = ()
    source: Annotated[str, Setting(read=False)] = "<memory>"

    def validate(self) -> None:
        names = [r.name for r in self.robots]
        for i, name in enumerate(names):
            if name in names[:i]:
                raise Invalid(f"robots[{i}].name", f"robot {name!r} appears twice")


def fails(data: dict[str, object], source: str = "site.toml") -> str:
    with pytest.raises(ConfigError) as err:
        parse(data, Site, source=source)
    return str(err.value)


R = {"name": "r1"}


def test_a_good_file_builds_the_dataclasses_with_defaults_and_conversions() -> None:
    site = parse(
        {
            "robots": [{"name": "r1", "heading_deg": 90, "lidar": {"rate_hz": 5}}, {"name": "r2", "tag": "t2"}],
            "mode": "slow",
            "doors": {"d1": [1, 2]},
            "events": [{"kind": "slip", "at_s": 2}, {"kind": "door", "at_s": 1, "door": "d1"}],
        },
        Site,
    )
    assert site.robots[0].heading == pytest.approx(math.pi / 2)
    assert site.robots[0].lidar == Lidar(5.0, True) and isinstance(site.robots[0].lidar.rate_hz, float)
    assert site.robots[1].lidar == Lidar() and site.robots[1].tag == "t2" and site.robots[0].tag is None
    assert site.mode is Mode.SLOW and site.doors == {"d1": (1.0, 2.0)}
    assert site.events == (Slip(2.0), Door(1.0, "d1"))
    assert site.source == "<memory>"


@pytest.mark.parametrize(
    ("data", "message"),
    [
        # unknown keys, at any depth, with the closest known key suggested
        ({"robots": [R], "sed": 1}, "site.toml: sed: unknown key (did you mean seed?); allowed: bounds, doors,"),
        (
            {"robots": [R, R, {"name": "r3", "lidar": {"rate_hzz": 5}}]},
            "site.toml: robots[2].lidar.rate_hzz: unknown key (did you mean rate_hz?); allowed: enabled, rate_hz",
        ),
        ({"robots": [R], "colour": 1}, "colour: unknown key; allowed:"),
        ({"robots": [R], "source": "x"}, "source: unknown key"),  # filled by the program, not the file
        # missing required keys
        ({}, "site.toml: robots: missing required key"),
        ({"robots": [{"lidar": {}}]}, "site.toml: robots[0].name: missing required key"),
        ({"robots": [R], "events": [{"kind": "door", "at_s": 1}]}, "events[0].door: missing required key"),
        ({"robots": [R], "events": [{"at_s": 1}]}, "events[0].kind: missing required key (one of door, slip)"),
        # wrong types
        ({"robots": [R], "seed": 1.5}, "seed: expected a whole number, got float 1.5"),
        ({"robots": [R], "seed": True}, "seed: expected a whole number, got bool True"),
        ({"robots": [{"name": 3}]}, "robots[0].name: expected a string, got int 3"),
        ({"robots": [{"name": "r", "lidar": {"enabled": 1}}]}, "robots[0].lidar.enabled: expected true or false"),
        ({"robots": [{"name": "r", "lidar": {"rate_hz": "5"}}]}, "robots[0].lidar.rate_hz: expected a number, got str"),
        ({"robots": [{"name": "r", "lidar": 5}]}, "robots[0].lidar: expected a table, got int 5"),
        ({"robots": R}, "robots: expected an array of tables, got a table"),
        ({"robots": [R], "bounds": [0, 0, 1]}, "bounds: expected [xmin, ymin, xmax, ymax], got [0, 0, 1]"),
        ({"robots": [R], "bounds": [0, 0, 1, "x"]}, "bounds[3]: expected a number, got str 'x'"),
        ({"robots": [{"name": "r", "script": [[0, 1, math.inf]]}]}, "robots[0].script[0][2]: must be finite, got inf"),
        ({"robots": [R], "doors": {"d1": [1]}}, "doors.d1: expected a list of 2 values"),
        ({"robots": [R], "doors": [1]}, "doors: expected a table, got [1]"),
        # out of range, empty, too few
        ({"robots": [{"name": "r", "lidar": {"rate_hz": 50}}]}, "robots[0].lidar.rate_hz: must be <= 20.0, got 50.0"),
        ({"robots": [R], "seed": -1}, "seed: must be >= 0, got -1"),
        ({"robots": [{"name": ""}]}, "robots[0].name: must not be empty"),
        ({"robots": []}, "robots: needs at least 1 item, got 0"),
        ({"robots": [R], "events": [{"kind": "slip", "at_s": 1, "fraction": 2}]}, "events[0].fraction: must be <="),
        # choices
        ({"robots": [{"name": "r", "drive": "wandr"}]}, "robots[0].drive: expected one of wander, script, idle, got 'wandr' (did you mean wander?)"),
        ({"robots": [R], "mode": "fastest"}, "mode: expected one of fast, slow, got 'fastest' (did you mean fast?)"),
        ({"robots": [R], "events": [{"kind": "dor", "at_s": 1}]}, "events[0].kind: expected one of door, slip, got 'dor' (did you mean door?)"),
        # post-validation hooks, at the section's depth
        ({"robots": [R, {"name": "r2", "drive": "script"}]}, 'robots[1].script: drive = "script" needs a script'),
        ({"robots": [R, R]}, "site.toml: robots[1].name: robot 'r1' appears twice"),
    ],
)  # fmt: skip
def test_each_kind_of_error_names_the_file_the_dotted_key_and_the_problem(
    data: dict[str, object], message: str
) -> None:
    assert message in fails(data)
    assert fails(data).startswith("site.toml: ")


def test_error_carries_its_parts_and_a_chosen_error_class() -> None:
    with pytest.raises(PlanishError) as err:
        parse({"robots": [{"name": "r", "lidar": {"rate_hz": 0}}]}, Site, source="s.toml", error=PlanishError)
    assert (err.value.source, err.value.key) == ("s.toml", "robots[0].lidar.rate_hz")
    assert err.value.problem == "must be >= 1.0, got 0.0"
    assert isinstance(err.value, ConfigError) and isinstance(err.value, ValueError)


def test_where_prefixes_keys_of_a_table_read_on_its_own() -> None:
    with pytest.raises(ConfigError, match=r"^robot\.toml: lidar\.rate_hz: must be >= 1\.0"):
        parse({"rate_hz": 0.5}, Lidar, source="robot.toml", where="lidar")


def test_load_and_loads_name_the_file(tmp_path: Path) -> None:
    path = tmp_path / "site.toml"
    path.write_text('[[robots]]\nname = "r1"\n[[robots]]\nname = "r2"\nlidar = { rate_hz = 99 }\n')
    with pytest.raises(ConfigError, match=r"site\.toml: robots\[1\]\.lidar\.rate_hz: must be <= 20\.0, got 99\.0"):
        load(path, Site)
    with pytest.raises(ConfigError, match="cannot read"):
        load(tmp_path / "missing.toml", Site)
    path.write_text("robots = \n")
    with pytest.raises(ConfigError, match=r"site\.toml: not valid TOML"):
        load(path, Site)
    assert loads('[[robots]]\nname = "r1"\n', Site).robots[0].name == "r1"
    with pytest.raises(ConfigError, match=r"^inline: top level: not valid TOML"):
        loads("x = ", Site, source="inline")


def test_describe_lists_every_key_with_type_default_limits_and_doc() -> None:
    lines = describe(Robot)
    assert "name  string  required" in lines
    assert "lidar.rate_hz  float  default 10.0  in [1.0, 20.0]  # turns a second" in lines
    assert "drive  'wander' | 'script' | 'idle'  default 'wander'" in lines
    assert any(line.startswith("heading_deg  float") for line in lines)
    assert any(line.startswith("events  [[door | slip]]  default []") for line in describe(Site))
