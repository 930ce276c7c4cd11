"""Failover from the primary link (Zenoh) to the fallback (MQTT): how long, and what is lost.

    python bench/failover.py [--trials 50] [--json FILE]

Real parts on loopback: a private Mosquitto (tests/harness), the operator's OperatorLink
(Zenoh peer + paho client, link manager polling at 50 Hz) and a robot made of the agent's real
command gate behind its own Zenoh session and MQTT client, publishing its pose at 20 Hz on both.
The operator sends a goal (an Order, acked) every 20 ms throughout. Each trial cuts the primary by
closing the robot's Zenoh session and measures the time from the cut to the first goal the robot
executes that came over MQTT; then the primary comes back and the operator fails back after the
hold-off. At the end every goal must have run exactly once.

Baseline, same run: one goal's trip operator -> robot over plain MQTT while healthy (the floor
for any failover: the fallback's own latency), and the detection window the policy allows.
Goals: failover p99 <= 500 ms, 0 lost, 0 duplicated.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fleetlink.operator.linkmanager import FALLBACK, PRIMARY, LinkPolicy  # noqa: E402
from fleetlink.shared import keys  # noqa: E402
from fleetlink.shared.clock import SystemClock  # noqa: E402
from fleetlink.shared.messages import Order  # noqa: E402
from fleetlink.site.brokers import MosquittoBroker  # noqa: E402
from tests.harness import wait_until  # noqa: E402
from tests.harness.link_robot import LinkRobot, goal, open_operator  # noqa: E402


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=50)
    parser.add_argument("--json", type=Path, help="also write the figures as JSON (SI units)")
    args = parser.parse_args()
    policy = LinkPolicy(state_window_s=0.35, ack_timeout_s=0.25, holdoff_s=0.3)
    clock = SystemClock()
    with tempfile.TemporaryDirectory() as tmp, MosquittoBroker(Path(tmp)) as broker:
        op, endpoint = open_operator(broker.port, policy, sender="bench-op")
        robot = LinkRobot("r1", endpoint, broker.port, clock)
        sent = 0
        try:
            wait_until(lambda: all(h.age_s is not None for h in op.health("r1")), message="robot on both links")
            # Baseline: goals over MQTT alone, operator -> robot execution time.
            base: list[float] = []
            for _ in range(50):
                n = len(robot.executed)
                t0 = clock.now()
                op._put(FALLBACK, keys.sender_key("r1", Order.TOPIC, op.sender), _encoded_goal(op, sent))
                sent += 1
                wait_until(lambda n=n: len(robot.executed) > n, interval=0.0005, message="baseline goal")
                base.append(robot.executed[-1].at - t0)
                time.sleep(0.01)
            failover: list[float] = []
            for trial in range(args.trials):
                wait_until(lambda: op.active("r1") == PRIMARY, timeout=10, message="back on the primary")
                for _ in range(5):
                    op.send(Order, "r1", **goal(sent))
                    sent += 1
                    time.sleep(0.02)
                robot.cut_primary()
                cut = clock.now()
                first = None
                while first is None:
                    op.send(Order, "r1", **goal(sent))
                    sent += 1
                    time.sleep(0.02)
                    after = [e.at for e in list(robot.executed) if e.link == "mqtt" and e.at >= cut]
                    if after:
                        first = min(after)
                    elif clock.now() - cut > 5:
                        raise RuntimeError(f"trial {trial}: no command over MQTT 5 s after the cut")
                failover.append(first - cut)
                robot.open_primary()
                print(f"\rtrial {trial + 1}/{args.trials}: {1000 * failover[-1]:.0f} ms", end="", file=sys.stderr)
            wait_until(lambda: op.pending("r1") == 0, timeout=10, message="every goal acked")
        finally:
            robot.close()
            op.close()
        print(file=sys.stderr)
    orders = [e.order for e in robot.executed if e.order is not None]
    wanted = {(f"goal-{i}", 0) for i in range(sent)}
    lost = len(wanted - set(orders))
    dup = len(orders) - len(set(orders))
    figures = {
        "trials": args.trials,
        "goals_sent": sent,
        "failover_p50_s": statistics.median(failover),
        "failover_p99_s": pct(failover, 0.99),
        "failover_max_s": max(failover),
        "baseline_mqtt_p50_s": statistics.median(base),
        "baseline_mqtt_p99_s": pct(base, 0.99),
        "detection_window_s": policy.state_window_s,
        "ratio_p99_to_window": pct(failover, 0.99) / policy.state_window_s,
        "lost": lost,
        "duplicated": dup,
        "goal_p99_s": 0.5,
        "goal_met": pct(failover, 0.99) <= 0.5 and lost == 0 and dup == 0,
    }
    f = figures
    print(f"failover Zenoh -> MQTT, {args.trials} trials, goal every 20 ms, {sent} goals in all")
    print(f"{'':28} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}")
    print(
        f"{'failover (cut -> MQTT run)':28} {1e3 * f['failover_p50_s']:8.1f} {1e3 * f['failover_p99_s']:8.1f}"
        f" {1e3 * f['failover_max_s']:8.1f}"
    )
    print(
        f"{'baseline: goal over MQTT':28} {1e3 * f['baseline_mqtt_p50_s']:8.2f} {1e3 * f['baseline_mqtt_p99_s']:8.2f}"
    )
    print(f"detection window {1e3 * policy.state_window_s:.0f} ms; p99 / window = {f['ratio_p99_to_window']:.2f}")
    print(f"lost {lost}, duplicated {dup}; goal p99 <= 500 ms, 0 lost, 0 dup: {'MET' if f['goal_met'] else 'NOT MET'}")
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0 if f["goal_met"] else 1


def _encoded_goal(op: object, i: int) -> bytes:
    from fleetlink.shared import wire

    msg = Order(header=op.counter.header(Order.TOPIC, robot="r1"), **goal(i))  # type: ignore[attr-defined]
    return wire.encode(msg)


if __name__ == "__main__":
    sys.exit(main())
