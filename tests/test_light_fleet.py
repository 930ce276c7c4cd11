"""Light robots (field/light.py, field/light_runner.py) and the two-router mesh (site/mesh.py).

The core: every message it publishes decodes with the wire contract and the console's fleet model
shows every robot; a command is acked on the link it came on (a second copy as a duplicate), the
robot moves as told, the lease and the e-stop are kept; a simulator that falls behind skips
instead of bursting. The shell through a real mesh: `fleetlink field --light` on router A, an
operator link on router B; telemetry, presence, commands and acks cross both ways. Behaviour
only; the figures are bench/scale.py --light's.
"""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from fleetlink.field.light import LightFleet, light_names
from fleetlink.links.base import LinkStats
from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.links import OperatorLink
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SimClock, SystemClock
from fleetlink.shared.messages import (
    Ack,
    AckResult,
    Action,
    ActionType,
    BlockingType,
    Goal,
    InstantActions,
    Lease,
    LeaseRequest,
    LinkName,
    Order,
    Pose,
    State,
    Teleop,
)
from fleetlink.site.mesh import RouterMesh

WALL = 1_800_000_000.0


def decode_all(out: list[tuple[str, bytes]]) -> list[wire.Message]:
    return [wire.decode_key(k, p) for k, p in out]


class Operator:
    """Commands as a console makes them (its HeaderCounter), for the pure core."""

    def __init__(self, name: str = "op-a") -> None:
        self.clock = SimClock()
        self.counter = wire.HeaderCounter(self.clock, robot="operator", sender=name)
        self.name = name

    def command(self, cls: type[wire.Message], robot: str, **fields: object) -> tuple[str, bytes]:
        msg = cls(header=self.counter.header(cls.TOPIC, robot=robot), **fields)
        return keys.sender_key(robot, cls.TOPIC, self.name), wire.encode(msg)


def acks(out: list[tuple[str, bytes]]) -> list[Ack]:
    return [m for m in decode_all(out) if isinstance(m, Ack)]


def test_light_robots_publish_wire_messages_the_console_shows() -> None:
    names = light_names(120)
    fleet = LightFleet(names, 0.0)
    model = FleetModel("op-a")
    out: list[tuple[str, bytes]] = []
    for i in range(1, 21):  # one second in 50 ms steps
        out += fleet.due(i * 0.05, WALL + i * 0.05)
    msgs = decode_all(out)
    for m in msgs:
        model.apply(m, "zenoh", 1.0)
    assert set(model.robots) == set(names)
    poses = [m for m in msgs if isinstance(m, Pose)]
    states = [m for m in msgs if isinstance(m, State)]
    assert {p.header.robot for p in poses} == set(names) and {s.header.robot for s in states} == set(names)
    per_robot = {r: [p.header.headerId for p in poses if p.header.robot == r] for r in names}
    assert all(ids == list(range(len(ids))) and len(ids) in (19, 20, 21) for ids in per_robot.values())
    assert all(m.header.sender == m.header.robot for m in msgs)  # a robot speaks for itself
    assert all(WALL <= m.header.timestamp <= WALL + 1.0 for m in msgs)
    assert all(isinstance(m, Pose | State | Lease) for m in msgs)
    # Spread over the period, not all at once: the first 10 ms carry about a fifth of the poses.
    assert 15 <= len([k for k, _ in LightFleet(names, 0.0).due(0.01, WALL) if k.endswith("/pose")]) <= 35


def test_a_command_is_acked_on_its_link_once_and_moves_the_robot() -> None:
    fleet = LightFleet(light_names(3), 0.0)
    op = Operator()
    key, payload = op.command(Teleop, "L0001", v=0.5, omega=0.0, ttl_s=0.5)
    first = acks(fleet.command(LinkName.ZENOH, key, payload, 1.0, WALL + 1))
    again = acks(fleet.command(LinkName.MQTT, key, payload, 1.01, WALL + 1.01))
    assert [(a.result, a.link, a.commandTopic, a.commandSender) for a in first] == [
        (AckResult.ACCEPTED, LinkName.ZENOH, "teleop", "op-a")
    ]
    assert [(a.result, a.link) for a in again] == [(AckResult.DUPLICATE, LinkName.MQTT)]
    x0 = 2.0  # L0001's place on the grid
    poses: list[Pose] = [
        m for m in decode_all(fleet.due(1.4, WALL + 1.4)) if isinstance(m, Pose) and m.header.robot == "L0001"
    ]
    assert poses and 0.1 < poses[-1].x - x0 < 0.25 and poses[-1].vx == 0.5
    later = [m for m in decode_all(fleet.due(3.0, WALL + 3)) if isinstance(m, Pose) and m.header.robot == "L0001"]
    assert later[-1].vx == 0.0 and later[-1].x - x0 < 0.3  # the teleop's time-to-live lapsed: it stopped
    assert fleet.stats.accepted == 1 and fleet.stats.duplicates == 1


def test_an_order_drives_the_robot_to_its_goal_and_actions_stop_it() -> None:
    fleet = LightFleet(light_names(1), 0.0)
    op = Operator()
    key, payload = op.command(
        Order, "L0000", orderId="o1", orderUpdateId=0, goal=Goal(x=3.0, y=4.0, theta=None), returnHome=False
    )
    (ack,) = acks(fleet.command(LinkName.ZENOH, key, payload, 0.0, WALL))
    assert ack.result is AckResult.ACCEPTED and ack.orderId == "o1"
    out: list[tuple[str, bytes]] = []
    for i in range(1, 161):
        out += fleet.due(i * 0.05, WALL + i * 0.05)
    pose = [m for m in decode_all(out) if isinstance(m, Pose)][-1]
    assert math.hypot(pose.x - 3.0, pose.y - 4.0) < 0.06 and pose.vx == 0.0
    state = [m for m in decode_all(out) if isinstance(m, State)][-1]
    assert state.orderId == "o1" and state.goal is None
    # An e-stop latches: a teleop is refused until it is released.
    stop = (Action(actionId="a1", actionType=ActionType.ESTOP, actionParameters=(), blockingType=BlockingType.HARD),)
    key, payload = op.command(InstantActions, "L0000", actions=stop)
    assert [a.result for a in acks(fleet.command(LinkName.ZENOH, key, payload, 9.0, WALL + 9))] == [AckResult.ACCEPTED]
    key, payload = op.command(Teleop, "L0000", v=0.3, omega=0.0, ttl_s=0.5)
    refused = acks(fleet.command(LinkName.ZENOH, key, payload, 9.1, WALL + 9.1))
    assert [(a.result, a.reason) for a in refused] == [(AckResult.REJECTED, "e-stop latched")]


def test_the_lease_keeps_a_second_operator_off_and_bad_input_is_not_acked() -> None:
    fleet = LightFleet(light_names(1), 0.0)
    alice, bob = Operator("op-alice"), Operator("op-bob")
    key, payload = alice.command(LeaseRequest, "L0000", duration_s=60.0, release=False)
    (lease,) = [m for m in decode_all(fleet.command(LinkName.ZENOH, key, payload, 0.0, WALL)) if isinstance(m, Lease)]
    assert lease.holder == "op-alice" and lease.until == WALL + 60
    key, payload = bob.command(Teleop, "L0000", v=0.3, omega=0.0, ttl_s=0.5)
    assert [a.result for a in acks(fleet.command(LinkName.ZENOH, key, payload, 1.0, WALL + 1))] == [AckResult.REJECTED]
    assert fleet.command(LinkName.ZENOH, key, b"\xc1garbage", 1.0, WALL + 1) == []
    assert fleet.command(LinkName.ZENOH, keys.sender_key("L9999", "teleop", "op-bob"), payload, 1.0, WALL) == []
    assert fleet.stats.undecodable == 1 and fleet.stats.rejected == 1


def test_a_simulator_that_falls_behind_skips_instead_of_bursting() -> None:
    fleet = LightFleet(light_names(10), 0.0)
    fleet.due(0.0, WALL)
    out = fleet.due(2.0, WALL + 2.0)  # two seconds asleep: each robot one pose, not forty
    poses = [m for m in decode_all(out) if isinstance(m, Pose)]
    assert len(poses) == 10 and fleet.stats.skipped > 300
    assert all(p.header.timestamp >= WALL + 1.95 for p in poses)  # stamped when due, within a period


class NoLink:
    """The operator link's fallback on a site without a broker: never up, sends nothing."""

    name = LinkName.MQTT
    up = False

    def __init__(self) -> None:
        self.stats = LinkStats()

    def start(self) -> None:
        pass

    def subscribe(self, key_expr: str, receiver: Callable[[str, bytes], None]) -> None:
        pass

    def prioritise(self, priority_keys: frozenset[str], *, then_topics: frozenset[str] = frozenset()) -> None:
        pass

    def publish(self, key: str, payload: bytes) -> bool:
        return False

    def close(self) -> None:
        pass


@pytest.fixture
def mesh() -> Iterator[RouterMesh]:
    with RouterMesh() as m:
        yield m


def wait_for(cond: Callable[[], bool], timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.05)
    return cond()


def test_the_two_router_mesh_carries_light_telemetry_and_commands(mesh: RouterMesh) -> None:
    """`fleetlink field --light 5` on router A; an operator link on router B."""
    from fleetlink.links.zenoh import ZenohEndpoint

    fleet = subprocess.Popen(
        [sys.executable, "-m", "fleetlink.cli.main", "field", "--light", "5", "--zenoh-connect", mesh.a.listen,
         "--duration", "30"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    clock = SystemClock()
    console = ZenohEndpoint(connect=[mesh.b.listen], mode="client", label="zenoh-console")
    link = OperatorLink(clock, "op-a", console, NoLink())  # type: ignore[arg-type]
    heard: list[wire.Message] = []
    present: set[str] = set()
    lock = threading.Lock()

    def sink(msg: wire.Message, _link: str, _now: float) -> None:
        with lock:
            heard.append(msg)

    link.add_sink(sink)
    link.add_presence_sink(lambda robot, _l, alive, _w: present.add(robot) if alive else present.discard(robot))
    link.start()
    try:
        names = set(light_names(5))

        def robots(cls: type[wire.Message]) -> set[str]:
            with lock:
                return {m.header.robot for m in heard if isinstance(m, cls)}

        assert wait_for(lambda: robots(Pose) == names and robots(State) == names, 20.0), robots(Pose)
        assert wait_for(lambda: present == names)
        x0 = max(m.x for m in heard if isinstance(m, Pose) and m.header.robot == "L0003")
        sent = link.send(Teleop, "L0003", v=0.5, omega=0.0, ttl_s=1.0)

        def acked() -> list[Ack]:
            with lock:
                return [m for m in heard if isinstance(m, Ack) and m.commandHeaderId == sent.header.headerId]

        assert wait_for(lambda: bool(acked()))
        first, *copies = [(a.result, a.link, a.commandSender) for a in acked()]
        assert first == (AckResult.ACCEPTED, LinkName.ZENOH, "op-a")
        # An ack later than the link's ack timeout (0.25 s, a loaded machine) has the command sent
        # again: that copy is acked as a duplicate, never run twice.
        assert all(c == (AckResult.DUPLICATE, LinkName.ZENOH, "op-a") for c in copies), copies
        assert wait_for(
            lambda: any(isinstance(m, Pose) and m.header.robot == "L0003" and m.x > x0 + 0.1 for m in list(heard))
        )
        assert wait_for(lambda: any(isinstance(m, Lease) and m.holder == "op-a" for m in list(heard)))
    finally:
        link.close()
        fleet.terminate()
        fleet.wait(10)
    assert fleet.returncode == 0


def test_deploys_mesh_configs_route_between_their_clients() -> None:
    """deploy/zenohd-mesh-{a,b}.json5 (ports rewritten) run as routers: a put on A reaches B's client."""
    from pathlib import Path

    from fleetlink.links.zenoh import open_session
    from fleetlink.site.brokers import free_port
    from fleetlink.site.mesh import ZenohRouter

    deploy = Path(__file__).resolve().parent.parent / "deploy"
    ep_a, ep_b = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    with (
        ZenohRouter(ep_a, config=deploy / "zenohd-mesh-a.json5"),
        ZenohRouter(ep_b, [ep_a], config=deploy / "zenohd-mesh-b.json5"),
    ):
        robot = open_session(connect=[ep_a], mode="client")
        console = open_session(connect=[ep_b], mode="client")
        got: list[str] = []
        try:
            console.declare_subscriber("fleetlink/v1/*/pose", lambda s: got.append(str(s.key_expr)))
            assert wait_for(lambda: (robot.put("fleetlink/v1/r1/pose", b"x"), bool(got))[1], 10.0)
        finally:
            console.close()
            robot.close()
    assert got[0] == "fleetlink/v1/r1/pose"


def test_a_full_agent_and_light_robots_on_router_a_are_driven_from_router_b(mesh: RouterMesh) -> None:
    """A real agent (the real-time field's robot over TCP) and three light robots, all clients of
    router A; the operator link on router B drives the agent and sees everyone."""
    from fleetlink.field.light_runner import open_light_fleet
    from fleetlink.field.realtime import RealtimeField
    from fleetlink.links.zenoh import ZenohEndpoint
    from fleetlink.site.agents import FieldAgents
    from tests.test_field_realtime import quiet_scenario

    clock = SystemClock()
    field = RealtimeField(quiet_scenario(lidar={"enabled": False}), clock=clock)
    agents = light = None
    link = OperatorLink(
        clock,
        "op-a",
        ZenohEndpoint(connect=[mesh.b.listen], mode="client"),
        NoLink(),  # type: ignore[arg-type]
    )
    heard: list[wire.Message] = []
    link.add_sink(lambda msg, _l, _n: heard.append(msg))
    try:
        endpoints = field.start()
        agents = FieldAgents(endpoints, clock=clock, zenoh_connect=[mesh.a.listen], zenoh_mode="client")
        agents.start()
        light = open_light_fleet(3, clock, connect=[mesh.a.listen], mode="client")
        link.start()
        everyone = {"uvc-1", *light_names(3)}
        assert wait_for(lambda: {m.header.robot for m in list(heard) if isinstance(m, Pose)} == everyone, 20.0)
        (body,) = field.world.robots
        x0, y0 = body.pose[0], body.pose[1]
        acks_before = len([m for m in list(heard) if isinstance(m, Ack)])

        def drive() -> bool:
            link.send(Teleop, "uvc-1", v=0.2, omega=0.0, ttl_s=0.5)
            return math.hypot(body.pose[0] - x0, body.pose[1] - y0) > 0.1

        assert wait_for(drive, 20.0)
        agent_acks = [m for m in list(heard) if isinstance(m, Ack) and m.header.robot == "uvc-1"]
        assert len(agent_acks) > acks_before
        # Re-sent copies (an ack later than the link's 0.25 s timeout, on a loaded machine) are acked
        # as duplicates; nothing is refused.
        results = [(a.result, a.reason) for a in agent_acks]
        assert all(r in (AckResult.ACCEPTED, AckResult.DUPLICATE) for r, _ in results), results
        assert any(r is AckResult.ACCEPTED for r, _ in results)
    finally:
        link.close()
        if light is not None:
            light.close()
        if agents is not None:
            agents.stop()
        field.stop()
