"""The disinfection round (issue 16): whole agents in lockstep, an operator who plans a round on
the robots' own maps as the console does, sends it as orders, and a score against the truth.

``RoundRun(setup)`` runs one round as a ``MissionRun`` (every robot's real agent: board, lidar,
UWB fixes, onboard map, pilot, dose layer; in-process Zenoh and MQTT) and adds an operator who,
in simulated time:

* takes each robot's lease and renews it every 2 s on both links (as the console does);
* drives each robot 2.4 m into the room by teleop (``DRIVE_IN_S``): the fusion finds the
  robot's heading from UWB over its first half metre, and the map is started in the site frame;
* after ``PLAN_AT_S`` fetches each robot's map over the link (the queryable the console asks),
  merges them as the console does (``operator/rounds.py`` ``floor_of``) and plans:
  - ``uv``: the console's own planner (``site/rounds.py`` ``plan_round``: dwell points, the split
    between robots, the orders);
  - ``park`` (baseline a, the common practice): drive to the room's middle and dwell until the
    farthest floor in line of sight has the dose (``coverage.park_in_middle``);
  - ``lawnmower`` (baseline b): lanes ``LAWNMOWER_LANE_M`` apart over the room with the lamp on, at
    the one constant speed that brings the dose to as much of the reachable floor as ``uv`` plans
    for (the dose along a pass scales as 1/speed: computed once at 1 m/s);
  - ``sweep``: the console's boustrophedon floor-coverage route (``plan_round`` kind ``sweep``);
* sends every order (VDA 5050 nodes, edges, payload and dwell actions) and waits for each robot's
  ``order ... finished`` event.

Truth: each robot's true pose and its board's lamp every ``SAMPLE_S`` give the dose the floor
really got (``shared/dose.py`` on the plan's own floor at 5 cm, walls and furniture casting
shadows), the time the lamp was on outside the room, the path each robot really drove and, for
a sweep, the floor its brush (a disc of the robot's diameter) passed over. The score is taken on
the floor the lamp (or brush) can reach from where the robot can stand in the room, on the plan's
true floor (``coverage.reachable``/``sweepable``): what the operator's certificate claims.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fleetlink.agent import coverage as cv
from fleetlink.agent.dose_share import fetch_dose
from fleetlink.agent.mapping.share import fetch_map
from fleetlink.field.plans import FloorPlan, load_plan
from fleetlink.field.scenario import LidarSettings, RobotSpec, Scenario
from fleetlink.operator.fleet import TRAIL_POINTS, extend_trail
from fleetlink.operator.maps import to_grid
from fleetlink.operator.rounds import MAX_SURVEYS, RectArea, RoundError, RoundRequest, floor_of
from fleetlink.shared import wire
from fleetlink.shared.dose import DoseGrid, FloorMask, Lamp, irradiance_window
from fleetlink.shared.dose_codec import SharedDose
from fleetlink.shared.map_codec import SharedMap
from fleetlink.shared.messages import AckResult, ActionType, Event, LeaseRequest, Order, Pose, Teleop
from fleetlink.site.agents import FIELD_LAMP
from fleetlink.site.lockstep import MissionRun
from fleetlink.site.rounds import ROUND_CONFIG, plan_round

__all__ = ["MODES", "RoundResult", "RoundRun", "RoundSetup"]

MODES = ("uv", "park", "lawnmower", "sweep")
LEASE_S = 60.0
RENEW_S = 2.0
DRIVE_IN_S = (0.5, 8.5)
"""The operator drives each robot in at ``DRIVE_SPEED`` in this window: 2.4 m, over which the
fusion finds its heading from UWB to 2 degrees and the map starts in the site frame."""
DRIVE_SPEED = 0.3
PLAN_AT_S = 11.0
"""When the operator plans (the map has settled after the drive in)."""
PLAN_RETRY_S = 30.0
"""A first plan the maps do not allow yet is tried again every 2 s for this long."""
SAMPLE_S = 0.2
"""Truth sampling period: the lamp's dose, the path, the brush."""
STILL_M = 0.01
"""A robot that moved less than this since the last footprint is standing: the footprint is reused."""
LAWNMOWER_LANE_M = 0.6
TRUTH_RES = 0.05
SETTLE_S = 2.0
HAZARD_RESUME_S = 5.0
MAX_HAZARD_RESUMES = 3
"""A bump or a cliff holds a robot's order (safety first: agent/core.py); as an operator who
looks, sees the robot against a wall, backs it off and presses resume, the operator backs it out
(``BACK_OUT_*``) and resumes it after ``HAZARD_RESUME_S``, at most this many times in a row while the
order gets no further (a node done since the last bump starts the count again: a long sweep may
brush a few walls; a robot pressing the same spot is left for a person to look at)."""
BACK_OUT_AFTER_S = 1.0
BACK_OUT_FOR_S = 1.0
BACK_OUT_MPS = -0.1
"""``BACK_OUT_AFTER_S`` after a bump or a cliff, for ``BACK_OUT_FOR_S``, the operator holds the drive
key back at this speed (10 teleops a second): the robot backs 0.1 m off what it touched. A robot
left touching it keeps its bumper pressed, and the lamp interlock refuses a UV round's resume (the
kitchen's two-robot round at seed 16 waited on "lamp refused" until its deadline)."""
MAX_PASSES = 2
"""A UV round is planned again on what the robots' own dose layers say is still short (a top-up,
as an operator does with a second ``:disinfect``; none once they read ``CERTIFIED``), at most this
many passes in all."""


@dataclass(frozen=True, slots=True)
class RoundSetup:
    plan: str
    room: str
    rect: tuple[float, float, float, float]
    """The room as the operator gives it (``:disinfect rect X0 Y0 X1 Y1``, from the facility's
    plan): the same area for every pass, whatever the robots' maps show through its doors."""
    robots: tuple[tuple[str, float, float, float], ...]
    """(name, x, y, heading in degrees) where each robot is put down; it drives in along its heading."""
    mode: str = "uv"
    target_j_m2: float = 100.0
    seed: int = 16
    deadline_s: float = 7200.0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.mode != "uv" and len(self.robots) != 1:
            raise ValueError(f"{self.mode}: one robot")


@dataclass
class RoundResult:
    setup: RoundSetup
    coverage: float
    """Share of the reachable floor (true) at the target dose (UV) or passed by the brush (sweep)."""
    reachable_m2: float
    time_s: float | None
    """From the orders sent to the last robot's order finished (None: not finished by the deadline)."""
    predicted_s: float
    lamp_on_s: float
    lamp_outside_s: float
    """Lamp-on seconds with the robot's centre outside the room (true)."""
    path_m: float
    """The path the robots really drove while the round's orders ran (passes and top-ups; for a
    sweep from the first lane on), the surveys' not counted: they map the room, and a room mapped
    before is planned without them."""
    ideal_path_m: float | None = None
    """Sweep: the reachable floor / the tool's width."""
    plan_wall_s: float = 0.0
    wall_s: float = 0.0
    sim_s: float = 0.0
    skipped_nodes: int = 0
    bumps: int = 0
    notes: list[str] = field(default_factory=list)
    surveys: int = 0
    """Survey passes before the round (the robots looked into what their maps had not seen)."""
    survey_path_m: float = 0.0
    """The path the robots drove on survey orders (the floor their brush passed then counts)."""
    approach_path_m: float = 0.0
    """A sweep: the path from where the robot stood to its first lane (not in ``path_m``)."""

    @property
    def finished(self) -> bool:
        return self.time_s is not None

    def figures(self) -> dict[str, Any]:
        s = self.setup
        return {
            "plan": s.plan,
            "room": s.room,
            "mode": s.mode,
            "robots": len(s.robots),
            "coverage_ratio": round(self.coverage, 5),
            "reachable_m2": round(self.reachable_m2, 3),
            "time_s": None if self.time_s is None else round(self.time_s, 2),
            "predicted_s": round(self.predicted_s, 2),
            "lamp_on_s": round(self.lamp_on_s, 2),
            "lamp_outside_s": round(self.lamp_outside_s, 2),
            "path_m": round(self.path_m, 3),
            "ideal_path_m": None if self.ideal_path_m is None else round(self.ideal_path_m, 3),
            "skipped_nodes": self.skipped_nodes,
            "bumps": self.bumps,
            "surveys": self.surveys,
            "survey_path_m": round(self.survey_path_m, 3),
            "approach_path_m": round(self.approach_path_m, 3),
            "plan_wall_s": round(self.plan_wall_s, 3),
            "wall_s": round(self.wall_s, 2),
            "sim_s": round(self.sim_s, 2),
        }


@dataclass
class _Crew:
    name: str
    order_id: str = ""
    sent_at: float | None = None
    done_at: float | None = None
    last: tuple[float, float] | None = None
    footprint: tuple[int, int, np.ndarray[Any, np.dtype[np.float64]]] | None = None
    fp_at: tuple[float, float] | None = None
    first_lane_at: tuple[float, float] | None = None
    brush_at: tuple[float, float] | None = None
    """Where the brush was at the last sample (``_brush`` sweeps from there)."""
    sweeping: bool = False
    """A sweep's order has reached its first lane (node n1): its path counts from there."""
    bumped: bool = False
    resume_at: float | None = None
    back_out: tuple[float, float] | None = None
    """When the operator holds the drive key back (``BACK_OUT_*``): from, until."""
    resumes: int = 0
    stuck: int = 0
    """Bumps since the order last got on (``MAX_HAZARD_RESUMES``)."""
    progress_at_bump: tuple[str, int] | None = None
    trail: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=TRAIL_POINTS))
    """Its fused positions as the console's trail keeps them (the planner's ``trails``)."""


class RoundRun:
    """One round: ``run()`` until every robot's order has finished (or the deadline)."""

    def __init__(self, setup: RoundSetup, plan: FloorPlan | None = None, *, lamp: Lamp | None = None) -> None:
        self.setup = setup
        self.plan = plan or load_plan(setup.plan)
        self.lamp = lamp or FIELD_LAMP.lamp
        robots = tuple(RobotSpec(name=n, pose=(x, y, math.radians(th)), drive="agent") for n, x, y, th in setup.robots)
        scenario = Scenario(
            name=f"round-{setup.plan}-{setup.room}-{setup.mode}",
            plan=setup.plan,
            seed=setup.seed,
            duration=setup.deadline_s,
            robots=robots,
            lidar=LidarSettings(rate_hz=5.0, samples_per_second=2000.0),
        )
        self.mission = MissionRun(scenario, self.plan, record=False)
        self.clock = self.mission.clock
        self.op = self.mission.operator
        self.crews = {r.name: _Crew(r.name) for r in self.mission.robots}
        self.notes: list[str] = []
        # The truth: the plan's floor, the room on it, the floor a round can reach there.
        grid = self.plan.to_grid(TRUTH_RES)
        self.truth_mask = FloorMask.from_occupancy(grid.grid, grid.resolution, (grid.origin[0], grid.origin[1]))
        self.truth_fm = cv.FloorMap.from_mask(self.truth_mask, ROUND_CONFIG)
        self.room = cv.rectangle(self.truth_fm, *setup.rect)
        start = (setup.robots[0][1], setup.robots[0][2])
        if setup.mode == "sweep":
            self.reach = cv.sweepable(self.truth_fm, self.room, start)
        else:
            self.reach = cv.reachable(self.truth_fm, self.room, self.lamp, target_dose=setup.target_j_m2)
        self.dose = np.zeros(self.truth_fm.shape)
        """J/m² the true floor got, on the truth grid's own cells."""
        self.swept = np.zeros(self.truth_fm.shape, dtype=bool)
        self.lamp_on_s = self.lamp_outside_s = self.path_m = self.survey_path_m = self.approach_path_m = 0.0
        self.predicted_s = 0.0
        self.ideal_path_m: float | None = None
        self.plan_wall_s = 0.0
        self.skipped = 0
        self.bumps = 0
        self._next_renew = 0.2
        self._next_sample = 0.0
        self._next_teleop = 0.0
        self._planned = False
        self._plan_at = PLAN_AT_S
        self.passes = 0
        self.surveys = 0
        self.surveys_left = MAX_SURVEYS
        self.looked_from: tuple[tuple[float, float], ...] = ()
        self._surveying = False
        self._events = 0
        self._acks = 0
        self._finished_at: float | None = None
        self.mission.field.controllers.append(self._step)

    def close(self) -> None:
        self.mission.close()

    def __enter__(self) -> RoundRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- running ---------------------------------------------------------------------------------

    def run(self, chunk_s: float = 5.0) -> RoundResult:
        wall0 = time.perf_counter()
        end = self.setup.deadline_s
        t = self.clock.now()
        while t < end - 1e-9:
            stop = end if self._finished_at is None else min(end, self._finished_at + SETTLE_S)
            if t >= stop - 1e-9:
                break
            self.mission.run(min(stop, t + chunk_s))
            t = self.clock.now()
        return self._score(time.perf_counter() - wall0)

    def _step(self, t: float) -> None:
        self._after_hazards(t)
        if t >= self._next_renew:
            self._next_renew = t + RENEW_S
            for name in self.crews:
                self._send_both(name, LeaseRequest, duration_s=LEASE_S, release=False)
        if DRIVE_IN_S[0] <= t < DRIVE_IN_S[1] and t >= self._next_teleop:
            self._next_teleop = t + 0.1  # a held key: 10 a second, as the console sends them
            for name in self.crews:
                self._send(name, Teleop, v=DRIVE_SPEED, omega=0.0, ttl_s=0.5)
        if not self._planned and t >= self._plan_at:
            # As an operator would: a plan refused because a map is not there yet (not placed in
            # the site frame, not fetched) is asked for again a little later.
            self._planned = self._plan_and_send(t) or t >= PLAN_AT_S + PLAN_RETRY_S
            self._plan_at = t + 2.0
        self._read(t)
        for name, crew in self.crews.items():
            pose = self.op.poses.get(name)
            if isinstance(pose, Pose):
                extend_trail(crew.trail, pose.x, pose.y)
        if t >= self._next_sample:
            self._next_sample = t + SAMPLE_S
            self._sample()
        all_done = self._planned and all(c.done_at is not None for c in self.crews.values())
        if self._finished_at is None and all_done and not self._top_up(t):
            self._finished_at = t
        while self.mission.zenoh.deliver() + self.mission.mqtt.deliver():
            pass

    # -- the operator ------------------------------------------------------------------------------

    def _after_hazards(self, t: float) -> None:
        """The operator's hands after a bump or a cliff (``_read`` schedules them): the drive key held
        back, then resume."""
        for crew in self.crews.values():
            if crew.back_out is not None and crew.back_out[0] <= t:
                if t < crew.back_out[1]:
                    self._send(crew.name, Teleop, v=BACK_OUT_MPS, omega=0.0, ttl_s=0.5)
                    crew.back_out = (t + 0.1, crew.back_out[1])  # a held key: 10 a second
                else:
                    crew.back_out = None
            if crew.resume_at is not None and t >= crew.resume_at:
                crew.resume_at = None
                crew.resumes += 1
                self.op.action(crew.name, ActionType.RESUME, f"resume-{crew.name}-{crew.resumes}")

    def _send(self, robot: str, cls: type[wire.Message], **fields: Any) -> wire.Message:
        msg = self.op.counter(robot).make(cls, **fields)
        self.op.zenoh.publish(wire.key_of(msg), wire.encode(msg))
        return msg

    def _send_both(self, robot: str, cls: type[wire.Message], **fields: Any) -> None:
        msg = self.op.counter(robot).make(cls, **fields)
        data, key = wire.encode(msg), wire.key_of(msg)
        for endpoint in (self.op.zenoh, self.op.mqtt):
            endpoint.publish(key, data)

    def _top_up(self, t: float) -> bool:
        """The round itself once a survey is done, or another UV pass on what the robots' dose
        layers still lack; False when there is none."""
        if any(c.done_at is None or not math.isfinite(c.done_at) for c in self.crews.values()):
            return False
        if self._surveying:
            self._surveying = False
            self.surveys_left -= 1
            return self._plan_and_send(t)
        if self.setup.mode != "uv" or self.passes >= MAX_PASSES:
            return False
        got = (
            float((self.dose[self.reach] >= self.setup.target_j_m2 * (1.0 - 1e-6)).mean()) if self.reach.any() else 0.0
        )
        self.notes.append(
            f"t={t:.1f}: pass {self.passes} done: {100 * got:.2f} % of the reachable floor at the dose (truth)"
        )
        return self._plan_and_send(t)

    def _plan_and_send(self, t: float) -> bool:
        s = self.setup
        names = [n for n, *_ in s.robots]
        grids = []
        for name in names:
            snap = fetch_map(self.op.zenoh, name)
            if snap is None:
                self.notes.append(f"t={t:.1f}: {name} has no map to plan on")
                return False
            grids.append(to_grid(SharedMap.from_snapshot(snap)))  # as the console keeps and merges them
        cells, res, origin = floor_of(grids, [tuple(self.crews[n].trail) for n in names])
        starts = {}
        for name in names:
            pose = self.op.poses.get(name)
            if not isinstance(pose, Pose):
                self.notes.append(f"t={t:.1f}: no pose from {name}")
                return False
            starts[name] = (pose.x, pose.y)
        prior = None
        if self.passes or (self.surveys and s.mode == "uv"):
            # What the robots' own layers say the floor has had (as the console sums them): a pass's,
            # or a survey's (the lamp is on between its views).
            layers = [fetch_dose(self.op.zenoh, name) for name in names]
            dose_grids = [SharedDose.from_snapshot(d).grid() for d in layers if d is not None]
            prior = DoseGrid.merged(dose_grids) if dose_grids else None
            if prior is not None:
                layer = self._layer_coverage(cells, res, origin, prior)
                self.notes.append(f"t={t:.1f}: the robots' layers: {100 * layer:.2f} % of the lamp's floor at the dose")
        wall0 = time.perf_counter()
        try:
            orders, survey = self._orders(cells, res, origin, starts, prior)
        except RoundError as exc:
            self.notes.append(f"t={t:.1f}: pass {self.passes + 1}: {exc}")
            return False
        finally:
            self.plan_wall_s += time.perf_counter() - wall0
        if survey:
            self._surveying = True
            self.surveys += 1
            self.notes.append(f"t={t:.1f}: survey {self.surveys} sent: {self.predicted_s:.0f} s predicted so far")
        else:
            self.passes += 1
            self.notes.append(f"t={t:.1f}: pass {self.passes} sent: {self.predicted_s:.0f} s predicted so far")
        for name, crew in self.crews.items():
            if name not in orders:  # nothing for it in this pass (a survey's views all went to the other)
                crew.done_at = t
        for name, fields in orders.items():
            crew = self.crews[name]
            crew.order_id = fields["orderId"]
            crew.sent_at = t if crew.sent_at is None else crew.sent_at
            crew.done_at = None
            crew.sweeping = False
            self._send(name, Order, **fields)
        return True

    def _layer_coverage(
        self, cells: np.ndarray[Any, np.dtype[np.int8]], res: float, origin: tuple[float, float], dose: DoseGrid
    ) -> float:
        """Share of the room's lamp-reachable floor, on the robots' merged map, that their dose
        layers say has the dose (what an operator reads off ``:dose`` before deciding on a top-up)."""
        fm = cv.FloorMap.from_cells(cells, res, origin, ROUND_CONFIG)
        try:
            area = cv.rectangle(fm, *self.setup.rect)
        except ValueError:
            return 0.0
        reach = cv.reachable(fm, area, self.lamp, target_dose=self.setup.target_j_m2)
        if not reach.any():
            return 0.0
        h, w = fm.shape
        xs = fm.origin[0] + (np.arange(w, dtype=np.float64) + 0.5) * fm.resolution
        ys = fm.origin[1] + (np.arange(h, dtype=np.float64) + 0.5) * fm.resolution
        had = dose.dose_at(xs, ys)
        return float((had[reach] >= self.setup.target_j_m2).mean())

    def _orders(
        self,
        cells: np.ndarray[Any, np.dtype[np.int8]],
        res: float,
        origin: tuple[float, float],
        starts: dict[str, tuple[float, float]],
        prior: DoseGrid | None = None,
    ) -> tuple[dict[str, dict[str, Any]], bool]:
        """Each robot's order, and whether they are a survey's (the round is planned after it)."""
        s = self.setup
        names = tuple(starts)
        seed = RectArea(*s.rect)
        if s.mode in ("uv", "sweep"):
            surveys = self.surveys_left if self.passes == 0 else 0  # a top-up plans on what the round mapped
            request = RoundRequest(s.mode, seed, names, s.target_j_m2, surveys, self.looked_from)  # type: ignore[arg-type]
            ids = {n: f"{s.mode}-{n}-{self.passes + self.surveys + 1}" for n in names}
            result = plan_round(request, cells, res, origin, starts, self.lamp, ids, prior)
            for robot, why in result.left_out:  # as the console shows them
                self.notes.append(f"{robot} left out: {why}")
            if result.survey:  # as the console does: the next survey does not look from there again
                self.looked_from += tuple((n.x, n.y) for r in result.rounds for n in r.route[1:])
            self.predicted_s += max(r.total_s for r in result.rounds)
            if s.mode == "sweep":  # the boustrophedon ideal over the true reachable floor
                self.ideal_path_m = (
                    float(self.reach.sum()) * self.truth_fm.cell_area / self.truth_fm.config.tool_width_m
                )
            return {r.robot: dict(r.order) for r in result.rounds}, result.survey
        name = names[0]
        start = starts[name]
        fm = cv.FloorMap.from_cells(cells, res, origin, ROUND_CONFIG)  # the floor a round counts as reachable
        area = cv.rectangle(fm, *s.rect)
        reach = cv.reachable(fm, area, self.lamp, start, target_dose=s.target_j_m2)
        if s.mode == "park":
            plan = cv.park_in_middle(fm, area, self.lamp, s.target_j_m2, start, robot=name, within=reach)
            self.predicted_s = plan.predicted.total_s
            return {name: cv.plan_order(plan, f"park-{name}-1")}, False
        # lawnmower: lanes with the lamp on at the one speed that doses as much as a round plans for
        sweep = cv.plan_sweep(fm, area, start, tool_width_m=LAWNMOWER_LANE_M, robot=name)
        lit = cv.CoveragePlan(
            "lawnmower",
            sweep.nodes,
            tuple(dataclasses.replace(e, lamp=i > 0) for i, e in enumerate(sweep.edges)),
            s.target_j_m2,
            sweep.predicted,
            name,
        )
        per_mps = cv.dose_map(fm, [lit], self.lamp, travel=True, speed_mps=1.0)
        goal = 1.0 - (1.0 - 0.995)  # as much as a round plans for (site/rounds.py ROUND_CONFIG)
        speeds = np.sort(per_mps[reach] / s.target_j_m2)
        k = min(len(speeds) - 1, max(0, math.floor((1.0 - goal) * len(speeds))))
        speed = float(min(0.5, max(0.01, speeds[k]))) if len(speeds) else 0.3
        path = sweep.predicted.path_m + sum(e.length_m for e in sweep.edges[:1])
        self.predicted_s = path / speed
        self.notes.append(f"lawnmower: lanes {LAWNMOWER_LANE_M} m apart at {speed:.3f} m/s")
        return {
            name: cv.plan_order(
                lit, f"lawnmower-{name}-1", max_speed_mps=speed, pass_deviation_m=fm.config.pass_deviation_m
            )
        }, False

    def _read(self, t: float) -> None:
        acks = self.op.acks
        while self._acks < len(acks):
            ack = acks[self._acks]
            self._acks += 1
            crew = self.crews.get(ack.header.robot)
            if crew is not None and ack.commandTopic == Order.TOPIC and ack.result is AckResult.REJECTED:
                self.notes.append(f"t={t:.1f}: {crew.name} refused the order: {ack.reason}")
                crew.done_at = math.inf
        events = self.op.events
        while self._events < len(events):
            ev: Event = events[self._events]
            self._events += 1
            crew = self.crews.get(ev.header.robot)
            running = crew is not None and crew.sent_at is not None and crew.done_at is None
            if crew is not None and running and ev.kind in ("bump", "cliff"):
                st = self.op.states.get(crew.name)
                got = (st.orderId, st.progress.nodesDone) if st is not None and st.progress is not None else None
                if got != crew.progress_at_bump:
                    crew.progress_at_bump, crew.stuck = got, 0
                crew.stuck += 1
                if crew.stuck <= MAX_HAZARD_RESUMES:
                    crew.resume_at = t + HAZARD_RESUME_S
                    crew.back_out = (t + BACK_OUT_AFTER_S, t + BACK_OUT_AFTER_S + BACK_OUT_FOR_S)
                    self.notes.append(
                        f"t={t:.1f}: {crew.name}: {ev.text}; the operator backs it out and resumes in"
                        f" {HAZARD_RESUME_S:g} s"
                    )
            if crew is None or ev.kind != "order" or not crew.order_id:
                continue
            if f"order {crew.order_id} finished" in ev.text:
                crew.done_at = t
                if "skipped" in ev.text:
                    self.notes.append(f"t={t:.1f}: {crew.name}: {ev.text}")
                    found = re.search(r"(\d+) skipped", ev.text)
                    self.skipped += int(found.group(1)) if found else 0
            elif ev.severity.value != "info":
                self.notes.append(f"t={t:.1f}: {crew.name}: {ev.text}")

    # -- the truth ---------------------------------------------------------------------------------

    def _sample(self) -> None:
        for r in self.mission.robots:
            crew = self.crews[r.name]
            st = self.mission.field.rigs[r.index].robot.board.state
            x, y = float(st.x), float(st.y)
            bumped = bool(st.bumped_left or st.bumped_right)
            if bumped and not crew.bumped:
                self.bumps += 1
            crew.bumped = bumped
            running = crew.sent_at is not None and crew.done_at is None
            if running and crew.last is not None:
                step = math.dist(crew.last, (x, y))
                if self._surveying:
                    self.survey_path_m += step
                elif self.setup.mode != "sweep":
                    self.path_m += step
                elif crew.sweeping or self._on_first_lane(crew):
                    crew.sweeping = True
                    self.path_m += step
                else:
                    self.approach_path_m += step
            crew.last = (x, y)
            if running and self.setup.mode == "sweep":
                self._brush(crew, x, y)
            if st.uv_lamp:
                self.lamp_on_s += SAMPLE_S
                if not self._in_room(x, y):
                    self.lamp_outside_s += SAMPLE_S
                if crew.footprint is None or crew.fp_at is None or math.dist(crew.fp_at, (x, y)) > STILL_M:
                    m = self.truth_mask
                    crew.footprint = irradiance_window(self.lamp, x, y, m.free, m.resolution, m.origin)
                    crew.fp_at = (x, y)
                r0, c0, e = crew.footprint
                self.dose[r0 : r0 + e.shape[0], c0 : c0 + e.shape[1]] += e * SAMPLE_S

    def _on_first_lane(self, crew: _Crew) -> bool:
        """The robot says its sweep order has reached node n1, where the first lane begins (or a
        node after it): the boustrophedon's path starts there; the way to it depends on where the
        robot happened to stand."""
        st = self.op.states.get(crew.name)
        if st is None or st.orderId != crew.order_id or st.progress is None:
            return False
        return bool(st.progress.lastNodeSequenceId >= 2)

    def _in_room(self, x: float, y: float) -> bool:
        fm = self.truth_fm
        c = math.floor((x - fm.origin[0]) / fm.resolution)
        r = math.floor((y - fm.origin[1]) / fm.resolution)
        h, w = fm.shape
        return 0 <= r < h and 0 <= c < w and bool(self.room.target[r, c])

    def _brush(self, crew: _Crew, x: float, y: float) -> None:
        """The brush's disc swept from where it was at the last sample to (x, y): the brush sweeps
        all the way, not only where it is sampled (discs every 0.2 s, 6-10 cm apart at 0.3-0.5 m/s,
        would leave 0.5-1.5 cm unswept at each side of every lane)."""
        fm = self.truth_fm
        if crew.first_lane_at is None:
            if not self._in_room(x, y):
                return
            crew.first_lane_at = (x, y)
        start = crew.brush_at if crew.brush_at is not None else (x, y)
        crew.brush_at = (x, y)
        self.swept |= cv.swept_cells(fm, [start, (x, y)], fm.config.tool_width_m / 2.0)

    def _score(self, wall: float) -> RoundResult:
        s = self.setup
        cells = int(self.reach.sum())
        if s.mode == "sweep":
            got = int((self.swept & self.reach).sum())
        else:
            dose = self.dose
            got = int((dose[self.reach] >= s.target_j_m2 * (1.0 - 1e-6)).sum())
        sent = [c.sent_at for c in self.crews.values() if c.sent_at is not None]
        done = [c.done_at for c in self.crews.values()]
        time_s = None
        if sent and all(d is not None and math.isfinite(d) for d in done):
            time_s = max(d for d in done if d is not None) - min(sent)
        return RoundResult(
            setup=s,
            coverage=got / max(1, cells),
            reachable_m2=cells * self.truth_fm.cell_area,
            time_s=time_s,
            predicted_s=self.predicted_s,
            lamp_on_s=self.lamp_on_s,
            lamp_outside_s=self.lamp_outside_s,
            path_m=self.path_m,
            ideal_path_m=self.ideal_path_m,
            plan_wall_s=self.plan_wall_s,
            wall_s=wall,
            sim_s=self.clock.now(),
            skipped_nodes=self.skipped,
            bumps=self.bumps,
            notes=self.notes,
            surveys=self.surveys,
            survey_path_m=self.survey_path_m,
            approach_path_m=self.approach_path_m,
        )


def summary_line(r: RoundResult) -> str:
    f = r.figures()
    t = "not finished" if f["time_s"] is None else f"{f['time_s']:.0f} s"
    return (
        f"{f['plan']}/{f['room']} {f['mode']} x{f['robots']}: coverage {100 * f['coverage_ratio']:.2f} % of "
        f"{f['reachable_m2']:.1f} m², {t} (predicted {f['predicted_s']:.0f} s), lamp outside {f['lamp_outside_s']:.0f} s"
    )
