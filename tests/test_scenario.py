from __future__ import annotations

import math
from pathlib import Path

import pytest

from fleetlink.field.build import lidar_model
from fleetlink.field.scenario import ScenarioError, load_scenario, parse_scenario

MINIMAL = {"plan": "apartment", "robots": [{"name": "r1", "start": "dock"}]}


def test_minimal_scenario_gets_documented_defaults() -> None:
    sc = parse_scenario(MINIMAL)
    assert sc.plan == "apartment"
    assert sc.seed == 0 and sc.duration == 60.0
    assert sc.robots[0].drive == "wander" and sc.robots[0].start == "dock"
    assert sc.lidar.enabled and sc.lidar.rate_hz == 10.0
    assert sc.noise.wheel_scale_sd == 0.01


def test_the_sites_uwb_can_be_off_whatever_the_anchors() -> None:
    plan_anchors = [("A1", 0.0, 0.0, 2.4), ("A2", 5.0, 0.0, 2.4), ("A3", 0.0, 5.0, 2.4)]
    on = parse_scenario(MINIMAL)
    assert on.uwb and on.uwb_anchors(plan_anchors) == tuple(plan_anchors)  # the plan's
    own = parse_scenario({**MINIMAL, "anchors": [{"id": "B1", "x": 1.0, "y": 2.0, "z": 3.0}]})
    assert own.uwb_anchors(plan_anchors) == (("B1", 1.0, 2.0, 3.0),)  # the scenario's instead
    off = parse_scenario({**MINIMAL, "uwb": False, "anchors": [{"id": "B1", "x": 1.0, "y": 2.0, "z": 3.0}]})
    assert not off.uwb and off.uwb_anchors(plan_anchors) == ()


def test_full_scenario_parses_every_field(tmp_path: Path) -> None:
    path = tmp_path / "drill.toml"
    path.write_text(
        """
name = "drill"
plan = "plans/custom.toml"
seed = 7
duration_s = 12.5
[noise]
gyro_bias_sd = 0.0
[lidar]
rate_hz = 5.5
samples_per_second = 2000.0
[[robots]]
name = "a"
pose = [1.0, 2.0, 90.0]
drive = "script"
script = [[0.0, 0.2, 0.0], [2.0, 0.0, 0.5]]
[[robots]]
name = "b"
start = "entrance"
[[anchors]]
id = "A1"
x = 0.0
y = 0.0
[[events]]
at_s = 5.0
kind = "link_cut"
robot = "a"
[[events]]
at_s = 1.0
kind = "obstacle"
polygon = [[1, 1], [2, 1], [2, 2]]
"""
    )
    sc = load_scenario(path)
    assert sc.name == "drill" and sc.seed == 7 and sc.duration == 12.5
    assert sc.plan == str((tmp_path / "plans/custom.toml").resolve())
    assert sc.robots[0].pose == pytest.approx((1.0, 2.0, math.pi / 2))
    assert sc.robots[0].script[1] == (2.0, 0.0, 0.5)
    assert sc.anchors == (("A1", 0.0, 0.0, 2.4),)
    assert [e.kind for e in sc.events] == ["obstacle", "link_cut"]  # sorted by time
    assert sc.events[1].duration == 3.0  # the documented default for a link cut
    assert sc.lidar.rate_hz == 5.5 and sc.noise.gyro_bias_sd == 0.0
    assert sc.lidar.samples_per_second == 2000.0
    model = lidar_model(sc, sc.robots[0], 0)
    assert model is not None and model.config.samples_per_revolution == pytest.approx(2000.0 / 5.5)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"plan": None}, "bad.toml: plan: missing required key"),
        ({"colour": "red"}, "bad.toml: colour: unknown key; allowed: anchors,"),
        ({"seed": -1}, "seed"),
        ({"duration_s": float("nan")}, "duration_s: must be finite"),
        ({"robots": []}, "bad.toml: robots: needs at least 1 item, got 0"),
        ({"robots": [{"name": "r1"}]}, "exactly one of start"),
        ({"robots": [{"name": "r1", "start": "dock"}, {"name": "r1", "start": "dock"}]}, "appears twice"),
        ({"robots": [{"name": "r1", "pose": [0, 0]}]}, "robots[0].pose"),
        ({"robots": [{"name": "r1", "start": "dock", "drive": "fly"}]}, "robots[0].drive"),
        ({"robots": [{"name": "r1", "start": "dock", "drive": "script"}]}, "needs a script"),
        ({"events": [{"at_s": 1.0, "kind": "earthquake"}]}, "events[0].kind"),
        ({"events": [{"at_s": 1.0, "kind": "link_cut", "robot": "ghost"}]}, "no robot named 'ghost'"),
        ({"events": [{"at_s": 1.0, "kind": "obstacle", "polygon": [[0, 0], [1, 1]]}]}, "events[0].polygon"),
        ({"noise": {"lidar_dropout": 2.0}}, "probability"),
        ({"lidar": {"rate_hz": 100.0}}, "lidar.rate_hz"),
        ({"lidar": {"samples_per_second": 10.0}}, "lidar.samples_per_second"),
        ({"uwb": "off"}, "uwb"),
    ],
)
def test_bad_scenarios_are_refused_with_the_key_and_reason(change: dict[str, object], message: str) -> None:
    data = dict(MINIMAL)
    for k, v in change.items():
        if v is None:
            data.pop(k)
        else:
            data[k] = v
    with pytest.raises(ScenarioError) as err:
        parse_scenario(data, source="bad.toml")
    assert message in str(err.value)
    assert str(err.value).startswith("bad.toml: ")


def test_unreadable_and_invalid_toml_files_are_reported(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("plan = \n")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(bad)
