"""The field's radio (field/radio.py): access points, walls, dead zones, hysteresis; the plan format;
the office's dark room; and the radio applied by a lockstep run (site/lockstep.py: a robot's
endpoints cut while out of reach, contact spans) and by the real-time site (links behind a gate)."""

from __future__ import annotations

import math
import threading
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fleetlink.field.plans import FloorPlan, PlanError, dump_plan, load_plan, parse_plan, save_plan
from fleetlink.field.radio import (
    LINKS,
    AccessPoint,
    ContactLog,
    FleetRadio,
    RadioModel,
    RadioSettings,
    RadioTracker,
    walls_crossed,
)
from fleetlink.field.scenario import parse_scenario
from fleetlink.links.gated import GatedLink
from fleetlink.links.inprocess import InProcessBus
from fleetlink.shared.messages import Action, ActionType, InstantActions, LinkName

Z, M = LinkName.ZENOH, LinkName.MQTT
S = RadioSettings()  # sensitivity -80 dBm, 40 dB at 1 m, exponent 3, 5 dB a wall, hysteresis 3 dB


def free_space(d: float, tx: float = 20.0) -> float:
    return tx - S.reference_loss_db - 10 * S.path_loss_exponent * math.log10(max(d, 1.0))


# A 30 x 10 m hall cut by a full-height wall at x = 10 and another at x = 20.
WALLS = [(0.0, 0.0, 30.0, 0.0), (30.0, 0.0, 30.0, 10.0), (30.0, 10.0, 0.0, 10.0), (0.0, 10.0, 0.0, 0.0)]
WALLS += [(10.0, 0.0, 10.0, 10.0), (20.0, 0.0, 20.0, 10.0)]


def hall(*aps: AccessPoint, dead: tuple[tuple[tuple[float, float], ...], ...] = (), **settings: float) -> RadioModel:
    return RadioModel(aps, WALLS, dead, RadioSettings(**settings))


# -- the pure core ----------------------------------------------------------------------------------


def test_walls_crossed_counts_each_wall_on_the_line_of_sight() -> None:
    assert walls_crossed(WALLS, 1.0, 5.0, 9.0, 5.0) == 0
    assert walls_crossed(WALLS, 1.0, 5.0, 11.0, 5.0) == 1
    assert walls_crossed(WALLS, 1.0, 5.0, 29.0, 9.0) == 2
    assert walls_crossed(WALLS, 1.0, 5.0, 10.0, 5.0) == 0  # ending on a wall does not cross it
    assert walls_crossed(WALLS, 10.0, 2.0, 10.0, 8.0) == 0  # along a wall, not through it
    assert walls_crossed([], 1.0, 5.0, 29.0, 5.0) == 0


def test_line_of_sight_follows_the_log_distance_law_and_each_wall_costs_its_loss() -> None:
    m = hall(AccessPoint("ap", 1.0, 5.0))
    assert m.levels(9.0, 5.0)[Z] == pytest.approx(free_space(8.0))
    assert m.levels(11.0, 5.0)[Z] == pytest.approx(free_space(10.0) - S.wall_loss_db)
    assert m.levels(21.0, 5.0)[M] == pytest.approx(free_space(20.0) - 2 * S.wall_loss_db)
    assert m.levels(1.2, 5.0)[Z] == pytest.approx(free_space(1.0))  # nearer than 1 m counts as 1 m
    # One more wall is one more loss, whatever the distance law says: the same 9 m either side.
    a, b = hall(AccessPoint("ap", 9.5, 5.0)).levels(0.5, 5.0)[Z], hall(AccessPoint("ap", 9.5, 5.0)).levels(18.5, 5.0)[Z]
    assert a - b == pytest.approx(S.wall_loss_db)
    heavy = hall(AccessPoint("ap", 1.0, 5.0), wall_loss_db=20.0, path_loss_exponent=2.0)
    assert heavy.levels(11.0, 5.0)[Z] == pytest.approx(20 - 40 - 20 * 1.0 - 20.0)


def test_a_link_is_reachable_at_the_sensitivity_and_the_best_access_point_counts() -> None:
    m = hall(AccessPoint("west", 1.0, 5.0), AccessPoint("east", 29.0, 5.0, tx_power_dbm=0.0))
    # From the west AP alone, 15 m and one wall: 20 - 40 - 35.3 - 5 = -60.3 dBm.
    assert m.reachable(Z, 16.0, 5.0)
    assert m.levels(28.0, 5.0)[Z] == pytest.approx(max(free_space(27.0) - 10.0, free_space(1.0, tx=0.0)))
    weak = hall(AccessPoint("ap", 1.0, 5.0), sensitivity_dbm=-62.0)
    assert weak.reachable(Z, 9.0, 5.0) and not weak.reachable(Z, 21.0, 5.0)


def test_hysteresis_keeps_a_link_on_the_edge_from_flapping() -> None:
    m = hall(AccessPoint("ap", 0.5, 5.0), wall_loss_db=0.0)
    # The distance where the level is exactly the sensitivity, and 1.5 dB below it.
    edge = 10 ** ((20 - 40 - S.sensitivity_dbm) / 30)
    inside = 10 ** ((20 - 40 - S.sensitivity_dbm + 1.5) / 30)
    x_edge, x_grey = 0.5 + edge, 0.5 + inside
    assert m.levels(x_grey, 5.0)[Z] == pytest.approx(S.sensitivity_dbm - 1.5)
    assert m.reachable(Z, x_grey, 5.0, was_up=True)  # an up link stays up in the grey band
    assert not m.reachable(Z, x_grey, 5.0, was_up=False)  # a down link needs the sensitivity
    assert not m.reachable(Z, x_grey, 5.0)  # no history: the sensitivity
    tracker = RadioTracker(m, 2.0, 5.0)
    changes: list[tuple[LinkName, ...]] = []
    # Jitter around the sensitivity's edge: the link stays up.
    for k in range(200):
        changes.append(tracker.update(x_edge + 0.3 * math.sin(k), 5.0))
    assert not any(changes) and tracker.up[Z]
    far = 0.5 + 10 ** ((20 - 40 - S.sensitivity_dbm + S.hysteresis_db + 0.5) / 30)
    assert tracker.update(far, 5.0) == (Z, M) and not tracker.in_contact
    # Back in the grey band: still down, jitter and all, until the sensitivity is reached again.
    for k in range(200):
        assert tracker.update(x_grey + 0.05 * math.sin(k), 5.0) == ()
    assert tracker.update(x_edge - 0.3, 5.0) == (Z, M) and tracker.in_contact


def test_a_dead_zone_lets_nothing_through_even_beside_an_access_point() -> None:
    zone = ((2.0, 2.0), (6.0, 2.0), (6.0, 8.0), (2.0, 8.0))
    m = hall(AccessPoint("ap", 1.0, 5.0), dead=(zone,))
    assert m.in_dead_zone(3.0, 5.0) and not m.in_dead_zone(7.0, 5.0)
    assert m.levels(3.0, 5.0) == {Z: -math.inf, M: -math.inf}
    assert not m.reachable(Z, 3.0, 5.0, was_up=True) and not m.reachable(M, 3.0, 5.0, was_up=True)
    assert m.reachable(Z, 7.0, 5.0)
    tracker = RadioTracker(m, 1.5, 5.0)
    assert tracker.update(2.1, 5.0) == (Z, M)  # the zone's edge, not a centimetre later
    assert tracker.update(5.99, 5.0) == ()
    assert tracker.update(6.01, 5.0) == (Z, M)


def test_without_access_points_or_dead_zones_every_link_reaches_everywhere() -> None:
    m = RadioModel((), WALLS)
    assert not m.enabled and m.modelled == ()
    assert all(m.reachable(link, x, 5.0, was_up=False) for link in LINKS for x in (0.5, 15.0, 29.5))
    tracker = RadioTracker(m, 1.0, 1.0)
    assert tracker.update(25.0, 9.0) == () and tracker.up == {Z: True, M: True}
    for name in ("apartment", "hall", "apartment-map"):  # every built-in but the office: as before
        assert not RadioModel.from_plan(load_plan(name)).enabled


def test_a_link_no_access_point_carries_is_not_modelled_but_dead_zones_still_stop_it() -> None:
    zone = ((24.0, 2.0), (28.0, 2.0), (28.0, 8.0), (24.0, 8.0))
    m = hall(AccessPoint("zen", 1.0, 5.0, links=(Z,)), dead=(zone,), sensitivity_dbm=-60.0)
    assert m.modelled == (Z,)
    assert m.reachable(M, 22.0, 5.0, was_up=False) and not m.reachable(Z, 22.0, 5.0)
    assert not m.reachable(M, 25.0, 5.0, was_up=True)
    both = hall(
        AccessPoint("zen", 1.0, 5.0, links=(Z,)), AccessPoint("mq", 29.0, 5.0, links=(M,)), sensitivity_dbm=-60.0
    )
    assert both.reachable(Z, 2.0, 5.0) and not both.reachable(M, 2.0, 5.0)
    assert both.reachable(M, 28.0, 5.0) and not both.reachable(Z, 28.0, 5.0)


def test_the_model_is_deterministic_and_the_tracker_matches_a_fresh_evaluation() -> None:
    plan = load_plan("office")
    a, b = RadioModel.from_plan(plan), RadioModel.from_plan(plan)
    rng = np.random.default_rng(1)
    for x, y in rng.uniform((0.2, 0.2), (39.8, 19.8), size=(300, 2)):
        assert a.levels(x, y) == b.levels(x, y)
        assert a.reachable_all(x, y, {Z: True, M: False}) == b.reachable_all(x, y, {Z: True, M: False})


def test_fleet_radio_and_the_contact_log() -> None:
    zone = ((12.0, 2.0), (14.0, 2.0), (14.0, 8.0), (12.0, 8.0))
    fleet = FleetRadio(hall(AccessPoint("ap", 1.0, 5.0), dead=(zone,)), {"r1": (2.0, 5.0), "r2": (13.0, 5.0)})
    assert fleet.reachable("r1", Z) and not fleet.reachable("r2", M)
    assert fleet.update("r1", 13.0, 5.0) == (Z, M) and not fleet.reachable("r1", Z)
    log = ContactLog(["r1", "r2"])
    assert log.update("r1", 1.0, True) is False
    assert log.update("r1", 2.0, False) is True and log.update("r1", 2.5, False) is False
    assert log.update("r1", 4.0, True) is True
    log.update("r1", 6.0, False)
    assert log.intervals == {"r1": [(2.0, 4.0), (6.0, None)], "r2": []}
    assert log.lost_seconds("r1", until=7.0) == pytest.approx(3.0)


# -- the plan format --------------------------------------------------------------------------------

RADIO_PLAN = """
name = "garage"
bounds = [0.0, 0.0, 10.0, 5.0]
walls = [[0.0, 0.0, 10.0, 0.0], [5.0, 0.0, 5.0, 3.0]]

[radio]
sensitivity_dbm = -75.0
wall_loss_db = 9.5

[[access_points]]
name = "ap-1"
x = 1.0
y = 1.0

[[access_points]]
name = "ap-2"
x = 12.0                 # outside the bounds, like an anchor on a fence
y = 1.0
links = ["mqtt"]
tx_power_dbm = 15.0

[[dead_zones]]
name = "lift"
polygon = [[6.0, 0.0], [7.0, 0.0], [7.0, 5.0], [6.0, 5.0]]
"""


def test_a_plan_reads_access_points_dead_zones_and_radio_settings_and_round_trips(tmp_path: Path) -> None:
    plan = parse_plan(tomllib.loads(RADIO_PLAN), "garage.toml")
    assert plan.access_points == (AccessPoint("ap-1", 1.0, 1.0), AccessPoint("ap-2", 12.0, 1.0, (M,), 15.0))
    assert plan.dead_zones == (((6.0, 0.0), (7.0, 0.0), (7.0, 5.0), (6.0, 5.0)),)
    assert plan.radio == RadioSettings(sensitivity_dbm=-75.0, wall_loss_db=9.5)
    again = load_plan(save_plan(plan, tmp_path / "copy.toml"))
    assert again.access_points == plan.access_points and again.dead_zones == plan.dead_zones
    assert again.radio == plan.radio and dump_plan(again) == dump_plan(plan)
    assert "[radio]" not in dump_plan(load_plan("apartment"))  # the defaults are not written out
    model = RadioModel.from_plan(plan)
    assert model.settings.wall_loss_db == 9.5 and model.modelled == (Z, M)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ('links = ["mqtt"]', 'links = ["wifi"]', "garage.toml: access_points[1].links[0]: expected one of zenoh, mqtt"),
        ('links = ["mqtt"]', 'links = ["mqtt", "mqtt"]', "garage.toml: access_points[1].links: a link is named twice"),
        ('links = ["mqtt"]', "links = []", "garage.toml: access_points[1].links: needs at least 1 item"),
        (
            'links = ["mqtt"]',
            'lnks = ["mqtt"]',
            "garage.toml: access_points[1].lnks: unknown key (did you mean links?)",
        ),
        ("tx_power_dbm = 15.0", "tx_power_dbm = 90.0", "garage.toml: access_points[1].tx_power_dbm: must be <= 40.0"),
        ("x = 12.0 ", 'x = "east" ', "garage.toml: access_points[1].x: expected a number"),
        ('name = "ap-2"', 'name = "ap-1"', "garage.toml: access_points[1].name: access point 'ap-1' appears twice"),
        ('name = "ap-2"', 'name = "ap 2"', "garage.toml: access_points[1].name: names use letters"),
        (
            "wall_loss_db = 9.5",
            "wall_loss = 9.5",
            "garage.toml: radio.wall_loss: unknown key (did you mean wall_loss_db?)",
        ),
        ("sensitivity_dbm = -75.0", "sensitivity_dbm = 5.0", "garage.toml: radio.sensitivity_dbm: must be <= 0.0"),
        ("sensitivity_dbm = -75.0", 'sensitivity_dbm = "low"', "garage.toml: radio.sensitivity_dbm: expected a number"),
        (
            "[7.0, 5.0], [6.0, 5.0]]",
            "[7.0, 5.0], [16.0, 5.0]]",
            "garage.toml: dead_zones[0][3]: point (16, 5) lies outside",
        ),
        (
            "[[6.0, 0.0], [7.0, 0.0], [7.0, 5.0], [6.0, 5.0]]",
            "[[6.0, 0.0], [7.0, 0.0]]",
            "dead_zones[0].polygon: needs at least 3",
        ),
        ("[[6.0, 0.0], [7.0, 0.0], [7.0, 5.0], [6.0, 5.0]]", "[[6.0, 0.0], [7.0, 0.0], [8.0, 0.0]]", "no area"),
    ],
)
def test_bad_radio_entries_are_refused_naming_the_file_and_the_key(old: str, new: str, message: str) -> None:
    assert old in RADIO_PLAN
    with pytest.raises(PlanError) as err:
        parse_plan(tomllib.loads(RADIO_PLAN.replace(old, new, 1)), "garage.toml")
    assert message in str(err.value)


def test_a_plan_built_in_python_is_held_to_the_same_rules() -> None:
    box = {"name": "box", "bounds": (0.0, 0.0, 5.0, 5.0)}
    with pytest.raises(PlanError, match=r"access_points\[0\]\.x: must be finite"):
        FloorPlan(**box, access_points=(AccessPoint("a", math.nan, 1.0),))  # type: ignore[arg-type]
    with pytest.raises(PlanError, match=r"access_points\[0\]\.links: expected one or both"):
        FloorPlan(**box, access_points=(AccessPoint("a", 1.0, 1.0, ()),))  # type: ignore[arg-type]
    with pytest.raises(PlanError, match=r"radio\.hysteresis_db: must be >= 0"):
        FloorPlan(**box, radio=RadioSettings(hysteresis_db=-1.0))  # type: ignore[arg-type]


# -- the office: one dark room ----------------------------------------------------------------------

DARK_ROOM = (34.0, 0.0, 40.0, 8.5)  # room-6, the records room
OUTSIDE_DARK_ROOM = (35.45, 9.75)  # the corridor in front of its door


def test_the_office_has_one_dark_room_and_signal_in_the_corridor_and_every_other_room() -> None:
    plan = load_plan("office")
    m = RadioModel.from_plan(plan)
    assert m.enabled and m.modelled == (Z, M)
    x0, y0, x1, y1 = DARK_ROOM
    for x in np.linspace(x0 + 0.2, x1 - 0.2, 12):
        for y in np.linspace(y0 + 0.2, y1 - 0.05, 12):
            assert not any(m.reachable_all(x, y, {Z: True, M: True}).values()), (x, y)
    # Corridor (all its length) and lobby: both links, with the hysteresis to spare.
    margin = S.sensitivity_dbm + S.hysteresis_db
    for x in np.arange(0.3, 39.8, 0.1):
        for y in (8.7, 9.75, 10.8):
            assert min(m.levels(x, y).values()) >= margin, (x, y)
    assert min(m.levels(*OUTSIDE_DARK_ROOM).values()) >= margin
    for name, pose in plan.starts.items():
        assert min(m.levels(pose.x, pose.y).values()) >= margin, name
    # Every other room, the plant room and the stairwell have signal wall to wall.
    rooms = {f"room-{i + 1}": (6.0 + b[0], 0.0, 6.0 + b[1], 8.5) for i, b in enumerate(_BAYS[:5])}
    rooms |= {f"room-{i + 7}": (6.0 + b[0], 11.0, 6.0 + b[1], 20.0) for i, b in enumerate(_BAYS)}
    rooms |= {"plant": (0.0, 0.0, 6.0, 4.0), "stairwell": (3.8, 16.0, 6.0, 20.0)}
    for name, (ax, ay, bx, by) in rooms.items():
        pts = [(x, y) for x in np.linspace(ax + 0.3, bx - 0.3, 8) for y in np.linspace(ay + 0.3, by - 0.3, 8)]
        lit = sum(1 for x, y in pts if all(m.reachable_all(x, y, {Z: False, M: False}).values()))
        assert lit == len(pts), (name, lit)


_BAYS = [(0.0, 5.5), (5.5, 11.0), (11.0, 16.5), (16.5, 22.0), (22.0, 28.0), (28.0, 34.0)]


# -- the in-process bus: two causes of a cut ---------------------------------------------------------


def test_a_bus_endpoint_is_back_only_when_every_reason_for_its_cut_is_lifted() -> None:
    bus = InProcessBus(Z)
    a, b = bus.endpoint("a"), bus.endpoint("b")
    got: list[bytes] = []
    for e in (a, b):
        e.start()
    b.subscribe("k/**", lambda _k, p: got.append(p))
    bus.cut("b")  # a scenario's cut
    bus.cut("b", "radio")
    assert bus.cut_reasons("b") == {"scenario", "radio"} and not b.up
    bus.restore("b", "radio")
    assert not b.up and bus.cut_reasons("b") == {"scenario"}
    a.publish("k/1", b"lost")
    bus.deliver()
    bus.restore("b")
    assert b.up and bus.cut_reasons("b") == frozenset()
    bus.restore("b")  # idempotent
    a.publish("k/2", b"kept")
    bus.deliver()
    assert got == [b"kept"] and b.stats.dropped == 1
    with pytest.raises(KeyError):
        bus.cut("nobody", "radio")


# -- the gate the real-time site puts on an agent's links ------------------------------------------


def test_a_gated_link_passes_nothing_either_way_and_reads_down_while_closed() -> None:
    bus = InProcessBus(M)
    inner, peer = bus.endpoint("agent-r1"), bus.endpoint("operator")
    open_ = [True]
    gated = GatedLink(inner, lambda: open_[0])
    got: list[bytes] = []
    heard: list[bytes] = []
    for e in (gated, peer):
        e.start()
    gated.subscribe("fleetlink/**", lambda _k, p: got.append(p))
    peer.subscribe("fleetlink/**", lambda _k, p: heard.append(p))
    gated.serve("fleetlink/r1/map", lambda _q: [("fleetlink/r1/map", b"map")])
    assert gated.up and gated.name is M and gated.stats is inner.stats
    open_[0] = False
    assert not gated.up and inner.up  # the transport underneath stays connected
    assert gated.publish("fleetlink/r1/pose", b"out") is False
    peer.publish("fleetlink/r1/order", b"in")
    bus.deliver()
    assert got == [] and heard == [] and inner.stats.dropped == 2
    assert peer.query("fleetlink/r1/map") == [] and gated.query("fleetlink/**") == []
    open_[0] = True
    assert gated.publish("fleetlink/r1/pose", b"out2")
    peer.publish("fleetlink/r1/order", b"in2")
    bus.deliver()
    assert got == [b"in2"] and heard == [b"out2"]
    assert peer.query("fleetlink/r1/map") == [("fleetlink/r1/map", b"map")]
    gated.unserve("fleetlink/r1/map")
    assert peer.query("fleetlink/r1/map") == []
    gated.close()
    assert not inner.up


def test_the_agent_runtime_puts_its_links_behind_the_radio() -> None:
    from fleetlink.agent.config import AgentConfig, ZenohSettings, mqtt_settings
    from fleetlink.agent.runtime import AgentRuntime

    reach = {Z: True, M: True}
    config = AgentConfig(
        robot="r1",
        board="socket://127.0.0.1:1",
        zenoh=ZenohSettings(connect=("tcp/127.0.0.1:1",)),
        mqtt=mqtt_settings("mqtt://127.0.0.1:1"),
    )
    agent = AgentRuntime(config, reachable=lambda link: reach[link])  # not started: no sockets
    try:
        assert [type(link) for link in agent.node.links] == [GatedLink, GatedLink]
        assert agent.node.map_link is agent.node.links[0]
        assert [link.inner for link in agent.node.links] == [agent.zenoh, agent.mqtt]  # type: ignore[attr-defined]
        reach[Z] = False
        assert [link.is_open() for link in agent.node.links] == [False, True]  # type: ignore[attr-defined]
    finally:
        agent.node.close()
    plain = AgentRuntime(config)
    assert plain.node.links == [plain.zenoh, plain.mqtt]


# -- lockstep: the radio cuts a robot's endpoints where the map says ------------------------------


def _run_until(run: Any, done: Callable[[], bool], limit: float, step: float = 0.01) -> float:
    while not done():
        t = run.clock.now()
        assert t < limit, "the condition never came"
        run.run(t + step)
    return float(run.clock.now())


def _endpoints(run: Any, robot: str) -> list[Any]:
    return [e for bus in (run.zenoh, run.mqtt) for e in bus.endpoints if e.client_id == f"agent-{robot}"]


def test_a_robot_in_the_office_dark_room_loses_both_links_and_gets_them_back_outside() -> None:
    from fleetlink.site.lockstep import MissionRun

    x, y = OUTSIDE_DARK_ROOM
    scenario = parse_scenario(
        {
            "name": "dark-room",
            "plan": "office",
            "seed": 3,
            "duration_s": 30.0,
            "lidar": {"enabled": False},
            # In the corridor just outside room-6's door, facing into the room.
            "robots": [{"name": "scout-1", "pose": [x, 8.85, -90.0], "drive": "agent"}],
            "events": [{"at_s": 2.0, "kind": "teleop", "robot": "scout-1", "v": 0.2, "duration_s": 3.0}],
        }
    )
    with MissionRun(scenario, mapping=False) as run:
        board = run.field.rigs[0].robot.board
        zenoh, mqtt = _endpoints(run, "scout-1")
        run.run(1.5)
        assert zenoh.up and mqtt.up and run.reachable("scout-1", Z) and run.contact == {"scout-1": []}
        # The operator's teleop drives it through the door: both links go at the doorway.
        lost = _run_until(run, lambda: not run.reachable("scout-1", Z), limit=8.0)
        assert board.state.y <= 8.5 and not zenoh.up and not mqtt.up and not run.reachable("scout-1", M)
        assert run.zenoh.cut_reasons("agent-scout-1") == {"radio"}
        assert run.contact["scout-1"] == [(pytest.approx(lost), None)]
        # Its last teleop lapses; it stands in the dark room. Commands sent now never reach it.
        run.run(8.0)
        assert board.state.y < 8.5
        received = (zenoh.stats.received, mqtt.stats.received)
        dropped = zenoh.stats.dropped + mqtt.stats.dropped
        stop = run.operator.send(InstantActions, "scout-1", actions=_stop("in-the-dark"))
        run.run(10.0)
        assert (zenoh.stats.received, mqtt.stats.received) == received
        assert zenoh.stats.dropped + mqtt.stats.dropped > dropped
        # A rescuer carries it out into the corridor: both links come back.
        board.state.x, board.state.y = x, y
        back = _run_until(run, lambda: run.reachable("scout-1", Z), limit=12.0)
        assert zenoh.up and mqtt.up and run.contact["scout-1"] == [(pytest.approx(lost), pytest.approx(back))]
        again = run.operator.send(InstantActions, "scout-1", actions=_stop("in-the-corridor"))
        result = run.run(14.0)
    acked = {a.commandHeaderId for a in result.acks if a.commandTopic == "actions"}
    assert again.header.headerId in acked and stop.header.headerId not in acked
    assert result.contact == {"scout-1": [(pytest.approx(lost), pytest.approx(back))]}
    assert result.field.stats["scout-1"]["out_of_contact_s"] == pytest.approx(back - lost)
    radio_lines = [e for e in result.field.events if "radio reach" in e]
    assert len(radio_lines) == 4 and "scout-1 zenoh out of radio reach" in radio_lines[0]


def _stop(action_id: str) -> tuple[Action, ...]:
    return (Action(actionId=action_id, actionType=ActionType.STOP, actionParameters=()),)


def test_a_robot_driving_through_a_dead_zone_loses_and_regains_its_links_beside_a_scripted_cut(tmp_path: Path) -> None:
    """A goal through a 0.5 m dead zone across a corridor: both links go while the robot is in
    it and come back after it; the scenario's own Zenoh cut stays until the scenario lifts it."""
    from fleetlink.site.lockstep import MissionRun, write_mission_outputs

    plan = parse_plan(
        {
            "name": "tunnel",
            "bounds": [0.0, 0.0, 12.0, 3.0],
            "walls": [[0.0, 0.0, 12.0, 0.0], [12.0, 0.0, 12.0, 3.0], [12.0, 3.0, 0.0, 3.0], [0.0, 3.0, 0.0, 0.0]],
            "access_points": [{"name": "ap-west", "x": 0.5, "y": 1.5}],
            "dead_zones": [{"polygon": [[6.0, 0.0], [6.5, 0.0], [6.5, 3.0], [6.0, 3.0]]}],
            "anchors": [
                {"id": f"A{i}", "x": ax, "y": ay, "z": 2.5}
                for i, (ax, ay) in enumerate([(0.2, 0.2), (11.8, 0.2), (11.8, 2.8), (0.2, 2.8)])
            ],
        },
        "tunnel.toml",
    )
    scenario = parse_scenario(
        {
            "name": "tunnel",
            "plan": "tunnel.toml",
            "seed": 5,
            "duration_s": 20.0,
            "lidar": {"enabled": False},
            "robots": [{"name": "scout-1", "pose": [5.0, 1.5, 0.0], "drive": "agent"}],
            "events": [
                {"at_s": 3.0, "kind": "goal", "robot": "scout-1", "x": 7.5, "y": 1.5},
                {"at_s": 3.5, "kind": "link", "robot": "scout-1", "link": "zenoh", "state": "cut"},
                {"at_s": 15.0, "kind": "link", "robot": "scout-1", "link": "zenoh", "state": "restore"},
            ],
        }
    )
    with MissionRun(scenario, plan, mapping=False) as run:
        board = run.field.rigs[0].robot.board
        zenoh, mqtt = _endpoints(run, "scout-1")
        run.run(3.6)
        assert not zenoh.up and mqtt.up and run.zenoh.cut_reasons("agent-scout-1") == {"scenario"}
        lost = _run_until(run, lambda: not mqtt.up, limit=12.0)
        assert 6.0 <= board.state.x < 6.05
        assert run.zenoh.cut_reasons("agent-scout-1") == {"scenario", "radio"}
        assert run.mqtt.cut_reasons("agent-scout-1") == {"radio"}
        back = _run_until(run, lambda: mqtt.up, limit=12.0)
        assert 6.5 <= board.state.x < 6.55
        # Out of the zone: MQTT is back, Zenoh stays cut by the scenario until its restore at 15 s.
        assert not zenoh.up and run.zenoh.cut_reasons("agent-scout-1") == {"scenario"}
        result = run.run(16.0)
        assert zenoh.up and mqtt.up
    # Out of contact only inside the zone (MQTT carried the robot before and after it).
    assert result.contact == {"scout-1": [(pytest.approx(lost), pytest.approx(back))]}
    out = write_mission_outputs(result, tmp_path)
    rows = (out / "contact.csv").read_text().splitlines()
    assert rows == ["robot,t_lost_s,t_regained_s", f"scout-1,{lost:.3f},{back:.3f}"]


# -- real time: the site gates each agent's links ---------------------------------------------------


def test_the_real_time_site_silences_a_robot_in_the_dark_room_until_it_is_carried_out() -> None:
    from fleetlink.shared.clock import SystemClock
    from fleetlink.shared.messages import Ack, Pose, Teleop
    from fleetlink.site.field import FieldSite
    from tests.harness import wait_until

    x, y = OUTSIDE_DARK_ROOM
    scenario = parse_scenario(
        {
            "plan": "office",
            "seed": 2,
            "lidar": {"enabled": False},
            "robots": [
                {"name": "lit", "pose": [x, y, 0.0], "drive": "idle"},
                {"name": "dark", "pose": [36.0, 6.5, 0.0], "drive": "idle"},  # in room-6
            ],
        }
    )
    site = FieldSite(scenario, clock=SystemClock(), operator="operator-1", say=print)
    got: list[tuple[Any, str]] = []
    lock = threading.Lock()

    def heard(robot: str, cls: type, on: str | None = None) -> int:
        with lock:
            return sum(1 for m, lk in got if isinstance(m, cls) and m.header.robot == robot and on in (None, lk))

    try:
        site.start()
        assert site.radio is not None and site.agents is not None and site.link is not None
        link = site.link

        def sink(msg: Any, on: str, _t: float) -> None:
            with lock:
                got.append((msg, on))

        link.add_sink(sink)
        dark = site.agents.agents["dark"]
        assert not site.radio.reachable("dark", Z) and not site.radio.reachable("dark", M)
        assert site.radio.reachable("lit", Z) and site.radio.reachable("lit", M)
        assert not any(link_.up for link_ in dark.node.links)  # the agent sees both links down
        wait_until(lambda: heard("lit", Pose, "zenoh") > 20 and heard("lit", Pose, "mqtt") > 20, timeout=20)
        assert heard("dark", Pose) == 0
        # A teleop to each: the lit robot acks, the dark one hears nothing.
        sent = {r: link.send(Teleop, r, v=0.0, omega=0.0, ttl_s=0.5).header.headerId for r in ("lit", "dark")}

        def acked(robot: str) -> bool:
            with lock:
                return any(
                    isinstance(m, Ack) and m.header.robot == robot and m.commandHeaderId == sent[robot] for m, _ in got
                )

        wait_until(lambda: acked("lit"), timeout=10, message="the lit robot's ack")
        assert not acked("dark") and heard("dark", Pose) == 0
        # Carried out into the corridor: the radio lets its links through again.
        with site.field.lock:
            state = site.field.world.by_name["dark"].board.state
            state.x, state.y = x + 1.0, y
        wait_until(lambda: site.radio is not None and site.radio.reachable("dark", Z), timeout=5, message="reach")
        wait_until(lambda: heard("dark", Pose, "zenoh") > 0 and heard("dark", Pose, "mqtt") > 0, timeout=10)
        wait_until(lambda: all(link_.up for link_ in dark.node.links), timeout=10, message="its links up")
    finally:
        site.stop()
