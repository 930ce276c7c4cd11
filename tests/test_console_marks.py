"""The console's marks store (operator/marks.py): naming, saving, loading."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fleetlink.operator.marks import MarksStore, mark_from_record, mark_record
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import Mark


def header(robot: str = "r1", sender: str = "op-1", clock: SimClock | None = None) -> wire.Header:
    counter = wire.HeaderCounter(clock or SimClock(start=1000.0), robot=robot, sender=sender)
    return counter.header(Mark.TOPIC, robot=robot)


def test_new_marks_get_unique_ids_and_the_kind_as_a_missing_label(tmp_path: Path) -> None:
    store = MarksStore(tmp_path / "marks.json")
    a = store.new(header(), 1.0, 2.0, "casualty", "", wall=1712345678.9)
    b = store.new(header(), 3.0, 4.0, "hazard", "gas leak", wall=1712345678.9)
    assert (a.markId, b.markId) == ("op-1-1712345678-1", "op-1-1712345678-2")
    assert (a.label, a.kind, b.label, b.kind) == ("casualty", "casualty", "gas leak", "hazard")
    assert (a.x, a.y, a.removed, a.header.robot, a.header.sender) == (1.0, 2.0, False, "r1", "op-1")
    wire.encode(a)
    wire.encode(b)


def test_over_long_texts_are_cut_to_what_the_wire_allows() -> None:
    store = MarksStore(None)
    m = store.new(header(sender="o" * 60), 0.0, 0.0, "k" * 50, "l" * 100, wall=1e9)
    assert (len(m.markId), len(m.kind), len(m.label)) == (64, 32, 64)
    wire.encode(m)  # valid as sent


def test_saved_marks_load_back_the_same(tmp_path: Path) -> None:
    path = tmp_path / "marks.json"
    store = MarksStore(path)
    clock = SimClock(start=500.0)
    marks = [store.new(header("r1", clock=clock), 1.5, -2.0, "casualty", "victim", wall=10.0),
             store.new(header("r2", clock=clock), 0.0, 3.25, "hazard", "", wall=11.0)]  # fmt: skip
    store.save(marks)
    assert not path.with_suffix(".tmp").exists()  # written aside, then renamed over
    doc = json.loads(path.read_text())
    assert [r["markId"] for r in doc["marks"]] == [m.markId for m in marks]
    loaded = MarksStore(path).load()
    assert [mark_record(m) for m in loaded] == [mark_record(m) for m in marks]
    # Saving again replaces the file: a removed mark is gone from it.
    store.save(marks[1:])
    assert [m.markId for m in MarksStore(path).load()] == [marks[1].markId]


def test_no_path_no_file_nothing_to_load(tmp_path: Path) -> None:
    MarksStore(None).save([MarksStore(None).new(header(), 0, 0, "note", "", wall=1.0)])
    assert MarksStore(None).load() == []
    assert MarksStore(tmp_path / "absent.json").load() == []
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "text",
    [
        "not json",
        '["a list, not an object"]',
        '{"marks": [{"markId": "m1"}]}',  # fields missing
        '{"marks": [{"markId": "m1", "x": "east", "y": 0, "label": "", "kind": "k", "by": "o", "robot": "r", "timestamp": 1}]}',
        '{"marks": [{"markId": "m1", "x": NaN, "y": 0, "label": "", "kind": "k", "by": "o", "robot": "r", "timestamp": 1}]}',
    ],
)
def test_a_bad_file_is_ignored_with_a_warning(tmp_path: Path, text: str, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "marks.json"
    path.write_text(text)
    assert MarksStore(path).load() == []
    assert "marks file" in caplog.text and "ignored" in caplog.text


def test_the_marks_before_a_bad_one_are_kept(tmp_path: Path) -> None:
    good = mark_record(MarksStore(None).new(header(), 1.0, 1.0, "casualty", "", wall=5.0))
    path = tmp_path / "marks.json"
    path.write_text(json.dumps({"marks": [good, {"markId": "broken"}]}))
    assert [m.markId for m in MarksStore(path).load()] == [good["markId"]]


def test_a_record_round_trips() -> None:
    m = MarksStore(None).new(header(), 2.0, 3.0, "note", "door", wall=7.0)
    back = mark_from_record(mark_record(m))
    assert (back.markId, back.x, back.y, back.label, back.kind, back.header.sender, back.header.robot) == (
        m.markId, 2.0, 3.0, "door", "note", "op-1", "r1",
    )  # fmt: skip
    assert back.header.timestamp == m.header.timestamp
