"""Go-to-coordinate accuracy and time over random reachable goals, steering on the fused pose.

    python bench/goto.py [--plan office|apartment] [--goals 100] [--seed 1] [--quick] [--planned]
                         [--breakdown N] [--json FILE]

One robot in the lockstep field (default office plan, default scenario noise: ~1 % wheel-scale
error, gyro bias and noise), driven through real Control Bus bytes by an agent-side board
session. The agent side is the real pipeline: wheel+gyro ``Odometry`` -> ``Fusion`` (EKF) with UWB
fixes from the positioning ranging model (``NoiseProfile.realistic()``: 0.1 m noise, 10 % NLOS,
1 % gross outliers, 5 % dropouts) solved by ``positioning.solver.solve`` at 10 Hz and delivered
50 ms late -> ``Pilot.tick`` (guard inside) -> velocity. The robot drives from goal to goal; each
goal is a random free point 1-6 m away in a straight clear line with a random final heading.

``--planned``: the pilot gets the A* planner over the plan's rasterised map (``FloorPlan.to_grid``,
0.05 m) as its path provider, and goals are any free point the planner reaches (path 1-15 m, any
room); the ideal time is then the planned path's length / v_max plus its turns / omega_max. The
planner lays legs the guard accepts (the ultrasonic's cone ray-cast over the map, door centres),
so the path, and its ideal time, has the extra stops a real robot needs in front of doors.

Per goal: control error (fused pose at arrival vs goal), true error (truth at arrival vs goal),
final heading error (true), time to goal against the ideal (distance / v_max + turns / omega_max).
Baselines measured in the same run: the ideal time, and the fusion's own error (fused vs truth at
every control tick) that bounds how well any controller steering on it can do.

Where the time goes: each goal's time is split by what the go-to was doing (turn toward the goal,
accelerating, cruising, braking, inside near_radius = approach and arrival window, re-aim, final
turn, correction after it); printed for the N slowest goals and as means by distance, next to the
floor: the least time the limits allow (the ideal plus the acceleration ramps it ignores).

Goals: control error median <= 2 cm, p95 <= 3 cm; true error p95 <= 15 cm and no worse than the
fusion's own p95; heading <= 2 deg (p95); time <= 1.3x ideal (median).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fleetlink.agent.board.session import PollRates
from fleetlink.agent.fusion import Fusion
from fleetlink.agent.guard import GuardInputs
from fleetlink.agent.mapping.planner import PathPlanner
from fleetlink.agent.motion import wrap_angle
from fleetlink.agent.odometry import Odometry
from fleetlink.agent.pilot import EventKind, Pilot
from fleetlink.agent.uwb_input import FixObservation
from fleetlink.devices.controlbus.snapshot import BoardSnapshot
from fleetlink.field.lockstep import FieldRun
from fleetlink.field.plans import FloorPlan, load_plan
from fleetlink.field.scenario import LidarSettings, RobotSpec, Scenario
from fleetlink.positioning.anchors import anchors_from
from fleetlink.positioning.ranging import NoiseProfile, RangingModel
from fleetlink.positioning.solver import Solution, solve
from fleetlink.site.lockstep import drive_by_session

POLL = PollRates(
    motion=50.0, motor=50.0, sensors=20.0, bumpers=20.0, status=0.5, power=0.0, health=1.0,
    payload=0.0, env=0.0, buttons=0.0, imu=50.0, base_command=0.0,
)  # fmt: skip
UWB_HZ = 10.0
UWB_LATENCY_S = 0.05
TAG_Z = 0.25
WARMUP_S = 4.0  # drive straight so the fusion finds its heading before the first goal
GOAL_TIMEOUT_S = 40.0


@dataclass
class Goal:
    x: float
    y: float
    theta: float
    t_sent: float
    ideal_s: float
    distance_m: float
    turn_rad: float = 0.0
    turns: list[float] = field(default_factory=list)  # each turn, rad (straight: toward the goal, final)
    legs: list[float] = field(default_factory=list)  # planned: each leg, m (the robot stops to turn between)
    result: dict[str, float | str] = field(default_factory=dict)
    phases: dict[str, float] = field(default_factory=dict)  # where the time went (s)
    final_seen: bool = False


def pick_goal(plan: FloorPlan, rng: np.random.Generator, x: float, y: float, th: float) -> tuple[float, float, float]:
    """A free point 1-6 m away whose straight line from here is clear, and clear around the goal
    (the guard refuses a drive that would end within its stop distance of something ahead)."""
    for _ in range(2000):
        d = rng.uniform(1.0, 6.0)
        a = rng.uniform(-math.pi, math.pi)
        gx, gy = x + d * math.cos(a), y + d * math.sin(a)
        if not plan.is_clear(gx, gy, 0.85):
            continue
        steps = max(2, int(d / 0.1))
        if all(plan.is_clear(x + (gx - x) * k / steps, y + (gy - y) * k / steps, 0.5) for k in range(1, steps)):
            return gx, gy, float(rng.uniform(-math.pi, math.pi))
    raise RuntimeError(f"no reachable goal from ({x:.2f}, {y:.2f})")


def pick_planned_goal(
    plan: FloorPlan, planner: PathPlanner, rng: np.random.Generator, x: float, y: float
) -> tuple[float, float, float, list[tuple[float, float]]]:
    """Any free point (clear for the guard's end check) whose planned path from here is 1-15 m."""
    xmin, ymin, xmax, ymax = plan.bounds
    for _ in range(2000):
        gx, gy = float(rng.uniform(xmin, xmax)), float(rng.uniform(ymin, ymax))
        if not plan.is_clear(gx, gy, 0.85) or not planner.is_free((gx, gy)):
            continue
        path = planner((x, y), (gx, gy))
        if not path:
            continue
        pts = [(x, y), *path]
        length = sum(math.dist(a, b) for a, b in itertools.pairwise(pts))
        if 1.0 <= length <= 15.0:
            return gx, gy, float(rng.uniform(-math.pi, math.pi)), pts
    raise RuntimeError(f"no reachable goal from ({x:.2f}, {y:.2f})")


def free_start(plan: FloorPlan, rng: np.random.Generator) -> tuple[float, float, float]:
    """A start with room to drive WARMUP_S straight ahead."""
    xmin, ymin, xmax, ymax = plan.bounds
    while True:
        x, y, th = rng.uniform(xmin, xmax), rng.uniform(ymin, ymax), rng.uniform(-math.pi, math.pi)
        if all(plan.is_clear(x + k * 0.1 * math.cos(th), y + k * 0.1 * math.sin(th), 0.85) for k in range(0, 25)):
            return x, y, th


class Bench:
    def __init__(self, plan_name: str, goals: int, seed: int, planned: bool = False) -> None:
        self.plan = load_plan(plan_name)
        self.planner: PathPlanner | None = None
        if planned:
            grid = self.plan.to_grid(0.05)
            self.planner = PathPlanner(grid.grid, grid.resolution, grid.origin[:2])
        self.rng = np.random.default_rng(seed)
        start = free_start(self.plan, self.rng)
        scenario = Scenario(
            name="goto-bench",
            plan=plan_name,
            seed=seed,
            duration=1e9,
            robots=(RobotSpec("r1", pose=start, drive="idle", lidar=False),),
            lidar=LidarSettings(enabled=False),
        )
        self.run = FieldRun(scenario, self.plan, open_loop=False)
        self.rig = self.run.rigs[0]
        drive_by_session(self.run, 0, self.drive, POLL)
        self.board = self.rig.robot.board
        self.anchors = anchors_from(self.plan.anchors)
        self.ranging = RangingModel(
            self.anchors, NoiseProfile.realistic(), np.random.default_rng(seed + 1), self.plan.segments()
        )
        self.odometry = Odometry(wheel_track_m=self.board.config.wheel_track)
        self.fusion = Fusion()
        self.pilot = Pilot(path_provider=self.planner.route if self.planner else None)
        self.replans = 0
        self.wanted = goals
        self.goals: list[Goal] = []
        self.current: Goal | None = None
        self.next_fix = 0.0
        self.in_flight: list[tuple[float, FixObservation]] = []
        self.last_solution: Solution | None = None
        self.last_odom_t = -1.0
        self.fused_err: list[float] = []
        self.fix_err: list[float] = []
        self.refused = 0
        self.failed: list[str] = []
        self.done = False
        self.last_tick: float | None = None
        self.last_v = 0.0

    def truth(self) -> tuple[float, float, float]:
        st = self.board.state
        return st.x, st.y, st.theta

    def uwb(self, t: float) -> None:
        """Fixes measured at the true position every 0.1 s, delivered UWB_LATENCY_S later."""
        while t >= self.next_fix:
            x, y, _ = self.truth()
            sol = solve(self.anchors, self.ranging.measure(x, y, TAG_Z), TAG_Z, self.last_solution)
            if sol.ok:
                self.last_solution = sol
                self.fix_err.append(math.hypot(sol.x - x, sol.y - y))
                obs = FixObservation(t, sol.x, sol.y, sol.sd_x, sol.sd_y, sol.quality, "native")
                self.in_flight.append((t + UWB_LATENCY_S, obs))
            self.next_fix += 1.0 / UWB_HZ
        while self.in_flight and self.in_flight[0][0] <= t:
            _, obs = self.in_flight.pop(0)
            self.fusion.add_fix(obs, t)

    def drive(self, snap: BoardSnapshot, t: float) -> tuple[float, float]:
        if snap.motor is not None and snap.updated > self.last_odom_t:
            self.last_odom_t = snap.updated
            odom = self.odometry.update(
                snap.updated, snap.motor.left, snap.motor.right, snap.imu.yaw if snap.imu else None
            )
            self.fusion.predict(odom)
        self.uwb(t)
        mp = self.fusion.map_pose()
        pose = (mp.x, mp.y, mp.theta)
        b = snap.bumpers
        front = snap.sensors.distances[0] if snap.sensors and snap.sensors.distances else 0.0
        inputs = GuardInputs(
            ultrasonic_m=front if front > 0 else None,
            cliff=b is not None and (b.triggered(2) or b.triggered(3)),
            bumped=b is not None and (b.triggered(0) or b.triggered(1)),
        )
        if t < WARMUP_S:
            # Warm-up: straight ahead until the fusion knows its heading.
            self.pilot.teleop(t, 0.3, 0.0, 0.5, "bench")
        elif self.fusion.heading_initialized:
            tx, ty, _ = self.truth()
            self.fused_err.append(math.hypot(mp.x - tx, mp.y - ty))
            if self.current is None and not self.done:
                self.send_goal(t, pose)
        out = self.pilot.tick(t, pose, inputs)
        self.account(t, out.v, pose)
        for ev in out.events:
            self.on_event(t, ev.kind, ev.reason, pose)
        if self.current is not None and t - self.current.t_sent > max(GOAL_TIMEOUT_S, 3 * self.current.ideal_s):
            self.pilot.action(t, "cancel", "bench")
        return out.v, out.omega

    def account(self, t: float, v: float, pose: tuple[float, float, float]) -> None:
        """Charge the time since the last tick to what the go-to was doing."""
        g, last = self.current, self.last_tick
        self.last_tick = t
        if g is None or last is None or t <= last:
            self.last_v = v
            return
        gt = self.pilot.goto
        phase = gt.phase.value
        if phase == "final_heading":
            g.final_seen = True
            key = "final_turn"
        elif g.final_seen:
            key = "correction"  # closing a pose that settled during the final turn, and turning again
        elif phase == "rotate":
            key = "turn" if gt.retries == 0 else "re_aim"
        elif phase == "drive":
            lim = self.pilot.config.limits.v_max
            near = gt.goal is not None and math.dist(gt.goal, pose[:2]) <= gt.config.near_radius_m
            if near and gt.index == len(gt.waypoints) - 1:
                key = "arrive"  # inside near_radius: creeping and the arrival window
            elif v > self.last_v + 1e-4 and v < lim - 1e-3:
                key = "accel"
            elif v < self.last_v - 1e-4:
                key = "brake"
            else:
                key = "cruise"
        else:
            key = "other"
        g.phases[key] = g.phases.get(key, 0.0) + (t - last)
        self.last_v = v

    def send_goal(self, t: float, pose: tuple[float, float, float]) -> None:
        if len(self.goals) >= self.wanted:
            self.done = True
            return
        tx, ty, _ = self.truth()
        lim = self.pilot.config.limits
        if self.planner is not None:
            gx, gy, gth, pts = pick_planned_goal(self.plan, self.planner, self.rng, pose[0], pose[1])
            d, turn, heading = 0.0, 0.0, pose[2]
            turns, legs = [], []
            for (ax, ay), (bx, by) in itertools.pairwise(pts):
                d += math.hypot(bx - ax, by - ay)
                legs.append(math.hypot(bx - ax, by - ay))
                bearing = math.atan2(by - ay, bx - ax)
                turns.append(wrap_angle(bearing - heading))
                turn += abs(turns[-1])
                heading = bearing
            turns.append(wrap_angle(gth - heading))
            turn += abs(turns[-1])
            g = Goal(gx, gy, gth, t, d / lim.v_max + turn / lim.omega_max, d, turn, turns, legs)
            self.goals.append(g)
            self.current = g
            r = self.pilot.order(t, f"g{len(self.goals)}", 0, gx, gy, gth, "bench")
            assert r.accepted, r
            return
        gx, gy, gth = pick_goal(self.plan, self.rng, tx, ty, pose[2])
        d = math.hypot(gx - pose[0], gy - pose[1])
        bearing = math.atan2(gy - pose[1], gx - pose[0])
        turn = abs(wrap_angle(bearing - pose[2])) + abs(wrap_angle(gth - bearing))
        g = Goal(gx, gy, gth, t, d / lim.v_max + turn / lim.omega_max, d, turn)
        g.turns = [wrap_angle(bearing - pose[2]), wrap_angle(gth - bearing)]
        self.goals.append(g)
        self.current = g
        r = self.pilot.order(t, f"g{len(self.goals)}", 0, gx, gy, gth, "bench")
        assert r.accepted, r

    def on_event(self, t: float, kind: EventKind, reason: str, pose: tuple[float, float, float]) -> None:
        g = self.current
        if kind is EventKind.GUARD_REFUSAL:
            self.refused += 1
        if kind is EventKind.REPLANNED:
            self.replans += 1
        if g is None or kind not in (EventKind.GOAL_REACHED, EventKind.GOAL_FAILED, EventKind.GOAL_CANCELLED):
            return
        self.current = None
        if kind is not EventKind.GOAL_REACHED:
            self.failed.append(f"goal {len(self.goals)}: {kind.value} {reason}")
            g.result = {"status": kind.value}
            return
        tx, ty, tth = self.truth()
        g.result = {
            "status": "reached",
            "control_error_m": math.hypot(pose[0] - g.x, pose[1] - g.y),
            "true_error_m": math.hypot(tx - g.x, ty - g.y),
            "heading_error_rad": abs(wrap_angle(tth - g.theta)),
            "control_heading_error_rad": abs(wrap_angle(pose[2] - g.theta)),
            "time_s": t - g.t_sent,
            "ideal_s": g.ideal_s,
            "distance_m": g.distance_m,
            "turn_rad": g.turn_rad,
            "retries": float(self.pilot.goto.retries),
        }

    def go(self) -> float:
        t0 = time.perf_counter()
        chunk = 20.0
        end = 0.0
        while not self.done and end < WARMUP_S + self.wanted * GOAL_TIMEOUT_S * (3 if self.planner else 1):
            end += chunk
            self.run.run(end)
        self.run.close()
        return time.perf_counter() - t0


def pct(vals: list[float], q: float) -> float:
    return float(np.percentile(vals, q)) if vals else math.nan


def profile_s(dist: float, v_max: float, accel: float, decel: float) -> float:
    """Least time over ``dist`` from rest to rest: speed up at ``accel``, brake at ``decel``, top speed ``v_max``."""
    reach = v_max * v_max / 2.0 * (1.0 / accel + 1.0 / decel)
    if dist >= reach:
        return v_max / accel + v_max / decel + (dist - reach) / v_max
    peak = math.sqrt(2.0 * dist / (1.0 / accel + 1.0 / decel))
    return peak / accel + peak / decel


def floor_s(bench: Bench, g: Goal) -> float:
    """The least time the limits allow (ideal + the acceleration ramps it ignores), each turn and the
    drive from rest to rest with the controller's braking share; no windows, no motor lag."""
    lim, c = bench.pilot.config.limits, bench.pilot.config.goto
    turns = g.turns or [g.turn_rad]
    t = sum(profile_s(abs(a), lim.omega_max, lim.alpha_max, c.brake_margin * lim.alpha_max) for a in turns)
    return t + sum(profile_s(leg, lim.v_max, lim.a_max, c.brake_margin * lim.a_max) for leg in g.legs or [g.distance_m])


PHASES = ("turn", "accel", "cruise", "brake", "arrive", "re_aim", "final_turn", "correction", "other")


def print_breakdown(bench: Bench, slowest: int) -> None:
    """Where the time goes: the slowest goals one by one, and the time over ideal by distance."""
    done = [g for g in bench.goals if g.result.get("status") == "reached"]
    if not done:
        return

    def ratio(g: Goal) -> float:
        return float(g.result["time_s"]) / g.ideal_s

    print(
        f"slowest {min(slowest, len(done))} goals (s per phase; arrive = inside near_radius: creep + arrival window):"
    )
    print(
        f"{'dist m':>6} {'turn deg':>8} {'ideal':>6} {'time':>6} {'ratio':>6} {'retry':>5} "
        + " ".join(f"{p:>7}" for p in PHASES)
    )
    for g in sorted(done, key=ratio, reverse=True)[:slowest]:
        cells = " ".join(f"{g.phases.get(p, 0.0):>7.2f}" for p in PHASES)
        print(
            f"{g.distance_m:>6.2f} {math.degrees(g.turn_rad):>8.0f} {g.ideal_s:>6.2f} {float(g.result['time_s']):>6.2f} "
            f"{ratio(g):>6.2f} {int(float(g.result['retries'])):>5} {cells}"
        )
    print("mean s per phase by distance (and the time / ideal median, p95):")
    print(
        f"{'dist m':>7} {'n':>3} {'ratio med':>9} {'p95':>6} {'floor med':>9} {'p95':>6} {'t/floor p95':>11} "
        + " ".join(f"{p:>7}" for p in PHASES)
    )
    for lo, hi in ((1, 2), (2, 3), (3, 4), (4, 6), (6, 16), (0, 16)):
        bucket = [g for g in done if lo <= g.distance_m < hi]
        if not bucket:
            continue
        rs = [ratio(g) for g in bucket]
        fl = [floor_s(bench, g) / g.ideal_s for g in bucket]
        over = [float(g.result["time_s"]) / floor_s(bench, g) for g in bucket]
        cells = " ".join(f"{sum(g.phases.get(p, 0.0) for g in bucket) / len(bucket):>7.2f}" for p in PHASES)
        name = "all" if lo == 0 else f"{lo}-{hi}"
        print(
            f"{name:>7} {len(bucket):>3} {pct(rs, 50):>9.2f} {pct(rs, 95):>6.2f} {pct(fl, 50):>9.2f} "
            f"{pct(fl, 95):>6.2f} {pct(over, 95):>11.2f} {cells}"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--plan", default="office", choices=("office", "apartment"))
    parser.add_argument("--goals", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--quick", action="store_true", help="10 goals (a smoke test)")
    parser.add_argument("--planned", action="store_true", help="goals anywhere reachable, routed by A* over the plan")
    parser.add_argument("--breakdown", type=int, default=10, help="print where the time went on the N slowest goals")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON (SI units)")
    args = parser.parse_args(argv)
    n = 10 if args.quick else args.goals

    bench = Bench(args.plan, n, args.seed, planned=args.planned)
    wall = bench.go()
    ok = [g.result for g in bench.goals if g.result.get("status") == "reached"]

    def col(key: str) -> list[float]:
        return [float(r[key]) for r in ok]

    ctrl, true, head = col("control_error_m"), col("true_error_m"), col("heading_error_rad")
    chead = col("control_heading_error_rad")
    ratio = [float(r["time_s"]) / float(r["ideal_s"]) for r in ok]
    fused_p95, fix_p95 = pct(bench.fused_err, 95), pct(bench.fix_err, 95)
    figures = {
        "plan": args.plan,
        "seed": args.seed,
        "goals": len(bench.goals),
        "reached": len(ok),
        "not_reached": bench.failed,
        "guard_refusals": bench.refused,
        "planned": args.planned,
        "replans": bench.replans,
        "sim_s": bench.run.clock.now(),
        "wall_s": wall,
        "control_error_median_m": pct(ctrl, 50),
        "control_error_p95_m": pct(ctrl, 95),
        "control_error_max_m": max(ctrl, default=math.nan),
        "true_error_median_m": pct(true, 50),
        "true_error_p95_m": pct(true, 95),
        "true_error_max_m": max(true, default=math.nan),
        "fusion_error_median_m": pct(bench.fused_err, 50),
        "fusion_error_p95_m": fused_p95,
        "uwb_fix_error_p95_m": fix_p95,
        "true_vs_fusion_p95_ratio": pct(true, 95) / fused_p95,
        "heading_error_median_rad": pct(head, 50),
        "heading_error_p95_rad": pct(head, 95),
        "control_heading_error_p95_rad": pct(chead, 95),
        "time_to_goal_median_s": pct(col("time_s"), 50),
        "ideal_time_median_s": pct(col("ideal_s"), 50),
        "time_vs_ideal_median_ratio": pct(ratio, 50),
        "time_vs_ideal_p95_ratio": pct(ratio, 95),
    }
    f = figures
    cm, deg = 100.0, math.degrees(1.0)
    print(
        f"go-to: {f['reached']}/{f['goals']} goals reached on the {args.plan} plan (seed {args.seed}), "
        f"steering on the fused pose{', routed by A*' if args.planned else ''}; "
        f"{f['sim_s']:.0f} s simulated in {wall:.0f} s"
    )
    print(f"{'figure':<34} {'median':>8} {'p95':>8} {'max':>8} {'baseline (same run)':>28} {'goal':>16}")
    rows = [
        ("control error (fused vs goal) cm", pct(ctrl, 50) * cm, pct(ctrl, 95) * cm, f["control_error_max_m"] * cm,
         "", "med<=2, p95<=3"),
        ("true error (truth vs goal) cm", pct(true, 50) * cm, pct(true, 95) * cm, f["true_error_max_m"] * cm,
         f"fusion p95 {fused_p95 * cm:.1f} -> {f['true_vs_fusion_p95_ratio']:.2f}x", "p95<=15, <=1x"),
        ("heading error (truth) deg", pct(head, 50) * deg, pct(head, 95) * deg, max(head, default=math.nan) * deg,
         f"fused-pose p95 {pct(chead, 95) * deg:.2f}", "p95<=2"),
        ("time to goal / ideal", pct(ratio, 50), pct(ratio, 95), max(ratio, default=math.nan),
         f"ideal median {f['ideal_time_median_s']:.1f} s", "med<=1.3x"),
    ]  # fmt: skip
    for name, med, p95, mx, base, goal in rows:
        print(f"{name:<34} {med:>8.2f} {p95:>8.2f} {mx:>8.2f} {base:>28} {goal:>16}")
    print(f"raw UWB fix error p95: {fix_p95 * cm:.1f} cm; guard refusals: {bench.refused}; re-plans: {bench.replans}")
    for line in bench.failed:
        print(f"  not reached: {line}")
    print_breakdown(bench, args.breakdown)
    checks = [
        ("control error median <= 2 cm", f["control_error_median_m"] <= 0.02),
        ("control error p95 <= 3 cm", f["control_error_p95_m"] <= 0.03),
        ("true error p95 <= 15 cm", f["true_error_p95_m"] <= 0.15),
        ("true error p95 <= fusion p95", f["true_vs_fusion_p95_ratio"] <= 1.0),
        ("heading p95 <= 2 deg", f["heading_error_p95_rad"] <= math.radians(2)),
        ("time median <= 1.3x ideal", f["time_vs_ideal_median_ratio"] <= 1.3),
        ("all goals reached", f["reached"] == f["goals"]),
    ]
    for what, met in checks:
        print(f"goal {what}: {'met' if met else 'NOT met'}")
    if args.json:
        figures["checks"] = {what: met for what, met in checks}
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
