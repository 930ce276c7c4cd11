"""CARMEN logs: parsing (robust to junk), replay of a small constructed log, the CLI's outputs read
back by the map_server rules and as a field floor plan."""

from __future__ import annotations

import gzip
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from fleetlink.agent.mapping.carmen import (
    OTHER_KINDS,
    UNKNOWN_KINDS_KEPT,
    CarmenStats,
    LaserRecord,
    OdomRecord,
    corrected_lines,
    read_records,
)
from fleetlink.agent.mapping.mapper import MapperConfig, compose, relative
from fleetlink.agent.mapping.replay import replay
from fleetlink.cli.main import main
from fleetlink.field.mapserver import read_map
from fleetlink.field.plans import load_plan
from fleetlink.field.raycast import Raycaster

ROOM = np.array(
    [
        [0.0, 0.0, 6.0, 0.0],
        [6.0, 0.0, 6.0, 4.0],
        [6.0, 4.0, 0.0, 4.0],
        [0.0, 4.0, 0.0, 0.0],
        [2.5, 1.5, 3.1, 1.5],
        [3.1, 1.5, 3.1, 2.1],
        [3.1, 2.1, 2.5, 2.1],
        [2.5, 2.1, 2.5, 1.5],
    ]
)
TIMESTAMPS = ["1000.000100", "1000.2", "1000.40000", "1000.6", "1000.8", "1001", "1001.2", "1001.4"]


def _poses() -> list[tuple[float, float, float]]:
    return [(1.0 + 0.12 * i, 1.0 + 0.05 * i, 0.1 * i) for i in range(len(TIMESTAMPS))]


def _flaser(rc: Raycaster, pose: tuple[float, float, float], odom: tuple[float, float, float], ts: str) -> str:
    n = 181
    r = rc.cast_fan(pose[0], pose[1], pose[2] - math.pi / 2, math.pi / 180, n, 80.0)
    r = np.where(np.isfinite(r), r, 81.91)
    ranges = " ".join(f"{v:.3f}" for v in r)
    return f"FLASER {n} {ranges} {pose[0]} {pose[1]} {pose[2]} {odom[0]} {odom[1]} {odom[2]} {ts} nohost {ts}"


def _log_lines() -> list[str]:
    rc = Raycaster(ROOM)
    # Odometry lives in its own frame: the true path seen from an arbitrary start, slightly off.
    frame = (10.0, -3.0, 1.0)
    lines = [
        "# message formats defined: PARAM SYNC ODOM FLASER",
        "PARAM robot_frontlaser_offset 0.0 nohost 0",
        "",
        "SYNC 0.0 nohost 0",
    ]
    poses = _poses()
    for i, (pose, ts) in enumerate(zip(poses, TIMESTAMPS, strict=True)):
        odom = compose(frame, relative(poses[0], pose))
        odom = (odom[0] + 0.02 * i, odom[1], odom[2] + 0.01 * i)  # drifting odometry
        lines.append(f"ODOM {odom[0]} {odom[1]} {odom[2]} 0.1 0.0 0.0 {ts} nohost {ts}")
        lines.append(_flaser(rc, pose, odom, ts))
        lines.append(f"NEFF {i} 100 nohost {ts}")
        if i == 3:
            lines += ["FLASER 181 1.0 2.0", "FLASER abc", "FLASER 3 1 2 3 a b c 0 0 0 1.0 nohost 1.0", "ODOM 1 2"]
    return lines


def test_a_file_of_garbage_is_counted_in_a_few_names_and_its_scans_still_read() -> None:
    """Lines of binary junk and of made-up kinds between a log's own: every scan is read, the skipped
    lines are counted under at most ``UNKNOWN_KINDS_KEPT`` names (the rest together, junk that is no
    record name apart), and the summary stays one short line instead of naming every line."""
    rng = np.random.default_rng(5)
    junk = [bytes(rng.integers(33, 256, 40, dtype=np.uint8)).decode("latin-1") for _ in range(200)]
    made_up = [f"KIND{i} 1 2 3" for i in range(100)]
    long_kind = "X" * 40  # counted under its first 32 characters, the same name each time
    lines = [long_kind, *_log_lines(), *junk, *made_up, long_kind]
    stats = CarmenStats()
    lasers = [r for r in read_records(lines, stats) if isinstance(r, LaserRecord)]
    assert len(lasers) == len(TIMESTAMPS)
    assert len(stats.unknown) <= UNKNOWN_KINDS_KEPT + 2  # + the other kinds and the unreadable
    assert sum(stats.unknown.values()) == len(TIMESTAMPS) + 1 + len(junk) + len(made_up) + 2  # NEFF, SYNC too
    assert stats.unknown["X" * 32] == 2
    assert stats.unknown[OTHER_KINDS] >= len(made_up) - UNKNOWN_KINDS_KEPT
    summary = stats.summary()
    assert len(summary) < 400 and "NEFF" in summary and "other kinds" in summary
    assert all(ch.isprintable() for ch in summary)


def test_reader_skips_and_counts_what_it_cannot_use() -> None:
    stats = CarmenStats()
    recs = list(read_records(_log_lines(), stats))
    lasers = [r for r in recs if isinstance(r, LaserRecord)]
    assert len(lasers) == len(TIMESTAMPS) == stats.scans
    assert sum(isinstance(r, OdomRecord) for r in recs) == len(TIMESTAMPS)
    assert [r.ipc_timestamp for r in lasers] == TIMESTAMPS
    assert stats.unknown == {"NEFF": len(TIMESTAMPS), "SYNC": 1}
    assert sum(stats.malformed.values()) == 4 and len(stats.examples) == 4
    assert stats.comments == 1 and stats.blank == 1 and stats.params["robot_frontlaser_offset"] == "0.0"
    # FLASER beams: -90 deg upwards in 1 degree steps.
    assert lasers[0].angles[0] == pytest.approx(-math.pi / 2)
    assert lasers[0].angles[90] == pytest.approx(0.0)


def test_robotlaser1_is_read_with_its_own_geometry() -> None:
    n = 5
    line = (
        f"ROBOTLASER1 0 -1.0 2.0 0.5 30.0 0.01 0 {n} 1 2 3 4 5 0 "
        "1.1 2.0 0.5 1.0 2.0 0.5 0.2 0.0 0.5 0.2 0.0 77.125 host 77.2"
    )
    (rec,) = list(read_records([line]))
    assert isinstance(rec, LaserRecord) and rec.kind == "ROBOTLASER1"
    assert rec.angles.tolist() == [-1.0, -0.5, 0.0, 0.5, 1.0]
    assert rec.max_range == 30.0 and rec.ipc_timestamp == "77.125"
    assert rec.laser_offset == pytest.approx((0.1 * math.cos(0.5), -0.1 * math.sin(0.5), 0.0))


def test_a_sick_s_error_codes_under_its_maximum_are_no_return() -> None:
    """A SICK LMS 2xx in centimetre mode reports 81.83 m ("over range") to 81.91 m as codes; a
    ROBOTLASER1 line gives 81.9 m as its maximum. None of them is a wall 81.83 m off (mapped, it
    would clear every cell along the beam); a reading short of them is."""
    line = (
        "ROBOTLASER1 0 -1.5707963 3.1415927 0.0174533 81.9 0.01 0 5 3.5 81.83 81.91 81.0 79.5 0 "
        "0.22 0.0 0.0 0.0 0.0 0.0 0.0 0.0 0.5 0.2 0.0 77.125 host 77.2"
    )
    (rec,) = list(read_records([line]))
    assert isinstance(rec, LaserRecord)
    got = rec.measured()
    assert np.isnan(got[[1, 2]]).all() and got[[0, 3, 4]].tolist() == [3.5, 81.0, 79.5]
    assert rec.ranges[1] == 81.83  # the record itself keeps what the log says


def test_corrected_lines_replace_the_pose_and_nothing_else() -> None:
    """A SLAM result in the form the Freiburg metricEvaluator reads: the same log, each laser line
    carrying the new robot pose (FLASER: in both triples, as a corrected log; ROBOTLASER1: its laser
    pose moved with it, the mount kept)."""
    robot = (
        "ROBOTLASER1 0 -1.0 2.0 0.5 30.0 0.01 0 5 1 2 3 4 5 2 7 8 "
        "1.0 2.0 -2.7831853 0.8 2.1 3.0 0.2 0.0 0.5 0.2 0.0 77.125 host 77.2\n"
    )
    lines = [*_log_lines()[:9], robot, "ODOM 1 2 3 0 0 0 78.0 host 78.0"]
    recs = [r for r in read_records(lines) if isinstance(r, LaserRecord)]
    assert [r.kind for r in recs] == ["FLASER", "FLASER", "ROBOTLASER1"]
    new = {r.line: (5.0 + k, -1.0 - k, 3.0 - k) for k, r in enumerate(recs)}
    out = list(corrected_lines(lines, new))
    assert len(out) == len(lines)
    for number, (before, after) in enumerate(zip(lines, out, strict=True), start=1):
        if number not in new:
            assert after == before  # ODOM, PARAM, comments, NEFF: verbatim
    again = [r for r in read_records(out) if isinstance(r, LaserRecord)]
    for old, r in zip(recs, again, strict=True):
        assert r.pose == pytest.approx(new[old.line], abs=1e-6)
        assert r.ipc_timestamp == old.ipc_timestamp and r.kind == old.kind
        assert np.array_equal(r.ranges, old.ranges) and np.array_equal(r.angles, old.angles)
        assert r.laser_offset == pytest.approx(old.laser_offset, abs=1e-6)
        if r.kind == "FLASER":  # both triples: metricEvaluator reads the robot pose from odom_*
            assert r.odom == pytest.approx(new[old.line], abs=1e-6)
    assert out[-2].endswith("\n") and out[-2].split()[-3:] == ["77.125", "host", "77.2"]
    # The laser pose: the new robot pose composed with the mount (turned 0.5 rad: 1.0 + 0.5, unwrapped).
    assert recs[2].laser_offset[2] == pytest.approx(0.5)
    laser = compose(new[recs[2].line], recs[2].laser_offset)
    assert [float(v) for v in out[-2].split()[17:20]] == pytest.approx([laser[0], laser[1], 1.5], abs=1e-6)
    wrapped = list(corrected_lines(lines, {recs[2].line: (0.0, 0.0, 3.0)}))[-2].split()[19]
    assert float(wrapped) == pytest.approx(3.5 - 2 * math.pi, abs=1e-6)  # 3.0 + 0.5 wrapped past pi
    with pytest.raises(ValueError, match="line 1: not a laser line"):
        list(corrected_lines(lines, {1: (0.0, 0.0, 0.0)}))


def test_flaser_poses_are_the_laser_s_then_the_robot_s_as_carmen_writes_them() -> None:
    """A front laser 0.3 m ahead (PARAM robot_frontlaser_offset): FLASER's ``x y theta`` is the laser's
    pose, ``odom_*`` the robot's (CARMEN's log2log writes laser_pose then robot_pose); metricEvaluator
    scores the second. The record's pose is the robot's; a corrected log writes both."""
    robot, odom = (2.0, 1.0, math.pi / 2), (7.0, -4.0, 0.25)
    laser = (2.0, 1.3, math.pi / 2)
    ranges = " ".join(["1.0"] * 181)
    lines = [
        "PARAM robot_frontlaser_offset 0.3 nohost 0",
        f"FLASER 181 {ranges} {laser[0]} {laser[1]} {laser[2]} {odom[0]} {odom[1]} {odom[2]} 5.5 nohost 5.5",
    ]
    (rec,) = [r for r in read_records(lines) if isinstance(r, LaserRecord)]
    assert rec.laser_offset == (0.3, 0.0, 0.0)
    assert rec.pose == pytest.approx(robot, abs=1e-9) and rec.odom == odom
    new = (-1.0, 4.0, math.pi)  # facing -x: the laser 0.3 m towards -x
    out = list(corrected_lines(lines, {rec.line: new}))
    assert out[0] == lines[0]
    fields = [float(v) for v in out[1].split()[183:189]]
    assert (
        fields[:2] == pytest.approx([-1.3, 4.0], abs=1e-6)
        and abs(math.remainder(fields[2] - math.pi, 2 * math.pi)) < 1e-6
    )
    assert fields[3:] == pytest.approx(list(new), abs=1e-6)  # the robot pose, where metricEvaluator reads it
    (again,) = [r for r in read_records(out) if isinstance(r, LaserRecord)]
    assert again.pose[:2] == pytest.approx(new[:2], abs=1e-6) and again.odom == pytest.approx(new, abs=1e-6)


def _rawlaser_lines(with_flaser: bool = False, flaser_late: bool = False) -> list[str]:
    """The room log as a CARMEN logger writes a bare laser: RAWLASER1 lines (no pose, 181 beams from
    -90 degrees at 1 degree, 80 m) between ODOM lines that are not at the scans' times; the robot's
    odometry there is the true path, sampled 0.05 s before and after each scan. ``with_flaser``: the
    logger wrote each scan as a FLASER line too (``flaser_late``: after the next ODOM line)."""
    rc = Raycaster(ROOM)
    lines = ["PARAM robot_frontlaser_offset 0.0 nohost 0"]
    poses = _poses()
    for i, (pose, ts) in enumerate(zip(poses, TIMESTAMPS, strict=True)):
        t = float(ts)
        nxt = poses[min(i + 1, len(poses) - 1)]
        # The robot moves 1/4 of the way to the next pose in 0.05 s (scans are 0.2 s apart).
        ahead = tuple(a + 0.25 * (b - a) for a, b in zip(pose, nxt, strict=True))
        behind = tuple(a - 0.25 * (b - a) for a, b in zip(pose, nxt, strict=True))
        lines.append(f"ODOM {behind[0]} {behind[1]} {behind[2]} 0.1 0.0 0.0 {t - 0.05:.3f} nohost {t:.3f}")
        r = rc.cast_fan(pose[0], pose[1], pose[2] - math.pi / 2, math.pi / 180, 181, 80.0)
        r = np.where(np.isfinite(r), r, 81.91)
        ranges = " ".join(f"{v:.3f}" for v in r)
        lines.append(f"RAWLASER1 0 -1.5707963 3.1415927 0.0174533 81.91 0.01 0 181 {ranges} 0 {ts} nohost {ts}")
        if with_flaser and not flaser_late:
            lines.append(_flaser(rc, pose, pose, ts))
        lines.append(f"ODOM {ahead[0]} {ahead[1]} {ahead[2]} 0.1 0.0 0.0 {t + 0.05:.3f} nohost {t:.3f}")
        if with_flaser and flaser_late:
            lines.append(_flaser(rc, pose, pose, ts))
    return lines


def test_rawlaser1_is_placed_by_the_odometry_at_its_time_and_maps() -> None:
    """A log of bare RAWLASER1 scans and ODOM lines: each scan's pose is the odometry interpolated to
    its time; replayed, the room's path comes back; written back, each becomes the ROBOTLASER1 line
    of the same scan with the SLAM pose (what metricEvaluator reads)."""
    stats = CarmenStats()
    lines = _rawlaser_lines()
    recs = [r for r in read_records(lines, stats) if isinstance(r, LaserRecord)]
    assert [r.kind for r in recs] == ["RAWLASER1"] * len(TIMESTAMPS) == ["RAWLASER1"] * stats.scans
    assert [r.ipc_timestamp for r in recs] == TIMESTAMPS and stats.odom == 2 * len(TIMESTAMPS)
    for r, pose in zip(recs, _poses(), strict=True):  # (the ODOM lines' times are rounded to 1 ms)
        assert r.pose == pytest.approx(pose, abs=1e-3) and r.odom == r.pose
    assert recs[0].angles[0] == pytest.approx(-math.pi / 2) and recs[0].max_range == pytest.approx(81.91)
    result = replay(iter(recs))
    est, truth = [p for _, p in result.rows], _poses()
    for e, t in zip(est, truth, strict=True):
        r_est, r_true = relative(est[0], e), relative(truth[0], t)
        assert math.hypot(r_est[0] - r_true[0], r_est[1] - r_true[1]) < 0.03
    new = {r.line: (5.0 + k, -1.0, 0.5) for k, r in enumerate(recs)}
    out = list(corrected_lines(lines, new))
    assert len(out) == len(lines)
    again = [r for r in read_records(out) if isinstance(r, LaserRecord)]
    assert [r.kind for r in again] == ["ROBOTLASER1"] * len(recs)
    for old, r in zip(recs, again, strict=True):
        assert r.pose == pytest.approx(new[old.line], abs=1e-6) and r.ipc_timestamp == old.ipc_timestamp
        assert np.array_equal(r.ranges, old.ranges) and np.allclose(r.angles, old.angles)


def test_a_log_without_odometry_is_mapped_by_the_scans_alone() -> None:
    """A bare laser's log (RAWLASER1, no ODOM lines): no step is known, so none is assumed to be zero
    (held to a centimetre, the matcher would keep the robot where it started); the last step is
    guessed again and the matcher's own prior decides."""
    lines = [line for line in _rawlaser_lines() if not line.startswith("ODOM")]
    recs = [r for r in read_records(lines) if isinstance(r, LaserRecord)]
    assert len(recs) == len(TIMESTAMPS) and not any(r.has_odometry for r in recs)
    result = replay(iter(recs))
    est, truth = [p for _, p in result.rows], _poses()
    for e, t in zip(est, truth, strict=True):
        r_est, r_true = relative(est[0], e), relative(truth[0], t)
        assert math.hypot(r_est[0] - r_true[0], r_est[1] - r_true[1]) < 0.03
        assert abs(math.remainder(r_est[2] - r_true[2], 2 * math.pi)) < math.radians(1.0)


def test_rawlaser1_beside_flaser_lines_is_not_mapped_twice() -> None:
    stats = CarmenStats()
    recs = [r for r in read_records(_rawlaser_lines(with_flaser=True), stats) if isinstance(r, LaserRecord)]
    assert [r.kind for r in recs] == ["FLASER"] * len(TIMESTAMPS) and stats.scans == len(TIMESTAMPS)
    assert stats.unknown == {"RAWLASER1 (the same scans as FLASER/ROBOTLASER1)": len(TIMESTAMPS)}
    # The robot module's FLASER line after the next ODOM line: the first scan's RAWLASER1 line was
    # placed (and given out) by then, so its FLASER line is the copy left out; then FLASER throughout.
    late = CarmenStats()
    recs = [
        r for r in read_records(_rawlaser_lines(with_flaser=True, flaser_late=True), late) if isinstance(r, LaserRecord)
    ]
    assert [r.kind for r in recs] == ["RAWLASER1"] + ["FLASER"] * (len(TIMESTAMPS) - 1)
    assert [r.ipc_timestamp for r in recs] == TIMESTAMPS and late.scans == len(TIMESTAMPS)
    assert late.unknown == {
        "FLASER (the same scan as a RAWLASER1 line before it)": 1,
        "RAWLASER1 (the same scans as FLASER/ROBOTLASER1)": len(TIMESTAMPS) - 1,
    }
    # Scans whose times go back are placed each at its own time.
    lines = _rawlaser_lines()
    lines[2], lines[5] = lines[5], lines[2]  # the first two RAWLASER1 lines swapped
    first_two = [r for r in read_records(lines) if isinstance(r, LaserRecord)][:2]
    assert [r.ipc_timestamp for r in first_two] == TIMESTAMPS[:2]
    for r, pose in zip(first_two, _poses(), strict=False):
        assert r.pose == pytest.approx(pose, abs=1e-3)
    # Without odometry a bare scan has none (the matcher alone places it).
    (rec,) = read_records([_rawlaser_lines()[2]])
    assert isinstance(rec, LaserRecord) and rec.pose == (0.0, 0.0, 0.0) and not rec.has_odometry
    bad = CarmenStats()
    assert list(read_records(["RAWLASER1 0 -1.57 3.14 0.0175 80 0.01 0 3 1 2"], bad)) == []
    assert bad.malformed == {"RAWLASER1: too few fields": 1}


def test_replay_recovers_the_path_despite_drifting_odometry() -> None:
    heard: list[tuple[str, int]] = []
    result = replay(read_records(_log_lines()), progress=lambda stage, n: heard.append((stage, n)))
    # Progress: every scan as it is mapped, then the final pass with the graph's nodes.
    assert heard == [("scans", k) for k in range(1, len(TIMESTAMPS) + 1)] + [("final", len(result.mapper.closer or []))]
    est = [p for _, p in result.rows]
    truth = _poses()
    assert [ts for ts, _ in result.rows] == TIMESTAMPS
    # The map frame is the first odometry pose; compare the path relative to the first scan.
    for e, t in zip(est, truth, strict=True):
        r_est, r_true = relative(est[0], e), relative(truth[0], t)
        assert math.hypot(r_est[0] - r_true[0], r_est[1] - r_true[1]) < 0.03
        assert abs(r_est[2] - r_true[2]) < math.radians(0.5)
    # Odometry alone drifts about 0.15 m and 4 degrees by the end.
    plain = replay(read_records(_log_lines()), MapperConfig(matching=False, closer=None))  # the odometry alone
    r_odo = relative(plain.rows[0][1], plain.rows[-1][1])
    r_true = relative(truth[0], truth[-1])
    assert math.hypot(r_odo[0] - r_true[0], r_odo[1] - r_true[1]) > 0.12


def test_cli_replay_writes_map_server_files_and_a_verbatim_trajectory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "room.log.gz"
    with gzip.open(log, "wt") as f:
        f.write("\n".join(_log_lines()) + "\n")
    out = tmp_path / "out"
    assert main(["map", "replay", str(log), "--out", str(out)]) == 0
    assert f"{log}: final pass over " in capsys.readouterr().err  # progress on stderr, not in the summary
    rows = (out / "trajectory.txt").read_text().splitlines()
    assert [r.split()[0] for r in rows] == TIMESTAMPS
    assert all(len(r.split()) == 4 for r in rows)
    # Read back by the map_server rules: the room's walls are occupied, its inside free.
    m = read_map(out / "map.yaml")
    assert m.image is not None and m.resolution == pytest.approx(0.05)
    first = [float(v) for v in rows[0].split()[1:]]

    def cell(x: float, y: float) -> int:
        # Room coordinates -> map frame (the map frame is the first scan's odometry pose).
        p = compose(tuple(first), relative(_poses()[0], (x, y, 0.0)))  # type: ignore[arg-type]
        col, row = m.cell_of(p[0], p[1])
        return int(m.grid[row, col])

    assert cell(1.5, 2.8) == 0  # free floor
    assert cell(3.0, 0.0) == 100 or cell(3.0, 0.02) == 100 or cell(3.0, -0.02) == 100  # south wall
    # The same file is a field floor plan.
    plan = load_plan(out / "map.yaml")
    assert len(plan.walls) > 4
    assert main(["map", "load", str(out / "map.yaml")]) == 0
    # --no-closure: the front end alone (no pose graph); the same scans, the same timestamps.
    bare = tmp_path / "bare"
    assert main(["map", "replay", str(log), "--out", str(bare), "--no-closure"]) == 0
    assert [r.split()[0] for r in (bare / "trajectory.txt").read_text().splitlines()] == TIMESTAMPS
    # corrected.log: the input, line for line, with the trajectory's poses on the laser lines; the
    # scorer reads it as it reads trajectory.txt.
    text = (out / "corrected.log").read_text()
    assert len(text.splitlines()) == len(_log_lines())
    again = [r for r in read_records(text.splitlines()) if isinstance(r, LaserRecord)]
    assert [r.ipc_timestamp for r in again] == TIMESTAMPS
    for r, row in zip(again, rows, strict=True):
        assert r.pose == pytest.approx(tuple(float(v) for v in row.split()[1:]), abs=1e-6)
    # As metricEvaluator's logutil reads a FLASER line: skip n ranges and the laser pose, then the
    # robot pose and the ipc_timestamp. It must find the trajectory there, not the raw odometry.
    read_as_evaluator = []
    for line in text.splitlines():
        toks = line.split()
        if toks[:1] == ["FLASER"] and toks[1] == "181" and len(toks) == 2 + 181 + 9:
            k = 2 + 181 + 3
            read_as_evaluator.append([toks[k + 3], *toks[k : k + 3]])
    assert [r[0] for r in read_as_evaluator] == TIMESTAMPS
    for got, row in zip(read_as_evaluator, rows, strict=True):
        assert [float(v) for v in got[1:]] == pytest.approx([float(v) for v in row.split()[1:]], abs=1e-6)
    rel = tmp_path / "room.relations"
    rel.write_text(
        f"{TIMESTAMPS[0]} {TIMESTAMPS[-1]} 0.84 0.35 0 0 0 0.7\n{TIMESTAMPS[2]} {TIMESTAMPS[5]} 0.3 0.1 0 0 0 0.3\n"
    )
    scored = []
    for name in ("trajectory.txt", "corrected.log"):
        assert (
            main(
                [
                    "map",
                    "score",
                    "--trajectory",
                    str(out / name),
                    "--relations",
                    str(rel),
                    "--json",
                    str(tmp_path / "s.json"),
                ]
            )
            == 0
        )
        scored.append(json.loads((tmp_path / "s.json").read_text()))
    # The same poses, read back two ways (the log reader takes the laser's offset off again, which
    # wraps the heading: the last bit may differ).
    assert scored[0]["all"] == pytest.approx(scored[1]["all"], rel=1e-9, abs=1e-12)
    assert scored[0]["all"]["count"] == 2


def test_cli_replay_of_a_log_with_a_front_laser_offset_says_which_pose_it_writes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The room's log with its laser 0.25 m ahead of the robot: the FLASER x y theta are the laser's.
    lines = []
    for line in _log_lines():
        toks = line.split()
        if toks[:2] == ["PARAM", "robot_frontlaser_offset"]:
            line = "PARAM robot_frontlaser_offset 0.25 nohost 0"
        lines.append(line)
    log = tmp_path / "room.log"
    log.write_text("\n".join(lines) + "\n")
    assert main(["map", "replay", str(log), "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    assert "laser mounted at (0.250, 0.000) m, 0.0 deg on the robot: trajectory.txt holds the robot's pose" in printed
    rows = (tmp_path / "out" / "trajectory.txt").read_text().splitlines()
    again = [
        r
        for r in read_records((tmp_path / "out" / "corrected.log").read_text().splitlines())
        if isinstance(r, LaserRecord)
    ]
    # Both read back as the robot's pose, not the laser's 0.25 m ahead. The file holds six decimals: the
    # first triple is the laser's pose rounded, taken back by the offset turned through a rounded
    # heading, so the two agree to two roundings (5e-7 each) and the lever's 0.25 x 5e-7, not to 1e-6.
    for r, row in zip(again, rows, strict=True):
        assert r.odom == pytest.approx(tuple(float(v) for v in row.split()[1:]), abs=1e-6)
        assert (
            r.pose[:2] == pytest.approx(r.odom[:2], abs=2e-6)
            and abs(math.remainder(r.pose[2] - r.odom[2], 2 * math.pi)) < 2e-6
        )


def test_cli_replay_rejects_a_log_without_scans(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "empty.log"
    log.write_text("# nothing\nODOM 0 0 0 0 0 0 1.0 h 1.0\nGARBAGE\n")
    assert main(["map", "replay", str(log), "--out", str(tmp_path / "o")]) == 1
    assert "no usable scans" in capsys.readouterr().err


def _spied_replay(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[list[MapperConfig | None], Path]:
    """A room's log written, and the configurations ``fleetlink map replay`` hands the replay, as it runs."""
    from fleetlink.agent.mapping import replay as replay_module

    seen: list[MapperConfig | None] = []
    real = replay_module.replay

    def spy(records, config=None, **kw):  # type: ignore[no-untyped-def]
        seen.append(config)
        return real(records, config, **kw)

    monkeypatch.setattr(replay_module, "replay", spy)
    log = tmp_path / "room.log"
    log.write_text("\n".join(_log_lines()) + "\n")
    return seen, log


def test_cli_replay_long_loops_searches_each_submap_in_its_own_window(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--long-loops``: the closer of ``closure.long_loops`` (a window per submap, three checks a node),
    with ``--open-space`` too when both are asked; the same scans and timestamps written."""
    from fleetlink.agent.mapping.closure import long_loops, open_space

    seen, log = _spied_replay(tmp_path, monkeypatch)
    assert main(["map", "replay", str(log), "--out", str(tmp_path / "a"), "--long-loops"]) == 0
    assert main(["map", "replay", str(log), "--out", str(tmp_path / "b"), "--long-loops", "--open-space"]) == 0
    assert seen[0] is not None and seen[0].closer == long_loops()
    assert seen[1] is not None and seen[1].closer == long_loops(open_space())
    rows = [r.split()[0] for r in (tmp_path / "a" / "trajectory.txt").read_text().splitlines()]
    assert rows == TIMESTAMPS


def test_cli_replay_open_space_maps_with_filled_submaps(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--open-space``: the closer of ``closure.open_space`` (every submap filled, not only those that saw
    far walls); the same scans and timestamps, and a map of the same room."""
    from fleetlink.agent.mapping.closure import open_space

    seen, log = _spied_replay(tmp_path, monkeypatch)
    plain, wide = tmp_path / "plain", tmp_path / "wide"
    assert main(["map", "replay", str(log), "--out", str(plain)]) == 0
    assert main(["map", "replay", str(log), "--out", str(wide), "--open-space"]) == 0
    assert seen[0] is not None and seen[0].closer is not None and seen[0].closer.fill_from_range > 0.0
    assert seen[1] is not None and seen[1].closer == open_space()
    a = [r.split() for r in (plain / "trajectory.txt").read_text().splitlines()]
    b = [r.split() for r in (wide / "trajectory.txt").read_text().splitlines()]
    assert [r[0] for r in b] == [r[0] for r in a] == TIMESTAMPS
    for ra, rb in zip(a, b, strict=True):  # a small room: no closure either way, the same path to centimetres
        assert math.dist([float(v) for v in ra[1:3]], [float(v) for v in rb[1:3]]) < 0.05


def test_cli_replay_says_what_the_odometry_was_found_worth(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A log long enough for the final graph to learn its odometry's worth (20 matched steps or more):
    the summary says how many of its steps were weighed, and at what sd."""
    rc = Raycaster(ROOM)
    rng = np.random.default_rng(2)
    lines = ["PARAM robot_frontlaser_offset 0.0 nohost 0"]
    odom = (10.0, -3.0, 1.0)
    last = None
    for i in range(90):  # twice round a circle of 1.2 m about the room's middle, 4 degrees a scan
        a = math.radians(4.0 * i)
        pose = (3.0 + 1.2 * math.cos(a), 2.0 + 1.2 * math.sin(a), a + math.pi / 2)
        if last is not None:
            step = relative(last, pose)
            odom = compose(odom, (step[0] + rng.normal(0, 0.005), step[1] + rng.normal(0, 0.005), step[2]))
        last = pose
        lines.append(_flaser(rc, pose, odom, f"{1000 + 0.2 * i:.1f}"))
    log = tmp_path / "circle.log"
    log.write_text("\n".join(lines) + "\n")
    assert main(["map", "replay", str(log), "--out", str(tmp_path / "out")]) == 0
    said = capsys.readouterr().out
    m = re.search(r"the odometry's (\d+) steps held at (\d+\.\d) cm", said)
    assert m is not None, said
    assert int(m.group(1)) >= 20 and 0.2 <= float(m.group(2)) < 5.0
