"""Marks (operator/marks.py and the console, issue 15): naming, saving, loading; versions and
their merge; the retained sets; the export; the console's keys and commands (on the in-memory rig).
Against real Mosquitto and Zenoh: tests/test_marks_late_join.py."""

from __future__ import annotations

import csv
import dataclasses
import io
import itertools
import json
import logging
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

import msgpack
import pytest
from textual.widgets import RichLog

from fleetlink.operator.commands import (
    CommandError,
    MarkAt,
    MarkEdit,
    MarkHere,
    MarkRemove,
    MarksExport,
    MarksList,
    parse_command,
)
from fleetlink.operator.console import ConsoleApp, MarkDialog
from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.marks import (
    CSV_COLUMNS,
    MarksStore,
    SetTracker,
    bound_set,
    export_marks,
    find_mark,
    iso_utc,
    mark_from_record,
    mark_record,
    marks_csv,
    marks_geojson,
    marks_of_set,
    merge,
    own_sets,
    revised,
    set_message,
    supersedes,
)
from fleetlink.operator.marksync import MarkSharing
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import MAX_MARK_LABEL, MAX_MARK_SET, Mark, MarkSet, Teleop
from tests.harness.console_rig import ME, Rig
from tests.test_console import run_async, settle, type_text


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


# -- versions and merging (operator/marks.py, pure) -------------------------------------------------


def version(
    mark_id: str = "op-1-100-1",
    t: float = 100.0,
    sender: str = "op-1",
    robot: str = "r1",
    *,
    label: str = "victim",
    removed: bool = False,
    x: float = 1.0,
) -> Mark:
    h = wire.Header(headerId=0, timestamp=t, version=wire.WIRE_VERSION, robot=robot, sender=sender)
    return Mark(header=h, markId=mark_id, x=x, y=2.0, label=label, kind="casualty", sd_m=0.3, removed=removed)


def test_the_newest_version_wins_in_any_order_of_arrival() -> None:
    first, edit, removal = (
        version(t=100.0),
        version(t=105.0, sender="op-2", label="two"),
        version(t=110.0, removed=True),
    )
    other = version("op-2-1", t=90.0, sender="op-2")
    results = {
        tuple(sorted((k, v.header.timestamp) for k, v in merge({}, order).items()))
        for order in itertools.permutations([first, edit, removal, other])
    }
    assert results == {(("op-1-100-1", 110.0), ("op-2-1", 90.0))}  # the tombstone wins, whatever came last
    assert supersedes(edit, first) and not supersedes(first, edit) and not supersedes(first, first)


def test_a_tie_in_time_goes_to_the_greater_sender_id_on_every_console() -> None:
    a, b = version(t=100.0, sender="op-a", label="a"), version(t=100.0, sender="op-b", label="b")
    assert merge({}, [a, b])["op-1-100-1"].label == merge({}, [b, a])["op-1-100-1"].label == "b"


def test_merge_leaves_what_it_was_given_alone() -> None:
    held = {"op-1-100-1": version(t=100.0)}
    merged = merge(held, [version(t=200.0, label="new")])
    assert held["op-1-100-1"].label == "victim" and merged["op-1-100-1"].label == "new"


def test_an_edit_is_newer_than_what_it_edits_even_from_a_clock_behind() -> None:
    old = version(t=1000.0, robot="r2")
    editor = wire.Header(headerId=7, timestamp=900.0, version=wire.WIRE_VERSION, robot="r1", sender="op-2")
    new = revised(old, editor, label="two people")
    assert supersedes(new, old)
    assert (new.markId, new.header.robot, new.header.sender, new.label, new.kind, new.x, new.sd_m, new.removed) == (
        old.markId, "r2", "op-2", "two people", "casualty", old.x, old.sd_m, False,
    )  # fmt: skip
    gone = revised(new, editor, removed=True)
    assert gone.removed and gone.label == "two people" and supersedes(gone, new)
    wire.encode(gone)


def test_a_mark_is_found_by_its_id_or_a_unique_tail() -> None:
    marks = merge({}, [version("op-a-1712-3"), version("op-b-1713-3", sender="op-b"), version("op-a-1712-4")])
    marks = merge(marks, [version("op-a-1712-9", removed=True)])
    assert isinstance(found := find_mark(marks, "op-a-1712-3"), Mark) and found.markId == "op-a-1712-3"
    assert isinstance(found := find_mark(marks, "4"), Mark) and found.markId == "op-a-1712-4"
    assert isinstance(found := find_mark(marks, "1713-3"), Mark) and found.markId == "op-b-1713-3"
    assert "names 2 marks (op-a-1712-3, op-b-1713-3)" in str(find_mark(marks, "3"))
    assert "no mark '12'" in str(find_mark(marks, "12"))  # a tail is whole segments
    assert "was removed already" in str(find_mark(marks, "op-a-1712-9"))
    assert "no mark '9'" in str(find_mark(marks, "9"))  # a tail finds live marks only


# -- the retained sets (pure) -------------------------------------------------------------------------


def test_a_set_carries_its_marks_and_comes_back_the_same() -> None:
    marks = [version("m1", t=10.0), version("m2", t=11.0, removed=True)]
    h = wire.Header(headerId=3, timestamp=12.0, version=wire.WIRE_VERSION, robot="r1", sender="op-1")
    msg = set_message(h, marks)
    data = wire.encode(msg)
    back = wire.decode_key(keys.sender_key("r1", "marks/set", "op-1"), data)
    assert isinstance(back, MarkSet) and wire.key_of(msg) == "fleetlink/v1/r1/marks/set/op-1"
    assert [mark_record(m) for m in marks_of_set(back)] == [mark_record(m) for m in marks]


def test_own_sets_hold_per_robot_the_marks_whose_newest_version_the_login_wrote() -> None:
    marks = merge(
        {},
        [
            version("a", sender="op-1", robot="r1"),
            version("b", sender="op-1", robot="r2", removed=True),
            version("c", sender="op-2", robot="r1"),
            version("d", t=100.0, sender="op-1", robot="r1"),
            version("d", t=101.0, sender="op-2", robot="r1"),  # op-2 edited op-1's mark: op-2's now
        ],
    ).values()
    sets = own_sets(marks, "op-1")
    assert {r: [m.markId for m in ms] for r, ms in sets.items()} == {"r1": ["a"], "r2": ["b"]}
    assert {r: [m.markId for m in ms] for r, ms in own_sets(marks, "op-2").items()} == {"r1": ["c", "d"]}


def test_at_the_bound_the_oldest_tombstones_go_first_then_the_oldest_marks() -> None:
    live = [version(f"l{i}", t=float(i)) for i in range(4)]
    dead = [version(f"d{i}", t=float(10 + i), removed=True) for i in range(4)]
    assert [m.markId for m in bound_set(live + dead, limit=6)] == ["l0", "l1", "l2", "l3", "d2", "d3"]
    assert [m.markId for m in bound_set(live + dead, limit=3)] == ["l1", "l2", "l3"]
    assert len(bound_set(live + dead)) == 8


def test_a_full_set_fits_the_wire_and_one_more_mark_does_not() -> None:
    worst = [
        version("é" * 64, t=float(i), sender="o" * 64, label="✚" * MAX_MARK_LABEL) for i in range(MAX_MARK_SET + 1)
    ]
    worst = [dataclasses.replace(m, markId=f"{i:03d}" + "é" * 61, kind="k" * 32) for i, m in enumerate(worst)]
    h = wire.Header(headerId=0, timestamp=1e9, version=wire.WIRE_VERSION, robot="r" * 64, sender="o" * 64)
    assert len(wire.encode(set_message(h, worst[:MAX_MARK_SET]))) < wire.MAX_PAYLOAD
    with pytest.raises(wire.WireError, match="more than the limit of 256"):
        wire.encode(set_message(h, worst))
    assert len(own_sets(worst, "o" * 64)["r1"]) == MAX_MARK_SET  # own_sets never builds one too big


def test_the_tracker_says_which_sets_changed_since_they_were_sent() -> None:
    tracker = SetTracker()
    a, b = version("a"), version("b", robot="r2")
    assert tracker.due({"r1": (a,)}) == [("r1", (a,))]
    tracker.sent("r1", (a,))
    assert tracker.due({"r1": (a,)}) == []
    assert tracker.due({"r1": (a,), "r2": (b,)}) == [("r2", (b,))]  # not sent: due until it is
    tracker.sent("r2", (b,))
    # op-2 edits "a": our r1 set is now empty, and the broker must be told.
    assert tracker.due({"r2": (b,)}) == [("r1", ())]
    tracker.sent("r1", ())
    tracker.resend()  # reconnected: the broker may have forgotten everything
    assert tracker.due({"r2": (b,)}) == [("r1", ()), ("r2", (b,))]
    assert tracker.due({"r2": (b,)}) == []


def test_the_tracker_takes_our_set_from_the_broker_only_after_a_restart() -> None:
    tracker = SetTracker()
    old = version("old")
    tracker.heard("r1", (old,))  # retained from our last run
    assert tracker.due({"r1": (old,)}) == []  # the broker holds it already
    new = version("new")
    tracker.sent("r1", (old, new))
    tracker.heard("r1", (old,))  # the echo of an older set we sent: ignored
    assert tracker.due({"r1": (old, new)}) == []


# -- the file keeps uncertainty and tombstones ----------------------------------------------------------


def test_the_file_keeps_the_uncertainty_and_removed_marks(tmp_path: Path) -> None:
    path = tmp_path / "marks.json"
    marks = [version("a", t=1.0), version("b", t=2.0, removed=True)]
    MarksStore(path).save(marks)
    back = MarksStore(path).load()
    assert [(m.markId, m.sd_m, m.removed) for m in back] == [("a", 0.3, False), ("b", 0.3, True)]


def test_a_file_from_before_uncertainty_loads_with_none(tmp_path: Path) -> None:
    path = tmp_path / "marks.json"
    record = {"markId": "m1", "x": 1, "y": 2, "label": "", "kind": "note", "by": "o", "robot": "r", "timestamp": 1}
    path.write_text(json.dumps({"marks": [record]}))
    (m,) = MarksStore(path).load()
    assert (m.sd_m, m.removed) == (0.0, False)


# -- the export (pure writers) ---------------------------------------------------------------------------


def test_the_csv_export_has_one_row_per_live_mark_in_the_site_frame() -> None:
    marks = [
        version("b", t=1767225605.25, sender="op-2", robot="r2", label="two, trapped", x=-3.14159),
        version("a", t=1767225600.0, label='=HYPERLINK("x")'),
        version("gone", t=1767225601.0, removed=True),
    ]
    rows = list(csv.reader(io.StringIO(marks_csv(marks))))
    assert tuple(rows[0]) == CSV_COLUMNS == (
        "markId", "kind", "label", "x_m", "y_m", "sd_m", "robot", "by", "time_utc",
    )  # fmt: skip
    assert rows[1:] == [
        ["a", "casualty", '\'=HYPERLINK("x")', "1.000", "2.000", "0.300", "r1", "op-1", "2026-01-01T00:00:00.000Z"],
        ["b", "casualty", "two, trapped", "-3.142", "2.000", "0.300", "r2", "op-2", "2026-01-01T00:00:05.250Z"],
    ]


def test_the_geojson_export_is_points_in_metres_marked_as_the_site_frame() -> None:
    doc = marks_geojson([version("a", t=1767225600.0, x=1.23456), version("gone", removed=True)])
    assert doc["type"] == "FeatureCollection" and doc["frame"] == "site" and doc["units"] == "m"
    assert "not WGS84" in doc["note"]
    (feature,) = doc["features"]
    assert feature["geometry"] == {"type": "Point", "coordinates": [1.235, 2.0]}
    assert feature["properties"] == {
        "markId": "a", "kind": "casualty", "label": "victim", "sd_m": 0.3, "robot": "r1", "by": "op-1",
        "time_utc": "2026-01-01T00:00:00.000Z", "frame": "site",
    }  # fmt: skip
    assert iso_utc(0.0) == "1970-01-01T00:00:00.000Z"


def test_export_marks_writes_by_the_suffix_and_refuses_others(tmp_path: Path) -> None:
    marks = [version("a"), version("b", removed=True)]
    assert export_marks(marks, tmp_path / "m.csv") == 1
    assert (tmp_path / "m.csv").read_text().startswith("markId,kind,label")
    assert export_marks(marks, tmp_path / "m.geojson") == 1
    assert json.loads((tmp_path / "m.geojson").read_text())["features"][0]["id"] == "a"
    with pytest.raises(ValueError, match=r"\.csv or \.geojson"):
        export_marks(marks, tmp_path / "m.xlsx")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv", "m.geojson"]


# -- the fleet model ---------------------------------------------------------------------------------------


def test_the_fleet_model_merges_sets_and_live_marks_and_counts_changes() -> None:
    fleet = FleetModel("op-3")
    h = wire.Header(headerId=0, timestamp=50.0, version=wire.WIRE_VERSION, robot="r9", sender="op-1")
    sent = set_message(h, [version("a", t=10.0), version("b", t=11.0, removed=True)])
    assert fleet.apply(sent, "mqtt", 1.0)
    assert fleet.marks_version == 3  # the set itself, and two marks
    assert [m.markId for m in fleet.live_marks()] == ["a"]
    assert [(m.markId, m.header.robot, m.header.sender) for m in fleet.mark_sets[("r9", "op-1")]] == [
        ("a", "r9", "op-1"), ("b", "r9", "op-1"),
    ]  # fmt: skip
    assert "r9" not in fleet.robots  # marks are site-wide: a mark creates no robot
    assert not fleet.apply(sent, "zenoh", 1.0) and fleet.marks_version == 3  # the same set again
    assert not fleet.apply(marks_of_set(sent)[0], "zenoh", 1.0)  # the same version, live: nothing new
    assert fleet.apply(version("b", t=12.0, sender="op-2"), "zenoh", 1.0)  # an edit after the removal
    assert fleet.marks_version == 4 and {m.markId for m in fleet.live_marks()} == {"a", "b"}


# -- the console: keys and commands (the in-memory rig of tests/test_console.py) ---------------------


def notices(app: ConsoleApp) -> str:
    """What the notices pane shows, its lines joined (a long notice wraps at a space)."""
    return " ".join(line.text for line in app.query_one("#notices", RichLog).lines)


def sent_marks(rig: Rig) -> tuple[list[Mark], list[Mark]]:
    return rig.zenoh.messages(Mark), rig.mqtt.messages(Mark)


@run_async
async def test_shift_m_marks_at_the_selected_robot_after_asking_kind_and_label(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        rig.voices["r1"] = (2.5, -1.25)  # poses with sd 0.05 m on x and y
        await settle(pilot)
        await pilot.press("M")
        await pilot.pause()
        assert isinstance(rig.app.screen, MarkDialog)
        rig.voices["r1"] = (9.0, 9.0)  # the robot drives on while the label is typed
        await pilot.press("down")  # casualty -> hazard
        await type_text(pilot, "gas leak")
        await pilot.press("enter")
        await pilot.pause()
        zenoh, mqtt = sent_marks(rig)
        assert len(zenoh) == len(mqtt) == 1 and wire.encode(zenoh[0]) == wire.encode(mqtt[0])  # both links
        m = zenoh[0]
        # Where the robot was when M was pressed, with that pose's uncertainty.
        assert (m.kind, m.label, m.x, m.y, m.sd_m, m.header.robot, m.header.sender) == (
            "hazard", "gas leak", 2.5, -1.25, 0.05, "r1", ME,
        )  # fmt: skip
        assert f"mark {m.markId}: hazard 'gas leak' at (2.50, -1.25) ±0.05 m shared" in notices(rig.app)
        saved = json.loads(rig.marks_file.read_text())["marks"]
        assert [(r["markId"], r["sd_m"]) for r in saved] == [(m.markId, 0.05)]
        # ctrl+c leaves the dialog without a mark; drive keys typed there are the label's.
        await pilot.press("M")
        await pilot.pause()
        await type_text(pilot, "ijkl")
        await pilot.press("ctrl+c")
        await pilot.pause()
        assert not isinstance(rig.app.screen, MarkDialog)
        assert len(sent_marks(rig)[0]) == 1 and rig.zenoh.messages(Teleop) == []


@run_async
async def test_typed_marks_here_edit_remove_list_and_export(rig: Rig, tmp_path: Path) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        rig.voices["r1"] = (1.0, 2.0)
        await settle(pilot)
        rig.app.run_command("mark here victim under the stairs")
        here = sent_marks(rig)[0][-1]
        assert (here.kind, here.label, here.x, here.y, here.sd_m) == (
            "casualty",
            "victim under the stairs",
            1.0,
            2.0,
            0.05,
        )
        rig.app.run_command("mark hazard 4 5 gas")
        typed = sent_marks(rig)[0][-1]
        assert (typed.kind, typed.x, typed.y, typed.sd_m) == ("hazard", 4.0, 5.0, 0.0)
        # Another console's mark, edited here: this console is the new version's author.
        other = wire.HeaderCounter(rig.clock, robot="r2", sender="operator-2")
        rig.zenoh.inject(
            other.make(Mark, markId="operator-2-7-1", x=9.0, y=9.0, label="x", kind="note", sd_m=1.5, removed=False)
        )
        await settle(pilot, 0.1)
        rig.app.run_command("mark edit 7-1 casualty two people")
        edit = sent_marks(rig)[0][-1]
        assert (edit.markId, edit.kind, edit.label, edit.x, edit.sd_m, edit.header.robot, edit.header.sender) == (
            "operator-2-7-1", "casualty", "two people", 9.0, 1.5, "r2", ME,
        )  # fmt: skip
        tail = typed.markId.rsplit("-", 1)[1]
        rig.app.run_command(f"mark rm {tail}")
        assert sent_marks(rig)[0][-1].removed and sent_marks(rig)[1][-1].removed
        with rig.lock:
            assert {m.markId for m in rig.fleet.live_marks()} == {here.markId, "operator-2-7-1"}
        rig.app.run_command("marks")
        assert f"info    {here.markId}  casualty 'victim under the stairs' (1.00, 2.00) ±0.05 m  r1 by {ME}" in notices(
            rig.app
        )
        rig.app.run_command(f"marks export {tmp_path / 'report.csv'}")
        rows = list(csv.DictReader(io.StringIO((tmp_path / "report.csv").read_text())))
        assert [(r["markId"], r["by"], r["label"]) for r in rows] == [
            (here.markId, ME, "victim under the stairs"), ("operator-2-7-1", ME, "two people"),
        ]  # fmt: skip
        await settle(pilot, 0.1)
        saved = {r["markId"]: r for r in json.loads(rig.marks_file.read_text())["marks"]}
        assert saved[typed.markId]["removed"] and saved["operator-2-7-1"]["label"] == "two people"


@run_async
async def test_bad_typed_marks_are_refused_with_a_reason_and_nothing_is_sent(rig: Rig, tmp_path: Path) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        rig.app.run_command("mark here")  # no robot yet
        rig.voices["r1"] = (1.0, 2.0)
        await settle(pilot)
        for line in (
            "mark casualty nan 2",
            "mark casualty 1 inf",
            "mark casualty 1e9 2",
            "mark here " + "x" * (MAX_MARK_LABEL + 1),
            "mark " + "k" * 33 + " 1 2",
            "mark rm nope",
            "mark edit nope label",
            f"marks export {tmp_path / 'marks.xlsx'}",
        ):
            rig.app.run_command(line)
        assert sent_marks(rig) == ([], [])
        with rig.lock:
            assert rig.fleet.marks == {}
        said = notices(rig.app)
        for reason in (
            "no robot known yet",
            "coordinates must be finite numbers",
            "mark refused: x: 1000000000.0 out of range [-100000.0, 100000.0]",
            f"mark refused: the label is {MAX_MARK_LABEL + 1} characters, more than {MAX_MARK_LABEL}",
            "mark refused: the kind is 33 characters, more than 32",
            "mark removal refused: no mark 'nope'",
            "mark edit refused: no mark 'nope'",
            "marks export refused:",
        ):
            assert reason in said, reason
        assert not (tmp_path / "marks.xlsx").exists()


@run_async
async def test_mark_here_needs_a_fresh_pose(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        rig.pose("r1", 1.0, 1.0)
        await settle(pilot, 0.1)
        with rig.lock:
            rig.fleet.robots["r1"].lost = True
        rig.app.run_command("mark here")
        assert sent_marks(rig) == ([], [])
        assert "r1: lost, its last pose is stale: mark refused" in notices(rig.app)


def _raw_mark(counter: wire.HeaderCounter, **over: object) -> bytes:
    """A mark encoded by hand, so it may break the contract (NaN, an oversized label)."""
    good = counter.make(Mark, markId="bad-1", x=1.0, y=1.0, label="l", kind="casualty", sd_m=0.0, removed=False)
    body = msgpack.unpackb(wire.encode(good), raw=False)
    body.update(over)
    return msgpack.packb(body, use_bin_type=True)


@run_async
async def test_bad_marks_from_the_wire_are_refused_counted_and_disturb_nothing(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        rig.voices["r1"] = (1.0, 2.0)
        await settle(pilot)
        with rig.lock:
            before = (rig.fleet.robots["r1"].pose, dict(rig.fleet.marks))
        other = wire.HeaderCounter(rig.clock, robot="r1", sender="op-x")
        key = keys.sender_key("r1", "marks", "op-x")
        entry = {
            "markId": "e",
            "x": float("nan"),
            "y": 0.0,
            "label": "",
            "kind": "note",
            "sd_m": 0.0,
            "removed": False,
            "timestamp": 1.0,
        }
        good_set = set_message(other.header("marks/set"), [])
        bad_set = msgpack.unpackb(wire.encode(good_set), raw=False)
        bad_set["marks"] = [entry]
        with caplog.at_level(logging.WARNING, logger="fleetlink.operator.links"):
            for _ in range(3):  # counted every time, logged once per reason
                rig.mqtt.inject_raw(key, _raw_mark(other, x=float("nan")))
                rig.zenoh.inject_raw(key, _raw_mark(other, label="x" * (MAX_MARK_LABEL + 1)))
            rig.mqtt.inject_raw("fleetlink/v1/sim/marks/op-x", _raw_mark(other))  # not a robot id
            rig.mqtt.inject_raw(keys.sender_key("r1", "marks", "op-y"), _raw_mark(other))  # another's name
            rig.mqtt.inject_raw(keys.sender_key("r1", "marks/set", "op-x"), msgpack.packb(bad_set, use_bin_type=True))
            # A well-formed mark under a robot this console has never heard of is still a mark.
            stranger = wire.HeaderCounter(rig.clock, robot="r77", sender="op-x")
            rig.mqtt.inject(
                stranger.make(Mark, markId="ok-1", x=3.0, y=3.0, label="", kind="note", sd_m=0.0, removed=False)
            )
            await settle(pilot, 0.1)
        rejected = dict(rig.link.rejected)
        assert rejected == {
            "x: non-finite number nan": 3,
            f"label: string of {MAX_MARK_LABEL + 1} characters, more than the limit of {MAX_MARK_LABEL}": 3,
            "key: invalid truth key 'fleetlink/v1/sim/marks/op-x': expected fleetlink/v1/sim/<robot>/truth": 1,
            "header.sender: 'op-x' does not match the key's sender 'op-y' (who published it)": 1,
            "marks[0].x: non-finite number nan": 1,
        }, rejected
        logged = [r.getMessage() for r in caplog.records if "rejected a message" in r.getMessage()]
        assert len(logged) == 5
        with rig.lock:
            assert rig.fleet.robots["r1"].pose == before[0]
            assert set(rig.fleet.marks) == set(before[1]) | {"ok-1"} and "r77" not in rig.fleet.robots


# -- the retained sets' publisher (operator/marksync.py), without a network --------------------------------


class FakeLink:
    """What MarkSharing uses of OperatorLink: retained publishes recorded, the broker up or down."""

    sender = "op-1"

    def __init__(self) -> None:
        self.retained: list[MarkSet] = []
        self.up = True
        self.on_connect: list[Callable[[], object]] = []

    def serve_marks(self, marks: Callable[[], Sequence[Mark]]) -> None:
        self.served = marks

    def fetch_marks(self, timeout: float = 2.0) -> int:
        return 0

    def publish_retained(self, msg: wire.Message) -> bool:
        assert isinstance(msg, MarkSet)
        wire.encode(msg)
        if self.up:
            self.retained.append(msg)
        return self.up

    def add_connect_listener(self, listener: Callable[[], object]) -> None:
        self.on_connect.append(listener)


def sets_sent(link: FakeLink) -> list[tuple[str, list[str]]]:
    out = [(m.header.robot, [e.markId for e in m.marks]) for m in link.retained]
    link.retained.clear()
    return out


def test_the_sets_go_out_when_they_change_and_again_after_a_reconnect() -> None:
    link, fleet, lock = FakeLink(), FleetModel("op-1"), threading.Lock()
    sharing = MarkSharing(link, fleet, lock, clock=SimClock(start=1000.0), asks=())
    sharing.start()
    sharing.stop()  # the worker is not needed: publish_due is called by hand
    assert sharing.publish_due() == 0 and sets_sent(link) == []
    fleet.apply(version("a", robot="r1"), "local", 0.0)
    fleet.apply(version("b", robot="r2", removed=True), "local", 0.0)
    fleet.apply(version("c", sender="op-2"), "zenoh", 0.0)  # another console's: not in our sets
    assert sharing.publish_due() == 2 and sets_sent(link) == [("r1", ["a"]), ("r2", ["b"])]
    assert sharing.publish_due() == 0  # nothing changed
    # op-2 edits "a": our r1 set must now be empty on the broker.
    fleet.apply(version("a", t=200.0, sender="op-2"), "zenoh", 0.0)
    assert sharing.publish_due() == 1 and sets_sent(link) == [("r1", [])]
    # The broker goes away: what changes meanwhile goes out after the reconnect, with the rest.
    link.up = False
    fleet.apply(version("d", robot="r2"), "local", 0.0)
    assert sharing.publish_due() == 0
    link.up = True
    for hook in link.on_connect:
        hook()
    assert sharing.publish_due() == 2 and sets_sent(link) == [("r1", []), ("r2", ["b", "d"])]
    assert {m.markId for m in link.served()} == {"a", "b", "c", "d"}  # the queryable's source


def test_a_restarted_console_replaces_its_stale_set_and_keeps_a_current_one() -> None:
    link, fleet, lock = FakeLink(), FleetModel("op-1"), threading.Lock()
    sharing = MarkSharing(link, fleet, lock, asks=())
    h = wire.Header(headerId=0, timestamp=50.0, version=wire.WIRE_VERSION, robot="r1", sender="op-1")
    # Our sets from before the restart, as the broker returns them: r1's is current...
    fleet.apply(set_message(h, [version("a")]), "mqtt", 0.0)
    assert sharing.publish_due() == 0
    # ...r2's holds a mark op-2 has since edited: replaced by an empty set.
    fleet.apply(set_message(dataclasses.replace(h, robot="r2"), [version("b", robot="r2")]), "mqtt", 0.0)
    fleet.apply(version("b", t=300.0, sender="op-2", robot="r2"), "mqtt", 0.0)
    assert sharing.publish_due() == 1 and sets_sent(link) == [("r2", [])]


def test_a_read_only_console_publishes_no_set() -> None:
    link, fleet = FakeLink(), FleetModel("op-1")
    sharing = MarkSharing(link, fleet, threading.Lock(), publish=False, asks=())
    sharing.start()
    try:
        fleet.apply(version("a"), "local", 0.0)
        sharing.wake()
        assert link.on_connect == [] and link.retained == []
    finally:
        sharing.stop()


# -- the typed commands, parsed (operator/commands.py) --------------------------------------------------------


@pytest.mark.parametrize(
    ("line", "parsed"),
    [
        ("mark here", MarkHere("casualty", "")),
        ("mark HERE Hazard gas leak", MarkHere("hazard", "gas leak")),
        ("mark here two people", MarkHere("casualty", "two people")),  # not a kind: all label
        ("mark edit 3 note", MarkEdit("3", "note", None)),
        ("mark edit op-a-17-3 two  people", MarkEdit("op-a-17-3", None, "two people")),
        ("mark edit 3 hazard gas", MarkEdit("3", "hazard", "gas")),
        ("mark rm 3", MarkRemove("3")),
        ("unmark op-a-17-3", MarkRemove("op-a-17-3")),
        ("marks", MarksList()),
        ("marks export out/report.geojson", MarksExport("out/report.geojson")),
        ("mark casualty 1 2 " + "x" * 64, MarkAt("casualty", 1.0, 2.0, "x" * 64)),
    ],
)
def test_mark_commands_parse(line: str, parsed: object) -> None:
    assert parse_command(line) == parsed


@pytest.mark.parametrize(
    ("line", "reason"),
    [
        ("mark edit 3", "mark edit ID [KIND] [LABEL]"),
        ("mark rm", "mark rm ID"),
        ("mark rm 3 4", "mark rm ID"),
        ("marks export", "unknown command"),
        ("mark here " + "x" * 65, "the label is 65 characters, more than 64"),
        ("mark edit 3 " + "x" * 65, "the label is 65 characters, more than 64"),
        ("mark casualty 1 2 " + "x" * 65, "the label is 65 characters, more than 64"),
        ("mark casualty nan 2", "coordinates must be finite numbers"),
    ],
)
def test_bad_mark_commands_say_why(line: str, reason: str) -> None:
    error = parse_command(line)
    assert isinstance(error, CommandError) and reason in error.text
