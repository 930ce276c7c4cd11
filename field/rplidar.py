"""The simulated RPLIDAR A1: the slave side of its serial protocol, sans-I/O.

``SimulatedRplidar(lidar_config, scan_source)`` takes request bytes in ``receive(data, now)`` and
returns the answer bytes; while it scans, ``step(now)`` returns the measurement nodes (or express
capsules) due since the last call, paced at the scan mode's µs per sample. It plugs into
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
  ``first_node_delay`` later, starting with a fresh turn. No samples while the motor is off, during
  ``spinup_s`` after it starts (FORCE_SCAN skips the wait), or while the health status is error.
* EXPRESS_SCAN ``82`` (payload: working mode u8, flags u16, param u16): working mode 0 (the legacy
  express scan) or the id of a scan mode whose answer type is 0x82 starts the capsule stream:
  answer ``A5 5A 54 00 00 40 82``, then 84-byte capsules of 32 samples each, a capsule as soon as
  its last sample is due (``devices.rplidar.protocol.CapsuleEncoder``). Any other working mode is
  ignored (no answer), as is a payload too short to hold one.
* GET_LIDAR_CONF ``84``: the scan modes (``RplidarConfig.scan_modes``: count, per-mode µs per
  sample, max distance, answer type and name) and the typical mode. An entry the simulator does not
  know, or a mode id out of range, gets no answer (counted, logged once), so a master waits its
  timeout as with firmware that lacks it; ``conf_commands=False`` models firmware before 1.24.
* GET_INFO ``50``, GET_HEALTH ``52``, GET_SAMPLERATE ``59``: their answers (GET_SAMPLERATE: the
  standard and express modes' µs per sample). Any request other than SET_MOTOR_PWM ends a running
  scan first, so an answer is never buried in the stream (masters, SLAMTEC's SDK included, always
  send STOP before other requests anyway).
* SET_MOTOR_PWM ``F0`` (payload u16): 0 stops the motor, anything else starts it. The A1 itself
  ignores this command (its motor is on DTR); the simulator honours it because DTR cannot travel
  over TCP or a pty. ``set_dtr(level)`` is the DTR line for in-process use: low (False) = motor on.
  ``motor_on_at_start``: a unit served over TCP or a pty has no DTR line, so its motor runs from
  the start (``motor_at_start`` says so from a scenario's ``lidar.motor`` setting).
* GET_ACC_BOARD_FLAG ``FF`` and unknown commands: ignored, no answer.

Pacing: samples flow at the scan mode's µs per sample; by default (``scan_modes=None``) both modes
run at the ``LidarConfig``'s ``samples_per_second``, so the turn the model casts is the turn that is
sent and the rotation rate is the configured one. The stream is not throttled to 115200 baud.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from fleetlink.devices.ports import InProcessPort
from fleetlink.devices.rplidar.protocol import (
    ANGLE_Q,
    CAPSULE_LEN,
    CAPSULE_SAMPLES,
    EXPRESS_DESCRIPTOR,
    HEALTH_ERROR,
    HEALTH_GOOD,
    PER_MODE_CONF,
    SCAN_DESCRIPTOR,
    SEND_MODE_SINGLE,
    AnswerType,
    CapsuleEncoder,
    Command,
    ConfType,
    DeviceHealth,
    DeviceInfo,
    RequestDecoder,
    SampleRate,
    ScanMode,
    encode_descriptor,
    encode_device_info,
    encode_health,
    encode_lidar_conf,
    encode_nodes,
    encode_samplerate,
    parse_conf_request,
    rad_to_device_deg,
)
from fleetlink.field.lidar import LidarConfig
from fleetlink.shared.clock import Clock

log = logging.getLogger(__name__)

__all__ = [
    "MOTOR_AT_START",
    "DeviceStats",
    "FixedScan",
    "MotorAtStart",
    "RplidarConfig",
    "ScanSource",
    "SimulatedRplidar",
    "default_scan_modes",
    "motor_at_start",
]

MotorAtStart = Literal["auto", "running", "stopped"]
MOTOR_AT_START: tuple[MotorAtStart, ...] = ("auto", "running", "stopped")


def motor_at_start(setting: MotorAtStart, served: bool) -> bool:
    """Whether the simulated A1's motor turns from the start. ``auto``: when it is served over TCP or
    a pty (no DTR line reaches it, and SLAMTEC's SDK drives an A1's motor only by DTR), not in
    process (the master's DTR does, as on hardware)."""
    if setting == "auto":
        return served
    return setting == "running"


def default_scan_modes(lidar: LidarConfig) -> tuple[ScanMode, ...]:
    """The A1's two scan modes, "Standard" (id 0, nodes) and "Express" (id 1, capsules), both at the
    model's sample rate and range: what the field casts is what the unit streams."""
    us = 1e6 / float(lidar.samples_per_second)
    return (
        ScanMode(0, "Standard", us, float(lidar.max_range), AnswerType.MEASUREMENT),
        ScanMode(1, "Express", us, float(lidar.max_range), AnswerType.MEASUREMENT_CAPSULED),
    )


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
    motor_on_at_start: bool = False  # True when served over TCP / a pty (no DTR): see motor_at_start()
    boot_banner: bool = False  # RESET answers with the A1's text banner
    max_backlog_s: float = 0.5  # after a longer stall of step(), the missed samples are skipped
    scan_modes: tuple[ScanMode, ...] | None = None  # None: default_scan_modes(the LidarConfig)
    typical_mode: int = 1  # "Express"
    conf_commands: bool = True  # False: firmware before 1.24, which does not answer GET_LIDAR_CONF

    def __post_init__(self) -> None:
        if self.max_backlog_s <= 0.0 or self.first_node_delay < 0.0 or self.spinup_s < 0.0:
            raise ValueError("max_backlog_s must be positive, first_node_delay and spinup_s not negative")
        if len(self.serial) > 16:
            raise ValueError("the serial number has 16 bytes")
        if self.scan_modes is not None:
            if [m.id for m in self.scan_modes] != list(range(len(self.scan_modes))):
                raise ValueError("scan mode ids must be 0, 1, ... in order")
            if any(m.us_per_sample <= 0.0 for m in self.scan_modes):
                raise ValueError("a scan mode's us_per_sample must be positive")
            if not 0 <= self.typical_mode < len(self.scan_modes):
                raise ValueError(f"typical_mode {self.typical_mode} is not a scan mode")

    def banner(self) -> bytes:
        major, minor = self.firmware
        return (
            f"RP LIDAR System.\r\nFirmware Ver {major}.{minor:02d} - rtm, HW Ver {self.hardware}\r\n"
            f"Model: {self.model:02X}\r\n"
        ).encode("ascii")


@dataclass(slots=True)
class DeviceStats:
    requests: int = 0
    ignored: int = 0  # unknown commands, the accessory-board flag, GET_LIDAR_CONF without conf_commands
    bad_requests: int = 0  # GET_LIDAR_CONF / EXPRESS_SCAN the unit cannot answer (unknown entry or mode)
    scans: int = 0  # SCAN / FORCE_SCAN / EXPRESS_SCAN accepted
    revolutions: int = 0  # turns fetched from the scan source
    nodes: int = 0  # samples sent (as nodes or in capsules)
    capsules: int = 0  # express capsules sent
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
        self.scan_modes: tuple[ScanMode, ...] = self.config.scan_modes or default_scan_modes(lidar)
        self.health = DeviceHealth(HEALTH_GOOD, 0)
        self.stats = DeviceStats()
        self.pwm = 0
        self.mode: ScanMode = self._standard_mode()  # the mode of the scan running (or last run)
        self._sps = self.mode.samples_per_second
        self._decoder = RequestDecoder()
        self._now = now
        self._motor_on = self.config.motor_on_at_start
        self._motor_since = now
        self._scanning = False
        self._force = False
        self._capsules: CapsuleEncoder | None = None  # set while an express scan runs
        self._complained: set[str] = set()
        # Pacing: sample i of the stream is due at _t0 + i / samples_per_second.
        self._t0 = now
        self._sent = 0
        self._turn_q6 = np.zeros(0, dtype=np.int64)  # the turn in progress, in wire order
        self._turn_d = np.zeros(0, dtype=np.float64)
        self._turn_q = np.zeros(0, dtype=np.int64)
        self._turn_pos = 0  # samples of it already sent

    # -- state -----------------------------------------------------------------------------------

    @property
    def scanning(self) -> bool:
        return self._scanning

    @property
    def express(self) -> bool:
        """Whether the scan running (or last run) streams capsules."""
        return self._capsules is not None

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
        """GET_SAMPLERATE: µs per sample of the standard and of the express scan."""
        std = self._standard_mode()
        exp = self._express_mode(0) or std
        return SampleRate(max(1, round(std.us_per_sample)), max(1, round(exp.us_per_sample)))

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
                self._start_scan(now, self._standard_mode(), force=cmd == Command.FORCE_SCAN)
                out += SCAN_DESCRIPTOR.encode()
                continue
            if cmd == Command.EXPRESS_SCAN:
                mode = self._express_mode(req.payload[0]) if req.payload else None
                if mode is None:
                    self._bad("express", f"EXPRESS_SCAN with working mode {req.payload[:1].hex() or 'missing'}")
                    continue
                self._start_scan(now, mode, force=False)
                out += EXPRESS_DESCRIPTOR.encode()
                continue
            if cmd == Command.GET_LIDAR_CONF and not self.config.conf_commands:
                self.stats.ignored += 1  # firmware before 1.24
                continue
            if cmd not in (
                Command.STOP,
                Command.RESET,
                Command.GET_INFO,
                Command.GET_HEALTH,
                Command.GET_SAMPLERATE,
                Command.GET_LIDAR_CONF,
            ):
                self.stats.ignored += 1  # accessory-board flag, unknown
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
            elif cmd == Command.GET_LIDAR_CONF:
                out += self._lidar_conf(req.payload)
        return bytes(out)

    def step(self, now: float) -> bytes | None:
        """The samples due by ``now`` while scanning, as nodes or capsules (None when there are none)."""
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
        capsules = self._capsules
        while True:
            due = self._next_due()
            if due > now:
                break
            n = self._turn_q6.size
            if self._turn_pos >= n:
                self._fetch_turn(due)
                n = self._turn_q6.size
                if n == 0:
                    # Nothing to send this turn: let its time pass in silence.
                    self._restart_stream(due + 1.0 / self.lidar.rate_hz)
                    continue
            pos = self._turn_pos
            k = min(n - pos, math.floor((now - due) * sps + 1e-9) + 1)
            end = pos + k
            q6 = self._turn_q6[pos:end]
            if capsules is None:
                out += encode_nodes(q6 / ANGLE_Q, self._turn_d[pos:end], self._turn_q[pos:end], start_first=pos == 0)
                self.stats.nodes += k
            else:
                follow = int(self._turn_q6[end]) if end < n else None
                chunk = capsules.push(q6, self._turn_d[pos:end], new_turn=pos == 0, next_q6=follow)
                if chunk:
                    caps = len(chunk) // CAPSULE_LEN
                    self.stats.capsules += caps
                    self.stats.nodes += caps * CAPSULE_SAMPLES
                    out += chunk
            self._turn_pos = end
            self._sent += k
        return bytes(out) if out else None

    # -- internals -------------------------------------------------------------------------------

    def _standard_mode(self) -> ScanMode:
        for m in self.scan_modes:
            if m.answer_type == AnswerType.MEASUREMENT:
                return m
        return self.scan_modes[0]

    def _express_mode(self, working_mode: int) -> ScanMode | None:
        """The capsule mode EXPRESS_SCAN's working mode asks for: 0 is the legacy express scan (the
        first capsule mode), otherwise the id of a capsule mode (SLAMTEC's SDK sends the mode id)."""
        capsule_modes = [m for m in self.scan_modes if m.answer_type == AnswerType.MEASUREMENT_CAPSULED]
        if working_mode == 0:
            return capsule_modes[0] if capsule_modes else None
        return next((m for m in capsule_modes if m.id == working_mode), None)

    def _start_scan(self, now: float, mode: ScanMode, force: bool) -> None:
        self._scanning = True
        self._force = force
        self.mode = mode
        self._sps = mode.samples_per_second
        if mode.answer_type == AnswerType.MEASUREMENT_CAPSULED:
            step_q6 = 360.0 * ANGLE_Q * self.lidar.rate_hz / self._sps
            self._capsules = CapsuleEncoder(step_q6)
        else:
            self._capsules = None
        self._restart_stream(now + self.config.first_node_delay)
        self.stats.scans += 1

    def _lidar_conf(self, payload: bytes) -> bytes:
        parsed = parse_conf_request(payload)
        if parsed is None:
            self._bad("conf-short", f"GET_LIDAR_CONF with a payload of {len(payload)} bytes")
            return b""
        conf, mode_id = parsed
        if conf == ConfType.SCAN_MODE_COUNT:
            return encode_lidar_conf(conf, len(self.scan_modes).to_bytes(2, "little"))
        if conf == ConfType.SCAN_MODE_TYPICAL:
            return encode_lidar_conf(conf, self.config.typical_mode.to_bytes(2, "little"))
        if conf not in PER_MODE_CONF:
            self._bad(f"conf-{conf}", f"GET_LIDAR_CONF entry 0x{conf:X}, which this unit does not have")
            return b""
        if mode_id is None or not 0 <= mode_id < len(self.scan_modes):
            self._bad("conf-mode", f"GET_LIDAR_CONF 0x{conf:X} for scan mode {mode_id}, which does not exist")
            return b""
        mode = self.scan_modes[mode_id]
        if conf == ConfType.SCAN_MODE_US_PER_SAMPLE:
            value = round(mode.us_per_sample * 256).to_bytes(4, "little")
        elif conf == ConfType.SCAN_MODE_MAX_DISTANCE:
            value = round(mode.max_distance_m * 256).to_bytes(4, "little")
        elif conf == ConfType.SCAN_MODE_ANS_TYPE:
            value = bytes((mode.answer_type & 0xFF,))
        else:
            value = mode.name.encode("ascii", "replace") + b"\x00"
        return encode_lidar_conf(conf, value)

    def _bad(self, kind: str, what: str) -> None:
        """A request this unit cannot answer: counted, logged once per kind, no answer."""
        self.stats.bad_requests += 1
        if kind not in self._complained:
            self._complained.add(kind)
            log.warning("simulated RPLIDAR: %s: no answer (further ones are only counted)", what)

    def _set_motor(self, on: bool, now: float) -> None:
        if on and not self._motor_on:
            self._motor_since = now
        self._motor_on = on

    def _next_due(self) -> float:
        return self._t0 + self._sent / self._sps

    def _restart_stream(self, t: float) -> None:
        """Samples flow again from time ``t``, starting with a fresh turn (and a new capsule chain)."""
        self._t0 = t
        self._sent = 0
        self._turn_q6 = self._turn_q6[:0]
        self._turn_pos = 0
        if self._capsules is not None:
            self._capsules.reset()

    def _fetch_turn(self, t: float) -> None:
        angles, distances, qualities = self.scan_source(t)
        a = np.asarray(angles, dtype=np.float64).reshape(-1)
        self._turn_pos = 0
        if a.size == 0:
            self._turn_q6 = np.zeros(0, dtype=np.int64)
            return
        d = np.asarray(distances, dtype=np.float64).reshape(-1)
        q = np.asarray(qualities).reshape(-1)
        q6 = np.rint(rad_to_device_deg(a) * ANGLE_Q).astype(np.int64) % _FULL_TURN_Q6
        order = np.argsort(q6, kind="stable")
        self.stats.revolutions += 1
        self._turn_q6 = q6[order]
        self._turn_d = d[order]
        self._turn_q = q[order].astype(np.int64)


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
