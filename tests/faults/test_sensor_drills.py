"""Sensor drills: the lidar unplugged while it is read, and a UWB outage and an NLOS burst on the
real agent (``AgentRuntime``, fusion wired in).

The lidar drill runs twice: at the driver level (a reader loop over a TCP "cable" to the field's
simulated RPLIDAR, served exactly as hardware would be), and at the runtime level (the agent of a
real-time field robot reading its lidar through the cable: the fault in its events and state,
driving on meanwhile, mapping again once the cable is back, no restart).
"""

from __future__ import annotations

import contextlib
import math
import random
import threading
from collections.abc import Iterator
from types import SimpleNamespace

import numpy as np
import pytest

from fleetlink.agent.lidar.driver import LidarDisconnected, LidarDriver, LidarError
from fleetlink.field.device_server import DeviceServer
from fleetlink.field.lidar import LidarConfig, LidarModel, scan_source_for
from fleetlink.field.raycast import Raycaster
from fleetlink.field.rplidar import SimulatedRplidar
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import FixStatus, Pose, State, UwbFix
from tests.faults.relay import TcpRelay
from tests.faults.test_drills import Drill, drill  # noqa: F401  (the fixture)
from tests.harness import wait_until

# ------------------------------------------------------------------------------------------------
# Lidar unplugged

ROOM = np.array([(0, 0, 6, 0), (6, 0, 6, 4), (6, 4, 0, 4), (0, 4, 0, 0)], dtype=float)


@pytest.fixture(autouse=True)
def _no_close_sleep_in_pyserial_sockets(monkeypatch: pytest.MonkeyPatch) -> None:
    from serial.urlhandler import protocol_socket

    monkeypatch.setattr(protocol_socket, "time", SimpleNamespace(sleep=lambda seconds: None))


class LidarReader:
    """The agent-side loop: read revolutions; on a loss, report it and reconnect until it is back."""

    def __init__(self, url: str) -> None:
        self.clock = SystemClock()
        self.url = url
        self.revolutions = 0
        self.losses: list[str] = []
        self.resyncs = 0
        self.lost = threading.Event()
        self.bad_turns = 0
        self.crash: BaseException | None = None
        self._stop = threading.Event()
        self.drv = LidarDriver.open(url, self.clock, stall_timeout=0.5)
        self._t = threading.Thread(target=self._run, name="lidar-reader", daemon=True)
        self._t.start()

    def _run(self) -> None:
        try:
            self.drv.start_scan()
            while not self._stop.is_set():
                try:
                    for rev in self.drv.poll(self.clock.now() + 0.1):
                        ok = np.isfinite(rev.distances_m).all() and len(rev.angles_rad) > 100
                        near = rev.distances_m[rev.distances_m > 0]
                        if not ok or near.size == 0 or near.max() > 8.0:
                            self.bad_turns += 1
                        self.revolutions += 1
                except LidarError as exc:  # unplugged (closed) or silent (stalled): report, then resync
                    self.losses.append(type(exc).__name__)
                    self.lost.set()
                    self._resync()
        except BaseException as exc:
            self.crash = exc

    def _resync(self) -> None:
        while not self._stop.is_set():
            try:
                self.drv.reconnect()
                self.drv.start_scan(timeout=0.5)
                self.resyncs += 1
                self.lost.clear()
                return
            except (LidarError, OSError):
                self._stop.wait(0.1)

    def stop(self) -> None:
        self._stop.set()
        self._t.join(5)
        self.drv.close()


@pytest.fixture
def lidar_cable() -> Iterator[TcpRelay]:
    model = LidarModel(LidarConfig(rate_hz=10.0).noiseless(), np.random.default_rng(3))
    device = SimulatedRplidar(model.config, scan_source_for(model, lambda t: (2.0, 1.5, 0.3), Raycaster(ROOM)))
    server = DeviceServer(device, SystemClock(), step_hz=100, name="lidar")
    relay = TcpRelay(server.serve_tcp())
    try:
        yield relay
    finally:
        relay.close()
        server.stop()


@pytest.mark.parametrize("how", ["unplugged", "silent"])
def test_lidar_unplugged_driver_reports_the_loss_and_resynchronises(lidar_cable: TcpRelay, how: str) -> None:
    reader = LidarReader(f"socket://127.0.0.1:{lidar_cable.port}")
    try:
        wait_until(lambda: reader.revolutions >= 3, message="revolutions")
        if how == "unplugged":
            lidar_cable.unplug()  # the USB cable pulled: the port closes, reopening fails
        else:
            lidar_cable.blackhole()  # the wire still there, nothing on it
        wait_until(reader.lost.is_set, message="the loss reported")
        n = reader.revolutions
        lidar_cable.plug()
        lidar_cable.restore()
        wait_until(lambda: not reader.lost.is_set() and reader.revolutions >= n + 3, timeout=15, message="scans back")
        expected = {"unplugged": "LidarDisconnected", "silent": "LidarTimeout"}[how]
        assert reader.losses[0] == expected, reader.losses
        assert reader.resyncs >= 1 and reader.drv.stats.reconnects >= 1
        assert reader.bad_turns == 0  # no half-turn or garbage from before the loss leaks into a scan
        assert reader.crash is None
    finally:
        reader.stop()
    assert isinstance(LidarDisconnected("x"), ConnectionError)


def test_lidar_unplugged_agent_reports_keeps_driving_and_maps_again() -> None:
    import dataclasses

    import zenoh

    from fleetlink.field.realtime import RealtimeField
    from fleetlink.shared.messages import Event, Teleop
    from fleetlink.site.agents import FieldAgents
    from tests.harness.mosquitto import free_port
    from tests.harness.zenoh_peers import zenoh_config
    from tests.test_field_realtime import quiet_scenario

    clock = SystemClock()
    field = RealtimeField(quiet_scenario(), clock=clock)  # uvc-1, its lidar at 10 Hz over TCP
    listen = f"tcp/127.0.0.1:{free_port()}"
    seen: list[object] = []
    lock = threading.Lock()
    relay = session = agents = None

    def on(sample: object) -> None:
        try:
            msg = wire.decode_key(str(sample.key_expr), sample.payload.to_bytes())  # type: ignore[attr-defined]
        except wire.WireError:
            return
        if isinstance(msg, Event | State):
            with lock:
                seen.append(msg)

    def events(kind: str) -> list[Event]:
        with lock:
            return [m for m in seen if isinstance(m, Event) and m.kind == kind]

    def lidar_error_in_state() -> bool | None:
        with lock:
            last = next((m for m in reversed(seen) if isinstance(m, State)), None)
        return None if last is None else any("lidar" in e.errorDescription for e in last.errors)

    try:
        endpoints = field.start()
        ep = endpoints["uvc-1"]
        assert ep.lidar is not None
        relay = TcpRelay(int(ep.lidar.rsplit(":", 1)[1]))
        cabled = {"uvc-1": dataclasses.replace(ep, lidar=f"socket://127.0.0.1:{relay.port}")}
        session = zenoh.open(zenoh_config(listen=[listen]))
        session.declare_subscriber(keys.zenoh_robot("uvc-1"), on)
        agents = FieldAgents(cabled, clock=clock, zenoh_connect=[listen])
        agent = agents.start()["uvc-1"]
        robot = field.world.robots[0]
        wait_until(lambda: agent.scans >= 5, timeout=20, message="mapping from the lidar")
        wait_until(lambda: lidar_error_in_state() is False, message="a state without a lidar error")
        relay.unplug()  # the USB cable pulled
        wait_until(lambda: events("lidar_fault"), message="the lidar_fault event")
        wait_until(lambda: lidar_error_in_state() is True, message="the lidar error in the state")
        scans = agent.scans
        # Still drivable: the guard reads the front ultrasonic, not the lidar.
        op = wire.HeaderCounter(clock, robot="uvc-1", sender="operator-1")
        x0, y0, _ = robot.pose

        def drive() -> bool:
            msg = op.make(Teleop, v=0.2, omega=0.0, ttl_s=0.4)
            session.put(wire.key_of(msg), wire.encode(msg))
            x, y, _ = robot.pose
            return math.hypot(x - x0, y - y0) > 0.1

        wait_until(drive, interval=0.1, timeout=15, message="driving with the lidar unplugged")
        assert agent.scans == scans  # nothing mapped from a missing lidar
        wait_until(lambda: abs(robot.board.state.true_v) < 0.01, message="the stop when teleop ends")
        relay.plug()
        wait_until(lambda: events("lidar_ok"), timeout=15, message="the lidar_ok event")
        wait_until(lambda: agent.scans >= scans + 5, timeout=15, message="mapping again, no restart")
        wait_until(lambda: lidar_error_in_state() is False, message="the lidar error cleared from the state")
        assert len(events("lidar_fault")) == 1  # reported once per outage, not once per retry
        assert agent._thread is not None and agent._thread.is_alive()
    finally:
        if agents is not None:
            agents.stop()
        if session is not None:
            session.close()
        if relay is not None:
            relay.close()
        field.stop()


# ------------------------------------------------------------------------------------------------
# UWB outage and NLOS burst, on the agent runtime (fusion in the runtime since ddbe175)

TRUE_X, TRUE_Y = 5.0, 3.0


class Uwb:
    """The positioning system's fixes for r1 over Zenoh at 10 Hz: good, biased (NLOS) or none."""

    def __init__(self, d: Drill) -> None:
        self.d = d
        self.clock = SystemClock()
        self.counter = wire.HeaderCounter(self.clock, robot="r1", sender="uwb")
        self.mode = "good"
        self.sent_biased = 0
        self.rng = random.Random(5)
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, name="uwb", daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            if self.mode == "off":
                continue
            x, y = TRUE_X + self.rng.gauss(0, 0.03), TRUE_Y + self.rng.gauss(0, 0.03)
            if self.mode == "nlos":
                a, bias = self.rng.uniform(0, 2 * math.pi), self.rng.uniform(1.0, 2.5)
                x, y = x + bias * math.cos(a), y + bias * math.sin(a)
                self.sent_biased += 1
            fix = self.counter.make(
                UwbFix,
                tag="r1",
                x=x,
                y=y,
                z=0.3,
                sd_x=0.05,
                sd_y=0.05,
                quality=90,
                status=FixStatus.OK,
                anchors=("A1", "A2", "A3", "A4"),
                residual_rms_m=0.05,
                measured_at=self.clock.wall(),
            )
            with contextlib.suppress(Exception):
                self.d.op.zsession.put(keys.key("r1", "uwb"), wire.encode(fix))

    def stop(self) -> None:
        self._stop.set()
        self._t.join(2)


def _poses(d: Drill) -> list[Pose]:
    got: list[Pose] = []

    def on(sample: object) -> None:
        msg = wire.decode_key(str(sample.key_expr), sample.payload.to_bytes())  # type: ignore[attr-defined]
        if isinstance(msg, Pose):
            got.append(msg)

    d.op.zsession.declare_subscriber(keys.key("r1", "pose"), on)
    return got


def _sane(p: Pose, tol: float = 0.3) -> bool:
    return abs(p.x - TRUE_X) < tol and abs(p.y - TRUE_Y) < tol


def _state(d: Drill) -> State | None:
    return d.op.last_state()


@pytest.mark.slow
def test_uwb_outage_and_nlos_burst(drill: Drill) -> None:  # noqa: F811
    poses = _poses(drill)
    uwb = Uwb(drill)
    core = drill.agent.core
    try:
        wait_until(lambda: poses and not poses[-1].uwbStale and _sane(poses[-1], 0.1), message="a fused pose")
        # Outage: no fix at all for 2.5 s. UWB reported stale; the pose stays where the robot is.
        uwb.mode = "off"
        wait_until(lambda: (s := _state(drill)) is not None and s.uwbStale, message="uwbStale in state")
        wait_until(lambda: poses[-1].uwbStale, message="uwbStale in pose")
        n = len(poses)
        wait_until(lambda: len(poses) > n + 20, message="a second of poses in the outage")
        assert all(_sane(p) for p in poses[n:]), [(p.x, p.y) for p in poses[n:] if not _sane(p)]
        uwb.mode = "good"
        wait_until(lambda: (s := _state(drill)) is not None and not s.uwbStale, message="UWB back")
        # NLOS burst: 8 fixes 1-2.5 m off in random directions, then good ones, twice.
        accepted, rejected = core.fixes_accepted, core.fixes_rejected
        n = len(poses)
        biased0 = uwb.sent_biased
        for _ in range(2):
            uwb.mode = "nlos"
            target = uwb.sent_biased + 8
            wait_until(lambda t=target: uwb.sent_biased >= t, message="the burst sent")
            uwb.mode = "good"
            good = core.fixes_accepted
            wait_until(lambda g=good: core.fixes_accepted >= g + 5, message="good fixes after the burst")
        burst = uwb.sent_biased - biased0
        assert core.fixes_rejected - rejected >= burst, (core.fixes_rejected - rejected, burst)
        assert core.fixes_accepted > accepted
        assert all(_sane(p) for p in poses[n:]), [(p.x, p.y) for p in poses[n:] if not _sane(p)]
        assert not poses[-1].uwbStale
        # Safe throughout: nobody drove, the wheels never turned; the agent is alive.
        assert drill.stopped()
        assert drill.alive()
    finally:
        uwb.stop()
