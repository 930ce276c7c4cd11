"""The agent end to end against a simulated board over TCP: teleop moves the wheels, silence stops them;
UWB fixes over MQTT (native and PANS) localise it; the control lease and the operators allowlist."""

from __future__ import annotations

import itertools
import json
import math
import statistics
import time
from typing import Any

import pytest

from fleetlink.agent.config import ConfigError, parse_agent_config
from fleetlink.shared import wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import (
    AckResult,
    Action,
    ActionType,
    FixStatus,
    InstantActions,
    LeaseRequest,
    Teleop,
    UwbFix,
)
from tests.harness import MosquittoBroker, wait_until
from tests.test_agent_links import Rig, make_rig, rig  # noqa: F401  (the fixture)


def test_teleop_moves_the_wheels_and_silence_stops_them(rig: Rig) -> None:  # noqa: F811
    op, board, agent = rig.op, rig.board, rig.agent
    sent = []

    def drive() -> bool:
        m = op.counter.make(Teleop, v=0.3, omega=0.0, ttl_s=0.5)
        sent.append(m.header.headerId)
        op.send(m, mqtt_=False)
        return board.state.v_left > 0.1 and board.state.v_right > 0.1

    wait_until(drive, interval=0.1, message="the wheels to turn under teleop")
    assert op.acks_for(sent[0], "teleop")[0][1].result is AckResult.ACCEPTED
    # The operator goes quiet: the agent's deadman stops the robot (not the board's watchdog,
    # which needs the agent itself to fall silent).
    wait_until(lambda: abs(board.state.v_left) < 0.01 and abs(board.state.v_right) < 0.01, message="the stop")
    assert not board.state.watchdog_tripped
    assert agent.board.snapshot.command == (0.0, 0.0)
    wait_until(lambda: (s := op.last_state()) is not None and s.driveMode == "idle", message="idle in state")


def test_an_idle_agent_ticks_per_pose_and_a_driving_one_at_the_control_rate(rig: Rig) -> None:  # noqa: F811
    """Idle, the control loop wakes for each pose (20 Hz) instead of at 50 Hz, and no pose is lost;
    a command wakes it at once and it steers at the control rate until the robot is idle again."""
    op, agent = rig.op, rig.agent
    ticks: list[float] = []
    tick = agent.core.tick

    def counted(now: float, board: Any) -> Any:
        ticks.append(now)
        return tick(now, board)

    agent.core.tick = counted  # type: ignore[method-assign]

    def since(t0: float) -> list[float]:
        return [x for x in list(ticks) if x >= t0]

    def median_gap(t0: float) -> float:
        t = since(t0)
        assert len(t) >= 10, f"only {len(t)} ticks"
        return statistics.median(b - a for a, b in itertools.pairwise(t))

    def zenoh_pose_ids(since: float) -> list[int]:
        with op.lock:
            return [p.header.headerId for lk, p in op.poses if lk == "zenoh" and p.header.timestamp >= since]

    start = time.time()
    t0 = agent.clock.now()
    wait_until(
        lambda: len(since(t0)) >= 30 and len(zenoh_pose_ids(start + 0.2)) >= 20, message="30 idle ticks, 20 poses"
    )
    assert not agent.core.driving
    assert median_gap(t0) == pytest.approx(0.05, abs=0.01)  # one tick per pose
    ids = zenoh_pose_ids(start + 0.2)
    assert ids == list(range(ids[0], ids[0] + len(ids))), "poses lost while idle"

    t1 = agent.clock.now()

    def hold_key() -> bool:  # an operator holding a key, a teleop every 0.1 s
        op.send(op.counter.make(Teleop, v=0.2, omega=0.0, ttl_s=0.5), mqtt_=False)
        return len(since(t1 + 0.2)) >= 60

    wait_until(hold_key, interval=0.1, message="60 ticks under teleop")
    assert agent.core.driving
    assert median_gap(t1 + 0.2) == pytest.approx(0.02, abs=0.005)  # the control rate, 50 Hz

    wait_until(lambda: not agent.core.driving, message="the teleop to lapse and the robot to stop")
    t2 = agent.clock.now()
    wait_until(lambda: len(since(t2 + 0.1)) >= 20, message="20 idle ticks again")
    assert median_gap(t2 + 0.1) == pytest.approx(0.05, abs=0.01)


@pytest.mark.parametrize(
    ("data", "fragment"),
    [
        ({"board": "socket://x:1", "zenoh": {}}, "robot.toml: robot: missing required key"),
        ({"robot": "sim", "board": "x", "zenoh": {}}, "reserved"),
        ({"robot": "r1", "board": "x"}, "needs a [zenoh] or an [mqtt]"),
        ({"robot": "r1", "board": "x", "mqtt": {"url": "http://h"}}, "mqtt.url"),
        ({"robot": "r1", "board": "x", "zenoh": {"connect": "tcp/1.2.3.4:1"}}, "zenoh.connect"),
        ({"robot": "r1", "board": "x", "zenoh": {}, "limits": {"v_max": -1}}, "limits.v_max"),
        ({"robot": "r1", "board": "x", "zenoh": {}, "bogus": 1}, "bogus: unknown key; allowed: board,"),
        ({"robot": "r1", "board": "x", "zenoh": {}, "operators": "op-alice"}, "operators"),
        ({"robot": "r1", "board": "x", "zenoh": {"username": "r1"}}, "go together"),
        ({"robot": "r1", "board": "x", "zenoh": {"root_ca": "/nonexistent/ca.crt"}}, "zenoh.root_ca"),
        ({"robot": "r1", "board": "x", "mqtt": {"url": "mqtt://h", "password": "p"}}, "needs a username"),
    ],
)
def test_config_errors_are_clear(data: dict[str, object], fragment: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_agent_config(data, "robot.toml")
    assert fragment in str(info.value)
    assert str(info.value).startswith("robot.toml: ")


def test_example_config_loads() -> None:
    from pathlib import Path

    from fleetlink.agent.config import load_agent_config

    cfg = load_agent_config(Path(__file__).resolve().parent.parent / "deploy" / "robot.example.toml")
    assert cfg.robot == "r1" and cfg.zenoh is not None and cfg.mqtt is not None
    assert cfg.operators == ("op-alice", "op-bob")
    assert cfg.comms.policy.value == "retrace" and cfg.home is None  # a rescue robot retraces


def test_home_and_comms_tables_are_validated_with_clear_messages() -> None:
    import pytest

    from fleetlink.agent.config import ConfigError, parse_agent_config

    base = {"robot": "r1", "board": "socket://h:1", "mqtt": {"url": "mqtt://h:1"}}
    cfg = parse_agent_config({**base, "home": {"x": 1.0, "y": -2.0, "theta_deg": 90}, "comms": {"timeout_s": 4}})
    assert cfg.home is not None and (cfg.home.x, cfg.home.y, cfg.home.theta_deg) == (1.0, -2.0, 90.0)
    assert cfg.comms.timeout_s == 4.0 and cfg.comms.policy.value == "stop"
    for bad, where in (
        ({"comms": {"policy": "fly"}}, "comms.policy"),
        ({"comms": {"timeout_s": 0}}, "comms.timeout_s"),
        ({"home": {"x": 1.0}}, "home.y"),
        ({"home": {"x": float("nan"), "y": 0.0}}, "home.x"),
    ):
        with pytest.raises(ConfigError, match=where):
            parse_agent_config({**base, **bad})


# --------------------------------------------------------------------------------------------------
# Localisation: UWB fixes over MQTT into the fusion


def _native_fix(gw: wire.HeaderCounter, x: float, y: float) -> bytes:
    return wire.encode(
        gw.make(
            UwbFix,
            tag="r1",
            x=x,
            y=y,
            z=0.3,
            sd_x=0.05,
            sd_y=0.05,
            quality=90,
            status=FixStatus.OK,
            anchors=("a1", "a2", "a3"),
            residual_rms_m=0.02,
            measured_at=time.time(),
        )
    )


def _pans_fix(x: float, y: float) -> bytes:
    stamp = str(int(time.time() * 1e6))
    return json.dumps({"position": {"x": x, "y": y, "z": 0.3, "quality": 90}, "timestamp": stamp}).encode()


def test_uwb_fixes_native_and_pans_localise_the_agent_and_silence_goes_stale(rig: Rig) -> None:  # noqa: F811
    op, core = rig.op, rig.agent.core
    gw = wire.HeaderCounter(SystemClock(), robot="r1", sender="uwb-gateway")
    assert core.fusion is not None and not core.fusion.position_initialized
    st = op.last_state()
    assert st is not None and st.uwbStale and not st.agvPosition.positionInitialized

    def localised(send: object) -> bool:
        send()  # type: ignore[operator]
        s = op.last_state()
        return (
            s is not None
            and s.agvPosition.positionInitialized
            and not s.uwbStale
            and math.hypot(s.agvPosition.x - 3.0, s.agvPosition.y - 2.0) < 0.1
        )

    # Native fixes (the gateway's UwbFix on fleetlink/v1/r1/uwb), the robot standing at (3, 2).
    wait_until(
        lambda: localised(lambda: op.mclient.publish("fleetlink/v1/r1/uwb", _native_fix(gw, 3.0, 2.0), qos=0)),
        interval=0.05,
        message="positionInitialized and a map pose near the native fixes",
    )
    # PANS JSON from a DWM1001 tag: accepted by the fusion too.
    before = core.fusion.accepted
    wait_until(
        lambda: (
            localised(lambda: op.mclient.publish("dwm/node/r1/uplink/location", _pans_fix(3.0, 2.0)))
            and core.fusion.accepted >= before + 10
        ),
        interval=0.05,
        message="PANS fixes accepted by the fusion",
    )
    assert core.gate.stats.rejected.get(("mqtt", "pans"), 0) == 0
    # Silence: UWB stale in state (the pose holds on odometry).
    wait_until(lambda: (s := op.last_state()) is not None and s.uwbStale, message="uwbStale after UWB silence")
    s = op.last_state()
    assert s is not None and s.agvPosition.positionInitialized
    assert math.hypot(s.agvPosition.x - 3.0, s.agvPosition.y - 2.0) < 0.1


# --------------------------------------------------------------------------------------------------
# Access: the control lease and the operators allowlist


def _teleop(counter: wire.HeaderCounter) -> Teleop:
    return counter.make(Teleop, v=0.3, omega=0.0, ttl_s=0.5)


def _ack(r: Rig, msg: wire.Message, link: str) -> tuple[AckResult, str]:
    hid, sender = msg.header.headerId, msg.header.sender

    def mine() -> list[wire.Message]:
        return [a for lk, a in r.op.acks_for(hid, msg.TOPIC) if lk == link and a.commandSender == sender]

    wait_until(mine, message=f"ack of {msg.TOPIC} on {link}")
    a = mine()[0]
    return a.result, a.reason


def test_lease_holder_drives_others_are_refused_with_the_holder_named(rig: Rig) -> None:  # noqa: F811
    op, board = rig.op, rig.board
    eve = wire.HeaderCounter(SystemClock(), robot="r1", sender="op-eve")
    wait_until(lambda: any(le.holder == "" for _, le in op.leases), message="the free lease announced")
    take = op.counter.make(LeaseRequest, duration_s=30.0, release=False)
    op.send(take, mqtt_=False)
    assert _ack(rig, take, "zenoh") == (AckResult.ACCEPTED, "")
    for link in ("zenoh", "mqtt"):  # every console sees it, on either link
        wait_until(
            lambda link=link: any(lk == link and le.holder == "operator-1" for lk, le in op.leases),
            message=f"the lease announced on {link}",
        )
    # Another operator: its teleop, order-like actions and lease request are refused, naming the holder.
    m = _teleop(eve)
    op.send(m, zenoh_=False)
    result, reason = _ack(rig, m, "mqtt")
    assert result is AckResult.REJECTED and "leased to operator-1" in reason
    resume = eve.make(
        InstantActions, actions=(Action(actionId="a1", actionType=ActionType.RESUME, actionParameters=()),)
    )
    op.send(resume, zenoh_=False)
    assert _ack(rig, resume, "mqtt")[0] is AckResult.REJECTED
    grab = eve.make(LeaseRequest, duration_s=30.0, release=False)
    op.send(grab, mqtt_=False)
    result, reason = _ack(rig, grab, "zenoh")
    assert result is AckResult.REJECTED and "operator-1" in reason
    assert abs(board.state.v_left) < 0.01 and rig.agent.board.snapshot.command == (0.0, 0.0)
    assert rig.agent.core.refused_lease == 2
    # Stopping stays everyone's right.
    stop = eve.make(InstantActions, actions=(Action(actionId="s1", actionType=ActionType.STOP, actionParameters=()),))
    op.send(stop, mqtt_=False)
    assert _ack(rig, stop, "zenoh")[0] is AckResult.ACCEPTED
    # The holder drives.
    wait_until(
        lambda: op.send(_teleop(op.counter), mqtt_=False) is not None and board.state.v_left > 0.1,
        interval=0.1,
        message="the holder's teleop to turn the wheels",
    )
    # Released: the other operator may drive.
    free = op.counter.make(LeaseRequest, duration_s=0.0, release=True)
    op.send(free, mqtt_=False)
    assert _ack(rig, free, "zenoh")[0] is AckResult.ACCEPTED
    wait_until(lambda: op.leases[-1][1].holder == "", message="the release announced")
    wait_until(
        lambda: (s := op.last_state()) is not None and s.driveMode == "idle", message="the holder's ttl to lapse"
    )
    m = _teleop(eve)
    op.send(m, mqtt_=False)
    assert _ack(rig, m, "zenoh") == (AckResult.ACCEPTED, "")
    # Driving took the free lease for op-eve: every console sees it, and the first operator is
    # now the one refused -- nobody drives without holding the lease.
    wait_until(lambda: op.leases[-1][1].holder == "op-eve", message="driving took the free lease")
    m = _teleop(op.counter)
    op.send(m, mqtt_=False)
    result, reason = _ack(rig, m, "zenoh")
    assert result is AckResult.REJECTED and "leased to op-eve" in reason


def test_unlisted_operator_cannot_drive_over_either_link(mosquitto: MosquittoBroker) -> None:
    """An agent with an allowlist subscribes its commands under the listed operators' names only
    (agent/node.py ``input_keys``): what anyone else sends never reaches it, on either link."""
    with make_rig(mosquitto, operators=("operator-1",)) as r:
        eve = wire.HeaderCounter(SystemClock(), robot="r1", sender="op-eve")
        for link in ("zenoh", "mqtt"):
            sent = [_teleop(eve), eve.make(LeaseRequest, duration_s=30.0, release=False)]
            for m in sent:
                r.op.send(m, zenoh_=link == "zenoh", mqtt_=link == "mqtt")
            # The sentinel: the listed operator's zero teleop, after eve's on the same path.
            sentinel = r.op.counter.make(Teleop, v=0.0, omega=0.0, ttl_s=0.5)
            r.op.send(sentinel, zenoh_=link == "zenoh", mqtt_=link == "mqtt")
            assert _ack(r, sentinel, link)[0] is AckResult.ACCEPTED
            with r.op.lock:
                assert not [a for _, a in r.op.acks if a.commandSender == "op-eve"]
        assert abs(r.board.state.v_left) < 0.01 and r.agent.board.snapshot.command == (0.0, 0.0)
        core = r.agent.core
        assert core.gate.stats.rejected_total == 0  # nothing of eve's even reached the gate
        assert all(le.holder == "" for _, le in r.op.leases)
        # The listed operator drives.
        wait_until(
            lambda: r.op.send(_teleop(r.op.counter), mqtt_=False) is not None and r.board.state.v_left > 0.1,
            interval=0.1,
            message="the listed operator's teleop to turn the wheels",
        )
