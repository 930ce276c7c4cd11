"""Every kind of configuration file goes through shared/config.py: a bad key is reported with the
file and the dotted key (uwb.toml: tests/test_uwb_gateway.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from fleetlink.agent.config import load_agent_config
from fleetlink.cli.console import add_arguments, load_settings
from fleetlink.field.plans import PlanError, load_plan
from fleetlink.field.scenario import ScenarioError, load_scenario
from fleetlink.shared.config import ConfigError


def console_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(list(argv))


def test_robot_toml(tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    path.write_text('robot = "r1"\nboard = "socket://h:1"\n[zenoh]\nconnect = ["tcp/h:7447"]\n[limits]\nv_mx = 0.3\n')
    with pytest.raises(ConfigError, match=r"robot\.toml: limits\.v_mx: unknown key \(did you mean v_max\?\)"):
        load_agent_config(path)
    path.write_text('robot = "r1"\nboard = "socket://h:1"\n[mqtt]\nurl = "mqtt://h"\nkeepalive_s = 0\n')
    with pytest.raises(ConfigError, match=r"robot\.toml: mqtt\.keepalive_s: must be >= 1, got 0"):
        load_agent_config(path)


def test_a_round_base_lets_the_guard_allow_turning_in_place(tmp_path: Path) -> None:
    from fleetlink.agent.node import pilot_config
    from fleetlink.site.agents import field_limits

    path = tmp_path / "robot.toml"
    path.write_text('robot = "r1"\nboard = "socket://h:1"\n[zenoh]\nconnect = ["tcp/h:7447"]\n')
    assert not pilot_config(load_agent_config(path)).guard.allow_turn_in_place  # the seed's rule by default
    path.write_text(
        'robot = "r1"\nboard = "socket://h:1"\n[zenoh]\nconnect = ["tcp/h:7447"]\n[limits]\nround_base = true\n'
    )
    assert pilot_config(load_agent_config(path)).guard.allow_turn_in_place
    assert field_limits("uvc-1").round_base and not field_limits("scout-1").round_base
    assert field_limits("uvc-1").creep_speed_mps > 0 and field_limits("scout-1").creep_speed_mps == 0
    assert pilot_config(load_agent_config(path)).guard.creep_speed_mps == 0.0


def test_loop_closure_on_board_can_be_turned_off(tmp_path: Path) -> None:
    from fleetlink.agent.node import mapper_config

    path = tmp_path / "robot.toml"
    path.write_text('robot = "r1"\nboard = "socket://h:1"\n[zenoh]\nconnect = ["tcp/h:7447"]\n')
    assert mapper_config(load_agent_config(path)).closer is not None  # on by default
    path.write_text(path.read_text() + "[mapping]\nloop_closure = false\n")
    assert mapper_config(load_agent_config(path)).closer is None
    path.write_text(path.read_text().replace("false", '"no"'))
    with pytest.raises(ConfigError, match=r"mapping\.loop_closure"):
        load_agent_config(path)


def test_scenario_toml(tmp_path: Path) -> None:
    path = tmp_path / "drill.toml"
    path.write_text(
        'plan = "office"\n[[robots]]\nname = "a"\nstart = "entrance"\n[[robots]]\nname = "b"\nstrat = "x"\n'
    )
    with pytest.raises(ScenarioError, match=r"drill\.toml: robots\[1\]\.strat: unknown key \(did you mean start\?\)"):
        load_scenario(path)


def test_plan_toml(tmp_path: Path) -> None:
    path = tmp_path / "lab.toml"
    path.write_text("bounds = [0, 0, 5, 5]\nwalls = []\n[starts]\nhome = { x = 1, y = 1, theta = 0 }\n")
    with pytest.raises(PlanError, match=r"lab\.toml: starts\.home\.theta: unknown key \(did you mean theta_deg\?\)"):
        load_plan(path)


def test_console_toml(tmp_path: Path) -> None:
    path = tmp_path / "console.toml"
    path.write_text('operator = "op-a"\n[zenoh]\nconect = ["tcp/h:7447"]\n')
    with pytest.raises(ConfigError, match=r"console\.toml: zenoh\.conect: unknown key \(did you mean connect\?\)"):
        load_settings(console_args("--config", str(path)))
    path.write_text('read_only = "yes"\n')
    with pytest.raises(ConfigError, match=r"console\.toml: read_only: expected true or false, got str 'yes'"):
        load_settings(console_args("--config", str(path)))
    path.write_text("[mqtt]\nport = 1883\n")
    with pytest.raises(ConfigError, match=r"console\.toml: mqtt\.port: unknown key; allowed: url"):
        load_settings(console_args("--config", str(path)))


def test_console_toml_then_the_command_line(tmp_path: Path) -> None:
    path = tmp_path / "console.toml"
    path.write_text(
        'operator = "op-a"\nread_only = true\nmarks_file = "m.json"\n'
        '[zenoh]\nconnect = ["tcp/h:7447"]\n[mqtt]\nurl = "mqtt://h:1884"\n'
    )
    s = load_settings(console_args("--config", str(path)))
    assert (s.operator, s.read_only, s.marks_file) == ("op-a", True, Path("m.json"))
    assert (s.zenoh_connect, s.zenoh_listen, s.mqtt_url) == (("tcp/h:7447",), (), "mqtt://h:1884")
    s = load_settings(console_args("--config", str(path), "--operator", "op-b", "--mqtt", "mqtt://k"))
    assert (s.operator, s.mqtt_url, s.zenoh_connect) == ("op-b", "mqtt://k", ("tcp/h:7447",))


def test_console_links_table(tmp_path: Path) -> None:
    path = tmp_path / "console.toml"
    assert load_settings(console_args()).links.policy().redundant  # redundant sending by default
    path.write_text("[links]\nredundant = false\ndegraded_rtt_s = 0.2\n")
    policy = load_settings(console_args("--config", str(path))).links.policy()
    assert not policy.redundant and policy.degraded_rtt_s == 0.2 and policy.degraded_loss_pct == 5.0
    path.write_text("[links]\ndegraded_loss_pct = 150.0\n")
    with pytest.raises(ConfigError, match=r"console\.toml: links\.degraded_loss_pct: must be <= 100"):
        load_settings(console_args("--config", str(path)))
