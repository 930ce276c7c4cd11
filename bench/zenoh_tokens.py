"""What liveliness tokens cost the Zenoh routers: N light robots through a two-router mesh.

    .venv/bin/python bench/zenoh_tokens.py [--robots 500] [--seconds 10] [--json FILE]

The light fleet (field/light.py, in this process) publishes on router A; a bare subscriber on
router B counts the poses. Three runs, one after the other, differing only in the robots'
liveliness tokens: at the contract's key ``fleetlink/alive/v1/<robot>`` (``keys.alive_key``: what
agents and ``fleetlink field --light`` declare, which consoles watch), at the old key
``fleetlink/v1/<robot>/alive`` (the contract until issue 18: next to the robot's data keys), and
none. Measured: poses/s arriving at B (goal: 20 x N) and the CPU of each router and of this
process. zenoh 1.10.2 (the Python wheel's router) spends far more per routed sample when the
tokens share the data's key tree, which is why the contract moved them (docs/operations.md,
"Scale").
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.scale import cpu_seconds  # noqa: E402


def measure(tokens: str, n: int, seconds: float) -> dict[str, Any]:
    from fleetlink.field.light import LightFleet, light_names
    from fleetlink.field.light_runner import LightRunner
    from fleetlink.links.zenoh import ZenohEndpoint, open_session
    from fleetlink.shared import keys
    from fleetlink.shared.clock import SystemClock
    from fleetlink.site.mesh import RouterMesh

    clock = SystemClock()
    names = light_names(n)
    with RouterMesh() as mesh:
        link = ZenohEndpoint(connect=[mesh.a.listen], mode="client", label="zenoh-light")
        alive = {"contract": keys.alive_key, "old": lambda name: f"fleetlink/v1/{name}/alive", "none": None}[tokens]
        runner = LightRunner(LightFleet(names, clock.now()), [link], clock, owns_links=True, alive=alive).start()
        sub = open_session(connect=[mesh.b.listen], mode="client")
        count = [0]
        sub.declare_subscriber("fleetlink/v1/*/pose", lambda _s: count.__setitem__(0, count[0] + 1))
        try:
            time.sleep(3.0)
            pids = {"router_a": mesh.a.pid, "router_b": mesh.b.pid, "fleet_and_subscriber": os.getpid()}
            cpu0 = {k: cpu_seconds(p) for k, p in pids.items()}
            n0, t0 = count[0], time.perf_counter()
            time.sleep(seconds)
            window = time.perf_counter() - t0
            cpu = {f"{k}_cpu_ratio": (cpu_seconds(p) - cpu0[k]) / window for k, p in pids.items()}
            poses = (count[0] - n0) / window
        finally:
            sub.close()
            runner.close()
    return {"tokens": tokens, "robots": n, "seconds_s": window, "poses_at_b_hz": poses, "goal_hz": 20.0 * n, **cpu}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", type=int, default=500)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--layouts", default="contract,old,none", help="which runs, comma-separated: contract, old, none")
    args = ap.parse_args()
    runs = [measure(t, args.robots, args.seconds) for t in args.layouts.split(",")]
    print(f"{args.robots} light robots on router A, a subscriber on router B; load average {os.getloadavg()[0]:.1f}")
    print(f"{'tokens':38} {'poses/s at B':>14} {'router A':>9} {'router B':>9} {'fleet+sub':>10}")
    for r in runs:
        label = {
            "contract": "fleetlink/alive/v1/<robot> (contract)",
            "old": "fleetlink/v1/<robot>/alive (old)",
            "none": "none",
        }[r["tokens"]]
        print(
            f"{label:38} {r['poses_at_b_hz']:8.0f} / {r['goal_hz']:.0f} {r['router_a_cpu_ratio'] * 100:8.1f}% "
            f"{r['router_b_cpu_ratio'] * 100:8.1f}% {r['fleet_and_subscriber_cpu_ratio'] * 100:9.1f}%"
        )
    if args.json:
        args.json.write_text(json.dumps({"runs": runs, "load_average_1min": os.getloadavg()[0]}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
