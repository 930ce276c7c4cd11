"""Benchmark: the lease holder's teleops while a flood hits the agent (issue 14).

    .venv/bin/python bench/abuse.py [--seconds 10] [--rate 10000] [--json FILE]

A real ``fleetlink agent`` process (tests/harness/agent_process.py: a simulated board over TCP,
Zenoh listening on loopback, a private Mosquitto) with a site's allowlist, ``operator-1`` and
``op-bob``. The operator ``operator-1`` takes the lease and sends a teleop every 100 ms on Zenoh,
timing each until its ack comes back. Three phases of ``--seconds`` each:

* baseline: nothing else (the figure every other phase is compared with, in the same run);
* garbage: ``--rate`` messages a second the agent must refuse, half on Zenoh, half on MQTT, on
  op-bob's command keys -- an operator's login gone rogue: on a secured site nobody else can write
  to the agent's keys, and what a login off the allowlist sends never reaches the agent
  (undecodable bytes, and decodable teleops with an unknown field named differently each time);
* valid flood: ``--rate`` valid zero teleops a second from op-bob, half on each link.

Per phase: the holder's teleops acked (ratio), ack latency p50/p99 and p99 added over the
baseline, the number acked later than their 0.5 s TTL; the agent's RSS growth and the lines it
logged. Goals (issue 14): 100 % delivered, p99 <= 50 ms added, RSS growth < 5 MB, log < 100 lines.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import multiprocessing
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import paho.mqtt.client as mqtt
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, LeaseRequest, Teleop
from fleetlink.site.brokers import MosquittoBroker
from tests.harness.agent_process import agent_process
from tests.harness.zenoh_peers import zenoh_config

TTL_S = 0.5
GOALS = {"delivered_ratio": 1.0, "added_p99_s": 0.050, "rss_growth_bytes": 5 * 1024 * 1024, "log_lines": 100}


def _rss(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


class Holder:
    """The lease holder: a teleop every 100 ms on Zenoh, each timed to its ack."""

    def __init__(self, session: Any, clock: SystemClock) -> None:
        self.session = session
        self.counter = wire.HeaderCounter(clock, robot="r1", sender="operator-1")
        self.sent: dict[int, float] = {}
        self.acked: dict[int, float] = {}
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(keys.key("r1", Ack.TOPIC), self._on_ack)

    def _on_ack(self, sample: Any) -> None:
        try:
            ack = wire.decode_key(str(sample.key_expr), sample.payload.to_bytes())
        except wire.WireError:
            return
        if isinstance(ack, Ack) and ack.commandSender == "operator-1":
            with self.lock:
                self.acked.setdefault(ack.commandHeaderId, time.monotonic())

    def run(self, seconds: float) -> list[int]:
        ids = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            msg = self.counter.make(Teleop, v=0.0, omega=0.0, ttl_s=TTL_S)
            with self.lock:
                self.sent[msg.header.headerId] = time.monotonic()
            self.session.put(wire.key_of(msg), wire.encode(msg))
            ids.append(msg.header.headerId)
            time.sleep(0.1)
        time.sleep(1.0)  # late acks still count (as late)
        return ids

    def figures(self, ids: list[int]) -> dict[str, float]:
        with self.lock:
            lat = [self.acked[i] - self.sent[i] for i in ids if i in self.acked]
        lat.sort()

        def pct(p: float) -> float:
            return lat[min(len(lat) - 1, int(p * len(lat)))] if lat else float("nan")

        return {
            "sent": len(ids),
            "delivered_ratio": len(lat) / len(ids) if ids else 0.0,
            "p50_s": statistics.median(lat) if lat else float("nan"),
            "p99_s": pct(0.99),
            "late": sum(1 for x in lat if x > TTL_S),
        }


def flood(kind: str, zenoh_endpoint: str, mqtt_port: int, rate: float, seconds: float) -> int:
    """In a process of its own (an attacker is not the measuring operator; in one process the two
    would share a GIL, and the holder's acks would wait on the flood's own loop): ``rate``
    messages a second for ``seconds``, alternating Zenoh and MQTT, from op-bob's login; returns how
    many. ``kind``: ``garbage`` or ``valid``."""
    clock = SystemClock()
    session = zenoh.open(zenoh_config(connect=[zenoh_endpoint]))
    mclient = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="flooder")
    mclient.max_queued_messages_set(0)
    mclient.connect("127.0.0.1", mqtt_port)
    mclient.loop_start()
    bob = wire.HeaderCounter(clock, robot="r1", sender="op-bob")
    template = msgpack.unpackb(wire.encode(bob.make(Teleop, v=0.0, omega=0.0, ttl_s=TTL_S)), raw=False)

    def garbage(i: int) -> tuple[str, bytes]:
        if i % 4 == 0:
            return keys.sender_key("r1", "order", "op-bob"), b"\xc1garbage"
        body = dict(template)
        body[f"field{i}"] = i  # an unknown field, named differently every time
        return keys.sender_key("r1", "teleop", "op-bob"), msgpack.packb(body, use_bin_type=True)

    def valid(i: int) -> tuple[str, bytes]:
        msg = bob.make(Teleop, v=0.0, omega=0.0, ttl_s=TTL_S)
        return wire.key_of(msg), wire.encode(msg)

    make = garbage if kind == "garbage" else valid
    time.sleep(1.0)  # the session finds the agent
    n = 0
    end = time.monotonic() + seconds
    start = time.monotonic()
    try:
        while time.monotonic() < end:
            for _ in range(100):
                key, payload = make(n)
                if n % 2:
                    mclient.publish(key, payload, qos=0)
                else:
                    session.put(key, payload)
                n += 1
            ahead = n / rate - (time.monotonic() - start)
            if ahead > 0:
                time.sleep(ahead)
    finally:
        mclient.loop_stop()
        mclient.disconnect()
        session.close()
    return n


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--rate", type=float, default=10_000.0, help="flood messages a second (both links)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    clock = SystemClock()
    rows: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp, MosquittoBroker(Path(tmp) / "broker") as broker:
        log_path = Path(tmp) / "agent.log"
        with (
            log_path.open("wb") as log,
            agent_process(Path(tmp), broker.port, output=log.fileno(), operators=("operator-1", "op-bob")) as agent,
        ):
            session = zenoh.open(zenoh_config(connect=[agent.zenoh_endpoint]))
            holder = Holder(session, clock)
            try:
                deadline = time.monotonic() + 30
                while not (agent.board.state is not None and agent.board.state.connected):
                    if time.monotonic() > deadline:
                        raise SystemExit("the agent did not come up")
                    time.sleep(0.1)
                time.sleep(1.5)
                # The holder takes the lease, as an operator driving the robot does.
                lease = holder.counter.make(LeaseRequest, duration_s=300.0, release=False)
                session.put(wire.key_of(lease), wire.encode(lease))
                rss0, lines0 = _rss(agent.proc.pid), len(log_path.read_bytes().splitlines())
                rows["baseline"] = holder.figures(holder.run(args.seconds))

                with concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
                    for name, kind in (("garbage", "garbage"), ("valid flood", "valid")):
                        job = pool.submit(flood, kind, agent.zenoh_endpoint, broker.port, args.rate, args.seconds + 3.0)
                        time.sleep(3.0)  # the process up (a second to start, a second for its links) and flooding
                        rows[name] = holder.figures(holder.run(args.seconds))
                        rows[name]["flood_sent"] = job.result()
                rss1, lines1 = _rss(agent.proc.pid), len(log_path.read_bytes().splitlines())
            finally:
                holder.sub.undeclare()
                session.close()
    base99 = rows["baseline"]["p99_s"]
    print(
        f"the lease holder's teleops (10 Hz on Zenoh) under a flood of {args.rate:.0f} msg/s, {args.seconds:g} s per phase"
    )
    print(
        f"{'phase':>12} {'flood sent':>11} {'delivered':>10} {'p50 ms':>8} {'p99 ms':>8} {'added p99':>10} {'late':>5}"
    )
    for name, r in rows.items():
        r["added_p99_s"] = max(0.0, r["p99_s"] - base99) if name != "baseline" else 0.0
        print(
            f"{name:>12} {r.get('flood_sent', 0):>11.0f} {r['delivered_ratio']:>9.1%} {1e3 * r['p50_s']:>8.2f}"
            f" {1e3 * r['p99_s']:>8.2f} {1e3 * r['added_p99_s']:>9.2f}  {r['late']:>4.0f}"
        )
    growth, lines = rss1 - rss0, lines1 - lines0
    print(f"agent RSS growth {growth / 1e6:.1f} MB; log lines written during the floods: {lines}")
    worst = [r for n, r in rows.items() if n != "baseline"]
    met = (
        all(r["delivered_ratio"] >= GOALS["delivered_ratio"] for r in worst)
        and all(r["added_p99_s"] <= GOALS["added_p99_s"] for r in worst)
        and growth < GOALS["rss_growth_bytes"]
        and lines < GOALS["log_lines"]
    )
    print(f"goals (100 % delivered, p99 +<= 50 ms, RSS +< 5 MB, < 100 log lines): {'met' if met else 'NOT met'}")
    if args.json:
        out = {"phases": rows, "rss_growth_bytes": growth, "log_lines": lines, "rate_msg_per_s": args.rate, "met": met}
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
