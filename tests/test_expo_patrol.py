"""Open-space mapping as a mission: a scout patrols the exhibition hall (field/scenarios/expo-patrol.toml)
with its whole agent in lockstep, and its map is scored against the plan and the truth; then again in a
hall without UWB (field/scenarios/expo-dark.toml), where the map is the robot's only reference.

The hall's walls are 5-12 m from its aisles, where a one-degree scanner draws them as dotted lines; the
loop closer then draws its submaps with their surfaces filled for matching (``CloserConfig.fill_from_range``,
docs/mapping.md "Open spaces"). The run checks that it did, that every closure it accepted is true (the
relative pose it asserts against the truth's), and that the map and the robot's pose in it are where
the plan and the truth have them, in the site frame the UWB anchors give.

Without anchors the robot is never placed in the site frame: its map is built in its own frame (the
odometry's where it started), each turn matched where the map's last pose moved by the odometry puts
it, and the robot is localised on that map (``Update.odom_frame``), so the pilot drives among the
walls it plans on. The scripted operator picks the patrol's places on that map, as a person at the
console would. Before this (the map seeded with the fused pose, which without UWB is the odometry
and its drift), the same patrol's map was 3.2 m from the truth (aligned) and its walls 2.4 m from the
plan's, and the robot failed or gave up half its goals.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fleetlink.agent.mapping.keeper import MapKeeper
from fleetlink.agent.mapping.relations import transform_xy
from fleetlink.agent.mapping.share import fetch_map
from fleetlink.agent.mapping.worker import DeferredKeeper
from fleetlink.field.scenario import load_scenario
from fleetlink.shared.map_codec import SharedMap
from fleetlink.shared.se2 import relative
from fleetlink.site.lockstep import MissionResult, MissionRun
from tests.harness.scoring import aligned_rmse, wall_distances

# Each patrol's tests on one worker (its module-scoped run once there), the two patrols on two.
WITH_UWB = pytest.mark.xdist_group("expo_patrol")
WITHOUT_UWB = pytest.mark.xdist_group("expo_patrol_own_frame")

SCENARIO = Path(__file__).resolve().parents[1] / "field" / "scenarios" / "expo-patrol.toml"
DARK = SCENARIO.with_name("expo-dark.toml")  # the same patrol with the site's UWB off
PATROL_S = 300.0


Pose = tuple[float, float, float]


class Patrol:
    def __init__(
        self, result: MissionResult, keeper: MapKeeper, snapshot: SharedMap, segments: np.ndarray, start: Pose
    ) -> None:
        self.result = result
        self.keeper = keeper
        self.map = snapshot
        self.segments = segments
        self.start = start  # where the robot started (the own frame's origin, without UWB)
        truth = np.array([row[:4] for row in result.field.truth["scout-1"]])
        self._t, self._x, self._y = truth[:, 0], truth[:, 1], truth[:, 2]
        self._th = np.unwrap(truth[:, 3])

    def truth_at(self, t: float) -> tuple[float, float, float]:
        return (
            float(np.interp(t, self._t, self._x)),
            float(np.interp(t, self._t, self._y)),
            float(np.interp(t, self._t, self._th)),
        )


def _patrol(path: Path) -> Patrol:
    with MissionRun(load_scenario(path), record=False, map_worker=False) as run:
        assert (run.uwb is None) == (path == DARK)
        st = run.field.rigs[0].robot.board.state
        start = (st.x, st.y, st.theta)
        result = run.run(PATROL_S)
        host = run.robots[0].node.keeper
        assert isinstance(host, DeferredKeeper)
        snap = fetch_map(run.operator.zenoh, "scout-1", timeout=2.0)
        assert snap is not None
        return Patrol(result, host.keeper, SharedMap.from_snapshot(snap), run.plan.segments(), start)


@pytest.fixture(scope="module")
def patrol() -> Patrol:
    return _patrol(SCENARIO)


@pytest.fixture(scope="module")
def patrol_without_uwb() -> Patrol:
    return _patrol(DARK)


@WITH_UWB
@pytest.mark.slow
def test_the_patrol_goes_round_the_hall(patrol: Patrol) -> None:
    reached = [e for e in patrol.result.events if e.kind == "goal_reached"]
    assert len(reached) >= 8, [e.kind for e in patrol.result.events]
    assert patrol.result.field.stats["scout-1"]["watchdog_trips"] == 0


@WITH_UWB
@pytest.mark.slow
def test_the_halls_submaps_are_drawn_filled_and_every_closure_is_true(patrol: Patrol) -> None:
    closer = patrol.keeper.mapper.closer
    assert closer is not None
    st = closer.stats
    # Measured 23 of 25 drawn filled at 400 s (with the fill off: 0, and twice the score rejections).
    assert st.submaps_drawn > 5 and st.submaps_filled >= 0.8 * st.submaps_drawn, st
    assert len(closer.closures) >= 20, st
    # Measured over 47 closures: 2 cm (median) and 6 cm (worst) from the truth's relative pose, 0.1 deg
    # and 2.2 deg; the degrees are the truth's, read at the turn's start as the agent dates it, where a
    # robot turning in place at 1 rad/s turns a degree in 17 ms.
    for c in closer.closures:
        a, b = patrol.truth_at(closer.times[c.anchor]), patrol.truth_at(closer.times[c.node])
        z = relative(a, b)
        assert math.hypot(c.z[0] - z[0], c.z[1] - z[1]) < 0.1, (c, z)
        assert abs(math.remainder(c.z[2] - z[2], math.tau)) < math.radians(3.0), (c, z)


@WITH_UWB
@pytest.mark.slow
def test_the_map_and_the_pose_in_it_are_where_the_truth_has_them(patrol: Patrol) -> None:
    # The map's own pose of the robot at every mapped turn, in the site frame (no alignment): the field
    # patrol goal of issue 17 is 0.03 m. Measured 0.016 m RMSE.
    traj = patrol.keeper.mapper.corrected_trajectory()
    assert len(traj) > 1000
    err = [math.hypot(p[0] - q[0], p[1] - q[1]) for (t, p) in traj for q in [patrol.truth_at(t)]]
    assert math.sqrt(float(np.mean(np.square(err)))) <= 0.03
    # The map served to the console: its occupied cells against the plan's walls (5 cm cells on the
    # plan's lattice). Measured median 0.05 m, mean 0.056 m.
    m = patrol.map
    d = wall_distances(m.cells, m.origin, m.resolution, patrol.segments)
    assert len(d) > 5000  # the hall's walls, its pillars, the stage and the stands
    assert float(np.median(d)) <= 0.05 and float(d.mean()) < 0.07, (float(np.median(d)), float(d.mean()))


@WITHOUT_UWB
@pytest.mark.slow
def test_without_uwb_the_map_holds_together_in_its_own_frame_and_the_robot_drives_on_it(
    patrol_without_uwb: Patrol,
) -> None:
    p = patrol_without_uwb
    assert not p.keeper.in_site_frame and p.keeper.restarts == 0  # never placed: no anchors
    reached = [e for e in p.result.events if e.kind == "goal_reached"]
    assert len(reached) >= 8, [e.kind for e in p.result.events]
    closer = p.keeper.mapper.closer
    assert closer is not None and len(closer.closures) >= 20, closer.stats if closer else None
    traj = p.keeper.mapper.corrected_trajectory()
    est = [q for _, q in traj]
    truth = [p.truth_at(t) for t, _ in traj]
    # Consistent: after the one best rigid transform, the map's poses of the robot are where the truth
    # has them (measured 0.021 m RMSE; 3.2 m before the map was built in its own frame) ...
    rmse, tf = aligned_rmse(est, truth)
    assert rmse <= 0.05, rmse
    # ... and the frame is the one it started in (measured 0.24 m RMSE from the start's over the hall:
    # the map turned a fraction of a degree while its first metres were all it had).
    own = transform_xy(p.start, np.array([q[:2] for q in est]))
    drift = np.hypot(own[:, 0] - [q[0] for q in truth], own[:, 1] - [q[1] for q in truth])
    assert math.sqrt(float(np.mean(drift**2))) <= 0.5
    # The map served to the console, moved by the same transform onto the plan: walls on its walls.
    m = p.map
    d = wall_distances(m.cells, m.origin, m.resolution, p.segments, tf)
    assert len(d) > 5000
    assert float(np.median(d)) <= 0.06 and float(d.mean()) < 0.08, (float(np.median(d)), float(d.mean()))
    # The pose the robot publishes (and drives on) is its map's: at the end of the run, on the map's
    # own pose of it, moved onto the truth by the same transform.
    pose = p.result.poses["scout-1"]
    end = transform_xy(tf, np.array([[pose.x, pose.y]]))[0]
    x, y, _ = p.truth_at(p.result.field.sim_seconds)  # published within a twentieth of a second of it
    assert math.hypot(end[0] - x, end[1] - y) <= 0.1, (end, (x, y))
