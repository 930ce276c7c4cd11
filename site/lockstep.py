"""Whole agents in lockstep: a scenario run with every robot's real agent, in simulated time.

``MissionRun(scenario)`` composes, on one ``SimClock`` and one thread:

* the field (``FieldRun`` with ``open_loop=False``): physics, scripted events, ground truth, each
  robot's simulated board and RPLIDAR;
* an agent per robot (``AgentNode``): its ``BoardSession`` speaks Control Bus bytes to the board
  over an in-process port, its ``LidarFeed`` reads RPLIDAR bytes from the device, and its core,
  pilot, fusion, guard, map keeper and planner run exactly as on a robot;
* the UWB gateway's core (positioning/gateway.py), fed with the truth, publishing fixes;
* two in-process links (``InProcessBus``), Zenoh and MQTT, carrying the same wire bytes as the real
  ones, pumped between steps;
* with ``fleet_map``, the console's fleet map service (site/fleetmap.py) on the operator's Zenoh
  link, as the demo's console runs it: its map follower kept current by the robots' patches, the
  snapshots it wants fetched and the fleet map built every ``FLEET_MAP_PERIOD_S``; its frames
  (``FleetFrames``) reach the agents, which put peers mapping in their own frames into their own
  with them (agent/peers.py);
* a scripted operator (``ScriptedOperator``) that sends what the scenario's events ask for
  (teleop bursts, goals, instant actions, marks), turns a robot's ``script`` into teleop and sends a
  wandering robot to its plan's named places one after another (without UWB, as the robot's own map
  has them: its frame begins where the robot started), or, for a mission script, a round of places
  each sent once the last goal ended (``visit``); it sends on Zenoh, and on MQTT while its Zenoh link
  is cut (the fallback).

Every step runs in a fixed order (events, physics, radio, links, each agent: board, control, lidar;
UWB; links; truth), every random stream is seeded from the scenario, and time comes only from the
clock, so the same scenario and seed give byte-identical truth and agent logs.

The radio (field/radio.py): when the plan has access points or dead zones, every step takes each
robot's true pose and cuts its agent's endpoint on a bus (reason ``"radio"``) while that link does
not reach it, restoring it when it does again; a scenario's own ``link`` cuts are another reason on
the same endpoint, so either keeps it cut. ``contact[robot]`` lists the (t_lost, t_regained) spans
in which neither of the robot's links was up, for whatever reason (t_regained None: still lost);
``write_mission_outputs`` writes them to ``contact.csv``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import random
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack

from fleetlink.agent.board.session import BoardSession, PollRates
from fleetlink.agent.config import AgentConfig
from fleetlink.agent.lidar.driver import LidarDriver
from fleetlink.agent.mapping.keeper import MapKeeper
from fleetlink.agent.mapping.mapper import MapperConfig
from fleetlink.agent.mapping.share import MapShare, fetch_map
from fleetlink.agent.mapping.worker import DeferredKeeper, MapWorker
from fleetlink.agent.node import POLL_RATES, AgentNode, LidarFeed, mapper_config
from fleetlink.devices.controlbus.snapshot import BoardSnapshot
from fleetlink.devices.ports import InProcessPort
from fleetlink.field.build import robot_seed
from fleetlink.field.lockstep import FieldRun, RunResult, write_outputs
from fleetlink.field.plans import FloorPlan, load_plan
from fleetlink.field.radio import LINKS, ContactLog, FleetRadio, RadioModel
from fleetlink.field.scenario import Scenario
from fleetlink.links.inprocess import InProcessBus, InProcessLink
from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.maps import MapFetcher, MapFollower
from fleetlink.shared import keys, wire
from fleetlink.shared.messages import (
    Action,
    ActionType,
    Event,
    Goal,
    InstantActions,
    LinkName,
    MapUpdate,
    Mark,
    Order,
    Teleop,
)
from fleetlink.shared.se2 import relative
from fleetlink.site.agents import field_limits, field_peers, field_uv
from fleetlink.site.fleetmap import FleetMapService

__all__ = [
    "SESSION_POLL",
    "MissionResult",
    "MissionRun",
    "ScriptedOperator",
    "drive_by_session",
    "write_mission_outputs",
]

OPERATOR = "operator-1"
TELEOP_PERIOD_S = 0.25
"""An operator holding a key: one Teleop every quarter second (the console's key repeat)."""
TELEOP_TTL_S = 0.5
WANDER_GOAL_TIMEOUT_S = 60.0
"""A wandering robot that has neither reached nor failed its goal by then gets the next one."""
GOAL_ENDS = ("goal_reached", "goal_failed", "goal_cancelled")
"""The events that end a go-to (``visit`` waits for one about its order)."""
UWB_START_S = 0.0
FLEET_MAP_PERIOD_S = 2.0
"""How often the console's map fetcher polls, each poll followed by a build of its fleet map service
(the console polls every 0.5 s, and its service builds at most every 2 s: site/fleetmap.py)."""
RADIO_CUT = "radio"
"""The reason the radio cuts an agent's endpoint on a bus (a scenario's cuts are another)."""


@dataclass(slots=True)
class MissionResult:
    field: RunResult
    logs: dict[str, list[str]]
    """Per robot: every message on either link about it, one line each (time, link, topic, body)."""
    acks: list[Any]
    events: list[Any]
    poses: dict[str, Any]
    """The last pose each robot published."""
    commands: list[str]
    """What the operator sent, one line each."""
    contact: dict[str, list[tuple[float, float | None]]] = dataclasses.field(default_factory=dict)
    """Per robot: (t_lost, t_regained) while neither link reached it (t_regained None: lost at the end)."""

    @property
    def real_time_factor(self) -> float:
        return self.field.real_time_factor


class ScriptedOperator:
    """An operator without a screen: sends commands as wire messages, reads what the robots say."""

    def __init__(self, name: str, zenoh: InProcessLink, mqtt: InProcessLink, now: Callable[[], float]) -> None:
        self.name = name
        self.zenoh, self.mqtt = zenoh, mqtt
        self._now = now
        self._counters: dict[str, wire.HeaderCounter] = {}
        self.clock: Any = None
        self.sent: list[str] = []
        self.acks: list[Any] = []
        self.events: list[Any] = []
        self.poses: dict[str, Any] = {}
        self.states: dict[str, Any] = {}
        """The latest ``State`` from each robot (its order's progress among it)."""
        self.on_event: Callable[[Any], None] | None = None
        for link in (zenoh, mqtt):
            link.start()
            link.subscribe(keys.zenoh_all_robots("ack"), self._ack)
            link.subscribe(keys.zenoh_all_robots("events"), self._event)
            link.subscribe(keys.zenoh_all_robots("state"), self._state)
        zenoh.subscribe(keys.zenoh_all_robots("pose"), self._pose)
        self._seen: set[tuple[str, str, int]] = set()

    def counter(self, robot: str) -> wire.HeaderCounter:
        if robot not in self._counters:
            self._counters[robot] = wire.HeaderCounter(self.clock, robot=robot, sender=self.name)
        return self._counters[robot]

    def send(self, cls: type[wire.Message], robot: str, **fields: Any) -> wire.Message:
        msg = self.counter(robot).make(cls, **fields)
        data = wire.encode(msg)
        link = self.zenoh if self.zenoh.up else self.mqtt
        link.publish(wire.key_of(msg), data)
        self.sent.append(f"{self._now():.3f} {link.name.value} {robot} {msg.TOPIC} {_summary(msg)}")
        return msg

    def teleop(self, robot: str, v: float, omega: float) -> None:
        self.send(Teleop, robot, v=v, omega=omega, ttl_s=TELEOP_TTL_S)

    def goal(self, robot: str, x: float, y: float, theta: float | None, order_id: str) -> None:
        self.send(Order, robot, orderId=order_id, orderUpdateId=0, goal=Goal(x=x, y=y, theta=theta), returnHome=False)

    def action(self, robot: str, kind: ActionType, action_id: str) -> None:
        action = Action(actionId=action_id, actionType=kind, actionParameters=())
        self.send(InstantActions, robot, actions=(action,))

    def mark(self, robot: str, x: float, y: float, kind: str, label: str, mark_id: str) -> None:
        self.send(Mark, robot, markId=mark_id, x=x, y=y, label=label, kind=kind, sd_m=0.0, removed=False)

    # -- what the robots say (each message once, though it may come on both links) -------------------

    def _fresh(self, msg: wire.Message) -> bool:
        k = (msg.header.robot, msg.TOPIC, msg.header.headerId)
        if k in self._seen:
            return False
        self._seen.add(k)
        return True

    def _ack(self, key: str, payload: bytes) -> None:
        msg = wire.decode_key(key, payload)
        if self._fresh(msg):
            self.acks.append(msg)

    def _event(self, key: str, payload: bytes) -> None:
        msg = wire.decode_key(key, payload)
        if self._fresh(msg):
            self.events.append(msg)
            if self.on_event is not None:
                self.on_event(msg)

    def _state(self, key: str, payload: bytes) -> None:
        msg = wire.decode_key(key, payload)
        last = self.states.get(msg.header.robot)
        # The same State comes on both links, and the MQTT copy of an older one may come after a newer one.
        if self._fresh(msg) and (last is None or msg.header.headerId > last.header.headerId):
            self.states[msg.header.robot] = msg

    def _pose(self, key: str, payload: bytes) -> None:
        msg = wire.decode_key(key, payload)
        self.poses[msg.header.robot] = msg


@dataclass(slots=True)
class _Robot:
    name: str
    index: int
    node: AgentNode
    lidar: LidarFeed | None
    next_session: float = 0.0
    next_control: float = 0.0
    next_lidar: float = 0.0
    teleop: tuple[float, float] | None = None
    teleop_until: float = -math.inf
    next_teleop: float = 0.0
    script: tuple[tuple[float, float, float], ...] = ()
    wander: bool = False
    wander_goal_at: float = -math.inf
    own_frame: tuple[float, float, float] | None = None
    """Without UWB (the scenario's ``uwb`` off, or fewer than three anchors): the site pose the robot
    started from, where its map's own frame begins; the scripted operator picks places on that map, as a
    person at the console would."""
    log: list[str] = field(default_factory=list)


class MissionRun:
    def __init__(
        self,
        scenario: Scenario,
        plan: FloorPlan | None = None,
        *,
        mapping: bool = True,
        record: bool = True,
        map_worker: bool | None = None,
        mapper: MapperConfig | None = None,
        fleet_map: bool = False,
    ) -> None:
        """``mapping``: agents with a lidar build and share their onboard maps (as on a robot);
        ``record``: keep every message about each robot for the agent logs; ``map_worker``: the
        keepers run in a second process (None: when there are two cores and two robots mapping).
        Either way a turn's map update reaches its agent with the next turn (agent/mapping/worker.py),
        so the outputs do not depend on ``map_worker``. ``mapper``: every agent's mapping configuration
        instead of its own (``mapper_config``; a benchmark's variant). ``fleet_map``: run the console's
        fleet map service (``self.fleet_map``) on the operator's Zenoh link."""
        self._mapper = mapper
        self._mapping = mapping
        self.scenario = scenario
        self.plan = plan or load_plan(scenario.plan)
        self.field = FieldRun(scenario, self.plan, open_loop=False, on_command=self._command)
        self.clock = self.field.clock
        self.zenoh = InProcessBus(LinkName.ZENOH, clock_now=self.clock.now)
        self.mqtt = InProcessBus(LinkName.MQTT, clock_now=self.clock.now)
        self.record = record
        self.operator = ScriptedOperator(
            OPERATOR, self.zenoh.endpoint(OPERATOR), self.mqtt.endpoint(OPERATOR), self.clock.now
        )
        self.operator.clock = self.clock
        self.operator.on_event = self._robot_event
        self.robots: list[_Robot] = []
        self._rng = random.Random(scenario.seed)
        self._places = sorted(self.plan.starts.items())
        self._ids = 0
        mappers = sum(1 for rig in self.field.rigs if rig.device is not None) if mapping else 0
        if map_worker is None:
            map_worker = (os.cpu_count() or 1) > 1 and mappers > 1
        self.map_worker = MapWorker() if map_worker and mappers else None
        for rig in self.field.rigs:
            self.robots.append(self._agent(rig.robot.index, mapping))
        model = RadioModel.from_plan(self.plan)
        self.radio: FleetRadio | None = None
        """Each robot's links under the plan's radio model (None: the plan has none; reachable everywhere)."""
        if model.enabled:
            self.radio = FleetRadio(model, {r.name: self._true_xy(r) for r in self.robots})
            for r in self.robots:
                for link in LINKS:
                    self._radio_link(r.name, link)
        self.contact_log = ContactLog(r.name for r in self.robots)
        self._radio_step(self.clock.now(), update_radio=False)
        self.uwb = self._uwb_gateway()
        self._next_uwb = UWB_START_S
        if self.uwb is None:
            for r, rig in zip(self.robots, self.field.rigs, strict=True):
                st = rig.robot.board.state
                r.own_frame = (st.x, st.y, st.theta)
        if record:
            for bus in (self.zenoh, self.mqtt):
                tap = bus.endpoint(f"recorder-{bus.name.value}")
                tap.start()
                tap.subscribe("fleetlink/v1/**", self._recorder(bus.name))
        self.fleet_map: FleetMapService | None = None
        """The console's fleet map service, with ``fleet_map`` (its ``result``: the fleet map built)."""
        self._next_fleet_map = 0.0
        self._map_fetcher: MapFetcher | None = None
        if fleet_map:
            # As the console wires it (cli/console.py): its map follower kept current by the robots'
            # patches, its fetcher taking the snapshots the follower wants, then a build.
            op_link = self.operator.zenoh
            share = MapShare(op_link, keys.FLEET_MAP, self.clock, sender=OPERATOR)
            share.start()
            follower = MapFollower(FleetModel(OPERATOR))
            for r in self.robots:
                follower.fleet.robot(r.name)  # (the console knows them from their poses)
            lock = threading.Lock()
            self.fleet_map = FleetMapService(follower, lock, self.clock, share=share, query=op_link)
            op_link.subscribe(f"{keys.PREFIX}/*/{MapUpdate.TOPIC}", self._map_update)
            self._map_fetcher = MapFetcher(
                follower,
                lambda robot: fetch_map(op_link, robot, timeout=0.0),
                self.clock,
                lock,
                period_s=FLEET_MAP_PERIOD_S,
                after_poll=self.fleet_map.step,
            )
        self.field.controllers.append(self._step_agents)

    # -- composition --------------------------------------------------------------------------------

    def _agent(self, index: int, mapping: bool) -> _Robot:
        rig = self.field.rigs[index]
        spec = rig.spec
        name = spec.name
        lidar_url = f"inprocess://{name}/lidar" if rig.device is not None else None
        config = AgentConfig(
            robot=name,
            board=f"inprocess://{name}/board",
            lidar=lidar_url,
            tag=name,
            uv=field_uv(name),
            limits=field_limits(name),
            peers=field_peers(name, [r.spec.name for r in self.field.rigs]),
        )
        peer = self.field.board_peer(index)
        session = BoardSession(
            lambda: InProcessPort(peer, advance_clock=False),
            self.clock,
            rates=POLL_RATES,
            seed=robot_seed(self.scenario, index),
        )
        zenoh = self.zenoh.endpoint(f"agent-{name}")
        mqtt = self.mqtt.endpoint(f"agent-{name}")
        node = AgentNode(config, self.clock, session, links=[zenoh, mqtt], map_link=zenoh if mapping else None)
        node.subscribe()
        zenoh.start()
        mqtt.start()
        feed = None
        if rig.device is not None and mapping:
            mapping_config = self._mapper or mapper_config(config)
            node.open_map(
                self.map_worker.keeper(name, mapping_config)
                if self.map_worker is not None
                else DeferredKeeper(MapKeeper(mapping_config))
            )

            def open_driver(index: int = index) -> LidarDriver:
                return LidarDriver(self.field.lidar_port(index), self.clock, pwm_motor_control=True)

            feed = LidarFeed(node, open_driver)
        robot = _Robot(name, index, node, feed)
        if spec.drive == "script":
            robot.script = tuple(spec.script)
        robot.wander = spec.drive == "wander" and bool(self._places)
        return robot

    def restart_agent(self, robot: str) -> None:
        """``robot``'s agent stops and starts again, as a process restarted by systemd: its links, board
        session and lidar driver closed and opened afresh, everything it held in memory (its map, its
        pose, its peers) lost, its map begun again where the robot stands. The simulated hardware goes
        on (the board's link watchdog stops the wheels while no agent speaks to it)."""
        i = next((k for k, r in enumerate(self.robots) if r.name == robot), None)
        if i is None:
            raise ValueError(f"no robot {robot!r} in this run")
        old = self.robots[i]
        if old.lidar is not None:
            old.lidar.close()
        old.node.close()
        old.node.board.stop()
        for link in old.node.links:
            link.close()
        if self.map_worker is not None:
            self.map_worker.forget(robot)
        new = self._agent(old.index, self._mapping)
        if old.own_frame is not None:  # the new map's own frame begins where it stands now
            st = self.field.rigs[old.index].robot.board.state
            new.own_frame = (st.x, st.y, st.theta)
        new.wander, new.log = old.wander, old.log
        self.robots[i] = new
        self.field.events.log.append(f"t={self.clock.now():.3f} s: {robot}'s agent restarted")

    def _uwb_gateway(self) -> Any:
        from fleetlink.positioning.anchors import Anchor
        from fleetlink.positioning.config import GatewayConfig
        from fleetlink.positioning.gateway import GatewayCore

        sc, plan = self.scenario, self.plan
        anchors = tuple(Anchor(*a) for a in sc.uwb_anchors(plan.anchors))
        if len(anchors) < 3:
            return None
        config = GatewayConfig(
            anchors=anchors, auto_tags=True, walls=plan.segments(), gateway_id="field-uwb", seed=sc.seed
        )
        self._uwb_link = self.mqtt.endpoint("field-uwb")
        self._uwb_link.start()
        return GatewayCore(config)

    # -- running ------------------------------------------------------------------------------------------

    def run(self, duration: float | None = None) -> MissionResult:
        wall0 = time.perf_counter()
        result = self.field.run(duration)
        result.wall_seconds = time.perf_counter() - wall0
        for r in self.robots:
            result.stats[r.name].update(
                {
                    "agent_scans": r.node.scans,
                    "published": r.node.published,
                    "board_connects": r.node.board.snapshot.connects,
                    "board_requests": r.node.board.client.stats.requests if r.node.board.client else None,
                }
            )
            result.stats[r.name]["out_of_contact_s"] = self.contact_log.lost_seconds(r.name, result.sim_seconds)
        return MissionResult(
            field=result,
            logs={r.name: r.log for r in self.robots},
            acks=self.operator.acks,
            events=self.operator.events,
            poses=dict(self.operator.poses),
            commands=self.operator.sent,
            contact=self.contact,
        )

    def visit(
        self, robot: str, places: Sequence[str], *, step_s: float = 5.0, until_s: float = math.inf
    ) -> list[tuple[str, str | None]]:
        """The operator's round: ``robot`` sent to each of the plan's named ``places`` in turn, each goal
        sent once the last one ended, as a person at the console sends them: on the robot's own map
        without UWB (its frame begins where it started, or where its agent last restarted). The field
        runs ``step_s`` at a time until the robot says how that order ended (``"goal_reached"``,
        ``"goal_failed"`` or ``"goal_cancelled"``) or until ``until_s`` (simulated); from then on
        nothing more is sent. Each place with how its goal ended (None: still going at ``until_s``, or
        never sent)."""
        if not any(r.name == robot for r in self.robots):
            raise ValueError(f"no robot {robot!r} in this run")
        outcomes: list[tuple[str, str | None]] = []
        t = self.clock.now()
        for place in places:
            if t >= until_s:
                outcomes.append((place, None))
                continue
            r = next(r for r in self.robots if r.name == robot)  # a restarted agent's frame is its new one
            x, y, _ = self.plan.starts[place]
            order = self._id("visit")
            seen = len(self.operator.events)
            self.operator.goal(robot, *_on_map(r, x, y), None, order)
            outcome: str | None = None
            while outcome is None and t < until_s:
                t = min(until_s, t + step_s)
                self.run(t)
                events, seen = self.operator.events[seen:], len(self.operator.events)
                for e in events:
                    if e.header.robot == robot and e.kind in GOAL_ENDS and _order_of(e) == order:
                        outcome = e.kind
                        break
            outcomes.append((place, outcome))
        return outcomes

    def close(self) -> None:
        for r in self.robots:
            if r.lidar is not None:
                r.lidar.close()
            r.node.close()
            r.node.board.stop()
        if self.map_worker is not None:
            self.map_worker.close()
            self.map_worker = None
        self.field.close()

    def __enter__(self) -> MissionRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the radio and contact ----------------------------------------------------------------------

    @property
    def contact(self) -> dict[str, list[tuple[float, float | None]]]:
        """Per robot: (t_lost, t_regained) spans with neither link up (t_regained None: still lost)."""
        return self.contact_log.intervals

    def reachable(self, robot: str, link: LinkName) -> bool:
        """Is the robot's agent on ``link`` now (neither the radio nor the scenario cuts it)?"""
        bus = self.zenoh if link is LinkName.ZENOH else self.mqtt
        return f"agent-{robot}" not in bus.cut_endpoints

    def _true_xy(self, r: _Robot) -> tuple[float, float]:
        st = self.field.rigs[r.index].robot.board.state
        return st.x, st.y

    def _radio_link(self, robot: str, link: LinkName) -> None:
        assert self.radio is not None
        bus = self.zenoh if link is LinkName.ZENOH else self.mqtt
        (bus.restore if self.radio.reachable(robot, link) else bus.cut)(f"agent-{robot}", RADIO_CUT)

    def _radio_step(self, t: float, update_radio: bool = True) -> None:
        """Each robot's links at its true pose; its contact (a link up, whatever cut the others)."""
        for r in self.robots:
            if self.radio is not None and update_radio:
                x, y = self._true_xy(r)
                for link in self.radio.update(r.name, x, y):
                    self._radio_link(r.name, link)
                    reach = "in radio reach" if self.radio.reachable(r.name, link) else "out of radio reach"
                    self.field.events.log.append(f"t={t:.3f} s: {r.name} {link.value} {reach} at ({x:.2f}, {y:.2f})")
            in_contact = self.reachable(r.name, LinkName.ZENOH) or self.reachable(r.name, LinkName.MQTT)
            self.contact_log.update(r.name, t, in_contact)

    def _step_agents(self, t: float) -> None:
        """After the physics at ``t``: the radio, links, every agent in order, UWB, the operator, links again."""
        self._radio_step(t)
        self._pump()
        for r in self.robots:
            node = r.node
            if t >= r.next_session or node.board.urgent:
                r.next_session = node.board.tick()
            if t >= r.next_control:
                r.next_control = node.control(t)
                if node.board.urgent:  # a new velocity goes to the board in the same step
                    r.next_session = node.board.tick()
            if r.lidar is not None and t >= r.next_lidar:
                r.next_lidar = r.lidar.step(t)
        if self.uwb is not None and t >= self._next_uwb:
            self._next_uwb += 1.0 / self.uwb.config.rate_hz
            for rig in self.field.rigs:
                st = rig.robot.board.state
                self.uwb.on_truth(rig.spec.name, st.x, st.y, t, st.theta, st.true_v)
            for pub in self.uwb.tick(t, self.clock.wall()):
                self._uwb_link.publish(pub.topic, pub.payload)
        self._operate(t)
        if self.fleet_map is not None and t >= self._next_fleet_map:
            self._next_fleet_map = t + FLEET_MAP_PERIOD_S
            self._build_fleet_map()
        self._pump()

    def _map_update(self, key: str, payload: bytes) -> None:
        """A robot's map patch heard on the operator's Zenoh link: to the console's map follower."""
        assert self.fleet_map is not None
        try:
            msg = wire.decode_key(key, payload)
        except wire.WireError:
            return  # (the console's feed counts what does not decode; the agents here send none)
        if isinstance(msg, MapUpdate):
            self.fleet_map.follower.on_update(msg)

    def _build_fleet_map(self) -> None:
        """What the console's map fetcher does at each poll: the snapshots its follower wants (a robot
        not fetched yet, a copy a patch did not follow) fetched over the operator's Zenoh link, then a
        build (which fetches the submaps it lacks and publishes the frames on the same link)."""
        assert self._map_fetcher is not None
        self._map_fetcher.poll()

    def _pump(self) -> None:
        # A command and its ack cross in one pump; telemetry published on both links interleaves
        # deterministically: Zenoh first, then MQTT, until both are quiet.
        while self.zenoh.deliver() + self.mqtt.deliver():
            pass

    # -- the scripted operator --------------------------------------------------------------------------

    def _operate(self, t: float) -> None:
        op = self.operator
        for r in self.robots:
            if t < r.next_teleop:
                continue
            command = None
            if r.teleop is not None and t < r.teleop_until:
                command = r.teleop
            elif r.teleop is not None:
                r.teleop = None
                command = (0.0, 0.0)  # the burst ends: the key is released
            elif r.script:
                command = _scripted(r.script, t)
            if command is not None:
                r.next_teleop = t + TELEOP_PERIOD_S
                op.teleop(r.name, *command)
            if r.wander and t >= r.wander_goal_at:
                self._next_wander_goal(r, t)

    def _next_wander_goal(self, r: _Robot, t: float) -> None:
        _, (x, y, _th) = self._places[self._rng.randrange(len(self._places))]
        r.wander_goal_at = t + WANDER_GOAL_TIMEOUT_S
        self.operator.goal(r.name, *_on_map(r, x, y), None, self._id("wander"))

    def _robot_event(self, ev: Event) -> None:
        if ev.kind in ("goal_reached", "goal_failed"):
            r = next((r for r in self.robots if r.name == ev.header.robot), None)
            if r is not None and r.wander:
                r.wander_goal_at = self.clock.now()  # the next goal at the next step

    def _command(self, event: Any, t: float) -> None:
        """A scenario event the field hands on: operator commands and network links."""
        kind, op = event.kind, self.operator
        r = next((r for r in self.robots if r.name == getattr(event, "robot", None)), None)
        if kind == "teleop" and r is not None:
            r.teleop = (event.v, event.omega)
            r.teleop_until = t + event.duration
            r.next_teleop = t
        elif kind == "goal":
            op.goal(event.robot, event.x, event.y, event.theta, self._id("goal"))
        elif kind == "action":
            op.action(event.robot, event.action_type, self._id(event.action))
        elif kind == "mark":
            robot = event.robot or self.robots[0].name
            op.mark(robot, event.x, event.y, event.mark_kind, event.label, self._id("mark"))
        elif kind == "link":
            self._link(event.robot, event.link, event.state == "cut")
        elif kind == "agent_restart":
            self.restart_agent(event.robot)
        else:
            raise ValueError(f"event at {t:g} s: no way to carry out {kind!r} in a lockstep run")

    def _link(self, robot: str, link: str, cut: bool) -> None:
        who = robot if robot == OPERATOR else f"agent-{robot}"
        if link == "board":
            self.field._cut_link(robot, cut)
            return
        if link == "lidar":
            self.field.cut_lidar(robot, cut)
            return
        bus = self.zenoh if link == "zenoh" else self.mqtt
        (bus.cut if cut else bus.restore)(who)

    def _id(self, prefix: str) -> str:
        self._ids += 1
        return f"{prefix}-{self._ids}"

    # -- the agent logs -----------------------------------------------------------------------------------

    def _recorder(self, link: LinkName) -> Callable[[str, bytes], None]:
        by_name = {r.name: r for r in self.robots}

        def record(key: str, payload: bytes) -> None:
            parts = key.split("/")
            r = by_name.get(parts[2]) if len(parts) > 3 else None
            if r is None:
                return
            body = msgpack.unpackb(payload, raw=False)
            text = json.dumps(body, sort_keys=True, default=_blob)
            r.log.append(f"{self.clock.now():.3f} {link.value} {'/'.join(parts[3:])} {text}")

        return record


SESSION_POLL = PollRates(
    motion=20.0,
    motor=5.0,
    sensors=10.0,
    bumpers=10.0,
    status=0.5,
    power=0.0,
    health=1.0,
    payload=0.0,
    env=0.0,
    buttons=0.0,
    base_command=1.0,
    imu=0.0,
)
"""A hand-assembled driver's board polls: enough to drive, cheap enough for 50 robots."""

Drive = Callable[[BoardSnapshot, float], tuple[float, float]]


def _on_map(r: _Robot, x: float, y: float) -> tuple[float, float]:
    """A place of the plan (site frame) as the robot's map has it: without UWB, in its own frame."""
    if r.own_frame is not None:
        x, y, _ = relative(r.own_frame, (x, y, 0.0))
    return float(x), float(y)


def _order_of(event: Event) -> str | None:
    """The order an agent's event is about (its ``orderId`` datum), if any."""
    return next((kv.value for kv in event.data if kv.key == "orderId"), None)


def drive_by_session(run: FieldRun, index: int, drive: Drive, rates: PollRates = SESSION_POLL) -> BoardSession:
    """Drive robot ``index`` of a driven ``FieldRun`` (``open_loop=False``) through Control Bus bytes
    with a board session alone: ``drive(snapshot, t)`` gives the velocity at each session round.

    For benches and tests that assemble agent parts by hand (a pilot, a fusion); a whole agent is
    ``MissionRun``."""
    peer = run.board_peer(index)
    session = BoardSession(
        lambda: InProcessPort(peer, advance_clock=False), run.clock, rates=rates, seed=robot_seed(run.scenario, index)
    )
    due = [0.0]

    def controller(t: float) -> None:
        if t >= due[0]:
            session.set_velocity(*drive(session.snapshot, t))
            due[0] = session.tick()

    run.controllers.append(controller)
    return session


def _scripted(script: tuple[tuple[float, float, float], ...], t: float) -> tuple[float, float]:
    v = w = 0.0
    for at, sv, sw in script:
        if at > t:
            break
        v, w = sv, sw
    return v, w


def _blob(value: object) -> str:
    """Bytes in a log line (compressed map cells): their length and digest, not the bytes."""
    if isinstance(value, bytes | bytearray):
        return f"<{len(value)} bytes sha256:{hashlib.sha256(value).hexdigest()[:16]}>"
    raise TypeError(f"cannot log a {type(value).__name__}")


def _summary(msg: wire.Message) -> str:
    fields = {k: v for k, v in msgpack.unpackb(wire.encode(msg), raw=False).items() if k != "header"}
    return json.dumps(fields, sort_keys=True, default=_blob)


def write_mission_outputs(result: MissionResult, out_dir: str | Path) -> Path:
    """The field's outputs (truth/, events.log, summary.json) plus agents/<robot>.log (every
    message about the robot on either link), operator.log (what the operator sent) and contact.csv
    (robot, t_lost_s, t_regained_s: each span out of contact; t_regained_s empty if still lost)."""
    out = write_outputs(result.field, out_dir)
    (out / "agents").mkdir(exist_ok=True)
    for name, lines in result.logs.items():
        (out / "agents" / f"{name}.log").write_text("".join(line + "\n" for line in lines))
    (out / "operator.log").write_text("".join(line + "\n" for line in result.commands))
    rows = [
        f"{name},{lost:.3f},{'' if back is None else f'{back:.3f}'}\n"
        for name, spans in result.contact.items()
        for lost, back in spans
    ]
    (out / "contact.csv").write_text("robot,t_lost_s,t_regained_s\n" + "".join(rows))
    return out
