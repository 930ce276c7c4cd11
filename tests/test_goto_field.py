"""Lockstep field tests: the pilot drives a simulated board through real Control Bus bytes.

Each robot's board session (agent side, in-process port) carries the pilot's velocity to the
simulated firmware; the pilot steers on the board's own dead reckoning (odometry frame put at the
start pose) and sees the board's ultrasonic, cliff and bumper readings. Truth comes from the field.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from fleetlink.agent.guard import GuardInputs
from fleetlink.agent.motion import wrap_angle
from fleetlink.agent.pilot import ActionKind, EventKind, Pilot, PilotEvent
from fleetlink.devices.controlbus.snapshot import BoardSnapshot
from fleetlink.field.board import BUMPER_LEFT, BUMPER_RIGHT, CLIFF_LEFT, CLIFF_RIGHT
from fleetlink.field.lockstep import FieldRun
from fleetlink.field.scenario import LidarSettings, LinkCut, Noise, RobotSpec, Scenario
from fleetlink.site.lockstep import drive_by_session

Pose = tuple[float, float, float]


def compose(a: Pose, b: Pose) -> Pose:
    x, y, th = a
    c, s = math.cos(th), math.sin(th)
    return x + c * b[0] - s * b[1], y + s * b[0] + c * b[1], wrap_angle(th + b[2])


def guard_inputs(snap: BoardSnapshot) -> GuardInputs:
    us = snap.sensors.distances[0] if snap.sensors and snap.sensors.distances else 0.0
    b = snap.bumpers
    return GuardInputs(
        ultrasonic_m=us if us > 0 else None,
        cliff=b is not None and (b.triggered(CLIFF_LEFT) or b.triggered(CLIFF_RIGHT)),
        bumped=b is not None and (b.triggered(BUMPER_LEFT) or b.triggered(BUMPER_RIGHT)),
    )


@dataclass
class Agent:
    """A pilot in the lockstep loop, with commands scripted by simulated time."""

    start: Pose
    pilot: Pilot
    script: list[tuple[float, Callable[[Pilot, float], object]]] = field(default_factory=list)
    events: list[PilotEvent] = field(default_factory=list)
    poses: list[tuple[float, Pose]] = field(default_factory=list)

    def drive(self, snap: BoardSnapshot, t: float) -> tuple[float, float]:
        while self.script and self.script[0][0] <= t:
            _, command = self.script.pop(0)
            command(self.pilot, t)
        pose = compose(self.start, snap.odom)
        self.poses.append((t, pose))
        out = self.pilot.tick(t, pose, guard_inputs(snap))
        self.events.extend(out.events)
        return out.v, out.omega

    def kinds(self) -> list[EventKind]:
        return [e.kind for e in self.events]


def run(
    start: Pose, agent_script: list[tuple[float, Callable[[Pilot, float], object]]], duration: float, **kw: object
) -> tuple[Agent, FieldRun, list[tuple[float, float, float, float, float, float]]]:
    scenario = Scenario(
        name="pilot",
        plan="hall",
        seed=7,
        duration=duration,
        robots=(RobotSpec("r1", pose=start, drive="idle", lidar=False),),
        noise=kw.pop("noise", Noise()),  # type: ignore[arg-type]
        lidar=LidarSettings(enabled=False),
        events=kw.pop("events", ()),  # type: ignore[arg-type]
    )
    agent = Agent(start, Pilot(home=start), sorted(agent_script, key=lambda s: s[0]))
    fr = FieldRun(scenario, open_loop=False)
    drive_by_session(fr, 0, agent.drive)
    result = fr.run()
    return agent, fr, result.truth["r1"]


def test_goto_accuracy_through_the_board_link() -> None:
    start = (10.0, 10.0, 0.0)
    goal = (13.0, 12.0, math.radians(90))
    # Perfect wheels: this test is about control through the link; odometry drift is the fusion's.
    noise = Noise(wheel_scale_sd=0.0, gyro_bias_sd=0.0)
    agent, _, truth = run(start, [(0.5, lambda p, t: p.order(t, "o1", 0, *goal, "op"))], 16.0, noise=noise)
    assert agent.kinds() == [EventKind.GOAL_REACHED]
    reached = agent.events[0].t
    # Control error: the pose the pilot steered on, at arrival.
    t_arrive, seen = next((t, pose) for t, pose in agent.poses if t >= reached)
    assert math.hypot(seen[0] - goal[0], seen[1] - goal[1]) < 0.02
    assert abs(wrap_angle(seen[2] - goal[2])) < math.radians(2)
    _, x, y, th, v, w = truth[-1]
    assert math.hypot(x - goal[0], y - goal[1]) < 0.03
    assert abs(wrap_angle(th - goal[2])) < math.radians(2)
    assert abs(v) < 1e-6 and abs(w) < 1e-6  # and it stays stopped
    # Time: ideal 3.6 m / 0.5 m/s + (33.7 + 56.3) deg / 1.5 rad/s = 8.3 s.
    assert t_arrive - 0.5 < 1.3 * 8.3


def test_guard_stops_teleop_in_front_of_a_wall_and_lets_it_back_away() -> None:
    # Facing the west wall (x = 0) from 1.5 m: the body edge is 1.33 m from it.
    start = (1.5, 20.0, math.pi)
    script = [(0.2 + 0.2 * k, lambda p, t: p.teleop(t, 0.3, 0.0, 0.5, "op")) for k in range(40)]
    script += [(8.2 + 0.2 * k, lambda p, t: p.teleop(t, -0.2, 0.0, 0.5, "op")) for k in range(10)]
    agent, fr, truth = run(start, script, 11.0)
    refusals = [e for e in agent.events if e.kind is EventKind.GUARD_REFUSAL]
    assert refusals and refusals[0].reason == "obstacle_ahead"
    closest = min(x for _, x, *_ in truth)
    robot = fr.rigs[0].robot.board
    assert closest - robot.config.radius > 0.25  # stopped short of the wall: never touched it
    assert not robot.state.bumped_left and not robot.state.bumped_right
    assert EventKind.BUMP not in agent.kinds()
    stopped_at = next(x for t, x, *_ in truth if t >= 8.0)
    assert truth[-1][1] > stopped_at + 0.2  # backing away was allowed


def test_goto_refused_when_the_goal_is_too_close_to_a_wall() -> None:
    # The sensor sees the wall 1.65 - 0.17 = 1.48 m ahead; the goal 1.1 m ahead would leave 0.38 m.
    start = (1.65, 20.0, math.pi)
    agent, _, truth = run(start, [(0.5, lambda p, t: p.order(t, "near-wall", 0, 0.55, 20.0, None, "op"))], 4.0)
    assert agent.kinds() == [EventKind.GUARD_REFUSAL, EventKind.GOAL_FAILED]
    assert agent.events[0].reason == "obstacle_in_path" and agent.events[1].order_id == "near-wall"
    assert abs(truth[-1][1] - start[0]) < 0.01  # never drove


def test_deadman_stops_the_robot_when_teleop_goes_quiet() -> None:
    start = (10.0, 10.0, 0.0)
    agent, _, truth = run(start, [(1.0, lambda p, t: p.teleop(t, 0.4, 0.0, 0.5, "op"))], 4.0)
    stop = next(e for e in agent.events if e.kind is EventKind.DEADMAN_STOP)
    # The pilot runs at the board session's 20 Hz motion poll: it stops within one poll of the ttl.
    assert 1.5 <= stop.t <= 1.55
    moving_after = [t for t, x, y, th, v, w in truth if abs(v) > 1e-3]
    assert moving_after and max(moving_after) < stop.t + 0.3  # the motors' lag, then still
    assert truth[-1][1] - start[0] < 0.4 * 0.6


def test_board_watchdog_stops_the_wheels_when_the_agent_goes_quiet() -> None:
    start = (10.0, 10.0, 0.0)
    # The operator keeps driving, but the agent's board link is cut at t = 2 s for 3 s.
    script = [(0.5 + 0.2 * k, lambda p, t: p.teleop(t, 0.3, 0.0, 0.5, "op")) for k in range(40)]
    cut = LinkCut(at=2.0, robot="r1", duration=3.0)
    agent, fr, truth = run(start, script, 4.0, events=(cut,))
    board = fr.rigs[0].robot.board
    assert board.state.watchdog_trips == 1
    moving = [t for t, x, y, th, v, w in truth if abs(v) > 1e-3]
    # Wheels stop ~1 s after the last request (plus the motors' lag), not before and not later.
    assert 2.9 < max(moving) < 3.4
    assert EventKind.DEADMAN_STOP not in agent.kinds()  # the pilot never knew: the board saved it


def test_estop_and_return_home_in_the_field() -> None:
    start = (10.0, 10.0, 0.0)
    script: list[tuple[float, Callable[[Pilot, float], object]]] = [
        (0.5, lambda p, t: p.order(t, "o1", 0, 12.0, 10.0, None, "op")),
        (2.5, lambda p, t: p.action(t, ActionKind.ESTOP, "op")),
        (3.5, lambda p, t: p.action(t, ActionKind.ESTOP_RELEASE, "op")),
        (4.0, lambda p, t: p.action(t, ActionKind.RETURN_HOME, "op")),
    ]
    noise = Noise(wheel_scale_sd=0.0, gyro_bias_sd=0.0)
    agent, _, truth = run(start, script, 12.0, noise=noise)
    assert agent.kinds() == [
        EventKind.GOAL_CANCELLED,
        EventKind.ESTOP_LATCHED,
        EventKind.ESTOP_RELEASED,
        EventKind.GOAL_REACHED,
    ]
    still = [(t, v) for t, x, y, th, v, w in truth if 2.8 <= t <= 4.0]
    assert all(abs(v) < 1e-6 for _, v in still)
    _, x, y, th, *_ = truth[-1]
    assert math.hypot(x - start[0], y - start[1]) < 0.05 and abs(wrap_angle(th - start[2])) < math.radians(3)
