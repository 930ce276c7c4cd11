"""Rounds planned from an operator's request (operator/rounds.py, site/rounds.py) on synthetic maps:
a room from a seed, a rectangle, a polygon, two robots sharing a room, a sweep; every bad input
refused with its reason; the maps merged as the console holds them."""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np
import pytest

from fleetlink.agent.coverage import CoverageConfig
from fleetlink.operator.rounds import (
    DEFAULT_LAMP,
    PolyArea,
    RectArea,
    RoomArea,
    RoundError,
    RoundIds,
    RoundPlan,
    RoundRequest,
    check_request,
    describe_time,
    floor_of,
    robots_off,
)
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.geometry import point_in_polygon
from fleetlink.shared.messages import MAX_ORDER_NODES, ActionType, Order
from fleetlink.site.rounds import plan_round

RES = 0.1
DOOR_Y = (1.8, 2.7)


def two_rooms() -> np.ndarray:
    """8.9 x 4.1 m: a 4.9 x 3.9 m room (x 0.1-5.0) and a 3.8 x 3.9 m room (x 5.1-8.9) joined by a
    0.9 m door in the wall at x 5.0-5.1; a sealed 1 x 1 m closet (walls all round) at x 2-3, y 2.8-3.8
    of the left room has no way in."""
    cells = np.zeros((42, 90), dtype=np.int8)
    cells[0, :] = cells[-1, :] = 100
    cells[:, 0] = cells[:, -1] = 100
    cells[:, 50] = 100
    cells[18:27, 50] = 0  # the door
    cells[28, 20:31] = cells[38, 20:31] = 100  # the closet
    cells[28:39, 20] = cells[28:39, 30] = 100
    return cells


CELLS = two_rooms()
A, B = (1.0, 1.0), (4.0, 1.0)


def plan(kind: str, area: Any, robots: dict[str, tuple[float, float]], **kw: Any) -> RoundPlan:
    request = RoundRequest(kind, area, tuple(robots), kw.pop("target_j_m2", 100.0))  # type: ignore[arg-type]
    return plan_round(request, CELLS, RES, (0.0, 0.0), robots, DEFAULT_LAMP, **kw)


def as_order(fields: Any) -> Order:
    """The fields as an Order on the wire (what the console sends), decoded again."""
    counter = wire.HeaderCounter(SimClock(), robot="r1", sender="operator-1")
    msg = counter.make(Order, **fields)
    decoded = wire.decode(Order, wire.encode(msg))
    assert isinstance(decoded, Order)
    return decoded


def action_types(order: Order) -> list[str]:
    return [a.actionType.value for n in order.nodes for a in n.actions]


def test_a_uv_round_of_a_room_from_a_seed_dwells_only_in_that_room_and_reaches_the_dose() -> None:
    p = plan("uv", RoomArea(2.5, 1.0), {"r1": A}, order_ids={"r1": "uv-r1-7"})
    assert len(p.rounds) == 1
    r = p.rounds[0]
    assert r.robot == "r1" and r.order_id == "uv-r1-7" and p.coverage >= 0.99
    # The left room less the closet, its walls and what the lamp cannot reach: about 18 m².
    assert 15.0 < p.area_m2 < 19.2
    order = as_order(r.order)
    assert order.orderId == "uv-r1-7" and order.goal is None and not order.returnHome
    assert len(order.nodes) == len(r.route) and len(order.edges) == len(order.nodes) - 1
    assert (order.nodes[0].x, order.nodes[0].y) == A and order.nodes[0].actions == ()  # it starts where it stands
    dwell = [n for n in r.route if n.dwell_s > 0]
    assert dwell and all(0.1 < n.x < 5.0 for n in dwell)  # never through the door
    kinds = action_types(order)
    assert kinds.count("dwell") == len(dwell) and kinds[0] == "payload" and kinds[-1] == "payload"
    last = order.nodes[-1].actions[-1]
    assert last.actionType is ActionType.PAYLOAD and {(k.key, k.value) for k in last.actionParameters} >= {
        ("on", "false")
    }  # the lamp off at the end
    assert p.total_s == pytest.approx(r.total_s) and r.total_s > r.dwell_s > 0
    text = p.summary()
    assert "UV round of the room at (2.50, 1.00)" in text and "predicted" in text and "10 mJ/cm²" in text


def test_a_rectangle_and_a_polygon_keep_their_dwell_points_inside() -> None:
    rect = plan("uv", RectArea(0.5, 0.5, 3.0, 2.0), {"r1": A}, target_j_m2=20.0)
    assert rect.coverage >= 0.99 and 3.0 < rect.area_m2 <= 2.5 * 1.5 + 0.01
    assert all(0.5 <= n.x <= 3.0 and 0.5 <= n.y <= 2.0 for n in rect.rounds[0].route[1:])
    tri = [(0.5, 0.5), (4.5, 0.5), (2.5, 2.5)]
    poly = plan("uv", PolyArea(tuple(tri)), {"r1": A}, target_j_m2=20.0)
    assert poly.coverage >= 0.99 and 2.0 < poly.area_m2 < 4.0
    assert all(point_in_polygon(n.x, n.y, tri) for n in poly.rounds[0].route[1:])


def test_two_robots_share_a_room_each_from_where_it_stands_and_finish_sooner() -> None:
    area = RectArea(0.5, 0.5, 4.5, 2.5)
    one = plan("uv", area, {"r1": A}, target_j_m2=20.0)
    two = plan("uv", area, {"r1": A, "r2": B}, target_j_m2=20.0)
    assert [r.robot for r in two.rounds] == ["r1", "r2"]
    assert [r.order_id for r in two.rounds] == ["uv-r1-1", "uv-r2-1"]
    assert [(r.route[0].x, r.route[0].y) for r in two.rounds] == [A, B]
    assert all(r.dwell_points > 0 for r in two.rounds)
    # The dwell times are shared, not changed: together the same dose.
    assert sum(r.dwell_s for r in two.rounds) == pytest.approx(one.rounds[0].dwell_s, rel=1e-6)
    assert two.coverage >= 0.99 and two.total_s < 0.8 * one.total_s
    for r in two.rounds:
        as_order(r.order)


def test_a_sweep_drives_lanes_without_the_lamp() -> None:
    p = plan("sweep", RoomArea(7.0, 2.0), {"r1": A}, order_ids={"r1": "sweep-r1-3"})
    r = p.rounds[0]
    # Lanes stop 0.3 m short of the walls they run into (the guard's stopping room): ~0.85 predicted.
    assert r.order_id == "sweep-r1-3" and p.coverage >= 0.8 and r.dwell_s == 0.0
    order = as_order(r.order)
    assert action_types(order) == [] and len(order.nodes) > 10
    assert all(n.x > 5.0 for n in r.route[2:])  # the lanes are in the right room (it got there by the door)
    assert "sweep of the room at (7.00, 2.00)" in p.summary() and "swept" in p.summary()


@pytest.mark.parametrize(
    ("kind", "area", "robots", "target", "why"),
    [
        ("uv", PolyArea(((0.5, 0.5), (3.0, 2.0), (3.0, 0.5), (0.5, 2.0))), {"r1": A}, 100.0, "self-intersecting"),
        ("uv", PolyArea(((0.5, 0.5), (12.0, 0.5), (3.0, 2.0))), {"r1": A}, 100.0, "outside the map"),
        ("uv", RectArea(0.5, 0.5, 12.0, 2.0), {"r1": A}, 100.0, "outside the map"),
        ("uv", RoomArea(0.5, 0.5), {"r1": A}, 0.0, "target dose must be a finite number > 0"),
        ("uv", RoomArea(0.5, 0.5), {"r1": A}, math.nan, "target dose must be a finite number > 0"),
        ("uv", RoomArea(0.5, 0.5), {"r1": A}, -10.0, "target dose must be a finite number > 0"),
        ("uv", RoomArea(0.5, 0.5), {"r1": A}, math.inf, "target dose must be a finite number > 0"),
        ("uv", RectArea(2.15, 2.95, 2.85, 3.65), {"r1": A}, 100.0, "cannot get there"),  # the sealed closet
        ("uv", RectArea(4.85, 0.5, 5.25, 1.5), {"r1": A}, 100.0, "1.50): the robot can stand nowhere"),  # a wall
        ("uv", RoomArea(5.05, 1.0), {"r1": A}, 100.0, "lies in a wall"),
        ("uv", RoomArea(0.5, 0.5), {"r1": (20.0, 1.0)}, 100.0, "r1 stands at (20.00, 1.00)"),
        ("uv", RoomArea(0.5, 0.5), {"r1": (20.0, 1.0), "r2": (2.5, 3.3)}, 100.0, "r1 stands at (20.00, 1.00)"),
        ("sweep", RoomArea(0.5, 0.5), {"r1": A, "r2": B}, 100.0, "a sweep is for one robot"),
        ("uv", RoomArea(0.5, 0.5), {"r1": A, "bad id!": B}, 100.0, "is not a robot id"),
        ("uv", PolyArea(((0.5, 0.5), (1.0, 0.5))), {"r1": A}, 100.0, "3 to 32 corners"),
        ("uv", RoomArea(math.nan, 0.5), {"r1": A}, 100.0, "finite numbers"),
    ],
)
def test_bad_input_is_refused_with_its_reason(kind: str, area: Any, robots: Any, target: float, why: str) -> None:
    with pytest.raises(RoundError, match=re.escape(why)):
        plan(kind, area, robots, target_j_m2=target)


def test_an_area_with_nowhere_to_stand_says_how_much_of_it_the_map_holds_as_floor() -> None:
    # Along a wall (x 5.0-5.1 of it is wall): some floor, too narrow to stand on.
    with pytest.raises(RoundError, match=r"stand nowhere inside it .*: 0\.30 of its 0\.40 m² is floor on the map"):
        plan("uv", RectArea(4.85, 0.5, 5.25, 1.5), {"r1": A})
    # Mostly unmapped: the map knows only its bottom 0.2 m as floor (the operator's cue that the area
    # was not mapped, not that it is too small; none known at all is "contains no floor").
    unmapped = CELLS.copy()
    unmapped[7:16, 9:22] = -1  # y 0.7-1.6 never seen
    request = RoundRequest("uv", RectArea(1.0, 0.5, 2.0, 1.5), ("r1",), 100.0)
    with pytest.raises(RoundError, match=r"stand nowhere inside it .*: 0\.20 of its 1\.00 m² is floor on the map"):
        plan_round(request, unmapped, RES, (0.0, 0.0), {"r1": (4.0, 1.0)}, DEFAULT_LAMP)


def test_a_robot_that_cannot_take_part_is_left_out_and_the_others_share_the_round() -> None:
    # r1 stands off the map (as a robot backed into a corner by a bump may stand where no round
    # starts), r2 in the sealed closet: r3 does the room alone, and the plan says why the others
    # are not in it (the console shows each as a warning).
    p = plan("uv", RoomArea(2.5, 1.0), {"r1": (20.0, 1.0), "r2": (2.5, 3.3), "r3": A})
    assert [r.robot for r in p.rounds] == ["r3"] and p.coverage >= 0.99
    assert [robot for robot, _ in p.left_out] == ["r1", "r2"]
    assert "r1 stands at (20.00, 1.00)" in p.left_out[0][1] and "r2 cannot get there" in p.left_out[1][1]
    both = plan("uv", RoomArea(2.5, 1.0), {"r1": A, "r3": B})
    assert {r.robot for r in both.rounds} == {"r1", "r3"} and both.left_out == ()


def test_a_robot_without_a_known_position_is_refused() -> None:
    request = RoundRequest("uv", RoomArea(2.5, 1.0), ("r1", "r2"))
    with pytest.raises(RoundError, match="r2: no known position"):
        plan_round(request, CELLS, RES, (0.0, 0.0), {"r1": A}, DEFAULT_LAMP)
    with pytest.raises(RoundError, match="a round needs a robot"):
        check_request(RoundRequest("uv", RoomArea(2.5, 1.0), ()))


def test_a_route_longer_than_one_order_is_refused_before_anything_is_sent() -> None:
    narrow = CoverageConfig(tool_width_m=0.02)  # lanes every 2 cm: far more lane ends than one order carries
    with pytest.raises(RoundError, match=f"one order carries {MAX_ORDER_NODES}"):
        plan("sweep", RectArea(0.1, 0.1, 8.9, 4.0), {"r1": A}, config=narrow)


def grid(ox: float, oy: float, cells: np.ndarray) -> tuple[float, float, float, int, int, bytes]:
    h, w = cells.shape
    return (ox, oy, RES, w, h, cells.astype(np.uint8).tobytes())


def test_maps_are_merged_as_the_console_draws_them() -> None:
    a = np.full((3, 4), 255, dtype=np.uint8)
    a[0, :] = 0
    a[1, 1] = 100
    b = np.zeros((2, 2), dtype=np.uint8)
    b[1, 1] = 100
    cells, res, origin = floor_of([grid(0.0, 0.0, a), grid(0.2, 0.1, b)])
    assert res == RES and origin == (0.0, 0.0) and cells.shape == (3, 4) and cells.dtype == np.int8
    assert cells[0].tolist() == [0, 0, 0, 0]
    assert cells[1].tolist() == [-1, 100, 0, 0]  # b's free cells fill a's unknown ones
    assert cells[2].tolist() == [-1, -1, 0, 100]  # occupied wins
    # Another lattice (half a cell off): the first map alone.
    cells2, _, origin2 = floor_of([grid(0.0, 0.0, a), grid(0.25, 0.0, b)])
    assert origin2 == (0.0, 0.0) and cells2.shape == (3, 4) and cells2[2].tolist() == [-1, -1, -1, -1]
    with pytest.raises(RoundError, match="no map"):
        floor_of([])


def room_map(res: float = 0.05) -> np.ndarray:
    """A 3 x 2 m room at 5 cm (drawable cells: 0 free, 100 wall), walls one cell thick."""
    cells = np.zeros((40, 60), dtype=np.uint8)
    cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = 100
    return cells


def at(res: float, x: float, y: float) -> tuple[int, int]:
    return int(y / res), int(x / res)


def test_another_robots_body_on_a_map_is_taken_off_where_that_robot_drove() -> None:
    """r2's map holds an arc where r1 drove past it (r1 never sees itself); r1's own map has the
    floor there. Merged with r1's trail, the arc is floor; the walls and a chair leg r1 saw stay."""
    res = 0.05
    mine = room_map()  # r1's own map: the room, a chair leg at (2.5, 1.2) it drove past
    mine[at(res, 2.5, 1.2)] = 100
    theirs = room_map()  # r2's: the same, and r1's body as r2 saw it at (1.0, 1.0)
    theirs[at(res, 2.5, 1.2)] = 100
    for a in np.linspace(-0.8, 0.8, 7):
        theirs[at(res, 1.0 + 0.17 * math.cos(math.pi + a), 1.0 + 0.17 * math.sin(math.pi + a))] = 100
    arc = int(np.count_nonzero(theirs == 100) - np.count_nonzero(mine == 100))
    assert arc >= 4
    trail = [(0.4 + 0.05 * k, 1.0) for k in range(50)]  # r1 drove along y = 1 from x = 0.4 to 2.85
    g_mine = (0.0, 0.0, res, 60, 40, mine.tobytes())
    g_theirs = (0.0, 0.0, res, 60, 40, theirs.tobytes())
    # r2's map knows as much as r1's: in charge on a tie if first.
    cells, _, _ = floor_of([g_theirs, g_mine], [(), trail])
    assert cells[at(res, 0.83, 1.0)] == 0 and np.count_nonzero(cells == 100) == np.count_nonzero(mine == 100)
    assert cells[at(res, 2.5, 1.2)] == 100  # r1 saw the chair leg itself: not its body
    # ... also where r1's map has the leg a cell over (two maps agree on a wall to a cell or so).
    shifted = mine.copy()
    shifted[at(res, 2.5, 1.2)] = 0
    shifted[at(res, 2.55, 1.2)] = 100
    cells, _, _ = floor_of([g_theirs, (0.0, 0.0, res, 60, 40, shifted.tobytes())], [(), trail])
    assert cells[at(res, 2.5, 1.2)] == 100
    assert cells[0, 30] == 100 and cells[20, 0] == 100  # walls r1 drove beside are joined to more
    # Without the trail (or with r2's, who stood elsewhere) the arc stays.
    cells, _, _ = floor_of([g_theirs, g_mine])
    assert np.count_nonzero(cells == 100) == np.count_nonzero(theirs == 100)
    cells, _, _ = floor_of([g_theirs, g_mine], [[(2.0, 0.5)], ()])
    assert np.count_nonzero(cells == 100) == np.count_nonzero(theirs == 100)
    # Beyond a body's reach of the trail: not r1.
    far = [(x, y - 0.4) for x, y in trail]
    cells, _, _ = floor_of([g_theirs, g_mine], [(), far])
    assert np.count_nonzero(cells == 100) == np.count_nonzero(theirs == 100)
    # The count of freed cells, and nothing freed on the map of the robot itself.
    merged = np.where(theirs == 100, 100, 0).astype(np.int8)
    assert robots_off(merged, res, (0.0, 0.0), g_mine, trail) == arc
    again = np.where(theirs == 100, 100, 0).astype(np.int8)
    assert robots_off(again, res, (0.0, 0.0), g_theirs, trail) == 0  # its own map holds the arc: seen, kept


def test_the_map_that_knows_most_is_in_charge_where_maps_disagree() -> None:
    # Two robots' maps of one wall, a cell apart (their alignment): merged, the wall stays one map's,
    # not both copies; the other map only fills what the first does not know.
    a = np.full((4, 5), 0, dtype=np.uint8)
    a[2, :] = 100  # the wall, as the map that knows most draws it
    a[0, 0] = 255
    b = np.full((4, 5), 0, dtype=np.uint8)
    b[3, :] = 100  # the same wall a cell further up
    b[0, 0] = 100
    b[:, 4] = 255
    for order in ([grid(0.0, 0.0, a), grid(0.0, 0.0, b)], [grid(0.0, 0.0, b), grid(0.0, 0.0, a)]):
        cells, _, _ = floor_of(order)
        assert cells[2].tolist() == [100] * 5 and cells[3].tolist() == [0] * 5  # one wall, a's
        assert cells[0, 0] == 100  # unknown to a: b's


ROOM_8_CORNER = (  # office room-8's top-left corner on uvc-2's map (0.05 m cells, top row first), where
    # uvc-1 stood (row 12, column 14) when the two-robot round was planned: its outline, as uvc-2's
    # lidar drew it, round it
    "###########################",
    "###########################",
    "###..#.###...........#....#",
    *["##........................."] * 8,
    "##..............#..........",
    "##..............##.........",
    "##..............##.........",
    "##........#.....##.........",
    "##........##...##..........",
    "##..........#####..........",
    *["##........................."] * 8,
)


def test_a_robot_seen_as_an_obstacle_on_the_other_robots_map_still_takes_part() -> None:
    res = 0.05
    cells = np.zeros((60, 80), dtype=np.int8)  # a 4 x 3 m room
    cells[0, :] = cells[:, -1] = 100
    window = np.array([[100 if ch == "#" else 0 for ch in row] for row in ROOM_8_CORNER[::-1]], dtype=np.int8)
    cells[-window.shape[0] :, : window.shape[1]] = window
    corner = ((14 + 0.5) * res, (60 - 12 - 0.5) * res)
    request = RoundRequest("uv", RectArea(0.1, 0.05, 3.95, 2.9), ("r1", "r2"), 100.0)
    p = plan_round(request, cells, res, (0.0, 0.0), {"r1": corner, "r2": (3.0, 1.0)}, DEFAULT_LAMP)
    assert p.left_out == () and sorted(r.robot for r in p.rounds) == ["r1", "r2"]


def test_a_top_up_is_planned_only_below_the_share_a_round_certifies() -> None:
    from fleetlink.shared.dose import DoseGrid

    request = RoundRequest("uv", RectArea(0.5, 0.5, 4.5, 3.5), ("r1",), 100.0)
    dose = np.full((43, 91), 150.0)

    def top_up(hole: tuple[slice, slice]) -> RoundPlan:
        had = dose.copy()
        had[hole] = 0.0
        prior = DoseGrid.from_array(had, RES, (-0.05, -0.05))  # centres on multiples of 0.1 m
        return plan_round(request, CELLS, RES, (0.0, 0.0), {"r1": A}, DEFAULT_LAMP, prior=prior)

    # 0.06 m² short of the dose (about 0.5 % of the rectangle): the round is done, though the plan
    # itself aims at 99.5 %.
    with pytest.raises(RoundError, match=r"has the dose already \(a round certifies 99 %\): nothing to top up"):
        top_up((slice(15, 17), slice(20, 23)))
    p = top_up((slice(15, 25), slice(20, 30)))  # a square metre short
    assert p.rounds and p.rounds[0].dwell_s > 0


def test_order_ids_stay_new_and_times_read_as_people_say_them() -> None:
    ids = RoundIds()
    first = ids.next("uv", "r1", 1000.2)
    assert first == "uv-r1-1000" and ids.next("uv", "r2", 1000.5) == "uv-r2-1001"
    assert ids.next("sweep", "r1", 5000.0) == "sweep-r1-5000"
    assert [describe_time(s) for s in (4.4, 65, 3725)] == ["4 s", "1 min 5 s", "1 h 02 min"]


def test_a_round_over_a_pocket_the_map_has_not_seen_is_a_survey_first() -> None:
    """An unknown 1.2 x 1.2 m pocket behind a wall stub in the left room: a request that allows a
    survey gets one (view points, the lamp on between them, the orders' ids marked; a sweep's dark); with none left it plans the
    round on the map as it is; two robots share the looking."""
    cells = CELLS.copy()
    cells[5:18, 30] = 100  # a stub wall x 3.0, y 0.5..1.8
    cells[5:17, 31:43] = -1  # what it hid from a robot at (1, 1): x 3.1..4.3, y 0.5..1.7
    area = RectArea(0.1, 0.1, 5.0, 4.0)
    request = RoundRequest("uv", area, ("r1",), 100.0, surveys=1)
    look = plan_round(request, cells, RES, (0.0, 0.0), {"r1": A}, DEFAULT_LAMP, {"r1": "uv-r1-3"})
    assert look.survey and look.area_m2 == pytest.approx(1.44, rel=0.05) and look.coverage >= 0.9
    (r,) = look.rounds
    assert r.order_id == "uv-r1-3-survey" and r.dwell_points >= 1
    assert all(n.x > 3.0 for n in r.route[1:]), r.route  # past the stub
    # The views stand in the area: the lamp goes on at the first (before its dwell) and off at the last.
    order = as_order(r.order)
    lamp = [
        (n.nodeId, a.actionParameters[1].value)
        for n in order.nodes
        for a in n.actions
        if a.actionType.value == "payload"
    ]
    assert lamp == [(order.nodes[1].nodeId, "true"), (order.nodes[-1].nodeId, "false")], lamp
    assert [a.actionType.value for a in order.nodes[1].actions][:2] == ["payload", "dwell"]
    # A sweep's survey looks with the lamp off.
    sweep = plan_round(
        RoundRequest("sweep", area, ("r1",), 100.0, surveys=1), cells, RES, (0.0, 0.0), {"r1": A}, DEFAULT_LAMP
    )
    assert sweep.survey and set(action_types(as_order(sweep.rounds[0].order))) == {"dwell"}
    assert "survey before the UV round of the rectangle" in look.summary() and "view points" in look.summary()
    # No survey left: the round itself, on the map as it is (the pocket is not floor on it).
    uv = plan_round(RoundRequest("uv", area, ("r1",), 100.0), cells, RES, (0.0, 0.0), {"r1": A}, DEFAULT_LAMP)
    assert not uv.survey and "payload" in action_types(as_order(uv.rounds[0].order))
    # Two robots: the view points shared between them.
    both = RoundRequest("uv", area, ("r1", "r2"), 100.0, surveys=1)
    shared = plan_round(both, cells, RES, (0.0, 0.0), {"r1": A, "r2": B}, DEFAULT_LAMP)
    assert shared.survey and {r.robot for r in shared.rounds} <= {"r1", "r2"}
    assert all("payload" in action_types(as_order(r.order)) for r in shared.rounds)  # each share lit
    # The same map fully seen: no survey, whatever is allowed.
    seen = plan_round(request, CELLS, RES, (0.0, 0.0), {"r1": A}, DEFAULT_LAMP)
    assert not seen.survey


def test_the_lamp_is_off_on_any_way_that_leaves_the_area() -> None:
    """A rectangle across the wall between the two rooms (x 3-7, y 0.1-1.5): the way from its left
    part to its right one runs out of it, through the door (y 1.8-2.7). The lamp goes off before
    that edge and on again at the next dwell, in the round and in a UV round's survey."""
    cells = CELLS.copy()
    cells[1:6, 38] = 100  # stubs hiding unknown pockets on each side (for the survey)
    cells[1:6, 39:44] = -1
    cells[1:6, 62] = 100
    cells[1:6, 57:62] = -1
    area = RectArea(3.0, 0.1, 7.0, 1.5)
    for surveys in (1, 0):
        request = RoundRequest("uv", area, ("r1",), 100.0, surveys=surveys)
        p = plan_round(request, cells, RES, (0.0, 0.0), {"r1": (1.0, 3.5)}, DEFAULT_LAMP)
        assert p.survey == (surveys == 1)
        order = as_order(p.rounds[0].order)
        lamp, lit_edges = False, 0
        for n, e in zip(order.nodes, (*order.edges, None), strict=True):
            for a in n.actions:
                if a.actionType is ActionType.PAYLOAD:
                    lamp = [kv.value for kv in a.actionParameters if kv.key == "on"] == ["true"]
            if e is None or not lamp:
                continue
            lit_edges += 1
            assert e.trajectory is not None
            for c in e.trajectory.controlPoints:
                assert 2.9 <= c.x <= 7.1 and 0.0 <= c.y <= 1.6, (surveys, e.edgeId, c)
        assert lit_edges >= (0 if surveys else 3)
        assert any(kv.value == "false" for n in order.nodes[1:-1] for a in n.actions for kv in a.actionParameters)


def test_a_survey_sends_no_robot_to_look_from_where_another_round_robot_stands() -> None:
    """The best view behind the stub, with a second robot of the round standing on it: the views
    go elsewhere (a robot sent there would wait for the other to move, then give the view up)."""
    cells = CELLS.copy()
    cells[5:18, 30] = 100
    cells[5:17, 31:43] = -1
    area = RectArea(0.1, 0.1, 5.0, 4.0)
    alone = plan_round(
        RoundRequest("uv", area, ("r1",), 100.0, surveys=1), cells, RES, (0.0, 0.0), {"r1": A}, DEFAULT_LAMP
    )
    best = alone.rounds[0].route[1]
    spot = (best.x, best.y)
    both = RoundRequest("uv", area, ("r1", "r2"), 100.0, surveys=1)
    shared = plan_round(both, cells, RES, (0.0, 0.0), {"r1": A, "r2": spot}, DEFAULT_LAMP)
    assert shared.survey
    views = [(n.x, n.y) for r in shared.rounds for n in r.route[1:]]
    assert views and all(math.dist(v, spot) > 0.39 and math.dist(v, A) > 0.39 for v in views), (spot, views)
