"""Turn a scenario and its plan into a populated ``World``: the same for lockstep and real time."""

from __future__ import annotations

import random
from typing import TYPE_CHECKING

import numpy as np

from fleetlink.field.board import BoardConfig
from fleetlink.field.plans import FloorPlan
from fleetlink.field.scenario import RobotSpec, Scenario
from fleetlink.field.world import World

if TYPE_CHECKING:
    from fleetlink.field.lidar import LidarModel

__all__ = ["build_world", "lidar_model", "robot_seed", "start_pose"]


def robot_seed(scenario: Scenario, index: int) -> int:
    """Every random stream of robot ``index`` derives from this, so runs repeat exactly."""
    return scenario.seed * 1000 + index


def start_pose(plan: FloorPlan, spec: RobotSpec) -> tuple[float, float, float]:
    if spec.pose is not None:
        return spec.pose
    assert spec.start is not None
    try:
        x, y, th = plan.starts[spec.start]
    except KeyError:
        known = ", ".join(sorted(plan.starts)) or "none"
        raise ValueError(f"robot {spec.name}: plan {plan.name} has no start {spec.start!r} (known: {known})") from None
    return float(x), float(y), float(th)


def board_config(scenario: Scenario, spec: RobotSpec, index: int) -> BoardConfig:
    noise = scenario.noise
    rng = random.Random(robot_seed(scenario, index))
    return BoardConfig(
        wheel_track=spec.wheel_track,
        wheel_scale=(1.0 + rng.gauss(0.0, noise.wheel_scale_sd), 1.0 + rng.gauss(0.0, noise.wheel_scale_sd)),
        gyro_bias=rng.gauss(0.0, noise.gyro_bias_sd),
        gyro_noise=noise.gyro_noise_sd,
        ultrasonic_noise=noise.ultrasonic_sd,
        noise_seed=robot_seed(scenario, index),
    )


def lidar_model(scenario: Scenario, spec: RobotSpec, index: int) -> LidarModel | None:
    if not (scenario.lidar.enabled and spec.lidar):
        return None
    from fleetlink.field.lidar import LidarConfig, LidarModel

    config = LidarConfig(
        rate_hz=scenario.lidar.rate_hz,
        samples_per_second=scenario.lidar.samples_per_second,
        range_noise_sd=scenario.noise.lidar_range_sd,
        dropout=scenario.noise.lidar_dropout,
    )
    return LidarModel(config, np.random.default_rng(robot_seed(scenario, index)))


def build_world(scenario: Scenario, plan: FloorPlan) -> World:
    world = World(plan.segments(), plan.is_cliff, control_period=scenario.control_period)
    for i, spec in enumerate(scenario.robots):
        world.add_robot(spec.name, start_pose(plan, spec), board_config(scenario, spec, i))
    return world
