"""FieldAgents: an agent per robot of the real-time field, over its boards on TCP; teleop over Zenoh moves one."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh

from fleetlink.agent.runtime import AgentRuntime
from fleetlink.field.realtime import RealtimeField
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Teleop
from fleetlink.site.agents import FieldAgents
from tests.harness import wait_until
from tests.harness.mosquitto import MosquittoBroker, free_port
from tests.harness.zenoh_peers import zenoh_config
from tests.test_field_realtime import quiet_scenario


@contextlib.contextmanager
def two_agents(**agents_kw: Any) -> Iterator[tuple[RealtimeField, zenoh.Session, dict[str, AgentRuntime]]]:
    """The field's two disinfection robots, idle, lidars off, and an agent each whose Zenoh session
    connects to the operator's, which listens (as the console does); ``agents_kw`` go to FieldAgents."""
    clock = SystemClock()
    scenario = quiet_scenario(
        robots=[
            {"name": "uvc-1", "start": "living", "drive": "idle"},
            {"name": "uvc-2", "start": "bedroom", "drive": "idle"},
        ],
        lidar={"enabled": False},
    )
    field = RealtimeField(scenario, clock=clock)
    listen = f"tcp/127.0.0.1:{free_port()}"
    session = None
    agents = None
    try:
        endpoints = field.start()
        session = zenoh.open(zenoh_config(listen=[listen]))
        agents = FieldAgents(endpoints, clock=clock, zenoh_connect=[listen], **agents_kw)
        yield field, session, agents.start()
    finally:
        if agents is not None:
            agents.stop()
        if session is not None:
            session.close()
        field.stop()


def test_field_agents_drive_the_field_robots_over_zenoh() -> None:
    with two_agents(operators=("op-test",)) as (field, session, running):
        clock = SystemClock()
        assert set(running) == {"uvc-1", "uvc-2"}
        wait_until(
            lambda: all(a.board.snapshot.connected and a.zenoh is not None and a.zenoh.up for a in running.values()),
            message="every agent on its board and on zenoh",
        )
        # Each names the other its peer (planned around where it stands: agent/peers.py).
        assert running["uvc-1"].config.peers == ("uvc-2",) and running["uvc-2"].config.peers == ("uvc-1",)
        robots = {r.name: r for r in field.world.robots}
        start = {name: r.pose for name, r in robots.items()}
        op = wire.HeaderCounter(clock, robot="uvc-1", sender="op-test")

        def moved(name: str) -> float:
            a, b = start[name], robots[name].pose
            return math.hypot(b[0] - a[0], b[1] - a[1])

        def drive() -> bool:
            session.put(
                keys.sender_key("uvc-1", "teleop", "op-test"), wire.encode(op.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5))
            )
            return moved("uvc-1") > 0.1

        wait_until(drive, interval=0.1, message="uvc-1 to move under teleop over zenoh")
        assert moved("uvc-2") < 0.01  # the other robot was not addressed


@pytest.mark.slow
def test_field_agent_maps_with_the_field_lidar_and_serves_the_map_over_zenoh() -> None:
    from fleetlink.agent.mapping.share import fetch_map
    from fleetlink.links.zenoh import ZenohEndpoint
    from fleetlink.shared.map_codec import decode_cells

    clock = SystemClock()
    field = RealtimeField(quiet_scenario(), clock=clock)  # one robot, its lidar at 10 Hz over TCP
    listen = f"tcp/127.0.0.1:{free_port()}"
    session = None
    asker: ZenohEndpoint | None = None
    agents = None
    try:
        endpoints = field.start()
        assert endpoints["uvc-1"].lidar is not None
        session = zenoh.open(zenoh_config(listen=[listen]))
        agents = FieldAgents(endpoints, clock=clock, zenoh_connect=[listen])
        agent = agents.start()["uvc-1"]
        wait_until(lambda: agent.scans >= 15, timeout=20.0, message="lidar scans into the mapper")
        assert agent._lidar is not None and agent._lidar.background  # mapping gives way to control

        asker = ZenohEndpoint(session=session)  # fetch_map asks through a link (the session stays ours)
        asker.start()

        def occupied() -> int:
            snap = fetch_map(asker, "uvc-1", timeout=2.0)
            if snap is None:
                return 0
            cells = decode_cells(snap.cells, snap.width, snap.height)
            return int((cells >= 65).sum())

        wait_until(lambda: occupied() > 50, timeout=10.0, interval=0.5, message="a map with walls from a get")
        # The map also reaches the pilot: go-tos now follow A* waypoints over it.
        wait_until(lambda: agent.core.pilot.path_provider is not None, message="a planner in the pilot")
        with agent._lock:
            pose = agent.core.fusion.map_pose()
            x, y = pose.x, pose.y
            route = agent.core.pilot.path_provider((x, y), (x + 0.5, y))
        assert route and route[-1] == (x + 0.5, y)

        # Standing still, the planner is not rebuilt although the map keeps changing (keyframes)...
        def planner() -> object:
            provider = agent.core.pilot.path_provider
            return getattr(provider, "__self__", None)

        first, version = planner(), agent.mapper.grid.version
        wait_until(lambda: agent.mapper.grid.version > version, timeout=10.0, message="a new keyframe in the map")
        scans = agent.scans
        wait_until(lambda: agent.scans >= scans + 3, message="three more turns mapped")
        assert planner() is first
        # ... while driving it is renewed (every PLANNER_PERIOD while the map changes).
        op = wire.HeaderCounter(clock, robot="uvc-1", sender="op-test")

        def spin() -> bool:
            session.put(
                keys.sender_key("uvc-1", "teleop", "op-test"), wire.encode(op.make(Teleop, v=0.0, omega=0.6, ttl_s=0.5))
            )
            return planner() is not first

        wait_until(spin, timeout=10.0, interval=0.1, message="a new planner while the robot turns")
    finally:
        if agents is not None:
            agents.stop()
        if asker is not None:
            asker.close()
        if session is not None:
            session.close()
        field.stop()


def test_field_agents_hear_each_others_poses_on_the_broker(mosquitto: MosquittoBroker) -> None:
    """Each agent hears the other's pose, as the demo wires them: their Zenoh sessions are peers of
    the operator's, which passes nothing between peers, so the poses come over MQTT (every second
    pose while Zenoh is up); a site's router carries them over Zenoh too (tests/test_deploy.py)."""
    with two_agents(mqtt_url=mosquitto.url) as (_, _, running):
        wait_until(
            lambda: all(a.core.peers.heard_from() == a.config.peers for a in running.values()),
            message="every agent hearing the other's pose",
        )
        assert {name: a.config.peers for name, a in running.items()} == {"uvc-1": ("uvc-2",), "uvc-2": ("uvc-1",)}
        assert all(sum(a.core.gate.stats.rejected.values()) == 0 for a in running.values())
