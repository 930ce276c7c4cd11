"""The Textual console with run_test and Pilot.

The console runs on the real OperatorLink (link manager, codec, command ids) over in-memory
transports: the test sees exactly the bytes that would go on Zenoh or MQTT and injects what a
robot would say. (Real Zenoh and Mosquitto under the link: tests/test_operator_links.py; the real
field and agents: tests/e2e.)
"""

from __future__ import annotations

import asyncio
import functools
import html
import itertools
import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from textual import events
from textual.widgets import Input, Static

from fleetlink.operator.console import ConsoleApp
from fleetlink.operator.maprender import FREE, WALL
from fleetlink.operator.maps import MapFollower
from fleetlink.operator.mapview import ASPECT, MapView
from fleetlink.shared import wire
from fleetlink.shared.map_codec import snapshot_fields
from fleetlink.shared.messages import (
    ActionType,
    InstantActions,
    Lease,
    MapSnapshot,
    Mark,
    Order,
    Teleop,
)
from tests.harness.console_rig import ME, PROMPT, Rig


def run_async(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Run an async test on a fresh event loop (no pytest async plugin needed)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        return asyncio.run(fn(*args, **kwargs))

    return wrapper


async def settle(pilot: Any, seconds: float = 0.25) -> None:
    await asyncio.sleep(seconds)
    await pilot.pause()


async def with_robots(rig: Rig, pilot: Any, *robots: str) -> None:
    for i, robot in enumerate(robots):
        rig.voices[robot] = (float(i), 0.0)
    await settle(pilot)


def dedupe(drives: list[Teleop]) -> list[Teleop]:
    """Consecutive re-sends of the same twist (the 10 Hz keep-alive) collapsed into one."""
    out: list[Teleop] = []
    for t in drives:
        if not out or (out[-1].v, out[-1].omega) != (t.v, t.omega):
            out.append(t)
    return out


async def type_text(pilot: Any, text: str) -> None:
    names = {" ": "space", "-": "minus", ".": "full_stop"}
    await pilot.press(*[names.get(c, c) for c in text])


def screen_text(app: ConsoleApp) -> str:
    svg = app.export_screenshot()
    text = " ".join(re.findall(r">([^<]*)</text>", svg))
    return html.unescape(text).replace("\xa0", " ")


@run_async
async def test_keys_produce_drive_commands(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        await pilot.press("i")
        await pilot.press("j")
        await pilot.press("comma")
        await pilot.press("u")
        await pilot.press("up")
        await pilot.press("d")
        await pilot.pause()
        drives = dedupe(rig.zenoh.messages(Teleop))
        signs = [(round(t.v, 2) > 0) - (round(t.v, 2) < 0) for t in drives[:6]]
        turns = [(t.omega > 0) - (t.omega < 0) for t in drives[:6]]
        assert signs == [1, 0, -1, 1, 1, 0]
        assert turns == [0, 1, 0, 1, 0, -1]
        assert all(t.header.robot == "r1" and t.ttl_s > 0 for t in drives)
        # Speed step: q raises both speeds by 10 %.
        v0 = drives[0].v
        await pilot.press("q")
        await pilot.press("i")
        await pilot.pause()
        assert rig.zenoh.messages(Teleop)[-1].v == pytest.approx(v0 * 1.1)


@run_async
async def test_drive_repeats_at_10hz_then_auto_stop(rig: Rig) -> None:
    # The rig's repeat timeout is 2 s: a held key's repeats may come far apart on a loaded machine,
    # and a slow repeat must not read as a release.
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        for _ in range(20):  # a held key: a stream of repeats
            await pilot.press("i")
        held = rig.zenoh.messages(Teleop)
        assert len(held) >= 2 and all(t.v > 0 for t in held)
        gaps = [b.header.timestamp - a.header.timestamp for a, b in itertools.pairwise(held)]
        assert min(gaps) >= 0.09  # never faster than 10 Hz, however fast the repeats
        for _ in range(100):  # repeats stopped: the console sends stop by itself, after the timeout
            await settle(pilot, 0.1)
            if rig.zenoh.messages(Teleop)[-1].v == 0:
                break
        await settle(pilot, 0.3)  # and no more after it
        after = rig.zenoh.messages(Teleop)
        assert after[-1].v == 0 and after[-1].omega == 0
        assert sum(1 for t in after if t.v == 0 and t.omega == 0) == 1  # once, not forever
        await pilot.press("i")
        await pilot.press("space")
        await pilot.pause()
        last = rig.zenoh.messages(Teleop)[-1]
        assert (last.v, last.omega) == (0.0, 0.0)


@run_async
async def test_a_key_typed_between_a_click_and_its_dialog_does_not_drive(rig: Rig) -> None:
    """``d``, ``s`` and ``m`` answer the click's dialog and also drive: typed before the dialog is
    up (the click's message still on its way to the app), they must not send a teleop."""
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        mv = rig.app.query_one(MapView)
        before = len(rig.zenoh.messages(Teleop))
        mv.click_pending = True  # as MapView.on_click leaves it until the app has put the dialog up
        await pilot.press("d")
        await pilot.pause()
        assert rig.app._drive_key_now(events.Key("s", "s")) is False  # the input thread's path too
        assert len(rig.zenoh.messages(Teleop)) == before
        # A click answered (its dialog up, then closed): the keys drive again.
        await pilot.click("#map", offset=(3, 3))
        await pilot.pause()
        assert not mv.click_pending
        await pilot.press("n")
        await pilot.pause()
        await pilot.press("w")
        await pilot.pause()
        assert len(rig.zenoh.messages(Teleop)) > before


@run_async
async def test_click_on_map_sends_goal_at_world_coordinate(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        mv = rig.app.query_one(MapView)
        mv.geometry.center_x, mv.geometry.center_y, mv.geometry.scale = 0.0, 0.0, 0.5
        w, h = mv.content_size.width, mv.content_size.height
        col, row = 10, 5
        await pilot.click("#map", offset=(col + 1, row + 1))  # +1: the map's border
        await pilot.pause()
        await pilot.press("y")
        await pilot.pause()
        orders = rig.zenoh.messages(Order)
        assert len(orders) == 1
        goal = orders[0].goal
        assert goal.x == pytest.approx((col + 0.5 - w / 2) * 0.5)
        assert goal.y == pytest.approx(-(row + 0.5 - h / 2) * 0.5 * ASPECT)
        # Cancel: nothing sent.
        await pilot.click("#map", offset=(3, 3))
        await pilot.pause()
        await pilot.press("n")
        await pilot.pause()
        assert len(rig.zenoh.messages(Order)) == 1


@pytest.mark.slow
@run_async
async def test_typed_goal_home_and_payload(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        await pilot.press("colon")
        await type_text(pilot, "goal 3.5 -2 90")
        await pilot.press("enter")
        await pilot.pause()
        order = rig.zenoh.messages(Order)[-1]
        assert (order.goal.x, order.goal.y) == (3.5, -2.0)
        assert order.goal.theta == pytest.approx(1.5708, abs=1e-3)
        await pilot.press("h")
        await pilot.press("p")
        await pilot.pause()
        home = rig.zenoh.messages(Order)[-1]
        assert home.returnHome and home.goal is None
        action = rig.zenoh.messages(InstantActions)[-1].actions[0]
        params = {kv.key: kv.value for kv in action.actionParameters}
        assert action.actionType is ActionType.PAYLOAD and params == {"device": "uv", "on": "true"}
        await pilot.press("colon")
        await type_text(pilot, "payload atomiser 2")
        await pilot.press("enter")
        await pilot.pause()
        action = rig.zenoh.messages(InstantActions)[-1].actions[0]
        params = {kv.key: kv.value for kv in action.actionParameters}
        assert params == {"device": "atomiser", "on": "true", "level": "2"}
        await pilot.press("colon")
        await type_text(pilot, "goal nan 1")
        await pilot.press("enter")
        await pilot.pause()
        assert len(rig.zenoh.messages(Order)) == 2  # refused, with a notice
        assert "bad command" in screen_text(rig.app)


@run_async
async def test_keys_typed_right_after_colon_go_to_the_command_line_not_to_teleop(rig: Rig) -> None:
    """A fast typist (or a paste, or tmux) sends ':goal 1.5 2' in one burst: every key after the
    colon belongs to the command line. Were the focus moved later, 'l' would turn the robot."""
    from textual import events

    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        names = {" ": "space", ".": "full_stop", ":": "colon"}
        burst = [events.Key(names.get(c, c), c) for c in ":goal 1.5 2"] + [events.Key("enter", "\r")]
        for key in burst:  # as the terminal driver delivers them: all queued before the first is handled
            key.set_sender(rig.app)
            rig.app._driver.send_message(key)  # what pilot.press does, without waiting between keys
        await pilot.pause()
        await pilot.pause()
        # On a loaded machine the link manager may have moved commands to MQTT (the rig's primary
        # "silent" for a few hundred ms): the order counts on whichever link carried it.
        order = await rig.last_order(pilot)
        assert rig.zenoh.messages(Teleop) == [] and rig.mqtt.messages(Teleop) == []
        assert (order.goal.x, order.goal.y) == (1.5, 2.0)
        # In the command line a colon is just a character.
        await pilot.press("colon")
        await type_text(pilot, "mark hazard 1 2 gas:leak")
        await pilot.press("enter")
        await pilot.pause()
        assert rig.zenoh.messages(Mark)[-1].label == "gas:leak"


@run_async
async def test_mark_flow_shared_and_saved(rig: Rig, tmp_path: Path) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        await pilot.click("#map", offset=(20, 8))
        await pilot.pause()
        await pilot.press("m")
        await pilot.pause()
        await pilot.press("colon")
        await type_text(pilot, "mark hazard 1 2 gas leak")
        await pilot.press("enter")
        await pilot.pause()
        marks = rig.zenoh.messages(Mark)
        assert [m.kind for m in marks] == ["casualty", "hazard"]
        assert (marks[1].x, marks[1].y, marks[1].label) == (1.0, 2.0, "gas leak")
        saved = json.loads(rig.marks_file.read_text())["marks"]
        assert {m["markId"] for m in saved} == {m.markId for m in marks}
        # A mark from another console arrives over Zenoh and shows up.
        other = wire.HeaderCounter(rig.clock, robot="r1", sender="operator-2")
        rig.zenoh.inject(
            other.make(Mark, markId="op2-1", x=4.0, y=4.0, label="victim", kind="casualty", sd_m=0.0, removed=False)
        )
        await settle(pilot)
        assert "op2-1" in rig.fleet.marks
    # A new console loads the saved marks.
    again = Rig(tmp_path)
    assert {m.markId for m in marks} <= set(again.fleet.marks)


@run_async
async def test_link_indicator_changes_on_failover(tmp_path: Path) -> None:
    rig = Rig(tmp_path, policy=PROMPT)  # the production window: this test is about failing over
    rig.start()
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            await with_robots(rig, pilot, "r1")
            assert rig.app.query_one("#fleet").get_cell("r1", "link").plain == "zenoh"
            rig.up = ("mqtt",)  # the robot is heard on MQTT only now
            for _ in range(50):  # the state window (0.35 s), however slow the machine
                await settle(pilot, 0.1)
                if rig.app.query_one("#fleet").get_cell("r1", "link").plain == "mqtt":
                    break
            assert rig.app.query_one("#fleet").get_cell("r1", "link").plain == "mqtt"
            assert "failover" in screen_text(rig.app)
            await pilot.press("i")
            await pilot.pause()
            assert rig.mqtt.messages(Teleop), "drive commands follow the fallback"
    finally:
        rig.close()


@run_async
async def test_lease_held_by_another_refuses_driving(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        rig.zenoh.inject(rig.counter("r1").make(Lease, holder="operator-2", until=rig.clock.wall() + 30))
        await settle(pilot)
        await pilot.press("i")
        await pilot.pause()
        assert not rig.zenoh.messages(Teleop)
        text = screen_text(rig.app)
        assert "held by operator-2" in text and "operator-2" in rig.app.query_one("#fleet").get_cell("r1", "lease")
        # Take it: the request goes out; once the robot grants it, driving works.
        await pilot.press("t")
        await pilot.pause()
        assert rig.zenoh.messages()[-1].TOPIC == "lease/request"
        rig.zenoh.inject(rig.counter("r1").make(Lease, holder=ME, until=rig.clock.wall() + 30))
        await settle(pilot)
        await pilot.press("i")
        await pilot.pause()
        assert rig.zenoh.messages(Teleop)


@run_async
async def test_escape_stops_every_robot_and_quit_sends_stop(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1", "r2", "r3")
        await pilot.press("escape")
        await pilot.pause()

        # Under load the rig's link manager may have moved commands to MQTT: a stop counts on
        # whichever link carried it (re-sends of one stop share its header id).
        def sent(kind: type) -> list[Any]:
            seen: dict[tuple[str, int], Any] = {}
            for m in [*rig.zenoh.messages(kind), *rig.mqtt.messages(kind)]:
                seen.setdefault((m.header.robot, m.header.headerId), m)
            return list(seen.values())

        stops = sent(InstantActions)
        assert sorted(m.header.robot for m in stops) == ["r1", "r2", "r3"]
        assert all(m.actions[0].actionType is ActionType.STOP for m in stops)
        await pilot.press("ctrl+q")
        await pilot.pause()
    after = sent(InstantActions)
    drives = [*rig.zenoh.messages(Teleop), *rig.mqtt.messages(Teleop)]
    assert len(after) == 6 and drives and drives[-1].v == 0


@run_async
async def test_read_only_sends_nothing(tmp_path: Path) -> None:
    r = Rig(tmp_path, read_only=True)
    r.start()
    try:
        async with r.app.run_test(size=(140, 44)) as pilot:
            await with_robots(r, pilot, "r1")
            for key in ("i", "escape", "h", "p", "t"):
                await pilot.press(key)
            await pilot.press("colon")
            await type_text(pilot, "goal 1 1")
            await pilot.press("enter")
            await pilot.press("ctrl+q")
            await pilot.pause()
        assert r.zenoh.sent == [] and r.mqtt.sent == []
    finally:
        r.close()


@run_async
async def test_main_screen_snapshot(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1", "r2")
        rig.zenoh.inject(rig.counter("r2").make(Lease, holder="", until=0.0))
        await settle(pilot)
        text = screen_text(rig.app)
        for needle in ("fleetlink console", ME, "id", "mode", "batt", "link", "health", "age", "uwb", "lease",
                       "r1", "r2", "zenoh", "free", "STOP ALL"):  # fmt: skip
            assert needle in text, needle
        # The map draws both robots' labels.
        assert re.search(r"r1", text) and re.search(r"r2", text)
        # Filter: only r2 remains.
        await pilot.press("slash", "r", "2", "enter")
        await settle(pilot)
        table = rig.app.query_one("#fleet")
        assert [str(k.value) for k in table.rows] == ["r2"]


def status_line(app: ConsoleApp) -> str:
    """The status line as drawn (style tags in it would have been swallowed)."""
    return app.query_one("#status", Static).render_line(0).text


@run_async
async def test_status_line_shows_the_mode(rig: Rig, tmp_path: Path) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        assert "[driving]" in status_line(rig.app) and "READ-ONLY" not in status_line(rig.app)
    r = Rig(tmp_path, read_only=True)
    r.start()
    try:
        async with r.app.run_test(size=(140, 44)) as pilot:
            await with_robots(r, pilot, "r1")
            assert "[READ-ONLY]" in status_line(r.app)
    finally:
        r.close()


@run_async
async def test_tab_selects_the_next_robot(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1", "r2", "r3")
        assert rig.app.selected == "r1"
        seen = []
        for _ in range(3):
            await pilot.press("tab")
            await pilot.pause()
            seen.append(rig.app.selected)
        assert seen == ["r2", "r3", "r1"]  # wraps round
        assert isinstance(rig.app.focused, MapView)  # the focus stayed where it was
        for _ in range(50):  # the status line is refreshed on the next tick, not with the key
            if "robot r1" in status_line(rig.app):
                break
            await pilot.pause(0.05)
        assert "robot r1" in status_line(rig.app)
        # In an input, tab keeps its usual meaning: the focus moves on, the robot stays.
        await pilot.press("slash")
        assert rig.app.focused is rig.app.query_one("#filter", Input)
        await pilot.press("tab")
        await pilot.pause()
        assert rig.app.selected == "r1"
        assert rig.app.focused is not rig.app.query_one("#filter", Input)


@run_async
async def test_robot_name_shows_inside_a_mapped_room(rig: Rig) -> None:
    """The label is drawn over the map's free cells and walls, beside the robot's glyph."""
    cells = np.zeros((40, 60), dtype=np.int8)  # 6 m x 4 m from (0, 0), walls all round
    cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = 100
    snap = rig.counter("r1").make(MapSnapshot, **snapshot_fields(cells, 0.1, (0.0, 0.0), 1))
    with rig.lock:
        assert MapFollower(rig.fleet).on_snapshot("r1", snap)
    async with rig.app.run_test(size=(140, 44)) as pilot:
        rig.voices["r1"] = (3.0, 2.0)
        rig.voices["r2"] = (5.8, 1.0)  # its label runs over the right-hand wall and out of the room
        await settle(pilot)
        await pilot.press("f")  # centre on the robots
        await settle(pilot)
        view = rig.app.query_one(MapView)
        lines = {}
        for robot, (x, y) in rig.voices.items():
            col, row = view.geometry.to_cell(x, y)
            line = view.render_line(row).text
            lines[robot] = line
            assert line[col] == "→", (robot, line)  # the glyph is not hidden by any label
            assert line[col + 2 : col + 4] == robot, (robot, line)
        _, row = view.geometry.to_cell(*rig.voices["r1"])
        drawn = {view.frame.pixels(col, row)[1] for col in range(view.geometry.width)} if view.frame else set()
        assert {FREE, WALL} <= drawn  # the row is inside the mapped room
