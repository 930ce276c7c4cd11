"""The disinfection round and the sweep, scored against truth, with the baselines in the same run.

    python bench/coverage.py [--quick] [--rooms apartment/living,office/room-1] [--jobs N] [--json FILE]

In lockstep with whole agents (fleetlink.site.disinfection ``RoundRun``, over site/lockstep.py's
MissionRun): for each room, a robot (the field's disinfection robot: 40 W of UV-C at 0.6 m, see
site/agents.py) is put down by the door, the operator drives it 2.4 m in, fetches its map over
the link, plans as the console does, sends the orders and waits for them to finish; the floor's
true dose comes from the robot's true pose and its board's lamp. Modes, each its own run:

* ``uv``: the console's planner (``site/rounds.py``: dwell points, 99.5 % of the lamp-reachable
  floor, 10 % dose margin, the lamp on between points), then a top-up pass on what the robot's
  own dose layer says is still short, when it reads under 99 % (``MAX_PASSES``, ``CERTIFIED``);
* ``uv x2``: the same with two robots splitting the room;
* ``park`` (baseline a): park in the middle, dwell until the farthest reachable floor in line of
  sight has the dose;
* ``lawnmower`` (baseline b): lanes 0.6 m apart over the room with the lamp on at the one constant
  speed that doses as much of the reachable floor as ``uv`` plans for;
* ``sweep``: the boustrophedon floor-coverage route (no lamp), scored as the floor the robot's
  brush (its 0.34 m diameter) passed over (surveys included), and the path driven on the sweep's
  order from its first lane on against the boustrophedon ideal (reachable floor / brush width);
  the surveys' path (they map the room first; a room mapped before needs none) is reported
  beside it as ``survey_path_m``.

Scored on the floor a round can reach (``coverage.reachable``: floor some place the robot may
stand in the room lights well enough to give the dose within 2 minutes, on the plan's true
floor; for a sweep ``coverage.sweepable``). Lamp-on time with the robot outside the room is
reported. Goals (issue 16): >= 99 % of the reachable floor at the target dose in every room; time
<= 0.5x baseline (a) on the apartment and the office; two robots <= 0.6x one robot's time; sweep
>= 95 % with a path <= 1.2x the ideal.
"""

from __future__ import annotations

# ruff: noqa: E402 -- first, before numpy is imported: the BLAS kernels every fleetlink command runs
# (shared/blas.py), so the figures are the same on every x86-64 host.
from fleetlink.shared.blas import pin_blas_kernels

pin_blas_kernels()

import argparse
import json
import logging
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

# (plan, room, rectangle, where one robot is put down (x, y, heading deg), where a second one is)
ROOMS: dict[
    str, tuple[str, str, tuple[float, float, float, float], tuple[float, float, float], tuple[float, float, float]]
] = {
    "apartment/living": ("apartment", "living", (0.0, 0.0, 6.0, 4.5), (1.0, 0.8, 25.0), (5.5, 3.8, -150.0)),
    "apartment/kitchen": ("apartment", "kitchen", (6.0, 0.0, 10.0, 4.5), (6.5, 3.5, 0.0), (8.8, 0.6, 180.0)),
    "apartment/bedroom": ("apartment", "bedroom", (0.0, 5.7, 6.5, 8.0), (2.2, 6.2, 0.0), (6.0, 6.6, 180.0)),
    "office/room-1": ("office", "room-1", (6.0, 0.0, 11.5, 8.5), (6.8, 7.6, -45.0), (10.8, 2.5, 120.0)),
    "office/room-8": ("office", "room-8", (11.5, 11.0, 17.0, 20.0), (12.5, 12.0, 60.0), (16.0, 19.0, 180.0)),
}
QUICK = ("apartment/living",)
MODES = ("uv", "uv2", "park", "lawnmower", "sweep")


def run_one(room: str, mode: str, seed: int) -> dict[str, Any]:
    from fleetlink.site.disinfection import RoundRun, RoundSetup

    logging.disable(logging.WARNING)
    plan, name, rect, a, b = ROOMS[room]
    robots = (("uvc-1", *a),) if mode != "uv2" else (("uvc-1", *a), ("uvc-2", *b))
    setup = RoundSetup(plan, name, rect, robots, mode="uv" if mode == "uv2" else mode, seed=seed, deadline_s=7200.0)
    with RoundRun(setup) as run:
        result = run.run()
    figures = result.figures()
    figures["mode"] = mode
    figures["notes"] = result.notes[-6:]
    return figures


def ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b <= 0 else a / b


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the apartment's living room only")
    ap.add_argument("--rooms", help="comma-separated rooms: " + ", ".join(ROOMS))
    ap.add_argument("--modes", default=",".join(MODES), help="comma-separated: " + ", ".join(MODES))
    ap.add_argument("--seed", type=int, default=16)
    ap.add_argument("--jobs", type=int, default=2, help="runs in parallel (processes)")
    ap.add_argument("--json", help="write the figures (SI units) to this file")
    args = ap.parse_args(argv)
    rooms = list(QUICK) if args.quick else (args.rooms.split(",") if args.rooms else list(ROOMS))
    modes = args.modes.split(",")
    for r in rooms:
        if r not in ROOMS:
            ap.error(f"unknown room {r!r} (one of: {', '.join(ROOMS)})")
    wall0 = time.perf_counter()
    jobs = [(r, m) for r in rooms for m in modes]
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = {pool.submit(run_one, job[0], job[1], args.seed): job for job in jobs}
        done: dict[tuple[str, str], dict[str, Any]] = {}
        for f in as_completed(futures):  # progress as each run ends (a run takes minutes)
            job = futures[f]
            done[job] = f.result()
            print(f"  {len(done)}/{len(jobs)} {job[0]} {job[1]}: {done[job]['coverage_ratio']:.4f}", file=sys.stderr)
        results = {job: done[job] for job in jobs}
    rows = []
    print(f"{'room':20} {'mode':10} {'coverage':>9} {'reach m2':>8} {'time s':>8} {'pred s':>8} "
          f"{'lamp out s':>10} {'path m':>7} {'ideal m':>7} {'skips':>5} {'bumps':>5}")  # fmt: skip
    for (room, mode), f in results.items():
        t = "-" if f["time_s"] is None else f"{f['time_s']:.0f}"
        ideal = "-" if f["ideal_path_m"] is None else f"{f['ideal_path_m']:.1f}"
        print(f"{room:20} {mode:10} {100 * f['coverage_ratio']:8.2f}% {f['reachable_m2']:8.1f} {t:>8} "
              f"{f['predicted_s']:8.0f} {f['lamp_outside_s']:10.0f} {f['path_m']:7.1f} {ideal:>7} "
              f"{f['skipped_nodes']:5d} {f['bumps']:5d}")  # fmt: skip
        rows.append({"room": room, **f})
    print()
    summary: dict[str, Any] = {}
    for room in rooms:
        got = {m: results.get((room, m)) for m in modes}
        uv, uv2, park, mow, sweep = (got.get(m) for m in MODES)
        s: dict[str, Any] = {}
        if uv is not None:
            s["uv_coverage_ratio"] = uv["coverage_ratio"]
            s["uv_time_s"] = uv["time_s"]
        if uv is not None and park is not None:
            s["time_vs_park_ratio"] = ratio(uv["time_s"], park["time_s"])
            s["park_coverage_ratio"] = park["coverage_ratio"]
        if uv is not None and mow is not None:
            s["time_vs_lawnmower_ratio"] = ratio(uv["time_s"], mow["time_s"])
            s["lawnmower_coverage_ratio"] = mow["coverage_ratio"]
        if uv is not None and uv2 is not None:
            s["two_robots_time_ratio"] = ratio(uv2["time_s"], uv["time_s"])
            s["two_robots_coverage_ratio"] = uv2["coverage_ratio"]
        if sweep is not None:
            s["sweep_coverage_ratio"] = sweep["coverage_ratio"]
            s["sweep_path_vs_ideal_ratio"] = ratio(sweep["path_m"], sweep["ideal_path_m"])
        summary[room] = s

        def show(v: Any) -> str:
            return "-" if v is None else f"{v:.3f}"

        print(f"{room}: " + ", ".join(f"{k} {show(v)}" for k, v in s.items()))
    for plan in sorted({ROOMS[r][0] for r in rooms}):
        ours = [results[(r, "uv")]["time_s"] for r in rooms if ROOMS[r][0] == plan and (r, "uv") in results]
        base = [results[(r, "park")]["time_s"] for r in rooms if ROOMS[r][0] == plan and (r, "park") in results]
        if ours and base and None not in ours and None not in base:
            summary[f"{plan}_time_vs_park_ratio"] = sum(ours) / sum(base)
            print(
                f"{plan}: uv time {sum(ours):.0f} s vs park {sum(base):.0f} s: {sum(ours) / sum(base):.3f}x (goal <= 0.5)"
            )
    wall = time.perf_counter() - wall0
    print(f"\n{len(jobs)} runs in {wall:.0f} s wall")
    if args.json:
        Path(args.json).write_text(json.dumps({"runs": rows, "summary": summary, "wall_s": wall}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
