"""The flight recorder on a real field session: real Zenoh on loopback (multicast scouting off), a
private Mosquitto, the field's boards and lidars, an agent per robot, an operator's console link;
read back with the ``mcap`` library, every channel validated against its schema; replayed into a
fresh console model that must show the fleet as the live one did; and a recorder killed with
SIGKILL that still leaves everything but its last chunk.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from mcap.stream_reader import StreamReader

from fleetlink.cli.replay import console_parts
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.operator.fleet_table import fleet_rows
from fleetlink.shared import wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import InstantActions, Mark, Pose, Teleop
from fleetlink.site.agents import FieldAgents
from fleetlink.site.operator import open_operator_link
from fleetlink.site.recorder import BATCH_PERIOD_S, CHUNK_AGE_S, Recorder, open_recorder_links, summarise
from fleetlink.site.replay import ReplaySource
from tests.harness import wait_until
from tests.harness.mosquitto import free_port
from tests.test_field_realtime import quiet_scenario
from tests.test_record import pose, read_validated

ME = "op-rec"
ROBOTS = ("uvc-1", "uvc-2")


def comparable(rows: dict[str, Any]) -> dict[str, list[str]]:
    """The fleet table without the columns that depend on when one looks (age, link health)."""
    return {robot: [str(c) for i, c in enumerate(row) if i not in (4, 5)] for robot, row in rows.items()}


def view_state(fleet: Any) -> dict[str, tuple[Any, ...]]:
    return {
        r: (v.mode, v.drive_mode, v.battery, v.pose, v.goal, v.lease_holder, v.estop, v.present, v.connection, v.board)
        for r, v in fleet.robots.items()
    }


@pytest.mark.slow
def test_a_recorded_field_session_reads_back_and_replays_to_the_same_fleet(mosquitto, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from fleetlink.field.realtime import RealtimeField

    clock = SystemClock()
    scenario = quiet_scenario(
        robots=[
            {"name": "uvc-1", "start": "living", "drive": "idle"},
            {"name": "uvc-2", "start": "bedroom", "drive": "idle"},
        ],
    )
    field = RealtimeField(scenario, clock=clock)
    # Zenoh peers do not route for each other: the recorder and the console each listen, the agents
    # connect to both, and the console to the recorder (on a site, all of them to its router).
    at_recorder, at_console = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "mission.mcap"
    recorder = agents = console = None
    try:
        endpoints = field.start()
        recorder = Recorder(
            out, open_recorder_links(mqtt_url=mosquitto.url, zenoh_listen=[at_recorder], clock=clock), clock
        ).start()
        console = open_operator_link(
            clock, ME, mqtt_url=mosquitto.url, zenoh_listen=[at_console], zenoh_connect=[at_recorder], client_id=ME
        ).start()
        live, live_lock, _maps, _doses = console_parts(console)
        agents = FieldAgents(
            endpoints, clock=clock, zenoh_connect=[at_recorder, at_console], mqtt_url=mosquitto.url, operators=(ME,)
        )
        agents.start()
        wait_until(lambda: set(live.robots) >= set(ROBOTS), timeout=30, message="both robots in the console")
        # Commands and their answers, a mark, as an operator makes them.
        console.send(InstantActions, "uvc-1", actions=())
        for _ in range(5):
            console.send(Teleop, "uvc-1", expect_ack=False, v=0.1, omega=0.0, ttl_s=0.5)
            time.sleep(0.1)
        mark = wire.HeaderCounter(clock, robot="uvc-1", sender=ME).make(
            Mark, markId=f"{ME}-1", kind="casualty", label="here", x=1.0, y=2.0, sd_m=0.5, removed=False
        )
        console.publish(mark, links=("zenoh", "mqtt"))
        wait_until(
            lambda: (
                recorder.core.messages["/foxglove/uvc-1/map"] >= 1
                and recorder.core.messages["/fleetlink/zenoh/ack"] >= 1
            ),
            timeout=60,
            message="a map drawn whole and an ack recorded",
        )
        wait_until(  # three seconds of both robots' poses (20 Hz) on record
            lambda: all(recorder.core.messages[f"/foxglove/{r}/pose"] >= 60 for r in ROBOTS),
            timeout=30,
            message="3 s of poses from each robot",
        )
        said = recorder.core.messages["/fleetlink/mqtt/connection"]
        agents.stop()  # the robots go quiet (and say OFFLINE), so both sides end on the same messages
        agents = None

        def both_heard_offline() -> bool:
            with live_lock:
                offline = all(live.robots[r].connection == "OFFLINE" for r in ROBOTS)
            return offline and recorder.core.messages["/fleetlink/mqtt/connection"] >= said + len(ROBOTS)

        wait_until(both_heard_offline, timeout=30, message="both robots' OFFLINE in the console and on record")
        with live_lock:
            live_rows = comparable(fleet_rows(live, console.active, console.health, ME, clock.now()))
            live_views = view_state(live)
    finally:
        if agents is not None:
            agents.stop()
        if console is not None:
            console.close()
        if recorder is not None:
            recorder.stop()
        field.stop()

    got = read_validated(out)  # the mcap library's reader; every message valid against its schema
    for topic in (
        "/fleetlink/zenoh/pose", "/fleetlink/mqtt/pose", "/fleetlink/zenoh/state", "/fleetlink/mqtt/state",
        "/fleetlink/zenoh/board", "/fleetlink/zenoh/lease", "/fleetlink/mqtt/connection", "/fleetlink/zenoh/events",
        "/fleetlink/zenoh/actions", "/fleetlink/zenoh/teleop", "/fleetlink/zenoh/ack", "/fleetlink/zenoh/marks",
        "/fleetlink/mqtt/marks", "/fleetlink/zenoh/map/updates", "/fleetlink/zenoh/map", "/fleetlink/zenoh/alive",
        "/foxglove/uvc-1/pose", "/foxglove/uvc-2/pose", "/foxglove/uvc-1/map",
    ):  # fmt: skip
        assert got.get(topic), f"nothing on {topic}: {sorted(got)}"
    assert {m["header"]["robot"] for m in got["/fleetlink/zenoh/pose"]} == set(ROBOTS)
    assert got["/foxglove/uvc-1/map"][-1]["fields"] == [{"name": "occupancy", "offset": 0, "type": 2}]
    summary = summarise(out)
    assert summary.complete and summary.robots == ROBOTS and summary.duration_s > 2

    # Replayed into a fresh console model: the fleet as the live console had it.
    source = ReplaySource(out)
    fleet, lock, _m, _d = console_parts(source)
    source.play_until(source.last)
    with lock:
        replay_rows = comparable(fleet_rows(fleet, source.active, source.health, ME, source.clock.now()))
        assert view_state(fleet) == live_views
    assert replay_rows == live_rows
    assert source.skipped == {}


@pytest.mark.slow
def test_a_recorder_killed_mid_recording_loses_at_most_its_last_chunk(mosquitto, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    clock = SystemClock()
    listen = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "crash.mcap"
    agent = ZenohEndpoint(listen=[listen], label="zenoh-test-agent")
    agent.start()
    fleetlink = str(Path(sys.executable).with_name("fleetlink"))
    log = tmp_path / "recorder.log"
    with log.open("w") as err:
        proc = subprocess.Popen(
            [fleetlink, "record", "--out", str(out), "--zenoh-connect", listen, "--mqtt", mosquitto.url], stderr=err
        )
    sent: list[float] = []
    try:
        wait_until(lambda: "recording to" in log.read_text(), message="the recorder started")
        counter = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
        wait_until(lambda: out.stat().st_size > 0, message="the file started")
        header_size = out.stat().st_size

        def publish() -> bool:
            p: Pose = pose(counter, len(sent) * 0.01)
            agent.publish(wire.key_of(p), wire.encode(p))
            time.sleep(0.01)
            return out.stat().st_size > header_size

        wait_until(publish, interval=0, message="the first chunk on disk (the recorder is connected)")
        # Its zenoh runtime reads with one receive thread (site/recorder.py ZENOH_RUNTIME).
        names = [
            (Path(f"/proc/{proc.pid}/task") / t / "comm").read_text().strip()
            for t in os.listdir(f"/proc/{proc.pid}/task")
        ]
        assert sorted(n for n in names if n.startswith("rx-")) == ["rx-0"], names
        end = time.monotonic() + 4.0
        while time.monotonic() < end:
            p: Pose = pose(counter, len(sent) * 0.01)
            agent.publish(wire.key_of(p), wire.encode(p))
            sent.append(clock.wall())
            time.sleep(0.01)
        killed_at = clock.wall()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        agent.close()
    assert proc.returncode == -signal.SIGKILL

    # The mcap library reads every whole chunk; the tail (the chunk being filled) is cut off.
    validators: dict[str, Any] = {}
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    times: list[int] = []
    with out.open("rb") as f:
        records = StreamReader(f, validate_crcs=True).records
        try:
            for record in records:
                kind = type(record).__name__
                if kind == "Schema":
                    schemas[record.id] = json.loads(record.data)
                elif kind == "Channel":
                    channels[record.id] = record
                elif kind == "Message":
                    ch = channels[record.channel_id]
                    v = validators.get(ch.topic)
                    if v is None:
                        v = validators[ch.topic] = jsonschema.Draft202012Validator(schemas[ch.schema_id])
                    v.validate(json.loads(record.data))
                    if ch.topic == "/fleetlink/zenoh/pose":
                        times.append(record.log_time)
                elif kind == "Footer":
                    raise AssertionError("a killed recorder cannot have written its footer")
        except AssertionError:
            raise
        except Exception:
            pass  # the truncated tail: everything before it was read
    assert times, "nothing recovered"
    last = max(times) / 1e9
    # Lost: at most what came in the last chunk's time (CHUNK_AGE_S) and the batch before it
    # (BATCH_PERIOD_S), and the flush of the file, with room for a busy machine.
    lost_s = CHUNK_AGE_S + BATCH_PERIOD_S + 0.5
    assert killed_at - last <= lost_s, (killed_at - last, len(times), len(sent))
    before = sum(1 for t in sent if t <= killed_at - lost_s)
    assert len(times) >= before * 0.98, (len(times), before)
    summary = summarise(out)
    assert not summary.complete and summary.robots == ("r1",)
