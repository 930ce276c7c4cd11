"""The onboard mapper: one small class the agent runtime feeds with lidar scans and fused poses.

    mapper = OnboardMapper(MapperConfig())
    result = mapper.add_scan(t, ranges, angles, pose_guess)   # -> ScanResult; result.pose is the robot pose
    mapper.plan((x0, y0), (x1, y1))                           # -> [(x, y), ...], [] (no path) or None (no map)

Per scan: prepare (valid returns, polar to Cartesian), segment and drop tiny segments, thin the
points for matching, match against the map seeded by ``pose_guess`` (the fused pose), and fall back
to the guess when the match is poor (score below ``min_score``, too few points, or no map yet). The
scan is integrated into the grid when the robot has moved ``keyframe_distance`` / turned
``keyframe_angle`` since the last integrated scan (the matcher needs no new map between nearby
scans, and ray updates are the costly part), or when ``keyframe_period`` seconds have passed;
``keyframe_period_waiting`` while the pilot stands waiting for the way to clear (``add_scan``'s
``waiting``): a robot that saw another stand on its goal holds it as a wall until enough scans have
seen through the place, and one a turn every 5 s takes 40 s to clear a cell hit at its clamp.

``add_scan_odometry(t, ranges, angles, odom_pose)`` is the same with an odometry pose (in its own
frame) instead of a map-frame guess: the guess is the last matched pose moved by the odometry
increment (used by log replay).

Poses are the *robot* pose (x, y, theta) in the map frame (the UWB frame when seeded by fusion);
the lidar's mount on the robot is in the config. Time is passed in; nothing here reads a clock.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from fleetlink.agent.mapping import scan as scanprep
from fleetlink.agent.mapping.closure import CloserConfig, ClosureSearch, LoopCloser, NodeScan
from fleetlink.agent.mapping.grid import GridConfig, LogOddsGrid
from fleetlink.agent.mapping.matcher import LocalMap, MatchConfig, field_score, icp_refine, match_scan, scan_normals
from fleetlink.agent.mapping.planner import PathPlanner, PlannerConfig
from fleetlink.shared.se2 import Pose, compose, inverse, relative, wrap

__all__ = ["MapperConfig", "OnboardMapper", "Pose", "ScanResult", "compose", "relative"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class MapperConfig:
    grid: GridConfig = field(default_factory=GridConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    matching: bool = True  # False: map at the guess (odometry / fused pose only)
    min_range: float = 0.15  # m
    max_range: float = 12.0  # m; readings at/over it only clear space
    missing_ray: float = 0.0  # m: a sector with no return clears this far (0: off; scan.prepare)
    missing_run: int = 5  # samples with no return in a row that make a sector (fewer: dropouts)
    segment_eps: float = 0.3  # m, absolute break distance
    segment_tau: float = 5.0  # break where a gap is tau times its neighbour
    min_segment_points: int = 3
    match_cell: float = 0.1  # m, thinning cell for the matcher's points
    min_score: float = 0.15  # below: the match is poor, keep the guess (measured on intel and the office)
    min_points: int = 20  # fewer matchable points: keep the guess
    keyframe_distance: float = 0.1  # m
    keyframe_angle: float = math.radians(5.0)
    keyframe_period: float = 5.0  # s
    keyframe_period_waiting: float = 0.2  # s, while the pilot waits for the way to clear (``add_scan``)
    mount: Pose = (0.0, 0.0, 0.0)  # lidar on the robot: x, y, yaw
    refine_local: bool = True  # point-to-line refinement against the last keyframes (False: field only)
    local_keyframes: int = 5
    local_cell: float = 0.1  # m, fusion cell of the local map
    local_spacing: float = 0.3  # m: a keyframe joins the local map this far from the last one that did
    local_spacing_angle: float = math.radians(10.0)
    icp_cell: float = 0.0  # m, thinning of the refined points (0: all)
    icp_sigma: float = 0.03  # m, point-to-line residual scale (Cauchy)
    icp_max_distance: float = 0.15  # m, farthest correspondence
    min_inlier_ratio: float = 0.3  # refined with at least this share of points matched: accept (else min_score rules)
    # Motion prior of an odometry-seeded guess (add_scan_odometry): sd = base + per metre moved
    # (+ per radian turned, for the heading). add_scan uses MatchConfig's prior_sigma_* unless given.
    odom_sigma_xy: float = 0.01  # m
    odom_sigma_xy_per_m: float = 0.1
    odom_sigma_theta: float = 0.01  # rad
    odom_sigma_theta_per_m: float = 0.035  # rad per m (2 deg)
    odom_sigma_theta_per_rad: float = 0.1
    # ... a default for odometry of unknown worth. What it is worth is learned as the log goes: each
    # matched scan's heading against the odometry's guess, in units of that guess's sd, over the last
    # ``odom_learn_scans`` steps of 0.29 m or more (where the distance adds at least the fixed 0.01 rad
    # to the sd); once half of them are in, the refinement's prior is that median spread (as a
    # Gaussian sd) times ``odom_learn_margin``, never wider than the default nor narrower than
    # ``odom_learn_min_scale`` of it. A corrected log's poses (GMapping's: a few tenths of a degree
    # from the scans a step of 0.7-1 m) are worth far more than 2 degrees a metre, and held at the
    # default the front end moved them by its own drift (aces' complete relations 0.041 -> 0.030 m).
    # Logs of short steps (the raw Freiburg logs, 0.06-0.2 m a scan) learn nothing and keep the
    # default (0: off).
    odom_learn_scans: int = 100
    odom_learn_margin: float = 2.0
    odom_learn_min_scale: float = 0.15
    # ... and only once that is at most this share of the default: odometry 10 % off a step (the
    # corrected logs' bench perturbs them so) came out at 0.8-0.9, and held there it cost aces at two
    # seeds of five 0.045-0.048 -> 0.055-0.060 m; the default suits such odometry.
    odom_learn_engage: float = 0.5
    # Loop closure (closure.py): the spaced keyframes become pose-graph nodes, closures are searched
    # and verified at a bounded rate, and the grid is redrawn from the optimised poses. None: off.
    closer: CloserConfig | None = field(default_factory=CloserConfig)
    # With loop closure, the front end matches the older of two staggered grids of the last
    # ``recent_scans`` keyframes instead of the whole grid (Cartographer's local SLAM): its steps, the
    # graph's odometry, are then local and not pulled onto older walls (measured: office final ATE
    # 0.027 -> 0.015 m; intel and aces within their seed-to-seed spread or better). 0: the whole grid.
    recent_scans: int = 60
    redraw_distance: float = 0.05  # m (a turn counts as its arc 3 m out): redraw the grid past this
    # A redraw draws at most this many keyframes per read of the grid, into a second grid that takes
    # the first one's place once every keyframe is in it (0: all at once). Bounds what a read costs
    # however long the run: on a robot the map is read every second or two (share, planner).
    redraw_batch: int = 0
    # A match refused (neither rule accepts it) is tried again with the motion prior's sd this many
    # times wider, and taken if its refinement finds lines for ``min_inlier_ratio`` of the points. The
    # prior costs ``prior_weight * d^2 / 2`` of mean field value, 0.6 at 2 sd: more than a whole match
    # scores on a real log, so odometry 2-3 sd off (10 % noise does it now and then) made the right pose
    # lose to the guess, and the scan went into the map at the guess (aces seed 2: two turns in place
    # 6 and 9 deg short, a map 15 deg askew from there on). 0: off (the guess is kept).
    retry_prior_scale: float = 3.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_range < self.max_range:
            raise ValueError("need 0 <= min_range < max_range")
        if self.segment_eps <= 0 or self.segment_tau <= 1.0:
            raise ValueError("need segment_eps > 0 and segment_tau > 1")
        if not (self.missing_ray >= 0.0 and self.missing_run >= 1):
            raise ValueError(f"need missing_ray >= 0 and missing_run >= 1, got {self.missing_ray}, {self.missing_run}")
        if not (self.keyframe_period > 0.0 and self.keyframe_period_waiting > 0.0):
            raise ValueError("need keyframe_period and keyframe_period_waiting > 0")
        if not 0.0 <= self.min_score <= 1.0:
            raise ValueError("min_score must be in [0, 1]")
        if self.odom_learn_scans < 0 or not (
            self.odom_learn_margin > 0 and 0 < self.odom_learn_min_scale <= self.odom_learn_engage <= 1
        ):
            raise ValueError(
                "need odom_learn_scans >= 0, odom_learn_margin > 0"
                " and 0 < odom_learn_min_scale <= odom_learn_engage <= 1"
            )


@dataclass(frozen=True, slots=True)
class ScanResult:
    t: float
    pose: Pose  # robot pose after matching (or the guess)
    guess: Pose
    matched: bool  # the match was used (False: fell back to the guess)
    score: float
    integrated: bool  # the scan was added to the grid
    weak: float = 0.0  # the refinement's weakest information (1/m^2; 0: not refined): how well the match is posed
    information: FloatArray | None = (
        None  # the refinement's data information on the sensor pose (x, y, theta), map frame
    )


class OnboardMapper:
    """Builds the map on board; see the module docstring. Not thread-safe (one owner)."""

    def __init__(self, config: MapperConfig | None = None, search: ClosureSearch | None = None) -> None:
        """``search``: where loop closure's checks run (agent/mapping/worker.py; their verdicts come
        back at a later node); None: in line, each node searched and solved as it is made (a replay)."""
        self.config = cfg = config or MapperConfig()
        self.search = search
        self._grid = LogOddsGrid(cfg.grid)
        # With loop closure and recent grids the whole grid is an output only (the front end matches
        # the recent grids): its likelihood field is brought up to date, and the grid drawn again
        # after solves, when it is read (``grid``, ``occupancy``, ``plan``, ``version``), not per scan.
        # Lazily: a keyframe is drawn into the whole grid when the grid is next read, at its node's pose
        # then (a replay draws each scan once, at the end, instead of once per scan and again at the end).
        self._lazy = cfg.closer is not None and cfg.recent_scans > 0
        self._redraw_due = False
        self._undrawn = 0  # entries of ``_drawn`` from here on are not in the grid yet (lazy only)
        self._mapped = False  # some keyframe has been integrated (the grid may not show it yet)
        self.trajectory: list[tuple[float, Pose]] = []
        self.scans = 0
        self.matched = 0
        self.fallbacks = 0
        self.retried = 0  # scans matched only on the retry with a wider motion prior (``retry_prior_scale``)
        self.rejected = 0  # scans with no usable beams, or a non-finite pose
        self._last_key: tuple[float, Pose] | None = None
        self._last_pose: Pose | None = None
        self._last_odom: Pose | None = None
        # The odometry's worth (``odom_learn_scans``): matched headings against its guesses, in units of
        # the guess's sd, the newest last; and the scale its prior is held at in the refinement now.
        self._odom_spread: deque[float] = deque(maxlen=max(cfg.odom_learn_scans, 1))
        self.odom_scale = 1.0
        self._planner: PathPlanner | None = None
        self._local = LocalMap(cfg.local_keyframes, cfg.local_cell)
        self._last_local: Pose | None = None
        self._planner_version = -1
        # The recent grids, oldest first: [scans integrated], the grid, and the transform from the map
        # frame into the grid's own frame (the frame the grid was drawn in: a solve that moves the
        # front end moves the grid with it by composing this, not by drawing it again).
        self._recent: list[tuple[list[int], LogOddsGrid, list[Pose]]] = []
        self.closer = LoopCloser(cfg.closer, cfg.grid, cfg.mount) if cfg.closer is not None else None
        # For redrawing after a solve: each integrated scan's node, its pose in the node's frame, and
        # its beams; per trajectory entry, its node and offset (-1: before the first node).
        self._drawn: list[
            tuple[int, Pose, npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.bool_]]
        ] = []
        self._links: list[tuple[int, Pose]] = []
        self._node_pose: Pose | None = None  # the newest node's pose as the front end has it
        self._steps: list[Pose] = []  # per node, the front end's step from the node before (first: 0)
        self._drawn_at: list[Pose] = []  # each node's pose when the grid was last drawn from it
        self.redraws = 0
        # A redraw under way in steps (``redraw_batch``): the grid drawn into, the next entry of
        # ``_drawn`` to draw, each node's pose as drawn there.
        self._back: LogOddsGrid | None = None
        self._back_next = 0
        self._back_at: list[Pose] = []
        self._moved: Pose | None = None  # how the solves since ``take_moved`` moved the frame at the robot

    @property
    def grid(self) -> LogOddsGrid:
        """The map, up to date: drawn again from the graph's poses if a solve has moved some node more
        than ``redraw_distance`` since it was last drawn, its likelihood field refreshed. A redraw costs
        every integrated scan's ray update, so with loop closure the grid is drawn when read, at the
        reader's rate (the map share's 1 Hz on board; once at the end of a replay), not after every
        solve."""
        cfg = self.config
        if self._redraw_due and self._back is None:
            self._redraw_due = False
            if cfg.redraw_batch > 0 and self._lazy:
                if self._moved_since_drawn() > cfg.redraw_distance:
                    self._back, self._back_next, self._back_at = self._grid.blank_like(), 0, []
            else:
                self.redraw(cfg.redraw_distance)
        if self._back is not None:
            self._redraw_step(cfg.redraw_batch)
        if self._undrawn < len(self._drawn):
            self._draw(self._drawn[self._undrawn :])
        self._grid.refresh_stale()
        return self._grid

    @property
    def version(self) -> int:
        return self.grid.version

    @property
    def pose(self) -> Pose | None:
        return self._last_pose

    def add_scan_odometry(
        self,
        t: float,
        ranges: npt.ArrayLike,
        angles: npt.ArrayLike,
        odom: Pose,
        site: tuple[float, float, float] | None = None,
        waiting: bool = False,
    ) -> ScanResult:
        """Like ``add_scan`` with the guess = last pose moved by the odometry increment since the last scan,
        held to it as the odometry's step is worth (``odom_sigma_*``; in the point-to-line refinement scaled
        by ``odom_scale`` once learned): down a corridor the scans cannot place, the odometry carries the pose."""
        cfg = self.config
        prior: tuple[float, float] | None = None
        d = 0.0  # m, the odometry's step
        if self._last_pose is None or self._last_odom is None:
            guess = odom
        else:
            inc = relative(self._last_odom, odom)
            guess = compose(self._last_pose, inc)
            d = math.hypot(inc[0], inc[1])
            prior = (
                cfg.odom_sigma_xy + cfg.odom_sigma_xy_per_m * d,
                cfg.odom_sigma_theta + cfg.odom_sigma_theta_per_m * d + cfg.odom_sigma_theta_per_rad * abs(inc[2]),
            )
        if prior is None:
            res = self.add_scan(t, ranges, angles, guess, prior, site, odometry=odom, waiting=waiting)
            self._last_odom = odom
            return res
        moved = self._moved
        res = self.add_scan(
            t, ranges, angles, guess, prior, site, odometry=odom, refine_scale=self.odom_scale, waiting=waiting
        )
        # Only once the turn was taken: a refused one (a NaN odometry, say) leaves the next step measured
        # from the last good odometry, not from the refused one.
        self._last_odom = odom
        # Learned from steps along the way, where holding the heading is what the prior is for (a turn
        # in place mixes in the wheels' slip and the matcher's own turn), and long enough that the
        # distance's share of the guess's sd is at least its fixed share: on shorter steps the
        # matcher's own noise is all there is to see.
        # (Not a scan whose node a solve moved: its pose is in the corrected frame, the guess is not.)
        if (
            res.matched
            and self._moved is moved
            and res.weak > 0.0
            and cfg.odom_learn_scans
            and cfg.odom_sigma_theta_per_m * d >= cfg.odom_sigma_theta
        ):
            self._learn_odometry(abs(wrap(res.pose[2] - res.guess[2])) / prior[1])
        return res

    def _learn_odometry(self, spread: float) -> None:
        """One matched scan's heading against the odometry's guess, in units of the guess's sd."""
        cfg = self.config
        self._odom_spread.append(spread)
        if 2 * len(self._odom_spread) >= cfg.odom_learn_scans:
            # The median of |N(0, s)| is 0.6745 s.
            sd = float(np.median(np.fromiter(self._odom_spread, dtype=np.float64))) / 0.6745
            scale = cfg.odom_learn_margin * sd
            self.odom_scale = 1.0 if scale > cfg.odom_learn_engage else max(cfg.odom_learn_min_scale, scale)

    def add_scan(
        self,
        t: float,
        ranges: npt.ArrayLike,
        angles: npt.ArrayLike,
        pose_guess: Pose,
        prior: tuple[float, float] | None = None,
        site: tuple[float, float, float] | None = None,
        odometry: Pose | None = None,
        refine_scale: float = 1.0,
        waiting: bool = False,
    ) -> ScanResult:
        """One lidar turn (ranges m, angles rad CCW in the sensor frame) near ``pose_guess``; returns the pose.

        ``prior``: (sd xy m, sd theta rad) of the guess; None: ``MatchConfig.prior_sigma_*``.
        ``site``: (x, y, sd) a site-frame position measured at this scan (a UWB fix, or the fused
        pose once UWB has placed the robot); with loop closure, a node made from this scan takes it
        as a prior, so the map is pulled into the site frame and stays there through closures.
        ``refine_scale``: the prior's sd in the point-to-line refinement is this share of it
        (``add_scan_odometry``: what the odometry is worth, learned). ``waiting``: the pilot stands
        waiting for the way to clear; a standing robot's scans join the grid every
        ``keyframe_period_waiting`` instead of ``keyframe_period``."""
        cfg = self.config
        self.scans += 1
        guess = (float(pose_guess[0]), float(pose_guess[1]), wrap(float(pose_guess[2])))
        if not all(math.isfinite(v) for v in guess) or not math.isfinite(t):
            self.rejected += 1
            raise ValueError(f"non-finite pose guess {pose_guess!r} or time {t!r}")
        if odometry is not None and not all(math.isfinite(float(v)) for v in odometry):
            self.rejected += 1
            raise ValueError(f"non-finite odometry {odometry!r}")
        if site is not None and not (
            len(site) == 3 and all(math.isfinite(float(v)) for v in site) and float(site[2]) > 0
        ):
            self.rejected += 1
            raise ValueError(f"site must be (x, y, sd) finite with sd > 0, got {site!r}")
        r, a, hit = scanprep.prepare(ranges, angles, cfg.min_range, cfg.max_range, cfg.missing_ray, cfg.missing_run)
        pts = scanprep.to_points(r[hit], a[hit])
        keep_hit = np.ones(len(pts), dtype=bool)
        labels = np.zeros(len(pts), dtype=np.int64)
        if len(pts):
            labels = scanprep.segment_labels(pts, cfg.segment_eps, cfg.segment_tau)
            keep_hit = scanprep.filter_segments(labels, cfg.min_segment_points)
        kept = pts[keep_hit]
        match_pts = scanprep.thin(kept, cfg.match_cell)

        sensor_guess = compose(guess, cfg.mount)
        pose, score, matched, weak = guess, 0.0, False, 0.0
        info: FloatArray | None = None
        target, to_target = self._match_grid()
        if cfg.matching and not target.empty and len(match_pts) >= cfg.min_points:
            sd = prior if prior is not None else (cfg.match.prior_sigma_xy, cfg.match.prior_sigma_theta)
            found, score, good, weak, info = self._match(
                target, to_target, match_pts, kept, sensor_guess, sd, refine_scale
            )
            if not (good or score >= cfg.min_score) and cfg.retry_prior_scale > 0:
                k = cfg.retry_prior_scale
                found2, score2, good2, weak2, info2 = self._match(
                    target, to_target, match_pts, kept, sensor_guess, (sd[0] * k, sd[1] * k), refine_scale
                )
                if good2:
                    found, score, good, weak, info = found2, score2, good2, weak2, info2
                    self.retried += 1
            if good or score >= cfg.min_score:
                pose = compose(found, inverse(cfg.mount))
                pose = (pose[0], pose[1], wrap(pose[2]))
                matched = True
        if matched:
            self.matched += 1
        elif self._mapped:
            self.fallbacks += 1

        integrated = False
        if r.size and self._is_keyframe(t, pose, waiting):
            # Drop the noise segments' endpoints from the map, but keep their beams' free space.
            full_hit = hit.copy()
            idx = np.flatnonzero(hit)
            full_hit[idx[~keep_hit]] = False
            if not self._lazy:
                self._grid.integrate(compose(pose, cfg.mount), r, a, full_hit)
            self._mapped = True
            if cfg.recent_scans and self.closer is not None:
                self._add_recent(compose(pose, cfg.mount), r, a, full_hit)
            made_node = False
            if self._spaced(pose):
                self._last_local = pose
                normals = scan_normals(pts, labels)[keep_hit]
                if cfg.refine_local:
                    self._local.add(compose(pose, cfg.mount), kept, normals)
                if self.closer is not None:
                    scan = NodeScan(r, a, full_hit, kept, normals, match_pts)
                    self.closer.add_node(t, pose, scan, site, info if matched else None, odometry)
                    self._steps.append(
                        relative(self._node_pose, pose) if self._node_pose is not None else (0.0, 0.0, 0.0)
                    )
                    self._node_pose = pose
                    made_node = True
            self._last_key = (t, pose)
            integrated = True
            if self.closer is not None and self._node_pose is not None:
                node = len(self.closer) - 1
                self._drawn.append(
                    (node, relative(self._node_pose, pose), r.astype(np.float32), a.astype(np.float32), full_hit)
                )
                if not self._lazy:
                    self._undrawn = len(self._drawn)
                if made_node and self._close():
                    pose = self._after_solve(pose)
        self._last_pose = pose
        self.trajectory.append((t, pose))
        if self.closer is not None:
            self._links.append(
                (len(self.closer) - 1, relative(self._node_pose, pose)) if self._node_pose is not None else (-1, pose)
            )
        if not matched:
            weak, info = 0.0, None
        return ScanResult(t, pose, guess, matched, score, integrated, weak, info)

    def _match(
        self,
        target: LogOddsGrid,
        to_target: Pose,
        match_pts: FloatArray,
        kept: FloatArray,
        sensor_guess: Pose,
        sd: tuple[float, float],
        refine_scale: float,
    ) -> tuple[Pose, float, bool, float, FloatArray | None]:
        """The front end's match of one scan near ``sensor_guess`` with motion-prior sd ``sd`` (held at
        ``refine_scale`` of it in the point-to-line refinement): the sensor
        pose found, its field score, whether the refinement found lines for enough points, the
        refinement's weakest information and its information matrix (None: not refined)."""
        cfg = self.config
        # Matched in the target grid's frame (a rigid move of the map frame: the prior's penalty,
        # isotropic in x and y, is the same in either), refined and reported in the map frame.
        m = match_scan(target, match_pts, compose(to_target, sensor_guess), cfg.match, sd)
        found, score = compose(inverse(to_target), m.pose), m.score
        good, weak = False, 0.0
        info: FloatArray | None = None
        if cfg.refine_local and len(self._local):
            icp_pts = scanprep.thin(kept, cfg.icp_cell)
            k = refine_scale
            r_ = icp_refine(
                self._local, icp_pts, found, sensor_guess, (sd[0] * k, sd[1] * k), cfg.icp_sigma, cfg.icp_max_distance
            )
            if r_.inliers >= cfg.min_points:
                found, weak, info = r_.pose, r_.weak, r_.information
                score = field_score(target, match_pts, compose(to_target, found))
                good = r_.inliers >= cfg.min_inlier_ratio * len(icp_pts)
        return found, score, good, weak, info

    def _close(self) -> bool:
        """Loop closure for the node just made: in line, or (``search``) the verdicts that came back
        taken into the graph and this node's checks handed out, one batch at a time (a node made
        while the last batch still runs is not searched: the search's rate is its own). True when
        the graph was solved."""
        closer, search = self.closer, self.search
        assert closer is not None
        if search is None:
            return closer.close()
        solved = closer.take(search.collect())
        if not search.busy:
            checks = closer.plan()
            if checks:
                search.submit(checks)
        return solved

    def _after_solve(self, pose: Pose) -> Pose:
        """The graph moved: carry the front end's state into the corrected frame, redraw the grid and
        the local map from the optimised node poses. Returns ``pose`` corrected."""
        cfg = self.config
        closer = self.closer
        assert closer is not None and self._node_pose is not None
        new = closer.poses[-1]
        fix = compose(new, inverse(self._node_pose))  # old frame -> corrected frame
        self._moved = fix if self._moved is None else compose(fix, self._moved)
        self._node_pose = new
        self._last_local = new
        if self._last_key is not None:
            self._last_key = (self._last_key[0], compose(fix, self._last_key[1]))
        pose = compose(fix, pose)
        poses = closer.poses
        if cfg.refine_local:
            self._local = LocalMap(cfg.local_keyframes, cfg.local_cell)
            self._local.extend(
                [
                    (compose(poses[n], cfg.mount), closer.scans[n].points, closer.scans[n].normals)
                    for n in range(max(0, len(poses) - cfg.local_keyframes), len(poses))
                ]
            )
        # The recent grids the front end matches move with it, rigidly: each keeps the transform from
        # the map frame into its own, and the correction is composed into it (exact, and no scan is
        # drawn again: redrawing the last 60 keyframes after every solve was a quarter of intel's
        # replay time). Rigidly, not at the graph's poses: those bend the recent stretch to fit older
        # closures, and the front end matching that bend measured the office 0.034 m off, not 0.015 m.
        back = inverse(fix)
        for _, _, tf in self._recent:
            tf[0] = compose(tf[0], back)
        # Redraw only once some node has moved enough since it was drawn to blur the walls (the grid's
        # field is blurred over ~2 cells anyway, and a redraw costs every scan's ray update again), and
        # only when the grid is read (see ``grid``).
        self._redraw_due = True
        if not self._lazy:
            self.grid  # noqa: B018 (drawn now: the front end matches this grid)
        return pose

    def take_moved(self) -> Pose | None:
        """How the loop closer's solves since the last call moved the map frame where the robot is:
        the transform taking a pose in the old frame to the corrected one (composed over the solves),
        or None (no solve moved it). Whoever localises the robot in this map moves its pose by it."""
        moved, self._moved = self._moved, None
        return moved

    def finish(self) -> int:
        """The end of a run (a replay): the loop closer's final pass (every node matched against the
        submaps near it, the graph solved again; ``LoopCloser.finish``), the grid due a redraw. Returns
        the edges the pass added; 0 without loop closure."""
        if self.closer is None:
            return 0
        added = self.closer.finish()
        self._redraw_due = True
        return added

    def redraw(self, threshold: float = 0.0) -> bool:
        """Draw the grid again from every integrated scan at the graph's poses, if some node moved more
        than ``threshold`` (m; a turn as its arc 3 m out) since the last drawing. True if it did."""
        closer = self.closer
        if closer is None:
            return False
        if self._drawn_at and self._moved_since_drawn() <= threshold:
            return False
        self.redraws += 1
        self._redraw_due = False
        self._back = None
        self._grid.clear()
        self._undrawn = 0
        self._drawn_at = []
        self._draw(self._drawn)
        self._grid.refresh()
        return True

    def _moved_since_drawn(self) -> float:
        """How far the node that moved most has moved since the grid was drawn from it (m; a turn as
        its arc ``REDRAW_LEVER_M`` out); 0 before any drawing."""
        n_drawn = len(self._drawn_at)
        if self.closer is None or not n_drawn:
            return 0.0
        was = np.array(self._drawn_at)
        now = np.array(self.closer.poses[:n_drawn])
        turn = np.abs(np.remainder(now[:, 2] - was[:, 2] + math.pi, 2.0 * math.pi) - math.pi)
        return float(np.max(np.hypot(now[:, 0] - was[:, 0], now[:, 1] - was[:, 1]) + REDRAW_LEVER_M * turn))

    def _redraw_step(self, batch: int) -> None:
        """Draw the next ``batch`` keyframes into the grid being redrawn, placed from their nodes' poses
        now (``_placed``); once every keyframe is in it (those integrated meanwhile too), it takes the
        grid's place: the version goes on from the old grid's, and all of it is marked changed."""
        back = self._back
        assert back is not None and self.closer is not None
        poses = self.closer.poses
        mount = self.config.mount
        stop = min(len(self._drawn), self._back_next + batch)
        for node, offset, r, a, hit in self._drawn[self._back_next : stop]:
            sensor = compose(self._placed(poses, node, offset), mount)
            back.integrate(sensor, r.astype(np.float64), a.astype(np.float64), hit, refresh=False)
            if node >= len(self._back_at):
                self._back_at.extend(poses[len(self._back_at) : node + 1])
        self._back_next = stop
        if stop < len(self._drawn):
            return
        back.version = max(back.version, self._grid.version) + 1
        back.dirty = (0, 0, *back.shape)
        self._grid, self._back = back, None
        self._undrawn = len(self._drawn)
        self._drawn_at = self._back_at
        self.redraws += 1
        self._redraw_due = True  # a solve since the redraw began may have moved nodes again

    def _draw(
        self, entries: list[tuple[int, Pose, npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.bool_]]]
    ) -> None:
        """Integrate ``entries`` (the tail of ``_drawn``) into the grid, placed from their nodes' poses
        now (``_placed``); the field is left stale (refreshed when read). Each node's pose is remembered
        as drawn."""
        poses = self.closer.poses if self.closer is not None else []
        mount = self.config.mount
        for node, offset, r, a, hit in entries:
            sensor = compose(self._placed(poses, node, offset), mount)
            self._grid.integrate(sensor, r.astype(np.float64), a.astype(np.float64), hit, refresh=False)
        self._undrawn = len(self._drawn)
        self._drawn_at.extend(poses[len(self._drawn_at) :])

    def corrected_trajectory(self) -> list[tuple[float, Pose]]:
        """Every scan's pose as the optimised graph has it now (the online poses were each the best
        estimate at their time; after a closure the past moves too), placed as ``_placed`` says.
        Without loop closure: the trajectory as it was."""
        if self.closer is None:
            return list(self.trajectory)
        poses = self.closer.poses
        return [
            (t, offset if node < 0 else self._placed(poses, node, offset))
            for (t, _), (node, offset) in zip(self.trajectory, self._links, strict=True)
        ]

    def _placed(self, poses: list[Pose], node: int, offset: Pose) -> Pose:
        """Where a scan taken ``offset`` from node ``node`` (the front end's) lies with the nodes at
        ``poses``: between two nodes, placed from both, from the node before by the offset and from the
        next node by the same offset taken back along the front end's step between them, weighted by
        how far along that step it lies. The trajectory and the grid's keyframes are placed alike."""
        pose = compose(poses[node], offset)
        if node + 1 >= len(poses):
            return pose
        # Hung off the node before alone, a scan just short of the next node kept none of that node's
        # correction: where the final pass moved a node against its neighbour down a corridor, the
        # scans before it stayed behind (aces, published relations: scan 5118, 0.15 m off its
        # neighbours both ways, the worst revisit 0.223 m; blended 0.185 m). How far along the step:
        # the offset projected on it in (x, y, a metre's arc per radian), so a turn in place is
        # measured by its turn and a straight step by its length.
        step = self._steps[node + 1]
        d2 = step[0] ** 2 + step[1] ** 2 + step[2] ** 2
        w = (offset[0] * step[0] + offset[1] * step[1] + offset[2] * step[2]) / d2 if d2 > 1e-12 else 0.0
        w = min(1.0, max(0.0, w))
        if w <= 0.0:
            return pose
        other = compose(poses[node + 1], relative(step, offset))
        return (
            pose[0] + w * (other[0] - pose[0]),
            pose[1] + w * (other[1] - pose[1]),
            wrap(pose[2] + w * wrap(other[2] - pose[2])),
        )

    def _match_grid(self) -> tuple[LogOddsGrid, Pose]:
        """What the front end matches against and the transform from the map frame into its frame:
        the whole grid, or (``recent_scans``) the older of two staggered recent grids, so the steps it
        measures are local (Cartographer's local SLAM)."""
        if not self._recent:
            return self.grid, (0.0, 0.0, 0.0)
        _, grid, tf = self._recent[0]
        return grid, tf[0]

    def _add_recent(self, sensor: Pose, r: FloatArray, a: FloatArray, hit: npt.NDArray[np.bool_]) -> None:
        """Add a keyframe to the recent grids: a second grid starts when the first holds half of
        ``recent_scans``, and the first is dropped once it holds them all, so the one matched against
        always holds between half and all of the last ``recent_scans`` keyframes. A new grid starts in
        the map frame as it is now."""
        n = self.config.recent_scans
        if not self._recent or (self._recent[-1][0][0] >= n // 2 and len(self._recent) < 2):
            self._recent.append(([0], LogOddsGrid(self.config.grid), [(0.0, 0.0, 0.0)]))
        for i, (count, grid, tf) in enumerate(self._recent):
            # Only the grid matched against needs its likelihood field now; the younger one's is
            # brought up to date (to the bit the same) when it takes over.
            grid.integrate(compose(tf[0], sensor), r, a, hit, refresh=i == 0)
            count[0] += 1
        if self._recent[0][0][0] >= n:
            self._recent.pop(0)
            if self._recent:
                self._recent[0][1].refresh_stale()

    def _spaced(self, pose: Pose) -> bool:
        p0 = self._last_local
        if p0 is None:
            return True
        cfg = self.config
        return (
            math.hypot(pose[0] - p0[0], pose[1] - p0[1]) >= cfg.local_spacing
            or abs(wrap(pose[2] - p0[2])) >= cfg.local_spacing_angle
        )

    def _is_keyframe(self, t: float, pose: Pose, waiting: bool = False) -> bool:
        if self._last_key is None:
            return True
        cfg = self.config
        t0, p0 = self._last_key
        return (
            math.hypot(pose[0] - p0[0], pose[1] - p0[1]) >= cfg.keyframe_distance
            or abs(wrap(pose[2] - p0[2])) >= cfg.keyframe_angle
            or t - t0 >= (cfg.keyframe_period_waiting if waiting else cfg.keyframe_period)
        )

    # -- outputs -------------------------------------------------------------------------------

    def occupancy(self) -> tuple[npt.NDArray[np.int8], float, tuple[float, float]]:
        """(cells, resolution, origin): map_server-style int8 cells, row 0 at the bottom."""
        grid = self.grid
        return grid.occupancy(), grid.resolution, grid.origin

    def planner(self) -> PathPlanner:
        """A planner over the current map (rebuilt when the map changed)."""
        if self._planner is None or self._planner_version != self.grid.version:
            cells, res, origin = self.occupancy()
            self._planner = PathPlanner(cells, res, origin, self.config.planner)
            self._planner_version = self.grid.version
        return self._planner

    def plan(
        self,
        start_xy: tuple[float, float],
        goal_xy: tuple[float, float],
        blocked: Sequence[tuple[float, float]] = (),
        bodies: Sequence[tuple[float, float]] = (),
    ) -> list[tuple[float, float]] | None:
        """The path provider the pilot takes: waypoints from start to goal, [] when there is no path,
        None when there is no map yet (the pilot then drives straight). ``blocked``: points where the
        robot found the way barred, planned around; ``bodies``: other robots standing there."""
        if self.grid.empty:
            return None
        return self.planner().route(start_xy, goal_xy, blocked, bodies)


REDRAW_LEVER_M = 3.0
"""A node's turn counts towards ``redraw_distance`` as the arc it moves a wall this far away."""
