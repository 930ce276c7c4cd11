"""How the network reaches the console (operator/feed.py), lease renewal (operator/fleet.py) and
the fleet table (operator/fleet_table.py): headless, then in the app.

The feed has two ways of folding what the network heard into the fleet model: at once on the
network thread (no app), or as a wake-up posted to the app, which drains the inbox on its own
thread. The app tests prove it draws what arrives without any polling timer.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from rich.text import Text

from fleetlink.operator.console import ConsoleApp
from fleetlink.operator.feed import FleetFeed, attach
from fleetlink.operator.fleet import FleetModel, LeaseRenewal
from fleetlink.operator.fleet_table import COLUMNS, FleetTable, fleet_rows, row_cells
from fleetlink.operator.linkmanager import Failed, LinkHealth, Switch
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import Lease, Pose
from tests.test_console import ME, Rig, run_async, settle, with_robots


class FakeSource:
    """Just the subscription side of a console source."""

    sender = ME

    def __init__(self) -> None:
        self.sinks: list[Callable[[wire.Message, str, float], None]] = []
        self.listeners: list[Callable[[Switch | Failed], None]] = []
        self.anchor_sinks: list[Callable[[str, list[tuple[str, float, float, float]]], None]] = []

    def add_sink(self, sink: Callable[[wire.Message, str, float], None]) -> None:
        self.sinks.append(sink)

    def add_listener(self, listener: Callable[[Switch | Failed], None]) -> None:
        self.listeners.append(listener)

    def add_anchor_sink(self, sink: Callable[[str, list[tuple[str, float, float, float]]], None]) -> None:
        self.anchor_sinks.append(sink)

    def hear(self, msg: wire.Message, link: str = "zenoh", now: float = 1.0) -> None:
        for sink in self.sinks:
            sink(msg, link, now)


def pose(counter: wire.HeaderCounter, x: float) -> Pose:
    return counter.make(
        Pose, x=x, y=0.0, theta=0.0, sd_x_m=0.1, sd_y_m=0.1, sd_theta_rad=0.1, odom_x=x, odom_y=0.0,
        odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=False,
    )  # fmt: skip


def feed_rig() -> tuple[FakeSource, FleetModel, FleetFeed, wire.HeaderCounter]:
    source, fleet = FakeSource(), FleetModel(ME)
    feed = attach(source, fleet, threading.Lock())  # type: ignore[arg-type]
    return source, fleet, feed, wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")


def test_unbound_the_feed_folds_messages_in_at_once() -> None:
    source, fleet, feed, agent = feed_rig()
    source.hear(pose(agent, 1.0))
    assert fleet.robots["r1"].pose == (1.0, 0.0, 0.0)
    source.anchor_sinks[0]("g1", [("a1", 0.0, 1.0, 2.0)])
    assert fleet.anchors == {"a1": (0.0, 1.0)}
    health = (LinkHealth("zenoh", False, 0.5, 0.0, None, "silent"),)
    source.listeners[0](Switch("r1", "zenoh", "mqtt", "silent", 2.0, health))
    source.listeners[0](Failed("r1", "order", 7, "no ack"))
    texts = [n.text for n in fleet.drain()]
    assert texts[0].startswith("failover: r1: commands zenoh -> mqtt") and texts[1] == "r1: order #7 lost: no ack"
    assert feed.applied == 4


def test_bound_the_network_only_queues_and_wakes_the_app_once_per_batch() -> None:
    source, fleet, feed, agent = feed_rig()
    wakes: list[int] = []
    feed.bind(lambda: wakes.append(1) is None)
    for k in range(5):
        source.hear(pose(agent, float(k)))
    assert wakes == [1] and "r1" not in fleet.robots  # nothing touched the model yet
    assert feed.drain() == 1 and feed.conflated == 4  # one robot's poses: its latest, once
    assert fleet.robots["r1"].pose == (4.0, 0.0, 0.0)
    source.hear(pose(agent, 9.0))
    assert wakes == [1, 1]  # the next batch wakes again
    feed.unbind()  # what still waits is folded in, and from now on at once
    assert fleet.robots["r1"].pose == (9.0, 0.0, 0.0)
    source.hear(pose(agent, 10.0))
    assert fleet.robots["r1"].pose == (10.0, 0.0, 0.0) and wakes == [1, 1]


def test_a_robots_newer_pose_takes_the_place_of_one_still_waiting_and_nothing_else_is_merged() -> None:
    source, fleet, feed, r1 = feed_rig()
    r2 = wire.HeaderCounter(SimClock(), robot="r2", sender="agent-r2")
    feed.bind(lambda: True)
    first, newer = pose(r1, 1.0), pose(r1, 2.0)
    source.hear(first)
    source.hear(r1.make(Lease, holder="op-bob", until=0.0))
    source.hear(pose(r2, 5.0))
    source.hear(newer, "mqtt")
    source.hear(first, "zenoh")  # a late copy of the older pose does not take the newer one's place
    source.hear(r1.make(Lease, holder="op-eve", until=0.0))
    seen: list[tuple[str, str]] = []
    real = fleet.apply

    def applying(msg: wire.Message, link: str, now: float) -> bool:
        seen.append((msg.header.robot, type(msg).__name__))
        return real(msg, link, now)

    fleet.apply = applying  # type: ignore[method-assign]
    assert feed.drain() == 4 and feed.conflated == 2
    # r1's pose where its first one waited, then the rest in the order they came: leases both.
    assert seen == [("r1", "Pose"), ("r1", "Lease"), ("r2", "Pose"), ("r1", "Lease")]
    assert fleet.robots["r1"].pose == (2.0, 0.0, 0.0) and fleet.robots["r2"].pose == (5.0, 0.0, 0.0)
    assert fleet.robots["r1"].lease_holder == "op-eve"
    assert list(fleet.robots["r1"].trail) == [(1.0, 0.0), (2.0, 0.0)]  # the pose passed over: on the trail
    source.hear(pose(r1, 3.0))  # drained: the next pose waits on its own again
    assert feed.drain() == 1 and fleet.robots["r1"].pose == (3.0, 0.0, 0.0)
    assert list(fleet.robots["r1"].trail) == [(1.0, 0.0), (2.0, 0.0), (3.0, 0.0)]


def test_an_app_that_cannot_take_the_wake_up_is_woken_again_later() -> None:
    source, _fleet, feed, agent = feed_rig()
    answers = [False, True]
    feed.bind(lambda: answers.pop(0))
    source.hear(pose(agent, 1.0))  # refused (the app is shutting down, say)
    source.hear(pose(agent, 2.0))  # so this one wakes again (though it takes the first one's place)
    assert answers == [] and feed.drain() == 1


def test_one_feed_per_fleet_model() -> None:
    source, fleet, feed, agent = feed_rig()
    assert attach(source, fleet, threading.Lock()) is feed  # type: ignore[arg-type]
    source.hear(pose(agent, 1.0))
    assert len(source.sinks) == 1 and feed.applied == 1  # subscribed once: folded in once
    app = ConsoleApp(source, fleet, SimClock())  # type: ignore[arg-type]
    assert app.feed is feed and app.lock is feed.lock and len(source.sinks) == 1  # the app shares it
    other = FleetModel(ME)
    assert attach(source, other, threading.Lock()) is not feed  # type: ignore[arg-type]


def test_lease_renewal_every_2_s_for_the_leases_held() -> None:
    """A third of the lease at most, and every ``CONTACT_RENEW_S`` (2 s): the robot's sign of contact."""
    fleet = FleetModel(ME)
    agent = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")
    other = wire.HeaderCounter(SimClock(), robot="r2", sender="agent-r2")
    renewal = LeaseRenewal(60.0)
    assert renewal.due(fleet, 0.0) == []  # nothing held
    fleet.apply(agent.make(Lease, holder=ME, until=100.0), "zenoh", 1.0)
    fleet.apply(other.make(Lease, holder="operator-2", until=100.0), "zenoh", 1.0)
    assert renewal.due(fleet, 1.0) == []  # 2 s have not passed since the last look
    assert renewal.due(fleet, 2.0) == ["r1"]  # ours only
    assert renewal.due(fleet, 3.9) == []
    assert renewal.due(fleet, 4.0) == ["r1"]


def test_row_cells_say_and_colour_what_matters() -> None:
    fleet = FleetModel(ME)
    agent = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")
    fleet.apply(pose(agent, 1.0), "zenoh", 10.0)
    view = fleet.robots["r1"]
    up = (LinkHealth("zenoh", True, 0.1, 0.0, 0.0042, ""), LinkHealth("mqtt", True, 0.1, 0.0, None, ""))
    cells = row_cells(view, "zenoh", up, True, ME, 10.25)
    assert [str(c) for c in cells] == ["r1", "?", "?", "zenoh", "ok 0% 4ms", "250ms", "ok", "-"]
    assert isinstance(cells[3], Text) and cells[3].style == "green"
    down = (LinkHealth("zenoh", False, 2.0, 50.0, None, "silent"),)
    view.lost, view.estop, view.lease_holder = True, True, ME
    cells = row_cells(view, "mqtt", down, False, ME, 12.5)
    assert [str(c) for c in cells] == ["r1", "ESTOP", "?", "mqtt", "DOWN 50%", "2.5s", "stale", "you"]
    styles = [c.style for c in cells if isinstance(c, Text)]
    assert styles == ["bold red", "bold red", "bold yellow", "bold red", "bold yellow"]
    rows = fleet_rows(fleet, lambda r: "zenoh", lambda r: up, ME, 10.5, filter_text="MQTT")
    assert rows == {}  # the filter keeps only rows whose text contains it


@run_async
async def test_the_table_touches_only_cells_that_changed(tmp_path: Path) -> None:
    rig = Rig(tmp_path)
    rig.start()
    updates: list[tuple[str, str]] = []
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            table = rig.app.query_one(FleetTable)
            real = table.update_cell

            def counting(row: Any, column: Any, value: Any, **kw: Any) -> None:
                updates.append((str(row), str(column)))
                real(row, column, value, **kw)

            table.update_cell = counting  # type: ignore[method-assign]
            await with_robots(rig, pilot, "r1")
            rig.zenoh.inject(rig.counter("r1").make(Lease, holder="", until=0.0))
            # The lease cell changes once; the age cell whenever a redraw finds another age (a pose
            # arrives every 50 ms, the clock ticks at 2 Hz): wait for both, as long as a loaded
            # machine needs (within 0.5 s on a calm one; once no redraw saw a new age in it).
            columns: set[str] = set()
            for _ in range(40):
                await settle(pilot, 0.1)
                columns = {c for _, c in updates}
                if {"lease", "age"} <= columns:
                    break
            assert "lease" in columns and "age" in columns
            assert not columns & {"robot", "battery", "mode"}  # never changed: never redrawn
            assert table.get_cell("r1", "lease") == "free"
            assert [k for _, k in COLUMNS] == [str(c.key.value) for c in table.columns.values()]
    finally:
        rig.close()


@run_async
async def test_telemetry_is_drawn_as_it_arrives_without_a_polling_timer(tmp_path: Path) -> None:
    """The clock tick is set to once a minute: what the robots say still shows at once, because
    the feed posts it to the app."""
    rig = Rig(tmp_path)
    rig.app = ConsoleApp(rig.link, rig.fleet, rig.clock, lock=rig.lock, clock_hz=1 / 60)
    rig.start()
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            await settle(pilot)
            frames = len(rig.app.frame_times)
            rig.pose("r7", 1.0, 2.0)  # from this (the test's) thread, as a transport would
            threading.Thread(target=rig.pose, args=("r8", 3.0, 4.0)).start()  # and from another
            await settle(pilot, 0.3)
            table = rig.app.query_one(FleetTable)
            assert [str(k.value) for k in table.rows] == ["r7", "r8"]
            assert len(rig.app.frame_times) > frames
            assert rig.app.feed.applied >= 2
    finally:
        rig.close()


@run_async
async def test_the_network_never_waits_for_the_ui(tmp_path: Path) -> None:
    """While the app is busy (here: holding the model's lock), a transport's callback returns at
    once; the message is folded in when the app gets to it."""
    rig = Rig(tmp_path)
    rig.start()
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            await settle(pilot)
            done = threading.Event()
            with rig.lock:
                t = threading.Thread(target=lambda: (rig.pose("r1", 1.0, 1.0), done.set()))
                t.start()
                assert done.wait(2.0), "the transport's thread was blocked by the UI"
                assert "r1" not in rig.fleet.robots
            await settle(pilot)
            assert "r1" in rig.fleet.robots
    finally:
        rig.close()


def test_the_detail_shows_what_the_robots_agent_refused() -> None:
    """The agent's ``Diagnostics`` (issue 14) reach the operator: refused inputs and the last reason."""
    from fleetlink.operator.detail import detail_text
    from fleetlink.shared.messages import Count, Diagnostics

    fleet = FleetModel(ME)
    agent = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")
    fleet.apply(agent.make(Pose, x=0.0, y=0.0, theta=0.0, sd_x_m=0.1, sd_y_m=0.1, sd_theta_rad=0.1,
                           odom_x=0.0, odom_y=0.0, odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=False), "zenoh", 0.0)  # fmt: skip
    assert "refused" not in detail_text("r1", fleet.robots["r1"], ())
    reason = "header.sender: 'op-alice' does not match the key's sender 'op-bob' (who published it)"
    diag = agent.make(
        Diagnostics,
        rejected=(Count(key="zenoh/teleop", count=7), Count(key="mqtt/teleop", count=2)),
        duplicates=3,
        handler_failures=1,
        oversized=(Count(key="zenoh", count=1),),
        dropped=(Count(key="mqtt", count=5),),
        last_reason=reason,
    )
    assert fleet.apply(diag, "zenoh", 1.0)
    text = detail_text("r1", fleet.robots["r1"], ())
    assert "refused 11 inputs" in text and "does not match the key's sender 'op-bob'" in text


def test_the_fleet_maps_own_messages_make_no_robot() -> None:
    """``fleet`` is where the fleet map is served (another console's, or ``fleetlink map fleet``):
    what comes from it is no robot to list, drive or stop."""
    source, fleet, feed, _agent = feed_rig()
    other = wire.HeaderCounter(SimClock(), robot=keys.FLEET_MAP, sender="fleet-map")
    source.hear(pose(other, 1.0))
    assert keys.FLEET_MAP not in fleet.robots and feed.applied == 1


def test_a_robot_may_not_be_called_fleet() -> None:
    from fleetlink.agent.config import _robot_id

    with pytest.raises(ValueError, match="fleet map"):
        _robot_id(keys.FLEET_MAP)


def test_telemetry_on_both_links_counts_once_and_either_link_alone_keeps_it_coming() -> None:
    fleet = FleetModel(ME)
    agent = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")
    both = pose(agent, 1.0)
    assert fleet.apply(both, "mqtt", 1.0)  # whichever copy comes first is taken ...
    assert not fleet.apply(both, "zenoh", 1.001)  # ... and the other skipped
    assert fleet.robots["r1"].pose == (1.0, 0.0, 0.0) and len(fleet.robots["r1"].trail) == 1
    for i, link in enumerate(("zenoh", "zenoh", "mqtt", "mqtt")):  # Zenoh cut after two: MQTT alone
        assert fleet.apply(pose(agent, 2.0 + i), link, 2.0 + i)
    assert fleet.robots["r1"].pose == (5.0, 0.0, 0.0)


def test_health_cell_shows_a_degraded_primary_and_a_fallback_that_is_not_fine() -> None:
    from fleetlink.operator.fleet_table import health_cell

    ok = LinkHealth("zenoh", True, 0.1, 0.0, 0.0008, "")
    slow = LinkHealth("mqtt", True, 0.1, 0.0, 0.15, "", 0.2, degraded="rtt p95 200 ms > 100 ms")
    assert str(health_cell((ok, slow))) == "ok 0% 1ms m!"
    degr = LinkHealth("zenoh", True, 0.1, 20.0, 0.001, "", degraded="loss 20% > 5%")
    down = LinkHealth("mqtt", False, 2.0, 0.0, None, "silent")
    cell = health_cell((degr, down))
    assert str(cell) == "degr 20% 1ms m✗" and cell.style == "bold yellow"


def test_a_robot_in_its_own_frame_is_drawn_on_the_fleet_map_through_the_frame_found_for_it() -> None:
    """A robot without UWB reports poses in its own map's frame; once the fleet map service found
    that frame (``FleetResult.frames``), the console draws the robot, its trail and its scan on the
    fleet map, and a goal typed there goes to the robot in its own frame (``to_robot``)."""
    import math

    import numpy as np

    from fleetlink.operator.alarms import AlarmKind
    from fleetlink.operator.detail import detail_text
    from fleetlink.shared.messages import UNKNOWN_SD_M, AgvPosition, State
    from tests.harness.messages import state_fields

    fleet = FleetModel(ME)
    agent = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")
    fleet.apply(agent.make(Pose, x=1.0, y=0.0, theta=0.0, sd_x_m=UNKNOWN_SD_M, sd_y_m=UNKNOWN_SD_M, sd_theta_rad=UNKNOWN_SD_M,
                           odom_x=0.0, odom_y=0.0, odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=True), "zenoh", 0.0)  # fmt: skip
    fleet.set_frames({}, unframed=("r1",))
    view = fleet.robots["r1"]
    assert view.pose == (1.0, 0.0, 0.0) and view.off_fleet_map
    assert "not on the fleet map yet" in detail_text("r1", view, ())
    why = "on r2's map: 336 walls, fewer than the overlap needs"
    fleet.set_frames({}, unframed=("r1",), why={"r1": why})  # the fleet map's search says why
    assert f"its own frame: not on the fleet map yet ({why})" in detail_text("r1", view, ())
    trail_before = view.trail_added
    # Found: its frame lies at (5, 2), turned a quarter turn, on the fleet map.
    # Its localisation alarm speaks of the fleet map, not of the site position it never has.
    dark = AgvPosition(x=1.0, y=0.0, theta=0.0, mapId="", positionInitialized=False, localizationScore=0.0)
    fleet.alarms.observe(agent.make(State, **state_fields(agvPosition=dark, uwbStale=True)), 1.0)
    alarm = fleet.alarms.alarms.get("r1", AlarmKind.LOCALISATION)
    assert alarm is not None and alarm.text == f"localisation: its own map, not on the fleet map yet ({why})"
    fleet.set_frames({"r1": (5.0, 2.0, math.pi / 2)})
    assert not view.off_fleet_map and "not on the fleet map" not in detail_text("r1", view, ())
    fleet.alarms.observe(agent.make(State, **state_fields(agvPosition=dark, uwbStale=True)), 2.0)
    assert fleet.alarms.alarms.get("r1", AlarmKind.LOCALISATION) is None
    assert view.pose is not None and view.reported == (1.0, 0.0, 0.0)
    assert math.hypot(view.pose[0] - 5.0, view.pose[1] - 3.0) < 1e-9 and abs(view.pose[2] - math.pi / 2) < 1e-9
    assert list(view.trail) == [(view.pose[0], view.pose[1])] and view.trail_added > trail_before + len(view.trail)
    # Later poses and scans come through the frame too.
    fleet.apply(agent.make(Pose, x=2.0, y=0.0, theta=0.0, sd_x_m=UNKNOWN_SD_M, sd_y_m=UNKNOWN_SD_M, sd_theta_rad=UNKNOWN_SD_M,
                           odom_x=0.0, odom_y=0.0, odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=True), "zenoh", 0.1)  # fmt: skip
    assert math.hypot(view.pose[0] - 5.0, view.pose[1] - 4.0) < 1e-9
    fleet.set_scan("r1", np.array([[3.0, 0.0]]), 0.1)
    assert view.scan is not None and np.allclose(view.scan, [[5.0, 5.0]])
    # A goal at (5, 6) on the fleet map is (4, 0) in its own frame, facing its own heading 0 when
    # asked to face the fleet map's north.
    x, y, th = fleet.to_robot("r1", 5.0, 6.0, math.pi / 2)
    assert math.hypot(x - 4.0, y) < 1e-9 and th is not None and abs(th) < 1e-9
    assert fleet.to_robot("r1", 5.0, 6.0)[2] is None
    assert fleet.to_robot("r2", 5.0, 6.0, 1.0) == (5.0, 6.0, 1.0)  # a robot the fleet map has no frame for
    # A robot with a UWB position reports site poses (even while its map is still in its own frame,
    # before it restarts in the site frame): the frame found for its map does not move them.
    fleet.apply(agent.make(Pose, x=2.0, y=0.0, theta=0.0, sd_x_m=0.1, sd_y_m=0.1, sd_theta_rad=0.1,
                           odom_x=0.0, odom_y=0.0, odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=False), "zenoh", 0.2)  # fmt: skip
    assert view.pose == (2.0, 0.0, 0.0) and fleet.to_robot("r1", 5.0, 6.0, 1.0) == (5.0, 6.0, 1.0)


def test_a_robot_whose_map_began_again_is_not_placed_or_sent_goals_through_its_old_maps_frame() -> None:
    """A robot without UWB whose agent restarted reports poses in a new map (``Pose.map_began``),
    whose frame begins where it then stood. The frame the fleet map found for its old map would draw
    it, and send it goals, metres off: the console holds it off the fleet map, and says why, until
    the fleet map has found the new map (``RobotFrame.began``, ``set_frames``'s ``began``)."""
    import math

    from fleetlink.operator.detail import detail_text
    from fleetlink.shared.messages import UNKNOWN_SD_M

    fleet = FleetModel(ME)
    agent = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")

    def dark(x: float, began: float, t: float) -> None:
        fleet.apply(agent.make(Pose, x=x, y=0.0, theta=0.0, sd_x_m=UNKNOWN_SD_M, sd_y_m=UNKNOWN_SD_M, sd_theta_rad=UNKNOWN_SD_M,
                               odom_x=0.0, odom_y=0.0, odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=True, map_began=began),
                    "zenoh", t)  # fmt: skip

    dark(1.0, 20.0, 0.0)
    fleet.set_frames({"r1": (5.0, 2.0, 0.0)}, began={"r1": 20.0})
    view = fleet.robots["r1"]
    assert view.pose == (6.0, 2.0, 0.0) and not view.off_fleet_map
    assert fleet.to_robot("r1", 7.0, 2.0) == (2.0, 0.0, None)
    # Its agent restarts 1 m on: its new map's frame begins there, and its pose there is (0, 0).
    dark(0.0, 61.0, 1.0)
    assert view.pose == (0.0, 0.0, 0.0) and view.off_fleet_map  # as reported, not through the old frame
    assert "its map began again" in detail_text("r1", view, ())
    assert fleet.to_robot("r1", 7.0, 2.0) == (7.0, 2.0, None)  # not through the old frame either
    fleet.set_frames({"r1": (5.0, 2.0, 0.0)}, began={"r1": 20.0})  # a build of the old map: still off
    assert view.off_fleet_map and view.pose == (0.0, 0.0, 0.0)
    # The service forgets the old map and has not found the new one: its reason, after the restart's.
    nowhere = {"r1": "on r2's map: no place overlaps enough of the other's known floor"}
    fleet.set_frames({}, unframed=["r1"], why=nowhere)
    assert view.off_fleet_map_why == "its map began again; " + nowhere["r1"]
    assert "its map began again; on r2's map" in " ".join(detail_text("r1", view, ()).split())
    # The fleet map finds the new map, 1 m on from the old one's.
    fleet.set_frames({"r1": (6.0, 2.0, 0.0)}, began={"r1": 61.0})
    assert not view.off_fleet_map and view.pose is not None
    fleet.set_frames({}, unframed=["r1"], why=nowhere)  # lost again, its map the same: the reason alone
    assert view.off_fleet_map_why == nowhere["r1"]
    fleet.set_frames({"r1": (6.0, 2.0, 0.0)}, began={"r1": 61.0})
    assert not view.off_fleet_map
    assert math.hypot(view.pose[0] - 6.0, view.pose[1] - 2.0) < 1e-9
    assert fleet.to_robot("r1", 7.0, 2.0) == (1.0, 0.0, None)
    # Found where the old one was (restarted where it began): placed again all the same.
    dark(0.0, 90.0, 2.0)
    assert view.off_fleet_map
    fleet.set_frames({"r1": (6.0, 2.0, 0.0)}, began={"r1": 90.0})
    assert not view.off_fleet_map and view.pose == (6.0, 2.0, 0.0)
    # Restarted once more: its first poses say 0 (its new map not begun yet), and are not placed.
    dark(0.0, 0.0, 3.0)
    assert view.off_fleet_map and view.pose == (0.0, 0.0, 0.0)
    # An agent before 1.2.0 names no map: the frame found for it holds, whatever map it was found for.
    legacy = wire.HeaderCounter(SimClock(), robot="r2", sender="agent-r2")
    fleet.apply(legacy.make(Pose, x=1.0, y=0.0, theta=0.0, sd_x_m=UNKNOWN_SD_M, sd_y_m=UNKNOWN_SD_M,
                            sd_theta_rad=UNKNOWN_SD_M, odom_x=0.0, odom_y=0.0, odom_theta=0.0, vx=0.0, omega=0.0,
                            uwbStale=True), "zenoh", 4.0)  # fmt: skip
    fleet.set_frames({"r1": (6.0, 2.0, 0.0), "r2": (5.0, 2.0, 0.0)}, began={"r1": 90.0, "r2": 33.0})
    assert fleet.robots["r2"].pose == (6.0, 2.0, 0.0) and not fleet.robots["r2"].off_fleet_map
