"""How fast the simulated field runs in lockstep, and what one lidar revolution costs.

    python bench/field.py [--quick] [--json FILE]

Lockstep, the field alone: the "hall-50" scenario cut to 1, 10 and 50 robots, lidar at 10 Hz,
robots wandering open-loop (field/open_loop.py commands the boards directly), lidars cast inline
or partly in a worker process (both cores).

Lockstep with whole agents (``"agents": true``; fleetlink.site.lockstep.MissionRun): the office
plan, 10 and 50 robots, each with its real agent (board session over Control Bus bytes, lidar
over RPLIDAR bytes at 10 Hz, fusion with the UWB gateway's fixes, guard, pilot, mapping on,
planner), wandering from named place to named place by goals a scripted operator sends over the
in-process Zenoh link; their map keepers run in a second process (agent/mapping/worker.py). Lidar
samples per second: 8000 (the model's A1) and 2000 (what a real A1's
standard SCAN delivers at 115200 baud, the node format the simulator speaks).
The real-time factor is simulated seconds per wall second: the baseline is real time (1x).

Ray casting: one revolution (800 rays at 10 Hz, 1450 at 5.5 Hz) on the hall and the office,
our culled caster beside a brute-force numpy caster (every ray against every segment), same run.

Goals on this 2-core machine: >= 20x real time for 10 robots with lidar, >= 2x for 50 (field
alone); >= 2x for 10 whole agents with mapping (50 reported).
"""

from __future__ import annotations

# ruff: noqa: E402 -- first, before numpy is imported: the BLAS kernels every fleetlink command runs
# (shared/blas.py), so the figures are the same on every x86-64 host.
from fleetlink.shared.blas import pin_blas_kernels

pin_blas_kernels()

import argparse
import json
import logging
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def lockstep(n: int, duration: float, worker: bool) -> dict[str, float]:
    from fleetlink.field.lockstep import FieldRun
    from fleetlink.field.scenario import LidarSettings, load_scenario

    sc = load_scenario(ROOT / "field" / "scenarios" / "hall-50.toml")
    sc = replace(sc, robots=sc.robots[:n], lidar=LidarSettings(True, 10.0), duration=duration)
    with FieldRun(sc, lidar_worker=worker) as run:
        result = run.run()
    return {
        "robots": n,
        "agents": False,
        "lidar_worker": worker,
        "sim_s": result.sim_seconds,
        "wall_s": result.wall_seconds,
        "real_time_factor_ratio": result.real_time_factor,
        "lidar_scans": result.scans,
        "raycast_per_scan_s": result.raycast_seconds / max(1, result.scans),
        "raycast_share_ratio": result.raycast_seconds / result.wall_seconds,  # > 1 when the worker overlaps
    }


def agents(n: int, duration: float, samples_per_second: float) -> dict[str, float]:
    """Whole agents in lockstep: the office, ``n`` robots wandering by goals, mapping on."""
    from fleetlink.field.plans import load_plan
    from fleetlink.field.scenario import LidarSettings, RobotSpec, Scenario
    from fleetlink.site.lockstep import MissionRun

    plan = load_plan("office")
    starts = sorted(plan.starts)
    robots = tuple(RobotSpec(f"r{i}", start=starts[i % len(starts)], drive="wander") for i in range(n))
    sc = Scenario(
        name=f"office-agents-{n}",
        plan="office",
        seed=1,
        duration=duration,
        robots=robots,
        lidar=LidarSettings(True, 10.0, samples_per_second),
    )
    quiet = logging.getLogger("fleetlink")
    level = quiet.level
    quiet.setLevel(logging.ERROR)  # each agent logs its links coming up: noise in the table
    try:
        with MissionRun(sc, plan, mapping=True, record=False) as run:
            map_worker = run.map_worker is not None
            result = run.run()
    finally:
        quiet.setLevel(level)
    stats = result.field.stats
    return {
        "robots": n,
        "agents": True,
        "mapping": True,
        "map_worker": map_worker,
        "lidar_samples_per_s": samples_per_second,
        "sim_s": result.field.sim_seconds,
        "wall_s": result.field.wall_seconds,
        "real_time_factor_ratio": result.real_time_factor,
        "lidar_scans": sum(int(s.get("agent_scans", 0)) for s in stats.values()),
        "goals_reached": sum(1 for e in result.events if e.kind == "goal_reached"),
        "board_requests": sum(int(s.get("board_requests") or 0) for s in stats.values()),
    }


def brute_force(segs: np.ndarray, x: float, y: float, angles: np.ndarray, max_range: float) -> np.ndarray:
    """Every ray against every segment: the obvious vectorised caster."""
    dx, dy = np.cos(angles)[:, None], np.sin(angles)[:, None]
    x1, y1, x2, y2 = (segs[:, i][None, :] for i in range(4))
    ex, ey = x2 - x1, y2 - y1
    denom = dx * ey - dy * ex
    wx, wy = x1 - x, y1 - y
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wx * ey - wy * ex) / denom
        u = (wx * dy - wy * dx) / denom
    ok = (denom != 0) & (t >= 0) & (u >= 0) & (u <= 1)
    d = np.where(ok, t, np.inf).min(axis=1)
    return np.where(d <= max_range, d, np.inf)


def raycast(plan_name: str, rays: int, repeats: int) -> dict[str, float]:
    from fleetlink.field.plans import load_plan
    from fleetlink.field.raycast import Raycaster

    plan = load_plan(plan_name)
    segs = plan.segments()
    caster = Raycaster(segs)
    rng = np.random.default_rng(1)
    starts = list(plan.starts.values())
    poses = [starts[int(i)] for i in rng.integers(0, len(starts), repeats)]
    angles = np.linspace(-math.pi, math.pi, rays, endpoint=False)
    agree = total = 0
    t0 = time.perf_counter()
    ours = [caster.cast(p[0], p[1], angles + p[2], 12.0) for p in poses]
    t1 = time.perf_counter()
    base = [brute_force(segs, p[0], p[1], angles + p[2], 12.0) for p in poses]
    t2 = time.perf_counter()
    for a, b in zip(ours, base, strict=True):
        # Rays through a wall's very end point are ambiguous: ours counts them as hits, the brute
        # force's rounding may miss them. Everything else must agree to the micrometre.
        both_inf = np.isinf(a) & np.isinf(b)
        with np.errstate(invalid="ignore"):  # inf - inf is NaN: compare finite pairs only
            close = np.abs(np.where(both_inf, 0.0, a - b)) < 1e-6
        same = both_inf | close
        agree += int(same.sum())
        total += a.size
    return {
        "plan": plan_name,
        "segments": len(segs),
        "rays": rays,
        "per_scan_s": (t1 - t0) / repeats,
        "baseline_per_scan_s": (t2 - t1) / repeats,
        "speedup_ratio": (t2 - t1) / (t1 - t0),
        "agree_ratio": agree / total,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="short runs (for a smoke test)")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON (SI units)")
    args = parser.parse_args(argv)
    duration = 2.0 if args.quick else 10.0
    repeats = 20 if args.quick else 200

    runs = [lockstep(n, duration, worker) for n in (1, 10, 50) for worker in (False, True)]
    agent_runs = [agents(n, duration, sps) for n in (10, 50) for sps in (2000.0, 8000.0) if n == 10 or sps == 2000.0]
    casts = [raycast(plan, rays, repeats) for plan in ("hall", "office") for rays in (800, 1450)]

    print(f"lockstep field, hall plan, lidar at 10 Hz, {duration:g} s simulated per run")
    print(
        f"{'robots':>6} {'driven':>8} {'lidar':>7} {'real-time factor':>17} {'wall s':>7} {'scans':>6} {'ray ms/scan':>12} {'ray share':>10}"
    )
    for r in runs:
        print(
            f"{r['robots']:>6} {'field':>8} {'worker' if r['lidar_worker'] else 'inline':>7}"
            f" {r['real_time_factor_ratio']:>16.1f}x "
            f"{r['wall_s']:>7.2f} {r['lidar_scans']:>6} {1e3 * r['raycast_per_scan_s']:>12.3f} {r['raycast_share_ratio']:>9.0%}"
        )

    def best(n: int) -> float:
        return max(r["real_time_factor_ratio"] for r in runs if r["robots"] == n)

    goal10, goal50 = best(10), best(50)
    print(f"goal >= 20x for 10 robots: {goal10:.1f}x {'met' if goal10 >= 20 else 'NOT met'}")
    print(f"goal >=  2x for 50 robots: {goal50:.1f}x {'met' if goal50 >= 2 else 'NOT met'}")
    print()
    print(f"lockstep with whole agents, office plan, lidar at 10 Hz, mapping on, {duration:g} s simulated per run")
    print(
        f"{'robots':>6} {'samples/s':>9} {'real-time factor':>17} {'wall s':>7} {'turns read':>13} {'goals reached':>14}"
    )
    for r in agent_runs:
        print(
            f"{r['robots']:>6} {r['lidar_samples_per_s']:>9.0f} {r['real_time_factor_ratio']:>16.2f}x {r['wall_s']:>7.2f}"
            f" {r['lidar_scans']:>13} {r['goals_reached']:>14}"
        )
    a10 = max(r["real_time_factor_ratio"] for r in agent_runs if r["robots"] == 10)
    print(f"goal >= 2x for 10 whole agents: {a10:.2f}x {'met' if a10 >= 2 else 'NOT met'}")
    print()
    print("ray casting, one revolution (max range 12 m)")
    print(f"{'plan':>7} {'segments':>9} {'rays':>5} {'ours ms':>8} {'brute-force ms':>15} {'speed-up':>9} {'agree':>9}")
    for c in casts:
        print(
            f"{c['plan']:>7} {c['segments']:>9} {c['rays']:>5} {1e3 * c['per_scan_s']:>8.3f} "
            f"{1e3 * c['baseline_per_scan_s']:>15.3f} {c['speedup_ratio']:>8.1f}x {c['agree_ratio']:>9.5f}"
        )
    calib = time.perf_counter()
    sum(range(100_000))
    calib = time.perf_counter() - calib
    print(f"\nmachine calibration: sum(range(100000)) takes {calib * 1e3:.2f} ms")
    if args.json:
        args.json.write_text(
            json.dumps(
                {"lockstep": runs + agent_runs, "raycast": casts, "calibration_sum_range_100k_s": calib}, indent=2
            )
            + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
