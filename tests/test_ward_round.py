"""A UV disinfection robot's round of a hospital floor without UWB (field/scenarios/ward-dark.toml),
its whole agent in lockstep: two identical wings of twelve rooms joined by a 40 m link corridor, the
goals sent one after another on the robot's own map, as a person at the console picks them.

Down the link the scans fix nothing along the corridor (for 16 m of it both ends lie beyond the
lidar's 12 m): the odometry alone carries the pose there. Before the agent held its own-frame turns
to the odometry's step as a replay does (``OnboardMapper.add_scan_odometry``), the matcher held the
pose back where the map was drawn: in 600 s of wandering the map's pose fell 10 m behind the robot in
the link, the map came out 3.0 m from the truth after the best rigid alignment (11.5 m at worst), and
sent across the link the robot turned back halfway, blocked against a wall its map did not have yet.

Back from the other wing every doorway looks like the one a room along, and the map has not been held
by a closure for the 80 m of the link there and back: every closure the map accepted is checked
against the truth's relative pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
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
from tests.harness.scoring import aligned_rmse, truth_at, wall_distances

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("ward_round")]

SCENARIO = Path(__file__).resolve().parents[1] / "field" / "scenarios" / "ward-dark.toml"
# Wing A's room 3, the link's far end, wing B's room 3, back along the link, wing A's room 4 (its
# neighbour's twin), and the end of wing A's corridor where the robot started.
ROUND = ("a-3", "link-east", "b-3", "link-west", "a-4", "a-end")
STEP_S = 5.0
LIMIT_S = 900.0  # the round takes 435 s (measured)


@dataclass
class Round:
    outcomes: list[tuple[str, str | None]]
    result: MissionResult
    keeper: MapKeeper
    map: SharedMap
    segments: np.ndarray

    def __post_init__(self) -> None:
        self.truth_at = truth_at(self.result.field.truth["uvc-1"])


@pytest.fixture(scope="module")
def ward_round() -> Round:
    with MissionRun(load_scenario(SCENARIO), record=False, map_worker=False) as run:
        assert run.uwb is None and run.robots[0].own_frame is not None  # its own map's frame
        run.run(STEP_S)
        outcomes = run.visit("uvc-1", ROUND, step_s=STEP_S, until_s=LIMIT_S)
        result = run.run(run.clock.now() + STEP_S)
        host = run.robots[0].node.keeper
        assert isinstance(host, DeferredKeeper)
        snap = fetch_map(run.operator.zenoh, "uvc-1", timeout=2.0)
        assert snap is not None
        return Round(outcomes, result, host.keeper, SharedMap.from_snapshot(snap), run.plan.segments())


def test_the_round_reaches_every_room_in_both_wings(ward_round: Round) -> None:
    assert ward_round.outcomes == [(place, "goal_reached") for place in ROUND], ward_round.outcomes
    assert ward_round.result.field.stats["uvc-1"]["watchdog_trips"] == 0
    # It went there, not only its map: the truth at the far room (b-3 stands at x 81.5).
    far = max(row[1] for row in ward_round.result.field.truth["uvc-1"])
    assert far > 75.0, far


def test_every_closure_the_map_took_is_true(ward_round: Round) -> None:
    closer = ward_round.keeper.mapper.closer
    assert closer is not None
    assert len(closer.closures) >= 20, closer.stats  # measured 40
    for c in closer.closures:
        a, b = ward_round.truth_at(closer.times[c.anchor]), ward_round.truth_at(closer.times[c.node])
        z = relative(a, b)
        assert math.hypot(c.z[0] - z[0], c.z[1] - z[1]) < 0.1, (c, z)
        assert abs(math.remainder(c.z[2] - z[2], math.tau)) < math.radians(3.0), (c, z)


def test_the_map_holds_along_the_link_and_its_walls_lie_on_the_plans(ward_round: Round) -> None:
    traj = ward_round.keeper.mapper.corrected_trajectory()
    est = [q for _, q in traj]
    truth = [ward_round.truth_at(t) for t, _ in traj]
    # After the best rigid alignment (its own frame is the start's, turned by the first metres' error):
    # measured 0.041 m RMSE, 0.13 m at worst (8.8 m with the pose held by the scans alone; the odometry 3.1 m).
    rmse, tf = aligned_rmse(est, truth)
    assert rmse <= 0.1, rmse
    xy = transform_xy(tf, np.array([q[:2] for q in est]))
    worst = float(np.max(np.hypot(xy[:, 0] - [q[0] for q in truth], xy[:, 1] - [q[1] for q in truth])))
    assert worst <= 0.3, worst
    # The map served to the console, moved by the same transform: its walls on the plan's, the link's
    # 40 m included (the far wing drawn where it is, not a room along). Measured median 0.038 m, mean
    # 0.040 m over 11 936 wall cells.
    m = ward_round.map
    d = wall_distances(m.cells, m.origin, m.resolution, ward_round.segments, tf)
    assert len(d) > 5000
    assert float(np.median(d)) <= 0.06 and float(d.mean()) < 0.1, (float(np.median(d)), float(d.mean()))
