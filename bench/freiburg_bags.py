"""The Freiburg benchmark's raw logs put together again from ROS bags, for ``bench/mapping.py --freiburg``.

    python bench/freiburg_bags.py BAG... --out DIR

The relation files of Kuemmerle et al. (2009) score the raw CARMEN logs, which are not always found
beside them. INESCTEC/ricoslam (``inesctec_mrdt_slam_2d_datasets``) keeps the relation files and each
raw log as ROS 1 bags converted from it: ``NAME.orig.bag`` holds the log's messages in the log's line
order, each header stamped with its line's ``ipc_timestamp``. This reads such a bag record by record
in the file's order (the bag format 2.0, its bz2 or uncompressed chunks, and the three message types
it needs, by hand: the standard library and numpy only) and writes ``DIR/NAME.clf``:

- an ODOM line for every ``/odom`` message;
- a laser line for every ``/scan`` message, posed at the last ``/odom`` before it in the file: intel,
  aces and fr079 keep only the log's ODOM lines (interpolated to the scan's time instead, intel scores
  0.017 m, not the 0.013 m of docs/mapping.md; an ODOM line stamped as a scan but written after it is
  not its pose either: aces' figure moves), and where the converter kept each scan's own odometry
  (``save_odom``: the hospital) it comes just before its scan;
- FLASER lines (beams from -90 degrees as far apart as CARMEN guesses from their count, or the bag is
  refused; no mount: fr079's bag has one, 0.04 m, which the published relations do not fit,
  docs/mapping.md), or
  ROBOTLASER1 lines for a bag named ``*_robotlaser*`` (the Freiburg hospital, whose SICK interleaves
  four start angles and sits 0.22 m ahead of the robot: each scan's own angles, and the
  ``/tf_static`` base-to-laser transform as the laser pose).

NAME is the bag's name less ``.orig.bag``. A time-sorted conversion (``*.sort.bag``) is refused: a
scan and the odometry stamped with it come in either order there.

MIT's Killian Court log is kept only as ``mit-killian.clf2bag.bag`` (its ``.orig.bag`` is not in the
repository). That converter writes each scan with its own odometry (the FLASER line's pose) but stamps
the messages 0.1 s apart from 1e9 s, not with the log's times, which the relations name. A
``NAME.clf2bag.bag`` is read with ``NAME.relations`` beside it (or in ``--out``), and the log's times
are recovered from it where the log's scans came at one fixed period (``recover_times``): the
relations' stamps, sorted, then lie on that period's grid (Killian: 0.44 s, every gap within 0.27
period of a whole number of them), which gives each stamp's scan up to one offset; the offset is the
one at which the relations that turn (under 5 s apart, 8.6 degrees or more) agree best in heading with
the odometry (Killian: 0.026 rad on 498 such relations at the best offset, 0.033 and 0.070 one scan
either side; the best in nine tenths of the log taken apart). Every other scan is timed between them.

Then copy ``NAME.relations`` into DIR (``fr-clinic.relations`` finds ``fr-clinic_robotlaser.clf``) and
run ``python bench/mapping.py --freiburg DIR``. Put together so (2026-12-05), the logs reproduce the
figures of docs/mapping.md ("Against the published relations") to the digit.
"""

from __future__ import annotations

import argparse
import bz2
import math
import struct
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fleetlink.agent.mapping.carmen import guess_increment
from fleetlink.agent.mapping.relations import Relation, parse_relations

MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_CHUNK, OP_CONNECTION = 0x02, 0x05, 0x07


class BagError(ValueError):
    pass


@dataclass(frozen=True, slots=True)
class Stamp:
    sec: int
    nsec: int

    def text(self) -> str:
        """Seconds to the microsecond, as CARMEN writes an ``ipc_timestamp``."""
        us = (self.nsec + 500) // 1000
        return f"{self.sec + us // 1_000_000}.{us % 1_000_000:06d}"


@dataclass(frozen=True, slots=True)
class Scan:
    stamp: Stamp
    angle_min: float
    angle_max: float
    angle_increment: float
    range_max: float
    ranges: np.ndarray


@dataclass(frozen=True, slots=True)
class Odom:
    stamp: Stamp
    pose: tuple[float, float, float]
    tv: float = 0.0  # m/s, the twist's linear x
    rv: float = 0.0  # rad/s, its angular z


def _fields(header: bytes) -> dict[bytes, bytes]:
    out: dict[bytes, bytes] = {}
    i = 0
    while i < len(header):
        (n,) = struct.unpack_from("<I", header, i)
        name, sep, value = header[i + 4 : i + 4 + n].partition(b"=")
        if not sep:
            raise BagError("a record header field without '='")
        out[name] = value
        i += 4 + n
    return out


def _records(buf: bytes, at: int = 0) -> Iterator[tuple[dict[bytes, bytes], bytes]]:
    while at < len(buf):
        if at + 4 > len(buf):
            raise BagError("a record cut short")
        (hl,) = struct.unpack_from("<I", buf, at)
        header = _fields(buf[at + 4 : at + 4 + hl])
        at += 4 + hl
        if at + 4 > len(buf):
            raise BagError("a record cut short")
        (dl,) = struct.unpack_from("<I", buf, at)
        if at + 4 + dl > len(buf):
            raise BagError("a record's data cut short")
        yield header, buf[at + 4 : at + 4 + dl]
        at += 4 + dl


def messages(data: bytes) -> Iterator[tuple[str, bytes]]:
    """(topic, serialized message) for every message of a bag, in the order the file holds them."""
    if not data.startswith(MAGIC):
        raise BagError("not a ROS bag, version 2.0")
    topics: dict[int, str] = {}

    def walk(buf: bytes) -> Iterator[tuple[str, bytes]]:
        for header, body in _records(buf):
            op = header.get(b"op", b"\0")[0]
            if op == OP_CONNECTION:
                topics[struct.unpack("<I", header[b"conn"])[0]] = header[b"topic"].decode()
            elif op == OP_MESSAGE:
                yield topics[struct.unpack("<I", header[b"conn"])[0]], body
            elif op == OP_CHUNK:
                kind = header[b"compression"]
                if kind == b"bz2":
                    body = bz2.decompress(body)
                elif kind != b"none":
                    raise BagError(f"chunks compressed with {kind.decode()!r}: only bz2 and none are read")
                yield from walk(body)

    yield from walk(data[len(MAGIC) :])


class _Reader:
    """ROS 1 serialization, read field by field."""

    def __init__(self, buf: bytes) -> None:
        self.buf, self.at = buf, 0

    def take(self, fmt: str) -> tuple[float | int, ...]:
        out = struct.unpack_from(fmt, self.buf, self.at)
        self.at += struct.calcsize(fmt)
        return out

    def string(self) -> str:
        (n,) = self.take("<I")
        s = self.buf[self.at : self.at + int(n)].decode()
        self.at += int(n)
        return s

    def stamp(self) -> Stamp:
        """A std_msgs/Header: its stamp (the sequence number and frame skipped)."""
        _seq, sec, nsec = self.take("<3I")
        self.string()
        return Stamp(int(sec), int(nsec))


def laser_scan(buf: bytes) -> Scan:
    r = _Reader(buf)
    stamp = r.stamp()
    angle_min, angle_max, increment, _dt, _scan_time, _range_min, range_max = r.take("<7f")
    (n,) = r.take("<I")
    if r.at + 4 * int(n) > len(buf):
        raise BagError(f"a LaserScan of {n} ranges cut short")
    ranges = np.frombuffer(buf, dtype="<f4", count=int(n), offset=r.at)
    return Scan(stamp, float(angle_min), float(angle_max), float(increment), float(range_max), ranges)


def _yaw(qx: float, qy: float, qz: float, qw: float) -> float:
    return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def odometry(buf: bytes) -> Odom:
    r = _Reader(buf)
    stamp = r.stamp()
    r.string()  # child_frame_id
    x, y, _z, qx, qy, qz, qw = (float(v) for v in r.take("<7d"))
    r.take("<36d")  # the pose's covariance
    tv, _vy, _vz, _wx, _wy, rv = (float(v) for v in r.take("<6d"))
    return Odom(stamp, (x, y, _yaw(qx, qy, qz, qw)), tv, rv)


def laser_mount(buf: bytes) -> tuple[float, float, float] | None:
    """The first transform of a tf2_msgs/TFMessage (the converter's one static base-to-laser one)."""
    r = _Reader(buf)
    (n,) = r.take("<I")
    if not n:
        return None
    r.stamp()
    r.string()  # child_frame_id
    x, y, _z, qx, qy, qz, qw = (float(v) for v in r.take("<7d"))
    return x, y, _yaw(qx, qy, qz, qw)


def _ranges(scan: Scan) -> str:
    # Each float32 as the shortest text that reads back to it (the logs' "46.56", not 46.560001373...).
    return " ".join(np.format_float_positional(v, unique=True, trim="-") for v in scan.ranges)


def _pose(p: tuple[float, float, float]) -> str:
    return f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f}"


def _flaser(scan: Scan, pose: tuple[float, float, float], t: str) -> str:
    """A FLASER line of ``scan`` at the robot's ``pose``, stamped ``t``. It has no angles: a reader takes
    its beams from -90 degrees, as far apart as CARMEN guesses from their count, and no mount (fr079's
    bag has one, 0.04 m: docs/mapping.md); a scan that is not so is refused."""
    n = len(scan.ranges)
    guess = guess_increment(n)
    if abs(scan.angle_min + math.pi / 2) > 1e-4 or abs(scan.angle_increment - guess) > 0.01 * guess:
        raise BagError(
            f"a scan of {n} beams from {math.degrees(scan.angle_min):.2f} degrees,"
            f" {math.degrees(scan.angle_increment):.3f} apart, is no FLASER line (a reader would take"
            f" {math.degrees(guess):.3f} from -90): name the bag *_robotlaser*"
        )
    return f"FLASER {n} {_ranges(scan)} {_pose(pose)} {_pose(pose)} {t} bag {t}"


def log_lines(data: bytes, robotlaser: bool) -> Iterator[str]:
    """A bag's CARMEN lines (see the module's docstring)."""
    mount = (0.0, 0.0, 0.0)
    last: Odom | None = None
    pending: list[Scan] = []  # scans before any odometry: placed at the first

    def line(scan: Scan, odom: Odom) -> str:
        t = scan.stamp.text()
        if not robotlaser:
            return _flaser(scan, odom.pose, t)
        x, y, th = odom.pose
        c, s = math.cos(th), math.sin(th)
        laser = (x + c * mount[0] - s * mount[1], y + s * mount[0] + c * mount[1], th + mount[2])
        fov = scan.angle_max - scan.angle_min
        return (
            f"ROBOTLASER1 0 {scan.angle_min:.6f} {fov:.6f} {scan.angle_increment:.6f} {scan.range_max:.2f} 0.01 0"
            f" {len(scan.ranges)} {_ranges(scan)} 0 {_pose(laser)} {_pose(odom.pose)} 0 0 0 0 0 {t} bag {t}"
        )

    items = list(messages(data))
    for topic, body in items:  # the laser's mount first: the converter writes it once, anywhere
        if topic == "/tf_static":
            mount = laser_mount(body) or mount
    for topic, body in items:
        if topic == "/odom":
            last = odometry(body)
            t = last.stamp.text()
            yield f"ODOM {_pose(last.pose)} {last.tv:.6f} {last.rv:.6f} 0 {t} bag {t}"
            for scan in pending:
                yield line(scan, last)
            pending.clear()
        elif topic == "/scan":
            scan = laser_scan(body)
            if last is None:
                pending.append(scan)
            else:
                yield line(scan, last)
    if pending:
        raise BagError(f"{len(pending)} scans and no /odom to place them by")


def clf2bag_records(data: bytes) -> tuple[list[Scan], list[tuple[float, float, float]]]:
    """A clf2bag bag's scans, each with the odometry written with it (the /odom stamped as the scan)."""
    scans: list[Scan] = []
    odom: dict[Stamp, Odom] = {}
    for topic, body in messages(data):
        if topic == "/scan":
            scans.append(laser_scan(body))
        elif topic == "/odom":
            o = odometry(body)
            odom[o.stamp] = o
    missing = sum(s.stamp not in odom for s in scans)
    if missing:
        raise BagError(f"{missing} of {len(scans)} scans without the /odom stamped as they are")
    return scans, [odom[s.stamp].pose for s in scans]


PERIOD_SLACK = 0.35  # of a period: how far a gap between two relation stamps may lie from the grid (Killian: 0.27)
TURN_RAD = 0.15  # a relation that turns at least this much tells an offset of one scan from the next
TURNS_NEEDED = 20


def recover_times(
    odom: list[tuple[float, float, float]], relations: list[Relation]
) -> tuple[np.ndarray, float, int, list[float]]:
    """The log's time of each scan, from the relations (see the module's docstring): the times, the
    period, the first relation stamp's scan, and each offset's mean heading error (rad) at that period.
    The shortest gap between two stamps is the period or a whole number of them (relations that name
    every second scan): each of those periods whose grid fits in the bag is tried, and the period and
    offset where the turning relations agree best with the odometry kept."""
    stamps = np.array(sorted({r.t1 for r in relations} | {r.t2 for r in relations}))
    if len(stamps) < 2:
        raise BagError("the relations name fewer than two stamps")
    gaps = np.diff(stamps)
    base = float(gaps.min())
    if base <= 0:
        raise BagError("two relation stamps are the same")
    period = float(np.median(gaps / np.maximum(np.round(gaps / base), 1.0)))
    off_grid = float(np.max(np.abs(gaps / period - np.round(gaps / period))))
    if off_grid > PERIOD_SLACK:
        raise BagError(
            f"the relation stamps do not lie on one period's grid (a gap {off_grid:.2f} of {period:.3f} s off it):"
            " the log's times cannot be recovered"
        )
    n = len(odom)
    at = {float(t): k for k, t in enumerate(stamps)}
    turns = [r for r in relations if abs(r.t2 - r.t1) < 5.0 and abs(r.dtheta) >= TURN_RAD]
    if len(turns) < TURNS_NEEDED:
        raise BagError(
            f"{len(turns)} relations turn {math.degrees(TURN_RAD):.1f} degrees or more: too few to place them"
        )
    heading = np.array([p[2] for p in odom])
    yaw = np.array([r.dtheta for r in turns])
    best: tuple[float, float, np.ndarray, int, list[float]] | None = None
    for share in range(1, 5):
        index = np.concatenate(([0], np.cumsum(np.round(gaps / period) * share))).astype(np.int64)
        if index[-1] >= n:
            break
        if float(np.max(np.abs(gaps * share / period - np.diff(index)))) > PERIOD_SLACK:
            continue  # a finer grid some gap is off
        i = np.array([index[at[r.t1]] for r in turns])
        j = np.array([index[at[r.t2]] for r in turns])
        errors = []
        for offset in range(n - int(index[-1])):
            d = heading[j + offset] - heading[i + offset] - yaw
            errors.append(float(np.mean(np.abs(np.remainder(d + math.pi, 2.0 * math.pi) - math.pi))))
        first = int(np.argmin(errors))
        if best is None or errors[first] < best[0]:
            best = (errors[first], period / share, index + first, first, errors)
    if best is None:
        raise BagError(
            f"the relations span more scans at {period:.3f} s a scan than the bag's {n}: the log's times cannot be recovered"
        )
    _, step, known, first, errors = best
    times = np.interp(np.arange(n, dtype=float), known.astype(float), stamps)
    times[: known[0]] = stamps[0] - step * (known[0] - np.arange(known[0]))
    times[known[-1] + 1 :] = stamps[-1] + step * (np.arange(known[-1] + 1, n) - known[-1])
    times[known] = stamps
    return times, step, first, errors


def clf2bag_lines(data: bytes, relations_text: str) -> tuple[list[str], str]:
    """A clf2bag bag's CARMEN lines (an ODOM and a FLASER line per scan), timed by ``recover_times``;
    and a line saying how the times were found."""
    scans, odom = clf2bag_records(data)
    if not scans:
        raise BagError("no /scan messages")
    times, period, first, errors = recover_times(odom, parse_relations(relations_text.splitlines()))
    lines = []
    for scan, pose, t in zip(scans, odom, times, strict=True):
        stamp = f"{t:.6f}"
        lines.append(f"ODOM {_pose(pose)} 0 0 0 {stamp} bag {stamp}")
        lines.append(_flaser(scan, pose, stamp))
    nearby = sorted(errors[max(0, first - 1) : first + 2])
    note = (
        f"times recovered on a {period:.3f} s grid, the relations' first stamp at scan {first}"
        f" (mean heading error of the turning relations there {math.degrees(errors[first]):.2f} deg;"
        f" next best offset beside it {math.degrees(nearby[1]) if len(nearby) > 1 else float('nan'):.2f} deg)"
    )
    return lines, note


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "bags",
        nargs="+",
        type=Path,
        help="NAME.orig.bag files (INESCTEC/ricoslam), or NAME.clf2bag.bag with NAME.relations",
    )
    ap.add_argument("--out", type=Path, required=True, help="folder for NAME.clf")
    args = ap.parse_args(argv)
    names: dict[str, Path] = {}
    for bag in args.bags:
        if bag.name.endswith(".sort.bag"):
            # Time order: a scan and the odometry stamped with it come in either order there, and the
            # last odometry before a scan is then, half the time, the scan before's.
            print(f"{bag}: a time-sorted conversion; give the NAME.orig.bag (the log's line order)", file=sys.stderr)
            return 1
        name = bag.name.removesuffix(".bag").removesuffix(".orig").removesuffix(".clf2bag")
        if name in names:
            print(f"{bag} and {names[name]} would both be {name}.clf", file=sys.stderr)
            return 1
        names[name] = bag
    args.out.mkdir(parents=True, exist_ok=True)
    for name, bag in names.items():
        try:
            data = bag.read_bytes()
            if bag.name.endswith(".clf2bag.bag"):
                beside = [d / f"{name}.relations" for d in (bag.parent, args.out)]
                found = [p for p in beside if p.exists()]
                if not found:
                    raise BagError(f"its stamps are not the log's: give {name}.relations beside it or in --out")
                lines, note = clf2bag_lines(data, found[0].read_text())
                print(f"{bag}: {note}")
            else:
                lines = list(log_lines(data, robotlaser="_robotlaser" in name))
        except (OSError, BagError, struct.error, UnicodeDecodeError, ValueError, KeyError, IndexError) as exc:
            print(f"{bag}: not read: {type(exc).__name__}: {exc}", file=sys.stderr)
            return 1
        scans = sum(1 for s in lines if not s.startswith("ODOM"))
        if not scans:
            print(f"{bag}: no /scan messages", file=sys.stderr)
            return 1
        (args.out / f"{name}.clf").write_text("\n".join(lines) + "\n")
        print(f"{bag} -> {args.out / (name + '.clf')}: {scans} scans, {len(lines) - scans} odometry lines")
    return 0


if __name__ == "__main__":
    sys.exit(main())
