"""Rounds from the console (issue 16): ``:disinfect`` / ``:sweep`` parsed, planned in a worker and
sent as orders with nodes; ``:pause``, ``:resume``, ``:cancel`` and ``P`` as instant actions; the
detail showing a round's progress from the robot's State; the map drawing the running round and the
people-present zones; bad input refused with a warning and nothing sent."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from textual.widgets import Input, RichLog

from fleetlink.cli.console import load_settings
from fleetlink.operator.commands import CommandError, RoundAction, StartRound, parse_command
from fleetlink.operator.detail import RobotDetail, detail_text
from fleetlink.operator.fleet import FleetModel, grid_through
from fleetlink.operator.maprender import ROUTE_DONE_STYLE, ROUTE_STYLE, ZONE_STYLE
from fleetlink.operator.mapview import MapView
from fleetlink.operator.rounds import DEFAULT_LAMP, PolyArea, RectArea, RoomArea
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.config import ConfigError
from fleetlink.shared.dose import Lamp
from fleetlink.shared.geometry import components
from fleetlink.shared.messages import ActionType, Goal, Lease, Order, OrderEdge, OrderNode, OrderProgress, Trajectory
from fleetlink.shared.se2 import compose, inverse
from tests.harness.console_rig import Rig
from tests.harness.messages import state
from tests.test_console import run_async, screen_text, settle, with_robots
from tests.test_console_sortie import actions, sent
from tests.test_fleetmap import undo

# -- parsing ------------------------------------------------------------------------------------


def test_disinfect_and_sweep_take_an_area_a_dose_and_robots() -> None:
    assert parse_command("disinfect room 1 2") == StartRound("uv", RoomArea(1.0, 2.0))
    assert parse_command("Disinfect rect 0 0 2 1.5 dose 5 with r1,r2") == StartRound(
        "uv", RectArea(0.0, 0.0, 2.0, 1.5), 5.0, ("r1", "r2")
    )
    assert parse_command("disinfect polygon 0 0 1 0 1 1 with r1, r2 dose 2.5") == StartRound(
        "uv", PolyArea(((0.0, 0.0), (1.0, 0.0), (1.0, 1.0))), 2.5, ("r1", "r2")
    )
    assert parse_command("sweep rect 0 0 3 3 with r2") == StartRound(
        "sweep", RectArea(0.0, 0.0, 3.0, 3.0), None, ("r2",)
    )
    assert [parse_command(w) for w in ("pause", "resume", "CANCEL")] == [
        RoundAction("pause"),
        RoundAction("resume"),
        RoundAction("cancel"),
    ]


@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("disinfect room 1 2 dose 0", "the dose must be a finite number > 0 mJ/cm²"),
        ("disinfect room 1 2 dose nan", "the dose must be a finite number > 0 mJ/cm²"),
        ("disinfect room 1 2 dose -3", "the dose must be a finite number > 0 mJ/cm²"),
        ("disinfect room 1 2 dose inf", "the dose must be a finite number > 0 mJ/cm²"),
        ("disinfect room 1 2 dose lots", "the dose must be a finite number > 0 mJ/cm²"),
        ("disinfect room 1", "room takes 2 numbers"),
        ("disinfect rect 0 0 1", "rect takes 4 numbers"),
        ("disinfect poly 0 0 1 0", "poly takes 6 to 64"),
        ("disinfect poly 0 0 1 0 1 1 2", "poly takes 6 to 64"),
        ("disinfect room x 2", "could not convert string to float: 'x'"),
        ("disinfect room nan 2", "coordinates must be finite numbers"),
        ("disinfect hall 1 2", "disinfect room X Y | rect"),
        ("disinfect", "disinfect room X Y | rect"),
        ("disinfect room 1 2 with", "disinfect room X Y | rect"),
        ("disinfect room 1 2 with r1,r1", "a robot is named twice"),
        ("disinfect room 1 2 with r/1", "'r/1' is not a robot id"),
        ("disinfect room 1 2 dose 5 dose 6", "disinfect room X Y | rect"),
        ("sweep room 1 2 with r1,r2", "a sweep is for one robot"),
        ("sweep room 1 2 dose 5", "a sweep takes no dose"),
    ],
)
def test_a_bad_round_command_says_why(line: str, why: str) -> None:
    err = parse_command(line)
    assert isinstance(err, CommandError) and why in err.text, err


def test_pause_resume_cancel_take_nothing() -> None:
    for line in ("pause now", "resume r1", "cancel all"):
        err = parse_command(line)
        assert isinstance(err, CommandError) and err.text.startswith("unknown command")


# -- the detail ---------------------------------------------------------------------------------


def test_the_detail_shows_the_rounds_progress() -> None:
    fleet = FleetModel("operator-1")
    r1 = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")
    progress = OrderProgress(
        nodesTotal=31, nodesDone=5, skipped=2, lastNodeId="n4", lastNodeSequenceId=8, dwellLeft_s=75.0, waiting=""
    )
    fleet.apply(state(r1, orderId="uv-r1-9", progress=progress), "zenoh", 1.0)
    text = detail_text("r1", fleet.robots["r1"], ())
    assert "round uv-r1-9: 5/31 nodes done, 2 skipped, dwell 1 min 15 s left" in text and "WAITING" not in text
    waiting = OrderProgress(
        nodesTotal=31, nodesDone=5, skipped=0, lastNodeId="n4", lastNodeSequenceId=8, dwellLeft_s=0.0, waiting="e-stop"
    )
    fleet.apply(state(r1, orderId="uv-r1-9", progress=waiting), "zenoh", 2.0)
    assert "round uv-r1-9: 5/31 nodes done  WAITING: e-stop" in detail_text("r1", fleet.robots["r1"], ())
    fleet.apply(state(r1, orderId="uv-r1-9"), "zenoh", 3.0)  # the round is over
    assert "round" not in detail_text("r1", fleet.robots["r1"], ())


def test_a_round_between_two_nodes_is_not_said_to_be_finished() -> None:
    fleet = FleetModel("operator-1")
    r1 = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")
    running = OrderProgress(
        nodesTotal=4, nodesDone=1, skipped=0, lastNodeId="n0", lastNodeSequenceId=0, dwellLeft_s=0.0, waiting=""
    )
    to_n1 = Goal(x=1.0, y=0.0, theta=None)
    fleet.apply(state(r1, orderId="uv-r1-9", goal=to_n1, progress=running), "zenoh", 1.0)
    fleet.apply(state(r1, orderId="uv-r1-9", goal=None, progress=running), "zenoh", 2.0)  # dwelling at n1
    assert not [n for n in fleet.drain() if "finished" in n.text]
    fleet.apply(state(r1, orderId="g-1", goal=to_n1), "zenoh", 3.0)
    fleet.apply(state(r1, orderId="g-1", goal=None), "zenoh", 4.0)  # a goal's end is said
    assert [n.text for n in fleet.drain() if "finished" in n.text] == ["r1: order g-1 finished"]


# -- the console --------------------------------------------------------------------------------


def node_at(i: int, x: float, y: float, theta: float | None) -> OrderNode:
    return OrderNode(nodeId=f"n{i}", sequenceId=2 * i, released=True, x=x, y=y, theta=theta)


RES = 0.1
ORIGIN = (-1.0, -1.0)


def room_grid() -> tuple[float, float, float, int, int, bytes]:
    """A 3 x 2.4 m room, walls all round, from (-1, -1): the robots stand at (0, 0) and (1, 0)."""
    cells = np.zeros((26, 32), dtype=np.uint8)
    cells[0, :] = cells[-1, :] = 100
    cells[:, 0] = cells[:, -1] = 100
    return (ORIGIN[0], ORIGIN[1], RES, 32, 26, cells.tobytes())


def detail(rig: Rig) -> str:
    return rig.app.query_one(RobotDetail)._text or ""


def notices(rig: Rig) -> str:
    """The notices as shown (long ones wrap over several lines: joined again)."""
    return "".join(line.text for line in rig.app.query_one("#notices", RichLog).lines)


def map_styles(rig: Rig) -> set[Any]:
    """The styles of every glyph the map draws."""
    frame = rig.app.query_one(MapView).frame
    return frame.styles() if frame is not None else set()


def orders(rig: Rig) -> list[Order]:
    seen: dict[tuple[str, int], Order] = {}
    for m in [*rig.zenoh.messages(Order), *rig.mqtt.messages(Order)]:
        seen.setdefault((m.header.robot, m.header.headerId), m)
    return sorted(seen.values(), key=lambda m: m.header.timestamp)


async def until(pilot: Any, what: Any, timeout: float = 10.0) -> Any:
    """Wait (the app keeps running) until ``what()`` is truthy; its value."""
    for _ in range(int(timeout / 0.05)):
        if got := what():
            return got
        await settle(pilot, 0.05)
    return what()


async def command(pilot: Any, line: str, *, typed: bool = False) -> None:
    """``:line`` entered in the command line (``:``, the text pasted in, Enter), or (faster) handed
    to it as Enter does. (Typed key by key, each key waits for the app to be idle: ~0.3 s a key.)"""
    if typed:
        await pilot.press("colon")
        pilot.app.query_one("#command", Input).value = line
        await pilot.press("enter")
    else:
        pilot.app.run_command(line)
        await pilot.pause()


async def mapped(rig: Rig, pilot: Any, *robots: str) -> None:
    await with_robots(rig, pilot, *robots)
    assert await until(pilot, lambda: len(rig.app.fleet.robots) == len(robots) and rig.app.selected == robots[0])
    with rig.lock:
        for robot in robots:
            rig.fleet.set_grid(robot, room_grid())


@run_async
async def test_disinfect_sends_an_order_with_nodes_and_the_detail_and_map_follow_its_progress(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await mapped(rig, pilot, "r1")
        await command(pilot, "disinfect rect -0.6 -0.6 0.9 0.8 dose 2", typed=True)
        (order,) = await until(pilot, lambda: orders(rig))
        assert order.header.robot == "r1" and order.orderId.startswith("uv-r1-") and order.goal is None
        assert len(order.nodes) >= 2 and (order.nodes[0].x, order.nodes[0].y) == (0.0, 0.0)
        kinds = [a.actionType for n in order.nodes for a in n.actions]
        assert ActionType.DWELL in kinds and ActionType.PAYLOAD in kinds
        said = notices(rig)
        assert "UV round of the rectangle (-0.60, -0.60)-(0.90, 0.80)" in said and "predicted" in said
        assert "at 2 mJ/cm²" in said and f"r1: UV round sent as order {order.orderId}" in said
        # The robot reports the round under way: the detail shows it, the map draws what is left.
        progress = OrderProgress(
            nodesTotal=len(order.nodes), nodesDone=1, skipped=0, lastNodeId="n0", lastNodeSequenceId=0,
            dwellLeft_s=12.0, waiting="",
        )  # fmt: skip
        rig.zenoh.inject(state(rig.counter("r1"), orderId=order.orderId, progress=progress, driveMode="order"))
        line = f"round {order.orderId}: 1/{len(order.nodes)} nodes done, dwell 12 s left"
        assert await until(pilot, lambda: line in detail(rig)), detail(rig)
        assert line in screen_text(rig.app)
        frame = rig.app.query_one(MapView).frame
        assert frame is not None
        drawn = frame.styles()
        assert ROUTE_STYLE in drawn and ROUTE_DONE_STYLE not in drawn
        assert "o" in frame.chars(ROUTE_STYLE)  # dwell points
        # Another robot's order, or the round over: not drawn any more.
        rig.zenoh.inject(state(rig.counter("r1"), orderId=order.orderId, driveMode="idle"))
        assert await until(pilot, lambda: "round uv-" not in detail(rig))
        await settle(pilot, 0.2)
        assert ROUTE_STYLE not in map_styles(rig)


@run_async
async def test_a_click_on_the_map_then_d_or_s_plans_a_round_of_the_room_there(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await mapped(rig, pilot, "r1")
        mv = rig.app.query_one(MapView)
        mv.geometry.center_x, mv.geometry.center_y, mv.geometry.scale = 0.5, 0.2, 0.05
        w, h = mv.content_size.width, mv.content_size.height
        col, row = w // 2, h // 2  # (0.5, 0.2) within a cell: inside the room
        await pilot.click("#map", offset=(col + 1, row + 1))  # +1: the map's border
        await pilot.pause()
        await pilot.press("d")
        (order,) = await until(pilot, lambda: orders(rig))
        assert order.orderId.startswith("uv-r1-")
        assert ActionType.PAYLOAD in {a.actionType for n in order.nodes for a in n.actions}
        assert "UV round of the room at (0.5" in notices(rig)
        rig.zenoh.inject(state(rig.counter("r1"), orderId=order.orderId, driveMode="idle"))  # done
        await pilot.click("#map", offset=(col + 1, row + 1))
        await pilot.pause()
        await pilot.press("s")
        assert await until(pilot, lambda: len(orders(rig)) == 2)
        sweep = orders(rig)[1]
        assert sweep.orderId.startswith("sweep-r1-")
        assert ActionType.PAYLOAD not in {a.actionType for n in sweep.nodes for a in n.actions}
        assert "sweep of the room at (0.5" in notices(rig)


@run_async
async def test_pause_resume_and_cancel_go_to_the_selected_robot_and_p_toggles(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await mapped(rig, pilot, "r1")
        await command(pilot, "pause", typed=True)
        for line in ("resume", "cancel"):
            await command(pilot, line)
        for kind in (ActionType.PAUSE, ActionType.RESUME, ActionType.CANCEL):
            assert [m.header.robot for m in await sent(pilot, rig, kind, 1)] == ["r1"]
        await pilot.press("P")  # not paused: P pauses
        assert len(await sent(pilot, rig, ActionType.PAUSE, 2)) == 2
        paused = OrderProgress(
            nodesTotal=5, nodesDone=2, skipped=0, lastNodeId="n1", lastNodeSequenceId=2, dwellLeft_s=3.0,
            waiting="paused",
        )  # fmt: skip
        rig.zenoh.inject(state(rig.counter("r1"), orderId="uv-r1-1", progress=paused, paused=True))
        assert await until(pilot, lambda: "WAITING: paused" in detail(rig))
        await pilot.press("P")  # paused: P resumes
        assert len(await sent(pilot, rig, ActionType.RESUME, 2)) == 2
        assert len(actions(rig, ActionType.PAUSE)) == 2


@run_async
async def test_two_robots_share_a_round_each_with_its_own_order(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await mapped(rig, pilot, "r1", "r2")
        await command(pilot, "disinfect rect -0.6 -0.6 1.7 1.1 dose 2 with r1,r2")
        got = await until(pilot, lambda: len(orders(rig)) == 2 and orders(rig))
        assert got, notices(rig)
        assert sorted(o.header.robot for o in got) == ["r1", "r2"]
        assert all(o.orderId.startswith(f"uv-{o.header.robot}-") for o in got)
        starts = {o.header.robot: (o.nodes[0].x, o.nodes[0].y) for o in got}
        assert starts == {"r1": (0.0, 0.0), "r2": (1.0, 0.0)}


BAD = [
    ("disinfect poly -0.5 -0.5 0.5 0.5 0.5 -0.5 -0.5 0.5", "self-intersecting, edges 0 and 2 cross"),
    ("disinfect poly -0.5 -0.5 9 -0.5 0 0.5", "vertex 1 (9, -0.5) lies outside the map"),
    ("disinfect room 0 0 dose 0", "the dose must be a finite number > 0"),
    ("disinfect room 0 0 dose nan", "the dose must be a finite number > 0"),
    ("disinfect room 0 0 with r1,r9", "unknown robot 'r9' (known: r1)"),
    ("sweep room 0 0 with r1,r9", "a sweep is for one robot"),
]


@run_async
async def test_bad_input_is_a_warning_and_nothing_is_sent(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await mapped(rig, pilot, "r1")
        for line, why in BAD:
            await command(pilot, line)
            assert await until(pilot, lambda why=why: why in notices(rig)), (line, notices(rig))
            assert rig.app.planning is None and orders(rig) == [], line
        assert notices(rig).count("warning") == len(BAD)
        # Nothing else disturbed: the next round goes out.
        await command(pilot, "disinfect rect -0.6 -0.6 0.9 0.8 dose 2")
        assert await until(pilot, lambda: orders(rig)), notices(rig)


@run_async
async def test_a_robot_without_a_pose_or_a_map_or_whose_lease_is_anothers_gets_no_round(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robots(rig, pilot, "r1")
        assert await until(pilot, lambda: rig.app.selected == "r1")
        await command(pilot, "disinfect room 0 0")  # no map from r1 yet
        assert await until(pilot, lambda: "no map from the round's robots" in notices(rig))
        rig.zenoh.inject(state(rig.counter("r2")))  # r2 says only a State: it has a pose from it
        rig.voices.pop("r1")
        with rig.lock:
            rig.fleet.robots["r1"].pose = None
        await command(pilot, "disinfect room 0 0")
        assert await until(pilot, lambda: "r1: no fused pose yet" in notices(rig))
        rig.zenoh.inject(rig.counter("r1").make(Lease, holder="op-other", until=1e12))
        await until(pilot, lambda: rig.fleet.robots["r1"].lease_holder == "op-other")
        await command(pilot, "sweep room 0 0")
        assert await until(pilot, lambda: "r1: control lease held by op-other" in notices(rig))
        assert orders(rig) == []


def test_a_grid_through_a_frame_keeps_its_walls_whole_and_where_they_were() -> None:
    frame = (2.0, -1.0, math.radians(37.0))
    ox, oy, res, w, h, data = grid_through(room_grid(), frame)
    cells = np.frombuffer(data, dtype=np.uint8).reshape(h, w)
    assert (ox - 0.0) / res == pytest.approx(round(ox / res))  # on the lattice the room was on
    walls = cells == 100
    assert len(components(walls)) == 1  # the four walls, unbroken at 37 degrees
    rows, cols = np.nonzero(walls)
    back = undo(frame, np.column_stack((ox + (cols + 0.5) * res, oy + (rows + 0.5) * res)))
    x0, y0 = ORIGIN[0] + RES / 2, ORIGIN[1] + RES / 2  # the room's wall cells' centres
    x1, y1 = x0 + 31 * RES, y0 + 25 * RES
    to_wall = np.minimum(
        np.minimum(abs(back[:, 0] - x0), abs(back[:, 0] - x1)), np.minimum(abs(back[:, 1] - y0), abs(back[:, 1] - y1))
    )
    assert float(to_wall.max()) <= res  # every wall cell lies on the room's walls, to a cell
    assert np.count_nonzero(cells == 0) == pytest.approx(30 * 24, rel=0.05)  # the floor, as much of it


async def with_robot_in_its_own_frame(rig: Rig, pilot: Any, frame: tuple[float, float, float]) -> None:
    """r1 without UWB, reporting in its own frame, which lies at ``frame`` on the fleet map; it stands
    at (0, 0) of the fleet map, and its map is the room's, in its own frame."""
    own = compose(inverse(frame), (0.0, 0.0, 0.0))
    rig.unplaced.add("r1")
    await with_robots(rig, pilot, "r1")
    rig.voices["r1"] = (own[0], own[1])
    assert await until(pilot, lambda: rig.fleet.robots.get("r1") is not None and rig.fleet.robots["r1"].in_own_frame)
    with rig.lock:
        rig.fleet.set_grid("r1", grid_through(room_grid(), inverse(frame)))


@run_async
async def test_a_robot_in_its_own_frame_sweeps_a_room_drawn_on_the_fleet_map(rig: Rig) -> None:
    """A robot without UWB maps and reports in its own frame; the fleet map found that frame. A
    sweep of a room drawn on the fleet map is planned there, on its map put through the frame, and
    sent in its own frame. Until the fleet map has found it, and for a UV round (no site position,
    no dose on the floor), nothing is sent and the console says why."""
    frame = (2.0, -1.0, 0.7)  # where r1's own frame lies on the fleet map
    own = compose(inverse(frame), (0.0, 0.0, 0.0))  # it stands at (0, 0) of the fleet map
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robot_in_its_own_frame(rig, pilot, frame)
        with rig.lock:
            rig.fleet.set_frames({}, ["r1"])
        await command(pilot, "sweep rect -0.6 -0.6 1.7 1.1 with r1")
        assert await until(pilot, lambda: "r1 maps in its own frame and is not on the fleet map yet" in notices(rig))
        with rig.lock:
            rig.fleet.set_frames({"r1": frame})
        assert await until(pilot, lambda: math.hypot(*rig.fleet.robots["r1"].pose[:2]) < 1e-6)  # type: ignore[index]
        await command(pilot, "disinfect rect -0.6 -0.6 1.7 1.1 with r1")
        assert await until(pilot, lambda: "r1 has no site position (no UWB)" in notices(rig))
        await command(pilot, "sweep rect -0.6 -0.6 1.7 1.1 with r1")
        got = await until(pilot, lambda: orders(rig))
        assert got, notices(rig)
        (order,) = got
        nodes = np.array([(n.x, n.y) for n in order.nodes])
        assert nodes[0] == pytest.approx(own[:2], abs=1e-6)  # where it stands, as it reports it
        on_map = undo(inverse(frame), nodes)  # its own frame's nodes where the fleet map has them
        assert len(nodes) > 4 and on_map[1:].min(axis=0).tolist() >= [-0.75, -0.75]
        assert on_map[1:].max(axis=0).tolist() <= [1.85, 1.25]  # in the rectangle, lanes 0.15 m in
        way = undo(
            inverse(frame),
            np.array([(p.x, p.y) for e in order.edges if e.trajectory for p in e.trajectory.controlPoints]),
        )
        assert len(way) and way.min(axis=0).tolist() >= [-0.9, -0.9] and way.max(axis=0).tolist() <= [2.1, 1.5]
        with rig.lock:  # the round is drawn where it was planned: on the fleet map
            route = rig.fleet.routes["r1"]
        assert route[0] == order.orderId and (route[1][1][0], route[1][1][1]) == pytest.approx(
            tuple(on_map[1]), abs=1e-6
        )


@run_async
async def test_a_round_whose_robot_s_frame_moved_while_it_was_planned_is_not_sent(rig: Rig) -> None:
    frame = (2.0, -1.0, 0.7)
    planner = rig.app.planner
    assert planner is not None

    def moving(*args: Any) -> Any:  # the fleet map moves r1's frame while the round is planned
        with rig.lock:
            rig.fleet.set_frames({"r1": (2.5, -1.0, 0.7)})
        return planner(*args)

    async with rig.app.run_test(size=(140, 44)) as pilot:
        await with_robot_in_its_own_frame(rig, pilot, frame)
        with rig.lock:
            rig.fleet.set_frames({"r1": frame})
        rig.app.planner = moving
        await command(pilot, "sweep rect -0.6 -0.6 1.7 1.1 with r1")
        said = "sweep not sent: r1's frame on the fleet map moved 0.50 m while it was planned"
        assert await until(pilot, lambda: said in notices(rig)), notices(rig)
        await settle(pilot, 0.3)
        assert orders(rig) == []


def test_an_order_through_a_frame_moves_its_nodes_headings_and_trajectories() -> None:
    frame = (1.0, 2.0, 0.7)
    nodes = (node_at(0, 3.0, 2.0, None), node_at(1, 1.0, 4.0, 0.5))
    way = Trajectory.polyline(((3.0, 2.0), (2.0, 3.0), (1.0, 4.0)))
    e = OrderEdge(edgeId="e0", sequenceId=1, startNodeId="n0", endNodeId="n1", released=True, trajectory=way)
    fields = {
        "orderId": "sweep-r1-1",
        "orderUpdateId": 0,
        "goal": None,
        "returnHome": False,
        "nodes": nodes,
        "edges": (e,),
    }
    sent = FleetModel.order_through(frame, fields)
    assert FleetModel.order_through(None, fields) is fields  # in the site frame: as planned
    for planned, got in zip(nodes, sent["nodes"], strict=True):
        back = compose(frame, (got.x, got.y, got.theta or 0.0))
        assert back[:2] == pytest.approx((planned.x, planned.y), abs=1e-9)
        assert (got.theta is None) == (planned.theta is None)
    assert sent["nodes"][1].theta == pytest.approx(0.5 - 0.7)
    points = [(p.x, p.y) for p in sent["edges"][0].trajectory.controlPoints]
    assert undo(inverse(frame), np.array(points)) == pytest.approx(np.array([(3.0, 2.0), (2.0, 3.0), (1.0, 4.0)]))
    assert sent["edges"][0].trajectory.knotVector == way.knotVector


@run_async
async def test_people_present_zones_are_drawn_on_the_map(rig: Rig) -> None:
    async with rig.app.run_test(size=(140, 44)) as pilot:
        await mapped(rig, pilot, "r1")
        legend = screen_text(rig.app).count("░")  # the legend's
        await command(pilot, "zone add ward -0.9 0.3 0.5 0.3 0.5 1.3 -0.9 1.3")
        assert await until(pilot, lambda: ZONE_STYLE in map_styles(rig))
        assert screen_text(rig.app).count("░") > legend
        await command(pilot, "zone rm ward")
        await until(pilot, lambda: ZONE_STYLE not in map_styles(rig))
        assert screen_text(rig.app).count("░") == legend


def test_the_order_ids_and_the_default_lamp_match_the_agents() -> None:
    from fleetlink.agent.config import UvTable
    from fleetlink.cli.console import ConsoleUvTable

    console = ConsoleUvTable()
    agent = UvTable(uvc_power_w=console.uvc_power_w, height_m=console.height_m)
    assert console.lamp() == DEFAULT_LAMP == agent.lamp
    assert console.target_dose_mj_cm2 == agent.target_dose_mj_cm2
    assert math.isclose(agent.target_j_m2, 100.0)


def test_console_toml_sets_the_lamp_and_target_rounds_are_planned_for(tmp_path: Path) -> None:
    from fleetlink.cli.console import round_options
    from fleetlink.site.rounds import plan_round
    from tests.test_config_files import console_args

    path = tmp_path / "console.toml"
    path.write_text("[uv]\nuvc_power_w = 20.0\nheight_m = 1.0\ntarget_dose_mj_cm2 = 5\n")
    options = round_options(load_settings(console_args("--config", str(path))))
    assert options["planner"] is plan_round and options["target_j_m2"] == 50.0
    assert options["lamp"] == Lamp(uvc_power_w=20.0, height_m=1.0)
    assert round_options(load_settings(console_args()))["lamp"] == DEFAULT_LAMP  # no [uv]: the agent's defaults
    path.write_text("[uv]\nheight_m = 0.2\n")  # nearer the floor than the model holds
    with pytest.raises(ConfigError, match=r"console\.toml: uv\.height_m: the lamp is 0\.2 m above the floor"):
        load_settings(console_args("--config", str(path)))


def test_a_rounds_default_target_is_the_one_its_robots_advertise(rig: Rig) -> None:
    from fleetlink.shared.dose_codec import SharedDose

    # r1's dose layer carries its [uv] target (50 J/m² = 5 mJ/cm²); r2 has none: the console's.
    rig.app.doses.layers["r1"] = SharedDose(np.zeros((2, 2), dtype=np.float32), 0.1, (0.0, 0.0), 1, 50.0, 0.0, 0.0)
    assert rig.app.target_for(("r1",)) == 50.0
    assert rig.app.target_for(("r2",)) == rig.app.target_j_m2 == 100.0
    assert rig.app.target_for(("r1", "r2")) == 100.0  # the strictest


def hidden_grid() -> tuple[float, float, float, int, int, bytes]:
    """``room_grid`` with a cabinet (x 0.4..0.6, y -0.6..0.4) whose far side (x 0.6..1.4, y -0.6..0.4)
    the robot at (0, 0) has not seen: unknown on its map."""
    cells = np.frombuffer(room_grid()[5], dtype=np.uint8).reshape(26, 32).copy()
    cells[4:14, 14:16] = 100
    cells[4:14, 16:24] = 255
    return (ORIGIN[0], ORIGIN[1], RES, 32, 26, cells.tobytes())


@run_async
async def test_a_round_over_floor_the_map_has_not_seen_surveys_first_then_plans_on_what_was_seen(rig: Rig) -> None:
    from fleetlink.shared.messages import Event, KeyValue, Severity

    def ended(order_id: str, outcome: str) -> None:
        data = (KeyValue(key="order", value=order_id), KeyValue(key="outcome", value=outcome))
        text = f"order {order_id} {outcome}"
        rig.zenoh.inject(rig.counter("r1").make(Event, kind="order", text=text, severity=Severity.INFO, data=data))

    async with rig.app.run_test(size=(140, 44)) as pilot:
        await mapped(rig, pilot, "r1")
        with rig.lock:
            rig.fleet.set_grid("r1", hidden_grid())
        await command(pilot, "disinfect rect -0.9 -0.9 1.9 1.3 dose 2")
        (look,) = await until(pilot, lambda: orders(rig))
        assert look.orderId.startswith("uv-r1-") and look.orderId.endswith("-survey")
        # A UV round's survey: the lamp on from the first view (they stand in the area) to the last.
        lamp = [a for n in look.nodes for a in n.actions if a.actionType is ActionType.PAYLOAD]
        assert [kv.value for a in lamp for kv in a.actionParameters if kv.key == "on"] == ["true", "false"]
        assert lamp[0] in look.nodes[1].actions and lamp[1] in look.nodes[-1].actions
        assert all(n.x > 0.5 for n in look.nodes[1:])  # looking past the cabinet
        said = notices(rig)
        assert "survey before the UV round of the rectangle" in said and "view points" in said
        # The robot looked: its map now has the floor behind the cabinet. The survey's order
        # finishes, and the round is planned on that map and sent, with the lamp this time.
        with rig.lock:
            rig.fleet.set_grid("r1", room_grid())
        ended(look.orderId, "finished")
        assert await until(pilot, lambda: len(orders(rig)) == 2)
        uv = orders(rig)[1]
        assert uv.orderId.startswith("uv-r1-") and not uv.orderId.endswith("-survey")
        assert ActionType.PAYLOAD in {a.actionType for n in uv.nodes for a in n.actions}
        assert "at 2 mJ/cm²" in notices(rig)

        # A survey cancelled (or stopped, or replaced) drops its round: nothing more is sent.
        with rig.lock:
            rig.fleet.set_grid("r1", hidden_grid())
        await command(pilot, "disinfect rect -0.9 -0.9 1.9 1.3 dose 2")
        assert await until(pilot, lambda: len(orders(rig)) == 3)
        again = orders(rig)[2]
        assert again.orderId.endswith("-survey")
        ended(again.orderId, "ended")
        assert await until(pilot, lambda: "survey ended before it finished" in notices(rig))
        await settle(pilot, 0.3)
        assert len(orders(rig)) == 3
