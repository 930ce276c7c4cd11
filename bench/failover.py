"""Losing the primary link (Zenoh): what it costs with redundant sending and with failover only.

    python bench/failover.py [--cuts 10] [--mode both|redundant|failover|stall|lossy] [--loss 10] [--json FILE]

Real parts on loopback: a private Mosquitto (tests/harness), the operator's OperatorLink
(Zenoh peer + paho client, link manager polling at 50 Hz) and a robot made of the agent's real
command gate behind its own Zenoh session and MQTT client (tests/harness/link_robot.py), publishing
its pose at 20 Hz on both. Throughout, the operator sends a goal (an Order, acked) every 40 ms and
holds a teleop key (a drive command every 50 ms, time-to-live 0.5 s: the robot's deadman). Every
``--period`` seconds the primary is cut -- the robot's Zenoh session closed, like a dead radio --
for half the period, then opened again.

The modes, the same load and the same cuts:

* **redundant** (the consoles' default): every command goes out on both links at once; the robot
  runs the first copy and acks each on its link. Goals: added delay p99 <= 20 ms, 0 lost, 0 run
  twice, no deadman stop while the key is held through a cut.
* **failover** (a site with a metered link): commands go over the active link and move to MQTT
  once the link manager sees the primary silent (0.35 s) or a command unacked (0.25 s). Goal: cut ->
  first goal run over MQTT p99 <= 500 ms, 0 lost, 0 run twice.

* **stall** (``--mode stall``): redundant sending, but the primary *stalls* instead of dropping:
  the console's Zenoh publish blocks for the window (as a put with congestion control BLOCK waits
  when its queue towards a peer is full; tests/test_link_stall.py makes that stall for real), the
  robot's session stays open. Run twice: ``stall`` (each link's copy on its own send thread,
  operator/links.py) and ``stall-inline`` (the baseline: both copies from the caller's thread, one
  after the other, as before issue 18). Goal for ``stall``: added delay p99 <= 20 ms, 0 lost, 0
  run twice, no deadman stop.

* **lossy** (``--mode lossy --loss P``): no cuts; for as long as the cuts would have taken, P % of
  Zenoh's packets are dropped at random each way (tests/harness/lossy.py: the robot's session a
  client of a router inside a network namespace whose veth loses them; MQTT clean), once with
  redundant sending and once with failover only. Shown, not judged: goal delay, the longest gap
  between drives, deadman stops (docs/operations.md, "A lossy link"). Needs root, ``ip``, ``nft``.

*Added delay*: each goal's time from send to execution; the p99 of the goals sent in the first
second after each cut, minus the p99 of the goals sent while both links were up and had been for
a second (the same run).
*Deadman stop*: a gap between two executed drive commands longer than their time-to-live.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import logging
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fleetlink.operator.commander import TELEOP_TTL_S  # noqa: E402
from fleetlink.operator.linkmanager import FALLBACK, PRIMARY, LinkPolicy  # noqa: E402
from fleetlink.shared.clock import SystemClock  # noqa: E402
from fleetlink.shared.messages import LinkName, Order, Teleop  # noqa: E402
from fleetlink.site.brokers import MosquittoBroker, free_port  # noqa: E402
from tests.harness import wait_until  # noqa: E402
from tests.harness.link_robot import LinkRobot, goal, open_operator  # noqa: E402
from tests.harness.lossy import LossyLink  # noqa: E402

GOAL_PERIOD_S = 0.04
"""With a drive every 50 ms: 45 commands/s, within the agent's rate of 50 per sender (agent/links/
gate.py ``RateLimit``; a goal every 20 ms on top of the drives is refused in part, by design)."""
DRIVE_PERIOD_S = 0.05
CUT_WINDOW_S = 1.0
"""Goals sent this long after a cut count as 'during the cut' for the added delay."""
GOALS = {"added_delay_p99_s": 0.020, "failover_p99_s": 0.5}


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


def run(mode: str, cuts: int, period: float, port: int, clock: SystemClock, loss: float = 0.0) -> dict[str, Any]:
    with contextlib.ExitStack() as stack:
        return _run(mode, cuts, period, port, clock, loss, stack)


def _run(
    mode: str, cuts: int, period: float, port: int, clock: SystemClock, loss: float, stack: contextlib.ExitStack
) -> dict[str, Any]:
    redundant = mode not in ("failover", "lossy-failover")
    stalls = mode.startswith("stall")
    lossy = mode.startswith("lossy")
    policy = LinkPolicy(state_window_s=0.35, ack_timeout_s=0.25, holdoff_s=0.3, redundant=redundant)
    listen = None
    if lossy:  # Zenoh through a router in a namespace whose packets the kernel drops; MQTT clean
        link = stack.enter_context(LossyLink())
        listen = f"tcp/{link.host_ip}:{free_port(link.host_ip)}"
    op, endpoint = open_operator(
        port, policy, sender=f"bench-{mode}", stalling=stalls, inline=mode == "stall-inline", listen=listen
    )
    stack.callback(op.close)  # after the robot (closed below), and if what follows fails
    if lossy:
        endpoint = stack.enter_context(link.router(endpoint))
        link.set_loss(loss)
    stalling: Any = op.links[LinkName.ZENOH] if stalls else None
    robot = LinkRobot("r1", endpoint, port, clock, zenoh_mode="client" if lossy else "peer")
    sent_at: dict[str, float] = {}
    cut_times: list[float] = []
    open_times: list[float] = []
    stop = threading.Event()

    def cutter() -> None:
        if lossy:  # no cuts: the loss runs as long as the cuts would have
            stop.wait(cuts * period)
            return
        for _ in range(cuts):
            if stop.wait(period / 2):
                return
            cut_times.append(clock.now())
            if stalling is not None:
                stalling.stall()
            else:
                robot.cut_primary()
            if stop.wait(period / 2):
                if stalling is not None:
                    stalling.resume()
                return
            if stalling is not None:
                stalling.resume()
            else:
                robot.open_primary()
            open_times.append(clock.now())

    try:
        wait_until(lambda: all(h.age_s is not None for h in op.health("r1")), message="robot on both links")
        time.sleep(0.5)  # the robot's Zenoh subscriptions reach the console
        thread = threading.Thread(target=cutter, name="cutter", daemon=True)
        i = 0
        next_goal = next_drive = start = clock.now()
        thread.start()
        while thread.is_alive():
            now = clock.now()
            if now >= next_drive:
                op.send(Teleop, "r1", expect_ack=False, v=0.2, omega=0.0, ttl_s=TELEOP_TTL_S)
                next_drive += DRIVE_PERIOD_S
            if now >= next_goal:
                fields = goal(i)
                sent_at[fields["orderId"]] = clock.now()
                op.send(Order, "r1", **fields)
                i += 1
                next_goal += GOAL_PERIOD_S
            time.sleep(max(0.0, min(next_goal, next_drive) - clock.now()))
        end = clock.now()
        wait_until(lambda: op.pending("r1") == 0, timeout=10, message="every goal acked")
        time.sleep(0.3)  # late copies' acks, for the health figures
        health = {h.link: h for h in op.health("r1")}
    finally:
        stop.set()
        if stalling is not None:
            stalling.resume()
        robot.close()
    executed = list(robot.executed)
    orders = [e for e in executed if e.order is not None]
    ran = [e.order[0] for e in orders if e.order is not None]
    first_run = {}
    for e in orders:
        if e.order is not None:
            first_run.setdefault(e.order[0], e.at)
    lost = len(set(sent_at) - set(first_run))
    twice = len(ran) - len(set(ran))
    delay = {k: first_run[k] - t for k, t in sent_at.items() if k in first_run}

    def after_cut(t: float) -> bool:
        return any(c <= t < c + CUT_WINDOW_S for c in cut_times)

    def healthy(t: float) -> bool:
        # Both links up, and not in the second after a re-open: the robot's fresh Zenoh session
        # declares its subscriptions, and failover mode fails back (goals sent to Zenoh before the
        # subscriptions are in place wait an ack timeout) -- a cost of the cut, not of calm.
        cut = any(c <= t < o + 1.0 for c, o in zip(cut_times, [*open_times, end + 1], strict=False))
        return t > start + 0.2 and not cut

    during = [delay[k] for k, t in sent_at.items() if k in delay and after_cut(t)]
    calm = [delay[k] for k, t in sent_at.items() if k in delay and healthy(t)]
    # Cut -> the first goal run after it that came over MQTT (failover's own figure).
    over_mqtt = []
    for c in cut_times:
        later = [e.at for e in orders if e.link == "mqtt" and e.at >= c]
        if later:
            over_mqtt.append(min(later) - c)
    drives = [e.at for e in executed if e.topic == "teleop"]
    gaps = [b - a for a, b in itertools.pairwise(drives)]
    return {
        "mode": mode,
        "loss_ratio": loss / 100.0 if lossy else 0.0,
        "cuts_count": len(cut_times),
        "goals_sent_count": len(sent_at),
        "drives_run_count": len(drives),
        "refused_over_rate_count": robot.gate.limit.limited,
        "goal_delay_nocut_p50_s": pct(calm, 0.5),
        "goal_delay_nocut_p99_s": pct(calm, 0.99),
        "goal_delay_cut_p50_s": pct(during, 0.5),
        "goal_delay_cut_p99_s": pct(during, 0.99),
        "goal_delay_cut_max_s": max(during) if during else float("nan"),
        "added_delay_p99_s": pct(during, 0.99) - pct(calm, 0.99),
        "failover_p50_s": statistics.median(over_mqtt) if over_mqtt else float("nan"),
        "failover_p99_s": pct(over_mqtt, 0.99),
        "lost_count": lost,
        "executed_twice_count": twice,
        "deadman_stop_count": sum(1 for g in gaps if g > TELEOP_TTL_S),
        "drive_gap_max_s": max(gaps) if gaps else float("nan"),
        "zenoh_first_pct": health[PRIMARY].first_pct,
        "zenoh_lead_p50_s": health[PRIMARY].lead_s,
        "mqtt_lead_p50_s": health[FALLBACK].lead_s,
        "rtt_zenoh_p50_s": health[PRIMARY].rtt_s,
        "rtt_mqtt_p50_s": health[FALLBACK].rtt_s,
    }


def verdict(f: dict[str, Any]) -> bool:
    clean = f["lost_count"] == 0 and f["executed_twice_count"] == 0
    if f["mode"] in ("stall-inline", "lossy-redundant", "lossy-failover"):
        return True  # a baseline, or a measurement without a goal: shown, not judged
    if f["mode"] in ("redundant", "stall"):
        return clean and f["added_delay_p99_s"] <= GOALS["added_delay_p99_s"] and f["deadman_stop_count"] == 0
    return clean and f["failover_p99_s"] <= GOALS["failover_p99_s"]


ROWS = (
    ("goal delay, no cut p50", "goal_delay_nocut_p50_s", 1e3, "ms"),
    ("goal delay, no cut p99", "goal_delay_nocut_p99_s", 1e3, "ms"),
    ("goal delay, 1 s after a cut p50", "goal_delay_cut_p50_s", 1e3, "ms"),
    ("goal delay, 1 s after a cut p99", "goal_delay_cut_p99_s", 1e3, "ms"),
    ("added delay p99 (cut - no cut)", "added_delay_p99_s", 1e3, "ms"),
    ("cut -> first goal run over MQTT p99", "failover_p99_s", 1e3, "ms"),
    ("goals lost", "lost_count", 1, ""),
    ("goals run twice", "executed_twice_count", 1, ""),
    ("deadman stops, key held", "deadman_stop_count", 1, ""),
    ("copies refused over the robot's rate", "refused_over_rate_count", 1, ""),
    ("longest gap between drives", "drive_gap_max_s", 1e3, "ms"),
    ("zenoh's ack first (both links up)", "zenoh_first_pct", 1, "%"),
    ("  by (p50, when first)", "zenoh_lead_p50_s", 1e3, "ms"),
    ("mqtt's ack first: by (p50)", "mqtt_lead_p50_s", 1e3, "ms"),
)


def table(results: dict[str, dict[str, Any]]) -> str:
    modes = list(results)
    w = max(13, *(len(m) + 2 for m in modes))
    head = f"{'':38}" + "".join(f"{m:>{w}}" for m in modes)
    if len(modes) == 2:
        head += f"{'ratio':>9}"
    lines = [head]
    for label, key, scale, unit in ROWS:
        cells = []
        for m in modes:
            v = results[m].get(key)
            if v is None or v != v:
                cells.append(f"{'-':>{w}}")
            elif isinstance(v, int):
                cells.append(f"{v:>{w - 2}d}{unit:>2}")
            else:
                cells.append(f"{v * scale:>{w - 2}.1f}{unit:>2}")
        line = f"{label:38}" + "".join(cells)
        if len(modes) == 2:
            a, b = results[modes[0]].get(key), results[modes[1]].get(key)
            ok = isinstance(a, int | float) and isinstance(b, int | float) and b and a == a and b == b
            line += f"{a / b:>9.3f}" if ok else f"{'-':>9}"
        lines.append(line)
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cuts", type=int, default=10, help="primary cuts per mode")
    parser.add_argument("--period", type=float, default=3.0, help="seconds between cuts (down half of it)")
    parser.add_argument("--mode", choices=("both", "redundant", "failover", "stall", "lossy"), default="both")
    parser.add_argument(
        "--loss", type=float, default=10.0, help="with --mode lossy: percent of Zenoh's packets dropped, each way"
    )
    parser.add_argument("--json", type=Path, help="also write the figures as JSON (SI units)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)  # the link switches of failover mode are expected
    clock = SystemClock()
    modes = {
        "both": ["redundant", "failover"],
        "stall": ["stall", "stall-inline"],
        "lossy": ["lossy-redundant", "lossy-failover"],
    }.get(args.mode, [args.mode])
    if args.mode == "lossy" and (why := LossyLink.unavailable()) is not None:
        raise SystemExit(f"--mode lossy: {why}")
    results: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp, MosquittoBroker(Path(tmp)) as broker:
        for mode in modes:
            print(f"{mode}: {args.cuts} cuts, every {args.period:g} s ...", file=sys.stderr)
            results[mode] = run(mode, args.cuts, args.period, broker.port, clock, args.loss)
    load = os.getloadavg()
    print(
        f"primary (Zenoh) cut {args.cuts} times per mode, every {args.period:g} s for {args.period / 2:g} s; "
        f"a goal every {GOAL_PERIOD_S * 1e3:.0f} ms, a drive every {DRIVE_PERIOD_S * 1e3:.0f} ms (ttl "
        f"{TELEOP_TTL_S:g} s)"
        + (" -- the primary stalls (its publish blocks) instead" if args.mode == "stall" else "")
        + (
            f" -- no cuts: for as long, {args.loss:g} % of Zenoh's packets dropped each way (MQTT clean)"
            if args.mode == "lossy"
            else ""
        )
    )
    ratio = f"\n(ratio: {modes[0]} / {modes[1]})" if len(results) == 2 else ""
    print(table(results) + ratio)
    print(f"machine: {os.cpu_count()} cores, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    met = {m: verdict(f) for m, f in results.items()}
    for m, ok in met.items():
        if m in ("stall-inline", "lossy-redundant", "lossy-failover"):
            continue  # shown, not judged
        goal_text = (
            "added delay p99 <= 20 ms, 0 lost, 0 run twice, no deadman stop"
            if m in ("redundant", "stall")
            else "cut -> MQTT p99 <= 500 ms, 0 lost, 0 run twice"
        )
        print(f"{m}: {goal_text}: {'MET' if ok else 'NOT MET'}")
    if args.json:
        doc = {
            "modes": results,
            "goals": {"redundant_added_delay_p99_s": GOALS["added_delay_p99_s"], "failover_p99_s": 0.5},
            "goal_met": met,
            "cpu_count": os.cpu_count(),
            "load_average": list(load),
        }
        if len(results) == 2:
            r, f = results[modes[0]], results[modes[1]]
            doc[f"ratio_{modes[0]}_to_{modes[1]}".replace("-", "_")] = {
                k: r[k] / f[k]
                for k in ("added_delay_p99_s", "goal_delay_cut_p99_s", "drive_gap_max_s")
                if isinstance(r[k], float) and isinstance(f[k], float) and f[k]
            }
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
    return 0 if all(met.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
