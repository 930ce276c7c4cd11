"""Link drills on the real agent (``AgentRuntime``): Zenoh peers partitioned, the broker SIGKILLed and
restarted, the agent's broker connection severed. An operator drives throughout, sending every
teleop on both links; each drill checks that every command ran exactly once (one ACCEPTED ack, the
other copy a DUPLICATE or lost with its link), the robot stops when the operator lets go, and each
link comes back by itself: the agent is never restarted.
"""

from __future__ import annotations

import contextlib
import threading
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
import zenoh

from fleetlink.agent.config import AgentConfig, Rates, ZenohSettings, mqtt_settings
from fleetlink.agent.runtime import AgentRuntime
from fleetlink.field.board import SimulatedBoard
from fleetlink.field.device_server import DeviceServer
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import AckResult, Connection, ConnectionState, Teleop
from tests.faults.relay import TcpRelay
from tests.harness import wait_until
from tests.harness.mosquitto import MosquittoBroker, free_port
from tests.harness.zenoh_peers import zenoh_config
from tests.test_agent_links import Operator


class Stick:
    """The operator holding the stick: a fresh teleop every 50 ms on both links until released."""

    def __init__(self, op: Operator) -> None:
        self.op = op
        self.sent: list[int] = []
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, name="stick", daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            m = self.op.counter.make(Teleop, v=0.2, omega=0.0, ttl_s=0.4)
            self.sent.append(m.header.headerId)
            with contextlib.suppress(Exception):  # a link that is down may refuse it: the other carries it
                self.op.send(m)

    def release(self) -> None:
        self._stop.set()
        self._t.join(2.0)

    def accepted(self, link: str | None = None) -> Counter[int]:
        with self.op.lock:
            return Counter(
                a.commandHeaderId
                for lk, a in self.op.acks
                if a.commandTopic == "teleop" and a.result is AckResult.ACCEPTED and link in (None, lk)
            )

    def received(self) -> set[int]:
        """Commands the agent ran: ACCEPTED on a link, or DUPLICATE (``already received on`` the other)
        and not REJECTED on either. A copy ACCEPTED on MQTT just before the broker dies loses its ack
        with the broker; the Zenoh copy's DUPLICATE is then the agent's word that it had it."""
        with self.op.lock:
            teleops = [a for _, a in self.op.acks if a.commandTopic == "teleop"]
        refused = {a.commandHeaderId for a in teleops if a.result is AckResult.REJECTED}
        return {
            a.commandHeaderId
            for a in teleops
            if a.result is AckResult.ACCEPTED or (a.result is AckResult.DUPLICATE and a.commandHeaderId not in refused)
        }

    def acked_since(self, link: str, n: int) -> bool:
        """A command sent after the first ``n`` was acked on ``link``."""
        later = set(self.sent[n:])
        with self.op.lock:
            return any(lk == link and a.commandHeaderId in later for lk, a in self.op.acks)


@dataclass
class Rig:
    agent: AgentRuntime
    board: SimulatedBoard
    op: Operator
    broker: MosquittoBroker
    zenoh_relay: TcpRelay
    mqtt_relay: TcpRelay
    connection: list[ConnectionState]

    def stopped(self) -> bool:
        s = self.board.state
        return abs(s.v_left) < 0.01 and abs(s.v_right) < 0.01

    def moving(self) -> bool:
        return self.board.state.v_left > 0.05

    def alive(self) -> bool:
        t = self.agent._thread
        return t is not None and t.is_alive()


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    clock = SystemClock()
    broker = MosquittoBroker(tmp_path / "broker").start()
    board = SimulatedBoard()
    server = DeviceServer(board, clock, name="board")
    board_port = server.serve_tcp()
    endpoint_port = free_port()
    zenoh_relay = TcpRelay(endpoint_port)  # the operator reaches the agent's Zenoh listener through it
    mqtt_relay = TcpRelay(broker.port)  # the agent reaches the broker through it
    cfg = AgentConfig(
        robot="r1",
        board=f"socket://127.0.0.1:{board_port}",
        zenoh=ZenohSettings(listen=(f"tcp/127.0.0.1:{endpoint_port}",)),
        mqtt=mqtt_settings(f"mqtt://127.0.0.1:{mqtt_relay.port}"),
        rates=Rates(control_hz=50.0, pose_hz=20.0, state_hz=5.0),
    )
    agent = AgentRuntime(cfg, clock, seed=1)
    zs = None
    mc = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="operator-1")
    connection: list[ConnectionState] = []
    try:
        agent.start()
        zs = zenoh.open(zenoh_config(connect=[f"tcp/127.0.0.1:{zenoh_relay.port}"]))
        op = Operator(zs, mc)
        zs.declare_subscriber(
            keys.zenoh_robot("r1"), lambda s: op.record("zenoh", str(s.key_expr), s.payload.to_bytes())
        )

        def on_message(_c: object, _u: object, m: mqtt.MQTTMessage) -> None:
            if m.topic == keys.key("r1", "connection"):
                msg = wire.decode_key(m.topic, m.payload)
                assert isinstance(msg, Connection)
                with op.lock:
                    connection.append(msg.connectionState)
            else:
                op.record("mqtt", m.topic, bytes(m.payload))

        mc.on_message = on_message
        mc.on_connect = lambda c, *_: c.subscribe(keys.mqtt_robot("r1"), qos=1)  # again after every reconnect
        mc.reconnect_delay_set(0.1, 0.5)  # type: ignore[arg-type]
        mc.connect_async("127.0.0.1", broker.port)
        mc.loop_start()
        wait_until(lambda: agent.board.snapshot.connected, message="the agent's board link")
        wait_until(
            lambda: any(lk == "zenoh" for lk, _ in list(op.states)) and any(lk == "mqtt" for lk, _ in list(op.states)),
            message="states on both links",
        )
        wait_until(lambda: ConnectionState.ONLINE in connection, message="ONLINE on the connection topic")
        yield Rig(agent, board, op, broker, zenoh_relay, mqtt_relay, connection)
    finally:
        mc.loop_stop()
        mc.disconnect()
        agent.stop()
        if zs is not None:
            zs.close()
        zenoh_relay.close()
        mqtt_relay.close()
        server.stop()
        broker.stop()


def _finish(rig: Rig, stick: Stick) -> None:
    """Release the stick; the robot stops; every command ran exactly once; the agent is alive."""
    stick.release()
    wait_until(rig.stopped, message="the stop when the operator lets go")
    sent = list(stick.sent)
    # Every teleop reached the agent on at least one link (acks can trail): none lost.
    wait_until(lambda: set(sent) <= stick.received(), timeout=10, message="an ack for every command")
    twice = {h: n for h, n in stick.accepted().items() if n > 1}
    assert not twice, f"commands run more than once: {twice}"
    assert rig.alive()


def test_zenoh_partitioned_commands_keep_arriving_over_mqtt_and_zenoh_recovers(rig: Rig) -> None:
    zlink = rig.agent.zenoh
    stick = Stick(rig.op)
    try:
        wait_until(rig.moving, message="driving")
        wait_until(lambda: stick.acked_since("zenoh", 0), message="acks on zenoh")
        rig.zenoh_relay.unplug()  # the operator's and the robot's Zenoh peers are partitioned
        n = len(stick.sent)
        wait_until(lambda: stick.acked_since("mqtt", n + 3), message="commands arriving over MQTT")
        n = len(stick.sent)
        wait_until(lambda: len(stick.sent) > n + 10)  # half a second more of partition
        assert rig.moving()  # driving on, over MQTT alone
        assert not stick.acked_since("zenoh", n), "an ack over zenoh through a partition"
        rig.zenoh_relay.plug()
        n = len(stick.sent)
        wait_until(lambda: stick.acked_since("zenoh", n), timeout=15, message="zenoh back by itself")
        assert rig.agent.zenoh is zlink  # the same session: nothing restarted
    finally:
        _finish(rig, stick)


def test_broker_killed_and_restarted(rig: Rig) -> None:
    stick = Stick(rig.op)
    try:
        wait_until(rig.moving, message="driving")
        wait_until(lambda: stick.acked_since("mqtt", 0), message="acks on mqtt")
        rig.broker.kill()
        wait_until(lambda: not rig.agent.mqtt.up, message="the agent noticing")  # type: ignore[union-attr]
        wait_until(
            lambda: (s := rig.op.last_state()) is not None and not s.links.mqtt, message="a state saying MQTT is down"
        )
        n = len(stick.sent)
        wait_until(lambda: stick.acked_since("zenoh", n + 3), message="commands still arriving over zenoh")
        assert rig.moving()
        with rig.op.lock:
            seen = len(rig.connection)
        rig.broker.start()
        n = len(stick.sent)
        wait_until(lambda: stick.acked_since("mqtt", n), timeout=15, message="commands over MQTT again")
        # The agent said ONLINE again (retained) after its reconnect.
        wait_until(lambda: ConnectionState.ONLINE in rig.connection[seen:], message="ONLINE after the restart")
        wait_until(lambda: (s := rig.op.last_state()) is not None and s.links.mqtt, message="a state: MQTT up")
    finally:
        _finish(rig, stick)


def test_agent_cut_from_the_broker_shows_connectionbroken_then_online(rig: Rig) -> None:
    """A killed broker cannot publish anyone's last will; an agent whose connection dies while the
    broker lives (its network cut) is reported CONNECTIONBROKEN by the broker, then ONLINE again."""
    stick = Stick(rig.op)
    try:
        wait_until(rig.moving, message="driving")
        with rig.op.lock:
            seen = len(rig.connection)
        rig.mqtt_relay.unplug()
        wait_until(
            lambda: ConnectionState.CONNECTIONBROKEN in rig.connection[seen:], message="the last will CONNECTIONBROKEN"
        )
        n = len(stick.sent)
        wait_until(lambda: stick.acked_since("zenoh", n + 3), message="commands still arriving over zenoh")
        rig.mqtt_relay.plug()
        wait_until(lambda: rig.connection[-1] is ConnectionState.ONLINE, timeout=15, message="ONLINE again")
        after = rig.connection[seen:]
        assert after.index(ConnectionState.CONNECTIONBROKEN) < len(after) - 1
        n = len(stick.sent)
        wait_until(lambda: stick.acked_since("mqtt", n), message="commands over MQTT again")
    finally:
        _finish(rig, stick)
