"""The rescue sortie (issue 15): whole agents in lockstep, an operator who drives them, casualties.

``SortieRun(scenario)`` runs a scenario with ``[[casualties]]`` (field/scenarios/sortie.toml) as a
``MissionRun`` (every robot's real agent, in-process Zenoh and MQTT, the plan's radio) and adds an
operator who works the way a person at the console does, step by step in simulated time:

* takes each robot's control lease and renews it every 2 s on both links (as the console:
  operator/commander.py ``lease``, operator/fleet.py ``LeaseRenewal``), so the robot counts a
  silence as lost contact;
* sends every command through the console's own link manager (operator/linkmanager.py: the active
  link, failover to MQTT, re-sending what goes unacked), return home on both links at once;
* follows a script per robot (``SortieScript``): teleop out of the entrance, go-tos, searches of
  rooms, a comms-loss policy, return home. A search drives to a point inside a room and looks
  through the robot's camera: a casualty is in sight when it is within ``SIGHT_M`` of the robot's
  *reported* (fused) pose with a line of sight on the plan. For each one in sight the operator
  reads the camera (range and bearing from the robot, with noise), drives up to ``STANDOFF_M`` in
  front of it, reads the camera again and marks it: the robot's published pose plus that reading,
  with the pose's standard deviation as the mark's ``sd_m``.

Truth is used only to place the casualties, for what the camera shows (a sensor, as the lidar's
ray casting is) and to score: each mark against its casualty, each robot's final position against
where it started, bumps (the simulated board's bumper firing: the body touched a wall, an obstacle
or the other robot), the radio's contact spans (``MissionRun.contact``: neither link reaching the
robot), and commands executed twice (counted at each agent: a command that its pilot accepted,
keyed by (orderId, orderUpdateId) for orders and by (topic, sender, headerId, timestamp) for the
rest; the gate refusing a copy is fine and counted apart).

The same marks are also computed from the robot's odometry alone (``Pose.odom_*`` carried into the
site frame from the pose the robot was deployed at): what marking would give without UWB, as a
baseline measured in the same run.
"""

from __future__ import annotations

import json
import math
import random
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fleetlink.field.plans import FloorPlan, load_plan
from fleetlink.field.radio import walls_crossed
from fleetlink.field.scenario import Casualty, Scenario
from fleetlink.operator.linkmanager import Failed, LinkManager, Send, Switch
from fleetlink.shared import keys, wire
from fleetlink.shared.messages import (
    AckResult,
    Action,
    ActionType,
    CommsPolicy,
    Event,
    Goal,
    InstantActions,
    KeyValue,
    LeaseRequest,
    LinkName,
    Mark,
    Order,
    Pose,
    Teleop,
)
from fleetlink.site.lockstep import MissionResult, MissionRun, write_mission_outputs

__all__ = [
    "Drive",
    "GoTo",
    "Home",
    "MarkRecord",
    "Policy",
    "Search",
    "SortieResult",
    "SortieRun",
    "SortieScript",
    "office_sortie",
    "write_sortie_outputs",
]

SIGHT_M = 4.0
"""The camera shows a casualty this far away (with a line of sight)."""
STANDOFF_M = 0.35
"""The operator stops the robot this far from a casualty (its front 18 cm away) to mark it."""
CAMERA_RANGE_SD = 0.05
"""The operator's range estimate from the camera: sd as a fraction of the range ..."""
CAMERA_RANGE_SD_MIN_M = 0.02
"""... and at least this."""
CAMERA_BEARING_SD_RAD = math.radians(2.0)
CLOSE_ENOUGH_M = 0.15
"""Arrived more than this beyond the standoff (the first look misjudged the range): closer again ..."""
MAX_APPROACHES = 3
"""... at most this many approaches in all."""
LEASE_S = 60.0
"""The lease the operator asks for (the console's, operator/commander.py ``LEASE_S``)."""
RENEW_S = 2.0
"""How often the operator renews a held lease (the console's, operator/fleet.py ``CONTACT_RENEW_S``)."""
TELEOP_PERIOD_S = 0.25
"""A held key: one Teleop every quarter second (the console's key repeat)."""
TELEOP_TTL_S = 0.5
READY_S = 3.0
"""The agents connect to their boards and localise before the operator starts."""
STEP_TIMEOUT_S = 150.0
"""A go-to not reached, failed or cancelled by then is given up."""
SILENCE_GIVE_UP_S = 60.0
"""A robot not heard from for this long: the operator gives up the step it was on."""
POLL_S = 0.05
"""The operator's link manager runs at 20 Hz."""
SETTLE_S = 2.0
"""Simulated seconds the run goes on after the last robot's last step."""


# -- the script ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Drive:
    """Hold a teleop key: ``v`` m/s, ``omega`` rad/s for ``seconds``."""

    v: float
    omega: float
    seconds: float
    note: str = ""


@dataclass(frozen=True, slots=True)
class GoTo:
    """A go-to order (``theta_deg`` None: any final heading)."""

    x: float
    y: float
    theta_deg: float | None = None
    note: str = ""


@dataclass(frozen=True, slots=True)
class Search:
    """Go to (x, y) inside a room and mark every casualty in sight from there."""

    x: float
    y: float
    note: str = ""


@dataclass(frozen=True, slots=True)
class Policy:
    """Set the robot's comms-loss policy (``setCommsPolicy``); None: the run's policy."""

    policy: CommsPolicy | None = None


@dataclass(frozen=True, slots=True)
class Home:
    """Return home (an Order with ``returnHome``), sent on both links."""

    note: str = ""


Task = Drive | GoTo | Search | Policy | Home
SortieScript = dict[str, tuple[Task, ...]]
"""Each robot's tasks, in order."""


def office_sortie(scenario: Scenario, *, quick: bool = False) -> SortieScript:
    """The sortie of field/scenarios/sortie.toml on the office plan, for its first two robots.

    Both drive out of the entrance by teleop, then on by go-tos along the corridor in stages, as an
    operator watching the map would. The first scout searches room-4, goes into the records room (room-6, no radio:
    it loses both links there), searches room-11 and returns home; the second searches room-8 and
    room-2, checks the stairwell door by a go-to, and returns home. ``quick``: the first scout goes
    to the records room and home, the second searches room-8 and goes home (the same parts in a
    shorter run, for the tests)."""
    if len(scenario.robots) < 2:
        raise ValueError(f"scenario {scenario.name}: the office sortie needs two robots")
    first, second = (r.name for r in scenario.robots[:2])
    out_of_entrance = Drive(0.3, 0.0, 5.0, "out of the entrance by teleop")
    corridor = (GoTo(9.0, 9.4, None, "corridor"), GoTo(17.0, 9.4, None, "corridor"))
    to_records = (
        GoTo(29.5, 9.4, None, "corridor"),
        GoTo(35.45, 9.6, None, "in front of the records room"),
        GoTo(35.45, 6.5, None, "into the records room (room-6): no radio"),
    )
    if quick:
        return {
            first: (Policy(), out_of_entrance, *corridor, GoTo(24.0, 9.4, None, "corridor"), *to_records, Home()),
            second: (
                Policy(),
                out_of_entrance,
                GoTo(12.95, 10.1, None, "in front of room-8"),
                Search(12.95, 12.3, "room-8"),
                Home(),
            ),
        }
    return {
        first: (
            Policy(),
            out_of_entrance,
            *corridor,
            GoTo(23.95, 9.4, None, "in front of room-4"),
            Search(23.95, 7.2, "room-4"),
            *to_records,
            GoTo(29.45, 10.1, None, "in front of room-11"),
            Search(29.45, 12.2, "room-11"),
            Home(),
        ),
        second: (
            Policy(),
            out_of_entrance,
            GoTo(12.95, 10.1, None, "in front of room-8"),
            Search(12.95, 12.3, "room-8"),
            GoTo(12.95, 9.4, None, "in front of room-2"),
            Search(12.95, 7.2, "room-2"),
            GoTo(4.95, 15.0, 90.0, "the stairwell door"),
            Home(),
        ),
    }


# -- results -------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class MarkRecord:
    casualty: str
    robot: str
    t: float
    x: float
    y: float
    sd_m: float
    error_m: float
    """The mark against the casualty's true position."""
    odometry_x: float
    odometry_y: float
    odometry_error_m: float
    """The same mark from the robot's odometry alone (the baseline)."""
    range_m: float
    """How far the casualty was from the robot when it was marked (truth)."""


@dataclass(slots=True)
class SortieResult:
    mission: MissionResult
    policy: CommsPolicy
    marks: list[MarkRecord]
    unmarked: list[str]
    """Casualties nobody marked."""
    home_distance_m: dict[str, float]
    """Each robot's true final position against its true start (where it was deployed)."""
    home_fix_error_m: dict[str, float]
    """Each agent's home (where it first localised, in its site frame) against its true start."""
    collisions: dict[str, int]
    min_clearance_m: float
    """The closest any robot's body came to a wall, an obstacle or the other robot."""
    contact: dict[str, list[tuple[float, float | None]]]
    out_of_contact_s: dict[str, float]
    regained: dict[str, list[str]]
    """The agents' own contact_regained reports (what the policy did meanwhile)."""
    regained_at: dict[str, list[float]]
    """When the operator heard them (the robot heard the operator again: at its next lease renewal)."""
    executions: dict[str, Counter[tuple[Any, ...]]]
    duplicates_refused: int
    """Copies the agents refused (gate and pilot): re-sends and the second link's copy."""
    sends: int
    resends: int
    failed: int
    switches: list[str]
    log: list[str]
    sim_s: float
    wall_s: float
    done: dict[str, bool]
    """Each robot finished its script (its last step reached or given up) before the deadline."""

    @property
    def executed_twice(self) -> int:
        """Commands an agent carried out more than once (each extra execution counts)."""
        return sum(n - 1 for runs in self.executions.values() for n in runs.values() if n > 1)

    @property
    def regain_s(self) -> float | None:
        """The longest span out of contact, lost to regained (0 if no robot lost contact; None:
        a robot was still out of contact at the end)."""
        spans = [s for spans in self.contact.values() for s in spans]
        if any(back is None for _, back in spans):
            return None
        return max((back - lost for lost, back in spans if back is not None), default=0.0)

    @property
    def regain_heard_s(self) -> float | None:
        """The longest time from losing the links to the robot reporting contact regained (the
        agent's view: it hears the operator's next lease renewal); None as ``regain_s``."""
        worst = 0.0
        for robot, spans in self.contact.items():
            for lost, back in spans:
                if back is None:
                    return None
                heard = [t for t in self.regained_at.get(robot, []) if t >= lost]
                if not heard:
                    return None
                worst = max(worst, min(heard) - lost)
        return worst

    @property
    def lost_robots(self) -> list[str]:
        return [name for name, spans in self.contact.items() if spans]

    def figures(self) -> dict[str, Any]:
        """The run's figures in SI units, the unit in the key."""
        errs = sorted(m.error_m for m in self.marks)
        odo = sorted(m.odometry_error_m for m in self.marks)
        return {
            "policy": self.policy.value,
            "sim_s": self.sim_s,
            "wall_s": self.wall_s,
            "marks": len(self.marks),
            "unmarked": list(self.unmarked),
            "mark_error_p95_m": percentile(errs, 95),
            "mark_error_max_m": max(errs, default=math.nan),
            "mark_errors_m": {m.casualty: m.error_m for m in self.marks},
            "mark_sd_m": {m.casualty: m.sd_m for m in self.marks},
            "odometry_mark_error_p95_m": percentile(odo, 95),
            "odometry_mark_errors_m": {m.casualty: m.odometry_error_m for m in self.marks},
            "home_distance_max_m": max(self.home_distance_m.values()),
            "home_distance_m": dict(self.home_distance_m),
            "home_fix_error_m": dict(self.home_fix_error_m),
            "collisions": sum(self.collisions.values()),
            "collisions_by_robot": dict(self.collisions),
            "min_clearance_m": self.min_clearance_m,
            "out_of_contact_s": sum(self.out_of_contact_s.values()),
            "out_of_contact_by_robot_s": dict(self.out_of_contact_s),
            "regain_s": self.regain_s,
            "regain_heard_s": self.regain_heard_s,
            "contact_regained": {k: list(v) for k, v in self.regained.items()},
            "lost_contact": self.lost_robots,
            "contact_spans_s": {k: [[a, b] for a, b in v] for k, v in self.contact.items()},
            "executed_twice": self.executed_twice,
            "executed": sum(sum(c.values()) for c in self.executions.values()),
            "duplicates_refused": self.duplicates_refused,
            "commands_sent": self.sends,
            "resends": self.resends,
            "commands_failed": self.failed,
            "scripts_done": dict(self.done),
        }


def percentile(values: Sequence[float], q: float) -> float:
    """Linear interpolation between closest ranks (numpy's default); NaN for no values."""
    xs = sorted(values)
    if not xs:
        return math.nan
    k = (len(xs) - 1) * q / 100.0
    lo = math.floor(k)
    hi = min(lo + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (k - lo)


# -- the run -------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Sighting:
    """One look through the camera at a casualty."""

    range_m: float
    """As the operator judges it."""
    bearing: float
    """From the robot's heading, radians, as the operator judges it."""
    true_range_m: float
    pose: tuple[float, float, float]
    """The robot's reported pose it is placed by."""
    site_xy: tuple[float, float]
    message: Pose


@dataclass(slots=True)
class _Crew:
    """What the operator is doing with one robot."""

    name: str
    tasks: deque[Task]
    deploy: tuple[float, float, float]
    task: Task | None = None
    phase: str = ""
    started: float = 0.0
    order: str | None = None
    """The orderId the current step waits on ('' for a return home)."""
    command: tuple[str, int] | None = None
    """(topic, headerId) of the command the step waits on, for the link manager's Failed."""
    teleop_until: float = -math.inf
    next_teleop: float = 0.0
    targets: list[Casualty] = field(default_factory=list)
    target: Casualty | None = None
    approaches: int = 0
    inbox: list[Event] = field(default_factory=list)
    last_heard: float = 0.0
    pose: Pose | None = None
    done: bool = False
    orders: int = 0


class SortieRun:
    """A sortie: ``run()`` until every robot has done its script (or the scenario's duration)."""

    def __init__(
        self,
        scenario: Scenario,
        plan: FloorPlan | None = None,
        *,
        script: SortieScript | None = None,
        policy: CommsPolicy = CommsPolicy.RETRACE,
        record: bool = False,
        map_worker: bool | None = None,
    ) -> None:
        if not scenario.casualties:
            raise ValueError(f"scenario {scenario.name}: a sortie needs [[casualties]]")
        self.scenario = scenario
        self.plan = plan or load_plan(scenario.plan)
        for c in scenario.casualties:
            if not self.plan.contains(c.x, c.y) or self.plan.in_obstacle(c.x, c.y):
                raise ValueError(f"casualty {c.name} at ({c.x:g}, {c.y:g}) is outside the plan or inside an obstacle")
        self.policy = policy
        if script is None and self.plan.name != "office":
            raise ValueError(f"no sortie script for plan {self.plan.name} (the built-in one is the office's)")
        self.script = script if script is not None else office_sortie(scenario)
        unknown = set(self.script) - {r.name for r in scenario.robots}
        if unknown:
            raise ValueError(f"the sortie script names robots the scenario does not have: {sorted(unknown)}")
        self.mission = MissionRun(scenario, self.plan, record=record, map_worker=map_worker)
        self.clock = self.mission.clock
        self.op = self.mission.operator
        self.links = LinkManager()
        self._rng = random.Random(f"sortie-camera-{scenario.seed}")
        self._walls = [(float(a), float(b), float(c), float(d)) for a, b, c, d in self.plan.segments()]
        self.crews: dict[str, _Crew] = {}
        for r in self.mission.robots:
            rig = self.mission.field.rigs[r.index]
            st = rig.robot.board.state
            tasks = self.script.get(r.name, ())
            self.crews[r.name] = _Crew(r.name, deque(tasks), (st.x, st.y, st.theta), done=not tasks)
            self._count_executions(r.name, r.node.core)
        self.marks: list[MarkRecord] = []
        self.marked: set[str] = set()
        self.log: list[str] = []
        self.executions: dict[str, Counter[tuple[Any, ...]]] = {name: Counter() for name in self.crews}
        self.collisions: dict[str, int] = dict.fromkeys(self.crews, 0)
        self.regained_at: dict[str, list[float]] = {name: [] for name in self.crews}
        """When the operator heard each robot's contact_regained event."""
        self.min_clearance_m = math.inf
        self.sends = self.resends = self.failed = 0
        self.switches: list[str] = []
        self._bumped: dict[str, bool] = dict.fromkeys(self.crews, False)
        self._next_renew = READY_S
        self._next_poll = 0.0
        self._next_clearance = 0.0
        self._acks = 0
        self._events = 0
        self._finished_at: float | None = None
        for link in (self.op.zenoh, self.op.mqtt):
            for topic in ("pose", "state", "lease", "board"):
                link.subscribe(keys.zenoh_all_robots(topic), self._heard(link.name))
        self.mission.field.controllers.append(self._step)

    def close(self) -> None:
        self.mission.close()

    def __enter__(self) -> SortieRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- running ---------------------------------------------------------------------------------

    def run(self, deadline_s: float | None = None, chunk_s: float = 1.0) -> SortieResult:
        """Step until every script is done (plus ``SETTLE_S``) or ``deadline_s`` (default: the
        scenario's duration)."""
        end = self.scenario.duration if deadline_s is None else deadline_s
        wall0 = time.perf_counter()
        result = None
        t = self.clock.now()
        while t < end - 1e-9:
            stop = end
            if self._finished_at is not None:
                stop = min(end, self._finished_at + SETTLE_S)
            if t >= stop - 1e-9:
                break
            result = self.mission.run(min(stop, t + chunk_s))
            t = self.clock.now()
        if result is None:
            result = self.mission.run(t)
        wall = time.perf_counter() - wall0
        result.field.wall_seconds = wall
        return self._score(result, wall)

    def _step(self, t: float) -> None:
        """After the agents at ``t``: collisions, the operator's links, each robot's script, links."""
        self._watch_bodies(t)
        self._read_inputs(t)
        if t >= READY_S:
            if t >= self._next_renew:
                self._next_renew = t + RENEW_S
                for name in self.crews:
                    self._lease(name, t)
            for crew in self.crews.values():
                if not crew.done:
                    self._work(crew, t)
        if t >= self._next_poll:
            self._next_poll = t + POLL_S
            for item in self.links.poll(t):
                self._link_item(item, t)
        if self._finished_at is None and all(c.done for c in self.crews.values()):
            self._finished_at = t
            self._note(t, "", "every robot has done its script")
        while self.mission.zenoh.deliver() + self.mission.mqtt.deliver():
            pass

    # -- what the operator hears -------------------------------------------------------------------

    def _heard(self, link: LinkName) -> Callable[[str, bytes], None]:
        def heard(key: str, payload: bytes) -> None:
            parts = key.split("/")
            crew = self.crews.get(parts[2]) if len(parts) > 3 else None
            if crew is None:
                return
            now = self.clock.now()
            self.links.heard(crew.name, link.value, now)
            crew.last_heard = now
            if parts[3] == "pose":
                msg = wire.decode_key(key, payload)
                if isinstance(msg, Pose) and (crew.pose is None or msg.header.headerId > crew.pose.header.headerId):
                    crew.pose = msg

        return heard

    def _read_inputs(self, t: float) -> None:
        acks = self.op.acks
        while self._acks < len(acks):
            ack = acks[self._acks]
            self._acks += 1
            robot = ack.header.robot
            if robot in self.crews:
                self.links.acked(robot, ack.link.value, ack.commandTopic, ack.commandHeaderId, t)
                self.crews[robot].last_heard = t
        events = self.op.events
        while self._events < len(events):
            ev = events[self._events]
            self._events += 1
            crew = self.crews.get(ev.header.robot)
            if crew is None:
                continue
            crew.last_heard = t
            crew.inbox.append(ev)
            if ev.kind in ("contact_regained", "contact_lost"):
                self._note(t, crew.name, f"{ev.kind}: {ev.text}")
            if ev.kind == "contact_regained":
                self.regained_at[crew.name].append(t)

    def _link_item(self, item: Send | Switch | Failed, t: float) -> None:
        if isinstance(item, Send):
            self._put(item.robot, item.link, keys.sender_key(item.robot, item.topic, self.op.name), item.payload)
            self.resends += 1
        elif isinstance(item, Switch):
            self.switches.append(f"t={t:.2f} s: {item.describe()}")
        else:
            self.failed += 1
            crew = self.crews[item.robot]
            self._note(t, crew.name, f"{item.topic} {item.header_id} failed: {item.reason}")
            if crew.command == (item.topic, item.header_id):
                self._next_task(crew, t, f"given up: {item.reason}")

    # -- what the operator sends --------------------------------------------------------------------

    def _put(self, robot: str, link: str, key: str, payload: bytes) -> None:
        endpoint = self.op.zenoh if link == LinkName.ZENOH.value else self.op.mqtt
        endpoint.publish(key, payload)

    def _send(self, crew: _Crew, cls: type[wire.Message], t: float, *, expect_ack: bool = True, both: bool = False,
              **fields: Any) -> wire.Message:  # fmt: skip
        """Through the console's link manager (re-sent when unacked); ``both``: a copy on the other link too."""
        msg = self.op.counter(crew.name).make(cls, **fields)
        data = wire.encode(msg)
        sends, failed = self.links.command(crew.name, msg.TOPIC, msg.header.headerId, data, t, expect_ack=expect_ack)
        key = wire.key_of(msg)
        for s in sends:
            self._put(crew.name, s.link, key, data)
            self.sends += 1
            self.op.sent.append(f"{t:.3f} {s.link} {crew.name} {msg.TOPIC} #{msg.header.headerId}")
            if both:
                other = LinkName.MQTT.value if s.link == LinkName.ZENOH.value else LinkName.ZENOH.value
                self._put(crew.name, other, key, data)
                self.sends += 1
                self.op.sent.append(f"{t:.3f} {other} {crew.name} {msg.TOPIC} #{msg.header.headerId} (copy)")
        self.failed += len(failed)
        if expect_ack:
            crew.command = (msg.TOPIC, msg.header.headerId)
        return msg

    def _lease(self, robot: str, t: float) -> None:
        """Ask for (or renew) the lease on both links, as the console does."""
        msg = self.op.counter(robot).make(LeaseRequest, duration_s=LEASE_S, release=False)
        data, key = wire.encode(msg), wire.key_of(msg)
        for endpoint in (self.op.zenoh, self.op.mqtt):
            endpoint.publish(key, data)

    def _goal(self, crew: _Crew, t: float, x: float, y: float, theta: float | None) -> None:
        crew.orders += 1
        crew.order = f"{crew.name}-{crew.orders}"
        goal = Goal(x=x, y=y, theta=theta)
        self._send(crew, Order, t, orderId=crew.order, orderUpdateId=0, goal=goal, returnHome=False)

    # -- each robot's script ---------------------------------------------------------------------------

    def _note(self, t: float, robot: str, text: str) -> None:
        self.log.append(f"t={t:.2f} s: {robot + ': ' if robot else ''}{text}")

    def _next_task(self, crew: _Crew, t: float, outcome: str = "") -> None:
        if crew.task is not None and outcome:
            self._note(t, crew.name, f"{_describe(crew.task)}: {outcome}")
        crew.task, crew.phase, crew.order, crew.command = None, "", None, None
        crew.targets, crew.target = [], None
        if not crew.tasks:
            crew.done = True
            self._note(t, crew.name, "script done")

    def _work(self, crew: _Crew, t: float) -> None:
        if crew.task is None:
            crew.inbox.clear()
            if not crew.tasks:
                crew.done = True
                return
            crew.task = crew.tasks.popleft()
            crew.started = t
            self._start(crew, crew.task, t)
            return
        task = crew.task
        if isinstance(task, Drive):
            self._drive(crew, task, t)
            return
        if isinstance(task, Policy):
            if crew.command is None or self._acked(crew):
                self._next_task(crew, t, "set")
            return
        outcome = self._goal_outcome(crew, t)
        if outcome is None:
            return
        if isinstance(task, Search):
            self._search(crew, task, t, outcome)
        else:
            self._next_task(crew, t, outcome)

    def _start(self, crew: _Crew, task: Task, t: float) -> None:
        self._note(t, crew.name, f"{_describe(task)}: started")
        if isinstance(task, Drive):
            crew.teleop_until = t + task.seconds
            crew.next_teleop = t
            self._drive(crew, task, t)
        elif isinstance(task, Policy):
            policy = task.policy or self.policy
            action = Action(
                actionId=f"policy-{crew.name}",
                actionType=ActionType.SET_COMMS_POLICY,
                actionParameters=(KeyValue(key="policy", value=policy.value),),
            )
            self._send(crew, InstantActions, t, actions=(action,))
        elif isinstance(task, GoTo):
            theta = None if task.theta_deg is None else math.radians(task.theta_deg)
            self._goal(crew, t, task.x, task.y, theta)
        elif isinstance(task, Search):
            crew.phase = "to room"
            self._goal(crew, t, task.x, task.y, None)
        elif isinstance(task, Home):
            crew.order = ""
            crew.orders += 1
            oid = f"{crew.name}-home-{crew.orders}"
            self._send(crew, Order, t, both=True, orderId=oid, orderUpdateId=0, goal=None, returnHome=True)

    def _drive(self, crew: _Crew, task: Drive, t: float) -> None:
        if t < crew.next_teleop:
            return
        crew.next_teleop = t + TELEOP_PERIOD_S
        if t < crew.teleop_until:
            self._send(crew, Teleop, t, expect_ack=False, v=task.v, omega=task.omega, ttl_s=TELEOP_TTL_S)
        elif crew.phase != "released":
            crew.phase = "released"
            self._send(crew, Teleop, t, expect_ack=False, v=0.0, omega=0.0, ttl_s=TELEOP_TTL_S)
        elif crew.pose is not None and abs(crew.pose.vx) < 1e-3 and abs(crew.pose.omega) < 1e-3:
            self._next_task(crew, t, "done")

    def _acked(self, crew: _Crew) -> bool:
        assert crew.command is not None
        topic, header_id = crew.command
        return any(
            a.header.robot == crew.name and a.commandTopic == topic and a.commandHeaderId == header_id
            for a in self.op.acks[-20:]
        )

    def _goal_outcome(self, crew: _Crew, t: float) -> str | None:
        """How the go-to the step waits on ended (None: not yet)."""
        for ev in crew.inbox:
            data = {kv.key: kv.value for kv in ev.data}
            if ev.kind in ("goal_reached", "goal_failed", "goal_cancelled"):
                oid = data.get("orderId", "")
                if oid == crew.order:
                    crew.inbox.clear()
                    return f"{ev.kind.removeprefix('goal_')} ({ev.text})"
            elif ev.kind == "contact_regained":
                crew.inbox.clear()
                return f"contact regained ({ev.text})"
        crew.inbox.clear()
        if t - crew.last_heard > SILENCE_GIVE_UP_S:
            return f"given up: robot silent for {t - crew.last_heard:.0f} s"
        if t - crew.started > STEP_TIMEOUT_S:
            return f"given up after {STEP_TIMEOUT_S:g} s"
        return None

    # -- searching and marking -------------------------------------------------------------------------

    def _search(self, crew: _Crew, task: Search, t: float, outcome: str) -> None:
        if crew.phase == "to room":
            self._note(t, crew.name, f"{_describe(task)}: in the room ({outcome})")
            crew.targets = self._in_sight(crew)
            self._note(t, crew.name, f"in sight: {', '.join(c.name for c in crew.targets) or 'nobody'}")
        elif crew.phase == "approach" and crew.target is not None:
            seen = self._look(crew, crew.target)
            if seen is not None and seen.range_m > STANDOFF_M + CLOSE_ENOUGH_M and crew.approaches < MAX_APPROACHES:
                self._approach(crew, seen, t)  # still too far to tell: closer
                return
            self._mark(crew, crew.target, seen, t)
        crew.target = None
        while crew.targets:
            crew.target = crew.targets.pop(0)
            crew.approaches = 0
            seen = self._look(crew, crew.target)
            if seen is not None:
                self._approach(crew, seen, t)
                return
            self._note(t, crew.name, f"cannot see {crew.target.name}: no pose from the robot")
        self._next_task(crew, t, "searched")

    def _approach(self, crew: _Crew, seen: _Sighting, t: float) -> None:
        """A go-to ``STANDOFF_M`` short of where the camera shows the casualty, facing it."""
        cx, cy = seen.site_xy
        px, py, _ = seen.pose
        d = math.hypot(cx - px, cy - py)
        ux, uy = ((cx - px) / d, (cy - py) / d) if d > 1e-6 else (1.0, 0.0)
        crew.phase = "approach"
        crew.started = t
        crew.approaches += 1
        assert crew.target is not None
        self._note(t, crew.name, f"drives up to {crew.target.name}, seen {seen.range_m:.2f} m away")
        self._goal(crew, t, cx - STANDOFF_M * ux, cy - STANDOFF_M * uy, math.atan2(uy, ux))

    def _in_sight(self, crew: _Crew) -> list[Casualty]:
        """Unmarked casualties within ``SIGHT_M`` of the robot's reported pose, with a line of sight
        on the plan (walls and obstacles block it), nearest first."""
        if crew.pose is None:
            return []
        px, py = crew.pose.x, crew.pose.y
        seen = [
            (math.hypot(c.x - px, c.y - py), c.name, c)
            for c in self.scenario.casualties
            if c.name not in self.marked
            and math.hypot(c.x - px, c.y - py) <= SIGHT_M
            and walls_crossed(self._walls, px, py, c.x, c.y) == 0
        ]
        return [c for _, _, c in sorted(seen)]

    def _true_pose(self, robot: str) -> tuple[float, float, float]:
        r = next(r for r in self.mission.robots if r.name == robot)
        st = self.mission.field.rigs[r.index].robot.board.state
        return st.x, st.y, st.theta

    def _look(self, crew: _Crew, c: Casualty) -> _Sighting | None:
        """The camera: the casualty's range and bearing from the robot as the operator judges them
        (the truth plus noise: a sensor, as the lidar's ray casting is), placed in the site frame by
        the robot's reported pose (None: no pose heard yet)."""
        pose = crew.pose
        if pose is None:
            return None
        x, y, th = self._true_pose(crew.name)
        true_range = math.hypot(c.x - x, c.y - y)
        bearing = math.atan2(c.y - y, c.x - x) - th + self._rng.gauss(0.0, CAMERA_BEARING_SD_RAD)
        sd = max(CAMERA_RANGE_SD_MIN_M, CAMERA_RANGE_SD * true_range)
        rng = max(0.0, true_range + self._rng.gauss(0.0, sd))
        a = pose.theta + bearing
        site = (pose.x + rng * math.cos(a), pose.y + rng * math.sin(a))
        return _Sighting(rng, bearing, true_range, (pose.x, pose.y, pose.theta), site, pose)

    def _mark(self, crew: _Crew, c: Casualty, seen: _Sighting | None, t: float) -> None:
        if seen is None:
            self._note(t, crew.name, f"cannot mark {c.name}: no pose from the robot")
            return
        pose = seen.message
        x, y = seen.site_xy
        sd = max(pose.sd_x_m, pose.sd_y_m)
        # The baseline: the same reading from the odometry alone, carried from the deployment pose.
        x0, y0, th0 = crew.deploy
        ox = x0 + math.cos(th0) * pose.odom_x - math.sin(th0) * pose.odom_y
        oy = y0 + math.sin(th0) * pose.odom_x + math.cos(th0) * pose.odom_y
        oa = th0 + pose.odom_theta + seen.bearing
        odo_x, odo_y = ox + seen.range_m * math.cos(oa), oy + seen.range_m * math.sin(oa)
        self.op.send(Mark, crew.name, markId=f"mark-{c.name}", x=x, y=y, label=c.label, kind="casualty",
                     sd_m=min(1000.0, sd), removed=False)  # fmt: skip
        record = MarkRecord(
            casualty=c.name,
            robot=crew.name,
            t=t,
            x=x,
            y=y,
            sd_m=sd,
            error_m=math.hypot(x - c.x, y - c.y),
            odometry_x=odo_x,
            odometry_y=odo_y,
            odometry_error_m=math.hypot(odo_x - c.x, odo_y - c.y),
            range_m=seen.true_range_m,
        )
        self.marks.append(record)
        self.marked.add(c.name)
        self._note(t, crew.name, f"marked {c.name} at ({x:.2f}, {y:.2f}) sd {sd:.2f} m: {record.error_m:.3f} m off")

    # -- what the agents did -----------------------------------------------------------------------------

    def _count_executions(self, robot: str, core: Any) -> None:
        """Count, at the agent, every command its pilot accepted (``AgentCore._run``)."""
        run = core._run

        def counted(msg: Any, now: float, out: Any) -> Any:
            result = run(msg, now, out)
            if getattr(result.status, "value", "") == AckResult.ACCEPTED.value:
                if isinstance(msg, Order):
                    ident: tuple[Any, ...] = ("order", msg.orderId, msg.orderUpdateId)
                else:
                    h = msg.header
                    ident = (msg.TOPIC, h.sender, h.headerId, h.timestamp)
                self.executions[robot][ident] += 1
            return result

        core._run = counted

    def _watch_bodies(self, t: float) -> None:
        """Bumps (the bumper's rising edge) every step; the closest approach every 50 ms."""
        clearance = t >= self._next_clearance
        if clearance:
            self._next_clearance = t + 0.05
        for r in self.mission.robots:
            board = self.mission.field.rigs[r.index].robot.board
            st = board.state
            bumped = st.bumped_left or st.bumped_right
            if bumped and not self._bumped[r.name]:
                self.collisions[r.name] += 1
                self._note(t, r.name, f"BUMP at ({st.x:.2f}, {st.y:.2f})")
            self._bumped[r.name] = bumped
            if clearance:
                gap = board.floor.clearance(st.x, st.y) - board.config.radius
                self.min_clearance_m = min(self.min_clearance_m, gap)

    def _score(self, result: MissionResult, wall: float) -> SortieResult:
        home: dict[str, float] = {}
        fix: dict[str, float] = {}
        for r in self.mission.robots:
            truth = result.field.truth[r.name]
            _, x0, y0, *_ = truth[0]
            x, y, _ = self._true_pose(r.name)
            home[r.name] = math.hypot(x - x0, y - y0)
            h = r.node.core.home.home
            fix[r.name] = math.nan if h is None else math.hypot(h.x - x0, h.y - y0)
        end = result.field.sim_seconds
        contact = {name: list(spans) for name, spans in result.contact.items()}
        out = {name: sum((end if b is None else b) - a for a, b in spans) for name, spans in contact.items()}
        regained: dict[str, list[str]] = {name: [] for name in self.crews}
        for ev in result.events:
            if ev.kind == "contact_regained" and ev.header.robot in regained:
                regained[ev.header.robot].append(ev.text)
        refused = sum(1 for a in result.acks if a.result is AckResult.DUPLICATE)
        return SortieResult(
            mission=result,
            policy=self.policy,
            marks=list(self.marks),
            unmarked=[c.name for c in self.scenario.casualties if c.name not in self.marked],
            home_distance_m=home,
            home_fix_error_m=fix,
            collisions=dict(self.collisions),
            min_clearance_m=self.min_clearance_m,
            contact=contact,
            out_of_contact_s=out,
            regained=regained,
            regained_at={k: list(v) for k, v in self.regained_at.items()},
            executions={k: Counter(v) for k, v in self.executions.items()},
            duplicates_refused=refused,
            sends=self.sends,
            resends=self.resends,
            failed=self.failed,
            switches=list(self.switches),
            log=list(self.log),
            sim_s=end,
            wall_s=wall,
            done={name: c.done for name, c in self.crews.items()},
        )


def write_sortie_outputs(result: SortieResult, out_dir: str | Path) -> Path:
    """``write_mission_outputs`` (truth/, agents/, operator.log, events.log, contact.csv,
    summary.json) plus marks.csv (each mark against its casualty), sortie.log (what the operator
    did, step by step) and sortie.json (``SortieResult.figures``)."""
    out = write_mission_outputs(result.mission, out_dir)
    rows = [
        f"{m.casualty},{m.robot},{m.t:.3f},{m.x:.4f},{m.y:.4f},{m.sd_m:.4f},{m.error_m:.4f},"
        f"{m.odometry_x:.4f},{m.odometry_y:.4f},{m.odometry_error_m:.4f},{m.range_m:.4f}\n"
        for m in result.marks
    ]
    header = "casualty,robot,t_s,x_m,y_m,sd_m,error_m,odometry_x_m,odometry_y_m,odometry_error_m,range_m\n"
    (out / "marks.csv").write_text(header + "".join(rows))
    (out / "sortie.log").write_text("".join(line + "\n" for line in [*result.log, *result.switches]))
    (out / "sortie.json").write_text(json.dumps(result.figures(), indent=2) + "\n")
    return out


def _describe(task: Task) -> str:
    if isinstance(task, Drive):
        return f"teleop {task.v:g} m/s, {task.omega:g} rad/s for {task.seconds:g} s" + (
            f" ({task.note})" if task.note else ""
        )
    if isinstance(task, GoTo):
        return f"go to ({task.x:g}, {task.y:g})" + (f" ({task.note})" if task.note else "")
    if isinstance(task, Search):
        return f"search {task.note or f'at ({task.x:g}, {task.y:g})'}"
    if isinstance(task, Policy):
        return f"comms-loss policy {task.policy.value if task.policy else 'of the run'}"
    return "return home"
