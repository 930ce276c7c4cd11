"""Benchmark: operator command published -> matching SET_VELOCITY frame at the board, over Zenoh and MQTT.

    .venv/bin/python bench/latency.py [--trials N] [--json FILE]

Everything on loopback in this process: a private Mosquitto (tests/harness), a simulated board
served on TCP exactly as hardware would be (``DeviceServer``), one ``AgentRuntime`` with both
links, and an operator (a Zenoh peer + a paho client with TCP_NODELAY). Each trial publishes a
teleop command (v = 0.2 m/s) on one link and timestamps, in the board server's reader thread,
the arrival of the first SET_VELOCITY frame that asks for forward motion; then a stop action
brings the set-point back to zero and the next trial starts after a random pause.

Baseline, measured in the same run: the raw transport's one-way floor (publish -> the
subscriber's callback, same process, same message size) for Zenoh (express, high priority)
and for MQTT (QoS 1, TCP_NODELAY). Goals: Zenoh p99 <= 5 ms, MQTT p99 <= 10 ms.
"""

from __future__ import annotations

import argparse
import json
import random
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fleetlink.agent.config import AgentConfig, Rates, ZenohSettings, mqtt_settings
from fleetlink.agent.runtime import AgentRuntime
from fleetlink.field.board import SimulatedBoard
from fleetlink.field.device_server import DeviceServer
from fleetlink.links.zenoh import peer_config
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Action, ActionType, InstantActions, Teleop
from fleetlink.site.brokers import MosquittoBroker, free_port

GOALS_P99_S = {"zenoh": 0.005, "mqtt": 0.010}


class TimedBoard:
    """A SimulatedBoard whose receive() notes when the wheel set-point first turns forward."""

    def __init__(self, board: SimulatedBoard) -> None:
        self.board = board
        self.armed = threading.Event()
        self.hit = threading.Event()
        self.hit_at = 0.0

    def receive(self, data: bytes, now: float) -> bytes:
        out = self.board.receive(data, now)
        # Any forward set-point is the command's effect: the acceleration limit may make the first
        # step small when the command lands just after a control tick.
        if self.armed.is_set() and self.board.state.set_left > 0.0:
            self.hit_at = time.perf_counter()
            self.armed.clear()
            self.hit.set()
        return out

    def step(self, now: float) -> bytes | None:
        return self.board.step(now)

    def start_clock(self, now: float) -> None:
        self.board.start_clock(now)


def pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


def floor_zenoh(n: int, payload: bytes) -> list[float]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    a = zenoh.open(peer_config([ep]))
    b = zenoh.open(peer_config(connect=[ep]))
    got = threading.Event()
    t = [0.0]

    def cb(_s: Any) -> None:
        t[0] = time.perf_counter()
        got.set()

    out: list[float] = []
    try:
        sub = a.declare_subscriber("bench/floor", cb)
        pub = b.declare_publisher("bench/floor", express=True, priority=zenoh.Priority.INTERACTIVE_HIGH)
        time.sleep(0.5)
        for i in range(n + 20):
            got.clear()
            t0 = time.perf_counter()
            pub.put(payload)
            if got.wait(1.0) and i >= 20:
                out.append(t[0] - t0)
            time.sleep(0.002)
        pub.undeclare()
        sub.undeclare()
    finally:
        b.close()
        a.close()
    return out


def mqtt_client(port: int, name: str) -> mqtt.Client:
    c = mqtt.Client(callback_api_version=mqtt.CallbackAPIVersion.VERSION2, client_id=name)
    c.connect("127.0.0.1", port)
    c.socket().setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    c.loop_start()
    return c


def floor_mqtt(port: int, n: int, payload: bytes) -> list[float]:
    sub = mqtt_client(port, "floor-sub")
    pub = mqtt_client(port, "floor-pub")
    got = threading.Event()
    t = [0.0]

    def on_message(*_a: Any) -> None:
        t[0] = time.perf_counter()
        got.set()

    sub.on_message = on_message
    sub.subscribe("bench/floor", qos=1)
    time.sleep(0.3)
    out: list[float] = []
    for i in range(n + 20):
        got.clear()
        t0 = time.perf_counter()
        pub.publish("bench/floor", payload, qos=1)
        if got.wait(1.0) and i >= 20:
            out.append(t[0] - t0)
        time.sleep(0.002)
    for c in (sub, pub):
        c.loop_stop()
        c.disconnect()
    return out


def command_latency(
    n: int, link: str, send: Any, timed: TimedBoard, op: wire.HeaderCounter, rng: random.Random
) -> list[float]:
    out: list[float] = []
    misses = 0
    for i in range(n + 10):
        timed.hit.clear()
        timed.armed.set()
        msg = op.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5)
        data = wire.encode(msg)
        t0 = time.perf_counter()
        send("teleop", data)
        if timed.hit.wait(1.0):
            if i >= 10:
                out.append(timed.hit_at - t0)
        else:
            misses += 1
            timed.armed.clear()
        stop = op.make(
            InstantActions, actions=(Action(actionId=f"s{i}", actionType=ActionType.STOP, actionParameters=()),)
        )
        send("actions", wire.encode(stop))
        deadline = time.perf_counter() + 1.0
        while timed.board.state.set_left > 0.0 and time.perf_counter() < deadline:
            time.sleep(0.002)
        time.sleep(rng.uniform(0.01, 0.04))
    if misses:
        print(f"  warning: {misses} {link} command(s) never reached the board within 1 s", file=sys.stderr)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rng = random.Random(5)
    clock = SystemClock()
    op = wire.HeaderCounter(clock, robot="r1", sender="operator-1")
    sample = wire.encode(op.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5))

    with tempfile.TemporaryDirectory() as tmp:
        broker = MosquittoBroker(Path(tmp) / "mosquitto").start()
        timed = TimedBoard(SimulatedBoard())
        server = DeviceServer(timed, clock, name="board")  # type: ignore[arg-type]
        port = server.serve_tcp()
        ep = f"tcp/127.0.0.1:{free_port()}"
        cfg = AgentConfig(
            robot="r1",
            board=f"socket://127.0.0.1:{port}",
            zenoh=ZenohSettings(listen=(ep,)),
            mqtt=mqtt_settings(f"mqtt://127.0.0.1:{broker.port}"),
            rates=Rates(control_hz=50.0, pose_hz=20.0, state_hz=1.0),
        )
        agent = AgentRuntime(cfg, clock, seed=1)
        zs = None
        mc = None
        try:
            agent.start()
            zs = zenoh.open(peer_config(connect=[ep]))
            pubs = {
                t: zs.declare_publisher(
                    keys.sender_key("r1", t, "operator-1"), express=True, priority=zenoh.Priority.INTERACTIVE_HIGH
                )
                for t in ("teleop", "actions")
            }
            mc = mqtt_client(broker.port, "operator-1")
            deadline = time.perf_counter() + 10
            while not (
                agent.board.snapshot.connected and agent.mqtt and agent.mqtt.up and agent.zenoh and agent.zenoh.up
            ):
                if time.perf_counter() > deadline:
                    raise SystemExit("agent did not come up")
                time.sleep(0.05)
            time.sleep(0.5)
            results = {
                "zenoh": command_latency(args.trials, "zenoh", lambda t, d: pubs[t].put(d), timed, op, rng),
                "mqtt": command_latency(
                    args.trials,
                    "mqtt",
                    lambda t, d: mc.publish(keys.sender_key("r1", t, "operator-1"), d, qos=1),
                    timed,
                    op,
                    rng,
                ),
            }
            for p in pubs.values():
                p.undeclare()
        finally:
            if mc is not None:
                mc.loop_stop()
                mc.disconnect()
            agent.stop()
            if zs is not None:
                zs.close()
            server.stop()
        floors = {"zenoh": floor_zenoh(args.trials, sample), "mqtt": floor_mqtt(broker.port, args.trials, sample)}
        broker.stop()

    figures: dict[str, Any] = {}
    print(f"command published -> SET_VELOCITY frame at the board ({args.trials} trials per link, loopback)")
    print(
        f"{'link':6} {'p50 ms':>8} {'p99 ms':>8} {'floor p50':>10} {'floor p99':>10} {'p99/floor p99':>14} {'goal p99':>9}  ok"
    )
    for link in ("zenoh", "mqtt"):
        xs, fl = results[link], floors[link]
        if not xs or not fl:
            print(f"{link:6} no samples")
            continue
        p50, p99, f50, f99 = pct(xs, 0.5), pct(xs, 0.99), pct(fl, 0.5), pct(fl, 0.99)
        ok = p99 <= GOALS_P99_S[link]
        print(
            f"{link:6} {p50 * 1e3:8.2f} {p99 * 1e3:8.2f} {f50 * 1e3:10.3f} {f99 * 1e3:10.3f} {p99 / f99:14.1f} "
            f"{GOALS_P99_S[link] * 1e3:8.1f}  {'yes' if ok else 'NO'}"
        )
        figures[link] = {
            "p50_s": p50,
            "p99_s": p99,
            "mean_s": statistics.fmean(xs),
            "max_s": max(xs),
            "floor_p50_s": f50,
            "floor_p99_s": f99,
            "ratio": p99 / f99,
            "goal_p99_s": GOALS_P99_S[link],
            "goal_met": ok,
            "samples": len(xs),
        }
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
