"""The flight recorder (docs/recording.md): wire messages as JSON-schema MCAP channels, Foxglove's
schemas for poses and maps, chunks a crash cannot take with it, the summary, bad files.

Files are read back with the ``mcap`` library's own readers and every message is validated against
its channel's schema with ``jsonschema``.
"""

from __future__ import annotations

import dataclasses
import json
import struct
from collections import Counter
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from fleetlink.links.inprocess import InProcessBus
from fleetlink.shared import foxglove, keys, wire, wire_json
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.map_codec import patch_fields, snapshot_fields
from fleetlink.shared.messages import LinkName, MapSnapshot, MapUpdate, Pose
from fleetlink.shared.wire import Limits
from fleetlink.site.recorder import Recorder, RecordingError, RecordingReader, summarise
from fleetlink.site.recording import RecordingCore
from tests.harness import wait_until
from tests.harness.mcap_doctor import doctor
from tests.harness.messages import state as harness_state
from tests.test_wire import strategy_for


def pose(counter: wire.HeaderCounter, x: float, theta: float = 0.5) -> Pose:
    return counter.make(
        Pose, x=x, y=1.0, theta=theta, sd_x_m=0.1, sd_y_m=0.1, sd_theta_rad=0.01,
        odom_x=x, odom_y=0.0, odom_theta=0.0, vx=0.2, omega=0.0, uwbStale=False,
    )  # fmt: skip


def read_validated(path: Path, compression: str = "zstd") -> dict[str, list[Any]]:
    """Every message of a closed file, via the mcap library's seeking reader, each validated against
    its channel's JSON Schema; topic -> decoded JSON messages. The file's structure first checked
    record by record as the official CLI's ``mcap doctor`` checks it (tests/harness/mcap_doctor.py):
    what the library's readers take on trust (message and chunk indexes, statistics, CRCs). Every
    message is in a chunk (the doctor checks), and every chunk is compressed with ``compression``."""
    assert doctor(path) == []
    out: dict[str, list[Any]] = {}
    validators: dict[int, Any] = {}
    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {compression}
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert channel.message_encoding == "json" and schema is not None and schema.encoding == "jsonschema"
            v = validators.get(channel.id)
            if v is None:
                doc = json.loads(schema.data)
                jsonschema.validators.validator_for(doc).check_schema(doc)
                v = validators[channel.id] = jsonschema.validators.validator_for(doc)(doc)
            obj = json.loads(message.data)
            v.validate(obj)
            out.setdefault(channel.topic, []).append(obj)
        counts = summary.statistics.channel_message_counts
        assert sum(counts.values()) == sum(len(v) for v in out.values())
    return out


# -- the JSON form of the wire contract -----------------------------------------------------------


@pytest.mark.parametrize("topic", sorted(wire.registered()))
@settings(max_examples=25, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_every_message_round_trips_through_json_and_fits_its_schema(topic: str, data: st.DataObject) -> None:
    cls = wire.registered()[topic]
    msg = data.draw(strategy_for(cls, Limits()))
    text = wire_json.to_json(msg)
    doc = wire_json.json_schema(cls)
    jsonschema.Draft202012Validator(doc).validate(json.loads(text))
    assert wire_json.from_json(cls, text) == msg


def test_schema_refuses_what_the_wire_refuses() -> None:
    doc = wire_json.json_schema(Pose)
    good = json.loads(wire_json.to_json(pose(wire.HeaderCounter(SystemClock(), robot="r1", sender="a"), 1.0)))
    validator = jsonschema.Draft202012Validator(doc)
    validator.validate(good)
    for bad in ({**good, "theta": 4.0}, {**good, "bogus": 1}, {k: v for k, v in good.items() if k != "vx"}):
        assert not validator.is_valid(bad)
        with pytest.raises(wire.WireError):
            wire_json.from_json(Pose, json.dumps(bad))


def test_from_json_raises_only_wire_errors() -> None:
    for junk in (b"", b"[1]", b"{", b'{"header": 3}', b"\xff", b'{"cells": "###"}'):
        with pytest.raises(wire.WireError):
            wire_json.from_json(MapSnapshot, junk)


def test_foxglove_pose_quaternion_and_time() -> None:
    p = foxglove.pose_in_frame(1767225600.25, 1.0, 2.0, np.pi / 2)
    assert p["timestamp"] == {"sec": 1767225600, "nsec": 250_000_000}
    q = p["pose"]["orientation"]
    assert q["z"] == pytest.approx(np.sqrt(0.5)) and q["w"] == pytest.approx(np.sqrt(0.5))
    for name, doc in foxglove.SCHEMAS.items():
        jsonschema.Draft7Validator.check_schema(doc)
        assert doc["title"] == name
    scan = foxglove.laser_scan(1.0, pose=(0.0, 0.0, 0.0), start_angle=0.0, end_angle=6.0, ranges=[1.0, 2.0])
    jsonschema.Draft7Validator(foxglove.SCHEMAS[foxglove.LASER_SCAN]).validate(scan)


# -- the core ---------------------------------------------------------------------------------------


def test_core_channels_per_type_and_link_and_one_foxglove_pose_per_copy() -> None:
    core = RecordingCore()
    c = wire.HeaderCounter(SystemClock(), robot="r1", sender="agent-r1")
    recs = []
    for i in range(4):
        p = pose(c, float(i))
        raw = wire.encode(p)
        recs += core.receive("zenoh", wire.key_of(p), raw, 100.0 + i)
        recs += core.receive("mqtt", wire.key_of(p), raw, 100.0 + i)  # the same pose on the fallback
    topics = Counter(r.channel.topic for r in recs)
    assert topics == {"/fleetlink/zenoh/pose": 4, "/fleetlink/mqtt/pose": 4, "/foxglove/r1/pose": 4}
    assert recs[0].log_time_ns == 100_000_000_000
    assert recs[0].channel.metadata() == {"kind": "wire", "link": "zenoh", "wire_topic": "pose"}
    assert core.receive("zenoh", "fleetlink/v1/r1/pose", b"\x00junk", 1.0) == []
    assert core.receive("zenoh", "fleetlink/v1/r2/pose", wire.encode(pose(c, 1.0)), 1.0) == []  # header says r1
    assert sum(core.rejected.values()) == 2
    assert core.robots == {"r1"}


def test_core_records_fleet_frames_as_sent_and_as_foxglove_transforms() -> None:
    from fleetlink.shared.messages import FleetFrames, RobotFrame

    core = RecordingCore()
    c = wire.HeaderCounter(SystemClock(), robot=keys.FLEET_MAP, sender="op-1")
    msg = c.make(
        FleetFrames, reference="", frames=(RobotFrame(robot="r2", x=1.0, y=2.0, theta=0.3, began=0.0),), unframed=()
    )
    recs = core.receive("zenoh", wire.key_of(msg), wire.encode(msg), 100.0)
    assert [r.channel.topic for r in recs] == ["/fleetlink/zenoh/frames", "/foxglove/fleet/frames"]
    (t,) = json.loads(recs[1].data)["transforms"]
    assert (t["parent_frame_id"], t["child_frame_id"], t["translation"]["x"]) == ("map", "r2/map", 1.0)
    assert core.robots == set()  # the fleet map's service is no robot


def test_core_draws_a_whole_map_from_a_snapshot_and_its_updates() -> None:
    core = RecordingCore()
    c = wire.HeaderCounter(SystemClock(), robot="r1", sender="agent-r1")
    cells = np.full((10, 20), -1, dtype=np.int8)
    patch = c.make(MapUpdate, **patch_fields(cells, 0.1, (1.0, 2.0), (0, 0, 2, 2), 4, 3))
    assert [r.channel.topic for r in core.receive("zenoh", wire.key_of(patch), wire.encode(patch), 1.0)] == [
        "/fleetlink/zenoh/map/updates"
    ]
    assert core.wanted_snapshots() == [("r1", "map")] and core.wanted_snapshots() == []
    snap = c.make(MapSnapshot, **snapshot_fields(cells, 0.1, (1.0, 2.0), 3))
    recs = core.snapshot("zenoh", keys.key("r1", "map"), wire.encode(snap), 2.0)
    assert [r.channel.topic for r in recs] == ["/fleetlink/zenoh/map", "/foxglove/r1/map"]
    cells[0:2, 0:2] = 100
    patch = c.make(MapUpdate, **patch_fields(cells, 0.1, (1.0, 2.0), (0, 0, 2, 2), 4, 3))
    recs = core.receive("zenoh", wire.key_of(patch), wire.encode(patch), 3.0)
    grid = json.loads(recs[-1].data)
    assert grid["column_count"] == 20 and grid["cell_size"] == {"x": 0.1, "y": 0.1}
    assert grid["pose"]["position"] == {"x": 1.0, "y": 2.0, "z": 0.0}
    data = np.frombuffer(__import__("base64").b64decode(grid["data"]), dtype=np.int8).reshape(10, 20)
    assert (data == cells).all()


def test_core_asks_for_a_robots_dose_layer_when_its_updates_cannot_be_followed() -> None:
    """The recorder keeps no dose cells (it draws no dose layer), only each layer's version and
    shape: the first update heard, and one that does not follow, ask for the robot's snapshot once;
    updates that follow, and a copy on the other link, ask for nothing."""
    from fleetlink.shared import dose_codec
    from fleetlink.shared.dose import Lamp
    from fleetlink.shared.messages import DoseSnapshot, DoseUpdate

    core = RecordingCore()
    c = wire.HeaderCounter(SystemClock(), robot="r1", sender="agent-r1")
    dose, common = np.zeros((10, 20)), {"target_j_m2": 100.0, "lamp_on_s": 1.0, "unplaced_s": 0.0}

    def update(version: int, base: int) -> tuple[str, bytes]:
        fields = dose_codec.patch_fields(dose, 0.1, (-0.05, -0.05), (0, 0, 2, 2), version, base, **common)
        assert fields is not None
        msg = c.make(DoseUpdate, **fields)
        return wire.key_of(msg), wire.encode(msg)

    first = update(4, 3)
    core.receive("zenoh", *first, 1.0)
    assert core.wanted_snapshots() == [("r1", "dose")] and core.wanted_snapshots() == []
    fields = dose_codec.snapshot_fields(dose, 0.1, (-0.05, -0.05), 4, **common, lamp=Lamp(10.0, 0.6))
    assert fields is not None
    snap = c.make(DoseSnapshot, **fields)
    assert [r.channel.topic for r in core.snapshot("zenoh", keys.key("r1", "dose"), wire.encode(snap), 2.0)] == [
        "/fleetlink/zenoh/dose"
    ]
    core.receive("mqtt", *first, 2.1)  # the first update's copy, late on the other link
    for version in (5, 6):
        heard = update(version, version - 1)
        core.receive("zenoh", *heard, 3.0)
        core.receive("mqtt", *heard, 3.0)
    assert core.wanted_snapshots() == []
    core.receive("zenoh", *update(9, 8), 4.0)  # two were missed
    assert core.wanted_snapshots() == [("r1", "dose")]


# -- the recorder over in-process links -------------------------------------------------------------


def test_recorder_writes_a_readable_file_and_its_summary(tmp_path: Path) -> None:
    clock = SystemClock()
    zb, mb = InProcessBus(LinkName.ZENOH), InProcessBus(LinkName.MQTT)
    out = tmp_path / "mission.mcap"
    rec = Recorder(out, [zb.endpoint("recorder"), mb.endpoint("recorder")], clock).start()
    agent_z, agent_m = zb.endpoint("agent-r1"), mb.endpoint("agent-r1")
    agent_z.start()
    agent_m.start()
    c = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    try:
        for i in range(20):
            p = pose(c, i * 0.1)
            agent_z.publish(wire.key_of(p), wire.encode(p))
            if i % 2 == 0:
                agent_m.publish(wire.key_of(p), wire.encode(p))
        s = harness_state(c)
        agent_z.publish(wire.key_of(s), wire.encode(s))
        agent_m.publish(
            "fleetlink/uwb/gw-1/status", json.dumps({"gateway": "gw-1", "anchors": [["a1", 0, 0, 2]]}).encode()
        )
        zb.deliver()
        mb.deliver()
        wait_until(lambda: rec.written >= 20 + 10 + 20 + 1 + 1, message="everything written")
    finally:
        rec.stop()
    got = read_validated(out)
    assert len(got["/fleetlink/zenoh/pose"]) == 20 and len(got["/fleetlink/mqtt/pose"]) == 10
    assert len(got["/foxglove/r1/pose"]) == 20
    assert got["/fleetlink/zenoh/state"][0]["header"]["robot"] == "r1"
    assert got["/fleetlink/mqtt/uwb-status"][0]["status"]["gateway"] == "gw-1"
    summary = summarise(out)
    assert summary.complete and summary.robots == ("r1",)
    assert {c.topic: c.messages for c in summary.channels}["/fleetlink/zenoh/pose"] == 20
    text = summary.text(str(out))
    assert "robots (1): r1" in text and "/foxglove/r1/pose" in text and "foxglove.PoseInFrame" in text


def test_bad_files_give_a_clear_error(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        summarise(junk)
    with pytest.raises(RecordingError, match="cannot open"):
        summarise(tmp_path / "missing.mcap")


def test_a_truncated_or_damaged_file_gives_what_came_before(tmp_path: Path) -> None:
    clock = SystemClock()
    zb = InProcessBus(LinkName.ZENOH)
    out = tmp_path / "whole.mcap"
    rec = Recorder(out, [zb.endpoint("recorder")], clock, chunk_size=2_000).start()
    agent = zb.endpoint("agent-r1")
    agent.start()
    c = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    try:
        for i in range(200):
            p = pose(c, i * 0.01)
            agent.publish(wire.key_of(p), wire.encode(p))
        zb.deliver()
        wait_until(lambda: rec.written >= 400, message="written")
    finally:
        rec.stop()
    whole = out.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole[: len(whole) * 2 // 3])
    reader = RecordingReader(cut)
    n = sum(1 for _ in reader.messages())
    assert 100 < n < 400 and not reader.complete and reader.problem
    assert not summarise(cut).complete
    damaged = tmp_path / "damaged.mcap"
    mid = len(whole) // 2
    damaged.write_bytes(whole[:mid] + bytes(b ^ 0x5A for b in whole[mid : mid + 64]) + whole[mid + 64 :])
    # Its summary section is whole: --summary says what the index says, without reading a chunk.
    assert summarise(damaged).messages == 400 and summarise(damaged).from_index
    summary = summarise(damaged, index=False)  # --scan: no traceback, what came before the damage, a note
    assert 0 < summary.messages < 400 and any("damaged" in n for n in summary.notes)


def test_a_chunk_whose_opcode_is_damaged_is_not_skipped_without_a_word(tmp_path: Path) -> None:
    # MCAP readers skip records of an unknown opcode: a chunk whose opcode byte is damaged (and its
    # length not) would vanish with its messages and no note, were the data section's CRC not
    # written. Every chunk in turn, as the flipped window of the test above can land on any.
    whole = tmp_path / "whole.mcap"
    record_poses(whole, 60, chunk_size=1_000)
    total = summarise(whole, index=False).messages
    data = whole.read_bytes()
    chunks, at = [], 8
    while data[at] != 0x0F:  # up to Data End
        if data[at] == 0x06:
            chunks.append(at)
        at += 9 + struct.unpack_from("<Q", data, at + 1)[0]
    assert len(chunks) >= 5
    for at in chunks:
        damaged = tmp_path / "damaged.mcap"
        damaged.write_bytes(data[:at] + bytes([data[at] ^ 0x5A]) + data[at + 1 :])
        summary = summarise(damaged, index=False)
        assert summary.messages < total and any("damaged" in n for n in summary.notes), (at, summary.notes)
        reader = RecordingReader(damaged)
        assert sum(1 for _ in reader.messages()) < total and not reader.complete and "CRC" in (reader.problem or "")


def record_poses(path: Path, n: int, *, chunk_size: int = 16 * 1024) -> None:
    """``n`` poses of r1 on Zenoh (every second one on MQTT too) and a state, recorded into ``path``."""
    clock = SystemClock()
    zb, mb = InProcessBus(LinkName.ZENOH), InProcessBus(LinkName.MQTT)
    rec = Recorder(path, [zb.endpoint("recorder"), mb.endpoint("recorder")], clock, chunk_size=chunk_size)
    rec.start()
    agent_z, agent_m = zb.endpoint("agent-r1"), mb.endpoint("agent-r1")
    agent_z.start()
    agent_m.start()
    c = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    try:
        for i in range(n):
            p = pose(c, i * 0.001)
            agent_z.publish(wire.key_of(p), wire.encode(p))
            if i % 2 == 0:
                agent_m.publish(wire.key_of(p), wire.encode(p))
        s = harness_state(c)
        agent_z.publish(wire.key_of(s), wire.encode(s))
        zb.deliver()
        mb.deliver()
        wait_until(lambda: rec.written >= n + n // 2 + n + 1, message="everything written")
    finally:
        rec.stop()


def test_summary_of_a_closed_file_is_read_from_its_summary_section(tmp_path: Path) -> None:
    """No chunk is read: the counts, span and channels come from the statistics and the summary's
    channels, the robots from the recorder's metadata; the same as reading every message."""
    out = tmp_path / "long.mcap"
    record_poses(out, 3000)
    size = out.stat().st_size
    summary = summarise(out)
    assert summary.from_index and summary.complete and not summary.notes
    # The summary section (145 chunk indexes of 16 KiB chunks: ~6 % of this file; with the
    # recorder's 256 KiB chunks, a few hundredths of one) read twice, parsed and its CRC checked.
    assert summary.bytes_read < size / 7
    scanned = summarise(out, index=False)
    assert not scanned.from_index and scanned.bytes_read == size
    assert (summary.channels, summary.start_ns, summary.end_ns, summary.robots) == (
        scanned.channels,
        scanned.start_ns,
        scanned.end_ns,
        scanned.robots,
    )
    counts = {c.topic: c.messages for c in summary.channels}
    assert counts["/fleetlink/zenoh/pose"] == 3000 and counts["/fleetlink/mqtt/pose"] == 1500
    assert summary.robots == ("r1",) and summary.text() == scanned.text()


def test_summary_of_a_file_cut_short_is_read_message_by_message_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from fleetlink.cli.main import main

    out = tmp_path / "whole.mcap"
    record_poses(out, 600, chunk_size=4_000)
    cut = tmp_path / "crashed.mcap"
    cut.write_bytes(out.read_bytes()[: out.stat().st_size * 2 // 3])
    summary = summarise(cut)
    assert not summary.from_index and not summary.complete and 0 < summary.messages < 600 * 2.5
    assert summary.robots == ("r1",)
    assert any("no summary section" in n and "read message by message" in n for n in summary.notes)
    assert main(["record", "--summary", str(cut)]) == 0
    said = capsys.readouterr().out
    assert "recovered" in said and "no summary section (the file was not closed" in said
    assert main(["record", "--summary", str(out), "--scan"]) == 0
    assert "read message by message" not in capsys.readouterr().out
    assert main(["record", "--out", str(tmp_path / "x.mcap"), "--scan"]) == 2


def test_summary_falls_back_to_reading_every_message_when_its_summary_cannot_be_used(tmp_path: Path) -> None:
    out = tmp_path / "whole.mcap"
    record_poses(out, 200, chunk_size=4_000)
    whole = out.read_bytes()
    # A byte of the summary section changed: its CRC (in the footer) no longer matches.
    from mcap.reader import make_reader

    with out.open("rb") as f:
        stats = make_reader(f).get_summary()
    assert stats is not None and stats.statistics is not None
    at = whole.rfind(b"/fleetlink/zenoh/pose")  # the channel, repeated in the summary section
    bad = tmp_path / "bad-summary.mcap"
    bad.write_bytes(whole[:at] + b"X" + whole[at + 1 :])
    summary = summarise(bad)
    assert not summary.from_index and summary.messages == 200 + 100 + 200 + 1
    assert any("does not match the CRC" in n for n in summary.notes)

    # Another writer's file: a summary, but not the recorder's metadata (the robots): every message.
    from mcap.writer import Writer

    other = tmp_path / "other.mcap"
    with other.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="test")
        schema = writer.register_schema(name="fleetlink.Pose", encoding="jsonschema", data=b"{}")
        channel = writer.register_channel(
            topic="/fleetlink/zenoh/pose", message_encoding="json", schema_id=schema, metadata={"kind": "wire"}
        )
        c = wire.HeaderCounter(SystemClock(), robot="r7", sender="agent-r7")
        for i in range(3):
            writer.add_message(channel, log_time=i, data=wire_json.to_json(pose(c, 0.0)), publish_time=i)
        writer.finish()
    summary = summarise(other)
    assert not summary.from_index and summary.complete and summary.robots == ("r7",) and summary.messages == 3
    assert any("no fleetlink.recording metadata" in n for n in summary.notes)


# -- the commands ---------------------------------------------------------------------------------


def test_record_summary_and_replay_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from fleetlink.cli.main import main

    clock = SystemClock()
    zb = InProcessBus(LinkName.ZENOH)
    out = tmp_path / "mission.mcap"
    rec = Recorder(out, [zb.endpoint("recorder")], clock).start()
    agent = zb.endpoint("agent-r1")
    agent.start()
    c = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    try:
        for i in range(10):
            p = pose(c, i * 0.1)
            agent.publish(wire.key_of(p), wire.encode(p))
        s = harness_state(c)
        agent.publish(wire.key_of(s), wire.encode(s))
        zb.deliver()
        wait_until(lambda: rec.written >= 21, message="written")
    finally:
        rec.stop()
    assert main(["record", "--summary", str(out)]) == 0
    said = capsys.readouterr().out
    assert "21 messages on 3 channels" in said and "robots (1): r1" in said and "/fleetlink/zenoh/state" in said
    assert main(["replay", str(out), "--headless", "--speed", "1000"]) == 0
    said = capsys.readouterr().out
    assert "r1" in said and "SEMIAUTOMATIC" in said

    cut = tmp_path / "cut.mcap"
    cut.write_bytes(out.read_bytes()[:40])
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(bytes(range(256)) * 4)
    for bad in (cut, empty, junk, tmp_path / "missing.mcap"):
        assert main(["record", "--summary", str(bad)]) == 2
        assert main(["replay", str(bad), "--headless"]) == 2
        err = capsys.readouterr().err
        assert err.count("error: ") == 2 and "Traceback" not in err, err
    assert main(["replay", str(out), "--speed", "0"]) == 2
    assert "speed must be a positive number" in capsys.readouterr().err


def test_the_recorder_takes_tokens_under_the_contracts_key_and_counts_bad_ones() -> None:
    core = RecordingCore()
    records = core.alive("zenoh", keys.alive_key("r1"), True, 1.0)
    assert [json.loads(r.data) for r in records] == [{"robot": "r1", "alive": True}]
    assert "r1" in core.robots
    for bad in ("fleetlink/alive/v1/sim", "fleetlink/v1/r1/alive"):  # reserved id; the old key
        assert core.alive("zenoh", bad, True, 2.0) == []
    assert sum(n for r, n in core.rejected.items() if r.startswith("bad liveliness token")) == 2
    assert core.robots == {"r1"}


def test_a_timestamp_far_in_the_future_is_recorded_and_the_writer_goes_on(tmp_path: Path) -> None:
    # The wire takes any finite timestamp >= 0; MCAP's times are uint64 nanoseconds.
    clock = SystemClock()
    zb = InProcessBus(LinkName.ZENOH)
    out = tmp_path / "future.mcap"
    rec = Recorder(out, [zb.endpoint("recorder")], clock).start()
    agent = zb.endpoint("agent-r1")
    agent.start()
    c = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    try:
        for ts in (1e300, 1e12, None):
            p = pose(c, 0.5)
            if ts is not None:
                p = dataclasses.replace(p, header=dataclasses.replace(p.header, timestamp=ts))
            agent.publish(wire.key_of(p), wire.encode(p))
            zb.deliver()
            wait_until(lambda n=rec.written: rec.written >= n + 2, message="written")
    finally:
        rec.stop()
    assert sum(1 for _ in RecordingReader(out).messages()) == 6


# -- cost and bounds ---------------------------------------------------------------------------------


def test_the_message_appender_writes_what_the_mcap_writer_writes() -> None:
    """``MessageAppender`` (site/recorder.py) bypasses ``Writer.add_message`` for speed: the file must
    be byte for byte the library's own, chunk boundaries, indexes and statistics included."""
    import io

    from mcap.writer import CompressionType, Writer

    from fleetlink.site.recorder import MessageAppender

    def write(fast: bool) -> bytes:
        buf = io.BytesIO()
        w = Writer(buf, chunk_size=4096, compression=CompressionType.ZSTD)
        w.start(profile="fleetlink", library="test")
        sid = w.register_schema(name="s", encoding="jsonschema", data=b"{}")
        ids = [w.register_channel(topic=f"/c{i}", message_encoding="json", schema_id=sid) for i in range(3)]
        appender = MessageAppender(w)
        assert appender.fast  # mcap 1.6's writer: the fast path is taken
        for i in range(500):  # out of order times too: a recorder's two links interleave
            t = 1_000_000 + i * 1000 - (i % 7) * 3000
            data = json.dumps({"i": i, "pad": "x" * (i % 50)}).encode()
            if fast:
                appender.add(ids[i % 3], t, data, t - 5)
            else:
                w.add_message(ids[i % 3], log_time=t, data=data, publish_time=t - 5)
            if i == 250:
                w.flush()  # a chunk closed by age, as the recorder does
        w.finish()
        return buf.getvalue()

    assert write(True) == write(False)


def test_the_doctor_passes_the_libraries_file_and_finds_what_its_readers_take_on_trust(tmp_path: Path) -> None:
    """The MCAP structure check every recording in these tests goes through
    (tests/harness/mcap_doctor.py, after the official CLI's ``mcap doctor``): a file the ``mcap``
    writer wrote passes; a message index entry one byte off, a statistics count one too high, a
    chunk index pointing past its chunk do not, though the library's seeking reader reads each of
    them without a word."""
    from mcap.opcode import Opcode
    from mcap.writer import CompressionType, Writer

    from tests.harness.mcap_doctor import _lex

    path = tmp_path / "good.mcap"
    with path.open("wb") as f:
        w = Writer(f, chunk_size=2048, compression=CompressionType.ZSTD)
        w.start(profile="fleetlink", library="test")
        sid = w.register_schema(name="s", encoding="jsonschema", data=b"{}")
        ids = [w.register_channel(topic=f"/c{i}", message_encoding="json", schema_id=sid) for i in range(2)]
        for i in range(200):
            w.add_message(ids[i % 2], log_time=1000 + i, data=json.dumps({"i": i}).encode(), publish_time=1000 + i)
        w.add_metadata("m", {"k": "v"})
        w.finish()
    good = path.read_bytes()
    assert doctor(path) == []
    records = _lex(good, 8, len(good) - 8)

    def damaged(opcode: int, at: int, change: int, name: str) -> Path:
        """A copy with the u64 ``at`` bytes into the first record of ``opcode``'s body changed by ``change``."""
        offset = next(o for o, op, _n, _r in records if op == opcode) + 9 + at
        data = bytearray(good)
        (value,) = struct.unpack_from("<Q", data, offset)
        struct.pack_into("<Q", data, offset, value + change)
        out = tmp_path / name
        out.write_bytes(bytes(data))
        with out.open("rb") as f:  # the library reads it as it is
            assert sum(1 for _ in make_reader(f).iter_messages()) == 200
        return out

    # A message index: channel id u16, records length u32, then (log time u64, offset u64) entries.
    index = doctor(damaged(Opcode.MESSAGE_INDEX, 2 + 4 + 8, 1, "index.mcap"))
    assert any("message indexes after the chunk" in p for p in index), index
    # Statistics: message count u64 first.
    stats = doctor(damaged(Opcode.STATISTICS, 0, 1, "stats.mcap"))
    assert any("statistics say" in p for p in stats), stats
    # A chunk index: message start u64, end u64, chunk start offset u64, chunk length u64.
    chunk = doctor(damaged(Opcode.CHUNK_INDEX, 24, 1, "chunk.mcap"))
    assert any("chunk index of the chunk" in p for p in chunk), chunk


def test_a_flood_of_robot_ids_is_refused_counted_and_bounded(caplog: pytest.LogCaptureFixture) -> None:
    """A sender making up robot ids (each wire-valid) must not grow the recorder without bound: past
    ``MAX_ROBOTS`` a new robot's messages are refused, counted under one reason, logged once, and the
    robots already known are still recorded."""
    from fleetlink.site.recording import MAX_ROBOTS, TOO_MANY_ROBOTS

    core = RecordingCore()
    known = wire.HeaderCounter(SystemClock(), robot="r-known", sender="agent-r-known")
    p = pose(known, 1.0)
    assert core.receive("zenoh", wire.key_of(p), wire.encode(p), 1.0)
    flood = MAX_ROBOTS + 300
    for i in range(flood):
        c = wire.HeaderCounter(SystemClock(), robot=f"fake-{i}", sender="x")
        p = pose(c, 1.0)
        core.receive("zenoh", wire.key_of(p), wire.encode(p), 2.0)
        core.alive("zenoh", keys.alive_key(f"ghost-{i}"), True, 2.0)
    assert len(core.robots) == MAX_ROBOTS
    assert core.rejected[TOO_MANY_ROBOTS] == flood - (MAX_ROBOTS - 1) + flood  # poses and tokens
    assert core.new_reasons == [TOO_MANY_ROBOTS]  # one reason, to be logged once
    assert len(core.scene._last_pose) <= MAX_ROBOTS and len(core.messages) <= 2 * MAX_ROBOTS + 2
    p = pose(known, 2.0)
    assert [r.channel.topic for r in core.receive("mqtt", wire.key_of(p), wire.encode(p), 3.0)] == [
        "/fleetlink/mqtt/pose",
        "/foxglove/r-known/pose",
    ]

    # The recorder logs the reason once and keeps recording.
    clock = SystemClock()
    bus = InProcessBus(LinkName.ZENOH)
    rec = Recorder(Path(__import__("tempfile").mkdtemp()) / "flood.mcap", [bus.endpoint("recorder")], clock)
    rec.core = core
    rec.start()
    sender = bus.endpoint("x")
    sender.start()
    try:
        with caplog.at_level("WARNING", logger="fleetlink.site.recorder"):
            for i in range(3):
                c = wire.HeaderCounter(clock, robot=f"more-{i}", sender="x")
                p = pose(c, 1.0)
                sender.publish(wire.key_of(p), wire.encode(p))
            bus.deliver()
            wait_until(lambda: core.rejected[TOO_MANY_ROBOTS] >= 2 * flood - MAX_ROBOTS + 1 + 3, message="counted")
            wait_until(lambda: not core.new_reasons, message="taken by the writer")
    finally:
        rec.stop()
    said = [r.getMessage() for r in caplog.records if "too many robots" in r.getMessage()]
    assert len(said) == 1 and "further ones are counted" in said[0]


def test_zenoh_samples_are_taken_in_batches_with_their_receive_time(tmp_path: Path) -> None:
    """On a real Zenoh session the recorder takes samples from zenoh's queue (no Python per sample
    on zenoh's thread); each is logged at the time zenoh stamped it on arrival, not when taken."""
    from mcap.reader import make_reader

    from fleetlink.links.zenoh import ZenohEndpoint
    from fleetlink.site.brokers import free_port
    from fleetlink.site.recorder import open_recorder_links

    clock = SystemClock()
    at = f"tcp/127.0.0.1:{free_port()}"
    links = open_recorder_links(mqtt_url="mqtt://127.0.0.1:1", zenoh_listen=[at], clock=clock)
    out = tmp_path / "z.mcap"
    rec = Recorder(out, links[:1], clock, fetch_maps=False).start()
    agent = ZenohEndpoint(connect=[at], label="zenoh-agent")
    agent.start()
    c = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    sent: list[float] = []
    try:
        wait_until(lambda: agent.up, message="linked")
        for i in range(40):
            p = pose(c, i * 0.1)
            sent.append(clock.wall())
            agent.publish(wire.key_of(p), wire.encode(p))
            if i == 0:
                wait_until(lambda: rec.core.messages["/fleetlink/zenoh/pose"] >= 1, message="the route is up")
                sent = [clock.wall()]
            clock.sleep(0.002)
        wait_until(lambda: rec.core.messages["/fleetlink/zenoh/pose"] >= 40, message="all recorded")
    finally:
        agent.close()
        rec.stop()
    with out.open("rb") as f:
        times = [m.log_time / 1e9 for _, ch, m in make_reader(f).iter_messages() if ch.topic == "/fleetlink/zenoh/pose"]
    assert len(times) == 40
    # Stamped on arrival, one by one: stamps taken when the batch is taken (every 20 ms) would be
    # one for the whole batch. In sending order, each after its send and soon after.
    assert times == sorted(times) and len(set(times)) == 40
    lags = [t - s for t, s in zip(times[1:], sent[-39:], strict=True)]
    assert min(lags) > -0.001 and max(lags) < 0.25, lags
