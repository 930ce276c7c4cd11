"""Marks survive a console restart and reach a console that joins late, with Zenoh down (issue 15),
over a real Mosquitto and real Zenoh peers on loopback.

Console A (op-a) places a mark with its ``M`` key at its robot's fused pose: the mark goes out on
Zenoh and MQTT, and A's retained ``MarkSet`` holds it on the broker. A closes. Then, with no Zenoh
peer reachable:

- A restarts without its marks file and gets its mark back from its own retained set (and leaves
  the set on the broker as it was);
- console B (op-b) joins late, sees A's mark, and edits it: its own retained set now holds the
  newer version;
- A restarts with its marks file: its mark is back, with B's edit, and A's set for that robot
  empties (the mark's newest version is B's), so the broker holds each version once;
- ``fleetlink marks export`` collects them from the broker into CSV and GeoJSON.
"""

from __future__ import annotations

import asyncio
import csv
import io
import json
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from textual.widgets import Input

from fleetlink.cli.main import main
from fleetlink.links.mqtt import MqttEndpoint
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.operator.console import ConsoleApp, MarkDialog, attach
from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.links import OperatorLink, mqtt_settings_for
from fleetlink.operator.marks import mark_record, marks_of_set
from fleetlink.operator.marksync import MarkSharing
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import LinkName, Mark, MarkSet, Pose
from tests.harness import MosquittoBroker, wait_until

LABEL = "two under the stairs"


class Console:
    """A console as ``fleetlink console`` assembles it: OperatorLink (Zenoh + MQTT), fleet model,
    marks sharing, the app (not running until ``run_test``)."""

    def __init__(self, login: str, session: Any, url: str, marks_file: Path, clock: SystemClock) -> None:
        self.link = OperatorLink(
            clock, login, ZenohEndpoint(session=session), MqttEndpoint(mqtt_settings_for(url), client_id=login)
        ).start()
        self.fleet = FleetModel(login)
        self.lock = threading.Lock()
        attach(self.link, self.fleet, self.lock)
        self.app = ConsoleApp(self.link, self.fleet, clock, lock=self.lock, marks_file=marks_file)
        self.sharing = MarkSharing(self.link, self.fleet, self.lock, asks=(0.1,), check_hz=20.0).start()

    def marks(self) -> dict[str, Mark]:
        with self.lock:
            return dict(self.fleet.marks)

    def close(self) -> None:
        self.sharing.stop()
        self.link.close()


class Listener:
    """Every fleetlink message on one link, decoded (an MQTT endpoint, or a Zenoh session)."""

    def __init__(self) -> None:
        self.got: list[tuple[str, wire.Message]] = []
        self.lock = threading.Lock()

    def __call__(self, key: str, payload: bytes) -> None:
        try:
            msg = wire.decode_key(key, payload)
        except wire.WireError:
            return
        with self.lock:
            self.got.append((key, msg))

    def of(self, cls: type[wire.Message]) -> list[Any]:
        with self.lock:
            return [m for _, m in self.got if isinstance(m, cls)]


@contextmanager
def mqtt_listener(url: str, name: str) -> Iterator[Listener]:
    listener = Listener()
    ep = MqttEndpoint(mqtt_settings_for(url), client_id=name)
    ep.subscribe(keys.ZENOH_ALL, listener)
    ep.start()
    try:
        wait_until(lambda: ep.up, message=f"{name} connected")
        yield listener
    finally:
        ep.close()


def retained_sets(url: str, name: str) -> dict[str, MarkSet]:
    """What the broker holds now: every console's retained set, by key (a fresh subscriber)."""
    with mqtt_listener(url, name) as listener:
        # A sentinel published after subscribing comes back after every retained message.
        probe = MqttEndpoint(mqtt_settings_for(url), client_id=f"{name}-probe")
        probe.start()
        try:
            wait_until(lambda: probe.up)
            sentinel = wire.HeaderCounter(SystemClock(), robot="r0", sender="probe").make(
                Pose, x=0.0, y=0.0, theta=0.0, sd_x_m=0.0, sd_y_m=0.0, sd_theta_rad=0.0, odom_x=0.0,
                odom_y=0.0, odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=False,
            )  # fmt: skip

            def seen() -> bool:
                probe.publish(wire.key_of(sentinel), wire.encode(sentinel))
                return bool(listener.of(Pose))

            wait_until(seen, message="the sentinel after the retained sets")
        finally:
            probe.close()
        with listener.lock:
            return {k: m for k, m in listener.got if isinstance(m, MarkSet)}


def robot_voice(url: str, stop: threading.Event, x: float, y: float) -> threading.Thread:
    """r1's agent, reporting its fused pose (sd 0.4 m x, 0.25 m y) on MQTT at 20 Hz."""
    clock = SystemClock()
    counter = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    ep = MqttEndpoint(mqtt_settings_for(url), client_id="agent-r1")
    ep.start()

    def talk() -> None:
        try:
            while not stop.wait(0.05):
                pose = counter.make(
                    Pose, x=x, y=y, theta=0.0, sd_x_m=0.4, sd_y_m=0.25, sd_theta_rad=0.05, odom_x=x, odom_y=y,
                    odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=False,
                )  # fmt: skip
                ep.publish(wire.key_of(pose), wire.encode(pose))
        finally:
            ep.close()

    thread = threading.Thread(target=talk, daemon=True)
    thread.start()
    return thread


async def until(pilot: Any, predicate: Callable[[], object], message: str, timeout: float = 15.0) -> None:
    """``wait_until`` that lets the app run meanwhile."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not predicate():
        assert loop.time() < deadline, f"timed out after {timeout:.0f} s waiting for {message}"
        await pilot.pause(0.05)


def test_a_mark_reaches_a_console_that_joins_later_with_zenoh_down_and_survives_restarts(
    mosquitto: MosquittoBroker, zenoh_peers: Callable[..., Any], tmp_path: Path
) -> None:
    clock = SystemClock()
    url = f"mqtt://127.0.0.1:{mosquitto.port}"
    a_session, watcher = zenoh_peers(2)
    on_zenoh = Listener()
    subscriber = watcher.declare_subscriber(keys.ZENOH_ALL, lambda s: on_zenoh(str(s.key_expr), s.payload.to_bytes()))
    assert subscriber is not None  # kept: a dropped subscriber is undeclared
    a_file = tmp_path / "a-marks.json"
    stop = threading.Event()
    voice = robot_voice(url, stop, 3.5, -1.25)

    # -- A places a mark at r1's fused pose, asking kind and label (M), on both links -----------
    a = Console("op-a", a_session, url, a_file, clock)
    try:
        with mqtt_listener(url, "mqtt-watch") as on_mqtt:

            async def place() -> Mark:
                async with a.app.run_test(size=(140, 44)) as pilot:
                    await until(pilot, lambda: a.fleet.robots.get("r1") and a.fleet.robots["r1"].pose_sd_m, "r1's pose")
                    await pilot.press("M")
                    await until(pilot, lambda: isinstance(a.app.screen, MarkDialog), "the mark dialog")
                    # Typed key by key on the in-memory rig (test_console_marks.py); here the
                    # label is filled in at once (each key waits for the app to go idle, and a
                    # live robot's 20 Hz poses keep it busy).
                    a.app.screen.query_one("#mark-label", Input).value = LABEL
                    await pilot.press("enter")
                    await until(pilot, lambda: a.marks(), "the mark in A's model")
                    (mark,) = a.marks().values()
                    return mark

            mark = asyncio.run(place())
            assert (mark.kind, mark.label, mark.x, mark.y, mark.sd_m) == ("casualty", LABEL, 3.5, -1.25, 0.4)
            assert (mark.header.robot, mark.header.sender) == ("r1", "op-a")
            wait_until(lambda: on_zenoh.of(Mark), message="A's mark on Zenoh")
            wait_until(lambda: on_mqtt.of(Mark), message="A's mark on MQTT")
            wait_until(lambda: on_mqtt.of(MarkSet), message="A's retained set")
            assert wire.encode(on_zenoh.of(Mark)[0]) == wire.encode(on_mqtt.of(Mark)[0]) == wire.encode(mark)
    finally:
        a.close()
    stop.set()
    voice.join(2)
    key_a = keys.sender_key("r1", "marks/set", "op-a")
    held = retained_sets(url, "check-1")
    assert [m.markId for m in marks_of_set(held[key_a])] == [mark.markId]

    # -- Zenoh is down from here on: each console's Zenoh session reaches no peer ---------------
    # A restarts without its marks file: its own retained set brings the mark back.
    (lonely,) = zenoh_peers(1)
    a2 = Console("op-a", lonely, url, tmp_path / "fresh.json", clock)
    try:
        wait_until(lambda: mark.markId in a2.marks(), message="A's own mark from its retained set")
        assert mark_record(a2.marks()[mark.markId]) == mark_record(mark)
    finally:
        a2.close()
    held = retained_sets(url, "check-2")
    assert [m.markId for m in marks_of_set(held[key_a])] == [mark.markId]  # not clobbered on the way

    # B joins late: A is gone, Zenoh down; the broker has A's set. B edits the mark.
    (lonely_b,) = zenoh_peers(1)
    b = Console("op-b", lonely_b, url, tmp_path / "b-marks.json", clock)
    try:

        async def join_and_edit() -> Mark:
            async with b.app.run_test(size=(140, 44)) as pilot:
                await until(pilot, lambda: mark.markId in b.marks(), "A's mark on console B")
                assert b.marks()[mark.markId] == mark
                assert b.fleet.live_marks() == [mark]
                b.app.run_command(f"mark edit {mark.markId.rsplit('-', 1)[1]} three under the stairs")
                await until(pilot, lambda: b.marks()[mark.markId].header.sender == "op-b", "B's edit")
                return b.marks()[mark.markId]

        edit = asyncio.run(join_and_edit())
        key_b = keys.sender_key("r1", "marks/set", "op-b")
        wait_until(lambda: key_b in retained_sets(url, "check-3"), message="B's retained set")
    finally:
        b.close()
    assert json.loads((tmp_path / "b-marks.json").read_text())["marks"][0]["label"] == "three under the stairs"

    # A restarts with its marks file: its mark again, with B's edit; A's set for r1 empties.
    (lonely_a,) = zenoh_peers(1)
    a3 = Console("op-a", lonely_a, url, a_file, clock)
    try:
        assert mark.markId in a3.marks()  # from the file (and the broker)
        wait_until(lambda: mark_record(a3.marks()[mark.markId]) == mark_record(edit), message="B's edit on A")

        def a_set_empty() -> bool:
            sets = retained_sets(url, "check-4")
            return sets[key_a].marks == () and [e.label for e in sets[key_b].marks] == ["three under the stairs"]

        wait_until(a_set_empty, timeout=15, message="A's set for r1 emptied, B's holding the edit")
    finally:
        a3.close()

    # The incident report, from the broker alone.
    for name in ("marks.csv", "marks.geojson"):
        assert main(["marks", "export", "--out", str(tmp_path / name), "--mqtt", url, "--wait", "0.4"]) == 0
    rows = list(csv.DictReader(io.StringIO((tmp_path / "marks.csv").read_text())))
    assert [(r["markId"], r["label"], r["x_m"], r["y_m"], r["sd_m"], r["robot"], r["by"]) for r in rows] == [
        (mark.markId, "three under the stairs", "3.500", "-1.250", "0.400", "r1", "op-b")
    ]
    (feature,) = json.loads((tmp_path / "marks.geojson").read_text())["features"]
    assert feature["geometry"]["coordinates"] == [3.5, -1.25] and feature["properties"]["frame"] == "site"


def test_a_broker_restarted_without_its_retained_messages_gets_the_sets_again(
    mosquitto: MosquittoBroker, zenoh_peers: Callable[..., Any], tmp_path: Path
) -> None:
    """Mosquitto here keeps nothing across a restart (``persistence false``): every console
    publishes its sets again after it reconnects, so a console joining after the restart still
    gets them."""
    clock = SystemClock()
    url = f"mqtt://127.0.0.1:{mosquitto.port}"
    (lonely,) = zenoh_peers(1)
    a = Console("op-a", lonely, url, tmp_path / "a.json", clock)
    try:
        counter = wire.HeaderCounter(clock, robot="r2", sender="op-a")
        mark = counter.make(Mark, markId="op-a-9-1", x=1.0, y=2.0, label="", kind="hazard", sd_m=0.0, removed=False)
        with a.lock:
            a.fleet.apply(mark, "local", clock.now())
        a.sharing.wake()
        key = keys.sender_key("r2", "marks/set", "op-a")
        wait_until(lambda: key in retained_sets(url, "check-1"), message="A's set on the broker")
        connects = a.link.links[LinkName.MQTT].connects  # type: ignore[attr-defined]
        mosquitto.restart()
        assert key not in retained_sets(url, "check-2")  # forgotten...
        wait_until(lambda: a.link.links[LinkName.MQTT].connects > connects, message="A reconnected")  # type: ignore[attr-defined]
        wait_until(lambda: key in retained_sets(url, "check-3"), message="A's set published again")
    finally:
        a.close()
    (lonely_b,) = zenoh_peers(1)
    b = Console("op-b", lonely_b, url, tmp_path / "b.json", clock)
    try:
        wait_until(lambda: mark.markId in b.marks(), message="A's mark on a console joining after the restart")
    finally:
        b.close()


def test_the_export_refuses_an_unknown_format(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["marks", "export", "--out", str(tmp_path / "marks.xlsx")]) == 2
    assert "--out must end in .csv or .geojson" in capsys.readouterr().err
