"""Open-space mapping as a mission: a scout patrols the exhibition hall (field/scenarios/expo-patrol.toml)
with its whole agent in lockstep, and its map is scored against the plan and the truth.

The hall's walls are 5-12 m from its aisles, where a one-degree scanner draws them as dotted lines; the
loop closer then draws its submaps with their surfaces filled for matching (``CloserConfig.fill_from_range``,
docs/mapping.md "Open spaces"). The run checks that it did, that every closure it accepted is true (the
relative pose it asserts against the truth's), and that the map and the robot's pose in it are where
the plan and the truth have them, in the site frame the UWB anchors give.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fleetlink.agent.mapping.keeper import MapKeeper
from fleetlink.agent.mapping.se2 import relative
from fleetlink.agent.mapping.share import fetch_map
from fleetlink.agent.mapping.worker import DeferredKeeper
from fleetlink.field.plans import nearest_segment_distances
from fleetlink.field.scenario import load_scenario
from fleetlink.shared.map_codec import SharedMap
from fleetlink.site.lockstep import MissionResult, MissionRun

pytestmark = pytest.mark.xdist_group("expo_patrol")

SCENARIO = Path(__file__).resolve().parents[1] / "field" / "scenarios" / "expo-patrol.toml"
PATROL_S = 300.0


class Patrol:
    def __init__(self, result: MissionResult, keeper: MapKeeper, snapshot: SharedMap, segments: np.ndarray) -> None:
        self.result = result
        self.keeper = keeper
        self.map = snapshot
        self.segments = segments
        truth = np.array([row[:4] for row in result.field.truth["scout-1"]])
        self._t, self._x, self._y = truth[:, 0], truth[:, 1], truth[:, 2]
        self._th = np.unwrap(truth[:, 3])

    def truth_at(self, t: float) -> tuple[float, float, float]:
        return (
            float(np.interp(t, self._t, self._x)),
            float(np.interp(t, self._t, self._y)),
            float(np.interp(t, self._t, self._th)),
        )


@pytest.fixture(scope="module")
def patrol() -> Patrol:
    with MissionRun(load_scenario(SCENARIO), record=False, map_worker=False) as run:
        result = run.run(PATROL_S)
        host = run.robots[0].node.keeper
        assert isinstance(host, DeferredKeeper)
        snap = fetch_map(run.operator.zenoh, "scout-1", timeout=2.0)
        assert snap is not None
        return Patrol(result, host.keeper, SharedMap.from_snapshot(snap), run.plan.segments())


@pytest.mark.slow
def test_the_patrol_goes_round_the_hall(patrol: Patrol) -> None:
    reached = [e for e in patrol.result.events if e.kind == "goal_reached"]
    assert len(reached) >= 8, [e.kind for e in patrol.result.events]
    assert patrol.result.field.stats["scout-1"]["watchdog_trips"] == 0


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
    rows, cols = np.nonzero(m.cells >= 65)
    pts = np.column_stack((m.origin[0] + (cols + 0.5) * m.resolution, m.origin[1] + (rows + 0.5) * m.resolution))
    d = nearest_segment_distances(pts, patrol.segments)
    assert len(d) > 5000  # the hall's walls, its pillars, the stage and the stands
    assert float(np.median(d)) <= 0.05 and float(d.mean()) < 0.07, (float(np.median(d)), float(d.mean()))
