"""The multi-robot world: physics against closed form, collisions, cliffs, sensors, determinism."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fleetlink.field.board import BoardConfig
from fleetlink.field.lockstep import FieldRun, write_outputs
from fleetlink.field.plans import load_plan
from fleetlink.field.scenario import DoorClose, LidarSettings, Noise, RobotSpec, Scenario, parse_scenario
from fleetlink.field.world import POSE_HISTORY_S, World

ROOM = np.array([(0, 0, 10, 0), (10, 0, 10, 10), (10, 10, 0, 10), (0, 10, 0, 0)], dtype=float)


def run_steady(world: World, t0: float, seconds: float, dt: float = 0.05) -> float:
    t = t0
    robot = world.robots[0]
    while t < t0 + seconds - 1e-9:
        t += dt
        robot.board.state.last_ctrl_bus = t  # keep the watchdog fed, as a master would
        world.step(t)
    return t


@pytest.mark.parametrize(("v", "omega"), [(0.3, 0.0), (0.2, 0.5), (0.25, -0.8), (0.0, 1.0)])
def test_motion_matches_the_closed_form_differential_drive(v: float, omega: float) -> None:
    world = World(ROOM)
    robot = world.add_robot("r", (5.0, 5.0, 0.3), BoardConfig(wheel_track=0.22, ultrasonic_noise=0.0))
    robot.board.drive(v, omega, 0.0)
    t = run_steady(world, 0.0, 1.0)  # past the motor's transient
    st = robot.board.state
    x0, y0, th0 = st.x, st.y, st.theta
    dl0, dr0 = st.dist_left, st.dist_right
    t = run_steady(world, t, 2.0)
    dl, dr = st.dist_left - dl0, st.dist_right - dr0
    # Steady state: the wheels turn at the commanded speeds.
    assert dl / 2.0 == pytest.approx(v - omega * 0.11, abs=2e-3)
    assert dr / 2.0 == pytest.approx(v + omega * 0.11, abs=2e-3)
    # Closed form from the wheel distances: an arc of length ds turning dth.
    ds, dth = (dl + dr) / 2, (dr - dl) / 0.22
    if abs(dth) < 1e-12:
        ex, ey = ds * math.cos(th0), ds * math.sin(th0)
    else:
        chord = 2 * ds / dth * math.sin(dth / 2)
        ex, ey = chord * math.cos(th0 + dth / 2), chord * math.sin(th0 + dth / 2)
    # (the wheel PID still trims by micrometres per second, hence 1 µm rather than exact equality)
    assert st.x - x0 == pytest.approx(ex, abs=1e-6)
    assert st.y - y0 == pytest.approx(ey, abs=1e-6)
    assert math.remainder(st.theta - th0 - dth, 2 * math.pi) == pytest.approx(0.0, abs=1e-6)


def test_wheel_scale_error_makes_odometry_drift_from_truth() -> None:
    world = World(ROOM)
    robot = world.add_robot("r", (2.0, 5.0, 0.0), BoardConfig(wheel_scale=(1.02, 0.98)))
    robot.board.drive(0.3, 0.0, 0.0)
    run_steady(world, 0.0, 5.0)
    st = robot.board.state
    # Encoders agree (the wheels turn equally); the body turned because the wheels differ.
    assert st.dist_left == pytest.approx(st.dist_right, rel=1e-6)
    assert st.theta < -0.1


def test_a_robot_driving_into_a_wall_stops_and_its_bumper_fires() -> None:
    world = World(ROOM)
    robot = world.add_robot("r", (8.0, 5.0, 0.0), BoardConfig())
    robot.board.drive(0.4, 0.0, 0.0)
    run_steady(world, 0.0, 8.0)
    st = robot.board.state
    assert st.x == pytest.approx(10.0 - 0.17, abs=0.02)  # the body touches the wall and stops there
    assert st.v_left == 0.0 and st.v_right == 0.0
    bitmap = robot.board.bumper_bitmap()
    assert not (bitmap & 0b01) and not (bitmap & 0b10)  # both front bumpers triggered (0 = pressed)


def test_robots_collide_with_each_other() -> None:
    world = World(ROOM)
    a = world.add_robot("a", (3.0, 5.0, 0.0), BoardConfig())
    b = world.add_robot("b", (6.0, 5.0, math.pi), BoardConfig())
    a.board.drive(0.3, 0.0, 0.0)
    b.board.drive(0.3, 0.0, 0.0)
    t = 0.0
    while t < 10.0:
        t += 0.05
        a.board.state.last_ctrl_bus = b.board.state.last_ctrl_bus = t
        world.step(t)
    gap = math.hypot(a.board.state.x - b.board.state.x, a.board.state.y - b.board.state.y)
    assert gap == pytest.approx(0.34, abs=0.02)  # two 0.17 m bodies touching, not overlapping
    assert a.board.state.bumped_left or a.board.state.bumped_right


def test_a_cliff_sensor_reports_over_a_cliff_region() -> None:
    plan = load_plan("office")
    world = World(plan.segments(), plan.is_cliff)
    # Find a point just outside the stairwell's cliff polygon, facing it.
    cliff = plan.cliffs[0]
    cx = sum(p[0] for p in cliff) / len(cliff)
    cy = sum(p[1] for p in cliff) / len(cliff)
    robot = world.add_robot("r", (cx, cy, 0.0), BoardConfig())
    left, right = robot.board.cliff_sensors()
    assert left and right
    bitmap = robot.board.bumper_bitmap()
    assert not (bitmap & 0b100) and not (bitmap & 0b1000)


def test_ultrasonic_sees_walls_and_other_robots_in_its_cone() -> None:
    world = World(ROOM)
    a = world.add_robot("a", (5.0, 5.0, 0.0), BoardConfig(ultrasonic_noise=0.0))
    assert a.board.ultrasonic() == 0.0  # the wall is 4.83 m away: beyond 1.5 m, no echo
    world.add_robot("b", (6.2, 5.0, 0.0), BoardConfig())
    world.step(0.1)
    # Sensor at the front of a (x = 5.17); b's body starts at 6.03.
    assert a.board.ultrasonic() == pytest.approx(6.2 - 0.17 - 5.17, abs=1e-6)


def scenario(**kw: object) -> Scenario:
    data: dict[str, object] = {
        "plan": "office",
        "seed": 3,
        "duration_s": 6.0,
        "robots": [
            {"name": "s1", "start": "entrance", "speed": 0.3},
            {
                "name": "s2",
                "start": "lobby-06",
                "drive": "script",
                "script": [[0, 0.2, 0.0], [2, 0.0, 0.8], [3, 0.2, 0]],
            },
        ],
        "lidar": {"rate_hz": 10.0},
        "events": [
            {"at_s": 1.0, "kind": "link_cut", "robot": "s1", "duration_s": 2.0},
            {"at_s": 2.0, "kind": "door_close", "door": "room-3"},
            {"at_s": 2.5, "kind": "wheel_slip", "robot": "s2", "fraction": 0.5, "duration_s": 1.0},
        ],
    }
    data.update(kw)
    return parse_scenario(data)


def test_same_scenario_and_seed_give_identical_truth(tmp_path: Path) -> None:
    first = FieldRun(scenario()).run()
    second = FieldRun(scenario()).run()
    assert first.truth == second.truth
    assert len(first.truth["s1"]) == 6 * 20 + 1
    moved = first.truth["s2"][-1][1:3] != first.truth["s2"][0][1:3]
    assert moved
    third = FieldRun(scenario(seed=4)).run()
    assert third.truth != first.truth
    write_outputs(first, tmp_path / "a")
    write_outputs(second, tmp_path / "b")
    assert (tmp_path / "a/truth/s1.csv").read_bytes() == (tmp_path / "b/truth/s1.csv").read_bytes()


def test_scripted_events_happen_and_a_cut_link_trips_the_watchdog() -> None:
    from fleetlink.site.lockstep import MissionRun

    # Whole agents: the board's watchdog only trips when its master, an agent, goes quiet.
    with MissionRun(scenario()) as run:
        result = run.run().field
    text = "\n".join(result.events)
    assert "board link of s1 cut for 2 s" in text
    assert "board link of s1 restored" in text
    assert "door room-3 closes" in text
    assert "left wheel of s2 slips 50%" in text
    assert result.stats["s1"]["watchdog_trips"] == 1  # 2 s without a request: the board stopped
    assert result.stats["s1"]["board_connects"] == 2  # and the session reconnected afterwards
    assert result.scans == 2 * 6 * 10


def test_a_closed_door_blocks_the_lidar() -> None:
    plan = load_plan("office")
    door = plan.doors["room-3"]
    mx, my = (door[0] + door[2]) / 2, (door[1] + door[3]) / 2
    sc = scenario(
        robots=[{"name": "s1", "pose": [mx, my + 1.0, -90.0], "drive": "idle"}],
        events=[{"at_s": 0.5, "kind": "door_close", "door": "room-3"}],
        duration_s=1.0,
    )
    sc = replace(sc, noise=Noise.none())
    run = FieldRun(sc)
    run.run(0.2)
    ahead = np.pi / 2  # the robot faces -y; straight ahead in world frame is -90 degrees
    x, y, th = run.world.robots[0].pose
    open_d = run.world.raycaster.cast(x, y, np.array([th]), 12.0)[0]
    run.run(1.0)
    closed_d = run.world.raycaster.cast(x, y, np.array([th]), 12.0)[0]
    assert closed_d == pytest.approx(1.0, abs=1e-6)
    assert open_d > closed_d + 0.5
    del ahead


def test_robot_spec_and_unknown_start_are_reported() -> None:
    sc = Scenario(name="x", plan="office", robots=(RobotSpec("r", start="nowhere"),), lidar=LidarSettings(False))
    with pytest.raises(ValueError, match="no start 'nowhere'"):
        FieldRun(sc)
    sc = replace(sc, robots=(RobotSpec("r", start="entrance"),), events=(DoorClose(1.0, "x"),))
    with pytest.raises(ValueError, match="no door 'x'"):
        FieldRun(sc)


def test_the_gyro_reports_turn_rate_with_its_bias_over_the_control_bus() -> None:
    from fleetlink.devices.controlbus import protocol as p
    from fleetlink.devices.controlbus.frames import FrameDecoder

    world = World(ROOM)
    robot = world.add_robot("r", (5.0, 5.0, 0.0), BoardConfig(gyro_bias=0.01, gyro_noise=0.0))
    robot.board.drive(0.0, 0.5, 0.0)
    run_steady(world, 0.0, 2.0)
    frames = FrameDecoder(p.REPLY_CODES).feed(robot.board.receive(p.encode_request(p.GetImuData()), 2.0))
    imu = p.decode_reply(frames[0], p.ImuData)  # type: ignore[arg-type]
    assert isinstance(imu, p.ImuData)
    assert imu.yaw_rate == pytest.approx(0.5 + 0.01, abs=2e-3)
    truth_turn = robot.board.state.theta
    assert imu.yaw == pytest.approx(truth_turn + 0.01 * 2.0, abs=0.02)  # integrated bias shows as drift
    assert imu.samples >= 400  # one gyro sample per 5 ms control tick, for 2 s


def test_the_lidar_worker_process_gives_the_same_scans_as_in_process() -> None:
    sc = replace(scenario(), lidar=LidarSettings(True, 10.0), duration=2.0)
    local = FieldRun(sc)
    local_result = local.run()
    with FieldRun(sc, lidar_worker=True, worker_share=0.5) as remote:
        remote_result = remote.run()
        assert any(r.remote_lidar for r in remote.rigs) and not all(r.remote_lidar for r in remote.rigs)
        assert remote_result.truth == local_result.truth
        assert remote_result.scans == local_result.scans == 2 * 2 * 10
        for a, b in zip(local.rigs, remote.rigs, strict=True):
            assert a.last_scan is not None and b.last_scan is not None
            for x, y in zip(a.last_scan, b.last_scan, strict=True):  # type: ignore[call-overload]
                assert np.array_equal(x, y)


def test_a_robots_pose_at_a_moment_between_the_physics_steps_is_where_it_was_then() -> None:
    # A lidar turn begins at its own time, which the field learns only when the device is next
    # stepped: it is cast from the pose then (field/lockstep.py, field/realtime.py).
    world = World(ROOM)
    robot = world.add_robot("r", (5.0, 5.0, 1.9), BoardConfig(ultrasonic_noise=0.0))
    robot.board.drive(0.2, 1.0, 0.0)
    past: list[tuple[float, float, float, float]] = []
    t = 0.0
    while t < 2.0 - 1e-9:
        t += 0.025
        robot.board.state.last_ctrl_bus = t
        world.step(t)  # five physics steps of 5 ms each
        past.append((t, *robot.pose))
    assert robot.pose_at(t + 1.0) == robot.pose  # not yet: where it is
    crossed = 0
    for a, b in itertools.pairwise(past[-38:]):  # within the last second it keeps
        mid = a[0] + 0.0125  # halfway between these two samples, between two physics steps
        x, y, th = robot.pose_at(mid)
        assert math.hypot(x - a[1], y - a[2]) < math.hypot(b[1] - a[1], b[2] - a[2])
        # Turned part of the way from a's heading to b's, the short way (across +-pi too).
        assert 0.0 < math.remainder(th - a[3], math.tau) < math.remainder(b[3] - a[3], math.tau)
        assert robot.pose_at(a[0]) == pytest.approx(a[1:], abs=1e-12)
        if b[3] < a[3]:  # the heading wrapped from +pi to -pi: millisecond by millisecond, it turns on
            crossed += 1
            headings = [robot.pose_at(a[0] + k * 0.001)[2] for k in range(26)]
            steps = [math.remainder(q - p, math.tau) for p, q in itertools.pairwise(headings)]
            assert all(0.0 <= d < 0.002 for d in steps), steps
    assert crossed == 1
    # Before the last second it keeps: the oldest pose it kept, a second back.
    oldest = robot.pose_at(t - 5.0)
    assert oldest == robot.pose_at(t - POSE_HISTORY_S) and oldest != robot.pose_at(t - POSE_HISTORY_S + 0.01)


def test_other_robots_in_a_turn_cast_from_its_start_are_where_they_were_then() -> None:
    # A turn cast from its start (the physics stepped past it) places the robot casting it where it
    # was, and the robots it sees with it: a robot crossing at 0.4 m/s is 1 cm on after a 25 ms poll.
    world = World(ROOM)
    world.add_robot("a", (2.0, 5.0, 0.0), BoardConfig(ultrasonic_noise=0.0))
    b = world.add_robot("b", (4.0, 3.0, math.pi / 2), BoardConfig(ultrasonic_noise=0.0))
    b.board.drive(0.4, 0.4, 0.0)
    t = 0.0
    while t < 1.0 - 1e-9:
        t += 0.025
        for robot in world.robots:
            robot.board.state.last_ctrl_bus = t
        world.step(t)
    earlier = t - 0.0125
    now = world.other_bodies(0, 2.0, 5.0, 12.0)
    then = world.other_bodies(0, 2.0, 5.0, 12.0, at=earlier)
    assert now is not None and then is not None and len(now) == len(then) == 1
    assert tuple(now[0]) == (*b.pose[:2], b.radius)
    assert tuple(then[0]) == pytest.approx((*b.pose_at(earlier)[:2], b.radius), abs=1e-12)
    assert 0.004 < math.hypot(now[0][0] - then[0][0], now[0][1] - then[0][1]) < 0.006  # 12.5 ms at 0.4 m/s
    # At the world's time or later: where they are (the same circles as without ``at``).
    later = world.other_bodies(0, 2.0, 5.0, 12.0, at=t + 0.5)
    assert later is not None and np.array_equal(later, now)
