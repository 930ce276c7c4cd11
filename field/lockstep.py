"""Run the field in lockstep: simulated time as fast as the CPU allows, the same numbers for the same seed.

``FieldRun`` owns the world, the scripted events, the lidars and the ground truth, on one
``SimClock``. ``step(t)`` advances everything to ``t``; ``run()`` loops it over the scenario.
Who drives the robots is not the field's business:

* **field only** (``FieldRun(scenario)``): each robot follows its scenario's open-loop motion
  (field/open_loop.py) straight onto its board, and its lidar revolutions are cast as arrays (the
  field's own benchmarks and plan checks);
* **driven** (``FieldRun(scenario, open_loop=False)``): whoever drives opens each robot's ports,
  ``board_port(i)`` (Control Bus bytes to the simulated board) and ``lidar_port(i)`` (RPLIDAR
  bytes from the simulated device), and registers a ``controller(t)`` that ``step`` calls after
  the physics. ``fleetlink.site.lockstep`` drives every robot with its whole agent this way.

Scripted events change the world (doors, obstacles, slip, the home button, a severed board
cable); events the field cannot carry out itself (operator commands, network links) go to
``on_command(event, t)``.
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

from fleetlink.devices.ports import InProcessPort
from fleetlink.field.build import build_world, lidar_model, robot_seed
from fleetlink.field.events import EventRunner
from fleetlink.field.lidar import scan_source_for
from fleetlink.field.lidar_worker import LidarWorker
from fleetlink.field.open_loop import Motion, motion_for
from fleetlink.field.plans import FloorPlan, load_plan
from fleetlink.field.rplidar import RplidarConfig, SimulatedRplidar, motor_at_start
from fleetlink.field.scenario import RobotSpec, Scenario
from fleetlink.field.world import WorldRobot
from fleetlink.shared.clock import SimClock

__all__ = ["FieldRun", "RunResult", "write_outputs"]

Truth = tuple[float, float, float, float, float, float]
"""t, x, y, theta, v, omega."""

OPEN_LOOP_HZ = 20.0
"""How often open-loop motion re-reads its board (a field-only run)."""


@dataclass(slots=True)
class Rig:
    """One robot of the run: its body and board in the world, its lidar, its open-loop motion."""

    spec: RobotSpec
    robot: WorldRobot
    motion: Motion | None
    lidar: Any
    device: SimulatedRplidar | None = None  # the RPLIDAR the robot's driver reads (driven runs)
    remote_lidar: bool = False  # cast by the lidar worker process
    link_cut: bool = False
    lidar_cut: bool = False
    lidar_ports: list[InProcessPort] = field(default_factory=list)
    next_motion: float = 0.0
    next_scan: float = 0.0
    scans: int = 0
    last_scan: object = None
    truth: list[Truth] = field(default_factory=list)


@dataclass(slots=True)
class RunResult:
    scenario: Scenario
    sim_seconds: float
    wall_seconds: float
    truth: dict[str, list[Truth]]
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
        *,
        open_loop: bool = True,
        lidar_worker: bool = False,
        worker_share: float = 0.7,
        on_command: Callable[[Any, float], None] | None = None,
        clock: SimClock | None = None,
    ) -> None:
        """``lidar_worker`` casts ``worker_share`` of a field-only run's lidars in a second process
        while this one steps the physics and casts the rest (same results; both cores busy);
        ``close()`` ends it."""
        self.scenario = scenario
        self.open_loop = open_loop
        self.plan = plan or load_plan(scenario.plan)
        self.clock = clock or SimClock()
        self.world = build_world(scenario, self.plan)
        self.rigs: list[Rig] = []
        self.controllers: list[Callable[[float], None]] = []
        self.events = EventRunner(scenario.events, self.plan, self.world, self._cut_link, on_command=on_command)
        self.raycast_seconds = 0.0
        self._truth_period = 1.0 / scenario.truth_rate_hz
        self._next_truth = 0.0
        for i, (spec, robot) in enumerate(zip(scenario.robots, self.world.robots, strict=True)):
            seed = robot_seed(scenario, i)
            lidar = lidar_model(scenario, spec, i)
            rig = Rig(spec, robot, motion_for(spec, seed) if open_loop else None, lidar)
            robot.board.start_clock(0.0)
            if lidar is not None and not open_loop:
                motor = motor_at_start(scenario.lidar.motor, served=False)
                rig.device = SimulatedRplidar(
                    lidar.config, self._scan_source(rig), RplidarConfig(motor_on_at_start=motor)
                )
                rig.device.start_clock(0.0)
            self.rigs.append(rig)
        self.worker: LidarWorker | None = None
        self._worker_geometry = self.world.geometry_version
        if open_loop and lidar_worker and any(r.lidar is not None for r in self.rigs):
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

    # -- ports, for whoever drives the robots ---------------------------------------------------------

    def board_peer(self, index: int) -> Callable[[bytes], bytes]:
        """The robot's board as a byte peer: request bytes in, reply bytes out; nothing while its
        cable is cut (a scenario's ``link_cut``)."""
        rig = self.rigs[index]
        board = rig.robot.board

        def peer(data: bytes) -> bytes:
            return b"" if rig.link_cut else board.receive(data, self.clock.now())

        return peer

    def lidar_port(self, index: int) -> InProcessPort:
        """A fresh in-process port onto the robot's RPLIDAR (driven runs with a lidar)."""
        device = self.rigs[index].device
        if device is None:
            raise ValueError(f"robot {self.rigs[index].spec.name} has no lidar device in this run")
        rig = self.rigs[index]
        port = device.in_process_port(self.clock, advance_clock=False)
        port.cut = rig.lidar_cut
        rig.lidar_ports = [p for p in rig.lidar_ports if not p.closed] + [port]
        return port

    def cut_lidar(self, robot: str, cut: bool) -> None:
        """Sever (or mend) the robot's lidar cable: its bytes stop, its driver times out."""
        rig = next(r for r in self.rigs if r.spec.name == robot)
        rig.lidar_cut = cut
        for port in rig.lidar_ports:
            port.cut = cut

    # -- running ------------------------------------------------------------------------------------

    def run(self, duration: float | None = None) -> RunResult:
        end = self.scenario.duration if duration is None else duration
        dt = self.scenario.control_period
        wall0 = time.perf_counter()
        t = self.clock.now()
        if not any(r.truth for r in self.rigs):
            self._record(t)
            self._next_truth = t + self._truth_period
        while t < end - 1e-12:
            t = min(end, t + dt)
            self.step(t)
        return self.result(t, time.perf_counter() - wall0)

    def step(self, t: float) -> None:
        """Advance events, physics, open-loop motion, lidars and controllers to ``t``; record truth."""
        self.events.advance(t)
        self.world.step(t)
        self.clock.set(t)
        for rig in self.rigs:
            if rig.motion is not None and t >= rig.next_motion:
                rig.robot.board.drive(*rig.motion(rig.robot.board, t), t)
                rig.next_motion = t + 1.0 / OPEN_LOOP_HZ
            if self.open_loop and rig.lidar is not None and t >= rig.next_scan:
                self._scan(rig)
                rig.next_scan += 1.0 / rig.lidar.config.rate_hz
                if rig.next_scan <= t:
                    rig.next_scan = t + 1.0 / rig.lidar.config.rate_hz
        for controller in self.controllers:
            controller(t)
        if t >= self._next_truth - 1e-9:
            self._record(t)
            self._next_truth += self._truth_period

    def result(self, t: float, wall: float) -> RunResult:
        if self.worker is not None:
            results = list(self.worker.drain())
            self.worker.results.clear()
            self.raycast_seconds += sum(r.cast_seconds for r in results)
            for r in results:
                self.rigs[r.robot].last_scan = (r.angles, r.distances, r.qualities)
        return RunResult(
            scenario=self.scenario,
            sim_seconds=t,
            wall_seconds=wall,
            truth={r.spec.name: r.truth for r in self.rigs},
            events=self.events.log,
            scans=sum(r.scans for r in self.rigs),
            raycast_seconds=self.raycast_seconds,
            stats={
                r.spec.name: {"watchdog_trips": r.robot.board.state.watchdog_trips, "scans": r.scans} for r in self.rigs
            },
        )

    def _cut_link(self, robot: str, cut: bool) -> None:
        next(r for r in self.rigs if r.spec.name == robot).link_cut = cut

    def _record(self, t: float) -> None:
        for rig in self.rigs:
            st = rig.robot.board.state
            rig.truth.append((t, st.x, st.y, st.theta, st.true_v, st.true_w))

    def _scan_source(self, rig: Rig) -> Callable[[float], Any]:
        robot, model = rig.robot, rig.lidar

        def circles(x: float, y: float, at: float) -> Any:
            return self.world.other_bodies(robot.index, x, y, model.config.max_range, at)

        def counted(now: float) -> Any:
            rig.scans += 1
            t0 = time.perf_counter()
            turn = source(now)
            self.raycast_seconds += time.perf_counter() - t0
            return turn

        source = scan_source_for(model, robot.pose_at, lambda: self.world.raycaster, circles)
        return counted

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
