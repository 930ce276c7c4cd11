"""The one site (fleetlink.site): the demo field composed headless, its broker launcher, the open-loop mode.

The secured site is tests/test_field_secure.py (the same ``FieldSite`` with ``security``); the
console on the demo site is the tmux e2e test (tests/e2e).
"""

from __future__ import annotations

import logging
import math
import socket
import threading
from pathlib import Path
from typing import Any

import pytest

from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, AckResult, Connection, Pose, Teleop, UwbFix
from fleetlink.site import brokers
from fleetlink.site.brokers import AmqttBroker, MosquittoBroker, free_port, start_demo_broker
from fleetlink.site.field import FieldSite
from tests.harness import wait_until
from tests.test_field_realtime import quiet_scenario


def test_demo_site_runs_agents_uwb_and_the_operator_link_on_one_broker() -> None:
    scenario = quiet_scenario(
        robots=[
            {"name": "uvc-1", "start": "living", "drive": "idle"},
            {"name": "uvc-2", "start": "bedroom", "drive": "idle"},
        ],
        lidar={"enabled": False},
    )
    said: list[str] = []
    site = FieldSite(scenario, clock=SystemClock(), operator="operator-1", say=said.append)
    got: list[tuple[Any, str]] = []
    lock = threading.Lock()
    try:
        site.start()
        # The tests' MQTT path runs on real mosquitto, never on the demo's amqtt fallback.
        assert isinstance(site.broker, MosquittoBroker) and site.broker.running
        assert said == [f"fleetlink field: MQTT on {site.mqtt_url} (embedded mosquitto)"]
        assert site.gateway is not None and site.agents is not None and site.boards is None
        link = site.link
        assert link is not None

        def sink(msg: Any, on: str, _t: float) -> None:
            with lock:
                got.append((msg, on))

        link.add_sink(sink)

        def heard(cls: type, on: str) -> bool:
            with lock:
                return any(isinstance(m, cls) and lk == on for m, lk in got)

        wait_until(lambda: heard(Pose, "zenoh") and heard(Pose, "mqtt"), timeout=15, message="poses on both links")
        wait_until(lambda: heard(UwbFix, "mqtt"), timeout=15, message="the site's UWB gateway's fixes")
        robots = {r.name: r for r in site.field.world.robots}
        start = {n: r.pose for n, r in robots.items()}

        def moved(name: str) -> float:
            a, b = start[name], robots[name].pose
            return math.hypot(b[0] - a[0], b[1] - a[1])

        sent: list[int] = []

        def drive() -> bool:
            sent.append(link.send(Teleop, "uvc-1", v=0.2, omega=0.0, ttl_s=0.5).header.headerId)
            return moved("uvc-1") > 0.05

        wait_until(drive, interval=0.1, timeout=15, message="uvc-1 moving under the operator's teleop")
        with lock:
            acks = [m for m, _ in got if isinstance(m, Ack)]
        assert any(a.commandHeaderId in sent and a.result is AckResult.ACCEPTED for a in acks)
        assert moved("uvc-2") < 0.01
        # The demo has no router: its one console's peer is where the agents connect.
        with pytest.raises(RuntimeError, match="one console"):
            site.operator_link("operator-2")
        folder = site.broker.workdir
    finally:
        site.stop()
    assert site.broker is None and not folder.exists()  # the demo broker and its folder are gone


def test_take_link_hands_the_operators_link_over() -> None:
    site = FieldSite(quiet_scenario(lidar={"enabled": False}), clock=SystemClock(), operator="operator-1", say=print)
    closed: list[bool] = []
    try:
        site.start()
        link = site.take_link()
        close = link.close
        link.close = lambda: closed.append(True)  # type: ignore[method-assign]
        with pytest.raises(RuntimeError):
            site.take_link()
    finally:
        site.stop()
    assert closed == []  # the console closes it, not the site
    close()


def test_without_agents_the_boards_are_driven_open_loop_and_no_broker_starts() -> None:
    scenario = quiet_scenario(
        robots=[{"name": "uvc-1", "start": "living", "drive": "wander"}], lidar={"enabled": False}
    )
    clock = SystemClock()
    site = FieldSite(scenario, clock=clock, agents=False, say=print).start()
    try:
        assert site.broker is None and site.agents is None and site.gateway is None and site.link is None
        assert site.boards is not None
        robot = site.field.world.robots[0]
        start = robot.pose
        t0 = clock.now()

        def moved() -> bool:
            assert site.boards is not None
            site.boards.step(clock.now() - t0)
            return math.hypot(robot.pose[0] - start[0], robot.pose[1] - start[1]) > 0.05

        wait_until(moved, interval=0.05, timeout=15, message="the wanderer moving over its board link")
    finally:
        site.stop()
    assert site.boards is None


def test_an_agent_restart_event_restarts_that_agent_in_real_time(caplog: pytest.LogCaptureFixture) -> None:
    """The scenario's ``agent_restart`` in the real-time field: uvc-2's agent is shut down as on
    SIGTERM (its retained connection OFFLINE) and a new one started, which reconnects to the same board
    and is heard again. uvc-1's, due at 0 s, before the agents are up, waits for them. Operator
    commands and link changes are refused when the site is made, as is a restart on a field without
    agents."""
    robots = [
        {"name": "uvc-1", "start": "living", "drive": "idle"},
        {"name": "uvc-2", "start": "bedroom", "drive": "idle"},
    ]
    restarts = [
        {"at_s": 0.0, "kind": "agent_restart", "robot": "uvc-1"},
        {"at_s": 2.0, "kind": "agent_restart", "robot": "uvc-2"},
    ]
    refused = {
        "teleop": {"kind": "teleop", "robot": "uvc-2", "v": 0.1, "duration_s": 1.0},
        "link": {"kind": "link", "robot": "uvc-2", "link": "mqtt", "state": "cut"},
    }
    for kind, event in refused.items():
        with pytest.raises(ValueError, match=f"this run does not carry out {kind} events"):
            FieldSite(quiet_scenario(robots=robots, events=[{"at_s": 1.0, **event}], lidar={"enabled": False}))
    with pytest.raises(ValueError, match="uvc-1's agent restarts: this run does not carry out agent_restart events"):
        FieldSite(quiet_scenario(robots=robots, events=restarts, lidar={"enabled": False}), agents=False)
    scenario = quiet_scenario(robots=robots, events=restarts, lidar={"enabled": False})
    site = FieldSite(scenario, clock=SystemClock(), operator="operator-1", say=print)
    got: list[Any] = []
    lock = threading.Lock()
    caplog.set_level(logging.WARNING, logger="fleetlink.site.agents")
    try:
        site.start()
        assert site.agents is not None and site.link is not None

        def sink(msg: Any, _on: str, _t: float) -> None:
            with lock:
                got.append(msg)

        site.link.add_sink(sink)

        def restarted(robot: str) -> bool:
            return any(r.getMessage() == f"agent {robot}: restarting" for r in caplog.records)

        wait_until(lambda: restarted("uvc-1"), timeout=10, message="uvc-1's agent restarted once the agents were up")
        assert not restarted("uvc-2")
        first = site.agents.agents["uvc-2"]

        def uvc_2_again() -> bool:
            assert site.agents is not None
            agent = site.agents.agents.get("uvc-2")
            return agent is not None and agent is not first and agent.board.snapshot.connected

        wait_until(uvc_2_again, timeout=20, message="a new agent for uvc-2, on its board")
        with lock:
            mark = len(got)

        def heard() -> bool:
            with lock:
                return any(isinstance(m, Pose) and m.header.robot == "uvc-2" for m in got[mark:])

        wait_until(heard, timeout=15, message="uvc-2's new agent heard")
        with lock:
            states = [m.connectionState.value for m in got if isinstance(m, Connection) and m.header.robot == "uvc-2"]
        assert "OFFLINE" in states and states[-1] == "ONLINE", states
        assert sum(r.getMessage().startswith("agent ") for r in caplog.records) == 2  # each once
    finally:
        site.stop()
    assert site.agents is None


def test_a_secured_site_refuses_a_broker_url_and_unknown_operators() -> None:
    from fleetlink.site.field import Security

    scenario = quiet_scenario()
    with pytest.raises(ValueError, match="own broker"):
        FieldSite(scenario, security=Security(), mqtt_url="mqtt://127.0.0.1:1883")
    with pytest.raises(ValueError, match="no account"):
        FieldSite(scenario, security=Security(("op-alice",)), operator="op-bob")


def test_demo_broker_is_amqtt_only_without_mosquitto(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(brokers, "which_mosquitto", lambda fallback=brokers.FALLBACK_BINARY: None)
    broker, what = start_demo_broker(tmp_path / "broker")
    try:
        assert isinstance(broker, AmqttBroker) and "amqtt" in what
        assert broker.url == f"mqtt://127.0.0.1:{broker.port}"
    finally:
        if broker is not None:
            broker.stop()


def test_mosquitto_restarts_on_its_port(tmp_path: Path) -> None:
    broker = MosquittoBroker(tmp_path).start()
    try:
        pid, port = broker.pid, broker.port
        broker.restart()
        assert broker.running and broker.pid != pid and broker.port == port
        assert broker.url == f"mqtt://127.0.0.1:{port}"
    finally:
        broker.stop()
    assert not broker.running


def test_a_free_port_lies_outside_the_range_outgoing_connections_take(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A port the OS picks comes from the range it hands out to outgoing connections, one of which
    may take it before its caller binds it; ``free_port`` picks below that range, a free one."""
    low = int(brokers.EPHEMERAL_RANGE.read_text().split()[0])
    ports = [free_port() for _ in range(20)]
    assert all(low - brokers.PORT_SPAN <= p < low for p in ports)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", ports[0]))  # free, as said
    # Where the range cannot be read, the OS picks.
    monkeypatch.setattr(brokers, "EPHEMERAL_RANGE", tmp_path / "missing")
    assert 0 < free_port() < 65536
