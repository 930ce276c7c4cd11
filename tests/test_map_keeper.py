"""The map keeper (agent/mapping/keeper.py) under simulated time, and where it runs
(agent/mapping/worker.py): in line, one turn behind, or one turn behind in a second process."""

from __future__ import annotations

import math
import pickle
import threading
from dataclasses import replace

import numpy as np
import pytest

from fleetlink.agent.mapping.keeper import MapKeeper, Turn, Update, onboard_mapper_config
from fleetlink.agent.mapping.worker import DeferredKeeper, MapWorker
from fleetlink.field.raycast import Raycaster
from fleetlink.shared.worker import ProcessWorker

ROOM = np.array([[0.0, 0.0, 6.0, 0.0], [6.0, 0.0, 6.0, 4.0], [6.0, 4.0, 0.0, 4.0], [0.0, 4.0, 0.0, 0.0]])
ANGLES = np.linspace(0.0, 2 * math.pi, 360, endpoint=False)
CASTER = Raycaster(ROOM)


def _scan(pose: tuple[float, float, float]) -> np.ndarray:
    r = CASTER.cast_fan(pose[0], pose[1], pose[2], 2 * math.pi / 360, 360, 12.0)
    return np.where(np.isfinite(r), r, 0.0)


def _turn(
    keeper: MapKeeper, t: float, pose: tuple[float, float, float], *, placed: bool = True, driving: bool = True
) -> Update:
    return keeper.add(Turn(t, _scan(pose), ANGLES, pose, placed=placed, driving=driving, now=t))


def test_the_first_turn_gives_a_planner_and_a_publication() -> None:
    keeper = MapKeeper()
    up = _turn(keeper, 0.0, (1.0, 1.0, 0.0))
    assert up.planner is not None and up.publication is not None and not up.restarted
    pub = up.publication
    assert pub.version == keeper.mapper.version == 1
    assert pub.changed is not None and pub.cells.dtype == np.int8
    assert ((pub.cells >= 0) & (pub.cells < 50)).sum() > 1000  # free floor seen
    assert up.planner.route((1.0, 1.0), (2.0, 1.5))  # a route across the room it has seen


def test_the_motion_filter_skips_turns_seen_from_the_same_place() -> None:
    keeper = MapKeeper()
    _turn(keeper, 0.0, (1.0, 1.0, 0.0))
    for i in range(1, 5):  # standing still for 0.4 s: nothing new to map
        up = _turn(keeper, 0.1 * i, (1.0, 1.0, 0.0))
        assert up == Update()
    assert keeper.skipped == 4 and keeper.mapper.scans == 1
    _turn(keeper, 0.5, (1.0 + keeper.min_move_m, 1.0, 0.0))  # moved: mapped
    _turn(keeper, 0.6, (1.0 + keeper.min_move_m, 1.0, keeper.min_turn_rad))  # turned: mapped
    assert keeper.mapper.scans == 3
    _turn(keeper, 0.6 + keeper.max_gap_s, (1.0 + keeper.min_move_m, 1.0, keeper.min_turn_rad))  # a while later
    assert keeper.mapper.scans == 4 and keeper.skipped == 4


def test_the_map_restarts_once_when_the_robot_is_placed_in_the_site_frame() -> None:
    keeper = MapKeeper()
    old = _turn(keeper, 0.0, (1.0, 1.0, 0.0), placed=False).publication
    first = keeper.mapper
    up = _turn(keeper, 0.1, (1.2, 1.0, 0.0), placed=True)
    assert up.restarted and keeper.restarts == 1 and keeper.mapper is not first
    # The new map is shared and planned at once, though the old one was shared a moment ago, and
    # its version goes on from the old one's: a console takes it as newer and fetches it.
    assert up.planner is not None and up.publication is not None and old is not None
    assert up.publication.version > old.version and keeper.mapper.version == 1
    up = _turn(keeper, 0.5, (1.6, 1.0, 0.0), placed=True)
    assert not up.restarted and keeper.restarts == 1


def test_planners_are_renewed_while_driving_at_the_planner_period() -> None:
    keeper = MapKeeper(planner_period=2.0)
    t, x, planners = 0.0, 1.0, []
    while t < 6.0:
        up = _turn(keeper, t, (x, 1.0, 0.0))
        if up.planner is not None:
            planners.append(t)
        t, x = round(t + 0.1, 6), x + 0.02  # 0.2 m/s: a new keyframe every half second
    assert planners == [0.0, 2.0, 4.0]
    # Standing still, the map changes only by noise: no new planner however long it waits.
    for i in range(30):
        up = _turn(keeper, 6.0 + i, (x, 1.0, 0.0), driving=False)
        assert up.planner is None


def test_publications_come_at_the_share_period_while_the_map_changes() -> None:
    keeper = MapKeeper(share_period=1.0)
    t, x, shared = 0.0, 1.0, []
    while t < 3.05:
        up = _turn(keeper, t, (x, 1.0, 0.0))
        if up.publication is not None:
            shared.append((t, up.publication.version))
        t, x = round(t + 0.1, 6), x + 0.02
    assert [s[0] for s in shared] == [0.0, 1.0, 2.0, 3.0]
    versions = [s[1] for s in shared]
    assert versions == sorted(versions) and len(set(versions)) == len(versions)
    assert versions[-1] == keeper.mapper.version


def _same(a: Update | None, b: Update | None) -> bool:
    if a is None or b is None:
        return a is b
    if a.restarted != b.restarted or (a.planner is None) != (b.planner is None):
        return False
    pa_, pb_ = a.planner, b.planner
    if (
        pa_ is not None
        and pb_ is not None
        and not (np.array_equal(pa_.blocked, pb_.blocked) and pa_.origin == pb_.origin)
    ):
        return False
    if (a.publication is None) != (b.publication is None):
        return False
    if a.publication is not None and b.publication is not None:
        pa, pb = a.publication, b.publication
        return (pa.version, pa.changed, pa.origin) == (pb.version, pb.changed, pb.origin) and np.array_equal(
            pa.cells, pb.cells
        )
    return True


def test_a_keeper_in_the_map_worker_gives_what_one_in_line_gives_one_turn_late() -> None:
    robots = ("r1", "r2")
    inline = {r: DeferredKeeper() for r in robots}
    direct = {r: MapKeeper() for r in robots}
    with MapWorker() as worker:
        remote = {r: worker.keeper(r) for r in robots}
        with pytest.raises(ValueError):
            worker.keeper("r1")
        previous: dict[str, Update | None] = {r: None for r in robots}
        came: list[Update] = []
        for k in range(25):
            t = 0.1 * k
            for j, r in enumerate(robots):  # interleaved, as a lockstep run steps its robots
                pose = (1.0 + 0.03 * k, 1.0 + j, 0.02 * k)
                turn = Turn(t, _scan(pose), ANGLES, pose, placed=k >= 5, driving=True, now=t)
                now_update = direct[r].add(turn)
                a, b = inline[r].add(turn), remote[r].add(turn)
                assert _same(a, previous[r]) and _same(b, previous[r]), (r, k)
                previous[r] = now_update
                if b is not None:
                    came.append(b)
        # What came through the process: restarts (placed at k = 5), planners and publications.
        assert sum(u.restarted for u in came) == 2
        assert sum(u.planner is not None for u in came) >= 4
        assert sum(u.publication is not None for u in came) >= 4


def test_a_keeper_forgotten_in_the_map_worker_opens_again_with_a_map_begun_anew() -> None:
    """An agent restarted in a lockstep run (``MissionRun.restart_agent``): its keeper in the worker
    is let go with a reply still owed, and a new one under its name maps from nothing, one turn late
    as before, while the other robot's keeper goes on undisturbed."""
    with MapWorker() as worker:
        keepers = {r: worker.keeper(r) for r in ("r1", "r2")}
        alone = DeferredKeeper()
        for k in range(6):
            for j, r in enumerate(("r1", "r2")):
                pose = (1.0 + 0.03 * k, 1.0 + j, 0.02 * k)
                turn = Turn(0.1 * k, _scan(pose), ANGLES, pose, placed=False, driving=True, now=0.1 * k)
                keepers[r].add(turn)
                if r == "r2":
                    alone.add(turn)
        worker.forget("r1")  # one reply owed: read and dropped
        fresh, again = DeferredKeeper(), worker.keeper("r1")
        for k in range(6, 12):
            pose = (1.0 + 0.03 * k, 1.0, 0.02 * k)
            turn = Turn(0.1 * k, _scan(pose), ANGLES, pose, placed=False, driving=True, now=0.1 * k)
            assert _same(again.add(turn), fresh.add(turn)), k
            pose2 = (1.0 + 0.03 * k, 2.0, 0.02 * k)
            turn2 = Turn(0.1 * k, _scan(pose2), ANGLES, pose2, placed=False, driving=True, now=0.1 * k)
            assert _same(keepers["r2"].add(turn2), alone.add(turn2)), k


class _Echo:
    def __init__(self) -> None:
        self.told: list[object] = []

    def __call__(self, request: object) -> object:
        if isinstance(request, np.ndarray):
            return ("echo", request)
        if request == "boom":
            raise ValueError("boom")
        if request == "told?":
            return list(self.told)
        if request == "lambda":
            return lambda: None  # cannot be pickled back
        if isinstance(request, tuple) and request[0] == "tell":
            self.told.append(request[1])
        return None


def test_the_process_worker_replies_in_order_and_survives_bad_requests() -> None:
    worker = ProcessWorker("test-echo", _Echo)
    try:
        with pytest.raises(RuntimeError):
            worker.reply()  # nothing asked
        for i in range(100):  # large both ways: far more than a pipe holds before anyone reads
            worker.call(np.full(10_000, i))
        worker.tell(("tell", "a"))
        worker.call("boom")
        worker.call("lambda")
        with pytest.raises((TypeError, AttributeError, pickle.PicklingError)):
            worker.call(threading.Lock())  # cannot be sent: refused here, nothing pending
        worker.tell(("tell", "b"))
        worker.call("told?")
        assert worker.pending == 103
        for i in range(100):
            kind, arr = worker.reply()
            assert kind == "echo" and int(arr[0]) == i and arr.shape == (10_000,)
        with pytest.raises(RuntimeError, match="ValueError: boom"):
            worker.reply()
        with pytest.raises(RuntimeError, match="cannot be sent"):
            worker.reply()
        assert worker.reply() == ["a", "b"]  # the worker served on after each failure
        assert worker.pending == 0
    finally:
        worker.close()
    worker.close()  # idempotent


def _drifting_drive() -> tuple[list[tuple[float, float, float]], list[tuple[float, float, float]]]:
    """A drive round the room and the odometry of it (its frame: where the drive starts), whose heading
    drifts 0.004 rad a step (a gyro bias): 0.4 rad by the end."""
    truth: list[tuple[float, float, float]] = []
    x, y, th = 1.0, 1.0, 0.0
    for i in range(100):
        truth.append((x, y, th))
        turn = 0.12 if 20 <= i < 33 or 60 <= i < 73 else 0.0  # two half turns
        x, y, th = x + 0.08 * math.cos(th), y + 0.08 * math.sin(th), th + turn
        x, y = min(max(x, 0.8), 5.2), min(max(y, 0.8), 3.2)
    odom = [(0.0, 0.0, 0.0)]
    for i in range(1, len(truth)):
        a, b = truth[i - 1], truth[i]
        c, s = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        fwd, lat, dth = c * dx + s * dy, -s * dx + c * dy, b[2] - a[2] + 0.004
        o = odom[-1]
        co, so = math.cos(o[2]), math.sin(o[2])
        odom.append((o[0] + co * fwd - so * lat, o[1] + so * fwd + co * lat, o[2] + dth))
    return truth, odom


def _in_start_frame(truth: list[tuple[float, float, float]]) -> list[tuple[float, float, float]]:
    x0, y0, t0 = truth[0]
    c, s = math.cos(t0), math.sin(t0)
    return [(c * (x - x0) + s * (y - y0), -s * (x - x0) + c * (y - y0), th - t0) for x, y, th in truth]


@pytest.mark.parametrize("own_frame", [True, False])
def test_without_a_uwb_position_the_map_is_built_in_its_own_frame_on_the_odometry(own_frame: bool) -> None:
    # Without UWB the fused pose is the odometry. Given it as the turn's odometry (the agent does while
    # the fusion has no position), the map matches each turn where its last pose moved by the odometry
    # puts it and stays in the frame it began in; seeded with the drifting pose itself (before), it
    # follows the drift.
    truth, odom = _drifting_drive()
    want = _in_start_frame(truth)
    keeper = MapKeeper()
    last = Update()
    for i, (p, o) in enumerate(zip(truth, odom, strict=True)):
        turn = Turn(0.1 * i, _scan(p), ANGLES, o, placed=False, driving=True, now=0.1 * i)
        last = keeper.add(Turn(**{**_fields(turn), "odometry": o}) if own_frame else turn)
    mapped = keeper.mapper.trajectory
    err = [math.hypot(q[0] - want[round(t * 10)][0], q[1] - want[round(t * 10)][1]) for t, q in mapped]
    drift = max(math.hypot(o[0] - w[0], o[1] - w[1]) for o, w in zip(odom, want, strict=True))
    assert drift > 0.5  # what the odometry alone would show
    if own_frame:
        assert max(err) < 0.05, max(err)
        # The transform that puts the odometry on the map: the map's last pose of the robot.
        assert last.odom_frame is not None and keeper.mapper.pose is not None
        c, s = math.cos(last.odom_frame[2]), math.sin(last.odom_frame[2])
        o = odom[-1]
        placed = (last.odom_frame[0] + c * o[0] - s * o[1], last.odom_frame[1] + s * o[0] + c * o[1])
        assert math.dist(placed, keeper.mapper.pose[:2]) < 1e-9
    else:
        assert max(err) > 0.2, max(err)
        assert last.odom_frame is None


def test_placed_turns_are_mapped_at_the_fused_pose_and_carry_no_odom_frame() -> None:
    keeper = MapKeeper()
    up = keeper.add(
        Turn(0.0, _scan((1.0, 1.0, 0.0)), ANGLES, (0.0, 0.0, 0.0), False, True, 0.0, odometry=(0.0, 0.0, 0.0))
    )
    assert up.odom_frame == (0.0, 0.0, 0.0)
    up = keeper.add(Turn(0.1, _scan((1.2, 1.0, 0.0)), ANGLES, (1.2, 1.0, 0.0), True, True, 0.1))
    assert up.restarted and up.odom_frame is None and keeper.in_site_frame


def _fields(turn: Turn) -> dict[str, object]:
    return {name: getattr(turn, name) for name in Turn.__dataclass_fields__}


HALL = np.array([[0.0, 0.0, 40.0, 0.0], [0.0, 6.0, 40.0, 6.0], [0.0, 0.0, 0.0, 6.0], [40.0, 0.0, 40.0, 6.0]])
GHOST = np.array(  # another robot standing 1.2 m ahead, a 0.3 m box
    [[3.05, 2.85, 3.35, 2.85], [3.35, 2.85, 3.35, 3.15], [3.35, 3.15, 3.05, 3.15], [3.05, 3.15, 3.05, 2.85]]
)


def _hall_scan(pose: tuple[float, float, float], ghost: bool) -> np.ndarray:
    caster = Raycaster(np.vstack([HALL, GHOST]) if ghost else HALL)
    r = caster.cast_fan(pose[0], pose[1], pose[2], 2 * math.pi / 360, 360, 12.0)
    return np.where(np.isfinite(r), r, 0.0)  # the RPLIDAR's "nothing within 12 m"


def _ghost_left(keeper: MapKeeper, *, waiting: bool, seconds: float = 3.0) -> bool:
    """Drive up the hall towards another robot standing ahead (the far wall 38 m off: beyond it nothing
    returns), stop 1 m short; it leaves; stand ``seconds`` looking. True if the map still holds it."""
    t = 0.0
    for k in range(16):
        pose = (0.5 + 0.1 * k, 3.0, 0.0)
        keeper.add(Turn(t, _hall_scan(pose, True), ANGLES, pose, placed=True, driving=True, now=t))
        t += 0.1
    while t < 1.6 + seconds:
        keeper.add(Turn(t, _hall_scan(pose, False), ANGLES, pose, placed=True, driving=True, now=t, waiting=waiting))
        t += 0.1
    cells, res, origin = keeper.mapper.occupancy()
    face = cells[int((3.0 - origin[1]) / res), int((3.07 - origin[0]) / res)]
    return bool(face >= 65)


def test_a_robot_waiting_for_the_way_to_clear_sees_through_where_another_stood_in_an_open_hall() -> None:
    """The two-scout console test's goal where the other scout had just stood: the pilot waits for the
    way to clear (``Turn.waiting``); the map then integrates a turn every ``keyframe_period_waiting``,
    and the beams that return nothing within the lidar's range (a sector of the RPLIDAR's 0) clear
    their first ``missing_ray`` metres. Either alone leaves the other robot on the map: standing, a
    turn joins the map every 5 s; with no wall within 12 m behind it, no beam through it returns."""
    assert not _ghost_left(MapKeeper(), waiting=True)
    assert _ghost_left(MapKeeper(), waiting=False)
    assert _ghost_left(MapKeeper(replace(onboard_mapper_config(), missing_ray=0.0)), waiting=True)
