"""Drill: 10 MB payloads on both links to a running agent process (issue 14).

A real ``fleetlink agent`` on a simulated board; a raw Zenoh peer puts 10 MB on its command keys
(twenty times), and a paho client publishes 10 MB on them through a private Mosquitto. Every one
is refused before it is copied or decoded: the agent's RSS grows by less than 5 MB (it used to
copy each into Python and queue it: 85 -> 115 MB for one, ~200 MB repeated), the broker refuses
the packet at its edge (``max_packet_size``, the wire's 256 KiB plus headers), and a teleop sent
afterwards is acknowledged on each link.
"""

from __future__ import annotations

import contextlib
import threading
from pathlib import Path

import paho.mqtt.client as mqtt
import zenoh

from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, AckResult, Teleop
from tests.harness import MosquittoBroker, wait_until
from tests.harness.agent_process import AgentProcess, agent_process
from tests.harness.zenoh_peers import zenoh_config

BIG = b"\x00" * (10 * 1024 * 1024)


def _rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


def test_ten_megabyte_payloads_on_both_links_are_refused_before_decoding(
    tmp_path: Path, mosquitto: MosquittoBroker
) -> None:
    clock = SystemClock()
    with agent_process(tmp_path, mosquitto.port) as agent:
        _flood(agent, clock, mosquitto)


def _flood(agent: AgentProcess, clock: SystemClock, mosquitto: MosquittoBroker) -> None:
    proc, board, endpoint = agent.proc, agent.board, agent.zenoh_endpoint
    session = zenoh.open(zenoh_config(connect=[endpoint]))
    acks: list[tuple[str, Ack]] = []
    lock = threading.Lock()

    def on_ack(link: str, key: str, payload: bytes) -> None:
        msg = wire.decode_key(key, payload)
        with lock:
            acks.append((link, msg))  # type: ignore[arg-type]

    sub = session.declare_subscriber(
        keys.key("r1", "ack"), lambda s: on_ack("zenoh", str(s.key_expr), s.payload.to_bytes())
    )
    op = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="operator-1")
    op.on_message = lambda _c, _u, m: on_ack("mqtt", m.topic, bytes(m.payload))
    op.connect("127.0.0.1", mosquitto.port)
    op.subscribe(keys.key("r1", "ack"), qos=1)
    op.loop_start()
    counter = wire.HeaderCounter(clock, robot="r1", sender="operator-1")

    def acked(header_id: int, link: str) -> bool:
        with lock:
            return any(lk == link and a.commandHeaderId == header_id for lk, a in acks)

    def teleop_acked(link: str) -> None:
        """A teleop on ``link``, sent again every 0.2 s until one is acked (the links may be joining)."""
        sent: list[int] = []

        def send_and_check() -> bool:
            if any(acked(h, link) for h in sent):
                return True
            msg = counter.make(Teleop, v=0.0, omega=0.0, ttl_s=0.5)
            data = wire.encode(msg)
            if link == "zenoh":
                session.put(keys.sender_key("r1", "teleop", "operator-1"), data)
            else:
                op.publish(keys.sender_key("r1", "teleop", "operator-1"), data, qos=1)
            sent.append(msg.header.headerId)
            return False

        wait_until(send_and_check, timeout=10, interval=0.2, message=f"a teleop acked on {link}")

    try:
        wait_until(lambda: board.state is not None and board.state.connected, timeout=20, message="the agent up")
        teleop_acked("zenoh")
        teleop_acked("mqtt")
        before = _rss_bytes(proc.pid)
        for _ in range(20):
            session.put(keys.sender_key("r1", "teleop", "operator-1"), BIG)
            session.put(keys.sender_key("r1", "order", "operator-1"), BIG)
        big = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="flooder")
        big.connect("127.0.0.1", mosquitto.port)
        big.loop_start()
        for _ in range(3):
            info = big.publish(keys.sender_key("r1", "teleop", "operator-1"), BIG, qos=0)
        with contextlib.suppress(RuntimeError, ValueError):  # the broker may drop it mid-way
            info.wait_for_publish(10)  # written to the broker (which refuses it at its edge)
        big.loop_stop()
        big.disconnect()
        teleop_acked("zenoh")
        teleop_acked("mqtt")
        grown = _rss_bytes(proc.pid) - before
        assert grown < 5 * 1024 * 1024, f"agent RSS grew by {grown / 1e6:.1f} MB"
        with lock:
            assert all(a.result is AckResult.ACCEPTED for _, a in acks)
        assert proc.poll() is None
    finally:
        op.loop_stop()
        op.disconnect()
        sub.undeclare()
        session.close()
