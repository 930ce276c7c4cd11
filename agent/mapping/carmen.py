"""CARMEN log reader (FLASER, ROBOTLASER1, RAWLASER1, ODOM, PARAM), and replay of a log into a map.

Line-oriented, whitespace-separated, ``#`` comments (CARMEN's ``carmen/src/global/readlog.c``):

    FLASER n r1 .. rn x y theta odom_x odom_y odom_theta ipc_timestamp ipc_hostname logger_timestamp
    ROBOTLASER1 laser_type start_angle fov angular_resolution max_range accuracy remission_mode
                n r1 .. rn m rem1 .. remm laser_x laser_y laser_theta robot_x robot_y robot_theta
                tv rv forward_safety_dist side_safety_dist turn_axis ipc_timestamp ipc_hostname logger_timestamp
    RAWLASER1 laser_type start_angle fov angular_resolution max_range accuracy remission_mode
              n r1 .. rn m rem1 .. remm ipc_timestamp ipc_hostname logger_timestamp
    ODOM x y theta tv rv accel ipc_timestamp ipc_hostname logger_timestamp
    PARAM name value [ipc_hostname logger_timestamp]

FLASER beams follow CARMEN's guesses for an under-specified SICK: start at -90 degrees, field of
view and spacing from ``carmen_laser_guess_fov`` / ``carmen_laser_guess_angle_increment`` (180
beams: 1 degree apart, -90 .. +89), maximum range 80 m. A FLASER line carries two poses, as CARMEN
writes them (``log2log``: ``laser_pose`` then ``robot_pose``): ``x y theta`` is the laser's, the robot
pose moved ``robot_frontlaser_offset`` (a PARAM line) ahead; ``odom_*`` is the robot's, its raw
odometry in a raw log. Radish's corrected logs carry the corrected pose in both (their offset is 0).
``LaserRecord.pose`` is the robot pose the first triple gives (the offset taken back off: the
logged, or corrected, pose); ``LaserRecord.odom`` the second, which replay seeds the matcher with.
``ipc_timestamp`` is kept as the text found in the log so it can be written back verbatim.

RAWLASER1 (the front laser's raw scan, as CARMEN's logger writes it beside the odometry) carries no
pose: its robot pose is the odometry at the scan's time, interpolated between the ODOM lines either
side (held at the first or last one beyond them; none in a log without odometry:
``LaserRecord.has_odometry``), and its mount
``robot_frontlaser_offset``. A logger that also wrote the scans as FLASER or ROBOTLASER1 lines wrote
each one twice: once such a line is seen, the RAWLASER1 lines are skipped (and counted).

``corrected_lines`` writes a log back with each laser line's poses replaced: a SLAM result as the
Freiburg ``metricEvaluator`` reads it, which takes the robot pose -- FLASER's second triple,
ROBOTLASER1's ``robot_*`` -- and the ``ipc_timestamp`` of every laser line (a RAWLASER1 line, which
has no pose to replace, is written as the ROBOTLASER1 line of the same scan).

Anything else (unknown message types such as NEFF, blank lines, comments) is skipped and counted;
malformed lines are skipped and counted by reason, and the first few are kept for a log message.
Pure: parses text; ``open_log`` is the one helper that opens a file (plain or .gz).
"""

from __future__ import annotations

import bisect
import contextlib
import gzip
import io
import math
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TextIO

import numpy as np
import numpy.typing as npt

from fleetlink.shared.se2 import compose, inverse

__all__ = [
    "CarmenStats",
    "LaserRecord",
    "OdomRecord",
    "corrected_lines",
    "guess_fov",
    "guess_increment",
    "open_log",
    "read_records",
]

Pose = tuple[float, float, float]
MAX_BEAMS = 100_000
RAW_BESIDE_POSED = "RAWLASER1 (the same scans as FLASER/ROBOTLASER1)"
ODOMETRY_KEPT = 4096
ODOMETRY_KEPT_S = 60.0
"""ODOM records kept to place RAWLASER1 scans by: the last minute (once there are this many)."""
UNKNOWN_KINDS_KEPT = 16
"""Kinds of line skipped counted by name, at most this many; the rest together as ``OTHER_KINDS``: a
file that is not a CARMEN log at all would otherwise name (and keep) every one of its lines."""
OTHER_KINDS = f"(kinds past the first {UNKNOWN_KINDS_KEPT})"
UNREADABLE = "unreadable (not a record name)"
SUMMARY_KINDS = 6
"""Kinds of line skipped the summary names, the most frequent first."""
NO_RETURN_BAND_M = 0.1
"""Readings this close under a log's maximum range are no return too (``LaserRecord.measured``)."""


@dataclass(frozen=True, slots=True)
class LaserRecord:
    kind: str  # FLASER, ROBOTLASER1 or RAWLASER1
    ranges: npt.NDArray[np.float64]
    angles: npt.NDArray[np.float64]  # rad, sensor frame
    max_range: float
    pose: Pose  # the logged robot pose (corrected, in corrected logs; FLASER: x y theta less the offset)
    odom: Pose  # raw odometry of the robot (FLASER: odom_*; corrected logs: the corrected pose again)
    laser_offset: Pose  # the laser on the robot (ROBOTLASER1: from laser vs robot pose)
    ipc_timestamp: str  # verbatim
    timestamp: float
    line: int
    # False: the log has no odometry for it (a RAWLASER1 line in a log without ODOM lines); ``odom``
    # and ``pose`` are then zero, and a replay matches the scan on its own.
    has_odometry: bool = True

    def measured(self) -> npt.NDArray[np.float64]:
        """The ranges with every "no return" as NaN: a reading at the maximum range (glass, an open
        door, nothing within reach), or less than ``NO_RETURN_BAND_M`` under it, which a SICK LMS
        2xx uses for its error codes (centimetre mode: 81.83 "over range" to 81.91 m, a ROBOTLASER1
        line's maximum 81.9 m). Such a reading says nothing reliable, so it neither marks nor clears."""
        return np.where(self.ranges >= self.max_range - NO_RETURN_BAND_M, np.nan, self.ranges)


@dataclass(frozen=True, slots=True)
class OdomRecord:
    pose: Pose
    tv: float
    rv: float
    ipc_timestamp: str
    timestamp: float
    line: int


@dataclass(slots=True)
class CarmenStats:
    lines: int = 0
    scans: int = 0
    odom: int = 0
    params: dict[str, str] = field(default_factory=dict)
    comments: int = 0
    blank: int = 0
    unknown: Counter[str] = field(default_factory=Counter)
    malformed: Counter[str] = field(default_factory=Counter)
    examples: list[str] = field(default_factory=list)  # the first few malformed lines, with reasons

    def skip(self, kind: str) -> None:
        """Count a line of a kind this reader does not map (``UNKNOWN_KINDS_KEPT`` names at most)."""
        kind = kind[:32]
        if not (kind.isascii() and kind.isprintable() and kind[:1].isalpha()):
            kind = UNREADABLE
        elif kind not in self.unknown and len(self.unknown) >= UNKNOWN_KINDS_KEPT:
            kind = OTHER_KINDS
        self.unknown[kind] += 1

    def summary(self) -> str:
        parts = [f"{self.lines} lines", f"{self.scans} scans", f"{self.odom} odometry"]
        if self.unknown:
            ranked = sorted(self.unknown.items(), key=lambda kv: (-kv[1], kv[0]))
            named = [f"{n} {k}" for k, n in ranked[:SUMMARY_KINDS]]
            if len(ranked) > SUMMARY_KINDS:
                rest = ranked[SUMMARY_KINDS:]
                named.append(f"{sum(n for _, n in rest)} more of {len(rest)} other kinds")
            parts.append("skipped " + ", ".join(named))
        if self.malformed:
            parts.append("malformed " + ", ".join(f"{n} ({k})" for k, n in sorted(self.malformed.items())))
        return "; ".join(parts)


def guess_fov(n: int) -> float:
    """carmen_laser_guess_fov."""
    return {
        181: math.pi,
        180: math.pi / 180.0 * 179.0,
        361: math.pi,
        360: math.pi / 180.0 * 179.5,
        401: math.pi / 180.0 * 100.0,
        400: math.pi / 100.0 * 99.75,
    }.get(n, math.pi)


def guess_increment(n: int) -> float:
    """carmen_laser_guess_angle_increment."""
    if n in (180, 181):
        return math.pi / 180.0
    if n in (360, 361):
        return math.pi / 360.0
    if n in (400, 401):
        return math.pi / 720.0
    return guess_fov(n) / max(1, n - 1)


class _Bad(Exception):
    pass


def _num(tok: str, what: str) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise _Bad(f"{what}: not a number") from None
    if not math.isfinite(v):
        raise _Bad(f"{what}: not finite")
    return v


def _count(tok: str, what: str) -> int:
    try:
        n = int(tok)
    except ValueError:
        raise _Bad(f"{what}: not a whole number") from None
    if not 0 <= n <= MAX_BEAMS:
        raise _Bad(f"{what}: {n} out of range")
    return n


def _ranges(toks: list[str], at: int, n: int) -> npt.NDArray[np.float64]:
    try:
        r = np.array(toks[at : at + n], dtype=np.float64)
    except ValueError:
        raise _Bad("ranges: not numbers") from None
    return r  # NaN/inf ranges are dropped later as invalid returns


def _pose(toks: list[str], at: int, what: str) -> Pose:
    return (_num(toks[at], what + " x"), _num(toks[at + 1], what + " y"), _num(toks[at + 2], what + " theta"))


def _flaser(toks: list[str], line: int, offset: Pose) -> LaserRecord:
    if len(toks) < 2:
        raise _Bad("FLASER: missing beam count")
    n = _count(toks[1], "FLASER beam count")
    if len(toks) < 2 + n + 7:
        raise _Bad("FLASER: too few fields")
    ranges = _ranges(toks, 2, n)
    k = 2 + n
    robot = compose(_pose(toks, k, "pose"), inverse(offset))  # x y theta is the laser's pose
    odom = _pose(toks, k + 3, "odometry")
    ts_text = toks[k + 6]
    ts = _num(ts_text, "ipc_timestamp")
    angles = -math.pi / 2.0 + guess_increment(n) * np.arange(n, dtype=np.float64)
    return LaserRecord("FLASER", ranges, angles, 80.0, robot, odom, offset, ts_text, ts, line)


def _robotlaser(toks: list[str], line: int) -> LaserRecord:
    ranges, angles, max_range, k = _laser_head(toks, "ROBOTLASER1")
    if len(toks) < k + 12:
        raise _Bad("ROBOTLASER1: too few fields")
    laser = _pose(toks, k, "laser pose")
    robot = _pose(toks, k + 3, "robot pose")
    ts_text = toks[k + 11]
    ts = _num(ts_text, "ipc_timestamp")
    c, s = math.cos(robot[2]), math.sin(robot[2])
    dx, dy = laser[0] - robot[0], laser[1] - robot[1]
    offset = (c * dx + s * dy, -s * dx + c * dy, (laser[2] - robot[2] + math.pi) % (2 * math.pi) - math.pi)
    return LaserRecord("ROBOTLASER1", ranges, angles, max_range, robot, robot, offset, ts_text, ts, line)


def _laser_head(toks: list[str], kind: str) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], float, int]:
    """The laser fields ROBOTLASER1 and RAWLASER1 share: ranges, beam angles, maximum range, and the
    index of the first field after the remissions."""
    if len(toks) < 9:
        raise _Bad(f"{kind}: too few fields")
    start = _num(toks[2], "start_angle")
    res = _num(toks[4], "angular_resolution")
    max_range = _num(toks[5], "maximum_range")
    n = _count(toks[8], f"{kind} beam count")
    k = 9 + n
    if len(toks) < k + 1:
        raise _Bad(f"{kind}: too few fields")
    ranges = _ranges(toks, 9, n)
    m = _count(toks[k], "remission count")
    return ranges, start + res * np.arange(n, dtype=np.float64), max_range, k + 1 + m


def _rawlaser(toks: list[str], line: int, offset: Pose) -> LaserRecord:
    """A RAWLASER1 line, its pose not yet known (the odometry's at its time: ``read_records``)."""
    ranges, angles, max_range, k = _laser_head(toks, "RAWLASER1")
    if len(toks) < k + 3:
        raise _Bad("RAWLASER1: too few fields")
    ts_text = toks[k]
    ts = _num(ts_text, "ipc_timestamp")
    zero = (0.0, 0.0, 0.0)
    return LaserRecord("RAWLASER1", ranges, angles, max_range, zero, zero, offset, ts_text, ts, line)


def _odometry_at(before: OdomRecord | None, after: OdomRecord | None, t: float) -> Pose:
    """The odometry at time ``t`` between two ODOM records (either may be missing: held at the other)."""
    if before is None or after is None:
        known = before or after
        return known.pose if known is not None else (0.0, 0.0, 0.0)
    span = after.timestamp - before.timestamp
    u = 0.0 if span <= 0.0 else min(1.0, max(0.0, (t - before.timestamp) / span))
    (x0, y0, t0), (x1, y1, t1) = before.pose, after.pose
    turn = math.remainder(t1 - t0, 2.0 * math.pi)
    return (x0 + u * (x1 - x0), y0 + u * (y1 - y0), math.remainder(t0 + u * turn, 2.0 * math.pi))


def _odom(toks: list[str], line: int) -> OdomRecord:
    if len(toks) < 8:
        raise _Bad("ODOM: too few fields")
    pose = _pose(toks, 1, "pose")
    return OdomRecord(pose, _num(toks[4], "tv"), _num(toks[5], "rv"), toks[7], _num(toks[7], "ipc_timestamp"), line)


def _front_offset(toks: list[str], current: Pose) -> Pose:
    """The front laser's mount after a PARAM line (``toks``: name, value, ...): its value if it is
    ``robot_frontlaser_offset`` (metres ahead of the robot), else ``current``."""
    if toks[1] != "robot_frontlaser_offset":
        return current
    return (_num(toks[2], "robot_frontlaser_offset"), 0.0, 0.0)


def read_records(lines: Iterable[str], stats: CarmenStats | None = None) -> Iterator[LaserRecord | OdomRecord]:
    """Laser and odometry records from log lines; everything else is counted in ``stats``."""
    st = stats if stats is not None else CarmenStats()
    front_offset: Pose = (0.0, 0.0, 0.0)
    # RAWLASER1 scans wait, in time order, for an ODOM line at or after their time; each is then
    # placed between the ODOM lines either side of it by time (a log's lines can go back in time,
    # so the odometry of the last minute is kept in time order). ``posed``: the log writes its scans
    # with poses (FLASER, ROBOTLASER1) too; ``raw_times``: raw scans given out before that was known.
    waiting: list[LaserRecord] = []
    odometry: list[OdomRecord] = []
    posed = False
    raw_times: set[float] = set()

    def placed(upto: float | None) -> Iterator[LaserRecord]:
        n = len(waiting) if upto is None else bisect.bisect_right(waiting, upto, key=_time_of)
        ready = waiting[:n]
        del waiting[:n]
        for rec in ready:
            i = bisect.bisect_left(odometry, rec.timestamp, key=_time_of)
            before = odometry[i - 1] if i > 0 else None
            after = odometry[i] if i < len(odometry) else None
            pose = _odometry_at(before, after, rec.timestamp)
            st.scans += 1
            raw_times.add(round(rec.timestamp, 6))
            yield replace(rec, pose=pose, odom=pose, has_odometry=bool(odometry))

    for number, raw in enumerate(lines, start=1):
        st.lines += 1
        text = raw.strip()
        if not text:
            st.blank += 1
            continue
        if text.startswith("#"):
            st.comments += 1
            continue
        toks = text.split()
        kind = toks[0]
        try:
            if kind == "FLASER":
                rec: LaserRecord | OdomRecord = _flaser(toks, number, front_offset)
            elif kind == "ROBOTLASER1":
                rec = _robotlaser(toks, number)
            elif kind == "RAWLASER1":
                if posed:
                    st.unknown[RAW_BESIDE_POSED] += 1
                else:
                    bisect.insort(waiting, _rawlaser(toks, number, front_offset), key=_time_of)
                continue
            elif kind == "ODOM":
                rec = _odom(toks, number)
                st.odom += 1
                bisect.insort(odometry, rec, key=_time_of)
                if len(odometry) > ODOMETRY_KEPT and odometry[0].timestamp < odometry[-1].timestamp - ODOMETRY_KEPT_S:
                    del odometry[: bisect.bisect_left(odometry, odometry[-1].timestamp - ODOMETRY_KEPT_S, key=_time_of)]
                yield from placed(rec.timestamp)
            elif kind == "PARAM":
                if len(toks) < 3:
                    raise _Bad("PARAM: too few fields")
                st.params[toks[1]] = toks[2]
                front_offset = _front_offset(toks, front_offset)
                continue
            else:
                st.skip(kind)
                continue
        except _Bad as exc:
            reason = str(exc)
            st.malformed[reason] += 1
            if len(st.examples) < 5:
                st.examples.append(f"line {number}: {reason}")
            continue
        if isinstance(rec, LaserRecord):
            if not posed:
                posed = True  # the same scans again, with poses: the raw ones are not mapped twice
                if waiting:
                    st.unknown[RAW_BESIDE_POSED] += len(waiting)
                    waiting.clear()
            if round(rec.timestamp, 6) in raw_times:
                # Its RAWLASER1 line was given out already (the ODOM line after it came first).
                st.unknown[f"{kind} (the same scan as a RAWLASER1 line before it)"] += 1
                continue
            st.scans += 1
        yield rec
    yield from placed(None)


def _time_of(rec: LaserRecord | OdomRecord) -> float:
    return rec.timestamp


def _fmt(pose: Pose) -> list[str]:
    return [f"{pose[0]:.6f}", f"{pose[1]:.6f}", f"{pose[2]:.6f}"]


def corrected_lines(lines: Iterable[str], poses: Mapping[int, Pose]) -> Iterator[str]:
    """The log's lines with the robot pose of each laser line numbered in ``poses`` (1-based, as
    ``LaserRecord.line``) written in: FLASER's both triples -- ``odom_*`` the robot pose (where
    ``metricEvaluator`` reads it), ``x y theta`` the laser's (the pose moved the PARAM
    ``robot_frontlaser_offset`` ahead), as a corrected log has them -- and ROBOTLASER1's robot pose
    and its laser pose (the robot pose composed with the line's own laser offset). Every other line,
    and every other field, is passed through verbatim, so ODOM, PARAM and the timestamps are the
    input's. A numbered line that is not a well-formed laser line raises ValueError (the numbers
    must come from ``read_records`` on the same text)."""
    front_offset: Pose = (0.0, 0.0, 0.0)
    for number, raw in enumerate(lines, start=1):
        pose = poses.get(number)
        if pose is None:
            toks = raw.split(None, 3)
            if len(toks) >= 3 and toks[0] == "PARAM":
                with contextlib.suppress(_Bad):  # read_records counted it; the offset stays
                    front_offset = _front_offset(toks, front_offset)
            yield raw
            continue
        end = raw[len(raw.rstrip("\r\n")) :]
        toks = raw.split()
        try:
            if toks and toks[0] == "FLASER":
                k = 2 + _flaser(toks, number, front_offset).ranges.size
                toks[k : k + 6] = _fmt(compose(pose, front_offset)) + _fmt(pose)
            elif toks and toks[0] == "ROBOTLASER1":
                rec = _robotlaser(toks, number)
                k = _laser_head(toks, "ROBOTLASER1")[3]
                toks[k : k + 6] = _fmt(compose(pose, rec.laser_offset)) + _fmt(pose)
            elif toks and toks[0] == "RAWLASER1":
                # No pose to replace: the same scan as a ROBOTLASER1 line, laser and robot pose
                # written in (velocities, safety distances and turn axis unknown: 0).
                _, _, _, k = _laser_head(toks, "RAWLASER1")
                laser = compose(pose, front_offset)
                toks = ["ROBOTLASER1", *toks[1:k], *_fmt(laser), *_fmt(pose), "0", "0", "0", "0", "0", *toks[k:]]
            else:
                raise _Bad(f"not a laser line ({toks[0] if toks else 'blank'})")
        except _Bad as exc:
            raise ValueError(f"line {number}: {exc}") from None
        yield " ".join(toks) + end


def open_log(path: str | Path) -> TextIO:
    """A text stream over a log file, gunzipping ``.gz`` (by magic bytes, whatever the name)."""
    p = Path(path)
    with p.open("rb") as f:
        magic = f.read(2)
    if magic == b"\x1f\x8b":
        return io.TextIOWrapper(gzip.open(p, "rb"), encoding="utf-8", errors="replace")
    return p.open("r", encoding="utf-8", errors="replace")
