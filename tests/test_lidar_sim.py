"""The simulated RPLIDAR (field.rplidar) driven with raw bytes: answers, pacing, motor, health."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fleetlink.devices.rplidar import protocol as lp
from fleetlink.field.lidar import LidarConfig
from fleetlink.field.rplidar import FixedScan, RplidarConfig, SimulatedRplidar

N = 800  # samples per turn: 8000 samples/s at 10 Hz
ANGLES = np.arange(N) * 2 * math.pi / N
DISTANCES = 1.0 + 0.5 * np.sin(ANGLES)
SOURCE = FixedScan(ANGLES, DISTANCES, np.full(N, 40, np.uint8))
LIDAR = LidarConfig(rate_hz=10.0)


def device(**kw: object) -> SimulatedRplidar:
    return SimulatedRplidar(LIDAR, SOURCE, RplidarConfig(**kw), now=0.0)  # type: ignore[arg-type,unused-ignore]


def decode(data: bytes, scanning: bool = False) -> list[lp.Event]:
    dec = lp.LidarDecoder()
    if scanning:
        dec.assume(lp.SCAN_DESCRIPTOR)
    return dec.feed(data)


def test_answers() -> None:
    dev = device()
    out = dev.receive(lp.encode_request(lp.Command.GET_INFO) + lp.encode_request(lp.Command.GET_HEALTH), 0.0)
    out += dev.receive(lp.encode_request(lp.Command.GET_SAMPLERATE), 0.0)
    events = decode(out)
    assert events[1] == lp.DeviceInfo(0x18, (1, 29), 7, b"FLK-RPLIDAR-A1\x00\x01")
    assert events[3] == lp.DeviceHealth(lp.HEALTH_GOOD, 0)
    assert events[5] == lp.SampleRate(125, 125)
    dev.health = lp.DeviceHealth(lp.HEALTH_ERROR, 0x8001)
    assert decode(dev.receive(lp.encode_request(lp.Command.GET_HEALTH), 0.0))[1] == lp.DeviceHealth(2, 0x8001)


def test_scan_streams_paced_nodes_with_start_flags() -> None:
    dev = device(motor_on_at_start=True)
    assert dev.receive(lp.encode_request(lp.Command.SCAN), 1.0) == lp.SCAN_DESCRIPTOR.encode()
    assert dev.step(1.001) is None  # first node 2 ms after the answer
    stream = b""
    t = 1.0
    while t < 1.5:
        t += 0.01
        stream += dev.step(t) or b""
    nodes = lp.RevolutionAssembler()
    dec = lp.LidarDecoder(batch=True)
    dec.assume(lp.SCAN_DESCRIPTOR)
    events = dec.feed(stream)
    total = sum(len(e) for e in events if isinstance(e, lp.NodeBatch))
    assert total == pytest.approx(8000 * 0.498, abs=2)  # paced at samples_per_second
    revs = nodes.push_all(events)
    assert len(revs) == 4  # 5 turns started in 0.5 s at 10 Hz; the last is incomplete
    rev = revs[0]
    assert len(rev) == N
    np.testing.assert_allclose(rev.angles_rad, ANGLES, atol=math.radians(1 / 64))
    np.testing.assert_allclose(rev.distances_m, DISTANCES, atol=1.25e-4)
    assert np.all(rev.qualities == 40)
    # wire angles grow clockwise: after 0 deg comes 0.45 deg clockwise, the last counter-clockwise sample
    first = lp.LidarDecoder()
    first.assume(lp.SCAN_DESCRIPTOR)
    n0, n1 = first.feed(stream[:10])
    assert isinstance(n0, lp.Node) and isinstance(n1, lp.Node)
    assert n0.start and n0.angle_deg == 0.0 and n0.distance_m == pytest.approx(DISTANCES[0], abs=1.25e-4)
    assert not n1.start and n1.angle_deg == pytest.approx(0.45, abs=1 / 64)
    assert n1.distance_m == pytest.approx(DISTANCES[-1], abs=1.25e-4)


def test_stop_and_other_requests_end_the_scan() -> None:
    dev = device(motor_on_at_start=True)
    dev.receive(lp.encode_request(lp.Command.SCAN), 0.0)
    assert dev.step(0.1)
    assert dev.receive(lp.encode_request(lp.Command.STOP), 0.1) == b""
    assert dev.step(0.2) is None and not dev.scanning
    dev.receive(lp.encode_request(lp.Command.FORCE_SCAN), 0.2)
    assert dev.step(0.3)
    out = dev.receive(lp.encode_request(lp.Command.GET_HEALTH), 0.3)
    assert decode(out)[1] == lp.DeviceHealth(0, 0) and not dev.scanning
    assert dev.step(0.4) is None


def test_motor_gates_the_stream() -> None:
    dev = device(spinup_s=0.5)
    dev.receive(lp.encode_request(lp.Command.SCAN), 0.0)
    assert dev.step(0.3) is None  # motor off: the A1 default until DTR goes low
    dev.receive(lp.encode_request(lp.Command.SET_MOTOR_PWM, (660).to_bytes(2, "little")), 0.3)
    assert dev.motor_on and dev.pwm == 660
    assert dev.step(0.79) is None  # spinning up
    out = dev.step(0.9)
    assert out is not None and out[0] & 1  # a fresh turn: the first node has the start flag
    assert len(out) // 5 == pytest.approx(8000 * 0.1, abs=2)
    dev.receive(lp.encode_request(lp.Command.SET_MOTOR_PWM, b"\x00\x00"), 0.9)
    assert dev.step(1.5) is None
    dev.set_dtr(False)  # DTR low: motor on
    assert dev.motor_on and dev.step(1.9) is None and dev.step(2.1)
    dev.set_dtr(True)
    assert not dev.motor_on


def test_force_scan_skips_spinup_and_health_error_stops_data() -> None:
    dev = device(spinup_s=0.5, motor_on_at_start=True)
    dev.receive(lp.encode_request(lp.Command.FORCE_SCAN), 0.0)
    assert dev.step(0.1)
    dev.health = lp.DeviceHealth(lp.HEALTH_ERROR, 1)
    assert dev.step(0.2) is None


def test_ignored_commands_and_reset_banner() -> None:
    dev = device(motor_on_at_start=True)
    assert dev.receive(lp.encode_express_request(5), 0.0) == b""  # no such scan mode
    assert dev.receive(lp.encode_request(lp.Command.EXPRESS_SCAN), 0.0) == b""  # no working mode
    assert dev.stats.bad_requests == 2
    assert dev.receive(lp.encode_request(lp.Command.GET_ACC_BOARD_FLAG, bytes(4)), 0.0) == b""
    assert dev.receive(b"\xa5\x19", 0.0) == b""  # unknown
    assert dev.stats.ignored == 2 and not dev.scanning
    assert dev.receive(lp.encode_request(lp.Command.RESET), 0.0) == b""
    loud = device(boot_banner=True)
    assert loud.receive(lp.encode_request(lp.Command.RESET), 0.0).startswith(b"RP LIDAR System.\r\nFirmware Ver 1.29")


def test_requests_split_across_calls() -> None:
    dev = device()
    req = lp.encode_request(lp.Command.SET_MOTOR_PWM, (500).to_bytes(2, "little")) + lp.encode_request(
        lp.Command.GET_INFO
    )
    out = b""
    for i in range(len(req)):
        out += dev.receive(req[i : i + 1], 0.0)
    assert dev.pwm == 500 and isinstance(decode(out)[1], lp.DeviceInfo)


def test_stall_backlog_is_skipped_and_start_clock() -> None:
    dev = device(motor_on_at_start=True, max_backlog_s=0.2)
    dev.receive(lp.encode_request(lp.Command.SCAN), 0.0)
    out = dev.step(10.0)
    assert out is not None and len(out) // 5 == pytest.approx(8000 * 0.2, abs=2)
    assert dev.stats.skipped_s == pytest.approx(10.0 - 0.2 - 0.002)
    dev.start_clock(50.0)
    out = dev.step(50.05)
    assert out is not None and len(out) // 5 == pytest.approx(400, abs=2)


def test_empty_turns_pass_in_silence() -> None:
    calls: list[float] = []

    def nothing(now: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        calls.append(now)
        return np.zeros(0), np.zeros(0), np.zeros(0, np.uint8)

    dev = SimulatedRplidar(LIDAR, nothing, RplidarConfig(motor_on_at_start=True))
    dev.receive(lp.encode_request(lp.Command.SCAN), 0.0)
    assert dev.step(0.5) is None
    assert 4 <= len(calls) <= 6  # one attempt per (empty) turn at 10 Hz, not a busy loop
