"""Where the mapper's time goes: cProfile of ``OnboardMapper.add_scan_odometry`` along the office tour.

    python bench/mapping_profile.py [--beams 360] [--scans 600] [--top 25] [--reps 3]

Drives the office tour of ``bench/mapping.py`` once (lockstep, noisy odometry), then prints the
throughput in scans per CPU second (best of ``--reps`` fresh mappers; process CPU time, so other
work on the machine skews it little) and the ``--top`` functions by own time under cProfile (which
roughly doubles the cost of small numpy calls: read the ranking, not the absolute times).

To compare two builds in one session (the machine's load varies from minute to minute), run this
alternately from each build's checkout and compare the "per CPU s" lines.
"""

from __future__ import annotations

import argparse
import cProfile
import importlib.util
import pstats
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--beams", type=int, default=360, choices=(180, 360, 720))
    ap.add_argument("--scans", type=int, default=600)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)

    spec = importlib.util.spec_from_file_location("bench_mapping", Path(__file__).with_name("mapping.py"))
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    from fleetlink.agent.mapping.mapper import OnboardMapper

    drive = bench.drive_office(args.scans / 10.0 + 1.0, beams=(args.beams,))
    rows = list(zip(drive["times"], drive["scans"][args.beams], drive["odom"], strict=True))[: args.scans]

    def run() -> OnboardMapper:
        m = OnboardMapper()
        for t, (d, a), o in rows:
            m.add_scan_odometry(t, d, a, o)
        return m

    best = float("inf")
    for _ in range(args.reps):
        c0 = time.process_time()
        m = run()
        best = min(best, time.process_time() - c0)
    keyframes = m.grid.version
    print(f"{len(rows)} office scans, {args.beams} beams, {keyframes} keyframes integrated")
    print(f"per CPU s: {len(rows) / best:.0f} scans ({1000 * best / len(rows):.2f} ms per scan, best of {args.reps})")

    prof = cProfile.Profile()
    prof.runcall(run)
    pstats.Stats(prof, stream=sys.stdout).sort_stats("tottime").print_stats(args.top)
    return 0


if __name__ == "__main__":
    sys.exit(main())
