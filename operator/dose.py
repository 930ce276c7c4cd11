"""The robots' UV dose layers on the console, merged into the fleet's, and the dose report.

As maps (operator/maps.py): a snapshot per robot from its Zenoh queryable (``fleetlink/v1/<robot>/dose``),
then its ``dose/updates`` patches; a copy that misses a patch (or sees the layer grow) is fetched
again. The layers are summed into one fleet layer in the site frame (``DoseGrid.merged``: every
robot's layer is on one lattice, so no resampling), which the map draws (cells at or over the
target, under it, none) and ``:dose`` summarises.

* ``DoseFollower`` is pure (time passed in): which robots' layers to fetch (``wanted``), the copies
  kept current from snapshots and updates, and the merged ``FleetDose`` it is handed.
* ``DoseFetcher`` is the thin adapter: a worker thread that fetches what the follower wants
  (``fetch(robot)``: ``OperatorLink.fetch_dose``) and merges the layers when they changed, at most
  every ``merge_s``, off the UI thread (the copies are taken under the lock, the sum outside it).
* ``dose_report`` / ``save_report``: the summary (area at the target, area below it, where) over the
  floor of the robots' maps, and the report files (``dose.pgm``, ``dose.png``, ``dose.csv``,
  ``summary.txt``, ``summary.json``), for ``:dose save`` and ``fleetlink dose save``.

Dose updates reach the follower through the console's feed (operator/feed.py), like map updates.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import threading
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from fleetlink.operator.fetcher import SnapshotFetcher
from fleetlink.operator.fleet import FleetModel
from fleetlink.shared.clock import Clock
from fleetlink.shared.dose import (
    J_M2_PER_MJ_CM2,
    DoseGrid,
    DoseSummary,
    FloorMask,
    csv_report,
    pgm_report,
    png_report,
    summarise,
)
from fleetlink.shared.dose_codec import FULL_BITS, SharedDose
from fleetlink.shared.map_codec import SharedMap
from fleetlink.shared.messages import DoseSnapshot, DoseUpdate
from fleetlink.shared.wire import WireError

__all__ = [
    "AT_TARGET",
    "BELOW",
    "NONE",
    "DoseFetcher",
    "DoseFollower",
    "DoseReport",
    "FleetDose",
    "dose_report",
    "merge_layers",
    "report_floor",
    "save_report",
]

log = logging.getLogger(__name__)

NONE, BELOW, AT_TARGET = 0, 1, 2
"""What the map shows for a point: no dose, some but under the target, at or over the target."""
FREE_AT = 25
"""Map cells at or below this occupancy are floor (map_saver's free_thresh, as the dose model's)."""
OCCUPIED_AT = 65


@dataclass(frozen=True, slots=True)
class FleetDose:
    """Every robot's layer summed (J/m², site frame), at one resolution."""

    grid: DoseGrid
    target_j_m2: float
    """The highest of the robots' targets (the strictest)."""
    robots: tuple[str, ...]
    left_out: tuple[str, ...]
    """Robots whose layers are at another resolution (not summed; say so)."""
    lamp_on_s: float
    unplaced_s: float
    mantissa_bits: int
    """The fewest mantissa bits any layer kept (23: float32 as the agents sent it)."""
    version: int

    def classes(self, xs: npt.NDArray[np.float64], ys: npt.NDArray[np.float64]) -> npt.NDArray[np.uint8]:
        """``NONE``/``BELOW``/``AT_TARGET`` at the points ``ys x xs`` (rows x columns)."""
        d = self.grid.dose_at(xs, ys)
        out = np.zeros(d.shape, dtype=np.uint8)
        out[d > 0.0] = BELOW
        out[d >= self.target_j_m2] = AT_TARGET
        return out


def merge_layers(layers: Mapping[str, SharedDose], version: int = 0) -> FleetDose | None:
    """The fleet's layer: the robots' layers summed (those at the most common resolution; ties:
    the finest); None without any."""
    if not layers:
        return None
    counts = Counter(d.resolution for d in layers.values())
    res = max(counts, key=lambda r: (counts[r], -r))
    robots = tuple(sorted(r for r, d in layers.items() if d.resolution == res))
    left_out = tuple(sorted(r for r, d in layers.items() if d.resolution != res))
    picked = [layers[r] for r in robots]
    return FleetDose(
        grid=DoseGrid.merged(d.grid() for d in picked),
        target_j_m2=max(d.target_j_m2 for d in picked),
        robots=robots,
        left_out=left_out,
        lamp_on_s=sum(d.lamp_on_s for d in picked),
        unplaced_s=sum(d.unplaced_s for d in picked),
        mantissa_bits=min(d.mantissa_bits for d in picked),
        version=version,
    )


class DoseFollower:
    """Which dose layers to fetch, the copies kept current, and the fleet layer. Not thread-safe
    (the caller locks)."""

    def __init__(self, fleet: FleetModel, *, retry_s: float = 2.0, absent_retry_s: float = 10.0) -> None:
        self.fleet = fleet
        self.retry_s = retry_s
        self.absent_retry_s = absent_retry_s
        """Robots never heard on ``dose/updates`` are asked this seldom (most have no lamp; a robot
        whose lamp was on before this console started still has a layer to give)."""
        self.layers: dict[str, SharedDose] = {}
        self.version = 0
        """+1 whenever a layer changes."""
        self.layer: FleetDose | None = None
        """The merged layer the map draws (``DoseFetcher`` keeps it current)."""
        self.rejected = 0
        self._stale: set[str] = set()
        """Robots heard publishing updates whose copy is missing or behind: fetch them."""
        self._restarted: set[str] = set()
        """Robots whose updates went back in version (their agent restarted, its layer from 0): the
        next snapshot replaces the copy although its version is lower."""
        self._asked: dict[str, float] = {}
        self.forgotten = 0
        """Times ``forget`` was called: a snapshot fetched or a merge made before it is dropped."""

    def forget(self) -> None:
        """No layers, as a fresh follower (a replay seeking back: operator/feed.py
        ``FleetFeed.forget``); ``version`` moves on (views key their caches on it)."""
        fresh = DoseFollower(self.fleet, retry_s=self.retry_s, absent_retry_s=self.absent_retry_s)
        fresh.version, fresh.forgotten = self.version + 1, self.forgotten + 1
        vars(self).update(vars(fresh))

    def on_update(self, msg: DoseUpdate) -> bool:
        """A patch from ``dose/updates``: applied (True), or the copy is marked for a fresh snapshot."""
        robot = msg.header.robot
        shared = self.layers.get(robot)
        if shared is None:
            self._stale.add(robot)
            return False
        try:
            applied = shared.apply(msg)
        except WireError as exc:
            self.rejected += 1
            log.debug("dose update from %s rejected: %s", robot, exc.reason)
            applied = False
        if not applied:
            if msg.version > shared.version:
                self._stale.add(robot)  # missed one, or the layer grew: fetch the whole layer
            elif msg.base_version < shared.version and msg.version < shared.version:
                self._stale.add(robot)  # the agent restarted: its layer starts again
                self._restarted.add(robot)
            return False
        self.version += 1
        return True

    def on_snapshot(self, robot: str, msg: DoseSnapshot) -> bool:
        try:
            shared = SharedDose.from_snapshot(msg)
        except WireError as exc:
            self.rejected += 1
            log.warning("dose snapshot from %s rejected: %s", robot, exc.reason)
            return False
        old = self.layers.get(robot)
        if old is not None and old.version > shared.version and robot not in self._restarted:
            return False
        self.layers[robot] = shared
        self._stale.discard(robot)
        self._restarted.discard(robot)
        self.version += 1
        return True

    def wanted(self, now: float) -> list[str]:
        """Robots to fetch now: stale copies every ``retry_s``, robots with no layer yet every
        ``absent_retry_s``."""
        out = []
        for robot in sorted(self._stale):
            if now - self._asked.get(robot, -math.inf) >= self.retry_s:
                out.append(robot)
        for robot in self.fleet.robots:
            absent = robot not in self.layers and robot not in self._stale
            if absent and now - self._asked.get(robot, -math.inf) >= self.absent_retry_s:
                out.append(robot)
        for robot in out:
            self._asked[robot] = now
        return out

    def copies(self) -> dict[str, SharedDose]:
        """The layers as they are now, to merge outside the lock (their cells copied)."""
        return {r: dataclasses.replace(d, cells=d.cells.copy()) for r, d in self.layers.items()}


class DoseFetcher(SnapshotFetcher[DoseSnapshot]):
    """A thread fetching the snapshots ``follower`` wants through ``fetch(robot)``, and merging the
    layers into ``follower.layer`` when they changed (at most every ``merge_s``). ``on_merged()``
    (optional) is called after a merge, outside the lock (the console redraws)."""

    def __init__(
        self,
        follower: DoseFollower,
        fetch: Callable[[str], DoseSnapshot | None],
        clock: Clock,
        lock: threading.Lock,
        *,
        period_s: float = 0.5,
        merge_s: float = 1.0,
        on_merged: Callable[[], object] | None = None,
    ) -> None:
        super().__init__("dose layer", follower, fetch, clock, lock, period_s=period_s)
        self.doses = follower
        self.merge_s = merge_s
        self.on_merged = on_merged
        self.merges = 0
        self._next_merge = -math.inf

    def after_poll(self) -> None:
        self.merge()

    def merge(self, *, force: bool = False) -> bool:
        """Sum the layers into ``follower.layer`` if they changed since the last merge (and
        ``merge_s`` has passed, unless ``force``). True if it merged."""
        now = self.clock.now()
        if not force and self._next_merge - self.merge_s <= now < self._next_merge:  # (a clock gone back: due)
            return False
        with self.lock:
            f = self.doses
            if not f.layers or (f.layer is not None and f.layer.version == f.version):
                return False
            version, copies, forgotten = f.version, f.copies(), f.forgotten
        self._next_merge = now + self.merge_s
        layer = merge_layers(copies, version)  # outside the lock: the UI never waits for the sum
        with self.lock:
            if f.forgotten != forgotten:  # the layers were forgotten meanwhile (a replay's seek back)
                return False
            if f.layer is None or f.layer.version < version:
                f.layer = layer
        self.merges += 1
        if self.on_merged is not None:
            self.on_merged()
        return True


# -- the report ----------------------------------------------------------------------------------


def report_floor(
    grid: DoseGrid, maps: Iterable[SharedMap], box: tuple[float, float, float, float] | None = None
) -> tuple[FloorMask, str]:
    """The floor a report counts, on the dose layer's lattice, and where it came from: the robots'
    maps merged (free in one, occupied in none) over their extent, or, without maps, the cells the
    lamps reached (any dose > 0); cut to ``box`` (x1, y1, x2, y2, any two corners) if given."""
    res = grid.resolution
    maps = list(maps)
    if maps:
        x0 = min(m.origin[0] for m in maps)
        y0 = min(m.origin[1] for m in maps)
        x1 = max(m.origin[0] + m.cells.shape[1] * m.resolution for m in maps)
        y1 = max(m.origin[1] + m.cells.shape[0] * m.resolution for m in maps)
        kx0, ky0 = math.floor(x0 / res + 0.5), math.floor(y0 / res + 0.5)
        kx1, ky1 = math.ceil(x1 / res - 0.5), math.ceil(y1 / res - 0.5)
        xs = np.arange(kx0, kx1 + 1, dtype=np.float64) * res
        ys = np.arange(ky0, ky1 + 1, dtype=np.float64) * res
        free = np.zeros((ys.size, xs.size), dtype=bool)
        occupied = np.zeros_like(free)
        for m in maps:
            free |= FloorMask.from_occupancy(m.cells, m.resolution, m.origin, free_max=FREE_AT).sample(xs, ys)
            occupied |= FloorMask(np.ascontiguousarray(m.cells >= OCCUPIED_AT), m.resolution, m.origin).sample(xs, ys)
        mask = FloorMask(free & ~occupied, res, ((kx0 - 0.5) * res, (ky0 - 0.5) * res))
        source = f"the robots' maps ({len(maps)})"
    else:
        mask = FloorMask(np.ascontiguousarray(grid.dose > 0.0), res, grid.origin)
        source = "the cells the lamps reached (no map)"
    if box is not None:
        bx0, bx1 = sorted((box[0], box[2]))
        by0, by1 = sorted((box[1], box[3]))
        xs, ys = mask.centres()
        inside = ((ys >= by0) & (ys <= by1))[:, None] & ((xs >= bx0) & (xs <= bx1))[None, :]
        mask = FloorMask(mask.free & inside, res, mask.origin)
        source += f", within x {bx0:g}..{bx1:g}, y {by0:g}..{by1:g}"
    return mask, source


@dataclass(frozen=True, slots=True)
class DoseReport:
    """A dose layer, the floor it is judged on and its summary: what the report files say."""

    layer: FleetDose
    mask: FloorMask
    floor_source: str
    summary: DoseSummary
    robots: tuple[dict[str, Any], ...] = field(default=())

    def text(self) -> str:
        lay = self.layer
        lines = [
            f"robots: {', '.join(lay.robots)}"
            + (f" (left out, other resolution: {', '.join(lay.left_out)})" if lay.left_out else ""),
            f"lamp on: {lay.lamp_on_s:.1f} s on the layer, {lay.unplaced_s:.1f} s not placed (not counted)",
            f"floor: {self.floor_source}, {lay.grid.resolution:g} m cells",
        ]
        if lay.mantissa_bits < FULL_BITS:
            lines.append(f"precision: doses rounded down to {lay.mantissa_bits} mantissa bits (a large layer)")
        return "\n".join(lines) + "\n" + self.summary.text()

    def json(self) -> dict[str, Any]:
        s, lay, m = self.summary, self.layer, self.mask
        return {
            "target_j_m2": s.target_j_m2,
            "target_mj_cm2": s.target_j_m2 / J_M2_PER_MJ_CM2,
            "floor_m2": s.floor_m2,
            "reached_m2": s.reached_m2,
            "below_m2": s.below_m2,
            "fraction": s.fraction,
            "min_dose_j_m2": s.min_dose_j_m2,
            "regions_total": s.regions_total,
            "regions": [{"area_m2": r.area_m2, "centroid": list(r.centroid), "box": list(r.box)} for r in s.regions],
            "floor": self.floor_source,
            "resolution_m": m.resolution,
            "origin": list(m.origin),
            "width": m.shape[1],
            "height": m.shape[0],
            "lamp_on_s": lay.lamp_on_s,
            "unplaced_s": lay.unplaced_s,
            "mantissa_bits": lay.mantissa_bits,
            "robots": list(self.robots),
            "left_out": list(lay.left_out),
        }


def dose_report(
    layers: Mapping[str, SharedDose],
    maps: Iterable[SharedMap] = (),
    box: tuple[float, float, float, float] | None = None,
    *,
    layer: FleetDose | None = None,
    target_j_m2: float | None = None,
) -> DoseReport:
    """The report on ``layers`` (merged here unless ``layer`` is given) over the floor of ``maps``,
    judged against the layers' target or ``target_j_m2``.

    ValueError with the reason when there is nothing to report (no layer, no floor)."""
    lay = layer if layer is not None else merge_layers(layers)
    if lay is None:
        raise ValueError("no dose layer yet: no robot has shared one")
    mask, source = report_floor(lay.grid, maps, box)
    if not mask.free.any():
        raise ValueError(f"no floor to judge the dose on ({source})")
    robots = tuple(
        {
            "robot": r,
            "version": d.version,
            "resolution_m": d.resolution,
            "target_j_m2": d.target_j_m2,
            "lamp_on_s": d.lamp_on_s,
            "unplaced_s": d.unplaced_s,
            "mantissa_bits": d.mantissa_bits,
        }
        for r, d in sorted(layers.items())
    )
    if target_j_m2 is not None:
        lay = dataclasses.replace(lay, target_j_m2=target_j_m2)
    return DoseReport(lay, mask, source, summarise(lay.grid, lay.target_j_m2, mask), robots)


REPORT_FILES: Sequence[str] = ("dose.pgm", "dose.png", "dose.csv", "summary.txt", "summary.json")


def save_report(report: DoseReport, out: Path) -> list[Path]:
    """Write the report into folder ``out`` (made if missing): the picture as PGM and PNG (north
    up, the dose as a fraction of the target on the floor), one CSV line per floor cell, and the
    summary as text and JSON. The paths written."""
    out.mkdir(parents=True, exist_ok=True)
    grid, target, mask = report.layer.grid, report.layer.target_j_m2, report.mask
    files = {
        "dose.pgm": pgm_report(grid, target, mask),
        "dose.png": png_report(grid, target, mask),
        "dose.csv": csv_report(grid, target, mask).encode("ascii"),
        "summary.txt": report.text().encode("utf-8"),
        "summary.json": (json.dumps(report.json(), indent=2) + "\n").encode("utf-8"),
    }
    paths = []
    for name in REPORT_FILES:
        path = out / name
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(files[name])
        tmp.replace(path)
        paths.append(path)
    return paths
