"""bench/freiburg_bags.py: the Freiburg raw logs put together again from ROS 1 bags. A small bag is
written here by hand in the published bag format 2.0 (a bz2 chunk holding connection and message
records, the messages serialized as ROS 1 does) and read back as CARMEN lines, which the log reader
then takes as the replay would."""

from __future__ import annotations

import bz2
import itertools
import math
import re
import struct
from pathlib import Path

import pytest

from fleetlink.agent.mapping.carmen import LaserRecord, OdomRecord, read_records
from fleetlink.shared.se2 import relative
from tests.harness.bench import load_bench


def _tool():  # type: ignore[no-untyped-def]
    return load_bench("freiburg_bags")


def _field(name: str, value: bytes) -> bytes:
    item = name.encode() + b"=" + value
    return struct.pack("<I", len(item)) + item


def _record(fields: dict[str, bytes], body: bytes) -> bytes:
    header = b"".join(_field(k, v) for k, v in fields.items())
    return struct.pack("<I", len(header)) + header + struct.pack("<I", len(body)) + body


def _string(s: str) -> bytes:
    return struct.pack("<I", len(s)) + s.encode()


def _header(sec: int, nsec: int, frame: str) -> bytes:
    return struct.pack("<3I", 0, sec, nsec) + _string(frame)


def _quat(yaw: float) -> tuple[float, float, float, float]:
    return 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)


def _odom(sec: int, nsec: int, x: float, y: float, yaw: float) -> bytes:
    pose = struct.pack("<7d", x, y, 0.0, *_quat(yaw)) + struct.pack("<36d", *([0.0] * 36))
    twist = struct.pack("<6d", *([0.0] * 6)) + struct.pack("<36d", *([0.0] * 36))
    return _header(sec, nsec, "odom") + _string("base_link") + pose + twist


def _scan(sec: int, nsec: int, angle_min: float, ranges: list[float]) -> bytes:
    inc = math.radians(1.0)
    head = struct.pack("<7f", angle_min, angle_min + inc * (len(ranges) - 1), inc, 0.0, 0.0, 0.1, 81.9)
    return (
        _header(sec, nsec, "laser")
        + head
        + struct.pack(f"<I{len(ranges)}f", len(ranges), *ranges)
        + struct.pack("<I", 0)
    )


def _tf(x: float, y: float, yaw: float) -> bytes:
    transform = struct.pack("<7d", x, y, 0.0, *_quat(yaw))
    return struct.pack("<I", 1) + _header(0, 0, "base_link") + _string("laser") + transform


def _bag(messages: list[tuple[str, bytes]], compression: str = "bz2", per_chunk: int = 2) -> bytes:
    """A bag as the format has it: the bag header record, then chunks (each with its connections and
    messages, and an index data record after it), then the connections again and the chunk infos."""
    topics = {t: i for i, t in enumerate(dict.fromkeys(t for t, _ in messages))}

    def conn(t: str) -> bytes:
        fields = {"op": b"\x07", "conn": struct.pack("<I", topics[t]), "topic": t.encode()}
        return _record(fields, _field("type", b"x/y"))

    header = {"op": b"\x03", "index_pos": b"\0" * 8, "conn_count": b"\0" * 4, "chunk_count": b"\0" * 4}
    out = [_record(header, b" " * 16)]
    for k in range(0, len(messages), per_chunk):
        part = messages[k : k + per_chunk]
        inner = b"".join(conn(t) for t in dict.fromkeys(t for t, _ in part))
        inner += b"".join(
            _record({"op": b"\x02", "conn": struct.pack("<I", topics[t]), "time": b"\0" * 8}, body) for t, body in part
        )
        data = bz2.compress(inner) if compression == "bz2" else inner
        fields = {"op": b"\x05", "compression": compression.encode(), "size": struct.pack("<I", len(inner))}
        out.append(_record(fields, data))
        out.append(_record({"op": b"\x04", "ver": b"\1\0\0\0", "conn": b"\0" * 4, "count": b"\0" * 4}, b""))
    out += [conn(t) for t in topics]
    out.append(_record({"op": b"\x06", "ver": b"\1\0\0\0", "chunk_pos": b"\0" * 8}, b""))
    return b"#ROSBAG V2.0\n" + b"".join(out)


RANGES = [1.5, 2.25, 3.0, 81.91] + [4.0] * 176  # a SICK's 180 beams, 1 degree apart from -90


@pytest.mark.parametrize("compression", ["bz2", "none"])
def test_scans_take_the_last_odometry_before_them_in_the_files_order(compression: str) -> None:
    """As the log's lines ran: each scan at the last ODOM line before it (an ODOM line stamped like a
    scan but written after it is the next scan's), its time to the microsecond, its ranges as
    written; a scan before any odometry waits for the first."""
    tool = _tool()
    bag = _bag(
        [
            ("/scan", _scan(99, 0, -math.pi / 2, RANGES)),
            ("/odom", _odom(100, 0, 1.0, 2.0, 0.5)),
            ("/scan", _scan(100, 123_456_789, -math.pi / 2, RANGES)),
            ("/odom", _odom(100, 123_456_789, 1.5, 2.0, 0.6)),
            ("/odom", _odom(101, 0, 2.0, 2.0, 0.7)),
            ("/scan", _scan(101, 500_000_000, -math.pi / 2, RANGES)),
        ],
        compression,
    )
    lines = list(tool.log_lines(bag, robotlaser=False))
    recs = list(read_records(lines))
    lasers = [r for r in recs if isinstance(r, LaserRecord)]
    assert sum(isinstance(r, OdomRecord) for r in recs) == 3
    assert [r.kind for r in lasers] == ["FLASER"] * 3
    assert [r.ipc_timestamp for r in lasers] == ["99.000000", "100.123457", "101.500000"]
    assert [r.odom for r in lasers] == [
        pytest.approx((1.0, 2.0, 0.5)),
        pytest.approx((1.0, 2.0, 0.5)),
        pytest.approx((2.0, 2.0, 0.7)),
    ]
    assert lasers[1].ranges.tolist()[:3] == RANGES[:3] and lasers[1].ranges[3] == pytest.approx(81.91)
    assert "1.5 2.25 3 81.91 4 4" in lines[1]  # float32 written as the shortest text that reads back


def test_a_robotlaser_bag_keeps_each_scans_angles_and_the_lasers_mount() -> None:
    """The hospital's form: ROBOTLASER1 lines with each scan's own start angle and the static
    base-to-laser transform as the laser's place on the robot."""
    tool = _tool()
    bag = _bag(
        [
            ("/tf_static", _tf(0.22, 0.05, math.radians(5.0))),
            ("/odom", _odom(5, 0, 1.0, 0.0, math.pi / 2)),
            ("/scan", _scan(5, 0, -math.pi / 2, RANGES)),
            ("/odom", _odom(6, 0, 1.0, 1.0, math.pi / 2)),
            ("/scan", _scan(6, 0, math.radians(-89.75), RANGES)),
        ]
    )
    lasers = [r for r in read_records(list(tool.log_lines(bag, robotlaser=True))) if isinstance(r, LaserRecord)]
    assert [r.kind for r in lasers] == ["ROBOTLASER1"] * 2
    assert lasers[0].laser_offset == pytest.approx((0.22, 0.05, math.radians(5.0)), abs=1e-6)
    assert lasers[1].odom == pytest.approx((1.0, 1.0, math.pi / 2), abs=1e-6)
    assert lasers[0].angles[0] == pytest.approx(-math.pi / 2, abs=1e-6)
    assert lasers[1].angles[0] == pytest.approx(math.radians(-89.75), abs=1e-6)
    assert lasers[0].max_range == pytest.approx(81.9)


def test_what_cannot_be_read_right_is_refused_with_a_reason(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tool = _tool()
    out = str(tmp_path / "out")

    def refused(name: str, data: bytes, reason: str) -> None:
        (tmp_path / name).write_bytes(data)
        assert tool.main([str(tmp_path / name), "--out", out]) == 1
        assert reason in capsys.readouterr().err

    lz4 = _bag([("/odom", _odom(1, 0, 0.0, 0.0, 0.0))]).replace(b"compression=bz2", b"compression=lz4")
    no_odometry = _bag([("/scan", _scan(1, 0, -math.pi / 2, RANGES))], "none")
    refused("x.orig.bag", b"not a bag at all", "not a ROS bag")
    refused("y.orig.bag", lz4, "only bz2 and none")
    refused("z.orig.bag", no_odometry, "no /odom to place them by")
    # The hospital's angles need ROBOTLASER1 lines (a bag named *_robotlaser*).
    hospital = _bag([("/odom", _odom(1, 0, 0.0, 0.0, 0.0)), ("/scan", _scan(1, 0, math.radians(-89.75), RANGES))])
    refused("w.orig.bag", hospital, "is no FLASER line")
    refused("cut.orig.bag", no_odometry[:-60], "cut short")
    # Time order: a scan's own odometry may come before or after it there.
    refused("room.sort.bag", no_odometry, "time-sorted")
    assert not list(tmp_path.glob("out/*.clf"))  # nothing written for a bag refused
    good = _bag([("/odom", _odom(1, 0, 0.0, 0.0, 0.0)), ("/scan", _scan(1, 0, -math.pi / 2, RANGES))])
    (tmp_path / "room.orig.bag").write_bytes(good)
    (tmp_path / "room.bag").write_bytes(good)
    assert tool.main([str(tmp_path / "room.orig.bag"), str(tmp_path / "room.bag"), "--out", out]) == 1
    assert "would both be room.clf" in capsys.readouterr().err
    assert tool.main([str(tmp_path / "room.orig.bag"), "--out", out]) == 0
    assert "1 scans, 1 odometry lines" in capsys.readouterr().out
    assert (tmp_path / "out" / "room.clf").read_text().count("FLASER") == 1


def _clf2bag(poses: list[tuple[float, float, float]]) -> bytes:
    """A bag as the clf2bag converter writes one: per scan its /scan, /tf and /odom, stamped 0.1 s apart
    from 1e9 s, whatever the log's times were."""
    out: list[tuple[str, bytes]] = []
    for k, (x, y, th) in enumerate(poses):
        sec, nsec = 1_000_000_000 + k // 10, (k % 10) * 100_000_000
        out += [("/scan", _scan(sec, nsec, -math.pi / 2, RANGES)), ("/tf", _tf(x, y, th))]
        out.append(("/odom", _odom(sec, nsec, x, y, th)))
    return _bag(out, per_chunk=30)


def test_a_clf2bag_bag_gets_the_logs_times_back_from_the_relations(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """MIT's Killian Court log, kept only as a clf2bag bag: its scans came every 0.44 s, so the
    relations' stamps lie on that grid; the one offset left is where the turning relations agree with
    the odometry. Each scan a relation names gets that relation's stamp back, to the microsecond."""
    tool = _tool()
    poses = [(0.0, 0.0, 0.0)]
    for k in range(1, 130):
        th = 0.8 * math.sin(k / 6.0)
        poses.append((poses[-1][0] + 0.13 * math.cos(th), poses[-1][1] + 0.13 * math.sin(th), th))
    # The log's times: 0.44 s a scan, with the jitter a logger adds; the relations name every second
    # scan from scan 17 on (the first stamps of a log are seldom in them).
    times = [1031745833.448 + 0.44 * k + 0.03 * math.sin(k) for k in range(len(poses))]
    named = list(range(17, 121, 2))
    lines = []
    for a, b in itertools.pairwise(named):
        x, y, yaw = relative(poses[a], poses[b])
        lines.append(f"{times[a]:.6f} {times[b]:.6f} {x:.6f} {y:.6f} 0 0 0 {yaw:.6f}")
    (tmp_path / "killian.clf2bag.bag").write_bytes(_clf2bag(poses))
    out = tmp_path / "out"
    # Without its relations the bag's stamps would be taken for the log's: refused.
    assert tool.main([str(tmp_path / "killian.clf2bag.bag"), "--out", str(out)]) == 1
    assert "give killian.relations" in capsys.readouterr().err
    (tmp_path / "killian.relations").write_text("# timestamp1 timestamp2 x y z roll pitch yaw\n" + "\n".join(lines))
    assert tool.main([str(tmp_path / "killian.clf2bag.bag"), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert re.search(r"on a 0\.44\d s grid, the relations. first stamp at scan 17 ", said), said
    lasers = [r for r in read_records((out / "killian.clf").read_text().splitlines()) if isinstance(r, LaserRecord)]
    assert len(lasers) == len(poses)
    stamps = [r.ipc_timestamp for r in lasers]
    assert [stamps[k] for k in named] == [f"{times[k]:.6f}" for k in named]
    assert all(float(a) < float(b) for a, b in itertools.pairwise(stamps))
    assert lasers[40].odom == pytest.approx(poses[40], abs=1e-5)
    # Stamps that are not on one period's grid cannot be placed: refused, with the reason.
    for bad in (times[30] + 0.22, times[30] + 0.15):  # half a period off: a grid that will not fit; or no grid
        (tmp_path / "killian.relations").write_text("\n".join([*lines, f"{times[29]:.6f} {bad:.6f} 0 0 0 0 0 0"]))
        assert tool.main([str(tmp_path / "killian.clf2bag.bag"), "--out", str(out)]) == 1
        assert "the log's times cannot be recovered" in capsys.readouterr().err
