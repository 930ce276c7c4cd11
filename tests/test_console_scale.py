"""The console with many robots (issue 18): a frame works out only what changed and what is on
screen, and a drive key never waits for telemetry or a frame. Behaviour, not timings
(bench/console.py measures those)."""

from __future__ import annotations

import math
import random
from pathlib import Path
from typing import Any

import pytest
from textual import events
from textual.geometry import Region

from fleetlink.operator import console as console_module
from fleetlink.operator.fleet import TRAIL_POINTS, FleetModel
from fleetlink.operator.fleet_table import ROWS_PER_FRAME, FleetTable
from fleetlink.operator.maprender import MapFrame, MapGeometry, MapPainter
from fleetlink.operator.mapview import MapView
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import Lease, Pose, Teleop
from tests.test_console import ME, Rig, run_async, settle

ROBOTS = [f"r{i:02d}" for i in range(60)]


def counting_updates(table: FleetTable) -> list[tuple[str, str]]:
    updates: list[tuple[str, str]] = []
    real = table.update_cell

    def counting(row: Any, column: Any, value: Any, **kw: Any) -> None:
        updates.append((str(row), str(column)))
        real(row, column, value, **kw)

    table.update_cell = counting  # type: ignore[method-assign]
    return updates


@run_async
async def test_a_row_update_changes_only_that_row_and_rows_off_screen_wait_until_shown(tmp_path: Path) -> None:
    rig = Rig(tmp_path, clock=SimClock(start=100.0))  # ages stand still: only what is sent changes
    rig.link.start()
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            for i, robot in enumerate(ROBOTS):
                rig.pose(robot, float(i), 0.0, links=("zenoh",))
            await settle(pilot, 0.4)
            table = rig.app.query_one(FleetTable)
            assert [str(k.value) for k in table.rows] == ROBOTS
            first, end = table.visible_range()
            assert first == 0 and end < len(ROBOTS)  # the test needs rows off screen
            updates = counting_updates(table)

            rig.zenoh.inject(rig.counter("r01").make(Lease, holder="", until=0.0))
            await settle(pilot, 0.4)
            assert updates == [("r01", "lease")]
            assert table.get_cell("r01", "lease") == "free"

            updates.clear()
            rig.zenoh.inject(rig.counter("r59").make(Lease, holder="op-bob", until=0.0))
            await settle(pilot, 0.4)
            assert updates == []  # off screen: not worked out, not redrawn
            assert table.get_cell("r59", "lease") == "-"

            table.move_cursor(row=len(ROBOTS) - 1)  # scrolls to it: the next frame brings it up to date
            await settle(pilot, 0.4)
            assert ("r59", "lease") in updates
            assert table.get_cell("r59", "lease") == "op-bob"
    finally:
        rig.link.close()


@run_async
async def test_a_frame_redraws_a_few_rows_in_turn_until_every_row_on_screen_is_current(tmp_path: Path) -> None:
    rig = Rig(tmp_path, clock=SimClock(start=100.0))
    rig.link.start()
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            for i, robot in enumerate(ROBOTS):
                rig.pose(robot, float(i), 0.0, links=("zenoh",))
            await settle(pilot, 0.4)
            table = rig.app.query_one(FleetTable)
            first, end = table.visible_range()
            on_screen = ROBOTS[first:end]
            assert len(on_screen) > 2 * ROWS_PER_FRAME
            rows = {r: tuple(table.get_row(r)) for r in ROBOTS}
            updates = counting_updates(table)
            frames = 0
            while any(table.get_cell(r, "lease") != "op-bob" for r in on_screen):
                updates.clear()
                table.show_lazy(ROBOTS, lambda r: (*rows[r][:-1], "op-bob"))  # every row changed
                frames += 1
                redrawn = {r for r, _ in updates}
                assert 0 < len(redrawn) <= ROWS_PER_FRAME
                assert redrawn <= set(on_screen)
            assert frames == math.ceil(len(on_screen) / ROWS_PER_FRAME)  # each row once, in turn
    finally:
        rig.link.close()


@run_async
async def test_a_drive_key_sends_its_teleop_before_queued_telemetry_and_frames(tmp_path: Path) -> None:
    rig = Rig(tmp_path, clock=SimClock(start=100.0))
    rig.link.start()
    slice_s = console_module.DRAIN_SLICE_S
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            rig.pose("r00", 0.0, 0.0, links=("zenoh",))
            await settle(pilot, 0.4)
            assert rig.app.selected == "r00"
            frames = len(rig.app.frame_times)
            waiting: list[int] = []
            publish = rig.zenoh.publish

            def stamped(key: str, payload: bytes) -> bool:
                if "/teleop" in key:
                    waiting.append(len(rig.app.feed._inbox))
                return publish(key, payload)

            rig.zenoh.publish = stamped  # type: ignore[method-assign]
            console_module.DRAIN_SLICE_S = 0.0  # the smallest slices: 32 items each
            for k in range(2000):  # a burst of telemetry (2000 robots: one robot's poses fold into one), a frame due
                rig.pose(f"b{k:04d}", 0.001 * k, 0.0, links=("zenoh",))
            rig.app._changed()
            rig.app.post_message(events.Key("i", "i"))
            await settle(pilot, 0.5)
            assert len(waiting) >= 1
            assert waiting[0] > 1000  # sent while most of the burst still waited to be folded in
            assert len(rig.app.frame_times) > frames and not rig.app.feed.pending  # then all of it
            drives = [t for t in rig.zenoh.messages(Teleop) if t.v > 0]
            assert drives and drives[0].header.robot == "r00"
            assert len(rig.fleet.robots) == 2001 and rig.fleet.robots["b1999"].pose == (1.999, 0.0, 0.0)
    finally:
        console_module.DRAIN_SLICE_S = slice_s
        rig.link.close()


@run_async
async def test_frames_that_take_long_come_less_often(tmp_path: Path) -> None:
    clock = SimClock(start=100.0)
    rig = Rig(tmp_path, clock=clock)
    rig.link.start()
    real_show = FleetTable.show_lazy

    def slow_show(self: FleetTable, *args: Any) -> None:
        clock.advance(0.05)  # a frame that takes 50 ms to work out
        real_show(self, *args)

    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            assert rig.app.frame_period() == 0.1  # 1 / refresh_hz
            FleetTable.show_lazy = slow_show  # type: ignore[method-assign]
            rig.app._draw()
            assert rig.app.frame_period() == pytest.approx(0.05 * console_module.FRAME_SPACING)  # 0.2 s
            FleetTable.show_lazy = real_show  # type: ignore[method-assign]
            rig.app._draw()
            assert rig.app.frame_period() == 0.1
            await pilot.pause()
    finally:
        FleetTable.show_lazy = real_show  # type: ignore[method-assign]
        rig.link.close()


@run_async
async def test_the_map_refreshes_only_the_lines_that_changed(tmp_path: Path) -> None:
    rig = Rig(tmp_path, clock=SimClock(start=100.0))
    rig.link.start()
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            rig.pose("r00", 0.0, 0.0, links=("zenoh",))
            rig.pose("r01", 2.0, 2.0, links=("zenoh",))
            await settle(pilot, 0.4)
            view = rig.app.query_one(MapView)
            refreshed: list[Region] = []
            real = view.refresh

            def recording(*regions: Region, **kw: Any) -> Any:
                refreshed.extend(regions)
                return real(*regions, **kw)

            view.refresh = recording  # type: ignore[method-assign]
            _, row = view.geometry.to_cell(2.0, 2.0)
            rig.pose("r01", 2.5, 2.0, links=("zenoh",))  # along its line
            await settle(pilot, 0.4)
            assert refreshed and {r.y for r in refreshed} == {row}
            assert all(r.height == 1 for r in refreshed)
    finally:
        rig.link.close()


def same_frames(a: MapFrame, b: MapFrame) -> bool:
    return bool((a.codes == b.codes).all()) and a.glyphs == b.glyphs


def test_the_maps_kept_trails_match_drawing_from_scratch() -> None:
    """Trails are kept by their new and dropped points: after many poses (past the trail's
    length, robots crossing one another's pixels, a view change) the frame is the one a painter
    drawing from scratch gives."""
    fleet = FleetModel(ME)
    painter = MapPainter()
    geometry = MapGeometry(60, 20, scale=0.2)
    rnd = random.Random(7)
    counters = {r: wire.HeaderCounter(SimClock(start=1.0), robot=r, sender=f"agent-{r}") for r in ("r1", "r2", "r3")}
    for step in range(3 * TRAIL_POINTS):
        for i, counter in enumerate(counters.values()):
            th = 0.05 * step + i
            x, y = 2 * math.cos(th) + rnd.uniform(-0.1, 0.1), 1.5 * math.sin(th)
            msg = counter.make(
                Pose, x=x, y=y, theta=th, sd_x_m=0.05, sd_y_m=0.05, sd_theta_rad=0.01, odom_x=x, odom_y=y,
                odom_theta=th, vx=0.0, omega=0.0, uwbStale=False,
            )  # fmt: skip
            fleet.apply(msg, "zenoh", 1.0 + step)
        if step % 37 == 0:
            frame = painter.paint(fleet, geometry, "r1")
            assert same_frames(frame, MapPainter().paint(fleet, geometry, "r1"))
        if step == 300:
            geometry.pan(3, 1)
    frame = painter.paint(fleet, geometry, "r1")
    assert same_frames(frame, MapPainter().paint(fleet, geometry, "r1"))
    assert painter.trail_points() == sum(
        1 for v in fleet.robots.values() for x, y in v.trail if geometry.inside(*geometry.to_cell(x, y))
    )
