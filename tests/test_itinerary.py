"""Orders with nodes (issue 16): the itinerary alone (agent/itinerary.py), then in the agent's core
with a robot that moves as it is told (a unicycle integrated tick by tick) and a board whose lamp
follows the payload requests."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import msgpack
import pytest

from fleetlink.agent.core import AgentCore, BoardView, Output
from fleetlink.agent.itinerary import Finished, GoTo, Itinerary, ItineraryError, RunAction, Stop, StopAction
from fleetlink.agent.pilot import Pilot
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import (
    MAX_ORDER_NODES,
    MAX_TRAJECTORY_POINTS,
    Ack,
    AckResult,
    Action,
    ActionType,
    Event,
    Goal,
    InstantActions,
    KeyValue,
    LinkName,
    Order,
    OrderEdge,
    OrderNode,
    State,
    Teleop,
    Trajectory,
)


def dwell(s: float, aid: str = "d") -> StopAction:
    return StopAction(aid, "dwell", {"duration": str(s)})


def lamp(on: bool, aid: str = "l") -> StopAction:
    return StopAction(aid, "payload", {"device": "uv", "on": "true" if on else "false"})


def stops(*specs: tuple[float, float, tuple[StopAction, ...]]) -> list[Stop]:
    return [Stop(f"n{i}", 2 * i, x, y, None, True, None, acts) for i, (x, y, acts) in enumerate(specs)]


# -- the itinerary alone -------------------------------------------------------------------------------


def test_nodes_are_driven_in_order_and_each_nodes_actions_run_there_one_by_one() -> None:
    it = Itinerary.of("o", 0, "op", stops((0, 0, ()), (1, 0, (lamp(True), dwell(5.0))), (2, 0, (lamp(False),))))
    first = it.step(0.0)
    assert isinstance(first, GoTo) and first.stop.node_id == "n0"
    assert it.step(0.1) is None  # driving: nothing new until the go-to ends
    it.arrived(0.5)
    nxt = it.step(0.5)
    assert isinstance(nxt, GoTo) and nxt.stop.node_id == "n1"
    it.arrived(2.0)
    on = it.step(2.0)
    assert isinstance(on, RunAction) and on.action.params["on"] == "true"
    assert it.step(2.0) is None and it.dwell_left_s == 5.0  # dwelling
    assert it.step(6.0) is None and it.dwell_left_s == pytest.approx(1.0)
    last = it.step(7.0)
    assert isinstance(last, GoTo) and last.stop.node_id == "n2" and it.last is not None and it.last.node_id == "n1"
    it.arrived(8.0)
    off = it.step(8.0)
    assert isinstance(off, RunAction) and off.action.params["on"] == "false"
    done = it.step(8.0)
    assert isinstance(done, Finished) and done.nodes == 3 and done.skipped == ()
    assert it.progress()["nodesDone"] == 3


def test_a_pause_freezes_the_dwell_and_a_resume_carries_on_where_it_was() -> None:
    it = Itinerary.of("o", 0, "op", stops((0, 0, (dwell(10.0),))))
    assert isinstance(it.step(0.0), GoTo)
    it.arrived(0.0)
    assert it.step(0.0) is None
    it.step(4.0)
    it.hold(4.0, "paused")
    assert it.step(100.0) is None and it.dwell_left_s == pytest.approx(6.0) and it.waiting == "paused"
    it.release(100.0)
    assert it.step(105.0) is None and it.dwell_left_s == pytest.approx(1.0)
    assert isinstance(it.step(106.0), Finished)


def test_a_node_the_robot_cannot_reach_is_skipped_without_its_actions() -> None:
    it = Itinerary.of("o", 0, "op", stops((0, 0, ()), (5, 5, (lamp(True),)), (1, 1, ())))
    it.step(0.0)
    it.arrived(0.0)
    assert isinstance(it.step(0.0), GoTo)
    skipped = it.failed(1.0)
    assert skipped is not None and skipped.node_id == "n1"
    nxt = it.step(1.0)
    assert isinstance(nxt, GoTo) and nxt.stop.node_id == "n2"  # no lamp action: the node was not reached
    it.arrived(2.0)
    done = it.step(2.0)
    assert isinstance(done, Finished) and done.skipped == ("n1",)


def test_an_interrupted_go_to_is_asked_for_again_on_the_resume() -> None:
    it = Itinerary.of("o", 0, "op", stops((3, 0, ())))
    assert isinstance(it.step(0.0), GoTo)
    it.interrupted(1.0, "e-stop")
    assert it.step(2.0) is None and it.waiting == "e-stop"
    it.release(3.0)
    again = it.step(3.0)
    assert isinstance(again, GoTo) and again.stop.node_id == "n0"


def test_driven_away_by_hand_mid_dwell_it_drives_back_and_dwells_only_what_was_left() -> None:
    it = Itinerary.of("o", 0, "op", stops((0, 0, (dwell(10.0), lamp(False)))))
    it.step(0.0)
    it.arrived(0.0)
    it.step(0.0)
    it.step(3.0)
    it.moved(3.0, "teleop")
    assert it.step(50.0) is None
    it.release(50.0)
    back = it.step(50.0)
    assert isinstance(back, GoTo) and back.stop.node_id == "n0" and it.dwell_left_s == pytest.approx(7.0)
    it.arrived(55.0)
    assert it.step(55.0) is None
    off = it.step(62.0)
    assert isinstance(off, RunAction) and off.action.action_id == "l"  # the rest of the node's actions


def test_an_update_carries_on_after_the_last_node_reached() -> None:
    it = Itinerary.of(
        "o", 0, "op", [Stop("a", 0, 0, 0, None), Stop("b", 2, 1, 0, None), Stop("c", 4, 2, 0, None, False)]
    )
    it.step(0.0)
    it.arrived(0.0)
    it.step(0.0)
    it.arrived(1.0)
    assert it.step(1.0) is None and it.waiting == "horizon"  # the base ends at b: wait for an update
    newer = Itinerary.of("o", 1, "op", [Stop("b", 2, 1, 0, None), Stop("c", 4, 2, 0, None), Stop("d", 6, 3, 0, None)])
    it = it.updated(newer)
    nxt = it.step(2.0)
    assert isinstance(nxt, GoTo) and nxt.stop.node_id == "c" and it.waiting == ""


@pytest.mark.parametrize(
    ("nodes", "why"),
    [
        ([], "at least one node"),
        ([Stop("a", 0, math.nan, 0, None)], "finite"),
        ([Stop("a", 0, 500.0, 0, None)], "extent"),
        ([Stop("a", 0, 0, 0, None, False)], "first node"),
        ([Stop("a", 0, 0, 0, None), Stop("b", 2, 0, 0, None, False), Stop("c", 4, 0, 0, None)], "after a horizon"),
        ([Stop("a", 0, 0, 0, None, actions=(StopAction("x", "estop", {}),))], "not a node action"),
        ([Stop("a", 0, 0, 0, None, actions=(StopAction("x", "dwell", {"duration": "nan"}),))], "dwell duration"),
        ([Stop("a", 0, 0, 0, None, actions=(StopAction("x", "dwell", {"duration": "-1"}),))], "dwell duration"),
        ([Stop("a", 0, 0, 0, None, actions=(StopAction("x", "dwell", {}),))], "one parameter"),
    ],
)
def test_an_itinerary_it_cannot_run_is_refused_with_the_reason(nodes: list[Stop], why: str) -> None:
    with pytest.raises(ItineraryError, match=why):
        Itinerary.of("o", 0, "op", nodes, extent_m=100.0)


# -- in the agent's core --------------------------------------------------------------------------------

BOARD = BoardView(
    connected=True,
    left_m=0.0,
    right_m=0.0,
    gyro_yaw=0.0,
    odom_t=0.0,
    battery_percent=80.0,
    battery_known=True,
    has_payload=True,
    ultrasonic_m=5.0,
)


class Robot:
    """An agent core whose pose follows the velocity it commands and whose lamp follows its requests."""

    def __init__(self, board: BoardView = BOARD) -> None:
        self.clock = SimClock()
        self.core = AgentCore("r1", self.clock, Pilot())
        self.pose = [0.0, 0.0, 0.0]
        self.core._map_pose = lambda: (self.pose[0], self.pose[1], self.pose[2])  # type: ignore[method-assign]
        self.board = board
        self.lamp = False
        self.lamp_requests: list[bool] = []
        self.top_speed = 0.0
        self.events: list[Event] = []
        self.counter = wire.HeaderCounter(self.clock, robot="r1", sender="op-a")

    def _take(self, out: Output) -> Output:
        for req in out.payload:
            if req.device in ("uv", "all"):
                self.lamp = req.on
                self.lamp_requests.append(req.on)
        self.events += [m for m, _ in out.messages if isinstance(m, Event)]
        return out

    def send(self, cls: type[wire.Message], **fields: Any) -> Ack:
        msg = self.counter.make(cls, **fields)
        out = self._take(self.core.on_input(LinkName.ZENOH, wire.key_of(msg), wire.encode(msg), self.clock.now()))
        return next(m for m, _ in out.messages if isinstance(m, Ack))

    def action(self, kind: ActionType, **params: str) -> Ack:
        kvs = tuple(KeyValue(key=k, value=v) for k, v in params.items())
        return self.send(InstantActions, actions=(Action(actionId="a", actionType=kind, actionParameters=kvs),))

    def run(self, seconds: float, dt: float = 0.05) -> None:
        for _ in range(round(seconds / dt)):
            self.clock.advance(dt)
            board = dataclasses.replace(self.board, payload_on=self.lamp, odom_t=self.clock.now())
            out = self._take(self.core.tick(self.clock.now(), board))
            v, w = out.velocity if out.velocity is not None else (0.0, 0.0)
            self.top_speed = max(self.top_speed, abs(v))
            x, y, th = self.pose
            self.pose = [x + v * math.cos(th) * dt, y + v * math.sin(th) * dt, th + w * dt]

    def state(self) -> State:
        return self.core._state(self.clock.now())

    def texts(self) -> list[str]:
        return [e.text for e in self.events if e.kind == "order"]

    def outcomes(self) -> list[tuple[str, str]]:
        """(order, outcome) of each order event that ended one, for machines (the console's survey)."""
        found = [{kv.key: kv.value for kv in e.data} for e in self.events if e.kind == "order"]
        return [(d["order"], d["outcome"]) for d in found if "outcome" in d]


def node(i: int, x: float, y: float, *actions: Action, released: bool = True) -> OrderNode:
    return OrderNode(nodeId=f"n{i}", sequenceId=2 * i, released=released, x=x, y=y, theta=None, actions=actions)


def edge(i: int, max_speed: float | None = None) -> OrderEdge:
    return OrderEdge(
        edgeId=f"e{i}",
        sequenceId=2 * i + 1,
        startNodeId=f"n{i}",
        endNodeId=f"n{i + 1}",
        released=True,
        maxSpeed=max_speed,
    )


def act(kind: ActionType, aid: str, **params: str) -> Action:
    return Action(
        actionId=aid, actionType=kind, actionParameters=tuple(KeyValue(key=k, value=v) for k, v in params.items())
    )


def uv(on: bool) -> Action:
    return act(ActionType.PAYLOAD, f"uv-{on}", device="uv", on="true" if on else "false")


def order(
    nodes: tuple[OrderNode, ...], edges: tuple[OrderEdge, ...] | None = None, oid: str = "round-1", upd: int = 0
) -> dict[str, Any]:
    if edges is None:
        edges = tuple(edge(i) for i in range(len(nodes) - 1))
    return {"orderId": oid, "orderUpdateId": upd, "goal": None, "returnHome": False, "nodes": nodes, "edges": edges}


ROUND = (
    node(0, 0.0, 0.0),
    node(1, 1.0, 0.0, uv(True), act(ActionType.DWELL, "d1", duration="4")),
    node(2, 1.0, 1.0, act(ActionType.DWELL, "d2", duration="3"), uv(False)),
)


def test_an_order_with_nodes_drives_each_node_switches_the_lamp_and_dwells_then_reports_it_finished() -> None:
    r = Robot()
    ack = r.send(Order, **order(ROUND))
    assert ack.result is AckResult.ACCEPTED, ack.reason
    r.run(2.5)
    s = r.state()
    assert s.orderId == "round-1" and s.progress is not None and s.progress.nodesTotal == 3
    r.run(30.0)
    assert math.hypot(r.pose[0] - 1.0, r.pose[1] - 1.0) < 0.15
    assert r.lamp_requests == [True, False] and not r.lamp
    assert r.state().progress is None and any("finished: 3 nodes" in t for t in r.texts())
    assert r.outcomes() == [("round-1", "finished")]


def test_a_round_sent_while_a_goal_is_still_being_driven_replaces_it_and_runs_to_the_end() -> None:
    # The goal it replaces ends "replaced" (the pilot's doing, on the round's first go-to): that is
    # the round starting, not something that interrupts it (it once held the round, waiting).
    r = Robot()
    goal = r.send(Order, orderId="goal-1", orderUpdateId=0, goal=Goal(x=3.0, y=0.0, theta=None), returnHome=False)
    assert goal.result is AckResult.ACCEPTED, goal.reason
    r.run(1.0)
    assert r.core.pilot.order_id == "goal-1"
    r.send(Order, **order(ROUND))
    r.run(30.0)
    assert r.outcomes() == [("round-1", "finished")], (r.texts(), r.state().progress)
    assert math.hypot(r.pose[0] - 1.0, r.pose[1] - 1.0) < 0.15


def test_progress_says_which_node_was_reached_last_and_how_long_the_dwell_still_runs() -> None:
    r = Robot()
    r.send(Order, **order(ROUND))
    for _ in range(400):
        r.run(0.05)
        p = r.state().progress
        if p is not None and p.dwellLeft_s > 0:
            break
    p = r.state().progress
    assert p is not None and p.lastNodeId == "n1" and p.lastNodeSequenceId == 2 and 0 < p.dwellLeft_s <= 4.0
    assert (r.lamp and r.state().payloadOn is False) or r.lamp  # the board reports it on the next tick


def test_an_estop_switches_the_lamp_off_at_once_and_a_resume_after_the_release_finishes_the_round() -> None:
    r = Robot()
    r.send(Order, **order(ROUND))
    while not r.lamp:
        r.run(0.05)
    r.run(1.0)
    assert r.action(ActionType.ESTOP).result is AckResult.ACCEPTED
    assert not r.lamp  # at once, in the same input
    p = r.state().progress
    assert p is not None and p.waiting == "e-stop"
    left = p.dwellLeft_s
    r.run(10.0)
    p = r.state().progress
    assert p is not None and p.dwellLeft_s == pytest.approx(left) and not r.lamp  # frozen, dark
    refused = r.action(ActionType.RESUME)
    assert refused.result is AckResult.REJECTED and "e-stop" in refused.reason
    assert r.action(ActionType.ESTOP_RELEASE).result is AckResult.ACCEPTED
    assert r.action(ActionType.RESUME).result is AckResult.ACCEPTED
    assert r.lamp  # the round's lamp comes back with the resume
    r.run(30.0)
    assert r.state().progress is None and any("finished" in t for t in r.texts()) and not r.lamp


def test_a_pause_darkens_the_lamp_and_freezes_the_dwell_a_cancel_ends_the_round_with_the_lamp_off() -> None:
    r = Robot()
    r.send(Order, **order(ROUND))
    while not r.lamp:
        r.run(0.05)
    assert r.action(ActionType.PAUSE).result is AckResult.ACCEPTED
    assert not r.lamp and r.state().paused
    r.run(10.0)
    assert r.state().progress is not None
    assert r.action(ActionType.RESUME).result is AckResult.ACCEPTED and r.lamp
    assert r.action(ActionType.CANCEL).result is AckResult.ACCEPTED
    assert not r.lamp and r.state().progress is None and r.core.itinerary is None
    assert any("cancelled by op-a" in t for t in r.texts())
    assert r.outcomes() == [("round-1", "ended")]


def test_driving_by_hand_holds_the_round_and_the_resume_comes_back_to_the_node() -> None:
    r = Robot()
    r.send(Order, **order(ROUND))
    while not r.lamp:
        r.run(0.05)
    assert r.send(Teleop, v=0.3, omega=0.0, ttl_s=0.5).result is AckResult.ACCEPTED
    r.run(0.4)
    p = r.state().progress
    assert p is not None and p.waiting == "teleop"
    r.run(2.0)
    assert r.action(ActionType.RESUME).result is AckResult.ACCEPTED
    r.run(40.0)
    assert any("finished: 3 nodes" in t for t in r.texts())
    assert math.hypot(r.pose[0] - 1.0, r.pose[1] - 1.0) < 0.15


def test_an_edge_speed_cap_holds_the_robot_below_it() -> None:
    r = Robot()
    r.send(Order, **order((node(0, 0.0, 0.0), node(1, 3.0, 0.0)), (edge(0, max_speed=0.1),)))
    r.run(10.0)
    assert 0.05 < r.top_speed <= 0.1 + 1e-9


def test_a_nodes_allowed_deviation_reaches_the_go_to_and_one_out_of_bounds_is_refused() -> None:
    r = Robot()
    near = dataclasses.replace(node(1, 3.0, 0.0), allowedDeviationXY=0.15)
    assert r.send(Order, **order((node(0, 0.0, 0.0), near), (edge(0),))).result is AckResult.ACCEPTED
    r.run(1.0)
    route = r.core.pilot._route
    assert route is not None and (route.dest.x, route.dest.deviation) == (3.0, 0.15)
    for bad in (1.5, -0.1, math.nan):
        msg = r.counter.make(Order, **order((node(0, 0.0, 0.0), node(1, 3.0, 0.0)), (edge(0),), oid="o-bad"))
        obj = msgpack.unpackb(wire.encode(msg))
        obj["nodes"][1]["allowedDeviationXY"] = bad
        with pytest.raises(wire.WireError, match=r"nodes\[1\]\.allowedDeviationXY"):
            wire.decode(Order, msgpack.packb(obj))


def test_an_edges_trajectory_reaches_the_go_to_and_the_robot_drives_by_it() -> None:
    """The edge from (0, 0) to (2, 0) bends through (1, 1) (the way planned on the fleet's map):
    the robot, whose own map knows nothing of what the bend goes round, drives by (1, 1)."""
    r = Robot()
    bend = dataclasses.replace(edge(0), trajectory=Trajectory.polyline(((0.0, 0.0), (1.0, 1.0), (2.0, 0.0))))
    assert r.send(Order, **order((node(0, 0.0, 0.0), node(1, 2.0, 0.0)), (bend,))).result is AckResult.ACCEPTED
    r.run(0.1)
    route = r.core.pilot._route
    assert route is not None and route.dest.trajectory == ((0.0, 0.0), (1.0, 1.0), (2.0, 0.0))
    assert route.goto.waypoints == [(1.0, 1.0), (2.0, 0.0)]
    high = 0.0
    for _ in range(300):
        r.run(0.1)
        high = max(high, r.pose[1])
        if any("finished" in t for t in r.texts()):
            break
    assert any("finished: 2 nodes" in t for t in r.texts())
    assert high > 0.9  # by the bend, not straight along y = 0


def test_the_plans_drive_through_nodes_may_deviate_its_dwell_points_may_not() -> None:
    from fleetlink.agent.coverage import CoveragePlan, PlanEdge, PlanNode, Prediction, plan_order

    pred = Prediction(coverage=1.0, dwell_s=10.0, travel_s=0.0, total_s=10.0, path_m=2.0, area_m2=1.0)
    plan = CoveragePlan(
        "uv",
        (
            PlanNode("n0", 0, 0.0, 0.0, 0.0, False),
            PlanNode("n1", 2, 1.0, 0.0, 0.0, True),
            PlanNode("n2", 4, 2.0, 0.0, 10.0, True),
        ),
        (
            PlanEdge("e1", 1, "n0", "n1", ((0.0, 0.0), (1.0, 0.0)), 1.0, True),
            PlanEdge("e2", 3, "n1", "n2", ((1.0, 0.0), (2.0, 0.0)), 1.0, True),
        ),
        100.0,
        pred,
    )
    assert [n.allowedDeviationXY for n in plan_order(plan, "o")["nodes"]] == [0.0, 0.0, 0.0]
    assert [n.allowedDeviationXY for n in plan_order(plan, "o", pass_deviation_m=0.15)["nodes"]] == [0.15, 0.15, 0.0]
    # Each edge carries its path as the way to drive (a polyline: its waypoints, in order).
    edges = plan_order(plan, "o")["edges"]
    assert [e.trajectory.waypoints() for e in edges] == [[(0.0, 0.0), (1.0, 0.0)], [(1.0, 0.0), (2.0, 0.0)]]


def test_the_largest_route_with_its_trajectories_still_fits_one_message() -> None:
    """511 edges of 4 waypoints each: trajectories while they fit (MAX_ORDER_TRAJECTORY_POINTS), the
    rest left to the robot; the order encodes under the wire's limit."""
    from fleetlink.agent.coverage import (
        MAX_ORDER_TRAJECTORY_POINTS,
        CoveragePlan,
        PlanEdge,
        PlanNode,
        Prediction,
        plan_order,
    )

    n = MAX_ORDER_NODES
    nodes = tuple(PlanNode(f"n{i}", 2 * i, 0.1 * i, 0.0, 1.0 if i else 0.0, True) for i in range(n))
    edges = tuple(
        PlanEdge(
            f"e{i}",
            2 * i + 1,
            f"n{i}",
            f"n{i + 1}",
            ((0.1 * i, 0.0), (0.1 * i + 0.03, 0.02), (0.1 * i + 0.06, 0.02), (0.1 * i + 0.1, 0.0)),
            0.1,
            True,
        )
        for i in range(n - 1)
    )
    pred = Prediction(coverage=1.0, dwell_s=n - 1.0, travel_s=0.0, total_s=n - 1.0, path_m=51.0, area_m2=1.0)
    fields = plan_order(CoveragePlan("uv", nodes, edges, 100.0, pred), "big")
    carried = [e.trajectory for e in fields["edges"] if e.trajectory is not None]
    assert 0 < len(carried) < n - 1 and sum(len(t.controlPoints) for t in carried) <= MAX_ORDER_TRAJECTORY_POINTS
    msg = wire.HeaderCounter(SimClock(), robot="r1", sender="op").make(Order, **fields)
    assert len(wire.encode(msg)) <= wire.MAX_PAYLOAD


def test_an_edge_with_more_corners_than_a_trajectory_carries_leaves_the_others_theirs() -> None:
    from fleetlink.agent.coverage import CoveragePlan, PlanEdge, PlanNode, Prediction, plan_order

    winding = tuple((0.01 * k, 0.01 * (k % 2)) for k in range(MAX_TRAJECTORY_POINTS + 1))
    nodes = (PlanNode("n0", 0, 0.0, 0.0, 0.0, False), PlanNode("n1", 2, winding[-1][0], winding[-1][1], 1.0, True))
    nodes += (PlanNode("n2", 4, 1.0, 1.0, 1.0, True),)
    edges = (
        PlanEdge("e1", 1, "n0", "n1", winding, 0.7, True),
        PlanEdge("e2", 3, "n1", "n2", (winding[-1], (1.0, 1.0)), 1.0, True),
    )
    pred = Prediction(coverage=1.0, dwell_s=2.0, travel_s=0.0, total_s=2.0, path_m=1.7, area_m2=1.0)
    e1, e2 = plan_order(CoveragePlan("uv", nodes, edges, 100.0, pred), "o")["edges"]
    assert e1.trajectory is None and e2.trajectory is not None


def test_the_same_order_again_is_a_duplicate_and_an_older_update_is_refused() -> None:
    r = Robot()
    assert r.send(Order, **order(ROUND, upd=1)).result is AckResult.ACCEPTED
    assert r.send(Order, **order(ROUND, upd=1)).result is AckResult.DUPLICATE
    msg = r.counter.make(Order, **order(ROUND, upd=0))
    out = r.core.on_input(LinkName.ZENOH, wire.key_of(msg), wire.encode(msg), r.clock.now())
    assert any("older" in line for line in out.logs)  # refused at the gate, counted
    assert r.core.itinerary is not None and r.core.itinerary.update_id == 1


@pytest.mark.parametrize(
    ("fields", "why"),
    [
        (order((node(0, 0, 0), node(2, 1, 0))), "sequence id"),
        (order((node(0, 0, 0), node(1, 1, 0)), ()), "edges"),
        (order((node(0, 0, 0), node(1, 1, 0)), (edge(3),)), "must lead"),
        ({**order(ROUND), "goal": Goal(x=1.0, y=1.0, theta=None)}, "one of them"),
        (order((node(0, 0, 0, act(ActionType.ESTOP, "x")),)), "not a node action"),
        (order((node(0, 0, 0, act(ActionType.PAYLOAD, "x", device="atomiser", on="true", level="7")),)), "0-3"),
        (order((node(0, 0, 0, act(ActionType.PAYLOAD, "x", device="laser", on="true")),)), "unknown payload device"),
        (order((node(0, 0, 0, act(ActionType.DWELL, "x", duration="1e9")),)), "dwell duration"),
        (
            order(
                (node(0, 0, 0), node(1, 1, 0)),
                (dataclasses.replace(edge(0), trajectory=Trajectory.polyline(((0.0, 0.0), (0.5, 0.5)))),),
            ),
            "its trajectory ends at (0.50, 0.50), not at node 'n1'",
        ),
    ],
)
def test_an_order_that_is_not_one_route_is_refused_with_the_reason_and_nothing_moves(
    fields: dict[str, Any], why: str
) -> None:
    r = Robot()
    ack = r.send(Order, **fields)
    assert ack.result is AckResult.REJECTED and why in ack.reason, ack.reason
    r.run(1.0)
    assert r.core.itinerary is None and r.pose == [0.0, 0.0, 0.0]


def test_a_lamp_order_to_a_robot_without_a_payload_is_refused() -> None:
    r = Robot(dataclasses.replace(BOARD, has_payload=False))
    r.run(0.05)
    ack = r.send(Order, **order(ROUND))
    assert ack.result is AckResult.REJECTED and "no payload" in ack.reason


def test_dwell_as_an_instant_action_is_refused() -> None:
    r = Robot()
    ack = r.action(ActionType.DWELL, duration="3")
    assert ack.result is AckResult.REJECTED and "node action" in ack.reason


def test_a_skipped_nodes_lamp_on_applies_at_the_next_node_reached_so_the_rest_is_not_run_dark() -> None:
    """Not where the robot gave up (outside the area, maybe: a survey's robot still in the corridor)."""
    r = Robot()
    far = node(1, 80.0, 0.0, uv(True), act(ActionType.DWELL, "d", duration="5"))  # off the map's reach
    r.core.pilot.path_provider = lambda start, goal, blocked=(): [] if goal[0] > 50 else None  # type: ignore[assignment,misc]
    n2 = node(2, 1.0, 0.0, act(ActionType.DWELL, "d2", duration="2"))
    assert (
        r.send(Order, **order((node(0, 0.0, 0.0), far, n2, node(3, 1.5, 0.0, uv(False))))).result is AckResult.ACCEPTED
    )
    skipped_at = None
    for _ in range(400):
        r.run(0.05)
        if skipped_at is None and any("n1 skipped" in t for t in r.texts()):
            skipped_at = tuple(r.pose[:2])
        if r.lamp_requests:
            break
    assert skipped_at is not None and math.hypot(*skipped_at) < 0.1  # it gave up where it stood
    assert r.lamp_requests == [True]
    assert math.hypot(r.pose[0] - 1.0, r.pose[1]) < 0.3, r.pose  # on at n2, before n2's dwell
    r.run(20.0)
    assert r.lamp_requests == [True, False] and any("finished: 4 nodes, 1 skipped" in t for t in r.texts()), r.texts()


def test_a_skipped_nodes_lamp_off_applies_at_once() -> None:
    r = Robot()
    far = node(2, 80.0, 0.0, uv(False))
    r.core.pilot.path_provider = lambda start, goal, blocked=(): [] if goal[0] > 50 else None  # type: ignore[assignment,misc]
    lit = node(1, 0.5, 0.0, uv(True), act(ActionType.DWELL, "d", duration="1"))
    assert r.send(Order, **order((node(0, 0.0, 0.0), lit, far, node(3, 1.0, 0.0)))).result is AckResult.ACCEPTED
    for _ in range(400):
        r.run(0.05)
        if any("n2 skipped" in t for t in r.texts()):
            break
    r.run(0.05)
    assert r.lamp_requests == [True, False] and not r.lamp  # off where it gave up, not at n3


def test_a_dwell_longer_than_an_hour_goes_out_as_several_dwell_actions() -> None:
    from fleetlink.agent.coverage import CoveragePlan, PlanEdge, PlanNode, Prediction, plan_order

    pred = Prediction(coverage=1.0, dwell_s=7000.0, travel_s=0.0, total_s=7000.0, path_m=1.0, area_m2=1.0)
    plan = CoveragePlan(
        "park",
        (PlanNode("n0", 0, 0.0, 0.0, 0.0, False), PlanNode("n1", 2, 1.0, 0.0, 7000.0, True)),
        (PlanEdge("e1", 1, "n0", "n1", ((0.0, 0.0), (1.0, 0.0)), 1.0, False),),
        100.0,
        pred,
    )
    fields = plan_order(plan, "park-r1-1")
    dwells = [
        float(kv.value)
        for a in fields["nodes"][1].actions
        if a.actionType is ActionType.DWELL
        for kv in a.actionParameters
    ]
    assert dwells == [3600.0, 3400.0]
    r = Robot()
    assert r.send(Order, **fields).result is AckResult.ACCEPTED


def _bump_on_the_way_to_n1(r: Robot, within_m: float) -> None:
    """Drive the order until the robot is ``within_m`` of n1 (at (2, 0)), then press the bumper."""
    for _ in range(400):
        r.run(0.05)
        if math.hypot(r.pose[0] - 2.0, r.pose[1]) <= within_m:
            break
    r.board = dataclasses.replace(r.board, bumped=True)
    r.run(0.2)
    r.board = dataclasses.replace(r.board, bumped=False)
    r.run(0.5)


@pytest.mark.parametrize(("within_m", "next_node"), [(0.12, "n2"), (0.3, "n2"), (0.6, "n1")])
def test_a_bump_near_a_node_holds_the_order_and_the_resume_goes_on_to_the_next_node(
    within_m: float, next_node: str
) -> None:
    # A lane end beside a doorway's jamb, or by a wall the map put a little further out: the body
    # touches it short of the node, as near as a blocked go-to counts it reached (NODE_PASS_M for a
    # node without actions). Driven at again after the resume, the node would press the same spot;
    # further from it, it is driven again.
    r = Robot()
    nodes = (
        node(0, 0.0, 0.0),
        dataclasses.replace(node(1, 2.0, 0.0), allowedDeviationXY=0.15),
        dataclasses.replace(node(2, 2.0, 1.0), allowedDeviationXY=0.15),
    )
    assert r.send(Order, **order(nodes)).result is AckResult.ACCEPTED
    _bump_on_the_way_to_n1(r, within_m)
    p = r.state().progress
    assert p is not None and p.waiting == "bump"  # safety first: the operator looks before it goes on
    r.run(2.0)
    assert r.state().progress.waiting == "bump"  # type: ignore[union-attr]
    assert r.action(ActionType.RESUME).result is AckResult.ACCEPTED
    r.run(0.5)
    route = r.core.pilot._route
    assert route is not None and (route.dest.x, route.dest.y) == {"n1": (2.0, 0.0), "n2": (2.0, 1.0)}[next_node]
    r.run(30.0)
    assert any("finished: 3 nodes" in t for t in r.texts())
