"""Benchmark of the lidar path: ray casting, the lidar model, and decoding the node stream.

    .venv/bin/python bench/lidar.py [--quick] [--json FILE]

1. ``Raycaster.cast_fan``: one 1450-ray turn (8000 samples/s at 5.5 Hz) from random poses in a
   24 x 16 m hall with 50, 100 and 300 segments (the outer walls, boxes, free walls), without and
   with 20 other robots as circles, max range 12 m. Baseline, in the same run: a dense NumPy
   broadcast of every ray against every segment (what the span method avoids), and ``np.cos`` of
   1450 angles, as a yardstick of the machine's speed.
2. ``LidarModel.revolution`` (the cast plus noise, dropouts, quality) at 5.5 and 10 Hz, 300
   segments and 20 circles, and the field's budget: 50 robots at 10 Hz as a share of one core.
3. ``LidarDecoder`` + ``RevolutionAssembler``: nodes per second decoded from a recorded stream,
   batch and per-node events.

Times are the minimum over repeated batches (the machine is shared), medians alongside.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections.abc import Callable

import numpy as np

from fleetlink.devices.rplidar import protocol as lp
from fleetlink.field.lidar import LidarConfig, LidarModel
from fleetlink.field.raycast import Raycaster


def hall(n: int, rng: np.random.Generator, w: float = 24.0, h: float = 16.0) -> np.ndarray:
    segs: list[tuple[float, float, float, float]] = [(0, 0, w, 0), (w, 0, w, h), (w, h, 0, h), (0, h, 0, 0)]
    while len(segs) < n:
        if rng.random() < 0.6:  # a box
            x, y = rng.uniform(1, w - 2), rng.uniform(1, h - 2)
            bw, bh = rng.uniform(0.3, 1.5, 2)
            segs += [(x, y, x + bw, y), (x + bw, y, x + bw, y + bh), (x + bw, y + bh, x, y + bh), (x, y + bh, x, y)]
        else:  # a free wall
            x, y, a, length = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0, 2 * math.pi), rng.uniform(1, 6)
            segs.append((x, y, x + length * math.cos(a), y + length * math.sin(a)))
    return np.array(segs[:n], dtype=float)


def timed(fn: Callable[[int], object], calls: int, repeats: int) -> tuple[float, float]:
    """(min, median) seconds per call over ``repeats`` batches of ``calls`` calls."""
    per: list[float] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(calls):
            fn(i)
        per.append((time.perf_counter() - t0) / calls)
    return min(per), statistics.median(per)


def dense_cast(segs: np.ndarray, x: float, y: float, angles: np.ndarray, rmax: float) -> np.ndarray:
    """Every ray against every segment in one broadcast (the baseline)."""
    dx, dy = np.cos(angles)[:, None], np.sin(angles)[:, None]
    wx, wy = segs[:, 0] - x, segs[:, 1] - y
    ex, ey = segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        den = dx * ey - dy * ex
        t = (wx * ey - wy * ex) / den
        u = (wx * dy - wy * dx) / den
        t = np.where((t >= 0) & (u >= 0) & (u <= 1), t, np.inf).min(axis=1)
    return np.where(t <= rmax, t, np.inf)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions")
    ap.add_argument("--json", help="also write the figures to this file")
    args = ap.parse_args()
    calls, repeats = (20, 3) if args.quick else (100, 7)
    rng = np.random.default_rng(1)
    results: dict[str, float] = {}
    n_rays = 1450
    step = 2 * math.pi / n_rays
    poses = [(rng.uniform(1, 23), rng.uniform(1, 15), rng.uniform(-math.pi, math.pi)) for _ in range(calls)]
    circles = np.column_stack([rng.uniform(0, 24, 20), rng.uniform(0, 16, 20), np.full(20, 0.17)])
    angles = np.arange(n_rays) * step

    base, _ = timed(lambda i: np.cos(angles), calls * 10, repeats)
    results["np_cos_1450_us"] = base * 1e6
    print(f"yardstick: np.cos of 1450 angles {base * 1e6:.1f} us\n")
    print("1. one 1450-ray turn, max range 12 m           min ms   median ms   dense baseline ms")
    for n_seg in (50, 100, 300):
        segs = hall(n_seg, rng)
        rc = Raycaster(segs)
        for circ in (None, circles):
            lo, med = timed(
                lambda i, rc=rc, c=circ: rc.cast_fan(*poses[i][:2], poses[i][2], step, n_rays, 12.0, c), calls, repeats
            )
            key = f"cast_{n_seg}seg_{0 if circ is None else 20}circ_ms"
            results[key] = lo * 1e3
            dense = ""
            if circ is None:
                dlo, _ = timed(
                    lambda i, segs=segs: dense_cast(segs, *poses[i][:2], angles + poses[i][2], 12.0),
                    max(5, calls // 5),
                    3,
                )
                results[f"dense_{n_seg}seg_ms"] = dlo * 1e3
                dense = f"{dlo * 1e3:10.2f}"
            label = f"{n_seg:3d} segments, {0 if circ is None else 20:2d} circles"
            print(f"   {label:42s} {lo * 1e3:7.3f}   {med * 1e3:9.3f}   {dense}")

    print("\n2. LidarModel.revolution, 300 segments, 20 circles        min ms   median ms")
    segs = hall(300, rng)
    rc = Raycaster(segs)
    for rate in (5.5, 10.0):
        model = LidarModel(LidarConfig(rate_hz=rate, dropout=0.01), np.random.default_rng(0))
        lo, med = timed(lambda i, m=model: m.revolution(*poses[i], rc, circles), calls, repeats)
        results[f"revolution_{rate}hz_ms"] = lo * 1e3
        print(
            f"   {rate:4.1f} Hz ({model.config.samples_per_revolution:6.1f} samples)                        {lo * 1e3:7.3f}   {med * 1e3:9.3f}"
        )
        if rate == 10.0:
            share = 50 * rate * med
            results["fifty_robots_10hz_core_share"] = share
            print(
                f"   50 robots at 10 Hz: {share * 100:.0f} % of one core in real time, {2 * share * 100:.0f} % at 2x real time"
            )

    print("\n3. decoding the node stream                              Mnodes/s")
    model = LidarModel(LidarConfig(rate_hz=5.5, dropout=0.02), np.random.default_rng(0))
    stream = b""
    for k in range(10):
        a, d, q = model.revolution(*poses[k % len(poses)], rc, circles)
        stream += lp.encode_nodes(lp.rad_to_device_deg(a), d, q)
    n_nodes = len(stream) // lp.NODE_LEN
    for batch in (True, False):

        def decode(i: int, batch: bool = batch) -> None:
            dec = lp.LidarDecoder(batch=batch)
            dec.assume(lp.SCAN_DESCRIPTOR)
            asm = lp.RevolutionAssembler()
            for j in range(0, len(stream), 4096):
                asm.push_all(dec.feed(stream[j : j + 4096]))

        lo, _ = timed(decode, max(2, calls // 20), repeats)
        rate_n = n_nodes / lo / 1e6
        results[f"decode_{'batch' if batch else 'nodes'}_Mnodes_s"] = rate_n
        print(f"   {'NodeBatch events' if batch else 'one Node event each':50s} {rate_n:8.2f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=2)


if __name__ == "__main__":
    main()
