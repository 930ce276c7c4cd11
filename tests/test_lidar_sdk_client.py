"""The simulated RPLIDAR A1 as SLAMTEC's own SDK sees it, over TCP and over a pty.

``SdkClient`` below is written to SLAMTEC's published protocol and follows the sequence of
rplidar_sdk 2.x (``sl_lidar_driver.cpp``: ``connect``, ``getDeviceInfo``, ``getHealth``,
``getAllSupportedScanModes``, ``startScan(false, true)`` = the typical mode through
``startScanExpress``, ``grabScanDataHq``, ``stop``, ``reset``). It uses none of fleetlink's codec:
requests, descriptors, GET_LIDAR_CONF and the capsule decoder are its own small code, with the
SDK's integer arithmetic (``handler_capsules.cpp``: angles interpolated between a capsule's start
angle and the next capsule's, the per-sample offsets subtracted, a revolution flagged where the
uncompensated angle crosses 360 degrees), so what it reads checks the simulator against the
protocol rather than against fleetlink's own decoder.

The lidar is served by ``field.device_server.DeviceServer`` in real time; rates are checked from
the samples' count and the scan mode's µs per sample, as the SDK's ``getFrequency`` does, never
from wall-clock timing.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import math
import os
import select
import socket
import struct
import termios
import time
import tty
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from fleetlink.field.device_server import DeviceServer
from fleetlink.field.lidar import LidarConfig, LidarModel, scan_source_for
from fleetlink.field.plans import load_plan
from fleetlink.field.raycast import Raycaster
from fleetlink.field.rplidar import RplidarConfig, SimulatedRplidar, motor_at_start
from fleetlink.shared.clock import SystemClock

# -- the client: SLAMTEC's protocol, its own code --------------------------------------------------

CMD_STOP, CMD_RESET, CMD_GET_INFO, CMD_GET_HEALTH, CMD_GET_SAMPLERATE = 0x25, 0x40, 0x50, 0x52, 0x59
CMD_EXPRESS_SCAN, CMD_GET_LIDAR_CONF = 0x82, 0x84
ANS_DEVINFO, ANS_HEALTH, ANS_SAMPLERATE, ANS_CONF, ANS_CAPSULED = 0x04, 0x06, 0x15, 0x20, 0x82
CONF_DESIRED_ROT_FREQ = 0x01
CONF_COUNT, CONF_US_PER_SAMPLE, CONF_MAX_DISTANCE, CONF_ANS_TYPE, CONF_TYPICAL, CONF_NAME = (
    0x70,
    0x71,
    0x74,
    0x75,
    0x7C,
    0x7F,
)


class Unanswered(Exception):
    pass


@dataclass
class Mode:
    id: int
    name: str
    us_per_sample: float
    max_distance: float
    ans_type: int


@dataclass
class HqNode:
    angle_q6: int
    dist_q2: int
    quality: int
    sync: bool


class Wire:
    """Bytes both ways over a TCP socket or a pty's fd; reads wait with select (real time)."""

    def __init__(self, sock: socket.socket | None = None, fd: int | None = None) -> None:
        self.sock, self.fd = sock, fd
        self.buf = bytearray()

    def write(self, data: bytes) -> None:
        if self.sock is not None:
            self.sock.sendall(data)
        else:
            assert self.fd is not None
            os.write(self.fd, data)

    def fill(self, timeout: float) -> bool:
        handle = self.sock if self.sock is not None else self.fd
        assert handle is not None
        ready, _, _ = select.select([handle], [], [], timeout)
        if not ready:
            return False
        data = self.sock.recv(65536) if self.sock is not None else os.read(self.fd, 65536)  # type: ignore[arg-type]
        self.buf += data
        return bool(data)

    def take(self, n: int, timeout: float) -> bytes:
        end = time.monotonic() + timeout
        while len(self.buf) < n:
            left = end - time.monotonic()
            if left <= 0 or not self.fill(left):
                raise Unanswered(f"{len(self.buf)} of {n} bytes")
        out = bytes(self.buf[:n])
        del self.buf[:n]
        return out

    def drain(self, quiet: float) -> int:
        """Discard bytes until the line has been quiet for ``quiet`` seconds; how many came."""
        n = len(self.buf)
        self.buf.clear()
        while self.fill(quiet):
            n += len(self.buf)
            self.buf.clear()
        return n

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        if self.fd is not None:
            os.close(self.fd)


class SdkClient:
    """The parts of SLAMTEC's SDK that start an A1 in its typical mode and read revolutions."""

    def __init__(self, wire: Wire, timeout: float = 2.0) -> None:
        self.wire = wire
        self.timeout = timeout
        # the capsule decoder's state (UnpackerHandler_CapsuleNode)
        self.prev: bytes | None = None
        self.checksum_errors = 0
        self.scans: list[list[HqNode]] = []
        self._scan: list[HqNode] | None = None

    # requests and answers (sl_lidar_driver.cpp: _sendCommand, _waitResponseHeader)
    def send(self, cmd: int, payload: bytes = b"") -> None:
        pkt = bytes([0xA5, cmd])
        if cmd & 0x80:
            pkt += bytes([len(payload)]) + payload
            cs = 0
            for b in pkt:
                cs ^= b
            pkt += bytes([cs])
        self.wire.write(pkt)

    def header(self, timeout: float) -> tuple[int, int, int]:
        end = time.monotonic() + timeout
        while True:  # look for A5 5A, as _waitResponseHeader does
            b = self.wire.take(1, max(0.0, end - time.monotonic()))
            if b[0] != 0xA5:
                continue
            if self.wire.take(1, max(0.0, end - time.monotonic()))[0] != 0x5A:
                continue
            rest = self.wire.take(5, max(0.0, end - time.monotonic()))
            word = int.from_bytes(rest[:4], "little")
            return word & 0x3FFFFFFF, word >> 30, rest[4]

    def request(self, cmd: int, ans_type: int, payload: bytes = b"", timeout: float | None = None) -> bytes:
        self.send(cmd, payload)
        size, mode, kind = self.header(self.timeout if timeout is None else timeout)
        assert (mode, kind) == (0, ans_type), f"answer to 0x{cmd:02X}: mode {mode}, type 0x{kind:02X}"
        return self.wire.take(size, self.timeout)

    def get_lidar_conf(self, conf: int, mode: int | None = None, timeout: float | None = None) -> bytes:
        payload = struct.pack("<I", conf) + (b"" if mode is None else struct.pack("<H", mode))
        ans = self.request(CMD_GET_LIDAR_CONF, ANS_CONF, payload, timeout)
        assert len(ans) >= 4 and struct.unpack("<I", ans[:4])[0] == conf  # the type is echoed
        return ans[4:]

    # the SDK's calls
    def get_device_info(self) -> tuple[int, int, int, bytes]:
        ans = self.request(CMD_GET_INFO, ANS_DEVINFO)
        model, fw, hw = struct.unpack("<BHB", ans[:4])
        return model, fw, hw, ans[4:20]

    def get_health(self) -> tuple[int, int]:
        status, code = struct.unpack("<BH", self.request(CMD_GET_HEALTH, ANS_HEALTH))
        return status, code

    def check_support_config_commands(self) -> bool:
        _, fw, _, _ = self.get_device_info()
        return fw >= (1 << 8 | 24)

    def get_scan_mode(self, mode_id: int) -> Mode:
        us = struct.unpack("<I", self.get_lidar_conf(CONF_US_PER_SAMPLE, mode_id)[:4])[0] / 256.0
        dist = float(struct.unpack("<I", self.get_lidar_conf(CONF_MAX_DISTANCE, mode_id)[:4])[0] >> 8)
        ans = self.get_lidar_conf(CONF_ANS_TYPE, mode_id)[0]
        name = self.get_lidar_conf(CONF_NAME, mode_id).split(b"\0")[0].decode()
        return Mode(mode_id, name, us, dist, ans)

    def get_all_supported_scan_modes(self) -> list[Mode]:
        assert self.check_support_config_commands()
        count = struct.unpack("<H", self.get_lidar_conf(CONF_COUNT)[:2])[0]
        return [self.get_scan_mode(i) for i in range(count)]

    def get_typical_scan_mode(self) -> int:
        return int(struct.unpack("<H", self.get_lidar_conf(CONF_TYPICAL)[:2])[0])

    def start_motor(self, dtr: Wire) -> bool:
        """setMotorSpeed(DEFAULT_MOTOR_SPEED) on an A1 (no motor controller): the SDK asks for the
        desired speed, then can only set DTR on a serial port. Returns whether DTR could be set."""
        with contextlib.suppress(Unanswered):
            self.get_lidar_conf(CONF_DESIRED_ROT_FREQ, timeout=0.2)  # an A1 does not answer it
        if dtr.fd is None:
            return False  # a TCP channel has no DTR at all
        try:
            fcntl.ioctl(dtr.fd, termios.TIOCMBIC, struct.pack("I", termios.TIOCM_DTR))  # DTR low: motor on
        except OSError as exc:
            assert exc.errno in (errno.ENOTTY, errno.EINVAL, errno.ENOTSUP)
            return False
        return True

    def stop(self) -> None:
        self.send(CMD_STOP)
        self.wire.drain(0.1)

    def start_scan_express(self, mode: Mode, dtr: Wire) -> bool:
        """startScanExpress: STOP, the mode's description, the motor, EXPRESS_SCAN with the mode's
        id as working mode, then the capsule stream's descriptor. Returns whether DTR was set."""
        self.stop()
        assert mode.ans_type == ANS_CAPSULED
        dtr_set = self.start_motor(dtr)
        self.prev, self._scan, self.scans = None, None, []
        self.send(CMD_EXPRESS_SCAN, struct.pack("<BHH", mode.id, 0, 0))
        size, send_mode, kind = self.header(self.timeout)
        assert (size, send_mode, kind) == (84, 1, ANS_CAPSULED)
        return dtr_set

    # the capsule decoder, byte by byte as UnpackerHandler_CapsuleNode::onData
    def on_data(self, data: bytes) -> None:
        for byte in data:
            self._cap += bytes([byte])
            wanted_nibble = {1: 0xA, 2: 0x5}.get(len(self._cap))
            if wanted_nibble is not None and byte >> 4 != wanted_nibble:  # the sync nibbles
                self._cap = b""
                self.prev = None
            elif len(self._cap) == 84:
                cap, self._cap = self._cap, b""
                cs = 0
                for b in cap[2:]:
                    cs ^= b
                if cs != ((cap[0] & 0xF) | (cap[1] << 4)) & 0xFF:
                    self.checksum_errors += 1
                    self.prev = None
                    continue
                if struct.unpack("<H", cap[2:4])[0] & 0x8000:
                    self.prev = None  # a new scan session: drop what came before
                    self._scan = None
                self._on_capsule(cap)

    _cap = b""

    def _on_capsule(self, cap: bytes) -> None:
        prev = self.prev
        self.prev = cap
        if prev is None:
            return
        cur_q8 = (struct.unpack("<H", cap[2:4])[0] & 0x7FFF) << 2
        prev_q8 = (struct.unpack("<H", prev[2:4])[0] & 0x7FFF) << 2
        diff_q8 = cur_q8 - prev_q8
        if prev_q8 > cur_q8:
            diff_q8 += 360 << 8
        inc_q16 = diff_q8 << 3
        raw_q16 = prev_q8 << 8
        for c in range(16):
            d1, d2, offs = struct.unpack("<HHB", prev[4 + 5 * c : 9 + 5 * c])
            for dist_angle, off in ((d1, (offs & 0xF) | ((d1 & 0x3) << 4)), (d2, (offs >> 4) | ((d2 & 0x3) << 4))):
                angle_q6 = (raw_q16 - (off << 13)) >> 10
                sync = ((raw_q16 + inc_q16) % (360 << 16)) < inc_q16
                raw_q16 += inc_q16
                if angle_q6 < 0:
                    angle_q6 += 360 << 6
                if angle_q6 >= 360 << 6:
                    angle_q6 -= 360 << 6
                dist = dist_angle & 0xFFFC
                self._publish(HqNode(angle_q6, dist, 47 if dist else 0, sync))

    def _publish(self, node: HqNode) -> None:
        """The scan holder: a revolution runs from one sync flag to the next."""
        if node.sync:
            if self._scan is not None:
                self.scans.append(self._scan)
            self._scan = []
        if self._scan is not None:
            self._scan.append(node)

    def grab_scans(self, count: int, timeout: float) -> list[list[HqNode]]:
        end = time.monotonic() + timeout
        while len(self.scans) < count:
            left = end - time.monotonic()
            if left <= 0:
                raise Unanswered(f"{len(self.scans)} of {count} revolutions")
            if self.wire.fill(min(left, 0.2)):
                self.on_data(bytes(self.wire.buf))
                self.wire.buf.clear()
        return self.scans[:count]


# -- the field side ----------------------------------------------------------------------------------

POSE = (3.0, 2.5, 0.3)  # in the office plan, away from its walls


def served_lidar(rate_hz: float) -> tuple[SimulatedRplidar, Raycaster, LidarConfig]:
    plan = load_plan("office")
    raycaster = Raycaster(plan.segments())
    model = LidarModel(LidarConfig(rate_hz=rate_hz).noiseless(), np.random.default_rng(3))
    source = scan_source_for(model, lambda t: POSE, raycaster)
    config = RplidarConfig(motor_on_at_start=motor_at_start("auto", served=True))
    return SimulatedRplidar(model.config, source, config), raycaster, model.config


@contextlib.contextmanager
def connect(kind: str, lidar: SimulatedRplidar) -> Iterator[Wire]:
    server = DeviceServer(lidar, SystemClock(), step_hz=100, name="lidar")
    wire: Wire | None = None
    try:
        if kind == "tcp":
            port = server.serve_tcp()
            wire = Wire(sock=socket.create_connection(("127.0.0.1", port), timeout=2.0))
            wire.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # type: ignore[union-attr]
        else:
            fd = os.open(server.serve_pty(), os.O_RDWR | os.O_NOCTTY)
            tty.setraw(fd)
            wire = Wire(fd=fd)
        yield wire
    finally:
        if wire is not None:
            wire.close()
        server.stop()


@pytest.mark.parametrize(("kind", "rate_hz"), [("tcp", 10.0), ("pty", 5.5)])
def test_sdk_sequence_reads_full_revolutions(kind: str, rate_hz: float) -> None:
    lidar, raycaster, cfg = served_lidar(rate_hz)
    with connect(kind, lidar) as wire:
        sdk = SdkClient(wire)
        # connect(): checkMotorCtrlSupport reads the device info; model 0x18 = A1, no motor controller
        model, fw, hw, _serial = sdk.get_device_info()
        assert (model, fw >> 8, fw & 0xFF, hw) == (0x18, 1, 29, 7)
        assert sdk.get_health() == (0, 0)
        modes = sdk.get_all_supported_scan_modes()
        us = 1e6 / cfg.samples_per_second
        assert [(m.id, m.name, m.ans_type) for m in modes] == [(0, "Standard", 0x81), (1, "Express", 0x82)]
        assert all(m.us_per_sample == pytest.approx(us, abs=1 / 256) and m.max_distance == 12.0 for m in modes)
        typical = sdk.get_typical_scan_mode()
        assert typical == 1
        std_us, exp_us = struct.unpack("<HH", sdk.request(CMD_GET_SAMPLERATE, ANS_SAMPLERATE))
        assert std_us == exp_us == round(us)

        # startScan(false, true): the typical mode through startScanExpress
        mode = sdk.get_scan_mode(typical)
        assert not sdk.start_scan_express(mode, wire)  # DTR cannot be set over TCP or a pty ...
        assert lidar.motor_on  # ... and the served A1's motor runs anyway
        scans = sdk.grab_scans(3, timeout=5.0)

        n = math.ceil(cfg.samples_per_second / cfg.rate_hz - 1e-9)  # the model's turn, phase 0
        step = 2 * math.pi * cfg.rate_hz / cfg.samples_per_second
        ideal = np.arange(n) * step
        expected = raycaster.cast(POSE[0], POSE[1], ideal + POSE[2], cfg.max_range)
        expected = np.where(np.isfinite(expected), expected, 0.0)
        wire_q6 = np.rint(np.degrees(-ideal) % 360.0 * 64).astype(int) % (360 * 64)
        order = np.argsort(wire_q6, kind="stable")
        wire_deg, wire_dist = wire_q6[order] / 64.0, expected[order]
        for scan in scans:
            assert len(scan) == n  # samples per revolution
            frequency = 1e6 / (len(scan) * mode.us_per_sample)  # the SDK's getFrequency
            assert frequency == pytest.approx(cfg.rate_hz, rel=0.002)  # 5.5 Hz: 1455 samples, 5.498 Hz
            # The SDK's revolution is a run of consecutive samples of the stream, which sends each
            # turn in wire order (degrees clockwise): line it up with the model's turn in that order.
            angle = np.array([p.angle_q6 / 64.0 for p in scan])
            dist = np.array([p.dist_q2 / 4000.0 for p in scan])
            r = int(np.argmin(np.abs((angle[0] - wire_deg + 180.0) % 360.0 - 180.0)))
            ref_angle, ref_dist = np.roll(wire_deg, -r), np.roll(wire_dist, -r)
            err = np.abs((angle - ref_angle + 180.0) % 360.0 - 180.0)
            assert err.max() < 1 / 16 + 1 / 64 + 1e-9  # degrees: the offsets' 1/8 degree, floored to 1/64
            np.testing.assert_allclose(dist, ref_dist, atol=0.5e-3 + 1e-9)  # whole millimetres
            assert all((p.quality > 0) == (p.dist_q2 > 0) for p in scan)
        assert sdk.checksum_errors == 0

        sdk.stop()
        assert not lidar.scanning
        assert wire.drain(0.15) == 0  # nothing more after STOP
        sdk.send(CMD_RESET)
        assert wire.drain(0.15) == 0  # no banner by default
        assert sdk.get_health() == (0, 0)  # and it answers after the reset


def test_served_motor_stops_on_pwm_zero_and_runs_again() -> None:
    lidar, _, _ = served_lidar(10.0)
    with connect("tcp", lidar) as wire:
        sdk = SdkClient(wire)
        mode = sdk.get_scan_mode(sdk.get_typical_scan_mode())
        sdk.send(0xF0, struct.pack("<H", 0))  # SET_MOTOR_PWM 0: a served unit stops its motor
        sdk.start_scan_express(mode, wire)
        assert wire.drain(0.3) == 0 and not lidar.motor_on
        sdk.send(0xF0, struct.pack("<H", 660))
        assert len(sdk.grab_scans(1, timeout=3.0)[0]) == 800
        assert lidar.motor_on


def test_a_configured_stopped_motor_waits_for_pwm() -> None:
    lidar, _, _ = served_lidar(10.0)
    assert motor_at_start("auto", served=False) is False and motor_at_start("stopped", served=True) is False
    lidar.motor_on = False  # as RplidarConfig(motor_on_at_start=motor_at_start("stopped", True)) builds it
    with connect("pty", lidar) as wire:
        sdk = SdkClient(wire)
        mode = sdk.get_scan_mode(1)
        sdk.start_scan_express(mode, wire)
        assert wire.drain(0.3) == 0
        sdk.send(0xF0, struct.pack("<H", 500))
        assert len(sdk.grab_scans(1, timeout=3.0)[0]) == 800
