"""Relation errors (agent/mapping/relations.py) against hand-computed cases, the text formats, the
complete relation set on a synthetic loop, and ``fleetlink map relations`` / ``map score``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from fleetlink.agent.mapping.relations import (
    ErrorStats,
    Relation,
    align_se2,
    format_relations,
    format_score,
    generate_relations,
    parse_relations,
    parse_trajectory,
    relation,
    score,
    transform_xy,
    view_overlap,
)
from fleetlink.agent.mapping.replay import format_trajectory
from fleetlink.cli.main import main
from fleetlink.field.raycast import Raycaster

Pose = tuple[float, float, float]

# -- relation ----------------------------------------------------------------------------------------


def test_relation_by_hand() -> None:
    # p1 faces +y; p2 is 1 m along +y from it, i.e. 1 m straight ahead, and turned another 90 deg.
    assert relation((1.0, 2.0, math.pi / 2), (1.0, 3.0, math.pi)) == pytest.approx((1.0, 0.0, math.pi / 2))
    # The other way round: p2 faces -x, so its left is -y, where p1 lies 1 m away.
    assert relation((1.0, 3.0, math.pi), (1.0, 2.0, math.pi / 2)) == pytest.approx((0.0, 1.0, -math.pi / 2))
    assert relation((0.0, 0.0, 3.0), (0.0, 0.0, -3.0)) == pytest.approx((0.0, 0.0, 2 * math.pi - 6.0))  # wrapped


# -- formats -----------------------------------------------------------------------------------------


def test_relations_round_trip_bit_for_bit() -> None:
    rels = [
        Relation(976052857.136133, 976052859.141109, 0.005676, -0.000366, -0.002856),
        Relation(1.0 / 3.0, 2.0 / 3.0, 1e-9, -12345.678901234, math.pi),
        Relation(0.0, 1e6, -0.1, 0.2, -math.pi + 1e-12),
    ]
    text = format_relations(rels)
    assert parse_relations(text.splitlines()) == rels
    assert text.splitlines()[0].split()[4:7] == ["0", "0", "0"]  # z, roll, pitch


def test_parse_relations_skips_comments_and_uses_x_y_yaw() -> None:
    lines = ["# t1 t2 x y z roll pitch yaw", "", "   ", "10.5 12.25 1 2 9 0.1 0.2 0.3", "\t20 21 -1 -2 0 0 0 -0.5  "]
    assert parse_relations(lines) == [Relation(10.5, 12.25, 1.0, 2.0, 0.3), Relation(20.0, 21.0, -1.0, -2.0, -0.5)]


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        ("1 2 3 4 5 6 7", "line 3: expected 8 fields (t1 t2 x y z roll pitch yaw), found 7"),
        ("1 2 3 4 5 6 7 8 9", "line 3: expected 8 fields (t1 t2 x y z roll pitch yaw), found 9"),
        ("1 2 3 abc 0 0 0 0", "line 3: y is not a number: 'abc'"),
        ("1 2 3 4 0 0 0 nan", "line 3: yaw is not finite: 'nan'"),
        ("inf 2 3 4 0 0 0 0", "line 3: t1 is not finite: 'inf'"),
    ],
)
def test_parse_relations_names_the_line_and_the_reason(bad: str, message: str) -> None:
    with pytest.raises(ValueError) as exc:
        parse_relations(["# header", "1 2 0 0 0 0 0 0", bad, "3 4 0 0 0 0 0 0"])
    assert str(exc.value) == message


def test_parse_trajectory_reads_what_replay_writes() -> None:
    rows = [("1000.000100", (1.0, 2.0, 0.5)), ("1000.2", (-1.25, 0.0, -3.0))]
    times, poses = parse_trajectory(format_trajectory(rows).splitlines())
    assert times == [1000.0001, 1000.2]
    assert poses == [(1.0, 2.0, 0.5), (-1.25, 0.0, -3.0)]
    with pytest.raises(ValueError, match="line 2: expected 4 fields"):
        parse_trajectory(["1 0 0 0", "2 0 0"])
    with pytest.raises(ValueError, match=r"line 1: theta is not a number: 'x'"):
        parse_trajectory(["1 0 0 x"])


# -- score -------------------------------------------------------------------------------------------


def _loop(laps: int = 2, step: float = 0.5) -> tuple[list[float], list[Pose]]:
    """A 8 m x 4 m rectangle driven anticlockwise, one pose every `step` metres and second."""
    corners = [(0.0, 0.0), (8.0, 0.0), (8.0, 4.0), (0.0, 4.0)]
    poses: list[Pose] = []
    for _ in range(laps):
        for k in range(4):
            (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % 4]
            heading = math.atan2(y1 - y0, x1 - x0)
            n = round(math.hypot(x1 - x0, y1 - y0) / step)
            poses += [(x0 + (x1 - x0) * i / n, y0 + (y1 - y0) * i / n, heading) for i in range(n)]
    return [float(i) for i in range(len(poses))], poses


def test_a_perfect_trajectory_scores_zero_in_any_frame() -> None:
    times, poses = _loop()
    rels = generate_relations(times, poses)
    result = score(times, poses, rels)
    assert result.count == len(rels) > 100 and result.missing == 0
    assert result.all.trans_max_m == pytest.approx(0.0, abs=1e-12)
    assert result.all.rot_max_rad == pytest.approx(0.0, abs=1e-12)
    # Relations compare relative poses only: the same path in another frame scores zero too.
    c, s, th = math.cos(2.0), math.sin(2.0), 2.0
    moved = [(10.0 + c * x - s * y, -5.0 + s * x + c * y, th + t) for x, y, t in poses]
    shifted = score(times, moved, rels)
    assert shifted.all.trans_max_m == pytest.approx(0.0, abs=1e-9)
    assert shifted.all.rot_max_rad == pytest.approx(0.0, abs=1e-9)


def test_a_heading_error_at_one_pose_by_hand() -> None:
    times = [0.0, 1.0, 2.0]
    ref: list[Pose] = [(0.0, 0.0, 0.0), (2.0, 0.0, 0.0), (2.0, 2.0, math.pi / 2)]
    rels = [Relation(times[i], times[j], *relation(ref[i], ref[j])) for i, j in ((0, 1), (1, 2), (0, 2))]
    est = [ref[0], (2.0, 0.0, 0.1), ref[2]]  # 0.1 rad off at the middle pose only
    result = score(times, est, rels)
    # 0 -> 1: the end pose is turned: 0 m, 0.1 rad.
    # 1 -> 2: the start pose is turned, so the 2 m to the end swing by 0.1 rad: a chord of
    #         2 * 2 m * sin(0.05) = 0.19992 m, and 0.1 rad.
    # 0 -> 2: untouched: 0 m, 0 rad.
    chord = 4.0 * math.sin(0.05)
    assert chord == pytest.approx(0.199917, abs=1e-6)
    a = result.all
    assert a.count == 3
    assert a.trans_mean_m == pytest.approx(chord / 3)
    assert a.trans_std_m == pytest.approx(math.sqrt(2.0) / 3.0 * chord)  # population sd of (0, c, 0)
    assert a.trans_sq_mean_m2 == pytest.approx(chord**2 / 3)
    assert a.trans_max_m == pytest.approx(chord)
    assert a.rot_mean_rad == pytest.approx(0.2 / 3)
    assert a.rot_std_rad == pytest.approx(math.sqrt(2.0) / 3.0 * 0.1)
    assert a.rot_mean_deg == pytest.approx(math.degrees(0.2 / 3))
    assert a.rot_max_rad == pytest.approx(0.1)


def test_rotational_error_wraps() -> None:
    rel = Relation(0.0, 1.0, 1.0, 0.0, math.pi - 0.01)
    result = score([0.0, 1.0], [(0.0, 0.0, 0.0), (1.0, 0.0, -math.pi + 0.01)], [rel])
    assert result.all.rot_mean_rad == pytest.approx(0.02)


def test_local_and_revisit_split() -> None:
    times = [0.0, 10.0, 30.0, 100.0]
    poses: list[Pose] = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1.0, 0.5), (0.0, 0.5, 1.0)]

    def rel(i: int, j: int, ex: float, ey: float, eth: float) -> Relation:
        dx, dy, dth = relation(poses[i], poses[j])
        return Relation(times[i], times[j], dx - ex, dy - ey, dth - eth)  # reference off by a known error

    rels = [
        rel(0, 1, 0.1, 0.0, 0.0),  # 10 s: local
        rel(1, 2, 0.3, 0.0, 0.0),  # 20 s: not below 20 s, a revisit
        rel(2, 3, 0.0, 0.4, 0.02),  # 70 s: revisit
        rel(0, 3, 0.0, -0.5, -0.04),  # 100 s: revisit
    ]
    result = score(times, poses, rels, local_s=20.0)
    assert (result.count, result.local.count, result.revisit.count) == (4, 1, 3)
    assert result.local.trans_mean_m == pytest.approx(0.1)
    assert result.local.rot_mean_rad == pytest.approx(0.0)
    assert result.revisit.trans_mean_m == pytest.approx(0.4)
    assert result.revisit.trans_max_m == pytest.approx(0.5)
    assert result.revisit.rot_mean_rad == pytest.approx(0.02)
    assert result.all.trans_mean_m == pytest.approx(0.325)
    assert score(times, poses, rels, local_s=25.0).local.count == 2


def test_relations_at_times_not_in_the_trajectory_are_counted_missing() -> None:
    times = [0.0, 1.0, 2.0]
    poses: list[Pose] = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (2.0, 0.0, 0.0)]
    rels = [
        Relation(0.0, 1.0, 1.0, 0.0, 0.0),
        Relation(1.0004, 2.0, 1.0, 0.0, 0.0),  # within the 1 ms tolerance: the pose at 1.0
        Relation(0.0, 1.5, 1.5, 0.0, 0.0),  # no pose at 1.5
        Relation(-3.0, 2.0, 2.0, 0.0, 0.0),  # before the trajectory
        Relation(2.0, 7.0, 5.0, 0.0, 0.0),  # after it
    ]
    result = score(times, poses, rels)
    assert (result.count, result.missing) == (2, 3)
    assert result.all.trans_max_m == pytest.approx(0.0)
    assert score(times, poses, rels, tolerance_s=0.0).missing == 4
    # Trajectory times may come in any order.
    assert score(times[::-1], poses[::-1], rels).count == 2


def test_generate_relations_refuses_indistinct_times() -> None:
    # A corrected log written with %g stamps: every scan at "1.01893e+09".
    with pytest.raises(ValueError, match=r"times 1018930000\.0 and 1018930000\.0 are less than 1e-06 s apart \(2 such"):
        generate_relations([1.01893e09] * 3, [(0.0, 0.0, 0.0), (0.5, 0.0, 0.0), (1.0, 0.0, 0.0)])


def test_score_refuses_a_trajectory_with_indistinct_times() -> None:
    with pytest.raises(ValueError, match=r"trajectory times 1\.0 and 1\.0000004 are less than 1e-06 s apart"):
        score([0.0, 1.0, 1.0000004], [(0.0, 0.0, 0.0)] * 3, [])
    with pytest.raises(ValueError, match="differ in length"):
        score([0.0, 1.0], [(0.0, 0.0, 0.0)], [])


def test_scans_nearer_than_the_tolerance_each_keep_their_own_relations() -> None:
    # The published intel.clf has FLASER lines 6 us apart (IPC stamps of a burst): the nearest time
    # decides, and a relation time equally near two (to the microsecond) is not guessed.
    times = [0.0, 1.0, 1.000006, 2.0]
    poses: list[Pose] = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (1.5, 0.0, 0.0), (2.0, 0.0, 0.0)]
    rels = [
        Relation(0.0, 1.0, 1.0, 0.0, 0.0),
        Relation(0.0, 1.000006, 1.5, 0.0, 0.0),
        Relation(1.000006, 2.0, 0.5, 0.0, 0.0),
        Relation(0.0, 1.000003, 1.0, 0.0, 0.0),  # as near to both: missing
    ]
    result = score(times, poses, rels)
    assert (result.count, result.missing) == (3, 1)
    assert result.all.trans_max_m == pytest.approx(0.0)


def test_an_empty_set_has_no_figures() -> None:
    result = score([0.0, 1.0], [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)], [Relation(0.0, 1.0, 1.0, 0.0, 0.0)])
    assert result.revisit.count == 0 and math.isnan(result.revisit.trans_mean_m)
    d = result.as_dict()
    assert d["revisit"] == {k: (0 if k == "count" else None) for k in d["revisit"]}  # type: ignore[union-attr]
    json.dumps(d, allow_nan=False)
    assert "revisit (>= 20 s)" in format_score(result)


def test_error_stats_of_known_values() -> None:
    s = ErrorStats.of(np.array([0.0, 0.2]), np.array([0.1, 0.3]))
    assert (s.count, s.trans_mean_m, s.trans_std_m, s.trans_max_m) == (2, pytest.approx(0.1), pytest.approx(0.1), 0.2)
    assert s.trans_sq_mean_m2 == pytest.approx(0.02)
    assert (s.rot_mean_rad, s.rot_std_rad, s.rot_sq_mean_rad2) == (
        pytest.approx(0.2),
        pytest.approx(0.1),
        pytest.approx(0.05),
    )


# -- the complete relation set -----------------------------------------------------------------------


def test_generate_relations_pairs_revisits_within_the_distance_limit() -> None:
    times, poses = _loop(laps=2)  # 48 poses a lap, 1 s apart
    rels = generate_relations(times, poses, max_distance_m=1.0)
    at = {t: p for t, p in zip(times, poses, strict=True)}
    for r in rels:
        p1, p2 = at[r.t1], at[r.t2]
        assert math.hypot(p2[0] - p1[0], p2[1] - p1[1]) <= 1.0 + 1e-9
        assert abs(math.remainder(p2[2] - p1[2], 2 * math.pi)) <= math.pi / 2 + 1e-9
        assert (r.dx, r.dy, r.dtheta) == relation(p1, p2)
        assert r.t1 < r.t2
    spans = {r.t2 - r.t1 for r in rels}
    assert 1.0 in spans and 2.0 in spans  # neighbours on the same side
    assert 48.0 in spans  # the same place a lap later
    assert 50.0 in spans  # and 1 m further on
    # Close but facing opposite ways: the views do not overlap.
    assert generate_relations([0.0, 1.0], [(0.0, 0.0, 0.0), (0.5, 0.0, math.pi)]) == []


def test_generate_relations_is_deterministic_and_capped_by_stride() -> None:
    times, poses = _loop(laps=2)
    full = generate_relations(times, poses)
    assert full == generate_relations(times, poses)
    assert [(r.t1, r.t2) for r in full] == sorted((r.t1, r.t2) for r in full)  # log order: by t1, then t2
    capped = generate_relations(times, poses, max_relations=100)
    stride = math.ceil(len(full) / 100)
    assert capped == full[::stride] and len(capped) <= 100
    assert generate_relations(times, poses, max_relations=len(full)) == full


def test_generate_relations_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="differ in length"):
        generate_relations([0.0, 1.0], [(0.0, 0.0, 0.0)])
    with pytest.raises(ValueError, match="max_distance_m must be > 0"):
        generate_relations([0.0], [(0.0, 0.0, 0.0)], max_distance_m=0.0)
    with pytest.raises(ValueError, match=r"min_overlap must be within 0\.\.1"):
        generate_relations([0.0], [(0.0, 0.0, 0.0)], min_overlap=1.5)


# Two 4 m x 4 m rooms side by side, a solid wall between them at x = 4.
ROOMS = np.array(
    [
        [0.0, 0.0, 8.0, 0.0],
        [8.0, 0.0, 8.0, 4.0],
        [8.0, 4.0, 0.0, 4.0],
        [0.0, 4.0, 0.0, 0.0],
        [4.0, 0.0, 4.0, 4.0],
    ]
)
FAN = -math.pi / 2 + math.pi / 180 * np.arange(181)  # a SICK: 181 beams, -90 .. +90 deg


def _scan(rc: Raycaster, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    r = rc.cast_fan(pose[0], pose[1], pose[2] - math.pi / 2, math.pi / 180, 181, 30.0)
    return np.where(np.isfinite(r), r, 30.0), FAN.copy()


def test_view_overlap_sees_through_free_space_but_not_through_walls() -> None:
    rc = Raycaster(ROOMS)
    a, same_room, next_room = (2.0, 2.0, 0.0), (3.0, 2.5, 0.3), (4.6, 2.0, 0.0)
    sa, sb, sc = _scan(rc, a), _scan(rc, same_room), _scan(rc, next_room)
    assert view_overlap(a, sa, a, sa, max_range=30.0) == 1.0
    assert view_overlap(a, sa, same_room, sb, max_range=30.0) > 0.8
    # 2.6 m apart, same heading: close enough, but the wall hides each room from the other.
    assert view_overlap(a, sa, next_room, sc, max_range=30.0) < 0.1
    # Back to back in the same room: each sees what lies behind the other.
    west, east = (1.0, 2.0, math.pi), (3.0, 2.0, 0.0)
    assert view_overlap(west, _scan(rc, west), east, _scan(rc, east), max_range=30.0) == 0.0
    # A sensor mounted 0.5 m ahead of the robot: the same poses, the views move with it.
    assert view_overlap(a, sa, a, sa, max_range=30.0, mount=(0.5, 0.0, 0.0)) == 1.0


def test_generate_relations_with_scans_drops_pairs_that_do_not_see_each_other() -> None:
    rc = Raycaster(ROOMS)
    times = [0.0, 1.0, 2.0]
    poses: list[Pose] = [(3.0, 2.0, 0.0), (3.5, 2.2, 0.1), (4.6, 2.0, 0.0)]
    blind = generate_relations(times, poses)
    assert {(r.t1, r.t2) for r in blind} == {(0.0, 1.0), (0.0, 2.0), (1.0, 2.0)}
    seeing = generate_relations(times, poses, scans=[_scan(rc, p) for p in poses], max_range=30.0)
    assert {(r.t1, r.t2) for r in seeing} == {(0.0, 1.0)}


# ROOMS with the wall between them 0.1 m thick (its faces at x = 4.0 and x = 4.1): thinner than the
# occlusion margin, so each room's scans find the other face within it, 0.1 m behind their own.
PARTITION = np.vstack((ROOMS, [[4.1, 0.0, 4.1, 4.0]]))


def test_two_faces_of_a_thin_partition_are_not_one_view() -> None:
    rc = Raycaster(PARTITION)
    west, east, also_west = (3.0, 2.0, 0.0), (5.1, 2.0, math.pi), (2.5, 1.5, 0.3)
    sw, se, sa = _scan(rc, west), _scan(rc, east), _scan(rc, also_west)
    # 2.1 m apart, each facing the partition: the far face lies 0.1 m behind what each one sees.
    assert view_overlap(west, sw, east, se, max_range=30.0, facing_only=False) > 0.6
    assert view_overlap(west, sw, east, se, max_range=30.0) < 0.05
    # The same face seen from two places on its own side is one view.
    assert view_overlap(west, sw, also_west, sa, max_range=30.0) > 0.8
    times = [0.0, 1.0, 2.0]
    poses: list[Pose] = [west, also_west, east]
    scans = [sw, sa, se]
    both_faces = generate_relations(times, poses, scans=scans, max_range=30.0, facing_only=False)
    assert {(r.t1, r.t2) for r in both_faces} == {(0.0, 1.0), (0.0, 2.0), (1.0, 2.0)}
    seeing = generate_relations(times, poses, scans=scans, max_range=30.0)
    assert {(r.t1, r.t2) for r in seeing} == {(0.0, 1.0)}


# -- the CLI -----------------------------------------------------------------------------------------

# Two passes across the left room, the second 50 s after the first and 1 m to the side of it.
TIMES = [f"{100.0 + 0.5 * i:.6f}" for i in range(12)] + [f"{150.0 + 0.5 * i:.6f}" for i in range(12)]


def _log_poses() -> list[Pose]:
    return [(0.8 + 0.2 * i, 1.5, 0.0) for i in range(12)] + [(0.8 + 0.2 * i, 2.5, 0.0) for i in range(12)]


def _write_log(path: Path, times: list[str] = TIMES, poses: list[Pose] | None = None) -> None:
    rc = Raycaster(ROOMS)
    lines = ["# synthetic corrected log", "PARAM robot_frontlaser_offset 0.0 nohost 0"]
    for ts, pose in zip(times, poses or _log_poses(), strict=True):
        r, _ = _scan(rc, pose)
        r = np.where(r >= 30.0, 81.91, r)  # no return, as a SICK reports it
        ranges = " ".join(f"{v:.3f}" for v in r)
        p = f"{pose[0]} {pose[1]} {pose[2]}"
        lines.append(f"FLASER 181 {ranges} {p} {p} {ts} nohost {ts}")
    path.write_text("\n".join(lines) + "\n")


def test_cli_relations_and_score(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log, rel_file = tmp_path / "rooms.log", tmp_path / "rooms.relations"
    _write_log(log)
    assert main(["map", "relations", "--log", str(log), "--out", str(rel_file), "--max-distance", "1.5"]) == 0
    out = capsys.readouterr().out
    rels = parse_relations(rel_file.read_text().splitlines())
    assert f"{len(rels)} relations from 24 scans" in out and "wrote" in out
    assert any(r.t2 - r.t1 >= 20.0 for r in rels)  # the second pass against the first
    assert all(math.hypot(r.dx, r.dy) <= 1.5 + 1e-9 for r in rels)

    # The log's own poses score zero; a trajectory with a heading error on the second pass does not.
    exact = tmp_path / "exact.txt"
    exact.write_text(format_trajectory(zip(TIMES, _log_poses(), strict=True)))
    js = tmp_path / "score.json"
    assert main(["map", "score", "--trajectory", str(exact), "--relations", str(rel_file), "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert f"{len(rels)} relations scored, 0 missing" in out
    doc = json.loads(js.read_text())
    assert doc["count"] == len(rels) and doc["missing"] == 0
    assert doc["all"]["trans_mean_m"] == pytest.approx(0.0, abs=1e-5)  # the trajectory's 6 decimals
    assert set(doc["local"]) >= {"count", "trans_mean_m", "trans_std_m", "trans_max_m", "rot_mean_rad", "rot_mean_deg"}

    bent = tmp_path / "bent.txt"
    poses = [(x, y, th + (0.05 if i >= 12 else 0.0)) for i, (x, y, th) in enumerate(_log_poses())]
    bent.write_text(format_trajectory(zip(TIMES[:-1], poses[:-1], strict=True)))  # the last scan missing
    assert main(["map", "score", "--trajectory", str(bent), "--relations", str(rel_file), "--json", str(js)]) == 0
    doc = json.loads(js.read_text())
    assert doc["missing"] >= 1 and doc["count"] + doc["missing"] == len(rels)
    assert doc["all"]["rot_max_rad"] == pytest.approx(0.05, abs=1e-5)
    assert doc["revisit"]["count"] > 0 and doc["revisit"]["rot_mean_rad"] == pytest.approx(0.05, abs=1e-5)
    assert doc["local"]["rot_max_rad"] == pytest.approx(0.0, abs=1e-5)  # within a pass: both poses alike
    assert "revisit (>= 20 s)" in capsys.readouterr().out


def test_cli_relations_min_overlap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A stricter overlap keeps a subset of the pairs (those whose views share more), a looser one a
    superset; each pair is the same relation whichever set holds it."""
    log = tmp_path / "rooms.log"
    # The second pass comes back the other way: its 180 degree views share less of the first pass's
    # the further behind them it is.
    poses = _log_poses()[:12] + [(3.0 - 0.2 * i, 2.5, math.pi) for i in range(12)]
    _write_log(log, poses=poses)
    sets = {}
    for share in ("0.0", "0.5", "0.9"):
        out = tmp_path / f"{share}.relations"
        argv = ["map", "relations", "--log", str(log), "--out", str(out), "--max-distance", "3", "--min-overlap", share]
        assert main(argv) == 0
        sets[share] = {(r.t1, r.t2): r for r in parse_relations(out.read_text().splitlines())}
    capsys.readouterr()
    assert set(sets["0.9"]) < set(sets["0.5"]) < set(sets["0.0"])
    assert all(sets["0.0"][k] == r for k, r in sets["0.9"].items())
    # Share 0 pairs every scan within the distance, views or not.
    near = sum(
        math.hypot(poses[j][0] - poses[i][0], poses[j][1] - poses[i][1]) <= 3.0
        for i in range(len(poses))
        for j in range(i + 1, len(poses))
    )
    assert len(sets["0.0"]) == near


def test_cli_score_and_relations_refuse_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    traj, rels = tmp_path / "t.txt", tmp_path / "r.txt"
    traj.write_text("1.0 0 0 0\n2.0 1 0 0\n")
    rels.write_text("1.0 2.0 1 0 0 0 0 0\n1.0 2.0 1 0\n")
    assert main(["map", "score", "--trajectory", str(traj), "--relations", str(rels)]) == 1
    assert f"fleetlink map score: cannot read {rels}: line 2: expected 8 fields" in capsys.readouterr().err
    assert main(["map", "score", "--trajectory", str(tmp_path / "none.txt"), "--relations", str(rels)]) == 1
    assert "cannot read" in capsys.readouterr().err
    rels.write_text("5.0 6.0 1 0 0 0 0 0\n")
    assert main(["map", "score", "--trajectory", str(traj), "--relations", str(rels)]) == 1
    assert "none of the 1 relations' times is in" in capsys.readouterr().err
    log = tmp_path / "l.log"
    _write_log(log)
    out = str(tmp_path / "o.rel")
    assert main(["map", "relations", "--log", str(log), "--out", out, "--max-distance", "-1"]) == 2
    assert "--max-distance must be a number of metres above 0" in capsys.readouterr().err
    for bad in ("1.5", "-0.1", "nan"):
        assert main(["map", "relations", "--log", str(log), "--out", out, "--min-overlap", bad]) == 2
        assert "--min-overlap must be a share within 0..1" in capsys.readouterr().err
    log.write_text("ODOM 0 0 0 0 0 0 1.0 h 1.0\n")
    assert main(["map", "relations", "--log", str(log), "--out", out]) == 1
    assert "fewer than two scans" in capsys.readouterr().err


def test_cli_names_scans_by_index_where_the_log_has_no_usable_times(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Corrected logs in circulation (belgioioso, csail: "%g" stamps; orebro, the Freiburg campus: 0)
    # give every scan one time; relations by time could not name them, so they are refused, and named
    # by their order in the log on request, the same order replay's outputs keep.
    log, rel_file = tmp_path / "zero.log", tmp_path / "zero.relations"
    _write_log(log, ["0"] * len(TIMES))
    assert main(["map", "relations", "--log", str(log), "--out", str(rel_file)]) == 1
    err = capsys.readouterr().err
    assert "scan times 0.0 and 0.0 are less than 1e-06 s apart (23 such neighbours)" in err
    assert "--by-index" in err and not rel_file.exists()

    assert main(["map", "relations", "--log", str(log), "--out", str(rel_file), "--by-index"]) == 0
    out = capsys.readouterr().out
    rels = parse_relations(rel_file.read_text().splitlines())
    assert "its times are scan indices" in out and f"{len(rels)} relations from 24 scans" in out
    assert all(r.t1 == int(r.t1) and 0 <= r.t1 < r.t2 <= 23 for r in rels)
    assert any(r.t2 >= 12 > r.t1 for r in rels)  # the second pass against the first

    # The log itself is a corrected log: scored by index it scores zero; by time it is refused.
    assert main(["map", "score", "--trajectory", str(log), "--relations", str(rel_file)]) == 1
    assert "name scans by index with --by-index" in capsys.readouterr().err
    js = tmp_path / "score.json"
    assert (
        main(["map", "score", "--trajectory", str(log), "--relations", str(rel_file), "--by-index", "--json", str(js)])
        == 0
    )
    out = capsys.readouterr().out
    assert f"{len(rels)} relations scored, 0 missing" in out and "revisit (>= 20 scans)" in out
    doc = json.loads(js.read_text())
    assert doc["by_index"] is True and doc["all"]["trans_max_m"] == pytest.approx(0.0, abs=1e-5)

    # A trajectory with its rows in the log's order, the second pass turned: the revisits see it.
    bent = tmp_path / "bent.txt"
    poses = [(x, y, th + (0.05 if i >= 12 else 0.0)) for i, (x, y, th) in enumerate(_log_poses())]
    bent.write_text(format_trajectory(zip(["0"] * len(TIMES), poses, strict=True)))
    assert (
        main(["map", "score", "--trajectory", str(bent), "--relations", str(rel_file), "--by-index", "--json", str(js)])
        == 0
    )
    doc = json.loads(js.read_text())
    assert doc["missing"] == 0 and doc["all"]["rot_max_rad"] == pytest.approx(0.05, abs=1e-5)


def test_the_ate_alignment_recovers_a_rigid_transform_by_hand() -> None:
    # Three points turned a quarter turn and moved by (2, -1): (0,0) -> (2,-1), (1,0) -> (2,0), (0,2) -> (0,-1).
    est = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 2.0, 0.0)]
    ref = [(2.0, -1.0, 0.0), (2.0, 0.0, 0.0), (0.0, -1.0, 0.0)]
    tf = align_se2(est, ref)
    assert tf == pytest.approx((2.0, -1.0, math.pi / 2))
    moved = transform_xy(tf, np.array([p[:2] for p in est]))
    assert moved == pytest.approx(np.array([p[:2] for p in ref]))
    with pytest.raises(ValueError, match="as many poses"):
        align_se2(est, ref[:2])
