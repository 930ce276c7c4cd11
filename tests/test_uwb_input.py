"""UWB fix parsers (native UwbFix over the wire codec, PANS JSON), and fusion in a short lockstep field run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fleetlink.agent.uwb_input import FixObservation, fix_from_pans, fix_from_uwb, pans_node_id, quality_to_sd
from fleetlink.shared import wire
from fleetlink.shared.messages import FixStatus, UwbFix
from fleetlink.shared.wire import Header

OFFSET = 1_767_225_000.0  # the receiver's wall - monotonic
TOPIC = "dwm/node/0a1b/uplink/location"


def uwb_fix(**over: object) -> UwbFix:
    fields: dict[str, object] = dict(
        header=Header(headerId=1, timestamp=OFFSET + 10.05, version="1.0.0", robot="r1", sender="uwb"),
        tag="r1",
        x=3.25,
        y=-0.5,
        z=0.3,
        sd_x=0.08,
        sd_y=0.12,
        quality=100,
        status=FixStatus.OK,
        anchors=("A1", "A2", "A3"),
        residual_rms_m=0.05,
        measured_at=OFFSET + 10.0,
    )
    fields.update(over)
    return UwbFix(**fields)


def test_native_fix_through_the_wire_codec() -> None:
    msg = wire.decode(UwbFix, wire.encode(uwb_fix()))
    f = fix_from_uwb(msg, OFFSET)
    assert f == FixObservation(pytest.approx(10.0), 3.25, -0.5, 0.08, 0.12, 100, "native", "r1")


def test_native_fix_not_ok_is_refused() -> None:
    with pytest.raises(ValueError, match="status"):
        fix_from_uwb(uwb_fix(status=FixStatus.DIVERGED, x=math.nan, y=math.nan), OFFSET)


def test_native_fix_without_covariance_uses_the_quality() -> None:
    f = fix_from_uwb(uwb_fix(sd_x=0.0, sd_y=0.0, quality=50), OFFSET)
    assert f.sd_x == f.sd_y == pytest.approx(quality_to_sd(50)) == pytest.approx(0.2)


def pans(**over: object) -> bytes:
    doc: dict[str, object] = {
        "position": {"x": 3.25, "y": -0.009, "z": 0.425, "quality": 21},
        "superFrameNumber": 1144,
        "timestamp": "1767225010250000",
    }
    doc.update(over)
    return json.dumps(doc).encode()


def test_pans_location() -> None:
    f = fix_from_pans(TOPIC, pans(), OFFSET)
    assert f.t_measured == pytest.approx(10.25)
    assert (f.x, f.y, f.quality, f.source, f.tag) == (3.25, -0.009, 21, "pans", "0a1b")
    assert f.sd_x == f.sd_y == pytest.approx(0.1 * 100 / 21)


def test_pans_leaps_sd_and_missing_timestamp() -> None:
    doc = {"position": {"x": 1.0, "y": 2.0, "z": 0.0, "quality": 90, "sd_x": 0.05, "sd_y": 0.07}}
    f = fix_from_pans("dwm/node/7/uplink/location", json.dumps(doc), OFFSET, received_at=42.0)
    assert (f.t_measured, f.sd_x, f.sd_y) == (42.0, 0.05, 0.07)
    with pytest.raises(ValueError, match="timestamp"):
        fix_from_pans("dwm/node/7/uplink/location", json.dumps(doc), OFFSET)


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"", "not JSON"),
        (b"\xff\xfe garbage", "not JSON"),
        (b"[1, 2]", "not an object"),
        (b"{}", "position"),
        (json.dumps({"position": {"x": 1, "y": 2}}).encode(), "quality"),
        (pans(position={"x": "1", "y": 2, "quality": 5}), "not a number"),
        (pans(position={"x": True, "y": 2, "quality": 5}), "not a number"),
        (b'{"position": {"x": NaN, "y": 2, "quality": 5}}', "not finite"),
        (b'{"position": {"x": 1e400, "y": 2, "quality": 5}}', "not finite"),
        (pans(position={"x": 1e6, "y": 2, "quality": 5}), "out of range"),
        (pans(position={"x": 1, "y": 2, "quality": 101}), "outside 0-100"),
        (pans(position={"x": 1, "y": 2, "quality": 50, "sd_x": -1, "sd_y": 0.1}), "negative"),
        (pans(timestamp="12ab"), "microseconds"),
        (pans(timestamp=-5), "microseconds"),
        (b"[" * 100_000, "over"),
        (b"[" * 3000, "JSON"),
    ],
)
def test_pans_malformed_inputs_give_a_reason(payload: bytes, reason: str) -> None:
    with pytest.raises(ValueError, match=reason):
        fix_from_pans(TOPIC, payload, OFFSET)


@pytest.mark.parametrize("topic", ["dwm/node//uplink/location", "dwm/node/a/uplink/status", "node/a b/uplink/location"])
def test_pans_topic_must_be_a_location(topic: str) -> None:
    with pytest.raises(ValueError, match="PANS location topic"):
        pans_node_id(topic)
    with pytest.raises(ValueError):
        fix_from_pans(topic, pans(), OFFSET)


def test_fusion_in_a_lockstep_field_run() -> None:
    """One robot driving in the office, odometry from its simulated board over Control Bus bytes,
    realistic UWB fixes through the PANS JSON path: the fused pose tracks the truth."""
    from dataclasses import replace

    from fleetlink.agent.fusion import Fusion
    from fleetlink.agent.odometry import Odometry
    from fleetlink.field.lockstep import FieldRun
    from fleetlink.field.scenario import LidarSettings, RobotSpec, Scenario
    from fleetlink.positioning.anchors import Anchor
    from fleetlink.positioning.gateway import pans_location
    from fleetlink.positioning.ranging import NoiseProfile, RangingModel
    from fleetlink.positioning.solver import solve
    from fleetlink.site.lockstep import SESSION_POLL, drive_by_session

    script = ((0.0, 0.5, 0.0), (8.0, 0.0, 0.8), (10.0, 0.4, 0.0), (16.0, 0.3, -0.2))
    scenario = Scenario(
        name="fusion-test",
        plan="office",
        seed=3,
        duration=20.0,
        robots=(RobotSpec("r1", pose=(8.0, 9.75, 0.0), drive="idle", lidar=False),),
        lidar=LidarSettings(enabled=False),
    )
    poll = replace(SESSION_POLL, motor=20.0, imu=20.0)
    odo, fusion = Odometry(), Fusion()
    errors: list[float] = []
    rejected_reasons: list[str] = []
    with FieldRun(scenario, open_loop=False) as run:
        anchors = tuple(Anchor(a.id, a.x, a.y, a.z) for a in run.plan.anchors)
        ranging = RangingModel(anchors, NoiseProfile.realistic(), np.random.default_rng(3))
        board = run.rigs[0].robot.board
        truth: dict[float, tuple[float, float]] = {}
        state = {"last": -1.0, "next_fix": 0.0}

        def drive(snap, t):
            st = board.state
            truth[round(t, 6)] = (st.x, st.y)
            if snap.motor is not None and snap.imu is not None and snap.updated > state["last"]:
                state["last"] = snap.updated
                fusion.predict(odo.update(snap.updated, snap.motor.left, snap.motor.right, snap.imu.yaw))
                if fusion.heading_initialized and snap.updated > 5.0:
                    p = fusion.map_pose()
                    tx, ty = truth[round(snap.updated, 6)]
                    errors.append(math.hypot(p.x - tx, p.y - ty))
            if t >= state["next_fix"]:
                state["next_fix"] += 0.1
                sol = solve(anchors, ranging.measure(st.x, st.y, 0.3), 0.3)
                if sol.ok:
                    payload = pans_location(sol.x, sol.y, 0.3, sol.quality, 0, OFFSET + t)
                    v = fusion.add_fix(fix_from_pans(TOPIC, payload, OFFSET), t)
                    if not v.accepted:
                        rejected_reasons.append(v.reason)
            return next(((v, w) for at, v, w in reversed(script) if at <= t), (0.0, 0.0))

        drive_by_session(run, 0, drive, poll)
        run.run()
    assert len(errors) > 200
    rmse = math.sqrt(sum(e * e for e in errors) / len(errors))
    assert rmse < 0.08, rmse
    assert max(errors) < 0.3
    assert fusion.accepted > 150
    assert not fusion.uwb_stale(20.0)
