"""Drive keys taken on the terminal's input thread (operator/keylane.py).

The keys are handed to the app's driver as a terminal's input thread hands them on
(``Driver.process_message``, from a thread of the test's), some while the app's event loop is held
busy (as a long redraw holds it): a drive key's teleop must leave before the loop is free again, and
keys typed behind a ``:`` must still reach the command line, whatever the loop was doing.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Iterator
from typing import Any

from textual import events
from textual.message import Message

from fleetlink.operator.keylane import KeyLane
from fleetlink.operator.mapview import MapView
from fleetlink.shared.messages import Lease, Teleop
from tests.harness.console_rig import Rig
from tests.test_console import run_async, status_line, with_robots


def key(name: str, char: str | None = None) -> events.Key:
    return events.Key(name, char if char is not None else name)


async def with_loop_busy(keyboard: Callable[[], Any]) -> None:
    """Run ``keyboard`` on a thread of its own while the app's event loop is held busy (a
    callback that waits for the keyboard to be done, as a redraw of many lines keeps the loop)."""
    busy, done = threading.Event(), threading.Event()
    failure: list[BaseException] = []

    def typist() -> None:
        try:
            assert busy.wait(5)
            keyboard()
        except BaseException as exc:  # raised again in the test
            failure.append(exc)
        finally:
            done.set()

    def hold() -> None:
        busy.set()
        done.wait(5)

    thread = threading.Thread(target=typist, name="keyboard")
    thread.start()
    asyncio.get_running_loop().call_soon(hold)
    await asyncio.sleep(0)
    thread.join(5)
    if failure:
        raise failure[0]


@run_async
async def test_a_drive_key_goes_out_while_the_event_loop_is_busy(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        seen: list[list[Teleop]] = []

        def keyboard() -> None:
            rig.app._driver.process_message(key("i"))
            seen.append(rig.zenoh.messages(Teleop))  # the loop is still held here
            rig.app._driver.process_message(key("space", " "))
            seen.append(rig.zenoh.messages(Teleop))

        await with_loop_busy(keyboard)
        assert [len(s) for s in seen] == [1, 2]
        forward, stop = seen[1]
        assert forward.header.robot == "r1" and forward.v > 0 and forward.omega == 0
        assert (stop.v, stop.omega) == (0.0, 0.0)
        assert rig.app.key_lane.taken == 2 and rig.app.key_lane.handed_on == 0
        await pilot.pause()
        assert len(rig.zenoh.messages(Teleop)) == 2  # taken there: the loop does not drive again


@run_async
async def test_keys_typed_behind_a_colon_reach_the_command_line_though_the_loop_was_busy(rig: Rig) -> None:
    """``:goal 1.5 2`` typed in one burst while the loop is busy: the ``l`` of ``goal`` is a drive
    key, but the ``:`` before it has not been handled yet, so it goes through the loop behind it
    and is typed, not driven."""
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        names = {" ": "space", ".": "full_stop", ":": "colon"}
        burst = [key(names.get(c, c), c) for c in ":goal 1.5 2"] + [key("enter", "\r")]

        def keyboard() -> None:
            for k in burst:
                rig.app._driver.process_message(k)

        await with_loop_busy(keyboard)
        order = await rig.last_order(pilot)
        assert rig.zenoh.messages(Teleop) == [] and rig.mqtt.messages(Teleop) == []
        assert (order.goal.x, order.goal.y) == (1.5, 2.0)
        assert rig.app.key_lane.taken == 0
        for _ in range(50):  # Enter gives the focus back to the map (deferred, Widget.focus)
            if isinstance(rig.app.focused, MapView):
                break
            await pilot.pause(0.05)
        assert isinstance(rig.app.focused, MapView)
        # Every key handled: the next drive key is taken on the input thread again.
        assert rig.app.key_lane.waiting == 0
        await asyncio.to_thread(rig.app._driver.process_message, key("i"))
        assert rig.app.key_lane.taken == 1 and rig.zenoh.messages(Teleop)[-1].v > 0


@run_async
async def test_a_drive_key_typed_right_behind_tab_drives_the_robot_tab_selected(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1", "r2")
        assert rig.app.selected == "r1"

        def keyboard() -> None:
            for k in (key("tab", "\t"), key("i")):
                rig.app._driver.process_message(k)

        await with_loop_busy(keyboard)
        for _ in range(50):
            if rig.zenoh.messages(Teleop):
                break
            await pilot.pause(0.02)
        assert rig.app.selected == "r2"
        assert rig.zenoh.messages(Teleop)[0].header.robot == "r2"  # (before: r1, the old selection)


@run_async
async def test_a_label_typed_right_after_mark_here_goes_to_the_dialog(rig: Rig) -> None:
    """``M`` then ``victim`` in one burst: the ``i`` and the ``m`` are drive keys, but ``M`` opens
    its dialog when the app first sees it (a priority binding), so they are typed into the label."""
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        burst = [key("M")] + [key(c) for c in "victim"]

        def keyboard() -> None:
            for k in burst:
                rig.app._driver.process_message(k)

        await with_loop_busy(keyboard)
        for _ in range(50):
            if len(rig.app.screen_stack) > 1 and rig.app.screen.query_one("#mark-label").value == "victim":
                break
            await pilot.pause(0.05)
        assert rig.app.screen.query_one("#mark-label").value == "victim"
        assert rig.zenoh.messages(Teleop) == [] and rig.app.key_lane.taken == 0
        # In the dialog's label, M is a letter too.
        await pilot.press("M")
        await pilot.pause()
        assert rig.app.screen.query_one("#mark-label").value == "victimM"


@run_async
async def test_refused_drive_keys_and_speed_steps_go_through_the_app(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        rig.zenoh.inject(rig.counter("r1").make(Lease, holder="operator-2", until=rig.clock.wall() + 30))
        for _ in range(100):  # folded into the model (the app's thread, in its next slice)
            if rig.app.fleet.robots["r1"].lease_holder == "operator-2":
                break
            await pilot.pause(0.02)
        await asyncio.to_thread(rig.app._driver.process_message, key("i"))
        await pilot.pause()
        assert rig.zenoh.messages(Teleop) == []
        assert rig.app.key_lane.taken == 0  # the app refused it, and said why
        notices = "\n".join(str(line) for line in rig.app.query_one("#notices").lines)
        assert "held by operator-2" in notices
        # A speed step redraws the status line: the app's too.
        before = rig.app.drive.speed
        await asyncio.to_thread(rig.app._driver.process_message, key("q"))
        await pilot.pause()
        assert rig.app.drive.speed > before and rig.app.key_lane.taken == 0
        assert f"{rig.app.drive.speed:.2f}" in status_line(rig.app)
        # In the command line a drive key is a letter.
        await asyncio.to_thread(rig.app._driver.process_message, key("colon", ":"))
        await asyncio.to_thread(rig.app._driver.process_message, key("i"))
        await pilot.pause()
        assert rig.app.query_one("#command").value == "i" and rig.app.key_lane.taken == 0


class FakeDriver:
    def __init__(self) -> None:
        self.forwarded: list[Message] = []

    def process_message(self, message: Message) -> None:
        self.forwarded.append(message)


def lane_on(take: Callable[[events.Key], bool]) -> Iterator[tuple[KeyLane, FakeDriver]]:
    lane, driver = KeyLane(take), FakeDriver()
    assert lane.install(driver)
    yield lane, driver
    lane.uninstall()


def test_a_key_behind_an_unhandled_event_is_handed_on_in_order() -> None:
    taken: list[str] = []
    for lane, driver in lane_on(lambda k: taken.append(k.key) is None):
        i1, colon, i2 = key("i"), key("colon", ":"), key("i")
        driver.process_message(i1)
        assert taken == ["i"] and driver.forwarded == []
        lane._take = lambda k: False  # the app declines ':' (not a drive key)
        driver.process_message(colon)
        lane._take = lambda k: taken.append(k.key) is None
        driver.process_message(i2)  # ':' not handled yet: i2 follows it
        assert taken == ["i"] and driver.forwarded == [colon, i2] and lane.waiting == 2
        lane.handled(colon)
        assert lane.waiting == 1
        j1 = key("j")
        driver.process_message(j1)  # i2 still in flight: j1 follows it
        assert taken == ["i"] and driver.forwarded[-1] is j1
        lane.handled(i2)
        lane.handled(j1)
        driver.process_message(key("j"))
        assert taken == ["i", "j"]
        # A mouse move changes nothing a key depends on: not waited for.
        move = events.MouseMove(None, 1, 1, 0, 0, 0, False, False, False)
        driver.process_message(move)
        driver.process_message(key("l"))
        assert taken == ["i", "j", "l"] and driver.forwarded[-1] is move


def test_a_failing_take_hands_the_key_on_and_uninstall_restores_the_driver() -> None:
    def boom(_key: events.Key) -> bool:
        raise RuntimeError("boom")

    for lane, driver in lane_on(boom):
        k = key("i")
        driver.process_message(k)
        assert driver.forwarded == [k] and lane.taken == 0
    assert "process_message" not in driver.__dict__  # the class's own method again
    driver.process_message(key("x"))
    assert len(driver.forwarded) == 2
