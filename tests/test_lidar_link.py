"""The agent's lidar driver against the simulated RPLIDAR, over real bytes.

One suite, three transports: a real TCP socket and a pty (pyserial's ``serial_for_url``; the lidar
served by ``DeviceServer`` in real time, stepped at 100 Hz) and ``InProcessPort`` under a
``SimClock`` (lockstep: simulated time moves only while the driver waits).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

from fleetlink.agent.lidar.driver import (
    LidarDisconnected,
    LidarDriver,
    LidarError,
    LidarProtocolError,
    LidarTimeout,
)
from fleetlink.devices.ports import InProcessPort, SerialPort
from fleetlink.devices.rplidar import protocol as lp
from fleetlink.field.device_server import DeviceServer
from fleetlink.field.lidar import LidarConfig, LidarModel, scan_source_for
from fleetlink.field.raycast import Raycaster
from fleetlink.field.rplidar import RplidarConfig, SimulatedRplidar
from fleetlink.shared.clock import Clock, SimClock, SystemClock

W, H = 6.0, 4.0
ROOM = np.array([(0, 0, W, 0), (W, 0, W, H), (W, H, 0, H), (0, H, 0, 0)], dtype=float)
POSE = (2.0, 1.5, 0.4)
RATE_HZ = 10.0  # 800 samples a turn at 8000 samples/s: three turns in well under a second


def room_distance(x: float, y: float, a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 1e-15, (W - x) / c, np.where(c < -1e-15, -x / c, np.inf))
        ty = np.where(s > 1e-15, (H - y) / s, np.where(s < -1e-15, -y / s, np.inf))
    return np.minimum(tx, ty)


def make_lidar(rate_hz: float = RATE_HZ, now: float = 0.0) -> SimulatedRplidar:
    model = LidarModel(LidarConfig(rate_hz=rate_hz).noiseless(), np.random.default_rng(7))
    return SimulatedRplidar(model.config, scan_source_for(model, lambda t: POSE, Raycaster(ROOM)), now=now)


@pytest.fixture(autouse=True)
def _no_close_sleep_in_pyserial_sockets(monkeypatch: pytest.MonkeyPatch) -> None:
    """pyserial's socket:// ``close()`` sleeps 0.3 s "in case of quick reconnects"; skip it here."""
    from serial.urlhandler import protocol_socket

    monkeypatch.setattr(protocol_socket, "time", SimpleNamespace(sleep=lambda seconds: None))


@contextlib.contextmanager
def serve_lidar(kind: str, lidar: SimulatedRplidar | None = None, port: int = 0) -> Iterator[tuple[DeviceServer, str]]:
    server = DeviceServer(lidar or make_lidar(), SystemClock(), step_hz=100, name="lidar")
    try:
        url = f"socket://127.0.0.1:{server.serve_tcp(port=port)}" if kind == "tcp" else server.serve_pty()
        yield server, url
    finally:
        server.stop()


@dataclass
class Rig:
    kind: str
    lidar: SimulatedRplidar
    clock: Clock
    driver: LidarDriver
    server: DeviceServer | None = None


@pytest.fixture(params=["inproc", "tcp", "pty"])
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    kind = request.param
    if kind == "inproc":
        clock = SimClock(start=100.0)
        lidar = make_lidar(now=clock.now())
        driver = LidarDriver(lidar.in_process_port(clock), clock)
        yield Rig(kind, lidar, clock, driver)
        driver.close()
        return
    with serve_lidar(kind) as (server, url):
        clock = SystemClock()
        driver = LidarDriver(SerialPort(url), clock)
        try:
            yield Rig(kind, server.device, clock, driver, server)  # type: ignore[arg-type,unused-ignore]
        finally:
            driver.close()


def check_turn(rev: lp.Revolution, n: int = 800, rate_hz: float = RATE_HZ) -> None:
    """A whole turn of the noiseless model: ``n`` samples at k times the model's step (800 at 10 Hz,
    1455 at 5.5 Hz: phase 0), each with the ray caster's distance at its true angle. Standard
    nodes carry 1/64 degree and 1/4 mm; express capsules interpolated angles (within 1/16 degree
    plus 1/64 of rounding where a capsule straddles the turn's end) and whole millimetres."""
    assert len(rev) == n
    assert np.all(np.diff(rev.angles_rad) > 0)
    assert np.all(rev.distances_m > 0) and np.all(rev.qualities > 0)
    ideal = np.arange(n) * 2 * math.pi * rate_hz / 8000.0  # the model's sample step
    # Samples in turn order; one near 0 may have come out on the other side of the line.
    shifts = [np.roll(ideal, k) for k in (-1, 0, 1)]
    errors = [np.abs((rev.angles_rad - ref + math.pi) % (2 * math.pi) - math.pi) for ref in shifts]
    best = int(np.argmin([e.max() for e in errors]))
    assert errors[best].max() < math.radians(1 / 16 + 1 / 64 + 1e-6)
    np.testing.assert_allclose(rev.distances_m, room_distance(POSE[0], POSE[1], shifts[best] + POSE[2]), atol=1e-3)


def test_identify_scan_and_stop(rig: Rig) -> None:
    drv = rig.driver
    info = drv.get_info()
    assert info == lp.DeviceInfo(0x18, (1, 29), 7, b"FLK-RPLIDAR-A1\x00\x01")
    assert drv.get_health() == lp.DeviceHealth(lp.HEALTH_GOOD, 0)
    assert drv.get_samplerate() == lp.SampleRate(125, 125)
    t0 = rig.clock.now()
    # the typical mode, from GET_LIDAR_CONF: express capsules
    assert drv.start_scan() == lp.EXPRESS_DESCRIPTOR
    assert drv.mode is not None and drv.mode.name == "Express" and rig.lidar.express
    assert drv.scanning and drv.motor_on and rig.lidar.motor_on  # SET_MOTOR_PWM went ahead of the scan
    revs = drv.read_revolutions(3, timeout=3.0)
    for rev in revs:
        check_turn(rev)
    stamps = [r.stamp for r in revs]
    assert all(s is not None for s in stamps)
    elapsed = rig.clock.now() - t0
    assert 0.3 <= elapsed < 2.0  # the first complete turn ends when the second starts: 4 turn starts
    if rig.kind == "inproc":
        assert np.diff(np.array(stamps, dtype=float)) == pytest.approx([0.1, 0.1], abs=0.006)
    drv.stop()
    assert not drv.scanning and not rig.lidar.scanning
    assert drv.get_health().ok  # no stale nodes in the way of the next answer
    assert drv.decoder.stats.resync_bytes == 0
    drv.stop_motor()
    deadline = rig.clock.now() + 1.0
    while rig.lidar.motor_on and rig.clock.now() < deadline:  # over TCP / a pty it takes a moment
        rig.clock.sleep_until(rig.clock.now() + 0.01)
    assert not rig.lidar.motor_on


def test_restart_scan_and_requests_stop_it(rig: Rig) -> None:
    drv = rig.driver
    drv.start_scan()
    drv.read_revolutions(1, timeout=2.0)
    assert drv.get_info().model == 0x18  # stops the scan first
    assert not drv.scanning
    drv.start_scan(force=True)
    drv.start_scan()  # a scan restarted while running
    check_turn(drv.read_revolutions(1, timeout=2.0)[0])
    with pytest.raises(LidarError):
        drv.stop()
        drv.poll(rig.clock.now() + 0.1)


def test_inproc_slow_rate_matches_the_a1() -> None:
    clock = SimClock(start=5.0)
    lidar = make_lidar(rate_hz=5.5, now=clock.now())
    with LidarDriver(lidar.in_process_port(clock), clock) as drv:
        drv.start_scan()
        revs = drv.read_revolutions(3, timeout=2.0)
        assert [len(r) for r in revs] == [1455] * 3  # 8000 / 5.5 = 1454.5, phase 0
        for r in revs:
            check_turn(r, 1455, rate_hz=5.5)
    assert not lidar.motor_on and not lidar.scanning  # close() stopped both


def test_inproc_line_noise_is_survived() -> None:
    clock = SimClock()
    lidar = make_lidar(now=clock.now())
    port = lidar.in_process_port(clock)
    drv = LidarDriver(port, clock)
    drv.start_scan()
    drv.read_revolutions(1, timeout=1.0)
    port.inject(b"\x00\x55\xa5\x17garbage")
    revs = drv.read_revolutions(3, timeout=1.0)
    assert drv.decoder.stats.resync_bytes > 0
    assert sum(len(r) == 800 for r in revs) >= 2  # at most the turn hit by the noise is off
    drv.close()


def test_inproc_timeouts_and_stall() -> None:
    clock = SimClock()
    lidar = make_lidar(now=clock.now())
    port = lidar.in_process_port(clock)
    drv = LidarDriver(port, clock, timeout=0.3, stall_timeout=0.5)
    port.cut = True
    t0 = clock.now()
    with pytest.raises(LidarTimeout, match="GET_HEALTH"):
        drv.get_health()
    assert clock.now() - t0 == pytest.approx(0.3)
    with pytest.raises(LidarTimeout):
        drv.start_scan()
    port.cut = False
    drv.start_scan()
    drv.read_revolutions(1, timeout=1.0)
    lidar.motor_on = False  # the motor stalls: nothing more arrives
    with pytest.raises(LidarTimeout, match="nothing received"):
        for _ in range(10):
            drv.poll(clock.now() + 0.2)
    with pytest.raises(LidarTimeout):
        drv.read_revolutions(1, timeout=0.1)
    assert drv.stats.timeouts >= 3
    drv.close()


def test_protocol_errors() -> None:
    clock = SimClock()
    bad_health = lp.encode_descriptor(2, 0, lp.AnswerType.DEVICE_HEALTH) + b"\x00\x00"
    drv = LidarDriver(InProcessPort(lambda data: bad_health), clock, timeout=0.2)
    with pytest.raises(LidarProtocolError):
        drv.get_health()
    drv = LidarDriver(
        InProcessPort(lambda data: lp.encode_descriptor(20, 0, 4) if data[1:2] == b"\x20" else b""), clock
    )
    with pytest.raises(LidarProtocolError):
        drv.start_scan()
    assert drv.stats.protocol_errors == 1


def test_inproc_disconnect_and_reconnect() -> None:
    clock = SimClock()
    lidar = make_lidar(now=clock.now())
    ports: list[InProcessPort] = []

    def opener() -> InProcessPort:
        ports.append(lidar.in_process_port(clock))
        return ports[-1]

    drv = LidarDriver(opener(), clock, opener=opener)
    drv.start_scan()
    ports[0].close()
    with pytest.raises(LidarDisconnected):
        drv.poll(clock.now() + 0.1)
    assert not drv.scanning
    drv.reconnect()
    drv.start_scan()
    check_turn(drv.read_revolutions(1, timeout=1.0)[0])
    assert drv.stats.reconnects == 1
    drv.close()
    drv.close()  # idempotent


def test_tcp_device_restart_and_reconnect() -> None:
    """The lidar's server goes away mid-scan (a USB adapter unplugged); a new one takes the port."""
    with serve_lidar("tcp") as (server, url):
        drv = LidarDriver.open(url, SystemClock())
        drv.start_scan()
        drv.read_revolutions(1, timeout=2.0)
        port = server.port
        server.stop()
        with pytest.raises(LidarDisconnected):
            for _ in range(50):
                drv.poll(SystemClock().now() + 0.1)
    assert port is not None
    with serve_lidar("tcp", port=port):
        drv.reconnect()
        assert drv.get_health().ok
        drv.start_scan()
        check_turn(drv.read_revolutions(1, timeout=2.0)[0])
        drv.close()
    with pytest.raises(LidarDisconnected):
        LidarDriver.open("socket://127.0.0.1:1", SystemClock())


def test_angles_are_counter_clockwise_in_the_sensor_frame() -> None:
    """A wall 1 m to the robot's left (+y in the sensor frame) shows up at +pi/2."""
    clock = SimClock()
    segment = np.array([(-5.0, 1.0, 5.0, 1.0)])
    model = LidarModel(LidarConfig(rate_hz=RATE_HZ).noiseless(), np.random.default_rng(0))
    source = scan_source_for(model, lambda t: (0.0, 0.0, 0.0), Raycaster(segment))
    lidar = SimulatedRplidar(model.config, source, now=0.0)
    with LidarDriver(lidar.in_process_port(clock), clock) as drv:
        drv.start_scan()
        rev = drv.read_revolutions(1, timeout=1.0)[0]
    left = int(np.argmin(np.abs(rev.angles_rad - math.pi / 2)))
    right = int(np.argmin(np.abs(rev.angles_rad - 3 * math.pi / 2)))
    assert rev.distances_m[left] == pytest.approx(1.0, abs=1e-3)
    assert rev.distances_m[right] == 0.0  # nothing on the right within range


def test_inproc_scan_modes_and_fallback_for_old_firmware() -> None:
    clock = SimClock(start=1.0)
    lidar = make_lidar(now=clock.now())
    with LidarDriver(lidar.in_process_port(clock), clock) as drv:
        modes = drv.get_scan_modes()
        assert [(m.id, m.name, m.answer_type) for m in modes] == [(0, "Standard", 0x81), (1, "Express", 0x82)]
        assert modes[1].us_per_sample == 125.0 and modes[1].max_distance_m == 12.0
        assert drv.get_typical_mode() == 1
        with pytest.raises(LidarTimeout):
            drv.get_lidar_conf(0x01)  # not an A1's entry: no answer
    # firmware before 1.24 does not answer GET_LIDAR_CONF: the driver waits conf_timeout, then SCAN
    old = SimulatedRplidar(lidar.lidar, lidar.scan_source, RplidarConfig(conf_commands=False, firmware=(1, 20)))
    with LidarDriver(old.in_process_port(clock), clock, conf_timeout=0.2) as drv:
        t0 = clock.now()
        assert drv.start_scan() == lp.SCAN_DESCRIPTOR
        assert clock.now() - t0 == pytest.approx(0.2, abs=0.01) and drv.stats.conf_unanswered == 1
        assert drv.mode is None and not old.express
        check_turn(drv.read_revolutions(1, timeout=1.0)[0])
    # forced choices
    for choice, wanted in (("standard", lp.SCAN_DESCRIPTOR), ("express", lp.EXPRESS_DESCRIPTOR)):
        with LidarDriver(lidar.in_process_port(clock), clock, scan_mode=choice) as drv:  # type: ignore[arg-type]
            assert drv.start_scan() == wanted
            check_turn(drv.read_revolutions(1, timeout=1.0)[0])
    with pytest.raises(ValueError):
        LidarDriver(lidar.in_process_port(clock), clock, scan_mode="boost")  # type: ignore[arg-type]


def test_conf_answer_for_another_entry_is_a_protocol_error() -> None:
    clock = SimClock()
    wrong = lp.encode_lidar_conf(lp.ConfType.SCAN_MODE_COUNT, b"\x02\x00")
    drv = LidarDriver(InProcessPort(lambda data: wrong if data[1:2] == b"\x84" else b""), clock, timeout=0.2)
    with pytest.raises(LidarProtocolError, match="0x70"):
        drv.get_lidar_conf(lp.ConfType.SCAN_MODE_TYPICAL)
    short = lp.encode_lidar_conf(lp.ConfType.SCAN_MODE_TYPICAL, b"\x01")
    drv = LidarDriver(InProcessPort(lambda data: short if data[1:2] == b"\x84" else b""), clock, timeout=0.2)
    with pytest.raises(LidarProtocolError, match="need 2"):
        drv.get_typical_mode()


def test_inproc_express_scan_is_deterministic() -> None:
    def run() -> list[lp.Revolution]:
        clock = SimClock(start=3.0)
        model = LidarModel(LidarConfig(rate_hz=5.5), np.random.default_rng(11))  # noise and random phase
        lidar = SimulatedRplidar(model.config, scan_source_for(model, lambda t: POSE, Raycaster(ROOM)), now=3.0)
        with LidarDriver(lidar.in_process_port(clock), clock) as drv:
            drv.start_scan()
            return drv.read_revolutions(4, timeout=3.0)

    a, b = run(), run()
    assert [len(r) for r in a] == [len(r) for r in b] and all(1450 <= len(r) <= 1460 for r in a)
    for ra, rb in zip(a, b, strict=True):
        assert np.array_equal(ra.angles_rad, rb.angles_rad) and np.array_equal(ra.distances_m, rb.distances_m)
        assert ra.stamp == rb.stamp
