"""Collision guard: thresholds, backing away, the go-to drive check, cliff, bump, invalid commands."""

from __future__ import annotations

import math

import pytest

from fleetlink.agent.guard import CollisionGuard, GuardConfig, GuardInputs, RefusalReason

G = CollisionGuard(GuardConfig(stop_distance_m=0.4))


@pytest.mark.parametrize("reading", [None, 0.0, 1.6, math.inf, math.nan, 0.2, 0.41, 1.5])
def test_clear_or_out_of_range_readings_pass_everything(reading: float | None) -> None:
    d = G.filter(0.3, 0.5, GuardInputs(ultrasonic_m=reading))
    assert (d.v, d.omega, d.refusal) == (0.3, 0.5, None)


@pytest.mark.parametrize(("v", "omega"), [(0.2, 0.0), (0.05, 0.3), (0.0, 1.0), (0.0, -1.0)])
def test_forward_and_turning_refused_below_threshold(v: float, omega: float) -> None:
    d = G.filter(v, omega, GuardInputs(ultrasonic_m=0.3))
    assert (d.v, d.omega) == (0.0, 0.0)
    assert d.refusal is not None and d.refusal.reason is RefusalReason.OBSTACLE_AHEAD
    assert d.refusal.distance_m == 0.3 and "0.30 m" in d.refusal.text


def test_threshold_is_strict() -> None:
    assert G.filter(0.2, 0.0, GuardInputs(ultrasonic_m=0.39)).refused
    assert not G.filter(0.2, 0.0, GuardInputs(ultrasonic_m=0.40)).refused


@pytest.mark.parametrize("inputs", [GuardInputs(0.26), GuardInputs(None, cliff=True), GuardInputs(None, bumped=True)])
def test_backing_away_always_allowed(inputs: GuardInputs) -> None:
    d = G.filter(-0.2, 0.3, inputs)
    assert (d.v, d.omega, d.refusal) == (-0.2, 0.3, None)


def test_standing_still_is_never_a_refusal() -> None:
    assert not G.filter(0.0, 0.0, GuardInputs(0.26, cliff=True, bumped=True)).refused


def test_turn_in_place_option_for_round_bases() -> None:
    g = CollisionGuard(GuardConfig(allow_turn_in_place=True))
    assert not g.filter(0.0, 1.0, GuardInputs(0.3)).refused
    assert g.filter(0.1, 1.0, GuardInputs(0.3)).refused


def test_a_creeping_guard_slows_to_the_wall_and_the_bumper_is_the_last_stop() -> None:
    g = CollisionGuard(GuardConfig(stop_distance_m=0.4, creep_speed_mps=0.05))
    # On a planned path, inside the stop distance forward motion creeps on (an arc keeps its
    # turn), slower asks pass.
    d = g.filter(0.3, 0.2, GuardInputs(0.3), on_path=True)
    assert (d.v, d.omega, d.refusal) == (0.05, 0.2, None)
    assert g.filter(0.02, 0.0, GuardInputs(0.26), on_path=True).v == 0.02
    # Beyond it, full speed; a drive start is not refused for what the cone sees further on.
    assert g.filter(0.3, 0.0, GuardInputs(0.45), on_path=True).v == 0.3
    assert not g.filter(0.3, 0.0, GuardInputs(0.8), goto_drive_distance_m=1.0, on_path=True).refused
    # Off a planned path (straight at a goal with no map, teleop): the seed's rules.
    assert g.filter(0.3, 0.0, GuardInputs(0.3)).refused
    assert g.filter(0.3, 0.0, GuardInputs(0.8), goto_drive_distance_m=1.0).refused
    # The bumper and the cliff sensors still stop it; turning in place keeps the seed's rule.
    assert g.filter(0.05, 0.0, GuardInputs(0.26, bumped=True), on_path=True).refusal is not None
    assert g.filter(0.05, 0.0, GuardInputs(None, cliff=True), on_path=True).refusal is not None
    assert g.filter(0.0, 1.0, GuardInputs(0.3), on_path=True).refused
    with pytest.raises(ValueError, match="creep_speed_mps"):
        GuardConfig(creep_speed_mps=math.nan)


def test_cliff_and_bump_stop_forward_and_turning() -> None:
    c = G.filter(0.2, 0.0, GuardInputs(None, cliff=True))
    b = G.filter(0.0, 0.5, GuardInputs(None, bumped=True))
    assert c.refusal is not None and c.refusal.reason is RefusalReason.CLIFF and (c.v, c.omega) == (0, 0)
    assert b.refusal is not None and b.refusal.reason is RefusalReason.BUMP and (b.v, b.omega) == (0, 0)


def test_goto_drive_needs_distance_plus_threshold() -> None:
    # 1.0 m to the goal, obstacle at 1.3 m: the robot would end 0.3 m from it, inside the 0.4 m margin.
    d = G.filter(0.3, 0.0, GuardInputs(1.3), goto_drive_distance_m=1.0)
    assert d.refusal is not None and d.refusal.reason is RefusalReason.OBSTACLE_IN_PATH
    assert not G.filter(0.3, 0.0, GuardInputs(1.45), goto_drive_distance_m=1.0).refused
    # Nothing seen (beyond the sensor's range) is not an obstacle.
    assert not G.filter(0.3, 0.0, GuardInputs(None), goto_drive_distance_m=5.0).refused
    # Without a drive distance only the plain threshold applies.
    assert not G.filter(0.3, 0.0, GuardInputs(1.3)).refused


@pytest.mark.parametrize(("v", "omega"), [(math.nan, 0.0), (0.0, math.inf), (-math.inf, 0.0)])
def test_invalid_commands_refused(v: float, omega: float) -> None:
    d = G.filter(v, omega, GuardInputs())
    assert d.refusal is not None and d.refusal.reason is RefusalReason.INVALID_COMMAND and (d.v, d.omega) == (0, 0)


def test_config_validated() -> None:
    with pytest.raises(ValueError, match="stop_distance_m"):
        GuardConfig(stop_distance_m=-1)
    with pytest.raises(ValueError, match="below"):
        GuardConfig(sensor_min_m=2.0, sensor_max_m=1.0)
