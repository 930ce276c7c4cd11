"""bench/mapping.py --freiburg: a folder of published logs and relation files, replayed and scored.
A small constructed log (tests/test_mapping_replay.py's room) and a relation file written from its
true poses stand in for the benchmark's files, which are not in this repository."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from fleetlink.agent.mapping.relations import Relation, format_relations, relation
from tests.harness.bench import load_bench
from tests.test_mapping_replay import TIMESTAMPS, _log_lines, _poses


def _bench():  # type: ignore[no-untyped-def]
    return load_bench("mapping")


def test_published_logs_are_found_replayed_and_scored(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "room.clf").write_text("\n".join(_log_lines()) + "\n")
    poses, times = _poses(), [float(t) for t in TIMESTAMPS]
    pairs = [(0, 1), (1, 2), (2, 5), (0, 7)]
    rels = [Relation(times[i], times[j], *relation(poses[i], poses[j])) for i, j in pairs]
    (tmp_path / "room.relations").write_text(format_relations(rels))
    (tmp_path / "orphan.relations").write_text(format_relations(rels))  # no log beside it: skipped
    bench = _bench()
    assert [name for name, _, _ in bench.freiburg_logs(tmp_path)] == ["room"]
    out = tmp_path / "figures.json"
    assert bench.main(["--freiburg", str(tmp_path), "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    # Which BLAS kernels computed the figures goes with them (shared/blas.py).
    assert figures["openblas_coretype"] == os.environ.get("OPENBLAS_CORETYPE")
    room = figures["freiburg"]["room"]
    assert room["scans"] == len(TIMESTAMPS) and room["relations"] == len(pairs)
    for key in ("mapper", "mapper_online", "no_closure", "odometry"):
        assert room[key]["pairs"] == len(pairs) and room[key]["missing"] == 0
    # The mapper recovers the room's path; the log's odometry, in a frame of its own and slightly off, does not.
    assert room["mapper"]["trans_mean_m"] < 0.02 < room["odometry"]["trans_mean_m"]
    printed = capsys.readouterr().out
    assert "orphan.relations: no log beside it, skipped" in printed and "room" in printed
    assert bench.main(["--freiburg", str(tmp_path / "nothing-here")]) == 1
    # --open-space: every submap filled; the same room, the same answer within centimetres.
    wide = tmp_path / "open.json"
    assert bench.main(["--freiburg", str(tmp_path), "--open-space", "--json", str(wide)]) == 0
    figures = json.loads(wide.read_text())
    assert figures["open_space"] is True and json.loads(out.read_text())["open_space"] is False
    assert figures["freiburg"]["room"]["mapper"]["trans_mean_m"] < 0.02
    assert "every submap filled (--open-space)" in capsys.readouterr().out
    # --long-loops: the closer of fleetlink map replay --long-loops, with --open-space too when both are asked.
    loops = tmp_path / "loops.json"
    assert bench.main(["--freiburg", str(tmp_path), "--long-loops", "--open-space", "--json", str(loops)]) == 0
    figures = json.loads(loops.read_text())
    assert figures["long_loops"] is True and figures["open_space"] is True
    assert figures["freiburg"]["room"]["mapper"]["trans_mean_m"] < 0.02
    assert "three checks a node (--long-loops)" in capsys.readouterr().out


def test_the_bench_replays_with_the_closer_the_cli_would_use() -> None:
    from fleetlink.agent.mapping.closure import long_loops, open_space
    from fleetlink.agent.mapping.mapper import MapperConfig

    bench = _bench()
    assert bench._replay_config(False) == MapperConfig()
    assert bench._replay_config(False, True).closer == long_loops()
    assert bench._replay_config(True, True).closer == long_loops(open_space())


def _room_records():  # type: ignore[no-untyped-def]
    from fleetlink.agent.mapping.carmen import LaserRecord, read_records

    return [r for r in read_records(_log_lines()) if isinstance(r, LaserRecord)]


def test_a_relation_file_made_in_steps_of_the_odometry_is_seen_so() -> None:
    """``published_reference``: relations made by moving the log's odometry in 5 cm steps along the
    first scan's heading (as aces' and MIT CSAIL's files are) all lie on that grid, their times
    written to five decimals as MIT CSAIL's are (the log's to six); the scans, matched again, find the
    true relations, each rounded to that grid as a person stepping from the odometry would have.
    Relations from the true poses lie on no such grid."""
    bench = _bench()
    recs = _room_records()
    times, truth = [r.timestamp for r in recs], _poses()
    pairs = [(0, 1), (1, 2), (2, 3), (3, 5), (0, 2), (4, 6), (5, 7)]
    stepped, rounding = [], []
    for i, j in pairs:
        odo, true = relation(recs[i].odom, recs[j].odom), relation(truth[i], truth[j])
        k = round((true[0] - odo[0]) / 0.05)  # the step nearest the truth along the first scan's heading
        rounding.append(abs(true[0] - (odo[0] + 0.05 * k)))
        stepped.append(Relation(times[i] + 4e-6, times[j] - 3e-6, odo[0] + 0.05 * k, odo[1], odo[2]))
    made = bench.published_reference(recs, stepped, truth)
    assert made["relations_on_the_log"] == len(pairs)
    assert made["on_5cm_step_share"] == 1.0 and made["on_1cm_step_share"] == 1.0 and made["step_m"] == 0.05
    kept = made["kept"]
    assert kept >= 3 and made["scans_same_step_share"] == 1.0
    assert made["unjudged"]["pairs"] == len(pairs) - kept
    if kept == len(pairs):  # every pair judged: the scans' rounding is the hand-computed one
        assert made["scans_rounding_m"] == pytest.approx(sum(rounding) / len(rounding), abs=2e-3)
    true_rels = [Relation(times[i], times[j], *relation(truth[i], truth[j])) for i, j in pairs]
    seen = bench.published_reference(recs, true_rels, truth)
    assert seen["on_5cm_step_share"] < 0.5
    assert seen["kept"] >= 3 and seen["scans_vs_published_m"] < 0.01
    assert seen["mapper_vs_published_same_pairs_m"] < 1e-9


def test_a_raw_log_is_scored_on_the_complete_sets_of_its_corrected_subset(tmp_path: Path) -> None:
    """``raw_log_complete_sets``: a corrected subset of the log (every other scan, GMapping's way: the
    corrected pose in both of a FLASER line's poses, times of its own) is found in the raw log by its
    ranges, and the trajectory given is scored at those scans on the complete sets from its poses."""
    bench = _bench()
    raw = _room_records()
    lines = ["PARAM robot_frontlaser_offset 0.0 nohost 0"]
    for k, line in enumerate(ln for ln in _log_lines() if ln.startswith("FLASER 181 ") and len(ln.split()) > 100):
        if k % 2 == 0:
            toks = line.split()
            toks[-6:-3] = toks[-9:-6]  # odometry = the corrected pose
            ts = f"{50.0 + k:.3f}"
            toks[-3], toks[-1] = ts, ts
            lines.append(" ".join(toks))
    corrected = tmp_path / "room-corrected.log"
    corrected.write_text("\n".join(lines) + "\n")
    truth = _poses()
    out = bench.raw_log_complete_sets(raw, truth, corrected)
    assert out["corrected_scans"] == 4 and out["found"] == 4
    complete = out["mapper"]["complete"]
    assert complete["pairs"] > 0 and complete["missing"] == 0 and complete["trans_mean_m"] < 1e-9
    assert out["corrected_log"]["complete"]["trans_mean_m"] < 1e-9
    assert out["odometry"]["complete"]["trans_mean_m"] > 0.02  # the log's odometry drifts


def test_a_corrected_log_of_another_recording_is_not_scored(tmp_path: Path) -> None:
    """A corrected log of the same name whose scans are not in this raw log (another recording) is
    reported as found nowhere, and the bench goes on."""
    bench = _bench()
    raw = _room_records()
    other = [f"FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 {50 + k}.0 nohost {50 + k}.0" for k in range(3)]
    corrected = tmp_path / "room-corrected.log"
    corrected.write_text("\n".join(other) + "\n")
    out = bench.raw_log_complete_sets(raw, _poses(), corrected)
    assert out == {"corrected_scans": 3, "found": 0}
