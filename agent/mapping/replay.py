"""Replay a CARMEN log through the onboard mapper (the offline path of ``fleetlink map replay``).

Each laser record's raw odometry seeds the matcher (``OnboardMapper.add_scan_odometry``; a log
without odometry: the last pose, with the matcher's own prior); the
trajectory keeps the record's ``ipc_timestamp`` text verbatim. With loop closure (the default) the
trajectory and the map are the final pose graph's: every scan where the last solve put it.
Pure: records in, mapper and rows out.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace

from fleetlink.agent.mapping.carmen import LaserRecord, OdomRecord
from fleetlink.agent.mapping.mapper import MapperConfig, OnboardMapper, Pose

__all__ = ["ReplayResult", "format_trajectory", "replay"]

REPLAY_MAX_RANGE = 40.0  # m: a longer reading (short of the log's maximum, "no return") only clears space up to here


@dataclass(slots=True)
class ReplayResult:
    mapper: OnboardMapper
    rows: list[tuple[str, Pose]] = field(default_factory=list)  # (ipc_timestamp text, robot pose)
    logged: list[Pose] = field(default_factory=list)  # the log's own pose per scan (corrected logs: reference)
    lines: list[int] = field(default_factory=list)  # each row's line in the log (``carmen.corrected_lines``)
    online: list[tuple[str, Pose]] = field(default_factory=list)  # each scan's pose when it was mapped
    # Each scan where the last online solve put it, before the final pass (``OnboardMapper.finish``).
    before_final: list[tuple[str, Pose]] = field(default_factory=list)


def replay(
    records: Iterable[LaserRecord | OdomRecord],
    config: MapperConfig | None = None,
    max_range: float = REPLAY_MAX_RANGE,
    progress: Callable[[str, int], None] | None = None,
) -> ReplayResult:
    """Map every laser record in order. The mapper is made at the first scan (its mount and range).
    ``progress`` hears ("scans", n) after each scan mapped and ("final", nodes) before the final pass
    (a long log takes minutes: the caller says how far it has got)."""
    result: ReplayResult | None = None
    for rec in records:
        if not isinstance(rec, LaserRecord):
            continue
        if result is None:
            base = config or MapperConfig()
            cfg = replace(base, mount=rec.laser_offset, max_range=min(max_range, rec.max_range, base.max_range * 10))
            result = ReplayResult(OnboardMapper(cfg))
        # "No return" neither marks nor clears: clearing along it fans free space far outside the
        # building on real logs, and a SICK's error codes would erase the walls they were dazzled by.
        ranges = rec.measured()
        if rec.has_odometry:
            res = result.mapper.add_scan_odometry(rec.timestamp, ranges, rec.angles, rec.odom)
        else:
            # No odometry: from the last pose with the matcher's own prior, not a zero step held to
            # a centimetre. (The last pose is in the frame the map is in now, after any solve.)
            guess = result.rows[-1][1] if result.rows else (0.0, 0.0, 0.0)
            res = result.mapper.add_scan(rec.timestamp, ranges, rec.angles, guess)
        result.rows.append((rec.ipc_timestamp, res.pose))
        result.logged.append(rec.pose)
        result.lines.append(rec.line)
        if progress is not None:
            progress("scans", len(result.rows))
    if result is None:
        return ReplayResult(OnboardMapper(config))
    # With loop closure the past moves after each solve: the trajectory and the map written are the
    # final graph's (each scan's online pose is kept in ``online``), after the final pass (every node
    # matched against the submaps it sees, the graph solved again: ``LoopCloser.finish``).
    result.online = list(result.rows)
    result.before_final = [
        (ts, p) for (ts, _), (_, p) in zip(result.online, result.mapper.corrected_trajectory(), strict=True)
    ]
    if progress is not None and result.mapper.closer is not None:
        progress("final", len(result.mapper.closer))
    result.mapper.finish()
    final = result.mapper.corrected_trajectory()
    result.rows = [(ts, p) for (ts, _), (_, p) in zip(result.online, final, strict=True)]
    result.mapper.redraw()
    return result


def format_trajectory(rows: Iterable[tuple[str, Pose]]) -> str:
    """``timestamp x y theta`` per line; the timestamp is the log's text, untouched."""
    return "".join(f"{ts} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}\n" for ts, p in rows)
