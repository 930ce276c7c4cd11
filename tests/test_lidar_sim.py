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


def conf(dev: SimulatedRplidar, entry: int, mode: int | None = None) -> lp.LidarConf | None:
    events = decode(dev.receive(lp.encode_conf_request(entry, mode), 0.0))
    got = [e for e in events if isinstance(e, lp.LidarConf)]
    return got[0] if got else None


def test_lidar_conf_describes_the_scan_modes() -> None:
    dev = device()
    c = lp.ConfType
    assert conf(dev, c.SCAN_MODE_COUNT) == lp.LidarConf(0x70, b"\x02\x00")
    assert conf(dev, c.SCAN_MODE_TYPICAL) == lp.LidarConf(0x7C, b"\x01\x00")  # "Express"
    for mode, name, ans in ((0, "Standard", 0x81), (1, "Express", 0x82)):
        assert conf(dev, c.SCAN_MODE_NAME, mode) == lp.LidarConf(0x7F, name.encode() + b"\x00")
        assert conf(dev, c.SCAN_MODE_ANS_TYPE, mode) == lp.LidarConf(0x75, bytes((ans,)))
        us = conf(dev, c.SCAN_MODE_US_PER_SAMPLE, mode)
        assert us is not None and us.u32() == 125 * 256  # Q8: the model's 8000 samples/s
        dist = conf(dev, c.SCAN_MODE_MAX_DISTANCE, mode)
        assert dist is not None and dist.q8() == 12.0
    assert dev.stats.bad_requests == 0


def test_lidar_conf_it_cannot_answer(caplog: pytest.LogCaptureFixture) -> None:
    dev = device()
    assert conf(dev, 0x01) is None  # DESIRED_ROT_FREQ: an A1 has no motor controller
    assert conf(dev, 0x01) is None
    assert conf(dev, lp.ConfType.SCAN_MODE_NAME, 2) is None  # no mode 2
    assert conf(dev, lp.ConfType.SCAN_MODE_NAME) is None  # no mode id at all
    assert dev.receive(lp.encode_request(lp.Command.GET_LIDAR_CONF, b"\x70"), 0.0) == b""
    assert dev.stats.bad_requests == 5
    assert sum("entry 0x1," in r.message for r in caplog.records) == 1  # logged once, then counted
    assert conf(dev, lp.ConfType.SCAN_MODE_COUNT) is not None  # and it keeps serving
    old = device(conf_commands=False, firmware=(1, 20))
    assert conf(old, lp.ConfType.SCAN_MODE_COUNT) is None and old.stats.ignored == 1


def test_express_scan_streams_paced_capsules() -> None:
    dev = device(motor_on_at_start=True)
    assert dev.receive(lp.encode_express_request(1), 1.0) == lp.EXPRESS_DESCRIPTOR.encode()
    assert dev.scanning and dev.express and dev.mode.name == "Express"
    stream = b""
    t = 1.0
    while t < 1.5:
        t += 0.01
        stream += dev.step(t) or b""
    # a capsule goes out when its 32nd sample is due: 8000 samples/s from 1.002 s
    assert len(stream) // 84 == int(8000 * 0.498) // 32 == dev.stats.capsules
    assert len(stream) % 84 == 0 and stream[3] & 0x80  # the first capsule opens the session
    dec = lp.LidarDecoder(batch=True)
    dec.assume(lp.EXPRESS_DESCRIPTOR)
    revs = lp.RevolutionAssembler().push_all(dec.feed(stream))
    assert [len(r) for r in revs] == [N] * 3  # 5 turns started; the first ends in a wrap only at the 2nd
    np.testing.assert_allclose(revs[0].distances_m, DISTANCES, atol=5e-4)  # whole millimetres
    # legacy working mode 0 is the express scan too; STOP ends it
    assert dev.receive(lp.encode_express_request(0), 2.0) == lp.EXPRESS_DESCRIPTOR.encode()
    dev.receive(lp.encode_request(lp.Command.STOP), 2.0)
    assert dev.step(2.5) is None and not dev.scanning


def test_scan_modes_set_the_pace_and_samplerate() -> None:
    modes = (
        lp.ScanMode(0, "Standard", 500.0, 12.0, 0x81),
        lp.ScanMode(1, "Express", 250.0, 12.0, 0x82),
    )
    dev = device(motor_on_at_start=True, scan_modes=modes)
    assert decode(dev.receive(lp.encode_request(lp.Command.GET_SAMPLERATE), 0.0))[1] == lp.SampleRate(500, 250)
    dev.receive(lp.encode_request(lp.Command.SCAN), 0.0)
    assert len(dev.step(0.502) or b"") // 5 == 1001  # 2000 samples/s from 2 ms
    dev.receive(lp.encode_express_request(1), 1.0)
    assert len(dev.step(1.514) or b"") // 84 == 2001 // 32  # 4000 samples/s
    with pytest.raises(ValueError):
        RplidarConfig(scan_modes=modes[1:])  # ids must count from 0
    with pytest.raises(ValueError):
        RplidarConfig(scan_modes=modes, typical_mode=2)


def test_motor_at_start() -> None:
    from fleetlink.field.rplidar import motor_at_start

    assert motor_at_start("auto", served=True) and not motor_at_start("auto", served=False)
    assert motor_at_start("running", served=False) and not motor_at_start("stopped", served=True)
    dev = device(motor_on_at_start=True)
    dev.receive(lp.encode_express_request(0), 0.0)
    assert dev.step(0.1)
    dev.receive(lp.encode_request(lp.Command.SET_MOTOR_PWM, b"\x00\x00"), 0.1)  # PWM 0 stops it
    assert dev.step(0.5) is None and not dev.motor_on
