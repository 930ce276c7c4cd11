"""Run a scenario in real time: every robot's board and lidar served on TCP (or a pty) like hardware.

One physics thread advances the world on the system clock; the boards answer their masters from
the device servers' threads under the same lock, and the lidars' measurement streams go out as
the physics produces them. Ground truth goes to a sink (the field publishes it on the Zenoh key
the wire contract reserves for simulation). Scripted events run at their times.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fleetlink.field.build import build_world, lidar_model
from fleetlink.field.device_server import DeviceServer, Reactor
from fleetlink.field.events import CommandHandler, EventRunner
from fleetlink.field.plans import FloorPlan, load_plan
from fleetlink.field.rplidar import RplidarConfig, SimulatedRplidar, motor_at_start
from fleetlink.field.scenario import Event, Scenario
from fleetlink.field.world import World, WorldRobot
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.worker import Worker

log = logging.getLogger(__name__)

__all__ = ["Endpoints", "RealtimeField", "TruthSample"]


@dataclass(frozen=True, slots=True)
class TruthSample:
    robot: str
    sim_time: float
    x: float
    y: float
    theta: float
    v: float
    omega: float
    bumped: bool


@dataclass(frozen=True, slots=True)
class Endpoints:
    board: str  # socket://host:port or a pty path
    lidar: str | None


class RealtimeField:
    def __init__(
        self,
        scenario: Scenario,
        plan: FloorPlan | None = None,
        clock: Clock | None = None,
        truth_sink: Callable[[TruthSample], None] | None = None,
        truth_hz: float = 20.0,
        step_hz: float = 200.0,
        host: str = "127.0.0.1",
        pty: bool = False,
        on_command: CommandHandler | None = None,
        carries_out: Callable[[Event], bool] | None = None,
    ) -> None:
        """``on_command``: the events the field hands over (field/events.py), called on the physics
        thread under ``self.lock``, so it must not block, take the lock or wait on a device; without
        it a scenario with such events is refused, and so is one with events ``carries_out`` says
        it does not carry out."""
        self.scenario = scenario
        self.plan = plan or load_plan(scenario.plan)
        self.clock = clock or SystemClock()
        self.truth_sink = truth_sink
        self.truth_period = 1.0 / truth_hz
        self.step_period = 1.0 / step_hz
        self.host = host
        self.pty = pty
        self.lock = threading.Lock()
        self.world: World = build_world(scenario, self.plan)
        self.boards: dict[str, DeviceServer] = {}
        self.lidars: dict[str, tuple[SimulatedRplidar, DeviceServer]] = {}
        self.endpoints: dict[str, Endpoints] = {}
        self._reactor: Reactor | None = None  # one selector thread serves every device's TCP socket
        self.events = EventRunner(scenario.events, self.plan, self.world, self._cut_link, on_command, carries_out)
        self._physics: Worker | None = None
        self._start_time = 0.0

    # -- lifecycle -------------------------------------------------------------------------------

    def start(self) -> dict[str, Endpoints]:
        now = self.clock.now()
        self._start_time = now
        self.world.now = 0.0
        if not self.pty:
            self._reactor = Reactor("field-devices")
        for i, (spec, robot) in enumerate(zip(self.scenario.robots, self.world.robots, strict=True)):
            robot.board.start_clock(0.0)
            board_server = DeviceServer(
                robot.board, _Offset(self.clock, now), step_hz=None, lock=self.lock, name="board", reactor=self._reactor
            )
            board_url = self._serve(board_server)
            self.boards[spec.name] = board_server
            lidar_url = None
            model = lidar_model(self.scenario, spec, i)
            if model is not None:
                motor = motor_at_start(self.scenario.lidar.motor, served=True)
                device = SimulatedRplidar(
                    model.config, self._scan_source(robot, model), RplidarConfig(motor_on_at_start=motor)
                )
                device.start_clock(0.0)
                server = DeviceServer(
                    device, _Offset(self.clock, now), step_hz=None, lock=self.lock, name="lidar", reactor=self._reactor
                )
                lidar_url = self._serve(server)
                self.lidars[spec.name] = (device, server)
            self.endpoints[spec.name] = Endpoints(board_url, lidar_url)
        self._physics = Worker("field-physics", clock=self.clock, target=self._run).start()
        return self.endpoints

    def _serve(self, server: DeviceServer) -> str:
        if self.pty:
            return server.serve_pty()
        return f"socket://{self.host}:{server.serve_tcp(self.host, 0)}"

    def stop(self) -> None:
        physics, self._physics = self._physics, None
        if physics is not None:
            physics.stop(5.0)
        for server in self.boards.values():
            server.stop()
        for _, lidar_server in self.lidars.values():
            lidar_server.stop()
        if self._reactor is not None:
            self._reactor.stop()
            self._reactor = None

    def __enter__(self) -> RealtimeField:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def sim_time(self) -> float:
        return self.clock.now() - self._start_time

    # -- the physics loop ------------------------------------------------------------------------

    def _run(self, worker: Worker) -> None:
        next_step = self.clock.now()
        next_truth = next_step
        while not worker.stopping:
            t = self.sim_time
            outputs: list[tuple[DeviceServer, bytes]] = []
            with self.lock:
                self.events.advance(t)
                self.world.step(t)
                for device, server in self.lidars.values():
                    out = device.step(t)
                    if out:
                        outputs.append((server, out))
            for server, out in outputs:
                server.emit(out)
            now = self.clock.now()
            if self.truth_sink is not None and now >= next_truth:
                next_truth = max(next_truth + self.truth_period, now)
                self._publish_truth(t)
            next_step += self.step_period
            if next_step < now:
                next_step = now
            worker.wait(next_step - now)

    def _cut_link(self, robot: str, cut: bool) -> None:
        self.boards[robot].paused = cut

    def _publish_truth(self, t: float) -> None:
        assert self.truth_sink is not None
        for r in self.world.robots:
            st = r.board.state
            sample = TruthSample(
                r.name, t, st.x, st.y, st.theta, st.true_v, st.true_w, st.bumped_left or st.bumped_right
            )
            try:
                self.truth_sink(sample)
            except Exception:  # a sink failure must not stop the physics
                log.exception("truth sink failed")

    def _scan_source(
        self, robot: WorldRobot, model: object
    ) -> Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        def source(now: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            x, y, th = robot.pose_at(now)  # the turn's start: the physics may have stepped past it
            circles = self.world.other_bodies(robot.index, x, y, model.config.max_range, now)  # type: ignore[attr-defined]
            return model.revolution(x, y, th, self.world.raycaster, circles)  # type: ignore[attr-defined]

        return source


class _Offset:
    """The field's devices count time from the field's start, like the lockstep run."""

    def __init__(self, clock: Clock, start: float) -> None:
        self._clock = clock
        self._start = start

    def now(self) -> float:
        return self._clock.now() - self._start

    def wall(self) -> float:
        return self._clock.wall()

    def sleep_until(self, deadline: float) -> None:
        self._clock.sleep_until(deadline + self._start)

    def wait(self, event: threading.Event, timeout: float | None) -> bool:
        return self._clock.wait(event, timeout)  # a duration: the offset does not change it
