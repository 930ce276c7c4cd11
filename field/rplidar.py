"""The simulated RPLIDAR A1: the slave side of its serial protocol, sans-I/O.

``SimulatedRplidar(lidar_config, scan_source)`` takes request bytes in ``receive(data, now)`` and
returns the answer bytes; while it scans, ``step(now)`` returns the measurement nodes due since the
last call, paced at the ``LidarConfig``'s ``samples_per_second``. It plugs into
``field.device_server.DeviceServer`` (TCP or a pty, in real time) or, in one process, into
``fleetlink.devices.ports.InProcessPort`` (``in_process_port``: lockstep under a ``SimClock``).

Each revolution's data comes from ``scan_source(t)``, called when a turn begins at simulated time
``t`` and returning ``(angles_rad, distances_m, qualities)`` in the sensor frame (radians
counter-clockwise, as ``field.lidar.LidarModel.revolution`` returns them). The device converts to
the wire's convention (degrees clockwise), orders the turn by wire angle, sets the start flag on its
first node and streams it; the turn's length in samples sets the rotation rate.

Behaviour, command by command (``docs/protocols/rplidar.md`` has the table):

* STOP ``25``: stop streaming; no answer. RESET ``40``: the same, plus the boot banner if
  ``boot_banner`` is set (off by default; a real A1 prints one).
* SCAN ``20`` / FORCE_SCAN ``21``: answer ``A5 5A 05 00 00 40 81``, then nodes from
  ``first_node_delay`` later, starting with a fresh turn. No nodes while the motor is off, during
  ``spinup_s`` after it starts (FORCE_SCAN skips the wait), or while the health status is error.
* GET_INFO ``50``, GET_HEALTH ``52``, GET_SAMPLERATE ``59``: their answers. Any request other than
  SET_MOTOR_PWM ends a running scan first, so an answer is never buried in the node stream (masters,
  SLAMTEC's SDK included, always send STOP before other requests anyway).
* SET_MOTOR_PWM ``F0`` (payload u16): 0 stops the motor, anything else starts it. The A1 itself
  ignores this command (its motor is on DTR); the simulator honours it because DTR cannot travel
  over TCP or a pty. ``set_dtr(level)`` is the DTR line for in-process use: low (False) = motor on.
* EXPRESS_SCAN ``82``, GET_ACC_BOARD_FLAG ``FF`` and unknown commands: ignored, no answer.

Line rate: the stream is not throttled to 115200 baud. (At 8000 samples/s a standard SCAN needs
400 kbit/s; a real A1 reaches such rates only in express mode. The simulator keeps the simple node
format and the sample rate of the model.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from fleetlink.devices.ports import InProcessPort
from fleetlink.devices.rplidar.protocol import (
    ANGLE_Q,
    HEALTH_ERROR,
    HEALTH_GOOD,
    NODE_LEN,
    SCAN_DESCRIPTOR,
    SEND_MODE_SINGLE,
    AnswerType,
    Command,
    DeviceHealth,
    DeviceInfo,
    RequestDecoder,
    SampleRate,
    encode_descriptor,
    encode_device_info,
    encode_health,
    encode_nodes,
    encode_samplerate,
    rad_to_device_deg,
)
from fleetlink.field.lidar import LidarConfig
from fleetlink.shared.clock import Clock

__all__ = ["DeviceStats", "FixedScan", "RplidarConfig", "ScanSource", "SimulatedRplidar"]

ScanSource = Callable[[float], tuple[npt.ArrayLike, npt.ArrayLike, npt.ArrayLike]]

_FULL_TURN_Q6 = int(360 * ANGLE_Q)


@dataclass(frozen=True, slots=True)
class RplidarConfig:
    """Identity and behaviour of the simulated unit (defaults: an A1M8 as it reports itself).

    The sample rate and the rotation rate come from the ``LidarConfig`` the device is built with.
    """

    model: int = 0x18  # A1M8: series 1 (high nibble), sub-model 8
    firmware: tuple[int, int] = (1, 29)  # (major, minor)
    hardware: int = 7
    serial: bytes = b"FLK-RPLIDAR-A1\x00\x01"  # 16 bytes
    first_node_delay: float = 0.002  # s from the SCAN answer to the first node
    spinup_s: float = 0.0  # s from motor start until nodes flow (a real A1 takes about a second)
    motor_on_at_start: bool = False  # True for masters that only use DTR over TCP / a pty
    boot_banner: bool = False  # RESET answers with the A1's text banner
    max_backlog_s: float = 0.5  # after a longer stall of step(), the missed samples are skipped

    def __post_init__(self) -> None:
        if self.max_backlog_s <= 0.0 or self.first_node_delay < 0.0 or self.spinup_s < 0.0:
            raise ValueError("max_backlog_s must be positive, first_node_delay and spinup_s not negative")
        if len(self.serial) > 16:
            raise ValueError("the serial number has 16 bytes")

    def banner(self) -> bytes:
        major, minor = self.firmware
        return (
            f"RP LIDAR System.\r\nFirmware Ver {major}.{minor:02d} - rtm, HW Ver {self.hardware}\r\n"
            f"Model: {self.model:02X}\r\n"
        ).encode("ascii")


@dataclass(slots=True)
class DeviceStats:
    requests: int = 0
    ignored: int = 0  # express scans, unknown commands
    scans: int = 0  # SCAN / FORCE_SCAN accepted
    revolutions: int = 0  # turns fetched from the scan source
    nodes: int = 0  # nodes sent
    skipped_s: float = 0.0  # simulated time skipped after step() stalled


class SimulatedRplidar:
    """The lidar's firmware, as a sans-I/O device (``receive``/``step``/``start_clock``)."""

    def __init__(
        self,
        lidar: LidarConfig,
        scan_source: ScanSource,
        config: RplidarConfig | None = None,
        now: float = 0.0,
    ) -> None:
        """``lidar``: the sample and rotation rates (the model's config); ``scan_source(t)``: each
        turn's data; ``config``: identity and device behaviour."""
        self.lidar = lidar
        self.config = config or RplidarConfig()
        self.scan_source = scan_source
        self._sps = float(lidar.samples_per_second)
        self.health = DeviceHealth(HEALTH_GOOD, 0)
        self.stats = DeviceStats()
        self.pwm = 0
        self._decoder = RequestDecoder()
        self._now = now
        self._motor_on = self.config.motor_on_at_start
        self._motor_since = now
        self._scanning = False
        self._force = False
        # Pacing: sample i of the stream is due at _t0 + i / samples_per_second.
        self._t0 = now
        self._sent = 0
        self._turn = b""  # encoded nodes of the turn in progress
        self._turn_pos = 0  # nodes of it already sent

    # -- state -----------------------------------------------------------------------------------

    @property
    def scanning(self) -> bool:
        return self._scanning

    @property
    def motor_on(self) -> bool:
        return self._motor_on

    @motor_on.setter
    def motor_on(self, on: bool) -> None:
        self._set_motor(on, self._now)

    def set_dtr(self, level: bool) -> None:
        """The DTR line: low (False) starts the A1's motor, high stops it."""
        self._set_motor(not level, self._now)

    def info(self) -> DeviceInfo:
        cfg = self.config
        return DeviceInfo(cfg.model, cfg.firmware, cfg.hardware, bytes(cfg.serial[:16]).ljust(16, b"\x00"))

    def in_process_port(self, clock: Clock, *, advance_clock: bool = True, tick: float = 0.005) -> InProcessPort:
        """A master's port onto this device in the same process: requests answered at once, the
        scan stream stepped on every read, DTR forwarded (see ``InProcessPort``)."""
        return InProcessPort(
            lambda data: self.receive(data, clock.now()),
            stream=self.step,
            dtr=self.set_dtr,
            advance_clock=advance_clock,
            tick=tick,
        )

    def samplerate(self) -> SampleRate:
        us = max(1, round(1e6 / self._sps))
        return SampleRate(us, us)

    # -- the device protocol ---------------------------------------------------------------------

    def start_clock(self, now: float) -> None:
        """Set the time base before serving, without producing the samples of the time before it."""
        self._now = now
        self._motor_since = min(self._motor_since, now)
        if self._scanning:
            self._restart_stream(now)

    def receive(self, data: bytes, now: float) -> bytes:
        """Handle request bytes (any split); return the answer bytes."""
        self._now = max(self._now, now)
        out = bytearray()
        for req in self._decoder.feed(data):
            self.stats.requests += 1
            cmd = req.cmd
            if cmd == Command.SET_MOTOR_PWM:
                if len(req.payload) >= 2:
                    self.pwm = int.from_bytes(req.payload[:2], "little")
                    self._set_motor(self.pwm > 0, now)
                continue
            if cmd in (Command.SCAN, Command.FORCE_SCAN):
                self._scanning = True
                self._force = cmd == Command.FORCE_SCAN
                self._restart_stream(now + self.config.first_node_delay)
                self.stats.scans += 1
                out += SCAN_DESCRIPTOR.encode()
                continue
            if cmd not in (Command.STOP, Command.RESET, Command.GET_INFO, Command.GET_HEALTH, Command.GET_SAMPLERATE):
                self.stats.ignored += 1  # express scan, accessory-board flag, unknown
                continue
            self._scanning = False
            if cmd == Command.RESET and self.config.boot_banner:
                out += self.config.banner()
            elif cmd == Command.GET_INFO:
                out += encode_descriptor(20, SEND_MODE_SINGLE, AnswerType.DEVICE_INFO) + encode_device_info(self.info())
            elif cmd == Command.GET_HEALTH:
                out += encode_descriptor(3, SEND_MODE_SINGLE, AnswerType.DEVICE_HEALTH) + encode_health(self.health)
            elif cmd == Command.GET_SAMPLERATE:
                out += encode_descriptor(4, SEND_MODE_SINGLE, AnswerType.SAMPLE_RATE) + encode_samplerate(
                    self.samplerate()
                )
        return bytes(out)

    def step(self, now: float) -> bytes | None:
        """The nodes due by ``now`` while scanning (None when there are none)."""
        self._now = max(self._now, now)
        if not self._scanning or not self._motor_on or self.health.status == HEALTH_ERROR:
            return None
        cfg = self.config
        sps = self._sps
        ready = self._motor_since + (0.0 if self._force else cfg.spinup_s)
        if self._next_due() < ready:
            self._restart_stream(ready)  # the motor (re)started: a fresh turn once it is up to speed
        if now - self._next_due() > cfg.max_backlog_s:
            skip_to = now - cfg.max_backlog_s
            self.stats.skipped_s += skip_to - self._next_due()
            self._restart_stream(skip_to)
        out = bytearray()
        while True:
            due = self._next_due()
            if due > now:
                break
            if self._turn_pos * NODE_LEN >= len(self._turn):
                self._turn = self._fetch_turn(due)
                self._turn_pos = 0
                if not self._turn:
                    # Nothing to send this turn: let its time pass in silence.
                    self._restart_stream(due + 1.0 / self.lidar.rate_hz)
                    continue
            left = len(self._turn) // NODE_LEN - self._turn_pos
            k = min(left, math.floor((now - due) * sps + 1e-9) + 1)
            out += self._turn[self._turn_pos * NODE_LEN : (self._turn_pos + k) * NODE_LEN]
            self._turn_pos += k
            self._sent += k
        if not out:
            return None
        self.stats.nodes += len(out) // NODE_LEN
        return bytes(out)

    # -- internals -------------------------------------------------------------------------------

    def _set_motor(self, on: bool, now: float) -> None:
        if on and not self._motor_on:
            self._motor_since = now
        self._motor_on = on

    def _next_due(self) -> float:
        return self._t0 + self._sent / self._sps

    def _restart_stream(self, t: float) -> None:
        """Samples flow again from time ``t``, starting with a fresh turn."""
        self._t0 = t
        self._sent = 0
        self._turn = b""
        self._turn_pos = 0

    def _fetch_turn(self, t: float) -> bytes:
        angles, distances, qualities = self.scan_source(t)
        a = np.asarray(angles, dtype=np.float64).reshape(-1)
        if a.size == 0:
            return b""
        d = np.asarray(distances, dtype=np.float64).reshape(-1)
        q = np.asarray(qualities).reshape(-1)
        q6 = np.rint(rad_to_device_deg(a) * ANGLE_Q).astype(np.int64) % _FULL_TURN_Q6
        order = np.argsort(q6, kind="stable")
        self.stats.revolutions += 1
        return encode_nodes(q6[order] / ANGLE_Q, d[order], q[order], start_first=True)


@dataclass(slots=True)
class FixedScan:
    """A scan source that returns the same turn every time (tests, demos)."""

    angles_rad: npt.NDArray[np.float64]
    distances_m: npt.NDArray[np.float64]
    qualities: npt.NDArray[np.uint8] = field(default_factory=lambda: np.zeros(0, dtype=np.uint8))

    def __call__(self, now: float) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.uint8]]:
        q = (
            self.qualities
            if self.qualities.size == self.angles_rad.size
            else np.full(self.angles_rad.size, 47, np.uint8)
        )
        return self.angles_rad, self.distances_m, q
