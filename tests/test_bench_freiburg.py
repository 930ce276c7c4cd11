"""bench/mapping.py --freiburg: a folder of published logs and relation files, replayed and scored.
A small constructed log (tests/test_mapping_replay.py's room) and a relation file written from its
true poses stand in for the benchmark's files, which are not in this repository."""

from __future__ import annotations

import json
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
    room = json.loads(out.read_text())["freiburg"]["room"]
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
