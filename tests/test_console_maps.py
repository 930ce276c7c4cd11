"""The console's map data and shared marks against real parts: Zenoh peers on loopback, Mosquitto.

- A robot's map (a real Zenoh queryable answering ``fleetlink/v1/<robot>/map`` with a
  ``MapSnapshot``, then ``map/updates`` patches) ends up in the console's fleet model and on its
  map widget; a patch that does not follow the console's copy makes it fetch the map again.
- A console that starts after a mark was placed gets it from the other console's queryable.
- The embedded pure-Python broker (amqtt) carries the console's MQTT traffic, retained included.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
import pytest

from fleetlink.cli.console import share_marks
from fleetlink.links.mqtt import MqttEndpoint
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.operator.console import ConsoleApp, attach
from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.links import OperatorLink, mqtt_settings_for
from fleetlink.operator.maprender import WALL
from fleetlink.operator.maps import MapFetcher, MapFollower
from fleetlink.operator.mapview import MapView
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.map_codec import patch_fields, snapshot_fields
from fleetlink.shared.messages import MapSnapshot, MapUpdate, Mark, Pose
from fleetlink.site.brokers import AmqttBroker
from tests.harness import wait_until
from tests.test_console import run_async

RES = 0.1


class MapRobot:
    """A robot's map side on its own Zenoh session: the queryable and the updates publisher."""

    def __init__(self, session: Any, robot: str, clock: SystemClock) -> None:
        self.session = session
        self.robot = robot
        self.counter = wire.HeaderCounter(clock, robot=robot, sender=f"agent-{robot}")
        self.cells = np.full((40, 40), -1, dtype=np.int8)  # 4 m x 4 m from (0, 0), row 0 at the bottom
        self.version = 1
        self.began = 100.0  # when its agent began this map
        self.queries = 0
        self.queryable = session.declare_queryable(keys.key(robot, MapSnapshot.TOPIC), self._answer, complete=True)

    def _answer(self, query: Any) -> None:
        self.queries += 1
        snap = self.counter.make(MapSnapshot, **snapshot_fields(self.cells, RES, (0.0, 0.0), self.version, self.began))
        query.reply(keys.key(self.robot, MapSnapshot.TOPIC), wire.encode(snap))

    def change(self, row: int, col: int, value: int, *, publish: bool = True, base: int | None = None) -> None:
        old = self.version
        self.cells[row, col] = value
        self.version += 1
        if publish:
            box = (row, col, row + 1, col + 1)
            f = patch_fields(self.cells, RES, (0.0, 0.0), box, self.version, base or old, self.began)
            assert f is not None
            self.session.put(keys.key(self.robot, MapUpdate.TOPIC), wire.encode(self.counter.make(MapUpdate, **f)))

    def pose(self, x: float, y: float) -> None:
        msg = self.counter.make(
            Pose,
            x=x,
            y=y,
            theta=0.0,
            sd_x_m=0.1,
            sd_y_m=0.1,
            sd_theta_rad=0.1,
            odom_x=x,
            odom_y=y,
            odom_theta=0.0,
            vx=0.0,
            omega=0.0,
            uwbStale=False,
        )
        self.session.put(keys.key(self.robot, Pose.TOPIC), wire.encode(msg))

    def restart(self, began: float) -> None:
        """Its agent restarts: a new map (nothing known), its versions from 1 again."""
        self.cells = np.full((40, 40), -1, dtype=np.int8)
        self.version, self.began = 1, began

    def close(self) -> None:
        self.queryable.undeclare()


def cell(fleet: FleetModel, robot: str, row: int, col: int) -> int | None:
    grid = fleet.grids.get(robot)
    if grid is None:
        return None
    _, _, _, w, _, data = grid
    return data[row * w + col]


@pytest.fixture
def console(zenoh_peers: Any, mosquitto: Any) -> Any:
    clock = SystemClock()
    robot_session, console_session = zenoh_peers(2)
    link = OperatorLink(
        clock,
        "op-maps",
        ZenohEndpoint(session=console_session),
        MqttEndpoint(mqtt_settings_for(f"mqtt://127.0.0.1:{mosquitto.port}"), client_id="op-maps"),
    ).start()
    fleet = FleetModel("op-maps")
    lock = threading.Lock()
    follower = MapFollower(fleet, retry_s=0.5)
    attach(link, fleet, lock, follower)
    fetcher = MapFetcher(follower, lambda r: link.fetch_map(r, timeout=2.0), clock, lock, period_s=0.1).start()
    robot = MapRobot(robot_session, "r1", clock)
    try:
        yield robot, link, fleet, lock, clock
    finally:
        fetcher.stop()
        robot.close()
        link.close()


def test_a_robots_map_reaches_the_console_and_follows_its_updates(console: Any) -> None:
    robot, _link, fleet, lock, _clock = console
    robot.cells[10:30, 20] = 100  # a wall along x = 2.0-2.1 m
    robot.cells[10:30, 5:20] = 0
    robot.change(5, 5, 100, publish=False)  # version 2, before anyone asked

    def known() -> bool:
        robot.pose(1.0, 1.5)  # the console fetches the maps of robots it has heard of
        with lock:
            return cell(fleet, "r1", 15, 20) == 100

    wait_until(known, timeout=20, message="r1's snapshot in the console's fleet model")
    with lock:
        assert cell(fleet, "r1", 15, 10) == 0  # free
        assert cell(fleet, "r1", 35, 35) == 255  # unknown
        assert cell(fleet, "r1", 5, 5) == 100
    asked = robot.queries

    robot.change(12, 12, 100)  # a patch that follows the console's copy: applied, no new query
    wait_until(lambda: cell(fleet, "r1", 12, 12) == 100, timeout=10, message="the map update applied")
    assert robot.queries == asked

    robot.change(13, 13, 100, publish=False)  # the console misses this one...
    robot.change(14, 14, 100)  # ...so this patch does not follow its copy: it fetches the map again
    wait_until(
        lambda: cell(fleet, "r1", 13, 13) == 100 and cell(fleet, "r1", 14, 14) == 100,
        timeout=10,
        message="the stale copy fetched again",
    )
    assert robot.queries > asked


def test_a_robot_whose_agent_restarted_has_its_new_map_taken_though_its_versions_begin_again(console: Any) -> None:
    """A restarted agent begins a new map whose versions count from 1 again: the console's copy of
    the old map (hundreds of versions on) must not hold out against it. Each snapshot and patch says
    which map it is of (``began``): the first patch of the new map makes the console fetch it whole."""
    robot, _link, fleet, lock, _clock = console
    robot.cells[10:30, 20] = 100  # the old map: a wall along x = 2.0-2.1 m
    robot.version = 500

    def known() -> bool:
        robot.pose(1.0, 1.5)
        with lock:
            return cell(fleet, "r1", 15, 20) == 100

    wait_until(known, timeout=20, message="r1's old map in the console")
    robot.restart(began=900.0)
    robot.cells[10:30, 30] = 100  # the new map, in its own frame: a wall along x = 3.0-3.1 m
    robot.change(5, 5, 100)  # version 2, a patch of the new map

    def new_map() -> bool:
        robot.pose(0.0, 0.0)
        with lock:
            return cell(fleet, "r1", 15, 30) == 100 and cell(fleet, "r1", 15, 20) == 255

    wait_until(new_map, timeout=20, message="the restarted agent's new map in the console")


@run_async
async def test_the_map_widget_draws_the_fetched_walls(console: Any) -> None:
    robot, link, fleet, lock, clock = console
    robot.cells[0:40, 20] = 100  # a wall along x = 2.0-2.1 m, y 0-4 m

    def known() -> bool:
        robot.pose(1.0, 2.0)
        with lock:
            return "r1" in fleet.grids

    wait_until(known, timeout=20, message="r1's snapshot in the console's fleet model")
    app = ConsoleApp(link, fleet, clock, lock=lock)
    async with app.run_test(size=(160, 48)) as pilot:
        await pilot.pause()
        view = app.query_one(MapView)

        def wall_drawn() -> bool:
            view.geometry.center_x, view.geometry.center_y = 2.0, 2.0
            view.update_view()
            return bool(view.pixel_at(2.05, 2.0) == WALL)

        deadline = time.monotonic() + 10.0  # once laid out, the view draws the fleet's grid
        while not wall_drawn() and time.monotonic() < deadline:
            await pilot.pause(0.05)
        assert view.pixel_at(2.05, 2.0) == WALL
        assert view.pixel_at(3.5, 2.0) != WALL  # beyond the wall: unknown


def test_a_console_that_starts_late_gets_the_marks_placed_before(zenoh_peers: Any, mosquitto: Any) -> None:
    clock = SystemClock()
    a_session, b_session = zenoh_peers(2)
    url = f"mqtt://127.0.0.1:{mosquitto.port}"
    link_a = OperatorLink(clock, "op-a", ZenohEndpoint(session=a_session), _mqtt(url, "op-a")).start()
    fleet_a, lock_a = FleetModel("op-a"), threading.Lock()
    attach(link_a, fleet_a, lock_a)
    workers = [share_marks(link_a, fleet_a, lock_a, asks=())]
    link_b = None
    try:
        counter = wire.HeaderCounter(clock, robot="r1", sender="op-a")
        mark = counter.make(
            Mark, markId="op-a-1", x=3.0, y=4.0, label="casualty", kind="casualty", sd_m=0.0, removed=False
        )
        with lock_a:
            fleet_a.apply(mark, "local", clock.now())
        link_a.publish(mark)  # nobody else listens yet
        # Console B starts afterwards: it asks, A answers.
        link_b = OperatorLink(clock, "op-b", ZenohEndpoint(session=b_session), _mqtt(url, "op-b")).start()
        fleet_b, lock_b = FleetModel("op-b"), threading.Lock()
        attach(link_b, fleet_b, lock_b)
        workers.append(share_marks(link_b, fleet_b, lock_b, asks=(0.1, 0.5, 1.0, 2.0, 4.0)))

        def got() -> bool:
            with lock_b:
                return "op-a-1" in fleet_b.marks

        wait_until(got, timeout=15, message="console B holding the mark placed before it started")
        with lock_b:
            held = fleet_b.marks["op-a-1"]
        assert (held.x, held.y, held.kind, held.header.sender) == (3.0, 4.0, "casualty", "op-a")
    finally:
        for w in workers:
            w.stop()
        link_a.close()
        if link_b is not None:
            link_b.close()


def _mqtt(url: str, client_id: str) -> MqttEndpoint:
    return MqttEndpoint(mqtt_settings_for(url), client_id=client_id)


def _listening(url: str, client_id: str, got: list[tuple[str, bytes]]) -> MqttEndpoint:
    """An endpoint subscribed as a console is: every fleetlink key and the UWB gateways' status."""
    ep = _mqtt(url, client_id)
    for expr in (keys.ZENOH_ALL, "fleetlink/uwb/*/status"):
        ep.subscribe(expr, lambda k, p: got.append((k, p)))
    ep.start()
    return ep


def test_the_embedded_python_broker_carries_the_consoles_mqtt() -> None:
    broker = AmqttBroker()
    url = broker.start().url  # raises if amqtt did not start
    got: list[tuple[str, bytes]] = []
    sub = _listening(url, "sub", got)
    pub = _mqtt(url, "pub")
    pub.start()
    try:
        wait_until(lambda: sub.up and pub.up, timeout=10, message="both connected")
        assert pub.publish("fleetlink/uwb/g1/status", b'{"gateway":"g1"}', qos=1, retain=True)

        def arrived() -> bool:
            pub.publish("fleetlink/v1/r1/pose", b"x")
            return ("fleetlink/v1/r1/pose", b"x") in got

        wait_until(arrived, timeout=10, message="a message through the amqtt broker")
        wait_until(
            lambda: ("fleetlink/uwb/g1/status", b'{"gateway":"g1"}') in got, timeout=10, message="the gateway status"
        )
        late: list[tuple[str, bytes]] = []
        late_client = _listening(url, "late", late)
        try:
            wait_until(lambda: any(k == "fleetlink/uwb/g1/status" for k, _ in late), timeout=10, message="retained")
        finally:
            late_client.close()
    finally:
        sub.close()
        pub.close()
        broker.stop()
