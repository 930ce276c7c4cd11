"""Benchmark: operator command published -> matching SET_VELOCITY frame at the board, over Zenoh and MQTT.

    .venv/bin/python bench/latency.py [--trials N] [--stages] [--board-in-process] [--json FILE]

On loopback: a private Mosquitto (site/brokers.py), a simulated board served on TCP exactly as
hardware would be (``DeviceServer``) in a process of its own, as a board is a device of its own,
one ``AgentRuntime`` with both links, and an operator (a Zenoh peer + a paho client with
TCP_NODELAY) in this process. Each trial publishes a teleop command (v = 0.2 m/s) on one link and
timestamps, in the board server's reader thread, the arrival of the first SET_VELOCITY frame that
asks for forward motion (when its bytes were read, before the simulated board decodes them); then a stop action brings the set-point back to zero and the next trial
starts after a random pause. Times on both sides are ``time.perf_counter`` (CLOCK_MONOTONIC on
Linux: one clock for every process of the host). ``--board-in-process`` serves the board from a
thread of this process instead (how this bench ran before 2026-11-28: the board's reader then
waits for the agent's GIL, which a real board never does).

Baseline, measured in the same run and interleaved with it (a floor sample before every command
sample, so both see the same load on the machine): the raw transport's one-way floor, publish ->
the subscriber's callback with the same message, for Zenoh (two sessions, express, high priority)
and for MQTT (QoS 1, TCP_NODELAY, through the same broker), in a process of their own (the agent's
threads do not share its GIL). Goal (issue 18): command -> board frame
p99 <= 3x the floor's p99, on both links.

``--stages`` stamps the command along the agent's path with wrappers on its objects (a few
microseconds each): the link's callback on the transport's thread, the agent's input handler,
the decision (decode, gate, lease, pilot and guard), the velocity handed to the board session,
the SET_VELOCITY frame written to the port, the board's reader; and, beside them, the end of the
input handler (acks and lease published). docs/architecture.md "The command's path" has the
figures.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import itertools
import json
import multiprocessing
import random
import socket
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fleetlink.agent.config import AgentConfig, Rates, ZenohSettings, mqtt_settings
from fleetlink.agent.runtime import AgentRuntime
from fleetlink.cli.agent import AGENT_SWITCH_INTERVAL_S
from fleetlink.field.board import SimulatedBoard
from fleetlink.field.device_server import DeviceServer
from fleetlink.links.zenoh import peer_config
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Action, ActionType, InstantActions, Teleop
from fleetlink.site.brokers import MosquittoBroker, free_port

GOAL_RATIO = 3.0
"""Command -> board frame p99 over the transport floor's p99 (issue 18)."""
LINKS = ("zenoh", "mqtt")
WARMUP = 10


# -- the board --------------------------------------------------------------------------------------


class TimedBoard:
    """A SimulatedBoard that reports when the wheel set-point turns forward (``hit``) and when it is
    back at zero (``zero``), through ``report(kind, perf_counter time)``. The time reported is when
    the server read the frame's bytes (``arrived``, set by ``StampedServer``), before the simulated
    board decodes it or waits for its physics step: what is measured is the path to the board, not
    the simulator's own work, which real firmware does in microseconds."""

    def __init__(self, board: SimulatedBoard, report: Callable[[str, float], None]) -> None:
        self.board = board
        self.report = report
        self.armed = False
        self.arrived = 0.0
        self._moving = False

    def receive(self, data: bytes, now: float) -> bytes:
        out = self.board.receive(data, now)
        # Any forward set-point is the command's effect: the acceleration limit may make the first
        # step small when the command lands just after a control tick.
        moving = self.board.state.set_left > 0.0
        if moving and self.armed:
            self.armed = False
            self.report("hit", self.arrived)
        if self._moving and not moving:
            self.report("zero", self.arrived)
        self._moving = moving
        return out

    def step(self, now: float) -> bytes | None:
        return self.board.step(now)

    def start_clock(self, now: float) -> None:
        self.board.start_clock(now)


class StampedServer(DeviceServer):
    """A ``DeviceServer`` that notes when each read's bytes arrived (its reader thread, right
    after ``recv``) on the ``TimedBoard`` it serves."""

    def _handle(self, data: bytes) -> bytes:
        self.device.arrived = time.perf_counter()  # type: ignore[attr-defined]
        return super()._handle(data)


class BoardProbe:
    """The served board as the bench sees it: its port; arm, then wait for the hit and the zero."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._events: dict[str, float] = {}
        self.port = 0

    def _report(self, kind: str, t: float) -> None:
        with self._cond:
            self._events[kind] = t
            self._cond.notify_all()

    def arm(self) -> None:
        with self._cond:
            self._events.clear()
        self._arm()

    def wait(self, kind: str, timeout: float) -> float | None:
        with self._cond:
            self._cond.wait_for(lambda: kind in self._events, timeout)
            return self._events.get(kind)

    def _arm(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class ThreadBoard(BoardProbe):
    """Served by a ``DeviceServer`` thread in this process (``--board-in-process``)."""

    def __init__(self) -> None:
        super().__init__()
        self.timed = TimedBoard(SimulatedBoard(), self._report)
        self.server = StampedServer(self.timed, SystemClock(), name="board")  # type: ignore[arg-type]
        self.port = self.server.serve_tcp()

    def _arm(self) -> None:
        with self.server.lock:
            self.timed.armed = True

    def close(self) -> None:
        self.server.stop()


def room_scan() -> Any:
    """An A1's turn in the middle of a 6 m x 4 m room with a box in one corner: what the agent's
    lidar thread decodes and maps under ``--lidar``."""
    import numpy as np

    from fleetlink.field.lidar import LidarConfig
    from fleetlink.field.rplidar import FixedScan

    cfg = LidarConfig()
    n = round(cfg.samples_per_second / cfg.rate_hz)
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        d = np.minimum(np.where(c != 0, 3.0 / np.abs(c), np.inf), np.where(s != 0, 2.0 / np.abs(s), np.inf))
    box = (a > 0.4) & (a < 0.7)
    d[box] = np.minimum(d[box], 1.5)
    return cfg, FixedScan(a, d)


def _serve_board(conn: Any) -> None:
    """The board process: serve a TimedBoard on TCP, report to ``conn``, arm on request."""
    lock = threading.Lock()

    def report(kind: str, t: float) -> None:
        with lock:
            conn.send((kind, t))

    timed = TimedBoard(SimulatedBoard(), report)
    server = StampedServer(timed, SystemClock(), name="board")  # type: ignore[arg-type]
    port = server.serve_tcp()
    report("port", float(port))
    try:
        while (msg := conn.recv()) != "stop":
            if msg == "arm":
                with server.lock:
                    timed.armed = True
    finally:
        server.stop()


def _serve_lidar(conn: Any) -> None:
    """The lidar process (``--lidar``): a simulated RPLIDAR A1 on TCP, streaming ``room_scan``."""
    from fleetlink.field.rplidar import RplidarConfig, SimulatedRplidar

    cfg, scan = room_scan()
    device = SimulatedRplidar(cfg, scan, RplidarConfig(motor_on_at_start=True))
    server = DeviceServer(device, SystemClock(), name="lidar")
    conn.send(("port", float(server.serve_tcp())))
    try:
        conn.recv()
    except EOFError:
        pass
    finally:
        server.stop()


class Child:
    """A spawned process running ``target(conn)``, which first sends ("port", port)."""

    def __init__(self, target: Callable[[Any], None], name: str) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=target, args=(child,), name=name, daemon=True)
        self.proc.start()
        child.close()
        kind, port = self.conn.recv()
        assert kind == "port"
        self.port = int(port)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.send("stop")
        self.proc.join(5.0)
        if self.proc.is_alive():
            self.proc.kill()


class ProcessBoard(BoardProbe):
    """Served by a ``DeviceServer`` in a process of its own (the default)."""

    def __init__(self) -> None:
        super().__init__()
        self._child = Child(_serve_board, "board")
        self._conn = self._child.conn
        self.port = self._child.port
        self._reader = threading.Thread(target=self._read, name="board-reports", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        try:
            while True:
                kind, t = self._conn.recv()
                self._report(kind, t)
        except (EOFError, OSError):
            pass

    def _arm(self) -> None:
        self._conn.send("arm")

    def close(self) -> None:
        self._child.close()


# -- the floors -------------------------------------------------------------------------------------


class Floor:
    """One transport's raw one-way time: publish -> the subscriber's callback, same message."""

    def __init__(self) -> None:
        self._got = threading.Event()
        self._t = 0.0

    def _arrived(self, *_a: Any) -> None:
        self._t = time.perf_counter()
        self._got.set()

    def _put(self, payload: bytes) -> None:
        raise NotImplementedError

    def sample(self, payload: bytes, timeout: float = 1.0) -> float | None:
        self._got.clear()
        t0 = time.perf_counter()
        self._put(payload)
        return self._t - t0 if self._got.wait(timeout) else None

    def close(self) -> None:
        raise NotImplementedError


class ZenohFloor(Floor):
    def __init__(self) -> None:
        super().__init__()
        ep = f"tcp/127.0.0.1:{free_port()}"
        self.a = zenoh.open(peer_config([ep]))
        self.b = zenoh.open(peer_config(connect=[ep]))
        self.sub = self.a.declare_subscriber("bench/floor", self._arrived)
        self.pub = self.b.declare_publisher("bench/floor", express=True, priority=zenoh.Priority.INTERACTIVE_HIGH)

    def _put(self, payload: bytes) -> None:
        self.pub.put(payload)

    def close(self) -> None:
        self.pub.undeclare()
        self.sub.undeclare()
        self.b.close()
        self.a.close()


def mqtt_client(port: int, name: str) -> mqtt.Client:
    c = mqtt.Client(callback_api_version=mqtt.CallbackAPIVersion.VERSION2, client_id=name)
    c.connect("127.0.0.1", port)
    c.socket().setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    c.loop_start()
    return c


class MqttFloor(Floor):
    def __init__(self, port: int) -> None:
        super().__init__()
        self.sub = mqtt_client(port, "floor-sub")
        self.pub = mqtt_client(port, "floor-pub")
        self.sub.on_message = self._arrived
        self.sub.subscribe("bench/floor", qos=1)

    def _put(self, payload: bytes) -> None:
        self.pub.publish("bench/floor", payload, qos=1)

    def close(self) -> None:
        for c in (self.sub, self.pub):
            c.loop_stop()
            c.disconnect()


def _serve_floors(conn: Any, broker_port: int) -> None:
    """The floors' process: a Zenoh pair and an MQTT pair, sampled on request (("zenoh" | "mqtt",
    payload) -> seconds or None), so the agent's threads never share a GIL with them."""
    floors: dict[str, Floor] = {"zenoh": ZenohFloor(), "mqtt": MqttFloor(broker_port)}
    for floor in floors.values():  # subscriptions take a moment to reach the publisher
        for _ in range(50):
            if floor.sample(b"ready", timeout=0.1) is not None:
                break
    conn.send(("port", 0.0))
    try:
        while (msg := conn.recv()) != "stop":
            link, payload = msg
            conn.send(floors[link].sample(payload))
    except EOFError:
        pass
    finally:
        for f in floors.values():
            f.close()


class Floors(Child):
    """The transports' floors, measured in a process of their own (``_serve_floors``)."""

    def __init__(self, broker_port: int) -> None:
        super().__init__(functools.partial(_serve_floors, broker_port=broker_port), "floors")

    def sample(self, link: str, payload: bytes) -> float | None:
        self.conn.send((link, payload))
        result: float | None = self.conn.recv()
        return result


# -- stages -----------------------------------------------------------------------------------------

STAGES = ("pub", "link", "input", "decided", "velocity", "write", "board")
"""The command's path, in order; ``applied`` (the input handler done: acks published) is a branch."""
STAGE_PAIRS = (*itertools.pairwise(STAGES), ("velocity", "applied"), ("pub", "board"))


class Stages:
    """Stage timestamps of the trial in progress, stamped by wrappers on the agent's objects."""

    def __init__(self) -> None:
        self.armed = False
        self.t: dict[str, float] = {}
        self.rows: list[dict[str, float]] = []

    def arm(self) -> None:
        self.t = {}
        self.armed = True

    def stamp(self, name: str, after: str | None = None) -> None:
        if self.armed and name not in self.t and (after is None or after in self.t):
            self.t[name] = time.perf_counter()

    def keep(self, t0: float, hit: float) -> None:
        self.t["pub"], self.t["board"] = t0, hit
        self.rows.append(self.t)
        self.armed = False

    def install(self, agent: AgentRuntime) -> None:
        """Wrap the agent's objects (before ``agent.start()``)."""
        assert agent.zenoh is not None and agent.mqtt is not None
        stamp = self.stamp
        inbox = agent.zenoh._inbox
        put = inbox.put

        def inbox_put(item: Any, lane: int = 2) -> bool:
            stamp("link")
            return put(item, lane)

        inbox.put = inbox_put  # type: ignore[method-assign]
        mq = agent.mqtt
        on_message = mq._on_message

        def mqtt_message(*a: Any) -> None:
            stamp("link")
            on_message(*a)

        mq._on_message = mqtt_message  # type: ignore[method-assign]
        node = agent.node
        on_input = node.on_input

        def node_input(link: Any, key: str, payload: bytes) -> bool:
            stamp("link")  # (a link that hands over on its own thread was stamped already)
            stamp("input")
            started = on_input(link, key, payload)
            stamp("applied")
            return started

        node.on_input = node_input  # type: ignore[method-assign]
        core = node.core
        core_input = core.on_input

        def decided(*a: Any) -> Any:
            out = core_input(*a)
            stamp("decided")
            return out

        core.on_input = decided  # type: ignore[method-assign]
        board = agent.board
        set_velocity = board.set_velocity

        def velocity(vx: float, omega: float) -> None:
            if vx > 0.0:
                stamp("velocity")
            set_velocity(vx, omega)

        board.set_velocity = velocity  # type: ignore[method-assign]

    def install_port(self, agent: AgentRuntime) -> None:
        """Wrap the board port's write (once the board is connected)."""
        assert agent.board.client is not None
        port: Any = agent.board.client.port
        write = port.write

        def port_write(data: bytes) -> None:
            self.stamp("write", after="velocity")
            write(data)

        port.write = port_write

    def table(self) -> dict[str, tuple[float, float, float]]:
        out = {}
        for a, b in STAGE_PAIRS:
            xs = [r[b] - r[a] for r in self.rows if a in r and b in r]
            if xs:
                out[f"{a}->{b}"] = (pct(xs, 0.5), pct(xs, 0.9), pct(xs, 0.99))
        return out


# -- the run ----------------------------------------------------------------------------------------


def pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


def run_link(
    n: int,
    link: str,
    send: Callable[[str, bytes], None],
    board: BoardProbe,
    floor: Floors,
    op: wire.HeaderCounter,
    rng: random.Random,
    stages: Stages | None,
) -> tuple[list[float], list[float]]:
    """``n`` trials (after a warm-up), each a floor sample and then a command sample."""
    out: list[float] = []
    floors: list[float] = []
    misses = 0
    sample = wire.encode(op.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5))
    for i in range(n + WARMUP):
        f = floor.sample(link, sample)
        if f is not None and i >= WARMUP:
            floors.append(f)
        time.sleep(rng.uniform(0.005, 0.015))
        board.arm()
        data = wire.encode(op.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5))
        if stages is not None and i >= WARMUP:
            stages.arm()
        t0 = time.perf_counter()
        send("teleop", data)
        hit = board.wait("hit", 1.0)
        if hit is None:
            misses += 1
        elif i >= WARMUP:
            out.append(hit - t0)
            if stages is not None:
                time.sleep(0.003)  # the input handler's end (acks published) is stamped too
                stages.keep(t0, hit)
        stop = op.make(
            InstantActions, actions=(Action(actionId=f"s{i}", actionType=ActionType.STOP, actionParameters=()),)
        )
        send("actions", wire.encode(stop))
        board.wait("zero", 1.0)
        time.sleep(rng.uniform(0.01, 0.04))
    if misses:
        print(f"  warning: {misses} {link} command(s) never reached the board within 1 s", file=sys.stderr)
    return out, floors


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--stages", action="store_true", help="stamp the command along the agent's path")
    ap.add_argument("--board-in-process", action="store_true", help="serve the board from a thread of this process")
    ap.add_argument(
        "--lidar",
        action="store_true",
        help="the agent also reads a simulated RPLIDAR A1 (served by a process of its own) and maps its "
        "turns, as a robot does: its lidar thread decodes and maps while commands arrive",
    )
    ap.add_argument(
        "--no-direct",
        action="store_true",
        help="the agent's path as it was before direct delivery: every sample through the Zenoh delivery "
        "thread, every velocity written by the board session's thread",
    )
    ap.add_argument(
        "--switch-interval",
        type=float,
        default=AGENT_SWITCH_INTERVAL_S,
        help="seconds between GIL hand-overs in this process (default: the agent process's, cli/agent.py)",
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    # The agent's process hands the GIL over every 1 ms (cli/agent.py); this one hosts the agent.
    sys.setswitchinterval(args.switch_interval)
    rng = random.Random(5)
    clock = SystemClock()
    op = wire.HeaderCounter(clock, robot="r1", sender="operator-1")
    stages = Stages() if args.stages else None
    tables: dict[str, dict[str, tuple[float, float, float]]] = {}
    results: dict[str, tuple[list[float], list[float]]] = {}
    scans = 0

    with tempfile.TemporaryDirectory() as tmp:
        board: BoardProbe = ThreadBoard() if args.board_in_process else ProcessBoard()
        lidar = Child(_serve_lidar, "lidar") if args.lidar else None
        broker = MosquittoBroker(Path(tmp) / "mosquitto").start()
        ep = f"tcp/127.0.0.1:{free_port()}"
        cfg = AgentConfig(
            robot="r1",
            board=f"socket://127.0.0.1:{board.port}",
            lidar=f"socket://127.0.0.1:{lidar.port}" if lidar is not None else None,
            zenoh=ZenohSettings(listen=(ep,)),
            mqtt=mqtt_settings(f"mqtt://127.0.0.1:{broker.port}"),
            rates=Rates(control_hz=50.0, pose_hz=20.0, state_hz=1.0),
        )
        agent = AgentRuntime(cfg, clock, seed=1)
        if args.no_direct:
            assert agent.zenoh is not None
            agent.zenoh.direct = agent.board.direct = False
        if stages is not None:
            stages.install(agent)
        zs = mc = None
        floors: Floors | None = None
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
            floors = Floors(broker.port)
            deadline = time.perf_counter() + 10
            while not (
                agent.board.snapshot.connected and agent.mqtt and agent.mqtt.up and agent.zenoh and agent.zenoh.up
            ):
                if time.perf_counter() > deadline:
                    raise SystemExit("agent did not come up")
                time.sleep(0.05)
            if stages is not None:
                stages.install_port(agent)
            if args.lidar:  # mapping under way before the first trial
                while agent.scans < 10:
                    if time.perf_counter() > deadline + 10:
                        raise SystemExit("the agent's lidar did not deliver turns")
                    time.sleep(0.05)
            time.sleep(0.5)
            client = mc
            sends: dict[str, Callable[[str, bytes], None]] = {
                "zenoh": lambda t, d: pubs[t].put(d),
                "mqtt": lambda t, d: client.publish(keys.sender_key("r1", t, "operator-1"), d, qos=1),
            }
            for link in LINKS:
                if stages is not None:
                    stages.rows = []
                results[link] = run_link(args.trials, link, sends[link], board, floors, op, rng, stages)
                if stages is not None:
                    tables[link] = stages.table()
            for p in pubs.values():
                p.undeclare()
            scans = agent.scans
        finally:
            if floors is not None:
                floors.close()
            if mc is not None:
                mc.loop_stop()
                mc.disconnect()
            agent.stop()
            if zs is not None:
                zs.close()
            board.close()
            if lidar is not None:
                lidar.close()
            broker.stop()

    figures: dict[str, Any] = {"goal_ratio": GOAL_RATIO, "trials": args.trials}
    figures["board"] = "thread" if args.board_in_process else "process"
    figures["direct"] = not args.no_direct
    figures["lidar"] = args.lidar
    figures["switch_interval_s"] = args.switch_interval
    if args.lidar:
        figures["lidar_turns"] = scans
    where = "a thread of the bench" if args.board_in_process else "its own process"
    print(f"command published -> SET_VELOCITY frame at the board ({args.trials} trials per link, loopback,")
    path = "without direct delivery (--no-direct)" if args.no_direct else "direct delivery"
    load = f"; the agent mapping {scans} lidar turns meanwhile" if args.lidar else ""
    print(f"the board in {where}; {path}{load}; the floor sampled before every command)")
    print(
        f"{'link':6} {'p50 ms':>8} {'p99 ms':>8} {'floor p50':>10} {'floor p99':>10} "
        f"{'p50/floor p50':>14} {'p99/floor p99':>14} {'goal':>6}  met"
    )
    met_all = True
    for link in LINKS:
        xs, fl = results[link]
        if not xs or not fl:
            print(f"{link:6} no samples")
            met_all = False
            continue
        p50, p99, f50, f99 = pct(xs, 0.5), pct(xs, 0.99), pct(fl, 0.5), pct(fl, 0.99)
        ratio = p99 / f99
        ok = ratio <= GOAL_RATIO
        met_all = met_all and ok
        print(
            f"{link:6} {p50 * 1e3:8.2f} {p99 * 1e3:8.2f} {f50 * 1e3:10.3f} {f99 * 1e3:10.3f} {p50 / f50:14.2f} {ratio:14.2f} "
            f"{GOAL_RATIO:5.1f}x  {'yes' if ok else 'NO'}"
        )
        figures.update(
            {
                f"{link}_p50_s": p50,
                f"{link}_p99_s": p99,
                f"{link}_mean_s": statistics.fmean(xs),
                f"{link}_max_s": max(xs),
                f"{link}_floor_p50_s": f50,
                f"{link}_floor_p99_s": f99,
                f"{link}_ratio": ratio,
                f"{link}_ratio_p50": p50 / f50,
                f"{link}_goal_met": ok,
                f"{link}_samples": len(xs),
            }
        )
    figures["goal_met"] = met_all
    for link, table in tables.items():
        print(f"\nstages, {link} ({len(results[link][0])} trials)      p50 us   p90 us   p99 us")
        for name, (s50, s90, s99) in table.items():
            a, b = name.split("->")
            print(f"  {a:>8} -> {b:<8}          {s50 * 1e6:8.0f} {s90 * 1e6:8.0f} {s99 * 1e6:8.0f}")
            figures[f"{link}_stage_{a}_{b}_p50_s"] = s50
            figures[f"{link}_stage_{a}_{b}_p99_s"] = s99
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
