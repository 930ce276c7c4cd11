"""Loop closure on board: the map moves under the robot, and the pose the pilot drives on moves with it.

The ring corridor of tests/test_loop_closure.py, driven once round and on, with a biased odometry.
UWB places the robot over its first 9 m and then goes quiet (an outage): the fused pose carries on on
odometry alone and drifts, and the map keeper maps every turn at it, as the agent does
(agent/node.py ``add_revolution`` and ``_localise``). With scan matching off the map only follows
the fused pose, and the test tells the keeper the fusion follows the map (``Turn.follows``, as after
map poses pinned all round): when the robot comes back to its start a closure is solved, the map moves
where the robot is, and ``Update.moved`` shifts the fusion's frame by the same transform, at once.
With scan matching on, ``Update.seen`` (the turn's pose as matched in the map) is a pose measurement
for the fusion: the map keeps the robot localised through the outage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cache

import numpy as np
import pytest

from fleetlink.agent.fusion import Fusion, PoseObservation
from fleetlink.agent.mapping.closure import Check, CloserConfig, DeferredSearch, LoopCloser, run_check
from fleetlink.agent.mapping.keeper import MapKeeper, Turn, followed_part, onboard_mapper_config
from fleetlink.agent.mapping.mapper import MapperConfig
from fleetlink.agent.mapping.worker import SearchWorker
from fleetlink.agent.node import PLACE_SD_THETA_RAD
from fleetlink.agent.odometry import OdomPose
from fleetlink.agent.uwb_input import FixObservation
from fleetlink.shared.se2 import compose
from tests.test_loop_closure import STEP, _drive, _run

Pose = tuple[float, float, float]
DT = 0.1  # s between turns
UWB_STEPS = 60  # turns with a fix each (9 m: the map is anchored by then), then the outage


@dataclass
class Shift:
    step: int
    moved: Pose
    before: Pose  # the published fused pose just before the shift
    after: Pose  # ... and just after


@dataclass
class OnboardRun:
    fused: list[Pose]  # the published fused pose at each turn, after the turn's update
    mapped: list[Pose]  # the keeper's mapper pose at each turn (its frame: the map's)
    shifts: list[Shift]
    keeper: MapKeeper
    fusion: Fusion


ROOM = (0.05**2, 0.0, 0.0, 0.0, 0.05**2, 0.0, 0.0, 0.0, math.radians(1.0) ** 2)
"""A map pose pinned in every direction (a room's walls all round)."""


def _onboard(matching: bool, feedback: bool = True, turns: int | None = None, follow_all: bool = False) -> OnboardRun:
    """``follow_all``: the agent tells the keeper its fusion has been following the map in every
    direction (``Turn.follows``), as it would after map poses pinned in a room; with matching off
    there are no map poses, and the closures' corrections are the only news from the map."""
    truth, odom, scans = _drive()
    n = len(scans) if turns is None else turns
    fusion = Fusion()
    # The replay's closer (windows that grow with the path): the outage lets the pose drift metres
    # round the ring, far beyond the on-board window (UWB keeps a robot within centimetres of it).
    config = replace(onboard_mapper_config(), matching=matching, closer=CloserConfig())
    keeper = MapKeeper(config, search=DeferredSearch())
    run = OnboardRun([], [], [], keeper, fusion)
    follows: tuple[float, ...] | None = None
    for i in range(n):
        t = DT * (i + 1)
        fusion.predict(OdomPose(t, *odom[i], STEP / DT, 0.0))
        if i < UWB_STEPS:
            fusion.add_fix(FixObservation(t, truth[i][0], truth[i][1], 0.03, 0.03, 90, "test"), t)
        p = fusion.map_pose()
        r, a = scans[i]
        placed = fusion.heading_initialized and p.sd_theta <= PLACE_SD_THETA_RAD  # as AgentNode places it
        up = keeper.add(Turn(t, r, a, (p.x, p.y, p.theta), placed, True, t, not fusion.uwb_stale(t), follows))
        if feedback and up.moved is not None:  # as AgentNode._localise does
            before = fusion.map_pose()
            fusion.shift_frame(up.moved)
            after = fusion.map_pose()
            run.shifts.append(Shift(i, up.moved, (before.x, before.y, before.theta), (after.x, after.y, after.theta)))
        if feedback and up.seen is not None:
            s = up.seen
            if fusion.add_map_pose(PoseObservation(s.t, *s.pose, s.cov), t).accepted:
                follows = s.cov
        if follow_all and feedback and keeper.in_site_frame:
            follows = ROOM
        q = fusion.map_pose()
        run.fused.append((q.x, q.y, q.theta))
        pose = keeper.mapper.pose
        run.mapped.append(pose if pose is not None else (math.nan, math.nan, math.nan))
    return run


LAP = 300
"""Turns driven in the closing runs: once round the ring (the loop closes at about 277) and 7 m on."""


@cache
def _closing() -> OnboardRun:
    return _onboard(matching=False, turns=LAP, follow_all=True)


@cache
def _ring_mapper() -> LoopCloser:
    """The ring driven on odometry with the replay's closer (checks are planned from it below)."""
    m, _ = _run(MapperConfig(matching=False, closer=CloserConfig()))
    assert m.closer is not None
    return m.closer


def _err(p: Pose, q: Pose) -> float:
    return math.hypot(p[0] - q[0], p[1] - q[1])


def test_a_closure_on_board_moves_the_fused_pose_with_the_map() -> None:
    truth, _, _ = _drive()
    run = _closing()
    closer = run.keeper.mapper.closer
    assert closer is not None and len(closer.closures) >= 2, closer.stats
    assert run.keeper.in_site_frame and run.fusion.uwb_stale(DT * LAP)
    # The outage: by the time the robot is back at its start, the fused pose has drifted.
    big = [s for s in run.shifts if math.hypot(s.moved[0], s.moved[1]) > 0.2]
    assert big, [s.moved for s in run.shifts]
    first = big[0]
    drift = _err(run.fused[first.step - 1], truth[first.step - 1])
    assert drift > 0.3, drift
    # The solve moved the map where the robot is; the published pose moved by the same transform, at once.
    want = compose(first.moved, first.before)
    assert _err(first.after, want) < 1e-9 and abs(math.remainder(first.after[2] - want[2], math.tau)) < 1e-9
    assert run.fusion.frame_shifts == len(run.shifts)
    # So the pose the pilot drives on is where the corrected map puts the robot, and near the truth again.
    k = first.step
    assert _err(run.fused[k], run.mapped[k]) < 0.03, (run.fused[k], run.mapped[k])
    assert _err(run.fused[k], truth[k]) < 0.4 * drift, (_err(run.fused[k], truth[k]), drift)
    # And it stays with the map to the end (every later solve shifts it along).
    gaps = [_err(f, m) for f, m in zip(run.fused[k:], run.mapped[k:], strict=True)]
    assert max(gaps) < 0.05, max(gaps)


def test_without_the_shift_the_map_and_the_pose_part() -> None:
    """The same run with the updates not applied to the fusion (as before on board): after the
    closure the map has moved and the fused pose has not."""
    run = _onboard(matching=False, feedback=False, turns=LAP, follow_all=True)
    closer = run.keeper.mapper.closer
    assert closer is not None and closer.closures
    k = next(s.step for s in _closing().shifts if math.hypot(s.moved[0], s.moved[1]) > 0.2)
    assert _err(run.fused[k], run.mapped[k]) > 0.2


def test_the_maps_pose_keeps_the_robot_localised_through_an_outage() -> None:
    """Scan matching on: each turn's pose as matched in the map is a measurement for the fusion, so
    the fused pose follows the map instead of the odometry's drift while UWB is quiet."""
    truth, _, _ = _drive()
    n = 260  # 37 m round three corners, 28 m of it without UWB
    fed = _onboard(matching=True, turns=n)
    blind = _onboard(matching=True, feedback=False, turns=n)
    assert fed.fusion.map_accepted > 0.8 * (n - UWB_STEPS), (fed.fusion.map_accepted, fed.fusion.last_map_rejection)
    err_fed = max(_err(p, q) for p, q in zip(fed.fused[UWB_STEPS:], truth[UWB_STEPS:n], strict=True))
    err_blind = _err(blind.fused[-1], truth[n - 1])
    assert err_blind > 0.3, err_blind
    assert err_fed < 0.1, err_fed


def test_on_board_runs_are_deterministic() -> None:
    a, b = _closing(), _onboard(matching=False, turns=LAP, follow_all=True)
    assert a.fused == b.fused and a.mapped == b.mapped
    assert [s.moved for s in a.shifts] == [s.moved for s in b.shifts]
    assert np.array_equal(a.keeper.mapper.grid.logodds, b.keeper.mapper.grid.logodds)


def test_the_search_worker_gives_the_in_line_verdicts() -> None:
    """The real-time agent's closure search runs on a thread of its own (``SearchWorker``): the same
    checks give the same verdicts as in line."""
    closer = _ring_mapper()
    for sm in closer.submaps:  # planned afresh: the run tried the submaps near its end last
        sm.tried_at = -(10**9)
    checks: list[Check] = []
    for k in range(len(closer) - 1, 0, -1):
        checks.extend(closer._fresh_checks(k))
        if len(checks) >= 3:
            break
    assert checks
    inline = [run_check(c) for c in checks]
    with SearchWorker("closure-test") as worker:
        worker.submit(checks)
        assert worker.busy
        done = []
        for _ in range(1000):
            done += worker.collect()
            if len(done) == len(checks) and not worker.busy:
                break
            worker.clock.wait(worker._stop, 0.01)
    assert [r.outcome for r in done] == [r.outcome for r in inline]
    for r, s in zip(done, inline, strict=True):
        assert (r.closure is None) == (s.closure is None)
        if r.closure is not None and s.closure is not None:
            assert r.closure.z == s.closure.z
    assert worker.checks == len(checks) and worker.failures == 0


def test_results_planned_by_a_closer_before_a_restart_are_ignored() -> None:
    """The keeper restarts the map when the robot is placed; checks planned by the old map's closer
    that come back afterwards name nodes of a graph that is gone."""
    old = _ring_mapper()
    stale = [run_check(old._check(len(old) - 1, old.submaps[0]))]
    assert stale
    fresh = LoopCloser(CloserConfig())
    fresh.add_node(0.0, (0.0, 0.0, 0.0), old.scans[0])
    assert fresh.take(stale) is False
    assert fresh.stats.attempts == 0 and not fresh.closures


def test_the_pose_moves_with_the_map_only_where_it_followed_the_map() -> None:
    """Down a corridor along x the map's poses pinned y and the heading, not x: the fused pose kept
    UWB's x. A solve that moves the map 0.2 m along x and 0.05 m across moves the pose 0.05 m across."""
    before = (10.0, 2.0, 0.0)
    corridor = (4.0, 0.0, 0.0, 0.0, 0.05**2, 0.0, 0.0, 0.0, math.radians(1.0) ** 2)
    moved = (0.2, 0.05, 0.0)
    part = followed_part(moved, before, corridor)
    after = compose(part, before)
    assert after == pytest.approx((10.0, 2.05, 0.0), abs=1e-12)
    # In a room it pinned every direction: the whole correction, a turn included.
    turn = compose((0.0, 0.0, 0.01), (0.1, -0.1, 0.0))
    assert compose(followed_part(turn, before, ROOM), before) == pytest.approx(compose(turn, before), abs=1e-12)
