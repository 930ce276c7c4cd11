"""Relations measured by matching their two scans (agent/mapping/pairmatch.py): the matcher against
known relative poses, the gates (a corridor seen along its length, a corridor whose walls repeat, a
match far from the reference), determinism, bad input, and ``fleetlink map relations --match``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fleetlink.agent.mapping.pairmatch import LineScan, PairMatchConfig, match_pair, match_relations
from fleetlink.agent.mapping.relations import Relation, parse_relations, relation
from fleetlink.cli.main import main
from fleetlink.field.raycast import Raycaster
from fleetlink.shared.se2 import compose, inverse

Pose = tuple[float, float, float]
FAN = -math.pi / 2 + math.pi / 180 * np.arange(181)  # a SICK: 181 beams over 180 deg
MAX_RANGE = 8.0

# A room with an alcove and a pillar: every direction is pinned.
ROOM = np.array(
    [
        [0.0, 0.0, 7.0, 0.0],
        [7.0, 0.0, 7.0, 1.5],
        [7.0, 1.5, 8.0, 1.5],
        [8.0, 1.5, 8.0, 3.0],
        [8.0, 3.0, 7.0, 3.0],
        [7.0, 3.0, 7.0, 5.0],
        [7.0, 5.0, 0.0, 5.0],
        [0.0, 5.0, 0.0, 0.0],
        [3.0, 2.0, 3.4, 2.0],
        [3.4, 2.0, 3.4, 2.4],
        [3.4, 2.4, 3.0, 2.4],
        [3.0, 2.4, 3.0, 2.0],
    ]
)
# A corridor 60 m long, 2 m wide, plain walls: nothing along it within the lidar's 8 m.
CORRIDOR = np.array([[-30.0, 0.0, 30.0, 0.0], [-30.0, 2.0, 30.0, 2.0]])


def _zigzag(y: float, period: float, depth: float, sign: float) -> list[list[float]]:
    xs = np.arange(-30.0, 30.0, period)
    segs = []
    for x in xs:
        segs.append([x, y, x + period / 2, y + sign * depth])
        segs.append([x + period / 2, y + sign * depth, x + period, y])
    return segs


# The same corridor with saw-toothed walls repeating every 0.4 m: any one step fits at any multiple.
SAWTOOTH = np.array(_zigzag(0.0, 0.4, 0.15, -1.0) + _zigzag(2.0, 0.4, 0.15, 1.0))


def _scan(rc: Raycaster, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    r = rc.cast_fan(pose[0], pose[1], pose[2] - math.pi / 2, math.pi / 180, 181, MAX_RANGE)
    return np.where(np.isfinite(r), r, MAX_RANGE), FAN.copy()


def _line_scan(rc: Raycaster, pose: Pose) -> LineScan:
    r, a = _scan(rc, pose)
    return LineScan.from_ranges(r, a, max_range=MAX_RANGE)


def test_match_pair_recovers_a_known_relative_pose() -> None:
    rc = Raycaster(ROOM)
    a, b = (1.5, 1.2, 0.2), (2.3, 1.7, 0.45)
    truth = relation(a, b)
    guess = (truth[0] + 0.15, truth[1] - 0.1, truth[2] + math.radians(3.0))
    m = match_pair(_line_scan(rc, a), _line_scan(rc, b), guess)
    assert m is not None
    assert math.hypot(m.pose[0] - truth[0], m.pose[1] - truth[1]) < 0.005
    assert abs(m.pose[2] - truth[2]) < math.radians(0.1)
    assert m.inliers > 0.8 * m.points and m.weakest > 20.0


def test_a_matched_relation_is_nearer_the_truth_than_its_noisy_reference() -> None:
    # A corrected log's poses scatter by a few centimetres; the scans do not.
    rc = Raycaster(ROOM)
    poses: list[Pose] = [(1.5, 1.2, 0.2), (2.3, 1.7, 0.45), (1.8, 3.5, -0.3)]
    times = [10.0, 11.0, 60.0]
    scans = [_scan(rc, p) for p in poses]
    noisy = [(1.54, 1.16, 0.21), (2.26, 1.74, 0.44), (1.84, 3.46, -0.31)]
    refs = [Relation(times[i], times[j], *relation(noisy[i], noisy[j])) for i, j in ((0, 1), (0, 2), (1, 2))]
    out = match_relations(refs, times, scans, max_range=MAX_RANGE)
    assert len(out.relations) == 3 and not out.refused
    for i, j, got, ref in zip((0, 0, 1), (1, 2, 2), out.relations, refs, strict=True):
        truth = relation(poses[i], poses[j])
        assert (got.t1, got.t2) == (ref.t1, ref.t2)
        assert math.hypot(got.dx - truth[0], got.dy - truth[1]) < 0.005
        assert math.hypot(ref.dx - truth[0], ref.dy - truth[1]) > 0.02
    assert "3 of 3 relations kept" in out.summary()


def test_a_corridor_seen_along_its_length_is_refused_as_ill_posed() -> None:
    rc = Raycaster(CORRIDOR)
    a, b = (0.0, 1.0, 0.0), (1.0, 1.0, 0.0)
    m = match_pair(_line_scan(rc, a), _line_scan(rc, b), relation(a, b))
    assert m is not None and m.weakest < PairMatchConfig().min_weakest
    assert abs(m.weak_axis[0]) > 0.99  # the weak direction is along the corridor
    out = match_relations([Relation(0.0, 1.0, *relation(a, b))], [0.0, 1.0], [_scan(rc, a), _scan(rc, b)])
    assert out.relations == [] and out.refused == {"ill-posed": 1}


def test_walls_that_repeat_make_a_pair_ambiguous() -> None:
    rc = Raycaster(SAWTOOTH)
    a, b = (0.0, 1.0, 0.0), (1.0, 1.0, 0.0)
    first, second = _line_scan(rc, a), _line_scan(rc, b)
    # Each fit alone is sharp: the teeth pin the step along the corridor...
    m = match_pair(first, second, relation(a, b))
    assert m is not None and m.weakest >= PairMatchConfig().min_weakest
    shifted = match_pair(first, second, (relation(a, b)[0] + 0.4, 0.0, 0.0))
    assert shifted is not None and abs(shifted.pose[0] - 1.4) < 0.01  # ...at every multiple of the period
    out = match_relations([Relation(0.0, 1.0, *relation(a, b))], [0.0, 1.0], [_scan(rc, a), _scan(rc, b)])
    assert out.relations == [] and out.refused == {"ambiguous": 1}
    # Without the probes the same pair would have been kept: the check is what refuses it.
    kept = match_relations(
        [Relation(0.0, 1.0, *relation(a, b))],
        [0.0, 1.0],
        [_scan(rc, a), _scan(rc, b)],
        config=PairMatchConfig(probe_m=()),
    )
    assert len(kept.relations) == 1


def test_a_match_far_from_the_reference_is_refused() -> None:
    rc = Raycaster(ROOM)
    a, b = (1.5, 1.2, 0.2), (2.3, 1.7, 0.45)
    truth = relation(a, b)
    off = Relation(0.0, 1.0, truth[0] + 0.1, truth[1], truth[2] + math.radians(5.0))  # the reference is wrong here
    out = match_relations([off], [0.0, 1.0], [_scan(rc, a), _scan(rc, b)])
    assert out.relations == [] and out.refused == {"far from the reference": 1}


def test_a_match_its_neighbours_do_not_bear_out_is_refused() -> None:
    # The scan at t=11 was taken 2 deg further round than the log says (a match elsewhere than the
    # pair's neighbours put it: the stand-in for a second fit the pair alone cannot rule out).
    rc = Raycaster(ROOM)
    logged: list[Pose] = [(1.5, 1.2, 0.2), (2.0, 1.5, 0.3), (2.2, 1.6, 0.4), (2.4, 1.7, 0.5)]
    scanned = list(logged)
    scanned[2] = (2.2, 1.6, 0.4 + math.radians(2.0))
    times = [0.0, 10.0, 11.0, 12.0]
    scans = [_scan(rc, p) for p in scanned]
    refs = [Relation(times[0], times[k], *relation(logged[0], logged[k])) for k in (1, 2, 3)]
    out = match_relations(refs, times, scans, max_range=MAX_RANGE)
    assert [(r.t1, r.t2) for r in out.relations] == [(0.0, 10.0), (0.0, 12.0)]
    assert out.refused == {"its neighbours disagree": 1}
    # Alone, the same pair is kept: nothing beside it to say otherwise.
    alone = match_relations(refs[1:2], times, scans, max_range=MAX_RANGE)
    assert len(alone.relations) == 1 and not alone.refused


def test_the_relation_is_halfway_between_the_two_ways() -> None:
    # With range noise the two ways' answers differ by millimetres: the relation is their midpoint,
    # the same whichever scan is called first.
    rc = Raycaster(ROOM)
    rng = np.random.default_rng(4)
    a, b = (1.5, 1.2, 0.2), (2.3, 1.7, 0.45)
    (ra, aa), (rb, ab) = _scan(rc, a), _scan(rc, b)
    ra, rb = ra + rng.normal(0.0, 0.01, ra.shape), rb + rng.normal(0.0, 0.01, rb.shape)
    z = relation(a, b)
    first, second = LineScan.from_ranges(ra, aa, max_range=MAX_RANGE), LineScan.from_ranges(rb, ab, max_range=MAX_RANGE)
    there, back = match_pair(first, second, z), match_pair(second, first, inverse(z))
    assert there is not None and back is not None
    other = inverse(back.pose)
    assert 1e-5 < math.hypot(there.pose[0] - other[0], there.pose[1] - other[1]) < 0.02
    out = match_relations([Relation(0.0, 1.0, *z)], [0.0, 1.0], [(ra, aa), (rb, ab)], max_range=MAX_RANGE)
    got = out.relations[0]
    for k, v in enumerate((got.dx, got.dy, got.dtheta)):
        assert v == pytest.approx((there.pose[k] + other[k]) / 2.0, abs=1e-6)
    # The two ways held to agree within a micrometre, the same pair is refused for it.
    strict = PairMatchConfig(agree_m=1e-6)
    refused = match_relations(
        [Relation(0.0, 1.0, *z)], [0.0, 1.0], [(ra, aa), (rb, ab)], max_range=MAX_RANGE, config=strict
    )
    assert refused.relations == [] and refused.refused == {"the two ways disagree": 1}


def test_a_mounted_sensor_gives_relations_between_the_robot_poses() -> None:
    rc = Raycaster(ROOM)
    mount = (0.3, 0.1, 0.2)
    poses: list[Pose] = [(1.5, 1.2, 0.2), (2.3, 1.7, 0.9)]
    scans = [_scan(rc, compose(p, mount)) for p in poses]
    z = relation(poses[0], poses[1])
    rough = Relation(0.0, 1.0, z[0] + 0.05, z[1] - 0.04, z[2] + 0.02)
    on = match_relations([rough], [0.0, 1.0], scans, max_range=MAX_RANGE, mount=mount).relations
    assert len(on) == 1 and math.hypot(on[0].dx - z[0], on[0].dy - z[1]) < 0.005
    assert abs(on[0].dtheta - z[2]) < math.radians(0.1)
    # Taken as if the sensor sat at the robot's centre, the same scans give the sensors' relation.
    off = match_relations([rough], [0.0, 1.0], scans, max_range=MAX_RANGE).relations
    assert off and math.hypot(off[0].dx - z[0], off[0].dy - z[1]) > 0.05


def test_neighbours_of_the_second_kind_judge_a_pair_too() -> None:
    # The first scans differ (three poses 0.2 m apart), the second is shared and faces another way:
    # (i, j) is predicted from (i +- 1, j) through the reference's step i -> i +- 1.
    rc = Raycaster(ROOM)
    logged: list[Pose] = [(1.5, 1.2, 0.2), (1.7, 1.3, 0.3), (1.9, 1.4, 0.4), (4.0, 3.6, -2.0)]
    scanned = list(logged)
    scanned[1] = (1.7, 1.3, 0.3 + math.radians(2.0))
    times = [0.0, 1.0, 2.0, 30.0]
    scans = [_scan(rc, p) for p in scanned]
    refs = [Relation(times[k], times[3], *relation(logged[k], logged[3])) for k in (0, 1, 2)]
    out = match_relations(refs, times, scans, max_range=MAX_RANGE)
    assert [(r.t1, r.t2) for r in out.relations] == [(0.0, 30.0), (2.0, 30.0)]
    assert out.refused == {"its neighbours disagree": 1}


def test_repeats_and_odd_beams() -> None:
    rc = Raycaster(ROOM)
    poses: list[Pose] = [(1.5, 1.2, 0.2), (2.3, 1.7, 0.45)]
    scans = [_scan(rc, p) for p in poses]
    rel = Relation(0.0, 1.0, *relation(poses[0], poses[1]))
    out = match_relations([rel, rel, Relation(1.0, 1.0, 0.0, 0.0, 0.0)], [0.0, 1.0], scans, max_range=MAX_RANGE)
    assert len(out.relations) == 1 and out.refused == {"a repeat": 1, "one scan at both times": 1}
    assert "1 of 3 relations kept" in out.summary()
    r, a = scans[0]
    a = a.copy()
    a[10] = np.nan  # a beam without an angle is dropped, not fed to the tree
    assert (
        len(LineScan.from_ranges(r, a, max_range=MAX_RANGE).points)
        == len(LineScan.from_ranges(r, scans[0][1], max_range=MAX_RANGE).points) - 1
    )


def test_match_relations_is_deterministic() -> None:
    rc = Raycaster(ROOM)
    poses: list[Pose] = [(1.0 + 0.4 * k, 1.0 + 0.25 * k, 0.1 * k) for k in range(8)]
    times = [float(k) for k in range(8)]
    scans = [_scan(rc, p) for p in poses]
    refs = [Relation(times[i], times[j], *relation(poses[i], poses[j])) for i in range(8) for j in range(i + 1, 8)]
    one = match_relations(refs, times, scans, max_range=MAX_RANGE)
    two = match_relations(refs, times, scans, max_range=MAX_RANGE)
    assert one.relations == two.relations and one.refused == two.refused
    assert len(one.relations) > 10


def test_bad_input_is_refused_or_counted() -> None:
    rc = Raycaster(ROOM)
    r, a = _scan(rc, (1.5, 1.2, 0.2))
    with pytest.raises(ValueError, match="one length"):
        LineScan.from_ranges(r, a[:-1])
    with pytest.raises(ValueError, match="differ in length"):
        match_relations([], [0.0, 1.0], [(r, a)])
    # A relation whose time has no scan is counted, not guessed at; NaN and zero readings are no return.
    holes = np.where(np.arange(len(r)) % 7 == 0, np.nan, r)
    holes[3] = 0.0
    out = match_relations([Relation(0.0, 5.0, 0.1, 0.0, 0.0)], [0.0, 1.0], [(holes, a), (r, a)])
    assert out.refused == {"no scan at its time": 1}
    assert len(LineScan.from_ranges(holes, a).points) == len(r) - 27


def test_cli_relations_match(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = Raycaster(ROOM)
    poses: list[Pose] = [(1.0 + 0.3 * k, 1.0 + 0.2 * k, 0.08 * k) for k in range(10)]
    lines = ["PARAM robot_frontlaser_offset 0.0 nohost 0"]
    for k, pose in enumerate(poses):
        r, _ = _scan(rc, pose)
        ranges = " ".join(f"{v:.3f}" for v in np.where(r >= MAX_RANGE, 81.91, r))
        # The corrected pose a little off, as a SLAM system's would be.
        p = f"{pose[0] + 0.02 * math.sin(k):.4f} {pose[1] + 0.02 * math.cos(k):.4f} {pose[2]:.4f}"
        lines.append(f"FLASER 181 {ranges} {p} {p} {100.0 + k:.6f} nohost {100.0 + k:.6f}")
    log = tmp_path / "room.log"
    log.write_text("\n".join(lines) + "\n")
    plain, matched = tmp_path / "plain.relations", tmp_path / "matched.relations"
    assert main(["map", "relations", "--log", str(log), "--out", str(plain)]) == 0
    assert main(["map", "relations", "--log", str(log), "--out", str(matched), "--match"]) == 0
    assert "relations kept by matching their scans" in capsys.readouterr().out
    by_pose = parse_relations(plain.read_text().splitlines())
    by_scan = parse_relations(matched.read_text().splitlines())
    assert 0 < len(by_scan) <= len(by_pose)

    def worst(rels: list[Relation]) -> float:
        return max(
            math.hypot(r.dx - t[0], r.dy - t[1])
            for r in rels
            for t in [relation(poses[int(r.t1 - 100.0)], poses[int(r.t2 - 100.0)])]
        )

    assert worst(by_pose) > 0.02 and worst(by_scan) < 0.01  # the scans' relations, not the poses' noise
