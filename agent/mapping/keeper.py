"""The map keeper: which map the agent builds, and when the pilot gets a fresh planner. Pure.

The agent's lidar path hands every revolution to ``MapKeeper.add`` with the fused pose, whether
the fusion has placed the robot in the UWB (site) frame, whether it is driving, and the time. The
keeper decides:

* **The frame.** A map begun in the odometry frame would be smeared across both frames once UWB
  fixes place the robot, so the first revolution after the robot is placed restarts the map, once
  (``Update.restarted``: the shell then serves the new map instead of the old one).
* **Which turns to map.** A turn seen from where the last mapped turn was seen adds nothing the
  map lacks, yet matching it costs milliseconds; so a turn is mapped only once the fused pose has
  moved ``min_move_m`` or turned ``min_turn_rad`` since the last mapped turn, or ``max_gap_s`` has
  passed (a robot standing still still sees a door close), as Cartographer's motion filter does;
  every ``MapperConfig.keyframe_period_waiting`` while the pilot waits for the way to clear
  (``Turn.waiting``: what stood in the way is cleared from the map by the scans that see it gone).
  The mapper integrates keyframes at these same spacings, so the map loses nothing; a robot
  driving at 0.35 m/s maps three or four turns a second instead of ten.
* **Planner renewal.** The first planner as soon as the map has cells; then a fresh one every
  ``planner_period`` seconds while the robot drives and the map changed (standing still, the map
  changes only by noise, and building a planner costs tens of milliseconds).
* **Where the map says the robot is.** With loop closure on, the map moves under the robot when a
  closure is solved, while the pilot drives on the fused pose (UWB and odometry). So each update
  carries what localisation needs to move with the map: ``Update.moved``, how the solves since the
  last update moved the map frame where the robot is (the fusion shifts its frame by it, at once),
  and ``Update.seen``, the pose the scan matched at in the map (a pose measurement for the fusion,
  given only in the site frame, for a match that is well posed in every direction).
* **What to share.** Every ``share_period`` seconds, if the map changed, a ``MapPublication``: the
  cells copied at one version and the box changed since the last one, for the shell's ``MapShare``
  to serve and patch; with loop closure also every submap's pose as the graph has it now and the
  submaps drawn since the last one (a finished submap once, the open one as nodes join it), which
  the share serves for the fleet map.

Time is an argument. What the keeper hands out (planner, publication) is built over copies of
the cells, so it may be used on another thread, or in another process than the keeper's
(agent/mapping/worker.py), while mapping goes on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from fleetlink.agent.mapping.closure import CloserConfig, ClosureSearch, DeferredSearch
from fleetlink.agent.mapping.fleetmap import Submap
from fleetlink.agent.mapping.grid import Box
from fleetlink.agent.mapping.mapper import MapperConfig, OnboardMapper
from fleetlink.agent.mapping.planner import PathPlanner, PlannerConfig, SensorCone
from fleetlink.shared.se2 import Pose, compose
from fleetlink.shared.se2 import inverse as inverse_pose

__all__ = [
    "ONBOARD_CLOSER",
    "PLANNER_PERIOD_S",
    "SHARE_PERIOD_S",
    "MapKeeper",
    "MapPublication",
    "Seen",
    "Turn",
    "Update",
    "followed_part",
    "onboard_mapper_config",
    "seen_covariance",
]

PLANNER_PERIOD_S = 2.0
"""Seconds between planners handed to the pilot while the robot drives and the map grows."""
SITE_SIGMA_M = 0.1
"""How far a fused pose is trusted as a site-frame position in the map's pose graph (one prior per
node, ~0.3 m apart): looser than the fused pose's own ~2 cm because consecutive fused poses share
their errors. Measured on the office patrol on board (bench/mapping.py section 1b): at 0.3 m the map
began a few degrees askew (the fused heading when the robot was placed) stayed so for tens of metres
of corridor, 0.1-0.4 m off; at 0.1 m, solved every 10 nodes, the map's pose is 1.6 cm from the truth."""
ANCHOR_PRIORS = 20
"""Site priors (UWB-placed nodes, one per 0.3 m) a solve must have had before the fusion hears from
the map: ~6 m of travel, enough to turn a map begun at the first fused heading (sd up to 2 deg) onto
the anchors' frame."""
SEEN_SD_XY_M = 0.05
"""How far the map's pose of the robot is trusted as a measurement for the fusion (1 sd), along the
direction the scan pins best; along a direction it pins less well, less (see ``seen_covariance``)."""
SEEN_SD_THETA_RAD = math.radians(1.0)
SEEN_MIN_WEAK = 10000.0
"""A scan match whose weakest information (1/m^2) is below this is not passed on at all."""
SHARE_PERIOD_S = 1.0
"""Seconds between map publications (a snapshot to serve, a patch to send) while the map changes."""


ONBOARD_CLOSER = CloserConfig(
    search_xy=0.3,
    search_theta=math.radians(5.0),
    confirm_above=0.15,
    bnb_depth=4,
    check_period=1.0,
    prior_solve_nodes=10,
    solve_nodes_per_s=500.0,
)
"""Loop closure on a robot: the front end is seeded by the fused pose, which UWB holds within a few
centimetres of the site frame, so the map never drifts far from where a closure would put it: the
search window is small (+-0.3 m, +-5 deg) and grows only with the path since the last anchor, a
closure or a node UWB placed (with UWB fresh, never: on board 10 m windows under UWB accepted
look-alike places 0.5 m off, which bent the map under the robot). Without UWB, or through an outage,
it grows as a replay's does (0.1 m per metre, 0.5 deg per metre, to 10 m and 35 deg; before a UWB
position, when turns carry the odometry, also held to 3x how far the map has left it since). A closure that would move its node more than 0.15 m waits
for a second one that agrees, a node is searched at most once a second (the search's rate, whatever
the speed), and the graph is solved at most once per (nodes / 500) s (1 s at 500 nodes, 10 s at
5 000: a solve's cost grows with the graph, its share of a core does not). Site priors solved every
10 nodes (``SITE_SIGMA_M``)."""
ONBOARD_REDRAW_BATCH = 50
"""Keyframes drawn again per read of the map while a redraw is under way (the map is read every second
or two on a robot): what a read costs stays bounded however long the robot has mapped."""
ONBOARD_MISSING_RAY_M = 5.0
"""How far a sector with no return (5 samples or more in a row, ``MapperConfig.missing_run``) clears
on board (``MapperConfig.missing_ray``): the RPLIDAR reports nothing within its 12 m as 0. In an open
hall the floor where another robot stood is seen through only by such beams. Cartographer's
``missing_data_ray_length``; measured against 0, 2 and 3 m on the hall's patrols (docs/mapping.md)."""


def onboard_mapper_config(*, cone: bool = True, closures: bool = True) -> MapperConfig:
    """Unknown cells count as free on an onboard map: a scout is sent into rooms it has not seen
    (the guard still stops it at anything real). ``cone`` False: a robot whose guard creeps to the
    walls instead of refusing drive starts for what its ultrasonic cone sees (docs/motion.md):
    its legs are not cut short to please the cone. ``closures``: loop closure on board
    (``ONBOARD_CLOSER``; the keeper then hands the map's pose back to the fusion: docs/mapping.md
    "On board"; robot.toml ``[mapping] loop_closure``)."""
    sensor = SensorCone() if cone else None
    return MapperConfig(
        planner=PlannerConfig(unknown_is_blocked=False, sensor=sensor),
        # The RPLIDAR reports "nothing within 12 m" as 0: a sector of those clears its first metres.
        missing_ray=ONBOARD_MISSING_RAY_M,
        closer=ONBOARD_CLOSER if closures else None,
        redraw_batch=ONBOARD_REDRAW_BATCH,
    )


@dataclass(frozen=True, slots=True)
class Turn:
    """One lidar turn as the keeper takes it."""

    t: float
    """When the turn began (the agent takes its stamp, at completion, less a turn: agent/node.py)."""
    distances_m: npt.ArrayLike
    angles_rad: npt.ArrayLike
    pose: tuple[float, float, float]
    """The fused map pose (x, y, theta) it was seen from."""
    placed: bool
    """The fusion has placed the robot in the UWB (site) frame."""
    driving: bool
    now: float
    anchored: bool = True
    """UWB fixes are coming in (not stale): the fused pose is tied to the site frame now, so its
    position is a prior for the map's pose graph. During an outage it is odometry (and the map's own
    pose) carried on, and a prior from it would only pull the map along its drift."""
    follows: tuple[float, ...] | None = None
    """The covariance (3 x 3 row-major, map frame) of the last map pose the fusion took
    (``Update.seen`` accepted), or None: the fused pose has not been following the map, and a solve
    moves the map alone (``Update.moved`` stays None)."""
    odometry: tuple[float, float, float] | None = None
    """The odometry's own pose at the turn (its frame; only differences count), given while the fusion
    has no UWB position (the fused pose is then the odometry, drift and all), else None. The map is
    then built in its own frame: each turn is matched near the map's last pose moved by the odometry
    since, not at the fused pose, and ``Update.odom_frame`` puts the robot on that map. The loop
    closer also gets it (its search window follows how far the map has left the odometry since the
    last closure: ``CloserConfig.odometry_gain``)."""
    waiting: bool = False
    """The pilot stands waiting for the way to clear (agent/route.py ``RoutePhase.WAITING``): the map
    is to look, a turn mapped and integrated every ``MapperConfig.keyframe_period_waiting``."""


@dataclass(frozen=True, slots=True)
class MapPublication:
    """The map as the share sends it: map_server cells copied at ``version``, and the box of cells
    (row0, col0, row1, col1) changed since the previous publication (None: nothing known)."""

    version: int
    cells: npt.NDArray[np.int8]
    resolution: float
    origin: tuple[float, float]
    changed: Box | None
    site_frame: bool = False
    """The map is in the site (UWB) frame: the robot was placed before it began (the dose layer
    takes its floor only from such a map)."""
    began: float = 0.0
    """When this map began (the keeper's clock): its submaps are numbered within it."""
    submaps: tuple[Submap, ...] = ()
    """The submaps drawn since the previous publication (new ones, and the open one as it grew)."""
    submap_poses: tuple[tuple[int, int, Pose], ...] = ()
    """Every submap's (index, version, pose in the map frame) as the pose graph has them now."""

    @classmethod
    def of(cls, mapper: OnboardMapper, *, site_frame: bool = False, base: int = 0) -> MapPublication:
        """The mapper's map now, its version counted on from ``base``; takes (clears) its changed box."""
        cells, res, origin = mapper.occupancy()
        return cls(base + mapper.version, cells, res, origin, mapper.grid.take_dirty(), site_frame)


@dataclass(frozen=True, slots=True)
class Seen:
    """Where the map says the robot was at ``t``: the scan matched in the map (the site frame), with
    the covariance of (x, y, theta), row-major, in the map frame."""

    t: float
    pose: tuple[float, float, float]
    cov: tuple[float, ...]


def seen_covariance(
    information: npt.NDArray[np.float64],
    pose: tuple[float, float, float],
    mount: tuple[float, float, float],
    sd_xy: float = SEEN_SD_XY_M,
    sd_theta: float = SEEN_SD_THETA_RAD,
) -> tuple[float, ...]:
    """The covariance the fusion gives a scan match: shaped by the refinement's information (the
    directions the scan's walls pin down, and how much better than the others), scaled so that the
    best-pinned direction has ``sd_xy`` (the raw information, every point independent, would claim
    millimetres: the map's own errors are not in it), the heading at least ``sd_theta``. Along a
    corridor the variance is then large and the fusion keeps its own estimate there: the match only
    repeats the guess it was given. ``information`` is the sensor pose's; ``pose`` the robot's."""
    c = np.linalg.inv(information + np.eye(3) * 1e-6)
    c = (c + c.T) / 2.0
    ix, iy, iphi = inverse_pose(mount)
    cs, sn = math.cos(pose[2] - iphi), math.sin(pose[2] - iphi)  # the sensor's heading
    j = np.array([[1.0, 0.0, -sn * ix - cs * iy], [0.0, 1.0, cs * ix - sn * iy], [0.0, 0.0, 1.0]])
    c = j @ c @ j.T
    lo = float(np.linalg.eigvalsh(c[:2, :2])[0])
    c *= sd_xy * sd_xy / max(lo, 1e-18)
    c[2, 2] = max(float(c[2, 2]), sd_theta * sd_theta)
    return tuple(float(v) for v in c.ravel())


FOLLOW_SD_M = 0.15
"""A direction the map's pose pins to within this (1 sd, ``seen_covariance``) is one the fusion
follows the map in; along the others (a corridor) it keeps its own estimate."""
FOLLOW_SD_RAD = math.radians(3.0)


def followed_part(
    moved: tuple[float, float, float], before: tuple[float, float, float], cov: tuple[float, ...]
) -> tuple[float, float, float]:
    """The part of a solve's correction the fused pose moves with. ``moved`` takes the map's pose of
    the robot ``before`` the solve to where the solve put it; the fusion followed the map only along
    the directions its pose measurements pinned (``cov``, the last ``Seen``'s): there the fused pose
    was the map's and must move with it, and along the others (a corridor seen end-on) it stayed
    where UWB and odometry put it, which the map's correction there only brings the map nearer to. The
    robot's move is projected onto the pinned directions, the turn kept if the heading was pinned;
    returned as a transform of the frame that moves the robot so, at ``before``."""
    after = compose(moved, before)
    d = np.array([after[0] - before[0], after[1] - before[1]])
    c = np.array(cov).reshape(3, 3)
    w, v = np.linalg.eigh(c[:2, :2])
    keep = v[:, w <= FOLLOW_SD_M**2]
    dx, dy = (keep @ (keep.T @ d)).tolist()
    dth = math.remainder(after[2] - before[2], math.tau) if c[2, 2] <= FOLLOW_SD_RAD**2 else 0.0
    target = (before[0] + dx, before[1] + dy, before[2] + dth)
    return compose(target, inverse_pose(before))


@dataclass(frozen=True, slots=True)
class Update:
    restarted: bool = False
    """The map started again (the robot was just placed in the site frame)."""
    planner: PathPlanner | None = None
    """A fresh planner for the pilot, or None (keep the one it has)."""
    publication: MapPublication | None = None
    """The map to share now, or None (nothing new, or not yet time)."""
    moved: tuple[float, float, float] | None = None
    """How loop closure moved the map frame where the robot is since the last update (the transform
    from the old frame to the new one), or None. Localisation moves with it."""
    seen: Seen | None = None
    """The turn's pose as matched in the map (site frame only), or None."""
    odom_frame: tuple[float, float, float] | None = None
    """While the map is in its own frame (UWB has not placed the robot) and turns carry their odometry:
    the transform taking an odometry pose to the map's pose of the robot (its last match and the
    solves since, less the odometry there), for localisation to put the robot on its map
    (``Fusion.set_own_frame``); None in the site frame."""


class MapKeeper:
    def __init__(
        self,
        config: MapperConfig | None = None,
        planner_period: float = PLANNER_PERIOD_S,
        *,
        share_period: float = SHARE_PERIOD_S,
        max_gap_s: float = 1.0,
        search: ClosureSearch | None = None,
    ) -> None:
        """``search``: where loop closure's checks run (a worker thread on a robot:
        agent/mapping/worker.py); default ``DeferredSearch``, in line, each node's verdicts taken at
        the next node, as from a search that always keeps up (deterministic: lockstep runs)."""
        self.config = config or onboard_mapper_config()
        self.search: ClosureSearch = search if search is not None else DeferredSearch()
        self.planner_period = planner_period
        self.share_period = share_period
        self.min_move_m = self.config.keyframe_distance
        self.min_turn_rad = self.config.keyframe_angle
        self.max_gap_s = max_gap_s
        self.skipped = 0
        """Turns left out by the motion filter."""
        self._last: tuple[float, float, float, float] | None = None  # t, x, y, theta of the last mapped turn
        self.mapper = OnboardMapper(self.config, self.search)
        self._anchored = False
        self.in_site_frame = False
        self._odom_frame: Pose | None = None  # map pose = compose(this, odometry), in the map's own frame
        self.restarts = 0
        self._version_base = 0
        self._planned_version = -1
        self._next_planner = -math.inf
        self._shared_version = -1
        self._next_share = -math.inf
        self._began: float | None = None  # when the current map began
        self._submap_versions: dict[int, int] = {}  # the version of each submap last published

    def add(self, turn: Turn) -> Update:
        """One revolution, seen from ``turn.pose`` (the fused map pose)."""
        t, pose, placed, driving, now = turn.t, turn.pose, turn.placed, turn.driving, turn.now
        restarted = False
        if placed and not self.in_site_frame:
            self.in_site_frame = True
            self._last = None
            self._odom_frame = None
            if not self.mapper.grid.empty:
                # The new map's versions go on from the old one's: a console holding the old map
                # takes the first newer one it hears of as the map to fetch (a version it has
                # passed would be refused as stale, and the odometry-frame map would stay).
                self._version_base += self.mapper.version + 1
                self.mapper = OnboardMapper(self.config, self.search)
                self._anchored = False
                self._planned_version = -1
                self._shared_version, self._next_share = -1, -math.inf
                self._began, self._submap_versions = None, {}
                self.restarts += 1
                restarted = True
        if self._began is None:
            self._began = now
        # In its own frame (no UWB position: the turn carries its odometry) the map is its own reference.
        odom = turn.odometry if not self.in_site_frame else None
        if not self._due(t, pose, turn.waiting):
            self.skipped += 1
            return Update(
                restarted=restarted,
                publication=self._publication(now),
                odom_frame=self._odom_frame if odom is not None else None,
            )
        self._last = (t, *pose)
        # Once UWB has placed the robot, its fused position anchors the map's pose graph in the site
        # frame (loop closures then straighten the map without pulling it off the anchors' frame).
        site = (pose[0], pose[1], SITE_SIGMA_M) if placed and turn.anchored else None
        was_anchored = self._map_anchored()
        if odom is not None:
            # The turn is sought where the map's last pose moved by the odometry puts it (at first the
            # odometry's frame is the map's), not at the fused pose (the odometry, drift and all), and
            # held there as the odometry's step is worth, as a replay holds it: down a corridor longer
            # than the lidar sees, the scans alone would hold the pose back where the map is drawn.
            result = self.mapper.add_scan_odometry(
                t, turn.distances_m, turn.angles_rad, odom, site=site, waiting=turn.waiting
            )
        else:
            result = self.mapper.add_scan(t, turn.distances_m, turn.angles_rad, pose, site=site, waiting=turn.waiting)
        moved = self.mapper.take_moved()
        if odom is not None and self.mapper.pose is not None:
            self._odom_frame = compose(self.mapper.pose, inverse_pose(odom))  # after the solves, if any
        seen = None
        if not was_anchored or moved is None or turn.follows is None:
            # Before the map is anchored the fusion has not followed it, so the solve that anchors it
            # (which can turn a map begun a degree or two askew) must not move the pose.
            moved = None
        else:
            moved = followed_part(moved, compose(inverse_pose(moved), result.pose), turn.follows)
            if max(abs(v) for v in moved) < 1e-9:
                moved = None  # a solve that moved nothing here, or only along what the fusion kept its own
        info = result.information
        if self._map_anchored() and result.matched and info is not None and result.weak >= SEEN_MIN_WEAK:
            seen = Seen(t, result.pose, seen_covariance(info, result.pose, self.config.mount))

        # The grid is read (drawn up to date: agent/mapping/mapper.py) only when a planner may be due
        # here, or a share in ``_publication`` (at most every ``share_period``).
        renew = self._planned_version < 0 or (driving and now >= self._next_planner)
        planner = None
        if renew:
            grid = self.mapper.grid
            if not grid.empty and grid.version != self._planned_version:
                self._next_planner = now + self.planner_period
                self._planned_version = grid.version
                planner = self.mapper.planner()
        return Update(
            restarted, planner, self._publication(now), moved, seen, self._odom_frame if odom is not None else None
        )

    def _map_anchored(self) -> bool:
        """The map is in the site frame and its pose graph has been solved with ``ANCHOR_PRIORS``
        site priors or more: its frame is the anchors' now, not the fused heading it happened to start
        with. Only from then on does the fusion hear from the map (``Update.moved``, ``Update.seen``)."""
        closer = self.mapper.closer
        if closer is None or not self.in_site_frame:
            return False
        if not self._anchored:
            self._anchored = closer.stats.solves > 0 and len(closer.graph.priors) >= ANCHOR_PRIORS
        return self._anchored

    def _publication(self, now: float) -> MapPublication | None:
        mapper = self.mapper
        if now < self._next_share or mapper.version == self._shared_version or mapper.grid.empty:
            return None
        self._shared_version = mapper.version
        self._next_share = now + self.share_period
        pub = MapPublication.of(mapper, site_frame=self.in_site_frame, base=self._version_base)
        pub = replace(pub, began=self._began or 0.0)
        closer = mapper.closer
        if closer is None:
            return pub
        # The submaps as the graph has them now: each drawn again only when nodes joined it (a
        # finished submap once; Cartographer's submaps too stay as drawn when finished).
        drawn, poses = [], []
        for i, sm in enumerate(closer.submaps):
            version, pose = sm.last - sm.first, closer.poses[sm.first]
            poses.append((i, version, pose))
            if self._submap_versions.get(i) != version:
                cells, res, origin = closer.draw_occupancy(i)
                drawn.append(Submap(i, version, pose, cells, res, origin))
                self._submap_versions[i] = version
        return replace(pub, submaps=tuple(drawn), submap_poses=tuple(poses))

    def _due(self, t: float, pose: tuple[float, float, float], waiting: bool = False) -> bool:
        if self._last is None:
            return True
        t0, x0, y0, th0 = self._last
        turned = abs(math.remainder(pose[2] - th0, math.tau))
        moved = math.hypot(pose[0] - x0, pose[1] - y0)
        gap = min(self.max_gap_s, self.config.keyframe_period_waiting) if waiting else self.max_gap_s
        return moved >= self.min_move_m or turned >= self.min_turn_rad or t - t0 >= gap
