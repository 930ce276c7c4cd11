"""Run a scenario in lockstep: simulated time as fast as the CPU allows, the same numbers for the same seed.

Every robot's board is driven through real Control Bus bytes by an agent-side ``BoardSession``
over an in-process port, on one ``SimClock``. The loop advances the world in control sub-steps,
ticks each session when it is due, applies scripted events, casts lidar revolutions at their rate,
and records ground truth.
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fleetlink.agent.board import protocol as p
from fleetlink.agent.board.session import BoardSession, BoardSnapshot, PollRates
from fleetlink.agent.board.transport import InProcessPort
from fleetlink.field.build import build_world, lidar_model, robot_seed
from fleetlink.field.drivers import Driver, driver_for
from fleetlink.field.events import EventRunner
from fleetlink.field.lidar_worker import LidarWorker
from fleetlink.field.plans import FloorPlan, load_plan
from fleetlink.field.scenario import RobotSpec, Scenario
from fleetlink.field.world import WorldRobot
from fleetlink.shared.clock import SimClock

__all__ = ["FieldRun", "RunResult", "write_outputs"]

# The lockstep field's agents poll less often than a real one: enough to drive, cheap enough for 50.
LOCKSTEP_POLL = PollRates(
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


@dataclass(slots=True)
class Rig:
    """One robot of the run: its body and board in the world, its link, its driver, its lidar."""

    spec: RobotSpec
    robot: WorldRobot
    drive: Driver
    lidar: Any
    session: BoardSession = field(init=False)
    remote_lidar: bool = False  # cast by the lidar worker process
    link_cut: bool = False
    next_session: float = 0.0
    next_scan: float = 0.0
    scans: int = 0
    last_scan: object = None
    truth: list[tuple[float, float, float, float, float, float]] = field(default_factory=list)


@dataclass(slots=True)
class RunResult:
    scenario: Scenario
    sim_seconds: float
    wall_seconds: float
    truth: dict[str, list[tuple[float, float, float, float, float, float]]]
    events: list[str]
    scans: int
    raycast_seconds: float
    stats: dict[str, Any]

    @property
    def real_time_factor(self) -> float:
        return self.sim_seconds / self.wall_seconds if self.wall_seconds > 0 else math.inf


class FieldRun:
    def __init__(
        self,
        scenario: Scenario,
        plan: FloorPlan | None = None,
        poll: PollRates = LOCKSTEP_POLL,
        board_links: bool = True,
        lidar_worker: bool = False,
        worker_share: float = 0.7,
    ) -> None:
        """``board_links=False`` lets the stand-in drivers command the boards directly instead of
        through an agent-side board session (to measure the field alone). ``lidar_worker`` casts
        ``worker_share`` of the robots' lidars in a second process while this one steps the physics
        and casts the rest (same results; both cores busy); ``close()`` ends it."""
        self.scenario = scenario
        self.board_links = board_links
        self.plan = plan or load_plan(scenario.plan)
        self.clock = SimClock()
        self.closed_doors: set[str] = set()
        self.extra_obstacles: list[tuple[tuple[float, float], ...]] = []
        self.world = build_world(scenario, self.plan)
        self.rigs: list[Rig] = []
        self.events = EventRunner(scenario.events, self.plan, self.world, self._cut_link)
        self.raycast_seconds = 0.0
        for i, (spec, robot) in enumerate(zip(scenario.robots, self.world.robots, strict=True)):
            seed = robot_seed(scenario, i)
            lidar = lidar_model(scenario, spec, i)
            rig = Rig(spec, robot, driver_for(spec, seed), lidar)
            rig.session = BoardSession(self._port_factory(rig), self.clock, rates=poll, seed=seed)
            self.rigs.append(rig)
        self.worker: LidarWorker | None = None
        self._worker_geometry = self.world.geometry_version
        if lidar_worker and any(r.lidar is not None for r in self.rigs):
            self.worker = LidarWorker(self.world.segments)
            for rig in self.rigs:
                i = rig.robot.index
                # Spread the worker's robots evenly: robot i goes there when the running share steps up.
                if rig.lidar is not None and int((i + 1) * worker_share) > int(i * worker_share):
                    rig.remote_lidar = True
                    self.worker.add_model(i, rig.lidar.config, robot_seed(scenario, i))

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()
            self.worker = None

    def __enter__(self) -> FieldRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- running -------------------------------------------------------------------------------

    def run(self, duration: float | None = None) -> RunResult:
        end = self.scenario.duration if duration is None else duration
        dt = self.scenario.control_period
        truth_period = 1.0 / self.scenario.truth_rate_hz
        next_truth = 0.0
        t = self.clock.now()
        wall0 = time.perf_counter()
        self._record(t)
        next_truth = t + truth_period
        poll_hz = LOCKSTEP_POLL.motion
        while t < end - 1e-12:
            t = min(end, t + dt)
            self.events.advance(t)
            self.world.step(t)
            self.clock.set(t)
            for rig in self.rigs:
                if t >= rig.next_session:
                    if self.board_links:
                        rig.session.set_velocity(*rig.drive(rig.session.snapshot, t))
                        rig.next_session = rig.session.tick()
                    else:
                        rig.robot.board.drive(*rig.drive(_direct_snapshot(rig.robot), t), t)
                        rig.next_session = t + 1.0 / poll_hz
                if rig.lidar is not None and t >= rig.next_scan:
                    self._scan(rig)
                    rig.next_scan += 1.0 / rig.lidar.config.rate_hz
                    if rig.next_scan <= t:
                        rig.next_scan = t + 1.0 / rig.lidar.config.rate_hz
            if t >= next_truth - 1e-9:
                self._record(t)
                next_truth += truth_period
        if self.worker is not None:
            results = list(self.worker.drain())
            self.worker.results.clear()
            self.raycast_seconds += sum(r.cast_seconds for r in results)
            for r in results:
                self.rigs[r.robot].last_scan = (r.angles, r.distances, r.qualities)
        wall = time.perf_counter() - wall0
        return RunResult(
            scenario=self.scenario,
            sim_seconds=t,
            wall_seconds=wall,
            truth={r.spec.name: r.truth for r in self.rigs},
            events=self.events.log,
            scans=sum(r.scans for r in self.rigs),
            raycast_seconds=self.raycast_seconds,
            stats={
                r.spec.name: {
                    "connects": r.session.snapshot.connects,
                    "requests": r.session.client.stats.requests if r.session.client else None,
                    "watchdog_trips": r.robot.board.state.watchdog_trips,
                    "scans": r.scans,
                }
                for r in self.rigs
            },
        )

    def _port_factory(self, rig: Rig) -> Callable[[], InProcessPort]:
        """Each (re)connect opens a fresh in-process port; while the link is cut, bytes vanish."""
        board = rig.robot.board

        def peer(data: bytes) -> bytes:
            return b"" if rig.link_cut else board.receive(data, self.clock.now())

        return lambda: InProcessPort(peer, wait_advances_clock=False)

    def _cut_link(self, robot: str, cut: bool) -> None:
        next(r for r in self.rigs if r.spec.name == robot).link_cut = cut

    def _record(self, t: float) -> None:
        for rig in self.rigs:
            st = rig.robot.board.state
            rig.truth.append((t, st.x, st.y, st.theta, st.true_v, st.true_w))

    def _scan(self, rig: Rig) -> None:
        assert rig.lidar is not None
        x, y, th = rig.robot.pose
        circles = self.world.other_bodies(rig.robot.index, x, y, rig.lidar.config.max_range)
        if rig.remote_lidar and self.worker is not None:
            if self._worker_geometry != self.world.geometry_version:
                self.worker.set_segments(self.world.segments)
                self._worker_geometry = self.world.geometry_version
            self.worker.submit(rig.robot.index, self.clock.now(), x, y, th, circles)
            rig.scans += 1
            return
        t0 = time.perf_counter()
        rig.last_scan = rig.lidar.revolution(x, y, th, self.world.raycaster, circles)
        self.raycast_seconds += time.perf_counter() - t0
        rig.scans += 1


def _direct_snapshot(robot: WorldRobot) -> BoardSnapshot:
    """What a board session would know, read straight off the board (no byte link)."""
    board = robot.board
    return BoardSnapshot(
        connected=True,
        sensors=p.SensorData((board.ultrasonic(),)),
        bumpers=p.BumperData(board.bumper_bitmap(), 4),
    )


def write_outputs(result: RunResult, out_dir: str | Path) -> Path:
    """truth/<robot>.csv (t, x, y, theta, v, omega), events.log, summary.json."""
    out = Path(out_dir)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    for name, rows in result.truth.items():
        with (out / "truth" / f"{name}.csv").open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t_s", "x_m", "y_m", "theta_rad", "v_m_per_s", "omega_rad_per_s"])
            for row in rows:
                w.writerow([f"{row[0]:.3f}", *(f"{v:.6f}" for v in row[1:])])
    (out / "events.log").write_text("".join(e + "\n" for e in result.events))
    summary = {
        "scenario": result.scenario.name,
        "source": result.scenario.source,
        "plan": result.scenario.plan,
        "seed": result.scenario.seed,
        "robots": [r.name for r in result.scenario.robots],
        "sim_seconds": result.sim_seconds,
        "wall_seconds": result.wall_seconds,
        "real_time_factor": result.real_time_factor,
        "lidar_scans": result.scans,
        "raycast_seconds": result.raycast_seconds,
        "per_robot": result.stats,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return out
