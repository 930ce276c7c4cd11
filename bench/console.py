"""Is the console responsive with 50 robots reporting at 10 Hz?

    python bench/console.py [--robots 50] [--pose-hz 10] [--seconds 8] [--json FILE]

The real ConsoleApp (headless, Textual's run_test at 160x48) on the real OperatorLink over
in-memory transports; a feeder thread pushes every robot's Pose at ``--pose-hz`` (10 Hz; 20 is
an agent's and a light robot's rate) and State at 1 Hz through the link's decode path, robots drive in circles so table and map change every frame. Measured:

* frame time: the console's periodic refresh (fleet model under the lock, table cells, map cell
  table, status), p50/p99, while the feed runs;
* input latency: a drive key posted to the app until its Teleop reaches the transport (stamped in
  the transport's publish), p50/p99; a stop key between two presses, posted the same way.

Baseline, same run: the same figures with one robot. Goal: frame p99 well under the 100 ms
refresh period and input latency p99 under 50 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import statistics
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from textual import events  # noqa: E402

from fleetlink.shared.messages import (  # noqa: E402
    AgvPosition,
    BatteryState,
    CommsPolicy,
    Contact,
    LinkStatus,
    OperatingMode,
    SafetyState,
    State,
    Teleop,
    Velocity,
)
from tests.harness.console_rig import Rig  # noqa: E402


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


def feed(rig: Rig, n: int, stop: threading.Event, hz: float = 10.0) -> None:
    t0 = time.monotonic()
    tick = 0
    state_every = max(1, round(hz))
    while not stop.is_set():
        t = time.monotonic() - t0
        for i in range(n):
            robot = f"r{i:02d}"
            th = 0.3 * t + i
            x, y = 10 * (i % 10) + 2 * math.cos(th), 10 * (i // 10) + 2 * math.sin(th)
            rig.pose(robot, x, y, math.atan2(math.sin(th + 1.57), math.cos(th + 1.57)), links=("zenoh",))
            if tick % state_every == 0:
                st = rig.counter(robot).make(
                    State,
                    agvPosition=AgvPosition(x=x, y=y, theta=0.0, mapId="", positionInitialized=True, localizationScore=1.0),
                    velocity=Velocity(vx=0.6, omega=0.3), batteryState=BatteryState(batteryCharge=80.0, charging=False),
                    errors=(), operatingMode=OperatingMode.AUTOMATIC,
                    safetyState=SafetyState(eStop="NONE", fieldViolation=False), driveMode="goto",  # type: ignore[arg-type]
                    links=LinkStatus(zenoh=True, mqtt=True), uwbStale=False, payloadOn=False, boardConnected=True,
                    orderId="", orderUpdateId=0, goal=None, driving=True, paused=False, home=None,
                    contact=Contact(policy=CommsPolicy.STOP, lost=False, action="", silent_s=0.0),
                )  # fmt: skip
                rig.zenoh.inject(st)
        tick += 1
        stop.wait(max(0.0, t0 + tick / hz - time.monotonic()))


async def measure(n: int, seconds: float, tmp: Path, hz: float = 10.0) -> dict[str, float]:
    rig = Rig(tmp)
    rig.link.start()
    stop = threading.Event()
    feeder = threading.Thread(target=feed, args=(rig, n, stop, hz), daemon=True)
    teleops: list[float] = []
    """When each Teleop reached the (Zenoh) transport."""
    publish = rig.zenoh.publish

    def stamped(key: str, payload: bytes) -> bool:
        if f"/{Teleop.TOPIC}/" in key + "/":
            teleops.append(time.monotonic())
        return publish(key, payload)

    rig.zenoh.publish = stamped  # type: ignore[method-assign]
    try:
        async with rig.app.run_test(size=(160, 48)):
            feeder.start()
            await asyncio.sleep(1.0)
            rig.app.frame_times.clear()
            latencies: list[float] = []
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                for key in ("i", "space"):  # then stop, so the next "i" is a change and goes out at once
                    before = len(teleops)
                    t0 = time.monotonic()
                    rig.app.post_message(events.Key(key, " " if key == "space" else key))
                    while len(teleops) == before and time.monotonic() - t0 < 2:
                        await asyncio.sleep(0.0005)
                    if key == "i":  # stamped where it reaches the transport, not when this loop looks
                        latencies.append((teleops[before] if len(teleops) > before else time.monotonic()) - t0)
                await asyncio.sleep(0.15)
            frames = list(rig.app.frame_times)
            shown = len(rig.app.query_one("#fleet").rows)
    finally:
        stop.set()
        feeder.join(2)
        rig.link.close()
    return {
        "robots": n,
        "robots_shown": shown,
        "frames": len(frames),
        "frame_p50_s": statistics.median(frames),
        "frame_p99_s": pct(frames, 0.99),
        "input_p50_s": statistics.median(latencies),
        "input_p99_s": pct(latencies, 0.99),
        "inputs": len(latencies),
    }


def main() -> int:
    import tempfile

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robots", type=int, default=50)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--pose-hz", type=float, default=10.0, help="each robot's pose rate (state: 1 Hz)")
    parser.add_argument(
        "--refresh-goal-ms", type=float, default=100.0, help="refresh p99 goal (issue 18, 500 robots: 50)"
    )
    parser.add_argument("--json", type=Path, help="also write the figures as JSON (SI units)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        base = asyncio.run(measure(1, args.seconds, Path(tmp), args.pose_hz))
        full = asyncio.run(measure(args.robots, args.seconds, Path(tmp), args.pose_hz))
    print(
        f"console responsiveness, robots reporting pose at {args.pose_hz:g} Hz (+ state at 1 Hz), {args.seconds:g} s each"
    )
    print(f"{'':22} {f'{args.robots} robots':>12} {'1 robot':>10} {'ratio':>7}")
    for key, label in (("frame_p50_s", "refresh p50 ms"), ("frame_p99_s", "refresh p99 ms"),
                       ("input_p50_s", "key->teleop p50 ms"), ("input_p99_s", "key->teleop p99 ms")):  # fmt: skip
        print(f"{label:22} {1e3 * full[key]:12.2f} {1e3 * base[key]:10.2f} {full[key] / base[key]:6.1f}x")
    print(f"rows shown {full['robots_shown']}/{args.robots}; {full['frames']} refreshes, {full['inputs']} key presses")
    ok = full["frame_p99_s"] < args.refresh_goal_ms / 1e3 and full["input_p99_s"] < 0.05
    print(f"goal: refresh p99 < {args.refresh_goal_ms:g} ms and key->teleop p99 < 50 ms: {'MET' if ok else 'NOT MET'}")
    if args.json:
        figures = {"robots_n": full, "one_robot": base, "frame_p99_ratio": full["frame_p99_s"] / base["frame_p99_s"],
                   "input_p99_ratio": full["input_p99_s"] / base["input_p99_s"], "goal_met": ok,
                   "refresh_p99_goal_s": args.refresh_goal_ms / 1e3, "pose_rate_hz": args.pose_hz}  # fmt: skip
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
