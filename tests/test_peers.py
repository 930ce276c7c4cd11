"""Other robots as bodies to plan around (agent/peers.py): what a peer's pose counts for, the planner
keeping clear of a robot standing behind its own mapped face, and the agent core hearing peers
without taking them for commands."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from fleetlink.agent.core import AgentCore
from fleetlink.agent.fusion import Fusion
from fleetlink.agent.guard import CollisionGuard
from fleetlink.agent.mapping.planner import PathPlanner, PlannerConfig
from fleetlink.agent.motion import GoToConfig
from fleetlink.agent.peers import PeerBodies, PeerConfig
from fleetlink.agent.pilot import Pilot
from fleetlink.shared import keys, wire
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import UNKNOWN_SD_M, FleetFrames, LinkName, Pose, RobotFrame

RES = 0.05


def _pose(
    robot: str,
    x: float,
    y: float,
    *,
    t: float,
    vx: float = 0.0,
    omega: float = 0.0,
    sd: float = 0.01,
    began: float = 0.0,
) -> Pose:
    counter = wire.HeaderCounter(SimClock(t), robot=robot, sender=f"agent-{robot}")
    return counter.make(
        Pose,
        x=x,
        y=y,
        theta=0.0,
        sd_x_m=sd,
        sd_y_m=sd,
        sd_theta_rad=0.01,
        odom_x=0.0,
        odom_y=0.0,
        odom_theta=0.0,
        vx=vx,
        omega=omega,
        uwbStale=False,
        map_began=began,
    )


def test_only_peers_standing_still_in_the_site_frame_and_heard_lately_count() -> None:
    peers = PeerBodies(("r2", "r3", "r4", "r5"))
    assert peers.hear("r2", _pose("r2", 1.0, 2.0, t=10.0), now=10.0)
    assert peers.hear("r3", _pose("r3", 3.0, 1.0, t=10.0, vx=0.3), now=10.0)  # driving
    assert peers.hear("r4", _pose("r4", 5.0, 1.0, t=10.0, sd=UNKNOWN_SD_M), now=10.0)  # not placed
    assert peers.hear("r5", _pose("r5", 6.0, 1.0, t=10.0, omega=0.4), now=10.0)  # turning in place
    assert not peers.hear("r9", _pose("r9", 0.0, 0.0, t=10.0), now=10.0)  # not a peer
    assert peers.standing(10.5) == ((1.0, 2.0),)
    assert peers.standing(11.5) == ()  # nothing heard for more than a second: forgotten


def test_a_late_copy_does_not_move_a_peer_back_and_a_stale_one_is_replaced() -> None:
    peers = PeerBodies(("r2",))
    assert peers.hear("r2", _pose("r2", 1.0, 1.0, t=20.0), now=20.0)
    assert not peers.hear("r2", _pose("r2", 0.0, 0.0, t=19.9), now=20.05)  # the older pose, on the other link
    assert peers.standing(20.1) == ((1.0, 1.0),)
    assert peers.hear("r2", _pose("r2", 2.0, 2.0, t=5.0), now=30.0)  # a restarted peer's clock
    assert peers.standing(30.0) == ((2.0, 2.0),)


def _room_with_peer_face() -> np.ndarray:
    """6 x 3 m, walled, known free; the near face of a robot standing at (3.0, 1.5) as the lidar
    maps it: a short arc of cells on the side facing x = 0."""
    g = np.zeros((60, 120), dtype=np.int8)
    g[0, :] = g[-1, :] = 100
    g[:, 0] = g[:, -1] = 100
    for a in np.linspace(math.radians(130), math.radians(230), 12):
        x, y = 3.0 + 0.17 * math.cos(a), 1.5 + 0.17 * math.sin(a)
        g[int(y / RES), int(x / RES)] = 100
    return g


def _clearance_to(pts: list[tuple[float, float]], c: tuple[float, float]) -> float:
    best = math.inf
    for (x0, y0), (x1, y1) in itertools.pairwise(pts):
        for t in np.linspace(0.0, 1.0, 200):
            best = min(best, math.dist((x0 + (x1 - x0) * t, y0 + (y1 - y0) * t), c))
    return best


def test_a_robot_standing_behind_its_mapped_face_is_planned_around_as_a_body() -> None:
    cfg = PlannerConfig()
    planner = PathPlanner(_room_with_peer_face(), RES, (0.0, 0.0), cfg)
    peer = (3.0, 1.5)
    start = (1.0, 1.5)
    # A goal just past the face: the map alone says the body fits there, beside the other robot.
    goal = (3.2, 1.25)
    alone = planner(start, goal)
    assert alone is not None and _clearance_to([start, *alone], peer) < 2 * cfg.robot_radius + 0.05
    # The same peer handed over as a ``blocked`` mark is taken for the mapped face and ignored ...
    assert planner.unknown_marks([peer]) == []
    # ... as a body it is not: no goal where the two bodies would touch.
    assert planner(start, goal, bodies=[peer]) is None
    assert planner.route(start, goal, bodies=[peer]) == []
    # A goal beyond it is reached by a path that keeps the body clear of the other robot's.
    far = (5.0, 1.5)
    around = planner(start, far, bodies=[peer])
    assert around is not None and around[-1] == far
    assert _clearance_to([start, *around], peer) >= cfg.robot_radius + cfg.body_radius + cfg.margin - RES
    # A goal is refused where the bodies would stand nearer than the guard lets a robot drive up to
    # another (``body_clearance``), and only there: the blocked marks' wider radius does not apply.
    for apart in (0.35, 0.40):
        assert planner(start, (3.0, 1.5 - apart), bodies=[peer]) is None, apart
    assert planner(start, (3.0, 1.5 - 0.43), bodies=[peer]) is not None
    # ... no nearer than the guard stops a robot that approaches a goal at the go-to's slowest speed.
    guard = CollisionGuard()
    standoff = PeerConfig().lane_margin_m + guard.config.robot_gap_m + guard.stopping_m(GoToConfig().approach_v_min)
    assert standoff <= cfg.body_clearance < standoff + 0.03
    # The legs' ultrasonic checks see a body's face, not its centre: 0.60 m ahead of the sensor, a
    # robot's face is 0.43 m off, within the stop distance and its margin (0.48 m).
    body = (1.0 + cfg.robot_radius + 0.60, 1.5)
    seen = planner.cone_range((1.0, 1.5), 0.0, 1.0, planner._body_echoes([body]))
    assert seen == pytest.approx(0.43, abs=0.025)  # (the cone is cast in 2.5 cm steps)
    assert not planner.leg_ok((0.5, 1.5), (1.0, 1.5), planner._body_echoes([body]))
    assert planner.leg_ok((0.5, 1.5), (1.0, 1.5), [body])  # its centre alone would have let the leg through
    # Non-finite bodies are dropped, not planned around.
    assert planner(start, far, bodies=[(math.nan, 1.0)]) == planner(start, far)


class _Placed(Fusion):
    placed = True
    heading_known = False

    @property
    def position_initialized(self) -> bool:
        return self.placed

    @property
    def heading_initialized(self) -> bool:
        return self.heading_known


def test_the_core_asks_for_the_robots_ahead_whichever_way_until_it_knows_its_heading() -> None:
    from fleetlink.agent.core import BoardView

    fusion = _Placed()
    peers = PeerBodies(("r2",))
    core = AgentCore("r1", SimClock(100.0), Pilot(), fusion=fusion, peers=peers)
    assert peers.robot == "r1"  # its own frame among the fleet map's is found by its id
    asked: list[tuple[bool, object]] = []
    real = peers.robots_ahead

    def robots_ahead(
        now: float, pose: tuple[float, float, float], heading_known: bool = True, **kw: float
    ) -> tuple[object, ...]:
        asked.append((heading_known, kw["placed"]))
        assert set(kw) == {"sd_xy", "sd_theta", "placed"}  # its own pose's uncertainty, for the margin
        return real(now, pose, heading_known, **kw)

    peers.robots_ahead = robots_ahead  # type: ignore[method-assign]
    core.tick(100.0, BoardView())
    fusion.heading_known = True
    core.tick(100.02, BoardView())
    # Unplaced: its pose is in its own map's frame, its heading that map's (known there); only the
    # fleet map's frames can put anyone else in it.
    fusion.placed = False
    fusion.heading_known = False
    core.tick(100.04, BoardView())
    assert asked == [(False, True), (True, True), (True, False)]


def test_the_core_hands_standing_peers_to_the_planner_once_placed_and_never_takes_them_for_commands() -> None:
    clock = SimClock(100.0)
    fusion = _Placed()
    core = AgentCore("r1", clock, Pilot(), fusion=fusion, peers=PeerBodies(("r2",)))
    asked: list[tuple[object, ...]] = []

    def provider(
        start: tuple[float, float],
        goal: tuple[float, float],
        /,
        blocked: object = (),
        bodies: object = (),
    ) -> list[tuple[float, float]]:
        asked.append((tuple(blocked), tuple(bodies)))  # type: ignore[call-overload]
        return [goal]

    core.use_map(provider)
    plan = core.pilot.path_provider
    assert plan is not None
    key = keys.key("r2", Pose.TOPIC)
    out = core.on_peer(LinkName.ZENOH, key, wire.encode(_pose("r2", 2.0, 3.0, t=100.0)), 100.0)
    assert out.logs == ["hears r2's pose on zenoh: planned around and kept clear of"]  # once per peer
    assert core.on_peer(LinkName.MQTT, key, wire.encode(_pose("r2", 2.0, 3.0, t=100.05)), 100.05).logs == []
    core._plan_now = 100.2  # the control step's time (set by every tick)
    plan((0.0, 0.0), (5.0, 5.0))
    plan((0.0, 0.0), (5.0, 5.0), blocked=[(1.0, 1.0)])
    fusion.placed = False  # unplaced: its frame is its own map's, where no fleet map has put r2
    plan((0.0, 0.0), (5.0, 5.0))
    assert asked == [((), ((2.0, 3.0),)), (((1.0, 1.0),), ((2.0, 3.0),)), ((), ())]
    assert core.contact._heard_at is None  # a peer's pose is no word from an operator
    # A new provider for each map (the route tells a newer map by identity).
    core.use_map(provider)
    assert core.pilot.path_provider is not plan

    # Garbage, another robot's pose and another topic are refused and counted, nothing else changes.
    before = sum(core.gate.stats.rejected.values())
    out = core.on_peer(LinkName.ZENOH, key, b"\x00garbage", 100.3)
    core.on_peer(LinkName.ZENOH, keys.key("r7", Pose.TOPIC), wire.encode(_pose("r7", 1.0, 1.0, t=100.3)), 100.3)
    core.on_peer(LinkName.MQTT, keys.key("r2", "state"), b"", 100.3)
    core.on_peer(LinkName.MQTT, "not/a/key", b"", 100.3)
    assert sum(core.gate.stats.rejected.values()) == before + 4
    assert any(m.TOPIC == "events" for m, _ in out.messages)  # logged once, as every rejected input
    assert core.peers.standing(100.3) == ((2.0, 3.0),)


def test_without_peers_the_map_provider_is_handed_to_the_pilot_as_it_is() -> None:
    core = AgentCore("r1", SimClock(0.0), Pilot())

    def provider(start: tuple[float, float], goal: tuple[float, float], /, blocked: object = ()) -> list[object]:
        return []

    core.use_map(provider)
    assert core.pilot.path_provider is provider


@pytest.mark.parametrize("peers", [("r1",), ("fleet",)])
def test_robot_toml_refuses_peers_that_are_not_other_robots(peers: tuple[str, ...]) -> None:
    from fleetlink.agent.config import parse_agent_config
    from fleetlink.shared.config import ConfigError

    with pytest.raises(ConfigError, match="peers"):
        parse_agent_config({"robot": "r1", "board": "socket://h:1", "zenoh": {}, "peers": list(peers)})
    cfg = parse_agent_config({"robot": "r1", "board": "socket://h:1", "zenoh": {}, "peers": ["r2", "r3", "r2"]})
    assert cfg.peers == ("r2", "r3")


def _gaps(peers: PeerBodies, now: float, pose: tuple[float, float, float], heading_known: bool = True) -> list[float]:
    return [r.gap_m for r in peers.robots_ahead(now, pose, heading_known)]


def test_the_gap_ahead_is_how_far_the_body_drives_before_it_touches_a_peer() -> None:
    peers = PeerBodies(("r2", "r3"))
    reach = 2 * 0.17 + 0.02
    peers.hear("r2", _pose("r2", 2.0, 0.0, t=1.0, vx=0.3), now=1.0)  # moving ones count too
    assert _gaps(peers, 1.0, (0.0, 0.0, 0.0)) == [pytest.approx(2.0 - reach)]
    side = 0.2
    peers.hear("r2", _pose("r2", 1.0, side, t=1.1), now=1.1)
    assert _gaps(peers, 1.1, (0.0, 0.0, 0.0)) == [pytest.approx(1.0 - math.sqrt(reach**2 - side**2))]
    assert _gaps(peers, 1.1, (0.0, 0.0, math.pi)) == []  # behind
    assert _gaps(peers, 1.1, (0.0, 0.0, math.pi / 2)) == []  # beside, passing clear
    assert _gaps(peers, 1.1, (0.0, 0.0, -math.pi / 2)) == []
    assert _gaps(peers, 1.1, (0.75, 0.0, 0.0)) == [0.0]  # touching, ahead
    assert _gaps(peers, 1.1, (1.25, 0.0, 0.0)) == []  # touching, behind: it may drive away
    peers.hear("r3", _pose("r3", 0.5, 0.0, t=1.1, sd=UNKNOWN_SD_M), now=1.1)  # not placed: not known where
    assert _gaps(peers, 1.1, (0.0, 0.0, 0.0)) == [pytest.approx(1.0 - math.sqrt(reach**2 - side**2))]
    assert _gaps(peers, 3.0, (0.0, 0.0, 0.0)) == []  # stale
    assert _gaps(peers, 1.1, (math.nan, 0.0, 0.0)) == []
    # The control tick may read the clock just before the pose is taken in: that pose counts.
    assert _gaps(peers, 1.099, (0.0, 0.0, 0.0)) == [pytest.approx(1.0 - math.sqrt(reach**2 - side**2))]
    assert peers.standing(1.099) == ((1.0, side),)


def test_the_margin_grows_with_how_uncertain_the_two_poses_are() -> None:
    """A peer 0.33 m to the side of this robot's way, 1 m ahead: the bodies (0.17 m each) would graze.
    Both placed to a centimetre and the heading known to a tenth of a degree, the fixed 2 cm margin
    holds; just driven off after UWB placed it (position 2.3 cm, heading 4 degrees: the apartment, in
    tests/test_robots_meeting.py) the margin is 1.5 sd of where the peer lies across the way, and a
    peer 0.45 m to the side counts too."""
    peers = PeerBodies(("r2",))
    side = 0.33
    peers.hear("r2", _pose("r2", 1.0, side, t=1.0, sd=0.005), now=1.0)
    sure = _gaps(peers, 1.0, (0.0, 0.0, 0.0))
    assert sure == [pytest.approx(1.0 - math.sqrt(0.36**2 - side**2))]
    assert peers.robots_ahead(1.0, (0.0, 0.0, 0.0), sd_xy=0.005, sd_theta=0.001) == peers.robots_ahead(
        1.0, (0.0, 0.0, 0.0)
    )
    sd_xy, sd_theta = 0.023, math.radians(4.0)
    apart = math.hypot(1.0, side)
    k = PeerConfig().margin_sds
    reach = 0.34 + k * math.sqrt(sd_xy**2 + 0.005**2 + (apart * sd_theta) ** 2)
    (unsure,) = peers.robots_ahead(1.0, (0.0, 0.0, 0.0), sd_xy=sd_xy, sd_theta=sd_theta)
    assert unsure.gap_m == pytest.approx(1.0 - math.sqrt(reach**2 - side**2))
    assert unsure.gap_m < sure[0] - 0.1  # refused a tenth of a metre and more sooner
    peers.hear("r2", _pose("r2", 1.0, 0.45, t=1.1), now=1.1)
    assert _gaps(peers, 1.1, (0.0, 0.0, 0.0)) == []
    assert len(peers.robots_ahead(1.1, (0.0, 0.0, 0.0), sd_xy=sd_xy, sd_theta=sd_theta)) == 1
    # A peer's own uncertainty counts as well; a heading not known at all leaves it to ``heading_known``.
    peers.hear("r2", _pose("r2", 1.0, side, t=1.2, sd=0.05), now=1.2)
    (loose,) = peers.robots_ahead(1.2, (0.0, 0.0, 0.0))
    assert loose.gap_m == pytest.approx(1.0 - math.sqrt((0.34 + k * 0.05) ** 2 - side**2))
    assert peers.robots_ahead(1.2, (0.0, 0.0, 0.0), sd_theta=math.inf) == peers.robots_ahead(1.2, (0.0, 0.0, 0.0))


def test_before_the_robot_knows_its_heading_every_peer_near_enough_counts_whichever_way() -> None:
    peers = PeerBodies(("r2",))
    reach = 2 * 0.17 + 0.02
    peers.hear("r2", _pose("r2", 0.0, 0.5, t=1.0), now=1.0)  # beside, to the left
    assert _gaps(peers, 1.0, (0.0, 0.0, 0.0)) == []
    assert _gaps(peers, 1.0, (0.0, 0.0, 0.0), heading_known=False) == [pytest.approx(0.5 - reach)]
    peers.hear("r2", _pose("r2", -0.3, 0.0, t=1.1), now=1.1)  # touching, behind the heading it thinks it has
    assert _gaps(peers, 1.1, (0.0, 0.0, 0.0), heading_known=False) == [0.0]


def test_a_peer_coming_closer_is_moved_on_to_now_and_says_how_fast_it_comes() -> None:
    peers = PeerBodies(("r2", "r3"))
    reach = 2 * 0.17 + 0.02
    head_on = _pose("r2", 2.0, 0.0, t=1.0, vx=0.5)
    peers.hear("r2", _facing(head_on, math.pi), now=1.0)
    (r,) = peers.robots_ahead(1.1, (0.0, 0.0, 0.0))
    assert r.gap_m == pytest.approx(2.0 - 0.05 - reach)  # 0.1 s at 0.5 m/s nearer than it said
    assert r.closing_mps == pytest.approx(0.5)
    (r,) = peers.robots_ahead(1.9, (0.0, 0.0, 0.0))  # no pose since: moved on for 0.25 s at most
    assert r.gap_m == pytest.approx(2.0 - 0.125 - reach)
    peers.hear("r3", _facing(_pose("r3", 1.0, 0.0, t=1.0, vx=0.5), 0.0), now=1.0)  # ahead, driving away
    near = peers.robots_ahead(1.0, (0.0, 0.0, 0.0))
    assert [(round(x.gap_m, 6), x.closing_mps) for x in near] == [
        (round(1.0 - reach, 6), 0.0),
        (round(2.0 - reach, 6), 0.5),
    ]


def _facing(pose: Pose, theta: float) -> Pose:
    return dataclasses.replace(pose, theta=theta)


def test_a_peer_whose_clock_steps_back_is_heard_again() -> None:
    peers = PeerBodies(("r2",))
    assert peers.hear("r2", _pose("r2", 1.0, 1.0, t=20.0), now=20.0)
    assert not peers.hear("r2", _pose("r2", 0.0, 0.0, t=19.9), now=20.1)  # a late copy from the other link
    assert peers.hear("r2", _pose("r2", 1.5, 1.0, t=19.5), now=20.3)  # its clock went back 0.8 s: news
    assert peers.standing(20.3) == ((1.5, 1.0),)


def test_the_guard_refuses_driving_into_another_robot_and_allows_turning_and_backing() -> None:
    from fleetlink.agent.guard import CollisionGuard, GuardConfig, GuardInputs, RefusalReason, RobotAhead

    guard = CollisionGuard(GuardConfig(creep_speed_mps=0.05, allow_turn_in_place=True))
    near = GuardInputs(robots_ahead=(RobotAhead(0.1),))  # at 0.3 m/s it needs 0.03 + 0.045 + 0.03 m
    d = guard.filter(0.3, 0.0, near, on_path=True)  # never crept into, on a path or not
    assert d.v == 0.0 and d.refusal is not None and d.refusal.reason is RefusalReason.ROBOT_AHEAD
    assert "another robot" in d.refusal.text and d.refusal.distance_m == pytest.approx(0.1)
    assert guard.filter(0.0, 0.8, near).refusal is None  # a round body turning sweeps nothing new
    assert guard.filter(-0.1, 0.0, near).refusal is None
    assert guard.filter(0.3, 0.0, GuardInputs(robots_ahead=(RobotAhead(0.11),))).refusal is None
    assert guard.filter(0.05, 0.0, near).refusal is None  # slowly, nearer
    assert guard.filter(0.3, 0.0, GuardInputs(robots_ahead=(RobotAhead(math.nan),))).refusal is not None
    # Each robot keeps room for both to stop: 0.03 + 2 x (0.125 + 0.05) m head-on at 0.5 m/s each.
    head_on = (RobotAhead(0.37, closing_mps=0.5),)
    refused = guard.filter(0.5, 0.0, GuardInputs(robots_ahead=head_on)).refusal
    assert refused is not None and "coming at 0.50 m/s" in refused.text
    assert guard.filter(0.5, 0.0, GuardInputs(robots_ahead=(RobotAhead(0.39, closing_mps=0.5),))).refusal is None
    # Any robot in the way may be the one it must stop for, not only the nearest.
    both = (RobotAhead(0.2), RobotAhead(0.25, closing_mps=0.5))  # needs 0.105 m, and 0.28 m
    assert guard.filter(0.3, 0.0, GuardInputs(robots_ahead=both)).refusal is not None
    assert guard.filter(0.3, 0.0, GuardInputs(robots_ahead=both[:1])).refusal is None


# -- robots in their own frames, placed by the fleet map (FleetFrames) ---------------------------


def _frames(reference: str, **frames: tuple[float, ...]) -> FleetFrames:
    """Each robot's (x, y, theta) on the fleet map, and the ``began`` of the map it was found for (0 unless given)."""
    counter = wire.HeaderCounter(SimClock(0.0), robot=keys.FLEET_MAP, sender="fleet-map")
    return counter.make(
        FleetFrames,
        reference=reference,
        frames=tuple(
            RobotFrame(robot=r, x=f[0], y=f[1], theta=f[2], began=f[3] if len(f) > 3 else 0.0)
            for r, f in sorted(frames.items())
        ),
        unframed=(),
    )


def _unplaced(robot: str, x: float, y: float, *, t: float, vx: float = 0.0, began: float = 0.0) -> Pose:
    return _pose(robot, x, y, t=t, vx=vx, sd=UNKNOWN_SD_M, began=began)


def test_a_peer_in_its_own_frame_is_put_in_this_robots_own_frame_through_the_fleet_maps_frames() -> None:
    # r2's frame is the fleet map's; r1's own frame lies at (2, 0) on it, turned 90 degrees. r2 stands
    # at (1, 1) in its frame, so on the fleet map too; in r1's frame: (1, 1) - (2, 0) = (-1, 1), turned
    # back 90 degrees, (1, 1).
    peers = PeerBodies(("r2",), robot="r1")
    assert peers.hear("r2", _unplaced("r2", 1.0, 1.0, t=10.0), now=10.0)
    assert peers.standing(10.0, placed=False) == ()  # no fleet map heard: r2's frame is its own
    assert peers.hear_frames(_frames("r2", r1=(2.0, 0.0, math.pi / 2), r2=(0.0, 0.0, 0.0)), now=10.0)
    assert peers.framed(10.0) == ("r1", "r2")
    ((x, y),) = peers.standing(10.0, placed=False)
    assert (x, y) == pytest.approx((1.0, 1.0), abs=1e-9)
    # Through a frame that is not the identity on both sides: r2's at (0, 3), turned 180 degrees.
    assert peers.hear_frames(_frames("r1", r1=(0.0, 0.0, 0.0), r2=(0.0, 3.0, math.pi)), now=10.5)
    ((x, y),) = peers.standing(10.5, placed=False)
    assert (x, y) == pytest.approx((-1.0, 2.0), abs=1e-9)
    # A placed robot (the site frame) cannot use frames whose fleet map is a robot's own frame.
    assert peers.standing(10.5, placed=True) == ()
    # Frames not heard for frames_fresh_s are not used; nor is a robot they do not list.
    peers.hear("r2", _unplaced("r2", 1.0, 1.0, t=45.0), now=45.0)
    assert peers.standing(45.0, placed=False) == ()
    assert peers.hear_frames(_frames("r1", r1=(0.0, 0.0, 0.0)), now=45.0)
    assert peers.standing(45.0, placed=False) == ()


def test_with_the_site_frame_as_the_fleet_maps_placed_and_own_frame_robots_see_each_other() -> None:
    site = _frames("", r2=(1.0, 0.0, math.pi / 2))  # r2 maps in its own frame, which the fleet map placed
    placed = PeerBodies(("r2",), robot="r1")
    placed.hear("r2", _unplaced("r2", 1.0, 0.0, t=5.0), now=5.0)
    placed.hear_frames(site, now=5.0)
    ((x, y),) = placed.standing(5.0, placed=True)
    assert (x, y) == pytest.approx((1.0, 1.0), abs=1e-9)  # r2's own (1, 0) on the site frame
    # And r2, in its own frame, sees r1 (placed, in the site frame) in its own.
    own = PeerBodies(("r1",), robot="r2")
    own.hear("r1", _pose("r1", 1.0, 1.0, t=5.0), now=5.0)
    own.hear_frames(site, now=5.0)
    ((x, y),) = own.standing(5.0, placed=False)
    assert (x, y) == pytest.approx((1.0, 0.0), abs=1e-9)
    # A service that has not heard the placed robot's map yet (its frame a robot's own) does not
    # replace the site-referenced frames while they are fresh.
    assert not own.hear_frames(_frames("r2", r2=(0.0, 0.0, 0.0)), now=6.0)
    ((x, y),) = own.standing(6.0, placed=False)
    assert (x, y) == pytest.approx((1.0, 0.0), abs=1e-9)


def test_two_robots_in_their_own_frames_keep_clear_of_each_other_through_the_fleet_map() -> None:
    # r1 at its own origin facing +x; r2 0.6 m ahead of it on the fleet map, in a frame turned 180 deg.
    peers = PeerBodies(("r2",), robot="r1")
    peers.hear("r2", _unplaced("r2", 0.4, 0.0, t=1.0, vx=0.2), now=1.0)  # driving along its own +x
    assert peers.robots_ahead(1.0, (0.0, 0.0, 0.0), placed=False) == ()  # no frames: not counted
    peers.hear_frames(_frames("r1", r1=(0.0, 0.0, 0.0), r2=(1.0, 0.0, math.pi)), now=1.0)
    (ahead,) = peers.robots_ahead(1.0, (0.0, 0.0, 0.0), placed=False)
    # r2 at x = 0.6, coming toward r1 at 0.2 m/s; the bodies touch 2 radii plus the margin apart,
    # the margin 1.5 sd of both frames' placement on the fleet map.
    reach = 2 * BODY_RADIUS_M + 1.5 * math.hypot(0.05, 0.05)
    assert ahead.gap_m == pytest.approx(0.6 - reach, abs=1e-9)
    assert ahead.closing_mps == pytest.approx(0.2)


def test_a_frame_places_only_poses_of_the_map_it_was_found_for() -> None:
    # r2 (no UWB) mapped from 12 s; the fleet map found that map 3 m along r1's +x. Its agent restarts
    # at 40 s where it then stands, 1 m on: a new map, whose frame begins there. Through the old frame
    # its new pose (0, 0) would read as the old map's origin, a metre from where it stands.
    peers = PeerBodies(("r2",), robot="r1")
    peers.began = 5.0  # r1's own map
    peers.hear_frames(_frames("r1", r1=(0.0, 0.0, 0.0, 5.0), r2=(3.0, 0.0, 0.0, 12.0)), now=39.0)
    peers.hear("r2", _unplaced("r2", 1.0, 0.0, t=39.0, began=12.0), now=39.0)
    assert peers.standing(39.0, placed=False) == ((4.0, 0.0),)
    peers.hear("r2", _unplaced("r2", 0.0, 0.0, t=41.0, began=40.0), now=41.0)  # the new map
    assert peers.standing(41.0, placed=False) == ()
    assert peers.robots_ahead(41.0, (0.0, 0.0, 0.0), placed=False) == ()
    # The fleet map finds the new one at 44 s: r2 counts again, where it stands.
    peers.hear_frames(_frames("r1", r1=(0.0, 0.0, 0.0, 5.0), r2=(4.0, 0.0, 0.0, 40.0)), now=44.0)
    peers.hear("r2", _unplaced("r2", 0.0, 0.0, t=44.0, began=40.0), now=44.0)
    assert peers.standing(44.0, placed=False) == ((4.0, 0.0),)
    # Its own frame likewise: r1's map begun again places nobody through the old frame of it.
    peers.began = 50.0
    assert peers.standing(44.0, placed=False) == ()
    assert peers.robots_ahead(44.0, (0.0, 0.0, 0.0), placed=False) == ()
    # Restarted again: until its new map begins, its poses say 0, and no frame places them.
    peers.began = 5.0
    peers.hear("r2", _unplaced("r2", 0.0, 0.0, t=46.0, began=0.0), now=46.0)
    assert peers.standing(46.0, placed=False) == ()
    # An agent before 1.2.0 names no map (its poses say 0 always): every frame found for it holds.
    legacy = PeerBodies(("r3",), robot="r1")
    legacy.began = 5.0
    legacy.hear_frames(_frames("r1", r1=(0.0, 0.0, 0.0, 5.0), r3=(2.0, 0.0, 0.0, 30.0)), now=50.0)
    legacy.hear("r3", _unplaced("r3", 1.0, 0.0, t=50.0), now=50.0)
    assert legacy.standing(50.0, placed=False) == ((3.0, 0.0),)
    # And a service that does not say which map (0) places whichever map the poses name.
    legacy.hear_frames(_frames("r1", r1=(0.0, 0.0, 0.0), r3=(2.0, 0.0, 0.0)), now=51.0)
    legacy.hear("r3", _unplaced("r3", 1.0, 0.0, t=51.0, began=70.0), now=51.0)
    assert legacy.standing(51.0, placed=False) == ((3.0, 0.0),)
    # A placed robot needs no frame of its own: the site frame is one map.
    site = PeerBodies(("r2",), robot="r1")
    site.hear_frames(_frames("", r2=(3.0, 0.0, 0.0, 12.0)), now=39.0)
    site.hear("r2", _unplaced("r2", 1.0, 0.0, t=39.0, began=12.0), now=39.0)
    assert site.standing(39.0, placed=True) == ((4.0, 0.0),)


def test_the_core_says_which_map_its_poses_are_in_and_finds_its_own_frame_by_it() -> None:
    clock = SimClock(100.0)
    core = AgentCore("r1", clock, Pilot(), peers=PeerBodies(("r2",)))
    assert core._pose(100.0).map_began == 0.0  # no map yet
    core.map_begun(60.0)
    assert core._pose(100.0).map_began == 60.0
    assert core.peers.began == 60.0
    assert wire.decode(Pose, wire.encode(core._pose(100.0))).map_began == 60.0


def test_the_core_takes_the_fleet_maps_frames_and_plans_around_a_peer_while_unplaced() -> None:
    clock = SimClock(100.0)
    fusion = _Placed()
    fusion.placed = False
    core = AgentCore("r1", clock, Pilot(), fusion=fusion, peers=PeerBodies(("r2",)))

    def with_bodies(
        start: tuple[float, float], goal: tuple[float, float], /, blocked: object = (), bodies: object = ()
    ) -> list[tuple[float, float]]:
        seen.append(tuple(bodies))  # type: ignore[call-overload]
        return [goal]

    seen: list[tuple[object, ...]] = []
    core.use_map(with_bodies)
    plan = core.pilot.path_provider
    assert plan is not None
    core.on_peer(LinkName.ZENOH, keys.key("r2", Pose.TOPIC), wire.encode(_unplaced("r2", 1.0, 0.0, t=100.0)), 100.0)
    fkey = keys.key(keys.FLEET_MAP, FleetFrames.TOPIC)
    out = core.on_peer(LinkName.ZENOH, fkey, wire.encode(_frames("r1", r1=(0, 0, 0))), 99.9)
    assert out.logs == ["hears the fleet map's frames on zenoh: r1 placed on it"]  # r2 not found yet
    out = core.on_peer(LinkName.ZENOH, fkey, wire.encode(_frames("r1", r1=(0, 0, 0), r2=(2.0, 0.0, 0.0))), 100.0)
    assert out.logs == ["hears the fleet map's frames on zenoh: r2 placed on it"]
    assert core.on_peer(LinkName.ZENOH, fkey, wire.encode(_frames("r1", r1=(0, 0, 0), r2=(2, 0, 0))), 100.1).logs == []
    # A robot that is not its peer is not named; one that the frames newly place is, once.
    r3 = _frames("r1", r1=(0, 0, 0), r2=(2.0, 0.0, 0.0), r3=(5.0, 0.0, 0.0))
    assert core.on_peer(LinkName.ZENOH, fkey, wire.encode(r3), 100.15).logs == []
    core._plan_now = 100.2
    plan((0.0, 0.0), (5.0, 0.0))
    assert seen == [((3.0, 0.0),)]
    # Garbage on the frames' key is refused and counted; the frames kept are still used.
    before = sum(core.gate.stats.rejected.values())
    core.on_peer(LinkName.ZENOH, fkey, b"\x00garbage", 100.3)
    assert sum(core.gate.stats.rejected.values()) == before + 1
    assert core.peers.standing(100.3, placed=False) == ((3.0, 0.0),)
    assert core.contact._heard_at is None  # the fleet map's frames are no word from an operator
