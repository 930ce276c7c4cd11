"""One fleet map from robots without UWB, as a mission: two scouts sent into the exhibition hall with
the site's UWB down (field/scenarios/expo-dark-team.toml), whole agents in lockstep. Each maps and
localises in its own map's frame, which begins where it started; neither knows where the other began.
The console's fleet map service (site/fleetmap.py) fetches their maps and submaps over the link and
finds each map on the other's by a global search (every heading, anywhere: agent/mapping/fleetmap.py
``_global_match``), then registers them submap by submap and merges them.

Scored against the truth: both robots' trajectories, each put on the fleet map through the frame the
service found for it, against the truth after one rigid motion for both (the fleet map's frame is the
first robot's own, so one motion is all the alignment allowed); the fleet map's walls against the
plan's, through the same motion. The console's overlay before this (each robot's own map drawn as if
its frame were the site's) is the baseline: its two trajectories cannot be aligned by any one motion.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from fleetlink.agent.mapping.fleetmap import FleetResult
from fleetlink.agent.mapping.relations import transform_xy
from fleetlink.agent.mapping.share import fetch_map
from fleetlink.agent.mapping.worker import DeferredKeeper
from fleetlink.field.scenario import load_scenario
from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.maps import MapFollower, to_grid
from fleetlink.operator.rounds import DEFAULT_LAMP, RectArea, RoundRequest, floor_of
from fleetlink.shared.clock import SimClock
from fleetlink.shared.map_codec import SharedMap
from fleetlink.shared.se2 import Pose, compose
from fleetlink.site.fleetmap import FleetMapService
from fleetlink.site.lockstep import MissionResult, MissionRun
from fleetlink.site.rounds import plan_round
from tests.harness.scoring import aligned_rmse, wall_distances

TEAM = Path(__file__).resolve().parents[1] / "field" / "scenarios" / "expo-dark-team.toml"
RUN_S = 200.0

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("fleet_own_frames")]


@dataclass
class Team:
    result: MissionResult
    fleet: FleetResult
    model: FleetModel
    trajectories: dict[str, list[tuple[float, Pose]]]
    """Per robot: its map's pose of it at every mapped turn, in its own frame."""
    segments: np.ndarray

    def truth_at(self, robot: str, t: float) -> Pose:
        truth = np.array([row[:4] for row in self.result.field.truth[robot]])
        th = np.unwrap(truth[:, 3])
        return (
            float(np.interp(t, truth[:, 0], truth[:, 1])),
            float(np.interp(t, truth[:, 0], truth[:, 2])),
            float(np.interp(t, truth[:, 0], th)),
        )


@pytest.fixture(scope="module")
def team() -> Team:
    with MissionRun(load_scenario(TEAM), record=False, map_worker=False) as run:
        assert run.uwb is None
        result = run.run(RUN_S)
        trajectories = {}
        for r in run.robots:
            host = r.node.keeper
            assert isinstance(host, DeferredKeeper)
            assert not host.keeper.in_site_frame, r.name  # never placed: its own frame throughout
            trajectories[r.name] = host.keeper.mapper.corrected_trajectory()
        # The fleet map as the console builds it: maps followed, submaps fetched over the link.
        model = FleetModel("op-test")
        follower = MapFollower(model)
        for r in run.robots:
            snap = fetch_map(run.operator.zenoh, r.name, timeout=2.0)
            assert snap is not None, r.name
            follower.maps[r.name] = SharedMap.from_snapshot(snap)
        service = FleetMapService(follower, threading.Lock(), SimClock(), period_s=0.0, query=run.operator.zenoh)
        builds = 0
        while service.step() and builds < 10:
            builds += 1
        assert service.result is not None
        for r in run.robots:  # and what the console holds of each robot: its map, its last pose
            model.set_grid(r.name, to_grid(follower.maps[r.name]))
            model.apply(result.poses[r.name], "zenoh", result.field.sim_seconds)
        return Team(result, service.result, model, trajectories, run.plan.segments())


def test_both_scouts_patrol_in_their_own_frames(team: Team) -> None:
    for robot in ("scout-1", "scout-2"):
        reached = [e for e in team.result.events if e.kind == "goal_reached" and e.header.robot == robot]
        assert len(reached) >= 3, robot  # measured 6 and 4 in 200 s


def test_each_map_is_found_on_the_other_and_merged_from_its_submaps(team: Team) -> None:
    fleet = team.fleet
    assert fleet.unframed == () and set(fleet.frames) == {"scout-1", "scout-2"}
    for robot in ("scout-1", "scout-2"):  # merged submap by submap, not whole
        assert len(fleet.piece_corrections[robot]) > 5 and -1 not in fleet.piece_corrections[robot], robot
    pairs = {(r.a, r.b) for r in fleet.registrations}
    assert pairs == {("scout-1", "scout-2"), ("scout-2", "scout-1")}
    assert len(fleet.registrations) >= 10  # measured 54
    # The console's model has them: it draws each robot through its frame, and sends goals back
    # through it (tests/test_console_feed.py).
    assert team.model.frames == fleet.frames


def _on_fleet_map(team: Team, frames: dict[str, Pose]) -> tuple[list[Pose], list[Pose]]:
    est, ref = [], []
    for robot, traj in team.trajectories.items():
        for t, p in traj[::5]:
            est.append(compose(frames[robot], p))
            ref.append(team.truth_at(robot, t))
    return est, ref


def test_both_robots_and_the_walls_are_where_the_truth_has_them_up_to_one_motion(team: Team) -> None:
    rmse, tf = aligned_rmse(*_on_fleet_map(team, team.fleet.frames))
    assert rmse <= 0.05, rmse
    # The overlay before: both maps drawn as if their frames were one (each robot's own frame is where
    # it started; they began 2 m and 50 degrees apart).
    overlay, _ = aligned_rmse(*_on_fleet_map(team, {"scout-1": (0.0, 0.0, 0.0), "scout-2": (0.0, 0.0, 0.0)}))
    assert overlay > 20 * rmse
    # The fleet map's walls, through the same motion, against the plan's.
    m = team.fleet
    d = wall_distances(m.cells, m.origin, m.resolution, team.segments, tf)
    assert len(d) > 3000
    assert float(np.median(d)) <= 0.05 and float(d.mean()) < 0.08, (float(np.median(d)), float(d.mean()))


def test_a_sweep_drawn_on_the_fleet_map_is_sent_where_it_lies_in_the_hall(team: Team) -> None:
    """The operator draws a sweep round scout-2 on the fleet map (scout-1's frame). The console plans
    it on scout-2's map put through its frame and sends it back through that frame, in scout-2's own:
    each node, where scout-2 will drive to it (its own frame on the truth), is where the operator drew
    it (the fleet map on the truth). Sent as planned, it would be metres off."""
    model = team.model
    view = model.robots["scout-2"]
    assert view.in_own_frame and view.pose is not None and not view.off_fleet_map
    x, y = view.pose[:2]
    area = RectArea(x - 1.5, y - 1.5, x + 1.5, y + 1.5)
    floor = model.round_floor(("scout-2",), "sweep")
    assert not isinstance(floor, str), floor
    cells, res, origin = floor_of(floor.grids(), floor.trails)
    plan = plan_round(RoundRequest("sweep", area, ("scout-2",)), cells, res, origin, floor.starts, DEFAULT_LAMP)
    (sweep,) = plan.rounds
    planned = np.array([(n.x, n.y) for n in sweep.order["nodes"]])
    sent = np.array([(n.x, n.y) for n in model.order_through(floor.frames["scout-2"], sweep.order)["nodes"]])
    assert len(planned) >= 4
    # Each frame onto the hall, by the truth: the fleet map's (both robots' trajectories on it) and
    # scout-2's own (its trajectory as it mapped it).
    _, fleet_on_truth = aligned_rmse(*_on_fleet_map(team, team.fleet.frames))
    own = team.trajectories["scout-2"]
    _, own_on_truth = aligned_rmse([p for _, p in own], [team.truth_at("scout-2", t) for t, _ in own])
    drawn = transform_xy(fleet_on_truth, planned)
    driven = transform_xy(own_on_truth, sent)
    off = np.hypot(*(driven - drawn).T)
    assert float(off.max()) <= 0.1, off  # measured 0.013 m at most (33 nodes): the frames agree
    as_planned = np.hypot(*(transform_xy(own_on_truth, planned) - drawn).T)
    assert float(as_planned.min()) > 1.0, as_planned  # measured 9.0 m at least
