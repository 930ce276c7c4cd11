"""The UWB gateway's pure core and its configuration: no brokers."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from fleetlink.cli.main import main
from fleetlink.field.scenario import site_geometry
from fleetlink.positioning.anchors import Anchor
from fleetlink.positioning.config import ConfigError, GatewayConfig, TagSpec, load_config, parse_config
from fleetlink.positioning.gateway import GatewayCore, pans_location, pans_topic, status_topic
from fleetlink.positioning.ranging import NoiseProfile
from fleetlink.shared import wire
from fleetlink.shared.messages import FixStatus, UwbFix, UwbRanges

ANCHORS = (
    Anchor("A", 0.0, 0.0, 2.5),
    Anchor("B", 10.0, 0.0, 2.5),
    Anchor("C", 10.0, 8.0, 2.5),
    Anchor("D", 0.0, 8.0, 2.5),
)
WALL0 = 1_767_225_600.0


def core(**kw) -> GatewayCore:
    base = {
        "anchors": ANCHORS,
        "tags": (TagSpec("0d7f", "r1", 0.3),),
        "profile": NoiseProfile.los(),
        "gateway_id": "gw1",
    }
    base.update(kw)
    return GatewayCore(GatewayConfig(**base))


def by_topic(pubs):
    return {p.topic: p for p in pubs}


def test_tick_publishes_native_fix_ranges_and_pans() -> None:
    c = core()
    assert c.on_truth("r1", 3.0, 4.0, now=10.0)
    pubs = by_topic(c.tick(now=10.05, wall=WALL0 + 0.05))
    assert set(pubs) == {"fleetlink/v1/r1/uwb", "fleetlink/v1/r1/uwb/ranges", "dwm/node/0d7f/uplink/location"}

    fix = wire.decode_key("fleetlink/v1/r1/uwb", pubs["fleetlink/v1/r1/uwb"].payload)
    assert isinstance(fix, UwbFix)
    assert fix.header.robot == "r1" and fix.header.sender == "gw1" and fix.header.headerId == 0
    assert fix.tag == "0d7f" and fix.status is FixStatus.OK and fix.z == 0.3
    assert math.hypot(fix.x - 3.0, fix.y - 4.0) < 0.4
    assert fix.measured_at == WALL0 + 0.05 and 0 < fix.sd_x < 0.3 and 0 <= fix.quality <= 100
    assert set(fix.anchors) <= {"A", "B", "C", "D"} and len(fix.anchors) >= 3
    assert pubs["fleetlink/v1/r1/uwb"].qos == 0 and not pubs["fleetlink/v1/r1/uwb"].retain

    ranges = wire.decode_key("fleetlink/v1/r1/uwb/ranges", pubs["fleetlink/v1/r1/uwb/ranges"].payload)
    assert isinstance(ranges, UwbRanges) and ranges.measured_at == fix.measured_at
    assert {r.anchor for r in ranges.ranges} == {"A", "B", "C", "D"}

    pans = pubs["dwm/node/0d7f/uplink/location"]
    assert pans.qos == 0 and pans.retain
    doc = json.loads(pans.payload)
    assert list(doc) == ["position", "superFrameNumber", "timestamp"]
    assert list(doc["position"]) == ["x", "y", "z", "quality"]
    assert doc["position"]["x"] == round(fix.x, 3) and doc["position"]["quality"] == fix.quality
    assert doc["timestamp"] == str(round((WALL0 + 0.05) * 1e6)) and doc["timestamp"].isdigit()

    c.on_truth("r1", 3.1, 4.0, now=10.1)
    again = by_topic(c.tick(now=10.15, wall=WALL0 + 0.15))
    assert wire.decode(UwbFix, again["fleetlink/v1/r1/uwb"].payload).header.headerId == 1
    assert json.loads(again[pans.topic].payload)["superFrameNumber"] == doc["superFrameNumber"] + 1


def test_pans_payload_exactly_as_documented() -> None:
    assert pans_location(3.25, -0.009, 0.425, 21, 1144, 1679495047.880989) == (
        b'{"position":{"x":3.25,"y":-0.009,"z":0.425,"quality":21},'
        b'"superFrameNumber":1144,"timestamp":"1679495047880989"}'
    )
    assert pans_topic("dwm", "0d7f") == "dwm/node/0d7f/uplink/location"
    assert status_topic("gw1") == "fleetlink/uwb/gw1/status"


def test_unknown_robot_bad_pose_and_stale_truth_give_no_fix() -> None:
    c = core()
    assert not c.on_truth("stranger", 1.0, 1.0, now=0.0)
    assert not c.on_truth("r1", math.nan, 1.0, now=0.0)
    assert c.tick(now=0.1, wall=WALL0) == []
    assert c.counts["truth_unknown_robot"] == 1 and c.counts["truth_rejected"] == 1
    c.on_truth("r1", 1.0, 1.0, now=0.0)
    assert c.tick(now=5.0, wall=WALL0 + 5) == []  # 5 s old, timeout 1 s: the robot is gone
    assert c.counts["truth_stale"] == 1


def test_auto_tags_name_the_tag_after_the_robot() -> None:
    c = core(tags=(), auto_tags=True)
    assert c.on_truth("scout-2", 5.0, 5.0, now=0.0)
    assert "dwm/node/scout-2/uplink/location" in by_topic(c.tick(now=0.1, wall=WALL0))


def test_refused_fix_is_counted_not_published() -> None:
    line = tuple(Anchor(f"L{i}", 3.0 * i, 0.0, 2.5) for i in range(4))
    c = core(anchors=line)
    c.on_truth("r1", 4.0, 3.0, now=0.0)
    pubs = by_topic(c.tick(now=0.05, wall=WALL0))
    assert set(pubs) == {"fleetlink/v1/r1/uwb/ranges"}
    assert c.counts["fix_degenerate_geometry"] == 1


def test_truth_is_carried_forward_to_the_ranging_instant() -> None:
    c = core(profile=NoiseProfile.none())
    c.on_truth("r1", 3.0, 4.0, now=0.0, theta=math.pi / 2, v=1.0)
    fix = wire.decode(UwbFix, by_topic(c.tick(now=0.05, wall=WALL0))["fleetlink/v1/r1/uwb"].payload)
    assert fix.x == pytest.approx(3.0, abs=1e-3) and fix.y == pytest.approx(4.05, abs=1e-3)


def test_same_seed_same_fixes_whatever_other_tags_exist() -> None:
    def run(tags):
        c = core(tags=tags, seed=7, profile=NoiseProfile.realistic())
        out = []
        for k in range(5):
            for t in tags:
                c.on_truth(t.robot, 2.0 + k, 3.0, now=k * 0.1)
            pubs = by_topic(c.tick(now=k * 0.1 + 0.01, wall=WALL0 + k))
            out.append(pubs["dwm/node/0d7f/uplink/location"].payload)
        return out

    one = run((TagSpec("0d7f", "r1"),))
    assert one == run((TagSpec("0d7f", "r1"),))
    assert one == run((TagSpec("aaaa", "r0"), TagSpec("0d7f", "r1")))


def test_status_payload() -> None:
    c = core()
    p = c.status("online", WALL0)
    assert p.topic == "fleetlink/uwb/gw1/status" and p.retain and p.qos == 1
    doc = json.loads(p.payload)
    assert doc["state"] == "online" and doc["gateway"] == "gw1" and doc["tags"] == {"0d7f": "r1"}


# --------------------------------------------------------------------------------------------------
# configuration


def test_config_from_plan_and_from_file(tmp_path: Path) -> None:
    cfg = parse_config({"plan": "office", "gateway": {"auto_tags": True}}, site=site_geometry)
    assert len(cfg.anchors) == 10 and cfg.anchors[0] == Anchor("A1", 0.2, 0.2, 2.7)
    assert cfg.profile == NoiseProfile.realistic() and cfg.rate_hz == 10.0
    path = tmp_path / "uwb.toml"
    path.write_text(
        """
scenario = "demo"
[gateway]
id = "gw-a"
rate_hz = 5
[[tags]]
id = "0d7f"
robot = "r1"
z = 0.25
[noise]
profile = "los"
antenna_delay_m = 0.2
use_walls = true
[mqtt]
url = "mqtt://user:secret@127.0.0.1:18830"
[zenoh]
connect = ["tcp/127.0.0.1:7447"]
"""
    )
    cfg = load_config(path, site=site_geometry)
    assert cfg.gateway_id == "gw-a" and cfg.rate_hz == 5.0 and cfg.tags == (TagSpec("0d7f", "r1", 0.25),)
    assert cfg.profile.antenna_delay_m == 0.2 and cfg.profile.use_walls and cfg.walls is not None
    assert (cfg.mqtt.host, cfg.mqtt.port, cfg.mqtt.username, cfg.mqtt.password) == (
        "127.0.0.1",
        18830,
        "user",
        "secret",
    )
    assert cfg.zenoh_connect == ("tcp/127.0.0.1:7447",)
    assert len(cfg.anchors) == 5  # the demo scenario's apartment


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"plan": "office"}, r"tags: no \[\[tags\]\]"),
        ({"tags": [{"id": "t", "robot": "r1"}]}, "anchors: need at least 3 anchors, got 0"),
        ({"plan": "nowhere", "gateway": {"auto_tags": True}}, "plan: "),
        ({"plan": "office", "gateway": {"auto_tags": True, "rate_hz": 0}}, r"gateway.rate_hz: must be >= 0.1"),
        (
            {"plan": "office", "gateway": {"auto_tags": True, "bogus": 1}},
            r"gateway\.bogus: unknown key; allowed: auto_tags",
        ),
        ({"plan": "office", "tags": [{"id": "a/b", "robot": "r1"}]}, r"tags\[0\].id"),
        ({"plan": "office", "tags": [{"id": "t", "robot": "sim"}]}, r"tags\[0\].robot: .*reserved"),
        (
            {"plan": "office", "tags": [{"id": "t", "robot": "r1"}, {"id": "t", "robot": "r2"}]},
            "appears twice",
        ),
        ({"plan": "office", "gateway": {"auto_tags": True}, "noise": {"profile": "awful"}}, "noise.profile"),
        ({"plan": "office", "gateway": {"auto_tags": True}, "noise": {"nlos_ratio": 2}}, "probability"),
        ({"plan": "office", "gateway": {"auto_tags": True}, "noise": {"sigma_m": "big"}}, "expected a number"),
        ({"plan": "office", "gateway": {"auto_tags": True}, "mqtt": {"url": "ws://h"}}, "mqtt.url: .*scheme"),
        ({"plan": "office", "gateway": {"auto_tags": True}, "mqtt": {"url": "mqtt://h", "ca_file": "x"}}, "mqtt"),
        ({"plan": "office", "gateway": {"auto_tags": True}, "zenoh": {"username": "u"}}, "zenoh: username"),
        ({"plan": "office", "gateway": {"auto_tags": True}, "zenoh": {"connect": "tcp/x"}}, "zenoh.connect"),
        (
            {"anchors": [{"id": "A", "x": 0, "y": 0, "z": 2}] * 3, "gateway": {"auto_tags": True}},
            r"anchors\[1\].id: anchor 'A' appears twice",
        ),
        (
            {
                "anchors": [{"id": c, "x": 0, "y": 0, "z": 2} for c in "ABC"],
                "gateway": {"auto_tags": True},
                "noise": {"use_walls": True},
            },
            "needs a plan",
        ),
    ],
)
def test_bad_config_gets_a_clear_error(data, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        parse_config(data, source="uwb.toml", site=site_geometry)


def test_cli_reports_bad_config_and_checks_a_good_one(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('plan = "office"\n[gateway]\nrate_hz = "fast"\n')
    assert main(["uwb", "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.toml: gateway.rate_hz: expected a number" in err
    assert main(["uwb", "--config", str(tmp_path / "missing.toml")]) == 2
    assert "cannot read" in capsys.readouterr().err
    good = tmp_path / "good.toml"
    good.write_text('plan = "office"\n[gateway]\nauto_tags = true\n')
    assert main(["uwb", "--config", str(good), "--check"]) == 0
    assert "10 anchors" in capsys.readouterr().out


def test_positioning_reads_no_field_files_itself() -> None:
    """No positioning -> field import: the caller passes the plan/scenario reader in."""
    import subprocess
    import sys

    code = "import sys, fleetlink.positioning.config, fleetlink.positioning.gateway; print(sorted(m for m in sys.modules if m.startswith('fleetlink.field')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    with pytest.raises(ConfigError, match=r"^uwb\.toml: plan: this program reads no plans or scenarios"):
        parse_config({"plan": "office", "gateway": {"auto_tags": True}}, source="uwb.toml")


def test_a_bad_key_in_uwb_toml_names_the_file_and_the_key(tmp_path: Path) -> None:
    path = tmp_path / "uwb.toml"
    path.write_text('plan = "office"\n[gateway]\nauto_tags = true\n[noise]\nsigma = 0.2\n')
    with pytest.raises(ConfigError, match=r"uwb\.toml: noise\.sigma: unknown key \(did you mean sigma_m\?\)"):
        load_config(path, site=site_geometry)
