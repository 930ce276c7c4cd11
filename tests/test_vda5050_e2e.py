"""End to end: an independent VDA 5050 master control (the PyPI package ``vda5050-sdk``: its
``MasterClient`` over aiomqtt, its ``OrderBuilder``) drives a robot of the real-time simulated
field through ``fleetlink vda5050``'s bridge: a multi-node order, startPause, stopPause,
cancelOrder; a malformed order (published raw: the SDK will not build one) is refused in
``state.errors`` and a following valid order runs; a base with a horizon, extended when the vehicle
asks for a new base (``newBaseRequest``). A node inside a wall, in an order of its own: skipped,
its action FAILED, a ``noRouteError`` WARNING, the order finished. A real Mosquitto on a free port; the bridge's
operator link and the agent speak over real Zenoh on loopback (multicast scouting off). A separate
subscriber on ``#`` captures every VDA 5050 message on the wire, both directions, and each one is
validated against the official 2.1.0 schemas (``../shared/reference/vda5050-2.1.0/``).
"""

from __future__ import annotations

import asyncio
import json
import math
import threading
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion
from vda5050 import Action, ActionParameter, BlockingType, MasterClient, MasterConfig, OrderBuilder
from vda5050.model import ControlPoint, Trajectory

from fleetlink.field.realtime import RealtimeField
from fleetlink.operator.vda5050.schema import SchemaValidator, load_schemas
from fleetlink.shared.clock import SystemClock
from fleetlink.site.agents import FieldAgents
from fleetlink.site.vda5050 import open_bridge
from tests.harness import wait_until
from tests.harness.mosquitto import free_port
from tests.test_field_realtime import quiet_scenario
from tests.test_vda5050_core import REFERENCE

ROBOT = "uvc-1"
TARGET = f"fleetlink/{ROBOT}"
PREFIX = f"uagv/v2/fleetlink/{ROBOT}/"
MALFORMED = b'{"headerId": 9000, "orderId": "broken", "nodes": "not a list"}'


class Wire:
    """Every message under ``uagv/`` as the broker delivers it to a third party."""

    def __init__(self, host: str, port: int) -> None:
        self.messages: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="wire-capture")
        self.client.on_connect = lambda c, *_: c.subscribe("#", qos=1)
        self.client.on_message = self._on_message
        self.client.connect(host, port)
        self.client.loop_start()

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        if msg.topic.startswith("uagv/"):
            with self.lock:
                self.messages.append((msg.topic, bytes(msg.payload)))

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


async def wait_for(what: str, check: Any, timeout: float = 30.0) -> Any:
    deadline = asyncio.get_running_loop().time() + timeout
    while True:
        value = check()
        if value:
            return value
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.05)


@pytest.mark.slow
def test_a_vda5050_master_drives_a_field_robot_through_the_bridge(mosquitto) -> None:  # type: ignore[no-untyped-def]
    clock = SystemClock()
    field = RealtimeField(quiet_scenario(lidar={"enabled": False}), clock=clock)
    listen = f"tcp/127.0.0.1:{free_port()}"
    agents = bridge = wire = None
    try:
        endpoints = field.start()
        wire = Wire(mosquitto.host, mosquitto.port)
        bridge = open_bridge(clock, mqtt_url=mosquitto.url, zenoh_listen=[listen], state_period_s=1.0)
        bridge.start()
        agents = FieldAgents(endpoints, clock=clock, zenoh_connect=[listen], mqtt_url=mosquitto.url)
        agents.start()
        truth = field.world.robots[0]
        asyncio.run(master_session(mosquitto.url, lambda: truth.pose))
        stats = bridge.stats()[ROBOT]
        assert stats["invalid_out"] == {}
        assert stats["refused"] == {"order/validationError": 1}
    finally:
        if bridge is not None:
            bridge.close()
        if agents is not None:
            agents.stop()
        field.stop()
    # The bridge's clean exit says OFFLINE (retained): the last thing on its connection topic.
    wire_check(wire)


TOPICS = frozenset({"order", "instantActions", "state", "visualization", "connection", "factsheet"})


def wire_check(wire: Wire | None, topics: frozenset[str] = TOPICS) -> None:
    assert wire is not None

    def offline_heard() -> bool:
        with wire.lock:
            said = [json.loads(p)["connectionState"] for t, p in wire.messages if t == PREFIX + "connection"]
        return bool(said) and said[-1] == "OFFLINE"

    wait_until(offline_heard, timeout=10, message="the bridge's OFFLINE on the wire")
    wire.close()
    official = SchemaValidator(load_schemas(REFERENCE))
    seen: dict[str, int] = {}
    for topic, payload in wire.messages:
        sub = topic.rsplit("/", 1)[1]
        seen[sub] = seen.get(sub, 0) + 1
        if payload == MALFORMED:
            continue
        doc = json.loads(payload)
        assert official.problems(sub, doc) == [], (topic, doc)
    assert topics <= set(seen), seen
    connections = [json.loads(p)["connectionState"] for t, p in wire.messages if t == PREFIX + "connection"]
    assert connections[0] == "ONLINE" and connections[-1] == "OFFLINE"


async def stands_still(truth: Any, states: list[Any]) -> None:
    """The robot comes to rest (its true position unchanged over five polls in a row), then stays
    within 2 cm of where it rests while the vehicle publishes two more states."""
    last = [truth()]
    steady = [0]

    def at_rest() -> bool:
        p = truth()
        steady[0] = steady[0] + 1 if math.dist(p[:2], last[0][:2]) < 0.001 else 0
        last[0] = p
        return steady[0] >= 5

    await wait_for("the robot at rest", at_rest)
    held, seen = truth(), len(states)
    await wait_for("two more states", lambda: len(states) >= seen + 2)
    assert math.dist(truth()[:2], held[:2]) < 0.02


async def master_session(url: str, truth: Any) -> None:
    states: list[Any] = []
    master = MasterClient(MasterConfig(broker_url=url, client_id="vda-master", validate_messages=True))
    master.on_state(lambda s, key: states.append(s))
    async with master:
        state = await wait_for("a state from the vehicle", lambda: states and states[-1].agv_position)
        latest = lambda: states[-1]  # noqa: E731
        x0, y0, th = state.x, state.y, state.theta
        mp = state.map_id

        def point(d: float) -> tuple[float, float]:
            return x0 + d * math.cos(th), y0 + d * math.sin(th)

        # 1. A three-node order along the robot's heading.
        b = OrderBuilder(order_id="o-1", manufacturer="fleetlink", serial_number=ROBOT)
        for i, d in enumerate((0.0, 0.3, 0.6)):
            x, y = point(d)
            b.add_node(f"n{i}", x=x, y=y, map_id=mp, allowed_deviation_xy=0.5)
            if i:
                b.add_edge(f"n{i - 1}", f"n{i}")
        result = await master.dispatch(b.build(), TARGET)
        assert result.accepted, result
        await wait_for("the order in state", lambda: latest().order_id == "o-1" and latest().node_states)
        start = truth()
        await wait_for("driving", lambda: math.dist(truth()[:2], start[:2]) > 0.05)

        # 2. startPause: the robot stands, paused; 3. stopPause: it drives on.
        await master.pause(TARGET, action_id="pause-1")
        await wait_for("paused", lambda: latest().paused)
        await stands_still(truth, states)
        held = truth()
        status = lambda aid: next((a.action_status for a in latest().action_states if a.action_id == aid), None)  # noqa: E731
        assert str(getattr(status("pause-1"), "value", status("pause-1"))) == "FINISHED"
        await master.resume(TARGET, action_id="resume-1")
        await wait_for("not paused", lambda: not latest().paused)
        await wait_for("moving again", lambda: math.dist(truth()[:2], held[:2]) > 0.05)

        # 4. cancelOrder: the order's nodes go, the robot stops, the ids stay.
        await master.cancel_order(TARGET, action_id="cancel-1")
        await wait_for("the cancel finished", lambda: str(getattr(status("cancel-1"), "value", "")) == "FINISHED")
        await wait_for("no nodes left", lambda: not latest().node_states)
        assert latest().order_id == "o-1"
        await stands_still(truth, states)

        # 5. A malformed order is refused in state.errors; the vehicle keeps serving.
        pub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="raw-master")
        host, port = url.removeprefix("mqtt://").split(":")
        pub.connect(host, int(port))
        pub.loop_start()
        pub.publish(PREFIX + "order", MALFORMED, qos=1).wait_for_publish(5)
        pub.disconnect()
        pub.loop_stop()
        err = await wait_for(
            "a validationError",
            lambda: next((e for e in latest().errors if e.error_type == "validationError"), None),
        )
        assert str(getattr(err.error_level, "value", err.error_level)) == "WARNING"

        # 6. A following valid order runs to its end, along its edge's trajectory: a NURBS of degree 1
        # that bends 0.2 m to the robot's left half-way along the 0.5 m to m1 (the robot drives by it).
        here = latest().agv_position
        c, s = math.cos(here.theta), math.sin(here.theta)
        end = (here.x + 0.5 * c, here.y + 0.5 * s)
        bend = (here.x + 0.25 * c - 0.2 * s, here.y + 0.25 * s + 0.2 * c)
        b = OrderBuilder(order_id="o-2", manufacturer="fleetlink", serial_number=ROBOT)
        b.add_node("m0", x=here.x, y=here.y, map_id=mp, allowed_deviation_xy=0.5)
        b.add_node("m1", x=end[0], y=end[1], map_id=mp)
        way = Trajectory(
            degree=1,
            knot_vector=[0.0, 0.0, 0.5, 1.0, 1.0],
            control_points=[ControlPoint(x=x, y=y) for x, y in ((here.x, here.y), bend, end)],
        )
        b.add_edge("m0", "m1", trajectory=way)
        # Judged on the true pose: the bend where it lies from the robot (standing) in the true frame.
        tx0, ty0, tth = truth()
        tc, ts = math.cos(tth), math.sin(tth)
        true_bend = (tx0 + 0.25 * tc - 0.2 * ts, ty0 + 0.25 * ts + 0.2 * tc)
        result = await master.dispatch(b.build(), TARGET)
        assert result.accepted, result
        nearest = [math.inf]

        def finished() -> bool:
            tx, ty, _ = truth()
            nearest[0] = min(nearest[0], math.hypot(tx - true_bend[0], ty - true_bend[1]))
            return latest().order_id == "o-2" and latest().last_node_id == "m1" and not latest().node_states

        await wait_for("o-2 finished", finished)
        assert not any(e.error_type == "validationError" for e in latest().errors)
        assert nearest[0] < 0.1, f"the robot passed {nearest[0]:.2f} m from the trajectory's bend"

        # 7. A base with a horizon: near the base's end the vehicle asks for a new base
        # (newBaseRequest), which the master's SDK takes up as a base request; it extends the base
        # (an order update stitched at the decision point) and the robot drives on to the end.
        here = latest().agv_position
        b = OrderBuilder(order_id="o-3", manufacturer="fleetlink", serial_number=ROBOT)
        for i, d in enumerate((0.0, 0.3, 0.6)):
            x, y = here.x + d * math.cos(here.theta), here.y + d * math.sin(here.theta)
            b.add_node(f"h{i}", x=x, y=y, map_id=mp, allowed_deviation_xy=0.5 if i == 0 else None)
            if i:
                b.add_edge(f"h{i - 1}", f"h{i}")
        o3 = b.horizon_from("h2").build()
        assert [n.released for n in o3.nodes] == [True, True, False]
        result = await master.dispatch(o3, TARGET)
        assert result.accepted, result
        assert await master.wait_for_base_request(TARGET, timeout=30)
        assert latest().new_base_request and latest().order_id == "o-3"
        result = await master.extend_base(
            TARGET,
            [o3.nodes[2].model_copy(update={"released": True})],
            [o3.edges[1].model_copy(update={"released": True})],
        )
        assert result.accepted, result
        await wait_for(
            "o-3 finished",
            lambda: latest().order_id == "o-3" and latest().last_node_id == "h2" and not latest().node_states,
        )
        assert latest().order_update_id == 1 and not latest().new_base_request


IN_WALL = (5.97, 3.0)
"""A place in the wall between the living room and the kitchen (x = 6, y 2.1-4.5), 3 cm inside its
face as the robot's lidar sees it from the living room, in the plan's frame: no robot fits there."""


def robot_frame(agent: Any, truth: Any) -> Any:
    """Plan -> the robot's own frame. The field runs no UWB here, so the robot's frame (its map,
    its reported ``agvPosition``) starts where it stands; the robot has not moved yet."""
    tx, ty, tth = truth()
    p = agent.core.fusion.map_pose()
    d = p.theta - tth

    def to_robot(xy: tuple[float, float]) -> tuple[float, float]:
        dx, dy = xy[0] - tx, xy[1] - ty
        return p.x + dx * math.cos(d) - dy * math.sin(d), p.y + dx * math.sin(d) + dy * math.cos(d)

    return to_robot


def no_way_into_the_wall(agent: Any, truth: Any) -> bool:
    """The robot's planner has a map (a path to a free place beside it) and finds no way into the
    wall: the order may start (before its first map the robot would drive straight)."""
    plan = agent.core.pilot.path_provider
    if plan is None:
        return False
    to_robot = robot_frame(agent, truth)
    here = to_robot(truth()[:2])
    return bool(plan(here, to_robot(beside(truth)))) and not plan(here, to_robot(IN_WALL))


def beside(truth: Any) -> tuple[float, float]:
    """Free floor 0.4 m ahead of the robot's start (the living room), in the plan's frame."""
    x, y, th = truth()
    return x + 0.4 * math.cos(th), y + 0.4 * math.sin(th)


def test_a_node_inside_a_wall_is_skipped_its_actions_fail_and_the_robot_finishes_the_order(mosquitto) -> None:  # type: ignore[no-untyped-def]
    """A three-node order whose middle node lies in a wall: the master sees that node's action
    FAILED and a noRouteError WARNING naming it, and the robot goes on to the last node and
    finishes the order. The robot maps with its lidar (the planner then says there is no way into
    the wall at once: no time spent driving at it)."""
    clock = SystemClock()
    field = RealtimeField(quiet_scenario(), clock=clock)
    listen = f"tcp/127.0.0.1:{free_port()}"
    agents = bridge = wire = None
    try:
        endpoints = field.start()
        wire = Wire(mosquitto.host, mosquitto.port)
        bridge = open_bridge(clock, mqtt_url=mosquitto.url, zenoh_listen=[listen], state_period_s=1.0)
        bridge.start()
        agents = FieldAgents(endpoints, clock=clock, zenoh_connect=[listen], mqtt_url=mosquitto.url)
        agent = agents.start()[ROBOT]
        truth = field.world.robots[0]
        pose = lambda: truth.pose  # noqa: E731
        wait_until(lambda: no_way_into_the_wall(agent, pose), timeout=20, message="the robot's map")
        start = beside(pose)
        to_robot = robot_frame(agent, pose)
        asyncio.run(wall_session(mosquitto.url, to_robot(IN_WALL), to_robot(start)))
        assert math.dist(truth.pose[:2], start) < 0.35  # where the order's last node is
        stats = bridge.stats()[ROBOT]
        assert stats["invalid_out"] == {} and stats["refused"] == {}
        assert stats["skipped_nodes"] == 1 and stats["timed_out_actions"] == 0
    finally:
        if bridge is not None:
            bridge.close()
        if agents is not None:
            agents.stop()
        field.stop()
    wire_check(wire, TOPICS - {"instantActions"})


def dwell(action_id: str, seconds: float) -> Action:
    return Action(
        action_type="dwell",
        action_id=action_id,
        blocking_type=BlockingType.HARD,
        action_parameters=[ActionParameter(key="duration", value=seconds)],
    )


async def wall_session(url: str, in_wall: tuple[float, float], last: tuple[float, float]) -> None:
    states: list[Any] = []
    master = MasterClient(MasterConfig(broker_url=url, client_id="vda-master", validate_messages=True))
    master.on_state(lambda s, key: states.append(s))
    async with master:
        await wait_for("a state from the vehicle", lambda: states and states[-1].agv_position)
        latest = lambda: states[-1]  # noqa: E731
        here = latest().agv_position
        # Where the robot stands, a node in the wall, one beside the robot; a dwell at each of the
        # last two.
        b = OrderBuilder(order_id="o-wall", manufacturer="fleetlink", serial_number=ROBOT)
        b.add_node("w0", x=here.x, y=here.y, map_id=here.map_id, allowed_deviation_xy=0.5)
        b.add_node("w1", x=in_wall[0], y=in_wall[1], map_id=here.map_id, actions=[dwell("in-wall", 1.0)])
        b.add_node("w2", x=last[0], y=last[1], map_id=here.map_id, actions=[dwell("beside", 0.2)])
        b.add_edge("w0", "w1")
        b.add_edge("w1", "w2")
        result = await master.dispatch(b.build(), TARGET)
        assert result.accepted, result

        def status(aid: str) -> str:
            s = next((a.action_status for a in latest().action_states if a.action_id == aid), None)
            return str(getattr(s, "value", s))

        # The master sees the node in the wall given up: its action FAILED, and a noRouteError
        # WARNING naming the order, the node and the action.
        err = await wait_for(
            "a noRouteError", lambda: next((e for e in latest().errors if e.error_type == "noRouteError"), None)
        )
        assert str(getattr(err.error_level, "value", err.error_level)) == "WARNING"
        references = {(r.reference_key, r.reference_value) for r in err.error_references or []}
        assert {("orderId", "o-wall"), ("nodeId", "w1"), ("actionId", "in-wall")} <= references, references
        await wait_for("in-wall FAILED", lambda: status("in-wall") == "FAILED")
        assert "w1" not in [n.node_id for n in latest().node_states]
        # The robot goes on to the next node, dwells there and finishes the order.
        await wait_for(
            "o-wall finished",
            lambda: latest().last_node_id == "w2" and not latest().node_states and status("beside") == "FINISHED",
        )
        s = latest()
        assert s.order_id == "o-wall" and status("in-wall") == "FAILED"
        assert any(e.error_type == "noRouteError" for e in s.errors)  # held until the next new order
