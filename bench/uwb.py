"""UWB positioning on the office plan: fix accuracy against truth, robust solver vs linear LS, speed.

    python bench/uwb.py [--quick] [--json FILE]

Positions: uniform over the office floor (40 x 20 m, its 10 anchors at 2.7 m), tag at 0.3 m.
For each noise profile the same ranges go to both solvers (seeded):
  los        line of sight only, sigma 0.1 m
  realistic  + 10 % NLOS ranges (0.3 m mean positive exponential bias), 1 % gross outliers of
             0.5-5 m, 5 % dropouts
  walls      realistic, and every range whose path crosses a wall of the plan is NLOS too
Baseline: plain linear least squares (mean-subtracted squared range equations), measured in the
same run. Speed: single solves per second (one call per fix, the way the gateway uses it), and the
whole gateway round per tag (ranging + solve + encoding the fix, the ranges and the PANS JSON).

Goals: LOS RMSE <= 0.12 m; realistic: robust RMSE <= 0.6x linear LS; >= 5,000 solves/s.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

TAG_Z = 0.3


def errors(fn: Callable[..., Any], anchors: Any, ranges: list[Any], pts: np.ndarray) -> tuple[np.ndarray, int, float]:
    by_id = {a.id: a for a in anchors}
    t0 = time.perf_counter()
    sols = [fn(by_id, r, TAG_Z) for r in ranges]
    dt = time.perf_counter() - t0
    err = np.array([math.hypot(s.x - x, s.y - y) for s, (x, y) in zip(sols, pts, strict=True) if s.ok])
    return err, sum(not s.ok for s in sols), dt


def stats(err: np.ndarray) -> dict[str, float]:
    return {
        "rmse_m": float(np.sqrt(np.mean(err**2))),
        "p95_m": float(np.percentile(err, 95)),
        "max_m": float(err.max()),
    }


def main(argv: list[str] | None = None) -> int:
    from fleetlink.field.plans import load_plan
    from fleetlink.positioning.anchors import anchors_from
    from fleetlink.positioning.config import GatewayConfig, TagSpec
    from fleetlink.positioning.gateway import GatewayCore
    from fleetlink.positioning.ranging import NoiseProfile, RangingModel
    from fleetlink.positioning.solver import solve, solve_linear

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer positions")
    ap.add_argument("--json", type=Path, help="also write the figures as JSON (SI units)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    n = 2_000 if args.quick else 10_000

    plan = load_plan("office")
    anchors = anchors_from(plan.anchors)
    walls = plan.segments()
    rng = np.random.default_rng(args.seed)
    pts = rng.uniform((0.3, 0.3), (39.7, 19.7), size=(n, 2))
    profiles = {
        "los": NoiseProfile.los(),
        "realistic": NoiseProfile.realistic(),
        "walls": replace(NoiseProfile.realistic(), use_walls=True),
    }
    results: dict[str, Any] = {"positions": n, "anchors": len(anchors), "plan": "office"}
    print(f"UWB fixes on the office plan: {n} random positions, {len(anchors)} anchors, tag at {TAG_Z} m")
    print(
        f"{'noise':>10} {'solver':>7} {'RMSE m':>8} {'p95 m':>8} {'max m':>8} {'refused':>8} {'solves/s':>10}"
        f" {'RMSE robust/linear':>19}"
    )
    speed: dict[str, float] = {}
    for name, profile in profiles.items():
        model = RangingModel(anchors, profile, np.random.default_rng(args.seed + 1), walls)
        ranges = [model.measure(x, y, TAG_Z) for x, y in pts]
        row: dict[str, Any] = {}
        for label, fn in (("robust", solve), ("linear", solve_linear)):
            err, refused, dt = errors(fn, anchors, ranges, pts)
            row[label] = {**stats(err), "refused": refused, "solves_per_s": n / dt}
            speed[label] = max(speed.get(label, 0.0), n / dt)
        row["rmse_robust_over_linear_ratio"] = row["robust"]["rmse_m"] / row["linear"]["rmse_m"]
        results[name] = row
        for label in ("robust", "linear"):
            r = row[label]
            ratio = f"{row['rmse_robust_over_linear_ratio']:19.2f}" if label == "robust" else ""
            print(
                f"{name:>10} {label:>7} {r['rmse_m']:8.3f} {r['p95_m']:8.3f} {r['max_m']:8.3f} {r['refused']:8d}"
                f" {r['solves_per_s']:10.0f} {ratio}"
            )

    # The gateway's whole round per tag, in the same process (no broker): ranging + solve + encoding.
    config = GatewayConfig(anchors=anchors, tags=(TagSpec("t1", "r1"),), profile=NoiseProfile.realistic(), walls=walls)
    core = GatewayCore(config)
    rounds = n // 2
    t0 = time.perf_counter()
    for k in range(rounds):
        x, y = pts[k]
        core.on_truth("r1", float(x), float(y), now=k * 0.1)
        core.tick(now=k * 0.1, wall=1.7e9 + k * 0.1)
    gateway_per_s = rounds / (time.perf_counter() - t0)
    results["solves_per_s"] = speed["robust"]
    results["linear_solves_per_s"] = speed["linear"]
    results["robust_over_linear_speed_ratio"] = speed["robust"] / speed["linear"]
    results["gateway_fixes_per_s"] = gateway_per_s
    print(
        f"\nspeed: robust {speed['robust']:.0f} solves/s, linear {speed['linear']:.0f} solves/s "
        f"(ratio {speed['robust'] / speed['linear']:.2f}); gateway round per tag {gateway_per_s:.0f}/s"
        f" (= {gateway_per_s / 10:.0f} tags at 10 Hz on one core)"
    )

    los = results["los"]["robust"]["rmse_m"]
    ratio = results["realistic"]["rmse_robust_over_linear_ratio"]
    goals = {
        "los_rmse_goal_m": 0.12,
        "realistic_ratio_goal_ratio": 0.6,
        "solves_goal_per_s": 5000.0,
    }
    met = {
        "los": los <= goals["los_rmse_goal_m"],
        "ratio": ratio <= goals["realistic_ratio_goal_ratio"],
        "speed": speed["robust"] >= goals["solves_goal_per_s"],
    }
    print(f"goal LOS RMSE <= 0.12 m: {los:.3f} m {'met' if met['los'] else 'NOT met'}")
    print(f"goal realistic robust/linear RMSE <= 0.6: {ratio:.2f} {'met' if met['ratio'] else 'NOT met'}")
    print(f"goal >= 5000 solves/s: {speed['robust']:.0f} {'met' if met['speed'] else 'NOT met'}")
    results["goals"] = goals
    results["goals_met"] = met
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0 if all(met.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
