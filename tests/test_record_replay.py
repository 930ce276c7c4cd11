"""Replay (docs/recording.md): a recording played into a read-only console shows the fleet the live
console showed, the console refuses to command and says so, and a snapshot of the replayed screen.

A scene like tests/test_console_snapshot.py's is recorded over in-process links while a live
console model (the real ``OperatorLink``) hears the same links; the clock is stepped by the test,
so receive times, ages and link health come out the same on every run.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
import threading
from collections.abc import Callable, Coroutine, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fleetlink.cli.replay import console_parts, replay_app
from fleetlink.links.inprocess import InProcessBus
from fleetlink.operator.fleet_table import fleet_rows
from fleetlink.operator.linkmanager import LinkPolicy
from fleetlink.operator.links import OperatorLink
from fleetlink.shared import wire
from fleetlink.shared.map_codec import snapshot_fields
from fleetlink.shared.messages import (
    AgvPosition,
    BatteryState,
    EStop,
    Event,
    Goal,
    Lease,
    LinkName,
    MapSnapshot,
    Mark,
    OperatingMode,
    Pose,
    SafetyState,
    Severity,
    State,
)
from fleetlink.site.recorder import Recorder
from fleetlink.site.replay import ReadOnlyReplay, ReplaySource
from tests.harness import wait_until
from tests.harness.messages import state as harness_state
from tests.test_console_snapshot import ANCHORS, ORIGIN, RES, SIZE, before, room

ME = "operator-1"
EPOCH = 1_767_225_600.0


class SteppedClock:
    """Time only the test moves (``now`` = ``wall``); waits are real, so workers still run."""

    def __init__(self, t: float = EPOCH) -> None:
        self.t = t

    def now(self) -> float:
        return self.t

    def wall(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt

    def sleep_until(self, deadline: float) -> None:
        pass

    def wait(self, event: threading.Event, timeout: float | None) -> bool:
        return event.wait(None if timeout is None else min(0.05, max(0.0, timeout)))


def robots_talking(
    zb: InProcessBus, mb: InProcessBus, clock: SteppedClock
) -> tuple[dict[str, wire.HeaderCounter], Callable[..., None]]:
    """Robots r1 and r2 on both buses: their header counters, and ``say(msg, both=True)``, which
    publishes a message on Zenoh (and MQTT) and delivers it."""
    agents = {r: (zb.endpoint(f"agent-{r}"), mb.endpoint(f"agent-{r}")) for r in ("r1", "r2")}
    counters = {r: wire.HeaderCounter(clock, robot=r, sender=f"agent-{r}") for r in agents}
    for z, m in agents.values():
        z.start()
        m.start()

    def say(msg: wire.Message, both: bool = True) -> None:
        z, m = agents[msg.header.robot]
        z.publish(wire.key_of(msg), wire.encode(msg))
        if both:
            m.publish(wire.key_of(msg), wire.encode(msg))
        zb.deliver()
        mb.deliver()

    return counters, say


def run_closing(run: Callable[[], Coroutine[Any, Any, None]], source: ReplaySource, fetchers: Sequence[Any]) -> None:
    """``run()`` (a replayed console's test), then the source closed and the fetchers stopped."""
    try:
        asyncio.run(run())
    finally:
        source.close()
        for fetcher in fetchers:
            fetcher.stop()


def record_scene(path: Path) -> tuple[dict[str, Any], Any]:
    """Record two robots reporting (as tests/test_console_snapshot.py's ``two_robots``), with a
    live console model listening; returns the live fleet table and model views."""
    clock = SteppedClock()
    zb, mb = InProcessBus(LinkName.ZENOH, clock_now=clock.now), InProcessBus(LinkName.MQTT, clock_now=clock.now)
    recorder = Recorder(path, [zb.endpoint("recorder"), mb.endpoint("recorder")], clock, fetch_maps=False).start()
    # Sending as a console does by default (both links): the replay cannot know and assumes it.
    console = OperatorLink(clock, ME, zb.endpoint(ME), mb.endpoint(ME), policy=LinkPolicy(redundant=True)).start()
    live, lock, _maps, _doses = console_parts(console)
    counters, say = robots_talking(zb, mb, clock)

    def pose(robot: str, x: float, y: float, theta: float, stale: bool = False) -> None:
        say(
            counters[robot].make(
                Pose, x=x, y=y, theta=theta, sd_x_m=0.05, sd_y_m=0.05, sd_theta_rad=0.01, odom_x=x, odom_y=y,
                odom_theta=theta, vx=0.0, omega=0.0, uwbStale=stale,
            )
        )  # fmt: skip

    def state(robot: str, x: float, y: float, theta: float, **over: Any) -> State:
        at = AgvPosition(x=x, y=y, theta=theta, mapId="office", positionInitialized=True, localizationScore=0.9)
        return harness_state(counters[robot], agvPosition=at, **over)

    gateway = mb.endpoint("uwb-gateway")
    gateway.start()
    status = {"gateway": "g1", "anchors": [list(a) for a in ANCHORS]}
    gateway.publish("fleetlink/uwb/g1/status", json.dumps(status).encode())
    snap = counters["r1"].make(MapSnapshot, **snapshot_fields(room(), RES, ORIGIN, 7))
    say(snap, both=False)  # a queryable's answer, as the recorder's map fetcher records it
    say(state("r1", 0.5, 0.5, 0.0, batteryState=BatteryState(batteryCharge=87.0, charging=False)))
    say(counters["r1"].make(Lease, holder="", until=0.0))
    pose("r1", 0.5, 0.5, 0.0)
    say(counters["r1"].make(Event, kind="goal_reached", text="reached (0.50, 0.50)", severity=Severity.INFO, data=()))
    clock.advance(0.2)
    say(
        state(
            "r2", 4.0, 0.5, math.pi / 4, operatingMode=OperatingMode.AUTOMATIC, driveMode="goto",
            batteryState=BatteryState(batteryCharge=42.0, charging=False), uwbStale=True,
            orderId="operator-1-order-3", goal=Goal(x=6.5, y=1.5, theta=None), driving=True,
        )
    )  # fmt: skip
    say(counters["r2"].make(Lease, holder=ME, until=clock.wall() + 60))
    for k in range(6):
        clock.advance(0.05)
        pose("r2", 2.5 + 0.25 * k, -0.25 + 0.125 * k, math.pi / 4, stale=True)
    say(
        counters["r2"].make(
            Event,
            kind="guard_refusal",
            text="obstacle 0.35 m ahead: forward refused",
            severity=Severity.WARNING,
            data=(),
        )
    )
    other = wire.HeaderCounter(clock, robot="r1", sender="operator-2")
    mark = other.make(Mark, markId="op2-1", x=5.5, y=3.0, label="victim", kind="casualty", sd_m=0.0, removed=False)
    say(mark, both=False)  # on Zenoh only, from r1's endpoint
    zb.deliver()
    clock.advance(0.1)
    console.poll()
    wait_until(lambda: recorder.core.messages["/fleetlink/zenoh/marks"] == 1, message="everything recorded")
    with lock:
        rows = {
            r: [str(c) for c in row]
            for r, row in fleet_rows(live, console.active, console.health, ME, clock.now()).items()
        }
        views = {
            r: (v.mode, v.battery, v.pose, v.goal, v.lease_holder, v.uwb_stale, tuple(v.trail))
            for r, v in live.robots.items()
        }
        marks = sorted(m.markId for m in live.live_marks())
    console.close()
    recorder.stop()
    return {"rows": rows, "views": views, "marks": marks}, clock


def replayed(path: Path) -> ReplaySource:
    source = ReplaySource(path)
    source.play_until(source.last)
    source.clock.hold(source.last)
    return source


def test_replay_shows_the_fleet_the_live_console_showed(tmp_path: Path) -> None:
    path = tmp_path / "scene.mcap"
    live, clock = record_scene(path)
    source = ReplaySource(path)
    fleet, lock, _m, _d = console_parts(source)
    source.play_until(source.last)
    source.clock.hold(source.last)
    assert source.clock.now() == pytest.approx(clock.now())
    with lock:
        rows = fleet_rows(fleet, source.active, source.health, ME, source.clock.now())
        assert {r: [str(c) for c in row] for r, row in rows.items()} == live["rows"]
        views = {
            r: (v.mode, v.battery, v.pose, v.goal, v.lease_holder, v.uwb_stale, tuple(v.trail))
            for r, v in fleet.robots.items()
        }
        assert views == live["views"]
        assert sorted(m.markId for m in fleet.live_marks()) == live["marks"]
        assert set(fleet.anchors) == {a[0] for a in ANCHORS}
    assert source.fetch_map("r1") is not None and source.skipped == {}
    with pytest.raises(ReadOnlyReplay):
        source.send(Pose, "r1")
    assert source.refused == {"pose": 1}


def test_replay_plays_at_speed_and_seeks(tmp_path: Path) -> None:
    path = tmp_path / "scene.mcap"
    record_scene(path)
    source = ReplaySource(path, speed=50.0, start_s=0.25)
    fleet, lock, _m, _d = console_parts(source)
    source.start()
    try:
        with lock:
            assert "r2" in fleet.robots and fleet.robots["r1"].pose == (0.5, 0.5, 0.0)  # what came before 0.25 s
        wait_until(lambda: source.done, timeout=5, message="played to the end at 50x")
        with lock:
            assert fleet.robots["r2"].pose is not None and fleet.robots["r2"].pose[0] == pytest.approx(3.75)
        wait_until(lambda: source.clock.now() == pytest.approx(source.last), timeout=5, message="the end")
        source.seek(0.25)  # back: the player, waiting at the end, plays on from there
        assert not source.done and source.delivered < source.total
        with lock:
            assert fleet.robots["r2"].pose is not None and fleet.robots["r2"].pose[0] == pytest.approx(2.5)
        wait_until(lambda: source.done, timeout=5, message="played to the end again")
        with lock:
            assert fleet.robots["r2"].pose is not None and fleet.robots["r2"].pose[0] == pytest.approx(3.75)
    finally:
        source.close()


def test_replayed_console_snapshot(snap_compare: Any, tmp_path: Path) -> None:
    """The replayed scene in a read-only console: READ-ONLY in the status line, the fleet table and
    map as recorded; a drive key is refused with a notice and nothing is sent."""
    path = tmp_path / "scene.mcap"
    record_scene(path)
    source = ReplaySource(path)
    app, fetchers = replay_app(source)
    for fetcher in fetchers:
        fetcher.stop()  # the map is handed over below, in step with the frames
    source.play_until(source.last)
    source.clock.hold(source.last)
    maps = app.feed.maps
    assert maps is not None
    snap = source.fetch_map("r1")
    assert snap is not None
    with app.lock:
        assert maps.on_snapshot("r1", snap)

    async def drive(pilot: Any) -> None:
        await pilot.press("i")
        await asyncio.sleep(0)

    assert snap_compare(app, terminal_size=SIZE, run_before=before(lambda _p: None, drive))
    assert source.refused == {}


def test_a_long_recording_is_played_chunk_by_chunk_not_held(tmp_path: Path) -> None:
    """``ReplaySource`` reads a recording through its index as it plays (``FleetStream``): opening
    it reads the summary only, playing to a time reads the chunks up to that time, a seek to the
    end reads each remaining chunk once, and a seek back reads the chunks up to its target again;
    no list of the recording's messages is ever made."""
    clock = SteppedClock()
    bus = InProcessBus(LinkName.ZENOH, clock_now=clock.now)
    path = tmp_path / "long.mcap"
    recorder = Recorder(path, [bus.endpoint("recorder")], clock, fetch_maps=False, chunk_size=16 * 1024)
    recorder.start()
    agent = bus.endpoint("agent-r1")
    agent.start()
    counter = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    n = 3000  # 150 s of one robot's poses at 20 Hz
    for i in range(n):
        p = counter.make(
            Pose, x=i * 0.001, y=0.0, theta=0.0, sd_x_m=0.05, sd_y_m=0.05, sd_theta_rad=0.01,
            odom_x=0.0, odom_y=0.0, odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=False,
        )  # fmt: skip
        agent.publish(wire.key_of(p), wire.encode(p))
        bus.deliver()
        clock.advance(0.05)
        if i % 200 == 0:
            wait_until(lambda i=i: recorder.core.messages["/fleetlink/zenoh/pose"] > i, message="recorded")
    wait_until(lambda: recorder.core.messages["/fleetlink/zenoh/pose"] == n, message="all recorded")
    recorder.stop()
    size = path.stat().st_size

    from mcap.reader import make_reader

    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) >= 20  # a long file: many chunks

    source = ReplaySource(path)
    try:
        assert source.total == n and source.stream.complete and source.stream.indexed
        opened = source.stream.bytes_read
        assert opened < size / 10  # the summary (and the first chunk, for the first message)
        assert source.delivered == 0
        heard: list[float] = []
        source.add_sink(lambda msg, link, t: heard.append(msg.x))  # type: ignore[attr-defined]
        source.play_until(source.first + 0.25 * (source.last - source.first))
        quarter = source.stream.bytes_read
        assert abs(source.delivered - n // 4) <= 2
        assert quarter < size / 2  # only the chunks up to that time
        source.seek(source.last - source.first)  # to the end: the rest, each chunk once
        assert source.done and source.delivered == n
        assert heard == sorted(heard) and len(heard) == n  # in order, every one, once
        assert source.stream.bytes_read < 1.2 * size  # each chunk read once, not the file again
        # Back to the middle: the recording is read again from its start up to there (the fleet
        # model is cumulative), so a seek back costs the chunks before its target once more.
        at_end = source.stream.bytes_read
        heard.clear()
        source.seek(0.5 * (source.last - source.first))
        again = source.stream.bytes_read - at_end
        assert abs(source.delivered - n // 2) <= 2 and heard == sorted(heard) and len(heard) == source.delivered
        chunks = at_end - opened  # every chunk read once (here ~57 % of the file)
        assert 0.4 * chunks < again < 0.6 * chunks + opened
    finally:
        source.close()
    # Nothing holds the recording: the source keeps an iterator and the next message only.
    assert not any(isinstance(v, list) and len(v) > 100 for v in vars(source).values())

    # A recorder that crashed leaves no index: the file is read in file order (twice: its span,
    # then as it plays), in time order, up to the damage.
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: int(size * 0.6)])
    source = ReplaySource(cut)
    try:
        assert not source.stream.indexed and not source.complete and source.problem is not None
        xs: list[float] = []
        source.add_sink(lambda msg, link, t: xs.append(msg.x))  # type: ignore[attr-defined]
        source.play_until(source.last)
        assert source.done and 0.4 * n < len(xs) == source.total < 0.7 * n and xs == sorted(xs)
        xs.clear()
        source.seek(0.0)  # back: read in file order again, from its start
        assert xs == sorted(xs) and len(xs) == source.delivered < 0.05 * n and not source.done
        source.play_until(source.last)
        assert source.done and len(xs) == source.total and xs == sorted(xs)
    finally:
        source.close()


def test_a_replayed_console_follows_maps_and_dose_layers_past_their_recorded_snapshots(tmp_path: Path) -> None:
    """A robot's map and dose layer change after the recorder fetched their snapshots (it fetches
    a robot's snapshot when it hears an update it cannot follow, the dose layer's as the map's).
    The replay answers the console's fetches as the robot would have at the time played: the
    recorded snapshot with the updates played since, so a console that fetches late has the last
    picture and follows the updates after it (a console given the recorded snapshot as it was would
    refuse every later update: it does not follow its copy)."""
    from fleetlink.shared import dose_codec, map_codec
    from fleetlink.shared.dose import Lamp
    from fleetlink.shared.dose_codec import SharedDose
    from fleetlink.shared.map_codec import SharedMap
    from fleetlink.shared.messages import DoseSnapshot, DoseUpdate, MapUpdate

    clock = SteppedClock()
    bus = InProcessBus(LinkName.ZENOH, clock_now=clock.now)
    path = tmp_path / "layers.mcap"
    recorder = Recorder(path, [bus.endpoint("recorder")], clock).start()
    agent = bus.endpoint("agent-r1")
    counter = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    res, origin = 0.1, (-0.05, -0.05)
    cells = np.full((20, 30), -1, dtype=np.int8)
    dose = np.zeros((20, 30))
    common = {"target_j_m2": 100.0, "lamp_on_s": 1.0, "unplaced_s": 0.0}
    now = {"map": 7, "dose": 3}

    def answer(key: str) -> list[tuple[str, bytes]]:  # the robot's queryables: its layers as they are now
        if key.endswith("/map"):
            msg: wire.Message = counter.make(MapSnapshot, **map_codec.snapshot_fields(cells, res, origin, now["map"]))
        else:
            fields = dose_codec.snapshot_fields(dose, res, origin, now["dose"], **common, lamp=Lamp(10.0, 0.6))
            assert fields is not None
            msg = counter.make(DoseSnapshot, **fields)
        return [(key, wire.encode(msg))]

    agent.serve("fleetlink/v1/r1/map", answer)
    agent.serve("fleetlink/v1/r1/dose", answer)
    agent.start()

    def change(k: int) -> None:
        """The robot sees a wall and its lamp doses a spot, and publishes both patches."""
        box = (k, k, k + 2, k + 2)
        cells[k : k + 2, k : k + 2] = 100
        dose[k : k + 2, k : k + 2] += 40.0
        m = map_codec.patch_fields(cells, res, origin, box, now["map"] + 1, now["map"])
        d = dose_codec.patch_fields(dose, res, origin, box, now["dose"] + 1, now["dose"], **common)
        assert m is not None and d is not None
        now["map"] += 1
        now["dose"] += 1
        for msg in (counter.make(MapUpdate, **m), counter.make(DoseUpdate, **d)):
            agent.publish(wire.key_of(msg), wire.encode(msg))
        bus.deliver()
        clock.advance(1.0)

    try:
        change(0)  # the first updates heard: the recorder fetches both snapshots
        wait_until(
            lambda: recorder.core.messages["/fleetlink/zenoh/map"] and recorder.core.messages["/fleetlink/zenoh/dose"],
            message="both snapshots fetched and recorded",
        )
        for k in range(2, 8, 2):  # then they change three more times
            change(k)
        wait_until(lambda: recorder.core.messages["/fleetlink/zenoh/dose/updates"] == 4, message="all recorded")
    finally:
        recorder.stop()

    # The console asks only once everything has been played: it gets the layers as they ended.
    source = replayed(path)
    got_map, got_dose = source.fetch_map("r1"), source.fetch_dose("r1")
    assert got_map is not None and got_dose is not None
    assert (got_map.version, got_dose.version) == (now["map"], now["dose"])
    assert (SharedMap.from_snapshot(got_map).cells == cells).all()
    assert np.allclose(SharedDose.from_snapshot(got_dose).cells, dose)
    # A console that fetched right after the snapshots were recorded follows every update after them.
    source = ReplaySource(path)
    _fleet, lock, maps, doses = console_parts(source)
    first = min(m.log_time_ns for m in source.stream.messages() if m.topic == "/fleetlink/zenoh/dose") / 1e9
    source.play_until(first)
    early_map, early_dose = source.fetch_map("r1"), source.fetch_dose("r1")
    assert early_map is not None and early_dose is not None and early_map.version < now["map"]
    with lock:
        assert maps.on_snapshot("r1", early_map) and doses.on_snapshot("r1", early_dose)
    source.play_until(source.last)
    with lock:
        assert maps.maps["r1"].version == now["map"] and doses.layers["r1"].version == now["dose"]
        assert (maps.maps["r1"].cells == cells).all() and np.allclose(doses.layers["r1"].cells, dose)


def test_the_replayed_console_seeks_forward_and_changes_speed(tmp_path: Path) -> None:
    """``:seek S`` / ``:seek +S`` jump the replay forward (everything before the target delivered at
    once, off the UI thread), ``:speed X`` changes its speed, ``:seek 0`` goes back; a seek that is
    not a time is refused with a notice and moves nothing."""
    from tests.test_console import screen_text, type_text

    path = tmp_path / "scene.mcap"
    record_scene(path)
    source = ReplaySource(path, speed=0.001)  # all but still: only the commands move it
    app, fetchers = replay_app(source)

    async def run() -> None:
        async with app.run_test(size=SIZE) as pilot:
            source.start()

            async def command(text: str) -> None:
                await pilot.press("colon")
                await type_text(pilot, text)
                await pilot.press("enter")
                await pilot.pause()

            assert source.position < 0.05 and source.delivered < source.total
            await command("seek 0.3")
            await asyncio.to_thread(wait_until, lambda: source.position >= 0.3, message="the seek")
            assert source.delivered < source.total  # the marks came later
            await asyncio.to_thread(wait_until, lambda: "replay at 0.3 s" in screen_text(app), message="said")
            await command("seek +10")  # past the end: the end
            await asyncio.to_thread(wait_until, lambda: source.delivered == source.total, message="the rest")
            await command("speed 4")
            await asyncio.to_thread(wait_until, lambda: "replay at 4x" in screen_text(app), message="speed")
            assert source.speed == 4.0
            await command("speed 0.001")  # all but still again
            for bad in ("seek nan", "seek --1", "seek x"):
                await command(bad)
                assert "bad command" in screen_text(app) and source.delivered == source.total
            await command("seek 0")  # back to the start
            await asyncio.to_thread(wait_until, lambda: source.delivered < source.total, message="back")
            await asyncio.to_thread(wait_until, lambda: "replay at 0.0 s" in screen_text(app), message="said")
            assert source.refused == {}

    run_closing(run, source, fetchers)


# -- seeking back ------------------------------------------------------------------------------------

CHANGES_S = 8.0
"""The length of ``record_changes``' scene."""


def record_changes(path: Path) -> None:
    """Two robots heard every 0.25 s for 8 s while their state changes: r2 bumps at 2 s (a latching
    alarm), r1's map and dose layer change at 4 s (after their snapshots at 0 s), r1's battery goes
    low and its e-stop button is pressed and r2 starts a goal at 5 s, a mark is set and r1 reports a cliff at 6 s."""
    from fleetlink.shared import dose_codec, map_codec
    from fleetlink.shared.dose import Lamp
    from fleetlink.shared.messages import DoseSnapshot, DoseUpdate, MapUpdate

    clock = SteppedClock()
    zb, mb = InProcessBus(LinkName.ZENOH, clock_now=clock.now), InProcessBus(LinkName.MQTT, clock_now=clock.now)
    recorder = Recorder(path, [zb.endpoint("recorder"), mb.endpoint("recorder")], clock, fetch_maps=False).start()
    counters, say = robots_talking(zb, mb, clock)

    def state(robot: str, x: float, **over: Any) -> State:
        at = AgvPosition(x=x, y=0.0, theta=0.0, mapId="office", positionInitialized=True, localizationScore=0.9)
        return harness_state(counters[robot], agvPosition=at, **over)

    res, origin = 0.1, (-0.05, -0.05)
    cells = np.full((20, 30), -1, dtype=np.int8)
    dose = np.zeros((20, 30))
    common = {"target_j_m2": 100.0, "lamp_on_s": 1.0, "unplaced_s": 0.0}
    gateway = mb.endpoint("uwb-gateway")
    gateway.start()
    gateway.publish(
        "fleetlink/uwb/g1/status", json.dumps({"gateway": "g1", "anchors": [list(a) for a in ANCHORS]}).encode()
    )
    say(counters["r1"].make(MapSnapshot, **map_codec.snapshot_fields(cells, res, origin, 7)), both=False)
    dose_fields = dose_codec.snapshot_fields(dose, res, origin, 3, **common, lamp=Lamp(10.0, 0.6))
    assert dose_fields is not None
    say(counters["r1"].make(DoseSnapshot, **dose_fields), both=False)
    say(state("r1", 0.0, batteryState=BatteryState(batteryCharge=80.0, charging=False)))
    say(state("r2", 4.0, batteryState=BatteryState(batteryCharge=60.0, charging=False)))
    other = wire.HeaderCounter(clock, robot="r1", sender="operator-2")
    for k in range(int(CHANGES_S / 0.25)):
        t = k * 0.25
        for robot, x in (("r1", 0.1 * k), ("r2", 4.0)):
            say(
                counters[robot].make(
                    Pose, x=x, y=0.0, theta=0.0, sd_x_m=0.05, sd_y_m=0.05, sd_theta_rad=0.01, odom_x=x, odom_y=0.0,
                    odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=False,
                )
            )  # fmt: skip
        if t == 2.0:
            say(counters["r2"].make(Event, kind="bump", text="bumper pressed", severity=Severity.WARNING, data=()))
        if t == 4.0:
            cells[2:4, 2:4] = 100
            dose[2:4, 2:4] += 40.0
            m = map_codec.patch_fields(cells, res, origin, (2, 2, 4, 4), 8, 7)
            d = dose_codec.patch_fields(dose, res, origin, (2, 2, 4, 4), 4, 3, **common)
            assert m is not None and d is not None
            say(counters["r1"].make(MapUpdate, **m), both=False)
            say(counters["r1"].make(DoseUpdate, **d), both=False)
        if t == 5.0:
            say(
                state(
                    "r1", 0.1 * k, batteryState=BatteryState(batteryCharge=8.0, charging=False),
                    safetyState=SafetyState(eStop=EStop.MANUAL, fieldViolation=False),
                )
            )  # fmt: skip
            say(
                state(
                    "r2", 4.0, operatingMode=OperatingMode.AUTOMATIC, driveMode="goto", orderId="operator-1-order-1",
                    goal=Goal(x=6.5, y=1.5, theta=None), driving=True,
                    batteryState=BatteryState(batteryCharge=60.0, charging=False),
                )
            )  # fmt: skip
        if t == 6.0:
            mark = other.make(
                Mark, markId="op2-1", x=5.5, y=3.0, label="victim", kind="casualty", sd_m=0.0, removed=False
            )
            say(mark, both=False)  # on Zenoh only, from r1's endpoint
            zb.deliver()
            say(counters["r1"].make(Event, kind="cliff", text="cliff ahead", severity=Severity.ERROR, data=()))
        clock.advance(0.25)
    wait_until(lambda: recorder.core.messages["/fleetlink/zenoh/marks"] == 1, message="everything recorded")
    wait_until(lambda: recorder.core.messages["/fleetlink/mqtt/pose"] == 2 * CHANGES_S / 0.25, message="all poses")
    recorder.stop()


def console_state(source: ReplaySource, fleet: Any, lock: threading.Lock, maps: Any, doses: Any) -> dict[str, Any]:
    """What a console shows of ``fleet`` at the replay's time: the robots (every field of each,
    trails included), the marks, the alarms, the anchors, the fleet table's cells (link and health
    columns, ages), what the replay answers for r1's map and dose layer and the copies the console
    holds."""
    now = source.clock.now()
    got_map, got_dose = source.fetch_map("r1"), source.fetch_dose("r1")
    with lock:
        fleet.tick(now)  # (as a console's frame does)
        return {
            "robots": {r: dataclasses.replace(v, trail=list(v.trail)) for r, v in fleet.robots.items()},
            "marks": dict(fleet.marks),
            "mark_sets": dict(fleet.mark_sets),
            "alarms": [dataclasses.astuple(a) for a in fleet.alarms.rows()],
            "anchors": dict(fleet.anchors),
            "rows": {
                r: [str(c) for c in row] for r, row in fleet_rows(fleet, source.active, source.health, ME, now).items()
            },
            "answers": (got_map and got_map.version, got_dose and got_dose.version),
            "copies": ({r: m.version for r, m in maps.maps.items()}, {r: d.version for r, d in doses.layers.items()}),
        }


def started_at(path: Path, seconds: float, then: float | None = None) -> dict[str, Any]:
    """What a console started with ``--start seconds`` shows (at that moment: time all but still),
    or after it seeks on to ``then``."""
    source = ReplaySource(path, speed=1e-9, start_s=seconds)
    fleet, lock, maps, doses = console_parts(source)
    source.start()
    try:
        fetch(source, lock, maps, doses)
        if then is not None:
            source.seek(then)
            fetch(source, lock, maps, doses)
        return console_state(source, fleet, lock, maps, doses)
    finally:
        source.close()


def fetch(source: ReplaySource, lock: threading.Lock, maps: Any, doses: Any) -> None:
    """The console's fetchers' turn: r1's map and dose layer as the replay answers them now."""
    got_map, got_dose = source.fetch_map("r1"), source.fetch_dose("r1")
    with lock:
        if got_map is not None:
            maps.on_snapshot("r1", got_map)
        if got_dose is not None:
            doses.on_snapshot("r1", got_dose)


def test_a_seek_back_shows_what_a_replay_started_there_shows(tmp_path: Path) -> None:
    """Played to the end, then ``seek`` back to 3.1 s (before the battery, the e-stop, the goal, the map and dose
    changes, the mark and the cliff): the console shows what one started with ``--start 3.1``
    shows, not what it heard later; then forward again to 6.1 s, and back once more."""
    path = tmp_path / "changes.mcap"
    record_changes(path)
    source = ReplaySource(path, speed=1e-9)
    fleet, lock, maps, doses = console_parts(source)
    restarts: list[int] = []
    source.add_restart_listener(lambda: restarts.append(source.delivered))
    source.start()
    try:
        source.seek(CHANGES_S)
        fetch(source, lock, maps, doses)
        end = console_state(source, fleet, lock, maps, doses)
        assert end["marks"] and end["answers"] == (8, 4) and end["copies"] == ({"r1": 8}, {"r1": 4})
        assert {(a[0], a[1]) for a in end["alarms"]} == {("r1", "estop"), ("r1", "cliff"), ("r2", "bump")}
        assert end["robots"]["r2"].goal is not None
        assert restarts == []

        source.seek(3.1)
        assert restarts == [0]  # the listeners forgot before anything was played again
        fetch(source, lock, maps, doses)
        back = console_state(source, fleet, lock, maps, doses)
        assert back == started_at(path, 3.1)
        assert not back["marks"] and back["answers"] == (7, 3) and back["copies"] == ({"r1": 7}, {"r1": 3})
        assert [(a[0], a[1]) for a in back["alarms"]] == [("r2", "bump")]
        assert back["robots"]["r2"].goal is None and back["robots"]["r1"].battery == 80.0

        source.seek(6.1)  # forward again: on from 3.1 s (not from the start), as if started there
        assert restarts == [0]
        fetch(source, lock, maps, doses)
        assert console_state(source, fleet, lock, maps, doses) == started_at(path, 3.1, then=6.1)

        source.seek(5.1)
        assert len(restarts) == 2
        fetch(source, lock, maps, doses)
        assert console_state(source, fleet, lock, maps, doses) == started_at(path, 5.1)
        assert source.skipped == {} and source.refused == {}
    finally:
        source.close()


def test_a_seek_to_a_time_that_is_not_one_is_refused_and_moves_nothing(tmp_path: Path) -> None:
    path = tmp_path / "changes.mcap"
    record_changes(path)
    source = ReplaySource(path, speed=1e-9, start_s=6.1)
    fleet, lock, maps, doses = console_parts(source)
    source.start()
    try:
        before = console_state(source, fleet, lock, maps, doses), source.delivered, source.position
        for bad in (math.nan, -1.0, -math.inf, math.inf):
            with pytest.raises(ValueError, match="refused"):
                source.seek(bad)
        assert (console_state(source, fleet, lock, maps, doses), source.delivered, source.position) == before
    finally:
        source.close()


def test_the_replayed_console_seeks_back_to_what_a_console_started_there_shows(tmp_path: Path) -> None:
    """In the read-only console: played to the end (the e-stop, the cliff, the mark), then ``:seek
    3.1`` back, ``:seek +3`` on and ``:seek -1`` back: each time the console's robots, marks, alarms,
    fleet table and the map and dose layer its fetchers took are those of a console started with
    ``--start`` there (after ``+3``: one started at 3.1 s that seeks on), and the notices of the
    moments it went back before are gone."""
    from tests.test_console import screen_text, type_text

    path = tmp_path / "changes.mcap"
    record_changes(path)
    source = ReplaySource(path, speed=1e-9)  # still: only the commands move it
    app, fetchers = replay_app(source)
    assert app.feed.maps is not None

    def shown() -> dict[str, Any]:
        return console_state(source, app.fleet, app.lock, app.feed.maps, app.doses)

    async def run() -> None:
        async with app.run_test(size=SIZE) as pilot:
            source.start()

            async def seek(text: str, expected: dict[str, Any]) -> dict[str, Any]:
                await pilot.press("colon")
                await type_text(pilot, text)
                await pilot.press("enter")
                said = f"replay at {expected['at']:.1f} s"
                await asyncio.to_thread(wait_until, lambda: said in screen_text(app), message=said)
                # The fetchers ask for the robots the console knows again: until they have.
                await asyncio.to_thread(
                    wait_until, lambda: shown()["copies"] == expected["copies"], message=f"{text}: fetched"
                )
                await pilot.pause()
                return shown()

            end = await seek("seek 8", started_at(path, CHANGES_S) | {"at": CHANGES_S})
            assert end["marks"] and end["copies"] == ({"r1": 8}, {"r1": 4})
            assert {(a[0], a[1]) for a in end["alarms"]} == {("r1", "estop"), ("r1", "cliff"), ("r2", "bump")}
            assert "e-stop" in screen_text(app)

            expected = started_at(path, 3.1)
            assert await seek("seek 3.1", expected | {"at": 3.1}) == expected
            assert not expected["marks"] and expected["copies"] == ({"r1": 7}, {"r1": 3})
            assert "e-stop" not in screen_text(app)  # the notices of the moments after 3.1 s are gone

            expected = started_at(path, 3.1, then=6.1)
            assert await seek("seek +3", expected | {"at": 6.1}) == expected
            assert "e-stop" in screen_text(app)

            expected = started_at(path, 5.1)
            assert await seek("seek -1", expected | {"at": 5.1}) == expected
            assert source.refused == {} and source.skipped == {}

    run_closing(run, source, fetchers)
