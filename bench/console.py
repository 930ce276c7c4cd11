"""Is the console responsive with 50 robots reporting at 10 Hz?

    python bench/console.py [--robots 50] [--pose-hz 10] [--seconds 8] [--json FILE]

The real ConsoleApp (headless, Textual's run_test at 160x48) on the real OperatorLink over
in-memory transports. The robots run in a process of their own (as robots do): it builds and
encodes every robot's Pose at ``--pose-hz`` (10 Hz; 20 is an agent's and a light robot's rate)
and State at 1 Hz and sends each tick's bytes to the console's process, where a thread hands them
to the link's receive path (decode, link manager, feed), as Zenoh's callbacks do; robots drive in
circles so table and map change every frame. ``--encode-in-process`` builds and encodes them in
the console's process instead (the bench before 2026-11-28: the robots' encoding, ~50 us a
message, then shared the console's interpreter lock). Measured:

* frame time: the console's periodic refresh (fleet model under the lock, table cells, map cell
  table, status), p50/p99, while the feed runs;
* input latency: a drive key handed to the app's terminal driver on a keyboard thread (as a
  terminal's input thread hands it each key it read, ``Driver.process_message``) until its Teleop
  reaches the transport (stamped in the transport's publish), p50/p99; a stop key between two
  presses, handed on the same way (``--keys-from-loop``: posted to the app from its event loop, as
  the bench did before 2026-12-01);
* how many messages a second the console folded into its model (all of them, if it keeps up),
  and the host's load average.

With ``--maps``, each robot also has an onboard map of its 20 m x 20 m square at 0.05 m (walls
every 4 m) that changes once a second (as ``MapFollower`` hands the console a robot's map after
each update), and publishes its lidar ``Scan`` at 2 Hz through the link's decode path (the agents'
default ``[rates] scan_hz``): the map widget then rasters maps, draws the selected robot's scan and
re-renders the rows they touch.

Baseline, same run: the same figures with one robot. Goal: frame p99 well under the 100 ms
refresh period and input latency p99 under 50 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import multiprocessing
import os
import statistics
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from textual import events  # noqa: E402

from fleetlink.shared import wire  # noqa: E402
from fleetlink.shared.clock import SystemClock  # noqa: E402
from fleetlink.shared.messages import (  # noqa: E402
    AgvPosition,
    BatteryState,
    CommsPolicy,
    Contact,
    LinkStatus,
    OperatingMode,
    Pose,
    SafetyState,
    Scan,
    State,
    Teleop,
    Velocity,
)
from fleetlink.shared.scan_codec import scan_fields  # noqa: E402
from fleetlink.shared.wire import HeaderCounter  # noqa: E402
from tests.harness.console_rig import Rig  # noqa: E402

MAP_RES = 0.05
MAP_SIZE_M = 20.0


_CELLS: list[bytes] = []


def robot_grid(i: int) -> tuple[float, float, float, int, int, bytes]:
    """Robot ``i``'s onboard map (the fleet model's ``Grid``): its 20 m square around its circle,
    walls every 4 m; a new grid each call (as each map update hands the console a new one)."""
    n = int(MAP_SIZE_M / MAP_RES)
    if not _CELLS:
        cells = np.zeros((n, n), dtype=np.uint8)
        cells[::80, :] = 100
        cells[:, ::80] = 100
        cells[: n // 8, : n // 8] = 255  # a corner not seen yet
        _CELLS.append(cells.tobytes())
    ox, oy = 10 * (i % 10) - MAP_SIZE_M / 2, 10 * (i // 10) - MAP_SIZE_M / 2
    return (ox, oy, MAP_RES, n, n, _CELLS[0])


SCAN_ANGLES = np.arange(360) * (2 * math.pi / 360)
SCAN_RANGES = 3.0 + 0.5 * np.sin(4 * SCAN_ANGLES)


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


def robot_messages(
    n: int, t: float, tick: int, hz: float, maps: bool, counter: Callable[[str], HeaderCounter]
) -> list[wire.Message]:
    """What the ``n`` robots say at ``tick`` (``t`` s into the run): every robot's Pose, every
    second its State, with ``maps`` its Scan at 2 Hz (the robots spread over the ticks)."""
    out: list[wire.Message] = []
    state_every = max(1, round(hz))
    scan_every = max(1, round(hz / 2))
    for i in range(n):
        robot = f"r{i:02d}"
        th = 0.3 * t + i
        x, y = 10 * (i % 10) + 2 * math.cos(th), 10 * (i // 10) + 2 * math.sin(th)
        theta = math.atan2(math.sin(th + 1.57), math.cos(th + 1.57))
        out.append(counter(robot).make(
            Pose, x=x, y=y, theta=theta, sd_x_m=0.05, sd_y_m=0.05, sd_theta_rad=0.01, odom_x=x, odom_y=y,
            odom_theta=theta, vx=0.0, omega=0.0, uwbStale=False,
        ))  # fmt: skip
        if tick % state_every == 0:
            out.append(counter(robot).make(
                State,
                agvPosition=AgvPosition(x=x, y=y, theta=0.0, mapId="", positionInitialized=True, localizationScore=1.0),
                velocity=Velocity(vx=0.6, omega=0.3), batteryState=BatteryState(batteryCharge=80.0, charging=False),
                errors=(), operatingMode=OperatingMode.AUTOMATIC,
                safetyState=SafetyState(eStop="NONE", fieldViolation=False), driveMode="goto",  # type: ignore[arg-type]
                links=LinkStatus(zenoh=True, mqtt=True), uwbStale=False, payloadOn=False, boardConnected=True,
                orderId="", orderUpdateId=0, goal=None, driving=True, paused=False, home=None,
                contact=Contact(policy=CommsPolicy.STOP, lost=False, action="", silent_s=0.0),
            ))  # fmt: skip
        if maps and (tick + i) % scan_every == 0:  # 2 Hz, the robots spread over the ticks
            out.append(counter(robot).make(Scan, **scan_fields(SCAN_ANGLES, SCAN_RANGES, (x, y, th))))
    return out


def map_updates(rig: Rig, n: int, tick: int, hz: float) -> None:
    """A map update a second per robot (the robots spread over the ticks), as ``MapFollower``
    hands the console a robot's map: in the console's process, under its lock."""
    state_every = max(1, round(hz))
    for i in range(n):
        if (tick + i) % state_every == 0:
            with rig.lock:
                rig.fleet.set_grid(f"r{i:02d}", robot_grid(i))


def feed(rig: Rig, n: int, stop: threading.Event, hz: float = 10.0, maps: bool = False) -> None:
    """The robots' messages built, encoded and received in this process (``--encode-in-process``:
    the robots' encoding shares the console's interpreter lock, as before 2026-11-28)."""
    t0 = time.monotonic()
    tick = 0
    while not stop.is_set():
        for msg in robot_messages(n, time.monotonic() - t0, tick, hz, maps, rig.counter):
            rig.zenoh.inject(msg)
        if maps:
            map_updates(rig, n, tick, hz)
        tick += 1
        stop.wait(max(0.0, t0 + tick / hz - time.monotonic()))


def robots_process(n: int, hz: float, maps: bool, go: Any, stop: Any, out: Connection, theirs: Connection) -> None:
    """The robots, in a process of their own (as robots are): each tick's messages built and
    encoded here and sent to the console's process as one batch of (key, payload). ``theirs``
    (the console's end, inherited by the fork) is closed first, so a console that stops reading
    ends the robots' sends instead of blocking them."""
    theirs.close()
    clock = SystemClock()
    counters: dict[str, HeaderCounter] = {}

    def counter(robot: str) -> HeaderCounter:
        if robot not in counters:
            counters[robot] = HeaderCounter(clock, robot=robot, sender=f"agent-{robot}")
        return counters[robot]

    while not go.wait(0.1):
        if stop.is_set():
            return
    t0 = time.monotonic()
    tick = 0
    try:
        while not stop.is_set():
            msgs = robot_messages(n, time.monotonic() - t0, tick, hz, maps, counter)
            out.send((tick, [(wire.key_of(m), wire.encode(m)) for m in msgs]))
            tick += 1
            stop.wait(max(0.0, t0 + tick / hz - time.monotonic()))
    except (BrokenPipeError, EOFError, OSError):
        pass  # the console's side is gone
    finally:
        out.close()


def receive(rig: Rig, n: int, stop: threading.Event, hz: float, maps: bool, inbox: Connection) -> None:
    """The console's network thread: each batch of bytes through the link's receive path (as
    Zenoh's callbacks hand it samples), and each second's map updates."""
    while not stop.is_set():
        if not inbox.poll(0.05):
            continue
        try:
            tick, batch = inbox.recv()
        except EOFError:
            return
        for key, payload in batch:
            rig.zenoh.inject_raw(key, payload)
        if maps:
            map_updates(rig, n, tick, hz)


def keys_typed(app: Any, seconds: float, teleops: list[float], sent: threading.Event, out: list[float]) -> None:
    """The keyboard: for ``seconds``, ``i`` then space (stop, so the next ``i`` is a change and
    goes out at once) every 0.15 s, each handed to the app's driver on this thread as a terminal's
    input thread hands it what it read (``Driver.process_message``). ``out``: each ``i``'s time
    from then until its Teleop reached the transport."""
    driver = app._driver
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for key in ("i", "space"):
            before = len(teleops)
            sent.clear()
            t0 = time.monotonic()
            driver.process_message(events.Key(key, " " if key == "space" else key))
            while len(teleops) == before and time.monotonic() - t0 < 2:
                sent.wait(0.05)
                sent.clear()
            if key == "i":  # stamped where it reaches the transport
                out.append((teleops[before] if len(teleops) > before else time.monotonic()) - t0)
        time.sleep(0.15)


async def keys_posted(app: Any, seconds: float, teleops: list[float], sent: threading.Event, out: list[float]) -> None:
    """``--keys-from-loop``: the same keys posted to the app from the event loop (the bench before
    2026-12-01: a key then never waited for the loop to take it from the input thread)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for key in ("i", "space"):
            before = len(teleops)
            t0 = time.monotonic()
            app.post_message(events.Key(key, " " if key == "space" else key))
            while len(teleops) == before and time.monotonic() - t0 < 2:
                await asyncio.sleep(0.0005)
            if key == "i":
                out.append((teleops[before] if len(teleops) > before else time.monotonic()) - t0)
        await asyncio.sleep(0.15)


async def measure(
    n: int,
    seconds: float,
    tmp: Path,
    hz: float = 10.0,
    maps: bool = False,
    in_process: bool = False,
    keys_from_loop: bool = False,
) -> dict[str, float]:
    # The robots' process is forked before the rig starts any thread of its own.
    ctx = multiprocessing.get_context("fork")
    go, robots_stop = ctx.Event(), ctx.Event()
    inbox, outbox = ctx.Pipe(duplex=False)
    robots = (
        None
        if in_process
        else ctx.Process(target=robots_process, args=(n, hz, maps, go, robots_stop, outbox, inbox), daemon=True)
    )
    if robots is not None:
        robots.start()
    outbox.close()
    rig = Rig(tmp)
    rig.link.start()
    stop = threading.Event()
    if robots is None:
        feeder = threading.Thread(target=feed, args=(rig, n, stop, hz, maps), daemon=True)
    else:
        feeder = threading.Thread(target=receive, args=(rig, n, stop, hz, maps, inbox), daemon=True)
    teleops: list[float] = []
    """When each Teleop reached the (Zenoh) transport."""
    sent = threading.Event()
    publish = rig.zenoh.publish

    def stamped(key: str, payload: bytes) -> bool:
        if f"/{Teleop.TOPIC}/" in key + "/":
            teleops.append(time.monotonic())
            sent.set()
        return publish(key, payload)

    rig.zenoh.publish = stamped  # type: ignore[method-assign]
    try:
        async with rig.app.run_test(size=(160, 48)):
            feeder.start()
            go.set()
            await asyncio.sleep(1.0)
            rig.app.frame_times.clear()
            applied0, t_start, cpu0 = rig.app.feed.applied, time.monotonic(), time.process_time()
            received0 = sum(rig.link.delivered.values())
            conflated0 = getattr(rig.app.feed, "conflated", 0)
            latencies: list[float] = []
            if keys_from_loop:
                await keys_posted(rig.app, seconds, teleops, sent, latencies)
            else:
                keyboard = threading.Thread(
                    target=keys_typed, args=(rig.app, seconds, teleops, sent, latencies), name="keyboard", daemon=True
                )
                keyboard.start()
                while keyboard.is_alive():
                    await asyncio.sleep(0.05)
            frames = list(rig.app.frame_times)
            collector = getattr(rig.app, "collector", None)  # (None: a console before 2026-11-28)
            gc_passes = list(collector.passes) if collector is not None else [-1, -1, -1]
            gc_longest = list(collector.longest) if collector is not None else [0.0, 0.0, 0.0]
            conflated = getattr(rig.app.feed, "conflated", 0) - conflated0
            took = time.monotonic() - t_start
            cpu = (time.process_time() - cpu0) / took
            received = (sum(rig.link.delivered.values()) - received0) / took
            folded = (rig.app.feed.applied - applied0) / took
            shown = len(rig.app.query_one("#fleet").rows)
    finally:
        robots_stop.set()
        go.set()
        stop.set()
        feeder.join(2)
        inbox.close()  # a robots' send waiting on a full pipe fails now
        if robots is not None:
            robots.join(5)
            if robots.is_alive():
                robots.terminate()
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
        "folded_per_s": folded,
        "conflated_per_s": conflated / took,
        "received_per_s": received,
        "console_cpu_share": cpu,
        "load_1min": os.getloadavg()[0],
        "gc_passes": gc_passes,
        "gc_longest_s": gc_longest,
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
    parser.add_argument(
        "--maps", action="store_true", help="each robot's map (updated at 1 Hz) and lidar scan (2 Hz) too"
    )
    parser.add_argument(
        "--encode-in-process",
        action="store_true",
        help="build and encode the robots' messages in the console's process (the bench before 2026-11-28)",
    )
    parser.add_argument(
        "--keys-from-loop",
        action="store_true",
        help="post the keys to the app from its event loop (the bench before 2026-12-01), not from a keyboard thread",
    )
    parser.add_argument("--json", type=Path, help="also write the figures as JSON (SI units)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        where, loop = args.encode_in_process, args.keys_from_loop
        base = asyncio.run(measure(1, args.seconds, Path(tmp), args.pose_hz, args.maps, where, loop))
        full = asyncio.run(measure(args.robots, args.seconds, Path(tmp), args.pose_hz, args.maps, where, loop))
    extra = ", maps updated at 1 Hz and scans at 2 Hz" if args.maps else ""
    print(
        f"console responsiveness, robots reporting pose at {args.pose_hz:g} Hz (+ state at 1 Hz{extra}), "
        f"{args.seconds:g} s each"
    )
    print(f"{'':22} {f'{args.robots} robots':>12} {'1 robot':>10} {'ratio':>7}")
    for key, label in (("frame_p50_s", "refresh p50 ms"), ("frame_p99_s", "refresh p99 ms"),
                       ("input_p50_s", "key->teleop p50 ms"), ("input_p99_s", "key->teleop p99 ms")):  # fmt: skip
        print(f"{label:22} {1e3 * full[key]:12.2f} {1e3 * base[key]:10.2f} {full[key] / base[key]:6.1f}x")
    print(f"rows shown {full['robots_shown']}/{args.robots}; {full['frames']} refreshes, {full['inputs']} key presses")
    expected = args.robots * args.pose_hz * (1 + 1 / args.pose_hz)  # poses and states
    print(
        f"messages received {full['received_per_s']:.0f}/s, folded into the model {full['folded_per_s']:.0f}/s, poses replaced by a newer one before "
        f"they were {full['conflated_per_s']:.0f}/s (poses and states sent: {expected:.0f}/s); "
        f"robots encoded {'in the console' if args.encode_in_process else 'in a process of their own'}; "
        f"load average {full['load_1min']:.1f}; the console's process used {100 * full['console_cpu_share']:.0f} % of a core"
    )
    passes, longest = full["gc_passes"], full["gc_longest_s"]
    print(
        "garbage collector (the console's, whole run): passes of generation 0/1/2 "
        f"{'/'.join(str(p) for p in passes)}, longest {'/'.join(f'{1e3 * t:.1f}' for t in longest)} ms"
    )
    ok = full["frame_p99_s"] < args.refresh_goal_ms / 1e3 and full["input_p99_s"] < 0.05
    print(f"goal: refresh p99 < {args.refresh_goal_ms:g} ms and key->teleop p99 < 50 ms: {'MET' if ok else 'NOT MET'}")
    if args.json:
        figures = {"robots_n": full, "one_robot": base, "frame_p99_ratio": full["frame_p99_s"] / base["frame_p99_s"],
                   "input_p99_ratio": full["input_p99_s"] / base["input_p99_s"], "goal_met": ok,
                   "refresh_p99_goal_s": args.refresh_goal_ms / 1e3, "pose_rate_hz": args.pose_hz,
                   "maps_and_scans": args.maps}  # fmt: skip
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
