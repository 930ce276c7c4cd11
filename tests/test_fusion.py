"""Fusion: convergence, the gate (also after a long outage), late-fix replay, the two outputs, staleness;
the onboard map's pose as a measurement and the map frame's shift (loop closure on board)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import pytest

from fleetlink.agent.fusion import Fusion, FusionConfig, PoseObservation, SeedReset
from fleetlink.agent.odometry import Odometry, OdomPose
from fleetlink.agent.uwb_input import FixObservation

DT = 0.05  # odometry at 20 Hz
FIX_PERIOD = 0.1  # fixes at 10 Hz


@dataclass
class Sim:
    """A robot driving a wavy loop; wheels with a scale error, a gyro with a bias; noisy fixes from truth."""

    scale: float = 1.015  # encoder distance / true distance
    gyro_bias: float = 0.002  # rad/s
    fix_sd: float = 0.1
    seed: int = 0
    fix_phase: float = 0.013  # fixes are measured between odometry samples
    x: float = 2.0
    y: float = 3.0
    th: float = 0.7
    t: float = 0.0
    left: float = 0.0
    right: float = 0.0
    yaw: float = 0.0
    next_fix: float = 0.0
    odo: Odometry = field(default_factory=Odometry)
    rng: np.random.Generator = field(init=False)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        self.next_fix = self.fix_phase

    def truth_at(self, t: float) -> tuple[float, float]:
        """Truth at a time within the current step (linear between the step's ends)."""
        return self._prev[0] + (self.x - self._prev[0]) * (t - self._prev[2]) / DT, self._prev[1] + (
            self.y - self._prev[1]
        ) * (t - self._prev[2]) / DT

    def step(self) -> tuple[OdomPose, list[FixObservation]]:
        self._prev = (self.x, self.y, self.t)
        v = 0.5
        w = 0.4 * math.sin(self.t / 4.0)
        self.t += DT
        self.x += v * DT * math.cos(self.th + w * DT / 2)
        self.y += v * DT * math.sin(self.th + w * DT / 2)
        self.th += w * DT
        half = w * 0.11
        self.left += (v - half) * DT * self.scale
        self.right += (v + half) * DT * self.scale
        self.yaw += (w + self.gyro_bias) * DT
        pose = self.odo.update(self.t, self.left, self.right, self.yaw)
        fixes = []
        while self.next_fix <= self.t:
            tx, ty = self.truth_at(self.next_fix)
            zx, zy = tx + self.rng.normal(0, self.fix_sd), ty + self.rng.normal(0, self.fix_sd)
            fixes.append(FixObservation(self.next_fix, zx, zy, self.fix_sd, self.fix_sd, 90, "test"))
            self.next_fix += FIX_PERIOD
        return pose, fixes

    def run(self, fusion: Fusion, seconds: float, fixes: bool = True) -> Iterator[OdomPose]:
        for _ in range(round(seconds / DT)):
            pose, fx = self.step()
            if fixes:
                for f in fx:
                    fusion.add_fix(f, self.t)
            fusion.predict(pose)
            yield pose

    def error(self, fusion: Fusion) -> float:
        p = fusion.map_pose()
        return math.hypot(p.x - self.x, p.y - self.y)


def converged(seconds: float = 40.0, **kw: float) -> tuple[Sim, Fusion]:
    sim, fusion = Sim(**kw), Fusion()  # type: ignore[arg-type]
    for _ in sim.run(fusion, seconds):
        pass
    return sim, fusion


def test_converges_and_beats_the_fixes() -> None:
    sim, fusion = Sim(), Fusion()
    assert not fusion.position_initialized
    assert fusion.localization_score == 0.0
    errors = []
    for pose in sim.run(fusion, 60.0):
        if pose.t > 20.0:
            errors.append(sim.error(fusion))
    rmse = math.sqrt(sum(e * e for e in errors) / len(errors))
    assert fusion.position_initialized and fusion.heading_initialized
    assert rmse < 0.05  # the fixes alone are 0.14 m RMSE
    p = fusion.map_pose()
    assert abs(math.remainder(p.theta - sim.th, math.tau)) < 0.05
    assert p.sd_x < 0.1 and p.sd_theta < 0.1
    assert fusion.localization_score > 0.5
    scale, bias = fusion.calibration
    assert scale == pytest.approx(1 / 1.015, abs=0.006)  # true distance per odometry metre
    assert bias == pytest.approx(0.002, abs=0.001)
    assert fusion.rejected < 0.01 * fusion.accepted + 5


def test_gate_rejects_a_3_m_outlier() -> None:
    sim, fusion = converged()
    before = fusion.map_pose()
    v = fusion.add_fix(FixObservation(sim.t, sim.x + 3.0, sim.y, 0.1, 0.1, 90, "test"), sim.t)
    assert not v.accepted and v.reason == "gate"
    assert v.nis > fusion.config.gate_chi2
    assert fusion.map_pose() == before
    # The same fix with the gate off pulls the pose (so the gate is what refused it).
    sim2, open_gate = Sim(), Fusion(FusionConfig(gate=False))
    for _ in sim2.run(open_gate, 40.0):
        pass
    x0 = open_gate.filter_pose().x
    assert open_gate.add_fix(FixObservation(sim2.t, sim2.x + 3.0, sim2.y, 0.1, 0.1, 90, "test"), sim2.t).accepted
    assert open_gate.filter_pose().x > x0 + 0.02  # the filter trusts its odometry: a small but real pull


# A filter that trusts its odometry little (large position random walk) grows its covariance fast:
# after 60 s without fixes its position sd is over a metre, enough for an uncapped gate to take a 3 m
# outlier. scale 1.3: the odometry also drifts beyond the capped gate, so only a re-initialisation
# from a run of agreeing fixes brings the pose back.
LOOSE = {"pos_rw": 0.15}


@pytest.mark.parametrize("scale", [1.015, 1.3])
def test_gate_works_after_a_60_s_outage(scale: float) -> None:
    sim, fusion = Sim(scale=scale), Fusion(FusionConfig(**LOOSE))
    uncapped = Fusion(FusionConfig(gate_max_sd_m=1e6, **LOOSE))
    for pose, fixes in (sim.step() for _ in range(round(100.0 / DT))):
        if sim.t < 40.0:
            for f in fixes:
                fusion.add_fix(f, sim.t)
                uncapped.add_fix(f, sim.t)
        fusion.predict(pose)
        uncapped.predict(pose)
    assert fusion.uwb_stale(sim.t)
    drift = sim.error(fusion)
    assert fusion.map_pose().sd_x > 1.0  # the covariance has grown
    # A 3 m outlier right after the outage: refused, where an uncapped gate lets it in.
    # (3 m from where the filter believes it is, away from the truth: an outlier to truth and estimate)
    est = fusion.map_pose()
    ux, uy = (est.x - sim.x) / drift, (est.y - sim.y) / drift
    outlier = FixObservation(sim.t, est.x + 3.0 * ux, est.y + 3.0 * uy, 0.1, 0.1, 90, "test")
    v = fusion.add_fix(outlier, sim.t)
    assert not v.accepted, (drift, v)
    assert uncapped.add_fix(outlier, sim.t).accepted
    # Good fixes are taken again within a second and a half, and the error comes back down.
    accepted_at = None
    t0 = sim.t
    for _ in range(60):
        pose, fixes = sim.step()
        for f in fixes:
            if fusion.add_fix(f, sim.t).accepted and accepted_at is None:
                accepted_at = sim.t
        fusion.predict(pose)
    assert accepted_at is not None and accepted_at - t0 <= 1.5
    exact = fusion.filter_pose()
    assert math.hypot(exact.x - sim.x, exact.y - sim.y) < 0.15  # the filter is back
    if scale > 1.05:
        # Off by more than output_snap_m: the published pose was wrong by metres, it is corrected at once.
        assert drift > 2.0 and fusion.reinitialisations >= 1, drift
        assert fusion.output_snaps >= 1
    else:
        # Off by 0.5-1 m: the published pose glides there at output_rate_mps (a few seconds).
        assert fusion.output_snaps == 0
    for _ in sim.run(fusion, drift / fusion.config.output_rate_mps):
        pass
    assert sim.error(fusion) < 0.15
    assert math.hypot(*fusion.pending_correction()[:2]) < 0.05  # this loose filter moves by cm per fix
    # ... and the gate is tight again: the next outlier is refused.
    assert not fusion.add_fix(FixObservation(sim.t, sim.x + 3.0, sim.y, 0.1, 0.1, 90, "test"), sim.t).accepted


def test_late_fixes_replay_to_the_in_order_answer() -> None:
    on_time, late = Fusion(), Fusion()
    sim = Sim(seed=3)
    held: list[tuple[float, FixObservation]] = []
    for _ in range(round(30.0 / DT)):
        pose, fixes = sim.step()
        for f in fixes:
            on_time.add_fix(f, sim.t)
            held.append((f.t_measured + 0.2 + 0.1 * (len(held) % 2), f))  # 200-300 ms late, out of order
        on_time.predict(pose)
        late.predict(pose)
        due = sorted((h for h in held if h[0] <= sim.t), key=lambda h: -h[1].t_measured)
        for h in due:
            late.add_fix(h[1], sim.t)
            held.remove(h)
    for _, f in held:  # the last ones arrive after the run
        late.add_fix(f, sim.t + 0.3)
    a, b = on_time.filter_pose(), late.filter_pose()
    assert late.late > 100
    assert (b.x, b.y, b.theta) == pytest.approx((a.x, a.y, a.theta), abs=1e-9)
    assert (b.sd_x, b.sd_theta) == pytest.approx((a.sd_x, a.sd_theta), rel=1e-6)
    # The published poses saw the corrections at different moments, so they only agree closely.
    pa, pb = on_time.map_pose(), late.map_pose()
    assert math.hypot(pa.x - pb.x, pa.y - pb.y) < 0.01


def test_fix_older_than_the_history_or_from_the_future_is_refused() -> None:
    sim, fusion = converged(10.0)
    old = fusion.add_fix(FixObservation(sim.t - 5.0, sim.x, sim.y, 0.1, 0.1, 90, "test"), sim.t)
    assert not old.accepted and "older than the history" in old.reason
    future = fusion.add_fix(FixObservation(sim.t + 10.0, sim.x, sim.y, 0.1, 0.1, 90, "test"), sim.t)
    assert not future.accepted and "future" in future.reason
    nan = fusion.add_fix(FixObservation(sim.t, math.nan, sim.y, 0.1, 0.1, 90, "test"), sim.t)
    assert not nan.accepted and nan.reason == "not finite"
    assert fusion.rejected >= 3


def _seen(sim: Sim, dx: float = 0.0, dth: float = 0.0, t: float | None = None) -> PoseObservation:
    """The map's pose of the robot now (or at ``t``, from the truth then), off the truth by dx, dth."""
    return PoseObservation.of(sim.t if t is None else t, sim.x + dx, sim.y, sim.th + dth, 0.03, math.radians(1.0))


def test_a_map_pose_is_a_pose_measurement_gated_on_its_own() -> None:
    sim, fusion = converged(20.0)
    before = fusion.filter_pose()
    # The map says the robot is 5 cm east of where the filter has it, and turned 1 degree more.
    seen = PoseObservation.of(sim.t, before.x + 0.05, before.y, before.theta + math.radians(1.0), 0.03, math.radians(1))
    v = fusion.add_map_pose(seen, sim.t)
    assert v.accepted and v.reason == "accepted" and v.nis < fusion.config.map_gate_chi2
    after = fusion.filter_pose()
    # Pulled towards it in position and in heading (a full pose update), not past it.
    assert before.x + 0.005 < after.x < seen.x
    assert 0.001 < math.remainder(after.theta - before.theta, math.tau) < math.radians(1.0)
    assert after.sd_x < before.sd_x and after.sd_theta < before.sd_theta
    assert fusion.map_accepted == 1 and fusion.accepted > 0  # UWB's counters are its own
    # One 1 m off is refused by the gate, and changes nothing.
    far = fusion.add_map_pose(_seen(sim, dx=1.0), sim.t)
    assert not far.accepted and far.reason == "gate" and far.nis > fusion.config.map_gate_chi2
    assert fusion.filter_pose() == after and fusion.map_rejected == 1
    bad = fusion.add_map_pose(PoseObservation.of(sim.t, math.nan, 0.0, 0.0, 0.03, 0.01), sim.t)
    assert not bad.accepted and bad.reason == "not finite"
    flat = fusion.add_map_pose(PoseObservation(sim.t, sim.x, sim.y, sim.th, (1.0, 0, 0, 0, 0.0, 0, 0, 0, 1.0)), sim.t)
    assert not flat.accepted and "positive definite" in flat.reason
    # Along a direction the map pins down badly (a corridor seen end-on) the map's pose moves nothing.
    along = np.diag([100.0, 0.03**2, 0.02**2])
    p0 = fusion.filter_pose()
    obs = PoseObservation(sim.t, p0.x + 0.3, p0.y, p0.theta, tuple(along.ravel()))
    assert fusion.add_map_pose(obs, sim.t).accepted
    assert abs(fusion.filter_pose().x - p0.x) < 0.001


def test_a_map_pose_before_the_heading_is_known_is_refused() -> None:
    sim, fusion = Sim(), Fusion()
    for _ in sim.run(fusion, 0.8):  # placed, but the heading not known yet (the map is not in the site frame)
        pass
    assert fusion.position_initialized and not fusion.heading_initialized
    v = fusion.add_map_pose(_seen(sim), sim.t)
    assert not v.accepted and v.reason == "not placed"
    assert fusion.map_rejected == 1 and fusion.map_accepted == 0


def test_late_map_poses_replay_to_the_in_order_answer() -> None:
    on_time, late = Fusion(), Fusion()
    sim = Sim(seed=5)
    held: list[PoseObservation] = []
    for i in range(round(30.0 / DT)):
        pose, fixes = sim.step()
        for f in fixes:
            on_time.add_fix(f, sim.t)
            late.add_fix(f, sim.t)
        on_time.predict(pose)
        late.predict(pose)
        if sim.t > 10.0 and i % 4 == 0:  # a mapped turn, its pose ~0.3 s late (a turn, and the mapping)
            obs = _seen(sim, dx=0.02)
            on_time.add_map_pose(obs, sim.t)
            held.append(obs)
        while held and held[0].t <= sim.t - 0.3:
            late.add_map_pose(held.pop(0), sim.t)
    for obs in held:
        late.add_map_pose(obs, sim.t + 0.3)
    a, b = on_time.filter_pose(), late.filter_pose()
    assert on_time.map_accepted > 50 and late.map_accepted == on_time.map_accepted
    assert (b.x, b.y, b.theta) == pytest.approx((a.x, a.y, a.theta), abs=1e-9)


def test_the_frame_shift_moves_the_filter_and_the_published_pose_at_once() -> None:
    sim, fusion = converged(20.0)
    # A loop closure's solve moved the map 0.2 m east, 0.1 m north and turned it 3 degrees where
    # the robot is: the pose the pilot drives on moves with it, not at the output's glide rate.
    before, pub = fusion.filter_pose(), fusion.map_pose()
    c, s = math.cos(math.radians(3.0)), math.sin(math.radians(3.0))
    tf = (pub.x + 0.2 - (c * pub.x - s * pub.y), pub.y + 0.1 - (s * pub.x + c * pub.y), math.radians(3.0))
    fusion.shift_frame(tf)
    after, pub2 = fusion.filter_pose(), fusion.map_pose()
    for b, a in ((before, after), (pub, pub2)):
        assert a.x == pytest.approx(c * b.x - s * b.y + tf[0], abs=1e-9)
        assert a.y == pytest.approx(s * b.x + c * b.y + tf[1], abs=1e-9)
        assert math.remainder(a.theta - b.theta - tf[2], math.tau) == pytest.approx(0.0, abs=1e-9)
    assert after.sd_x == pytest.approx(math.hypot(before.sd_x * c, before.sd_y * s), rel=0.3)
    assert fusion.frame_shifts == 1 and fusion.output_snaps == 0
    # The next odometry carries on from there.
    pose, _ = sim.step()
    fusion.predict(pose)
    assert math.hypot(fusion.map_pose().x - after.x, fusion.map_pose().y - after.y) < 0.05
    # UWB keeps the site frame: with fixes the pose comes back to the truth over seconds, not at once.
    moved = math.dist((pub.x, pub.y), (pub2.x, pub2.y))
    errors = []
    for _ in sim.run(fusion, 10.0):
        errors.append(sim.error(fusion))
    assert moved > 0.15 and errors[0] > 0.6 * moved and errors[-1] < errors[0] / 3


def test_odom_pose_never_jumps_while_the_map_pose_absorbs_corrections() -> None:
    sim, fusion = Sim(scale=1.06), Fusion()
    rng = np.random.default_rng(9)
    prev = None
    for _ in range(round(60.0 / DT)):
        pose, fixes = sim.step()
        for f in fixes:
            if rng.random() < 0.05:  # some gross outliers
                f = FixObservation(f.t_measured, f.x + 4.0, f.y - 2.0, f.sd_x, f.sd_y, f.quality, f.source)
            fusion.add_fix(f, sim.t)
        fusion.predict(pose)
        o = fusion.odom_pose()
        assert (o.x, o.y, o.theta) == (pose.x, pose.y, pose.theta)  # exactly the odometry
        if prev is not None:
            assert math.hypot(o.x - prev.x, o.y - prev.y) <= 0.5 * DT * sim.scale + 1e-9
        prev = o
    # The map frame moved away from the odometry frame (scale error corrected), the odometry did not.
    tx, ty, _phi = fusion.map_from_odom()
    assert math.hypot(tx, ty) > 1.0


def _offset_after_outage(fusion: Fusion, kind: str) -> tuple[list[float], list[float], list[float]]:
    """Converge, lose the fixes for 30 s and come back ~30 cm off: either the wheels slipped 40 % for
    1.5 s (the odometry falls short along the track) or the robot was pushed 30 cm sideways (the
    odometry saw nothing). The covariance grew meanwhile, so the filter takes most of the offset
    from the first fix. Per output from the return of the fixes: how far the published pose moved
    unlike the robot, the published pose's error and the filter's own error."""
    sim = Sim(seed=4)
    for _ in sim.run(fusion, 40.0):
        pass
    for _ in range(round(30.0 / DT)):
        if kind == "slip":
            sim.scale = 0.6 if 44.0 <= sim.t < 45.5 else 1.015
        elif abs(sim.t - 44.0) < DT / 2:
            sim.x, sim.y = sim.x - 0.3 * math.sin(sim.th), sim.y + 0.3 * math.cos(sim.th)
        fusion.predict(sim.step()[0])
    sim.scale = 1.015
    jumps, errors, exact_errors = [], [], []
    prev = (fusion.map_pose(), sim.x, sim.y)
    for _ in sim.run(fusion, 8.0):
        p, e = fusion.map_pose(), fusion.filter_pose()
        jumps.append(math.hypot((p.x - prev[0].x) - (sim.x - prev[1]), (p.y - prev[0].y) - (sim.y - prev[2])))
        errors.append(sim.error(fusion))
        exact_errors.append(math.hypot(e.x - sim.x, e.y - sim.y))
        prev = (p, sim.x, sim.y)
    assert math.hypot(*fusion.pending_correction()[:2]) < 1e-3
    return jumps, errors, exact_errors


@pytest.mark.parametrize("kind", ["slip", "push"])
def test_a_30_cm_correction_after_an_outage_is_spread_over_outputs(kind: str) -> None:
    fusion = Fusion()
    jumps, errors, exact_errors = _offset_after_outage(fusion, kind)
    c = fusion.config
    assert errors[0] > 0.2  # 20-30 cm off when the fixes return (the odometry's own drift adds or takes some)
    assert errors[0] - exact_errors[0] > 0.1  # the filter's state jumped more than 10 cm at the first fix...
    bound = min(c.output_rate_mps * DT, c.output_max_step_m) + 0.005  # + the odometry's own error per step
    assert max(jumps) <= bound  # ...the published pose never moved more than the bound unlike the robot
    assert sum(1 for j in jumps if j > 0.005) >= 10  # it took many outputs to absorb
    assert errors[-1] < 0.05 and exact_errors[-1] < 0.05  # and it converged
    assert fusion.output_snaps == 0
    # Without the bounded rate, the same correction is one jump of the published pose.
    unbounded = FusionConfig(output_rate_mps=math.inf, output_max_step_m=math.inf, output_rate_rad_s=math.inf)
    raw_jumps, _, _ = _offset_after_outage(Fusion(unbounded), kind)
    assert max(raw_jumps) > 0.1


def test_published_pose_is_the_filters_in_steady_state() -> None:
    sim, fusion = converged()
    for _ in sim.run(fusion, 10.0):
        e, p = fusion.filter_pose(), fusion.map_pose()
        assert math.hypot(e.x - p.x, e.y - p.y) < 0.01  # ordinary corrections are applied at once or nearly
    tx, ty, phi = fusion.map_from_odom()
    o, p = fusion.odom_pose(), fusion.map_pose()
    assert (p.x, p.y) == pytest.approx(
        (math.cos(phi) * o.x - math.sin(phi) * o.y + tx, math.sin(phi) * o.x + math.cos(phi) * o.y + ty), abs=1e-9
    )


def test_uwb_stale_flag() -> None:
    sim, fusion = Sim(), Fusion(FusionConfig(stale_timeout_s=1.0))
    assert fusion.uwb_stale(0.0)
    for _ in sim.run(fusion, 5.0):
        pass
    assert not fusion.uwb_stale(sim.t)
    for _ in sim.run(fusion, 1.5, fixes=False):
        pass
    assert fusion.uwb_stale(sim.t)


def test_initialises_only_from_agreeing_fixes() -> None:
    sim, fusion = Sim(), Fusion()
    pose, _ = sim.step()
    fusion.predict(pose)
    # Scattered fixes (metres apart) never agree: no position yet.
    for k in range(10):
        fusion.add_fix(FixObservation(pose.t, 10.0 * (k % 3), 7.0 * (k % 4), 0.1, 0.1, 90, "test"), pose.t)
    assert not fusion.position_initialized
    for _ in sim.run(fusion, 2.0):  # the agreeing fixes must outnumber the scattered ones
        pass
    assert fusion.position_initialized
    assert sim.error(fusion) < 0.3


def test_config_is_checked() -> None:
    with pytest.raises(ValueError, match="history_s"):
        FusionConfig(history_s=0.5)
    with pytest.raises(ValueError, match="gate_chi2"):
        FusionConfig(gate_chi2=-1.0)
    with pytest.raises(ValueError, match="output_rate_mps"):
        FusionConfig(output_rate_mps=0.0)


def test_seed_reset_jumps_to_every_fix() -> None:
    seed = SeedReset(heading_offset=0.0)
    odo = Odometry()
    seed.predict(odo.update(0.0, 0.0, 0.0, None))
    seed.add_fix(FixObservation(0.0, 5.0, 5.0, 0.1, 0.1, 90, "test"), 0.0)
    seed.predict(odo.update(1.0, 0.5, 0.5, None))
    assert (seed.map_pose().x, seed.map_pose().y) == pytest.approx((5.5, 5.0))
    seed.add_fix(FixObservation(1.0, 9.0, 1.0, 0.1, 0.1, 90, "test"), 1.0)  # an outlier: taken as is
    assert (seed.map_pose().x, seed.map_pose().y) == pytest.approx((9.0, 1.0))


def test_without_a_uwb_position_the_pose_is_the_odometry_on_the_maps_own_frame() -> None:
    sim, fusion = Sim(), Fusion()
    for _ in sim.run(fusion, 2.0, fixes=False):
        pass
    o, p = fusion.odom_pose(), fusion.map_pose()
    assert (p.x, p.y, p.theta) == (o.x, o.y, o.theta) and math.isinf(p.sd_x)  # odometry alone
    tf = (1.0, -2.0, 0.5)  # the map keeper's map->odometry transform (Update.odom_frame)
    fusion.set_own_frame(tf)
    p = fusion.map_pose()
    c, s = math.cos(0.5), math.sin(0.5)
    assert p.x == pytest.approx(1.0 + c * o.x - s * o.y) and p.y == pytest.approx(-2.0 + s * o.x + c * o.y)
    assert p.theta == pytest.approx(math.remainder(o.theta + 0.5, math.tau))
    assert math.isinf(p.sd_x) and not fusion.heading_initialized  # on its map, not placed in the site frame
    assert fusion.map_from_odom() == tf
    with pytest.raises(ValueError, match="finite"):
        fusion.set_own_frame((math.nan, 0.0, 0.0))
    fusion.set_own_frame(None)
    assert fusion.map_pose().x == fusion.odom_pose().x


def test_once_uwb_gives_a_position_the_own_frame_is_not_used() -> None:
    sim, fusion = Sim(), Fusion()
    fusion.set_own_frame((50.0, 50.0, 1.0))  # far off: were it used, the pose would be there
    for _ in sim.run(fusion, 40.0):
        pass
    assert fusion.position_initialized
    assert sim.error(fusion) < 0.1
