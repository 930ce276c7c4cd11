"""Benchmark: what the flight recorder costs while 50 robots talk.

    .venv/bin/python bench/record.py [--robots 50] [--seconds 20] [--json FILE]

A generator process publishes, for each of ``--robots`` synthetic robots, wire-valid traffic at an
agent's rates through the link layer: ``Pose`` at 20 Hz on Zenoh and every second one on MQTT
(10 Hz, as an agent does while Zenoh is up), ``State`` at 1 Hz on both links. (bench/scale.py runs
real agents, an OS process each: too heavy to leave a core for measuring a recorder, so the
traffic here is synthetic but byte-for-byte what agents send.) Zenoh: the generator listens, the
subscriber connects (loopback, multicast scouting off); MQTT: a private Mosquitto.

Two subscribers in turn, each its own process, over the same traffic for ``--seconds`` after a
warm-up:

* **baseline**: the same links (``fleetlink.links`` Zenoh and MQTT endpoints, subscribed to
  everything), decoding every message with ``wire.decode_key`` and nothing else;
* **recorder**: ``fleetlink record --out FILE`` (decode, JSON, Foxglove poses, MCAP zstd chunks).

Measured from /proc: each process's CPU time (user + system) over the window divided by the wall
time, i.e. the share of one core, and the recorder's by thread (/proc/<pid>/task: zenoh's threads
by their names, the Python threads together as ``python``). Goal: the recorder <= 10 % of one core
at 50 robots. The table also gives the load average, the messages recorded, the file's size and
rate. ``--recorder-only`` skips the baselines: more runs in the time, to alternate two versions
on a busy host.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

CLK_TCK = os.sysconf("SC_CLK_TCK")
POSE_HZ = 20.0
GOAL_CPU_SHARE = 0.10
WARMUP_S = 4.0


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime + stime


# -- the processes --------------------------------------------------------------------------------


def generate(robots: int, listen: str, mqtt_url: str) -> None:
    """Publish every robot's poses and states until killed."""
    from fleetlink.links.mqtt import MqttEndpoint
    from fleetlink.links.zenoh import ZenohEndpoint
    from fleetlink.operator.links import mqtt_settings_for
    from fleetlink.shared import wire
    from fleetlink.shared.clock import SystemClock
    from fleetlink.shared.messages import Pose, State
    from tests.harness.messages import state_fields

    clock = SystemClock()
    zenoh = ZenohEndpoint(listen=[listen], label="zenoh-generator")
    mqtt = MqttEndpoint(mqtt_settings_for(mqtt_url), client_id="generator", label="mqtt-generator")
    zenoh.start()
    mqtt.start()
    names = [f"r{i:02d}" for i in range(robots)]
    counters = {n: wire.HeaderCounter(clock, robot=n, sender=f"agent-{n}") for n in names}
    period = 1.0 / POSE_HZ
    tick = 0
    next_at = time.monotonic()
    while True:
        for i, name in enumerate(names):
            c = counters[name]
            x = (tick * 0.01 + i) % 50.0
            pose = c.make(
                Pose, x=x, y=float(i), theta=0.1, sd_x_m=0.05, sd_y_m=0.05, sd_theta_rad=0.01,
                odom_x=x, odom_y=float(i), odom_theta=0.1, vx=0.2, omega=0.0, uwbStale=False,
            )  # fmt: skip
            raw = wire.encode(pose)
            key = wire.key_of(pose)
            zenoh.publish(key, raw)
            if tick % 2 == 0:
                mqtt.publish(key, raw)
            if tick % int(POSE_HZ) == i % int(POSE_HZ):
                state = c.make(State, **state_fields())
                raw, key = wire.encode(state), wire.key_of(state)
                zenoh.publish(key, raw)
                mqtt.publish(key, raw)
        tick += 1
        next_at += period
        time.sleep(max(0.0, next_at - time.monotonic()))


def decode_only(connect: str, mqtt_url: str, decode: bool = True) -> None:
    """The baselines: the recorder's links, every message decoded (or only counted), nothing written."""
    import signal

    from fleetlink.shared import keys, wire
    from fleetlink.site.recorder import open_recorder_links

    count = [0, 0]

    def receive(key: str, payload: bytes) -> None:
        if not decode:
            count[0] += 1
            return
        try:
            wire.decode_key(key, payload)
            count[0] += 1
        except wire.WireError:
            count[1] += 1

    links = open_recorder_links(mqtt_url=mqtt_url, zenoh_connect=[connect], client_id="baseline")
    for link in links:
        link.subscribe(keys.ZENOH_ALL, receive)
        link.start()
    stop = [False]
    signal.signal(signal.SIGTERM, lambda *_: stop.__setitem__(0, True))
    while not stop[0]:
        time.sleep(0.2)
    for link in links:
        link.close()
    print(json.dumps({"decoded": count[0], "rejected": count[1]}), flush=True)


# -- the run --------------------------------------------------------------------------------------


def thread_seconds(pid: int) -> dict[int, tuple[str, float]]:
    """Each thread of ``pid``: its name (``comm``: zenoh's Rust threads have their own, Python's
    threads are all named after the process) and its CPU seconds."""
    out: dict[int, tuple[str, float]] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                head, tail = f.read().rsplit(")", 1)
        except OSError:  # the thread ended
            continue
        fields = tail.split()
        out[int(tid)] = (head.split("(", 1)[1], (int(fields[11]) + int(fields[12])) / CLK_TCK)
    return out


def measure(proc: subprocess.Popen[Any], seconds: float) -> tuple[float, dict[str, float]]:
    """The share of one core ``proc`` took over ``seconds`` after the warm-up, and that share by
    thread name (``python`` for the process's own threads)."""
    time.sleep(WARMUP_S)
    threads0 = thread_seconds(proc.pid)
    c0, t0 = cpu_seconds(proc.pid), time.monotonic()
    time.sleep(seconds)
    c1, t1 = cpu_seconds(proc.pid), time.monotonic()
    threads1 = thread_seconds(proc.pid)
    wall = t1 - t0
    by_name: dict[str, float] = {}
    own = threads1.get(proc.pid, ("", 0.0))[0]  # the main thread's name: the Python threads'
    for tid, (name, cpu) in threads1.items():
        label = "python" if name == own else name
        by_name[label] = by_name.get(label, 0.0) + (cpu - threads0.get(tid, (name, 0.0))[1]) / wall
    return (c1 - c0) / wall, dict(sorted(by_name.items(), key=lambda kv: -kv[1]))


def run(robots: int, seconds: float, baselines: bool = True) -> dict[str, Any]:
    from fleetlink.site.brokers import MosquittoBroker, free_port
    from fleetlink.site.recorder import summarise

    py = sys.executable
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with tempfile.TemporaryDirectory(prefix="fleetlink-bench-record-") as tmp:
        work = Path(tmp)
        broker = MosquittoBroker(work / "mosquitto")
        broker.start()
        listen = f"tcp/127.0.0.1:{free_port()}"
        gen = subprocess.Popen(
            [py, __file__, "--role", "generator", "--robots", str(robots), "--listen", listen, "--mqtt", broker.url],
            env=env,
        )
        try:
            time.sleep(2.0)
            gen_c0, gen_t0 = cpu_seconds(gen.pid), time.monotonic()
            links_share = base_share = float("nan")
            decoded = {"decoded": 0}
            if baselines:
                bare = subprocess.Popen(
                    [py, __file__, "--role", "links", "--listen", listen, "--mqtt", broker.url],
                    env=env, stdout=subprocess.PIPE, text=True,
                )  # fmt: skip
                links_share, _ = measure(bare, seconds)
                bare.terminate()
                bare.communicate(timeout=30)
                base = subprocess.Popen(
                    [py, __file__, "--role", "baseline", "--listen", listen, "--mqtt", broker.url],
                    env=env, stdout=subprocess.PIPE, text=True,
                )  # fmt: skip
                base_share, _ = measure(base, seconds)
                base.terminate()
                out, _ = base.communicate(timeout=30)
                decoded = json.loads(out.strip().splitlines()[-1])
            load_before = os.getloadavg()[0]
            mcap = work / "bench.mcap"
            fleetlink = str(Path(py).with_name("fleetlink"))
            rec = subprocess.Popen(
                [fleetlink, "--log-level", "WARNING", "record", "--out", str(mcap), "--zenoh-connect", listen,
                 "--mqtt", broker.url],
                env=env, stderr=subprocess.DEVNULL,
            )  # fmt: skip
            rec_share, rec_threads = measure(rec, seconds)
            load_after = os.getloadavg()[0]
            rec.terminate()
            rec.wait(timeout=30)
            gen_share = (cpu_seconds(gen.pid) - gen_c0) / (time.monotonic() - gen_t0)
        finally:
            gen.kill()
            gen.wait()
            broker.stop()
        summary = summarise(mcap)
        size = mcap.stat().st_size
        wire_msgs = sum(c.messages for c in summary.channels if c.topic.startswith("/fleetlink/"))
        return {
            "robots": robots,
            "window_s": seconds,
            "recorder_cpu_share_of_core_ratio": rec_share,
            "recorder_threads_cpu_share_of_core_ratio": rec_threads,
            "load_average_1min_at_recorder_start": load_before,
            "load_average_1min_at_recorder_end": load_after,
            "baseline_decode_only_cpu_share_of_core_ratio": base_share,
            "baseline_links_only_cpu_share_of_core_ratio": links_share,
            "generator_cpu_share_of_core_ratio": gen_share,
            "goal_cpu_share_of_core_ratio": GOAL_CPU_SHARE,
            "recorded_messages": summary.messages,
            "recorded_wire_messages": wire_msgs,
            "recording_duration_s": summary.duration_s,
            "recorded_wire_message_rate_hz": wire_msgs / summary.duration_s if summary.duration_s else 0.0,
            "baseline_decoded_messages": decoded["decoded"],
            "file_size_bytes": size,
            "file_rate_bytes_per_second": size / summary.duration_s if summary.duration_s else 0.0,
            "file_complete": summary.complete,
        }


def table(r: dict[str, Any]) -> str:
    ok = "ok" if r["recorder_cpu_share_of_core_ratio"] <= r["goal_cpu_share_of_core_ratio"] else "OVER"
    rows = [
        ("robots (pose 20 Hz Zenoh + 10 Hz MQTT, state 1 Hz both)", f"{r['robots']}", ""),
        ("baseline: the links only (messages counted), CPU of one core", f"{r['baseline_links_only_cpu_share_of_core_ratio']:.1%}", ""),
        ("baseline: the links + wire.decode_key, CPU of one core", f"{r['baseline_decode_only_cpu_share_of_core_ratio']:.1%}", ""),
        ("recorder (fleetlink record), CPU of one core", f"{r['recorder_cpu_share_of_core_ratio']:.1%}", f"goal <= 10 %: {ok}"),
        ("  by thread: " + ", ".join(f"{k} {v:.1%}" for k, v in list(r["recorder_threads_cpu_share_of_core_ratio"].items())[:6]), "", ""),
        ("load average (1 min) while the recorder ran", f"{r['load_average_1min_at_recorder_start']:.1f}", f"..{r['load_average_1min_at_recorder_end']:.1f}"),
        ("recorder minus baseline", f"{r['recorder_cpu_share_of_core_ratio'] - r['baseline_decode_only_cpu_share_of_core_ratio']:.1%}", ""),
        ("generator process, CPU of one core", f"{r['generator_cpu_share_of_core_ratio']:.1%}", ""),
        ("wire messages recorded per second", f"{r['recorded_wire_message_rate_hz']:.0f}", ""),
        ("messages in the file (with Foxglove poses)", f"{r['recorded_messages']}", ""),
        ("file size, rate", f"{r['file_size_bytes'] / 1e6:.2f} MB", f"{r['file_rate_bytes_per_second'] / 1e3:.0f} kB/s"),
    ]  # fmt: skip
    w = max(len(a) for a, _, _ in rows)
    return "\n".join(f"{a:<{w}}  {b:>10}  {c}" for a, b, c in rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robots", type=int, default=50)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--json", type=Path, help="write the figures here (SI units, units in the keys)")
    parser.add_argument(
        "--recorder-only", action="store_true", help="skip the two baselines (more runs in the time, to alternate)"
    )
    parser.add_argument(
        "--role", choices=("bench", "generator", "baseline", "links"), default="bench", help=argparse.SUPPRESS
    )
    parser.add_argument("--listen", help=argparse.SUPPRESS)
    parser.add_argument("--mqtt", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.role == "generator":
        generate(args.robots, args.listen, args.mqtt)
        return 0
    if args.role in ("baseline", "links"):
        decode_only(args.listen, args.mqtt, decode=args.role == "baseline")
        return 0
    result = run(args.robots, args.seconds, baselines=not args.recorder_only)
    print(table(result))
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
