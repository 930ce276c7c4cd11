"""Lidar revolutions cast in a second process, so a lockstep run uses both cores.

The main process keeps stepping physics while the worker ray-casts; nothing waits unless the
pipe is full. Determinism is kept: the worker owns each robot's ``LidarModel`` (same seed as in
process), requests travel through one ordered pipe, so each robot's random stream is consumed in
the same order, and geometry changes (a door closes) reach the worker between the same scans.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from fleetlink.field.lidar import LidarConfig, LidarModel
from fleetlink.field.raycast import Raycaster

__all__ = ["LidarWorker", "ScanResult"]


@dataclass(frozen=True, slots=True)
class ScanResult:
    robot: int
    t: float
    angles: np.ndarray
    distances: np.ndarray
    qualities: np.ndarray
    cast_seconds: float  # worker time spent on this revolution


def _serve(conn: Connection) -> None:
    """The worker's loop: messages in order, results back."""
    models: dict[int, LidarModel] = {}
    caster: Raycaster | None = None
    conn.send(("ready",))
    while True:
        msg = conn.recv()
        kind = msg[0]
        if kind == "model":
            _, index, config, seed = msg
            models[index] = LidarModel(config, np.random.default_rng(seed))
        elif kind == "segments":
            caster = Raycaster(msg[1]) if caster is None else caster
            caster.set_segments(msg[1])
        elif kind == "scan":
            _, index, t, x, y, th, circles = msg
            assert caster is not None
            t0 = time.perf_counter()
            angles, dist, qual = models[index].revolution(x, y, th, caster, circles)
            conn.send(("scan", index, t, angles, dist, qual, time.perf_counter() - t0))
        elif kind == "stop":
            conn.send(("stopped",))
            return


class LidarWorker:
    """One worker process casting every robot's lidar. Use as a context manager, or ``close()``."""

    def __init__(self, segments: np.ndarray) -> None:
        # fork: the child needs nothing but numpy and the pipe (no logging, no locks), and spawn
        # would re-run the parent's main module. Platforms without fork use spawn.
        ctx: Any = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child,), name="fleetlink-lidar", daemon=True)
        self._proc.start()
        child.close()
        if self._conn.recv()[0] != "ready":
            raise RuntimeError("lidar worker failed to start")
        self._conn.send(("segments", np.asarray(segments, dtype=float)))
        self.results: list[ScanResult] = []
        self.pending = 0

    def add_model(self, index: int, config: LidarConfig, seed: int) -> None:
        self._conn.send(("model", index, config, seed))

    def set_segments(self, segments: np.ndarray) -> None:
        self._conn.send(("segments", np.asarray(segments, dtype=float)))

    def submit(self, index: int, t: float, x: float, y: float, theta: float, circles: np.ndarray | None) -> None:
        self._conn.send(("scan", index, t, x, y, theta, circles))
        self.pending += 1
        # Keep the pipe from filling up: take whatever has come back, without waiting.
        while self._conn.poll():
            self._take(self._conn.recv())

    def drain(self) -> list[ScanResult]:
        """Wait for every submitted revolution; return all results so far (in submission order)."""
        while self.pending:
            self._take(self._conn.recv())
        return self.results

    def _take(self, msg: Any) -> None:
        if msg[0] == "scan":
            _, index, t, angles, dist, qual, secs = msg
            self.results.append(ScanResult(index, t, angles, dist, qual, secs))
            self.pending -= 1

    def close(self) -> None:
        if self._proc.is_alive():
            try:
                self.drain()
                self._conn.send(("stop",))
                while self._conn.recv()[0] != "stopped":
                    pass
            except (EOFError, OSError, BrokenPipeError):
                pass
            self._proc.join(5.0)
            if self._proc.is_alive():
                self._proc.kill()
        self._conn.close()

    def __enter__(self) -> LidarWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
