"""Fault drills on the real agent (``AgentRuntime``), a simulated board behind a TCP "cable" the test
controls, real Zenoh peers and a real Mosquitto running deploy/'s ACL.

Each drill: nothing crashes (the agent's control thread is alive at the end), the robot is safe
(wheels stopped when they should be), nothing runs twice, and it recovers without a restart.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest
import zenoh

from fleetlink.agent.config import AgentConfig, Rates, ZenohSettings, mqtt_settings
from fleetlink.agent.runtime import AgentRuntime
from fleetlink.field.board import SimulatedBoard
from fleetlink.field.device_server import DeviceServer
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, AckResult, Teleop
from tests.faults.relay import TcpRelay
from tests.harness import wait_until
from tests.harness.deploy import DeployBroker, mosquitto_passwd
from tests.harness.mosquitto import free_port
from tests.harness.zenoh_peers import zenoh_config
from tests.test_agent_links import Operator


@dataclass
class Drill:
    agent: AgentRuntime
    board: SimulatedBoard
    relay: TcpRelay
    op: Operator
    endpoint: str

    def moving(self) -> bool:
        s = self.board.state
        return s.v_left > 0.05 and s.v_right > 0.05

    def stopped(self) -> bool:
        s = self.board.state
        return abs(s.v_left) < 0.01 and abs(s.v_right) < 0.01

    def alive(self) -> bool:
        t = self.agent._thread
        return t is not None and t.is_alive()


class Driver:
    """An operator holding the stick: a fresh teleop every 50 ms until stopped."""

    def __init__(self, op: Operator, ttl_s: float = 0.4) -> None:
        self.op, self.ttl_s = op, ttl_s
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, name="driver", daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            self.op.send(self.op.counter.make(Teleop, v=0.3, omega=0.0, ttl_s=self.ttl_s), mqtt_=False)

    def stop(self) -> None:
        self._stop.set()
        self._t.join(2.0)


@pytest.fixture
def drill() -> Iterator[Drill]:
    clock = SystemClock()
    board = SimulatedBoard()
    server = DeviceServer(board, clock, name="board")
    relay = TcpRelay(server.serve_tcp())
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = AgentConfig(
        robot="r1",
        board=f"socket://127.0.0.1:{relay.port}",
        zenoh=ZenohSettings(listen=(endpoint,)),
        rates=Rates(control_hz=50.0, pose_hz=20.0, state_hz=5.0),
    )
    agent = AgentRuntime(cfg, clock, seed=1)
    zs = None
    try:
        agent.start()
        zs = zenoh.open(zenoh_config(connect=[endpoint]))
        op = Operator(zs, None)
        zs.declare_subscriber(
            keys.zenoh_robot("r1"), lambda s: op.record("zenoh", str(s.key_expr), s.payload.to_bytes())
        )
        wait_until(lambda: agent.board.snapshot.connected, message="the agent's board link")
        wait_until(lambda: (s := op.last_state()) is not None and s.boardConnected, message="a state")
        yield Drill(agent, board, relay, op, endpoint)
    finally:
        agent.stop()
        if zs is not None:
            zs.close()
        relay.close()
        server.stop()


def test_board_link_cut_board_stops_agent_reports_and_recovers(drill: Drill) -> None:
    driver = Driver(drill.op)
    try:
        wait_until(drill.moving, message="driving")
        trips = drill.board.state.watchdog_trips
        drill.relay.blackhole()
        # The operator keeps driving; the board hears nothing and stops on its own watchdog.
        wait_until(lambda: drill.board.state.watchdog_trips > trips and drill.stopped(), message="the board's stop")
        wait_until(lambda: (s := drill.op.last_state()) is not None and not s.boardConnected, message="fault reported")
        drill.relay.restore()
        wait_until(lambda: drill.agent.board.snapshot.connected, timeout=15, message="the board link back")
        wait_until(lambda: (s := drill.op.last_state()) is not None and s.boardConnected, message="recovery reported")
        wait_until(drill.moving, message="driving again, no restart")
    finally:
        driver.stop()
    wait_until(drill.stopped, message="the stop when the operator lets go")
    assert drill.alive()


def test_garbage_on_the_board_line(drill: Drill) -> None:
    driver = Driver(drill.op)
    rng = random.Random(8)
    try:
        wait_until(drill.moving, message="driving")
        for _ in range(50):
            junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64)))
            drill.relay.inject_to_agent(junk)
            drill.relay.inject_to_device(junk)
        # Whatever the link made of it (resync or reconnect), the robot drives again.
        wait_until(lambda: drill.agent.board.snapshot.connected and drill.moving(), timeout=15, message="recovery")
    finally:
        driver.stop()
    wait_until(drill.stopped, message="the stop when the operator lets go")
    assert drill.alive()


def test_malformed_and_oversized_on_every_topic_while_driving(drill: Drill) -> None:
    topics = ["order", "actions", "teleop", "uwb", "lease/request", "state", "nope"]
    before = drill.agent.core.gate.stats.rejected_total
    driver = Driver(drill.op)
    try:
        wait_until(drill.moving, message="driving")
        for k in [f"fleetlink/v1/r1/{t}{sender}" for t in topics for sender in ("", "/operator-1")]:
            for data in (
                b"",
                b"\xc1",
                b"\x92\x01",
                b"\xff" * 300_000,
                wire.encode(drill.op.counter.make(Teleop, v=0.1, omega=0.0, ttl_s=0.5))[:-3],
            ):
                drill.op.zsession.put(k, data)
        wait_until(drill.moving, message="still driving")
    finally:
        driver.stop()
    wait_until(drill.stopped, message="the stop")
    # Input topics were counted as rejected (not crashes); the agent keeps serving.
    wait_until(lambda: drill.agent.core.gate.stats.rejected_total > before)
    assert drill.alive()


OPERATOR_SCRIPT = r"""
import json, sys, time, zenoh
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Teleop
c = zenoh.Config()
c.insert_json5("mode", '"peer"')
c.insert_json5("scouting/multicast/enabled", "false")
c.insert_json5("listen/endpoints", "[]")
c.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
s = zenoh.open(c)
counter = wire.HeaderCounter(SystemClock(), robot="r1", sender="operator-1")
k = keys.sender_key("r1", "teleop", "operator-1")
while True:
    s.put(k, wire.encode(counter.make(Teleop, v=0.3, omega=0.0, ttl_s=0.3)))
    time.sleep(0.05)
"""


def test_console_killed_while_driving(drill: Drill, tmp_path: Path) -> None:
    script = tmp_path / "console.py"
    script.write_text(OPERATOR_SCRIPT)
    proc = subprocess.Popen(
        [sys.executable, str(script), drill.endpoint], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    try:
        wait_until(lambda: drill.moving() or proc.poll() is not None, timeout=20, message="the console driving")
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        trips = drill.board.state.watchdog_trips
        os.kill(proc.pid, signal.SIGKILL)  # no goodbye, no last teleop with v=0
        proc.wait(10)
        wait_until(drill.stopped, message="the stop after the teleop time-to-live")
        # The agent stopped it (its deadman), not the board's watchdog: the agent is alive and well.
        assert drill.board.state.watchdog_trips == trips
        wait_until(lambda: (s := drill.op.last_state()) is not None and s.driveMode == "idle", message="idle")
        # A new console takes over without restarting anything.
        driver = Driver(drill.op)
        try:
            wait_until(drill.moving, message="a new console driving")
        finally:
            driver.stop()
        wait_until(drill.stopped)
        assert drill.alive()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


# ------------------------------------------------------------------------------------------------
# Security switched on: the agent logs in to a broker running deploy/'s ACL.

USERS = {"r1": "pw-r1", "r2": "pw-r2", "op-alice": "pw-alice"}


def test_unauthorised_clients_cannot_drive_over_mqtt(tmp_path: Path) -> None:
    broker = DeployBroker(tmp_path / "broker", "mosquitto.conf", passwd=mosquitto_passwd(tmp_path / "pw", USERS))
    broker.start()
    clock = SystemClock()
    board = SimulatedBoard()
    server = DeviceServer(board, clock, name="board")
    port = server.serve_tcp()
    cfg = AgentConfig(
        robot="r1",
        board=f"socket://127.0.0.1:{port}",
        zenoh=None,
        mqtt=mqtt_settings(f"mqtt://127.0.0.1:{broker.port}", "r1", "pw-r1"),
        rates=Rates(control_hz=50.0, pose_hz=20.0, state_hz=5.0),
    )
    agent = AgentRuntime(cfg, clock, seed=1)
    clients: list[mqtt.Client] = []

    def client(user: str | None, password: str | None, **callbacks: Any) -> mqtt.Client:
        c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"drill-{user}")
        if user:
            c.username_pw_set(user, password)
        for name, fn in callbacks.items():  # before connecting: a fast connect must not miss on_connect
            setattr(c, name, fn)
        c.connect_async("127.0.0.1", broker.port)
        c.loop_start()
        clients.append(c)
        return c

    try:
        agent.start()
        wait_until(lambda: agent.mqtt is not None and agent.mqtt.up and agent.board.snapshot.connected)
        acks: list[Ack] = []
        op = client(
            "op-alice",
            "pw-alice",
            on_message=lambda _c, _u, m: acks.append(wire.decode_key(m.topic, m.payload)),
            on_connect=lambda c, *_a: c.subscribe(keys.key("r1", "ack"), qos=1),
        )
        wait_until(op.is_connected)
        attackers = [client("r2", "pw-r2"), client(None, None), client("r1", "wrong")]
        wait_until(lambda: attackers[0].is_connected())
        for i, a in enumerate(attackers):
            counter = wire.HeaderCounter(clock, robot="r1", sender=f"operator-{i}")
            k = keys.sender_key("r1", "teleop", f"operator-{i}")
            for _ in range(20):
                info = a.publish(k, wire.encode(counter.make(Teleop, v=0.5, omega=0.0, ttl_s=5.0)), qos=1)
                if a.is_connected():
                    info.wait_for_publish(5)  # the broker has dealt with it before op-alice starts
        counter = wire.HeaderCounter(clock, robot="r1", sender="op-alice")
        k = keys.sender_key("r1", "teleop", "op-alice")

        def drive() -> bool:
            op.publish(k, wire.encode(counter.make(Teleop, v=0.2, omega=0.0, ttl_s=0.3)), qos=1)
            return board.state.v_left > 0.05 and any(a.commandSender == "op-alice" for a in list(acks))

        wait_until(drive, interval=0.05, message="the operator driving")
        # The agent acks every command it gets, in order: only op-alice's ever reached it.
        assert {a.commandSender for a in list(acks)} == {"op-alice"}
        assert all(a.result is AckResult.ACCEPTED for a in list(acks))
        assert agent.core.gate.stats.rejected_total == 0
        wait_until(lambda: abs(board.state.v_left) < 0.01, message="the stop")
    finally:
        for c in clients:
            c.loop_stop()
            c.disconnect()
        agent.stop()
        server.stop()
        broker.stop()
