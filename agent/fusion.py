"""UWB/odometry fusion: an EKF on the map-frame pose with odometry calibration, gated, with replay.

Pure: odometry poses and fixes come in with their times; nothing reads a clock.

State ``[x, y, theta, k, b]`` in the map (UWB) frame: position, heading, the odometry's distance
scale ``k`` (true distance = k * odometry distance: wheel-radius error) and its heading-rate bias
``b`` (rad/s: gyro bias). ``v`` and ``omega`` are outputs (``k * v_odom``, ``omega_odom - b``).

- ``predict(odom)``: the odometry increment since the previous odometry pose drives the model
  (robot_localization's "differential" use of odometry); process noise grows with distance, turn
  and time.
- ``add_fix(fix, now)``: a position update with R from the fix's sd_x/sd_y (floored), behind a chi^2
  gate on the normalised innovation squared. The gate sees the filter's position covariance capped
  at ``gate_max_sd_m``, so a covariance grown during an outage never opens the gate to every
  outlier; good fixes the capped gate refuses after a long outage are not locked out either: a run
  of ``reinit_after`` consecutive rejections that agree with each other (checked through the
  odometry between them) re-initialises the pose from that run.
- ``add_map_pose(obs, now)``: the robot's pose as its onboard map has it (scan-matched against the
  map, the map loop-closed and anchored to the site frame by UWB): a full pose update (x, y, heading)
  with R from the observation's sd, gated on its own chi^2 (3 degrees of freedom), applied at its time
  through the same history as fixes. Only once the heading is known (the map is in the site frame).
- ``shift_frame(tf)``: the map frame moved under the robot (a loop closure's solve corrected the map
  where the robot is): the filter's state, its history and the published pose move with it, rigidly
  and at once, so the pose the pilot drives on stays where the map says it is.
- Initialisation: the first ``init_fixes`` fixes that agree give the position; the heading comes
  from aligning the fixes' path with the odometry's path once the robot has moved
  ``heading_init_path_m``; before that the heading is marked unknown and not used.
- Late and out-of-order fixes: every odometry step and fix is a node in a ``history_s`` long
  history holding the state after it; a fix older than the newest node is inserted at its time
  (odometry interpolated) and everything after it is replayed. A fix newer than the last odometry
  waits until odometry passes its time, so fixes always apply at the instant they were measured.

Two outputs, as robot_localization: ``odom_pose()`` (continuous, never jumps) and ``map_pose()``
(absorbs corrections, at a bounded rate so that it does not jump either: it follows the odometry
and closes the gap to the filter's estimate at ``output_rate_mps``; the filter's own estimate,
exact and replay-consistent, is ``filter_pose()``). ``SeedReset`` is the rescue-robot seed's
method, for benchmarks only.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from fleetlink.agent.odometry import OdomPose, wrap_angle
from fleetlink.agent.uwb_input import FixObservation
from fleetlink.shared.se2 import compose

__all__ = ["FixVerdict", "Fusion", "FusionConfig", "MapPose", "Pose2D", "PoseObservation", "SeedReset"]

Vec = npt.NDArray[np.float64]

_X, _Y, _TH, _K, _B = range(5)
_I5 = np.eye(5)
_H = np.zeros((2, 5))
_H[0, _X] = _H[1, _Y] = 1.0
_H3 = np.zeros((3, 5))
_H3[0, _X] = _H3[1, _Y] = _H3[2, _TH] = 1.0


@dataclass(frozen=True, slots=True)
class FusionConfig:
    gate: bool = True
    gate_chi2: float = 13.82  # chi^2, 2 degrees of freedom, 99.9 %
    gate_max_sd_m: float = 0.5  # the filter's position sd is capped at this inside the gate
    history_s: float = 2.0  # late fixes up to this old are replayed (>= 1 s)
    stale_timeout_s: float = 1.0  # no fix measured for this long: UWB is stale
    future_tolerance_s: float = 0.5  # fixes measured further in the future than this are refused
    min_fix_sd_m: float = 0.03  # floor on a fix's sd (solvers can be over-confident)
    # process noise (1 sigma)
    dist_noise: float = 0.04  # forward, per metre travelled (slip, scale changes)
    lateral_noise: float = 0.01  # sideways, per metre travelled
    turn_noise: float = 0.01  # per radian turned
    heading_rw: float = 0.001  # rad per sqrt(s)
    pos_rw: float = 0.01  # m per sqrt(s) (bumps, pushes, unmodelled slip; tuned on bench/fusion.py)
    scale_rw: float = 0.0005  # per sqrt(m) travelled
    bias_rw: float = 2e-5  # rad/s per sqrt(s)
    init_scale_sd: float = 0.02
    init_bias_sd: float = 0.003  # rad/s
    estimate_scale: bool = True
    estimate_bias: bool = True
    # (re-)initialisation
    init_fixes: int = 5  # agreeing fixes needed to initialise
    reinit_after: int = 10  # consecutive gate rejections that agree: re-initialise from them
    heading_init_path_m: float = 0.5  # odometry path over which the heading is found at start
    reinit_rotate_path_m: float = 1.5  # a re-initialising run this long also re-estimates heading
    align_window_s: float = 5.0  # fixes kept for (re-)initialisation
    align_max_fixes: int = 50
    # the published pose (map_pose): corrections are applied at a bounded rate (see Fusion.map_pose)
    output_rate_mps: float = 0.2  # > 2.5x the worst real odometry drift (30 % slip at 0.5 m/s: 7.5 cm/s)
    output_max_step_m: float = 0.02  # and never more than this per output, however far apart outputs are
    output_rate_rad_s: float = 0.2  # heading corrections (100x the gyro's bias drift)
    output_snap_m: float = 1.0  # a correction larger than this is applied at once (counted: output_snaps)
    output_snap_rad: float = 0.5
    # the onboard map's pose (add_map_pose)
    map_gate_chi2: float = 16.27  # chi^2, 3 degrees of freedom, 99.9 %
    min_map_sd_m: float = 0.02  # floors on a map pose's sd
    min_map_sd_rad: float = 0.005

    def __post_init__(self) -> None:
        if self.history_s < 1.0:
            raise ValueError(f"history_s must be >= 1 s (late fixes), not {self.history_s}")
        for name in ("gate_chi2", "gate_max_sd_m", "stale_timeout_s", "min_fix_sd_m", "map_gate_chi2"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive number, not {v!r}")
        if self.init_fixes < 2 or self.reinit_after < 2:
            raise ValueError("init_fixes and reinit_after must be >= 2")
        for name in ("output_rate_mps", "output_max_step_m", "output_rate_rad_s", "output_snap_m", "output_snap_rad"):
            v = getattr(self, name)
            if not v > 0:  # inf is allowed: no limit
                raise ValueError(f"{name} must be a positive number, not {v!r}")


@dataclass(frozen=True, slots=True)
class FixVerdict:
    accepted: bool
    reason: str  # "accepted", "initialised", "reinitialised", "gate", "initialising", "too old", ...
    nis: float  # normalised innovation squared the gate saw (nan when not gated)


@dataclass(frozen=True, slots=True)
class PoseObservation:
    """The robot's pose at ``t`` (the agent's clock) as its onboard map has it: the scan matched
    against the map, in the map's frame, which UWB anchors to the site frame."""

    t: float
    x: float
    y: float
    theta: float
    cov: tuple[float, ...]
    """The covariance of (x, y, theta), 3 x 3 row-major, in the map frame."""

    @classmethod
    def of(cls, t: float, x: float, y: float, theta: float, sd_xy: float, sd_theta: float) -> PoseObservation:
        """One with ``sd_xy`` in every direction and ``sd_theta``, uncorrelated."""
        a, b = sd_xy * sd_xy, sd_theta * sd_theta
        return cls(t, x, y, theta, (a, 0.0, 0.0, 0.0, a, 0.0, 0.0, 0.0, b))


@dataclass(frozen=True, slots=True)
class Pose2D:
    x: float
    y: float
    theta: float


@dataclass(frozen=True, slots=True)
class MapPose:
    """The map-frame (UWB-frame) pose at time ``t``; sd_* are inf until the position is initialised."""

    t: float
    x: float
    y: float
    theta: float
    v: float
    omega: float
    sd_x: float
    sd_y: float
    sd_theta: float


@dataclass(frozen=True, slots=True)
class _Buf:
    """A fix kept for (re-)initialisation, with the odometry pose at its time."""

    t: float
    zx: float
    zy: float
    sd: float
    ox: float
    oy: float
    oth: float
    accepted: bool


@dataclass(frozen=True, slots=True)
class _Disc:
    """The filter's discrete state; immutable so history nodes can share it."""

    pos_init: bool = False
    heading_init: bool = False
    streak: int = 0  # consecutive gate rejections
    buffer: tuple[_Buf, ...] = ()


@dataclass(frozen=True, slots=True)
class _Output:
    """The published pose and the odometry pose it was published with."""

    x: float
    y: float
    theta: float
    odom: OdomPose
    heading_known: bool


@dataclass(slots=True)
class _Node:
    t: float
    odom: OdomPose
    fix: FixObservation | None
    x: Vec = field(default_factory=lambda: np.zeros(5))
    P: Vec = field(default_factory=lambda: np.zeros((5, 5)))
    disc: _Disc = field(default_factory=_Disc)
    verdict: FixVerdict | None = None
    counted: bool = False
    seen: PoseObservation | None = None  # a map pose (then ``fix`` is None)


@dataclass(frozen=True, slots=True)
class _Fit:
    phi: float  # map heading - odometry heading
    tx: float
    ty: float
    inliers: int
    sd_pos: float
    sd_phi: float
    rotated: bool


def _odom_increment(a: OdomPose, b: OdomPose) -> tuple[float, float, float, float]:
    """Forward and lateral motion in a's body frame, heading change, time."""
    dx, dy = b.x - a.x, b.y - a.y
    c, s = math.cos(a.theta), math.sin(a.theta)
    return c * dx + s * dy, -s * dx + c * dy, wrap_angle(b.theta - a.theta), b.t - a.t


def _interpolate(a: OdomPose, b: OdomPose, t: float) -> OdomPose:
    if b.t <= a.t:
        return replace(b, t=t)
    u = min(1.0, max(0.0, (t - a.t) / (b.t - a.t)))
    th = wrap_angle(a.theta + u * wrap_angle(b.theta - a.theta))
    return OdomPose(t, a.x + u * (b.x - a.x), a.y + u * (b.y - a.y), th, b.v, b.omega)


def _extrapolate(a: OdomPose, t: float) -> OdomPose:
    dt = t - a.t
    th = a.theta + a.omega * dt / 2
    return OdomPose(
        t,
        a.x + a.v * dt * math.cos(th),
        a.y + a.v * dt * math.sin(th),
        wrap_angle(a.theta + a.omega * dt),
        a.v,
        a.omega,
    )


def _circular_mode(angles: list[float], width: float) -> float:
    """The angle with the most others within ``width``, refined by their circular mean."""
    best, best_n = angles[0], -1
    for a in angles:
        n = sum(1 for b in angles if abs(wrap_angle(b - a)) <= width)
        if n > best_n:
            best, best_n = a, n
    near = [b for b in angles if abs(wrap_angle(b - best)) <= width]
    return math.atan2(sum(math.sin(b) for b in near), sum(math.cos(b) for b in near))


class Fusion:
    def __init__(self, config: FusionConfig | None = None) -> None:
        self.config = config or FusionConfig()
        self._nodes: list[_Node] = []
        self._pending: list[FixObservation] = []  # measured after the last odometry pose
        self._last_fix_t: float | None = None
        self.accepted = 0
        self.rejected = 0  # by the gate, as too old / from the future, or unusable
        self.late = 0  # fixes measured before the newest odometry: rolled back and replayed
        self.reinitialisations = 0
        self.odom_rejected = 0  # odometry older than the newest
        self.last_rejection = ""
        self.output_snaps = 0  # corrections beyond output_snap_m/rad applied to the published pose at once
        self.map_accepted = 0  # map poses (add_map_pose) applied
        self.map_rejected = 0  # ... refused (gate, not placed yet, too old, unusable)
        self.last_map_rejection = ""
        self.frame_shifts = 0  # shift_frame calls applied
        self._pending_map: list[PoseObservation] = []  # map poses measured after the last odometry pose
        self._out: _Output | None = None
        self._own_frame: tuple[float, float, float] | None = None  # ``set_own_frame``

    # -- inputs ---------------------------------------------------------------------------------

    def predict(self, odom: OdomPose) -> None:
        """Advance with the odometry pose at ``odom.t``; fixes waiting for this time are applied first."""
        if not self._nodes:
            self._nodes.append(self._anchor(odom))
            return
        last = self._nodes[-1]
        if odom.t < last.t:
            self.odom_rejected += 1
            return
        self._advance(odom)
        self._publish()

    def _advance(self, odom: OdomPose) -> None:
        last = self._nodes[-1]
        while True:
            tf = self._pending[0].t_measured if self._pending else math.inf
            tm = self._pending_map[0].t if self._pending_map else math.inf
            if min(tf, tm) > odom.t:
                break
            if tf <= tm:  # a fix and a map pose at the same time: the fix first
                fix = self._pending.pop(0)
                node = _Node(tf, _interpolate(last.odom, odom, tf), fix)
            else:
                seen = self._pending_map.pop(0)
                node = _Node(tm, _interpolate(last.odom, odom, tm), None, seen=seen)
            self._step(self._nodes[-1], node)
            self._nodes.append(node)
        node = _Node(odom.t, odom, None)
        self._step(self._nodes[-1], node)
        self._nodes.append(node)
        self._prune()

    def add_fix(self, fix: FixObservation, now: float) -> FixVerdict:
        """A fix measured at ``fix.t_measured`` and received at ``now`` (both on the agent's clock)."""
        c = self.config
        if not all(math.isfinite(v) for v in (fix.t_measured, fix.x, fix.y, fix.sd_x, fix.sd_y)):
            return self._refuse("not finite")
        if fix.t_measured > now + c.future_tolerance_s:
            return self._refuse(f"measured {fix.t_measured - now:.2f} s in the future")
        self._last_fix_t = fix.t_measured if self._last_fix_t is None else max(self._last_fix_t, fix.t_measured)
        if not self._nodes:
            return self._refuse("no odometry yet")
        last = self._nodes[-1]
        if fix.t_measured > last.t:
            bisect.insort(self._pending, fix, key=lambda f: f.t_measured)
            return self._preview(fix, last)
        if fix.t_measured == last.t:  # measured with the newest odometry: applies now, nothing to replay
            node = _Node(last.t, last.odom, fix)
            self._step(last, node)
            self._nodes.append(node)
            assert node.verdict is not None
            return node.verdict
        self.late += 1
        if fix.t_measured < self._nodes[0].t:
            return self._refuse(f"{last.t - fix.t_measured:.2f} s old, older than the history")
        times = [n.t for n in self._nodes]
        i = bisect.bisect_right(times, fix.t_measured)
        node = _Node(fix.t_measured, _interpolate(self._nodes[i - 1].odom, self._nodes[i].odom, fix.t_measured), fix)
        self._nodes.insert(i, node)
        for j in range(i, len(self._nodes)):
            self._step(self._nodes[j - 1], self._nodes[j])
        assert node.verdict is not None
        return node.verdict

    def add_map_pose(self, obs: PoseObservation, now: float) -> FixVerdict:
        """The robot's pose at ``obs.t`` as its onboard map has it (see ``PoseObservation``), received
        at ``now``: a pose update (x, y, heading) gated at ``map_gate_chi2``, applied at its time
        through the history (late ones replayed, ones ahead of the odometry held), as fixes are.
        Refused until the heading is known: the map is in the site frame only from then on."""
        c = self.config
        if not all(math.isfinite(v) for v in (obs.t, obs.x, obs.y, obs.theta, *obs.cov)):
            return self._refuse_map("not finite")
        if len(obs.cov) != 9:
            return self._refuse_map("the covariance is not 3 x 3")
        cov = np.array(obs.cov).reshape(3, 3)
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-15) or not np.all(np.linalg.eigvalsh(cov) > 0):
            return self._refuse_map("the covariance is not symmetric positive definite")
        if obs.t > now + c.future_tolerance_s:
            return self._refuse_map(f"measured {obs.t - now:.2f} s in the future")
        if not self._nodes:
            return self._refuse_map("no odometry yet")
        last = self._nodes[-1]
        if obs.t > last.t:
            bisect.insort(self._pending_map, obs, key=lambda o: o.t)
            ok = last.disc.pos_init and last.disc.heading_init
            return FixVerdict(ok, "accepted (pending)" if ok else "not placed (pending)", math.nan)
        if obs.t < self._nodes[0].t:
            return self._refuse_map(f"{last.t - obs.t:.2f} s old, older than the history")
        times = [n.t for n in self._nodes]
        i = bisect.bisect_right(times, obs.t)
        if i == len(self._nodes):  # measured with the newest odometry: applies now, nothing to replay
            node = _Node(last.t, last.odom, None, seen=obs)
            self._step(last, node)
            self._nodes.append(node)
        else:
            node = _Node(obs.t, _interpolate(self._nodes[i - 1].odom, self._nodes[i].odom, obs.t), None, seen=obs)
            self._nodes.insert(i, node)
            for j in range(i, len(self._nodes)):
                self._step(self._nodes[j - 1], self._nodes[j])
        assert node.verdict is not None
        return node.verdict

    def set_own_frame(self, tf: tuple[float, float, float] | None) -> None:
        """Until UWB places the robot: ``tf`` (x, y, theta) takes an odometry pose to the robot's pose in
        its onboard map's own frame (the map keeper's ``Update.odom_frame``: where the map's last match
        put the robot, less the odometry there), so the pose published and driven on is the map's, and
        the pilot steers among the walls it plans on instead of the odometry's drifting copy of them
        (robot_localization's map->odom from a SLAM node). None: odometry alone again. Once the
        position is known the site frame rules and this is not used; the sd stay unknown either way
        (the robot is not placed)."""
        if tf is not None and not all(math.isfinite(float(v)) for v in tf):
            raise ValueError(f"set_own_frame needs a finite transform, got {tf!r}")
        self._own_frame = None if tf is None else (float(tf[0]), float(tf[1]), float(tf[2]))

    def shift_frame(self, tf: tuple[float, float, float]) -> None:
        """The map frame moved: ``tf`` (x, y, theta) takes a pose in the old frame to the new one (a
        loop closure's solve moved the map where the robot is by it). The filter's state and its
        whole history, the map poses held or kept for replay and the published pose move with it,
        rigidly and at once (the map moved at once too: the pose the pilot drives on must not lag the
        walls it plans among). UWB fixes stay as measured: the site frame is theirs, and they pull
        the pose back as far as the map left it. Nothing happens before the position is known."""
        dx, dy, phi = (float(v) for v in tf)
        if not all(math.isfinite(v) for v in (dx, dy, phi)):
            raise ValueError(f"shift_frame needs a finite transform, got {tf!r}")
        if not self.position_initialized:
            return
        c, s = math.cos(phi), math.sin(phi)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        big = _I5.copy()
        big[:3, :3] = rot

        def moved(o: PoseObservation) -> PoseObservation:
            cov = rot @ np.array(o.cov).reshape(3, 3) @ rot.T
            return replace(
                o,
                x=c * o.x - s * o.y + dx,
                y=s * o.x + c * o.y + dy,
                theta=wrap_angle(o.theta + phi),
                cov=tuple(float(v) for v in cov.ravel()),
            )

        for n in self._nodes:
            if n.disc.pos_init:
                x = n.x.copy()
                x[_X], x[_Y] = c * n.x[_X] - s * n.x[_Y] + dx, s * n.x[_X] + c * n.x[_Y] + dy
                x[_TH] = wrap_angle(float(n.x[_TH]) + phi)
                n.x, n.P = x, big @ n.P @ big.T
            if n.seen is not None:
                n.seen = moved(n.seen)
        self._pending_map = [moved(o) for o in self._pending_map]
        out = self._out
        if out is not None:
            self._out = replace(
                out, x=c * out.x - s * out.y + dx, y=s * out.x + c * out.y + dy, theta=wrap_angle(out.theta + phi)
            )
        self.frame_shifts += 1

    # -- outputs --------------------------------------------------------------------------------

    def odom_pose(self) -> Pose2D:
        """The continuous odometry-frame pose: never jumps."""
        if not self._nodes:
            return Pose2D(0.0, 0.0, 0.0)
        o = self._nodes[-1].odom
        return Pose2D(o.x, o.y, o.theta)

    def odom_at(self, t: float) -> Pose2D:
        """The odometry-frame pose at time ``t``: interpolated in the history, clamped to its ends."""
        nodes = self._nodes
        if not nodes:
            return Pose2D(0.0, 0.0, 0.0)
        if t >= nodes[-1].t:
            o = nodes[-1].odom
        elif t <= nodes[0].t:
            o = nodes[0].odom
        else:
            i = bisect.bisect_right([n.t for n in nodes], t)
            o = _interpolate(nodes[i - 1].odom, nodes[i].odom, t)
        return Pose2D(o.x, o.y, o.theta)

    def map_pose(self) -> MapPose:
        """The published map-frame pose at the newest odometry time: absorbs corrections without jumping.

        Between two odometry poses it moves as the odometry did (with the filter's scale and bias);
        the gap to the filter's estimate (``filter_pose``) is closed at ``output_rate_mps`` /
        ``output_rate_rad_s`` (at most ``output_max_step_m`` per output), so an ordinary correction
        (millimetres per fix) is applied in full at once while a large one (after an outage, a
        re-initialisation, the heading's initialisation) is spread over several outputs. A gap larger
        than ``output_snap_m`` / ``output_snap_rad`` is closed at once: the old pose was wrong by
        more than the robot's size. The sd include the correction still pending.
        """
        exact = self.filter_pose()
        out = self._out
        if out is None or not self._nodes or out.odom.t != self._nodes[-1].odom.t:
            return exact
        ex, ey = exact.x - out.x, exact.y - out.y
        eth = abs(wrap_angle(exact.theta - out.theta)) if out.heading_known else 0.0
        return MapPose(
            exact.t,
            out.x,
            out.y,
            out.theta,
            exact.v,
            exact.omega,
            math.hypot(exact.sd_x, ex),
            math.hypot(exact.sd_y, ey),
            math.hypot(exact.sd_theta, eth),
        )

    def pending_correction(self) -> tuple[float, float, float]:
        """(dx, dy, dtheta): the filter's estimate minus the published pose (what is still to be applied)."""
        exact, pub = self.filter_pose(), self.map_pose()
        if not math.isfinite(exact.sd_x):
            return 0.0, 0.0, 0.0
        return exact.x - pub.x, exact.y - pub.y, wrap_angle(exact.theta - pub.theta)

    def filter_pose(self) -> MapPose:
        """The filter's own estimate at the newest odometry time (exact; jumps when corrected)."""
        if not self._nodes:
            return MapPose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, math.inf, math.inf, math.inf)
        n = self._nodes[-1]
        o = n.odom
        if not n.disc.pos_init:
            x0, y0, th0 = self._unplaced(o)
            return MapPose(o.t, x0, y0, th0, o.v, o.omega, math.inf, math.inf, math.inf)
        x, P = n.x, n.P
        sd_th = math.sqrt(P[_TH, _TH]) if n.disc.heading_init else math.inf
        return MapPose(
            o.t,
            float(x[_X]),
            float(x[_Y]),
            wrap_angle(float(x[_TH])),
            float(x[_K]) * o.v,
            o.omega - float(x[_B]),
            math.sqrt(P[_X, _X]),
            math.sqrt(P[_Y, _Y]),
            sd_th,
        )

    def _unplaced(self, o: OdomPose) -> tuple[float, float, float]:
        """The pose of an unplaced robot: the odometry, in the onboard map's own frame where one is set."""
        if self._own_frame is None:
            return o.x, o.y, o.theta
        return compose(self._own_frame, (o.x, o.y, o.theta))

    def map_from_odom(self) -> tuple[float, float, float]:
        """(tx, ty, phi): map_pose = R(phi) * odom + t at the newest time (robot_localization's map->odom)."""
        if not self._nodes or not self._nodes[-1].disc.pos_init:
            return self._own_frame or (0.0, 0.0, 0.0)
        o, p = self._nodes[-1].odom, self.map_pose()
        phi = wrap_angle(p.theta - o.theta)
        c, s = math.cos(phi), math.sin(phi)
        return p.x - (c * o.x - s * o.y), p.y - (s * o.x + c * o.y), phi

    def uwb_stale(self, now: float) -> bool:
        return self._last_fix_t is None or now - self._last_fix_t > self.config.stale_timeout_s

    @property
    def position_initialized(self) -> bool:
        return bool(self._nodes) and self._nodes[-1].disc.pos_init

    @property
    def heading_initialized(self) -> bool:
        return bool(self._nodes) and self._nodes[-1].disc.heading_init

    @property
    def localization_score(self) -> float:
        """0..1 (VDA 5050 localizationScore): 1 at sub-centimetre position sd, 0 at 0.5 m or unknown heading."""
        if not self.position_initialized:
            return 0.0
        p = self.map_pose()
        if not math.isfinite(p.sd_theta):
            return 0.0
        sd = math.sqrt((p.sd_x**2 + p.sd_y**2) / 2)
        return max(0.0, min(1.0, 1.0 - sd / 0.5))

    @property
    def calibration(self) -> tuple[float, float]:
        """The estimated odometry distance scale and heading-rate bias (rad/s)."""
        if not self._nodes:
            return 1.0, 0.0
        x = self._nodes[-1].x
        return float(x[_K]), float(x[_B])

    # -- the published pose ---------------------------------------------------------------------

    def _publish(self) -> None:
        """Move the published pose to the newest odometry time: odometry motion, then a bounded correction."""
        c = self.config
        n = self._nodes[-1]
        out, o = self._out, n.odom
        if not n.disc.pos_init:
            self._out = None
            return
        e = self.filter_pose()
        heading = n.disc.heading_init
        if out is None:  # the first pose: nothing was published, so nothing can jump
            self._out = _Output(e.x, e.y, e.theta, o, heading)
            return
        dt = max(0.0, o.t - out.odom.t)
        fwd, lat, dth, _ = _odom_increment(out.odom, o)
        k, bias = float(n.x[_K]), float(n.x[_B])
        if heading:
            # Heading just found: the old one meant nothing, take the filter's (the position still glides).
            th0 = out.theta if out.heading_known else wrap_angle(e.theta - dth + bias * dt)
            dth_c = dth - bias * dt
            thm = th0 + dth_c / 2
            px = out.x + k * (fwd * math.cos(thm) - lat * math.sin(thm))
            py = out.y + k * (fwd * math.sin(thm) + lat * math.cos(thm))
            pth = wrap_angle(th0 + dth_c)
            step = min(c.output_rate_mps * dt, c.output_max_step_m)
        else:
            # Direction of travel unknown (the output is not a pose yet: localizationScore 0): it may
            # move as far as the robot drove, plus the correction rate.
            px, py, pth = out.x, out.y, e.theta
            step = min(c.output_rate_mps * dt, c.output_max_step_m) + k * math.hypot(fwd, lat)
        ex, ey, eth = e.x - px, e.y - py, wrap_angle(e.theta - pth)
        gap = math.hypot(ex, ey)
        if gap > c.output_snap_m or abs(eth) > c.output_snap_rad:
            self.output_snaps += 1
            self._out = _Output(e.x, e.y, e.theta, o, heading)
            return
        if gap > step:
            px, py = px + ex * step / gap, py + ey * step / gap
        else:
            px, py = e.x, e.y
        turn = c.output_rate_rad_s * dt
        pth = wrap_angle(pth + max(-turn, min(turn, eth)))
        self._out = _Output(px, py, pth, o, heading)

    # -- the filter -----------------------------------------------------------------------------

    def _anchor(self, odom: OdomPose) -> _Node:
        c = self.config
        n = _Node(odom.t, odom, None)
        n.x = np.array([odom.x, odom.y, odom.theta, 1.0, 0.0])
        n.P = np.diag([0.0, 0.0, 0.0, c.init_scale_sd**2 * c.estimate_scale, c.init_bias_sd**2 * c.estimate_bias])
        return n

    def _refuse(self, reason: str) -> FixVerdict:
        self.rejected += 1
        self.last_rejection = reason
        return FixVerdict(False, reason, math.nan)

    def _refuse_map(self, reason: str) -> FixVerdict:
        self.map_rejected += 1
        self.last_map_rejection = reason
        return FixVerdict(False, reason, math.nan)

    def _prune(self) -> None:
        nodes = self._nodes
        if len(nodes) < 8 or nodes[1].t >= nodes[-1].t - self.config.history_s - 0.5:
            return  # prune in batches: only when the history is half a second over
        cutoff = nodes[-1].t - self.config.history_s
        i = bisect.bisect_left([n.t for n in nodes], cutoff)
        del nodes[: max(0, i - 1)]  # keep one node at or before the cut-off as the anchor

    def _preview(self, fix: FixObservation, last: _Node) -> FixVerdict:
        """The verdict a fix ahead of the odometry will most likely get (it is applied when odometry passes it)."""
        if not last.disc.pos_init:
            return FixVerdict(False, "initialising", math.nan)
        x, P = self._predict(last.x, last.P, last.odom, _extrapolate(last.odom, fix.t_measured), last.disc.heading_init)
        nis = self._gate_nis(x, P, fix)
        ok = not self.config.gate or nis <= self.config.gate_chi2
        return FixVerdict(ok, "accepted (pending)" if ok else "gate (pending)", nis)

    def _step(self, prev: _Node, node: _Node) -> None:
        """Recompute ``node`` from ``prev``: predict with the odometry between them, then the fix if any."""
        d = prev.disc
        if d.pos_init:
            x, P = self._predict(prev.x, prev.P, prev.odom, node.odom, d.heading_init)
        else:
            x, P = prev.x.copy(), prev.P.copy()
        if node.seen is not None:
            verdict, node.x, node.P = self._update_map(x, P, d, node.seen)
            node.disc = d
            node.verdict = verdict
            if not node.counted:
                node.counted = True
                if verdict.accepted:
                    self.map_accepted += 1
                else:
                    self.map_rejected += 1
                    self.last_map_rejection = verdict.reason
            return
        if node.fix is None:
            node.x, node.P, node.disc = x, P, d
            return
        verdict, node.x, node.P, node.disc = self._update(x, P, d, node.fix, node.odom)
        node.verdict = verdict
        if not node.counted:
            node.counted = True
            if verdict.accepted:
                self.accepted += 1
                if verdict.reason == "reinitialised":
                    self.reinitialisations += 1
            else:
                self.rejected += 1
                self.last_rejection = verdict.reason

    def _predict(self, x0: Vec, P0: Vec, a: OdomPose, b: OdomPose, heading_known: bool) -> tuple[Vec, Vec]:
        c = self.config
        fwd, lat, dth, dt = _odom_increment(a, b)
        k, bias = float(x0[_K]), float(x0[_B])
        dth_c = dth - bias * dt
        thm = float(x0[_TH]) + dth_c / 2
        cs, sn = math.cos(thm), math.sin(thm)
        ux, uy = fwd * cs - lat * sn, fwd * sn + lat * cs  # odometry displacement in the map frame
        dx, dy = k * ux, k * uy
        x = x0.copy()
        x[_X] += dx
        x[_Y] += dy
        x[_TH] = wrap_angle(float(x0[_TH]) + dth_c)
        F = _I5.copy()
        if heading_known:
            F[_X, _TH], F[_Y, _TH] = -dy, dx
            F[_X, _B], F[_Y, _B] = dy * dt / 2, -dx * dt / 2
        F[_X, _K], F[_Y, _K] = ux, uy
        F[_TH, _B] = -dt
        dist = math.hypot(fwd, lat)
        sf, sl = c.dist_noise * dist, c.lateral_noise * dist
        # Body-frame noise rotated into the map frame.
        q_ff, q_ll = sf * sf, sl * sl
        Q = np.zeros((5, 5))
        Q[_X, _X] = q_ff * cs * cs + q_ll * sn * sn
        Q[_Y, _Y] = q_ff * sn * sn + q_ll * cs * cs
        Q[_X, _Y] = Q[_Y, _X] = (q_ff - q_ll) * cs * sn
        pos_q = c.pos_rw**2 * dt
        if not heading_known:
            pos_q += dist * dist  # the direction of travel is unknown: the whole step is uncertain
        Q[_X, _X] += pos_q
        Q[_Y, _Y] += pos_q
        Q[_TH, _TH] = (c.turn_noise * dth) ** 2 + c.heading_rw**2 * dt
        if c.estimate_scale:
            Q[_K, _K] = c.scale_rw**2 * dist
        if c.estimate_bias:
            Q[_B, _B] = c.bias_rw**2 * dt
        P = F @ P0 @ F.T + Q
        if not heading_known:
            P[_TH, :] = P[:, _TH] = 0.0
            P[_TH, _TH] = math.pi**2
        return x, P

    def _r(self, fix: FixObservation) -> tuple[float, float]:
        m = self.config.min_fix_sd_m
        return max(fix.sd_x, m) ** 2, max(fix.sd_y, m) ** 2

    def _gate_nis(self, x: Vec, P: Vec, fix: FixObservation) -> float:
        rx, ry = self._r(fix)
        a, b, d = float(P[_X, _X]), float(P[_X, _Y]), float(P[_Y, _Y])
        # Cap the position covariance's largest eigenvalue: a grown covariance must not open the gate.
        lam = (a + d) / 2 + math.sqrt(((a - d) / 2) ** 2 + b * b)
        cap = self.config.gate_max_sd_m**2
        if lam > cap:
            s = cap / lam
            a, b, d = a * s, b * s, d * s
        a, d = a + rx, d + ry
        det = a * d - b * b
        nx, ny = fix.x - float(x[_X]), fix.y - float(x[_Y])
        return (d * nx * nx - 2 * b * nx * ny + a * ny * ny) / det

    def _update(
        self, x: Vec, P: Vec, d: _Disc, fix: FixObservation, odom: OdomPose
    ) -> tuple[FixVerdict, Vec, Vec, _Disc]:
        c = self.config
        rx, ry = self._r(fix)
        entry = _Buf(fix.t_measured, fix.x, fix.y, math.sqrt((rx + ry) / 2), odom.x, odom.y, odom.theta, False)
        buffer = tuple(b for b in d.buffer if b.t >= fix.t_measured - c.align_window_s)[-(c.align_max_fixes - 1) :]
        buffer = (*buffer, entry)
        if not d.pos_init:
            rotate = _path(buffer) >= c.heading_init_path_m
            fit = self._align(buffer, rotate, 0.0, c.init_fixes)
            if fit is None:
                return FixVerdict(False, "initialising", math.nan), x, P, replace(d, buffer=buffer)
            x, P = self._from_fit(x, P, fit, odom, heading_known=False)
            d = _Disc(pos_init=True, heading_init=fit.rotated, streak=0, buffer=_accepted(buffer))
            return FixVerdict(True, "initialised", 0.0), x, P, d
        nis = self._gate_nis(x, P, fix)
        if not c.gate or nis <= c.gate_chi2:
            R = np.array([[rx, 0.0], [0.0, ry]])
            S = P[:2, :2] + R
            K = P[:, :2] @ np.linalg.inv(S)
            nu = np.array([fix.x - x[_X], fix.y - x[_Y]])
            x = x + K @ nu
            x[_TH] = wrap_angle(float(x[_TH]))
            IKH = _I5 - K @ _H
            P = IKH @ P @ IKH.T + K @ R @ K.T
            buffer = (*buffer[:-1], replace(entry, accepted=True))
            d = _Disc(True, d.heading_init, 0, buffer)
            if not d.heading_init:
                ok = tuple(b for b in buffer if b.accepted)
                if _path(ok) >= c.heading_init_path_m:
                    fit = self._align(ok, True, 0.0, c.init_fixes)
                    if fit is not None and fit.rotated:
                        x, P = self._from_fit(x, P, fit, odom, heading_known=False)
                        d = replace(d, heading_init=True)
            return FixVerdict(True, "accepted", nis), x, P, d
        streak = d.streak + 1
        d = _Disc(True, d.heading_init, streak, buffer)
        if streak >= c.reinit_after:
            run = tuple(b for b in buffer if not b.accepted)[-streak:]
            rotate = _path(run) >= c.reinit_rotate_path_m
            phi0 = float(x[_TH]) - odom.theta
            fit = self._align(run, rotate, phi0, max(c.init_fixes, (c.reinit_after * 3) // 4))
            if fit is not None:
                x, P = self._from_fit(x, P, fit, odom, heading_known=d.heading_init)
                d = _Disc(True, d.heading_init or fit.rotated, 0, _accepted(buffer))
                return FixVerdict(True, "reinitialised", nis), x, P, d
        return FixVerdict(False, "gate", nis), x, P, d

    def _update_map(self, x: Vec, P: Vec, d: _Disc, obs: PoseObservation) -> tuple[FixVerdict, Vec, Vec]:
        """The pose update of a map pose: x, y and heading at once, gated on its NIS (3 dof)."""
        c = self.config
        if not (d.pos_init and d.heading_init):
            return FixVerdict(False, "not placed", math.nan), x, P
        R = np.array(obs.cov).reshape(3, 3)
        # Floors, added where the observation claims less (a PSD term each: R stays positive definite).
        R[0, 0] += max(0.0, c.min_map_sd_m**2 - R[0, 0])
        R[1, 1] += max(0.0, c.min_map_sd_m**2 - R[1, 1])
        R[2, 2] += max(0.0, c.min_map_sd_rad**2 - R[2, 2])
        nu = np.array([obs.x - x[_X], obs.y - x[_Y], wrap_angle(obs.theta - float(x[_TH]))])
        S = _H3 @ P @ _H3.T + R
        S_inv = np.linalg.inv(S)
        nis = float(nu @ S_inv @ nu)
        if c.gate and nis > c.map_gate_chi2:
            return FixVerdict(False, "gate", nis), x, P
        K = P @ _H3.T @ S_inv
        x = x + K @ nu
        x[_TH] = wrap_angle(float(x[_TH]))
        IKH = _I5 - K @ _H3
        P = IKH @ P @ IKH.T + K @ R @ K.T
        return FixVerdict(True, "accepted", nis), x, P

    def _from_fit(self, x0: Vec, P0: Vec, fit: _Fit, odom: OdomPose, heading_known: bool) -> tuple[Vec, Vec]:
        """The state at ``odom``'s time given a map-from-odometry fit; calibration states are kept."""
        c, s = math.cos(fit.phi), math.sin(fit.phi)
        x = x0.copy()
        x[_X] = c * odom.x - s * odom.y + fit.tx
        x[_Y] = s * odom.x + c * odom.y + fit.ty
        x[_TH] = wrap_angle(odom.theta + fit.phi)
        P = np.zeros((5, 5))
        P[_K, _K], P[_B, _B] = P0[_K, _K], P0[_B, _B]
        P[_X, _X] = P[_Y, _Y] = fit.sd_pos**2
        if fit.rotated:
            P[_TH, _TH] = fit.sd_phi**2
        elif heading_known:
            P[_TH, _TH] = max(float(P0[_TH, _TH]), 0.05**2)
        else:
            P[_TH, _TH] = math.pi**2
        return x, P

    def _align(self, buf: tuple[_Buf, ...], rotate: bool, phi0: float, need: int) -> _Fit | None:
        """Robust fit of map = R(phi) odom + t to buffered fixes; None unless ``need`` of them (and 60 %) agree."""
        n = len(buf)
        if n < need:
            return None
        thr = math.sqrt(self.config.gate_chi2)
        phi = phi0
        if rotate:
            pairs = []
            half = n // 2
            for i in range(n - half):
                a, b = buf[i], buf[i + half]
                if math.hypot(b.ox - a.ox, b.oy - a.oy) >= 0.3:
                    pairs.append(
                        wrap_angle(math.atan2(b.zy - a.zy, b.zx - a.zx) - math.atan2(b.oy - a.oy, b.ox - a.ox))
                    )
            if len(pairs) >= 3:
                phi = _circular_mode(pairs, 0.3)
            else:
                rotate = False
        inl: list[_Buf] = list(buf)
        tx = ty = 0.0
        for it in range(3):
            cs, sn = math.cos(phi), math.sin(phi)
            ts = [(b.zx - (cs * b.ox - sn * b.oy), b.zy - (sn * b.ox + cs * b.oy)) for b in (buf if it == 0 else inl)]
            if it == 0:
                tx = float(np.median([t[0] for t in ts]))
                ty = float(np.median([t[1] for t in ts]))
            else:
                w = [1.0 / b.sd**2 for b in inl]
                tx = sum(wi * t[0] for wi, t in zip(w, ts, strict=True)) / sum(w)
                ty = sum(wi * t[1] for wi, t in zip(w, ts, strict=True)) / sum(w)
            inl = [
                b
                for b in buf
                if math.hypot(b.zx - (cs * b.ox - sn * b.oy) - tx, b.zy - (sn * b.ox + cs * b.oy) - ty) <= thr * b.sd
            ]
            if len(inl) < need:
                return None
            if rotate:
                # Weighted 2D Procrustes (Umeyama) on the inliers.
                w = [1.0 / b.sd**2 for b in inl]
                sw = sum(w)
                ax = sum(wi * b.ox for wi, b in zip(w, inl, strict=True)) / sw
                ay = sum(wi * b.oy for wi, b in zip(w, inl, strict=True)) / sw
                bx = sum(wi * b.zx for wi, b in zip(w, inl, strict=True)) / sw
                by = sum(wi * b.zy for wi, b in zip(w, inl, strict=True)) / sw
                sxy = sum(
                    wi * ((b.ox - ax) * (b.zy - by) - (b.oy - ay) * (b.zx - bx)) for wi, b in zip(w, inl, strict=True)
                )
                sxx = sum(
                    wi * ((b.ox - ax) * (b.zx - bx) + (b.oy - ay) * (b.zy - by)) for wi, b in zip(w, inl, strict=True)
                )
                phi = math.atan2(sxy, sxx)
        if len(inl) < max(need, 0.6 * n):
            return None
        sd2 = sum(b.sd**2 for b in inl) / len(inl)
        sd_pos = math.sqrt(sd2 / len(inl) + 0.02**2)  # + odometry drift across the window
        spread = sum(
            (b.ox - sum(i.ox for i in inl) / len(inl)) ** 2 + (b.oy - sum(i.oy for i in inl) / len(inl)) ** 2
            for b in inl
        )
        sd_phi = math.sqrt(sd2 / max(spread, 1e-6)) if rotate else math.pi
        return _Fit(phi, tx, ty, len(inl), sd_pos, min(sd_phi, math.pi), rotate)


def _path(buf: tuple[_Buf, ...]) -> float:
    """How far apart the odometry poses of the buffered fixes are (largest extent)."""
    if len(buf) < 2:
        return 0.0
    xs, ys = [b.ox for b in buf], [b.oy for b in buf]
    return math.hypot(max(xs) - min(xs), max(ys) - min(ys))


def _accepted(buf: tuple[_Buf, ...]) -> tuple[_Buf, ...]:
    return tuple(replace(b, accepted=True) for b in buf)


class SeedReset:
    """The rescue-robot seed's localisation, for benchmarks only: every fix resets the odometry offset.

    The pose is odometry moved so that at each fix's arrival the position equals the fix ("the
    positioning system prevails"): no gate, no latency handling, every bad fix a jump. The heading
    offset between odometry and map is given (the seed took it from its start pose).
    """

    def __init__(self, heading_offset: float = 0.0) -> None:
        self.phi = heading_offset
        self.tx = self.ty = 0.0
        self.odom = OdomPose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        self.initialised = False

    def predict(self, odom: OdomPose) -> None:
        self.odom = odom

    def add_fix(self, fix: FixObservation, now: float) -> FixVerdict:
        c, s = math.cos(self.phi), math.sin(self.phi)
        o = self.odom
        self.tx = fix.x - (c * o.x - s * o.y)
        self.ty = fix.y - (s * o.x + c * o.y)
        self.initialised = True
        return FixVerdict(True, "accepted", math.nan)

    def map_pose(self) -> MapPose:
        c, s = math.cos(self.phi), math.sin(self.phi)
        o = self.odom
        sd = 0.0 if self.initialised else math.inf
        return MapPose(
            o.t,
            c * o.x - s * o.y + self.tx,
            s * o.x + c * o.y + self.ty,
            wrap_angle(o.theta + self.phi),
            o.v,
            o.omega,
            sd,
            sd,
            sd,
        )
