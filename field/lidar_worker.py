"""Lidar revolutions cast in a second process, so a lockstep run uses both cores.

The main process keeps stepping physics while the worker ray-casts; nothing waits until the
results are needed. Determinism is kept: the worker owns each robot's ``LidarModel`` (same seed as
in process), requests travel in order (``ProcessWorker``), so each robot's random stream is
consumed in the same order, and geometry changes (a door closes) reach the worker between the same
scans.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from fleetlink.field.lidar import LidarConfig, LidarModel
from fleetlink.field.raycast import Raycaster
from fleetlink.shared.worker import ProcessWorker

__all__ = ["LidarWorker", "ScanResult"]


@dataclass(frozen=True, slots=True)
class ScanResult:
    robot: int
    t: float
    angles: np.ndarray
    distances: np.ndarray
    qualities: np.ndarray
    cast_seconds: float  # worker time spent on this revolution


class _Caster:
    """The worker's side: the models and the caster, one request at a time."""

    def __init__(self) -> None:
        self.models: dict[int, LidarModel] = {}
        self.caster: Raycaster | None = None

    def __call__(self, msg: tuple[Any, ...]) -> Any:
        kind = msg[0]
        if kind == "model":
            _, index, config, seed = msg
            self.models[index] = LidarModel(config, np.random.default_rng(seed))
        elif kind == "segments":
            if self.caster is None:
                self.caster = Raycaster(msg[1])
            self.caster.set_segments(msg[1])
        elif kind == "scan":
            _, index, t, x, y, th, circles = msg
            assert self.caster is not None
            t0 = time.perf_counter()
            angles, dist, qual = self.models[index].revolution(x, y, th, self.caster, circles)
            return ScanResult(index, t, angles, dist, qual, time.perf_counter() - t0)
        return None


class LidarWorker:
    """One worker process casting every robot's lidar. Use as a context manager, or ``close()``."""

    def __init__(self, segments: np.ndarray) -> None:
        self._worker = ProcessWorker("fleetlink-lidar", _Caster)
        self._worker.tell(("segments", np.asarray(segments, dtype=float)))
        self.results: list[ScanResult] = []

    @property
    def pending(self) -> int:
        return self._worker.pending

    def add_model(self, index: int, config: LidarConfig, seed: int) -> None:
        self._worker.tell(("model", index, config, seed))

    def set_segments(self, segments: np.ndarray) -> None:
        self._worker.tell(("segments", np.asarray(segments, dtype=float)))

    def submit(self, index: int, t: float, x: float, y: float, theta: float, circles: np.ndarray | None) -> None:
        self._worker.call(("scan", index, t, x, y, theta, circles))

    def drain(self) -> list[ScanResult]:
        """Wait for every submitted revolution; return all results so far (in submission order)."""
        while self._worker.pending:
            self.results.append(self._worker.reply())
        return self.results

    def close(self) -> None:
        self._worker.close()

    def __enter__(self) -> LidarWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
