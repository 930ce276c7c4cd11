"""Benchmark: N robots on the real-time field, an agent process each, one headless console.

    .venv/bin/python bench/scale.py [--robots 50] [--seconds 300] [--lidar-hz 1] [--lidar-samples 720]
                                    [--drive] [--no-mqtt] [--json FILE]
    .venv/bin/python bench/scale.py --light --robots 500 [--seconds 60] [--command-robots 50] [--json FILE]
    .venv/bin/python bench/scale.py --light --lossy 0,1,5,10 --robots 50 [--seconds 20] [--json FILE]

The site as docs/operations.md lays it out: the real-time field (``RealtimeField``, the hall-50
scenario cut to N robots) serves every robot's simulated board (and lidar, at ``--lidar-hz``; 0:
none) over TCP from a process of its own, as hardware would be; one Zenoh router in its own process;
with MQTT on (the default) a private Mosquitto; and one ``fleetlink agent --config robot-<n>.toml``
process per robot, its Zenoh session a client of the router (pose at 20 Hz, state at 1 Hz), its MQTT
link on the broker. The console is a Zenoh client of the router in this process (nothing else runs
here: a field in the same process held the GIL through its lidars' ray casts while the console's
pose callbacks queued, and that queue, not the fleet, was most of the staleness measured before
2026-12-02) subscribed to ``fleetlink/v1/*/pose``: it decodes every pose and measures, over
``--seconds`` after a warm-up in which every robot has been heard:

* poses delivered: received / (20 Hz x robots x seconds) -- the goal's definition; beside it the
  ratio by sequence number (received / headerId span), which separates loss on the way from an
  agent publishing below its rate;
* staleness at the console: receive time minus the pose's header timestamp (same host, same wall
  clock), p50/p99/max;
* per agent: CPU % of one core and RSS (from /proc, sampled every second; max over the run);
  beside them the CPU of the agents together, of the field, of this process (the console), the
  router and the broker, so one sees where the cores go.

With ``--drive`` the console also drives every robot, as an operator holding a key would: a
``Teleop`` to each robot 4 times a second (spinning in place at 0.3 rad/s, so fifty robots in
their bays hit nothing), which keeps every agent's control loop at its full 50 Hz; the table then
says how many robots were seen turning. Without it the fleet stands idle, and idle agents tick
only once per pose.

``--light``: N light robots instead (``fleetlink field --light N``: one process publishing every
robot's real wire messages, pose 20 Hz, state and lease 1 Hz, liveliness tokens, acks; no agents,
no field) through a two-router Zenoh mesh (site/mesh.py): the robots are clients of router A, the
console a client of router B. Measured in the same run, one after the other on the same fleet:
the console on router A (one router: the baseline) and on router B (the mesh), each for
``--seconds``: poses delivered and staleness as above, and commands: a Teleop to each of the first
``--command-robots`` robots ``TELEOP_HZ`` times a second, acked by the robot (ack round trip
p50/p99 and the share acked). Beside them the CPU of the light fleet's process, each router and
this process (the console), which is where a larger fleet breaks. ``--light --robots 500`` is the
goal's configuration.

``--light --lossy 0,1,5,10``: the light robots behind a lossy link instead (tests/harness/lossy.py: a
network namespace made for the run, its veth's packets dropped at random by the kernel, each way;
root, ``ip`` and ``nft`` needed), clients of one router on the link's host end, the console on that
router; one phase of ``--seconds`` per loss rate, on the same fleet: delivery, staleness and teleop
acks as above, and the packets the link dropped.

Goals: >= 99.9 % delivered, staleness p99 <= 100 ms, agent RSS <= 80 MB. The table shows each
figure beside its goal. Every robot has a simulated lidar (``--lidar-hz`` turns a second, sending
``--lidar-samples`` measurements a second: a turn has samples / rate of them), and its agent reads
it and maps with it (``lidar =`` in its robot.toml; the runtime's lidar thread feeds its mapper,
its planner and the map share). The default, 1 Hz x 720 samples (0.5 degree steps), is the A1's
5.5 Hz x 1450 reduced so that fifty mapping agents, the field ray-casting fifty lidars, a router,
a broker and the console share one 2-core host; ``--lidar-hz 0`` runs without lidars. Both rates
are reported.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.harness import end_child  # noqa: E402

POSE_HZ = 20.0
TELEOP_HZ = 4.0  # per robot, with --drive
DRIVE_OMEGA = 0.3  # rad/s, turning in place
GOALS = {"delivered_ratio": 0.999, "staleness_p99_s": 0.100, "agent_rss_max_bytes": 80 * 1024 * 1024}
CLK_TCK = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")

FIELD_SCRIPT = r"""
import json, sys
from dataclasses import replace
from fleetlink.field.plans import load_plan
from fleetlink.field.realtime import RealtimeField
from fleetlink.field.scenario import LidarSettings, load_scenario
from fleetlink.shared.clock import SystemClock
scenario, n, hz, samples = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
sc = load_scenario(scenario)
sc = replace(sc, robots=sc.robots[:n], lidar=LidarSettings(hz > 0, hz if hz > 0 else 10.0, samples))
fld = RealtimeField(sc, load_plan(sc.plan), SystemClock())
endpoints = fld.start()
print(json.dumps({k: [e.board, e.lidar] for k, e in endpoints.items()}), flush=True)
sys.stdin.read()
fld.stop()
"""


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime + stime


def rss_bytes(pid: int) -> int:
    with open(f"/proc/{pid}/statm") as f:
        return int(f.read().split()[1]) * PAGE


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


@dataclass
class Console:
    """The headless console: decodes every pose, counts and times the ones inside the window."""

    measuring: bool = False
    counts: dict[str, int] = field(default_factory=dict)
    ids: dict[str, list[int]] = field(default_factory=dict)
    staleness: list[float] = field(default_factory=list)
    heard: set[str] = field(default_factory=set)
    turning: set[str] = field(default_factory=set)
    bad: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample: Any) -> None:
        from fleetlink.shared import wire

        now = time.time()  # a bench may read the wall clock to measure (same clock as the header's)
        try:
            msg = wire.decode_key(str(sample.key_expr), sample.payload.to_bytes())
        except wire.WireError:
            with self.lock:
                self.bad += 1
            return
        robot = msg.header.robot
        with self.lock:
            self.heard.add(robot)
            if self.measuring:
                self.counts[robot] = self.counts.get(robot, 0) + 1
                self.ids.setdefault(robot, []).append(msg.header.headerId)
                self.staleness.append(now - msg.header.timestamp)
                if abs(msg.omega) > 0.1:  # type: ignore[attr-defined]
                    self.turning.add(robot)


def drive(session: Any, robots: list[str], stop: threading.Event, sent: list[int]) -> None:
    """``--drive``: a Teleop to every robot ``TELEOP_HZ`` times a second until ``stop``."""
    from fleetlink.shared import wire
    from fleetlink.shared.clock import SystemClock
    from fleetlink.shared.messages import Teleop

    counter = wire.HeaderCounter(SystemClock(), robot=robots[0], sender="console-bench")
    next_t = time.perf_counter()
    while not stop.is_set():
        for r in robots:
            msg = Teleop(header=counter.header(Teleop.TOPIC, robot=r), v=0.0, omega=DRIVE_OMEGA, ttl_s=0.6)
            session.put(wire.key_of(msg), wire.encode(msg))
            sent[0] += 1
        next_t += 1.0 / TELEOP_HZ
        stop.wait(max(0.0, next_t - time.perf_counter()))


def robot_toml(name: str, board: str, lidar: str | None, router: str, mqtt_port: int | None) -> str:
    text = f"""robot = "{name}"
board = "{board}"
tag = "{name}"
{f'lidar = "{lidar}"' if lidar else ""}

[zenoh]
connect = ["{router}"]
mode = "client"

[rates]
control_hz = 50.0
pose_hz = {POSE_HZ}
state_hz = 1.0
"""
    if mqtt_port is not None:
        text += f'\n[mqtt]\nurl = "mqtt://127.0.0.1:{mqtt_port}"\n'
    return text


def run(
    n: int,
    seconds: float,
    lidar_hz: float,
    use_mqtt: bool,
    warmup_timeout: float,
    lidar_samples: float = 720.0,
    driving: bool = False,
) -> dict[str, Any]:
    import zenoh

    from fleetlink.field.scenario import load_scenario
    from fleetlink.links.zenoh import peer_config
    from fleetlink.site.brokers import MosquittoBroker, free_port
    from fleetlink.site.mesh import ZenohRouter

    scenario = ROOT / "field" / "scenarios" / "hall-50.toml"
    if n > len(load_scenario(scenario).robots):
        raise SystemExit(f"the hall-50 scenario has {len(load_scenario(scenario).robots)} robots; asked for {n}")
    tmp = Path(tempfile.mkdtemp(prefix="fleetlink-scale-"))
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    procs: list[subprocess.Popen[bytes]] = []
    broker = None
    console = Console()
    session = None
    stop_driving = threading.Event()
    teleops = [0]
    router = ZenohRouter(router_ep)
    fld = None
    try:
        router.start()
        if use_mqtt:
            broker = MosquittoBroker(tmp / "broker").start()
        # The field in a process of its own, as hardware is: in this process its physics and fifty
        # lidars' ray casts would hold the GIL while the console's pose callbacks queue behind them.
        fld = subprocess.Popen(
            [sys.executable, "-c", FIELD_SCRIPT, str(scenario), str(n), str(lidar_hz), str(lidar_samples)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        assert fld.stdout is not None
        line = fld.stdout.readline()
        if not line:
            raise SystemExit("the field did not start")
        endpoints: dict[str, list[str | None]] = json.loads(line)
        session = zenoh.open(peer_config(connect=[router_ep], mode="client"))
        session.declare_subscriber("fleetlink/v1/*/pose", console.on_sample)
        exe = str(Path(sys.executable).parent / "fleetlink")
        agents: dict[str, subprocess.Popen[bytes]] = {}
        for name, (board, lidar) in endpoints.items():
            cfg = tmp / f"robot-{name}.toml"
            cfg.write_text(robot_toml(name, str(board), lidar, router_ep, broker.port if broker else None))
            log = (tmp / f"agent-{name}.log").open("wb")
            agents[name] = subprocess.Popen(
                [exe, "agent", "--config", str(cfg)], stdin=subprocess.DEVNULL, stdout=log, stderr=log
            )
        procs = list(agents.values())
        if driving:
            threading.Thread(
                target=drive, args=(session, list(agents), stop_driving, teleops), name="drive", daemon=True
            ).start()
        t_start = time.perf_counter()
        while len(console.heard) < n:
            dead = [k for k, p in agents.items() if p.poll() is not None]
            if dead:
                raise SystemExit(f"agents exited: {dead}; logs in {tmp}")
            if time.perf_counter() - t_start > warmup_timeout:
                raise SystemExit(f"only {len(console.heard)} of {n} robots heard after {warmup_timeout:.0f} s")
            time.sleep(0.2)
        time.sleep(2.0)  # let the last ones settle
        startup_s = time.perf_counter() - t_start
        pids = {k: p.pid for k, p in agents.items()}
        cpu0 = {k: cpu_seconds(pid) for k, pid in pids.items()}
        self_cpu0, field_cpu0, router_cpu0 = cpu_seconds(os.getpid()), cpu_seconds(fld.pid), cpu_seconds(router.pid)
        broker_pid = broker.pid if broker is not None else None
        broker_cpu0 = cpu_seconds(broker_pid) if broker_pid else 0.0
        rss_max = dict.fromkeys(pids, 0)
        with console.lock:
            console.measuring = True
        t0 = time.perf_counter()
        end = t0 + seconds
        while (now := time.perf_counter()) < end:
            for k, pid in pids.items():
                rss_max[k] = max(rss_max[k], rss_bytes(pid))
            time.sleep(min(1.0, max(0.0, end - now)))
        with console.lock:
            console.measuring = False
        window = time.perf_counter() - t0
        cpu = {k: (cpu_seconds(pid) - cpu0[k]) / window for k, pid in pids.items()}
        self_cpu = (cpu_seconds(os.getpid()) - self_cpu0) / window
        field_cpu = (cpu_seconds(fld.pid) - field_cpu0) / window
        router_cpu = (cpu_seconds(router.pid) - router_cpu0) / window
        broker_cpu = (cpu_seconds(broker_pid) - broker_cpu0) / window if broker_pid else 0.0
        crashed = [k for k, p in agents.items() if p.poll() is not None]
        received = sum(console.counts.values())
        expected = POSE_HZ * n * window
        span = sum(max(v) - min(v) + 1 for v in console.ids.values() if v)
        return {
            "robots": n,
            "seconds_s": window,
            "startup_s": startup_s,
            "lidar_rate_hz": lidar_hz,
            "lidar_samples_per_s": lidar_samples if lidar_hz > 0 else 0.0,
            "mqtt": use_mqtt,
            "poses_expected": expected,
            "poses_received": received,
            "delivered_ratio": received / expected,
            "delivered_by_sequence_ratio": received / span if span else 0.0,
            "rate_min_robot_hz": min(console.counts.get(k, 0) for k in pids) / window,
            "staleness_p50_s": pct(console.staleness, 0.50),
            "staleness_p99_s": pct(console.staleness, 0.99),
            "staleness_max_s": max(console.staleness, default=float("nan")),
            "bad_poses": console.bad,
            "driving": driving,
            "teleops_sent": teleops[0],
            "robots_turning": len(console.turning),
            "agent_cpu_mean_ratio": statistics.fmean(cpu.values()),
            "agent_cpu_max_ratio": max(cpu.values()),
            "agent_rss_mean_bytes": statistics.fmean(rss_max.values()),
            "agent_rss_max_bytes": max(rss_max.values()),
            "field_cpu_ratio": field_cpu,
            "console_cpu_ratio": self_cpu,
            "router_cpu_ratio": router_cpu,
            "broker_cpu_ratio": broker_cpu,
            "agent_cpu_total_ratio": sum(cpu.values()),
            "host_cpus": os.cpu_count() or 0,
            "agents_crashed": len(crashed),
        }
    finally:
        stop_driving.set()
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        if session is not None:
            session.close()
        if fld is not None:
            end_child(fld)
        router.stop()
        if broker is not None:
            broker.stop()


@dataclass
class Commander:
    """Teleops to a few light robots from the console's session; their acks timed on arrival."""

    robots: list[str]
    measuring: bool = False
    sent: dict[tuple[str, int], float] = field(default_factory=dict)
    rtt: list[float] = field(default_factory=list)
    refused: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_ack(self, sample: Any) -> None:
        from fleetlink.shared import wire
        from fleetlink.shared.messages import Ack, AckResult

        now = time.perf_counter()
        try:
            msg = wire.decode_key(str(sample.key_expr), sample.payload.to_bytes())
        except wire.WireError:
            return
        if not isinstance(msg, Ack) or msg.commandSender != LIGHT_OPERATOR:
            return
        with self.lock:
            t = self.sent.pop((msg.header.robot, msg.commandHeaderId), None)
            if t is not None and self.measuring:
                self.rtt.append(now - t)
                self.refused += msg.result is not AckResult.ACCEPTED

    def drive(self, session: Any, stop: threading.Event) -> None:
        from fleetlink.shared import wire
        from fleetlink.shared.clock import SystemClock
        from fleetlink.shared.messages import Teleop

        counter = wire.HeaderCounter(SystemClock(), robot=self.robots[0], sender=LIGHT_OPERATOR)
        next_t = time.perf_counter()
        while not stop.is_set():
            for r in self.robots:
                msg = Teleop(header=counter.header(Teleop.TOPIC, robot=r), v=0.0, omega=DRIVE_OMEGA, ttl_s=0.6)
                with self.lock:
                    if self.measuring:
                        self.sent[(r, msg.header.headerId)] = time.perf_counter()
                session.put(wire.key_of(msg), wire.encode(msg))
            next_t += 1.0 / TELEOP_HZ
            stop.wait(max(0.0, next_t - time.perf_counter()))


LIGHT_OPERATOR = "op-bench"


def light_phase(
    where: str, endpoint: str, n: int, seconds: float, command_robots: int, pids: dict[str, int], warmup_timeout: float
) -> dict[str, Any]:
    """One measurement: a console session on ``endpoint`` for ``seconds`` after every robot was heard."""
    import zenoh

    from fleetlink.field.light import light_names
    from fleetlink.links.zenoh import peer_config

    console = Console()
    commander = Commander(light_names(n)[:command_robots])
    stop = threading.Event()
    session = zenoh.open(peer_config(connect=[endpoint], mode="client"))
    try:
        session.declare_subscriber("fleetlink/v1/*/pose", console.on_sample)
        session.declare_subscriber("fleetlink/v1/*/ack", commander.on_ack)
        t_start = time.perf_counter()
        while len(console.heard) < n:
            if time.perf_counter() - t_start > warmup_timeout:
                raise SystemExit(f"{where}: only {len(console.heard)} of {n} light robots heard")
            time.sleep(0.2)
        driver = None
        if command_robots:
            driver = threading.Thread(target=commander.drive, args=(session, stop), name="commands", daemon=True)
            driver.start()
        time.sleep(1.0)
        cpu0 = {k: cpu_seconds(pid) for k, pid in pids.items()}
        with console.lock, commander.lock:
            console.measuring = commander.measuring = True
        t0 = time.perf_counter()
        time.sleep(seconds)
        with console.lock, commander.lock:
            console.measuring = commander.measuring = False
        window = time.perf_counter() - t0
        cpu = {k: (cpu_seconds(pid) - cpu0[k]) / window for k, pid in pids.items()}
        time.sleep(1.0)  # the last acks
        with commander.lock:
            unanswered = len(commander.sent)
        stop.set()
        if driver is not None:
            driver.join(5)
    finally:
        stop.set()
        session.close()
    received = sum(console.counts.values())
    expected = POSE_HZ * n * window
    span = sum(max(v) - min(v) + 1 for v in console.ids.values() if v)
    answered = len(commander.rtt)
    return {
        "console_on": where,
        "seconds_s": window,
        "poses_expected": expected,
        "poses_received": received,
        "delivered_ratio": received / expected,
        "delivered_by_sequence_ratio": received / span if span else 0.0,
        "rate_min_robot_hz": min(console.counts.get(k, 0) for k in light_names(n)) / window,
        "staleness_p50_s": pct(console.staleness, 0.50),
        "staleness_p99_s": pct(console.staleness, 0.99),
        "staleness_max_s": max(console.staleness, default=float("nan")),
        "bad_poses": console.bad,
        "commands_acked": answered,
        "commands_unanswered": unanswered,
        "commands_refused": commander.refused,
        "acked_ratio": answered / (answered + unanswered) if answered + unanswered else 0.0,
        "ack_rtt_p50_s": pct(commander.rtt, 0.50),
        "ack_rtt_p99_s": pct(commander.rtt, 0.99),
        "cpu_ratio": cpu,
    }


def run_light(n: int, seconds: float, command_robots: int, warmup_timeout: float) -> dict[str, Any]:
    """``--light``: ``n`` light robots on router A of a two-router mesh; the console on A, then on B."""
    from fleetlink.shared import keys
    from fleetlink.site.mesh import RouterMesh

    tmp = Path(tempfile.mkdtemp(prefix="fleetlink-scale-light-"))
    exe = str(Path(sys.executable).parent / "fleetlink")
    with RouterMesh() as mesh:
        log_path = tmp / "light.log"
        with log_path.open("wb") as log:
            argv = [exe, "field", "--light", str(n), "--zenoh-connect", mesh.a.listen, "--zenoh-listen", "none"]
            fleet = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
        try:
            pids = {"light_fleet": fleet.pid, "router_a": mesh.a.pid, "router_b": mesh.b.pid, "console": os.getpid()}
            one = light_phase("router A", mesh.a.listen, n, seconds, command_robots, pids, warmup_timeout)
            two = light_phase("router B", mesh.b.listen, n, seconds, command_robots, pids, warmup_timeout)
        finally:
            end_child(fleet)
    status = [line for line in log_path.read_text(errors="replace").splitlines() if line.startswith("t=")]
    return {
        "robots": n,
        "light": True,
        "tokens": f"{keys.ALIVE_PREFIX}/<robot>",  # the contract's (keys.alive_key), as agents declare
        "command_robots": command_robots,
        "teleop_rate_hz": TELEOP_HZ,
        "host_cpus": os.cpu_count() or 0,
        "load_average_1min": os.getloadavg()[0],
        "one_router": one,
        "mesh": two,
        "light_fleet_last_status": status[-1] if status else "",
        "light_fleet_crashed": fleet.returncode not in (0, -15),
    }


def run_lossy(
    n: int, seconds: float, losses: list[float], command_robots: int, warmup_timeout: float
) -> dict[str, Any]:
    """``--light --lossy``: ``n`` light robots behind a lossy link (tests/harness/lossy.py: a network
    namespace whose packets the kernel drops at random, each way), a client of one router on the
    link's host end; the console on that router. One phase per loss rate, the same fleet."""
    from fleetlink.site.brokers import free_port
    from fleetlink.site.mesh import ZenohRouter
    from tests.harness.lossy import LossyLink

    why = LossyLink.unavailable()
    if why is not None:
        raise SystemExit(f"--lossy: {why}")
    tmp = Path(tempfile.mkdtemp(prefix="fleetlink-scale-lossy-"))
    exe = str(Path(sys.executable).parent / "fleetlink")
    phases: list[dict[str, Any]] = []
    with LossyLink() as link:
        router = ZenohRouter(f"tcp/{link.host_ip}:{free_port(link.host_ip)}").start()
        log_path = tmp / "light.log"
        try:
            with log_path.open("wb") as log:
                argv = link.argv([exe, "field", "--light", str(n), "--zenoh-connect", router.listen])
                fleet = subprocess.Popen(
                    [*argv, "--zenoh-listen", "none"], stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT
                )
            try:
                pids = {"light_fleet": fleet.pid, "router": router.pid, "console": os.getpid()}
                for loss in losses:
                    link.set_loss(loss)
                    dropped0 = link.dropped()
                    phase = light_phase(
                        f"{loss:g} % loss", router.listen, n, seconds, command_robots, pids, warmup_timeout
                    )
                    phase["loss_ratio"] = loss / 100.0
                    phase["packets_dropped"] = link.dropped() - dropped0
                    phases.append(phase)
            finally:
                end_child(fleet)
        finally:
            router.stop()
    return {
        "robots": n,
        "light": True,
        "lossy": True,
        "command_robots": command_robots,
        "teleop_rate_hz": TELEOP_HZ,
        "host_cpus": os.cpu_count() or 0,
        "load_average_1min": os.getloadavg()[0],
        "phases": phases,
    }


def lossy_table(r: dict[str, Any]) -> str:
    head = (
        f"{r['robots']} light robots behind a lossy link (a network namespace, packets dropped at random each "
        f"way by the kernel; no added delay), clients of one router; the console on it; teleops to "
        f"{r['command_robots']} robots at {r['teleop_rate_hz']:g} Hz each; {r['host_cpus']} CPUs, load average "
        f"{r['load_average_1min']:.1f} at the end"
    )
    lines = [
        head,
        f"{'loss':>6} {'delivered':>10} {'by seq':>9} {'stale p50':>10} {'p99':>8} {'max':>8} "
        f"{'acked':>8} {'ack p50':>8} {'ack p99':>8} {'dropped':>8}",
    ]
    for p in r["phases"]:
        lines.append(
            f"{p['loss_ratio'] * 100:5.1f}% {p['delivered_ratio'] * 100:9.3f}% {p['delivered_by_sequence_ratio'] * 100:8.3f}% "
            f"{p['staleness_p50_s'] * 1e3:8.1f}ms {p['staleness_p99_s'] * 1e3:6.0f}ms {p['staleness_max_s'] * 1e3:6.0f}ms "
            f"{p['acked_ratio'] * 100:7.2f}% {p['ack_rtt_p50_s'] * 1e3:6.1f}ms {p['ack_rtt_p99_s'] * 1e3:6.0f}ms "
            f"{p['packets_dropped']:8d}"
        )
    return "\n".join(lines)


def light_table(r: dict[str, Any]) -> str:
    one, two = r["one_router"], r["mesh"]
    rows: list[tuple[str, Any, str]] = [
        ("poses delivered", lambda p: f"{p['delivered_ratio'] * 100:.3f} %", ">= 99.9 %"),
        ("  by sequence (lost on the way)", lambda p: f"{p['delivered_by_sequence_ratio'] * 100:.3f} %", ""),
        ("  slowest robot's pose rate", lambda p: f"{p['rate_min_robot_hz']:.2f} Hz", "20 Hz"),
        ("staleness p50", lambda p: f"{p['staleness_p50_s'] * 1e3:.1f} ms", ""),
        ("staleness p99", lambda p: f"{p['staleness_p99_s'] * 1e3:.1f} ms", "<= 100 ms"),
        ("staleness max", lambda p: f"{p['staleness_max_s'] * 1e3:.1f} ms", ""),
        ("commands acked", lambda p: f"{p['acked_ratio'] * 100:.2f} % of {p['commands_acked'] + p['commands_unanswered']}", ""),
        ("ack round trip p50", lambda p: f"{p['ack_rtt_p50_s'] * 1e3:.1f} ms", ""),
        ("ack round trip p99", lambda p: f"{p['ack_rtt_p99_s'] * 1e3:.1f} ms", ""),
    ]  # fmt: skip
    for who in ("light_fleet", "router_a", "router_b", "console"):
        rows.append((f"CPU: {who.replace('_', ' ')}", lambda p, w=who: f"{p['cpu_ratio'][w] * 100:.1f} %", ""))
    head = (
        f"{r['robots']} light robots in one process on router A; console on router A (one router), then on "
        f"router B (two-router mesh); teleops to {r['command_robots']} robots at {r['teleop_rate_hz']:g} Hz each; "
        f"liveliness tokens at {r.get('tokens', 'fleetlink/alive/v1/<robot>')}; "
        f"{r['host_cpus']} CPUs, load average {r['load_average_1min']:.1f} at the end (other work on the host)"
    )
    lines = [head, f"{'':34} {'mesh (B)':>22} {'one router (A)':>22} {'goal':>10}"]
    for name, fmt, goal in rows:
        lines.append(f"{name:34} {fmt(two):>22} {fmt(one):>22} {goal:>10}")
    lines.append(f"light fleet's last status: {r['light_fleet_last_status']}")
    met = two["delivered_ratio"] >= GOALS["delivered_ratio"] and two["staleness_p99_s"] <= GOALS["staleness_p99_s"]
    lines.append(f"goals through the mesh {'met' if met else 'NOT met'}")
    return "\n".join(lines)


def table(r: dict[str, Any]) -> str:
    rows = [
        ("poses delivered", f"{r['delivered_ratio'] * 100:.3f} %", ">= 99.9 %", r["delivered_ratio"] / 0.999),
        ("  by sequence (lost on the way)", f"{r['delivered_by_sequence_ratio'] * 100:.3f} %", "", None),
        ("  slowest robot's pose rate", f"{r['rate_min_robot_hz']:.2f} Hz", "20 Hz", r["rate_min_robot_hz"] / POSE_HZ),
        ("staleness p50", f"{r['staleness_p50_s'] * 1e3:.1f} ms", "", None),
        ("staleness p99", f"{r['staleness_p99_s'] * 1e3:.1f} ms", "<= 100 ms", r["staleness_p99_s"] / 0.100),
        ("staleness max", f"{r['staleness_max_s'] * 1e3:.1f} ms", "", None),
        (
            "agent RSS max",
            f"{r['agent_rss_max_bytes'] / 2**20:.1f} MB",
            "<= 80 MB",
            r["agent_rss_max_bytes"] / 2**20 / 80,
        ),
        ("agent RSS mean", f"{r['agent_rss_mean_bytes'] / 2**20:.1f} MB", "", None),
        (
            "agent CPU mean / max",
            f"{r['agent_cpu_mean_ratio'] * 100:.1f} / {r['agent_cpu_max_ratio'] * 100:.1f} %",
            "",
            None,
        ),
        ("agents' CPU, all together", f"{r['agent_cpu_total_ratio'] * 100:.1f} %", "", None),
        ("field CPU", f"{r['field_cpu_ratio'] * 100:.1f} %", "", None),
        ("console CPU", f"{r['console_cpu_ratio'] * 100:.1f} %", "", None),
        ("router CPU", f"{r['router_cpu_ratio'] * 100:.1f} %", "", None),
        ("broker CPU", f"{r['broker_cpu_ratio'] * 100:.1f} %", "", None),
    ]
    lidar = (
        f"{r['lidar_rate_hz']:g} Hz x {r['lidar_samples_per_s'] / r['lidar_rate_hz']:.0f} samples, mapped by each agent"
        if r["lidar_rate_hz"]
        else "off"
    )
    head = (
        f"{r['robots']} robots, {r['seconds_s']:.0f} s measured, agents in separate processes, "
        f"lidar {lidar}, MQTT {'on' if r['mqtt'] else 'off'}, "
        + (
            f"driven by teleop ({r['robots_turning']} of {r['robots']} robots seen turning), "
            if r["driving"]
            else "idle, "
        )
        + f"{r['host_cpus']} CPUs; {r['agents_crashed']} agents crashed, {r['bad_poses']} undecodable poses"
    )
    lines = [head, f"{'':34} {'ours':>16} {'goal':>10} {'ratio':>7}"]
    for name, ours, goal, ratio in rows:
        lines.append(f"{name:34} {ours:>16} {goal:>10} {'' if ratio is None else f'{ratio:.3f}':>7}")
    met = (
        r["delivered_ratio"] >= GOALS["delivered_ratio"]
        and r["staleness_p99_s"] <= GOALS["staleness_p99_s"]
        and r["agent_rss_max_bytes"] <= GOALS["agent_rss_max_bytes"]
    )
    lines.append(f"goals {'met' if met else 'NOT met'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--lidar-hz", type=float, default=1.0, help="lidar turns per second (0: no lidars)")
    ap.add_argument("--lidar-samples", type=float, default=720.0, help="lidar measurements per second")
    ap.add_argument("--drive", action="store_true", help="the console drives every robot (teleop, 4 Hz each)")
    ap.add_argument("--no-mqtt", action="store_true", help="agents on Zenoh only (no broker)")
    ap.add_argument("--warmup-timeout", type=float, default=120.0)
    ap.add_argument("--light", action="store_true", help="light robots through a two-router mesh, no agents")
    ap.add_argument("--command-robots", type=int, default=50, help="with --light: robots sent teleops (4 Hz each)")
    ap.add_argument(
        "--lossy",
        metavar="PERCENTS",
        help="with --light: the robots behind a lossy link, one phase per loss rate (e.g. 0,1,5,10; needs root, ip, nft)",
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.lossy and not args.light:
        ap.error("--lossy needs --light")
    if args.light and args.lossy:
        losses = [float(x) for x in args.lossy.split(",")]
        r = run_lossy(args.robots, args.seconds, losses, min(args.command_robots, args.robots), args.warmup_timeout)
        print(lossy_table(r))
        if args.json:
            args.json.write_text(json.dumps(r, indent=2) + "\n")
        return 0
    if args.light:
        r = run_light(args.robots, args.seconds, min(args.command_robots, args.robots), args.warmup_timeout)
        print(light_table(r))
        if args.json:
            args.json.write_text(json.dumps(r, indent=2) + "\n")
        return 0
    r = run(
        args.robots, args.seconds, args.lidar_hz, not args.no_mqtt, args.warmup_timeout, args.lidar_samples, args.drive
    )
    print(table(r))
    if args.json:
        args.json.write_text(json.dumps(r, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
