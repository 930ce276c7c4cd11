"""bench/mapping.py --corrected: a folder of corrected logs replayed on their own poses and scored
against complete relation sets, the default one and those made with other distances and overlaps.
tests/test_relations.py's two passes across a room stand in for the corrected logs, which are not in
this repository."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.harness.bench import load_bench
from tests.test_relations import _write_log


def test_corrected_logs_are_scored_against_sets_made_other_ways(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _write_log(tmp_path / "rooms-corrected.log")
    (tmp_path / "notes.txt").write_text("not a log")  # skipped: not *.log / *.clf
    bench = load_bench("mapping")
    out = tmp_path / "figures.json"
    assert bench.main(["--corrected", str(tmp_path), "--json", str(out)]) == 0
    rooms = json.loads(out.read_text())["corrected"]["rooms-corrected.log"]
    assert rooms["scans"] == 24
    rows = rooms["other_sets"]
    assert [(r["max_distance_m"], r["min_overlap_ratio"], r["facing_only"]) for r in rows] == list(bench.OTHER_SETS)
    both_faces = by_set_of(rows, False)[(3.0, 0.5)]
    by_set = by_set_of(rows, True)
    # The first table's set is one of them: the same relations, the same figures.
    default = by_set[(3.0, 0.5)]
    # Counting the far faces of surfaces as seen never pairs fewer scans.
    assert both_faces["relations"] >= default["relations"]
    assert default["mapper"] == rooms["mapper"]["complete"]
    assert default["relations"] == rooms["mapper"]["complete"]["pairs"]
    for d in (1.0, 2.0, 3.0, 5.0):  # a looser overlap or a longer reach never pairs fewer scans
        assert by_set[(d, 0.3)]["relations"] >= by_set[(d, 0.5)]["relations"] >= by_set[(d, 0.7)]["relations"]
    assert by_set[(1.0, 0.5)]["relations"] < by_set[(5.0, 0.5)]["relations"]
    for r in rows:
        assert r["relations"] > 0 and r["mapper"]["missing"] == 0 and r["no_closure"]["missing"] == 0
        assert r["mapper"]["revisit"]["count"] > 0  # the second pass, 50 s on
        assert r["mapper"]["trans_mean_m"] < 0.05  # the room is mapped where the log's poses put it
    printed = capsys.readouterr().out
    assert "against complete sets made other ways" in printed and "heading" in printed


def by_set_of(rows: list[dict[str, object]], facing_only: bool) -> dict[tuple[object, object], dict[str, object]]:
    return {(r["max_distance_m"], r["min_overlap_ratio"]): r for r in rows if r["facing_only"] is facing_only}
